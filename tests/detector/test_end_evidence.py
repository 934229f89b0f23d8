"""The learned detector's end-identity evidence (common/detector/end_identity.py) on drawn
images: a tapered end against a blunt one, heatmaps, the coefficient fit and file."""
import json

import cv2
import numpy as np
import pytest

from common.detector.end_identity import (
    FEATURES,
    EndEvidence,
    fit_coefficients,
    network_evidence,
    shape_evidence,
)
from common.detector.weights import ModelFileError, load_end_coefficients


def drawn_needle(taper_px=12.0, wire_px=5.0, radius_px=90.0, size=320):
    """A grey image with a white arc: tapered to a point at its start (the tip, A), blunt at
    its end (the tail, E); returns the image (drawn 4x larger, then downscaled) and its
    centreline A -> E (px)."""
    s = 4
    big = np.full((size * s, size * s, 3), (80, 90, 170), np.uint8)
    ang = np.radians(np.linspace(200, 340, 400))
    c = np.array([size / 2, size / 2 + radius_px * 0.6])
    pts = c + radius_px * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    for p, a in zip(pts, arc):
        r = 0.5 * wire_px * min(1.0, a / taper_px) ** 0.75
        if r > 0.05:
            cv2.circle(big, tuple(np.round(p * s).astype(int)), max(1, int(round(r * s))), (235, 235, 235), -1)
    img = cv2.resize(big, (size, size), interpolation=cv2.INTER_AREA)
    return cv2.GaussianBlur(img, (0, 0), 0.7), pts


def test_the_tapered_end_is_told_from_the_blunt_one():
    img, line = drawn_needle()
    llr, rise_a, rise_e = shape_evidence(img, line)
    assert llr > 0.5 and rise_a > rise_e           # A, the tapered end, rises slowly
    llr_turned, ra, re = shape_evidence(img, line[::-1])
    assert llr_turned == pytest.approx(-llr, abs=0.3) and ra == pytest.approx(rise_e, abs=0.6)


def test_no_shape_evidence_from_too_little_curve_or_no_wire():
    img, line = drawn_needle()
    assert np.isnan(shape_evidence(img, line[:5])[0])
    assert np.isnan(shape_evidence(np.full_like(img, 100), line)[0])


def test_network_evidence_reads_which_end_each_heatmap_chose():
    m = 32
    logits = np.full((5, m, m), -10.0)
    A, E = np.array([5.0, 6.0]), np.array([25.0, 20.0])
    logits[0, 6, 5] = logits[4, 20, 25] = 10.0            # A's map at A, E's map at E
    cells = np.array([A, [10, 10], [15, 15], [20, 18], E])
    assert network_evidence(logits, cells) > 10
    logits[0, 20, 25] = logits[4, 6, 5] = 10.0            # both maps split between the ends
    assert network_evidence(logits, cells) == pytest.approx(0.0, abs=0.01)
    logits[0, 6, 5] = -10.0                               # A's map now at E only: turned
    assert network_evidence(logits, cells) < -10


def test_the_evidence_becomes_a_probability_and_the_fit_recovers_known_weights():
    assert EndEvidence(float("nan"), float("nan")).p_a_is_tip(np.array([1.0, 1.0, 0.0])) == 0.5
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.normal(0, 2, 4000), rng.normal(0, 2, 4000), np.ones(4000)])
    w_true = np.array([1.5, -0.5, 0.3])
    y = (rng.random(4000) < 1 / (1 + np.exp(-X @ w_true))).astype(float)
    assert np.allclose(fit_coefficients(X, y), w_true, atol=0.15)


def test_the_coefficient_file_beside_the_weights(tmp_path):
    weights = tmp_path / "model.pt"
    assert load_end_coefficients(weights) is None              # no file: nothing is stated
    (tmp_path / "end_identity.json").write_text(json.dumps({"coef": [1.0, 0.5, -0.1]}))
    assert np.allclose(load_end_coefficients(weights), [1.0, 0.5, -0.1])
    six = [1.0, 0.5, -0.1, 0.2, -0.3, -0.4]
    (tmp_path / "end_identity.json").write_text(json.dumps({"features": list(FEATURES), "coef": six}))
    assert np.allclose(load_end_coefficients(weights), six)
    (tmp_path / "end_identity.json").write_text(json.dumps({"coef": [1.0, "x"]}))
    with pytest.raises(ModelFileError, match="end_identity.json"):
        load_end_coefficients(weights)


def test_a_small_needle_weighs_its_evidence_by_the_fitted_size_terms():
    """features(): [shape, net, 1, small, small shape, small net] with small = log2 of how many
    times shorter than LENGTH_REF_PX the needle is (0 for a long one or an unknown length)."""
    big = EndEvidence(1.0, 2.0, length_px=400.0)
    small = EndEvidence(1.0, 2.0, length_px=40.0)            # a quarter of 160 px: small = 2
    assert np.allclose(big.features(), [1, 2, 1, 0, 0, 0, 0, 0, 0])
    assert np.allclose(small.features(), [1, 2, 1, 2, 2, 4, 0, 0, 0])
    assert np.allclose(EndEvidence(1.0, 2.0).features(), [1, 2, 1, 0, 0, 0, 0, 0, 0])
    assert len(big.features()) == len(FEATURES)
    coef = np.array([0.0, 1.0, 0.0, 0.0, 0.0, -0.5])        # the network not trusted when this small
    assert big.p_a_is_tip(coef) == pytest.approx(1 / (1 + np.exp(-2.0)))
    assert small.p_a_is_tip(coef) == pytest.approx(0.5)
    # an older 3-coefficient fit reads the first three features
    assert small.p_a_is_tip(np.array([0.0, 1.0, 0.0])) == pytest.approx(1 / (1 + np.exp(-2.0)))


def test_an_unfamiliar_image_weighs_the_networks_evidence_by_the_fitted_far_terms():
    """far = log2(unfamiliarity) clipped to [0, 3]: 0 when familiar (<= 1) or not stated; the
    fitted far_net_llr term takes the network's evidence back on an image unlike its training."""
    familiar = EndEvidence(1.0, 2.0, length_px=400.0, unfamiliarity=0.8)
    far = EndEvidence(1.0, 2.0, length_px=400.0, unfamiliarity=4.0)          # far = 2
    very = EndEvidence(1.0, 2.0, length_px=400.0, unfamiliarity=1e6)         # clipped at 3
    assert np.allclose(familiar.features()[6:], [0, 0, 0])
    assert np.allclose(far.features()[6:], [2, 2, 4])
    assert np.allclose(very.features()[6:], [3, 3, 6])
    coef = np.zeros(len(FEATURES))
    coef[1], coef[FEATURES.index("far_net_llr")] = 1.0, -0.5
    assert familiar.p_a_is_tip(coef) == pytest.approx(1 / (1 + np.exp(-2.0)))
    assert far.p_a_is_tip(coef) == pytest.approx(0.5)
    # a six-coefficient fit (before the far terms) reads the first six features
    assert far.p_a_is_tip(coef[:6]) == pytest.approx(1 / (1 + np.exp(-2.0)))


def test_the_fit_weighs_samples():
    """fit_coefficients with per-sample weights equals the fit on repeated samples."""
    from common.detector.end_identity import fit_coefficients
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.normal(size=60), np.ones(60)])
    y = (X[:, 0] + rng.normal(0, 1, 60) > 0).astype(float)
    w = rng.integers(1, 4, 60)
    rep = np.repeat(np.arange(60), w)
    assert np.allclose(fit_coefficients(X, y, weights=w), fit_coefficients(X[rep], y[rep]), atol=1e-6)
