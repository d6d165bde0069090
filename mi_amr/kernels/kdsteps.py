"""Steps of the kd-tree's build made on the device: what
:class:`~mi_amr.core.kdtree.KDTree` takes as ``device`` (:class:`DeviceSteps`).

* **Ropes.** :meth:`KDTree._ropes <mi_amr.core.kdtree.KDTree._ropes>` (NumPy, top-down, one
  depth at a time) is the host's way, and a kernel a depth takes the same steps here (a lane
  a node; :meth:`~mi_amr.core.kdtree.KDTree._ropes_from_root` is the slow twin): the rope of face
  ``2 * axis + side`` of node ``n`` is the deepest node holding the closed box half a finest
  cell beyond that face (the root for a face on the tree's boundary).
* **The leaves' lists.** Whether each (leaf, grid) pair of the leaves' lists is active, as
  :meth:`KDTree._active <mi_amr.core.kdtree.KDTree._active>` decides it: a lane a pair, the
  support test on the doubled lattice, and for a partly covered grid the leaf cells in its
  window counted from the host's summed-area tables; then each leaf's grids active first and
  the per-leaf summaries (:func:`leaf_lists`).
* **The build** itself: :mod:`mi_amr.kernels.kdbuild`.

Same numbers as the host (``tests/test_device_prep.py``). Coordinates are the tree's lattice
(cells of the finest level from the volume's anchor), doubled so that the face planes and the
hat supports, half a cell off the lattice, are whole numbers: int32, for lattices below
:data:`LATTICE_MAX` (else the host takes the step). Per-tree numbers are opaque kernel inputs
and the tree's arrays are gathered from, so every tree runs the kernels compiled once.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from mi_amr.core import kdtree, memory
from mi_amr.core.buffers import aligned_copy
from mi_amr.kernels import kdbuild
from mi_amr.kernels.arrays import device_array, device_table, mapped_array

LEAF = 3                  # the axis field of a leaf's node code (as in mi_amr.core.kdtree)
LATTICE_MAX = kdtree.INT32_LATTICE // 2   # |lattice coordinate|: doubled faces fit in int32


def fits(tree) -> bool:
    """Can the kernels take ``tree`` (its doubled lattice small enough for int32)?"""
    return tree.lattice_reach < LATTICE_MAX


# ---------------------------------------------------------------------- ropes

def node_ropes(m, tree) -> np.ndarray:
    """``node_ropes`` of ``tree`` (``(N, 6)`` uint32, aligned, as
    :meth:`KDTree._ropes <mi_amr.core.kdtree.KDTree._ropes>` sets it), made by a kernel a
    depth on backend ``m`` (a Dr.Jit module such as ``drjit.llvm.ad``), from the root's
    children down (:func:`_depth_ropes`). The tree's lattice must :func:`fit <fits>`."""
    N = tree.num_nodes
    nodes = _RopeNodes(m, tree)
    begin = np.searchsorted(tree.node_depth, np.arange(tree.depth + 1))
    none = dr.full(m.UInt32, NO_NODE, 2)
    dr.make_opaque(none)
    above = _Depth(0, [dr.zeros(m.UInt32, 2)] * 6, [none] * 3)    # the root: faces outside
    parts = [np.zeros((1, 6), dtype=np.uint32)]
    for first, stop in zip(begin[1:-1], begin[2:]):
        above = _depth_ropes(m, nodes, above, (int(first), int(stop)))
        parts.append(np.stack([r.numpy() for r in above.ropes], axis=1))
    return aligned_copy(np.concatenate(parts)[:N], np.uint32)


NO_NODE = 0xFFFFFFFF      # (a node number no tree reaches)


@dataclass
class _Depth:
    """One depth's nodes as :func:`_depth_ropes` leaves them: the first node's number, the
    ropes (a UInt32 array a face, in node order) and per axis ``touch``: the shallowest
    ancestor whose split plane on that axis is the node's upper face there (:data:`NO_NODE`:
    none)."""

    first: int
    ropes: list
    touch: list


class _RopeNodes:
    """What the rope kernels gather per node (device tables): codes, parents, doubled split
    planes and lattice boxes (three Int32 columns each), and the tree's doubled root box
    (opaque scalars)."""

    def __init__(self, m, tree):
        column = lambda box, a: device_table(m.Int32, 2 * box[:, a], np.int32)  # noqa: E731
        self.code = device_table(m.UInt32, tree.node_code, np.uint32)
        self.parent = device_table(m.UInt32, _parents(tree.node_code), np.uint32)
        self.split = device_table(m.Int32, 2 * tree.lattice_node_split, np.int32)
        self.lo = [column(tree.lattice_node_lo, a) for a in range(3)]
        self.hi = [column(tree.lattice_node_hi, a) for a in range(3)]
        self.root = [[dr.opaque(m.Int32, int(2 * tree.lattice_root[s][a])) for a in range(3)]
                     for s in (0, 1)]


def _parents(code) -> np.ndarray:
    """Each node's parent (the root's: 0) from the node codes."""
    parent = np.zeros(len(code), dtype=np.int64)
    inner = np.flatnonzero((code & 3) != LEAF)
    parent[code[inner] >> 2] = inner
    parent[(code[inner] >> 2) + 1] = inner
    return parent


def _depth_ropes(m, nodes, above: _Depth, span) -> _Depth:
    """The ropes of the nodes ``span`` (``(first, stop)``: one depth) from those of the depth
    ``above``, a lane a node and its six faces one after the other. A face's box lies in its
    parent's box beyond the same face, so its descent from the root passes through the
    parent's rope and starts there. The face on the parent's split plane starts at the
    sibling, which holds its box, unless the descent from the root stops above it: at the
    shallowest ancestor whose split plane on another axis is the node's upper face (the closed
    box touches that plane; a face box is half a cell off the lattice on its own axis, so no
    plane on that axis stops it), carried down as ``touch``."""
    first, stop = span
    local = dr.arange(m.UInt32, stop - first)
    node = dr.opaque(m.UInt32, first) + local
    p = dr.gather(m.UInt32, nodes.parent, node)
    c = dr.gather(m.UInt32, nodes.code, p)
    axis, lower = c & 3, node == (c >> 2)
    on_split = 2 * axis + dr.select(lower, 1, 0)    # a lower child's upper face, and back
    at = p - dr.opaque(m.UInt32, above.first)
    touch = [dr.gather(m.UInt32, t, at) for t in above.touch]
    stopped = m.UInt32(NO_NODE)
    for b in range(3):          # (ancestors number below their descendants: the min is shallowest)
        stopped = dr.select(axis == b, stopped, dr.minimum(stopped, touch[b]))
    split_start = dr.select(stopped != NO_NODE, stopped, (c >> 2) + dr.select(lower, 1, 0))
    lo = [dr.gather(m.Int32, t, node) for t in nodes.lo]
    hi = [dr.gather(m.Int32, t, node) for t in nodes.hi]
    boxes, starts = [], []
    for face in range(6):
        starts.append(dr.select(on_split == face, split_start,
                                dr.gather(m.UInt32, above.ropes[face], at)))
        boxes.append(_face_box(m, m.UInt32(face), lo, hi, nodes.root))
    out = _Depth(first, _descend(m, (nodes.code, nodes.split), boxes, starts), [])
    for b in range(3):          # a lower child's upper face on its parent's split is that split
        out.touch.append(dr.select((axis == b) & lower, p, touch[b]))
    dr.eval(out.ropes, out.touch)
    return out


def _face_box(m, face, lo, hi, root):
    """``(lo, hi, inside)``: the closed doubled-lattice box just beyond face ``face`` (0..5,
    ``2 * axis + side``) of the node box ``[lo, hi]`` (three Int32 arrays each), and whether
    it lies inside the tree's ``root`` box ``[root[0], root[1]]``."""
    axis, upper = face >> 1, (face & 1) == 1
    inside = m.Bool(True)
    lo, hi = list(lo), list(hi)
    for a in range(3):
        on = axis == a
        plane = dr.select(upper, hi[a] + 1, lo[a] - 1)
        inside &= ~on | dr.select(upper, plane <= root[1][a], plane >= root[0][a])
        lo[a] = dr.select(on, plane, lo[a])
        hi[a] = dr.select(on, plane, hi[a])
    return lo, hi, inside


def _descend(m, nodes, boxes, starts) -> list:
    """For each of ``boxes`` (closed boxes ``(lo, hi, inside)`` as :func:`_face_box` gives
    them, a list), the deepest node holding it, descending from ``starts`` (nodes holding
    them, a list); the root where not ``inside``. One loop takes them all, a step of each a
    turn. ``nodes``: the tree's node codes and doubled split planes (device tables)."""
    code, split = nodes

    def step(at, going, lo, hi):
        c = dr.gather(m.UInt32, code, at, going)
        axis = c & 3
        inner = going & (axis != LEAF)
        s = dr.gather(m.Int32, split, at, inner)
        low = dr.select(axis == 0, lo[0], dr.select(axis == 1, lo[1], lo[2]))
        high = dr.select(axis == 0, hi[0], dr.select(axis == 1, hi[1], hi[2]))
        above = inner & (low >= s)
        go = above | (inner & (high < s))
        return dr.select(go, (c >> 2) + dr.select(above, 1, 0), at), go

    def body(ats, goings):
        out = [step(at, going, box[0], box[1]) for at, going, box in zip(ats, goings, boxes)]
        return [o[0] for o in out], [o[1] for o in out]

    def any_going(ats, goings):
        out = goings[0]
        for going in goings[1:]:
            out = out | going
        return out

    state = ([dr.select(box[2], start, 0) for box, start in zip(boxes, starts)],
             [m.Bool(box[2]) for box in boxes])
    ats, _ = dr.while_loop(state, any_going, body)
    return ats


# ---------------------------------------------------------------------- active grids

def pair_active(m, tree, leaf, grid) -> np.ndarray:
    """Whether grid ``grid[i]`` is active in leaf ``leaf[i]`` (int arrays of (leaf, grid)
    pairs whose supports overlap), as :meth:`KDTree._active
    <mi_amr.core.kdtree.KDTree._active>` gives it: a boolean NumPy array. The tree's lattice
    must :func:`fit <fits>`."""
    if len(leaf) == 0:
        return np.zeros(0, dtype=bool)
    lanes = np.arange(len(leaf))
    lanes = np.repeat(lanes, 2) if len(leaf) == 1 else lanes    # (one lane: a broadcast)
    at = (device_array(m.UInt32, leaf[lanes], np.uint32),
          device_array(m.UInt32, grid[lanes], np.uint32))
    active = _active(m, _ActiveFrame(m, tree), at)
    dr.eval(active)
    return active.numpy()[:len(leaf)].astype(bool)


def _active(m, frame, at):
    """The active mask (``m.Bool``) of the (leaf, grid) pairs ``at`` (device UInt32 arrays)."""
    active = _in_support(m, frame, at)
    # Only a partly covered grid has a summed-area table: another grid's lanes must not read
    # one (its offset is clamped to 0, and its window would reach past the tables' end).
    partly = active & dr.gather(m.Bool, frame.partly, at[1], active)
    return dr.select(partly, _holds_leaf_cell(m, frame, at, partly), active)


def leaf_lists(m, tree, leaf, grid) -> dict:
    """What :meth:`KDTree._leaf_lists <mi_amr.core.kdtree.KDTree._leaf_lists>` gives for
    the (leaf, grid) pairs ``leaf``, ``grid`` (int arrays, at least two, sorted by leaf and
    grid), on backend ``m``: the pairs' active grids decided as :func:`pair_active` does, each
    leaf's grids put active first (stable: each pair's place from prefix sums over the pairs
    and the leaves), and per leaf the counts, the bitmask of its active grids' levels (levels
    below 32) and their narrowest cell side (atomic reductions)."""
    L, P = tree.num_leaves, len(leaf)
    at = (device_array(m.UInt32, leaf, np.uint32), device_array(m.UInt32, grid, np.uint32))
    active = _active(m, _ActiveFrame(m, tree), at)
    dr.eval(active)                 # (once: each kernel below reads it)
    counts = [kdbuild.zeros_target(m, L) for _ in range(2)]     # support, active
    for count, mask in zip(counts, (m.Bool(True), active)):
        dr.scatter_reduce(dr.ReduceOp.Add, count, m.UInt32(1), at[0], mask, mode=kdbuild.DIRECT)
    start, active_before = (dr.prefix_reduce(dr.ReduceOp.Add, c) for c in counts)
    seen = dr.prefix_reduce(dr.ReduceOp.Add, m.UInt32(active))    # active pairs before each
    first = dr.gather(m.UInt32, start, at[0])
    before = dr.gather(m.UInt32, active_before, at[0])
    through = before + dr.gather(m.UInt32, counts[1], at[0])     # active through the leaf
    place = dr.select(active, first + seen - before, through + dr.arange(m.UInt32, P) - seen)
    grids = dr.empty(m.UInt32, P)
    dr.scatter(grids, at[1], place)
    levels = kdbuild.zeros_target(m, L)
    bits = device_table(m.UInt32, np.left_shift(1, tree.level.astype(np.int64)), np.uint32)
    dr.scatter_reduce(dr.ReduceOp.Or, levels, dr.gather(m.UInt32, bits, at[1], active), at[0],
                      active, mode=kdbuild.DIRECT)
    min_h = dr.full(m.Float64, np.inf, max(L, 2))
    dr.make_opaque(min_h)
    spacing = device_table(m.Float64, tree.spacing.min(axis=1), np.float64)
    dr.scatter_reduce(dr.ReduceOp.Min, min_h, dr.gather(m.Float64, spacing, at[1], active),
                      at[0], active, mode=kdbuild.DIRECT)
    dr.eval(grids, counts, start, levels, min_h)
    host = lambda a: kdtree.compact_ints(a.numpy()[:L])    # noqa: E731
    return {"leaf_grids": aligned_copy(grids.numpy(), np.int32),
            "leaf_nsupport": host(counts[0]), "leaf_nactive": host(counts[1]),
            "leaf_start": host(start), "leaf_levels": host(levels),
            "leaf_min_h": min_h.numpy()[:L]}


class _ActiveFrame:
    """What :func:`pair_active` gathers from: per leaf its doubled lattice box, per grid its
    doubled support reach (its box grown by half a cell), lower lattice corner, cell width
    (finest cells), shape, whether it is partly covered and where its summed-area table of the
    leaf mask starts (:func:`mi_amr.core.kdtree.leaf_count_tables`, int32, mapped)."""

    def __init__(self, m, tree):
        vol = tree.volume
        step = tree.lattice_step
        self.leaf = [[device_table(m.Int32, 2 * box[:, a], np.int32) for a in range(3)]
                     for box in (tree.lattice_leaf_lo, tree.lattice_leaf_hi)]
        self.reach = [[device_table(m.Int32, 2 * box[:, a] + sign * step[:, a], np.int32)
                       for a in range(3)]
                      for box, sign in ((tree.lattice_grid_lo, -1), (tree.lattice_grid_hi, 1))]
        self.glo = [device_table(m.Float64, tree.lattice_grid_lo[:, a], np.float64)
                    for a in range(3)]
        self.step = [device_table(m.Float64, step[:, a], np.float64) for a in range(3)]
        self.leaf_lo = [device_table(m.Float64, tree.lattice_leaf_lo[:, a], np.float64)
                        for a in range(3)]
        self.leaf_hi = [device_table(m.Float64, tree.lattice_leaf_hi[:, a], np.float64)
                        for a in range(3)]
        self.shape = [device_table(m.Int32, tree.shape[:, a], np.int32) for a in range(3)]
        partly = vol.partly_covered()
        self.partly = device_table(m.Bool, partly, np.bool_)
        sat, offsets = kdtree.leaf_count_tables(vol, np.flatnonzero(partly))
        self.host_sat = sat         # (kept while the device maps it)
        self.sat = mapped_array(m.Int32, sat, np.int32) if len(sat) >= 2 else \
            device_table(m.Int32, sat, np.int32)
        self.offset = device_table(m.UInt32, np.maximum(offsets, 0), np.uint32)


def _in_support(m, frame, at):
    """Does the leaf's box overlap the grid's support reach (open boxes, doubled lattice)?"""
    leaf, grid = at
    out = m.Bool(True)
    for a in range(3):
        out &= dr.gather(m.Int32, frame.leaf[0][a], leaf) < \
            dr.gather(m.Int32, frame.reach[1][a], grid)
        out &= dr.gather(m.Int32, frame.leaf[1][a], leaf) > \
            dr.gather(m.Int32, frame.reach[0][a], grid)
    return out


def _holds_leaf_cell(m, frame, at, active):
    """Does the pair's cell window (the grid's cells whose hat support reaches the leaf, as
    :meth:`KDTree._windows_part <mi_amr.core.kdtree.KDTree._windows_part>` gives it) hold a
    leaf cell? Counted from the grid's summed-area table, at the lanes ``active``."""
    leaf, grid = at
    lo, hi, n = [], [], []
    for a in range(3):
        g_lo = dr.gather(m.Float64, frame.glo[a], grid, active)
        s = dr.gather(m.Float64, frame.step[a], grid, active)
        s = dr.select(active, s, 1.0)
        low = dr.floor((dr.gather(m.Float64, frame.leaf_lo[a], leaf, active) - g_lo - 1.5 * s)
                       / s)
        high = dr.ceil((dr.gather(m.Float64, frame.leaf_hi[a], leaf, active) - g_lo + 0.5 * s)
                       / s)
        n.append(dr.gather(m.Int32, frame.shape[a], grid, active))
        lo.append(dr.maximum(m.Int32(low) + 1, 0))
        hi.append(dr.minimum(m.Int32(high) - 1, n[a] - 1))
    empty = (hi[0] < lo[0]) | (hi[1] < lo[1]) | (hi[2] < lo[2])
    reads = active & ~empty
    base = dr.gather(m.UInt32, frame.offset, grid, reads)
    total = m.Int32(0)
    for corner in range(8):
        pick = [(corner >> (2 - a)) & 1 for a in range(3)]
        c = [m.UInt32(hi[a] + 1 if pick[a] else lo[a]) for a in range(3)]
        flat = base + (c[0] * m.UInt32(n[1] + 1) + c[1]) * m.UInt32(n[2] + 1) + c[2]
        value = dr.gather(m.Int32, frame.sat, flat, reads)
        total += value if (3 - sum(pick)) % 2 == 0 else -value
    return reads & (total > 0)


class DeviceSteps:
    """What :class:`~mi_amr.core.kdtree.KDTree` takes as ``device``: the steps above on
    backend ``m`` (a Dr.Jit module such as ``drjit.llvm.ad``), each None for a tree that does
    not :func:`fit <fits>` (the tree then takes the step on the host)."""

    def __init__(self, m):
        self.m = m

    def ropes(self, tree):
        """:func:`node_ropes`, or None."""
        return node_ropes(self.m, tree) if fits(tree) else None

    def leaf_lists(self, tree, leaf, grid):
        """:func:`leaf_lists`, or None (also for fewer than two pairs, or levels from 32)."""
        takes = fits(tree) and len(leaf) >= 2 and tree.level.max(initial=0) < 32
        return leaf_lists(self.m, tree, leaf, grid) if takes else None

    def build(self, tree, max_depth: int):
        """:func:`mi_amr.kernels.kdbuild.build`, or None."""
        if not kdbuild.fits(tree):
            return None
        built = kdbuild.build(self.m, tree, max_depth)
        if tree.volume.num_cells >= memory.RELEASE_CELLS:
            # The depths' pair arrays stay in Dr.Jit's cache once freed, where the host arrays
            # that follow (nodes, leaf lists, ropes) cannot reuse them: a large tree's peak
            # memory would hold both.
            dr.flush_malloc_cache()
        return built
