"""The viewer's own web page: the Fig. 1 picture, the numbers and small plots, served on a
loopback port (no WebGL: it renders in any browser, headless included).

- ``/``: the page; it polls the two below (``poll_ms``) and draws the plots as SVG: the last
  ``keep_s`` seconds of each series with axes, ticks and units (errors on a log scale), a legend
  of the lines, laid out to fill the window's height;
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
 html, body {height:100%} * {box-sizing:border-box}
 body {background:#111; color:#ddd; font:13px monospace; margin:0; padding:6px 8px;
       display:flex; flex-direction:column; gap:4px}
 .cams {display:flex; gap:4px; flex:0 1 auto; min-height:0; max-height:58vh}
 .cams img {width:50%; max-width:960px; max-height:58vh; object-fit:contain; object-position:left top;
            background:#000; min-height:100px}
 .lower {flex:1 1 0; min-height:180px; display:flex; gap:8px}
 .side {flex:0 0 auto; display:flex; flex-direction:column; gap:6px; overflow:hidden}
 table {border-collapse:collapse} td,th {padding:1px 8px; text-align:right} td.note {text-align:left; max-width:10em}
 .legend {padding:2px 8px; display:flex; flex-wrap:wrap; gap:3px 16px; max-width:600px}
 #plot_confidence {grid-column:span 2}
 .legend span {white-space:nowrap} .legend i {display:inline-block; width:18px; height:3px; margin:0 5px 3px 0;
               vertical-align:middle}
 .plots {flex:1 1 0; min-width:0; display:grid; grid-template-columns:repeat(3, minmax(0, 1fr));
         grid-template-rows:repeat(2, minmax(0, 1fr)); gap:6px}
 .plot {background:#1b1b1b; min-height:0; min-width:0; overflow:hidden} .plot svg {display:block}
 svg text {font:11px monospace; fill:#aaa} svg .title {fill:#ddd; font-size:12px}
 a {color:#7cf}
</style></head><body>
<div>needletrack · <span id="head">waiting for frames…</span> · <a id="rr" href="#">3D view (Rerun)</a></div>
<div class="cams"><img id="left" src="left.jpg" alt="left camera"><img id="right" src="right.jpg" alt="right camera"></div>
<div class="lower">
 <div class="side"><table id="tab"></table><div class="legend" id="legend"></div></div>
 <div class="plots" id="plots"></div>
</div>
<script>
const POLL = @POLL_MS@, RR = @RERUN_URL@;
if (RR) document.getElementById('rr').href = RR; else document.getElementById('rr').remove();
// series key, title, unit, y scale: log (errors span decades), lin (from 0), unit (0 to 1)
const PLOTS = [["pos_err_mm", "position error", "mm", "log"], ["rot_err_deg", "orientation error", "deg", "log"],
               ["rate_hz", "pose rate", "Hz", "lin"], ["latency_ms", "latency", "ms", "lin"],
               ["confidence", "detector confidence", "", "unit"]];
const plotsEl = document.getElementById('plots');
for (const [k] of PLOTS) { const d = document.createElement('div'); d.className = 'plot'; d.id = 'plot_' + k; plotsEl.appendChild(d); }
const legendEl = document.getElementById('legend');
function niceStep(span, n) {
  const raw = span / n, p = Math.pow(10, Math.floor(Math.log10(raw))), f = raw / p;
  return (f < 1.5 ? 1 : f < 3.5 ? 2 : f < 7.5 ? 5 : 10) * p;
}
function fmt(v) { return Math.abs(v) >= 100 || v === 0 ? v.toFixed(0) : String(+v.toPrecision(3)); }
function plot(el, series, [key, title, unit, scale], colours, keep) {
  const W = Math.max(160, el.clientWidth), H = Math.max(80, el.clientHeight);
  const L = 48, R = 12, T = 20, B = 32, pw = W - L - R, ph = H - T - B;
  let s = `<svg width="${W}" height="${H}"><text class="title" x="6" y="14">${title}${unit ? ' (' + unit + ')' : ''}</text>`;
  const names = Object.keys(series || {});
  let lo = Infinity, hi = -Infinity;
  for (const n of names) for (const [t, v] of series[n]) if (scale !== 'log' || v > 0) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  let ticks = [], y;
  if (scale === 'log') {
    const floor = 0.01, a = Math.floor(Math.log10(Math.max(Math.min(lo, hi), floor))), b = Math.max(a + 1, Math.ceil(Math.log10(Math.max(hi, floor))));
    for (let k = a; k <= b; k++) ticks.push(Math.pow(10, k));
    y = v => T + ph * (1 - (Math.log10(Math.max(v, Math.pow(10, a))) - a) / (b - a));
  } else {
    let top = scale === 'unit' ? 1 : Math.max(hi > -Infinity ? hi : 1, 1e-9);
    const step = niceStep(top, 4); top = Math.ceil(top / step - 1e-9) * step;
    for (let i = 0; i * step <= top * (1 + 1e-9); i++) ticks.push(i * step);
    y = v => T + ph * (1 - Math.min(v, top) / top);
  }
  const x = t => L + pw * (Math.max(t, -keep) + keep) / keep;
  for (const v of ticks) {
    const yy = y(v).toFixed(1);
    s += `<line x1="${L}" x2="${L + pw}" y1="${yy}" y2="${yy}" stroke="#333"/><line x1="${L - 4}" x2="${L}" y1="${yy}" y2="${yy}" stroke="#888"/>` +
         `<text x="${L - 6}" y="${+yy + 4}" text-anchor="end">${fmt(v)}</text>`;
  }
  const xs = niceStep(keep, 6);
  for (let t = -keep; t <= 1e-9; t += xs) {
    const xx = x(t).toFixed(1);
    s += `<line x1="${xx}" x2="${xx}" y1="${T + ph}" y2="${T + ph + 4}" stroke="#888"/>` +
         `<text x="${xx}" y="${T + ph + 16}" text-anchor="middle">${fmt(t)}</text>`;
  }
  s += `<text x="${L + pw / 2}" y="${H - 3}" text-anchor="middle">time (s)</text>`;
  s += `<path d="M${L},${T} V${T + ph} H${L + pw}" fill="none" stroke="#888"/>`;
  if (!names.length) s += `<text x="${L + pw / 2}" y="${T + ph / 2}" text-anchor="middle">no data yet</text>`;
  for (const n of names) {
    const pts = series[n].filter(([t]) => t >= -keep).map(([t, v]) => `${x(t).toFixed(1)},${y(v).toFixed(1)}`).join(' ');
    s += `<polyline fill="none" stroke="${colours[n] || '#fff'}" stroke-width="1.5" points="${pts}"/>`;
  }
  el.innerHTML = s + '</svg>';
}
function legend(st) {
  // the methods (the final first), then each camera's line, then the truth drawn on the pictures
  const methods = new Set(Object.keys(st.methods || {})), cams = new Set();
  for (const k in (st.series || {})) for (const n in st.series[k]) (k === 'confidence' ? cams : methods).add(n);
  const item = (n, text) => `<span><i style="background:${st.colours[n] || '#fff'}"></i>${text}</span>`;
  let h = '';
  h += [...methods].sort((a, b) => (b === st.final) - (a === st.final) || a.localeCompare(b))
    .map(n => item(n, n + (n === st.final ? ' (final, thick)' : ''))).join('');
  h += [...cams].sort().map(n => item(n, n + ' camera (confidence)')).join('');
  if (st.colours.truth) h += item('truth', 'truth (on the pictures)');
  legendEl.innerHTML = h;
}
async function tick() {
  try {
    const st = await (await fetch('state.json', {cache: 'no-store'})).json();
    document.getElementById('head').textContent = st.head || '';
    const rows = Object.entries(st.methods || {});
    let h = '<tr><th style="text-align:left">method</th><th>seq</th><th>x,y,z (mm)</th><th>err mm</th><th>err deg</th><th>poses/s</th><th>latency ms</th><th></th></tr>';
    for (const [m, r] of rows) h += `<tr style="color:${st.colours[m] || '#fff'}"><td style="text-align:left">${m}</td><td>${r.seq}</td><td>${r.t_mm}</td><td>${r.pos_err_mm ?? '—'}</td><td>${r.rot_err_deg ?? '—'}</td><td>${r.rate_hz}</td><td>${r.latency_ms}</td><td class="note">${r.ambiguous ? 'ambiguous' + (r.tip_p != null ? ` (tip p ${r.tip_p})` : '') : ''}</td></tr>`;
    document.getElementById('tab').innerHTML = h;
    if (st.colours) {
      legend(st);
      for (const spec of PLOTS) plot(document.getElementById('plot_' + spec[0]), (st.series || {})[spec[0]], spec, st.colours, st.keep_s || 30);
    }
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
