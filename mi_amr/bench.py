"""Benchmarks: frame timings of a scene (``python -m mi_amr bench --frames``).

Timings are wall-clock seconds around ``mi.render`` followed by ``dr.eval`` and
``dr.sync_thread()``. A frame "compiles" when Dr.Jit had to produce a kernel that was not in
memory (``dr.kernel_history()``: a cache miss, or a load from Dr.Jit's disk cache). The first
frame's time includes compilation only when the disk cache is cold: run with
``DRJIT_CACHE_DIR=$(mktemp -d)`` to measure that.
"""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

from .errors import AMRError

DEFAULT_SCENE = Path(__file__).resolve().parent.parent / "scenes_xml" / "sphere_wake.xml"


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


def _key(params, name):
    """The scene-parameter key ending in ``.name``."""
    for k in params.keys():
        if k.split(".")[-1] == name:
            return k
    raise AMRError(f"the scene has no parameter '{name}'")


def _camera_key(params):
    """Key of the camera's ``to_world`` (the object that also has ``x_fov``)."""
    prefix = _key(params, "x_fov").rsplit(".", 1)[0]
    return f"{prefix}.to_world"


def frame_timings(scene_path=DEFAULT_SCENE, *, resolution=(1024, 1024), defines=None,
                  frames: int = 5, variant: str = "llvm_ad_rgb") -> dict:
    """Time a scene: load, first frame (kernel compilation), warm frames (median), a frame after
    changing the isovalue and one after moving the camera (both should compile nothing)."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(variant)
    from .integrator import load_scene, register

    register()
    params = {"resx": str(resolution[0]), "resy": str(resolution[1]), "spp": "1"}
    params.update(defines or {})
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    t0 = time.perf_counter()
    scene = load_scene(scene_path, **params)
    load = time.perf_counter() - t0
    first, first_compiled, _ = _frame(mi, dr, scene, 0)
    warm = [_frame(mi, dr, scene, i + 1) for i in range(frames)]
    p = mi.traverse(scene)
    iso_key = _key(p, "isovalue")
    iso = p[iso_key]
    p[iso_key] = iso * 1.1
    p.update()
    new_iso = _frame(mi, dr, scene, 100)
    p[iso_key] = iso
    cam_key = _camera_key(p)
    p[cam_key] = mi.Transform4f().translate([0.05, 0.0, 0.0]) @ p[cam_key]
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
        print(f"timing {DEFAULT_SCENE.name} with {defines} ...", flush=True)
        results.append(frame_timings(DEFAULT_SCENE, resolution=resolution, defines=defines,
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
