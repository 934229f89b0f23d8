"""``needletrack dataset generate|generate-alt|generate-negatives``: render dataset folders from the
built-in scene or the second renderer (the other ``dataset`` subcommands: ``common.data.cli``,
``common.ros.cli``; the command itself: ``common.cli.dataset_main``)."""
from __future__ import annotations

import argparse

from common.cli_options import add_quiet
from common.geometry.ecm_kinematics import MULTIVIEW_STEP_RAD

PRESET_NAMES = ["none", "test", "train", "wide", "silicone", "liver", "random", "unseen"]   # common.sim.randomise.PRESETS (not imported: fast start)

STANDARD_TEST_SET = ("needletrack dataset generate --out data/test --sequences 30 --steps 5 "
                     "--seed 1000 --randomise test")


def _generate_args(p: argparse.ArgumentParser) -> None:
    """The arguments both scene generators take."""
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--sequences", type=int, required=True, help="number of needle poses")
    p.add_argument("--steps", type=int, default=1, help="endoscope poses per needle pose (default 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--format", default="jpg", choices=["jpg", "png"], help="image files (default jpg)")
    p.add_argument("--quality", type=int, default=95, help="JPEG quality (default 95)")
    p.add_argument("--thread", default="random", choices=["random", "none"],
                   help="suture thread: as the scene draws it (default), or none (a threadless twin of the same scenes)")
    p.add_argument("--overwrite", action="store_true", help="start over in a folder made with other settings")
    add_quiet(p)


def add_parsers(sub) -> dict:
    """The scene generators' subcommands of ``needletrack dataset``; returns their handlers."""
    g = sub.add_parser("generate", help="render a dataset folder from the built-in MuJoCo scene",
                       description="N needle poses (sequences), each seen from K endoscope poses (steps); "
                                   "between steps one random ECM joint (yaw, pitch or roll) moves 0.05 rad "
                                   "(--step-rad; a small step makes each sequence a video for the live bench). "
                                   "Resumable: rerun the same command after an interruption. "
                                   f"Standard test set: {STANDARD_TEST_SET}")
    _generate_args(g)
    g.add_argument("--randomise", default="train", choices=PRESET_NAMES,
                   help="randomisation preset (default train)")
    g.add_argument("--motion", default="none", choices=["none", "pickup", "handover", "throw", "suture", "mixed"],
                   help="none (default): the multi-view protocol; else each sequence is a moving take of "
                        "that instrument script at 30 Hz, as long as its script (--steps unused; mixed: "
                        "pickup, handover, throw, suture in turn; docs/simulation.md)")
    g.add_argument("--take-every", type=int, default=1, metavar="K",
                   help="with --motion: keep every K-th frame of each take (default 1: all, at 30 Hz); "
                        "for training sets, more takes for the same rendering time")
    g.add_argument("--arm-error", default="exact", metavar="SPEC",
                   help="with --motion: how the arms report the jaws: exact (default: as rendered) or dvrk "
                        "(a few mm and degrees: registration, a drift with the configuration, a jaw offset, "
                        "noise; the truth in T_world_jaw_truth), optionally with overrides, e.g. "
                        "dvrk:registration_mm=5,noise_mm=0.2 (docs/datasets.md)")
    g.add_argument("--jobs", type=int, default=2, help="render processes (default 2)")
    g.add_argument("--msaa", type=int, default=4, choices=[0, 2, 4, 8],
                   help="anti-aliasing samples (default 4; 0 renders ~2.5x faster with jagged thin wires)")
    g.add_argument("--step-rad", type=float, default=MULTIVIEW_STEP_RAD,
                   help=f"ECM joint step between a sequence's steps, rad (default {MULTIVIEW_STEP_RAD:g}, the "
                        "paper's multi-view protocol; e.g. 0.003 for a slowly moving endoscope video)")

    a = sub.add_parser("generate-alt", help="render a dataset folder with the second, independent renderer",
                       description="Like generate, but rendered by common/sim/alt_render.py (numpy/OpenCV z-buffer "
                                   "rasteriser, no MuJoCo) with its own needle meshes, tissue, lights and ECM base: "
                                   "a check that models and methods do not overfit the built-in scene. "
                                   "Same multi-view protocol; resumable.")
    _generate_args(a)
    a.add_argument("--supersample", type=int, default=3, choices=[1, 2, 3, 4],
                   help="samples per pixel side around the needle (default 3)")

    n = sub.add_parser("generate-negatives", help="render needle-free frames of the built-in scene",
                       description="Frames with the needle moved out of sight (instruments, thread, tissue "
                                   "stay), no keypoint visible: negatives for training the detector and for "
                                   "measuring its false detections. With --randomise random (or unseen): hard "
                                   "negatives, jaws of every instrument kind, some near the camera, threads "
                                   "without a needle, specular streaks, folds, cuts and stains.")
    n.add_argument("--out", required=True, help="output folder")
    n.add_argument("--frames", type=int, required=True, help="number of stereo frames")
    n.add_argument("--seed", type=int, default=777)
    n.add_argument("--randomise", default="train", choices=PRESET_NAMES,
                   help="randomisation preset (default train)")
    n.add_argument("--width", type=int, default=1920)
    n.add_argument("--height", type=int, default=1080)
    n.add_argument("--pale-thread", type=float, default=None, metavar="SHARE",
                   help="share of frames with the undyed, needle-pale thread (default: the preset's 1 in 5)")
    add_quiet(n)
    return {"generate": _generate, "generate-alt": _generate_alt, "generate-negatives": _generate_negatives}


def _generate(args) -> int:
    import time

    import common.sim.render  # noqa: F401  (selects the headless GL backend first)
    from common.sim.arm_error import arm_error_config
    from common.sim.generate import GenerateConfig, generate
    arm_error = arm_error_config(args.arm_error).spec()      # a bad spec: a ValueError naming the field
    cfg = GenerateConfig(args.sequences, args.steps, args.seed, args.randomise, args.width, args.height,
                         args.format, args.quality, args.msaa, args.step_rad, args.thread, args.motion,
                         args.take_every, arm_error)
    t0 = time.time()
    n = generate(args.out, cfg, jobs=args.jobs, progress=not args.quiet, overwrite=args.overwrite)
    shape = f"{args.steps} steps" if args.motion == "none" else f"{args.motion} takes"
    print(f"{args.out}: {n} frames ({args.sequences} sequences x {shape}, "
          f"{args.width}x{args.height}, randomise={args.randomise}, seed={args.seed}) "
          f"in {time.time() - t0:.1f} s")
    return 0


def _generate_alt(args) -> int:
    import time

    from common.sim.alt_generate import AltGenerateConfig, generate_alt
    cfg = AltGenerateConfig(args.sequences, args.steps, args.seed, args.width, args.height, args.format,
                            args.quality, args.supersample, args.thread)
    t0 = time.time()
    n = generate_alt(args.out, cfg, progress=not args.quiet, overwrite=args.overwrite)
    print(f"{args.out}: {n} frames ({args.sequences} sequences x {args.steps} steps, {args.width}x{args.height}, "
          f"second renderer, seed={args.seed}) in {time.time() - t0:.1f} s")
    return 0


def _generate_negatives(args) -> int:
    from common.sim.generate import generate_needle_free
    generate_needle_free(args.out, args.frames, args.seed, args.randomise, not args.quiet, args.pale_thread,
                         args.width, args.height)
    return 0
