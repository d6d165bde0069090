"""Reading cell values of one refinement level across all its grids (host side, NumPy).

A level's cells live in several grids; code that needs "the level-``l`` cell at integer index
``(i, j, k)``" (ghost cells for derivatives, interpolation from a coarser level) asks here. Index
coordinates are those of :meth:`AMRVolume.index_boxes`: cells of the level counted from the
volume's anchor, ``[i, j, k]`` = x, y, z.
"""

from __future__ import annotations

import contextlib

import numpy as np

from mi_amr.core.buffers import joined


DENSE_BLOCKS = 1 << 24     # blocks: up to this many, LevelIndex keeps a dense table (64 MiB)
# Cells per pass of a level-wide computation (derived fields, brick pools): whole grids are
# taken until a chunk holds at least this many cells, which bounds the pass's temporaries
# (~250 bytes a cell for the gradient, ~65 MB at 2^18) whatever the level's size; smaller
# chunks also reuse freed memory instead of page-faulting fresh temporaries (2^20: 30 % slower).
CHUNK_CELLS = 1 << 18


class LevelBlocks:
    """The blocks of one level's grids (index boxes ``lo``, ``hi``, ``(G, 3)``): ``block``, the
    largest power of two (at most 16) dividing every grid corner, so each block lies in whole
    grids; the blocks' ``origin`` and the extent ``dims`` of the level's bounding box in
    blocks; per block its ``key`` in that box (C order), sorted, and the grid that holds it
    (``owner``, position in ``lo``; a stable sort, so the grids sharing a block, where grids
    overlap, follow each other in increasing order)."""

    def __init__(self, block, origin, dims, keys, owner):
        self.block, self.origin, self.dims, self.keys, self.owner = \
            block, origin, dims, keys, owner

    @classmethod
    def count(cls, lo, hi) -> int:
        """How many blocks :meth:`of` would list (without listing them)."""
        block = _block_size(lo, hi)
        return int(np.prod(hi // block - lo // block, axis=1).sum())

    @classmethod
    def of(cls, lo, hi) -> "LevelBlocks":
        block = _block_size(lo, hi)
        blo, bhi = lo // block, hi // block
        origin = blo.min(axis=0)
        dims = bhi.max(axis=0) - origin
        cell, owner = box_points(blo, bhi)
        b = cell - origin
        keys = (b[:, 0] * dims[1] + b[:, 1]) * dims[2] + b[:, 2]
        order = np.argsort(keys, kind="stable")
        return cls(block, origin, dims, keys[order], owner[order])

    def first_overlap(self):
        """``(i, j)``, ``i < j``: the first pair of grids (positions in ``lo``) that share a
        block, in increasing order of ``i`` then ``j`` -- grids that overlap; None where no
        two do."""
        same = np.flatnonzero(self.keys[1:] == self.keys[:-1])
        if len(same) == 0:
            return None
        i, j = self.owner[same], self.owner[same + 1]
        k = np.lexsort((j, i))[0]
        return int(i[k]), int(j[k])


def _block_size(lo, hi) -> int:
    """The largest power of two, at most 16, dividing every corner of the boxes ``lo``,
    ``hi``."""
    corners = np.concatenate([lo.ravel(), hi.ravel()])
    block = 16
    while block > 1 and np.any(corners % block):
        block //= 2
    return block


class LevelIndex:
    """Which grid of one level holds a given cell: a sorted table of the blocks the level's grids
    cover, searched with ``np.searchsorted``.

    A block is ``block`` cells per side, the largest power of two (at most 16) dividing every
    grid corner of the level, so each block lies in exactly one grid. The table holds one entry
    per block, so memory grows with the cells the level has, not with the domain. Where the
    level's bounding box holds at most ``dense_blocks`` blocks, a dense table of them is kept
    too (``table``; None otherwise).
    """

    def __init__(self, volume, level: int, dense_blocks: int = DENSE_BLOCKS):
        lo, hi = volume.index_boxes()
        self.grids = np.flatnonzero(volume.levels == level)
        glo, ghi = lo[self.grids], hi[self.grids]
        # (The hierarchy's check may have listed the blocks already: LevelBlocks.)
        blocks = volume.level_caches.blocks.pop(level, None) or LevelBlocks.of(glo, ghi)
        self.block, self.origin, self.dims = blocks.block, blocks.origin, blocks.dims
        self.keys, self.owner = blocks.keys, blocks.owner
        self.lo, self.hi = glo, ghi
        counts = np.prod(ghi - glo, axis=1)
        self.offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        # A dense table of the blocks when it is small (the usual case): find() is then one
        # gather instead of a binary search.
        self.table = None
        if int(np.prod(self.dims)) <= dense_blocks:
            self.table = np.full(int(np.prod(self.dims)), -1, dtype=np.int32)
            self.table[self.keys] = self.owner

    def _key(self, block_idx):
        b = block_idx - self.origin
        return (b[:, 0] * self.dims[1] + b[:, 1]) * self.dims[2] + b[:, 2]

    def find(self, index) -> np.ndarray:
        """Position in ``self.grids`` of the grid holding each cell ``index`` (``(N, 3)`` int),
        -1 where the level has no such cell."""
        b = index // self.block
        rel = (b - self.origin).astype(np.uint64)       # below the origin: huge, so outside
        dims = self.dims.astype(np.uint64)
        inside = (rel[:, 0] < dims[0]) & (rel[:, 1] < dims[1]) & (rel[:, 2] < dims[2])
        out = np.full(len(index), -1, dtype=np.int64)
        if not inside.any() or len(self.keys) == 0:
            return out
        keys = self._key(b[inside])
        if self.table is not None:
            out[inside] = np.take(self.table, keys)
            return out
        at = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        hit = self.keys[at] == keys
        idx = np.flatnonzero(inside)
        out[idx[hit]] = self.owner[at[hit]]
        return out


def box_points(lo, hi):
    """All integer points of the half-open boxes ``[lo, hi)`` (``(B, 3)`` int each), box after
    box, each box's points in C order: ``(points (N, 3), box of each point (N,))``. For the
    index boxes of a level's grids these are its cells in the order of :func:`level_values`."""
    span = hi - lo
    counts = np.prod(span, axis=1)
    owner = np.repeat(np.arange(len(lo)), counts)
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    ny, nz = np.repeat(span[:, 1], counts), np.repeat(span[:, 2], counts)
    points = np.empty((len(k), 3), dtype=np.result_type(lo, np.int64))
    i = k // (ny * nz)
    k -= i * (ny * nz)
    j = k // nz
    points[:, 0] = np.repeat(lo[:, 0], counts) + i
    points[:, 1] = np.repeat(lo[:, 1], counts) + j
    points[:, 2] = np.repeat(lo[:, 2], counts) + (k - j * nz)
    return points, owner


def grid_chunks(table, cells: int | None = None):
    """``(start, stop)`` ranges of consecutive grids of :class:`LevelIndex` ``table`` holding
    at least ``cells`` (default :data:`CHUNK_CELLS`) cells each (the last may hold fewer)."""
    cells = CHUNK_CELLS if cells is None else cells
    ends = np.cumsum(np.prod(table.hi - table.lo, axis=1))
    start = 0
    while start < len(ends):
        before = ends[start - 1] if start else 0
        stop = min(int(np.searchsorted(ends, before + cells)) + 1, len(ends))
        yield start, stop
        start = stop


class LevelCaches:
    """What this module keeps of one volume (its ``level_caches``): ``index``, the
    :class:`LevelIndex` of each level; ``blocks``, the :class:`LevelBlocks` the hierarchy's
    check listed, for the levels whose index is not made yet (which takes them); ``values``,
    per ``(level, field name)`` the flat
    :func:`level_values` with the grid arrays it was made from (``(ids, arrays, flat)``);
    ``fields_fixed``, how many :func:`fields_fixed` blocks are open; ``dense_blocks``, the
    largest dense block table a :class:`LevelIndex` of the volume keeps (blocks; see there),
    read when a level's table is made."""

    def __init__(self, dense_blocks: int = DENSE_BLOCKS):
        self.index = {}
        self.blocks = {}
        self.values = {}
        self.fields_fixed = 0
        self.dense_blocks = dense_blocks


def level_index(volume, level: int) -> LevelIndex:
    """The (cached) :class:`LevelIndex` of ``level``."""
    cache = volume.level_caches.index
    if level not in cache:
        cache[level] = LevelIndex(volume, level, volume.level_caches.dense_blocks)
    return cache[level]


def level_values(volume, level: int, name: str) -> np.ndarray:
    """Field ``name`` of every grid of ``level``, grid after grid in the order of
    :class:`LevelIndex` (each in C order of its ``(nx, ny, nz)`` array), as one flat array
    (cached on the volume while the field is the same array). Read only: when the grids'
    arrays already lie end to end in one buffer (a file read whole, or :func:`mi_amr.derive`'s
    output) it is a view of that buffer, not a copy."""
    cache = volume.level_caches.values
    key = (level, name)
    if volume.level_caches.fields_fixed and key in cache:
        return cache[key][2]
    table = level_index(volume, level)
    arrays = [volume.grids[g].fields[name] for g in table.grids]
    if key not in cache or cache[key][0] != [id(a) for a in arrays]:
        flat = joined(arrays, arrays[0].dtype, aligned=False) if arrays else np.zeros(0)
        if flat is None:
            flat = np.concatenate([a.ravel() for a in arrays])
        cache[key] = ([id(a) for a in arrays], arrays, flat)
    return cache[key][2]


def adopt_level_values(volume, level: int, name: str, flat: np.ndarray, arrays) -> None:
    """Make ``flat`` the cached :func:`level_values` of field ``name`` on ``level`` where the
    caller made ``arrays`` (the level's grids' arrays of the field, grid after grid in the
    order of :class:`LevelIndex`) as views of ``flat``, end to end (a reader's level buffer,
    the derivation's output, a snapshot's), so that the address of each grid's array is not
    read to find that out (:func:`level_values`). Nothing is cached where the volume's grids
    do not hold those very arrays of ``flat``'s dtype and size (a copy was made on the
    way)."""
    arrays = list(arrays)
    held = [volume.grids[g].fields.get(name) for g in np.flatnonzero(volume.levels == level)]
    if len(held) == len(arrays) and all(a is b and a.dtype == flat.dtype
                                        for a, b in zip(held, arrays)) and \
            sum(a.size for a in arrays) == flat.size:
        volume.level_caches.values[(level, name)] = ([id(a) for a in arrays], arrays, flat)


def volume_values(volume, name: str):
    """Field ``name`` of every grid, grid after grid (the volume's order), as a view of the
    one buffer the grids' arrays lie in end to end, or None where they do not (as
    :func:`mi_amr.core.buffers.joined`, unaligned). Where the grids are in level order and
    each level's values are cached (:func:`adopt_level_values`) it reads a pointer a level,
    not one a grid."""
    cache = volume.level_caches.values
    by_level = volume.levels
    flats = []
    if len(by_level) and np.all(by_level[1:] >= by_level[:-1]):
        for level in range(volume.num_levels):
            entry = cache.get((level, name))
            ids = np.flatnonzero(by_level == level)
            if entry is None or entry[0] != [id(volume.grids[g].fields.get(name)) for g in ids]:
                break
            flats.append(entry[2])
    if flats and len(flats) == volume.num_levels:
        whole = joined(flats, flats[0].dtype, aligned=False)
        if whole is not None:
            return whole
    arrays = [g.fields[name] for g in volume.grids]
    return joined(arrays, arrays[0].dtype, aligned=False) if arrays else None


def forget_level_values(volume, level: int, names) -> None:
    """Drop the cached :func:`level_values` of fields ``names`` on ``level``."""
    for name in names:
        volume.level_caches.values.pop((level, name), None)


def adopt_caches(volume, source) -> None:
    """Give ``volume`` the level tables and the flat level values of its fields cached on
    ``source``, a volume of the same hierarchy (values are checked against the arrays before
    each use)."""
    volume.level_caches.index = dict(source.level_caches.index)
    volume.level_caches.blocks = dict(source.level_caches.blocks)
    volume.level_caches.dense_blocks = source.level_caches.dense_blocks
    # Only fields the volume holds: a flat copy of a dropped field would stay alive with it.
    volume.level_caches.values = {k: v for k, v in source.level_caches.values.items()
                                  if k[1] in volume.field_names}


def adopt_index(volume, source) -> None:
    """Give ``volume`` the level tables (:class:`LevelIndex`) made for ``source``, a volume of
    the same hierarchy (:meth:`AMRVolume.same_hierarchy
    <mi_amr.core.volume.AMRVolume.same_hierarchy>`), where both keep tables of the same dense
    block limit; tables ``volume`` made itself stay."""
    if volume.level_caches.dense_blocks == source.level_caches.dense_blocks:
        volume.level_caches.index = {**source.level_caches.index, **volume.level_caches.index}


def grid_offsets(volume, level: int) -> np.ndarray:
    """Where each grid of :class:`LevelIndex` ``level`` starts in :func:`level_values` (the
    table's own array: do not write to it)."""
    return level_index(volume, level).offsets


@contextlib.contextmanager
def fields_fixed(volume):
    """Inside, the volume's field arrays are taken not to change: :func:`level_values` returns
    what it has cached without first comparing every grid's array with it. That comparison is
    a pass over the level's grids; called per chunk of cells, with 10^4 grids to a level, it
    was a fifth of the derivation of 10^8 cells."""
    caches = volume.level_caches
    before = caches.fields_fixed
    caches.fields_fixed = before + 1
    try:
        yield
    finally:
        caches.fields_fixed = before


def cell_values(volume, level: int, index, fields):
    """Values of ``fields`` at level-``level`` cells ``index`` (``(N, 3)`` int).

    Returns ``(values, found)``: ``values`` is ``(len(fields), N)`` float64 (NaN where not found)
    and ``found`` is True where some grid of that level holds the cell. One gather per field
    from :func:`level_values`, whatever the number of grids; :func:`cell_values_reference` is
    the slow twin.
    """
    index = np.asarray(index, dtype=np.int64)
    table = level_index(volume, level)
    pos = table.find(index)
    found = pos >= 0
    values = np.full((len(fields), len(index)), np.nan)
    sel = np.flatnonzero(found)
    p = pos[sel]
    local = index[sel] - table.lo[p]
    n = (table.hi - table.lo)[p]
    flat = grid_offsets(volume, level)[p] + (local[:, 0] * n[:, 1] + local[:, 1]) * n[:, 2] + \
        local[:, 2]
    for f, name in enumerate(fields):
        values[f, sel] = np.take(level_values(volume, level, name), flat)
    return values, found


def cell_values_reference(volume, level: int, index, fields):
    """Slow twin of :func:`cell_values`: grid by grid."""
    index = np.asarray(index, dtype=np.int64)
    table = level_index(volume, level)
    pos = table.find(index)
    values = np.full((len(fields), len(index)), np.nan)
    for p in np.unique(pos[pos >= 0]):
        sel = np.flatnonzero(pos == p)
        local = index[sel] - table.lo[p]
        for f, name in enumerate(fields):
            arr = volume.grids[table.grids[p]].fields[name]
            values[f, sel] = arr[local[:, 0], local[:, 1], local[:, 2]]
    return values, pos >= 0


def interpolate(volume, level: int, points, fields, *, complete: bool = False):
    """Trilinear interpolation of level ``level`` at world ``points`` (``(N, 3)``).

    The 8 cells around each point (cell centres as nodes) are read across grids of the level;
    a cell the level does not have is itself interpolated from the next coarser level, and at
    level 0 a missing cell (outside the domain) is left out and the remaining weights are
    renormalised. Returns ``(len(fields), N)``; NaN where no cell around a point has data.
    ``complete=True`` gives NaN instead wherever a cell with non-zero weight lacks data, at any
    level, so the result is a true trilinear interpolation (exact for linear fields) or NaN.
    """
    points = np.asarray(points, dtype=np.float64)
    h = volume.level_spacing(level)
    u = (points - volume.anchor) / h - 0.5
    base = np.floor(u).astype(np.int64)
    frac = u - base
    # Points sharing a base cell share their 8 cells: look each base up once (ghost layers of a
    # fine level have ~4 points per coarse base).
    bases, which = _unique_rows(base)
    bits = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
    cells = (bases[None] + bits[:, None]).reshape(-1, 3)     # corner after corner
    vals, found = cell_values(volume, level, cells, fields)
    if level > 0 and not found.all():
        missing = np.flatnonzero(~found)
        centres = volume.anchor + (cells[missing] + 0.5) * h
        vals[:, missing] = interpolate(volume, level - 1, centres, fields, complete=complete)
    vals = vals.reshape(len(fields), 8, len(bases))
    num = np.zeros((len(fields), len(points)))
    den = np.zeros(len(points))
    lo_w, hi_w = 1.0 - frac, frac
    for corner in range(8):
        w = np.ones(len(points))
        for a in range(3):
            w *= hi_w[:, a] if bits[corner, a] else lo_w[:, a]
        v = vals[:, corner, which]
        ok = np.isfinite(v).all(axis=0)
        w = np.where(ok, w, 0.0)
        num += np.where(ok, w * v, 0.0)
        den += w
    # The weights sum to 1 up to rounding when no cell is missing.
    enough = den > 1.0 - 1e-9 if complete else den > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(enough, num / den, np.nan)


def interpolate_reference(volume, level: int, points, fields, *, complete: bool = False):
    """Slow twin of :func:`interpolate`: point by point, cells read grid by grid
    (:func:`cell_values_reference`), no sharing of base cells."""
    points = np.asarray(points, dtype=np.float64)
    h = volume.level_spacing(level)
    out = np.full((len(fields), len(points)), np.nan)
    for p, point in enumerate(points):
        u = (point - volume.anchor) / h - 0.5
        base = np.floor(u).astype(np.int64)
        frac = u - base
        num, den = np.zeros(len(fields)), 0.0
        for corner in range(8):
            bits = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            w = np.prod(np.where(bits == 1, frac, 1.0 - frac))
            vals, found = cell_values_reference(volume, level, (base + bits)[None], fields)
            if level > 0 and not found[0]:
                vals = interpolate_reference(volume, level - 1, (volume.anchor + (
                    base + bits + 0.5) * h)[None], fields, complete=complete)
            if np.all(np.isfinite(vals)):
                num, den = num + w * vals[:, 0], den + w
        if (den > 1.0 - 1e-9) if complete else den > 0:
            out[:, p] = num / den
    return out


def _unique_rows(index):
    """``(rows, which)``: the distinct rows of an ``(N, 3)`` int array and, per input row, the
    position of its row in ``rows``."""
    if len(index) == 0:
        return index, np.zeros(0, dtype=np.int64)
    low = index.min(axis=0)
    span = index.max(axis=0) - low + 1
    b = index - low
    keys = (b[:, 0] * span[1] + b[:, 1]) * span[2] + b[:, 2]
    keys, which = np.unique(keys, return_inverse=True)
    rows = np.stack([keys // (span[1] * span[2]), (keys // span[2]) % span[1], keys % span[2]],
                    axis=1) + low
    return rows, which.ravel()
