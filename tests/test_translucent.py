"""Translucent isosurfaces: the fast paths of ``exact`` against their slow twins.

* Primary rays resume their kd-tree walk between layers (``crossings(resume=True)``); the slow
  twin starts a new search just past each layer. Both find the same layers.
* Shadow rays count crossings in one walk (:mod:`mi_amr.kernels.transmit`); the slow twin
  composites them layer by layer (:func:`mi_amr.plugin.layers.front_to_back`). They agree
  except where the field comes within ``SIGN_SURE_REL`` of an isovalue and turns back.
* The walk takes a few steps of a leaf search per piece; any number of steps gives the same.
* A jump of the field across several isovalues (``finest`` at grid edges) is one layer per
  isovalue, met in the order the value passes them.

The scene is sphere_wake.xml with three isovalues of opacity 0.4, 0.5 and 0.6, rays random in
the volume's box (20,000) or the camera's at 64^2.
"""

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from mi_amr.plugin.twins import Twins, with_twins  # noqa: E402
from mi_amr.plugin.scene import load_scene  # noqa: E402
from mi_amr.workflows import project  # noqa: E402

ISOVALUES = (0.02, 0.05, 0.1)
OPACITY = (0.4, 0.5, 0.6)


@pytest.fixture(scope="module")
def scenes(scene_data_ready):
    """One translucent scene per reconstruction (64^2, 1 spp)."""
    integrator = {"iso_opacity": ", ".join(map(str, OPACITY))}
    return {rec: load_scene(project.scenes_dir() / "sphere_wake.xml", resx=64, resy=64, spp=1,
                            isovalue=", ".join(map(str, ISOVALUES)), reconstruction=rec,
                            integrator=integrator)
            for rec in ("basis", "finest")}


def random_rays(integ, n=20000, seed=1):
    """``n`` rays from random points of the volume's box in random unit directions (scene
    space is the volume's here: the scene gives the integrator no ``to_world``)."""
    lo = np.array([integ.dev.bounds_lo[i][0] for i in range(3)])
    hi = np.array([integ.dev.bounds_hi[i][0] for i in range(3)])
    rng = np.random.default_rng(seed)
    o = (lo + rng.random((n, 3)) * (hi - lo)).astype(np.float32)
    d = rng.normal(size=(n, 3))
    d = (d / np.linalg.norm(d, axis=1)[:, None]).astype(np.float32)
    return o, d


def layers(integ, o, d, resume, cfg=None):
    """``(t, k)`` of the first 8 layers along the rays (inf / -1 past the last), marching for
    ``cfg`` (default: the integrator's)."""
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.surface import crossings

    m = integ.m
    O, D = m.Array3f(*o.T), m.Array3f(*d.T)
    ray = RayContext(integ.dev, cfg or integ.config(), O, D, m.Float(0.0), m.Float(dr.inf),
                     m.Bool(True))
    state, after = crossings(ray, m.Float(0.5), resume=resume)
    alive = m.Bool(True)
    ts, ks = [], []
    for _ in range(8):
        c, state = after(state, alive)
        alive &= c.hit
        dr.eval(c.t, c.k, alive, state)
        hit = c.hit.numpy().astype(bool)
        ts.append(np.where(hit, c.t.numpy(), np.inf))
        ks.append(np.where(hit, c.k.numpy().astype(int), -1))
    return np.array(ts), np.array(ks)


@pytest.mark.parametrize("rec", ["basis", "finest"])
def test01_resumed_walks_find_the_layers_a_new_search_finds(scenes, rec):
    integ = scenes[rec].integrator()
    o, d = random_rays(integ, n=4000)
    t_fast, k_fast = layers(integ, o, d, resume=True)
    t_slow, k_slow = layers(integ, o, d, resume=False)
    assert (k_fast >= 0).sum() > 2000          # the rays do cross layers, many of them
    np.testing.assert_array_equal(k_fast, k_slow)
    np.testing.assert_array_equal(t_fast, t_slow)


def transmittance(integ, o, d, fast):
    """Shadow-ray transmittances of ``integ`` (``fast`` False: of its layer-by-layer twin)."""
    ray = mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*d.T))
    ray.maxt = mi.Float(50.0)
    if not fast:
        integ = with_twins(integ, Twins(layer_fast_paths=False))
    return np.array(integ.iso_transmittance(ray, False, mi.Bool(True)))


@pytest.mark.parametrize("rec", ["basis", "finest"])
def test02_one_walk_shadow_rays_match_layer_by_layer_compositing(scenes, rec):
    """Measured: 1 ray in 20,000 differs (a dip 1e-4 along the ray across 0.02 and back: two
    layers there, none here)."""
    integ = scenes[rec].integrator()
    o, d = random_rays(integ)
    fast, slow = transmittance(integ, o, d, True), transmittance(integ, o, d, False)
    assert np.mean(slow < 0.99) > 0.15                # a good share of rays pass a layer
    differ = np.abs(fast - slow) > 1e-5
    assert differ.mean() < 5e-4, differ.mean()


@pytest.mark.parametrize("rec", ["basis", "finest"])
def test03_images_with_the_fast_paths_match_the_slow_twins(scenes, rec):
    """Measured: max 9e-4 (basis), 4e-3 (finest) of a pixel; mean below 4e-6."""
    scene = scenes[rec]
    fast = np.array(mi.render(scene, seed=0), dtype=np.float64)
    slow_twin = with_twins(scene.integrator(), Twins(layer_fast_paths=False))
    slow = np.array(mi.render(scene, seed=0, integrator=slow_twin), dtype=np.float64)
    assert fast.mean() > 0.1
    diff = np.abs(fast - slow)
    assert diff.max() < 0.02 and diff.mean() < 2e-5, (diff.max(), diff.mean())


def test04_a_jump_across_isovalues_is_a_layer_for_each(scenes):
    """``finest`` jumps at grid edges: a ray whose value jumps across two or three isovalues
    at one place gets a layer for each, there, in the order the value passes them (dense
    sampling of the field along the rays, 3e-5 apart, counts the same sign changes)."""
    from mi_amr.kernels.reconstruct import reconstruct

    integ = scenes["finest"].integrator()
    m, dev = integ.m, integ.dev
    o, d = random_rays(integ, n=4000)
    t, k = layers(integ, o, d, resume=True)
    # Rays with two layers at (almost) the same place (the jumps), and fewer than 8 in all.
    with np.errstate(invalid="ignore"):
        same = (np.abs(np.diff(t, axis=0)) < 1e-3) & np.isfinite(t[1:])
    rays = np.nonzero(same.any(axis=0) & (k[-1] < 0))[0][:8]
    assert len(rays) >= 3, "no ray jumps across two isovalues"
    s = np.linspace(0.0, 12.0, 400001, dtype=np.float32)
    for r in rays:
        P = m.Array3f(*[m.Float(o[r, a] + s * d[r, a]) for a in range(3)])
        vals, _ = reconstruct(dev, False, P, dev.arrays(False), m.Bool(True))
        v = vals[0].numpy()
        ok = np.isfinite(v[1:]) & np.isfinite(v[:-1])
        for i, iso in enumerate(ISOVALUES):
            changes = np.count_nonzero((np.sign(v[1:] - iso) != np.sign(v[:-1] - iso)) & ok)
            assert np.count_nonzero(k[:, r] == i) == changes, (r, i)
        # In the order the value passes them: each jump's isovalues sorted from the value
        # before it (two crossings of one isovalue that close are a dip, no jump).
        for j in np.nonzero(same[:, r] & (k[1:, r] != k[:-1, r]))[0]:
            before = np.interp(t[j, r] - 1e-3, s, v)
            a, b = ISOVALUES[k[j, r]], ISOVALUES[k[j + 1, r]]
            assert abs(a - before) < abs(b - before)


def shadows(integ, o, d, cfg):
    """The shadow rays' one-walk transmittance (:mod:`mi_amr.kernels.transmit`) up to
    ``t = 50``, marching for ``cfg``."""
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.transmit import transmittance_exact

    m = integ.m
    ray = RayContext(integ.dev, cfg, m.Array3f(*o.T), m.Array3f(*d.T), m.Float(0.0),
                     m.Float(50.0), m.Bool(True))
    T = transmittance_exact(ray, integ.inputs["iso_opacity"], integ.opt.max_layers)
    dr.eval(T)
    return T.numpy()


def searching(integ, **plan):
    """The integrator's march configuration with the leaf searches taken as ``plan`` says
    (:class:`~mi_amr.kernels.config.SearchPlan`)."""
    import dataclasses

    from mi_amr.kernels.config import SearchPlan

    return dataclasses.replace(integ.config(), search=SearchPlan(**plan))


@pytest.mark.parametrize("rec", ["basis", "finest"])
def test05_leaf_searches_in_parts_find_what_whole_searches_find(scenes, rec):
    """The march takes a few steps of a leaf search per piece (``SearchPlan.steps``); one
    step at a time and the whole search at once (None) give the same layers, bit for bit, and
    the same shadow-ray transmittance."""
    integ = scenes[rec].integrator()
    o, d = random_rays(integ, n=3000, seed=2)
    results = []
    for steps in (1, None):
        cfg = searching(integ, steps=steps)
        results.append((*layers(integ, o, d, True, cfg), shadows(integ, o, d, cfg)))
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("rec", ["basis", "finest"])
def test06_two_levels_a_turn_take_the_steps_of_one_level_a_turn(scenes, rec):
    """A turn of the leaf search goes down through a non-empty inner node before its full step
    (``SearchPlan.two_levels``); one level a turn, the slow twin, gives the same layers, bit
    for bit, and the same shadow-ray transmittance, with the march's searches in parts as they
    are and whole."""
    from mi_amr.kernels.config import SEEK_STEPS

    integ = scenes[rec].integrator()
    o, d = random_rays(integ, n=3000, seed=3)
    for steps in (SEEK_STEPS, None):
        results = []
        for two in (True, False):
            cfg = searching(integ, steps=steps, two_levels=two)
            results.append((*layers(integ, o, d, True, cfg), shadows(integ, o, d, cfg)))
        for a, b in zip(*results):
            np.testing.assert_array_equal(a, b)
        assert np.isfinite(results[0][0]).any()          # the rays meet layers


@pytest.mark.parametrize("method", ["uniform", "adaptive", "bisect"])
def test07_sampled_layers_take_every_isovalue_two_samples_straddle(method):
    """Two samples that straddle two isovalues give a layer for each, in order, for the
    sampling methods too: the march after a layer starts from a value just past the crossed
    isovalue (with no value before, the second isovalue of the straddle was lost). A linear
    ramp ``f = x`` and steps of four cells put isovalues 0.30 and 0.31 between two samples;
    linear interpolation is exact on it."""
    from conftest import grid

    from mi_amr.core.volume import AMRVolume
    from mi_amr.kernels.config import MarchConfig
    from mi_amr.kernels.device import opaque_floats
    from mi_amr.kernels.prepared import PreparedVolume
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.surface import crossings

    m = dr.llvm.ad
    vol = AMRVolume.from_grids([grid(0, (0, 0, 0), (1, 0.5, 0.5), 1 / 32,
                                     fn=lambda c: c[..., 0])])
    dev = PreparedVolume(vol, "f", m=m).device
    isovalues = [0.30, 0.31, 0.6]
    cfg = MarchConfig(method=method, basis=True, isovalues=opaque_floats(m, isovalues),
                      step_scale=opaque_floats(m, [4.0]), num_iso=3)
    n = 64
    rng = np.random.default_rng(3)
    y, z = (0.1 + 0.3 * rng.random(n) for _ in range(2))
    o = m.Array3f(m.Float(np.zeros(n)), m.Float(y), m.Float(z))
    d = m.Array3f(m.Float(np.ones(n)), m.Float(np.zeros(n)), m.Float(np.zeros(n)))
    ray = RayContext(dev, cfg, o, d, m.Float(0.0), m.Float(dr.inf), m.Bool(True))
    state, after = crossings(ray, m.Float(rng.random(n)), resume=False)
    alive = m.Bool(True)
    found = []
    for _ in range(4):
        c, state = after(state, alive)
        alive &= c.hit
        dr.eval(c.t, c.k, alive, state)
        found.append((np.where(c.hit.numpy(), c.t.numpy(), np.inf),
                      np.where(c.hit.numpy(), c.k.numpy().astype(int), -1)))
    t = np.array([f[0] for f in found])
    k = np.array([f[1] for f in found])
    # Half a cell at either end holds the clamped outer half cell: 0.30 .. 0.6 lie inside.
    np.testing.assert_array_equal(k[:3], np.repeat([[0], [1], [2]], n, axis=1))
    np.testing.assert_array_equal(k[3], -1)
    np.testing.assert_allclose(t[:3], np.repeat([[0.30], [0.31], [0.6]], n, axis=1), atol=2e-3)
