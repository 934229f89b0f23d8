"""A small HTTP/1.1 server on asyncio in one thread, for the project's loopback pages (the live
viewer's, ``common/viewer/page.py``; the labelling page's, ``common/label/server.py``): GET and
HEAD, and where a page asks for it POST with a JSON body; keep-alive; whatever the number of
clients, every input is bounded (``HttpLimits``):

- a request line over ``max_request_line`` bytes: 414; a head (request line and header fields)
  over ``max_head`` bytes or with more than ``max_headers`` fields: 431; malformed: 400;
  a body where none is taken, or over ``max_body``: 413; another method: 405; HTTP/2 or later:
  505; then the connection is closed;
- more than ``max_connections`` served at once: a new one waits up to ``QUEUE_S`` for a slot,
  then gets 503 (``Retry-After: 1``) and is closed; beyond 4x ``max_connections`` open, dropped;
- a head not complete within ``timeout_s``: 408 and closed (an idle keep-alive connection is
  closed without an answer); a client that does not take its answer within ``timeout_s``: dropped;
- ``Host`` must name this server (DNS rebinding): ``localhost``, the bound host, a name in
  ``allowed_hosts`` (``"*"``: any) or an address literal (the page's origin is then the address
  itself, which no other site can take); the port is not checked (an SSH tunnel changes it).
  Another name: 403. HTTP/1.1 without ``Host``: 400;
- an ``Origin`` must be the page's own (``http://`` + the request's ``Host``): another site's
  page in the same browser gets 403, as does what a browser says another page fetches
  (``Sec-Fetch-Site`` not ``same-origin``, other than a navigation to it); a POST must state its
  ``Origin`` and send ``application/json`` (403, 415);
- a listen backlog of ``backlog`` (a burst of connections waits, it is not refused).

Refused requests (``http_bad_host``, ``http_bad_origin``, ``http_too_large``,
``http_bad_requests``), resets, timeouts and server errors are counted (``counters``, and the
``count`` callback: a node's stats, ``http_*``) and logged once a second per kind with the
number left out; no traceback. Binding a non-loopback address logs a warning.
"""
from __future__ import annotations

import asyncio
import collections
import logging
import socket
import threading
from dataclasses import dataclass
from typing import Callable, Iterable, Optional

from common.runtime.node import RateLimitedLog
from common.viewer.http_request import (
    HostCheck,
    HttpLimits,
    HttpRefusal,
    Request,
    host_name,
    http_response,
    is_loopback,
    parse_head,
)

QUEUE_S = 2.0           # a connection beyond max_connections waits this long for a slot, then 503


@dataclass
class Answer:
    """A handler's answer: ``status``, ``ctype`` and ``body``; ``body`` None with status 200 is
    a 503 ("not ready")."""
    status: int
    ctype: str
    body: Optional[bytes]


Handler = Callable[[Request, bytes], Answer]


class HttpServer:
    """Serves ``handler(request, body) -> Answer`` on ``http://host:port/`` from a daemon thread
    (``port`` 0: any free port; ``url`` says which), with the bounds and checks of the module
    docstring. ``methods``: those answered (GET and HEAD; add POST for a page that changes
    something: then ``limits.max_body`` bounds its body); ``blocking``: the handler may take a
    while (a fit, a file): it runs in a worker thread, one request at a time, not on the server's
    loop. ``name``: how the log calls it; ``allowed_hosts``: more ``Host`` names to answer;
    ``log``: where refusals go (once a second per kind); ``count(name)``: called for each counted
    event (``counters`` holds them too). Raises OSError when it cannot bind."""

    def __init__(self, host: str, port: int, handler: Handler, *, name: str = "page",
                 methods: Iterable[str] = ("GET", "HEAD"), blocking: bool = False,
                 allowed_hosts: Iterable[str] = (), limits: HttpLimits = HttpLimits(),
                 log: Optional[logging.Logger] = None, count: Optional[Callable[[str], None]] = None):
        self.handler, self.name, self.blocking = handler, name, blocking
        self.methods = tuple(m.upper() for m in methods)
        self._handler_lock = threading.Lock()
        self.requests = 0
        self.open_connections = 0
        self.counters: collections.Counter = collections.Counter()
        self.limits = limits
        self.log = log or logging.getLogger(f"http.{name}")
        self._errlog = RateLimitedLog(self.log, period=1.0, level=logging.WARNING)
        self._count = count
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._sock = socket.create_server((host, port), family=family, backlog=limits.backlog)
        self.host, self.port = self._sock.getsockname()[:2]
        self.hosts = HostCheck(host, allowed_hosts)
        self.url = f"http://{'[' + self.host + ']' if ':' in self.host else self.host}:{self.port}/"
        if not is_loopback(self.host):
            self.log.warning("the %s listens on %s, not a loopback address: whoever reaches port %d "
                             "sees the endoscope pictures (no authentication, no TLS); Host names "
                             "answered: %s and address literals (param allowed_hosts)", name, self.host,
                             self.port, ", ".join(sorted(self.hosts.names)) if not self.hosts.any else "any")
        self._writers: set = set()
        self._tasks: set = set()
        self._loop = asyncio.new_event_loop()
        self._loop.set_exception_handler(self._loop_error)
        started = threading.Event()
        self._start_error: Optional[BaseException] = None
        self._thread = threading.Thread(target=self._run, args=(started,), name=f"http-{name}", daemon=True)
        self._thread.start()
        started.wait()
        if self._start_error is not None:
            self._sock.close()
            raise OSError(f"{name}: cannot serve on {self.url}: {self._start_error}")

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
            self._errlog.error(name, f"{self.name}: {text} (counted {name})", exc_info=exc_info)

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
                return await self._answer_and_close(reader, writer, http_response(
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
                body = await self._read_body(reader, req)
                answer = await self._respond(req, body, close=not keep)
            except TimeoutError:
                if not got:                                # idle keep-alive, or never a byte
                    self._note("idle_closed")
                    return writer.transport.abort()
                self._note("timeouts", f"{peer}: no complete request head within {L.timeout_s:g} s: 408")
                return await self._answer_and_close(reader, writer, http_response(
                    408, "text/plain", b"request head not complete in time\n", close=True))
            except HttpRefusal as r:
                kind = r.kind or {403: "bad_host", 414: "too_large", 431: "too_large"}.get(r.status, "bad_requests")
                self._note(kind, f"{peer}: {r.status} {r.reason}")
                return await self._answer_and_close(reader, writer, http_response(
                    r.status, "text/plain", f"{r.status} {r.reason}\n".encode(), close=True,
                    extra=(f"Allow: {', '.join(self.methods)}",) if r.status == 405 else ()))
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

    async def _read_body(self, reader: asyncio.StreamReader, req: Request) -> bytes:
        """The request's body (``Content-Length`` bytes, at most ``limits.max_body``, only for a
        method other than GET and HEAD that this server answers), or ``HttpRefusal``."""
        lengths = req.get("content-length")
        if req.get("transfer-encoding"):
            raise HttpRefusal(413 if req.method in ("GET", "HEAD") else 411,
                              "request bodies must state their Content-Length (no chunked transfer)")
        if len(set(v.strip() for v in lengths)) > 1 or any(not v.strip().isdigit() for v in lengths):
            raise HttpRefusal(400, "malformed Content-Length")
        n = int(lengths[0]) if lengths else 0
        if n == 0:
            return b""
        if req.method in ("GET", "HEAD") or req.method not in self.methods:
            raise HttpRefusal(413, "request bodies are not accepted")
        if n > self.limits.max_body:
            raise HttpRefusal(413, f"request body of {n} bytes, over the limit of {self.limits.max_body}")
        try:
            return await reader.readexactly(n)
        except asyncio.IncompleteReadError:
            raise HttpRefusal(400, "request body shorter than its Content-Length") from None

    def _check_origin(self, req: Request, host: Optional[str]) -> None:
        """A request that states an ``Origin`` must come from this server's own page: exactly
        ``http://`` and the request's own ``Host``; one a browser marks as fetched by another
        page (``Sec-Fetch-Site`` other than ``same-origin``, not a navigation: an image or a
        script of another site's page) is refused too. One that changes something (a method other than
        GET and HEAD) must state it and send JSON: another site's page cannot then make the browser
        send it (a form cannot send JSON; a script's cross-site JSON needs a preflight, refused)."""
        origins = req.get("origin")
        changes = req.method not in ("GET", "HEAD")
        site = (req.get("sec-fetch-site") or [""])[0].strip().lower()
        mode = (req.get("sec-fetch-mode") or [""])[0].strip().lower()
        if site not in ("", "same-origin", "none") and mode != "navigate":
            raise HttpRefusal(403, f"a {site[:20]} request from another page (only this {self.name}'s own "
                                   "page may fetch from it)", "bad_origin")
        if len(origins) > 1:
            raise HttpRefusal(400, "expected at most one Origin header")
        if origins:
            if host is None or origins[0].strip().lower() != f"http://{host.strip().lower()}":
                raise HttpRefusal(403, f"Origin {origins[0][:80]!r} is not this {self.name}'s", "bad_origin")
        elif changes:
            raise HttpRefusal(403, f"a {req.method[:20]} must state its Origin (this {self.name}'s own page)",
                              "bad_origin")
        if changes:
            ctype = (req.get("content-type") or [""])[0].split(";", 1)[0].strip().lower()
            if ctype != "application/json":
                raise HttpRefusal(415, f"a {req.method[:20]} must send application/json, got {ctype[:60]!r}")

    async def _respond(self, req: Request, body: bytes, close: bool) -> bytes:
        """The answer to a parsed request, or ``HttpRefusal``."""
        hosts = req.get("host")
        if len(hosts) > 1 or (req.version >= (1, 1) and not hosts):
            raise HttpRefusal(400, "expected one Host header")
        if hosts:
            name = host_name(hosts[0])
            if name is None:
                raise HttpRefusal(400, f"malformed Host {hosts[0][:80]!r}")
            if not self.hosts.allows(name):
                raise HttpRefusal(403, f"Host {name[:80]!r} is not this {self.name}'s (allowed_hosts)")
        if req.method not in self.methods:
            raise HttpRefusal(405, f"method {req.method[:20]} not allowed")
        self._check_origin(req, hosts[0] if hosts else None)
        self.requests += 1
        head = req.method == "HEAD"
        if self.blocking:
            a = await asyncio.to_thread(self._handle_locked, req, body)
        else:
            a = self.handler(req, body)
        if a.status == 200 and a.body is None:
            return http_response(503, "text/plain", b"not ready yet\n", head, close)
        return http_response(a.status, a.ctype, a.body or b"", head, close)

    def _handle_locked(self, req: Request, body: bytes) -> Answer:
        with self._handler_lock:
            return self.handler(req, body)

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
