"""The evaluation of moving takes (docs/tracking.md#evaluation): per-frame pose error by the share
of the arc seen, and the needle in the jaws (``InHandPose``) against the true grasp.

The share of the arc seen in a stereo frame is the smaller of the two cameras' (``arc_visible``,
else the share of visible keypoints: ``common.evaluation.metrics.visible_fraction``): a frame
counts as seen from ``SEEN`` (30%) when both cameras see that much. The in-hand pose is scored
from the ``IN_HAND_FROM``-th frame (10th) of each run of frames one instrument holds the needle
(the truth's ``holds_needle``), against ``inv(T_world_jaw) @ T_world_needle``; a frame where the
tracker names no holder, or another, counts as ``wrong_holder``.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from common.evaluation.metrics import VISIBLE_BINS, summary, visible_fraction
from common.frames import CAMERAS
from common.geometry.transforms import inv_T, pose_error

SEEN = 0.3
IN_HAND_FROM = 10


def stereo_visible(frame) -> Optional[float]:
    """The smaller of the cameras' shares of the arc seen (None: the frame does not say)."""
    shares = [visible_fraction(frame, c) for c in CAMERAS]
    return None if any(s is None for s in shares) else float(min(shares))


def moving_seqs(truths: dict) -> list:
    """The frames of takes whose needle moves (``needle_at_rest`` false), in ``seq`` order."""
    return sorted(s for s, gt in truths.items() if gt.needle_at_rest is False)


def _errors(table: dict, seqs) -> dict:
    """{seq: (position m, orientation rad, nees)} of a method's error table (NaN: not posed)."""
    return {s: (p, o, n) for s, p, o, n in zip(table["seqs"], table["position_m"], table["orientation_rad"],
                                              table["nees"]) if s in seqs}


def by_visible(errors: dict, visible: dict) -> list:
    """Rows per bin of the visible share (``metrics.VISIBLE_BINS``): frames, posed, errors (mm, deg)."""
    rows = []
    for lo, hi in zip(VISIBLE_BINS[:-1], VISIBLE_BINS[1:]):
        sel = [s for s in errors if visible.get(s) is not None and lo <= visible[s] < hi]
        rows.append({"from": lo, "to": min(hi, 1.0), **_summary(errors, sel)})
    return rows


def _summary(errors: dict, seqs) -> dict:
    e = np.array([errors[s] for s in seqs], float).reshape(-1, 3)
    posed = np.isfinite(e[:, 0])
    nees = e[posed, 2][np.isfinite(e[posed, 2])]
    return {"n": len(seqs), "posed": int(posed.sum()), "posed_share": float(posed.mean()) if len(seqs) else None,
            "position_mm": summary(e[posed, 0] * 1e3), "orientation_deg": summary(np.degrees(e[posed, 1])),
            "nees_median": float(np.median(nees)) if len(nees) else None}


def held_runs(truths: dict, instruments: dict, seqs) -> dict:
    """{seq: (holder, index of the frame in its run of frames held by that holder)} per the truth."""
    out, run, prev = {}, 0, (None, None)
    for s in seqs:
        gt = truths[s]
        holder = next((n for n, m in sorted(instruments.get(s, {}).items()) if m.holds_needle), None)
        key = (gt.sequence, holder)
        run = run + 1 if key == prev and holder is not None else 0
        prev = key
        if holder is not None:
            out[s] = (holder, run)
    return out


def in_hand_table(truths: dict, instruments: dict, in_hand: dict, seqs) -> dict:
    """The published ``T_jaw_needle`` against the true grasp, from the ``IN_HAND_FROM``-th held frame."""
    pos, rot, wrong, scored = [], [], 0, 0
    for s, (holder, k) in held_runs(truths, instruments, seqs).items():
        if k < IN_HAND_FROM - 1:
            continue
        scored += 1
        est = in_hand.get(s)
        if est is None or est.name != holder:
            wrong += 1
            continue
        T_true = inv_T(np.asarray(instruments[s][holder].T_world_jaw, float)) @ np.asarray(truths[s].T_world_needle, float)
        dt, dr = pose_error(np.asarray(est.T_jaw_needle, float), T_true)
        pos.append(dt)
        rot.append(dr)
    return {"frames": scored, "posed": len(pos), "wrong_holder": wrong,
            "position_mm": summary(np.array(pos) * 1e3), "orientation_deg": summary(np.degrees(rot))}


def moving_summary(ev, truths: dict, instruments: dict, in_hand: dict, visible: dict, methods) -> Optional[dict]:
    """The ``moving`` section of results.json (None: no moving frame). ``ev``: the run's
    ``Evaluation``; ``instruments``: {seq: {name: InstrumentState}}; ``in_hand``: {seq:
    InHandPose}; ``visible``: {seq: share of the arc seen}; ``methods``: those to score."""
    seqs = set(moving_seqs(truths))
    if not seqs:
        return None
    out = {"frames": len(seqs), "seen_from": SEEN, "methods": {}}
    for m in methods:
        if m not in ev.pose:
            continue
        errors = _errors(ev.pose[m], seqs)
        seen = [s for s in errors if visible.get(s) is not None and visible[s] >= SEEN]
        out["methods"][m] = {"all": _summary(errors, list(errors)), "seen": _summary(errors, seen),
                             "by_visible": by_visible(errors, visible)}
    if instruments:
        out["in_hand"] = in_hand_table(truths, instruments, in_hand, sorted(seqs))
    return out


def _fmt(x, nd=2) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"


def moving_markdown(moving: dict) -> list:
    """report.md's lines for the ``moving`` section of results.json."""
    L = ["## Moving takes", "",
         f"{moving['frames']} frames whose needle moves. Error by the share of the arc seen (the "
         f"smaller of the two cameras'); 'seen': frames with at least {100 * moving['seen_from']:.0f}% seen.", "",
         "| method | frames | share of the arc | posed | position mean (mm) | median | orientation mean (deg) "
         "| median | NEES median |", "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for m, d in moving["methods"].items():
        rows = [("all", d["all"]), (f">= {100 * moving['seen_from']:.0f}%", d["seen"])] + \
               [(f"{100 * r['from']:.0f}-{100 * r['to']:.0f}%", r) for r in d["by_visible"]]
        for label, r in rows:
            L.append(f"| {m} | {r['n']} | {label} | {_fmt(None if r['posed_share'] is None else 100 * r['posed_share'], 0)}% "
                     f"| {_fmt(r['position_mm']['mean'])} | {_fmt(r['position_mm']['median'])} "
                     f"| {_fmt(r['orientation_deg']['mean'])} | {_fmt(r['orientation_deg']['median'])} "
                     f"| {_fmt(r['nees_median'])} |")
    h = moving.get("in_hand")
    if h:
        L += ["", f"The needle in the jaws (`T_jaw_needle`, from the {IN_HAND_FROM}th held frame on): "
              f"{h['posed']} of {h['frames']} frames scored, {h['wrong_holder']} with no or another holder; "
              f"{_fmt(h['position_mm']['mean'])} mm / {_fmt(h['orientation_deg']['mean'])} deg mean, "
              f"{_fmt(h['position_mm']['median'])} mm / {_fmt(h['orientation_deg']['median'])} deg median."]
    return L + [""]
