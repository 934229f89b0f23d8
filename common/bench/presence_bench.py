"""``needletrack bench presence``: where the detector reports a needle that is not there, and
(``--fit FILE``) the presence gate that keeps those reports under a share
(``common.detector.presence_gate``).

Runs the learned detector cold over dataset folders at the default threshold (0.5), keeps each
image's stage-2 presence, and prints per folder: for folders with a needle (``--data``) the images
read in the right place and in the wrong place (keypoints more than ``WRONG_PX`` from the truth),
for needle-free folders (``--negatives``) the images reporting a needle; each at 0.5 and at the
gate (the weights' ``presence_gate.json``, or the one ``--fit`` writes). Fit on looks the weights
never trained on and that no figure is measured on; the gate's shares are computed from the 0.5
run's presences (at a higher threshold the detector may try another proposal: ``needletrack
detect DIR --weights W`` measures the gate as it runs).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from common.bench.folder_detections import cold_detections
from common.cli_options import add_weights


def _misplaced_px(uv: np.ndarray, truth: np.ndarray) -> float:
    """Median distance (px) from the detected keypoints to the true ones, the nearer end order."""
    d = [np.median(np.linalg.norm(np.asarray(uv, float)[order] - truth, axis=1)) for order in (slice(None), slice(None, None, -1))]
    return float(min(d))


def presences(folder: str, detector, needle: bool, step: int = 1, progress: bool = True) -> dict:
    """Per image of a folder, read cold: ``presence`` (0 where no needle was reported) and, for a
    folder with a needle, ``misplaced_px`` (NaN where none was reported)."""
    pres, off = [], []
    for fr, cam, kp in cold_detections(folder, detector, step, progress=progress):
        pres.append(float(kp.confidence) if kp.found else 0.0)
        if needle:
            off.append(_misplaced_px(kp.uv, fr.keypoints[cam]) if kp.found and fr.keypoints is not None
                       else float("nan"))
    return {"presence": np.array(pres), "misplaced_px": np.array(off)}


def _split(r: dict) -> tuple[np.ndarray, np.ndarray]:
    """(presences read in the right place, in the wrong place) of a folder with a needle."""
    from common.detector.presence_gate import WRONG_PX
    found = r["presence"] > 0          # a detection without truth to score (NaN) is neither
    return (r["presence"][found & (r["misplaced_px"] <= WRONG_PX)],
            r["presence"][found & (r["misplaced_px"] > WRONG_PX)])


def main(argv=None) -> int:
    from common.detector.inference import KeypointDetector
    from common.detector.presence_gate import (DEFAULT_THRESHOLD, MAX_FALSE, fit_presence_gate,
                                               load_presence_gate, save_presence_gate)
    from common.detector.weights import DEFAULT_WEIGHTS
    ap = argparse.ArgumentParser(prog="needletrack bench presence", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", action="append", default=[], help="dataset folder with a needle and its truth (repeatable)")
    ap.add_argument("--negatives", action="append", default=[],
                    help="needle-free dataset folder (`needletrack dataset generate-negatives`; repeatable)")
    add_weights(ap)
    ap.add_argument("--step", type=int, default=1, help="every step-th frame (default 1)")
    ap.add_argument("--fit", metavar="FILE", help="fit the gate on these folders and write it here "
                                                  "(presence_gate.json beside the weights: the detector uses it)")
    ap.add_argument("--max-false", type=float, default=MAX_FALSE,
                    help=f"--fit: the share of needle-free images, and of images read in the wrong place, "
                         f"the gate allows (default {MAX_FALSE})")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--plot", metavar="PNG", help="draw the trade-off (right reads against false ones by threshold)")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    if not args.data and not args.negatives:
        ap.error("give --data and/or --negatives folders")
    if args.fit and not (args.data and args.negatives):
        ap.error("--fit needs both --data (needles) and --negatives (needle-free) folders")
    if not 0 <= args.max_false < 1:
        ap.error(f"--max-false must be in [0, 1), got {args.max_false}")
    weights = args.weights or str(DEFAULT_WEIGHTS)
    det = KeypointDetector(weights, device="cpu", tracking=False, threads=1, threshold=DEFAULT_THRESHOLD)
    res = {d: presences(d, det, True, args.step, not args.quiet) for d in args.data}
    neg = {d: presences(d, det, False, args.step, not args.quiet) for d in args.negatives}
    if args.fit:
        right, wrong = zip(*(_split(r) for r in res.values()))
        gate = fit_presence_gate(np.concatenate([r["presence"] for r in neg.values()]), np.concatenate(right),
                                 np.concatenate(wrong), sum(len(r["presence"]) for r in res.values()),
                                 [Path(d).name for d in args.data + args.negatives], args.max_false)
        save_presence_gate(gate, args.fit)
        print(f"wrote {args.fit}: threshold {gate.threshold:.4f} (needle-free reported {100 * gate.false_share:.1f}%, "
              f"wrong place {100 * gate.wrong_share:.1f}%, right place {100 * gate.right_share:.1f}% on the fit folders)")
    else:
        gate = load_presence_gate(weights)
    t_gate = None if gate is None else gate.threshold
    thresholds = TRADE_OFF if t_gate is None else TRADE_OFF + (t_gate,)
    rows = []
    print(f"{'set':<28} {'images':>6} {'kind':>10} {'at 0.5':>8} {'at gate':>8}")
    for d, r in res.items():
        right, wrong = _split(r)
        n = len(r["presence"])
        for kind, p in (("right", right), ("wrong", wrong)):
            at = lambda t: None if t is None else float((p >= t).sum() / max(n, 1))
            rows.append({"set": d, "images": n, "kind": kind, "at_default": at(DEFAULT_THRESHOLD), "at_gate": at(t_gate)})
    for d, r in neg.items():
        p, n = r["presence"], len(r["presence"])
        at = lambda t: None if t is None else float((p >= t).mean()) if n else None
        rows.append({"set": d, "images": n, "kind": "false", "at_default": at(DEFAULT_THRESHOLD), "at_gate": at(t_gate)})
    pct = lambda x: "-" if x is None else f"{100 * x:.1f}%"
    for row in rows:
        print(f"{Path(row['set']).name:<28} {row['images']:>6} {row['kind']:>10} {pct(row['at_default']):>8} "
              f"{pct(row['at_gate']):>8}")
    curve = trade_off(res, neg, thresholds)
    print(f"all folders: {'threshold':>9} {'needle-free reported':>21} {'wrong place':>12} {'right place':>12}")
    for c in curve:
        print(f"{'':12} {c['threshold']:>9.4f} {pct(c['false']):>21} {pct(c['wrong']):>12} {pct(c['right']):>12}")
    if args.plot:
        plot_trade_off(curve, t_gate, args.plot, Path(weights).parent.name)
    if args.json:
        Path(args.json).write_text(json.dumps({"weights": weights, "gate": None if gate is None else gate.to_dict(),
                                               "rows": rows, "trade_off": curve}, indent=1) + "\n")
    return 0


TRADE_OFF = (0.5, 0.7, 0.8, 0.9, 0.95, 0.98, 0.99, 0.995, 0.999)
"""The thresholds of the printed trade-off (the gate's own is added)."""


def trade_off(res: dict, neg: dict, thresholds=TRADE_OFF) -> list[dict]:
    """Over all folders, per threshold: the shares of needle-free images reporting a needle
    (``false``; None without needle-free folders) and of images with a needle read in the wrong
    and in the right place."""
    free = np.concatenate([r["presence"] for r in neg.values()] or [np.zeros(0)])
    parts = [_split(r) for r in res.values()]
    right = np.concatenate([p[0] for p in parts] or [np.zeros(0)])
    wrong = np.concatenate([p[1] for p in parts] or [np.zeros(0)])
    n = sum(len(r["presence"]) for r in res.values())
    share = lambda a, t, total: None if total == 0 else float((a >= t).sum() / total)
    return [{"threshold": float(t), "false": share(free, t, len(free)), "wrong": share(wrong, t, n),
             "right": share(right, t, n)} for t in sorted(set(thresholds))]


def plot_trade_off(curve: list[dict], gate, path, title: str) -> None:
    """Right-place reads against needle-free and wrong-place reports, by threshold (a point each)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4.5))
    t = [c["threshold"] for c in curve]
    for key, label in (("false", "needle-free images reporting a needle"), ("wrong", "images with a needle read in the wrong place")):
        pts = [(c[key], c["right"]) for c in curve if c[key] is not None and c["right"] is not None]
        if pts:
            x, y = zip(*pts)
            ax.plot(np.array(x) * 100, np.array(y) * 100, "o-", label=label)
            for xi, yi, ti in zip(x, y, t) if key == "false" else ():
                ax.annotate(f"{ti:.4g}", (xi * 100, yi * 100), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("false statements (% of images)")
    ax.set_ylabel("images with a needle read in the right place (%)")
    ax.set_title(f"presence threshold (labels) trade-off: {title}" + ("" if gate is None else f" (gate {gate:.4f})"), fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
