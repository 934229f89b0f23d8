"""``needletrack eval`` through the real graph on a small generated dataset (480x270)."""
import json
import shutil

import pytest
import yaml

from common.cli import dataset_main
from common.evaluation.cli import main as eval_main
from common.bench.graph_bench import main as bench_main
from common.evaluation.results import check_results

pytestmark = pytest.mark.graph


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("eval") / "ds"
    rc = dataset_main(["generate", "--out", str(path), "--sequences", "3", "--steps", "3",
                       "--width", "480", "--height", "270", "--seed", "3", "--randomise", "none",
                       "--jobs", "1", "--quiet"])
    assert rc == 0
    return path


def run_eval(dataset, out, *extra):
    rc = eval_main(["--dataset", str(dataset), "--detector", "oracle", "--out", str(out), "--quiet",
                    "--timeout", "120", *extra])
    assert rc == 0
    return json.loads((out / "results.json").read_text())


def test_oracle_without_noise_gives_zero_errors(small_dataset, tmp_path):
    res = run_eval(small_dataset, tmp_path)
    assert check_results(res) == []
    assert res["frames"] == 9 and res["detector"] == "oracle"
    assert res["detection_rate"] == 1.0
    assert res["keypoints_2d_px"]["all"]["mean"] < 1e-6
    assert res["keypoints_3d_mm"]["all"]["mean"] < 1e-6
    for m in ("pnp_joint", "triangulation", "multiview"):
        d = res["pose"][m]
        assert d["n"] == d["expected"] == (3 if m == "multiview" else 9), m
        assert d["position_mm"]["max"] < 1e-4, m
        assert d["orientation_deg"]["max"] < 1e-3, m
    assert res["pose"]["pnp_average"]["n"] >= 1
    t = res["timing"]
    assert t["throughput_hz"] > 0 and t["latency_ms"]["p50"] > 0
    assert {"detector", "epnp_joint", "fusion"} <= set(t["per_node_ms"])
    assert {"detector", "epnp_joint", "fusion"} <= set(t["per_node_cpu_ms_per_frame"])
    report = (tmp_path / "report.md").read_text()
    assert report.count("| pnp_joint | 9 / 9 |") == 1 and "| refined | " in report.split("| method | NEES median")[-1]
    assert (tmp_path / "error_vs_distance.png").stat().st_size > 10_000
    assert any((tmp_path / "overlays").glob("*worst*.png"))


def test_oracle_with_noise_gives_errors_of_the_expected_size(small_dataset, tmp_path):
    res = run_eval(small_dataset, tmp_path, "--noise-px", "1.0", "--seed", "7", "--support-normal", "0,0,1",
                   "--refine-param", "one_camera=false")
    assert check_results(res) == []
    # the resting prior and the refine params reach the refine node; the prior is reported
    assert res["support_normal_world"] == [0.0, 0.0, 1.0]
    graph = yaml.safe_load((tmp_path / "graph.yaml").read_text())
    refine = next(n for n in graph["nodes"] if n["id"] == "refine")["params"]
    assert refine["support_normal_world"] == [0, 0, 1] and refine["one_camera"] is False
    assert refine["tracking"] is False          # views of a needle at rest: each on its own
    assert "resting prior" in (tmp_path / "report.md").read_text()
    with pytest.raises(SystemExit):
        eval_main(["--dataset", str(small_dataset), "--support-normal", "0,0"])
    # Gaussian noise of 1 px per coordinate: radial error of mean sqrt(pi/2) = 1.25 px
    k2 = res["keypoints_2d_px"]["all"]
    assert k2["n"] == 90
    assert 1.0 < k2["mean"] < 1.5 and 0.4 < k2["std"] < 0.9
    # a pixel of noise moves a triangulated point by millimetres at 10-25 cm with a 4 mm baseline
    assert 1.0 < res["keypoints_3d_mm"]["all"]["mean"] < 100.0
    # docs/geometry.md#pose-sensitivity: the joint stereo fit at 1 px averages a few mm
    joint = res["pose"]["pnp_joint"]
    assert joint["n"] == 9
    assert 0.3 < joint["position_mm"]["mean"] < 50.0 and 0.3 < joint["orientation_deg"]["mean"] < 90.0
    # triangulation may refuse frames (registration RMS above its bound): failures, counted
    tri = res["pose"]["triangulation"]
    assert tri["n"] + tri["failures"] == 9 and tri["failure_rate"] == tri["failures"] / 9


def test_broken_folder_fails_clearly(small_dataset, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(small_dataset, broken)
    lines = (broken / "frames.jsonl").read_text().splitlines()
    frame = json.loads(lines[4])
    frame["T_world_needle"] = [[1, 0, 0], [0, 1, 0]]
    lines[4] = json.dumps(frame)
    (broken / "frames.jsonl").write_text("\n".join(lines) + "\n")
    rc = eval_main(["--dataset", str(broken), "--detector", "oracle", "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "frames.jsonl:5" in err and "T_world_needle" in err
    assert not (tmp_path / "o" / "results.json").exists()


def test_folder_without_ground_truth_is_refused(small_dataset, tmp_path, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(small_dataset, bare)
    lines = [json.loads(l) for l in (bare / "frames.jsonl").read_text().splitlines()]
    for d in lines:
        for k in ("T_world_needle", "keypoints", "visible", "bbox"):
            d.pop(k, None)
    (bare / "frames.jsonl").write_text("".join(json.dumps(d) + "\n" for d in lines))
    rc = eval_main(["--dataset", str(bare), "--detector", "oracle", "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "frames.jsonl:1" in err and "T_world_needle: missing" in err


def test_bench_reports_throughput_latency_and_nodes(small_dataset, tmp_path, capsys):
    """``needletrack bench graph`` on the live graph: figures printed, none asserted on time."""
    out = tmp_path / "bench.json"
    rc = bench_main(["graph", "--dataset", str(small_dataset), "--detector", "oracle",
                     "--duration", "3", "--warmup", "1.5", "--json", str(out),
                     "--plot", str(tmp_path / "bench.png")])
    assert rc == 0
    assert (tmp_path / "bench.png").stat().st_size > 10_000
    r = json.loads(out.read_text())
    assert "latency_samples_ms" not in r
    assert r["published_hz"] > 0 and r["throughput_hz"] > 0      # rates are printed, not asserted
    assert r["latency_ms"]["p50"] > 0 and r["latency_ms"]["p99"] >= r["latency_ms"]["p50"]
    # the tracking graph: only the nodes on the path to the final pose
    assert set(r["per_node"]) == {"replay", "detector_left", "detector_right", "ecm", "refine", "fusion_refined"}
    assert r["stages"]["refined"]["rate_hz"] > 0 and r["frames_processed_hz"] > 0
    text = capsys.readouterr().out
    assert "end to end" in text and "latency" in text and "frames processed" in text and "refine" in text
