"""Rigid transforms: 4x4 homogeneous ``T_a_b`` mapping frame b to frame a (metres, radians).

``p_a = T_a_b @ p_b``. Rotations are 3x3 matrices; rotation vectors are axis * angle (rad).
"""
from __future__ import annotations

import math

import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: ``T_b_a`` from ``T_a_b``."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply ``T_a_b`` to points ``p_b`` of shape (..., 3); returns ``p_a``."""
    p = np.asarray(p, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def rotvec_to_R(rvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (rad) -> 3x3 rotation."""
    rvec = np.asarray(rvec, dtype=float).reshape(3)
    theta = np.linalg.norm(rvec)
    if theta < 1e-12:
        K = skew(rvec)
        return np.eye(3) + K
    k = rvec / theta
    K = skew(k)
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def rotvecs_to_Rs(w: np.ndarray) -> np.ndarray:
    """Rodrigues for (k, 3) rotation vectors -> (k, 3, 3) rotations. Scalar math per vector: for
    the handful of vectors of an LM step numpy's per-call cost would dominate."""
    out = np.empty((len(w), 3, 3))
    for i, (x, y, z) in enumerate(np.asarray(w, dtype=float).tolist()):
        th2 = x * x + y * y + z * z
        if th2 < 1e-16:
            a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
        else:
            th = math.sqrt(th2)
            a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
        out[i] = ((1 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z),
                  (a * z + b * x * y, 1 - b * (x * x + z * z), -a * x + b * y * z),
                  (-a * y + b * x * z, a * x + b * y * z, 1 - b * (x * x + y * y)))
    return out


def R_to_rotvec(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> rotation vector (rad), stable near 0 and pi."""
    q = R_to_quat(R)
    w, v = q[0], q[1:]
    s = np.linalg.norm(v)
    if s < 1e-12:
        return 2.0 * v
    angle = 2.0 * np.arctan2(s, w)
    return v / s * angle


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = np.asarray(v, dtype=float).reshape(3)
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> unit quaternion [w, x, y, z] with w >= 0."""
    R = np.asarray(R, dtype=float)
    # Shepperd's method via the symmetric 4x4 matrix's dominant eigenvector.
    K = np.array([
        [R[0, 0] + R[1, 1] + R[2, 2], R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]],
        [R[2, 1] - R[1, 2], R[0, 0] - R[1, 1] - R[2, 2], R[0, 1] + R[1, 0], R[0, 2] + R[2, 0]],
        [R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], R[1, 1] - R[0, 0] - R[2, 2], R[1, 2] + R[2, 1]],
        [R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], R[2, 2] - R[0, 0] - R[1, 1]],
    ]) / 3.0
    w, V = np.linalg.eigh(K)
    q = V[:, np.argmax(w)]
    return q if q[0] >= 0 else -q


def quat_to_R(q: np.ndarray) -> np.ndarray:
    """Unit quaternion [w, x, y, z] -> 3x3 rotation."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def symmetrise(C: np.ndarray) -> np.ndarray:
    """The symmetric part of a square matrix, ``(C + C^T) / 2``: a covariance that rounding left a
    little asymmetric, made symmetric again."""
    return 0.5 * (C + C.T)


def project_to_SO3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to a 3x3 matrix, or to each of a stack (..., 3, 3): a
    determinant of +1, never a reflection."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.stack([np.ones_like(d), np.ones_like(d), d], axis=-1)[..., None, :]
    return (U * D) @ Vt


def rotation_mean(Rs, weights=None) -> np.ndarray:
    """Chordal L2 mean of rotations: the rotation nearest to the weighted sum of matrices."""
    Rs = np.asarray(Rs, dtype=float).reshape(-1, 3, 3)
    w = np.ones(len(Rs)) if weights is None else np.asarray(weights, dtype=float)
    return project_to_SO3(np.einsum("i,ijk->jk", w, Rs))


def pose_mean(Ts, weights=None) -> np.ndarray:
    """Mean of poses: chordal rotation mean, weighted mean translation."""
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    w = np.ones(len(Ts)) if weights is None else np.asarray(weights, dtype=float)
    t = (w[:, None] * Ts[:, :3, 3]).sum(0) / w.sum()
    return make_T(rotation_mean(Ts[:, :3, :3], w), t)


def rotation_angle(R: np.ndarray) -> float:
    """Angle (rad) of a rotation, in [0, pi]."""
    c = (np.trace(R) - 1.0) / 2.0
    s = np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.arctan2(s, c))


def pose_delta(T: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """[rotation vector of R R_ref^T (rad), t - t_ref (m)]: T as a left increment of T_ref, in the
    axes both are expressed in (the order of ``PoseEstimate.covariance``: [w, v])."""
    dR = T[:3, :3] @ T_ref[:3, :3].T
    c = (dR[0, 0] + dR[1, 1] + dR[2, 2] - 1.0) / 2.0
    if -0.99 < c < 1.0 - 1e-12:            # away from 0 and pi: the log map directly
        a = math.acos(c)
        w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) * (a / (2 * math.sin(a)))
    else:
        w = R_to_rotvec(dR)
    return np.concatenate([w, T[:3, 3] - T_ref[:3, 3]])


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(position error m, orientation error rad): origin distance and angle of R_est^T R_true."""
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    return dt, rotation_angle(T_est[:3, :3].T @ T_true[:3, :3])


def is_rigid(T, tol: float = 1e-6) -> bool:
    """True when T is a finite 4x4 rigid transform."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (np.allclose(R.T @ R, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol
            and np.allclose(T[3], [0, 0, 0, 1], atol=tol))
