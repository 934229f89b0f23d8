"""``needletrack bench detector``: speed and accuracy of a keypoint detector backend.

    needletrack bench detector --data data/test [--backend learned|classical] [--weights PATH]
        [--frames 30] [--negatives data/negatives] [--json OUT.json] [--picture OUT.png]

Accuracy on the first ``--frames`` needle poses of the test folder (step 0 of each sequence,
both cameras: 30 -> 60 images), each detected cold: detection rate, 2D keypoint error over the
visible keypoints (per keypoint A..E, mean and median) and the centreline's distance to the
true projected arc. False detections on needle-free images (``--negatives``: a folder of them;
made with the simulator by ``--make-negatives N`` if missing). Speed: ms per image from the BGR
array to ``Keypoints``, cold (tracking state reset) and in tracking mode (the previous
frame's box reused), with the warm-up excluded.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from common.cli_options import add_weights
from common.detector.data import DatasetError, read_dataset, true_arc_pixels
from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel



SURE_SCORE = 0.5   # the pose nodes' default min_score


def test_images(folder, n_frames: int):
    """[(image path, camera, keypoints (5,2), visible (5,), arc (P,2) or None)] of the first
    ``n_frames`` needle poses (step 0 of each sequence, or the first frames)."""
    folder = Path(folder)
    meta, frames = read_dataset(folder)
    rig = StereoRig.from_dict(meta["cameras"], meta["image_size"])
    needle = NeedleModel.from_dict(meta.get("needle") or {})
    firsts = [f for f in frames if f.get("step") in (None, 0)]
    out = []
    for fr in firsts[:n_frames]:
        for cam in CAMERAS:
            kp = (fr.get("keypoints") or {}).get(cam)
            vis = (fr.get("visible") or {}).get(cam)
            out.append((folder / fr[cam], cam,
                        None if kp is None else np.asarray(kp, float),
                        np.zeros(5, bool) if vis is None else np.asarray(vis, bool),
                        true_arc_pixels(rig, needle, cam, fr)))
    return out


def _arc_distance(line, w, arc):
    """Mean distance (px) of weighted centreline points to the true arc polyline."""
    if line is None or arc is None or w is None or not np.any(w > 0):
        return None
    p = line[w > 0]
    dense = np.concatenate([np.linspace(arc[i], arc[i + 1], 8, endpoint=False) for i in range(len(arc) - 1)])
    d = np.linalg.norm(p[:, None, :] - dense[None, :, :], axis=2).min(1)
    return float(d.mean())


def make_detector(backend: str, weights=None, threads=None, device="auto"):
    if backend == "learned":
        from common.detector.inference import KeypointDetector
        return KeypointDetector(weights, device=device, threads=threads)
    if backend == "classical":
        from common.detector.classical import ClassicalDetector
        return ClassicalDetector()
    raise ValueError(f"unknown backend {backend!r} (learned or classical)")


def run(data, backend="learned", weights=None, n_frames=30, negatives=None, threads=None,
        repeat=5, picture=None, device="auto", progress=True) -> dict:
    from common.progress import progress_bar
    det = make_detector(backend, weights, threads, device)
    items = test_images(data, n_frames)
    if not items:
        raise DatasetError(f"{data}: no frames to test on")
    imgs = []
    for path, *_ in items:
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None:
            raise DatasetError(f"{path}: cannot read image")
        imgs.append(img)
    reset = getattr(det, "reset", lambda *a: None)
    for img in imgs[:3]:  # warm-up
        reset()
        det.detect(img, "left")
    errs, sure, cl_err, found, n_pos, cold_ms, track_ms, results = [], [], [], 0, 0, [], [], []
    for (path, cam, kp, vis, arc), img in progress_bar(list(zip(items, imgs)), desc=f"bench {backend}",
                                                show=progress, unit="img"):
        reset()
        t0 = time.perf_counter()
        k = det.detect(img, cam)
        cold_ms.append((time.perf_counter() - t0) * 1e3)
        results.append(k)
        if kp is None or vis.sum() < 2:
            continue
        n_pos += 1
        if not k.found:
            continue
        found += 1
        errs.append(np.where(vis, np.linalg.norm(k.uv - kp, axis=1), np.nan))
        sure.append(vis & (np.asarray(k.scores) >= SURE_SCORE))
        d = _arc_distance(k.centreline, k.centreline_w, arc)
        if d is not None:
            cl_err.append(d)
        for _ in range(repeat):  # tracking: the previous frame's box is kept
            t0 = time.perf_counter()
            det.detect(img, cam)
            track_ms.append((time.perf_counter() - t0) * 1e3)
    res = {"backend": backend, "data": str(data), "images": len(items), "with_needle": n_pos,
           "found": found, "detection_rate": found / max(1, n_pos)}
    if errs:
        e = np.asarray(errs)
        res.update({"kp_error_mean_px": float(np.nanmean(e)), "kp_error_median_px": float(np.nanmedian(e)),
                    "kp_error_p90_px": float(np.nanpercentile(e, 90)),
                    "kp_error_per_kp_px": dict(zip("ABCDE", (float(v) for v in np.nanmean(e, 0)))),
                    "kp_error_per_kp_median_px": dict(zip("ABCDE", (float(v) for v in np.nanmedian(e, 0))))})
        m = np.asarray(sure)   # the points the detector vouches for: what the pose nodes use
        if m.any():
            res.update({"kp_error_sure_mean_px": float(e[m].mean()), "kp_error_sure_median_px": float(np.median(e[m])),
                        "kp_sure_fraction": float(m.sum() / np.isfinite(e).sum())})
    if cl_err:
        res["centreline_error_mean_px"] = float(np.mean(cl_err))
        res["centreline_error_median_px"] = float(np.median(cl_err))
    res["cold_ms_mean"] = float(np.mean(cold_ms))
    res["cold_ms_median"] = float(np.median(cold_ms))
    if track_ms:
        res["tracking_ms_mean"] = float(np.mean(track_ms))
        res["tracking_ms_median"] = float(np.median(track_ms))
    if negatives:
        neg_items = test_images(negatives, 10 ** 6)
        fp = 0
        for path, cam, *_ in neg_items:
            img = cv2.imread(str(path), cv2.IMREAD_COLOR)
            reset()
            fp += int(det.detect(img, cam).found)
        res["negatives"] = len(neg_items)
        res["false_detections"] = fp
    if picture:
        save_picture(picture, items, imgs, results)
    return res


def save_picture(path, items, imgs, results, n=12):
    """Contact sheet: crops around the true needle with truth (green) and detection (red)."""
    tiles = []
    for (p, cam, kp, vis, arc), img, k in list(zip(items, imgs, results))[:n]:
        if kp is None:
            continue
        c = np.nanmean(kp, 0)
        side = int(max(120, 1.6 * np.ptp(kp, 0).max()))
        x0, y0 = int(c[0] - side / 2), int(c[1] - side / 2)
        M = np.array([[400 / side, 0, -x0 * 400 / side], [0, 400 / side, -y0 * 400 / side]])
        t = cv2.warpAffine(img, M, (400, 400), flags=cv2.INTER_LINEAR)
        s = 400 / side
        for j, (u, v) in enumerate(kp):
            cv2.circle(t, (int((u - x0) * s), int((v - y0) * s)), 5, (0, 255, 0), 1)
        if k.found:
            if k.centreline is not None:
                for (u, v), w in zip(k.centreline, k.centreline_w):
                    if w > 0:
                        cv2.circle(t, (int((u - x0) * s), int((v - y0) * s)), 1, (255, 128, 0), -1)
            for j, (u, v) in enumerate(k.uv):
                cv2.drawMarker(t, (int((u - x0) * s), int((v - y0) * s)), (0, 0, 255), cv2.MARKER_CROSS, 10, 1)
            cv2.putText(t, "A", (int((k.uv[0, 0] - x0) * s) + 6, int((k.uv[0, 1] - y0) * s)), 0, 0.5, (0, 0, 255), 1)
        else:
            cv2.putText(t, "not found", (10, 20), 0, 0.6, (0, 0, 255), 2)
        tiles.append(t)
    if not tiles:
        return
    while len(tiles) % 4:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + 4]) for i in range(0, len(tiles), 4)]
    cv2.imwrite(str(path), np.vstack(rows))


def format_report(r: dict) -> str:
    lines = [f"detector backend: {r['backend']}   test data: {r['data']}",
             f"needle found: {r['found']}/{r['with_needle']} ({100 * r['detection_rate']:.1f}%)"]
    if "negatives" in r:
        lines.append(f"false detections on needle-free images: {r['false_detections']}/{r['negatives']}")
    if "kp_error_mean_px" in r:
        per = "  ".join(f"{k} {v:.2f}" for k, v in r["kp_error_per_kp_px"].items())
        lines.append(f"keypoint error (visible points, px): mean {r['kp_error_mean_px']:.3f}  "
                     f"median {r['kp_error_median_px']:.3f}  p90 {r['kp_error_p90_px']:.3f}")
        lines.append(f"  per keypoint (mean px): {per}")
        if "kp_error_sure_mean_px" in r:
            lines.append(f"  points scored >= {SURE_SCORE} (what the pose nodes use; "
                         f"{100 * r['kp_sure_fraction']:.1f}% of the visible ones): mean "
                         f"{r['kp_error_sure_mean_px']:.3f}  median {r['kp_error_sure_median_px']:.3f}")
    if "centreline_error_mean_px" in r:
        lines.append(f"centreline distance to the true arc (px): mean {r['centreline_error_mean_px']:.3f}  "
                     f"median {r['centreline_error_median_px']:.3f}")
    lines.append(f"ms per 1920x1080 image: cold {r['cold_ms_mean']:.1f} (median {r['cold_ms_median']:.1f})"
                 + (f"  tracking {r['tracking_ms_mean']:.1f} (median {r['tracking_ms_median']:.1f})"
                    if "tracking_ms_mean" in r else ""))
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench detector", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="test dataset folder (e.g. data/test)")
    ap.add_argument("--backend", default="learned", choices=["learned", "classical"])
    add_weights(ap)
    ap.add_argument("--frames", type=int, default=30, help="needle poses to test (x2 cameras)")
    ap.add_argument("--negatives", default=None, help="folder of needle-free frames")
    ap.add_argument("--make-negatives", type=int, default=0, metavar="N",
                    help="render N needle-free stereo frames into --negatives if it does not exist")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--repeat", type=int, default=5, help="tracking-mode repetitions per image")
    ap.add_argument("--json", default=None, help="write the figures as JSON here")
    ap.add_argument("--picture", default=None, help="write a contact sheet PNG here")
    a = ap.parse_args(argv)
    try:
        if a.negatives and a.make_negatives and not (Path(a.negatives) / "frames.jsonl").is_file():
            from common.sim.generate import generate_needle_free
            generate_needle_free(a.negatives, a.make_negatives, seed=777, preset="test", progress=False)
        r = run(a.data, a.backend, a.weights, a.frames, a.negatives, a.threads, a.repeat, a.picture, a.device)
    except (DatasetError, ValueError, OSError, RuntimeError) as exc:
        print(f"needletrack bench detector: error: {exc}", file=sys.stderr)
        return 2
    print(format_report(r))
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
