"""Per-run credentials: a local graph that no other process can steer, by default.

``needletrack launch`` of a graph without ``zenoh.tls`` (and without ``zenoh.open: true``) makes,
for that run, a CA held only in memory and a certificate per member (``launcher`` and every node
id, common name ``<graph>:<id>``, as ``needletrack certs`` makes), in a run directory of mode
0700 whose key files are 0600::

    $XDG_RUNTIME_DIR/needletrack/<graph>@<host>-<port>/    (else /tmp/needletrack-<uid>/...)
        ca.pem  launcher.pem  launcher.key  <node>.pem  <node>.key  owner.json

The graph then runs over mutual TLS on its loopback endpoints (``tcp/`` becomes ``tls/``) with
the access control of ``zenoh_session.access_control``: only the graph's own nodes and the operator
(the launcher and the CLI tools of the same user, which find the directory by the graph's name
and first listen endpoint) may publish, command, swap or hand over. Another user cannot read the
directory; a process without the files cannot complete a TLS handshake with any member. The CA
key is never written, so no further identity can be made for the run.

``NEEDLETRACK_RUN_DIR`` moves the base directory (it must be the user's own, mode 0700).
"""
from __future__ import annotations

import copy
import json
import os
import re
import shutil
import tempfile
import time
from pathlib import Path
from typing import Optional

from common.runtime.graph import DEFAULT_ENDPOINT, LAUNCHER_IDENTITY, Graph, GraphError, TlsSettings
from common.runtime.zenoh_session import identity_name

OWNER_FILE = "owner.json"


class CredentialsError(GraphError):
    """The run's credentials are missing (the graph is not running for this user) or unsafe."""


def base_dir() -> Path:
    """The user's directory of run credentials (made 0700 if missing); raises
    ``CredentialsError`` if it is not a directory of this user's that only this user can open."""
    env = os.environ.get("NEEDLETRACK_RUN_DIR")
    if env:
        base = Path(env)
    else:
        xdg = os.environ.get("XDG_RUNTIME_DIR")
        base = Path(xdg) / "needletrack" if xdg and _own_private_dir(Path(xdg)) else \
            Path(tempfile.gettempdir()) / f"needletrack-{os.getuid()}"
    try:
        base.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise CredentialsError([f"run credentials: cannot make {base}: {exc.strerror}"], "credentials") from None
    if not _own_private_dir(base):
        raise CredentialsError([f"run credentials: {base} is not a directory of uid {os.getuid()} with mode 0700 "
                                f"(another user may have made it): remove it, or set NEEDLETRACK_RUN_DIR"],
                               "credentials")
    return base


def _own_private_dir(p: Path) -> bool:
    try:
        st = os.lstat(p)
    except OSError:
        return False
    import stat
    return stat.S_ISDIR(st.st_mode) and st.st_uid == os.getuid() and st.st_mode & 0o077 == 0


def run_dir(graph: Graph) -> Path:
    """Where the credentials of a run of ``graph`` lie: by its name and first listen endpoint."""
    endpoint = (graph.zenoh.listen or [DEFAULT_ENDPOINT])[0]
    where = re.sub(r"[^A-Za-z0-9_.-]+", "-", endpoint.split("/", 1)[-1]).strip("-")
    return base_dir() / f"{graph.name}@{where}"


def applies(graph: Graph) -> bool:
    """Whether ``graph`` runs on per-run credentials: no ``zenoh.tls`` of its own, not ``zenoh.open``."""
    return graph.zenoh.tls is None and not graph.zenoh.open


def secured(graph: Graph, directory: Path) -> Graph:
    """A copy of ``graph`` on the credentials in ``directory``: ``zenoh.tls`` set, ``tcp/``
    endpoints as ``tls/``."""
    g = copy.copy(graph)
    g.zenoh = copy.copy(graph.zenoh)
    g.zenoh.listen = [_tls(e) for e in graph.zenoh.listen]
    g.zenoh.connect = [_tls(e) for e in graph.zenoh.connect]
    d = str(directory)
    g.zenoh.tls = TlsSettings(ca=f"{d}/ca.pem", cert=f"{d}/{{id}}.pem", key=f"{d}/{{id}}.key")
    g.zenoh.run_credentials = d
    return g


def _tls(endpoint: str) -> str:
    return "tls/" + endpoint[4:] if endpoint.startswith("tcp/") else endpoint


def owner_alive(directory: Path) -> Optional[int]:
    """The pid of the launcher that made the credentials in ``directory`` if it still runs."""
    try:
        pid = int(json.loads((directory / OWNER_FILE).read_text())["pid"])
        os.kill(pid, 0)
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return pid


def find(graph: Graph) -> Graph:
    """``graph`` on the credentials of its running launcher (the CLI tools, tests, a second
    launcher with ``--only``); raises ``CredentialsError`` saying why there are none."""
    d = run_dir(graph)
    if not (d / "ca.pem").is_file():
        raise CredentialsError([f"graph {graph.name!r} at {', '.join(graph.zenoh.listen)} is not running for "
                                f"this user: no run credentials in {d} (`needletrack launch` makes them; "
                                f"a graph of another user cannot be reached)"], graph.name)
    if not _own_private_dir(d):
        raise CredentialsError([f"run credentials: {d} is not this user's with mode 0700: refused"], graph.name)
    return secured(graph, d)


def wait_for(graph: Graph, timeout: float, alive=lambda: True) -> Graph:
    """``find`` retried for up to ``timeout`` s while ``alive()`` (a launcher starting up)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return find(graph)
        except CredentialsError:
            if time.monotonic() >= deadline or not alive():
                raise
        time.sleep(0.05)


def make(graph: Graph) -> tuple:
    """The credentials of a new run of ``graph`` (a CA in memory, a certificate per node and for
    the launcher); returns ``(secured graph, made)``. ``made`` is False when a launcher of this
    graph that is still running made them (``--only``: this launcher joins that run)."""
    from common.runtime.certs import new_ca, new_cert, write_identity
    d = run_dir(graph)
    if (d / "ca.pem").is_file() and owner_alive(d) is not None:
        return find(graph), False
    prune(d.parent)
    tmp = Path(tempfile.mkdtemp(prefix=f".{graph.name}-", dir=d.parent))     # mode 0700
    try:
        ca = new_ca(f"needletrack run CA {graph.name} {os.getpid()}", days=30)
        (tmp / "ca.pem").write_bytes(_pem(ca[0]))
        for ident in [LAUNCHER_IDENTITY] + graph.ids():
            write_identity(tmp, ident, new_cert(ca, identity_name(graph.name, ident), days=30))
        (tmp / OWNER_FILE).write_text(json.dumps({"pid": os.getpid(), "graph": graph.name,
                                                  "listen": list(graph.zenoh.listen)}))
        shutil.rmtree(d, ignore_errors=True)
        os.replace(tmp, d)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return secured(graph, d), True


def prune(base: Path) -> list:
    """Remove the credentials of runs whose launcher is gone (killed: it could not remove them)."""
    gone = []
    for d in base.iterdir():
        if d.is_dir() and not d.name.startswith(".") and (d / OWNER_FILE).is_file() and owner_alive(d) is None:
            shutil.rmtree(d, ignore_errors=True)
            gone.append(d)
    return gone


def remove(graph: Graph) -> None:
    """Remove the run's credentials (the launcher that made them, at its end)."""
    d = getattr(graph.zenoh, "run_credentials", None)
    if d:
        shutil.rmtree(d, ignore_errors=True)


def _pem(cert) -> bytes:
    from cryptography.hazmat.primitives import serialization
    return cert.public_bytes(serialization.Encoding.PEM)
