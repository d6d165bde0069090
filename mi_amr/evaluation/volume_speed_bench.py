"""``python -m mi_amr bench --volume --speed``: volume mode's frames beside surface mode's and
beside yt's volume renderer.

One run, one process: each scene of :data:`SCENES` at each of :data:`RESOLUTIONS` (square
images), 1 spp, seed 0 for the first frame (compilation, the shadow caches' build) and the
median of :data:`FRAMES` warm frames after it, in seconds; each warm frame is also given as a
multiple of surface mode's frame and of the one-band frame at the same size, beside the mean
pieces that the march walks along a camera ray (:func:`walked_per_ray`), which a frame's cost
follows.

yt's volume renderer (when yt is installed; ``yt.create_scene`` with a perspective lens, as yt's
users set it up) renders the same grids of the same field from the same camera at the same
size, with one Gaussian per band of the scene (the band's isovalue, width and colour; its height
the band's peak extinction over the ray's length), no lighting and no other shapes. Its first
render builds yt's bricks; the second is its warm frame. Compare ratios within one run only.

Writes ``volume_speed.md`` and ``volume_speed.json``.
"""

from __future__ import annotations

import json
import math
import statistics
import time
from pathlib import Path

import numpy as np

from mi_amr import tolerances as tol
from mi_amr.workflows import project

# The shells' lowest band (Q = 0.02) on its own: the three bands' cost against the one that
# meets the most pieces.
LOWEST_BAND = {"band_width": "0.002", "band_peak": "0.15", "iso_color": "0.1 0.3 1.0"}
# The shells as opaque as the one-band scene's band (its peak, 1.6, for each): what their
# translucency costs, since a ray crosses every shell only where the ones in front let light
# through (the march ends at tolerances.T_MIN).
OPAQUE_SHELLS = {"band_peak": "1.6, 1.6, 1.6"}
CORRECTED = {"volume_shadows": "corrected"}
# (label, scene file stem, <default> values, integrator parameters); the volume scenes with the
# default shadows (volume_shadows="cache") and with the cache corrected by one exact shadow ray
# per camera sample
SCENES = (("surface mode", "sphere_wake", {}, {}),
          ("1 band", "sphere_wake_volume", {}, {}),
          ("1 band, corrected shadows", "sphere_wake_volume", {}, CORRECTED),
          ("3 bands", "sphere_wake_shells", {}, {}),
          ("3 bands, corrected shadows", "sphere_wake_shells", {}, CORRECTED),
          ("3 bands' lowest alone", "sphere_wake_shells", {"isovalue": "0.02"}, LOWEST_BAND),
          ("3 bands, each at 1 band's peak", "sphere_wake_shells", {}, OPAQUE_SHELLS),
          ("3 bands, shadows off", "sphere_wake_shells", {"shadows": "false"}, {}),
          ("2D transfer function", "sphere_wake_tf2d", {}, {}))
YT_SCENES = ("1 band", "3 bands")
RESOLUTIONS = (256, 1024)
FRAMES = 3
QUICK = {"resolutions": (32,), "frames": 1, "yt_scenes": ("3 bands",)}
YT_BIN_WIDTHS = 4          # yt's transfer-function bins per band width (its narrowest)
YT_MAX_BINS = 2 ** 18


def volume_speed(out_dir="out/bench", *, quick: bool = False, variant: str = "llvm_ad_rgb",
                 progress: bool = True) -> list:
    """Time every scene at every size, yt beside (see the module docstring); write
    ``volume_speed.md`` and ``volume_speed.json`` into ``out_dir`` and return the rows."""
    from tqdm import tqdm

    from mi_amr.plugin.scene import use_variant

    use_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    project.ensure_scene_data(verbose=progress)
    sizes = QUICK["resolutions"] if quick else RESOLUTIONS
    frames = QUICK["frames"] if quick else FRAMES
    with_yt = QUICK["yt_scenes"] if quick else YT_SCENES
    bar = tqdm(total=len(sizes) * (len(SCENES) + len(with_yt)), desc="bench --volume --speed",
               unit="row", disable=not progress)
    rows = []
    for res in sizes:
        for label, name, defines, integrator in SCENES:
            row, scene = _mi_amr_row(label, name, (defines, integrator), res, frames)
            rows.append(row)
            bar.update()
            if label in with_yt:
                rows.append(_yt_row(label, scene, res))
                bar.update()
            del scene
    bar.close()
    _relate(rows)
    write_results(rows, Path(out_dir), frames)
    return rows


def _frame(scene, seed: int) -> float:
    import drjit as dr
    import mitsuba as mi

    t0 = time.perf_counter()
    img = mi.render(scene, seed=seed, spp=1)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0


def _mi_amr_row(label, name, edits, res, frames):
    """The row of one scene at ``res`` x ``res`` (``edits``: its ``<default>`` values and
    integrator parameters), and the loaded scene."""
    from mi_amr.plugin.scene import load_scene

    defines, integrator = edits
    scene = load_scene(project.scenes_dir() / f"{name}.xml", resx=res, resy=res, spp=1,
                       integrator=integrator or None, **defines)
    first = _frame(scene, 0)
    warm = statistics.median(_frame(scene, seed) for seed in range(1, frames + 1))
    return {"renderer": "mi_amr", "scene": label, "file": f"{name}.xml", "size": res,
            "first_s": first, "frame_s": warm, "walked": walked_per_ray(scene)}, scene


def walked_per_ray(scene) -> float:
    """The march's mean work along a camera ray through each pixel centre of ``scene``: cubic
    pieces (``exact``) or samples (the sampling methods) up to the first crossing in surface
    mode, and in volume mode up to the ray's end or to where less than
    :data:`~mi_amr.tolerances.T_MIN` of the light gets through (the transmittance march,
    which a camera ray's compositing walks alike). Rays that miss the volume count 0."""
    from mi_amr.evaluation.references import pixel_rays
    from mi_amr.kernels.composite import composite
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.surface import first_crossing

    integ = scene.integrator()
    m = integ.m
    ray = pixel_rays(scene.sensors()[0])
    o, d = integ.frame.ray_to_volume(m, ray.o, ray.d)
    ctx = RayContext(integ.dev, integ.config(), o, d, m.Float(0.0), m.Float(math.inf),
                     m.Bool(True))
    march = composite if integ.opt.mode == "volume" else first_crossing
    return float(np.mean(march(ctx, m.Float(0.5)).samples.numpy()))


def _yt_row(label, scene, res) -> dict:
    """yt's row for the scene's grids and bands (``skipped`` when yt is not installed)."""
    row = {"renderer": "yt", "scene": label, "file": "", "size": res,
           "first_s": math.nan, "frame_s": math.nan}
    try:
        import yt
    except ImportError:
        return dict(row, skipped="yt is not installed")
    from mi_amr.evaluation import peers

    integ = scene.integrator()
    with peers.quiet_yt():
        # (yt's source holds its dataset by a weak reference: keep ds alive)
        ds, source, cam = _yt_scene(yt, peers, integ, scene.sensors()[0], res)
        t0 = time.perf_counter()
        source.render(cam)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        image = np.asarray(source.render(cam))
        warm = time.perf_counter() - t0
    del ds
    row.update(first_s=first, frame_s=warm, yt=yt.__version__,
               opaque_pixels=float(np.mean(image[..., 3] > 0.5)))
    return row


def _yt_scene(yt, peers, integ, sensor, res):
    """yt's dataset, volume source and camera for the integrator's volume, field and
    bands."""
    from yt.visualization.volume_rendering.api import ColorTransferFunction

    opt, vol, field = integ.opt, peers.field_volume(integ), integ.prep.field
    ds = peers.yt_dataset(yt, vol, field)
    sc = yt.create_scene(ds, field=("stream", field), lens_type="perspective")
    source = sc.get_source(0)
    source.log_field = False
    frame = peers.yt_camera(ds, sc.camera, sensor, peers.matrix(integ.frame.to_scene), res,
                            res)
    # yt's opacity per sample is its height times the sample's share of the whole ray: the
    # band's extinction (its peak per finest cell) times the ray's length, in volume units.
    ray_len = float(np.median(np.linalg.norm(frame["vp_dir"], axis=-1)))
    finest = float(vol.level_spacing(vol.num_levels - 1).min())
    vmin, vmax = vol.value_range(field)
    widths = [float(w) for w in opt.band_width]
    bins = int(min(YT_MAX_BINS, math.ceil((vmax - vmin) * YT_BIN_WIDTHS / min(widths))))
    tf = ColorTransferFunction((vmin, vmax), nbins=bins, grey_opacity=True)
    for iso, width, colour, peak in zip(opt.isovalues, widths, opt.iso_colors, opt.band_peak):
        height = -math.log1p(-min(float(peak), tol.OPACITY_CAP)) / finest * ray_len
        tf.add_gaussian(float(iso), 2.0 * width ** 2, list(colour) + [height])
    source.set_transfer_function(tf)
    return ds, source, sc.camera


def _relate(rows) -> None:
    """Each mi_amr row's warm frame over surface mode's and the one band's at its size; each
    yt row's over mi_amr's of the same scene and size."""
    def frame(renderer, scene, size):
        return next((r["frame_s"] for r in rows if (r["renderer"], r["scene"], r["size"]) ==
                     (renderer, scene, size)), math.nan)

    for r in rows:
        if r["renderer"] == "mi_amr":
            r["x_surface"] = r["frame_s"] / frame("mi_amr", "surface mode", r["size"])
            r["x_one_band"] = r["frame_s"] / frame("mi_amr", "1 band", r["size"])
        else:
            r["mi_amr_over_yt"] = frame("mi_amr", r["scene"], r["size"]) / r["frame_s"]


def speed_table(rows) -> str:
    """The rows as a Markdown table."""
    lines = ["| renderer | scene | size | first frame (s) | warm frame (s) | x surface mode "
             "| x 1 band | pieces walked a ray | mi_amr / yt |",
             "|---|---|---|---|---|---|---|---|---|"]

    def num(r, key, fmt):
        v = r.get(key, math.nan)
        return "-" if not np.isfinite(v) else fmt.format(v)

    for r in rows:
        name = r["file"] or r.get("skipped") or f"yt {r.get('yt', '')}, same grids and bands"
        lines.append(f"| {r['renderer']} | {r['scene']} ({name}) | {r['size']}x{r['size']} | "
                     f"{num(r, 'first_s', '{:.2f}')} | {num(r, 'frame_s', '{:.3f}')} | "
                     f"{num(r, 'x_surface', '{:.2f}')} | {num(r, 'x_one_band', '{:.2f}')} | "
                     f"{num(r, 'walked', '{:.1f}')} | {num(r, 'mi_amr_over_yt', '{:.2f}')} |")
    return "\n".join(lines)


def write_results(rows, out: Path, frames: int = FRAMES) -> None:
    """``volume_speed.md`` and ``volume_speed.json`` into ``out`` (made if missing), each
    written to a temporary file first and then renamed."""
    from mi_amr.core.atomic import replacing

    out.mkdir(parents=True, exist_ok=True)
    plural = "s" if frames > 1 else ""
    text = (f"Volume mode's warm frames beside surface mode's and yt's, 1 spp, median of "
            f"{frames} warm frame{plural}, one run; written by "
            f"`python -m mi_amr bench --volume --speed`.\n\n" + speed_table(rows) + "\n")
    with replacing(out / "volume_speed.md") as tmp:
        tmp.write_text(text)
    with replacing(out / "volume_speed.json") as tmp:
        tmp.write_text(json.dumps([{k: (None if isinstance(v, float) and not math.isfinite(v)
                                        else v) for k, v in r.items()} for r in rows],
                                  indent=1))
    print(speed_table(rows))
    print(f"wrote {out / 'volume_speed.md'} and {out / 'volume_speed.json'}")
