"""Rigid transforms (common/geometry/transforms.py): the batched Rodrigues agrees with the single
one, and properties every pose in the project stands on, over random rotations and poses."""
import numpy as np

from common.geometry.transforms import R_to_rotvec, rotvec_to_R, rotvecs_to_Rs


def test_batched_rodrigues_matches_the_single_one():
    w = np.random.default_rng(0).normal(size=(20, 3))
    w[0] = 0.0
    w[1] = [1e-9, -2e-9, 0.0]
    Rs = rotvecs_to_Rs(w)
    for wi, R in zip(w, Rs):
        assert np.allclose(R, rotvec_to_R(wi), atol=1e-12)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.allclose(R_to_rotvec(Rs[5]), w[5], atol=1e-9)


# ---------------------------------------------------------------- properties (hypothesis)
import math  # noqa: E402

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from common.geometry.transforms import (  # noqa: E402
    R_to_quat,
    inv_T,
    is_rigid,
    make_T,
    pose_error,
    pose_mean,
    project_to_SO3,
    quat_to_R,
    rotation_angle,
    rotation_mean,
    transform_points,
)

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
# rotation vectors of any angle in [0, pi), the near-pi and near-zero ones included
angles = st.one_of(st.floats(0.0, math.pi - 1e-6), st.sampled_from([0.0, 1e-10, 1e-6, math.pi - 1e-4]))
axes = vec3.filter(lambda v: np.linalg.norm(v) > 1e-3).map(lambda v: v / np.linalg.norm(v))
rotvecs = st.tuples(axes, angles).map(lambda a: a[0] * a[1])
translations = st.tuples(finite, finite, finite).map(lambda t: 0.3 * np.array(t))
poses = st.tuples(rotvecs, translations).map(lambda a: make_T(rotvec_to_R(a[0]), a[1]))
points = st.lists(vec3, min_size=1, max_size=8).map(np.array)


@given(rotvecs)
def test_rodrigues_round_trips_and_is_a_rotation(w):
    R = rotvec_to_R(w)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and abs(np.linalg.det(R) - 1.0) < 1e-12
    assert np.allclose(rotvec_to_R(R_to_rotvec(R)), R, atol=1e-9)
    assert math.isclose(rotation_angle(R), np.linalg.norm(w), abs_tol=1e-7)
    assert np.allclose(rotvecs_to_Rs(w[None])[0], R, atol=1e-12)


@given(rotvecs)
def test_quaternions_round_trip_with_w_non_negative(w):
    R = rotvec_to_R(w)
    q = R_to_quat(R)
    assert q[0] >= 0.0 and math.isclose(np.linalg.norm(q), 1.0, abs_tol=1e-12)
    assert np.allclose(quat_to_R(q), R, atol=1e-9)


@given(poses, poses, points)
def test_composition_inverse_and_points(T_a_b, T_b_c, p_c):
    assert is_rigid(T_a_b) and is_rigid(inv_T(T_a_b))
    assert np.allclose(T_a_b @ inv_T(T_a_b), np.eye(4), atol=1e-12)
    # p_a = T_a_b p_b with p_b = T_b_c p_c: composing first is the same
    assert np.allclose(transform_points(T_a_b @ T_b_c, p_c),
                       transform_points(T_a_b, transform_points(T_b_c, p_c)), atol=1e-12)
    assert np.allclose(transform_points(inv_T(T_a_b), transform_points(T_a_b, p_c)), p_c, atol=1e-12)


@given(poses, poses)
def test_pose_error_is_symmetric_zero_on_itself_and_invariant_to_a_common_rotation(T1, T2):
    d0, r0 = pose_error(T1, T1)
    assert d0 == 0.0 and r0 < 1e-7
    dt, dr = pose_error(T1, T2)
    dt2, dr2 = pose_error(T2, T1)
    assert math.isclose(dt, dt2, abs_tol=1e-12) and math.isclose(dr, dr2, abs_tol=1e-7)
    assert 0.0 <= dr <= math.pi + 1e-12
    # the same frame change applied to both (estimate and truth in another frame)
    G = make_T(rotvec_to_R(np.array([0.3, -0.2, 0.9])), np.array([0.01, 0.02, -0.03]))
    dtg, drg = pose_error(G @ T1, G @ T2)
    assert math.isclose(dt, dtg, abs_tol=1e-9) and math.isclose(dr, drg, abs_tol=1e-7)


@given(st.lists(rotvecs, min_size=1, max_size=6), rotvecs)
@settings(max_examples=50)
def test_means_of_copies_are_the_copy_and_follow_a_common_rotation(ws, g):
    R = rotvec_to_R(ws[0])
    assert np.allclose(rotation_mean([R, R, R]), R, atol=1e-9)
    Rs = [rotvec_to_R(w * 0.2) for w in ws]          # a spread the chordal mean handles
    G = rotvec_to_R(g)
    assert np.allclose(rotation_mean([G @ Ri for Ri in Rs]), G @ rotation_mean(Rs), atol=1e-8)
    T = make_T(R, [0.1, 0.2, 0.3])
    assert np.allclose(pose_mean([T, T]), T, atol=1e-9)


@given(st.tuples(*[finite] * 9).map(lambda a: np.array(a).reshape(3, 3)))
def test_project_to_so3_gives_a_rotation_and_keeps_one(M):
    R = project_to_SO3(M + 1e-3 * np.eye(3))
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
    R0 = rotvec_to_R(M[0])
    assert np.allclose(project_to_SO3(R0), R0, atol=1e-9)


def test_project_to_SO3_takes_a_stack_and_never_returns_a_reflection():
    rng = np.random.default_rng(3)
    Ms = rng.normal(size=(64, 3, 3))
    Ms[0] = np.diag([1.0, 1.0, -1.0])                 # a reflection: its nearest rotation, not itself
    Rs = project_to_SO3(Ms)
    assert np.allclose(np.linalg.det(Rs), 1.0) and np.allclose(Rs @ Rs.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    for M, R in zip(Ms, Rs):                          # each as it would be alone
        assert np.array_equal(project_to_SO3(M), R)


def test_symmetrise_keeps_the_symmetric_part():
    from common.geometry.transforms import symmetrise
    C = np.array([[2.0, 1.0], [0.0, 3.0]])
    assert np.array_equal(symmetrise(C), [[2.0, 0.5], [0.5, 3.0]])
