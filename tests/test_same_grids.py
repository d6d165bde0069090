"""A preparation of a volume whose grids are those of one already kept (another time step of
unchanged grids, or the same file with other fields) takes that one's kd-tree and level tables
instead of making them again (:meth:`Preparations.like
<mi_amr.kernels.prepared.Preparations.like>`, :meth:`AMRVolume.same_hierarchy
<mi_amr.core.volume.AMRVolume.same_hierarchy>`), and prepares what a fresh preparation
would, array for array; grids that differ in any way (moved, reordered) or another leaf size
build their own."""

import numpy as np
import pytest

dr = pytest.importorskip("drjit")

from mi_amr import AMRVolume  # noqa: E402
from test_device_prep import _same_tree  # noqa: E402


def _records(volume, shift=(0.0, 0.0, 0.0), fields=None):
    """The grid records of ``volume``, origins moved by ``shift`` (world), with ``fields``
    (a function of a grid's fields) instead of its own."""
    return [{"level": g.level, "origin": tuple(np.add(g.origin, shift)), "spacing": g.spacing,
             "fields": (fields or dict)(g.fields)} for g in volume.grids]


def _swirled(f):
    """Other velocities on the same grid (another time step)."""
    return {"vx": 1.3 * f["vy"], "vy": f["vz"] - 0.2 * f["vx"], "vz": f["vx"]}


@pytest.fixture(scope="module")
def steps(tmp_path_factory):
    """Files of the small wake: a step, another step on its grids, the same grids moved by a
    coarse cell, and the same grids listed in another order."""
    from mi_amr.synthetic import datasets

    folder = tmp_path_factory.mktemp("steps")
    wake = datasets.sphere_wake("small", progress=False).select_fields(["vx", "vy", "vz"])
    h0 = wake.grids[0].spacing[0]
    made = {"a": wake,
            "b": AMRVolume.from_grids(_records(wake, fields=_swirled)),
            "moved": AMRVolume.from_grids(_records(wake, shift=(h0, 0.0, 0.0))),
            "reordered": AMRVolume.from_grids(_records(wake)[::-1])}
    paths = {}
    for name, volume in made.items():
        paths[name] = folder / f"{name}.npz"
        volume.save(paths[name])
    return paths


def _prepare(session, path, *fields, **kw):
    return session.prepare(path, *(fields or ("q_criterion", "speed")), m=dr.llvm.ad, **kw)


def _same_preparation(got, want):
    _same_tree(got.tree, want.tree)
    for basis in (True, False):
        np.testing.assert_array_equal(got.device.node_ranges(basis),
                                      want.device.node_ranges(basis))
    np.testing.assert_array_equal(got.device.brick_values.numpy(),
                                  want.device.brick_values.numpy())
    np.testing.assert_array_equal(got.volume.leaf_mask_flat(), want.volume.leaf_mask_flat())


def test01_a_step_of_the_same_grids_takes_the_kept_tree(steps, monkeypatch):
    """The second step's preparation says it reused the tree, shares the first's tree arrays,
    and equals a fresh preparation of that file (tree, leaf ranges, bricks, leaf masks); the
    same file with other fields does too."""
    from mi_amr.kernels.prepared import Preparations

    monkeypatch.setenv("MI_AMR_CACHE", "off")
    heard = []
    session = Preparations(report=heard.append)
    first = _prepare(session, steps["a"])
    assert not any("reused" in line for line in heard)
    heard.clear()
    second = _prepare(session, steps["b"])
    assert "  kd-tree of the same grids reused" in heard, heard
    assert not any(line.startswith("  kd-tree in") for line in heard), heard
    assert second.tree.node_code is first.tree.node_code
    _same_preparation(second, _prepare(Preparations(), steps["b"]))
    heard.clear()
    other_fields = _prepare(session, steps["a"], "speed", "q_criterion")
    assert "  kd-tree of the same grids reused" in heard, heard
    _same_preparation(other_fields, _prepare(Preparations(), steps["a"], "speed",
                                             "q_criterion"))


@pytest.mark.parametrize("other", ["moved", "reordered", "leaf size"])
def test02_other_grids_or_another_leaf_size_build_their_own(steps, monkeypatch, other):
    """Grids moved by a coarse cell (same shapes, levels and spacings), the same grids in
    another order, or another leaf size: the tree is built, and is that of a fresh
    preparation."""
    from mi_amr.kernels.prepared import LoadOptions, Preparations

    monkeypatch.setenv("MI_AMR_CACHE", "off")
    heard = []
    session = Preparations(report=heard.append)
    _prepare(session, steps["a"])
    heard.clear()
    path = steps["b" if other == "leaf size" else other]
    kw = {"how": LoadOptions(leaf_cells=16)} if other == "leaf size" else {}
    got = _prepare(session, path, **kw)
    assert not any("reused" in line for line in heard), heard
    assert any(line.startswith("  kd-tree in") for line in heard), heard
    _same_preparation(got, _prepare(Preparations(), path, **kw))


def test03_same_hierarchy_compares_every_column_grid_for_grid():
    """Equal for a volume and its own grids with other fields; not for one grid's origin,
    spacing or shape changed, or the grids in another order."""
    from test_kdtree import HIERARCHIES

    grids = HIERARCHIES["ratio2"]()
    vol = AMRVolume.from_grids(grids)
    assert vol.same_hierarchy(vol.with_fields({"g": [a * 2 for a in
                                                    (g.fields["f"] for g in vol.grids)]}))
    assert vol.same_hierarchy(AMRVolume.from_grids(HIERARCHIES["ratio2"]()))
    assert not vol.same_hierarchy(AMRVolume.from_grids(HIERARCHIES["ratio2"]()[::-1]))
    base = AMRVolume.from_grids(grids[:1])
    g = grids[0]
    for change in ({"origin": np.add(g["origin"], g["spacing"]).tolist()},
                   {"spacing": np.multiply(g["spacing"], 2).tolist()},
                   {"fields": {"f": g["fields"]["f"][:-1]}}):
        other = AMRVolume.from_grids([{**g, **change}])
        assert not base.same_hierarchy(other), change
    assert not vol.same_hierarchy(base)
