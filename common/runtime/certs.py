"""``needletrack certs``: a test CA and one certificate per member of a graph.

For a graph with ``zenoh.tls: {ca: certs/ca.pem, cert: "certs/{id}.pem", key: "certs/{id}.key"}``::

    needletrack certs dataflow.yaml                 # -> certs/ca.pem, ca.key, launcher.*, <node>.*

makes (in the folder of ``zenoh.tls.cert``, or ``--out DIR``) a CA (``ca.pem``, ``ca.key``; an
existing CA there is reused) and, for the launcher identity and every node, ``<id>.pem`` and
``<id>.key`` with the common name ``<graph>:<id>`` that the graph's access control matches
(``zenoh_session.access_control``). Keys are EC P-256, mode 0600. Every certificate is both a server and
a client certificate (every member listens and connects). ``--host`` adds subject alternative
names (addresses or DNS names), needed only with ``zenoh.tls.verify_name: true``.

These are test certificates: for a real deployment, have your own CA sign certificates with the
same common names, and keep ``ca.key`` off the graph's hosts (docs/multi-host.md). The
certificates are made in process with ``cryptography`` (about 1 ms each); ``launch`` makes a
graph's per-run certificates with the same functions (``common.runtime.credentials``).
"""
from __future__ import annotations

import argparse
import ipaddress
import os
import shutil
import sys
from pathlib import Path
from typing import Iterable, Optional

from common.errors import NeedletrackError
from common.runtime.graph import LAUNCHER_IDENTITY, GraphError, load_graph
from common.runtime.zenoh_session import identity_name

DEFAULT_DAYS = 30


class CertError(NeedletrackError, RuntimeError):
    """A CA file that cannot be read."""


def _private(path: Path) -> None:
    os.chmod(path, 0o600)


def _write_key(path: Path, key) -> None:
    """An EC private key as PEM, created with mode 0600 (never readable by others, not even briefly)."""
    from cryptography.hazmat.primitives import serialization
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        path.unlink()
    except FileNotFoundError:
        pass
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    _private(path)


def _write_cert(path: Path, cert) -> None:
    from cryptography.hazmat.primitives import serialization
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def new_ca(name: str = "needletrack test CA", days: int = DEFAULT_DAYS) -> tuple:
    """A self-signed CA in memory: (certificate, EC P-256 private key)."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return cert, key


def new_cert(ca: tuple, common_name: str, hosts: Iterable[str] = (), days: int = DEFAULT_DAYS) -> tuple:
    """(certificate, key) for ``common_name`` signed by ``ca`` (``new_ca``'s pair), usable as
    server and client, naming localhost, 127.0.0.1 and ``hosts`` (addresses or DNS names)."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    ca_cert, ca_key = ca
    names: list = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=True,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(list(dict.fromkeys(names))), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    return cert, key


def make_ca(out: Path, name: str = "needletrack test CA", days: int = DEFAULT_DAYS) -> tuple:
    """``out/ca.pem`` and ``out/ca.key`` (made if either is missing); returns their paths."""
    out.mkdir(parents=True, exist_ok=True)
    ca, key = out / "ca.pem", out / "ca.key"
    if not (ca.is_file() and key.is_file()):
        cert, k = new_ca(name, days)
        _write_key(key, k)
        _write_cert(ca, cert)
    return ca, key


def load_ca(ca: Path, ca_key: Path) -> tuple:
    """A CA pair from its PEM files; raises ``CertError`` naming the file that cannot be used."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    try:
        cert = x509.load_pem_x509_certificate(Path(ca).read_bytes())
    except (OSError, ValueError) as exc:
        raise CertError(f"{ca}: not a PEM certificate ({exc})") from None
    try:
        key = serialization.load_pem_private_key(Path(ca_key).read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as exc:
        raise CertError(f"{ca_key}: not an unencrypted PEM private key ({exc})") from None
    return cert, key


def make_cert(ca: Path, ca_key: Path, cert: Path, key: Path, common_name: str,
              hosts: Iterable[str] = (), days: int = DEFAULT_DAYS) -> None:
    """A key and a certificate signed by ``ca`` for ``common_name``, usable as server and client."""
    c, k = new_cert(load_ca(ca, ca_key), common_name, hosts, days)
    _write_key(Path(key), k)
    _write_cert(Path(cert), c)


def write_identity(out: Path, identity: str, pair: tuple) -> None:
    """``out/<identity>.pem`` and ``out/<identity>.key`` (0600) of a ``new_cert`` pair."""
    _write_key(out / f"{identity}.key", pair[1])
    _write_cert(out / f"{identity}.pem", pair[0])


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
