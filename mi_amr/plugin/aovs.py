"""Arbitrary output variables of the isosurface (Mitsuba's ``aov_names()`` mechanism), reported
by ``amr_iso`` when its ``aovs`` parameter is true, for the first isosurface crossing along each
camera ray (in volume mode: the first crossing of a band's centre, an isovalue):

=================  =====================================================================
channel            value (0 where the ray meets no isosurface in front of the meshes)
=================  =====================================================================
``iso_depth.T``    the ray's parameter at the hit: the distance along a unit camera ray
``iso_normal.X/Y/Z`` the shading normal (scene space, towards the viewer)
``iso_pos.X/Y/Z``  the hit point (scene space)
``iso_value.V``    the reconstructed field there (field units)
``iso_color.V``    the reconstructed colour field there
``iso_level.L``    the AMR level of the finest grid there
``iso_grid.G``     that grid's index in the volume (as a float)
=================  =====================================================================

The film also gets alpha: the coverage of the pixel by any surface (isosurface, opacity band
or mesh); see :meth:`~mi_amr.plugin.integrator` ``sample``.
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


def iso_aovs(integ, ray, o, d, t_mesh, jitter, active) -> list:
    """The values of :data:`NAMES` for the rays (Mitsuba floats), from the integrator
    ``integ``'s kernels; ``o``, ``d``: the rays in volume space."""
    m, dev = integ.m, integ.dev
    cfg = integ.config()
    if cfg.band is not None:
        cfg = type(cfg)(method=cfg.method, basis=cfg.basis, isovalues=cfg.isovalues,
                        step_scale=cfg.step_scale, num_iso=cfg.num_iso)
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

    return [out(t), out(n.x), out(n.y), out(n.z), out(P.x), out(P.y), out(P.z),
            out(bridge.to_mi(vals[0], mi.Float)), out(bridge.to_mi(vals[1], mi.Float)),
            out(bridge.to_mi(m.Float(level), mi.Float)),
            dr.select(bridge.to_mi(owned, mi.Bool), bridge.to_mi(m.Float(grid), mi.Float), 0.0)]
