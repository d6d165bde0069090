"""A field's statistics over its leaf cells and the isovalues worth trying first (NumPy only).

An isovalue is scored by how many pairs of neighbouring leaf cells (inside a grid, along each
axis) it separates: a value between the pair's two values puts the surface between them, so
the count is a proxy for the surface's area. The candidates are the values at evenly spaced
percentiles and evenly spaced values between the 2nd and 98th percentiles; the pick is the
best-scoring, and among near-ties (within :data:`TIE` of the best) the one nearest their
middle in percentile rank (a field that jumps from 0 to 1 through cut cells gets a value
halfway through them, not 0.01; a heavy tail does not pull the pick into it).

The Q-criterion is the exception. Its surface of most crossings is near 0, in the
small-scale fluctuations everywhere, while vortices are where it is positive (rotation
dominating strain, Hunt et al. 1988): where at least :data:`Q_POSITIVE_MIN` of its leaf cells
hold a positive value, its suggestions are the values below which :data:`Q_POSITIVE_RANKS`
of those positive values lie.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_amr.core.batches import axis_pairs, flat_field, shape_batches, stacked
from mi_amr.errors import AMRError

PERCENTILES = (1, 10, 50, 90, 99)
MAX_PAIRS = 1 << 21        # neighbour pairs scored at most (an even subsample beyond)
TIE = 0.9                  # candidates scoring at least this share of the best are near-ties
DISTINCT = 0.15            # suggestions lie at least this far apart in percentile rank ...
MIN_SPAN = 0.01            # ... and in value (share of the 2-98 percentile range); a pair of
                           # cells counts only when its values differ by more than this
# The Q-criterion's suggestions: these shares of its positive leaf values lie below them (0.8
# gives the sphere wake's hand-tuned 0.05), where at least this share of its cells is positive.
Q_POSITIVE_RANKS = (0.8, 0.5, 0.95)
Q_POSITIVE_MIN = 0.01
BAND_RANKS = 0.02          # a picked band's width: half the distance from its isovalue to the
                           # value this share of the leaf cells away in rank, on the nearer side
                           # (suggest_band_width)


@dataclass
class FieldStats:
    """``field``'s range, its values at :data:`PERCENTILES` and its suggested isovalues (the
    first is the pick) with volume mode's band width for each (:func:`suggest_band_width`),
    over ``cells`` finite leaf cells; ``levels`` holds per level ``(level, finite leaf cells,
    min, max)`` (min and max None for a level with none)."""

    field: str
    cells: int
    vmin: float
    vmax: float
    percentiles: dict
    suggested: list
    levels: list
    band_widths: list

    def text(self) -> str:
        pct = "  ".join(f"p{q} {v:.6g}" for q, v in self.percentiles.items())
        lines = [f"{self.field}: [{self.vmin:.6g}, {self.vmax:.6g}] over {self.cells:,} leaf "
                 f"cells", f"  percentiles  {pct}"]
        for level, n, lo, hi in self.levels:
            where = f"[{lo:.6g}, {hi:.6g}]" if n else "-"
            lines.append(f"  level {level}: {n:>12,} leaf cells  {where}")
        lines.append("  suggested isovalues: " + ", ".join(f"{v:.6g}" for v in self.suggested))
        lines.append("  their band widths (volume mode): " +
                     ", ".join(f"{w:.6g}" for w in self.band_widths))
        return "\n".join(lines)


def leaf_values(volume, field: str, level=None) -> np.ndarray:
    """``field``'s finite values over the volume's leaf cells (float64, each cell once, grid
    after grid in C order), of level ``level`` only when given. :func:`leaf_values_reference`
    is the slow twin (grid by grid)."""
    keep = volume.leaf_mask_flat()
    if level is not None:
        counts = volume.grid_columns()["shape"].prod(axis=1)
        keep = keep & np.repeat(volume.grid_columns()["level"] == level, counts)
    values = flat_field(volume, field)[keep]
    finite = np.isfinite(values)
    if not finite.all():
        values = values[finite]
    # (Filtered in the field's own precision: fewer new bytes than float64 first.)
    return np.asarray(values, dtype=np.float64)


def leaf_values_reference(volume, field: str, level=None) -> np.ndarray:
    """Slow twin of :func:`leaf_values`: grid by grid."""
    out = [np.asarray(g.fields[field], dtype=np.float64)[volume.leaf_mask(i)]
           for i, g in enumerate(volume.grids) if level is None or g.level == level]
    values = np.concatenate(out) if out else np.zeros(0)
    return values[np.isfinite(values)]


def sorted_quantile(values: np.ndarray, q):
    """``np.quantile(values, q)`` (its default, linear method: the same numbers and dtype) of
    ``values`` already sorted ascending (1-D, not empty, finite), read at the two values about
    each quantile instead of partitioning the whole array again for every call."""
    weak = type(q) in (int, float)          # NumPy keeps a float32 array's precision then
    q = np.asarray(q, dtype=np.float64)
    n = values.shape[0]
    virtual = (n - 1) * q
    above, below = virtual >= n - 1, virtual < 0
    prev = np.where(above, -1, np.floor(virtual))
    after = np.where(below, 0, np.where(above, -1, prev + 1)).astype(np.intp)
    prev = np.where(below, 0, prev).astype(np.intp)
    a, b = values[prev], values[after]
    gamma = virtual - prev
    if weak:
        gamma, a, b = float(gamma), a[()], b[()]
    diff = b - a
    # NumPy's interpolation: from the nearer of the two ends
    out = np.where(gamma >= 0.5, b - diff * (1 - gamma), a + diff * gamma)
    return out[()] if np.ndim(out) == 0 else out


def sorted_percentile(values: np.ndarray, p):
    """``np.percentile(values, p)`` of sorted ``values``, as :func:`sorted_quantile`."""
    return sorted_quantile(values, p / 100 if type(p) in (int, float) else
                           np.true_divide(p, 100))


def sorted_histogram(values: np.ndarray, bins: int, value_range) -> np.ndarray:
    """``np.histogram(values, bins, range=value_range)[0]`` of ``values`` already sorted
    ascending (1-D): each bin counts the values from its lower edge up to, not including, its
    upper edge (the last one's included), read off the sorted values at the edges, as NumPy
    computes the edges."""
    lo, hi = value_range
    edges = np.linspace(lo, hi, bins + 1, endpoint=True,
                        dtype=np.result_type(lo, hi, values))
    at = np.searchsorted(values, edges, side="left")
    at[-1] = np.searchsorted(values, edges[-1], side="right")
    return np.diff(at).astype(np.intp)


def finite_leaf_values(volume, field: str) -> np.ndarray:
    """:func:`leaf_values` of ``field``, sorted (what the picks read); one error naming the
    source and the field where there is none (every value NaN or Inf, kept as missing
    data)."""
    values = leaf_values(volume, field)
    values.sort()       # (in place: it is this call's own array)
    if values.size == 0:
        raise AMRError(f"{volume.source_prefix()}field '{field}' has no finite value in its "
                       f"leaf cells: nothing to pick an isovalue from")
    return values


def field_stats(volume, field: str, count: int = 3) -> FieldStats:
    """The statistics of ``field`` (stored or already derived in ``volume``)."""
    if field not in volume.field_names:
        raise AMRError(f"{volume.source_prefix()}no field '{field}'; it holds "
                       f"{list(volume.field_names)}")
    values = finite_leaf_values(volume, field)
    levels = []
    for level in range(volume.num_levels):
        v = leaf_values(volume, field, level)
        levels.append((level, int(v.size), float(v.min()) if v.size else None,
                       float(v.max()) if v.size else None))
    pct = dict(zip(PERCENTILES, sorted_percentile(values, PERCENTILES).tolist()))
    suggested = suggest_isovalues(volume, field, values, count)
    return FieldStats(field=field, cells=int(values.size), vmin=float(values[0]),
                      vmax=float(values[-1]), percentiles=pct, suggested=suggested,
                      levels=levels, band_widths=[suggest_band_width(values, v)
                                                  for v in suggested])


def suggest_isovalues(volume, field: str, values=None, count: int = 3) -> list:
    """Up to ``count`` isovalues of ``field``, best first (see the module docstring);
    ``values``: its finite leaf values sorted (:func:`finite_leaf_values`), read when None."""
    values = finite_leaf_values(volume, field) if values is None else values
    if values[0] == values[-1]:
        return [float(values[0])]
    if field == "q_criterion":
        positive = values[np.searchsorted(values, 0.0, "right"):]
        if positive.size >= Q_POSITIVE_MIN * values.size:
            return [float(v) for v in sorted_quantile(positive, Q_POSITIVE_RANKS[:count])]
    lo, hi = sorted_percentile(values, (2, 98))
    if lo == hi:
        lo, hi = values[0], values[-1]
    candidates = np.unique(np.concatenate([sorted_percentile(values, np.arange(5, 96, 5)),
                                           np.linspace(lo, hi, 35)[1:-1]]))
    scores = _crossings(volume, field, candidates, MIN_SPAN * (hi - lo))
    if scores.max() == 0:
        return [float(np.median(values))]
    ranks = np.searchsorted(values, candidates) / values.size
    near = np.flatnonzero(scores >= TIE * scores.max())
    middle = (ranks[near].min() + ranks[near].max()) / 2
    first = near[np.argmin(np.abs(ranks[near] - middle))]
    picked = [first]
    for i in np.argsort(-scores, kind="stable"):
        if len(picked) >= count:
            break
        if scores[i] > 0 and all(abs(ranks[i] - ranks[j]) >= DISTINCT and
                                 abs(candidates[i] - candidates[j]) >= MIN_SPAN * (hi - lo)
                                 for j in picked):
            picked.append(i)
    return [float(candidates[i]) for i in picked]


def suggest_band_width(values: np.ndarray, isovalue: float) -> float:
    """A Gaussian width (field units) for volume mode's opacity band about ``isovalue``, from
    the field's finite leaf values ``values`` (sorted, not empty): half the distance from the
    isovalue to the value :data:`BAND_RANKS` of the cells away in rank, on the nearer of its
    two sides, so that the band's default support (two widths each side) reaches that share
    of the cells on the side where they lie closer together. The hand-tuned bands of the
    sphere wake's Q (``scenes_xml/sphere_wake_volume.xml``, ``sphere_wake_shells.xml``) are
    within a factor of 2.5 of it. Where the cells near the isovalue all hold it (a flat
    field), :data:`MIN_SPAN` of the whole range; for a constant field, a width that is
    positive in single precision."""
    # The isovalue's place in the values, as np.quantile counts (0 to 1 from the first value
    # to the last), in the middle of its run of equal values (a flat field's cells hold it).
    at = (np.searchsorted(values, isovalue, "left") +
          np.searchsorted(values, isovalue, "right") - 1) / 2
    rank = min(max(at / max(values.size - 1, 1), 0.0), 1.0)
    lo, hi = sorted_quantile(values, (max(rank - BAND_RANKS, 0.0),
                                     min(rank + BAND_RANKS, 1.0)))
    sides = [d for d in (isovalue - lo, hi - isovalue) if d > 0]
    if sides:
        return float(min(sides) / 2)
    span = float(values[-1] - values[0])
    if span > 0:
        return MIN_SPAN * span
    return float(max(abs(isovalue) * MIN_SPAN, np.finfo(np.float32).tiny))


def suggest_band_widths(values: np.ndarray, isovalues) -> list:
    """:func:`suggest_band_width` of each of ``isovalues``, narrowed where two bands' default
    supports (two widths each side) would overlap: each to a little under a quarter of the
    distance to the nearest other isovalue, so that no value lies in two bands (which volume
    mode refuses). Equal isovalues keep their widths (their bands overlap whatever the
    width)."""
    isovalues = [float(v) for v in isovalues]
    out = []
    for i, v in enumerate(isovalues):
        w = suggest_band_width(values, v)
        gaps = [abs(v - u) for j, u in enumerate(isovalues) if j != i and u != v]
        out.append(min(w, min(gaps) / 4 * (1 - 1e-6)) if gaps else w)
    return out


def _crossings(volume, field: str, candidates: np.ndarray, min_span: float) -> np.ndarray:
    """For each candidate, the number of neighbouring leaf-cell pairs it separates, counting
    only pairs whose values differ by more than ``min_span`` (noise in a flat region would
    otherwise outvote every real surface). The grids of one shape are taken together
    (:mod:`mi_amr.core.batches`); :func:`_crossings_reference` is the slow twin (grid by
    grid), which counts the same pairs."""
    lows, highs = [], []
    step = _pair_step(volume)
    flat, leaf = flat_field(volume, field), volume.leaf_mask_flat()
    offsets = volume.grid_columns()["offset"]
    for ids, shape in shape_batches(volume):
        f = np.asarray(stacked(flat, offsets, ids, shape), dtype=np.float64)
        keep = stacked(leaf, offsets, ids, shape) & np.isfinite(f)
        for axis in range(3):
            if shape[axis] < 2:
                continue
            a, b = axis_pairs(axis)
            with np.errstate(invalid="ignore"):     # (inf - inf: such a pair is not kept)
                step_over = np.abs(f[b] - f[a]) > min_span
            both = (keep[a] & keep[b] & step_over).reshape(len(ids), -1)
            # every step-th pair of each grid, counted from its first, as the twin takes them
            both &= (np.cumsum(both, axis=1) - 1) % step == 0
            lows.append(np.minimum(f[a], f[b]).reshape(len(ids), -1)[both])
            highs.append(np.maximum(f[a], f[b]).reshape(len(ids), -1)[both])
    return _separated(lows, highs, candidates)


def _crossings_reference(volume, field: str, candidates: np.ndarray,
                         min_span: float) -> np.ndarray:
    """Slow twin of :func:`_crossings`: grid by grid, axis by axis, every ``step``-th pair."""
    lows, highs = [], []
    step = _pair_step(volume)
    for i, g in enumerate(volume.grids):
        f = np.asarray(g.fields[field], dtype=np.float64)
        keep = volume.leaf_mask(i) & np.isfinite(f)
        for axis in range(3):
            if f.shape[axis] < 2:
                continue
            a = np.take(f, range(f.shape[axis] - 1), axis=axis)
            b = np.take(f, range(1, f.shape[axis]), axis=axis)
            with np.errstate(invalid="ignore"):     # (inf - inf: such a pair is not kept)
                step_over = np.abs(b - a) > min_span
            both = np.take(keep, range(f.shape[axis] - 1), axis=axis) & \
                np.take(keep, range(1, f.shape[axis]), axis=axis) & step_over
            lows.append(np.minimum(a, b)[both][::step])
            highs.append(np.maximum(a, b)[both][::step])
    return _separated(lows, highs, candidates)


def _pair_step(volume) -> int:
    """Every how many-th pair of a grid is scored: an even subsample of at most about
    :data:`MAX_PAIRS` pairs."""
    return max(1, -(-3 * volume.num_cells // MAX_PAIRS))


def _separated(lows, highs, candidates) -> np.ndarray:
    """For each candidate ``c``, the pairs (their lower values ``lows``, upper ``highs``: lists
    of arrays) with ``low < c <= high``."""
    if not lows:
        return np.zeros(len(candidates))
    low, high = np.concatenate(lows), np.concatenate(highs)
    # A pair is separated by c when low < c <= high: count lows below c minus highs below c.
    low.sort()
    high.sort()
    return (np.searchsorted(low, candidates, side="left")
            - np.searchsorted(high, candidates, side="left")).astype(np.int64)
