"""The weighted reprojection error of a needle pose in one or more cameras, its analytic
Jacobian, its batched Levenberg-Marquardt over many starting poses (``lm``), and the pose
covariance.

Poses ``T_ecm_needle`` in the ECM frame (m, rad), pixels ideal (undistorted). Cost
``sum_i w_i |r_i|^2`` (px^2, ``w_i`` the keypoint's score). Perturbation convention (Jacobians,
covariances): ``delta = [w, v]`` (rad, m) acts as ``R = exp([w]x) R0``, ``t = t0 + v``: a
rotation vector in ECM axes about the needle origin and a translation of the needle origin in
the ECM frame, the order of ``PoseEstimate.covariance``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from common.geometry import lm
from common.geometry.covariance_bound import bounded_inverse, within_bound
from common.geometry.observations import CameraObs
from common.geometry.transforms import make_T, skew, symmetrise


class ReprojectionProblem:
    """The weighted reprojection error of a needle pose in one or more cameras.

    Holds every observation flattened to per-point arrays so residuals and their Jacobian are a
    handful of vectorised operations. Internally a pose is ``(R, t')`` with ``t' = R c + t``:
    rotations act about ``c``, the centroid of the observed model points, which decouples
    rotation from translation far better than the arc centre (off the points) does. ``refine``
    and ``evaluate`` take and return public ``T_ecm_needle`` and Jacobians in the module's
    [w, v] convention.
    """

    def __init__(self, observations: Sequence[CameraObs]):
        obs = [o for o in observations if o.n > 0]
        self.n = sum(o.n for o in obs)
        P = np.concatenate([o.points for o in obs]) if obs else np.zeros((0, 3))
        self.centre = P.mean(axis=0) if len(P) else np.zeros(3)
        self.P = P - self.centre
        self.size = float(np.max(np.linalg.norm(self.P, axis=1))) if len(P) else 0.0
        KRc, Ktc, r3 = [], [], []
        for o in obs:
            T_cam_ecm = o.camera.T_cam_ecm
            KR = o.camera.K @ T_cam_ecm[:3]                 # K [R_cam_ecm | t_cam_ecm]
            KRc.append(np.broadcast_to(KR[:, :3], (o.n, 3, 3)))
            Ktc.append(np.broadcast_to(KR[:, 3], (o.n, 3)))
            r3.append(np.broadcast_to(T_cam_ecm[2, :3], (o.n, 3)))   # camera z axis in ECM
        self.KRc = np.concatenate(KRc) if obs else np.zeros((0, 3, 3))
        self.Ktc = np.concatenate(Ktc) if obs else np.zeros((0, 3))
        self.r3 = np.concatenate(r3) if obs else np.zeros((0, 3))
        self.uv = np.concatenate([o.uv for o in obs]) if obs else np.zeros((0, 2))
        w = np.concatenate([o.weights for o in obs]) if obs else np.zeros(0)
        self.sw = np.sqrt(w)
        self.sw2 = np.repeat(self.sw[:, None], 2, axis=1)
        self.w_sum = float(np.sum(w))

    def _residuals(self, R: np.ndarray, t: np.ndarray, jacobian: bool = True):
        """Internal poses (R (k, 3, 3), t' (k, 3)) -> weighted residuals (k, 2n), Jacobians
        (k, 2n, 6) w.r.t. the internal [w, v'] (or None), and (k,) whether every point is in
        front of its camera (residuals of the others are meaningless)."""
        q = self.P @ R.transpose(0, 2, 1)                                   # (k, n, 3) rotated
        h = (self.KRc @ (q + t[:, None, :])[..., None])[..., 0] + self.Ktc  # K p_cam
        z = h[..., 2]
        front = z > 1e-9
        ok = front.all(axis=1)
        iz = 1.0 / np.where(front, z, 1.0)
        uvp = h[..., :2] * iz[..., None]
        r = ((uvp - self.uv) * self.sw2).reshape(len(R), -1)
        if not jacobian:
            return r, None, ok
        # d(u, v)/d(ECM point) = (K[:2] R_cam_ecm - uv r3^T) / z, r3 = the camera's z axis
        B = self.KRc[:, :2, :] - uvp[..., None] * self.r3[:, None, :]
        B *= (self.sw * iz)[..., None, None]
        # d(exp([w]x) q)/dw = -[q]x = [-q]x
        Jw = B @ (-q @ _SKEW).reshape(q.shape + (3,))
        return r, np.concatenate([Jw, B], axis=3).reshape(len(R), -1, 6), ok

    def _linearise(self, R, t, prev=None):
        """``lm.run``'s view: (r, J, weights None (in r already), cost, no extra); a pose with a
        point behind its camera costs inf."""
        r, J, ok = self._residuals(R, t)
        return r, J, None, np.where(ok, np.einsum("km,km->k", r, r), np.inf), {}

    def _to_internal(self, Ts):
        Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
        R = Ts[:, :3, :3].copy()
        return R, Ts[:, :3, 3] + R @ self.centre

    def _to_public(self, R, t, J):
        """Back to ``T_ecm_needle`` and the public Jacobian (one pose): t = t' - R c and
        v = v' + [R c]x w, so J = J' M^-1 with M^-1 = [[I, 0], [-[R c]x, I]]."""
        qc = R @ self.centre
        if J is not None:
            J = J.copy()
            J[:, :3] -= J[:, 3:] @ skew(qc)
        return make_T(R, t - qc), J

    def evaluate(self, T_ecm_needle: np.ndarray, jacobian: bool = True):
        """(weighted residuals (2n,), Jacobian (2n, 6) or None) at a pose; None when a point
        is behind its camera. Residual pairs follow the observations' point order."""
        R, t = self._to_internal(T_ecm_needle)
        r, J, ok = self._residuals(R, t, jacobian)
        if not ok[0]:
            return None
        return r[0], None if J is None else self._to_public(R[0], t[0], J[0])[1]

    def rms_px(self, T_ecm_needle: np.ndarray) -> float:
        """Weighted reprojection RMS (px) at a pose; inf when a point is behind its camera."""
        out = self.evaluate(T_ecm_needle, jacobian=False)
        return math.inf if out is None else float(np.sqrt(out[0] @ out[0] / self.w_sum))

    def refine(self, T0: np.ndarray, **kw) -> "LMResult | None":
        """Levenberg-Marquardt from ``T0`` (``T_ecm_needle``); see ``refine_many``."""
        return self.refine_many([T0], **kw)[0]

    def refine_many(self, T0s: Sequence[np.ndarray], max_iter: int = 60, tol_m: float = 1e-11,
                    rel_tol: float = 1e-7, merge_m: float = 1e-3,
                    merge_rad: float = np.deg2rad(1.0)) -> "list[LMResult | None]":
        """Levenberg-Marquardt from several starting poses at once (vectorised over them).

        Each fit stops when a step moves no model point by more than ``tol_m`` (m) or the
        decrease it predicts is below ``rel_tol`` times its cost; steps that would put a point
        behind a camera are rejected. A fit that comes within ``merge_m`` and ``merge_rad`` of
        one already converged stops there with ``merged_into`` set to that one's index (it
        would converge to the same minimum). None for a start that puts a point behind its
        camera (or with fewer than 3 points).
        """
        k = len(T0s)
        if self.n < 3 or k == 0:
            return [None] * k
        R, t = self._to_internal(T0s)
        size, cos_merge = self.size, math.cos(merge_rad)

        def stop(dx, acc, pred, c1, c0, fits, act):
            step_m = (np.sqrt(np.einsum("ki,ki->k", dx[:, :3], dx[:, :3])) * size
                      + np.sqrt(np.einsum("ki,ki->k", dx[:, 3:], dx[:, 3:])))
            return np.where(acc, (step_m < tol_m) | (pred <= rel_tol * c1) | (c1 < 1e-26),
                            (step_m < tol_m) | (pred <= 1e-3 * rel_tol * c0))   # nothing to gain

        def merge(fits, act):
            """Fits heading to a minimum already found stop there."""
            if not fits.converged.any():
                return np.ones(len(act), bool)
            conv_idx = np.flatnonzero(fits.converged)
            near_t = np.all(np.abs(fits.t[act, None, :] - fits.t[None, conv_idx, :]) < merge_m, axis=2)
            cosang = (np.einsum("aij,cij->ac", fits.R[act], fits.R[conv_idx]) - 1.0) / 2.0
            near = near_t & (cosang > cos_merge)
            hit = near.any(axis=1)
            fits.merged[act[hit]] = conv_idx[np.argmax(near[hit], axis=1)]
            return ~hit

        s = lm.run(lm.Fits(R, t, self._linearise(R, t)), self._linearise, max_iter, stop,
                   damping="nielsen", after=merge, scaled=False)
        ok = np.isfinite(s.cost)
        R, t, r, J, cost = s.R, s.t, s.r, s.J, s.cost
        iters, converged, merged = s.iters, s.converged, s.merged
        out: list = []
        for i in range(k):
            if not ok[i]:
                out.append(None)
                continue
            T, Ji = self._to_public(R[i], t[i], J[i])
            rms = float(np.sqrt(cost[i] / self.w_sum)) if self.w_sum > 0 else float("nan")
            out.append(LMResult(T, float(cost[i]), rms, Ji, r[i], int(iters[i]), bool(converged[i]),
                                None if merged[i] < 0 else int(merged[i])))
        return out


# [w]x = (w @ _SKEW).reshape(3, 3) for any vector w
_SKEW = np.array([[0, 0, 0, 0, 0, -1, 0, 1, 0],
                  [0, 0, 1, 0, 0, 0, -1, 0, 0],
                  [0, -1, 0, 1, 0, 0, 0, 0, 0]], dtype=float)


@dataclass
class LMResult:
    """A converged (or stopped) Levenberg-Marquardt fit."""

    T_ecm_needle: np.ndarray
    cost: float          # sum_i w_i |r_i|^2 (px^2)
    rms_px: float        # sqrt(cost / sum_i w_i)
    jacobian: np.ndarray  # (2n, 6) weighted residual Jacobian at the optimum, [w, v] order
    residuals: np.ndarray  # (2n,) weighted residuals (px * sqrt(weight))
    iterations: int
    converged: bool
    merged_into: int | None = None   # index of the known minimum this fit was heading to


def refine_pose_lm(T0: np.ndarray, observations: Sequence[CameraObs], max_iter: int = 60,
                   tol_m: float = 1e-11, rel_tol: float = 1e-7) -> LMResult | None:
    """Levenberg-Marquardt (numpy, analytic Jacobian) on the weighted reprojection error of all
    ``observations``, from ``T0`` = ``T_ecm_needle``.

    Stops when a step moves no model point by more than ``tol_m`` (m) or the decrease it
    predicts is below ``rel_tol`` times the cost. Steps that would put a point behind a camera
    are rejected. Returns None when T0 puts a point behind its camera or fewer than 3 points
    are given. Build a ``ReprojectionProblem`` once to refine many starting poses.
    """
    return ReprojectionProblem(observations).refine(T0, max_iter=max_iter, tol_m=tol_m, rel_tol=rel_tol)


def pose_covariance(jacobian: np.ndarray, cost: float, min_sigma_px: float = 0.25) -> tuple[np.ndarray, bool]:
    """(6, 6) covariance of [w, v] from the weighted Jacobian at the optimum, and whether the fit
    left a direction unfixed.

    ``sigma^2 (J^T J)^-1`` with sigma^2 the residual variance ``cost / (2n - 6)``, floored at
    ``min_sigma_px^2`` so an exact (noise-free) fit does not claim infinite certainty. A
    direction the keypoints do not fix (``J^T J`` singular or nearly) gets the widest honest
    variance (``covariance_bound.bounded_inverse``; then the flag is True), never an arbitrarily
    large one.
    """
    m = jacobian.shape[0]
    dof = m - 6
    s2 = max(cost / dof if dof > 0 else 0.0, min_sigma_px ** 2)
    H = jacobian.T @ jacobian
    try:
        cov = s2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = None
    if cov is None or not within_bound(cov):
        return bounded_inverse(H / s2), True
    return symmetrise(cov), False
