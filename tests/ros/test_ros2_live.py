"""Live ROS 2 over Zenoh without ROS: a test publisher writes CDR samples (camera_info, images,
ECM and needle poses) on bridge-style and rmw_zenoh-style keys; the ``ros2`` source feeds the
pipeline (oracle detector, EPnP) and ``ros2_out`` publishes the pose back, which a subscriber
here decodes with ``rosbags``: the pose in the ECM frame is exact."""
import json
import threading
import time

import numpy as np
import pytest
import zenoh
import zenoh.ext
from graphtools import free_port

from common.cli import dataset_main
from common.data.dataset import Dataset
from common.geometry.transforms import inv_T, pose_error
from common.ros import build
from common.ros.conventions import pose_to_T, ros_covariance
from common.ros.cdr import decode, encode, fastcdr_estimate
from common.ros.live import (
    attachment,
    dds_type_name,
    distro_of_key,
    entity_gid,
    liveliness_token,
    parse_attachment,
    topic_key,
    topic_of_key,
    type_hash,
)
from common.ros.types import typestore
from common.runtime.messages import EcmPose

pytestmark = pytest.mark.graph

RIG = "jhu_daVinci"


def test_keys_in_both_conventions():
    t = "geometry_msgs/msg/PoseStamped"
    assert topic_key("/ECM/measured_cp", t, "bridge") == "ECM/measured_cp"
    assert topic_key("/ECM/measured_cp", t, "bridge", namespace="robot1") == "robot1/ECM/measured_cp"
    key = topic_key("/ECM/measured_cp", t, "rmw_zenoh", domain_id=3)
    assert key == f"3/ECM/measured_cp/geometry_msgs::msg::dds_::PoseStamped_/{type_hash(t)}"
    assert type_hash(t).startswith("RIHS01_") and len(type_hash(t)) == 7 + 64
    assert topic_of_key(key, "rmw_zenoh") == ("/ECM/measured_cp", t)
    assert topic_key("/a/b", None, "rmw_zenoh", wildcard_type=True) == "0/a/b/*/*"
    tok = liveliness_token("MP", "ab12", "needletrack", topic="/needletrack/needle_pose", msgtype=t, entity_id=1)
    parts = tok.split("/")
    assert parts[:9] == ["@ros2_lv", "0", "ab12", "0", "1", "MP", "%", "%", "needletrack"]
    assert parts[9:12] == ["%needletrack%needle_pose", dds_type_name(t), type_hash(t)]


def test_humble_keys_and_tokens_carry_no_type_hash():
    t = "geometry_msgs/msg/PoseStamped"
    assert type_hash(t, "humble") == "TypeHashNotSupported"
    assert type_hash(t, "kilted") == type_hash(t, "rolling") == type_hash(t)
    key = topic_key("/needletrack/needle_pose", t, "rmw_zenoh", distro="humble")
    assert key == "0/needletrack/needle_pose/geometry_msgs::msg::dds_::PoseStamped_/TypeHashNotSupported"
    assert distro_of_key(key) == "humble" and distro_of_key(topic_key("/a", t, "rmw_zenoh")) == "jazzy"
    assert topic_of_key(key, "rmw_zenoh") == ("/needletrack/needle_pose", t)
    assert topic_key("/a/b", t, "bridge", distro="humble") == topic_key("/a/b", t, "bridge") == "a/b"
    tok = liveliness_token("MP", "ab12", "needletrack", topic="/needletrack/needle_pose", msgtype=t, entity_id=1,
                           distro="humble")
    assert tok == ("@ros2_lv/0/ab12/0/1/MP/%/%/needletrack/%needletrack%needle_pose/"
                   "geometry_msgs::msg::dds_::PoseStamped_/TypeHashNotSupported/::,10:,:,:,,")
    with pytest.raises(ValueError, match="distro must be one of humble, jazzy, kilted, rolling"):
        type_hash(t, "iron")


def test_attachment_is_zenoh_ext_serialisation_in_both_forms():
    gid = bytes(range(16))
    # rmw_zenoh >= 0.1.2 / 0.2.4 / 0.6: int64, int64, the GID as a sequence (attachment_helpers.cpp)
    ref = zenoh.ext.z_serialize((zenoh.ext.Int64(7), zenoh.ext.Int64(1234567890123), gid)).to_bytes()
    assert attachment(7, 1234567890123, gid) == ref
    assert len(ref) == 33 and ref[16] == 16 and ref[17:] == gid
    # rmw_zenoh 0.2.0-0.2.3 (and 0.1.0-0.1.1, 0.3-0.5): each value after its name
    ref = zenoh.ext.z_serialize(("sequence_number", zenoh.ext.Int64(7), "source_timestamp",
                                 zenoh.ext.Int64(1234567890123), "source_gid", gid)).to_bytes()
    assert attachment(7, 1234567890123, gid, "keyed") == ref and len(ref) == 77
    for form in ("positional", "keyed"):
        assert parse_attachment(attachment(7, 5, gid, form)) == {"form": form, "sequence_number": 7,
                                                                 "source_timestamp": 5, "source_gid": gid}
    for bad in (b"", b"\x00" * 32, attachment(7, 5, gid)[:-1], attachment(7, 5, gid, "keyed") + b"x"):
        with pytest.raises(ValueError, match="attachment"):
            parse_attachment(bad)


def test_gid_is_rmw_zenohs_xxh3_of_the_token():
    """Golden values from rmw_zenoh's own simplified_xxhash3.cpp (0.2.10), compiled: the GID is
    XXH3-128 of the entity's liveliness key, low 64 bits then high 64, little endian."""
    golden = {"": "7f498d4624c30160d8984701d306aa99",
              "@ros2_lv/0/aaaa/0/0/NN/%/%/needletrack": "ba118990bceebffd85029f5714070edc",
              "x" * 300: "5435c87d60b4d1a57abcd72aea375212"}
    for key, gid in golden.items():
        assert entity_gid(key).hex() == gid


def test_covariance_goes_out_in_ros_order_and_frame():
    cov = np.diag([1e-4, 2e-4, 3e-4, 1e-6, 4e-6, 9e-6])       # [rotvec, translation]
    out = ros_covariance(cov, np.eye(3), 1.0)
    assert np.allclose(np.diag(out), [1e-6, 4e-6, 9e-6, 1e-4, 2e-4, 3e-4])
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])         # 90 deg about z: x <-> y variances
    out = ros_covariance(cov, R, 0.1)                           # and decimetres
    assert np.allclose(np.diag(out), [4e-4, 1e-4, 9e-4, 2e-4, 1e-4, 3e-4])


@pytest.fixture(scope="module")
def small_ds(tmp_path_factory):
    path = tmp_path_factory.mktemp("live") / "ds"
    rc = dataset_main(["generate", "--out", str(path), "--sequences", "2", "--steps", "1", "--width", "320",
                       "--height", "240", "--seed", "8", "--randomise", "none", "--jobs", "1", "--quiet"])
    assert rc == 0
    return Dataset(path)


class RosSystem:
    """A stand-in ROS 2 system on its own Zenoh session: publishes a dVRK-like stream."""

    def __init__(self, port: int, keys: str, distro: str = "jazzy"):
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        self.session = zenoh.open(c)
        self.keys, self.distro = keys, distro
        self.seq = 0
        self.stop = threading.Event()

    def put(self, topic: str, msg, data: bytes = None) -> None:
        key = topic_key(topic, msg.__msgtype__, self.keys, distro=self.distro)
        data = encode(msg) if data is None else data
        self.seq += 1
        if self.keys == "rmw_zenoh":
            self.session.put(key, data, attachment=attachment(self.seq, time.time_ns(), bytes(16)))
        else:
            self.session.put(key, data)

    def publish_frame(self, ds, fr, stamp):
        st = typestore(2)
        for c in ("left", "right"):
            self.put(f"/{RIG}/{c}/camera_info", build.camera_info(st, stamp, ds.rig[c].K, ds.rig[c].dist,
                                                                  ds.meta.image_size))
        self.put("/ECM/measured_cp", build.make(st, "geometry_msgs/msg/PoseStamped",
                                                header=build.header(st, stamp), pose=build.pose(st, fr.T_world_ecm)))
        self.put("/needle/measured_cp", build.make(st, "geometry_msgs/msg/PoseStamped",
                                                   header=build.header(st, stamp),
                                                   pose=build.pose(st, fr.T_world_needle)))
        # positions only, as rclpy (rmw_fastrtps) writes it: 8 bytes of padding after the CDR
        js = build.make(st, "sensor_msgs/msg/JointState", header=build.header(st, stamp),
                        name=["yaw", "pitch", "insertion", "roll"], position=np.asarray(fr.ecm_joints, float))
        self.put("/ECM/measured_js", js, encode(js) + bytes(4 + fastcdr_estimate(js, js.__msgtype__) - len(encode(js))))
        for c in ("left", "right"):
            self.put(f"/{RIG}/{c}/image_raw", build.image(st, stamp, ds.image(fr, c), "bgr8"))

    def run(self, ds, hz: float = 4.0):
        i = 0
        while not self.stop.is_set():
            fr = ds[i % len(ds)]
            self.publish_frame(ds, fr, time.time_ns())
            i += 1
            self.stop.wait(1.0 / hz)

    def close(self):
        self.stop.set()
        self.session.close()


@pytest.mark.parametrize("keys,distro", [("bridge", "jazzy"), ("rmw_zenoh", "jazzy"), ("rmw_zenoh", "humble")])
def test_live_ros2_in_and_pose_out(run_graph, small_ds, keys, distro):
    port = free_port()
    ros = RosSystem(port, keys, distro)
    received = []
    attachments = []
    pose_key = topic_key("/needletrack/needle_pose", "geometry_msgs/msg/PoseStamped", keys, distro=distro)

    def on_pose(sample):
        received.append(decode(sample.payload.to_bytes(), "geometry_msgs/msg/PoseStamped"))
        if sample.attachment is not None:
            attachments.append(sample.attachment.to_bytes())
    sub = ros.session.declare_subscriber(pose_key, on_pose)
    ds = small_ds
    tmap = {"preset": "dvrk", "needle_pose": "/needle/measured_cp",
            "registration": {c: ds.rig[c].T_ecm_cam.tolist() for c in ("left", "right")}}
    link = {"connect": [f"tcp/127.0.0.1:{port}"], "keys": keys, "distro": distro}
    stereo = {"left": "detector/left", "right": "detector/right", "calib": "camera/calib", "ecm": "ecm/pose"}
    thread = threading.Thread(target=ros.run, args=(ds,), daemon=True)
    try:
        g = run_graph({"nodes": [
            {"id": "camera", "module": "ros2", "outputs": ["left", "right", "measured", "truth", "calib"],
             "params": {"preset": "dvrk", "rig": RIG, "topics": tmap, **link}},
            {"id": "detector", "module": "detector", "params": {"backend": "oracle"},
             "inputs": {"left": "camera/left", "right": "camera/right", "truth": "camera/truth",
                        "calib": "camera/calib"}, "outputs": ["left", "right"]},
            {"id": "ecm", "module": "ecm", "inputs": {"measured": "camera/measured", "calib": "camera/calib"},
             "outputs": ["pose"]},
            {"id": "epnp_joint", "module": "epnp", "params": {"method": "joint"}, "inputs": stereo,
             "outputs": ["pose"]},
            {"id": "out", "module": "ros2_out", "inputs": {"pose": "epnp_joint/pose", "calib": "camera/calib"},
             "params": {**link, "frame": "ecm"}},
        ]}, timeout=90)
        measured = g.subscribe("camera/measured", EcmPose)
        thread.start()
        deadline = time.monotonic() + 120
        while len(received) < 4 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(received) >= 4, f"{len(received)} poses came back"
        truths = {}
        for fr in ds:
            T_en = inv_T(fr.T_world_ecm) @ fr.T_world_needle
            truths[round(fr.T_world_needle[0, 3], 9)] = T_en
        for msg in received:
            assert msg.header.frame_id == "ECM"
            T = pose_to_T(msg.pose)
            err = min(pose_error(T, T_true) for T_true in truths.values())
            assert err[0] < 1e-6 and err[1] < 1e-5
        # the padded JointState decoded: its joints travel with the measured ECM pose
        joints = {tuple(np.round(fr.ecm_joints, 12)) for fr in ds}
        got = measured.wait(1, timeout=30, where=lambda m: m.q is not None)
        assert all(tuple(np.round(m.q, 12)) in joints for m in got if m.q is not None)
        assert g.stats("camera").counters.get("bad_samples", 0) == 0
        if keys == "rmw_zenoh":
            tokens = [str(r.ok.key_expr) for r in ros.session.liveliness().get("@ros2_lv/0/**", timeout=5.0)
                      if r.ok is not None]
            assert any("/NN/%/%/needletrack" in t for t in tokens), tokens
            hash_form = "TypeHashNotSupported/" if distro == "humble" else "RIHS01_"
            mp = [t for t in tokens if "/MP/%/%/needletrack/%needletrack%needle_pose/"
                  f"geometry_msgs::msg::dds_::PoseStamped_/{hash_form}" in t]
            assert len(mp) == 1, tokens
            a = parse_attachment(attachments[-1])              # rmw_zenoh's current, positional form
            assert len(attachments[-1]) == 33 and a["form"] == "positional"
            assert a["sequence_number"] >= 1 and a["source_gid"] == entity_gid(mp[0])
    finally:
        ros.stop.set()
        thread.join(timeout=5)
        sub.undeclare()
        ros.close()
