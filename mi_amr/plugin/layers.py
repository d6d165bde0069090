"""Compositing the isosurface layers met along a ray, front to back (the course report's
translucent surfaces; a single opaque surface is the one-layer case).

:func:`front_to_back` is the loop; what a layer is comes from callbacks, so the loop can be
checked without a scene or a volume. A ray stops after ``max_layers`` layers or once less than
:data:`~mi_amr.tolerances.T_MIN` of the light gets through, and what is left then counts as 0.

:func:`pick_one` is its stochastic counterpart (stochastic transparency, as Mitsuba's ``mask`` BSDF
treats opacity): it shades one layer per sample, layer ``i`` with the probability
``T_i alpha_i`` that is its weight in :func:`front_to_back`, and lets the sample through to
what lies behind with the probability of the transmittance left. Its expected image is
:func:`front_to_back`'s; a sample shades one layer (and traces its shadow rays) instead of
every one, and is noisier.

:func:`one_shadow_ray` keeps :func:`front_to_back`'s shading of every layer and traces one shadow
ray per light and sample instead of one per layer: from a layer picked with the probability of
its share of that light's unshadowed direct light, its visibility weighting all of that light.
The expectation is :func:`front_to_back`'s again; the noise is only where the layers of a pixel
see the light differently.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_amr import tolerances as tol

ONE_BELOW = 1.0 - 2.0 ** -24    # the largest float32 below 1: a rescaled number stays below 1
TINY = 1e-30                    # a divisor's floor where the quotient is not used


@dr.syntax
def front_to_back(state, crossing, opacity, shade, max_layers: int, active):
    """``(L, T)``: the radiance of the layers and the transmittance left behind them.

    ``crossing(state, alive) -> (hit, where, state, k)``: the next layer from where the search
    ``state`` stands (``where``: what ``shade`` needs to know of it; ``k``: which isovalue;
    ``state``: where to look for the one after it); ``opacity(k)``: its opacity;
    ``shade(hit, where, k)``: its radiance, or ``shade=None`` for the transmittance alone
    (shadow rays). Values are Mitsuba types; ``state`` is whatever ``crossing`` keeps."""
    # (No radiance in the loop without shading: a loop variable that never changes makes
    # Dr.Jit trace the loop again without it.)
    L = mi.Spectrum(0.0) if shade is not None else None
    T = mi.Float(1.0)
    layer = mi.UInt32(0)
    alive = mi.Bool(active)
    while dr.hint(alive, label="front_to_back"):
        hit, where, state, k = crossing(state, alive)
        alpha = opacity(k)
        if dr.hint(shade is not None, mode="scalar"):
            # A symbolic branch: a SIMD packet with no lane on a surface skips the shading.
            lit = mi.Spectrum(0.0)
            if dr.hint(hit, label="front_to_back_hit"):
                lit = T * alpha * shade(hit, where, k)
            L += lit
        T = dr.select(hit, T * (1.0 - alpha), T)
        layer += 1
        alive = hit & (T > tol.T_MIN) & (layer < max_layers)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return (mi.Spectrum(0.0) if L is None else L), T


@dr.syntax
def pick_one(state, crossing, opacity, shade, max_layers: int, u, nowhere, active):
    """``(L, T)`` of one sample: the radiance of one layer picked at random (weight 1), and
    ``T`` = 1 where the sample passes every layer (what lies behind counts in full), else 0.

    Callbacks as in :func:`front_to_back`, but ``where`` must be a Dr.Jit value (it is loop
    state; ``nowhere``: its value before a layer is picked) and ``shade`` is called once,
    after the loop. ``u`` (``mi.Float`` in ``[0, 1)``, one per sample) picks the first layer
    after which the transmittance falls to ``u`` or below: layer ``i`` with probability ``T_i -
    T_(i+1) = T_i alpha_i``; past the last layer (probability: the transmittance left) the
    sample passes, unless that is at most :data:`~mi_amr.tolerances.T_MIN` (front to back
    counts it as 0 there too)."""
    T = mi.Float(1.0)
    layer = mi.UInt32(0)
    picked = mi.Bool(False)
    where, k = nowhere, mi.UInt32(0)
    alive = mi.Bool(active)
    while dr.hint(alive, label="pick_one", exclude=[u]):
        hit, at, state, k_at = crossing(state, alive)
        T_next = dr.select(hit, T * (1.0 - opacity(k_at)), T)
        take = hit & (u >= T_next)
        where = dr.select(take, at, where)
        k = dr.select(take, k_at, k)
        picked |= take
        T = T_next
        layer += 1
        alive = hit & dr.select(take, False, True) & (T > tol.T_MIN) & (layer < max_layers)
    L = mi.Spectrum(0.0)
    if picked:          # a symbolic branch: packets with no layer picked skip the shading
        L = shade(picked, where, k)
    return L, dr.select(picked | (T <= tol.T_MIN), 0.0, 1.0)


@dr.syntax
def one_shadow_ray(state, crossing, opacity, shade_parts, visible, max_layers: int, u,
                   lights: int, active):
    """``(L, T)`` as :func:`front_to_back` gives them in expectation, with one shadow ray per
    light: ``shade_parts(hit, where, k) -> (base, [(direct, shadow_ray), ...])`` is a layer's
    ambient light and per light its unshadowed direct light and shadow ray (``shade`` is
    ``base + sum(direct * V)``), and ``visible(shadow_ray, active)`` the ray's ``V``.

    Per light, the layers' weighted direct light ``c_i = T_i alpha_i direct_i`` is summed
    (``Q``, over the channels) while one layer is kept by weighted reservoir sampling
    (``u``, ``mi.Float`` in ``[0, 1)``, rescaled at each choice): layer ``i`` with probability
    ``q_i / Q``, ``q_i`` its channels' sum. Its ``c_i V_i Q / q_i`` then stands for ``sum(c_i
    V_i)``; where every layer sees the light alike it is that sum exactly. ``lights``: how
    many lights (entries of ``shade_parts``' list) there are."""
    L = mi.Spectrum(0.0)
    T = mi.Float(1.0)
    layer = mi.UInt32(0)
    alive = mi.Bool(active)
    # Per light: (u, Q, c, q, shadow ray) of the layer kept so far.
    kept = tuple((mi.Float(u), mi.Float(0.0), mi.Spectrum(0.0), mi.Float(0.0),
                  dr.zeros(mi.Ray3f)) for _ in range(lights))
    while dr.hint(alive, label="one_shadow_ray"):
        hit, where, state, k = crossing(state, alive)
        alpha = opacity(k)
        if dr.hint(hit, label="one_shadow_ray_hit"):
            L, kept = _take_layer(L, kept, T * alpha, shade_parts(hit, where, k), hit)
        T = dr.select(hit, T * (1.0 - alpha), T)
        layer += 1
        alive = hit & (T > tol.T_MIN) & (layer < max_layers)
    for _, Q, c, q, ray in kept:
        on = q > 0.0
        L += dr.select(on, c * (Q / dr.maximum(q, TINY)) * visible(ray, on), 0.0)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return L, T


def _take_layer(L, kept, weight, shaded, hit):
    """``(L, kept)`` after a layer of weight ``weight`` (``T alpha``) whose
    ``shade_parts`` are ``shaded``: its ambient light added, and per light its weighted
    direct light offered to the reservoir (see :func:`one_shadow_ray`)."""
    base, parts = shaded
    L = L + weight * base
    out = []
    for (u, Q, c, q, ray), (direct, shadow) in zip(kept, parts):
        c_i = weight * direct
        q_i = dr.select(hit, c_i.x + c_i.y + c_i.z, 0.0)
        Q = Q + q_i
        p = dr.select(q_i > 0.0, q_i / dr.maximum(Q, TINY), 0.0)
        take = u < p
        # The uniform number rescaled to the part of [0, 1) it fell in, for the next choice.
        # (Denominators kept off 0 for scalar variants, whose floats raise; where a branch is
        # taken they are p > 0 and 1 - p >= 2^-24, unchanged.)
        u = dr.select(take, u / dr.maximum(p, TINY), (u - p) / dr.maximum(1.0 - p, TINY))
        out.append((dr.minimum(u, ONE_BELOW), Q, dr.select(take, c_i, c),
                    dr.select(take, q_i, q), dr.select(take, shadow, ray)))
    return L, tuple(out)
