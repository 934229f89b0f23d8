"""Which end of a detected needle is the tip: evidence from the needle's own shape and from the
network, as the probability that keypoint A is where the detector says.

A suture needle's tip tapers to a point over its last millimetres; its tail is blunt (swaged),
as thick as the wire or thicker. Along the detected centreline (ordered from A to E) the wire's
whiteness mass across the curve (``2 min(B,G,R) - max(B,G,R)`` above the local background,
summed over the profile: proportional to the wire's apparent width times its contrast) is
measured near each end and in the middle. The end whose mass falls off is the tip:
``shape_llr = log(r_E) - log(r_A)`` with ``r_X`` the mean mass over the last ``END_FRACTION``
of the arc at end X relative to the middle's (> 0: A is the thinner end, as said).

The network's own evidence: its A heatmap's probability mass at the reported A against at the
reported E, times the same for its E heatmap: ``net_llr = log(pA(A) pE(E)) - log(pA(E) pE(A))``.
A network that learned the end from the thread puts A's mass on both ends when there is none.

Both pieces of evidence weaken as the needle gets smaller in the image (a 640x480 stream shows
the taper over a pixel or two): with ``small = clip(log2(LENGTH_REF_PX / length_px), 0, 3)``, the
keypoints' polyline A..E length in pixels. The network's evidence also means less on an image
unlike its training data: with ``far = clip(log2(unfamiliarity), 0, 3)``
(``common.detector.familiarity``; 0 for a familiar image or when not stated),
``p_a_is_tip = sigmoid(COEF . [shape_llr, net_llr, 1, small, small shape_llr, small net_llr,
far, far shape_llr, far net_llr])``, the coefficients fitted by logistic regression
(``fit_coefficients``) on renders the weights never trained on, of looks they did and of looks
they did not (so that the fit sees the network on unfamiliar images: ``needletrack bench
end-identity --fit``). Three or six coefficients (older fits) stand for the first ones, the rest
zero.
Pixel convention: integer coordinates are pixel centres.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from common.geometry.end_identity import unfamiliar_octaves
from common.geometry.observations import curve_normals

END_FRACTION = 0.08      # the tip's taper: its last ~1.8 mm of a 21 mm arc
MID_RANGE = (0.3, 0.7)   # the reference stretch of the wire, as fractions of the arc
STATIONS = 12            # profile stations per end
HALF_PX = 6.0            # profile half-length across the curve
STEP_PX = 0.5
CORE_PX = 4.0            # the mass is summed within this distance of the centreline
OUTSIDE_PX = 6.0         # the end profiles start this far past each end
PEAK_RADIUS_CELLS = 2    # heatmap mass within this radius of a keypoint
LLR_CLIP = 8.0
LENGTH_REF_PX = 160.0    # a needle this long in the image (or longer) is not "small"
FEATURES = ("shape_llr", "net_llr", "bias", "small", "small_shape_llr", "small_net_llr",
            "far", "far_shape_llr", "far_net_llr")
COEF = np.array([1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])   # see FEATURES and fit_coefficients
FEATURE_SETS = (3, 6, len(FEATURES))
"""The coefficient counts a fit may have: older fits use the first 3 or 6 features."""


@dataclass
class EndEvidence:
    """The measured evidence for one image (NaN where it could not be measured)."""

    shape_llr: float
    net_llr: float
    r_a: float = float("nan")       # rise length at A, px
    r_e: float = float("nan")
    length_px: float = float("nan")  # the keypoints' polyline A..E, px (NaN: not small)
    unfamiliarity: float = float("nan")  # common.detector.familiarity (NaN: not stated, familiar)

    def features(self) -> np.ndarray:
        """The FEATURES vector, unmeasured evidence as 0 (no evidence)."""
        f = np.array([self.shape_llr, self.net_llr], float)
        f = np.where(np.isfinite(f), np.clip(f, -LLR_CLIP, LLR_CLIP), 0.0)
        small = (float(np.clip(np.log2(LENGTH_REF_PX / self.length_px), 0.0, 3.0))
                 if np.isfinite(self.length_px) and self.length_px > 0 else 0.0)
        far = unfamiliar_octaves(self.unfamiliarity)
        return np.array([f[0], f[1], 1.0, small, small * f[0], small * f[1], far, far * f[0], far * f[1]])

    def p_a_is_tip(self, coef: np.ndarray = COEF) -> float:
        """Probability that A is the tip as said (0.5: the images cannot tell); ``coef`` of one
        of ``FEATURE_SETS``' lengths (the first features)."""
        coef = np.asarray(coef, float)
        z = float(self.features()[:len(coef)] @ coef)
        return float(1.0 / (1.0 + np.exp(-z)))


def polyline_length(uv: np.ndarray) -> float:
    """Length (px) of the polyline through the points (N, 2) in order."""
    return float(np.linalg.norm(np.diff(np.asarray(uv, float), axis=0), axis=1).sum())


def _resample(curve: np.ndarray, fractions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit normals at the given fractions of a polyline's arc length."""
    seg = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.clip(fractions, 0.0, 1.0) * s[-1]
    pts = np.stack([np.interp(t, s, curve[:, 0]), np.interp(t, s, curve[:, 1])], axis=1)
    nrm = curve_normals(curve)
    nx, ny = np.interp(t, s, nrm[:, 0]), np.interp(t, s, nrm[:, 1])
    n = np.stack([nx, ny], axis=1)
    return pts, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)


def wire_mass(image: np.ndarray, pts: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Whiteness mass across the curve at each station (px x whiteness): the wire's width x
    contrast. BGR uint8 ``image``; (N, 2) ``pts`` and unit ``normals``."""
    steps = np.arange(-HALF_PX, HALF_PX + 1e-9, STEP_PX, dtype=np.float32)
    mx = (pts[:, 0:1] + steps[None] * normals[:, 0:1]).astype(np.float32)
    my = (pts[:, 1:2] + steps[None] * normals[:, 1:2]).astype(np.float32)
    smp = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
    smp = smp.reshape(len(pts), len(steps), -1)
    prof = (2.0 * smp.min(axis=2) - smp.max(axis=2)) / 255.0
    outer = np.abs(steps) > HALF_PX - 2.0
    bg = np.median(prof[:, outer], axis=1)
    core = np.abs(steps) <= CORE_PX
    return np.maximum(prof[:, core] - bg[:, None], 0.0).sum(axis=1) * STEP_PX


def _end_path(curve: np.ndarray, from_end: bool, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and unit normals at arc lengths ``s`` (px) inward from one end of a polyline;
    negative ``s`` continue past the end along its tangent."""
    c = curve[::-1] if from_end else curve
    seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    tang = c[min(3, len(c) - 1)] - c[0]
    tang /= max(np.linalg.norm(tang), 1e-9)
    inside = np.stack([np.interp(s, cum, c[:, 0]), np.interp(s, cum, c[:, 1])], axis=1)
    pts = np.where((s < 0)[:, None], c[0] + s[:, None] * tang, inside)
    nrm = curve_normals(c)
    n = np.stack([np.interp(np.maximum(s, 0), cum, nrm[:, 0]), np.interp(np.maximum(s, 0), cum, nrm[:, 1])], 1)
    return pts, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)


def rise_length(mass: np.ndarray, s: np.ndarray, plateau: float) -> float:
    """Arc length (px) over which the mass rises from 20% to 80% of ``plateau``, coming in from
    past the end: short for a blunt end, long for a taper."""
    m = np.convolve(mass, np.ones(3) / 3, mode="same") / plateau
    above20 = np.nonzero(m >= 0.2)[0]
    above80 = np.nonzero(m >= 0.8)[0]
    if len(above20) == 0:
        return float(s[-1] - s[0])
    i80 = above80[0] if len(above80) else len(s) - 1
    return float(max(s[i80] - s[above20[0]], 0.0))


def shape_evidence(image: np.ndarray, centreline: np.ndarray) -> tuple[float, float, float]:
    """(shape_llr, rise_A, rise_E) from the image and the centreline ordered A -> E: the rise
    lengths (px) of the wire's mass at each end; NaNs when the curve is too short or the middle
    shows no wire. ``shape_llr = log(rise_A / rise_E)``: > 0 when A tapers more (A is the tip)."""
    c = np.asarray(centreline, float)
    c = c[np.isfinite(c).all(axis=1)]
    if len(c) < 8:
        return float("nan"), float("nan"), float("nan")
    length = polyline_length(c)
    if length < 20.0:
        return float("nan"), float("nan"), float("nan")
    pts, nrm = _resample(c, np.linspace(*MID_RANGE, 2 * STATIONS))
    plateau = float(np.median(wire_mass(image, pts, nrm)))
    if not plateau > 1e-3:
        return float("nan"), float("nan"), float("nan")
    s = np.arange(-OUTSIDE_PX, END_FRACTION * 2.5 * length, 0.5)
    rises = []
    for from_end in (False, True):
        p, n = _end_path(c, from_end, s)
        rises.append(rise_length(wire_mass(image, p, n), s, plateau))
    r_a, r_e = rises
    return float(np.log((r_a + 0.5) / (r_e + 0.5))), r_a, r_e


def mass_near(prob: np.ndarray, uv_cell: np.ndarray) -> float:
    """The probability mass of ``prob`` (m, m) within ``PEAK_RADIUS_CELLS`` of a cell (x, y)."""
    m = prob.shape[-1]
    ix, iy = int(round(float(uv_cell[0]))), int(round(float(uv_cell[1])))
    r = PEAK_RADIUS_CELLS
    return float(prob[max(0, iy - r):min(m, iy + r + 1), max(0, ix - r):min(m, ix + r + 1)].sum())


def network_evidence(kp_logits: np.ndarray, uv_cells: np.ndarray) -> float:
    """net_llr from the crop's keypoint logits (5, m, m) and the keypoints in heatmap cells (5, 2)."""
    lg = np.asarray(kp_logits, float)
    a, e = lg[0], lg[4]
    pa = np.exp(a - a.max())
    pa /= pa.sum()
    pe = np.exp(e - e.max())
    pe /= pe.sum()
    A, E = uv_cells[0], uv_cells[4]
    eps = 1e-6
    return float(np.log(mass_near(pa, A) * mass_near(pe, E) + eps)
                 - np.log(mass_near(pa, E) * mass_near(pe, A) + eps))


def fit_coefficients(features: np.ndarray, labels: np.ndarray, l2: float = 1e-2, iters: int = 50,
                     weights: np.ndarray | None = None) -> np.ndarray:
    """Logistic regression (Newton's method, a little L2) of labels (1: A is the tip as said) on
    features (N, len(FEATURES)) as ``EndEvidence.features`` gives them; ``weights`` (N,) per
    sample (default 1)."""
    X, y = np.asarray(features, float), np.asarray(labels, float)
    sw = np.ones(len(y)) if weights is None else np.asarray(weights, float)
    w = np.zeros(X.shape[1])
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-X @ w))
        g = X.T @ (sw * (p - y)) + l2 * w
        H = (X * (sw * p * (1 - p))[:, None]).T @ X + l2 * np.eye(len(w))
        step = np.linalg.solve(H, g)
        w -= step
        if np.abs(step).max() < 1e-8:
            break
    return w
