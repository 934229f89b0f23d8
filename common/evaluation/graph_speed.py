"""The live pipeline's speed, end to end (``needletrack bench graph``, ``needletrack eval --bench``,
the soak and the fuzz): the graph run, each stream's arrival times recorded (``Recorder``), and
its throughput, latency per stage and each node's CPU measured (``measure``) and printed (``report``).
What is measured: ``common/bench/graph_bench.py``.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

BENCH_DATA = "data/bench"
BENCH_GENERATE = ["generate", "--out", BENCH_DATA, "--sequences", "6", "--steps", "5",
                  "--seed", "2000", "--randomise", "test"]
TARGET_HZ, TARGET_P50_MS = 30.0, 50.0


class Recorder:
    """Arrival times (wall clock, ns) of the messages the bench subscribes to, by stream.

    The callbacks only keep each payload's bytes and arrival time; they are decoded when asked
    for (``rows``, ``window``), so that the bench's own CPU stays small while it measures."""

    def __init__(self):
        self.lock = threading.Lock()
        self._raw: dict = {}          # stream -> list of (payload bytes, msg type, arrival_ns)
        self._rows: dict = {}         # stream -> list of (seq, stamp_ns, arrival_ns), decoded
        self.stats: dict = {}         # node -> newest NodeStats

    def callback(self, stream: str, msg_type):
        from common.runtime.messages import MessageError, decode

        def cb(sample):
            now = time.time_ns()
            if stream != "@stats":
                with self.lock:
                    self._raw.setdefault(stream, []).append((sample.payload.to_bytes(), msg_type, now))
                return
            try:
                msg = decode(sample.payload.to_bytes(), msg_type)
            except MessageError:
                return
            with self.lock:
                self.stats[msg.node] = msg
        return cb

    def rows(self, stream: str) -> list:
        """(seq, stamp_ns, arrival_ns) of every message of ``stream`` so far (malformed ones left out)."""
        from common.runtime.messages import MessageError, decode
        with self.lock:
            raw, self._raw[stream] = self._raw.get(stream, []), []
        out = []
        for payload, msg_type, now in raw:
            try:
                msg = decode(payload, msg_type)
            except MessageError:
                continue
            out.append((msg.seq, msg.stamp_ns, now))
        with self.lock:
            self._rows.setdefault(stream, []).extend(out)
            return list(self._rows[stream])

    def window(self, stream: str, t0_ns: int, t1_ns: int) -> list:
        """Rows of ``stream`` whose frame was published within [t0, t1)."""
        return [r for r in self.rows(stream) if t0_ns <= r[1] < t1_ns]


def latency_ms(rows) -> dict:
    lat = [(a - s) / 1e6 for _, s, a in rows]
    if not lat:
        return {"p50": None, "p95": None, "p99": None, "n": 0}
    p50, p95, p99 = (float(v) for v in np.percentile(lat, [50, 95, 99]))
    return {"p50": p50, "p95": p95, "p99": p99, "n": len(lat)}


def ensure_dataset(path) -> str:
    if path:
        return path
    if Path("data/test/frames.jsonl").is_file():
        return "data/test"
    if not Path(BENCH_DATA, "frames.jsonl").is_file():
        from common.cli import dataset_main
        print(f"bench: generating {BENCH_DATA} (30 stereo frames at 1920x1080, once)", file=sys.stderr)
        if dataset_main(BENCH_GENERATE) != 0:
            raise RuntimeError(f"could not generate {BENCH_DATA}")
    return BENCH_DATA


def viewer_node(doc: dict, split: bool, params: dict | None = None) -> dict:
    """A viewer node wired to everything ``doc`` (a ``pipeline_graph``) produces, as in
    dataflow.yaml, with dataflow.yaml's viewer params, then ``params``, on free ports (its page
    and Rerun's in-process gRPC server; no web viewer process)."""
    import yaml

    from common.evaluation.pipeline_graph import (
        SOURCE,
        free_port,
        keypoint_sources,
        pose_inputs,
    )
    from common.runtime.graph import REPO_ROOT
    flow = yaml.safe_load((REPO_ROOT / "dataflow.yaml").read_text())
    base = next((n.get("params") or {} for n in flow["nodes"] if n.get("module") == "viewer"), {})
    kp = keypoint_sources(split)
    return {"id": "viewer", "module": "viewer",
            "params": {**base, **(params or {}), "port": free_port(), "grpc_port": free_port(), "web_port": 0},
            "inputs": {"left": f"{SOURCE}/left", "right": f"{SOURCE}/right", "truth": f"{SOURCE}/truth",
                       "calib": f"{SOURCE}/calib", "ecm": "ecm/pose", "keypoints_left": kp["left"],
                       "keypoints_right": kp["right"], **pose_inputs(doc)},
            "restart": "never", "env": {"OMP_NUM_THREADS": "1"}}


def measure(args, dataset: str, log, viewer: bool = False) -> dict:
    from common.data.dataset import Dataset
    from common.methods import METHOD_NEEDS, MULTIVIEW_METHODS, POSE_OUTPUTS, last_stage
    from common.evaluation.pipeline_graph import (
        GraphRun,
        keypoint_sources,
        pipeline_graph,
        pose_inputs,
    )
    from common.evaluation.timing import cpu_steal_seconds, process_cpu_seconds
    from common.runtime.graph import output_key, stats_key
    from common.runtime.messages import GroundTruth, Keypoints, NodeStats, PoseEstimate

    ds = Dataset(dataset, check_files=False)
    rate = "paced" if str(args.rate) == "max" else float(args.rate)
    split = not args.one_detector
    from common.runtime.graph import parse_param
    det_params = {"weights": str(Path(args.model).resolve())} if args.model else {}
    det_params.update(dict(parse_param(p) for p in getattr(args, "param", [])))
    final = "multiview" if args.no_refine else "multiview_refined"
    tracker = not args.no_refine and (getattr(args, "tracker", False) or not all(fr.at_rest for fr in ds.frames))
    doc = pipeline_graph(dataset, detector=args.detector, detector_params=det_params, rate=rate, loop=True,
                         refine=False if args.no_refine else None, split_detector=split, tracker=tracker,
                         tracker_params=dict(parse_param(p) for p in getattr(args, "tracker_param", [])) or None,
                         methods=None if getattr(args, "all_methods", False) else [final, *(["tracked"] * tracker)],
                         name="needletrack-bench", decode=getattr(args, "decode", False))
    poses = pose_inputs(doc)
    viewer_params = None
    if viewer:
        vparams = dict(parse_param(p) for p in getattr(args, "viewer_param", []))
        doc["nodes"].append(viewer_node(doc, split, vparams))
        viewer_params = doc["nodes"][-1]["params"]
    if tracker and "tracked" in poses:
        final = "tracked"
    elif final not in poses:
        final = last_stage(m for m in poses if m in MULTIVIEW_METHODS)
    single = METHOD_NEEDS[final][0] if final in METHOD_NEEDS else "refined"    # the tracker filters refined poses
    frame_node = POSE_OUTPUTS[single].split("/")[0]   # pairs stereo keypoints
    rec = Recorder()
    streams = {"published": ("replay/truth", GroundTruth)}
    for cam, src in keypoint_sources(split).items():
        streams[f"keypoints_{cam}"] = (src, Keypoints)
    for m, src in poses.items():
        streams[m] = (src, PoseEstimate)

    with GraphRun(doc, log) as run:
        run.start_consumers()
        session = run.client_session()
        subs = [session.declare_subscriber(output_key(run.graph.name, *src.split("/")),
                                           rec.callback(name, typ))
                for name, (src, typ) in streams.items()]
        subs.append(session.declare_subscriber(stats_key(run.graph.name), rec.callback("@stats", NodeStats)))
        run.start_source()
        # the first frame's publish time starts the clock
        deadline = time.monotonic() + 60
        while not rec.rows("published"):
            if time.monotonic() > deadline:
                raise RuntimeError("the replay published no frame within 60 s")
            check_alive(run)
            time.sleep(0.05)
        first_ns = rec.rows("published")[0][1]
        w0 = first_ns + int(args.warmup * 1e9)
        while time.time_ns() < w0:
            check_alive(run)
            time.sleep(0.1)
        with rec.lock:
            pids = {n: st.pid for n, st in rec.stats.items()}
            drops0 = {n: _dropped(st) for n, st in rec.stats.items()}
            pairs0 = _pairs(rec.stats.get(frame_node))
            late0 = _late_poses(rec.stats.get("tracker"))
        cpu0 = {n: process_cpu_seconds(p) for n, p in pids.items()}
        steal0 = cpu_steal_seconds()
        w1 = w0 + int(args.duration * 1e9)
        while time.time_ns() < w1:
            check_alive(run)
            time.sleep(0.1)
        cpu1 = {n: process_cpu_seconds(p) for n, p in pids.items()}
        steal1 = cpu_steal_seconds()
        with rec.lock:
            pairs1 = _pairs(rec.stats.get(frame_node))
        time.sleep(0.5)  # outputs of the window's last frames still in flight
        for s in subs:
            s.undeclare()

    span = (w1 - w0) / 1e9
    published = rec.window("published", w0, w1)
    out = {"dataset": dataset, "frames_in_dataset": len(ds), "image_size": list(ds.meta.image_size),
           "detector": args.detector, "detector_processes": 2 if split else 1,
           "rate": str(rate), "duration_s": span, "final_method": final,
           "published_hz": len(published) / span}
    if viewer_params is not None:
        out["viewer_params"] = viewer_params
    fused = rec.window(final, w0, w1)
    seqs = {r[0] for r in fused}
    out["throughput_hz"] = len(seqs) / span
    # stats come once a second: the pair counts span from one stats message to another
    out["frame_node"] = frame_node
    out["frames_processed_hz"] = ((pairs1[0] - pairs0[0]) / ((pairs1[1] - pairs0[1]) / 1e9)
                                  if pairs0 and pairs1 and pairs1[1] > pairs0[1] else None)
    out["frames_through"] = (len(seqs) / len(published)) if published else None
    out["latency_ms"] = latency_ms(fused)
    stages = {}
    for name in streams:
        if name == "published":
            continue
        stages[name] = {**latency_ms(rec.window(name, w0, w1)),
                        "rate_hz": len({r[0] for r in rec.window(name, w0, w1)}) / span}
    out["stages"] = stages
    if final == "tracked" and "refined" in streams:
        # the tracker steps a frame once its refined pose is in, or a later frame's (the refine
        # node posed nothing for it: the tracker learns it only then), or max_wait frames passed
        refined = {r[0] for r in rec.window("refined", w0, w1)}
        out["tracked_latency_ms"] = {"measured": latency_ms([r for r in fused if r[0] in refined]),
                                     "coasted": latency_ms([r for r in fused if r[0] not in refined])}
        with rec.lock:
            late1 = _late_poses(rec.stats.get("tracker"))
        out["tracked_late_poses"] = {k: late1[k] - late0[k] for k in late1}
    if getattr(args, "plot", None):
        out["latency_samples_ms"] = {name: [(a - st) / 1e6 for _, st, a in rec.window(name, w0, w1)]
                                     for name in streams if name != "published"}
    nodes = {}
    with rec.lock:
        stats = dict(rec.stats)
    for n, st in sorted(stats.items()):
        c0, c1 = cpu0.get(n), cpu1.get(n)
        share = (c1 - c0) / span if c0 is not None and c1 is not None else None
        nodes[n] = {"proc_ms_p50": st.proc_ms_p50, "proc_ms_p99": st.proc_ms_p99,
                    "cpu_share": share,
                    "cpu_ms_per_frame": (1e3 * share / out["published_hz"]
                                         if share is not None and out["published_hz"] else None),
                    "dropped": _dropped(st) - drops0.get(n, 0),
                    "in_hz": {k[3:]: v for k, v in st.rates_hz.items() if k.startswith("in.")}}
    out["per_node"] = nodes
    out["per_node_ms"] = {n: v["proc_ms_p50"] for n, v in nodes.items()}
    out["cpu_total"] = sum(v["cpu_share"] or 0.0 for v in nodes.values())
    out["cpus"] = os.cpu_count()
    # the hypervisor's share of the CPUs during the window: how slow a minute this was
    out["cpu_steal"] = ((steal1 - steal0) / span / (out["cpus"] or 1)
                        if steal0 is not None and steal1 is not None else None)
    return out


def _pairs(st):
    """(stereo frames paired so far, stamp_ns of that count) from a pose node's stats."""
    if st is None:
        return None
    v = st.counters.get("pairs", 0)
    return (v if isinstance(v, int) else 0, st.stamp_ns)


def _late_poses(st) -> dict:
    """The tracker's late poses so far: filtered in by stepping again (``replayed``), dropped."""
    return {k: _counter(st, k) for k in ("replayed", "late_pose")}


def _dropped(st) -> int:
    return _counter(st, "dropped")


def _counter(st, name: str) -> int:
    """A node's counter ``name`` so far from its stats (0: no stats, not counted, not a count)."""
    v = st.counters.get(name, 0) if st is not None else 0
    return v if isinstance(v, int) else 0


def check_alive(run) -> None:
    from common.evaluation.pipeline_graph import GraphRunError
    dead = run.failed()
    if dead:
        raise GraphRunError(f"node(s) failed: {dead}")


def report(r: dict) -> str:
    f = lambda x, nd=1: "n/a" if x is None else f"{x:.{nd}f}"
    w, h = r["image_size"]
    L = [f"needletrack bench graph: {r['dataset']} ({w}x{h} stereo, {r['frames_in_dataset']} frames looped), "
         f"detector {r['detector']} ({r['detector_processes']} process(es)), replay rate {r['rate']}, "
         f"{r['duration_s']:.0f} s measured on {r['cpus']} CPU(s)",
         f"  frames published      {f(r['published_hz'])} /s",
         f"  frames processed      {f(r['frames_processed_hz'])} /s stereo frames paired and processed by "
         f"{r['frame_node']} (with or without a pose)",
         f"  end to end            {f(r['throughput_hz'])} /s final poses ({r['final_method']}); "
         f"{f(None if r['frames_through'] is None else 100 * r['frames_through'])}% of the published frames"
         f"   [target >= {TARGET_HZ:.0f}; paper 10 Hz on an RTX 3080]",
         f"  latency               p50 {f(r['latency_ms']['p50'])} ms, p95 {f(r['latency_ms'].get('p95'))} ms, "
         f"p99 {f(r['latency_ms']['p99'])} ms from frame publish to final pose   [target p50 <= {TARGET_P50_MS:.0f} ms]",
         *([f"  tracked, by frame     p50 {f(t['measured']['p50'])} ms with a refined pose "
            f"({t['measured']['n']}), {f(t['coasted']['p50'])} ms coasted ({t['coasted']['n']}: "
            "stepped at its no_pose notice, a later frame's pose or notice, or after max_wait frames)"]
           if (t := r.get("tracked_latency_ms")) else []),
         *([f"  late refined poses    {lp['replayed']} filtered in after their frame was out (stepping again), "
            f"{lp['late_pose']} too late, dropped"] if (lp := r.get("tracked_late_poses")) else []),
         "", f"  {'stage output':<22}{'frames/s':>9}{'p50 ms':>9}{'p99 ms':>9}   (latency from frame publish)"]
    for name, s in r["stages"].items():
        L.append(f"  {name:<22}{f(s['rate_hz']):>9}{f(s['p50']):>9}{f(s['p99']):>9}")
    L += ["", f"  {'node':<18}{'cpu %':>7}{'cpu ms/frame':>14}{'handler p50':>13}{'p99 ms':>9}"
               f"{'dropped':>9}   inputs Hz"]
    for n, v in r["per_node"].items():
        cpu = None if v["cpu_share"] is None else 100 * v["cpu_share"]
        ins = " ".join(f"{k}={val:g}" for k, val in sorted(v["in_hz"].items()))
        L.append(f"  {n:<18}{f(cpu, 0):>7}{f(v['cpu_ms_per_frame'], 2):>14}{f(v['proc_ms_p50'], 2):>13}"
                 f"{f(v['proc_ms_p99'], 2):>9}"
                 f"{v['dropped']:>9}   {ins}")
    L.append(f"  total CPU {f(100 * r['cpu_total'], 0)}% of {100 * (r['cpus'] or 1)}%; "
             f"cpu ms/frame = CPU time per published frame")
    if r.get("cpu_steal") is not None:
        L.append(f"  CPU steal {100 * r['cpu_steal']:.0f}% (taken by the hypervisor for other guests: "
                 f"above a few %, this machine ran slow during the window)")
    return "\n".join(L)
