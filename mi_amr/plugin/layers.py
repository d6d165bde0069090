"""Compositing the isosurface layers met along a ray, front to back (the course report's
translucent surfaces; a single opaque surface is the one-layer case).

:func:`front_to_back` is the loop; what a layer is comes from callbacks, so the loop can be
checked without a scene or a volume. A ray stops after ``max_layers`` layers or once less than
:data:`~mi_amr.tolerances.T_MIN` of the light gets through, and what is left then counts as 0.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_amr import tolerances as tol


@dr.syntax
def front_to_back(state, crossing, opacity, shade, max_layers: int, active):
    """``(L, T)``: the radiance of the layers and the transmittance left behind them.

    ``crossing(state, alive) -> (hit, where, state, k)``: the next layer from where the search
    ``state`` stands (``where``: what ``shade`` needs to know of it; ``k``: which isovalue;
    ``state``: where to look for the one after it); ``opacity(k)``: its opacity;
    ``shade(hit, where, k)``: its radiance, or ``shade=None`` for the transmittance alone
    (shadow rays). Values are Mitsuba types; ``state`` is whatever ``crossing`` keeps."""
    L = mi.Spectrum(0.0)
    T = mi.Float(1.0)
    layer = mi.UInt32(0)
    alive = mi.Bool(active)
    while alive:
        hit, where, state, k = crossing(state, alive)
        alpha = opacity(k)
        if dr.hint(shade is not None, mode="scalar"):
            # A symbolic branch: a SIMD packet with no lane on a surface skips the shading
            # (1024^2 frame 0.873 -> 0.862 s and 0.875 -> 0.851 s side by side).
            lit = mi.Spectrum(0.0)
            if hit:
                lit = T * alpha * shade(hit, where, k)
            L += lit
        T = dr.select(hit, T * (1.0 - alpha), T)
        layer += 1
        alive = hit & (T > tol.T_MIN) & (layer < max_layers)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return L, T
