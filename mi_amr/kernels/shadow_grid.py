"""Volume mode's transmittance cache: a regular grid over the leaves that hold band opacity,
holding at each grid point the transmittance towards one light, looked up by trilinear
interpolation (deep shadow maps; OSPRay's and ParaView's volume shadows).

The grid is node-centred in the volume's world space: point ``(i, j, k)`` lies at
``lo + (i, j, k) * cell`` and is stored at ``i + nx * (j + ny * k)`` (``[i, j, k]`` = x, y,
z). Its spacing is the finest cell width of the leaves that hold opacity, made coarser where
the grid would hold more than :data:`~mi_amr.tolerances.SHADOW_CACHE_POINTS` points. Only the
points within one grid cell of such a leaf are needed: a lit piece lies inside one, and the
eight corners of its lookup are that close. The host plans the grid (:func:`plan`,
:func:`needed_points`); the plugin fills it with the exact shadow compositing
(:mod:`mi_amr.plugin.shadow_cache`); :func:`lookup` reads it per piece.

A thin band's shadow on itself changes from clear to dark within far less than a grid cell,
and a lit piece lies inside that band: the trilinear lookup there blends corners on either
side of it, an error that a finer grid hardly reduces. So a piece's shadow is composited
exactly over the first stretch of its shadow ray, the grid's ``reach`` (one grid cell), and
looked up only beyond it, where the eight corners lie ahead of the piece's own band.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from mi_amr import tolerances as tol
from mi_amr.kernels.arrays import device_array
from mi_amr.kernels.device import opaque_floats, opaque_point

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Array3f, Float


@dataclass(frozen=True)
class GridPlan:
    """Where a cache's points lie (host, float64, volume world): the first point ``lo``, the
    spacing ``cell`` (3 floats) and the points per axis ``dims`` (3 ints, each >= 2);
    ``reach`` (volume world): how far along a shadow ray the band is composited exactly
    before the grid is read (see the module docstring)."""

    lo: np.ndarray
    cell: np.ndarray
    dims: np.ndarray
    reach: float = 0.0

    @property
    def size(self) -> int:
        return int(np.prod(self.dims))


def band_leaves(tree, ranges, bands) -> np.ndarray:
    """The kd leaves (leaf indices) whose value range (``ranges``: per node ``lo, hi`` side by
    side, see :meth:`~mi_amr.kernels.device.DeviceVolume.node_ranges`) overlaps one of
    ``bands`` (``(lo, hi)`` value ranges, field units): the leaves a volume march finds
    opacity in."""
    r = np.asarray(ranges, dtype=np.float64).reshape(-1, 2)[tree.leaf_node]
    holds = np.zeros(len(r), dtype=bool)
    for lo, hi in bands:
        holds |= (r[:, 0] <= hi) & (r[:, 1] >= lo)
    return np.flatnonzero(holds)


def plan(tree, leaves, max_points: int = tol.SHADOW_CACHE_POINTS) -> GridPlan:
    """The grid over the box of ``leaves`` (leaf indices of ``tree``, not empty), at their
    finest cell width, coarsened evenly until it holds at most ``max_points`` points; its
    reach is its longest cell side, at most :data:`~mi_amr.tolerances.SHADOW_REACH_CELLS`
    finest cells (a coarse preview grid keeps the exact stretch short)."""
    lo, hi = tree.leaf_boxes(leaves)
    lo, hi = lo.min(axis=0), hi.max(axis=0)
    h = float(np.nanmin(np.where(np.isfinite(tree.leaf_min_h[leaves]),
                                 tree.leaf_min_h[leaves], np.nan)))
    extent = np.maximum(hi - lo, h)
    finest = h
    while True:
        dims = np.maximum(np.ceil(extent / h).astype(np.int64) + 1, 2)
        if np.prod(dims) <= max_points:
            break
        h *= max(1.01, (np.prod(dims) / max_points) ** (1.0 / 3.0))
    cell = extent / (dims - 1)
    reach = min(float(cell.max()), tol.SHADOW_REACH_CELLS * finest)
    return GridPlan(lo=np.asarray(lo, np.float64), cell=cell, dims=dims.astype(np.int64),
                    reach=reach)


def needed_points(grid: GridPlan, tree, leaves) -> np.ndarray:
    """The flat indices (``uint32``, ascending) of the grid points within one grid cell of
    one of ``leaves``: every corner a lookup inside those leaves reads."""
    lo, hi = tree.leaf_boxes(leaves)
    first = np.floor((lo - grid.lo) / grid.cell).astype(np.int64) - 1
    last = np.ceil((hi - grid.lo) / grid.cell).astype(np.int64) + 1
    first = np.clip(first, 0, grid.dims - 1)
    last = np.clip(last, 0, grid.dims - 1) + 1
    # Each box adds 1 to the points it covers, by +-1 at its 8 corners of a difference array
    # whose running sums along the three axes count the boxes at each point.
    nx, ny, nz = (int(n) + 1 for n in grid.dims)
    flat, signs = [], []
    for corner in range(8):
        i, j, k = ((last if corner >> a & 1 else first)[:, a] for a in range(3))
        flat.append(i + nx * (j + ny * k))
        signs.append(np.full(len(i), -1.0 if bin(corner).count("1") % 2 else 1.0))
    diff = np.bincount(np.concatenate(flat), np.concatenate(signs), minlength=nx * ny * nz)
    count = diff.reshape(nz, ny, nx).cumsum(0).cumsum(1).cumsum(2)[:-1, :-1, :-1]   # [k, j, i]
    return np.flatnonzero(count.ravel() > 0).astype(np.uint32)


def needed_points_by_box(grid: GridPlan, tree, leaves) -> np.ndarray:
    """:func:`needed_points` one leaf box at a time (its slow twin, for tests)."""
    need = np.zeros(tuple(grid.dims[::-1]), dtype=bool)      # [k, j, i]
    lo, hi = tree.leaf_boxes(leaves)
    first = np.floor((lo - grid.lo) / grid.cell).astype(np.int64) - 1
    last = np.ceil((hi - grid.lo) / grid.cell).astype(np.int64) + 1
    first = np.clip(first, 0, grid.dims - 1)
    last = np.clip(last, 0, grid.dims - 1)
    for (i0, j0, k0), (i1, j1, k1) in zip(first, last):
        need[k0:k1 + 1, j0:j1 + 1, i0:i1 + 1] = True
    return np.flatnonzero(need.ravel()).astype(np.uint32)


def point_positions(m, grid: GridPlan, index) -> Array3f:
    """The positions (volume world) of the grid points at flat indices ``index`` (a device
    ``UInt32``)."""
    # (The sizes are opaque, each from its own host memory: a grid of another size compiles
    # nothing, also where two sizes are equal, which as literals would be one variable.)
    nx, ny = (_opaque_uint(m, n) for n in grid.dims[:2])
    i = index % nx
    j = (index // nx) % ny
    k = index // (nx * ny)
    lo, cell = opaque_point(m, grid.lo), opaque_point(m, grid.cell)
    return dr.fma(m.Array3f(m.Float(i), m.Float(j), m.Float(k)), cell, lo)


def _opaque_uint(m, n):
    v = device_array(m.UInt32, [int(n)], np.uint32)
    dr.make_opaque(v)
    return v


@dataclass
class TransmittanceGrid:
    """A filled cache on the device: the grid's first point ``lo`` and inverse spacing
    ``inv_cell`` (volume world), the points per axis ``dims`` (as floats), the transmittance
    ``values`` (flat, see the module docstring) and ``reach``, the exact stretch of a lookup's
    shadow ray (scene units); all kernel inputs, never literals, so a new grid compiles
    nothing."""

    lo: Array3f
    inv_cell: Array3f
    dims: Array3f
    values: Float
    reach: Float

    @staticmethod
    def of(m, grid: GridPlan, values, reach: float = 0.0) -> "TransmittanceGrid":
        """The device grid of ``grid`` holding ``values`` (a device ``Float`` of
        ``grid.size``), with the exact stretch ``reach`` (scene units)."""
        dims = m.Array3f(*(opaque_floats(m, [float(n)]) for n in grid.dims))
        return TransmittanceGrid(lo=opaque_point(m, grid.lo),
                                 inv_cell=opaque_point(m, 1.0 / grid.cell), dims=dims,
                                 values=values, reach=opaque_floats(m, [reach]))


def lookup(m, cache: TransmittanceGrid, p, active):
    """The cached transmittance at volume points ``p`` (trilinear in the grid's cell; points
    outside the grid take its nearest face's values); 1 where not ``active``."""
    u = dr.clip((p - cache.lo) * cache.inv_cell, 0.0, cache.dims - 1.0)
    base = dr.minimum(dr.floor(u), cache.dims - 2.0)
    f = u - base
    i0 = m.UInt32(base.x)
    nx = m.UInt32(cache.dims.x)
    row = nx * m.UInt32(cache.dims.y)
    first = i0 + nx * m.UInt32(base.y) + row * m.UInt32(base.z)
    out = m.Float(0.0)
    for dz in (0, 1):
        for dy in (0, 1):
            for dx in (0, 1):
                w = (f.x if dx else 1.0 - f.x) * (f.y if dy else 1.0 - f.y) * \
                    (f.z if dz else 1.0 - f.z)
                idx = first + dx + dy * nx + dz * row
                out += w * dr.gather(m.Float, cache.values, idx, active)
    return dr.select(active, out, 1.0)
