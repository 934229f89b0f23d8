"""Regression tests of the robustness defects found by probing the default graph (docs/robustness.md): source epochs, poison
messages validated at the codec, the pose invariant at publish, limits on disk input. Most run
in process; the restart and the poison run real processes, as the defects needed them."""
import os
import signal
import time

import msgpack
import numpy as np
import pytest
from test_geometry_nodes import CALIB, MODEL, RIG, _multiview_dataset, detect, frame

from common.data.check import check_dataset
from common.data.dataset import Dataset, DatasetError
from common.geometry.oracle import random_needle_pose
from common.runtime.graph import GraphError, load_graph
from common.runtime.graph_checks import validate_graph
from common.runtime.messages import (
    Calibration,
    CameraImage,
    EcmPose,
    GroundTruth,
    Keypoints,
    MessageError,
    PoseEstimate,
    decode,
    encode,
)
from common.runtime.pairing import SeqClock

T_NEEDLE = random_needle_pose(np.random.default_rng(3), RIG, MODEL, max_offaxis=0.15)   # in view


def raw(schema_cls, body) -> bytes:
    """A payload with any body (bypassing the encoder's types)."""
    return msgpack.packb({"schema": schema_cls.SCHEMA, "version": schema_cls.VERSION, "body": body})


def feed(node, name, msg) -> bool:
    """What the runtime does with a payload: decode (with the input's type), then deliver."""
    return node.deliver(name, decode(encode(msg) if not isinstance(msg, bytes) else msg, node.INPUTS[name]))


# ====================================================================== the frame clock

def test_seq_clock_follows_a_restarted_source_and_drops_lone_poison():
    c = SeqClock(window=100)
    assert [c.observe(s, 7) for s in range(500, 505)] == ["ok"] * 5
    assert c.observe(2 ** 62, 7) == "outlier"              # far-future seq: dropped ...
    assert c.observe(505, 7) == "ok" and c.newest == 505    # ... and forgotten
    assert c.observe(3, 99) == "outlier"                   # a foreign epoch once: dropped
    assert c.observe(506, 7) == "ok"
    # a restarted source (epoch 8) from seq 0: its second message confirms the new stream
    assert c.observe(0, 8) == "outlier" and c.observe(0, 8) == "outlier"   # a pair does not confirm
    assert c.observe(1, 8) == "reset"                                       # the next frame does
    assert c.epoch == 8 and c.newest == 1 and c.observe(2, 8) == "ok"
    assert c.observe(507, 7) == "stale"                    # in flight from the dead process
    # a source that restarts quickly: seq goes back by less than the window; the epoch tells
    c2 = SeqClock(window=1000)
    for s in range(40):
        c2.observe(s, 1)
    assert c2.observe(0, 2) == "outlier" and c2.observe(1, 2) == "reset" and c2.newest == 1
    c3 = SeqClock(window=100)                              # no epochs: a jump the stream confirms
    for s in range(500, 510):
        c3.observe(s)
    assert c3.observe(0) == "outlier" and c3.observe(1) == "reset" and c3.observe(2) == "ok"


def test_a_poisoned_stream_recovers_once_the_poison_stops():
    c = SeqClock(window=100, alive=16)
    for s in range(10):
        c.observe(s, 1)
    assert c.observe(2 ** 60, 5) == "outlier" and c.observe(2 ** 60 + 1, 5) == "reset"   # it moves on
    got = [c.observe(s, 1) for s in range(10, 40)]        # the real stream comes back
    assert "reset" in got and got[-1] == "ok" and c.epoch == 1


# ====================================================================== defect 1: restarts

def _stereo_pose_node(cls=None, **params):
    from nodes.triangulate import TriangulateNode
    node = (cls or TriangulateNode).offline(params, wired=["left", "right", "calib", "ecm"])
    node.on_calib(CALIB)
    return node


def _frames(seqs, epoch):
    """(left, right, EcmPose) of a still needle at frames ``seqs`` of a stream ``epoch``."""
    out = []
    truths = [frame(s, T_NEEDLE)[0] for s in seqs]
    lefts, rights = detect(truths)
    for t, l, r in zip(truths, lefts, rights):
        l.epoch = r.epoch = epoch
        out.append((l, r, EcmPose(t.seq, t.stamp_ns, t.T_world_ecm, epoch=epoch)))
    return out


def test_a_restarted_source_is_followed_at_once_offline():
    node = _stereo_pose_node()
    for l, r, e in _frames(range(100, 110), epoch=1):
        feed(node, "ecm", e), feed(node, "left", l), feed(node, "right", r)
    poses = lambda: [m for o, m in node.published if o == "pose"]     # noqa: E731
    n_before = len(poses())
    assert n_before == 10
    for l, r, e in _frames(range(0, 5), epoch=2):          # the camera restarted: seq from 0
        feed(node, "ecm", e), feed(node, "left", l), feed(node, "right", r)
    new = poses()[n_before:]
    assert [m.seq for m in new] == [1, 2, 3, 4]             # followed from its second frame
    assert all(m.T_world_needle is not None for m in new)
    assert node.counters["stream_resets"] == 1


# ====================================================================== defect 2: far-future seq

def test_one_far_future_keypoints_pair_does_not_stop_the_poses():
    from nodes.epnp import EpnpNode
    node = _stereo_pose_node(EpnpNode, method="joint")
    frames = _frames(range(10, 20), epoch=None)
    for l, r, e in frames[:5]:
        feed(node, "ecm", e), feed(node, "left", l), feed(node, "right", r)
    l, r, _ = frames[5]
    for kp in (l, r):
        bad = decode(encode(kp))
        bad.seq = 2 ** 62
        assert feed(node, bad.camera, bad) is False           # dropped, counted
    for l, r, e in frames[5:]:
        feed(node, "ecm", e), feed(node, "left", l), feed(node, "right", r)
    assert [m.seq for _, m in node.published] == list(range(10, 20))
    assert node.counters["seq_outlier"] == 2


def test_a_seq_a_few_hundred_frames_ahead_is_dropped_too():
    """Found by ``bench fuzz --live``: a poison seq 500 frames ahead (inside the old 1000-frame
    window) made the pairer drop the other camera's frames until the stream caught up."""
    from nodes.epnp import EpnpNode
    node = _stereo_pose_node(EpnpNode, method="joint")
    frames = _frames(range(10, 20), epoch=None)
    for l, r, e in frames[:3]:
        feed(node, "ecm", e), feed(node, "left", l), feed(node, "right", r)
    bad = decode(encode(frames[3][0]))
    bad.seq += 500
    assert feed(node, "left", bad) is False
    for l, r, e in frames[3:]:
        feed(node, "ecm", e), feed(node, "left", l), feed(node, "right", r)
    assert [m.seq for _, m in node.published] == list(range(10, 20))


# ====================================================================== defect 3: empty images

def test_an_empty_jpeg_is_refused_and_the_detector_keeps_detecting():
    from nodes.detector import DetectorNode
    empty = CameraImage("left", 1, 0, 64, 48, "jpeg", b"")
    with pytest.raises(MessageError, match="CameraImage.data: not a jpeg"):
        decode(encode(empty))
    det = DetectorNode.offline({"backend": "classical"}, wired=["left", "calib"])
    det.on_calib(Calibration(0, np.array([64, 48]), CALIB.cameras, CALIB.needle))
    det.on_left(empty)                  # a writer that skips the codec: handled, not raised
    good = CameraImage.from_bgr("left", 2, 0, np.zeros((48, 64, 3), np.uint8), "jpeg")
    det.on_left(good)
    assert [m.seq for _, m in det.published] == [1, 2] and det.counters["bad_image"] == 1
    assert "bad image" in det.published[0][1].reason


def test_a_frame_whose_detection_raises_is_not_retried_for_ever():
    from nodes.detector import DetectorNode
    det = DetectorNode.offline({"backend": "oracle"}, wired=["left", "right", "truth", "calib"])
    calls = []

    def boom(*a, **k):
        calls.append(1)
        raise RuntimeError("backend bug")
    det.backend.detect, real = boom, det.backend.detect
    det.on_calib(CALIB)
    truth = frame(1, T_NEEDLE)[0]
    det.on_truth(truth)
    with pytest.raises(RuntimeError):
        det.on_left(CameraImage.from_bgr("left", 1, 0, np.zeros((4, 4, 3), np.uint8)))
    det.backend.detect = real
    det.on_truth(frame(2, T_NEEDLE)[0])
    det.on_left(CameraImage.from_bgr("left", 2, 0, np.zeros((4, 4, 3), np.uint8)))
    assert len(calls) == 1 and [m.seq for _, m in det.published] == [2]


# ====================================================================== defect 4: malformed

def test_malformed_calibration_and_truth_are_refused_at_the_codec():
    body = CALIB.to_body()
    body["image_size"] = [float("inf"), 1080.0]
    for k in ("cameras", "needle", "ecm"):
        body[k] = {c: (v.tolist() if isinstance(v, np.ndarray) else v) for c, v in body[k].items()}
    body["cameras"] = {c: {k: np.asarray(v).tolist() if v is not None else None for k, v in cam.items()}
                       for c, cam in CALIB.cameras.items()}
    with pytest.raises(MessageError, match="Calibration.image_size"):
        decode(raw(Calibration, body))
    gt = {"seq": 1, "stamp_ns": 0, "keypoints": {"left": [[1.0, 2.0], [3.0]], "right": None}}
    with pytest.raises(MessageError, match="GroundTruth.keypoints.left"):
        decode(raw(GroundTruth, gt))
    gt["keypoints"] = {"left": [[1.0, 2.0]] * 4, "right": None}
    with pytest.raises(MessageError, match=r"GroundTruth.keypoints.left: expected shape \(5, 2\)"):
        decode(raw(GroundTruth, gt))
    for field, bad in (("seq", -1), ("seq", 2 ** 64 - 1), ("stamp_ns", -5)):
        with pytest.raises(MessageError, match=f"GroundTruth.{field}"):
            decode(raw(GroundTruth, {"seq": 1, "stamp_ns": 0, field: bad}))


# ====================================================================== defect 5: wrong poses

def test_bad_ecm_poses_are_refused_at_the_ecm_input():
    nan = np.full((4, 4), np.nan)
    skew = np.eye(4)
    skew[0, 1] = 0.3
    for T, why in ((nan, "not finite"), (skew, "not a rigid transform")):
        with pytest.raises(MessageError, match=f"EcmPose.T_world_ecm: {why}"):
            decode(encode(EcmPose(1, 0, T)))


@pytest.mark.parametrize("change, why", [
    (lambda p: p.T_ecm_needle.__setitem__((0, 3), 1e42), "working volume"),
    (lambda p: p.T_ecm_needle.__setitem__((0, 3), 1.5), "working volume"),
    (lambda p: p.T_ecm_needle.__setitem__((0, 0), np.nan), "not finite"),
    (lambda p: p.T_ecm_needle.__setitem__((0, 1), 0.2), "not a rigid"),
    (lambda p: setattr(p, "T_world_needle", np.diag([1.0, 1.0, -1.0, 1.0])), "not a rigid"),  # det -1
    (lambda p: setattr(p, "covariance", -np.eye(6)), "not positive semi-definite"),
    (lambda p: setattr(p, "covariance", np.triu(np.ones((6, 6)))), "not symmetric"),
    (lambda p: setattr(p, "model_sigma_m", -1e-4), "model_sigma_m"),
    (lambda p: setattr(p, "model_sigma_rad", float("nan")), "model_sigma_rad"),
    (lambda p: setattr(p, "end_identity", 1.5), "end_identity"),
])
def test_the_pose_invariant_holds_back_a_bad_pose_at_publish(change, why, caplog):
    from nodes.fusion import FusionNode
    node = FusionNode.offline({}, wired=["pose"])
    good = PoseEstimate(1, 0, "x", T_NEEDLE.copy(), covariance=np.eye(6) * 1e-6)
    node.publish("pose", good)
    bad = PoseEstimate(2, 0, "x", T_NEEDLE.copy())
    change(bad)
    node.publish("pose", bad)
    assert [m.seq for _, m in node.published] == [1]
    assert node.counters["invalid_pose"] == 1 and why in caplog.text


def test_pnp_average_with_a_keypoint_at_the_image_edge_publishes_no_far_pose():
    from nodes.epnp import EpnpNode
    node = _stereo_pose_node(EpnpNode, method="average")
    for l, r, e in _frames(range(5), epoch=None):
        l.uv[4, 0] = r.uv[4, 0] = 0.0                   # keypoint E at u = 0 in both cameras
        feed(node, "ecm", e), feed(node, "left", l), feed(node, "right", r)
    for _, m in node.published:
        assert np.linalg.norm(m.T_ecm_needle[:3, 3]) <= 1.0
    assert len(node.published) + node.counters["invalid_pose"] + sum(
        v for k, v in node.counters.items() if k.startswith("no_pose.")) == 5


# ====================================================================== defect 6: YAML bomb

BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8))


def test_a_yaml_bomb_is_refused_quickly(tmp_path):
    (tmp_path / "dataset.yaml").write_text(BOMB)
    (tmp_path / "frames.jsonl").write_text("")
    with pytest.raises(DatasetError, match="expands to more than"):
        Dataset(tmp_path)
    with pytest.raises(GraphError, match="expands to more than"):
        load_graph(BOMB + "graph: x\n")


# ====================================================================== defects 8 and 11: files

def _dataset(tmp_path, n=2):
    from test_dataset import _write
    _write(tmp_path, n)
    return tmp_path


def test_empty_huge_and_inflating_image_files_are_refused_before_reading(tmp_path):
    import cv2
    ds_path = _dataset(tmp_path)
    ds = Dataset(ds_path)
    left = ds_path / ds[0].image("left")
    right = ds_path / ds[0].image("right")
    left.write_bytes(b"")
    with open(right, "wb") as f:           # a sparse 2 GB file: takes no disk
        f.truncate(2 << 30)
    rep = check_dataset(Dataset(ds_path))
    assert any("image file is empty" in e for e in rep.errors), rep.errors
    assert any("over the limit" in e for e in rep.errors), rep.errors
    # a small PNG whose header claims 16000x16000: refused from the header, never inflated
    ok, png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))
    png = bytearray(png.tobytes())
    png[16:24] = (16000).to_bytes(4, "big") * 2
    left.write_bytes(bytes(png))
    with pytest.raises(DatasetError, match="header says 16000x16000"):
        Dataset(ds_path).image(0, "left")
    w, h = ds.meta.image_size
    with pytest.raises(MessageError, match="header says 16000x16000"):
        decode(encode(CameraImage("left", 0, 0, w, h, "png", bytes(png))))


def test_symlinks_out_of_the_folder_and_non_files_are_named(tmp_path):
    ds_path = _dataset(tmp_path / "ds")
    rel = Dataset(ds_path)[0].image("left")
    outside = tmp_path / "secret.jpg"
    outside.write_bytes((ds_path / rel).read_bytes())
    (ds_path / rel).unlink()
    (ds_path / rel).symlink_to(outside)
    with pytest.raises(DatasetError, match="leads out of the folder"):
        Dataset(ds_path)
    (ds_path / rel).unlink()
    (ds_path / rel).mkdir()
    with pytest.raises(DatasetError, match="is a directory"):
        Dataset(ds_path)
    (ds_path / rel).rmdir()
    os.mkfifo(ds_path / rel)
    with pytest.raises(DatasetError, match="is a FIFO"):
        Dataset(ds_path)


def test_dataset_check_fails_a_folder_with_no_frames(tmp_path):
    ds_path = _dataset(tmp_path, n=1)
    (ds_path / "frames.jsonl").write_text("")
    rep = check_dataset(Dataset(ds_path))
    assert not rep.ok and any("no frames" in e for e in rep.errors)


# ====================================================================== defect 9: cycles

def test_validate_reports_a_cycle_and_allows_declared_feedback():
    cyc = {"graph": "g", "nodes": [
        {"id": "a", "module": "relay", "inputs": {"in": "b/out"}},
        {"id": "b", "module": "relay", "inputs": {"in": "a/out"}}]}
    errs = validate_graph(cyc)
    assert any("cycle a -> b -> a" in e for e in errs), errs
    fb = {"graph": "g", "nodes": [
        {"id": "camera", "module": "replay", "params": {"path": "x", "rate": "paced"},
         "inputs": {"ack": "det/left"}},
        {"id": "det", "module": "detector", "inputs": {"left": "camera/left"}, "outputs": ["left"]}]}
    assert validate_graph(fb) == []
    cyc["nodes"][0]["feedback"] = ["in"]                  # a declared feedback edge in the graph
    assert validate_graph(cyc) == []


# ====================================================================== defect 10: model files

def test_a_pickle_model_file_is_refused_as_a_configuration_error(tmp_path):
    import pickle

    from common.runtime.node import NodeError
    from nodes.detector import DetectorNode

    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))
    path = tmp_path / "model.pt"
    path.write_bytes(pickle.dumps({"format": Evil()}))
    with pytest.raises(NodeError, match="refused: the file holds pickled Python objects") as exc:
        DetectorNode.offline({"backend": "learned", "weights": str(path)})
    assert "truncated" not in str(exc.value)


# ====================================================================== real processes

def _pose_graph(run_graph, tmp_path):
    _multiview_dataset(tmp_path / "ds", n_frames=10)
    stereo = {"left": "detector/left", "right": "detector/right", "calib": "camera/calib", "ecm": "ecm/pose"}
    return run_graph({"nodes": [
        {"id": "camera", "module": "replay", "outputs": ["left", "right", "joints", "truth", "calib", "eos"],
         "params": {"path": str(tmp_path / "ds"), "rate": 20, "loop": True}},
        {"id": "detector", "module": "detector", "params": {"backend": "oracle", "noise_px": 0.2, "seed": 1},
         "inputs": {"left": "camera/left", "right": "camera/right", "truth": "camera/truth",
                    "calib": "camera/calib"}, "outputs": ["left", "right"]},
        {"id": "ecm", "module": "ecm", "inputs": {"joints": "camera/joints", "calib": "camera/calib"},
         "outputs": ["pose"]},
        {"id": "triangulate", "module": "triangulate", "inputs": stereo, "outputs": ["pose", "points"]},
        {"id": "fusion", "module": "fusion", "inputs": {"pose": "triangulate/pose", "ecm": "ecm/pose",
                                                        "truth": "camera/truth"}, "outputs": ["pose"]},
    ]}, timeout=90)


@pytest.mark.graph
def test_kill_9_of_the_camera_poses_resume_from_its_first_frames(run_graph, tmp_path):
    """Defect 1: the restarted camera counts from seq 0 again; every node must follow it at
    once (before: every pose waited until the new seq passed the old one)."""
    g = _pose_graph(run_graph, tmp_path)
    old = g.collect("fusion/pose", n=1, timeout=90, where=lambda m: m.seq >= 40)[0]
    tri, fus = g.subscribe("triangulate/pose"), g.subscribe("fusion/pose")
    pid = g.pids()["camera"]
    os.kill(pid, signal.SIGKILL)
    g.wait_stats("camera", lambda st: st.pid != pid, timeout=60)
    new = lambda m: m.epoch != old.epoch and m.seq < 20     # noqa: E731
    tri.wait(3, timeout=60, where=new)
    fus.wait(3, timeout=60, where=new)
    assert all(m.T_world_needle is None or np.isfinite(m.T_world_needle).all() for m in tri.messages + fus.messages)
    st = g.stats("triangulate")
    assert st.counters["stream_resets"] >= 1 and st.counters["handler_errors"] == 0


@pytest.mark.graph
def test_poison_messages_neither_crash_nor_stall_a_graph(run_graph, tmp_path):
    """Defects 2, 4, 5 in real processes: far-future seq, inf image size, ragged truth, NaN ECM
    pose, empty JPEG, a foreign epoch; no node restarts, poses go on, none is non-finite."""
    g = _pose_graph(run_graph, tmp_path)
    g.collect("fusion/pose", n=2, timeout=90)
    uv = np.full((5, 2), 100.0)
    calib = Calibration(0, np.array([np.inf, 1080.0]), CALIB.cameras, CALIB.needle, CALIB.ecm)
    ragged = raw(GroundTruth, {"seq": 3, "stamp_ns": 0, "keypoints": {"left": [[1.0, 2.0], [3.0]]}})
    for _ in range(3):
        for cam in ("left", "right"):
            g.put(f"detector/{cam}", Keypoints(cam, 2 ** 62, 0, True, uv, np.ones(5), 1.0))
            g.put(f"detector/{cam}", Keypoints(cam, 5, 0, True, uv, np.ones(5), 1.0, epoch=12345))
            g.put(f"camera/{cam}", CameraImage(cam, 2 ** 62, 0, 1920, 1080, "jpeg", b""))
        g.put("camera/calib", calib)
        g.put("camera/truth", ragged)
        g.put("ecm/pose", EcmPose(2 ** 40, 0, np.full((4, 4), np.nan)))
        g.put("triangulate/pose", PoseEstimate(2 ** 40, 0, "x", np.full((4, 4), 1e300)))
        time.sleep(0.2)
    sub = g.subscribe("fusion/pose")
    tri = g.subscribe("triangulate/pose")
    sub.wait(10, timeout=90)
    tri.wait(10, timeout=90)
    assert all(np.isfinite(m.T_ecm_needle).all() and np.linalg.norm(m.T_ecm_needle[:3, 3]) < 1
               and (m.T_world_needle is None or np.isfinite(m.T_world_needle).all())
               for m in sub.messages + tri.messages)
    assert all(r["restarts"] == 0 for r in g.status()["nodes"])
    for node in ("detector", "ecm", "triangulate", "fusion"):
        c = g.stats(node).counters
        assert c["handler_errors"] == 0 and c["decode_errors"] > 0, (node, c)


def test_a_transform_with_huge_elements_is_refused_without_an_overflow_warning():
    """A fuzzed 4x4 of 1e300s is named not rigid, and numpy warns of no overflow on the way."""
    import warnings

    from common.runtime.checks import rigid_error
    T = np.eye(4)
    T[:3, :3] = 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert "not a rigid transform" in rigid_error(T, "PoseEstimate.T_ecm_needle")
