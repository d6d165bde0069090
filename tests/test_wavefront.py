"""The integrator's render loop (:mod:`mi_amr.plugin.wavefront`): pixels in tiles, and the same
images as Mitsuba's scanline loop (its slow twin)."""

import textwrap

import numpy as np
import pytest
from conftest import kernels_compiled
from hypothesis import given, settings
from hypothesis import strategies as st

from mi_amr.synthetic import datasets

pytest.importorskip("mitsuba")


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


def _order(width, height):
    from mi_amr.plugin.wavefront import pixel_order

    return pixel_order(width, height)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 70), st.integers(1, 70))
def test01_the_pixel_order_is_a_permutation(width, height):
    order = _order(width, height)
    assert order.dtype == np.uint32
    assert np.array_equal(np.sort(order), np.arange(width * height))


def test02_a_packet_of_16_lanes_is_a_square_of_4_x_4_pixels():
    """Where the film is a whole number of tiles each run of 16 lanes is one 4 x 4 square, and
    each run of 32 x 32 pixels one 32 x 32 square (lanes a thread takes in a row)."""
    from mi_amr.plugin.wavefront import SUPER, TILE

    width, height = 96, 64
    y, x = np.divmod(_order(width, height).astype(np.int64), width)
    for run, side in ((TILE * TILE, TILE), (SUPER * SUPER, SUPER)):
        ys, xs = y.reshape(-1, run), x.reshape(-1, run)
        assert np.all(ys.max(axis=1) - ys.min(axis=1) == side - 1)
        assert np.all(xs.max(axis=1) - xs.min(axis=1) == side - 1)
        assert np.all(ys.min(axis=1) % side == 0) and np.all(xs.min(axis=1) % side == 0)


SCENE = """
<scene version="3.0.0">
    <integrator type="amr_iso"><string name="filename" value="sphere.npz"/>
        <string name="field" value="f"/><float name="isovalue" value="0.3"/>
        <boolean name="aovs" value="{aovs}"/><string name="method" value="{method}"/>
        <string name="mode" value="{mode}"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="45"/>
        <transform name="to_world">
            <lookat origin="0.5, -0.9, 1.4" target="0.5, 0.5, 0.3" up="0, 0, 1"/>
        </transform>
        <sampler type="{sampler}"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{width}"/>
            <integer name="height" value="{height}"/>
            <string name="pixel_format" value="{pixels}"/>
            <rfilter type="{rfilter}"/>
        </film>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><scale value="1.5"/><translate x="0.5" y="0.5"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf>
    </shape>
    <emitter type="directional"><vector name="direction" value="0.3, 0.2, -1"/>
        <rgb name="irradiance" value="2"/></emitter>
</scene>"""


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("wavefront")
    datasets.sphere(8).save(out / "sphere.npz")
    return out


def _scene(folder, name, **kw):
    from mi_amr.plugin.scene import load_scene

    values = dict(aovs="false", method="exact", spp=4, width=36, height=28, pixels="rgb",
                  rfilter="box", sampler="independent", mode="surface")
    values.update(kw)
    path = folder / f"{name}.xml"
    path.write_text(textwrap.dedent(SCENE.format(**values)))
    return load_scene(path)


CASES = {
    "rgb, box filter": {},
    "rgba with the AOVs, gaussian filter": dict(aovs="true", pixels="rgba", rfilter="gaussian"),
    "adaptive (stable jitter), 1 spp, odd size": dict(method="adaptive", spp=1, width=23,
                                                     height=17),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test03_in_scanline_order_the_loop_renders_what_mitsubas_loop_renders(variant, folder, case):
    """``Twins(tile_order=False)``: the loop's image equals that of Mitsuba's own
    ``SamplingIntegrator.render`` (the same sampler streams, sample positions, film channels,
    alpha and AOVs) up to float rounding."""
    mi = variant
    from mi_amr.plugin.twins import Twins, with_twins

    scene = _scene(folder, "twin", **CASES[case])
    integ = scene.integrator()
    scanlines = with_twins(integ, Twins(tile_order=False))
    ours = np.array(mi.render(scene, seed=5, integrator=scanlines))
    # (The twin that hands every frame to Mitsuba's loop, as where wavefront does not apply.)
    theirs = np.array(mi.render(scene, seed=5,
                                integrator=with_twins(integ, Twins(wavefront_loop=False))))
    assert ours.shape == theirs.shape and ours.shape[2] >= 3
    assert ours[..., :3].std() > 0.01, "the test scene shows nothing"   # (AOV depth: inf)
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-6)


def test04_tiled_lanes_give_the_same_image_up_to_noise(variant, folder):
    """Tile order gives each pixel another lane's sampler stream: against Mitsuba's loop at
    another seed the image differs no more than Mitsuba's loop does from itself at that seed,
    and the mean agrees."""
    mi = variant
    scene = _scene(folder, "noise", spp=16, width=48, height=48)
    from mi_amr.plugin.twins import Twins, with_twins

    scanlines = with_twins(scene.integrator(), Twins(tile_order=False))
    scan = [np.array(mi.render(scene, seed=s, integrator=scanlines), dtype=np.float64)
            for s in (0, 1)]
    tiled = np.array(mi.render(scene, seed=0), dtype=np.float64)
    rmse = lambda a, b: np.sqrt(np.mean((a - b) ** 2))  # noqa: E731
    assert rmse(tiled, scan[0]) > 0, "tile order changed nothing"
    assert rmse(tiled, scan[1]) < 1.5 * rmse(scan[0], scan[1])
    assert abs(tiled.mean() - scan[0].mean()) < 0.01 * scan[0].mean()


def test05_a_new_film_size_compiles_no_more_than_mitsubas_loop(variant, folder):
    """The tile order and the film's size are kernel inputs of the loop; Mitsuba's own parts
    (the image block's size) compile one kernel for a new film size, in either loop."""
    mi = variant
    from mi_amr.plugin.twins import Twins, with_twins

    scene = _scene(folder, "sizes", spp=1, width=32, height=32)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("film.size"))

    def resized(width, height, integrator=None):
        params[key] = mi.ScalarVector2u(width, height)
        params.update()
        return kernels_compiled(lambda: np.array(mi.render(scene, integrator=integrator)))

    mi.render(scene)
    image, ours = resized(40, 24)
    assert image.shape[:2] == (24, 40)
    _, again = resized(40, 24)
    mitsubas = with_twins(scene.integrator(), Twins(wavefront_loop=False))
    mi.render(scene, integrator=mitsubas)
    _, theirs = resized(44, 20, mitsubas)
    assert again == 0 and ours <= theirs


@pytest.mark.parametrize("mode", ["surface", "volume"])
def test06_a_stratified_sampler_keeps_its_strata_per_pixel_in_tile_order(variant, folder, mode):
    """The volume scenes draw multi-jittered pixel samples: each pixel's samples must be one
    of the sampler's sequences (its strata), in tile order as in scanlines, or the image
    converges no faster than with independent samples. At 16 spp the error against 256 spp
    is well below the independent sampler's, and the tiled image's matches the scanline
    twin's."""
    mi = variant
    from mi_amr.plugin.twins import Twins, with_twins

    kw = dict(width=32, height=32, rfilter="box", mode=mode)
    reference = np.array(mi.render(_scene(folder, "strata_ref", spp=256, sampler="multijitter",
                                        **kw), seed=9),
                         dtype=np.float64)
    rmse = lambda a: np.sqrt(np.mean((a - reference) ** 2))  # noqa: E731
    errors = {}
    for sampler in ("independent", "multijitter"):
        scene = _scene(folder, f"strata_{sampler}", spp=16, sampler=sampler, **kw)
        scanlines = with_twins(scene.integrator(), Twins(tile_order=False))
        errors[sampler] = [np.mean([rmse(np.array(mi.render(scene, seed=s, **extra),
                                                   dtype=np.float64)) for s in (1, 2, 3)])
                           for extra in ({}, {"integrator": scanlines})]
    assert reference[..., :3].std() > 0.01, "the test scene shows nothing"
    tiled, scan = errors["multijitter"]
    assert tiled < 0.75 * errors["independent"][0], errors
    assert tiled < 1.2 * scan, errors
    # `python -m mi_amr render` and the viewer render in passes: a pixel's 16 samples stay in
    # one, so they keep their strata.
    import drjit as dr

    from mi_amr.workflows.render import render_passes

    passes = rmse(render_passes(mi, dr, np, scene, 16, quiet=True)[..., :3])
    assert passes < 0.75 * errors["independent"][0], (passes, errors)


def test07_a_sampler_that_rounds_its_count_renders_what_mitsubas_loop_renders(variant, folder):
    """A stratified sampler keeps a square number of samples (3 spp become 4): the wavefront
    takes the count the sampler kept, as Mitsuba's loop does (it crashed on a wavefront of
    the count asked for)."""
    mi = variant
    from mi_amr.plugin.twins import Twins, with_twins

    scene = _scene(folder, "rounded", spp=1, sampler="stratified")
    integ = scene.integrator()
    ours = np.array(mi.render(scene, seed=3, spp=3,
                              integrator=with_twins(integ, Twins(tile_order=False))))
    theirs = np.array(mi.render(scene, seed=3, spp=3,
                                integrator=with_twins(integ, Twins(wavefront_loop=False))))
    assert ours[..., :3].std() > 0.01, "the test scene shows nothing"
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-6)
    tiled = np.array(mi.render(scene, seed=3, spp=3), dtype=np.float64)
    assert abs(tiled.mean() - theirs.mean()) < 0.02 * theirs.mean()


def test07b_the_wavefront_size_check_counts_the_samples_the_sampler_keeps(variant):
    """:func:`wavefront.supported` leaves a wavefront of 2^32 lanes or more to Mitsuba's loop;
    it counts the samples a frame takes: 3 asked of a stratified sampler are 4, so a film of
    2^30 pixels (a stand-in: a real one would hold gigabytes) is too large at 3 spp, and an
    independent sampler keeps 3. A pass of a set takes the count given."""
    mi = variant
    from mi_amr.plugin import wavefront

    class Film:
        def crop_size(self):
            return (1 << 15, 1 << 15)

        def rfilter(self):
            return mi.load_dict({"type": "box"})

        def sample_border(self):
            return False

        def flags(self):
            return 0

    class Sensor:
        def __init__(self, sampler):
            self._sampler = mi.load_dict({"type": sampler, "sample_count": 1})

        def film(self):
            return Film()

        def sampler(self):
            return self._sampler

    assert not wavefront.supported(Sensor("stratified"), 3)
    assert wavefront.supported(Sensor("independent"), 3)
    assert wavefront.supported(Sensor("stratified"), 3, part=(0, 9))
    assert not wavefront.supported(Sensor("independent"), 4)


def test08_a_stratified_samplers_passes_are_parts_of_one_set(variant, folder, scene_data_ready):
    """With a sampler that stratifies, the render workflow's and the viewer's passes are
    equal parts of one set of the image's samples at one seed (one sample a pass up to 16):
    the progress bar moves, each stratum is drawn once, and no pass compiles a kernel of its
    own. With the independent sampler the passes are as before."""
    mi = variant
    from mi_amr.plugin.scene import load_scene
    from mi_amr.workflows import project
    from mi_amr.workflows.render import Pass, pass_samples, render_pass, scene_passes
    from mi_amr.workflows.render import stratified_passes as plan

    volume = load_scene(project.scenes_dir() / "sphere_wake_volume.xml", resx=8, resy=8, spp=1)
    assert scene_passes(volume, 4) == [Pass(0, 1, j, 4) for j in range(4)]
    for total in (1, 2, 3, 16, 17, 20, 64, 100, 1000, 1001):
        passes = plan(total)
        q = -(-total // 16)
        assert sum(p.spp for p in passes) == total and max(p.spp for p in passes) == q
        assert len(passes) <= 17 and (total > 16 or len(passes) == total)
        for seed in {p.seed for p in passes}:          # each set: its passes, end to end
            parts = [p for p in passes if p.seed == seed]
            assert [p.first for p in parts] == [parts[0].spp * i for i in range(len(parts))]
            assert len({p.spp for p in parts}) == 1
            assert {p.count for p in parts} == {sum(p.spp for p in parts)}
    assert plan(100)[-1] == Pass(1, 2, 0, 2) and len(plan(64)) == 16
    assert plan(16, 4) == [Pass(0, 4, first, 16) for first in (0, 4, 8, 12)]   # (stochastic
    assert plan(3, 4) == [Pass(0, 3, 0, 3)]                                     # layers)
    surface = _scene(folder, "independent_passes", spp=1)
    assert scene_passes(surface, 20) == [Pass(s, n) for s, n in enumerate(pass_samples(20))]

    scene = _scene(folder, "stratified_passes", spp=1, sampler="multijitter")
    images = [np.array(render_pass(mi, scene, p)) for p in plan(3)[:1]]
    compiled = [kernels_compiled(lambda p=p: np.array(render_pass(mi, scene, p)))[1]
                for p in plan(3)[1:]]
    assert compiled == [0, 0], compiled
    assert images[0][..., :3].std() > 0.01, "the test scene shows nothing"
    with pytest.raises(ValueError, match="not a pass of a set"):
        render_pass(mi, scene, Pass(0, 2, 1, 4))
