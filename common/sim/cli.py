"""``needletrack dataset generate|generate-alt|generate-negatives|check|show|from-bag|to-bag|distort``: make,
verify, convert and look at dataset folders (the ROS bag commands: docs/ros.md)."""
from __future__ import annotations

import argparse
import sys

from common.geometry.ecm_kinematics import MULTIVIEW_STEP_RAD

PRESET_NAMES = ["none", "test", "train", "wide"]   # common.sim.randomise.PRESETS (not imported: fast start)

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
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="needletrack dataset", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="render a dataset folder from the built-in MuJoCo scene",
                       description="N needle poses (sequences), each seen from K endoscope poses (steps); "
                                   "between steps one random ECM joint (yaw, pitch or roll) moves 0.05 rad "
                                   "(--step-rad; a small step makes each sequence a video for the live bench). "
                                   "Resumable: rerun the same command after an interruption. "
                                   f"Standard test set: {STANDARD_TEST_SET}")
    _generate_args(g)
    g.add_argument("--randomise", default="train", choices=PRESET_NAMES,
                   help="randomisation preset (default train)")
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
                                   "measuring its false detections.")
    n.add_argument("--out", required=True, help="output folder")
    n.add_argument("--frames", type=int, required=True, help="number of stereo frames")
    n.add_argument("--seed", type=int, default=777)
    n.add_argument("--randomise", default="train", choices=PRESET_NAMES,
                   help="randomisation preset (default train)")
    n.add_argument("--pale-thread", type=float, default=None, metavar="SHARE",
                   help="share of frames with the undyed, needle-pale thread (default: the preset's 1 in 5)")
    n.add_argument("--quiet", action="store_true", help="no progress bar")

    c = sub.add_parser("check", help="validate a folder against the dataset spec and its ground truth")
    c.add_argument("path")
    c.add_argument("--tol-px", type=float, default=0.1, help="max keypoint reprojection error (px)")
    c.add_argument("--no-images", action="store_true", help="skip decoding every image")

    s = sub.add_parser("show", help="contact sheet of frames with the ground-truth keypoints")
    s.add_argument("path")
    s.add_argument("--out", required=True, help="output PNG")
    s.add_argument("--frames", type=int, default=12, help="number of frames (evenly spaced)")
    s.add_argument("--cols", type=int, default=4)
    s.add_argument("--camera", default="left", choices=["left", "right"])
    s.add_argument("--tile-width", type=int, default=480)
    _ros_parsers(sub)
    return p


def _ros_parsers(sub) -> None:
    fb = sub.add_parser("from-bag", help="convert a ROS 1 .bag or ROS 2 .db3/.mcap bag into a dataset folder",
                        description="Stereo pairs by header stamp, intrinsics, camera poses, ECM joints/pose and the "
                                    "needle's ground truth where the bag has it (docs/ros.md: presets, topic maps, "
                                    "frames and units).")
    fb.add_argument("bag", help="ROS 1 .bag file, ROS 2 .db3/.mcap file or bag folder")
    fb.add_argument("--preset", choices=["ambf", "dvrk"], help="topic names and conventions")
    fb.add_argument("--topics", metavar="MAP.yaml", help="topic map (overrides the preset's keys)")
    fb.add_argument("--out", required=True, help="output dataset folder")
    fb.add_argument("--format", default="png", choices=["jpg", "png"], help="image files (default png)")
    fb.add_argument("--max-frames", type=int, default=0, help="stop after this many frames (0: all)")
    fb.add_argument("--stride", type=int, default=1, help="keep every Nth stereo frame")
    fb.add_argument("--quiet", action="store_true", help="no progress bar")
    tb = sub.add_parser("to-bag", help="write a dataset folder as a bag in the AMBF or dVRK conventions",
                        description="ambf: ROS 1 .bag, rgb8, ambf_msgs states, decimetres (2021-22 challenge); "
                                    "dvrk: ROS 2 MCAP with camera_info, /ECM topics, a registration file and a topic "
                                    "map beside it (common/ros/synth.py).")
    tb.add_argument("dataset")
    tb.add_argument("--convention", required=True, choices=["ambf", "dvrk"])
    tb.add_argument("--out", required=True, help="the bag (ambf: FILE.bag; dvrk: a bag folder)")
    tb.add_argument("--unit", choices=["m", "dm", "cm", "mm"], help="position unit (ambf default dm, dvrk m)")
    tb.add_argument("--compressed", action="store_true", help="sensor_msgs/CompressedImage (JPEG)")
    tb.add_argument("--encoding", help="raw image encoding (ambf default rgb8, dvrk bgr8)")
    tb.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"], help="ROS 2 storage (default mcap)")
    tb.add_argument("--max-frames", type=int, default=0)
    di = sub.add_parser("distort", help="the distorted twin of a pinhole dataset (same K, lens distortion added)")
    di.add_argument("dataset")
    di.add_argument("--out", required=True)
    di.add_argument("--dist", required=True, metavar="K1,K2,P1,P2[,K3]", help="OpenCV distortion coefficients")
    di.add_argument("--format", default="png", choices=["jpg", "png"])
    di.add_argument("--quiet", action="store_true")


def _ros(args) -> int:
    import time
    if args.cmd == "from-bag":
        from common.ros.convert import from_bag
        r = from_bag(args.bag, args.out, args.preset, args.topics, image_format=args.format,
                     max_frames=args.max_frames, stride=max(1, args.stride), progress=not args.quiet)
        print(f"{args.out}: {r['frames']} stereo frames {r['image_size'][0]}x{r['image_size'][1]} from {args.bag} "
              f"in {r['seconds']:.1f} s ({r['frames'] / max(r['seconds'], 1e-9):.1f} frames/s); ground truth in "
              f"{r['with_truth']}; unit {r['unit']}; unpaired images {r['unpaired']}")
        for role, topic in r["topics"].items():
            print(f"  {role}: {topic}")
        for topic, n in r["refused"].items():
            print(f"  skipped {n} message(s) on {topic} (the reason is logged above)")
        if r["recovered"]:
            print(f"warning: {args.bag}: {r['recovered']}", file=sys.stderr)
        return 0
    if args.cmd == "to-bag":
        from common.ros.synth import dataset_to_bag
        t0 = time.perf_counter()
        r = dataset_to_bag(args.dataset, args.out, args.convention, unit=args.unit, compressed=args.compressed,
                           encoding=args.encoding, storage=args.storage, max_frames=args.max_frames)
        print(f"{args.out}: {r['frames']} stereo frames in the {args.convention} convention "
              f"in {time.perf_counter() - t0:.1f} s")
        if "topics_file" in r:
            print(f"  topic map: {r['topics_file']} (registration {r['registration']})")
        return 0
    from common.ros.synth import distort_dataset
    try:
        dist = [float(x) for x in args.dist.split(",")]
    except ValueError:
        dist = []
    if len(dist) not in (4, 5, 8):
        raise ValueError(f"--dist: expected 4, 5 or 8 numbers, got {args.dist!r}")
    n = distort_dataset(args.dataset, args.out, dist, args.format, progress=not args.quiet)
    print(f"{args.out}: {n} frames, distortion {dist}")
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from common.data.dataset import DatasetError
    try:
        if args.cmd == "generate":
            return _generate(args)
        if args.cmd == "generate-alt":
            return _generate_alt(args)
        if args.cmd == "generate-negatives":
            from common.sim.generate import generate_needle_free
            generate_needle_free(args.out, args.frames, args.seed, args.randomise, not args.quiet,
                                 args.pale_thread)
            return 0
        if args.cmd == "check":
            return _check(args)
        if args.cmd == "show":
            return _show(args)
        if args.cmd in ("from-bag", "to-bag", "distort"):
            return _ros(args)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 2


def _generate(args) -> int:
    import time

    import common.sim.render  # noqa: F401  (selects the headless GL backend first)
    from common.sim.generate import GenerateConfig, generate
    cfg = GenerateConfig(args.sequences, args.steps, args.seed, args.randomise, args.width, args.height,
                         args.format, args.quality, args.msaa, args.step_rad, args.thread)
    t0 = time.time()
    n = generate(args.out, cfg, jobs=args.jobs, progress=not args.quiet, overwrite=args.overwrite)
    print(f"{args.out}: {n} frames ({args.sequences} sequences x {args.steps} steps, "
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


def _check(args) -> int:
    from common.data.dataset import Dataset, check_dataset
    ds = Dataset(args.path)
    rep = check_dataset(ds, tol_px=args.tol_px, images=not args.no_images, progress=sys.stderr.isatty())
    print(f"{args.path}: {rep.frames} frames, {ds.meta.image_size[0]}x{ds.meta.image_size[1]}, "
          f"{len(ds.sequences())} sequences; ground truth in {rep.with_truth} frames")
    if rep.with_truth:
        print(f"  keypoint reprojection: max {rep.max_reproj_px:.2e} px, mean {rep.mean_reproj_px:.2e} px "
              f"(tolerance {args.tol_px} px)")
    if ds.arm is not None:
        print(f"  ECM forward kinematics vs T_world_ecm: max {rep.max_fk_m:.2e} m")
    if not args.no_images:
        print(f"  images decoded: {rep.images_checked}")
    for w in rep.warnings:
        print(f"  warning: {w}")
    for e in rep.errors:
        print(f"  error: {e}")
    print("OK" if rep.ok else f"FAILED ({len(rep.errors)} errors)")
    return 0 if rep.ok else 1


def _show(args) -> int:
    import cv2

    from common.data.dataset import Dataset
    ds = Dataset(args.path)
    sheet = contact_sheet(ds, n=args.frames, cols=args.cols, camera=args.camera, tile_width=args.tile_width)
    if not cv2.imwrite(args.out, sheet):
        raise OSError(f"could not write {args.out}")
    print(f"{args.out}: {sheet.shape[1]}x{sheet.shape[0]} contact sheet of {min(args.frames, len(ds))} frames")
    return 0


# ---------------------------------------------------------------- contact sheet

# A..E: red, orange, yellow, green, blue (BGR)
KEYPOINT_COLOURS = ((40, 40, 230), (0, 150, 255), (0, 230, 230), (60, 200, 60), (230, 120, 30))


def draw_keypoints(img, uv, visible, scale: float = 1.0, offset=(0.0, 0.0), radius: int = 4):
    """Draw A..E on ``img`` in place: filled discs where visible, rings where not."""
    import cv2
    import numpy as np
    for k in range(5):
        p = (np.asarray(uv[k], float) - offset) * scale
        if not np.all(np.isfinite(p)):
            continue
        c = (int(round(p[0] * 16)), int(round(p[1] * 16)))
        if visible is None or bool(visible[k]):
            cv2.circle(img, c, radius * 16, (0, 0, 0), -1, cv2.LINE_AA, shift=4)
            cv2.circle(img, c, (radius - 1) * 16, KEYPOINT_COLOURS[k], -1, cv2.LINE_AA, shift=4)
        else:
            cv2.circle(img, c, (radius + 2) * 16, (0, 0, 0), 3, cv2.LINE_AA, shift=4)
            cv2.circle(img, c, (radius + 2) * 16, KEYPOINT_COLOURS[k], 1, cv2.LINE_AA, shift=4)


def contact_sheet(ds, n: int = 12, cols: int = 4, camera: str = "left", tile_width: int = 480):
    """BGR contact sheet of ``n`` evenly spaced frames: ground-truth keypoints A..E (filled =
    visible, ring = occluded or outside), the needle's box, and a zoomed inset of the needle."""
    import cv2
    import numpy as np
    n = max(1, min(n, len(ds)))
    idx = np.unique(np.linspace(0, len(ds) - 1, n).round().astype(int))
    w, h = ds.meta.image_size
    s = tile_width / w
    th = int(round(h * s))
    tiles = []
    for i in idx:
        fr = ds[int(i)]
        img = ds.image(fr, camera)
        tile = cv2.resize(img, (tile_width, th), interpolation=cv2.INTER_AREA)
        uv = None if fr.keypoints is None else fr.keypoints[camera]
        vis = None if fr.visible is None else fr.visible[camera]
        box = None if fr.bbox is None else fr.bbox.get(camera)
        if box is not None:
            cv2.rectangle(tile, (int(box[0] * s), int(box[1] * s)), (int(box[2] * s), int(box[3] * s)),
                          (255, 255, 255), 1)
        if uv is not None:
            # inset: the needle region magnified, in the top-right corner
            lo, hi = uv.min(axis=0), uv.max(axis=0)
            half = max(float(np.max(hi - lo)) * 0.8, 20.0)
            cx, cy = (lo + hi) / 2
            x0, y0 = int(max(0, cx - half)), int(max(0, cy - half))
            x1, y1 = int(min(w, cx + half)), int(min(h, cy + half))
            if x1 - x0 > 4 and y1 - y0 > 4:
                isz = int(tile_width * 0.4)
                z = isz / max(x1 - x0, y1 - y0)
                crop = cv2.resize(img[y0:y1, x0:x1], (int((x1 - x0) * z), int((y1 - y0) * z)),
                                  interpolation=cv2.INTER_CUBIC)
                draw_keypoints(crop, uv, vis, z, (x0, y0), radius=max(3, int(isz / 40)))
                ch, cw = crop.shape[:2]
                tile[2:2 + ch, tile_width - cw - 2:tile_width - 2] = crop
                cv2.rectangle(tile, (tile_width - cw - 3, 1), (tile_width - 2, ch + 2), (255, 255, 255), 1)
            draw_keypoints(tile, uv, vis, s, radius=3)
        label = f"#{fr.index}"
        if fr.sequence is not None:
            label += f" seq {fr.sequence} step {fr.step}"
        cv2.putText(tile, label, (6, th - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(tile, label, (6, th - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    cols = max(1, min(cols, len(tiles)))
    rows = (len(tiles) + cols - 1) // cols
    sheet = np.full((28 + rows * (th + 4), cols * (tile_width + 4), 3), 32, np.uint8)
    x = 8
    for k, name in enumerate("ABCDE"):
        cv2.circle(sheet, (x + 6, 14), 6, KEYPOINT_COLOURS[k], -1, cv2.LINE_AA)
        cv2.putText(sheet, name + (" (tip)" if k == 0 else " (tail)" if k == 4 else ""), (x + 16, 19),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (230, 230, 230), 1, cv2.LINE_AA)
        x += 90 if k in (0, 4) else 50
    cv2.putText(sheet, f"{camera} camera; filled = visible, ring = occluded/outside", (x + 10, 19),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (200, 200, 200), 1, cv2.LINE_AA)
    for t, tile in enumerate(tiles):
        r, c = divmod(t, cols)
        y0, x0 = 28 + r * (th + 4), c * (tile_width + 4)
        sheet[y0:y0 + th, x0:x0 + tile_width] = tile
    return sheet


if __name__ == "__main__":
    sys.exit(main())
