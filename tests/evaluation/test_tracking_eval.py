"""The moving takes' evaluation (common/evaluation/moving.py): its tables on hand-made frames, and
``needletrack eval`` with the tracker on a small generated pickup take with the oracle (its
tables, and tracking.mp4 read back)."""
import json
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from common.evaluation.moving import (
    CORRECTION_AFTER,
    by_visible,
    correction_table,
    held_runs,
    in_hand_table,
    moving_markdown,
    stereo_visible,
)
from common.geometry.transforms import make_T
from common.runtime.messages import ArmCorrection, GroundTruth, InHandPose, InstrumentState


def _truth(seq, sequence=0):
    return GroundTruth(seq, seq, sequence=sequence, T_world_needle=make_T(np.eye(3), [0, 0, 0.1]),
                       needle_at_rest=False)


def _inst(seq, holds):
    T = make_T(np.eye(3), [0.0, 0.0, 0.095])
    return {"psm1": InstrumentState("psm1", seq, seq, T, 0.06 if holds else 0.9, holds)}


def test_held_runs_count_frames_per_holder_and_take():
    truths = {s: _truth(s, 0 if s < 20 else 1) for s in range(30)}
    inst = {s: _inst(s, 5 <= s < 25) for s in range(30)}
    runs = held_runs(truths, inst, sorted(truths))
    assert runs[5] == ("psm1", 0) and runs[19] == ("psm1", 14)
    assert runs[20] == ("psm1", 0)                # a new take starts a new run
    assert 4 not in runs and 25 not in runs


def test_the_in_hand_pose_is_scored_from_the_10th_held_frame():
    truths = {s: _truth(s) for s in range(40)}
    inst = {s: _inst(s, s >= 5) for s in range(40)}
    T_true = make_T(np.eye(3), [0.0, 0.0, 0.005])     # the needle 5 mm along the jaws
    off = make_T(np.eye(3), [0.0, 0.001, 0.005])      # 1 mm off
    in_hand = {s: InHandPose("psm1", s, s, "psm1_jaw", T_true if s < 30 else off, np.eye(6) * 1e-8)
               for s in range(10, 38)}
    t = in_hand_table(truths, inst, in_hand, sorted(truths))
    assert t["frames"] == 40 - 14 and t["wrong_holder"] == 2     # held from 5: scored from 14; 38, 39 missing
    assert t["posed"] == 24 and t["position_mm"]["max"] == pytest.approx(1.0)
    assert t["position_mm"]["mean"] == pytest.approx(8 / 24)


def test_each_arm_s_correction_is_scored_against_its_true_jaws_from_3_s_after_it_first_holds():
    """The arm reports its jaws 3 mm off; the correction puts them 0.5 mm off (stated 0.5 mm per
    axis) from frame 100 on, 2 mm off before; it holds the needle from frame 10 (scored from 100)."""
    n = 10 + CORRECTION_AFTER + 30
    truths = {s: _truth(s) for s in range(n)}
    T_true = make_T(np.eye(3), [0.0, 0.0, 0.095])
    inst = {s: {"psm1": InstrumentState("psm1", s, s, make_T(np.eye(3), [0.003, 0.0, 0.095]), 0.06, s >= 10,
                                        T_world_jaw_truth=T_true)} for s in range(n)}
    cov = np.diag([1e-4] * 3 + [0.5e-3 ** 2] * 3)
    corr = {s: {"psm1": ArmCorrection("psm1", s, s, np.eye(4), make_T(np.eye(3), [0.0005 if s >= 100 else 0.002,
                                                                                0.0, 0.095]), cov)}
            for s in range(n) if s != n - 1}
    t = correction_table(truths, inst, corr, set(truths))
    assert t["corrected"]["n"] == 29 and t["missing"] == 1 and t["reported"]["n"] == 30
    assert t["corrected"]["position_mm"]["max"] == pytest.approx(0.5)
    assert t["corrected"]["within_1mm_1deg"] == 1.0 and t["corrected"]["nees_median"] == pytest.approx(1.0)
    assert t["reported"]["position_mm"]["mean"] == pytest.approx(3.0)
    lines = moving_markdown({"frames": n, "seen_from": 0.3, "methods": {}, "arm_correction": t})
    assert any("within 1 mm and 1 deg" in line for line in lines)


def test_the_visible_share_is_the_smaller_cameras_and_bins_count_unposed_frames():
    f = SimpleNamespace(arc_visible={"left": 0.8, "right": 0.35}, visible=None)
    assert stereo_visible(f) == 0.35
    g = SimpleNamespace(visible={"left": np.array([1, 1, 0, 0, 0], bool), "right": np.ones(5, bool)})
    assert stereo_visible(g) == pytest.approx(0.4)
    errors = {0: (1e-3, 0.01, 5.0), 1: (np.nan, np.nan, np.nan), 2: (2e-3, 0.02, 6.0)}
    rows = by_visible(errors, {0: 0.05, 1: 0.5, 2: 0.9})
    assert [r["n"] for r in rows] == [1, 0, 1, 1]
    assert rows[2]["posed"] == 0 and rows[3]["position_mm"]["mean"] == pytest.approx(2.0)


@pytest.fixture(scope="module")
def pickup_take(tmp_path_factory):
    """A pickup take, 320x240, every other frame (80 frames)."""
    from common.cli import dataset_main
    ds = tmp_path_factory.mktemp("take") / "pickup"
    assert dataset_main(["generate", "--out", str(ds), "--sequences", "1", "--motion", "pickup",
                         "--width", "320", "--height", "240", "--msaa", "0", "--jobs", "1", "--seed", "3400",
                         "--take-every", "2", "--quiet"]) == 0
    return ds


@pytest.mark.graph
def test_eval_tracks_a_pickup_take_with_the_oracle(pickup_take, tmp_path):
    from common.evaluation.cli import main as eval_main
    ds = pickup_take
    out = tmp_path / "out"
    rec = tmp_path / "refined.jsonl"
    assert eval_main(["--dataset", str(ds), "--detector", "oracle", "--out", str(out), "--quiet",
                      "--timeout", "300", "--record", str(rec)]) == 0
    res = json.loads((out / "results.json").read_text())
    t = res["pose"]["tracked"]
    assert t["n"] >= 0.95 * t["expected"] and t["position_mm"]["mean"] < 0.1 and t["orientation_deg"]["mean"] < 0.3
    mv = res["moving"]
    assert mv["frames"] == res["frames"]
    seen = mv["methods"]["tracked"]["seen"]
    assert seen["posed_share"] >= 0.95 and seen["position_mm"]["mean"] < 0.1
    h = mv["in_hand"]
    assert h["frames"] > 10 and h["posed"] >= 0.9 * h["frames"] and h["position_mm"]["mean"] < 0.1
    assert res["node_counters"]["tracker"].get("events.grasp") == 1
    assert "## Moving takes" in (out / "report.md").read_text()
    # moving takes: the refinement as deployed, warm from frame to frame (what the tracker gets live)
    graph = yaml.safe_load((out / "graph.yaml").read_text())
    assert next(n for n in graph["nodes"] if n["id"] == "refine")["params"]["tracking"] is True
    from test_take_video import read_video      # the take's video: a frame per frame at 320x240
    frames, fps = read_video(out / "tracking.mp4")
    assert len(frames) == res["frames"] and {f.shape for f in frames} == {(240, 320, 3)} and fps == pytest.approx(30.0)
    # the tracker replayed on the run's refined poses (needletrack bench tracker --replay) gives its figures
    from common.data.dataset import Dataset
    from common.evaluation.tracker_replay import replay_summary, replay_tracker
    folder = Dataset(str(ds), check_files=False)
    replayed = replay_summary(folder, replay_tracker(folder, rec))["methods"]["tracked"]["seen"]
    assert abs(replayed["posed"] - seen["posed"]) <= 1
    assert replayed["position_mm"]["mean"] == pytest.approx(seen["position_mm"]["mean"], abs=0.01)
    assert replayed["orientation_deg"]["mean"] == pytest.approx(seen["orientation_deg"]["mean"], abs=0.03)


@pytest.mark.graph
def test_the_live_bench_runs_the_tracker_on_a_moving_take(pickup_take, tmp_path, capsys):
    """``needletrack bench graph`` on moving takes: the tracker's poses are the final ones; the
    figures printed, none asserted on time."""
    from common.bench.graph_bench import main as bench_main
    out = tmp_path / "bench.json"
    assert bench_main(["graph", "--dataset", str(pickup_take), "--detector", "oracle", "--rate", "30",
                       "--duration", "3", "--warmup", "1.5", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["final_method"] == "tracked" and r["frame_node"] == "refine"
    assert set(r["per_node"]) == {"replay", "detector_left", "detector_right", "ecm", "refine", "fusion_refined",
                                  "tracker"}
    assert r["throughput_hz"] > 0 and r["stages"]["tracked"]["rate_hz"] > 0
    lat = r["latency_ms"]
    assert lat["n"] > 0 and 0 < lat["p50"] <= lat["p95"] <= lat["p99"]
    text = capsys.readouterr().out
    assert "final poses (tracked)" in text and "p95" in text and "tracker" in text


def test_the_lag_is_the_shift_that_brings_the_poses_nearest_the_truth():
    from common.evaluation.moving import lag_frames
    truths = {s: GroundTruth(s, s, sequence=0, T_world_needle=make_T(np.eye(3), [0.001 * s, 0, 0.1]),
                             needle_at_rest=False) for s in range(40)}
    late = {s: SimpleNamespace(T_world_needle=truths[max(s - 3, 0)].T_world_needle) for s in range(40)}
    assert lag_frames(late, truths, range(40)) == 3
    assert lag_frames({s: SimpleNamespace(T_world_needle=truths[s].T_world_needle) for s in range(40)},
                      truths, range(40)) == 0
    assert lag_frames({}, truths, range(40)) is None


def test_the_tip_is_scored_through_each_change_of_holder():
    from common.evaluation.moving import holder_events, identity_through
    truths = {s: _truth(s, 0 if s < 60 else 1) for s in range(90)}
    inst = {s: _inst(s, 10 <= s < 40 or s >= 70) for s in range(90)}
    events = holder_events(truths, inst, sorted(truths))
    assert events == [(10, "grasp"), (40, "release"), (70, "grasp")]     # a new take is no event
    right, turned = (0.001, np.radians(2.0), 1.0), (0.001, np.radians(178.0), 1.0)
    errors = {s: right for s in range(90)}
    errors.update({s: turned for s in range(45, 50)})     # turned after the release
    errors.update({s: (np.nan, np.nan, np.nan) for s in range(60, 85)})   # not posed around the last
    out = identity_through(events, errors, sorted(truths))
    assert out["grasp"] == {"kept": 1, "lost": 0, "unscored": 1}
    assert out["release"] == {"kept": 0, "lost": 1, "unscored": 0}
    assert out["all"] == {"kept": 1, "lost": 1, "unscored": 1}
