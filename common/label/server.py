"""``needletrack label DIR``: the labelling page over a dataset folder, served on 127.0.0.1
(``common.viewer.http_server``: the Host and Origin checks, the bounds), docs/label.md.

Routes: ``/`` the page; ``/api/session`` the frames' order and statuses, where to resume;
``/api/frame?i=N`` a frame's starting clicks (its label, else the detector's proposal, else the
nearest labelled frame's pose) and their fit; ``/image?i=N&camera=left`` an image file as the
folder holds it; POST ``/api/fit`` (the fit of clicks, nothing written), ``/api/save`` (a frame's
label written to the folder), ``/api/position`` (where the user is, for a reopened session).
A bad request gets 400 or 422 with ``{"error": ...}`` and changes nothing.
"""
from __future__ import annotations

import argparse
import collections
import json
import signal
import sys
import time
import urllib.parse
from typing import Optional

import numpy as np

from common.cli_options import add_quiet
from common.data.dataset import DatasetError
from common.frames import CAMERAS
from common.geometry.oracle import true_keypoints
from common.label.fit import (
    CLICK_SIGMA_PX,
    CameraClicks,
    LabelError,
    LabelFit,
    LabelInputError,
    LabelFitter,
    clicks_from_json,
    clicks_from_keypoints,
)
from common.label.page import page_html
from common.label.proposals import detect_folder, doubt, label_order
from common.label.store import LabelStore
from common.viewer.http_request import HttpLimits, Request
from common.viewer.http_server import Answer, HttpServer

IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


def _json(obj, status: int = 200) -> Answer:
    return Answer(status, "application/json", json.dumps(obj, separators=(",", ":")).encode())


def _error(status: int, text: str) -> Answer:
    return _json({"error": text}, status)


class LabelApp:
    """The page's logic over one folder (``LabelStore``), with the detector's ``proposals`` (one
    per frame, or None) and the click noise ``sigma_px``; ``handle`` answers one request."""

    def __init__(self, store: LabelStore, proposals: Optional[list] = None, sigma_px: float = CLICK_SIGMA_PX):
        self.store, self.proposals = store, proposals
        self.fitter = LabelFitter(store.ds.rig, store.ds.needle, sigma_px)
        self.order = label_order(proposals, len(store))
        self._images: collections.OrderedDict = collections.OrderedDict()

    # ------------------------------------------------------------ helpers
    def images(self, i: int) -> dict:
        """Frame ``i``'s decoded images (the last few frames kept)."""
        if i not in self._images:
            self._images[i] = {c: self.store.ds.image(i, c) for c in CAMERAS}
            while len(self._images) > 4:
                self._images.popitem(last=False)
        self._images.move_to_end(i)
        return self._images[i]

    def fit_json(self, fit: LabelFit) -> dict:
        t = fit.T_ecm_needle[:3, 3] * 1e3
        return {"keypoints": {c: np.round(fit.keypoints[c], 3).tolist() for c in CAMERAS},
                "visible": {c: [bool(b) for b in fit.visible[c]] for c in CAMERAS},
                "bbox": fit.bbox, "arc": {c: np.round(a, 2).tolist() for c, a in
                                          fit.arc(self.store.ds.rig, self.store.ds.needle).items()},
                "stereo": fit.stereo, "cameras": list(fit.cameras), "pose_known": fit.pose_known,
                "ambiguous": fit.ambiguous, "alternatives": len(fit.alternatives), "choice": fit.choice,
                "rms_px": fit.rms_px, "snapped": fit.snapped,
                "sigma_max_px": float(max(np.nanmax(fit.sigma_px[c][fit.visible[c]]) if fit.visible[c].any() else 0.0
                                          for c in CAMERAS)),
                "T_ecm_needle": fit.T_ecm_needle.tolist(),
                "pose_sigma_mm": fit.pose_sigma_mm, "pose_sigma_deg": fit.pose_sigma_deg,
                "pose": f"t [{t[0]:.1f} {t[1]:.1f} {t[2]:.1f}] mm (ECM)"}

    def _frame_index(self, v) -> int:
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < len(self.store):
            raise LabelInputError(f"frame: expected a frame index 0..{len(self.store) - 1}, got {v!r}"[:120])
        return v

    def fit(self, i: int, clicks: dict, choice: int = 0, snap: bool = True) -> LabelFit:
        return self.fitter.fit(clicks, self.images(i), [self.store.prior_pose(i)], choice, snap)

    def start(self, i: int) -> tuple:
        """(clicks as JSON, what they came from) for frame ``i``."""
        lab = self.store.label(i)
        if lab is not None and isinstance(lab.get("clicks"), dict):
            return lab["clicks"], "saved"
        prop = self.proposals[i] if self.proposals else None
        if prop and any((prop.get(c) or {}).get("found") for c in CAMERAS):
            uv = {c: (prop.get(c) or {}).get("uv") for c in CAMERAS}
            clicks = clicks_from_keypoints(uv)
            return {c: clicks[c].to_json() for c in CAMERAS}, "proposal"
        T = self.store.prior_pose(i)
        if T is not None:
            uv = {}
            for c in CAMERAS:
                k, inside = true_keypoints(self.store.ds.rig[c], T, self.store.ds.needle)
                uv[c] = k if inside.all() else None
            clicks = clicks_from_keypoints(uv)
            return {c: clicks[c].to_json() for c in CAMERAS}, "previous"
        return {c: CameraClicks().to_json() for c in CAMERAS}, "none"

    # ------------------------------------------------------------ routes
    def handle(self, req: Request, body: bytes) -> Answer:
        url = urllib.parse.urlsplit(req.target)
        q = dict(urllib.parse.parse_qsl(url.query))
        try:
            if req.method in ("GET", "HEAD"):
                if url.path in ("/", "/index.html"):
                    return Answer(200, "text/html; charset=utf-8", page_html())
                if url.path == "/api/session":
                    return _json(self.session())
                if url.path == "/api/frame":
                    return _json(self.frame(self._int(q, "i")))
                if url.path == "/image":
                    return self.image(self._int(q, "i"), q.get("camera", ""))
                return Answer(404, "text/plain", b"not found\n")
            if url.path not in ("/api/fit", "/api/save", "/api/position"):
                return Answer(404, "text/plain", b"not found\n")
            try:
                data = json.loads(body.decode("utf-8"))
            except (UnicodeDecodeError, ValueError) as exc:
                return _error(400, f"the body is not JSON: {exc}"[:200])
            if not isinstance(data, dict):
                return _error(400, "the body must be a JSON object")
            return {"/api/fit": self.post_fit, "/api/save": self.post_save,
                    "/api/position": self.post_position}[url.path](data)
        except LabelInputError as exc:
            return _error(400, str(exc))
        except (LabelError, DatasetError) as exc:         # clicks that give no label; an unreadable image
            return _error(422, str(exc))

    @staticmethod
    def _int(q: dict, key: str) -> int:
        v = q.get(key, "")
        if not v.isdigit():
            raise LabelInputError(f"{key}: expected a frame index, got {v[:40]!r}")
        return int(v)

    def session(self) -> dict:
        pos = self.store.session.get("position")
        order = self.order
        if not (isinstance(pos, int) and 0 <= pos < len(order)):
            todo = [k for k, i in enumerate(order) if self.store.status(i) == "unlabelled"]
            pos = todo[0] if todo else 0
        return {"n": len(self.store), "order": order, "position": pos,
                "image_size": list(self.store.ds.meta.image_size),
                "statuses": [self.store.status(i) for i in range(len(self.store))]}

    def frame(self, i: int) -> dict:
        if not 0 <= i < len(self.store):
            raise LabelInputError(f"i: expected a frame index 0..{len(self.store) - 1}, got {i}")
        clicks_json, start = self.start(i)
        out = {"index": i, "status": self.store.status(i), "start": start, "clicks": clicks_json,
               "fit": None, "error": None, "note": None,
               "doubt": None if not self.proposals else doubt(self.proposals[i])}
        lab = self.store.label(i)
        if out["status"] == "truth":
            out["note"] = "this frame holds ground truth not made here (a render's): it is shown, not overwritten"
        if lab is not None and lab.get("no_needle"):
            out["note"] = "labelled: no needle"
            return out
        clicks = clicks_from_json(clicks_json, self.store.ds.meta.image_size)
        if any(c.count for c in clicks.values()):
            try:
                out["fit"] = self.fit_json(self.fit(i, clicks))
            except LabelError as exc:
                out["error"] = str(exc)
        return out

    def image(self, i: int, camera: str) -> Answer:
        if camera not in CAMERAS or not 0 <= i < len(self.store):
            raise LabelInputError(f"image: expected i in 0..{len(self.store) - 1} and camera left or right")
        fr = self.store.ds.frames[i]
        ext = "." + fr.image(camera).rsplit(".", 1)[-1].lower()
        return Answer(200, IMAGE_TYPES.get(ext, "application/octet-stream"), self.store.ds.image_bytes(fr, camera))

    def _clicks(self, data: dict) -> dict:
        return clicks_from_json(data.get("clicks"), self.store.ds.meta.image_size)

    @staticmethod
    def _flags(data: dict) -> tuple:
        choice, snap = data.get("choice", 0), data.get("snap", True)
        if isinstance(choice, bool) or not isinstance(choice, int) or not 0 <= choice < 16:
            raise LabelInputError(f"choice: expected a small whole number, got {choice!r}"[:120])
        if not isinstance(snap, bool):
            raise LabelInputError(f"snap: expected true or false, got {snap!r}"[:120])
        return choice, snap

    def post_fit(self, data: dict) -> Answer:
        i = self._frame_index(data.get("frame"))
        clicks = self._clicks(data)
        choice, snap = self._flags(data)
        try:
            return _json({"fit": self.fit_json(self.fit(i, clicks, choice, snap)), "error": None})
        except LabelInputError:
            raise
        except LabelError as exc:
            return _json({"fit": None, "error": str(exc)})

    def post_save(self, data: dict) -> Answer:
        i = self._frame_index(data.get("frame"))
        no_needle = data.get("no_needle", False)
        if not isinstance(no_needle, bool):
            raise LabelInputError(f"no_needle: expected true or false, got {no_needle!r}"[:120])
        start, edits = data.get("start", "none"), data.get("edits", 0)
        if start not in ("saved", "proposal", "previous", "none"):
            raise LabelInputError(f"start: expected saved, proposal, previous or none, got {start!r}"[:120])
        if isinstance(edits, bool) or not isinstance(edits, int) or edits < 0:
            raise LabelInputError(f"edits: expected a count, got {edits!r}"[:120])
        choice, snap = self._flags(data)
        self.save(i, self._clicks(data), no_needle, choice, snap, start, edits)
        return _json({"ok": True, "status": self.store.status(i)})

    def save(self, i: int, clicks: dict, no_needle: bool = False, choice: int = 0, snap: bool = True,
             start: str = "none", edits: int = 0) -> Optional[LabelFit]:
        """Fit frame ``i``'s clicks ({camera: CameraClicks}) and write the label (``no_needle``:
        the frame shows none), then move the session past it: what the page's accept does.
        Returns the fit (None for no needle); LabelError (nothing written) when the clicks cannot
        give a label or a camera is neither clicked nor marked not seen."""
        fit = None
        if not no_needle:
            missing = [c for c in CAMERAS if not clicks[c].unseen and clicks[c].count == 0]
            if missing:
                raise LabelError(f"{' and '.join(missing)} camera: click the needle there or mark it not "
                                 "seen there (key v), or mark the frame no needle (key 0)")
            fit = self.fit(i, clicks, choice, snap)
        self.store.save(i, fit, clicks, click_sigma_px=self.fitter.sigma_px, start=start, edits=edits)
        self.store.save_session(position=min(self.order.index(i) + 1, len(self.order) - 1))
        return fit

    def post_position(self, data: dict) -> Answer:
        i = self._frame_index(data.get("frame"))
        self.store.save_session(position=self.order.index(i))
        return _json({"ok": True})


def proposals_for(store: LabelStore, detector: str, params: dict, progress: bool = True) -> Optional[list]:
    """The detector's proposals for the folder (None with ``detector`` ``none``), from the
    session file when the same detector made them, else run now and kept there."""
    if detector == "none":
        return None
    key = {"detector": detector, "params": params, "frames": len(store)}
    cached = store.session.get("proposals")
    if isinstance(cached, dict) and cached.get("key") == key and isinstance(cached.get("frames"), list):
        return cached["frames"]
    frames = detect_folder(store.ds, detector, params, progress)
    store.save_session(proposals={"key": key, "frames": frames})
    return frames


def serve(folder: str, host: str = "127.0.0.1", port: int = 9092, detector: str = "learned",
          params: Optional[dict] = None, sigma_px: float = CLICK_SIGMA_PX, allowed_hosts=(),
          progress: bool = True) -> tuple:
    """Open ``folder``, get the proposals, start the page: (server, app)."""
    store = LabelStore(folder)
    app = LabelApp(store, proposals_for(store, detector, dict(params or {}), progress), sigma_px)
    server = HttpServer(host, port, app.handle, name="label page", methods=("GET", "HEAD", "POST"),
                        blocking=True, allowed_hosts=allowed_hosts, limits=HttpLimits(max_connections=16))
    return server, app


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="needletrack label", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("folder", help="a dataset folder (docs/dataset.md); labels are written into it")
    p.add_argument("--port", type=int, default=9092, help="port on 127.0.0.1 (default 9092; 0: any free one)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1, loopback only)")
    p.add_argument("--allowed-host", action="append", default=[], metavar="NAME",
                   help="another Host name to answer (behind a proxy); repeatable")
    p.add_argument("--detector", default="learned",
                   help="detector backend whose proposals each frame starts from (default learned; "
                        "none: no proposals)")
    p.add_argument("--detector-param", action="append", default=[], metavar="KEY=VALUE",
                   help="a detector backend parameter (repeatable), e.g. weights=OUT/model.pt")
    p.add_argument("--click-sigma", type=float, default=CLICK_SIGMA_PX,
                   help=f"the stated 1-sigma error of a click per axis, px (default {CLICK_SIGMA_PX:g})")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    add_quiet(p)
    a = p.parse_args(argv)
    from common.detector.backends import BackendError
    from common.runtime.graph import parse_param
    try:
        params = dict(parse_param(t) for t in a.detector_param)
        server, app = serve(a.folder, a.host, a.port, a.detector, params, a.click_sigma, a.allowed_host,
                            not a.quiet)
    except (DatasetError, LabelError, BackendError, ValueError, OSError) as exc:
        print(f"needletrack label: {exc}", file=sys.stderr)
        return 1
    signal.signal(signal.SIGTERM, _interrupt)
    todo = sum(app.store.status(i) == "unlabelled" for i in range(len(app.store)))
    print(f"label: {server.url}  ({len(app.store)} frames, {todo} to label; Ctrl-C stops)", flush=True)
    deadline = None if a.duration is None else time.monotonic() + a.duration
    try:
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
