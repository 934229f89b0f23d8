"""Keypoint observations for the pose solvers, and the error they raise when no pose exists.

A solver never guesses: input that cannot give a pose (too few usable points, NaN, collinear or
coincident image points, a needle behind the cameras, a solver that fails) raises ``NoPose``
whose ``reason`` is a short name a node counts as ``no_pose.<reason>``.

Usable keypoints are those with finite pixels and a score >= ``min_score``. Pixels are
undistorted to ideal pinhole pixels (same K) before any geometry, so the solvers work with
``u = K[0,0] x/z + K[0,1] y/z + K[0,2]``, ``v = K[1,1] y/z + K[1,2]`` in each camera.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.geometry.camera import Camera, StereoRig
from common.geometry.camera import undistort_pixels as _undistort

REASONS = ("too_few_points", "non_finite", "coincident", "collinear", "behind_camera",
           "solver_failed", "high_residual", "unsure_keypoints")


class NoPose(NeedletrackError, ValueError):
    """No pose can be computed from this input. ``reason`` is one of ``REASONS``."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"no pose ({reason}){': ' + detail if detail else ''}")
        self.reason = reason
        self.detail = detail


@dataclass
class CameraObs:
    """The usable keypoints of one camera: ``uv`` (n, 2) ideal pixels of model ``points``
    (n, 3, needle frame, m), fit ``weights`` (n,), and ``index`` (n,) into A..E."""

    camera: Camera
    uv: np.ndarray
    points: np.ndarray
    weights: np.ndarray
    index: np.ndarray

    @property
    def n(self) -> int:
        return len(self.index)


def usable_mask(uv, scores=None, min_score: float = 0.5) -> np.ndarray:
    """(N,) bool: keypoints with finite pixels and a finite score >= ``min_score``."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    ok = np.all(np.isfinite(uv), axis=1)
    if scores is not None:
        s = np.asarray(scores, dtype=float).reshape(-1)
        if s.shape != (len(uv),):
            raise ValueError(f"scores: expected shape ({len(uv)},), got {s.shape}")
        ok &= np.isfinite(s) & (s >= min_score)
    return ok


def undistort_pixels(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """(N, 2) observed pixels -> ideal pinhole pixels with the same K (no-op without distortion)."""
    return _undistort(camera.K, camera.dist, uv)


def check_spread(uv: np.ndarray, where: str = "", min_spread_px: float = 1.0,
                 collinear_ratio: float = 1e-3) -> None:
    """Raise NoPose when image points are (nearly) coincident or collinear.

    Uses the singular values of the centred points: the RMS spread along the main direction must
    reach ``min_spread_px`` and the across spread must exceed ``collinear_ratio`` of it.
    """
    c = uv - uv.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False) / np.sqrt(len(uv))
    if s[0] < min_spread_px:
        raise NoPose("coincident", f"{where} keypoints span {s[0]:.3g} px")
    if len(s) < 2 or s[1] < collinear_ratio * s[0]:
        raise NoPose("collinear", f"{where} keypoints lie on a line")


def camera_observation(camera: Camera, uv, model_points, scores=None,
                       min_score: float = 0.5) -> CameraObs:
    """The usable keypoints of one camera as a ``CameraObs`` (possibly with n = 0).

    Weights are the scores (1 when no scores are given).
    """
    uv = np.asarray(uv, dtype=float)
    model_points = np.asarray(model_points, dtype=float)
    if uv.shape != model_points[:, :2].shape:
        raise ValueError(f"{camera.name} keypoints: expected shape {model_points[:, :2].shape}, "
                         f"got {uv.shape}")
    mask = usable_mask(uv, scores, min_score)
    idx = np.flatnonzero(mask)
    w = np.ones(len(idx)) if scores is None else np.asarray(scores, dtype=float)[idx]
    return CameraObs(camera, undistort_pixels(camera, uv[idx]), model_points[idx], w, idx)


def stereo_observations(uv: dict, rig: StereoRig, model_points, scores: dict | None = None,
                        min_score: float = 0.5) -> dict[str, CameraObs]:
    """``{camera: CameraObs}`` for the cameras in ``uv`` (a camera may be absent or None)."""
    out = {}
    for name in CAMERAS:
        if uv.get(name) is None:
            continue
        s = None if scores is None else scores.get(name)
        out[name] = camera_observation(rig[name], uv[name], model_points, s, min_score)
    return out


def curve_normals(pts: np.ndarray) -> np.ndarray:
    """(N, 2) unit normals of a polyline (tangent turned +90 deg in image coordinates)."""
    tang = np.gradient(np.asarray(pts, float), axis=0)
    tang /= np.maximum(np.linalg.norm(tang, axis=1, keepdims=True), 1e-9)
    return np.stack([-tang[:, 1], tang[:, 0]], axis=1)
