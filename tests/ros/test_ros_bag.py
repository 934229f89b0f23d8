"""ROS bags in, dataset folders out (common/ros): bags written here with ``rosbags`` from the
project's own renders in the AMBF (ROS 1, ambf_msgs, decimetres, 640x480) and dVRK (ROS 2 MCAP,
1920x1080, camera_info with distortion) conventions, converted back and evaluated: the oracle
geometry is exact at 0 px, so the conventions (axes, needle frame, units, distortion) are right."""
import json
from collections import deque

import numpy as np
import pytest

from common.cli import dataset_main
from common.data.check import check_dataset
from common.data.dataset import Dataset
from common.evaluation.cli import main as eval_main
from common.ros.bag import BagError, BagStereo
from common.ros.conventions import AMBF_NEEDLE_RADIUS_M, T_AMBF_NEEDLE
from common.ros.convert import from_bag
from common.ros.synth import dataset_to_bag, distort_dataset

DIST = [-0.12, 0.05, 0.0005, -0.0004, 0.0]


def _generate(path, w, h, sequences, steps, seed):
    rc = dataset_main(["generate", "--out", str(path), "--sequences", str(sequences), "--steps", str(steps),
                       "--width", str(w), "--height", str(h), "--seed", str(seed), "--randomise", "none",
                       "--jobs", "1", "--quiet", "--format", "png"])
    assert rc == 0
    return path


@pytest.fixture(scope="module")
def ds640(tmp_path_factory):
    return _generate(tmp_path_factory.mktemp("ros") / "ds640", 640, 480, 2, 2, 3)


@pytest.fixture(scope="module")
def ds1080_distorted(tmp_path_factory):
    root = tmp_path_factory.mktemp("ros1080")
    src = _generate(root / "pinhole", 1920, 1080, 1, 2, 5)
    distort_dataset(str(src), str(root / "distorted"), DIST)
    return root / "distorted"


def assert_same_truth(a: Dataset, b: Dataset, px=1e-6):
    assert len(a) == len(b)
    for fa, fb in zip(a, b):
        assert np.abs(fa.T_world_ecm - fb.T_world_ecm).max() < 1e-9
        assert np.abs(fa.T_world_needle - fb.T_world_needle).max() < 1e-9
        for c in ("left", "right"):
            assert np.abs(fa.keypoints[c] - fb.keypoints[c]).max() < px
    for c in ("left", "right"):
        np.testing.assert_allclose(a.rig[c].K, b.rig[c].K, atol=1e-9)
        np.testing.assert_allclose(a.rig[c].dist, b.rig[c].dist, atol=1e-12)
        np.testing.assert_allclose(a.rig[c].T_ecm_cam, b.rig[c].T_ecm_cam, atol=1e-12)


def run_oracle_eval(dataset, out):
    rc = eval_main(["--dataset", str(dataset), "--detector", "oracle", "--out", str(out), "--quiet",
                    "--timeout", "240"])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    for m in ("pnp_joint", "triangulation", "multiview", "refined"):
        d = res["pose"][m]
        assert d["n"] == d["expected"] and d["n"] >= 1, m
        assert d["position_mm"]["max"] < 1e-4, m
        assert d["orientation_deg"]["max"] < 1e-3, m
    return res


def test_ambf_needle_frame_puts_the_tip_where_the_challenge_does():
    """The challenge's scripts span the arc 60..180 deg; its evaluation puts the tip at
    (0.056, 0.085, 0) (56.6 deg) and the base (thread end) at (-0.102, 0, 0) in the needle body
    frame (decimetres): A (30 deg) and E (150 deg) of the dataset frame land on the 60 and 180 deg
    ends, A within 3.5 deg of the evaluation's tip (docs/ros.md)."""
    r = AMBF_NEEDLE_RADIUS_M * 10          # the challenge's scripts are in decimetres
    A = T_AMBF_NEEDLE[:3, :3] @ (r * np.array([np.cos(np.radians(30)), np.sin(np.radians(30)), 0]))
    E = T_AMBF_NEEDLE[:3, :3] @ (r * np.array([np.cos(np.radians(150)), np.sin(np.radians(150)), 0]))
    assert abs(np.degrees(np.arctan2(A[1], A[0])) - 60.0) < 1e-9
    assert abs(np.degrees(np.arctan2(A[1], A[0])) - np.degrees(np.arctan2(0.085, 0.056))) < 3.5
    assert np.linalg.norm(E - [-0.1018, 0.0, 0]) < 1e-12
    assert np.linalg.norm(E - [-0.102, 0.0, 0]) < 0.001


@pytest.mark.slow
def test_ambf_ros1_bag_in_decimetres_converts_exactly(ds640, tmp_path):
    bag = tmp_path / "ambf.bag"
    dataset_to_bag(str(ds640), str(bag), "ambf")           # ROS 1, rgb8, ambf_msgs, unit dm
    from common.ros.bag import open_reader
    r = open_reader(bag)
    types = {c.topic: c.msgtype for c in r.connections}
    r.close()
    assert types["/ambf/env/Needle/State"] == "ambf_msgs/msg/RigidBodyState"
    assert types["/ambf/env/cameras/cameraL/State"] == "ambf_msgs/msg/CameraState"
    assert types["/ambf/env/cameras/cameraL/ImageData"] == "sensor_msgs/msg/Image"
    out = tmp_path / "ds"
    summary = from_bag(str(bag), str(out), preset="ambf")
    assert summary["frames"] == 4 and summary["with_truth"] == 4
    assert summary["unit"].startswith("dm")
    src, ds = Dataset(ds640), Dataset(out)
    assert check_dataset(ds).ok
    assert ds.meta.image_size == (640, 480)
    assert abs(ds.needle.radius_m - 0.01018) < 1e-12
    assert_same_truth(src, ds)
    assert [f.sequence for f in ds] == [0, 0, 1, 1]          # the needle at rest: two groups
    assert np.array_equal(src.image(0, "left"), ds.image(0, "left"))   # rgb8 -> BGR, lossless
    run_oracle_eval(out, tmp_path / "eval")


def test_ambf_si_bag_infers_metres_and_a_wrong_unit_is_a_tenfold_error(ds640, tmp_path):
    bag = tmp_path / "si.bag"
    dataset_to_bag(str(ds640), str(bag), "ambf", unit="m", max_frames=1)
    s = from_bag(str(bag), str(tmp_path / "a"), preset="ambf")
    assert s["unit"].startswith("m ")
    src, a = Dataset(ds640)[0], Dataset(tmp_path / "a")[0]
    assert np.abs(src.T_world_needle - a.T_world_needle).max() < 1e-9
    s = from_bag(str(bag), str(tmp_path / "b"), topics={"preset": "ambf", "unit": "dm"})
    assert s["unit"] == "dm"
    a, b = Dataset(tmp_path / "a")[0], Dataset(tmp_path / "b")[0]
    np.testing.assert_allclose(b.T_world_needle[:3, 3], a.T_world_needle[:3, 3] / 10)


@pytest.mark.slow
def test_ambf_scene_in_dm_and_in_si_converts_to_the_same_dataset(ds640, tmp_path):
    """The 2021-22 challenge's scene is in decimetres, AMBF 2.0's in metres: the same scene in
    both units converts to the same dataset (the needle radius 10.18 mm in both), and the oracle
    is exact on both."""
    out = {}
    for unit in ("dm", "m"):
        bag = tmp_path / f"{unit}.bag"
        dataset_to_bag(str(ds640), str(bag), "ambf", unit=unit)
        out[unit] = tmp_path / f"ds_{unit}"
        s = from_bag(str(bag), str(out[unit]), preset="ambf")
        assert s["unit"].startswith(f"{unit} (inferred"), s["unit"]
        ds = Dataset(out[unit])
        assert check_dataset(ds).ok
        assert ds.needle.radius_m == pytest.approx(0.01018, abs=1e-15)
        assert_same_truth(Dataset(ds640), ds)
    a, b = Dataset(out["dm"]), Dataset(out["m"])
    assert a.needle.to_dict() == b.needle.to_dict()
    assert_same_truth(a, b, px=1e-9)
    for unit in ("dm", "m"):
        run_oracle_eval(out[unit], tmp_path / f"eval_{unit}")


@pytest.mark.slow
def test_dvrk_mcap_1080p_with_distortion_converts_exactly(ds1080_distorted, tmp_path):
    bag = tmp_path / "dvrk"
    r = dataset_to_bag(str(ds1080_distorted), str(bag), "dvrk")     # ROS 2 MCAP + camera_info
    assert any(p.suffix == ".mcap" for p in bag.iterdir())
    out = tmp_path / "ds"
    s = from_bag(str(bag), str(out), topics=r["topics_file"])
    assert s["topics"]["camera_info.left"] == "/jhu_daVinci/left/camera_info"
    assert s["topics"]["ecm_joints"] == "/ECM/measured_js"
    ds = Dataset(out)
    assert ds.meta.image_size == (1920, 1080)
    np.testing.assert_allclose(ds.rig.left.dist, DIST)
    assert check_dataset(ds).ok
    assert_same_truth(Dataset(ds1080_distorted), ds)
    np.testing.assert_allclose(ds[1].ecm_joints, Dataset(ds1080_distorted)[1].ecm_joints)
    run_oracle_eval(out, tmp_path / "eval")


def _as_rclpy_wrote_it(bag_in, bag_out, poison=()):
    """Rewrite a ROS 2 bag as rclpy (rmw_fastrtps) serialises: every message padded to its type
    support's size estimate, JointStates with positions only (116 -> 124 bytes); then the
    ``poison`` (topic, raw bytes) after the first message of that topic."""
    from common.ros import build
    from common.ros.bag import open_reader
    from common.ros.cdr import encode, fastcdr_estimate
    from common.ros.synth import BagWriter
    r, out = open_reader(bag_in), BagWriter(str(bag_out), 2, "mcap")
    conns, padded, poisoned = {}, 0, set()
    try:
        for c, t, raw in r.messages():
            msg = r.deserialize(raw, c.msgtype)
            if c.msgtype == "sensor_msgs/msg/JointState":
                msg = build.make(out.store, c.msgtype, header=msg.header, name=msg.name, position=msg.position)
            data = encode(msg)
            data += bytes(4 + fastcdr_estimate(msg, c.msgtype) - len(data))
            padded += len(data) > len(encode(msg))
            if c.topic not in conns:
                conns[c.topic] = out.w.add_connection(c.topic, c.msgtype, typestore=out.store)
            out.w.write(conns[c.topic], t, data)
            for topic, bad in poison:
                if topic == c.topic and topic not in poisoned:
                    poisoned.add(topic)
                    out.w.write(conns[topic], t + 1, bad)
    finally:
        r.close()
        out.close()
    return padded


@pytest.mark.slow
def test_a_bag_rclpy_serialised_converts_exactly_and_bad_messages_are_skipped(ds640, tmp_path, caplog):
    from common.ros import build
    from common.ros.cdr import encode
    from common.ros.types import typestore
    st = typestore(2)
    dataset_to_bag(str(ds640), str(tmp_path / "dvrk"), "dvrk")
    rig = Dataset(ds640).rig
    info = encode(build.camera_info(st, 10**18, rig.left.K, rig.left.dist, (640, 480)))
    poison = [("/ECM/measured_js", b"\x00\x01\x00\x00" + b"\xff" * 40),          # not a JointState
              ("/jhu_daVinci/left/camera_info", info[:-30])]                      # cut short
    padded = _as_rclpy_wrote_it(tmp_path / "dvrk", tmp_path / "rclpy", poison)
    assert padded >= 4                                   # every JointState at least
    topics = tmp_path / "dvrk.topics.yaml"
    s = from_bag(str(tmp_path / "rclpy"), str(tmp_path / "ds"), topics=str(topics))
    assert s["frames"] == 4 and s["with_truth"] == 4
    assert s["refused"] == {"/ECM/measured_js": 1, "/jhu_daVinci/left/camera_info": 1}
    assert caplog.text.count("cannot deserialise") == 2
    ds = Dataset(tmp_path / "ds")
    assert check_dataset(ds).ok
    assert_same_truth(Dataset(ds640), ds)
    np.testing.assert_allclose(ds[1].ecm_joints, Dataset(ds640)[1].ecm_joints)   # from the padded JointStates
    run_oracle_eval(tmp_path / "ds", tmp_path / "eval")
    # the rosbag source reads the same bag: every pair, the bad messages counted
    from nodes.rosbag import RosbagNode
    node = RosbagNode.offline({"path": str(tmp_path / "rclpy"), "topics": str(topics), "rate": "max"})
    try:
        while node.step():
            pass
    finally:
        node.teardown()
    assert sum(o == "left" for o, _ in node.published) == 4
    assert node.counters["refused_messages"] == 2
    assert all(np.asarray(m.q).shape == (4,) for o, m in node.published if o == "measured")


def test_compressed_image_bag(ds640, tmp_path):
    bag = tmp_path / "compressed.db3"
    r = dataset_to_bag(str(ds640), str(bag.with_suffix("")), "dvrk", compressed=True, storage="sqlite3",
                       max_frames=2)
    out = tmp_path / "ds"
    s = from_bag(r["bag"], str(out), topics=r["topics_file"])
    assert s["topics"]["image.left"] == "/jhu_daVinci/left/image_raw/compressed"
    ds, src = Dataset(out), Dataset(ds640)
    assert len(ds) == 2
    diff = np.abs(ds.image(1, "right").astype(int) - src.image(1, "right")).mean()
    assert diff < 3.0                              # JPEG quality 95
    assert np.abs(ds[1].T_world_needle - src[1].T_world_needle).max() < 1e-9


def test_bag_without_the_topics_is_refused_naming_them(ds640, tmp_path, capsys):
    bag = tmp_path / "ambf.bag"
    dataset_to_bag(str(ds640), str(bag), "ambf", max_frames=1)
    with pytest.raises(BagError, match=r"no image topic for the left camera.*looked for /jhu_daVinci|rig found"):
        BagStereo(bag, "dvrk")
    with pytest.raises(BagError, match=r"no image topic for the left camera: looked for /cam/left.*"
                                       r"the bag has: /ambf/env"):
        BagStereo(bag, topics={"images": {"left": "/cam/left", "right": "/cam/right"}})
    rc = dataset_main(["from-bag", str(bag), "--preset", "dvrk", "--out", str(tmp_path / "x"), "--quiet"])
    assert rc == 1 and "error:" in capsys.readouterr().err
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    with pytest.raises(BagError, match="not a readable"):
        BagStereo(tmp_path / "junk.bag", "ambf")


def test_pairs_need_stamps_within_the_tolerance(ds640, tmp_path):
    """Right images 20 ms after the left: no pair at the default 5 ms, all pairs at 30 ms."""
    from common.ros import build
    from common.ros.synth import BagWriter
    src = Dataset(ds640)
    out = BagWriter(str(tmp_path / "late"), 2, "mcap")
    for i, fr in enumerate(src.frames[:2]):
        t = 10**18 + i * 100_000_000
        for c, dt in (("left", 0), ("right", 20_000_000)):
            out.write(f"/cam/{c}/image_raw", build.image(out.store, t + dt, src.image(fr, c), "bgr8"), t + dt)
    out.close()
    tm = {"images": {"left": "/cam/left/image_raw", "right": "/cam/right/image_raw"}, "fovy_rad": 1.2,
          "registration": {c: src.rig[c].T_ecm_cam.tolist() for c in ("left", "right")}}
    with pytest.raises(BagError, match="no stereo pair"):
        from_bag(str(tmp_path / "late"), str(tmp_path / "a"), topics=tm)
    s = from_bag(str(tmp_path / "late"), str(tmp_path / "b"), topics={**tm, "stereo_tolerance_ms": 30})
    assert s["frames"] == 2 and s["with_truth"] == 0
    ds = Dataset(tmp_path / "b")
    np.testing.assert_allclose(ds.rig.left.K, src.rig.left.K)      # fovy 1.2 at 640x480


def test_topic_maps_name_what_is_wrong(tmp_path):
    from common.ros.topicmap import TopicMapError, load_topic_map
    bad = tmp_path / "map.yaml"
    bad.write_text("preset: dvrk\nimage: {left: /a, right: /b}\n")
    with pytest.raises(TopicMapError, match=r"map.yaml: unknown key 'image'"):
        load_topic_map(None, str(bad))
    with pytest.raises(TopicMapError, match=r"registration: expected \{left: 4x4 T_ecm_cam"):
        load_topic_map("dvrk", {"registration": {"left": np.eye(4).tolist()}})
    with pytest.raises(TopicMapError, match=r"left: expected a 4x4 rigid transform"):
        load_topic_map("dvrk", {"registration": {"left": np.ones((4, 4)).tolist(), "right": np.eye(4).tolist()}})
    with pytest.raises(TopicMapError, match="unit: must be one of"):
        load_topic_map("ambf", {"unit": "furlong"})
    (tmp_path / "reg.yaml").write_text(f"T_ecm_cam: {{left: {np.eye(4).tolist()}, right: {np.eye(4).tolist()}}}\n")
    bad.write_text("preset: dvrk\nregistration: reg.yaml\n")          # relative to the map's folder
    m = load_topic_map(None, str(bad))
    assert np.array_equal(m["registration"]["right"], np.eye(4)) and m["preset"] == "dvrk"


def test_a_state_stamped_only_after_the_pair_is_taken_nearest_not_latest():
    """A recording begun between a frame's images and its state: the pair takes the state stamped
    nearest after it, not the newest one received (that belongs to a later frame)."""
    from common.ros.bag import StereoAssembler
    asm = StereoAssembler({"stereo_tolerance_ms": 5, "unit": "m", "needle_frame": "cv"}, "test", {})
    asm.hist["needle_pose"] = deque([(1_040_000_000, "first"), (1_073_000_000, "second"), (1_106_000_000, "third")])
    assert asm._state_at(1_030_000_000)["needle_pose"] == "first"
    assert asm._state_at(1_080_000_000)["needle_pose"] == "second"     # stamped last at or before
    assert asm._state_at(1_200_000_000)["needle_pose"] == "third"
