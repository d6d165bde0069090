"""Filling the brick pools that the basis reconstruction reads, on the device.

A level's cells are gathered into bricks of ``BRICK_N^3`` values (``BRICK`` cells a side and one
of apron above, see :func:`~mi_amr.kernels.device.build_bricks`). Each value of
a brick is *pulled*: one kernel over the level's brick slots finds the cell a slot holds, the
grid of the level that holds that cell (through the level's block table,
:class:`~mi_amr.core.levels.LevelIndex`) and reads its value where the cell is a leaf cell (no
finer cell covers it); NaN elsewhere. One pass, no per-grid or per-chunk work on the host.
:func:`level_bricks_reference` (grid by grid, brick by brick with array
slices) is its slow twin.

Index coordinates are those of :meth:`AMRVolume.index_boxes` (cells of the level from the
volume's anchor).
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_amr.core import levels
from mi_amr.kernels.arrays import (device_array, device_table, grid_record, grid_records,
                                   mapped_array)

NO_BRICK = 0xFFFFFFFF
BRICK = 8                 # cells per brick side; a brick stores BRICK + 1 (one cell of apron)
BRICK_N = BRICK + 1


def build_pools(m, volume, arrays, parts, count):
    """The pools (one ``m.Float`` per field) of all levels' bricks, ``count`` in all, for the
    levels' ``parts`` (``(lo, dims, table, n)`` each, as :func:`brick_table` gives them, with
    brick numbers from 0 on). ``arrays``: each field's values of all cells on the device
    (float32, grid after grid: :meth:`AMRVolume.cell_offsets`), which the slots gather from."""
    leaf = mapped_array(m.Bool, volume.leaf_mask_flat(), np.bool_)
    # Left unset: the levels' bricks are numbered 0..count-1 without a gap (brick_table) and
    # fill_level writes every slot of each, so no value is read before it is written, and
    # new memory is touched once, by the fill (a NaN fill first would touch the pools twice,
    # and memory new to a process is slow to touch).
    if sum(int(n) for *_, n in parts) != count:
        raise ValueError(f"brick pools of {count} bricks for levels holding "
                         f"{sum(int(n) for *_, n in parts)}")
    pools = [dr.empty(m.Float, count * BRICK_N ** 3) for _ in arrays]
    for level, (lo, dims, table, _) in enumerate(parts):
        fill_level(m, volume, level, (lo, dims, table, 0), (arrays, leaf), pools)
    return pools


def fill_level(m, volume, level, bricks, sources, pools) -> None:
    """Write the level's bricks into ``pools`` (one ``m.Float`` per array of ``arrays``, see
    :func:`build_pools`; brick number ``base`` at slot 0, ``BRICK_N^3`` slots a brick) for its
    brick table ``bricks``, ``(lo, dims, table, base)``: ``lo`` (the level-index cell of the
    table's first corner), ``dims`` and ``table`` (brick numbers, ``NO_BRICK`` where unused) as
    :func:`brick_table` gives them. ``sources``: ``(arrays, leaf)``, the grids' values and
    :meth:`AMRVolume.leaf_mask_flat` on the device."""
    lo, dims, table, base = bricks
    arrays, leaf = sources
    used = np.flatnonzero(table != NO_BRICK)
    if len(used) == 0:
        return
    n = BRICK_N ** 3
    slot = dr.arange(m.UInt32, len(used) * n)
    brick, s = slot // n, slot % n
    # Per brick one record of 4 int32, read with one packet load: its first cell (level
    # index) and its number in the pools.
    rec = np.empty((len(used), 4), dtype=np.int32)
    rec[:, :3] = np.stack(np.unravel_index(used, tuple(int(x) for x in dims)), axis=1) * \
        BRICK + lo
    rec[:, 3] = table[used].astype(np.int64) - base
    first = dr.gather(m.Array4i, _ints(m, rec), brick)
    cell = m.Array3i(first[0], first[1], first[2]) + m.Array3i(
        m.Int32(s // (BRICK_N * BRICK_N)), m.Int32(s // BRICK_N % BRICK_N), m.Int32(s % BRICK_N))
    grid, found = _find(m, levels.level_index(volume, level), cell)
    at = _cell_index(m, volume, level, grid, cell, found)
    is_leaf = found & dr.gather(m.Bool, leaf, at, found)
    dst = dr.reinterpret_array(m.UInt32, first[3]) * n + s
    for pool, values in zip(pools, arrays):
        v = dr.gather(m.Float, values, at, is_leaf)
        dr.scatter(pool, dr.select(is_leaf, v, dr.nan), dst)
    dr.eval(*pools)


def _find(m, index: "levels.LevelIndex", cell):
    """``(grid, found)``: the position in ``index.grids`` of the grid holding each level cell
    ``cell`` (``m.Array3i``), through the level's dense block table or, where the level has
    none (a sparse level over a large box), a binary search of its sorted block keys."""
    if len(index.keys) == 0:
        return m.Int32(0), m.Bool(False)
    shift = _opaque(m, int(index.block).bit_length() - 1)
    rel = (cell >> shift) - m.Array3i(*(_opaque(m, x) for x in index.origin))
    dims = [_opaque(m, x) for x in index.dims]
    inside = dr.all((rel >= 0) & (rel < m.Array3i(*dims)))
    key = m.UInt32((rel.x * dims[1] + rel.y) * dims[2] + rel.z)
    if index.table is not None:
        grid = dr.gather(m.Int32, _ints(m, index.table), key, inside)
        return grid, inside & (grid >= 0)
    keys = _uints(m, index.keys)
    at = dr.binary_search(0, len(index.keys) - 1,
                          lambda i: dr.gather(m.UInt32, keys, i, inside) < key)
    hit = inside & (dr.gather(m.UInt32, keys, at, inside) == key)
    return dr.gather(m.Int32, _ints(m, index.owner), at, hit), hit


def _cell_index(m, volume, level, grid, cell, found):
    """Where each found cell (a level cell, in the level's grid ``grid``) lies among the cells
    of all grids (:meth:`AMRVolume.cell_offsets`)."""
    index = levels.level_index(volume, level)
    records = grid_records(m, index, volume.cell_offsets()[index.grids])
    lo, n, start = grid_record(m, records, m.UInt32(grid), found)
    local = cell - m.Array3i(*lo)
    return start + m.UInt32((local.x * n[1] + local.y) * n[2] + local.z)


def _opaque(m, value):
    """An int as an opaque kernel input (so that every level and volume runs one kernel)."""
    return dr.opaque(m.Int32, int(value))


def _ints(m, a):
    return device_table(m.Int32, a, np.int32)


def _uints(m, a):
    return device_table(m.UInt32, a, np.uint32)


# ---------------------------------------------------------------------- tables, one level

def level_bricks(volume, level, names, first, m=None):
    """One level's part of :func:`~mi_amr.kernels.device.build_bricks`: ``(lo, dims, table, pools)``
    (see :func:`brick_table`), ``pools`` per field of ``names`` the level's bricks'
    ``BRICK_N^3`` float32 values each, flat, as NumPy arrays (filled on the backend ``m``,
    :func:`mi_amr.kernels.bricks.fill_level`). :func:`level_bricks_reference` is the slow
    twin (grid by grid, brick by brick)."""
    m = m or dr.llvm.ad
    lo, dims, table, n = brick_table(volume, level, first)
    arrays = [device_array(m.Float, np.concatenate([g.fields[name].ravel()
                                                   for g in volume.grids]), np.float32)
              for name in names]
    pools = [dr.full(m.Float, dr.nan, n * BRICK_N ** 3) for _ in names]
    fill_level(m, volume, level, (lo, dims, table, first),
               (arrays, mapped_array(m.Bool, volume.leaf_mask_flat(), np.bool_)), pools)
    return lo, dims, table, [p.numpy() for p in pools]


def brick_table(volume, level, first):
    """``(lo, dims, table, n)`` of one level's bricks: ``lo`` the level-index cell one below
    the level's grids, ``dims`` the dense table's size in bricks, ``table`` the flat table
    (brick numbers from ``first`` on, :data:`NO_BRICK` where unused) and ``n`` the bricks
    used: those touched by a grid, its apron included (a dual cell may start one cell below
    a grid)."""
    index = levels.level_index(volume, level)
    lo = index.lo.min(axis=0) - 1
    dims = -(-(index.hi.max(axis=0) - lo) // BRICK)
    used = np.zeros(int(np.prod(dims)), dtype=bool)
    spans, _ = levels.box_points((index.lo - 1 - lo) // BRICK, (index.hi - 1 - lo) // BRICK + 1)
    used[(spans[:, 0] * dims[1] + spans[:, 1]) * dims[2] + spans[:, 2]] = True
    table = np.full(len(used), NO_BRICK, dtype=np.uint32)
    n = int(used.sum())
    table[used] = np.arange(first, first + n, dtype=np.uint32)
    return lo, dims, table, n


def level_bricks_reference(volume, level, names, first):
    """Slow twin of :func:`level_bricks`: grid by grid, brick by brick, with array slices."""
    ilo, ihi = volume.index_boxes()
    ids = np.flatnonzero(volume.levels == level)
    lo = ilo[ids].min(axis=0) - 1
    dims = -(-(ihi[ids].max(axis=0) - lo) // BRICK)
    table = np.full(tuple(dims), NO_BRICK, dtype=np.uint32)
    spans = [((ilo[g] - 1 - lo) // BRICK, (ihi[g] - 1 - lo) // BRICK) for g in ids]
    for a, b in spans:
        table[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1] = 0
    used = table == 0
    n = int(used.sum())
    table[used] = np.arange(first, first + n, dtype=np.uint32)
    pools = [np.full((n, BRICK_N, BRICK_N, BRICK_N), np.nan, dtype=np.float32) for _ in names]
    for g, (a, b) in zip(ids, spans):
        arrays = [np.where(volume.leaf_mask(g), volume.grids[g].fields[nm], np.nan)
                  for nm in names]
        for bx, by, bz in np.ndindex(*(b - a + 1)):
            start = lo + (a + (bx, by, bz)) * BRICK
            c0, c1 = np.maximum(start, ilo[g]), np.minimum(start + BRICK_N, ihi[g])
            k = table[tuple(a + (bx, by, bz))] - first
            dst = tuple(slice(x, y) for x, y in zip(c0 - start, c1 - start))
            src = tuple(slice(x, y) for x, y in zip(c0 - ilo[g], c1 - ilo[g]))
            for pool, arr in zip(pools, arrays):
                pool[k][dst] = arr[src]
    return lo, dims, table.ravel(), [p.ravel() for p in pools]
