"""The detector's unfamiliarity: a Mahalanobis distance of its crop descriptor from the
training looks' (common.detector.familiarity)."""
import json

import numpy as np
import pytest

from common.detector.familiarity import (
    Familiarity,
    FamiliarityFileError,
    fit_familiarity,
    load_familiarity,
    save_familiarity,
)


def _features(rng, n, d=40, shift=0.0):
    basis = rng.normal(size=(d, d))
    z = rng.normal(size=(n, d)) * np.linspace(3.0, 0.1, d)
    return z @ basis.T * 0.1 + shift


def test_unfamiliarity_is_about_one_on_the_reference_and_grows_off_it():
    rng = np.random.default_rng(1)
    ref = _features(rng, 600)
    fam = fit_familiarity(ref, components=8)
    rng2 = np.random.default_rng(1)
    same_look = _features(np.random.default_rng(2), 300)   # other draws, another basis: unlike
    again = _features(rng2, 600)                            # the same draws: the reference itself
    u_ref = fam.distance(again) / fam.median_distance
    assert np.median(u_ref) == pytest.approx(1.0, abs=1e-9)
    u_other = fam.distance(same_look) / fam.median_distance
    assert np.median(u_other) > 1.2
    shifted = ref[:50] + 5.0 * np.sqrt(fam.residual_variance)
    assert min(fam.unfamiliarity(f) for f in shifted) > np.quantile(u_ref, 0.99)


def test_a_familiarity_file_round_trips_and_bad_files_are_named(tmp_path):
    rng = np.random.default_rng(3)
    fam = fit_familiarity(_features(rng, 200), fitted_on=["std", "wide"], components=6)
    weights = tmp_path / "model.pt"
    save_familiarity(fam, tmp_path / "familiarity.json")
    back = load_familiarity(weights)
    x = _features(rng, 5)[0]
    assert back.unfamiliarity(x) == pytest.approx(fam.unfamiliarity(x))
    assert back.fitted_on == ("std", "wide")
    assert load_familiarity(tmp_path / "other" / "model.pt") is None
    d = fam.to_dict()
    d["variances"] = d["variances"][:-1]
    (tmp_path / "familiarity.json").write_text(json.dumps(d))
    with pytest.raises(FamiliarityFileError, match="familiarity.json: inconsistent shapes"):
        load_familiarity(weights)
    (tmp_path / "familiarity.json").write_text("{not json")
    with pytest.raises(FamiliarityFileError, match="familiarity.json: not readable JSON"):
        load_familiarity(weights)
    with pytest.raises(FamiliarityFileError, match="format must be"):
        Familiarity.from_dict({"mean": []}, "x")


def test_too_few_detections_to_fit_is_an_error_and_few_fit_fewer_components():
    with pytest.raises(ValueError, match="need at least 10"):
        fit_familiarity(np.zeros((9, 40)), components=8)
    fam = fit_familiarity(np.random.default_rng(0).normal(size=(12, 40)), components=8)
    assert len(fam.variances) == 6 and np.isfinite(fam.median_distance)
