"""The instruments from ROS: a dVRK-convention MCAP written here from a moving take (``/PSM1``,
``/PSM2`` ``measured_cp`` in each arm's base frame, ``jaw/measured_js``, the arms' registration
in a file) converts with the instruments in the right frame and the oracle exact at 0 px; the
``rosbag`` source publishes ``InstrumentState``; topic maps name what is wrong."""
import numpy as np
import pytest
import yaml
from test_ros_bag import run_oracle_eval

from common.cli import dataset_main
from common.data.check import check_dataset
from common.data.dataset import Dataset
from common.ros.convert import from_bag
from common.ros.synth import PSM_BASES, dataset_to_bag
from common.ros.topicmap import TopicMapError, load_topic_map

FRAMES = 24


@pytest.fixture(scope="module")
def dvrk_take(tmp_path_factory):
    root = tmp_path_factory.mktemp("ros_inst")
    rc = dataset_main(["generate", "--out", str(root / "ds"), "--sequences", "1", "--motion", "throw", "--width", "320",
                       "--height", "240", "--msaa", "0", "--seed", "11", "--randomise", "none", "--jobs", "1",
                       "--quiet", "--format", "png"])
    assert rc == 0
    r = dataset_to_bag(str(root / "ds"), str(root / "dvrk"), "dvrk", max_frames=FRAMES)
    return root, r


@pytest.mark.slow
def test_a_dvrk_mcap_with_psm_topics_converts_with_the_instruments_in_world(dvrk_take, tmp_path):
    root, r = dvrk_take
    assert r["instruments"] == ["psm1", "psm2"]
    reg = yaml.safe_load(open(r["psm_registration"]))
    assert set(reg["T_world_base"]) == {"psm1", "psm2"}
    s = from_bag(str(root / "dvrk"), str(tmp_path / "conv"), topics=r["topics_file"])
    assert s["topics"]["instrument_pose.psm1"] == "/PSM1/measured_cp"
    assert s["topics"]["instrument_jaw.psm2"] == "/PSM2/jaw/measured_js"
    src, out = Dataset(root / "ds"), Dataset(tmp_path / "conv")
    assert len(out) == FRAMES and check_dataset(out).ok
    moved = 0
    for a, b in zip(src, out):
        for name in ("psm1", "psm2"):
            ia, ib = a.instruments[name], b.instruments[name]
            assert np.abs(ia.T_world_jaw - ib.T_world_jaw).max() < 1e-9, (a.index, name)
            assert ib.jaw_rad == pytest.approx(ia.jaw_rad, abs=1e-12) and ib.holds_needle is None
            # the bag's pose is in the arm's base, not in world: the registration was applied
            assert np.abs(PSM_BASES[name] - np.eye(4)).max() > 0.1
        assert np.abs(a.T_world_needle - b.T_world_needle).max() < 1e-9
        for c in ("left", "right"):
            assert np.abs(a.keypoints[c] - b.keypoints[c]).max() < 1e-6
        moved += not np.allclose(a.T_world_needle, src[0].T_world_needle)
    assert moved > 0                                            # the needle moves in the jaws
    run_oracle_eval(tmp_path / "conv", tmp_path / "eval")       # exact at 0 px (poses < 1e-4 mm)


@pytest.mark.slow                 # the bag's take is rendered first (about 12 s)
def test_the_rosbag_source_publishes_the_instruments(dvrk_take):
    from common.runtime.messages import InstrumentState, decode, encode
    from nodes.rosbag import RosbagNode
    root, r = dvrk_take
    node = RosbagNode.offline(params={"path": str(root / "dvrk"), "topics": r["topics_file"], "rate": "max",
                                      "count": 3})
    try:
        for _ in range(20):
            if node.step() is False:
                break
    finally:
        node.teardown()
    inst = [decode(encode(m), InstrumentState) for o, m in node.published if o == "instruments"]
    src = Dataset(root / "ds")
    assert [(m.seq, m.name) for m in inst] == [(s, n) for s in range(3) for n in ("psm1", "psm2")]
    for m in inst:
        assert np.abs(m.T_world_jaw - src[m.seq].instruments[m.name].T_world_jaw).max() < 1e-9


def test_instrument_topic_maps(tmp_path):
    m = load_topic_map("dvrk")
    assert m["instruments"]["psm2"] == {"pose": "/PSM2/measured_cp", "jaw": "/PSM2/jaw/measured_js"}
    a = load_topic_map("ambf")["instruments"]["psm1"]
    assert a["pose"] == "/CRTK/psm1/measured_cp" and a["jaw"] == "/CRTK/psm1/jaw/measured_js"
    assert "/ambf/env/psm1/baselink/State" in a["base"] and a["unit"] == "m"
    # a user's entry overrides the preset's key by key
    m = load_topic_map("dvrk", {"instruments": {"psm1": {"pose": "/PSM1/local/measured_cp"}}})
    assert m["instruments"]["psm1"] == {"pose": "/PSM1/local/measured_cp", "jaw": "/PSM1/jaw/measured_js"}
    (tmp_path / "reg.yaml").write_text(yaml.safe_dump({"psm1": np.eye(4).tolist()}))
    (tmp_path / "map.yaml").write_text(yaml.safe_dump({"instrument_registration": "reg.yaml"}))
    assert np.array_equal(load_topic_map("dvrk", tmp_path / "map.yaml")["instrument_registration"]["psm1"], np.eye(4))
    bad = [({"instruments": {"psm3": {"pose": "/a"}}}, "instruments.psm3: needs a pose and a jaw topic"),
           ({"instruments": {"psm1": {"pose": "/a", "jaw": "/b", "colour": 1}}}, "unknown key 'colour'"),
           ({"instruments": {"psm1": {"pose": "/a", "jaw": "/b", "unit": "inch"}}}, "instruments.psm1.unit"),
           ({"instrument_registration": {"psm1": [[1, 0], [0, 1]]}}, "psm1: expected a 4x4 rigid transform"),
           ({"instrument_registration": "missing.yaml"}, "instrument_registration: cannot read")]
    for user, text in bad:
        with pytest.raises(TopicMapError, match=text):
            load_topic_map("dvrk", user)


def test_record_writes_instrument_states_as_a_dvrk_arm_and_plays_them_back():
    from common.geometry.camera import StereoRig
    from common.geometry.needle import NeedleModel
    from common.geometry.transforms import make_T, rotvec_to_R
    from common.ros.roles import pose_of
    from common.ros.record import replay_topic_map, ros_messages
    from common.runtime.messages import Calibration, InstrumentState
    T = make_T(rotvec_to_R([0.2, -0.4, 1.1]), [0.01, -0.02, 0.03])
    rows = dict(ros_messages("/camera/instruments", InstrumentState("psm2", 3, 1_000, T, 0.35, True)))
    assert set(rows) == {"/camera/instruments/psm2/measured_cp", "/camera/instruments/psm2/jaw/measured_js"}
    assert np.abs(pose_of(rows["/camera/instruments/psm2/measured_cp"]) - T).max() < 1e-12
    assert list(rows["/camera/instruments/psm2/jaw/measured_js"].position) == [0.35]
    calib = Calibration(0, np.array([320, 240]), StereoRig.default(320, 240).to_dict(), NeedleModel().to_dict())
    tm = replay_topic_map({"types": {"/camera/left": "CameraImage", "/camera/right": "CameraImage",
                                     "/camera/instruments": "InstrumentState"},
                           "calibration": calib, "calibration_topic": "/camera/calib",
                           "instruments": {"/camera/instruments": {"psm2", "psm1"}}})
    assert tm["instruments"]["psm2"] == {"pose": "/camera/instruments/psm2/measured_cp",
                                         "jaw": "/camera/instruments/psm2/jaw/measured_js"}
    assert sorted(load_topic_map(None, tm)["instruments"]) == ["psm1", "psm2"]


@pytest.mark.slow                 # the bag's take is rendered first (about 12 s)
def test_the_ros2_source_publishes_the_instruments(dvrk_take):
    """The live source fed the bag's CDR samples as its Zenoh subscribers would deliver them (its
    session on loopback, connected to nothing): the same InstrumentStates as the bag's."""
    from graphtools import free_port

    from common.ros.bag import open_reader
    from common.runtime.messages import InstrumentState
    from nodes.ros2 import Ros2Node
    root, r = dvrk_take
    node = Ros2Node.offline(params={"topics": r["topics_file"], "rig": "jhu_daVinci",
                                    "connect": [f"tcp/127.0.0.1:{free_port()}"]})
    reader = open_reader(root / "dvrk")
    try:
        for conn, t, raw in reader.messages():
            if conn.topic in node.keys:
                node._enqueue((conn.topic, node.keys[conn.topic], bytes(raw), t))
                while not node.queue.empty():
                    node.step()
    finally:
        reader.close()
        node.teardown()
    inst = [m for o, m in node.published if o == "instruments"]
    src = Dataset(root / "ds")
    assert len(inst) >= 2 * (FRAMES - 3) and all(isinstance(m, InstrumentState) for m in inst)
    for m in inst:
        assert np.abs(m.T_world_jaw - src[m.seq].instruments[m.name].T_world_jaw).max() < 1e-9


@pytest.mark.slow                 # the bag's take is rendered first (about 12 s)
def test_an_ambf_bag_in_decimetres_gives_the_instruments_through_the_crtk_wrapper_and_the_base(dvrk_take, tmp_path):
    """The challenge's way: the tip in its base (CRTK, metres) and the base body's state (scene
    units, here decimetres): the preset scales each by its own unit."""
    root, _ = dvrk_take
    r = dataset_to_bag(str(root / "ds"), str(tmp_path / "ambf.bag"), "ambf", max_frames=4)      # unit dm
    assert r["instruments"] == ["psm1", "psm2"]
    s = from_bag(str(tmp_path / "ambf.bag"), str(tmp_path / "conv"), preset="ambf")
    assert s["unit"].startswith("dm") and s["topics"]["instrument_base.psm1"] == "/ambf/env/psm1/baselink/State"
    src, out = Dataset(root / "ds"), Dataset(tmp_path / "conv")
    assert len(out) == 4 and check_dataset(out).ok
    for a, b in zip(src, out):
        for name in ("psm1", "psm2"):
            assert np.abs(a.instruments[name].T_world_jaw - b.instruments[name].T_world_jaw).max() < 1e-9
