"""What a ROS message must be to serve its role in a topic map (image, camera_info, camera_state,
ecm_joints, ecm_pose, needle_pose, camera_frame, instrument_jaw): ``message_problem`` says why one
cannot, read from its fields without decoding pixels; ``pose_part`` and ``pose_of`` read the pose
inside any pose-carrying message (metres after ``scale``). Used by the bag and live ROS 2 sources
(``common/ros/bag.py``) and the instruments' poses; conventions in docs/ros.md.
"""
from __future__ import annotations

import numpy as np

from common.ros.conventions import pose_to_T
from common.ros.images import image_problem

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
MAX_JOINTS = 64              # a JointState with more names or values is refused (the ECM has 4)
DISTORTION_COUNTS = (0, 4, 5, 8, 12, 14)


class _TransformAsPose:
    """A geometry_msgs/Transform read as a Pose."""

    def __init__(self, t):
        self.position, self.orientation = t.translation, t.rotation


def pose_part(msg):
    """The Pose (or Transform, as a Pose) inside a PoseStamped, Pose, PoseWithCovariance(Stamped),
    TransformStamped, Transform or ambf RigidBodyState/CameraState message; ValueError if none."""
    m = msg
    for _ in range(3):
        if hasattr(m, "position") and hasattr(m, "orientation"):
            return m
        if hasattr(m, "translation") and hasattr(m, "rotation"):
            return _TransformAsPose(m)
        m = getattr(m, "pose", None) or getattr(m, "transform", None)
        if m is None:
            break
    raise ValueError(f"{getattr(msg, '__msgtype__', type(msg).__name__)} carries no pose")


def pose_of(msg, scale: float = 1.0) -> np.ndarray:
    """T of ``pose_part(msg)``; positions times ``scale``."""
    return pose_to_T(pose_part(msg), scale)


def message_problem(role: str, msg, values: bool = True) -> str | None:
    """Why a message cannot serve ``role`` (image, camera_info, camera_state, ecm_joints, ecm_pose,
    needle_pose, camera_frame), read from its fields without decoding pixels; None when it can.
    The wrong type, an image header over the size limit, an uncalibrated K, oversized joint
    arrays; with ``values``, also what the graph's codec would refuse: non-finite or
    out-of-range numbers, a K that is not a pinhole matrix."""
    msgtype = getattr(msg, "__msgtype__", type(msg).__name__)
    if role == "image":
        if msgtype not in IMAGE_TYPES:
            return f"a {msgtype} is not an image ({' or '.join(IMAGE_TYPES)})"
        return image_problem(msg)
    if role == "camera_info":
        if not hasattr(msg, "k") and not hasattr(msg, "K"):
            return f"a {msgtype} is not a sensor_msgs/msg/CameraInfo"
        K = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), float).reshape(-1)
        D = np.asarray(getattr(msg, "d", getattr(msg, "D", [])), float).reshape(-1)
        if K.size != 9:
            return f"K has {K.size} elements, not 9"
        if len(D) not in DISTORTION_COUNTS:
            return f"{len(D)} distortion coefficients (expected one of {', '.join(map(str, DISTORTION_COUNTS))})"
        model = str(getattr(msg, "distortion_model", "plumb_bob") or "plumb_bob")
        if model not in ("plumb_bob", "rational_polynomial") and np.any(D):
            return f"distortion_model {model!r} is not supported (plumb_bob, rational_polynomial)"
        if K[0] <= 0 or K[4] <= 0:           # (a NaN compares false: a value, below)
            return f"K is not a camera matrix (uncalibrated camera?): {K.reshape(3, 3).tolist()}"
        if not values:
            return None
        if not np.all(np.isfinite(K)) or not np.all(np.isfinite(D)):
            return f"K and D must be finite numbers, got K={K.tolist()} D={D.tolist()[:16]}"
        from common.runtime.messages import Calibration
        cam = {"K": K.reshape(3, 3), "dist": D if len(D) else np.zeros(5), "T_ecm_cam": np.eye(4)}
        size = np.array([max(1, int(msg.width)), max(1, int(msg.height))])
        return _codec_problem(Calibration(0, size, {"left": cam, "right": cam}, {"radius_m": 0.01}))
    if role == "instrument_jaw":
        if not hasattr(msg, "position"):
            return f"a {msgtype} is not a sensor_msgs/msg/JointState"
        pos = np.asarray(msg.position, float).reshape(-1)
        if len(pos) < 1 or len(pos) > MAX_JOINTS:
            return f"a jaw JointState needs 1 to {MAX_JOINTS} positions, got {len(pos)}"
        if values and not np.isfinite(pos[0]):
            return f"non-finite jaw angle {pos[0]}"
        return None
    if role == "ecm_joints":
        if not hasattr(msg, "position"):
            return f"a {msgtype} is not a sensor_msgs/msg/JointState"
        sizes = {f: len(getattr(msg, f, ())) for f in ("name", "position", "velocity", "effort")}
        if max(sizes.values()) > MAX_JOINTS:
            return f"joint arrays longer than {MAX_JOINTS}: {sizes}"
        if not values:
            return None
        pos = np.asarray(msg.position, float).reshape(-1)
        if not np.all(np.isfinite(pos[:4])):
            return f"non-finite joint positions {pos[:4].tolist()}"
        if len(pos) >= 4:
            from common.runtime.messages import EcmPose
            return _codec_problem(EcmPose(0, 0, np.eye(4), pos[:4].copy()))
        return None
    try:
        p = pose_part(msg)
        v = [p.position.x, p.position.y, p.position.z, p.orientation.x, p.orientation.y, p.orientation.z,
             p.orientation.w]
    except (ValueError, AttributeError):
        return f"a {msgtype} carries no pose"
    if not values:
        return None
    if not np.all(np.isfinite(np.asarray(v, float))):
        return f"non-finite pose (position, quaternion x y z w): {v}"
    from common.runtime.messages import EcmPose
    try:
        T = pose_to_T(p)
    except ValueError as exc:
        return str(exc)
    return _codec_problem(EcmPose(0, 0, T))


def _codec_problem(msg) -> str | None:
    """What the graph's codec refuses in ``msg`` (the one check of a calibration, pose or joint
    state: finite, in range, a pinhole K, rigid), or None."""
    from common.runtime.messages import MessageError, decode, encode
    try:
        decode(encode(msg), type(msg))
    except MessageError as exc:
        return str(exc)
    return None
