"""The Zenoh session a graph configures: ``zenoh_config`` (mode, endpoints, shared memory, mutual
TLS), ``access_control`` (who may put, subscribe and query what), the TLS files each identity
needs, ``close_session``."""
from __future__ import annotations

import json
import os
import re
import socket
from pathlib import Path
from typing import Optional

from common.runtime.graph import (
    DEFAULT_ENDPOINT,
    Graph,
    GraphError,
    LAUNCHER_IDENTITY,
    launcher_key,
    live_key,
    output_key,
    stats_key,
)


def endpoint_host(endpoint: str) -> Optional[str]:
    """The host of an endpoint like ``tcp/127.0.0.1:7447`` (brackets of an IPv6 address off);
    None when it names no host and port."""
    m = re.match(r"^[a-z-]+/(\[[^\]]*\]|[^:/#?]*):\d+", endpoint)
    return m.group(1).strip("[]") if m else None


def is_loopback(host: str) -> bool:
    """Whether ``host`` (``localhost`` or an IP address) is loopback only."""
    if host == "localhost":
        return True
    try:
        import ipaddress
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


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
    if is_loopback(bare) or bare in ("0.0.0.0", "::"):
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
