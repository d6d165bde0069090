"""mi_amr's own .npz format: exact round trips, partial reads, safe writes, clear refusals of
files that are not ours; and the `info` command that prints a file's summary."""

import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import mi_amr
from mi_amr import AMRError, AMRVolume
from mi_amr.cli import main
from conftest import reference_grids


def at(path):
    """Regex for the start of a message about ``path``."""
    return "^" + re.escape(str(path)) + ": "


def mixed_volume(allow_nonfinite=False):
    """The reference hierarchy with a float32 field ``a`` and a float64 field ``b`` of random
    values (all bits matter for the round trip), optionally with NaN/Inf cells."""
    rng = np.random.default_rng(7)
    grids = reference_grids(names=("a", "b"))
    for g in grids:
        shape = g["fields"]["a"].shape
        g["fields"]["a"] = rng.normal(size=shape).astype(np.float32)
        g["fields"]["b"] = rng.normal(size=shape)
    if allow_nonfinite:
        grids[1]["fields"]["b"][0, 0, 0] = np.nan
        grids[5]["fields"]["a"][1, 2, 3] = np.inf
    return AMRVolume.from_grids(grids, allow_nonfinite=allow_nonfinite)


def assert_same_volume(got, want, fields=None):
    fields = want.field_names if fields is None else fields
    assert got.field_names == tuple(fields)
    assert got.ratios == want.ratios
    assert got.allow_nonfinite == want.allow_nonfinite
    assert len(got.grids) == len(want.grids)
    for g, w in zip(got.grids, want.grids):
        assert (g.level, g.origin, g.spacing, g.shape) == (w.level, w.origin, w.spacing, w.shape)
        for name in fields:
            assert g.fields[name].dtype == w.fields[name].dtype
            np.testing.assert_array_equal(g.fields[name], w.fields[name])


# ---------------------------------------------------------------------- round trips

def test01_save_load_round_trip_is_exact(tmp_path):
    vol = mixed_volume()
    path = tmp_path / "v.npz"
    vol.save(path)
    got = mi_amr.load(path)
    assert_same_volume(got, vol)
    assert got.source == str(path)
    assert got.grids[0].fields["a"].dtype == np.float32
    assert got.grids[0].fields["b"].dtype == np.float64


def test01b_each_level_is_read_into_one_aligned_slice(tmp_path):
    """The reader lays a field out level by level, each level's values one aligned slice
    (which the device maps without copying), whatever order the file holds the grids in; the
    grids' values and order are the file's."""
    from mi_amr.core import levels
    from mi_amr.core.buffers import ALIGN

    grids = mixed_volume().grids
    shuffled = [grids[i].as_dict() for i in (5, 0, 3, 1, 7, 2, 6, 4)]    # levels interleaved
    vol = AMRVolume.from_grids(shuffled)
    vol.save(tmp_path / "v.npz")
    got = mi_amr.load(tmp_path / "v.npz")
    assert_same_volume(got, vol)
    for level in range(got.num_levels):
        for name in got.field_names:
            flat = levels.level_values(got, level, name)
            first = got.grids[levels.level_index(got, level).grids[0]].fields[name]
            assert flat.ctypes.data % ALIGN == 0 and flat.ctypes.data == first.ctypes.data
            np.testing.assert_array_equal(flat, np.concatenate(
                [got.grids[g].fields[name].ravel() for g in levels.level_index(got, level).grids]))


def test01c_level_buffers_give_each_level_a_buffer_of_its_own(tmp_path):
    """A field named in ``level_buffers`` is read into one aligned buffer per level (so that a
    level's arrays, once dropped, free their memory), the others into one buffer; the values
    are the same either way, grids shuffled across levels included."""
    from mi_amr.core import levels
    from mi_amr.core.buffers import ALIGN
    from mi_amr.readers import native

    def owner(a):
        while isinstance(a.base, np.ndarray):
            a = a.base
        return a

    grids = mixed_volume().grids
    vol = AMRVolume.from_grids([grids[i].as_dict() for i in (5, 0, 3, 1, 7, 2, 6, 4)])
    vol.save(tmp_path / "v.npz")
    got = native.load(tmp_path / "v.npz", level_buffers={"a"})
    assert_same_volume(got, vol)
    for name, split in (("a", True), ("b", False)):
        owners = [{id(owner(got.grids[g].fields[name]))
                   for g in levels.level_index(got, level).grids}
                  for level in range(got.num_levels)]
        assert all(len(o) == 1 for o in owners)
        assert len(set().union(*owners)) == (got.num_levels if split else 1)
        for level in range(got.num_levels):
            assert levels.level_values(got, level, name).ctypes.data % ALIGN == 0


def test02_allow_nonfinite_is_preserved(tmp_path):
    vol = mixed_volume(allow_nonfinite=True)
    vol.save(tmp_path / "v.npz")
    got = mi_amr.load(tmp_path / "v.npz")
    assert got.allow_nonfinite
    assert np.isnan(got.grids[1].fields["b"][0, 0, 0])
    assert np.isposinf(got.grids[5].fields["a"][1, 2, 3])
    assert_same_volume(got, vol)
    assert got.value_range("b") == vol.value_range("b")
    # And a file without non-finite values keeps refusing them.
    mixed_volume().save(tmp_path / "w.npz")
    assert not mi_amr.load(tmp_path / "w.npz").allow_nonfinite


def test03_round_trip_of_a_loaded_volume(tmp_path):
    vol = mixed_volume()
    vol.save(tmp_path / "a.npz")
    mi_amr.load(tmp_path / "a.npz").save(tmp_path / "b.npz")
    assert_same_volume(mi_amr.load(tmp_path / "b.npz"), vol)


def test04_file_holds_no_pickled_objects(tmp_path):
    mixed_volume().save(tmp_path / "v.npz")
    with np.load(tmp_path / "v.npz", allow_pickle=False) as archive:
        arrays = {k: archive[k] for k in archive.files}
    assert all(a.dtype != object for a in arrays.values())
    assert str(arrays["mi_amr_format"]) == "mi_amr-volume"
    assert {"field:a", "field:b"} <= set(arrays)


# ---------------------------------------------------------------------- partial reads

def test05_load_reads_only_the_requested_fields(tmp_path, monkeypatch):
    vol = mixed_volume()
    vol.save(tmp_path / "v.npz")
    read = []
    original = zipfile.ZipFile.open

    def spy(self, name, *args, **kwargs):       # every entry read goes through open
        read.append(getattr(name, "filename", name))
        return original(self, name, *args, **kwargs)

    monkeypatch.setattr(zipfile.ZipFile, "open", spy)
    got = mi_amr.load(tmp_path / "v.npz", fields=["b"])
    assert got.field_names == ("b",)
    assert_same_volume(got, vol, fields=("b",))
    assert "field:b.npy" in read and "field:a.npy" not in read


def test06_unknown_field_is_refused(tmp_path):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    with pytest.raises(AMRError, match=at(path) + r"unknown field\(s\) \['c'\]; the file holds "
                       r"\['a', 'b'\]"):
        mi_amr.load(path, fields=["a", "c"])


# ---------------------------------------------------------------------- safe writes

def test07_save_refuses_to_overwrite(tmp_path):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    before = path.read_bytes()
    other = AMRVolume.from_grids(reference_grids(names=("z",)))
    with pytest.raises(AMRError, match=at(path) + "file exists; pass overwrite=True"):
        other.save(path)
    assert path.read_bytes() == before
    other.save(path, overwrite=True)
    assert mi_amr.load(path).field_names == ("z",)


def test08_failed_save_leaves_no_partial_file(tmp_path, monkeypatch):
    def broken_savez(f, **arrays):
        f.write(b"PK\x03\x04 half an archive")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken_savez)
    vol = mixed_volume()
    with pytest.raises(OSError, match="disk full"):
        vol.save(tmp_path / "new.npz")
    assert os.listdir(tmp_path) == []

    # Replacing an existing file: the old file survives a failed save.
    monkeypatch.undo()
    vol.save(tmp_path / "old.npz")
    before = (tmp_path / "old.npz").read_bytes()
    monkeypatch.setattr(np, "savez", broken_savez)
    with pytest.raises(OSError, match="disk full"):
        vol.save(tmp_path / "old.npz", overwrite=True)
    assert os.listdir(tmp_path) == ["old.npz"]
    assert (tmp_path / "old.npz").read_bytes() == before


def test08b_saved_file_has_the_usual_permissions(tmp_path):
    """The temporary file the save renames is created 0600; the saved file must not be."""
    mask = os.umask(0o022)
    try:
        mixed_volume().save(tmp_path / "v.npz")
    finally:
        os.umask(mask)
    assert (tmp_path / "v.npz").stat().st_mode & 0o777 == 0o644


def test09_save_into_a_missing_folder_is_refused(tmp_path):
    with pytest.raises(AMRError, match="does not exist"):
        mixed_volume().save(tmp_path / "no" / "v.npz")


# ---------------------------------------------------------------------- files that are not ours

def test10_plain_npz_without_marker_is_refused(tmp_path):
    path = tmp_path / "plain.npz"
    np.savez(path, level=np.zeros(1), origin=np.zeros((1, 3)))
    with pytest.raises(AMRError, match=at(path) + "unrecognised format"):
        mi_amr.load(path)
    # The native reader itself, if called directly, says what is missing.
    from mi_amr.readers import native
    with pytest.raises(AMRError, match=at(path) + "not an mi_amr volume"):
        native.load(path)


def test11_text_file_and_missing_path_are_refused(tmp_path):
    text = tmp_path / "notes.npz"
    text.write_text("level 0\norigin 0 0 0\n")
    with pytest.raises(AMRError, match=at(text) + "unrecognised format"):
        mi_amr.load(text)
    missing = tmp_path / "nothing.npz"
    with pytest.raises(AMRError, match=at(missing) + "no such file"):
        mi_amr.load(missing)


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9, 0.999])
def test12_truncated_file_is_refused(tmp_path, keep):
    full = tmp_path / "full.npz"
    mixed_volume().save(full)
    data = full.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[:int(len(data) * keep)])
    with pytest.raises(AMRError, match=at(cut)):
        mi_amr.load(cut)


def flipped_copy(path, target, entry="field:b.npy"):
    """``path`` written to ``target`` with a byte in the middle of ``entry``'s values flipped:
    the zip's CRC check catches it when the entry is read."""
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(entry)
    data = bytearray(Path(path).read_bytes())
    data[info.header_offset + 30 + len(info.filename) + info.file_size // 2] ^= 0xFF
    Path(target).write_bytes(bytes(data))
    return target


def test13_damaged_member_is_refused(tmp_path):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    flipped_copy(path, path)
    with pytest.raises(AMRError, match=at(path) + "damaged mi_amr volume.*CRC"):
        mi_amr.load(path)
    # Reading only the intact field still works.
    assert mi_amr.load(path, fields=["a"]).field_names == ("a",)


def test14_marker_with_missing_entries_is_refused(tmp_path):
    good = tmp_path / "good.npz"
    mixed_volume().save(good)
    with np.load(good) as archive:
        arrays = {k: archive[k] for k in archive.files}
    for key in ("version", "shape", "field:b"):
        path = tmp_path / f"no-{key.replace(':', '-')}.npz"
        np.savez(path, **{k: v for k, v in arrays.items() if k != key})
        with pytest.raises(AMRError, match=at(path) + rf"mi_amr volume is missing entry .*{key}"):
            mi_amr.load(path)


def test15_wrong_version_and_wrong_sizes_are_refused(tmp_path):
    good = tmp_path / "good.npz"
    mixed_volume().save(good)
    with np.load(good) as archive:
        arrays = {k: archive[k] for k in archive.files}
    path = tmp_path / "v2.npz"
    np.savez(path, **{**arrays, "version": np.array(2)})
    with pytest.raises(AMRError, match=at(path) + "mi_amr volume format version 2"):
        mi_amr.load(path)
    path = tmp_path / "short.npz"
    np.savez(path, **{**arrays, "field:a": arrays["field:a"][:-1]})
    with pytest.raises(AMRError, match=at(path) + r"field 'a' holds \d+ values, the grids need"):
        mi_amr.load(path)


def test16_invalid_hierarchy_in_a_file_names_the_file(tmp_path):
    good = tmp_path / "good.npz"
    mixed_volume().save(good)
    with np.load(good) as archive:
        arrays = {k: archive[k] for k in archive.files}
    origin = arrays["origin"].copy()
    origin[1, 0] += 0.5                        # level-0 grid 1 off the lattice
    path = tmp_path / "bad.npz"
    np.savez(path, **{**arrays, "origin": origin})
    with pytest.raises(AMRError, match=at(path) + r"grid 1 \(level 0.*not on a cell face"):
        mi_amr.load(path)


# ---------------------------------------------------------------------- python -m mi_amr info

def test17_info_prints_the_summary(tmp_path, capsys):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    # The summary first, then each field's range, percentiles and suggested isovalues.
    assert out.startswith(mi_amr.load(path).summary() + "\n")
    assert "3 level(s)" in out and "\na: [" in out and "\nb: [" in out


def test18_info_with_fields_reads_only_those(tmp_path, capsys):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    assert main(["info", str(path), "--fields", "b"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(mi_amr.load(path, fields=["b"]).summary() + "\n")
    assert "\n  b " in out and "\n  a " not in out
    assert "\nb: [" in out and "\na: [" not in out


def test19_info_on_a_bad_path_is_one_error_line(tmp_path, capsys):
    missing = tmp_path / "missing.npz"
    assert main(["info", str(missing)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == [f"error: {missing}: no such file or folder"]


def test20_python_m_mi_amr_info_exit_status(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_text("not an archive")
    run = subprocess.run([sys.executable, "-m", "mi_amr", "info", str(bad)], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 2
    assert run.stdout == ""
    lines = run.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {bad}: ")
    assert "Traceback" not in run.stderr


# ---------------------------------------------------------------------- damaged and odd files

def saved_arrays(tmp_path):
    """The arrays of a saved file, to write variants of it with np.savez."""
    good = tmp_path / "good.npz"
    mixed_volume().save(good)
    with np.load(good) as archive:
        return {k: archive[k] for k in archive.files}


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9, 0.999])
def test21_truncated_file_is_reported_as_damaged(tmp_path, keep):
    """Cut before its zip directory, the file is still recognised (its first entry is the
    marker) and reported damaged, not as an unrecognised format."""
    full = tmp_path / "full.npz"
    mixed_volume().save(full)
    data = full.read_bytes()
    cut = tmp_path / "cut.npz"
    cut.write_bytes(data[:int(len(data) * keep)])
    with pytest.raises(AMRError, match=at(cut) + "damaged mi_amr volume"):
        mi_amr.load(cut)


def test22_damaged_zip_directory_and_unknown_compression_are_amr_errors(tmp_path):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    data = path.read_bytes()
    directory = data.find(b"PK\x01\x02")
    # The zip directory's first signature broken: zipfile raises BadZipFile.
    broken = tmp_path / "directory.npz"
    broken.write_bytes(data[:directory] + b"PK\x01\x03" + data[directory + 4:])
    with pytest.raises(AMRError, match=at(broken) + "damaged mi_amr volume"):
        mi_amr.load(broken)
    # Compression method 99 (AES) in the directory entry of 'level': NotImplementedError.
    with zipfile.ZipFile(path) as z:
        names = [i.filename for i in z.infolist()]
    k = names.index("level.npy")
    entry = directory
    for _ in range(k):
        entry = data.find(b"PK\x01\x02", entry + 4)
    method = tmp_path / "method.npz"
    method.write_bytes(data[:entry + 10] + (99).to_bytes(2, "little") + data[entry + 12:])
    with pytest.raises(AMRError, match=at(method) + "damaged mi_amr volume"):
        mi_amr.load(method)


def rezip(source, target, change):
    """Copy the archive ``source`` to ``target`` with ``change(name, data) -> data`` applied
    to every entry (CRCs recomputed, so only the change itself is damage)."""
    with zipfile.ZipFile(source) as z, zipfile.ZipFile(target, "w") as out:
        for name in z.namelist():
            out.writestr(name, change(name, z.read(name)))
    return target


@pytest.mark.parametrize("old, new", [
    (b"), }", b" , }"),          # an unclosed bracket: tokenize.TokenError
    (b"'shape'", b"'shape_'"),    # a key NumPy does not expect: ValueError
    (b"'<i4'", b"'<i9'"),         # no such dtype
    (b"(8,)", b"(9,)"),           # more values declared than stored
])
def test23_damaged_npy_header_is_an_amr_error(tmp_path, old, new):
    good = tmp_path / "v.npz"
    mixed_volume().save(good)
    path = rezip(good, tmp_path / "bad.npz",
                 lambda name, data: data.replace(old, new, 1) if name == "level.npy" else data)
    with pytest.raises(AMRError, match=at(path) + "damaged mi_amr volume"):
        mi_amr.load(path)


@pytest.mark.parametrize("key, value, message", [
    ("level", lambda a: a[:-1], r"entry 'origin' has 8 row\(s\) but 'level' has 7"),
    ("shape", lambda a: a[:-1], r"entry 'shape' has 7 row\(s\) but 'level' has 8"),
    ("level", lambda a: a.astype(np.float64), r"entry 'level' must be integers"),
    ("level", lambda a: np.int32(0), r"entry 'level' must be integers shaped \(G,\)"),
    ("origin", lambda a: a[:, :2], r"entry 'origin' must be numbers shaped \(G, 3\)"),
    ("shape", lambda a: -a, r"grid 0 has shape \[-4, -8, -8\]"),
    ("field_names", lambda a: np.arange(2), r"entry 'field_names' must be a list of names"),
    ("version", lambda a: np.array("1"), r"entry 'version' must be one integer"),
    ("allow_nonfinite", lambda a: np.array([True, False]),
     r"entry 'allow_nonfinite' must be one boolean"),
])
def test24_entries_of_the_wrong_kind_or_length_are_refused(tmp_path, key, value, message):
    """A ``level`` array shorter than ``shape`` no longer drops grids silently; wrong dtypes
    and negative shapes are AMRErrors, not IndexError or ValueError."""
    arrays = saved_arrays(tmp_path)
    path = tmp_path / "bad.npz"
    np.savez(path, **{**arrays, key: value(arrays[key])})
    with pytest.raises(AMRError, match=at(path) + message):
        mi_amr.load(path)


def test25_fields_may_be_one_name(tmp_path):
    path = tmp_path / "v.npz"
    vol = mixed_volume()
    vol.save(path)
    got = mi_amr.load(path, fields="b")
    assert got.field_names == ("b",)
    assert_same_volume(got, vol, fields=("b",))
    with pytest.raises(AMRError, match=at(path) + "no fields requested"):
        mi_amr.load(path, fields=[])


def test26_a_fifo_is_refused_without_blocking(tmp_path):
    """Opening a FIFO blocks until a writer comes: the readers and their format probes must
    not open one. Run in a child so a regression times out instead of hanging the tests."""
    fifo = tmp_path / "x.npz"
    os.mkfifo(fifo)
    code = ("import sys; from mi_amr.readers import vdb, native, amrex; "
            "p = sys.argv[1]; print(vdb.is_vdb(p), native.is_native(p), amrex.is_plotfile(p))")
    probe = subprocess.run([sys.executable, "-c", code, str(fifo)], capture_output=True,
                           text=True, timeout=60)
    assert probe.stdout.split() == ["False", "False", "False"], probe.stderr
    for command in (["info", str(fifo)], ["info", str(fifo), "--fields", "a"]):
        run = subprocess.run([sys.executable, "-m", "mi_amr", *command], capture_output=True,
                             text=True, timeout=60)
        assert run.returncode == 2, run.stderr
        assert run.stderr.splitlines() == [f"error: {fifo}: not a regular file or a folder (a "
                                           f"FIFO, socket or device); mi_amr reads data files "
                                           f"and plotfile folders"]
    with pytest.raises(AMRError, match=at(Path("/dev/null")) + "not a regular file"):
        mi_amr.load("/dev/null")


# ---------------------------------------------------------------------- streamed fields

def streamed(path, names, chunk_values=5):
    """Every chunk of ``names`` from a FieldStream of ``path``, joined per name."""
    from mi_amr.readers import stream_fields

    with stream_fields(path, names) as s:
        s.chunk_values = chunk_values
        parts = [[a.copy() for a in values] for values in s.chunks()]
    return [np.concatenate([p[i] for p in parts]) for i in range(len(names))], s


def test27_a_field_stream_gives_each_fields_row_in_file_order(tmp_path):
    """Chunks of 5 values (cutting grids anywhere) joined are each field's row of every
    grid's values, in the file's grid order, in its dtype; only the named fields are read."""
    vol = mixed_volume(allow_nonfinite=True)
    path = tmp_path / "v.npz"
    vol.save(path)
    (b, a), s = streamed(path, ["b", "a"])
    assert (s.names, s.dtypes, s.allow_nonfinite) == (["b", "a"], [np.float64, np.float32], True)
    for got, name in ((a, "a"), (b, "b")):
        want = np.concatenate([g.fields[name].ravel() for g in vol.grids])
        assert got.dtype == want.dtype
        np.testing.assert_array_equal(got, want)


def test28_a_field_stream_refuses_what_load_refuses(tmp_path):
    """Damage found while streaming (a flipped byte: the CRC; an entry longer than its header
    says; a short field) and non-finite values in a file that does not allow them end as one
    AMRError naming the file; a folder is not streamed (None); an unknown name is refused
    when the stream opens."""
    from mi_amr.readers import stream_fields

    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    flipped = flipped_copy(path, tmp_path / "flipped.npz")
    with pytest.raises(AMRError, match=at(flipped) + "damaged mi_amr volume.*CRC"):
        streamed(flipped, ["b"])
    assert streamed(flipped, ["a"])[0][0].size        # the intact field still streams
    longer = rezip(path, tmp_path / "longer.npz",
                   lambda name, d: d + b"\0" * 8 if name == "field:a.npy" else d)
    with pytest.raises(AMRError, match=at(longer) + "damaged mi_amr volume"):
        streamed(longer, ["a"])
    arrays = saved_arrays(tmp_path)
    short = tmp_path / "short.npz"
    np.savez(short, **{**arrays, "field:a": arrays["field:a"][:-1]})
    with pytest.raises(AMRError, match=at(short) + r"field 'a' holds \d+ values"):
        streamed(short, ["a"])
    with pytest.raises(AMRError, match=at(path) + ".*'nope'"):
        streamed(path, ["nope"])
    nan = tmp_path / "nan.npz"
    values = arrays["field:b"].copy()
    values[-3] = np.nan
    np.savez(nan, **{**arrays, "field:b": values})
    last = len(arrays["level"]) - 1
    for chunk in (5, 10 ** 6):      # (a chunk cut in the bad grid, one chunk of all grids)
        with pytest.raises(AMRError, match=at(nan) + f"grid {last}: field 'b' has non-finite"):
            streamed(nan, ["a", "b"], chunk)
    assert stream_fields(tmp_path, ["a"]) is None


# ---------------------------------------------------------------------- columns

def same_structure(got, want):
    """Two volumes alike in every grid, lattice number and kept column."""
    assert_same_volume(got, want)
    for g, w in zip(got.grids, want.grids):
        assert (type(g.origin), type(g.spacing), type(g.shape)) == (tuple, tuple, tuple)
        assert all(type(x) is float for x in g.origin + g.spacing)
        assert all(type(x) is int for x in g.shape) and type(g.level) is int
    assert got.anchor.tolist() == want.anchor.tolist()
    np.testing.assert_array_equal(got._index_lo, want._index_lo)
    assert got._columns.keys() == want._columns.keys()
    for key in want._columns:
        assert got._columns[key].dtype == want._columns[key].dtype, key
        np.testing.assert_array_equal(got._columns[key], want._columns[key])


@pytest.mark.parametrize("allow", [False, True])
def test29_a_volume_from_columns_is_the_volume_from_grids(tmp_path, allow):
    """``AMRVolume.from_columns`` (what the reader builds a file's volume with) gives what
    ``from_grids`` gives for the same records: grids, lattice, the columns kept; with NaN
    cells where the file allows them, and with integer origins."""
    vol = mixed_volume(allow_nonfinite=allow)
    path = tmp_path / "v.npz"
    vol.save(path)
    got = mi_amr.load(path)
    want = AMRVolume.from_grids([g.as_dict() for g in got.grids], allow_nonfinite=allow,
                                source=str(path))
    same_structure(got, want)
    # Integer origins (a reader may hold them so): the same floats as from_grids makes.
    rng = np.random.default_rng(3)
    f0, f1 = rng.normal(size=(8, 8, 8)), rng.normal(size=(4, 4, 4))
    columns = {"level": np.array([0, 1]), "origin": np.array([[0, 0, 0], [2, 2, 2]]),
               "spacing": np.array([[1.0] * 3, [0.5] * 3]),
               "shape": np.array([[8, 8, 8], [4, 4, 4]])}
    records = [{"level": 0, "origin": (0, 0, 0), "spacing": 1.0, "fields": {"f": f0}},
               {"level": 1, "origin": (2, 2, 2), "spacing": 0.5, "fields": {"f": f1}}]
    same_structure(AMRVolume.from_columns(columns, {"f": [f0, f1]}, {"f": [f0, f1]}),
                   AMRVolume.from_grids(records))


def test30_columns_that_are_not_plain_get_from_grids_messages(tmp_path):
    """A NaN where the file allows none, a spacing <= 0 or a negative level: the volume from
    columns raises what ``from_grids`` raises for the same records, naming the grid."""
    vol = mixed_volume()
    base = {"level": np.array([g.level for g in vol.grids]),
            "origin": np.array([g.origin for g in vol.grids]),
            "spacing": np.array([g.spacing for g in vol.grids]),
            "shape": np.array([g.shape for g in vol.grids])}
    nan = {n: [g.fields[n].copy() for g in vol.grids] for n in vol.field_names}
    nan["b"][5][1, 1, 1] = np.nan
    plain = {n: [g.fields[n] for g in vol.grids] for n in vol.field_names}
    spacing = base["spacing"].copy()
    spacing[2] = -spacing[2]
    level = base["level"].copy()
    level[3] = -1
    cases = [(base, nan), ({**base, "spacing": spacing}, plain), ({**base, "level": level}, plain)]
    for columns, fields in cases:
        records = [{"level": int(columns["level"][i]), "origin": tuple(columns["origin"][i]),
                    "spacing": tuple(columns["spacing"][i]),
                    "fields": {n: fields[n][i] for n in fields}} for i in range(len(vol.grids))]
        with pytest.raises(AMRError) as want:
            AMRVolume.from_grids(records, source="f.npz")
        with pytest.raises(AMRError) as got:
            AMRVolume.from_columns(columns, fields, fields, source="f.npz")
        assert str(got.value) == str(want.value)
        assert re.search(r"grid \d", str(got.value)), str(got.value)


def test31_grid_offsets_are_pythons_sums_even_where_int64_would_overflow():
    """Each grid's first value in a field's row: NumPy's products for an ordinary index, the
    same numbers as Python's exact ones, and Python's where an index's shapes multiply past
    int64 (a damaged file, refused later for its entries' sizes, not read with wrapped
    offsets)."""
    import math
    from itertools import accumulate

    from mi_amr.readers.native import _offsets

    rng = np.random.default_rng(3)
    for shape in (rng.integers(1, 40, (3000, 3)), np.zeros((0, 3), dtype=np.int64),
                  np.array([[2 ** 31 - 1] * 3, [2, 3, 4]]), np.array([[2 ** 21] * 3] * 4)):
        want = [0, *accumulate(math.prod(int(n) for n in row) for row in shape)]
        got = _offsets(shape)
        assert got == want and all(type(x) is int for x in got)
