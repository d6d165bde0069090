"""The kd leaves' value ranges, on the device.

:meth:`KDTree.leaf_ranges <mi_amr.core.kdtree.KDTree.leaf_ranges>` (NumPy) takes, for each
(leaf, grid) pair of :meth:`~mi_amr.core.kdtree.KDTree.leaf_windows`, the min and max of the
finite values of the grid's cells in the pair's window widened to power-of-two blocks, then per
leaf the extremes over its pairs. Here one kernel widens each pair's window and walks it cell by
cell (a lane a pair); the per-leaf extremes over the pairs (listed leaf after leaf) are taken on
the host. The values are the field as the kernels read it (float32; rounding to float32 keeps the
order of values, so the extremes are the float32 roundings of the NumPy ones), and so is the
result.

Index coordinates are cells of the pair's grid, ``[i, j, k]`` = x, y, z, C order.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_amr.core.kdtree import run_starts
from mi_amr.kernels.arrays import device_array, mapped_array


# Pairs per kernel launch: bounds the host's per-pair temporaries (about 100 bytes a pair) and
# their device copies, whatever the number of pairs (10^8 cells have about 10^7). Smaller
# launches reuse their memory (2^19 was faster than 2^21 on 27M cells).
CHUNK_PAIRS = 1 << 19


def leaf_ranges(m, tree, values, field: str, reconstruction: str | None = None,
                pairs: int = CHUNK_PAIRS):
    """``(lo, hi)`` float32 NumPy arrays, one entry per leaf of ``tree``, as
    :meth:`~mi_amr.core.kdtree.KDTree.leaf_ranges` gives them (rounded to float32);
    ``values``: the field's values of all cells, grid after grid, as a device ``m.Float``.
    Leaves with no pair get ``(+inf, -inf)``. One kernel launch takes ``pairs`` (leaf, grid)
    pairs."""
    vol = tree.volume
    pl, pg, lo, hi = tree.leaf_windows(field, reconstruction)
    vmin = np.empty(len(pl), dtype=np.float32)
    vmax = np.empty(len(pl), dtype=np.float32)
    leaf = mapped_array(m.Bool, vol.leaf_mask_flat(), np.bool_) \
        if reconstruction == "basis" and len(pl) else None
    for a in range(0, len(pl), pairs):
        # A launch of one pair is given it twice: Dr.Jit compiles a one-lane input into a
        # broadcast, which would be another kernel.
        part = np.arange(a, min(a + pairs, len(pl)))
        lanes = np.repeat(part, 2) if len(part) == 1 else part
        shape = vol.shapes()[pg[lanes]]
        start = vol.cell_offsets()[pg[lanes]]
        lo_part, hi_part = _window_extremes(m, values, leaf, (start, shape), (lo[lanes], hi[lanes]))
        dr.eval(lo_part, hi_part)
        vmin[part], vmax[part] = lo_part.numpy()[:len(part)], hi_part.numpy()[:len(part)]
    # Per leaf, the extremes over its pairs (listed leaf after leaf), on the host: a scatter
    # on the device would compile its target's size (the number of leaves) into the kernel.
    out_lo = np.full(tree.num_leaves, np.inf, dtype=np.float32)
    out_hi = np.full(tree.num_leaves, -np.inf, dtype=np.float32)
    if len(pl):
        first = run_starts(pl)
        out_lo[pl[first]] = np.minimum.reduceat(vmin, first)
        out_hi[pl[first]] = np.maximum.reduceat(vmax, first)
    return out_lo, out_hi


def block_tops(lo, hi, shape):
    """The exclusive upper corners of the windows ``[lo, hi]`` (inclusive, ``(P, 3)``) widened
    as :func:`~mi_amr.core.kdtree._window_min_max` widens them: to the blocks of ``2**k`` cells
    a side (``2**k`` the largest power of two not longer than the window's longest side) that
    start at ``lo`` or end at ``hi``, cut at the grid's end (``shape``, ``(P, 3)``). The lower
    corner stays ``lo``. The slow twin of :func:`device_tops`, which the kernel uses."""
    side = (hi - lo + 1).max(axis=1)
    block = (1 << np.floor(np.log2(side)).astype(np.int64))[:, None]
    return np.minimum(np.maximum(lo, hi - block + 1) + block, shape)


def device_tops(m, lo, hi, shape):
    """:func:`block_tops` of the windows ``[lo, hi]`` (inclusive, not empty) in grids of
    ``shape`` (three ``m.Array3i``), on the device: ``2**k`` from the longest side's leading
    zeros."""
    side = dr.maximum(dr.maximum(hi.x - lo.x, hi.y - lo.y), hi.z - lo.z) + 1
    block = m.Int32(1) << m.Int32(31 - dr.lzcnt(m.UInt32(side)))
    return dr.minimum(dr.maximum(lo, hi - block + 1) + block, shape)


@dr.syntax
def _window_extremes(m, values, leaf, grid, box):
    """Per window (a lane each) the min and max of the finite ``values`` (of leaf cells where
    ``leaf`` is given) in the window ``[lo, hi]`` (``box``, inclusive) widened to its blocks
    (:func:`device_tops`) of the grid whose cells start at ``start`` (``grid``: ``(start,
    shape)``); ``(+inf, -inf)`` where there are none."""
    (start, shape), (lo, hi) = grid, box
    def ints(a):
        return device_array(m.Int32, a, np.int32)

    b_lo = m.Array3i(*(ints(lo[:, a]) for a in range(3)))
    n = m.Array3i(*(ints(shape[:, a]) for a in range(3)))
    b_top = device_tops(m, b_lo, m.Array3i(*(ints(hi[:, a]) for a in range(3))), n)
    ny, nz = n.y, n.z
    base = device_array(m.UInt32, start, np.uint32)
    x, y, z = m.Int32(b_lo.x), m.Int32(b_lo.y), m.Int32(b_lo.z)
    vmin = dr.full(m.Float, dr.inf, len(start))
    vmax = dr.full(m.Float, -dr.inf, len(start))
    active = dr.all(b_lo < b_top)
    while dr.hint(active, label="window"):
        at = base + m.UInt32((x * ny + y) * nz + z)
        v = dr.gather(m.Float, values, at, active)
        take = active & dr.isfinite(v)
        if dr.hint(leaf is not None, mode="scalar"):
            take &= dr.gather(m.Bool, leaf, at, active)
        vmin = dr.select(take, dr.minimum(vmin, v), vmin)
        vmax = dr.select(take, dr.maximum(vmax, v), vmax)
        # The next cell in C order of the box.
        z += 1
        wrap_z = z >= b_top.z
        z = dr.select(wrap_z, b_lo.z, z)
        y = dr.select(wrap_z, y + 1, y)
        wrap_y = wrap_z & (y >= b_top.y)
        y = dr.select(wrap_y, b_lo.y, y)
        x = dr.select(wrap_y, x + 1, x)
        active &= x < b_top.x
    return vmin, vmax
