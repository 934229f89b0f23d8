"""The hand-label learning curve: what 10, 30 and 100 labelled stereo frames buy on a look.

``models/learning_curve.sh LOOK WORK`` labels the first N frames of WORK/train by simulated clicks
(``needletrack bench label --out``), fine-tunes on each (``needletrack finetune``) and scores every
weights on WORK/test (``needletrack eval``), beside the shipped weights (WORK/eval_shipped) and a
fine-tune on all of WORK/train with its full truth (WORK/ref, ``models/finetune.sh``). This module
reads those folders back: ``curve(work)`` the figures, ``tables(works)`` the markdown of
docs/adapt.md, ``plot(works, path)`` the picture.

    python -m common.adapt.learning_curve WORK [WORK ...] [--plot PNG] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from common.evaluation.results_page import looks_table

TARGETS = {"keypoints_px": 2.0, "found": 0.98, "sure_and_right": 0.80}
"""Issue 55's figures with 30 labelled frames that the picture draws: keypoints mean (px), found,
sure and right (shares)."""

LOOK_TITLES = {"alt_threadless": "second renderer, threadless", "silicone": "silicone pads, threadless"}


def _read(path: Path):
    return json.loads(path.read_text()) if path.is_file() else None


def _sizes(work: Path) -> list[int]:
    return sorted(int(m.group(1)) for p in work.glob("eval_*") if (m := re.fullmatch(r"eval_(\d+)", p.name))
                  and (p / "results.json").is_file())


def _row(results: dict | None) -> dict | None:
    """The figures the curve plots, from one ``results.json``."""
    if results is None:
        return None
    p = results["pose"].get("refined") or {}
    return {"found": results["detection_rate"], "keypoints_px": results["keypoints_2d_px"]["all"]["mean"],
            "refined_mm": p.get("position_mm", {}).get("mean"), "refined_deg": p.get("orientation_deg", {}).get("mean"),
            "posed": p.get("n"), "expected": p.get("expected"), "sure_and_right": p.get("sure_and_right"),
            "confident_swaps": p.get("confident_swaps"), "nees_median": p.get("nees", {}).get("median")}


def curve(work: str | Path) -> dict:
    """Every measured point of one look's curve: ``{"look", "shipped", "ref", "sizes": {N: {...}}}``;
    a size's entry has its scores, the labelling figures (``bench label``: clicks a frame, the
    labels' keypoint error) and the fine-tune's split and minutes."""
    work = Path(work)
    out = {"look": work.name, "shipped": _row(_read(work / "eval_shipped" / "results.json")),
           "ref": _row(_read(work / "ref" / "eval_after" / "results.json")), "sizes": {}}
    sec = work / "ref.seconds"
    if out["ref"] is not None and sec.is_file():
        out["ref"]["minutes"] = int(sec.read_text()) / 60
    for n in _sizes(work):
        row = _row(_read(work / f"eval_{n}" / "results.json"))
        lab = _read(work / f"labels_{n}.json") or {}
        ft = _read(work / f"ft_{n}" / "finetune.json") or {}
        split = ft.get("split", {})
        count = lambda part: sum(len(s["frames"]) for s in split.get(part, []))
        sec = work / f"ft_{n}.seconds"
        row.update({"labelled": n, "trained_on": count("train"), "held_out": count("heldout"),
                    "clicks_per_frame": lab.get("clicks_per_frame"),
                    "label_keypoint_px": lab.get("keypoint_px", {}).get("mean"),
                    "finetune_minutes": int(sec.read_text()) / 60 if sec.is_file() else None,
                    "training_minutes": ft.get("train", {}).get("elapsed_s", 0) / 60 or None})
        out["sizes"][n] = row
    return out


def tables(works: list[str | Path]) -> str:
    """Markdown: per look, the labelling and time table and the scores (docs/results.md's columns)."""
    lines = []
    for work in works:
        work = Path(work)
        c = curve(work)
        title = LOOK_TITLES.get(c["look"], c["look"])
        lines += [f"**{title}** (`{work}/test`):", "",
                  "| labelled frames | trained on / held out | clicks a frame | labels' keypoints px, mean | "
                  "`needletrack finetune` min (training) |", "| --- | --- | --- | --- | --- |"]
        for n, r in c["sizes"].items():
            f = lambda x, fmt=".2f": "-" if x is None else format(x, fmt)
            lines.append(f"| {n} | {r['trained_on']} / {r['held_out']} | {f(r['clicks_per_frame'], '.1f')} | "
                         f"{f(r['label_keypoint_px'])} | {f(r['finetune_minutes'], '.1f')} "
                         f"({f(r['training_minutes'], '.1f')}) |")
        ref_min = (c["ref"] or {}).get("minutes")
        sets, results = [{"name": "shipped", "title": "shipped weights", "family": "held-out"}], {}
        results["shipped"] = _read(work / "eval_shipped" / "results.json")
        for n in c["sizes"]:
            sets.append({"name": str(n), "title": f"{n} labelled frames", "family": "held-out"})
            results[str(n)] = _read(work / f"eval_{n}" / "results.json")
        sets.append({"name": "ref", "title": "400 frames with full truth" +
                     ("" if ref_min is None else f" ({ref_min:.1f} min)"), "family": "held-out"})
        results["ref"] = _read(work / "ref" / "eval_after" / "results.json")
        results = {k: v for k, v in results.items() if v is not None}
        lines += [""] + looks_table(sets, results) + [""]
    return "\n".join(lines)


def plot(works: list[str | Path], path: str | Path) -> None:
    """The curves: keypoints, `refined` position, found and sure-and-right against labelled frames
    (log axis), each look a colour; dashed its shipped weights, dotted its full-truth fine-tune;
    grey the issue's targets at 30 frames."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    panels = (("keypoints_px", "keypoints, mean (px)", TARGETS["keypoints_px"], 1.0, True),
              ("refined_mm", "refined position, mean (mm)", None, 1.0, False),
              ("found", "found (%)", TARGETS["found"], 100.0, False),
              ("sure_and_right", "sure and right (%)", TARGETS["sure_and_right"], 100.0, False))
    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    curves = [curve(work) for work in works]
    for (key, label, target, scale, log_y), ax in zip(panels, axes.ravel()):
        for i, c in enumerate(curves):
            col = colours[i % len(colours)]
            ns = [n for n, r in c["sizes"].items() if r.get(key) is not None]
            ax.plot(ns, [c["sizes"][n][key] * scale for n in ns], "o-", color=col,
                    label=LOOK_TITLES.get(c["look"], c["look"]))
            for what, style in (("shipped", "--"), ("ref", ":")):
                if c[what] is not None and c[what].get(key) is not None:
                    ax.axhline(c[what][key] * scale, color=col, ls=style, lw=1)
        if target is not None:
            ax.axhline(target * scale, color="0.5", lw=3, alpha=0.4)
        ax.set_xscale("log")
        ax.set_xticks([10, 30, 100])
        ax.set_xticklabels(["10", "30", "100"])
        if log_y:
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.set_xlabel("labelled stereo frames")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=8, title="solid: fine-tuned; dashed: shipped;\ndotted: 400 frames, full truth",
                      title_fontsize=7)
    fig.suptitle("Hand labels by simulated clicks (2 px): the shipped detector fine-tuned, scored on each look's test set")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m common.adapt.learning_curve", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("works", nargs="+", metavar="WORK", help="a folder models/learning_curve.sh wrote")
    p.add_argument("--plot", help="also draw the curves into this PNG")
    p.add_argument("--json", help="also write the figures here")
    a = p.parse_args(argv)
    missing = [w for w in a.works if not Path(w).is_dir()]
    if missing:
        p.error(f"not a folder: {', '.join(missing)}")
    print(tables(a.works))
    if a.plot:
        plot(a.works, a.plot)
    if a.json:
        Path(a.json).write_text(json.dumps([curve(w) for w in a.works], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
