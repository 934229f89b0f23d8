"""Pipeline I (common/geometry/pnp.py): exact at zero noise, joint beats average, no pose from bad input."""
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.observations import NoPose, stereo_observations
from common.geometry.oracle import (
    Oracle,
    needle_pose_in_view,
    random_needle_pose,
    true_keypoints,
    view_tilt_rad,
)
from common.geometry.pnp import initial_poses, pnp_average, pnp_joint, refine_starts, unsure_starts
from common.geometry.reprojection import ReprojectionProblem, pose_covariance, refine_pose_lm
from common.geometry.transforms import inv_T, make_T, pose_error, rotvec_to_R

RIG = StereoRig.default()
MODEL = NeedleModel()
P = MODEL.keypoints()
TOL_M, TOL_RAD = 1e-6, np.deg2rad(1e-4)


def exact_uv(T, rig=RIG):
    return {c.name: true_keypoints(c, T, MODEL)[0] for c in rig.cameras}


@st.composite
def poses_in_view(draw):
    """Random needle poses 10-25 cm away, in both images, not seen edge-on (> 75 deg tilt)."""
    d = draw(st.floats(0.10, 0.25))
    x = draw(st.floats(-0.35, 0.35))
    y = draw(st.floats(-0.3, 0.3))
    q = draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4))
    assume(np.linalg.norm(q) > 0.1)
    T = needle_pose_in_view(d, (x, y), q)
    assume(view_tilt_rad(T) < np.deg2rad(75))
    for cam in RIG.cameras:
        uv, vis = true_keypoints(cam, T, MODEL)
        assume(vis.all())
    return T


SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])


@SETTINGS
@given(poses_in_view())
def test_joint_exact_at_zero_noise(T):
    res = pnp_joint(exact_uv(T), RIG, P)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < TOL_M and dr < TOL_RAD
    assert res.rms_px < 1e-6
    assert res.method == "pnp_joint"


@SETTINGS
@given(poses_in_view())
def test_average_exact_at_zero_noise(T):
    res = pnp_average(exact_uv(T), RIG, P)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < TOL_M and dr < TOL_RAD
    for T_cam in res.per_camera.values():
        dt, dr = pose_error(T_cam, T)
        assert dt < TOL_M and dr < TOL_RAD


def test_a_half_turn_in_both_camera_frames_is_found():
    # found by hypothesis: the needle face-on and upside down in both images; OpenCV's IPPE lost
    # the right camera's solution without returning anything near a half turn
    c, s = -0.30885800684178477, 0.95110815978505836
    T = np.array([[c, 0.0, s, 1.5368440888388724e-05], [0.0, 1.0, 0.0, -2.8198665390780205e-02],
                  [-s, 0.0, c, -1.5368440888388724e-01], [0.0, 0.0, 0.0, 1.0]])
    for method in (pnp_average, pnp_joint):
        dt, dr = pose_error(method(exact_uv(T), RIG, P).T_ecm_needle, T)
        assert dt < TOL_M and dr < TOL_RAD, method.__name__


def test_a_near_half_turn_returned_far_off_by_ippe_is_found():
    # found by hypothesis: within 1e-7 rad of a half turn in both cameras IPPE returned
    # rotations of 2.68-3.46 rad, 0.4-0.6 rad off, neither near a half turn nor far worse in
    # reprojection than the other: pnp_average was 1.9 mm / 0.32 rad off at zero noise
    T = np.array([[0.0191273, -0.95543186, -0.29459143, 0.0], [0.95543182, 0.10428265, -0.27617958, 0.0715794],
                  [0.29459154, -0.27617946, 0.91484465, -0.23953369], [0.0, 0.0, 0.0, 1.0]])
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    for method in (pnp_average, pnp_joint):
        dt, dr = pose_error(method(exact_uv(T), RIG, P).T_ecm_needle, T)
        assert dt < TOL_M and dr < TOL_RAD, method.__name__


def test_raw_epnp_is_not_exact_on_coplanar_keypoints():
    """Why pnp_average refines by default: raw EPnP misses on the planar arc even at 0 px."""
    rng = np.random.default_rng(3)
    errs = []
    for _ in range(40):
        T = random_needle_pose(rng, RIG, MODEL)
        errs.append(pose_error(pnp_average(exact_uv(T), RIG, P, refine=False).T_ecm_needle, T))
    errs = np.array(errs)
    assert np.max(errs[:, 0]) > 1e-4 or np.max(errs[:, 1]) > np.deg2rad(1.0)


def _noisy_errors(method, sigma, n=80, seed=0):
    rng = np.random.default_rng(seed)
    oracle = Oracle(noise_px=sigma, seed=seed)
    out = []
    for i in range(n):
        T = random_needle_pose(rng, RIG, MODEL)
        uv, sc = oracle.stereo(RIG, T, MODEL, seq=i)
        out.append(pose_error(method(uv, RIG, P, sc).T_ecm_needle, T))
    return np.array(out)


def test_joint_beats_average_at_1px():
    e_avg = _noisy_errors(pnp_average, 1.0)
    e_joint = _noisy_errors(pnp_joint, 1.0)
    assert e_joint[:, 0].mean() < e_avg[:, 0].mean()
    assert e_joint[:, 1].mean() < e_avg[:, 1].mean()


def test_candidates_sorted_distinct_and_best_first():
    rng = np.random.default_rng(5)
    oracle = Oracle(noise_px=0.5, seed=1)
    for i in range(20):
        T = random_needle_pose(rng, RIG, MODEL)
        uv, sc = oracle.stereo(RIG, T, MODEL, seq=i)
        res = pnp_joint(uv, RIG, P, sc)
        costs = [c.cost for c in res.candidates]
        assert costs == sorted(costs)
        assert np.allclose(res.candidates[0].T_ecm_needle, res.T_ecm_needle)
        for a in range(len(res.candidates)):
            for b in range(a + 1, len(res.candidates)):
                dt, dr = pose_error(res.candidates[a].T_ecm_needle, res.candidates[b].T_ecm_needle)
                assert dt > 1e-4 or dr > np.deg2rad(0.05)
        assert res.covariance.shape == (6, 6)
        assert np.all(np.linalg.eigvalsh(res.covariance) > 0)


def test_planar_ambiguity_gives_two_candidates():
    """Both IPPE branches survive as distinct minima of the joint fit."""
    T = needle_pose_in_view(0.18, (0.05, 0.02), [0.9, 0.3, 0.2, 0.1])
    res = pnp_joint(exact_uv(T), RIG, P)
    assert len(res.candidates) >= 2
    assert res.candidates[1].cost > 1e3 * max(res.candidates[0].cost, 1e-20)
    assert not res.ambiguous


def test_lm_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    T = random_needle_pose(rng, RIG, MODEL)
    uv = exact_uv(T)
    uv = {k: v + rng.normal(size=v.shape) for k, v in uv.items()}
    scores = {"left": np.array([1, .7, .9, 1, .6]), "right": np.ones(5)}
    prob = ReprojectionProblem(list(stereo_observations(uv, RIG, P, scores).values()))
    r, J = prob.evaluate(T)
    Jn = np.zeros_like(J)
    eps = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        Tp = make_T(rotvec_to_R(d[:3]) @ T[:3, :3], T[:3, 3] + d[3:])
        Tm = make_T(rotvec_to_R(-d[:3]) @ T[:3, :3], T[:3, 3] - d[3:])
        Jn[:, k] = (prob.evaluate(Tp, False)[0] - prob.evaluate(Tm, False)[0]) / (2 * eps)
    assert np.abs(J - Jn).max() < 1e-5 * np.abs(J).max()


def test_lm_optimum_has_zero_gradient_and_consistent_covariance():
    rng = np.random.default_rng(4)
    T = random_needle_pose(rng, RIG, MODEL)
    uv = {k: v + rng.normal(size=v.shape) * 0.5 for k, v in exact_uv(T).items()}
    obs = list(stereo_observations(uv, RIG, P).values())
    fit = refine_pose_lm(T, obs)
    assert fit.converged
    g = fit.jacobian.T @ fit.residuals
    assert np.linalg.norm(g) < 1e-6 * np.linalg.norm(fit.jacobian) * max(np.linalg.norm(fit.residuals), 1)
    cov, unfixed = pose_covariance(fit.jacobian, fit.cost)
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and not unfixed
    # the floor: an exact fit still reports a finite, positive covariance
    cov0, _ = pose_covariance(fit.jacobian, 0.0, min_sigma_px=0.25)
    assert np.all(np.linalg.eigvalsh(cov0) > 0)


def test_scores_weight_and_low_scores_are_dropped():
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.1, 0])
    uv = exact_uv(T)
    bad = {k: v.copy() for k, v in uv.items()}
    bad["left"][2] += [40.0, -30.0]                     # a gross error on C in the left image
    scores = {"left": np.array([1, 1, 0.2, 1, 1.0]), "right": np.ones(5)}
    res = pnp_joint(bad, RIG, P, scores, min_score=0.5)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < TOL_M and dr < TOL_RAD
    assert list(res.used["left"]) == [0, 1, 3, 4]
    res = pnp_average(bad, RIG, P, scores, min_score=0.5)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < TOL_M and dr < TOL_RAD


def test_outlier_rejection_drops_a_gross_error():
    T = needle_pose_in_view(0.15, (0.05, 0.0), [1, 0.2, 0.1, 0])
    uv = exact_uv(T)
    uv["right"][3] += [25.0, 10.0]
    res = pnp_joint(uv, RIG, P, outlier_px=3.0)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < TOL_M and dr < TOL_RAD
    assert 3 not in res.used["right"]
    with_outlier = pnp_joint(uv, RIG, P)
    assert with_outlier.rms_px > 1.0


def test_one_camera_is_enough_and_three_points_are_not():
    T = needle_pose_in_view(0.12, (0.0, 0.1), [1, -0.3, 0.2, 0.4])
    uv = exact_uv(T)
    for f in (pnp_joint, pnp_average):
        res = f({"left": uv["left"]}, RIG, P)
        dt, dr = pose_error(res.T_ecm_needle, T)
        assert dt < TOL_M and dr < TOL_RAD
        three = {k: v.copy() for k, v in uv.items()}
        three["left"][:2] = np.nan
        three["right"][1:3] = np.nan
        with pytest.raises(NoPose) as e:
            f({"left": three["left"]}, RIG, P)
        assert e.value.reason == "too_few_points"


@pytest.mark.parametrize("method", [pnp_joint, pnp_average])
def test_degenerate_inputs_give_no_pose(method):
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.1, 0])
    uv = exact_uv(T)
    cases = {
        "too_few_points": {"left": np.full((5, 2), np.nan), "right": np.full((5, 2), np.nan)},
        "coincident": {k: np.tile([[500.0, 400.0]], (5, 1)) for k in uv},
        "collinear": {k: np.stack([np.linspace(100, 300, 5), np.linspace(200, 260, 5)], 1) for k in uv},
    }
    nan3 = {k: v.copy() for k, v in uv.items()}
    for k in nan3:
        nan3[k][[0, 4]] = np.nan
    cases["too_few_points "] = nan3
    inf = {k: v.copy() for k, v in uv.items()}
    for k in inf:
        inf[k][:2] = np.inf
    cases["too_few_points  "] = inf
    for reason, bad in cases.items():
        with pytest.raises(NoPose) as e:
            method(bad, RIG, P)
        assert e.value.reason == reason.strip(), reason
    with pytest.raises(NoPose):
        method({}, RIG, P)


@pytest.mark.parametrize("method", [pnp_joint, pnp_average])
def test_needle_behind_the_cameras_gives_no_pose(method):
    """Points behind a camera project point-mirrored; stereo shows the depth is negative."""
    T = needle_pose_in_view(0.15, (0.02, 0.01), [1, 0.2, 0.1, 0])
    T_behind = T.copy()
    T_behind[:3, 3] *= -1          # the same offset, behind the endoscope (+z_ecm)
    uv = {}
    for cam in RIG.cameras:
        p = (inv_T(cam.T_ecm_cam) @ T_behind)[:3, :3] @ P.T + (inv_T(cam.T_ecm_cam) @ T_behind)[:3, 3:4]
        assert np.all(p[2] < 0)
        uv[cam.name] = cam.project(p.T)
    with pytest.raises(NoPose) as e:
        method(uv, RIG, P)
    assert e.value.reason == "behind_camera"


def test_initial_poses_are_in_front_and_labelled():
    T = needle_pose_in_view(0.2, (0.1, -0.1), [0.5, 0.5, -0.5, 0.2])
    obs = stereo_observations(exact_uv(T), RIG, P)
    inits = initial_poses(obs["left"])
    labels = [lab for lab, _ in inits]
    assert "epnp:left" in labels and "ippe0:left" in labels
    for _, Ti in inits:
        p = (RIG.left.T_cam_ecm @ Ti)[:3, :3] @ P.T + (RIG.left.T_cam_ecm @ Ti)[:3, 3:4]
        assert np.all(p[2] > 0)


def test_distorted_camera_is_undistorted_first():
    rig = StereoRig.default()
    for cam in rig.cameras:
        cam.dist = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    T = needle_pose_in_view(0.16, (0.15, 0.1), [1, 0.3, -0.2, 0.1])
    uv = exact_uv(T, rig)
    res = pnp_joint(uv, rig, P)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < 1e-6 and dr < np.deg2rad(1e-3)


def test_max_rms_rejects_inconsistent_views():
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.1, 0])
    uv = exact_uv(T)
    uv["right"] = uv["right"] + np.array([[0, 30.0]])     # right image shifted down 30 px
    with pytest.raises(NoPose) as e:
        pnp_joint(uv, RIG, P, max_rms_px=5.0)
    assert e.value.reason == "high_residual"


def test_unsure_starts_try_the_keypoints_both_ways_round():
    """Fewer than 4 sure keypoints: starts from all of them, as given and tip-for-tail turned."""
    T = random_needle_pose(np.random.default_rng(8), RIG, MODEL)
    uv = {c.name: true_keypoints(c, T, MODEL)[0] for c in RIG.cameras}
    sc = {n: np.array([0.9, 0.3, 0.3, 0.3, 0.2]) for n in uv}
    with pytest.raises(NoPose, match="too_few_points"):
        refine_starts(uv, RIG, P, sc)
    starts = unsure_starts(uv, RIG, P, sc)
    errs = [np.degrees(pose_error(S, T)[1]) for S in starts]
    assert min(errs) < 1e-6                    # the keypoints as given: exact
    assert max(errs) > 90.0                    # and the reversed order's pose, far from it
    with pytest.raises(NoPose, match="too_few_points"):
        unsure_starts({n: np.where(np.arange(5)[:, None] < 3, u, np.nan) for n, u in uv.items()}, RIG, P, sc)
