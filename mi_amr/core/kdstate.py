"""Checks of a kd-tree's state read from outside (a snapshot): every entry of
:attr:`KDTree.STATE <mi_amr.core.kdtree.KDTree.STATE>` of the type, number of axes and length
that a built tree gives it, so that a state whose values were changed (and the file signed
again) is refused as a whole instead of failing in the middle of a preparation.
"""

from __future__ import annotations

import numpy as np

from mi_amr.core.kdtree import KDTree

# Per array: its dtype kinds ("f" float, "iu" integer), its axes, and what its rows count:
# the volume's grids, the tree's nodes or leaves, (leaf, grid) pairs, 3 (a point), or anything
# (None). Two-axis arrays have 3 columns, the ropes 6 (one per face).
_ARRAYS = {
    "_level_h": ("f", 2, None), "h_fine": ("f", 1, 3), "lo": ("f", 1, 3), "hi": ("f", 1, 3),
    "lattice_step": ("f", 2, "grid"), "grid_lo": ("f", 2, "grid"), "grid_hi": ("f", 2, "grid"),
    "lattice_grid_lo": ("f", 2, "grid"), "lattice_grid_hi": ("f", 2, "grid"),
    "lattice_support_lo": ("f", 2, "grid"), "lattice_support_hi": ("f", 2, "grid"),
    "support_lo": ("f", 2, "grid"), "support_hi": ("f", 2, "grid"),
    "spacing": ("f", 2, "grid"), "shape": ("iu", 2, "grid"), "level": ("iu", 1, "grid"),
    "lattice_node_lo": ("iu", 2, "node"), "lattice_node_hi": ("iu", 2, "node"),
    "lattice_node_split": ("iu", 1, "node"), "node_code": ("iu", 1, "node"),
    "node_depth": ("iu", 1, "node"), "node_ropes": ("iu", 2, "node"),
    "lattice_leaf_lo": ("iu", 2, "leaf"), "lattice_leaf_hi": ("iu", 2, "leaf"),
    "leaf_levels": ("iu", 1, "leaf"), "leaf_min_h": ("f", 1, "leaf"),
    "leaf_nactive": ("iu", 1, "leaf"), "leaf_node": ("iu", 1, "leaf"),
    "leaf_nsupport": ("iu", 1, "leaf"), "leaf_owner": ("iu", 1, "leaf"),
    "leaf_start": ("iu", 1, "leaf"), "leaf_grids": ("iu", 1, "pair"),
}
_NUMBERS = ("depth", "leaf_cells")        # whole numbers, 0 to 2^31 - 1
_CORNERS = "lattice_root"                 # (low corner, high corner), two points


def state_problem(state, num_grids: int) -> str | None:
    """What is wrong with ``state`` (a mapping, as :meth:`KDTree.arrays` gives it) as the
    state of a tree of a volume of ``num_grids`` grids, or None where nothing is."""
    if not isinstance(state, dict) or set(state) != set(KDTree.STATE):
        return "not the tree's fields"
    for name in _NUMBERS:
        value = state[name]
        if type(value) is not int or not 0 <= value < 2 ** 31:
            return f"{name}: not a whole number"
    corners = state[_CORNERS]
    if not (isinstance(corners, tuple) and len(corners) == 2 and
            all(_is(a, "f", 1) and a.shape == (3,) for a in corners)):
        return f"{_CORNERS}: not two points"
    counts = {"grid": num_grids, "node": _rows(state["node_code"]),
              "leaf": _rows(state["leaf_node"]), "pair": None}
    for name, (kinds, axes, rows) in _ARRAYS.items():
        a = state[name]
        if not _is(a, kinds, axes):
            return f"{name}: not a {axes}-axis array of kind {kinds!r}"
        want = counts.get(rows, rows)
        if (want is not None and a.shape[0] != want) or \
                (axes == 2 and a.shape[1] != (6 if name == "node_ropes" else 3)):
            return f"{name}: shape {a.shape}"
    return None


def _is(a, kinds: str, axes: int) -> bool:
    return isinstance(a, np.ndarray) and a.dtype.kind in kinds and a.ndim == axes


def _rows(a):
    return a.shape[0] if isinstance(a, np.ndarray) and a.ndim >= 1 else None
