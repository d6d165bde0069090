"""mi_amr.from_yt and the yt branch of mi_amr.load: datasets yt reads become the same volumes.

The AMReX samples (../shared/data/amrex, see its SOURCE.md) read natively and through yt must be
identical, grid by grid and bit by bit. The other checks build their data here: in-memory yt
datasets with known values, and a two-level Athena VTK dump (a format only yt reads, written
with NumPy alone) for the path-based branch of mi_amr.load.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

yt = pytest.importorskip("yt", reason="yt is not installed (pip install 'mi_amr[yt]')")

import mi_amr  # noqa: E402
from mi_amr import AMRError  # noqa: E402
from mi_amr import cli
from mi_amr.readers import available_fields  # noqa: E402

yt.set_log_level(40)  # yt's INFO lines for every dataset built here are noise in a test log

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "amrex"
needs_samples = pytest.mark.skipif(not DATA.is_dir(), reason=f"AMReX sample plotfiles not found "
                                   f"at {DATA} (see shared/data/amrex/SOURCE.md)")
SAMPLES = ["plt_eb_3d", "example_plt_3d", "plt2_F"]


# ---------------------------------------------------------------------- helpers

def by_position(volume) -> dict:
    """Grids keyed by (level, origin); the key must be unique."""
    out = {(g.level, g.origin): g for g in volume.grids}
    assert len(out) == len(volume.grids)
    return out


def assert_identical(native, other):
    """Same grids (matched by level and origin), spacings, shapes, fields and values, exactly."""
    assert len(other.grids) == len(native.grids)
    assert set(other.field_names) == set(native.field_names)
    theirs = by_position(other)
    for key, g in sorted(by_position(native).items()):
        assert key in theirs, f"no grid at level {key[0]}, origin {key[1]}"
        h = theirs[key]
        assert h.spacing == g.spacing and h.shape == g.shape
        for name in g.fields:
            assert h.fields[name].dtype == np.float64
            np.testing.assert_array_equal(h.fields[name], g.fields[name], err_msg=name)
    assert other.ratios == native.ratios
    assert other.num_leaf_cells() == native.num_leaf_cells()


def two_level_grid_data(value_of):
    """yt.load_amr_grids input: a 4^3 root of cells 0.25 on [0, 1]^3 and a 4^3 level-1 patch
    of cells 0.125 at (0.25, 0.25, 0.5); ``density`` is ``value_of(level, centres)``."""
    boxes = [(0, (0.0, 0.0, 0.0), 0.25), (1, (0.25, 0.25, 0.5), 0.125)]
    out = []
    for level, lo, h in boxes:
        axes = [lo[a] + (np.arange(4) + 0.5) * h for a in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        out.append({"left_edge": list(lo), "right_edge": [x + 4 * h for x in lo],
                    "level": level, "dimensions": [4, 4, 4],
                    "density": (value_of(level, centres), "g/cm**3")})
    return out


def ramp(level, centres):
    """Distinct on every cell of both levels: exact binary fractions, so comparisons are ==."""
    return 1000.0 * level + centres[..., 0] + 10 * centres[..., 1] + 100 * centres[..., 2]


def write_athena_vtk(path, level, origin, spacing, fields):
    """One grid of an Athena (C version) VTK dump: a text header, then per field
    ``SCALARS name float`` / ``LOOKUP_TABLE default`` and big-endian float32 values, x fastest.
    ``ORIGIN``/``DIMENSIONS`` describe the grid's nodes, so DIMENSIONS is cells + 1."""
    shape = next(iter(fields.values())).shape
    header = ("# vtk DataFile Version 3.0\n"
              f"PRIMITIVE vars at time= 0.000000e+00, level= {level}, domain= 0\n"
              "BINARY\nDATASET STRUCTURED_POINTS\n"
              "DIMENSIONS {} {} {}\n".format(*(n + 1 for n in shape))
              + "ORIGIN {!r} {!r} {!r}\n".format(*origin)
              + f"SPACING {spacing!r} {spacing!r} {spacing!r}\n"
              f"CELL_DATA {int(np.prod(shape))}\n")
    with open(path, "wb") as f:
        f.write(header.encode())
        for name, values in fields.items():
            f.write(f"SCALARS {name} float\nLOOKUP_TABLE default\n".encode())
            f.write(np.asarray(values, dtype=">f4").ravel(order="F").tobytes() + b"\n")


@pytest.fixture
def athena_dump(tmp_path):
    """A two-level Athena dump ``blast.0000.vtk`` with its level-1 grid in
    ``lev1/blast-lev1.0000.vtk`` (yt reads every grid's fields at the offsets of the root
    file's, so both grids have the same number of cells). Returns the root file's path."""
    (tmp_path / "lev1").mkdir()
    for level, lo, h, where in ((0, (0.0, 0.0, 0.0), 0.25, "blast.0000.vtk"),
                                (1, (0.25, 0.25, 0.5), 0.125, "lev1/blast-lev1.0000.vtk")):
        axes = [lo[a] + (np.arange(4) + 0.5) * h for a in range(3)]
        density = ramp(level, np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1))
        write_athena_vtk(tmp_path / where, level, lo, h,
                         {"density": density, "pressure": -density})
    return tmp_path / "blast.0000.vtk"


# ---------------------------------------------------------------------- AMReX: native == yt

@needs_samples
@pytest.mark.parametrize("name", SAMPLES)
def test01_amrex_samples_native_and_through_yt_are_identical(name):
    # Every field: plain names go to the on-disk ("boxlib", name) fields.
    native = mi_amr.load(DATA / name)
    through_yt = mi_amr.from_yt(yt.load(str(DATA / name)))
    assert_identical(native, through_yt)


@needs_samples
def test02_yt_field_tuples_and_plain_names_read_the_same_fields():
    path = DATA / "example_plt_3d"
    names = ["x_velocity", "y_velocity", "z_velocity", "mag_vort"]
    native = mi_amr.load(path, fields=names)
    ds = yt.load(str(path))
    by_tuple = mi_amr.from_yt(ds, [("boxlib", n) for n in names])
    assert by_tuple.field_names == tuple(names)
    assert_identical(native, by_tuple)
    assert_identical(native, mi_amr.from_yt(ds, names))
    # A yt field object names its tuple; a single name stands for a list of one.
    assert mi_amr.from_yt(ds, ds.fields.boxlib.mag_vort).field_names == ("mag_vort",)
    assert mi_amr.from_yt(ds, [ds.fields.boxlib.mag_vort]).field_names == ("mag_vort",)


@needs_samples
def test03_yt_derived_fields_come_in_yts_units():
    # ("gas", "density") is yt's alias of the on-disk density in g/cm^3, which is what AMReX
    # codes store (code units are CGS), so the values agree to the last bit or nearly.
    path = DATA / "plt2_F"
    native = mi_amr.load(path, fields=["density"])
    derived = mi_amr.from_yt(yt.load(str(path)), [("gas", "density")])
    theirs = by_position(derived)
    for key, g in by_position(native).items():
        np.testing.assert_allclose(theirs[key].fields["density"], g.fields["density"],
                                   rtol=1e-14, atol=0)


# ---------------------------------------------------------------------- in-memory datasets

def test04_two_level_in_memory_dataset_keeps_levels_origins_and_values():
    ds = yt.load_amr_grids(two_level_grid_data(ramp), [4, 4, 4])
    vol = mi_amr.from_yt(ds, ["density"])
    assert vol.num_levels == 2 and vol.ratios == (2,)
    coarse, fine = sorted(vol.grids, key=lambda g: g.level)
    assert (coarse.level, coarse.origin, coarse.spacing) == (0, (0.0, 0.0, 0.0), (0.25,) * 3)
    assert (fine.level, fine.origin, fine.spacing) == (1, (0.25, 0.25, 0.5), (0.125,) * 3)
    for g in vol.grids:
        centres = np.stack(np.meshgrid(*g.cell_centers(), indexing="ij"), axis=-1)
        np.testing.assert_array_equal(g.fields["density"], ramp(g.level, centres))
    # The fine patch covers 2^3 coarse cells; yt keeps them, so does the volume.
    assert vol.num_cells == 128 and vol.num_leaf_cells() == 128 - 8


def test05_unknown_field_lists_the_available_ones():
    ds = yt.load_amr_grids(two_level_grid_data(ramp), [4, 4, 4])
    with pytest.raises(AMRError, match=r"unknown field 'temperature'; on-disk fields: "
                                       r"\['density'\]"):
        mi_amr.from_yt(ds, ["temperature"])
    with pytest.raises(AMRError, match=r"unknown field \('stream', 'temperature'\); "
                                       r"on-disk fields: \[\('stream', 'density'\)\]"):
        mi_amr.from_yt(ds, [("stream", "temperature")])
    with pytest.raises(AMRError, match=r"'density'\] more than once"):
        mi_amr.from_yt(ds, ["density", ("stream", "density")])
    with pytest.raises(AMRError, match=r"a field must be a name or a yt field tuple"):
        mi_amr.from_yt(ds, [3])


def particles():
    n = 50
    rng = np.random.default_rng(0)
    return yt.load_particles({f"particle_position_{a}": rng.random(n) for a in "xyz"}
                             | {"particle_mass": np.ones(n)}, length_unit=1.0)


def octree():
    mask = np.array([8] + [0] * 8, dtype=np.uint8)  # a root split once into 8 leaves
    return yt.load_octree(octree_mask=mask, data={("gas", "density"): np.ones(8)},
                          bbox=np.array([[0.0, 1.0]] * 3))


def unstructured():
    coords = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    return yt.load_unstructured_mesh(np.array([[0, 1, 2, 3]]), coords,
                                     node_data={("connect1", "test"): np.ones((1, 4))})


@pytest.mark.parametrize("make, kind", [(particles, "particles only"), (octree, "an octree"),
                                        (unstructured, "an unstructured mesh")])
def test06_datasets_without_grids_are_refused(make, kind):
    with pytest.raises(AMRError, match=f"holds {kind}.*, not grids"):
        mi_amr.from_yt(make())


def test07_two_dimensional_dataset_and_non_dataset_are_refused():
    flat = yt.load_uniform_grid({"density": np.ones((4, 4, 1))}, (4, 4, 1))
    with pytest.raises(AMRError, match=r"is 2-D cartesian; mi_amr reads 3-D Cartesian grids"):
        mi_amr.from_yt(flat)
    with pytest.raises(AMRError, match=r"expected a yt dataset .*got str; for a path use "
                                       r"mi_amr.load\(path\)"):
        mi_amr.from_yt("plt00000")


# ---------------------------------------------------------------------- mi_amr.load's yt branch

def test08_load_reads_a_format_only_yt_reads(athena_dump):
    vol = mi_amr.load(athena_dump)
    assert vol.source == str(athena_dump)
    assert vol.field_names == ("density", "pressure") and vol.num_levels == 2
    assert_identical(vol, mi_amr.from_yt(yt.load(str(athena_dump))))
    for g in vol.grids:
        centres = np.stack(np.meshgrid(*g.cell_centers(), indexing="ij"), axis=-1)
        # Athena stores float32; the ramp's values are exact in float32.
        np.testing.assert_array_equal(g.fields["density"], ramp(g.level, centres))
        np.testing.assert_array_equal(g.fields["pressure"], -ramp(g.level, centres))
    assert available_fields(athena_dump) == ["density", "pressure"]
    assert mi_amr.load(athena_dump, fields=["pressure"]).field_names == ("pressure",)


def test09_load_passes_options_to_yt_and_reports_its_errors(athena_dump, capsys):
    with pytest.raises(AMRError, match=r"blast\.0000\.vtk: yt could not read it \(TypeError: "
                                       r".*no_such_option"):
        mi_amr.load(athena_dump, no_such_option=1)
    with pytest.raises(AMRError, match=r"blast\.0000\.vtk: unknown field 'speed'"):
        mi_amr.load(athena_dump, fields=["speed"])
    assert cli.main(["info", str(athena_dump)]) == 0
    out = capsys.readouterr()
    assert "2 level(s), 2 grid(s)" in out.out and "density" in out.out
    assert "yt" not in out.err  # yt's log lines are silenced for mi_amr.load


def test10_unrecognised_file_says_yt_does_not_read_it_either(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("level 0\n")
    with pytest.raises(AMRError, match=r"notes\.txt: unrecognised format; .*OpenVDB .vdb files; "
                                       r"yt does not recognise it either"):
        mi_amr.load(text)
    with pytest.raises(AMRError, match=r"unrecognised format"):
        available_fields(text)


def test11_without_yt_the_errors_say_how_to_install_it(monkeypatch, tmp_path):
    ds = yt.load_amr_grids(two_level_grid_data(ramp), [4, 4, 4])
    monkeypatch.setitem(sys.modules, "yt", None)  # "import yt" now fails
    with pytest.raises(AMRError, match=r"yt is not installed.*pip install 'mi_amr\[yt\]'"):
        mi_amr.from_yt(ds)
    text = tmp_path / "notes.txt"
    text.write_text("level 0\n")
    with pytest.raises(AMRError, match=r"unrecognised format; .*install yt "
                                       r"\(pip install 'mi_amr\[yt\]'\)"):
        mi_amr.load(text)


def test12_importing_mi_amr_does_not_import_yt():
    code = "import sys, mi_amr; mi_amr.from_yt; print('yt' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
    assert done.stdout.strip() == "False"


def test13_load_reads_an_hdf5_grid_format_through_yt(tmp_path):
    # GDF, yt's own grid format, stands in for the HDF5 codes (Enzo, FLASH, Chombo) whose
    # files cannot be written here; yt's writer turns the in-memory dataset into one.
    pytest.importorskip("h5py", reason="h5py is not installed (pip install 'mi_amr[yt]')")
    from yt.utilities.grid_data_format.writer import write_to_gdf

    ds = yt.load_amr_grids(two_level_grid_data(ramp), [4, 4, 4])
    path = tmp_path / "two_levels.gdf"
    write_to_gdf(ds, str(path), fields=[("stream", "density")])
    assert available_fields(path) == ["density"]
    assert_identical(mi_amr.from_yt(ds), mi_amr.load(path))
