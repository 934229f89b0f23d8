"""Prior over the needle's orientation: a needle at rest lies flat on the surface beneath it.

A small planar arc seen from 10-25 cm can have two minima (the mirror pair about the line of
sight) whose projections differ by a few tenths of a pixel: the images cannot tell them apart.
What can is where the needle is: put down on tissue or a phantom, its plane lies on the
surface, so its normal is nearly the surface's normal (``support_normal``, a unit vector in the
ECM frame, e.g. the world's up through the ECM kinematics); held by an instrument it may point
anywhere. The prior is the mixture

    p(n) / p_uniform(n) = (1 - p_rest) + p_rest * exp(-tilt^2 / (2 sigma^2)) / sigma^2

with ``tilt`` the angle (rad) between the needle's normal (its z axis; the sign does not matter)
and the support normal: a Gaussian of the tilt of width ``sigma`` (rad) against the uniform
density over directions (small-angle form). It only weighs minima the images leave nearly equal
(``common.geometry.refine``): a held needle, tilted either way, gains nothing from it.
"""
from __future__ import annotations

import numpy as np


def resting_log_prior(R_ecm_needle: np.ndarray, support_normal: np.ndarray, p_rest: float = 0.5,
                      sigma_rad: float = np.deg2rad(10.0)) -> np.ndarray:
    """log(p / p_uniform) of needle orientations ``R_ecm_needle`` (K, 3, 3) or (3, 3) given the
    support surface's normal (3,) in the same frame; (K,) or a float."""
    n = np.asarray(support_normal, float)
    norm = np.linalg.norm(n)
    if not (np.all(np.isfinite(n)) and norm > 0):
        raise ValueError(f"support_normal must be a finite non-zero 3-vector, got {support_normal}")
    if not (0.0 <= p_rest < 1.0 and sigma_rad > 0):
        raise ValueError(f"p_rest must be in [0, 1) and sigma_rad positive, got {p_rest}, {sigma_rad}")
    R = np.asarray(R_ecm_needle, float)
    cos_tilt = np.abs(R[..., :, 2] @ (n / norm))
    tilt = np.arccos(np.minimum(cos_tilt, 1.0))
    return np.log((1.0 - p_rest) + p_rest * np.exp(-0.5 * (tilt / sigma_rad) ** 2) / sigma_rad ** 2)
