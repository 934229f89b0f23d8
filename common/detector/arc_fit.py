"""The needle's arc from the network's outputs: the centreline decoded from its logits, the
perspective image of the arc (an affine image of a circle) fitted through A, E and the
centreline, and B..D placed on it (image pixels, angles along the arc in degrees)."""
from __future__ import annotations

import cv2
import numpy as np

from common.geometry.observations import curve_normals

CENTRELINE_POINTS = 48
"""Points of a decoded centreline."""


def _curve_through(pts: np.ndarray, n: int) -> np.ndarray:
    """n points on a Catmull-Rom curve through the 5 points (from the first to the last)."""
    P = np.vstack([2 * pts[0] - pts[1], pts, 2 * pts[-1] - pts[-2]])
    t = np.linspace(0, len(pts) - 1, n)
    i = np.minimum(t.astype(int), len(pts) - 2)
    u = (t - i)[:, None]
    p0, p1, p2, p3 = P[i], P[i + 1], P[i + 2], P[i + 3]
    return 0.5 * (2 * p1 + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u * u
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3)


def decode_centreline(line_logit: np.ndarray, kp_cells: np.ndarray, n: int = CENTRELINE_POINTS,
                      search: float = 4.0, min_prob: float = 0.25):
    """The needle's centreline from the centreline heatmap (m, m logits), ordered A..E.

    A curve through the decoded keypoints (cell coordinates) seeds ``n`` stations; at each, the
    ridge is searched along the curve's normal within +-``search`` cells and located at sub-cell
    precision by a parabola fit to the log-probability. Returns (points (n, 2) in cells,
    weights (n,) = ridge probability, 0 where no ridge was found)."""
    prob = 1.0 / (1.0 + np.exp(-line_logit.astype(np.float32)))
    logp = np.log(prob + 1e-6)
    seed = _curve_through(kp_cells, n)
    normal = curve_normals(seed)
    steps = np.arange(-search, search + 1e-9, 0.5)
    pts = seed[:, None, :] + steps[None, :, None] * normal[:, None, :]
    mx = pts[..., 0].astype(np.float32)
    my = pts[..., 1].astype(np.float32)
    prof_p = cv2.remap(prob, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    prof_l = cv2.remap(logp, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-14)
    j = np.clip(prof_p.argmax(1), 1, len(steps) - 2)
    r = np.arange(n)
    a, b, c = prof_l[r, j - 1], prof_l[r, j], prof_l[r, j + 1]
    den = a - 2 * b + c
    off = np.where(den < -1e-6, 0.5 * (a - c) / np.minimum(den, -1e-6), 0.0).clip(-0.5, 0.5)
    t = steps[j] + 0.5 * off
    out = seed + t[:, None] * normal
    w = prof_p[r, j]
    w = np.where(w >= min_prob, w, 0.0)
    return out, w.astype(np.float64)


ARC_ANGLES_DEG = (30.0, 60.0, 90.0, 120.0, 150.0)
ARC_MIN_SCORE = 0.35   # A's and E's heatmap scores needed to place B..D on the fitted arc


def ideal_peak_mass(sigma: float) -> float:
    """Softmax mass within 2 cells of the peak (``decode_heatmaps``' score) of the Gaussian soft
    target the loss trains towards: a perfect heatmap scores this, so scores are divided by it."""
    x = np.arange(-12, 13, dtype=float)
    g = np.exp(-x ** 2 / (2 * sigma ** 2))
    return float((g[10:15].sum() / g.sum()) ** 2)


def fit_arc_affine(a: np.ndarray, e: np.ndarray, line_logit: np.ndarray,
                   angles_deg=ARC_ANGLES_DEG, min_prob: float = 0.3, iters: int = 8):
    """Fit the needle's arc in a heatmap under an affine (weak-perspective) camera.

    The arc is ``p(t) = c + U [cos t, sin t]`` (cell coordinates), t the needle-frame angle. It
    passes through the tip ``a`` at ``angles_deg[0]`` and the tail ``e`` at ``angles_deg[-1]``
    (both from their heatmaps) and along the centreline ridge (pixels of probability >=
    ``min_prob``, weighted by it). Start: the ridge point farthest from the chord a-e is the
    arc's midpoint (an affine map keeps ratios of distances to a line); then Gauss-Newton on the
    orthogonal distances of the ridge pixels (each pixel's own angle eliminated, so the fit does
    not crawl along the arc as plain alternation does) with a and e as heavily weighted
    constraints. Returns (c (2,), U (2, 2)) for ``arc_at``, or None when the ridge is too weak or
    the fit degenerate. Used for B, C, D, whose own heatmaps know "on the needle" far better than
    "where along it"."""
    prob = 1.0 / (1.0 + np.exp(-line_logit.astype(np.float32)))
    ys, xs = np.nonzero(prob >= min_prob)
    if len(xs) < 8:
        return None
    if len(xs) > 300:   # keep the strongest pixels: the cost grows with their number
        keep = np.argsort(-prob[ys, xs])[:300]
        ys, xs = ys[keep], xs[keep]
    w = prob[ys, xs].astype(np.float64)
    pts = np.stack([xs, ys], 1).astype(np.float64)
    ang = np.deg2rad(np.asarray(angles_deg, float))
    t0, t1 = ang[0], ang[-1]
    chord = e - a
    L = np.linalg.norm(chord)
    if L < 2.0:
        return None
    d = (chord[0] * (pts[:, 1] - a[1]) - chord[1] * (pts[:, 0] - a[0])) / L
    along = (pts - a) @ chord / (L * L)
    inside = (along > 0.2) & (along < 0.8)
    if inside.sum() < 3:
        return None
    k = np.argsort(-np.abs(d) * inside)[:5]
    mid = (pts[k] * w[k, None]).sum(0) / w[k].sum()
    T = np.array([t0, 0.5 * (t0 + t1), t1])
    D = np.stack([np.ones(3), np.cos(T), np.sin(T)], 1)
    sol = np.linalg.solve(D, np.stack([a, mid, e]))
    c, U = sol[0], sol[1:].T
    # initial angles: closest point on the initial curve (|p - q|^2 without the |p|^2 term)
    ts = np.linspace(t0 - 0.3, t1 + 0.3, 100)
    curve = c + np.stack([np.cos(ts), np.sin(ts)], 1) @ U.T
    tt = ts[((curve * curve).sum(1) - 2.0 * pts @ curve.T).argmin(1)]
    # a and e as heavily weighted constraints: rows of d(c + U [cos t, sin t]) / d(c, U) at t0, t1
    w_end = 10.0 * max(1.0, w.sum())
    ends = np.array([[1, 0, np.cos(t0), np.sin(t0), 0, 0], [0, 1, 0, 0, np.cos(t0), np.sin(t0)],
                     [1, 0, np.cos(t1), np.sin(t1), 0, 0], [0, 1, 0, 0, np.cos(t1), np.sin(t1)]])
    H_ends = w_end * ends.T @ ends
    target = np.concatenate([a, e])
    P = pts.T                                  # (2, N): row-wise arrays keep the loop cheap
    quarter = np.array([[0.0, -1.0], [1.0, 0.0]])   # tangent = U [-sin t, cos t] = U quarter [cos t, sin t]
    for it in range(iters):
        CS = np.stack([np.cos(tt), np.sin(tt)])
        tang = (U @ quarter) @ CS
        nrm = np.stack([-tang[1], tang[0]]) / np.maximum(np.hypot(tang[0], tang[1]), 1e-9)
        res = ((P - c[:, None] - U @ CS) * nrm).sum(0)
        inl = (np.abs(res) < 2.5) & (tt > t0 - 0.15) & (tt < t1 + 0.15)
        if inl.sum() < 5:
            return None
        J = np.concatenate([nrm, nrm[0] * CS, nrm[1] * CS])[:, inl]   # d res / d(c, U), (6, n)
        JtW = J * w[inl]
        r_ends = target - ends @ np.concatenate([c, U.ravel()])
        try:   # normal equations of the weighted least squares (6 unknowns)
            dx = np.linalg.solve(JtW @ J.T + H_ends, JtW @ res[inl] + w_end * ends.T @ r_ends)
        except np.linalg.LinAlgError:
            return None
        c = c + dx[:2]
        U = U + dx[2:].reshape(2, 2)
        # each pixel's angle follows: one Newton step along the tangent of the new curve
        tang = (U @ quarter) @ CS
        tt = tt + ((P - c[:, None] - U @ CS) * tang).sum(0) / np.maximum((tang * tang).sum(0), 1e-9)
        if np.abs(dx).max() < 1e-2:   # cells: B..D then move < 0.002 cell (measured); 1e-4 cost 2 more steps
            break
    if not (np.all(np.isfinite(U)) and np.all(np.isfinite(c))) or abs(np.linalg.det(U)) < 1e-6:
        return None
    # sanity: the fitted arc stays near the chord's scale and on the ridge
    m = prob.shape[0]
    pred = c + np.stack([np.cos(ang), np.sin(ang)], 1) @ U.T
    if (np.abs(pred - np.clip(pred, -0.25 * m, 1.25 * m)).max() > 0 or np.linalg.norm(U, 2) > 4 * m
            or np.linalg.norm(pred[0] - a) > 1.0 or np.linalg.norm(pred[-1] - e) > 1.0):
        return None
    cs, sn = np.cos(tt), np.sin(tt)
    res = np.linalg.norm(pts - (c + np.stack([cs, sn], 1) @ U.T), axis=1)
    inl = (res < 2.5) & (tt > t0 - 0.15) & (tt < t1 + 0.15)
    if inl.sum() < 5 or np.sqrt((w[inl] * res[inl] ** 2).sum() / w[inl].sum()) > 1.5:
        return None
    return c, U


def arc_at(fit, t_deg) -> np.ndarray:
    """Points (N, 2) of a ``fit_arc_affine`` fit at needle angles ``t_deg`` (degrees)."""
    c, U = fit
    t = np.deg2rad(np.asarray(t_deg, float)).reshape(-1)
    return c + np.stack([np.cos(t), np.sin(t)], 1) @ U.T


def refine_along_arc(prob: np.ndarray, fit, t_pred_deg: float, half_deg: float = 15.0,
                     band: float = 2.0) -> float:
    """Angle (deg) of a keypoint on the fitted arc: the mean of its heatmap probability ``prob``
    (m, m, cells) along the arc within +-``half_deg`` of the affine prediction (mass summed across
    the arc within +-``band`` cells). A flat heatmap leaves ``t_pred_deg``; a peaked one moves the
    point along the arc (perspective makes the true point differ from the affine one)."""
    ts = np.linspace(t_pred_deg - half_deg, t_pred_deg + half_deg, 61)
    curve = arc_at(fit, ts)
    tang = np.gradient(curve, axis=0)
    nrm = curve_normals(curve)
    offs = np.arange(-band, band + 1e-9, 0.5)
    pts = curve[:, None, :] + offs[None, :, None] * nrm[:, None, :]
    samp = cv2.remap(prob.astype(np.float32), pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    mass = samp.sum(1) * np.linalg.norm(tang, axis=1)   # mass per unit angle
    if not np.isfinite(mass).all() or mass.sum() <= 1e-9:
        return float(t_pred_deg)
    return float((mass * ts).sum() / mass.sum())


RIDGE_SEEN = 0.4
"""Centreline probability under which a point placed on the fitted arc is taken as not seen (held
needles, 4 moving takes: a jaw over the middle leaves C's cell at 0.3-0.4; 0.3 -> 0.4 took the
hidden keypoints stated sure where 60-100% is seen 7.7 -> 2.5%; the standard test set's share
of sure keypoints unchanged, 93.2%)."""


def ridge_seen(line_logit: np.ndarray, cells: np.ndarray, radius: int = 1) -> np.ndarray:
    """(N,) the centreline heatmap's highest probability within ``radius`` cells of each point
    (cell coordinates (N, 2)): near 1 where the network sees the wire, near 0 where the arc
    runs hidden (under the jaws, in tissue) or out of the crop."""
    m = line_logit.shape[-1]
    out = np.zeros(len(cells))
    for i, (x, y) in enumerate(np.asarray(cells, float)):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        ix, iy = int(round(x)), int(round(y))
        x0, x1, y0, y1 = max(ix - radius, 0), min(ix + radius + 1, m), max(iy - radius, 0), min(iy + radius + 1, m)
        if x0 < x1 and y0 < y1:
            out[i] = 1.0 / (1.0 + np.exp(-float(line_logit[y0:y1, x0:x1].max())))
    return out


def unseen_on_arc_scores(scores: np.ndarray, own: np.ndarray, line_logit: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Scores of points placed on the fitted arc (``scores``): where no centreline ridge runs
    under a point (``ridge_seen`` in the point's own cell < ``RIDGE_SEEN``), neither its own
    heatmap score ``own`` (the heatmaps learn hidden points too) nor that ridge probability may
    be exceeded, so a keypoint the arc places over a hidden stretch is not stated sure. The own
    cell, not its neighbours: a jaw over the middle of the needle hides a few cells of the ridge
    (held needles where 60-100% is seen: hidden keypoints stated sure 29.4 -> 7.7%,
    ``needletrack bench held``)."""
    seen = ridge_seen(line_logit, cells, radius=0)
    return np.where(seen < RIDGE_SEEN, np.minimum(scores, np.minimum(own, seen)), scores)
