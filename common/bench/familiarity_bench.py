"""``needletrack bench familiarity``: how unlike the detector's training looks each folder's images
are, and (``--fit FILE``) the reference that measures it (``common.detector.familiarity``).

Runs the learned detector (cold, each image on its own) over dataset folders and prints per
folder the detections' ``unfamiliarity``: median, 90th percentile and the share above 2.
``--fit`` fits the reference on the given folders first: give folders of the looks the weights
were trained on (renders of the same presets, not the training images, not a test set), and
write it beside the weights as ``familiarity.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from common.bench.folder_detections import cold_detections
from common.cli_options import add_weights


def descriptors(folder: str, detector, step: int = 1, progress: bool = True) -> np.ndarray:
    """The crop descriptors (N, D) of the needles the detector finds in a folder's images."""
    out = [detector.last_descriptor for _fr, _cam, kp in cold_detections(folder, detector, step, progress=progress)
           if kp.found]
    return np.array(out, float).reshape(len(out), -1)


def main(argv=None) -> int:
    from common.detector.familiarity import MIN_DETECTIONS, fit_familiarity, load_familiarity, save_familiarity
    from common.detector.inference import KeypointDetector
    from common.detector.weights import DEFAULT_WEIGHTS
    ap = argparse.ArgumentParser(prog="needletrack bench familiarity", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", action="append", required=True, help="dataset folder (repeatable)")
    add_weights(ap)
    ap.add_argument("--step", type=int, default=1, help="every step-th frame (default 1)")
    ap.add_argument("--fit", metavar="FILE", help="fit the reference on these folders and write it here")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)
    args.weights = args.weights or str(DEFAULT_WEIGHTS)
    det = KeypointDetector(args.weights, device="cpu", tracking=False, threads=1, familiarity=not args.fit)
    feats = {d: descriptors(d, det, args.step) for d in args.data}
    if args.fit:
        X = np.vstack(list(feats.values()))
        if len(X) < MIN_DETECTIONS:
            print(f"warning: {len(X)} detections in {', '.join(args.data)}: too few for a familiarity "
                  f"reference (at least {MIN_DETECTIONS}); {args.fit} not written: these weights state no "
                  f"unfamiliarity (add frames of the looks they were trained on)", file=sys.stderr)
            return 0
        fam = fit_familiarity(X, fitted_on=[Path(d).name for d in args.data])
        save_familiarity(fam, args.fit)
        print(f"wrote {args.fit}: {fam.detections} detections, {len(fam.variances)} components")
    else:
        fam = load_familiarity(args.weights)
        if fam is None:
            raise SystemExit(f"error: no familiarity.json beside {args.weights}; fit one with --fit")
    rows = []
    print(f"{'set':<28} {'found':>6} {'median':>7} {'p90':>7} {'> 2':>6}")
    for name, f in feats.items():
        u = fam.distance(f) / fam.median_distance if len(f) else np.zeros(0)
        r = {"set": name, "found": int(len(u)), "median": float(np.median(u)) if len(u) else None,
             "p90": float(np.quantile(u, 0.9)) if len(u) else None, "above_2": float(np.mean(u > 2)) if len(u) else None}
        rows.append(r)
        if len(u):
            print(f"{Path(name).name:<28} {r['found']:>6} {r['median']:>7.2f} {r['p90']:>7.2f} {r['above_2']:>6.1%}")
        else:
            print(f"{Path(name).name:<28} {0:>6}")
    print("(per image, cold; unfamiliarity about 1 on the looks the reference was fitted on)")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0
