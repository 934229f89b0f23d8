"""``needletrack eval --rrd FILE``: an evaluation's frames, poses and errors as a Rerun
recording, to scrub frame by frame (``needletrack view FILE``). Needs the ``viewer`` extra.

Every frame of the ``Collected`` evaluation (by ``seq``) gets the two Fig. 1 pictures (the
dataset's images, downscaled to fit ``width x height``), every method's needle arc, the truth's,
the ECM pose and path, and per method the position (mm) and orientation (deg) error and the
latency (ms, frame stamp to the evaluator's arrival), and the detector's confidence.
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from common.data.truth import true_T_ecm_needle, true_T_world_ecm
from common.geometry.transforms import pose_error
from common.methods import in_final_order
from common.viewer.draw import PoseToDraw, downscale
from common.frames import CAMERAS
from common.viewer.frame import log_frame, pictures

RRD_MAGIC = (b"RRF0", b"RRF1", b"RRF2")
"""The first bytes of a Rerun recording (.rrd), by format version."""


def rrd_target_problem(path) -> Optional[str]:
    """Why ``path`` may not be written as a new recording, or None when it may: it does not exist
    (in an existing folder), or it is a regular file that holds a Rerun recording (its first
    bytes one of ``RRD_MAGIC``), which the new one replaces. Anything else is the user's."""
    import os
    import stat
    from pathlib import Path
    p = Path(path)
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        parent = p.parent if str(p.parent) else Path(".")
        if not parent.is_dir():
            return f"{path}: its folder {parent} does not exist"
        return None
    except OSError as exc:
        return f"{path}: cannot be checked ({exc.strerror})"
    if stat.S_ISLNK(st.st_mode):
        return f"{path} is a symbolic link; give the recording's own path"
    if not stat.S_ISREG(st.st_mode):
        return f"{path} exists and is not a regular file"
    try:
        with open(p, "rb") as f:
            head = f.read(4)
    except OSError as exc:
        return f"{path}: cannot be read ({exc.strerror})"
    if head not in RRD_MAGIC:
        return f"{path} exists and is not a Rerun recording (.rrd): not replaced"
    return None



def write_rrd(path, col, rig, needle, arm=None, load_images: Optional[Callable[[int], dict]] = None,
              width: int = 960, height: int = 540, quality: int = 80) -> int:
    """Write the recording; returns the number of frames written. ``col``: a
    ``common.evaluation.collect.Collected``; ``load_images(seq)`` -> {camera: BGR or None}
    (None: black pictures)."""
    from common.viewer import rerun_log as rl
    rec = rl.new_recording("needletrack-eval")
    rl.set_sinks(rec, save=str(path))
    scale = min(1.0, width / rig.left.width, height / rig.left.height)
    rl.log_rig(rec, rig, scale)
    methods = in_final_order(m for m in col.poses if col.poses[m])    # the first is drawn in full
    final = methods[0] if methods else None
    path_pts = []
    n = 0
    for seq in sorted(col.truths):
        gt = col.truths[seq]
        T_true = true_T_ecm_needle(gt, arm)
        T_world_ecm = true_T_world_ecm(gt, arm)
        if T_world_ecm is not None:
            path_pts.append(np.asarray(T_world_ecm, float)[:3, 3])
        imgs = load_images(seq) if load_images is not None else {}
        images = {}
        for cam in CAMERAS:
            img = imgs.get(cam)
            if img is None:
                img = np.zeros((rig[cam].height, rig[cam].width, 3), np.uint8)
            images[cam] = downscale(img, width, height)
        poses, scalars = {}, {"pos_err_mm": {}, "rot_err_deg": {}, "latency_ms": {}, "confidence": {}}
        for m in methods:
            msg = col.poses[m].get(seq)
            if msg is None:
                continue
            poses[m] = PoseToDraw(np.asarray(msg.T_ecm_needle, float), bool(msg.ambiguous))
            if T_true is not None:
                dp, dr = pose_error(poses[m].T_ecm_needle, T_true)
                scalars["pos_err_mm"][m], scalars["rot_err_deg"][m] = dp * 1e3, float(np.degrees(dr))
            arrived = col.arrivals_ns.get(m, {}).get(seq)
            if arrived is not None:
                scalars["latency_ms"][m] = (arrived - msg.stamp_ns) * 1e-6
        kps = {}
        for cam in CAMERAS:
            kp = col.keypoints.get((cam, seq))
            if kp is not None:
                scalars["confidence"][cam] = kp.confidence
                kps[cam] = np.asarray(kp.uv, float) if kp.found else None
        jpegs = pictures(images, rig, needle, poses, final, kps, T_true, seq, quality)
        log_frame(rec, rl, seq, gt.stamp_ns, jpegs, needle, poses, T_true, T_world_ecm,
                  np.array(path_pts) if len(path_pts) >= 2 else None, scalars)
        n += 1
    rec.flush()
    rec.disconnect()
    return n
