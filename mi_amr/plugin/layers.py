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
def front_to_back(crossing, opacity, shade, max_layers: int, active):
    """``(L, T)``: the radiance of the layers and the transmittance left behind them.

    ``crossing(t, alive) -> (hit, where, t_next, k)``: the next layer at or after parameter
    ``t`` (``where``: what ``shade`` needs to know of it; ``k``: which isovalue; ``t_next``:
    where to look for the one after it); ``opacity(k)``: its opacity; ``shade(hit, where, k)``:
    its radiance, or ``shade=None`` for the transmittance alone (shadow rays). Values are
    Mitsuba types."""
    L = mi.Spectrum(0.0)
    T = mi.Float(1.0)
    t = mi.Float(0.0)
    layer = mi.UInt32(0)
    alive = mi.Bool(active)
    while alive:
        hit, where, t_next, k = crossing(t, alive)
        alpha = opacity(k)
        if dr.hint(shade is not None, mode="scalar"):
            L += dr.select(hit, T * alpha * shade(hit, where, k), 0.0)
        T = dr.select(hit, T * (1.0 - alpha), T)
        t = t_next
        layer += 1
        alive = hit & (T > tol.T_MIN) & (layer < max_layers)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return L, T
