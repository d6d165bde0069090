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

{table}

The parameters marked [traversable] appear in ``mi.traverse(scene)`` as ``integrator.<name>``
(the colour map as ``colormap_values`` and ``colormap_colors``, the band's support as
``band_offsets``; see :mod:`mi_amr.plugin.inputs`): changing them, or the camera, or loading
another file of the same scene structure, renders without compiling a kernel.

Python classes deriving from ``mi.SamplingIntegrator`` can only be defined once a variant is set,
so the class is made by :func:`register` for the active variant (``import mi_amr`` calls it when
a variant is already set; call it again after ``mi.set_variant``).
"""

from __future__ import annotations

import functools

import drjit as dr
import mitsuba as mi

from mi_amr import params
from mi_amr.errors import AMRError
from mi_amr.kernels.composite import composite
from mi_amr.kernels.config import MarchConfig, SearchPlan, clips
from mi_amr.kernels.device import backend_of
from mi_amr.kernels.jitter import stable_jitter
from mi_amr.kernels.prepared import LoadOptions, Preparations
from mi_amr.kernels.ray import RayContext
from mi_amr.plugin import aovs, bridge, options, shading, surfaces, wavefront
from mi_amr.plugin.frame import VolumeFrame
from mi_amr.plugin.inputs import FLAGS, PHONG, FrameInputs
from mi_amr.plugin.scene import resolve_data_file
from mi_amr.plugin.shadow_cache import ShadowCaches
from mi_amr.plugin.transfer2d import host_transfer2d
from mi_amr.plugin.twins import FAST, Twins
from mi_amr.plugin.iso import IsoShader

__doc__ = __doc__.replace("{table}", params.docstring_table())
_CLASSES = {}


def register() -> Preparations:
    """Register ``amr_iso`` for the active variant. Returns the volumes its integrators
    prepared and reuse (``clear()`` it for a first load; its ``report`` hears each step)."""
    variant = mi.variant()
    if variant is None:
        raise AMRError("mi_amr.register(): set a Mitsuba variant first (mi.set_variant(...))")
    if variant not in _CLASSES:
        # (nanobind classes take one base: the methods are copied in rather than mixed in.)
        methods = {k: v for k, v in vars(_AMRIso).items() if k not in ("__dict__", "__weakref__")}
        _CLASSES[variant] = type("AMRIsoIntegrator", (mi.SamplingIntegrator,),
                                 dict(methods, __doc__=__doc__, preparations=Preparations()))
    cls = _CLASSES[variant]
    mi.register_integrator("amr_iso", lambda props: cls(props))
    return cls.preparations


class _AMRIso:
    """The integrator's methods (the class itself is made per variant by :func:`register`)."""

    def __init__(self, props, twins: Twins = FAST, like=None):
        """``twins``: the fast paths taken (all for users); ``like``: an integrator whose
        parameters, volume, inputs and transform this one shares (:mod:`~.twins`)."""
        mi.SamplingIntegrator.__init__(self, props)
        self.twins = twins
        self.pixel_orders = wavefront.Orders()
        self.shadow_caches = ShadowCaches()
        if like is not None:
            self.opt, self.m, self.prep, self.dev = like.opt, like.m, like.prep, like.dev
            self.frame, self.inputs = like.frame, like.inputs
            return
        values = {k: props[k] for k in props.keys()}
        to_world = values.pop("to_world", None)
        self.opt = opt = options.parse(values)
        # Scalar variants run the volume kernels on one-element LLVM arrays: the same code as
        # the vectorised variants, and IEEE arithmetic where Python floats would raise.
        self.m = m = backend_of(mi.Float) if bridge.vectorised() else dr.llvm.ad
        if not bridge.vectorised() and opt.mode == "volume":
            raise AMRError("amr_iso: mode 'volume' needs a vectorised variant (llvm_ad_rgb "
                           "or cuda_ad_rgb); scalar variants render surfaces only")
        self._prepare(resolve_data_file(opt.filename))
        self.frame = VolumeFrame(to_world)
        data_range = self.prep.value_range(self.prep.color_field)
        self.inputs = FrameInputs(opt, m, data_range, self.dev.min_h_host, host_transfer2d(opt))
        options.warn_outside(self.prep, opt.isovalues)

    def _prepare(self, path):
        o, basis = self.opt, self.opt.reconstruction == "basis"
        how = LoadOptions(o.leaf_cells, o.allow_nonfinite, keep_fields=not basis)
        self.prep = self.preparations.prepare(path, o.field, o.color_field, m=self.m, how=how)
        self.dev = self.prep.device
        self.prep.search_ready(basis)

    def load_volume(self, path) -> None:
        """Show the data file ``path`` instead (the next step of a time series): it must hold
        the scene's field and colour field, or what they are derived from. Everything else
        stays; the next frame compiles no kernel."""
        self._prepare(path)
        self.inputs.min_h = self.dev.min_h_host
        self.inputs.refresh()

    # ------------------------------------------------------------------ parameters
    def traverse(self, callback):
        if bridge.vectorised():
            self.inputs.put(callback)
            callback.put("to_world", self.frame.scene_from_volume, FLAGS)

    def parameters_changed(self, keys):
        self.inputs.refresh()
        self.frame.refresh()

    def config(self) -> MarchConfig:
        """What the kernels look for, with this frame's values. Surfaces drawn by the exact
        method on the basis blend clip their rays to the isovalues' active box (unless the
        twins say otherwise)."""
        cfg = MarchConfig(method=self.opt.method, basis=self.opt.reconstruction == "basis",
                          isovalues=self.inputs["isovalue"], step_scale=self.inputs["step_scale"],
                          num_iso=len(self.opt.isovalues), band=self.inputs.band,
                          preintegrated=self.opt.preintegrated,
                          shading_extrema=self.opt.shading_extrema,
                          transfer2d=self.inputs.transfer2d,
                          search=SearchPlan(steps=self.twins.seek_steps,
                                            two_levels=self.twins.two_levels))
        if self.opt.mode == "surface" and self.twins.clip_to_active and clips(cfg):
            cfg.active_box = self.dev.active_box(self.inputs.host["isovalue"])
            if self.twins.start_tables:
                cfg.start_table = self.dev.start_table(self.inputs.host["isovalue"],
                                                       on_device=bridge.vectorised())
        return cfg

    def phong(self) -> shading.Phong:
        return shading.Phong(*(bridge.to_mi(self.inputs[n], mi.Float) for n in PHONG))

    def shadows(self):
        return bridge.to_mi(self.inputs["shadows"], mi.Bool)

    def to_string(self):
        o = self.opt
        return (f"AMRIsoIntegrator[field={o.field}, isovalue={o.isovalues}, mode={o.mode}, "
                f"method={o.method}, reconstruction={o.reconstruction}]")

    # ------------------------------------------------------------------ rendering
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True, part=None):
        """Mitsuba's render loop with the wavefront's lanes in tiles of pixels
        (:mod:`mi_amr.plugin.wavefront`; ``part``: a pass of a stratified set, see there);
        Mitsuba's own where that module does not apply (or the twins say so)."""
        sensor = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        # (Start table and shadow caches before the trace: a kernel they launched inside it
        # would take some of the frame's work, and the next frame would compile another.)
        if bridge.vectorised():
            self.config()
        self.shadow_caches.grids(self, scene)
        args = (self, scene, sensor, seed, spp, develop, evaluate)
        image = wavefront.render(*args, tiled=self.twins.tile_order,
                                 by_sample=self.picks_by_packet(), part=part) \
            if self.twins.wavefront_loop and wavefront.supported(sensor, spp, part) else \
            mi.SamplingIntegrator.render(*wavefront.own_seed(args, part))
        aovs.unfiltered(self, scene, sensor, image, evaluate)
        return image

    def picks_by_packet(self) -> bool:
        """Do frames of 2 or more spp share the numbers that pick by SIMD packet
        (:func:`mi_amr.plugin.wavefront.packet_u`)? Stochastic layers, unless the twin."""
        return self.twins.packet_picks and self.opt.layers == "stochastic"

    def sample(self, scene, sampler, ray, medium=None, active=True, lanes=None):
        """Mitsuba's ``sample``; ``lanes``: the :class:`~mi_amr.plugin.wavefront.Lanes` of
        the frame :func:`mi_amr.plugin.wavefront.render` traces (None in Mitsuba's loop).
        Returns ``(L, alpha, aovs)``: ``alpha`` the mask of covered lanes, or in volume mode
        under :func:`~mi_amr.plugin.wavefront.render` the opacity ``1 - T`` (a Float)."""
        active = mi.Bool(active)
        # Shadow rays see the frame's lanes (their roulette may pick by packet).
        shader = IsoShader(self, functools.partial(self.iso_transmittance, lanes=lanes))
        # ---- The first mesh along the ray bounds the search for isosurfaces.
        si = scene.ray_intersect(ray, active)
        t_mesh = dr.select(si.is_valid(), si.t, dr.inf)
        o, d = self.frame.ray_to_volume(self.m, ray.o, ray.d)
        jitter = self._jitter(sampler.next_1d(active), ray, lanes)
        # One light sample per emitter and ray, drawn here: the sampler's state must not
        # change inside the symbolic loops below.
        light_u = [sampler.next_2d(active) for _ in scene.emitters()]
        # ---- Isosurfaces (or the band) in front of the mesh, front to back.
        # Picking layers: the number that picks (the sampler's, or for stochastic layers a
        # hash of the packet and the seed; not a hash of the lane alone as jitter="stable"
        # takes, so that passes at seeds 0, 1, ... converge).
        u = sampler.next_1d(active) if surfaces.draws_u(self) else None
        # Where the frame picks by packet: one number per packet (stratified over the pixel's
        # samples), so its lanes stop at their picked layers together.
        shared = wavefront.packet_u(self.m, lanes, ray, salt=0)
        u = u if shared is None else shared
        if self.opt.mode == "surface":
            L, T = surfaces.surfaces(shader, scene, light_u, ray, o, d, t_mesh, jitter, u,
                                     active)
        else:
            # (The correcting pick's numbers too are drawn before the loops, as the jitter.)
            pick_u = [self._jitter(sampler.next_1d(active), ray, lanes, salt)
                      for salt in (1, 2)] if self.opt.volume_shadows == "corrected" else None
            L, T = shader.volume(scene, light_u, ray, (o, d, t_mesh), (jitter, pick_u),
                                 active)
        # ---- What lies behind them: a mesh, an emitter, or nothing.
        L += T * shading.mesh_light(scene, sampler, ray, si, self.phong(), active & (T > 0.0),
                                    self.shadows(), shader.transmittance)
        # ---- Alpha: the coverage by surfaces, or volume mode's opacity (aovs.alpha).
        covered = aovs.alpha(self.opt.mode, si, T, active, lanes)
        channels = aovs.iso_aovs(self, ray, o, d, t_mesh, jitter, active) if self.opt.aovs else []
        return L, covered, channels

    def aov_names(self):
        return list(aovs.NAMES) if self.opt.aovs else []

    def _jitter(self, u, ray, lanes, salt: int = 0):
        """A number in ``[0, 1)`` per ray (the sampling methods' step offset; ``salt`` 1, 2:
        the correcting shadow ray's pick): ``u`` from the sampler, or (``jitter="stable"``)
        a hash of the lane (pixel and sample index of the wavefront ``lanes``) and ``salt``,
        the same every frame."""
        if self.opt.jitter == "random" or not bridge.vectorised():
            return bridge.to_kernel(self.m, u)
        return stable_jitter(self.m, self.m.UInt32(wavefront.lane_index(lanes, ray)), salt)

    def iso_transmittance(self, ray, from_iso, active, lanes=None, start=None):
        """Light passing the isosurfaces (or the band) along a scene ray up to ``ray.maxt``;
        ``from_iso``: the ray leaves an isosurface (start just past it); ``lanes``: the
        frame's :class:`~mi_amr.plugin.wavefront.Lanes` (see :meth:`sample`); ``start``
        (volume mode): the walk whose leaf holds the ray's start, or None (see
        :func:`~mi_amr.kernels.composite.composite`)."""
        m = self.m
        o, d = self.frame.ray_to_volume(m, ray.o, ray.d)
        t0 = self.dev.layer_offset / dr.norm(d) if from_iso else m.Float(0.0)
        t1 = bridge.to_kernel(m, ray.maxt)
        if self.opt.mode == "volume":
            res = composite(RayContext(self.dev, self.config(), o, d, t0, t1, m.Bool(active)),
                            m.Float(0.5), start=start)
            return bridge.to_mi(res.T, mi.Float)
        # Where the frame picks by packet: Russian roulette, a number per packet deciding where
        # the walks stop (the packet's lanes together); else None, the exact transmittance.
        u = wavefront.packet_u(m, lanes, ray, salt=1)
        return surfaces.transmittance(self, self.config(), o, d, t0, t1, active, u)
