"""How unlike the detector's training data an image looks, from the network's own features.

The crop network's descriptor of a detection (``CropNet.forward_features``: the deepest
features' spatial mean and max) is compared with the descriptors of detections on the looks
the weights were trained on: a Mahalanobis distance in the ``COMPONENTS`` leading principal
directions plus the residual's, per dimension, divided by its median over those detections.
``unfamiliarity`` is then about 1 on a familiar look and grows on images unlike the training
data (another renderer, tissue or light). The end identity's calibration discounts the
network's own evidence as it grows (``common.detector.end_identity``).

The reference is fitted with ``needletrack bench familiarity --fit`` on folders of the training
looks (not the training images themselves, not a test set) and stored as JSON beside the weights
(``familiarity.json``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from common.errors import NeedletrackError

COMPONENTS = 24
"""Principal directions modelled one by one (fewer when fewer than twice as many detections are
given); the rest share one residual variance."""
MIN_DETECTIONS = 10
"""Fewer detections than this do not make a reference (``fit_familiarity`` refuses)."""
FORMAT = "needletrack-familiarity"


class FamiliarityFileError(NeedletrackError, ValueError):
    """A familiarity file that is unreadable or does not fit the weights' descriptor."""


@dataclass(frozen=True)
class Familiarity:
    """The training looks' descriptors: their mean (D,), leading principal directions (k, D)
    and variances (k,), the residual's variance per dimension, and the median raw distance
    (so that ``unfamiliarity`` is 1 at the median familiar detection)."""

    mean: np.ndarray
    components: np.ndarray
    variances: np.ndarray
    residual_variance: float
    median_distance: float
    fitted_on: tuple = ()
    detections: int = 0

    def distance(self, feat: np.ndarray) -> np.ndarray:
        """Raw RMS whitened distance of descriptors (N, D) or (D,) from the mean."""
        f = np.atleast_2d(np.asarray(feat, float)) - self.mean
        proj = f @ self.components.T
        resid = f - proj @ self.components
        d = self.mean.size
        k = len(self.variances)
        m2 = (proj ** 2 / self.variances).sum(axis=1) + (resid ** 2).sum(axis=1) / self.residual_variance
        return np.sqrt(m2 / (k + max(d - k, 1)))

    def unfamiliarity(self, feat: np.ndarray) -> float:
        """How unlike the training looks one descriptor (D,) is: about 1 when familiar."""
        return float(self.distance(feat)[0] / self.median_distance)

    def to_dict(self) -> dict:
        return {"format": FORMAT, "mean": self.mean.tolist(), "components": self.components.tolist(),
                "variances": self.variances.tolist(), "residual_variance": self.residual_variance,
                "median_distance": self.median_distance, "fitted_on": list(self.fitted_on),
                "detections": self.detections}

    @classmethod
    def from_dict(cls, d: dict, where: str = "familiarity") -> "Familiarity":
        try:
            if d.get("format") != FORMAT:
                raise ValueError(f"format must be {FORMAT!r}, got {d.get('format')!r}")
            mean = np.asarray(d["mean"], float)
            comps = np.asarray(d["components"], float)
            var = np.asarray(d["variances"], float)
            fam = cls(mean, comps, var, float(d["residual_variance"]), float(d["median_distance"]),
                      tuple(d.get("fitted_on", ())), int(d.get("detections", 0)))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise FamiliarityFileError(f"{where}: not a familiarity file ({exc})") from None
        if (mean.ndim != 1 or comps.ndim != 2 or comps.shape[1] != mean.size or var.shape != (comps.shape[0],)
                or not (var > 0).all() or not fam.residual_variance > 0 or not fam.median_distance > 0
                or not all(np.isfinite(a).all() for a in (mean, comps, var))):
            raise FamiliarityFileError(f"{where}: inconsistent shapes or non-positive variances "
                                       f"(mean {mean.shape}, components {comps.shape}, variances {var.shape})")
        return fam


def fit_familiarity(features: np.ndarray, fitted_on=(), components: int = COMPONENTS) -> Familiarity:
    """The reference of descriptors (N, D) of detections on the training looks."""
    X = np.asarray(features, float)
    n, d = X.shape
    if n < MIN_DETECTIONS:
        raise ValueError(f"fit_familiarity: {n} detections; need at least {MIN_DETECTIONS} "
                         f"(folders of the training looks where the detector finds the needle)")
    mean = X.mean(axis=0)
    Xc = X - mean
    _, s, vt = np.linalg.svd(Xc, full_matrices=False)
    var_all = s ** 2 / (n - 1)
    k = max(1, min(components, d - 1, n // 2))
    floor = 1e-6 * max(var_all[0], 1e-12)
    resid = max(float(var_all[k:].sum()) / max(d - k, 1), floor)
    fam = Familiarity(mean, vt[:k], np.maximum(var_all[:k], floor), resid, 1.0, tuple(fitted_on), n)
    med = float(np.median(fam.distance(X)))
    return Familiarity(fam.mean, fam.components, fam.variances, fam.residual_variance, med, tuple(fitted_on), n)


def familiarity_path(weights) -> Path:
    """Where the familiarity of these weights is kept: beside them."""
    return Path(weights).with_name("familiarity.json")


def load_familiarity(weights) -> Familiarity | None:
    """The familiarity fitted for these weights, or None when there is none (then no
    unfamiliarity is stated)."""
    path = familiarity_path(weights)
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise FamiliarityFileError(f"{path}: not readable JSON ({exc})") from None
    return Familiarity.from_dict(d, str(path))


def save_familiarity(fam: Familiarity, path) -> None:
    Path(path).write_text(json.dumps(fam.to_dict(), separators=(",", ":")) + "\n")
