"""Dense refinement (common/geometry/refine.py) on synthetic observations: no process, no network."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.observations import NoPose
from common.geometry.oracle import perturb_pose
from common.geometry.pnp import pnp_joint
from common.geometry.refine import (
    ArcObservation,
    DenseRefiner,
    RefineConfig,
    RefineError,
    mirror_pose,
    project_centreline,
    refine_pose,
)
from common.geometry.transforms import (
    make_T,
    pose_error,
    quat_to_R,
    rotvec_to_R,
    transform_points,
)
from common.runtime.messages import Keypoints

RIG = StereoRig.default()
NEEDLE = NeedleModel()
REFINER = DenseRefiner(RIG, NEEDLE)


def random_pose(rng, dist=(0.10, 0.25), rig=RIG):
    """A needle pose 10-25 cm in front of the endoscope with its whole arc in both images."""
    while True:
        d = rng.uniform(*dist)
        ray = np.array([rng.uniform(-0.45, 0.45), rng.uniform(-0.25, 0.25), 1.0])
        p_cam = ray / np.linalg.norm(ray) * d
        q = rng.normal(size=4)
        T = make_T(quat_to_R(q / np.linalg.norm(q)), rig.left.T_ecm_cam[:3, :3] @ p_cam)
        if all(cam.in_image(cam.project_from_ecm(transform_points(T, NEEDLE.sample_arc(64)))).all()
               for cam in rig.cameras):
            return T


def observe(T, rng=None, kp_px=0.0, curve_px=0.0, rig=RIG):
    """Keypoints (plus Gaussian noise) and the dense centreline (plus normal noise) per camera."""
    obs = {}
    for cam in rig.cameras:
        uv = cam.project_from_ecm(transform_points(T, NEEDLE.keypoints()))
        c = project_centreline(cam, NEEDLE, T)
        if kp_px:
            uv = uv + rng.normal(scale=kp_px, size=uv.shape)
        if curve_px:
            tang = np.gradient(c, axis=0)
            nrm = np.stack([-tang[:, 1], tang[:, 0]], 1) / np.linalg.norm(tang, axis=1)[:, None]
            c = c + nrm * rng.normal(scale=curve_px, size=(len(c), 1))
        obs[cam.name] = ArcObservation(uv, np.ones(5), c, np.ones(len(c)))
    return obs


def perturb(T, rng, deg=3.0, mm=2.0):
    return perturb_pose(T, rng, mm, deg)


def errors_mm_deg(T_est, T_true):
    dt, dr = pose_error(T_est, T_true)
    return dt * 1e3, np.degrees(dr)


def joint_candidates(obs):
    pj = pnp_joint({k: o.uv for k, o in obs.items()}, RIG, NEEDLE.keypoints(),
                   {k: o.scores for k, o in obs.items()})
    return pj, [c.T_ecm_needle for c in pj.candidates]


def view_pose(angle_deg, dist=0.15, spin_deg=0.0):
    """Needle straight ahead whose plane makes ``angle_deg`` with the line of sight (0: edge-on)."""
    t = np.array([0.0, 0.0, -dist])                      # ahead of the endoscope (-z_ecm)
    a = np.deg2rad(angle_deg)
    n = np.array([0.0, np.cos(a), np.sin(a)])            # plane normal; sight line is z
    e1 = np.array([np.cos(np.deg2rad(spin_deg)), 0.0, 0.0])
    e1 = e1 - (e1 @ n) * n
    e1 /= np.linalg.norm(e1)
    return make_T(np.stack([e1, np.cross(n, e1), n], axis=1), t)


# ------------------------------------------------------------------ exactness

def view_angle_deg(T, rig=RIG):
    """Angle between the needle's plane and the line of sight to it (0: edge-on)."""
    v = T[:3, 3] - rig.left.T_ecm_cam[:3, 3]
    return np.degrees(np.arcsin(abs(T[:3, 2] @ v) / np.linalg.norm(v)))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2 ** 32 - 1))
def test_noise_free_is_exact_from_a_perturbed_start(seed):
    """Every view but the nearly edge-on ones (there the cost has nearby local minima; those
    views are flagged, see the edge-on test) and the nearly face-on ones: within 10 deg of
    face-on, a start 2 mm off in translation can pull the weakly held tilt into the mirror's
    basin (2 of 1500 random views ended 12-16 deg off). Solving for the translation first
    avoided it but cost a third more time and some accuracy on the bench; the pipeline starts
    from the PnP's minima, from which face-on views are exact (next tests)."""
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    while not 15.0 <= view_angle_deg(T) <= 80.0:
        T = random_pose(rng)
    res = REFINER.refine(observe(T), [perturb(T, rng)])
    dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
    assert dt_mm < 1e-3 and dr_deg < 1e-4, (dt_mm, dr_deg)
    assert res.rms_px < 1e-4
    # an exact fit still reports a proper (positive definite) uncertainty
    assert np.linalg.eigvalsh(res.covariance).min() > 0


def test_noise_free_face_on_views_are_exact_from_the_joint_pnp_candidates():
    rng = np.random.default_rng(11)
    for _ in range(8):
        T = random_pose(rng)
        while view_angle_deg(T) < 80.0:
            T = random_pose(rng)
        obs = observe(T)
        res = refine_pose(RIG, NEEDLE, obs, joint_candidates(obs)[1])
        dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
        assert dt_mm < 1e-3 and dr_deg < 1e-4, (dt_mm, dr_deg, view_angle_deg(T))


def test_noise_free_is_exact_from_the_joint_pnp_candidates():
    rng = np.random.default_rng(7)
    for _ in range(10):
        T = random_pose(rng)
        while view_angle_deg(T) < 15.0:          # (nearly edge-on: keypoints on a line, no PnP)
            T = random_pose(rng)
        obs = observe(T)
        res = refine_pose(RIG, NEEDLE, obs, joint_candidates(obs)[1])
        dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
        assert dt_mm < 1e-3 and dr_deg < 1e-4


def test_partly_hidden_needle_is_still_exact():
    """Tail half hidden in both images (D, E missing): observed -> model residuals do not care."""
    rng = np.random.default_rng(3)
    T = random_pose(rng)
    obs = observe(T)
    for o in obs.values():
        o.uv[3:] = np.nan
        o.scores[3:] = 0.0
        o.centreline = o.centreline[: len(o.centreline) // 2]
        o.centreline_w = o.centreline_w[: len(o.centreline)]
    res = REFINER.refine(obs, [perturb(T, rng)])
    dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
    assert dt_mm < 1e-3 and dr_deg < 1e-4


def test_centreline_alone_fixes_the_arc():
    """No keypoints at all: the arc must cover every observed point, so its ends are pinned."""
    rng = np.random.default_rng(4)
    T = random_pose(rng)
    obs = {k: ArcObservation(centreline=o.centreline) for k, o in observe(T).items()}
    res = REFINER.refine(obs, [perturb(T, rng, deg=2.0, mm=1.0)])
    dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
    assert dt_mm < 1e-3 and dr_deg < 1e-4


def test_one_camera_needs_min_cameras_1_and_is_exact_without_noise():
    rng = np.random.default_rng(5)
    T = random_pose(rng)
    obs = {"left": observe(T)["left"]}
    with pytest.raises(RefineError) as e:
        REFINER.refine(obs, [perturb(T, rng)])
    assert e.value.reason == "too_few_cameras" and "seen by 1 camera(s) (left)" in str(e.value)
    res = DenseRefiner(RIG, NEEDLE, RefineConfig(min_cameras=1)).refine(obs, [perturb(T, rng)])
    dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
    assert dt_mm < 1e-3 and dr_deg < 1e-4


def test_distorted_cameras_are_undistorted_first():
    rig = StereoRig.default()
    for cam in rig.cameras:
        cam.dist = np.array([-0.08, 0.02, 0.0005, -0.0003, 0.0])
    rng = np.random.default_rng(6)
    T = random_pose(rng, rig=rig)
    res = refine_pose(rig, NEEDLE, observe(T, rig=rig), [perturb(T, rng)])
    dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
    # OpenCV's iterative undistortion is good to ~1e-4 px here
    assert dt_mm < 0.01 and dr_deg < 1e-2


# ------------------------------------------------------------------ with noise

@pytest.fixture(scope="module")
def noisy_runs():
    """40 random poses, 1 px keypoint and 0.5 px centreline noise: refined vs pnp_joint."""
    rng = np.random.default_rng(2024)
    rows = []
    for _ in range(40):
        T = random_pose(rng)
        obs = observe(T, rng, kp_px=1.0, curve_px=0.5)
        try:
            pj, cands = joint_candidates(obs)
        except NoPose:                            # keypoints (nearly) on a line: no PnP start
            continue
        res = REFINER.refine(obs, cands)
        d = _delta(T, res.T_ecm_needle)
        nees = float(d @ np.linalg.solve(res.covariance, d))
        rows.append((*errors_mm_deg(res.T_ecm_needle, T), *errors_mm_deg(pj.T_ecm_needle, T), nees))
    return np.array(rows)


def _delta(T, T_ref):
    from common.geometry.transforms import R_to_rotvec
    return np.concatenate([R_to_rotvec(T[:3, :3] @ T_ref[:3, :3].T), T[:3, 3] - T_ref[:3, 3]])


def test_refined_beats_keypoint_only_joint_fit(noisy_runs):
    r = noisy_runs
    assert len(r) >= 35
    print(f"\nrefined   position mean {r[:, 0].mean():.2f} mm, median {np.median(r[:, 0]):.2f} mm; "
          f"orientation mean {r[:, 1].mean():.2f} deg, median {np.median(r[:, 1]):.2f} deg")
    print(f"pnp_joint position mean {r[:, 2].mean():.2f} mm, median {np.median(r[:, 2]):.2f} mm; "
          f"orientation mean {r[:, 3].mean():.2f} deg, median {np.median(r[:, 3]):.2f} deg")
    assert r[:, 0].mean() * 2.0 <= r[:, 2].mean()
    assert np.median(r[:, 0]) * 2.0 <= np.median(r[:, 2])
    assert r[:, 1].mean() < r[:, 3].mean() and np.median(r[:, 1]) < np.median(r[:, 3])


def test_covariance_is_honest(noisy_runs):
    """The true pose lies within the stated uncertainty: the normalised squared error follows
    chi-square(6) closely enough (its 99% point is 16.8)."""
    nees = noisy_runs[:, 4]
    print(f"\nNEES median {np.median(nees):.2f} (chi2(6): 5.35), beyond 16.8: {(nees > 16.8).mean():.0%}")
    assert 2.0 < np.median(nees) < 10.0
    assert (nees > 16.8).mean() <= 0.15


def test_edge_on_needle_is_ambiguous_with_a_large_covariance():
    rng = np.random.default_rng(11)
    T_edge, T_oblique = view_pose(1.0, spin_deg=20.0), view_pose(45.0, spin_deg=20.0)
    sd_rot = {}
    for name, T in (("edge", T_edge), ("oblique", T_oblique)):
        obs = observe(T, rng, kp_px=0.5, curve_px=0.25)
        res = REFINER.refine(obs, joint_candidates(obs)[1])
        sd_rot[name] = np.degrees(np.sqrt(np.linalg.eigvalsh(res.covariance[:3, :3]).max()))
        if name == "edge":
            assert res.ambiguous and "edge_on" in res.reasons
            assert res.view_angle_deg < 2.0
        else:
            assert "edge_on" not in res.reasons
    assert sd_rot["edge"] > 20.0, sd_rot
    assert sd_rot["edge"] > 10.0 * sd_rot["oblique"], sd_rot


def test_competing_minima_inflate_the_covariance_to_cover_each_other():
    """When two distinct minima fit nearly equally, the result is flagged and its covariance
    spans the other solution (the mixture spread), whichever one is reported."""
    rng = np.random.default_rng(12)
    found = 0
    for _ in range(60):
        T = random_pose(rng)
        obs = observe(T, rng, kp_px=1.0, curve_px=0.5)
        res = REFINER.refine(obs, joint_candidates(obs)[1])
        if "competing_candidates" not in res.reasons:
            continue
        found += 1
        for T_other, _ in res.candidates[1:2]:
            d = _delta(T_other, res.T_ecm_needle)
            assert d @ np.linalg.solve(res.covariance, d) <= 1.0 + 1e-6
    assert found >= 1


def test_centreline_outliers_and_a_spur_past_the_tail_are_shrugged_off():
    """10% of the centreline thrown 20 px off, or the thread's first 15 px taken for needle past
    the tail: the robust fit stays near the clean one."""
    rng = np.random.default_rng(31)
    clean, outliers, spur = [], [], []
    for _ in range(30):
        T = random_pose(rng)
        obs = observe(T, rng, kp_px=0.5, curve_px=0.25)
        cands = joint_candidates(obs)[1]
        clean.append(errors_mm_deg(REFINER.refine(obs, cands).T_ecm_needle, T)[0])
        bad, thread = {}, {}
        for k, o in obs.items():
            c = o.centreline.copy()
            idx = rng.choice(len(c), len(c) // 10, replace=False)
            ang = rng.uniform(0, 2 * np.pi, len(idx))
            c[idx] += 20.0 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
            bad[k] = ArcObservation(o.uv, o.scores, c)
            tan = o.centreline[-1] - o.centreline[-2]
            ext = o.centreline[-1] + np.arange(1, 16)[:, None] * tan / np.linalg.norm(tan)
            thread[k] = ArcObservation(o.uv, o.scores, np.concatenate([o.centreline, ext]))
        outliers.append(errors_mm_deg(REFINER.refine(bad, cands).T_ecm_needle, T)[0])
        spur.append(errors_mm_deg(REFINER.refine(thread, cands).T_ecm_needle, T)[0])
    print(f"\nposition median: clean {np.median(clean):.2f} mm, 10% outliers {np.median(outliers):.2f} mm, "
          f"spur {np.median(spur):.2f} mm")
    assert np.median(outliers) < 1.0 and np.median(spur) < 1.0


# ------------------------------------------------------------------ pieces and bad input

def test_analytic_jacobian_matches_finite_differences():
    """With the feet held: keypoint rows and the distance rows of points whose foot is inside
    the arc are the residuals' exact derivatives (at a foot the distance needs no foot
    derivative); past an end the (normal, overshoot) pair leaves out the turn of the end's
    tangent, which cancels in the gradient of their squares: the cost's gradient is exact."""
    from common.geometry.arc_problem import ArcProblem
    rng = np.random.default_rng(21)
    T = random_pose(rng)
    obs = observe(T, rng, kp_px=1.0, curve_px=0.5)
    prob = ArcProblem(REFINER._static, obs)
    T0 = perturb(T, rng, deg=0.5, mm=0.3)
    R0, t0 = T0[None, :3, :3], T0[None, :3, 3]
    cs = prob.feet(R0, t0)
    for _ in range(3):                           # converge the feet
        cs = prob.feet(R0, t0, cs)
    r, J, valid = prob.evaluate(R0, t0, cs)
    assert valid[0]

    def at(d):
        return prob.evaluate(rotvec_to_R(d[:3])[None] @ R0, t0 + d[3:], cs, jacobian=False)[0][0]

    Jfd = np.zeros_like(J[0])
    for i, h in enumerate([1e-6] * 3 + [1e-7] * 3):
        d = np.zeros(6)
        d[i] = h
        Jfd[:, i] = (at(d) - at(-d)) / (2 * h)
    M = prob.M
    inside = cs[0, :, 5:, 0] > np.cos(prob.half - np.deg2rad(1.0))     # feet away from the ends
    rows = np.concatenate([np.ones((2, 10), bool), inside, np.zeros((2, M), bool)], axis=1).ravel()
    rows &= prob.wp > 0
    assert rows.sum() > 100
    err = np.abs(J[0, rows] - Jfd[rows]) / np.abs(Jfd[rows]).max(axis=0)
    assert err.max() < 1e-3, err.max()       # (the feet are converged to ~1e-4 of a pixel)
    g, g_fd = J[0].T @ (prob.wp * r[0]), Jfd.T @ (prob.wp * r[0])
    assert np.allclose(g, g_fd, rtol=1e-4, atol=1e-6 * np.abs(g_fd).max())


def test_mirror_pose_is_an_involution_and_looks_alike_far_away():
    rng = np.random.default_rng(8)
    T = random_pose(rng, dist=(0.24, 0.25))
    Tm = mirror_pose(T, NEEDLE)
    dt, dr = pose_error(mirror_pose(Tm, NEEDLE), T)
    assert dt < 1e-12 and dr < 1e-9
    cam = RIG.left
    a = cam.project_from_ecm(transform_points(T, NEEDLE.sample_arc(32)))
    b = cam.project_from_ecm(transform_points(Tm, NEEDLE.sample_arc(32)))
    span = np.ptp(a, axis=0).max()
    # the same image up to perspective: a few percent of the needle's size
    assert np.abs(a - b).max() < 0.1 * span


def test_project_centreline_is_ordered_dense_and_in_image():
    T = view_pose(60.0, dist=0.12)
    c = project_centreline(RIG.left, NEEDLE, T)
    uv = RIG.left.project_from_ecm(transform_points(T, NEEDLE.keypoints()))
    assert np.allclose(c[0], uv[0]) and np.allclose(c[-1], uv[-1])
    gaps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert gaps.max() <= 1.0 + 1e-9
    behind = make_T(np.eye(3), [0.0, 0.0, 0.1])           # behind the endoscope
    assert project_centreline(RIG.left, NEEDLE, behind).shape == (0, 2)


def test_from_keypoints_message():
    T = view_pose(50.0)
    uv = RIG.right.project_from_ecm(transform_points(T, NEEDLE.keypoints()))
    c = project_centreline(RIG.right, NEEDLE, T)
    msg = Keypoints("right", 3, 0, True, uv, np.full(5, 0.9), 0.9, centreline=c,
                    centreline_w=np.ones(len(c)))
    o = ArcObservation.from_keypoints(msg)
    assert np.array_equal(o.uv, uv) and np.array_equal(o.centreline, c)
    empty = ArcObservation.from_keypoints(Keypoints.not_found("right", 3, 0, "oracle", "no needle"))
    assert empty.uv is None and empty.centreline is None


def test_result_fields():
    rng = np.random.default_rng(9)
    T = random_pose(rng)
    res = REFINER.refine(observe(T, rng, 0.5, 0.25), [perturb(T, rng)])
    assert res.covariance.shape == (6, 6)
    assert np.allclose(res.covariance, res.covariance.T)
    assert np.linalg.eigvalsh(res.covariance).min() > 0
    assert 0.0 < res.rms_px < 2.0 and 0.0 < res.rms_kp_px and 0.0 < res.rms_curve_px
    assert res.n_residuals >= 2 * 10 + 2 * 32           # 10 keypoint coordinates + curve points
    assert res.candidates[0][0] is res.T_ecm_needle


def test_bad_input_gives_a_reason_not_a_pose():
    T = view_pose(50.0)
    obs = observe(T)
    with pytest.raises(RefineError) as e:
        REFINER.refine(obs, [])
    assert e.value.reason == "no_candidates"
    with pytest.raises(RefineError) as e:
        REFINER.refine(obs, [np.full((4, 4), np.nan), np.eye(3)])
    assert e.value.reason == "no_candidates"
    with pytest.raises(RefineError) as e:
        REFINER.refine({}, [T])
    assert e.value.reason == "too_few_points"
    one_point = ArcObservation(np.where(np.arange(5)[:, None] == 0, obs["left"].uv, np.nan),
                               np.array([1.0, 0, 0, 0, 0]))
    with pytest.raises(RefineError) as e:
        REFINER.refine({"left": one_point}, [T])
    assert e.value.reason == "too_few_points"
    with pytest.raises(RefineError) as e:
        REFINER.refine({"left": ArcObservation(centreline=np.zeros((10, 3)))}, [T])
    assert e.value.reason == "bad_centreline"
    with pytest.raises(RefineError) as e:
        REFINER.refine({"left": ArcObservation(np.zeros((4, 2)), np.ones(4))}, [T])
    assert e.value.reason == "bad_keypoints"
    behind = make_T(np.eye(3), [0.0, 0.0, 0.15])          # needle behind the endoscope (+z_ecm)
    with pytest.raises(RefineError) as e:
        REFINER.refine(obs, [behind])
    assert e.value.reason == "no_valid_candidate"


def test_nan_centreline_points_are_left_out():
    rng = np.random.default_rng(10)
    T = random_pose(rng)
    obs = observe(T)
    for o in obs.values():
        o.centreline[::7] = np.nan
    res = REFINER.refine(obs, [perturb(T, rng)])
    dt_mm, dr_deg = errors_mm_deg(res.T_ecm_needle, T)
    assert dt_mm < 1e-3 and dr_deg < 1e-4


def test_config_is_checked():
    for bad in ({"max_curve_points": 1}, {"sigma_kp_px": 0.0}, {"cauchy_scale": -1.0},
                {"n_samples": 1}, {"max_iter": 0}, {"model_sigma_mm": -0.1}, {"model_sigma_mm": float("nan")}, {"model_sigma_deg": -1.0}):
        with pytest.raises(ValueError):
            RefineConfig(**bad)


def test_bench_reports_errors_and_times():
    from common.bench.refine_bench import run, table
    rows = run([0.0, 0.5], frames=4, progress=False)
    assert [r["noise_px"] for r in rows] == [0.0, 0.5] and all(r["failed"] == 0 for r in rows)
    assert rows[0]["refined"]["position_mm"]["mean"] < 1e-4
    assert rows[0]["refined"]["orientation_deg"]["mean"] < 1e-4
    assert 0 < rows[1]["refined"]["position_mm"]["mean"] < 5.0
    assert rows[1]["wall_ms"]["p50"] > 0 and rows[1]["cpu_ms"]["max"] >= rows[1]["cpu_ms"]["p50"]
    text = table(rows)
    assert text.count("\n") == 3 and "n/a" in text.splitlines()[2]
    # repeated passes see the same frames: the same errors, each frame's least time
    again = run([0.5], frames=4, progress=False, repeat=2)[0]
    assert again["repeat"] == 2 and again["refined"] == rows[1]["refined"]
    assert again["tracking"]["refined"] == rows[1]["tracking"]["refined"]
    assert 0 < again["node_cpu_ms"]["p50"] and again["cpu_ms"]["max"] >= again["cpu_ms"]["p50"]


def test_stated_centreline_noise_and_keypoints_placed_on_the_arc():
    rng = np.random.default_rng(11)
    T = random_pose(rng)
    obs = observe(T, rng, kp_px=0.3, curve_px=0.1)
    start = [perturb(T, rng)]
    base = REFINER.refine(obs, start)
    # the default sigma stated per observation is the same fit; a smaller one weighs the curve more
    same = {k: ArcObservation(o.uv, o.scores, o.centreline, o.centreline_w, RefineConfig().sigma_curve_px)
            for k, o in obs.items()}
    assert np.allclose(REFINER.refine(same, start).T_ecm_needle, base.T_ecm_needle, atol=1e-12)
    # B..D pushed along the arc (a weak-perspective placement's bias) move the pose unless they
    # are marked as placed on the arc, which leaves them out as if the detector had not given them
    shifted, marked, dropped = {}, {}, {}
    for k, o in obs.items():
        uv = o.uv.copy()
        uv[1:4] += 3.0 * (o.uv[4] - o.uv[0]) / np.linalg.norm(o.uv[4] - o.uv[0])
        shifted[k] = ArcObservation(uv, o.scores, o.centreline, o.centreline_w)
        marked[k] = ArcObservation(uv, o.scores, o.centreline, o.centreline_w,
                                   on_arc=np.array([False, True, True, True, False]))
        dropped[k] = ArcObservation(uv, np.array([1.0, 0, 0, 0, 1]), o.centreline, o.centreline_w)
    T_marked = REFINER.refine(marked, start).T_ecm_needle
    assert np.allclose(T_marked, REFINER.refine(dropped, start).T_ecm_needle, atol=1e-12)
    assert errors_mm_deg(T_marked, T)[1] < errors_mm_deg(REFINER.refine(shifted, start).T_ecm_needle, T)[1]
    with pytest.raises(RefineError) as e:
        REFINER.refine({k: ArcObservation(o.uv, o.scores, o.centreline, o.centreline_w, -1.0)
                        for k, o in obs.items()}, start)
    assert e.value.reason == "bad_centreline"


def test_correlated_centreline_points_widen_the_covariance_not_the_fit():
    """A detector stating that k neighbouring centreline points share their error: the pose is
    the same, the covariance of a curve-only fit k times the variance."""
    rng = np.random.default_rng(21)
    T = view_pose(45.0, spin_deg=20.0)
    obs = observe(T, rng, kp_px=0.5, curve_px=0.25)
    curve_only = {n: ArcObservation(centreline=o.centreline, centreline_w=o.centreline_w) for n, o in obs.items()}
    corr = {n: ArcObservation(centreline=o.centreline, centreline_w=o.centreline_w, centreline_corr_points=4.0)
            for n, o in obs.items()}
    starts = joint_candidates(obs)[1]
    images_only = DenseRefiner(RIG, NEEDLE, RefineConfig(model_sigma_mm=0.0, model_sigma_deg=0.0))  # images alone
    a, b = images_only.refine(curve_only, starts), images_only.refine(corr, starts)
    assert not a.ambiguous and np.allclose(a.T_ecm_needle, b.T_ecm_needle, atol=1e-12)
    # (up to the far competitor's share, exp(-chi2 / 2) of its offset, not scaled)
    assert np.allclose(b.covariance, 4.0 * a.covariance, rtol=2e-3)
    with pytest.raises(RefineError, match="centreline_corr_points"):
        images_only.refine({n: ArcObservation(centreline=o.centreline, centreline_corr_points=0.5)
                        for n, o in obs.items()}, starts)


def test_a_stated_keypoint_sigma_weighs_the_keypoints_as_the_config_would():
    """``keypoint_sigma_px`` from the detector stands for ``RefineConfig.sigma_kp_px``."""
    rng = np.random.default_rng(22)
    T = view_pose(50.0, spin_deg=-30.0)
    obs = observe(T, rng, kp_px=1.0, curve_px=0.25)
    starts = joint_candidates(obs)[1]
    stated = {n: replace(o, keypoint_sigma_px=2.0) for n, o in obs.items()}
    a = DenseRefiner(RIG, NEEDLE, RefineConfig(sigma_kp_px=2.0)).refine(obs, starts)
    b = REFINER.refine(stated, starts)
    assert np.allclose(a.T_ecm_needle, b.T_ecm_needle, atol=1e-12)
    assert np.allclose(a.covariance, b.covariance, rtol=1e-9)
    assert not np.allclose(REFINER.refine(obs, starts).T_ecm_needle, b.T_ecm_needle, atol=1e-9)
    with pytest.raises(RefineError, match="keypoint_sigma_px"):
        REFINER.refine({n: replace(o, keypoint_sigma_px=0.0) for n, o in obs.items()}, starts)


def test_the_model_error_floors_the_covariance():
    """Noise-free images claim near-certainty; the model's own orientation and position error
    (model_sigma_deg, model_sigma_mm) stays in the covariance, and with both 0 the images' own
    covariance is left as it was."""
    rng = np.random.default_rng(11)
    T = random_pose(rng)
    obs = observe(T, rng, kp_px=0.2, curve_px=0.1)
    starts = [perturb(T, rng)]
    res = REFINER.refine(obs, starts)
    bare = DenseRefiner(RIG, NEEDLE, RefineConfig(model_sigma_mm=0.0, model_sigma_deg=0.0)).refine(obs, starts)
    assert np.allclose(res.T_ecm_needle, bare.T_ecm_needle)
    cfg = REFINER.config
    assert cfg.model_sigma_mm > 0 and cfg.model_sigma_deg > 0
    f_t, f_r = (cfg.model_sigma_mm * 1e-3) ** 2, math.radians(cfg.model_sigma_deg) ** 2
    assert np.allclose(res.covariance - bare.covariance, np.diag([f_r] * 3 + [f_t] * 3), atol=1e-12)
    assert np.linalg.eigvalsh(res.covariance[3:, 3:]).min() >= f_t
    assert np.linalg.eigvalsh(res.covariance[:3, :3]).min() >= f_r
