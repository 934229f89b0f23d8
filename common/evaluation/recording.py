"""The ``recorder`` node's file read back: each frame's refined pose and detections.

The recorder (nodes/recorder.py) writes one JSON line per message of a pipeline run
(``needletrack adapt``'s runs, ``needletrack eval --record``) and an ``end`` line when the run is
over. ``read_recording`` reads it per frame; a file without its ``end`` line is an unfinished run.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.errors import NeedletrackError


class RecordingError(NeedletrackError, RuntimeError):
    """A pipeline run that left no complete recording."""


@dataclass
class FrameOutputs:
    """What the pipeline gave for one frame ``seq``: the refined ``pose`` (a dict of
    ``PoseEstimate`` fields, arrays as numpy; None: no pose), ``one_camera`` (a pose fitted to
    one camera's view, the same way; None: none) and each camera's detection (dicts of
    ``Keypoints`` fields)."""

    seq: int
    pose: dict | None = None
    one_camera: dict | None = None
    keypoints: dict = field(default_factory=dict)


def recording_complete(path) -> bool:
    """Whether the file ends with the recorder's ``end`` line."""
    path = Path(path)
    if not path.is_file() or path.stat().st_size == 0:
        return False
    with open(path, "rb") as f:
        f.seek(max(0, path.stat().st_size - 200))
        tail = f.read().decode("utf-8", "replace").strip().splitlines()
    try:
        return bool(tail) and json.loads(tail[-1]).get("kind") == "end"
    except json.JSONDecodeError:
        return False


def _array(v):
    return None if v is None else np.array(v, dtype=float)


def read_recording(path) -> dict:
    """``{seq: FrameOutputs}`` from a recorder file; raises RecordingError when it is unfinished."""
    if not recording_complete(path):
        raise RecordingError(f"{path}: no end line: the pipeline run did not finish")
    out: dict = {}
    with open(path, encoding="utf-8") as f:
        for ln, line in enumerate(f, 1):
            try:
                rec = json.loads(line)
            except json.JSONDecodeError as exc:
                raise RecordingError(f"{path}:{ln}: not valid JSON: {exc}") from None
            kind = rec.pop("kind", None)
            if kind == "end":
                break
            seq = int(rec["seq"])
            fo = out.setdefault(seq, FrameOutputs(seq))
            for k in ("T_ecm_needle", "T_world_needle", "T_world_ecm", "covariance", "uv", "scores",
                      "centreline"):
                if k in rec:
                    rec[k] = _array(rec[k])
            if kind == "pose":
                fo.pose = rec
            elif kind == "one_camera":
                fo.one_camera = rec
            elif kind == "keypoints":
                fo.keypoints[rec["camera"]] = rec
    return out
