"""Every per-dataset and per-frame value is a kernel input: a new data file, a new colour map or
colour range, or the first change of any value in ``mi.traverse`` compiles no kernel.

Compiled kernels are counted with ``dr.kernel_history()`` (:func:`conftest.kernels_compiled`:
a kernel not found in memory counts, also one loaded from Dr.Jit's disk cache).
"""

import gc

import numpy as np
import pytest

from conftest import kernels_compiled, random_grids, small_scene
from mi_amr import AMRVolume, params
from mi_amr.synthetic import datasets

RES = 24


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


def scene_xml(folder, colormap=True, mode="surface", method="exact", iso="0.3"):
    """A small scene reading ``$filename`` (field ``f``), coloured by ``f`` itself."""
    colour = ('<string name="color_field" value="f"/>'
              '<string name="colormap" value="0.1: 0 0 1, 0.3: 0 1 0, 0.5: 1 0 0"/>'
              if colormap else "")
    return small_scene(folder, f"""
            <string name="filename" value="$filename"/>
            <string name="field" value="f"/>
            <string name="isovalue" value="{iso}"/>
            <string name="mode" value="{mode}"/>
            <string name="method" value="{method}"/>
            {colour}""", RES, '<default name="filename" value="a.npz"/>')


def distance_field(centre=(0.5, 0.5, 0.5)):
    return lambda p: np.linalg.norm(p - np.asarray(centre), axis=-1)


def _scaled(vol, s):
    """``vol`` with its world space scaled by ``s`` (values scaled too: a distance field)."""
    return AMRVolume.from_grids([{"level": g.level, "origin": tuple(np.asarray(g.origin) * s),
                                  "spacing": tuple(np.asarray(g.spacing) * s),
                                  "fields": {"f": g.fields["f"] * s}} for g in vol.grids])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Volumes of one field ``f`` with different grids, levels and extents: the analytic
    sphere at two resolutions, the torus, and a random three-level hierarchy (8 x 6 x 6
    level-0 cells of 1/8)."""
    folder = tmp_path_factory.mktemp("opaque")
    vols = {"a.npz": datasets.sphere(8), "b.npz": datasets.sphere(16), "c.npz": datasets.torus(8),
            "d.npz": _scaled(AMRVolume.from_grids(random_grids(3, num_levels=3,
                                                               fn=distance_field((4, 3, 3)))),
                             0.125)}
    for name, vol in vols.items():
        vol.save(folder / name)
    return folder


def render(mi, scene, seed=0):
    import drjit as dr

    img = mi.render(scene, seed=seed)
    dr.eval(img)
    return np.array(img)


def test01_a_new_data_file_compiles_nothing(variant, files):
    """Scenes of the same structure on four files (other grids, 2 or 3 levels, other bounds):
    after the first, each compiles 0 kernels, whether the scene is loaded anew (once the old
    one is gone: Mitsuba numbers the BSDFs of every live scene into the kernels) or the
    integrator is pointed at the next file."""
    mi = variant
    from mi_amr.plugin.scene import load_scene

    path = scene_xml(files)
    render(mi, load_scene(path, filename="a.npz"))
    gc.collect()
    for name in ("b.npz", "c.npz", "d.npz"):
        scene = load_scene(path, filename=name)
        image, compiled = kernels_compiled(lambda: render(mi, scene))
        assert compiled == 0, f"{name}: {compiled} kernel(s) compiled for a new data file"
        assert image.sum() > 0, f"{name}: a black image"
        del scene
        gc.collect()
    scene = load_scene(path, filename="a.npz")
    first = render(mi, scene)
    scene.integrator().load_volume(str(files / "d.npz"))
    image, compiled = kernels_compiled(lambda: render(mi, scene))
    assert compiled == 0
    assert not np.allclose(image, first)


CHANGES = {
    "isovalue": lambda mi: mi.Float(0.25),
    "iso_color": lambda mi: mi.Float([0.2, 0.3, 0.4]),
    "iso_opacity": lambda mi: mi.Float(0.5),
    "step_scale": lambda mi: mi.Float(0.25),
    "shadows": lambda mi: mi.Bool(False),
    "ka": lambda mi: mi.Float(0.3),
    "kd": lambda mi: mi.Float(0.5),
    "ks": lambda mi: mi.Float(0.1),
    "shininess": lambda mi: mi.Float(8.0),
    "ambient": lambda mi: mi.Float(0.5),
    "color_range": lambda mi: mi.Float([0.2, 0.6]),
    "to_world": lambda mi: mi.Transform4f().translate([0.02, 0.0, 0.0]),
    "band_width": lambda mi: mi.Float(0.02),
    "band_offsets": lambda mi: mi.Float([-0.03, 0.05]),
    "band_peak": lambda mi: mi.Float(0.8),
}


@pytest.mark.parametrize("mode", ["surface", "volume"])
def test02_the_first_change_of_every_traversable_value_compiles_nothing(variant, files, mode):
    """Each value in ``mi.traverse`` changed once, right after the first frame, then a frame:
    0 kernels compiled, and the value took effect (the image changed, except for the values
    that do not show here: the isovalue's colour under a colour map, its opacity in volume
    mode)."""
    mi = variant
    from mi_amr.plugin.scene import load_scene

    scene = load_scene(scene_xml(files, mode=mode, method="adaptive"))
    p = mi.traverse(scene)
    keys = [k for k in p.keys() if k.startswith("integrator.")]
    expected = {"colormap_values", "colormap_colors", *CHANGES} - \
        ({"band_width", "band_offsets", "band_peak"} if mode == "surface" else set())
    assert {k.split(".", 1)[1] for k in keys} == expected
    unseen = {"iso_color"} | ({"iso_opacity"} if mode == "volume" else set())
    before = render(mi, scene)
    for name, value in CHANGES.items():
        key = f"integrator.{name}"
        if key not in p:
            continue
        p[key] = value(mi)
        p.update()
        image, compiled = kernels_compiled(lambda: render(mi, scene))
        assert compiled == 0, f"changing {name} compiled {compiled} kernel(s)"
        if name not in unseen:     # the colour map colours this scene; the band has no opacity
            assert not np.allclose(image, before), f"changing {name} changed nothing"
        before = image


def test03_a_new_colour_map_compiles_nothing(variant, files):
    """A matplotlib map in place of the pairs, and back to other pairs, through ``mi.traverse``
    (:func:`mi_amr.plugin.inputs.colormap_table`): 0 kernels, other colours."""
    mi = variant
    from mi_amr.plugin.inputs import colormap_table
    from mi_amr.plugin.scene import load_scene

    scene = load_scene(scene_xml(files))
    p = mi.traverse(scene)
    before = render(mi, scene)
    for spec in ("viridis", "0.2: 1 1 0, 0.4: 0 1 1", "magma"):
        edges, colors, rng = colormap_table(spec, (0.0, 0.6))
        p["integrator.colormap_values"] = mi.Float(edges)
        p["integrator.colormap_colors"] = mi.Float(colors)
        p["integrator.color_range"] = mi.Float(rng)
        p.update()
        image, compiled = kernels_compiled(lambda: render(mi, scene))
        assert compiled == 0, f"colour map {spec}: {compiled} kernel(s) compiled"
        assert not np.allclose(image, before)
        before = image


def test04_changes_that_would_break_the_structure_are_refused(variant, files):
    """A different number of isovalues, a table of another size or a decreasing table through
    ``mi.traverse`` are refused with an AMRError that names the value."""
    mi = variant
    from mi_amr import AMRError
    from mi_amr.plugin.scene import load_scene

    scene = load_scene(scene_xml(files))
    p = mi.traverse(scene)
    for key, value, message in [
            ("isovalue", mi.Float([0.2, 0.3]), "'isovalue' must keep 1 value"),
            ("colormap_values", mi.Float([0.0, 1.0]), "'colormap_values' must keep 512"),
            ("colormap_values", mi.Float(np.linspace(1, 0, 512)), "must not decrease"),
            ("iso_opacity", mi.Float(1.5), "'iso_opacity' must lie in"),
            ("color_range", mi.Float([1.0, 0.0]), "'color_range' needs finite low < high")]:
        old = mi.Float(p[f"integrator.{key}"])
        p[f"integrator.{key}"] = value
        with pytest.raises(AMRError, match=message):
            p.update()
        p[f"integrator.{key}"] = old
        p.update()


def test05_the_traversable_parameters_are_the_tables():
    """What the integrator puts in ``mi.traverse`` is what the parameter table marks."""
    marked = set(params.TRAVERSABLE)
    put = set(CHANGES) | {"colormap_values", "colormap_colors", "transfer2d_table",
                          "transfer2d_range"}
    renamed = {"colormap": {"colormap_values", "colormap_colors"},
               "band_support": {"band_offsets"},
               "transfer2d": {"transfer2d_table", "transfer2d_range"}}
    for name, keys in renamed.items():
        assert name in marked
        marked = (marked - {name}) | keys
    assert marked == put


def _still_scene(files, jitter):
    path = scene_xml(files, method="adaptive")
    text = path.read_text().replace(
        '<sampler type="independent"><integer name="sample_count" value="1"/></sampler>',
        '<sampler type="stratified"><integer name="sample_count" value="1"/>'
        '<boolean name="jitter" value="false"/></sampler>')
    # A box filter: each sample lands in its own pixel only. The default Gaussian splats it
    # into the neighbours too, summed by threads in varying order, which differs in the last
    # bit from frame to frame whatever the jitter (seen once in a run of the suite).
    text = text.replace('<string name="pixel_format" value="rgb"/>',
                        '<string name="pixel_format" value="rgb"/><rfilter type="box"/>')
    text = text.replace('<string name="method" value="adaptive"/>',
                        f'<string name="method" value="adaptive"/>'
                        f'<float name="step_scale" value="2"/>'
                        f'<string name="jitter" value="{jitter}"/>')
    path.write_text(text)
    return path


def test06_a_still_camera_does_not_flicker_with_stable_jitter(variant, files):
    """Pixel centres (no antialiasing jitter) and the adaptive method with coarse steps: with
    ``jitter="stable"`` two frames with different sampler seeds are the same image, and the
    offsets do vary from pixel to pixel (the image differs from one with the sampler's constant
    0.5 of a non-jittered stratified sampler, ``jitter="random"``)."""
    mi = variant
    from mi_amr.plugin.scene import load_scene

    stable = load_scene(_still_scene(files, "stable"))
    a, b = render(mi, stable, seed=1), render(mi, stable, seed=2)
    np.testing.assert_array_equal(a, b)
    del stable
    gc.collect()
    constant = render(mi, load_scene(_still_scene(files, "random")), seed=1)
    assert not np.array_equal(a, constant)
