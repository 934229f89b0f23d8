"""``needletrack bench soak [--duration 600]``: the default graph (dataflow.yaml) for a long run,
its camera replaced by a replay of a dataset folder looping at ``--rate`` (30 Hz).

Prints, after the source stops and the graph drains:

- accounting per frame: every frame the camera published (its ``truth`` seqs, traced) either
  got keypoints from both detectors or a detector counted why not (its newest-only input
  replaced it while busy: ``dropped.<camera>``; ``stride_skipped``; ...); every frame with both
  keypoints was paired by each stereo pose node or dropped there (counted ``dropped``/``unpaired``),
  and every pair gave a pose or a counted ``no_pose.<reason>`` (or ``invalid_pose``); fusion:
  every joint pose in is fused or counted. "Unaccounted" is what no counter explains (0 wanted);
- RSS of every node process (``/proc``): after the warm-up (median over 10-20% of the run)
  against the end (median over the last 10%), growth in % (within 5% wanted), split into the
  process's own memory (RssAnon) and shared memory (RssShmem: the Zenoh pool's pages as they
  come into use, bounded by ``shm_pool_mb``); a node passes with its RSS within 5%, or with
  its own memory within 5% and its shared memory within the pool;
- restarts of every node (0 wanted) and handler/decode errors.

Exit status 0 when all three hold. ``--json FILE`` writes the figures.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from common.cli_options import add_dataset

STEREO_POSE_NODES = ("epnp_average", "epnp_joint", "triangulate", "refine")
RSS_TOLERANCE = 0.05


def rss_mb(pid: int):
    """``{"rss", "anon", "shmem"}`` MB of a process (/proc: VmRSS, RssAnon, RssShmem), or None.
    ``shmem`` is mostly the Zenoh shared-memory pool's pages as they are first used (bounded by
    the pool, ``zenoh.shm_pool_mb``); ``anon`` is the process's own heap, where a leak shows."""
    keys = {"VmRSS:": "rss", "RssAnon:": "anon", "RssShmem:": "shmem"}
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            k = keys.get(line.split(":")[0] + ":")
            if k:
                out[k] = int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        return None
    return out if "rss" in out else None


def soak_graph(dataset: str, rate: float) -> dict:
    """The default graph with its camera replaced by a looping replay of ``dataset``."""
    from common.runtime.graph import REPO_ROOT, load_graph
    doc = load_graph(REPO_ROOT / "dataflow.yaml").to_dict()
    doc["graph"] = f"needletrack-soak-{int(time.time())}"
    from common.evaluation.pipeline_graph import free_port
    doc["zenoh"]["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    for n in doc["nodes"]:
        if n["id"] == "camera":
            n.clear()
            n.update(id="camera", module="replay", params={"path": str(Path(dataset).resolve()), "rate": rate,
                                                           "loop": True},
                     outputs=["left", "right", "joints", "truth", "calib", "eos"], inputs={},
                     restart="on-failure")
    return doc


def _counter(c: dict, key: str) -> int:
    v = c.get(key, 0)
    return v if isinstance(v, int) else 0


def _sum_prefix(c: dict, prefix: str) -> int:
    return sum(v for k, v in c.items() if k.startswith(prefix) and isinstance(v, int))


def account(seqs: dict, stats: dict) -> dict:
    """The per-frame accounting of the module docstring from the traced seqs and final stats."""
    F = seqs["published"]
    out = {"frames_published": len(F), "replay_out_left": _counter(stats["camera"].counters, "out.left")}
    dets = {}
    for det, cam in (("detector_left", "left"), ("detector_right", "right")):
        c = stats[det].counters
        K = seqs[f"keypoints_{cam}"] & F
        counted = (_counter(c, f"dropped.{cam}") + _counter(c, "stride_skipped") + _counter(c, "superseded")
                   + _counter(c, "no_calibration") + _counter(c, "decode_errors") + _counter(c, "seq_outlier")
                   + _counter(c, "seq_stale"))
        dets[det] = {"keypoints": len(K), "counted_skipped": counted, "unaccounted": len(F) - len(K) - counted}
    out["detectors"] = dets
    both = F & seqs["keypoints_left"] & seqs["keypoints_right"]
    out["frames_with_both_keypoints"] = len(both)
    pose_nodes = {}
    for p in STEREO_POSE_NODES:
        if p not in stats:
            continue
        c = stats[p].counters
        posed = seqs[p] & F
        pairs = _counter(c, "pairs")
        no_pose = _sum_prefix(c, "no_pose.")
        invalid = _counter(c, "invalid_pose")
        lost = len(both) - pairs              # both keypoints out, never paired here
        counted_lost = _counter(c, "dropped") + _counter(c, "unpaired") + _counter(c, "seq_outlier") \
            + _counter(c, "seq_stale")
        pose_nodes[p] = {"posed": len(posed), "no_pose": no_pose, "invalid_pose": invalid, "pairs": pairs,
                         "not_paired": lost, "counted_halves_dropped": counted_lost,
                         "no_pose_reasons": {k[8:]: v for k, v in c.items() if k.startswith("no_pose.")},
                         "unaccounted": pairs - len(posed) - no_pose - invalid
                         + max(0, lost - counted_lost)}
    out["pose_nodes"] = pose_nodes
    if "fusion" in stats:
        c = stats["fusion"].counters
        joint_in = seqs["epnp_joint"]
        fused = seqs["fusion"]
        no_pose = _sum_prefix(c, "no_pose.")
        dropped = _counter(c, "dropped") + _counter(c, "seq_outlier") + _counter(c, "seq_stale")
        out["fusion"] = {"poses_in": len(joint_in), "fused": len(fused), "no_pose": no_pose,
                         "invalid_pose": _counter(c, "invalid_pose"), "dropped_inputs": dropped,
                         "unaccounted": len(joint_in) - len(fused) - no_pose - _counter(c, "invalid_pose") - dropped}
    # every camera frame: posed by refine (the final single-frame pose), or why not
    if "refine" in pose_nodes:
        r = pose_nodes["refine"]
        out["frames_accounted_refine"] = {
            "published": len(F), "posed": r["posed"], "no_pose": r["no_pose"] + r["invalid_pose"],
            "not_paired_at_refine": r["not_paired"], "missing_keypoints": len(F) - len(both),
            "unaccounted": len(F) - r["posed"] - r["no_pose"] - r["invalid_pose"] - r["not_paired"]
            - (len(F) - len(both))}
    return out


def run_soak(args, log) -> dict:
    from common.evaluation.graph_speed import Recorder, check_alive, ensure_dataset
    from common.evaluation.pipeline_graph import GraphRun
    from common.runtime.graph import output_key, stats_key
    from common.runtime.messages import GroundTruth, Keypoints, NodeStats, PoseEstimate

    dataset = ensure_dataset(args.dataset)
    doc = soak_graph(dataset, args.rate)
    streams = {"published": ("camera/truth", GroundTruth), "keypoints_left": ("detector_left/left", Keypoints),
               "keypoints_right": ("detector_right/right", Keypoints), "fusion": ("fusion/pose", PoseEstimate)}
    for p in STEREO_POSE_NODES:
        streams[p] = (f"{p}/pose", PoseEstimate)
    rec = Recorder()
    rss: dict = {}                 # node -> [(t, MB)]
    pids_seen: dict = {}
    with GraphRun(doc, log, source="camera") as run:
        run.start_consumers()
        session = run.client_session()
        subs = [session.declare_subscriber(output_key(run.graph.name, *src.split("/")), rec.callback(name, typ))
                for name, (src, typ) in streams.items()]
        subs.append(session.declare_subscriber(stats_key(run.graph.name), rec.callback("@stats", NodeStats)))
        run.start_source()
        t0 = time.monotonic()
        next_print = t0 + 30
        while time.monotonic() - t0 < args.duration:
            check_alive(run)
            with rec.lock:
                stats = dict(rec.stats)
            now = time.monotonic() - t0
            for n, st in stats.items():
                pids_seen.setdefault(n, set()).add(st.pid)
                mb = rss_mb(st.pid)
                if mb is not None:
                    rss.setdefault(n, []).append((now, mb))
            if time.monotonic() >= next_print:
                print(f"soak: {now:.0f} s of {args.duration:.0f}: {len(rec.rows('published'))} frames published, "
                      f"{len(rec.rows('refine'))} refined poses", file=sys.stderr, flush=True)
                next_print += 30
            time.sleep(args.sample_s)
        run.src.stop()                       # the source stops cleanly; the graph drains
        time.sleep(args.drain_s)
        t_final = time.time_ns()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:   # stats published after the drain, from every node
            with rec.lock:
                stats = dict(rec.stats)
            if all(st.stamp_ns > t_final for n, st in stats.items() if n != "camera"):
                break
            time.sleep(0.2)
        status = {nid: s.restarts for l in (run.main, run.src) for nid, s in l.slots.items()}
        for s in subs:
            s.undeclare()
    seqs = {name: {r[0] for r in rec.rows(name)} for name in streams}
    out = {"dataset": dataset, "rate_hz": args.rate, "duration_s": args.duration,
           "shm_pool_mb": doc["zenoh"].get("shm_pool_mb", 64)}
    out.update(account(seqs, stats))
    rss_out = {}
    for n, samples in sorted(rss.items()):
        d = args.duration
        early = [mb for t, mb in samples if 0.1 * d <= t <= 0.2 * d]
        late = [mb for t, mb in samples if t >= 0.9 * d]
        if early and late:
            med = {k: (statistics.median(m.get(k, 0.0) for m in early), statistics.median(m.get(k, 0.0) for m in late))
                   for k in ("rss", "anon", "shmem")}
            (e, l_), (ea, la), (es, ls) = med["rss"], med["anon"], med["shmem"]
            rss_out[n] = {"early_mb": round(e, 1), "end_mb": round(l_, 1), "growth": (l_ - e) / e,
                          "anon_early_mb": round(ea, 1), "anon_end_mb": round(la, 1),
                          "anon_growth": (la - ea) / ea if ea else 0.0,
                          "shmem_early_mb": round(es, 1), "shmem_end_mb": round(ls, 1),
                          "max_mb": round(max(m["rss"] for _, m in samples), 1)}
    out["rss"] = rss_out
    out["rss_series_mb"] = {n: [(round(t), round(m["rss"], 1), round(m.get("shmem", 0.0), 1)) for t, m in smp[::15]]
                            for n, smp in rss.items()}
    out["restarts"] = status
    out["pids"] = {n: len(p) for n, p in pids_seen.items()}
    out["errors"] = {n: {k: st.counters.get(k, 0) for k in ("handler_errors", "decode_errors", "step_errors",
                                                           "invalid_pose", "stream_resets")}
                     for n, st in stats.items()}
    return out


def report(r: dict) -> str:
    lines = [f"soak: {r['duration_s']:.0f} s of the default graph fed by a replay of {r['dataset']} at "
             f"{r['rate_hz']:g} Hz (looping)",
             f"  frames published: {r['frames_published']} (replay counter out.left {r['replay_out_left']}), "
             f"with both keypoints: {r['frames_with_both_keypoints']}"]
    for d, v in r["detectors"].items():
        lines.append(f"  {d:15s} keypoints {v['keypoints']:6d}  skipped (counted) {v['counted_skipped']:6d}  "
                     f"unaccounted {v['unaccounted']}")
    for p, v in r["pose_nodes"].items():
        reasons = ", ".join(f"{k} {n}" for k, n in sorted(v["no_pose_reasons"].items()))
        lines.append(f"  {p:15s} pairs {v['pairs']:6d} = posed {v['posed']:6d} + no pose {v['no_pose']:5d} "
                     f"+ invalid {v['invalid_pose']}; not paired {v['not_paired']} (halves dropped, counted: "
                     f"{v['counted_halves_dropped']}); unaccounted {v['unaccounted']}" + (f"  [{reasons}]" if reasons else ""))
    if "fusion" in r:
        v = r["fusion"]
        lines.append(f"  {'fusion':15s} joint poses in {v['poses_in']} = fused {v['fused']} + no pose {v['no_pose']} "
                     f"+ invalid {v['invalid_pose']} + dropped inputs {v['dropped_inputs']}; unaccounted {v['unaccounted']}")
    if "frames_accounted_refine" in r:
        v = r["frames_accounted_refine"]
        lines.append(f"  every frame, at refine: published {v['published']} = posed {v['posed']} + no pose "
                     f"{v['no_pose']} + not paired {v['not_paired_at_refine']} + a detector skipped it "
                     f"{v['missing_keypoints']}; unaccounted {v['unaccounted']}")
    growth = {n: v["growth"] for n, v in r["rss"].items()}
    for n, v in r["rss"].items():
        lines.append(f"  rss {n:15s} {v['early_mb']:8.1f} MB -> {v['end_mb']:8.1f} MB ({100 * v['growth']:+.1f}%); "
                     f"own (anon) {v['anon_early_mb']:.1f} -> {v['anon_end_mb']:.1f} MB ({100 * v['anon_growth']:+.1f}%), "
                     f"shared memory {v['shmem_early_mb']:.1f} -> {v['shmem_end_mb']:.1f} MB")
    worst = max(growth.items(), key=lambda kv: abs(kv[1])) if growth else ("-", 0.0)
    lines.append(f"  RSS: largest change {100 * worst[1]:+.1f}% ({worst[0]}); restarts: "
                 f"{sum(r['restarts'].values())} ({', '.join(f'{k} {v}' for k, v in r['restarts'].items() if v) or 'none'})")
    errs = {n: {k: v for k, v in e.items() if v} for n, e in r["errors"].items()}
    errs = {n: e for n, e in errs.items() if e}
    lines.append(f"  errors and resets: {errs or 'none'}")
    return "\n".join(lines)


def verdict(r: dict) -> list:
    bad = []
    for d, v in r["detectors"].items():
        if v["unaccounted"]:
            bad.append(f"{d}: {v['unaccounted']} frames unaccounted")
    for p, v in r["pose_nodes"].items():
        if v["unaccounted"]:
            bad.append(f"{p}: {v['unaccounted']} unaccounted")
    if r.get("fusion", {}).get("unaccounted"):
        bad.append(f"fusion: {r['fusion']['unaccounted']} unaccounted")
    pool = r.get("shm_pool_mb", 64)
    for n, v in r["rss"].items():
        # within 5%, or the growth is the shared-memory pool's pages coming into use (bounded by
        # the pool) while the process's own memory stays within 5%
        if abs(v["growth"]) > RSS_TOLERANCE and (abs(v["anon_growth"]) > RSS_TOLERANCE
                                                  or v["shmem_end_mb"] > pool + 8):
            bad.append(f"{n}: RSS {100 * v['growth']:+.1f}% (own memory {100 * v['anon_growth']:+.1f}%)")
    if any(r["restarts"].values()):
        bad.append(f"restarts: {r['restarts']}")
    return bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench soak", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=600.0, help="seconds (default 600)")
    ap.add_argument("--rate", type=float, default=30.0, help="replay rate, Hz (default 30)")
    add_dataset(ap, looped=True)
    ap.add_argument("--sample-s", type=float, default=2.0, help="RSS sampling period (s)")
    ap.add_argument("--drain-s", type=float, default=6.0, help="seconds for the graph to drain at the end")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--log", help="the graph's log (default: a temporary file)")
    args = ap.parse_args(argv)
    log_path = args.log or tempfile.mktemp(prefix="soak-", suffix=".log")
    with open(log_path, "w") as log:
        r = run_soak(args, log)
    print(report(r))
    bad = verdict(r)
    print("soak: " + ("PASS" if not bad else "FAIL: " + "; ".join(bad)) + f" (graph log: {log_path})")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=1, default=str))
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
