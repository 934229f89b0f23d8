"""The viewer page's HTTP server against hostile and unlucky clients, over real sockets to
127.0.0.1: bounded heads (431/414/400), the connection cap (503), timeouts (408, idle closed),
a burst of connections (the backlog), resets (counted, logged once a second, no traceback),
the Host allow-list (DNS rebinding), the warning on a non-loopback host, memory after a flood."""
import logging
import socket
import subprocess
import sys
import threading
import time

import pytest
from graphtools import REPO

from common.robustness.http_fuzz import (
    CLEAN,
    ServerProcess,
    burst,
    exchange,
    flood,
    rss_mb,
    statuses,
)
from common.viewer.http_request import HostCheck, HttpLimits, HttpRefusal, host_name, parse_head
from common.viewer.page import PageServer

DEADLINE = 30.0        # generous: the machine is shared


def _wait(pred, timeout=DEADLINE):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


@pytest.fixture
def server():
    servers = []

    def make(**kw):
        limits = kw.pop("limits", HttpLimits())
        s = PageServer("127.0.0.1", 0, limits=limits, **kw)
        s.set_state({"ok": 1})
        servers.append(s)
        return s
    yield make
    for s in servers:
        s.close()


def _get(port, host=b"127.0.0.1", extra=b"", version=b"HTTP/1.1"):
    data = b"GET /state.json " + version + b"\r\n" + (b"Host: " + host + b"\r\n" if host is not None else b"") \
        + extra + b"Connection: close\r\n\r\n"
    return exchange(port, data, timeout=DEADLINE)[0]


def test_parse_head_and_host_names():
    r = parse_head(b"GET /x?y HTTP/1.1\r\n", [b"Host: A.example:80\r\n", b"X-Two: 1\r\n", b"x-two: 2\r\n"])
    assert (r.method, r.target, r.version) == ("GET", "/x?y", (1, 1)) and r.get("x-two") == ["1", "2"]
    for line, fields, status in [(b"GET /\r\n", [], 400), (b"GET / HTTP/2.0\r\n", [], 505),
                                 (b"GET http://a/ HTTP/1.1\r\n", [], 400), (b"G@T / HTTP/1.1\r\n", [], 400),
                                 (b"GET / HTTP/1.1\r\n", [b" folded\r\n"], 400),
                                 (b"GET / HTTP/1.1\r\n", [b"Bad Name: 1\r\n"], 400),
                                 (b"GET / HTTP/1.1\r\n", [b"X: a\x00b\r\n"], 400)]:
        with pytest.raises(HttpRefusal) as e:
            parse_head(line, fields)
        assert e.value.status == status, (line, fields)
    assert host_name("LocalHost:9090") == "localhost" and host_name("[::1]:1") == "::1"
    assert host_name("example.org.") == "example.org" and host_name("a b") is None
    assert host_name("x:port") is None and host_name("[::1") is None and host_name("") is None
    check = HostCheck("127.0.0.1", ["viewer.lan"])
    assert check.allows("localhost") and check.allows("viewer.lan") and check.allows("10.1.2.3")
    assert not check.allows("rebind.attacker.test") and not check.allows("localhost.attacker.test")
    assert HostCheck("0.0.0.0", ["*"]).allows("anything.example")
    assert HostCheck("myhost", []).allows("myhost") and not HostCheck("0.0.0.0", []).allows("0.0.0.0.example")


def test_oversized_and_malformed_heads_are_refused_and_the_server_keeps_serving(server):
    s = server()
    big = b"X-Big: " + b"b" * 20_000 + b"\r\n"
    many = b"".join(b"X-%d: 1\r\n" % i for i in range(70))
    assert _get(s.port, extra=big) == [431]
    assert _get(s.port, extra=many) == [431]
    assert exchange(s.port, b"GET /" + b"a" * 9000 + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")[0] == [414]
    assert exchange(s.port, b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n")[0] == [400]
    assert exchange(s.port, b"POST / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")[0] == [405]
    assert exchange(s.port, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 9\r\n\r\nxxxxxxxxx")[0] == [413]
    assert _get(s.port) == [200]
    assert s.counters["http_too_large"] == 3 and s.counters["http_bad_requests"] == 3
    assert s.counters["http_errors"] == 0
    # keep-alive and pipelining still work within the limits
    codes, how = exchange(s.port, CLEAN * 3
                          + b"HEAD / HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n", timeout=DEADLINE)
    assert codes == [200, 200, 200, 200] and how == "closed"


def test_the_host_header_must_name_this_viewer(server):
    s = server()
    assert _get(s.port, b"rebind.attacker.test:%d" % s.port) == [403]
    assert _get(s.port, b"localhost:%d" % s.port) == [200]
    assert _get(s.port, b"localhost:8080") == [200]          # an SSH tunnel's port
    assert _get(s.port, b"[::1]:%d" % s.port) == [200]
    assert _get(s.port, None) == [400]                        # HTTP/1.1 without Host
    assert _get(s.port, None, version=b"HTTP/1.0") == [200]   # HTTP/1.0 may omit it
    assert _get(s.port, b"a\xffb") == [400]
    assert s.counters["http_bad_host"] == 1
    lan = server(allowed_hosts=["viewer.lan"])
    assert _get(lan.port, b"Viewer.LAN:9090") == [200] and _get(lan.port, b"other.lan") == [403]
    anyhost = server(allowed_hosts=["*"])
    assert _get(anyhost.port, b"whatever.example") == [200]


@pytest.mark.slow
def test_beyond_the_connection_cap_a_client_gets_503_then_a_slot_frees(server):
    s = server(limits=HttpLimits(max_connections=2, timeout_s=DEADLINE))
    holders = [socket.create_connection(("127.0.0.1", s.port)) for _ in range(2)]
    try:
        assert _wait(lambda: s.open_connections == 2)
        codes = _get(s.port)                      # waits QUEUE_S for a slot, then 503
        assert codes == [503] and s.counters["http_over_capacity"] == 1
    finally:
        for h in holders:
            h.close()
    assert _wait(lambda: s.open_connections == 0)
    assert _get(s.port) == [200]


def test_idle_and_slow_clients_are_let_go(server):
    s = server(limits=HttpLimits(timeout_s=0.5))
    with socket.create_connection(("127.0.0.1", s.port), timeout=DEADLINE) as idle, \
            socket.create_connection(("127.0.0.1", s.port), timeout=DEADLINE) as slow:
        slow.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
        assert idle.recv(100) == b""                   # closed, no answer
        answer = b""
        while chunk := slow.recv(4096):
            answer += chunk
        assert statuses(answer) == [408]
    assert s.counters["http_idle_closed"] == 1 and s.counters["http_timeouts"] == 1
    assert _wait(lambda: s.open_connections == 0)


def _listen_backlog(port: int) -> int:
    """The listen queue's length of 127.0.0.1:``port``, as ``ss`` reports it (Send-Q)."""
    out = subprocess.run(["ss", "-ltnH", f"sport = :{port}"], capture_output=True, text=True, check=True).stdout
    return int(out.split()[2])


def test_a_burst_of_200_connections_is_answered_none_times_out(server):
    s = server()
    assert _listen_backlog(s.port) == min(HttpLimits().backlog, int(open("/proc/sys/net/core/somaxconn").read()))
    s.set_frame("left", b"\xff\xd8" + b"j" * 50_000)
    res = burst(s.port, 200, timeout=DEADLINE)
    assert res["timeout"] == 0 and res["other"] == 0 and res["ok"] + res["503"] == 200, res
    assert res["ok"] >= 64, res


def test_resets_are_counted_and_logged_at_most_once_a_second_without_traceback(server, caplog):
    log = logging.getLogger("test-viewer-page")
    s = server(log=log)
    caplog.set_level(logging.WARNING, logger="test-viewer-page")
    t0 = time.monotonic()
    for i in range(200):
        exchange(s.port, CLEAN[:5 + i % 30], reset=True)
    assert _wait(lambda: s.counters["http_resets"] == 200), s.counters
    elapsed = time.monotonic() - t0
    records = [r for r in caplog.records if r.name == "test-viewer-page"]
    assert 1 <= len(records) <= int(elapsed) + 2
    assert not any(r.exc_info for r in records) and "http_resets" in records[0].getMessage()
    assert s.counters["http_errors"] == 0 and _get(s.port) == [200]


def test_the_viewer_node_counts_page_events_and_takes_its_http_params():
    from nodes.viewer import ViewerNode
    node = ViewerNode.offline({"port": 0, "rerun": False, "allowed_hosts": ["viewer.lan"], "max_connections": 3},
                              wired=["left", "right", "calib"])
    try:
        assert node.page.limits.max_connections == 3
        assert _get(node.page.port, b"viewer.lan") == [200] and _get(node.page.port, b"evil.example") == [403]
        assert node.counters["http_bad_host"] == 1
    finally:
        node.teardown()


def test_a_non_loopback_host_logs_a_warning():
    # in a network namespace of its own (only lo, down): binding 0.0.0.0 there reaches nothing
    code = ("import logging, sys; logging.basicConfig(stream=sys.stdout, format='%(levelname)s %(message)s');"
            "from nodes.viewer import ViewerNode;"
            "n = ViewerNode.offline({'host': '0.0.0.0', 'port': 0, 'rerun': False}, wired=['left']);"
            "n.teardown();"
            "m = ViewerNode.offline({'host': '127.0.0.1', 'port': 0, 'rerun': False}, wired=['left']); m.teardown()")
    p = subprocess.run(["unshare", "-rn", sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=REPO, timeout=120)
    assert p.returncode == 0, p.stderr
    warnings = [l for l in p.stdout.splitlines() if l.startswith("WARNING") and "not a loopback address" in l]
    assert len(warnings) == 1 and "0.0.0.0" in warnings[0] and "allowed_hosts" in warnings[0], p.stdout


@pytest.mark.slow
def test_memory_returns_after_a_header_flood(tmp_path):
    srv = ServerProcess(REPO, tmp_path / "server.log")
    try:
        base = rss_mb(srv.p.pid)
        out = flood(srv.port, clients=30, fields=98, size=60_000)
        assert set(out["answers"]) <= {431}
        time.sleep(1.0)
        after = rss_mb(srv.p.pid)
        assert after < 2 * base, (base, after)
        assert exchange(srv.port, CLEAN, timeout=DEADLINE)[0] == [200]
    finally:
        srv.close()
    assert "Traceback" not in (tmp_path / "server.log").read_text()


def test_many_connections_use_one_server_thread(server):
    s = server()
    before = threading.active_count()
    socks = [socket.create_connection(("127.0.0.1", s.port)) for _ in range(50)]
    try:
        assert _wait(lambda: s.open_connections == 50)
        assert threading.active_count() == before
    finally:
        for c in socks:
            c.close()
