"""Snapshots of prepared volumes on disk (mi_amr.kernels.snapshot): a second load reads back
exactly what the first one prepared, renders the same image, and never uses an entry that is
stale, unreadable or turned off; the folder stays within its size limit."""

import os
import shutil
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
    yield root


def prepare(path, cache=None):
    return prepared.prepare_file(path, "q_criterion", "speed", m=M,
                                 by=prepared.Preparations(cache=cache))


def host(prep):
    """Everything the kernels read, as NumPy arrays."""
    dev = prep.device
    out = {name: np.array(getattr(dev, name)) for name in
           ("brick_values", "brick_colors", "brick_table", "level_table", "values",
            "color_values", "node_code_split", "node_box", "leaf_lo", "leaf_grids", "node_ropes",
            "grid_offset", "level_geom")}
    out["ranges"] = np.array(dev.node_ranges(True))
    return out


def wake_scene(path, data, res: int = 48):
    """Write ``path``: the Q = 0.05 surface of the wake file ``data`` coloured by speed, seen
    from beside it at ``res`` x ``res`` with a directional light, through a box filter (no
    splats of neighbours summed in varying order: the same image, bit for bit, from the same
    volume)."""
    path.write_text(textwrap.dedent(f"""
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
                <film type="hdrfilm"><integer name="width" value="{res}"/>
                    <integer name="height" value="{res}"/><rfilter type="box"/></film>
            </sensor>
            <emitter type="directional"><vector name="direction" value="-0.3, 0.5, -1"/></emitter>
        </scene>"""))
    return path


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
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import load_scene

    preparations = register()

    xml = wake_scene(tmp_path / "scene.xml", data)
    images = []
    for _ in range(2):
        preparations.clear()            # a new process, as far as the integrator knows
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
    monkeypatch.setenv("MI_AMR_CACHE_GB", str(2.5 * max(sizes.values()) / 1e9))
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
        assert snapshot.limit_bytes() == int(snapshot.DEFAULT_LIMIT_GB * 1e9)


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


# ---------------------------------------------------------------------- issue 33: trust nothing

def snapshot_arrays(root, entry):
    return sorted(p.name for p in (root / entry).iterdir() if p.name.endswith(".arr"))


def mark(folder, age_s=None):
    """Make ``folder`` look like one of the cache's own folders (``age_s`` seconds old)."""
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder, os.O_RDONLY)
    try:
        snapshot_folder.write_marker(fd)
    finally:
        os.close(fd)
    if age_s is not None:
        then = time.time() - age_s
        for p in [*folder.iterdir(), folder]:
            os.utime(p, (then, then), follow_symlinks=False)


def tree_listing(folder):
    """Every path under ``folder`` (links not followed) with its size and contents' hash."""
    import hashlib

    out = {}
    for dirpath, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = os.path.join(dirpath, name)
            if os.path.islink(p):
                out[p] = ("link", os.readlink(p))
            elif os.path.isfile(p):
                out[p] = ("file", hashlib.sha256(open(p, "rb").read()).hexdigest())
            else:
                out[p] = ("dir",)
    return out


def test11_a_users_folders_in_the_cache_are_never_removed_nor_counted(data, cache, tmp_path,
                                                                      monkeypatch):
    """Issue 33 item 1: folders that do not carry the cache's marker (a user's ``sim/``, a
    key-named folder, a ``.tmp-`` folder, a link to a folder outside, a file) stay as they are
    when the cache evicts down to nothing, and do not count against its limit."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_text("the user's")
    cache.mkdir()
    (cache / "sim").mkdir()
    (cache / "sim" / "checkpoint.bin").write_bytes(b"\0" * 100_000)
    (cache / ("ab" * 16)).mkdir()
    (cache / ("ab" * 16) / "notes.txt").write_text("mine")
    (cache / ".tmp-user").mkdir()
    (cache / ".tmp-user" / "x").write_text("mine too")
    os.utime(cache / ".tmp-user", (0, 0))
    (cache / ("cd" * 16)).symlink_to(outside, target_is_directory=True)
    (cache / "README.txt").write_text("a file")
    before = tree_listing(cache) | tree_listing(outside)
    prepare(data)
    ours = [p for p in cache.iterdir() if (p / snapshot_folder.MARKER).is_file()]
    assert len(ours) == 1
    entry_gb = sum(f.stat().st_size for f in ours[0].rglob("*")) / 1e9
    after = tree_listing(cache) | tree_listing(outside)
    assert {p: v for p, v in before.items()} == {p: after[p] for p in before}
    # Entries of the cache's own do go (room for one entry: the new one replaces the old).
    monkeypatch.setenv("MI_AMR_CACHE_GB", str(1.5 * entry_gb))
    copy = tmp_path / "copy.npz"
    copy.write_bytes(data.read_bytes())
    prepare(copy)
    now = [p for p in cache.iterdir() if (p / snapshot_folder.MARKER).is_file()]
    assert len(now) == 1 and now != ours
    assert {p: after[p] for p in before} == {p: tree_listing(cache).get(p, tree_listing(
        outside).get(p)) for p in before}


def test12_a_planted_pickle_never_runs(data, cache, tmp_path):
    """Issue 33 item 2: no pickle is ever loaded from the cache. A pickle that would create a
    file when loaded, planted as ``meta.pkl`` in an entry and as an old-format entry under the
    key, never runs; the cache's code imports no pickle at all."""
    import ast
    import pickle

    sentinel = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.mkdir, (str(sentinel),))

    evil = pickle.dumps(Payload())
    key = snapshot.entry_key(data, "q_criterion", "speed", 64)
    old = cache / key
    old.mkdir(parents=True)
    (old / "meta.pkl").write_bytes(evil)
    (old / "pool0.npy").write_bytes(b"\0" * 256)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        first = prepare(data)
    assert not sentinel.exists() and "derive" in first.timings
    entry = next(p for p in cache.iterdir() if (p / snapshot_folder.MARKER).is_file())
    (entry / "meta.pkl").write_bytes(evil)
    assert "snapshot" in prepare(data).timings
    assert not sentinel.exists()
    for module in ("mi_amr/kernels/snapshot.py", "mi_amr/kernels/snapshot_folder.py",
                   "mi_amr/core/rawarrays.py"):
        tree = ast.parse(open(os.path.join(os.path.dirname(__file__), "..", module)).read())
        names = {a.name for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
                 for a in n.names} | {n.module for n in ast.walk(tree)
                                      if isinstance(n, ast.ImportFrom)}
        assert not names & {"pickle", "cPickle", "dill", "marshal", "shelve"}, module


@pytest.mark.parametrize("target", ["pool0.arr", "field2_0.arr", "tree.node_code.arr",
                                    "volume.origin.arr", "table2.arr", "meta.json"])
def test13_a_changed_byte_is_caught_and_prepared_afresh(data, cache, target):
    """Issue 33 item 3: one flipped bit anywhere in an entry's data (an array's values, its
    header, the metadata) is caught by the checksums: a warning naming the entry and the file,
    the entry removed and the volume prepared afresh -- the same arrays as the first time, never
    silently other ones."""
    want = host(prepare(data))
    (entry,) = entries(cache)
    path = cache / entry / target
    raw = bytearray(path.read_bytes())
    if target == "meta.json":       # a digit changed into another: still valid JSON
        at = raw.index(b'"count":') + len(b'"count":')
        raw[at] = ord("0") + (raw[at] - ord("0") + 1) % 10
    else:
        raw[len(raw) - 7] ^= 0x10
    path.write_bytes(bytes(raw))
    with pytest.warns(UserWarning, match=f"unreadable snapshot .*{entry}.*"
                                         f"({target.replace('.', '[.]')}|checksum)"):
        again = prepare(data)
    assert "derive" in again.timings
    assert_same(want, host(again))
    assert "snapshot" in prepare(data).timings


def test14_files_that_are_links_or_not_files_are_refused(data, cache, tmp_path):
    """Links pointing outside the cache are never read through nor their targets removed: an
    array file replaced by a link to a file outside, a FIFO planted as the metadata."""
    want = host(prepare(data))
    (entry,) = entries(cache)
    outside = tmp_path / "outside.arr"
    outside.write_bytes((cache / entry / "pool1.arr").read_bytes())
    (cache / entry / "pool1.arr").unlink()
    (cache / entry / "pool1.arr").symlink_to(outside)
    with pytest.warns(UserWarning, match="unreadable snapshot"):
        assert_same(want, host(prepare(data)))
    assert outside.is_file()
    (entry,) = entries(cache)
    (cache / entry / "meta.json").unlink()
    os.mkfifo(cache / entry / "meta.json")
    with pytest.warns(UserWarning, match="not a regular file"):
        assert_same(want, host(prepare(data)))


def _swap(mapping, a, b):
    mapping[a], mapping[b] = mapping[b], mapping[a]


def test15_metadata_of_the_wrong_types_is_refused(data, cache):
    """Every field of the metadata is checked: JSON that parses and carries a valid checksum
    but holds a wrong type or value is refused (warning, prepared afresh), never used."""
    import json
    import zlib

    want = host(prepare(data))
    edits = [lambda b: b["volume"].__setitem__("ratios", ["2", 2, 2]),
             lambda b: b["volume"].__setitem__("fields", []),
             lambda b: b["arrays"]["pool0"].__setitem__("dtype", "|O"),
             lambda b: b["arrays"]["pool0"].__setitem__("file", "../../outside"),
             lambda b: b["arrays"]["pool0"].__setitem__("shape", [-1]),
             lambda b: b["bricks"].pop(),
             lambda b: b.__setitem__("tree", {"$array": "nothing"}),
             lambda b: b.__setitem__("extra", 1),
             # the kd-tree's state: each entry of a built tree's type, axes and length
             lambda b: b["tree"].__setitem__("lattice_leaf_hi", {}),
             lambda b: b["tree"].__setitem__("depth", "x"),
             lambda b: b["tree"].__setitem__("leaf_cells", 2 ** 70),
             lambda b: b["tree"].__setitem__("lattice_root", {"$tuple": [1, 2]}),
             lambda b: b["tree"].__setitem__("lattice_leaf_hi", {"$array": "tree.leaf_grids"}),
             lambda b: b["tree"].__setitem__("node_ropes", {"$array": "tree.lattice_node_lo"}),
             lambda b: b["tree"].__setitem__("grid_lo", {"$array": "tree.lattice_node_lo"}),
             lambda b: b["tree"].pop("leaf_owner"),
             lambda b: _swap(b["tree"], "lattice_node_split", "leaf_owner"),    # rows
             lambda b: _swap(b["tree"], "node_ropes", "lattice_node_lo")]       # columns
    for edit in edits:
        # (The entry written after the last edit's refusal, whose array files are its own.)
        (entry,) = entries(cache)
        head, body = (cache / entry / "meta.json").read_bytes().split(b"\n", 1)
        parsed = json.loads(body)
        edit(parsed)
        text = json.dumps(parsed).encode()
        h = json.loads(head)
        h["crc32"] = zlib.crc32(text)
        (cache / entry / "meta.json").write_bytes(json.dumps(h).encode() + b"\n" + text)
        with pytest.warns(UserWarning, match="unreadable snapshot") as heard:
            assert_same(want, host(prepare(data)))
        assert not any("No such file" in str(w.message) for w in heard), \
            [str(w.message) for w in heard]         # refused for the edit, not a stale file
    (entry,) = entries(cache)
    (cache / entry / "meta.json").write_bytes(b'{"kind": ' + b"[" * 100_000)
    with pytest.warns(UserWarning, match="unreadable snapshot"):
        assert_same(want, host(prepare(data)))


def test16_a_plotfile_folder_with_broken_links_gets_a_key_and_renders(cache, tmp_path,
                                                                      caplog):
    """Issue 33 item 7: the key's file walk skips a dangling link and a loop of links (named
    in a debug message) and the folder is prepared, written and read back."""
    import logging
    import sys

    sys.path.insert(0, os.path.dirname(__file__))
    from amrex_writer import write_plotfile

    plt = write_plotfile(tmp_path / "plt00010")
    (plt / "dangling").symlink_to(tmp_path / "nowhere")
    (plt / "Level_0" / "loop").symlink_to(plt / "Level_0" / "loop")
    with caplog.at_level(logging.DEBUG, logger="mi_amr.snapshot"):
        key = snapshot.entry_key(plt, "density", "temp", 4)
    assert "dangling" in caplog.text and "loop" in caplog.text
    first = prepared.prepare_file(plt, "density", "temp", m=M)
    again = prepared.prepare_file(plt, "density", "temp", m=M)
    assert "snapshot" in again.timings and entries(cache) == [key]
    assert_same(host(first), host(again))


def test17_entries_follow_the_umask_in_a_private_root(data, tmp_path, monkeypatch):
    """A cache folder the cache makes is 0700; entries in it are written with the umask (a
    shared folder made beforehand keeps its own mode)."""
    root = tmp_path / "made" / "cache"
    monkeypatch.setenv("MI_AMR_CACHE", str(root))
    saved = os.umask(0o027)
    try:
        prepare(data)
    finally:
        os.umask(saved)
    assert root.stat().st_mode & 0o777 == 0o700
    (entry,) = entries(root)
    assert (root / entry).stat().st_mode & 0o777 == 0o750
    assert {f.stat().st_mode & 0o777 for f in (root / entry).iterdir()} == {0o640}
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o775)
    os.chmod(shared, 0o2775)
    monkeypatch.setenv("MI_AMR_CACHE", str(shared))
    saved = os.umask(0o002)
    try:
        prepare(data)
    finally:
        os.umask(saved)
    assert shared.stat().st_mode & 0o7777 == 0o2775
    (entry,) = entries(shared)
    assert {f.stat().st_mode & 0o777 for f in (shared / entry).iterdir()} == {0o664}


def test18_temporary_and_old_format_folders(data, cache, tmp_path, monkeypatch):
    """Temporary folders count against the limit: a fresh one of a live process stays, one a
    killed process left (its pid gone) or an old one goes, an unmarked one stays. Old-format
    entries (``meta.pkl`` and ``.npy`` files in a key-named folder) are never read and are
    removed in turn; one holding anything else is not the cache's and stays."""
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    mark(cache / ".tmp-live")
    (cache / ".tmp-live" / "pool0.arr").write_bytes(b"\0" * 50_000)
    mark(cache / ".tmp-killed")
    marker = cache / ".tmp-killed" / snapshot_folder.MARKER
    marker.write_text(marker.read_text().replace(f'"pid": {os.getpid()}', f'"pid": {dead}'))
    mark(cache / ".tmp-old", age_s=2 * snapshot_folder.STALE_TMP_S)
    (cache / ".tmp-unmarked").mkdir()
    old = cache / ("0123456789abcdef" * 2)
    old.mkdir()
    (old / "meta.pkl").write_bytes(b"not a pickle")
    (old / "field0_q.npy").write_bytes(b"\0" * 10)
    foreign = cache / ("fedcba9876543210" * 2)
    foreign.mkdir()
    (foreign / "meta.pkl").write_bytes(b"x")
    (foreign / "thesis.tex").write_text("mine")
    monkeypatch.setenv("MI_AMR_CACHE_GB", "0")
    prepare(data)
    names = {p.name for p in cache.iterdir()}
    assert {".tmp-live", ".tmp-unmarked", foreign.name} <= names
    assert not names & {".tmp-killed", ".tmp-old", old.name}
    assert (foreign / "thesis.tex").read_text() == "mine"


def test19_ctrl_c_while_a_snapshot_is_written_leaves_nothing_and_exits_130(data, tmp_path):
    """Issue 33 item 11 (Ctrl-C): SIGINT while the entry is written removes the temporary
    folder; the command line says one line and exits with 130, no traceback."""
    import subprocess
    import sys

    xml = wake_scene(tmp_path / "scene.xml", data, res=8)
    child = textwrap.dedent("""
        import os, signal, sys
        from mi_amr.core import rawarrays
        from mi_amr.cli import main
        write = rawarrays.write_array
        def interrupted(dir_fd, name, array):
            if name.startswith("pool"):
                os.kill(os.getpid(), signal.SIGINT)
            return write(dir_fd, name, array)
        rawarrays.write_array = interrupted
        sys.exit(main(["render", sys.argv[1], "-o", sys.argv[2]]))
        """)
    root = tmp_path / "cache"
    env = dict(os.environ, MI_AMR_CACHE=str(root), PYTHONPATH=os.pathsep.join(
        [os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
         os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", child, str(xml), str(tmp_path / "o.exr")],
                          capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "interrupted", proc.stderr
    assert "Traceback" not in proc.stderr and "KeyboardInterrupt" not in proc.stderr
    assert [p.name for p in root.iterdir()] == []


def test20_the_cache_stays_within_its_limit_after_every_load(data, cache, tmp_path,
                                                             monkeypatch):
    """The limit holds after every load, its leaf ranges added included: an entry larger than
    the whole limit is not kept (one warning naming the file), and the one just written goes
    last, only when it does not fit by itself."""
    def used():
        return sum(f.stat().st_size for f in cache.rglob("*") if f.is_file())

    prep = prepare(data)
    prep.search_ready(True)
    entry = used()
    shutil.rmtree(cache)
    monkeypatch.setenv("MI_AMR_CACHE_GB", str(1.5 * entry / 1e9))
    for i in range(3):
        copy = tmp_path / f"copy{i}.npz"
        copy.write_bytes(data.read_bytes())
        prepare(copy).search_ready(True)            # the ranges are added after the save
        assert 0 < used() <= 1.5 * entry
    monkeypatch.setenv("MI_AMR_CACHE_GB", str(0.5 * entry / 1e9))
    with pytest.warns(UserWarning, match=r"no snapshot kept: .*copy3.npz prepared takes"):
        copy = tmp_path / "copy3.npz"
        copy.write_bytes(data.read_bytes())
        prepare(copy).search_ready(True)
    assert used() <= 0.5 * entry
