"""An end keypoint where something covers the wire: the needle goes on under it.

The detector puts A or E where the wire it sees ends. When an instrument's jaws or shaft lie over
the needle, that is where the cover starts, not where the needle does: the heatmaps place the
hidden end at the cut, often with a score past the pose nodes' gate (on the standard test set,
the tail in the jaws, 10-40 px off, scored 0.65). A real end lies on tissue: just past it, along
the wire's tangent, the image is the tissue beside the wire. ``beyond_end_covered`` measures the
share of samples past the end that are unlike that tissue; ``cut_end_scores`` lowers the end's
score by it (and the scores of points the detector placed on its arc through that end).

Where the jaws hold the needle, they lie beside the wire at the cut as well as over it: the
image beside the end is the jaw, and past the end the same jaw. Then (fewer than
``LOCAL_TISSUE_MIN`` of the samples beside the end look like the tissue beside the whole wire)
the tissue is taken from beside the whole wire.

A thread leaving the tail is thin, a fraction of the samples; the tip in tissue shows tissue
past it, so this does not see that cut. What does: a real tip narrows over a few pixels, a wire
cut by the tissue's surface ends at its full width (``blunt_tip_scores``). Pixels: integer
coordinates are pixel centres.
"""
from __future__ import annotations

import numpy as np

WIRE_PX = 4.0
"""Lateral spacing of the samples (px): about a wire's width at working distances."""
UNLIKE = 3.0
"""A sample is unlike the tissue when a colour channel differs from the tissue's median by this
many times the tissue's own spread (at least 10 grey levels)."""
COVERED = 0.5
"""An end is cut when at least this share of the samples past it are unlike the tissue (on the
standard test set: every end scored sure and 15 px or more off, 2 of 570 right ones; on held
needles a quarter of the wrong ones, 5% of the right ones)."""
ALONG_PX = (3.0, 5.0, 7.0, 9.0)
"""Distances past the end (px) of the samples ahead of it; the tissue is sampled as far behind,
three wire widths to each side."""
WIRE_STATIONS = 16
"""Stations along the whole centreline beside which the wire-wide tissue is sampled."""
LOCAL_TISSUE_MIN = 5
"""Of the six samples beside the end, at least this many must look like the wire-wide tissue for
them to be the reference (held needles: sure ends 15 px or more off caught 66 -> 219 of 332,
right ones cut 166 -> 201 of 2160; standard test set: 6 of 6 wrong ones caught, right ones cut
2 -> 10 of 570, tails with the thread beside them)."""


def _tangent(end_uv: np.ndarray, centreline: np.ndarray) -> np.ndarray | None:
    """Unit direction (2,) pointing out of the wire at ``end_uv``: from the centreline points
    farther from the end to the six nearest it."""
    pts = centreline[np.isfinite(centreline).all(axis=1)]
    if len(pts) < 6:
        return None
    order = np.argsort(np.linalg.norm(pts - end_uv, axis=1))
    near, far = pts[order[:6]], pts[order[6:12]] if len(pts) >= 12 else pts[order[-3:]]
    t = near.mean(0) - far.mean(0)
    n = float(np.linalg.norm(t))
    return t / n if n > 1e-6 else None


def beyond_end_covered(image: np.ndarray, end_uv, centreline, wire_px: float = WIRE_PX,
                       wire_samples: np.ndarray | None = None) -> float:
    """Share (0..1) of the samples just past an end keypoint ``end_uv`` (px), along the wire's
    tangent, that are unlike the tissue beside the wire; NaN when it cannot be judged (too short
    a centreline, samples off the image). ``image`` BGR, ``centreline`` (N, 2) px;
    ``wire_samples``: ``beside_wire``'s colours when already taken (one set serves both ends)."""
    end_uv = np.asarray(end_uv, float)
    t = _tangent(end_uv, np.asarray(centreline, float).reshape(-1, 2))
    if t is None:
        return float("nan")
    nrm = np.array([-t[1], t[0]])
    h, w = image.shape[:2]

    def colours(offsets):
        q = np.array([end_uv + a * t + b * nrm for a, b in offsets])
        x, y = np.round(q[:, 0]).astype(int), np.round(q[:, 1]).astype(int)
        ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        return image[y[ok], x[ok]].astype(float)

    side = colours([(-a - 1.0, s * 3.0 * wire_px) for a in (3.0, 7.0, 11.0) for s in (1, -1)])
    ahead = colours([(a, b * wire_px) for a in ALONG_PX for b in (-1, 0, 1)])
    if len(side) < 2 or not len(ahead):
        return float("nan")
    tissue, spread = _reference(side)
    wire = beside_wire(image, centreline, 3.0 * wire_px) if wire_samples is None else wire_samples
    if len(wire) >= 2:
        w_tissue, w_spread = _reference(wire)
        if np.count_nonzero(np.abs(side - w_tissue).max(axis=1) <= UNLIKE * w_spread) < LOCAL_TISSUE_MIN:
            tissue, spread = w_tissue, w_spread          # jaws beside the end: the wire-wide tissue
    return float(np.mean(np.abs(ahead - tissue).max(axis=1) > UNLIKE * spread))


def _reference(samples: np.ndarray) -> tuple[np.ndarray, float]:
    """The tissue colour of samples (N, 3): their median, and their spread (the median of the
    samples' largest channel difference from it, at least 10 grey levels)."""
    tissue = np.median(samples, axis=0)
    return tissue, max(float(np.median(np.abs(samples - tissue).max(axis=1))), 10.0)


def beside_wire(image: np.ndarray, centreline, offset_px: float) -> np.ndarray:
    """Colours (N, 3) at ``offset_px`` to each side of the wire at ``WIRE_STATIONS`` stations along
    the centreline (N, 2) px, across its local direction; those off the image left out."""
    pts = np.asarray(centreline, float).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 3:
        return np.zeros((0, 3))
    idx = np.unique(np.linspace(0, len(pts) - 1, min(len(pts), WIRE_STATIONS)).round().astype(int))
    d = pts[np.minimum(idx + 2, len(pts) - 1)] - pts[np.maximum(idx - 2, 0)]
    n = np.linalg.norm(d, axis=1)
    ok = n > 1e-6
    nrm = np.stack([-d[ok, 1], d[ok, 0]], 1) / n[ok, None]
    q = np.concatenate([pts[idx[ok]] + offset_px * nrm, pts[idx[ok]] - offset_px * nrm])
    x, y = np.round(q[:, 0]).astype(int), np.round(q[:, 1]).astype(int)
    h, w = image.shape[:2]
    keep = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    return image[y[keep], x[keep]].astype(float)


def cut_end_scores(image: np.ndarray, uv: np.ndarray, scores: np.ndarray, centreline,
                   on_arc=None) -> np.ndarray:
    """``scores`` (5,) with A's and E's each times (1 - ``beyond_end_covered``) where that is at
    least ``COVERED`` (a cut end), and the points ``on_arc`` (placed on the detector's arc
    through A and E) then no surer than the less sure end."""
    out = np.asarray(scores, float).copy()
    if centreline is None:
        return out
    cut = False
    wire = beside_wire(image, centreline, 3.0 * WIRE_PX)
    for end in (0, 4):
        covered = beyond_end_covered(image, uv[end], centreline, wire_samples=wire)
        if covered >= COVERED:
            out[end] *= 1.0 - covered
            cut = True
    if cut and on_arc is not None:
        placed = np.asarray(on_arc, bool)
        out[placed] = np.minimum(out[placed], min(out[0], out[4]))
    return out


TIP_RISE_PX = 2.5
"""The wire's mass rises to its plateau over at least this many pixels at a real tip
(``common.detector.end_identity.shape_evidence``'s rise at A). Held needles, 4 moving takes: of
the detections whose one sure keypoint is A, A 8 px or more off (the tip in tissue, read at the
entry) rises within it in 71 of 95, A within 3 px in 27 of 281."""


def blunt_tip_scores(scores: np.ndarray, rise_a: float, gate: float = 0.5) -> np.ndarray:
    """``scores`` (5,) with A's no surer than ``gate * rise_a / TIP_RISE_PX`` when A is the only
    keypoint at or above ``gate`` (the pose nodes' default ``min_score``) and the wire reaches its
    full mass within ``TIP_RISE_PX`` of A (``rise_a``, px; NaN: not measured, no change): a lone
    tip that does not taper is where the tissue's surface cuts the wire, not the tip."""
    out = np.asarray(scores, float).copy()
    if not np.isfinite(rise_a) or rise_a >= TIP_RISE_PX or out[0] < gate or (out[1:] >= gate).any():
        return out
    out[0] = min(out[0], gate * max(float(rise_a), 0.0) / TIP_RISE_PX)
    return out
