"""A data file is a scene: ``render``/``movie`` FILE with no XML, the camera that frames the data
(checked through Mitsuba's own camera projection and one real render), the isovalue picked from
the histogram, ``--save-scene`` and :func:`mi_amr.scene` giving the same pixels, and the bad
inputs that each get one error naming them."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from conftest import grid
from mi_amr import AMRVolume
from mi_amr.cli import main
from mi_amr.core.framing import frame_box
from mi_amr.core.suggest import field_stats, suggest_isovalues

AMREX = Path(__file__).resolve().parents[2] / "shared" / "data" / "amrex"
PLOTFILES = sorted(p for p in AMREX.glob("*") if (p / "Header").is_file()) \
    if AMREX.is_dir() else []


@pytest.fixture(scope="module")
def mi():
    import mitsuba

    mitsuba.set_variant("llvm_ad_rgb")
    import mi_amr

    mi_amr.register()
    return mitsuba


def box_volume(lo, hi, cells=16, names=("f",)):
    """One grid over ``lo``..``hi`` whose field ``f`` is the max-norm distance from the centre
    in half extents: the isosurface ``f = c`` is the box shrunk by ``c`` about its centre."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    h = float((hi - lo).max()) / cells
    centre, half = (lo + hi) / 2, (hi - lo) / 2

    def fn(p):
        return np.max(np.abs(p - centre) / half, axis=-1)

    return AMRVolume.from_grids([grid(0, lo, hi, h, fn, names)])


def save(volume, path):
    volume.save(path)
    return str(path)


def projected_columns(mi, made, shrink=1.0, box=None):
    """The pixel columns (min, max) and rows (min, max) of the corners of ``box`` (default:
    the data's bounds) shrunk about its centre by ``shrink``, projected by Mitsuba's camera
    of the made scene."""
    d = made.as_dict()
    sensor = mi.load_dict(d["sensor"])
    lo, hi = (np.asarray(b, float) for b in (box or made_bounds(made)))
    c, half = (lo + hi) / 2, (hi - lo) / 2 * shrink
    corners = np.array([c + half * np.array([sx, sy, sz]) for sx in (-1, 1) for sy in (-1, 1)
                        for sz in (-1, 1)])
    to_world = d["integrator"]["to_world"]
    pts = [to_world @ mi.ScalarPoint3f(*p) for p in corners]
    it = mi.Interaction3f()
    it.p = mi.Point3f([p[0] for p in pts], [p[1] for p in pts], [p[2] for p in pts])
    ds, weight = sensor.sample_direction(it, mi.Point2f(0.5, 0.5))
    uv = np.array(ds.uv)
    assert np.all(np.array(weight)[0] > 0), "a corner is behind the camera"
    return uv[0].min(), uv[0].max(), uv[1].min(), uv[1].max()


def made_bounds(made):
    from mi_amr import load

    return load(made.path).bounds


SHAPES = [((0, 0, 0), (1, 1, 1)), ((0, 0, 0), (0.08, 0.04, 0.02)), ((-1, -1, 0), (1, 1, 8)),
          ((0, 0, 0), (8, 1, 1)), ((5, 5, 5), (6, 13, 6)), ((0, 0, 0), (4, 4, 0.25))]
ASPECTS = [(160, 120), (160, 90), (90, 160), (200, 80), (120, 120)]


def test01_the_camera_frames_the_surface_at_30_to_90_percent_of_the_width(mi, tmp_path):
    """The camera frames the box of the cells the isosurface passes through (here the data
    box shrunk by half about its centre, to within a cell): its corners cover 30-90 % of the
    image's width at any aspect, inside the image."""
    from mi_amr.plugin.autoscene import data_scene

    for i, (lo, hi) in enumerate(SHAPES):
        path = save(box_volume(lo, hi, cells=16), tmp_path / f"shape{i}.npz")
        cell = float((np.asarray(hi, float) - lo).max()) / 16
        centre, half = (np.add(lo, hi)) / 2, (np.subtract(hi, lo)) / 2
        for width, height in ASPECTS:
            made = data_scene(path, "f", 0.5, resolution=(width, height))
            f_lo, f_hi, what = made.framed
            assert what == "isosurface"
            assert np.all(f_lo <= centre - half / 2) and np.all(f_hi >= centre + half / 2)
            reach = 1.001 * cell            # (the cells beside the surface, within rounding)
            assert np.all(f_lo >= centre - half / 2 - reach) and \
                np.all(f_hi <= centre + half / 2 + reach), (f_lo, f_hi)
            u0, u1, v0, v1 = projected_columns(mi, made, box=(f_lo, f_hi))
            fill = (u1 - u0) / width
            where = f"box {lo}..{hi} at {width}x{height}"
            assert 0.3 <= fill <= 0.9, f"{where}: the data covers {fill:.0%} of the width"
            assert 0 <= u0 and u1 <= width and 0 <= v0 and v1 <= height, \
                f"{where}: the data leaves the image ({u0:.1f}..{u1:.1f}, {v0:.1f}..{v1:.1f})"
            assert (v1 - v0) / height <= 0.9, f"{where}: {(v1 - v0) / height:.0%} of the height"
            # The framing's own figure is the camera's projection, not a guess.
            assert made.framing.width_fill == pytest.approx(fill, abs=0.01), where



def test01b_a_small_feature_off_centre_is_framed_in_the_middle(mi, tmp_path, capsys):
    """A ball of radius 0.1 in a corner of a 2 x 1 x 1 box, on two levels: the camera frames
    the ball (the cells its isosurface or band passes through), not the box, and a render
    shows it across the middle of the image. Where the scene's values are not read (a
    derived field at a given isovalue), or the band's opacity is a 2D table, or nothing
    meets the isovalue, it frames the data's bounds."""
    from mi_amr.plugin.autoscene import data_scene
    from mi_amr.workflows.render import render_file

    centre = np.array([1.7, 0.25, 0.2])

    def ball(p):
        return np.linalg.norm(p - centre, axis=-1)

    def swirl(p):                           # a velocity whose speed is the distance again
        d = p - centre
        return np.stack([-d[..., 1], d[..., 0], 0 * d[..., 2]], axis=-1)

    names = ("f", "vx", "vy", "vz")

    def fields(p):
        return {"f": ball(p), **{n: swirl(p)[..., k] for k, n in enumerate(names[1:])}}

    grids = [grid(0, (0, 0, 0), (2, 1, 1), 1 / 16, lambda p: 0 * p[..., 0], names),
             grid(1, (1.5, 0, 0), (2, 0.5, 0.5), 1 / 32, lambda p: 0 * p[..., 0], names)]
    for g in grids:
        lo, h = np.asarray(g["origin"]), g["spacing"]
        shape = g["fields"]["f"].shape
        axes = [lo[a] + (np.arange(shape[a]) + 0.5) * h for a in range(3)]
        g["fields"] = fields(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1))
    path = save(AMRVolume.from_grids(grids), tmp_path / "ball.npz")
    made = data_scene(path, "f", 0.1, resolution=(96, 72), spp=1)
    lo, hi, what = made.framed
    assert what == "isosurface"
    assert np.all(lo <= centre - 0.1) and np.all(hi >= centre + 0.1), (lo, hi)
    assert np.all(hi - lo <= 0.2 + 2 / 16), (lo, hi)       # within a coarse cell each side
    band = data_scene(path, "f", 0.1, mode="volume", band_width=0.02).framed
    assert band[2] == "band" and np.all(band[0] <= lo) and np.all(band[1] >= hi)
    assert np.all(band[1] - band[0] <= 0.2 + 2 * 0.02 + 2 / 16)
    whole = AMRVolume.from_grids(grids).bounds
    for kind, kw in [("a 2D table", dict(mode="volume", transfer2d_blobs="0.1 0 0.01 1 1")),
                     ("no cell at 5", dict(isovalue=5.0)),
                     ("speed not derived", dict(field="speed", isovalue=0.1))]:
        kw = {"field": "f", "isovalue": 0.1, **kw}
        other = data_scene(path, kw.pop("field"), kw.pop("isovalue"), **kw).framed
        assert other[2] == "data", kind
        np.testing.assert_array_equal(np.array(other[:2]), np.array(whole), err_msg=kind)
    picked = data_scene(path, "speed").framed           # (its values read for the pick)
    assert picked[2] == "isosurface"
    # A movie's isovalue sweep frames every isovalue it shows: the ball of radius 0.3 too.
    outer = data_scene(path, "f", 0.3).framed
    swept = data_scene(path, "f", 0.1, framed_values=(0.1, 0.3)).framed
    assert swept[2] == "isosurfaces" and np.all(swept[0] <= np.minimum(lo, outer[0])) and \
        np.all(swept[1] >= np.maximum(hi, outer[1])) and np.any(outer[1] - outer[0] > hi - lo)
    xml = tmp_path / "sweep.xml"
    rc, _, err = render_cli(["movie", path, "--field", "f", "--isovalues", "0.1:0.3", "--frames",
                             "2", "--resolution", "16", "12", "--spp", "1", "--save-scene",
                             str(xml), "-o", str(tmp_path / "sweep")], capsys)
    assert rc == 0, err
    assert "the camera frames the cells of the isovalues swept" in xml.read_text()
    scene = tmp_path / "ball.xml"
    scene.write_text(made.xml())
    render_file(scene, tmp_path / "ball.exr", quiet=True)
    alpha = np.array(mi.Bitmap(str(tmp_path / "ball.exr")))[..., 3]
    cols, rows = np.flatnonzero(alpha.max(axis=0) > 0.5), np.flatnonzero(alpha.max(axis=1) > 0.5)
    # (A ball's outline is narrower than its box's corners, which cover 30-90 %; framing the
    # data's bounds it would cover a tenth.)
    assert (cols.max() + 1 - cols.min()) / 96 >= 0.2, cols
    assert abs((cols.min() + cols.max() + 1) / 2 - 48) < 10 and \
        abs((rows.min() + rows.max() + 1) / 2 - 36) < 10, (cols, rows)

def test02_a_real_render_covers_the_projected_bounds(mi, tmp_path):
    """The isosurface f = 0.9 of the max-norm field is the data box shrunk by 0.9: its alpha
    covers the columns Mitsuba's camera projects it to (within 2 pixels)."""
    from mi_amr.plugin.autoscene import data_scene
    from mi_amr.workflows.render import render_file

    path = save(box_volume((0, 0, 0), (0.08, 0.04, 0.02)), tmp_path / "slab.npz")
    scene = tmp_path / "slab.xml"
    made = data_scene(path, "f", 0.9, resolution=(128, 72), spp=1)
    scene.write_text(made.xml())
    out = tmp_path / "slab.exr"
    render_file(scene, out, quiet=True)
    alpha = np.array(mi.Bitmap(str(out)))[..., 3]
    cols = np.flatnonzero(alpha.max(axis=0) > 0.5)
    u0, u1, _, _ = projected_columns(mi, made, shrink=0.9)
    assert abs(cols.min() - u0) <= 2 and abs(cols.max() + 1 - u1) <= 2, (cols, u0, u1)
    assert 0.3 <= (cols.max() + 1 - cols.min()) / 128 <= 0.9


def test03_framing_is_refused_for_empty_bounds():
    from mi_amr.errors import AMRError

    with pytest.raises(AMRError, match="cannot frame bounds"):
        frame_box((0, 0, 0), (0, 0, 0), 1.0)


def test04_the_isovalue_is_picked_where_the_surface_is_not_in_noise():
    """A field that is 0 on one side and 1 on the other, with the 0 side's cells jittered by
    1e-9: the pick lies between the sides (a score that counted the noise's crossings would
    pick a value within 1e-9 of 0)."""
    rng = np.random.default_rng(0)

    def fn(p):
        step = np.clip((p[..., 0] - 3.5) / 1.0 + 0.5, 0, 1)
        return step + np.where(step == 0, rng.normal(0, 1e-9, step.shape), 0)

    vol = AMRVolume.from_grids([grid(0, (0, 0, 0), (8, 8, 8), 0.5, fn)])
    picked = suggest_isovalues(vol, "f")
    assert 0.2 <= picked[0] <= 0.8, picked
    stats = field_stats(vol, "f")
    assert stats.vmin < 1e-8 and stats.vmax == 1.0 and set(stats.percentiles) == {1, 10, 50,
                                                                                 90, 99}
    assert "suggested isovalues" in stats.text()


def velocity_of(fn, h=0.125):
    """One grid over [-1, 1]^3 whose velocity is ``fn(x, y, z)`` (three arrays), with Q
    derived."""
    import mi_amr

    names = ("vx", "vy", "vz")
    records = [grid(0, (-1, -1, -1), (1, 1, 1), h,
                    lambda p, a=a: fn(p[..., 0], p[..., 1], p[..., 2])[a], (n,))
               for a, n in enumerate(names)]
    fields = {k: v for r in records for k, v in r["fields"].items()}
    return mi_amr.derive(AMRVolume.from_grids([dict(records[0], fields=fields)]),
                         "q_criterion")


def test04c_a_scene_derives_the_picked_field_as_its_load_does(tmp_path):
    """A data file's derived field, read for the pick (and ``info``), is derived by the scene
    load's Dr.Jit kernels: the host derivation's numbers, bit for bit, and the same picks."""
    import mi_amr
    from mi_amr.plugin.datafields import load_with_fields

    rng = np.random.default_rng(4)
    vol = velocity_of(lambda x, y, z: (np.sin(3 * y) * z + 0.1 * rng.standard_normal(x.shape),
                                       np.cos(2 * x) + z * z, x * y))
    path = save(vol.select_fields(["vx", "vy", "vz"]), tmp_path / "v.npz")
    host = mi_amr.derive(mi_amr.load(path), "q_criterion", "speed")
    read, names = load_with_fields(path, ["q_criterion", "speed"])
    assert names == ["q_criterion", "speed"]
    for name in names:
        for a, b in zip(read.grids, host.grids):
            assert a.fields[name].dtype == b.fields[name].dtype
            np.testing.assert_array_equal(a.fields[name], b.fields[name])
    assert suggest_isovalues(read, "q_criterion") == suggest_isovalues(host, "q_criterion")


def test04b_the_q_criterion_is_picked_among_its_positive_values():
    """A vortex (rotation about z, fading with the radius) in a field of small fluctuations:
    the crossings of Q would pick a value near 0, in the fluctuations; Q's picks are the
    values below which 80, 50 and 95 % of its positive values lie. A strain whose Q is never
    positive keeps the picks of any field."""
    from mi_amr.core.suggest import Q_POSITIVE_RANKS, leaf_values

    rng = np.random.default_rng(1)

    def vortex(x, y, z):
        swirl = np.exp(-4 * (x * x + y * y))
        wiggle = 0.01 * rng.standard_normal((3,) + x.shape)
        return -y * swirl + wiggle[0], x * swirl + wiggle[1], wiggle[2]

    vol = velocity_of(vortex)
    q = np.sort(leaf_values(vol, "q_criterion"))
    picked = suggest_isovalues(vol, "q_criterion")
    assert picked == pytest.approx(np.quantile(q[q > 0], Q_POSITIVE_RANKS).tolist())
    # The cells above the pick lie in the vortex (within 0.5 of its axis); above the pick any
    # other field would get, three in four lie in the wiggles outside.
    g = vol.grids[0]
    centres = np.stack(np.meshgrid(*[(np.arange(n) + 0.5) * 0.125 - 1 for n in g.shape],
                                   indexing="ij"), axis=-1)
    near_axis = np.hypot(centres[..., 0], centres[..., 1]) < 0.5

    def in_vortex(v):
        return near_axis[g.fields["q_criterion"] > v].mean()

    generic = vol.with_fields({"g": [g.fields["q_criterion"] for g in vol.grids]})
    assert in_vortex(picked[0]) > 0.95 and in_vortex(suggest_isovalues(generic, "g")[0]) < 0.5

    strain = velocity_of(lambda x, y, z: (x * (1.5 + z), -y * (1.5 + z), 0 * z))
    assert leaf_values(strain, "q_criterion").max() < 0
    same = strain.with_fields({"g": [g.fields["q_criterion"] for g in strain.grids]})
    assert suggest_isovalues(strain, "q_criterion") == suggest_isovalues(same, "g")


def render_cli(argv, capsys):
    rc = main(argv)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


@pytest.mark.skipif(not PLOTFILES, reason="../shared/data/amrex is absent")
@pytest.mark.parametrize("plotfile", PLOTFILES, ids=lambda p: p.name)
def test05_each_plotfile_goes_to_a_png_with_one_command(mi, plotfile, tmp_path, capsys):
    out = tmp_path / "out.png"
    rc, text, err = render_cli(["render", str(plotfile), "-o", str(out), "--resolution", "96",
                                "72", "--spp", "1"], capsys)
    assert rc == 0, err
    assert "picked from the histogram" in text
    image = np.array(mi.Bitmap(str(out)))
    assert image.shape == (72, 96, 4)
    covered = (image[..., 3] > 0).mean()
    assert 0.01 < covered < 0.95, f"{plotfile.name}: surface covers {covered:.1%} of the image"


@pytest.mark.skipif(not PLOTFILES, reason="../shared/data/amrex is absent")
def test06_derived_fields_are_named_on_the_command_line(mi, tmp_path, capsys):
    plotfile = AMREX / "example_plt_3d"
    for field in ("q_criterion", "vorticity"):
        out = tmp_path / f"{field}.png"
        rc, text, err = render_cli(["render", str(plotfile), "--field", field, "-o", str(out),
                                    "--resolution", "64", "48", "--spp", "1"], capsys)
        assert rc == 0, err
        assert np.array(mi.Bitmap(str(out)))[..., 3].max() > 0
    rc, _, err = render_cli(["render", str(AMREX / "plt_eb_3d"), "--field", "q_criterion",
                             "-o", str(tmp_path / "x.png")], capsys)
    assert rc == 2 and "no field(s) 'q_criterion'" in err and "plt_eb_3d" in err


# The LLVM backend's run-to-run jitter: rendering one scene twice now and then differs in the
# last bit of a few pixels (so does a scene against its own reload).
JITTER_ABS, JITTER_SHARE = 1e-6, 0.05


def assert_same_pixels(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    assert a.shape == b.shape
    diff = np.abs(a - b)
    assert diff.max() <= JITTER_ABS and (diff > 0).mean() <= JITTER_SHARE, \
        f"differ by up to {diff.max():.3g} in {(diff > 0).mean():.2%} of the values"


def test07f_a_render_of_a_data_file_reads_its_field_once(mi, tmp_path, capsys):
    """``render FILE``: the field that its isovalue pick read goes on to the scene's load
    (which says so) instead of being read again, and makes the pixels that a load of the
    saved scene, reading the file, makes."""
    from mi_amr.plugin.integrator import register

    path = save(box_volume((0, 0, 0), (2, 1, 1)), tmp_path / "once.npz")
    a, b, xml = tmp_path / "a.png", tmp_path / "b.png", tmp_path / "made.xml"
    rc, text, err = render_cli(["render", path, "--field", "f", "--save-scene", str(xml),
                                "-o", str(a), "--resolution", "48", "32", "--spp", "1"], capsys)
    assert rc == 0, err
    assert "once.npz (f: " in text and "already read" in text, text
    assert "read once.npz" not in text, text
    register().clear()                  # (the saved scene's render reads the file)
    rc, text, err = render_cli(["render", str(xml), "-o", str(b), "--spp", "1"], capsys)
    assert rc == 0 and "read once.npz" in text, text
    first, second = np.array(mi.Bitmap(str(a))), np.array(mi.Bitmap(str(b)))
    assert first[..., 3].max() > 0 and np.array_equal(first, second)
    # The viewer's session (view FILE) loads the scene through the same preparations.
    import mi_amr.readers
    from mi_amr.workflows.datafile import scene_file
    from mi_amr.workflows.viewer.state import Session

    path = save(box_volume((0, 0, 0), (1, 1, 2)), tmp_path / "viewed.npz")
    reads, real = [], mi_amr.readers.load
    try:
        mi_amr.readers.load = lambda *a, **kw: reads.append(a) or real(*a, **kw)
        with scene_file(path, field="f", offer=register().offer, say=lambda *_: None) as scene:
            Session(scene, resolution=(24, 16), spp=1).close()
    finally:
        mi_amr.readers.load = real
    assert len(reads) == 1, reads


def test07g_a_movie_of_a_data_file_in_this_process_reads_its_field_once(mi, tmp_path, capsys):
    """``movie FILE`` with one worker (its frames rendered in this process): the field that the
    isovalue pick read goes on to the scene's load, as for ``render FILE``, and the frames are
    those of a run that reads it twice; with Dask workers (other processes) nothing is
    offered, so the volume read for the pick is not held through the movie."""
    import mi_amr.readers
    from mi_amr.plugin.integrator import register

    path = save(box_volume((0, 0, 0), (2, 1, 1)), tmp_path / "moving.npz")
    args = ["movie", path, "--field", "f", "--orbit", "90", "--frames", "2", "--resolution",
            "24", "16"]
    reads, real = [], mi_amr.readers.load
    try:
        mi_amr.readers.load = lambda *a, **kw: reads.append(a) or real(*a, **kw)
        rc, text, err = render_cli(args + ["-o", str(tmp_path / "once")], capsys)
    finally:
        mi_amr.readers.load = real
    assert rc == 0, err
    assert len(reads) == 1, reads
    register().clear()
    offered = []
    mi_amr_offer = type(register()).offer
    try:
        type(register()).offer = lambda self, *a, **kw: offered.append(a)
        rc, text, err = render_cli(args + ["-o", str(tmp_path / "twice")], capsys)
        assert rc == 0, err
        assert len(offered) == 1            # (the run above: offered and taken)
        offered.clear()
        rc, text, err = render_cli(args + ["-o", str(tmp_path / "dask"), "--workers", "2"],
                                   capsys)
        assert rc == 0, err
        assert offered == []
    finally:
        type(register()).offer = mi_amr_offer
    for name in ("frame_00000.png", "frame_00001.png"):
        once = np.array(mi.Bitmap(str(tmp_path / "once" / name)))
        assert once[..., 3].max() > 0
        np.testing.assert_array_equal(once, np.array(mi.Bitmap(str(tmp_path / "dask" / name))))


def test07_the_saved_scene_and_the_dict_render_the_same_pixels(mi, tmp_path, capsys):
    import mi_amr
    from mi_amr.plugin.scene import load_dict

    path = save(box_volume((0, 0, 0), (2, 1, 1)), tmp_path / "box.npz")
    a, b, xml = tmp_path / "a.png", tmp_path / "b.png", tmp_path / "made.xml"
    rc, text, err = render_cli(["render", path, "--field", "f", "--save-scene", str(xml),
                                "-o", str(a), "--resolution", "64", "40", "--spp", "2"], capsys)
    assert rc == 0, err
    rc, _, err = render_cli(["render", str(xml), "-o", str(b)], capsys)
    assert rc == 0, err
    first, second = np.array(mi.Bitmap(str(a))), np.array(mi.Bitmap(str(b)))
    assert first.shape == (40, 64, 4) and first[..., 3].max() > 0
    assert np.abs(first.astype(int) - second).max() <= 1 and (first != second).mean() < 0.001
    picked = float(text.split("isovalue ")[1].split()[0])
    scene_dict = mi_amr.scene(path, field="f", resolution=(64, 40), spp=2)
    assert float(scene_dict["integrator"]["isovalue"]) == pytest.approx(picked, rel=1e-5)
    for from_dict, from_xml in ((mi.load_dict(scene_dict), mi.load_file(str(xml))),
                                (load_dict(scene_dict), mi_amr.load_scene(xml))):
        # (1 spp a render: two samples of a pixel are summed in the film in thread order)
        d, x = mi.render(from_dict, spp=1, seed=0), mi.render(from_xml, spp=1, seed=0)
        assert np.array(d)[..., 3].max() > 0
        assert_same_pixels(d, x)


def one_error(result, *words):
    rc, _, err = result
    lines = [l for l in err.splitlines() if l.strip()]
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])


def test08_bad_inputs_each_get_one_error_naming_them(mi, tmp_path, capsys):
    f_file = save(box_volume((0, 0, 0), (1, 1, 1)), tmp_path / "f1.npz")
    g_file = save(box_volume((0, 0, 0), (1, 1, 1), names=("g",)), tmp_path / "f2.npz")
    out = str(tmp_path / "frames")
    pattern = str(tmp_path / "nothing*.npz")
    one_error(render_cli(["movie", pattern, "--field", "f", "-o", out], capsys), pattern,
              "matches no file")
    one_error(render_cli(["render", f_file, "--field", "nope", "-o", str(tmp_path / "x.png")],
                          capsys), f_file, "'nope'", "f")
    one_error(render_cli(["movie", f_file, g_file, "--field", "f", "-o", out, "--resolution",
                           "16", "16"], capsys), "f2.npz", "'f'")
    one_error(render_cli(["render", str(tmp_path / "missing.npz"), "-o",
                           str(tmp_path / "x.png")], capsys), "missing.npz")
    # A derived field of a file without velocity: what it would need, not only what it holds.
    one_error(render_cli(["render", f_file, "--field", "speed", "-o", str(tmp_path / "x.png")],
                         capsys), f_file, "'speed'", "it holds f", "velocity components",
              "vx/vy/vz")
    # ... and as the colour field (the message named neither the file nor the field).
    one_error(render_cli(["render", f_file, "--field", "f", "--isovalue", "0.5", "-D",
                          "color_field=speed", "-o", str(tmp_path / "x.png")], capsys),
              f_file, "'speed'", "it holds f", "velocity components", "vx/vy/vz")
    import mi_amr
    from mi_amr.errors import AMRError

    for bad in ("abc", "nan", [0.5]):           # (not a number: one error, before any read)
        with pytest.raises(AMRError, match="isovalue must be a finite number"):
            mi_amr.scene(tmp_path / "missing.npz", field="f", isovalue=bad)
    scene = tmp_path / "s.xml"
    scene.write_text("<scene version='3.0.0'/>")
    one_error(render_cli(["render", str(scene), "--field", "f", "-o", str(tmp_path / "x.png")],
                          capsys), "--field", "scene file")
    assert not (tmp_path / "frames").exists() or not any((tmp_path / "frames").iterdir())


def test09_a_movie_of_data_files_needs_no_scene(mi, tmp_path, capsys):
    files = [save(box_volume((0, 0, 0), (1, 1, 1 + 0.5 * t)), tmp_path / f"plt{t}.npz")
             for t in (1, 2, 10)]
    out = tmp_path / "frames"
    rc, text, err = render_cli(["movie", str(tmp_path / "plt*.npz"), "--field", "f",
                                "--isovalue", "0.8", "-o", str(out), "--resolution", "32",
                                "24", "--spp", "1"], capsys)
    assert rc == 0, text + err
    frames = sorted(out.glob("frame_*.png"))
    assert len(frames) == len(files)
    import mitsuba

    first = np.array(mitsuba.Bitmap(str(frames[0])))
    assert first.shape == (24, 32, 4), "movie frames are RGBA PNGs, as render's"
    assert first[..., 3].min() == 0 and first[..., 3].max() == 255
    assert "isovalue 0.8 (given)" in text
    # A time series frames its first step's bounds: later steps' surfaces may lie elsewhere.
    xml = tmp_path / "series.xml"
    rc, _, err = render_cli(["movie", str(tmp_path / "plt*.npz"), "--field", "f", "--isovalue",
                             "0.8", "-o", str(tmp_path / "again"), "--resolution", "16", "12",
                             "--spp", "1", "--save-scene", str(xml)], capsys)
    assert rc == 0 and "the camera frames the data's bounds" in xml.read_text(), err


def test10_color_field_none_switches_the_colour_field_off():
    from mi_amr.plugin.options import parse

    base = {"filename": "x.npz", "field": "f", "isovalue": "0.5"}
    opt = parse(dict(base, color_field="none", colormap="viridis", color_range="0 1"))
    assert opt.color_field is None and opt.colormap is None and opt.color_range is None
    opt = parse(dict(base, color_field="g", colormap="viridis"))
    assert opt.color_field == "g" and opt.colormap == "viridis"


RGB_SCENE = """<scene version="3.0.0">
    <default name="filename" value="box.npz"/>
    <integrator type="amr_iso">
        <string name="filename" value="$filename"/>
        <string name="field" value="f"/>
        <float name="isovalue" value="0.7"/>
    </integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world">
            <lookat origin="3, -2, 2" target="0.5, 0.5, 0.5" up="0, 0, 1"/></transform>
        <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="16"/>
            <string name="pixel_format" value="rgb"/></film>
    </sensor>
    <emitter type="directional"><vector name="direction" value="-0.4, 0.5, -1.0"/>
        <rgb name="irradiance" value="2.5"/></emitter>
</scene>
"""


def test11_movie_frames_and_viewer_saves_are_rgba_pngs_as_render_makes(mi, tmp_path, capsys):
    """One convention for every PNG: RGBA with the film's coverage as alpha, also from a scene
    whose film is RGB."""
    from mi_amr.workflows.movie.output import write_image_atomic
    from mi_amr.workflows.viewer.state import Session

    save(box_volume((0, 0, 0), (1, 1, 1)), tmp_path / "box.npz")
    scene = tmp_path / "scene.xml"
    scene.write_text(RGB_SCENE)
    images = {}
    rc, _, err = render_cli(["render", str(scene), "-o", str(tmp_path / "r.png")], capsys)
    assert rc == 0, err
    images["render"] = tmp_path / "r.png"
    rc, _, err = render_cli(["movie", str(scene), "-o", str(tmp_path / "m"), "--frames", "1"],
                            capsys)
    assert rc == 0, err
    images["movie"] = tmp_path / "m" / "frame_00000.png"
    session = Session(scene, resolution=(24, 16), spp=1)
    try:
        write_image_atomic(tmp_path / "v.png", session.render_refined((24, 16), 1))
    finally:
        session.close()
    images["viewer"] = tmp_path / "v.png"
    pixels = {k: np.array(mi.Bitmap(str(p))) for k, p in images.items()}
    for k, px in pixels.items():
        assert px.shape == (16, 24, 4), f"{k}: {px.shape}"
        assert px[..., 3].min() == 0 and px[..., 3].max() == 255, k
    assert np.array_equal(pixels["movie"][..., 3], pixels["render"][..., 3])


def velocity_volume():
    """A shear flow vx = z, vy = x, vz = 0 on one grid (Q derivable), plus a stored field."""
    def fn_of(name):
        return {"vx": lambda p: p[..., 2], "vy": lambda p: p[..., 0],
                "vz": lambda p: 0 * p[..., 0], "rho": lambda p: 1 + p[..., 0] ** 2}[name]

    records = [grid(0, (0, 0, 0), (2, 2, 2), 0.25, fn_of(n), (n,)) for n in
               ("vx", "vy", "vz", "rho")]
    fields = {k: v for r in records for k, v in r["fields"].items()}
    return AMRVolume.from_grids([dict(records[0], fields=fields)])


def test12_info_prints_each_fields_percentiles_levels_and_isovalues(tmp_path, capsys):
    path = save(velocity_volume(), tmp_path / "flow.npz")
    rc, text, err = render_cli(["info", path, "--fields", "q_criterion", "vorticity", "rho"],
                               capsys)
    assert rc == 0, err
    for word in ("q_criterion: [", "vorticity_magnitude: [", "rho: [", "p1 ", "p10 ", "p50 ",
                 "p90 ", "p99 ", "level 0:", "leaf cells", "suggested isovalues:"):
        assert word in text, word
    rho = text[text.index("rho: ["):]
    p50 = float(rho.split("p50 ")[1].split()[0])
    assert p50 == pytest.approx(np.median(1 + (0.125 + 0.25 * np.arange(8)) ** 2), rel=1e-5)
    # Each suggested isovalue with the band width volume mode would pick for it.
    from mi_amr.core.suggest import leaf_values, suggest_band_width

    widths = [float(w) for w in
              rho.split("their band widths (volume mode): ")[1].split("\n")[0].split(", ")]
    stats = field_stats(velocity_volume(), "rho")
    values = np.sort(leaf_values(velocity_volume(), "rho"))
    assert stats.band_widths == [suggest_band_width(values, v) for v in stats.suggested]
    assert len(widths) == len(stats.suggested) >= 1
    assert widths == pytest.approx(stats.band_widths, rel=1e-5)
    one_error(render_cli(["info", path, "--fields", "nope"], capsys), "'nope'", "flow.npz",
              "q_criterion")


def test13_show_takes_a_data_file_a_dict_or_a_scene_file_alike(mi, tmp_path, capsys):
    import mi_amr
    from mi_amr.errors import AMRError

    path = save(box_volume((0, 0, 0), (1, 2, 1)), tmp_path / "b.npz")
    made = mi_amr.scene(path, field="f", isovalue=0.6, resolution=(48, 32), spp=1)
    from mi_amr.plugin.autoscene import data_scene

    xml = tmp_path / "b.xml"
    xml.write_text(data_scene(path, "f", 0.6, resolution=(48, 32), spp=1).xml())
    images = [mi_amr.show(path, field="f", isovalue=0.6, resolution=(48, 32), spp=1),
              mi_amr.show(made, spp=1), mi_amr.show(xml, spp=1)]
    for image in images:
        assert image.size == (48, 32) and image.numpy().shape == (32, 48, 4)
        assert image._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
        assert_same_pixels(image.numpy(), images[0].numpy())
    assert images[0].numpy()[..., 3].max() == 1.0
    with pytest.raises(AMRError, match="missing.npz"):
        mi_amr.show(tmp_path / "missing.npz")
    with pytest.raises(AMRError, match="missing.npz"):
        mi_amr.explore(tmp_path / "missing.npz")
    # A scene file takes a film size; what only a data file's scene takes is refused, not
    # ignored: one error naming it.
    assert mi_amr.show(xml, resolution=(24, 16), spp=1).size == (24, 16)
    for scene, kw, named in [(xml, dict(field="g"), "field="),
                             (xml, dict(isovalue=0.3, mode="volume"), "isovalue=, mode="),
                             (made, dict(resolution=(24, 16)), "resolution="),
                             (made, dict(band_width=0.1), "band_width=")]:
        with pytest.raises(AMRError, match=f"{named} appl.* to data files only"):
            mi_amr.show(scene, spp=1, **kw)
    for kw, named in [(dict(isovalue=0.3), "isovalue="),
                      (dict(allow_nonfinite=True), "allow_nonfinite=")]:
        with pytest.raises(AMRError, match=f"b.xml: {named} applies to data files only"):
            mi_amr.explore(xml, **kw)
    # A picked isovalue is printed with the way to set it in Python words, not the CLI's.
    capsys.readouterr()
    import mi_amr.readers

    fresh = save(box_volume((0, 0, 0), (1, 2, 1)), tmp_path / "c.npz")    # (none kept)
    reads = []
    real = mi_amr.readers.load
    try:
        mi_amr.readers.load = lambda *a, **kw: reads.append(a) or real(*a, **kw)
        mi_amr.show(fresh, field="f", resolution=(24, 16), spp=1)
    finally:
        mi_amr.readers.load = real
    out = capsys.readouterr().out
    assert "picked from the histogram" in out and "isovalue= sets it" in out, out
    assert "--isovalue" not in out, out
    assert len(reads) == 1, reads           # the pick's read goes on to the scene's load


def test14_view_serves_a_data_file(tmp_path):
    """``view FILE --field F``: the page's state is the made scene's; Ctrl-C stops it and the
    scene written for it is gone."""
    import json
    import os
    import re
    import signal
    import subprocess
    import sys
    import time
    import urllib.request

    path = save(box_volume((0, 0, 0), (1, 1, 2)), tmp_path / "v.npz")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]),
               TMPDIR=str(tmp_path))
    proc = subprocess.Popen([sys.executable, "-m", "mi_amr", "view", path, "--field", "f",
                             "--isovalue", "0.5", "--port", "0", "--no-browser", "--out",
                             str(tmp_path / "out")], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env)
    try:
        url, seen, deadline = None, [], time.time() + 300
        while url is None and time.time() < deadline:
            line = proc.stdout.readline()
            assert line, "".join(seen)
            seen.append(line)
            found = re.search(r"serving (http://\S+)", line)
            url = found and found.group(1)
        assert url, "".join(seen)
        with urllib.request.urlopen(url + "api/state", timeout=60) as reply:
            state = json.loads(reply.read())["state"]
        assert state["field"] == "f" and state["isovalues"] == pytest.approx([0.5])
        assert state["data_file"] == str(Path(path).resolve())
        assert list(tmp_path.glob("mi_amr_scene_*/v.npz.xml")), "the scene is made in TMPDIR"
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)
    assert not list(tmp_path.glob("mi_amr_scene_*")), "the made scene is left behind"


def test15_the_picked_band_width_is_half_the_nearer_side_of_a_rank_window():
    """:func:`suggest_band_width` on values whose answer is known: 0, 1, ..., 1000 about 500
    (the window of 2 % of the ranks each side ends 20 values away: a width of 10), values
    denser on one side, a field that is flat about the isovalue, and a constant one."""
    from mi_amr.core.suggest import BAND_RANKS, suggest_band_width

    assert BAND_RANKS == 0.02
    assert suggest_band_width(np.arange(1001.0), 500.0) == pytest.approx(10.0)
    assert suggest_band_width(np.arange(1001.0), 100.0) == pytest.approx(10.0)
    # Denser above the isovalue: the band follows the denser side.
    skewed = np.sort(np.concatenate([np.linspace(0, 100, 500), np.linspace(100, 110, 500)]))
    w = suggest_band_width(skewed, 100.0)
    assert 0 < w < 0.2
    flat = np.sort(np.concatenate([np.full(1000, 3.0), [0.0, 10.0]]))
    assert suggest_band_width(flat, 3.0) == pytest.approx(0.01 * 10.0)
    tiny = suggest_band_width(np.full(10, 0.0), 0.0)
    assert tiny > 0 and np.float32(tiny) > 0



@settings(max_examples=300, deadline=None)
@given(values=st.lists(st.floats(-1e6, 1e6, width=32), min_size=1, max_size=60),
       qs=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=8),
       double=st.booleans(), scalar=st.booleans())
def test15b_quantiles_of_sorted_values_are_numpys_to_the_bit(values, qs, double, scalar):
    """The picks and the viewer read quantiles of the sorted leaf values without NumPy's
    partition of the whole array: the same numbers and dtype as ``np.quantile`` and
    ``np.percentile`` (runs of equal values, one value, the ends, a scalar or a list)."""
    from mi_amr.core.suggest import sorted_percentile, sorted_quantile

    v = np.sort(np.asarray(values, dtype=np.float64 if double else np.float32))
    q = qs[0] if scalar else qs
    for ours, numpys in ((sorted_quantile(v, q), np.quantile(v, q)),
                         (sorted_percentile(v, q * 100 if scalar else tuple(100 * x for x in q)),
                          np.percentile(v, q * 100 if scalar else tuple(100 * x for x in q)))):
        assert np.asarray(ours).dtype == np.asarray(numpys).dtype
        np.testing.assert_array_equal(ours, numpys)

@settings(max_examples=300, deadline=None)
@given(values=st.lists(st.floats(-1e3, 1e3, width=32), min_size=0, max_size=80),
       ends=st.tuples(st.floats(-1e3, 1e3, width=32), st.floats(0.0, 1e3, width=32)),
       bins=st.integers(1, 70), double=st.booleans(), grid_values=st.booleans())
def test15c_a_histogram_of_sorted_values_is_numpys(values, ends, bins, double, grid_values):
    """The viewer's histogram counts the sorted leaf values at the bin edges instead of
    binning them again: NumPy's counts, values on an edge and on the last edge included,
    values outside the range left out."""
    from mi_amr.core.suggest import sorted_histogram

    lo, hi = float(ends[0]), float(ends[0]) + max(float(ends[1]), 1.0)
    if grid_values:     # values on the edges themselves
        values = list(np.linspace(lo, hi, bins + 1)) + values[:5]
    v = np.sort(np.asarray(values, dtype=np.float64 if double else np.float32))
    ours, numpys = sorted_histogram(v, bins, (lo, hi)), np.histogram(v, bins, (lo, hi))[0]
    assert ours.dtype == numpys.dtype
    np.testing.assert_array_equal(ours, numpys)


def ball_volume(scale=1000.0):
    """One grid over the unit cube whose field ``f`` is ``scale`` times the distance from the
    centre: a data file in other units than the sphere wake's Q."""
    def fn(p):
        return scale * np.linalg.norm(p - 0.5, axis=-1)

    return AMRVolume.from_grids([grid(0, (0, 0, 0), (1, 1, 1), 1 / 24, fn)])


def test16_volume_mode_for_a_data_file_picks_its_band_from_the_histogram(mi, tmp_path, capsys):
    """``--mode volume`` (and ``mode="volume"`` in Python): the band's width is picked about
    the isovalue, said, and written into the saved scene, whose pixels are the dict's. The
    parameter's default width (0.004, in the sphere wake's units) on a field of hundreds shows
    next to nothing, which the picked band does not; ``mi_amr.explore`` serves the same band,
    and a surface scene whose isovalue is picked carries its band for the viewer's switch to
    volume mode. With a 2D transfer function no band is picked (the two refuse each other).
    A scene file takes no ``--mode``."""
    import mi_amr
    from mi_amr.core.suggest import leaf_values, suggest_band_width
    from mi_amr.plugin.autoscene import data_scene

    path = save(ball_volume(), tmp_path / "ball.npz")
    out, xml = tmp_path / "v.png", tmp_path / "v.xml"
    rc, text, err = render_cli(["render", path, "--mode", "volume", "--isovalue", "300",
                                "--save-scene", str(xml), "-o", str(out), "--resolution", "48",
                                "40", "--spp", "1"], capsys)
    assert rc == 0, err
    want = suggest_band_width(np.sort(leaf_values(mi_amr.load(path), "f")), 300.0)
    assert 1.0 < want < 100.0
    assert f"volume band width {want:.6g} (picked from the histogram" in text
    assert '<string name="mode" value="volume"/>' in xml.read_text()
    assert f'<float name="band_width" value="{want!r}"/>' in xml.read_text()
    made = mi_amr.scene(path, isovalue=300.0, mode="volume", resolution=(48, 40), spp=1)
    assert made["integrator"]["band_width"] == want
    d = mi.render(mi.load_dict(made), spp=1, seed=0)
    assert_same_pixels(d, mi.render(mi.load_file(str(xml)), spp=1, seed=0))
    picked = np.array(d)[..., 3].mean()
    thin = np.array(mi.render(mi.load_dict(mi_amr.scene(
        path, isovalue=300.0, mode="volume", band_width=0.004, resolution=(48, 40), spp=1)),
        spp=1, seed=0))[..., 3].mean()
    assert picked > 0.05 and thin < 0.1 * picked, (picked, thin)
    assert "band_width" not in data_scene(path, "f", 300.0, mode="volume",
                                          transfer2d_blobs="300 0 20 5 1").params
    # A surface scene whose isovalue is given reads no values for a band; one whose isovalue
    # is picked carries the band it would have in volume mode, which the viewer switches to.
    assert "band_width" not in data_scene(path, "f", 300.0).params
    surface = data_scene(path, "f")
    values = np.sort(leaf_values(mi_amr.load(path), "f"))
    assert surface.params["band_width"] == suggest_band_width(values, surface.isovalue)
    assert "band width" not in surface.xml()          # (said in volume mode only)
    import json
    import urllib.request

    for kw, width in (({"isovalue": 300.0, "mode": "volume"}, want),
                      ({}, surface.params["band_width"])):
        explorer = mi_amr.explore(path, out_dir=tmp_path, resolution=(32, 24), **kw)
        try:
            with urllib.request.urlopen(explorer.url + "api/state", timeout=60) as reply:
                state = json.loads(reply.read())["state"]
        finally:
            explorer.close()
        assert state["mode"] == kw.get("mode", "surface"), kw
        assert state["band_width"] == pytest.approx(width, rel=1e-6), kw
    scene = tmp_path / "s.xml"
    scene.write_text("<scene version='3.0.0'/>")
    one_error(render_cli(["render", str(scene), "--mode", "volume", "-o",
                          str(tmp_path / "x.png")], capsys), "--mode", "scene file",
              "parameter mode")


def test17_a_field_without_a_finite_value_gets_one_error_from_the_picks(mi, tmp_path, capsys):
    """A file whose field is NaN in every cell, kept as missing data: picking an isovalue (or
    a band) from it, or ``info``'s statistics, say so, naming the file and the field, instead
    of failing on an empty array."""
    vol = AMRVolume.from_grids([grid(0, (0, 0, 0), (1, 1, 1), 0.25, lambda p: np.full(
        p.shape[:-1], np.nan))], allow_nonfinite=True)
    path = save(vol, tmp_path / "empty.npz")
    one_error(render_cli(["render", path, "--allow-nonfinite", "-o", str(tmp_path / "x.png")],
                         capsys), "empty.npz", "'f'", "no finite value")
    one_error(render_cli(["render", path, "--allow-nonfinite", "--isovalue", "1", "--mode",
                          "volume", "-o", str(tmp_path / "x.png")], capsys), "no finite value")
    # info's statistics too (they named the volume through a method it does not have)
    one_error(render_cli(["info", path, "--allow-nonfinite"], capsys), "empty.npz", "'f'",
              "no finite value")


def test18_the_viewer_picks_a_new_fields_bands_in_its_units(mi, tmp_path):
    """The viewer's field change reloads the scene with the bands of the old field, whose
    widths are in the old field's units: they are picked again from the new field's
    histogram about the isovalues (moved into its range first; narrowed where two bands
    would overlap, which volume mode refuses), in volume mode and out of it."""
    import mi_amr
    from mi_amr.core.suggest import leaf_values, suggest_band_width, suggest_band_widths
    from mi_amr.plugin.autoscene import data_scene
    from mi_amr.workflows.viewer.state import Session

    vol = AMRVolume.from_grids([grid(0, (0, 0, 0), (1, 1, 1), 1 / 16, lambda p: np.linalg.norm(
        p - 0.5, axis=-1), ("f",))])
    vol = vol.with_fields({"g": [1000.0 * g.fields["f"] for g in vol.grids]})
    path = save(vol, tmp_path / "two.npz")
    g_values = np.sort(leaf_values(mi_amr.load(path), "g"))
    for mode in ("volume", "surface"):
        scene = tmp_path / f"{mode}.xml"
        scene.write_text(data_scene(path, "f", 0.3, mode=mode, band_width=0.01,
                                    resolution=(24, 16), spp=1).xml())
        session = Session(scene, resolution=(24, 16), spp=1)
        try:
            assert session.state.band_width == pytest.approx((0.01,))
            shown = session.apply(session.state.replace(field="g"))[1]
        finally:
            session.close()
        # (0.3 lies below g's values: the isovalue moves to the middle of them, the band too)
        assert shown.field == "g" and g_values[0] < shown.isovalues[0] < g_values[-1], mode
        want = suggest_band_width(g_values, shown.isovalues[0])
        assert shown.band_width == pytest.approx((want,), rel=1e-6), mode
        assert np.allclose(shown.band_offsets, [(-2 * want, 2 * want)], rtol=1e-6), mode
    # Two isovalues closer than their picked bands: narrowed to stay apart.
    wide = suggest_band_width(g_values, 300.0)
    apart = suggest_band_widths(g_values, [300.0, 500.0])
    assert apart == [wide, suggest_band_width(g_values, 500.0)] and 4 * max(apart) < 200
    close = suggest_band_widths(g_values, [300.0, 300.0 + wide])
    assert all(w < wide / 4 for w in close) and 300.0 + 2 * close[0] < 300.0 + wide - 2 * close[1]


def hand_scene(scene, data, integrator: str, camera: str):
    """Write a scene as a person would, with no shape: ``amr_iso`` on field ``f`` of ``data``
    with the further children ``integrator``, a 24 x 16 camera placed by ``camera`` (the
    children of its ``to_world``)."""
    scene.write_text(f"""<scene version="3.0.0">
        <integrator type="amr_iso">
            <string name="filename" value="{data}"/>
            <string name="field" value="f"/>
            {integrator}
        </integrator>
        <sensor type="perspective">
            <transform name="to_world">{camera}</transform>
            <film type="hdrfilm"><integer name="width" value="24"/>
                <integer name="height" value="16"/></film>
        </sensor>
    </scene>""")
    return scene


def test19_a_surface_scene_without_bands_gets_them_from_the_histogram_in_the_viewer(
        mi, tmp_path):
    """A scene written by hand in surface mode, on a field of hundreds, without
    ``band_width``: the viewer's bands for a switch to volume mode are picked from the
    histogram about its isovalues (the parameter's default would show nothing); a scene that
    sets ``band_width`` keeps its own."""
    import mi_amr
    from mi_amr.core.suggest import leaf_values, suggest_band_widths
    from mi_amr.workflows.viewer.state import Session

    path = save(ball_volume(), tmp_path / "ball.npz")
    values = np.sort(leaf_values(mi_amr.load(path), "f"))
    want = suggest_band_widths(values, [250.0, 400.0])
    for band, widths in (("", want), ('<string name="band_width" value="5"/>', [5.0, 5.0])):
        scene = hand_scene(tmp_path / "hand.xml", path,
                           f'<string name="isovalue" value="250, 400"/>{band}',
                           '<lookat origin="2.5, -2, 2" target="0.5, 0.5, 0.5" up="0, 0, 1"/>')
        session = Session(scene, resolution=(24, 16), spp=1)
        try:
            state = session.state
            assert state.mode == "surface"
            assert state.band_width == pytest.approx(widths, rel=1e-6), band
            shown = session.apply(state.replace(mode="volume"))[1]
            assert shown.band_width == pytest.approx(widths, rel=1e-6), band
            alpha = session.render((24, 16), 1)[..., 3].mean()
        finally:
            session.close()
        assert alpha > 0.02, (band, alpha)


def test20_a_matrix_camera_over_a_scene_without_shapes_aims_at_the_volume(mi, tmp_path):
    """The viewer's home camera of a scene whose camera is a matrix (no ``<lookat>`` to read
    the target from) and which has no shape (an empty bounding box, whose centre is NaN): the
    target is on the view axis at the volume's centre, placed by the integrator's
    ``to_world``; it was NaN."""
    from mi_amr.workflows.viewer.state import Session

    path = save(ball_volume(), tmp_path / "ball.npz")
    scene = hand_scene(tmp_path / "matrix.xml", path,
                       '<float name="isovalue" value="300"/>'
                       '<transform name="to_world"><translate value="2, 0, 0"/></transform>',
                       '<matrix value="1 0 0 2.5  0 1 0 0.5  0 0 1 -3  0 0 0 1"/>')
    session = Session(scene, resolution=(24, 16), spp=1)
    try:
        home = session.home_camera
    finally:
        session.close()
    assert np.allclose(home.origin, (2.5, 0.5, -3.0))
    assert np.allclose(home.target, (2.5, 0.5, 0.5)), home.target
