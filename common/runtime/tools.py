"""Graph tools of the CLI: ``validate``, ``ps``, ``echo``, ``hz``, ``swap``, ``cmd``.

Each opens a short-lived Zenoh session that joins the graph at its ``listen`` endpoint
(``-g/--graph FILE``, default ``dataflow.yaml``), so it sees only that graph.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import defaultdict, deque
from pathlib import Path
from typing import Optional

import numpy as np

from common.runtime.graph import (
    REPO_ROOT,
    GraphError,
    launcher_key,
    live_key,
    load_graph,
    parse_param,
    stats_key,
)


def _graph_arg(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("-g", "--graph", default="dataflow.yaml", help="graph YAML (default: dataflow.yaml)")


def _load(path: str):
    p = Path(path)
    if not p.exists() and path == "dataflow.yaml":
        p = REPO_ROOT / "dataflow.yaml"
    return load_graph(p)


def load_or_report(path: str):
    """The graph, or None after printing why it cannot be loaded (the caller exits 2)."""
    try:
        return _load(path)
    except GraphError as exc:
        print(str(exc), file=sys.stderr)
        return None


def open_session(graph, wait_s: float = 2.0):
    """A Zenoh session joined to ``graph`` (connects to its listen endpoints; under TLS, the
    graph's own or its launcher's per-run credentials, with the launcher's certificate: the
    operator's identity that may send commands; exits 1 saying so when the graph has no run
    credentials for this user, i.e. it is not running); waits up to
    ``wait_s`` for a first peer so that queries and liveliness see the graph at once."""
    import zenoh

    from common.runtime.credentials import CredentialsError
    from common.runtime.zenoh_session import zenoh_config
    try:
        cfg = zenoh_config(graph, role="node")     # as the launcher identity, on the run's credentials
    except CredentialsError as exc:                # not running for this user: say so, exit 1
        print(f"needletrack: {exc.errors[0]}", file=sys.stderr)
        raise SystemExit(1) from None
    session = zenoh.open(cfg)
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and not list(session.info.peers_zid()):
        time.sleep(0.02)
    time.sleep(0.1)   # gossip: let the peers' declarations arrive
    return session


# ------------------------------------------------------------------ validate

def validate_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack validate", description="Check graph YAML files; exit 2 on errors.")
    ap.add_argument("graphs", nargs="*", default=["dataflow.yaml"])
    args = ap.parse_args(argv)
    rc = 0
    for path in args.graphs:
        try:
            g = _load(path)
        except GraphError as exc:
            print(str(exc), file=sys.stderr)
            rc = 2
            continue
        from common.runtime.node import graph_param_errors
        errors = graph_param_errors(g)
        if errors:
            print(f"{path}: {len(errors)} error(s):\n" + "\n".join(f"  {e}" for e in errors), file=sys.stderr)
            rc = 2
            continue
        from common.runtime.graph_checks import graph_warnings
        for w in graph_warnings(g):
            print(f"{path}: WARNING {w}", file=sys.stderr)
        print(f"{path}: ok: graph {g.name!r}, {len(g.nodes)} nodes ({', '.join(g.ids())})"
              + (" over mutual TLS with access control" if g.zenoh.tls is not None else ""))
    return rc


# ------------------------------------------------------------------ ps

def query_json(session, key: str, timeout: float = 2.0, payload: Optional[dict] = None) -> list:
    kw = {"timeout": timeout}
    if payload is not None:
        kw["payload"] = json.dumps(payload).encode()
    out = []
    for reply in session.get(key, **kw):
        if reply.ok is not None:
            out.append(json.loads(reply.ok.payload.to_bytes().decode()))
    return out


def collect_stats(session, graph_name: str, wait_s: float = 1.3) -> dict:
    """Newest ``NodeStats`` per (node, pid) seen within ``wait_s``."""
    from common.runtime.messages import NodeStats, decode
    seen: dict = {}
    lock = threading.Lock()

    def cb(sample):
        try:
            st = decode(sample.payload.to_bytes(), NodeStats)
        except Exception:
            return
        with lock:
            seen[(st.node, st.pid)] = st
    sub = session.declare_subscriber(stats_key(graph_name), cb)
    time.sleep(wait_s)
    sub.undeclare()
    with lock:
        return dict(seen)


def live_nodes(session, graph_name: str, timeout: float = 1.0) -> set:
    """The ids of the graph's nodes whose liveliness token is up."""
    live = set()
    for reply in session.liveliness().get(live_key(graph_name), timeout=timeout):
        if reply.ok is not None:
            live.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
    return live


def ps_rows(session, graph) -> list:
    live = live_nodes(session, graph.name)
    stats = collect_stats(session, graph.name)
    launcher = query_json(session, launcher_key(graph.name, "status"), timeout=1.0)
    lstat = {r["node"]: r for L in launcher for r in L["nodes"]}
    rows = []
    ids = list(dict.fromkeys(graph.ids() + sorted(live) + sorted(n for n, _ in stats)))
    for nid in ids:
        sts = [s for (n, _), s in stats.items() if n == nid]
        if not sts and nid not in live and nid not in lstat:
            continue
        for st in sts or [None]:
            c = st.counters if st else {}
            r = st.rates_hz if st else {}
            rows.append({
                "node": nid, "pid": st.pid if st else (lstat.get(nid) or {}).get("pid"),
                "live": nid in live, "state": c.get("state", (lstat.get(nid) or {}).get("state", "?")),
                "module": st.module if st else (lstat.get(nid) or {}).get("module", ""),
                "up_s": st.uptime_s if st else None,
                "in_hz": sum(v for k, v in r.items() if k.startswith("in.") and k != "in.cmd"),
                "out_hz": sum(v for k, v in r.items() if k.startswith("out.")),
                "dropped": c.get("dropped", 0), "decode_errors": c.get("decode_errors", 0),
                "handler_errors": c.get("handler_errors", 0) + c.get("step_errors", 0),
                "restarts": (lstat.get(nid) or {}).get("restarts", c.get("restarts", 0)),
                "p50_ms": st.proc_ms_p50 if st else None, "p99_ms": st.proc_ms_p99 if st else None})
    return rows


def ps_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack ps", description="Live nodes of a graph: rates and error counts.")
    _graph_arg(ap)
    ap.add_argument("--json", action="store_true", help="print JSON rows")
    args = ap.parse_args(argv)
    graph = load_or_report(args.graph)
    if graph is None:
        return 2
    session = open_session(graph)
    try:
        rows = ps_rows(session, graph)
    finally:
        session.close()
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0 if rows else 1
    if not rows:
        print(f"no live nodes in graph {graph.name!r} at {', '.join(graph.zenoh.listen)}", file=sys.stderr)
        return 1
    cols = [("node", "NODE", "{}"), ("pid", "PID", "{}"), ("state", "STATE", "{}"), ("live", "LIVE", "{}"),
            ("module", "MODULE", "{}"), ("up_s", "UP_S", "{:.0f}"), ("in_hz", "IN_HZ", "{:.1f}"),
            ("out_hz", "OUT_HZ", "{:.1f}"), ("dropped", "DROPPED", "{}"), ("decode_errors", "DEC_ERR", "{}"),
            ("handler_errors", "ERR", "{}"), ("restarts", "RESTARTS", "{}"), ("p50_ms", "P50_MS", "{:.1f}"),
            ("p99_ms", "P99_MS", "{:.1f}")]
    table = [[h for _, h, _ in cols]] + [["-" if r[k] is None else f.format(r[k]) for k, _, f in cols] for r in rows]
    widths = [max(len(row[i]) for row in table) for i in range(len(cols))]
    for row in table:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths)))
    return 0


# ------------------------------------------------------------------ echo / hz

def summarize(value, width: int = 120) -> str:
    """A short, one-line rendering of a message field."""
    if isinstance(value, np.ndarray):
        if value.size <= 16:
            return np.array2string(value, precision=4, suppress_small=True, max_line_width=10_000).replace("\n", "")
        return f"<{value.dtype}{list(value.shape)}>"
    if isinstance(value, (bytes, bytearray, memoryview)):
        return f"<{len(value)} bytes>"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {summarize(v, 40)}" for k, v in value.items()) + "}"
    s = repr(value)
    return s if len(s) <= width else s[:width - 3] + "..."


def format_message(key: str, msg) -> str:
    fields = ", ".join(f"{k}={summarize(v)}" for k, v in msg.to_body().items() if v is not None)
    return f"{key} {type(msg).__name__}({fields})"


def echo_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack echo", description="Print decoded messages on a key.")
    _graph_arg(ap)
    ap.add_argument("key", help="key expression; relative keys (camera/left) get the graph prefix")
    ap.add_argument("-n", "--count", type=int, default=0, help="exit after this many messages")
    ap.add_argument("--timeout", type=float, default=0, help="exit after this many seconds")
    args = ap.parse_args(argv)
    from common.runtime.messages import MessageError, decode
    graph = load_or_report(args.graph)
    if graph is None:
        return 2
    key = graph.resolve_key(args.key)
    done = threading.Event()
    n = [0]

    def cb(sample):
        if done.is_set():
            return
        k = str(sample.key_expr)
        try:
            line = format_message(k, decode(sample.payload.to_bytes()))
        except MessageError as exc:
            line = f"{k} <undecodable {len(sample.payload)} bytes: {exc}>"
        print(line, flush=True)
        n[0] += 1
        if args.count and n[0] >= args.count:
            done.set()
    session = open_session(graph)
    sub = session.declare_subscriber(key, cb)
    try:
        done.wait(args.timeout or None)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        session.close()
    return 0 if n[0] or not args.count else 1


class RateMeter:
    """Per-key message counts, intervals and sizes over a sliding window."""

    def __init__(self, window: int = 300):
        self.times: dict = defaultdict(lambda: deque(maxlen=window))
        self.sizes: dict = defaultdict(lambda: deque(maxlen=window))
        self.total: dict = defaultdict(int)
        self.lock = threading.Lock()

    def add(self, key: str, size: int, t: Optional[float] = None) -> None:
        with self.lock:
            self.times[key].append(time.monotonic() if t is None else t)
            self.sizes[key].append(size)
            self.total[key] += 1

    def report(self) -> dict:
        out = {}
        with self.lock:
            for k, ts in self.times.items():
                if len(ts) < 2:
                    out[k] = {"hz": 0.0, "n": self.total[k]}
                    continue
                dts = np.diff(np.asarray(ts))
                out[k] = {"hz": float(1.0 / dts.mean()) if dts.mean() > 0 else float("inf"),
                          "min_ms": float(dts.min() * 1e3), "max_ms": float(dts.max() * 1e3),
                          "std_ms": float(dts.std() * 1e3), "bytes": float(np.mean(self.sizes[k])),
                          "n": self.total[k]}
        return out


def hz_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack hz", description="Print message rates on a key (once a second).")
    _graph_arg(ap)
    ap.add_argument("key", help="key expression; relative keys (camera/left) get the graph prefix")
    ap.add_argument("--duration", type=float, default=0, help="exit after this many seconds")
    ap.add_argument("--window", type=int, default=300, help="messages in the sliding window")
    args = ap.parse_args(argv)
    graph = load_or_report(args.graph)
    if graph is None:
        return 2
    meter = RateMeter(args.window)
    session = open_session(graph)
    sub = session.declare_subscriber(graph.resolve_key(args.key),
                                     lambda s: meter.add(str(s.key_expr), len(s.payload)))
    t_end = time.monotonic() + args.duration if args.duration else None
    try:
        while t_end is None or time.monotonic() < t_end:
            time.sleep(1.0)
            rep = meter.report()
            if not rep:
                print(f"{graph.resolve_key(args.key)}: no messages", flush=True)
            for k, r in sorted(rep.items()):
                if "min_ms" in r:
                    print(f"{k}: {r['hz']:.2f} Hz  interval min {r['min_ms']:.1f} ms max {r['max_ms']:.1f} ms "
                          f"std {r['std_ms']:.1f} ms  {r['bytes'] / 1e3:.1f} kB/msg  n={r['n']}", flush=True)
                else:
                    print(f"{k}: n={r['n']}", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        session.close()
    return 0


# ------------------------------------------------------------------ swap / cmd

def swap_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack swap",
                                 description="Replace a running node by another module and/or params, make-before-break.")
    _graph_arg(ap)
    ap.add_argument("node", help="node id")
    ap.add_argument("--module", help="the new module (nodes/<module>.py); default: the same")
    ap.add_argument("--param", action="append", default=[], metavar="K=V", help="set a param (YAML value); repeatable")
    ap.add_argument("--unset", action="append", default=[], metavar="K",
                    help="remove a param (e.g. the old backend's when the detector's backend changes); repeatable")
    ap.add_argument("--timeout", type=float, default=150.0)
    args = ap.parse_args(argv)
    graph = load_or_report(args.graph)
    if graph is None:
        return 2
    try:
        params = dict(parse_param(p) for p in args.param)
    except ValueError as exc:
        print(f"needletrack swap: {exc}", file=sys.stderr)
        return 2
    session = open_session(graph)
    try:
        answers = query_json(session, launcher_key(graph.name, "swap"), timeout=args.timeout,
                             payload={"node": args.node, "module": args.module, "params": params,
                                      "unset": args.unset})
    finally:
        session.close()
    if not answers:
        print(f"needletrack swap: no launcher of graph {graph.name!r} answered at "
              f"{', '.join(graph.zenoh.listen)} (is the graph launched?)", file=sys.stderr)
        return 1
    ans = answers[0]
    if not ans.get("ok"):
        print(f"needletrack swap: {ans.get('error')}", file=sys.stderr)
        for e in ans.get("errors", []):
            print(f"  {e}", file=sys.stderr)
        return 2 if ans.get("errors") else 1
    print(f"swapped {ans['node']}: pid {ans['old_pid']} -> {ans['new_pid']} ({ans['module']}, params {ans['params']}); "
          f"new outputs from seq {ans['cuts'] or '(none yet)'}; ready in {ans['ready_s']:.2f} s")
    return 0


def cmd_main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack cmd", description="Send a Command to a node's cmd key.")
    _graph_arg(ap)
    ap.add_argument("node")
    ap.add_argument("name", help="command name, e.g. place_needle")
    ap.add_argument("args", nargs="*", metavar="K=V", help="command arguments (YAML values)")
    args = ap.parse_args(argv)
    from common.runtime.graph import cmd_key
    from common.runtime.messages import Command, encode
    from common.runtime.params import did_you_mean
    try:
        graph = _load(args.graph)
        cargs = dict(parse_param(a) for a in args.args)
        payload = encode(Command(args.name, cargs))
    except (GraphError, ValueError, TypeError) as exc:
        print(f"needletrack cmd: {exc}", file=sys.stderr)
        return 2
    if args.node not in graph.ids():
        print(f"needletrack cmd: graph {graph.name!r} has no node {args.node!r} "
              f"({did_you_mean(args.node, graph.ids())})", file=sys.stderr)
        return 2
    session = open_session(graph)
    try:
        live = live_nodes(session, graph.name)
        if args.node in live:
            session.put(cmd_key(graph.name, args.node), payload)
            time.sleep(0.1)
    finally:
        session.close()
    if args.node not in live:
        print(f"needletrack cmd: no node answered: {args.node!r} of graph {graph.name!r} is not running at "
              f"{', '.join(graph.zenoh.listen)} ({'running: ' + ', '.join(sorted(live)) if live else 'is the graph launched?'}); "
              f"nothing sent", file=sys.stderr)
        return 1
    print(f"sent {args.name} {cargs} to {graph.name}/{args.node}")
    return 0
