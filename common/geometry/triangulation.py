"""Pipeline II: DLT stereo triangulation of the keypoints and Arun's registration of the needle
model onto them -> ``T_ecm_needle`` (ECM frame, m).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.observations import NoPose, stereo_observations
from common.geometry.transforms import make_T

MIN_POINTS = 4


def triangulate_dlt(uv_left, uv_right, P_left, P_right) -> np.ndarray:
    """Linear (DLT) triangulation of N point pairs -> (N, 3) points in the frame of the 3x4
    projection matrices ``P = K [R | t]`` (e.g. ``Camera.P_ecm``). Pixels must be undistorted.

    Each point is the null vector of its 4x4 DLT system (rows scaled to unit norm for
    conditioning). Rows with a non-finite pixel, or whose solution is at infinity, are NaN.
    """
    a = np.asarray(uv_left, dtype=float).reshape(-1, 2)
    b = np.asarray(uv_right, dtype=float).reshape(-1, 2)
    if a.shape != b.shape:
        raise ValueError(f"triangulate_dlt: left {a.shape} and right {b.shape} differ")
    P1, P2 = np.asarray(P_left, float), np.asarray(P_right, float)
    A = np.stack([a[:, :1] * P1[2] - P1[0], a[:, 1:] * P1[2] - P1[1],
                  b[:, :1] * P2[2] - P2[0], b[:, 1:] * P2[2] - P2[1]], axis=1)   # (N, 4, 4)
    out = np.full((len(a), 3), np.nan)
    ok = np.all(np.isfinite(A), axis=(1, 2))
    if not np.any(ok):
        return out
    A = A[ok] / np.linalg.norm(A[ok], axis=2, keepdims=True)
    _, _, Vt = np.linalg.svd(A)
    X = Vt[:, -1, :]
    w = X[:, 3]
    good = np.abs(w) > 1e-12 * np.linalg.norm(X, axis=1)
    res = np.full((len(X), 3), np.nan)
    res[good] = X[good, :3] / w[good, None]
    out[ok] = res
    return out


def arun_register(model_points, measured_points, weights=None) -> tuple[np.ndarray, float]:
    """Rigid ``T`` minimising sum_i w_i |T p_i - q_i|^2 (Arun/Umeyama SVD), and its weighted
    RMS residual (m).

    ``model_points`` p (N, 3) in the needle frame, ``measured_points`` q (N, 3), N >= 3. When
    the SVD's best orthogonal matrix is a reflection (det -1), the sign of the last singular
    direction is flipped, giving the best proper rotation (this is exact for coplanar points,
    such as the needle's, whose reflection across their plane fits equally well).
    Raises NoPose for fewer than 3 finite points or collinear/coincident ones.
    """
    p = np.asarray(model_points, dtype=float).reshape(-1, 3)
    q = np.asarray(measured_points, dtype=float).reshape(-1, 3)
    if p.shape != q.shape:
        raise ValueError(f"arun_register: model {p.shape} and measured {q.shape} differ")
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    ok = np.all(np.isfinite(p), 1) & np.all(np.isfinite(q), 1) & np.isfinite(w) & (w > 0)
    p, q, w = p[ok], q[ok], w[ok]
    if len(p) < 3:
        raise NoPose("too_few_points", f"{len(p)} finite 3D points, need 3")
    ws = w / w.sum()
    pc, qc = ws @ p, ws @ q
    P, Q = p - pc, q - qc
    for pts, name in ((P, "model"), (Q, "measured")):
        s = np.linalg.svd(pts * np.sqrt(ws)[:, None], compute_uv=False)
        if s[0] < 1e-9:
            raise NoPose("coincident", f"{name} points coincide")
        if s[1] < 1e-6 * s[0]:
            raise NoPose("collinear", f"{name} points are collinear")
    H = (P * ws[:, None]).T @ Q                       # sum w p q^T
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    t = qc - R @ pc
    r = q - (p @ R.T + t)
    rms = float(np.sqrt(ws @ np.sum(r * r, axis=1)))
    return make_T(R, t), rms


@dataclass
class TriangulationResult:
    """Pipeline II output: the pose, the triangulated keypoints (5, 3) in the ECM frame (NaN
    where not triangulated), ``valid`` (5,), and the registration RMS (m)."""

    T_ecm_needle: np.ndarray
    points_ecm: np.ndarray
    valid: np.ndarray
    rms_m: float


def triangulate_keypoints(uv: dict, rig: StereoRig, n_points: int = 5, scores: dict | None = None,
                          min_score: float = 0.5) -> tuple[np.ndarray, np.ndarray, int]:
    """Triangulate keypoints usable in both images -> (points_ecm (n, 3), valid (n,), n_behind).

    A point is valid when both its pixels are usable, it triangulates to a finite point and
    lies in front of both cameras; ``n_behind`` counts the ones that lay behind.
    """
    dummy = np.zeros((n_points, 3))
    obs = stereo_observations(uv, rig, dummy, scores, min_score)
    pts = np.full((n_points, 3), np.nan)
    valid = np.zeros(n_points, dtype=bool)
    if "left" not in obs or "right" not in obs:
        return pts, valid, 0
    L, R = obs["left"], obs["right"]
    idx, il, ir = np.intersect1d(L.index, R.index, return_indices=True)
    if len(idx) == 0:
        return pts, valid, 0
    X = triangulate_dlt(L.uv[il], R.uv[ir], rig.left.P_ecm, rig.right.P_ecm)
    finite = np.all(np.isfinite(X), axis=1)
    in_front = finite.copy()
    for cam in rig.cameras:
        z = X[finite] @ cam.T_cam_ecm[2, :3] + cam.T_cam_ecm[2, 3]
        in_front[finite] &= z > 0
    pts[idx[in_front]] = X[in_front]
    valid[idx[in_front]] = True
    return pts, valid, int(np.sum(finite & ~in_front))


def triangulation_pose(uv: dict, rig: StereoRig, model_points, scores: dict | None = None,
                       min_score: float = 0.5, max_rms_m: float | None = None) -> TriangulationResult:
    """Pipeline II: triangulate the keypoints seen in both cameras, register the model onto them.

    Weighted by the smaller of the two scores per point. Needs ``MIN_POINTS`` (4) valid points,
    otherwise NoPose (``behind_camera`` when points were dropped for lying behind the cameras).
    """
    model_points = np.asarray(model_points, dtype=float)
    pts, valid, n_behind = triangulate_keypoints(uv, rig, len(model_points), scores, min_score)
    n = int(valid.sum())
    if n < MIN_POINTS:
        if n_behind and n + n_behind >= MIN_POINTS:
            raise NoPose("behind_camera", f"{n_behind} keypoints triangulate behind the cameras")
        raise NoPose("too_few_points", f"{n} keypoints triangulated, need {MIN_POINTS}")
    w = None
    if scores is not None and scores.get("left") is not None and scores.get("right") is not None:
        w = np.minimum(np.asarray(scores["left"], float), np.asarray(scores["right"], float))[valid]
    T, rms = arun_register(model_points[valid], pts[valid], w)
    if max_rms_m is not None and rms > max_rms_m:
        raise NoPose("high_residual", f"registration RMS {rms * 1e3:.2f} mm > {max_rms_m * 1e3} mm")
    return TriangulationResult(T, pts, valid, rms)
