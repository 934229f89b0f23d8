"""The viewer's own web page: the Fig. 1 picture, the numbers and small plots, served on a
loopback port (no WebGL: it renders in any browser, headless included).

- ``/``: the page; it polls the two below (``poll_ms``) and draws the plots as SVG;
- ``/left.jpg``, ``/right.jpg``: each camera's newest picture (JPEG; 503 before the first);
- ``/state.json``: the newest numbers and the time series (``ViewerState.to_json``).

The server is a small HTTP/1.1 one on asyncio in one thread (GET and HEAD, no request bodies,
keep-alive), whatever the number of clients; every input is bounded (``HttpLimits``):

- a request line over ``max_request_line`` bytes: 414; a head (request line and header fields)
  over ``max_head`` bytes or with more than ``max_headers`` fields: 431; malformed: 400;
  a body: 413; another method: 405; HTTP/2 or later: 505; then the connection is closed;
- more than ``max_connections`` served at once: a new one waits up to ``QUEUE_S`` for a slot,
  then gets 503 (``Retry-After: 1``) and is closed; beyond 4x ``max_connections`` open, dropped;
- a head not complete within ``timeout_s``: 408 and closed (an idle keep-alive connection is
  closed without an answer); a client that does not take its answer within ``timeout_s``: dropped;
- ``Host`` must name this server (DNS rebinding): ``localhost``, the bound host, a name in
  ``allowed_hosts`` (``"*"``: any) or an address literal (the page's origin is then the address
  itself, which no other site can take); the port is not checked (an SSH tunnel changes it).
  Another name: 403. HTTP/1.1 without ``Host``: 400;
- a listen backlog of ``backlog`` (a burst of connections waits, it is not refused).

Refused requests, resets, timeouts and server errors are counted (``counters``, and the
``count`` callback: the node's stats, ``http_*``) and logged once a second per kind with the
number left out; no traceback. Binding a non-loopback address logs a warning.
"""
from __future__ import annotations

import asyncio
import collections
import json
import logging
import socket
import threading
from typing import Callable, Iterable, Optional

from common.runtime.node import RateLimitedLog
from common.viewer.http_request import (
    HostCheck,
    HttpLimits,
    HttpRefusal,
    Request,
    _response,
    host_name,
    is_loopback,
    parse_head,
)

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>needletrack viewer</title>
<style>
 body {background:#111; color:#ddd; font:13px monospace; margin:8px}
 .cams {display:flex; gap:4px} .cams img {width:50%; max-width:960px; background:#000; min-height:100px}
 table {border-collapse:collapse; margin:6px 0} td,th {padding:1px 8px; text-align:right}
 .plots {display:flex; flex-wrap:wrap; gap:8px} .plot {background:#1b1b1b; padding:4px}
 a {color:#7cf}
</style></head><body>
<div>needletrack · <span id="head">waiting for frames…</span> · <a id="rr" href="#">3D view (Rerun)</a></div>
<div class="cams"><img id="left" src="left.jpg" alt="left camera"><img id="right" src="right.jpg" alt="right camera"></div>
<table id="tab"></table>
<div class="plots" id="plots"></div>
<script>
const POLL = @POLL_MS@, RR = @RERUN_URL@;
if (RR) document.getElementById('rr').href = RR; else document.getElementById('rr').remove();
const PLOTS = [["pos_err_mm","position error (mm)"],["rot_err_deg","orientation error (deg)"],
               ["rate_hz","poses/s"],["latency_ms","latency (ms)"],["confidence","detector confidence"]];
function plot(series, title, colours) {
  const W = 300, H = 110, names = Object.keys(series);
  let t0 = Infinity, t1 = -Infinity, v1 = 1e-9;
  for (const n of names) for (const [t, v] of series[n]) { t0 = Math.min(t0, t); t1 = Math.max(t1, t); v1 = Math.max(v1, v); }
  let s = `<svg width="${W}" height="${H}"><text x="4" y="12" fill="#ccc">${title} (max ${v1.toPrecision(3)})</text>`;
  for (const n of names) {
    const pts = series[n].map(([t, v]) => `${(4 + (W - 8) * (t - t0) / Math.max(t1 - t0, 1e-9)).toFixed(1)},${(H - 4 - (H - 24) * v / v1).toFixed(1)}`).join(' ');
    s += `<polyline fill="none" stroke="${colours[n] || '#fff'}" stroke-width="1.5" points="${pts}"/>`;
  }
  return `<div class="plot">${s}</svg></div>`;
}
async function tick() {
  try {
    const st = await (await fetch('state.json', {cache: 'no-store'})).json();
    document.getElementById('head').textContent = st.head || '';
    const rows = Object.entries(st.methods || {});
    let h = '<tr><th style="text-align:left">method</th><th>seq</th><th>x,y,z (mm)</th><th>err mm</th><th>err deg</th><th>poses/s</th><th>latency ms</th><th></th></tr>';
    for (const [m, r] of rows) h += `<tr style="color:${st.colours[m] || '#fff'}"><td style="text-align:left">${m}</td><td>${r.seq}</td><td>${r.t_mm}</td><td>${r.pos_err_mm ?? '—'}</td><td>${r.rot_err_deg ?? '—'}</td><td>${r.rate_hz}</td><td>${r.latency_ms}</td><td>${r.ambiguous ? 'ambiguous' + (r.tip_p != null ? ` (tip p ${r.tip_p})` : '') : ''}</td></tr>`;
    document.getElementById('tab').innerHTML = h;
    document.getElementById('plots').innerHTML = PLOTS.filter(([k]) => st.series && st.series[k] && Object.keys(st.series[k]).length)
      .map(([k, title]) => plot(st.series[k], title, st.colours)).join('');
  } catch (e) {}
  const t = Date.now();
  await Promise.all(['left', 'right'].map(cam => new Promise(done => {
    const img = new Image();
    img.onload = () => { document.getElementById(cam).src = img.src; done(); };
    img.onerror = done;
    img.src = cam + '.jpg?t=' + t;
  })));
  setTimeout(tick, POLL);
}
tick();
</script></body></html>
"""

QUEUE_S = 2.0           # a connection beyond max_connections waits this long for a slot, then 503


class PageServer:
    """Serves the page on ``http://host:port/`` from a daemon thread (``port`` 0: any free
    port; ``url`` says which). ``set_frame(camera, jpeg)`` and ``set_state(dict)`` replace what it
    serves; both are cheap (a reference swap under a lock). ``allowed_hosts``: more ``Host``
    names to answer; ``log``: where refusals go (once a second per kind); ``count(name)``: called
    for each counted event (``counters`` holds them too). Raises OSError when it cannot bind."""

    def __init__(self, host: str = "127.0.0.1", port: int = 9090, poll_ms: int = 100,
                 rerun_url: Optional[str] = None, *, allowed_hosts: Iterable[str] = (),
                 limits: HttpLimits = HttpLimits(), log: Optional[logging.Logger] = None,
                 count: Optional[Callable[[str], None]] = None):
        self._lock = threading.Lock()
        self._frames: dict = {}
        self._state = b"{}"
        self.requests = 0
        self.open_connections = 0
        self.counters: collections.Counter = collections.Counter()
        self.limits = limits
        self.log = log or logging.getLogger("viewer.page")
        self._errlog = RateLimitedLog(self.log, period=1.0, level=logging.WARNING)
        self._count = count
        self._page = PAGE.replace("@POLL_MS@", str(int(poll_ms))).replace(
            "@RERUN_URL@", json.dumps(rerun_url)).encode()
        self._routes = {"/": ("text/html; charset=utf-8", lambda: self._page),
                        "/index.html": ("text/html; charset=utf-8", lambda: self._page),
                        "/state.json": ("application/json", self._get_state),
                        "/left.jpg": ("image/jpeg", lambda: self._get_frame("left")),
                        "/right.jpg": ("image/jpeg", lambda: self._get_frame("right"))}
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._sock = socket.create_server((host, port), family=family, backlog=limits.backlog)
        self.host, self.port = self._sock.getsockname()[:2]
        self.hosts = HostCheck(host, allowed_hosts)
        self.url = f"http://{'[' + self.host + ']' if ':' in self.host else self.host}:{self.port}/"
        if not is_loopback(self.host):
            self.log.warning("the page listens on %s, not a loopback address: whoever reaches port %d "
                             "sees the endoscope pictures (no authentication, no TLS); Host names "
                             "answered: %s and address literals (param allowed_hosts)", self.host,
                             self.port, ", ".join(sorted(self.hosts.names)) if not self.hosts.any else "any")
        self._writers: set = set()
        self._tasks: set = set()
        self._loop = asyncio.new_event_loop()
        self._loop.set_exception_handler(self._loop_error)
        started = threading.Event()
        self._start_error: Optional[BaseException] = None
        self._thread = threading.Thread(target=self._run, args=(started,), name="viewer-page", daemon=True)
        self._thread.start()
        started.wait()
        if self._start_error is not None:
            self._sock.close()
            raise OSError(f"viewer page: cannot serve on {self.url}: {self._start_error}")

    # ------------------------------------------------------------ what it serves
    def set_frame(self, camera: str, jpeg: bytes) -> None:
        with self._lock:
            self._frames[camera] = bytes(jpeg)

    def set_state(self, state: dict) -> None:
        body = json.dumps(state, separators=(",", ":")).encode()
        with self._lock:
            self._state = body

    def _get_state(self) -> bytes:
        with self._lock:
            return self._state

    def _get_frame(self, camera: str) -> Optional[bytes]:
        with self._lock:
            return self._frames.get(camera)

    # ------------------------------------------------------------ the server
    def _run(self, started: threading.Event) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._slots = asyncio.Semaphore(self.limits.max_connections)
            self._server = self._loop.run_until_complete(asyncio.start_server(
                self._client, sock=self._sock, limit=self.limits.max_head, backlog=self.limits.backlog))
        except Exception as exc:        # noqa: BLE001  (reported to the constructor)
            self._start_error = exc
            self._loop.close()
            started.set()
            return
        started.set()
        try:
            self._loop.run_forever()
        finally:
            self._loop.close()

    def _note(self, kind: str, text: Optional[str] = None, exc_info: bool = False) -> None:
        """Count ``kind`` (``http_<kind>``); log ``text`` once a second per kind."""
        name = f"http_{kind}"
        self.counters[name] += 1
        if self._count is not None:
            self._count(name)
        if text is not None:
            self._errlog.error(name, f"viewer page: {text} (counted {name})", exc_info=exc_info)

    def _loop_error(self, loop, context: dict) -> None:
        exc = context.get("exception")
        if isinstance(exc, ConnectionError):      # a client's reset, surfacing in a stream future
            return self._note("resets", f"{type(exc).__name__}: {exc}")
        self._note("errors", f"{context.get('message', 'error')}: {type(exc).__name__ if exc else ''} {exc or ''}")

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "a client"
        self.open_connections += 1
        self._writers.add(writer)
        self._tasks.add(asyncio.current_task())
        try:
            if self.open_connections > 4 * self.limits.max_connections:
                self._note("over_capacity", f"{self.open_connections} connections open: dropped {peer}")
                return writer.transport.abort()
            try:                                 # a burst waits a little for a slot
                async with asyncio.timeout(QUEUE_S):
                    await self._slots.acquire()
            except TimeoutError:
                self._note("over_capacity", f"{self.limits.max_connections} connections served and no "
                                            f"slot free within {QUEUE_S:g} s: 503 to {peer}")
                try:
                    async with asyncio.timeout(1.0):
                        await self._read_head(reader, [])
                except (TimeoutError, HttpRefusal):
                    pass
                return await self._answer_and_close(reader, writer, _response(
                    503, "text/plain", b"too many connections\n", close=True, extra=("Retry-After: 1",)))
            try:
                await self._serve(reader, writer, peer)
            finally:
                self._slots.release()
        except (ConnectionError, asyncio.IncompleteReadError) as exc:
            self._note("resets", f"{peer}: {type(exc).__name__}: {exc}")
            writer.transport.abort()
        except Exception as exc:                 # noqa: BLE001  a bug: counted, logged, never a loop
            self._note("errors", f"{peer}: {type(exc).__name__}: {exc}", exc_info=True)
            writer.transport.abort()
        finally:
            self.open_connections -= 1
            self._writers.discard(writer)
            self._tasks.discard(asyncio.current_task())
            if not writer.transport.is_closing():
                writer.transport.abort()
            try:                                  # and retrieve a reset's exception
                async with asyncio.timeout(1.0):
                    await writer.wait_closed()
            except (Exception, asyncio.CancelledError):   # noqa: BLE001  (closing anyway)
                pass

    async def _read_head(self, reader: asyncio.StreamReader, got: list) -> Optional[Request]:
        """The next request; None at the end of the stream; ``got`` gets True at its first byte."""
        L = self.limits
        try:
            line = await reader.readline()
            if line in (b"\r\n", b"\n"):           # one empty line before a request is allowed
                line = await reader.readline()
        except ValueError:                            # longer than the reader's limit (max_head)
            raise HttpRefusal(414, f"request line longer than {L.max_request_line} bytes") from None
        if not line.endswith(b"\n"):
            return None                              # closed (mid-line or between requests)
        got.append(True)
        if len(line) > L.max_request_line:
            raise HttpRefusal(414, f"request line longer than {L.max_request_line} bytes")
        total, fields = len(line), []
        while True:
            try:
                field = await reader.readline()
            except ValueError:
                raise HttpRefusal(431, f"request head larger than {L.max_head} bytes") from None
            if not field.endswith(b"\n"):
                return None
            total += len(field)
            if total > L.max_head:
                raise HttpRefusal(431, f"request head larger than {L.max_head} bytes")
            if field in (b"\r\n", b"\n"):
                return parse_head(line, fields)
            if len(fields) >= L.max_headers:
                raise HttpRefusal(431, f"more than {L.max_headers} header fields")
            fields.append(field)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: str) -> None:
        L = self.limits
        while True:
            got: list = []
            try:
                async with asyncio.timeout(L.timeout_s):
                    req = await self._read_head(reader, got)
                if req is None:
                    return writer.close()
                keep = self._keep_alive(req)
                answer = self._respond(req, close=not keep)
            except TimeoutError:
                if not got:                                # idle keep-alive, or never a byte
                    self._note("idle_closed")
                    return writer.transport.abort()
                self._note("timeouts", f"{peer}: no complete request head within {L.timeout_s:g} s: 408")
                return await self._answer_and_close(reader, writer, _response(
                    408, "text/plain", b"request head not complete in time\n", close=True))
            except HttpRefusal as r:
                kind = {403: "bad_host", 414: "too_large", 431: "too_large"}.get(r.status, "bad_requests")
                self._note(kind, f"{peer}: {r.status} {r.reason}")
                return await self._answer_and_close(reader, writer, _response(
                    r.status, "text/plain", f"{r.status} {r.reason}\n".encode(), close=True,
                    extra=("Allow: GET, HEAD",) if r.status == 405 else ()))
            writer.write(answer)
            try:
                async with asyncio.timeout(L.timeout_s):
                    await writer.drain()
            except TimeoutError:
                self._note("slow_clients", f"{peer}: did not take its answer within {L.timeout_s:g} s: dropped")
                return writer.transport.abort()
            if not keep:
                return await self._close(writer)

    @staticmethod
    def _keep_alive(req: Request) -> bool:
        tokens = {t.strip().lower() for v in req.get("connection") for t in v.split(",")}
        return "close" not in tokens and (req.version >= (1, 1) or "keep-alive" in tokens)

    def _respond(self, req: Request, close: bool) -> bytes:
        """The answer to a parsed request, or ``HttpRefusal``."""
        hosts = req.get("host")
        if len(hosts) > 1 or (req.version >= (1, 1) and not hosts):
            raise HttpRefusal(400, "expected one Host header")
        if hosts:
            name = host_name(hosts[0])
            if name is None:
                raise HttpRefusal(400, f"malformed Host {hosts[0][:80]!r}")
            if not self.hosts.allows(name):
                raise HttpRefusal(403, f"Host {name[:80]!r} is not this viewer's (viewer param allowed_hosts)")
        if req.get("transfer-encoding") or any(v.strip() != "0" for v in req.get("content-length")):
            raise HttpRefusal(413, "request bodies are not accepted")
        if req.method not in ("GET", "HEAD"):
            raise HttpRefusal(405, f"method {req.method[:20]} not allowed")
        self.requests += 1
        route = self._routes.get(req.target.split("?", 1)[0])
        head = req.method == "HEAD"
        if route is None:
            return _response(404, "text/plain", b"not found\n", head, close)
        ctype, get = route
        body = get()
        if body is None:
            return _response(503, "text/plain", b"no frame yet\n", head, close)
        return _response(200, ctype, body, head, close)

    async def _answer_and_close(self, reader, writer, answer: bytes) -> None:
        """Send ``answer``, stop writing, read and discard what the client still sends (up to 1 s,
        so that the answer is not lost to a reset), then close."""
        writer.write(answer)
        try:
            async with asyncio.timeout(1.0):
                await writer.drain()
                if writer.can_write_eof():
                    writer.write_eof()
                while await reader.read(65536):
                    pass
        except (TimeoutError, ConnectionError, ValueError):
            return writer.transport.abort()
        await self._close(writer)

    async def _close(self, writer) -> None:
        writer.close()
        try:
            async with asyncio.timeout(self.limits.timeout_s):
                await writer.wait_closed()
        except (TimeoutError, ConnectionError):
            writer.transport.abort()

    def close(self) -> None:
        """Stop serving and drop every connection."""
        if not self._loop.is_running():
            return

        async def stop():
            self._server.close()
            for w in list(self._writers):
                w.transport.abort()
            for t in list(self._tasks):
                t.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)
            self._loop.stop()
        asyncio.run_coroutine_threadsafe(stop(), self._loop)
        self._thread.join(10)
