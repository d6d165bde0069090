"""The finite extremes of values that come a chunk at a time (a field read from a file a
stretch at a time, a level's values cut in pieces): colour ranges taken without holding a
field whole."""

from __future__ import annotations

import math

import numpy as np


def finite_extremes(chunks) -> tuple:
    """``(lo, hi)``: the least and the greatest finite value of the arrays ``chunks`` (NumPy
    scalars of their dtype), ``(inf, -inf)`` where none is finite."""
    lo, hi = np.inf, -np.inf
    for c in chunks:
        finite = c if np.isfinite(c).all() else c[np.isfinite(c)]
        if finite.size:
            lo, hi = min(lo, finite.min()), max(hi, finite.max())
    return lo, hi


def finite_range(chunks) -> tuple:
    """:func:`finite_extremes` as Python floats, ``(nan, nan)`` where no value is finite (what
    :meth:`~mi_amr.core.volume.AMRVolume.value_range` gives for the same values)."""
    lo, hi = finite_extremes(chunks)
    if lo > hi:
        return (math.nan, math.nan)
    return (float(lo), float(hi))
