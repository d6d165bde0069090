"""Rendering a scene file to an image, with progress and timings (used by the command line)."""

from __future__ import annotations

import time
from pathlib import Path

from mi_amr.core.atomic import check_output, replacing
from mi_amr.errors import AMRError

IMAGE_TYPES = (".png", ".exr")
# libpng refuses wider or taller images (its default user limit), after the render has run.
PNG_MAX_SIDE = 1_000_000


def render_file(scene_path, output, *, spp=None, resolution=None, defines=None,
                variant: str = "llvm_ad_rgb", overwrite: bool = False, quiet: bool = False):
    """Render ``scene_path`` to ``output`` (.png: 8-bit sRGB; .exr: linear float) and return the
    image as a NumPy array. ``spp`` and ``resolution`` override the scene's ``spp``, ``resx``
    and ``resy`` defaults; ``defines`` sets other ``<default>`` values. Prints what it does and
    how long each part took (scene load, first frame with kernel compilation). The output path
    is checked before anything else, and the image is written atomically: a failed write leaves
    an existing ``output`` as it was."""
    output = Path(output)
    if output.suffix.lower() not in IMAGE_TYPES:
        raise AMRError(f"{output}: the image must end in {' or '.join(IMAGE_TYPES)}")
    check_output(output, overwrite=overwrite, make_folders=True)
    if spp is not None and spp < 1:
        raise AMRError(f"--spp must be >= 1, got {spp}")
    if resolution is not None and min(resolution) < 1:
        raise AMRError(f"--resolution must be positive, got {resolution}")
    if resolution is not None:
        _check_png_size(output, resolution)
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    if variant not in mi.variants():
        raise AMRError(f"variant '{variant}' is not available; choose from {mi.variants()}")
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import load_scene

    register()
    params = dict(defines or {})
    if spp is not None:
        params["spp"] = str(spp)
    if resolution is not None:
        params["resx"], params["resy"] = str(resolution[0]), str(resolution[1])
    t0 = time.perf_counter()
    say(f"loading {scene_path} ({variant})")
    scene = load_scene(scene_path, **params)
    t1 = time.perf_counter()
    sensor = scene.sensors()[0]
    total_spp = sensor.sampler().sample_count()
    size = sensor.film().size()
    _check_png_size(output, size)
    say(f"  scene ready in {t1 - t0:.1f} s; rendering {size[0]}x{size[1]} at {total_spp} spp")
    # Many samples per pixel go in passes, so progress can be shown and memory stays bounded.
    passes = max(1, min(total_spp, (total_spp + 15) // 16))
    per_pass = [total_spp // passes + (1 if i < total_spp % passes else 0) for i in range(passes)]
    from tqdm import tqdm

    accum = None
    bar = tqdm(total=total_spp, unit="spp", disable=quiet or passes == 1, leave=False)
    for i, n in enumerate(per_pass):
        img = mi.render(scene, spp=n, seed=i)
        dr.eval(img)
        dr.sync_thread()
        part = np.array(img) * n
        accum = part if accum is None else accum + part
        bar.update(n)
    bar.close()
    image = accum / total_spp
    t2 = time.perf_counter()
    _write_image(mi, image.astype(np.float32), output)
    say(f"  rendered in {t2 - t1:.2f} s (includes compiling the kernels on first use)")
    say(f"wrote {output.resolve()}  [total {t2 - t0:.1f} s]")
    if not np.all(np.isfinite(image)):
        raise AMRError(f"{output}: the image has NaN/Inf pixels; this is a bug, please report it")
    return image


def _check_png_size(output: Path, size) -> None:
    if output.suffix.lower() == ".png" and max(size) > PNG_MAX_SIDE:
        raise AMRError(f"{output}: a PNG image can be at most {PNG_MAX_SIDE:,} pixels a side "
                       f"(libpng), the image is {size[0]}x{size[1]}; write an .exr instead")


def _write_image(mi, image, output: Path) -> None:
    """Write ``image`` (linear RGB, float32) to ``output`` through a temporary file of the same
    type in the same folder (Mitsuba picks the format from the extension), then rename it."""
    output.parent.mkdir(parents=True, exist_ok=True)
    bitmap = mi.Bitmap(image, pixel_format=mi.Bitmap.PixelFormat.RGB)
    if output.suffix.lower() == ".png":
        bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    try:
        with replacing(output) as tmp:
            bitmap.write(str(tmp))
    except (RuntimeError, OSError) as e:
        raise AMRError(f"{output}: cannot write the image ({str(e).strip()}); "
                       f"any existing file is unchanged") from None
