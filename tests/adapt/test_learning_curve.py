"""``common.adapt.learning_curve`` reads back what models/learning_curve.sh wrote: the scores of
every size, the labelling and time figures, the markdown tables and the picture; and
``needletrack finetune --threads`` reaches the training config."""
import json
from pathlib import Path

import pytest
import yaml

from common.adapt.learning_curve import curve, main, tables

REPO = Path(__file__).resolve().parents[2]


def _results(found, kp, mm, deg, n, sure, swaps, nees):
    pose = {"position_mm": {"mean": mm, "median": mm / 2}, "orientation_deg": {"mean": deg, "median": deg / 2},
            "n": n, "expected": 150, "sure_and_right": sure, "confident_swaps": swaps, "nees": {"median": nees}}
    return {"detection_rate": found, "images": 300, "keypoints_2d_px": {"all": {"mean": kp, "median": kp / 2}},
            "pose": {"refined": pose}}


def _write(path: Path, obj):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj))


@pytest.fixture
def work(tmp_path):
    w = tmp_path / "silicone"
    _write(w / "eval_shipped" / "results.json", _results(0.9, 40.0, 0.8, 30.0, 55, 0.15, 0, 3.6))
    _write(w / "ref" / "eval_after" / "results.json", _results(0.99, 1.5, 0.5, 2.0, 140, 0.85, 0, 4.0))
    (w / "ref.seconds").write_text("900\n")
    for n, kp in ((10, 6.0), (30, 2.5)):
        _write(w / f"eval_{n}" / "results.json", _results(0.97, kp, 0.6, 3.0, 120, 0.7, 1, 4.5))
        _write(w / f"labels_{n}.json", {"clicks_per_frame": 7.5, "keypoint_px": {"mean": 1.1}})
        third = n // 4
        _write(w / f"ft_{n}" / "finetune.json", {"split": {"train": [{"frames": list(range(n - third))}],
                                                           "heldout": [{"frames": list(range(third))}]},
                                                 "train": {"elapsed_s": 480}})
        (w / f"ft_{n}.seconds").write_text("600\n")
    (w / "eval_100").mkdir()          # a size still running: no results.json yet, not on the curve
    return w


def test_curve_reads_every_finished_size(work):
    c = curve(work)
    assert c["look"] == "silicone" and list(c["sizes"]) == [10, 30]
    r = c["sizes"][30]
    assert r["keypoints_px"] == 2.5 and r["trained_on"] == 23 and r["held_out"] == 7
    assert r["clicks_per_frame"] == 7.5 and r["finetune_minutes"] == 10 and r["training_minutes"] == 8
    assert c["shipped"]["found"] == 0.9 and c["ref"]["minutes"] == 15 and c["ref"]["refined_mm"] == 0.5


def test_tables_and_picture(work, tmp_path, capsys):
    md = tables([work])
    assert "| 30 | 23 / 7 | 7.5 | 1.10 | 10.0 (8.0) |" in md
    assert "| 30 labelled frames | held-out | 97.0% | 2.50 |" in md
    assert "| 400 frames with full truth (15.0 min) | held-out | 99.0% | 1.50 |" in md
    png, js = tmp_path / "curve.png", tmp_path / "curve.json"
    assert main([str(work), "--plot", str(png), "--json", str(js)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads(js.read_text())[0]["sizes"]["10"]["keypoints_px"] == 6.0
    with pytest.raises(SystemExit):
        main([str(tmp_path / "missing")])
    assert "not a folder" in capsys.readouterr().err


def test_finetune_threads_reach_the_training_config(tmp_path):
    from common.adapt.finetune import write_config
    init = REPO / "models" / "keypoint" / "model.pt"
    cfg = yaml.safe_load(write_config(str(REPO / "models" / "finetune.yaml"), str(init), 3.0, tmp_path,
                                      threads=1).read_text())
    assert cfg["train"]["threads"] == 1 and cfg["train"]["time_budget_min"] == 3.0
    again = yaml.safe_load(write_config(str(REPO / "models" / "finetune.yaml"), str(init), 3.0, tmp_path).read_text())
    assert again["train"]["threads"] == yaml.safe_load((REPO / "models" / "finetune.yaml").read_text())["train"]["threads"]
