"""How much of a fitted arc the images saw: the share of the needle's arc, at a pose, that an
observed centreline point or keypoint lies near in a camera.

A pose fitted to a partly seen arc (the jaws or the tissue hide the rest) is fixed by that part
alone: where it is short, the fit can be millimetres and tens of degrees off while its residuals
are small and its covariance thin (``needletrack eval`` on a moving take: the refined poses by
the share of the arc seen). The share measured here, from the fit and the observations alone,
is what tells such a pose apart from a well-seen one (``nodes/refine.py``: ``min_arc_seen``).
"""
from __future__ import annotations

from typing import Mapping, Optional

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import transform_points

SUPPORT_PX = 3.0
"""An arc sample counts as seen within this many pixels of an observation (the detectors'
centrelines err by about a pixel; a hidden part's projection lies at least a wire's width off)."""
ARC_SAMPLES = 41
"""Points along the arc (A to E) whose support is counted: 3 degrees apart on a 120-degree arc."""


def arc_seen(rig: StereoRig, needle: NeedleModel, T_ecm_needle: np.ndarray, observations: Mapping,
             tol_px: float, min_weight: float = 0.0, min_score: float = 0.5,
             n: int = ARC_SAMPLES) -> dict:
    """{camera: the share (0..1) of the arc at ``T_ecm_needle`` (4x4, m) that the camera's
    observation supports}: a sample of the projected arc counts when an observed centreline
    point (weight above ``min_weight``) or an observed keypoint (scored at least ``min_score``, not
    placed ``on_arc``) lies within
    ``tol_px`` of it (or of 3/4 of the centreline points' median spacing, if larger). ``observations``: {camera: ``refine.ArcObservation``}; a camera without one
    is left out. A sample behind the camera or outside its image is unsupported."""
    pts = needle.sample_arc(n)
    out = {}
    for name, obs in observations.items():
        cam, seen, tol = rig[name], [], tol_px
        if obs.centreline is not None and len(obs.centreline):
            c = np.asarray(obs.centreline, float).reshape(-1, 2)
            w = None if obs.centreline_w is None else np.asarray(obs.centreline_w, float).reshape(-1)
            c = c if w is None else c[w > min_weight]
            seen.append(c)
            if len(c) > 2:      # points sparser than the tolerance: half their spacing and a bit
                tol = max(tol, 0.75 * float(np.median(np.linalg.norm(np.diff(c, axis=0), axis=1))))
        if obs.uv is not None and len(obs.uv):
            uv, sc = np.asarray(obs.uv, float).reshape(-1, 2), np.asarray(obs.scores, float).reshape(-1)
            observed = np.ones(len(uv), bool) if obs.on_arc is None else ~np.asarray(obs.on_arc, bool).reshape(-1)
            seen.append(uv[np.isfinite(uv).all(axis=1) & (sc >= min_score) & observed])
        seen = np.concatenate(seen) if seen else np.zeros((0, 2))
        out[name] = supported_share(cam, pts, T_ecm_needle, seen, tol)
    return out


def supported_share(camera, arc_points: np.ndarray, T_ecm_needle: np.ndarray, seen_uv: np.ndarray,
                    tol_px: float) -> float:
    """The share of ``arc_points`` (needle frame, m) that project within ``tol_px`` of some
    pixel of ``seen_uv`` (N, 2) in ``camera``."""
    p_cam = transform_points(camera.T_cam_ecm @ T_ecm_needle, arc_points)
    front = p_cam[:, 2] > 1e-6
    if not front.any() or len(seen_uv) == 0:
        return 0.0
    uv = np.full((len(arc_points), 2), np.nan)
    uv[front] = camera.project(p_cam[front])
    ok = front & camera.in_image(np.nan_to_num(uv, nan=-1e9))
    d2 = ((uv[ok, None, :] - seen_uv[None, :, :]) ** 2).sum(-1).min(axis=1) if ok.any() else np.zeros(0)
    return float(np.count_nonzero(d2 <= tol_px ** 2) / len(arc_points))


def best_seen(shares: Mapping) -> Optional[float]:
    """The larger of the cameras' shares (None: no camera): the two views of a 4 mm baseline see
    nearly the same part; a pose is as well fixed as its better-seen view."""
    return max(shares.values()) if shares else None


def partial_view(covariance: Optional[np.ndarray], seen: Optional[float], min_seen: float,
                 inflation: float) -> tuple[bool, Optional[np.ndarray]]:
    """What a pose fitted to the share ``seen`` of its arc states: ``(partial, covariance)``.
    Below ``min_seen`` the pose is a partial view, to be flagged ``ambiguous``, its covariance
    (6x6, [w, v]; None stays None) times ``inflation``: the part seen may fix it to the
    residuals' precision and still leave it millimetres and degrees off (the module docstring)."""
    if seen is None or seen >= min_seen:
        return False, covariance
    return True, None if covariance is None else np.asarray(covariance, float) * inflation
