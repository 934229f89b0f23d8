"""One viewer frame, shared by the live node and ``needletrack eval --rrd``: the two Fig. 1
pictures as JPEG (``pictures``), and everything of that frame logged to Rerun (``log_frame``).

Units as in ``common.viewer.draw`` and ``common.viewer.rerun_log``.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from common.viewer.draw import encode_jpeg, fig1_with_zoom



def pictures(images: dict, rig, needle, poses: dict, final: Optional[str], keypoints: dict,
             T_true, seq: int, quality: int = 75, instruments=()) -> dict:
    """``{camera: JPEG bytes}``: each camera's Fig. 1 (with its zoomed inset). ``images``:
    camera -> (downscaled BGR image, scale); ``poses``: method -> ``PoseToDraw``; ``keypoints``:
    camera -> (5, 2) full-size px or None; ``instruments``: ``InstrumentToDraw``."""
    out = {}
    for cam, (small, scale) in images.items():
        caption = f"{cam}  seq {seq}  {final or 'no pose input'}" + ("" if final in poses else ": no pose")
        pic = fig1_with_zoom(small, scale, rig[cam], needle, poses, final, keypoints.get(cam), T_true, caption,
                             instruments=instruments)
        out[cam] = encode_jpeg(pic, quality)
    return out


def log_frame(rec, rl, seq: int, stamp_ns: int, jpegs: dict, needle, poses: dict, T_true,
              T_world_ecm=None, ecm_path=None, scalars: Optional[dict] = None) -> None:
    """Log one frame to the Rerun stream ``rec`` (``rl``: the ``rerun_log`` module): the
    pictures, the ECM pose and path, each method's needle arc and the truth's, and ``scalars``
    ``{series: {line: value}}`` (None values skipped)."""
    rl.set_frame(rec, seq, stamp_ns)
    for cam, jpeg in jpegs.items():
        rl.log_image(rec, cam, jpeg)
    if T_world_ecm is not None:
        rl.log_ecm(rec, T_world_ecm, ecm_path)
    arc = needle.sample_arc(48)
    for m, pose in poses.items():
        rl.log_needle(rec, m, arc, pose.T_ecm_needle, pose.ambiguous)
    if T_true is not None:
        rl.log_needle(rec, "truth", arc, T_true)
    for series, lines in (scalars or {}).items():
        for line, v in lines.items():
            if v is not None and np.isfinite(v):
                rl.log_scalar(rec, series, line, v)
