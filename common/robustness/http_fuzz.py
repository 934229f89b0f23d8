"""The viewer page's HTTP server (``common.viewer.page``) under hostile and unlucky clients.

- ``fuzz_page(server, n, seed)``: ``n`` poison requests over real sockets to 127.0.0.1, one kind
  after another (``KINDS``: random bytes, truncated and bit-flipped requests, an over-long
  request line, too many or too large header fields, folded and control-character fields, a
  foreign or missing ``Host``, other methods and versions, request bodies, pipelined requests,
  resets mid-request, a half-closed request), a clean GET after every ``clean_every``; part of
  ``needletrack bench fuzz`` (the viewer's ``@http`` input). A crash: a clean GET not answered
  200, a poison request neither answered nor closed within ``ANSWER_S``, or a server error
  counted (``http_errors``).
- ``needletrack bench viewer-http``: the probe's cases against a page server in a child process
  (``--tree DIR``: the server of another checkout, e.g. to compare with main): RSS after 30
  clients sent 99 header fields of 60 KB and closed, against the process's baseline; a burst of
  200 concurrent GETs (answered, 503, timed out); 200 resets (log lines they caused); 100 idle
  clients (threads while they wait; whether the server closes them); a foreign ``Host``.
"""
from __future__ import annotations

import argparse
import os
import random
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

ANSWER_S = 5.0          # a poison request is answered or closed within this (s)
CLEAN = b"GET /state.json HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"

KINDS = ("random_bytes", "truncated", "bit_flips", "long_request_line", "many_headers", "large_head",
         "folded_header", "control_chars", "foreign_host", "no_host", "bad_host", "other_method",
         "bad_version", "body", "pipelined", "non_ascii_target", "reset", "half_close")


# ====================================================================== a raw client

def exchange(port: int, data: bytes, timeout: float = ANSWER_S, reset: bool = False,
             half_close: bool = False) -> tuple:
    """Send ``data`` on a new connection to 127.0.0.1:``port``; returns (status codes of the
    answers read until the server closed, what happened: 'closed' | 'timeout' | 'reset' | 'sent')."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        try:
            s.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            return [], "reset"
        if reset:                                 # RST instead of FIN
            s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            return [], "sent"
        if half_close:
            s.shutdown(socket.SHUT_WR)
        buf = b""
        try:
            while True:
                chunk = s.recv(65536)
                if not chunk:
                    return statuses(buf), "closed"
                buf += chunk
                if _complete(buf, data):
                    return statuses(buf), "answered"
        except socket.timeout:
            return statuses(buf), "timeout"
        except ConnectionResetError:
            return statuses(buf), "reset"


def _complete(buf: bytes, data: bytes) -> bool:
    """A keep-alive answer to one clean request is in (so that the client need not wait for a close)."""
    if data != CLEAN:
        return False
    head, sep, body = buf.partition(b"\r\n\r\n")
    if not sep:
        return False
    for line in head.split(b"\r\n"):
        if line.lower().startswith(b"content-length:"):
            return len(body) >= int(line.split(b":")[1])
    return False


def statuses(buf: bytes) -> list:
    """The status codes of the answers in ``buf`` (the page's bodies never hold a status line)."""
    return [int(m) for m in re.findall(rb"HTTP/1\.[01] ([0-9]{3}) ", buf)]


def poison(kind: str, rng: random.Random) -> tuple:
    """(payload, reset, half_close) of one poison request of ``kind``."""
    path = rng.choice([b"/", b"/state.json", b"/left.jpg", b"/x"])
    good = b"GET " + path + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"
    if kind == "random_bytes":
        return os.urandom(rng.randint(1, 4096)) + b"\r\n\r\n", False, False
    if kind == "truncated":
        return good[:rng.randint(1, len(good) - 1)], False, True
    if kind == "bit_flips":
        b = bytearray(good)
        for _ in range(rng.randint(1, 6)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        return bytes(b), False, True
    if kind == "long_request_line":
        return b"GET /" + b"a" * rng.randint(8200, 200_000) + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", False, False
    if kind == "many_headers":
        return (b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n" + b"".join(b"X-%d: 1\r\n" % i for i in range(rng.randint(65, 3000)))
                + b"\r\n"), False, False
    if kind == "large_head":
        return (b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n" + b"X-Big: " + b"b" * rng.randint(16_400, 300_000)
                + b"\r\n\r\n"), False, False
    if kind == "folded_header":
        return b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-A: 1\r\n  folded\r\n\r\n", False, False
    if kind == "control_chars":
        return b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-A: a\x00b\x7f\r\n\r\n", False, False
    if kind == "foreign_host":
        return b"GET / HTTP/1.1\r\nHost: " + rng.choice([b"evil.example", b"rebind.attacker.test:9090",
                                                         b"localhost.evil.test"]) + b"\r\n\r\n", False, False
    if kind == "no_host":
        return b"GET / HTTP/1.1\r\n\r\n", False, False
    if kind == "bad_host":
        return b"GET / HTTP/1.1\r\nHost: " + rng.choice([b"a b", b"[::1", b"x:port", b"", b"\xff\xfe",
                                                         b"127.0.0.1\r\nHost: evil"]) + b"\r\n\r\n", False, False
    if kind == "other_method":
        return rng.choice([b"POST", b"DELETE", b"PUT", b"get", b"CONNECT", b"G(T"]) + b" / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", False, False
    if kind == "bad_version":
        return b"GET / " + rng.choice([b"HTTP/2.0", b"HTTP/1.10", b"HTTP/x", b"FTP/1.0", b"", b"HTTP/1.1 extra"]) \
            + b"\r\nHost: 127.0.0.1\r\n\r\n", False, False
    if kind == "body":
        return b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n" + rng.choice(
            [b"Content-Length: 1000000000000\r\n", b"Content-Length: -1\r\n", b"Transfer-Encoding: chunked\r\n",
             b"Content-Length: 5\r\nContent-Length: 6\r\n"]) + b"\r\nhello", False, False
    if kind == "pipelined":
        return good.replace(b"\r\n\r\n", b"\r\nConnection: keep-alive\r\n\r\n") * rng.randint(2, 20) \
            + b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n", False, False
    if kind == "non_ascii_target":
        return b"GET /\xc3\xa9\xff HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", False, False
    if kind == "reset":
        return good[:rng.randint(0, len(good))], True, False
    if kind == "half_close":
        return good, False, True
    raise ValueError(f"unknown kind {kind!r}")


# ====================================================================== bench fuzz's @http input

def fuzz_page(server, n: int, seed: int = 0, clean_every: int = 50) -> dict:
    """``n`` poison requests to ``server`` (a ``PageServer``); see the module docstring.
    Returns payloads, refused (answered 4xx/5xx or closed), delivered (answered 2xx), crashes,
    first_crash and recovery (clean GETs until the first 200 after the poison)."""
    rng = random.Random(seed)
    res = {"payloads": 0, "refused": 0, "delivered": 0, "crashes": 0, "first_crash": "", "recovery": None}
    errors0 = server.counters["http_errors"]

    def crash(text):
        res["crashes"] += 1
        res["first_crash"] = res["first_crash"] or text[:300]

    def clean(where):
        try:
            codes, how = exchange(server.port, CLEAN)
        except OSError as exc:
            codes, how = [], f"{type(exc).__name__}: {exc}"
        if codes[:1] != [200]:
            crash(f"{where}: a clean GET got {codes} ({how})")
            return False
        return True

    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        data, reset, half = poison(kind, rng)
        res["payloads"] += 1
        try:
            codes, how = exchange(server.port, data, reset=reset, half_close=half)
        except OSError as exc:
            crash(f"{kind}: connect: {type(exc).__name__}: {exc}")
            continue
        if how == "timeout":
            crash(f"{kind}: neither answered nor closed in {ANSWER_S:g} s (codes {codes})")
        elif codes and all(200 <= c < 300 for c in codes):
            res["delivered"] += 1
        else:
            res["refused"] += 1
        if (i + 1) % clean_every == 0:
            clean(f"after {i + 1} payloads")
    for k in range(1, 61):
        if clean("recovery") or k == 60:
            res["recovery"] = k if res["crashes"] == 0 or k < 60 else None
            break
    deadline = time.monotonic() + 10
    while server.open_connections and time.monotonic() < deadline:
        time.sleep(0.05)
    if server.open_connections:
        crash(f"{server.open_connections} connections still open 10 s after the fuzz")
    if server.counters["http_errors"] > errors0:
        crash(f"{server.counters['http_errors'] - errors0} server errors counted (http_errors)")
    return res


# ====================================================================== the probe, in a child process

SERVER = r"""
import logging, os, sys
logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
if sys.argv[1] == "node":
    from common.runtime.node import node_class     # the library never imports nodes/
    s = node_class("viewer").offline({"port": 0, "rerun": False}, wired=["left", "right", "calib"]).page
else:
    from common.viewer.page import PageServer
    s = PageServer("127.0.0.1", 0)
s.set_frame("left", os.urandom(100_000))
print(s.port, file=sys.__stdout__, flush=True)
sys.stdin.read()
"""


def _proc(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def rss_mb(pid: int) -> float:
    return _proc(pid, "VmRSS") / 1024


def threads(pid: int) -> int:
    return _proc(pid, "Threads")


class ServerProcess:
    """A page server in a child process (``tree``: the checkout it imports; ``node``: inside an
    offline viewer node, with the node's imports, rather than alone); stderr to a file."""

    def __init__(self, tree: Path, log_path: Path, node: bool = False):
        env = dict(os.environ, PYTHONPATH=str(tree))
        self.log_path = log_path
        self.err = open(log_path, "w")
        self.p = subprocess.Popen([sys.executable, "-c", SERVER, "node" if node else "page"],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.err, env=env,
                                  cwd=str(tree))
        line = b""
        while line.strip().isdigit() is False:       # the node prints its URL first
            line = self.p.stdout.readline()
            if not line:
                raise RuntimeError(f"the page server did not start; see {log_path}")
        self.port = int(line)
        time.sleep(0.5)

    def log_lines(self) -> int:
        self.err.flush()
        return len(self.log_path.read_text().splitlines())

    def close(self):
        self.p.stdin.close()
        self.p.kill()
        self.p.wait(10)
        self.err.close()


def flood(port: int, clients: int = 30, fields: int = 98, size: int = 60_000) -> dict:
    """``clients`` at once, each sends ``Host`` and ``fields`` header fields of ``size`` bytes (99 in
    all: the most the standard library's server takes), then closes."""
    field = b"X-Flood: " + b"f" * size + b"\r\n"
    out = {"answers": [], "errors": 0}

    def one():
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
                s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
                for _ in range(fields):
                    s.sendall(field)
                s.sendall(b"\r\n")
                out["answers"] += statuses(s.recv(4096))
        except OSError:
            out["errors"] += 1               # the server closed after its 431 while we still sent
    ts = [threading.Thread(target=one) for _ in range(clients)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    return out


def burst(port: int, n: int = 200, timeout: float = 5.0) -> dict:
    """``n`` GETs at once, each on its own connection, ``timeout`` s each."""
    res = {"ok": 0, "503": 0, "timeout": 0, "other": 0}
    lock = threading.Lock()
    go = threading.Event()

    def one():
        go.wait()
        try:
            codes, how = exchange(port, b"GET /left.jpg HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n",
                                  timeout=timeout)
            key = "ok" if codes[:1] == [200] else "503" if codes[:1] == [503] else \
                "timeout" if how == "timeout" else "other"
        except socket.timeout:
            key = "timeout"
        except OSError:
            key = "other"
        with lock:
            res[key] += 1
    ts = [threading.Thread(target=one) for _ in range(n)]
    for t in ts:
        t.start()
    go.set()
    for t in ts:
        t.join()
    return res


def resets(port: int, n: int = 200) -> None:
    """``n`` connections that send part of a request and reset."""
    for i in range(n):
        exchange(port, CLEAN[:10 + i % 20], reset=True)


def idle(server: ServerProcess, n: int = 100, hold_s: float = 15.0) -> dict:
    """``n`` connections that send nothing: the server's threads while they wait, and how many it
    closed within ``hold_s``."""
    socks = [socket.create_connection(("127.0.0.1", server.port), timeout=hold_s) for _ in range(n)]
    time.sleep(1.0)
    during = threads(server.p.pid)
    t0 = time.monotonic()
    closed = 0
    for s in socks:
        s.settimeout(max(0.01, hold_s - (time.monotonic() - t0)))
        try:
            s.recv(1)                        # an answer (408, 503) or the end: the server let go
            closed += 1
        except OSError:
            pass
        s.close()
    return {"threads_while_idle": during, "closed_by_server": closed}


def probe(tree: Path, log_dir: Path, node: bool = False) -> dict:
    out = {}
    srv = ServerProcess(tree, log_dir / "server.log", node)
    try:
        base = rss_mb(srv.p.pid)
        f = flood(srv.port)
        time.sleep(2.0)
        out["flood"] = {"baseline_mb": round(base, 1), "after_mb": round(rss_mb(srv.p.pid), 1),
                        "answers": sorted(set(f["answers"])), "threads_after": threads(srv.p.pid)}
        out["burst"] = burst(srv.port)
        lines = srv.log_lines()
        resets(srv.port)
        time.sleep(2.5)
        out["resets"] = {"log_lines": srv.log_lines() - lines}
        out["host"] = exchange(srv.port, b"GET / HTTP/1.1\r\nHost: rebind.attacker.test:9090\r\n\r\n")[0]
        out["idle"] = idle(srv)
    finally:
        srv.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench viewer-http", description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", default=str(Path(__file__).resolve().parents[2]),
                    help="the checkout whose common/viewer/page.py serves (default: this one)")
    ap.add_argument("--log-dir", default=None, help="where the server's log goes (default: a temporary folder)")
    ap.add_argument("--node", action="store_true",
                    help="serve from an offline viewer node (the node's imports: its baseline RSS)")
    args = ap.parse_args(argv)
    import tempfile
    log_dir = Path(args.log_dir or tempfile.mkdtemp(prefix="viewer-http-"))
    log_dir.mkdir(parents=True, exist_ok=True)
    r = probe(Path(args.tree), log_dir, args.node)
    fl = r["flood"]
    print(f"viewer-http ({args.tree}{', in a viewer node' if args.node else ''}): header flood (30 clients x 99 fields of 60 KB): RSS {fl['baseline_mb']} MB "
          f"-> {fl['after_mb']} MB after they closed ({fl['after_mb'] / fl['baseline_mb']:.2f}x), answers "
          f"{fl['answers']}, {fl['threads_after']} threads")
    b = r["burst"]
    print(f"  burst of 200 GETs (5 s each): {b['ok']} answered 200, {b['503']} 503, {b['timeout']} timed out, "
          f"{b['other']} other")
    print(f"  200 resets: {r['resets']['log_lines']} log lines")
    print(f"  Host: rebind.attacker.test: answered {r['host']}")
    i = r["idle"]
    print(f"  100 idle clients: {i['threads_while_idle']} server threads while they wait; "
          f"{i['closed_by_server']} closed by the server within 15 s")
    print(f"  server log: {log_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
