"""``results.json``: what ``needletrack eval`` writes (``build_results``), its checker
(``check_results``) and the JSON conversion of numpy values (``to_jsonable``)."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from common.evaluation.collect import Collected, Evaluation, evaluate, keypoint_table, pose_table
from common.evaluation.timing import timing_summary
from common.geometry.needle import KEYPOINT_NAMES
from common.methods import PAPER_POSE, REPORTED_METHODS



RESULT_KEYS = ("dataset", "frames", "detector", "detection_rate", "keypoints_2d_px",
               "keypoints_3d_mm", "pose", "timing")

PAPER = {
    "keypoints_2d_px": {"all": 5.58},
    "pose": PAPER_POSE,
    "rate_hz": 10.0,
}
"""The paper's figures: mean 2D keypoint error (px), Table III (mean mm, mean deg), speed."""



def build_results(col: Collected, *, dataset: str, detector: str, ev: Optional[Evaluation] = None,
                  extra: Optional[dict] = None) -> dict:
    """The ``results.json`` document: exactly RESULT_KEYS, plus informative keys beside them."""
    ev = ev if ev is not None else evaluate(col)
    kt = keypoint_table(ev)
    pt = pose_table(ev)
    res = {
        "dataset": str(dataset),
        "frames": int(ev.frames),
        "detector": str(detector),
        "detection_rate": (ev.detected / ev.images) if ev.images else None,
        "keypoints_2d_px": kt["keypoints_2d_px"],
        "keypoints_3d_mm": kt["keypoints_3d_mm"],
        "pose": pt,
        "timing": timing_summary(col),
        "correlation_2d_3d": kt["correlation_2d_3d"],
        "failure_rate": {m: v["failure_rate"] for m, v in pt.items()},
        "images": ev.images,
        "false_detections": ev.false_detections,
        "images_without_needle": ev.empty_images,
        "frames_with_truth": len(ev.T_true),
        "node_counters": {n: {k: v for k, v in c.items()
                              if isinstance(v, int) and not isinstance(v, bool) and k != "restarts"}
                          for n, c in sorted(col.node_counters.items())},
        "paper": {"keypoints_2d_px": PAPER["keypoints_2d_px"],
                  "pose": {m: {"position_mm": p, "orientation_deg": o}
                           for m, (p, o) in PAPER["pose"].items()},
                  "rate_hz": PAPER["rate_hz"]},
    }
    if extra:
        res.update(extra)
    return res


def check_results(res: dict) -> list[str]:
    """Problems with a ``results.json`` document's required keys and types (empty when fine)."""
    bad = []

    def num(x, where, optional=True):
        if x is None and optional:
            return
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            bad.append(f"{where}: expected a number, got {type(x).__name__}")

    for k in RESULT_KEYS:
        if k not in res:
            bad.append(f"{k}: missing")
    if bad:
        return bad
    if not isinstance(res["dataset"], str):
        bad.append("dataset: expected a string")
    if isinstance(res["frames"], bool) or not isinstance(res["frames"], int):
        bad.append("frames: expected an int")
    if not isinstance(res["detector"], str):
        bad.append("detector: expected a string")
    num(res["detection_rate"], "detection_rate")
    for key in ("keypoints_2d_px", "keypoints_3d_mm"):
        for name in (*KEYPOINT_NAMES, "all"):
            d = res[key].get(name)
            if not isinstance(d, dict):
                bad.append(f"{key}.{name}: missing")
                continue
            for f in ("mean", "std"):
                if f not in d:
                    bad.append(f"{key}.{name}.{f}: missing")
                num(d.get(f), f"{key}.{name}.{f}")
    for m in REPORTED_METHODS:
        d = res["pose"].get(m)
        if not isinstance(d, dict):
            bad.append(f"pose.{m}: missing")
            continue
        for q in ("position_mm", "orientation_deg"):
            for f in ("mean", "median", "std", "max"):
                if not isinstance(d.get(q), dict) or f not in d[q]:
                    bad.append(f"pose.{m}.{q}.{f}: missing")
                else:
                    num(d[q][f], f"pose.{m}.{q}.{f}")
        if isinstance(d.get("n"), bool) or not isinstance(d.get("n"), int):
            bad.append(f"pose.{m}.n: expected an int")
    t = res["timing"]
    if not isinstance(t, dict):
        return bad + ["timing: expected a map"]
    num(t.get("throughput_hz"), "timing.throughput_hz")
    if not isinstance(t.get("latency_ms"), dict):
        bad.append("timing.latency_ms: missing")
    else:
        for f in ("p50", "p99"):
            if f not in t["latency_ms"]:
                bad.append(f"timing.latency_ms.{f}: missing")
            num(t["latency_ms"].get(f), f"timing.latency_ms.{f}")
    if not isinstance(t.get("per_node_ms"), dict):
        bad.append("timing.per_node_ms: expected a map")
    else:
        for node, v in t["per_node_ms"].items():
            num(v, f"timing.per_node_ms.{node}", optional=False)
    return bad


def to_jsonable(obj):
    """Replace NaN/inf by None and numpy scalars by Python numbers (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj
