"""Invariants of a :class:`~mi_amr.core.kdtree.KDTree`, checked the slow, obvious way (in the
spirit of yt's ``check_tree``). :meth:`KDTree.check` calls :func:`check`; the tests and the
10^5-grid benchmark run it.

* **tiling** -- every split node's two children are its box cut at the split plane, and the
  leaves' volumes add up to the root's: the leaves tile the root without gaps or overlaps;
* **owners** -- a leaf's owner is the finest grid whose box contains the whole leaf (the lowest
  index among equals), and a leaf no grid contains has none;
* **ropes** -- the rope of each node face is the deepest node holding everything just beyond
  that face (the root for faces on the tree's boundary);
* **ranges** -- a leaf's value range bounds the reconstructed field at points inside it
  (float64 model, :class:`~mi_amr.core.field64.Field64`), and a node's range holds its
  children's.

Boxes are compared on the tree's integer lattice (finest cells from the anchor), so the checks
are exact. A broken invariant raises ``AssertionError`` naming the node or leaf: it is a bug,
not a user's mistake.
"""

from __future__ import annotations

import numpy as np

LEAF = 3


def check(tree, field: str | None = None, *, reconstruction: str = "basis", sample: int = 2048,
          seed: int = 0) -> dict:
    """Check ``tree`` (the owners on at most ``sample`` leaves, the ranges of ``field`` at
    ``sample`` points when a field is given). Returns what was checked (counts)."""
    rng = np.random.default_rng(seed)
    out = {"nodes": tree.num_nodes, "leaves": tree.num_leaves}
    out["tiling"] = _tiling(tree)
    out["owners"] = _owners(tree, rng, sample)
    out["ropes"] = _ropes(tree)
    if field is not None:
        out["ranges"] = _ranges(tree, field, reconstruction, rng, sample)
    return out


def _tiling(tree) -> int:
    code = tree.node_code
    inner = np.flatnonzero((code & 3) != LEAF)
    axis = code[inner] & 3
    # float64: the leaves' volumes below are products that overflow integers
    lo, hi = (np.asarray(a, dtype=np.float64)
              for a in (tree.lattice_node_lo, tree.lattice_node_hi))
    plane = tree.lattice_node_split[inner]
    rows = np.arange(len(inner))
    for side in (0, 1):
        child = (code[inner] >> 2) + side
        want_lo, want_hi = lo[inner].copy(), hi[inner].copy()
        (want_hi if side == 0 else want_lo)[rows, axis] = plane
        bad = np.flatnonzero(np.any(lo[child] != want_lo, axis=1) |
                             np.any(hi[child] != want_hi, axis=1))
        assert len(bad) == 0, (f"kd-tree: child {child[bad[0]]} of node {inner[bad[0]]} is not "
                               f"its parent's box cut at the split")
    leaves = np.flatnonzero((code & 3) == LEAF)
    volume = np.prod(hi[leaves] - lo[leaves], axis=1).sum()
    root = np.prod(tree.lattice_root[1] - tree.lattice_root[0])
    assert volume == root, f"kd-tree: the leaves' volume {volume} is not the root's {root}"
    return len(inner)


def _owners(tree, rng, sample) -> int:
    leaves = np.arange(tree.num_leaves)
    if len(leaves) > sample:
        leaves = np.sort(rng.choice(leaves, sample, replace=False))
    node = tree.leaf_node[leaves]
    lo, hi = tree.lattice_node_lo[node], tree.lattice_node_hi[node]
    G = len(tree.grid_lo)
    for start in range(0, len(leaves), 256):
        part = slice(start, start + 256)
        inside = np.all((tree.lattice_grid_lo[None] <= lo[part, None])
                        & (tree.lattice_grid_hi[None] >= hi[part, None]), axis=2)
        score = np.where(inside, tree.level[None] * G + (G - 1 - np.arange(G))[None], -1)
        best = score.max(axis=1)
        want = np.where(best >= 0, G - 1 - best % G, -1)
        got = tree.leaf_owner[leaves[part]]
        bad = np.flatnonzero(got != want)
        assert len(bad) == 0, (f"kd-tree: leaf {leaves[part][bad[0]]} is owned by grid "
                               f"{got[bad[0]]}, the finest grid containing it is {want[bad[0]]}")
    return len(leaves)


def _ropes(tree) -> int:
    nodes = np.arange(tree.num_nodes)
    lo, hi, outside = tree.face_boxes(nodes)
    rope = tree.node_ropes.reshape(-1)
    r_lo, r_hi = tree.lattice_node_lo[rope], tree.lattice_node_hi[rope]
    holds = np.all((r_lo <= lo) & (r_hi >= hi), axis=1)
    # Deeper: a child of the rope would hold the face box too (a point on a split plane
    # belongs to the upper child, as in the descent).
    code = tree.node_code[rope]
    axis = np.minimum(code & 3, 2)
    rows = np.arange(len(rope))
    split = tree.lattice_node_split[rope]
    deeper = ((code & 3) != LEAF) & ((hi[rows, axis] < split) | (lo[rows, axis] >= split))
    bad = np.flatnonzero(np.where(outside, rope != 0, ~holds | deeper))
    assert len(bad) == 0, (f"kd-tree: the rope of face {bad[0] % 6} of node {bad[0] // 6} is "
                           f"node {rope[bad[0]]}, not the deepest node beyond that face")
    return len(rope)


def _ranges(tree, field, reconstruction, rng, sample) -> int:
    from mi_amr.core.field64 import Field64

    code = tree.node_code
    r_lo, r_hi = tree.node_ranges(*tree.leaf_ranges(field, reconstruction))
    inner = np.flatnonzero((code & 3) != LEAF)
    for side in (0, 1):
        c = (code[inner] >> 2) + side
        bad = np.flatnonzero((r_lo[c] < r_lo[inner]) | (r_hi[c] > r_hi[inner]))
        assert len(bad) == 0, f"kd-tree: node {inner[bad[0]]}'s range does not hold its child's"
    owned = np.flatnonzero(tree.leaf_owner >= 0)
    leaf = rng.choice(owned, sample) if len(owned) else np.zeros(0, dtype=np.int64)
    u = rng.random((len(leaf), 3))
    points = tree.leaf_lo[leaf] + u * (tree.leaf_hi[leaf] - tree.leaf_lo[leaf])
    values = Field64(tree.volume, field, reconstruction == "basis")(points)
    node = tree.leaf_node[leaf]
    slack = 1e-9 * np.maximum(np.abs(r_lo[node]), np.abs(r_hi[node])) + 1e-12
    ok = ~np.isfinite(values) | ((values >= r_lo[node] - slack) & (values <= r_hi[node] + slack))
    bad = np.flatnonzero(~ok)
    assert len(bad) == 0, (f"kd-tree: leaf {leaf[bad[0]]}'s range [{r_lo[node[bad[0]]]:g}, "
                           f"{r_hi[node[bad[0]]]:g}] misses the value {values[bad[0]]:g} at "
                           f"{points[bad[0]].tolist()}")
    return len(leaf)
