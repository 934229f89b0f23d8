"""The camera source nodes, offline (no process, no network): sim and replay."""
import os

import cv2
import time

import numpy as np
import pytest

import common.sim.render  # noqa: F401  (headless GL before mujoco)
from common.data.check import project_keypoints
from common.data.dataset import DatasetMeta, Frame
from common.data.writer import DatasetWriter
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from common.runtime.messages import (
    Calibration,
    Command,
    EcmJoints,
    EndOfStream,
    decode,
    encode,
)
from common.sim.randomise import default_arm
from common.runtime.node import NodeError
from common.runtime.pacing import parse_rate
from nodes.replay import ReplayNode
from nodes.sim import SimNode

W, H = 160, 90


def _dataset(folder, n=3, truth=True):
    meta = DatasetMeta((W, H), StereoRig.default(W, H), NeedleModel(), default_arm(), "test")
    img = np.full((H, W, 3), 90, np.uint8)
    with DatasetWriter(folder, meta, image_format="png") as w:
        for i in range(n):
            paths = w.write_images(i, {"left": img, "right": img})
            q = np.array([0.01 * i, 0.0, 0.12, 0.0])
            T_we = meta.arm.T_world_ecm(q)
            T_wn = T_we @ make_T(rotvec_to_R([2.8, 0.1, 0.2]), [0.0, 0.0, -0.12])
            extra = dict(sequence=0, step=i, ecm_joints=q, T_world_ecm=T_we, T_world_needle=T_wn,
                         keypoints=project_keypoints(meta, T_we, T_wn),
                         visible={c: np.ones(5, bool) for c in ("left", "right")},
                         bbox={"left": [1.0, 2.0, 3.0, 4.0], "right": None}) if truth else {}
            w.append(Frame(index=i, stamp_ns=1000 + i * 10_000_000, left=paths["left"], right=paths["right"], **extra))
    return meta


def _run(node, max_steps=100):
    for _ in range(max_steps):
        if node.step() is False:
            return True
    return False


def _roundtrip(msg):
    return decode(encode(msg), type(msg))


def test_replay_sends_a_withheld_camera_s_images_black_in_one_window(tmp_path):
    _dataset(tmp_path, 10)
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "max", "withhold": "right",
                                      "withhold_share": 0.3, "withhold_seed": 2})
    assert _run(node)
    msgs = [(o, _roundtrip(m)) for o, m in node.published]
    black = [m.seq for o, m in msgs if o == "right" and not m.to_bgr().any()]
    assert len(black) == 3 and black == list(range(black[0], black[0] + 3))
    assert all(m.to_bgr().any() for o, m in msgs if o == "left")              # the other camera as it is
    assert node.counters["withheld"] == 3 and sum(o == "truth" for o, _ in msgs) == 10


def test_replay_publishes_calib_frames_truth_and_eos(tmp_path):
    meta = _dataset(tmp_path, 3)
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "max"})
    assert _run(node)
    outs = [o for o, _ in node.published]
    assert outs[0] == "calib"
    assert outs[-1] == "eos"
    msgs = [(o, _roundtrip(m)) for o, m in node.published]
    frames = [m for o, m in msgs if o == "left"]
    assert [m.seq for m in frames] == [0, 1, 2]
    assert all(m.encoding == "png" and m.to_bgr().shape == (H, W, 3) for m in frames)
    truths = [m for o, m in msgs if o == "truth"]
    assert len(truths) == 3 and truths[1].step == 1
    assert np.allclose(truths[2].keypoints["left"], project_keypoints(meta, truths[2].T_world_ecm, truths[2].T_world_needle)["left"])
    joints = [m for o, m in msgs if o == "joints"]
    assert isinstance(joints[0], EcmJoints) and np.allclose(joints[1].q, [0.01, 0, 0.12, 0])
    eos = msgs[-1][1]
    assert isinstance(eos, EndOfStream) and eos.frames == 3
    calib = msgs[0][1]
    assert isinstance(calib, Calibration) and np.allclose(StereoRig.from_dict(calib.cameras, calib.image_size).left.K, meta.rig.left.K)
    assert EcmArm.from_calibration(calib.ecm) is not None


def test_replay_loop_and_no_truth(tmp_path):
    _dataset(tmp_path, 2, truth=False)
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": 1000, "loop": True})
    assert not _run(node, 5)  # looping never ends
    seqs = [m.seq for o, m in node.published if o == "left"]
    assert seqs == [0, 1, 2, 3, 4]
    assert not any(o in ("truth", "joints", "eos") for o, _ in node.published)


def test_replay_stamps_the_recorded_timing_whatever_its_pace(tmp_path):
    """``stamps: recorded``: the frames 10 ms apart as recorded, played as fast as it goes and
    looped (the next pass one interval after the last frame); ``wall``: the time of sending."""
    _dataset(tmp_path, 3)
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "max", "loop": True, "stamps": "recorded"})
    _run(node, 6)
    stamps = [m.stamp_ns for o, m in node.published if o == "left"]
    assert np.diff(stamps).tolist() == [10_000_000] * 5
    t0 = time.time_ns()
    truth = [m.stamp_ns for o, m in node.published if o == "truth"]
    assert truth == stamps and abs(stamps[0] - t0) < 60e9      # anchored at the first frame's sending
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "max"})
    _run(node)
    assert np.diff([m.stamp_ns for o, m in node.published if o == "left"]).max() < 10_000_000


def test_replay_skips_an_unreadable_frame(tmp_path):
    _dataset(tmp_path, 3)
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "max"})
    os.remove(tmp_path / "images" / "right" / "000001.png")
    assert _run(node)
    assert node.counters["image_errors"] == 1
    assert [m.seq for o, m in node.published if o == "left"] == [0, 2]
    assert node.published[-1][1].frames == 2


def test_replay_decode_sends_raw_images_and_skips_a_broken_one(tmp_path, monkeypatch):
    _dataset(tmp_path, 3)
    (tmp_path / "images" / "left" / "000001.png").write_bytes(b"not a png")
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": 1000, "loop": True, "decode": True})
    assert node.counters["image_errors"] == 1      # found at start-up, logged and counted once
    assert not _run(node, 6)
    frames = [_roundtrip(m) for o, m in node.published if o == "left"]
    assert [m.seq for m in frames] == [0, 2, 3, 5]  # frame 1 skipped in every loop
    want = cv2.imread(str(tmp_path / "images" / "left" / "000002.png"), cv2.IMREAD_COLOR)
    assert all(m.encoding == "bgr8" for m in frames) and np.array_equal(frames[1].to_bgr(), want)
    import nodes.replay
    monkeypatch.setattr(nodes.replay, "MAX_DECODED_BYTES", 10)
    with pytest.raises(ValueError, match="count"):
        ReplayNode.offline(params={"path": str(tmp_path), "decode": True})


def test_replay_paced_sends_the_next_frame_once_both_acks_are_in(tmp_path):
    from common.runtime.messages import Keypoints
    _dataset(tmp_path, 4)
    ack = lambda cam, seq: Keypoints.not_found(cam, seq, 0, "oracle", "test")
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "paced", "in_flight": 1,
                                      "ack_timeout": 60}, wired=["ack", "ack2"])
    seqs = lambda: [m.seq for o, m in node.published if o == "left"]
    for _ in range(5):
        node.step()
    assert seqs() == [0]                       # frame 0 unanswered: nothing more goes out
    node.on_ack(ack("left", 0))
    node.step()
    assert seqs() == [0]                       # one camera of two
    node.on_ack2(ack("right", 0))
    node.step()
    assert seqs() == [0, 1]
    # two in flight; an unanswered frame stops counting after ack_timeout (the window's clock
    # moved on by hand: no race with a loaded machine)
    import time
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "paced", "in_flight": 2,
                                      "ack_timeout": 60}, wired=["ack"])
    later = [0.0]
    node.acks.clock = lambda: time.monotonic() + later[0]
    node.step(), node.step(), node.step()
    assert seqs() == [0, 1]
    later[0] = 120.0
    node.step()
    assert seqs() == [0, 1, 2] and node.counters["ack_timeouts"] >= 1
    with pytest.raises(ValueError, match="paced"):
        ReplayNode.offline(params={"path": str(tmp_path), "rate": "paced"}, wired=[])


def test_replay_params_are_checked(tmp_path):
    assert parse_rate("recorded") is None and parse_rate("max") == 0.0 and parse_rate("12.5") == 12.5
    for bad in ("fast", -1, 0):
        with pytest.raises(ValueError):
            parse_rate(bad)
    with pytest.raises(ValueError):
        ReplayNode.offline(params={})


def test_sim_node_publishes_consistent_frames_and_obeys_commands():
    node = SimNode.offline(params={"width": 320, "height": 180, "rate_hz": 0, "count": 4, "motion": "multiview",
                                   "steps": 2, "hold_frames": 1, "randomise": "none", "encoding": "png"})
    try:
        assert _run(node)
        msgs = [(o, _roundtrip(m)) for o, m in node.published]
        assert msgs[0][0] == "calib"
        calib = msgs[0][1]
        rig, needle, arm = StereoRig.from_dict(calib.cameras, calib.image_size), NeedleModel.from_dict(calib.needle), EcmArm.from_calibration(calib.ecm)
        lefts = [m for o, m in msgs if o == "left"]
        assert [m.seq for m in lefts] == [0, 1, 2, 3]
        assert lefts[0].to_bgr().shape == (180, 320, 3)
        truths = [m for o, m in msgs if o == "truth"]
        joints = [m for o, m in msgs if o == "joints"]
        # multiview: 2 steps of 1 frame per needle pose, then a new pose
        assert [(t.sequence, t.step) for t in truths] == [(0, 0), (0, 1), (1, 0), (1, 1)]
        assert np.allclose(truths[0].T_world_needle, truths[1].T_world_needle)
        assert not np.allclose(truths[1].T_world_needle, truths[2].T_world_needle)
        moved = np.abs(joints[1].q - joints[0].q)
        assert np.isclose(moved.max(), 0.05) and np.sum(moved > 1e-12) == 1
        for t, j in zip(truths, joints):
            T_we = arm.T_world_ecm(j.q)
            assert np.allclose(T_we, t.T_world_ecm)
            p = transform_points(inv_T(T_we) @ t.T_world_needle, needle.keypoints())
            for cam in ("left", "right"):
                assert np.allclose(rig[cam].project_from_ecm(p), t.keypoints[cam], atol=1e-9)
            assert t.visible["left"].sum() >= 3
        # the needle can be re-placed on command
        node.count_max = 0
        T = truths[-1].T_world_needle.copy()
        T[:3, 3] += [0.005, 0.0, 0.002]
        node.on_command(Command("place_needle", {"T_world_needle": T.tolist()}))
        node.published.clear()
        node.step()
        t = [m for o, m in node.published if o == "truth"][0]
        assert np.allclose(t.T_world_needle, T)
        node.on_command(Command("set_motion", {"motion": "dance"}))        # refused, counted, not raised
        node.on_command(Command("place_needle", {"T_world_needle": np.full((4, 4), np.nan)}))
        assert node.counters["bad_commands"] == 2
        node.published.clear()
        node.step()
        assert np.allclose([m for o, m in node.published if o == "truth"][0].T_world_needle, T)
    finally:
        node.teardown()


def test_sim_node_in_a_take_publishes_the_instruments_and_the_held_needle_with_them():
    from common.runtime.messages import InstrumentState
    node = SimNode.offline(params={"width": 160, "height": 120, "rate_hz": 0, "count": 3, "motion": "handover",
                                   "randomise": "none", "encoding": "png", "msaa": 0})
    try:
        assert _run(node)
        msgs = [(o, _roundtrip(m)) for o, m in node.published]
        inst = [m for o, m in msgs if o == "instruments"]
        truths = [m for o, m in msgs if o == "truth"]
        assert all(isinstance(m, InstrumentState) for m in inst)
        assert [(m.seq, m.name) for m in inst] == [(s, n) for s in range(3) for n in ("psm1", "psm2")]
        assert all(t.needle_at_rest is False and t.multiview_group is None for t in truths)
        held = {(m.seq, m.name): m for m in inst}
        for t in truths:                      # psm1 holds it at the start of a handover, psm2 waits open
            m = held[(t.seq, "psm1")]
            assert m.holds_needle and not held[(t.seq, "psm2")].holds_needle and m.jaw_rad < 0.1
            T_jn = inv_T(m.T_world_jaw) @ t.T_world_needle
            assert np.linalg.norm(T_jn[:3, 3]) < 0.02               # the needle's centre by the jaws
        node.count_max = 0
        T = truths[-1].T_world_needle.copy()                  # placed by pose: at rest, even in a take
        T[:3, 3] += [0.0, 0.004, 0.002]
        node.on_command(Command("place_needle", {"T_world_needle": T.tolist()}))
        for _ in range(2):
            node.published.clear()
            node.step()
            t = [m for o, m in node.published if o == "truth"][0]
            assert np.allclose(t.T_world_needle, T) and t.needle_at_rest is None
        node.on_command(Command("set_motion", {"motion": "static"}))
        node.published.clear()
        node.step()
        t = [m for o, m in node.published if o == "truth"][0]
        assert t.needle_at_rest is None and [m.holds_needle for o, m in node.published if o == "instruments"] == []
    finally:
        node.teardown()


def test_sim_node_with_an_arm_error_reports_the_jaws_off_the_truth_and_renders_the_same_frames():
    from common.geometry.transforms import pose_error
    out = {}
    for arm_error in ("exact", "dvrk"):
        node = SimNode.offline(params={"width": 160, "height": 120, "rate_hz": 0, "count": 2, "motion": "handover",
                                       "randomise": "none", "encoding": "png", "msaa": 0, "arm_error": arm_error})
        try:
            assert _run(node)
            out[arm_error] = [(o, _roundtrip(m)) for o, m in node.published]
        finally:
            node.teardown()
    images = {k: [bytes(m.data) for o, m in v if o in ("left", "right")] for k, v in out.items()}
    assert images["exact"] == images["dvrk"] and len(images["exact"]) == 4
    exact = {(m.seq, m.name): m for o, m in out["exact"] if o == "instruments"}
    for o, m in out["dvrk"]:
        if o != "instruments":
            continue
        e = exact[(m.seq, m.name)]
        assert e.T_world_jaw_truth is None and e.jaw_rad_truth is None
        assert np.array_equal(m.T_world_jaw_truth, e.T_world_jaw) and m.jaw_rad_truth == e.jaw_rad
        dt, da = pose_error(m.T_world_jaw, m.T_world_jaw_truth)
        assert 1e-3 < dt < 8e-3 and np.deg2rad(0.5) < da < np.deg2rad(6)
    with pytest.raises(NodeError, match="arm error"):
        SimNode.offline(params={"width": 160, "height": 120, "arm_error": "dvrk:noise=1"})


def test_replay_publishes_the_instruments_a_folder_lists(tmp_path):
    from common.data.dataset import Dataset
    from common.data.instruments import InstrumentPose
    from common.runtime.messages import InstrumentState
    _dataset(tmp_path, 2)
    ds = Dataset(tmp_path)
    lines = []
    for fr in ds.frames:
        if fr.index == 1:
            fr.needle_at_rest = False
            fr.instruments = {"psm2": InstrumentPose(make_T(np.eye(3), [0.01, 0.0, 0.03]), 0.4, True)}
            fr.sequence = 1
        lines.append(fr.to_json())
    (tmp_path / "frames.jsonl").write_text("".join(__import__("json").dumps(o) + "\n" for o in lines))
    node = ReplayNode.offline(params={"path": str(tmp_path), "rate": "max"})
    assert _run(node)
    inst = [(o, _roundtrip(m)) for o, m in node.published if o == "instruments"]
    assert len(inst) == 1 and isinstance(inst[0][1], InstrumentState)
    m = inst[0][1]
    assert (m.name, m.seq, m.jaw_rad, m.holds_needle) == ("psm2", 1, 0.4, True)
    assert np.allclose(m.T_world_jaw[:3, 3], [0.01, 0.0, 0.03])
    truth = [m for o, m in node.published if o == "truth"]
    assert truth[1].needle_at_rest is False and truth[0].needle_at_rest is None
