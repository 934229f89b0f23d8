"""``needletrack bench held``: the keypoint detector on moving takes, by how much of the needle is seen.

    needletrack bench held --data data/moving [--weights PATH] [--takes N] [--json OUT.json]
        [--picture OUT.png]

Every frame of each take (``needle_at_rest: false``), both cameras, run as the live detector
runs: in tracking mode (the previous frame's box reused), reset at the start of each take. Each
image is put in a bin of its visible fraction: the frame's ``arc_visible`` (the share of the arc
the render shows, docs/datasets.md), else the share of visible keypoints. Per bin:

- ``found``: the share of images where the detector states a needle;
- keypoint error over the visible keypoints of found images (mean, median px), and over those it
  vouches for (score >= the pose nodes' ``min_score`` gate);
- ``hidden_sure``: hidden keypoints (not ``visible``) placed with a score at or above the gate,
  as a share of the hidden keypoints of found images. A hidden point must never be sure; over
  all bins, ``hidden_sure_by_keypoint`` says which points they are and how far from the truth
  they were placed (within ``PLACED_RIGHT_PX``, or ``PLACED_WRONG_PX`` or more);
- ``no_sure_points``: the share of images with no needle stated or no keypoint at or above the
  gate (what a frame with under 10% seen must give).
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from common.data.dataset import Dataset, DatasetError
from common.evaluation.detector_bench import SURE_SCORE, make_detector
from common.evaluation.metrics import VISIBLE_BINS, visible_fraction
from common.frames import CAMERAS
from common.geometry.needle import KEYPOINT_NAMES

PLACED_RIGHT_PX = 3.0
"""A hidden keypoint stated sure within this distance of the truth is placed right (px)."""
PLACED_WRONG_PX = 8.0
"""... and this far or farther, placed wrong (px): the tip read at the tissue's surface, an end
at a jaw's edge."""


def image_record(k, kp: np.ndarray, vis: np.ndarray, fraction: float, gate: float = SURE_SCORE) -> dict:
    """What the bench keeps of one detection ``k`` (``Keypoints``) against the truth (keypoints
    (5, 2) px, visible (5,) bool) of an image whose visible fraction is ``fraction``."""
    scores = np.asarray(k.scores, float) if k.found else np.zeros(5)
    sure = k.found & (scores >= gate)
    err = np.linalg.norm(np.asarray(k.uv, float) - kp, axis=1) if k.found else np.full(5, np.nan)
    vis = vis & np.isfinite(err)
    return {"fraction": float(fraction), "found": bool(k.found),
            "err_visible": err[vis].tolist(), "err_sure": err[vis & sure].tolist(),
            "hidden": int((~vis).sum()) if k.found else 0, "hidden_sure": int((~vis & sure).sum()),
            "hidden_sure_points": [[int(i), float(err[i])] for i in np.flatnonzero(~vis & sure)],
            "any_sure": bool(sure.any())}


def summarise(records: list[dict], bins=VISIBLE_BINS) -> list[dict]:
    """Per visible-fraction bin: images, found share, keypoint errors, hidden-and-sure share,
    the share with no sure keypoint."""
    out = []
    for lo, hi in zip(bins[:-1], bins[1:]):
        rs = [r for r in records if lo <= r["fraction"] < hi]
        row = {"bin": f"{lo * 100:.0f}-{min(hi, 1.0) * 100:.0f}%", "images": len(rs)}
        if rs:
            ev = np.concatenate([r["err_visible"] for r in rs] + [[]])
            es = np.concatenate([r["err_sure"] for r in rs] + [[]])
            hidden = sum(r["hidden"] for r in rs)
            row.update({"found": float(np.mean([r["found"] for r in rs])),
                        "kp_error_mean_px": float(ev.mean()) if ev.size else None,
                        "kp_error_median_px": float(np.median(ev)) if ev.size else None,
                        "kp_error_sure_mean_px": float(es.mean()) if es.size else None,
                        "hidden_keypoints": hidden,
                        "hidden_sure": float(sum(r["hidden_sure"] for r in rs) / hidden) if hidden else 0.0,
                        "no_sure_points": float(np.mean([not r["any_sure"] for r in rs]))})
        out.append(row)
    return out


def hidden_sure_by_keypoint(records: list[dict]) -> dict:
    """Over all images: per keypoint (A..E), how many hidden points were stated sure, and of
    them how many placed within ``PLACED_RIGHT_PX`` of the truth and ``PLACED_WRONG_PX`` or
    more from it."""
    out = {name: {"n": 0, "placed_right": 0, "placed_wrong": 0} for name in KEYPOINT_NAMES}
    for r in records:
        for i, e in r.get("hidden_sure_points", []):
            row = out[KEYPOINT_NAMES[i]]
            row["n"] += 1
            row["placed_right"] += int(e < PLACED_RIGHT_PX)
            row["placed_wrong"] += int(e >= PLACED_WRONG_PX)
    return out


def run(data, weights=None, takes: int | None = None, threads=None, device="auto", progress=True) -> dict:
    from tqdm import tqdm
    ds = Dataset(str(data))
    moving = [f for f in ds if not f.at_rest and f.keypoints is not None and f.visible is not None]
    if not moving:
        raise DatasetError(f"{data}: no frame of a moving take with ground truth (needle_at_rest: false)")
    seqs = sorted({f.sequence for f in moving})[:takes]
    frames = [f for f in moving if f.sequence in set(seqs)]
    det = make_detector("learned", weights, threads, device)
    records, last_seq = [], None
    for f in tqdm(frames, desc="bench held", unit="frame", disable=not progress):
        if f.sequence != last_seq:
            det.reset()
            last_seq = f.sequence
        for cam in CAMERAS:
            k = det.detect(ds.image(f, cam), cam, seq=f.index, stamp_ns=f.stamp_ns)
            rec = image_record(k, np.asarray(f.keypoints[cam], float), np.asarray(f.visible[cam], bool),
                               visible_fraction(f, cam))
            rec.update({"frame": f.index, "camera": cam, "sequence": f.sequence})
            records.append(rec)
    seen30 = [r for r in records if r["fraction"] >= 0.3]
    return {"data": str(data), "weights": str(weights or "shipped"), "takes": len(seqs), "frames": len(frames),
            "images": len(records), "gate": SURE_SCORE,
            "found_where_30pct_seen": float(np.mean([r["found"] for r in seen30])) if seen30 else None,
            "bins": summarise(records), "hidden_sure_by_keypoint": hidden_sure_by_keypoint(records),
            "per_image": records}


def format_report(r: dict) -> str:
    f = lambda v, fmt: "-" if v is None else format(v, fmt)
    lines = [f"{r['data']}: {r['takes']} takes, {r['frames']} frames, {r['images']} images (weights {r['weights']})",
             f"found where >= 30% of the arc is seen: {f(r['found_where_30pct_seen'], '.1%')}",
             "| visible | images | found | kp error mean / median px | sure kp error px | hidden kp stated sure"
             " | no sure keypoint |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for b in r["bins"]:
        if not b["images"]:
            lines.append(f"| {b['bin']} | 0 | | | | | |")
            continue
        lines.append(f"| {b['bin']} | {b['images']} | {b['found']:.1%} | {f(b['kp_error_mean_px'], '.2f')} / "
                     f"{f(b['kp_error_median_px'], '.2f')} | {f(b['kp_error_sure_mean_px'], '.2f')} | "
                     f"{b['hidden_sure']:.1%} of {b['hidden_keypoints']} | {b['no_sure_points']:.1%} |")
    by = r.get("hidden_sure_by_keypoint")
    if by:
        lines.append(f"hidden keypoints stated sure, all bins (placed within {PLACED_RIGHT_PX:g} px / "
                     f"{PLACED_WRONG_PX:g} px or more from the truth): "
                     + ", ".join(f"{k} {v['n']} ({v['placed_right']} / {v['placed_wrong']})" for k, v in by.items()))
    return "\n".join(lines)


def save_picture(path, r: dict) -> None:
    """Found share and keypoint error against the visible fraction (10 bins), as a PNG."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    edges = np.linspace(0, 1.0001, 11)
    rows = summarise(r["per_image"], tuple(edges))
    x = (edges[:-1] + np.minimum(edges[1:], 1.0)) / 2 * 100
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    ok = [b["images"] > 0 for b in rows]
    ax.bar(x[ok], [b["found"] * 100 for b, o in zip(rows, ok) if o], width=8, color="#9ecae1", label="found (%)")
    ax.set_xlabel("share of the arc seen (%)")
    ax.set_ylabel("found (%)")
    ax.set_ylim(0, 105)
    ax2 = ax.twinx()
    e = [(xi, b["kp_error_median_px"]) for xi, b in zip(x, rows) if b["images"] and b["kp_error_median_px"] is not None]
    if e:
        ax2.plot(*zip(*e), "o-", color="#d62728", label="keypoint error, median (px)")
    ax2.set_ylabel("keypoint error, median (px)")
    ax.set_title(f"detector on {r['takes']} moving takes ({r['images']} images)")
    fig.legend(loc="upper left", bbox_to_anchor=(0.1, 0.88), fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="needletrack bench held", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="a dataset folder of moving takes (dataset generate --motion ...)")
    p.add_argument("--weights", default=None, help="detector weights (default: the shipped models/keypoint/model.pt)")
    p.add_argument("--takes", type=int, default=None, help="only the first N takes")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--device", default="auto")
    p.add_argument("--json", default=None, help="write the figures (and per-image records) here")
    p.add_argument("--picture", default=None, help="write found share and error against visible fraction (PNG)")
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    try:
        r = run(a.data, a.weights, a.takes, a.threads, a.device, not a.quiet)
    except (DatasetError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(format_report(r))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(r, fh, indent=1)
    if a.picture:
        save_picture(a.picture, r)
    return 0
