"""Volume mode's 2D transfer function (opacity by value and |grad f|, issue 13 item 4): the host
table and its checks, the kernel lookup against its float64 twin, blobs against their formula,
image files against ``.npy``, no compilation for a new table, and the acceptance test -- less
haze than a 1D band of the same value, with the material boundary still drawn.

The renders use Phong with ``ka = ambient = 1``, ``kd = ks = 0``, colour 1 and no shadows, so a
pixel is the accumulated opacity ``1 - T`` of its ray (the compositing sums ``T_i alpha_i``).
"""

import gc
import textwrap
from pathlib import Path

import numpy as np
import pytest

from conftest import kernels_compiled
from mi_amr import AMRError
from mi_amr.core.transfer2d import Transfer2D, blobs_numpy, from_blobs, parse_blobs, parse_range
from mi_amr.synthetic import datasets

RES = 64
ISO, BW = 0.5, 0.1            # the value and the 1D band's width (field units)
G_MAX, G_CUT = 40.0, 10.0     # the table's |grad f| range and the 2D TF's threshold
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "amrex"


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


def band_alpha(v):
    """The 1D band's opacity (band.py's formula, peak 1.6, width :data:`BW`)."""
    return np.minimum(1.0, 1.6 * np.exp(-0.5 * ((np.asarray(v) - ISO) / BW) ** 2))


def threshold_table(rows=9, cols=33):
    """The 1D band's columns over ``ISO +- 2 BW``, opaque only at ``|grad f| >= G_CUT``."""
    vs, gs = np.linspace(ISO - 2 * BW, ISO + 2 * BW, cols), np.linspace(0, G_MAX, rows)
    return band_alpha(vs)[None, :] * (gs[:, None] >= G_CUT)


TABLE_RANGE = f"{ISO - 2 * BW:g} {ISO + 2 * BW:g} 0 {G_MAX:g}"


def scene(folder, extra, method="adaptive", filename="bab.npz", field="f", iso=ISO,
          view=("0.5, -1, 0.5", "0.5, 0.5, 0.5", "0, 0, 1", 0.5, 0.5), height=RES):
    """An orthographic camera (``view``: origin, target, up, half width, half height of the
    film in world units) over the unit cube, looking along +y by default: pixel column ``c`` is
    world ``x = (c + 0.5) / RES``, row ``r`` is ``z = 1 - (r + 0.5) / RES``."""
    origin, target, up, sx, sy = view
    path = folder / "tf2d.xml"
    path.write_text(textwrap.dedent(f"""
        <scene version="3.0.0">
            <integrator type="amr_iso">
                <string name="filename" value="{filename}"/>
                <string name="field" value="{field}"/>
                <float name="isovalue" value="{iso}"/>
                <string name="mode" value="volume"/>
                <string name="method" value="{method}"/>
                <string name="iso_color" value="1 1 1"/>
                <float name="ka" value="1"/><float name="kd" value="0"/>
                <float name="ks" value="0"/><boolean name="shadows" value="false"/>
                {extra}
            </integrator>
            <sensor type="orthographic">
                <transform name="to_world"><scale x="{sx}" y="{sy}"/>
                    <lookat origin="{origin}" target="{target}" up="{up}"/></transform>
                <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
                <film type="hdrfilm"><integer name="width" value="{RES}"/>
                    <integer name="height" value="{height}"/>
                    <string name="pixel_format" value="rgb"/></film>
            </sensor>
        </scene>"""))
    return path


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("tf2d")
    datasets.boundary_and_blob().save(out / "bab.npz")
    np.save(out / "tf.npy", threshold_table())
    return out


def render(mi, path, seed=0):
    import drjit as dr

    from mi_amr.plugin.scene import load_scene

    img = mi.render(load_scene(path), seed=seed)
    dr.eval(img)
    return np.array(img, dtype=np.float64)[..., 0]


def table_xml(name="tf.npy", rng=TABLE_RANGE):
    return (f'<string name="transfer2d" value="{name}"/>'
            f'<string name="transfer2d_range" value="{rng}"/>')


# ---------------------------------------------------------------------- checks

@pytest.mark.parametrize("values,message", [
    ({"transfer2d": "tf.npy"}, "'transfer2d_range'"),
    ({"transfer2d_range": "0 1 0 1"}, "'transfer2d_range'"),
    ({"transfer2d": "tf.npy", "transfer2d_range": "0 1 0", }, "'transfer2d_range' must be four"),
    ({"transfer2d": "tf.npy", "transfer2d_range": "1 0 0 1"}, "'transfer2d_range' needs v0 < v1"),
    ({"transfer2d": "tf.npy", "transfer2d_range": "0 1 -1 1"}, "'transfer2d_range' needs 0 <= g0"),
    ({"transfer2d": "tf.npy", "transfer2d_range": "0 1 2 2"}, "'transfer2d_range' needs 0 <= g0"),
    ({"transfer2d": "tf.npy", "transfer2d_range": "0 1 0 nan"}, "'transfer2d_range' must hold"),
    ({"transfer2d": "tf.npy", "transfer2d_range": "0 1 0 1", "transfer2d_blobs": "0.5 1 1 1 1"},
     "'transfer2d' and 'transfer2d_blobs' exclude"),
    ({"transfer2d_blobs": "0.5 1 1 1"}, "'transfer2d_blobs': each blob is five"),
    ({"transfer2d_blobs": "0.5 1 a 1 1"}, "'transfer2d_blobs': each blob is five"),
    ({"transfer2d_blobs": ";"}, "'transfer2d_blobs' needs at least one"),
    ({"transfer2d_blobs": "0.5 1 0 1 1"}, "'transfer2d_blobs': sigma_v and sigma_g must be > 0"),
    ({"transfer2d_blobs": "0.5 1 1 -1 1"}, "'transfer2d_blobs': sigma_v and sigma_g must be > 0"),
    ({"transfer2d_blobs": "0.5 1 1 1 0"}, "'transfer2d_blobs': peak must be > 0"),
    ({"transfer2d_blobs": "0.5 1 1 1 1", "mode": "surface"}, "'transfer2d_blobs' needs mode"),
    ({"transfer2d_blobs": "0.5 1 1 1 1", "preintegrated": True}, "'preintegrated'.*not supported"),
    ({"transfer2d_blobs": "0.5 1 1 1 1", "isovalue": "0.4, 0.5"}, "give one isovalue"),
    ({"transfer2d_blobs": "0.5 1 1 1 1", "band_width": 0.1}, "'band_width' do not apply"),
])
def test01_bad_parameters_are_refused_naming_them(values, message):
    from mi_amr.plugin import options

    base = {"filename": "a.npz", "field": "f", "isovalue": "0.5", "mode": "volume",
            "method": "uniform"}
    with pytest.raises(AMRError, match=message):
        options.parse({**base, **values})


@pytest.mark.parametrize("table,message", [
    (np.zeros(5), "expected a 2-D table"),
    (np.zeros((2, 2, 2)), "expected a 2-D table"),
    (np.zeros((1, 5)), "at least 2 x 2"),
    (np.array([[0.0, np.nan], [0, 0]]), "NaN or infinite"),
    (np.array([[0.0, np.inf], [0, 0]]), "NaN or infinite"),
    (np.array([[0.0, 1.5], [0, 0]]), r"must lie in \[0, 1\]"),
    (np.array([[0.0, -0.1], [0, 0]]), r"must lie in \[0, 1\]"),
])
def test02_bad_table_files_are_refused_naming_the_file(variant, folder, table, message):
    """Through the scene loader: the message names the file and the parameter."""
    np.save(folder / "bad.npy", table)
    with pytest.raises(AMRError, match=r"bad\.npy \('transfer2d'\).*" + message):
        render(variant, scene(folder, table_xml("bad.npy")))


@pytest.mark.parametrize("name,content,message", [
    ("missing.npy", None, "'transfer2d': missing.npy not found"),
    ("junk.npy", b"not a numpy file", r"junk\.npy: cannot read a 2D transfer function"),
    ("junk.png", b"not a png", r"junk\.png \('transfer2d'\): cannot read the image"),
    ("table.txt", b"0 1", r"'transfer2d': .*table\.txt must be a \.npy, \.png or \.exr"),
])
def test03_missing_or_unreadable_files_are_refused(variant, folder, name, content, message):
    if content is not None:
        (folder / name).write_bytes(content)
    with pytest.raises(AMRError, match=message):
        render(variant, scene(folder, table_xml(name)))


def test04_range_and_blob_strings_parse():
    assert parse_range("0, 1 0 2.5") == (0.0, 1.0, 0.0, 2.5)
    assert parse_blobs("0.5 20 0.05 5 1; 0.3, 2, 0.1, 1, 0.5;") == \
        [(0.5, 20.0, 0.05, 5.0, 1.0), (0.3, 2.0, 0.1, 1.0, 0.5)]


# ---------------------------------------------------------------------- lookups

def test05_kernel_lookup_matches_the_float64_twin():
    """Bilinear lookup of a random 7 x 11 table at random points, inside and outside both
    ranges and NaN: the kernel (float32) agrees with ``alpha_numpy`` to 1e-5."""
    import drjit as dr

    from mi_amr.kernels.transfer2d import alpha, transfer2d_inputs

    m = dr.llvm.ad
    rng = np.random.default_rng(3)
    tf = Transfer2D(rng.uniform(size=(7, 11)), -0.5, 1.5, 2.0, 30.0)
    v = np.concatenate([rng.uniform(-1.0, 2.0, 4000), [-0.5, 1.5, np.nan, 0.2]])
    g = np.concatenate([rng.uniform(0.0, 40.0, 4000), [2.0, 30.0, 3.0, np.nan]])
    got = alpha(m, transfer2d_inputs(m, tf, 1.0), m.Float(v), m.Float(g)).numpy()
    np.testing.assert_allclose(got, tf.alpha_numpy(v, g), atol=1e-5)
    assert np.all(got[(v < -0.5) | (v > 1.5)] == 0.0) and got[-2] == 0.0


def test06_rasterized_blobs_match_the_blob_formula():
    """Two blobs of very different widths: the table is within 0.005 of the formula at random
    points of the plane (8 samples per narrowest sigma bound the bilinear error at about 1/256
    of the peak per axis), and covers each blob to +- 3 sigma, from |grad f| = 0."""
    blobs = [(0.5, 20.0, 0.05, 5.0, 0.8), (0.3, 2.0, 0.2, 1.0, 0.6)]
    tf = from_blobs(blobs)
    assert tf.v0 == pytest.approx(0.3 - 0.6) and tf.v1 == pytest.approx(0.3 + 0.6)
    assert tf.g0 == 0.0 and tf.g1 == pytest.approx(35.0)
    rng = np.random.default_rng(0)
    v, g = rng.uniform(tf.v0, tf.v1, 20000), rng.uniform(tf.g0, tf.g1, 20000)
    np.testing.assert_allclose(tf.alpha_numpy(v, g), blobs_numpy(blobs, v, g), atol=5e-3)


def test07_png_exr_and_npy_give_the_same_image(variant, folder):
    """One table of 8-bit levels as ``.npy``, a grey PNG, an RGBA PNG (the table in alpha, junk
    in colour) and an EXR, each image's top row the highest |grad f|: the same image."""
    mi = variant
    table = np.round(threshold_table() * 255) / 255
    np.save(folder / "levels.npy", table)
    image = np.round(table[::-1] * 255).astype(np.uint8)
    mi.Bitmap(image[..., None]).write(str(folder / "grey.png"))
    rgba = np.stack([255 - image, image // 2, np.full_like(image, 7), image], axis=-1)
    mi.Bitmap(rgba, pixel_format=mi.Bitmap.PixelFormat.RGBA).write(str(folder / "alpha.png"))
    mi.Bitmap(table[::-1].astype(np.float32)[..., None]).write(str(folder / "table.exr"))
    ref = render(mi, scene(folder, table_xml("levels.npy")))
    assert ref.max() > 0.5
    for name in ("grey.png", "alpha.png", "table.exr"):
        np.testing.assert_allclose(render(mi, scene(folder, table_xml(name))), ref, atol=1e-6,
                                   err_msg=name)


@pytest.mark.parametrize("method", ["adaptive", "exact"])
def test08_a_new_table_compiles_nothing(variant, folder, method):
    """After a first frame, scenes with another table of the same shape, one of another
    shape and blobs (another shape and range) compile 0 kernels, and draw other images."""
    mi = variant
    rng = np.random.default_rng(1)
    np.save(folder / "t1.npy", threshold_table())
    np.save(folder / "t2.npy", threshold_table() * rng.uniform(0.2, 1.0, (9, 33)))
    np.save(folder / "t3.npy", threshold_table(rows=5, cols=17))
    # (a scene of an earlier test still alive would give the first scene other BSDF numbers
    # in Mitsuba's call tables, and so other kernels, than the ones loaded after it is gone)
    gc.collect()
    first = render(mi, scene(folder, table_xml("t1.npy"), method))
    gc.collect()
    for extra in (table_xml("t2.npy"), table_xml("t3.npy", "0.35 0.65 0 20"),
                  '<string name="transfer2d_blobs" value="0.5 30 0.05 10 1"/>'):
        image, compiled = kernels_compiled(lambda: render(mi, scene(folder, extra, method)))
        gc.collect()
        assert compiled == 0, f"{extra}: {compiled} kernel(s) compiled"
        assert not np.allclose(image, first)


# ---------------------------------------------------------------------- less haze

def _haze_and_boundary(one, two, far, boundary):
    """Mean accumulated opacity of the 1D band's and the 2D TF's images over the pixels whose
    rays never meet the boundary (``far``) and over those that cross it (``boundary``)."""
    return (one[far].mean(), two[far].mean()), (one[boundary].mean(), two[boundary].mean())


@pytest.mark.parametrize("method", ["exact", "uniform", "adaptive", "bisect"])
def test09_the_2d_transfer_function_has_less_haze_than_a_1d_band(variant, folder, method):
    """``boundary_and_blob``: 0.5 is crossed at the ball's sharp edge (|grad f| about 30 as
    reconstructed) and across the smooth blob (|grad f| 3.2). The 1D band (width 0.1) lights
    both; the 2D TF -- the same band's columns, zero below |grad f| = 10 -- only the edge.

    Haze: the mean accumulated opacity ``1 - T`` over the pixels whose rays pass more than
    0.03 outside the ball (float64 geometry of the orthographic view). Boundary: the same over
    the rays through the ball more than 0.03 inside its rim. Measured (adaptive): haze 0.148
    against 3e-6; boundary 0.975 against 0.974."""
    mi = variant
    one = render(mi, scene(folder, f'<float name="band_width" value="{BW}"/>', method))
    two = render(mi, scene(folder, table_xml(), method))
    (centre, radius, _) = datasets.BALL
    x = (np.arange(RES) + 0.5) / RES
    X, Z = np.meshgrid(x, 1.0 - x)
    rim = np.hypot(X - centre[0], Z - centre[2])
    (haze1, haze2), (edge1, edge2) = _haze_and_boundary(one, two, rim > radius + 0.03,
                                                        rim < radius - 0.03)
    assert haze1 > 0.1, "the 1D band should light the smooth blob"
    assert haze2 < 1e-3 * haze1, f"haze {haze2:.3g} (2D) against {haze1:.3g} (1D)"
    assert edge1 > 0.8 and edge2 > 0.95 * edge1, f"boundary {edge2:.3g} against {edge1:.3g}"


@pytest.mark.skipif(not (SHARED / "plt_eb_3d").is_dir(),
                    reason=f"AMReX sample plotfiles not found at {SHARED}")
@pytest.mark.parametrize("method", ["adaptive", "exact"])
def test10_plt_eb_3d_wall_with_less_haze(variant, tmp_path, method):
    """The real plotfile's wall, seen down the cylinder's axis (z). Its fluid density is
    constant (1.17985 nearly everywhere, |grad f| < 2.5) and drops to 0 at the wall (|grad f|
    about 1000): no value is crossed both at the wall and in a smooth stretch, so the smooth
    region here is the fluid that has the band's value. The 1D band (centre 1.17985, width
    0.3) fills the fluid; the 2D TF (its columns, zero below |grad f| = 20) draws the wall.
    Haze over the pixels more than 4 fine cells outside the wall; wall: the pixels within one
    fine cell of it. Measured: haze 0.988 against 0.006; wall 0.21 against 0.09 (the 2D TF
    keeps what is made at the wall, the 1D band adds the fluid there too)."""
    mi = variant
    iso, bw = 1.17985, 0.3
    vs, gs = np.linspace(iso - 2 * bw, iso + 2 * bw, 33), np.linspace(0, 100, 11)
    table = np.minimum(1.0, 1.6 * np.exp(-0.5 * ((vs - iso) / bw) ** 2))[None, :] * \
        (gs[:, None] >= 20)
    np.save(tmp_path / "eb.npy", table)
    view = ("0.02, 0.02, 1", "0.02, 0.02, 0", "0, 1, 0", 0.04, 0.02)
    kw = dict(filename=str(SHARED / "plt_eb_3d"), field="density", iso=iso, view=view,
              height=RES // 2, method=method)
    one = render(mi, scene(tmp_path, f'<float name="band_width" value="{bw}"/>', **kw))
    two = render(mi, scene(tmp_path, table_xml("eb.npy", f"{iso - 2 * bw} {iso + 2 * bw} 0 100"),
                           **kw))
    # Pixel (r, c) looks down at x = -0.02 + (c + 0.5) h0, y = 0.04 - (r + 0.5) h0 (h0 the
    # coarse cell, 0.00125); the obstacle is the cylinder of radius 0.006 around x = 0,
    # y = 0.02 (its cut cells, volFrac < 1, span fine cells 22-41 on both axes).
    h0, h1, radius = 0.00125, 0.000625, 0.006
    X, Y = np.meshgrid(-0.02 + (np.arange(RES) + 0.5) * h0, 0.04 - (np.arange(RES // 2) + 0.5) * h0)
    d = np.hypot(X, Y - 0.02)
    (haze1, haze2), (wall1, wall2) = _haze_and_boundary(one, two, d > radius + 4 * h1,
                                                        np.abs(d - radius) < h1)
    assert haze1 > 0.5 and haze2 < 0.02 * haze1, f"haze {haze2:.3g} against {haze1:.3g}"
    assert wall2 > 0.05 and wall2 > 0.3 * wall1, f"wall {wall2:.3g} against {wall1:.3g}"


def test10_a_table_set_through_traverse_compiles_nothing(variant, folder):
    """``integrator.transfer2d_table`` and ``transfer2d_range`` in ``mi.traverse``: a new table
    and range of the same shape render without compiling, as a scene loaded with that table
    renders; another shape or an opacity above 1 is refused, naming the parameter."""
    import drjit as dr

    from mi_amr.plugin.scene import load_scene

    mi = variant
    rng = np.random.default_rng(2)
    other = threshold_table() * rng.uniform(0.2, 1.0, (9, 33))
    np.save(folder / "t_other.npy", other)
    other_range = f"{ISO - 3 * BW:g} {ISO + 2 * BW:g} 0 {G_MAX / 2:g}"
    expected = render(mi, scene(folder, table_xml("t_other.npy", other_range)))
    gc.collect()
    live = load_scene(scene(folder, table_xml()))
    first = mi.render(live)
    dr.eval(first)
    params = mi.traverse(live)
    table = next(k for k in params.keys() if k.endswith(".transfer2d_table"))
    params[table] = mi.Float(other.ravel())
    params[table.replace("_table", "_range")] = mi.Float([float(x) for x in
                                                          other_range.split()])
    params.update()

    def again():
        img = mi.render(live)
        dr.eval(img)
        return np.array(img, dtype=np.float64)[..., 0]

    image, compiled = kernels_compiled(again)
    assert compiled == 0
    assert not np.allclose(image, np.array(first, dtype=np.float64)[..., 0])
    np.testing.assert_allclose(image, expected, atol=1e-5)
    for value, message in [(np.zeros(10), "must keep 297 value"),
                           (np.full(297, 1.5), "opacities must lie in")]:
        params[table] = mi.Float(value)
        with pytest.raises(AMRError, match=message):
            params.update()
        params[table] = mi.Float(other.ravel())
        params.update()
