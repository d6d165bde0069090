"""The ray context every march kernel takes: one typed object instead of ``(dev, cfg, o, d,
t0, t1, active)`` and the values derived from them.

A ray ``p(t) = o + t d`` is in the volume's world space; ``d`` need not be unit length and
``t`` is the caller's parameter. :class:`RayContext` holds the device volume, the march
configuration, the ray, its stretch ``(t0, t1)`` and the lanes that march (``active``), and
computes once per ray what every piece of the march reads: ``|d|`` (``dnorm``), ``1 / d``
(``inv_d``, infinite where ``d`` is 0) and the per-leaf masks of the levels whose dual planes
cut the ray (:attr:`RayContext.level_masks`). :meth:`RayContext.clipped` cuts the stretch to
the volume's bounds (and the active box).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels.config import MarchConfig
from mi_amr.kernels.device import DeviceVolume

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Array3f, Bool, Float


@dataclass
class RayContext:
    """A bundle of rays to march. ``dev``: the device volume; ``cfg``: what the march looks
    for; ``o``, ``d``: origins and directions (volume world space); ``(t0, t1)``: the stretch
    of ``t`` to march; ``active``: the lanes that march. ``dnorm`` and ``inv_d`` are derived
    once, here."""

    dev: DeviceVolume
    cfg: MarchConfig
    o: Array3f
    d: Array3f
    t0: Float
    t1: Float
    active: Bool
    dnorm: Optional[Float] = None      # |d| (derived when not given)
    inv_d: Optional[Array3f] = None    # 1 / d, infinite where d is 0 (derived when not given)

    def __post_init__(self):
        if self.dnorm is None:
            self.dnorm = dr.norm(self.d)
        if self.inv_d is None:
            self.inv_d = dr.select(self.d != 0.0, dr.rcp(self.d), dr.inf)

    @property
    def m(self):
        """The Dr.Jit backend module."""
        return self.dev.m

    @property
    def level_masks(self):
        """Per kd leaf, the bitmask of the levels whose dual-cell planes cut the ray into cubic
        pieces there: all its active levels for the basis blend, its owner's level for the
        finest-level reconstruction (a device array)."""
        return self.dev.leaf_levels if self.cfg.basis else self.dev.leaf_owner_levels

    def at(self, t):
        """The point ``o + t d``."""
        return dr.fma(self.d, t, self.o)

    def eps(self, t):
        """A step in ``t`` well below a cell yet large enough to move ``t`` in float32."""
        return dr.maximum(self.dev.step_eps / self.dnorm, dr.abs(t) * tol.STEP_EPS_REL)

    def clipped(self, box=None) -> "RayContext":
        """The rays' stretch inside the volume's bounds (and inside ``box``, ``(lo, hi)``, when
        given: :func:`~mi_amr.kernels.config.clip_box`), ``active`` where it is not empty. A
        ray lying in an upper face of the bounds is moved inside by a rounding step: kd points
        on a split plane go to the upper side, which beyond the upper faces holds no data."""
        lo, hi = self.dev.bounds_lo, self.dev.bounds_hi
        d = self.d
        on_top = (d == 0.0) & (self.o == hi)
        o = dr.select(on_top, hi - dr.maximum(dr.abs(hi), 1e-30) * tol.UPPER_FACE_REL, self.o)
        t_in, t_out = box_interval(lo, hi, o, d)
        t0 = dr.maximum(self.t0, t_in)
        t1 = dr.minimum(self.t1, t_out)
        if box is not None:
            b_in, b_out = box_interval(box[0], box[1], o, d)
            # The empty box (+inf, -inf) would give every ray the whole line.
            b_out = dr.select(dr.all(box[0] <= box[1]), b_out, -dr.inf)
            t0, t1 = dr.maximum(t0, b_in), dr.minimum(t1, b_out)
        return self.replaced(o=o, t0=t0, t1=t1, active=self.m.Bool(self.active) & (t0 < t1))

    def replaced(self, **changes) -> "RayContext":
        """These rays with ``changes`` (fields of the constructor: ``t0=``, ``cfg=`` ...); the
        direction stays, and with it the derived values."""
        return replace(self, **changes)


def box_interval(lo, hi, o, d):
    """Parametric interval ``(t_in, t_out)`` of the ray ``o + t d`` inside the box
    ``[lo, hi]``."""
    inv = dr.rcp(d)
    t_a = (lo - o) * inv
    t_b = (hi - o) * inv
    flat = d == 0.0
    inside = (o >= lo) & (o <= hi)
    near = dr.select(flat, dr.select(inside, -dr.inf, dr.inf), dr.minimum(t_a, t_b))
    far = dr.select(flat, dr.select(inside, dr.inf, -dr.inf), dr.maximum(t_a, t_b))
    return dr.max(near), dr.min(far)
