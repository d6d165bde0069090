"""Arbitrary output variables of the isosurface (Mitsuba's ``aov_names()`` mechanism), reported
by ``amr_iso`` when its ``aovs`` parameter is true, for the first isosurface crossing along the
ray through each pixel's centre (in volume mode: the first crossing of a band's centre, an
isovalue):

=================  =====================================================================
channel            value (where that ray meets no isosurface in front of the meshes: depth
                   ``inf``, the other channels 0)
=================  =====================================================================
``iso_depth.T``    the ray's parameter at the hit: the distance along a unit camera ray
``iso_normal.X/Y/Z`` the shading normal (scene space, towards the viewer)
``iso_pos.X/Y/Z``  the hit point (scene space)
``iso_value.V``    the reconstructed field there (field units)
``iso_color.V``    the reconstructed colour field there
``iso_level.L``    the AMR level of the finest grid there (an exact whole number)
``iso_grid.G``     that grid's index in the volume (an exact whole number, as a float)
=================  =====================================================================

The AOVs are not filtered: the film's pixel filter (Gaussian by default) would blend
neighbouring pixels' labels into numbers such as 61.27 and a hit's depth with a miss. Each pixel
holds the values of one ray through its centre, the same at every sample count and seed, so a
level or grid id is exact and a depth is the surface's. (Vectorised variants; on scalar
variants the AOVs are the film's filtered samples, with depth 0 where nothing was hit.)

The film also gets alpha: the coverage of the pixel by any surface (isosurface, opacity band
or mesh), filtered like the colour; see :meth:`~mi_amr.plugin.integrator` ``sample``.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_amr.kernels.device import NO_GRID
from mi_amr.kernels.reconstruct import locate, reconstruct
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.surface import first_crossing
from mi_amr.plugin import bridge, shading

NAMES = ["iso_depth.T", "iso_normal.X", "iso_normal.Y", "iso_normal.Z", "iso_pos.X",
         "iso_pos.Y", "iso_pos.Z", "iso_value.V", "iso_color.V", "iso_level.L", "iso_grid.G"]



def alpha(mode: str, si, T, active, lanes):
    """A sample's alpha: the coverage by surfaces (a mask: the environment behind counts as
    empty; with stochastic layers, the share of samples that stop at a layer, 1 - T on
    average), or in volume mode under the integrator's own render loop (``lanes`` given) the
    opacity ``1 - T`` of the bands (a Float; 1 where a mesh lies behind), which that loop
    writes as it is (Mitsuba's loop takes a mask)."""
    if lanes is not None and mode == "volume":
        return dr.select(active, dr.select(si.is_valid(), 1.0, 1.0 - T), 0.0)
    return active & (si.is_valid() | (T < 1.0))

def iso_aovs(integ, ray, o, d, t_mesh, jitter, active, miss_depth=0.0) -> list:
    """The values of :data:`NAMES` for the rays (Mitsuba floats), from the integrator
    ``integ``'s kernels; ``o``, ``d``: the rays in volume space; ``miss_depth``: the depth
    where a ray meets no isosurface."""
    m, dev = integ.m, integ.dev
    cfg = integ.config()
    if cfg.band is not None:
        cfg = type(cfg)(method=cfg.method, basis=cfg.basis, isovalues=cfg.isovalues,
                        step_scale=cfg.step_scale, num_iso=cfg.num_iso, search=cfg.search)
    c = first_crossing(RayContext(dev, cfg, o, d, m.Float(0.0), bridge.to_kernel(m, t_mesh),
                                  m.Bool(active)), jitter)
    hit = c.hit
    p = dr.fma(d, c.t, o)
    vals, grad = reconstruct(dev, cfg.basis, p, dev.arrays(cfg.basis, color=True), hit)
    leaf = locate(dev, p, hit)
    grid = dr.gather(m.UInt32, dev.leaf_owner, leaf, hit)
    owned = hit & (grid != NO_GRID)
    level = dr.gather(m.UInt32, dev.grid_level, grid, owned)
    n = shading.facing_normal(integ.frame.to_scene, bridge.to_mi3(grad, mi.Normal3f), ray.d)
    t = bridge.to_mi(c.t, mi.Float)
    on = bridge.to_mi(hit, mi.Bool)
    P = ray(t)

    def out(x):
        return dr.select(on, mi.Float(x), 0.0)

    return [dr.select(on, t, miss_depth), out(n.x), out(n.y), out(n.z),
            out(P.x), out(P.y), out(P.z),
            out(bridge.to_mi(vals[0], mi.Float)), out(bridge.to_mi(vals[1], mi.Float)),
            out(bridge.to_mi(m.Float(level), mi.Float)),
            dr.select(bridge.to_mi(owned, mi.Bool), bridge.to_mi(m.Float(grid), mi.Float), 0.0)]


def unfiltered(integ, scene, sensor, image, evaluate: bool) -> None:
    """After a frame of ``integ`` with ``aovs`` on a JIT variant: its AOV channels replaced by
    :func:`centre_aovs` (the film's filter would blend labels), evaluated if ``evaluate``."""
    if not integ.opt.aovs or image is None or not dr.is_jit_v(mi.Float):
        return
    centre_aovs(integ, scene, sensor, image)
    if evaluate:
        dr.eval(image)
        dr.sync_thread()


def centre_aovs(integ, scene, sensor, image):
    """Write :data:`NAMES` into the last channels of the developed film ``image`` (a
    ``TensorXf`` of shape ``(H, W, C)``, the film's crop) in place: the values of the ray
    through each pixel's centre (crop pixel ``(x, y)`` at film position ``(x + 1/2, y + 1/2)``
    plus the crop offset), depth ``inf`` where it meets no isosurface. Unfiltered, so labels
    stay whole numbers; deterministic (no sample number is drawn). Returns ``image``."""
    film = sensor.film()
    width, height = (int(v) for v in film.crop_size())
    idx = dr.arange(mi.UInt32, width * height)
    y = idx // width
    x = idx - y * width
    # The sensor takes positions relative to the crop window, in [0, 1]^2 (as Mitsuba's loop).
    pos = mi.Point2f((mi.Float(x) + 0.5) / width, (mi.Float(y) + 0.5) / height)
    ray, _ = sensor.sample_ray(mi.Float(sensor.shutter_open()), 0.0, pos, mi.Point2f(0.5))
    active = mi.Bool(True)
    si = scene.ray_intersect(ray, active)
    t_mesh = dr.select(si.is_valid(), si.t, dr.inf)
    o, d = integ.frame.ray_to_volume(integ.m, ray.o, ray.d)
    values = iso_aovs(integ, ray, o, d, t_mesh, integ.m.Float(0.5), active,
                      miss_depth=dr.inf)
    channels = image.shape[2]
    first = channels - len(NAMES)
    flat = image.array
    for k, v in enumerate(values):
        dr.scatter(flat, v, idx * channels + (first + k))
    return image
