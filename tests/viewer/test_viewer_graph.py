"""The viewer node in a launched graph, looked at in headless Chromium.

sim (640x360 JPEG) -> oracle detector -> epnp joint -> viewer (page + Rerun recording). The
browser's screenshot of the viewer's page must show the endoscope image (a scene, not a flat
fill) and the drawn needle (the final method's colour, which the raw camera image lacks).
The screenshot is also written to docs/viewer.png when NEEDLETRACK_DOCS_SHOT=1.
"""
import json
import os
import shutil
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.runtime.messages import CameraImage
from common.viewer.browser import find_chromium, screenshot
from common.viewer.draw import method_bgr

REPO = Path(__file__).resolve().parents[2]
FINAL = "pnp_joint"


def _graph(port, grpc_port, rrd):
    cam = {"left": "camera/left", "right": "camera/right", "truth": "camera/truth", "calib": "camera/calib"}
    return {"nodes": [
        {"id": "camera", "module": "sim", "outputs": ["left", "right", "joints", "truth", "calib"],
         "params": {"width": 640, "height": 360, "rate_hz": 10, "motion": "sweep", "randomise": "none",
                    "encoding": "jpeg"}},
        {"id": "detector", "module": "detector", "params": {"backend": "oracle", "noise_px": 0.0},
         "inputs": cam, "outputs": ["left", "right"]},
        {"id": "epnp_joint", "module": "epnp", "params": {"method": "joint"},
         "inputs": {"left": "detector/left", "right": "detector/right", "calib": "camera/calib"},
         "outputs": ["pose"]},
        {"id": "viewer", "module": "viewer",
         "params": {"port": port, "grpc_port": grpc_port, "web_port": 0, "save": str(rrd), "rate_hz": 5},
         "inputs": {**cam, "keypoints_left": "detector/left", "keypoints_right": "detector/right",
                    FINAL: "epnp_joint/pose"}},
    ]}


def _near(rgb, colour_bgr, tol=40):
    target = np.array(colour_bgr[::-1], int)
    return int((np.abs(rgb.astype(int) - target).max(axis=2) <= tol).sum())


@pytest.mark.browser
def test_viewer_page_shows_the_image_and_the_needle_in_a_browser(run_graph, free_port, tmp_path):
    # not optional: .ci/run installs both
    assert find_chromium() is not None, "needs Debian's chromium: apt-get install -y chromium"
    import rerun  # noqa: F401  (the viewer extra: pip install -e '.[viewer]')
    from graphtools import free_port as another_port
    rrd = tmp_path / "session.rrd"
    g = run_graph(_graph(free_port, another_port(), rrd), timeout=90)
    raw = g.collect("camera/left", 1, timeout=60, expect=CameraImage)[0].to_bgr()
    g.wait_stats("viewer", lambda st: st.counters.get("frames_drawn", 0) >= 5, timeout=90)
    url = f"http://127.0.0.1:{free_port}/"
    g.wait_log(f"viewer: {url}")
    # a pose meets its frame's truth as both arrive: wait for the first error on the page
    deadline = time.monotonic() + 90
    while True:
        state = json.load(urllib.request.urlopen(url + "state.json", timeout=10))
        row = state["methods"].get(FINAL) or {}
        if row.get("pos_err_mm") is not None or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert row.get("pos_err_mm") is not None and row["pos_err_mm"] < 0.5      # the oracle without noise: exact
    assert row["rate_hz"] > 0 and row["latency_ms"] > 0

    shot = tmp_path / "viewer.png"
    screenshot(url, shot, wait_s=4.0, size=(1300, 700))
    rgb = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB)
    if os.environ.get("NEEDLETRACK_DOCS_SHOT") == "1":
        shutil.copy(shot, REPO / "docs" / "viewer.png")
    # the two camera pictures sit in the top rows, side by side; at 1300 px each is ~640 wide
    top = rgb[30:360]
    left_half = top[:, :640]
    assert left_half.std() > 15, "no endoscope image on the page"
    # the scene's own colours: the image is textured, not one flat fill
    assert len(np.unique(left_half.reshape(-1, 3) // 16, axis=0)) > 30
    overlay = _near(top, method_bgr(FINAL))
    background = _near(cv2.cvtColor(raw, cv2.COLOR_BGR2RGB), method_bgr(FINAL))
    assert overlay > 150 and overlay > 5 * background, (overlay, background)
    # the numbers table lists the method
    assert g.stats("viewer").counters.get("handler_errors", 0) == 0
    g.stop()
    assert rrd.stat().st_size > 10_000
    from rerun.chunk import RrdReader
    paths = {str(c.entity_path) for c in RrdReader(rrd).stream()}
    for p in ("/world/ecm/left/image", f"/world/ecm/needle/{FINAL}", "/world/ecm/needle/truth",
              f"/plots/pos_err_mm/{FINAL}"):
        assert p in paths, (p, sorted(paths))


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from common.cli import dataset_main
    ds = tmp_path_factory.mktemp("viewer") / "ds"
    assert dataset_main(["generate", "--out", str(ds), "--sequences", "2", "--steps", "3", "--width", "480",
                         "--height", "270", "--seed", "3", "--randomise", "none", "--jobs", "1", "--quiet"]) == 0
    return ds


@pytest.mark.graph
def test_eval_rrd_records_every_frame_with_poses_and_errors(tiny_dataset, tmp_path):
    """``needletrack eval --rrd``: a frame-by-frame recording of an evaluation."""
    from common.evaluation.cli import main as eval_main
    ds = tiny_dataset
    rrd = tmp_path / "eval.rrd"
    assert eval_main(["--dataset", str(ds), "--detector", "oracle", "--out", str(tmp_path / "out"), "--quiet",
                      "--timeout", "150", "--no-refine", "--rrd", str(rrd)]) == 0
    from rerun.chunk import RrdReader
    rows: dict = {}
    for c in RrdReader(rrd).stream():
        if not c.is_static:
            rows[str(c.entity_path)] = rows.get(str(c.entity_path), 0) + c.num_rows
    assert rows.get("/world/ecm/left/image") == 6 and rows.get("/world/ecm/right/image") == 6
    assert rows.get("/world/ecm/needle/truth") == 6 and rows.get("/world/ecm/needle/pnp_joint") == 6
    assert rows.get("/plots/pos_err_mm/pnp_joint") == 6 and rows.get("/world/ecm") == 6


@pytest.mark.graph
def test_bench_viewer_prints_what_the_viewer_costs(tiny_dataset, tmp_path, capsys):
    """``needletrack bench --viewer`` runs (its figures are printed, not asserted)."""
    from common.bench.graph_bench import main as bench_main
    out = tmp_path / "bench.json"
    assert bench_main(["graph", "--dataset", str(tiny_dataset), "--detector", "oracle", "--rate", "10",
                       "--duration", "3", "--warmup", "1", "--no-refine", "--viewer",
                       "--viewer-param", "rate_hz=10", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "the viewer's cost (pictures 960x540 at 10 Hz)" in text and "viewer CPU" in text
    r = json.loads(out.read_text())
    assert "viewer" in r["with_viewer"]["per_node"] and "viewer" not in r["per_node"]


def test_screenshot_reads_the_viewers_url_and_the_monitors_line():
    """``needletrack screenshot``'s reading of the launcher's output, and its refusals."""
    import io

    from common.viewer.shot import LaunchOutput, final_posed
    sink = io.StringIO()
    out = LaunchOutput(sink, "viewer", {"monitor"})
    out.write("[viewer] INFO up\n[other] viewer: http://127.0.0.1:1/\n")
    assert out.url is None and not out.url_seen.is_set()
    out.write("[viewer] viewer: http://127.0.0.1:9091/\n[monitor] seq    42 6/6 tracked  t=[1 2 3]mm\n")
    assert out.url == "http://127.0.0.1:9091/" and out.url_seen.is_set()
    assert out.monitor_line == "seq    42 6/6 tracked  t=[1 2 3]mm" and "[viewer] INFO up" in sink.getvalue()
    assert final_posed({"final": "tracked", "methods": {"tracked": {"pos_err_mm": 0.2}}})
    assert not final_posed({"final": "tracked", "methods": {"tracked": {"pos_err_mm": None}}})
    assert not final_posed({})


def test_screenshot_refuses_a_graph_without_a_viewer(tmp_path, capsys):
    from common.viewer.shot import main as shot_main
    g = tmp_path / "g.yaml"
    g.write_text("graph: g\nnodes:\n  - {id: a, module: counter}\n")
    if find_chromium() is None:
        assert shot_main([str(g), "--out", str(tmp_path / "x.png")]) == 2
        assert "apt-get install -y chromium" in capsys.readouterr().err
        return
    assert shot_main([str(g), "--out", str(tmp_path / "x.png")]) == 2
    assert "no viewer node" in capsys.readouterr().err and not (tmp_path / "x.png").exists()


@pytest.mark.browser
def test_needletrack_screenshot_launches_a_graph_and_shoots_its_page(free_port, tmp_path):
    """The command that makes docs/launch.png, on a small graph: the PNG shows the final
    method's arc, and the graph is stopped afterwards."""
    assert find_chromium() is not None, "needs Debian's chromium: apt-get install -y chromium"
    from graphtools import cli, prepare_graph
    from graphtools import free_port as another_port
    graph = _graph(free_port, another_port(), tmp_path / "s.rrd")
    graph["nodes"][-1]["params"].pop("save")
    path = prepare_graph(graph, tmp_path)          # a free Zenoh port, a unique graph name
    out = tmp_path / "shot.png"
    res = cli("screenshot", path, "--out", out, "--size", "1300x700", "--settle", "2", "--timeout", "120",
              timeout=240)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert "final: pnp_joint" in res.stdout and "[launcher] stopped" in res.stdout
    rgb = cv2.cvtColor(cv2.imread(str(out)), cv2.COLOR_BGR2RGB)
    assert rgb.shape == (700, 1300, 3) and _near(rgb[30:360], method_bgr(FINAL)) > 150
