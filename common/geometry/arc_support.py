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
from common.geometry.covariance_bound import bounded_covariance
from common.geometry.needle import NeedleModel
from common.geometry.transforms import transform_points

SUPPORT_PX = 3.0
"""An arc sample counts as seen within this many pixels of an observation (the detectors'
centrelines err by about a pixel; a hidden part's projection lies at least a wire's width off)."""
ARC_SAMPLES = 41
"""Points along the arc (A to E) whose support is counted: 3 degrees apart on a 120-degree arc."""


END_SAMPLES = 3
"""An end of the arc counts as seen when one of its first (last) this many arc samples is: the
6 degrees of the arc nearest it."""


def arc_support(rig: StereoRig, needle: NeedleModel, T_ecm_needle: np.ndarray, observations: Mapping,
                tol_px: float, min_weight: float = 0.0, min_score: float = 0.5,
                n: int = ARC_SAMPLES) -> dict:
    """{camera: (n,) bool, which samples of the arc (A to E) at ``T_ecm_needle`` (4x4, m) the
    camera's observation supports}: a sample counts when an observed centreline point (weight
    above ``min_weight``) or an observed keypoint (scored at least ``min_score``, not placed
    ``on_arc``) lies within ``tol_px`` of it (or of 3/4 of the centreline points' median spacing,
    if larger). ``observations``: {camera: ``refine.ArcObservation``}; a camera without one is
    left out. A sample behind the camera or outside its image is unsupported."""
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
        out[name] = supported(cam, pts, T_ecm_needle, seen, tol)
    return out


def arc_seen(rig: StereoRig, needle: NeedleModel, T_ecm_needle: np.ndarray, observations: Mapping,
             tol_px: float, min_weight: float = 0.0, min_score: float = 0.5,
             n: int = ARC_SAMPLES) -> dict:
    """{camera: the share (0..1) of the arc at ``T_ecm_needle`` that the camera's observation
    supports} (``arc_support``)."""
    return shares(arc_support(rig, needle, T_ecm_needle, observations, tol_px, min_weight, min_score, n))


def shares(support: Mapping) -> dict:
    """{camera: the share of the arc supported} of ``arc_support``'s masks."""
    return {name: float(np.mean(m)) for name, m in support.items()}


def ends_seen(support: Mapping, k: int = END_SAMPLES) -> tuple[bool, bool]:
    """(A's end seen, E's end seen) in some camera, of ``arc_support``'s masks: a pose fitted to
    an arc one of whose ends no camera saw (under the jaws, in the tissue) has its tip read from
    one end and a cut, which tells little about which end is the tip."""
    return (any(bool(m[:k].any()) for m in support.values()),
            any(bool(m[-k:].any()) for m in support.values()))


def supported(camera, arc_points: np.ndarray, T_ecm_needle: np.ndarray, seen_uv: np.ndarray,
              tol_px: float) -> np.ndarray:
    """(N,) bool: which of ``arc_points`` (needle frame, m) project within ``tol_px`` of some
    pixel of ``seen_uv`` (M, 2) in ``camera``."""
    out = np.zeros(len(arc_points), bool)
    p_cam = transform_points(camera.T_cam_ecm @ T_ecm_needle, arc_points)
    front = p_cam[:, 2] > 1e-6
    if not front.any() or len(seen_uv) == 0:
        return out
    uv = np.full((len(arc_points), 2), np.nan)
    uv[front] = camera.project(p_cam[front])
    ok = front & camera.in_image(np.nan_to_num(uv, nan=-1e9))
    if ok.any():
        out[ok] = ((uv[ok, None, :] - seen_uv[None, :, :]) ** 2).sum(-1).min(axis=1) <= tol_px ** 2
    return out


def best_seen(shares: Mapping) -> Optional[float]:
    """The larger of the cameras' shares (None: no camera): the two views of a 4 mm baseline see
    nearly the same part; a pose is as well fixed as its better-seen view."""
    return max(shares.values()) if shares else None


def partial_view(covariance: Optional[np.ndarray], seen: Optional[float], min_seen: float,
                 inflation: float) -> tuple[bool, Optional[np.ndarray]]:
    """What a pose fitted to the share ``seen`` of its arc states: ``(partial, covariance)``.
    Below ``min_seen`` the pose is a partial view, to be flagged ``ambiguous``, its covariance
    (6x6, [w, v]; None stays None) times ``inflation``: the part seen may fix it to the
    residuals' precision and still leave it millimetres and degrees off (the module docstring)),
    no wider than ``covariance_bound.bounded_covariance`` allows."""
    if seen is None or seen >= min_seen:
        return False, covariance
    return True, None if covariance is None else bounded_covariance(np.asarray(covariance, float) * inflation)[0]
