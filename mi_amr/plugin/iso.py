"""Colour and light of isosurface points: the kernels' reconstruction and colour map, and
Phong shading in the scene (:mod:`mi_amr.plugin.shading`)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_amr.kernels import colormap
from mi_amr.kernels.composite import Shading, composite
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.reconstruct import reconstruct
from mi_amr.plugin import bridge, shading
from mi_amr.plugin.shadow_cache import CachedShadow


class IsoShader:
    """Shades the crossings of the integrator ``integ`` (its device volume, frame inputs and
    placement in the scene); ``transmittance(ray, from_iso, active)``: what the shadow rays of
    the frame's samples see (:meth:`iso_transmittance` of the integrator for those lanes)."""

    def __init__(self, integ, transmittance):
        self.integ = integ
        self.m = integ.m
        self.transmittance = transmittance

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
            def one(shares, value):
                return self.color(0, value)

            one.same_for_all_bands = True
            return one

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
        n = self.normal(grad, ray)
        return shading.iso_light(scene, light_u, ray, ray(t), n, integ.phong(), active,
                                 integ.shadows(), self.transmittance)

    def shade(self, scene, light_u, ray, o, d, c, k, hit):
        """Phong-shaded colour of the crossing ``c`` (kernel types) where ``hit``."""
        if not bridge.vectorised() and not hit:
            return mi.Spectrum(0.0)
        color, grad = self.surface_point(o, d, c, hit)
        A, S = self.light(scene, light_u, ray, bridge.to_mi(c.t, mi.Float), grad, hit)
        return color * A + S

    def shade_parts(self, scene, light_u, ray, o, d, c, hit):
        """:meth:`shade` with its shadow rays not yet traced: ``(base, parts)``, the ambient
        light ``base`` and per emitter ``(direct, shadow ray)``, so that ``shade`` is ``base +
        sum(direct * V)`` with each shadow ray's visibility ``V`` (Mitsuba types out)."""
        color, grad = self.surface_point(o, d, c, hit)
        P = ray(bridge.to_mi(c.t, mi.Float))
        A0, parts = shading.iso_light_parts(scene, light_u, ray, P, self.normal(grad, ray),
                                            self.integ.phong(), hit)
        return color * A0, [(color * p.diffuse + p.specular, p.shadow) for p in parts]

    def surface_point(self, o, d, c, hit):
        """``(colour, gradient)`` at the crossing ``c`` of the volume ray ``o + t d``: the
        colour as a Mitsuba colour, the volume-space gradient as a kernel ``Array3f``."""
        m, dev, integ = self.m, self.integ.dev, self.integ
        basis = integ.opt.reconstruction == "basis"
        vals, grad = reconstruct(dev, basis, o + d * c.t, dev.arrays(basis, color=True),
                                 m.Bool(hit))
        return bridge.to_mi3(self.color(c.k, vals[1]), mi.Color3f), grad

    def normal(self, grad, ray):
        """The shading normal (scene space, facing the viewer) of volume gradient ``grad``."""
        return shading.facing_normal(self.integ.frame.to_scene,
                                     bridge.to_mi3(grad, mi.Normal3f), ray.d)

    def volume(self, scene, light_u, ray, od_mesh, numbers, active):
        """Front-to-back compositing of the opacity band along the scene ray ``ray``, which
        is ``o + t d`` in the volume (``od_mesh``: ``(o, d, t_mesh)``), up to its mesh hit
        ``t_mesh``; ``numbers``: ``(jitter, pick_u)``, the sampling methods' step offset and,
        where one lit piece's cached shadow is corrected, that pick's two numbers (else
        None). Returns the light (a Mitsuba ``Spectrum``) and the transmittance."""
        m, integ = self.m, self.integ
        o, d, t_mesh = od_mesh
        jitter, pick_u = numbers
        ray_v = RayContext(integ.dev, integ.config(), o, d, m.Float(0.0), m.Float(t_mesh),
                           m.Bool(active))
        lighting = self.lighting(scene, light_u, ray, o, d, pick_u)
        res = composite(ray_v, jitter, Shading(self.band_colors(), lighting))
        L = mi.Spectrum(res.C.x, res.C.y, res.C.z)
        L += lighting.correction(res.pick) if res.pick is not None else 0.0
        return L, mi.Float(res.T)

    def lighting(self, scene, light_u, ray, o, d, pick_u=None):
        """The ``lighting`` object of the volume compositing
        (:func:`~mi_amr.kernels.composite.composite`) for the ray ``ray`` (scene) that is
        ``o + t d`` in the volume; its shadows from the integrator's transmittance caches
        where it keeps them (:mod:`mi_amr.plugin.shadow_cache`). ``pick_u``: two uniform
        numbers per ray (kernel Floats) where one lit piece's cached shadow is corrected by
        an exact shadow ray (``volume_shadows="corrected"``), else None."""
        grids = self.integ.shadow_caches.grids(self.integ, scene)
        return VolumeLighting(self, scene, light_u, ray, (o, d), grids, pick_u)


class VolumeLighting:
    """Light samples, Phong terms and the diffuse term for the volume compositing, at volume
    points ``o + t d`` of one scene ray (kernel types in and out)."""

    def __init__(self, shader: IsoShader, scene, light_u, ray, od, grids, pick_u=None):
        """``od``: the ray ``(o, d)`` in the volume; ``grids``: per emitter its transmittance
        cache (:class:`~mi_amr.kernels.shadow_grid.TransmittanceGrid`) or None; ``pick_u``:
        see :meth:`IsoShader.lighting`. Where it is given and a light has a cache, the
        lighting ``corrects``: each ray picks one cached light (``pick_u[0]``) whose shadow
        it corrects, and ``pick_u[1]`` picks the piece
        (:class:`~mi_amr.kernels.composite.Pick`)."""
        self.shader, self.scene, self.light_u, self.ray = shader, scene, light_u, ray
        self.o, self.d = od
        self.grids = grids
        self.m = shader.m
        self.cached_lights = [i for i, g in enumerate(grids) if g is not None]
        self.corrects = pick_u is not None and bool(self.cached_lights)
        if self.corrects:
            n = len(self.cached_lights)
            self.choice = dr.minimum(mi.UInt32(bridge.to_mi(pick_u[0], mi.Float) * n), n - 1)
            self.pick_u = pick_u[1]

    def _t(self, p):
        """The scene ray's parameter at the volume point ``p`` (a Mitsuba Float)."""
        return bridge.to_mi(dr.dot(p - self.o, self.d) / dr.squared_norm(self.d), mi.Float)

    def sample(self, p, lit, visible: bool, near=None):
        """The light samples at volume point ``p``, shadowed where ``visible``: through the
        lights' caches where they have one, else by exact shadow rays. ``near``: where and
        from which leaf the caches' exact stretch is taken
        (:class:`~mi_amr.kernels.near.NearStretch`; None: exactly everywhere, from the root)."""
        integ = self.shader.integ
        t = self._t(p)
        shadows = integ.shadows() if visible else False
        cached = [None if g is None or not visible else
                  CachedShadow(self.m, g, self.shader.transmittance, integ.frame.to_volume,
                               near)
                  for g in self.grids]
        return shading.light_samples(self.scene, self.light_u, self.ray, self.ray(t),
                                     mi.Bool(lit), shading.Shadowing(
                                         shadows, self.shader.transmittance, cached))

    def terms(self, samples, grad, lit):
        """``(A, S)`` (kernel ``Array3f``) of a point with volume-space gradient ``grad``."""
        n = self.shader.normal(grad, self.ray)
        A, S = shading.volume_terms(samples, self.shader.integ.phong(), n, -self.ray.d,
                                    mi.Bool(lit))
        return self.m.Array3f(A.x, A.y, A.z), self.m.Array3f(S.x, S.y, S.z)

    def direct_terms(self, samples, grad, lit):
        """``(A, S)`` (kernel ``Array3f``) of the ray's correcting light alone, with its
        light past the meshes but not the band (``open``), times the number of cached lights
        (the ray picks one of them)."""
        k = float(len(self.cached_lights))
        picked = [shading.LightSample(to_light=samples[i].to_light, radiance=samples[i].open * k,
                                      valid=samples[i].valid & (self.choice == pos))
                  for pos, i in enumerate(self.cached_lights)]
        n = self.shader.normal(grad, self.ray)
        A, S = shading.phong_sum(picked, self.shader.integ.phong(), n, -self.ray.d,
                                 mi.Bool(lit), mi.Spectrum(0.0))
        return self.m.Array3f(A.x, A.y, A.z), self.m.Array3f(S.x, S.y, S.z)

    def cached(self, samples):
        """The band's cached transmittance (kernel ``Float``) towards the ray's correcting
        light."""
        out = mi.Float(0.0)
        for pos, i in enumerate(self.cached_lights):
            out = dr.select(self.choice == pos, samples[i].cached, out)
        return bridge.to_kernel(self.m, out)

    def correction(self, pick):
        """The light that the exact shadow ray from the picked piece adds to the ray (a
        Mitsuba ``Spectrum``, either sign): the pick's estimate times the exact transmittance
        of the band towards the correcting light minus the cached one."""
        integ = self.shader.integ
        P = self.ray(self._t(pick.p))
        picked = mi.Bool(pick.picked)
        exact = mi.Float(0.0)
        for pos, i in enumerate(self.cached_lights):
            emitter = self.scene.emitters()[i]
            on = picked & (self.choice == pos)
            ds, _ = shading.sample_emitter(emitter, self.light_u[i], self.ray, P, on)
            T = self.shader.transmittance(shading.shadow_ray(P, ds), True, on)
            exact = dr.select(on, T, exact)
        exact = dr.select(integ.shadows(), exact, 1.0)
        D = bridge.to_mi3(pick.estimate_weight(), mi.Color3f)
        return dr.select(picked, D * (exact - bridge.to_mi(pick.cached, mi.Float)), 0.0)

    def lambert(self, samples, grad):
        """The first light's unnormalised diffuse term: the gradient taken to the scene (as a
        normal) dotted with the direction to the light; linear in ``grad``."""
        if not samples:
            return self.m.Float(0.0) * grad[0]
        n = self.shader.integ.frame.to_scene @ bridge.to_mi3(grad, mi.Normal3f)
        return bridge.to_kernel(self.m, dr.dot(n, samples[0].to_light))
