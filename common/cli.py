"""``needletrack``: the command line. Subcommands are dispatched lazily from ``COMMANDS``.

Each target is ``"module:function"`` with ``function(argv: list[str]) -> int``; add a line to
``COMMANDS`` (or ``BENCHES`` for ``needletrack bench NAME``) to add a command. A module is
imported only when its command runs.
"""
from __future__ import annotations

import importlib
import sys
from typing import Optional

COMMANDS = {
    # name: (target, one-line help)
    "launch": ("common.runtime.launcher:launch_main", "run a graph, one process per node (default dataflow.yaml)"),
    "ps": ("common.runtime.tools:ps_main", "live nodes of a graph with rates and error counts"),
    "echo": ("common.runtime.tools:echo_main", "print decoded messages on a key"),
    "hz": ("common.runtime.tools:hz_main", "print the rate of messages on a key"),
    "swap": ("common.runtime.tools:swap_main", "replace a running node (make-before-break)"),
    "cmd": ("common.runtime.tools:cmd_main", "send a Command to a node"),
    "validate": ("common.runtime.tools:validate_main", "check a graph YAML and list every error"),
    "describe": ("common.runtime.describe:describe_main", "a node's inputs, outputs and params (docs/nodes.md)"),
    "certs": ("common.runtime.certs:certs_main", "make a test CA and a TLS graph's certificates"),
    "bench": ("common.cli:bench_main", "benchmarks: transport, sim, detector, graph, refine, geometry"),
    "dataset": ("common.cli:dataset_main", "make, check, convert and look at dataset folders"),
    "detect": ("common.adapt.detect_files:main", "the detector on your own images, videos or folders: JSON lines and overlays"),
    "train": ("common.detector.train:main", "train the keypoint detector"),
    "eval": ("common.evaluation.cli:main", "evaluate pose pipelines"),
    "adapt": ("common.adapt.adapt:main", "fit the detector to a scene from recordings without ground truth"),
    "finetune": ("common.adapt.finetune:main", "fine-tune the detector on frames labelled by hand (needletrack label), with a before/after report"),
    "results": ("common.evaluation.results_page:main", "evaluate the documented sets and write docs/results.md"),
    "record": ("common.ros.record:record_main", "record a running graph to MCAP with ROS 2 schemas"),
    "label": ("common.label.server:main", "label a dataset folder's frames by hand in the browser (docs/label.md)"),
    "view": ("common.viewer.cli:main", "open a recording (.rrd) in Rerun's web viewer on 127.0.0.1"),
    "screenshot": ("common.viewer.shot:main", "launch a graph briefly and screenshot its viewer's page (docs/launch.png)"),
}

BENCHES = {
    "transport": ("common.bench.transport_bench:main", "1080p stereo frames between two node processes"),
    "restart": ("common.bench.restart_bench:main", "seconds without poses after kill -9 of the camera"),
    "sim": ("common.bench.sim_bench:main", "simulator rendering"),
    "detector": ("common.bench.detector_bench:main", "keypoint detector speed and accuracy"),
    "held": ("common.bench.held_bench:main", "the detector on moving takes, by the share of the needle seen"),
    "tracker": ("common.bench.tracker_bench:main", "the needle tracker on the motion scripts' takes (no rendering)"),
    "graph": ("common.bench.graph_bench:main", "the full graph end to end"),
    "label": ("common.bench.label_bench:main", "hand labels (needletrack label) by simulated clicks on a folder with truth"),
    "refine": ("common.bench.refine_bench:main", "dense pose refinement speed and accuracy (synthetic)"),
    "end-identity": ("common.bench.end_identity_bench:main", "tip vs tail: the detector's end identity on dataset folders"),
    "familiarity": ("common.bench.familiarity_bench:main", "how unlike the training looks each folder's images are (--fit: the reference)"),
    "presence": ("common.bench.presence_bench:main", "needles reported where there is none or in the wrong place (--fit: the presence gate)"),
    "fuzz": ("common.robustness.fuzz:main", "poison payloads into every input of every node (in process)"),
    "viewer-http": ("common.robustness.http_fuzz:main", "the viewer page's server against floods, bursts, resets, idle clients"),
    "soak": ("common.robustness.soak:main", "the default graph from a replay for a long run: accounting, RSS, restarts"),
    "geometry": ("common.bench.geometry_bench:main", "pose methods (PnP, triangulation, fusion) vs keypoint noise, on the oracle"),
    "ros-bag": ("common.bench.ros_bench:bag_main", "ROS bag read speed (stereo frames/s)"),
    "ros-live": ("common.bench.ros_bench:live_main", "latency the live ROS 2 path adds (p50/p99) against the native graph"),
}


DATASET_COMMANDS = ("common.sim.cli", "common.data.cli", "common.ros.cli")
"""The packages whose ``add_parsers(sub) -> {subcommand: handler}`` make ``needletrack dataset``:
the scene generators, the folder checks, the ROS conversions (each imports its heavy parts only
when its subcommand runs)."""


def dataset_main(argv: Optional[list] = None) -> int:
    """``needletrack dataset SUBCOMMAND``: 0 on success, 1 with one ``error:`` line on a bad folder,
    bag or argument value (``DatasetError``, ``ValueError``, ``OSError``), 2 on bad usage."""
    import argparse
    p = argparse.ArgumentParser(prog="needletrack dataset",
                                description="Make, check, convert and look at dataset folders (docs/dataset.md; "
                                            "the ROS bag commands: docs/ros.md).")
    sub = p.add_subparsers(dest="cmd", required=True)
    handlers = {}
    for mod in DATASET_COMMANDS:
        handlers.update(importlib.import_module(mod).add_parsers(sub))
    args = p.parse_args(sys.argv[1:] if argv is None else list(argv))
    from common.data.dataset import DatasetError
    try:
        return handlers[args.cmd](args)
    except (DatasetError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


def _call(target: str, argv: list) -> int:
    mod_name, func = target.split(":")
    try:
        mod = importlib.import_module(mod_name)
    except ModuleNotFoundError as exc:
        if exc.name and (exc.name == mod_name or mod_name.startswith(exc.name + ".")):
            print(f"needletrack: {mod_name} is not available yet ({exc})", file=sys.stderr)
            return 1
        raise
    rc = getattr(mod, func)(list(argv))
    return 0 if rc is None else int(rc)


def _usage(table: dict, prog: str) -> str:
    w = max(len(k) for k in table)
    return f"usage: {prog} COMMAND [ARGS...]\n\ncommands:\n" + "\n".join(
        f"  {k.ljust(w)}  {h}" for k, (_, h) in table.items()) + f"\n\n'{prog} COMMAND --help' for a command's options."


def bench_main(argv: list) -> int:
    """``needletrack bench [NAME] [ARGS]``; no NAME (or options first, e.g. ``--dataset DIR``) runs ``graph``."""
    if argv and argv[0] in ("-h", "--help"):
        print(_usage(BENCHES, "needletrack bench"))
        return 0
    if not argv or argv[0].startswith("-"):
        name, rest = "graph", argv
    else:
        name, rest = argv[0], argv[1:]
    if name not in BENCHES:
        print(f"needletrack bench: unknown benchmark {name!r}\n\n" + _usage(BENCHES, "needletrack bench"), file=sys.stderr)
        return 2
    return _call(BENCHES[name][0], rest)


def main(argv: Optional[list] = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage(COMMANDS, "needletrack"))
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"needletrack: unknown command {name!r}\n\n" + _usage(COMMANDS, "needletrack"), file=sys.stderr)
        return 2
    return _call(COMMANDS[name][0], rest)


if __name__ == "__main__":
    sys.exit(main())
