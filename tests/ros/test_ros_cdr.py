"""CDR as real ROS 2 writes it (common/ros/cdr.py): rmw_fastrtps sends the size its type support
estimates, which aligns empty sequences of 8-byte numbers; a JointState with positions only is
124 bytes where its CDR is 116. The padding is accepted exactly as far as a writer may leave it,
and nothing more."""
import numpy as np
import pytest
from rosbags.serde import SerdeError

from common.ros import build
from common.ros.cdr import CdrError, decode, encode, fastcdr_estimate
from common.ros.types import typestore

JS = "sensor_msgs/msg/JointState"


def joint_state(velocity=(), effort=()):
    st = typestore(2)
    return build.make(st, JS, header=build.header(st, 1_700_000_000_123_456_789, ""),
                      name=["yaw", "pitch", "insertion", "roll"], position=np.array([0.1, -0.2, 0.05, 0.3]),
                      velocity=np.asarray(velocity, float), effort=np.asarray(effort, float))


def as_fastrtps_sends(msg) -> bytes:
    """The bytes rmw_fastrtps publishes: the CDR, then the estimate's slack (never written: here
    filled with 0xAB to show it is not read)."""
    data = encode(msg)
    size = 4 + fastcdr_estimate(msg, msg.__msgtype__)
    assert size >= len(data)
    return data + b"\xab" * (size - len(data))


def test_positions_only_joint_state_is_124_bytes_as_rclpy_writes_it_and_decodes():
    msg = joint_state()
    data = as_fastrtps_sends(msg)
    assert (len(encode(msg)), len(data)) == (116, 124)
    with pytest.raises(SerdeError, match="size mismatch"):            # what rosbags alone says
        typestore(2).deserialize_cdr(data, JS)
    out = decode(data, JS)
    np.testing.assert_array_equal(out.position, msg.position)
    assert list(out.name) == list(msg.name) and len(out.velocity) == 0 and len(out.effort) == 0
    assert out.header.stamp.nanosec == 123_456_789


def test_more_than_the_writers_padding_is_refused():
    data = as_fastrtps_sends(joint_state())
    with pytest.raises(CdrError, match=r"12 bytes after the message's end .*pads to 124 at most"):
        decode(data + b"\0" * 4, JS)
    full = joint_state(velocity=np.zeros(4), effort=np.zeros(4))      # no empty sequence: no slack
    assert len(as_fastrtps_sends(full)) == len(encode(full))
    with pytest.raises(CdrError, match="bytes after the message's end"):
        decode(encode(full) + b"\0" * 4, JS)
    decode(encode(full) + b"\0" * 3, JS)                               # RTPS end padding to 4


def test_garbage_truncation_and_headers_name_the_problem():
    data = encode(joint_state())
    with pytest.raises(CdrError, match="truncated|not a CDR message"):
        decode(data[:40], JS)
    with pytest.raises(CdrError, match="encapsulation header is 0300"):
        decode(b"\x03\x00" + data[2:], JS)
    with pytest.raises(CdrError, match="not CDR"):
        decode(b"", JS)
    with pytest.raises(CdrError, match="unknown message type"):
        decode(data, "nope_msgs/msg/Nothing")
    rng = np.random.default_rng(0)
    for _ in range(200):                 # random bytes never escape as anything but CdrError
        raw = b"\x00\x01\x00\x00" + rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()
        try:
            decode(raw, JS)
        except CdrError:
            pass


def test_big_endian_and_ros1_decode_the_same_message():
    st = typestore(2)
    msg = joint_state()
    be = bytes(st.serialize_cdr(msg, JS, little_endian=False))
    assert be[:2] == b"\x00\x00"
    np.testing.assert_array_equal(decode(be, JS).position, msg.position)
    st1 = typestore(1)
    m1 = build.make(st1, JS, header=build.header(st1, 5, "x"), name=["a"], position=np.array([1.5]))
    raw = bytes(st1.serialize_ros1(m1, JS))
    assert decode(raw, JS, ros=1).position[0] == 1.5
    with pytest.raises(CdrError, match="bytes after the message's end"):
        decode(raw + b"\0", JS, ros=1)


@pytest.mark.parametrize("msgtype", ["geometry_msgs/msg/PoseStamped", "sensor_msgs/msg/CameraInfo",
                                     "geometry_msgs/msg/PoseWithCovarianceStamped"])
def test_estimate_equals_the_cdr_when_no_sequence_is_empty(msgtype):
    st = typestore(2)
    if msgtype.endswith("CameraInfo"):
        msg = build.camera_info(st, 3, np.diag([500.0, 500.0, 1.0]), [0.1, 0, 0, 0, 0], (640, 480), "left")
    else:
        msg = build.make(st, msgtype, header=build.header(st, 3, "ECM"))
    n = len(encode(msg)) - 4
    assert fastcdr_estimate(msg, msgtype) in range(n, n + 4)
