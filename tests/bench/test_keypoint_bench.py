"""``needletrack bench detector``: the figures it reports are computed from the detections."""
import json

import numpy as np

from common.detector.synthetic import write_synthetic_dataset
from common.bench.detector_bench import SURE_SCORE, main, run


def test_bench_reports_accuracy_speed_and_false_detections(tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path / "syn", 3, seed=2, size=(960, 540))
    neg = write_synthetic_dataset(tmp_path / "neg", 1, seed=3, size=(960, 540), n_empty=1)
    r = run(data, "classical", n_frames=3, negatives=neg, repeat=1, progress=False)
    assert r["images"] == 6 and r["with_needle"] == 6 and 0 <= r["found"] <= 6
    assert r["negatives"] == 2 and 0 <= r["false_detections"] <= 2
    assert r["cold_ms_mean"] > 0
    assert r["found"] >= 3   # the drawn needles are easy for the arc segmentation
    assert np.isfinite(r["kp_error_mean_px"]) and set(r["kp_error_per_kp_px"]) == set("ABCDE")
    assert 0 < r["kp_sure_fraction"] <= 1 and np.isfinite(r["kp_error_sure_mean_px"])
    out = tmp_path / "r.json"
    assert main(["--data", str(data), "--backend", "classical", "--frames", "2", "--repeat", "1",
                 "--json", str(out)]) == 0
    assert json.loads(out.read_text())["images"] == 4
    assert "needle found" in capsys.readouterr().out
    assert SURE_SCORE == 0.5
