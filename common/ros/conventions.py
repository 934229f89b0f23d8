"""Frames, fixed transforms and units of the ROS sources (docs/ros.md states them all).

Poses are 4x4 ``T_a_b`` (frame b -> frame a) in metres everywhere in the project; these helpers
turn ROS poses (``geometry_msgs/Pose`` quaternion x, y, z, w) into them and back.

AMBF (the AccelNet Surgical Robotics Challenge simulator):

- camera axes: an AMBF camera looks along its -x with y right and z up. The challenge's
  ``docs/camera_conventions.md`` converts with ``F = [[0,1,0],[0,0,-1],[-1,0,0]]``,
  ``p_cv = F p_ambf``, so ``T_x_cv = T_x_ambfcam @ F^-1`` (``F_AMBF_CAM`` below, 4x4).
- needle body: the challenge's scripts put the needle's points at radius 0.1018 (decimetres; 10.18 mm) on
  its arc at angles 60 .. 180 deg from +x towards +y in the needle body frame; its evaluation code
  puts the tip at (0.056, 0.085, 0) (56.6 deg, i.e. the 60-deg end) and the base, where the
  thread is, at (-0.102, 0, 0) (180 deg). The dataset needle frame (docs/dataset.md) has the tip
  at 30 deg and the tail at 150 deg with the arc's middle on +y: the same arc turned by -30 deg
  about z, same origin and normal. So ``T_ambfneedle_needle = RotZ(+30 deg)``
  (``T_AMBF_NEEDLE``) and ``T_world_needle = T_world_ambfneedle @ T_AMBF_NEEDLE``.
- units: the 2021-22 challenge worked in decimetres (scene scaled by 10: stereo baseline 0.04,
  needle radius 0.1018); AMBF 2.0 (July 2024) and later are SI (baseline 0.004, radius 0.01018).
  ``infer_ambf_unit`` decides from the baseline. The constants below are in metres (or unitless),
  whatever the scene's unit: only positions read from its topics are scaled.
"""
from __future__ import annotations

import math

import numpy as np

from common.geometry.transforms import R_to_quat, inv_T, make_T, quat_to_R

# p_cv = F p_ambf: OpenCV camera (x right, y down, z forward) from the AMBF camera (-x forward,
# y right, z up).
F_AMBF_CAM = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
# T_ambfcam_cv: maps OpenCV camera coordinates into the AMBF camera frame.
T_AMBFCAM_CV = inv_T(F_AMBF_CAM)
# T_ambfneedle_needle: the dataset needle frame in AMBF's needle body frame (RotZ(+30 deg)).
_c, _s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
T_AMBF_NEEDLE = np.array([[_c, -_s, 0.0, 0.0], [_s, _c, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
AMBF_NEEDLE_RADIUS_M = 0.01018       # the challenge's needle: 10.18 mm (0.1018 in the 2021-22 scene's dm)
AMBF_FOVY_RAD = 1.2                  # the challenge's cameras' vertical field of view
AMBF_BASELINE_M = 0.004              # its stereo baseline (0.04 in decimetres)

UNITS = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001}


def unit_scale(unit: str) -> float:
    """Metres per unit of ``unit`` (m, dm, cm, mm)."""
    if unit not in UNITS:
        raise ValueError(f"unit must be one of {', '.join(UNITS)} (or auto), got {unit!r}")
    return UNITS[unit]


def infer_ambf_unit(baseline: float) -> str:
    """``dm`` when the AMBF stereo baseline reads ~0.04 (the 2021-22 challenge), ``m`` when
    ~0.004 (SI versions); else ValueError asking for the unit."""
    if 0.02 <= baseline <= 0.08:
        return "dm"
    if 0.002 <= baseline <= 0.008:
        return "m"
    raise ValueError(f"cannot infer the AMBF unit from a stereo baseline of {baseline:.6g} "
                     f"(0.04 = decimetres, 0.004 = metres); set unit: m|dm|cm|mm")


def pose_to_T(pose, scale: float = 1.0) -> np.ndarray:
    """A ``geometry_msgs/Pose`` (position, orientation x y z w) -> 4x4, position times ``scale``."""
    q = pose.orientation
    quat = np.array([q.w, q.x, q.y, q.z], dtype=float)
    n = np.linalg.norm(quat)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"pose orientation is not a quaternion: {quat.tolist()} (w, x, y, z)")
    p = pose.position
    return make_T(quat_to_R(quat / n), scale * np.array([p.x, p.y, p.z], dtype=float))


def T_to_pose_fields(T: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """4x4 -> (position (3,) divided by ``scale``, quaternion (4,) as x, y, z, w)."""
    w, x, y, z = R_to_quat(T[:3, :3])
    return np.asarray(T[:3, 3], float) / scale, np.array([x, y, z, w])


def stamp_ns(header) -> int:
    """A ``std_msgs/Header`` stamp (ROS 1 secs/nsecs or ROS 2 sec/nanosec) in nanoseconds."""
    s = header.stamp
    sec = getattr(s, "sec", None)
    if sec is None:
        sec = getattr(s, "secs", 0)
    nsec = getattr(s, "nanosec", None)
    if nsec is None:
        nsec = getattr(s, "nsecs", 0)
    return int(sec) * 1_000_000_000 + int(nsec)


def ros_covariance(cov_rt: np.ndarray, R_frame_ecm: np.ndarray, scale: float) -> np.ndarray:
    """(6, 6) over [rotvec, translation] in the ECM frame -> ROS's (x, y, z, rx, ry, rz) in the
    header frame, positions divided by ``scale`` (metres per unit)."""
    from common.geometry.fusion import covariance_to_frame
    c = covariance_to_frame(np.asarray(cov_rt, float), R_frame_ecm)
    P = np.zeros((6, 6))
    P[0:3, 3:6] = np.eye(3) / scale      # translation first
    P[3:6, 0:3] = np.eye(3)
    return P @ c @ P.T
