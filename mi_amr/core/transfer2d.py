"""The 2D transfer function of volume mode (the lecture's value / |grad f| plane), on the host.

A :class:`Transfer2D` is a table of opacities over two axes: its columns are the field's value
``v`` from ``v0`` to ``v1`` (field units), its rows the gradient magnitude ``g = |grad f|`` from
``g0`` to ``g1`` (field units per volume-world unit), ascending: ``table[j, i]`` is the opacity
at ``(v0 + i (v1 - v0) / (cols - 1), g0 + j (g1 - g0) / (rows - 1))``. In between it is
bilinear; outside ``[v0, v1]`` it is 0; ``g`` is clamped to ``[g0, g1]``. Like the 1D band's
(:mod:`mi_amr.kernels.band`), an opacity is that of a step of length ``dx0`` (the finest cell
width), so the kernels' opacity correction applies unchanged.

The table comes from a file (``transfer2d`` with ``transfer2d_range``) or is rasterized from
Gaussian blobs in the plane (``transfer2d_blobs``, :func:`from_blobs`), so the kernels have one
code path. Every mistake is an :class:`~mi_amr.errors.AMRError` naming the parameter or file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError

# Rasterized blobs: this many table samples per (narrowest) sigma, so the bilinear table stays
# within about 1 % of the Gaussian; ...
BLOB_SAMPLES_PER_SIGMA = 8
# ... and at most this many columns or rows (4 MiB of float32 at the cap), which still resolves
# a blob of a 1/100 of the plane's span.
BLOB_TABLE_MAX = 1024
# Blobs cover the plane to this many sigmas each side of their centres.
BLOB_REACH = 3.0


@dataclass
class Transfer2D:
    """A checked table (float64, shape ``(rows, cols)``) and its ranges (see the module
    docstring); ``source`` names where it came from, for messages."""

    table: np.ndarray
    v0: float
    v1: float
    g0: float
    g1: float
    source: str = "transfer2d"

    def __post_init__(self):
        self.table = check_table(self.table, self.source)
        self.v0, self.v1, self.g0, self.g1 = check_range((self.v0, self.v1, self.g0, self.g1))

    @property
    def shape(self):
        return self.table.shape

    def alpha_numpy(self, v, g):
        """Slow twin of :func:`mi_amr.kernels.transfer2d.alpha` (float64): the bilinear
        opacity at values ``v`` (field) and gradient magnitudes ``g`` (field per world unit)."""
        v, g = np.broadcast_arrays(np.asarray(v, np.float64), np.asarray(g, np.float64))
        rows, cols = self.table.shape
        inside = (v >= self.v0) & (v <= self.v1)
        u = np.where(inside, (v - self.v0) / (self.v1 - self.v0), 0.0) * (cols - 1)
        w = np.clip(np.nan_to_num((g - self.g0) / (self.g1 - self.g0)), 0.0, 1.0) * (rows - 1)
        i = np.clip(np.floor(u).astype(np.int64), 0, cols - 2)
        j = np.clip(np.floor(w).astype(np.int64), 0, rows - 2)
        fu, fw = u - i, w - j
        t = self.table
        low = t[j, i] * (1 - fu) + t[j, i + 1] * fu
        high = t[j + 1, i] * (1 - fu) + t[j + 1, i + 1] * fu
        return np.where(inside, low * (1 - fw) + high * fw, 0.0)

    def row_integrals(self, dx0: float, cap: float) -> np.ndarray:
        """Per row (gradient magnitude), the extinction ``-ln(1 - min(alpha, cap)) / dx0``
        (per world unit) integrated over the values from ``v0`` to each column (trapezoids;
        field units per world unit): along a ramp of value at a fixed gradient the optical
        depth is the difference of two entries over the ramp's value change."""
        tau = -np.log1p(-np.minimum(self.table, cap)) / dx0
        step = (self.v1 - self.v0) / (self.table.shape[1] - 1)
        steps = 0.5 * (tau[:, 1:] + tau[:, :-1]) * step
        return np.concatenate([np.zeros((tau.shape[0], 1)), np.cumsum(steps, axis=1)], axis=1)

    def value_support(self):
        """``(lo, hi)``: the values (field) outside which the opacity is 0 at every gradient --
        the columns holding some opacity and one column each side (the bilinear ramp). A kd
        node whose values lie outside it is empty space."""
        cols = self.table.shape[1]
        used = np.flatnonzero(np.any(self.table > 0.0, axis=0))
        if used.size == 0:
            return (self.v0, self.v0)
        step = (self.v1 - self.v0) / (cols - 1)
        lo = self.v0 + max(int(used[0]) - 1, 0) * step
        hi = self.v0 + min(int(used[-1]) + 1, cols - 1) * step
        return (lo, hi)


def check_table(table, source: str = "transfer2d") -> np.ndarray:
    """``table`` as float64 if it is a 2-D array of at least 2 x 2 finite opacities in
    ``[0, 1]``; an AMRError naming ``source`` otherwise."""
    try:
        t = np.array(table, dtype=np.float64)
    except (TypeError, ValueError):
        raise AMRError(f"{source}: expected a 2-D table of numbers (rows = |grad f|, "
                       f"columns = value)") from None
    if t.ndim != 2:
        raise AMRError(f"{source}: expected a 2-D table (rows = |grad f|, columns = value), "
                       f"got shape {t.shape}")
    if t.shape[0] < 2 or t.shape[1] < 2:
        raise AMRError(f"{source}: expected at least 2 x 2 entries, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise AMRError(f"{source}: the table holds NaN or infinite entries "
                       f"({int(np.sum(~np.isfinite(t)))} of {t.size})")
    if t.min() < 0.0 or t.max() > 1.0:
        raise AMRError(f"{source}: opacities must lie in [0, 1], got [{t.min():g}, "
                       f"{t.max():g}]")
    return t


def check_range(values, name: str = "transfer2d_range"):
    """``(v0, v1, g0, g1)`` as floats if ``v0 < v1`` and ``0 <= g0 < g1``, all finite."""
    try:
        v0, v1, g0, g1 = (float(x) for x in values)
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter '{name}' must be four numbers 'v0 v1 g0 g1', "
                       f"got {values!r}") from None
    if not all(math.isfinite(x) for x in (v0, v1, g0, g1)):
        raise AMRError(f"amr_iso: parameter '{name}' must hold finite numbers, got {values!r}")
    if not v0 < v1:
        raise AMRError(f"amr_iso: parameter '{name}' needs v0 < v1 (the value range), got "
                       f"{v0:g} {v1:g}")
    if not 0.0 <= g0 < g1:
        raise AMRError(f"amr_iso: parameter '{name}' needs 0 <= g0 < g1 (the |grad f| range), "
                       f"got {g0:g} {g1:g}")
    return v0, v1, g0, g1


def parse_range(text, name: str = "transfer2d_range"):
    """``transfer2d_range``: ``"v0 v1 g0 g1"`` (commas allowed) -> checked floats."""
    items = text.replace(",", " ").split() if isinstance(text, str) else text
    if len(items) != 4:
        raise AMRError(f"amr_iso: parameter '{name}' must be four numbers 'v0 v1 g0 g1', "
                       f"got {text!r}")
    return check_range(items, name)


def parse_blobs(text, name: str = "transfer2d_blobs"):
    """``transfer2d_blobs``: ``"v g sigma_v sigma_g peak; ..."`` -> a list of 5-tuples (value
    and sigma_v in field units, g and sigma_g in field per world unit, peak > 0)."""
    groups = [s for s in str(text).split(";") if s.strip()]
    if not groups:
        raise AMRError(f"amr_iso: parameter '{name}' needs at least one blob "
                       f"'v g sigma_v sigma_g peak', got {text!r}")
    blobs = []
    for s in groups:
        try:
            blob = tuple(float(x) for x in s.replace(",", " ").split())
        except ValueError:
            blob = ()
        if len(blob) != 5 or not all(math.isfinite(x) for x in blob):
            raise AMRError(f"amr_iso: parameter '{name}': each blob is five finite numbers "
                           f"'v g sigma_v sigma_g peak', got {s.strip()!r}")
        if not (blob[2] > 0 and blob[3] > 0):
            raise AMRError(f"amr_iso: parameter '{name}': sigma_v and sigma_g must be > 0, "
                           f"got {s.strip()!r}")
        if not blob[4] > 0:
            raise AMRError(f"amr_iso: parameter '{name}': peak must be > 0, got {s.strip()!r}")
        blobs.append(blob)
    return blobs


def blobs_numpy(blobs, v, g):
    """The blobs' opacity ``min(1, sum peak exp(-((v - vi) / sv)^2 / 2 - ((g - gi) / sg)^2 /
    2))`` at values ``v`` and gradient magnitudes ``g`` (float64, exact)."""
    v, g = np.asarray(v, np.float64), np.asarray(g, np.float64)
    total = np.zeros(np.broadcast(v, g).shape)
    for vi, gi, sv, sg, peak in blobs:
        total = total + peak * np.exp(-0.5 * ((v - vi) / sv) ** 2 - 0.5 * ((g - gi) / sg) ** 2)
    return np.minimum(total, 1.0)


def _axis(lo, hi, sigma):
    """Samples of ``[lo, hi]`` at :data:`BLOB_SAMPLES_PER_SIGMA` per ``sigma`` (capped)."""
    n = int(math.ceil((hi - lo) / sigma * BLOB_SAMPLES_PER_SIGMA)) + 1
    return np.linspace(lo, hi, min(max(n, 2), BLOB_TABLE_MAX))


def from_blobs(blobs) -> Transfer2D:
    """The blobs rasterized into a table: values over every blob's ``+- 3 sigma_v``, gradient
    magnitudes from 0 (so a smooth region is looked up where it lies, not clamped up to the
    lowest blob's edge) to every blob's ``g + 3 sigma_g``."""
    b = np.asarray(blobs, dtype=np.float64)
    v0 = float(np.min(b[:, 0] - BLOB_REACH * b[:, 2]))
    v1 = float(np.max(b[:, 0] + BLOB_REACH * b[:, 2]))
    g1 = float(np.max(b[:, 1] + BLOB_REACH * b[:, 3]))
    if not g1 > 0.0:
        raise AMRError("amr_iso: parameter 'transfer2d_blobs': every blob lies at |grad f| < 0 "
                       "(gradient magnitudes are >= 0)")
    vs, gs = _axis(v0, v1, b[:, 2].min()), _axis(0.0, g1, b[:, 3].min())
    table = blobs_numpy(blobs, vs[None, :], gs[:, None])
    return Transfer2D(table, v0, v1, 0.0, g1, source="amr_iso: parameter 'transfer2d_blobs'")


def load_npy(path) -> np.ndarray:
    """The table in the ``.npy`` file ``path`` (no pickles); an AMRError naming the file when
    it cannot be read."""
    try:
        return np.load(Path(path), allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise AMRError(f"{path}: cannot read a 2D transfer function table ({e})") from None
