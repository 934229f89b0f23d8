"""Pipeline II (common/geometry/triangulation.py): DLT, Arun with the reflection case, the pose."""
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.observations import NoPose
from common.geometry.oracle import (
    needle_pose_in_view,
    random_needle_pose,
    true_keypoints,
    view_tilt_rad,
)
from common.geometry.transforms import (
    make_T,
    pose_error,
    quat_to_R,
    rotvec_to_R,
    transform_points,
)
from common.geometry.triangulation import (
    arun_register,
    triangulate_dlt,
    triangulate_keypoints,
    triangulation_pose,
)

RIG = StereoRig.default()
MODEL = NeedleModel()
P = MODEL.keypoints()


def exact_uv(T):
    return {c.name: true_keypoints(c, T, MODEL)[0] for c in RIG.cameras}


def test_dlt_recovers_points_exactly():
    rng = np.random.default_rng(0)
    X = np.stack([rng.uniform(-0.05, 0.05, 50), rng.uniform(-0.05, 0.05, 50),
                  -rng.uniform(0.05, 0.3, 50)], axis=1)               # in front: -z_ecm
    uvl, uvr = RIG.left.project_from_ecm(X), RIG.right.project_from_ecm(X)
    Y = triangulate_dlt(uvl, uvr, RIG.left.P_ecm, RIG.right.P_ecm)
    assert np.abs(Y - X).max() < 1e-9


def test_dlt_nan_rows_stay_nan():
    X = np.array([[0.0, 0.0, -0.1], [0.01, 0.0, -0.2]])
    uvl, uvr = RIG.left.project_from_ecm(X), RIG.right.project_from_ecm(X)
    uvl[1] = np.nan
    Y = triangulate_dlt(uvl, uvr, RIG.left.P_ecm, RIG.right.P_ecm)
    assert np.all(np.isfinite(Y[0])) and np.all(np.isnan(Y[1]))
    with pytest.raises(ValueError):
        triangulate_dlt(uvl, uvr[:1], RIG.left.P_ecm, RIG.right.P_ecm)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4), st.lists(st.floats(-0.3, 0.3), min_size=3, max_size=3))
def test_arun_exact_for_planar_points(q, t):
    assume(np.linalg.norm(q) > 0.1)
    T = make_T(quat_to_R(q), t)
    T_est, rms = arun_register(P, transform_points(T, P))
    dt, dr = pose_error(T_est, T)
    assert dt < 1e-12 and dr < 1e-9 and rms < 1e-12
    assert np.linalg.det(T_est[:3, :3]) > 0


def test_arun_reflection_case():
    """Planar points whose SVD solution is a reflection: the fix yields the proper rotation."""
    rng = np.random.default_rng(1)
    found = 0
    for _ in range(200):
        T = make_T(rotvec_to_R(rng.normal(size=3) * 2), rng.normal(size=3) * 0.1)
        Q = transform_points(T, P)
        # without the fix: would the plain SVD answer be a reflection?
        Pc, Qc = P - P.mean(0), Q - Q.mean(0)
        U, _, Vt = np.linalg.svd(Pc.T @ Qc)
        if np.linalg.det(Vt.T @ U.T) < 0:
            found += 1
            T_est, _ = arun_register(P, Q)
            assert np.linalg.det(T_est[:3, :3]) == pytest.approx(1.0)
            dt, dr = pose_error(T_est, T)
            assert dt < 1e-12 and dr < 1e-9
    assert found > 10       # the case is common for coplanar points, not a corner


def test_arun_weights_and_degenerate_input():
    rng = np.random.default_rng(2)
    T = make_T(rotvec_to_R(rng.normal(size=3)), [0.01, 0.02, -0.15])
    Q = transform_points(T, P)
    Q[2] += [0.01, 0, 0]                     # one bad point, weighted out
    T_est, _ = arun_register(P, Q, weights=[1, 1, 0, 1, 1])
    dt, dr = pose_error(T_est, T)
    assert dt < 1e-12 and dr < 1e-9
    with pytest.raises(NoPose) as e:
        arun_register(P[:2], Q[:2])
    assert e.value.reason == "too_few_points"
    line = np.stack([np.linspace(0, 0.01, 5), np.zeros(5), np.zeros(5)], 1)
    with pytest.raises(NoPose) as e:
        arun_register(P, line)
    assert e.value.reason == "collinear"
    with pytest.raises(NoPose) as e:
        arun_register(P, np.zeros((5, 3)))
    assert e.value.reason == "coincident"


@st.composite
def poses_in_view(draw):
    d = draw(st.floats(0.10, 0.25))
    xy = (draw(st.floats(-0.35, 0.35)), draw(st.floats(-0.3, 0.3)))
    q = draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4))
    assume(np.linalg.norm(q) > 0.1)
    T = needle_pose_in_view(d, xy, q)
    assume(view_tilt_rad(T) < np.deg2rad(75))
    for cam in RIG.cameras:
        assume(true_keypoints(cam, T, MODEL)[1].all())
    return T


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(poses_in_view())
def test_triangulation_pose_exact_at_zero_noise(T):
    res = triangulation_pose(exact_uv(T), RIG, P)
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < 1e-6 and dr < np.deg2rad(1e-4)
    assert res.valid.all() and res.rms_m < 1e-9
    assert np.abs(res.points_ecm - transform_points(T, P)).max() < 1e-6


def test_triangulation_needs_four_points():
    T = needle_pose_in_view(0.15, (0.05, 0.0), [1, 0.2, 0.1, 0])
    uv = exact_uv(T)
    uv["left"][1] = np.nan
    sc = {"left": np.ones(5), "right": np.array([1, 1, 1, 0.1, 1])}
    with pytest.raises(NoPose) as e:
        triangulation_pose(uv, RIG, P, sc, min_score=0.5)
    assert e.value.reason == "too_few_points"
    pts, valid, _ = triangulate_keypoints(uv, RIG, 5, sc, 0.5)
    assert list(valid) == [True, False, True, False, True]
    assert np.all(np.isnan(pts[~valid]))
    uv["left"][1] = exact_uv(T)["left"][1]
    res = triangulation_pose(uv, RIG, P, sc, min_score=0.5)
    assert res.valid.sum() == 4
    dt, dr = pose_error(res.T_ecm_needle, T)
    assert dt < 1e-6 and dr < np.deg2rad(1e-4)


def test_triangulation_degenerate_inputs():
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.1, 0])
    uv = exact_uv(T)
    with pytest.raises(NoPose) as e:
        triangulation_pose({"left": uv["left"]}, RIG, P)
    assert e.value.reason == "too_few_points"
    with pytest.raises(NoPose) as e:
        triangulation_pose({k: np.full((5, 2), np.nan) for k in uv}, RIG, P)
    assert e.value.reason == "too_few_points"
    same = {k: np.tile([[960.0, 540.0]], (5, 1)) for k in uv}      # zero disparity: at infinity
    with pytest.raises(NoPose):
        triangulation_pose(same, RIG, P)
    # the needle behind the endoscope: negative disparity
    T_b = T.copy()
    T_b[:3, 3] *= -1
    uvb = {c.name: c.project(transform_points(c.T_cam_ecm @ T_b, P)) for c in RIG.cameras}
    with pytest.raises(NoPose) as e:
        triangulation_pose(uvb, RIG, P)
    assert e.value.reason == "behind_camera"


def test_triangulation_is_worse_than_joint_pnp_at_1px():
    """The paper's finding, reproduced: the 4 mm baseline makes DLT depth noisy."""
    from common.geometry.oracle import Oracle
    from common.geometry.pnp import pnp_joint
    rng = np.random.default_rng(0)
    oracle = Oracle(noise_px=1.0, seed=3)
    e_tri, e_joint = [], []
    for i in range(60):
        T = random_needle_pose(rng, RIG, MODEL)
        uv, sc = oracle.stereo(RIG, T, MODEL, seq=i)
        e_tri.append(pose_error(triangulation_pose(uv, RIG, P, sc).T_ecm_needle, T))
        e_joint.append(pose_error(pnp_joint(uv, RIG, P, sc).T_ecm_needle, T))
    assert np.mean(e_joint, axis=0)[0] < np.mean(e_tri, axis=0)[0]
