"""``ros2_out`` publishes the tracker's in-hand pose (``InHandPose``) as PoseWithCovarianceStamped in
the jaw frame of the instrument that holds the needle, over Zenoh on loopback."""
import json
import time

import numpy as np
import pytest
import zenoh
from graphtools import free_port

from common.geometry.transforms import make_T, pose_error, rotvec_to_R
from common.ros.cdr import decode
from common.ros.conventions import pose_to_T, ros_covariance
from common.ros.live import topic_key
from common.runtime.messages import InHandPose
from nodes.ros2_out import Ros2OutNode

T_JN = make_T(rotvec_to_R([0.2, -0.4, 1.1]), [0.001, -0.009, 0.0035])
COV = np.diag([1e-4, 2e-4, 3e-4, 1e-8, 4e-8, 9e-8])


@pytest.mark.parametrize("keys", ["bridge", "rmw_zenoh"])
def test_the_needle_in_the_jaws_goes_out_in_the_jaw_frame(keys):
    port = free_port()
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    ros = zenoh.open(c)
    got = []
    key = topic_key("/needletrack/needle_in_jaw", "geometry_msgs/msg/PoseWithCovarianceStamped", keys)
    sub = ros.declare_subscriber(key, lambda s: got.append(
        decode(s.payload.to_bytes(), "geometry_msgs/msg/PoseWithCovarianceStamped")))
    node = Ros2OutNode.offline(params={"connect": [f"tcp/127.0.0.1:{port}"], "keys": keys},
                               wired=["pose", "in_hand"])
    try:
        deadline = time.monotonic() + 30
        while not got and time.monotonic() < deadline:     # until the link is up
            node.on_in_hand(InHandPose("psm2", 7, 123_000_000_456, "psm2_jaw", T_JN, COV, 0.99))
            time.sleep(0.2)
        assert got, "no in-hand pose came"
        msg = got[0]
        assert msg.header.frame_id == "psm2_jaw"
        assert msg.header.stamp.sec == 123 and msg.header.stamp.nanosec == 456
        dt, dr = pose_error(pose_to_T(msg.pose.pose), T_JN)
        assert dt < 1e-9 and dr < 1e-9
        assert np.allclose(np.asarray(msg.pose.covariance).reshape(6, 6), ros_covariance(COV, np.eye(3), 1.0))
        assert node.counters["sent.in_hand"] >= 1
    finally:
        node.teardown()
        sub.undeclare()
        ros.close()


def test_a_relative_in_hand_topic_is_refused():
    from common.runtime.params import ParamError
    with pytest.raises(ParamError, match="in_hand_topic: must be an absolute ROS name"):     # by its params' check
        Ros2OutNode.offline(params={"in_hand_topic": "needle_in_jaw", "connect": ["tcp/127.0.0.1:1"]},
                            wired=["pose", "in_hand"])
