"""``needletrack detect PATH [PATH ...] --out DIR``: the keypoint detector on a user's own images,
videos and folders, without a graph, calibration or ground truth (docs/commands.md).

Each camera image (``common.data.media``) goes through a detector backend's public interface
(``common.detector.backends``: ``load_backend``, ``detect``, ``reset``), whatever network is
behind it. Cold by default: the backend is reset before every image, so each is read on its
own; ``--tracking`` keeps the backend's tracking state along a video (or a dataset folder's
sequence). Writes ``DIR/detections.jsonl`` (``common.detector.detections_file``), one line per
image, and ``DIR/overlays/NAME.png`` (``common.viewer.draw.draw_detection``); prints a summary.
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path
from typing import Optional

from common.cli_options import add_quiet, add_weights

DETECTIONS_FILE = "detections.jsonl"
OVERLAYS_DIR = "overlays"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="needletrack detect",
        description="Run the keypoint detector on your own images, videos or folders: one JSON line per "
                    "image (keypoints A..E, scores, presence, tip probability, unfamiliarity) in "
                    "OUT/detections.jsonl and an overlay per image in OUT/overlays/.")
    p.add_argument("paths", nargs="+", metavar="PATH",
                   help="image files, video files (frames in order), folders of images (sorted by name) or "
                        "dataset folders (docs/dataset.md)")
    p.add_argument("--out", required=True, help="output folder (made if missing; detections.jsonl is replaced)")
    p.add_argument("--backend", default="learned", help="detector backend: learned (default) or classical")
    add_weights(p)
    p.add_argument("--threshold", type=float, help="presence threshold (default: the weights' fitted gate, presence_gate.json beside them, else 0.5)")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="another backend param (YAML value), e.g. threads=4; `needletrack describe detector`")
    p.add_argument("--every", type=int, default=1, metavar="N", help="every N-th frame of a video or folder")
    p.add_argument("--max-frames", type=int, metavar="N", help="at most N frames of each video or folder")
    p.add_argument("--split-stereo", action="store_true",
                   help="images and video frames are side-by-side stereo: detect in the left and the right half")
    p.add_argument("--tracking", action="store_true",
                   help="track along each video (the backend's tracking mode) instead of reading each frame cold")
    p.add_argument("--no-overlays", action="store_true", help="write no overlay PNGs")
    add_quiet(p)
    return p


def backend_params(backend: str, weights: Optional[str], threshold: Optional[float], tracking: bool,
                   extra: list) -> dict:
    """The backend's params from the command's options; ValueError saying what is wrong."""
    from common.detector.backends import BACKEND_PARAMS, available_backends
    from common.runtime.limits import load_yaml
    if backend not in BACKEND_PARAMS:
        raise ValueError(f"detector backend {backend!r} is unknown; known: {', '.join(available_backends())}")
    known = {f.name for f in dataclasses.fields(BACKEND_PARAMS[backend])}
    params = {}
    for item in extra:
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise ValueError(f"--param {item!r}: expected KEY=VALUE")
        params[key.strip()] = load_yaml(value, f"--param {key}")
    if weights is not None:
        if not Path(weights).is_file():
            raise ValueError(f"--weights {weights}: no such file")
        params["weights"] = weights
    if threshold is not None:
        if not 0 <= threshold <= 1:
            raise ValueError(f"--threshold {threshold}: must be in [0, 1]")
        params["threshold"] = threshold
    if "tracking" in known:
        params.setdefault("tracking", tracking)
    elif tracking:
        raise ValueError(f"backend {backend!r} has no tracking mode (--tracking)")
    unknown = sorted(set(params) - known)
    if unknown:
        what = "--weights" if unknown == ["weights"] else ", ".join(unknown)
        raise ValueError(f"backend {backend!r} takes no {what} (its params: {', '.join(sorted(known)) or 'none'})")
    return params


def _caption(item, kp, size) -> str:
    where = Path(item.source).name + ("" if item.frame is None else f"  frame {item.frame}") + \
        ("" if item.camera is None else f"  {item.camera}")
    lines = [f"{where}  {size[0]}x{size[1]}"]
    if kp.found:
        said = f"needle  presence {kp.confidence:.2f}"
        if kp.end_identity is not None:
            said += f"  A is the tip: p={kp.end_identity:.2f}"
        lines.append(said)
    else:
        lines.append(f"presence {kp.confidence:.2f}")
    if kp.unfamiliarity is not None:
        lines.append(f"unfamiliarity {kp.unfamiliarity:.2f} (about 1: like the training images)")
    if kp.found:
        lines.append("A..E coloured by score: red 0, yellow 0.5, green 1")
    return "\n".join(lines)


@dataclasses.dataclass
class Summary:
    """What a run saw: images given, unreadable, found; presences, unfamiliarities of the found
    ones, detection times (ms)."""
    images: int = 0
    unreadable: int = 0
    found: int = 0
    presence: list = dataclasses.field(default_factory=list)
    unfamiliarity: list = dataclasses.field(default_factory=list)
    ms: list = dataclasses.field(default_factory=list)

    def add(self, rec) -> None:
        self.images += 1
        if rec.error is not None:
            self.unreadable += 1
            return
        self.found += rec.found
        self.presence.append(rec.presence)
        self.ms.append(rec.ms)
        if rec.found and rec.unfamiliarity is not None:
            self.unfamiliarity.append(rec.unfamiliarity)

    def lines(self) -> list[str]:
        read = self.images - self.unreadable
        out = [f"{self.images} images: {read} read, {self.unreadable} unreadable; needle found in {self.found}"
               + (f" ({self.found / read:.0%})" if read else "")]
        if read:
            out.append(f"presence mean {statistics.fmean(self.presence):.3f}; detection {statistics.fmean(self.ms):.1f} ms "
                       f"mean, {statistics.median(self.ms):.1f} ms median per image")
        if self.unfamiliarity:
            out.append(f"unfamiliarity of the found needles {min(self.unfamiliarity):.2f} .. "
                       f"{max(self.unfamiliarity):.2f} (median {statistics.median(self.unfamiliarity):.2f}; "
                       f"about 1: like the training images, larger: less so)")
        return out


def detect_files(paths, out, backend: str = "learned", params: Optional[dict] = None, every: int = 1,
                 max_frames: Optional[int] = None, split_stereo: bool = False, overlays: bool = True,
                 progress: bool = True) -> Summary:
    """Run ``backend`` (with ``params``) on the images of ``paths`` and write ``out``; returns the
    ``Summary``. The backend is reset before each image unless its ``tracking`` param is true,
    then at each new stream (a video, a dataset folder's sequence) and before each image file.
    ``MediaError`` / ``DatasetError`` / ``BackendError`` (all ``NeedletrackError``) before any
    image for bad paths or params."""
    import cv2
    from common.progress import progress_bar

    from common.data.media import input_images, open_sources, planned_images
    from common.detector.backends import BackendError, backend_class, load_backend
    from common.detector.detections_file import detection_record, record_line, unreadable_record

    sources = open_sources(paths)
    params = dict(params or {})
    if backend_class(backend).needs_truth:
        raise BackendError(f"detector backend {backend!r} needs ground truth; it cannot read your images")
    det = load_backend(backend, params)
    tracking = bool(params.get("tracking", False))
    out = Path(out)
    (out / OVERLAYS_DIR).mkdir(parents=True, exist_ok=True)
    summary = Summary()
    stream = None
    bar = progress_bar(total=planned_images(sources, every, max_frames, split_stereo), desc="detect", unit="img",
               show=progress)
    with open(out / DETECTIONS_FILE, "wb") as f:
        try:
            for i, item in enumerate(input_images(sources, every, max_frames, split_stereo)):
                where = dict(source=item.source, frame=item.frame, camera=item.camera, name=item.name)
                if item.image is None:
                    rec = unreadable_record(**where, error=item.error, detector=backend)
                    bar.write(f"warning: {item.error}", file=sys.stderr)
                    kp = None
                else:
                    if not tracking or item.stream is None or item.stream != stream:
                        det.reset()
                    stream = item.stream
                    t0 = time.perf_counter()
                    kp = det.detect(item.image, item.camera or "left", None, item.calib, seq=i, stamp_ns=0)
                    ms = (time.perf_counter() - t0) * 1e3
                    size = (item.image.shape[1], item.image.shape[0])
                    rec = detection_record(kp, **where, size=size, ms=ms)
                f.write(record_line(rec))
                f.flush()
                summary.add(rec)
                if overlays and kp is not None:
                    from common.viewer.draw import draw_detection
                    pic = draw_detection(item.image, kp, _caption(item, kp, size))
                    path = out / OVERLAYS_DIR / f"{item.name}.png"
                    if not cv2.imwrite(str(path), pic):
                        raise OSError(f"{path}: could not write the overlay")
                bar.update(1)
        finally:
            bar.close()
    return summary


def main(argv: Optional[list] = None) -> int:
    """``needletrack detect``: 0 when at least one image was read, 1 with an ``error:`` line on
    bad paths, params or when no image could be read, 2 on bad usage."""
    from common.errors import NeedletrackError
    args = _parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    try:
        if args.every < 1:
            raise ValueError(f"--every {args.every}: must be at least 1")
        if args.max_frames is not None and args.max_frames < 1:
            raise ValueError(f"--max-frames {args.max_frames}: must be at least 1")
        params = backend_params(args.backend, args.weights, args.threshold, args.tracking, args.param)
        summary = detect_files(args.paths, args.out, args.backend, params, args.every, args.max_frames,
                               args.split_stereo, not args.no_overlays, progress=not args.quiet)
    except (NeedletrackError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"interrupted; the images done are in {Path(args.out) / DETECTIONS_FILE}", file=sys.stderr)
        return 130
    for line in summary.lines():
        print(line)
    print(f"detections: {Path(args.out) / DETECTIONS_FILE}" +
          ("" if args.no_overlays else f"; overlays: {Path(args.out) / OVERLAYS_DIR}/"))
    if summary.images == summary.unreadable:
        print("error: no image could be read", file=sys.stderr)
        return 1
    return 0
