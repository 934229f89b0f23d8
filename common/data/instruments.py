"""The patient-side instruments of a dataset frame (``instruments`` in ``docs/dataset.md``).

``InstrumentPose``: one instrument's jaw frame ``T_world_jaw`` (4x4, m; origin at the jaws'
pivot, z along the closed jaws towards their tips, y the axis they open about), its opening
``jaw_rad`` (0 closed), both as the robot reports them, and, as optional ground truth,
``holds_needle`` and the true ``T_world_jaw_truth`` and ``jaw_rad_truth`` (absent: the reported
ones are exact). ``parse_instruments`` validates the frames.jsonl field (a ``BadValue`` names the
instrument and its field); ``T_jaw_needle`` is the grasp, constant while the jaws hold the needle
(in the true jaw frame; a reported one moves with the arm's kinematic error).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Optional

import numpy as np

from common.data.values import BadValue, parse_number, parse_rigid
from common.geometry.transforms import inv_T

NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,31}$")
"""An instrument's name: a word such as ``psm1``, ``psm2`` (1 to 32 characters)."""

MAX_JAW_RAD = math.pi
MAX_INSTRUMENTS = 8


@dataclass
class InstrumentPose:
    """One instrument in one frame (see the module docstring for the frame)."""

    T_world_jaw: np.ndarray
    jaw_rad: float
    holds_needle: Optional[bool] = None
    T_world_jaw_truth: Optional[np.ndarray] = None
    jaw_rad_truth: Optional[float] = None

    @property
    def T_world_jaw_true(self) -> np.ndarray:
        """The true jaw pose: ``T_world_jaw_truth`` where given, else the reported one (then exact)."""
        return self.T_world_jaw if self.T_world_jaw_truth is None else self.T_world_jaw_truth

    def to_json(self) -> dict:
        d = {"T_world_jaw": np.asarray(self.T_world_jaw, dtype=float).tolist(), "jaw_rad": float(self.jaw_rad)}
        if self.holds_needle is not None:
            d["holds_needle"] = bool(self.holds_needle)
        if self.T_world_jaw_truth is not None:
            d["T_world_jaw_truth"] = np.asarray(self.T_world_jaw_truth, dtype=float).tolist()
        if self.jaw_rad_truth is not None:
            d["jaw_rad_truth"] = float(self.jaw_rad_truth)
        return d


def parse_instrument(v) -> InstrumentPose:
    if not isinstance(v, dict):
        raise BadValue(f"expected a map with T_world_jaw and jaw_rad, got {type(v).__name__}")
    for k in ("T_world_jaw", "jaw_rad"):
        if v.get(k) is None:
            raise BadValue("required field missing", k)
    try:
        T = parse_rigid(v["T_world_jaw"])
    except BadValue as exc:
        raise BadValue(str(exc), "T_world_jaw") from None
    jaw = _opening(v["jaw_rad"], "jaw_rad")
    holds = v.get("holds_needle")
    if holds is not None and not isinstance(holds, bool):
        raise BadValue(f"expected true or false, got {holds!r}"[:120], "holds_needle")
    T_truth = None
    if v.get("T_world_jaw_truth") is not None:
        try:
            T_truth = parse_rigid(v["T_world_jaw_truth"])
        except BadValue as exc:
            raise BadValue(str(exc), "T_world_jaw_truth") from None
    jaw_truth = None if v.get("jaw_rad_truth") is None else _opening(v["jaw_rad_truth"], "jaw_rad_truth")
    return InstrumentPose(T, jaw, holds, T_truth, jaw_truth)


def _opening(value, field: str) -> float:
    try:
        jaw = parse_number(value)
    except BadValue as exc:
        raise BadValue(str(exc), field) from None
    if not 0.0 <= jaw <= MAX_JAW_RAD:
        raise BadValue(f"must be an opening angle in [0, pi] rad, got {jaw:g}", field)
    return jaw


def parse_instruments(v) -> dict:
    """``{name: InstrumentPose}`` from the frames.jsonl ``instruments`` value."""
    if not isinstance(v, dict):
        raise BadValue(f"expected a map {{NAME: {{T_world_jaw, jaw_rad}}}}, got {type(v).__name__}")
    if len(v) > MAX_INSTRUMENTS:
        raise BadValue(f"{len(v)} instruments, more than the {MAX_INSTRUMENTS} a frame may list")
    out = {}
    for name, entry in v.items():
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise BadValue("not an instrument name (a letter, then letters, digits, _ or -)", repr(str(name)[:40]))
        try:
            out[name] = parse_instrument(entry)
        except BadValue as exc:
            raise BadValue(str(exc), name if exc.sub is None else f"{name}.{exc.sub}") from None
    return out


def instruments_json(instruments: Optional[dict]) -> Optional[dict]:
    """The frames.jsonl value of ``{name: InstrumentPose}`` (None stays None)."""
    if instruments is None:
        return None
    return {name: p.to_json() for name, p in instruments.items()}


def holder(instruments: Optional[dict]) -> Optional[str]:
    """The name of the instrument marked as holding the needle (the first, by name), or None."""
    for name in sorted(instruments or {}):
        if instruments[name].holds_needle:
            return name
    return None


def T_jaw_needle(inst: InstrumentPose, T_world_needle: np.ndarray, truth: bool = False) -> np.ndarray:
    """The needle's pose in the reported jaw frame (``truth``: in the true one, constant while the
    jaws hold it; the reported one carries the arm's error)."""
    T_world_jaw = inst.T_world_jaw_true if truth else inst.T_world_jaw
    return inv_T(np.asarray(T_world_jaw, float)) @ np.asarray(T_world_needle, float)

