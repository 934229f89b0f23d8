"""Rotation helpers: the batched Rodrigues agrees with the single one, small angles included."""
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
