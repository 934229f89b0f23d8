"""The graph YAML checked: ``validate_graph`` (every error at once, each with its place),
``graph_cycles``, ``graph_warnings`` (what runs but is risky: a graph open to other hosts)."""
from __future__ import annotations

import re
from typing import Any, Optional

from common.runtime.graph import (
    ENDPOINT_RE,
    FEEDBACK_ERROR,
    LAUNCHER_IDENTITY,
    NAME_RE,
    Graph,
    NodeSpec,
    TlsSettings,
    ZenohSettings,
    available_modules,
    module_info,
)
from common.runtime.schema import kind_name, section_errors, unknown_key_errors
from common.runtime.zenoh_session import endpoint_host, is_loopback


def validate_graph(data: Any) -> list:
    """Every error of a parsed graph document, each prefixed with its place; [] if valid. Each
    field's own checks are declared on it (``Graph``, ``ZenohSettings``, ``TlsSettings``,
    ``NodeSpec``: ``common.runtime.schema.section_errors``); what joins fields is checked here."""
    if not isinstance(data, dict):
        return [f"top level: expected a map with keys graph, zenoh, nodes; got {kind_name(data)}"]
    errs = unknown_key_errors("", Graph, data) + section_errors("", Graph, data, ("graph", "zenoh"))
    z = data.get("zenoh") or {}
    if isinstance(z, dict):
        errs += unknown_key_errors("zenoh.", ZenohSettings, z) + section_errors("zenoh.", ZenohSettings, z, ("mode",))
        for k in ("listen", "connect"):
            wrong = section_errors("zenoh.", ZenohSettings, z, (k,))
            errs += wrong
            for i, e in enumerate(z[k] if k in z and not wrong else ()):
                if not isinstance(e, str) or not ENDPOINT_RE.match(e):
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
        wrong = section_errors("zenoh.", ZenohSettings, z, ("open",))
        errs += wrong
        if not wrong and z.get("open") is True and "tls" in z:
            errs.append("zenoh.open: true contradicts zenoh.tls (a TLS graph admits only its certificates): "
                        "remove one")
        if "tls" in z:
            errs += _tls_errors(z)
        errs += section_errors("zenoh.", ZenohSettings, z, ("shm_pool_mb",))
    errs += section_errors("", Graph, data, ("pose_volume_m",))

    wrong = section_errors("", Graph, data, ("nodes",))
    if wrong:
        return errs + wrong
    nodes = data["nodes"]
    if not nodes:
        errs.append("nodes: empty")

    # first pass: ids and outputs, so that inputs can be checked against them
    ids: dict[str, int] = {}
    outputs: dict[str, Optional[list]] = {}
    for i, n in enumerate(nodes):
        if not isinstance(n, dict):
            continue
        nid = n.get("id")
        if isinstance(nid, str) and NAME_RE.match(nid):
            if nid in ids:
                errs.append(f"nodes[{i}].id: duplicate id {nid!r} (also nodes[{ids[nid]}])")
            else:
                ids[nid] = i
                outs = n.get("outputs")
                if outs is None and isinstance(n.get("module"), str):
                    info = module_info(n["module"]) if not section_errors("", NodeSpec, n, ("module",)) else None
                    outs = info["outputs"] if info else None
                outputs[nid] = outs if isinstance(outs, list) else None

    for i, n in enumerate(nodes):
        at = f"nodes[{i}]"
        if not isinstance(n, dict):
            errs.append(f"{at}: expected a map with id and module, got {kind_name(n)}")
            continue
        errs += _node_errors(at, n, isinstance(z, dict) and "tls" in z, ids, outputs)
    if not errs:
        errs += graph_cycles(nodes)
    return errs


def _node_errors(at: str, n: dict, tls: bool, ids: dict, outputs: dict) -> list:
    """The errors of the graph's node ``n`` (at ``at``), its wiring against the other nodes'
    ``ids`` and ``outputs`` included."""
    errs = unknown_key_errors(f"{at}.", NodeSpec, n)
    wrong = section_errors(f"{at}.", NodeSpec, n, ("id",))
    errs += wrong
    if not wrong and n["id"] == LAUNCHER_IDENTITY and tls:
        errs.append(f"{at}.id: {n['id']!r} is the launcher's TLS identity (zenoh.tls): rename the node")
    info = None
    has_mod, has_cmd = "module" in n, "command" in n
    if has_mod == has_cmd:
        errs.append(f"{at}: needs exactly one of 'module' (a module of nodes/) or 'command'")
    if has_mod:
        wrong = section_errors(f"{at}.", NodeSpec, n, ("module",))
        errs += wrong
        m = n["module"]
        if not wrong:
            info = module_info(m)
            if info is None:
                errs.append(f"{at}.module: unknown module {m!r}: no file nodes/{m.replace('.', '/')}.py "
                            f"(available: {', '.join(available_modules())})")
            elif info["syntax_error"]:
                errs.append(f"{at}.module: nodes/{m}.py has a syntax error at {info['syntax_error']}")
            elif not info["has_node"]:
                errs.append(f"{at}.module: nodes/{m}.py defines no NODE")
    errs += section_errors(f"{at}.", NodeSpec, n, ("command", "params", "restart"))
    wrong = section_errors(f"{at}.", NodeSpec, n, ("spare",))
    errs += wrong
    if not wrong and n.get("spare") is True and ("module" not in n or n.get("restart") == "never"):
        errs.append(f"{at}.spare: a spare needs a module node that is restarted (restart: on-failure or always)")
    wrong = section_errors(f"{at}.", NodeSpec, n, ("env",))
    errs += wrong
    for k, v in (n.get("env") or {}).items() if not wrong else ():
        if not isinstance(k, str) or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", k):
            errs.append(f"{at}.env.{k}: not a valid environment variable name")
        elif not isinstance(v, (str, int, float, bool)):
            errs.append(f"{at}.env.{k}: expected a scalar, got {kind_name(v)}")
    wrong = section_errors(f"{at}.", NodeSpec, n, ("feedback",))
    ins = n.get("inputs")
    if not wrong and not set(n.get("feedback") or ()) <= set(ins if isinstance(ins, (dict, list)) else ()):
        wrong = [f"{at}.feedback: " + FEEDBACK_ERROR.format(value=n["feedback"])]
    errs += wrong
    wrong = section_errors(f"{at}.", NodeSpec, n, ("outputs",))
    errs += wrong
    seen = set()
    for j, o in enumerate(n.get("outputs") or () if not wrong else ()):
        if not isinstance(o, str) or not NAME_RE.match(o) or o == "cmd":
            errs.append(f"{at}.outputs[{j}]: bad output name {o!r}")
        elif o in seen:
            errs.append(f"{at}.outputs[{j}]: duplicate output {o!r}")
        elif info and info["outputs"] is not None and o not in info["outputs"]:
            errs.append(f"{at}.outputs[{j}]: module {n['module']!r} has no output {o!r} "
                        f"(outputs: {', '.join(info['outputs']) or 'none'})")
        seen.add(o)
    wrong = section_errors(f"{at}.", NodeSpec, n, ("inputs",))
    errs += wrong
    for name, src in (ins or {}).items() if not wrong else ():
        where = f"{at}.inputs.{name}"
        if not isinstance(name, str) or not NAME_RE.match(name):
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


def _tls_errors(z: dict) -> list:
    """The errors of ``zenoh.tls``: the section's declared fields, and each identity's files
    named with ``{id}``."""
    errs = section_errors("zenoh.", ZenohSettings, z, ("tls",))
    t = z["tls"]
    if errs:
        return errs
    errs = unknown_key_errors("zenoh.tls.", TlsSettings, t)
    for k in ("ca", "cert", "key"):
        wrong = section_errors("zenoh.tls.", TlsSettings, t, (k,))
        errs += wrong
        if k != "ca" and not wrong and "{id}" not in t[k]:
            errs.append(f"zenoh.tls.{k}: must contain '{{id}}' (each node, and the launcher, has its own "
                        f"certificate: e.g. 'certs/{{id}}.{'pem' if k == 'cert' else 'key'}'); got {t[k]!r}")
    return errs + section_errors("zenoh.tls.", TlsSettings, t, ("verify_name",))


def graph_warnings(graph: "Graph") -> list:
    """What is allowed but unsafe: ``zenoh.open: true`` (no credentials), and then a listen
    endpoint on a non-loopback address."""
    if not graph.zenoh.open:
        return []
    warns = ["zenoh.open: true: the graph runs without credentials: any local process can publish poses, "
             "send commands, swap and hand over nodes (for interop set-ups only; docs/runtime.md)"]
    for i, e in enumerate(graph.zenoh.listen):
        host = endpoint_host(e)
        if not e.startswith("tls/") and host is not None and not is_loopback(host):
            warns.append(f"zenoh.listen[{i}]: {e!r} listens beyond this host without TLS: any process "
                         f"that reaches it can publish poses and send commands (use tls/ and zenoh.tls; "
                         f"docs/multi-host.md)")
    return warns
