"""Leaf searches start from the start table over the active box
(:mod:`mi_amr.kernels.starts`) instead of the root: the table's nodes against a plain descent
cell by cell, and the same crossings, layers, shadow-ray transmittances and images as searches
from the root (``with_twins(integ, Twins(start_tables=False))``, ``trace(start_table=False)``).

The scene is sphere_wake.xml (64^2, 1 spp), rays as in ``test_active_box``.
"""

import dataclasses

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from mi_amr.kernels import starts  # noqa: E402
from mi_amr.kernels.config import clips, start_table  # noqa: E402
from mi_amr.kernels.device import node_holds  # noqa: E402
from mi_amr.plugin.twins import Twins, with_twins  # noqa: E402
# (opaque, translucent: the fixtures of test_active_box, one scene each per module)
from test_active_box import (ISOVALUES, assert_shadow_rays_and_images_agree,  # noqa: E402, F401
                             assert_trace_twins_agree, new_isovalue, opaque,
                             sample_rays, scene, translucent)


def host_table(integ, iso, **kw):
    tree = integ.dev.tree
    holds = node_holds(integ.dev.node_ranges(True), iso)
    active = np.flatnonzero(holds & ((tree.node_code & 3) == 3))
    return tree, ~holds, starts.start_table_host(tree, active, ~holds, **kw)


@pytest.mark.parametrize("iso, max_cells", [((0.05,), starts.MAX_START_CELLS),
                                            (ISOVALUES, starts.MAX_START_CELLS),
                                            ((0.05,), 5000)])
def test01_each_cell_starts_where_a_plain_descent_stops(opaque, iso, max_cells):
    """A cell's node is the first empty node on the way down from the root, else the deepest
    node holding the whole cell (a plain descent, cell by cell, on 3000 cells); it holds the
    cell, and it is marked final where it is a leaf or empty. The table covers every leaf
    whose range holds an isovalue, with at most ``max_cells`` cells (coarser cells beyond)."""
    tree, empty, (lo, cell, dims, entries) = host_table(opaque.integrator(), iso,
                                                        max_cells=max_cells)
    assert np.prod(dims) <= max_cells and len(entries) == np.prod(dims) > 1000
    nodes = (entries & (starts.FINAL - 1)).astype(np.int64)
    final = entries >= starts.FINAL
    is_leaf = (tree.node_code[nodes] & 3) == 3
    np.testing.assert_array_equal(final, is_leaf | empty[nodes])
    idx = np.indices(dims[::-1]).reshape(3, -1)[::-1].T
    c_lo = lo + idx * cell
    c_hi = c_lo + cell
    assert np.all(tree.lattice_node_lo[nodes] <= c_lo)
    assert np.all(c_hi <= tree.lattice_node_hi[nodes])
    pick = np.random.default_rng(1).choice(len(nodes), 3000, replace=False)
    slow = [starts.descend_box_reference(tree, c_lo[i], c_hi[i], empty) for i in pick]
    np.testing.assert_array_equal(nodes[pick], slow)
    # Every active leaf lies inside the table's box; they come in several sizes (a table cell
    # is at most the smallest's: a larger leaf spans many cells, each of which must find it).
    active = np.flatnonzero(~empty & ((tree.node_code & 3) == 3))
    sizes = np.unique(tree.lattice_node_hi[active] - tree.lattice_node_lo[active], axis=0)
    assert len(sizes) > 1
    if max_cells == starts.MAX_START_CELLS:
        np.testing.assert_array_equal(cell, sizes.min(axis=0))
    assert np.all(tree.lattice_node_lo[active] >= lo)
    assert np.all(tree.lattice_node_hi[active] <= lo + dims * cell)
    if max_cells == starts.MAX_START_CELLS:     # the smallest active leaves' cells
        assert final.mean() > 0.9


@pytest.mark.parametrize("iso, max_cells", [((0.05,), starts.MAX_START_CELLS),
                                            (ISOVALUES, starts.MAX_START_CELLS),
                                            ((0.05,), 5000), ((0.2,), 64)])
def test01b_the_devices_table_is_the_hosts(opaque, iso, max_cells):
    """The table the device builds (a lane a cell, each descending from the root) holds the
    host's entries, node and final mark, cell for cell; so does the one the integrator
    uses for its isovalues (:meth:`DeviceVolume.start_table`)."""
    from mi_amr.kernels.device import active_leaves

    integ = opaque.integrator()
    tree, empty, (lo, cell, dims, entries) = host_table(integ, iso, max_cells=max_cells)
    active = np.flatnonzero(~empty & ((tree.node_code & 3) == 3))
    frame = starts.table_frame(tree, active, max_cells)
    for a, b in zip(frame, (lo, cell, dims)):
        np.testing.assert_array_equal(a, b)
    got = starts.start_table_device(integ.m, integ.dev._descent(empty), frame)
    np.testing.assert_array_equal(got.numpy()[:len(entries)], entries)
    if max_cells == 64:         # coarse cells: descents that stop above the leaves too
        assert (entries >= starts.FINAL).any() and (entries < starts.FINAL).any()
    # Descents that stop at inner nodes too: a tenth of all nodes marked to skip.
    stop = empty | (np.random.default_rng(5).random(tree.num_nodes) < 0.1)
    want = starts.start_table_host(tree, active, stop, max_cells=max_cells)[3]
    inner = (tree.node_code[want & (starts.FINAL - 1)] & 3) != 3
    assert (inner & (want >= starts.FINAL)).any()
    got = starts.start_table_device(integ.m, integ.dev._descent(stop), frame)
    np.testing.assert_array_equal(got.numpy()[:len(want)], want)
    ranges = integ.dev.node_ranges(True)
    iso = np.asarray(iso, dtype=np.float32)
    want = starts.start_table_host(tree, active_leaves(tree, ranges, iso),
                                   ~node_holds(ranges, iso, widen=0.0))[3]
    table = integ.dev.start_table(iso)
    np.testing.assert_array_equal(table.nodes.numpy()[:len(want)], want)


def test02_no_active_leaf_gives_an_empty_table(opaque):
    tree, _, (lo, cell, dims, entries) = host_table(opaque.integrator(), (1e9,))
    assert np.prod(dims) == 0 and len(entries) == 1


def crossings(integ, o, d, table):
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.surface import first_crossing

    m = integ.m
    cfg = integ.config()
    if not table:
        cfg = dataclasses.replace(cfg, start_table=None)
    ray = RayContext(integ.dev, cfg, m.Array3f(*o.T), m.Array3f(*d.T), m.Float(0.0),
                     m.Float(dr.inf), m.Bool(True))
    c = first_crossing(ray, m.Float(0.5))
    dr.eval(c.t, c.hit, c.k, c.samples)
    hit = c.hit.numpy().astype(bool)
    return (np.where(hit, c.t.numpy(), np.inf), np.where(hit, c.k.numpy().astype(int), -1),
            c.samples.numpy())


def test03_first_crossings_are_the_searches_from_the_root(opaque):
    integ = opaque.integrator()
    assert start_table(integ.config()) is not None
    o, d = sample_rays(integ)
    fast, slow = crossings(integ, o, d, True), crossings(integ, o, d, False)
    assert np.isfinite(slow[0]).sum() > 1500
    for a, b in zip(fast, slow):                 # depths, isovalues, pieces examined
        np.testing.assert_array_equal(a, b)


def test04_layers_are_the_searches_from_the_root(translucent):
    from test_translucent import layers

    integ = translucent.integrator()
    o, d = sample_rays(integ, n=6000)
    fast = layers(integ, o, d, resume=True)
    slow = layers(with_twins(integ, Twins(start_tables=False)), o, d, resume=True)
    assert (fast[1] >= 0).sum() > 2000
    np.testing.assert_array_equal(fast[1], slow[1])
    np.testing.assert_array_equal(fast[0], slow[0])


@pytest.mark.parametrize("which", ["opaque", "translucent"])
def test05_shadow_rays_and_images_are_the_twins(request, which):
    assert_shadow_rays_and_images_agree(request.getfixturevalue(which),
                                        Twins(start_tables=False))


def test06_a_new_isovalue_builds_its_table_without_compiling(opaque):
    from conftest import kernels_compiled

    integ = opaque.integrator()
    before = integ.config().start_table
    with new_isovalue(opaque):
        after = integ.config().start_table
        assert after is not before and after.nodes.shape != before.nodes.shape
        assert kernels_compiled(lambda: dr.eval(mi.render(opaque, seed=0)))[1] == 0
        o, d = sample_rays(integ, n=3000)
        np.testing.assert_array_equal(crossings(integ, o, d, True)[0],
                                      crossings(integ, o, d, False)[0])


@pytest.mark.parametrize("kw", [{"reconstruction": "finest"}, {"method": "uniform"},
                                {"method": "bisect"}, {"mode": "volume"}])
def test07_only_searches_in_the_active_box_use_a_table(scene_data_ready, kw):
    """A search from a deeper node skips smaller nodes, which changes the sides that the
    sampling methods and the finest level see: only the clipped exact march uses a table."""
    cfg = scene(**kw).integrator().config()
    assert not clips(cfg) and start_table(cfg) is None


def test08_trace_starts_from_the_table_too(opaque):
    assert_trace_twins_agree(opaque.integrator(), "start_table")
