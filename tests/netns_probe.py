"""A member or an intruder of a graph, run in a network namespace by tests/runtime/test_multihost_tls.py.

``python tests/netns_probe.py GRAPH AS ACTION [ARGS]`` prints one JSON line ``{"peers": n, ...}``.

AS: ``launcher`` or a node id (that identity's certificate, as in the graph's ``zenoh.tls``),
``nocert`` (trusts the graph's CA but has no certificate), or ``rogue:DIR`` (``DIR/rogue.pem``
and ``.key``: a certificate of another CA that claims the launcher's common name).

ACTION: ``stats NODE`` (the node's newest stats counters), ``poses KEY N`` (publish N forged
poses), ``cmd NODE NAME`` (send a command), ``swap NODE MODULE`` (ask the launcher for a swap;
prints the answers), ``attack KEY N NODE`` (N forged poses on KEY, a ``reset`` command to NODE
and a swap of NODE), ``control KEY N`` (publish poses on KEY until N of them come out of fusion:
what a legitimate member sees happen).
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402
import zenoh  # noqa: E402

from common.runtime.graph import launcher_key, load_graph, stats_key
from common.runtime.zenoh_session import zenoh_config
from common.runtime.messages import Command, NodeStats, PoseEstimate, decode, encode  # noqa: E402

FORGED_T = np.eye(4)
FORGED_T[:3, 3] = (0.05, -0.05, 0.3)


def intruder_config(graph, cert=None, key=None):
    """Connect-only TLS to the graph's endpoints, trusting its CA; a client certificate if given."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps(list(graph.zenoh.listen)))
    t = "transport/link/tls/"
    c.insert_json5(t + "root_ca_certificate", json.dumps(graph.zenoh.tls.ca))
    c.insert_json5(t + "verify_name_on_connect", "false")
    if cert:
        for side in ("listen", "connect"):
            c.insert_json5(t + f"{side}_certificate", json.dumps(str(cert)))
            c.insert_json5(t + f"{side}_private_key", json.dumps(str(key)))
    return c


def pose(seq: int, stamp_ns: int, T=FORGED_T, method: str = "forged") -> bytes:
    return encode(PoseEstimate(seq, stamp_ns, method, T.copy(), residual=0.0, residual_unit="m"))


def main(argv: list) -> dict:
    graph = load_graph(argv[0])
    who, action, args = argv[1], argv[2], argv[3:]
    if who == "nocert":
        cfg = intruder_config(graph)
    elif who.startswith("rogue:"):
        d = Path(who.split(":", 1)[1])
        cfg = intruder_config(graph, d / "rogue.pem", d / "rogue.key")
    else:
        cfg = zenoh_config(graph, role="node", identity=who)
    session = zenoh.open(cfg)
    out: dict = {}
    try:
        deadline = time.monotonic() + (4.0 if who == "nocert" or who.startswith("rogue:") else 20.0)
        while time.monotonic() < deadline and not list(session.info.peers_zid()):
            time.sleep(0.05)
        time.sleep(1.0)                  # gossip: the peers' declarations arrive
        out["peers"] = len(list(session.info.peers_zid()))
        g = graph.name
        if action == "stats":
            got: list = []
            sub = session.declare_subscriber(stats_key(g, args[0]),
                                             lambda s: got.append(decode(s.payload.to_bytes(), NodeStats)))
            t_end = time.monotonic() + 60.0
            while time.monotonic() < t_end and not got:
                time.sleep(0.05)
            sub.undeclare()
            out["counters"] = got[-1].counters if got else None
            out["pid"] = got[-1].pid if got else None
        elif action == "poses":
            key, n = f"{g}/{args[0]}", int(args[1])
            for i in range(n):
                session.put(key, pose(100_000 + i, time.time_ns()))
                time.sleep(0.02)
            out["sent"] = n
        elif action == "attack":          # forged poses on KEY, a reset to NODE, a swap of NODE
            key, n, node = f"{g}/{args[0]}", int(args[1]), args[2]
            for i in range(n):
                session.put(key, pose(100_000 + i, time.time_ns()))
                time.sleep(0.02)
            session.put(f"{g}/{node}/cmd", encode(Command("reset", None)))
            answers = []
            for reply in session.get(launcher_key(g, "swap"), timeout=5.0,
                                     payload=json.dumps({"node": node, "params": {"k": 9}}).encode()):
                answers.append(reply.ok.payload.to_bytes().decode() if reply.ok is not None else "error")
            out.update(sent=n, answers=answers)
        elif action == "cmd":
            session.put(f"{g}/{args[0]}/cmd", encode(Command(args[1], None)))
            out["sent"] = 1
        elif action == "swap":
            answers = []
            for reply in session.get(launcher_key(g, "swap"), timeout=10.0,
                                     payload=json.dumps({"node": args[0], "module": args[1]}).encode()):
                answers.append(reply.ok.payload.to_bytes().decode() if reply.ok is not None else "error")
            out["answers"] = answers
        elif action == "control":
            key, n = f"{g}/{args[0]}", int(args[1])
            T = np.eye(4)
            T[2, 3] = 0.1
            stamps: set = set()
            fused: set = set()
            sub = session.declare_subscriber(f"{g}/fusion/pose",
                                             lambda s: fused.add(decode(s.payload.to_bytes(), PoseEstimate).stamp_ns))
            pub = session.declare_publisher(key)
            t_end, seq = time.monotonic() + 60.0, 1000
            while time.monotonic() < t_end and not pub.matching_status.matching:   # the fusion subscribes
                time.sleep(0.05)
            time.sleep(0.5)
            while time.monotonic() < t_end and len(stamps & fused) < n:
                stamp = time.time_ns()
                if len(stamps) < n:     # exactly n poses: the fusion's input count is checked against it
                    stamps.add(stamp)
                    pub.put(pose(seq, stamp, T, "control"))
                    seq += 1
                time.sleep(0.3)
            sub.undeclare()
            pub.undeclare()
            out["sent"], out["fused"] = len(stamps), len(stamps & fused)
        else:
            raise SystemExit(f"unknown action {action!r}")
    finally:
        session.close()
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1:])), flush=True)
