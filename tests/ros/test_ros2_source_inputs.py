"""The ``ros2`` source against what a ROS 2 peer may send (issue: the ROS samples as a way in):
malformed CDR, a type that does not fit the topic, a 20000x20000 PNG, a JointState of 10^6 names,
NaN calibration and poses. Each is refused where it is decoded, counted, logged at most once a
second per topic, and the good frames around it go through: the node's own path (its queue, then
``step``) on an offline node, samples made by ``common/robustness/fuzz_ros.py``."""
import logging
import random
import time

import numpy as np
import pytest

from common.robustness.fuzz_ros import RosSamples, _huge, fuzz_ros2, ros_poison
from common.ros import bag as rosbag_mod
from common.ros import roles as ros_roles
from common.ros.cdr import encode
from nodes.ros2 import Ros2Node

T0 = 1_700_000_000 * 10 ** 9


class Source:
    def __init__(self, keys="bridge"):
        self.s = RosSamples(keys)
        self.node = Ros2Node.offline(self.s.params(), node_id="camera")
        self.stamp = T0

    def put(self, topic, key, payload):
        self.node.queue.put((topic, key, payload, 0))
        assert self.node.step() is True                    # never raises, never stops

    def frame(self):
        self.stamp += 33_000_000
        for item in self.s.frame(self.stamp):
            self.put(*item)

    def pairs(self):
        return sum(o == "left" for o, _ in self.node.published)

    def close(self):
        self.node.teardown()


@pytest.fixture
def src():
    s = Source()
    yield s
    s.close()


@pytest.fixture
def zsrc():
    s = Source("rmw_zenoh")
    yield s
    s.close()


def test_a_flood_of_malformed_cdr_starves_no_good_frame(src, caplog):
    rng, np_rng = random.Random(1), np.random.default_rng(1)
    caplog.set_level(logging.ERROR)
    t0 = time.monotonic()
    for _ in range(20):
        for kind in ("random_bytes", "truncated", "trailing_garbage") * 10:   # 30 poison per good frame
            src.put(*ros_poison(src.s, kind, src.stamp, rng, np_rng))
        src.frame()
    assert src.pairs() >= 19                               # every frame but the one still pairing
    bad = src.node.counters["bad_samples"]
    assert bad >= 550
    assert src.node.counters.get("step_errors", 0) == 0
    seconds = time.monotonic() - t0
    refused = [r.getMessage().split(":")[1].strip() for r in caplog.records if "sample refused" in r.getMessage()]
    per_topic = {t: refused.count(t) for t in set(refused)}
    assert max(per_topic.values()) <= seconds + 1, (per_topic, seconds)   # at most once a second per topic
    assert sum(src.node.asm.refused.values()) == bad


def test_a_joint_state_typed_key_on_the_image_topic_is_refused(zsrc, caplog):
    caplog.set_level(logging.ERROR)
    zsrc.frame()
    st, b = zsrc.s.st, zsrc.s.build
    js = b.make(st, "sensor_msgs/msg/JointState", header=b.header(st, zsrc.stamp), name=["a"], position=np.zeros(1))
    topic = zsrc.s.topics["left"]
    zsrc.put(topic, zsrc.s.key(topic, js.__msgtype__), encode(js))
    assert zsrc.node.asm.refused[topic] == 1
    assert "is not an image" in caplog.text and "AttributeError" not in caplog.text
    zsrc.frame()
    zsrc.frame()
    assert zsrc.pairs() >= 2


def test_a_huge_compressed_image_is_refused_from_its_header_without_decoding(src, monkeypatch, caplog):
    import cv2

    def no_decode(*a, **k):
        raise AssertionError("cv2.imdecode ran on a refused image")
    monkeypatch.setattr(cv2, "imdecode", no_decode)
    caplog.set_level(logging.ERROR)
    src.frame()
    topic = src.s.topics["compressed"]
    for _ in range(3):
        src.put(topic, src.s.key(topic, "sensor_msgs/msg/CompressedImage"), _huge("huge_compressed_image", src.s))
    assert src.node.asm.refused[topic] == 3
    assert "20000x20000" in caplog.text
    src.frame()
    assert src.pairs() >= 1


def test_joint_arrays_and_history_are_bounded(src, caplog):
    caplog.set_level(logging.ERROR)
    topic = src.s.topics["joints"]
    key = src.s.key(topic, "sensor_msgs/msg/JointState")
    src.put(topic, key, _huge("huge_joint_state", src.s))           # 10^6 names: refused undecoded
    assert f"more than {rosbag_mod.MAX_STATE_BYTES}" in caplog.text
    st, b = src.s.st, src.s.build
    js = b.make(st, "sensor_msgs/msg/JointState", header=b.header(st, 5), name=["j"] * 100, position=np.zeros(100))
    import zenoh

    class Sample:                                                    # as the Zenoh session hands it over
        key_expr, payload = key, zenoh.ZBytes(_huge("huge_joint_state", src.s))
    src.node._callback(topic)(Sample)
    item = src.node.queue.get_nowait()
    assert item[2] == len(_huge("huge_joint_state", src.s))          # its size, not a copy of it
    src.node.queue.put(item)
    src.node.step()
    assert src.node.asm.refused[topic] == 2
    src.node.last_bad_log.clear()                                    # (the log is once a second per topic)
    src.put(topic, key, encode(js))                                  # small, but 100 joints
    assert f"joint arrays longer than {ros_roles.MAX_JOINTS}" in caplog.text
    assert src.node.asm.refused[topic] == 3
    for _ in range(rosbag_mod.HISTORY + 20):
        src.frame()
    hist = src.node.asm.hist["ecm_joints"]
    assert len(hist) == rosbag_mod.HISTORY
    assert all(isinstance(v, np.ndarray) and v.shape == (4,) for _, v in hist)    # what is kept: 4 floats


@pytest.mark.parametrize("kind", ["non_finite_calibration", "non_finite_pose"])
def test_non_finite_calibration_and_poses_are_refused_at_the_source(src, kind):
    from common.runtime.messages import decode as decode_msg
    from common.runtime.messages import encode as encode_msg
    rng, np_rng = random.Random(2), np.random.default_rng(2)
    src.frame()
    start = len(src.node.published)
    for _ in range(10):
        src.put(*ros_poison(src.s, kind, src.stamp, rng, np_rng))
        src.frame()
    assert src.node.counters["bad_samples"] == 10
    for out, m in src.node.published[start:]:
        decode_msg(encode_msg(m))                                  # the graph's codec accepts all
        if out == "calib":
            for c in ("left", "right"):
                assert np.all(np.isfinite(m.cameras[c]["K"])) and np.all(np.isfinite(m.cameras[c]["dist"]))
        if out == "measured":
            assert np.all(np.isfinite(m.T_world_ecm))
    assert src.pairs() >= 10


def test_padded_samples_as_ros_2_writes_them_are_accepted(src):
    rng, np_rng = random.Random(3), np.random.default_rng(3)
    for _ in range(10):
        src.put(*ros_poison(src.s, "padded", src.stamp, rng, np_rng))
    assert src.node.counters.get("bad_samples", 0) == 0


@pytest.mark.slow
@pytest.mark.parametrize("keys", ["bridge", "rmw_zenoh"])
def test_every_ros_poison_kind_on_both_key_forms(keys):
    """A small run of ``needletrack bench fuzz``'s ROS part: no crash, nothing invalid published,
    a stereo pair again after one clean frame."""
    from common.robustness.fuzz_ros import ROS_KINDS
    for i, kind in enumerate(ROS_KINDS):
        r = fuzz_ros2(keys, kind, 6, seed=i)
        assert r.crashes == 0, r.first_crash
        assert r.invalid_published == 0
        assert r.recovery_frames is not None and r.recovery_frames <= 2, (kind, r)
        assert r.refused == (0 if kind == "padded" else r.refused)
        if kind not in ("padded", "bit_flips"):
            assert r.refused == r.payloads, (kind, r)


def test_a_camera_info_or_pose_the_graphs_codec_would_refuse_is_refused_at_the_source(src):
    """Found by the fuzz (bit flips): a K that is not a pinhole matrix, or a position of 1e300,
    passed the source and made a Calibration / EcmPose every consumer refused."""
    st, b = src.s.st, src.s.build
    src.frame()
    K = src.s.rig.left.K.copy()
    K[2, 0] = 5.0
    t = src.s.topics["info_left"]
    src.put(t, src.s.key(t, "sensor_msgs/msg/CameraInfo"), encode(b.camera_info(st, src.stamp, K, [0] * 5, src.s.size)))
    T = np.eye(4)
    T[0, 3] = 1e300
    t = src.s.topics["pose"]
    src.put(t, src.s.key(t, "geometry_msgs/msg/PoseStamped"),
            encode(b.make(st, "geometry_msgs/msg/PoseStamped", header=b.header(st, src.stamp), pose=b.pose(st, T))))
    assert src.node.asm.refused == {src.s.topics["info_left"]: 1, t: 1}
    src.frame()
    from common.runtime.messages import decode as decode_msg
    from common.runtime.messages import encode as encode_msg
    for _, m in src.node.published:
        decode_msg(encode_msg(m))


def test_samples_on_another_distributions_keys_are_read_and_the_mismatch_said_once(zsrc, caplog):
    from common.ros.live import topic_key
    caplog.set_level(logging.WARNING)
    for _ in range(3):
        zsrc.stamp += 33_000_000
        for topic, msg in zsrc.s.messages(zsrc.stamp):        # a Humble publisher: no type hash
            zsrc.put(topic, topic_key(topic, msg.__msgtype__, "rmw_zenoh", distro="humble"), encode(msg))
    assert zsrc.pairs() >= 2 and zsrc.node.counters.get("bad_samples", 0) == 0
    warned = [r for r in caplog.records if "Humble type hash but distro is jazzy" in r.getMessage()]
    assert len(warned) == len(zsrc.s.messages(0))            # once per topic
