"""Simulated clicks: what a user would click on a frame whose true pose is known, with a stated
error, for the benchmark of the labels (``needletrack bench label``) and for learning curves
that label a train split without a person, through the same code path as the page
(``LabelApp.save``).

The tip and the tail are clicked within ``end_px`` of the true A and E, ``wire`` points within
``wire_px`` of the true arc (uniform in a disc: a click lands anywhere within that radius), in
each camera where the truth says the needle is seen; a keypoint the truth says is not seen is
marked hidden; a camera that sees none of it is marked unseen.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from common.frames import CAMERAS
from common.geometry.needle import NeedleModel
from common.geometry.oracle import true_keypoints
from common.geometry.transforms import transform_points
from common.label.fit import CameraClicks


def _in_disc(rng: np.random.Generator, r: float) -> np.ndarray:
    a, d = rng.uniform(0.0, 2.0 * np.pi), r * np.sqrt(rng.uniform())
    return d * np.array([np.cos(a), np.sin(a)])


def simulated_clicks(rig, needle: NeedleModel, T_ecm_needle: np.ndarray, rng: np.random.Generator,
                     end_px: float = 1.0, wire_px: float = 2.0, wire: int = 2,
                     visible: Optional[dict] = None) -> Optional[dict]:
    """{camera: CameraClicks} for a needle at ``T_ecm_needle`` (see the module docstring), or None
    when no camera sees it (a frame to mark no needle). ``visible`` ({camera: (5,) bool}, the
    truth's) marks hidden keypoints; None: seen where inside the image. ``wire`` points per
    camera, evenly spread along the arc between the first and the last seen keypoint."""
    a = needle.keypoint_angles_rad
    out = {}
    for cam in CAMERAS:
        c = rig[cam]
        uv, inside = true_keypoints(c, T_ecm_needle, needle)
        seen = inside if visible is None or visible.get(cam) is None else inside & np.asarray(visible[cam], bool)
        if not seen.any():
            out[cam] = CameraClicks(unseen=True)
            continue
        lo, hi = a[np.flatnonzero(seen)[[0, -1]]]          # the wire points on the seen part
        if hi - lo < 1e-9:
            lo, hi = max(lo - 0.1, a[0]), min(hi + 0.1, a[-1])
        wire_ang = np.linspace(lo, hi, wire + 2)[1:-1] if wire else np.zeros(0)
        p = transform_points(c.T_cam_ecm @ T_ecm_needle, needle.arc_points(wire_ang))
        w = c.project(p) if len(p) else np.zeros((0, 2))
        w = np.array([q + _in_disc(rng, wire_px) for q in w]).reshape(-1, 2)
        w = w[c.in_image(w)]
        clip = lambda q: np.clip(q, -0.5, [c.width - 0.5, c.height - 0.5])
        out[cam] = CameraClicks(clip(uv[0] + _in_disc(rng, end_px)) if seen[0] else None,
                                clip(uv[4] + _in_disc(rng, end_px)) if seen[4] else None,
                                w, ~seen)
    if all(k.unseen for k in out.values()):
        return None
    return out
