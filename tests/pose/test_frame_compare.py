"""tests/pose/frame_compare.py, the before/after comparison: it finds a changed field of one
message (naming the ordering, node, output, seq and field), lists a field that only the second
tree's messages carry without counting it, and compares two eval folders cell by cell."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import msgpack
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import frame_compare  # noqa: E402

from common.runtime.messages import PoseEstimate, decode, encode  # noqa: E402

DATA = Path(__file__).parent / "data"


def recorded() -> dict:
    return msgpack.unpackb((DATA / "frames_outputs.msgpack").read_bytes(), raw=False, strict_map_key=False)


def first_pose(outputs: dict) -> tuple[int, PoseEstimate]:
    i = next(i for i, (o, _) in enumerate(outputs["prompt"]["refine"]["out"]) if o == "pose")
    return i, decode(outputs["prompt"]["refine"]["out"][i][1], PoseEstimate)


def test_the_same_outputs_compare_equal():
    n, bad, added = frame_compare.message_differences(recorded(), recorded())
    assert n > 100 and bad == [] and added == {}


def test_a_changed_field_is_named_with_its_node_and_frame():
    a, b = recorded(), recorded()
    i, pose = first_pose(b)
    T = np.array(pose.T_ecm_needle, float)
    T[0, 3] = np.nextafter(T[0, 3], np.inf)          # one bit of one element
    pose.T_ecm_needle = T
    b["prompt"]["refine"]["out"][i] = ["pose", encode(pose)]
    _, bad, _ = frame_compare.message_differences(a, b)
    assert bad == [f"prompt refine pose seq {pose.seq} T_ecm_needle"]


def test_a_field_only_the_second_tree_has_is_listed_not_counted():
    a, b = recorded(), recorded()
    i, _ = first_pose(b)
    raw = msgpack.unpackb(b["prompt"]["refine"]["out"][i][1], raw=False, strict_map_key=False)
    raw["body"]["new_field"] = 3
    b["prompt"]["refine"]["out"][i] = ["pose", msgpack.packb(raw)]
    _, bad, added = frame_compare.message_differences(a, b)
    assert bad == [] and added == {"needletrack.PoseEstimate.new_field": {"3": 1}}
    _, bad, _ = frame_compare.message_differences(b, a)                   # missing from the second: a difference
    assert len(bad) == 1 and bad[0].endswith("new_field")


def test_counters_and_missing_outputs_differ():
    a, b = recorded(), recorded()
    b["late"]["tracker"]["counters"]["late_pose"] = 1
    b["mid"]["fusion"]["out"].pop()
    _, bad, _ = frame_compare.message_differences(a, b)
    assert any(x.startswith("late tracker counters") for x in bad)
    assert any(x.startswith("mid fusion: outputs") for x in bad)


def test_eval_folders_compare_cell_by_cell_less_timing(tmp_path):
    for name, mm, hz in (("a", "0.1234", 10.0), ("b", "0.1235", 12.0)):
        d = tmp_path / name
        d.mkdir()
        (d / "per_frame.csv").write_text(f"seq,sequence,refined_mm\n0,0,0.5\n1,0,{mm}\n")
        (d / "results.json").write_text(json.dumps({"timing": {"throughput_hz": hz}, "frames": 2,
                                                     "dataset": str(d)}))
    bad = frame_compare.eval_differences(tmp_path / "a", tmp_path / "b")
    assert bad == ["per_frame.csv seq 1 refined_mm: 0.1234 != 0.1235"]
    (tmp_path / "b" / "results.json").write_text(json.dumps({"timing": {}, "frames": 3}))
    assert frame_compare.eval_differences(tmp_path / "a", tmp_path / "b")[1:] == ["results.json .frames"]


def test_eval_recordings_compare_by_frame_less_the_clock(tmp_path):
    lines = {"a": [{"kind": "pose", "seq": 3, "stamp_ns": 1, "epoch": 7, "residual": 0.25},
                   {"kind": "end", "frames": 4}],
             "b": [{"kind": "pose", "seq": 3, "stamp_ns": 2, "epoch": 8, "residual": 0.25, "new": True},
                   {"kind": "end", "frames": 4}]}
    for name, recs in lines.items():
        (tmp_path / name / "rec").mkdir(parents=True)
        (tmp_path / name / "rec" / "refined.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
        (tmp_path / name / "per_frame.csv").write_text("seq,refined_mm\n3,0.1\n")
        (tmp_path / name / "results.json").write_text("{}")
    assert frame_compare.eval_differences(tmp_path / "a", tmp_path / "b") == []
    lines["b"][0]["residual"] = 0.5
    (tmp_path / "b" / "rec" / "refined.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines["b"]))
    assert frame_compare.eval_differences(tmp_path / "a", tmp_path / "b") == ["rec/refined.jsonl pose seq 3: residual"]
