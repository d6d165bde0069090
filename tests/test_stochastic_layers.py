"""Translucent isosurfaces with one layer per sample (``layers="stochastic"``) or one shadow ray
per light and sample (``layers="one_shadow"``): the same image in expectation as front-to-back
compositing with a shadow ray per layer.

* :func:`~mi_amr.plugin.layers.pick_one` on made-up layers: averaged over evenly spread ``u``
  it gives :func:`~mi_amr.plugin.layers.front_to_back`'s radiance and transmittance, to the
  spread's step, with ``max_layers`` cutting the ray short too.
* :func:`~mi_amr.plugin.layers.one_shadow_ray` on made-up layers that see the light
  differently: averaged over evenly spread ``u`` it gives a shadow ray per layer's radiance;
  where they see it alike, every ``u`` gives it.
* Images: both scenes at many samples per pixel are the composited one within the samples'
  noise (what two seeds of each scene differ by), with no bias.

The scene is sphere_wake.xml with three isovalues of opacity 0.4, 0.5 and 0.6.
"""

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from mi_amr.errors import AMRError  # noqa: E402
from mi_amr.plugin.scene import load_scene  # noqa: E402
from mi_amr.workflows import project  # noqa: E402

TRANSLUCENT = {"isovalue": "0.02, 0.05, 0.1", "iso_opacity": "0.4, 0.5, 0.6"}
SPREAD = 1000          # evenly spread u per made-up ray / shadow ray


def made_up_layers(mi):
    """Callbacks of three layers of opacity 0.5, 0.5 and 1 with radiance 1, 2 and 4 (layer
    ``k`` at ``t = k + 0.5``)."""
    alphas, radiance = [0.5, 0.5, 1.0], [1.0, 2.0, 4.0]

    def crossing(t, alive):
        k = mi.UInt32(mi.Float(t))
        hit = alive & (k < 3)
        return hit, mi.Float(k) + 0.5, mi.Float(k) + 1.0, k

    def pick(values, k):
        return dr.select(k == 0, values[0], dr.select(k == 1, values[1], values[2]))

    def shade(hit, where, k):
        return mi.Spectrum(pick(radiance, k))

    return crossing, (lambda k: pick(alphas, k)), shade


@pytest.mark.parametrize("max_layers", [8, 2, 1])
def test01_picking_one_layer_averages_to_compositing_them(variant, max_layers):
    mi = variant
    from mi_amr.plugin.layers import front_to_back, pick_one

    crossing, opacity, shade = made_up_layers(mi)
    u = mi.Float((np.arange(SPREAD) + 0.5) / SPREAD)
    start = dr.zeros(mi.Float, SPREAD)
    L, T = pick_one(start, crossing, opacity, shade, max_layers, u, mi.Float(dr.inf),
                    mi.Bool(True))
    L_ref, T_ref = front_to_back(mi.Float(0.0), crossing, opacity, shade, max_layers,
                                 mi.Bool(True))
    L, T = np.array(L)[0], np.array(T)
    assert set(np.unique(T)) <= {0.0, 1.0}
    assert L.mean() == pytest.approx(np.array(L_ref)[0, 0], abs=4.0 / SPREAD)
    assert T.mean() == pytest.approx(np.array(T_ref)[0], abs=1.0 / SPREAD)
    # Each sample shows one layer's own radiance, or none.
    assert set(np.unique(L)) <= {0.0, 1.0, 2.0, 4.0}


@pytest.mark.parametrize("max_layers", [8, 2])
def test05_one_shadow_ray_averages_to_a_shadow_ray_per_layer(variant, max_layers):
    """Made-up layers with ambient light 0.1, 0.2, 0.4 and direct light 1, 2, 4 (times
    colour channels 1, 2, 3) whose shadow rays see 1, 0.5 and 0 of it (the ray's ``maxt``
    carries the layer): averaged over evenly spread ``u``, one shadow ray from a layer picked
    by its share gives what a shadow ray from every layer gives; where all layers see the
    light alike (V = 0.5 for all) every ``u`` gives it exactly."""
    mi = variant
    from mi_amr.plugin.layers import front_to_back, one_shadow_ray

    crossing, opacity, _ = made_up_layers(mi)

    def pick(values, k):
        return dr.select(k == 0, values[0], dr.select(k == 1, values[1], values[2]))

    def parts(hit, where, k):
        base = mi.Spectrum(pick([0.1, 0.2, 0.4], k))
        direct = mi.Spectrum(1.0, 2.0, 3.0) * pick([1.0, 2.0, 4.0], k)
        ray = dr.zeros(mi.Ray3f, dr.width(k))
        ray.maxt = mi.Float(k)
        return base, [(direct, ray)]

    for seen in ([1.0, 0.5, 0.0], [0.5, 0.5, 0.5]):
        def visible(ray, on):
            return pick(seen, mi.UInt32(ray.maxt))

        def shade(hit, where, k):
            base, ((direct, ray),) = parts(hit, where, k)
            return base + direct * visible(ray, hit)

        u = mi.Float((np.arange(SPREAD) + 0.5) / SPREAD)
        start = dr.zeros(mi.Float, SPREAD)
        L, T = one_shadow_ray(start, crossing, opacity, parts, visible, max_layers, u, 1,
                              mi.Bool(True))
        L_ref, T_ref = front_to_back(mi.Float(0.0), crossing, opacity, shade, max_layers,
                                     mi.Bool(True))
        L, ref = np.array(L), np.array(L_ref)[:, 0]
        np.testing.assert_allclose(np.array(T), np.array(T_ref)[0], rtol=1e-6)
        np.testing.assert_allclose(L.mean(axis=1), ref, rtol=2e-3)
        if seen[0] == seen[2]:
            np.testing.assert_allclose(L, np.broadcast_to(ref[:, None], L.shape), rtol=1e-5)


def render(seed, **kw):
    """The translucent scene at 64^2, 128 spp."""
    sc = load_scene(project.scenes_dir() / "sphere_wake.xml", resx=64, resy=64, spp=128,
                    integrator=dict(TRANSLUCENT, **kw))
    return np.array(mi.render(sc, seed=seed), dtype=np.float64)


@pytest.fixture(scope="module")
def composited(scene_data_ready):
    return render(0), render(1)


@pytest.mark.parametrize("layers", ["stochastic", "one_shadow"])
def test02_many_samples_give_the_composited_image(composited, layers):
    """Measured (64^2, 128 spp; mean squared differences per pixel and channel): composited,
    two seeds 3.2e-5; stochastic, two seeds 1.05e-4 (the price of one layer a sample);
    stochastic against composited 7.2e-5, 1.045x the mean of the two; bias over the image
    -1.8e-5, over 8x8-pixel blocks 0.67x the blocks' noise. One shadow ray per sample
    (``one_shadow``): two seeds 6.1e-5, against composited 4.5e-5 and 4.7e-5, 0.96x and 1.0x
    the mean; bias over the image 1.9e-5, over blocks 0.38x their noise."""
    a0, a1 = composited
    s0, s1 = render(0, layers=layers), render(1, layers=layers)
    assert a0.mean() > 0.1
    # Two renders that agree in expectation differ by their noise alone: the mean squared
    # difference of these and the composited is the mean of each one's with another seed.
    def msd(x, y):
        return np.mean((x - y) ** 2)

    noise_a, noise_s = msd(a0, a1), msd(s0, s1)
    assert noise_s < 5.0 * noise_a
    for s, a in ((s0, a1), (s1, a0)):
        assert msd(s, a) < 1.1 * (noise_a + noise_s) / 2
    # No bias: the mean over the image and over 8x8-pixel blocks.
    bias = ((s0 + s1) - (a0 + a1)) / 2
    assert abs(bias.mean()) < 3e-4

    def blocks(x):
        return x.reshape(8, 8, 8, 8, -1).mean(axis=(1, 3))

    block_noise = np.sqrt((np.abs(blocks(a0) - blocks(a1)).mean() ** 2 +
                           np.abs(blocks(s0) - blocks(s1)).mean() ** 2) / 2)
    assert np.abs(blocks(bias)).mean() < 1.15 * block_noise / np.sqrt(2)


def test03_layers_is_checked(scene_data_ready):
    with pytest.raises(AMRError, match="layers"):
        load_scene(project.scenes_dir() / "sphere_wake.xml", resx=8, resy=8, spp=1,
                   integrator={"layers": "random"})
    with pytest.raises(AMRError, match="layers"):
        load_scene(project.scenes_dir() / "sphere_wake.xml", resx=8, resy=8, spp=1,
                   integrator={"layers": "stochastic", "mode": "volume"})


@pytest.mark.parametrize("layers", ["stochastic", "one_shadow"])
def test04_picks_repeat_with_the_seed_and_new_opacities_compile_nothing(scene_data_ready,
                                                                        layers):
    """A frame at one seed is the same every time (a still camera does not flicker); passes
    at other seeds pick other layers (so they converge); new opacities and isovalues render
    without compiling a kernel."""
    from conftest import kernels_compiled

    sc = load_scene(project.scenes_dir() / "sphere_wake.xml", resx=32, resy=32, spp=2,
                    integrator=dict(TRANSLUCENT, layers=layers))
    first = np.array(mi.render(sc, seed=0))
    # (to an ulp or two: renders after the first differ from it by that, composited too)
    np.testing.assert_allclose(np.array(mi.render(sc, seed=0)), first, rtol=0, atol=1e-6)
    assert np.abs(np.array(mi.render(sc, seed=1)) - first).max() > 0.05
    params = mi.traverse(sc)
    params["integrator.iso_opacity"] = mi.Float([0.2, 0.3, 0.9])
    params["integrator.isovalue"] = mi.Float([0.03, 0.06, 0.12])
    params.update()
    img, compiled = kernels_compiled(lambda: np.array(mi.render(sc, seed=0)))
    assert compiled == 0
    assert np.abs(img - first).mean() > 1e-3


SCALAR_CHILD = """
import sys, numpy as np, mitsuba as mi
mi.set_variant("scalar_rgb")
import mi_amr
out = []
for layers in ("composite", "one_shadow", "stochastic"):
    scene = mi.load_dict({"type": "scene",
        "integrator": {"type": "amr_iso", "filename": sys.argv[1], "field": "q_criterion",
                       "isovalue": "0.02, 0.05, 0.1", "iso_opacity": "0.4, 0.5, 0.6",
                       "layers": layers},
        "sensor": {"type": "perspective", "fov": 30, "to_world": mi.ScalarTransform4f().look_at(
                       origin=[-10, 8, 20], target=[2, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 4, "height": 4},
                   "sampler": {"type": "independent", "sample_count": 2}},
        "light": {"type": "directional", "direction": [0.3, -1, -0.2],
                  "irradiance": {"type": "rgb", "value": 3.0}}})
    out.append(np.array(mi.render(scene, seed=0), dtype=np.float64))
# And a scene file through mi_amr's own loader (which writes no camera values back there).
from mi_amr.plugin.scene import load_scene
scene = load_scene(sys.argv[3], resx=4, resy=4, spp=1, integrator={"layers": "stochastic",
                   "iso_opacity": "0.5"})
out.append(np.array(mi.render(scene, seed=0), dtype=np.float64)[..., :3])
np.save(sys.argv[2], np.array(out))
"""


def test06_scalar_variants_render_every_layer_mode(scene_data_ready, tmp_path):
    """scalar_rgb runs the layer loops on Python numbers: no division by zero, no ``~`` of a
    bool (in a fresh process, as ``tests/test_integrator.py`` test14 explains); and
    ``load_scene`` loads a scene file there."""
    import subprocess
    import sys

    if "scalar_rgb" not in mi.variants():
        pytest.skip("scalar_rgb is not available")
    out = tmp_path / "scalar.npy"
    proc = subprocess.run([sys.executable, "-c", SCALAR_CHILD,
                           str(project.data_dir() / "sphere_wake.npz"), str(out),
                           str(project.scenes_dir() / "sphere_wake.xml")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    images = np.load(out)
    assert np.all(np.isfinite(images))
    assert np.all(images.reshape(4, -1).sum(axis=1) > 0)
