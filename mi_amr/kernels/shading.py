"""Colour maps, the volume-mode opacity band, and Phong shading (Dr.Jit, generic over a backend).

* :class:`ColorMap` -- value/colour pairs as in the course report (section 3.9): a flat band of
  ``+- band`` around each value takes that value's colour, colours are interpolated linearly
  between bands, and clamped outside the first and last value. A named matplotlib map is turned
  into 256 pairs over a value range (with no flat band).
* :class:`OpacityBand` -- the Gaussian opacity band around the isovalue (section 3.7):
  ``alpha(v) = min(1, peak * exp(-(v - centre)^2 / (2 width^2)))`` inside ``(lo, hi)``, zero
  outside; its opacity correction ``alpha' = 1 - (1 - alpha)^(dx / dx0)`` (section 3.8), and a
  pre-integrated form (lecture): the optical depth of a segment along which the value goes
  linearly from ``a`` to ``b`` is ``dx * (T(b) - T(a)) / (b - a)`` with ``T`` the integral of the
  extinction ``tau(v) = -ln(1 - alpha(v)) / dx0``, tabulated once.
* :func:`phong_direct` -- ``C = C_obj (ka I_A + kd I_L max(N.L, 0)) + ks I_L max(N.H, 0)^ns``
  (the light-dependent part, per emitter).

Colours are linear RGB triples.
"""

from __future__ import annotations

import math

import drjit as dr
import numpy as np

from mi_amr.kernels.device import gather
from mi_amr.errors import AMRError

COLOR_BAND = 0.0025       # course report: each value's colour holds within +-0.0025
OPACITY_CAP = 1.0 - 1e-4  # alpha = 1 would mean infinite extinction in the pre-integrated table


class ColorMap:
    """Piecewise-linear colour map from sorted value/colour pairs (see the module docstring)."""

    def __init__(self, values, colors, band: float = COLOR_BAND):
        values = np.asarray(values, dtype=np.float64)
        colors = np.asarray(colors, dtype=np.float64).reshape(len(values), 3)
        if len(values) == 0:
            raise AMRError("colormap: at least one value/colour pair is needed")
        order = np.argsort(values)
        self.values, self.colors, self.band = values[order], colors[order], float(band)
        if np.any(np.diff(self.values) < 2 * self.band):
            raise AMRError(f"colormap: values {self.values.tolist()} must be at least "
                           f"{2 * self.band:g} apart (each holds its colour over +-{self.band:g})")

    @classmethod
    def parse(cls, text: str, value_range=None):
        """``"v: r g b, v: r g b, ..."`` or a matplotlib map name (then over ``value_range``)."""
        text = text.strip()
        if ":" in text:
            values, colors = [], []
            for item in text.split(","):
                try:
                    v, rgb = item.split(":")
                    c = [float(x) for x in rgb.split()]
                    values.append(float(v))
                except ValueError:
                    raise AMRError(f"colormap: cannot read '{item.strip()}'; expected "
                                   f"'value: r g b' pairs separated by commas") from None
                if len(c) != 3 or not all(math.isfinite(x) for x in c + [values[-1]]):
                    raise AMRError(f"colormap: '{item.strip()}' needs a value and 3 colour "
                                   f"components")
                colors.append(c)
            return cls(values, colors)
        try:
            from matplotlib import colormaps
        except ImportError:
            raise AMRError(f"colormap '{text}': named colour maps need matplotlib "
                           f"(pip install 'mi_amr[plot]'), or give 'value: r g b' pairs") from None
        if text not in colormaps:
            raise AMRError(f"colormap '{text}' is not a matplotlib colour map; e.g. viridis, "
                           f"magma, coolwarm, or give 'value: r g b' pairs")
        lo, hi = value_range
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
            hi = lo + 1.0
        x = np.linspace(0.0, 1.0, 256)
        rgb = colormaps[text](x)[:, :3]
        return cls(lo + x * (hi - lo), rgb ** 2.2, band=0.0)

    def numpy(self, x):
        """Slow twin: colours ``(N, 3)`` for values ``x``."""
        x = np.asarray(x, dtype=np.float64)
        out = np.empty((len(x), 3))
        for c in range(3):
            xp = np.ravel(np.column_stack([self.values - self.band, self.values + self.band]))
            fp = np.repeat(self.colors[:, c], 2)
            out[:, c] = np.interp(x, xp, fp)
        return out

    def device(self, m):
        """Arrays for :meth:`lookup` on backend ``m``."""
        edges = np.ravel(np.column_stack([self.values - self.band, self.values + self.band]))
        colors = np.repeat(self.colors, 2, axis=0)
        mk = (lambda a: dr.scalar.ArrayXf(a)) if m is dr.scalar else m.Float
        return mk(edges.astype(np.float32)), mk(colors.astype(np.float32).ravel()), len(edges)

    @staticmethod
    def lookup(m, table, x):
        """Colour (``m.Array3f``) of values ``x`` from the arrays of :meth:`device`: binary
        search for the bracketing edges, then linear interpolation (clamped at the ends)."""
        edges, colors, n = table
        lo = m.UInt32(0)
        size = n
        # Branch-free binary search over a table whose size is known when tracing.
        while size > 1:
            half = size // 2
            probe = gather(m.Float, edges, lo + half)
            lo = dr.select(probe <= x, lo + half, lo)
            size -= half
        hi = dr.minimum(lo + 1, n - 1)
        e0 = gather(m.Float, edges, lo)
        e1 = gather(m.Float, edges, hi)
        c0 = gather(m.Array3f, colors, lo)
        c1 = gather(m.Array3f, colors, hi)
        w = dr.select(e1 > e0, dr.clip((x - e0) / (e1 - e0), 0.0, 1.0), 0.0)
        return dr.lerp(c0, c1, w)


class OpacityBand:
    """The Gaussian opacity band of volume mode (see the module docstring), centred on the
    isovalue. ``width`` and the support ``(lo, hi)`` are offsets from the centre, so a new
    isovalue moves the band without rebuilding anything. ``dx0`` is the step length (world
    units) at which ``alpha`` is the opacity of one step."""

    def __init__(self, width: float = 0.004, support=None, peak: float = 1.6, dx0: float = 1.0):
        if not width > 0:
            raise AMRError(f"amr_iso: parameter 'band_width' must be > 0, got {width}")
        if not peak > 0:
            raise AMRError(f"amr_iso: parameter 'band_peak' must be > 0, got {peak}")
        lo, hi = support if support is not None else (-2.0 * width, 2.0 * width)
        if not lo < 0.0 < hi:
            raise AMRError(f"amr_iso: parameter 'band_support' must contain the isovalue "
                           f"(offsets {lo:g}, {hi:g})")
        self.width, self.lo, self.hi, self.peak = float(width), float(lo), float(hi), float(peak)
        self.dx0 = float(dx0)
        # Integral of the extinction over value offsets, tabulated across the support.
        self.table_x = np.linspace(self.lo, self.hi, 1025)
        tau = -np.log1p(-np.minimum(self.alpha_numpy(self.table_x, 0.0), OPACITY_CAP)) / self.dx0
        self.table_T = np.concatenate([[0.0], np.cumsum(0.5 * (tau[1:] + tau[:-1]) *
                                                        np.diff(self.table_x))])

    def alpha_numpy(self, v, centre):
        x = np.asarray(v, dtype=np.float64) - centre
        a = np.minimum(1.0, self.peak * np.exp(-0.5 * (x / self.width) ** 2))
        return np.where((x > self.lo) & (x < self.hi), a, 0.0)

    def alpha(self, m, v, centre):
        """Opacity of one step of length ``dx0`` at value ``v``."""
        x = v - centre
        a = dr.minimum(1.0, self.peak * dr.exp(-0.5 * dr.square(x / self.width)))
        return dr.select((x > self.lo) & (x < self.hi), a, 0.0)

    def corrected(self, alpha, dx):
        """Opacity correction for a step of length ``dx`` (world units)."""
        return 1.0 - dr.power(dr.maximum(1.0 - dr.minimum(alpha, OPACITY_CAP), 0.0),
                              dx / self.dx0)

    def device(self, m):
        mk = (lambda a: dr.scalar.ArrayXf(a)) if m is dr.scalar else m.Float
        return mk(self.table_T.astype(np.float32))

    def integral(self, m, table, x):
        """``T(x)``: the extinction integrated from the support's low end to offset ``x``."""
        n = len(self.table_x) - 1
        u = dr.clip((x - self.lo) / (self.hi - self.lo), 0.0, 1.0) * n
        i = dr.minimum(m.UInt32(dr.floor(u)), n - 1)
        f = u - m.Float(i)
        return dr.lerp(gather(m.Float, table, i), gather(m.Float, table, i + 1), f)

    def segment_alpha(self, m, table, a, b, dx, centre):
        """Pre-integrated opacity of a step of length ``dx`` (world) along which the value goes
        linearly from ``a`` to ``b``."""
        xa, xb = a - centre, b - centre
        Ta, Tb = self.integral(m, table, xa), self.integral(m, table, xb)
        close = dr.abs(xb - xa) < 1e-6 * self.width
        tau_point = -dr.log(1.0 - dr.minimum(self.alpha(m, 0.5 * (a + b), centre),
                                             OPACITY_CAP)) / self.dx0
        tau_mean = dr.select(close, tau_point, (Tb - Ta) / (xb - xa))
        return 1.0 - dr.exp(-dr.maximum(tau_mean, 0.0) * dx)


def phong_direct(normal, to_light, to_eye, color, light, kd, ks, shininess):
    """Light from one emitter by Phong's model (lecture 23):
    ``color kd light max(N.L, 0) + ks light max(N.H, 0)^ns``. Vectors are unit length; ``light``
    is the incident radiance, already shadowed. (The ambient term ``color ka ambient`` is added
    once per shaded point by the caller.)"""
    n_l = dr.maximum(dr.dot(normal, to_light), 0.0)
    h = dr.normalize(to_light + to_eye)
    n_h = dr.maximum(dr.dot(normal, h), 0.0)
    spec = dr.select(n_l > 0.0, dr.power(n_h, shininess), 0.0)
    return color * (kd * light * n_l) + ks * light * spec
