"""What people look at after an evaluation: ``report.md``, ``error_vs_distance.png``,
``nees.png``, ``overlays/``, ``per_frame.csv`` and ``results.json``, written from a
``common.evaluation.collect.Collected``; for moving takes also ``tracking.png`` and ``tracking.mp4``.

No process, no network. The overlays are drawn in ``common/evaluation/overlays.py``, the
video in ``common/evaluation/take_video.py``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from common.evaluation.collect import Collected, Evaluation, evaluate
from common.evaluation.metrics import NEES_99PCT
from common.evaluation.moving import moving_markdown, moving_summary, plot_take
from common.evaluation.overlays import write_overlays
from common.evaluation.results import PAPER, build_results, check_results, to_jsonable
from common.geometry.needle import KEYPOINT_NAMES, NeedleModel
from common.methods import METHOD_COLOURS


def _fmt(x, nd=2) -> str:
    return "—" if x is None else f"{x:.{nd}f}"


# ---------------------------------------------------------------- report.md

def _sure(d: dict) -> str:
    s = d.get("sure")
    if not s:
        return "—"
    return f"{s['n']}, {_fmt(s['position_mm']['mean'])} / {_fmt(s['orientation_deg']['mean'])}"


def _swaps(d: dict) -> str:
    sw = d.get("end_for_end")
    if not sw:
        return "—"
    return f"{100 * sw['share']:.0f}% ({100 * sw['confident_share']:.0f}%)"


def _tip(d: dict) -> str:
    """Turned end for end: the share the poses' stated end identity gives, and the share measured."""
    e = d.get("end_identity")
    if not e:
        return "—"
    return "; ".join(f"{part} {100 * v['stated']:.1f}% / {100 * v['measured']:.1f}%" for part, v in e.items())


def end_identity_section(res: dict) -> list[str]:
    """Which end is the tip, per method that states it: confident swaps, undecided tips, the
    errors modulo the turn, sure and right, and the reliability table of the stated probability."""
    rows = [(m, d) for m, d in res["pose"].items() if d.get("reliability")]
    if not rows:
        return []
    L = ["", "Which end is the tip (docs/evaluation.md#end-identity-of-the-poses): confident swaps "
         "(turned, stated sure or not flagged), undecided tips (flagged below a 0.95 tip "
         "probability; of them turned), orientation modulo the turn (an undecided pose against "
         "the nearer of its two readings), sure and right (frames posed unflagged within 2 mm / "
         "5 deg, of all frames):", "",
         "| method | confident swaps | undecided (turned) | modulo the turn: mm / deg mean (median) "
         "| sure and right |", "| --- | ---: | ---: | ---: | ---: |"]
    for m, d in rows:
        u, mt = d["undecided"], d["modulo_turn"]
        L.append(f"| {m} | {d['confident_swaps']} | {_fmt(100 * u['share'], 1)}% ({u['turned']}) "
                 f"| {_fmt(mt['position_mm']['mean'])} / {_fmt(mt['orientation_deg']['mean'])} "
                 f"({_fmt(mt['position_mm']['median'])} / {_fmt(mt['orientation_deg']['median'])}) "
                 f"| {_fmt(100 * d['sure_and_right'], 1) if d.get('sure_and_right') is not None else '—'}% |")
    L += ["", "Reliability of the stated tip probability p (turned: stated 1 - p against measured; "
          "within the bound: measured at most 1.5 x stated + 2 points):", "",
          "| method | p | n | turned: stated | measured | within |", "| --- | --- | ---: | ---: | ---: | --- |"]
    for m, d in rows:
        for r in d["reliability"]:
            L.append(f"| {m} | {r['p_from']:.2f}-{r['p_to']:.2f} | {r['n']} | {_fmt(100 * r['stated'], 1)}% "
                     f"| {_fmt(100 * r['measured'], 1)}% | {'yes' if r['within_bound'] else '**no**'} |")
    return L


def report_markdown(res: dict) -> str:
    """Table II (keypoints) and Table III (poses) beside the paper's figures, with medians."""
    L = ["# needletrack evaluation", "",
         f"- dataset: `{res['dataset']}`",
         f"- frames: {res['frames']} stereo frames ({res.get('images', 2 * res['frames'])} images)",
         f"- detector: `{res['detector']}`" + (f" (noise {res['noise_px']} px)"
                                               if res.get("noise_px") else ""),
         *([f"- refinement's resting prior: support surface normal {res['support_normal_world']} "
            "(world frame)"] if res.get("support_normal_world") else []),
         f"- needle found in {_fmt(100 * res['detection_rate'] if res['detection_rate'] is not None else None, 1)}% "
         f"of the images; false detections: {res.get('false_detections', 0)} "
         f"of {res.get('images_without_needle', 0)} images without a needle", ""]

    L += ["## Table II: keypoint errors", "",
          "2D: pixel distance between detected and true keypoints over both cameras (points the "
          "truth marks visible). 3D: distance between the triangulated and the true keypoint. "
          "Correlation: Pearson, over frames, between a keypoint's 2D error (mean of the two "
          "cameras) and its 3D error.", "",
          "| keypoint | 2D mean (px) | 2D std | 2D median | 3D mean (mm) | 3D std | 3D median "
          "| 2D-3D corr. | paper 2D mean (px) |",
          "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    paper2d = PAPER["keypoints_2d_px"]
    for name in (*KEYPOINT_NAMES, "all"):
        k2, k3 = res["keypoints_2d_px"][name], res["keypoints_3d_mm"][name]
        c = res.get("correlation_2d_3d", {}).get(name)
        L.append(f"| {name} | {_fmt(k2['mean'])} | {_fmt(k2['std'])} | {_fmt(k2.get('median'))} "
                 f"| {_fmt(k3['mean'])} | {_fmt(k3['std'])} | {_fmt(k3.get('median'))} "
                 f"| {_fmt(c)} | {_fmt(paper2d.get(name))} |")
    L += ["", "The paper reports only the overall mean 2D error (5.58 px, Keypoint R-CNN at "
          "1920x1080).", ""]

    L += ["## Table III: pose errors", "",
          "Position: distance between estimated and true needle origins. Orientation: angle of "
          "R_est^T R_true. Single-frame methods are scored on every frame, multi-view ones on the "
          "last endoscope step of every sequence; a frame without a pose is a failure.", "",
          "| method | n / counted | failures | position mean (mm) | median | std | max "
          "| orientation mean (deg) | median | std | max | paper (mm / deg) |",
          "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for m, d in res["pose"].items():
        p, o = d["position_mm"], d["orientation_deg"]
        paper = PAPER["pose"].get(m)
        fr = d.get("failure_rate")
        L.append(f"| {m} | {d['n']} / {d.get('expected', d['n'])} | "
                 f"{_fmt(100 * fr if fr is not None else None, 1)}% "
                 f"| {_fmt(p['mean'])} | {_fmt(p['median'])} | {_fmt(p['std'])} | {_fmt(p['max'])} "
                 f"| {_fmt(o['mean'])} | {_fmt(o['median'])} | {_fmt(o['std'])} | {_fmt(o['max'])} "
                 f"| {f'{paper[0]:.2f} / {paper[1]:.2f}' if paper else '—'} |")
    honest = [(m, d) for m, d in res["pose"].items() if d.get("nees")]
    if honest:
        L += ["", "Stated covariances against the errors (NEES: the squared error in the covariance's "
              "metric; chi-square(6) has median 5.35 and exceeds 16.8 in 1% of the frames):", "",
              "| method | NEES median | share over 16.8 | ambiguous "
              "| turned end for end (not flagged, or sure of the tip) "
              "| turned: stated / measured | not flagged: n, mm / deg mean |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
        L += [f"| {m} | {_fmt(d['nees']['median'], 1)} | {_fmt(100 * d['nees']['over_99pct'], 0)}% "
              f"| {_fmt(100 * d['ambiguous_share'], 0) + '%' if d.get('ambiguous_share') is not None else '—'} "
              f"| {_swaps(d)} | {_tip(d)} | {_sure(d)} |"
              for m, d in honest]
        L += end_identity_section(res)
        L += ["", "![NEES against chi-square(6)](nees.png)"]
    L += ["", "![error vs distance](error_vs_distance.png)", ""]

    t = res["timing"]
    L += ["## Speed", "",
          f"- end to end: {_fmt(t['throughput_hz'], 1)} frames/s "
          f"(final output `{t.get('final_method')}`; the paper: {PAPER['rate_hz']:.0f} Hz on an RTX 3080)",
          f"- latency from frame publish to pose: p50 {_fmt(t['latency_ms']['p50'], 1)} ms, "
          f"p99 {_fmt(t['latency_ms']['p99'], 1)} ms (at the replay's pace, every input queued: "
          f"`needletrack bench` measures the live graph's speed)",
          "- per node: CPU time per frame over the run, and the median handler time over every "
          "message it handled (calibration and ECM poses included):", ""]
    if t["per_node_ms"]:
        cpu = t.get("per_node_cpu_ms_per_frame") or {}
        L += ["| node | CPU ms / frame | handler p50 ms |", "| --- | ---: | ---: |"]
        L += [f"| {n} | {_fmt(cpu.get(n))} | {_fmt(v)} |" for n, v in t["per_node_ms"].items()]
    else:
        L.append("(no node statistics received)")
    why = {n: {k: v for k, v in c.items() if not k.startswith(("in.", "out."))}
           for n, c in res.get("node_counters", {}).items()}
    why = {n: c for n, c in why.items() if any(c.values())}
    if why:
        L += ["", "## Why frames gave no pose (node counters)", "",
              "| node | counter | count |", "| --- | --- | ---: |"]
        L += [f"| {n} | {k} | {v} |" for n, c in why.items() for k, v in sorted(c.items()) if v]
    if res.get("moving"):
        L += [""] + moving_markdown(res["moving"])
    L += ["", "Overlays of chosen frames, worst cases included, are in `overlays/`.", ""]
    return "\n".join(L)


# ---------------------------------------------------------------- Fig. 8

def plot_error_vs_distance(ev: Evaluation, path, bins: int = 6) -> None:
    """Position (mm) and orientation (deg) error against camera distance (cm), one series per
    method: the paper's Fig. 8. Each frame is a dot; the line is the median per distance bin;
    frames without a pose are crosses on the x axis. The y axis is logarithmic when the errors
    span more than two decades."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    all_d = np.concatenate([t["distance_m"] for t in ev.pose.values()] or [np.zeros(0)]) * 100
    edges = np.linspace(all_d.min(), all_d.max(), bins + 1) if all_d.size else np.zeros(0)
    for ax_i, (ax, unit) in enumerate(((axes[0], "position error (mm)"), (axes[1], "orientation error (deg)"))):
        vals_all = []
        for m, t in ev.pose.items():
            d = t["distance_m"] * 100
            vals = t["position_m"] * 1e3 if ax_i == 0 else np.degrees(t["orientation_rad"])
            colour = METHOD_COLOURS.get(m)
            ok = np.isfinite(vals)
            vals_all.append(vals[ok])
            ax.scatter(d[ok], vals[ok], s=9, alpha=0.35, color=colour, linewidths=0)
            if edges.size and ok.any():
                idx = np.clip(np.digitize(d[ok], edges) - 1, 0, bins - 1)
                centres, meds = [], []
                for b in range(bins):
                    sel = vals[ok][idx == b]
                    if sel.size:
                        centres.append((edges[b] + edges[b + 1]) / 2)
                        meds.append(np.median(sel))
                ax.plot(centres, meds, "o-", ms=4, lw=1.6, color=colour,
                        label=f"{m} (n={int(ok.sum())}/{len(ok)})")
            if (~ok).any():
                ax.plot(d[~ok], np.zeros((~ok).sum()), "x", color=colour, ms=7, clip_on=False,
                        transform=ax.get_xaxis_transform())
        v = np.concatenate(vals_all) if vals_all else np.zeros(0)
        v = v[v > 0]
        if v.size and v.max() / max(v.min(), 1e-12) > 100 and v.min() > 1e-6:
            ax.set_yscale("log")
        else:
            ax.set_ylim(bottom=0)
        ax.set_xlabel("camera distance (cm)")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=8)
    fig.suptitle("Pose error vs camera distance: dots per frame, lines the median per distance bin, "
                 "x: no pose", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def chi2_6_cdf(x):
    """CDF of chi-square with 6 degrees of freedom (closed form for even dof)."""
    h = np.minimum(np.maximum(np.asarray(x, float), 0.0), 1e3) / 2.0    # 1 beyond (and at inf)
    return 1.0 - np.exp(-h) * (1.0 + h + h * h / 2.0)


def plot_nees(ev: Evaluation, path) -> bool:
    """How honest each method's stated covariance is: the share of frames whose NEES is below x
    against chi-square(6)'s (what an honest 6-dof covariance gives). A curve to the right of it
    is over-confident, to the left under-confident. False (nothing drawn) when no method states
    covariances."""
    series = {m: np.sort(t["nees"][np.isfinite(t["nees"])]) for m, t in ev.pose.items()}
    series = {m: v for m, v in series.items() if v.size}
    if not series:
        return False
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    lo = min(max(float(v[0]), 1e-3) for v in series.values())
    hi = max(float(v[-1]) for v in series.values())
    x = np.geomspace(min(lo, 0.1), max(hi, 100.0), 400)
    ax.plot(x, chi2_6_cdf(x), "k--", lw=1.5, label="chi-square(6): honest")
    for m, v in series.items():
        ax.step(np.maximum(v, x[0]), np.arange(1, v.size + 1) / v.size, where="post",
                color=METHOD_COLOURS.get(m), lw=1.6, label=f"{m} (median {np.median(v):.1f}, n={v.size})")
    ax.axvline(NEES_99PCT, color="grey", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_ylim(0, 1)
    ax.set_xlabel("NEES (squared pose error in the stated covariance's metric); dotted: 99% bound")
    ax.set_ylabel("share of frames below")
    ax.set_title("Stated covariance vs actual error: right of the dashed curve = over-confident",
                 fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


# ---------------------------------------------------------------- per frame

def write_per_frame_csv(path, col: Collected, ev: Evaluation) -> None:
    """One row per frame: seq, sequence, step, camera distance (mm), the keypoints' mean 2D
    (px) and 3D (mm) errors, and each method's position (mm) and orientation (deg) errors:
    empty where the method is not scored on that frame, ``nan`` where it gave no pose; for the
    methods that flag poses also the flag (1/0), the NEES and the stated end identity; for those
    whose poses state it, the share of the arc seen (``arc_seen``)."""
    import csv
    idx = {m: {s: i for i, s in enumerate(t["seqs"])} for m, t in ev.pose.items()}
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        flags = [m for m, t in ev.pose.items() if np.isfinite(t["ambiguous"]).any()]
        seen = [m for m in ev.pose if any(p.arc_seen is not None for p in col.poses.get(m, {}).values())]
        w.writerow(["seq", "sequence", "step", "distance_mm", "kp2d_px", "kp3d_mm"]
                   + [f"{m}_{q}" for m in ev.pose for q in ("mm", "deg")]
                   + [f"{m}_{q}" for m in flags for q in ("ambiguous", "nees", "end_identity")]
                   + [f"{m}_arc_seen" for m in seen])
        for s in ev.seqs:
            gt = col.truths[s]
            T = ev.T_true.get(s)
            with np.errstate(invalid="ignore"):
                e2 = np.nanmean(ev.err2d_px[s]) if np.isfinite(ev.err2d_px[s]).any() else np.nan
                e3 = (np.nanmean(ev.err3d_m[s]) * 1e3 if s in ev.err3d_m
                      and np.isfinite(ev.err3d_m[s]).any() else np.nan)
            row = [s, "" if gt.sequence is None else gt.sequence, "" if gt.step is None else gt.step,
                   "" if T is None else f"{np.linalg.norm(T[:3, 3]) * 1e3:.2f}", f"{e2:.4f}", f"{e3:.4f}"]
            for m, t in ev.pose.items():
                i = idx[m].get(s)
                if i is None:
                    row += ["", ""]
                else:
                    row += [f"{t['position_m'][i] * 1e3:.4f}", f"{np.degrees(t['orientation_rad'][i]):.4f}"]
            for m in flags:
                t, i = ev.pose[m], idx[m].get(s)
                row += ["", "", ""] if i is None else [
                    "" if not np.isfinite(t["ambiguous"][i]) else int(t["ambiguous"][i]),
                    f"{t['nees'][i]:.3f}", f"{t['end_identity'][i]:.4f}"]
            for m in seen:
                p = col.poses[m].get(s)
                row.append("" if p is None or p.arc_seen is None else f"{p.arc_seen:.3f}")
            w.writerow(row)


# ---------------------------------------------------------------- everything

def write_outputs(outdir, col: Collected, *, dataset: str, detector: str,
                  load_images: Optional[Callable[[int], dict]] = None,
                  extra: Optional[dict] = None, methods: Optional[list] = None,
                  visible: Optional[dict] = None) -> dict:
    """Write results.json, report.md, error_vs_distance.png, nees.png (when a method states
    covariances), tracking.png and tracking.mp4 (moving takes: ``moving.plot_take``,
    ``take_video.write_take_video``) and overlays/ into ``outdir``;
    returns the results document. ``load_images`` as in ``write_overlays`` (None: black);
    ``methods`` as in ``evaluate``; ``visible``: {seq: share of the arc seen} for the moving
    takes' figures (``common.evaluation.moving``; key ``moving``, when the run has moving frames)."""
    from common.geometry.camera import StereoRig

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    ev = evaluate(col, methods)
    res = to_jsonable(build_results(col, dataset=dataset, detector=detector, ev=ev, extra=extra))
    moving = moving_summary(ev, col.truths, col.instruments, col.in_hand, visible or {}, list(ev.pose), col.poses,
                            col.arm_corrections)
    if moving is not None:
        res["moving"] = to_jsonable(moving)
    problems = check_results(res)
    if problems:  # a bug here, not bad input: say so rather than write a broken file
        raise AssertionError("results.json would break its contract: " + "; ".join(problems))
    rig = StereoRig.from_dict(col.calib.cameras, col.calib.image_size) if col.calib is not None else StereoRig.default()
    needle = NeedleModel.from_dict(col.calib.needle) if col.calib is not None else NeedleModel()
    overlays = write_overlays(outdir, col, ev, rig, needle, load_images or (lambda seq: {}))
    res["overlays"] = overlays
    tmp = outdir / "results.json.tmp"
    tmp.write_text(json.dumps(res, indent=2, allow_nan=False) + "\n")
    os.replace(tmp, outdir / "results.json")
    (outdir / "report.md").write_text(report_markdown(res))
    plot_error_vs_distance(ev, outdir / "error_vs_distance.png")
    if not plot_nees(ev, outdir / "nees.png"):
        (outdir / "nees.png").unlink(missing_ok=True)     # a stale one from an earlier run
    write_per_frame_csv(outdir / "per_frame.csv", col, ev)
    if not (moving is not None and plot_take(ev, col.truths, visible or {}, outdir / "tracking.png")):
        (outdir / "tracking.png").unlink(missing_ok=True)     # a stale one from an earlier run
    (outdir / "tracking.mp4").unlink(missing_ok=True)
    if moving is not None:        # last: every other output is written when it cannot be
        from common.evaluation.take_video import write_take_video
        from common.geometry.ecm_kinematics import EcmArm
        write_take_video(outdir / "tracking.mp4", col, ev, rig, needle, load_images, visible,
                         EcmArm.from_calibration(col.calib.ecm) if col.calib is not None else None)
    return res
