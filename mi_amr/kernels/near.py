"""The first stretch of a lit point's shadow ray in volume mode: what the point's cached
shadow (the plugin's ``CachedShadow``) composites itself before it reads its light's
transmittance cache one cache cell further on.

A lit point lies inside its band, so that stretch holds the band's shadow on itself, which
changes within a small part of a cache cell: the cache read at the point would blend it
away. Two ways to take it:

* **exactly** (:class:`NearStretch` without a ramp): the bands composited along the stretch
  by the exact march, started in the camera ray's leaf. The sampling methods take it so,
  and it is the slow twin of the ramp in the tests.
* **from the value around the point** (:class:`NearRamp`, the exact method's lit pieces):
  the reconstructed value at the point and its gradient give the value along the shadow ray
  as a linear ramp, whose band opacity is pre-integrated in closed form as a camera ray's
  step is (:func:`~mi_amr.kernels.band.segment_alpha`). Where the shadow ray runs nearly
  along the band (its direction within :data:`~mi_amr.tolerances.NEAR_RAMP_GRAZING` of
  the band's surface), the ramp alone would keep it in the band for the whole stretch; there
  the value at the stretch's end is reconstructed too and the ramp bends to it (the
  quadratic through the value and slope at the point and the value at the end, taken as
  two linear halves).

Points are volume world coordinates; gradients are per volume world unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels import roots
from mi_amr.kernels.band import Ramp, segment_alpha
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.transfer2d import segment_alpha as segment_alpha2d
from mi_amr.kernels.traverse import Walk

# The bent ramp's halves: the quadratic's value at the stretch's start, middle and end.
_HALVES = 2


@dataclass
class NearRamp:
    """The value around a lit point ``p`` (volume world): ``value`` there and its
    ``gradient`` (per volume world unit), the bands' ``centres`` (their isovalues) and the
    camera ray's context ``ray`` (the volume, the bands or the 2D transfer function)."""

    ray: RayContext
    p: object
    value: object
    gradient: object
    centres: list

    @staticmethod
    def at(ray: RayContext, cubic, gradient, s, centres) -> "NearRamp":
        """At parameter ``s`` of a camera ray's cubic piece (``cubic``: its
        :class:`~mi_amr.kernels.traverse.CubicPiece`; ``gradient(s)``: the piece's gradient)."""
        value = roots.cubic(cubic.num, s) / roots.cubic(cubic.den, s)
        return NearRamp(ray=ray, p=ray.at(cubic.t + s), value=value, gradient=gradient(s),
                        centres=centres)

    def transmittance(self, seg, active):
        """The bands' transmittance along the stretch ``seg`` (a volume world vector from
        ``p``) where ``active``; 1 elsewhere."""
        m = self.ray.m
        slope = dr.dot(self.gradient, seg)
        length = dr.norm(seg)
        across = dr.abs(slope) / dr.maximum(dr.norm(self.gradient) * length, tol.NO_WEIGHT)
        bend = _bend(self.ray, self.p + seg, self.value + slope,
                     active & (across < tol.NEAR_RAMP_GRAZING))
        T = m.Float(1.0)
        for i in range(_HALVES):
            u0, u1 = i / _HALVES, (i + 1) / _HALVES
            a = self.value + u0 * slope + u0 * u0 * bend
            b = self.value + u1 * slope + u1 * u1 * bend
            T *= 1.0 - self._opacity(a, b, length / _HALVES)
        return dr.select(active, T, 1.0)

    def _opacity(self, a, b, dx):
        """The bands' opacity over a step of length ``dx`` (volume world) along which the
        value runs linearly from ``a`` to ``b``."""
        m, cfg = self.ray.m, self.ray.cfg
        if cfg.transfer2d is not None:
            return segment_alpha2d(m, cfg.transfer2d, a, b, dx, dr.norm(self.gradient))
        T = m.Float(1.0)
        for k, c in enumerate(self.centres):
            T *= 1.0 - segment_alpha(m, cfg.band, k, Ramp(a, b, dx), c)
        return 1.0 - T


@dr.syntax
def _bend(ray: RayContext, end, straight, active):
    """Where ``active``, the reconstructed value at ``end`` (volume world) less the straight
    ramp's value there (``straight``); 0 elsewhere and where the end holds no value (a
    packet with no lane active skips the reconstruction: a symbolic branch)."""
    bend = ray.m.Float(0.0)
    if dr.hint(active, label="near_bend", exclude=[end, ray, straight]):
        arrays = ray.dev.arrays(ray.cfg.basis, color=False)
        values, _ = rec.reconstruct(ray.dev, ray.cfg.basis, end, arrays, active)
        bend = dr.select(active & dr.isfinite(values[0]), values[0] - straight, 0.0)
    return bend


@dataclass
class NearStretch:
    """What a lit point tells its cached shadows (see the plugin's ``CachedShadow``): the
    camera ray's ``walk``, whose leaf holds the point, the lanes ``where`` the first grid cell
    of the shadow ray is taken apart from the cache: those whose light makes more than
    :data:`~mi_amr.tolerances.SHADOW_NEAR_WEIGHT` of the pixel (the light reaching them from
    the eye times their opacity), and how: from the value around the point (``ramp``, a
    :class:`NearRamp`), or, without one, composited exactly from the walk's leaf."""

    walk: Walk
    where: object
    ramp: Optional[NearRamp] = None

    @staticmethod
    def of(walk: Walk, lit, T, alpha, ramp: Optional[NearRamp] = None) -> "NearStretch":
        """For a piece or sample of opacity ``alpha`` behind transmittance ``T``, ``lit``."""
        return NearStretch(walk=walk, where=lit & (T * alpha > tol.SHADOW_NEAR_WEIGHT),
                           ramp=ramp)
