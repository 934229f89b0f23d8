"""The dataflow graph (``dataflow.yaml``): loading, validation, key names and Zenoh settings.

A graph is a YAML map::

    graph: needletrack            # key prefix of everything the graph publishes
    zenoh: {mode: peer, listen: ["tcp/127.0.0.1:7447"], connect: []}
    # by default a run is mutual TLS on per-run credentials (common/runtime/credentials.py);
    # `open: true` turns that off (interop set-ups: any local process can then steer the graph)
    # across hosts: mutual TLS and access control (docs/multi-host.md)
    #   zenoh: {listen: ["tls/10.0.0.1:7447"],
    #           tls: {ca: certs/ca.pem, cert: "certs/{id}.pem", key: "certs/{id}.key"}}
    nodes:
      - id: camera
        module: sim               # nodes/sim.py, or `command: [prog, arg, ...]`
        params: {rate_hz: 30}
        inputs: {cmd_in: other/out}   # input name -> "<node id>/<output>"
        outputs: [left, right]
        restart: on-failure       # never | on-failure | always
        spare: true               # keep a warm spare process (set up, idle) to take over at once
        env: {OMP_NUM_THREADS: "1"}

``validate_graph`` returns every error at once, each with its place
(``nodes[3].inputs.keypoints: no node 'detektor'``); ``load_graph`` raises ``GraphError`` carrying
that list. Modules are checked without importing them: ``nodes/<module>.py`` must exist and is
parsed (``ast``) for ``NODE``, ``INPUTS`` and ``OUTPUTS`` when they are literals.
"""
from __future__ import annotations

import ast
import copy
import functools
import json
import os
import re
import socket
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

from common.errors import NeedletrackError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
RESTART_POLICIES = ("never", "on-failure", "always")
ZENOH_MODES = ("peer", "client", "router")
NODES_DIR = Path(__file__).resolve().parents[2] / "nodes"
REPO_ROOT = NODES_DIR.parent

_NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
_MODULE_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")
_TOP_KEYS = {"graph", "zenoh", "nodes", "pose_volume_m"}
_ZENOH_KEYS = {"mode", "listen", "connect", "shm_pool_mb", "tls", "open"}
_TLS_KEYS = {"ca", "cert", "key", "verify_name"}
LAUNCHER_IDENTITY = "launcher"     # the TLS identity of launchers and CLI tools (the operator)
_NODE_KEYS = {"id", "module", "command", "params", "inputs", "outputs", "restart", "env", "feedback", "spare"}


class GraphError(NeedletrackError, ValueError):
    """An invalid graph; ``errors`` lists every problem with its place."""

    def __init__(self, errors: list[str], source: str = "graph"):
        self.errors = list(errors)
        self.source = source
        super().__init__(f"{source}: {len(self.errors)} error(s)\n" + "\n".join(f"  {e}" for e in self.errors))


@dataclass
class TlsSettings:
    """Mutual TLS of a graph: ``ca`` (PEM of the CA that signed every member), ``cert``/``key``
    (PEM paths with ``{id}``: the node id, or ``launcher`` for launchers and CLI tools).
    Paths are absolute once loaded (relative ones are taken from the graph file's folder)."""
    ca: str
    cert: str
    key: str
    verify_name: bool = False      # check the peer's certificate names the address connected to

    def files(self, identity: str) -> tuple:
        """(ca, cert, key) paths of ``identity``."""
        return self.ca, self.cert.replace("{id}", identity), self.key.replace("{id}", identity)

    def to_dict(self) -> dict:
        d = {"ca": self.ca, "cert": self.cert, "key": self.key}
        if self.verify_name:
            d["verify_name"] = True
        return d


@dataclass
class ZenohSettings:
    mode: str = "peer"
    listen: list = field(default_factory=lambda: [DEFAULT_ENDPOINT])
    connect: list = field(default_factory=list)
    shm_pool_mb: int = 64
    tls: Optional[TlsSettings] = None
    open: bool = False             # no per-run credentials: any local process may join (a warning)
    run_credentials: Optional[str] = None   # the run directory whose certificates ``tls`` names (not in the YAML)


@dataclass
class NodeSpec:
    id: str
    module: Optional[str] = None
    command: Optional[list] = None
    params: dict = field(default_factory=dict)
    inputs: dict = field(default_factory=dict)      # input name -> "node/output"
    outputs: list = field(default_factory=list)
    restart: str = "on-failure"
    spare: bool = False            # a warm spare process takes over when the node's process exits
    env: dict = field(default_factory=dict)
    feedback: list = field(default_factory=list)    # inputs that close a declared cycle (acks)

    def to_dict(self) -> dict:
        d = {"id": self.id}
        if self.module is not None:
            d["module"] = self.module
        if self.command is not None:
            d["command"] = list(self.command)
        d.update(params=copy.deepcopy(self.params), inputs=dict(self.inputs), outputs=list(self.outputs),
                 restart=self.restart)
        if self.env:
            d["env"] = dict(self.env)
        if self.feedback:
            d["feedback"] = list(self.feedback)
        if self.spare:
            d["spare"] = True
        return d


@dataclass
class Graph:
    name: str
    zenoh: ZenohSettings
    nodes: list
    path: Optional[Path] = None
    pose_volume_m: Optional[float] = None    # the pose invariant's working volume (m from the ECM; None: 1 m)

    def node(self, node_id: str) -> NodeSpec:
        for n in self.nodes:
            if n.id == node_id:
                return n
        raise KeyError(f"graph {self.name!r} has no node {node_id!r} (nodes: {', '.join(self.ids())})")

    def ids(self) -> list:
        return [n.id for n in self.nodes]

    # keys -------------------------------------------------------------------------------
    def output_key(self, node_id: str, output: str) -> str:
        return output_key(self.name, node_id, output)

    def input_key(self, spec: NodeSpec, name: str) -> str:
        src, out = spec.inputs[name].split("/", 1)
        return output_key(self.name, src, out)

    def resolve_key(self, key: str) -> str:
        """``camera/left`` -> ``<graph>/camera/left``; keys already under the graph stay as they are."""
        key = key.strip("/")
        return key if key == self.name or key.startswith(self.name + "/") else f"{self.name}/{key}"

    def to_dict(self) -> dict:
        z = self.zenoh
        zd = {"mode": z.mode, "listen": list(z.listen), "connect": list(z.connect), "shm_pool_mb": z.shm_pool_mb}
        if z.tls is not None:
            zd["tls"] = z.tls.to_dict()
        if z.open:
            zd["open"] = True
        return {"graph": self.name, "zenoh": zd, "nodes": [n.to_dict() for n in self.nodes],
                **({"pose_volume_m": self.pose_volume_m} if self.pose_volume_m is not None else {})}

    def dump(self, path) -> Path:
        path = Path(path)
        path.write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))
        return path


def output_key(graph: str, node_id: str, output: str) -> str:
    return f"{graph}/{node_id}/{output}"


def stats_key(graph: str, node_id: str = "*") -> str:
    return f"{graph}/@stats/{node_id}"


def live_key(graph: str, node_id: str = "*") -> str:
    return f"{graph}/@live/{node_id}"


def cmd_key(graph: str, node_id: str) -> str:
    return f"{graph}/{node_id}/cmd"


def ctl_key(graph: str, node_id: str, pid, op: str) -> str:
    """Runtime control (swap handover) of one process of a node."""
    return f"{graph}/@ctl/{node_id}/{pid}/{op}"


def launcher_key(graph: str, op: str) -> str:
    return f"{graph}/@launcher/{op}"


# ------------------------------------------------------------------ module introspection

def module_path(module: str) -> Path:
    return NODES_DIR.joinpath(*module.split(".")).with_suffix(".py")


@functools.lru_cache(maxsize=256)
def _module_info_cached(path: str, mtime: float) -> dict:
    info: dict[str, Any] = {"has_node": False, "inputs": None, "outputs": None, "feedback": None,
                            "syntax_error": None}
    try:
        tree = ast.parse(Path(path).read_text(), filename=path)
    except SyntaxError as exc:
        info["syntax_error"] = f"line {exc.lineno}: {exc.msg}"
        return info
    classes = {n.name: n for n in tree.body if isinstance(n, ast.ClassDef)}
    node_cls = None
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "NODE" for t in stmt.targets):
            info["has_node"] = True
            if isinstance(stmt.value, ast.Name):
                node_cls = classes.get(stmt.value.id)
    if node_cls is not None:
        for stmt in node_cls.body:
            if not isinstance(stmt, ast.Assign) or len(stmt.targets) != 1 or not isinstance(stmt.targets[0], ast.Name):
                continue
            name = stmt.targets[0].id
            if name == "INPUTS" and isinstance(stmt.value, ast.Dict):
                keys = [k.value for k in stmt.value.keys if isinstance(k, ast.Constant)]
                if len(keys) == len(stmt.value.keys):
                    info["inputs"] = keys
            elif name in ("OUTPUTS", "FEEDBACK") and isinstance(stmt.value, (ast.Tuple, ast.List)):
                vals = [e.value for e in stmt.value.elts if isinstance(e, ast.Constant)]
                if len(vals) == len(stmt.value.elts):
                    info[name.lower()] = vals
    return info


def module_info(module: str) -> Optional[dict]:
    """What ``nodes/<module>.py`` declares, read without importing it; None if there is no file.

    Returns ``{"has_node", "inputs", "outputs", "syntax_error"}``; ``inputs``/``outputs`` are None
    when they are not plain literals in the class that ``NODE`` names.
    """
    p = module_path(module)
    if not p.is_file():
        return None
    return _module_info_cached(str(p), p.stat().st_mtime)


def available_modules() -> list:
    return sorted(p.stem for p in NODES_DIR.glob("*.py") if not p.stem.startswith("_"))


# ------------------------------------------------------------------ validation

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


def _endpoint_host(endpoint: str) -> Optional[str]:
    m = re.match(r"^[a-z-]+/(\[[^\]]*\]|[^:/#?]*):\d+", endpoint)
    return m.group(1).strip("[]") if m else None


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        import ipaddress
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def graph_from_dict(data: dict, path: Optional[Path] = None, source: str = "graph") -> Graph:
    """A validated ``Graph`` from a parsed document; raises ``GraphError`` listing every error."""
    errs = validate_graph(data)
    if errs:
        raise GraphError(errs, source)
    z = data.get("zenoh") or {}
    default_listen = DEFAULT_ENDPOINT.replace("tcp/", "tls/") if z.get("tls") else DEFAULT_ENDPOINT
    zs = ZenohSettings(mode=z.get("mode", "peer"), listen=list(z.get("listen", [default_listen])),
                       connect=list(z.get("connect", [])), shm_pool_mb=int(z.get("shm_pool_mb", 64)),
                       open=z.get("open") is True)
    if z.get("tls"):
        base = path.parent if path is not None else Path.cwd()
        t = z["tls"]
        zs.tls = TlsSettings(*(str((base / Path(t[k]).expanduser()).resolve()) for k in ("ca", "cert", "key")),
                             verify_name=bool(t.get("verify_name", False)))
    nodes = []
    for n in data["nodes"]:
        outs = n.get("outputs")
        if outs is None and n.get("module"):
            outs = (module_info(n["module"]) or {}).get("outputs") or []
        nodes.append(NodeSpec(id=n["id"], module=n.get("module"),
                              command=[str(a) for a in n["command"]] if n.get("command") else None,
                              params=dict(n.get("params") or {}), inputs=dict(n.get("inputs") or {}),
                              outputs=list(outs or []), restart=n.get("restart", "on-failure"),
                              spare=n.get("spare") is True,
                              env={k: str(v) for k, v in (n.get("env") or {}).items()},
                              feedback=list(n.get("feedback") or [])))
    return Graph(name=data["graph"], zenoh=zs, nodes=nodes, path=path,
                 pose_volume_m=None if data.get("pose_volume_m") is None else float(data["pose_volume_m"]))


def parse_yaml(text: str, source: str = "graph") -> Any:
    from common.runtime.limits import InputLimitError, load_yaml
    try:
        return load_yaml(text, source)           # with an alias budget (a YAML bomb is refused)
    except InputLimitError as exc:
        raise GraphError([str(exc)], source) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "?"
        problem = getattr(exc, "problem", None) or str(exc)
        raise GraphError([f"{where}: YAML syntax error: {problem}"], source) from None


def load_graph(src) -> Graph:
    """A graph from a YAML file path, YAML text or a dict; raises ``GraphError`` listing every error."""
    if isinstance(src, dict):
        return graph_from_dict(copy.deepcopy(src))
    if isinstance(src, str) and "\n" in src:
        return graph_from_dict(parse_yaml(src))
    path = Path(src)
    if not path.is_file():
        raise GraphError([f"no such file: {path}"], str(path))
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise GraphError([f"not a YAML text file: byte {exc.start} is not UTF-8"], str(path)) from None
    except OSError as exc:
        raise GraphError([f"cannot be read: {exc.strerror}"], str(path)) from None
    if "\0" in text:
        raise GraphError([f"not a YAML text file: byte {text.index(chr(0))} is NUL"], str(path))
    return graph_from_dict(parse_yaml(text, str(path)), path=path.resolve(), source=str(path))


def parse_param(text: str) -> tuple:
    """``k=v`` -> (k, v) with v parsed as YAML (``noise_px=1.5`` -> ("noise_px", 1.5); text that is
    not YAML stays a string); ValueError (``InputLimitError``) for a value over the YAML limits
    (nested too deep, too many nodes: ``common.runtime.limits``)."""
    from common.runtime.limits import load_yaml
    if "=" not in text:
        raise ValueError(f"--param expects key=value, got {text[:80]!r}")
    k, v = text.split("=", 1)
    if not k:
        raise ValueError(f"--param expects key=value, got {text[:80]!r}")
    try:
        val = load_yaml(v, f"the value of {k[:80]!r}") if v else ""
    except yaml.YAMLError:
        val = v
    return k, val


# ------------------------------------------------------------------ Zenoh configuration

def close_session(session, declarations: list) -> None:
    """Undeclare ``declarations`` (subscribers, queryables, tokens) and close ``session``, best
    effort: at shutdown the session may already be gone, and nothing is left to report to."""
    for d in declarations:
        try:
            d.undeclare()
        except Exception:
            pass
    declarations.clear()
    if session is not None:
        try:
            session.close()
        except Exception:
            pass


def zenoh_config(graph, role: str = "node", listen: Optional[list] = None, identity: str = LAUNCHER_IDENTITY):
    """A ``zenoh.Config`` for a member of ``graph`` (a ``Graph``; a bare ``ZenohSettings`` only
    without TLS).

    ``role="hub"`` (the launcher) listens on the graph's ``listen`` endpoints; every other
    member (nodes, CLI tools, tests) connects to them and listens on an ephemeral port of the
    local address that reaches the first of them (loopback for a loopback graph, this host's
    address on that network otherwise), so peers gossip and connect directly. Multicast
    scouting is always off: graphs on different endpoints never see each other.

    With ``zenoh.tls`` every link is mutual TLS: the member presents the certificate of
    ``identity`` (its node id, or ``launcher`` for launchers and CLI tools) and accepts only
    peers whose certificates the graph's CA signed; access control (``access_control``) lets
    each peer publish only what its identity may. Raises ``GraphError`` naming a missing file.
    A ``Graph`` with neither ``zenoh.tls`` nor ``zenoh.open`` runs on its launcher's per-run
    credentials (``common.runtime.credentials``: the CLI tools of the same user find them);
    ``CredentialsError`` (a ``GraphError``) says when there are none (the graph is not running).
    """
    import zenoh
    if isinstance(graph, Graph) and graph.zenoh.tls is None and not graph.zenoh.open:
        from common.runtime import credentials
        graph = credentials.find(graph)
    z, g = (graph.zenoh, graph) if isinstance(graph, Graph) else (graph, None)
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(z.mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    if role == "hub":
        lis = list(z.listen) if listen is None else listen
        con = list(z.connect)
    else:
        lis = listen if listen is not None else [_local_like(e) for e in (z.listen or [DEFAULT_ENDPOINT])[:1]]
        con = list(z.listen) + list(z.connect)
    if z.mode == "client":
        lis = []
    c.insert_json5("listen/endpoints", json.dumps(lis))
    c.insert_json5("connect/endpoints", json.dumps(con))
    if z.shm_pool_mb > 0:
        c.insert_json5("transport/shared_memory/enabled", "true")
        c.insert_json5("transport/shared_memory/transport_optimization/pool_size", str(z.shm_pool_mb << 20))
    else:
        c.insert_json5("transport/shared_memory/enabled", "false")
    if z.tls is not None:
        if g is None:
            raise ValueError("zenoh_config: a graph with zenoh.tls needs the Graph (its access control "
                             "is built from its nodes), not its ZenohSettings")
        errs = tls_file_errors(g, [identity])
        if errs:
            raise GraphError(errs, g.name)
        ca, cert, key = z.tls.files(identity)
        t = "transport/link/tls/"
        c.insert_json5(t + "root_ca_certificate", json.dumps(ca))
        for side in ("listen", "connect"):
            c.insert_json5(t + f"{side}_private_key", json.dumps(key))
            c.insert_json5(t + f"{side}_certificate", json.dumps(cert))
        c.insert_json5(t + "enable_mtls", "true")
        c.insert_json5(t + "verify_name_on_connect", json.dumps(z.tls.verify_name))
        c.insert_json5("access_control", json.dumps(access_control(g)))
    return c


def tls_file_errors(graph: "Graph", identities) -> list:
    """Missing or unreadable TLS files of ``identities`` (node ids or ``launcher``), each with its place."""
    t = graph.zenoh.tls
    if t is None:
        return []
    errs, seen = [], set()
    for ident in identities:
        for what, f in zip(("ca", "cert", "key"), t.files(ident)):
            if f in seen:
                continue
            seen.add(f)
            p = Path(f)
            if not p.is_file():
                errs.append(f"zenoh.tls.{what}: no file {f}" + ("" if what == "ca" else f" (identity {ident!r})")
                            + "; make the certificates with `needletrack certs` (docs/multi-host.md)")
            elif not os.access(p, os.R_OK):
                errs.append(f"zenoh.tls.{what}: {f} is not readable")
    return errs


def identity_name(graph_name: str, identity: str) -> str:
    """The certificate common name of a member: ``<graph>:<node id>`` or ``<graph>:launcher``."""
    return f"{graph_name}:{identity}"


_ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                 "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"]


def access_control(graph: "Graph") -> dict:
    """Zenoh ``access_control`` of a TLS graph: deny unless allowed, by certificate common name.

    - the launcher identity (launchers, CLI tools) may do everything: it alone sends commands
      (``<graph>/<node>/cmd``), swaps (``@launcher/swap``) and handovers (``@ctl``);
    - node ``n`` may publish only its own outputs (``<graph>/n/<output>``) and stats, declare its
      own liveliness token and ``@ctl/n`` queryables (and reply on them), subscribe to the
      graph's keys, stats and liveliness, and ask the launcher's status; nothing else (no
      command, swap or handover, no output of another node);
    - anything may be sent to a member (egress); what a member accepts (ingress) is the check.
    Every peer is a member: mutual TLS refuses a certificate the graph's CA did not sign.
    """
    g = graph.name
    verbatim = [f"{g}/@live/**", f"{g}/@stats/**", f"{g}/@ctl/**", f"{g}/@launcher/**"]
    rules = [{"id": "launcher", "permission": "allow", "messages": list(_ALL_MESSAGES),
              "key_exprs": ["**"] + verbatim},
             {"id": "to-members", "permission": "allow", "flows": ["egress"], "messages": list(_ALL_MESSAGES),
              "key_exprs": ["**"] + verbatim},
             {"id": "members-subscribe", "permission": "allow", "flows": ["ingress"],
              "messages": ["declare_subscriber"], "key_exprs": [f"{g}/**", f"{g}/@stats/**"]},
             {"id": "members-liveliness", "permission": "allow", "flows": ["ingress"],
              "messages": ["declare_liveliness_subscriber", "liveliness_query"], "key_exprs": [f"{g}/@live/**"]},
             {"id": "members-status", "permission": "allow", "flows": ["ingress"],
              "messages": ["query"], "key_exprs": [launcher_key(g, "status")]}]
    subjects = [{"id": LAUNCHER_IDENTITY, "cert_common_names": [identity_name(g, LAUNCHER_IDENTITY)]}]
    policies = [{"rules": ["launcher"], "subjects": [LAUNCHER_IDENTITY]}]
    node_subjects = []
    for n in graph.nodes:
        sid = f"node:{n.id}"
        subjects.append({"id": sid, "cert_common_names": [identity_name(g, n.id)]})
        node_subjects.append(sid)
        rules += [{"id": f"{sid}:publish", "permission": "allow", "flows": ["ingress"], "messages": ["put", "delete"],
                   "key_exprs": [output_key(g, n.id, o) for o in n.outputs] + [stats_key(g, n.id)]},
                  {"id": f"{sid}:live", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
                   "key_exprs": [live_key(g, n.id)]},
                  {"id": f"{sid}:ctl", "permission": "allow", "flows": ["ingress"],
                   "messages": ["declare_queryable", "reply"], "key_exprs": [f"{g}/@ctl/{n.id}/**"]}]
        policies.append({"rules": [f"{sid}:publish", f"{sid}:live", f"{sid}:ctl"], "subjects": [sid]})
    policies.append({"rules": ["to-members", "members-subscribe", "members-liveliness", "members-status"],
                     "subjects": node_subjects})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _local_like(endpoint: str) -> str:
    """An ephemeral endpoint of the same protocol on the local address that reaches ``endpoint``:
    ``tcp/127.0.0.1:7447`` -> ``tcp/127.0.0.1:0``; on another host of ``tls/10.0.0.1:7447``,
    ``tls/10.0.0.2:0`` (the address of the interface the route to 10.0.0.1 leaves by)."""
    m = re.match(r"^(tcp|udp|tls|quic|ws)/(.+):(\d+)$", endpoint)
    if not m:
        return "tcp/127.0.0.1:0"
    proto, host, port = m.group(1), m.group(2), int(m.group(3))
    bare = host.strip("[]")
    if _is_loopback(bare) or bare in ("0.0.0.0", "::"):
        return f"{proto}/{host}:0"
    try:
        family = socket.AF_INET6 if ":" in bare else socket.AF_INET
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.connect((bare, port))          # no packet is sent: this only picks the route
            local = s.getsockname()[0]
    except OSError:
        return f"{proto}/{host}:0"
    if local == bare:
        return f"{proto}/{host}:0"
    return f"{proto}/[{local}]:0" if ":" in local else f"{proto}/{local}:0"
