"""The fusion node (nodes/fusion.py) told by the tracker whether the needle is at rest: views at
rest are fused as without it, a frame the tracker says is held or free passes alone, and without
the tracker the truth's take of a moving needle decides, as before (docs/tracking.md)."""
import numpy as np
import pytest

from common.bench.geometry_bench import multiview_scenario
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import retract
from common.geometry.transforms import inv_T, make_T, pose_error, rotvec_to_R
from common.runtime.messages import (
    EcmPose,
    EndOfStream,
    GroundTruth,
    InstrumentState,
    MessageError,
    NoPoseNotice,
    PoseEstimate,
    decode,
    encode,
)
from common.sim.motion import FPS, script_take
from nodes.fusion import FusionNode
from nodes.tracker import TrackerNode

RIG, NEEDLE = StereoRig.default(), NeedleModel()
ARM = EcmArm(make_T(rotvec_to_R([0, 0, 0.2]), [0.1, 0.0, 0.3]), 0.01, 0.02)
C = np.diag([np.radians(0.5) ** 2] * 3 + [0.2e-3 ** 2] * 2 + [0.6e-3 ** 2])   # ECM axes
WIRED = ["pose", "ecm", "truth", "motion"]


def views(seed, n=8):
    """``n`` noisy estimates with covariances of one needle at rest, seen from moving ECM poses."""
    rng = np.random.default_rng(seed)
    _, T_we, T_en = multiview_scenario(rng, RIG, NEEDLE, ARM, n_views=n)
    return T_we, [retract(T, rng.multivariate_normal(np.zeros(6), C)) for T in T_en]


def run(node, T_we, T_en, modes=None, at_rest=None):
    """Each frame's ECM pose, truth, estimate and (when ``modes``) the tracker's pose, in the
    order the graph may deliver them: the estimate first."""
    for s, (T_w, T_e) in enumerate(zip(T_we, T_en)):
        node.deliver("pose", wire(PoseEstimate(s, s, "pnp_joint", T_e, covariance=C)))
        node.deliver("ecm", wire(EcmPose(s, s, T_w)))
        node.deliver("truth", wire(GroundTruth(s, s, sequence=3, needle_at_rest=at_rest)))
        if modes is not None and modes[s] is not None:
            node.deliver("motion", wire(PoseEstimate(s, s, "tracked", T_e, covariance=C, mode=modes[s])))
    return [m for o, m in node.published if o == "pose"]


def wire(msg):
    return decode(encode(msg), type(msg))


def test_views_the_tracker_says_are_at_rest_are_fused_as_without_it():
    T_we, T_en = views(1)
    before = run(FusionNode.offline({}, wired=["pose", "ecm", "truth"]), T_we, T_en)
    node = FusionNode.offline({}, wired=WIRED)
    # the truth says the take moves: where the tracker runs, its mode decides, not the truth
    after = run(node, T_we, T_en, modes=["rest"] * len(T_en), at_rest=False)
    assert [p.n_views for p in before] == [1, 2, 3, 4, 5, 5, 5, 5]
    assert [p.n_views for p in after] == [p.n_views for p in before]
    for a, b in zip(after, before):
        assert np.array_equal(a.T_ecm_needle, b.T_ecm_needle) and np.array_equal(a.covariance, b.covariance)
    assert not any(k.startswith("resets.") for k in node.counters)


def test_a_frame_the_tracker_says_is_held_or_free_resets_and_passes_alone():
    T_we, T_en = views(2, n=10)
    modes = ["rest", "rest", "rest", "held", "held", "free", "rest", "rest", "rest", "rest"]
    node = FusionNode.offline({}, wired=WIRED)
    fused = run(node, T_we, T_en, modes=modes)
    assert [p.n_views for p in fused] == [1, 2, 3, 1, 1, 1, 1, 2, 3, 4]
    assert node.counters["resets.needle_moves"] == 3 and "resets.moving_needle" not in node.counters
    for s in (3, 4, 5):                                   # alone: the estimate itself
        assert np.allclose(fused[s].T_ecm_needle, T_en[s], atol=1e-12) and fused[s].residual == 0.0
    # the window after the move holds only views at rest since: the same as a fusion of those alone
    fresh = run(FusionNode.offline({}, wired=["pose", "ecm"]), T_we[6:], T_en[6:])
    assert np.allclose(fused[-1].T_ecm_needle, fresh[-1].T_ecm_needle, atol=1e-12)


def test_without_the_tracker_the_truth_of_a_moving_take_decides_as_before():
    T_we, T_en = views(3)
    node = FusionNode.offline({}, wired=["pose", "ecm", "truth"])
    fused = run(node, T_we, T_en, at_rest=False)
    assert [p.n_views for p in fused] == [1] * len(T_en)
    assert node.counters["resets.moving_needle"] == len(T_en) and "resets.needle_moves" not in node.counters
    node = FusionNode.offline({}, wired=["pose", "ecm", "truth"])
    assert [p.n_views for p in run(node, T_we, T_en, at_rest=True)] == [1, 2, 3, 4, 5, 5, 5, 5]


def test_an_estimate_waits_for_its_mode_and_a_frame_without_a_track_passes_alone():
    T_we, T_en = views(4, n=7)
    node = FusionNode.offline({"max_wait": 3}, wired=WIRED)
    for s in range(3):
        node.deliver("ecm", EcmPose(s, s, T_we[s]))
        node.deliver("truth", GroundTruth(s, s, sequence=3))
        node.deliver("pose", PoseEstimate(s, s, "pnp_joint", T_en[s], covariance=C))
    assert node.published == []                           # every frame waits for the tracker
    node.deliver("motion", PoseEstimate(0, 0, "tracked", T_en[0], covariance=C, mode="rest"))
    assert [m.seq for _, m in node.published] == [0]
    # the tracker stated frame 2, not 1: it had no track at frame 1 (it steps frames in order)
    node.deliver("motion", PoseEstimate(2, 2, "tracked", T_en[2], covariance=C, mode="rest"))
    assert [(m.seq, m.n_views) for _, m in node.published] == [(0, 1), (1, 1), (2, 1)]
    assert node.counters["resets.motion_unknown"] == 1
    # a mode that never comes: after max_wait frames the estimate goes on alone, counted
    for s in range(3, 7):
        node.deliver("ecm", EcmPose(s, s, T_we[s]))
        node.deliver("truth", GroundTruth(s, s, sequence=3))
        node.deliver("pose", PoseEstimate(s, s, "pnp_joint", T_en[s], covariance=C))
    assert [m.seq for _, m in node.published][3:] == [3]
    assert node.counters["no_motion"] == 1 and node.counters["resets.motion_unknown"] == 2
    # a pose on the input without a mode (not the tracker's) holds nothing up and fuses nothing
    node.deliver("motion", PoseEstimate(4, 4, "refined", T_en[4], covariance=C))
    assert [m.seq for _, m in node.published][4:] == [4] and node.counters["motion.no_mode"] == 1
    assert node.counters["resets.motion_unknown"] == 3


def test_a_frame_the_tracker_says_it_has_no_track_for_passes_alone_at_once():
    T_we, T_en = views(5, n=4)
    node = FusionNode.offline({"max_wait": 30}, wired=WIRED + ["untracked"])
    for s in range(3):
        node.deliver("ecm", EcmPose(s, s, T_we[s]))
        node.deliver("truth", GroundTruth(s, s, sequence=3))
        node.deliver("pose", PoseEstimate(s, s, "pnp_joint", T_en[s], covariance=C))
    node.deliver("untracked", wire(NoPoseNotice(0, 0, "tracked", "no_track")))
    assert [(m.seq, m.n_views) for _, m in node.published] == [(0, 1)]     # no later frame needed
    assert node.counters["resets.motion_unknown"] == 1 and "no_motion" not in node.counters
    # said for frame 2 only: frame 1 still waits for its mode, and frame 2 behind it (in order)
    node.deliver("untracked", wire(NoPoseNotice(2, 2, "tracked", "no_track")))
    assert [m.seq for _, m in node.published] == [0]
    node.deliver("motion", wire(PoseEstimate(1, 1, "tracked", T_en[1], covariance=C, mode="rest")))
    assert [(m.seq, m.n_views) for _, m in node.published] == [(0, 1), (1, 1), (2, 1)]
    assert node.counters["resets.motion_unknown"] == 2 and "no_motion" not in node.counters
    # the tracker's own output feeds it: frames before its first measurement have no track
    tracker = TrackerNode.offline(wired=["pose", "ecm", "no_pose"])
    for s in range(2):
        tracker.deliver("ecm", EcmPose(s, s, T_we[s]))
        tracker.deliver("no_pose", NoPoseNotice(s, s, "refined", "too_few_points"))
    assert [(o, m.seq, m.reason) for o, m in tracker.published] == [("no_pose", 0, "no_track"), ("no_pose", 1, "no_track")]


def test_the_mode_travels_on_the_tracked_pose_and_older_payloads_decode():
    T = make_T(np.eye(3), [0, 0, 0.1])
    for mode in ("rest", "held", "free", None):
        assert wire(PoseEstimate(1, 2, "tracked", T, mode=mode)).mode == mode
    with pytest.raises(MessageError, match="PoseEstimate.mode"):
        wire(PoseEstimate(1, 2, "tracked", T, mode="flying"))
    # a payload of a writer that has no mode field decodes, without one
    import msgpack
    raw = msgpack.unpackb(encode(PoseEstimate(1, 2, "tracked", T, mode="held")), raw=False, strict_map_key=False)
    raw["body"].pop("mode")
    assert "mode" not in raw["body"]
    assert decode(msgpack.packb(raw, use_bin_type=True)).mode is None


def test_the_tracker_s_modes_over_a_pickup_keep_the_fusion_to_the_needle_at_rest():
    """The tracker node on a scripted pickup (the needle on the pad, grasped, lifted): the fusion
    of the same refined poses, told the tracker's mode, fuses the frames before the grasp and
    passes every held frame alone."""
    take = script_take("pickup", np.random.default_rng(1), NEEDLE, NEEDLE.wire_diameter_m / 2).frames
    take = take[:120]
    T_world_ecm = make_T(np.diag([1.0, -1.0, -1.0]), take[0].T_world_needle[:3, 3] + [0.0, 0.0, 0.12])
    tracker = TrackerNode.offline()
    fusion = FusionNode.offline({}, wired=["pose", "ecm", "motion"])
    rng = np.random.default_rng(0)
    dt_ns = int(round(1e9 / FPS))
    for k, fr in enumerate(take):
        for name, (T, jaw, holds) in fr.instruments.items():
            tracker.deliver("instruments", InstrumentState(name, k, k * dt_ns, T, jaw, holds))
        ecm = EcmPose(k, k * dt_ns, T_world_ecm)
        tracker.deliver("ecm", ecm)
        fusion.deliver("ecm", ecm)
        pose = PoseEstimate(k, k * dt_ns, "refined", retract(inv_T(T_world_ecm) @ fr.T_world_needle,
                                                             rng.multivariate_normal(np.zeros(6), C)), covariance=C)
        tracker.deliver("pose", pose)
        fusion.deliver("pose", pose)
        for out, m in tracker.published:
            if out == "pose":
                fusion.deliver("motion", wire(m))
        tracker.published.clear()
    tracker.deliver("eos", EndOfStream(len(take), 0))
    for out, m in tracker.published:
        if out == "pose":
            fusion.deliver("motion", wire(m))
    modes = {s: m for s, m in fusion.modes.items()}
    fused = {m.seq: m for _, m in fusion.published}
    assert sorted(fused) == list(range(len(take)))
    held = [s for s in fused if modes[s] == "held"]
    rest = [s for s in fused if modes[s] == "rest"]
    assert held and rest and max(rest) < min(held)        # on the pad, then in the jaws
    assert all(fused[s].n_views == 1 for s in held)
    assert fusion.counters["resets.needle_moves"] == len(held) + sum(m == "free" for m in modes.values())
    assert [fused[s].n_views for s in rest[:5]] == [1, 2, 3, 4, 5]
    T_world_rest = take[rest[-1]].T_world_needle
    assert pose_error(fused[rest[-1]].T_world_needle, T_world_rest)[0] < 0.5e-3


def test_the_evaluation_graph_wires_the_tracker_s_modes_to_the_fusions_where_it_runs():
    from common.evaluation.pipeline_graph import LOSSLESS_TRACKER_WAIT, pipeline_graph
    by_id = {n["id"]: n for n in pipeline_graph("dataset", detector="oracle", refine=True, tracker=True)["nodes"]}
    for fid in ("fusion", "fusion_refined"):
        assert by_id[fid]["inputs"]["motion"] == "tracker/pose"
        assert by_id[fid]["inputs"]["untracked"] == "tracker/no_pose"
    assert by_id["tracker"]["inputs"]["no_pose"] == "refine/no_pose"       # stepped without waiting
    assert "no_pose" in by_id["refine"]["outputs"] and "no_pose" in by_id["tracker"]["outputs"]
    static = {n["id"]: n for n in pipeline_graph("dataset", detector="oracle", refine=True)["nodes"]}
    assert all(not {"motion", "untracked"} & set(static[fid]["inputs"]) for fid in ("fusion", "fusion_refined"))
    lossless = {n["id"]: n for n in pipeline_graph("dataset", detector="oracle", refine=True, tracker=True,
                                                    lossless=True)["nodes"]}
    assert lossless["fusion"]["params"]["max_wait"] == 2 * LOSSLESS_TRACKER_WAIT
    assert lossless["tracker"]["params"]["max_wait"] == LOSSLESS_TRACKER_WAIT
    # the refinement answers every frame of a lossless graph, tens of seconds after the source ends
    assert "eos" in by_id["tracker"]["inputs"] and "eos" not in lossless["tracker"]["inputs"]
    assert by_id["tracker"]["inputs"]["one_camera"] == "refine/one_camera"


def test_a_monocular_evaluation_graph_runs_one_camera_s_detector_refinement_and_tracker():
    from common.evaluation.pipeline_graph import pipeline_graph
    doc = pipeline_graph("dataset", detector="learned", cameras=("left",), replay_params={"withhold": "left"})
    by_id = {n["id"]: n for n in doc["nodes"]}
    assert set(by_id) == {"replay", "detector_left", "ecm", "refine", "tracker"}
    assert set(by_id["refine"]["inputs"]) >= {"left", "calib", "ecm"} and "right" not in by_id["refine"]["inputs"]
    assert by_id["tracker"]["params"]["start_one_camera"] is True
    assert by_id["replay"]["params"]["withhold"] == "left"
    # its recorder (eval --record) keeps the one-camera poses, the only ones such a graph gives
    from common.evaluation.pipeline_graph import recorder_node
    rec = recorder_node(doc, "r.jsonl", split_detector=True, cameras=("left",))
    assert rec["inputs"]["one_camera"] == "refine/one_camera" and "pose" not in rec["inputs"]
    assert recorder_node(pipeline_graph("dataset", detector="learned"), "r.jsonl", True)["inputs"]["pose"] == "refine/pose"
