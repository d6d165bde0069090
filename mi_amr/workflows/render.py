"""Rendering a scene file to an image, with progress and timings (used by the command line)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from mi_amr.core.atomic import check_output, replacing
from mi_amr.errors import AMRError, did_you_mean

IMAGE_TYPES = (".png", ".exr")
# libpng refuses wider or taller images (its default user limit), after the render has run.
PNG_MAX_SIDE = 1_000_000
# Dr.Jit arrays hold fewer than 2^32 entries: a film's pixels times its channels, and its pixels
# times the samples of one pass, must stay below.
JIT_MAX_ENTRIES = 2 ** 32 - 1


def render_file(scene_path, output, *, spp=None, resolution=None, defines=None,
                variant: str = "llvm_ad_rgb", overwrite: bool = False, quiet: bool = False,
                aovs: bool = False, started: float | None = None):
    """Render ``scene_path`` to ``output`` (.png: 8-bit sRGB with alpha; .exr: linear float
    RGBA) and return the RGB image as a NumPy array. Alpha is the pixel's coverage by surfaces.
    ``aovs=True`` (.exr only) adds the isosurface's AOV channels (:mod:`mi_amr.plugin.aovs`).
    ``spp`` and ``resolution`` set the scene's sampler and film (whether or not it has
    ``spp``, ``resx`` and ``resy`` defaults); ``defines`` sets ``<default>`` values. Prints
    what it does and how long each part took (the scene's preparation step by step, the render
    with a progress bar). The output path is checked before anything else, and the image is
    written atomically: a failed write leaves an existing ``output`` as it was. ``started``:
    the :func:`time.perf_counter` at which the caller's work began (a data file's scene made
    first), from which the printed total counts; the load's start when None."""
    output = Path(output)
    params = _check_request(scene_path, output, spp, resolution, defines, overwrite, aovs)
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    from mi_amr.plugin.scene import load_scene, use_variant

    use_variant(variant)
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    from mi_amr.plugin.integrator import register

    preparations = register()
    t0 = time.perf_counter()
    say(f"loading {scene_path} ({variant})")
    preparations.report = None if quiet else say
    try:
        scene = load_scene(scene_path, integrator={"aovs": True} if aovs else None,
                           pixel_format="rgba", **params)
    finally:
        preparations.report = None
    t1 = time.perf_counter()
    sensor = scene.sensors()[0]
    size = sensor.film().size()
    _check_png_size(output, size)
    total_spp = sensor.sampler().sample_count()
    _check_film_entries(scene_path, size, len(_channels(scene, aovs)),
                        max(p.spp for p in scene_passes(scene, total_spp)))
    say(f"  scene ready in {t1 - t0:.1f} s; rendering {size[0]}x{size[1]} at {total_spp} spp")
    image = render_passes(mi, dr, np, scene, total_spp, quiet)
    t2 = time.perf_counter()
    _write_image(mi, image.astype(np.float32), output, _channels(scene, aovs))
    say(f"  rendered in {t2 - t1:.2f} s (includes compiling the kernels on first use)")
    say(f"wrote {output.resolve()}  [total {t2 - (t0 if started is None else started):.1f} s]")
    # (The AOVs' depth is inf where no isosurface was hit: only the colour must be finite.)
    if not np.all(np.isfinite(image[..., :4])):
        raise AMRError(f"{output}: the image has NaN/Inf pixels; this is a bug, please report it")
    return image[..., :3]


def check_image_request(output, spp=None, resolution=None, overwrite: bool = False,
                        aovs: bool = False) -> None:
    """The checks of an image request that need no scene (the output path (a
    :class:`~pathlib.Path`), the sample count, the size in pixels): done again by
    :func:`render_file`, and first by the command line before it makes a data file's scene."""
    if output.suffix.lower() not in IMAGE_TYPES:
        raise AMRError(f"{output}: the image must end in {' or '.join(IMAGE_TYPES)}")
    if aovs and output.suffix.lower() != ".exr":
        raise AMRError(f"{output}: --aovs writes a multichannel EXR; give a .exr output")
    check_output(output, overwrite=overwrite, make_folders=True)
    if spp is not None and spp < 1:
        raise AMRError(f"--spp must be >= 1, got {spp}")
    if resolution is not None and min(resolution) < 1:
        raise AMRError(f"--resolution must be positive, got {resolution}")
    if resolution is not None:
        _check_png_size(output, resolution)


def _check_request(scene_path, output, spp, resolution, defines, overwrite, aovs) -> dict:
    """The checks done before any work (output path, numbers, ``-D`` names against the
    scene's ``<default>``s); returns the scene parameters."""
    check_image_request(output, spp, resolution, overwrite, aovs)
    if resolution is not None:
        _check_film_entries(scene_path, resolution, 4, 1)
    params = dict(defines or {})
    _check_defines(scene_path, params)
    # Set on the film and sampler directly: a scene need not have spp/resx/resy defaults.
    return dict(params, film_size=None if resolution is None else tuple(resolution),
                sample_count=spp)


def _check_film_entries(scene_path, size, channels: int, pass_spp: int) -> None:
    """Refuse a film too large for one Dr.Jit array before rendering (else a raw error comes
    from deep inside the render)."""
    pixels = int(size[0]) * int(size[1])
    if pixels * max(channels, pass_spp) > JIT_MAX_ENTRIES:
        raise AMRError(f"{scene_path}: a {size[0]}x{size[1]} image with {channels} channels at "
                       f"{pass_spp} spp a pass is too large to render at once (Dr.Jit arrays "
                       f"hold fewer than 2^32 values); choose a smaller --resolution")


def _check_defines(scene_path, defines: dict) -> None:
    """Every ``-D`` name must be a ``<default>`` of the scene (else Mitsuba would report
    "unused parameters" after loading): an unknown name gets a did-you-mean."""
    import xml.etree.ElementTree as ET

    if not defines:
        return
    try:
        root = ET.parse(str(scene_path)).getroot()
    except (OSError, ET.ParseError):
        return                      # the scene loader reports an unreadable file
    known = [d.get("name") for d in root.iter("default")]
    for name in defines:
        if name not in known:
            raise AMRError(f"-D {name}: the scene {scene_path} has no default "
                           f"'{name}'{did_you_mean(name, known)}; "
                           f"it has {', '.join(known) or 'none'}")


STOCHASTIC_PASS_SPP = 4    # stochastic layers: samples a pass at least (see pass_samples)
MAX_PASSES = 16            # passes of an image, at most (more samples make larger passes)


@dataclass(frozen=True)
class Pass:
    """One pass of an image: ``spp`` samples a pixel drawn at ``seed``. Where ``count`` is
    not 0, the sampler stratifies a pixel's samples, and these are samples ``first .. first
    + spp - 1`` of the image's ``count``: the passes share the seed and together draw each
    stratum once (``amr_iso``'s ``render(..., part=(first, count))``)."""

    seed: int
    spp: int
    first: int = 0
    count: int = 0


def least_pass_spp(integrator) -> int:
    """Samples a pass at least for ``integrator``: :data:`STOCHASTIC_PASS_SPP` where its
    frames of 2 or more spp share the numbers that pick by SIMD packet (``amr_iso``'s
    ``picks_by_packet``, stochastic layers: faster, and stratified over a pixel's samples;
    frames of 1 spp keep a number per lane), else 1."""
    shares = getattr(integrator, "picks_by_packet", None)
    return STOCHASTIC_PASS_SPP if shares is not None and shares() else 1


def stratified_passes(total: int, least: int = 1) -> list:
    """The passes of a ``total``-spp image whose sampler stratifies: passes of ``q`` =
    ``ceil(total / MAX_PASSES)`` samples a pixel (one up to 16 spp; ``least`` at least, as
    :func:`pass_samples` takes it), all parts of one set at seed 0 as far as whole passes go,
    and what is left, fewer than ``q``, one more pass that is a set of its own (seed 1)."""
    q = min(max(-(-total // MAX_PASSES), least), total)
    whole = total - total % q
    return [Pass(0, q, first, whole) for first in range(0, whole, q)] + \
        ([Pass(1, total - whole, 0, total - whole)] if total > whole else [])


def scene_passes(scene, total: int) -> list:
    """The :class:`Pass` es of a ``total``-spp image of ``scene``: :func:`stratified_passes`
    where ``amr_iso`` renders it and the first sensor's sampler stratifies (any but Mitsuba's
    ``independent``), else :func:`pass_samples` at seeds 0, 1, ... The render workflow and the
    viewer's refinement both take these, so a scene the viewer saves renders to the same
    pixels."""
    integrator = scene.integrator()
    sampler = scene.sensors()[0].sampler()
    if hasattr(integrator, "picks_by_packet") and \
            sampler.class_name() != "IndependentSampler":
        return stratified_passes(total, least_pass_spp(integrator))
    return [Pass(seed, n) for seed, n in
            enumerate(pass_samples(total, least_pass_spp(integrator)))]


def render_pass(mi, scene, p: Pass):
    """``mi.render`` of pass ``p`` of ``scene`` (its first sensor): the developed image."""
    if p.count:
        return scene.integrator().render(scene, 0, p.seed, p.spp, True, True,
                                         part=(p.first, p.count))
    return mi.render(scene, spp=p.spp, seed=p.seed)


def pass_samples(total: int, least: int = 1) -> list:
    """Samples per pass of a ``total``-spp image drawn independently: passes of at most 16
    spp -- one sample a pass (``least`` a pass) up to :data:`MAX_PASSES` passes -- so a
    progress bar moves and memory stays bounded."""
    passes = max(min(-(-total // max(least, 1)), MAX_PASSES), -(-total // 16))
    return [total // passes + (1 if i < total % passes else 0) for i in range(passes)]


def render_passes(mi, dr, np, scene, total_spp, quiet):
    """The image (all film channels), rendered in the passes of :func:`scene_passes`: the
    colour and alpha averaged over the passes, the AOVs (the same every pass, unfiltered, see
    :mod:`mi_amr.plugin.aovs`) as the last pass gave them, whole numbers kept whole."""
    from tqdm import tqdm

    passes = scene_passes(scene, total_spp)
    accum = None
    with tqdm(total=total_spp, unit="spp", disable=quiet or len(passes) == 1,
              leave=False) as bar:
        for p in passes:
            img = render_pass(mi, scene, p)
            dr.eval(img)
            dr.sync_thread()
            last = np.array(img)
            part = last[..., :4] * p.spp
            accum = part if accum is None else accum + part
            bar.update(p.spp)
    return np.concatenate([accum / total_spp, last[..., 4:]], axis=-1)


def _channels(scene, aovs):
    """The film's channel names: R, G, B, A and with ``aovs`` the isovalue AOVs."""
    from mi_amr.plugin.aovs import NAMES

    return ["R", "G", "B", "A"] + (list(NAMES) if aovs else [])


def _check_png_size(output: Path, size) -> None:
    if output.suffix.lower() == ".png" and max(size) > PNG_MAX_SIDE:
        raise AMRError(f"{output}: a PNG image can be at most {PNG_MAX_SIDE:,} pixels a side "
                       f"(libpng), the image is {size[0]}x{size[1]}; write an .exr instead")


def _write_image(mi, image, output: Path, channels) -> None:
    """Write ``image`` (linear RGBA and maybe AOVs, float32) to ``output`` (PNG or EXR, by its
    extension) through a temporary file in the same folder, then rename it. PNG: 8-bit sRGB
    with alpha."""
    output.parent.mkdir(parents=True, exist_ok=True)
    if output.suffix.lower() == ".png":
        bitmap = mi.Bitmap(image[..., :4], pixel_format=mi.Bitmap.PixelFormat.RGBA)
        bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGBA, mi.Struct.Type.UInt8, srgb_gamma=True)
    elif len(channels) == 4:
        bitmap = mi.Bitmap(image, pixel_format=mi.Bitmap.PixelFormat.RGBA)
    else:
        bitmap = mi.Bitmap(image, pixel_format=mi.Bitmap.PixelFormat.MultiChannel,
                           channel_names=channels)
    fmt = mi.Bitmap.FileFormat.PNG if output.suffix.lower() == ".png" else \
        mi.Bitmap.FileFormat.OpenEXR
    try:
        # Encoded in memory, the bytes written by Python: Mitsuba's file writer does not
        # report a write the disk refuses (it would leave an empty image in the file's place).
        stream = mi.MemoryStream()
        bitmap.write(stream, fmt)
        data = stream.raw_buffer()
        with replacing(output) as tmp:
            tmp.write_bytes(data)
    except (RuntimeError, OSError) as e:
        raise AMRError(f"{output}: cannot write the image ({str(e).strip()}); "
                       f"any existing file is unchanged") from None
