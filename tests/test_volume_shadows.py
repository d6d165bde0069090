"""Volume mode's transmittance caches (``volume_shadows="cache"``,
:mod:`mi_amr.plugin.shadow_cache`) against their slow twin, the exact shadow ray per lit piece
(``volume_shadows="exact"``): the same image within
:data:`~mi_amr.tolerances.SHADOW_CACHE_REL_RMSE`, the same transmittance at the grid's points
and within :data:`~mi_amr.tolerances.SHADOW_CACHE_MEAN_ABS` between them; built again for a
new band or light, not for a camera move, and a new light direction compiles nothing.
``volume_shadows="corrected"`` (the cache and one exact shadow ray per camera sample)
converges to the exact image as the samples grow. A lit piece whose light counts takes the
first grid cell of its shadow ray apart from the grid, and reads the grid beyond: composited
exactly from its own leaf (the sampling methods; on a thin band far closer to the exact
transmittance than the grid read at the piece), or from the value around it (the exact
method's near ramp, held against that exact stretch).
"""

import textwrap

import numpy as np
import pytest

from conftest import kernels_compiled
from mi_amr import tolerances as tol
from mi_amr.synthetic import datasets

RES = 32


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


def scene_xml(folder, volume_shadows="cache", method="exact", band_width=0.02):
    """Two bands (0.3 and 0.4, ``band_width`` wide) of the ellipsoid field of
    :func:`ellipsoid`, a ball below, a directional and a point light; the compositing
    ``method``."""
    text = f"""
    <scene version="3.0.0">
        <integrator type="amr_iso" id="integrator">
            <string name="filename" value="a.npz"/>
            <string name="field" value="f"/>
            <string name="isovalue" value="0.3, 0.4"/>
            <string name="iso_color" value="0.9 0.5 0.2; 0.2 0.6 1.0"/>
            <string name="mode" value="volume"/>
            <string name="band_width" value="{band_width}"/>
            <string name="band_peak" value="0.5"/>
            <string name="volume_shadows" value="{volume_shadows}"/>
            <string name="method" value="{method}"/>
            <integer name="leaf_cells" value="2"/>
        </integrator>
        <sensor type="perspective" id="sensor">
            <float name="fov" value="30"/>
            <transform name="to_world">
                <lookat origin="1.6, -0.9, 1.4" target="0.5, 0.5, 0.5" up="0, 0, 1"/>
            </transform>
            <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
            <film type="hdrfilm">
                <integer name="width" value="{RES}"/><integer name="height" value="{RES}"/>
                <string name="pixel_format" value="rgb"/>
            </film>
        </sensor>
        <emitter type="directional" id="light">
            <vector name="direction" value="-0.4, 0.5, -1.0"/>
            <rgb name="irradiance" value="2.0"/>
        </emitter>
        <emitter type="point" id="lamp">
            <point name="position" value="1.4, 0.2, 1.5"/>
            <rgb name="intensity" value="1.5"/>
        </emitter>
        <shape type="sphere" id="ball">
            <point name="center" value="0.5, 0.5, -0.6"/><float name="radius" value="0.3"/>
        </shape>
    </scene>"""
    path = folder / f"scene_{volume_shadows}_{method}_{band_width}.xml"
    path.write_text(textwrap.dedent(text))
    return path


def ellipsoid():
    """``f = |(p - c) / (1, 0.8, 0.5)|`` on the analytic datasets' two levels: the bands'
    leaves (of 2 cells) span a box of three different sides (so a grid axis mixed up shows)."""
    scale = np.array([1.0, 0.8, 0.5])
    return datasets.two_levels(lambda p, level: np.linalg.norm((p - 0.5) / scale, axis=-1))


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("volume_shadows")
    ellipsoid().save(folder / "a.npz")
    return folder


def load(folder, volume_shadows="cache", method="exact", band_width=0.02):
    from mi_amr.plugin.scene import load_scene

    return load_scene(scene_xml(folder, volume_shadows, method, band_width))


def render(mi, scene):
    import drjit as dr

    img = mi.render(scene, seed=0)
    dr.eval(img)
    return np.array(img)


def rel_rmse(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b ** 2)))


@pytest.fixture(scope="module")
def cached(variant, folder):
    """The scene with caches, after its first frame (and that frame)."""
    scene = load(folder)
    return scene, render(variant, scene)


def test01_the_cached_image_matches_exact_shadow_rays(variant, folder, cached):
    scene, image = cached
    exact = render(variant, load(folder, "exact"))
    assert scene.integrator().shadow_caches.builds == 1
    err = rel_rmse(image, exact)
    assert err < tol.SHADOW_CACHE_REL_RMSE, f"relative RMSE {err:.4f} against exact shadows"
    # (the shadows show: without them the image differs far more)
    assert rel_rmse(image, exact * 0 + image.mean()) > 5 * err


def _exact_transmittance(mi, integ, emitter, p, active):
    """The exact shadow compositing from volume points ``p`` towards ``emitter`` (what a lit
    piece's shadow ray sees, its mesh test aside)."""
    import drjit as dr

    from mi_amr.plugin import bridge, shading

    P = integ.frame.to_scene @ bridge.to_mi3(p, mi.Point3f)
    it = dr.zeros(mi.Interaction3f, dr.width(p.x))
    it.p = P
    ds, _ = emitter.sample_direction(it, mi.Point2f(0.5), True)
    return np.array(integ.iso_transmittance(shading.shadow_ray(P, ds), True, active))


def _lookups(mi, scene, points):
    """Per emitter: (cached, exact) transmittance at the volume points ``points`` (n x 3)."""
    from mi_amr.kernels import shadow_grid

    integ = scene.integrator()
    m = integ.m
    p = m.Array3f(*(m.Float(points[:, a]) for a in range(3)))
    active = m.Bool(np.ones(len(points), dtype=bool))
    out = []
    for emitter, grid in zip(scene.emitters(), integ.shadow_caches.grids(integ, scene)):
        out.append((np.array(shadow_grid.lookup(m, grid, p, active)),
                    _exact_transmittance(mi, integ, emitter, p, active)))
    return out


def _band_points(integ, rng, n):
    """``n`` random points (volume world) of the leaves that hold band opacity, and the
    cache's plan."""
    from mi_amr.kernels import shadow_grid
    from mi_amr.plugin.shadow_cache import opacity_leaves

    tree = integ.dev.tree
    leaves = opacity_leaves(integ)
    pick = rng.choice(leaves, n)
    pts = tree.leaf_lo[pick] + rng.random((n, 3)) * (tree.leaf_hi[pick] - tree.leaf_lo[pick])
    return pts, shadow_grid.plan(tree, leaves), leaves


def test02_lookups_match_the_exact_transmittance(variant, cached):
    """At the grid's own points the lookup is the exact transmittance (to float rounding);
    at random points of the leaves with opacity it is within the interpolation's error."""
    scene, _ = cached
    from mi_amr.kernels import shadow_grid

    integ = scene.integrator()
    rng = np.random.default_rng(7)
    pts, grid, leaves = _band_points(integ, rng, 2000)
    assert len(set(grid.dims.tolist())) > 1, "the test grid must not be a cube"
    needed = shadow_grid.needed_points(grid, integ.dev.tree, leaves)
    index = rng.choice(needed, 500)
    i, j, k = index % grid.dims[0], (index // grid.dims[0]) % grid.dims[1], \
        index // (grid.dims[0] * grid.dims[1])
    at_nodes = grid.lo + np.stack([i, j, k], axis=1) * grid.cell
    for cached_T, exact_T in _lookups(variant, scene, at_nodes):
        assert np.max(np.abs(cached_T - exact_T)) < 1e-5
    for cached_T, exact_T in _lookups(variant, scene, pts):
        assert np.any(exact_T < 0.9), "the points must see some shadow"
        assert np.mean(np.abs(cached_T - exact_T)) < tol.SHADOW_CACHE_MEAN_ABS


def test03_a_camera_move_does_not_build_again(variant, cached):
    mi = variant
    scene, image = cached
    caches = scene.integrator().shadow_caches
    builds = caches.builds
    p = mi.traverse(scene)
    before = mi.Transform4f(p["sensor.to_world"])
    p["sensor.to_world"] = mi.Transform4f().look_at(origin=[1.5, -1.1, 1.2],
                                                    target=[0.5, 0.5, 0.5], up=[0, 0, 1])
    p.update()
    moved = render(mi, scene)
    assert caches.builds == builds
    assert not np.allclose(moved, image)
    p["sensor.to_world"] = before
    p.update()
    assert np.allclose(render(mi, scene), image)
    assert caches.builds == builds


def test04_a_new_band_or_light_builds_again_and_compiles_nothing(variant, folder, cached):
    """Each change builds the caches again, renders what a scene loaded with the new value
    renders, and compiles no kernel (the build's and the frame's programs do not depend on
    the values, nor on the grid's size)."""
    mi = variant
    scene, _ = cached
    caches = scene.integrator().shadow_caches
    p = mi.traverse(scene)
    changes = [("integrator.isovalue", mi.Float([0.28, 0.41])),
               ("integrator.band_width", mi.Float([0.03, 0.015])),
               ("light.to_world", mi.Transform4f().look_at(origin=[0, 0, 0],
                                                           target=[0.5, -0.3, -1.0],
                                                           up=[0, 1, 0])),
               ("lamp.position", mi.Point3f(0.2, 1.3, 1.4))]
    before = render(mi, scene)
    for key, value in changes:
        builds = caches.builds
        p[key] = value
        p.update()
        image, compiled = kernels_compiled(lambda: render(mi, scene))
        assert caches.builds == builds + 1, key
        assert compiled == 0, f"changing {key} compiled {compiled} kernel(s)"
        assert not np.allclose(image, before), key
        before = image



def test04b_a_build_in_wavefronts_is_the_same_and_stops_when_told(variant, folder, monkeypatch):
    """The viewer builds a full cache in wavefronts (``stop``: asked before each): the same
    values as one wavefront, no kernel compiled for the later ones, and when ``stop`` says
    True nothing is kept (the next frame builds it whole)."""
    from mi_amr.plugin import shadow_cache

    scene = load(folder)
    integ = scene.integrator()
    integ.config()
    whole = [np.array(g.values) for g in shadow_cache.build_all(integ, scene.emitters())]
    points = int(np.count_nonzero(whole[0] != 1.0))
    for parts in (3, 5):            # (the first wavefronts compile their kernel, once)
        monkeypatch.setattr(tol, "SHADOW_CACHE_BUILD_CHUNK", max(points // parts, 1))
        asked = []
        grids, compiled = kernels_compiled(lambda: shadow_cache.build_all(
            integ, scene.emitters(), stop=lambda: asked.append(1) and False))
        assert len(asked) >= 2 * parts, "each light's points in several wavefronts"
        for a, b in zip(whole, grids):
            np.testing.assert_array_equal(np.array(b.values), a)
    assert compiled == 0, f"wavefronts of another size compiled {compiled} kernel(s)"
    caches = integ.shadow_caches
    caches.max_points = tol.SHADOW_CACHE_POINTS + 1         # (a key not built yet)
    builds, calls = caches.builds, []
    assert caches.grids(integ, scene, stop=lambda: len(calls) > 1 or calls.append(1)) is None
    assert caches.builds == builds and len(calls) == 2
    assert [np.array(g.values).size for g in caches.grids(integ, scene)] == \
        [a.size for a in whole] and caches.builds == builds + 1


def test04c_the_viewers_refinement_stops_within_the_cache_build(variant, folder, monkeypatch):
    """A request that comes while the viewer's refined frame builds its full cache stops it
    at the next wavefront (the render thread then answers the request); left alone, the
    refined frame is the one it renders without being asked."""
    from mi_amr.workflows.viewer.state import Session

    monkeypatch.setattr(tol, "SHADOW_CACHE_BUILD_CHUNK", 64)
    session = Session(scene_xml(folder), resolution=(RES, RES), spp=1)
    try:
        caches = session.integrator.shadow_caches
        session.render((RES, RES), 1, preview=True)
        builds, asked = caches.builds, []
        stopped = session.render_refined((RES, RES), 1,
                                         lambda: len(asked) > 2 or asked.append(1))
        assert stopped is None
        assert len(asked) == 3 and caches.builds == builds, "stopped in the build's third part"
        refined = session.render_refined((RES, RES), 1, lambda: False)
        assert caches.builds == builds + 1
        assert caches.max_points == tol.SHADOW_CACHE_POINTS
        again = session.render_refined((RES, RES), 1)
        assert caches.builds == builds + 1
    finally:
        session.close()
    # (The film may sum a pixel's samples in another order: the same image to float noise.)
    np.testing.assert_allclose(again, refined, rtol=1e-5, atol=1e-6)

def test05_exact_keeps_no_cache_and_other_lights_keep_exact_rays(variant, folder):
    mi = variant
    from mi_amr import params
    from mi_amr.errors import AMRError
    from mi_amr.plugin.shadow_cache import cacheable

    assert params.default("volume_shadows") == "cache"
    scene = load(folder, "exact")
    assert scene.integrator().shadow_caches.grids(scene.integrator(), scene) == [None, None]
    assert [cacheable(mi.load_dict({"type": t})) for t in ("directional", "point",
                                                              "constant")] == \
        [True, True, False]
    bad = scene_xml(folder, "maybe")
    from mi_amr.plugin.scene import load_scene

    with pytest.raises(AMRError, match="volume_shadows"):
        load_scene(bad)


def alpha_scene_xml(folder):
    """The bands of :func:`scene_xml` without a mesh, one ray through each pixel's centre
    (a stratified sampler without jitter, a box filter) and an alpha channel; each ray's
    pieces cut only where the value turns relative to a band."""
    text = scene_xml(folder).read_text()
    start, end = text.index("<shape"), text.index("</shape>") + len("</shape>")
    text = text[:start] + text[end:]
    text = text.replace('<sampler type="independent"><integer name="sample_count" value="1"/>'
                        '</sampler>',
                        '<sampler type="stratified"><integer name="sample_count" value="1"/>'
                        '<boolean name="jitter" value="false"/></sampler>')
    # (The camera rays' pieces cut as a shadow ray's are: not where the diffuse term turns.)
    text = text.replace('<integer name="leaf_cells" value="2"/>',
                        '<integer name="leaf_cells" value="2"/>'
                        '<boolean name="shading_extrema" value="false"/>')
    text = text.replace('<string name="pixel_format" value="rgb"/>',
                        '<string name="pixel_format" value="rgba"/><rfilter type="box"/>')
    path = folder / "scene_alpha.xml"
    path.write_text(text)
    return path


def test06_volume_alpha_is_one_minus_the_transmittance(variant, folder):
    """The alpha channel of a volume frame is the opacity ``1 - T`` of each pixel's ray (the
    bands' transmittance along it, composited without shading), through the integrator's
    render loop."""
    import drjit as dr

    mi = variant
    from mi_amr.plugin.scene import load_scene

    scene = load_scene(alpha_scene_xml(folder))
    image = render(mi, scene)
    sensor = scene.sensors()[0]
    x, y = np.meshgrid(np.arange(RES) + 0.5, np.arange(RES) + 0.5)
    pos = mi.Point2f(x.ravel() / RES, y.ravel() / RES)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    T = scene.integrator().iso_transmittance(ray, False, mi.Bool(True))
    dr.eval(T)
    alpha = image[..., 3].ravel()
    assert np.all(alpha > -1e-6) and np.ptp(alpha) > 0.5, "the test needs clear and opaque rays"
    assert np.max(np.abs(alpha - (1.0 - np.array(T)))) < 1e-5


@pytest.mark.parametrize("method", ["exact", "adaptive"])
def test07_corrected_shadows_converge_to_the_exact_ones(variant, folder, method):
    """``volume_shadows="corrected"``: the cache plus, per camera sample, one exact shadow
    ray from a lit piece (or sample) picked by its light (either of the two lights), weighted
    so that it is unbiased. Against the exact image of the same seed and samples its error
    is noise: it goes down as ``1 / sqrt(spp)`` and falls well below the cache's own, which
    stays."""
    mi = variant
    images = {}
    for spp in (16, 64):
        for shadows in ("exact", "cache", "corrected"):
            scene = load(folder, shadows, method)
            images[shadows, spp] = np.array(mi.render(scene, seed=0, spp=spp))
    err = {(s, spp): rel_rmse(images[s, spp], images["exact", spp])
           for s in ("cache", "corrected") for spp in (16, 64)}
    assert err["cache", 64] > 0.8 * err["cache", 16], err         # (a bias: it stays)
    assert err["corrected", 64] < 0.65 * err["corrected", 16], err  # (noise: it goes)
    assert err["corrected", 64] < 0.4 * err["cache", 64], err
    assert err["corrected", 64] < tol.SHADOW_CORRECTED_REL_RMSE, err


def test08_needed_points_match_their_box_by_box_twin(variant, cached):
    """The grid points a cache fills (one pass of running sums over the leaves' boxes) are
    those that marking each leaf's box grown by one cell finds, at the full and at a coarse
    (the viewer's preview) size."""
    from mi_amr.kernels import shadow_grid
    from mi_amr.plugin.shadow_cache import opacity_leaves

    scene, _ = cached
    integ = scene.integrator()
    tree, leaves = integ.dev.tree, opacity_leaves(integ)
    for points in (tol.SHADOW_CACHE_POINTS, tol.PREVIEW_SHADOW_CACHE_POINTS, 64):
        grid = shadow_grid.plan(tree, leaves, points)
        fast = shadow_grid.needed_points(grid, tree, leaves)
        assert 0 < len(fast) <= grid.size
        assert np.array_equal(fast, shadow_grid.needed_points_by_box(grid, tree, leaves)), points


def _cached_shadows(mi, scene, points):
    """Per emitter: (cached shadow, grid alone, exact) transmittance at volume ``points``."""
    import drjit as dr

    from mi_amr.kernels import shadow_grid
    from mi_amr.plugin import bridge
    from mi_amr.plugin.shadow_cache import CachedShadow

    integ = scene.integrator()
    m = integ.m
    p = m.Array3f(*(m.Float(points[:, a]) for a in range(3)))
    active = m.Bool(np.ones(len(points), dtype=bool))
    P = integ.frame.to_scene @ bridge.to_mi3(p, mi.Point3f)
    it = dr.zeros(mi.Interaction3f, len(points))
    it.p = P
    out = []
    for emitter, grid in zip(scene.emitters(), integ.shadow_caches.grids(integ, scene)):
        ds, _ = emitter.sample_direction(it, mi.Point2f(0.5), True)
        shadow = CachedShadow(m, grid, integ.iso_transmittance, integ.frame.to_volume)
        out.append((np.array(shadow(P, ds, mi.Bool(True))),
                    np.array(shadow_grid.lookup(m, grid, p, active)),
                    _exact_transmittance(mi, integ, emitter, p, active)))
    return out


def test09_a_lit_piece_s_own_band_is_composited_exactly(variant, folder):
    """On a thin band itself (where its lit pieces lie) its shadow on itself goes from clear to
    dark within a small part of a grid cell, so the grid read at the point blends corners on
    either side of the band. A lit piece's cached shadow composites the first grid cell of its
    shadow ray exactly and reads the grid beyond: within
    :data:`~mi_amr.tolerances.SHADOW_NEAR_MEAN_ABS` of the exact transmittance, and far closer
    than the grid alone."""
    scene = load(folder, band_width=0.002)
    render(variant, scene)
    rng = np.random.default_rng(11)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    iso = rng.choice([0.3, 0.4], len(u))[:, None]
    # (on the bands' isovalues of the ellipsoid field: f = |(p - 0.5) / scale| = iso)
    pts = 0.5 + iso * u * np.array([1.0, 0.8, 0.5])
    for near_T, grid_T, exact_T in _cached_shadows(variant, scene, pts):
        assert 0.1 < np.mean(exact_T) < 0.9, "the points must see their bands' shadow"
        near_err = np.mean(np.abs(near_T - exact_T))
        grid_err = np.mean(np.abs(grid_T - exact_T))
        assert near_err < tol.SHADOW_NEAR_MEAN_ABS, (near_err, grid_err)
        assert near_err < 0.6 * grid_err, (near_err, grid_err)


def test10_a_shadow_ray_started_in_its_leaf_matches_the_search_from_the_root(variant, folder):
    """A lit piece's exact stretch starts in the piece's own leaf (``composite(start=)``,
    :meth:`~mi_amr.kernels.traverse.Walk.within`) instead of searching from the root: the same
    transmittance, including points on a leaf's face; a wrong leaf would read another grid's
    values."""
    import drjit as dr

    from mi_amr.kernels.composite import composite
    from mi_amr.kernels.ray import RayContext
    from mi_amr.kernels.traverse import Walk

    scene = load(folder, band_width=0.002)
    render(variant, scene)
    integ = scene.integrator()
    m, tree = integ.m, integ.dev.tree
    rng = np.random.default_rng(5)
    u = rng.normal(size=(2000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = 0.5 + rng.choice([0.3, 0.4], len(u))[:, None] * u * np.array([1.0, 0.8, 0.5])
    pts[:200] = tree.leaf_lo[tree.locate(pts[:200])]        # (corners of their leaves)
    d = np.array([0.4, -0.5, 1.0]) / np.linalg.norm([0.4, -0.5, 1.0])
    n = len(pts)

    def transmittance(leaves):
        o = m.Array3f(*(m.Float(pts[:, a]) for a in range(3)))
        ray = RayContext(integ.dev, integ.config(), o, m.Array3f(*map(float, d)),
                         m.Float(np.zeros(n)), m.Float(np.full(n, 0.1)), m.Bool(True))
        start = None if leaves is None else Walk(
            node=m.UInt32(tree.leaf_node[leaves].astype(np.uint32)),
            leaf=m.UInt32(leaves.astype(np.uint32)), face=m.UInt32(6),
            t_exit=m.Float(0.0), t=m.Float(0.0))
        T = composite(ray, m.Float(0.5), start=start).T
        dr.eval(T)
        return np.array(T)

    leaves = tree.locate(pts)
    from_root = transmittance(None)
    assert 0.2 < np.mean(from_root) < 0.95, "the rays must cross their bands"
    assert np.max(np.abs(transmittance(leaves) - from_root)) < 1e-5
    wrong = transmittance(np.roll(leaves, 1))
    assert np.max(np.abs(wrong - from_root)) > 0.05, "a wrong leaf must show"


def test11_a_thin_band_s_image_gets_the_exact_stretch_where_its_light_counts(variant, folder):
    """Thinner bands (width 0.005) at 4 spp: the pieces whose light counts
    (:class:`~mi_amr.kernels.near.NearStretch`) take the first grid cell of their shadow ray
    from their near ramp, and the image is within :data:`~mi_amr.tolerances.SHADOW_THIN_REL_RMSE`
    of exact shadow rays; reading the grid at every piece is not."""
    mi = variant
    images = {s: np.array(mi.render(load(folder, s, band_width=0.005), seed=0, spp=4))
              for s in ("exact", "cache")}
    err = rel_rmse(images["cache"], images["exact"])
    assert err < tol.SHADOW_THIN_REL_RMSE, f"relative RMSE {err:.4f} against exact shadows"


def test12_a_lamp_within_the_exact_stretch_is_never_looked_past(variant, folder):
    """A point light nearer to a lit point than the grid's reach: the whole shadow ray is the
    exact stretch, and the grid is not read beyond the lamp (where its points look back at the
    lamp from the other side)."""
    mi = variant
    scene = load(folder, band_width=0.002)
    params = mi.traverse(scene)
    params["lamp.position"] = mi.Point3f(0.5, 0.5, 0.715)     # 0.015 above the outer band's top
    params.update()
    render(mi, scene)
    grid = scene.integrator().shadow_caches.grids(scene.integrator(), scene)[1]
    reach = float(np.array(grid.reach)[0])
    rng = np.random.default_rng(3)
    # (points of the outer band's top, within the reach of the lamp)
    xy = 0.5 + 0.02 * rng.uniform(-1, 1, (400, 2)) * np.array([1.0, 0.8])
    z = 0.5 + 0.5 * np.sqrt(np.maximum(0.16 - ((xy[:, 0] - 0.5) / 1.0) ** 2 -
                                       ((xy[:, 1] - 0.5) / 0.8) ** 2, 0.0))
    pts = np.column_stack([xy, z])
    dist = np.linalg.norm(pts - [0.5, 0.5, 0.715], axis=1)
    assert np.all(dist < reach), (dist.max(), reach)
    near_T, _, exact_T = _cached_shadows(mi, scene, pts)[1]
    assert np.ptp(exact_T) > 0.01, "the lamp's light must pass some of the band"
    assert np.max(np.abs(near_T - exact_T)) < 1e-5


def test13_the_near_ramp_follows_the_exact_stretch(variant, folder):
    """A lit piece's first stretch from the value around it
    (:class:`~mi_amr.kernels.near.NearRamp`) against that stretch composited exactly, on a
    thin band (width 0.005) itself, towards both lights: within
    :data:`~mi_amr.tolerances.NEAR_RAMP_MEAN_ABS` where the shadow ray runs nearly along the
    band (a straight ramp would keep it in the band for the whole stretch there), and within
    half of that over all points."""
    import drjit as dr

    from mi_amr.kernels import reconstruct as rec
    from mi_amr.kernels.composite import Bands
    from mi_amr.kernels.near import NearRamp
    from mi_amr.kernels.ray import RayContext
    from mi_amr.plugin import bridge, shading

    mi = variant
    scene = load(folder, band_width=0.005)
    render(mi, scene)
    integ = scene.integrator()
    m, cfg = integ.m, integ.config()
    rng = np.random.default_rng(11)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = 0.5 + rng.choice([0.3, 0.4], len(u))[:, None] * u * np.array([1.0, 0.8, 0.5])
    n = len(pts)
    p = m.Array3f(*(m.Float(pts[:, a]) for a in range(3)))
    on = m.Bool(np.ones(n, dtype=bool))
    values, grad = rec.reconstruct(integ.dev, cfg.basis, p, integ.dev.arrays(cfg.basis, False),
                                   on)
    ray = RayContext(integ.dev, cfg, p, m.Array3f(0.0, 0.0, 1.0), m.Float(np.zeros(n)),
                     m.Float(np.ones(n)), on)
    ramp = NearRamp(ray=ray, p=p, value=values[0], gradient=grad,
                    centres=Bands.of(ray, None).centres)
    P = integ.frame.to_scene @ bridge.to_mi3(p, mi.Point3f)
    it = dr.zeros(mi.Interaction3f, n)
    it.p = P
    for emitter, grid in zip(scene.emitters(), integ.shadow_caches.grids(integ, scene)):
        ds, _ = emitter.sample_direction(it, mi.Point2f(0.5), True)
        shadow_ray = shading.shadow_ray(P, ds)
        shadow_ray.maxt = dr.minimum(shadow_ray.maxt, bridge.to_mi(grid.reach, mi.Float))
        exact = np.array(integ.iso_transmittance(shadow_ray, True, mi.Bool(True)))
        seg = bridge.to_kernel3(m, integ.frame.to_volume @ (ds.d * shadow_ray.maxt))
        near = np.array(ramp.transmittance(seg, on))
        g, s = np.array(grad), np.array(seg)
        across = np.abs((g * s).sum(0)) / (np.linalg.norm(g, axis=0) * np.linalg.norm(s, axis=0))
        grazing = across < tol.NEAR_RAMP_GRAZING
        assert 0.1 < np.mean(exact) < 0.95 and grazing.sum() > 100, "the band must shadow itself"
        err = np.abs(near - exact)
        assert np.mean(err[grazing]) < tol.NEAR_RAMP_MEAN_ABS, np.mean(err[grazing])
        assert np.mean(err) < 0.5 * tol.NEAR_RAMP_MEAN_ABS, np.mean(err)
