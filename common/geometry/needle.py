"""The needle model: a circular arc in the needle frame's x-y plane.

Needle frame (dataset spec): origin at the arc's centre, arc in the x-y plane, z its normal.
Keypoints A (tip) .. E (tail) sit at ``radius_m * [cos a_k, sin a_k, 0]``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KEYPOINT_NAMES = ("A", "B", "C", "D", "E")


@dataclass(frozen=True)
class NeedleModel:
    """Needle geometry: arc radius (m) and the keypoint angles (deg) from +x towards +y."""

    radius_m: float = 0.01018
    keypoint_angles_deg: tuple = (30.0, 60.0, 90.0, 120.0, 150.0)
    wire_diameter_m: float = 0.0008

    def __post_init__(self):
        angles = tuple(float(a) for a in self.keypoint_angles_deg)
        if len(angles) != 5:
            raise ValueError(f"needle: keypoint_angles_deg needs 5 angles, got {len(angles)}")
        if not (np.isfinite(self.radius_m) and self.radius_m > 0):
            raise ValueError(f"needle: radius_m must be positive, got {self.radius_m}")
        object.__setattr__(self, "keypoint_angles_deg", angles)

    @classmethod
    def from_dict(cls, d: dict) -> "NeedleModel":
        """From the dataset.yaml ``needle`` mapping (or a graph's needle params)."""
        return cls(radius_m=float(d.get("radius_m", cls.radius_m)),
                   keypoint_angles_deg=tuple(d.get("keypoint_angles_deg", cls.keypoint_angles_deg)),
                   wire_diameter_m=float(d.get("wire_diameter_m", cls.wire_diameter_m)))

    def to_dict(self) -> dict:
        return {"radius_m": self.radius_m, "keypoint_angles_deg": list(self.keypoint_angles_deg)}

    @property
    def keypoint_angles_rad(self) -> np.ndarray:
        return np.deg2rad(np.asarray(self.keypoint_angles_deg))

    @property
    def arc_span_rad(self) -> tuple[float, float]:
        """(start, end) angle of the arc: the tip A to the tail E."""
        a = self.keypoint_angles_rad
        return float(a[0]), float(a[-1])

    def keypoints(self) -> np.ndarray:
        """(5, 3) keypoints A..E in the needle frame (m)."""
        return self.arc_points(self.keypoint_angles_rad)

    def arc_points(self, angles_rad) -> np.ndarray:
        """(N, 3) points on the needle's circle at the given angles (rad), needle frame."""
        a = np.asarray(angles_rad, dtype=float)
        return self.radius_m * np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=-1)

    def sample_arc(self, n: int = 64) -> np.ndarray:
        """(n, 3) points evenly spaced along the arc from A to E, needle frame."""
        a0, a1 = self.arc_span_rad
        return self.arc_points(np.linspace(a0, a1, n))
