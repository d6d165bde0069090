"""The kd leaves' value ranges, on the device.

:meth:`KDTree.leaf_ranges <mi_amr.core.kdtree.KDTree.leaf_ranges>` (NumPy) takes, for each
(leaf, grid) pair of :meth:`~mi_amr.core.kdtree.KDTree.leaf_windows`, the min and max of the
finite values of the grid's cells in the pair's window widened to power-of-two blocks, then per
leaf the extremes over its pairs. Here one kernel takes each pair's window (from the leaf's and
the grid's lattice boxes, :meth:`~mi_amr.core.kdtree.KDTree.window_frame`), widens it and walks
it cell by cell (a lane a pair, nearby pairs ordered by their windows' sizes so that a
vector's lanes finish together); the host hands over only the pairs
(:meth:`~mi_amr.core.kdtree.KDTree.leaf_pairs`), and takes the per-leaf extremes over them
(listed leaf after leaf). The values are the field as the kernels read it (float32; rounding
to float32 keeps the order of values, so the extremes are the float32 roundings of the NumPy
ones), and so is the result.

Index coordinates are cells of the pair's grid, ``[i, j, k]`` = x, y, z, C order.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_amr.core.kdtree import run_starts
from mi_amr.kernels.arrays import device_array, device_table, mapped_array
from mi_amr.kernels.bricks import BRICK, BRICK_N


# Pairs per kernel launch: bounds the host's per-pair temporaries (about 100 bytes a pair) and
# their device copies, whatever the number of pairs (10^8 cells have about 10^7). Smaller
# launches reuse their memory (2^19 was faster than 2^21 on 27M cells).
CHUNK_PAIRS = 1 << 19
SIZE_KEY_MAX = (1 << 16) - 1     # window cells beyond which pairs are not told apart in order
# Pairs ordered by window size among runs of this many (leaf after leaf) only: a pair's cells
# lie near its neighbours' in memory, and a global order loses that (slower on 27M cells than no
# order at all; 1024 was faster than 256 and 4096 there).
SORT_BLOCK = 1 << 10


def leaf_ranges(m, tree, values, field: str, reconstruction: str | None = None,
                pairs: int = CHUNK_PAIRS):
    """``(lo, hi)`` float32 NumPy arrays, one entry per leaf of ``tree``, as
    :meth:`~mi_amr.core.kdtree.KDTree.leaf_ranges` gives them (rounded to float32);
    ``values``: the field's values of all cells, grid after grid, as a device ``m.Float``.
    Leaves with no pair get ``(+inf, -inf)``. One kernel launch takes ``pairs`` (leaf, grid)
    pairs."""
    vol = tree.volume
    pl, pg = tree.leaf_pairs(field, reconstruction)
    leaf = mapped_array(m.Bool, vol.leaf_mask_flat(), np.bool_) \
        if reconstruction == "basis" and len(pl) else None
    return _extremes(m, tree, (pl, pg), lambda frame, at: _window_extremes(
        m, values, leaf, frame, at), pairs)


def brick_leaf_ranges(m, tree, bricks, pairs: int = CHUNK_PAIRS):
    """:func:`leaf_ranges` of the basis blend (the same float32 numbers) read from the brick
    pools of ``bricks`` (a :class:`~mi_amr.kernels.device.DeviceVolume`: the field's pool,
    the brick table and each level's part of it) instead of the grids' values: a pool holds
    a leaf cell's value and NaN where the cell is not a leaf, so a window's finite pool
    values are its finite leaf values. Each window's cells are read from their bricks (one
    table lookup a cell); for a preparation that keeps no values
    (:attr:`~mi_amr.kernels.prepared.PreparedVolume.keeps_fields` False)."""
    vol = tree.volume
    lo, _ = vol.index_boxes()
    cells = np.zeros((len(lo), 4), dtype=np.int32)
    cells[:, :3], cells[:, 3] = lo, vol.levels
    grids = device_table(m.Int32, cells, np.int32)
    return _extremes(m, tree, tree.leaf_pairs(None, "basis"), lambda frame, at: (
        _brick_window_extremes(m, (bricks, grids), frame, at)), pairs)


def _extremes(m, tree, listed, walk, pairs: int):
    """The per-leaf ``(lo, hi)`` of :func:`leaf_ranges` from the (leaf, grid) pairs
    ``listed`` (leaf after leaf), ``pairs`` a launch, each launch's extremes taken by
    ``walk(frame, lanes)``."""
    pl, pg = listed
    vmin = np.empty(len(pl), dtype=np.float32)
    vmax = np.empty(len(pl), dtype=np.float32)
    frame = _Frame.of(m, tree) if len(pl) else None
    for a in range(0, len(pl), pairs):
        part = np.arange(a, min(a + pairs, len(pl)))
        part = part[_by_window_size(m, frame, _lanes(m, pl, pg, part), len(part))]
        lo_part, hi_part = walk(frame, _lanes(m, pl, pg, part))
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


def _lanes(m, pl, pg, part):
    """The pairs ``part`` of ``(pl, pg)`` as two device ``m.UInt32`` (a launch of one pair is
    given it twice: Dr.Jit compiles a one-lane input into a broadcast, another kernel)."""
    lanes = np.repeat(part, 2) if len(part) == 1 else part
    return (device_array(m.UInt32, pl[lanes], np.uint32),
            device_array(m.UInt32, pg[lanes], np.uint32))


def _by_window_size(m, frame: "_Frame", at, count: int) -> np.ndarray:
    """The order of the ``count`` pairs ``at`` (device, as :func:`_lanes` gives them) by the
    number of cells of their widened windows (up to :data:`SIZE_KEY_MAX`) within each run of
    :data:`SORT_BLOCK` of them (a stable order, so equal sizes keep theirs): the walk's lanes
    run in vectors that go on until their longest window is done, so lanes of like windows
    together waste few steps (in leaf order about half the steps walked nothing)."""
    b_lo, b_hi, n, _ = frame.windows(m, *at)
    full = dr.all(b_lo <= b_hi)
    side = m.Array3f(dr.maximum(device_tops(m, b_lo, dr.select(full, b_hi, b_lo), n) - b_lo, 0))
    cells = m.UInt32(dr.minimum(side.x * side.y * side.z, SIZE_KEY_MAX))   # (no overflow)
    key = dr.select(full, cells, 0).numpy()[:count].astype(np.uint16)
    return _blockwise_order(key, SORT_BLOCK)


def _blockwise_order(key, block: int) -> np.ndarray:
    """The stable order of ``key`` (uint16) within each run of ``block`` consecutive entries,
    the runs kept in place."""
    n = len(key)
    pad = np.full(-(-n // block) * block, np.iinfo(np.uint16).max, dtype=np.uint16)
    pad[:n] = key
    rows = np.argsort(pad.reshape(-1, block), axis=1, kind="stable")
    order = (rows + np.arange(0, len(pad), block)[:, None]).ravel()
    return order[order < n]


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


class _Frame:
    """The tree's :meth:`~mi_amr.core.kdtree.KDTree.window_frame` on the device: per leaf its
    box, per grid its lower corner and cell width (lattice coordinates, float64), its shape
    and where its cells start in the values."""

    def __init__(self, m, arrays: dict, start):
        self.leaf_lo, self.leaf_hi, self.grid_lo, self.step = (
            device_table(m.Float64, arrays[k], np.float64)
            for k in ("leaf_lo", "leaf_hi", "grid_lo", "step"))
        self.shape = device_table(m.Int32, arrays["shape"], np.int32)
        self.start = device_table(m.UInt32, start, np.uint32)

    @staticmethod
    def of(m, tree) -> "_Frame":
        return _Frame(m, tree.window_frame(), tree.volume.cell_offsets())

    def windows(self, m, leaf, grid):
        """The inclusive windows ``(lo, hi)`` (``m.Array3i``) of the pairs ``(leaf, grid)``,
        as :meth:`~mi_amr.core.kdtree.KDTree._windows` computes them (the same float64
        operations in the same order), the grid's shape and its first value."""
        g_lo = dr.gather(m.Array3f64, self.grid_lo, grid)
        s = dr.gather(m.Array3f64, self.step, grid)
        n = dr.gather(m.Array3i, self.shape, grid)
        lo = dr.floor((dr.gather(m.Array3f64, self.leaf_lo, leaf) - g_lo - 1.5 * s) / s)
        hi = dr.ceil((dr.gather(m.Array3f64, self.leaf_hi, leaf) - g_lo + 0.5 * s) / s)
        return (dr.maximum(m.Array3i(lo) + 1, 0), dr.minimum(m.Array3i(hi) - 1, n - 1), n,
                dr.gather(m.UInt32, self.start, grid))


@dr.syntax
def _brick_window_extremes(m, source, frame: _Frame, pairs):
    """:func:`_window_extremes` read from the brick pools: ``source`` is ``(bricks, grids)``,
    the device volume and per grid its lower corner (level index) and level (4 int32). A
    window's cell ``(x, y, z)`` of the pair's grid is the level cell ``lo + (x, y, z)``, read
    from the brick that starts at or below it (its place in that brick below ``BRICK`` on
    each axis: a cell a brick's apron holds is read from its own brick)."""
    bricks, grids = source
    b_lo, b_hi, n, base = frame.windows(m, *pairs)
    full = dr.all(b_lo <= b_hi)
    b_top = device_tops(m, b_lo, dr.select(full, b_hi, b_lo), n)
    g = dr.gather(m.Array4i, grids, pairs[1])
    t_lo, t_at, dims = bricks.level_bricks(m.UInt32(g.w))
    o = m.Array3i(g.x, g.y, g.z) - t_lo          # (the grid's corner in the table's cells)
    dy, dz = m.Int32(dims.y), m.Int32(dims.z)
    pool, table = bricks.brick_values, bricks.brick_table
    shift, low = BRICK.bit_length() - 1, BRICK - 1
    x, y, z = m.Int32(b_lo.x), m.Int32(b_lo.y), m.Int32(b_lo.z)
    vmin = dr.full(m.Float, dr.inf, dr.width(base))
    vmax = dr.full(m.Float, -dr.inf, dr.width(base))
    active = full & dr.all(b_lo < b_top)
    while dr.hint(active, label="window", exclude=[b_lo, b_top, o, t_at, dy, dz, pool, table,
                                                   m]):
        r = [o.x + x, o.y + y, o.z + z]
        key = t_at + m.UInt32(((r[0] >> shift) * dy + (r[1] >> shift)) * dz + (r[2] >> shift))
        brick = dr.gather(m.UInt32, table, key, active)
        at = brick * BRICK_N ** 3 + m.UInt32(
            ((r[0] & low) * BRICK_N + (r[1] & low)) * BRICK_N + (r[2] & low))
        v = dr.gather(m.Float, pool, at, active)
        take = active & dr.isfinite(v)
        vmin = dr.select(take, dr.minimum(vmin, v), vmin)
        vmax = dr.select(take, dr.maximum(vmax, v), vmax)
        x, y, z, active = _next_cell(m, (x, y, z), (b_lo, b_top), active)
    return vmin, vmax


def _next_cell(m, at, box, active):
    """``(x, y, z, active)``: the cell after ``at`` in C order of the box ``(lo, top)`` (top
    exclusive); ``active`` cleared past its end."""
    x, y, z = at
    lo, top = box
    z += 1
    wrap_z = z >= top.z
    z = dr.select(wrap_z, lo.z, z)
    y = dr.select(wrap_z, y + 1, y)
    wrap_y = wrap_z & (y >= top.y)
    y = dr.select(wrap_y, lo.y, y)
    x = dr.select(wrap_y, x + 1, x)
    return x, y, z, active & (x < top.x)


@dr.syntax
def _window_extremes(m, values, leaf, frame: _Frame, pairs):
    """Per (leaf, grid) pair (``pairs``: two ``m.UInt32``, a lane each) the min and max of the
    finite ``values`` (of leaf cells where ``leaf`` is given) in the pair's window
    (:meth:`_Frame.windows`) widened to its blocks (:func:`device_tops`); ``(+inf, -inf)``
    where there are none (an empty window holds none)."""
    b_lo, b_hi, n, base = frame.windows(m, *pairs)
    full = dr.all(b_lo <= b_hi)
    b_top = device_tops(m, b_lo, dr.select(full, b_hi, b_lo), n)
    ny, nz = n.y, n.z
    x, y, z = m.Int32(b_lo.x), m.Int32(b_lo.y), m.Int32(b_lo.z)
    vmin = dr.full(m.Float, dr.inf, dr.width(base))
    vmax = dr.full(m.Float, -dr.inf, dr.width(base))
    active = full & dr.all(b_lo < b_top)
    while dr.hint(active, label="window", exclude=[b_lo, b_top, base, leaf, m, ny, nz, values]):
        at = base + m.UInt32((x * ny + y) * nz + z)
        v = dr.gather(m.Float, values, at, active)
        take = active & dr.isfinite(v)
        if dr.hint(leaf is not None, mode="scalar"):
            take &= dr.gather(m.Bool, leaf, at, active)
        vmin = dr.select(take, dr.minimum(vmin, v), vmin)
        vmax = dr.select(take, dr.maximum(vmax, v), vmax)
        x, y, z, active = _next_cell(m, (x, y, z), (b_lo, b_top), active)
    return vmin, vmax
