"""The OpenVDB reader on .vdb files written by the real OpenVDB library.

The files are written by ``tests/vdb_writer.py``, run by the system Python (``/usr/bin/python3``)
with Debian's ``python3-openvdb``; OpenVDB's own ``vdb_tool`` (Debian ``libopenvdb-tools``)
re-encodes them with each compression and as a stream without grid offsets. Without an importable
OpenVDB the module is skipped; without ``vdb_tool`` the re-encoding tests are skipped, and
Blosc-compressed files (OpenVDB's default) are read only when the ``blosc`` package is installed.
Expected values are the writer's linear field at each cell centre, never the reader's output.
Voxel sizes 0.1, 0.05, 0.025 (not binary fractions) make values equal to float32 precision only.
"""

import importlib.util
import json
import re
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mi_amr
from mi_amr import AMRError
from mi_amr.readers import available_fields, vdb

SYSTEM_PYTHON = "/usr/bin/python3"
WRITER = Path(__file__).with_name("vdb_writer.py")
VDB_TOOL = shutil.which("vdb_tool")
HAS_BLOSC = importlib.util.find_spec("blosc") is not None
IMPORT_OPENVDB = "try:\n import pyopenvdb\nexcept ImportError:\n import openvdb"


def _has_openvdb() -> bool:
    try:
        run = subprocess.run([SYSTEM_PYTHON, "-c", IMPORT_OPENVDB], capture_output=True,
                             timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return run.returncode == 0


if not _has_openvdb():
    pytest.skip(f"{SYSTEM_PYTHON} cannot import OpenVDB's Python module (Debian: apt-get install "
                f"python3-openvdb; .ci/setup does this when it can)", allow_module_level=True)


# ---------------------------------------------------------------------- the test files

def components(x, y, z):
    """The writer's vector field (tests/vdb_writer.py); float grids take one component."""
    f = 1.0 + 2.0 * x + 3.0 * y - 5.0 * z
    return f, f + 100.0, -f


def grid_spec(kind, name, h, lo, shape, **extra):
    return {"type": kind, "name": name, "voxel_size": h, "lo": list(lo), "shape": list(shape),
            **extra}


def patch(h, lo, shape, **extra):
    """A float ``density`` and a vec3s ``v`` grid on one box."""
    return [grid_spec("float", "density", h, lo, shape, **extra),
            grid_spec("vec3s", "v", h, lo, shape, **extra)]


# Voxel i of level l covers [h_l i, h_l (i + 1)] (translation h_l / 2), so the level-0 box is
# [0, 0.8]^3, level 1 has two patches and level 2 one patch inside the first of them.
HIERARCHY = [*patch(0.1, (0, 0, 0), (8, 8, 8)),
             *patch(0.05, (2, 2, 2), (6, 4, 4)),
             *patch(0.05, (10, 10, 10), (4, 4, 4)),
             *patch(0.025, (6, 6, 6), (4, 4, 4))]
EXPECTED_GRIDS = [  # level, world origin, spacing, shape
    (0, (0.0, 0.0, 0.0), 0.1, (8, 8, 8)),
    (1, (0.1, 0.1, 0.1), 0.05, (6, 4, 4)),
    (1, (0.5, 0.5, 0.5), 0.05, (4, 4, 4)),
    (2, (0.15, 0.15, 0.15), 0.025, (4, 4, 4)),
]

SPECS = {
    "hierarchy": HIERARCHY,
    "half": [{**g, "half": True} for g in HIERARCHY],
    "components": [grid_spec("float", name, h, lo, shape, component=c)
                   for h, lo, shape in ((0.1, (0, 0, 0), (4, 4, 4)), (0.05, (2, 2, 2), (4, 4, 2)))
                   for c, name in enumerate(("vx", "vy", "vz"))],
    # Zeros (= the background) inside the box are inactive voxels; the box stays whole.
    "holes": [grid_spec("float", "density", 0.1, (0, 0, 0), (6, 6, 6),
                        zero_box=[[1, 1, 1], [3, 4, 2]])],
    # Zeros on the x = 0 face: with tolerance 0 they are inactive and the box shrinks.
    "edge": [grid_spec("float", "density", 0.1, (0, 0, 0), (6, 6, 6),
                       zero_box=[[0, 0, 0], [0, 5, 5]])],
    "edge_kept": [grid_spec("float", "density", 0.1, (0, 0, 0), (6, 6, 6),
                            zero_box=[[0, 0, 0], [0, 5, 5]], tolerance=-1)],
    # An active 128^3 tile (x < 128) beside an inactive one of value -3 that holds one active
    # voxel: OpenVDB splits it into 8^3 inactive tiles and one mask-compressed leaf.
    "tiles": [{"type": "float", "name": "c", "voxel_size": 0.125,
               "fills": [[[0, 0, 0], [127, 127, 127], 1.5, True],
                         [[128, 0, 0], [255, 127, 127], -3.0, False]],
               "sets": [[[130, 5, 6], 7.0]]}],
    "root_tile": [{"type": "float", "name": "c", "voxel_size": 1.0,
                   "fills": [[[0, 0, 0], [4095, 4095, 4095], 1.0, True]]}],
    # One tree, placed twice side by side (the second grid is written as an instance).
    "instance": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4)),
                 {"type": "float", "name": "density", "voxel_size": 0.1, "instance_of": 0,
                  "translation": [0.45, 0.05, 0.05]}],
    "ratio4": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4)),
               grid_spec("float", "density", 0.025, (4, 4, 4), (8, 4, 4))],
    "bool": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4)),
             grid_spec("bool", "mask", 0.1, (0, 0, 0), (4, 4, 4))],
    "not_a_chain": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4)),
                    grid_spec("float", "density", 0.03, (2, 2, 2), (4, 4, 4))],
    "rotated": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4),
                          matrix=[[0, 0.1, 0, 0], [-0.1, 0, 0, 0], [0, 0, 0.1, 0], [0, 0, 0, 1]])],
    "anisotropic": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4),
                              matrix=[[0.1, 0, 0, 0], [0, 0.2, 0, 0], [0, 0, 0.1, 0],
                                      [0, 0, 0, 1]])],
    # Voxels 0.1 x 0.2 x 0.1 refined by 2 on every axis (voxel i covers [s i, s (i + 1)]).
    "anisotropic_levels": [
        grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4),
                  matrix=[[0.1, 0, 0, 0], [0, 0.2, 0, 0], [0, 0, 0.1, 0], [0.05, 0.1, 0.05, 1]]),
        grid_spec("float", "density", 0.05, (2, 2, 2), (4, 4, 4),
                  matrix=[[0.05, 0, 0, 0], [0, 0.1, 0, 0], [0, 0, 0.05, 0],
                          [0.025, 0.05, 0.025, 1]])],
    # Refined by 2, 4 and 2 along x, y and z: no AMR level.
    "anisotropic_ratio": [
        grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4),
                  matrix=[[0.1, 0, 0, 0], [0, 0.2, 0, 0], [0, 0, 0.1, 0], [0.05, 0.1, 0.05, 1]]),
        grid_spec("float", "density", 0.05, (2, 2, 2), (4, 4, 4))],
    "misaligned": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4)),
                   grid_spec("float", "pressure", 0.1, (0, 0, 0), (4, 4, 3))],
    "name_clash": [grid_spec("vec3s", "v", 0.1, (0, 0, 0), (4, 4, 4)),
                   grid_spec("float", "v_x", 0.1, (0, 0, 0), (4, 4, 4))],
    "empty": [grid_spec("float", "density", 0.1, (0, 0, 0), (4, 4, 4)),
              {"type": "float", "name": "pressure", "voxel_size": 0.1}],
}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Every file of SPECS, written by OpenVDB in one run: ``{name: (path, compressions)}``,
    the compressions as OpenVDB's file_compression metadata of the grids."""
    folder = tmp_path_factory.mktemp("vdb")
    spec = {str(folder / f"{name}.vdb"): grids for name, grids in SPECS.items()}
    (folder / "spec.json").write_text(json.dumps(spec))
    run = subprocess.run([SYSTEM_PYTHON, str(WRITER), str(folder / "spec.json")],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    return {name: (folder / f"{name}.vdb", set(report[str(folder / f"{name}.vdb")]))
            for name in SPECS}


def recode(src: Path, codec: str, *, stream=False, half=False) -> Path:
    """``src`` rewritten by OpenVDB's vdb_tool with ``codec`` (none, zip, active, blosc), as a
    stream without grid offsets when ``stream``, with half floats when ``half``."""
    if VDB_TOOL is None:
        pytest.skip("vdb_tool (Debian libopenvdb-tools) is not installed; it re-encodes files")
    # Same file name in a folder per encoding, so error messages name the same file.
    dst = src.parent / f"{codec}{'_stream' if stream else ''}{'_half' if half else ''}" / src.name
    if not dst.exists():
        dst.parent.mkdir(exist_ok=True)
        args = [VDB_TOOL, "-read", str(src), "-write", f"codec={codec}"] + \
            (["bits=16"] if half else []) + ["stdout.vdb" if stream else str(dst)]
        run = subprocess.run(args, capture_output=True, timeout=60)
        assert run.returncode == 0, run.stderr.decode(errors="replace")
        if stream:
            dst.write_bytes(run.stdout)
    return dst


def readable(written, name) -> Path:
    """The file ``name`` in a compression this environment reads: as written when it is not
    Blosc or the blosc package is installed, otherwise re-encoded with zip."""
    path, compression = written[name]
    if HAS_BLOSC or not any("blosc" in c for c in compression):
        return path
    return recode(path, "zip")


def world_centres(grid):
    return np.meshgrid(*grid.cell_centers(), indexing="ij")


def check_hierarchy(volume, fields=("density", "v_x", "v_y", "v_z"), rtol=1e-6):
    """Levels, origins, spacings, shapes and values of the HIERARCHY volume (fields in file
    order, which vdb_tool reverses; requested fields in the order asked for)."""
    assert sorted(volume.field_names) == sorted(fields)
    assert volume.num_levels == 3 and volume.ratios == (2, 2)
    got = sorted(volume.grids, key=lambda g: (g.level, g.origin))
    assert len(got) == len(EXPECTED_GRIDS)
    for g, (level, origin, h, shape) in zip(got, EXPECTED_GRIDS):
        assert g.level == level and g.shape == shape
        np.testing.assert_allclose(g.origin, origin, atol=1e-12)
        np.testing.assert_allclose(g.spacing, (h, h, h), rtol=1e-12)
        expected = dict(zip(("v_x", "v_y", "v_z"), components(*world_centres(g))))
        expected["density"] = expected["v_x"]
        for name in fields:
            assert g.fields[name].dtype == np.float32
            np.testing.assert_allclose(g.fields[name], expected[name], rtol=rtol, atol=rtol)


# ---------------------------------------------------------------------- reading

def test01_recognises_vdb_files(written, tmp_path):
    path, _ = written["hierarchy"]
    assert vdb.is_vdb(path)
    other = tmp_path / "other.vdb"
    other.write_bytes(b"VDB?" + bytes(60))
    assert not vdb.is_vdb(other)
    assert not vdb.is_vdb(tmp_path)
    assert not vdb.is_vdb(tmp_path / "missing.vdb")


def test02_field_names_from_the_header(written):
    path, _ = written["hierarchy"]
    assert vdb.field_names(path) == ["density", "v_x", "v_y", "v_z"]
    assert available_fields(path) == ["density", "v_x", "v_y", "v_z"]
    header = vdb.read_header(path)
    assert header.has_grid_offsets and header.file_version >= vdb.MIN_FILE_VERSION
    assert [d.name for d in header.grids] == ["density", "v"] * 4


def test03_hierarchy_levels_boxes_and_values(written):
    path = readable(written, "hierarchy")
    volume = vdb.load(path)
    assert list(volume.field_names) == vdb.field_names(path)  # file order
    check_hierarchy(volume)


def test04_load_dispatches_to_the_vdb_reader(written):
    path = readable(written, "hierarchy")
    volume = mi_amr.load(path)
    check_hierarchy(volume)
    assert volume.source == str(path)
    with pytest.raises(AMRError, match="unknown option"):
        mi_amr.load(path, level=2)


@pytest.mark.parametrize("codec", ["none", "zip", "active", "blosc"])
def test05_every_compression(written, codec):
    if codec == "blosc" and not HAS_BLOSC:
        pytest.skip("the blosc package is not installed (pip install blosc)")
    check_hierarchy(vdb.load(recode(written["hierarchy"][0], codec)))


def test06_as_written_by_default(written):
    path, compression = written["hierarchy"]
    if any("blosc" in c for c in compression) and not HAS_BLOSC:
        pytest.skip(f"OpenVDB wrote {compression}; the blosc package is not installed")
    check_hierarchy(vdb.load(path))


@pytest.mark.parametrize("codec", ["none", "zip"])
def test07_stream_without_grid_offsets(written, codec):
    path = recode(written["hierarchy"][0], codec, stream=True)
    header = vdb.read_header(path)
    assert not header.has_grid_offsets
    assert sorted(vdb.field_names(path)) == ["density", "v_x", "v_y", "v_z"]
    check_hierarchy(vdb.load(path))
    check_hierarchy(vdb.load(path, fields=["v_y"]), fields=["v_y"])


def test08_half_floats(written):
    path = readable(written, "half")
    assert all(d.half for d in vdb.read_header(path).grids)
    check_hierarchy(vdb.load(path), rtol=1e-3)
    check_hierarchy(vdb.load(recode(written["hierarchy"][0], "none", half=True)), rtol=1e-3)


def test09_reads_only_the_requested_fields(written, tmp_path):
    """The grids of fields not asked for are not decoded: here their records are overwritten
    with bytes no decoder gets past (a load of every field fails on them), and the fields
    asked for still load, with their values."""
    path = readable(written, "hierarchy")
    header = vdb.read_header(path)
    assert header.has_grid_offsets

    def spoiled(name):
        data = bytearray(path.read_bytes())
        for d in header.grids:
            if d.name == name:
                data[d.grid_pos:d.end_pos] = b"\xff" * (d.end_pos - d.grid_pos)
        out = tmp_path / f"no_{name}" / path.name
        out.parent.mkdir()
        out.write_bytes(bytes(data))
        return out

    no_v, no_density = spoiled("v"), spoiled("density")
    check_hierarchy(vdb.load(no_v, fields=["density"]), fields=["density"])
    volume = mi_amr.load(no_density, fields=["v_z", "v_x"])
    assert volume.field_names == ("v_z", "v_x")
    check_hierarchy(volume, fields=["v_z", "v_x"])
    for spoilt, name in ((no_v, "v"), (no_density, "density")):
        with pytest.raises(AMRError, match=rf"grid '{name}.*ends early"):
            vdb.load(spoilt)
    with pytest.raises(AMRError, match=r"unknown field\(s\) \['pressure'\]; the file holds "
                                       r"\[.*'v_x'.*\]"):
        vdb.load(path, fields=["pressure"])


def test10_float_components_keep_their_names(written):
    path = readable(written, "components")
    volume = vdb.load(path)
    assert sorted(volume.field_names) == ["vx", "vy", "vz"] and volume.ratios == (2,)
    for g in volume.grids:
        for name, expected in zip(("vx", "vy", "vz"), components(*world_centres(g))):
            np.testing.assert_allclose(g.fields[name], expected, rtol=1e-6, atol=1e-6)


def test11_inactive_voxels_inside_the_box_keep_their_values(written):
    volume = vdb.load(readable(written, "holes"))
    (g,) = volume.grids
    assert g.shape == (6, 6, 6) and g.origin == pytest.approx((0, 0, 0), abs=1e-12)
    expected = components(*world_centres(g))[0]
    expected[1:4, 1:5, 1:3] = 0
    np.testing.assert_allclose(g.fields["density"], expected, rtol=1e-6, atol=1e-6)


def test12_the_box_is_the_active_voxels(written):
    (g,) = vdb.load(readable(written, "edge")).grids
    assert g.shape == (5, 6, 6) and g.origin == pytest.approx((0.1, 0, 0), abs=1e-12)
    (g,) = vdb.load(readable(written, "edge_kept")).grids
    assert g.shape == (6, 6, 6) and np.all(g.fields["density"][0] == 0)


def test13_tiles(written):
    (g,) = vdb.load(readable(written, "tiles")).grids
    assert g.shape == (131, 128, 128) and g.spacing == (0.125,) * 3
    assert g.origin == pytest.approx((0, 0, 0), abs=1e-12)
    expected = np.full(g.shape, 1.5, dtype=np.float32)
    expected[128:] = -3.0
    expected[130, 5, 6] = 7.0
    np.testing.assert_array_equal(g.fields["c"], expected)
    zipped = recode(written["tiles"][0], "none")
    np.testing.assert_array_equal(vdb.load(zipped).grids[0].fields["c"], expected)


def test14_instances_share_the_tree(written):
    volume = vdb.load(readable(written, "instance"))
    assert vdb.read_header(readable(written, "instance")).grids[1].instance_parent
    a, b = sorted(volume.grids, key=lambda g: g.origin)
    assert a.origin == pytest.approx((0, 0, 0), abs=1e-12)
    assert b.origin == pytest.approx((0.4, 0, 0), abs=1e-12)
    np.testing.assert_array_equal(a.fields["density"], b.fields["density"])
    np.testing.assert_allclose(a.fields["density"], components(*world_centres(a))[0],
                               rtol=1e-6, atol=1e-6)


def test15_ratio_four(written):
    volume = vdb.load(readable(written, "ratio4"))
    coarse, fine = sorted(volume.grids, key=lambda g: g.level)
    assert volume.ratios == (4,) and (coarse.level, fine.level) == (0, 1)
    assert fine.origin == pytest.approx((0.1, 0.1, 0.1), abs=1e-12) and fine.shape == (8, 4, 4)


# ---------------------------------------------------------------------- errors

def test16_unsupported_grid_type(written):
    path = readable(written, "bool")
    with pytest.raises(AMRError, match=r"bool\.vdb: grid 'mask' \(#\d, Tree_bool_5_4_3\).*"
                                       r"unsupported grid type.*fields=\['density'\]"):
        vdb.load(path)
    assert vdb.field_names(path) == ["density"]
    assert vdb.load(path, fields=["density"]).field_names == ("density",)


def test17_voxel_sizes_not_a_ratio_chain(written):
    with pytest.raises(AMRError, match=r"not_a_chain\.vdb: voxel size 0\.03 .*3\.33333 times "
                                       r"smaller.*must be 2 or 4"):
        vdb.load(readable(written, "not_a_chain"))


@pytest.mark.parametrize("name, message", [
    ("rotated", r"grid 'density' .*AffineMap.*rotates"),
])
def test18_unsupported_transforms(written, name, message):
    with pytest.raises(AMRError, match=f"{name}\\.vdb: {message}"):
        vdb.load(readable(written, name))


def test18b_voxels_that_are_not_cubes(written):
    """A voxel size per axis (a ScaleMap of 0.1, 0.2, 0.1) reads as cells of that size, one
    level or two refined by 2 on every axis, with OpenVDB's values at the voxel centres; a
    refinement that differs between the axes is refused, naming the sizes."""
    for name, levels in (("anisotropic", 1), ("anisotropic_levels", 2)):
        volume = vdb.load(readable(written, name))
        assert volume.num_levels == levels
        for g in volume.grids:
            np.testing.assert_allclose(g.spacing, np.array([0.1, 0.2, 0.1]) / 2 ** g.level,
                                       rtol=1e-12)
            np.testing.assert_allclose(g.fields["density"], components(*world_centres(g))[0],
                                       rtol=1e-6, atol=1e-6)
    fine = volume.grids[1] if volume.grids[1].level == 1 else volume.grids[0]
    np.testing.assert_allclose(fine.origin, (0.1, 0.2, 0.1), atol=1e-12)
    with pytest.raises(AMRError, match=r"anisotropic_ratio\.vdb: voxel size 0\.05 .* is "
                                       r"\(2, 4, 2\) times smaller .*same factor on every axis"):
        vdb.load(readable(written, "anisotropic_ratio"))


def test19_fields_of_one_patch_must_share_the_box(written):
    with pytest.raises(AMRError, match=r"misaligned\.vdb: grid '(pressure|density)'.*grid "
                                       r"'(density|pressure)'.*overlap without having the same "
                                       r"box.*tolerance=-1"):
        vdb.load(readable(written, "misaligned"))


def test20_names_and_empty_grids(written):
    with pytest.raises(AMRError, match=r"name_clash\.vdb: field 'v_x' is given both by a float "
                                       r"grid and by a component of a vector grid"):
        vdb.load(readable(written, "name_clash"))
    with pytest.raises(AMRError, match=r"empty\.vdb: grid 'pressure' .*no active voxels"):
        vdb.load(readable(written, "empty"))
    assert vdb.load(readable(written, "empty"), fields=["density"]).num_cells == 64


def test21_active_root_tile_is_too_big(written):
    with pytest.raises(AMRError, match=r"root_tile\.vdb: grid 'c'.*too big"):
        vdb.load(readable(written, "root_tile"))


def test22_wrong_magic(tmp_path):
    path = tmp_path / "fake.vdb"
    path.write_bytes(struct.pack("<q", 0x12345678) + bytes(100))
    with pytest.raises(AMRError, match=r"fake\.vdb: not an OpenVDB file"):
        vdb.load(path)
    with pytest.raises(AMRError, match=r"fake\.vdb: unrecognised format.*OpenVDB"):
        mi_amr.load(path)
    empty = tmp_path / "empty.vdb"
    empty.write_bytes(b"")
    with pytest.raises(AMRError, match=r"empty\.vdb: not an OpenVDB file"):
        vdb.load(empty)


@pytest.mark.parametrize("keep", [0.5, 0.9, 60])
def test23_truncated_file(written, tmp_path, keep):
    data = readable(written, "hierarchy").read_bytes()
    cut = tmp_path / "cut.vdb"
    cut.write_bytes(data[:int(keep * len(data)) if keep < 1 else keep])
    with pytest.raises(AMRError, match=r"cut\.vdb: .*(truncated|ends early)"):
        vdb.load(cut)


def test24_truncated_stream(written, tmp_path):
    stream = recode(written["hierarchy"][0], "zip", stream=True)
    data = stream.read_bytes()
    cut = tmp_path / "cut.vdb"
    cut.write_bytes(data[:len(data) - 100])
    last = vdb.read_header(stream).grids[-1]
    with pytest.raises(AMRError, match=re.escape(f"cut.vdb: {last.describe()}: ends early")):
        vdb.field_names(cut)


def test25_corrupt_compressed_data(written, tmp_path):
    src = recode(written["hierarchy"][0], "zip")
    data = bytearray(src.read_bytes())

    def first_leaf(d):
        # A leaf buffer: value mask (64 bytes), compression byte (0: all voxels active), the
        # int64 size of the zlib stream (negative: stored raw), then the stream.
        at = d.block_pos + 64
        return at, data[at] == 0 and struct.unpack_from("<q", data, at + 1)[0] > 0
    grid = next(d for d in vdb.read_header(src).grids if first_leaf(d)[1])
    at = first_leaf(grid)[0]
    data[at + 9:at + 13] = b"\xff\xff\xff\xff"  # the zlib header
    bad = tmp_path / "bad.vdb"
    bad.write_bytes(bytes(data))
    with pytest.raises(AMRError, match=re.escape(f"bad.vdb: {grid.describe()}: ") +
                       ".*cannot decompress"):
        vdb.load(bad)


def test26_blosc_needs_the_blosc_package(written, monkeypatch):
    path, compression = written["hierarchy"]
    if not any("blosc" in c for c in compression):
        path = recode(path, "blosc")
    monkeypatch.setitem(sys.modules, "blosc", None)  # makes `import blosc` fail
    with pytest.raises(AMRError, match=r"hierarchy\.vdb: grid '\w+\[\d\]'.*Blosc.*"
                                       r"pip install blosc"):
        vdb.load(path)


def test27_transform_maps():
    """Map decoding on hand-made map bytes (OpenVDB's Python module simplifies every linear
    transform, so it never writes these two maps)."""
    def cursor(map_type, values):
        name = map_type.encode()
        raw = struct.pack("<I", len(name)) + name + np.asarray(values, "<f8").tobytes()
        return vdb._Cursor(raw, 0, len(raw), "test")
    m = np.eye(4) * 0.5
    m[3] = (1.0, 2.0, 3.0, 1.0)
    m[0, 1] = 1e-17  # rounding left by a rotation by 2 pi
    s, t = vdb._read_transform(cursor("AffineMap", m.ravel()))
    assert s.tolist() == [0.5] * 3 and t.tolist() == [1.0, 2.0, 3.0]
    s, t = vdb._read_transform(cursor("TranslationMap", [1.0, 2.0, 3.0]))
    assert s.tolist() == [1.0] * 3 and t.tolist() == [1.0, 2.0, 3.0]
    s, t = vdb._read_transform(cursor("ScaleTranslateMap", [1.0, 2.0, 3.0, 0.1, 0.2, 0.1] +
                                      [0.0] * 12))
    assert s.tolist() == [0.1, 0.2, 0.1] and t.tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(AMRError, match="NonlinearFrustumMap.*not supported"):
        vdb._read_transform(cursor("NonlinearFrustumMap", []))
    assert vdb._read_transform(cursor("UniformScaleMap", [0.25] * 15))[0].tolist() == [0.25] * 3
