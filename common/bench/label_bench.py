"""``needletrack bench label --dataset DIR``: how good hand labels are, by simulated clicks on a
folder with ground truth.

The folder is copied without its truth (``dataset strip-truth``; images hard-linked) and each
frame is labelled through the page's own code path (``LabelApp.save``: the fit through the
clicks, the wire snapped in the images, the label written to frames.jsonl) from clicks within
``--end-px`` of the true tip and tail and ``--wire-px`` of the true arc
(``common.label.simulate``), a frame no camera sees as no needle. The labels are then read back
and scored against the truth. Prints: the keypoints' error (visible ones: mean, median, max,
the share within 1 px), the poses written (the share of frames) and their error (median, max,
the share within 1 mm and 2 deg), how honest their stated covariance is (NEES median, chi-square(6)'s
is 5.35), the fit's time per frame and the clicks per frame. ``--detector NAME``: frames the
backend finds in both cameras are accepted as it proposes them (one key, the page's start), the
others clicked; how many of those proposals were right (every keypoint within 1 px) is counted.
``--json`` writes the figures. ``--out DIR`` keeps the labelled copy (a hand-label folder made
without a person, e.g. for ``needletrack finetune``'s tests and learning curves).
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

from common.cli_options import add_dataset, add_quiet


def run(dataset: str, end_px: float = 1.0, wire_px: float = 2.0, wire: int = 2, seed: int = 0,
        max_frames: int = 0, snap: bool = True, progress: bool = True, detector: str = "none",
        params: dict | None = None, out: str | None = None) -> dict:
    """The figures (see the module docstring) of ``dataset``'s frames (the first ``max_frames``;
    0: all) labelled by simulated clicks; with a ``detector`` (a backend's name), each frame whose
    proposal finds the needle in both cameras is accepted as proposed instead (one key), and
    the share of those within 1 px of the truth is counted. ``out``: label a copy there (a new
    folder) and keep it; None: a temporary copy."""
    import numpy as np
    from common.data.dataset import Dataset
    from common.data.writer import without_truth
    from common.frames import CAMERAS
    from common.geometry.transforms import R_to_rotvec, inv_T, pose_error
    from common.label.fit import CameraClicks, LabelError, clicks_from_keypoints
    from common.label.proposals import detect_folder
    from common.label.server import LabelApp
    from common.label.simulate import simulated_clicks
    from common.label.store import LabelStore
    from common.progress import progress_bar

    truth = Dataset(dataset)
    frames = [fr for fr in truth.frames if fr.T_ecm_needle is not None]
    if max_frames:
        frames = frames[:max_frames]
    if not frames:
        raise ValueError(f"{dataset}: no frame with T_world_needle and T_world_ecm to label by simulation")
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory(prefix="label-bench-") as tmp:
        work = Path(out) if out else Path(tmp) / "work"
        without_truth(truth.path, str(work))
        store = LabelStore(str(work))
        props = None if detector == "none" else detect_folder(store.ds, detector, dict(params or {}), progress)
        app = LabelApp(store, props)
        times, clicks_n, failed, accepted = [], [], [], set()
        for fr in progress_bar(frames, desc="labelling", unit="frame", show=progress):
            prop = props[fr.index] if props else None
            start = "none"
            if prop and all(prop[c]["found"] for c in CAMERAS):
                clicks, start = clicks_from_keypoints({c: prop[c]["uv"] for c in CAMERAS}), "proposal"
                accepted.add(fr.index)
            else:
                clicks = simulated_clicks(truth.rig, truth.needle, fr.T_ecm_needle, rng, end_px, wire_px, wire,
                                          fr.visible)
            t0 = time.perf_counter()
            try:
                if clicks is None:
                    app.save(fr.index, {c: CameraClicks(unseen=True) for c in CAMERAS}, no_needle=True)
                else:
                    app.save(fr.index, clicks, snap=snap, start=start)
            except LabelError as exc:
                failed.append(f"frame {fr.index}: {exc}")
                continue
            times.append(time.perf_counter() - t0)
            clicks_n.append(0 if clicks is None or start == "proposal" else sum(k.count for k in clicks.values()))
        labelled = Dataset(str(work))
    kp_err, pose_err, nees, posed, right = [], [], [], 0, 0
    for fr in frames:
        lab = labelled[fr.index]
        if lab.label is None or lab.keypoints is None:
            continue
        worst = 0.0
        for c in CAMERAS:
            seen = lab.visible[c] & (fr.visible[c] if fr.visible is not None else True)
            e = np.linalg.norm(lab.keypoints[c] - fr.keypoints[c], axis=1)[seen]
            kp_err += e.tolist()
            worst = max(worst, float(e.max(initial=0.0)))
        right += fr.index in accepted and worst < 1.0
        if lab.T_world_needle is not None:
            posed += 1
            T = inv_T(lab.T_world_ecm) @ lab.T_world_needle
            dt, dr = pose_error(T, fr.T_ecm_needle)
            pose_err.append((dt * 1e3, math.degrees(dr)))
            d = np.concatenate([R_to_rotvec(T[:3, :3] @ fr.T_ecm_needle[:3, :3].T), T[:3, 3] - fr.T_ecm_needle[:3, 3]])
            cov = np.asarray(lab.label["covariance"], float)
            nees.append(float(d @ np.linalg.solve(cov, d)))
    kp = np.array(kp_err)
    pe = np.array(pose_err).reshape(-1, 2)
    q = lambda a, f: float(f(a)) if len(a) else float("nan")
    return {
        "dataset": str(dataset), "frames": len(frames), "failed": failed, "end_px": end_px, "wire_px": wire_px,
        "wire_points": wire, "snap": snap,
        "keypoint_px": {"mean": q(kp, np.mean), "median": q(kp, np.median), "max": q(kp, np.max),
                        "within_1px": q(kp, lambda a: np.mean(a < 1.0)), "n": int(len(kp))},
        "posed_share": posed / len(frames),
        "pose_mm": {"median": q(pe[:, 0], np.median), "max": q(pe[:, 0], np.max)},
        "pose_deg": {"median": q(pe[:, 1], np.median), "max": q(pe[:, 1], np.max)},
        "pose_within_1mm_2deg": q(pe, lambda a: np.mean((a[:, 0] < 1.0) & (a[:, 1] < 2.0))),
        "nees_median": q(np.array(nees), np.median),
        "fit_ms": {"median": q(np.array(times) * 1e3, np.median), "max": q(np.array(times) * 1e3, np.max)},
        "clicks_per_frame": q(np.array(clicks_n), np.mean),
        "detector": detector, "proposals_accepted": len(accepted), "proposals_within_1px": right,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="needletrack bench label", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_dataset(p)
    p.add_argument("--end-px", type=float, default=1.0, help="tip and tail clicks within this of the truth (px)")
    p.add_argument("--wire-px", type=float, default=2.0, help="wire clicks within this of the true arc (px)")
    p.add_argument("--wire", type=int, default=2, help="wire clicks per camera (default 2)")
    p.add_argument("--no-snap", action="store_true", help="fit the clicks alone (the page's key s)")
    p.add_argument("--max-frames", type=int, default=0, help="label only the first N frames")
    p.add_argument("--detector", default="none",
                   help="accept this backend's proposals as they are where it finds the needle in both "
                        "cameras (one key), and count those within 1 px of the truth (default none)")
    p.add_argument("--detector-param", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="also write the figures here")
    p.add_argument("--out", metavar="DIR", help="label a copy in this new folder and keep it (a hand-label "
                                                "folder without a person; --max-frames: the rest unlabelled)")
    add_quiet(p)
    a = p.parse_args(argv)
    from common.runtime.graph import parse_param
    r = run(a.dataset, a.end_px, a.wire_px, a.wire, a.seed, a.max_frames, not a.no_snap, not a.quiet,
            a.detector, dict(parse_param(t) for t in a.detector_param), a.out)
    k, pm, pd = r["keypoint_px"], r["pose_mm"], r["pose_deg"]
    print(f"label bench ({r['dataset']}, {r['frames']} frames; clicks: tip and tail within {a.end_px:g} px, "
          f"{a.wire} wire points within {a.wire_px:g} px, snap {'on' if r['snap'] else 'off'}):")
    print(f"  keypoints: mean {k['mean']:.2f} px, median {k['median']:.2f}, max {k['max']:.2f}, "
          f"within 1 px {100 * k['within_1px']:.1f}% of {k['n']}")
    print(f"  poses written: {100 * r['posed_share']:.0f}% of the frames; error median {pm['median']:.2f} mm "
          f"{pd['median']:.2f} deg, max {pm['max']:.2f} mm {pd['max']:.2f} deg; within 1 mm and 2 deg "
          f"{100 * r['pose_within_1mm_2deg']:.0f}%; NEES median {r['nees_median']:.1f} (chi-square(6): 5.35)")
    print(f"  fit and save: {r['fit_ms']['median']:.0f} ms a frame (median), {r['fit_ms']['max']:.0f} max; "
          f"{r['clicks_per_frame']:.1f} clicks a frame")
    if a.detector != "none":
        print(f"  {a.detector}'s proposals accepted with one key: {r['proposals_accepted']} frames, "
              f"{r['proposals_within_1px']} of them with every keypoint within 1 px of the truth")
    for f in r["failed"]:
        print(f"  not labelled: {f}")
    if a.out:
        print(f"  the labelled copy: {a.out}")
    if a.json:
        Path(a.json).write_text(json.dumps(r, indent=1))
    return 0
