"""``python -m mi_amr bench --volume``: volume mode's speed against its accuracy.

Each volume-mode method (``exact``, and ``bisect``, ``adaptive`` and ``uniform`` at each step
scale) renders the frame at 1 sample per pixel; its image is scored against

* a converged reference: ``exact`` at ``ref_spp`` samples per pixel (pixel sampling and method
  error together; ``exact`` at 1 spp shows how much of that is pixel sampling alone), and
* ``exact`` at 1 spp with the same seed, so the pixel positions agree (the method's own error).

Two scenes: the course report's (sphere_wake in volume mode: one Gaussian band of the
Q-criterion, coloured by speed, with shadow rays) and the analytic sphere of
``analytic_sphere.xml`` with a band of width 0.01 around ``f = 0.3``. Images are linear RGB;
RMSE is over all pixels and channels, relative RMSE divides by the reference's RMS. Frame times
are the median of warm frames in seconds.

Then the shading cut (Marchesin et al. 2009, section 3.2: ``exact`` also cuts each cell's
piece where the diffuse term turns): ``exact`` with and without it against ``uniform`` at
:data:`CUT_STEP` cells per step, each sample shaded where it is, at the same pixels
(:data:`CUT_RESOLUTION`).

Writes ``volume.csv``, ``volume.md`` (both tables) and ``volume_chart.png``.
"""

from __future__ import annotations

import csv
import statistics
import time
from pathlib import Path

import numpy as np

from mi_amr.workflows import project

#: scene file -> amr_iso parameters that turn it into the benchmarked volume-mode scene
SCENES = {
    "sphere_wake_volume": {},
    "analytic_sphere": {"mode": "volume", "band_width": 0.01},
}
METHODS = ("exact", "bisect", "adaptive", "uniform")
STEP_SCALES = (2.0, 1.0, 0.5, 0.25, 0.1, 0.05)
RESOLUTION = (256, 256)
REF_SPP = 64
FRAMES = 3
CUT_RESOLUTION = (128, 128)
CUT_STEP = 0.02
QUICK = {"resolution": (32, 32), "ref_spp": 4, "step_scales": (1.0, 0.25), "frames": 1,
         "cut_resolution": (32, 32), "cut_step": 0.25}
COLUMNS = ("scene", "method", "step_scale", "frame_s", "rmse_ref", "rel_rmse_ref",
           "rmse_same", "rel_rmse_same")


def rmse(image, ref) -> tuple:
    """(RMSE, RMSE divided by the RMS of ``ref``) of two images of the same shape."""
    err = float(np.sqrt(np.mean((np.asarray(image, np.float64) - ref) ** 2)))
    scale = float(np.sqrt(np.mean(np.asarray(ref, np.float64) ** 2)))
    return err, err / scale if scale > 0 else float("nan")


def volume_sweep(out_dir="out/bench", *, quick: bool = False, variant: str = "llvm_ad_rgb",
                 progress: bool = True) -> list:
    """Time and score every (scene, method, step scale) in volume mode; write the results
    into ``out_dir`` and return the rows (see the module docstring)."""
    import mitsuba as mi
    from tqdm import tqdm

    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    project.ensure_scene_data(verbose=progress)
    res = QUICK["resolution"] if quick else RESOLUTION
    ref_spp = QUICK["ref_spp"] if quick else REF_SPP
    steps = QUICK["step_scales"] if quick else STEP_SCALES
    frames = QUICK["frames"] if quick else FRAMES
    per_scene = 1 + (len(METHODS) - 1) * len(steps) + 3
    bar = tqdm(total=len(SCENES) * per_scene, desc="bench --volume", unit="config",
               disable=not progress)
    rows = []
    for name, overrides in SCENES.items():
        rows += _scene_rows(name, overrides, res, ref_spp, steps, frames, bar)
    cut = [_cut_rows(name, overrides, QUICK["cut_resolution"] if quick else CUT_RESOLUTION,
                     QUICK["cut_step"] if quick else CUT_STEP, bar) for name, overrides in
           SCENES.items()]
    bar.close()
    write_results(rows, Path(out_dir), res, ref_spp, [r for pair in cut for r in pair])
    return rows


def _load(name, overrides, res, method):
    from mi_amr.plugin.scene import load_scene

    return load_scene(project.scenes_dir() / f"{name}.xml", resx=res[0], resy=res[1], spp=1,
                      method=method, integrator=dict(overrides) or None)


def _scene_rows(name, overrides, res, ref_spp, steps, frames, bar) -> list:
    """One scene's rows: the reference first (``exact`` at ``ref_spp``, seed 1000), then each
    method loaded once and, per step scale, ``frames`` warm 1-spp frames (seed 0) timed and
    the last one scored. Advances ``bar`` once per row."""
    import drjit as dr
    import mitsuba as mi

    from mi_amr.evaluation import references as ref
    from mi_amr.evaluation.bench import param_key

    reference = None
    same = None
    rows = []
    for method in METHODS:
        scene = _load(name, overrides, res, method)
        if reference is None:
            reference = ref.render(scene, ref_spp, seed=1000)
        params = mi.traverse(scene)
        key = param_key(params, "step_scale")
        ref.render(scene, 1, seed=0)                      # compile
        for step in ((None,) if method == "exact" else steps):
            if step is not None:
                params[key] = mi.Float(step)
                params.update()
            times, image = [], None
            for _ in range(frames):
                t0 = time.perf_counter()
                image = ref.render(scene, 1, seed=0)
                times.append(time.perf_counter() - t0)
            same = image if same is None else same          # exact comes first
            rows.append(_row(name, method, step, statistics.median(times), image, reference,
                             same))
            bar.update(1)
        del scene, params
        dr.flush_malloc_cache()
    return rows


def _cut_rows(name, overrides, res, step, bar) -> list:
    """``exact`` with and without the shading cut against ``uniform`` at ``step`` on one
    scene (1 spp, seed 0; frame times of one warm frame)."""
    import drjit as dr

    from mi_amr.evaluation import references as ref

    def frame(method, **extra):
        scene = _load(name, {**overrides, **extra}, res, method)
        ref.render(scene, 1, seed=0)                      # compile
        t0 = time.perf_counter()
        image = ref.render(scene, 1, seed=0)
        elapsed = time.perf_counter() - t0
        del scene
        dr.flush_malloc_cache()
        bar.update(1)
        return image, elapsed

    truth, _ = frame("uniform", step_scale=step)
    rows = []
    for cut in (True, False):
        image, elapsed = frame("exact", shading_extrema=cut)
        rows.append({"scene": name, "shading_extrema": cut, "frame_s": elapsed,
                     "rel_rmse": rmse(image, truth)[1], "step": step, "res": res})
    return rows


def _row(name, method, step, frame_s, image, reference, same) -> dict:
    e_ref, r_ref = rmse(image, reference)
    e_same, r_same = rmse(image, same)
    return {"scene": name, "method": method, "step_scale": "" if step is None else step,
            "frame_s": frame_s, "rmse_ref": e_ref, "rel_rmse_ref": r_ref,
            "rmse_same": e_same, "rel_rmse_same": r_same}


def write_results(rows, out: Path, res, ref_spp, cut=()) -> None:
    """``volume.csv``, ``volume.md`` and ``volume_chart.png`` into ``out`` (made if missing),
    each written to a temporary file first and then renamed."""
    from mi_amr.core.atomic import replacing

    out.mkdir(parents=True, exist_ok=True)
    with replacing(out / "volume.csv") as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows({k: r[k] for k in COLUMNS} for r in rows)
    with replacing(out / "volume.md") as tmp:
        tmp.write_text(volume_table(rows, res, ref_spp) + "\n\n" + cut_table(cut) + "\n")
    with replacing(out / "volume_chart.png") as tmp:
        volume_chart(rows, tmp, res, ref_spp)
    print(volume_table(rows, res, ref_spp))
    print(cut_table(cut))
    print(f"wrote {out / 'volume.csv'}, {out / 'volume.md'} and {out / 'volume_chart.png'}")


def volume_table(rows, res, ref_spp) -> str:
    """Markdown table of the rows (frame times in ms)."""
    lines = [f"Volume mode, {res[0]}x{res[1]}, 1 spp against exact at {ref_spp} spp "
             "(converged) and exact at 1 spp with the same pixel positions (method error).",
             "",
             "| scene | method | step | frame (ms) | RMSE vs converged | relative | "
             "RMSE vs exact 1 spp | relative |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['method']} | {r['step_scale']} | "
                     f"{1000 * r['frame_s']:.0f} | {r['rmse_ref']:.4f} | "
                     f"{r['rel_rmse_ref']:.3f} | {r['rmse_same']:.4f} | "
                     f"{r['rel_rmse_same']:.3f} |")
    return "\n".join(lines)


def cut_table(cut) -> str:
    """Markdown table of the shading-cut rows (empty without any)."""
    if not cut:
        return ""
    res, step = cut[0]["res"], cut[0]["step"]
    lines = [f"The shading cut: exact with and without it, {res[0]}x{res[1]}, 1 spp, against "
             f"uniform at {step} cells per step at the same pixels.", "",
             "| scene | shading cut | frame (ms) | relative RMSE vs uniform |",
             "|---|---|---|---|"]
    for r in cut:
        lines.append(f"| {r['scene']} | {'yes' if r['shading_extrema'] else 'no'} | "
                     f"{1000 * r['frame_s']:.0f} | {r['rel_rmse']:.4f} |")
    return "\n".join(lines)


def volume_chart(rows, path, res, ref_spp) -> None:
    """Per scene: relative RMSE against the converged reference (left) and against exact at the
    same pixel positions (right), over time per frame, one curve per method (log axes; a zero
    error is drawn on the bottom edge)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mi_amr.evaluation.bench import METHOD_COLORS as colors

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    panels = (("rel_rmse_ref", f"relative RMSE vs exact at {ref_spp} spp"),
              ("rel_rmse_same", "relative RMSE vs exact at 1 spp (same pixels)"))
    fig, axes = plt.subplots(len(scenes), 2, figsize=(11, 3.6 * len(scenes)), squeeze=False)
    for row_axes, scene in zip(axes, scenes):
        sub = [r for r in rows if r["scene"] == scene]
        for ax, (key, label) in zip(row_axes, panels):
            for method in METHODS:
                pts = sorted((1000 * r["frame_s"], max(r[key], 1e-4)) for r in sub
                             if r["method"] == method)
                ax.plot([p[0] for p in pts], [p[1] for p in pts], "-",
                        marker="*" if method == "exact" else "o", color=colors[method],
                        ms=10 if method == "exact" else 4, label=method)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("time per frame (ms)")
            ax.set_ylabel(label, fontsize=8)
            if key == "rel_rmse_same":
                ax.text(0.99, 0.01, "zero (exact itself) is drawn on the bottom edge",
                        transform=ax.transAxes, ha="right", va="bottom", fontsize=7,
                        color="gray")
            ax.set_title(f"{scene} ({res[0]}x{res[1]}, 1 spp)")
            ax.grid(True, which="both", alpha=0.3)
        row_axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
