"""The oracle detector (common/geometry/oracle.py) and the backend registry (common/detector/backends.py)."""
import numpy as np
import pytest

from common.detector.backends import (
    BACKENDS,
    BackendError,
    KeypointBackend,
    OracleBackend,
    available_backends,
    load_backend,
    register_backend,
)
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import (
    Oracle,
    arc_bbox,
    needle_pose_in_view,
    random_needle_pose,
    true_keypoints,
    view_tilt_rad,
)
from common.geometry.transforms import make_T, transform_points
from common.runtime.messages import Calibration, GroundTruth, Keypoints, decode, encode

RIG = StereoRig.default()
MODEL = NeedleModel()


def calib(rig=RIG):
    return Calibration(0, np.array([rig.left.width, rig.left.height]), rig.to_dict(), MODEL.to_dict())


def truth_for(T_ecm_needle, seq=3, T_world_ecm=None):
    T_world_ecm = make_T(np.eye(3), [0.1, 0.2, 0.3]) if T_world_ecm is None else T_world_ecm
    return GroundTruth(seq, 0, T_world_ecm=T_world_ecm, T_world_needle=T_world_ecm @ T_ecm_needle)


def test_zero_noise_is_the_exact_projection():
    T = needle_pose_in_view(0.15, (0.1, -0.05), [1, 0.2, 0.3, 0.1])
    uv, sc = Oracle().keypoints(RIG.left, T, MODEL, seq=0)
    expect = RIG.left.project(transform_points(RIG.left.T_cam_ecm @ T, MODEL.keypoints()))
    assert np.array_equal(uv, expect)
    assert np.all(sc == 1.0)


def test_noise_statistics_and_seeding():
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.3, 0.1])
    exact, _ = true_keypoints(RIG.left, T, MODEL)
    o = Oracle(noise_px=2.0, seed=7)
    d = np.concatenate([o.keypoints(RIG.left, T, MODEL, seq=i)[0] - exact for i in range(400)])
    assert abs(d.mean()) < 0.15 and abs(d.std() - 2.0) < 0.15
    a = o.keypoints(RIG.left, T, MODEL, seq=11)[0]
    assert np.array_equal(a, Oracle(noise_px=2.0, seed=7).keypoints(RIG.left, T, MODEL, seq=11)[0])
    noise_right = o.keypoints(RIG.right, T, MODEL, seq=11)[0] - true_keypoints(RIG.right, T, MODEL)[0]
    assert not np.allclose(a - exact, noise_right)           # cameras draw independent noise
    assert not np.array_equal(a, Oracle(noise_px=2.0, seed=8).keypoints(RIG.left, T, MODEL, seq=11)[0])


def test_missing_and_outliers():
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.3, 0.1])
    exact, _ = true_keypoints(RIG.left, T, MODEL)
    o = Oracle(missing_prob=0.3, outlier_prob=0.2, outlier_px=40.0, seed=1)
    n_missing = n_out = 0
    for i in range(400):
        uv, sc = o.keypoints(RIG.left, T, MODEL, seq=i)
        miss = np.isnan(uv).any(axis=1)
        assert np.array_equal(miss, sc == 0)
        n_missing += miss.sum()
        dist = np.linalg.norm(uv[~miss] - exact[~miss], axis=1)
        assert np.all((dist == 0) | ((dist >= 20 - 1e-9) & (dist <= 40 + 1e-9)))
        n_out += (dist > 0).sum()
    assert abs(n_missing / 2000 - 0.3) < 0.04
    assert abs(n_out / (2000 - n_missing) - 0.2) < 0.04


def test_invisible_points_are_missing():
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.3, 0.1])
    T_behind = T.copy()
    T_behind[:3, 3] *= -1
    uv, sc = Oracle().keypoints(RIG.left, T_behind, MODEL, seq=0)
    assert np.all(np.isnan(uv)) and np.all(sc == 0)
    T_out = needle_pose_in_view(0.15, (3.0, 0.0), [1, 0.2, 0.3, 0.1])      # far off to the side
    assert not true_keypoints(RIG.left, T_out, MODEL)[1].any()
    uv, sc = Oracle().keypoints(RIG.left, T, MODEL, seq=0, visible=[True, False, True, True, False])
    assert list(sc) == [1, 0, 1, 1, 0]


def test_bad_parameters_are_refused():
    for kw in ({"noise_px": -1}, {"missing_prob": 1.5}, {"outlier_prob": -0.1}, {"noise_px": np.nan}):
        with pytest.raises(ValueError):
            Oracle(**kw)


def test_random_poses_follow_the_protocol():
    rng = np.random.default_rng(0)
    for _ in range(50):
        T = random_needle_pose(rng, RIG, MODEL)
        assert 0.10 <= np.linalg.norm(T[:3, 3]) <= 0.25
        assert view_tilt_rad(T) <= np.deg2rad(75)
        for cam in RIG.cameras:
            assert true_keypoints(cam, T, MODEL)[1].all()


def test_oracle_backend_from_truth():
    T = needle_pose_in_view(0.15, (0.05, 0.02), [1, 0.2, 0.3, 0.1])
    be = load_backend("oracle", {"noise_px": 0.0})
    assert isinstance(be, OracleBackend) and not be.needs_image
    kp = be.detect(None, "right", truth_for(T), calib(), seq=3, stamp_ns=99)
    assert kp.found and kp.camera == "right" and kp.seq == 3 and kp.stamp_ns == 99
    assert np.allclose(kp.uv, true_keypoints(RIG.right, T, MODEL)[0], atol=1e-9)
    assert kp.bbox is not None and kp.bbox[0] <= kp.uv[:, 0].min() and kp.bbox[2] >= kp.uv[:, 0].max()
    assert np.allclose(kp.bbox, arc_bbox(RIG.right, T, MODEL))
    assert isinstance(decode(encode(kp), Keypoints), Keypoints)
    # both halves at once
    both = be.detect_stereo({"left": None, "right": None}, truth_for(T), calib(), seq=3)
    assert set(both) == {"left", "right"} and both["left"].camera == "left"


def test_oracle_backend_without_poses_uses_truth_keypoints():
    T = needle_pose_in_view(0.15, (0.05, 0.02), [1, 0.2, 0.3, 0.1])
    uv_true = true_keypoints(RIG.left, T, MODEL)[0]
    gt = GroundTruth(4, 0, keypoints={"left": uv_true}, visible={"left": np.array([True] * 4 + [False])})
    kp = load_backend("oracle").detect(None, "left", gt, calib(), seq=4)
    assert kp.found and np.allclose(kp.uv[:4], uv_true[:4]) and np.isnan(kp.uv[4]).all()
    nothing = load_backend("oracle").detect(None, "right", GroundTruth(4, 0), calib(), seq=4)
    assert not nothing.found and "neither" in nothing.reason
    none = load_backend("oracle").detect(None, "left", None, calib(), seq=4)
    assert not none.found and np.isnan(none.uv).all()


def test_oracle_backend_not_found_when_invisible():
    T = needle_pose_in_view(0.15, (0.0, 0.0), [1, 0.2, 0.3, 0.1])
    T[:3, 3] *= -1
    kp = load_backend("oracle").detect(None, "left", truth_for(T), calib(), seq=1)
    assert not kp.found and kp.reason == "needle not visible"


def test_registry_is_lazy_and_names_errors():
    assert "oracle" in available_backends()
    with pytest.raises(BackendError, match="unknown"):
        load_backend("nope")
    register_backend("broken", "common.no_such_module:Thing")
    try:
        with pytest.raises(BackendError, match="cannot import"):
            load_backend("broken")
        register_backend("broken", "common.geometry.oracle:Oracle")          # not a KeypointBackend
        with pytest.raises(BackendError, match="no KeypointBackend"):
            load_backend("broken")
    finally:
        BACKENDS.pop("broken")
    with pytest.raises(ValueError):
        register_backend("x", "no_colon")
    with pytest.raises(BackendError, match="bad params"):
        load_backend("oracle", {"noise_px": -2})
    with pytest.raises(NotImplementedError):
        KeypointBackend().detect(None, "left", None, calib())
