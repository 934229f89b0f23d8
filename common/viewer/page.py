"""The viewer's own web page: the Fig. 1 picture, the numbers and small plots, served on a
loopback port (no WebGL: it renders in any browser, headless included).

- ``/``: the page; it polls the two below (``poll_ms``) and draws the plots as SVG;
- ``/left.jpg``, ``/right.jpg``: each camera's newest picture (JPEG; 503 before the first);
- ``/state.json``: the newest numbers and the time series (``ViewerState.to_json``).

The server, its bounds and its checks (Host, Origin): ``common.viewer.http_server``.
"""
from __future__ import annotations

import json
import logging
import threading
from typing import Callable, Iterable, Optional

from common.viewer.http_request import HttpLimits, Request
from common.viewer.http_server import Answer, HttpServer

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


class PageServer(HttpServer):
    """Serves the viewer's page on ``http://host:port/`` (``HttpServer``, GET and HEAD).
    ``set_frame(camera, jpeg)`` and ``set_state(dict)`` replace what it serves; both are cheap
    (a reference swap under a lock)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 9090, poll_ms: int = 100,
                 rerun_url: Optional[str] = None, *, allowed_hosts: Iterable[str] = (),
                 limits: HttpLimits = HttpLimits(), log: Optional[logging.Logger] = None,
                 count: Optional[Callable[[str], None]] = None):
        self._lock = threading.Lock()
        self._frames: dict = {}
        self._state = b"{}"
        self._page = PAGE.replace("@POLL_MS@", str(int(poll_ms))).replace(
            "@RERUN_URL@", json.dumps(rerun_url)).encode()
        self._routes = {"/": ("text/html; charset=utf-8", lambda: self._page),
                        "/index.html": ("text/html; charset=utf-8", lambda: self._page),
                        "/state.json": ("application/json", self._get_state),
                        "/left.jpg": ("image/jpeg", lambda: self._get_frame("left")),
                        "/right.jpg": ("image/jpeg", lambda: self._get_frame("right"))}
        super().__init__(host, port, self._handle, name="viewer page", allowed_hosts=allowed_hosts,
                         limits=limits, log=log or logging.getLogger("viewer.page"), count=count)

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

    def _handle(self, req: Request, body: bytes) -> Answer:
        route = self._routes.get(req.target.split("?", 1)[0])
        if route is None:
            return Answer(404, "text/plain", b"not found\n")
        ctype, get = route
        return Answer(200, ctype, get())
