"""``needletrack bench sim``: how fast the built-in scene renders stereo frames, and their size.

Prints (1) a per-stage breakdown in one process (new needle pose, stereo colour render,
segmentation/depth window, ground truth, degradations, image encoding) and (2) end-to-end
``dataset generate`` throughput with the requested number of processes: stereo frames per
second and bytes per frame on disk (both images + the frames.jsonl line).
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

from common.sim.cli import PRESET_NAMES


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench sim", description=__doc__)
    ap.add_argument("--frames", type=int, default=30, help="stereo frames per measurement (default 30)")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--jobs", type=int, default=2, help="processes for the end-to-end run (default 2)")
    ap.add_argument("--steps", type=int, default=5, help="endoscope poses per needle pose (default 5)")
    ap.add_argument("--randomise", default="test", choices=PRESET_NAMES)
    ap.add_argument("--format", default="jpg", choices=["jpg", "png"])
    ap.add_argument("--msaa", type=int, default=4, help="anti-aliasing samples (default 4; 0 = off)")
    ap.add_argument("--skip-breakdown", action="store_true")
    args = ap.parse_args(argv)

    import cv2
    import numpy as np

    import common.sim.render  # noqa: F401  (headless GL before mujoco)
    from common.sim.generate import GenerateConfig, generate, scene_meta
    from common.sim.randomise import degrade_stereo, get_preset, plan_sequence
    from common.sim.render import SceneRenderer

    print(f"sim bench: {args.width}x{args.height} stereo, randomise={args.randomise}, msaa={args.msaa}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    if not args.skip_breakdown:
        meta = scene_meta(args.width, args.height, "")
        preset = get_preset(args.randomise)
        r = SceneRenderer()
        t = {"new needle pose (load)": [], "colour render, 2 cameras": [], "segmentation window, 2 cameras": [],
             "ground truth": [], "degradations": [], "JPEG q95 encode, 2 images": []}
        n_seq = max(2, args.frames // args.steps)
        rng = np.random.default_rng(0)
        plan_sequence(0, 0, 1, preset, meta.rig, meta.needle, meta.arm)  # warm caches
        cpu0 = wall0 = None
        frames_timed = 0
        for s in range(n_seq + 1):
            if s == 1:
                cpu0, wall0 = time.process_time(), time.perf_counter()
            plan = plan_sequence(1, s, args.steps, preset, meta.rig, meta.needle, meta.arm, msaa=args.msaa)
            t0 = time.perf_counter()
            r.load(plan.spec)
            t1 = time.perf_counter()
            if s > 0:  # the first load compiles the model and creates the GL context
                t["new needle pose (load)"].append(t1 - t0)
            for q in plan.joints:
                T = meta.arm.T_world_ecm(q)
                rd = r.render(T)
                b = time.perf_counter()
                r.ground_truth(T, rd)
                c = time.perf_counter()
                imgs = degrade_stereo({k: v.bgr for k, v in rd.items()}, rng, preset, jpeg=False)
                d = time.perf_counter()
                for img in imgs.values():
                    cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
                e = time.perf_counter()
                if s > 0:
                    frames_timed += 1
                    t["colour render, 2 cameras"].append(r.last_timings["colour"])
                    t["segmentation window, 2 cameras"].append(r.last_timings["window"])
                    t["ground truth"].append(c - b)
                    t["degradations"].append(d - c)
                    t["JPEG q95 encode, 2 images"].append(e - d)
        print("\nper-stage median, one process:")
        for k, v in t.items():
            print(f"  {k:34s} {1000 * float(np.median(v)):8.1f} ms")
        per_frame = sum(float(np.median(v)) for k, v in t.items() if k != "new needle pose (load)")
        per_frame += float(np.median(t["new needle pose (load)"])) / args.steps
        print(f"  {'per stereo frame (steps=%d)' % args.steps:34s} {1000 * per_frame:8.1f} ms "
              f"-> {1 / per_frame:.2f} frames/s in one process")
        cpu = (time.process_time() - cpu0) / frames_timed
        wall = (time.perf_counter() - wall0) / frames_timed
        print(f"  CPU time per stereo frame (all threads): {1000 * cpu:.0f} ms (wall {1000 * wall:.0f} ms) "
              f"-> at most {(os.cpu_count() or 1) / cpu:.1f} frames/s on {os.cpu_count()} idle cores")
        r.close()

    tmp = tempfile.mkdtemp(prefix="needletrack_bench_sim_")
    try:
        n_seq = max(1, args.frames // args.steps)
        cfg = GenerateConfig(n_seq, args.steps, 12345, args.randomise, args.width, args.height, args.format,
                             msaa=args.msaa)
        t0 = time.perf_counter()
        n = generate(tmp, cfg, jobs=args.jobs, progress=False)
        dt = time.perf_counter() - t0
        size = sum(os.path.getsize(os.path.join(dp, f)) for dp, _, fs in os.walk(tmp) for f in fs
                   if f.endswith((".jpg", ".png", ".jsonl")))
        print(f"\ndataset generate, {args.jobs} process(es), {n} stereo frames "
              f"({n_seq} needle poses x {args.steps} steps), start-up included:")
        print(f"  {n / dt:.2f} stereo {args.width}x{args.height} frames/s  ({dt:.1f} s)")
        print(f"  {size / n / 1e6:.3f} MB per stereo frame on disk ({args.format}, both images + frames.jsonl line)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    import sys
    sys.exit(main())
