"""What the device prepares from the host's data model equals its NumPy twin: the kd leaves'
value ranges (:mod:`mi_amr.kernels.ranges`, one lane per (leaf, grid) window) against
:meth:`KDTree.leaf_ranges` rounded to float32, for every reconstruction, on hierarchies with
missing values; and the node ranges the search reads. (The brick pools' twin is
``tests/test_reconstruct.py`` test08.)"""

import numpy as np
import pytest

dr = pytest.importorskip("drjit")

from mi_amr import AMRVolume, KDTree  # noqa: E402
from mi_amr.kernels import ranges  # noqa: E402
from test_kdtree import HIERARCHIES  # noqa: E402


def with_missing(grids, seed):
    """The hierarchy with a tenth of its cells NaN and a few +-inf."""
    rng = np.random.default_rng(seed)
    for g in grids:
        f = g["fields"]["f"]
        f[rng.random(f.shape) < 0.1] = np.nan
        f[rng.random(f.shape) < 0.01] = np.inf * np.sign(rng.normal())
    return grids


@pytest.mark.parametrize("hierarchy", sorted(HIERARCHIES))
def test01_device_leaf_ranges_are_the_numpy_ones(hierarchy):
    m = dr.llvm.ad
    vol = AMRVolume.from_grids(with_missing(HIERARCHIES[hierarchy](), 7), allow_nonfinite=True)
    tree = KDTree(vol, leaf_cells=4)
    values = m.Float(np.concatenate([g.fields["f"].ravel() for g in vol.grids])
                     .astype(np.float32))
    for reconstruction in (None, "basis", "finest"):
        want = tree.leaf_ranges("f", reconstruction)
        got = ranges.leaf_ranges(m, tree, values, "f", reconstruction)
        for a, b in zip(got, want):
            assert a.dtype == np.float32
            np.testing.assert_array_equal(a, b.astype(np.float32))
        assert np.isfinite(got[0]).mean() > 0.5       # most leaves have a range
        assert np.any(got[0] == np.inf)               # leaves without an owner have none


def test02_windows_widen_to_the_blocks_of_the_numpy_twin():
    """A 3-cell window widens to blocks of 2 that start at its low end or end at its high end
    (3 cells: no change); a 3 x 1 x 1 window to 2 cells on the short axes, cut at the grid."""
    lo = np.array([[0, 0, 0], [2, 5, 7]])
    hi = np.array([[2, 2, 2], [4, 5, 7]])
    shape = np.array([[8, 8, 8], [8, 6, 8]])
    np.testing.assert_array_equal(ranges.block_tops(lo, hi, shape), [[3, 3, 3], [5, 6, 8]])


def test02b_the_kernels_widened_windows_are_the_host_twins():
    """The kernel widens each window on the device (:func:`ranges.device_tops`, the block from
    the longest side's leading zeros); its tops equal :func:`ranges.block_tops` on random
    windows of random grids, sides from 1 to 300 cells."""
    rng = np.random.default_rng(8)
    shape = rng.integers(1, 300, size=(5000, 3))
    a, b = (rng.integers(0, 300, size=(5000, 3)) % shape for _ in range(2))
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    m = dr.llvm.ad
    dev = [m.Array3i(*(m.Int32(np.ascontiguousarray(x[:, k], dtype=np.int32))
                       for k in range(3))) for x in (lo, hi, shape)]
    top = ranges.device_tops(m, *dev)
    got = np.stack([np.array(top.x), np.array(top.y), np.array(top.z)], axis=1)
    want = ranges.block_tops(lo, hi, shape)
    assert np.any(want - lo > hi - lo + 1)              # some windows widen
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("name", sorted(HIERARCHIES))
def test02c_the_kernels_windows_are_the_trees(name):
    """The kernel takes each (leaf, grid) pair's cell window itself (from the leaves' and
    grids' lattice boxes, float64, the tree's operations in its order); they equal
    :meth:`KDTree._windows` for every listed pair, those with an empty window included."""
    tree = KDTree(AMRVolume.from_grids(HIERARCHIES[name]()), leaf_cells=4)
    pl, pg = tree.leaf_pairs("f", None)
    m = dr.llvm.ad
    lo, hi, _, _ = ranges._Frame.of(m, tree).windows(
        m, m.UInt32(pl.astype(np.uint32)), m.UInt32(pg.astype(np.uint32)))
    want = tree._windows(pl, pg)
    assert np.any(np.any(want[1] < want[0], axis=1))        # some empty windows
    for got, w in zip((lo, hi), want):
        np.testing.assert_array_equal(np.stack([np.array(got.x), np.array(got.y),
                                                np.array(got.z)], axis=1), w)


@pytest.mark.parametrize("basis", [True, False])
def test03_node_ranges_the_search_reads_are_the_numpy_ones(basis):
    from mi_amr.kernels.prepared import PreparedVolume

    vol = AMRVolume.from_grids(with_missing(HIERARCHIES["random1"](), 8), allow_nonfinite=True)
    dev = PreparedVolume(vol, "f", m=dr.llvm.ad).device
    key = "basis" if basis else "finest"
    lo, hi = dev.tree.node_ranges(*dev.tree.leaf_ranges("f", key))
    want = np.stack([lo, hi], axis=1).astype(np.float32).ravel()
    np.testing.assert_array_equal(dev.node_ranges(basis), want)


def test04_ranges_first_asked_for_inside_a_traced_loop_are_the_same():
    """No kernel may run while a symbolic loop is traced: there the NumPy twin gives them."""
    from mi_amr.kernels.prepared import PreparedVolume

    m = dr.llvm.ad
    vol = AMRVolume.from_grids(with_missing(HIERARCHIES["ratio2"](), 9), allow_nonfinite=True)
    outside = PreparedVolume(vol, "f", m=m).device.node_ranges(True)
    dev = PreparedVolume(vol, "f", m=m).device
    got = []

    def body(i):
        got.append(dev.node_ranges(True))
        return (i + 1,)

    dr.while_loop((m.UInt32(0),), lambda i: i < 2, body)
    np.testing.assert_array_equal(got[0], outside)


def test05_ranges_in_many_launches_are_the_same():
    m = dr.llvm.ad
    vol = AMRVolume.from_grids(with_missing(HIERARCHIES["random0"](), 10), allow_nonfinite=True)
    tree = KDTree(vol, leaf_cells=4)
    values = m.Float(np.concatenate([g.fields["f"].ravel() for g in vol.grids])
                     .astype(np.float32))
    want = ranges.leaf_ranges(m, tree, values, "f", "basis")
    got = ranges.leaf_ranges(m, tree, values, "f", "basis", pairs=7)
    assert len(tree.leaf_windows("f", "basis")[0]) > 70
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


def test06_a_volume_of_another_structure_compiles_no_kernel():
    """The brick fill and the ranges read sizes, tables and offsets as kernel inputs, so a
    volume with other grids, levels of one grid and a different number of leaves runs the
    kernels the first one compiled (a scatter into the leaves' ranges compiled their number
    in; a one-entry table compiled a broadcast)."""
    from conftest import kernels_compiled
    from mi_amr.kernels.prepared import PreparedVolume

    m = dr.llvm.ad

    def prepare(name, seed):
        vol = AMRVolume.from_grids(with_missing(HIERARCHIES[name](), seed), allow_nonfinite=True)
        dev = PreparedVolume(vol, "f", m=m).device
        return dev.node_ranges(True), dev.node_ranges(False)

    prepare("random2", 11)
    _, compiled = kernels_compiled(lambda: prepare("ratio4-2", 12))
    assert compiled == 0


def test06b_a_launch_of_one_pair_compiles_no_kernel():
    """A last launch of the ranges holding a single (leaf, grid) pair runs the kernel the
    others compiled (a one-lane input would compile into a broadcast), with the same ranges."""
    from conftest import kernels_compiled
    from mi_amr.kernels import ranges
    from mi_amr.kernels.prepared import PreparedVolume

    m = dr.llvm.ad
    vol = AMRVolume.from_grids(with_missing(HIERARCHIES["random2"](), 11), allow_nonfinite=True)
    prep = PreparedVolume(vol, "f", m=m)
    want = ranges.leaf_ranges(m, prep.tree, prep.device.values, "f", "basis")
    pairs = len(prep.tree.leaf_windows("f", "basis")[0])
    got, compiled = kernels_compiled(lambda: ranges.leaf_ranges(
        m, prep.tree, prep.device.values, "f", "basis", pairs=pairs - 1))    # pairs - 1, 1
    assert compiled == 0
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


def _grids(name):
    from mi_amr.synthetic import datasets

    return {"one grid": lambda: HIERARCHIES["ratio2"]()[:1],
            "many grids": lambda: datasets.many_grids(10, 300)}.get(name, HIERARCHIES.get(name))()


def _same_tree(got, want):
    for key in KDTree.STATE + ("leaf_node",):
        np.testing.assert_array_equal(getattr(got, key), getattr(want, key), err_msg=key)


@pytest.mark.parametrize("name", sorted(HIERARCHIES) + ["one grid", "many grids"])
def test08_a_tree_built_with_the_devices_steps_is_the_hosts(name):
    """The kernels' ropes (a kernel a depth, top-down) equal the host's top-down ones
    and their slow twin, and the kernel's active grids the host's, on every test hierarchy at
    two leaf sizes, a lone grid (a handful of nodes) and a thousand tiny grids: the tree built
    with the device's steps is the host's, array for array."""
    from mi_amr.kernels import kdsteps

    m = dr.llvm.ad
    for leaf_cells in (2, 8):
        host = KDTree(AMRVolume.from_grids(_grids(name)), leaf_cells=leaf_cells)
        made = KDTree(AMRVolume.from_grids(_grids(name)), leaf_cells=leaf_cells,
                      device=kdsteps.DeviceSteps(m))
        got = kdsteps.node_ropes(m, host)
        assert got.dtype == np.uint32 and got.shape == (host.num_nodes, 6)
        np.testing.assert_array_equal(got, host.node_ropes)
        np.testing.assert_array_equal(got, host._ropes_from_root())
        _same_tree(made, host)
    assert host.num_nodes > 1


@pytest.mark.parametrize("name", ["ratio4-2", "random0", "random2", "anisotropic"])
def test08b_the_kernels_active_grids_are_the_hosts(name):
    """Every (leaf, grid) pair of the leaves' lists: active on the device exactly where the host
    says so, partly covered grids (a window with and without leaf cells) included; a launch of
    one pair gives the same; the leaves' lists put in order from them are the host's."""
    from mi_amr.kernels import kdsteps

    tree = KDTree(AMRVolume.from_grids(_grids(name)), leaf_cells=4)
    pl = np.repeat(np.arange(tree.num_leaves), tree.leaf_nsupport)
    pg = tree.leaf_grids.astype(np.int64)
    want = tree._active(pl, pg)
    partly = tree.volume.partly_covered()[pg]
    assert want[partly].any() and not want[partly].all()      # both kinds are tested
    got = kdsteps.pair_active(dr.llvm.ad, tree, pl, pg)
    assert got.dtype == bool
    np.testing.assert_array_equal(got, want)
    one = np.flatnonzero(partly & want)[:1]
    np.testing.assert_array_equal(kdsteps.pair_active(dr.llvm.ad, tree, pl[one], pg[one]), [True])
    made, host = kdsteps.leaf_lists(dr.llvm.ad, tree, pl, pg), tree._leaf_lists(pl, pg)
    assert sorted(made) == sorted(host)
    for key, value in host.items():
        assert made[key].dtype == value.dtype, key
        np.testing.assert_array_equal(made[key], value, err_msg=key)
    assert (host["leaf_nactive"] < host["leaf_nsupport"]).any()     # some grids move


def test08b2_only_partly_covered_grids_read_a_summed_area_table(capfd):
    """The active-grid kernel reads the leaf-count tables only for partly covered grids: a large
    uncovered grid beside a small partly covered one (the only table, 5^3 entries) makes no
    out-of-bounds read (Dr.Jit's debug mode checks every gather), with the host's answers."""
    from conftest import grid
    from mi_amr.kernels import kdsteps

    vol = AMRVolume.from_grids([grid(0, (0, 0, 0), (4, 4, 4), 1.0),
                                grid(0, (4, 0, 0), (20, 16, 16), 1.0),
                                grid(1, (1, 1, 1), (3, 3, 3), 0.5)])
    tree = KDTree(vol, leaf_cells=4)
    assert list(vol.partly_covered()) == [True, False, False]
    pl = np.repeat(np.arange(tree.num_leaves), tree.leaf_nsupport)
    pg = tree.leaf_grids.astype(np.int64)
    capfd.readouterr()
    was = dr.flag(dr.JitFlag.Debug)
    dr.set_flag(dr.JitFlag.Debug, True)
    try:
        got = kdsteps.pair_active(dr.llvm.ad, tree, pl, pg)
        dr.sync_thread()
    finally:
        dr.set_flag(dr.JitFlag.Debug, was)
    assert "out-of-bounds" not in capfd.readouterr().err
    np.testing.assert_array_equal(got, tree._active(pl, pg))


@pytest.mark.parametrize("name", ["ratio4-2", "random0", "random2"])
def test08b3_a_load_reads_and_writes_nothing_out_of_bounds(name, capfd):
    """Preparing a volume (derivation, kd-tree steps on the device, device arrays, brick pools,
    leaf ranges for both reconstructions, the nodes' search tables) in Dr.Jit's debug mode,
    which checks every gather and scatter: none is out of bounds."""
    from mi_amr.kernels.prepared import PreparedVolume

    from test_derive import _velocity_hierarchy

    grids = with_missing(HIERARCHIES[name](), 3)
    vols = [AMRVolume.from_grids(grids, allow_nonfinite=True),
            _velocity_hierarchy(2, (2, 4), np.float32, True)]
    capfd.readouterr()
    was = dr.flag(dr.JitFlag.Debug)
    dr.set_flag(dr.JitFlag.Debug, True)
    try:
        for vol, field in zip(vols, ("f", "q_criterion")):
            prep = PreparedVolume(vol, field, m=dr.llvm.ad)
            for basis in (True, False):
                prep.device.node_search(basis)
        dr.sync_thread()
    finally:
        dr.set_flag(dr.JitFlag.Debug, was)
    assert "out-of-bounds" not in capfd.readouterr().err


def test08c_a_lattice_too_large_for_the_kernels_gets_the_hosts_steps(monkeypatch):
    """A tree whose doubled lattice would overflow the kernels' int32 takes every step on the
    host (the device declines it), the same tree."""
    from mi_amr.kernels import kdbuild, kdsteps

    vol = AMRVolume.from_grids(HIERARCHIES["random1"]())
    want = KDTree(vol, leaf_cells=4)
    assert kdsteps.fits(want) and kdbuild.fits(want)
    for module in (kdsteps, kdbuild):
        monkeypatch.setattr(module, "LATTICE_MAX", 1)
    asked = []
    for module, name in ((kdsteps, "node_ropes"), (kdsteps, "leaf_lists"), (kdbuild, "build")):
        monkeypatch.setattr(module, name, lambda *a: asked.append(a))
    _same_tree(KDTree(vol, leaf_cells=4, device=kdsteps.DeviceSteps(dr.llvm.ad)), want)
    assert asked == []


def test07_a_session_gives_back_what_it_prepared_until_cleared(tmp_path):
    """:class:`~mi_amr.kernels.prepared.Preparations` keeps what it prepared (the same
    object for the same file, fields and backend; another for other fields), tells its
    ``report`` each step of a load, forgets all on ``clear``; another session, or
    ``prepare_file`` alone, prepares afresh."""
    from mi_amr.kernels.prepared import Preparations, prepare_file
    from mi_amr.synthetic import datasets

    path = tmp_path / "wake.npz"
    datasets.sphere_wake("small", progress=False).select_fields(["vx", "vy", "vz"]).save(path)
    heard = []
    session = Preparations(report=heard.append)
    first = session.prepare(path, "q_criterion", "speed", m=dr.llvm.ad)
    assert any("read wake.npz" in line for line in heard) and \
        any("kd-tree" in line for line in heard)
    heard.clear()
    assert session.prepare(path, "q_criterion", "speed", m=dr.llvm.ad) is first
    assert not heard                                     # nothing loaded again
    assert session.prepare(path, "speed", m=dr.llvm.ad) is not first
    assert Preparations().prepare(path, "q_criterion", "speed", m=dr.llvm.ad) is not first
    assert prepare_file(path, "q_criterion", "speed", m=dr.llvm.ad) is not first
    session.clear()
    assert session.prepare(path, "q_criterion", "speed", m=dr.llvm.ad) is not first


def test07c_a_volume_offered_for_its_file_is_prepared_without_reading_it(tmp_path):
    """:meth:`Preparations.offer`: the next preparation of that file takes the fields from the
    volume offered (a data file's scene read them for its isovalue pick) instead of reading and
    deriving them again, and prepares what a read would; it does not where the file changed
    since, where the volume lacks a field, or where the offer was for NaN/Inf kept otherwise;
    one preparation of the file takes the offer or drops it."""
    import os

    from mi_amr.kernels.prepared import Preparations
    from mi_amr.plugin.datafields import load_with_fields
    from mi_amr.synthetic import datasets

    path = tmp_path / "wake.npz"
    datasets.sphere_wake("small", progress=False).select_fields(["vx", "vy", "vz"]).save(path)
    picked, _ = load_with_fields(path, ["q_criterion"])
    heard = []

    def prepare(session, *fields, offer=None, nonfinite=False):
        if offer is not None:
            session.offer(path, offer, allow_nonfinite=nonfinite)
        heard.clear()
        return session.prepare(path, *fields, m=dr.llvm.ad)

    session = Preparations(report=heard.append)
    offered = prepare(session, "q_criterion", offer=picked.select_fields(["q_criterion"]))
    assert any("already read" in line for line in heard) and \
        not any("read wake.npz" in line for line in heard), heard
    read = prepare(Preparations(report=heard.append), "q_criterion")
    assert any("read wake.npz" in line for line in heard), heard
    for g, (a, b) in enumerate(zip(offered.volume.grids, read.volume.grids)):
        assert np.shares_memory(a.fields["q_criterion"], picked.grids[g].fields["q_criterion"])
        np.testing.assert_array_equal(a.fields["q_criterion"], b.fields["q_criterion"])
    for kind in (True, False):
        np.testing.assert_array_equal(offered.device.node_ranges(kind),
                                      read.device.node_ranges(kind))
    np.testing.assert_array_equal(offered.device.brick_values.numpy(),
                                  read.device.brick_values.numpy())
    # Not taken: a field it lacks, a file changed since the offer, NaN/Inf kept otherwise.
    q_only = picked.select_fields(["q_criterion"])
    for fields, nonfinite, touch in ((("q_criterion", "speed"), False, False),
                                     (("q_criterion",), True, False),
                                     (("q_criterion",), False, True)):
        session = Preparations(report=heard.append)
        session.offer(path, q_only, allow_nonfinite=nonfinite)
        if touch:
            os.utime(path, ns=(os.stat(path).st_atime_ns, os.stat(path).st_mtime_ns + 10**9))
        heard.clear()
        session.prepare(path, *fields, m=dr.llvm.ad)
        assert any("read wake.npz" in line for line in heard), (fields, nonfinite, touch)
        assert session.take_offer(str(path)) is None           # dropped either way


class _Prepared:
    """What a stand-in ``prepare_file`` gives: something a weak reference can watch."""


def test07b_a_session_full_forgets_its_oldest_before_it_prepares_another(tmp_path, monkeypatch):
    """With :attr:`Preparations.SIZE` volumes kept, preparing another first forgets the
    oldest, so that what it held is freed before the new load (which then reuses that memory
    instead of touching new memory); :meth:`Preparations.retain` forgets those of the other
    files, and a file forgotten is prepared again when asked for."""
    import weakref

    from mi_amr.kernels import prepared

    made, alive_at_call = [], []

    def stand_in(path, *args, **kwargs):
        alive_at_call.append([ref() is not None for ref in made])
        out = _Prepared()
        made.append(weakref.ref(out))
        return out

    monkeypatch.setattr(prepared, "prepare_file", stand_in)
    paths = []
    for i in range(prepared.Preparations.SIZE + 2):
        paths.append(tmp_path / f"step{i}.npz")
        paths[-1].write_bytes(b"")
    session = prepared.Preparations()
    size = session.SIZE
    for p in paths:
        session.prepare(p, "q_criterion", m=dr.llvm.ad)
    # While the volume after the first SIZE is prepared, the oldest is already gone.
    assert alive_at_call[size] == [False] + [True] * (size - 1)
    assert alive_at_call[size + 1] == [False, False] + [True] * (size - 1)
    kept = session.prepare(paths[-1], "q_criterion", m=dr.llvm.ad)
    assert len(made) == size + 2                       # the kept one is given again
    session.retain([str(paths[-1])])
    assert [ref() is not None for ref in made][:-1] == [False] * (size + 1)
    assert session.prepare(paths[-1], "q_criterion", m=dr.llvm.ad) is kept
    session.prepare(paths[-2], "q_criterion", m=dr.llvm.ad)
    assert len(made) == size + 3                       # forgotten: prepared again


def test01d_pairs_are_put_in_order_of_window_size_within_runs():
    """The walk's order: within each run of ``block`` pairs their keys ascend, equal keys in
    their first order (stable), and no pair leaves its run."""
    from mi_amr.kernels.ranges import _blockwise_order

    key = np.random.default_rng(3).integers(0, 40, 1000).astype(np.uint16)
    order = _blockwise_order(key, 64)
    assert sorted(order) == list(range(1000))
    for a in range(0, 1000, 64):
        run = order[a:a + 64]
        assert np.all((run >= a) & (run < a + 64))
        pairs = list(zip(key[run], run))
        assert pairs == sorted(pairs)
