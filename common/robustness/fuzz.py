"""``needletrack bench fuzz``: poison payloads into every input of every node of a graph, in
process, the way the runtime hands them over (``decode`` with the input's type, then
``Node.deliver``), between frames of a clean stream.

For each node of the graph (default: dataflow.yaml; the ``sim`` camera is a source whose only
input is its command key) and each of its inputs (and its ``cmd`` key; a viewer's page too,
``@http``: poison HTTP requests over sockets to 127.0.0.1, ``common.robustness.http_fuzz``), a fresh offline node gets
a clean warm-up stream, then ``--per-input`` poison payloads, one clean frame after every
``--clean-every`` of them, then clean frames until it publishes again. Payload kinds: random
bytes, truncated and bit-flipped valid payloads, type-confused fields, missing/extra fields,
wrong schema or version, non-finite and huge values (NaN/inf, 1e300, 2^64, 10^6-element arrays,
ndarray headers claiming 2^40 elements), far-future and negative ``seq``, and new ``epoch``s
(alone and as consistent runs). Figures: payloads, refused at decode, delivered, crashes (an
exception other than MessageError, from the codec or a handler), poses published that break
the pose invariant, and the clean frames each node needed to publish again after the poison
(at 30 Hz, 60 frames = 2 s).

``--bags N``: damaged bag files (cut short, corrupt chunks, bad CRCs and lengths, unfinished)
read through the bag reader (``common/ros/bagfuzz.py``).

The clean stream is the oracle's: a still needle seen by the default rig while the ECM yaws,
through the ecm, detector (oracle keypoints; an image backend gets a 1080p JPEG) and pose nodes.

The ROS 2 way in (``--node ros2``, included by default): ``common.robustness.fuzz_ros``. The
clean stream and the poison payloads: ``common.robustness.fuzz_payloads``.
"""
from __future__ import annotations

import argparse
import dataclasses
import io
import random
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Optional

import numpy as np

from common.cli_options import add_dataset
from common.robustness.fuzz_payloads import FRAME_HZ, KINDS, CleanStream, poison
from common.runtime.messages import (
    Command,
    MessageError,
    PoseEstimate,
    decode,
    encode,
    pose_invariant_error,
)

RECOVERY_LIMIT = 60          # clean frames (2 s at 30 Hz) a node may need to publish again


# ====================================================================== the run

@dataclasses.dataclass
class InputResult:
    node: str
    input: str
    payloads: int = 0
    refused: int = 0
    delivered: int = 0
    crashes: int = 0
    invalid_published: int = 0
    recovery_frames: Optional[int] = None      # clean frames until the node published again
    first_crash: str = ""


def _node_specs(graph):
    from common.runtime.node import Node, node_class
    for spec in graph.nodes:
        if not spec.module:
            continue
        cls = node_class(spec.module)
        if isinstance(cls, type) and issubclass(cls, Node):
            yield spec, cls


class _NoPacing:
    def wait(self, *a, **k):
        pass

    def delay(self):
        return 0.0


def _make(cls, spec):
    node = cls.offline(spec.params, wired=spec.inputs.keys(), node_id=spec.id)
    if hasattr(node, "out"):
        node.out = io.StringIO()               # the monitor's lines
    return node


def _feed_frame(node, spec, stream: CleanStream, seq: int, epoch) -> None:
    """One clean frame on every wired input (calibration included), in the graph's order."""
    for name, src in spec.inputs.items():
        msg = stream.message(src, seq, epoch)
        if msg is not None:
            node.deliver(name, decode(encode(msg), node.INPUTS[name]))


def _check_published(node, start: int) -> int:
    bad = 0
    for _, m in node.published[start:]:
        if isinstance(m, PoseEstimate):
            try:
                decode(encode(m))
                bad += pose_invariant_error(m, node.pose_volume_m) is not None
            except MessageError:
                bad += 1
    return bad


def fuzz_http(spec, cls, n: int, seed: int) -> InputResult:
    """The viewer's page (``@http``): ``n`` poison requests over sockets to 127.0.0.1
    (``common.robustness.http_fuzz``), the node's own server with its params."""
    from common.robustness.http_fuzz import fuzz_page
    node = cls.offline({**spec.params, "port": 0, "rerun": False}, wired=spec.inputs.keys(), node_id=spec.id)
    try:
        r = fuzz_page(node.page, n, seed)
    finally:
        node.teardown()
    return InputResult(spec.id, "@http", r["payloads"], r["refused"], r["delivered"], r["crashes"], 0,
                       r["recovery"], r["first_crash"])


def fuzz_input(spec, cls, input_name: str, stream: CleanStream, n: int, seed: int,
               clean_every: int = 50, warmup: int = 12) -> InputResult:
    """Fuzz one input (or ``@cmd``, or the viewer's ``@http``) of one node; see the module docstring."""
    if input_name == "@http":
        return fuzz_http(spec, cls, n, seed)
    rng, np_rng = random.Random(seed), np.random.default_rng(seed)
    res = InputResult(spec.id, input_name)
    node = _make(cls, spec)
    if cls.is_source() and hasattr(node, "pacer"):
        node.pacer = _NoPacing()                # no pacing offline
    epoch, seq = rng.randrange(1, 2 ** 56), 0
    for _ in range(warmup):
        _feed_frame(node, spec, stream, seq, epoch)
        seq += 1
    if input_name == "@cmd":
        args = {"T_world_needle": np.eye(4).tolist(), "seed": 3} if spec.module == "sim" else {"x": 0.01}
        expect, template = Command, Command(rng.choice(["place_needle", "set_motion", "reset", "x"]), args)
    else:
        expect, template = cls.INPUTS[input_name], None
    start = len(node.published)
    run = 0
    for i in range(n):
        src = spec.inputs.get(input_name, "")
        clean = template or stream.message(src, seq, epoch) or stream.message(src, seq + 1, epoch)
        if clean is None:
            break
        kind = KINDS[i % len(KINDS)] if run == 0 else "epoch_run"
        payload = poison(clean, kind, rng, np_rng)
        if kind == "epoch_run" and run == 0:
            run = rng.randint(2, 6)             # a consistent foreign stream for a few messages
        run = max(0, run - 1)
        res.payloads += 1
        try:
            msg = decode(payload, expect)
        except MessageError:
            res.refused += 1
            msg = None
        except Exception as exc:                # the codec must raise nothing else
            res.crashes += 1
            res.first_crash = res.first_crash or f"decode: {type(exc).__name__}: {exc}"[:300]
            msg = None
        if msg is not None:
            res.delivered += 1
            try:
                node.deliver(input_name, msg)
            except Exception as exc:
                res.crashes += 1
                res.first_crash = res.first_crash or f"{kind}: on_{input_name}: {type(exc).__name__}: {exc}"[:300]
        if (i + 1) % clean_every == 0:
            _feed_frame(node, spec, stream, seq, epoch)
            seq += 1
    res.invalid_published = _check_published(node, start)
    # recovery: clean frames until the node publishes (a sink: until its handlers run clean)
    if cls.OUTPUTS:
        mark = len(node.published)
        for k in range(1, RECOVERY_LIMIT * 3 + 1):
            try:
                if cls.is_source():
                    node.step()                 # a source: its next frame
                else:
                    _feed_frame(node, spec, stream, seq, epoch)
            except Exception as exc:
                res.crashes += 1
                res.first_crash = res.first_crash or f"recovery: {type(exc).__name__}: {exc}"[:300]
            seq += 1
            if len(node.published) > mark:
                res.recovery_frames = k
                break
    else:
        res.recovery_frames = 0
    return res


def run_fuzz(graph, per_input: int, seed: int = 0, nodes: Optional[list] = None, log=print) -> list:
    stream = CleanStream(seed=seed)
    results = []
    for j, (spec, cls) in enumerate(_node_specs(graph)):
        if nodes and spec.id not in nodes:
            continue
        inputs = list(spec.inputs) + ["@cmd"] + (["@http"] if spec.module == "viewer" else [])
        for i, name in enumerate(inputs):
            t0 = time.perf_counter()
            r = fuzz_input(spec, cls, name, stream, per_input, seed * 7919 + j * 101 + i)
            results.append(r)
            log(result_line(r, time.perf_counter() - t0))
    return results


def result_line(r: InputResult, seconds: float) -> str:
    """One fuzzed input's line of the report."""
    return (f"  {r.node:15s} {r.input:14s} {r.payloads:6d} payloads  {r.refused:6d} refused  "
            f"{r.delivered:6d} delivered  {r.crashes} crashes  {r.invalid_published} invalid published  "
            f"recovery {r.recovery_frames if r.recovery_frames is not None else 'NEVER'} frames  "
            f"({seconds:.1f} s)" + (f"\n    first crash: {r.first_crash}" if r.first_crash else ""))


def summary(results: list) -> dict:
    rec = [r.recovery_frames for r in results]
    return {"inputs": len(results), "payloads": sum(r.payloads for r in results),
            "refused": sum(r.refused for r in results), "delivered": sum(r.delivered for r in results),
            "crashes": sum(r.crashes for r in results),
            "invalid_poses_published": sum(r.invalid_published for r in results),
            "never_recovered": sum(x is None for x in rec),
            "max_recovery_frames": max((x for x in rec if x is not None), default=0)}


def live_check(args) -> int:
    """``--live``: the default graph in processes (camera: a replay at 30 Hz, as the soak), a
    clean period, then ``--poison-s`` seconds of poison payloads of every kind on every input
    key at ``--poison-hz``; prints, per output, the longest gap between messages in the clean
    period and the time from the end of the poison to its first message; and restarts."""
    import tempfile

    import zenoh  # noqa: F401

    from common.evaluation.graph_speed import ensure_dataset
    from common.evaluation.pipeline_graph import GraphRun
    from common.robustness.soak import soak_graph
    from common.runtime.graph import graph_from_dict, output_key

    doc = soak_graph(ensure_dataset(args.dataset), 30.0)
    graph = graph_from_dict(doc)
    stream = CleanStream(seed=args.seed)
    rng, np_rng = random.Random(args.seed), np.random.default_rng(args.seed)
    targets = sorted({src for spec in graph.nodes for src in spec.inputs.values()})
    # the outputs watched (not no_pose: only a frame without a pose has one)
    outputs = [f"{spec.id}/{o}" for spec in graph.nodes for o in spec.outputs
               if spec.id != "camera" and o not in ("points", "no_pose")] + ["camera/truth"]
    arrivals: dict = {k: [] for k in outputs}
    log_path = tempfile.mktemp(prefix="fuzz-live-", suffix=".log")
    with open(log_path, "w") as log, GraphRun(doc, log, source="camera") as run:
        run.start_consumers()
        session = run.client_session()

        def cb_for(key):
            def cb(_sample):
                arrivals[key].append(time.monotonic())
            return cb
        subs = [session.declare_subscriber(output_key(graph.name, *k.split("/")), cb_for(k)) for k in outputs]
        run.start_source()
        time.sleep(args.clean_s)                 # warm-up and the clean period
        t_clean0 = time.monotonic() - args.clean_s / 2
        t_poison0 = time.monotonic()
        kinds_sent: Counter = Counter()
        seq = 0
        while time.monotonic() - t_poison0 < args.poison_s:
            key = rng.choice(targets)
            clean = stream.message(key, seq) or stream.message(key, seq + 1)
            seq += 1
            if clean is None:
                continue
            kind = rng.choice(KINDS)
            session.put(output_key(graph.name, *key.split("/")), poison(clean, kind, rng, np_rng))
            kinds_sent[kind] += 1
            time.sleep(1.0 / args.poison_hz)
        t_stop = time.monotonic()
        time.sleep(args.after_s)
        failed = run.failed()
        restarts = {nid: s.restarts for l in (run.main, run.src) for nid, s in l.slots.items()}
        for s in subs:
            s.undeclare()
    print(f"fuzz --live: {sum(kinds_sent.values())} poison payloads in {args.poison_s:g} s on "
          f"{len(targets)} keys ({', '.join(targets)}); graph log {log_path}")
    worst = 0.0
    for k in outputs:
        ts = arrivals[k]
        clean = [t for t in ts if t_clean0 <= t < t_poison0]
        gaps = [b - a for a, b in zip(clean, clean[1:])]
        during = sum(t_poison0 <= t < t_stop for t in ts)
        after = [t - t_stop for t in ts if t >= t_stop]
        first = after[0] if after else None
        worst = max(worst, first if first is not None else float("inf"))
        print(f"  {k:22s} clean: {len(clean):4d} msgs, longest gap {max(gaps) if gaps else float('nan'):5.2f} s;"
              f" during poison {during:4d} msgs; first after it {'NEVER' if first is None else f'{first:.2f} s'}")
    print(f"fuzz --live: every output published again within {worst:.2f} s of the poison stopping; "
          f"restarts {sum(restarts.values())}; failed nodes {failed or 'none'}")
    return 0 if worst <= 2.0 and not any(restarts.values()) and not failed else 1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench fuzz", description=__doc__.split("\n\n")[0])
    ap.add_argument("--graph", default=str(Path(__file__).resolve().parents[2] / "dataflow.yaml"))
    ap.add_argument("--per-input", type=int, default=10_000, help="poison payloads per input (10000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--node", action="append", help="only these node ids (repeatable)")
    ap.add_argument("--bags", type=int, default=200,
                    help="damaged bag files per base bag (MCAP, ROS 1) read through the bag reader (200; 0: none)")
    ap.add_argument("--live", action="store_true",
                    help="instead: poison the default graph in processes (see live_check)")
    add_dataset(ap, looped=True, what="--live: the replay's folder")
    ap.add_argument("--clean-s", type=float, default=25.0, help="--live: seconds before the poison")
    ap.add_argument("--poison-s", type=float, default=10.0, help="--live: seconds of poison")
    ap.add_argument("--poison-hz", type=float, default=200.0, help="--live: poison payloads per second")
    ap.add_argument("--after-s", type=float, default=8.0, help="--live: seconds watched after the poison")
    ap.add_argument("--intruder", action="store_true",
                    help="instead: a process without the run's credentials sends fake poses, handovers and "
                         "a swap to the default graph (common/robustness/intruder.py)")
    ap.add_argument("--uid", type=int, help="--intruder: the intruder runs as this user (needs root)")
    ap.add_argument("--open", action="store_true", help="--intruder: the graph with zenoh.open: true")
    args = ap.parse_args(argv)
    if args.intruder:
        from common.robustness.intruder import intruder_check
        return intruder_check(args.graph, args.clean_s, args.poison_s, args.uid, args.open)
    if args.live:
        return live_check(args)
    import logging

    from common.runtime.graph import load_graph
    logging.disable(logging.CRITICAL)          # the nodes log every refused message
    graph = load_graph(args.graph)
    t0 = time.perf_counter()
    print(f"fuzz: {args.graph}, {args.per_input} poison payloads per input (kinds: {', '.join(KINDS)})")
    results = run_fuzz(graph, args.per_input, args.seed, args.node)
    if not args.node or "ros2" in args.node:    # the ROS 2 way in (not in dataflow.yaml)
        from common.robustness.fuzz_ros import run_fuzz_ros2
        results += run_fuzz_ros2(args.per_input, args.seed)
    s = summary(results)
    print(f"fuzz: {s['payloads']} payloads into {s['inputs']} inputs of {len({r.node for r in results})} nodes "
          f"in {time.perf_counter() - t0:.0f} s: {s['refused']} refused at decode, {s['delivered']} delivered; "
          f"{s['crashes']} crashes, {s['invalid_poses_published']} invalid poses published, "
          f"{s['never_recovered']} inputs never recovered; publishing again after at most "
          f"{s['max_recovery_frames']} clean frames ({s['max_recovery_frames'] / FRAME_HZ:.2f} s at {FRAME_HZ:g} Hz)")
    ok = s["crashes"] == 0 and s["invalid_poses_published"] == 0 and s["never_recovered"] == 0 \
        and s["max_recovery_frames"] <= RECOVERY_LIMIT
    if args.bags and not args.node:
        from common.ros.bagfuzz import fuzz_bags
        b = fuzz_bags(args.bags, args.seed)
        print(f"fuzz: {b.files} damaged bag files ({', '.join(sorted(b.kinds))}) in {b.seconds:.0f} s: "
              f"{b.read} read to the end ({b.recovered} recovered from unfinished files), {b.refused} refused "
              f"with a BagError; {b.crashes} crashes" + (f" (first: {b.first_crash})" if b.crashes else ""))
        ok = ok and b.crashes == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
