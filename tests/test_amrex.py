"""The AMReX plotfile reader on real plotfiles, on rewritten variants, and on broken copies.

The samples live outside the repository (../shared/data/amrex, see its SOURCE.md); without them
the module is skipped. Every check of values goes against something the reader does not use: the
min/max tables of ``Cell_H`` and an independent parse of a FAB written here.
"""

import re
import shutil
import stat
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import mi_amr
from mi_amr import AMRError
from mi_amr import cli
from mi_amr.readers import amrex

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "amrex"
if not DATA.is_dir():
    pytest.skip(f"AMReX sample plotfiles not found at {DATA} (see shared/data/amrex/SOURCE.md)",
                allow_module_level=True)

SAMPLES = ["plt_eb_3d", "example_plt_3d", "plt2_F"]
DESCRIPTORS = {
    "<f8": "((8, (64 11 52 0 1 12 0 1023)),(8, (8 7 6 5 4 3 2 1)))",
    ">f8": "((8, (64 11 52 0 1 12 0 1023)),(8, (1 2 3 4 5 6 7 8)))",
    "<f4": "((8, (32 8 23 0 1 9 0 127)),(4, (4 3 2 1)))",
    ">f4": "((8, (32 8 23 0 1 9 0 127)),(4, (1 2 3 4)))",
}


# ---------------------------------------------------------------------- independent helpers

def copy_plotfile(name, tmp_path) -> Path:
    """A writable copy of a sample (the originals are read-only)."""
    dst = tmp_path / name
    shutil.copytree(DATA / name, dst)
    for p in [dst, *dst.rglob("*")]:
        p.chmod(p.stat().st_mode | stat.S_IWUSR)
    return dst


def cell_h_tables(path):
    """Boxes (lo, hi inclusive), FabOnDisk entries and min/max tables of a Cell_H, parsed here."""
    lines = Path(path).read_text().splitlines()
    boxes = [[int(x) for x in re.findall(r"-?\d+", ln)] for ln in lines if ln.startswith("((")]
    fabs = [(ln.split()[1], int(ln.split()[2])) for ln in lines if ln.startswith("FabOnDisk:")]
    starts = [i for i, ln in enumerate(lines) if re.fullmatch(r"\d+,\d+", ln.strip())]
    n = len(fabs)

    def table(i):
        return np.array([[float(x) for x in ln.strip().rstrip(",").split(",")]
                         for ln in lines[i + 1:i + 1 + n]])
    return ([(b[0:3], b[3:6]) for b in boxes], fabs, table(starts[0]), table(starts[1]))


def raw_fab(path, offset):
    """Parse one little-endian double FAB by hand: header line, lo, hi and data ``[c, i, j, k]``."""
    with open(path, "rb") as f:
        f.seek(offset)
        line = f.readline()
        nums = [int(x) for x in re.findall(rb"-?\d+", line)]
        lo, hi, ncomp = nums[18:21], nums[21:24], nums[27]
        shape = tuple(h - l + 1 for l, h in zip(lo, hi))
        data = np.frombuffer(f.read(ncomp * int(np.prod(shape)) * 8), dtype="<f8")
    return line, lo, hi, data.reshape((ncomp,) + shape[::-1]).transpose(0, 3, 2, 1)


def rewrite_fabs(root, dtype="<f8", ngrow=0):
    """Rewrite every FAB of the plotfile ``root`` in ``dtype`` (descriptor changed to match),
    optionally with ``ngrow`` ghost cells of NaN around each box; Cell_H offsets follow."""
    for cell_h in sorted(root.glob("Level_*/Cell_H")):
        _, fabs, _, _ = cell_h_tables(cell_h)
        new_data, new_offsets = {}, []
        for name, offset in fabs:
            line, lo, hi, data = raw_fab(cell_h.parent / name, offset)
            if ngrow:
                data = np.pad(data, [(0, 0)] + [(ngrow, ngrow)] * 3, constant_values=np.nan)
                lo, hi = [x - ngrow for x in lo], [x + ngrow for x in hi]
            box = f"(({','.join(map(str, lo))}) ({','.join(map(str, hi))}) (0,0,0))"
            head = f"FAB {DESCRIPTORS[dtype]}{box} {data.shape[0]}\n".encode()
            body = data.transpose(0, 3, 2, 1).astype(dtype).tobytes()
            chunks = new_data.setdefault(name, [])
            new_offsets.append(sum(len(c) for c in chunks))
            chunks.append(head + body)
        for name, chunks in new_data.items():
            (cell_h.parent / name).write_bytes(b"".join(chunks))
        offsets = iter(new_offsets)
        text = re.sub(r"^(FabOnDisk: \S+) \d+$", lambda m: f"{m.group(1)} {next(offsets)}",
                      cell_h.read_text(), flags=re.M)
        if ngrow:
            text = re.sub(r"\A(\d+\n\d+\n\d+\n)0\n", rf"\g<1>{ngrow}\n", text)
        cell_h.write_text(text)


def replace_bytes(path, old: bytes, new: bytes, count=1):
    data = path.read_bytes()
    assert data.count(old) >= count, (path, old)
    path.write_bytes(data.replace(old, new, count))


def grids_of(vol, level):
    return [g for g in vol.grids if g.level == level]


# ---------------------------------------------------------------------- real plotfiles

def test01_samples_are_recognised():
    for name in SAMPLES:
        assert amrex.is_plotfile(DATA / name)
    assert not amrex.is_plotfile(DATA)
    assert not amrex.is_plotfile(DATA / "SOURCE.md")


@pytest.mark.parametrize("name, counts, shapes, fields", [
    ("plt_eb_3d", [1, 1], [(64, 32, 16), (64, 64, 32)], ["volFrac", "density"]),
    ("example_plt_3d", [1, 8, 64], [(8, 8, 8)] * 3, None),
    ("plt2_F", [1, 8, 64], [(8, 8, 8)] * 3, ["x_velocity", "density", "temp"]),
])
def test02_samples_load_natively(name, counts, shapes, fields):
    vol = mi_amr.load(DATA / name)
    header_names = (DATA / name / "Header").read_text().splitlines()
    nfields = int(header_names[1])
    assert vol.field_names == tuple(ln.strip() for ln in header_names[2:2 + nfields])
    if fields is not None:
        assert list(vol.field_names) == fields
    else:
        assert len(vol.field_names) == 38 and "mag_vort" in vol.field_names
    assert vol.num_levels == len(counts)
    for level, (count, shape) in enumerate(zip(counts, shapes)):
        grids = grids_of(vol, level)
        assert len(grids) == count
        assert all(g.shape == shape for g in grids)
        assert all(a.dtype == np.float64 for g in grids for a in g.fields.values())


@pytest.mark.parametrize("name", SAMPLES)
def test03_values_match_the_cell_h_min_max_tables(name):
    vol = mi_amr.load(DATA / name)
    for level in range(vol.num_levels):
        boxes, _, mins, maxs = cell_h_tables(DATA / name / f"Level_{level}" / "Cell_H")
        grids = grids_of(vol, level)
        assert len(grids) == len(boxes)
        for b, g in enumerate(grids):
            lo, hi = boxes[b]
            assert g.shape == tuple(h - l + 1 for l, h in zip(lo, hi))
            for c, field in enumerate(vol.field_names):
                np.testing.assert_allclose(g.fields[field].min(), mins[b, c], rtol=1e-14)
                np.testing.assert_allclose(g.fields[field].max(), maxs[b, c], rtol=1e-14)


def test04_values_match_an_independent_parse_of_one_fab():
    root = DATA / "example_plt_3d"
    vol = mi_amr.load(root)
    boxes, fabs, _, _ = cell_h_tables(root / "Level_2" / "Cell_H")
    b = 37
    name, offset = fabs[b]
    _, lo, hi, data = raw_fab(root / "Level_2" / name, offset)
    assert (lo, hi) == tuple(boxes[b])
    grid = grids_of(vol, 2)[b]
    for c, field in enumerate(vol.field_names):
        np.testing.assert_array_equal(grid.fields[field], data[c])
    # A hand-picked cell: index [i, j, k] is x, y, z, so x-neighbours are 8 bytes apart on disk.
    assert grid.fields["temp"][3, 1, 6] == data[vol.field_names.index("temp"), 3, 1, 6]


def test05_refinement_ratios_and_origins():
    vol = mi_amr.load(DATA / "plt_eb_3d")
    assert vol.ratios == (2,)
    (g0,) = grids_of(vol, 0)
    (g1,) = grids_of(vol, 1)
    np.testing.assert_allclose(g0.lo, [-0.02, 0.0, 0.0])
    np.testing.assert_allclose(g0.hi, [0.06, 0.04, 0.02])
    # The Header lists level 1 at x in [-0.02, 0.02]: half the domain, a real coarse/fine edge.
    np.testing.assert_allclose(g1.lo, [-0.02, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(g1.hi, [0.02, 0.04, 0.02], atol=1e-15)
    np.testing.assert_allclose(g1.spacing, [0.000625] * 3)
    assert vol.num_leaf_cells() == 64 * 64 * 32 + 32 * 32 * 16

    vol = mi_amr.load(DATA / "example_plt_3d", fields=["density"])
    assert vol.ratios == (2, 2)
    lo, hi = vol.grid_boxes()
    np.testing.assert_allclose(vol.bounds[0], 0, atol=1e-15)
    np.testing.assert_allclose(vol.bounds[1], 0.016)
    level2 = vol.levels == 2
    np.testing.assert_allclose(np.unique(np.round(lo[level2, 0], 12)), [0, 0.004, 0.008, 0.012])
    np.testing.assert_allclose(hi[level2] - lo[level2], 0.004)
    # Level 2 tiles the whole domain: 64 grids of 8^3 cells of 0.0005.
    assert vol.num_leaf_cells() == 32 ** 3


def test06_selected_fields_only(capsys):
    root = DATA / "example_plt_3d"
    full = mi_amr.load(root)
    two = mi_amr.load(root, fields=["temp", "mag_vort"])
    assert two.field_names == ("temp", "mag_vort")
    for g, h in zip(two.grids, full.grids):
        assert set(g.fields) == {"temp", "mag_vort"}
        np.testing.assert_array_equal(g.fields["temp"], h.fields["temp"])
        np.testing.assert_array_equal(g.fields["mag_vort"], h.fields["mag_vort"])
    assert two.nbytes * 19 == full.nbytes
    assert mi_amr.load(root, fields="density").field_names == ("density",)

    def peak(fields):
        tracemalloc.start()
        try:
            vol = mi_amr.load(root, fields=fields)
            return vol.nbytes, tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    nbytes_two, peak_two = peak(["temp", "mag_vort"])
    nbytes_all, peak_all = peak(None)
    with capsys.disabled():
        print(f"\nexample_plt_3d: 2 fields nbytes {nbytes_two:,} peak {peak_two:,}; "
              f"38 fields nbytes {nbytes_all:,} peak {peak_all:,}")
    assert peak_two < 0.15 * peak_all
    assert peak_two < 3 * nbytes_two


def test07_unknown_field_lists_the_available_ones():
    with pytest.raises(AMRError, match=r"example_plt_3d: unknown field\(s\) \['nope'\].*mag_vort"):
        mi_amr.load(DATA / "example_plt_3d", fields=["density", "nope"])
    with pytest.raises(AMRError, match="no fields requested"):
        mi_amr.load(DATA / "plt2_F", fields=[])


def test08_info_command_prints_two_levels(capsys):
    assert cli.main(["info", str(DATA / "plt_eb_3d")]) == 0
    out = capsys.readouterr().out
    assert "2 level(s), 2 grid(s)" in out
    assert "volFrac" in out and "density" in out


# ---------------------------------------------------------------------- rewritten variants

@pytest.mark.parametrize("dtype", [">f8", "<f4", ">f4"])
def test09_byte_order_and_real_size_follow_the_fab_header(tmp_path, dtype):
    original = mi_amr.load(DATA / "plt2_F")
    root = copy_plotfile("plt2_F", tmp_path)
    rewrite_fabs(root, dtype)
    assert (root / "Level_0" / "Cell_D_00000").read_bytes().startswith(
        f"FAB {DESCRIPTORS[dtype]}".encode())
    vol = mi_amr.load(root)
    expected_dtype = np.float64 if dtype.endswith("8") else np.float32
    for g, h in zip(vol.grids, original.grids):
        assert (g.origin, g.shape) == (h.origin, h.shape)
        for name in original.field_names:
            assert g.fields[name].dtype == expected_dtype
            assert g.fields[name].dtype.isnative
            np.testing.assert_array_equal(g.fields[name], h.fields[name].astype(expected_dtype))


def test10_ghost_cells_are_dropped(tmp_path):
    original = mi_amr.load(DATA / "plt_eb_3d")
    root = copy_plotfile("plt_eb_3d", tmp_path)
    rewrite_fabs(root, "<f8", ngrow=2)
    # The ghost cells are NaN: reading them would fail validation.
    vol = mi_amr.load(root, fields=["density"])
    for g, h in zip(vol.grids, original.grids):
        np.testing.assert_array_equal(g.fields["density"], h.fields["density"])


def test11_unsupported_byte_order_is_an_error(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    replace_bytes(root / "Level_0" / "Cell_D_00000", b"(8 7 6 5 4 3 2 1)", b"(2 1 4 3 6 5 8 7)")
    with pytest.raises(AMRError, match=r"Level_0/Cell_D_00000: FAB 0 at byte 0: byte order"):
        mi_amr.load(root)


# ---------------------------------------------------------------------- malformed plotfiles

def test12_truncated_cell_d(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    path = root / "Level_1" / "Cell_D_00000"
    data = path.read_bytes()
    path.write_bytes(data[:-100])
    with pytest.raises(AMRError, match=r"Level_1/Cell_D_00000: FAB 0 at byte 0: truncated"):
        mi_amr.load(root)
    # Asking only for the first component does not hide the damage.
    with pytest.raises(AMRError, match=r"Level_1/Cell_D_00000: .*truncated"):
        mi_amr.load(root, fields=["volFrac"])
    for size in (0, 40):
        path.write_bytes(data[:size])
        with pytest.raises(AMRError, match=r"Level_1/Cell_D_00000: FAB 0 .*truncated"):
            mi_amr.load(root)


def test13_missing_cell_h(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    (root / "Level_1" / "Cell_H").unlink()
    with pytest.raises(AMRError, match=r"Level_1/Cell_H: missing.*'Level_1/Cell'"):
        mi_amr.load(root)


def test14_cell_h_box_disagrees_with_the_header(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    replace_bytes(root / "Level_1" / "Cell_H", b"(63,63,31)", b"(63,63,15)")
    with pytest.raises(AMRError, match=r"Level_1/Cell_H: box 0 .*does not match grid 0"):
        mi_amr.load(root)


def test15_fab_box_disagrees_with_cell_h(tmp_path):
    root = copy_plotfile("plt2_F", tmp_path)
    # FAB 0 of level 1 is box ((0,0,0) (7,7,7)) at byte 0 of Cell_D_00001; same length, moved.
    replace_bytes(root / "Level_1" / "Cell_D_00001", b"((0,0,0) (7,7,7) (0,0,0))",
                  b"((1,0,0) (8,7,7) (0,0,0))")
    with pytest.raises(AMRError, match=r"Level_1/Cell_D_00001: FAB 0 at byte 0: FAB box "
                                       r"\(\(1,0,0\) \(8,7,7\) \(0,0,0\)\) differs from box 0"):
        mi_amr.load(root)


def test16_fab_shorter_than_its_box(tmp_path):
    root = copy_plotfile("plt2_F", tmp_path)
    _, fabs, _, _ = cell_h_tables(root / "Level_1" / "Cell_H")
    assert fabs[:2] == [("Cell_D_00001", 0), ("Cell_D_00001", 12374)]
    path = root / "Level_1" / "Cell_D_00001"
    data = path.read_bytes()
    path.write_bytes(data[:12374 - 8] + data[12374:])
    replace_bytes(root / "Level_1" / "Cell_H", b"Cell_D_00001 12374", b"Cell_D_00001 12366")
    with pytest.raises(AMRError, match=r"Level_1/Cell_D_00001: FAB 0 at byte 0: the FAB is "
                                       r"shorter .*puts the next FAB of this file at byte 12366"):
        mi_amr.load(root)


def test17_component_count_disagrees_with_the_header(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    replace_bytes(root / "Level_0" / "Cell_D_00000", b"(0,0,0)) 2\n", b"(0,0,0)) 3\n")
    with pytest.raises(AMRError, match=r"Level_0/Cell_D_00000: FAB 0 at byte 0: the FAB holds 3 "
                                       r"component\(s\), but the plotfile Header lists 2 field"):
        mi_amr.load(root)
    root = copy_plotfile("plt2_F", tmp_path / "b")
    cell_h = root / "Level_2" / "Cell_H"
    cell_h.write_text(cell_h.read_text().replace("1\n1\n3\n", "1\n1\n4\n", 1))
    with pytest.raises(AMRError, match=r"Level_2/Cell_H: line 3: 4 component\(s\), but the "
                                       r"Header lists 3"):
        mi_amr.load(root)


def test18_header_cut_short(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    header = root / "Header"
    lines = header.read_text().splitlines(keepends=True)
    for n in range(1, len(lines)):
        header.write_text("".join(lines[:n]))
        with pytest.raises(AMRError, match=r"plt_eb_3d/Header: ends early after"):
            amrex.load(root)
    header.write_text("".join(lines[:8]) + "0.06 0.0")
    with pytest.raises(AMRError, match=r"plt_eb_3d/Header: line 9: expected prob_hi"):
        amrex.load(root)


def test19_header_that_is_not_a_plotfile(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    header = root / "Header"
    header.write_text("Checkpoint version: 1\n" + header.read_text().split("\n", 1)[1])
    assert not amrex.is_plotfile(root)
    with pytest.raises(AMRError, match=r"plt_eb_3d/Header: line 1: first line 'Checkpoint "
                                       r"version: 1' is not an AMReX plotfile version"):
        amrex.load(root)
    with pytest.raises(AMRError, match=r"plt_eb_3d: unrecognised format.*AMReX plotfile"):
        mi_amr.load(root)
    header.unlink()
    with pytest.raises(AMRError, match=r"plt_eb_3d/Header: missing"):
        amrex.load(root)


def test20_missing_cell_d(tmp_path):
    root = copy_plotfile("plt2_F", tmp_path)
    (root / "Level_2" / "Cell_D_00002").unlink()
    with pytest.raises(AMRError, match=r"Level_2/Cell_D_00002: missing; .*Level_2/Cell_H puts "
                                       r"FAB \d+ in this file"):
        mi_amr.load(root)


def test21_two_dimensional_plotfile_is_refused(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    header = root / "Header"
    lines = header.read_text().splitlines(keepends=True)
    assert lines[4] == "3\n"
    lines[4] = "2\n"
    header.write_text("".join(lines))
    with pytest.raises(AMRError, match=r"plt_eb_3d/Header: line 5: the plotfile is 2-dimensional"):
        mi_amr.load(root)


def test22_any_damaged_line_gives_amr_error_or_a_volume(tmp_path):
    """Replacing any one line of the Header or a Cell_H by junk never escapes as another error."""
    root = copy_plotfile("plt_eb_3d", tmp_path)
    for path in (root / "Header", root / "Level_1" / "Cell_H"):
        original = path.read_text()
        lines = original.splitlines(keepends=True)
        for i in range(len(lines)):
            for junk in ("((x\n", "-1\n", "\n"):
                path.write_text("".join(lines[:i] + [junk] + lines[i + 1:]))
                try:
                    mi_amr.load(root)
                except AMRError as e:
                    assert str(root) in str(e)
        path.write_text(original)
    mi_amr.load(root)


def test23_info_command_reports_a_broken_plotfile(tmp_path, capsys):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    (root / "Level_1" / "Cell_D_00000").unlink()
    assert cli.main(["info", str(root)]) == 2
    assert "Level_1/Cell_D_00000: missing" in capsys.readouterr().err


# ---------------------------------------------------------------------- values that lie

def test24_fab_holding_doubles_under_a_float_header_is_refused(tmp_path):
    """A FAB whose header declares 4-byte reals but which holds doubles used to load with
    values around -3e12: each FAB must be exactly the size its header declares."""
    root = copy_plotfile("plt_eb_3d", tmp_path)
    path = root / "Level_0" / "Cell_D_00000"    # one FAB, at byte 0
    replace_bytes(path, DESCRIPTORS["<f8"].encode(), DESCRIPTORS["<f4"].encode())
    with pytest.raises(AMRError, match=r"Level_0/Cell_D_00000: FAB 0 at byte 0: the FAB holds "
                                       r"\d+ data bytes, but its header declares box .* of "
                                       r"4-byte reals .*does not match the data"):
        mi_amr.load(root)


def test25_header_index_beyond_32_bits_is_refused(tmp_path):
    """A domain lo of 10^26 (Header fuzzing) overflowed int64 in the grid checks: the grid was
    moved to y = -1.25e23 and accepted with only a NumPy RuntimeWarning."""
    root = copy_plotfile("plt_eb_3d", tmp_path)
    replace_bytes(root / "Header", b"((0,0,0) (63,31,15) (0,0,0))",
                  b"((0," + str(10 ** 26).encode() + b",0) (63,31,15) (0,0,0))")
    with pytest.raises(AMRError, match=r"plt_eb_3d/Header: line 11: level domain box .* has an "
                                       r"index beyond AMReX's 32-bit range"):
        with np.errstate(all="raise"):
            mi_amr.load(root)


def test26_header_messages_show_plain_numbers(tmp_path):
    root = copy_plotfile("plt_eb_3d", tmp_path)
    replace_bytes(root / "Header", b"0.06 0.04 0.02\n", b"-0.06 0.04 0.02\n")
    with pytest.raises(AMRError) as info:
        mi_amr.load(root)
    assert "domain [-0.02, 0.0, 0.0] .. [-0.06, 0.04, 0.02] is not a finite box" in \
        str(info.value)
    assert "np." not in str(info.value)


def test27_a_fifo_as_fab_file_is_refused(tmp_path):
    """A Cell_D that is a FIFO would block the reader; it is refused from its stat."""
    import os
    import subprocess
    import sys

    root = copy_plotfile("plt_eb_3d", tmp_path)
    (root / "Level_1" / "Cell_D_00000").unlink()
    os.mkfifo(root / "Level_1" / "Cell_D_00000")
    run = subprocess.run([sys.executable, "-m", "mi_amr", "info", str(root)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run.stderr
    assert "Level_1/Cell_D_00000: not a regular file" in run.stderr


@pytest.mark.parametrize("old, new, message", [
    (b"\n0.00125 0.00125 0.00125\n", b"\n0.00125 1e308 0.00125\n",
     r"refinement ratio 2 from level 0 to 1 disagrees with the cell sizes \[0\.00125, 1e\+308"),
    (b"\n-0.02 0.06\n", b"\n-0.02 1e308\n", r"box 0 .* does not match grid 0 of level 0"),
])
def test28_huge_header_numbers_are_refused_without_overflow_warnings(tmp_path, old, new,
                                                                     message):
    """Numbers near the float limit (Header fuzzing) overflow to inf in the checks; that must
    be an AMRError, not a NumPy RuntimeWarning on the way to it."""
    import warnings

    root = copy_plotfile("plt_eb_3d", tmp_path)
    replace_bytes(root / "Header", old, new)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(AMRError, match=message):
            mi_amr.load(root)
