"""The volume-mode opacity band (course report, sections 3.7-3.8; the lecture's pre-integration).

Around the isovalue ``c`` (field units), with ``x = v - c``:
``alpha(v) = min(1, peak * exp(-x^2 / (2 width^2)))`` for ``lo < x < hi`` (the support, offsets
from the centre), zero outside. ``alpha`` is the opacity of a step of length ``dx0`` (world
units; the finest cell width). A step of length ``dx`` has the corrected opacity
``1 - (1 - alpha)^(dx / dx0)``. Pre-integrated: along a step where the value runs linearly from
``a`` to ``b`` the optical depth is ``dx * (T(b) - T(a)) / (b - a)``, with ``T`` the integral of
the extinction ``tau(x) = -ln(1 - alpha) / dx0`` over value offsets, tabulated once per band
shape (:data:`TABLE_SIZE` + 1 points over the support).

:class:`OpacityBand` holds one band's shape on the host; :func:`band_inputs` makes
:class:`BandInputs` of one band per isovalue, the opaque device values the kernels read, so a new
width, support, peak or isovalue is new kernel input. Several bands add their optical depths
(their opacities combine as ``1 - prod(1 - alpha_k)``); the kernel functions take the band's
index ``k`` (a Python int: the number of bands is part of the scene's structure).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import numpy as np

from mi_amr import tolerances as tol
from mi_amr.errors import AMRError
from mi_amr.kernels.device import opaque_floats

TABLE_SIZE = 1024


@dataclass
class BandInputs:
    """The bands on the device: ``width``, ``lo``, ``hi``, ``peak`` one value per band, ``dx0``
    one value, the bands' integral tables one after another (``TABLE_SIZE + 1`` each) and their
    inverses (the offset at which the integral reaches ``j / TABLE_SIZE`` of its total)."""

    width: Any
    lo: Any
    hi: Any
    peak: Any
    dx0: Any
    table: Any
    inverse: Any
    count: int = 1

    def get(self, m, name, k):
        return dr.gather(m.Float, getattr(self, name), m.UInt32(k))


def band_inputs(m, bands) -> BandInputs:
    """The device values of the bands ``bands`` (one :class:`OpacityBand` per isovalue, with
    the same ``dx0``), opaque."""
    return BandInputs(width=opaque_floats(m, [b.width for b in bands]),
                      lo=opaque_floats(m, [b.lo for b in bands]),
                      hi=opaque_floats(m, [b.hi for b in bands]),
                      peak=opaque_floats(m, [b.peak for b in bands]),
                      dx0=opaque_floats(m, [bands[0].dx0]),
                      table=opaque_floats(m, np.concatenate([b.table_T for b in bands])),
                      inverse=opaque_floats(m, np.concatenate([b.table_inv for b in bands])),
                      count=len(bands))


class OpacityBand:
    """The band's shape (see the module docstring); ``support`` is ``(lo, hi)`` as offsets from
    the isovalue (default ``+- 2 width``)."""

    def __init__(self, width: float = 0.004, support=None, peak: float = 1.6, dx0: float = 1.0):
        if not width > 0:
            raise AMRError(f"amr_iso: parameter 'band_width' must be > 0, got {width:g}")
        if not peak > 0:
            raise AMRError(f"amr_iso: parameter 'band_peak' must be > 0, got {peak:g}")
        lo, hi = support if support is not None else (-2.0 * width, 2.0 * width)
        if not lo < 0.0 < hi:
            raise AMRError(f"amr_iso: parameter 'band_support' must contain the isovalue "
                           f"(offsets {lo:g}, {hi:g})")
        self.width, self.lo, self.hi, self.peak = float(width), float(lo), float(hi), float(peak)
        self.dx0 = float(dx0)
        self.table_x = np.linspace(self.lo, self.hi, TABLE_SIZE + 1)
        tau = -np.log1p(-np.minimum(self.alpha_numpy(self.table_x, 0.0), tol.OPACITY_CAP)) / \
            self.dx0
        self.table_T = np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) *
                                                        np.diff(self.table_x))])
        # tau > 0 over the open support, so T rises strictly and has an inverse
        self.table_inv = np.interp(np.linspace(0.0, self.table_T[-1], TABLE_SIZE + 1),
                                   self.table_T, self.table_x)

    def alpha_numpy(self, v, centre):
        """Slow twin of :func:`alpha`."""
        x = np.asarray(v, dtype=np.float64) - centre
        a = np.minimum(1.0, self.peak * np.exp(-0.5 * (x / self.width) ** 2))
        return np.where((x > self.lo) & (x < self.hi), a, 0.0)

    def half_point_numpy(self, a, b, dx, centre=0.0, n: int = 200001) -> float:
        """Slow twin of :func:`segment_alpha_and_point`'s point, by float64 quadrature: the
        fraction of a step of length ``dx`` (world), its value running linearly from ``a`` to
        ``b``, at which the step's opacity is half made."""
        u = np.linspace(0.0, 1.0, n)
        alpha = np.minimum(self.alpha_numpy(a + u * (b - a), centre), tol.OPACITY_CAP)
        tau = -np.log1p(-alpha) / self.dx0 * dx
        depth = np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) * np.diff(u))])
        made = -np.expm1(-depth)
        return float(np.interp(0.5 * made[-1], made, u))

    def inputs(self, m) -> BandInputs:
        """The device values of this band alone on backend ``m`` (opaque)."""
        return band_inputs(m, [self])


def alpha(m, band: BandInputs, k, v, centre):
    """Opacity of band ``k`` for one step of length ``dx0`` at value ``v``."""
    x = v - centre
    width, peak = band.get(m, "width", k), band.get(m, "peak", k)
    a = dr.minimum(1.0, peak * dr.exp(-0.5 * dr.square(x / width)))
    return dr.select((x > band.get(m, "lo", k)) & (x < band.get(m, "hi", k)), a, 0.0)


def corrected(band: BandInputs, a, dx):
    """Opacity correction of ``a`` for a step of length ``dx`` (world units)."""
    return 1.0 - dr.power(dr.maximum(1.0 - dr.minimum(a, tol.OPACITY_CAP), 0.0), dx / band.dx0)


def integral(m, band: BandInputs, k, x):
    """``T(x)`` of band ``k``: its extinction integrated from its support's low end to offset
    ``x``."""
    lo, hi = band.get(m, "lo", k), band.get(m, "hi", k)
    u = dr.clip((x - lo) / (hi - lo), 0.0, 1.0) * TABLE_SIZE
    i = dr.minimum(m.UInt32(dr.floor(u)), TABLE_SIZE - 1) + k * (TABLE_SIZE + 1)
    f = u - m.Float(i - k * (TABLE_SIZE + 1))
    return dr.lerp(dr.gather(m.Float, band.table, i), dr.gather(m.Float, band.table, i + 1), f)


def _ramp_depth(m, band: BandInputs, k, a, b, dx, centre):
    """Band ``k``'s optical depth over a step of length ``dx`` (world) along which the value
    goes linearly from ``a`` to ``b``; with the integral at both ends and whether the ramp is
    flat (then the depth is the point value's)."""
    xa, xb = a - centre, b - centre
    Ta, Tb = integral(m, band, k, xa), integral(m, band, k, xb)
    flat = dr.abs(xb - xa) < tol.RAMP_FLAT_REL * band.get(m, "width", k)
    tau_point = -dr.log(1.0 - dr.minimum(alpha(m, band, k, 0.5 * (a + b), centre),
                                         tol.OPACITY_CAP)) / band.dx0
    tau_mean = dr.select(flat, tau_point, (Tb - Ta) / (xb - xa))
    return dr.maximum(tau_mean, 0.0) * dx, Ta, Tb, flat


def segment_alpha(m, band: BandInputs, k, a, b, dx, centre):
    """Pre-integrated opacity of band ``k`` for a step of length ``dx`` (world) along which the
    value goes linearly from ``a`` to ``b``."""
    return 1.0 - dr.exp(-_ramp_depth(m, band, k, a, b, dx, centre)[0])


def _inverse(m, band: BandInputs, k, T):
    """The offset at which band ``k``'s integral reaches ``T`` (the inverse of
    :func:`integral`)."""
    base = k * (TABLE_SIZE + 1)
    total = dr.gather(m.Float, band.table, m.UInt32(base + TABLE_SIZE))
    u = dr.clip(T / total, 0.0, 1.0) * TABLE_SIZE
    i = dr.minimum(m.UInt32(dr.floor(u)), TABLE_SIZE - 1)
    f = u - m.Float(i)
    return dr.lerp(dr.gather(m.Float, band.inverse, i + base),
                   dr.gather(m.Float, band.inverse, i + base + 1), f)


def segment_alpha_and_point(m, band: BandInputs, k, a, b, dx, centre):
    """:func:`segment_alpha`, and where along the step band ``k`` has made half of the step's
    opacity (a fraction of the step, 0 at ``a``): the light a viewer at the ``a`` end receives
    from the step comes from around there, so that is where the step is lit and coloured. A
    thin transparent step gives the point where half its optical depth lies, an opaque one a
    point near its front."""
    tau, Ta, Tb, flat = _ramp_depth(m, band, k, a, b, dx, centre)
    xa, xb = a - centre, b - centre
    # the depth at which 1 - exp(-depth) is half of 1 - exp(-tau), as a fraction of tau
    r = dr.select(tau > tol.HALF_DEPTH_THIN, -dr.log(0.5 * (1.0 + dr.exp(-tau))) / tau, 0.5)
    x = _inverse(m, band, k, dr.lerp(Ta, Tb, r))
    u = dr.select(flat, r, (x - xa) / (xb - xa))
    return 1.0 - dr.exp(-tau), dr.clip(u, 0.0, 1.0)


def combine(alphas):
    """The opacity of bands of opacities ``alphas`` together, and each band's share of it (its
    optical depth over the total; 0 where all are 0)."""
    if len(alphas) == 1:
        return alphas[0], [1.0]
    taus = [-dr.log(1.0 - dr.minimum(a, tol.OPACITY_CAP)) for a in alphas]
    total = taus[0]
    for t in taus[1:]:
        total = total + t
    shares = [dr.select(total > 0.0, t / total, 0.0) for t in taus]
    return 1.0 - dr.exp(-total), shares
