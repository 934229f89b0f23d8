"""``needletrack bench end-identity``: how well the learned detector tells the tip from the tail.

Runs the detector (cold, each image on its own) over dataset folders with ground truth and
labels each detection: its A at the true tip (A..E as said) or at the true tail (turned). Per
folder it prints the network's own swap rate, how often each piece of evidence
(``common.detector.end_identity``) points the right way, and what the stated probability does:
sure and right, sure and wrong (the failure that matters), and unsure (the pose nodes flag it).
``--fit FILE`` fits the evidence's coefficients on the given folders, each weighing the same,
and writes them as JSON (the detector reads ``end_identity.json`` beside its weights). Fit on
folders no training stage saw, of looks the weights know and of looks they do not, so that the
fit sees the network on unfamiliar images: ``--hue-data`` and ``--grey-data`` read a folder with
its hues turned or without colour (looks no training renders). Never fit on a folder you report.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from common.bench.folder_detections import cold_detections
from common.cli_options import add_weights
from common.detector.data import turn_hue
from common.detector.end_identity import FEATURES
from common.geometry.end_identity import TIP_SURE as SURE

MIN_FIT_ERRORS = 5      # fewer detections read end for end (or as said) than this: warn at --fit
FOLDER_WEIGHT = 1000.0  # at --fit every folder weighs as this many detections, however many it has
FIT_L2 = 1.0            # the fit's L2 penalty on the coefficients, against FOLDER_WEIGHT per folder


def to_grey(img: np.ndarray) -> np.ndarray:
    """A BGR image without its colours (luma in all three channels): a look no training renders."""
    return cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)


def collect(folder: str, detector, step: int = 1, hue: tuple | None = None, grey: bool = False,
            progress: bool = True) -> dict:
    """Features (N, len(FEATURES)), labels (N,) (1: A at the true tip) and the images seen, for
    one folder; ``hue`` (lo, hi): turn each image's hue by a draw from this range (degrees,
    ``turn_hue``; one draw per frame, seeded by the folder's frame order); ``grey``: read the
    images without colour (``to_grey``)."""
    feats, labels, seen = [], [], 0
    rng = np.random.default_rng(0)

    def look(_frame):
        shift = float(rng.uniform(*hue)) if hue else 0.0      # one draw per frame, skipped ones too

        def change(img):
            if shift:
                img = turn_hue(img, shift)
            return to_grey(img) if grey else img
        return change

    for fr, cam, kp in cold_detections(folder, detector, step, only=lambda fr: fr.keypoints is not None, look=look,
                                    progress=progress):
        seen += 1
        true = np.asarray(fr.keypoints[cam], float)
        if not kp.found or not np.isfinite(true[[0, 4]]).all():
            continue
        as_said = np.linalg.norm(kp.uv[0] - true[0]) + np.linalg.norm(kp.uv[4] - true[4])
        turned = np.linalg.norm(kp.uv[0] - true[4]) + np.linalg.norm(kp.uv[4] - true[0])
        feats.append(detector.last_evidence.features())
        labels.append(float(as_said < turned))
    return {"features": np.array(feats).reshape(-1, len(FEATURES)), "labels": np.array(labels), "images": seen}


def summary(name: str, data: dict, coef: np.ndarray) -> dict:
    """The figures of one folder under coefficients ``coef``."""
    X, y = data["features"], data["labels"]
    n = len(y)
    if n == 0:
        return {"set": name, "found": 0}
    p = 1.0 / (1.0 + np.exp(-X[:, :len(coef)] @ coef))
    right = np.where(p >= 0.5, y == 1, y == 0)        # the stated side is the true one
    sure = (p >= SURE) | (p <= 1 - SURE)
    return {"set": name, "images": data["images"], "found": n,
            "network_swaps": float(np.mean(y == 0)),
            "shape_right": float(np.mean((X[:, 0] > 0) == (y == 1))),
            "network_right": float(np.mean((X[:, 1] > 0) == (y == 1))),
            "sure_right": float(np.mean(sure & right)), "sure_wrong": float(np.mean(sure & ~right)),
            "unsure": float(np.mean(~sure))}


def main(argv=None) -> int:
    from common.detector.end_identity import COEF, fit_coefficients
    from common.detector.inference import KeypointDetector
    from common.detector.weights import DEFAULT_WEIGHTS, load_end_coefficients
    ap = argparse.ArgumentParser(prog="needletrack bench end-identity", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", action="append", default=[], help="dataset folder with ground truth (repeatable)")
    add_weights(ap)
    ap.add_argument("--step", type=int, default=1, help="every step-th frame (default 1)")
    ap.add_argument("--fit", metavar="FILE", help="fit the coefficients on these folders and write them here")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--dump", metavar="NPZ", help="write each folder's features and labels here (numpy .npz)")
    ap.add_argument("--hue-data", action="append", default=[], metavar="DIR",
                    help="a folder read with its hues turned (--hue; repeatable): a look family no training renders")
    ap.add_argument("--hue", default="40,100", help="the range of --hue-data's turn, degrees (default 40,100)")
    ap.add_argument("--grey-data", action="append", default=[], metavar="DIR",
                    help="a folder read without colour (repeatable): a look family no training renders")
    args = ap.parse_args(argv)
    args.weights = args.weights or str(DEFAULT_WEIGHTS)
    if not (args.data or args.hue_data or args.grey_data):
        ap.error("give at least one folder: --data, --hue-data or --grey-data")
    det = KeypointDetector(args.weights, device="cpu", tracking=False, threads=1)
    data = {d: collect(d, det, args.step) for d in args.data}
    try:
        hue = tuple(float(v) for v in args.hue.split(","))
        assert len(hue) == 2
    except (ValueError, AssertionError):
        ap.error(f"--hue: two degrees LO,HI, got {args.hue!r}")
    data.update({f"{d}@hue": collect(d, det, args.step, hue) for d in args.hue_data})
    data.update({f"{d}@grey": collect(d, det, args.step, grey=True) for d in args.grey_data})
    if args.dump:
        np.savez(args.dump, **{f"{Path(d).name}.{k}": v[k] for d, v in data.items() for k in ("features", "labels")})
    coef = load_end_coefficients(args.weights)
    coef = COEF if coef is None else coef
    if args.fit:
        X = np.vstack([d["features"] for d in data.values()])
        y = np.concatenate([d["labels"] for d in data.values()])
        w = np.concatenate([np.full(len(d["labels"]), FOLDER_WEIGHT / max(len(d["labels"]), 1))
                            for d in data.values()])
        coef = fit_coefficients(X, y, l2=FIT_L2, weights=w)
        turned, as_said = int(np.sum(y == 0)), int(np.sum(y == 1))
        if min(turned, as_said) < MIN_FIT_ERRORS:
            print(f"warning: of {len(y)} detections the network read {turned} end for end and {as_said} "
                  f"as said: too few of one kind to learn how sure it may be; the coefficients may "
                  f"state a sure tip too often (add frames, or a harder part of the look)", file=sys.stderr)
        Path(args.fit).write_text(json.dumps({
            "features": list(FEATURES), "coef": [float(c) for c in coef],
            "fitted_on": [Path(d.split("@")[0]).name + ("@" + d.split("@")[1] if "@" in d else "") for d in data],
            "detections": int(len(y))}, indent=1) + "\n")
        print(f"wrote {args.fit}: coef {np.round(coef, 3).tolist()} from {len(y)} detections")
    rows = [summary(name, d, coef) for name, d in data.items()]
    print(f"{'set':<28} {'found':>6} {'net swaps':>9} {'shape ok':>8} {'net ok':>7} "
          f"{'sure ok':>8} {'SURE WRONG':>10} {'unsure':>7}")
    for r in rows:
        if not r["found"]:
            print(f"{Path(r['set']).name:<28} {0:>6}")
            continue
        print(f"{Path(r['set']).name:<28} {r['found']:>6} {r['network_swaps']:>9.1%} {r['shape_right']:>8.1%} "
              f"{r['network_right']:>7.1%} {r['sure_right']:>8.1%} {r['sure_wrong']:>10.1%} {r['unsure']:>7.1%}")
    print(f"(per image, cold; sure = stated probability beyond {SURE:g}; coefficients {np.round(coef, 3).tolist()})")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0
