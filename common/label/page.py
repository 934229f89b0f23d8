"""The labelling page (HTML and JavaScript, no library): both cameras on canvases with zoom
(wheel) and pan (right or middle drag, or shift + drag); a click places the tip, then the tail,
then points on the wire; the server fits the arc after every change and the page draws it with
A..E. A frame opens zoomed on the needle where its start says where it is. Keys are listed on
the page (``KEYS``). ``window.label`` exposes the view's pixel mapping
for the browser tests."""

KEYS = [("Enter / Space", "accept: save this frame's label and go to the next"),
        ("0", "no needle in this frame: save and go to the next"),
        ("n / →", "next frame (nothing saved)"), ("p / ←", "previous frame"),
        ("u / Ctrl+Z", "undo the last change"),
        ("1 / 2 / 3", "the next click is the tip / the tail / a wire point (else: tip, tail, then wire)"),
        ("h", "keypoint nearest the pointer: hidden / seen"),
        ("v", "camera under the pointer: needle not seen there / seen"),
        ("Delete", "remove the click nearest the pointer"),
        ("m", "the fit's other solution, where the images leave two"),
        ("s", "snap the arc to the wire in the images: on / off"),
        ("r", "the whole image; again: back to the needle")]

PAGE = r"""<!doctype html>
<html><head><meta charset="utf-8"><title>needletrack label</title>
<style>
 body {background:#111; color:#ddd; font:13px monospace; margin:6px}
 #bar {margin-bottom:4px; white-space:nowrap; overflow:hidden}
 .cams {display:flex; gap:6px} .cam {flex:1; min-width:0}
 canvas {width:100%; background:#000; display:block; cursor:crosshair}
 #msg {color:#fc6; min-height:1.3em} .err {color:#f66} .keys {color:#999; font-size:12px}
 b {color:#fff}
</style></head><body>
<div id="bar">needletrack label · <span id="head">loading…</span></div>
<div id="msg"></div>
<div class="cams"><div class="cam"><div>left</div><canvas id="left"></canvas></div>
<div class="cam"><div>right</div><canvas id="right"></canvas></div></div>
<div id="fit"></div>
<div class="keys">@KEYS@</div>
<script>
const CAMS = ['left', 'right'], KP = 'ABCDE';
const S = {session: null, frame: null, pos: 0, clicks: null, hist: [], edits: 0, choice: 0, snap: true,
           fit: null, err: null, force: null, views: {}, imgs: {}, pointer: null, busy: 0, seq: 0};
const $ = id => document.getElementById(id);
const clone = o => JSON.parse(JSON.stringify(o));

async function api(path, body) {
  const r = await fetch(path, body === undefined ? {cache: 'no-store'} :
    {method: 'POST', headers: {'Content-Type': 'application/json'}, body: JSON.stringify(body)});
  const text = await r.text();
  let js = null; try { js = JSON.parse(text); } catch (e) {}
  if (!r.ok) throw new Error((js && js.error) || text || r.status);
  return js;
}
function say(text, err) { $('msg').textContent = text || ''; $('msg').className = err ? 'err' : ''; }

// ---------------------------------------------------------------- views: image px <-> canvas px
function fitView(cam) {
  const c = $(cam), [w, h] = S.session.image_size;
  const cw = c.clientWidth; c.width = cw; c.height = Math.round(cw * h / w);
  S.views[cam] = {s: cw / w, ox: 0, oy: 0};
}
function toScreen(cam, u, v) {  // image px (pixel centres at integers) -> CSS px of the page
  const V = S.views[cam], r = $(cam).getBoundingClientRect();
  return [r.left + (u + 0.5) * V.s + V.ox, r.top + (v + 0.5) * V.s + V.oy];
}
function toImage(cam, x, y) {
  const V = S.views[cam], r = $(cam).getBoundingClientRect();
  return [(x - r.left - V.ox) / V.s - 0.5, (y - r.top - V.oy) / V.s - 0.5];
}
function zoomAt(cam, x, y, f) {
  const V = S.views[cam], r = $(cam).getBoundingClientRect(), px = x - r.left, py = y - r.top;
  V.ox = px - (px - V.ox) * f; V.oy = py - (py - V.oy) * f; V.s *= f; draw(cam);
}
function autoZoom(cam) {  // the needle a third of the canvas wide, where a fit or clicks say where it is
  fitView(cam);
  const k = S.clicks && S.clicks[cam], pts = [];
  if (S.fit && S.fit.arc[cam].length) pts.push(...S.fit.arc[cam]);
  else if (k) [k.tip, k.tail, ...k.wire].forEach(p => { if (p) pts.push(p); });
  if (pts.length < 2) return;
  const us = pts.map(p => p[0]), vs = pts.map(p => p[1]), c = $(cam);
  const ext = Math.max(Math.max(...us) - Math.min(...us), Math.max(...vs) - Math.min(...vs), 4);
  const scale = Math.min(Math.max(c.width / 3 / ext, S.views[cam].s), 8);
  setView(cam, scale, (Math.max(...us) + Math.min(...us)) / 2, (Math.max(...vs) + Math.min(...vs)) / 2);
}
function setView(cam, scale, u, v) {  // zoom so that one image px is `scale` canvas px, (u, v) centred
  const c = $(cam), V = S.views[cam];
  V.s = scale; V.ox = c.width / 2 - (u + 0.5) * scale; V.oy = c.height / 2 - (v + 0.5) * scale; draw(cam);
}

// ---------------------------------------------------------------- drawing
function draw(cam) {
  const c = $(cam), g = c.getContext('2d'), V = S.views[cam], img = S.imgs[cam];
  g.setTransform(1, 0, 0, 1, 0, 0); g.fillStyle = '#000'; g.fillRect(0, 0, c.width, c.height);
  if (!img || !V) return;
  g.imageSmoothingEnabled = V.s < 2;
  g.setTransform(V.s, 0, 0, V.s, V.ox, V.oy); g.drawImage(img, 0, 0); g.setTransform(1, 0, 0, 1, 0, 0);
  const P = (u, v) => [(u + 0.5) * V.s + V.ox, (v + 0.5) * V.s + V.oy];
  const k = S.clicks && S.clicks[cam];
  if (k && k.unseen) { g.fillStyle = 'rgba(0,0,0,0.5)'; g.fillRect(0, 0, c.width, c.height);
    g.fillStyle = '#fc6'; g.font = '16px monospace'; g.fillText('needle not seen here', 10, 24); }
  const f = S.fit;
  if (f && f.arc && f.arc[cam].length) {
    g.strokeStyle = f.pose_known ? '#3f3' : '#ff3'; g.lineWidth = 1.5; g.setLineDash(f.ambiguous ? [6, 4] : []);
    g.beginPath(); f.arc[cam].forEach(([u, v], i) => { const [x, y] = P(u, v); i ? g.lineTo(x, y) : g.moveTo(x, y); });
    g.stroke(); g.setLineDash([]);
    f.keypoints[cam].forEach(([u, v], i) => {
      const [x, y] = P(u, v), seen = f.visible[cam][i];
      g.strokeStyle = seen ? '#3f3' : '#888'; g.beginPath(); g.arc(x, y, 5, 0, 7); g.stroke();
      g.fillStyle = seen ? '#3f3' : '#888'; g.font = 'bold 13px monospace'; g.fillText(KP[i], x + 7, y - 7);
    });
  }
  if (k) {
    const mark = (p, col, r) => { if (!p) return; const [x, y] = P(p[0], p[1]);
      g.strokeStyle = col; g.lineWidth = 1.5; g.beginPath(); g.moveTo(x - r, y); g.lineTo(x + r, y);
      g.moveTo(x, y - r); g.lineTo(x, y + r); g.stroke(); };
    mark(k.tip, '#f44', 7); mark(k.tail, '#4af', 7); k.wire.forEach(p => mark(p, '#fd3', 5));
  }
}
function drawAll() { CAMS.forEach(draw); }

function status() {
  const s = S.session, i = S.frame ? S.frame.index : null;
  const n = s.statuses.filter(x => x === 'labelled' || x === 'no_needle').length;
  $('head').innerHTML = i === null ? 'no frames' :
    `frame <b>${i}</b> (${S.pos + 1}/${s.order.length} in order, least sure first) · <b>${s.statuses[i]}</b>` +
    ` · started from ${S.frame.start} · ${n} labelled · snap ${S.snap ? 'on' : 'off'}` +
    (S.frame.doubt !== null ? ` · detector doubt ${S.frame.doubt.toFixed(2)}` : '');
  const f = S.fit;
  $('fit').innerHTML = S.err ? `<span class="err">${S.err}</span>` : !f ? '' :
    `fit: ${f.stereo ? 'stereo' : 'one camera (' + f.cameras.join(',') + ')'} · fit rms ${f.rms_px.toFixed(2)} px` +
    ` · wire points snapped ${f.snapped} · keypoint sigma ${f.sigma_max_px.toFixed(2)} px` +
    ` · pose ${f.pose} ± ${f.pose_sigma_mm.toFixed(2)} mm, ${f.pose_sigma_deg.toFixed(1)} deg` +
    (f.pose_known ? ' <b>(written)</b>' : ' (not written: ' + (!f.stereo ? 'one camera' : f.ambiguous ? 'ambiguous' : 'not sure enough') + ')') +
    (f.alternatives ? ` · ${f.alternatives} other solution(s): m` : '');
}

// ---------------------------------------------------------------- frames
async function loadImage(i, cam) {
  return new Promise((done, fail) => { const im = new Image();
    im.onload = () => done(im); im.onerror = () => fail(new Error(`the ${cam} image cannot be shown`)); im.src = `image?i=${i}&camera=${cam}`; });
}
async function go(pos) {
  const s = S.session; if (!s.order.length) return;
  S.pos = Math.max(0, Math.min(s.order.length - 1, pos));
  const i = s.order[S.pos], my = ++S.seq;
  let fr, L, R;
  try { [fr, L, R] = await Promise.all([api(`api/frame?i=${i}`), loadImage(i, 'left'), loadImage(i, 'right')]); }
  catch (e) { say(`frame ${i}: ${e.message || e}`, true); return; }
  if (my !== S.seq) return;
  S.frame = fr; S.imgs = {left: L, right: R}; S.clicks = fr.clicks; S.hist = []; S.edits = 0; S.choice = 0;
  S.fit = fr.fit; S.err = fr.error; say(fr.note || '');
  api('api/position', {frame: i}).catch(() => {});
  CAMS.forEach(autoZoom); status(); drawAll();
}
async function refit() {
  const my = ++S.seq; S.busy++;
  try {
    const anyClick = CAMS.some(c => { const k = S.clicks[c]; return !k.unseen && (k.tip || k.tail || k.wire.length); });
    if (!anyClick) { S.fit = null; S.err = null; }
    else { const r = await api('api/fit', {frame: S.frame.index, clicks: S.clicks, choice: S.choice, snap: S.snap});
      if (my !== S.seq) return; S.fit = r.fit; S.err = r.error; }
  } catch (e) { S.err = String(e.message || e); }
  finally { S.busy--; }
  status(); drawAll();
}
function change(fn) { S.hist.push(clone(S.clicks)); fn(); S.edits++; S.choice = 0; refit(); drawAll(); }
async function save(noNeedle) {
  try {
    const r = await api('api/save', {frame: S.frame.index, clicks: S.clicks, choice: S.choice, snap: S.snap,
                                     no_needle: !!noNeedle, start: S.frame.start, edits: S.edits});
    S.session.statuses[S.frame.index] = r.status;
    say(`frame ${S.frame.index} saved (${r.status})`);
    await go(S.pos + 1 < S.session.order.length ? S.pos + 1 : S.pos);
  } catch (e) { say(String(e.message || e), true); }
}

// ---------------------------------------------------------------- mouse and keys
function nearestClick(cam, x, y, within) {
  const k = S.clicks[cam]; let best = null, bd = within;
  const test = (p, kind, j) => { if (!p) return; const [sx, sy] = toScreen(cam, p[0], p[1]);
    const d = Math.hypot(sx - x, sy - y); if (d < bd) { bd = d; best = {kind, j}; } };
  test(k.tip, 'tip'); test(k.tail, 'tail'); k.wire.forEach((p, j) => test(p, 'wire', j));
  return best;
}
function setClick(cam, h, p) { const k = S.clicks[cam]; if (h.kind === 'wire') k.wire[h.j] = p; else k[h.kind] = p; }
function inside(p) { const [w, h] = S.session.image_size; return p[0] >= -0.5 && p[1] >= -0.5 && p[0] <= w - 0.5 && p[1] <= h - 0.5; }
function setup(cam) {
  const c = $(cam); let drag = null;
  c.addEventListener('contextmenu', e => e.preventDefault());
  c.addEventListener('wheel', e => { e.preventDefault(); zoomAt(cam, e.clientX, e.clientY, e.deltaY < 0 ? 1.25 : 0.8); });
  c.addEventListener('mousedown', e => {
    if (!S.clicks) return;
    if (e.button !== 0 || e.shiftKey) { drag = {pan: true, x: e.clientX, y: e.clientY}; return; }
    const h = nearestClick(cam, e.clientX, e.clientY, 8);
    if (h) { drag = {h, before: clone(S.clicks), moved: false}; return; }
    const p = toImage(cam, e.clientX, e.clientY); if (!inside(p)) return;
    const k = S.clicks[cam];
    const kind = S.force || (!k.tip ? 'tip' : !k.tail ? 'tail' : 'wire'); S.force = null;
    change(() => { k.unseen = false; if (kind === 'wire') k.wire.push(p); else k[kind] = p; });
  });
  c.addEventListener('mousemove', e => {
    S.pointer = {cam, x: e.clientX, y: e.clientY};
    if (!drag) return;
    if (drag.pan) { const V = S.views[cam]; V.ox += e.clientX - drag.x; V.oy += e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY; draw(cam); return; }
    const p = toImage(cam, e.clientX, e.clientY); if (inside(p)) { setClick(cam, drag.h, p); drag.moved = true; draw(cam); }
  });
  window.addEventListener('mouseup', () => {
    if (drag && drag.h && drag.moved) { S.hist.push(drag.before); S.edits++; S.choice = 0; refit(); }
    drag = null;
  });
}
function nearestKeypoint() {
  const P = S.pointer; if (!P || !S.fit) return null; let best = null, bd = 1e9;
  S.fit.keypoints[P.cam].forEach(([u, v], i) => { const [x, y] = toScreen(P.cam, u, v);
    const d = Math.hypot(x - P.x, y - P.y); if (d < bd) { bd = d; best = i; } });
  return best === null ? null : {cam: P.cam, i: best};
}
document.addEventListener('keydown', e => {
  if (!S.frame) return;
  const k = e.key, P = S.pointer;
  if (k === 'Enter' || k === ' ') { e.preventDefault(); save(false); }
  else if (k === '0') save(true);
  else if (k === 'n' || k === 'ArrowRight') go(S.pos + 1);
  else if (k === 'p' || k === 'ArrowLeft') go(S.pos - 1);
  else if (k === 'u' || (k === 'z' && (e.ctrlKey || e.metaKey))) {
    if (S.hist.length) { S.clicks = S.hist.pop(); S.edits++; S.choice = 0; refit(); drawAll(); } else say('nothing to undo'); }
  else if (k === '1' || k === '2' || k === '3') { S.force = {1: 'tip', 2: 'tail', 3: 'wire'}[k]; say('next click: ' + S.force); }
  else if (k === 'h') { const n = nearestKeypoint(); if (n) change(() => { const h = S.clicks[n.cam].hidden; h[n.i] = !h[n.i]; }); }
  else if (k === 'v' && P) change(() => { S.clicks[P.cam].unseen = !S.clicks[P.cam].unseen; });
  else if ((k === 'Delete' || k === 'Backspace') && P) { const h = nearestClick(P.cam, P.x, P.y, 1e9);
    if (h) change(() => { const c = S.clicks[P.cam]; if (h.kind === 'wire') c.wire.splice(h.j, 1); else c[h.kind] = null; }); }
  else if (k === 'm') { if (S.fit && S.fit.alternatives) { S.choice++; refit(); } else say('no other solution'); }
  else if (k === 's') { S.snap = !S.snap; refit(); }
  else if (k === 'r') { S.whole = !S.whole; CAMS.forEach(S.whole ? fitView : autoZoom); drawAll(); }
});
window.addEventListener('resize', () => { CAMS.forEach(fitView); drawAll(); });

window.label = {S, toScreen, toImage, setView, go, idle: () => S.busy === 0 && !!S.frame};
(async () => {
  S.session = await api('api/session');
  CAMS.forEach(c => { setup(c); fitView(c); });
  await go(S.session.position);
})().catch(e => say(String(e.message || e), true));
</script></body></html>
"""


def page_html() -> bytes:
    keys = " · ".join(f"<b>{k}</b> {what}" for k, what in KEYS)
    return PAGE.replace("@KEYS@", keys).encode()
