"""Pinhole cameras and the stereo endoscope rig (OpenCV conventions).

Camera frame: x right, y down, z forward. Pixel (0, 0) is the centre of the top-left pixel.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.frames import CAMERAS
from common.geometry.transforms import inv_T, transform_points


def intrinsics_from_fovy(width: int, height: int, fovy_rad: float) -> np.ndarray:
    """3x3 K of an ideal pinhole with square pixels and a vertical field of view (rad).

    The principal point is the image centre: ((w - 1) / 2, (h - 1) / 2) with pixel centres at
    integers, which is what an OpenGL renderer such as MuJoCo produces.
    """
    f = (height / 2.0) / np.tan(fovy_rad / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


UNDISTORT_CRITERIA = (3, 50, 1e-12)   # cv2.TERM_CRITERIA_COUNT | EPS, iterations, eps


def undistort_pixels(K: np.ndarray, dist: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 2) observed (distorted) pixels -> ideal pinhole pixels with the same K.

    Iterates OpenCV's fixed point to convergence (50 iterations, 1e-12) instead of its default
    5, which leaves ~0.1 px at the corners of a strongly distorted (k1 = -0.35) 1080p image."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if not np.any(dist) or len(uv) == 0:
        return uv.copy()
    import cv2
    out = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, np.asarray(dist, float), None, None, K,
                              UNDISTORT_CRITERIA)
    return out.reshape(-1, 2)


@dataclass
class Camera:
    """One camera: intrinsics K (3x3), OpenCV distortion, and its pose ``T_ecm_cam``."""

    name: str
    K: np.ndarray
    dist: np.ndarray
    T_ecm_cam: np.ndarray
    width: int
    height: int

    @property
    def T_cam_ecm(self) -> np.ndarray:
        return inv_T(self.T_ecm_cam)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Project (N, 3) camera-frame points to (N, 2) pixels (distortion applied if any)."""
        p = np.asarray(p_cam, dtype=float).reshape(-1, 3)
        if np.any(self.dist):
            import cv2
            uv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), self.K, self.dist)
            return uv.reshape(-1, 2)
        x = p[:, :2] / p[:, 2:3]
        return x @ self.K[:2, :2].T + self.K[:2, 2]

    def project_from_ecm(self, p_ecm: np.ndarray) -> np.ndarray:
        """Project (N, 3) ECM-frame points to (N, 2) pixels."""
        return self.project(transform_points(self.T_cam_ecm, p_ecm))

    @property
    def P_ecm(self) -> np.ndarray:
        """3x4 projection matrix from the ECM frame (undistorted pixels)."""
        return self.K @ self.T_cam_ecm[:3, :]

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """Boolean mask of pixels inside the image."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return ((uv[:, 0] >= -0.5) & (uv[:, 0] <= self.width - 0.5)
                & (uv[:, 1] >= -0.5) & (uv[:, 1] <= self.height - 0.5))

    def to_dict(self) -> dict:
        return {"K": self.K.tolist(), "dist": list(map(float, self.dist)),
                "T_ecm_cam": self.T_ecm_cam.tolist()}


@dataclass
class StereoRig:
    """The stereo endoscope: left and right cameras, both posed in the ECM frame."""

    left: Camera
    right: Camera

    def __getitem__(self, name: str) -> Camera:
        if name not in CAMERAS:
            raise KeyError(f"camera must be 'left' or 'right', got {name!r}")
        return getattr(self, name)

    @property
    def cameras(self) -> tuple[Camera, Camera]:
        return self.left, self.right

    def sees(self, p_ecm: np.ndarray, margin: float = 0.0, min_depth_m: float = 0.01) -> bool:
        """All (N, 3) ECM-frame points at least ``min_depth_m`` in front of both cameras and
        inside both images shrunk by ``margin`` (a fraction of the image size) on every side."""
        for cam in self.cameras:
            p = transform_points(cam.T_cam_ecm, p_ecm)
            if np.any(p[:, 2] <= min_depth_m):
                return False
            uv = cam.project(p)
            mx, my = margin * cam.width, margin * cam.height
            if np.any(uv[:, 0] < mx) or np.any(uv[:, 0] > cam.width - 1 - mx) or \
                    np.any(uv[:, 1] < my) or np.any(uv[:, 1] > cam.height - 1 - my):
                return False
        return True

    @classmethod
    def default(cls, width: int = 1920, height: int = 1080, fovy_rad: float = 1.2,
                baseline_m: float = 0.004) -> "StereoRig":
        """The built-in endoscope: two parallel cameras ``baseline_m`` apart along ECM x.

        The ECM arm's insertion axis points along -z of the ECM frame (see ecm_kinematics), so
        the cameras look along -z_ecm: camera x = ecm x, y = -ecm y, z = -ecm z, and the
        left camera sits at x = -baseline/2, the right one at +baseline/2.
        """
        K = intrinsics_from_fovy(width, height, fovy_rad)
        cams = []
        for name, sx in (("left", -0.5), ("right", 0.5)):
            T = np.diag([1.0, -1.0, -1.0, 1.0])
            T[0, 3] = sx * baseline_m
            cams.append(Camera(name, K.copy(), np.zeros(5), T, width, height))
        return cls(*cams)

    @classmethod
    def from_dict(cls, cameras: dict, image_size) -> "StereoRig":
        """From the dataset.yaml ``cameras`` mapping and ``image_size`` [w, h]."""
        w, h = int(image_size[0]), int(image_size[1])
        cams = []
        for name in CAMERAS:
            c = cameras[name]
            cams.append(Camera(name, np.asarray(c["K"], dtype=float),
                               np.asarray(c.get("dist", [0] * 5), dtype=float),
                               np.asarray(c["T_ecm_cam"], dtype=float), w, h))
        return cls(*cams)

    def to_dict(self) -> dict:
        return {"left": self.left.to_dict(), "right": self.right.to_dict()}
