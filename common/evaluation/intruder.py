"""An intruder on a running graph: a local process without the run's credentials, optionally
of another user (``--uid``), that tries to steer it (issue 32's probe).

``python -m common.evaluation.intruder GRAPH.yaml [--uid N] [--duration S] [--keys K,...]``
prints one JSON line of what it got: the peers it reached with each of its sessions (plain TCP
to the graph's endpoint; TLS trusting the run's CA when it can read it, with no certificate),
whether it could read the run's credentials, the fake ``PoseEstimate``s it sent (copies of the
real poses on ``--keys`` it saw, moved ``--offset-mm`` along x; blind ones with the newest seq
when it sees none), and the answers to a handover query on ``<graph>/@ctl/*/*/handover`` and a
swap on ``<graph>/@launcher/swap``. On an open graph (``zenoh.open: true``, or before per-run
credentials) everything gets in; on the default graph nothing does. ``needletrack bench fuzz
--live`` runs it against the default graph; ``tests/test_credentials.py`` as another user.
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
                    if msg.method == "forged" or abs(msg.T_ecm_needle[0, 3] - shift[0, 3]) < 1e-9:
                        return
                    with lock:
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
        for x in subs + pubs:
            x.undeclare()
    finally:
        for _, s in sessions:
            s.close()
    return out


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
    ap = argparse.ArgumentParser(prog="python -m common.evaluation.intruder", description=__doc__.split("\n\n")[0])
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
