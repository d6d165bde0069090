"""A preparation for the basis blend alone (a scene whose reconstruction is ``basis``): its
brick pools are made and its fields' values dropped before the kd-tree is built, and it ranges,
renders and is snapshotted as one that keeps them; what needs the values says so."""

import gc
import json
import weakref
import zlib

import numpy as np
import pytest

dr = pytest.importorskip("drjit")

from mi_amr import AMRError, AMRVolume, KDTree  # noqa: E402
from mi_amr.kernels import prepared, ranges, snapshot  # noqa: E402
from mi_amr.kernels.device import DeviceVolume  # noqa: E402
from test_device_prep import with_missing  # noqa: E402
from test_kdtree import HIERARCHIES  # noqa: E402
from test_snapshot import cache, data, wake_scene  # noqa: E402,F401 (fixtures)

M = dr.llvm.ad
BASIS = prepared.LoadOptions(keep_fields=False)      # a scene of the basis blend's


def prepare(path, keep: bool, cache=None):
    how = prepared.LoadOptions(keep_fields=keep)
    return prepared.prepare_file(path, "q_criterion", "speed", m=M, how=how,
                                 by=prepared.Preparations(cache=cache))


def what_the_kernels_read(prep):
    dev = prep.device
    out = {name: np.array(getattr(dev, name)) for name in
           ("brick_values", "brick_colors", "brick_table", "level_table", "node_code_split",
            "node_box", "leaf_grids", "node_ropes", "grid_offset", "level_geom")}
    out["search"] = np.array(dev.node_search(True))
    return out


@pytest.mark.parametrize("hierarchy", sorted(HIERARCHIES))
def test01_the_brick_pools_ranges_are_the_values_ranges(hierarchy):
    """The basis blend's leaf ranges read from the brick pools are the ones read from the
    grids' values and leaf masks, bit for bit (missing values, +-inf and covered cells
    alike)."""
    vol = AMRVolume.from_grids(with_missing(HIERARCHIES[hierarchy](), 5), allow_nonfinite=True)
    tree = KDTree(vol, leaf_cells=4)
    dev = DeviceVolume(vol, tree, "f", m=M)
    want = ranges.leaf_ranges(M, tree, dev.values, "f", "basis")
    got = ranges.brick_leaf_ranges(M, tree, dev)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))
    assert np.isfinite(got[0]).mean() > 0.5
    got = ranges.brick_leaf_ranges(M, tree, dev, pairs=7)          # in many launches
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))


def test02_without_fields_frees_the_values_it_made_pools_of(data):
    """What :func:`prepared.without_fields` gives back holds no field value: once the caller
    drops the volume, its fields' arrays are freed (before the kd-tree is built)."""
    from mi_amr.readers import load

    volume, _ = prepared.needed_fields(load(data, fields=["vx", "vy", "vz"]), "q_criterion",
                                       "speed", m=M)
    watched = [weakref.ref(volume.grids[g].fields[n]) for g in (0, -1)
               for n in ("q_criterion", "speed")]
    volume, (bricks, value_ranges) = prepared.without_fields(volume, "q_criterion", "speed", M)
    gc.collect()
    assert volume.field_names == () or list(volume.field_names) == []
    assert all(w() is None for w in watched)
    assert set(value_ranges) == {"q_criterion", "speed"} and len(bricks[1]) == 2


def test03_a_preparation_without_fields_reads_as_one_with_them(data):
    """The same brick pools, tree and search records (its leaf ranges from the pools) and
    value ranges; no values; the finest-level reconstruction asked of it is one error."""
    kept, bare = prepare(data, True), prepare(data, False)
    assert kept.keeps_fields and not bare.keeps_fields
    assert bare.device.values is None and kept.device.values is not None
    want, got = what_the_kernels_read(kept), what_the_kernels_read(bare)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    for name in ("q_criterion", "speed"):
        assert bare.value_range(name) == kept.value_range(name)
    assert {"read", "derive", "tree", "device"} <= set(bare.timings)
    for ask in (lambda: bare.device.arrays(False), lambda: bare.device.node_ranges(False)):
        with pytest.raises(AMRError, match="keep_fields"):
            ask()


def test04_a_basis_scene_renders_the_same_image_without_the_values(data, variant, tmp_path):
    """The integrator of a basis-blend scene prepares its file without the values; the image
    is the one a preparation keeping them gives, bit for bit."""
    mi = variant
    from mi_amr.kernels import snapshot as snap
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import load_scene

    xml = wake_scene(tmp_path / "scene.xml", data, res=40)
    preparations = register()
    images, kept = [], []
    try:
        with snap.using("off"):
            for keep in (False, True):
                preparations.clear()
                preparations.keep_fields = keep
                scene = load_scene(xml)
                kept.append(scene.integrator().prep.keeps_fields)
                images.append(np.array(mi.render(scene, seed=0)))
                del scene
    finally:
        preparations.keep_fields = False
        preparations.clear()
    assert kept == [False, True]
    np.testing.assert_array_equal(images[0], images[1])
    assert np.count_nonzero(images[0]) > 0


def test05_a_snapshot_without_the_values_is_read_back_as_it_was(data, cache):
    """An entry of a preparation without values holds the pools, tree, ranges and value
    ranges; read back it is the same; a preparation that keeps the values never reads it."""
    first = prepare(data, False)
    want = what_the_kernels_read(first)                 # (its ranges join the entry)
    second = prepare(data, False)
    assert "snapshot" in second.timings and not second.keeps_fields
    got = what_the_kernels_read(second)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    for name in ("q_criterion", "speed"):
        assert second.value_range(name) == first.value_range(name)
    full = prepare(data, True)
    assert "snapshot" not in full.timings and full.keeps_fields


def test06_a_session_gives_a_kept_preparation_to_a_basis_scene_not_the_other_way(data):
    """A preparation that keeps the values serves a scene of the basis blend too; one without
    them does not serve a scene that needs them (it is prepared again)."""
    with snapshot.using("off"):
        session = prepared.Preparations()
        full = session.prepare(data, "q_criterion", "speed", m=M)
        assert full.keeps_fields
        assert session.prepare(data, "q_criterion", "speed", m=M, how=BASIS) is full
        session.clear()
        bare = session.prepare(data, "q_criterion", "speed", m=M, how=BASIS)
        assert not bare.keeps_fields
        again = session.prepare(data, "q_criterion", "speed", m=M)
        assert again is not bare and again.keeps_fields
        session.keep_fields = True
        session.clear()
        assert session.prepare(data, "q_criterion", "speed", m=M, how=BASIS).keeps_fields


@pytest.mark.parametrize("edit", ["drop", "names", "string", "three", "one more field"])
def test07_a_snapshot_without_values_is_refused_where_its_value_ranges_are_wrong(
        data, cache, edit):
    """The value ranges of an entry without values are checked as every other field of its
    metadata: refused (a warning, prepared afresh) where missing or of the wrong type, and
    an entry naming fields and value ranges both is refused too."""
    want = what_the_kernels_read(prepare(data, False))
    (entry,) = [p for p in cache.iterdir() if not p.name.startswith(".")]
    head, body = (entry / "meta.json").read_bytes().split(b"\n", 1)
    parsed = json.loads(body)
    ranges_of = parsed["value_ranges"]
    if edit == "drop":
        del parsed["value_ranges"]
    elif edit == "names":
        parsed["value_ranges"] = {"q_criterion": ranges_of["q_criterion"]}
    elif edit == "string":
        ranges_of["speed"] = ["0", 1.0]
    elif edit == "three":
        ranges_of["speed"] = [0.0, 1.0, 2.0]
    else:
        parsed["volume"]["fields"] = ["q_criterion", "speed"]
    text = json.dumps(parsed).encode()
    h = json.loads(head)
    h["crc32"] = zlib.crc32(text)
    (entry / "meta.json").write_bytes(json.dumps(h).encode() + b"\n" + text)
    with pytest.warns(UserWarning, match="unreadable snapshot"):
        again = prepare(data, False)
    assert "snapshot" not in again.timings
    got = what_the_kernels_read(again)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
