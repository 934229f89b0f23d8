"""The needle's two ends from the centreline heatmap, when the tip and tail heatmaps lose one.

On looks the network has not learned (another renderer's threadless needle) the heatmaps of A
and E can both peak at the same end of the wire: the keypoints collapse onto it, the next pass's
crop shrinks around them and the centreline seeded through them covers a fraction of the needle.
The centreline heatmap still follows the whole wire, and the ends of its ridge are the needle's
ends, or where it goes under an instrument. ``ends_on_ridge`` puts A and E there when the
decoded ends span much less of the ridge than it covers, each moved to the strongest "an end is
here" evidence nearby (the sum of A's and E's heatmaps) and named by which assignment the two
heatmaps prefer, but only when that evidence is there at both (``min_score``): a ridge that
ends under a jaw, with no end seen there, leaves the decoded keypoints as they were. Each end's
score is that evidence's peak mass, as ``decode_heatmaps`` scores a keypoint; the end identity
stays the business of ``common.detector.end_identity``.

All coordinates are heatmap cells (x, y), as ``decode_heatmaps`` returns them divided by its
stride.
"""
from __future__ import annotations

import cv2
import numpy as np

from common.detector.end_identity import mass_near
from common.detector.model import parabola_vertex

RIDGE_PROB = 0.25      # centreline probability that makes a cell part of the ridge (as decode_centreline)
MIN_RIDGE_CELLS = 12   # fewer ridge cells: no ridge to speak of
COLLAPSE_RATIO = 0.4   # decoded ends closer than this fraction of the ridge's larger extent collapsed
SNAP_CELLS = 3         # an end moves to the strongest end evidence within this many cells


def _softmax2d(logits: np.ndarray) -> np.ndarray:
    x = np.asarray(logits, np.float64)
    p = np.exp(x - x.max())
    return p / p.sum()


def ridge_component(line_logit: np.ndarray, min_prob: float = RIDGE_PROB) -> np.ndarray | None:
    """Boolean mask (m, m) of the largest 8-connected component of cells whose centreline
    probability is at least ``min_prob``; None when it has fewer than ``MIN_RIDGE_CELLS``."""
    mask = (np.asarray(line_logit, np.float32) >= np.log(min_prob / (1.0 - min_prob))).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n < 2:
        return None
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    if stats[k, cv2.CC_STAT_AREA] < MIN_RIDGE_CELLS:
        return None
    return labels == k


def _farthest_along(mask: np.ndarray, seed: tuple[int, int]) -> tuple[int, int]:
    """The cell (x, y) of ``mask`` reached last by a grassfire from ``seed`` that spreads within
    the mask (8-connected): the farthest along a thin curve."""
    reached = np.zeros(mask.shape, np.uint8)
    reached[seed[1], seed[0]] = 1
    allowed = mask.astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    last = reached
    for _ in range(mask.size):
        grown = cv2.dilate(reached, kernel) & allowed
        front = grown & (1 - reached)
        if not front.any():
            break
        last, reached = front, grown
    ys, xs = np.nonzero(last)
    return int(xs[0]), int(ys[0])


def ridge_ends(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two ends (x, y) of a thin ridge: the cell farthest along it from any cell, then the
    cell farthest along it from that one (a curve's geodesic diameter)."""
    ys, xs = np.nonzero(mask)
    p1 = _farthest_along(mask, (int(xs[0]), int(ys[0])))
    p2 = _farthest_along(mask, p1)
    return np.array(p1, float), np.array(p2, float)


def _snap(q: np.ndarray, xy: np.ndarray, r: int = SNAP_CELLS) -> np.ndarray:
    """The peak of ``q`` within ``r`` cells of ``xy``, at sub-cell precision (a parabola through
    the log-probabilities, as ``decode_heatmaps``)."""
    m = q.shape[-1]
    x0, y0 = int(round(float(xy[0]))), int(round(float(xy[1])))
    ya, yb, xa, xb = max(0, y0 - r), min(m, y0 + r + 1), max(0, x0 - r), min(m, x0 + r + 1)
    win = q[ya:yb, xa:xb]
    iy, ix = np.unravel_index(int(np.argmax(win)), win.shape)
    iy, ix = iy + ya, ix + xa
    lq = np.log(q + 1e-12)
    dx = float(parabola_vertex(lq[iy, ix - 1], lq[iy, ix], lq[iy, ix + 1])) if 0 < ix < m - 1 else 0.0
    dy = float(parabola_vertex(lq[iy - 1, ix], lq[iy, ix], lq[iy + 1, ix])) if 0 < iy < m - 1 else 0.0
    return np.array([ix + dx, iy + dy])


def ends_on_ridge(kp_logits: np.ndarray, line_logit: np.ndarray, a: np.ndarray, e: np.ndarray,
                  peak_mass: float, min_score: float, collapse_ratio: float = COLLAPSE_RATIO):
    """A and E (cells) and their scores from the ridge's ends, when the decoded ends ``a``, ``e``
    span less than ``collapse_ratio`` of the ridge's larger extent and both ridge ends score at
    least ``min_score``; else None.

    ``kp_logits`` (5, m, m) the keypoint logits (A is 0, E is 4), ``line_logit`` (m, m) the
    centreline logit, ``peak_mass`` a perfect peak's mass within ``PEAK_RADIUS_CELLS`` (scores are
    divided by it and clipped to [0, 1]). Returns (a (2,), e (2,), score_a, score_e)."""
    mask = ridge_component(line_logit)
    if mask is None:
        return None
    ys, xs = np.nonzero(mask)
    extent = max(xs.max() - xs.min(), ys.max() - ys.min()) + 1.0
    if np.linalg.norm(np.asarray(a, float) - np.asarray(e, float)) >= collapse_ratio * extent:
        return None
    pa, pe = _softmax2d(kp_logits[0]), _softmax2d(kp_logits[4])
    q = pa + pe
    p1, p2 = (_snap(q, p) for p in ridge_ends(mask))
    if np.linalg.norm(p1 - p2) < collapse_ratio * extent:
        return None
    if mass_near(pa, p1) * mass_near(pe, p2) < mass_near(pa, p2) * mass_near(pe, p1):
        p1, p2 = p2, p1
    score = [min(1.0, mass_near(q, p) / peak_mass) for p in (p1, p2)]
    if min(score) < min_score:
        return None
    return p1, p2, score[0], score[1]
