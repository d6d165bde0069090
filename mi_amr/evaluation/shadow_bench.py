"""``python -m mi_amr bench --volume --shadows``: volume mode's shadow designs side by side.

One run, one process: the report's scene in surface mode (``sphere_wake.xml``), then each
volume scene (``sphere_wake_volume.xml``, one band; ``sphere_wake_shells.xml``, three) with
shadows off, with transmittance caches (``volume_shadows="cache"``, the default), with the
caches corrected by one exact shadow ray per camera sample (``"corrected"``) and with a shadow
ray per lit piece (``"exact"``).

- **Speed** (:data:`RESOLUTION`, 1 spp, seed 0): the median of warm frames in seconds (one
  warm frame of ``exact``); the first frame (compilation, and the caches' build) apart, and
  the caches' build timed again on its own. Each image is scored against the exact one of
  the same seed (relative RMSE over pixels and channels).
- **Accuracy** (:data:`ACCURACY_RES`, the issue's measure): each design at
  :data:`ACCURACY_SPP` spp, seed 2, against ``exact`` at :data:`REFERENCE_SPP` spp, seed 1;
  and against ``exact`` at the same spp and seed, which leaves out the pixels' own sampling
  noise (``exact`` against its own reference is that noise alone).

Compare ratios within one run only. Writes ``shadows.md`` and ``shadows.csv``.
"""

from __future__ import annotations

import csv
import statistics
import time
from pathlib import Path

import numpy as np

from mi_amr.evaluation.volume_bench import rmse
from mi_amr.workflows import project

SCENES = ("sphere_wake_volume", "sphere_wake_shells")
DESIGNS = ("off", "cache", "corrected", "exact")
RESOLUTION = 256
FRAMES = 2
ACCURACY_RES = 128
ACCURACY_SPP = 16
REFERENCE_SPP = 64
COLUMNS = ("scene", "shadows", "first_s", "frame_s", "build_s", "grid", "points",
           "rel_rmse_exact", "spp", "rel_rmse_reference", "rel_rmse_same_seed")


def _frame(scene, spp=1, seed=0):
    import drjit as dr
    import mitsuba as mi

    t0 = time.perf_counter()
    img = mi.render(scene, seed=seed, spp=spp)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0, np.array(img)


def _build(scene) -> dict:
    """The caches built again on their own: seconds, the grid's points per axis and the
    points filled."""
    import drjit as dr

    from mi_amr.kernels import shadow_grid
    from mi_amr.plugin import shadow_cache

    integ = scene.integrator()
    t0 = time.perf_counter()
    shadow_cache.build_all(integ, scene.emitters())
    dr.sync_thread()
    seconds = time.perf_counter() - t0
    leaves = shadow_cache.opacity_leaves(integ)
    grid = shadow_grid.plan(integ.dev.tree, leaves)
    points = len(shadow_grid.needed_points(grid, integ.dev.tree, leaves))
    return {"build_s": seconds, "grid": "x".join(map(str, grid.dims)), "points": points}


def _load(name, shadows, res):
    """The scene ``name`` at ``res`` with ``shadows`` (a design of :data:`DESIGNS`, or
    ``surface``)."""
    from mi_amr.plugin.scene import load_scene

    extra = {} if shadows in ("off", "surface") else {"volume_shadows": shadows}
    return load_scene(project.scenes_dir() / f"{name}.xml", resx=res, resy=res, spp=1,
                      shadows="false" if shadows == "off" else "true",
                      integrator=extra or None)


def _row(name, shadows, res, frames):
    """Load ``name`` with ``shadows`` (see :func:`_load`) and time it; returns the row and
    the last image."""
    scene = _load(name, shadows, res)
    first, image = _frame(scene)
    times = []
    # (The exact twin's frames are the slowest by far: one warm frame of it.)
    for _ in range(frames if shadows != "exact" else 1):
        t, image = _frame(scene)
        times.append(t)
    row = {"scene": name, "shadows": shadows, "first_s": first,
           "frame_s": statistics.median(times)}
    if shadows in ("cache", "corrected"):
        row.update(_build(scene))
    return row, image


def _accuracy(name, res, spp, ref_spp) -> list:
    """The accuracy rows of ``name`` (see the module docstring)."""
    exact = _load(name, "exact", res)
    reference = _frame(exact, ref_spp, seed=1)[1]
    same = _frame(exact, spp, seed=2)[1]
    rows = []
    for shadows in ("exact", "cache", "corrected"):
        image = same if shadows == "exact" else _frame(_load(name, shadows, res), spp, 2)[1]
        rows.append({"scene": name, "shadows": shadows, "spp": spp,
                     "rel_rmse_reference": rmse(image, reference)[1],
                     "rel_rmse_same_seed": rmse(image, same)[1]})
    return rows


def shadow_sweep(out_dir="out/bench", *, res: int = RESOLUTION, frames: int = FRAMES,
                 accuracy: tuple = (ACCURACY_RES, ACCURACY_SPP, REFERENCE_SPP),
                 variant: str = "llvm_ad_rgb", progress: bool = True) -> list:
    """Time every scene and shadow design and score their accuracy (``accuracy``: the
    resolution, spp and reference spp; see the module docstring); write the results into
    ``out_dir`` and return the rows (speed rows first)."""
    import mitsuba as mi

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    project.ensure_scene_data(verbose=progress)
    rows = [_row("sphere_wake", "surface", res, frames)[0]]
    for name in SCENES:
        images, named = {}, {}
        for shadows in DESIGNS:
            named[shadows], images[shadows] = _row(name, shadows, res, frames)
            rows.append(named[shadows])
            if progress:
                print(_line(named[shadows]), flush=True)
        for shadows in ("cache", "corrected"):
            named[shadows]["rel_rmse_exact"] = rmse(images[shadows], images["exact"])[1]
    scored = []
    for name in SCENES:
        scored += _accuracy(name, *accuracy)
        if progress:
            print("\n".join(_line(r) for r in scored[-3:]), flush=True)
    _write(rows, scored, Path(out_dir), (res, accuracy))
    return rows + scored


def _line(row) -> str:
    return " ".join(f"{k}={row[k]:.3f}" if isinstance(row.get(k), float) else f"{k}={row[k]}"
                    for k in COLUMNS if k in row)


def _write(rows, scored, out: Path, sizes) -> None:
    res, (acc_res, spp, ref_spp) = sizes
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "shadows.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows + scored)
    surface = rows[0]["frame_s"]
    lines = [f"Volume shadows, {res}x{res}, 1 spp, median warm frame (one run; ratios to "
             f"surface mode's frame, {surface:.3f} s)", "",
             "| scene | shadows | frame (s) | x surface | first frame (s) | build (s) | grid "
             "| points built | rel. RMSE vs exact |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        def cell(k, fmt="{:.3f}"):
            return fmt.format(r[k]) if k in r else "-"
        lines.append(f"| {r['scene']} | {r['shadows']} | {r['frame_s']:.3f} | "
                     f"{r['frame_s'] / surface:.1f} | {r['first_s']:.2f} | "
                     f"{cell('build_s', '{:.1f}')} | {r.get('grid', '-')} | "
                     f"{r.get('points', '-')} | {cell('rel_rmse_exact', '{:.4f}')} |")
    lines += ["", f"Accuracy, {acc_res}x{acc_res}: each design at {spp} spp (seed 2) against "
              f"`exact` at {ref_spp} spp (seed 1), and against `exact` at {spp} spp (seed 2, "
              "the same pixel samples)", "",
              f"| scene | shadows | rel. RMSE vs exact {ref_spp} spp | rel. RMSE vs exact, "
              "same samples |", "|---|---|---|---|"]
    lines += [f"| {r['scene']} | {r['shadows']} | {r['rel_rmse_reference']:.4f} | "
              f"{r['rel_rmse_same_seed']:.4f} |" for r in scored]
    (out / "shadows.md").write_text("\n".join(lines) + "\n")
