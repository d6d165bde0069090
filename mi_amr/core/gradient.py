"""The velocity gradient across levels, by central differences with ghost cells.

A derivative at a cell is the central difference of its two neighbours along the axis. A
neighbour beyond the grid's edge (a *ghost cell*, one cell of the grid's level) comes from the
grid of the same level that holds it; failing that, from trilinear interpolation of the coarser
level at the ghost cell's centre; failing that (outside the domain, or so near its edge that the
interpolation would lack cells) the difference is one-sided, second order (first order for a
grid 2 cells thick; a grid 1 cell thick uses its other ghost, or 0).
This is what keeps Q continuous across level boundaries (the course report, section 4.1, saw it
jump when every grid used one-sided differences at its own edges).

Two implementations give the same numbers bit for bit:

* :func:`level_gradients` works on whole levels: the level's cells flattened grid after grid
  (the order of :func:`levels.level_values`), neighbours found by index arithmetic, and one
  ghost-cell pass (one lookup, one interpolation) per chunk of :data:`levels.CHUNK_CELLS`
  cells.
* :func:`grid_gradients_reference` is the slow obvious twin: grid by grid, each grid padded
  with its ghost layers and differenced with array slices.

Units: derivatives are per world unit; index coordinates are those of
:meth:`AMRVolume.index_boxes` (cells of the level from the volume's anchor, ``[i, j, k]`` =
x, y, z).
"""

from __future__ import annotations

import numpy as np

from mi_amr.core import levels, parallel


def level_gradients(volume, comps, chunk_cells: int = levels.CHUNK_CELLS):
    """Yields ``(grids, grad)`` chunk by chunk, level by level: ``grids`` the volume's indices
    of consecutive grids of one level and ``grad`` the ``(3, 3, N)`` float64 array
    ``[i][j] = d v_i / d x_j`` (per world unit) of their cells, grid after grid, each grid's
    cells in C order of its ``(nx, ny, nz)`` array. A chunk is whole grids holding at least
    ``chunk_cells`` cells (:func:`levels.grid_chunks`)."""
    with levels.fields_fixed(volume):
        for job in _chunk_jobs(volume, comps, chunk_cells):
            grad, _ = _job_gradient(volume, comps, job)
            level, start, stop = job
            yield levels.level_index(volume, level).grids[start:stop], grad


def map_chunks(volume, comps, fn, threads: int | None = None,
               chunk_cells: int = levels.CHUNK_CELLS, todo=None):
    """``fn(level, at, grad)`` for the chunks of :func:`level_gradients` (``at``: where the
    chunk's cells start in the level's :func:`levels.level_values`), yielded in the same
    order, the chunks computed side by side (:func:`parallel.map_ordered`); only those of the
    levels ``todo`` (a list) where given."""
    def work(job):
        grad, at = _job_gradient(volume, comps, job)
        return fn(job[0], at, grad)

    with levels.fields_fixed(volume):
        yield from parallel.map_ordered(work, _chunk_jobs(volume, comps, chunk_cells, todo),
                                        threads)


def _chunk_jobs(volume, comps, chunk_cells, todo=None):
    """``(level, start, stop)`` of every chunk of the levels ``todo`` (default: all); the
    level tables and flat values every chunk reads (its level's, and the coarser ones
    interpolation reads) are cached first, so threads only read them."""
    todo = list(range(volume.num_levels)) if todo is None else list(todo)
    for level in range(max(todo, default=-1) + 1):
        levels.level_index(volume, level)
        for name in comps:
            levels.level_values(volume, level, name)
    for level in todo:
        for start, stop in levels.grid_chunks(levels.level_index(volume, level), chunk_cells):
            yield level, start, stop


def _job_gradient(volume, comps, job):
    """The gradient of chunk ``job`` and where its cells start in the level's flat values."""
    level, start, stop = job
    cells = _ChunkCells(volume, levels.level_index(volume, level), start, stop)
    at = levels.grid_offsets(volume, level)[start]
    values = [np.asarray(levels.level_values(volume, level, name)[at:at + cells.size],
                         dtype=np.float64) for name in comps]
    return _chunk_gradient(volume, level, comps, cells, values), at


class _ChunkCells:
    """Where the cells of grids ``start:stop`` of a level's :class:`LevelIndex` lie, one flat
    array per axis (cells grid after grid, each grid in C order): ``local[a]`` the cell's
    index in its grid, ``thick[a]`` the grid's size, ``stride[a]`` the step to the next cell
    (in cells of the chunk), ``spacing[a]`` the cell size (world units; a number when the
    level's grids agree) and ``faces[a]`` the chunk positions of the cells on the grid's lower
    and upper face. ``grid`` is each cell's grid (position in the table)."""

    def __init__(self, volume, table, start, stop):
        dims = (table.hi - table.lo)[start:stop]
        counts = np.prod(dims, axis=1)
        self.size = int(counts.sum())
        self.grid = np.repeat(np.arange(start, stop), counts)
        offset = np.arange(self.size) - np.repeat(np.cumsum(counts) - counts, counts)
        self.thick = [np.repeat(dims[:, a], counts) for a in range(3)]
        plane = self.thick[1] * self.thick[2]
        i = offset // plane
        rest = offset - i * plane
        j = rest // self.thick[2]
        self.local = [i, j, rest - j * self.thick[2]]
        self.stride = [plane, self.thick[2], 1]
        h = volume.spacings()[table.grids[start:stop]]
        self.spacing = [h[0, a] if np.all(h[:, a] == h[0, a]) else np.repeat(h[:, a], counts)
                        for a in range(3)]
        self.faces = [(np.flatnonzero(self.local[a] == 0),
                       np.flatnonzero(self.local[a] == self.thick[a] - 1)) for a in range(3)]
        self.origin = table.lo

    def index(self, at):
        """Level index of the cells at chunk positions ``at``: ``(len(at), 3)`` int64."""
        return self.origin[self.grid[at]] + np.stack([x[at] for x in self.local], axis=1)


def _chunk_gradient(volume, level, comps, cells, values):
    """``(3, 3, N)`` gradient of one chunk; ``values`` the chunk's float64 components."""
    ghosts = _ghost_values(volume, level, comps, cells)
    grad = np.empty((3, 3, cells.size))
    for axis in range(3):
        for c in range(3):
            lo_ghost, hi_ghost = ghosts[axis]
            grad[c, axis] = _axis_difference(values[c], lo_ghost[c], hi_ghost[c], cells, axis)
    return grad


def _ghost_values(volume, level, comps, cells):
    """Per axis ``(below, above)``: ``(3, F)`` float64 values of the ghost cells beyond the
    chunk's lower and upper faces (``cells.faces``), NaN where no level has data. One lookup on
    the level and one interpolation of the coarser level for the whole chunk."""
    parts = []
    for axis in range(3):
        for side, step in ((0, -1), (1, 1)):
            index = cells.index(cells.faces[axis][side])
            index[:, axis] += step
            parts.append(index)
    index = np.concatenate(parts)
    values, found = levels.cell_values(volume, level, index, comps)
    if level > 0 and not found.all():
        missing = np.flatnonzero(~found)
        centres = volume.anchor + (index[missing] + 0.5) * volume.level_spacing(level)
        values[:, missing] = levels.interpolate(volume, level - 1, centres, comps, complete=True)
    ends = np.cumsum([0] + [len(p) for p in parts])
    return [(values[:, ends[2 * a]:ends[2 * a + 1]], values[:, ends[2 * a + 1]:ends[2 * a + 2]])
            for a in range(3)]


def _axis_difference(v, lo_ghost, hi_ghost, cells, axis):
    """d v / d x along ``axis`` for a chunk's cells (``v`` flat float64): central differences,
    neighbours beyond a face taken from the ghosts, one-sided where a ghost is NaN."""
    stride = cells.stride[axis]
    lo_face, hi_face = cells.faces[axis]
    if axis == 2:                               # stride 1: shifted copies
        above, below = np.empty_like(v), np.empty_like(v)
        above[:-1], below[1:] = v[1:], v[:-1]
    else:                                       # the values beyond a face are replaced below
        here = np.arange(cells.size)
        above = np.take(v, here + stride, mode="clip")
        below = np.take(v, here - stride, mode="clip")
    above[hi_face] = hi_ghost
    below[lo_face] = lo_ghost
    h = cells.spacing[axis]
    d = (above - below) / (2.0 * h)
    # The lower face first, then the upper: a cell 1 thick is on both and the upper one wins,
    # as in the slow twin.
    for sign, face, ghost, other in ((1, lo_face, below, above), (-1, hi_face, above, below)):
        at = face[~np.isfinite(ghost[face])]
        if len(at):
            d[at] = _one_sided(v, at, sign, np.broadcast_to(stride, v.shape)[at],
                               cells.thick[axis][at], np.broadcast_to(h, v.shape)[at], other[at])
    return d


def _one_sided(v, at, sign, stride, thick, h, other):
    """One-sided differences at cells ``at`` of a face whose ghost is missing, stepping into
    the grid (``sign`` +1 from the lower face, -1 from the upper): second order where the grid
    is 3 cells thick or more, first order at 2, and at 1 the difference to the ``other``
    ghost (0 where that is missing too)."""
    f0 = v[at]
    step = sign * stride
    f1 = v[np.where(thick >= 2, at + step, at)]
    f2 = v[np.where(thick >= 3, at + 2 * step, at)]
    second = sign * (-3.0 * f0 + 4.0 * f1 - f2) / (2.0 * h)
    first = sign * (f1 - f0) / h
    with np.errstate(invalid="ignore"):
        lone = np.where(np.isfinite(other), sign * (other - f0) / h, 0.0)
    return np.where(thick >= 3, second, np.where(thick == 2, first, lone))


# ---------------------------------------------------------------------- the slow twin

def grid_gradients_reference(volume, comps):
    """Per grid (a generator), ``(3, 3, nx, ny, nz)`` float64 with ``[i][j] = d v_i / d x_j``:
    the slow twin of :func:`level_gradients`, grid by grid."""
    ghosts = _ghost_layers(volume, comps)
    for gi, g in enumerate(volume.grids):
        grad = np.empty((3, 3) + g.shape)
        for c, name in enumerate(comps):
            v = g.fields[name].astype(np.float64)
            for axis in range(3):
                lo_ghost, hi_ghost = ghosts[gi][axis]
                grad[c, axis] = _difference(v, lo_ghost[c], hi_ghost[c], axis, g.spacing[axis])
        yield grad


def _ghost_layers(volume, comps) -> list:
    """Per grid and axis, the ghost layers below and above: ``(3, ...)`` arrays shaped like a
    one-cell slab of the grid along that axis, NaN where no level has data."""
    lo, _ = volume.index_boxes()
    result = [[[None, None] for _ in range(3)] for _ in volume.grids]
    for gi, g in enumerate(volume.grids):
        for axis in range(3):
            slab = list(g.shape)
            slab[axis] = 1
            idx = np.stack(np.meshgrid(*[np.arange(n) for n in slab], indexing="ij"),
                           axis=-1).reshape(-1, 3) + lo[gi]
            for side, pos in ((0, -1), (1, g.shape[axis])):
                cells = idx.copy()
                cells[:, axis] = lo[gi, axis] + pos
                values, found = levels.cell_values_reference(volume, g.level, cells, comps)
                if g.level > 0 and not found.all():
                    missing = np.flatnonzero(~found)
                    centres = volume.anchor + (cells[missing] + 0.5) * \
                        volume.level_spacing(g.level)
                    values[:, missing] = levels.interpolate(volume, g.level - 1, centres,
                                                            comps, complete=True)
                result[gi][axis][side] = values.reshape((3,) + tuple(slab))
    return result


def _difference(v, lo_ghost, hi_ghost, axis, h):
    """d v / d x along ``axis``: central differences using the ghost layers, one-sided (second
    order where the grid has 3 cells or more) where a ghost value is missing (NaN)."""
    ext = np.concatenate([lo_ghost, v, hi_ghost], axis=axis)
    n = v.shape[axis]
    take = lambda a, i: np.take(a, i, axis=axis)  # noqa: E731
    d = (take(ext, np.arange(2, n + 2)) - take(ext, np.arange(0, n))) / (2.0 * h)
    # The side picks the ghost layers, not ``end``: with one cell, both ends are cell 0.
    for end, sign, ghost, other in ((0, 1, lo_ghost, hi_ghost), (n - 1, -1, hi_ghost, lo_ghost)):
        missing = ~np.isfinite(np.take(ghost, 0, axis=axis))
        if not missing.any():
            continue
        if n >= 3:
            f0, f1, f2 = (take(v, end + sign * k) for k in range(3))
            one_sided = sign * (-3.0 * f0 + 4.0 * f1 - f2) / (2.0 * h)
        elif n == 2:
            one_sided = sign * (take(v, end + sign) - take(v, end)) / h
        else:
            g = np.take(other, 0, axis=axis)
            one_sided = np.where(np.isfinite(g), sign * (g - take(v, 0)) / h, 0.0)
        idx = [slice(None)] * 3
        idx[axis] = end
        d[tuple(idx)] = np.where(missing, one_sided, d[tuple(idx)])
    return d
