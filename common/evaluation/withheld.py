"""The frames whose one camera was withheld (``needletrack eval --withhold``): the tracked pose
there, against the frames both cameras saw (docs/tracking.md#one-camera).

The withheld frames are the replay's (``common.data.withhold.withheld_frames``, the same share
and seed); each method's errors come from the run's ``per_frame.csv`` (empty: not posed), split
by the share of the arc seen as the moving takes' evaluation splits them
(``common.evaluation.moving``: from ``SEEN`` in both cameras' truth).
"""
from __future__ import annotations

import csv
import math
from pathlib import Path


from common.data.withhold import withheld_frames
from common.evaluation.moving import SEEN, error_summary, stereo_visible


def withheld_summary(ds, per_frame: Path, share: float, seed: int = 0, methods=("tracked",)) -> dict:
    """``{method: {"withheld": {...}, "seen": {...}}}``: for the withheld frames and the others, each
    where at least ``SEEN`` of the arc is seen and where less: frames, posed share, position (mm)
    and orientation (deg) summaries, NEES median."""
    mask = withheld_frames([f.sequence for f in ds.frames], share, seed)
    withheld = {f.index for f, m in zip(ds.frames, mask) if m}
    seen = {f.index: stereo_visible(f) for f in ds.frames}
    with open(per_frame) as fh:
        rows = {int(r["seq"]): r for r in csv.DictReader(fh)}
    out = {}
    for m in methods:
        out[m] = {}
        for part, sel in (("withheld", lambda s: s in withheld), ("both_cameras", lambda s: s not in withheld)):
            for where, ok in ((f">= {SEEN:.0%}", lambda v: v is not None and v >= SEEN),
                              (f"< {SEEN:.0%}", lambda v: v is not None and v < SEEN)):
                seqs = [s for s in rows if sel(s) and ok(seen.get(s))]
                out[m][f"{part}, {where} seen"] = _summary([rows[s] for s in seqs], m)
    return out


def _float(text: str) -> float:
    return float(text) if text not in ("", None) else float("nan")


def _summary(rows: list, method: str) -> dict:
    return error_summary([[_float(r.get(f"{method}_mm")) / 1e3, math.radians(_float(r.get(f"{method}_deg"))),
                           _float(r.get(f"{method}_nees"))] for r in rows])


def withheld_markdown(table: dict) -> list[str]:
    """The table as Markdown lines."""
    lines = ["| method | frames | n | posed | mm mean / median | deg mean / median | NEES median |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for m, parts in table.items():
        for name, s in parts.items():
            posed = "n/a" if s["posed_share"] is None else f"{s['posed_share']:.0%}"
            nees = "n/a" if s["nees_median"] is None else f"{s['nees_median']:.1f}"
            lines.append(f"| {m} | {name} | {s['n']} | {posed} | {_pair(s['position_mm'])} | "
                         f"{_pair(s['orientation_deg'])} | {nees} |")
    return lines


def _pair(s: dict) -> str:
    return "n/a" if s.get("mean") is None else f"{s['mean']:.2f} / {s['median']:.2f}"
