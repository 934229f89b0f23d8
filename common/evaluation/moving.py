"""The evaluation of moving takes (docs/tracking.md#evaluation): per-frame pose error by the share
of the arc seen, and the needle in the jaws (``InHandPose``) against the true grasp.

The share of the arc seen in a stereo frame is the smaller of the two cameras' (``arc_visible``,
else the share of visible keypoints: ``common.evaluation.metrics.visible_fraction``): a frame
counts as seen from ``SEEN`` (30%) when both cameras see that much. The in-hand pose is scored
from the ``IN_HAND_FROM``-th frame (10th) of each run of frames one instrument holds the needle
(the truth's ``holds_needle``), against ``inv(T_world_jaw) @ T_world_needle`` in the true jaw frame
(``T_world_jaw_truth`` where the arm reports its jaws with an error); a frame where the
tracker names no holder, or another, counts as ``wrong_holder``. A method's lag behind the truth:
the shift in frames that brings its world poses nearest the truth (``lag_frames``). Each arm's
estimated error (the tracker's ``ArmCorrection``, with ``arm_correction``): its corrected jaw pose
against the true jaws from ``CORRECTION_AFTER`` frames (3 s at 30 Hz) after that arm is first seen
holding the needle in the take, beside the arm's report against the same truth
(``correction_table``).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from common.evaluation.metrics import SWAP_DEG, VISIBLE_BINS, summary, visible_fraction
from common.frames import CAMERAS
from common.geometry.transforms import inv_T, pose_delta, pose_error

SEEN = 0.3
IN_HAND_FROM = 10
CORRECTION_AFTER = 90
"""Frames (3 s at 30 Hz) after an arm first holds the needle from which its correction is scored."""


def stereo_visible(frame) -> Optional[float]:
    """The smaller of the cameras' shares of the arc seen (None: the frame does not say)."""
    shares = [visible_fraction(frame, c) for c in CAMERAS]
    return None if any(s is None for s in shares) else float(min(shares))


def moving_seqs(truths: dict) -> list:
    """The frames of takes whose needle moves (``needle_at_rest`` false), in ``seq`` order."""
    return sorted(s for s, gt in truths.items() if gt.needle_at_rest is False)


def method_errors(table: dict, seqs) -> dict:
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


def error_summary(e) -> dict:
    """Frames' errors, rows of (position m, orientation rad, NEES), NaN where the frame was not
    posed (NEES NaN: no covariance), summarised: frames, posed, mm and deg, NEES median."""
    e = np.asarray(e, float).reshape(-1, 3)
    posed = np.isfinite(e[:, 0])
    nees = e[posed, 2][np.isfinite(e[posed, 2])]
    return {"n": len(e), "posed": int(posed.sum()), "posed_share": float(posed.mean()) if len(e) else None,
            "position_mm": summary(e[posed, 0] * 1e3), "orientation_deg": summary(np.degrees(e[posed, 1])),
            "nees_median": float(np.median(nees)) if len(nees) else None}


def _summary(errors: dict, seqs) -> dict:
    return error_summary([errors[s] for s in seqs])


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
        T_true = inv_T(np.asarray(instruments[s][holder].T_world_jaw_true, float)) @ np.asarray(truths[s].T_world_needle, float)
        dt, dr = pose_error(np.asarray(est.T_jaw_needle, float), T_true)
        pos.append(dt)
        rot.append(dr)
    return {"frames": scored, "posed": len(pos), "wrong_holder": wrong,
            "position_mm": summary(np.array(pos) * 1e3), "orientation_deg": summary(np.degrees(rot))}


def correction_table(truths: dict, instruments: dict, corrections: dict, seqs) -> dict:
    """The corrected jaw poses (``ArmCorrection.T_world_jaw``) and the reports against the true jaws
    (``InstrumentState.T_world_jaw_true``), per arm and frame from ``CORRECTION_AFTER`` frames after
    the arm first holds the needle in its take (the truth's ``holds_needle``): position (mm),
    orientation (deg), the share within 1 mm and 1 deg, the NEES of the stated covariance; frames
    with no correction said are counted ``missing``."""
    first: dict = {}
    for s in sorted(seqs):
        for name, m in instruments.get(s, {}).items():
            if m.holds_needle:
                first.setdefault((truths[s].sequence, name), s)
    est, reported, nees, missing = [], [], [], 0
    for s in sorted(seqs):
        for name, m in instruments.get(s, {}).items():
            f = first.get((truths[s].sequence, name))
            if f is None or s - f < CORRECTION_AFTER:
                continue
            T_true = np.asarray(m.T_world_jaw_true, float)
            reported.append(pose_error(np.asarray(m.T_world_jaw, float), T_true))
            c = corrections.get(s, {}).get(name)
            if c is None:
                missing += 1
                continue
            T = np.asarray(c.T_world_jaw, float)
            est.append(pose_error(T, T_true))
            r = pose_delta(T_true, T)
            nees.append(float(r @ np.linalg.solve(np.asarray(c.covariance, float), r)))

    def table(errs):
        e = np.array(errs, float).reshape(-1, 2)
        within = (e[:, 0] <= 1e-3) & (e[:, 1] <= np.radians(1.0))
        return {"n": len(e), "position_mm": summary(e[:, 0] * 1e3), "orientation_deg": summary(np.degrees(e[:, 1])),
                "within_1mm_1deg": float(within.mean()) if len(e) else None}
    return {"from_frame": CORRECTION_AFTER, "missing": missing, "corrected": {**table(est), "nees_median":
            float(np.median(nees)) if nees else None}, "reported": table(reported)}


def holder_events(truths: dict, instruments: dict, seqs) -> list:
    """``(seq, kind)`` of each change of the needle's holder within a take, per the truth: kind
    ``grasp`` (none to one), ``handover`` (one to another), ``release`` (one to none)."""
    out, prev = [], None
    for s in seqs:
        holder = next((n for n, m in sorted(instruments.get(s, {}).items()) if m.holds_needle), None)
        here = (truths[s].sequence, holder)
        if prev is not None and prev[0] == here[0] and prev[1] != holder:
            out.append((s, "grasp" if prev[1] is None else "release" if holder is None else "handover"))
        prev = here
    return out


def identity_through(events: list, errors: dict, seqs, window: int = 15) -> dict:
    """Whether a method keeps the tip through each holder event: of the ``window`` frames before
    and after it (same take), the last posed one before is not turned end for end (orientation
    error under ``SWAP_DEG``) and no posed one after is: ``kept``; right before and turned
    after: ``lost``; else (not posed, or turned before) ``unscored``. Per kind and in all."""
    order = sorted(seqs)
    at = {s: i for i, s in enumerate(order)}
    out = {k: {"kept": 0, "lost": 0, "unscored": 0} for k in ("grasp", "handover", "release", "all")}

    def turned(s):
        e = errors.get(s)
        return None if e is None or not np.isfinite(e[1]) else bool(np.degrees(e[1]) > SWAP_DEG)

    for s, kind in events:
        i = at[s]
        before = [turned(q) for q in order[max(0, i - window):i]]
        after = [turned(q) for q in order[i:i + window]]
        before, after = [t for t in before if t is not None], [t for t in after if t is not None]
        verdict = "unscored" if not before or not after or before[-1] else "lost" if any(after) else "kept"
        out[kind][verdict] += 1
        out["all"][verdict] += 1
    return out


def lag_frames(poses: dict, truths: dict, seqs, max_lag: int = 8) -> Optional[int]:
    """How many frames a method's world poses lag the truth: the shift ``k`` (0..``max_lag``)
    that makes the pose of frame ``s`` nearest (mean distance) to the truth of frame ``s - k`` of
    the same take, over frames where the needle moves (the truth moved since the frame before).
    None: nothing to compare."""
    moving = [s for s in seqs if s - 1 in truths and truths[s - 1].sequence == truths[s].sequence
              and np.linalg.norm(truths[s].T_world_needle[:3, 3] - truths[s - 1].T_world_needle[:3, 3]) > 1e-5]
    best, best_err = None, np.inf
    for k in range(max_lag + 1):
        d = [np.linalg.norm(np.asarray(poses[s].T_world_needle)[:3, 3] - truths[s - k].T_world_needle[:3, 3])
             for s in moving if s in poses and poses[s].T_world_needle is not None and s - k in truths
             and truths[s - k].sequence == truths[s].sequence]
        if d and np.mean(d) < best_err:
            best, best_err = k, float(np.mean(d))
    return best


def moving_summary(ev, truths: dict, instruments: dict, in_hand: dict, visible: dict, methods,
                   poses: Optional[dict] = None, corrections: Optional[dict] = None) -> Optional[dict]:
    """The ``moving`` section of results.json (None: no moving frame). ``ev``: the run's
    ``Evaluation``; ``instruments``: {seq: {name: InstrumentState}}; ``in_hand``: {seq:
    InHandPose}; ``visible``: {seq: share of the arc seen}; ``methods``: those to score;
    ``poses``: {method: {seq: PoseEstimate}}, for each method's lag behind the truth (``lag_ms``:
    ``lag_frames`` at 30 Hz); ``corrections``: {seq: {name: ArmCorrection}} (``correction_table``)."""
    seqs = set(moving_seqs(truths))
    if not seqs:
        return None
    out = {"frames": len(seqs), "seen_from": SEEN, "methods": {}}
    for m in methods:
        if m not in ev.pose:
            continue
        errors = method_errors(ev.pose[m], seqs)
        seen = [s for s in errors if visible.get(s) is not None and visible[s] >= SEEN]
        out["methods"][m] = {"all": _summary(errors, list(errors)), "seen": _summary(errors, seen),
                             "by_visible": by_visible(errors, visible)}
        if instruments:
            out["methods"][m]["identity"] = identity_through(holder_events(truths, instruments, sorted(seqs)),
                                                             errors, seqs)
        lag = lag_frames((poses or {}).get(m, {}), truths, sorted(seqs))
        if lag is not None:                  # frames of the take's 30 Hz: 1000 / 30 ms each
            out["methods"][m]["lag_ms"] = lag * 1e3 / 30.0
    if instruments:
        out["in_hand"] = in_hand_table(truths, instruments, in_hand, sorted(seqs))
    if instruments and corrections:
        out["arm_correction"] = correction_table(truths, instruments, corrections, seqs)
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
    lags = {m: d["lag_ms"] for m, d in moving["methods"].items() if d.get("lag_ms") is not None}
    if lags:
        L += ["", "Lag behind the truth (the shift that brings the poses nearest it, in 30 Hz frames): " +
              ", ".join(f"{m} {v:.0f} ms" for m, v in lags.items()) + "."]
    ids = {m: d["identity"] for m, d in moving["methods"].items() if d.get("identity")}
    if ids:
        L += ["", "The tip through each change of holder (grasp, handover, release; the 15 frames before and "
              "after): kept / lost / not scored: " + ", ".join(
                  f"{m} {d['all']['kept']} / {d['all']['lost']} / {d['all']['unscored']}"
                  f" (handovers {d['handover']['kept']} / {d['handover']['lost']} / {d['handover']['unscored']})"
                  for m, d in ids.items()) + "."]
    h = moving.get("in_hand")
    if h:
        L += ["", f"The needle in the jaws (`T_jaw_needle`, from the {IN_HAND_FROM}th held frame on): "
              f"{h['posed']} of {h['frames']} frames scored, {h['wrong_holder']} with no or another holder; "
              f"{_fmt(h['position_mm']['mean'])} mm / {_fmt(h['orientation_deg']['mean'])} deg mean, "
              f"{_fmt(h['position_mm']['median'])} mm / {_fmt(h['orientation_deg']['median'])} deg median."]
    c = moving.get("arm_correction")
    if c:
        est, rep = c["corrected"], c["reported"]
        within = "n/a" if est["within_1mm_1deg"] is None else f"{100 * est['within_1mm_1deg']:.0f}%"
        L += ["", f"Each arm's estimated error (the corrected jaws against the true ones, from {c['from_frame']} "
              f"frames after the arm first holds the needle): {est['n']} frames ({c['missing']} without a "
              f"correction), {_fmt(est['position_mm']['mean'])} mm / {_fmt(est['orientation_deg']['mean'])} deg "
              f"mean, {within} within 1 mm and 1 deg, NEES median {_fmt(est['nees_median'])}; the reports: "
              f"{_fmt(rep['position_mm']['mean'])} mm / {_fmt(rep['orientation_deg']['mean'])} deg mean."]
    return L + [""]


def shown_take(truths: dict) -> list:
    """The seqs of the take the figures show (``tracking.png``, ``tracking.mp4``): the longest
    moving one (the first of equals), in order; empty without a moving take."""
    takes: dict = {}
    for s in moving_seqs(truths):
        takes.setdefault(truths[s].sequence, []).append(s)
    return max(takes.values(), key=len) if takes else []


def plot_take(ev, truths: dict, visible: dict, path, methods=("refined", "tracked")) -> bool:
    """One take's figure: each method's position and orientation error over its frames, and the
    share of the arc seen. The take: ``shown_take``. False (nothing drawn) without one."""
    take = shown_take(truths)
    if not take:
        return False
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from common.methods import METHOD_COLOURS
    fig, (a_pos, a_rot) = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    x = np.arange(len(take)) / 30.0
    for m in methods:
        if m not in ev.pose:
            continue
        e = method_errors(ev.pose[m], set(take))
        pos = np.array([e.get(s, (np.nan,) * 3)[0] for s in take]) * 1e3
        rot = np.degrees([e.get(s, (np.nan,) * 3)[1] for s in take])
        a_pos.plot(x, pos, ".-", ms=3, lw=1, color=METHOD_COLOURS.get(m), label=m)
        a_rot.plot(x, rot, ".-", ms=3, lw=1, color=METHOD_COLOURS.get(m), label=m)
    for ax in (a_pos, a_rot):
        share = ax.twinx()
        share.fill_between(x, [visible.get(s) or 0.0 for s in take], color="grey", alpha=0.15, step="mid")
        share.axhline(SEEN, color="grey", lw=0.8, ls=":")
        share.set_ylim(0, 1)
        share.set_ylabel("share of the arc seen", fontsize=8)
        ax.grid(alpha=0.3)
    a_pos.set_ylabel("position error (mm)")
    a_rot.set_ylabel("orientation error (deg)")
    a_rot.set_xlabel("time in the take (s, at 30 Hz)")
    a_pos.legend(fontsize=8, loc="upper left")
    a_pos.set_title(f"take {truths[take[0]].sequence}: errors (a gap: not posed) and the arc seen (grey)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
