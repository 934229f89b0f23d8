"""The evaluator and monitor nodes with no process: messages in, files and lines out."""
import io
import json
import time

import numpy as np

from common.messages import EndOfStream
from nodes.evaluator import EvaluatorNode
from nodes.monitor import MonitorNode, format_line
from test_evaluation import synthetic


def feed(node, col, methods):
    node.on_calib(col.calib)
    for seq, gt in sorted(col.truths.items()):
        node.on_truth(gt)
        for cam in ("left", "right"):
            if hasattr(node, "on_left") and (cam, seq) in col.keypoints:
                getattr(node, f"on_{cam}")(col.keypoints[(cam, seq)])
        if hasattr(node, "on_points3d") and seq in col.points3d:
            node.on_points3d(col.points3d[seq])
        for m in methods:
            if seq in col.poses.get(m, {}):
                getattr(node, f"on_{m}")(col.poses[m][seq])


def test_evaluator_writes_once_everything_arrived(tmp_path):
    col = synthetic(n_seq=3, steps=3, px_noise=0.5)
    methods = ["pnp_average", "pnp_joint", "triangulation", "multiview"]
    node = EvaluatorNode.offline(params={"out": str(tmp_path / "out"), "detector": "oracle",
                                         "drain_s": 30},
                                 wired=["truth", "left", "right", "points3d", "calib", "eos", *methods])
    feed(node, col, methods)
    assert node.step() is True          # no EndOfStream yet
    node.on_eos(EndOfStream(9, 0))
    assert node.step() is False         # complete: no need to wait for the drain timeout
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    assert res["frames"] == 9 and res["detector"] == "oracle"
    assert res["pose"]["pnp_joint"]["n"] == 9 and res["pose"]["multiview"]["n"] == 3
    assert abs(res["keypoints_2d_px"]["all"]["mean"] - 0.5) < 1e-9
    assert (tmp_path / "out" / "report.md").exists()


def test_evaluator_drains_then_counts_missing_poses_as_failures(tmp_path):
    col = synthetic(n_seq=2, steps=2, drop={("pnp_joint", 1)})
    methods = ["pnp_joint", "multiview"]
    node = EvaluatorNode.offline(params={"out": str(tmp_path), "drain_s": 0.2},
                                 wired=["truth", "left", "right", "calib", "eos", *methods])
    feed(node, col, methods)
    node.on_eos(EndOfStream(4, 0))
    assert node.step() is True          # pnp_joint of frame 1 may still come
    t0 = time.monotonic()
    while node.step():
        assert time.monotonic() - t0 < 5
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["pose"]["pnp_joint"]["n"] == 3 and res["pose"]["pnp_joint"]["failures"] == 1
    assert res["pose"]["pnp_average"]["n"] == 0   # not wired: reported, all failures
    assert res["graph_methods"] == methods


def test_monitor_prints_pose_and_error():
    col = synthetic(n_seq=1, steps=3, pos_err=0.002, ang_err=np.radians(3.0))
    methods = ["pnp_joint", "multiview"]
    node = MonitorNode.offline(params={"every_s": 0}, wired=["truth", "calib", *methods])
    node.out = io.StringIO()
    feed(node, col, methods)
    lines = node.out.getvalue().splitlines()
    assert len(lines) == 3
    assert lines[0].startswith("seq     0 | pnp_joint t=[")
    assert "err 2.00mm 3.0deg" in lines[0] and "err 1.00mm 1.5deg" in lines[0]
    assert "views 3" in lines[2]


def test_monitor_line_without_truth_or_pose():
    col = synthetic(n_seq=1, steps=1)
    line = format_line(0, {"pnp_joint": col.poses["pnp_joint"][0]}, None, ["pnp_joint", "refined"])
    assert "err" not in line and "refined no pose" in line and "mm r=[" in line
