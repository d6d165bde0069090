// The page of `python -m mi_amr view`: every control sends one JSON request over the
// WebSocket; the server answers with the shared state (all tabs), messages, and frames
// (binary: uint32 header length, JSON header, PNG). Frames carry the version of the state they
// show; an older frame never replaces a newer one, and a preview never replaces the refined
// image of the same version.
"use strict";

const $ = (id) => document.getElementById(id);
const RANK = { preview: 0, refined: 1 };
let ws = null;
let state = null;
let info = null;
let active = 0;                  // the isovalue the slider moves
let shown = { version: -1, rank: -1 };
let sliderHeld = false;
// Functions of the page's other scripts (timeline.js, bands.js) called with each new state,
// info and shown frame.
const hooks = { state: [], info: [], frame: [] };

// ---------------------------------------------------------------- connection
function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  ws = new WebSocket(`${scheme}://${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => setConnection(true);
  ws.onclose = () => { setConnection(false); setTimeout(connect, 1500); };
  ws.onmessage = (ev) => {
    if (typeof ev.data === "string") onText(JSON.parse(ev.data));
    else onFrame(ev.data);
  };
}

function setConnection(ok) {
  const c = $("connection");
  c.textContent = ok ? "connected" : "disconnected (retrying)";
  c.className = ok ? "good" : "bad";
}

function send(msg) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(msg));
}

function set(name, value, extra) { send(Object.assign({ op: "set", name, value }, extra)); }

// Every message shown, oldest first (for scripts driving the page; the page shows the last).
window.messages = [];

function showMessage(text, kind) {
  const m = $("message");
  m.textContent = text;
  m.className = kind;
  window.messages.push({ kind, text });
}

function onText(m) {
  if (m.type === "state") applyState(m.state);
  else if (m.type === "info") applyInfo(m);
  else if (m.type === "error") showMessage(m.message, "error");
  else if (m.type === "notice") showMessage(m.message, "notice");
  else if (m.type === "saved") {
    showMessage(m.message, "notice");
    if (m.next_frame !== undefined) $("keyframe-frame").value = m.next_frame;
  } else if (m.type === "confirm") {
    if (window.confirm(m.message)) send(m.request);
    else showMessage("Not saved: the existing file was kept.", "notice");
  }
}

// ---------------------------------------------------------------- frames
function onFrame(buf) {
  const n = new DataView(buf).getUint32(0, true);
  const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  const rank = RANK[head.quality];
  if (head.version < shown.version || (head.version === shown.version && rank <= shown.rank)) {
    return;
  }
  shown = { version: head.version, rank };
  const url = URL.createObjectURL(new Blob([new Uint8Array(buf, 4 + n)], { type: "image/png" }));
  const img = $("image");
  const previous = img.src;
  img.src = url;
  img.decode().then(() => {
    if (img.src !== url) return;
    img.dataset.version = head.version;
    img.dataset.quality = head.quality;
    img.dataset.spp = head.spp;
    img.dataset.compiled = JSON.stringify(head.compiled);
    hooks.frame.forEach((f) => f(head));
    if (previous.startsWith("blob:")) URL.revokeObjectURL(previous);
    $("frame-info").textContent =
      `${head.quality} ${head.width}x${head.height}, ${head.spp} spp, ${head.seconds} s; ` +
      `kernels compiled by controls: ${head.compiled.controls}`;
  }).catch(() => {});
}

// ---------------------------------------------------------------- info and state
function fillSelect(sel, values, labels) {
  const key = values.join("|");
  if (sel.dataset.key === key) return;
  sel.dataset.key = key;
  sel.replaceChildren(...values.map((v, i) => new Option(labels ? labels[i] : v, v)));
}

function fillList(list, values) {
  list.replaceChildren(...values.map((v) => { const o = document.createElement("option");
    o.value = v; return o; }));
}

function applyInfo(m) {
  info = m;
  $("scene-name").textContent = m.scene;
  fillSelect($("method"), m.methods);
  fillSelect($("reconstruction"), m.reconstructions);
  fillSelect($("layers"), m.layer_modes);
  fillSelect($("mode"), m.modes);
  fillSelect($("color-field"), ["none", ...m.fields], ["(none: iso colours)", ...m.fields]);
  fillList($("field-list"), m.fields);
  fillList($("colormap-list"), m.colormaps);
  fillList($("file-list"), m.files);
  $("out-dir").textContent = `to ${m.out_dir}`;
  const [w, h] = m.resolution;
  const img = $("image");
  img.style.width = `${w}px`;
  img.style.height = `${h}px`;
  if (!$("image-width").value) { $("image-width").value = w; $("image-height").value = h; }
  const [lo, hi] = m.value_range;
  const scale = $("isovalue-scale");
  if (!scale.dataset.chosen) scale.value = m.slider_scale;
  configureSlider();
  if (state && !sliderHeld) $("isovalue").value = toSlider(state.isovalues[active]);
  $("range-lo").textContent = fmt(lo, 4);
  $("range-hi").textContent = fmt(hi, 4);
  const smaller = m.preview_budget_s > 0 ?
    ` (smaller while a preview takes over ${m.preview_budget_s} s)` : "";
  $("quality-note").textContent = `While a control moves: 1 spp at 1/${m.preview_scale} of ` +
    `the size${smaller}; when idle: refined to the samples per pixel above.`;
  drawHistogram();
  hooks.info.forEach((f) => f(m));
}

// A number in `digits` significant digits, without trailing zeros ("0.31", "1000", "1e-05").
function fmt(x, digits = 6) {
  const s = Number(x).toPrecision(digits);
  if (s.includes("e")) return s.replace(/\.?0+e/, "e");
  return s.includes(".") ? s.replace(/\.?0+$/, "") : s;
}

function setValue(id, value) {
  const el = $(id);
  if (el.dataset.dirty === "1" || (el === document.activeElement && el.type === "text")) return;
  el.value = value;
}

function applyState(s) {
  state = s;
  active = Math.min(active, s.isovalues.length - 1);
  if (!sliderHeld && info) $("isovalue").value = toSlider(s.isovalues[active]);
  setValue("isovalue-text", fmt(s.isovalues[active]));
  buildIsoList(s);
  for (const [id, v] of [["method", s.method], ["reconstruction", s.reconstruction],
    ["layers", s.layers], ["mode", s.mode], ["color-field", s.color_field || "none"]]) $(id).value = v;
  setValue("step-scale", s.step_scale);
  setValue("band-width", s.band_width);
  $("band-row").style.display = s.mode === "volume" ? "" : "none";
  $("layers-row").style.display = s.mode === "volume" ? "none" : "";
  setValue("field", s.field);
  setValue("colormap", s.colormap || "");
  $("colormap").disabled = $("color-lo").disabled = $("color-hi").disabled = !s.colormap;
  setValue("color-lo", s.color_range ? fmt(s.color_range[0]) : "");
  setValue("color-hi", s.color_range ? fmt(s.color_range[1]) : "");
  const light = s.light;
  for (const id of ["light-azimuth", "light-elevation", "light-strength"]) {
    $(id).disabled = !light;
  }
  if (light) {
    setValue("light-azimuth", Math.round(light.azimuth));
    setValue("light-elevation", Math.round(light.elevation));
    setValue("light-strength", fmt(light.strength));
  }
  $("shadows").checked = s.shadows;
  setValue("spp", s.spp);
  $("open-path").placeholder = s.data_file;
  $("data-name").textContent = s.data_file;
  drawHistogram();
  hooks.state.forEach((f) => f(s));
}

function buildIsoList(s) {
  const list = $("isolist");
  if (list.children.length !== s.isovalues.length) {
    list.replaceChildren(...s.isovalues.map((_, i) => isoRow(i)));
  }
  s.isovalues.forEach((v, i) => {
    const row = list.children[i];
    row.querySelector("input[type=radio]").checked = i === active;
    const text = row.querySelector("input[type=text]");
    if (text !== document.activeElement) text.value = fmt(v);
    row.querySelector("input[type=color]").value = s.iso_colors[i];
    const op = row.querySelector("input[type=number]");
    if (op !== document.activeElement) op.value = s.iso_opacity[i];
    row.querySelector("button").disabled = s.isovalues.length === 1;
  });
}

function isoRow(i) {
  const li = document.createElement("li");
  li.innerHTML = `<input type="radio" name="active-iso" title="the slider moves this one">` +
    `<input type="text" data-testid="iso-value-${i}" inputmode="decimal">` +
    `<input type="color" data-testid="iso-color-${i}" title="colour (without a colour map)">` +
    `<input type="number" data-testid="iso-opacity-${i}" min="0.01" max="1" step="0.05" ` +
    `title="opacity">` +
    `<button type="button" data-testid="iso-remove-${i}" title="remove">&times;</button>`;
  const [radio, text, color, opacity, remove] = li.children;
  radio.addEventListener("change", () => { active = i; applyState(state); });
  text.addEventListener("change", () => set("isovalue", text.value, { index: i }));
  color.addEventListener("input", () => set("iso_color", color.value, { index: i }));
  opacity.addEventListener("change", () => set("iso_opacity", opacity.value, { index: i }));
  remove.addEventListener("click", () => send({ op: "remove_isovalue", index: i }));
  return li;
}

function drawHistogram() {
  const canvas = $("histogram");
  if (!info || !canvas.getContext) return;
  const ctx = canvas.getContext("2d");
  const counts = info.histogram;
  const top = Math.log1p(Math.max(1, ...counts));
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.fillStyle = "#4a5a70";
  const base = canvas.height - 14;      // the slider's track sits below the bars
  const [lo, hi] = info.value_range;
  // Each bin where the slider's scale puts its edges.
  const edge = (i) => sliderFraction(lo + (hi - lo) * i / counts.length) * canvas.width;
  counts.forEach((c, i) => {
    const h = base * Math.log1p(c) / top;
    const x0 = edge(i);
    ctx.fillRect(x0, base - h, Math.max(1, edge(i + 1) - x0 - 0.5), h);
  });
  if (!state) return;
  ctx.fillStyle = "#ffd866";
  for (const v of state.isovalues) {
    ctx.fillRect(sliderFraction(v) * canvas.width - 0.5, 0, 1.5, base);
  }
}

// ---------------------------------------------------------------- controls
// A typed value is sent on Enter (or when the field is left); a field that is left shows
// the shared state again, so a refused value does not linger in it.
function onEnter(id, fn) {
  const el = $(id);
  el.addEventListener("input", () => { el.dataset.dirty = "1"; });
  el.addEventListener("change", () => { el.dataset.dirty = ""; fn(el.value); });
  el.addEventListener("blur", () => { if (state && !el.dataset.dirty) applyState(state); });
}

function wireControls() {
  const slider = $("isovalue");
  slider.addEventListener("pointerdown", () => { sliderHeld = true; });
  window.addEventListener("pointerup", () => { sliderHeld = false; });
  slider.addEventListener("input", () => {
    const v = toValue(slider.value);
    $("isovalue-text").value = fmt(v);
    set("isovalue", v, { index: active });
  });
  $("isovalue-scale").addEventListener("change", () => {
    $("isovalue-scale").dataset.chosen = "1";
    configureSlider();
    if (state) slider.value = toSlider(state.isovalues[active]);
    drawHistogram();
  });
  onEnter("isovalue-text", (v) => set("isovalue", v, { index: active }));
  $("add-isovalue").addEventListener("click", () => send({ op: "add_isovalue" }));
  for (const id of ["method", "reconstruction", "layers", "mode"]) {
    $(id).addEventListener("change", () => set(id, $(id).value));
  }
  onEnter("step-scale", (v) => set("step_scale", v));
  onEnter("band-width", (v) => set("band_width", v));
  onEnter("field", (v) => set("field", v));
  $("color-field").addEventListener("change", () => set("color_field", $("color-field").value));
  onEnter("colormap", (v) => set("colormap", v));
  const range = () => set("color_range", [$("color-lo").value, $("color-hi").value]);
  onEnter("color-lo", range);
  onEnter("color-hi", range);
  $("reset-color-range").addEventListener("click", () => send({ op: "reset_color_range" }));
  $("reset-camera").addEventListener("click", () => send({ op: "camera", action: "reset" }));
  $("light-azimuth").addEventListener("input", (e) => set("light_azimuth", e.target.value));
  $("light-elevation").addEventListener("input", (e) => set("light_elevation", e.target.value));
  onEnter("light-strength", (v) => set("light_strength", v));
  $("shadows").addEventListener("change", (e) => set("shadows", e.target.checked));
  onEnter("spp", (v) => set("spp", v));
  $("open").addEventListener("click", () => send({ op: "open", path: $("open-path").value }));
  wireSaving();
}

function wireSaving() {
  $("image-format").addEventListener("change", () => {
    const name = $("image-name");
    name.value = name.value.replace(/(\.[^.]*)?$/, `.${$("image-format").value}`);
  });
  const size = () => ({ width: $("image-width").value, height: $("image-height").value });
  $("save-image").addEventListener("click", () =>
    send(Object.assign({ op: "save_image", name: $("image-name").value }, size())));
  $("save-scene").addEventListener("click", () =>
    send(Object.assign({ op: "save_scene", name: $("scene-file").value }, size())));
  $("add-keyframe").addEventListener("click", () =>
    send({ op: "add_keyframe", name: $("keyframe-file").value,
           frame: $("keyframe-frame").value }));
}

// Drag to orbit, shift-drag to pan, wheel to zoom: moves are summed and sent every 16 ms.
function wireCamera() {
  const img = $("image");
  const acc = { dx: 0, dy: 0, zoom: 0, pan: false };
  let drag = null;
  let timer = null;
  const flush = () => {
    timer = null;
    if (acc.dx || acc.dy) {
      send({ op: "camera", action: acc.pan ? "pan" : "orbit", dx: acc.dx, dy: acc.dy });
    }
    if (acc.zoom) send({ op: "camera", action: "zoom", amount: acc.zoom });
    acc.dx = acc.dy = acc.zoom = 0;
  };
  const later = () => { if (timer === null) timer = setTimeout(flush, 16); };
  img.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY };
    img.setPointerCapture(e.pointerId);
    img.classList.add("dragging");
  });
  img.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const width = img.clientWidth || 1;
    if (acc.pan !== e.shiftKey && (acc.dx || acc.dy)) flush();
    acc.pan = e.shiftKey;
    acc.dx += (e.clientX - drag.x) / width;
    acc.dy += (e.clientY - drag.y) / width;
    drag = { x: e.clientX, y: e.clientY };
    later();
  });
  const end = () => { drag = null; img.classList.remove("dragging"); flush(); };
  img.addEventListener("pointerup", end);
  img.addEventListener("pointercancel", end);
  img.addEventListener("wheel", (e) => {
    e.preventDefault();
    acc.zoom += Math.max(-2, Math.min(2, e.deltaY * 0.001));
    later();
  }, { passive: false });
}

window.addEventListener("DOMContentLoaded", () => {
  wireControls();
  wireCamera();
  connect();
});
