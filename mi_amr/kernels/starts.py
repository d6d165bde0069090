"""Where a ray's leaf search starts: a table of kd nodes over the active box, so that a search
that would descend from the root starts at the deepest node holding the point.

The exact march on the basis blend clips its rays to the active box of the frame's isovalues
(:meth:`~mi_amr.kernels.device.DeviceVolume.active_box`) and then searches the kd-tree for the
leaves inside it, each search descending from the root (a camera ray at its entry, every shadow
ray) or from a rope. The kd nodes are power-of-two boxes of the finest level's lattice, as in an
octree (:mod:`mi_amr.core.kdtree`), so a uniform table whose cells are the smallest active
leaves' size, laid on the same lattice, has each cell inside one node, often a leaf: the
**start table** holds, for every cell, the first node on the way down from the root that the
search skips (its range holds no isovalue), else the deepest node whose box holds the whole
cell. A search from a point in the box looks its cell up and goes on from that node instead of
the root, which is where a descent from the root would arrive (it passes through every node
holding the point and stops at the first it skips), so the same leaves are found at the same
parameters. Entries that end a descent (a leaf, or a node to skip) are marked :data:`FINAL`:
there the search does not read its rope either; elsewhere it takes the deeper of the two.

Cells are half open, ``[lo + i s, lo + (i + 1) s)`` on each axis (a point on a split plane goes
up, as in the tree). The table is built on the host when the isovalues change (with the active
box), in lattice integers; the kernels read it as opaque inputs (a new isovalue compiles
nothing), and check that the node found holds the point (rounding at a cell's face may give
its neighbour), falling back to the root where it does not or where the point is outside the
table.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Array3f, UInt32

from mi_amr.kernels.intmath import quotient

# Cells of a start table at most (4 bytes each): a coarser cell (twice the size, a shallower
# start node) where the smallest active leaves would need more.
MAX_START_CELLS = 1 << 21
FINAL = 1 << 31           # set in a table entry whose node ends a descent (a leaf, or empty)


@dataclass
class StartTable:
    """A start table as kernel inputs: ``nodes`` (``m.UInt32``, x fastest), the box's lower
    corner ``lo`` and ``inv_cell`` (one over the cell's size) as opaque points (volume world),
    and ``dims``, the cells per axis, as an opaque point (0 for an empty table)."""

    nodes: UInt32
    lo: Array3f
    inv_cell: Array3f
    dims: Array3f


def table_frame(tree, active_nodes, max_cells: int = MAX_START_CELLS):
    """``(lo, cell, dims)`` of the start table over the leaves ``active_nodes`` (kd node
    indices, at least one) of ``tree``: lower corner and cell size in lattice units (finest
    cells from the volume's anchor, whole numbers as float64 3-vectors) and cells per axis,
    at most ``max_cells`` in all (the cells twice as large where they would be more)."""
    node_lo = tree.lattice_node_lo[active_nodes].astype(np.float64)   # (integers in the tree)
    node_hi = tree.lattice_node_hi[active_nodes].astype(np.float64)
    lo, hi, cell = node_lo.min(axis=0), node_hi.max(axis=0), (node_hi - node_lo).min(axis=0)
    origin = tree.lattice_root[0]
    while True:
        # The corner on the cells' lattice from the root's corner (node boxes are aligned so).
        start = origin + np.floor((lo - origin) / cell) * cell
        dims = np.ceil((hi - start) / cell).astype(np.int64)
        if np.prod(dims) <= max_cells:
            return start, cell, dims
        cell = cell * 2


def start_table_host(tree, active_nodes, empty=None, max_cells: int = MAX_START_CELLS):
    """``(lo, cell, dims, nodes)`` of the start table over the leaves ``active_nodes`` (kd node
    indices) of ``tree``: :func:`table_frame`, and the node of each cell (x fastest); an empty
    table (no cells) where there are no active nodes. Descents stop at the nodes where
    ``empty`` (a bool per node: ranges the search skips); entries of leaves and of such nodes
    have :data:`FINAL` set. The slow twin of :func:`start_table_device`."""
    if len(active_nodes) == 0:
        return np.zeros(3), np.ones(3), np.zeros(3, dtype=np.int64), np.zeros(1, np.uint32)
    start, cell, dims = table_frame(tree, active_nodes, max_cells)
    idx = np.indices(dims[::-1]).reshape(3, -1)[::-1].T       # x fastest
    c_lo = start + idx * cell
    # Cells are half open on a lattice of whole numbers: [lo, lo + cell) holds what the
    # closed box [lo, lo + cell - 1/2] does.
    nodes = tree.descend_boxes(c_lo, c_lo + cell - 0.5, stop=empty)
    final = (tree.node_code[nodes] & 3) == 3
    if empty is not None:
        final |= empty[nodes]
    return start, cell, dims, (nodes | np.where(final, FINAL, 0)).astype(np.uint32)


@dataclass
class Descent:
    """The kd-tree as a table's descents read it on the device: ``code_split`` (per node its
    code and a second uint32, side by side: :attr:`DeviceVolume.node_code_split
    <mi_amr.kernels.device.DeviceVolume.node_code_split>`), ``split`` (its split plane in
    lattice units, Int32) and ``stop`` (Bool: the nodes the search skips)."""

    code_split: UInt32
    split: object
    stop: object


def start_table_device(m, descent: Descent, frame):
    """The entries of :func:`start_table_host` for the table ``frame`` (``(lo, cell, dims)``
    of :func:`table_frame`, lattice whole numbers that int32 holds), computed on backend ``m``:
    a lane a cell, each descending from the root (a ``UInt32`` array, x fastest). In whole
    numbers the half-open cell ``[lo, lo + cell)`` goes below a split plane ``s`` where
    ``lo + cell - 1 < s``, as the host's ``lo + cell - 1/2`` does."""
    start, cell, dims = frame
    n = int(np.prod(dims))
    i = dr.arange(m.UInt32, max(n, 2))
    nx, nxy = (dr.opaque(m.UInt32, int(x)) for x in (dims[0], dims[0] * dims[1]))
    iz = quotient(m, i, nxy)
    rest = i - iz * nxy
    iy = quotient(m, rest, nx)
    idx = m.Array3i(m.Int32(rest - iy * nx), m.Int32(iy), m.Int32(iz))
    size = m.Array3i(*(dr.opaque(m.Int32, int(c)) for c in cell))
    lo = m.Array3i(*(dr.opaque(m.Int32, int(c)) for c in start)) + idx * size
    node, code = _descend(m, descent, lo, lo + size - 1)
    final = ((code & 3) == 3) | dr.gather(m.Bool, descent.stop, node)
    out = node | dr.select(final, m.UInt32(FINAL), 0)
    dr.eval(out)
    return out


@dr.syntax
def _descend(m, descent: Descent, lo, hi):
    """``(node, code)``: for each closed lattice box ``[lo, hi]`` (``m.Array3i``) the deepest
    node holding it all, descending from the root, or the first node met that ``stop``
    marks; and that node's code (:meth:`~mi_amr.core.kdtree.KDTree.descend_boxes`)."""
    node = m.UInt32(0)
    code = dr.gather(m.UInt32, descent.code_split, m.UInt32(0))
    going = m.Bool(True)
    while dr.hint(going, label="start_table", exclude=[descent, hi, lo, m]):
        axis = code & 3
        inner = (axis != 3) & ~dr.gather(m.Bool, descent.stop, node, going)
        split = dr.gather(m.Int32, descent.split, node, going)
        a_lo = dr.select(axis == 0, lo.x, dr.select(axis == 1, lo.y, lo.z))
        a_hi = dr.select(axis == 0, hi.x, dr.select(axis == 1, hi.y, hi.z))
        above = inner & (a_lo >= split)
        going &= above | (inner & (a_hi < split))
        node = dr.select(going, (code >> 2) + dr.select(above, m.UInt32(1), 0), node)
        code = dr.select(going, dr.gather(m.UInt32, descent.code_split, 2 * node, going), code)
    return node, code


def descend_box_reference(tree, lo, hi, stop=None) -> int:
    """Slow twin of the table's descents (:meth:`~mi_amr.core.kdtree.KDTree.descend_boxes`)
    for one half-open box ``[lo, hi)``: the plain descent, node by node."""
    node = 0
    while (tree.node_code[node] & 3) != 3 and not (stop is not None and stop[node]):
        axis = tree.node_code[node] & 3
        split = tree.lattice_node_split[node]
        if lo[axis] >= split:
            node = (tree.node_code[node] >> 2) + 1
        elif hi[axis] <= split:
            node = tree.node_code[node] >> 2
        else:
            break
    return int(node)


def table_start(dev, table: StartTable, p, active):
    """``(node, lo, hi, found, final)``: the table's node for the point ``p`` (volume world),
    its box and whether its entry is :data:`FINAL`, where ``found`` (the point is in the table
    and the node holds it)."""
    m = dev.m
    rel = (p - table.lo) * table.inv_cell
    in_table = active & dr.all((rel >= 0.0) & (rel < table.dims))
    cell = m.Array3u(dr.floor(rel))
    nx, ny = m.UInt32(table.dims.x), m.UInt32(table.dims.y)
    index = (cell.z * ny + cell.y) * nx + cell.x
    entry = dr.gather(m.UInt32, table.nodes, index, in_table)
    node = entry & (FINAL - 1)
    lo = dr.gather(m.Array4f, dev.node_box, 2 * node, in_table)
    hi = dr.gather(m.Array4f, dev.node_box, 2 * node + 1, in_table)
    lo, hi = m.Array3f(lo.x, lo.y, lo.z), m.Array3f(hi.x, hi.y, hi.z)
    # Half open, as the descent goes: a point on a split plane belongs to the upper node.
    found = in_table & dr.all((p >= lo) & (p < hi))
    return node, lo, hi, found, entry >= FINAL
