"""Forward kinematics of the da Vinci endoscope arm (ECM), as the dataset spec defines it.

``T_world_ecm = T_world_base @ F(q)``, ``q = [yaw, pitch, insertion, roll]`` (rad, rad, m, rad);
F chains five modified-DH links, each ``RotX(alpha) @ TransX(a) @ RotZ(theta) @ TransZ(d)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# The paper's multi-view protocol: between views one revolute joint (yaw, pitch or roll) steps
MULTIVIEW_STEP_RAD = 0.05
REVOLUTE_JOINTS = (0, 1, 3)


def mdh_link(alpha: float, a: float, theta: float, d: float) -> np.ndarray:
    """One modified Denavit-Hartenberg link transform."""
    ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta)
    return np.array([
        [ct, -st, 0.0, a],
        [st * ca, ct * ca, -sa, -d * sa],
        [st * sa, ct * sa, ca, d * ca],
        [0.0, 0.0, 0.0, 1.0],
    ])


def ecm_forward(q, L_rcc: float = 0.0, L_scopelen: float = 0.0) -> np.ndarray:
    """``T_base_ecm`` for joints q = [yaw, pitch, insertion, roll] (rad, rad, m, rad)."""
    q = np.asarray(q, dtype=float).reshape(-1)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise ValueError(f"ecm joints: need 4 finite values, got {q.tolist()}")
    links = (
        (np.pi / 2, 0.0, q[0] + np.pi / 2, 0.0),
        (-np.pi / 2, 0.0, q[1] - np.pi / 2, 0.0),
        (np.pi / 2, 0.0, 0.0, q[2] - L_rcc),
        (0.0, 0.0, q[3], L_scopelen),
        (np.pi, 0.0, np.pi / 2, 0.0),
    )
    T = np.eye(4)
    for link in links:
        T = T @ mdh_link(*link)
    return T


@dataclass
class EcmArm:
    """The endoscope arm: base pose in world and its two lengths (m)."""

    T_world_base: np.ndarray = field(default_factory=lambda: np.eye(4))
    L_rcc: float = 0.0
    L_scopelen: float = 0.0

    @classmethod
    def from_dict(cls, d: dict) -> "EcmArm":
        """From the dataset.yaml ``ecm`` mapping (or a node's params)."""
        return cls(np.asarray(d.get("T_world_base", np.eye(4)), dtype=float),
                   float(d.get("L_rcc", 0.0)), float(d.get("L_scopelen", 0.0)))

    @classmethod
    def from_calibration(cls, ecm: dict | None) -> "EcmArm | None":
        """From a Calibration's optional ``ecm`` mapping; None when the source has no arm."""
        return None if ecm is None else cls.from_dict(ecm)

    def to_dict(self) -> dict:
        return {"T_world_base": np.asarray(self.T_world_base).tolist(),
                "L_rcc": self.L_rcc, "L_scopelen": self.L_scopelen}

    def T_world_ecm(self, q) -> np.ndarray:
        return self.T_world_base @ ecm_forward(q, self.L_rcc, self.L_scopelen)
