"""The ``refine`` node: offline (message in, message out) and in a launched graph; its poses are
the library's (common/geometry/refine.py on the joint PnP's candidates)."""
from dataclasses import replace

import numpy as np
import pytest

from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.end_identity import stereo_end_identity
from common.geometry.needle import NeedleModel
from common.geometry.oracle import Oracle, random_needle_pose
from common.geometry.pnp import refine_starts
from common.geometry.refine import ArcObservation, DenseRefiner, RefineConfig
from common.geometry.refine_tracking import TrackingConfig, TrackingRefiner
from common.geometry.transforms import inv_T, make_T, pose_error, rotvec_to_R
from common.runtime.messages import (
    Calibration,
    EcmPose,
    Keypoints,
    NoPoseNotice,
    PoseEstimate,
    decode,
    encode,
)
from common.runtime.params import ParamError
from nodes.refine import RefineNode

RIG = StereoRig.default()
MODEL = NeedleModel()
ARM = EcmArm(make_T(rotvec_to_R([0, 0, 0.2]), [0.1, 0.0, 0.3]), 0.01, 0.02)
CALIB = Calibration(0, np.array([1920, 1080]), RIG.to_dict(), MODEL.to_dict(), ARM.to_dict())
Q = (0.0, 0.0, 0.05, 0.0)


def roundtrip(msg):
    return decode(encode(msg), type(msg))


def oracle_frames(n, noise_px=0.5, seed=3):
    """Keypoints messages with centrelines from the oracle, and the true poses."""
    rng = np.random.default_rng(seed)
    oracle = Oracle(noise_px=noise_px, seed=seed)
    frames = []
    for seq in range(n):
        T = random_needle_pose(rng, RIG, MODEL)
        kps = []
        for cam in RIG.cameras:
            uv, sc = oracle.keypoints(cam, T, MODEL, seq)
            c, w = oracle.centreline(cam, T, MODEL, seq)
            kps.append(Keypoints(cam.name, seq, seq * 1000, True, uv, sc, 1.0, detector="oracle",
                                 centreline=c, centreline_w=w))
        frames.append((T, *kps))
    return frames


def library(left, right, config=RefineConfig(), support_normal=None):
    uv = {k.camera: k.uv for k in (left, right)}
    sc = {k.camera: k.scores for k in (left, right)}
    starts = refine_starts(uv, RIG, MODEL.keypoints(), sc, config.min_score)
    obs = {k.camera: ArcObservation.from_keypoints(k) for k in (left, right)}
    return DenseRefiner(RIG, MODEL, config).refine(obs, starts, support_normal=support_normal)


def poses(node):
    return [m for o, m in node.published if o == "pose"]


def notices(node):
    return [m for o, m in node.published if o == "no_pose"]


def test_node_matches_the_library_and_adds_the_world_pose():
    frames = oracle_frames(4)
    node = RefineNode.offline({"tracking": False}, wired=["left", "right", "calib", "ecm"])
    node.on_calib(roundtrip(CALIB))
    T_world_ecm = ARM.T_world_ecm(Q)
    for T, left, right in frames:
        node.on_ecm(roundtrip(EcmPose(left.seq, left.stamp_ns, T_world_ecm)))
        node.on_right(roundtrip(right))
        node.on_left(roundtrip(left))
    out = poses(node)
    assert [p.seq for p in out] == [0, 1, 2, 3]
    for p, (T, left, right) in zip(out, frames):
        ref = library(left, right)
        assert p.method == "refined" and p.residual_unit == "px"
        assert np.allclose(p.T_ecm_needle, ref.T_ecm_needle, atol=1e-12)
        assert np.allclose(p.covariance, ref.covariance)
        assert p.residual == pytest.approx(ref.rms_px) and p.ambiguous == ref.ambiguous
        assert np.allclose(p.T_world_needle, T_world_ecm @ p.T_ecm_needle)
        dt, dr = pose_error(p.T_ecm_needle, T)
        assert dt < 5e-3 and np.degrees(dr) < 5.0
        roundtrip(p)
    assert node.counters.get("keypoints_only", 0) == 0 and node.counters["cold"] == 4


def test_node_support_normal_is_turned_into_each_frames_ecm_frame():
    frames = oracle_frames(3, noise_px=1.0)
    node = RefineNode.offline({"tracking": False, "support_normal_world": [0, 0, 2]},
                              wired=["left", "right", "calib", "ecm"])
    node.on_calib(CALIB)
    assert node.step.support_normal_ecm(0) is None and node.counters["no_support_prior"] == 1
    T_world_ecm = ARM.T_world_ecm(Q)
    node.on_ecm(EcmPose(0, 0, T_world_ecm))
    assert np.allclose(T_world_ecm[:3, :3] @ node.step.support_normal_ecm(7), [0, 0, 1])   # the newest
    for T, left, right in frames:
        node.on_ecm(EcmPose(left.seq, left.stamp_ns, T_world_ecm))
        node.on_right(right)
        node.on_left(left)
        ref = library(left, right, support_normal=T_world_ecm[:3, :3].T @ [0, 0, 1])
        assert np.allclose(poses(node)[-1].T_ecm_needle, ref.T_ecm_needle, atol=1e-12)
        assert np.allclose(poses(node)[-1].covariance, ref.covariance)
    for bad in ([0, 0], [0, 0, 0], "up"):
        with pytest.raises(ValueError, match="support_normal_world"):
            RefineNode.offline({"support_normal_world": bad})


def test_node_tracks_a_video_as_the_library_does():
    from tests.geometry.test_refine_tracking import FRAME_NS, video
    node = RefineNode.offline({"cold_every": 4}, wired=["left", "right", "calib"])
    node.on_calib(CALIB)
    tracker = TrackingRefiner(DenseRefiner(RIG, MODEL), MODEL.keypoints(), config=TrackingConfig(cold_every=4))
    for seq, (T, uv, sc, obs) in enumerate(video(8)):
        for cam in ("right", "left"):
            o = obs[cam]
            getattr(node, f"on_{cam}")(Keypoints(cam, seq, seq * FRAME_NS, True, o.uv, o.scores, 1.0,
                                                 centreline=o.centreline, centreline_w=o.centreline_w))
        ref = tracker.refine(uv, sc, obs, seq * FRAME_NS)
        assert np.allclose(poses(node)[-1].T_ecm_needle, ref.T_ecm_needle, atol=1e-12)
    assert node.counters["warm"] == 6 and node.counters["cold"] == 2
    with pytest.raises(ValueError, match="tracking"):
        RefineNode.offline({"tracking": "yes"})


def test_node_params_reach_the_fit():
    node = RefineNode.offline({"sigma_curve_px": 0.3, "min_score": 0.7, "max_rms_px": 5, "max_curve_points": 48,
                               "tracking": False, "cold_every": 7}, wired=["left", "right", "calib"])
    assert node.step.config.sigma_curve_px == 0.3 and node.step.config.min_score == 0.7 and node.step.config.max_curve_points == 48
    assert node.step.gates.max_rms_px == 5 and not node.step.tracking.enabled and node.step.tracking.cold_every == 7
    assert RefineNode.offline({}, wired=["left", "right", "calib"]).step.config.min_score == 0.5
    with pytest.raises(ParamError, match=r"sigma_kp_px: must be a positive number, got -1.0"):   # RefineConfig's constraint
        RefineNode.offline({"sigma_kp_px": -1.0})
    with pytest.raises(ParamError, match="max_iter: expected int, got 'many'"):
        RefineNode.offline({"max_iter": "many"})
    with pytest.raises(ParamError, match="max_curve_points: expected int, got 48.0"):
        RefineNode.offline({"max_curve_points": 48.0})
    with pytest.raises(ParamError, match="other: unknown param"):
        RefineNode.offline({"other": 1})


def test_node_without_centreline_refines_keypoints_and_counts_it():
    (T, left, right), = oracle_frames(1)
    node = RefineNode.offline({}, wired=["left", "right", "calib"])
    node.on_calib(CALIB)
    for kp in (left, right):
        kp.centreline = kp.centreline_w = None
        getattr(node, f"on_{kp.camera}")(kp)
    assert len(poses(node)) == 1 and node.counters["keypoints_only"] == 1
    assert poses(node)[0].T_world_needle is None


def test_node_counts_why_there_is_no_pose_and_never_publishes_one():
    node = RefineNode.offline({}, wired=["left", "right", "calib"])
    kp = Keypoints("left", 0, 0, True, np.full((5, 2), 100.0), np.ones(5), 1.0)
    node.on_left(kp)
    node.on_right(Keypoints("right", 0, 0, True, np.full((5, 2), 100.0), np.ones(5), 1.0))
    assert node.counters["no_pose.no_calibration"] == 1
    node.on_calib(CALIB)
    cases = [(np.full((5, 2), 100.0), "coincident"),
             (np.array([[1, 2], [3, 4], [5, 6], [np.nan, 0], [np.nan, np.nan]], float), "too_few_points")]
    for seq, (uv, reason) in enumerate(cases, start=1):
        node.on_left(Keypoints("left", seq, 0, True, uv, np.ones(5), 1.0))
        node.on_right(Keypoints("right", seq, 0, True, uv, np.ones(5), 1.0))
        assert node.counters[f"no_pose.{reason}"] == 1, reason
    node.on_left(Keypoints.not_found("left", 9, 0, "oracle", "x"))
    node.on_right(Keypoints.not_found("right", 9, 0, "oracle", "x"))
    assert node.counters["no_pose.too_few_points"] == 2
    # a malformed centreline: a reason, not a crash
    (T, left, right), = oracle_frames(1)
    left.seq = right.seq = 10
    left.centreline_w = np.ones(3)
    node.on_left(left)
    node.on_right(right)
    assert node.counters["no_pose.bad_centreline"] == 1
    # a fit worse than max_rms_px is not published
    strict = RefineNode.offline({"max_rms_px": 1e-9}, wired=["left", "right", "calib"])
    strict.on_calib(CALIB)
    (T, left, right), = oracle_frames(1, noise_px=1.0)
    strict.on_left(left)
    strict.on_right(right)
    assert strict.counters["no_pose.high_residual"] == 1 and poses(strict) == []
    assert poses(node) == []
    # each frame without a pose is said at once, with the reason it is counted under
    said = [roundtrip(m) for m in notices(node)]
    assert [(m.seq, m.method, m.reason) for m in said] == [
        (0, "refined", "no_calibration"), (1, "refined", "coincident"), (2, "refined", "too_few_points"),
        (9, "refined", "too_few_points"), (10, "refined", "bad_centreline")]
    assert [(m.seq, m.reason) for m in notices(strict)] == [(0, "high_residual")]


def test_a_notice_goes_out_for_each_frame_without_a_pose_and_never_for_a_posed_one():
    frames = oracle_frames(8)
    node = RefineNode.offline({}, wired=["left", "right", "calib"])
    node.on_calib(CALIB)
    hidden = {2, 3, 6}                                  # the jaws hide the needle: nothing found
    for T, left, right in frames:
        if left.seq in hidden:
            left, right = (Keypoints.not_found(k.camera, k.seq, k.stamp_ns, "oracle", "hidden") for k in (left, right))
        node.on_left(left)
        node.on_right(right)
        said = {m.seq for m in notices(node)}
        assert said == {s for s in hidden if s <= left.seq}        # at once, not at a later frame
    posed = {m.seq for m in poses(node)}
    assert posed == set(range(8)) - hidden
    for m in notices(node):
        back = roundtrip(m)
        assert isinstance(back, NoPoseNotice) and back.method == "refined" and back.reason == "too_few_points"
        assert back.stamp_ns == m.seq * 1000
    assert node.counters["no_pose.too_few_points"] == len(hidden)


def test_a_fit_far_worse_than_the_stated_noise_is_not_published():
    """Residuals many times the noise the detector states (a jaw's edge taken for the wire) give
    no pose (``poor_fit``); the same frame stating its real noise is posed."""
    (T, left, right), = oracle_frames(1, noise_px=2.0)
    claimed = [replace(k, keypoint_sigma_px=0.2, centreline_sigma_px=0.1) for k in (left, right)]
    honest = [replace(k, keypoint_sigma_px=2.0, centreline_sigma_px=1.0) for k in (left, right)]
    for kps, gate, posed in ((claimed, 1.5, False), (honest, 1.5, True), (claimed, None, True)):
        node = RefineNode.offline({"max_residual_variance": gate}, wired=["left", "right", "calib"])
        node.on_calib(CALIB)
        node.on_left(kps[0])
        node.on_right(kps[1])
        assert (len(poses(node)) == 1) == posed, (gate, kps[0].keypoint_sigma_px)
        assert node.counters.get("no_pose.poor_fit", 0) == (0 if posed else 1)


@pytest.mark.graph
def test_refine_node_in_a_launched_graph_matches_the_library(run_graph):
    """sim (truth and calibration) -> detector (oracle, with centreline) -> refine."""
    g = run_graph({"nodes": [
        {"id": "camera", "module": "sim",
         "params": {"width": 640, "height": 360, "rate_hz": 5, "randomise": "none",
                    "motion": "static", "encoding": "jpeg", "count": 40},
         "outputs": ["left", "right", "joints", "truth", "calib"]},
        {"id": "detector", "module": "detector", "params": {"backend": "oracle", "noise_px": 0.3, "seed": 2},
         "inputs": {"truth": "camera/truth", "calib": "camera/calib"}, "outputs": ["left", "right"]},
        {"id": "refine", "module": "refine", "params": {"tracking": False},   # each frame as the library
         "inputs": {"left": "detector/left", "right": "detector/right", "calib": "camera/calib"},
         "outputs": ["pose"]},
    ]}, timeout=90)
    kp_sub = g.subscribe("detector/*")
    calib = g.collect("camera/calib", n=1, timeout=30)[0]
    out = g.collect("refine/pose", n=3, timeout=60)
    rig, model = StereoRig.from_dict(calib.cameras, calib.image_size), NeedleModel.from_dict(calib.needle)
    kp_sub.wait(2, timeout=10)
    kps = {}
    for m in kp_sub.messages:
        kps.setdefault(m.seq, {})[m.camera] = m
    checked = 0
    for p in out:
        pair = kps.get(p.seq)
        if not pair or len(pair) < 2:
            continue
        uv = {c: k.uv for c, k in pair.items()}
        sc = {c: k.scores for c, k in pair.items()}
        starts = refine_starts(uv, rig, model.keypoints(), sc, 0.5)
        obs = {c: ArcObservation.from_keypoints(k) for c, k in pair.items()}
        ref = DenseRefiner(rig, model, RefineConfig(min_score=0.5)).refine(obs, starts)
        assert isinstance(p, PoseEstimate) and p.method == "refined"
        assert np.allclose(p.T_ecm_needle, ref.T_ecm_needle, atol=1e-12)
        assert np.allclose(p.covariance, ref.covariance)
        assert all(k.centreline is not None and len(k.centreline) > 10 for k in pair.values())
        checked += 1
    assert checked >= 1
    st = g.stats("refine")
    assert st.counters.get("handler_errors", 0) == 0 and st.counters.get("decode_errors", 0) == 0


def test_end_identity_belongs_to_the_tracked_needle_not_to_a_frame():
    """A detector unsure of the tip (0.8 per image) in every frame: every pose is flagged with
    that probability (frames that agree share their causes of error: they do not make the tip
    sure); a frame it reads the other way round, as unsure, is turned back to the track's
    reading; then one sure frame makes it sure."""
    import dataclasses

    from common.pose.stereo import turn_keypoints
    from tests.geometry.test_refine_tracking import FRAME_NS, video
    node = RefineNode.offline({}, wired=["left", "right", "calib"])
    node.on_calib(CALIB)
    frames = video(8)
    for seq, (T, uv, sc, obs) in enumerate(frames):
        for cam in ("right", "left"):
            o = obs[cam]
            kp = Keypoints(cam, seq, seq * FRAME_NS, True, o.uv, o.scores, 1.0,
                           centreline=o.centreline, centreline_w=o.centreline_w, end_identity=0.8)
            if seq == 5:
                kp = dataclasses.replace(turn_keypoints(kp), end_identity=0.8)
            if seq == 7:
                kp = dataclasses.replace(kp, end_identity=0.9999)
            getattr(node, f"on_{cam}")(kp)
    out = poses(node)
    assert len(out) == 8
    for (T, *_), pose in zip(frames, out):
        assert pose_error(pose.T_ecm_needle, T)[1] < np.radians(5.0)
    p = stereo_end_identity(0.8, 0.8)
    assert all(q.ambiguous for q in out[:7]) and not out[7].ambiguous
    assert all(q.end_identity == pytest.approx(p) for q in out[:5])
    assert out[5].end_identity < p and out[7].end_identity > 0.95
    assert node.counters["end_identity.turned"] == 1


def test_a_needle_at_rest_keeps_its_identity_over_the_endoscopes_moves():
    """Five views of one needle at rest from five endoscope poses, seconds apart (no frame
    follows the last one as a video would). Each detector reading states 0.99; the third view
    reads the needle end for end with the same 0.99. With the ECM poses, that view is read
    against the needle's identity so far (its last world pose seen from the new endoscope pose):
    turned back to the right reading, and flagged, since its own evidence contests it. Without
    them it stands alone: a sure, turned pose (what the world track prevents)."""
    import dataclasses

    from common.pose.stereo import turn_keypoints
    rng = np.random.default_rng(11)
    T_ecm0 = random_needle_pose(rng, RIG, MODEL)
    qs = [(0.0, 0.0, 0.05, 0.0), (0.04, 0.0, 0.05, 0.0), (0.0, 0.04, 0.05, 0.0),
          (-0.04, 0.0, 0.05, 0.0), (0.0, -0.04, 0.05, 0.0)]
    T_world_needle = ARM.T_world_ecm(qs[0]) @ T_ecm0
    oracle = Oracle(noise_px=0.3, seed=4)

    def run(with_ecm: bool):
        wired = ["left", "right", "calib"] + (["ecm"] if with_ecm else [])
        node = RefineNode.offline({}, wired=wired)
        node.on_calib(CALIB)
        truth = []
        for seq, q in enumerate(qs):
            T_world_ecm = ARM.T_world_ecm(q)
            T = inv_T(T_world_ecm) @ T_world_needle
            truth.append(T)
            stamp = seq * 2_000_000_000
            if with_ecm:
                node.on_ecm(EcmPose(seq, stamp, T_world_ecm))
            for cam in RIG.cameras:
                uv, sc = oracle.keypoints(cam, T, MODEL, seq)
                c, w = oracle.centreline(cam, T, MODEL, seq)
                kp = Keypoints(cam.name, seq, stamp, True, uv, sc, 1.0, centreline=c, centreline_w=w,
                               end_identity=0.99)
                if seq == 2:
                    kp = dataclasses.replace(turn_keypoints(kp), end_identity=0.99)
                getattr(node, f"on_{cam.name}")(kp)
        out = poses(node)
        assert [p.seq for p in out] == list(range(len(qs)))
        return out, truth

    out, truth = run(with_ecm=True)
    for pose, T in zip(out, truth):
        assert np.degrees(pose_error(pose.T_ecm_needle, T)[1]) < 5.0
    assert out[2].ambiguous and out[2].end_identity < 0.95
    assert not any(p.ambiguous for i, p in enumerate(out) if i != 2)
    alone, truth = run(with_ecm=False)
    assert np.degrees(pose_error(alone[2].T_ecm_needle, truth[2])[1]) > 150.0
    assert not alone[2].ambiguous and alone[2].end_identity > 0.95


def test_a_pose_fitted_to_part_of_the_arc_is_flagged_a_partial_view_with_a_wider_covariance():
    """Half the arc hidden (the jaws, the tissue): the pose states how much of the arc it was
    fitted to, and below ``min_arc_seen`` it is flagged, its covariance widened."""
    frames = oracle_frames(6, noise_px=0.3, seed=11)
    node = RefineNode.offline({"tracking": False}, wired=["left", "right", "calib"])
    node.on_calib(roundtrip(CALIB))
    hidden = []
    for T, left, right in frames:
        cut = []
        for kp in (left, right):               # the arc past D hidden, the centreline past B
            n = len(kp.centreline)
            cut.append(replace(kp, scores=np.where(np.arange(5) >= 4, 0.0, kp.scores),
                               centreline=kp.centreline[: int(0.3 * n)], centreline_w=kp.centreline_w[: int(0.3 * n)]))
        hidden.append(cut)
        node.on_right(roundtrip(cut[1]))
        node.on_left(roundtrip(cut[0]))
    out = poses(node)
    partial = [p for p in out if p.arc_seen < node.p.min_arc_seen]
    assert len(partial) >= len(out) // 2 and node.counters["partial_view"] == len(partial)
    for p in out:
        left, right = hidden[p.seq]
        ref = library(left, right)
        assert p.arc_seen < 0.75 and np.allclose(p.T_ecm_needle, ref.T_ecm_needle)
        if p in partial:
            assert p.ambiguous is True and np.allclose(p.covariance, 4.0 * ref.covariance)
        else:
            assert p.ambiguous == ref.ambiguous and np.allclose(p.covariance, ref.covariance)
    whole = RefineNode.offline({"tracking": False}, wired=["left", "right", "calib"])
    whole.on_calib(roundtrip(CALIB))
    for T, left, right in frames:
        whole.on_right(roundtrip(right))
        whole.on_left(roundtrip(left))
    assert all(p.arc_seen > 0.9 for p in poses(whole)) and "partial_view" not in whole.counters


def test_a_pose_whose_arc_shows_one_end_only_states_its_tip_at_most_end_unseen_p_max_sure():
    """The tail's end hidden (the jaws over it): the detectors' sure tip was read from one end and
    a cut, so the pose states it at most 0.9 sure, flagged; a whole arc keeps what they state."""
    frames = oracle_frames(6, noise_px=0.3, seed=11)

    def run(cut_tail):
        node = RefineNode.offline({"tracking": False}, wired=["left", "right", "calib"])
        node.on_calib(roundtrip(CALIB))
        for T, left, right in frames:
            kps = []
            for kp in (left, right):
                n = len(kp.centreline)
                keep = int(0.7 * n) if cut_tail else n
                kps.append(replace(kp, end_identity=0.99,
                                   scores=np.where(np.arange(5) >= 4, 0.0, kp.scores) if cut_tail else kp.scores,
                                   centreline=kp.centreline[:keep], centreline_w=kp.centreline_w[:keep]))
            node.on_right(roundtrip(kps[1]))
            node.on_left(roundtrip(kps[0]))
        return node

    cut, whole = run(True), run(False)
    assert len(poses(cut)) == len(poses(whole)) == len(frames)
    assert cut.counters["end_identity.end_unseen"] == len(frames)
    assert all(p.end_identity == 0.9 and p.ambiguous for p in poses(cut))
    assert all(p.end_identity > 0.95 for p in poses(whole)) and "end_identity.end_unseen" not in whole.counters


def test_a_pose_whose_keypoints_one_camera_reads_end_for_end_states_no_sure_tip():
    """The fit rests on the one keypoint scored above the gate, a stray E on the tip (the other
    keypoints, scored below it, read the needle as it lies): the pose comes out turned, and the
    detectors' sure tip (0.99) was the keypoints', not the pose's, so it states at most 0.5."""
    frames = oracle_frames(6, noise_px=0.3, seed=5)
    node = RefineNode.offline({"tracking": False}, wired=["left", "right", "calib"])
    node.on_calib(roundtrip(CALIB))
    for T, left, right in frames:
        stray = np.array(right.uv, float)
        stray[4] = stray[0] + 1.0
        node.on_right(roundtrip(replace(right, uv=stray, scores=np.array([0.3, 0.3, 0.3, 0.3, 0.8]),
                                        end_identity=0.99)))
        node.on_left(roundtrip(replace(left, scores=np.full(5, 0.45), end_identity=0.99)))
    out = {p.seq: p for p in poses(node)}
    turned = [s for s, p in out.items() if np.degrees(pose_error(p.T_ecm_needle, frames[s][0])[1]) > 150]
    assert turned, "the stray keypoint should have turned some fits (the case under test)"
    assert all(out[s].end_identity <= 0.5 and out[s].ambiguous for s in turned)
    assert node.counters["end_identity.reading_turned"] >= len(turned)
    right_way = [p for s, p in out.items() if s not in turned]
    assert all(p.end_identity > 0.95 for p in right_way)


def test_a_pair_is_refined_once_its_ecm_pose_is_in_and_in_seq_order():
    """The resting prior and the needle's last world pose need the frame's ECM pose: a pair
    whose ECM pose is late waits for it (so a loaded machine gives the same poses as an idle
    one), later pairs wait behind it, and after max_wait frames without it, it is refined anyway."""
    frames = oracle_frames(4)
    node = RefineNode.offline({"tracking": False, "support_normal_world": [0, 0, 1], "max_wait": 2},
                              wired=["left", "right", "calib", "ecm"])
    node.on_calib(roundtrip(CALIB))
    T_world_ecm = ARM.T_world_ecm(Q)
    (_, l0, r0), (_, l1, r1), (_, l2, r2), (_, l3, r3) = frames
    node.on_left(l0)
    node.on_right(r0)
    node.on_ecm(EcmPose(1, l1.stamp_ns, T_world_ecm))
    node.on_left(l1)
    node.on_right(r1)
    assert not node.published                         # 0 waits for its ECM pose, 1 behind it
    node.on_ecm(EcmPose(0, l0.stamp_ns, T_world_ecm))
    assert [p.seq for p in poses(node)] == [0, 1]
    assert all(p.T_world_needle is not None for p in poses(node))
    # frame 2's ECM pose never comes: refined after max_wait frames, counted
    for left, right in ((l2, r2), (l3, r3)):
        node.on_left(left)
        node.on_right(right)
    assert [p.seq for p in poses(node)] == [0, 1]
    node.on_ecm(EcmPose(3, l3.stamp_ns, T_world_ecm))
    node.on_left(replace(l3, seq=4))
    assert [p.seq for p in poses(node)] == [0, 1, 2, 3]
    assert node.counters["solved_without_ecm"] == 1


def test_without_ecm_wired_a_pair_is_refined_at_once():
    (_, left, right), = oracle_frames(1)
    node = RefineNode.offline({"tracking": False}, wired=["left", "right", "calib"])
    node.on_calib(roundtrip(CALIB))
    node.on_left(left)
    node.on_right(right)
    assert [p.seq for p in poses(node)] == [0]


def test_the_expected_pose_that_picks_between_minima_is_confirmed_by_the_pose_before():
    """Views of a needle at rest: the expected pose, seen from the next endoscope pose, is given
    once two poses in a row agree; a needle moved between two views gives none (one wrong pose
    must not pick the next frame's minimum)."""
    rng = np.random.default_rng(11)
    T_ecm0 = random_needle_pose(rng, RIG, MODEL)
    qs = [(0.0, 0.0, 0.05, 0.0), (0.04, 0.0, 0.05, 0.0), (0.0, 0.04, 0.05, 0.0), (-0.04, 0.0, 0.05, 0.0)]
    T_world_needle = ARM.T_world_ecm(qs[0]) @ T_ecm0
    moved = T_world_needle @ make_T(rotvec_to_R([0.0, 0.0, 0.5]), [0.004, 0.0, 0.0])
    oracle = Oracle(noise_px=0.3, seed=4)
    node = RefineNode.offline({}, wired=["left", "right", "calib", "ecm"])
    node.on_calib(CALIB)
    expected = []
    for seq, q in enumerate(qs):
        T_world_ecm = ARM.T_world_ecm(q)
        node.on_ecm(EcmPose(seq, seq * 2_000_000_000, T_world_ecm))
        expected.append(node.step.expected_T_ecm_needle(seq, confirmed=True))
        T = inv_T(T_world_ecm) @ (moved if seq == 2 else T_world_needle)
        for cam in RIG.cameras:
            uv, sc = oracle.keypoints(cam, T, MODEL, seq)
            c, w = oracle.centreline(cam, T, MODEL, seq)
            getattr(node, f"on_{cam.name}")(Keypoints(cam.name, seq, seq * 2_000_000_000, True, uv, sc, 1.0,
                                                      centreline=c, centreline_w=w, end_identity=0.99))
    out = poses(node)
    assert len(out) == 4 and expected[0] is None and expected[1] is None     # one pose: unconfirmed
    assert np.degrees(pose_error(expected[2], inv_T(ARM.T_world_ecm(qs[2])) @ T_world_needle)[1]) < 2.0
    assert expected[3] is None                                                # the needle moved
    assert node.step.expected_T_ecm_needle(3) is not None                          # unconfirmed: the last pose
