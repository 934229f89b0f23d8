"""``detections.jsonl``: what the detector found in each image of a user's files, one JSON object
a line (``needletrack detect``; its fields: docs/commands.md#needletrack-detect).

``DetectionRecord`` is the line, declared once; ``detection_record`` makes it from a backend's
``Keypoints`` message, ``unreadable_record`` for an image that could not be read, and
``read_detections`` reads a file back (each line checked against the record, a bad one named by
its line). Pixels as OpenCV's: (0, 0) the centre of the image's top-left pixel.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import msgspec
import numpy as np

from common.errors import NeedletrackError
from common.geometry.needle import KEYPOINT_NAMES


class DetectionsFileError(NeedletrackError, ValueError):
    """A detections.jsonl line that is not a ``DetectionRecord``; the text names file and line."""


class KeypointRecord(msgspec.Struct, forbid_unknown_fields=True):
    """One keypoint: ``u``, ``v`` pixels (null: a point the detector did not place), ``score`` in
    [0, 1] (the detector's own), ``on_arc`` true where the detector placed it on its fitted arc
    instead of seeing it itself (null: not stated), ``visible`` the probability that the point is
    seen, not inside tissue or behind an instrument (null: not stated; the score is capped at it)."""

    u: Optional[float]
    v: Optional[float]
    score: Optional[float]
    on_arc: Optional[bool] = None
    visible: Optional[float] = None


class DetectionRecord(msgspec.Struct, forbid_unknown_fields=True):
    """One image's detection. ``source``: the file; ``frame``: its index in a video or dataset
    folder (null: an image file); ``camera``: ``left``/``right`` for a stereo half or a dataset
    folder's camera (null: a single image); ``name``: the overlay's name (``overlays/NAME.png``);
    ``width``, ``height``: px (null when unreadable); ``found``: a needle stated; ``presence``:
    the detector's confidence in [0, 1] (also below the threshold when not found); ``keypoints``:
    A (the tip) .. E (the tail) when found, else null; ``end_identity``: the probability that A
    is the tip as said (0.5: the image cannot tell; null: not stated); ``unfamiliarity``: how
    unlike the detector's training images this one looks (about 1 familiar, larger less so;
    null: not stated); ``bbox``: [x0, y0, x1, y1] px; ``reason``: why no needle; ``error``: why
    the image could not be read (then ``found`` is false); ``detector``: the backend; ``ms``:
    the detection's time in milliseconds."""

    source: str
    frame: Optional[int]
    camera: Optional[str]
    name: str
    width: Optional[int]
    height: Optional[int]
    found: bool
    presence: float
    keypoints: Optional[dict[str, KeypointRecord]] = None
    end_identity: Optional[float] = None
    unfamiliarity: Optional[float] = None
    bbox: Optional[list[float]] = None
    reason: Optional[str] = None
    error: Optional[str] = None
    detector: str = ""
    ms: Optional[float] = None


def _num(x, digits: int) -> Optional[float]:
    return None if x is None or not np.isfinite(x) else round(float(x), digits)


def detection_record(kp, *, source: str, frame: Optional[int], camera: Optional[str], name: str,
                     size: tuple, ms: float) -> DetectionRecord:
    """The record of a ``Keypoints`` message ``kp`` of an image of ``size`` (width, height)."""
    keypoints = None
    if kp.found:
        on_arc = None if kp.on_arc is None else np.asarray(kp.on_arc, bool)
        seen = getattr(kp, "visibility", None)
        keypoints = {n: KeypointRecord(_num(uv[0], 3), _num(uv[1], 3), _num(s, 4),
                                       None if on_arc is None else bool(on_arc[k]),
                                       None if seen is None else _num(seen[k], 4))
                     for k, (n, uv, s) in enumerate(zip(KEYPOINT_NAMES, kp.uv, kp.scores, strict=True))}
    return DetectionRecord(
        source=str(source), frame=frame, camera=camera, name=name, width=int(size[0]), height=int(size[1]),
        found=bool(kp.found), presence=_num(kp.confidence, 4) or 0.0, keypoints=keypoints,
        end_identity=_num(kp.end_identity, 4), unfamiliarity=_num(kp.unfamiliarity, 3),
        bbox=None if kp.bbox is None or not kp.found else [_num(x, 2) for x in kp.bbox],
        reason=None if kp.found else kp.reason, detector=kp.detector, ms=round(float(ms), 2))


def unreadable_record(*, source: str, frame: Optional[int], camera: Optional[str], name: str,
                      error: str, detector: str = "") -> DetectionRecord:
    """The record of an image that could not be read: not found, ``error`` says why."""
    return DetectionRecord(source=str(source), frame=frame, camera=camera, name=name, width=None, height=None,
                           found=False, presence=0.0, error=error, detector=detector)


_ENCODER = msgspec.json.Encoder()
_DECODER = msgspec.json.Decoder(DetectionRecord)


def record_line(rec: DetectionRecord) -> bytes:
    """The record as one line of JSON, newline included."""
    return _ENCODER.encode(rec) + b"\n"


def read_detections(path) -> list[DetectionRecord]:
    """The records of a detections.jsonl file (``DetectionsFileError`` naming the bad line)."""
    out = []
    with open(Path(path), "rb") as f:
        for i, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                out.append(_DECODER.decode(line))
            except msgspec.DecodeError as exc:
                raise DetectionsFileError(f"{path}:{i}: not a detection record ({exc})") from None
    return out
