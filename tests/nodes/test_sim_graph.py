"""sim and replay publishing through a launched graph (real processes, Zenoh on loopback)."""
import pytest
import numpy as np

from common.data.check import project_keypoints
from common.data.dataset import DatasetMeta, Frame
from common.data.writer import DatasetWriter
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from common.runtime.messages import Calibration, CameraImage, EndOfStream, GroundTruth
from common.sim.randomise import default_arm

pytestmark = pytest.mark.graph


def test_sim_node_in_a_graph(run_graph):
    g = run_graph({"nodes": [{"id": "camera", "module": "sim", "outputs": ["left", "right", "joints", "truth", "calib"],
                              "params": {"width": 320, "height": 180, "rate_hz": 15, "motion": "sweep",
                                         "randomise": "none", "encoding": "jpeg"}}]}, timeout=60)
    calib = g.collect("camera/calib", 1, timeout=20, expect=Calibration)[0]
    lefts = g.subscribe("camera/left", CameraImage)
    truths = g.subscribe("camera/truth", GroundTruth)
    lefts.wait(3, timeout=30)
    tr = truths.wait(3, timeout=30)
    img = lefts.messages[0].to_bgr()
    assert img.shape == (180, 320, 3) and img.std() > 5  # a scene, not a blank image
    rig, needle = StereoRig.from_dict(calib.cameras, calib.image_size), NeedleModel.from_dict(calib.needle)
    t = tr[-1]
    p = transform_points(inv_T(t.T_world_ecm) @ t.T_world_needle, needle.keypoints())
    assert np.allclose(rig.left.project_from_ecm(p), t.keypoints["left"], atol=1e-9)
    # re-place the needle on command
    T = t.T_world_needle.copy()
    T[:3, 3] += [0.004, -0.003, 0.003]
    g.command("camera", "place_needle", T_world_needle=T.tolist())
    moved = truths.wait(len(truths.messages) + 1, timeout=30,
                        where=lambda m: np.allclose(m.T_world_needle, T))
    assert moved
    assert g.stats("camera").counters.get("handler_errors", 0) == 0


def _dataset(folder, n):
    w, h = 160, 90
    meta = DatasetMeta((w, h), StereoRig.default(w, h), NeedleModel(), default_arm(), "graph test")
    img = np.full((h, w, 3), 120, np.uint8)
    with DatasetWriter(folder, meta) as wr:
        for i in range(n):
            paths = wr.write_images(i, {"left": img, "right": img})
            q = np.array([0.0, 0.01 * i, 0.12, 0.0])
            T_we = meta.arm.T_world_ecm(q)
            T_wn = T_we @ make_T(rotvec_to_R([2.9, 0.1, 0.0]), [0.0, 0.0, -0.13])
            wr.append(Frame(index=i, stamp_ns=i * 50_000_000, left=paths["left"], right=paths["right"],
                            ecm_joints=q, T_world_ecm=T_we, T_world_needle=T_wn,
                            keypoints=project_keypoints(meta, T_we, T_wn)))


def test_replay_node_in_a_graph(run_graph, tmp_path):
    _dataset(tmp_path / "ds", 30)
    g = run_graph({"nodes": [{"id": "camera", "module": "replay",
                              "outputs": ["left", "right", "joints", "truth", "calib", "eos"],
                              "params": {"path": str(tmp_path / "ds"), "rate": "recorded"}}]}, timeout=60)
    lefts = g.subscribe("camera/left", CameraImage)
    truths = g.subscribe("camera/truth", GroundTruth)
    calib = g.subscribe("camera/calib", Calibration)
    eos = g.collect("camera/eos", 1, timeout=30, expect=EndOfStream)[0]
    assert eos.frames == 30
    lefts.wait(1, timeout=10, where=lambda m: m.seq == 29)
    seqs = [m.seq for m in lefts.messages]
    assert seqs and seqs == list(range(seqs[0], 30))  # every frame since we subscribed, in order
    assert lefts.messages[-1].encoding == "jpeg" and lefts.messages[-1].to_bgr().shape == (90, 160, 3)
    last = truths.wait(1, timeout=10, where=lambda m: m.seq == 29)[-1]  # other keys may lag the eos a little
    assert last.keypoints["right"].shape == (5, 2)
    assert calib.messages and np.allclose(StereoRig.from_dict(calib.messages[0].cameras, calib.messages[0].image_size).left.K, StereoRig.default(160, 90).left.K)
