"""An intruder on a running graph: a local process without the run's credentials, optionally
of another user (``--uid``), that tries to steer it (issue 32's probe).

``python -m common.robustness.intruder GRAPH.yaml [--uid N] [--duration S] [--keys K,...]``
prints one JSON line of what it got: the peers it reached with each of its sessions (plain TCP
to the graph's endpoint; TLS trusting the run's CA when it can read it, with no certificate),
whether it could read the run's credentials, the fake ``PoseEstimate``s it sent (copies of the
real poses on ``--keys`` it saw, moved ``--offset-mm`` along x; blind ones with the newest seq
when it sees none), and the answers to a handover query on ``<graph>/@ctl/*/*/handover`` and a
swap on ``<graph>/@launcher/swap``. On an open graph (``zenoh.open: true``, or before per-run
credentials) everything gets in; on the default graph nothing does. ``needletrack bench fuzz
--live`` runs it against the default graph; ``tests/runtime/test_credentials.py`` as another user.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

DEFAULT_KEYS = ("epnp_joint/pose", "refine/pose")
OFFSET_MM = 80.0


def _configs(graph, victim_dir) -> list:
    """(name, zenoh.Config) of each way in: plain TCP to the graph's endpoints, and TLS trusting
    the run's CA (when readable) without a client certificate."""
    import zenoh
    endpoints = [e for e in graph.zenoh.listen]
    out = []
    for proto in ("tcp", "tls"):
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints", "[]")
        c.insert_json5("connect/endpoints", json.dumps([proto + e[3:] if e[:3] in ("tcp", "tls") else e
                                                        for e in endpoints]))
        if proto == "tls":
            try:
                ca = Path(victim_dir) / "ca.pem"
                ca.read_bytes()
            except (OSError, TypeError):
                ca = None
            if ca is not None:
                c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca)))
            c.insert_json5("transport/link/tls/verify_name_on_connect", "false")
        out.append((proto, c))
    return out


def probe(graph, victim_dir=None, duration: float = 5.0, keys=DEFAULT_KEYS, offset_mm: float = OFFSET_MM) -> dict:
    """Try every way in for ``duration`` s; returns what got through (see the module docstring).
    ``victim_dir``: the run's credentials directory (of the user who launched it), tried too."""
    import copy

    import numpy as np
    import zenoh

    from common.runtime.messages import MessageError, PoseEstimate, decode, encode
    out: dict = {"uid": os.getuid(), "graph": graph.name}
    try:
        (Path(victim_dir) / "launcher.key").read_bytes()
        out["credentials"] = f"readable: {victim_dir}"
    except (OSError, TypeError) as exc:
        out["credentials"] = f"refused: {exc}"
    sessions = []
    for name, cfg in _configs(graph, victim_dir):
        try:
            sessions.append((name, zenoh.open(cfg)))
        except Exception as exc:              # a TLS config that cannot even be set up
            out[f"{name}_open"] = f"{type(exc).__name__}: {exc}"
    try:
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and not any(list(s.info.peers_zid()) for _, s in sessions):
            time.sleep(0.05)
        time.sleep(0.5)
        out["peers"] = {name: len(list(s.info.peers_zid())) for name, s in sessions}
        lock = threading.Lock()
        seen: list = []
        forged: set = set()
        sent = [0]
        shift = np.eye(4)
        shift[0, 3] = offset_mm / 1000.0

        def forge(msg):
            """The real pose moved by ``shift`` (in the ECM frame), its world pose to match."""
            fake = copy.copy(msg)
            fake.T_ecm_needle = shift @ msg.T_ecm_needle
            if msg.T_world_ecm is not None:
                fake.T_world_needle = msg.T_world_ecm @ fake.T_ecm_needle
            return encode(fake)

        subs, pubs = [], []
        for _, s in sessions:
            for k in keys:
                key = graph.resolve_key(k)
                pub = s.declare_publisher(key, express=True)
                pubs.append(pub)

                def cb(sample, pub=pub, key=key):
                    try:
                        msg = decode(sample.payload.to_bytes(), PoseEstimate)
                    except MessageError:
                        return
                    ident = (key, msg.epoch, msg.seq, msg.stamp_ns)
                    with lock:
                        if msg.method == "forged" or ident in forged:      # our own copies come back
                            return
                        forged.add(ident)
                        seen.append(msg.seq)
                        sent[0] += 1
                    pub.put(forge(msg))
                subs.append(s.declare_subscriber(key, cb))
        t_end = time.monotonic() + duration
        blind_seq = 0
        T = np.eye(4)
        T[:3, 3] = (offset_mm / 1000.0, 0.0, 0.15)
        while time.monotonic() < t_end:       # blind fakes too: no real pose is seen under TLS
            with lock:
                blind_seq = max([blind_seq] + seen) + 1
            for pub in pubs:
                pub.put(encode(PoseEstimate(blind_seq, time.time_ns(), "forged", T)))
                sent[0] += 1
            time.sleep(1 / 30)
        out["poses_seen"] = len(seen)
        out["poses_sent"] = sent[0]
        handovers, swaps = [], []
        for _, s in sessions:
            for reply in s.get(f"{graph.name}/@ctl/*/*/handover", timeout=2.0, payload=b"{}"):
                handovers.append(reply.ok.payload.to_bytes().decode() if reply.ok is not None else "error")
            for reply in s.get(f"{graph.name}/@launcher/swap", timeout=2.0,
                               payload=json.dumps({"node": "fusion", "params": {"k": 1}}).encode()):
                swaps.append(reply.ok.payload.to_bytes().decode() if reply.ok is not None else "error")
        out["handover_answers"] = handovers
        out["swap_answers"] = swaps
    finally:
        for _, s in sessions:                  # (undeclaring while a callback runs raises: close only)
            try:
                s.close()
            except Exception:
                pass
    return out


def intruder_check(graph_path: str = "dataflow.yaml", clean_s: float = 20.0, duration: float = 10.0,
                   uid=None, open_graph: bool = False, offset_mm: float = OFFSET_MM) -> int:
    """``needletrack bench fuzz --intruder``: the default graph (its viewer left out, on a free
    loopback port) through the real launcher; after ``clean_s`` s of fused poses, this module
    runs as a process without the run's credentials (as ``uid`` if given) for ``duration`` s.
    Prints how many fused poses lay more than 20 mm off the truth toward the fake (along the
    fake's offset, ECM x), in the clean period and during the intrusion, what the intruder
    reached and got answered, and the nodes that retired. ``open_graph``: the same with
    ``zenoh.open: true`` (the graph as it was before per-run credentials)."""
    import io
    import subprocess
    import tempfile

    import numpy as np
    import zenoh

    from common.bench.restart_bench import bench_graph
    from common.runtime.graph import REPO_ROOT
    from common.runtime.zenoh_session import zenoh_config
    from common.runtime.launcher import Launcher
    from common.runtime.messages import GroundTruth, MessageError, PoseEstimate, decode
    graph = bench_graph(graph_path)
    graph.zenoh.open = open_graph
    launcher = Launcher(graph, out=io.StringIO())
    launcher.start()
    runner = threading.Thread(target=launcher.run, daemon=True)
    runner.start()
    truth: dict = {}
    fused: list = []

    def on_truth(sample):
        try:
            t = decode(sample.payload.to_bytes(), GroundTruth)
        except MessageError:
            return
        if t.T_world_ecm is not None and t.T_world_needle is not None:
            truth[(t.epoch, t.seq)] = np.linalg.inv(t.T_world_ecm) @ t.T_world_needle

    def on_fused(sample):
        try:
            m = decode(sample.payload.to_bytes(), PoseEstimate)
        except MessageError:
            return
        fused.append((time.monotonic(), m.epoch, m.seq, m.T_ecm_needle))
    session = zenoh.open(zenoh_config(launcher.graph, role="node"))
    subs = [session.declare_subscriber(graph.resolve_key("camera/truth"), on_truth),
            session.declare_subscriber(graph.resolve_key("fusion/pose"), on_fused)]
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not fused:
            time.sleep(0.2)
        if not fused:
            raise RuntimeError("no fused pose within 300 s")
        t_clean = time.monotonic()
        time.sleep(clean_s)
        with tempfile.TemporaryDirectory() as tmp:
            path = graph.dump(Path(tmp) / "graph.yaml")          # the graph as its user wrote it
            os.chmod(tmp, 0o755)
            argv = [sys.executable, "-m", "common.robustness.intruder", str(path), "--duration", str(duration),
                    "--offset-mm", str(offset_mm)] + ([] if uid is None else ["--uid", str(uid)])
            t0 = time.monotonic()
            res = subprocess.run(argv, cwd=REPO_ROOT, capture_output=True, text=True, timeout=duration + 120,
                                 env=dict(os.environ, PYTHONPATH=str(REPO_ROOT)))
            t1 = time.monotonic()
        got = json.loads(res.stdout.strip().splitlines()[-1]) if res.returncode == 0 else {"error": res.stderr[-2000:]}
        time.sleep(1.0)
        retired = sorted(nid for nid, sl in launcher.slots.items()
                         if sl.proc is not None and launcher._reported.get(sl.proc.pid) == "retired")
        restarts = {nid: sl.restarts for nid, sl in launcher.slots.items() if sl.restarts}
    finally:
        for x in subs:
            x.undeclare()
        session.close()
        launcher.stop()
        runner.join(30)

    def moved(a, b):
        rows = [(T[:3, 3] - truth[(e, q)][:3, 3])[0] * 1e3 for t, e, q, T in fused if a <= t < b and (e, q) in truth]
        return sum(r > 20.0 for r in rows), len(rows), max(rows, default=float("nan"))
    clean, during = moved(t_clean, t0), moved(t0, t1 + 1.0)
    who = f"uid {got.get('uid')}" if "uid" in got else "?"
    print(f"intruder: {graph.name} ({'zenoh.open: true' if open_graph else 'per-run credentials'}), an intruder "
          f"without the credentials ({who}) for {duration:g} s: {got.get('credentials', '')}")
    if "error" in got:
        print(f"  the intruder failed: {got['error']}")
    print(f"  peers reached {got.get('peers')}; real poses seen {got.get('poses_seen')}; fake poses sent "
          f"{got.get('poses_sent')}; handover answers {got.get('handover_answers')}; swap answers "
          f"{len(got.get('swap_answers') or [])}")
    print(f"  fused poses > 20 mm toward the fake: clean {clean[0]} of {clean[1]}; during the intrusion "
          f"{during[0]} of {during[1]} (largest {during[2]:.1f} mm)")
    print(f"  nodes retired: {retired or 'none'}; restarts: {restarts or 'none'}")
    ok = during[0] == 0 and not retired and not any((got.get("peers") or {"x": 1}).values())
    return 0 if ok or open_graph else 1


def drop_to(uid: int) -> None:
    """Become ``uid`` (and its group; no supplementary groups): needs root."""
    import pwd
    try:
        gid = pwd.getpwuid(uid).pw_gid
    except KeyError:
        gid = uid
    os.setgroups([])
    os.setgid(gid)
    os.setuid(uid)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m common.robustness.intruder", description=__doc__.split("\n\n")[0])
    ap.add_argument("graph", help="the graph's YAML (as launched)")
    ap.add_argument("--uid", type=int, help="run as this user (needs root; e.g. 65534, nobody)")
    ap.add_argument("--duration", type=float, default=5.0, help="seconds of fake poses")
    ap.add_argument("--keys", default=",".join(DEFAULT_KEYS), help="pose keys to forge (relative to the graph)")
    ap.add_argument("--offset-mm", type=float, default=OFFSET_MM, help="how far the forged poses are moved (x)")
    args = ap.parse_args(argv)
    import numpy  # noqa: F401  (everything imported before the uid changes: the new user may not read it)
    import zenoh  # noqa: F401

    import common.runtime.messages  # noqa: F401
    from common.runtime.graph import load_graph
    from common.runtime import credentials
    graph = load_graph(Path(args.graph))
    try:
        victim = credentials.run_dir(graph)      # where the launching user's credentials are
    except credentials.CredentialsError:
        victim = None
    if args.uid is not None:
        drop_to(args.uid)
        os.environ.pop("XDG_RUNTIME_DIR", None)
        os.environ.pop("NEEDLETRACK_RUN_DIR", None)
    print(json.dumps(probe(graph, victim, args.duration, args.keys.split(","), args.offset_mm)), flush=True)
    sys.stdout.flush()
    os._exit(0)                                # (a zenoh session's threads can hold the exit)


if __name__ == "__main__":
    main()
