"""``python -m mi_amr bench --limit``: mi_amr against the practical limit, in one run,
interleaved.

* **Frame against a mesh of the same surface.** The report's scene (sphere_wake, exact + basis,
  shadow rays) at 256^2 ... 2048^2, 1 spp, warm frames; against Mitsuba's ``direct`` integrator
  drawing the marching-cubes mesh of the same isosurface (scikit-image per grid, as
  :func:`mi_amr.evaluation.peers.marching_cubes_route` builds it) with the same camera, light,
  ball and floor. Frames alternate between the two, so a drift of the machine hits both.
* **Loading against reading the file.** Preparing the scene's volume (read, derive Q and speed,
  kd-tree, device arrays, leaf value ranges) against reading the same file's arrays with NumPy
  alone (the best of :data:`RAW_READS` reads); and the same preparation read back from its snapshot
  (:mod:`mi_amr.kernels.snapshot`, in a temporary folder) by a second process, once it is on
  disk.

Writes ``limit.md`` and ``limit.json``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mi_amr.workflows import project

SIZES = (256, 512, 1024, 2048)
FRAMES = 5
RAW_READS = 3       # the raw read is the best of these (the file then in the page cache)


def _frame(mi, dr, scene, seed, integrator=None) -> float:
    """Seconds of one frame of ``scene`` (by ``integrator``, else the scene's own)."""
    t0 = time.perf_counter()
    img = mi.render(scene, seed=seed, integrator=integrator)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0


def frame_against_mesh(sizes=SIZES, frames=FRAMES) -> list:
    """Rows ``{size, mi_amr_s, mesh_s, ratio, triangles}`` (median warm frames)."""
    import drjit as dr
    import mitsuba as mi
    from skimage.measure import marching_cubes

    from mi_amr.evaluation import peers
    from mi_amr.plugin.scene import load_scene

    rs = peers.route_scene("sphere_wake")
    arrays = [np.asarray(g.fields[rs.field]) for g in rs.vol.grids]
    pieces = peers.grid_pieces(marching_cubes, rs.vol, arrays, rs.iso, False)
    rows = []
    for size in sizes:
        ours = load_scene(project.scenes_dir() / "sphere_wake.xml", resx=size, resy=size, spp=1,
                          method="exact", reconstruction="basis")
        _, mesh_scene, triangles = peers.build_mesh_scene(mi, dataclasses.replace(rs, scene=ours),
                                                     pieces)
        # Where mi_amr's frame goes: the same scene without shadow rays.
        unlit = load_scene(project.scenes_dir() / "sphere_wake.xml", resx=size, resy=size,
                           spp=1, method="exact", reconstruction="basis", shadows="false")
        for sc in (ours, mesh_scene, unlit):                      # compile all first
            _frame(mi, dr, sc, 0)
        a, b, c = [], [], []
        for i in range(frames):
            a.append(_frame(mi, dr, ours, i + 1))
            b.append(_frame(mi, dr, mesh_scene, i + 1))
            c.append(_frame(mi, dr, unlit, i + 1))
        row = {"size": size, "mi_amr_s": statistics.median(a), "mesh_s": statistics.median(b),
               "no_shadows_s": statistics.median(c), "triangles": triangles}
        row["ratio"] = row["mi_amr_s"] / row["mesh_s"]
        print(f"{size}^2: mi_amr {row['mi_amr_s']:.3f} s, mesh {row['mesh_s']:.3f} s "
              f"({row['ratio']:.1f}x)", flush=True)
        rows.append(row)
        del ours, mesh_scene, unlit
    return rows


TRANSLUCENT = {"isovalue": "0.02, 0.05, 0.1", "iso_opacity": "0.4, 0.5, 0.6"}
TRANSLUCENT_SIZE, TRANSLUCENT_SPP = 256, 4
REFERENCE_SPP = 64      # the translucent frames' errors are against the composited scene at this


def translucent_against_opaque(frames=3, size=TRANSLUCENT_SIZE, spp=TRANSLUCENT_SPP,
                               out_dir=None) -> dict:
    """Three translucent isovalues against one opaque one (sphere_wake.xml, 256^2, 4 spp,
    shadow rays): median warm frames, interleaved; the translucent scene composited, with one
    shadow ray per sample (``layers="one_shadow"``), with one layer picked per sample
    (``layers="stochastic"``), and composited with the slow twins of
    its fast paths (every layer's search restarted, shadow rays composited layer by layer),
    which is what it cost before them; and the same without shadow rays. The composited and
    faster ones' mean squared error per pixel and channel against the composited scene
    at :data:`REFERENCE_SPP` samples per pixel tells what the faster ones cost in noise. With
    ``out_dir``, ``translucent_modes.png`` there shows the reference and one frame of each,
    side by side."""
    import drjit as dr
    import mitsuba as mi

    from mi_amr.plugin.scene import load_scene
    from mi_amr.plugin.twins import Twins, with_twins

    def scene(spp=spp, **integrator):
        return load_scene(project.scenes_dir() / "sphere_wake.xml", resx=size, resy=size,
                          spp=spp, integrator=integrator)

    opaque, layered = scene(isovalue="0.05"), scene(**TRANSLUCENT)
    picked = scene(layers="stochastic", **TRANSLUCENT)
    one_shadow = scene(layers="one_shadow", **TRANSLUCENT)
    # Where the difference is: the same without shadow rays.
    unshadowed = {key: scene(shadows="false", **kw) for key, kw in (
        ("opaque_unshadowed_s", {"isovalue": "0.05"}), ("translucent_unshadowed_s", TRANSLUCENT),
        ("stochastic_unshadowed_s", dict(TRANSLUCENT, layers="stochastic")))}
    slow = with_twins(layered.integrator(), Twins(layer_fast_paths=False))
    runs = [("opaque_s", opaque, None), ("translucent_s", layered, None),
            ("one_shadow_s", one_shadow, None), ("stochastic_s", picked, None),
            ("translucent_slow_s", layered, slow)]
    runs += [(key, sc, None) for key, sc in unshadowed.items()]
    times = {key: [] for key, _, _ in runs}
    for i in range(frames + 1):
        for key, sc, integ in runs:
            t = _frame(mi, dr, sc, i, integ)
            if i:                                    # the first round compiles
                times[key].append(t)
    row = {k: statistics.median(v) for k, v in times.items()}
    for ratio, key, base in (("ratio", "translucent_s", "opaque_s"),
                             ("ratio_slow", "translucent_slow_s", "opaque_s"),
                             ("ratio_stochastic", "stochastic_s", "opaque_s"),
                             ("ratio_one_shadow", "one_shadow_s", "opaque_s"),
                             ("ratio_unshadowed", "translucent_unshadowed_s",
                              "opaque_unshadowed_s"),
                             ("ratio_stochastic_unshadowed", "stochastic_unshadowed_s",
                              "opaque_unshadowed_s")):
        row[ratio] = row[key] / row[base]
    reference = np.array(mi.render(scene(spp=REFERENCE_SPP, **TRANSLUCENT), seed=1000),
                         dtype=np.float64)
    shown = [reference]
    for key, sc in (("translucent_mse", layered), ("one_shadow_mse", one_shadow),
                    ("stochastic_mse", picked)):
        images = [np.array(mi.render(sc, seed=s), dtype=np.float64) for s in range(frames)]
        row[key] = statistics.mean(float(np.mean((im - reference) ** 2)) for im in images)
        shown.append(images[0])
    if out_dir is not None:
        from mi_amr.workflows.movie.output import write_image_atomic

        write_image_atomic(Path(out_dir) / "translucent_modes.png",
                           np.concatenate([im[..., :3] for im in shown], axis=1))
    print(f"translucent {row['translucent_s']:.3f} s (slow twins {row['translucent_slow_s']:.3f}"
          f" s), one shadow ray {row['one_shadow_s']:.3f} s, stochastic "
          f"{row['stochastic_s']:.3f} s, opaque {row['opaque_s']:.3f} s: {row['ratio']:.1f}x, "
          f"{row['ratio_one_shadow']:.1f}x, {row['ratio_stochastic']:.1f}x; squared error "
          f"{row['translucent_mse']:.2e} / {row['one_shadow_mse']:.2e} / "
          f"{row['stochastic_mse']:.2e}", flush=True)
    return row


def load_against_read(paths) -> list:
    """Rows ``{file, cells, raw_s, load_s, ratio, steps}`` for each data file of the scene's
    field (q_criterion coloured by speed, from vx, vy, vz)."""
    import drjit as dr

    from mi_amr.kernels.prepared import PreparedVolume
    from mi_amr.readers import load

    rows = []
    for path in paths:
        raw_s = min(_raw_read(path) for _ in range(RAW_READS))
        t0 = time.perf_counter()
        vol = load(path, fields=["vx", "vy", "vz"])
        read = time.perf_counter() - t0
        prep = PreparedVolume(vol, "q_criterion", "speed", m=dr.llvm.ad)
        t1 = time.perf_counter()
        prep.device.node_ranges(True)
        steps = dict(read=read, **prep.timings, ranges=time.perf_counter() - t1)
        load_s = time.perf_counter() - t0
        cells = vol.num_cells
        del vol, prep
        written_s, again_s = _snapshot_load(path)
        rows.append({"file": Path(path).name, "cells": cells, "raw_s": raw_s,
                     "load_s": load_s, "ratio": load_s / raw_s, "steps": steps,
                     "snapshot_write_s": written_s, "snapshot_s": again_s,
                     "snapshot_ratio": again_s / raw_s})
        print(f"{Path(path).name}: load {load_s:.2f} s, raw read {raw_s:.3f} s "
              f"({load_s / raw_s:.0f}x) {({k: round(v, 2) for k, v in steps.items()})}; "
              f"from its snapshot {again_s:.3f} s ({again_s / raw_s:.1f}x)", flush=True)
    return rows


def _raw_read(path) -> float:
    """Seconds to read the three velocity arrays of ``path`` with NumPy alone, with NumPy's
    own huge-page advice (which a load turns off for the process: :mod:`mi_amr.core.memory`)."""
    from mi_amr.core import memory

    before = memory.huge_page_advice(True)
    try:
        t0 = time.perf_counter()
        with np.load(path) as f:
            raw = [np.asarray(f[f"field:{n}"]) for n in ("vx", "vy", "vz")]
        seconds = time.perf_counter() - t0
    finally:
        if before is not None:
            memory.huge_page_advice(before)
    del raw
    return seconds


def _snapshot_load(path):
    """``(first, again)``: seconds of a first :func:`prepare_file` of ``path`` that writes its
    snapshot (in a temporary folder), and of one in a new process that reads it back once it
    is on disk (as the next process to open the file would: its memory fresh from the system,
    none recycled from the first preparation; the best of :data:`RAW_READS` processes, as the
    raw read is the best of as many reads); leaf ranges included in both."""
    import drjit as dr

    from mi_amr.kernels import prepared, snapshot

    with tempfile.TemporaryDirectory(prefix="mi_amr-snapshots-") as folder, \
            snapshot.using(folder):
        t0 = time.perf_counter()        # (prepare_file keeps nothing: a first load)
        prep = prepared.prepare_file(path, "q_criterion", "speed", m=dr.llvm.ad)
        prep.device.node_ranges(True)
        first = time.perf_counter() - t0
        del prep
        os.sync()       # the snapshot on disk, as a later process finds it (not mid-write)
        root = str(Path(__file__).resolve().parents[2])      # this copy of mi_amr
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        again = min(float(subprocess.run([sys.executable, "-c", _READ_BACK, str(path)],
                                         check=True, capture_output=True, text=True,
                                         env=env).stdout.split()[-1])
                    for _ in range(RAW_READS))
    return first, again


# What the new process runs: the same preparation, timed without the interpreter's start and
# Dr.Jit's (its backend started by a first small kernel).
_READ_BACK = """
import sys, time
import drjit as dr
from mi_amr.kernels import prepared
dr.eval(dr.llvm.ad.Float(1.0) + dr.arange(dr.llvm.ad.Float, 4))
t0 = time.perf_counter()
prep = prepared.prepare_file(sys.argv[1], "q_criterion", "speed", m=dr.llvm.ad)
prep.device.node_ranges(True)
assert prep.timings.get("snapshot") is not None, "not read from its snapshot"
print(time.perf_counter() - t0)
"""


def run_limit_bench(out_dir="out/bench", variant: str = "llvm_ad_rgb") -> dict:
    import mitsuba as mi

    from mi_amr.workflows.movie.output import write_bytes_atomic

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    project.ensure_scene_data()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames = frame_against_mesh()
    layers = translucent_against_opaque(out_dir=out)
    data = project.data_dir()
    paths = [data / "sphere_wake.npz"] + sorted((data / "scaling").glob("cells_large*.npz"))
    loads = load_against_read(paths)
    table = _table(frames, loads) + "\n\n" + _layers_table(layers)
    write_bytes_atomic(out / "limit.md", (table + "\n").encode())
    result = {"frames": frames, "loads": loads, "translucent": layers}
    write_bytes_atomic(out / "limit.json", json.dumps(result, indent=2).encode())
    print(table)
    print(f"wrote {out / 'limit.md'}")
    return result


def _layers_table(r) -> str:
    return "\n".join([
        f"| {TRANSLUCENT_SIZE}^2, {TRANSLUCENT_SPP} spp | shadow rays (s) | ratio to one opaque "
        f"isovalue | no shadow rays (s) | ratio | squared error against {REFERENCE_SPP} spp |",
        "|---|---|---|---|---|---|",
        f"| one opaque isovalue | {r['opaque_s']:.3f} | 1x | {r['opaque_unshadowed_s']:.3f} | "
        "1x | |",
        f"| three translucent, composited | {r['translucent_s']:.3f} | {r['ratio']:.1f}x | "
        f"{r['translucent_unshadowed_s']:.3f} | {r['ratio_unshadowed']:.1f}x | "
        f"{r['translucent_mse']:.2e} |",
        f"| three translucent, one shadow ray a sample (`layers=\"one_shadow\"`) | "
        f"{r['one_shadow_s']:.3f} | {r['ratio_one_shadow']:.1f}x | | | "
        f"{r['one_shadow_mse']:.2e} |",
        f"| three translucent, one layer a sample (`layers=\"stochastic\"`) | "
        f"{r['stochastic_s']:.3f} | {r['ratio_stochastic']:.1f}x | "
        f"{r['stochastic_unshadowed_s']:.3f} | {r['ratio_stochastic_unshadowed']:.1f}x | "
        f"{r['stochastic_mse']:.2e} |",
        f"| three translucent, composited by the slow twins | {r['translucent_slow_s']:.3f} | "
        f"{r['ratio_slow']:.1f}x | | | |"])


def _table(frames, loads) -> str:
    lines = ["| image | mi_amr warm frame (s) | mesh in Mitsuba (s) | ratio | mi_amr without "
             "shadow rays (s) |", "|---|---|---|---|---|"]
    lines += [f"| {r['size']}x{r['size']} | {r['mi_amr_s']:.3f} | {r['mesh_s']:.3f} | "
              f"{r['ratio']:.1f}x | {r['no_shadows_s']:.3f} |" for r in frames]
    lines += ["", f"(mesh: {frames[0]['triangles']:,} triangles, marching cubes per grid)", "",
              "| file | cells | raw read (s) | load (s) | ratio | read / derive / tree / device "
              "/ ranges (s) | from its snapshot (s) | ratio |", "|---|---|---|---|---|---|---|---|"]
    for r in loads:
        s = r["steps"]
        lines.append(f"| {r['file']} | {r['cells']:,} | {r['raw_s']:.3f} | {r['load_s']:.2f} | "
                     f"{r['ratio']:.0f}x | {s['read']:.2f} / {s['derive']:.2f} / {s['tree']:.2f}"
                     f" / {s['device']:.2f} / {s['ranges']:.2f} | {r['snapshot_s']:.3f} | "
                     f"{r['snapshot_ratio']:.1f}x |")
    return "\n".join(lines)
