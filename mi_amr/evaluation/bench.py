"""Benchmarks: frame timings of a scene (``python -m mi_amr bench --frames``).

Timings are wall-clock seconds around ``mi.render`` followed by ``dr.eval`` and
``dr.sync_thread()``. A frame "compiles" when Dr.Jit had to produce a kernel that was not in
memory (``dr.kernel_history()``: a cache miss, or a load from Dr.Jit's disk cache). The first
frame's time includes compilation only when the disk cache is cold: run with
``DRJIT_CACHE_DIR=$(mktemp -d)`` to measure that.
"""

from __future__ import annotations

import gc
import json
import statistics
import time
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.kernels import snapshot
from mi_amr.workflows import project

DEFAULT_SCENE = "sphere_wake.xml"    # in the checkout's scenes_xml/


def _frame(mi, dr, scene, seed):
    """Render one frame; returns (seconds, kernels compiled)."""
    dr.kernel_history()  # clear
    t0 = time.perf_counter()
    img = mi.render(scene, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    # A kernel not found in memory was compiled now (or loaded from Dr.Jit's disk cache).
    compiled = sum(1 for k in dr.kernel_history()
                   if k.get("type") == dr.KernelType.JIT and
                   (not k.get("cache_hit", True) or k.get("cache_disk", False)))
    return seconds, compiled, img


def reset_peak_rss() -> bool:
    """Start measuring this process's peak resident memory afresh (Linux: writing 5 to
    ``/proc/self/clear_refs`` resets ``VmHWM``); False where that cannot be done."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def rss_gb():
    """This process's resident memory now, in GB (10^9 bytes; ``VmRSS`` of
    ``/proc/self/status``), or None where there is no such file."""
    return _status_gb("VmRSS:")


def peak_rss_gb():
    """This process's peak resident memory since :func:`reset_peak_rss`, in GB (10^9 bytes;
    ``VmHWM`` of ``/proc/self/status``), or None where there is no such file."""
    return _status_gb("VmHWM:")


def _status_gb(key: str):
    """The figure ``key`` of ``/proc/self/status`` (kB there) in GB, or None."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) * 1024 / 1e9
    except OSError:
        pass
    return None


def param_key(params, name):
    """The scene-parameter key ending in ``.name``."""
    for k in params.keys():
        if k.split(".")[-1] == name:
            return k
    raise AMRError(f"the scene has no parameter '{name}'")


def frame_timings(scene_path=None, *, resolution=(1024, 1024), defines=None,
                  frames: int = 5, variant: str = "llvm_ad_rgb") -> dict:
    """Time a scene: load, first frame (kernel compilation), warm frames (median), a frame after
    changing the isovalue and one after moving the camera (both should compile nothing)."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import load_scene

    register()
    scene_path = scene_path or project.scenes_dir() / DEFAULT_SCENE
    params = {"resx": str(resolution[0]), "resy": str(resolution[1]), "spp": "1"}
    params.update(defines or {})
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    t0 = time.perf_counter()
    scene = load_scene(scene_path, **params)
    load = time.perf_counter() - t0
    first, first_compiled, _ = _frame(mi, dr, scene, 0)
    warm = [_frame(mi, dr, scene, i + 1) for i in range(frames)]
    p = mi.traverse(scene)
    iso_key = param_key(p, "isovalue")
    iso = p[iso_key]
    p[iso_key] = iso * 1.1
    p.update()
    new_iso = _frame(mi, dr, scene, 100)
    p[iso_key] = iso
    from mi_amr.plugin.camera import Camera, scene_camera, set_camera

    cam = scene_camera(scene_path, params, scene)
    set_camera(p, Camera(tuple(np.add(cam.origin, [0.05, 0.0, 0.0])), cam.target, cam.up,
                         cam.fov))
    p.update()
    new_camera = _frame(mi, dr, scene, 101)
    return {
        "scene": str(scene_path), "variant": variant, "resolution": list(resolution),
        "defines": defines or {},
        "load_s": load, "first_frame_s": first, "first_frame_kernels_compiled": first_compiled,
        "warm_frame_s": statistics.median(w[0] for w in warm),
        "warm_kernels_compiled": sum(w[1] for w in warm),
        "new_isovalue_frame_s": new_iso[0], "new_isovalue_kernels_compiled": new_iso[1],
        "new_camera_frame_s": new_camera[0], "new_camera_kernels_compiled": new_camera[1],
    }


def print_frames(results: list) -> str:
    """Markdown table of :func:`frame_timings` results."""
    rows = ["| scene | settings | load (s) | first frame (s) | warm frame (s) | new isovalue (s) "
            "| new camera (s) | recompiles after first |",
            "|---|---|---|---|---|---|---|---|"]
    for r in results:
        settings = ", ".join(f"{k}={v}" for k, v in r["defines"].items()) or "defaults"
        recompiles = (r["warm_kernels_compiled"] + r["new_isovalue_kernels_compiled"] +
                      r["new_camera_kernels_compiled"])
        rows.append(f"| {Path(r['scene']).name} {r['resolution'][0]}x{r['resolution'][1]} | "
                    f"{settings} | {r['load_s']:.1f} | {r['first_frame_s']:.2f} | "
                    f"{r['warm_frame_s']:.2f} | {r['new_isovalue_frame_s']:.2f} | "
                    f"{r['new_camera_frame_s']:.2f} | {recompiles} |")
    return "\n".join(rows)


def run_frames(out_dir=None, resolution=(1024, 1024), variant="llvm_ad_rgb") -> list:
    """The README's speed figures: exact + basis with shadows, and adaptive at step 0.5."""
    configs = [{"method": "exact", "reconstruction": "basis"},
               {"method": "adaptive", "reconstruction": "basis", "step_scale": "0.5"}]
    results = []
    for defines in configs:
        print(f"timing {DEFAULT_SCENE} with {defines} ...", flush=True)
        results.append(frame_timings(None, resolution=resolution, defines=defines,
                                     variant=variant))
    table = print_frames(results)
    print(table)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "frames.json").write_text(json.dumps(results, indent=2))
        (out / "frames.md").write_text(table + "\n")
        print(f"wrote {out / 'frames.json'} and {out / 'frames.md'}")
    if any(r["warm_kernels_compiled"] or r["new_isovalue_kernels_compiled"] or
           r["new_camera_kernels_compiled"] for r in results):
        raise AMRError("a frame after the first compiled a kernel: per-frame values are not "
                       "opaque (this is a bug)")
    return results


# ---------------------------------------------------------------------- speed against accuracy

STEP_SCALES = (2.0, 1.0, 0.5, 0.25, 0.1, 0.05, 0.01)
METHOD_COLORS = {"exact": "black", "bisect": "tab:green", "adaptive": "tab:blue",
                 "uniform": "tab:orange"}      # one colour per method in every chart
SWEEP_SCENES = ("sphere_wake", "plt_eb_3d", "analytic_spike", "analytic_torus")
QUICK = {"scenes": ("analytic_spike", "sphere_wake"), "step_scales": (1.0, 0.25),
         "reconstructions": ("basis",), "frames": 2}
CSV_COLUMNS = ("scene", "method", "reconstruction", "step_scale", "frame_s", "compile_s",
               "missed", "false", "depth_mean", "depth_p99", "normal_mean", "rmse",
               "samples_per_ray")


def sweep(out_dir="out/bench", *, quick: bool = False, scenes=None, frames: int = 3,
          variant: str = "llvm_ad_rgb", progress: bool = True) -> list:
    """Time and score every (scene, method, reconstruction, step_scale) against the exact
    references in ``reference/`` (see :mod:`mi_amr.evaluation.references`). Writes
    ``sweep.csv``, ``sweep.md`` and ``chart.png`` into ``out_dir``; returns the rows.

    Frames are rendered at the references' resolution with 1 sample per pixel: the frame time is
    the median of ``frames`` warm frames, the compile time is the first frame's extra time. Hit
    scores come from the primary hit buffers; the image RMSE compares with an ``exact``/``basis``
    frame rendered in the same run with the same seed (so pixel positions agree)."""
    import mitsuba as mi
    from tqdm import tqdm

    from mi_amr.evaluation import references as ref

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    project.ensure_scene_data(verbose=progress)
    methods = ("exact", "bisect", "adaptive", "uniform")
    recons = QUICK["reconstructions"] if quick else ("basis", "finest")
    steps = QUICK["step_scales"] if quick else STEP_SCALES
    frames = QUICK["frames"] if quick else frames
    names = [n for n in (scenes or (QUICK["scenes"] if quick else SWEEP_SCENES))
             if ref.available(n)]
    skipped = sorted(set(scenes or SWEEP_SCENES) - set(names)) if not quick else []
    jobs = [(n, r, m, s) for n in names for r in recons for m in methods
            for s in ((None,) if m == "exact" else steps)]
    bar = tqdm(total=len(jobs), desc="bench", unit="config", disable=not progress)
    rows = []
    for name in names:
        rows += _sweep_scene(name, recons, methods, steps, frames, bar)
    bar.close()
    _write_sweep(rows, Path(out_dir), skipped)
    if not quick:
        run_peers_only(Path(out_dir), variant=variant, progress=progress)
    return rows


def _sweep_scene(name, recons, methods, steps, frames, bar) -> list:
    """The sweep's rows of reference scene ``name``: per reconstruction and method, the scene
    loaded at the references' resolution (1 spp), its first frame timed, then per step scale
    (``exact``: none) ``frames`` warm frames timed (seconds, median) and scored against the
    reference hit buffers and the scene's first ``exact``/``basis`` image. Advances ``bar``
    once per configuration."""
    import drjit as dr
    import mitsuba as mi

    from mi_amr.evaluation import references as ref
    from mi_amr.plugin.scene import load_scene

    w, h = ref.RESOLUTION
    ref_hits = ref.HitBuffers.load(ref.reference_path(name, "hits"))
    base_image = None
    rows = []
    for recon in recons:
        for method in methods:
            scene = load_scene(ref.scene_path(name), resx=w, resy=h, spp=1, method=method,
                               reconstruction=recon)
            params = mi.traverse(scene)
            step_key = param_key(params, "step_scale")
            t0 = time.perf_counter()
            ref.render(scene, 1)
            first = time.perf_counter() - t0
            for step in ((None,) if method == "exact" else steps):
                if step is not None:
                    params[step_key] = mi.Float(step)
                    params.update()
                times = []
                for i in range(frames):
                    t0 = time.perf_counter()
                    image = ref.render(scene, 1, seed=0)
                    times.append(time.perf_counter() - t0)
                if base_image is None:
                    base_image = image  # exact + basis comes first
                hits = ref.hit_buffers(scene)
                sc = ref.score(hits, ref_hits, image, base_image)
                rows.append({"scene": name, "method": method, "reconstruction": recon,
                             "step_scale": step if step is not None else "",
                             "frame_s": statistics.median(times),
                             "compile_s": max(first - statistics.median(times), 0.0),
                             **sc.as_dict(),
                             "samples_per_ray": _samples_per_ray(scene)})
                bar.update(1)
            del scene, params
            dr.flush_malloc_cache()
    return rows


def _write_sweep(rows, out: Path, skipped):
    """Write ``sweep.csv``, ``sweep.md`` and ``chart.png`` into ``out`` (made if missing) and
    say so, naming the ``skipped`` scenes (no data here)."""
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(rows, out / "sweep.csv")
    table = sweep_table(rows)
    (out / "sweep.md").write_text(table + "\n")
    chart(rows, out / "chart.png")
    if skipped:
        print(f"skipped scenes without data: {', '.join(skipped)}")
    print(f"wrote {out / 'sweep.csv'}, {out / 'sweep.md'} and {out / 'chart.png'}")


def run_peers_only(out_dir="out/bench", variant: str = "llvm_ad_rgb", progress: bool = True):
    """The tools a user would pick instead, on the same data and machine, in this run
    (see :mod:`mi_amr.peers`); writes ``peers.md`` (with notes), ``peers_short.md`` and
    ``peers.json``."""
    from mi_amr.evaluation import references as ref
    from mi_amr.evaluation.peers import peers_table, run_peers

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    peers = run_peers(tuple(n for n in ("sphere_wake", "plt_eb_3d") if ref.available(n)),
                      variant=variant, progress=progress)
    (out / "peers.md").write_text(peers_table(peers) + "\n")
    (out / "peers_short.md").write_text(peers_table(peers, notes=False) + "\n")
    (out / "peers.json").write_text(json.dumps(peers, indent=2))
    print(peers_table(peers, notes=False))
    print(f"wrote {out / 'peers.md'}, {out / 'peers_short.md'} and {out / 'peers.json'}")
    return peers


def _samples_per_ray(scene) -> float:
    """Mean field evaluations per camera ray through a pixel centre (``exact``: cubic pieces),
    up to the first crossing: :func:`~mi_amr.evaluation.volume_speed_bench.walked_per_ray`
    of the sweep's surface scenes."""
    from mi_amr.evaluation.volume_speed_bench import walked_per_ray

    return walked_per_ray(scene)


def _write_csv(rows, path):
    import csv

    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: r[k] for k in CSV_COLUMNS})


def sweep_table(rows) -> str:
    """Markdown table of the sweep (times in ms, error rates in %)."""
    lines = ["| scene | method | reconstruction | step | frame (ms) | compile (s) | missed (%) "
             "| false (%) | depth mean (cells) | depth p99 (cells) | normal (deg) | RMSE "
             "| samples/ray |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['method']} | {r['reconstruction']} | "
                     f"{r['step_scale']} | {1000 * r['frame_s']:.0f} | {r['compile_s']:.1f} | "
                     f"{100 * r['missed']:.3f} | {100 * r['false']:.3f} | "
                     f"{r['depth_mean']:.2e} | {r['depth_p99']:.2e} | {r['normal_mean']:.2f} | "
                     f"{r['rmse']:.4f} | {r['samples_per_ray']:.1f} |")
    return "\n".join(lines)


def pareto(points) -> list:
    """Indices of the points (time, error) that no other point beats on both."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], float("inf")
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def read_csv(path) -> list:
    """Rows written by :func:`sweep` (numbers as floats)."""
    import csv

    rows = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            rows.append({k: (v if k in ("scene", "method", "reconstruction") or v == "" else
                             float(v)) for k, v in r.items()})
    return rows


def chart(rows, path):
    """Time per frame against error, one curve per method and reconstruction (filled markers:
    basis, hollow: finest), per scene, with the Pareto front marked. Errors: missed-hit rate
    (left) and the 99th percentile depth error in finest cells (right), both against the exact
    basis reference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    colors = METHOD_COLORS
    metrics = (("missed", "missed hits (% of pixels)", 100.0),
               ("depth_p99", "depth error p99 (finest cells)", 1.0))
    fig, axes = plt.subplots(len(scenes), 2, figsize=(11, 3.6 * len(scenes)), squeeze=False)
    floor = {"missed": 1e-3, "depth_p99": 1e-6}
    for row_axes, scene in zip(axes, scenes):
        sub = [r for r in rows if r["scene"] == scene]
        for ax, (key, label, scale) in zip(row_axes, metrics):
            for (method, recon) in dict.fromkeys((r["method"], r["reconstruction"]) for r in sub):
                pts = sorted([(1000 * r["frame_s"], max(scale * r[key], floor[key]))
                              for r in sub if r["method"] == method and
                              r["reconstruction"] == recon])
                style = "-" if recon == "basis" else "--"
                marker = "*" if method == "exact" else "o"
                face = colors[method] if recon == "basis" else "white"
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style, marker=marker,
                        color=colors[method], markerfacecolor=face,
                        label=f"{method} / {recon}", ms=9 if method == "exact" else 4)
            allpts = [(1000 * r["frame_s"], max(scale * r[key], floor[key])) for r in sub]
            front = [allpts[i] for i in pareto(allpts)]
            ax.plot([p[0] for p in front], [p[1] for p in front], ":", color="crimson", lw=2,
                    label="Pareto front", zorder=0)
            ax.scatter([p[0] for p in front], [p[1] for p in front], s=120, facecolors="none",
                       edgecolors="crimson", zorder=5)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("time per frame (ms)")
            ax.set_ylabel(label)
            ax.text(0.99, 0.01, "zero is drawn on the bottom edge", transform=ax.transAxes,
                    ha="right", va="bottom", fontsize=7, color="gray")
            ax.set_title(scene)
            ax.grid(True, which="both", alpha=0.3)
        row_axes[0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------- scaling

@snapshot.using("off")   # every load prepared from the file, as a user's first
def scaling(out_dir="out/bench", variant: str = "llvm_ad_rgb", frames: int = 3) -> list:
    """How the warm frame time of the default scene (exact, basis, shadows) grows with the image
    size, the number of grids (the same cells cut into smaller grids) and the number of cells
    (the sphere_wake sizes, up to ``xxlarge``: 105M cells), with the peak resident memory of
    each load.
    Writes ``scaling.md``; returns the rows."""
    import mitsuba as mi
    from tqdm import tqdm

    from mi_amr.synthetic import datasets
    from mi_amr.readers import load

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import load_scene

    preparations = register()
    project.ensure_scene_data()
    SCENES = project.scenes_dir()
    out = Path(out_dir)
    # The derived datasets are kept beside the scenes' data (not committed) and reused; delete
    # scenes_xml/data/scaling/ after changing the dataset code.
    work = SCENES / "data" / "scaling"
    work.mkdir(parents=True, exist_ok=True)
    base = SCENES / "sphere_wake.xml"
    default = load(SCENES / "data" / "sphere_wake.npz")

    def split(max_cells):
        scene = _scene_copy(base, work, f"grids{max_cells}",
                            lambda: datasets.split_grids(default, max_cells))
        grids = len(load(scene.with_suffix(".npz")).grids)
        return f"{grids:,} (<= {max_cells}^3 cells each)", scene

    def size(name):
        scene = _scene_copy(base, work, f"cells_{name}",
                            lambda: datasets.sphere_wake(name, progress=True))
        return f"{load(scene.with_suffix('.npz')).num_cells:,} ({name})", scene

    # (varied, image size, how to get (value, scene file)); datasets are made when their case
    # comes, so the big ones do not sit in memory while the others are timed.
    cases = [("image size", n, lambda n=n: (f"{n}x{n}", base)) for n in (256, 512, 1024, 2048)]
    cases += [("grids", 512, lambda: (f"{len(default.grids):,} (<= 32^3 cells each)", base)),
              ("grids", 512, lambda: split(16)), ("grids", 512, lambda: split(8)),
              ("cells", 512, lambda: size("small")),
              ("cells", 512, lambda: (f"{default.num_cells:,} (default)", base)),
              ("cells", 512, lambda: size("large")), ("cells", 512, lambda: size("xlarge")),
              ("cells", 512, lambda: size("xxlarge"))]
    rows = []
    for what, res, make in tqdm(cases, desc="scaling", unit="case"):
        value, scene_file = make()
        preparations.clear()     # every load from the file, as a user's first load would be
        gc.collect()
        _dr().flush_malloc_cache()      # memory the cases before freed, not counted again
        measured = reset_peak_rss()
        start = rss_gb()
        t0 = time.perf_counter()
        scene = load_scene(scene_file, resx=res, resy=res, spp=1)
        load_s = time.perf_counter() - t0
        peak = peak_rss_gb() if measured else None
        cells = scene.integrator().prep.volume.num_cells
        _frame(mi, _dr(), scene, 0)
        times = [_frame(mi, _dr(), scene, i + 1)[0] for i in range(frames)]
        rows.append({"what": what, "value": value, "resolution": res, "load_s": load_s,
                     "peak_gb": peak, "frame_s": statistics.median(times),
                     "per_cell": None if peak is None or start is None else
                     (peak - start) * 1e9 / cells})
        del scene
    return _scaling_table(out, rows)


def _scaling_table(out, rows) -> list:
    """Write :func:`scaling`'s ``scaling.md`` (and print it); returns the rows."""
    lines = ["| varied | value | image | scene load (s) | peak resident while loading (GB) | "
             "peak above the load's start (bytes a cell) | warm frame (s) |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        peak = "-" if r["peak_gb"] is None else f"{r['peak_gb']:.2f}"
        per_cell = "-" if r["per_cell"] is None else f"{r['per_cell']:.1f}"
        lines.append(f"| {r['what']} | {r['value']} | {r['resolution']}x{r['resolution']} | "
                     f"{r['load_s']:.1f} | {peak} | {per_cell} | {r['frame_s']:.2f} |")
    table = "\n".join(lines)
    from mi_amr.workflows.movie.output import write_bytes_atomic

    write_bytes_atomic(out / "scaling.md", (table + "\n").encode())
    print(table)
    return rows


def kdtree_build(out_dir="out/bench", sizes=((20, 2000), (40, 36000))) -> list:
    """Seconds to validate a hierarchy of very many tiny grids (:func:`datasets.many_grids`:
    10^4 and 10^5 grids), to build its kd-tree as the renderer does (its ``leaf_cells``, the
    ropes on the device), which is then checked (:meth:`KDTree.check`, not timed), and to take
    its leaf value ranges as the renderer does (on the device, :mod:`mi_amr.kernels.ranges`,
    the field already there);
    writes ``kdtree.md``; returns the rows."""
    import drjit as dr

    from mi_amr import params
    from mi_amr.core import memory
    from mi_amr.core.kdtree import KDTree
    from mi_amr.core.volume import AMRVolume
    from mi_amr.kernels import ranges
    from mi_amr.kernels.kdsteps import DeviceSteps
    from mi_amr.synthetic import datasets

    memory.keep_freed_memory()      # as every load of a file does (kernels.prepared)
    rows = []
    for per_axis, fine in sizes:
        grids = datasets.many_grids(per_axis, fine)
        t0 = time.perf_counter()
        vol = AMRVolume.from_grids(grids)
        t1 = time.perf_counter()
        tree = KDTree(vol, leaf_cells=params.default("leaf_cells"), device=DeviceSteps(dr.llvm.ad))
        t2 = time.perf_counter()
        values = dr.llvm.ad.Float(np.concatenate([g.fields["f"].ravel() for g in vol.grids])
                                  .astype(np.float32))
        dr.eval(values)
        t2, t_kd = time.perf_counter(), t2 - t1
        ranges.leaf_ranges(dr.llvm.ad, tree, values, "f", "basis")
        t3 = time.perf_counter()
        tree.check("f")
        rows.append({"grids": len(vol.grids), "validate_s": t1 - t0, "kdtree_s": t_kd,
                     "ranges_s": t3 - t2, "leaves": tree.num_leaves, "depth": tree.depth})
        print(f"{len(vol.grids):,} grids: validation {t1 - t0:.2f} s, kd-tree {t_kd:.2f} s, "
              f"leaf value ranges {t3 - t2:.2f} s", flush=True)
    lines = ["| grids | validation (s) | kd-tree build (s) | leaf value ranges (s) | leaves | depth |",
             "|---|---|---|---|---|---|"]
    lines += [f"| {r['grids']:,} | {r['validate_s']:.2f} | {r['kdtree_s']:.2f} | "
              f"{r['ranges_s']:.2f} | {r['leaves']:,} | {r['depth']} |" for r in rows]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    from mi_amr.workflows.movie.output import write_bytes_atomic

    write_bytes_atomic(out / "kdtree.md", ("\n".join(lines) + "\n").encode())
    print(f"wrote {out / 'kdtree.md'}")
    return rows


def _dr():
    import drjit as dr

    return dr


def _scene_copy(scene_file, folder, name, make_volume):
    """A copy of ``scene_file`` in ``folder`` reading the volume ``make_volume()`` (saved there as
    ``name.npz``, or reused when that file exists) and the scene's ball."""
    data = folder / f"{name}.npz"
    if not data.exists():
        make_volume().save(data)
    text = Path(scene_file).read_text()
    ball = (Path(scene_file).parent / "data" / "ball.ply").resolve()
    text = text.replace('value="data/sphere_wake.npz"', f'value="{data.resolve()}"')
    text = text.replace('value="data/ball.ply"', f'value="{ball}"')
    path = folder / f"{name}.xml"
    path.write_text(text)
    return path


def run_viewer(out_dir, scene=None, variant: str = "llvm_ad_rgb") -> list:
    """The browser explorer's slider-to-image round trip on ``scene`` (a scene file; None:
    the default scene) (:mod:`mi_amr.evaluation.viewer_bench`); writes ``viewer.md`` (for
    another scene ``viewer_<stem>.md``) to ``out_dir``."""
    from mi_amr.evaluation import viewer_bench

    name = "viewer" if scene is None else f"viewer_{Path(scene).stem}"
    scene = project.scenes_dir() / DEFAULT_SCENE if scene is None else scene
    return viewer_bench.run(out_dir, scene, variant=variant, name=name)
