"""The one traversal (:mod:`mi_amr.kernels.traverse`) counted: the kd nodes its leaf searches
visit per ray, against the slow twin of the ropes (every search after a leaf restarts at the
root). A rope that leads nowhere falls back to the root: the crossings stay the same, and only
these counts see it."""

import drjit as dr
import numpy as np
import pytest

from mi_amr.kernels.config import MarchConfig
from mi_amr.kernels.device import opaque_floats
from mi_amr.kernels.prepared import PreparedVolume
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.traverse import walk_counts
from mi_amr.synthetic import datasets

m = dr.llvm.ad
AXES = [(a, s) for a in range(3) for s in (1.0, -1.0)]


@pytest.fixture(scope="module")
def torus():
    vol = datasets.torus(16)
    dev = PreparedVolume(vol, "f", m=m).device
    cfg = MarchConfig(method="exact", basis=True,
                      isovalues=opaque_floats(m, [datasets.ISOVALUES["torus"]]),
                      step_scale=opaque_floats(m, [1.0]), num_iso=1)
    dev.node_search(cfg.basis)
    return vol, dev, cfg


def counts(torus, axis, sign, ropes):
    """``(nodes, leaves, pieces)`` per ray of a 24 x 24 bundle of rays along ``sign`` times
    ``axis``, through the whole volume."""
    vol, dev, cfg = torus
    lo, hi = (np.asarray(b, dtype=np.float64) for b in vol.bounds)
    u = (np.arange(24) + 0.37) / 24
    a, b = np.meshgrid(u, u, indexing="ij")
    o = np.empty((a.size, 3))
    others = [x for x in range(3) if x != axis]
    o[:, others[0]] = lo[others[0]] + a.ravel() * (hi - lo)[others[0]]
    o[:, others[1]] = lo[others[1]] + b.ravel() * (hi - lo)[others[1]]
    o[:, axis] = lo[axis] - 0.1 if sign > 0 else hi[axis] + 0.1
    d = np.zeros_like(o)
    d[:, axis] = sign
    ray = RayContext(dev, cfg, m.Array3f(*o.T), m.Array3f(*d.T), m.Float(0.0),
                     m.Float(dr.inf), dr.full(m.Bool, True, len(o))).clipped()
    out = walk_counts(ray, ropes)
    dr.eval(out)
    return [c.numpy().astype(np.int64) for c in out]


@pytest.mark.parametrize("axis, sign", AXES)
def test01_ropes_visit_fewer_nodes_than_restarts_from_the_root(torus, axis, sign):
    """Along every axis, both ways: the same leaves and pieces with ropes as with every search
    restarted at the root, and the ropes' searches visit at most 3/4 of the nodes in all (no
    ray more than its twin). A wrong rope (one face's rope read for another) falls back to the
    root and fails the bound for rays leaving leaves through that face."""
    nodes, leaves, pieces = counts(torus, axis, sign, True)
    twin_nodes, twin_leaves, twin_pieces = counts(torus, axis, sign, False)
    np.testing.assert_array_equal(leaves, twin_leaves)
    np.testing.assert_array_equal(pieces, twin_pieces)
    assert leaves.sum() > 2 * len(leaves)          # the rays pass several leaves
    assert np.all(nodes <= twin_nodes)
    assert nodes.sum() <= 0.75 * twin_nodes.sum(), (nodes.sum(), twin_nodes.sum())
