// The transfer-function editor of volume mode: the bands drawn over the field's histogram
// (log counts). Drag a band to move it, its side to widen it, its top to raise its peak; its
// colour is its isovalue's colour. Each drag sends {op: "band", index, center|width|peak}
// every SEND_MS at most (the newest value wins); the server answers with the state, and the
// image follows without compiling.
"use strict";

const SEND_MS = 30;
const PICK_PX = 7;
const tf = { drag: null, yMax: 2, pending: null, timer: null };

function tfCanvas() { return $("tf-editor"); }

function tfGeometry() {
  const c = tfCanvas();
  const [lo, hi] = info.value_range;
  const top = 8, base = c.height - 4;
  return {
    w: c.width, lo, hi, top, base,
    x: (v) => (v - lo) / (hi - lo || 1) * c.width,
    v: (x) => lo + x / c.width * (hi - lo),
    y: (p) => base - p / tf.yMax * (base - top),
    p: (y) => (base - y) / (base - top) * tf.yMax,
  };
}

// The bands as the page shows them: the state's, with the one being dragged at its new value.
function shownBands() {
  const b = state.bands;
  const out = state.isovalues.map((iso, i) => ({
    iso, width: b.width[i], lo: b.offsets[i][0], hi: b.offsets[i][1], peak: b.peak[i],
    color: state.iso_colors[i] }));
  const d = tf.drag;
  if (d && d.value !== undefined) {
    const band = out[d.i];
    if (d.kind === "center") band.iso = d.value;
    if (d.kind === "width") { band.width = d.value; band.lo = -2 * d.value; band.hi = 2 * d.value; }
    if (d.kind === "peak") band.peak = d.value;
  }
  return out;
}

function drawBands() {
  const c = tfCanvas();
  const box = $("tf-fieldset");
  box.hidden = !state || !info || state.mode !== "volume";
  c.hidden = !!(state && state.tf2d);
  if (box.hidden || c.hidden || !c.getContext) return;
  if (!tf.drag) tf.yMax = Math.max(2, 1.25 * Math.max(...state.bands.peak));
  const g = tfGeometry();
  const ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  const counts = info.histogram;
  const most = Math.log1p(Math.max(1, ...counts));
  ctx.fillStyle = "#3c4656";
  counts.forEach((n, i) => {
    const h = (g.base - g.top) * Math.log1p(n) / most;
    ctx.fillRect(i * c.width / counts.length, g.base - h, c.width / counts.length, h);
  });
  ctx.strokeStyle = "#777";
  ctx.setLineDash([3, 3]);
  ctx.beginPath(); ctx.moveTo(0, g.y(1)); ctx.lineTo(c.width, g.y(1)); ctx.stroke();
  ctx.setLineDash([]);
  for (const b of shownBands()) drawBand(ctx, g, b);
  const note = $("band-color-note");
  note.textContent = state.color_field ?
    `Band colours are replaced by the colour map of '${state.color_field}' (the colour field); ` +
    `set Colour field to (none) to give each band its own colour.` : "";
}

function drawBand(ctx, g, b) {
  ctx.beginPath();
  const x0 = g.x(b.iso + b.lo), x1 = g.x(b.iso + b.hi);
  for (let x = Math.floor(x0); x <= Math.ceil(x1); x++) {
    const u = (g.v(x) - b.iso) / b.width;
    const y = g.y(b.peak * Math.exp(-0.5 * u * u));
    if (x === Math.floor(x0)) ctx.moveTo(x, g.base); else ctx.lineTo(x, y);
  }
  ctx.lineTo(x1, g.base);
  ctx.fillStyle = b.color + "99";
  ctx.strokeStyle = b.color;
  ctx.fill();
  ctx.stroke();
  ctx.fillStyle = "#fff";
  const cx = g.x(b.iso), w = g.x(b.iso + b.width) - cx;
  ctx.fillRect(cx - 3, g.y(b.peak) - 3, 6, 6);                     // the peak's handle
  for (const side of [-1, 1]) ctx.fillRect(cx + side * w - 1, g.y(0.6 * b.peak), 2, 8);
}

// Where each band's handles are, in page (client) pixels: for scripts driving the page.
window.bandHandles = () => {
  const c = tfCanvas(), r = c.getBoundingClientRect(), g = tfGeometry();
  const sx = r.width / c.width, sy = r.height / c.height;
  return shownBands().map((b) => ({
    center: [r.left + g.x(b.iso) * sx, r.top + g.y(0.3 * b.peak) * sy],
    side: [r.left + g.x(b.iso + b.width) * sx, r.top + g.y(0.3 * b.peak) * sy],
    peak: [r.left + g.x(b.iso) * sx, r.top + g.y(b.peak) * sy],
  }));
};

function pick(x, y) {
  const g = tfGeometry();
  let best = null;
  shownBands().forEach((b, i) => {
    const cx = g.x(b.iso), w = Math.abs(g.x(b.iso + b.width) - cx);
    let kind = null;
    if (Math.abs(x - cx) < PICK_PX && Math.abs(y - g.y(b.peak)) < PICK_PX) kind = "peak";
    else if (Math.abs(Math.abs(x - cx) - w) < PICK_PX / 2) kind = "width";
    else if (x >= g.x(b.iso + b.lo) && x <= g.x(b.iso + b.hi)) kind = "center";
    const d = Math.abs(x - cx);
    if (kind && (!best || d < best.d)) best = { i, kind, d, b };
  });
  return best;
}

function canvasPoint(e) {
  const c = tfCanvas(), r = c.getBoundingClientRect();
  return [(e.clientX - r.left) * c.width / r.width, (e.clientY - r.top) * c.height / r.height];
}

function flushBand() {
  tf.timer = null;
  if (tf.pending) { send(tf.pending); tf.pending = null; }
}

function dragBand(e) {
  const d = tf.drag;
  if (!d) return;
  const [x, y] = canvasPoint(e);
  const g = tfGeometry();
  if (d.kind === "center") d.value = Math.min(g.hi, Math.max(g.lo, d.b.iso + g.v(x) - g.v(d.x0)));
  else if (d.kind === "width") d.value = Math.max(Math.abs(g.v(x) - d.b.iso), (g.hi - g.lo) * 1e-4);
  else d.value = Math.max(g.p(y), 0.01);
  tf.pending = { op: "band", index: d.i, [d.kind]: d.value };
  if (tf.timer === null) tf.timer = setTimeout(flushBand, SEND_MS);
  drawBands();
}

function wireBands() {
  const c = tfCanvas();
  c.addEventListener("pointerdown", (e) => {
    const [x, y] = canvasPoint(e);
    const hit = pick(x, y);
    if (!hit) return;
    tf.drag = { i: hit.i, kind: hit.kind, b: hit.b, x0: x };
    c.setPointerCapture(e.pointerId);
  });
  c.addEventListener("pointermove", dragBand);
  const end = () => {
    if (!tf.drag) return;
    if (tf.timer !== null) clearTimeout(tf.timer);
    flushBand();
    tf.drag = null;
    drawBands();
  };
  c.addEventListener("pointerup", end);
  c.addEventListener("pointercancel", end);
  hooks.state.push(drawBands);
  hooks.info.push(() => { if (state) drawBands(); });
}

window.addEventListener("DOMContentLoaded", wireBands);
