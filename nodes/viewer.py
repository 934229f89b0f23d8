"""Viewer: the tracker live in a browser. A fan-out consumer: any number of them,
never slowing the pipeline: the images (the only large inputs) are newest-only, so a slow
viewer drops frames; the small messages (poses, keypoints, truth, ECM poses, instruments,
calibration) queue,
each handled in microseconds, so that every pose counts in the rates and finds its truth.

Two outputs, both on loopback:

- its own page (``common.viewer.page``), ``viewer: http://127.0.0.1:<port>/`` printed at start:
  the paper's Fig. 1 on both cameras (``common.viewer.draw.draw_fig1``; with ``instruments``
  wired, each instrument's jaw frame and which one holds the needle), each method's pose,
  error, rate and latency, and plots of them;
- Rerun (when ``rerun-sdk`` is installed, the ``viewer`` extra): the same pictures in the two
  cameras' frusta, every method's needle arc in 3D, the ECM's path, the time series; its web
  viewer is served on ``web_port`` and printed (``viewer 3D (Rerun): ...``); ``save`` records
  the session to an .rrd file (``needletrack view FILE.rrd``).

Images are sampled at most ``rate_hz`` per camera, shrunk to fit ``width x height`` and JPEG'd;
a sampled frame is drawn once its final pose is in, or after ``pose_wait_s`` without it.
"""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from typing import Literal, Optional

import numpy as np

from common.constraints import PositiveNumber, at_least
from common.data.truth import true_T_ecm_needle
from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.runtime.messages import (
    Calibration,
    CameraImage,
    EcmPose,
    GroundTruth,
    InstrumentState,
    Keypoints,
    PoseEstimate,
)
from common.runtime.node import Node, run
from common.runtime.pairing import SeqCache
from common.viewer.draw import PoseToDraw, decode_small, instruments_to_draw
from common.viewer.frame import log_frame, pictures
from common.viewer.http_request import HttpLimits
from common.viewer.page import PageServer
from common.viewer.state import ViewerState
from common.methods import POSE_METHODS, final_method
from nodes._pose import PoseMethodInputs

KEEP = 16           # frames remembered per input (by seq)
PATH_POINTS = 600   # ECM path length (frames)


def port_or_free(port: int, host: str = "127.0.0.1") -> int:
    """``port`` when it is free on ``host``, else (or for 0) a free port picked by the system."""
    import socket
    for candidate in ((port, 0) if port else (0,)):
        with socket.socket() as s:
            try:
                s.bind((host, candidate))
            except OSError:
                continue
            return s.getsockname()[1]
    raise OSError(f"no free port on {host}")


class ViewerNode(PoseMethodInputs, Node):
    """See the module docstring."""

    INPUTS = {"left": CameraImage, "right": CameraImage,
              "keypoints_left": Keypoints, "keypoints_right": Keypoints,
              "truth": GroundTruth, "calib": Calibration, "ecm": EcmPose, "instruments": InstrumentState,
              **{m: PoseEstimate for m in POSE_METHODS}}
    OUTPUTS = ()
    KEEP_ALL = tuple(k for k in INPUTS if k not in CAMERAS)

    @dataclass
    class Params:
        host: str = "127.0.0.1"       # the page's address (loopback; another logs a warning)
        port: int = 9090              # the page's port (0, or taken: any free port)
        allowed_hosts: tuple[str, ...] = ()   # more Host names the page answers (beside localhost,
                                      # the bound host and addresses; "*": any): DNS rebinding
        max_connections: at_least(1) = 64     # page connections served at once (then 503)
        rerun: bool = True            # also log to Rerun when rerun-sdk is installed
        web_port: int = 9091          # Rerun's web viewer on 127.0.0.1 (0: none; taken: any free port)
        grpc_port: int = 9876         # Rerun's data server on 127.0.0.1 (0: none; taken: any free port)
        save: Optional[str] = None    # record the Rerun stream to this .rrd file
        history_mb: int = 16          # Rerun's server keeps this much for a web viewer that joins
                                      # late (then drops the oldest): the node's memory is bounded
        rate_hz: PositiveNumber = 5.0          # pictures per second at most (per camera; docs/viewer.md: cost)
        width: at_least(16) = 960              # pictures shrunk to fit width x height (px)
        height: at_least(16) = 540
        jpeg_quality: int = 75
        final: Optional[Literal[POSE_METHODS]] = None   # the method drawn in full (default: first wired of FINAL_ORDER)
        pose_wait_s: float = 0.5      # a sampled frame waits this long for its final pose

    def setup(self):
        p = self.p
        wired = [m for m in POSE_METHODS if self.wired(m)]
        self.final = p.final or final_method(wired)
        self.images = {c: SeqCache(KEEP) for c in CAMERAS}   # seq -> (img, scale, stamp, t)
        self.keypoints = {c: SeqCache(KEEP) for c in CAMERAS}
        self.poses = {m: SeqCache(KEEP) for m in POSE_METHODS}
        self.truths = SeqCache(KEEP)
        self.ecm = SeqCache(KEEP)
        self.instruments = SeqCache(KEEP)           # seq -> {name: InstrumentState}
        self.path = collections.deque(maxlen=PATH_POINTS)
        self.last_sample = {c: -1e9 for c in CAMERAS}
        self.rendered = -1
        self.rig = self.needle = self.arm = None
        self.calib_key = None
        self.state = ViewerState()
        self.state.final = self.final
        self.rec = self.web = None
        rerun_url = None
        if p.rerun:
            rerun_url = self._start_rerun()
        page = dict(poll_ms=int(1000 / p.rate_hz), rerun_url=rerun_url, allowed_hosts=p.allowed_hosts,
                    limits=HttpLimits(max_connections=p.max_connections), log=self.log, count=self.count)
        try:
            self.page = PageServer(p.host, p.port, **page)
        except OSError as exc:      # taken (another viewer?): any free port rather than no viewer
            self.page = PageServer(p.host, 0, **page)
            self.log.warning("port %d: %s; serving on %d instead", p.port, exc, self.page.port)
        print(f"viewer: {self.page.url}", flush=True)
        if rerun_url:
            print(f"viewer 3D (Rerun): {rerun_url}", flush=True)
        if p.save:
            print(f"viewer: recording to {p.save}", flush=True)

    def _start_rerun(self) -> Optional[str]:
        p = self.p
        try:
            import rerun  # noqa: F401

            from common.viewer import rerun_log
        except ImportError:
            self.log.warning("rerun-sdk is not installed (pip install -e '.[viewer]'): no 3D view, "
                             "no recording; the page still works")
            return None
        self.rl = rerun_log
        self.rec = rerun_log.new_recording()
        grpc_port = port_or_free(p.grpc_port) if p.grpc_port else None
        grpc = rerun_log.set_sinks(self.rec, grpc_port, p.save, memory_limit=f"{max(1, p.history_mb)}MiB")
        if grpc and p.web_port:
            from common.viewer.cli import serve_web, web_url
            web_port = port_or_free(p.web_port)
            self.web = serve_web(web_port, grpc)
            return web_url(web_port, grpc)
        return None

    def teardown(self):
        if getattr(self, "page", None) is not None:
            self.page.close()
        if self.web is not None:
            self.web.terminate()
            self.web.wait(10)
        if self.rec is not None:
            self.rec.flush()
            self.rec.disconnect()

    # ---------------------------------------------------------------- inputs
    def on_calib(self, msg: Calibration):
        key = (repr(msg.cameras), repr(msg.needle), repr(msg.ecm), tuple(np.asarray(msg.image_size).tolist()))
        if key == self.calib_key:
            return
        self.calib_key = key
        self.rig = StereoRig.from_dict(msg.cameras, msg.image_size)
        self.needle = NeedleModel.from_dict(msg.needle)
        self.arm = EcmArm.from_calibration(msg.ecm)
        if self.rec is not None:
            w, h = (int(x) for x in np.asarray(msg.image_size))
            self.rl.log_rig(self.rec, self.rig, min(1.0, self.p.width / w, self.p.height / h))

    def on_left(self, msg: CameraImage):
        self._sample(msg)

    def on_right(self, msg: CameraImage):
        self._sample(msg)

    def _sample(self, msg: CameraImage):
        now = time.monotonic()
        if now - self.last_sample[msg.camera] < 1.0 / self.p.rate_hz:
            self.count("images_skipped")
            return
        try:
            small, scale = decode_small(msg.data, msg.encoding, msg.width, msg.height,
                                        self.p.width, self.p.height)
        except ValueError as exc:
            self.count("bad_input")
            self.log.warning("seq %d %s: %s", msg.seq, msg.camera, exc)
            return
        self.last_sample[msg.camera] = now
        self.images[msg.camera].put(msg.seq, (small, scale, msg.stamp_ns, now))
        self._render_ready(now)

    def on_keypoints_left(self, msg: Keypoints):
        self._keypoints(msg)

    def on_keypoints_right(self, msg: Keypoints):
        self._keypoints(msg)

    def _keypoints(self, msg: Keypoints):
        self.keypoints[msg.camera].put(msg.seq, msg)
        self.state.add_point("confidence", msg.camera, time.monotonic(), msg.confidence)

    def on_truth(self, msg: GroundTruth):
        self.truths.put(msg.seq, msg)

    def on_instruments(self, msg: InstrumentState):
        self.instruments.setdefault(msg.seq, {})[msg.name] = msg
        self.instruments.move_to_end(msg.seq)
        while len(self.instruments) > KEEP:
            self.instruments.popitem(last=False)

    def _instruments_to_draw(self, seq: int) -> list:
        """The frame's instruments in the ECM frame (its ECM pose from ``ecm`` or the truth)."""
        T_we = self.ecm.get(seq)
        gt = self.truths.get(seq)
        if T_we is None and gt is not None and gt.T_world_ecm is not None:
            T_we = np.asarray(gt.T_world_ecm, float)
        return instruments_to_draw(self.instruments.get(seq, {}), T_we)

    def on_ecm(self, msg: EcmPose):
        T = np.asarray(msg.T_world_ecm, float)
        self.ecm.put(msg.seq, T)
        self.path.append(T[:3, 3].copy())

    def on_pose(self, method: str, msg: PoseEstimate):
        now = time.monotonic()
        self.poses[method].put(msg.seq, msg)
        self.state.add_pose(method, msg.seq, msg.T_ecm_needle, self._true(msg.seq),
                            (time.time_ns() - msg.stamp_ns) * 1e-6, bool(msg.ambiguous), now, msg.end_identity)
        self._render_ready(now)

    # ---------------------------------------------------------------- drawing
    def _true(self, seq: int):
        gt = self.truths.get(seq)
        return None if gt is None else true_T_ecm_needle(gt, self.arm)

    def _render_ready(self, now: float) -> None:
        """Draw the newest sampled stereo frame whose final pose is in (or that waited long enough)."""
        both = [s for s in self.images["left"] if s in self.images["right"] and s > self.rendered]
        final = self.poses.get(self.final, {}) if self.final else {}
        ready = [s for s in both if s in final
                 or now - max(self.images[c][s][3] for c in CAMERAS) >= self.p.pose_wait_s]
        if ready and self.rig is not None:
            self._render(max(ready), now)

    def _render(self, seq: int, now: float) -> None:
        self.rendered = seq
        poses = {m: PoseToDraw(d[seq].T_ecm_needle, bool(d[seq].ambiguous))
                 for m, d in self.poses.items() if seq in d}
        T_true = self._true(seq)
        kps = {}
        for cam in CAMERAS:
            kp = self.keypoints[cam].get(seq)
            kps[cam] = np.asarray(kp.uv, float) if kp is not None and kp.found else None
        images = {cam: self.images[cam][seq][:2] for cam in CAMERAS}
        jpegs = pictures(images, self.rig, self.needle, poses, self.final, kps, T_true, seq,
                         self.p.jpeg_quality, self._instruments_to_draw(seq))
        for cam, jpeg in jpegs.items():
            self.page.set_frame(cam, jpeg)
        row = self.state.methods.get(self.final, {})
        err = "" if row.get("pos_err_mm") is None else f"  err {row['pos_err_mm']:.2f} mm {row['rot_err_deg']:.2f} deg"
        self.state.head = f"seq {seq}  final: {self.final}{err}"
        self.page.set_state(self.state.to_json(now))
        if self.rec is not None:
            scalars = {k: {m: row.get(k) for m, row in self.state.methods.items() if m in poses}
                       for k in ("pos_err_mm", "rot_err_deg", "rate_hz", "latency_ms")}
            scalars["confidence"] = {c: self.keypoints[c][seq].confidence
                                     for c in CAMERAS if seq in self.keypoints[c]}
            log_frame(self.rec, self.rl, seq, self.images["left"][seq][2], jpegs, self.needle, poses,
                      T_true, self.ecm.get(seq), np.array(self.path) if len(self.path) >= 2 else None,
                      scalars)
        self.count("frames_drawn")


NODE = ViewerNode
if __name__ == "__main__":
    run(NODE)
