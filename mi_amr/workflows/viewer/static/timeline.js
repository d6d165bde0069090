// The time slider of a series (`view SCENE --files 'run/plt*'`): each step is one request,
// {op: "step", index: K}; the server keeps the camera, isovalues and colours. Play steps to
// the next file once the current step's image is shown (and at most every PLAY_MS), looping.
"use strict";

const PLAY_MS = 250;
const timeline = { playing: false, timer: null, held: false, wanted: -1 };

function seriesFiles() { return (info && info.series) || []; }

function currentStep() { return state ? seriesFiles().indexOf(state.data_file) : -1; }

function showTimeline() {
  const files = seriesFiles();
  $("timeline").hidden = files.length < 2;
  const k = currentStep();
  const slider = $("time-step");
  slider.max = Math.max(0, files.length - 1);
  if (k >= 0 && !timeline.held) slider.value = k;
  $("time-label").textContent = k >= 0 ? `step ${k + 1} of ${files.length}` : "";
}

function stepTo(k) {
  timeline.wanted = k;
  send({ op: "step", index: k });
}

function setPlaying(on) {
  timeline.playing = on;
  $("play").textContent = on ? "Pause" : "Play";
  if (!on && timeline.timer !== null) { clearTimeout(timeline.timer); timeline.timer = null; }
  if (on) nextWhenShown({ version: shown.version });
}

// A frame is shown: while playing, the next step follows once this step is on screen.
function nextWhenShown(head) {
  if (!timeline.playing || timeline.timer !== null || !state) return;
  if (head.version < state.version) return;
  timeline.timer = setTimeout(() => {
    timeline.timer = null;
    if (!timeline.playing) return;
    const n = seriesFiles().length;
    if (n > 1) stepTo((Math.max(currentStep(), 0) + 1) % n);
  }, PLAY_MS);
}

function wireTimeline() {
  const slider = $("time-step");
  slider.addEventListener("pointerdown", () => { timeline.held = true; });
  window.addEventListener("pointerup", () => { timeline.held = false; });
  slider.addEventListener("input", () => stepTo(Number(slider.value)));
  $("play").addEventListener("click", () => setPlaying(!timeline.playing));
  hooks.info.push(showTimeline);
  hooks.state.push(showTimeline);
  hooks.frame.push(nextWhenShown);
}

window.addEventListener("DOMContentLoaded", wireTimeline);
