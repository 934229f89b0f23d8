"""``needletrack dataset from-bag|to-bag|distort``: ROS bags to dataset folders and back, and the
distorted twin of a folder (docs/ros.md)."""
from __future__ import annotations

import sys

from common.cli_options import add_quiet


def add_parsers(sub) -> dict:
    """The ROS subcommands of ``needletrack dataset``; returns their handlers."""
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
    add_quiet(fb)
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
    add_quiet(di)
    return {name: _ros for name in ("from-bag", "to-bag", "distort")}


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
