"""The volume-mode opacity band (course report, sections 3.7-3.8; the lecture's pre-integration).

Around the isovalue ``c`` (field units), with ``x = v - c``:
``alpha(v) = min(1, peak * exp(-x^2 / (2 width^2)))`` for ``lo < x < hi`` (the support, offsets
from the centre), zero outside. ``alpha`` is the opacity of a step of length ``dx0`` (world
units; the finest cell width). A step of length ``dx`` has the corrected opacity
``1 - (1 - alpha)^(dx / dx0)``. Pre-integrated: along a step where the value runs linearly from
``a`` to ``b`` the optical depth is ``dx * (I(b) - I(a)) / (b - a)``, with ``I`` the integral of
the extinction ``tau(x) = -ln(1 - alpha) / dx0`` over value offsets, tabulated once per band
shape (:data:`TABLE_SIZE` + 1 points over the support), with its inverse.

Pre-integrated colour (Marchesin et al. 2009, sections 3.1-3.2): where the shaded colour runs
linearly from ``E_front`` to ``E_back`` along the step, the step's light is
``alpha * lerp(E_front, E_back, u_bar)``, ``u_bar`` the step's *centroid*: the opacity-weighted
mean position along it, ``u_bar = (1 / alpha) int_0^1 u dF(u)`` with ``F(u) = 1 - exp(-depth in
front of u)``. :func:`segment_alpha_and_centroid` splits the step where it enters and leaves
the plateau (where the opacity is capped; there the centroid has a closed form) and takes it
on the flanks by Gauss-Legendre quadrature in ``F`` (:data:`COLOR_NODES` nodes; each node's
position from the inverse table), which is smooth where the integrand in ``u`` is not (the
support's ends). Short ramps (see :func:`_ramp_depth`) take the extinction as linear.

:class:`OpacityBand` holds one band's shape on the host; :func:`band_inputs` makes
:class:`BandInputs` of one band per isovalue, the opaque device values the kernels read, so a new
width, support, peak or isovalue is new kernel input. Several bands add their optical depths
(their opacities combine as ``1 - prod(1 - alpha_k)``); the kernel functions take the band's
index ``k`` (a Python int: the number of bands is part of the scene's structure).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import drjit as dr
import numpy as np

from mi_amr import tolerances as tol
from mi_amr.errors import AMRError
from mi_amr.kernels.device import opaque_floats

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Float

TABLE_SIZE = 8192     # cells of each band's integral table over its support
TABLE_SUB = 4         # quadrature steps per table cell when the integral table is built
INVERSE_SIZE = 8192   # cells of each band's inverse table (over the integral's range)
COLOR_NODES = 4       # Gauss-Legendre nodes of the centroid quadrature
_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(COLOR_NODES)
GL_NODES = tuple(float(0.5 * (1.0 + x)) for x in _NODES)      # on [0, 1]
GL_WEIGHTS = tuple(float(0.5 * w) for w in _WEIGHTS)


@dataclass
class BandInputs:
    """The bands on the device: ``width``, ``lo``, ``hi``, ``peak`` one value per band, ``dx0``
    one value, the bands' integral tables one after another (``TABLE_SIZE + 1`` each) and their
    inverses (``INVERSE_SIZE + 1`` each: the offset at which the integral reaches
    ``j / INVERSE_SIZE`` of its total)."""

    width: Float
    lo: Float
    hi: Float
    peak: Float
    cap: Float
    dx0: Float
    table: Float
    inverse: Float
    count: int = 1

    def get(self, m, name, k):
        return dr.gather(m.Float, getattr(self, name), m.UInt32(k))


@functools.lru_cache(maxsize=64)
def band_shape(width: float, support: tuple, peak: float, dx0: float) -> "OpacityBand":
    """The :class:`OpacityBand` of these parameters, its tables built once: a frame that
    changes an isovalue, a colour or the step reuses them (the tables depend on the band's
    shape alone)."""
    return OpacityBand(width, support, peak, dx0)


def band_inputs(m, bands) -> BandInputs:
    """The device values of the bands ``bands`` (one :class:`OpacityBand` per isovalue, with
    the same ``dx0``), opaque."""
    return BandInputs(width=opaque_floats(m, [b.width for b in bands]),
                      lo=opaque_floats(m, [b.lo for b in bands]),
                      hi=opaque_floats(m, [b.hi for b in bands]),
                      peak=opaque_floats(m, [b.peak for b in bands]),
                      cap=opaque_floats(m, [b.cap_offset() for b in bands]),
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
        self.table_x, self.table_T, self.table_inv = self._tables()

    def _tables(self):
        """The integral table at :data:`TABLE_SIZE` + 1 offsets (trapezoids of
        :data:`TABLE_SUB` steps per cell, the extinction taken up to the support's ends) and
        its inverse at :data:`INVERSE_SIZE` + 1 equally spaced integrals."""
        x = np.linspace(self.lo, self.hi, TABLE_SIZE * TABLE_SUB + 1)
        tau = self.extinction_numpy(x)
        cum = np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) * np.diff(x))])
        # tau > 0 over the support, so the integral rises strictly and has an inverse
        inverse = np.interp(np.linspace(0.0, cum[-1], INVERSE_SIZE + 1), cum, x)
        return x[::TABLE_SUB], cum[::TABLE_SUB], inverse

    def cap_offset(self) -> float:
        """The offset from the centre within which the opacity is capped (the plateau; 0 if it
        has none): the extinction has a kink there."""
        if self.peak <= tol.OPACITY_CAP:
            return 0.0
        return float(min(self.width * np.sqrt(2.0 * np.log(self.peak / tol.OPACITY_CAP)),
                         -self.lo, self.hi))

    def extinction_numpy(self, x):
        """``tau`` (per world unit) of the band's shape at offsets ``x``, support ignored."""
        a = np.minimum(1.0, self.peak * np.exp(-0.5 * (np.asarray(x) / self.width) ** 2))
        return -np.log1p(-np.minimum(a, tol.OPACITY_CAP)) / self.dx0

    def _fine_integral(self, n: int = 400001):
        """``(x, T)``: the integral of the extinction over the support at ``n`` offsets, by
        float64 trapezoids (no table)."""
        x = np.linspace(self.lo, self.hi, n)
        tau = self.extinction_numpy(x)
        return x, np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) * np.diff(x))])

    def integral_numpy(self, x):
        """Slow twin of :func:`integral`: ``T`` at offsets ``x`` (clipped to the support)."""
        xs, T = self._fine_integral()
        return np.interp(np.asarray(x, dtype=np.float64), xs, T)

    def inverse_numpy(self, T):
        """Slow twin of :func:`integral_inverse`: the offsets at which the integral reaches
        ``T`` (clipped to its range)."""
        xs, Ts = self._fine_integral()
        return np.interp(np.asarray(T, dtype=np.float64), Ts, xs)

    def alpha_numpy(self, v, centre):
        """Slow twin of :func:`alpha`."""
        x = np.asarray(v, dtype=np.float64) - centre
        a = np.minimum(1.0, self.peak * np.exp(-0.5 * (x / self.width) ** 2))
        return np.where((x > self.lo) & (x < self.hi), a, 0.0)

    def centroid_numpy(self, a, b, dx, centre=0.0, n: int = 400001):
        """Slow twin of :func:`segment_alpha_and_centroid`, by float64 quadrature in ``u``:
        ``(alpha, u_bar)`` of a step of length ``dx`` (world), its value running linearly from
        ``a`` to ``b``."""
        u = np.linspace(0.0, 1.0, n)
        x = a + u * (b - a) - centre
        tau = np.where((x > self.lo) & (x < self.hi), self.extinction_numpy(x), 0.0) * dx
        depth = np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) * np.diff(u))])
        made = -np.expm1(-depth)
        if made[-1] <= 0.0:
            return 0.0, 0.5
        # int u dF = F(1) - int F du
        return float(made[-1]), float(1.0 - np.sum(0.5 * (made[1:] + made[:-1]) * np.diff(u)) / made[-1])

    def point_numpy(self, a, b, dx, r=0.5, centre=0.0, n: int = 400001) -> float:
        """Slow twin of :func:`segment_alpha_and_point`'s point, by float64 quadrature: the
        fraction of a step of length ``dx`` (world), its value running linearly from ``a`` to
        ``b``, at which a fraction ``r`` of the step's opacity is made."""
        u = np.linspace(0.0, 1.0, n)
        x = a + u * (b - a) - centre
        tau = np.where((x > self.lo) & (x < self.hi), self.extinction_numpy(x), 0.0) * dx
        depth = np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) * np.diff(u))])
        made = -np.expm1(-depth)
        return float(np.interp(r * made[-1], made, u))

    def inputs(self, m) -> BandInputs:
        """The device values of this band alone on backend ``m`` (opaque)."""
        return band_inputs(m, [self])


def alpha(m, band: BandInputs, k, v, centre):
    """Opacity of band ``k`` for one step of length ``dx0`` at value ``v``."""
    x = v - centre
    width, peak = band.get(m, "width", k), band.get(m, "peak", k)
    a = dr.minimum(1.0, peak * dr.exp(-0.5 * dr.square(x / width)))
    return dr.select((x > band.get(m, "lo", k)) & (x < band.get(m, "hi", k)), a, 0.0)


def optical_depth(a):
    """The optical depth of opacity ``a`` (capped at :data:`~mi_amr.tolerances.OPACITY_CAP`,
    whose depth is finite)."""
    return -dr.log(1.0 - dr.minimum(a, tol.OPACITY_CAP))


def corrected(band: BandInputs, a, dx):
    """Opacity correction of ``a`` for a step of length ``dx`` (world units)."""
    return 1.0 - dr.power(dr.maximum(1.0 - dr.minimum(a, tol.OPACITY_CAP), 0.0), dx / band.dx0)


def integral(m, band: BandInputs, k, x):
    """``I(x)`` of band ``k``: its extinction integrated from its support's low end to offset
    ``x``."""
    lo, hi = band.get(m, "lo", k), band.get(m, "hi", k)
    u = dr.clip((x - lo) / (hi - lo), 0.0, 1.0) * TABLE_SIZE
    i = dr.minimum(m.UInt32(dr.floor(u)), TABLE_SIZE - 1) + k * (TABLE_SIZE + 1)
    f = u - m.Float(i - k * (TABLE_SIZE + 1))
    return dr.lerp(dr.gather(m.Float, band.table, i), dr.gather(m.Float, band.table, i + 1), f)


def cut_point(m, band: BandInputs, k, x):
    """What a ramp end at offset ``x`` contributes to :func:`_ramp_depth`, shared by the
    steps on either side of it: band ``k``'s integral there, and its shape's extinction (per
    ``dx0``) there clipped to the support."""
    clipped = dr.clip(x, band.get(m, "lo", k), band.get(m, "hi", k))
    return integral(m, band, k, x), _shape_tau(m, band, k, clipped)


@dataclass
class Ramp:
    """A step of length ``dx`` (world) along which the value goes linearly from ``a`` to
    ``b``."""

    a: Float
    b: Float
    dx: Float


def _ramp_depth(m, band: BandInputs, k, ramp: Ramp, centre, ends=None):
    """Band ``k``'s optical depth over a step of length ``dx`` (world) along which the value
    goes linearly from ``a`` to ``b``; with the integral at both ends and whether the ramp is
    short (it holds less than :data:`~mi_amr.tolerances.SHORT_RAMP_DEPTH` of the band's
    integral). A short ramp's depth is Simpson's rule of the extinction over its part inside
    the support (the difference of two float32 integrals would lose its digits). ``ends``:
    :func:`cut_point` of both ends where the caller has them."""
    xa, xb, dx = ramp.a - centre, ramp.b - centre, ramp.dx
    (Ia, ta), (Ib, tb) = ends if ends is not None else \
        (cut_point(m, band, k, xa), cut_point(m, band, k, xb))
    total = dr.gather(m.Float, band.table, m.UInt32(k * (TABLE_SIZE + 1) + TABLE_SIZE))
    short = dr.abs(Ib - Ia) < tol.SHORT_RAMP_DEPTH * total
    lo, hi = band.get(m, "lo", k), band.get(m, "hi", k)
    ca, cb = dr.clip(xa, lo, hi), dr.clip(xb, lo, hi)
    moving = xb != xa
    # the fraction of the ramp inside the support
    inside = dr.select(moving, dr.abs(cb - ca) / dr.abs(dr.select(moving, xb - xa, 1.0)),
                       dr.select((xa > lo) & (xa < hi), 1.0, 0.0))
    tm = _shape_tau(m, band, k, 0.5 * (ca + cb))
    simpson = inside * (ta + 4.0 * tm + tb) / (6.0 * band.dx0)
    tau_mean = dr.select(short, simpson, (Ib - Ia) / dr.select(short, 1.0, xb - xa))
    return dr.maximum(tau_mean, 0.0) * dx, Ia, Ib, short


def segment_alpha(m, band: BandInputs, k, ramp: Ramp, centre, ends=None):
    """Pre-integrated opacity of band ``k`` for the step ``ramp`` (``ends``: :func:`cut_point`
    of its ends' values, if known)."""
    return 1.0 - dr.exp(-_ramp_depth(m, band, k, ramp, centre, ends)[0])


def integral_inverse(m, band: BandInputs, k, reached):
    """The offset at which band ``k``'s integral reaches ``reached`` (the inverse of
    :func:`integral`)."""
    total = dr.gather(m.Float, band.table, m.UInt32(k * (TABLE_SIZE + 1) + TABLE_SIZE))
    base = k * (INVERSE_SIZE + 1)
    u = dr.clip(reached / total, 0.0, 1.0) * INVERSE_SIZE
    i = dr.minimum(m.UInt32(dr.floor(u)), INVERSE_SIZE - 1)
    f = u - m.Float(i)
    return dr.lerp(dr.gather(m.Float, band.inverse, i + base),
                   dr.gather(m.Float, band.inverse, i + base + 1), f)


def depth_fraction(s, tau):
    """The fraction of a step's optical depth ``tau`` in front of the place where a fraction
    ``s`` of its opacity is made: ``-ln(1 - s (1 - e^-tau)) / tau``; for thin steps its series
    (the closed form's float32 rounding would exceed the series' error)."""
    alpha = 1.0 - dr.exp(-tau)
    closed = -dr.log(dr.maximum(1.0 - s * alpha, tol.NO_WEIGHT)) / tau
    series = s + tau * (0.5 * (s * s - s) + tau * (s / 6.0 - 0.5 * s * s + s * s * s / 3.0))
    return dr.select(tau > tol.THIN_DEPTH, closed, series)


def _short_ramp_u(m, band, k, xa, xb, g):
    """Where along a short ramp (value offsets ``xa`` to ``xb``) a fraction ``g`` of its
    optical depth lies in front, with the extinction taken as linear along the part of it
    inside the support (the inverse table is too coarse for ramps shorter than a few of its
    cells)."""
    u0, u1 = _within(xa, xb, band.get(m, "lo", k), band.get(m, "hi", k))
    ta = _shape_tau(m, band, k, dr.lerp(xa, xb, u0))
    tb = _shape_tau(m, band, k, dr.lerp(xa, xb, u1))
    tm, dt = 0.5 * (ta + tb), tb - ta
    # root of (dt / 2) u^2 + ta u - g tm = 0 in [0, 1], in the form without cancellation
    u = 2.0 * g * tm / (ta + dr.sqrt(dr.maximum(ta * ta + 2.0 * dt * g * tm, 0.0)))
    return dr.lerp(u0, u1, dr.select(tm > 0.0, u, g))


def _shape_tau(m, band, k, x):
    """The extinction (per ``dx0``) of band ``k``'s shape at offset ``x``, support ignored."""
    a = dr.minimum(1.0, band.get(m, "peak", k) *
                   dr.exp(-0.5 * dr.square(x / band.get(m, "width", k))))
    return optical_depth(a)


def _place(m, band: BandInputs, k, ramp, r):
    """Where along a step (``ramp``: its value offsets, integrals, depth and shortness from
    :func:`_ramp`) a fraction ``r`` of its opacity is made (a fraction of the step)."""
    xa, xb, Ia, Ib, tau, short = ramp
    g = depth_fraction(r, tau)
    u_long = (integral_inverse(m, band, k, dr.lerp(Ia, Ib, g)) - xa) / (xb - xa)
    return dr.select(short, _short_ramp_u(m, band, k, xa, xb, g), u_long)


def _ramp(m, band: BandInputs, k, ramp: Ramp, centre):
    tau, Ia, Ib, short = _ramp_depth(m, band, k, ramp, centre)
    return ramp.a - centre, ramp.b - centre, Ia, Ib, tau, short


def segment_alpha_and_point(m, band: BandInputs, k, ramp: Ramp, centre, r=0.5):
    """:func:`segment_alpha`, and where along the step band ``k`` has made a fraction ``r`` of
    the step's opacity (a fraction of the step, 0 at ``a``). With ``r = 1/2`` (the median of
    its light) that is where a step is lit: for light arriving from the viewer's side it gives
    the shadow of the band in front exactly. A thin step gives the point where half its
    optical depth lies, an opaque one a point near its front."""
    ramped = _ramp(m, band, k, ramp, centre)
    return 1.0 - dr.exp(-ramped[4]), dr.clip(_place(m, band, k, ramped, r), 0.0, 1.0)


def _stretch(m, band: BandInputs, k, xa, xb, dx):
    """A ramp of value offsets ``xa`` to ``xb`` over length ``dx`` (world) as :func:`_ramp`
    gives it."""
    tau, Ia, Ib, short = _ramp_depth(m, band, k, Ramp(xa, xb, dx), 0.0)
    return xa, xb, Ia, Ib, tau, short


def _flank_centroid(m, band: BandInputs, k, ramp):
    """The centroid of a stretch on which the extinction is smooth: Gauss-Legendre in the
    fraction of its opacity, each node placed through the inverse table."""
    u_bar = 0.0
    for s, w in zip(GL_NODES, GL_WEIGHTS):
        u_bar += w * _place(m, band, k, ramp, s)
    return u_bar


def flat_centroid(tau):
    """The centroid of a stretch of constant extinction and depth ``tau``."""
    alpha = 1.0 - dr.exp(-tau)
    closed = 1.0 / tau - dr.exp(-tau) / dr.maximum(alpha, tol.NO_WEIGHT)
    return dr.select(tau > tol.THIN_DEPTH, closed, 0.5 - tau / 12.0)


def segment_alpha_and_centroid(m, band: BandInputs, k, ramp: Ramp, centre):
    """Pre-integrated opacity of band ``k`` over a step of length ``dx`` (world) along which
    the value goes linearly from ``a`` to ``b``, and the step's centroid ``u_bar`` (a fraction
    of the step, 0 at ``a``; see the module docstring): the light of the step is
    ``alpha * lerp(E_front, E_back, u_bar)`` where the shaded colour runs linearly along it,
    so it is shaded there. The step is split where it enters and leaves the band's plateau
    (where the opacity is capped): there the extinction is constant and the centroid has a
    closed form; on the flanks it is smooth, and its kink at the cap would spoil the
    quadrature."""
    a, b, dx = ramp.a, ramp.b, ramp.dx
    xa, xb = a - centre, b - centre
    cap = band.get(m, "cap", k)
    p0, p1 = _within(xa, xb, -cap, cap)
    ends = [0.0 * dx, p0, p1, 1.0 + 0.0 * dx]
    alpha = m.Float(0.0)
    moment = m.Float(0.0)      # int u dF, F the opacity made from the front
    for j in range(3):
        u0, u1 = ends[j], ends[j + 1]
        part = _stretch(m, band, k, dr.lerp(xa, xb, u0), dr.lerp(xa, xb, u1), dx * (u1 - u0))
        a_j = 1.0 - dr.exp(-part[4])
        c_j = flat_centroid(part[4]) if j == 1 else _flank_centroid(m, band, k, part)
        moment += (1.0 - alpha) * a_j * dr.lerp(u0, u1, c_j)
        alpha += (1.0 - alpha) * a_j
    u_bar = dr.select(alpha > 0.0, moment / dr.maximum(alpha, tol.NO_WEIGHT), 0.5)
    return alpha, dr.clip(u_bar, 0.0, 1.0)


def _within(xa, xb, lo, hi):
    """The fractions ``(p0, p1)`` of a ramp of offsets ``xa`` to ``xb`` between which it lies
    in ``[lo, hi]`` (both at the same place where it misses it, before or after)."""
    moving = xb != xa
    span = dr.select(moving, xb - xa, 1.0)
    u_lo, u_hi = (lo - xa) / span, (hi - xa) / span
    p0 = dr.clip(dr.minimum(u_lo, u_hi), 0.0, 1.0)
    p1 = dr.maximum(dr.clip(dr.maximum(u_lo, u_hi), 0.0, 1.0), p0)
    inside = (xa >= lo) & (xa <= hi)
    return (dr.select(moving, p0, dr.select(inside, 0.0, 1.0)),
            dr.select(moving, p1, 1.0))


def in_order(m, alphas, lights, centres, rising):
    """One step crossed by bands of disjoint supports: each band's opacity ``alphas[k]`` and
    light ``lights[k]`` (premultiplied), composited front to back in the order the ramp meets
    them (ascending centres where the value ``rising``, else descending). Returns the step's
    light and transmittance."""
    light = 0.0 * lights[0]
    trans = m.Float(1.0)
    for k, (a, c) in enumerate(zip(alphas, lights)):
        seen = m.Float(1.0)
        for j in range(len(alphas)):
            if j != k:
                before = dr.select(rising, centres[j] < centres[k], centres[j] > centres[k])
                seen *= dr.select(before, 1.0 - alphas[j], 1.0)
        light += seen * c
        trans *= 1.0 - a
    return light, trans


def combine(alphas):
    """The opacity of bands of opacities ``alphas`` together, and each band's share of it (its
    optical depth over the total; 0 where all are 0)."""
    if len(alphas) == 1:
        return alphas[0], [1.0]
    taus = [optical_depth(a) for a in alphas]
    total = taus[0]
    for t in taus[1:]:
        total = total + t
    shares = [dr.select(total > 0.0, t / total, 0.0) for t in taus]
    return 1.0 - dr.exp(-total), shares
