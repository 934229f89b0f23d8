"""HTTP/1.1 request heads for the loopback pages' server (``common/viewer/http_server.py``): the bounds on
what a client may send (``HttpLimits``), parsing a head (``parse_head``, or ``HttpRefusal`` with
the status to answer), the ``Host`` check against DNS rebinding (``host_name``, ``HostCheck``:
``localhost``, the bound host, allowed names, address literals) and a response's bytes
(``http_response``).
Standard library only.
"""
from __future__ import annotations

import collections
import ipaddress
import re
from dataclasses import dataclass
from http import HTTPStatus
from typing import Iterable, Optional


@dataclass(frozen=True)
class HttpLimits:
    """Bounds on what a client may send or hold (see the module docstring)."""
    max_request_line: int = 8192      # bytes (414 beyond)
    max_head: int = 16384             # request line + header fields, bytes (431 beyond)
    max_headers: int = 64             # header fields (431 beyond)
    max_connections: int = 64         # served at once (then a short wait, then 503)
    timeout_s: float = 10.0           # to send a request head, to take an answer; keep-alive idle
    backlog: int = 1024               # listen queue (the kernel caps it at net.core.somaxconn)
    max_body: int = 65536             # a POST's body, bytes, where a server takes one (413 beyond)


_TOKEN = re.compile(rb"[!#$%&'*+\-.^_`|~0-9A-Za-z]+")
_VERSION = re.compile(rb"HTTP/([0-9])\.([0-9])")
_HOST = re.compile(r"[a-z0-9._~!$&'()*+,;=%-]+")
LOOPBACK_NAMES = ("localhost",)
WILDCARD_HOSTS = ("", "0.0.0.0", "::")


class HttpRefusal(Exception):
    """A request the server answers with ``status`` (and ``reason``), then closes; ``kind``
    names its counter (``http_<kind>``; None: the status's)."""

    def __init__(self, status: int, reason: str, kind: Optional[str] = None):
        super().__init__(f"{status} {reason}")
        self.status, self.reason, self.kind = status, reason, kind


@dataclass
class Request:
    method: str
    target: str
    version: tuple
    headers: dict                     # lower-case name -> list of values

    def get(self, name: str) -> list:
        return self.headers.get(name, [])


def parse_head(request_line: bytes, fields: list) -> Request:
    """The request from its raw request line and header field lines (CRLF or LF ended), or
    ``HttpRefusal`` (400 malformed, 505 not HTTP/1.x)."""
    parts = request_line.rstrip(b"\r\n").split(b" ")
    if len(parts) != 3:
        raise HttpRefusal(400, "request line: expected METHOD TARGET HTTP/1.x")
    method, target, version = parts
    m = _VERSION.fullmatch(version)
    if m is None:
        raise HttpRefusal(400, "request line: bad HTTP version")
    if m.group(1) != b"1":
        raise HttpRefusal(505, "only HTTP/1.0 and HTTP/1.1")
    if not _TOKEN.fullmatch(method):
        raise HttpRefusal(400, "request line: bad method")
    if not target.startswith(b"/") or any(c < 0x21 or c > 0x7e for c in target):
        raise HttpRefusal(400, "request line: the target must be a path")
    headers: dict = collections.defaultdict(list)
    for raw in fields:
        line = raw.rstrip(b"\r\n")
        if line[:1] in (b" ", b"\t"):
            raise HttpRefusal(400, "header: folded lines are not accepted")
        name, sep, value = line.partition(b":")
        if not sep or not _TOKEN.fullmatch(name):
            raise HttpRefusal(400, "header: expected NAME: VALUE")
        value = value.strip(b" \t")
        if any(c < 0x20 and c != 0x09 or c == 0x7f for c in value):
            raise HttpRefusal(400, "header: control character in a value")
        headers[name.decode("ascii").lower()].append(value.decode("latin-1"))
    return Request(method.decode("ascii"), target.decode("ascii"), (1, int(m.group(2))), dict(headers))


def host_name(value: str) -> Optional[str]:
    """The host of a ``Host`` value: lower case, no port, no brackets, no trailing dot; None when
    malformed."""
    v = value.strip().lower()
    if v.startswith("["):
        end = v.find("]")
        name, rest = (v[1:end], v[end + 1:]) if end > 0 else ("", "")
        if not name or any(c not in "0123456789abcdef:." for c in name):
            return None
    else:
        name, sep, port = v.partition(":")
        rest = sep + port
        name = name[:-1] if name.endswith(".") else name
        if not name or not _HOST.fullmatch(name):
            return None
    if rest and not (rest[0] == ":" and rest[1:].isdigit() or rest == ":"):
        return None
    return name


def is_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def is_loopback(address: str) -> bool:
    """Whether ``address`` (an IP address or a name) is loopback only."""
    if address.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(address).is_loopback
    except ValueError:
        return False


class HostCheck:
    """Which ``Host`` names the server answers (see the module docstring)."""

    def __init__(self, bound_host: str, allowed: Iterable[str] = ()):
        allowed = [str(a).strip().lower() for a in allowed]
        self.any = "*" in allowed
        self.names = set(LOOPBACK_NAMES) | {a.rstrip(".") for a in allowed if a and a != "*"}
        if bound_host.lower() not in WILDCARD_HOSTS:
            self.names.add(bound_host.lower().strip("[]").rstrip("."))

    def allows(self, name: str) -> bool:
        return self.any or name in self.names or is_address(name)


def http_response(status: int, ctype: str, body: bytes, head_only: bool = False, close: bool = False,
              extra: tuple = ()) -> bytes:
    lines = [f"HTTP/1.1 {status} {HTTPStatus(status).phrase}", f"Content-Type: {ctype}",
             f"Content-Length: {len(body)}", "Cache-Control: no-store", "X-Content-Type-Options: nosniff",
             *extra, *(("Connection: close",) if close else ())]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + (b"" if head_only else body)
