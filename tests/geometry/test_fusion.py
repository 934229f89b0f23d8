"""Multi-view fusion (common/geometry/fusion.py)."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.bench.geometry_bench import multiview_scenario
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.fusion import (
    MultiViewFusion,
    covariance_to_frame,
    fuse_poses,
    information_mean,
    mirror_consensus,
    robust_centre,
    within_views,
)
from common.geometry.end_identity import identity_covariance
from common.geometry.refine import mirror_covariance, mirror_pose
from common.geometry.needle import NeedleModel
from common.geometry.oracle import Oracle
from common.geometry.pnp import pnp_joint
from common.geometry.transforms import R_to_rotvec, inv_T, make_T, pose_error, rotvec_to_R

RIG = StereoRig.default()
MODEL = NeedleModel()
P = MODEL.keypoints()


def jitter(T, rng, mm=1.0, deg=1.0):
    return make_T(rotvec_to_R(rng.normal(size=3) * np.deg2rad(deg)) @ T[:3, :3],
                  T[:3, 3] + rng.normal(size=3) * mm * 1e-3)


def test_covariance_to_frame_matches_moving_the_perturbation():
    """Sigma in frame b -> frame a: the same random perturbations seen from a."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6))
    cov_b = A @ A.T * 1e-6
    T_a_b = make_T(rotvec_to_R([0.3, -1.0, 0.4]), [0.1, 0.2, -0.3])
    T_b = make_T(rotvec_to_R([0.2, 0.1, 0.0]), [0.01, 0.0, -0.15])
    samples = rng.multivariate_normal(np.zeros(6), cov_b, 4000)
    deltas_a = []
    T_a = T_a_b @ T_b
    for d in samples:
        Tp_b = make_T(rotvec_to_R(d[:3]) @ T_b[:3, :3], T_b[:3, 3] + d[3:])
        Tp_a = T_a_b @ Tp_b
        deltas_a.append(np.concatenate([R_to_rotvec(Tp_a[:3, :3] @ T_a[:3, :3].T), Tp_a[:3, 3] - T_a[:3, 3]]))
    emp = np.cov(np.array(deltas_a).T)
    pred = covariance_to_frame(cov_b, T_a_b[:3, :3])
    assert np.allclose(emp, pred, atol=0.1 * np.abs(pred).max())


def test_robust_centre_and_outlier_removal():
    rng = np.random.default_rng(1)
    T0 = make_T(rotvec_to_R([0.4, 0.2, -1.0]), [0.01, 0.02, -0.15])
    Ts = [jitter(T0, rng) for _ in range(4)]
    wild = make_T(rotvec_to_R([2.0, 0, 0]) @ T0[:3, :3], T0[:3, 3] + [0.02, 0, 0])
    Ts.insert(2, wild)
    assert robust_centre(Ts, 0.005, np.deg2rad(15)) != 2
    T, inl, cov = fuse_poses(Ts)
    assert list(inl) == [True, True, False, True, True]
    assert cov is None
    dt, dr = pose_error(T, T0)
    assert dt < 2e-3 and dr < np.deg2rad(2)


def test_information_mean_with_equal_covariances_is_the_mean():
    rng = np.random.default_rng(2)
    T0 = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    Ts = [jitter(T0, rng, 0.5, 0.5) for _ in range(5)]
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    T, C = information_mean(Ts, [cov] * 5)
    assert np.allclose(T[:3, 3], np.mean([t[:3, 3] for t in Ts], axis=0), atol=1e-12)
    assert np.allclose(C, cov / 5)
    # an estimate certain along x only pulls x
    sharp = np.diag([1e-4] * 3 + [1e-10, 1e-6, 1e-6])
    T2, _ = information_mean(Ts, [sharp] + [cov] * 4)
    assert abs(T2[0, 3] - Ts[0][0, 3]) < 1e-6
    assert information_mean(Ts, [np.zeros((6, 6))] * 5) is None


def test_views_are_mapped_into_the_current_ecm_frame():
    """A still needle seen from a moving endoscope: exact estimates fuse to the exact pose."""
    arm = EcmArm(make_T(rotvec_to_R([0, 0, 0.3]), [0.1, 0, 0.2]), 0.0, 0.0)
    rng = np.random.default_rng(3)
    T_wn, T_we, T_en = multiview_scenario(rng, RIG, MODEL, arm)
    f = MultiViewFusion(k=5)
    for T_w, T_e in zip(T_we, T_en):
        out = f.add(T_e, T_w)
    assert out.n_views == 5 and out.n_queued == 5 and not out.reset
    assert np.allclose(out.T_ecm_needle, T_en[-1], atol=1e-12)
    assert np.allclose(out.T_world_needle, T_wn, atol=1e-12)
    # without the ECM poses the views disagree (the endoscope moved 0.05 rad each time)
    g = MultiViewFusion(k=5, max_dist_mm=1000.0, max_angle_deg=180.0)
    for T_e in T_en:
        bad = g.add(T_e)
    assert pose_error(bad.T_ecm_needle, T_en[-1])[0] > 1e-3


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0, 1, 3]))
def test_multiview_exact_at_zero_noise(seed, joint):
    """Noise-free oracle keypoints -> pnp_joint per view -> fusion: the exact pose, for random
    needle poses and ECM motions (yaw, pitch or roll stepping 0.05 rad)."""
    rng = np.random.default_rng(seed)
    _, T_we, T_en = multiview_scenario(rng, RIG, MODEL, EcmArm(), joint=joint)
    f = MultiViewFusion(k=5)
    for i, (T_w, T_e) in enumerate(zip(T_we, T_en)):
        uv, sc = Oracle().stereo(RIG, T_e, MODEL, seq=i)
        res = pnp_joint(uv, RIG, P, sc)
        out = f.add(res.T_ecm_needle, T_w, res.covariance)
    assert out.n_views == 5
    dt, dr = pose_error(out.T_ecm_needle, T_en[-1])
    assert dt < 1e-6 and dr < np.deg2rad(1e-4)


@pytest.mark.slow
def test_fusion_over_five_views_beats_one_view_at_1px():
    """The ECM yaw joint moves 0.05 rad between views; one joint PnP estimate per view."""
    rng = np.random.default_rng(4)
    oracle = Oracle(noise_px=1.0, seed=5)
    e_one, e_fused = [], []
    seq = 0
    for _ in range(40):
        _, T_we, T_en = multiview_scenario(rng, RIG, MODEL, EcmArm(), n_views=5, joint=0, step_rad=0.05)
        f = MultiViewFusion(k=5)
        for T_w, T_e in zip(T_we, T_en):
            uv, sc = oracle.stereo(RIG, T_e, MODEL, seq=seq)
            seq += 1
            res = pnp_joint(uv, RIG, P, sc)
            fused = f.add(res.T_ecm_needle, T_w, res.covariance)
        e_one.append(pose_error(res.T_ecm_needle, T_en[-1]))
        e_fused.append(pose_error(fused.T_ecm_needle, T_en[-1]))
    e_one, e_fused = np.array(e_one), np.array(e_fused)
    assert e_fused[:, 0].mean() < e_one[:, 0].mean()
    assert e_fused[:, 1].mean() < e_one[:, 1].mean()


def test_queue_keeps_the_last_k():
    rng = np.random.default_rng(6)
    T0 = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    f = MultiViewFusion(k=3)
    for i in range(7):
        out = f.add(jitter(T0, rng, 0.2, 0.2), seq=i)
    assert len(f) == 3 and out.n_queued == 3
    assert [e.seq for e in f.queue] == [4, 5, 6]


def test_reset_when_the_needle_moves_not_on_one_outlier():
    rng = np.random.default_rng(7)
    A = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    B = make_T(A[:3, :3], A[:3, 3] + [0.03, 0.0, 0.0])       # the needle moved by 3 cm
    f = MultiViewFusion(k=5, reset_after=3)
    for _ in range(5):
        f.add(jitter(A, rng, 0.2, 0.2))
    out = f.add(jitter(B, rng, 0.2, 0.2))                   # one estimate far away: an outlier
    assert not out.reset and out.n_views == 4
    assert pose_error(out.T_ecm_needle, A)[0] < 1e-3
    out = f.add(jitter(B, rng, 0.2, 0.2))
    assert not out.reset
    out = f.add(jitter(B, rng, 0.2, 0.2))                   # third in a row that agree: moved
    assert out.reset and out.n_queued == 3 and out.n_views == 3
    assert pose_error(out.T_ecm_needle, B)[0] < 1e-3
    assert f.resets == 1


def test_reset_on_sequence_change_and_explicit_reset():
    rng = np.random.default_rng(8)
    A = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    f = MultiViewFusion()
    for _ in range(3):
        f.add(jitter(A, rng, 0.2, 0.2), sequence=1)
    out = f.add(jitter(A, rng, 0.2, 0.2), sequence=2)
    assert out.reset and out.n_queued == 1
    f.reset()
    assert len(f) == 0
    with pytest.raises(ValueError):
        MultiViewFusion(k=0)


def test_covariance_weighting_is_used_when_every_view_has_one():
    rng = np.random.default_rng(9)
    T0 = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    f = MultiViewFusion()
    for _ in range(4):
        out = f.add(jitter(T0, rng, 0.3, 0.3), covariance=cov)
    # covariance intersection: the views' errors may move together, so n of them do not
    # divide the covariance by n (the information mean's own figure, cov / 4, is the bound)
    assert out.covariance is not None and np.allclose(out.covariance, cov)
    out = f.add(jitter(T0, rng, 0.3, 0.3))                 # one without: plain mean
    assert out.covariance is None
    off = MultiViewFusion(use_covariance=False)
    assert off.add(T0, covariance=cov).covariance is None


def test_a_shared_position_error_is_not_averaged_nor_weighs_the_views():
    """Two views: one pins x, the other y, each within the shared model error declared inside
    its covariance. Weighed by their own parts, the fused position takes x from the first and y
    from the second; the shared error is added back once."""
    s = 5e-4                                                        # 0.5 mm, shared
    own_x, own_y = np.diag([1e-4] * 3 + [1e-10, 1e-6, 1e-6]), np.diag([1e-4] * 3 + [1e-6, 1e-10, 1e-6])
    common = np.diag([0.0] * 3 + [s * s] * 3)
    T_true = make_T(np.eye(3), [0.0, 0.0, -0.15])
    Ta = make_T(np.eye(3), [0.0, 0.0005, -0.15])                   # right in x, 0.5 mm off in y
    Tb = make_T(np.eye(3), [0.0005, 0.0, -0.15])                   # right in y, 0.5 mm off in x
    for shared, expect_mm in ((True, 0.0), (False, 0.05)):
        f = MultiViewFusion()
        f.add(Ta, covariance=own_x + common, common_sigma_m=s if shared else 0.0)
        out = f.add(Tb, covariance=own_y + common, common_sigma_m=s if shared else 0.0)
        err_mm = pose_error(out.T_ecm_needle, T_true)[0] * 1e3
        assert err_mm < 0.01 if shared else err_mm > expect_mm      # else each view's y/x drags
        if shared:
            assert out.common_sigma_m == s
            assert np.linalg.eigvalsh(out.covariance[3:, 3:]).min() >= s * s
    # a producer that did not put it in: its covariance is used as it is
    f = MultiViewFusion()
    out = f.add(Ta, covariance=np.diag([1e-4] * 3 + [1e-10] * 3), common_sigma_m=s)
    assert np.isfinite(out.covariance).all()


def test_a_shared_orientation_error_is_added_back_once_not_averaged_down():
    """Five alike views, each declaring a shared orientation error inside its covariance: the
    fused covariance keeps that error whole (averaging views does not shrink it); declared as
    not shared, it is weighed with the views' own part and the fused covariance is smaller."""
    s = math.radians(0.25)
    own = np.diag([math.radians(0.1) ** 2] * 3 + [1e-8] * 3)
    cov = own + np.diag([s * s] * 3 + [0.0] * 3)
    T = make_T(np.eye(3), [0.0, 0.0, -0.15])
    rot_min = {}
    for shared in (True, False):
        f = MultiViewFusion()
        for _ in range(5):
            out = f.add(T, covariance=cov, common_sigma_rad=s if shared else 0.0)
        assert out.common_sigma_rad == (s if shared else 0.0)
        rot_min[shared] = np.linalg.eigvalsh(out.covariance[:3, :3]).min()
    assert rot_min[True] >= s * s and rot_min[False] < rot_min[True]


def test_views_unsure_of_the_tip_do_not_decide_the_turn_between_them():
    """Each view's covariance spans its end-for-end turn (a half turn about nearly the same
    axis, as the pose nodes state an unsure end identity). Weighed by such covariances as they
    are, the fused rotation about that axis is left to the views' thin cross-terms and lands
    far outside the views; weighed within the inlier gate it stays among them."""
    fused, raw, worst = [], [], []
    for seed in range(8):
        rng = np.random.default_rng(seed)
        T0 = make_T(np.eye(3), [0, 0, -0.15])
        Ts, Cs = [], []
        for _ in range(5):
            Ts.append(make_T(rotvec_to_R(rng.normal(size=3) * np.radians(1.0)),
                             [0, 0, -0.15] + rng.normal(size=3) * 1e-4))
            u = np.r_[np.array([0.05 * rng.normal(), 0.05 * rng.normal(), 1.0]) * np.pi, 0, 0, 0]
            Cs.append(np.diag([np.radians(1.0) ** 2] * 3 + [1e-4 ** 2] * 3) + 0.5 * np.outer(u, u))
        T, inl, cov = fuse_poses(Ts, Cs)
        assert inl.all()
        fused.append(pose_error(T, T0)[1])
        raw.append(pose_error(information_mean(Ts, Cs)[0], T0)[1])
        worst.append(max(pose_error(t, T0)[1] for t in Ts))
    assert np.mean(fused) < 1.25 * np.mean(worst) and np.mean(raw) > 2.0 * np.mean(worst)


def test_views_that_each_could_not_decide_give_an_ambiguous_fused_pose():
    """Averaging views that are each flagged does not decide: the fused pose is flagged and
    keeps their spread; one view that did decide is enough to fuse as before."""
    rng = np.random.default_rng(4)
    T0 = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    turn = np.r_[0.0, 0.0, np.pi, 0.0, 0.0, 0.0]
    unsure = np.diag([1e-4] * 3 + [1e-6] * 3) + 0.5 * np.outer(turn, turn)
    f = MultiViewFusion()
    for _ in range(3):
        out = f.add(jitter(T0, rng, 0.3, 0.3), covariance=unsure, ambiguous=True)
    assert out.ambiguous and np.linalg.eigvalsh(out.covariance[:3, :3]).max() > 4.0   # spans the turn
    out = f.add(jitter(T0, rng, 0.3, 0.3), covariance=np.diag([1e-4] * 3 + [1e-6] * 3), ambiguous=False)
    assert not out.ambiguous and out.n_views == 4


def test_the_tip_is_decided_by_the_views_evidence_not_by_their_count():
    rng = np.random.default_rng(5)
    T0 = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    turn = make_T(rotvec_to_R([0.0, np.pi, 0.0]), [0.0, 0.0, 0.0])   # end for end, same origin
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    logit = lambda p: np.log(p / (1 - p))                             # noqa: E731
    f = MultiViewFusion()
    for p in (0.9, 0.7, None):
        out = f.add(jitter(T0, rng, 0.3, 0.3), covariance=cov, end_identity=p)
    # the mean log-odds of the views that stated one
    assert out.end_identity == pytest.approx(1 / (1 + np.exp(-(logit(0.9) + logit(0.7)) / 2)))
    # below 0.95 the fused pose is an undecided tip, as one view's would be: flagged, spanning the turn
    d = np.r_[np.pi * (out.T_ecm_needle[:3, :3] @ [0.0, 1.0, 0.0]), np.zeros(3)]
    assert out.ambiguous and out.turned == 0
    assert d @ np.linalg.solve(out.covariance, d) < 1.0 / (1.0 - out.end_identity) + 0.5
    # a weaker view turned end for end: not averaged in, but it contests the tip
    out = f.add(T0 @ turn, covariance=cov, end_identity=0.8)
    assert out.n_views == 3 and out.turned == 1 and pose_error(out.T_ecm_needle, T0)[1] < 0.05
    p = 1 / (1 + np.exp(-(logit(0.9) + logit(0.7) - logit(0.8)) / 3))
    assert out.end_identity == pytest.approx(p) and out.ambiguous
    d = np.r_[np.pi * (out.T_ecm_needle[:3, :3] @ [0.0, 1.0, 0.0]), np.zeros(3)]   # its turn, about the arc's axis
    assert d @ np.linalg.solve(out.covariance, d) < 1.0 / (1.0 - p) + 0.5
    # turned views with more evidence than the others: the fused pose is theirs
    out = f.add(T0 @ turn, covariance=cov, end_identity=0.999)
    assert out.turned == 3 and out.n_views == 2
    assert pose_error(out.T_ecm_needle, T0 @ turn)[1] < 1e-6 and out.end_identity < 0.95
    assert MultiViewFusion().add(T0).end_identity is None


def _delta(T, T_ref):
    """[rotation vector of R R_ref^T, t - t_ref] (ECM frame)."""
    return np.r_[R_to_rotvec(T[:3, :3] @ T_ref[:3, :3].T), T[:3, 3] - T_ref[:3, 3]]


def test_mirror_covariance_is_the_mirror_images_first_order():
    """Far from the eye (the line of sight held), a small [w, v] step of a pose moves its mirror
    image as ``mirror_covariance``'s Jacobian says: compared by finite differences."""
    T = make_T(rotvec_to_R([0.4, -0.3, 0.2]), [0.01, -0.02, 5.0])
    M = mirror_pose(T, MODEL)
    eps, J = 1e-6, np.zeros((6, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        Tk = make_T(rotvec_to_R(d[:3]) @ T[:3, :3], T[:3, 3] + d[3:])
        J[:, k] = _delta(mirror_pose(Tk, MODEL), M) / eps
    S = np.diag([0.05] * 3 + [1e-3] * 3) @ np.random.default_rng(0).normal(size=(6, 6))   # 3 deg, 1 mm
    C = S @ S.T
    got, want = mirror_covariance(T, C, MODEL), J @ C @ J.T
    sd = np.sqrt(np.diag(want))
    assert np.abs(got - want).max() > 0 and np.all(np.abs(got - want) < 0.02 * np.outer(sd, sd))


def test_a_group_reads_a_view_unsure_of_the_mirror_image_as_the_other_views_show_it():
    """A still needle seen from five endoscope poses: two views flagged ambiguous read its
    mirror image (which moves with the viewpoint, the needle does not). The group takes their
    mirror readings where the others agree: all five fused, the pose right and decided."""
    rng = np.random.default_rng(7)
    T_world_needle = make_T(rotvec_to_R([1.2, 0.3, -0.4]), [0.0, 0.0, 0.0])
    cov = np.diag([np.deg2rad(2.0) ** 2] * 3 + [0.5e-3 ** 2] * 3)
    f = MultiViewFusion()
    for i, (a, mirrored) in enumerate(zip((-0.4, -0.2, 0.0, 0.2, 0.4), (False, True, False, True, False))):
        T_world_ecm = make_T(rotvec_to_R([0.0, a, 0.0]), rotvec_to_R([0.0, a, 0.0]) @ [0.0, 0.0, -0.12])
        T = inv_T(T_world_ecm) @ T_world_needle
        T = jitter(mirror_pose(T, MODEL) if mirrored else T, rng, 0.2, 0.5)
        out = f.add(T, T_world_ecm, cov, seq=i, ambiguous=mirrored or i == 4)
    assert out.n_views == 5 and not out.ambiguous
    dt, dr = pose_error(out.T_world_needle, T_world_needle)
    assert dt < 0.5e-3 and dr < np.deg2rad(1.5)
    # without the mirror readings the two are outliers: what the group gained
    Ts = [np.asarray(e.T_world_needle) for e in f.queue]
    assert (pose_error(Ts[1], T_world_needle)[1] > np.deg2rad(20)
            and pose_error(Ts[3], T_world_needle)[1] > np.deg2rad(20))


def test_mirror_consensus_counts_views_then_their_own_readings():
    """Every view unsure and the viewpoint nearly still: the mirror images agree as well as the
    readings do, and the readings the views gave themselves win."""
    T = make_T(rotvec_to_R([1.2, 0.3, -0.4]), [0.0, 0.0, 0.1])
    M = mirror_pose(T, MODEL)
    assert pose_error(M, T)[1] > np.deg2rad(20)
    take = mirror_consensus([T, T, M], [M, M, T], 0.005, np.deg2rad(15))
    assert take.tolist() == [False, False, True]
    assert not mirror_consensus([T, M], [None, None], 0.005, np.deg2rad(15)).any()


def test_the_turn_a_view_is_unsure_of_does_not_weigh_its_reading():
    """A view unsure of its tip states a covariance widened over its turn; the fused pose is
    weighed as if each view had stated the covariance of its reading alone."""
    rng = np.random.default_rng(3)
    T0 = make_T(rotvec_to_R([0.1, 0.2, 0.3]), [0.0, 0.01, -0.2])
    views = []
    for _ in range(3):
        A = rng.normal(size=(6, 6)) * np.r_[[0.02] * 3, [3e-4] * 3][:, None]
        views.append((jitter(T0, rng, 0.3, 1.0), A @ A.T + np.diag([1e-6] * 6)))
    sure, unsure = MultiViewFusion(), MultiViewFusion()
    for T, C in views:
        a = sure.add(T, covariance=C, end_identity=0.99)
        b = unsure.add(T, covariance=identity_covariance(T, C, MODEL, 0.9), end_identity=0.9, ambiguous=True)
    assert pose_error(a.T_ecm_needle, b.T_ecm_needle)[1] < 1e-9
    assert b.ambiguous and not a.ambiguous


def test_a_weighted_rotation_is_held_among_the_views():
    T_mean = make_T(np.eye(3), [0.0, 0.0, 0.1])
    Ts = [make_T(rotvec_to_R([0.0, 0.0, s * 0.03]), [0.0, 0.0, 0.1]) for s in (-1, 1)]
    far = make_T(rotvec_to_R([0.0, 0.0, 0.1]), [0.001, 0.0, 0.1])
    held = within_views(far, Ts, T_mean)
    np.testing.assert_allclose(held[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(held[:3, 3], far[:3, 3])           # the position keeps its weighting
    near = make_T(rotvec_to_R([0.0, 0.0, 0.02]), [0.001, 0.0, 0.1])
    np.testing.assert_allclose(within_views(near, Ts, T_mean), near)
