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


def viewer_soak(work: Path, progress: bool = True, changes: int = VIEWER_CHANGES) -> dict:
    """The ``viewer`` part (see the module docstring)."""
    from mi_amr.evaluation.viewer_client import ViewerProcess
    from mi_amr.evaluation.viewer_client import ViewerClient, rss_bytes
    from mi_amr.workflows import project

    project.ensure_scene_data(verbose=False)
    out, tmp = work / "viewer-out", work / "viewer-tmp"
    tmp.mkdir()
    # Its own temporary folder: what the viewer leaves there is its own.
    viewer = ViewerProcess(project.scenes_dir() / "analytic_sphere.xml", out, "--resolution",
                           *map(str, VIEWER_RESOLUTION), "--spp", "2",
                           env=dict(main_env(), TMPDIR=str(tmp), PYTHONFAULTHANDLER="1"))
    saved, errors = set(), []
    try:
        client = ViewerClient(viewer.url)
        info = client.until(lambda m: m["type"] == "info", WAIT_S)
        state = client.until(lambda m: m["type"] == "state", WAIT_S)
        rng = random.Random(0)
        t0, rss = time.perf_counter(), {"start": rss_bytes(viewer.proc.pid)}
        for i in range(1, changes + 1):
            state = _one_change(client, _request(rng, i, info, state, saved), state, errors)
            if i % SETTLE_EVERY == 0 or i == changes:
                _settle(client, state["version"])
            if i == VIEWER_WARMUP:
                rss["baseline"], compiled_warm = rss_bytes(viewer.proc.pid), viewer.status()
            if progress and i % 100 == 0:
                print(f"  viewer: {i}/{changes} changes, {rss_bytes(viewer.proc.pid) / 1e6:.0f} "
                      f"MB, {time.perf_counter() - t0:.0f} s", flush=True)
        client.until(lambda m: False, 2.0)      # the last saves' replies
        rss["end"], status = rss_bytes(viewer.proc.pid), viewer.status()
        client.close()
    finally:
        viewer.stop()
    left = [str(p) for p in out.iterdir() if p.name not in saved]
    left += [str(p) for p in tmp.iterdir()]
    return {"changes": changes, "memory_start_mb": rss["start"] / 1e6,
            "memory_baseline_mb": rss["baseline"] / 1e6, "memory_end_mb": rss["end"] / 1e6,
            "memory_growth_mb": (rss["end"] - rss["baseline"]) / 1e6,
            "compiled_after_warmup": _compiled_since(compiled_warm["compiled"],
                                                     status["compiled"]),
            "compiled_total": status["compiled"], "frames": status["frames"],
            "images_saved": len(saved), "errors": errors[:20], "error_count": len(errors),
            "files_left_behind": left, "seconds": time.perf_counter() - t0}


def _request(rng, i, info, state, saved) -> dict:
    # The warm-up visits the other method and saves once: what compiles, compiles in it.
    if i in (VIEWER_WARMUP // 2, 3 * VIEWER_WARMUP // 4) or i % STRUCTURE_EVERY == 0:
        return {"op": "set", "name": "method",
                "value": "adaptive" if state["state"]["method"] == "exact" else "exact"}
    if i % SAVE_EVERY == 0 or i == VIEWER_WARMUP - 10:
        name = f"soak_{i}.png"
        saved.add(name)
        return {"op": "save_image", "name": name, "width": rng.randint(16, 300),
                "height": rng.randint(16, 300)}
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
    if reply["type"] == "error" and "soak-probe" not in reply["message"]:
        errors.append(reply["message"])
        if request["op"] != "save_image":
            client.until(lambda m: m["type"] == "error" and "soak-probe" in m["message"],
                         WAIT_S)
    return state


def _settle(client, version: int) -> None:
    """Wait for the refined frame of ``version`` or newer (it may have come already, while
    waiting for another answer)."""
    def refined(m):
        return m["type"] == "frame" and m["version"] >= version and m["quality"] == "refined"

    if not any(refined(f) for f in client.frames):
        client.until(refined, WAIT_S)
    client.frames.clear()
    client.texts.clear()


def _compiled_since(before: dict, after: dict) -> dict:
    return {k: after[k] - before.get(k, 0) for k in after}


# ---------------------------------------------------------------------- the movie

MOVIE_FRAMES = 200
MOVIE_KILL_EVERY = 20           # frames between killed worker processes
MOVIE_WORKERS = 2


def movie_soak(work: Path, progress: bool = True, frames: int = MOVIE_FRAMES) -> dict:
    """The ``movie`` part: ``python -m mi_amr movie`` of an orbit on 2 Dask workers, a worker
    process killed (SIGKILL) each time 20 more frames are written."""
    import threading

    from mi_amr.workflows import project

    project.ensure_scene_data(verbose=False)
    out = work / "movie-out"
    cmd = [sys.executable, "-m", "mi_amr", "movie", str(project.scenes_dir() /
                                                          "analytic_sphere.xml"),
           "-o", str(out), "--frames", str(frames), "--orbit", "360", "--workers",
           str(MOVIE_WORKERS), "--resolution", "32", "32", "--spp", "1"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=main_env())
    killed = []
    watcher = threading.Thread(target=_kill_workers, args=(proc, out, frames, killed),
                               daemon=True)
    watcher.start()
    log = proc.communicate(timeout=3600)[0]
    watcher.join(timeout=5)
    names = {f"frame_{i:05d}.png" for i in range(frames)}
    present = {p.name for p in out.iterdir()} if out.is_dir() else set()
    result = {"frames": frames, "workers_killed": len(killed), "exit_status": proc.returncode,
              "frames_lost": len(names - present),
              "files_left_behind": sorted(present - names), "seconds": round(
                  time.perf_counter() - t0, 1)}
    if proc.returncode != 0 and progress:
        print(log[-2000:])
    return result


def _kill_workers(proc, out: Path, frames: int, killed: list) -> None:
    """Kill one of ``proc``'s Dask worker processes (SIGKILL) each time
    :data:`MOVIE_KILL_EVERY` more frames are in ``out``, until the movie ends."""
    import signal

    while proc.poll() is None:
        done = len(list(out.glob("frame_*.png"))) if out.is_dir() else 0
        if done >= (len(killed) + 1) * MOVIE_KILL_EVERY and done < frames:
            victims = _worker_processes(proc.pid)
            if victims:
                try:
                    os.kill(victims[len(killed) % len(victims)], signal.SIGKILL)
                    killed.append(done)
                except ProcessLookupError:
                    pass
        time.sleep(0.05)


def _worker_processes(root: int) -> list:
    """Process ids below ``root`` that have no children of their own and are not
    multiprocessing's resource tracker: the Dask workers (their nannies have children)."""
    children = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except (OSError, IndexError):
            continue
        if b"resource_tracker" not in cmdline:
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    below, todo = [], list(children.get(root, []))
    while todo:
        pid = todo.pop()
        below.append(pid)
        todo += children.get(pid, [])
    return sorted(p for p in below if p not in children)


# ---------------------------------------------------------------------- the cache

CACHE_LOADS = 50
CACHE_FILES = 25
CACHE_GB = 0.2


def cache_soak(work: Path, progress: bool = True, loads: int = CACHE_LOADS) -> dict:
    """The ``cache`` part: ``python -m mi_amr render`` of 25 data files, each twice, with
    ``MI_AMR_CACHE`` a folder that also holds a folder of the user's and ``MI_AMR_CACHE_GB``
    0.2; the cache's size (its entries, without the user's folder) after every load."""
    from mi_amr.synthetic import datasets
    from mi_amr.workflows import project

    project.ensure_scene_data(verbose=False)
    cache, data = work / "cache", work / "cache-data"
    user = cache / "sim"
    user.mkdir(parents=True)
    (user / "checkpoint.bin").write_bytes(b"the user's" * 1000)
    data.mkdir()
    env = dict(main_env(), MI_AMR_CACHE=str(cache), MI_AMR_CACHE_GB=str(CACHE_GB))
    sizes, failed, t0 = [], [], time.perf_counter()
    for i in range(loads):
        path = data / f"volume_{i % CACHE_FILES:02d}.npz"
        if not path.exists():
            datasets.sphere(40 + 4 * (i % CACHE_FILES)).save(path)
        run = subprocess.run([sys.executable, "-m", "mi_amr", "render",
                              str(project.scenes_dir() / "analytic_sphere.xml"), "-o",
                              str(work / "cache-frame.png"), "--force", "-D",
                              f"filename={path}", "--resolution", "16", "16"],
                             capture_output=True, text=True, env=env)
        if run.returncode != 0:
            failed.append(run.stderr.strip()[-300:])
        sizes.append(_folder_bytes(cache) - _folder_bytes(user))
        if progress and (i + 1) % 10 == 0:
            print(f"  cache: {i + 1}/{loads} loads, {sizes[-1] / 1e9:.3f} GB", flush=True)
    return {"loads": loads, "limit_gb": CACHE_GB, "largest_gb": round(max(sizes) / 1e9, 3),
            "over_limit_loads": sum(1 for n in sizes if n > CACHE_GB * 1e9),
            "failed_loads": len(failed), "failures": failed[:3],
            "user_folder_kept": (user / "checkpoint.bin").is_file(),
            "seconds": round(time.perf_counter() - t0, 1)}


def _folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file() and
               not p.is_symlink()) if folder.is_dir() else 0


# ---------------------------------------------------------------------- the report

PARTS = {"viewer": viewer_soak, "movie": movie_soak, "cache": cache_soak}


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

