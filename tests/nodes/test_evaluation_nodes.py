"""The evaluator and monitor nodes with no process: messages in, files and lines out."""
import io
import json
import time

import numpy as np
from test_evaluation import synthetic

from common.geometry.transforms import rotvec_to_R
from common.runtime.messages import EndOfStream
from nodes.evaluator import EvaluatorNode
from nodes.monitor import WIDTH, MonitorNode, format_lines


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


def test_monitor_prints_the_final_pose_and_error_in_one_short_line():
    col = synthetic(n_seq=1, steps=3, pos_err=0.002, ang_err=np.radians(3.0))
    methods = ["pnp_joint", "multiview"]
    node = MonitorNode.offline(params={"every_s": 0}, wired=["truth", "calib", *methods])
    node.out = io.StringIO()
    feed(node, col, methods)
    lines = node.out.getvalue().splitlines()
    assert len(lines) == 3
    # multiview leads (it comes before pnp_joint in FINAL_ORDER); the other is only counted
    assert lines[0].startswith("seq     0 2/2 multiview t=[")
    assert "err 1.00mm 1.5deg" in lines[0] and "pnp_joint" not in lines[0]
    assert "views 3" in lines[2]


def test_monitor_all_methods_and_the_width_of_the_longest_line():
    col = synthetic(n_seq=1, steps=3, pos_err=0.002, ang_err=np.radians(3.0))
    methods = ["pnp_joint", "multiview"]
    node = MonitorNode.offline(params={"every_s": 0, "all_methods": True}, wired=["truth", "calib", *methods])
    node.out = io.StringIO()
    feed(node, col, methods)
    lines = node.out.getvalue().splitlines()
    assert len(lines) == 6 and lines[1].lstrip().startswith("pnp_joint t=[") and "err 2.00mm 3.0deg" in lines[1]
    # the widest a pose in the working volume prints: every field at its longest, ambiguous, fused
    worst = col.poses["pnp_joint"][0]
    worst.T_ecm_needle = np.eye(4)
    worst.T_ecm_needle[:3, 3] = [-0.1999, -0.1999, -0.9999]
    worst.T_ecm_needle[:3, :3] = rotvec_to_R(np.radians([-100.0, -100.0, -101.0]))
    worst.ambiguous, worst.n_views, worst.end_identity = True, 10, 0.5
    T_true = np.eye(4)
    T_true[:3, 3] = [-0.19, -0.19, -0.93]
    methods = ["refined", "multiview_refined"]
    lines = format_lines(99999, {m: worst for m in methods}, T_true, methods, all_methods=True)
    for line in lines:
        assert len(line) <= WIDTH and not line.endswith("..."), (len(line), line)
    assert "r=[-100.0 -100.0 -101.0]deg" in lines[1] and "tip 0.50 views 10" in lines[1]
    worst.end_identity = 0.99                       # ambiguous for another reason (a mirror image)
    assert "ambiguous views 10" in format_lines(1, {"refined": worst}, None, ["refined"])[0]


def test_monitor_line_without_truth_or_pose():
    col = synthetic(n_seq=1, steps=1)
    lines = format_lines(0, {"pnp_joint": col.poses["pnp_joint"][0]}, None, ["refined", "pnp_joint"], True)
    assert lines[0] == "seq     0 1/2 refined  no pose" and "err" not in lines[1]
    assert "mm r=[" in lines[1]
