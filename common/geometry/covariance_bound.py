"""The widest a needle pose's covariance may honestly be: no direction of its error spread more
than knowing nothing of the needle's orientation (``MAX_SIGMA_RAD``) and nothing of its position
within the working volume (``MAX_SIGMA_M``), 1 sigma.

A fit whose images leave a direction of the pose unfixed (a short stretch of arc seen, the
keypoints placed on it rather than observed; a near-degenerate PnP) inverts a near-singular
normal matrix: its variance there is arbitrarily large (1e7 and beyond, more than a message may
carry: ``common.runtime.checks.MAX_COORD``) and says only "not known". Such a direction is given
the bound's variance instead (``bounded_inverse`` from the information, ``bounded_covariance``
from a covariance), and the pose is to be flagged ``ambiguous``. A covariance within the bound
is returned as it is, bit for bit.

Covariances are 6x6 over [rotation vector (rad), translation (m)] (``PoseEstimate.covariance``);
"within the bound" is measured in the bound's units: every eigenvalue of ``S^-1 C S^-1`` at most
1, ``S = diag(MAX_SIGMA_RAD x3, MAX_SIGMA_M x3)``.
"""
from __future__ import annotations

import math

import numpy as np

from common.geometry.transforms import symmetrise

MAX_SIGMA_RAD = math.pi
"""A rotation error's widest spread per axis (rad): a rotation vector's angle is at most pi."""
MAX_SIGMA_M = 1.0
"""A translation error's widest spread per axis (m): the pose nodes' working volume
(``pose_volume_m``, 1 m from the ECM by default)."""


def bound_scale(max_sigma_rad: float = MAX_SIGMA_RAD, max_sigma_m: float = MAX_SIGMA_M) -> np.ndarray:
    """The bound's 1-sigma per parameter (6,): [rad x3, m x3]."""
    if not (max_sigma_rad > 0 and max_sigma_m > 0):
        raise ValueError(f"covariance bound: sigmas must be positive, got {max_sigma_rad} rad, {max_sigma_m} m")
    return np.array([max_sigma_rad] * 3 + [max_sigma_m] * 3, float)


def within_bound(covariance, max_sigma_rad: float = MAX_SIGMA_RAD, max_sigma_m: float = MAX_SIGMA_M) -> bool:
    """Whether a (6, 6) covariance is finite and spreads no direction beyond the bound."""
    C = _square6(covariance, "within_bound")
    if not np.isfinite(C).all():
        return False
    s = bound_scale(max_sigma_rad, max_sigma_m)
    return bool(np.linalg.eigvalsh(symmetrise(C / np.outer(s, s)))[-1] <= 1.0)


def bounded_covariance(covariance, max_sigma_rad: float = MAX_SIGMA_RAD,
                       max_sigma_m: float = MAX_SIGMA_M) -> tuple[np.ndarray, bool]:
    """``(covariance, clipped)``: a (6, 6) covariance with every direction spread beyond the bound
    given the bound's variance (its eigenvalues in the bound's units clipped to 1), the others
    kept; ``clipped`` whether any was. Within the bound it is returned as given. A non-finite
    covariance knows nothing: the bound itself. For a covariance a few times the bound (a spread
    of competitors added, an inflation); one beyond by orders of magnitude is better bounded from
    its information (``bounded_inverse``), where its well-fixed directions keep their precision."""
    C = _square6(covariance, "bounded_covariance")
    s = bound_scale(max_sigma_rad, max_sigma_m)
    if not np.isfinite(C).all():
        return np.diag(s * s), True
    w, V = np.linalg.eigh(symmetrise(C / np.outer(s, s)))
    if w[-1] <= 1.0:
        return covariance, False
    return symmetrise((V * np.minimum(w, 1.0)) @ V.T * np.outer(s, s)), True


def bounded_inverse(information, max_sigma_rad: float = MAX_SIGMA_RAD,
                    max_sigma_m: float = MAX_SIGMA_M) -> np.ndarray:
    """The covariance of a fit whose information (inverse covariance, (6, 6) positive
    semi-definite, 1/rad^2 and 1/m^2) leaves directions unfixed: each direction with less
    information than the bound's given the bound's variance, the others their own. Computed on the
    information, so that the directions the fit fixes keep their precision however singular the
    rest is."""
    H = _square6(information, "bounded_inverse")
    if not np.isfinite(H).all():
        raise ValueError("bounded_inverse: information not finite")
    s = bound_scale(max_sigma_rad, max_sigma_m)
    mu, V = np.linalg.eigh(symmetrise(H * np.outer(s, s)))     # in the bound's units
    return symmetrise((V / np.maximum(mu, 1.0)) @ V.T * np.outer(s, s))


def _square6(C, where: str) -> np.ndarray:
    C = np.asarray(C, float)
    if C.shape != (6, 6):
        raise ValueError(f"{where}: expected a (6, 6) matrix over [rotation vector, translation], got {C.shape}")
    return C
