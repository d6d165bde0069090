"""``python -m mi_amr bench --movie``: frames per second of the kinds of movie (an orbit on
one file, an isovalue sweep, a time series of ``sphere_wake`` with one file per frame, and one
whose files share a grid layout, :func:`_series_one_layout`) with 1 and 2 Dask workers at
512 x 512, the cost of one new time step broken down (a new grid layout; the grids of the step
before; a new layout whose snapshot is written), a step with and without the next one
prepared in the background, and an estimate for a long series of big files from the measured
per-cell costs. Writes ``movie.md`` (and ``movie.json``) and a strip
of four frames, ``movie_strip.png``."""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np

from mi_amr.workflows import project

RESOLUTION = (512, 512)
FRAMES = 12
STEPS = FRAMES      # a time series with one file per frame: each frame loads a new step
SERIES_SIZE = "default"


def _series(folder: Path) -> list:
    """``sphere_wake`` with seeds 0 to ``STEPS - 1`` (made once, kept beside the scenes'
    data)."""
    from mi_amr.synthetic import datasets

    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for seed in range(STEPS):
        path = folder / f"wake_{seed:02d}.npz"
        if not path.exists():
            print(f"making {path} ...", flush=True)
            datasets.sphere_wake(SERIES_SIZE, seed=seed, progress=True).save(path)
        files.append(path)
    return files


def _series_one_layout(folder: Path) -> list:
    """The flows of seeds 0 to ``STEPS - 1`` on the grids of seed 0's wake
    (:func:`~mi_amr.synthetic.datasets.sphere_wake_on`: one grid layout through time, as
    static refinement has it; made once, kept beside the scenes' data)."""
    from mi_amr.synthetic import datasets

    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / f"layout_{seed:02d}.npz" for seed in range(STEPS)]
    missing = [p for p in paths if not p.exists()]
    if missing:
        grids = datasets.sphere_wake(SERIES_SIZE, seed=0, progress=False)
        for seed, path in enumerate(paths):
            if path in missing:
                print(f"making {path} ...", flush=True)
                datasets.sphere_wake_on(grids, seed).save(path)
    return paths


def _run(scene, out, workers, **kw) -> dict:
    from mi_amr.workflows.movie import render_movie

    t0 = time.perf_counter()
    summary = render_movie(scene, out, frames=FRAMES, resolution=RESOLUTION, workers=workers,
                           force=True, progress=False, **kw)
    seconds = time.perf_counter() - t0
    if summary.failed:
        raise RuntimeError(summary.text())
    return {"seconds": seconds, "fps": FRAMES / seconds, "frames": summary.rendered}


def _breakdown(files, scene) -> dict:
    """One new time step in one process: read, derive, tree, device, ranges, compile, frame."""
    import drjit as dr

    from mi_amr.plugin.integrator import register
    from mi_amr.workflows.movie.frames import FrameRenderer
    from mi_amr.workflows.movie.spec import FrameSpec

    register().clear()              # the runs before prepared these files: start afresh
    # (run_movie_bench turned snapshots off for this process and its workers)

    r = FrameRenderer(scene, resolution=RESOLUTION, defines={"filename": str(files[0])})
    cam = r.base_camera()
    r.render(FrameSpec(index=0, file=str(files[0]), camera=cam))      # compiles, once
    rows = []
    for i, f in enumerate(files[1:], start=1):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        t0 = time.perf_counter()
        timings = r.show(FrameSpec(index=i, file=str(f), camera=cam))
        t1 = time.perf_counter()
        img = r.mi.render(r.scene, seed=i)
        dr.eval(img)
        dr.sync_thread()
        t2 = time.perf_counter()
        compiled = sum(1 for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT and
                       (not k.get("cache_hit", False) or k.get("cache_disk", False)))
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        rows.append(dict(timings, step=t1 - t0, frame=t2 - t1, compiled=compiled,
                         cells=r.integ.prep.volume.num_cells))
    return {k: statistics.median(row[k] for row in rows) for k in rows[0]}


def _overlap(files, scene, folder: Path) -> dict:
    """Seconds a step of the time series ``files`` takes in one process (load, frame and its
    PNG; median over the files after the first), with the next file prepared in a background
    thread while the frame renders (``ahead``, as a one-worker movie does) and without
    (``after``: each step loaded, then rendered)."""
    from mi_amr.plugin.integrator import register
    from mi_amr.workflows.movie.frames import FrameRenderer
    from mi_amr.workflows.movie.spec import FrameSpec

    out = {}
    for name, ahead in (("after", False), ("ahead", True)):
        register().clear()
        r = FrameRenderer(scene, resolution=RESOLUTION, defines={"filename": str(files[0])})
        cam = r.base_camera()
        seconds = []
        for i, f in enumerate(files):
            following = str(files[i + 1]) if ahead and i + 1 < len(files) else None
            t0 = time.perf_counter()
            r.render_to(FrameSpec(index=i, file=str(f), camera=cam), folder / f"{name}{i}.png",
                        next_file=following)
            seconds.append(time.perf_counter() - t0)
        r.prefetch.wait()
        out[name] = statistics.median(seconds[1:])
    return out


def _strip(folder: Path, out: Path) -> None:
    """Four frames of the movie in ``folder`` side by side, written to ``out``."""
    import io

    import imageio.v2 as imageio

    from mi_amr.workflows.movie.output import write_bytes_atomic

    frames = sorted(folder.glob("frame_*.png"))
    pick = [frames[i] for i in np.linspace(0, len(frames) - 1, 4).astype(int)]
    strip = np.concatenate([np.asarray(imageio.imread(p))[..., :3] for p in pick], axis=1)
    buf = io.BytesIO()
    imageio.imwrite(buf, strip, format="png")
    write_bytes_atomic(out, buf.getvalue())


def _estimate(b: dict, nodes=(1, 16, 64)) -> list:
    """Hours for 1000 time steps of 10^8 cells on N nodes like this machine, scaling the
    measured per-cell load and the frame time (a frame grows slowly with cells; the load
    linearly)."""
    per_cell = (b["read"] + b["derive"] + b["tree"] + b["device"] + b["ranges"]) / b["cells"]
    load = per_cell * 1e8
    frame = b["frame"] * 1.6         # the scaling table: 6.7x the cells cost ~1.5x per frame
    lines = [f"- per time step of 10^8 cells: load ~{load:.0f} s (read "
             f"{b['read'] / b['cells'] * 1e8:.0f} s, derive {b['derive'] / b['cells'] * 1e8:.0f} s,"
             f" tree and ranges {(b['tree'] + b['ranges']) / b['cells'] * 1e8:.0f} s, device "
             f"{b['device'] / b['cells'] * 1e8:.0f} s), frame ~{frame:.1f} s"]
    for n in nodes:
        hours = 1000 * (load + frame) / n / 3600
        lines.append(f"- 1000 steps on {n} node(s) of 2 cores: ~{hours:.1f} h "
                     f"(the load is {100 * load / (load + frame):.0f} % of it)")
    return lines


def run_movie_bench(out_dir="out/bench") -> dict:
    """Measure (see the module docstring); returns the figures. Every run, and every worker
    process it starts, loads its data as a first render would: no snapshot read or written
    (but for the step table's last row, whose snapshots go to a temporary folder)."""
    from mi_amr.kernels import snapshot

    with snapshot.using("off"):             # worker processes inherit it
        return _measure(out_dir)


def _measure(out_dir) -> dict:
    from mi_amr.workflows.movie.output import write_bytes_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    project.ensure_scene_data()
    scene = project.scenes_dir() / "sphere_wake.xml"
    files = _series(project.data_dir() / "movie")
    one_layout = _series_one_layout(project.data_dir() / "movie")
    import tempfile

    from mi_amr.kernels import snapshot

    work = Path(tempfile.mkdtemp(prefix="mi_amr-movie-bench-"))
    kinds = {"orbit (one file)": {"orbit": 360},
             "isovalue sweep": {"isovalues": "0.03:0.09"},
             f"time series ({STEPS} files)": {"files": [str(f) for f in files]},
             f"time series, one grid layout ({STEPS} files)": {
                 "files": [str(f) for f in one_layout]}}
    results = {}
    for name, kw in kinds.items():
        for workers in (1, 2):
            print(f"{name}, {workers} worker(s) ...", flush=True)
            results[(name, workers)] = _run(scene, work / f"{len(results)}", workers, **kw)
    _strip(work / "0", out / "movie_strip.png")
    b = _breakdown(files, scene)
    same = _breakdown(one_layout, scene)
    with tempfile.TemporaryDirectory(prefix="mi_amr-movie-snapshots-") as folder, \
            snapshot.using(folder):
        written = _breakdown(files, scene)      # each new step's snapshot written
    overlap = _overlap(files, scene, work)
    table = _table(results, (b, same, written), overlap)
    write_bytes_atomic(out / "movie.md", (table + "\n").encode())
    write_bytes_atomic(out / "movie.json", json.dumps({
        "runs": {f"{k[0]} / {k[1]}": {"seconds": v["seconds"], "fps": v["fps"]}
                 for k, v in results.items()}, "time_step": b, "time_step_one_layout": same,
        "time_step_snapshot_written": written, "step_with_and_without_background": overlap},
        indent=2).encode())
    print(table)
    print(f"wrote {out / 'movie.md'} and {out / 'movie_strip.png'}")
    return {"runs": results, "time_step": b, "time_step_one_layout": same,
            "time_step_snapshot_written": written, "step_with_and_without_background": overlap}


def _table(results, steps, overlap) -> str:
    """The frame rates, the steps of a new time step (``steps``: a new grid layout, the grids
    of the step before, a new layout with its snapshot written), a step with and without the
    next prepared in the background (``overlap``, :func:`_overlap`) and the estimate from
    the first of ``steps``."""
    b, same, written = steps
    lines = [f"{FRAMES} frames at {RESOLUTION[0]}x{RESOLUTION[1]}, 1 spp, exact/basis with "
             f"shadows, sphere_wake:", "",
             "| movie | 1 worker (frames/s) | 2 workers (frames/s) |", "|---|---|---|"]
    for name in dict.fromkeys(k[0] for k in results):
        lines.append(f"| {name} | {results[(name, 1)]['fps']:.2f} | "
                     f"{results[(name, 2)]['fps']:.2f} |")
    lines += ["", "One new time step in one process (median of "
              f"{STEPS - 1}, seconds; {b['cells']:,.0f} and {same['cells']:,.0f} cells):", "",
              "| grids | read | derive | kd-tree | device arrays | leaf ranges | load, all told "
              "| kernels compiled | frame |", "|---|---|---|---|---|---|---|---|---|"]
    for name, row in (("new layout", b), ("the step before's", same),
                      ("new layout, snapshot written", written)):
        lines.append(f"| {name} | {row['read']:.2f} | {row['derive']:.2f} | {row['tree']:.2f} | "
                     f"{row['device']:.2f} | {row['ranges']:.2f} | {row['load']:.2f} | "
                     f"{row['compiled']:.0f} | {row['frame']:.2f} |")
    lines += ["", f"A step of the time series in one process (load, frame and PNG, median of "
              f"{STEPS - 1}): {overlap['ahead']:.2f} s with the next file prepared in "
              f"the background while the frame renders, {overlap['after']:.2f} s "
              "without.",
              "", "Estimate for 1000 time steps of 10^8 cells of new layouts, from the per-cell "
              "costs of the first row:", ""]
    return "\n".join(lines + _estimate(b))
