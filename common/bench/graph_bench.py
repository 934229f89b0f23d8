"""``needletrack bench [graph] [--dataset DIR]``: the live pipeline's speed, end to end.

The tracking graph as deployed, i.e. with newest-only inputs (``common.evaluation.pipeline_graph``:
replay -> one detector process per camera -> refine -> fusion over refined poses, with ecm; with
``--tracker``, or on a folder of moving takes (``needle_at_rest: false``), also the tracker beside
the fusion, whose ``tracked`` poses are then the final ones, docs/tracking.md),
fed by the replay source looping over a 1920x1080 stereo dataset as fast as the graph goes
(``--rate max``, the default: closed loop, the replay sends the next frame once both cameras'
keypoints of the last one are out, ``rate: paced``), or at ``--rate`` Hz (30: the endoscope's). ``--all-methods`` adds the other pose methods
(epnp average and joint, triangulate, fusion over joint poses), as in an evaluation; they are
not on the path to the final pose. After a warm-up it measures for ``--duration`` seconds:

- frames/s published by the source, stereo frames/s through the last single-frame pose node
  (paired and processed, with or without a pose: with a detector that misses the needle most
  frames give none) and final poses/s (end to end: the fusion's, or the tracker's);
- latency from frame publish (``CameraImage.stamp_ns``, wall clock) to the final pose, p50/p95/p99,
  and to each stage's output (keypoints, each pose method);
- each node's CPU share and CPU time per published frame (from /proc over the window), its
  handler times (its stats: p50/p99 over the messages whose handler published, i.e. a frame's
  work: a detector's images, not its calibration or ground truth; the replay's step is not a
  handler, its CPU ms/frame is its cost) and dropped inputs.

``--viewer``: what the live viewer (nodes/viewer.py, docs/viewer.md) costs: the graph is measured
twice, without and then with a viewer node attached as in dataflow.yaml (every method's pose, the
images, keypoints, truth; its page and Rerun logging on, Rerun's web viewer process off), and the
difference is printed: the viewer's CPU ms per published frame, fused poses/s and latency.

Prints a table; ``--json FILE`` also writes the figures. Without ``--dataset`` it uses
``data/test`` when present, else generates ``data/bench`` once (30 frames).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from common.cli_options import add_dataset, add_weights
from common.evaluation.graph_speed import ensure_dataset, measure, report


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="needletrack bench graph", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_dataset(p, looped=True)
    p.add_argument("--detector", default="learned", choices=("learned", "classical", "oracle"))
    add_weights(p, "--model", learned_only=True)
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="a detector parameter (repeatable), e.g. --param stride=1")
    p.add_argument("--rate", default="max",
                   help="'max' (default): as fast as the graph goes (closed loop: the next frame once "
                        "both cameras' keypoints of the last one are out; the detectors take every "
                        "frame), or a replay rate in Hz (e.g. 30, the endoscope's)")
    p.add_argument("--decode", action="store_true",
                   help="the replay decodes the images once at start-up and sends them raw (bgr8, by "
                        "shared memory), as a live capture card delivers them: the detectors then do "
                        "not pay the dataset's JPEG decoding (9 ms per 1080p image)")
    p.add_argument("--duration", type=float, default=20.0, help="measured seconds (default 20)")
    p.add_argument("--warmup", type=float, default=4.0, help="seconds ignored after the first frame")
    p.add_argument("--one-detector", action="store_true",
                   help="one detector process for both cameras (default: one per camera)")
    p.add_argument("--no-refine", action="store_true",
                   help="leave out the refinement node (then the final pose is multiview over pnp_joint)")
    p.add_argument("--tracker", action="store_true",
                   help="also run the tracker (method tracked, then the final pose), as dataflow.yaml does; "
                        "the default on a folder of moving takes (needle_at_rest: false)")
    p.add_argument("--tracker-param", action="append", default=[], metavar="KEY=VALUE",
                   help="a tracker parameter (repeatable), e.g. --tracker-param max_wait=1")
    p.add_argument("--all-methods", action="store_true",
                   help="also run the pose methods not on the path to the final pose (epnp average, "
                        "triangulate, ...), as an evaluation does")
    p.add_argument("--viewer", action="store_true",
                   help="measure the graph without and with a viewer node (its params as in "
                        "dataflow.yaml) and print what it costs")
    p.add_argument("--viewer-param", action="append", default=[], metavar="KEY=VALUE",
                   help="with --viewer: a viewer parameter (repeatable), e.g. --viewer-param rate_hz=10")
    p.add_argument("--json", help="also write the figures to this JSON file")
    p.add_argument("--plot", help="also draw the latencies (per stage) and each node's CPU per frame "
                                  "into this PNG")
    p.add_argument("--log", help="write the graph's log here (default: a temporary file)")
    return p


def viewer_report(without: dict, with_viewer: dict) -> str:
    """What the viewer costs: its CPU, and the change in fused poses/s and latency."""
    f = lambda x, nd=1: "n/a" if x is None else f"{x:.{nd}f}"
    v = with_viewer["per_node"].get("viewer", {})
    a, b = without["throughput_hz"], with_viewer["throughput_hz"]
    change = None if not a else 100 * (b - a) / a
    la, lb = without["latency_ms"], with_viewer["latency_ms"]
    share = v.get("cpu_share")
    vp = with_viewer.get("viewer_params", {})
    return "\n".join([
        "needletrack bench --viewer: the viewer's cost (pictures "
        f"{vp.get('width', '?')}x{vp.get('height', '?')} at {vp.get('rate_hz', '?')} Hz)",
        f"  viewer CPU            {f(v.get('cpu_ms_per_frame'), 2)} ms per published frame "
        f"({f(None if share is None else 100 * share, 0)}% of one core); handler p50 "
        f"{f(v.get('proc_ms_p50'), 2)} ms, dropped inputs {v.get('dropped', 'n/a')}",
        f"  fused poses/s         {f(a)} without -> {f(b)} with ({f(change)}%)   [target: at most 10% fewer]",
        f"  latency p50           {f(la['p50'])} -> {f(lb['p50'])} ms; p99 {f(la['p99'])} -> {f(lb['p99'])} ms",
        f"  frames published      {f(without['published_hz'])} -> {f(with_viewer['published_hz'])} /s "
        f"(replay rate {with_viewer['rate']})"])


def plot(r: dict, samples: dict, path) -> None:
    """Latency distribution per stage (from frame publish, ms) beside each node's CPU time per
    published frame (ms), with the issue 6 targets."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [3, 2]})
    for name, lat in samples.items():
        if lat:
            x = np.sort(lat)
            ax.plot(x, np.arange(1, len(x) + 1) / len(x), label=f"{name} (p50 {np.median(x):.0f} ms)")
    ax.axvline(50, color="k", ls="--", lw=1, label="target p50 <= 50 ms")
    ax.axhline(0.5, color="grey", lw=0.5)
    ax.set_xlabel("latency from frame publish (ms)")
    ax.set_ylabel("share of frames")
    ax.set_xlim(0, max(120.0, min(400.0, max((max(v) for v in samples.values() if v), default=0))))
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"{r['throughput_hz']:.1f} final poses/s ({r['final_method']}), rate {r['rate']}")
    nodes = r["per_node"]
    names = [n for n in nodes if nodes[n]["cpu_ms_per_frame"] is not None]
    cpu = [nodes[n]["cpu_ms_per_frame"] for n in names]
    bx.barh(names, cpu, color="tab:blue", label="CPU per published frame")
    bx.scatter([nodes[n]["proc_ms_p50"] for n in names], names, color="tab:red", zorder=3,
               label="handler p50 (wall)")
    bx.set_xlabel("ms")
    steal = "" if r.get("cpu_steal") is None else f", steal {100 * r['cpu_steal']:.0f}%"
    bx.set_title(f"CPU {100 * r['cpu_total']:.0f}% of {100 * (r['cpus'] or 1)}%{steal}; "
                 f"{sum(cpu):.1f} ms per frame in all")
    bx.legend(fontsize=8, loc="center right")
    fig.suptitle(f"needletrack bench: {r['dataset']}, detector {r['detector']}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    argv = list(argv or [])
    if argv and argv[0] == "graph":
        argv = argv[1:]
    args = _parser().parse_args(argv)
    from common.data.dataset import DatasetError
    from common.evaluation.pipeline_graph import GraphRunError
    try:
        dataset = ensure_dataset(args.dataset)
    except (DatasetError, RuntimeError) as exc:
        print(f"needletrack bench: {exc}", file=sys.stderr)
        return 2
    import tempfile
    log_path = args.log or tempfile.mktemp(prefix="needletrack-bench-", suffix=".log")
    try:
        with open(log_path, "w") as log:
            r = measure(args, dataset, log)
            r_viewer = measure(args, dataset, log, viewer=True) if args.viewer else None
    except DatasetError as exc:
        print(f"needletrack bench: {dataset}: {exc}", file=sys.stderr)
        return 2
    except (GraphRunError, RuntimeError) as exc:
        print(f"needletrack bench: {exc}; last lines of {log_path}:", file=sys.stderr)
        print("".join(Path(log_path).read_text().splitlines(True)[-25:]), file=sys.stderr)
        return 1
    samples = r.pop("latency_samples_ms", None)
    print(report(r))
    if r_viewer is not None:
        r_viewer.pop("latency_samples_ms", None)
        print("\nwith the viewer:\n" + report(r_viewer) + "\n\n" + viewer_report(r, r_viewer))
        r = {**r, "with_viewer": r_viewer}
    if args.plot and samples is not None:
        plot(r, samples, args.plot)
        print(f"wrote {args.plot}")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=2) + "\n")
        print(f"wrote {args.json}")
    if not args.log:
        os.unlink(log_path)
    return 0
