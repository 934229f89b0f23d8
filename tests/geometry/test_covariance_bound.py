"""The widest honest pose covariance (common/geometry/covariance_bound.py): a covariance within the
bound is kept bit for bit; a direction beyond it gets the bound's variance, computed from the
information so that the directions a fit fixes keep their precision (issue 56: a refined pose's
covariance beyond 1e7 was not published)."""
import math

import numpy as np
import pytest

from common.geometry.covariance_bound import (
    MAX_SIGMA_M,
    MAX_SIGMA_RAD,
    bound_scale,
    bounded_covariance,
    bounded_inverse,
    within_bound,
)
from common.geometry.reprojection import pose_covariance
from common.runtime.checks import MAX_COORD, covariance_error


def _rotation(rng, n=6):
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return q


def test_a_covariance_within_the_bound_is_kept_as_it_is():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 6)) * np.array([1e-2] * 3 + [1e-3] * 3)
    C = A @ A.T
    out, clipped = bounded_covariance(C)
    assert out is C and not clipped and within_bound(C)
    s = bound_scale()
    assert s.tolist() == [MAX_SIGMA_RAD] * 3 + [MAX_SIGMA_M] * 3
    edge = np.diag(s * s)                       # exactly at the bound: within
    assert within_bound(edge) and bounded_covariance(edge) == (edge, False)


def test_a_direction_beyond_the_bound_gets_the_bounds_variance_the_others_keep_theirs():
    rng = np.random.default_rng(1)
    V = _rotation(rng)                          # in the bound's units
    lam = np.array([1e9, 30.0, 0.5, 1e-3, 1e-5, 1e-6])
    s = bound_scale()
    C = (V * lam) @ V.T * np.outer(s, s)
    out, clipped = bounded_covariance(C)
    assert clipped and not within_bound(C) and within_bound(out * (1 - 1e-9))
    want = (V * np.minimum(lam, 1.0)) @ V.T * np.outer(s, s)
    assert np.allclose(out, want, rtol=0, atol=1e-6 * np.abs(want).max())
    assert covariance_error(out, "C") is None and np.abs(out).max() <= MAX_SIGMA_RAD ** 2 + 1e-9
    bad, clipped = bounded_covariance(np.full((6, 6), np.inf))
    assert clipped and np.array_equal(bad, np.diag(s * s))              # nothing known: the bound
    with pytest.raises(ValueError, match=r"bounded_covariance: expected a \(6, 6\) matrix"):
        bounded_covariance(np.eye(3))


def test_from_the_information_a_fixed_direction_keeps_its_precision_beside_an_unfixed_one():
    """An information matrix with one direction nearly unobservable (1e-14 of the bound's) and the
    others fixed to tenths of a millimetre: inverting and clipping the covariance would drown the
    fixed directions in the rounding of the huge one; ``bounded_inverse`` keeps them."""
    rng = np.random.default_rng(2)
    V = _rotation(rng)
    mu = np.array([1e-14, 1e6, 1e7, 1e8, 1e9, 1e10])     # information in the bound's units
    s = bound_scale()
    H = (V * mu) @ V.T / np.outer(s, s)
    C = bounded_inverse(H)
    want = (V / np.maximum(mu, 1.0)) @ V.T * np.outer(s, s)
    assert np.allclose(C, want, rtol=1e-6, atol=1e-14)
    for k in range(1, 6):                       # each fixed direction's variance, to 1e-6
        v = (V[:, k] / s) @ C @ (V[:, k] / s)
        assert v == pytest.approx(1.0 / mu[k], rel=1e-6), k
    assert covariance_error(C, "C") is None and within_bound(C * (1 - 1e-9))
    with pytest.raises(ValueError, match="not finite"):
        bounded_inverse(np.full((6, 6), np.nan))


def test_a_pnp_whose_keypoints_leave_a_direction_unfixed_states_the_bound_and_says_so():
    """A Jacobian of rank 5 (one direction no residual moves): the covariance is the bound there,
    the flag set; a full-rank one is the plain inverse, the flag clear."""
    rng = np.random.default_rng(3)
    J = rng.normal(size=(12, 6)) * 500.0
    cov, unfixed = pose_covariance(J, 12.0)
    assert not unfixed and np.allclose(cov, 2.0 * np.linalg.inv(J.T @ J))
    J[:, 5] = 0.0                               # the depth moves no keypoint
    cov, unfixed = pose_covariance(J, 12.0)
    assert unfixed and covariance_error(cov, "C") is None
    assert cov[5, 5] == pytest.approx(MAX_SIGMA_M ** 2) and np.abs(cov).max() < MAX_COORD
    assert cov[0, 0] == pytest.approx(2.0 * np.linalg.inv(J[:, :5].T @ J[:, :5])[0, 0], rel=1e-9)
    assert math.isfinite(cov.sum())
