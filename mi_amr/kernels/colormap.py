"""Colour maps: value/colour pairs (course report, section 3.9) or a matplotlib map, looked up
in a kernel from a fixed-size table, so a new map or colour range is new kernel *input* only.

A map is a piecewise-linear function on the unit interval ``u`` in ``[0, 1]``; the colour range
``(lo, hi)`` (field units) maps a value ``v`` to ``u = (v - lo) / (hi - lo)``. Below the first
and above the last edge the colour is clamped.

* Pairs ``"v: r g b, ..."``: each value holds its colour over ``+- hold`` and colours are
  interpolated linearly between the holds. ``hold`` is 1/24 of the pairs' span (the report's
  +-0.0025 on its pairs 0.012 ... 0.072), at most a quarter of the gap to the nearest pair, so
  it scales with the field's units. The default colour range is the first and last pair's
  values; another range stretches the pairs onto it.
* A matplotlib map: 256 colours evenly over the colour range (default: the field's range).

Colours are linear RGB (a matplotlib map's sRGB colours are linearised with gamma 2.2).
:meth:`ColorMap.numpy` is the slow twin of :func:`lookup`.
"""

from __future__ import annotations

import math

import drjit as dr
import numpy as np

from mi_amr.errors import AMRError

TABLE_SIZE = 512          # edges in every device table (a power of two: a fixed binary search)
HOLD_FRACTION = 1.0 / 24.0
HOLD_GAP_FRACTION = 0.25
NAMED_COLORS = 256


class ColorMap:
    """Edges ``u`` (sorted, on the unit interval) with a colour each, and the default colour
    range (field units). Build it with :meth:`parse`, :meth:`from_pairs` or :meth:`named`."""

    def __init__(self, edges, colors, value_range):
        self.edges = np.asarray(edges, dtype=np.float64)
        self.colors = np.asarray(colors, dtype=np.float64).reshape(len(self.edges), 3)
        if len(self.edges) > TABLE_SIZE:
            raise AMRError(f"colormap: at most {TABLE_SIZE // 2} value/colour pairs")
        self.value_range = check_range(value_range, "color_range")

    @classmethod
    def from_pairs(cls, values, colors):
        values = np.asarray(values, dtype=np.float64)
        colors = np.asarray(colors, dtype=np.float64).reshape(len(values), 3)
        if len(values) == 0:
            raise AMRError("colormap: at least one value/colour pair is needed")
        order = np.argsort(values, kind="stable")
        values, colors = values[order], colors[order]
        gaps = np.diff(values)
        if np.any(gaps <= 0):
            raise AMRError(f"colormap: the pairs' values must differ, got {values.tolist()}")
        span = values[-1] - values[0]
        hold = HOLD_FRACTION * span
        if len(gaps):
            hold = min(hold, HOLD_GAP_FRACTION * float(gaps.min()))
        lo, hi = (values[0], values[-1]) if span > 0 else (values[0] - 0.5, values[0] + 0.5)
        edges = np.ravel(np.column_stack([values - hold, values + hold]))
        return cls((edges - lo) / (hi - lo), np.repeat(colors, 2, axis=0), (lo, hi))

    @classmethod
    def named(cls, name: str, value_range):
        try:
            from matplotlib import colormaps
        except ImportError:
            raise AMRError(f"colormap '{name}': named colour maps need matplotlib "
                           f"(pip install 'mi_amr[plot]'), or give 'value: r g b' pairs") from None
        if name not in colormaps:
            raise AMRError(f"colormap '{name}' is not a matplotlib colour map; e.g. viridis, "
                           f"magma, coolwarm, or give 'value: r g b' pairs")
        u = np.linspace(0.0, 1.0, NAMED_COLORS)
        return cls(u, colormaps[name](u)[:, :3] ** 2.2, usable_range(value_range))

    @classmethod
    def parse(cls, text: str, data_range=None):
        """``"v: r g b, v: r g b, ..."`` or a matplotlib map name (over ``data_range``)."""
        text = text.strip()
        if ":" not in text:
            return cls.named(text, data_range)
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
        return cls.from_pairs(values, colors)

    def table(self):
        """``(edges, colors)`` padded to :data:`TABLE_SIZE` edges (float32, colours flat RGB):
        the last edge and colour repeat, which the lookup reads as the clamped end."""
        n = len(self.edges)
        edges = np.empty(TABLE_SIZE, dtype=np.float32)
        colors = np.empty((TABLE_SIZE, 3), dtype=np.float32)
        edges[:n], edges[n:] = self.edges, self.edges[-1]
        colors[:n], colors[n:] = self.colors, self.colors[-1]
        return edges, colors.ravel()

    def numpy(self, x, value_range=None):
        """Slow twin of :func:`lookup`: colours ``(N, 3)`` of values ``x``."""
        lo, hi = self.value_range if value_range is None else value_range
        u = (np.asarray(x, dtype=np.float64) - lo) / (hi - lo)
        return np.stack([np.interp(u, self.edges, self.colors[:, c]) for c in range(3)], axis=1)


def check_range(value_range, name):
    lo, hi = (float(v) for v in value_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise AMRError(f"amr_iso: parameter '{name}' needs finite low < high, got "
                       f"({lo:g}, {hi:g})")
    return lo, hi


def usable_range(value_range):
    """A data range made usable as a colour range (a constant field gets a unit-wide one)."""
    lo, hi = (float(v) for v in (value_range if value_range is not None else (0.0, 1.0)))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return 0.0, 1.0
    return (lo, hi) if hi > lo else (lo - 0.5, lo + 0.5)


def lookup(m, edges, colors, value_range, x):
    """Colour (``m.Array3f``) of values ``x``: ``edges`` and ``colors`` from
    :meth:`ColorMap.table` and ``value_range`` (``m.Array2f``), all device arrays. A binary
    search of fixed depth finds the last edge at or below ``u``, then colours are interpolated
    linearly (equal edges: the lower colour)."""
    u = (x - value_range.x) / (value_range.y - value_range.x)
    lo = m.UInt32(0)
    size = TABLE_SIZE
    while size > 1:
        half = size // 2
        probe = dr.gather(m.Float, edges, lo + half)
        lo = dr.select(probe <= u, lo + half, lo)
        size -= half
    hi = dr.minimum(lo + 1, TABLE_SIZE - 1)
    e0 = dr.gather(m.Float, edges, lo)
    e1 = dr.gather(m.Float, edges, hi)
    c0 = dr.gather(m.Array3f, colors, lo)
    c1 = dr.gather(m.Array3f, colors, hi)
    w = dr.select(e1 > e0, dr.clip((u - e0) / (e1 - e0), 0.0, 1.0), 0.0)
    return dr.lerp(c0, c1, w)
