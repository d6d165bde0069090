"""Vectorised queries on sets of axis-aligned boxes (host side, NumPy).

Boxes are given as ``lo``/``hi`` arrays of shape ``(N, 3)``; they may be integer index boxes
(half-open, ``[lo, hi)`` in cells) or world-space boxes. Nothing here knows about AMR.
"""

from __future__ import annotations

import numpy as np

# A box spanning more hash bins than this is tested against every box of the other set instead
# of being entered into the hash (a few big boxes, such as a level-0 grid, stay cheap that way).
_MAX_BINS_PER_BOX = 64


def overlap_pairs(alo, ahi, blo, bhi, *, closed: bool = False):
    """All pairs ``(a, b)`` of boxes from two sets that overlap.

    ``closed=False`` keeps pairs whose intersection has positive volume; ``closed=True`` also keeps
    boxes that only touch (shared face, edge or corner). Broad phase: a uniform hash grid whose
    bin is the median box size, so the work grows with the number of boxes and of true
    neighbours, not with their product. Returns two index arrays of equal length, sorted by
    ``a`` then ``b``.
    """
    alo, ahi, blo, bhi = (np.asarray(x, dtype=np.float64) for x in (alo, ahi, blo, bhi))
    if len(alo) == 0 or len(blo) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    # Bin size: the larger of the two sets' median box sizes, so boxes of the set with the
    # bigger boxes each fall into a few bins and small boxes (or points) into one.
    size = np.zeros(3)
    for ext in (ahi - alo, bhi - blo):
        positive = ext[np.all(ext > 0, axis=1)]
        if len(positive):
            size = np.maximum(size, np.median(positive, axis=0))
    if not np.all(size > 0):
        size = np.ones(3)
    origin = np.minimum(alo.min(axis=0), blo.min(axis=0))

    def bins(lo, hi):
        # An open box ending exactly on a bin face does not reach into the next bin.
        first = np.floor((lo - origin) / size).astype(np.int64)
        end = (hi - origin) / size
        last = np.floor(end) if closed else np.ceil(end) - 1
        return first, np.maximum(last.astype(np.int64), first)

    a_first, a_last = bins(alo, ahi)
    b_first, b_last = bins(blo, bhi)
    a_count = np.prod(a_last - a_first + 1, axis=1)
    b_count = np.prod(b_last - b_first + 1, axis=1)
    a_big = a_count > _MAX_BINS_PER_BOX
    b_big = b_count > _MAX_BINS_PER_BOX
    dims = np.maximum(a_last.max(axis=0), b_last.max(axis=0)) + 1

    def entries(first, last, count, ids):
        n = count[ids]
        box = np.repeat(ids, n)
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        span = (last - first + 1)[box]
        cell = first[box] + np.stack([k // (span[:, 1] * span[:, 2]), (k // span[:, 2]) % span[:, 1],
                                      k % span[:, 2]], axis=1)
        key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
        return key, box

    ka, ia = entries(a_first, a_last, a_count, np.flatnonzero(~a_big))
    kb, ib = entries(b_first, b_last, b_count, np.flatnonzero(~b_big))
    order = np.argsort(kb)      # the order within a bin does not matter: pairs are sorted below
    kb, ib = kb[order], ib[order]
    start = np.searchsorted(kb, ka, side="left")
    n = np.searchsorted(kb, ka, side="right") - start
    pa = np.repeat(ia, n)
    bin_key = np.repeat(ka, n)
    pb = ib[np.repeat(start, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)]
    # A pair shares every bin its intersection touches; report it only from the bin that holds
    # the intersection's lower corner.
    corner = np.floor((np.maximum(alo[pa], blo[pb]) - origin) / size).astype(np.int64)
    own = (corner[:, 0] * dims[1] + corner[:, 1]) * dims[2] + corner[:, 2] == bin_key
    pa, pb = pa[own], pb[own]

    # Big boxes of either set against every box of the other set (big against big once).
    big_a, big_b = np.flatnonzero(a_big), np.flatnonzero(b_big)
    small_a = np.flatnonzero(~a_big)
    pa = np.concatenate([pa, np.repeat(big_a, len(blo)), np.repeat(small_a, len(big_b))])
    pb = np.concatenate([pb, np.tile(np.arange(len(blo)), len(big_a)), np.tile(big_b, len(small_a))])

    lo = np.maximum(alo[pa], blo[pb])
    hi = np.minimum(ahi[pa], bhi[pb])
    keep = np.all(hi >= lo, axis=1) if closed else np.all(hi > lo, axis=1)
    pa, pb = pa[keep], pb[keep]
    order = np.lexsort((pb, pa))
    return pa[order], pb[order]


def intersection_volume(alo, ahi, blo, bhi):
    """Volume of the intersection of box pairs given row by row (zero where they are disjoint)."""
    ext = np.minimum(ahi, bhi) - np.maximum(alo, blo)
    return np.prod(np.maximum(ext, 0), axis=1)


def contains_points(lo, hi, points):
    """Row-wise test: does closed box ``[lo, hi]`` contain ``points`` (all arrays ``(N, 3)``)?"""
    return np.all((points >= lo) & (points <= hi), axis=1)
