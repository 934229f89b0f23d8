"""``needletrack bench restart``: how long the graph is without poses after ``kill -9`` of its camera.

Launches a graph (default ``dataflow.yaml`` without its viewer, on a free loopback port) through
the real launcher, waits for poses on ``--pose`` keys, then ``kill -9``s the ``--node`` (the
camera) ``--kills`` times and prints, per kill, when (seconds after the kill) each step of the
recovery happened:

- ``exit``: the launcher saw the process gone; ``spawn``: the new process started (from its
  first stats: stamp minus uptime; before the kill for a warm spare, ``spare: true``, counted
  from its takeover); ``live``: its liveliness token (its ``setup()`` is done);
- ``frame``: its first frame (``joints``, a new epoch); ``keypoints``: the first keypoints of the
  new stream; ``pose``: the first pose of the new stream on each ``--pose`` key.

The figure is ``pose`` (the issue's target: under 2 s); the steps say where the time goes.
"""
from __future__ import annotations

import argparse
import io
import json
import os
import signal
import statistics
import sys
import threading
import time
from pathlib import Path


def bench_graph(path: str = "dataflow.yaml", node: str = "camera"):
    """The graph at ``path`` (``dataflow.yaml``: the repository's) without its viewer nodes,
    with a unique name on a free loopback port."""
    from common.evaluation.pipeline_graph import free_port
    from common.runtime.graph import REPO_ROOT, load_graph
    p = Path(path)
    if not p.exists() and path == "dataflow.yaml":
        p = REPO_ROOT / "dataflow.yaml"
    g = load_graph(p)
    g.nodes = [n for n in g.nodes if n.module != "viewer"]
    g.name = f"restart{os.getpid()}"
    g.zenoh.listen = [f"tcp/127.0.0.1:{free_port()}"]
    g.node(node)
    return g


def measure(graph, node: str, pose_keys: list, kills: int, settle_s: float, log) -> list:
    """Per kill, the recovery steps in seconds after the kill (see the module docstring)."""
    import zenoh

    from common.runtime.graph import live_key, stats_key
    from common.runtime.zenoh_session import zenoh_config
    from common.runtime.launcher import Launcher
    from common.runtime.messages import MessageError, NodeStats, decode
    launcher = Launcher(graph, out=log)
    launcher.start()
    runner = threading.Thread(target=launcher.run, daemon=True)
    runner.start()
    events: dict = {}
    lock = threading.Lock()
    spawn: dict = {}
    latest: dict = {}           # key -> the newest epoch seen on it

    def mark(what, epoch=None):
        now = time.monotonic()
        with lock:
            events.setdefault((what, epoch), now)

    def on_frame(key):
        def cb(sample):
            try:
                msg = decode(sample.payload.to_bytes())
            except MessageError:
                return
            latest[key] = getattr(msg, "epoch", None)
            mark(key, latest[key])
        return cb

    def on_stats(sample):
        try:
            st = decode(sample.payload.to_bytes(), NodeStats)
        except MessageError:
            return
        if st.node == node and st.pid not in spawn:
            spawn[st.pid] = time.monotonic() - st.uptime_s

    session = zenoh.open(zenoh_config(launcher.graph, role="node"))
    src = graph.node(node)
    frame_key = next((o for o in ("joints", "calib", "left") if o in src.outputs), src.outputs[0])
    kp_keys = [f"{n.id}/{o}" for n in graph.nodes if n.module == "detector" for o in n.outputs]
    subs = [session.declare_subscriber(graph.resolve_key(k), on_frame(k))
            for k in [f"{node}/{frame_key}"] + kp_keys + pose_keys]
    subs.append(session.declare_subscriber(stats_key(graph.name), on_stats))
    subs.append(session.liveliness().declare_subscriber(
        live_key(graph.name, node), lambda s: mark("live") if s.kind == zenoh.SampleKind.PUT else None))
    rows = []
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not any(k[0] in pose_keys for k in events):
            time.sleep(0.1)
        if not any(k[0] in pose_keys for k in events):
            raise RuntimeError(f"no pose on {pose_keys} within 300 s")
        for i in range(kills):
            time.sleep(settle_s)
            with lock:
                events.clear()
            old = launcher.slots[node].proc
            old_epochs = {latest.get(f"{node}/{frame_key}")}
            t_kill = time.monotonic()
            os.kill(old.pid, signal.SIGKILL)
            t_exit = None
            t_end = t_kill + 60
            while time.monotonic() < t_end:
                p = launcher.slots[node].proc
                if t_exit is None and (p is None or p is not old):
                    t_exit = time.monotonic()
                with lock:
                    new_epochs = {e for (w, e) in events if w == f"{node}/{frame_key}" and e is not None} - old_epochs
                    done = new_epochs and all(any(w == k and e in new_epochs for (w, e) in events)
                                              for k in pose_keys)
                if done:
                    break
                time.sleep(0.02)
            with lock:
                ev = dict(events)
            ep = min(new_epochs, key=lambda e: ev[(f"{node}/{frame_key}", e)]) if new_epochs else None

            def first(key):
                t = ev.get((key, ep))
                return None if t is None else round(t - t_kill, 3)
            p = launcher.slots[node].proc
            row = {"kill": i + 1, "exit": None if t_exit is None else round(t_exit - t_kill, 3),
                   "spawn": round(spawn[p.pid] - t_kill, 3) if p is not None and p.pid in spawn else None,
                   "live": None if ev.get(("live", None)) is None else round(ev[("live", None)] - t_kill, 3),
                   "frame": first(f"{node}/{frame_key}"),
                   "keypoints": min([t for t in (first(k) for k in kp_keys) if t is not None], default=None),
                   **{f"pose {k}": first(k) for k in pose_keys}}
            rows.append(row)
            print("  " + "  ".join(f"{k} {'-' if v is None else v}" for k, v in row.items()), flush=True)
    finally:
        for s in subs:
            try:
                s.undeclare()
            except Exception:
                pass
        session.close()
        launcher.stop()
        runner.join(30)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench restart", description=__doc__.split("\n\n")[0])
    ap.add_argument("--graph", default="dataflow.yaml", help="graph YAML (default dataflow.yaml; its viewer is left out)")
    ap.add_argument("--node", default="camera", help="the node to kill -9 (default camera)")
    ap.add_argument("--pose", action="append", help="pose keys to wait for (default refine/pose, fusion/pose)")
    ap.add_argument("--kills", type=int, default=3)
    ap.add_argument("--settle-s", type=float, default=12.0,
                    help="seconds of poses before each kill (a spare starts 5 s after its node)")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    ap.add_argument("-v", "--verbose", action="store_true", help="show the graph's output")
    args = ap.parse_args(argv)
    graph = bench_graph(args.graph, args.node)
    pose_keys = args.pose or [k for k in ("refine/pose", "fusion/pose")
                              if k.split("/")[0] in graph.ids()] or ["fusion/pose"]
    print(f"restart: kill -9 of {args.node!r} in {args.graph} ({len(graph.nodes)} nodes), {args.kills} times; "
          f"seconds after the kill")
    log = sys.stdout if args.verbose else io.StringIO()
    rows = measure(graph, args.node, pose_keys, args.kills, args.settle_s, log)
    for k in pose_keys:
        vals = [r[f"pose {k}"] for r in rows if r[f"pose {k}"] is not None]
        print(f"restart: poses again on {k} after {statistics.median(vals) if vals else float('nan'):.2f} s "
              f"(median of {len(vals)}; max {max(vals) if vals else float('nan'):.2f} s)")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
