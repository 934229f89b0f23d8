"""``tracking.mp4``: the moving take that ``tracking.png`` shows (``moving.shown_take``) as a
video, written from a run's ``Collected`` poses (docs/tracking.md#evaluation).

Each frame is the left endoscope image, downscaled to ``width`` px, with the paper's Fig. 1
drawn on it (``common.viewer.draw.fig1_with_zoom``): the tracked pose's arc in full (keypoints
A..E, A the tip; its axes), the other methods' arcs thin, the true arc and keypoints in thin
green, each instrument's jaw frame (the one the truth says holds the needle ringed), a zoomed
inset around the needle, and a caption: the frame, its time in the take, the method's error
(mm / deg), the track's mode (``PoseEstimate.mode``: rest, held, free) with the jaws that hold
the needle (the tracker's ``InHandPose``), the share of the arc seen.
MPEG-4 Part 2 (fourcc ``mp4v``, in every OpenCV build with FFmpeg), ``30 / every`` frames a
second: the take's own pace when its frames are 30 Hz.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import numpy as np

from common.errors import NeedletrackError
from common.data.truth import true_T_world_ecm
from common.evaluation.moving import method_errors, shown_take

FOURCC = "mp4v"
TAKE_HZ = 30.0


class VideoError(NeedletrackError, RuntimeError):
    """The video could not be written (no encoder for ``FOURCC``, or the file not writable)."""


def _caption(seq: int, t_s: float, method: str, err, mode: Optional[str], holder: Optional[str],
             seen: Optional[float]) -> str:
    pose = "no pose" if err is None or not np.isfinite(err[0]) else \
        f"{err[0] * 1e3:.2f} mm / {np.degrees(err[1]):.1f} deg"
    return "\n".join([f"frame {seq}  {t_s:.2f} s", f"{method}: {pose}",
                      f"mode: {mode or 'n/a'}" + (f" by {holder}" if holder else ""),
                      f"arc seen: {'n/a' if seen is None else f'{100 * seen:.0f}%'}"])


def take_frames(col, ev, rig, needle, load_images: Optional[Callable[[int], dict]], visible: dict,
                arm=None, method: str = "tracked", also=("refined",), width: int = 640, every: int = 1):
    """Yield ``(seq, BGR picture)`` for every ``every``-th frame of the shown take (module
    docstring). ``col``: a ``Collected``; ``ev``: its ``Evaluation``; ``load_images(seq)`` ->
    {camera: full-size BGR or None} (None: black); ``visible``: {seq: share of the arc seen};
    ``arm``: the ``EcmArm`` when the truth gives joints, not ``T_world_ecm``. Pictures are
    ``width`` px wide at most (never enlarged), with even sides (what the encoder needs)."""
    from common.viewer.draw import PoseToDraw, downscale, fig1_with_zoom, instruments_to_draw

    take = shown_take(col.truths)
    cam = rig.left
    errors = method_errors(ev.pose[method], set(take)) if method in ev.pose else {}
    for k, seq in enumerate(take[::max(1, int(every))]):
        gt = col.truths[seq]
        img = (load_images(seq) if load_images is not None else {}).get("left")
        if img is None:
            img = np.zeros((cam.height, cam.width, 3), np.uint8)
        small, scale = downscale(img, width, 4 * width)
        small = small[:small.shape[0] // 2 * 2, :small.shape[1] // 2 * 2]
        poses = {}
        for m in (method, *also):
            msg = col.poses.get(m, {}).get(seq)
            if msg is not None:
                poses[m] = PoseToDraw(np.asarray(msg.T_ecm_needle, float), bool(msg.ambiguous))
        held, tracked = col.in_hand.get(seq), col.poses.get(method, {}).get(seq)
        caption = _caption(seq, k * max(1, int(every)) / TAKE_HZ, method, errors.get(seq),
                           tracked.mode if tracked is not None else None, held.name if held is not None else None,
                           visible.get(seq))
        yield seq, fig1_with_zoom(small, scale, cam, needle, poses, method, None, ev.T_true.get(seq), caption,
                                  instruments=instruments_to_draw(col.instruments.get(seq, {}),
                                                                  true_T_world_ecm(gt, arm)))


def write_take_video(path, col, ev, rig, needle, load_images: Optional[Callable[[int], dict]] = None,
                     visible: Optional[dict] = None, arm=None, method: str = "tracked",
                     width: int = 640, every: int = 1) -> int:
    """Write ``take_frames`` to ``path`` (MP4, ``TAKE_HZ / every`` frames/s); returns the frames
    written (0, and no file: no moving take). Raises ``VideoError`` when OpenCV cannot write it."""
    import cv2

    path = Path(path)
    path.unlink(missing_ok=True)
    writer, n = None, 0
    try:
        for _, pic in take_frames(col, ev, rig, needle, load_images, visible or {}, arm, method,
                                  width=width, every=every):
            if writer is None:
                h, w = pic.shape[:2]
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*FOURCC), TAKE_HZ / max(1, int(every)),
                                         (w, h))
                if not writer.isOpened():
                    raise VideoError(f"{path}: OpenCV cannot write {FOURCC} video {w}x{h} "
                                     f"(cv2 {cv2.__version__}, its video I/O: cv2.getBuildInformation())")
            writer.write(pic)
            n += 1
    finally:
        if writer is not None:
            writer.release()
    return n
