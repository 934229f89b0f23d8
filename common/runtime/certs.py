"""``needletrack certs``: a test CA and one certificate per member of a graph (openssl).

For a graph with ``zenoh.tls: {ca: certs/ca.pem, cert: "certs/{id}.pem", key: "certs/{id}.key"}``::

    needletrack certs dataflow.yaml                 # -> certs/ca.pem, ca.key, launcher.*, <node>.*

makes (in the folder of ``zenoh.tls.cert``, or ``--out DIR``) a CA (``ca.pem``, ``ca.key``; an
existing CA there is reused) and, for the launcher identity and every node, ``<id>.pem`` and
``<id>.key`` with the common name ``<graph>:<id>`` that the graph's access control matches
(``graph.access_control``). Keys are EC P-256, mode 0600. Every certificate is both a server and
a client certificate (every member listens and connects). ``--host`` adds subject alternative
names (addresses or DNS names), needed only with ``zenoh.tls.verify_name: true``.

These are test certificates: for a real deployment, have your own CA sign certificates with the
same common names, and keep ``ca.key`` off the graph's hosts (docs/multi-host.md).
"""
from __future__ import annotations

import argparse
import ipaddress
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Iterable, Optional

from common.errors import NeedletrackError
from common.runtime.graph import (
    LAUNCHER_IDENTITY,
    GraphError,
    identity_name,
    load_graph,
)

DEFAULT_DAYS = 30


class CertError(NeedletrackError, RuntimeError):
    """openssl is missing or failed."""


def _openssl(*args: str) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise CertError("openssl not found: install it (Debian: apt-get install openssl)")
    res = subprocess.run([exe, *args], capture_output=True, text=True)
    if res.returncode != 0:
        raise CertError(f"openssl {args[0]} failed ({res.returncode}): {res.stderr.strip()}")


def _private(path: Path) -> None:
    os.chmod(path, 0o600)


def make_ca(out: Path, name: str = "needletrack test CA", days: int = DEFAULT_DAYS) -> tuple:
    """``out/ca.pem`` and ``out/ca.key`` (made if either is missing); returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    ca, key = out / "ca.pem", out / "ca.key"
    if not (ca.is_file() and key.is_file()):
        _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                 "-keyout", str(key), "-out", str(ca), "-days", str(days), "-subj", f"/CN={name}",
                 "-addext", "basicConstraints=critical,CA:TRUE",
                 "-addext", "keyUsage=critical,keyCertSign,cRLSign")
        _private(key)
    return ca, key


def make_cert(ca: Path, ca_key: Path, cert: Path, key: Path, common_name: str,
              hosts: Iterable[str] = (), days: int = DEFAULT_DAYS) -> None:
    """A key and a certificate signed by ``ca`` for ``common_name``, usable as server and client."""
    sans = ["DNS:localhost", "IP:127.0.0.1"]
    for h in hosts:
        try:
            ipaddress.ip_address(h)
            sans.append(f"IP:{h}")
        except ValueError:
            sans.append(f"DNS:{h}")
    cert.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        csr, ext = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        ext.write_text("basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\n"
                       "extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=" + ",".join(dict.fromkeys(sans)) + "\n")
        _openssl("req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                 "-keyout", str(key), "-out", str(csr), "-subj", f"/CN={common_name}")
        _private(key)
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca), "-CAkey", str(ca_key), "-set_serial",
                 str(int.from_bytes(os.urandom(8), "big")), "-out", str(cert), "-days", str(days),
                 "-extfile", str(ext))


def make_graph_certs(graph, out: Optional[Path] = None, identities: Optional[Iterable[str]] = None,
                     hosts: Iterable[str] = (), days: int = DEFAULT_DAYS) -> list:
    """A CA and the certificates of ``identities`` (default: the launcher and every node) of a TLS
    graph, at the paths its ``zenoh.tls`` names (or as ``<out>/<id>.pem|key``, CA in ``out``).
    Returns the identities made."""
    t = graph.zenoh.tls
    if t is None and out is None:
        raise GraphError(["zenoh.tls: not set: give the certificate paths in the graph, or --out DIR"], graph.name)
    idents = list(identities) if identities else [LAUNCHER_IDENTITY] + graph.ids()
    if out is not None:
        out = Path(out)
        ca, ca_key = make_ca(out)
        paths = {i: (out / f"{i}.pem", out / f"{i}.key") for i in idents}
    else:
        ca_path = Path(t.ca)
        ca, ca_key = make_ca(ca_path.parent)
        if ca != ca_path:
            shutil.copyfile(ca, ca_path)
        paths = {i: tuple(map(Path, t.files(i)[1:])) for i in idents}
    for i in idents:
        make_cert(ca, ca_key, *paths[i], identity_name(graph.name, i), hosts, days)
    return idents


def certs_main(argv: list) -> int:
    """``needletrack certs [GRAPH] [--out DIR] [--identity ID ...] [--host H ...] [--days N]``."""
    ap = argparse.ArgumentParser(prog="needletrack certs", description=(
        "Make a test CA and the certificates of a TLS graph's launcher and nodes (common name "
        "<graph>:<id>), at the paths of its zenoh.tls or in --out DIR."))
    ap.add_argument("graph", nargs="?", default="dataflow.yaml", help="graph YAML (default: dataflow.yaml)")
    ap.add_argument("--out", help="folder for ca.pem and <id>.pem/.key (default: the graph's zenoh.tls paths)")
    ap.add_argument("--identity", action="append", help="only this identity (a node id or 'launcher'); repeatable")
    ap.add_argument("--host", action="append", default=[], help="subject alternative name (IP or DNS); repeatable")
    ap.add_argument("--days", type=int, default=DEFAULT_DAYS, help=f"validity (default {DEFAULT_DAYS})")
    args = ap.parse_args(argv)
    if args.out and Path(args.out).exists() and not Path(args.out).is_dir():
        print(f"needletrack certs: --out {args.out} exists and is not a folder", file=sys.stderr)
        return 2
    try:
        graph = load_graph(args.graph)
        if args.identity:
            unknown = [i for i in args.identity if i != LAUNCHER_IDENTITY and i not in graph.ids()]
            if unknown:
                raise GraphError([f"--identity: no node {u!r} (nodes: {', '.join(graph.ids())}, or "
                                  f"{LAUNCHER_IDENTITY!r})" for u in unknown], args.graph)
        idents = make_graph_certs(graph, Path(args.out) if args.out else None, args.identity, args.host, args.days)
    except GraphError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    except CertError as exc:
        print(f"needletrack certs: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:            # the folder cannot be made or written
        print(f"needletrack certs: cannot write {exc.filename or args.out}: {exc.strerror}", file=sys.stderr)
        return 1
    where = Path(args.out) if args.out else Path(graph.zenoh.tls.cert).parent
    print(f"{where}: CA and {len(idents)} certificate(s) for graph {graph.name!r}: {', '.join(idents)}")
    return 0


if __name__ == "__main__":
    sys.exit(certs_main(sys.argv[1:]))
