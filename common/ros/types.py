"""ROS message types without a ROS installation (the ``rosbags`` typestores).

``typestore(ros=1|2)`` is the standard store of ROS 1 Noetic or ROS 2 Humble with the
``ambf_msgs`` types the AMBF simulator (and the 2021-22 AccelNet Surgical Robotics Challenge)
publishes added from ``.msg`` text. ``ambf_msgs`` is not a standard package: the definitions below
are the fields of ``ambf_msgs/RigidBodyState`` and ``ambf_msgs/CameraState`` as the AMBF
repository defines them (ROS 1 and its ROS 2 port have the same fields).
"""
from __future__ import annotations

from functools import lru_cache

AMBF_MSGS = {
    "ambf_msgs/msg/RigidBodyState": """\
std_msgs/Header header
uint32 sim_step
std_msgs/String identifier
std_msgs/String name
float32 wall_time
float32 sim_time
float32 mass
geometry_msgs/Point p_inertia
geometry_msgs/Pose pose
geometry_msgs/Twist twist
geometry_msgs/Wrench wrench
string[] children_names
string[] joint_names
float32[] joint_positions
float32[] joint_velocities
float32[] joint_efforts
""",
    "ambf_msgs/msg/CameraState": """\
std_msgs/Header header
uint32 sim_step
std_msgs/String parent_name
std_msgs/String identifier
std_msgs/String name
float32 wall_time
float32 sim_time
geometry_msgs/Pose pose
""",
}

KEYPOINTS_MSG = ("needletrack_msgs/msg/Keypoints", """\
# The five needle keypoints A (tip) .. E (tail) in one camera's image (docs/ros.md).
# u, v: pixels, (0, 0) the centre of the top-left pixel; NaN where not found.
# score: the detector's confidence in [0, 1] per keypoint.
std_msgs/Header header
string camera
float64[5] u
float64[5] v
float64[5] score
""")


@lru_cache(maxsize=None)
def typestore(ros: int = 2):
    """The rosbags typestore of ROS ``ros`` (1: Noetic, 2: Humble) with ambf_msgs and the
    project's keypoint message registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    add = {}
    for name, text in AMBF_MSGS.items():
        add.update(get_types_from_msg(text, name))
    add.update(get_types_from_msg(KEYPOINTS_MSG[1], KEYPOINTS_MSG[0]))
    store.register(add)
    return store


def normalise_type(name: str) -> str:
    """``sensor_msgs/Image`` or ``sensor_msgs/msg/Image`` -> ``sensor_msgs/msg/Image``."""
    parts = name.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return name
