"""The AMReX plotfile reader on plotfiles written here (``tests/amrex_writer.py``), whole and
damaged: the checks that ``tests/test_amrex.py`` makes on the real samples, on a machine without
them (a fresh CI machine has no ``../shared``). Values are checked against the writer's own
formula, not against anything the reader computes.
"""

import os
import subprocess
import sys

import numpy as np
import pytest
from amrex_writer import DESCRIPTORS, LEVELS, NAMES, field_value, write_plotfile

import mi_amr
from mi_amr import AMRError


@pytest.fixture
def plotfile(tmp_path):
    return write_plotfile(tmp_path / "plt00000")


def _cell_d(root, level):
    return root / f"Level_{level}" / "Cell_D_00000"


def _replace(path, old: bytes, new: bytes):
    data = path.read_bytes()
    assert data.count(old) >= 1, (path, old)
    path.write_bytes(data.replace(old, new, 1))


@pytest.mark.parametrize("dtype", ["<f8", "<f4"])
def test01_values_are_the_writers_at_the_cell_centres(tmp_path, dtype):
    vol = mi_amr.load(write_plotfile(tmp_path / "plt", dtype=dtype))
    expected = np.float64 if dtype == "<f8" else np.float32
    assert sorted(vol.field_names) == sorted(NAMES)
    assert [g.level for g in vol.grids] == [0, 1, 1]
    for g in vol.grids:
        h = LEVELS[g.level]["dx"]
        axes = [g.origin[a] + (np.arange(g.shape[a]) + 0.5) * h for a in range(3)]
        x, y, z = np.meshgrid(*axes, indexing="ij")
        for name in NAMES:
            assert g.fields[name].dtype == expected
            np.testing.assert_allclose(g.fields[name], field_value(name, x, y, z),
                                       rtol=1e-6 if dtype == "<f4" else 1e-12)


def test02_a_truncated_fab_file_is_refused(plotfile):
    path = _cell_d(plotfile, 1)
    data = path.read_bytes()
    for size in (len(data) - 100, 40, 0):
        path.write_bytes(data[:size])
        with pytest.raises(AMRError, match=r"Level_1/Cell_D_00000: FAB \d+ .*truncated"):
            mi_amr.load(plotfile)


def test03_a_missing_cell_h_or_cell_d_is_named(plotfile):
    (plotfile / "Level_1" / "Cell_H").rename(plotfile / "Level_1" / "Cell_H.away")
    with pytest.raises(AMRError, match=r"Level_1/Cell_H: missing"):
        mi_amr.load(plotfile)
    (plotfile / "Level_1" / "Cell_H.away").rename(plotfile / "Level_1" / "Cell_H")
    _cell_d(plotfile, 1).unlink()
    with pytest.raises(AMRError, match=r"Level_1/Cell_D_00000: missing; .*Level_1/Cell_H puts "
                                       r"FAB \d+ in this file"):
        mi_amr.load(plotfile)


def test04_boxes_that_disagree_are_refused(plotfile):
    """A Cell_H box against the Header's grid, and a FAB's box against its Cell_H entry."""
    cell_h = plotfile / "Level_1" / "Cell_H"
    original = cell_h.read_bytes()
    _replace(cell_h, b"((4,4,4) (7,7,7) (0,0,0))", b"((4,4,4) (7,7,6) (0,0,0))")
    with pytest.raises(AMRError, match=r"Level_1/Cell_H: box 0 .*does not match grid 0"):
        mi_amr.load(plotfile)
    cell_h.write_bytes(original)
    _replace(_cell_d(plotfile, 1), b"((8,4,4) (11,7,7) (0,0,0))", b"((9,4,4) (12,7,7) (0,0,0))")
    with pytest.raises(AMRError, match=r"Level_1/Cell_D_00000: FAB 1 at byte \d+: FAB box "
                                       r"\(\(9,4,4\) \(12,7,7\) \(0,0,0\)\) differs from box 1"):
        mi_amr.load(plotfile)


def test05_a_component_count_that_disagrees_with_the_header_is_refused(plotfile):
    _replace(_cell_d(plotfile, 0), b"(0,0,0)) 2\n", b"(0,0,0)) 3\n")
    with pytest.raises(AMRError, match=r"Level_0/Cell_D_00000: FAB 0 at byte 0: the FAB holds 3 "
                                       r"component\(s\), but the plotfile Header lists 2 field"):
        mi_amr.load(plotfile)


def test06_a_fab_of_doubles_under_a_float_header_is_refused(plotfile):
    _replace(_cell_d(plotfile, 0), DESCRIPTORS["<f8"].encode(), DESCRIPTORS["<f4"].encode())
    with pytest.raises(AMRError, match=r"Level_0/Cell_D_00000: FAB 0 at byte 0: the FAB holds "
                                       r"\d+ data bytes, but its header declares box .* of "
                                       r"4-byte reals"):
        mi_amr.load(plotfile)


def _with_a_nan(plotfile):
    """``plotfile`` with one NaN: the sixth value of level 1's FAB 0's first component
    (``density`` of grid 1)."""
    path = _cell_d(plotfile, 1)
    data = bytearray(path.read_bytes())
    at = data.index(b"\n") + 1 + 8 * 5
    data[at:at + 8] = np.array([np.nan]).tobytes()
    path.write_bytes(bytes(data))
    return plotfile


def test07_a_nan_in_a_fab_is_refused_naming_it(plotfile):
    _with_a_nan(plotfile)
    with pytest.raises(AMRError, match=r"plt00000: grid 1 \(level 1, origin \(0\.25, 0\.25, "
                                       r"0\.25\)\): field 'density' has 1 non-finite value"):
        mi_amr.load(plotfile)
    vol = mi_amr.load(plotfile, allow_nonfinite=True)       # kept, as missing values
    assert np.isnan(vol.grids[1].fields["density"]).sum() == 1
    vol.save(plotfile.parent / "kept.npz")                  # a scene reads this one
    again = mi_amr.load(plotfile.parent / "kept.npz")
    assert np.isnan(again.grids[1].fields["density"]).sum() == 1


def test08_any_damaged_cell_h_line_gives_amr_error_or_a_volume(plotfile):
    """Each line of a Cell_H replaced by junk (the fuzz harness mutates the Header only)."""
    cell_h = plotfile / "Level_1" / "Cell_H"
    original = cell_h.read_text()
    lines = original.splitlines(keepends=True)
    for i in range(len(lines)):
        for junk in ("((x\n", "-1\n", "\n", "99999999999999999999\n"):
            cell_h.write_text("".join(lines[:i] + [junk] + lines[i + 1:]))
            try:
                mi_amr.load(plotfile)
            except AMRError as e:
                assert str(plotfile) in str(e)
    cell_h.write_text(original)
    mi_amr.load(plotfile)


def test09_a_fifo_as_fab_file_is_refused_without_blocking(plotfile):
    _cell_d(plotfile, 1).unlink()
    os.mkfifo(_cell_d(plotfile, 1))
    run = subprocess.run([sys.executable, "-m", "mi_amr", "info", str(plotfile)],
                         capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)
    assert run.returncode == 2, run.stderr
    assert "Level_1/Cell_D_00000: not a regular file" in run.stderr
    assert "Traceback" not in run.stderr


def test10_allow_nonfinite_keeps_nan_values_in_a_scene_and_on_the_command_line(
        plotfile, tmp_path, capsys):
    """A plotfile with a NaN renders from the command line with ``--allow-nonfinite``, which
    the scene made for it keeps as the ``allow_nonfinite`` parameter; without either the file
    is refused, naming the grid, the field and both ways to keep the values. The snapshot of
    the file read with NaN kept is not read back for a scene that refuses them."""
    from mi_amr import cli
    from mi_amr.kernels import snapshot

    _with_a_nan(plotfile)
    out, scene, bare = tmp_path / "nan.png", tmp_path / "nan.xml", tmp_path / "bare.xml"
    render = ["render", str(plotfile), "-o", str(out), "--resolution", "32", "24", "--spp", "1",
              "--field", "density"]
    with snapshot.using(str(tmp_path / "cache")):
        assert cli.main(render) == 2
        err = capsys.readouterr().err
        assert "grid 1 (level 1" in err and "field 'density' has 1 non-finite" in err
        assert "--allow-nonfinite" in err and "scene parameter allow_nonfinite" in err
        assert "Traceback" not in err and not out.exists()
        assert cli.main(render + ["--allow-nonfinite", "--save-scene", str(scene)]) == 0
        assert out.exists()
        assert '<boolean name="allow_nonfinite" value="true"/>' in scene.read_text()
        again = ["render", str(scene), "-o", str(tmp_path / "again.png"), "--spp", "1"]
        assert cli.main(again) == 0
        assert cli.main(again + ["--force", "--allow-nonfinite", "--field", "density"]) == 2
        err = capsys.readouterr().err
        assert f"{scene} is a scene file: --field, --allow-nonfinite apply to data files" in err
        assert "its amr_iso parameter allow_nonfinite" in err
        assert cli.main(again + ["--force", "--allow-nonfinite"]) == 2
        assert "--allow-nonfinite applies to data files only" in capsys.readouterr().err
        bare.write_text(scene.read_text().replace(
            '<boolean name="allow_nonfinite" value="true"/>', ""))
        assert cli.main(["render", str(bare), "-o", str(tmp_path / "bare.png")]) == 2
        assert "field 'density' has 1 non-finite" in capsys.readouterr().err
        assert cli.main(["info", str(plotfile), "--allow-nonfinite"]) == 0
        assert "density" in capsys.readouterr().out


def test11_a_series_colour_range_keeps_nan_values_where_the_scene_does(plotfile, tmp_path):
    """The colour range of a time series reads each file as its frames will: a scene with
    ``allow_nonfinite`` gets the range of the finite values of a plotfile (read a box at a
    time) and of an ``.npz`` file (a stretch at a time) holding a NaN; a scene without it
    leaves such a file out of the range (its frames fail, naming it)."""
    from mi_amr.workflows import movie

    _with_a_nan(plotfile)
    vol = mi_amr.load(plotfile, allow_nonfinite=True)
    values = np.concatenate([g.fields["density"].ravel() for g in vol.grids])
    want = (float(np.nanmin(values)), float(np.nanmax(values)))
    vol.allow_nonfinite = False                 # a file that does not allow its NaN
    npz = tmp_path / "nan.npz"
    vol.save(npz)
    for path in (plotfile, npz):
        with pytest.raises(AMRError, match="non-finite"):
            movie._file_range(path, "density")
        assert movie._file_range(path, "density", allow_nonfinite=True) == want
    scene = tmp_path / "scene.xml"
    made = mi_amr.plugin.autoscene.data_scene(plotfile, "density", 1.0, allow_nonfinite=True,
                                              color_field="density", colormap="viridis")
    scene.write_text(made.xml())
    assert movie.series_color_range([plotfile, npz], scene) == want
    scene.write_text(made.xml().replace('<boolean name="allow_nonfinite" value="true"/>', ""))
    assert movie.series_color_range([plotfile, npz], scene) is None


def test12_python_s_show_and_explore_keep_nan_values_when_asked(plotfile, tmp_path):
    """``mi_amr.show`` and ``mi_amr.explore`` of a plotfile holding a NaN: refused, naming the
    field, unless ``allow_nonfinite=True``."""
    _with_a_nan(plotfile)
    with pytest.raises(AMRError, match="field 'density' has 1 non-finite"):
        mi_amr.show(plotfile, "density", resolution=(16, 12), spp=1)
    image = mi_amr.show(plotfile, "density", resolution=(16, 12), spp=1, allow_nonfinite=True)
    assert image.size == (16, 12) and np.isfinite(image.numpy()).all()
    # as a scene reads a boolean: the string "false" keeps the refusal, anything else is named
    with pytest.raises(AMRError, match="field 'density' has 1 non-finite"):
        mi_amr.scene(plotfile, "density", allow_nonfinite="false")
    with pytest.raises(AMRError, match="parameter 'allow_nonfinite' must be true or false"):
        mi_amr.scene(plotfile, "density", allow_nonfinite="maybe")
    with pytest.raises(AMRError, match="field 'density' has 1 non-finite"):
        mi_amr.explore(plotfile, "density", out_dir=tmp_path)
    explorer = mi_amr.explore(plotfile, "density", out_dir=tmp_path, allow_nonfinite=True)
    try:
        assert explorer.url.startswith("http://127.0.0.1:")
    finally:
        explorer.close()
