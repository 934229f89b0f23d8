"""Errors against ground truth: statistics, which frames count, pose,
NEES, keypoint and 3D-point errors. Pure functions.

Units: poses and points in metres inside, reported in mm / deg / px as the result keys say. A
pose's position error is the distance between the estimated and true needle origins; its
orientation error is the angle of ``R_est^T R_true`` (``common.geometry.transforms.pose_error``),
both compared in the ECM frame of the frame they were made for.

Which frames count: a single-frame method (``pnp_average``, ``pnp_joint``, ``triangulation``,
``refined``) counts every frame with a known true pose; a multi-view method (``multiview``,
``multiview_refined``) counts the last step of every sequence (frames without a ``sequence``
are each a sequence of their own). A counted frame without a pose is a failure.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from common.geometry.needle import NeedleModel
from common.geometry.refine import tip_for_tail
from common.geometry.transforms import R_to_rotvec, pose_error
from common.methods import MULTIVIEW_METHODS
from common.runtime.messages import GroundTruth, Keypoints, Points3D, PoseEstimate


# ---------------------------------------------------------------- statistics

def summary(values) -> dict:
    """``{"mean", "median", "std", "max"}`` of the finite values (None for each when none)."""
    v = _finite(values)
    if v.size == 0:
        return {"mean": None, "median": None, "std": None, "max": None}
    return {"mean": float(v.mean()), "median": float(np.median(v)), "std": float(v.std()),
            "max": float(v.max())}


def mean_std(values) -> dict:
    """``{"mean", "std", "median", "n"}`` of the finite values (None when there are none)."""
    v = _finite(values)
    if v.size == 0:
        return {"mean": None, "std": None, "median": None, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std()), "median": float(np.median(v)),
            "n": int(v.size)}


def pearson(x, y) -> Optional[float]:
    """Pearson correlation of the pairs where both are finite (x, y in px or mm); None if
    undefined (fewer than 3 pairs or no spread)."""
    x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 3:
        return None
    # Spreads below 1e-9 (px, mm) are numerical noise: no correlation to speak of.
    if x.std() < 1e-9 or y.std() < 1e-9:
        return None
    dx, dy = x - x.mean(), y - y.mean()
    return float(dx @ dy / math.sqrt(float(dx @ dx) * float(dy @ dy)))


def percentile(values, q: float) -> Optional[float]:
    v = _finite(values)
    return float(np.percentile(v, q)) if v.size else None


def _finite(values) -> np.ndarray:
    v = np.asarray(values, dtype=float).ravel()
    return v[np.isfinite(v)]


# ---------------------------------------------------------------- which frames count

def last_steps(truths: dict) -> list[int]:
    """Seqs of the last step of every sequence (largest ``step``, then largest seq).

    A frame without ``sequence``, or of a take whose needle moves (``needle_at_rest`` false), is a
    sequence of its own (``GroundTruth.multiview_group``).
    """
    best: dict = {}
    for seq, gt in truths.items():
        group = gt.multiview_group
        key = ("seq", seq) if group is None else ("sequence", group)
        rank = (gt.step if gt.step is not None else -1, seq)
        if key not in best or rank > best[key][0]:
            best[key] = (rank, seq)
    return sorted(s for _, s in best.values())


def counted_seqs(method: str, truths: dict, posed: set) -> list[int]:
    """Frames on which ``method`` is scored: see the module docstring. ``posed``: seqs with a
    known true pose."""
    seqs = last_steps(truths) if method in MULTIVIEW_METHODS else sorted(truths)
    return [s for s in seqs if s in posed]


def needle_distance_m(T_ecm_needle: np.ndarray) -> float:
    """Camera distance of the needle: its origin's distance from the ECM origin (m)."""
    return float(np.linalg.norm(T_ecm_needle[:3, 3]))


def pose_error_table(poses: dict, T_true: dict, seqs, needle: Optional[NeedleModel] = None) -> dict:
    """Errors of one method on the counted ``seqs``: NaN where no pose was given. With the
    ``needle``, also ``orientation_turned_rad``: the error of the pose's other reading, turned
    end for end (``tip_for_tail``: the same origin, so the same position error)."""
    pos = np.full(len(seqs), np.nan)
    rot = np.full(len(seqs), np.nan)
    rot_turned = np.full(len(seqs), np.nan)
    views = np.full(len(seqs), np.nan)
    nees = np.full(len(seqs), np.nan)
    amb = np.full(len(seqs), np.nan)
    tip = np.full(len(seqs), np.nan)
    for i, s in enumerate(seqs):
        p = poses.get(s)
        if p is None:
            continue
        T = np.asarray(p.T_ecm_needle if isinstance(p, PoseEstimate) else p, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            continue
        pos[i], rot[i] = pose_error(T, T_true[s])
        if needle is not None:
            rot_turned[i] = pose_error(tip_for_tail(T, needle), T_true[s])[1]
        views[i] = getattr(p, "n_views", 1)
        nees[i] = pose_nees(T, getattr(p, "covariance", None), T_true[s])
        if getattr(p, "ambiguous", None) is not None:
            amb[i] = float(p.ambiguous)
        if getattr(p, "end_identity", None) is not None:
            tip[i] = float(p.end_identity)
    dist = np.array([needle_distance_m(T_true[s]) for s in seqs])
    return {"seqs": list(seqs), "position_m": pos, "orientation_rad": rot, "distance_m": dist,
            "n_views": views, "nees": nees, "ambiguous": amb, "end_identity": tip,
            "orientation_turned_rad": rot_turned}


NEES_99PCT = 16.81   # chi-square(6) exceeds this in 1% of the draws (its median: 5.35)
SWAP_DEG = 150.0
"""A pose this far off in orientation is the needle turned end for end (tip for tail)."""
RIGHT_MM, RIGHT_DEG = 2.0, 5.0
"""A pose within this of the truth is right ("sure and right": stated sure, and right)."""
RELIABILITY_BINS = (0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99, 1.0)
"""Bins of a pose's stated tip probability for the reliability table (the last bin closed)."""


def within_calibration_bound(stated: float, measured: float) -> bool:
    """The tip probability's honesty bound: the measured turned share at most 1.5 times the
    stated one plus 2 points."""
    return measured <= 1.5 * stated + 0.02


def reliability_table(p_tip: np.ndarray, turned: np.ndarray) -> list[dict]:
    """Per bin of the stated tip probability ``p_tip`` (>= 0.5): n, the turned share the poses
    state (mean 1 - p), the share found ``turned``, and whether it is within the bound."""
    rows = []
    edges = RELIABILITY_BINS
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        sel = (p_tip >= lo) & ((p_tip < hi) if k < len(edges) - 2 else (p_tip <= hi))
        if not sel.any():
            continue
        stated, measured = float(np.mean(1.0 - p_tip[sel])), float(np.mean(turned[sel]))
        rows.append({"p_from": lo, "p_to": hi, "n": int(sel.sum()), "stated": stated, "measured": measured,
                     "within_bound": within_calibration_bound(stated, measured)})
    return rows


def pose_nees(T_est: np.ndarray, covariance, T_true: np.ndarray) -> float:
    """Normalised estimation error squared of a pose with its covariance (6, 6) over [rotation
    vector (rad), translation (m)] in the ECM frame, the error being the truth as a left
    increment of the estimate: chi-square with 6 degrees of freedom (median 5.35) when the
    covariance is honest. NaN without a usable covariance."""
    if covariance is None:
        return float("nan")
    C = np.asarray(covariance, float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return float("nan")
    d = np.concatenate([R_to_rotvec(T_true[:3, :3] @ T_est[:3, :3].T), T_true[:3, 3] - T_est[:3, 3]])
    try:
        return float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        return float("nan")


def keypoint_errors_2d(kp: Optional[Keypoints], uv_true, visible=None) -> np.ndarray:
    """(5,) pixel errors of a detection against the true A..E; NaN where the detector gave no
    point (not found, or NaN) or the truth marks the point invisible."""
    err = np.full(5, np.nan)
    if kp is None or not kp.found or uv_true is None:
        return err
    uv_true = np.asarray(uv_true, float).reshape(5, 2)
    d = np.linalg.norm(np.asarray(kp.uv, float).reshape(5, 2) - uv_true, axis=1)
    ok = np.isfinite(d)
    if visible is not None:
        ok &= np.asarray(visible, bool).reshape(5)
    err[ok] = d[ok]
    return err


def point_errors_3d(p3: Optional[Points3D], T_true: np.ndarray, needle: NeedleModel) -> np.ndarray:
    """(5,) distances (m) of triangulated A..E from the true keypoints in the ECM frame."""
    err = np.full(5, np.nan)
    if p3 is None:
        return err
    true = needle.keypoints() @ T_true[:3, :3].T + T_true[:3, 3]
    d = np.linalg.norm(np.asarray(p3.points_ecm, float).reshape(5, 3) - true, axis=1)
    ok = np.isfinite(d) & np.asarray(p3.valid, bool).reshape(5)
    err[ok] = d[ok]
    return err


def needle_visible(gt: GroundTruth, camera: str) -> Optional[bool]:
    """Whether the truth says the needle is seen in a camera (None when it does not say)."""
    if gt.visible is not None and gt.visible.get(camera) is not None:
        return bool(np.any(np.asarray(gt.visible[camera], bool)))
    if gt.bbox is not None and camera in gt.bbox:
        return gt.bbox[camera] is not None
    return None


VISIBLE_BINS = (0.0, 0.1, 0.3, 0.6, 1.0001)
"""Edges of the visible-fraction bins: under 10%, 10-30%, 30-60%, 60-100%."""


def visible_fraction(frame, camera: str) -> Optional[float]:
    """The share of the arc seen in ``camera``: ``arc_visible``, else the share of visible keypoints."""
    if getattr(frame, "arc_visible", None) is not None:
        return float(frame.arc_visible[camera])
    if frame.visible is not None and frame.visible.get(camera) is not None:
        return float(np.mean(frame.visible[camera]))
    return None
