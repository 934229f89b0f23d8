"""``needletrack bench held``: the keypoint detector on moving takes, by how much of the needle is seen.

    needletrack bench held --data data/moving [--weights PATH] [--takes N] [--json OUT.json]
        [--picture OUT.png] [--hidden-sure-picture OUT.png]

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
  they were placed (within ``PLACED_RIGHT_PX``, or ``PLACED_WRONG_PX`` or more), and
  ``--hidden-sure-picture`` shows up to ``GALLERY_PER_KEYPOINT`` of them per keypoint, each from
  another take;
- ``no_sure_points``: the share of images with no needle stated or no keypoint at or above the
  gate (what a frame with under 10% seen must give).
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from common.bench.detector_bench import SURE_SCORE, make_detector
from common.cli_options import add_quiet, add_weights
from common.data.dataset import Dataset, DatasetError
from common.evaluation.metrics import VISIBLE_BINS, visible_fraction
from common.frames import CAMERAS
from common.geometry.needle import KEYPOINT_NAMES
from common.viewer.draw import TRUTH_BGR

PLACED_RIGHT_PX = 3.0
"""A hidden keypoint stated sure within this distance of the truth is placed right (px)."""
PLACED_WRONG_PX = 8.0
"""... and this far or farther, placed wrong (px): the tip read at the tissue's surface, an end
at a jaw's edge."""
GALLERY_PER_KEYPOINT = 2
"""Hidden points stated sure shown per keypoint by ``--hidden-sure-picture``."""
SURE_BGR, UNSURE_BGR, RING_BGR = (40, 40, 230), (230, 120, 40), (0, 230, 255)


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


def hidden_sure_crop(image: np.ndarray, k, kp: np.ndarray, vis: np.ndarray, i: int, side: int = 240) -> np.ndarray:
    """A ``side`` x ``side`` BGR picture of the needle in ``image`` around hidden keypoint ``i``
    that detection ``k`` states sure: the truth in green (seen points filled, hidden ones as
    rings), the detection's keypoints filled, red where sure and blue where not, point ``i``
    ringed in yellow."""
    import cv2
    uv = np.asarray(k.uv, float)
    pts = np.concatenate([kp, uv])
    pts = pts[np.isfinite(pts).all(axis=1)]
    lo, hi = pts.min(0), pts.max(0)
    half = max(float((hi - lo).max()) * 0.6, 40.0)
    cx, cy = (lo + hi) / 2
    scale = side / (2 * half)
    M = np.array([[scale, 0, side / 2 - scale * cx], [0, scale, side / 2 - scale * cy]])
    out = cv2.warpAffine(image, M, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    to = lambda p: tuple(int(round(v)) for v in M[:, :2] @ p + M[:, 2])
    for j in np.flatnonzero(np.isfinite(kp).all(axis=1)):
        cv2.circle(out, to(kp[j]), 5, TRUTH_BGR, -1 if vis[j] else 1, cv2.LINE_AA)
    for p, sc in zip(uv, np.asarray(k.scores, float)):
        cv2.circle(out, to(p), 3, SURE_BGR if sc >= SURE_SCORE else UNSURE_BGR, -1, cv2.LINE_AA)
    cv2.circle(out, to(uv[i]), 9, RING_BGR, 1, cv2.LINE_AA)
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


def run(data, weights=None, takes: int | None = None, threads=None, device="auto", progress=True,
        gallery_too: bool = False) -> dict:
    """The bench's figures (module docstring); ``gallery_too``: also ``gallery``, per keypoint
    the pictures (``hidden_sure_crop``) of up to ``GALLERY_PER_KEYPOINT`` hidden points stated sure."""
    from common.progress import progress_bar
    ds = Dataset(str(data))
    moving = [f for f in ds if not f.at_rest and f.keypoints is not None and f.visible is not None]
    if not moving:
        raise DatasetError(f"{data}: no frame of a moving take with ground truth (needle_at_rest: false)")
    seqs = sorted({f.sequence for f in moving})[:takes]
    frames = [f for f in moving if f.sequence in set(seqs)]
    det = make_detector("learned", weights, threads, device)
    records, last_seq = [], None
    gallery = {name: [] for name in KEYPOINT_NAMES}
    for f in progress_bar(frames, desc="bench held", unit="frame", show=progress):
        if f.sequence != last_seq:
            det.reset()
            last_seq = f.sequence
        for cam in CAMERAS:
            k = det.detect(ds.image(f, cam), cam, seq=f.index, stamp_ns=f.stamp_ns)
            rec = image_record(k, np.asarray(f.keypoints[cam], float), np.asarray(f.visible[cam], bool),
                               visible_fraction(f, cam))
            rec.update({"frame": f.index, "camera": cam, "sequence": f.sequence})
            records.append(rec)
            for i, e in rec["hidden_sure_points"] if gallery_too else ():
                shown = gallery[KEYPOINT_NAMES[i]]
                if len(shown) < GALLERY_PER_KEYPOINT and f.sequence not in {g["sequence"] for g in shown}:
                    shown.append({"sequence": f.sequence, "frame": f.index, "camera": cam, "error_px": e,
                                  "score": float(k.scores[i]),
                                  "crop": hidden_sure_crop(ds.image(f, cam), k, np.asarray(f.keypoints[cam], float),
                                                           np.asarray(f.visible[cam], bool), i)})
    seen30 = [r for r in records if r["fraction"] >= 0.3]
    return {"data": str(data), "weights": str(weights or "shipped"), "takes": len(seqs), "frames": len(frames),
            "images": len(records), "gate": SURE_SCORE,
            "found_where_30pct_seen": float(np.mean([r["found"] for r in seen30])) if seen30 else None,
            "bins": summarise(records), "hidden_sure_by_keypoint": hidden_sure_by_keypoint(records),
            "per_image": records, **({"gallery": gallery} if gallery_too else {})}


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


def save_hidden_sure_picture(path, r: dict) -> None:
    """The hidden keypoints stated sure of ``r["gallery"]`` (``run(gallery_too=True)``), a row per
    keypoint, as a PNG."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    g = r["gallery"]
    fig, axes = plt.subplots(len(KEYPOINT_NAMES), GALLERY_PER_KEYPOINT, figsize=(2.6 * GALLERY_PER_KEYPOINT, 13.5),
                             dpi=100, squeeze=False)
    for row, name in zip(axes, KEYPOINT_NAMES):
        for j, ax in enumerate(row):
            ax.set_xticks([])
            ax.set_yticks([])
            if j < len(g[name]):
                s = g[name][j]
                ax.imshow(s["crop"][..., ::-1])
                ax.set_title(f"{name} hidden, {s['score']:.2f}, {s['error_px']:.0f} px off\n"
                             f"take {s['sequence']} frame {s['frame']} {s['camera']}", fontsize=7)
            else:
                ax.text(0.5, 0.5, f"no hidden {name}\nstated sure", ha="center", va="center", fontsize=8)
    fig.suptitle("hidden keypoints stated sure (ringed): truth green (hollow: hidden),\n"
                 "detection red (sure) / blue (unsure)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="needletrack bench held", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="a dataset folder of moving takes (dataset generate --motion ...)")
    add_weights(p)
    p.add_argument("--takes", type=int, default=None, help="only the first N takes")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--device", default="auto")
    p.add_argument("--json", default=None, help="write the figures (and per-image records) here")
    p.add_argument("--picture", default=None, help="write found share and error against visible fraction (PNG)")
    p.add_argument("--hidden-sure-picture", default=None,
                   help="write pictures of hidden keypoints stated sure, per keypoint (PNG)")
    add_quiet(p)
    a = p.parse_args(argv)
    try:
        r = run(a.data, a.weights, a.takes, a.threads, a.device, not a.quiet, bool(a.hidden_sure_picture))
    except (DatasetError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(format_report(r))
    if a.hidden_sure_picture:
        save_hidden_sure_picture(a.hidden_sure_picture, r)
    if a.json:
        r.pop("gallery", None)
        with open(a.json, "w") as fh:
            json.dump(r, fh, indent=1)
    if a.picture:
        save_picture(a.picture, r)
    return 0
