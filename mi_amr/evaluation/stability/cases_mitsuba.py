"""The stability suite's Mitsuba cases: whole frames rendered by the plugin's integrator (a
camera inside the ball, an isovalue outside the data range, a camera orbit rendered twice with
different jitter). Their rows have no ray reference: ``missed`` and ``false`` are ``None``
except where no ray may be hit at all. Each ``case_*(quick)`` returns its rows; ``quick`` uses
smaller images (and, for sphere_wake, the ``small`` dataset).

Positions are the scene's world space unless said; times are wall-clock seconds around
``mi.render`` followed by ``dr.eval`` and ``dr.sync_thread``; depths are in finest cells.
"""

from __future__ import annotations

import time

import numpy as np

from mi_amr.evaluation.stability.cases_rays import random_rays
from mi_amr.evaluation.stability.scoring import row
from mi_amr.kernels.trace import trace
from mi_amr.params import METHODS
from mi_amr.synthetic import datasets


def _mitsuba(variant="llvm_ad_rgb"):
    """Mitsuba set to ``variant`` (when it is not already) with the plugin registered."""
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    return mi


def _camera_key(params):
    """Key of the camera's ``to_world`` among the scene's parameters (the object with
    ``x_fov``)."""
    return [k for k in params.keys() if k.endswith("to_world") and
            k.rsplit(".", 1)[0] + ".x_fov" in params][0]


def _render(mi, scene, seed=0):
    """One frame at 1 spp, evaluated and synchronised; float64 ``(H, W, C)``."""
    import drjit as dr

    img = mi.render(scene, spp=1, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return np.array(img, dtype=np.float64)


def _scene_file(name, quick, folder=None):
    """``scenes_xml/NAME.xml`` after :func:`mi_amr.workflows.project.ensure_scene_data`; for
    a quick sphere_wake, a copy of that file in ``folder`` reading the ``small`` dataset
    instead of the default one, whose preparation alone (some 13 s) takes a good part of the
    quick version's minute."""
    from pathlib import Path

    from mi_amr.workflows import project
    from mi_amr.evaluation.references import scene_path

    project.ensure_scene_data(verbose=False)
    path = scene_path(name)
    if name != "sphere_wake" or not quick:
        return path
    folder = Path(folder)
    data = folder / "sphere_wake_small.npz"
    datasets.sphere_wake("small", progress=False).save(data)
    text = path.read_text()
    for stored, target in (("data/sphere_wake.npz", data.resolve()),
                           ("data/ball.ply", (path.parent / "data" / "ball.ply").resolve())):
        text = text.replace(f'value="{stored}"', f'value="{target}"')
    copy = folder / "sphere_wake.xml"
    copy.write_text(text)
    return copy


def case_inside_ball(quick):
    """The sphere_wake scene with the camera inside the ball (at its centre looking
    downstream, and off-centre looking back), moved through ``mi.traverse``: the render
    completes and every pixel is finite. (Quick: the scene file reads the ``small``
    dataset, see :func:`_scene_file`.)"""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="mi_amr_stability_") as folder:
        return _inside_ball(_scene_file("sphere_wake", quick, folder), 16 if quick else 48)


def _inside_ball(path, res):
    """The rows of :func:`case_inside_ball` for the scene file ``path`` at ``res x res``
    pixels: per method, two cameras inside the ball (world space), non-finite pixel values
    counted."""
    mi = _mitsuba()
    from mi_amr.plugin.scene import load_scene

    rows = []
    for method in METHODS:
        t0 = time.perf_counter()
        scene = load_scene(path, resx=res, resy=res, spp=1, method=method)
        params = mi.traverse(scene)
        key = _camera_key(params)
        bad = 0
        lit = []
        for origin, target in (((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
                               ((0.1, 0.05, -0.05), (-1.0, 0.2, 0.1))):
            params[key] = mi.Transform4f(mi.ScalarTransform4f().look_at(
                origin=origin, target=target, up=(0, 0, 1)))
            params.update()
            img = _render(mi, scene)
            bad += int(np.sum(~np.isfinite(img)))
            lit.append(float(np.mean(img)))
        seconds = time.perf_counter() - t0
        data = "default data" if path.parent.name == "scenes_xml" else "copy, small data"
        notes = (f"{path.name} ({data}), {res}x{res}, 2 cameras; mean radiance "
                 + ", ".join(f"{x:.3g}" for x in lit))
        if bad:
            notes += f"; {bad} non-finite pixel values"
        rows.append(row("inside: camera inside the ball (sphere_wake)", method, "basis",
                        2 * res * res, None, None, None, notes,
                        metrics={"nonfinite": bad, "mean": lit, "seconds": seconds,
                                 "headline": "finite" if bad == 0 else f"{bad} NaN"}))
    return rows


def case_out_of_range(quick):
    """Isovalues above and below the sphere's data range: no ray is hit (every method), and a
    frame of the analytic sphere scene costs a small fraction of a normal frame (timed after
    a warm-up frame, with the isovalue changed through ``mi.traverse``, no recompilation)."""
    vol = datasets.sphere()
    vmin, vmax = vol.value_range("f")
    rng = np.random.default_rng(71)
    o, d = random_rays(rng, 256, 0.45)
    rows = []
    mi = _mitsuba()
    from mi_amr.plugin.scene import load_scene

    path = _scene_file("analytic_sphere", quick)
    res = 384 if quick else 512
    frames = 3
    for method in METHODS:
        hits = 0
        for iso in (vmax + 1.0, vmin - 1.0):
            for rec in ("basis", "finest"):
                r = trace(vol, o, d, field="f", isovalue=iso, method=method, reconstruction=rec)
                hits += int(r.hit.sum())
        scene = load_scene(path, resx=res, resy=res, spp=1, method=method)
        params = mi.traverse(scene)
        times = {}
        images = {}
        for label, iso in (("normal", datasets.ISOVALUES["sphere"]), ("out", vmax + 1.0)):
            params["integrator.isovalue"] = mi.Float([iso])
            params.update()
            _render(mi, scene)              # warm-up: compile, or reuse the kernel
            t0 = time.perf_counter()
            for k in range(frames):
                images[label] = _render(mi, scene, seed=k + 1)
            times[label] = (time.perf_counter() - t0) / frames
        ratio = times["out"] / times["normal"]
        # Nothing but the background: no pixel of the out-of-range frame is lit.
        blank = bool(np.all(images["out"] == 0.0))
        notes = (f"{4 * len(o)} rays + {res}x{res} frame; frame {times['out'] * 1e3:.1f} ms vs "
                 f"{times['normal'] * 1e3:.1f} ms (ratio {ratio:.2f}); image "
                 f"{'blank' if blank else 'NOT blank'}")
        rows.append(row("iso outside the data range", method, "both", 4 * len(o), 0, hits, 0.0,
                        notes, expected=0,
                        metrics={"frame_ratio": ratio, "frame_ms": times["out"] * 1e3,
                                 "normal_ms": times["normal"] * 1e3, "blank": blank,
                                 "headline": f"{hits} hits, {'blank' if blank else 'NOT blank'},"
                                             f" frame x{ratio:.2f}"}))
    return rows


def _orbit(t, radius=1.75, height=1.0):
    """Camera position (world) at ``t`` turns of the orbit around the cube's centre, ``radius``
    away in the xy plane and ``height`` above it."""
    a = 2 * np.pi * t
    return (0.5 + radius * np.cos(a), 0.5 + radius * np.sin(a), 0.5 + height)


def case_temporal(quick):
    """A 16-frame camera orbit around the analytic torus (22.5 degrees per frame). Camera rays
    through the pixel centres come from the scene's sensor, moved through ``mi.traverse``
    (:func:`_orbit_rays`); all frames' rays then go through the integrator at once, twice, with
    different jitter (sampler seeds 1 and 2, :func:`_jittered_frames`): its hit depths (its
    kernels, as in :func:`mi_amr.evaluation.references.hit_buffers`) and its shaded colours
    (its ``sample``) must not change for exact, the jittered methods flicker. Also the
    fraction of pixels whose hit mask changes between consecutive frames
    (:func:`_flicker_metrics`)."""
    mi = _mitsuba()
    from mi_amr.plugin.scene import load_scene

    path = _scene_file("analytic_torus", quick)
    res = 48 if quick else 96
    frames = 16
    n = res * res
    rows = []
    for method in METHODS:
        scene = load_scene(path, resx=res, resy=res, spp=1, method=method)
        integ = scene.integrator()
        cell = integ.dev.min_h_host
        ray = _orbit_rays(mi, scene, res, frames)
        o, dv = integ.frame.ray_to_volume(integ.m, ray.o, ray.d)
        (h1, t1, i1), (h2, t2, i2) = (_jittered_frames(mi, scene, ray, o, dv, frames, n, seed)
                                      for seed in (1, 2))
        metrics = _flicker_metrics(h1, t1, i1, h2, t2, i2, cell)
        notes = _temporal_notes(metrics, frames, res)
        metrics["headline"] = f"flicker {100 * metrics['flicker_pixels']:.2f}% px"
        rows.append(row("temporal: torus orbit, two jitters per frame", method, "basis",
                        frames * n, None, None, None, notes, metrics=metrics))
    return rows


def _orbit_rays(mi, scene, res, frames):
    """The camera rays through the pixel centres of ``frames`` positions of the orbit
    (:func:`_orbit`, world space, looking at the cube's centre), frame after frame, each
    ``res x res`` pixels row by row: one ``mi.Ray3f`` of ``frames * res^2`` rays (float32),
    from the scene's sensor moved through ``mi.traverse``."""
    import drjit as dr

    sensor = scene.sensors()[0]
    params = mi.traverse(scene)
    key = _camera_key(params)
    n = res * res
    idx = dr.arange(mi.UInt32, n)
    pos = mi.Vector2f(mi.Float(idx % res) + 0.5, mi.Float(idx // res) + 0.5) / res
    origins, directions = [], []
    for f in range(frames):
        params[key] = mi.Transform4f(mi.ScalarTransform4f().look_at(
            origin=_orbit(f / frames), target=(0.5, 0.5, 0.5), up=(0, 0, 1)))
        params.update()
        ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), pos, mi.Point2f(0.5, 0.5))
        origins.append(np.array(ray.o).T)        # Mitsuba's arrays are (3, N)
        directions.append(np.array(ray.d).T)
    o_np = np.concatenate(origins).astype(np.float32)
    d_np = np.concatenate(directions).astype(np.float32)
    return mi.Ray3f(mi.Point3f(o_np[:, 0], o_np[:, 1], o_np[:, 2]),
                    mi.Vector3f(d_np[:, 0], d_np[:, 1], d_np[:, 2]))


def _jittered_frames(mi, scene, ray, o, dv, frames, n, seed):
    """The integrator on all the orbit's rays (``ray``, world; ``o``, ``dv``: the same in the
    volume's space) with the jitter of sampler seed ``seed``: the first crossing of its
    kernels and the colour of its ``sample``. Returns ``(hit, t, image)`` per frame and pixel,
    shapes ``(frames, n)``, ``(frames, n)`` (volume-space ray parameter, inf where no hit) and
    ``(frames, n, 3)`` (linear RGB)."""
    import drjit as dr

    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.surface import first_crossing

    integ = scene.integrator()
    sensor = scene.sensors()[0]
    m = integ.m
    sampler = sensor.sampler().fork()
    sampler.seed(seed, frames * n)
    jitter = m.Float(sampler.next_1d())
    c = first_crossing(RayContext(integ.dev, integ.config(), o, dv, m.Float(0.0),
                                  m.Float(dr.inf), m.Bool(True)), jitter)
    sampler = sensor.sampler().fork()
    sampler.seed(seed, frames * n)
    L, _, _ = integ.sample(scene, sampler, ray)
    dr.eval(c.t, c.hit, L)
    hit = c.hit.numpy().astype(bool).reshape(frames, n)
    t = np.where(hit, c.t.numpy().reshape(frames, n), np.inf)
    img = np.stack([L.x.numpy(), L.y.numpy(), L.z.numpy()], axis=-1).reshape(frames, n, 3)
    return hit, t, img


def _flicker_metrics(h1, t1, i1, h2, t2, i2, cell) -> dict:
    """How two jitters' frames (hit masks ``h``, depths ``t`` in volume units, images ``i``;
    see :func:`_jittered_frames`) differ: the share of pixels whose hit or depth changes, the
    depth change there in finest cells (``cell``: the finest cell, volume units), the mean
    image difference, whether every pixel is finite, the share of pixels whose hit mask
    changes between consecutive frames (first jitter), and the share of pixels hit."""
    both = h1 & h2
    changed = (h1 != h2) | (both & (t1 != t2))
    depth = np.abs(np.where(both, t1, 0.0) - np.where(both, t2, 0.0)) / cell
    finite = bool(np.all(np.isfinite(i1)) and np.all(np.isfinite(i2)))
    mask_change = np.mean(h1 != np.roll(h1, -1, axis=0), axis=1)
    return {"flicker_pixels": float(changed.mean()),
            "flicker_depth_cells": float(depth[changed & both].mean())
            if np.any(changed & both) else 0.0,
            "flicker_depth_max_cells": float(depth.max()),
            "flicker_image": float(np.abs(i1 - i2).mean()),
            "images_finite": finite,
            "mask_change_mean": float(mask_change.mean()),
            "mask_change_max": float(mask_change.max()),
            "hit_fraction": float(h1.mean())}


def _temporal_notes(metrics, frames, res) -> str:
    """The temporal row's notes from :func:`_flicker_metrics`' numbers."""
    notes = (f"{frames} frames {res}x{res}: two jitters differ on "
             f"{100 * metrics['flicker_pixels']:.2f}% of pixels (depth change there "
             f"{metrics['flicker_depth_cells']:.3g} cells on average, at most "
             f"{metrics['flicker_depth_max_cells']:.3g}; image "
             f"{metrics['flicker_image']:.3g}); consecutive frames' hit masks change on "
             f"{100 * metrics['mask_change_mean']:.1f}% (max "
             f"{100 * metrics['mask_change_max']:.1f}%)")
    if not metrics["images_finite"]:
        notes += "; NON-FINITE pixels"
    return notes
