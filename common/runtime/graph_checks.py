"""The graph YAML checked: ``validate_graph`` (every error at once, each with its place),
``graph_cycles``, ``graph_warnings`` (what runs but is risky: a graph open to other hosts)."""
from __future__ import annotations

import re
from typing import Any, Optional

from common.runtime.graph import (
    available_modules,
    _ENDPOINT_RE,
    Graph,
    LAUNCHER_IDENTITY,
    module_info,
    _MODULE_RE,
    _NAME_RE,
    _NODE_KEYS,
    RESTART_POLICIES,
    _TLS_KEYS,
    _TOP_KEYS,
    _ZENOH_KEYS,
    ZENOH_MODES,
)
from common.runtime.zenoh_session import _endpoint_host, _is_loopback


def _tname(v) -> str:
    return {dict: "map", list: "list", str: "string", int: "int", float: "number", bool: "bool",
            type(None): "null"}.get(type(v), type(v).__name__)


def validate_graph(data: Any) -> list:
    """Every error of a parsed graph document, each prefixed with its place; [] if valid."""
    errs: list[str] = []
    if not isinstance(data, dict):
        return [f"top level: expected a map with keys graph, zenoh, nodes; got {_tname(data)}"]
    for k in data:
        if k not in _TOP_KEYS:
            errs.append(f"{k}: unknown key (allowed: {', '.join(sorted(_TOP_KEYS))})")
    name = data.get("graph")
    if name is None:
        errs.append("graph: missing (the key prefix of the graph, e.g. 'needletrack')")
    elif not isinstance(name, str) or not _NAME_RE.match(name):
        errs.append(f"graph: must be a name of letters, digits, '_', '-', '.'; got {name!r}")

    z = data.get("zenoh", {})
    if z is None:
        z = {}
    if not isinstance(z, dict):
        errs.append(f"zenoh: expected a map, got {_tname(z)}")
    else:
        for k in z:
            if k not in _ZENOH_KEYS:
                errs.append(f"zenoh.{k}: unknown key (allowed: {', '.join(sorted(_ZENOH_KEYS))})")
        if "mode" in z and z["mode"] not in ZENOH_MODES:
            errs.append(f"zenoh.mode: must be one of {', '.join(ZENOH_MODES)}; got {z['mode']!r}")
        for k in ("listen", "connect"):
            if k in z:
                v = z[k]
                if not isinstance(v, list):
                    errs.append(f"zenoh.{k}: expected a list of endpoints, got {_tname(v)}")
                    continue
                for i, e in enumerate(v):
                    if not isinstance(e, str) or not _ENDPOINT_RE.match(e):
                        errs.append(f"zenoh.{k}[{i}]: not an endpoint like 'tcp/127.0.0.1:7447': {e!r}")
                    elif e.startswith("tls/") and "tls" not in z:
                        errs.append(f"zenoh.{k}[{i}]: {e!r} is a TLS endpoint: configure zenoh.tls "
                                    f"{{ca, cert, key}} (certificates: `needletrack certs`; docs/multi-host.md)")
                    elif "tls" in z and not e.startswith("tls/"):
                        errs.append(f"zenoh.{k}[{i}]: {e!r}: with zenoh.tls every endpoint must be tls/ "
                                    f"(another protocol would bypass TLS and access control)")
                    elif "tls" not in z and z.get("open") is not True and not e.startswith(("tcp/", "tls/")):
                        errs.append(f"zenoh.{k}[{i}]: {e!r}: the per-run credentials (the default) need tcp/ "
                                    f"endpoints (they run as tls/); use tcp/, zenoh.tls, or zenoh.open: true")
        if "open" in z and not isinstance(z["open"], bool):
            errs.append(f"zenoh.open: expected true or false, got {z['open']!r}")
        elif z.get("open") is True and "tls" in z:
            errs.append("zenoh.open: true contradicts zenoh.tls (a TLS graph admits only its certificates): "
                        "remove one")
        if "tls" in z:
            errs += _tls_errors(z["tls"])
        if "shm_pool_mb" in z and (isinstance(z["shm_pool_mb"], bool) or not isinstance(z["shm_pool_mb"], int)
                                   or z["shm_pool_mb"] < 0):
            errs.append(f"zenoh.shm_pool_mb: expected a non-negative int, got {z['shm_pool_mb']!r}")

    pv = data.get("pose_volume_m")
    if pv is not None and (isinstance(pv, bool) or not isinstance(pv, (int, float)) or not 0 < pv < 1e6):
        errs.append(f"pose_volume_m: expected a positive number of metres, got {pv!r}")

    nodes = data.get("nodes")
    if nodes is None:
        errs.append("nodes: missing (a list of nodes)")
        return errs
    if not isinstance(nodes, list):
        errs.append(f"nodes: expected a list, got {_tname(nodes)}")
        return errs
    if not nodes:
        errs.append("nodes: empty")

    # first pass: ids and outputs, so that inputs can be checked against them
    ids: dict[str, int] = {}
    outputs: dict[str, Optional[list]] = {}
    for i, n in enumerate(nodes):
        if not isinstance(n, dict):
            continue
        nid = n.get("id")
        if isinstance(nid, str) and _NAME_RE.match(nid):
            if nid in ids:
                errs.append(f"nodes[{i}].id: duplicate id {nid!r} (also nodes[{ids[nid]}])")
            else:
                ids[nid] = i
                outs = n.get("outputs")
                if outs is None and isinstance(n.get("module"), str):
                    info = module_info(n["module"]) if _MODULE_RE.match(n["module"]) else None
                    outs = info["outputs"] if info else None
                outputs[nid] = outs if isinstance(outs, list) else None

    for i, n in enumerate(nodes):
        at = f"nodes[{i}]"
        if not isinstance(n, dict):
            errs.append(f"{at}: expected a map with id and module, got {_tname(n)}")
            continue
        for k in n:
            if k not in _NODE_KEYS:
                errs.append(f"{at}.{k}: unknown key (allowed: {', '.join(sorted(_NODE_KEYS))})")
        nid = n.get("id")
        if nid is None:
            errs.append(f"{at}.id: missing")
        elif not isinstance(nid, str) or not _NAME_RE.match(nid) or nid in ("cmd",):
            errs.append(f"{at}.id: must be a name of letters, digits, '_', '-', '.'; got {nid!r}")
        elif nid == LAUNCHER_IDENTITY and isinstance(z, dict) and "tls" in z:
            errs.append(f"{at}.id: {nid!r} is the launcher's TLS identity (zenoh.tls): rename the node")
        info = None
        has_mod, has_cmd = "module" in n, "command" in n
        if has_mod == has_cmd:
            errs.append(f"{at}: needs exactly one of 'module' (a module of nodes/) or 'command'")
        if has_mod:
            m = n["module"]
            if not isinstance(m, str) or not _MODULE_RE.match(m):
                errs.append(f"{at}.module: expected a module name like 'sim', got {m!r}")
            else:
                info = module_info(m)
                if info is None:
                    errs.append(f"{at}.module: unknown module {m!r}: no file nodes/{m.replace('.', '/')}.py "
                                f"(available: {', '.join(available_modules())})")
                elif info["syntax_error"]:
                    errs.append(f"{at}.module: nodes/{m}.py has a syntax error at {info['syntax_error']}")
                elif not info["has_node"]:
                    errs.append(f"{at}.module: nodes/{m}.py defines no NODE")
        if has_cmd:
            c = n["command"]
            if not isinstance(c, list) or not c or not all(isinstance(a, (str, int, float)) for a in c):
                errs.append(f"{at}.command: expected a non-empty list of strings, got {c!r}")
        if "params" in n and n["params"] is not None and not isinstance(n["params"], dict):
            errs.append(f"{at}.params: expected a map, got {_tname(n['params'])}")
        if "restart" in n and n["restart"] not in RESTART_POLICIES:
            errs.append(f"{at}.restart: must be one of {', '.join(RESTART_POLICIES)}; got {n['restart']!r}")
        if "spare" in n and not isinstance(n["spare"], bool):
            errs.append(f"{at}.spare: expected true or false, got {n['spare']!r}")
        elif n.get("spare") is True and ("module" not in n or n.get("restart") == "never"):
            errs.append(f"{at}.spare: a spare needs a module node that is restarted (restart: on-failure or always)")
        if "env" in n and n["env"] is not None:
            env = n["env"]
            if not isinstance(env, dict):
                errs.append(f"{at}.env: expected a map of NAME: value, got {_tname(env)}")
            else:
                for k, v in env.items():
                    if not isinstance(k, str) or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", k):
                        errs.append(f"{at}.env.{k}: not a valid environment variable name")
                    elif not isinstance(v, (str, int, float, bool)):
                        errs.append(f"{at}.env.{k}: expected a scalar, got {_tname(v)}")
        fb = n.get("feedback")
        if fb is not None and (not isinstance(fb, list) or not all(isinstance(x, str) for x in fb)
                               or not set(fb) <= set(n.get("inputs") or {})):
            errs.append(f"{at}.feedback: expected a list of this node's input names, got {fb!r}")
        outs = n.get("outputs")
        if outs is not None:
            if not isinstance(outs, list):
                errs.append(f"{at}.outputs: expected a list of output names, got {_tname(outs)}")
            else:
                seen = set()
                for j, o in enumerate(outs):
                    if not isinstance(o, str) or not _NAME_RE.match(o) or o == "cmd":
                        errs.append(f"{at}.outputs[{j}]: bad output name {o!r}")
                    elif o in seen:
                        errs.append(f"{at}.outputs[{j}]: duplicate output {o!r}")
                    elif info and info["outputs"] is not None and o not in info["outputs"]:
                        errs.append(f"{at}.outputs[{j}]: module {n['module']!r} has no output {o!r} "
                                    f"(outputs: {', '.join(info['outputs']) or 'none'})")
                    seen.add(o)
        ins = n.get("inputs")
        if ins is not None:
            if not isinstance(ins, dict):
                errs.append(f"{at}.inputs: expected a map of input name -> 'node/output', got {_tname(ins)}")
            else:
                for name, src in ins.items():
                    where = f"{at}.inputs.{name}"
                    if not isinstance(name, str) or not _NAME_RE.match(name):
                        errs.append(f"{where}: bad input name")
                        continue
                    if info and info["inputs"] is not None and name not in info["inputs"]:
                        errs.append(f"{where}: module {n['module']!r} has no input {name!r} "
                                    f"(inputs: {', '.join(info['inputs']) or 'none'})")
                    if not isinstance(src, str) or src.count("/") != 1:
                        errs.append(f"{where}: expected 'node/output', got {src!r}")
                        continue
                    sid, sout = src.split("/")
                    if sid not in ids:
                        errs.append(f"{where}: no node {sid!r}")
                    elif outputs.get(sid) is not None and sout not in outputs[sid]:
                        errs.append(f"{where}: node {sid!r} has no output {sout!r} "
                                    f"(outputs: {', '.join(map(str, outputs[sid])) or 'none'})")
    if not errs:
        errs += graph_cycles(nodes)
    return errs


def graph_cycles(nodes: list) -> list:
    """Errors for the cycles of a graph's wiring: a message could circulate for ever. An input a
    module lists in its class's ``FEEDBACK`` (e.g. replay's ``ack``: acknowledgements, never
    published on), or a node lists under ``feedback:`` in the graph, is a declared feedback edge
    and left out."""
    edges: dict = {n["id"]: set() for n in nodes}
    for n in nodes:
        info = module_info(n["module"]) if n.get("module") else None
        feedback = set((info or {}).get("feedback") or ()) | set(n.get("feedback") or ())
        for name, src in (n.get("inputs") or {}).items():
            if name not in feedback:
                edges.setdefault(src.split("/")[0], set()).add(n["id"])
    errs, state, stack = [], {}, []

    def visit(u):
        state[u] = 1
        stack.append(u)
        for v in sorted(edges.get(u, ())):
            if state.get(v) == 1:
                cyc = stack[stack.index(v):] + [v]
                errs.append(f"nodes: cycle {' -> '.join(cyc)}: a message can circulate for ever "
                            "(a feedback input must be listed in its module's FEEDBACK)")
            elif v not in state:
                visit(v)
        stack.pop()
        state[u] = 2

    for u in sorted(edges):
        if u not in state:
            visit(u)
    return errs


def _tls_errors(t: Any) -> list:
    if not isinstance(t, dict):
        return [f"zenoh.tls: expected a map {{ca, cert, key}}, got {_tname(t)}"]
    errs = [f"zenoh.tls.{k}: unknown key (allowed: {', '.join(sorted(_TLS_KEYS))})" for k in t if k not in _TLS_KEYS]
    for k in ("ca", "cert", "key"):
        v = t.get(k)
        if v is None:
            errs.append(f"zenoh.tls.{k}: missing (a PEM file path" + (")" if k == "ca" else ", with {id})"))
        elif not isinstance(v, str) or not v:
            errs.append(f"zenoh.tls.{k}: expected a file path, got {v!r}")
        elif k != "ca" and "{id}" not in v:
            errs.append(f"zenoh.tls.{k}: must contain '{{id}}' (each node, and the launcher, has its own "
                        f"certificate: e.g. 'certs/{{id}}.{'pem' if k == 'cert' else 'key'}'); got {v!r}")
    if "verify_name" in t and not isinstance(t["verify_name"], bool):
        errs.append(f"zenoh.tls.verify_name: expected true or false, got {t['verify_name']!r}")
    return errs


def graph_warnings(graph: "Graph") -> list:
    """What is allowed but unsafe: ``zenoh.open: true`` (no credentials), and then a listen
    endpoint on a non-loopback address."""
    if not graph.zenoh.open:
        return []
    warns = ["zenoh.open: true: the graph runs without credentials: any local process can publish poses, "
             "send commands, swap and hand over nodes (for interop set-ups only; docs/runtime.md)"]
    for i, e in enumerate(graph.zenoh.listen):
        host = _endpoint_host(e)
        if not e.startswith("tls/") and host is not None and not _is_loopback(host):
            warns.append(f"zenoh.listen[{i}]: {e!r} listens beyond this host without TLS: any process "
                         f"that reaches it can publish poses and send commands (use tls/ and zenoh.tls; "
                         f"docs/multi-host.md)")
    return warns
