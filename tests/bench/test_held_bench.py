"""``needletrack bench held``: the detector on moving takes, binned by the share of the arc seen."""
import json

import numpy as np
import pytest

from common.bench.held_bench import (
    RING_BGR,
    format_report,
    hidden_sure_by_keypoint,
    hidden_sure_crop,
    image_record,
    save_hidden_sure_picture,
    summarise,
    visible_fraction,
)
from common.runtime.messages import Keypoints


def _kp(uv, scores, found=True):
    if not found:
        return Keypoints.not_found("left", 0, 0, "t", "no needle")
    return Keypoints("left", 0, 0, True, np.asarray(uv, float), np.asarray(scores, float), 0.9)


def test_records_count_hidden_points_stated_sure_and_errors_of_seen_points_only():
    truth = np.arange(10, dtype=float).reshape(5, 2)
    vis = np.array([True, True, True, False, False])
    uv = truth + [[1, 0], [0, 2], [0, 0], [30, 0], [0, 0]]
    r = image_record(_kp(uv, [0.9, 0.9, 0.2, 0.8, 0.1]), truth, vis, 0.45)
    assert r["err_visible"] == [1.0, 2.0, 0.0] and r["err_sure"] == [1.0, 2.0]
    assert r["hidden"] == 2 and r["hidden_sure"] == 1 and r["any_sure"]
    miss = image_record(_kp(None, None, found=False), truth, vis, 0.05)
    assert not miss["found"] and miss["err_visible"] == [] and not miss["any_sure"] and miss["hidden"] == 0
    unsure = image_record(_kp(uv, [0.3] * 5), truth, np.zeros(5, bool), 0.05)
    rows = summarise([r, miss, unsure])
    low, mid = rows[0], rows[2]
    assert low["bin"] == "0-10%" and low["images"] == 2 and low["found"] == 0.5 and low["no_sure_points"] == 1.0
    assert low["hidden_sure"] == 0.0 and low["hidden_keypoints"] == 5
    assert mid["bin"] == "30-60%" and mid["kp_error_mean_px"] == pytest.approx(1.0)
    assert mid["hidden_sure"] == 0.5 and rows[1]["images"] == 0


def test_hidden_points_stated_sure_are_told_apart_by_keypoint_and_by_how_far_off_they_were_placed():
    truth = np.arange(10, dtype=float).reshape(5, 2)
    hidden_a = np.array([False, True, True, True, True])
    tip_at_entry = image_record(_kp(truth + [[20, 0], [0, 0], [0, 0], [0, 0], [0, 0]], [0.8] * 5), truth, hidden_a, 0.7)
    c_under_jaw = image_record(_kp(truth + [[0, 0], [0, 0], [1, 1], [0, 0], [0, 0]], [0.9] * 5), truth,
                               np.array([True, True, False, True, True]), 0.8)
    unsure = image_record(_kp(truth + 50, [0.2] * 5), truth, np.zeros(5, bool), 0.2)
    assert tip_at_entry["hidden_sure_points"] == [[0, 20.0]] and unsure["hidden_sure_points"] == []
    by = hidden_sure_by_keypoint([tip_at_entry, c_under_jaw, unsure])
    assert by["A"] == {"n": 1, "placed_right": 0, "placed_wrong": 1}
    assert by["C"] == {"n": 1, "placed_right": 1, "placed_wrong": 0}
    assert by["B"]["n"] == by["D"]["n"] == by["E"]["n"] == 0
    records = [tip_at_entry, c_under_jaw, unsure]
    text = format_report({"data": "d", "takes": 1, "frames": 3, "images": 3, "weights": "w",
                          "found_where_30pct_seen": 1.0, "bins": summarise(records), "hidden_sure_by_keypoint": by})
    assert "A 1 (0 / 1), B 0 (0 / 0), C 1 (1 / 0)" in text


def test_a_hidden_point_stated_sure_is_pictured_ringed_in_its_needles_crop(tmp_path):
    image = np.full((480, 640, 3), 120, np.uint8)
    truth = np.array([[300.0, 200], [320, 210], [340, 215], [360, 210], [380, 200]])
    k = _kp(truth + [[25, 0], [0, 0], [0, 0], [0, 0], [0, 0]], [0.8, 0.9, 0.2, 0.9, 0.9])
    crop = hidden_sure_crop(image, k, truth, np.array([False, True, True, True, True]), 0, side=200)
    assert crop.shape == (200, 200, 3)
    ring = (np.abs(crop.astype(int) - RING_BGR) < 60).all(axis=2)
    ys, xs = np.nonzero(ring)
    # the ring is round A as detected (25 px right of the truth's A); the crop spans the truth and
    # the detection (x 300..380, y 200..215) with a margin: 0.6 x 80 px each side of their middle
    scale = 200 / (2 * 0.6 * 80)
    assert ring.sum() > 20
    assert abs(xs.mean() - (100 + scale * (325 - 340))) < 1.5 and abs(ys.mean() - (100 + scale * (200 - 207.5))) < 1.5
    gallery = {n: [] for n in "ABCDE"}
    gallery["A"].append({"sequence": 0, "frame": 3, "camera": "left", "error_px": 25.0, "score": 0.8, "crop": crop})
    save_hidden_sure_picture(tmp_path / "g.png", {"gallery": gallery})
    assert (tmp_path / "g.png").stat().st_size > 5000


def test_visible_fraction_prefers_arc_visible_and_falls_back_to_the_keypoints():
    from common.data.dataset import parse_frame
    base = {"index": 0, "stamp_ns": 0, "left": "a.png", "right": "a.png"}
    f = parse_frame({**base, "visible": {"left": [True, False, False, False, False], "right": [True] * 5}})
    assert visible_fraction(f, "left") == 0.2 and visible_fraction(f, "right") == 1.0
    g = parse_frame({**base, "visible": {"left": [True] * 5, "right": [True] * 5},
                     "arc_visible": {"left": 0.33, "right": 0.9}})
    assert visible_fraction(g, "left") == 0.33


@pytest.mark.slow
def test_the_bench_runs_a_generated_take_and_writes_its_figures(tmp_path, capsys):
    from common.cli import bench_main, dataset_main
    out = tmp_path / "take"
    assert dataset_main(["generate", "--out", str(out), "--sequences", "1", "--motion", "pickup", "--width", "320",
                         "--height", "240", "--msaa", "0", "--seed", "5", "--randomise", "test", "--jobs", "1",
                         "--take-every", "8", "--quiet"]) == 0
    assert bench_main(["held", "--data", str(out), "--quiet", "--json", str(tmp_path / "r.json"),
                       "--picture", str(tmp_path / "r.png"), "--hidden-sure-picture", str(tmp_path / "h.png")]) == 0
    text = capsys.readouterr().out
    assert "found where >= 30% of the arc is seen" in text and "| 60-100% |" in text
    r = json.loads((tmp_path / "r.json").read_text())
    n = len((out / "frames.jsonl").read_text().splitlines())
    assert r["frames"] == n and r["images"] == 2 * n == sum(b["images"] for b in r["bins"])
    assert (tmp_path / "r.png").stat().st_size > 5000 and (tmp_path / "h.png").stat().st_size > 5000
    assert "gallery" not in r
    assert set(r["hidden_sure_by_keypoint"]) == set("ABCDE")
    assert sum(v["n"] for v in r["hidden_sure_by_keypoint"].values()) == sum(p["hidden_sure"] for p in r["per_image"])
    # a folder of needles at rest has no take to run on
    still = tmp_path / "still"
    assert dataset_main(["generate", "--out", str(still), "--sequences", "1", "--width", "160", "--height", "120",
                         "--msaa", "0", "--jobs", "1", "--quiet"]) == 0
    assert bench_main(["held", "--data", str(still), "--quiet"]) == 1
    assert "no frame of a moving take" in capsys.readouterr().err
