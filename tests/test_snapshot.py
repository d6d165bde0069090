"""Snapshots of prepared volumes on disk (mi_amr.kernels.snapshot): a second load reads back
exactly what the first one prepared, renders the same image, and never uses an entry that is
stale, unreadable or turned off; the folder stays within its size limit."""

import os
import textwrap
import time
import warnings

import drjit as dr
import numpy as np
import pytest

from mi_amr.kernels import prepared, snapshot, snapshot_folder
from mi_amr.synthetic import datasets

M = dr.llvm.ad


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("snap")
    path = folder / "wake.npz"
    datasets.sphere_wake("small", progress=False).save(path)
    return path


@pytest.fixture
def cache(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("MI_AMR_CACHE", str(root))
    prepared._CACHE.clear()
    yield root
    prepared._CACHE.clear()


def prepare(path, cache=None):
    prepared._CACHE.clear()             # a new process, as far as the preparation knows
    return prepared.prepare_file(path, "q_criterion", "speed", m=M, cache=cache)


def host(prep):
    """Everything the kernels read, as NumPy arrays."""
    dev = prep.device
    out = {name: np.array(getattr(dev, name)) for name in
           ("brick_values", "brick_colors", "brick_table", "level_table", "values",
            "color_values", "node_code_split", "node_box", "leaf_lo", "leaf_grids", "node_ropes",
            "grid_offset", "level_geom")}
    out["ranges"] = np.array(dev.node_ranges(True))
    return out


def assert_same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def entries(root):
    return sorted(p.name for p in root.iterdir() if not p.name.startswith(".tmp-"))


def test01_a_second_load_reads_back_what_the_first_prepared(data, cache):
    first = prepare(data)
    assert "derive" in first.timings and "snapshot" not in first.timings
    want = host(first)                          # computes the ranges: added to the entry
    (entry,) = entries(cache)
    assert '"ranges":{"basis"' in (cache / entry / "meta.json").read_text()
    second = prepare(data)
    assert "snapshot" in second.timings and "derive" not in second.timings
    assert_same(want, host(second))
    assert "basis" in second.device.host_ranges      # brought by the snapshot, not recomputed
    for g, h in zip(first.volume.grids, second.volume.grids):
        assert (g.level, g.origin, g.spacing, g.shape) == (h.level, h.origin, h.spacing, h.shape)
        for name in g.fields:
            np.testing.assert_array_equal(g.fields[name], h.fields[name])
    for k, v in first.tree.__dict__.items():
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(v, second.tree.__dict__[k], err_msg=k)
    assert second.volume.num_levels == first.volume.num_levels
    assert second.tree.check("q_criterion")["leaves"] == first.tree.num_leaves


def test02_a_restored_volume_renders_the_same_image(data, cache, variant, tmp_path):
    mi = variant
    from mi_amr.plugin.scene import load_scene

    xml = tmp_path / "scene.xml"
    xml.write_text(textwrap.dedent(f"""
        <scene version="3.0.0">
            <integrator type="amr_iso">
                <string name="filename" value="{data}"/>
                <string name="field" value="q_criterion"/>
                <string name="color_field" value="speed"/>
                <string name="colormap" value="0: 0 0 1, 1: 1 0 0"/>
                <float name="isovalue" value="0.05"/>
            </integrator>
            <sensor type="perspective">
                <float name="fov" value="40"/>
                <transform name="to_world">
                    <lookat origin="2, -5, 2" target="1, 0, 0" up="0, 0, 1"/>
                </transform>
                <film type="hdrfilm"><integer name="width" value="48"/>
                    <integer name="height" value="48"/><rfilter type="box"/></film>
            </sensor>
            <emitter type="directional"><vector name="direction" value="-0.3, 0.5, -1"/></emitter>
        </scene>"""))
    images = []         # a box filter: no splats of neighbours summed in varying order
    for _ in range(2):
        prepared._CACHE.clear()
        scene = load_scene(xml)
        images.append(np.array(mi.render(scene, seed=0)))
        del scene
    assert len(entries(cache)) == 1
    np.testing.assert_array_equal(images[0], images[1])
    assert np.count_nonzero(images[0]) > 0


def test03_a_changed_file_is_prepared_again(data, cache, tmp_path):
    copy = tmp_path / "copy.npz"
    copy.write_bytes(data.read_bytes())
    prepare(copy)
    stamp = os.stat(copy).st_mtime_ns
    os.utime(copy, ns=(stamp + 10 ** 9, stamp + 10 ** 9))
    again = prepare(copy)
    assert "derive" in again.timings
    assert len(entries(cache)) == 2


def test04_an_unreadable_entry_is_dropped_and_the_volume_prepared_afresh(data, cache):
    want = host(prepare(data))
    (entry,) = entries(cache)
    pool = cache / entry / "pool0.arr"
    pool.write_bytes(pool.read_bytes()[: pool.stat().st_size // 2])     # truncated
    with pytest.warns(UserWarning, match="unreadable snapshot"):
        again = prepare(data)
    assert "derive" in again.timings
    assert_same(want, host(again))
    (entry2,) = entries(cache)                      # written anew
    assert (cache / entry2 / "pool0.arr").stat().st_size == len(
        (cache / entry2 / "pool0.arr").read_bytes())
    assert "snapshot" in prepare(data).timings


def test05_off_reads_and_writes_nothing(data, cache, monkeypatch):
    monkeypatch.setenv("MI_AMR_CACHE", "off")
    prepare(data)
    assert "derive" in prepare(data).timings
    monkeypatch.setenv("MI_AMR_CACHE", str(cache))
    prepare(data, cache=snapshot.SnapshotCache.off())     # the caller's own setting wins
    assert not cache.exists()


def test06_the_least_recently_used_entries_go_beyond_the_limit(data, cache, tmp_path,
                                                                monkeypatch):
    copies = []
    for i in range(3):
        copies.append(tmp_path / f"c{i}.npz")
        copies[-1].write_bytes(data.read_bytes())
        prepare(copies[-1])
        time.sleep(0.02)
    assert len(entries(cache)) == 3
    sizes = {e: sum(f.stat().st_size for f in (cache / e).iterdir()) for e in entries(cache)}
    stale = cache / ".tmp-crashed"          # the cache's own, left by a crash long ago
    stale.mkdir()
    fd = os.open(stale, os.O_RDONLY)
    snapshot_folder.write_marker(fd)
    os.close(fd)
    os.utime(stale / snapshot_folder.MARKER, (0, 0))
    os.utime(stale, (0, 0))
    # Room for two entries: using c0 again makes c1 the least recently used.
    assert "snapshot" in prepare(copies[0]).timings
    monkeypatch.setenv("MI_AMR_CACHE_GB", str(2.5 * max(sizes.values()) / 2 ** 30))
    fourth = tmp_path / "c3.npz"
    fourth.write_bytes(data.read_bytes())
    prepare(fourth)
    assert len(entries(cache)) == 2 and not stale.exists()
    assert "snapshot" in prepare(copies[0]).timings and "snapshot" in prepare(fourth).timings
    assert "derive" in prepare(copies[1]).timings


def test07_a_folder_that_cannot_be_written_only_costs_the_snapshot(data, tmp_path,
                                                                   monkeypatch):
    blocked = tmp_path / "not_a_folder"
    blocked.write_text("a file where the cache folder should be")
    monkeypatch.setenv("MI_AMR_CACHE", str(blocked / "cache"))
    with pytest.warns(UserWarning, match="could not write a snapshot"):
        p = prepare(data)
    assert "derive" in p.timings and blocked.read_text().startswith("a file")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert snapshot.SnapshotCache.from_env().load(
            snapshot.entry_key(data, "q_criterion", "speed", 64)) is None


def test08_data_files_beside_the_named_file_are_part_of_the_key(data, cache, tmp_path,
                                                               monkeypatch):
    """A file named after the data file (as Enzo's ``DD0010.cpu0000`` beside ``DD0010``)
    changes the key when it changes; an unrelated file does not. A limit that is not a number
    is warned about."""
    copy = tmp_path / "run.npz"
    copy.write_bytes(data.read_bytes())
    key = snapshot.entry_key(copy, "q_criterion", "speed", 4)
    (tmp_path / "other.txt").write_text("x")
    assert snapshot.entry_key(copy, "q_criterion", "speed", 4) == key
    (tmp_path / "run.npz.cpu0000").write_text("x")
    assert snapshot.entry_key(copy, "q_criterion", "speed", 4) != key
    assert snapshot.entry_key(copy, "q_criterion", None, 4) != \
        snapshot.entry_key(copy, "q_criterion", "speed", 4)
    monkeypatch.setenv("MI_AMR_CACHE_GB", "lots")
    with pytest.warns(UserWarning, match="MI_AMR_CACHE_GB='lots'"):
        assert snapshot.limit_bytes() == int(snapshot.DEFAULT_LIMIT_GB * 2 ** 30)


def test09_a_second_writer_of_the_same_entry_leaves_the_first_one(data, cache):
    """Two processes preparing the same data at once both write an entry: the second rename
    fails on the existing folder, its temporary folder is removed and the entry stays good."""
    p = prepare(data)
    (entry,) = entries(cache)
    before = sorted(f.name for f in (cache / entry).iterdir())
    assert snapshot.SnapshotCache.from_env().save(entry, p)
    assert entries(cache) == [entry]
    assert not [d for d in cache.iterdir() if d.name.startswith(".tmp-")]
    assert sorted(f.name for f in (cache / entry).iterdir()) == before
    assert "snapshot" in prepare(data).timings


def test10_a_restored_field_is_held_once(data, cache):
    """Read back, each field lies in one aligned buffer, level after level, which the device
    maps as it is (no second copy of the values)."""
    from mi_amr.core.buffers import joined

    prepare(data)
    restored = prepare(data)
    assert "snapshot" in restored.timings
    vol, dev = restored.volume, restored.device
    for name, arr in (("q_criterion", dev.values), ("speed", dev.color_values)):
        flat = joined([g.fields[name] for g in vol.grids], np.float32)
        assert flat is not None, name
        assert arr.numpy().ctypes.data == flat.ctypes.data, name
