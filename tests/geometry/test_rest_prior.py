"""The resting prior (common/geometry/rest_prior.py) and how the refinement uses it: no process, no network."""
from __future__ import annotations

import numpy as np
import pytest

from common.geometry.rest_prior import resting_log_prior
from common.geometry.transforms import rotvec_to_R
from tests.geometry.test_refine import (
    REFINER,
    _delta,
    errors_mm_deg,
    joint_candidates,
    observe,
    random_pose,
)


def test_flat_needles_are_likelier_either_side_up():
    up = np.array([0.0, 0.0, 2.0])                    # any length
    R = np.stack([np.eye(3), rotvec_to_R([np.pi, 0, 0]), rotvec_to_R([np.deg2rad(10), 0, 0]),
                  rotvec_to_R([np.deg2rad(60), 0, 0]), rotvec_to_R([0, np.deg2rad(90), 0])])
    lp = resting_log_prior(R, up, p_rest=0.5, sigma_rad=np.deg2rad(10))
    s2 = np.deg2rad(10) ** 2
    assert lp[0] == pytest.approx(np.log(0.5 + 0.5 / s2)) and lp[1] == pytest.approx(lp[0])
    assert lp[2] == pytest.approx(np.log(0.5 + 0.5 * np.exp(-0.5) / s2))
    assert lp[3] == pytest.approx(np.log(0.5), abs=1e-6) and lp[4] == pytest.approx(np.log(0.5))
    assert np.all(resting_log_prior(R, up, p_rest=0.0) == 0.0)     # no resting needles: no prior
    assert resting_log_prior(np.eye(3), up) == pytest.approx(lp[0])


def test_bad_prior_input_is_named():
    for bad in ([0, 0, 0], [np.nan, 0, 1]):
        with pytest.raises(ValueError, match="support_normal"):
            resting_log_prior(np.eye(3), bad)
    with pytest.raises(ValueError, match="p_rest"):
        resting_log_prior(np.eye(3), [0, 0, 1], p_rest=1.0)


def _ambiguous_frames(n_wanted, seed=12):
    """Noisy frames whose two best minima the images leave nearly equal, their normals apart."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(200):
        T = random_pose(rng)
        obs = observe(T, rng, kp_px=1.0, curve_px=0.5)
        starts = joint_candidates(obs)[1]
        res = REFINER.refine(obs, starts)
        if "competing_candidates" not in res.reasons:
            continue
        (T_a, _), (T_b, _) = res.candidates[:2]
        if np.degrees(np.arccos(abs(T_a[:3, 2] @ T_b[:3, 2]))) > 30.0:
            out.append((obs, starts, res))
        if len(out) == n_wanted:
            break
    return out


def test_prior_picks_between_near_equal_minima_and_leaves_them_ambiguous():
    frames = _ambiguous_frames(3)
    assert len(frames) == 3
    cfg = REFINER.config
    for obs, starts, res in frames:
        (T_a, _), (T_b, _) = res.candidates[:2]
        for T_flat, T_other in ((T_a, T_b), (T_b, T_a)):
            out = REFINER.refine(obs, starts, support_normal=T_flat[:3, 2])
            gain = 2.0 * float(resting_log_prior(T_flat[:3, :3], T_flat[:3, 2], cfg.rest_prior,
                                                 np.deg2rad(cfg.rest_sigma_deg))
                               - resting_log_prior(T_other[:3, :3], T_flat[:3, 2], cfg.rest_prior,
                                                   np.deg2rad(cfg.rest_sigma_deg)))
            # the costlier minimum wins when its prior gain outweighs its cost in variances
            want = T_flat if (T_flat is T_a or res.competitor_chi2 < gain) else T_other
            assert errors_mm_deg(out.T_ecm_needle, want)[1] < 0.5
            # judged on the images, the view stays ambiguous and the covariance spans both
            assert out.ambiguous and "competing_candidates" in out.reasons
            T_lost = T_other if want is T_flat else T_flat
            d = _delta(T_lost, out.T_ecm_needle)
            assert d @ np.linalg.solve(out.covariance, d) <= 1.0 + 1e-6
        assert res.competitor_chi2 < gain    # this frame's mirror is within the prior's reach


def _clear_frames(clear_chi2, seed=5, n=20):
    """Of ``n`` low-noise frames, those with a competitor costing at least ``clear_chi2(res)``
    residual variances more than the best: (obs, starts, res)."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        T = random_pose(rng)
        obs = observe(T, rng, kp_px=0.5, curve_px=0.25)
        starts = joint_candidates(obs)[1]
        res = REFINER.refine(obs, starts)
        if len(res.candidates) >= 2 and res.competitor_chi2 >= clear_chi2(res):
            yield obs, starts, res


def test_prior_does_not_overrule_clear_images():
    checked = 0
    for obs, starts, res in _clear_frames(lambda res: 50.0):
        T_other = res.candidates[1][0]
        out = REFINER.refine(obs, starts, support_normal=T_other[:3, 2])
        assert np.allclose(out.T_ecm_needle, res.T_ecm_needle)
        checked += 1
    assert checked >= 3


def test_the_expected_pose_picks_between_near_equal_minima_only():
    """The needle's expected pose (its pose in the other views of a multi-view group, or the
    previous frame) chooses the near-equal minimum near it; the view stays ambiguous."""
    frames = _ambiguous_frames(2, seed=21)
    assert len(frames) == 2
    for obs, starts, res in frames:
        (T_a, _), (T_b, _) = res.candidates[:2]
        for want in (T_a, T_b):
            moved = want.copy()
            moved[:3, 3] += 1e-3                                      # 1 mm off, within expected_mm
            out = REFINER.refine(obs, starts, expected=moved)
            assert errors_mm_deg(out.T_ecm_needle, want)[1] < 0.5
            assert out.ambiguous and "competing_candidates" in out.reasons
        far = T_a.copy()
        far[:3, 3] += 0.05                                            # 50 mm off: near neither
        out = REFINER.refine(obs, starts, expected=far)
        assert np.allclose(out.T_ecm_needle, res.T_ecm_needle)


def test_the_expected_pose_does_not_overrule_clear_images():
    checked = 0
    # edge-on, a competitor within edge_on_chi2 is near-equal (the covariance spans it)
    clear = lambda res: REFINER.config.edge_on_chi2 if "edge_on" in res.reasons else 50.0  # noqa: E731
    for obs, starts, res in _clear_frames(clear):
        out = REFINER.refine(obs, starts, expected=res.candidates[1][0])
        assert np.allclose(out.T_ecm_needle, res.T_ecm_needle)
        checked += 1
    assert checked >= 3
