"""The kd-tree's build with its (node, grid) pair passes on the device.

:meth:`KDTree._build <mi_amr.core.kdtree.KDTree._build>` (NumPy) is the host's way and the
twin: breadth first, one depth at a time, each depth's (node, grid) pairs sorted by node and
grid. Here the pairs live on the device, and per depth two kernels take them, a lane a pair:

* **classify**: whether the grid's box contains the node or cuts it, reduced per node into the
  greatest owner key (:meth:`~mi_amr.core.kdtree.KDTree.owner_keys`), a cut mark and the finest
  level (atomic maxima into per-node arrays);
* **children**: which sides of the node's split the grid's support reaches; each pair's place
  among its child's pairs is its rank among its parent's pairs going that way (exclusive prefix
  sums over the pairs, less the sum at the parent's first pair), after the pairs of the
  children before it (a prefix sum over the children's counts). So the next depth's pairs are
  sorted by child and grid again, with no sort.

The host keeps what is per node (the split planes: :meth:`KDTree.split_planes
<mi_amr.core.kdtree.KDTree.split_planes>`, the children's boxes, the emitted arrays), and
takes the pairs of each depth's leaves. The numbers are the host's (``tests/test_device_prep.py``).

Coordinates are the tree's lattice (cells of the finest level from the volume's anchor), int32:
the tree must :func:`fit <fits>`. Every size is a kernel input, so all depths and trees run the
kernels compiled once.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from mi_amr.core import kdtree
from mi_amr.kernels.arrays import device_table

LATTICE_MAX = kdtree.INT32_LATTICE   # |lattice coordinate| below which boxes fit in int32
KEY_MAX = 1 << 31         # owner keys (plus one) below this fit in uint32 with room to spare
# Atomic reductions into the per-node arrays: the default on the CPU keeps a copy of the target
# per thread, whose size the kernel would then hold (a kernel per depth and tree).
DIRECT = dr.ReduceMode.Direct


def fits(tree) -> bool:
    """Can :func:`build` take ``tree`` (its lattice and owner keys small enough)?"""
    keys = tree.owner_keys()
    return bool(tree.lattice_reach < LATTICE_MAX and (len(keys) == 0 or keys.max() + 1 < KEY_MAX))


@dataclass
class _Grids:
    """Per grid, what the pair kernels gather (device tables): box and support on the lattice
    (three Int32 columns each), owner key plus one and level plus one (UInt32)."""

    lo: list
    hi: list
    support_lo: list
    support_hi: list
    key: object
    level: object

    @classmethod
    def of(cls, m, tree):
        columns = lambda box: [device_table(m.Int32, box[:, a], np.int32)  # noqa: E731
                               for a in range(3)]
        return cls(columns(tree.lattice_grid_lo), columns(tree.lattice_grid_hi),
                   columns(tree.lattice_support_lo), columns(tree.lattice_support_hi),
                   device_table(m.UInt32, tree.owner_keys() + 1, np.uint32),
                   device_table(m.UInt32, tree.level.astype(np.int64) + 1, np.uint32))


def build(m, tree, max_depth: int):
    """``(out, (leaf, grid))``: what :meth:`KDTree._build <mi_amr.core.kdtree.KDTree._build>`
    emits for ``tree`` (the depths' node arrays, for its ``_store``) and the leaves' (leaf,
    grid) pairs (int32 NumPy arrays, by leaf and grid), the pair passes on backend ``m``."""
    G = len(tree.grid_lo)
    grids = _Grids.of(m, tree)
    f_lo = tree.lattice_root[0][None, :].astype(np.int32)
    f_hi = tree.lattice_root[1][None, :].astype(np.int32)
    pairs = (dr.zeros(m.UInt32, G), dr.arange(m.UInt32, G))     # the root and every grid
    out = kdtree.emitted()
    listed, base, n_leaves = [], 0, 0
    for depth in range(max_depth + 1):
        owner, has_partial, node_h = tree.node_summary(
            *_classify(m, grids, (f_lo, f_hi), pairs))
        axis, plane = tree.split_planes(f_lo, f_hi, owner, has_partial, node_h, np.int32)
        if depth == max_depth:
            axis[:] = kdtree.LEAF
        c_lo, c_hi, child_of = kdtree.child_boxes(f_lo, f_hi, axis, plane)
        node = _Nodes.of(m, child_of, axis, plane)
        listed.append(_leaf_pairs(m, node, child_of, n_leaves, pairs))
        n_leaves = kdtree.emit(out, depth, base, n_leaves, f_lo, f_hi, axis, plane, owner)
        base += len(f_lo)
        if len(c_lo) == 0:
            break
        pairs = _children(m, grids, node, len(c_lo), pairs)
        f_lo, f_hi = c_lo, c_hi
    return out, tuple(np.concatenate(column) for column in zip(*listed))


def _classify(m, grids, box, pairs):
    """``(best, has_partial, finest)`` per node of one depth (NumPy): the greatest owner key of
    the grids containing the node (-1: none), whether some grid's box cuts into it without
    containing it, and the finest level whose support reaches it (-1: none). ``box``: the
    nodes' lattice boxes ``(lo, hi)`` (host, ``(N, 3)``); ``pairs``: ``(node, grid)``."""
    n = len(box[0])
    best, cut, finest = (zeros_target(m, n) for _ in range(3))
    p_node, p_grid = pairs
    if dr.width(p_node):
        node_lo = [device_table(m.Int32, box[0][:, a], np.int32) for a in range(3)]
        node_hi = [device_table(m.Int32, box[1][:, a], np.int32) for a in range(3)]
        overlap, inside = m.Bool(True), m.Bool(True)
        for a in range(3):
            nl = dr.gather(m.Int32, node_lo[a], p_node)
            nh = dr.gather(m.Int32, node_hi[a], p_node)
            gl = dr.gather(m.Int32, grids.lo[a], p_grid)
            gh = dr.gather(m.Int32, grids.hi[a], p_grid)
            overlap &= dr.minimum(gh, nh) > dr.maximum(gl, nl)
            inside &= (gl <= nl) & (gh >= nh)
        key = dr.select(inside, dr.gather(m.UInt32, grids.key, p_grid), 0)
        dr.scatter_reduce(dr.ReduceOp.Max, best, key, p_node, mode=DIRECT)
        dr.scatter_reduce(dr.ReduceOp.Max, cut, m.UInt32(1), p_node, overlap & ~inside,
                          mode=DIRECT)
        dr.scatter_reduce(dr.ReduceOp.Max, finest, dr.gather(m.UInt32, grids.level, p_grid),
                          p_node, mode=DIRECT)
    dr.eval(best, cut, finest)
    best, cut, finest = (a.numpy()[:n].astype(np.int64) for a in (best, cut, finest))
    return best - 1, cut > 0, finest - 1


@dataclass
class _Nodes:
    """One depth's nodes on the device: each one's first child among the next depth's nodes
    (Int32, -1 for a leaf), split axis (UInt32) and plane (Int32)."""

    child: object
    axis: object
    plane: object

    @classmethod
    def of(cls, m, child_of, axis, plane):
        return cls(device_table(m.Int32, child_of, np.int32),
                   device_table(m.UInt32, np.minimum(axis, 2), np.uint32),
                   device_table(m.Int32, plane, np.int32))


def _leaf_pairs(m, node, child_of, n_leaves: int, pairs):
    """The pairs of one depth's leaves as (leaf, grid) int32 NumPy arrays, the leaves numbered
    from ``n_leaves`` in node order (as :func:`~mi_amr.core.kdtree.emit` numbers them)."""
    p_node, p_grid = pairs
    is_leaf = child_of < 0
    if not dr.width(p_node) or not is_leaf.any():
        return np.zeros(0, dtype=np.int32), np.zeros(0, dtype=np.int32)
    numbers = np.cumsum(is_leaf) - 1 + n_leaves
    kept = dr.compress(dr.gather(m.Int32, node.child, p_node) < 0)
    if dr.width(kept) < 2:          # (none: leaves with no data hold no pair)
        # One pair read on the host: a one-lane gather would compile into another kernel.
        at = [int(kept[0])] if dr.width(kept) else []
        return (np.array([numbers[int(p_node[i])] for i in at], dtype=np.int32),
                np.array([int(p_grid[i]) for i in at], dtype=np.int32))
    leaf_id = device_table(m.UInt32, numbers, np.uint32)
    leaf = dr.gather(m.UInt32, leaf_id, dr.gather(m.UInt32, p_node, kept))
    grid = dr.gather(m.UInt32, p_grid, kept)
    dr.eval(leaf, grid)
    # int32, not int64: a large tree holds tens of millions of pairs here (leaves and grids
    # both number far below 2^31).
    return leaf.numpy().view(np.int32), grid.numpy().view(np.int32)


def _children(m, grids, node, children: int, pairs):
    """The next depth's ``(node, grid)`` pairs (device UInt32): each pair of a split node goes
    to the side (or both) that the grid's open support reaches, placed after the pairs of the
    children before its own and in its parent's order (see the module docstring)."""
    p_node, p_grid = pairs
    P = dr.width(p_node)
    child = dr.gather(m.Int32, node.child, p_node)
    axis = dr.gather(m.UInt32, node.axis, p_node)
    plane = dr.gather(m.Int32, node.plane, p_node)
    lo = dr.select(axis == 0, dr.gather(m.Int32, grids.support_lo[0], p_grid),
                   dr.select(axis == 1, dr.gather(m.Int32, grids.support_lo[1], p_grid),
                             dr.gather(m.Int32, grids.support_lo[2], p_grid)))
    hi = dr.select(axis == 0, dr.gather(m.Int32, grids.support_hi[0], p_grid),
                   dr.select(axis == 1, dr.gather(m.Int32, grids.support_hi[1], p_grid),
                             dr.gather(m.Int32, grids.support_hi[2], p_grid)))
    split = child >= 0
    sides = (split & (lo < plane), split & (hi > plane))
    first = m.UInt32(dr.maximum(child, 0))
    count = zeros_target(m, children)
    for side, go in enumerate(sides):
        dr.scatter_reduce(dr.ReduceOp.Add, count, m.UInt32(1), first + side, go, mode=DIRECT)
    # Where each node's pairs begin: the pairs before it (sorted by node).
    begin = zeros_target(m, dr.width(node.child))
    dr.scatter_reduce(dr.ReduceOp.Add, begin, m.UInt32(1), p_node, mode=DIRECT)
    begin = dr.prefix_reduce(dr.ReduceOp.Add, begin)
    start = dr.prefix_reduce(dr.ReduceOp.Add, count)
    dr.eval(start, count, begin)
    # (Every split node has a pair whose grid contains it, which reaches both its children.)
    total = int(start.numpy()[children - 1] + count.numpy()[children - 1])
    nxt = (dr.empty(m.UInt32, total), dr.empty(m.UInt32, total))
    own = dr.gather(m.UInt32, begin, p_node)
    for side, go in enumerate(sides):
        before = dr.prefix_reduce(dr.ReduceOp.Add, m.UInt32(go))
        rank = before - dr.gather(m.UInt32, before, own)
        at = dr.gather(m.UInt32, start, first + side, go) + rank
        dr.scatter(nxt[0], first + side, at, go)
        dr.scatter(nxt[1], p_grid, at, go)
    dr.eval(nxt)
    return nxt


def zeros_target(m, n: int):
    """A new ``m.UInt32`` of at least two zeros (``n`` wanted) that kernels scatter into
    (evaluated first: a literal target would be made inside the kernel)."""
    out = dr.zeros(m.UInt32, max(n, 2))
    dr.make_opaque(out)
    return out
