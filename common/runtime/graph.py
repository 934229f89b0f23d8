"""The dataflow graph (``dataflow.yaml``): its model (``Graph``, ``NodeSpec``, the Zenoh and TLS
settings), loading, key names and the node modules it names. Validation: ``graph_checks``; the
Zenoh session it configures (endpoints, TLS, access control): ``zenoh_session``.

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

``graph_checks.validate_graph`` returns every error at once, each with its place
(``nodes[3].inputs.keypoints: no node 'detektor'``); ``load_graph`` raises ``GraphError`` carrying
that list. Modules are checked without importing them: ``nodes/<module>.py`` must exist and is
parsed (``ast``) for ``NODE``, ``INPUTS`` and ``OUTPUTS`` when they are literals.
"""
from __future__ import annotations

import ast
import copy
import functools
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Optional, Union

import msgspec
import yaml

from common.errors import NeedletrackError
from common.runtime.schema import Says

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
RESTART_POLICIES = ("never", "on-failure", "always")
ZENOH_MODES = ("peer", "client", "router")
NODES_DIR = Path(__file__).resolve().parents[2] / "nodes"
REPO_ROOT = NODES_DIR.parent

_NAME = r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$"
NAME_RE = re.compile(_NAME)
_MODULE = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$"
_MODULE_RE = re.compile(_MODULE)
ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")
LAUNCHER_IDENTITY = "launcher"     # the TLS identity of launchers and CLI tools (the operator)

# the graph file's fields (common/runtime/schema.py): a field is declared once below, its type and
# constraints with the words of its refusal; graph_checks.validate_graph adds what joins fields
_NAMED = "must be a name of letters, digits, '_', '-', '.'; got {value!r}"
Name = Annotated[str, msgspec.Meta(pattern=_NAME), Says(_NAMED, types=True)]
Flag = Annotated[bool, Says("expected true or false, got {value!r}", types=True)]
PemPath = Annotated[str, msgspec.Meta(min_length=1), Says("expected a file path, got {value!r}", types=True,
                                                          missing="missing (a PEM file path)")]
PemPathOfId = Annotated[str, msgspec.Meta(min_length=1), Says("expected a file path, got {value!r}", types=True,
                                                              missing="missing (a PEM file path, with {id})")]
Endpoints = Annotated[list, Says("expected a list of endpoints, got {kind}", types=True)]


class GraphError(NeedletrackError, ValueError):
    """An invalid graph; ``errors`` lists every problem with its place."""

    def __init__(self, errors: list[str], source: str = "graph"):
        self.errors = list(errors)
        self.source = source
        super().__init__(f"{source}: {len(self.errors)} error(s)\n" + "\n".join(f"  {e}" for e in self.errors))


FEEDBACK_ERROR = "expected a list of this node's input names, got {value!r}"


@dataclass
class TlsSettings:
    """Mutual TLS of a graph: ``ca`` (PEM of the CA that signed every member), ``cert``/``key``
    (PEM paths with ``{id}``: the node id, or ``launcher`` for launchers and CLI tools).
    Paths are absolute once loaded (relative ones are taken from the graph file's folder)."""
    ca: PemPath
    cert: PemPathOfId
    key: PemPathOfId
    verify_name: Flag = False      # check the peer's certificate names the address connected to

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
    mode: Annotated[Literal[ZENOH_MODES], Says(f"must be one of {', '.join(ZENOH_MODES)}; got {{value!r}}",
                                               types=True)] = "peer"
    listen: Endpoints = field(default_factory=lambda: [DEFAULT_ENDPOINT])
    connect: Endpoints = field(default_factory=list)
    shm_pool_mb: Annotated[int, msgspec.Meta(ge=0), Says("expected a non-negative int, got {value!r}", types=True)] = 64
    tls: Annotated[TlsSettings, Says("expected a map {{ca, cert, key}}, got {kind}", types=True)] = None   # None: no TLS
    open: Flag = False             # no per-run credentials: any local process may join (a warning)
    run_credentials: Optional[str] = field(default=None, metadata={"key": None})   # the run directory whose certificates ``tls`` names (not in the YAML)


@dataclass
class NodeSpec:
    """One node of the graph file; a field that may be null in the file is loaded as empty."""
    id: Annotated[str, msgspec.Meta(pattern=r"^(?!cmd$)" + _NAME[1:]), Says(_NAMED, types=True, missing="missing")]
    module: Annotated[str, msgspec.Meta(pattern=_MODULE),
                      Says("expected a module name like 'sim', got {value!r}", types=True)] = None   # None: a command
    command: Annotated[list[Union[str, int, float, bool]], msgspec.Meta(min_length=1),
                       Says("expected a non-empty list of strings, got {value!r}", types=True)] = None
    params: Annotated[Optional[dict], Says("expected a map, got {kind}", types=True)] = field(default_factory=dict)
    inputs: Annotated[Optional[dict], Says("expected a map of input name -> 'node/output', got {kind}",
                                           types=True)] = field(default_factory=dict)      # input name -> "node/output"
    outputs: Annotated[Optional[list], Says("expected a list of output names, got {kind}", types=True)] = field(
        default_factory=list)
    restart: Annotated[Literal[RESTART_POLICIES], Says(f"must be one of {', '.join(RESTART_POLICIES)}; got {{value!r}}",
                                                       types=True)] = "on-failure"
    spare: Flag = False            # a warm spare process takes over when the node's process exits
    env: Annotated[Optional[dict], Says("expected a map of NAME: value, got {kind}", types=True)] = field(
        default_factory=dict)
    feedback: Annotated[Optional[list[str]], Says(FEEDBACK_ERROR, types=True)] = field(
        default_factory=list)    # inputs that close a declared cycle (acks)

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
    name: Annotated[str, msgspec.Meta(pattern=_NAME), Says(
        _NAMED, types=True, missing="missing (the key prefix of the graph, e.g. 'needletrack')")] = field(
        metadata={"key": "graph"})
    zenoh: Annotated[Optional[ZenohSettings], Says("expected a map, got {kind}", types=True)]
    nodes: Annotated[list, Says("expected a list, got {kind}", types=True, missing="missing (a list of nodes)")]
    path: Optional[Path] = field(default=None, metadata={"key": None})
    # the pose invariant's working volume (m from the ECM; None: 1 m)
    pose_volume_m: Optional[Annotated[float, msgspec.Meta(gt=0, lt=1e6),
                                      Says("expected a positive number of metres, got {value!r}", types=True)]] = None

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

def graph_from_dict(data: dict, path: Optional[Path] = None, source: str = "graph") -> Graph:
    """A validated ``Graph`` from a parsed document; raises ``GraphError`` listing every error."""
    from common.runtime.graph_checks import validate_graph
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
