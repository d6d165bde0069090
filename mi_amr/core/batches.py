"""Grids taken together by shape: the grids of one shape stacked into one NumPy array, so that
a pass over tens of thousands of small grids (an isovalue pick, the camera's framing) costs a
few array operations per shape and batch instead of a few per grid.

Index order: a batch is ``(k, nx, ny, nz)``, grid ``ids[j]`` at ``[j]`` in the C order of its
own array; the flat arrays are all cells grid after grid (:meth:`AMRVolume.cell_offsets`).
"""

from __future__ import annotations

import numpy as np

from mi_amr.core import levels

# Cells a batch holds at most (one grid at least): bounds its temporaries, a few bytes to a few
# tens of bytes a cell.
BATCH_CELLS = 1 << 20


def flat_field(volume, name: str) -> np.ndarray:
    """Field ``name`` of all grids, raveled and concatenated grid after grid, in its own dtype
    (read only: the buffer the grids' arrays are views of, when they lie end to end in one)."""
    flat = levels.volume_values(volume, name)
    return flat if flat is not None else \
        np.concatenate([g.fields[name].reshape(-1) for g in volume.grids])


def shape_batches(volume, cells: int | None = None):
    """``(ids, shape)`` for each batch: grid ids (ascending) of one shape, as many as hold at
    most ``cells`` cells (:data:`BATCH_CELLS` when None), and that shape (a tuple of ints).
    Every grid is in one batch."""
    cells = BATCH_CELLS if cells is None else cells
    shapes = volume.grid_columns()["shape"]
    if len(shapes) == 0:
        return
    kinds, which = np.unique(shapes, axis=0, return_inverse=True)
    which = np.asarray(which).reshape(-1)
    order = np.argsort(which, kind="stable")
    starts = np.searchsorted(which[order], np.arange(len(kinds) + 1))
    for kind in range(len(kinds)):
        ids = order[starts[kind]:starts[kind + 1]]
        shape = tuple(int(n) for n in kinds[kind])
        per = max(1, cells // max(1, shape[0] * shape[1] * shape[2]))
        for start in range(0, len(ids), per):
            yield ids[start:start + per], shape


def stacked(flat: np.ndarray, offsets: np.ndarray, ids, shape) -> np.ndarray:
    """The cells of grids ``ids`` (all of ``shape``) of the flat array ``flat`` (offsets: each
    grid's first cell), as a ``(len(ids), *shape)`` array: read only, a view of ``flat`` where
    the grids lie end to end in it (one grid, or grids one after the other), else a copy."""
    n = shape[0] * shape[1] * shape[2]
    starts = offsets[ids]
    if len(starts) == 1 or np.all(np.diff(starts) == n):
        return flat[starts[0]:starts[0] + len(starts) * n].reshape((len(ids),) + tuple(shape))
    index = starts[:, None] + np.arange(n, dtype=np.int64)
    return flat[index].reshape((len(ids),) + tuple(shape))


def _pairs(axis: int):
    a = tuple(slice(0, -1) if k == axis + 1 else slice(None) for k in range(4))
    b = tuple(slice(1, None) if k == axis + 1 else slice(None) for k in range(4))
    return a, b


_AXIS_PAIRS = tuple(_pairs(axis) for axis in range(3))


def axis_pairs(axis: int):
    """Index tuples ``(a, b)`` of a batch ``(k, nx, ny, nz)`` that pair each cell with its
    neighbour above along grid axis ``axis`` (0-2) in the same grid."""
    return _AXIS_PAIRS[axis]
