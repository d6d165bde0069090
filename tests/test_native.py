"""mi_amr's own .npz format: exact round trips, partial reads, safe writes, clear refusals of
files that are not ours; and the `info` command that prints a file's summary."""

import os
import re
import subprocess
import sys
import zipfile

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
    original = np.lib.npyio.NpzFile.__getitem__

    def spy(self, key):
        read.append(key)
        return original(self, key)

    monkeypatch.setattr(np.lib.npyio.NpzFile, "__getitem__", spy)
    got = mi_amr.load(tmp_path / "v.npz", fields=["b"])
    assert got.field_names == ("b",)
    assert_same_volume(got, vol, fields=("b",))
    assert "field:b" in read and "field:a" not in read


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


def test13_damaged_member_is_refused(tmp_path):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("field:b.npy")
    data = bytearray(path.read_bytes())
    # Flip a byte in the middle of the field's values: the zip's CRC check catches it on read.
    data[info.header_offset + 30 + len(info.filename) + info.file_size // 2] ^= 0xFF
    path.write_bytes(bytes(data))
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
    assert out.strip() == mi_amr.load(path).summary()
    assert "3 level(s)" in out and "a" in out and "b" in out


def test18_info_with_fields_reads_only_those(tmp_path, capsys):
    path = tmp_path / "v.npz"
    mixed_volume().save(path)
    assert main(["info", str(path), "--fields", "b"]) == 0
    out = capsys.readouterr().out
    assert out.strip() == mi_amr.load(path, fields=["b"]).summary()
    assert "\n  b " in out and "\n  a " not in out


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
