"""The kd-tree's ropes, made on the device.

:meth:`KDTree._ropes <mi_amr.core.kdtree.KDTree._ropes>` (NumPy, top-down, one depth at a
time) is the host's way; here one kernel descends every face of every node from the root
(a lane a face), as :meth:`~mi_amr.core.kdtree.KDTree._ropes_from_root` does on the host: the
rope of face ``2 * axis + side`` of node ``n`` is the deepest node holding the closed box half
a finest cell beyond that face (the root for a face on the tree's boundary). Same numbers as
both host versions (``tests/test_kdtree.py``).

Coordinates are the tree's lattice (cells of the finest level from the volume's anchor),
doubled so that the face planes, half a cell off the lattice, are whole numbers: int32, for
lattices below :data:`LATTICE_MAX`. The root box is an opaque kernel input and the tree's
arrays are gathered from, so every tree runs the same compiled kernel.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_amr.core.buffers import aligned_copy
from mi_amr.kernels.arrays import device_table

LEAF = 3                  # the axis field of a leaf's node code (as in mi_amr.core.kdtree)
LATTICE_MAX = 1 << 29     # |lattice coordinate| below which doubled faces fit in int32


def fits(tree) -> bool:
    """Can :func:`node_ropes` take ``tree`` (its lattice small enough for int32)?"""
    root = np.abs(np.concatenate(tree._root))
    return bool(root.max() < LATTICE_MAX)


def node_ropes(m, tree) -> np.ndarray:
    """``node_ropes`` of ``tree`` (``(N, 6)`` uint32, aligned, as
    :meth:`KDTree._ropes <mi_amr.core.kdtree.KDTree._ropes>` sets it), made by a kernel on
    backend ``m`` (a Dr.Jit module such as ``drjit.llvm.ad``). The tree's lattice must
    :func:`fit <fits>`."""
    N = tree.num_nodes
    code = device_table(m.UInt32, tree.node_code, np.uint32)
    split = device_table(m.Int32, 2 * tree._node_split, np.int32)
    lo = [device_table(m.Int32, 2 * tree._node_lo[:, a], np.int32) for a in range(3)]
    hi = [device_table(m.Int32, 2 * tree._node_hi[:, a], np.int32) for a in range(3)]
    root = [[dr.opaque(m.Int32, int(2 * tree._root[s][a])) for a in range(3)] for s in (0, 1)]
    face = dr.arange(m.UInt32, 6 * N)
    node = face // 6
    box = _face_box(m, face - 6 * node, [dr.gather(m.Int32, t, node) for t in lo],
                    [dr.gather(m.Int32, t, node) for t in hi], root)
    rope = _descend(m, (code, split), box)
    dr.eval(rope)
    return aligned_copy(rope.numpy(), np.uint32).reshape(N, 6)


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


def _descend(m, nodes, box):
    """The deepest node holding each closed box of ``box`` (``(lo, hi, inside)`` as
    :func:`_face_box` gives it), descending from the root; the root where not ``inside``.
    ``nodes``: the tree's node codes and doubled split planes (device tables)."""
    code, split = nodes
    lo, hi, inside = box

    def body(at, going):
        c = dr.gather(m.UInt32, code, at, going)
        axis = c & 3
        inner = going & (axis != LEAF)
        s = dr.gather(m.Int32, split, at, inner)
        low = dr.select(axis == 0, lo[0], dr.select(axis == 1, lo[1], lo[2]))
        high = dr.select(axis == 0, hi[0], dr.select(axis == 1, hi[1], hi[2]))
        above = inner & (low >= s)
        go = above | (inner & (high < s))
        return dr.select(go, (c >> 2) + dr.select(above, 1, 0), at), go

    at, _ = dr.while_loop((dr.zeros(m.UInt32, dr.width(inside)), m.Bool(inside)),
                          lambda at, going: going, body)
    return at


def maker(m):
    """What :class:`~mi_amr.core.kdtree.KDTree` takes as ``ropes``: :func:`node_ropes` on
    backend ``m`` for a tree that :func:`fits`, else None (the tree makes them on the host)."""
    return lambda tree: node_ropes(m, tree) if fits(tree) else None
