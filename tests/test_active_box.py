"""The exact march on the basis blend clips its rays to the isovalues' active box
(:meth:`DeviceVolume.active_box`): the same crossings, layers, shadow-ray transmittances and
images as its slow twin, the walk through the whole volume.

The scene is sphere_wake.xml (64^2, 1 spp), whose active box at q = 0.05 is a sliver of the
volume's box. Rays start at random points of the volume's box (inside and outside the active
box) in random directions, and along the axes in the planes of the active box's faces.
"""

import contextlib
import dataclasses

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from mi_amr.kernels.config import clip_box, clips  # noqa: E402
from mi_amr.kernels.device import active_box_host  # noqa: E402
from mi_amr.plugin.twins import Twins, with_twins  # noqa: E402
from mi_amr.plugin.scene import load_scene  # noqa: E402
from mi_amr.workflows import project  # noqa: E402

ISOVALUES = (0.02, 0.05, 0.1)


def scene(**integrator):
    return load_scene(project.scenes_dir() / "sphere_wake.xml", resx=64, resy=64, spp=1,
                      integrator={"method": "exact", "reconstruction": "basis", **integrator})


@pytest.fixture(scope="module")
def opaque(scene_data_ready):
    return scene()


@pytest.fixture(scope="module")
def translucent(scene_data_ready):
    return scene(isovalue=", ".join(map(str, ISOVALUES)), iso_opacity="0.4, 0.5, 0.6")


def host_box(integ):
    lo, hi = integ.config().active_box
    return np.array([lo[i][0] for i in range(3)]), np.array([hi[i][0] for i in range(3)])


def sample_rays(integ, n=20000, seed=3):
    """Rays in random directions from random points of the active box grown by its size on
    every side (inside and outside it; a quarter from anywhere in the volume's box), then
    axis-aligned rays lying in the planes of the active box's faces (grazing its faces and
    edges)."""
    lo = np.array([integ.dev.bounds_lo[i][0] for i in range(3)])
    hi = np.array([integ.dev.bounds_hi[i][0] for i in range(3)])
    b_lo, b_hi = host_box(integ)
    near_lo = np.maximum(lo, 2 * b_lo - b_hi)
    near_hi = np.minimum(hi, 2 * b_hi - b_lo)
    rng = np.random.default_rng(seed)
    anywhere = rng.random(n) < 0.25
    o = np.where(anywhere[:, None], lo + rng.random((n, 3)) * (hi - lo),
                 near_lo + rng.random((n, 3)) * (near_hi - near_lo))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    grazing_o, grazing_d = [], []
    for axis in range(3):
        for other in range(3):
            if other == axis:
                continue
            for face in (b_lo, b_hi):
                for u in np.linspace(0.0, 1.0, 25):
                    p = b_lo + u * (b_hi - b_lo)
                    p[other] = face[other]
                    p[axis] = lo[axis]
                    grazing_o.append(p)
                    grazing_d.append(np.eye(3)[axis])
    o = np.concatenate([o, grazing_o]).astype(np.float32)
    d = np.concatenate([d, grazing_d]).astype(np.float32)
    return o, d


def first_crossings(integ, o, d, box):
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.surface import first_crossing

    m = integ.m
    cfg = integ.config()
    if not box:          # the whole volume, each search from the root
        cfg = dataclasses.replace(cfg, active_box=None, start_table=None)
    ray = RayContext(integ.dev, cfg, m.Array3f(*o.T), m.Array3f(*d.T), m.Float(0.0),
                     m.Float(dr.inf), m.Bool(True))
    c = first_crossing(ray, m.Float(0.5))
    dr.eval(c.t, c.hit, c.k)
    hit = c.hit.numpy().astype(bool)
    return np.where(hit, c.t.numpy(), np.inf), np.where(hit, c.k.numpy().astype(int), -1)


def test01_the_box_holds_every_leaf_that_may_hold_the_isovalue(opaque):
    integ = opaque.integrator()
    tree, ranges = integ.dev.tree, integ.dev.node_ranges(True).reshape(-1, 2)
    leaf = (tree.node_code & 3) == 3
    active = leaf & (ranges[:, 0] <= np.float32(0.05)) & (np.float32(0.05) <= ranges[:, 1])
    b_lo, b_hi = host_box(integ)
    assert active.sum() > 100
    assert np.all(tree.node_lo[active] > b_lo) and np.all(tree.node_hi[active] < b_hi)
    # A sliver of the volume's box: most of a camera ray's walk is outside it.
    volume = np.prod(tree.node_hi[0] - tree.node_lo[0])
    assert np.prod(b_hi - b_lo) < 0.05 * volume
    # No isovalue in any leaf: the empty box, through which no ray passes.
    lo, hi = active_box_host(tree, ranges.ravel(), [1e9], 0.1)
    assert np.all(lo == np.inf) and np.all(hi == -np.inf)


def test02_clipped_first_crossings_are_the_walk_through_the_whole_volume(opaque):
    integ = opaque.integrator()
    o, d = sample_rays(integ)
    t_box, k_box = first_crossings(integ, o, d, True)
    t_all, k_all = first_crossings(integ, o, d, False)
    assert np.isfinite(t_all).sum() > 1500           # many rays cross the surface
    np.testing.assert_array_equal(k_box, k_all)
    np.testing.assert_array_equal(t_box, t_all)


def test03_clipped_layers_are_the_walk_through_the_whole_volume(translucent):
    from test_translucent import layers

    integ = translucent.integrator()
    o, d = sample_rays(integ, n=6000)
    fast = layers(integ, o, d, resume=True)
    slow = layers(with_twins(integ, Twins(clip_to_active=False)), o, d, resume=True)
    assert (fast[1] >= 0).sum() > 2000
    np.testing.assert_array_equal(fast[1], slow[1])
    np.testing.assert_array_equal(fast[0], slow[0])


def transmittances(integ, o, d):
    ray = mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*d.T))
    ray.maxt = mi.Float(50.0)
    return np.array(integ.iso_transmittance(ray, False, mi.Bool(True)))


def assert_shadow_rays_and_images_agree(sc, twins):
    """Shadow-ray transmittances bit for bit and images of scene ``sc`` by its integrator and
    by the integrator taking the slow twins ``twins``."""
    integ = sc.integrator()
    slow_integ = with_twins(integ, twins)
    o, d = sample_rays(integ, n=3000)
    fast_T, fast_img = transmittances(integ, o, d), np.array(mi.render(sc, seed=0))
    slow_T = transmittances(slow_integ, o, d)
    slow_img = np.array(mi.render(sc, seed=0, integrator=slow_integ))
    assert np.mean(slow_T < 0.99) > 0.1
    np.testing.assert_array_equal(fast_T, slow_T)
    assert fast_img.mean() > 0.05
    # The samples are the same bit for bit; the film adds each into its neighbouring pixels
    # (Gaussian filter) with atomic adds whose order across threads varies from render to
    # render: a pixel may then differ in its last bit (seen once in a full run, 251 of 12,288).
    np.testing.assert_allclose(fast_img, slow_img, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("which", ["opaque", "translucent"])
def test04_clipped_shadow_rays_and_images_are_the_twins(request, which):
    assert_shadow_rays_and_images_agree(request.getfixturevalue(which),
                                        Twins(clip_to_active=False))


@contextlib.contextmanager
def new_isovalue(sc, value=0.2, back=0.05):
    """Scene ``sc`` rendered once, then with its isovalue set to ``value`` (``back`` after)."""
    params = mi.traverse(sc)
    mi.render(sc, seed=0)
    try:
        params["integrator.isovalue"] = mi.Float(value)
        params.update()
        yield
    finally:
        params["integrator.isovalue"] = mi.Float(back)
        params.update()


def test05_a_new_isovalue_moves_the_box_without_compiling(opaque):
    from conftest import kernels_compiled

    integ = opaque.integrator()
    before = host_box(integ)
    with new_isovalue(opaque):
        assert not np.array_equal(host_box(integ)[0], before[0])
        assert kernels_compiled(lambda: dr.eval(mi.render(opaque, seed=0)))[1] == 0
        o, d = sample_rays(integ, n=3000)
        np.testing.assert_array_equal(first_crossings(integ, o, d, True)[0],
                                      first_crossings(integ, o, d, False)[0])


@pytest.mark.parametrize("kw, clipped", [
    ({}, True), ({"reconstruction": "finest"}, False), ({"method": "uniform"}, False),
    ({"method": "bisect"}, False), ({"mode": "volume"}, False)])
def test06_only_the_exact_march_on_the_basis_blend_clips(scene_data_ready, kw, clipped):
    """``finest`` jumps at grid edges (a crossing between two skipped nodes) and the sampling
    methods take the side of the nodes skipped before their first sample: they walk the whole
    volume."""
    integ = scene(**kw).integrator()
    cfg = integ.config()
    assert clips(cfg) == clipped
    assert (clip_box(cfg) is not None) == clipped


def assert_trace_twins_agree(integ, twin_flag):
    """``mi_amr.trace`` with its keyword ``twin_flag`` True and False (its slow twin): the same
    hits, depths, normals and isovalues, for one isovalue and three."""
    from mi_amr.kernels.trace import trace
    from mi_amr.readers import load

    o, d = sample_rays(integ, n=6000)
    volume = load(integ.prep.volume.source)     # (the scene's file: its preparation keeps no Q)
    for iso in (0.05, list(ISOVALUES)):
        fast, slow = (trace(volume, o, d, field="q_criterion", isovalue=iso,
                            **{twin_flag: on}) for on in (True, False))
        assert fast.hit.sum() > 500
        for a, b in ((fast.hit, slow.hit), (fast.t, slow.t), (fast.iso_index, slow.iso_index)):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(fast.normal[fast.hit], slow.normal[slow.hit])


def test07_trace_clips_to_the_box_too(opaque):
    """``mi_amr.trace`` (exact, basis) clips its rays to the active box as the integrator
    does, against ``active_box=False``."""
    assert_trace_twins_agree(opaque.integrator(), "active_box")
