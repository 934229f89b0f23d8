"""An arm's kinematic error, as the tracker estimates it: a lumped correction of the reported jaw pose.

A real arm reports its jaw frame (``T_world_jaw``, docs/dataset.md) millimetres and degrees off
(the registration of its base, joint offsets, noise: docs/datasets.md). The correction is one
rigid transform per arm, applied on the left in world::

    T_world_jaw_corrected = K @ T_world_jaw_reported,   K = T(p) @ (R_c, t_c) @ T(-p)

a turn ``R_c`` about the point ``p`` (the arm's first reported jaw position: near the work, so
that the turn and the shift are nearly independent) and a shift ``t_c``. A registration error of
the arm's base is such a ``K``, constant; what changes with the arm's configuration makes ``K``
drift as the arm moves. Its error is ``[w, v]`` (rad, m) of the inner ``(R_c, t_c)``, the
convention of ``common.geometry.error_state.retract``: a point ``x`` the correction maps to
``x'`` moves by ``w x (x' - c) + v`` with ``c = p + t_c`` the turn's centre after the shift.

The grasp's geometry (``grasp_constraint``): jaws that hold a wire hold it between their faces,
which close about the jaw frame's y (docs/dataset.md): the arc's point nearest the jaws' axis has
``x = 0`` in the jaw frame and the wire's tangent there no x part. Where along the jaws (y, z)
it lies the faces do not say (the wire crosses them anywhere within their length and width). A
pose of the needle in jaws that are off breaks that; the tracker weighs it once per grasp.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.needle import NeedleModel
from common.geometry.transforms import make_T, rotation_angle, skew


@dataclass
class ArmCorrection:
    """One arm's correction: the inner ``(R_c, t_c)`` as a 4x4 (``inner``), the turn's point ``p``
    (world, m), and the reported jaw pose the drift was last counted from (``last``)."""
    inner: np.ndarray
    p: np.ndarray
    last: np.ndarray

    @classmethod
    def at(cls, T_world_jaw: np.ndarray) -> "ArmCorrection":
        """No correction yet, turning about the jaws' reported position."""
        T = np.asarray(T_world_jaw, float)
        return cls(np.eye(4), T[:3, 3].copy(), T.copy())

    @property
    def K(self) -> np.ndarray:
        """The correction in world (4x4): ``T_world_jaw_corrected = K @ T_world_jaw_reported``."""
        R, t = self.inner[:3, :3], self.inner[:3, 3]
        return make_T(R, self.p + t - R @ self.p)

    @property
    def centre(self) -> np.ndarray:
        """Where the correction's turn is about, after its shift (world, m)."""
        return self.p + self.inner[:3, 3]

    def corrected(self, T_world_jaw: np.ndarray) -> np.ndarray:
        return self.K @ T_world_jaw


def lever(point: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """d(pose error at ``point``, world axes) / d(correction error about ``centre``): 6x6."""
    J = np.eye(6)
    J[3:, :3] = -skew(np.asarray(point, float) - centre)
    return J


def configuration_change(T_from: np.ndarray, T_to: np.ndarray, length_m: float, turn_rad: float) -> float:
    """How far the arm's configuration moved, in units of ``length_m`` of the jaws' travel plus
    ``turn_rad`` of their turn: what the configuration-dependent part of the error drifts over."""
    return float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3]) / length_m
                 + rotation_angle(T_from[:3, :3].T @ T_to[:3, :3]) / turn_rad)


def grasp_constraint(T_jaw_needle: np.ndarray, needle: NeedleModel, jaw_length_m: float, n_arc: int = 65):
    """The grasp's geometry (module docstring) at ``T_jaw_needle``: (residual (2,), H (2, 6)):
    what ``[x, tangent x]`` of the arc's point nearest the jaws' axis (pivot to ``jaw_length_m``
    along z) must be (0) less what they are, and their derivative by the pose's error ``[w, v]``
    in jaw axes."""
    R, t = T_jaw_needle[:3, :3], T_jaw_needle[:3, 3]
    a0, a1 = needle.arc_span_rad
    lo, hi = a0, a1
    for _ in range(2):                         # the nearest sample, then finer about it
        a = np.linspace(lo, hi, n_arc)
        p = needle.arc_points(a) @ R.T + t
        z = np.clip(p[:, 2], 0.0, jaw_length_m)
        i = int(np.argmin(p[:, 0] ** 2 + p[:, 1] ** 2 + (p[:, 2] - z) ** 2))
        step = a[1] - a[0]
        lo, hi = max(a[i] - step, a0), min(a[i] + step, a1)
    tangent = R @ np.array([-np.sin(a[i]), np.cos(a[i]), 0.0])
    H = np.zeros((2, 6))
    H[0, :3] = -skew(p[i] - t)[0]              # d p = w x (R q) + v
    H[0, 3] = 1.0
    H[1, :3] = -skew(tangent)[0]               # d tangent = w x tangent
    return -np.array([p[i, 0], tangent[0]]), H
