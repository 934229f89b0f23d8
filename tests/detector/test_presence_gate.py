"""The presence gate (``common.detector.presence_gate``): fitted as the lowest threshold that keeps
needle-free and misplaced reports under a share, kept beside the weights, used by the detector
unless a threshold is given, and fitted end to end by ``needletrack bench presence --fit``."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from common.detector.presence_gate import (
    DEFAULT_THRESHOLD, PresenceGateError, fit_presence_gate, load_presence_gate, presence_gate_path,
    save_presence_gate,
)

REPO = Path(__file__).resolve().parents[2]
WEIGHTS = REPO / "models" / "keypoint" / "model.pt"


def test_the_gate_is_the_lowest_threshold_under_both_shares():
    free = np.r_[np.zeros(95), 0.6, 0.7, 0.8, 0.9, 0.95]     # 100 needle-free images, 5 report a needle
    right = np.r_[np.full(80, 0.99), 0.97]
    wrong = np.r_[0.55, 0.9]                                  # of 100 images with a needle
    g = fit_presence_gate(free, right, wrong, 100, ["a", "b"], max_false=0.01)
    # above 0.8: 0.9 and 0.95 remain (2%); just above 0.9: one needle-free report (1%), no wrong one
    assert 0.9 < g.threshold < 0.9 + 1e-9
    assert g.false_share == pytest.approx(0.01) and g.wrong_share == 0 and g.right_share == pytest.approx(0.81)
    assert fit_presence_gate(free, right, wrong, 100, ["a"], max_false=0.06).threshold == DEFAULT_THRESHOLD
    strict = fit_presence_gate(free, right, wrong, 100, ["a"], max_false=0.0)
    assert 0.95 < strict.threshold < 0.97 and strict.false_share == 0 and strict.right_share == pytest.approx(0.81)
    with pytest.raises(ValueError):
        fit_presence_gate([], right, wrong, 100, ["a"])


def test_the_gate_file_round_trips_and_bad_files_are_named(tmp_path):
    w = tmp_path / "model.pt"
    assert load_presence_gate(w) is None
    g = fit_presence_gate(np.r_[0.0, 0.8], [0.99], [], 1, ["x"], max_false=0.0)
    save_presence_gate(g, presence_gate_path(w))
    assert load_presence_gate(w) == g
    presence_gate_path(w).write_text(json.dumps({**g.to_dict(), "threshold": 1.5}))
    with pytest.raises(PresenceGateError, match="presence_gate.json: threshold"):
        load_presence_gate(w)
    presence_gate_path(w).write_text("{")
    with pytest.raises(PresenceGateError, match="not a presence-gate file"):
        load_presence_gate(w)


def test_the_detector_uses_the_weights_gate_unless_told_a_threshold(tmp_path):
    from common.detector.inference import KeypointDetector
    w = tmp_path / "model.pt"
    shutil.copy(WEIGHTS, w)
    assert KeypointDetector(w, threads=1).threshold == DEFAULT_THRESHOLD
    save_presence_gate(fit_presence_gate(np.r_[0.0, 0.8], [0.99], [], 1, ["x"], max_false=0.0), presence_gate_path(w))
    det = KeypointDetector(w, threads=1)
    assert 0.8 < det.threshold < 0.81 and det.presence_gate.fitted_on == ("x",)
    assert KeypointDetector(w, threads=1, threshold=0.3).threshold == 0.3


def test_bench_presence_fits_a_gate_on_folders(tmp_path, capsys):
    from common.bench.presence_bench import main
    from common.cli import dataset_main
    pos, neg = tmp_path / "pos", tmp_path / "neg"
    assert dataset_main(["generate", "--out", str(pos), "--sequences", "2", "--steps", "1", "--width", "640",
                         "--height", "480", "--seed", "3", "--jobs", "1", "--quiet"]) == 0
    assert dataset_main(["generate-negatives", "--out", str(neg), "--frames", "2", "--width", "640",
                         "--height", "480", "--seed", "4", "--quiet"]) == 0
    gate_file, js = tmp_path / "presence_gate.json", tmp_path / "figures.json"
    assert main(["--data", str(pos), "--negatives", str(neg), "--fit", str(gate_file), "--json", str(js),
                 "--max-false", "0", "--plot", str(tmp_path / "t.png"), "--quiet"]) == 0
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"
    g = json.loads(gate_file.read_text())
    assert g["false_share"] == 0 and g["wrong_share"] == 0 and g["fitted_on"] == ["pos", "neg"]
    assert g["needle_free_images"] == 4 and g["images_with_needle"] == 4
    rows = json.loads(js.read_text())["rows"]
    assert {r["kind"] for r in rows} == {"right", "wrong", "false"}
    assert all(r["at_gate"] <= r["at_default"] for r in rows)
    assert "threshold" in capsys.readouterr().out
    curve = json.loads(js.read_text())["trade_off"]
    assert [c["threshold"] for c in curve] == sorted(c["threshold"] for c in curve)
    assert all(a["right"] >= b["right"] and a["false"] >= b["false"] for a, b in zip(curve, curve[1:]))
    with pytest.raises(SystemExit):
        main(["--data", str(pos), "--fit", str(gate_file)])
