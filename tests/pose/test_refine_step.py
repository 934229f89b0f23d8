"""The dense refinement's frame step (common/pose/refine_step.py) driven directly: a frame waits
for its ECM pose before it is solved, in seq order; the gates; a partial view's caps; a needle one
camera alone sees, and a monocular endoscope."""
from dataclasses import replace

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import Oracle, random_needle_pose
from common.geometry.refine import RefineConfig
from common.geometry.refine_tracking import TrackingConfig
from common.geometry.transforms import make_T, pose_error, rotvec_to_R
from common.pose.refine_step import ONE_CAMERA_DEPTH_SIGMA, RefineGates, RefineStep
from common.runtime.messages import Calibration, EcmPose, Keypoints, PoseEstimate

RIG = StereoRig.default()
MODEL = NeedleModel()
CALIB = Calibration(0, np.array([1920, 1080]), RIG.to_dict(), MODEL.to_dict())
T_WORLD_ECM = make_T(rotvec_to_R([0.0, 0.0, 0.2]), [0.1, 0.0, 0.3])


def perturb(T, mm=1.0, deg=2.0):
    """T moved ``mm`` along x and turned ``deg`` about y (its own axes)."""
    return T @ make_T(rotvec_to_R([0.0, np.radians(deg), 0.0]), [mm * 1e-3, 0.0, 0.0])


def frames(n, seed=3):
    rng, oracle = np.random.default_rng(seed), Oracle(noise_px=0.5, seed=seed)
    out = []
    for seq in range(n):
        T = random_needle_pose(rng, RIG, MODEL)
        kps = []
        for cam in RIG.cameras:
            uv, sc = oracle.keypoints(cam, T, MODEL, seq)
            c, w = oracle.centreline(cam, T, MODEL, seq)
            kps.append(Keypoints(cam.name, seq, seq * 1000, True, uv, sc, 1.0, detector="oracle",
                                 centreline=c, centreline_w=w))
        out.append((T, *kps))
    return out


def test_a_pair_waits_unsolved_for_its_ecm_pose_and_is_solved_in_seq_order():
    counts = {}
    step = RefineStep(tracking=TrackingConfig(enabled=False), max_wait=3,
                      count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k))
    step.on_calib(CALIB)
    fr = frames(3)
    for _, left, right in fr:
        assert step.on_keypoints(right) + step.on_keypoints(left) == []    # no ECM pose yet: not solved
    assert counts["pairs"] == 3 and "cold" not in counts
    assert step.on_ecm(EcmPose(1, 1000, T_WORLD_ECM)) == []                 # 1 waits behind 0
    out = step.on_ecm(EcmPose(0, 0, T_WORLD_ECM))
    assert [(o, m.seq) for o, m in out] == [("pose", 0), ("pose", 1)] and counts["cold"] == 2
    for (T, _, _), (_, pose) in zip(fr, out):
        assert pose.method == "refined" and pose.identity_widened is False and pose.arc_seen > 0.6
        assert np.allclose(pose.T_world_needle, T_WORLD_ECM @ pose.T_ecm_needle)
        dt, dr = pose_error(pose.T_ecm_needle, T)
        assert dt < 5e-3 and np.degrees(dr) < 5.0


def test_a_fit_beyond_the_gates_gives_no_pose_and_says_why():
    counts = {}
    step = RefineStep(RefineConfig(), TrackingConfig(enabled=False), RefineGates(max_rms_px=1e-3), ecm_wired=False,
                      count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k))
    step.on_calib(CALIB)
    _, left, right = frames(1)[0]
    out = step.on_keypoints(left) + step.on_keypoints(right)
    assert [(o, m.reason, m.method) for o, m in out] == [("no_pose", "high_residual", "refined")]
    assert counts["no_pose.high_residual"] == 1


def test_a_partial_view_is_flagged_and_its_tip_capped():
    """Most of the arc hidden in both cameras (the centreline past 40 % and keypoint E cut): a partial
    view, flagged ambiguous, its covariance inflated, its tip at most end_unseen_p_max sure."""
    counts = {}
    gates = RefineGates(end_unseen_p_max=0.7)
    step = RefineStep(tracking=TrackingConfig(enabled=False), gates=gates, ecm_wired=False,
                      count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k))
    step.on_calib(CALIB)
    _, left, right = frames(2)[1]

    def cut(kp):
        half = 2 * len(kp.centreline) // 5
        sc = np.array(kp.scores, float)
        sc[4:] = 0.0
        return replace(kp, centreline=kp.centreline[:half], centreline_w=kp.centreline_w[:half], scores=sc,
                       end_identity=0.99)
    left, right = cut(left), cut(right)
    (_, pose), = step.on_keypoints(left) + step.on_keypoints(right)
    assert counts.get("partial_view") == 1 and pose.ambiguous
    # capped once: for the end no camera saw (E's end is cut) or, failing that, as a partial view
    assert pose.end_identity <= 0.7
    assert counts.get("end_identity.end_unseen", 0) + counts.get("end_identity.partial_view", 0) == 1
    assert pose.identity_widened and counts["end_identity.unsure"] == 1


def test_a_fit_that_leaves_a_direction_unfixed_states_the_widest_honest_covariance():
    """Issue 56 (``pose: seq 912: not published: PoseEstimate.covariance: beyond 1e+07``): a short
    stretch of arc in each camera, its keypoints placed on it (``on_arc``) rather than seen, and an
    unsure tip. The fit's normal matrix is nearly singular (its plain inverse reached 1e8 and
    beyond, times the partial view's inflation); the pose is published, valid, flagged ambiguous,
    each direction no wider than the bound (the turn's widening on top), counted unobservable."""
    from common.geometry.covariance_bound import MAX_SIGMA_M, MAX_SIGMA_RAD
    from common.runtime.checks import pose_invariant_error
    posed = 0
    for seed in (1, 2, 3):
        counts = {}
        step = RefineStep(tracking=TrackingConfig(enabled=False), ecm_wired=False,
                          count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k))
        step.on_calib(CALIB)
        _, left, right = frames(1, seed)[0]

        def short(kp, k=3):
            i = len(kp.centreline) // 2
            return replace(kp, centreline=kp.centreline[i:i + k], centreline_w=np.ones(k), on_arc=np.ones(5, bool),
                           end_identity=0.7)
        out = step.on_keypoints(short(left)) + step.on_keypoints(short(right))
        assert len(out) == 1
        name, pose = out[0]
        if name == "no_pose":                 # a gate may refuse it; it says why
            assert pose.reason in ("poor_fit", "high_residual")
            continue
        posed += 1
        assert name == "pose" and pose_invariant_error(pose) is None, pose_invariant_error(pose)
        assert pose.ambiguous and counts["unobservable"] == 1 and pose.identity_widened
        C = np.asarray(pose.covariance)
        assert np.diag(C)[:3].max() <= 1.5 * MAX_SIGMA_RAD ** 2 + 1e-9       # the bound, and half a turn
        assert np.diag(C)[3:].max() <= MAX_SIGMA_M ** 2 + 1e-9
    assert posed >= 2


def test_a_camera_that_the_other_and_the_tracker_disagree_with_is_said_a_wrong_lock():
    """Issue 56: the right detector stuck on a distractor from the first frame, so the step has no
    pose of its own; the tracker's pose (fed back on ``track``) places the needle. Two frames in a
    row: a ``LockRejected`` for the right camera on ``lock``, with its box; the frames that agree
    say nothing."""
    from common.geometry.transforms import inv_T
    from common.runtime.messages import PoseEstimate
    counts = {}
    step = RefineStep(tracking=TrackingConfig(enabled=False), max_wait=3,
                      count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k))
    step.on_calib(CALIB)
    T, left, right = frames(1, 5)[0]
    T_world_needle = T_WORLD_ECM @ T
    step.on_track(PoseEstimate(0, 0, "tracked", inv_T(T_WORLD_ECM) @ T_world_needle, T_world_needle, T_WORLD_ECM,
                               0.0, "px"))
    blob = right.uv.mean(axis=0) + [-300.0, 160.0] + np.array([[-6, 0], [-3, 3], [0, 4], [3, 3], [6, 0]], float)
    stuck = replace(right, uv=blob, centreline=None, centreline_w=None, bbox=np.r_[blob.min(0), blob.max(0)])
    locks = []
    for seq in (1, 2, 3):
        step.on_ecm(EcmPose(seq, seq * 1000, T_WORLD_ECM))
        out = step.on_keypoints(replace(left, seq=seq, stamp_ns=seq * 1000))
        out += step.on_keypoints(replace(stuck, seq=seq, stamp_ns=seq * 1000))
        locks += [(m.seq, m.camera, m.reason) for o, m in out if o == "lock"]
    assert locks == [(2, "right", "wrong_lock")] and counts["lock_rejected.right"] == 1
    # both cameras on the needle: nothing said, whatever the track
    for seq in (4, 5, 6):
        step.on_ecm(EcmPose(seq, seq * 1000, T_WORLD_ECM))
        out = step.on_keypoints(replace(left, seq=seq, stamp_ns=seq * 1000))
        out += step.on_keypoints(replace(right, seq=seq, stamp_ns=seq * 1000))
        assert not [m for o, m in out if o == "lock"] and any(o == "pose" for o, _ in out)


def one_camera_step(counts, **kw):
    kw.setdefault("one_camera", True)
    step = RefineStep(tracking=TrackingConfig(enabled=False), max_wait=3,
                      count=lambda n, k=1: counts.__setitem__(n, counts.get(n, 0) + k), **kw)
    step.on_calib(CALIB)
    return step


def depth_sigma_m(pose) -> float:
    """1 sigma of the pose's position along the left camera's viewing ray (m)."""
    C = np.asarray(pose.covariance)[3:, 3:]
    ray = pose.T_ecm_needle[:3, 3] - RIG["left"].T_ecm_cam[:3, 3]
    ray = ray / np.linalg.norm(ray)
    return float(np.sqrt(ray @ C @ ray))


def lateral_sigma_m(pose) -> float:
    return float(np.sqrt(np.linalg.eigvalsh(np.asarray(pose.covariance)[3:, 3:])[0]))


def test_a_needle_one_camera_sees_is_fitted_from_the_track_and_said_on_one_camera():
    """The right camera lost it: the left camera's view, fitted from the tracker's pose, goes out
    on one_camera (flagged, its covariance wide along the left camera's ray), and ``pose`` says no
    pose for that frame; the stereo frame before it is posed as always."""
    counts = {}
    step = one_camera_step(counts)
    T, left, right = frames(1)[0]
    tracked = PoseEstimate(0, 0, "tracked", T, T_WORLD_ECM @ perturb(T), T_WORLD_ECM)
    step.on_track(tracked)
    step.on_ecm(EcmPose(0, 0, T_WORLD_ECM))
    blocked = Keypoints.not_found("right", 0, 0, "oracle", "no_needle")
    out = step.on_keypoints(left) + step.on_keypoints(blocked)
    assert [(o, getattr(m, "method", None)) for o, m in out] == [("one_camera", "refined_one_camera"),
                                                                ("no_pose", "refined")]
    pose, notice = out[0][1], out[1][1]
    assert notice.reason == "one_camera" and counts["one_camera"] == 1
    assert pose.ambiguous and pose.T_world_needle is not None
    dt, dr = pose_error(pose.T_ecm_needle, T)
    assert dt < 5e-3 and np.degrees(dr) < 5.0
    assert depth_sigma_m(pose) > 3 * lateral_sigma_m(pose)    # one view leaves the depth open
    dist = np.linalg.norm(pose.T_ecm_needle[:3, 3] - RIG["left"].T_ecm_cam[:3, 3])
    assert depth_sigma_m(pose) >= ONE_CAMERA_DEPTH_SIGMA * dist   # the arc's apparent size misread alike


def test_without_a_track_a_one_camera_frame_has_no_pose():
    counts = {}
    step = one_camera_step(counts)
    _, left, _ = frames(1)[0]
    step.on_ecm(EcmPose(0, 0, T_WORLD_ECM))
    out = step.on_keypoints(left) + step.on_keypoints(Keypoints.not_found("right", 0, 0, "oracle", "no_needle"))
    assert [(o, m.reason) for o, m in out] == [("no_pose", "one_camera_untracked")]


def test_one_camera_off_gives_the_stereo_step_s_no_pose():
    counts = {}
    step = one_camera_step(counts, one_camera=False)
    T, left, _ = frames(1)[0]
    step.on_track(PoseEstimate(0, 0, "tracked", T, T_WORLD_ECM @ T, T_WORLD_ECM))
    step.on_ecm(EcmPose(0, 0, T_WORLD_ECM))
    out = step.on_keypoints(left) + step.on_keypoints(Keypoints.not_found("right", 0, 0, "oracle", "no_needle"))
    assert [o for o, _ in out] == ["no_pose"] and out[0][1].reason != "one_camera"


def test_a_monocular_step_poses_every_frame_of_its_one_camera_cold_then_warm():
    """Only the left camera wired: each of its frames is a frame, the first fitted cold from the
    left camera's PnP minima (no track yet), the next from the tracked pose."""
    counts = {}
    step = one_camera_step(counts, cameras=("left",))
    assert step.monocular
    fr = frames(2)
    step.on_ecm(EcmPose(0, 0, T_WORLD_ECM))
    step.on_ecm(EcmPose(1, 1000, T_WORLD_ECM))
    out = step.on_keypoints(fr[0][1])
    assert [o for o, _ in out] == ["one_camera", "no_pose"]
    assert step.on_keypoints(fr[0][2]) == [] and counts["bad_input"] == 1     # the right camera is not wired
    dt, _ = pose_error(out[0][1].T_ecm_needle, fr[0][0])
    assert dt < 0.02                              # depth from the arc's apparent size alone
    step.on_track(PoseEstimate(0, 0, "tracked", fr[1][0], T_WORLD_ECM @ fr[1][0], T_WORLD_ECM))
    out = step.on_keypoints(fr[1][1])
    assert out[0][0] == "one_camera"
    dt, dr = pose_error(out[0][1].T_ecm_needle, fr[1][0])
    assert dt < 5e-3 and np.degrees(dr) < 5.0
