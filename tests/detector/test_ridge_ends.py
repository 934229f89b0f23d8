"""A and E from the centreline ridge's ends when the tip and tail heatmaps collapse on one end."""
import numpy as np
import pytest

from common.detector.arc_fit import ARC_ANGLES_DEG, ideal_peak_mass
from common.detector.model import centreline_target
from common.detector.ridge_ends import ends_on_ridge, ridge_component, ridge_ends

M = 128
C = np.array([60.3, 70.6])
U = np.array([[34.0, 8.0], [-5.0, -22.0]])          # a tilted, foreshortened circle
T = np.deg2rad(np.asarray(ARC_ANGLES_DEG))
TRUE = C + np.stack([np.cos(T), np.sin(T)], 1) @ U.T   # A..E in cells
PEAK = ideal_peak_mass(1.5)


def _line_logit(t0=T[0], t1=T[-1]):
    tt = np.linspace(t0, t1, 300)
    dense = C + np.stack([np.cos(tt), np.sin(tt)], 1) @ U.T
    ridge = centreline_target([dense], M, 1.0)[0].numpy()
    return np.log(ridge + 1e-6) - np.log(1 - ridge + 1e-6)


def _peaks(*weighted):
    """Keypoint logits (m, m): a mixture of Gaussian peaks (sigma 1.5 cells) at (x, y) with weights."""
    yy, xx = np.mgrid[0:M, 0:M].astype(float)
    p = sum(w * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.5 ** 2)) for (x, y), w in weighted)
    p = p / p.sum() + 1e-12
    return np.log(p)


def _kp_logits(a_peaks, e_peaks):
    flat = np.full((M, M), -20.0)
    return np.stack([_peaks(*a_peaks), flat, flat, flat, _peaks(*e_peaks)])


def test_the_ridge_ends_are_the_arcs_ends():
    mask = ridge_component(_line_logit())
    p1, p2 = ridge_ends(mask)
    ends = sorted([p1, p2], key=lambda p: np.linalg.norm(p - TRUE[0]))
    assert np.linalg.norm(ends[0] - TRUE[0]) < 2.5 and np.linalg.norm(ends[1] - TRUE[4]) < 2.5


def test_both_ends_on_the_tail_are_moved_to_the_ridges_ends_and_named_by_the_heatmaps():
    # A's heatmap: most of its mass on the tail, some on the tip; E's: all on the tail
    kp = _kp_logits([(TRUE[4], 0.6), (TRUE[0], 0.4)], [(TRUE[4], 1.0)])
    a, e = TRUE[4] + 0.3, TRUE[4]                      # as decoded: collapsed on the tail
    found = ends_on_ridge(kp, _line_logit(), a, e, PEAK, 0.35)
    assert found is not None
    a2, e2, sa, se = found
    assert np.linalg.norm(a2 - TRUE[0]) < 1.0 and np.linalg.norm(e2 - TRUE[4]) < 1.0
    # each end is scored by the evidence of an end there (both heatmaps), not by A's alone
    assert sa == pytest.approx(0.4, abs=0.05) and se == pytest.approx(1.0)
    # named the other way round when the heatmaps say so (A's all on the far end)
    kp_turned = _kp_logits([(TRUE[4], 1.0)], [(TRUE[4], 0.6), (TRUE[0], 0.4)])
    a3, e3, _, _ = ends_on_ridge(kp_turned, _line_logit(), TRUE[4], TRUE[4], PEAK, 0.35)
    assert np.linalg.norm(a3 - TRUE[4]) < 1.0 and np.linalg.norm(e3 - TRUE[0]) < 1.0


def test_ends_that_span_the_ridge_are_left_alone():
    kp = _kp_logits([(TRUE[0], 1.0)], [(TRUE[4], 1.0)])
    assert ends_on_ridge(kp, _line_logit(), TRUE[0], TRUE[4], PEAK, 0.35) is None
    # no ridge: nothing to go by
    assert ends_on_ridge(kp, np.full((M, M), -9.0), TRUE[4], TRUE[4], PEAK, 0.35) is None


def test_a_ridge_end_where_no_end_is_seen_leaves_the_keypoints_alone():
    # the ridge runs on past the tip's heatmaps (under a jaw, say): no evidence of an end there
    kp = _kp_logits([(TRUE[4], 1.0)], [(TRUE[4], 1.0)])
    assert ends_on_ridge(kp, _line_logit(), TRUE[4], TRUE[4], PEAK, 0.35) is None
    assert ends_on_ridge(kp, _line_logit(), TRUE[4], TRUE[4], PEAK, 0.0) is not None


def test_the_detector_moves_collapsed_ends_and_states_no_end_identity():
    import torch

    from common.detector.inference import KeypointDetector
    det = KeypointDetector(device="cpu")
    kp = _kp_logits([(TRUE[4], 0.6), (TRUE[0], 0.4)], [(TRUE[4], 1.0)])
    heat = torch.from_numpy(np.concatenate([kp, _line_logit()[None]])[None]).float()
    uv_crop = np.repeat(TRUE[4][None], 5, axis=0)          # out_stride 1: cells are crop pixels
    sc = np.full(5, 0.3)
    on_arc = det._ends_from_ridge(uv_crop, sc, heat, heat[0, 5].numpy())
    assert on_arc is not None and on_arc.tolist() == [False, True, True, True, False]
    assert np.abs(uv_crop - TRUE).max() < 1.5               # B..D on the arc through the new ends
    assert sc[0] >= 0.35 and np.all(sc[1:4] == min(sc[0], sc[4]))
    assert det._p_a_is_tip({"ends_from_ridge": True}) == 0.5


def test_a_point_the_arc_places_over_a_stretch_with_no_ridge_is_not_stated_sure():
    from common.detector.arc_fit import RIDGE_SEEN, ridge_seen, unseen_on_arc_scores
    line = np.full((32, 32), -8.0)
    line[10, 2:20] = 6.0                                   # a ridge along row 10, x 2..19
    pts = np.array([[5.0, 10.0], [18.4, 10.4], [26.0, 10.0], [np.nan, 1.0], [12.0, 11.0]])
    seen = ridge_seen(line, pts)
    assert seen[0] > 0.99 and seen[1] > 0.99 and seen[2] < RIDGE_SEEN and seen[3] == 0.0
    assert seen[4] > 0.99 and ridge_seen(line, pts[4:], radius=0)[0] < RIDGE_SEEN   # beside the ridge
    own = np.array([0.2, 0.2, 0.9, 0.1, 0.9])             # the heatmaps place hidden points surely too
    sc = unseen_on_arc_scores(np.full(5, 0.9), own, line, pts)
    assert sc[:2].tolist() == [0.9, 0.9] and np.all(sc[2:] < RIDGE_SEEN)
