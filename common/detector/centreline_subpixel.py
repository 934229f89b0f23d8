"""Sub-pixel needle centreline from the full-resolution image, along a coarse curve's normals.

The learned detector finds the needle's centreline on a 128x128 crop (0.2-0.3 px from the true
arc at the median, with along-curve wobble); the wire itself, 3-8 px wide and brighter and less
saturated than tissue, pins its centre far better. At each station of the coarse curve the
whiteness ``2 min(B,G,R) - max(B,G,R)`` (as the classical detector segments metal) is sampled
across the curve, the wire's two edges are found as the strongest rising and falling gradient
within ``search_px``, and the station moves to the centroid of the whiteness above the local
background between them (symmetric for a round wire, so unbiased by its width or blur).

Stations whose profile does not look like one wire (no clear edges, a width far from the
curve's median, e.g. an instrument's jaw over the needle) and the ``trim`` stations at each end
(their profile straddles the tip's point or the tail's cap, which biases them outwards by about
half a pixel) get weight 0. Pixel convention: integer coordinates are pixel centres.
"""
from __future__ import annotations

import cv2
import numpy as np

from common.geometry.observations import curve_normals

HALF_PX = 6.0        # profile half-length across the curve
STEP_PX = 0.25       # profile sampling step
SEARCH_PX = 3.0      # the edges are searched within this distance of the coarse station
TRIM = 2             # stations left out at each end
CENTRELINE_SIGMA_PX = 0.2   # 1-sigma error across the curve of a refined station
# (needletrack bench detector measures the centreline's distance to the true arc)
# Neighbouring stations' errors move together (the crop's coarse curve, the wire's shading): in
# a fit's covariance every this many count as one independent observation (chosen so that the
# refined poses' NEES median, in needletrack eval's results, comes near chi-square(6)'s 5.35;
# taken as independent it is about three times that)
CENTRELINE_CORR_POINTS = 5.0


def _subsample_peak(g: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Offset (in samples, within +-0.5) of the parabola's vertex through g[j-1], g[j], g[j+1]."""
    r = np.arange(len(j))
    j = np.clip(j, 1, g.shape[1] - 2)
    a, b, c = g[r, j - 1], g[r, j], g[r, j + 1]
    den = a - 2 * b + c
    return j + np.where(den < -1e-9, 0.5 * (a - c) / np.minimum(den, -1e-9), 0.0).clip(-0.5, 0.5)


def refine_centreline(image: np.ndarray, pts: np.ndarray, weights: np.ndarray, *,
                      half_px: float = HALF_PX, step_px: float = STEP_PX,
                      search_px: float = SEARCH_PX, trim: int = TRIM,
                      width_tol: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Move each station of a coarse centreline (N, 2) px onto the wire's centre in ``image``
    (BGR uint8, full resolution). Returns (points (N, 2), weights (N,)): the input weight where
    the station was refined, 0 where it was left out (then its point is the input's)."""
    pts = np.asarray(pts, float)
    w = np.asarray(weights, float).copy()
    n = len(pts)
    if n < 2 * trim + 3:
        return pts, np.zeros(n)
    steps = np.arange(-half_px, half_px + 1e-9, step_px, dtype=np.float32)
    nrm = curve_normals(pts).astype(np.float32)
    p32 = pts.astype(np.float32)
    mx = p32[:, 0:1] + steps[None, :] * nrm[:, 0:1]
    my = p32[:, 1:2] + steps[None, :] * nrm[:, 1:2]
    samples = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    samples = samples.reshape(n, len(steps), -1).astype(np.float32)
    prof = (2.0 / 255.0) * samples.min(axis=2) - (1.0 / 255.0) * samples.max(axis=2)   # whiteness
    g = np.zeros_like(prof)
    g[:, 1:-1] = 0.5 * (prof[:, 2:] - prof[:, :-2])                  # per sample
    mid, win = len(steps) // 2, int(round(search_px / step_px))
    jl = mid - win + np.argmax(g[:, mid - win:mid + 1], axis=1)      # rising edge (before)
    jr = mid + np.argmin(g[:, mid:mid + win + 1], axis=1)            # falling edge (after)
    tl = (_subsample_peak(g, jl) - mid) * step_px
    tr = (_subsample_peak(-g, jr) - mid) * step_px
    r = np.arange(n)
    edge = np.minimum(g[r, jl], -g[r, jr]) / step_px                # weaker edge's slope (1/px)
    # the darker side's median: a jaw or glare in one side's window must not raise the background
    bg = np.minimum(np.median(prof[:, :8], axis=1), np.median(prof[:, -8:], axis=1))
    inside = (steps[None] >= tl[:, None] - 1.0) & (steps[None] <= tr[:, None] + 1.0)
    mass = np.maximum(prof - bg[:, None], 0.0) * inside
    total = mass.sum(axis=1)
    offset = (mass @ steps) / np.maximum(total, 1e-9)
    width = tr - tl
    ok = (w > 0) & (total > 0) & (edge > 0.02) & (width > 0.5)
    ok[:trim] = ok[n - trim:] = False
    if ok.sum() >= 3:
        wmed = float(np.median(width[ok]))
        ok &= np.abs(width - wmed) <= width_tol * wmed + 1.0
    out = np.where(ok[:, None], pts + offset[:, None] * nrm, pts)
    return out, np.where(ok, w, 0.0)


def ellipse_residual(pts: np.ndarray, iterations: int = 3, floor_px: float = 0.3) -> tuple[float, float]:
    """How far a centreline (N, 2) px is from one ellipse, the perspective image of the needle's
    circle: (median distance of the inliers to the best-fit ellipse, px; inlier share).

    Direct least-squares ellipse fit (``cv2.fitEllipseDirect``), refitted on the points within
    ``max(3 x median, floor_px)`` (a jaw over part of the needle bends a few stations away);
    distances are Sampson's first-order geometric distances. (inf, 0) for fewer than 6 finite
    points or when no ellipse can be fitted."""
    pts = np.asarray(pts, float).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 6:
        return float("inf"), 0.0
    keep = np.ones(len(pts), bool)
    d = np.zeros(len(pts))
    for it in range(iterations + 1):
        if keep.sum() < 6:
            return float("inf"), 0.0
        try:
            (cx, cy), (w, h), ang = cv2.fitEllipseDirect(pts[keep].astype(np.float32))
        except cv2.error:
            return float("inf"), 0.0
        a, b = 0.5 * w, 0.5 * h
        if not (np.isfinite([cx, cy, a, b]).all() and a > 1e-6 and b > 1e-6):
            return float("inf"), 0.0
        c, s = np.cos(np.deg2rad(ang)), np.sin(np.deg2rad(ang))
        x = (pts[:, 0] - cx) * c + (pts[:, 1] - cy) * s
        y = -(pts[:, 0] - cx) * s + (pts[:, 1] - cy) * c
        q = (x / a) ** 2 + (y / b) ** 2 - 1.0
        d = np.abs(q) / np.maximum(2.0 * np.hypot(x / a ** 2, y / b ** 2), 1e-12)
        if it < iterations:
            keep = d <= max(3.0 * float(np.median(d[keep])), floor_px)
    return float(np.median(d[keep])), float(keep.mean())
