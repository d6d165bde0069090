"""A kd-tree over the grids of an AMR volume, built on the host and flattened for Dr.Jit kernels.

Every grid has a **support**: its world box grown by one cell of its level on every side (an open
box), the region where its cells can carry weight in the basis reconstruction. The tree partitions the
support of the whole volume into leaf boxes such that

* each leaf lies entirely inside or entirely outside every grid box, so one grid, its **owner**
  (the finest grid containing the leaf, as in yt's AMR kd-tree), covers the whole leaf, or none
  does (owner ``-1``: a region with no data);
* each leaf is at most ``leaf_cells`` cells of the finest level whose support reaches it on every
  axis, so the per-leaf value ranges used to skip empty space stay tight;
* each leaf lists every grid whose support overlaps it, the **active** ones first: those
  with at least one leaf cell whose hat function is non-zero somewhere in the leaf. The basis
  reconstruction needs only the active grids.

The build is breadth-first and vectorised over all nodes of a depth. The (node, grid) pairs
of a depth stay in order of node and grid, so the leaves' lists come out of the build in
order: no second descent and no sort.
Flattened layout (what kernels gather from): node ``n`` has ``node_split[n]`` and
``node_code[n] = child << 2 | axis`` (axis 3 marks a leaf and ``child`` is then the leaf index;
otherwise the children are nodes ``child`` (below the split) and ``child + 1`` (at or above it)).
"""

from __future__ import annotations

import numpy as np

from mi_amr import params
from mi_amr.core import parallel
from mi_amr.core.batches import flat_field
from mi_amr.core.buffers import aligned_copy, aligned_empty, aligned_full
from mi_amr.core.boxes import contains_points
from mi_amr.core.points import (as_points, finest_of,  # noqa: F401  (twins: tests)
                                finest_grid_bruteforce, support_grids_bruteforce)
from mi_amr.errors import AMRError

LEAF = 3
# |lattice coordinate| below which boxes (and sums of two coordinates) fit in int32; doubled
# coordinates need half of it.
INT32_LATTICE = 1 << 30
# Rows per block of the long per-pair computations: temporaries of a block stay below the
# allocator's mmap threshold, so they reuse memory instead of page-faulting fresh memory
# (which cost 5x the arithmetic on 2.8M pairs).
CHUNK = 1 << 16
# Boxes descended together by KDTree.overlapping_leaves: their (box, node) pairs stay a few
# CHUNKs long however many boxes there are.
BOX_BLOCK = 1 << 13
ROPE_BLOCK = 1 << 13   # nodes whose 6 faces descend together (threads take a block each)


def _world_array(name: str, doc: str) -> property:
    """A read-only :class:`KDTree` property: its lattice array ``name`` in world coordinates,
    computed on each use."""
    return property(lambda tree: tree._world(getattr(tree, name)), doc=doc)


class KDTree:
    """kd-tree over the grid supports of ``volume`` (see the module docstring).

    ``leaf_cells`` bounds the leaf size in cells of the finest level present at the leaf.
    Positions given and returned are world space. The ``lattice_*`` arrays are the same boxes
    on the build's exact lattice (whole numbers of finest-level cells from the volume's
    anchor): ``lattice_root`` (low and high corner), ``lattice_grid_lo/hi`` and
    ``lattice_support_lo/hi`` and ``lattice_step`` (cell widths) per grid, ``(G, 3)``
    (float64), ``lattice_node_lo/hi/split`` per node and ``lattice_leaf_lo/hi`` per leaf
    (int32 where they fit, else int64); the per-node and per-leaf integers are int32 where
    they fit too (:func:`compact_ints`). The device
    kernels (:mod:`mi_amr.kernels.kdbuild`, :mod:`mi_amr.kernels.kdsteps`) read them.
    ``chunk`` ((node or leaf, grid) pairs, or boxes) and
    ``box_block`` (boxes) are the blocks the build and the queries work through at a time
    (:data:`CHUNK`, :data:`BOX_BLOCK`): they bound the temporaries, not the result.
    """

    # What a built tree holds besides its volume: :meth:`arrays` gives them, and
    # :meth:`from_arrays` makes the tree from them again without building it.
    STATE = ("_level_h", "depth", "lattice_grid_hi", "lattice_grid_lo", "lattice_leaf_hi",
             "lattice_leaf_lo", "lattice_node_hi", "lattice_node_lo", "lattice_node_split",
             "lattice_root", "lattice_step", "lattice_support_hi", "lattice_support_lo",
             "grid_hi", "grid_lo", "h_fine", "hi", "leaf_cells", "leaf_grids",
             "leaf_levels", "leaf_min_h", "leaf_nactive", "leaf_node",
             "leaf_nsupport", "leaf_owner", "leaf_start", "level", "lo", "node_code",
             "node_depth", "node_ropes", "shape", "spacing", "support_hi", "support_lo")

    def __init__(self, volume, *, leaf_cells: int = params.default("leaf_cells"),
                 max_depth: int = 80, arrays: dict | None = None, chunk: int = CHUNK,
                 box_block: int = BOX_BLOCK, device=None):
        """Build the tree of ``volume``; or, given ``arrays`` (:meth:`arrays` of a tree of this
        volume), take them as they are (:meth:`from_arrays`). ``device``: what takes steps of
        the build on a device (:class:`mi_amr.kernels.kdsteps.DeviceSteps`): its
        ``build(tree, max_depth)`` does what :meth:`_build` does, ``ropes(tree)`` gives
        :attr:`node_ropes` (an ``(N, 6)`` uint32 array) and ``leaf_lists(tree, leaf, grid)``
        what :meth:`_leaf_lists` gives, each None where it cannot; None: the host takes every
        step."""
        self.volume = volume
        self.chunk, self.box_block = int(chunk), int(box_block)
        if arrays is not None:
            missing = sorted(set(self.STATE) - set(arrays))
            if missing:
                raise AMRError(f"KDTree: saved tree state lacks {missing}")
            for name in self.STATE:
                setattr(self, name, arrays[name])
            return
        if leaf_cells < 2:
            raise AMRError(f"KDTree: leaf_cells must be >= 2, got {leaf_cells}")
        self.leaf_cells = int(leaf_cells)
        self.grid_lo, self.grid_hi = volume.grid_boxes()
        self.spacing = volume.spacings()
        self.level = volume.levels
        self.shape = volume.shapes()
        self.support_lo = self.grid_lo - self.spacing
        self.support_hi = self.grid_hi + self.spacing
        # The build works in exact integer coordinates: cells of the finest level from the
        # anchor. Every grid face and support face is on that lattice.
        self.h_fine = volume.level_spacing(volume.num_levels - 1)
        lattice = lambda x: np.round((x - volume.anchor) / self.h_fine)  # noqa: E731
        self.lattice_grid_lo, self.lattice_grid_hi = lattice(self.grid_lo), lattice(self.grid_hi)
        step = np.round(self.spacing / self.h_fine)
        self.lattice_step = step
        # Cell width of each level in finest cells, per axis.
        self._level_h = np.array([np.round(volume.level_spacing(l) / self.h_fine)
                                  for l in range(volume.num_levels)])
        self.lattice_support_lo = self.lattice_grid_lo - step
        self.lattice_support_hi = self.lattice_grid_hi + step
        # The root's middle is the lower corner of the grids: its halves, and every node below,
        # then split on the lattice of power-of-two blocks from that corner, where grid faces
        # lie, and not through the middle of grids. The low half holds only support margins.
        corner = self.lattice_grid_lo.min(axis=0)
        half = 2.0 ** np.ceil(np.log2(np.maximum.reduce([
            self.lattice_support_hi.max(axis=0) - corner,
            corner - self.lattice_support_lo.min(axis=0), np.ones(3)])))
        self.lattice_root = (corner - half, corner + half)
        self.lo, self.hi = self._world(self.lattice_root[0]), self._world(self.lattice_root[1])
        listed = self._build(max_depth, device)
        # One after the other, in this thread: Dr.Jit work from two threads at once is a
        # hazard (a test run crashed once with the ropes in a thread of their own) for no gain.
        self._order_active(*listed, device=device)
        self._make_ropes(device)

    @classmethod
    def from_arrays(cls, volume, arrays: dict) -> "KDTree":
        """The tree of ``volume`` whose state is ``arrays`` (what :meth:`arrays` gave, e.g.
        read back from a snapshot), not built again."""
        return cls(volume, arrays=arrays)

    def arrays(self) -> dict:
        """The tree's state (:data:`STATE`: NumPy arrays, tuples and numbers; not the volume)."""
        return {name: getattr(self, name) for name in self.STATE}

    def _world(self, u, axis=None):
        """World coordinates of lattice coordinates ``u`` (all axes, or one ``axis``)."""
        if axis is None:
            out = u * self.h_fine
            out += self.volume.anchor           # (the same sum, with one temporary fewer)
            return out
        return self.volume.anchor[axis] + u * self.h_fine[axis]

    # ------------------------------------------------------------------ build
    def _build(self, max_depth: int, device=None):
        """Build the tree breadth first, one depth at a time, on the integer lattice of the
        finest level (all boxes are whole numbers of finest cells from the anchor). Returns
        the (leaf, grid) pairs of the leaves' lists (every grid whose open support overlaps
        the leaf), sorted by leaf and then grid: the pairs of each depth stay sorted by node
        and grid (:func:`_children`), and leaves are numbered in node order. ``device``: see
        the constructor (its ``build(tree, max_depth)`` makes the same nodes and pairs, the
        pairs' passes on the device, or declines with None)."""
        made = device.build(self, max_depth) if device is not None else None
        if made is not None:
            out, listed = made
            self._store(out)
            return listed
        G = len(self.grid_lo)
        # Lattice coordinates are whole numbers: int32 (when they fit) halves the memory traffic
        # of the pair tests, which dominate the build.
        ity = self.lattice_int
        lattice = tuple(box.astype(ity) for box in (
            self.lattice_grid_lo, self.lattice_grid_hi,
            self.lattice_support_lo, self.lattice_support_hi))
        f_lo = self.lattice_root[0][None, :].astype(ity)
        f_hi = self.lattice_root[1][None, :].astype(ity)
        # (node, grid) pairs whose open support overlaps the node.
        p_node, p_grid = np.zeros(G, dtype=np.int64), np.arange(G, dtype=np.int64)
        out = emitted()
        listed = []
        # Each depth's pairs go into one of two buffers, in turn: reused, not new memory.
        buffers = (_Buffer(), _Buffer())
        base, n_leaves = 0, 0
        for depth in range(max_depth + 1):
            owner, has_partial, node_h = self._classify(f_lo, f_hi, p_node, p_grid, lattice)
            axis, plane = self.split_planes(f_lo, f_hi, owner, has_partial, node_h, ity)
            if depth == max_depth:
                axis[:] = LEAF
            listed.append(_leaf_pairs(axis, n_leaves, p_node, p_grid))
            n_leaves = emit(out, depth, base, n_leaves, f_lo, f_hi, axis, plane, owner)
            base += len(f_lo)
            if np.all(axis == LEAF):
                break
            f_lo, f_hi, p_node, p_grid = _children(f_lo, f_hi, axis, plane, p_node, p_grid,
                                                   lattice, chunk=self.chunk,
                                                   into=buffers[depth % 2])
        self._store(out)
        return tuple(np.concatenate(column) for column in zip(*listed))

    def _classify(self, f_lo, f_hi, p_node, p_grid, lattice):
        """For the nodes ``[f_lo, f_hi]`` of one depth and their (node, grid) pairs: the owner
        of each node (the finest grid containing it, lowest index among equals, -1: none),
        whether a grid face cuts the node, and the finest cell width (in finest cells) of the
        grids whose support reaches into it.

        A pair whose grid box misses the node (support only) and that is no finer than the
        owner changes none of these: the owner contains the node, so it bounds the finest
        level from below, and such a grid cuts no face through it."""
        n = len(f_lo)
        overlap, contains = _pair_boxes(f_lo, f_hi, p_node, p_grid, lattice, chunk=self.chunk)
        best = np.full(n, -1, dtype=np.int64)
        has_partial = np.zeros(n, dtype=bool)
        finest = np.full(n, -1, dtype=np.int64)
        # The pairs are sorted by node: reduce over each node's run of them.
        first = run_starts(p_node)
        if len(first):
            held = np.take(p_node, first)
            key = np.take(self.owner_keys(), p_grid)
            key[~contains] = -1
            best[held] = np.maximum.reduceat(key, first)
            overlap &= ~contains
            has_partial[held] = np.logical_or.reduceat(overlap, first)
            finest[held] = np.maximum.reduceat(np.take(self.level.astype(np.int64), p_grid),
                                               first)
        return self.node_summary(best, has_partial, finest)

    def owner_keys(self) -> np.ndarray:
        """Per grid, its key as a node's owner (int64): the greatest key among the grids
        containing a node is its owner's, finer grids first, then the lowest index."""
        G = len(self.grid_lo)
        return self.level.astype(np.int64) * G + (G - 1 - np.arange(G))

    def node_summary(self, best, has_partial, finest):
        """``(owner, has_partial, node_h)`` of nodes (see :meth:`_classify`) from the greatest
        :meth:`owner_keys` of the grids containing each (-1: none), whether a grid face cuts it,
        and the finest level whose support reaches it (-1: none)."""
        G = len(self.grid_lo)
        owner = np.where(best >= 0, G - 1 - best % G, -1)
        level_h = self._level_h
        node_h = np.where(finest[:, None] >= 0, level_h[np.maximum(finest, 0)], np.inf)
        return owner, has_partial, node_h

    def split_planes(self, f_lo, f_hi, owner, has_partial, node_h, ity):
        """Split nodes cut by a grid face, and clean nodes with data that are too large, in the
        middle of their longest axis (in cells of the volume's finest level). Nodes are then
        power-of-two boxes of that lattice, as in an octree, so neighbouring subtrees are cut
        alike and a rope leads close to the neighbouring leaf. Returns ``(axis, plane)``
        (``axis`` :data:`LEAF` for leaves)."""
        n = len(f_lo)
        axis = np.full(n, LEAF, dtype=np.int64)
        plane = np.zeros(n, dtype=ity)
        ext = f_hi - f_lo
        with np.errstate(invalid="ignore", divide="ignore"):
            cells = np.where(np.isfinite(node_h), ext / node_h, 0.0)
        big = (~has_partial) & (owner >= 0) & np.any(cells > self.leaf_cells, axis=1)
        cut = np.flatnonzero(has_partial | big)
        ax = np.argmax(ext[cut], axis=1)
        axis[cut] = ax
        plane[cut] = (f_lo[cut, ax] + f_hi[cut, ax]) // 2   # boxes are 2^k cells wide
        return axis, plane

    def _store(self, out) -> None:
        """The emitted depths as the tree's arrays, in lattice coordinates (the world boxes
        and splits are computed from them when asked for: :attr:`node_lo` and the others)."""
        # Node and leaf boxes are whole numbers of finest cells: kept in the build's integer
        # type (int32 when they fit), half the memory of float64. A use that offsets them by a
        # half cell converts them first (face_boxes, the start table).
        ity = self.lattice_int
        self.node_code = compact_ints(np.concatenate(out["code"]))
        self.lattice_node_split = np.concatenate(out["split"], dtype=ity)
        self.lattice_node_lo = np.concatenate(out["lo"], dtype=ity)
        self.lattice_node_hi = np.concatenate(out["hi"], dtype=ity)
        self.node_depth = compact_ints(np.concatenate(out["depth"]))
        self.depth = len(out["code"])
        self.lattice_leaf_lo = np.concatenate(out["leaf_lo"], dtype=ity)
        self.lattice_leaf_hi = np.concatenate(out["leaf_hi"], dtype=ity)
        self.leaf_owner = compact_ints(np.concatenate(out["leaf_owner"]))

    # World boxes and splits: computed from the lattice ones on each use, not stored (a copy
    # of each would hold a third of the tree's memory). Each is float64 in world units.
    node_lo = _world_array("lattice_node_lo", "Lower corner of each node's box, ``(N, 3)``.")
    node_hi = _world_array("lattice_node_hi", "Upper corner of each node's box, ``(N, 3)``.")
    leaf_lo = _world_array("lattice_leaf_lo", "Lower corner of each leaf's box, ``(L, 3)``.")
    leaf_hi = _world_array("lattice_leaf_hi", "Upper corner of each leaf's box, ``(L, 3)``.")

    def node_boxes(self, nodes):
        """``(lo, hi)`` (world) of the boxes of ``nodes`` alone."""
        return self._world(self.lattice_node_lo[nodes]), self._world(self.lattice_node_hi[nodes])

    def leaf_boxes(self, leaves):
        """``(lo, hi)`` (world) of the boxes of ``leaves`` alone."""
        return self._world(self.lattice_leaf_lo[leaves]), self._world(self.lattice_leaf_hi[leaves])

    @property
    def node_split(self) -> np.ndarray:
        """Split plane of each node on its axis, ``(N,)`` (a leaf has none: its entry, the
        anchor's z, is never read)."""
        return self.split_of(np.arange(self.num_nodes))

    def split_of(self, nodes) -> np.ndarray:
        """:attr:`node_split` of ``nodes`` alone."""
        axis = np.minimum(np.take(self.node_code, nodes) & 3, 2)
        return self._world(np.take(self.lattice_node_split, nodes), axis)

    def _order_active(self, pl, pg, device=None) -> None:
        """Sort each leaf's grid list with the active grids first, and summarise them.
        ``(pl, pg)``: the (leaf, grid) pairs of the lists, sorted by leaf and then grid (what
        :meth:`_build` returns; :meth:`_listed_by_descent` is the slow twin); ``device``: see
        the constructor."""
        made = device.leaf_lists(self, pl, pg) if device is not None else None
        for name, value in (made or self._leaf_lists(pl, pg)).items():
            setattr(self, name, value)

    def _leaf_lists(self, pl, pg) -> dict:
        """What :meth:`_order_active` sets, by name: ``leaf_grids`` (int32, aligned),
        ``leaf_nsupport``, ``leaf_nactive``, ``leaf_start``, ``leaf_levels``
        (:func:`compact_ints`) and ``leaf_min_h`` (float64, ``(L,)``: the narrowest cell side of
        the leaf's active grids, world units; inf for none), on the host."""
        L, P = self.num_leaves, len(pl)
        active = self._active(pl, pg)
        # Active first within each leaf, each part in grid order: a stable partition, each
        # pair's place counted from the leaf's start (no sort).
        nsupport = np.bincount(pl, minlength=L).astype(np.int64)
        nactive = np.bincount(pl[active], minlength=L).astype(np.int64)
        start = np.cumsum(nsupport) - nsupport
        active_before = np.cumsum(nactive) - nactive
        seen = np.cumsum(active) - active       # active pairs before each pair
        place = np.where(active, np.take(start, pl) + seen - np.take(active_before, pl),
                         np.take(nactive + active_before, pl) + np.arange(P) - seen)
        # The active grids, leaf after leaf, in the order they will have.
        ga = pg[active]
        # Only pairs behind an inactive one in their leaf move: permute those in place (the
        # moved pairs' places are the moved pairs' positions).
        moved = np.flatnonzero(place != np.arange(P))
        pg = aligned_copy(pg, np.int32)         # (aligned: the device maps it)
        pg[place[moved]] = pg[moved]
        # The active pairs are contiguous per leaf: reduce over those runs.
        has = nactive > 0
        runs = (np.cumsum(nactive) - nactive)[has]
        levels = np.zeros(L, dtype=np.int64)
        min_h = np.full(L, np.inf)
        if len(runs):
            bits = np.left_shift(1, self.level.astype(np.int64))
            levels[has] = _reduce_runs(np.bitwise_or, bits, ga, runs, self.chunk)
            min_h[has] = _reduce_runs(np.minimum, self.spacing.min(axis=1), ga, runs,
                                      self.chunk)
        return {"leaf_grids": pg, "leaf_nsupport": compact_ints(nsupport),
                "leaf_nactive": compact_ints(nactive), "leaf_start": compact_ints(start),
                "leaf_levels": compact_ints(levels), "leaf_min_h": min_h}

    def _listed_by_descent(self):
        """Slow twin of the pairs :meth:`_build` returns: every leaf overlapping each grid's
        open support, found by descending the built tree with the supports, then sorted by
        leaf and grid."""
        pg, pl = self.overlapping_leaves(self.support_lo, self.support_hi)
        order = np.lexsort((pg, pl))
        return pl[order], pg[order]

    def _active(self, leaf, grid):
        """For (leaf, grid) pairs with overlapping supports: whether the grid is active in the
        leaf (its cell window, :meth:`_windows`, is not empty and holds at least one leaf
        cell), :attr:`chunk` pairs at a time.

        The window is not empty exactly when the leaf overlaps the union of the cells' open hat
        supports, the grid's box grown by half a cell (the window's integer bounds, worked
        out): in doubled lattice coordinates, whole numbers compared without a division. Only
        the pairs of partly covered grids need the window itself, to count its leaf cells."""
        P = len(leaf)
        active = np.empty(P, dtype=bool)
        # Grids with covered cells: is there a leaf cell in the window? (Count it from a
        # summed-area table of the leaf mask.)
        partly = self.volume.partly_covered()
        tables = leaf_count_tables(self.volume, np.flatnonzero(partly)) \
            if partly[grid].any() else None
        # Per axis, contiguous int32 columns of doubled lattice coordinates, where they fit.
        ity = np.int32 if 2 * self.lattice_reach < INT32_LATTICE else np.int64
        column = lambda x, a: np.ascontiguousarray(x[:, a], dtype=ity)  # noqa: E731
        reach = [(column(2.0 * self.lattice_grid_lo - self.lattice_step, a),
                  column(2.0 * self.lattice_grid_hi + self.lattice_step, a)) for a in range(3)]
        leaf2 = [(column(2.0 * self.lattice_leaf_lo, a), column(2.0 * self.lattice_leaf_hi, a))
                 for a in range(3)]
        chunk = self.chunk

        def one_part(a):
            part = slice(a, a + chunk)
            lf, g = leaf[part], grid[part]
            act = np.ones(len(g), dtype=bool)
            for (l_lo, l_hi), (r_lo, r_hi) in zip(leaf2, reach):
                act &= np.take(l_lo, lf) < np.take(r_hi, g)
                act &= np.take(l_hi, lf) > np.take(r_lo, g)
            sel = np.flatnonzero(act & partly[g])
            if len(sel):
                sat, offsets = tables
                gs = g[sel]
                w_lo, w_hi = self._windows_part(lf[sel], gs)
                act[sel] = _box_sum(sat, offsets[gs], self.shape[gs], w_lo, w_hi) > 0
            active[part] = act

        parallel.for_each(one_part, range(0, P, chunk))      # each writes its own rows
        return active

    def _ropes(self) -> None:
        """``node_ropes[n, 2 * axis + side]``: the deepest node holding everything just beyond
        face ``side`` (0 low, 1 high) of node ``n``'s box along ``axis`` (Havran's ropes), so a
        ray leaving a node restarts its descent there instead of at the root. Faces on the
        tree's boundary get the root. ``leaf_node[l]`` is the node of leaf ``l``.

        Built top-down, one depth at a time: a child's face box off its parent's split axis
        lies inside the same face box of its parent, so its descent from the root passes
        through the parent's rope and starts there. The face on the split plane starts at the
        sibling, which holds its box, unless the descent from the root stops above: at the
        shallowest ancestor whose split plane on another axis is the node's upper face there
        (the closed face box touches that plane, so neither side holds it; a face box is half
        a cell off the lattice on its own axis, so no split on that axis stops it). ``touch``
        carries those ancestors down, per axis. :meth:`_ropes_from_root` is the slow twin."""
        N = self.num_nodes
        code = self.node_code
        inner = np.flatnonzero((code & 3) != LEAF)
        parent = np.full(N, -1, dtype=np.int64)
        parent[code[inner] >> 2] = inner
        parent[(code[inner] >> 2) + 1] = inner
        # uint32 and aligned, as the device reads them: its array maps these, no copy.
        ropes = aligned_full(N * 6, 0, np.uint32).reshape(N, 6)
        # touch[n, b]: the shallowest ancestor of n splitting axis b on n's upper face (-1: none).
        touch = np.full((N, 3), -1, dtype=np.int64)
        for depth in range(1, self.depth):
            nodes = np.flatnonzero(self.node_depth == depth)
            if len(nodes) == 0:
                continue
            p = parent[nodes]
            start = ropes[p]
            axis = code[p] & 3
            right = nodes == (code[p] >> 2) + 1
            rows = np.arange(len(nodes))
            # A lower child's upper face on the split axis is its parent's split; no ancestor
            # splits that axis there (the parent straddles the plane).
            t = touch[p]
            t[rows[~right], axis[~right]] = p[~right]
            touch[nodes] = t
            t[rows, axis] = -1          # (the split face's own axis never stops it)
            t_depth = np.where(t >= 0, np.take(self.node_depth, np.maximum(t, 0)), depth)
            stop = np.take_along_axis(t, np.argmin(t_depth, axis=1)[:, None], axis=1)[:, 0]
            sibling = (code[p] >> 2) + ~right
            start[rows, 2 * axis + ~right] = np.where(stop >= 0, stop, sibling)
            parts = range(0, len(nodes), ROPE_BLOCK)     # side by side, in order
            ropes[nodes] = np.concatenate(list(parallel.map_ordered(
                lambda a: self._descend_faces(nodes[a:a + ROPE_BLOCK],
                                              start[a:a + ROPE_BLOCK].ravel()), parts))
                ).reshape(-1, 6)
        self._set_ropes(ropes)

    def _make_ropes(self, device) -> None:
        """Set :attr:`node_ropes` by ``device`` (see the constructor), else by :meth:`_ropes`."""
        made = device.ropes(self) if device is not None else None
        if made is None:
            self._ropes()
        else:
            self._set_ropes(made)

    def _ropes_from_root(self) -> np.ndarray:
        """Slow twin of :meth:`_ropes`: every face's descent starts at the root."""
        nodes = np.arange(self.num_nodes)
        return self._descend_faces(nodes, np.zeros(6 * len(nodes), dtype=np.int64)).reshape(-1, 6)

    def face_boxes(self, nodes):
        """Closed lattice boxes half a finest cell beyond each face of ``nodes`` (6 rows per
        node, face ``2 * axis + side``), and whether each lies outside the tree's box."""
        node_lo = self.lattice_node_lo[nodes].astype(np.float64)   # (half cells below)
        node_hi = self.lattice_node_hi[nodes].astype(np.float64)
        lo = np.repeat(node_lo[:, None, :], 6, axis=1)
        hi = np.repeat(node_hi[:, None, :], 6, axis=1)
        outside = np.empty((len(nodes), 6), dtype=bool)
        for face in range(6):
            axis, side = divmod(face, 2)
            # Off the face's axis the box is the node's, inside the tree's box.
            if side:
                plane = node_hi[:, axis] + 0.5
                outside[:, face] = plane > self.lattice_root[1][axis]
            else:
                plane = node_lo[:, axis] - 0.5
                outside[:, face] = plane < self.lattice_root[0][axis]
            lo[:, face, axis] = plane
            hi[:, face, axis] = plane
        return lo.reshape(-1, 3), hi.reshape(-1, 3), outside.reshape(-1)

    def _descend_faces(self, nodes, start) -> np.ndarray:
        """For each face of ``nodes`` (6 per node), the deepest node holding its face box,
        descending from ``start`` (a node holding it); the root for faces outside the tree."""
        lo, hi, outside = self.face_boxes(nodes)
        inside = ~outside
        node = np.zeros(len(lo), dtype=np.int64)
        node[inside] = self.descend_boxes(lo[inside], hi[inside],
                                          np.asarray(start, dtype=np.int64)[inside])
        return node

    def descend_boxes(self, lo, hi, start=None, stop=None) -> np.ndarray:
        """For each closed lattice box ``[lo, hi]`` (rows), the deepest node holding it all,
        descending from ``start`` (nodes holding them; the root by default), or the first
        node met where ``stop`` (a bool per node) is True."""
        lo_flat, hi_flat = np.asarray(lo).reshape(-1), np.asarray(hi).reshape(-1)
        node = np.zeros(len(lo), dtype=np.int64) if start is None else start.copy()
        todo = np.arange(len(lo))
        at = node.copy()
        while len(todo):
            code = np.take(self.node_code, at)
            ax = code & 3
            split = np.take(self.lattice_node_split, at)
            inner = ax != LEAF
            if stop is not None:
                inner &= ~np.take(stop, at)
            pos = todo * 3 + np.where(inner, ax, 0)
            above = inner & (np.take(lo_flat, pos) >= split)
            go = above | (inner & (np.take(hi_flat, pos) < split))
            at = (code[go] >> 2) + above[go]
            todo = todo[go]
            node[todo] = at
        return node

    def _set_ropes(self, ropes) -> None:
        self.node_ropes = ropes
        is_leaf = (self.node_code & 3) == LEAF
        self.leaf_node = np.empty(self.num_leaves,
                                  dtype=np.int32 if self.num_nodes < 2 ** 31 else np.int64)
        self.leaf_node[self.node_code[is_leaf] >> 2] = np.flatnonzero(is_leaf)

    def node_ranges(self, leaf_lo, leaf_hi):
        """Value ranges of every node (each ``(N,)``): the union of the ranges ``leaf_lo`` /
        ``leaf_hi`` of the leaves below it."""
        lo = np.full(self.num_nodes, np.inf)
        hi = np.full(self.num_nodes, -np.inf)
        lo[self.leaf_node] = leaf_lo
        hi[self.leaf_node] = leaf_hi
        inner = (self.node_code & 3) != LEAF
        for depth in range(self.depth - 1, -1, -1):
            n = np.flatnonzero(inner & (self.node_depth == depth))
            c = self.node_code[n] >> 2
            lo[n] = np.minimum(lo[c], lo[c + 1])
            hi[n] = np.maximum(hi[c], hi[c + 1])
        return lo, hi

    def _windows(self, leaf, grid):
        """Inclusive cell index ranges ``(lo, hi)`` (each ``(P, 3)``) of the cells of ``grid``
        whose hat support (centre +- one cell, open) overlaps the box of ``leaf``; rows
        where ``lo > hi`` on some axis are empty.

        Exact, in integers: with ``u`` a leaf face in the grid's cells from its lower corner
        (a lattice distance ``D`` over the grid's cell width ``s``, both in finest cells), cell
        ``i`` (centre ``i + 1/2``) reaches past the low face when ``i > u - 3/2``, before the
        high face when ``i < u + 1/2``: ``lo = floor((D - 3 s / 2) / s) + 1``, ``hi =
        ceil((D + s / 2) / s) - 1``. int32, :attr:`chunk` pairs at a time."""
        lo = np.empty((len(leaf), 3), dtype=np.int32)
        hi = np.empty((len(leaf), 3), dtype=np.int32)
        chunk = self.chunk

        def one_part(a):
            part = slice(a, a + chunk)
            lo[part], hi[part] = self._windows_part(leaf[part], grid[part])

        parallel.for_each(one_part, range(0, len(leaf), chunk))   # each writes its own rows
        return lo, hi

    def _windows_part(self, leaf, grid):
        # (In float64: a quotient of whole numbers below 2^26 is rounded exactly, and never
        # across a whole number, so floor and ceil of it are exact; integer division is slow.)
        g_lo = np.take(self.lattice_grid_lo, grid, axis=0)
        s = np.take(self.lattice_step, grid, axis=0)
        lo = np.floor((np.take(self.lattice_leaf_lo, leaf, axis=0) - g_lo - 1.5 * s) / s)
        hi = np.ceil((np.take(self.lattice_leaf_hi, leaf, axis=0) - g_lo + 0.5 * s) / s)
        return (np.maximum(lo.astype(np.int64) + 1, 0),
                np.minimum(hi.astype(np.int64) - 1, np.take(self.shape, grid, axis=0) - 1))

    def _windows_world(self, leaf, grid):
        """Slow twin of :meth:`_windows` in world coordinates (float64; may differ where a
        support ends exactly on a leaf face and rounding falls the other way)."""
        o = np.take(self.grid_lo, grid, axis=0)
        h = np.take(self.spacing, grid, axis=0)
        lo = np.floor((np.take(self.leaf_lo, leaf, axis=0) - o) / h - 1.5).astype(np.int64) + 1
        hi = np.ceil((np.take(self.leaf_hi, leaf, axis=0) - o) / h + 0.5).astype(np.int64) - 1
        return np.maximum(lo, 0), np.minimum(hi, np.take(self.shape, grid, axis=0) - 1)

    def _listed_pairs(self, count):
        """The first ``count[l]`` listed grids of each owned leaf ``l``: ``(leaf, grid)``, leaf
        after leaf (int32 where the pairs' positions fit: 10^8 cells list about 10^7)."""
        taken = np.where(self.leaf_owner >= 0, np.minimum(count, self.leaf_nsupport), 0)
        fits = max(len(self.leaf_grids), self.num_leaves) < np.iinfo(np.int32).max
        index = np.int32 if fits else np.int64
        leaf = np.repeat(np.arange(self.num_leaves, dtype=index), taken)
        # each taken pair's place in leaf_grids: its leaf's start plus its rank in the leaf
        at = np.repeat((self.leaf_start - (np.cumsum(taken) - taken)).astype(index), taken)
        at += np.arange(len(at), dtype=index)
        return leaf, np.take(self.leaf_grids, at)

    # ------------------------------------------------------------------ queries
    def check(self, field: str | None = None, **kw) -> dict:
        """Check the tree's invariants (:mod:`mi_amr.core.kdcheck`): the leaves tile the root,
        owners are the finest covering grids, ropes point to the neighbouring nodes, and (with
        ``field``) the value ranges bound the data. Returns what was checked; raises
        ``AssertionError`` at the first broken invariant."""
        from mi_amr.core.kdcheck import check

        return check(self, field, **kw)

    @property
    def num_leaves(self) -> int:
        return len(self.lattice_leaf_lo)

    @property
    def lattice_reach(self) -> float:
        """The largest |lattice coordinate| of the tree (its root's corners bound every box)."""
        return float(np.abs(np.concatenate(self.lattice_root)).max())

    @property
    def lattice_int(self):
        """The integer type of the tree's lattice boxes: int32 where they fit, else int64."""
        return np.int32 if self.lattice_reach < INT32_LATTICE else np.int64

    @property
    def num_nodes(self) -> int:
        return len(self.node_code)

    def locate(self, points) -> np.ndarray:
        """Leaf index of each point ``(N, 3)`` (world). A point on a split plane goes to the
        upper side. Points outside the tree's box still land in some leaf."""
        points = np.asarray(points, dtype=np.float64)
        node = np.zeros(len(points), dtype=np.int64)
        todo = np.arange(len(points))
        for _ in range(self.depth + 1):
            code = self.node_code[node[todo]]
            axis = code & 3
            inner = axis != LEAF
            todo = todo[inner]
            if len(todo) == 0:
                break
            code, axis = code[inner], axis[inner]
            n = node[todo]
            up = points[todo, axis] >= self.split_of(n)
            node[todo] = (code >> 2) + up
        return self.node_code[node] >> 2

    def overlapping_leaves(self, lo, hi):
        """Pairs ``(box, leaf)`` for every leaf overlapping one of the open boxes ``[lo, hi]``
        (each ``(N, 3)``, world) with positive volume, by descending the tree with
        :attr:`box_block` boxes at a time (the pairs come block after block)."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        step = self.box_block
        parts = [self._overlapping_block(lo[a:a + step], hi[a:a + step], a)
                 for a in range(0, len(lo), step)]
        if not parts:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return tuple(np.concatenate(column) for column in zip(*parts))

    def _overlapping_block(self, lo, hi, first):
        """:meth:`overlapping_leaves` of one block of boxes, numbered from ``first``."""
        lo_flat, hi_flat = lo.reshape(-1), hi.reshape(-1)
        q = np.arange(len(lo))
        node = np.zeros(len(lo), dtype=np.int64)
        done_q, done_leaf = [], []
        for _ in range(self.depth + 1):
            code = np.take(self.node_code, node)
            axis = code & 3
            leaf = axis == LEAF
            done_q.append(q[leaf])
            done_leaf.append(code[leaf] >> 2)
            inner = ~leaf
            q, code, axis = q[inner], code[inner], axis[inner]
            if len(q) == 0:
                break
            split = self.split_of(np.take(node, np.flatnonzero(inner)))
            at = q * 3 + axis
            left = np.take(lo_flat, at) < split
            right = np.take(hi_flat, at) > split
            child = code >> 2
            q = np.concatenate([q[left], q[right]])
            node = np.concatenate([child[left], child[right] + 1])
        return np.concatenate(done_q) + first, np.concatenate(done_leaf)

    def _candidates(self, points):
        """(point index, grid index) for every grid listed in the leaf of each point."""
        leaf = self.locate(points)
        counts = self.leaf_nsupport[leaf]
        pi = np.repeat(np.arange(len(points)), counts)
        first = np.repeat(np.cumsum(counts) - counts, counts)
        gi = self.leaf_grids[np.repeat(self.leaf_start[leaf], counts) +
                             np.arange(counts.sum()) - first]
        return pi, gi.astype(np.int64)

    def finest_grid(self, points) -> np.ndarray:
        """Index of the finest grid whose closed box contains each point (``-1``: none).

        Among grids of the same level that share a face, the lowest index wins."""
        points = as_points(points)
        pi, gi = self._candidates(points)
        inside = contains_points(self.grid_lo[gi], self.grid_hi[gi], points[pi])
        return finest_of(points, pi[inside], gi[inside], self.level)

    def support_grids(self, points) -> list:
        """For each point, the sorted indices of the grids whose (open) support contains it."""
        points = as_points(points)
        pi, gi = self._candidates(points)
        inside = np.all((points[pi] > self.support_lo[gi]) & (points[pi] < self.support_hi[gi]),
                        axis=1)
        return _group(pi[inside], gi[inside], len(points))

    def leaf_ranges(self, field: str, reconstruction: str | None = None):
        """Conservative ``(lo, hi)`` bounds (each ``(L,)``) of ``field`` reconstructed inside
        each leaf: they contain the min and max of the finite values of the cells whose hat
        support (centre +- one cell) reaches the leaf (the extremes are taken over power-of-two
        blocks of cells covering that window, so a few cells beyond it may widen them). ``reconstruction`` narrows the cells to those that method uses:
        ``"basis"`` -- leaf cells of the leaf's active grids; ``"finest"`` -- cells of the
        owner grid; ``None`` -- every cell of every grid listed at the leaf (valid for both).
        Leaves with no owner get the empty range ``(+inf, -inf)``. The windows are those of
        :meth:`leaf_windows` (the device computes the same extremes, taking each pair's window
        itself: :meth:`leaf_pairs`, :meth:`window_frame`, :mod:`mi_amr.kernels.ranges`)."""
        vol = self.volume
        pl, pg, lo, hi = self.leaf_windows(field, reconstruction)
        if reconstruction == "basis":
            values = np.where(vol.leaf_mask_flat(), flat_field(vol, field), np.nan)
        else:
            values = flat_field(vol, field)
        vmin, vmax = _window_min_max(vol, values, pg, lo, hi, chunk=self.chunk)
        out_lo = np.full(self.num_leaves, np.inf)
        out_hi = np.full(self.num_leaves, -np.inf)
        np.minimum.at(out_lo, pl, vmin)
        np.maximum.at(out_hi, pl, vmax)
        return out_lo, out_hi

    def leaf_windows(self, field: str, reconstruction: str | None = None):
        """What :meth:`leaf_ranges` takes the extremes over: ``(leaf, grid, lo, hi)``, per
        (leaf, grid) pair the inclusive cell index window (``(P, 3)`` each, cells of the grid)
        of the grid's cells whose hat support reaches the leaf, for the pairs that
        ``reconstruction`` reads (see there), leaf after leaf (a leaf's pairs one after the
        other, leaves in increasing order); the values to take are all cells' for
        ``"finest"`` and None, the leaf cells' for ``"basis"``."""
        pl, pg = self.leaf_pairs(field, reconstruction)
        # (computed for the pairs asked for: the tree keeps no windows, which would take 24
        # bytes a listed pair)
        lo, hi = self._windows(pl, pg)
        keep = np.all(hi >= lo, axis=1)
        if keep.all():          # (the active grids' windows, for one, are never empty)
            return pl, pg, lo, hi
        return pl[keep], pg[keep], lo[keep], hi[keep]

    def leaf_pairs(self, field: str, reconstruction: str | None = None):
        """The (leaf, grid) pairs of :meth:`leaf_windows`, those whose window is empty
        included (they hold no cell), without the windows: ``(leaf, grid)``, leaf after leaf.
        The device takes each pair's window itself (:mod:`mi_amr.kernels.ranges`). ``field``
        None: the pairs whatever the volume holds (the brick pools' ranges)."""
        vol = self.volume
        if field is not None and field not in vol.field_names:
            raise AMRError(f"unknown field '{field}'; available: {list(vol.field_names)}")
        if reconstruction not in (None, "basis", "finest"):
            raise AMRError(f"reconstruction must be 'basis' or 'finest', got {reconstruction!r}")
        if reconstruction == "finest":
            pl = np.flatnonzero(self.leaf_owner >= 0)
            return pl, self.leaf_owner[pl].astype(np.int64)
        count = self.leaf_nactive if reconstruction == "basis" else self.leaf_nsupport
        return self._listed_pairs(count)

    def window_frame(self) -> dict:
        """What a pair's window (:meth:`_windows`) is computed from, as the device reads it:
        the leaves' boxes ``leaf_lo``/``leaf_hi`` and the grids' lower corners ``grid_lo`` and
        cell widths ``step`` (lattice coordinates, ``(L, 3)`` integers and ``(G, 3)``
        float64), and the grids' ``shape``."""
        return {"leaf_lo": self.lattice_leaf_lo, "leaf_hi": self.lattice_leaf_hi,
                "grid_lo": self.lattice_grid_lo, "step": self.lattice_step, "shape": self.shape}


# ---------------------------------------------------------------------- brute-force twins

# ---------------------------------------------------------------------- helpers

def emitted() -> dict:
    """The empty columns that :func:`emit` appends each depth's node arrays to."""
    return {k: [] for k in ("split", "code", "lo", "hi", "depth", "leaf_lo", "leaf_hi",
                            "leaf_owner")}


def emit(out, depth, base, n_leaves, f_lo, f_hi, axis, plane, owner) -> int:
    """Append one depth's nodes to ``out``: split nodes point at their children (stored right
    after this depth), leaves at their leaf index. Returns the new leaf count."""
    n = len(f_lo)
    is_split = axis != LEAF
    rank = np.cumsum(is_split) - 1
    code = np.empty(n, dtype=np.int64)
    code[is_split] = ((base + n + 2 * rank[is_split]) << 2) | axis[is_split]
    leaf_ids = np.flatnonzero(~is_split)
    code[leaf_ids] = ((n_leaves + np.arange(len(leaf_ids))) << 2) | LEAF
    for key, value in (("split", plane), ("code", code), ("lo", f_lo), ("hi", f_hi),
                       ("depth", np.full(n, depth)), ("leaf_lo", f_lo[leaf_ids]),
                       ("leaf_hi", f_hi[leaf_ids]), ("leaf_owner", owner[leaf_ids])):
        out[key].append(value)
    return n_leaves + len(leaf_ids)


def compact_ints(a) -> np.ndarray:
    """Integer array ``a`` as int32 where all its values fit (half the memory of int64: the
    tree's per-node and per-leaf numbers), else as int64."""
    a = np.asarray(a)
    if a.size == 0 or (int(a.min()) >= -2 ** 31 and int(a.max()) < 2 ** 31):
        return a.astype(np.int32, copy=False)
    return a.astype(np.int64, copy=False)


def run_starts(keys) -> np.ndarray:
    """Where each run of equal values of the sorted array ``keys`` starts (empty for none)."""
    if len(keys) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.concatenate([[True], keys[1:] != keys[:-1]]))


def _leaf_pairs(axis, n_leaves, p_node, p_grid):
    """The pairs of one depth's leaves (``axis`` :data:`LEAF`) as (leaf, grid), the leaves
    numbered from ``n_leaves`` in node order (as :func:`emit` numbers them)."""
    is_leaf = axis == LEAF
    leaf_id = np.cumsum(is_leaf) - 1 + n_leaves
    keep = np.flatnonzero(np.take(is_leaf, p_node))
    return np.take(leaf_id, np.take(p_node, keep)), np.take(p_grid, keep)


class _Buffer:
    """Room for (node, grid) pairs that grows when it must and is otherwise reused."""

    def __init__(self):
        self.rows = np.empty((2, 0), dtype=np.int64)

    def pairs(self, n: int):
        """Two int64 arrays of ``n`` items (views of the buffer, valid until the next call)."""
        if n > self.rows.shape[1]:
            self.rows = np.empty((2, max(n, 2 * self.rows.shape[1])), dtype=np.int64)
        return self.rows[0, :n], self.rows[1, :n]


def _children(f_lo, f_hi, axis, plane, p_node, p_grid, lattice, *, chunk: int = CHUNK,
              into: _Buffer | None = None):
    """The children of the split nodes (two each, low side first) and the pairs whose open
    support reaches each side (in ``into``'s room when given), ``chunk`` pairs at a time.
    Pairs sorted by node (and within a node by grid) give pairs sorted by child (and grid):
    each side's pairs keep their order, and are placed after the other side's pairs of the
    earlier parents."""
    _, _, slo, shi = lattice
    c_lo, c_hi, child_of = child_boxes(f_lo, f_hi, axis, plane)
    slo_flat, shi_flat = slo.reshape(-1), shi.reshape(-1)

    def sides(start):
        child = np.take(child_of, p_node[start:start + chunk])
        keep = np.flatnonzero(child >= 0)
        kn, kg, kc = np.take(p_node[start:start + chunk], keep), np.take(
            p_grid[start:start + chunk], keep), np.take(child, keep)
        at, kpos = kg * 3 + np.take(axis, kn), np.take(plane, kn)
        go_left = np.take(slo_flat, at) < kpos
        go_right = np.take(shi_flat, at) > kpos
        return kc[go_left], kg[go_left], kc[go_right] + 1, kg[go_right]

    # The chunks' pairs stay in pieces (no whole-depth copies: new memory is slow to touch).
    parts = list(parallel.map_ordered(sides, range(0, len(p_node), chunk)))
    if not parts:
        return c_lo, c_hi, p_node[:0], p_grid[:0]
    S = len(c_lo) // 2
    n_left, n_right = np.zeros(S, dtype=np.int64), np.zeros(S, dtype=np.int64)
    for ln, _, rn, _ in parts:
        for side, count in ((ln, n_left), (rn, n_right)):
            if len(side):
                first = side[0] >> 1
                count[first:(side[-1] >> 1) + 1] += np.bincount((side >> 1) - first)
    right_before = np.cumsum(n_right) - n_right         # of the earlier parents
    left_through = np.cumsum(n_left)                    # of the parents up to this one
    p_node, p_grid = (into or _Buffer()).pairs(int(n_left.sum() + n_right.sum()))
    done_left = done_right = 0
    for ln, lg, rn, rg in parts:
        at = np.arange(done_left, done_left + len(ln)) + np.take(right_before, ln >> 1)
        p_node[at], p_grid[at] = ln, lg
        at = np.arange(done_right, done_right + len(rn)) + np.take(left_through, rn >> 1)
        p_node[at], p_grid[at] = rn, rg
        done_left, done_right = done_left + len(ln), done_right + len(rn)
    return c_lo, c_hi, p_node, p_grid


def child_boxes(f_lo, f_hi, axis, plane):
    """``(c_lo, c_hi, child_of)``: the boxes of the children of one depth's split nodes (two
    each, low side first, cut at ``plane`` on ``axis``) and each node's first child among
    them (-1 for a leaf)."""
    sp = np.flatnonzero(axis != LEAF)
    a, pos = axis[sp], plane[sp]
    c_lo = np.repeat(f_lo[sp], 2, axis=0)
    c_hi = np.repeat(f_hi[sp], 2, axis=0)
    c_hi[0::2][np.arange(len(sp)), a] = pos
    c_lo[1::2][np.arange(len(sp)), a] = pos
    child_of = np.full(len(f_lo), -1, dtype=np.int64)
    child_of[sp] = 2 * np.arange(len(sp))
    return c_lo, c_hi, child_of


def _pair_boxes(f_lo, f_hi, p_node, p_grid, lattice, *, chunk: int = CHUNK):
    """For (node, grid) pairs: does the grid's box overlap the node's box ``[f_lo, f_hi]`` with
    positive volume, and does it contain it (lattice coordinates)? ``chunk`` pairs at a
    time, so the gathered boxes stay small."""
    glo, ghi, _, _ = lattice
    overlap = np.empty(len(p_node), dtype=bool)
    contains = np.empty(len(p_node), dtype=bool)

    def one_part(a):                # each writes its own rows
        part = slice(a, a + chunk)
        # (np.take gathers rows several times faster than fancy indexing.)
        pl, ph = np.take(f_lo, p_node[part], axis=0), np.take(f_hi, p_node[part], axis=0)
        gl, gh = np.take(glo, p_grid[part], axis=0), np.take(ghi, p_grid[part], axis=0)
        cut = np.minimum(gh, ph) > np.maximum(gl, pl)
        overlap[part] = cut[:, 0] & cut[:, 1] & cut[:, 2]
        inside = (gl <= pl) & (gh >= ph)
        contains[part] = inside[:, 0] & inside[:, 1] & inside[:, 2]

    parallel.for_each(one_part, range(0, len(p_node), chunk))
    return overlap, contains


def _group(pi, gi, n) -> list:
    order = np.lexsort((gi, pi))
    pi, gi = pi[order], gi[order]
    cuts = np.searchsorted(pi, np.arange(1, n))
    return np.split(gi, cuts)


def _grid_offsets(volume) -> np.ndarray:
    """Where each grid's cells start in the flat array of all cells, grid after grid."""
    return volume.cell_offsets()


def leaf_count_tables(volume, grids):
    """Summed-area tables of the leaf masks of ``grids`` (shape + 1 per axis), concatenated in
    one aligned int32 array (a grid holds fewer than 2^31 cells); returns the tables and the
    offset of each grid's table (indexed by grid, -1 if absent). Grids of one shape are
    stacked and summed together, in place in the result; :func:`leaf_count_tables_reference`
    is the slow twin (one grid at a time, tables in the order of ``grids``)."""
    shapes = volume.grid_columns()["shape"]
    cell_start = volume.grid_columns()["offset"]
    flat = volume.leaf_mask_flat()
    offsets = np.full(len(volume.grids), -1, dtype=np.int64)
    grids = np.asarray(grids, dtype=np.int64)
    kinds, kind_of = _shape_kinds(shapes[grids])
    members = [grids[kind_of == kind] for kind in range(len(kinds))]
    sizes = [len(g) * int(np.prod(np.asarray(shape) + 1)) for g, shape in zip(members, kinds)]
    out = aligned_empty(int(sum(sizes)), np.int32)
    at = 0
    for shape, group, size in zip(kinds, members, sizes):
        sat = out[at:at + size].reshape((len(group),) + tuple(int(n) + 1 for n in shape))
        sat[:, 0] = 0
        sat[:, :, 0] = 0
        sat[:, :, :, 0] = 0
        cells = (cell_start[group][:, None] + np.arange(int(np.prod(shape)))).ravel()
        inner = sat[:, 1:, 1:, 1:]
        inner[...] = np.take(flat, cells).reshape(len(group), *shape)
        for axis in (1, 2, 3):
            np.cumsum(inner, axis=axis, out=inner)
        offsets[group] = at + np.arange(len(group)) * sat[0].size
        at += size
    return out, offsets


def leaf_count_tables_reference(volume, grids):
    """Slow twin of :func:`leaf_count_tables`: one grid's table after the other."""
    tables, offsets, at = [], np.full(len(volume.grids), -1, dtype=np.int64), 0
    for i in grids:
        g = volume.grids[i]
        sat = np.zeros(tuple(n + 1 for n in g.shape), dtype=np.int64)
        sat[1:, 1:, 1:] = volume.leaf_mask(i).cumsum(0).cumsum(1).cumsum(2)
        tables.append(sat.ravel())
        offsets[i] = at
        at += sat.size
    return np.concatenate(tables), offsets


def _reduce_runs(ufunc, column, index, runs, chunk: int = CHUNK) -> np.ndarray:
    """``ufunc.reduceat(column[index], runs)`` (``runs``: the increasing starts of the runs of
    ``index``, the first at 0), over blocks of about ``chunk`` rows that start at a run's
    start, so no gather of all of ``index`` at once."""
    cut = np.unique(np.searchsorted(runs, np.arange(0, len(index), chunk)))
    cut = np.append(cut[cut < len(runs)], len(runs))
    out = np.empty(len(runs), dtype=column.dtype)
    for r0, r1 in zip(cut[:-1], cut[1:]):
        begin = runs[r0]
        end = runs[r1] if r1 < len(runs) else len(index)
        out[r0:r1] = ufunc.reduceat(np.take(column, index[begin:end]), runs[r0:r1] - begin)
    return out


def _box_sum(sat, offset, shape, lo, hi):
    """Sum of a grid's leaf mask over inclusive boxes ``[lo, hi]`` (rows), from its table."""
    n1, n2 = shape[:, 1] + 1, shape[:, 2] + 1
    empty = np.any(hi < lo, axis=1)
    a, b = lo.astype(np.int64), hi.astype(np.int64) + 1
    total = np.zeros(len(lo), dtype=np.int64)
    for cx, sx in ((b[:, 0], 1), (a[:, 0], -1)):
        tx = cx * n1
        for cy, sy in ((b[:, 1], 1), (a[:, 1], -1)):
            txy = (tx + cy) * n2 + offset
            for cz, sz in ((b[:, 2], 1), (a[:, 2], -1)):
                if sx * sy * sz > 0:
                    total += np.take(sat, txy + cz)
                else:
                    total -= np.take(sat, txy + cz)
    return np.where(empty, 0, total)


def _window_min_max(volume, values, grid, lo, hi, *, chunk: int = CHUNK):
    """Min and max of the finite ``values`` (all cells of all grids, flat, grid after grid) over
    inclusive index boxes ``[lo, hi]`` (rows) of the grids ``grid``, widened to power-of-two
    blocks: a box is covered by the (at most 8) blocks of ``2**k`` cells per axis, ``2**k`` the
    largest power of two not longer than its longest side, that start at ``lo`` or end at
    ``hi`` (a block is cut at the grid's end). :func:`_window_min_max_reference` is the slow
    twin.

    Grids of one shape are stacked into one array; per block size a sparse table holds, per
    cell, the extremum over the block starting there, built by halving along each axis. The
    boxes are looked up ``chunk`` at a time."""
    shapes = volume.grid_columns()["shape"]
    offsets = volume.grid_columns()["offset"]
    finite = np.isfinite(values)
    # In the values' own precision: their min and max are the same numbers in float64, and
    # float32 tables halve the memory the lookups stream through.
    vmin_all = np.where(finite, values, np.inf)
    vmax_all = np.where(finite, values, -np.inf)
    del finite
    k_need = _block_log2(lo, hi, chunk)
    out_min = np.full(len(grid), np.inf)
    out_max = np.full(len(grid), -np.inf)
    kinds, kind_of = _shape_kinds(shapes)
    # The queries and the grids of each shape, found for all shapes in one sort each (a pass
    # over all of them per shape made this quadratic in the number of shapes).
    by_kind = [_runs_by_key(kind_of[grid], len(kinds)), _runs_by_key(kind_of, len(kinds))]

    def one_shape(kind):
        shape = kinds[kind]
        queries, members = (order[bounds[kind]:bounds[kind + 1]] for order, bounds in by_kind)
        if len(queries) == 0:
            return
        row = np.empty(len(shapes), dtype=np.int64)
        row[members] = np.arange(len(members))
        cells = (offsets[members][:, None] + np.arange(int(np.prod(shape)))).ravel()
        tmin = np.take(vmin_all, cells).reshape(len(members), *shape)
        tmax = np.take(vmax_all, cells).reshape(len(members), *shape)
        k_here = k_need[queries]
        for k in range(int(k_here.max()) + 1):
            if k > 0:
                _halve_tables(tmin, tmax, 1 << (k - 1))
            sel = queries[k_here == k] if k_here.min() != k_here.max() else queries
            for a in range(0, len(sel), chunk):
                part = sel[a:a + chunk]
                out_min[part], out_max[part] = _block_lookup(
                    tmin, tmax, row[grid[part]], lo[part], hi[part], k)

    parallel.for_each(one_shape, range(len(kinds)))      # each writes its own queries
    return out_min, out_max


def _block_log2(lo, hi, chunk: int = CHUNK) -> np.ndarray:
    """``floor(log2(longest side))`` of each inclusive box ``[lo, hi]`` (rows), ``chunk`` rows
    at a time."""
    out = np.zeros(len(lo), dtype=np.int64)
    for a in range(0, len(lo), chunk):
        side = (hi[a:a + chunk] - lo[a:a + chunk] + 1).max(axis=1)
        out[a:a + chunk] = np.floor(np.log2(side))
    return out


def _runs_by_key(keys, n: int):
    """``(order, bounds)``: the positions of ``keys`` (ints in ``[0, n)``) sorted by key, in
    increasing position within each key, and where each key's run starts
    (``order[bounds[k]:bounds[k + 1]]`` is ``np.flatnonzero(keys == k)``)."""
    order = np.argsort(keys, kind="stable")
    return order, np.searchsorted(keys[order], np.arange(n + 1))


def _shape_kinds(shapes):
    """The distinct rows of ``shapes`` (``(G, 3)`` int64, in increasing order) and the index of
    each grid's row among them, as :func:`np.unique` with ``axis=0`` gives them."""
    top = shapes.max(initial=0) + 1
    key = (shapes[:, 0] * top + shapes[:, 1]) * top + shapes[:, 2]
    keys, kind_of = np.unique(key, return_inverse=True)
    kinds = np.stack([keys // (top * top), keys // top % top, keys % top], axis=1)
    return kinds, kind_of.ravel()


def _halve_tables(tmin, tmax, step) -> None:
    """Grow the blocks of the stacked sparse tables ``tmin``/``tmax`` (grid, x, y, z) from
    ``step`` to ``2 * step`` cells per axis, in place (blocks are cut at the grid's end)."""
    for axis in (1, 2, 3):
        n = tmin.shape[axis]
        if step >= n:
            continue
        head = [slice(None)] * 4
        tail = [slice(None)] * 4
        head[axis], tail[axis] = slice(0, n - step), slice(step, n)
        head, tail = tuple(head), tuple(tail)
        tmin[head] = np.minimum(tmin[head], tmin[tail])
        tmax[head] = np.maximum(tmax[head], tmax[tail])


def _block_lookup(tmin, tmax, row, lo, hi, k):
    """Min and max over the 8 blocks of ``2**k`` cells starting at ``lo`` or ending at ``hi``
    (inclusive boxes, rows) of the stacked tables' grids ``row``."""
    shape = tmin.shape[1:]
    # Flat positions in the stacked tables (np.take on flat indices is several times faster
    # than indexing a 4D array with four index arrays).
    strides = np.array([shape[1] * shape[2], shape[2], 1], dtype=np.int64)
    r = row * (shape[0] * strides[0])
    first = lo * strides
    last = np.maximum(lo, hi - (1 << k) + 1) * strides
    flat_min, flat_max = tmin.reshape(-1), tmax.reshape(-1)
    best_min = np.full(len(row), np.inf)
    best_max = np.full(len(row), -np.inf)
    for cx in (first[:, 0], last[:, 0]):
        for cy in (first[:, 1], last[:, 1]):
            rxy = r + cx + cy
            for cz in (first[:, 2], last[:, 2]):
                at = rxy + cz
                np.minimum(best_min, np.take(flat_min, at), out=best_min)
                np.maximum(best_max, np.take(flat_max, at), out=best_max)
    return best_min, best_max


def _window_min_max_reference(volume, values, grid, lo, hi):
    """Slow twin of :func:`_window_min_max`: one box at a time, the min and max of the finite
    values over the union of its covering blocks, taken directly from the grid's array."""
    offsets = _grid_offsets(volume)
    out_min = np.full(len(grid), np.inf)
    out_max = np.full(len(grid), -np.inf)
    for q, g in enumerate(grid):
        shape = volume.grids[g].shape
        cells = values[offsets[g]:offsets[g] + int(np.prod(shape))].reshape(shape)
        block = 1 << int(np.floor(np.log2((hi[q] - lo[q] + 1).max())))
        top = np.maximum(lo[q], hi[q] - block + 1) + block  # the last block's end (exclusive)
        box = cells[lo[q][0]:top[0], lo[q][1]:top[1], lo[q][2]:top[2]]
        box = box[np.isfinite(box)]
        if box.size:
            out_min[q], out_max[q] = box.min(), box.max()
    return out_min, out_max
