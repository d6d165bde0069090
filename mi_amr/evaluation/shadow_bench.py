"""``python -m mi_amr bench --volume --shadows``: volume mode's shadows side by side.

One run, one process: the report's scene in surface mode (``sphere_wake.xml``), then each
volume scene (``sphere_wake_volume.xml``, one band; ``sphere_wake_shells.xml``, three) with
shadows off, with transmittance caches (``volume_shadows="cache"``) and with a shadow ray per
lit piece (``"exact"``). Frame times are the median of warm frames at 1 spp, seed 0, in
seconds (one warm frame of ``exact``); the first frame (compilation, and the caches' build) is shown apart, and the caches'
build is timed again on its own. The cached image is scored against the exact one of the same
seed (relative RMSE over pixels and channels). Compare ratios within one run only.

Writes ``shadows.md`` and ``shadows.csv``.
"""

from __future__ import annotations

import csv
import statistics
import time
from pathlib import Path

import numpy as np

from mi_amr.workflows import project

SCENES = ("sphere_wake_volume", "sphere_wake_shells")
RESOLUTION = 256
FRAMES = 2
COLUMNS = ("scene", "shadows", "first_s", "frame_s", "build_s", "grid", "points",
           "rel_rmse_exact")


def _frame(scene):
    import drjit as dr
    import mitsuba as mi

    t0 = time.perf_counter()
    img = mi.render(scene, seed=0, spp=1)
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


def _row(name, shadows, res, frames):
    """Load ``name`` with ``shadows`` (``off``, ``cache``, ``exact``, or ``surface``) and
    time it; returns the row and the last image."""
    from mi_amr.plugin.scene import load_scene

    extra = {} if shadows in ("off", "surface") else {"volume_shadows": shadows}
    scene = load_scene(project.scenes_dir() / f"{name}.xml", resx=res, resy=res, spp=1,
                       shadows="false" if shadows == "off" else "true",
                       integrator=extra or None)
    first, image = _frame(scene)
    times = []
    # (The exact twin's frames are the slowest by far: one warm frame of it.)
    for _ in range(frames if shadows != "exact" else 1):
        t, image = _frame(scene)
        times.append(t)
    row = {"scene": name, "shadows": shadows, "first_s": first,
           "frame_s": statistics.median(times)}
    if shadows == "cache":
        row.update(_build(scene))
    return row, image


def shadow_sweep(out_dir="out/bench", *, res: int = RESOLUTION, frames: int = FRAMES,
                 variant: str = "llvm_ad_rgb", progress: bool = True) -> list:
    """Time every scene and shadow design (see the module docstring); write the results into
    ``out_dir`` and return the rows."""
    import mitsuba as mi

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    project.ensure_scene_data(verbose=progress)
    rows = [_row("sphere_wake", "surface", res, frames)[0]]
    for name in SCENES:
        images = {}
        for shadows in ("off", "cache", "exact"):
            row, images[shadows] = _row(name, shadows, res, frames)
            rows.append(row)
            if progress:
                print(_line(row), flush=True)
        exact = images["exact"]
        err = np.sqrt(np.mean((images["cache"] - exact) ** 2)) / np.sqrt(np.mean(exact ** 2))
        rows[-2]["rel_rmse_exact"] = float(err)
    _write(rows, Path(out_dir), res)
    return rows


def _line(row) -> str:
    return " ".join(f"{k}={row[k]:.3f}" if isinstance(row.get(k), float) else f"{k}={row[k]}"
                    for k in COLUMNS if k in row)


def _write(rows, out: Path, res: int) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "shadows.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
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
    (out / "shadows.md").write_text("\n".join(lines) + "\n")
