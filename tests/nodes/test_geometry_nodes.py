"""The geometry nodes (detector/oracle, epnp, triangulate, ecm, fusion): offline, message in,
message out, matching the library functions; bad input counted, never a wrong pose."""
import numpy as np
import pytest

from common.bench.geometry_bench import multiview_scenario
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.oracle import Oracle, random_needle_pose
from common.geometry.pnp import pnp_average, pnp_joint
from common.geometry.transforms import inv_T, make_T, pose_error, rotvec_to_R
from common.geometry.triangulation import triangulation_pose
from common.runtime.messages import (
    Calibration,
    CameraImage,
    Command,
    EcmJoints,
    EcmPose,
    GroundTruth,
    Keypoints,
    Points3D,
    PoseEstimate,
    decode,
    encode,
)
from nodes.detector import DetectorNode
from nodes.ecm import EcmNode
from nodes.epnp import EpnpNode
from nodes.fusion import FusionNode
from nodes.triangulate import TriangulateNode

RIG = StereoRig.default()
MODEL = NeedleModel()
P = MODEL.keypoints()
ARM = EcmArm(make_T(rotvec_to_R([0, 0, 0.2]), [0.1, 0.0, 0.3]), 0.01, 0.02)
CALIB = Calibration(0, np.array([1920, 1080]), RIG.to_dict(), MODEL.to_dict(), ARM.to_dict())


def roundtrip(msg):
    """What a node receives: the message after encoding and decoding."""
    return decode(encode(msg), type(msg))


def outputs(node, name):
    return [m for o, m in node.published if o == name]


def frame(seq, T_ecm_needle, q=(0.0, 0.0, 0.05, 0.0)):
    T_world_ecm = ARM.T_world_ecm(q)
    truth = GroundTruth(seq, seq * 1000, sequence=0, step=seq, ecm_joints=np.array(q),
                        T_world_ecm=T_world_ecm, T_world_needle=T_world_ecm @ T_ecm_needle)
    return truth, EcmJoints(seq, seq * 1000, np.array(q, dtype=float))


def detect(truths, noise_px=0.0, seed=0):
    """Keypoints from the detector node (oracle backend) run on ground truth alone."""
    det = DetectorNode.offline({"backend": "oracle", "noise_px": noise_px, "seed": seed},
                               wired=["truth", "calib"])
    det.on_calib(roundtrip(CALIB))
    for t in truths:
        det.on_truth(roundtrip(t))
    return outputs(det, "left"), outputs(det, "right")


def test_detector_oracle_matches_the_library_and_needs_no_image():
    rng = np.random.default_rng(0)
    T = random_needle_pose(rng, RIG, MODEL)
    truth, _ = frame(7, T)
    left, right = detect([truth], noise_px=0.7, seed=3)
    uv, sc = Oracle(noise_px=0.7, seed=3).stereo(RIG, T, MODEL, seq=7)
    assert np.allclose(left[0].uv, uv["left"]) and np.allclose(right[0].uv, uv["right"])
    assert left[0].seq == 7 and left[0].stamp_ns == 7000 and left[0].detector == "oracle"
    # with images wired: an image triggers detection; a corrupt image is never decoded by the oracle
    det = DetectorNode.offline({"backend": "oracle"})
    det.on_calib(CALIB)
    bad = CameraImage("left", 7, 7000, 4, 4, "png", b"not a png")
    det.on_left(bad)                                   # truth not here yet: waits
    assert det.published == []
    det.on_truth(truth)
    (out, kp), = det.published
    assert out == "left" and kp.found and np.allclose(kp.uv, Oracle().stereo(RIG, T, MODEL, 7)[0]["left"])


def test_detector_waits_bounded_and_counts():
    det = DetectorNode.offline({"backend": "oracle", "max_wait": 3})
    img = CameraImage("right", 1, 0, 2, 2, "bgr8", bytes(12))
    det.on_right(img)                                  # no calibration yet, no truth yet
    for s in range(2, 6):
        det.on_right(CameraImage("right", s, 0, 2, 2, "bgr8", bytes(12)))
    assert det.counters["superseded"] == 4            # only the newest image waits for the calibration
    det.on_calib(CALIB)
    for s in range(6, 10):
        det.on_right(CameraImage("right", s, 0, 2, 2, "bgr8", bytes(12)))
    kps = outputs(det, "right")
    assert kps and all(not k.found for k in kps)     # gave up waiting for truth: not found
    with pytest.raises(Exception):
        DetectorNode.offline({"backend": "no-such-backend"})


def test_ecm_node_from_params_and_from_calibration():
    q = np.array([0.1, -0.05, 0.08, 0.3])
    node = EcmNode.offline({}, wired=["joints", "calib"])
    node.on_joints(EcmJoints(1, 10, q))
    assert node.published == [] and node.counters["no_pose.no_calibration"] == 1
    node.on_calib(roundtrip(CALIB))
    node.on_joints(roundtrip(EcmJoints(2, 20, q)))
    (out, pose), = node.published
    assert out == "pose" and pose.seq == 2 and np.allclose(pose.T_world_ecm, ARM.T_world_ecm(q))
    assert np.allclose(pose.T_world_left, ARM.T_world_ecm(q) @ RIG.left.T_ecm_cam)
    roundtrip(pose)
    base = make_T(rotvec_to_R([0.3, 0, 0]), [0, 1, 2])
    node = EcmNode.offline({"T_world_base": base.tolist(), "L_rcc": 0.0}, wired=["joints"])
    node.on_joints(EcmJoints(3, 30, q))
    assert np.allclose(node.published[0][1].T_world_ecm, EcmArm(base).T_world_ecm(q))
    with pytest.raises(ValueError, match="rigid"):
        EcmNode.offline({"T_world_base": np.eye(4).tolist()[:3]})
    with pytest.raises(ValueError):
        EcmNode.offline({"T_world_base": (2 * np.eye(4)).tolist()})


@pytest.mark.parametrize("method", ["joint", "average"])
def test_epnp_node_matches_the_library(method):
    rng = np.random.default_rng(1)
    truths = [frame(s, random_needle_pose(rng, RIG, MODEL))[0] for s in range(4)]
    left, right = detect(truths, noise_px=0.5, seed=1)
    node = EpnpNode.offline({"method": method}, wired=["left", "right", "calib", "ecm"])
    node.on_calib(roundtrip(CALIB))
    for t in truths:
        node.on_ecm(roundtrip(EcmPose(t.seq, t.stamp_ns, t.T_world_ecm)))
    for l, r in zip(left, right):
        node.on_right(roundtrip(r))                   # order within a frame does not matter
        node.on_left(roundtrip(l))
    poses = outputs(node, "pose")
    assert [p.seq for p in poses] == [0, 1, 2, 3]
    f = pnp_joint if method == "joint" else pnp_average
    for p, l, r, t in zip(poses, left, right, truths):
        ref = f({"left": l.uv, "right": r.uv}, RIG, P, {"left": l.scores, "right": r.scores})
        assert np.allclose(p.T_ecm_needle, ref.T_ecm_needle, atol=1e-9)
        assert p.method == f"pnp_{method}" and p.residual_unit == "px"
        assert p.residual == pytest.approx(ref.rms_px)
        assert np.allclose(p.T_world_needle, t.T_world_ecm @ p.T_ecm_needle)
        assert (p.covariance is not None) == (method == "joint")
        roundtrip(p)


def test_epnp_joint_covariance_takes_the_stated_keypoint_noise():
    """The fit's residuals miss the errors both cameras share: a detector's stated
    ``keypoint_sigma_px`` (or the ``min_sigma_px`` param) floors the covariance's noise."""
    from dataclasses import replace
    rng = np.random.default_rng(2)
    truths = [frame(s, random_needle_pose(rng, RIG, MODEL))[0] for s in range(2)]
    left, right = detect(truths, noise_px=0.1, seed=2)

    def covariances(params, sigma=None):
        node = EpnpNode.offline({"method": "joint", **params}, wired=["left", "right", "calib"])
        node.on_calib(roundtrip(CALIB))
        for l, r in zip(left, right):
            node.on_left(roundtrip(replace(l, keypoint_sigma_px=sigma)))
            node.on_right(roundtrip(replace(r, keypoint_sigma_px=sigma)))
        return [p.covariance for p in outputs(node, "pose")]

    base, stated, param = covariances({}), covariances({}, 1.0), covariances({"min_sigma_px": 1.0})
    for l, r, c0, c1, c2 in zip(left, right, base, stated, param):
        ref = pnp_joint({"left": l.uv, "right": r.uv}, RIG, P, {"left": l.scores, "right": r.scores},
                        min_sigma_px=1.0)
        assert np.allclose(c1, ref.covariance, rtol=1e-9) and np.allclose(c2, c1, rtol=1e-9)
        # 0.1 px of noise: the residual variance is below both floors, so the ratio is theirs
        assert np.allclose(c1, c0 * (1.0 / 0.25) ** 2, rtol=1e-9)
    for bad in (0, "abc", None, float("inf")):
        with pytest.raises(ValueError, match="min_sigma_px"):
            EpnpNode.offline({"method": "joint", "min_sigma_px": bad}, wired=["left", "right", "calib"])


def test_a_pose_waits_for_its_ecm_pose():
    rng = np.random.default_rng(5)
    truths = [frame(s, random_needle_pose(rng, RIG, MODEL))[0] for s in range(3)]
    left, right = detect(truths)
    node = EpnpNode.offline({"method": "joint", "max_wait": 2}, wired=["left", "right", "calib", "ecm"])
    node.on_calib(CALIB)
    node.on_left(left[0])
    node.on_right(right[0])
    assert outputs(node, "pose") == []                       # computed, waiting for the ECM pose
    node.on_ecm(EcmPose(0, 0, truths[0].T_world_ecm))
    p, = outputs(node, "pose")
    assert np.allclose(p.T_world_needle, truths[0].T_world_needle, atol=1e-9)
    node.on_left(left[1])
    node.on_right(right[1])                                  # its ECM pose never comes
    node.on_left(left[2])
    node.on_right(right[2])
    assert len(outputs(node, "pose")) == 1
    node.on_left(Keypoints.not_found("left", 3, 0, "oracle", "x"))   # frame 3: seq 1 is now stale
    assert [q.seq for q in outputs(node, "pose")] == [0, 1]
    assert outputs(node, "pose")[1].T_world_needle is None and node.counters["no_ecm_pose"] == 1


def test_epnp_node_counts_no_pose_and_never_publishes_one():
    node = EpnpNode.offline({"method": "joint"}, wired=["left", "right", "calib"])
    kp = Keypoints("left", 0, 0, True, np.full((5, 2), 100.0), np.ones(5), 1.0)
    node.on_left(kp)
    node.on_right(Keypoints("right", 0, 0, True, np.full((5, 2), 100.0), np.ones(5), 1.0))
    assert node.counters["no_pose.no_calibration"] == 1
    node.on_calib(CALIB)
    cases = [
        (np.full((5, 2), 100.0), "coincident"),
        (np.stack([np.linspace(100, 400, 5), np.linspace(100, 200, 5)], 1), "collinear"),
        (np.array([[1, 2], [3, 4], [5, 6], [np.nan, 0], [np.nan, np.nan]], float), "too_few_points"),
    ]
    for seq, (uv, reason) in enumerate(cases, start=1):
        node.on_left(Keypoints("left", seq, 0, True, uv, np.ones(5), 1.0))
        node.on_right(Keypoints("right", seq, 0, True, uv, np.ones(5), 1.0))
        assert node.counters[f"no_pose.{reason}"] == 1, reason
    node.on_left(Keypoints.not_found("left", 9, 0, "oracle", "x"))
    node.on_right(Keypoints.not_found("right", 9, 0, "oracle", "x"))
    assert node.counters["no_pose.too_few_points"] == 2
    assert outputs(node, "pose") == []
    with pytest.raises(ValueError, match="method"):
        EpnpNode.offline({"method": "median"})


def test_triangulate_node_matches_the_library_and_publishes_points():
    rng = np.random.default_rng(2)
    truths = [frame(s, random_needle_pose(rng, RIG, MODEL))[0] for s in range(3)]
    left, right = detect(truths, noise_px=0.3, seed=2)
    node = TriangulateNode.offline({}, wired=["left", "right", "calib"])
    node.on_calib(roundtrip(CALIB))
    for l, r in zip(left, right):
        node.on_left(roundtrip(l))
        node.on_right(roundtrip(r))
    poses, pts = outputs(node, "pose"), outputs(node, "points")
    assert len(poses) == 3 and len(pts) == 3
    for p, q, l, r in zip(poses, pts, left, right):
        ref = triangulation_pose({"left": l.uv, "right": r.uv}, RIG, P, {"left": l.scores, "right": r.scores})
        assert np.allclose(p.T_ecm_needle, ref.T_ecm_needle, atol=1e-12)
        assert p.method == "triangulation" and p.residual_unit == "m" and p.T_world_needle is None
        assert isinstance(q, Points3D) and q.valid.all() and np.allclose(q.points_ecm, ref.points_ecm)
        roundtrip(p), roundtrip(q)
    # three usable points: the points go out, the pose does not
    l, r = left[0], right[0]
    uv = l.uv.copy()
    uv[:2] = np.nan
    node.on_left(Keypoints("left", 50, 0, True, uv, np.ones(5), 1.0))
    node.on_right(Keypoints("right", 50, 0, True, r.uv, np.ones(5), 1.0))
    assert node.counters["no_pose.too_few_points"] == 1
    assert outputs(node, "points")[-1].valid.sum() == 3 and len(outputs(node, "pose")) == 3


def test_fusion_node_maps_views_through_the_ecm_and_resets_on_sequence():
    rng = np.random.default_rng(3)
    T_wn, T_we, T_en = multiview_scenario(rng, RIG, MODEL, ARM)
    node = FusionNode.offline({}, wired=["pose", "ecm", "truth"])
    for s, (T_w, T_e) in enumerate(zip(T_we, T_en)):
        node.on_pose(PoseEstimate(s, s, "pnp_joint", T_e))           # before its ECM pose and truth
        assert len(outputs(node, "pose")) == s
        node.on_ecm(EcmPose(s, s, T_w))
        node.on_truth(GroundTruth(s, s, sequence=4))
    fused = outputs(node, "pose")
    assert [p.n_views for p in fused] == [1, 2, 3, 4, 5]
    last = fused[-1]
    assert last.method == "multiview" and last.sequence == 4 and last.residual_unit == "m"
    assert np.allclose(last.T_ecm_needle, T_en[-1], atol=1e-12)
    assert np.allclose(last.T_world_needle, T_wn, atol=1e-12)
    roundtrip(last)
    # a new sequence starts a new queue
    node.on_truth(GroundTruth(5, 5, sequence=5))
    node.on_ecm(EcmPose(5, 5, T_we[-1]))
    node.on_pose(PoseEstimate(5, 5, "pnp_joint", T_en[-1]))
    assert outputs(node, "pose")[-1].n_views == 1 and node.counters["resets"] == 1
    node.on_command(Command("reset"))
    assert len(node.fusion) == 0


def test_fusion_node_does_not_fuse_the_frames_of_a_moving_take():
    rng = np.random.default_rng(4)
    T_wn, T_we, T_en = multiview_scenario(rng, RIG, MODEL, ARM)
    node = FusionNode.offline({}, wired=["pose", "ecm", "truth"])
    for s, (T_w, T_e) in enumerate(zip(T_we, T_en)):
        node.on_ecm(EcmPose(s, s, T_w))
        node.on_truth(GroundTruth(s, s, sequence=4, needle_at_rest=False))
        node.on_pose(PoseEstimate(s, s, "pnp_joint", T_e))
    fused = outputs(node, "pose")
    assert [p.n_views for p in fused] == [1] * len(T_en)
    assert node.counters["resets.moving_needle"] == len(T_en)


def test_fusion_node_drops_estimates_whose_ecm_pose_never_comes():
    node = FusionNode.offline({"max_wait": 2}, wired=["pose", "ecm"])
    T = make_T(np.eye(3), [0, 0, -0.15])
    node.on_pose(PoseEstimate(0, 0, "pnp_joint", T))
    node.on_ecm(EcmPose(1, 1, np.eye(4)))
    node.on_pose(PoseEstimate(1, 1, "pnp_joint", T))
    node.on_ecm(EcmPose(2, 2, np.eye(4)))
    node.on_pose(PoseEstimate(2, 2, "pnp_joint", T))
    assert node.counters["no_pose.no_ecm_pose"] == 1
    assert [p.seq for p in outputs(node, "pose")] == [1, 2]


def test_fusion_node_uses_the_estimate_own_ecm_pose():
    node = FusionNode.offline({}, wired=["pose"])
    T = make_T(np.eye(3), [0, 0, -0.15])
    Tw = make_T(rotvec_to_R([0, 0.1, 0]), [0.01, 0, 0])
    node.on_pose(PoseEstimate(0, 0, "pnp_joint", T, T_world_ecm=Tw))
    p, = outputs(node, "pose")
    assert np.allclose(p.T_world_needle, Tw @ T)


def test_pipeline_offline_end_to_end_five_views():
    """detector -> epnp (joint) -> fusion with the ecm node, on a 5-view oracle sequence."""
    rng = np.random.default_rng(4)
    arm_calib = CALIB
    ecm = EcmNode.offline({}, wired=["joints", "calib"])
    ecm.on_calib(arm_calib)
    epnp = EpnpNode.offline({"method": "joint"}, wired=["left", "right", "calib", "ecm"])
    epnp.on_calib(arm_calib)
    fusion = FusionNode.offline({}, wired=["pose", "ecm"])
    T_wn = ARM.T_world_ecm([0, 0, 0.05, 0]) @ random_needle_pose(rng, RIG, MODEL, max_offaxis=0.2)
    truths = []
    for s in range(5):
        q = np.array([-0.1 + 0.05 * s, 0.0, 0.05, 0.0])
        T_w = ARM.T_world_ecm(q)
        truths.append(GroundTruth(s, s, sequence=0, step=s, ecm_joints=q, T_world_ecm=T_w, T_world_needle=T_wn))
        ecm.on_joints(EcmJoints(s, s, q))
    for out, pose in ecm.published:
        epnp.on_ecm(roundtrip(pose))
        fusion.on_ecm(roundtrip(pose))
    left, right = detect(truths)
    for l, r in zip(left, right):
        epnp.on_left(l)
        epnp.on_right(r)
    for out, pose in epnp.published:
        fusion.on_pose(roundtrip(pose))
    fused = outputs(fusion, "pose")
    assert len(fused) == 5 and fused[-1].n_views == 5
    T_en_last = inv_T(truths[-1].T_world_ecm) @ T_wn
    dt, dr = pose_error(fused[-1].T_ecm_needle, T_en_last)
    assert dt < 1e-6 and dr < np.deg2rad(1e-4)


# ---------------------------------------------------------------------- in a launched graph

def _multiview_dataset(folder, n_frames=10):
    """A still needle, the ECM yawing 0.05 rad per frame (back and forth), as a dataset folder."""
    from common.data.check import project_keypoints
    from common.data.dataset import DatasetMeta, Frame
    from common.data.writer import DatasetWriter
    w, h = 1920, 1080
    meta = DatasetMeta((w, h), StereoRig.default(w, h), MODEL, ARM, "geometry graph test")
    img = np.full((h, w, 3), 90, np.uint8)
    rng = np.random.default_rng(11)
    T_wn = ARM.T_world_ecm([0, 0, 0.05, 0]) @ random_needle_pose(rng, RIG, MODEL, max_offaxis=0.15)
    with DatasetWriter(folder, meta) as wr:
        for i in range(n_frames):
            k = i % 8 if i % 8 < 5 else 8 - i % 8          # 0 1 2 3 4 3 2 1 0 ...
            q = np.array([-0.1 + 0.05 * k, 0.0, 0.05, 0.0])
            paths = wr.write_images(i, {"left": img, "right": img})
            T_we = ARM.T_world_ecm(q)
            wr.append(Frame(index=i, stamp_ns=i * 100_000_000, left=paths["left"], right=paths["right"],
                            sequence=0, step=i, ecm_joints=q, T_world_ecm=T_we, T_world_needle=T_wn,
                            keypoints=project_keypoints(meta, T_we, T_wn)))
    return T_wn


@pytest.mark.graph
def test_nodes_in_a_launched_graph_match_the_library(run_graph, tmp_path):
    T_wn = _multiview_dataset(tmp_path / "ds")
    stereo = {"left": "detector/left", "right": "detector/right", "calib": "camera/calib", "ecm": "ecm/pose"}
    g = run_graph({"nodes": [
        {"id": "camera", "module": "replay", "outputs": ["left", "right", "joints", "truth", "calib", "eos"],
         "params": {"path": str(tmp_path / "ds"), "rate": 10, "loop": True}},
        {"id": "detector", "module": "detector", "params": {"backend": "oracle", "noise_px": 0.3, "seed": 2},
         "inputs": {"left": "camera/left", "right": "camera/right", "truth": "camera/truth",
                    "calib": "camera/calib"}, "outputs": ["left", "right"]},
        {"id": "ecm", "module": "ecm", "inputs": {"joints": "camera/joints", "calib": "camera/calib"},
         "outputs": ["pose"]},
        {"id": "epnp_joint", "module": "epnp", "params": {"method": "joint"}, "inputs": stereo, "outputs": ["pose"]},
        {"id": "epnp_average", "module": "epnp", "params": {"method": "average"}, "inputs": stereo,
         "outputs": ["pose"]},
        {"id": "triangulate", "module": "triangulate", "inputs": stereo, "outputs": ["pose", "points"]},
        {"id": "fusion", "module": "fusion", "inputs": {"pose": "epnp_joint/pose", "ecm": "ecm/pose",
                                                        "truth": "camera/truth"}, "outputs": ["pose"]},
    ]}, timeout=90)
    subs = {k: g.subscribe(k) for k in ("detector/left", "detector/right", "ecm/pose", "epnp_joint/pose",
                                         "epnp_average/pose", "triangulate/pose", "triangulate/points",
                                         "fusion/pose")}
    fused = subs["fusion/pose"].wait(20, timeout=120)   # under load some lack 5 consecutive estimates
    kps = {(m.camera, m.seq): m for k in ("detector/left", "detector/right") for m in subs[k].messages}
    ecm = {m.seq: m for m in subs["ecm/pose"].messages}
    checked = 0
    for key, f in (("epnp_joint/pose", pnp_joint), ("epnp_average/pose", pnp_average),
                   ("triangulate/pose", triangulation_pose)):
        for p in subs[key].messages:
            if ("left", p.seq) not in kps or ("right", p.seq) not in kps:
                continue
            l, r = kps["left", p.seq], kps["right", p.seq]
            ref = f({"left": l.uv, "right": r.uv}, RIG, P, {"left": l.scores, "right": r.scores})
            assert np.allclose(p.T_ecm_needle, ref.T_ecm_needle, atol=1e-9), key
            if p.seq in ecm:
                assert np.allclose(p.T_world_needle, ecm[p.seq].T_world_ecm @ p.T_ecm_needle)
                assert pose_error(p.T_world_needle, T_wn)[0] < 0.02
            checked += 1
    assert checked >= 9
    for s, m in ecm.items():
        assert np.allclose(m.T_world_ecm, ARM.T_world_ecm(m.q), atol=1e-12)
    # the fused pose: the library's fusion of the same five joint estimates (the node sees every
    # one: its input keeps all; so do we, from the first one we saw on), each at its ECM pose
    from common.geometry.fusion import MultiViewFusion
    joints = sorted(subs["epnp_joint/pose"].messages, key=lambda m: m.seq)
    done = 0
    for fp in fused:
        prior = [p for p in joints if p.seq <= fp.seq][-5:]
        if len(prior) < 5 or prior[-1].seq != fp.seq or fp.n_views < 5:
            continue
        lib = MultiViewFusion(k=5)
        for p in prior:
            out = lib.add(p.T_ecm_needle, p.T_world_ecm, p.covariance)
        assert np.allclose(fp.T_ecm_needle, out.T_ecm_needle, atol=1e-9)
        assert fp.n_views == out.n_views and fp.method == "multiview" and fp.sequence == 0
        assert pose_error(fp.T_world_needle, T_wn)[0] < 0.01
        done += 1
    assert done >= 1
    for node in ("detector", "ecm", "epnp_joint", "epnp_average", "triangulate", "fusion"):
        st = g.stats(node)
        assert st.counters.get("handler_errors", 0) == 0 and st.counters.get("decode_errors", 0) == 0, node
