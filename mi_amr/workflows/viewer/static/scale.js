// The isovalue slider's scale. "linear": the slider's value is the isovalue. "percentile": the
// slider's position (0 to STEPS) is the share of leaf cells below the isovalue (the server's
// quantiles, every half percent), so a field whose useful values sit at the far edge of its
// range (Q) still gets the whole slider. "symlog": sign(v) log10(1 + |v| / c), c a millionth
// of the largest |value|: linear near 0, logarithmic across decades. The server picks
// percentile for a field whose middle 90 % of cells span under a tenth of its range.
"use strict";

const STEPS = 1000;

function sliderScale() { return $("isovalue-scale").value || "linear"; }

function symlog(v, c) { return Math.sign(v) * Math.log10(1 + Math.abs(v) / c); }

function symlogInverse(s, c) { return Math.sign(s) * c * (Math.pow(10, Math.abs(s)) - 1); }

function symlogC() {
  const [lo, hi] = info.value_range;
  return Math.max(Math.abs(lo), Math.abs(hi), 1e-30) * 1e-6;
}

// Slider position (its value) -> isovalue.
function toValue(pos) {
  const [lo, hi] = info.value_range;
  const x = Number(pos);
  const scale = sliderScale();
  if (scale === "percentile") {
    const q = info.quantiles, t = x / STEPS * (q.length - 1);
    const j = Math.min(Math.floor(t), q.length - 2);
    return q[j] + (q[j + 1] - q[j]) * (t - j);
  }
  if (scale === "symlog") {
    const c = symlogC(), a = symlog(lo, c), b = symlog(hi, c);
    return Math.min(hi, Math.max(lo, symlogInverse(a + (b - a) * x / STEPS, c)));
  }
  return x;
}

// Isovalue -> slider position.
function toSlider(v) {
  const [lo, hi] = info.value_range;
  const scale = sliderScale();
  if (scale === "percentile") {
    const q = info.quantiles;
    if (v <= q[0]) return 0;
    if (v >= q[q.length - 1]) return STEPS;
    let j = 1;
    while (q[j] < v) j++;
    const f = q[j] > q[j - 1] ? (v - q[j - 1]) / (q[j] - q[j - 1]) : 0.5;
    return (j - 1 + f) / (q.length - 1) * STEPS;
  }
  if (scale === "symlog") {
    const c = symlogC(), a = symlog(lo, c), b = symlog(hi, c);
    return (symlog(v, c) - a) / (b - a || 1) * STEPS;
  }
  return v;
}

// Where along the slider (0 to 1) the isovalue v sits.
function sliderFraction(v) {
  const [lo, hi] = info.value_range;
  const pos = toSlider(v);
  return sliderScale() === "linear" ? (pos - lo) / (hi - lo || 1) : pos / STEPS;
}

function configureSlider() {
  const slider = $("isovalue");
  const [lo, hi] = info.value_range;
  if (sliderScale() === "linear") {
    slider.min = lo;
    slider.max = hi;
    slider.step = (hi - lo) / STEPS || "any";
  } else {
    slider.min = 0;
    slider.max = STEPS;
    slider.step = "any";
  }
}
