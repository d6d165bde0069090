"""``python -m mi_amr bench --viewer``: how fast the browser explorer answers a slider.

The viewer runs as a user runs it (``python -m mi_amr view ... --no-browser``, its own process)
on ``sphere_wake`` (or ``bench --viewer --scene NAME``) at 512 x 512; Debian's chromium, driven
by Playwright, opens the page. The slider moves the scene's last isovalue (with several bands,
the highest, which has room above it). Each of 50 moves sets the slider one step further and
fires its ``input`` event, as a drag does, and the time is taken in the page from that event to
the moment the new image is decoded and shown (``performance.now()``): the whole round trip
(WebSocket, ``mi.traverse`` update, render, PNG, back, decode). The next move starts when the
image is shown. Kernels are counted in the viewer's process (``GET /api/status``) from the
first refined frame on.

Two previews are measured: 1 spp at the full 512 x 512 (``--preview-scale 1
--preview-budget 0``) and the default, 1 spp at 256 x 256 shown at 512 x 512
(``--preview-scale 2``), which goes down to 128 x 128 or 64 x 64 while a preview takes
longer than its budget (0.25 s); the table gives the preview's size at the end.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

from mi_amr.errors import AMRError
from mi_amr.evaluation.viewer_client import ViewerProcess  # noqa: F401 (its launcher)

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
RESOLUTION = (512, 512)
MOVES = 50

# One slider move, timed in the page: input event -> the next frame decoded and shown.
MOVE_JS = """async (value) => {
    const img = document.querySelector('[data-testid=image]');
    const slider = document.querySelector('[data-testid=isovalue]');
    const before = +img.dataset.version;
    const shown = new Promise((resolve) => {
        const watch = new MutationObserver(() => {
            if (+img.dataset.version > before) { watch.disconnect(); resolve(); } });
        watch.observe(img, {attributes: true, attributeFilter: ['data-version']}); });
    const t0 = performance.now();
    slider.value = value;
    slider.dispatchEvent(new Event('input', {bubbles: true}));
    await shown;
    return performance.now() - t0; }"""


def chromium(playwright, profile):
    """Debian's chromium (never a downloaded browser), headless, with a fresh profile."""
    if not os.path.exists(CHROMIUM):
        raise AMRError(f"bench --viewer needs Debian's chromium at {CHROMIUM} "
                       f"(apt-get install chromium; .ci/setup installs it)")
    return playwright.chromium.launch_persistent_context(
        str(profile), executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS,
        viewport={"width": 1100, "height": 1000})


def _wait_refined(page, newer_than: int) -> int:
    page.wait_for_function(
        """v => { const i = document.querySelector('[data-testid=image]');
                  return +i.dataset.version > v && i.dataset.quality === 'refined'; }""",
        arg=newer_than, timeout=600_000)
    return int(page.get_attribute("[data-testid=image]", "data-version"))


def round_trips(page, moves: int = MOVES) -> list:
    """Seconds of ``moves`` slider moves of the isovalue the slider moves, one slider step
    each, up then down."""
    step = float(page.get_attribute("[data-testid=isovalue]", "step"))
    value = float(page.input_value("[data-testid=isovalue]"))
    lo = float(page.get_attribute("[data-testid=isovalue]", "min"))
    out = []
    for i in range(moves):
        k = i + 1 if i < moves // 2 else moves - i - 1
        out.append(page.evaluate(MOVE_JS, lo + (round((value - lo) / step) + k) * step) / 1e3)
    return out


def measure(scene, *, preview_scale: int, spp: int = 4, moves: int = MOVES,
            screenshot=None, variant: str = "llvm_ad_rgb", adaptive: bool = True) -> dict:
    """The round trips of one viewer run, and the kernels compiled after its first frame
    (``adaptive``: the previews adapt their size to the budget, else ``--preview-budget 0``)."""
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp:
        viewer = ViewerProcess(scene, Path(tmp) / "out", "--resolution", *map(str, RESOLUTION),
                               "--preview-scale", str(preview_scale), "--spp", str(spp),
                               "--variant", variant,
                               *(() if adaptive else ("--preview-budget", "0")))
        try:
            with sync_playwright() as p:
                context = chromium(p, Path(tmp) / "profile")
                page = context.new_page()
                page.set_default_timeout(600_000)
                t0 = time.perf_counter()
                page.goto(viewer.url)
                _wait_refined(page, -1)
                first = time.perf_counter() - t0
                before = viewer.status()["compiled"]
                # The slider moves the last isovalue (the highest band has room above it).
                page.check("[data-testid=isolist] li:last-child input[type=radio]")
                typed = page.input_value("[data-testid=isovalue-text]")
                times = round_trips(page, moves)
                # Back to the scene's own isovalue (the slider moves in steps), then refined.
                shown = int(page.get_attribute("[data-testid=image]", "data-version"))
                page.fill("[data-testid=isovalue-text]", typed)
                page.press("[data-testid=isovalue-text]", "Enter")
                _wait_refined(page, shown)
                status = viewer.status()
                after, scale_now = status["compiled"], status["preview_scale"]
                if screenshot is not None:
                    page.screenshot(path=str(screenshot), full_page=True)
                context.close()
        finally:
            viewer.stop()
    return {"preview_scale": preview_scale, "adaptive": adaptive, "scale_at_end": scale_now,
            "moves": moves, "first_frame_s": first,
            "median_s": statistics.median(times), "p95_s": _percentile(times, 95),
            "min_s": min(times), "max_s": max(times),
            "compiled_after_first": sum(after.values()) - sum(before.values()),
            "compiled_by_controls": after["controls"] - before["controls"], "times_s": times}


def _percentile(values, q: float) -> float:
    import numpy as np

    return float(np.percentile(values, q))


def viewer_table(rows, scene_name: str) -> str:
    w, h = RESOLUTION
    lines = ["| scene | view | preview while moving | median (s) | p95 (s) | min (s) | max (s) "
             "| moves | kernels compiled after the first frame |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s = r["preview_scale"]
        preview = f"1 spp at {w // s}x{h // s}" + ("" if s == 1 else f", shown at {w}x{h}")
        end = r.get("scale_at_end", s)
        if r.get("adaptive"):
            preview += f", adaptive (at the end {w // end}x{h // end})"
        lines.append(f"| {scene_name} | {w}x{h} | {preview} | {r['median_s']:.3f} | "
                     f"{r['p95_s']:.3f} | {r['min_s']:.3f} | {r['max_s']:.3f} | {r['moves']} | "
                     f"{r['compiled_after_first']} |")
    return "\n".join(lines)


def run(out_dir, scene, *, moves: int = MOVES, variant: str = "llvm_ad_rgb",
        name: str = "viewer") -> list:
    """Both previews; writes ``NAME.md``, ``NAME.json`` and the page's screenshot
    ``NAME.png`` (taken after the default preview's run) to ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scale in (1, 2):
        print(f"viewer round trip, preview scale {scale}: {moves} slider moves ...", flush=True)
        rows.append(measure(scene, preview_scale=scale, moves=moves, variant=variant,
                            screenshot=out / f"{name}.png" if scale == 2 else None,
                            adaptive=scale != 1))
        print(f"  median {rows[-1]['median_s']:.3f} s, p95 {rows[-1]['p95_s']:.3f} s, "
              f"kernels compiled after the first frame: {rows[-1]['compiled_after_first']}",
              flush=True)
    table = viewer_table(rows, Path(scene).name)
    note = (f"\nSlider input event to the new image shown in the page (Debian's chromium "
            f"{_chromium_version()}, headless, same machine), {os.cpu_count()} CPU cores; "
            f"written by `python -m mi_amr bench --viewer`.\n")
    (out / f"{name}.md").write_text(table + "\n" + note)
    (out / f"{name}.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(table)
    print(f"wrote {out / f'{name}.md'}, {out / f'{name}.json'} and {out / f'{name}.png'}")
    return rows


def _chromium_version() -> str:
    try:
        text = subprocess.run([CHROMIUM, "--version"], capture_output=True, text=True,
                              timeout=30).stdout
    except (OSError, subprocess.TimeoutExpired):
        return ""
    m = re.search(r"(\d+\.\d+\.\d+\.\d+)", text)
    return m.group(1) if m else ""
