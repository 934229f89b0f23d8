"""ECM forward kinematics (common/geometry/ecm_kinematics.py) against hand-computed values.

Working the spec's modified-DH chain through by hand (RotX(pi/2) maps z to -y, etc.) gives the
closed form

    F(q) = [ RotY(-yaw) RotX(-pitch) RotZ(-roll) ,  RotY(-yaw) RotX(-pitch) [0, 0, -(ins - L_rcc + L_scopelen)] ]

i.e. at q = 0 the ECM frame is the base frame, insertion moves the ECM along -z (the viewing
direction), yaw turns about -y, pitch about -x and roll about -z, all about the remote centre.
"""
import numpy as np
import pytest

from common.geometry.ecm_kinematics import EcmArm, ecm_forward, mdh_link
from common.geometry.transforms import is_rigid, make_T


def RotX(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def RotY(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def RotZ(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def closed_form(q, L_rcc=0.0, L_scopelen=0.0):
    yaw, pitch, ins, roll = q
    R0 = RotY(-yaw) @ RotX(-pitch)
    return make_T(R0 @ RotZ(-roll), R0 @ [0.0, 0.0, -(ins - L_rcc + L_scopelen)])


def test_zero_joints_is_identity():
    assert np.allclose(ecm_forward([0, 0, 0, 0]), np.eye(4), atol=1e-15)


def test_hand_computed_values():
    s, c = np.sin(0.05), np.cos(0.05)
    # insertion 0.1 m: 10 cm down the viewing axis (-z)
    assert np.allclose(ecm_forward([0, 0, 0.1, 0]), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -0.1], [0, 0, 0, 1]], atol=1e-15)
    # yaw 0.05 rad with 0.1 m insertion: the tip swings towards +x
    assert np.allclose(ecm_forward([0.05, 0, 0.1, 0]),
                       [[c, 0, -s, 0.1 * s], [0, 1, 0, 0], [s, 0, c, -0.1 * c], [0, 0, 0, 1]], atol=1e-15)
    # pitch 0.05 rad: the tip swings towards -y
    assert np.allclose(ecm_forward([0, 0.05, 0.1, 0]),
                       [[1, 0, 0, 0], [0, c, s, -0.1 * s], [0, -s, c, -0.1 * c], [0, 0, 0, 1]], atol=1e-15)
    # roll 0.3 rad: about the viewing axis, clockwise seen from behind
    c3, s3 = np.cos(0.3), np.sin(0.3)
    assert np.allclose(ecm_forward([0, 0, 0.1, 0.3]),
                       [[c3, s3, 0, 0], [-s3, c3, 0, 0], [0, 0, 1, -0.1], [0, 0, 0, 1]], atol=1e-15)
    # lengths: L_rcc shortens the insertion, L_scopelen lengthens it
    T = ecm_forward([0, 0, 0.1, 0], L_rcc=0.03, L_scopelen=0.01)
    assert np.allclose(T[:3, 3], [0, 0, -0.08], atol=1e-15)


@pytest.mark.parametrize("seed", range(5))
def test_matches_closed_form(seed):
    rng = np.random.default_rng(seed)
    q = [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0, 0.2), rng.uniform(-np.pi, np.pi)]
    L = rng.uniform(0, 0.05, 2)
    T = ecm_forward(q, *L)
    assert is_rigid(T)
    assert np.allclose(T, closed_form(q, *L), atol=1e-14)


def test_mdh_link_convention():
    a = mdh_link(0.3, 0.02, -0.4, 0.05)
    Tx = make_T(RotX(0.3), [0, 0, 0]) @ make_T(np.eye(3), [0.02, 0, 0])
    Tz = make_T(RotZ(-0.4), [0, 0, 0]) @ make_T(np.eye(3), [0, 0, 0.05])
    assert np.allclose(a, Tx @ Tz, atol=1e-15)


def test_arm_applies_base_pose_and_rejects_bad_joints():
    base = make_T(RotZ(0.7), [0.1, -0.2, 0.3])
    arm = EcmArm(base, 0.01, 0.02)
    q = [0.1, -0.2, 0.12, 0.4]
    assert np.allclose(arm.T_world_ecm(q), base @ closed_form(q, 0.01, 0.02), atol=1e-14)
    arm2 = EcmArm.from_dict(arm.to_dict())
    assert np.allclose(arm2.T_world_ecm(q), arm.T_world_ecm(q))
    for bad in ([0, 0, 0], [0, 0, np.nan, 0]):
        with pytest.raises(ValueError):
            ecm_forward(bad)
