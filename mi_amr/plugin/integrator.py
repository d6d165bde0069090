"""The ``amr_iso`` Mitsuba integrator: isosurfaces (or an opacity band) of an AMR volume, with
Mitsuba's meshes, emitters, shadows, camera and film.

.. code-block:: xml

    <integrator type="amr_iso">
        <string name="filename" value="data/sphere_wake.npz"/>
        <string name="field" value="q_criterion"/>
        <float name="isovalue" value="0.05"/>
        <string name="color_field" value="speed"/>
        <string name="colormap" value="0.012: 0.03 0.03 1, 0.025: 0.03 1 0.03, 0.072: 1 0.03 0.03"/>
    </integrator>

==================  =============  ================================================  ==========
Parameter           Type           Meaning                                           Default
==================  =============  ================================================  ==========
filename            string         anything :func:`mi_amr.load` reads; relative to   (required)
                                   the scene file
field               string         field to contour; stored, or derived              (required)
                                   (``q_criterion``, ``speed``,
                                   ``vorticity_magnitude``) from the velocity
isovalue            float / list   one or up to 8 isovalues, ``"0.05, 0.1"``         (required)
iso_color           rgb / list     colour per isovalue, ``"r g b; r g b"``           0.8 0.8 0.8
iso_opacity         float / list   opacity per isovalue in (0, 1]; below 1 the       1
                                   surfaces are composited front to back
color_field         string         colour the surface by this field ...              none
colormap            string         ... with ``"v: r g b, ..."`` pairs (flat +-0.0025  none
                                   around each) or a matplotlib map name
color_range         2 floats       value range of a named colour map                 field range
mode                string         ``surface`` or ``volume``                         surface
method              string         ``exact``, ``bisect``, ``adaptive``, ``uniform``  exact
reconstruction      string         ``basis`` (Wald et al.) or ``finest``             basis
step_scale          float          step in cells (sampling methods)                  0.5
shadows             boolean        shadow rays test meshes and isosurfaces           true
to_world            transform      places the volume's world space in the scene      identity
ka, kd, ks          float          Phong ambient, diffuse, specular                  .15 .75 .25
shininess           float          Phong exponent                                    32
ambient             float          ambient light level                               1
band_width          float          volume mode: Gaussian width of the opacity band   0.004
                                   centred on ``isovalue``
band_support        2 floats       volume mode: where opacity is non-zero            iso+-2w
band_peak           float          volume mode: opacity scale (clamped to 1)         1.6
preintegrated       boolean        volume mode: pre-integrated opacity per step      false
leaf_cells          integer        kd leaf size in cells (empty-space skipping)      4
max_layers          integer        translucent surfaces composited per ray, at most  8
==================  =============  ================================================  ==========

``isovalue`` and ``step_scale`` appear in ``mi.traverse(scene)`` as ``integrator.isovalue`` and
``integrator.step_scale``; changing them (or the camera) renders without recompiling.

Python classes deriving from ``mi.SamplingIntegrator`` can only be defined once a variant is set,
so the class is made by :func:`register` for the active variant (``import mi_amr`` calls it when
a variant is already set; call it again after ``mi.set_variant``).
"""

from __future__ import annotations

import math
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr.plugin import options as opts
from mi_amr.kernels.device import backend_of, lnot
from mi_amr.errors import AMRError
from mi_amr.kernels.march import Crossing, MarchConfig, composite, first_crossing
from mi_amr.kernels.prepared import prepare_file
from mi_amr.plugin.scene import resolve_data_file
from mi_amr.kernels.reconstruct import reconstruct
from mi_amr.kernels.shading import ColorMap, OpacityBand

_CLASSES = {}
_DOC = __doc__


def register() -> None:
    """Register ``amr_iso`` with Mitsuba for the active variant."""
    variant = mi.variant()
    if variant is None:
        raise AMRError("mi_amr.register(): set a Mitsuba variant first (mi.set_variant(...))")
    if variant not in _CLASSES:
        _CLASSES[variant] = _make_class()
    cls = _CLASSES[variant]
    mi.register_integrator("amr_iso", lambda props: cls(props))


def _make_class():
    class AMRIsoIntegrator(mi.SamplingIntegrator):
        __doc__ = _DOC

        def __init__(self, props):
            super().__init__(props)
            values = {k: props[k] for k in props.keys()}
            to_world = values.pop("to_world", None)
            opt = opts.parse(values)
            self.opt = opt
            # Scalar variants run the volume kernels on one-element LLVM arrays: the same code
            # as the vectorised variants, and IEEE arithmetic where Python floats would raise.
            self.m = m = backend_of(mi.Float) if dr.is_jit_v(mi.Float) else dr.llvm.ad
            if not dr.is_jit_v(mi.Float) and opt.mode == "volume":
                raise AMRError("amr_iso: mode 'volume' needs a vectorised variant (llvm_ad_rgb "
                               "or cuda_ad_rgb); scalar variants render surfaces only")
            self.prep = prepare_file(resolve_data_file(opt.filename), opt.field, opt.color_field,
                                     leaf_cells=opt.leaf_cells, m=m)
            self.dev = self.prep.device
            vol = self.prep.volume
            matrix = np.eye(4) if to_world is None else np.array(to_world.matrix, dtype=np.float64)
            if not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix[:3, :3])) < 1e-12:
                raise AMRError("amr_iso: parameter 'to_world' must be an invertible transform")
            self.to_world = mi.Transform4f(matrix.astype(np.float32))
            self.to_local = self.to_world.inverse()
            self.isovalue = m.Float(opt.isovalues)
            self.step_scale = m.Float(opt.step_scale)
            self._make_opaque()
            self.colormap = None
            if opt.colormap is not None:
                rng = opt.color_range or vol.value_range(self.prep.color_field)
                self.colormap = ColorMap.parse(opt.colormap, rng).device(m)
            self.band = self.band_table = None
            if opt.mode == "volume":
                iso = opt.isovalues[0]
                support = None if opt.band_support is None else \
                    (opt.band_support[0] - iso, opt.band_support[1] - iso)
                self.band = OpacityBand(opt.band_width, support, opt.band_peak,
                                        dx0=self.dev.min_h)
                self.band_table = self.band.device(m)

        # ------------------------------------------------------------------ parameters
        def _make_opaque(self):
            dr.make_opaque(self.isovalue, self.step_scale)

        def traverse(self, callback):
            if not dr.is_jit_v(mi.Float):
                return
            callback.put("isovalue", self.isovalue, mi.ParamFlags.NonDifferentiable)
            callback.put("step_scale", self.step_scale, mi.ParamFlags.NonDifferentiable)

        def parameters_changed(self, keys):
            if dr.width(self.isovalue) != len(self.opt.isovalues):
                raise AMRError(f"amr_iso: 'isovalue' must keep {len(self.opt.isovalues)} "
                               f"value(s); load the scene again to change how many")
            if not dr.all(self.step_scale > 0.0):
                raise AMRError("amr_iso: 'step_scale' must be > 0")
            self._make_opaque()

        def config(self):
            return MarchConfig(method=self.opt.method,
                               basis=self.opt.reconstruction == "basis",
                               isovalues=self.isovalue, step_scale=self.step_scale,
                               num_iso=len(self.opt.isovalues), band=self.band,
                               band_table=self.band_table, preintegrated=self.opt.preintegrated)

        def to_string(self):
            o = self.opt
            return (f"AMRIsoIntegrator[field={o.field}, isovalue={o.isovalues}, mode={o.mode}, "
                    f"method={o.method}, reconstruction={o.reconstruction}]")

        # ------------------------------------------------------------------ rendering
        def sample(self, scene, sampler, ray, medium=None, active=True):
            m = self.m
            active = mi.Bool(active)
            si = scene.ray_intersect(ray, active)
            t_mesh = dr.select(si.is_valid(), si.t, dr.inf)
            o, d = self._local_ray(ray.o, ray.d)
            jitter = self._kernel_float(sampler.next_1d(active))
            # One light sample per emitter and ray, drawn here: the sampler's state must not
            # change inside the symbolic loops below.
            light_u = [sampler.next_2d(active) for _ in scene.emitters()]
            if self.opt.mode == "surface":
                L, T = self._surfaces(scene, light_u, ray, o, d, t_mesh, jitter, active)
            else:
                L, T = self._volume(scene, light_u, ray, o, d, t_mesh, jitter, active)
            # ---- What lies behind the isosurfaces: a mesh, an emitter, or nothing.
            L += T * self._shade_mesh(scene, sampler, ray, si, active & (T > 0.0))
            hit_any = si.is_valid() | (T < 1.0)
            return L, active & (hit_any | (dr.max(L) > 0.0)), []

        # ---- values between Mitsuba's types (mi.*) and the kernels' (self.m.*); the same
        # types in vectorised variants, Python numbers against one-element arrays in scalar ones.
        def _mi(self, x, T):
            if dr.is_jit_v(mi.Float):
                return T(x)
            dr.eval(x)
            return T(x.numpy()[0])

        def _mi3(self, v, T):
            if dr.is_jit_v(mi.Float):
                return T(v.x, v.y, v.z)
            dr.eval(v)
            return T(float(v.x.numpy()[0]), float(v.y.numpy()[0]), float(v.z.numpy()[0]))

        def _local_ray(self, o, d):
            m = self.m
            ol = self.to_local @ o
            dl = self.to_local @ d
            o, d = m.Array3f(ol.x, ol.y, ol.z), m.Array3f(dl.x, dl.y, dl.z)
            if not dr.is_jit_v(mi.Float):
                # Python numbers would enter the kernels as literals; the loops need variables.
                dr.make_opaque(o, d)
            return o, d

        def _kernel_float(self, x):
            """A Mitsuba float as a kernel value (opaque in scalar variants, see _local_ray)."""
            v = self.m.Float(x)
            if not dr.is_jit_v(mi.Float):
                dr.make_opaque(v)
            return v

        @dr.syntax
        def _surfaces(self, scene, light_u, ray, o, d, t_mesh, jitter, active):
            """Front-to-back over the isosurface crossings in front of the mesh hit."""
            cfg = self.config()
            L = mi.Spectrum(0.0)
            T = mi.Float(1.0)
            t = mi.Float(0.0)
            layer = mi.UInt32(0)
            alive = mi.Bool(active)
            while dr.hint(alive, exclude=[self, cfg]):
                c = first_crossing(self.dev, cfg, o, d, self._kernel_float(t),
                                   self._kernel_float(t_mesh), jitter, self.m.Bool(alive))
                hit = self._mi(c.hit, mi.Bool) & alive
                shade = self._shade_iso(scene, light_u, ray, o, d, c, hit)
                alpha = self._iso_opacity(self._mi(c.k, mi.UInt32))
                L += dr.select(hit, T * alpha * shade, 0.0)
                T = dr.select(hit, T * (1.0 - alpha), T)
                t = self._mi(c.t + 1e-3 * self.dev.min_h / dr.norm(d), mi.Float)
                layer += 1
                alive = hit & (T > 0.01) & (layer < self.opt.max_layers)
            T = dr.select(T <= 0.01, 0.0, T)
            return L, T

        def _iso_opacity(self, k):
            alphas = self.opt.iso_opacity
            out = mi.Float(alphas[0])
            for i in range(1, len(alphas)):
                out = dr.select(mi.UInt32(k) == i, alphas[i], out)
            return out

        def _iso_color(self, k, value):
            """Colour of isovalue ``k`` (mi type) at colour-field ``value`` (kernel type)."""
            if self.colormap is not None:
                return self._mi3(ColorMap.lookup(self.m, self.colormap, self.m.Float(value)),
                                 mi.Color3f)
            cols = self.opt.iso_colors
            out = mi.Color3f(*cols[0])
            for i in range(1, len(cols)):
                out = dr.select(mi.UInt32(k) == i, mi.Color3f(*cols[i]), out)
            return out

        def _arrays(self):
            return self.dev.arrays(self.opt.reconstruction == "basis", color=True)

        def _shade_iso(self, scene, light_u, ray, o, d, c: Crossing, hit):
            """Phong shading of the isosurface point of crossing ``c`` (world normal from the
            analytic gradient, turned towards the viewer)."""
            m = self.m
            if not dr.is_jit_v(mi.Float) and not hit:
                return mi.Spectrum(0.0)
            basis = self.opt.reconstruction == "basis"
            p = o + d * c.t
            vals, grad = reconstruct(self.dev, basis, p, self._arrays(), m.Bool(hit))
            color = self._iso_color(self._mi(c.k, mi.UInt32), vals[1])
            A, S = self._phong_terms(scene, light_u, ray, self._mi(c.t, mi.Float),
                                     self._mi3(grad, mi.Normal3f), hit)
            return color * A + S

        def _phong_terms(self, scene, light_u, ray, t, grad, active):
            """``(A, S)`` with the Phong-shaded colour of a point ``ray(t)`` of colour ``c``
            being ``c * A + S``; the normal is the gradient ``grad`` (volume space) taken to the
            world and turned towards the viewer."""
            n = dr.normalize(self.to_world @ grad)
            n = dr.select(dr.dot(n, ray.d) > 0.0, -n, n)
            n = dr.select(dr.all(dr.isfinite(n)), n, -ray.d)
            P = ray(t)
            A = mi.Spectrum(self.opt.ka * self.opt.ambient)
            S = mi.Spectrum(0.0)
            for emitter, u in zip(scene.emitters(), light_u):
                it = dr.zeros(mi.Interaction3f)
                it.p = P
                it.time = ray.time
                it.wavelengths = ray.wavelengths
                ds, w = emitter.sample_direction(it, u, active)
                lit = active & (ds.pdf > 0.0) & (dr.dot(n, ds.d) > 0.0)
                vis = self._visibility(scene, P, ds, lit, offset_iso=True)
                light = w * vis
                n_l = dr.maximum(dr.dot(n, ds.d), 0.0)
                n_h = dr.maximum(dr.dot(n, dr.normalize(ds.d - ray.d)), 0.0)
                A += dr.select(lit, self.opt.kd * light * n_l, 0.0)
                S += dr.select(lit, self.opt.ks * light * dr.power(n_h, self.opt.shininess), 0.0)
            return A, S

        def _shade_mesh(self, scene, sampler, ray, si, active):
            """Emission plus direct light through the mesh's BSDF, shadowed by meshes and
            isosurfaces; the environment where the ray escaped."""
            emitter = si.emitter(scene, active)
            scalar = not dr.is_jit_v(mi.Float)
            # (Scalar variants give None for "no emitter" / "no BSDF" instead of masked calls.)
            L = mi.Spectrum(0.0) if scalar and emitter is None else \
                dr.select(active, emitter.eval(si, active), 0.0)
            on_mesh = active & si.is_valid()
            if scalar and not on_mesh:
                return L
            bsdf = si.bsdf(ray)
            ctx = mi.BSDFContext()
            L += dr.select(on_mesh, bsdf.eval_diffuse_reflectance(si, on_mesh) *
                           (self.opt.ka * self.opt.ambient), 0.0)
            for emitter in scene.emitters():
                ds, w = emitter.sample_direction(si, sampler.next_2d(on_mesh), on_mesh)
                lit = on_mesh & (ds.pdf > 0.0)
                vis = self._visibility(scene, si, ds, lit, offset_iso=False)
                f = bsdf.eval(ctx, si, si.to_local(ds.d), lit)
                L += dr.select(lit, f * w * vis, 0.0)
            return L

        def _visibility(self, scene, origin, ds, active, offset_iso):
            """Fraction of light from ``ds`` reaching ``origin`` (a point, or a surface
            interaction whose spawned ray avoids self-intersection)."""
            if isinstance(origin, mi.SurfaceInteraction3f):
                shadow = origin.spawn_ray(ds.d)
                P = origin.p
            else:
                shadow = mi.Ray3f(origin, ds.d)
                P = origin
            shadow.maxt = ds.dist * (1.0 - 1e-4)
            blocked = scene.ray_test(shadow, active)
            vis = dr.select(blocked, 0.0, mi.Float(1.0))
            if not self.opt.shadows:
                return dr.select(active, mi.Float(1.0), 0.0)
            o, d = self._local_ray(P, ds.d)
            t0 = (1e-3 if offset_iso else 0.0) * self.dev.min_h / dr.norm(d)
            T = self._transmittance(o, d, self._kernel_float(t0), self._kernel_float(shadow.maxt),
                                    active & lnot(blocked))
            return vis * self._mi(T, mi.Float)

        @dr.syntax
        def _transmittance(self, o, d, t0, t1, active):
            """Light passing the isosurfaces (or the opacity band) between ``t0`` and ``t1``
            (kernel types in and out)."""
            m = self.m
            if dr.hint(self.opt.mode == "volume", mode="scalar"):
                T = self._band_transmittance(o, d, t0, t1, active)
            else:
                cfg = self.config()
                alphas = self.opt.iso_opacity
                T = m.Float(1.0)
                t = m.Float(t0)
                alive = m.Bool(active)
                layer = m.UInt32(0)
                # The integrator and the configuration are read, not loop state.
                while dr.hint(alive, exclude=[self, cfg]):
                    c = first_crossing(self.dev, cfg, o, d, t, t1, m.Float(0.5), alive)
                    hit = c.hit & alive
                    alpha = m.Float(alphas[0])
                    for i in range(1, len(alphas)):
                        alpha = dr.select(c.k == i, alphas[i], alpha)
                    T = dr.select(hit, T * (1.0 - alpha), T)
                    t = c.t + 1e-3 * self.dev.min_h / dr.norm(d)
                    layer += 1
                    alive = hit & (T > 0.01) & (layer < self.opt.max_layers)
                T = dr.select(T <= 0.01, 0.0, T)
            return T

        def _volume(self, scene, light_u, ray, o, d, t_mesh, jitter, active):
            """Front-to-back compositing of the opacity band up to the mesh hit."""
            m = self.m
            ray_len = dr.norm(mi.Vector3f(d.x, d.y, d.z))

            def color_of(value):
                c = self._iso_color(0, value)
                return m.Array3f(c.x, c.y, c.z)

            def lighting(p, grad, lit):
                # Back from the volume point to the ray parameter: p = o + t d.
                t = mi.Float(dr.dot(p - o, d)) / (ray_len * ray_len)
                A, S = self._phong_terms(scene, light_u, ray, t,
                                         mi.Normal3f(grad.x, grad.y, grad.z), mi.Bool(lit))
                return m.Array3f(A.x, A.y, A.z), m.Array3f(S.x, S.y, S.z)

            res = composite(self.dev, self.config(), o, d, m.Float(0.0), m.Float(t_mesh), jitter,
                            color_of, lighting, m.Bool(active))
            return mi.Spectrum(res.C.x, res.C.y, res.C.z), mi.Float(res.T)

        def _band_transmittance(self, o, d, t0, t1, active):
            m = self.m
            res = composite(self.dev, self.config(), o, d, m.Float(t0), m.Float(t1),
                            m.Float(0.5), None, None, m.Bool(active))
            return res.T

    return AMRIsoIntegrator
