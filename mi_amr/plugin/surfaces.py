"""The isosurfaces along the integrator's rays: the kernels' crossing search wired into the
layer loops of :mod:`mi_amr.plugin.layers`, shaded for camera rays and as transmittance alone
for shadow rays.

A camera ray's sample shades every layer it meets, each with its own shadow rays
(``layers="composite"``, :func:`~mi_amr.plugin.layers.front_to_back`); every layer with one
shadow ray per light from a layer picked by its share of that light (``layers="one_shadow"``,
:func:`~mi_amr.plugin.layers.one_shadow_ray`); or one layer, picked at random with the
probability of its weight (``layers="stochastic"``, :func:`~mi_amr.plugin.layers.pick_one`).
The last two give the same pixels in expectation, noisier per sample. Shadow rays carry the
exact transmittance of the layers they cross, except with stochastic layers: there they play
Russian roulette below :data:`~mi_amr.tolerances.ROULETTE_T`
(:func:`~mi_amr.kernels.transmit.transmittance_exact` with ``u``).

With stochastic layers and 2 or more samples per pixel in a frame, the number that picks, and
the shadow rays' roulette, are shared by the lanes of a SIMD packet (:func:`mi_amr.plugin.wavefront.packet_u`: 16 pixels, one sample index,
the numbers stratified over a pixel's samples). A packet runs its loops until its last lane
is done, so with a number per lane nearly every packet had a lane walking past every layer
(three translucent isovalues, 256^2, 4 spp: frame 0.49 -> 0.42 s with the roulette; squared
error per pixel 1.45e-3 -> 1.26e-3, the stratification's gain; ``Twins(packet_picks=False)``
is the per-lane twin). The noise of neighbouring pixels is then correlated, by the
pixels of a packet; their expectations are what compositing gives. At 1 spp, where a pixel's
one number would be its 4 x 4 tile's too (blocks of noise), lanes keep their own numbers.

Rays are in the volume's world space (``o + t d``); scene rays come in as Mitsuba types.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_amr.kernels.surface import Crossing, crossings
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.transmit import transmittance_exact
from mi_amr.plugin import bridge, shading
from mi_amr.plugin.layers import front_to_back, one_shadow_ray, pick_one


def draws_u(integ) -> bool:
    """Whether the integrator ``integ``'s camera rays pick (one layer, or one layer's shadow
    rays) and so draw a number per sample: ``layers`` other than ``composite``."""
    return integ.opt.layers != "composite"


def layer_crossing(integ, o, d, t_start, t_end, jitter):
    """``(state, crossing)`` for the layer loops along a ray in the volume (kernel
    ``t_start``, ``t_end``). ``integ.twins.layer_fast_paths`` False restarts every layer's
    search (the slow twin, for tests)."""
    m = integ.m
    ray = RayContext(integ.dev, integ.config(), o, d, t_start, t_end, m.Bool(True))
    state, after = crossings(ray, jitter, resume=integ.twins.layer_fast_paths)

    def crossing(state, alive):
        c, state = after(state, m.Bool(alive))
        hit = bridge.to_mi(c.hit, mi.Bool) & alive
        return hit, c, state, bridge.to_mi(c.k, mi.UInt32)

    return state, crossing


def opacity(integ, k):
    """Opacity of isovalue ``k`` (``mi.UInt32``) this frame."""
    return bridge.to_mi(dr.gather(integ.m.Float, integ.inputs["iso_opacity"],
                                  integ.m.UInt32(k)), mi.Float)


def surfaces(shader, scene, light_u, ray, o, d, t_mesh, jitter, u, active):
    """``(L, T)``: the shaded isosurfaces in front of the mesh at ``t_mesh`` and the weight of
    what lies behind them, shaded by ``shader`` (:class:`~mi_amr.plugin.iso.IsoShader`, of the
    integrator ``shader.integ``); ``u``: where :func:`draws_u`, the uniform number per sample
    (``mi.Float``) that picks, else None."""
    integ = shader.integ
    m = integ.m
    state, crossing = layer_crossing(integ, o, d, m.Float(0.0), bridge.to_kernel(m, t_mesh),
                                     jitter)

    def opacity_of(k):
        return opacity(integ, k)

    if integ.opt.layers == "one_shadow":
        def parts(hit, c, k):
            return shader.shade_parts(scene, light_u, ray, o, d, c, hit)

        def visible(shadow, on):
            return shading.ray_visibility(scene, shadow, on, integ.shadows(),
                                          shader.transmittance, from_iso=True)

        return one_shadow_ray(state, crossing, opacity_of, parts, visible,
                              integ.opt.max_layers, u, len(scene.emitters()), active)
    if integ.opt.layers == "composite":
        def shade(hit, c, k):
            return shader.shade(scene, light_u, ray, o, d, c, k, hit)

        return front_to_back(state, crossing, opacity_of, shade, integ.opt.max_layers, active)

    # stochastic
    def crossing_t(state, alive):           # the loop keeps only where the layer is
        hit, c, state, k = crossing(state, alive)
        return hit, bridge.to_mi(c.t, mi.Float), state, k

    def shade_at(hit, t, k):
        c = Crossing(hit=m.Bool(hit), t=bridge.to_kernel(m, t), k=m.UInt32(k), samples=None)
        return shader.shade(scene, light_u, ray, o, d, c, k, hit)

    return pick_one(state, crossing_t, opacity_of, shade_at, integ.opt.max_layers, u,
                    mi.Float(dr.inf), active)


def transmittance(integ, cfg, o, d, t0, t1, active, u=None):
    """Light passing the isosurfaces on ``(t0, t1)`` (kernel values) of a ray in the volume:
    one walk counting the crossings (``exact``), else the layers composited one by one.
    ``u`` (``mi.Float`` in ``[0, 1)``, ``exact`` only): an unbiased sample of it by Russian
    roulette (:func:`~mi_amr.kernels.transmit.transmittance_exact`)."""
    m = integ.m
    if cfg.method == "exact" and integ.twins.layer_fast_paths:
        ray = RayContext(integ.dev, cfg, o, d, t0, t1, m.Bool(active))
        return bridge.to_mi(transmittance_exact(
            ray, integ.inputs["iso_opacity"], integ.opt.max_layers,
            None if u is None else bridge.to_kernel(m, u)), mi.Float)
    state, crossing = layer_crossing(integ, o, d, t0, t1, m.Float(0.5))
    _, T = front_to_back(state, crossing, lambda k: opacity(integ, k), None,
                         integ.opt.max_layers, active)
    return T
