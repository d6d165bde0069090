// The 2D transfer function's editor (volume mode): the value x |grad f| histogram of the leaf
// cells as an image, and Gaussian blobs on it (ellipses at 1 and 2 sigma). Drag on the image
// to draw a blob, drag a blob to move it, shift-drag to resize it, double-click to remove it.
// Each edit sends every blob, {op: "tf2d", blobs: [[v, g, sigma_v, sigma_g, peak], ...]}, at
// most every SEND_MS; the server rasterizes them into the integrator's table (traversed,
// nothing compiles).
"use strict";

const tf2 = { drag: null, blobs: null, timer: null };

function plane() { return state.tf2d ? state.tf2d.plane : info.histogram2d.plane; }

function tf2Geometry() {
  const c = $("tf2d-editor");
  const [v0, v1, g0, g1] = plane();
  return {
    x: (v) => (v - v0) / (v1 - v0) * c.width,
    y: (g) => c.height - (g - g0) / (g1 - g0) * c.height,
    v: (x) => v0 + x / c.width * (v1 - v0),
    g: (y) => g0 + (c.height - y) / c.height * (g1 - g0),
    sx: (s) => s / (v1 - v0) * c.width,
    sy: (s) => s / (g1 - g0) * c.height,
  };
}

function currentBlobs() { return tf2.blobs || (state.tf2d ? state.tf2d.blobs : []); }

function drawTf2d() {
  const c = $("tf2d-editor");
  const on = !!(state && info && state.mode === "volume" && state.tf2d && info.histogram2d);
  c.hidden = !on;
  $("tf2d-help").hidden = !on;
  $("tf-help").hidden = on;
  $("tf2d-toggle").textContent = state && state.tf2d ? "Back to bands" :
    "2D transfer function";
  if (!on) return;
  const ctx = c.getContext("2d");
  const counts = info.histogram2d.counts;
  const rows = counts.length, cols = counts[0].length;
  const top = Math.max(1e-9, ...counts.map((r) => Math.max(...r)));
  const img = ctx.createImageData(c.width, c.height);
  for (let py = 0; py < c.height; py++) {
    const j = Math.min(rows - 1, Math.floor((c.height - 1 - py) / c.height * rows));
    for (let px = 0; px < c.width; px++) {
      const i = Math.min(cols - 1, Math.floor(px / c.width * cols));
      const t = counts[j][i] / top, k = 4 * (py * c.width + px);
      img.data[k] = 255 * Math.sqrt(t); img.data[k + 1] = 160 * t; img.data[k + 2] = 90 * t;
      img.data[k + 3] = 255;
    }
  }
  ctx.putImageData(img, 0, 0);
  const g = tf2Geometry();
  for (const [v, gr, sv, sg, peak] of currentBlobs()) {
    for (const n of [1, 2]) {
      ctx.beginPath();
      ctx.ellipse(g.x(v), g.y(gr), Math.max(1, n * g.sx(sv)), Math.max(1, n * g.sy(sg)), 0, 0,
                  2 * Math.PI);
      ctx.strokeStyle = n === 1 ? "#9fd4ff" : "#9fd4ff80";
      ctx.fillStyle = `rgba(120, 190, 255, ${0.25 * Math.min(1, peak)})`;
      if (n === 1) ctx.fill();
      ctx.stroke();
    }
  }
}

function tf2Point(e) {
  const c = $("tf2d-editor"), r = c.getBoundingClientRect();
  return [(e.clientX - r.left) * c.width / r.width, (e.clientY - r.top) * c.height / r.height];
}

function hitBlob(x, y) {
  const g = tf2Geometry();
  let best = -1, bestD = Infinity;
  currentBlobs().forEach(([v, gr, sv, sg], i) => {
    const d = ((x - g.x(v)) / Math.max(2, 2 * g.sx(sv))) ** 2 +
              ((y - g.y(gr)) / Math.max(2, 2 * g.sy(sg))) ** 2;
    if (d <= 1 && d < bestD) { best = i; bestD = d; }
  });
  return best;
}

function sendBlobs() {
  tf2.timer = null;
  if (tf2.blobs) send({ op: "tf2d", blobs: tf2.blobs });
}

function later() { if (tf2.timer === null) tf2.timer = setTimeout(sendBlobs, SEND_MS); }

function moveTf2(e) {
  const d = tf2.drag;
  if (!d) return;
  const [x, y] = tf2Point(e);
  const g = tf2Geometry();
  const blobs = d.start.map((b) => b.slice());
  const [x0, y0] = d.at;
  if (d.kind === "draw") {
    const sv = Math.abs(g.v(x) - g.v(x0)) / 4, sg = Math.abs(g.g(y) - g.g(y0)) / 4;
    if (sv <= 0 || sg <= 0) return;
    blobs.push([g.v((x + x0) / 2), Math.max(0, g.g((y + y0) / 2)), sv, sg, 1.0]);
  } else if (d.kind === "move") {
    const b = blobs[d.i];
    b[0] += g.v(x) - g.v(x0);
    b[1] = Math.max(0, b[1] + g.g(y) - g.g(y0));
  } else {
    const b = blobs[d.i];
    b[2] = Math.max(1e-9, Math.abs(g.v(x) - b[0]) / 2);
    b[3] = Math.max(1e-9, Math.abs(g.g(y) - b[1]) / 2);
  }
  tf2.blobs = blobs;
  later();
  drawTf2d();
}

// Where each blob's centre is, in page (client) pixels: for scripts driving the page.
window.blobCentres = () => {
  const c = $("tf2d-editor"), r = c.getBoundingClientRect(), g = tf2Geometry();
  return currentBlobs().map(([v, gr]) => [r.left + g.x(v) * r.width / c.width,
                                         r.top + g.y(gr) * r.height / c.height]);
};

function wireTf2d() {
  const c = $("tf2d-editor");
  c.addEventListener("pointerdown", (e) => {
    const [x, y] = tf2Point(e);
    const i = hitBlob(x, y);
    const kind = i < 0 ? "draw" : e.shiftKey ? "size" : "move";
    tf2.drag = { kind, i, at: [x, y], start: currentBlobs().map((b) => b.slice()) };
    c.setPointerCapture(e.pointerId);
  });
  c.addEventListener("pointermove", moveTf2);
  const end = () => {
    if (!tf2.drag) return;
    tf2.drag = null;
    if (tf2.timer !== null) { clearTimeout(tf2.timer); sendBlobs(); }
    tf2.blobs = null;
    drawTf2d();
  };
  c.addEventListener("pointerup", end);
  c.addEventListener("pointercancel", end);
  c.addEventListener("dblclick", (e) => {
    const i = hitBlob(...tf2Point(e));
    if (i >= 0) send({ op: "tf2d", blobs: currentBlobs().filter((_, j) => j !== i) });
  });
  $("tf2d-toggle").addEventListener("click", () =>
    send({ op: "tf2d", action: state && state.tf2d ? "stop" : "start" }));
  hooks.state.push(drawTf2d);
  hooks.info.push(() => { if (state) drawTf2d(); });
}

window.addEventListener("DOMContentLoaded", wireTf2d);
