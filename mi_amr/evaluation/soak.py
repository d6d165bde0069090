"""``python -m mi_amr bench --soak``: long runs that look for slow leaks and lost work, each a
part of its own that reports what it measured.

* ``viewer`` -- 2,000 random valid changes to a running viewer (``python -m mi_amr view``, its
  own process) of the analytic sphere at 128 x 128: isovalue, camera, colours, opacity, step,
  shadows, light, samples per pixel, now and then the method (a new kernel structure) and an
  image saved at a random size. Reports the viewer's memory growth after the first 100 changes
  (when the kernels of every structure and size it uses have compiled), the kernels compiled by
  cause, errors, frames, and files left behind (temporary files, the viewer's work folder).
* ``movie`` -- 200 frames rendered by 2 workers, one worker process killed every 20 frames:
  frames lost and files left behind.
* ``cache`` -- 50 loads of 25 data files into a snapshot cache limited to 0.2 GB
  (``MI_AMR_CACHE``, ``MI_AMR_CACHE_GB``): the cache's size after every load, and whether a
  folder of the user's inside it survived.

Each part is a function ``part(work_folder, progress) -> dict`` in :data:`PARTS`; ``soak.md``
in the results folder is the table of all of them.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mi_amr.errors import AMRError

VIEWER_CHANGES = 2000
VIEWER_WARMUP = 100             # changes before the memory baseline
VIEWER_RESOLUTION = (128, 128)
SAVE_EVERY = 100                # changes between saved images (of random sizes)
STRUCTURE_EVERY = 250           # changes between method switches (a new kernel structure)
SETTLE_EVERY = 20               # changes between waits for the refined frame
WAIT_S = 300.0
MEMORY_TARGET = 50e6            # bytes the viewer may grow over the changes


# ---------------------------------------------------------------------- the viewer

def random_change(rng: random.Random, info: dict, state: dict) -> dict:
    """One valid request a person could make with the page's controls."""
    lo, hi = info["value_range"]
    kinds = ["isovalue", "orbit", "orbit", "zoom", "pan", "color", "opacity", "step",
             "shadows"]
    if state.get("light"):
        kinds += ["light_azimuth", "light_elevation", "light_strength"]
    kind = rng.choice(kinds)
    if kind == "isovalue":
        return {"op": "set", "name": "isovalue", "value": lo + (hi - lo) * rng.uniform(0.2, 0.8)}
    if kind == "orbit":
        return {"op": "camera", "action": "orbit", "dx": rng.uniform(-0.2, 0.2),
                "dy": rng.uniform(-0.1, 0.1)}
    if kind == "zoom":          # towards the start distance: the camera does not wander off
        return {"op": "camera", "action": "reset"} if rng.random() < 0.3 else \
            {"op": "camera", "action": "zoom", "amount": rng.uniform(-0.2, 0.2)}
    if kind == "pan":
        return {"op": "camera", "action": "pan", "dx": rng.uniform(-0.05, 0.05),
                "dy": rng.uniform(-0.05, 0.05)}
    if kind == "color":
        return {"op": "set", "name": "iso_color", "value": f"#{rng.randrange(1 << 24):06x}"}
    if kind == "opacity":
        return {"op": "set", "name": "iso_opacity", "value": rng.choice((1.0, 0.5, 0.8))}
    if kind == "step":
        return {"op": "set", "name": "step_scale", "value": rng.uniform(0.25, 1.0)}
    if kind == "shadows":
        return {"op": "set", "name": "shadows", "value": not state["shadows"]}
    if kind == "light_strength":
        return {"op": "set", "name": kind, "value": rng.uniform(0.5, 4.0)}
    return {"op": "set", "name": kind, "value": rng.uniform(10.0, 80.0)}


def _view_folders() -> set:
    return set(Path(tempfile.gettempdir()).glob("mi_amr-view-*"))


def viewer_soak(work: Path, progress: bool = True, changes: int = VIEWER_CHANGES) -> dict:
    """The ``viewer`` part (see the module docstring)."""
    from mi_amr.evaluation.viewer_bench import ViewerProcess
    from mi_amr.evaluation.viewer_client import ViewerClient, rss_bytes
    from mi_amr.workflows import project

    project.ensure_scene_data(verbose=False)
    out = work / "viewer-out"
    folders = _view_folders()
    viewer = ViewerProcess(project.scenes_dir() / "analytic_sphere.xml", out, "--resolution",
                           *map(str, VIEWER_RESOLUTION), "--spp", "2")
    saved, errors = set(), []
    try:
        client = ViewerClient(viewer.url)
        info = client.until(lambda m: m["type"] == "info", WAIT_S)
        state = client.until(lambda m: m["type"] == "state", WAIT_S)
        rng = random.Random(0)
        t0, rss = time.perf_counter(), {"start": rss_bytes(viewer.proc.pid)}
        for i in range(1, changes + 1):
            state = _one_change(client, _request(rng, i, info, state, saved), state, errors)
            if i % SETTLE_EVERY == 0:
                _settle(client, state["version"])
            if i == VIEWER_WARMUP:
                rss["baseline"], compiled_warm = rss_bytes(viewer.proc.pid), viewer.status()
            if progress and i % 100 == 0:
                print(f"  viewer: {i}/{changes} changes, {rss_bytes(viewer.proc.pid) / 1e6:.0f} "
                      f"MB, {time.perf_counter() - t0:.0f} s", flush=True)
        _settle(client, state["version"])
        client.until(lambda m: False, 2.0)      # the last saves' replies
        rss["end"], status = rss_bytes(viewer.proc.pid), viewer.status()
        client.close()
    finally:
        viewer.stop()
    left = [str(p) for p in out.iterdir() if p.name not in saved]
    left += [str(p) for p in _view_folders() - folders]
    return {"changes": changes, "memory_start_mb": rss["start"] / 1e6,
            "memory_baseline_mb": rss["baseline"] / 1e6, "memory_end_mb": rss["end"] / 1e6,
            "memory_growth_mb": (rss["end"] - rss["baseline"]) / 1e6,
            "compiled_after_warmup": _compiled_since(compiled_warm["compiled"],
                                                     status["compiled"]),
            "compiled_total": status["compiled"], "frames": status["frames"],
            "images_saved": len(saved), "errors": errors[:20], "error_count": len(errors),
            "files_left_behind": left, "seconds": time.perf_counter() - t0}


def _request(rng, i, info, state, saved) -> dict:
    if i % SAVE_EVERY == 0:
        name = f"soak_{i}.png"
        saved.add(name)
        return {"op": "save_image", "name": name, "width": rng.randint(16, 300),
                "height": rng.randint(16, 300)}
    if i % STRUCTURE_EVERY == 0:
        return {"op": "set", "name": "method",
                "value": "adaptive" if state["state"]["method"] == "exact" else "exact"}
    return random_change(rng, info, state["state"])


def _one_change(client, request, state, errors) -> dict:
    """Send ``request`` and wait for its answer: the new state, a saved image, or an error
    (kept in ``errors``); returns the newest state. A change to what the view already shows
    has no answer: a probe request after it (answered at once, "unknown request") ends the
    wait."""
    client.send(request)
    if request["op"] == "save_image":
        wanted = lambda m: m["type"] in ("saved", "error")     # noqa: E731
    else:
        client.send({"op": "soak-probe"})
        wanted = lambda m: m["type"] in ("state", "error")     # noqa: E731
    reply = client.until(wanted, WAIT_S)
    if reply is None:
        raise AMRError(f"bench --soak: the viewer did not answer {request} in {WAIT_S:g} s")
    if reply["type"] == "state":
        client.until(lambda m: m["type"] == "error" and "soak-probe" in m["message"], WAIT_S)
        return reply
    if "soak-probe" not in reply["message"]:
        errors.append(reply["message"])
        if request["op"] != "save_image":
            client.until(lambda m: m["type"] == "error" and "soak-probe" in m["message"],
                         WAIT_S)
    return state


def _settle(client, version: int) -> None:
    client.until(lambda m: m["type"] == "frame" and m["version"] >= version and
                 m["quality"] == "refined", WAIT_S)


def _compiled_since(before: dict, after: dict) -> dict:
    return {k: after[k] - before.get(k, 0) for k in after}


# ---------------------------------------------------------------------- the report

PARTS = {"viewer": viewer_soak}


def run_soak(out_dir, parts=None, progress: bool = True) -> dict:
    """Run the ``parts`` (default all of :data:`PARTS`) in a temporary work folder; write
    ``soak.json`` and ``soak.md`` to ``out_dir`` and return the results by part."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    with tempfile.TemporaryDirectory(prefix="mi_amr-soak-") as folder:
        for name in parts or PARTS:
            if progress:
                print(f"soak: {name} ...", flush=True)
            results[name] = PARTS[name](Path(folder), progress)
    (out / "soak.json").write_text(json.dumps(results, indent=2) + "\n")
    text = soak_table(results)
    (out / "soak.md").write_text(text + "\n")
    print(text)
    print(f"wrote {out / 'soak.md'}")
    return results


def soak_table(results: dict) -> str:
    lines = ["| part | measured | result |", "|---|---|---|"]
    v = results.get("viewer")
    if v:
        compiled = sum(v["compiled_after_warmup"].values())
        ok = v["memory_growth_mb"] * 1e6 < MEMORY_TARGET
        lines += [
            f"| viewer | memory growth over changes {VIEWER_WARMUP}-{v['changes']} | "
            f"{v['memory_growth_mb']:+.1f} MB ({v['memory_baseline_mb']:.0f} -> "
            f"{v['memory_end_mb']:.0f} MB; target < {MEMORY_TARGET / 1e6:.0f} MB: "
            f"{'met' if ok else 'NOT met'}) |",
            f"| viewer | kernels compiled after change {VIEWER_WARMUP} | {compiled} "
            f"({_causes(v['compiled_after_warmup'])}); in all {_causes(v['compiled_total'])} |",
            f"| viewer | images saved at random sizes | {v['images_saved']} |",
            f"| viewer | errors | {v['error_count']} |",
            f"| viewer | files left behind | {len(v['files_left_behind'])} |"]
    for name in ("movie", "cache"):
        for key, value in (results.get(name) or {}).items():
            lines.append(f"| {name} | {key.replace('_', ' ')} | {value} |")
    return "\n".join(lines)


def _causes(compiled: dict) -> str:
    return ", ".join(f"{k} {n}" for k, n in compiled.items() if n) or "none"


def main_env() -> dict:
    """The environment of the processes a part starts: this checkout first on the path."""
    root = str(Path(__file__).resolve().parents[2])
    return dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))


if __name__ == "__main__":
    run_soak(sys.argv[1] if len(sys.argv) > 1 else "out/bench")
