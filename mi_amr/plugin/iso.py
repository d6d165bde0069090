"""Colour and light of isosurface points: the kernels' reconstruction and colour map, and
Phong shading in the scene (:mod:`mi_amr.plugin.shading`)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_amr.kernels import colormap
from mi_amr.kernels.reconstruct import reconstruct
from mi_amr.plugin import bridge, shading


class IsoShader:
    """Shades the crossings of the integrator ``integ`` (its device volume, frame inputs and
    placement in the scene)."""

    def __init__(self, integ):
        self.integ = integ
        self.m = integ.m

    def color(self, k, value):
        """Colour (kernel ``Array3f``) of isovalue ``k`` at colour-field ``value``: the colour
        map where there is one, else the isovalue's colour."""
        m, inputs = self.m, self.integ.inputs
        if inputs.has_colormap:
            rng = dr.gather(m.Array2f, inputs["color_range"], m.UInt32(0))
            return colormap.lookup(m, inputs["colormap_values"], inputs["colormap_colors"], rng,
                                   m.Float(value))
        return dr.gather(m.Array3f, inputs["iso_color"], m.UInt32(k))

    def band_colors(self):
        """The ``color_of(shares, value)`` callback of the volume compositing: the colour map
        at the colour field's ``value``, else the isovalues' colours mixed by the bands'
        shares of the opacity."""
        m, k = self.m, len(self.integ.opt.isovalues)
        if self.integ.inputs.has_colormap or k == 1:
            return lambda shares, value: self.color(0, value)

        def mix(shares, value):
            out = m.Array3f(0.0)
            for i in range(k):
                out += shares[i] * self.color(i, value)
            return out

        return mix

    def light(self, scene, light_u, ray, t, grad, active):
        """``(A, S)`` (Mitsuba spectra) at the scene point ``ray(t)`` with volume-space
        gradient ``grad`` (kernel types in)."""
        integ = self.integ
        n = shading.facing_normal(integ.frame.to_scene, bridge.to_mi3(grad, mi.Normal3f), ray.d)
        return shading.iso_light(scene, light_u, ray, ray(t), n, integ.phong(), active,
                                 integ.shadows(), integ.iso_transmittance)

    def shade(self, scene, light_u, ray, o, d, c, k, hit):
        """Phong-shaded colour of the crossing ``c`` (kernel types) where ``hit``."""
        m, dev, integ = self.m, self.integ.dev, self.integ
        if not bridge.vectorised() and not hit:
            return mi.Spectrum(0.0)
        basis = integ.opt.reconstruction == "basis"
        vals, grad = reconstruct(dev, basis, o + d * c.t, dev.arrays(basis, color=True),
                                 m.Bool(hit))
        color = bridge.to_mi3(self.color(c.k, vals[1]), mi.Color3f)
        A, S = self.light(scene, light_u, ray, bridge.to_mi(c.t, mi.Float), grad, hit)
        return color * A + S

    def lighting(self, scene, light_u, ray, o, d):
        """The ``lighting(p, grad, lit)`` callback of the volume compositing: ``(A, S)`` as
        kernel arrays at volume point ``p``."""
        m = self.m
        ray_len = dr.norm(mi.Vector3f(d.x, d.y, d.z))

        def lighting(p, grad, lit):
            # Back from the volume point to the ray parameter: p = o + t d.
            t = mi.Float(dr.dot(p - o, d)) / (ray_len * ray_len)
            A, S = self.light(scene, light_u, ray, t, grad, mi.Bool(lit))
            return m.Array3f(A.x, A.y, A.z), m.Array3f(S.x, S.y, S.z)

        return lighting
