"""The error-state pieces of the needle tracker (``common.geometry.needle_tracker``) on SE(3):
a pose's error ``[w, v]`` (rad, m) with ``R = exp([w]x) R_hat``, ``t = t_hat + v``; the motion
models' process noise, the jaws' lever arm, the Mahalanobis distance."""
from __future__ import annotations

import numpy as np

from common.geometry.transforms import make_T, rotvec_to_R, skew


def retract(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``T`` moved by the error ``d`` = [w, v]: ``R = exp([w]x) R``, ``t = t + v``."""
    return make_T(rotvec_to_R(d[:3]) @ T[:3, :3], T[:3, 3] + d[3:6])


def jaw_jacobian(T_world_jaw: np.ndarray, T_world_needle: np.ndarray) -> np.ndarray:
    """d(needle pose error, world) / d(jaw pose error about its pivot, world): a turn of the jaws
    moves the needle's origin by its lever arm from the pivot."""
    J = np.eye(6)
    J[3:, :3] = -skew(T_world_needle[:3, 3] - T_world_jaw[:3, 3])
    return J


def random_walk(sigma_rad: float, sigma_m: float, dt: float) -> np.ndarray:
    """6x6 process noise of a pose's random walk over ``dt`` s (sigmas per sqrt(s))."""
    return np.diag([sigma_rad ** 2] * 3 + [sigma_m ** 2] * 3) * max(dt, 0.0)


def constant_velocity(dt: float, accel_rad_s2: float, accel_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, Q) 12x12 of the error [w, v, omega, u] over ``dt`` s under white acceleration."""
    F = np.eye(12)
    F[:6, 6:] = dt * np.eye(6)
    q = np.array([accel_rad_s2 ** 2] * 3 + [accel_m_s2 ** 2] * 3)
    Q = np.zeros((12, 12))
    Q[:6, :6] = np.diag(q) * dt ** 3 / 3
    Q[:6, 6:] = Q[6:, :6] = np.diag(q) * dt ** 2 / 2
    Q[6:, 6:] = np.diag(q) * dt
    return F, Q


def nis(r: np.ndarray, S: np.ndarray) -> float:
    """Mahalanobis^2 of a residual ``r`` under covariance ``S`` (inf when S is singular)."""
    try:
        return float(r @ np.linalg.solve(S, r))
    except np.linalg.LinAlgError:
        return float("inf")


def block_rotation(R: np.ndarray, n: int = 6) -> np.ndarray:
    """blkdiag(R, R[, ...]) of size n: a [w, v(, ...)] error from one frame's axes to another's."""
    A = np.zeros((n, n))
    for i in range(0, n, 3):
        A[i:i + 3, i:i + 3] = R
    return A
