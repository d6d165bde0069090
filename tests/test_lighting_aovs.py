"""Lighting under every kind of Mitsuba emitter (amr_iso against Mitsuba's own ``direct``
integrator on a mesh-only view), and the isosurface's AOVs and alpha (against
:func:`mi_amr.trace` on the same rays)."""

import textwrap

import numpy as np
import pytest

from mi_amr.synthetic import datasets

RES = 24
SPP = 256


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


EMITTERS = {
    "directional": '<emitter type="directional"><vector name="direction" value="0.3, 0.2, -1"/>'
                   '<rgb name="irradiance" value="2"/></emitter>',
    "point": '<emitter type="point"><point name="position" value="0.5, 0.3, 2"/>'
             '<rgb name="intensity" value="6"/></emitter>',
    "spot": '<emitter type="spot"><transform name="to_world"><lookat origin="0.2, 0.2, 2" '
            'target="0.5, 0.5, 0" up="0, 1, 0"/></transform><rgb name="intensity" value="8"/>'
            '<float name="cutoff_angle" value="30"/></emitter>',
    "rectangle": '<shape type="rectangle"><transform name="to_world"><scale value="0.2"/>'
                 '<rotate x="1" angle="180"/><translate x="0.5" y="0.5" z="1.2"/></transform>'
                 '<emitter type="area"><rgb name="radiance" value="12"/></emitter></shape>',
    "sphere": '<shape type="sphere"><point name="center" value="0.3, 0.6, 1.1"/>'
              '<float name="radius" value="0.1"/>'
              '<emitter type="area"><rgb name="radiance" value="60"/></emitter></shape>',
    "constant": '<emitter type="constant"><rgb name="radiance" value="0.7"/></emitter>',
    "envmap": '<emitter type="envmap"><string name="filename" value="env.exr"/></emitter>',
}


def scene_text(emitter, integrator):
    return textwrap.dedent(f"""
    <scene version="3.0.0">
        {integrator}
        <sensor type="perspective">
            <float name="fov" value="50"/>
            <transform name="to_world">
                <lookat origin="0.5, -0.9, 1.4" target="0.5, 0.5, 0.0" up="0, 0, 1"/>
            </transform>
            <sampler type="independent"><integer name="sample_count" value="{SPP}"/></sampler>
            <film type="hdrfilm"><integer name="width" value="{RES}"/>
                <integer name="height" value="{RES}"/><string name="pixel_format" value="rgb"/>
            </film>
        </sensor>
        <shape type="rectangle">
            <transform name="to_world"><scale value="1.5"/><translate x="0.5" y="0.5"/>
            </transform>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf>
        </shape>
        {emitter}
    </scene>""")


@pytest.fixture(scope="module")
def folder(tmp_path_factory, variant):
    mi = variant
    out = tmp_path_factory.mktemp("lights")
    datasets.sphere(8).save(out / "sphere.npz")
    sky = np.ones((16, 32, 3), dtype=np.float32) * np.linspace(0.2, 1.5, 16)[:, None, None]
    mi.Bitmap(sky.astype(np.float32)).write(str(out / "env.exr"))
    return out


@pytest.mark.parametrize("kind", sorted(EMITTERS))
def test01_a_mesh_lit_by_any_emitter_matches_mitsubas_direct_integrator(variant, folder, kind):
    """A plate under each emitter, the isovalue outside the data (no isosurface), Phong's
    ambient term off: amr_iso's image equals Mitsuba's ``direct`` integrator's within the noise
    of 256 spp. (Shadow rays spawned with ``spawn_ray`` and shortened by 1e-4 hit area lights
    themselves and left most of the plate dark.)"""
    mi = variant
    from mi_amr.plugin.scene import load_scene

    ours = ('<integrator type="amr_iso"><string name="filename" value="sphere.npz"/>'
            '<string name="field" value="f"/><float name="isovalue" value="99"/>'
            '<float name="ka" value="0"/></integrator>')
    theirs = '<integrator type="direct"/>'
    images = []
    for i, integ in enumerate((ours, theirs)):
        path = folder / f"{kind}_{i}.xml"
        path.write_text(scene_text(EMITTERS[kind], integ))
        images.append(np.array(mi.render(load_scene(path), seed=i), dtype=np.float64))
    a, b = images
    assert b.mean() > 0.05, "the test scene is not lit"
    # Mean over the image (noise averages out) and per pixel block (where the light falls).
    assert abs(a.mean() - b.mean()) < 0.03 * b.mean()
    blocks = lambda x: x.reshape(6, 4, 6, 4, 3).mean(axis=(1, 3))  # noqa: E731
    np.testing.assert_allclose(blocks(a), blocks(b), atol=0.08 * b.max() + 0.02)


def test02_aovs_and_alpha_describe_the_isosurface(variant, folder):
    """With ``aovs`` on (``load_scene(..., integrator={"aovs": True}, pixel_format="rgba")``):
    depth equals :func:`mi_amr.trace` for the same pixel-centre rays, the position lies on the
    ray at that depth, the value is the isovalue, alpha is the hit mask (no meshes here)."""
    mi = variant
    import mi_amr
    from mi_amr.evaluation.references import pixel_rays
    from mi_amr.plugin.aovs import NAMES
    from mi_amr.plugin.scene import load_scene

    path = folder / "aov.xml"
    integ = ('<integrator type="amr_iso"><string name="filename" value="sphere.npz"/>'
             '<string name="field" value="f"/><float name="isovalue" value="0.3"/></integrator>')
    text = scene_text("", integ).replace('type="independent"><integer name="sample_count" '
                                         f'value="{SPP}"/>',
                                         'type="stratified"><integer name="sample_count" '
                                         'value="1"/><boolean name="jitter" value="false"/>')
    text = text[:text.index("<shape")] + text[text.index("</shape>") + 8:]
    # A box filter: each pixel holds its own sample (the default Gaussian blends neighbours).
    text = text.replace('<string name="pixel_format" value="rgb"/>',
                        '<string name="pixel_format" value="rgb"/><rfilter type="box"/>')
    path.write_text(text)
    scene = load_scene(path, integrator={"aovs": True}, pixel_format="rgba")
    img = np.array(mi.render(scene))
    assert img.shape == (RES, RES, 4 + len(NAMES))
    ch = {name: img[..., 4 + i] for i, name in enumerate(NAMES)}
    ray = pixel_rays(scene.sensors()[0])
    o = np.stack([np.array(ray.o.x), np.array(ray.o.y), np.array(ray.o.z)], axis=1)
    d = np.stack([np.array(ray.d.x), np.array(ray.d.y), np.array(ray.d.z)], axis=1)
    r = mi_amr.trace(mi_amr.load(folder / "sphere.npz"), o, d, field="f", isovalue=0.3)
    hit = r.hit.reshape(RES, RES)
    assert 0.1 < hit.mean() < 0.9
    np.testing.assert_array_equal(img[..., 3] > 0.5, hit)
    np.testing.assert_allclose(ch["iso_depth.T"][hit], r.t.reshape(RES, RES)[hit], atol=1e-4)
    assert np.all(ch["iso_depth.T"][~hit] == np.inf)
    pos = np.stack([ch["iso_pos.X"], ch["iso_pos.Y"], ch["iso_pos.Z"]], axis=-1)[hit]
    want = (o + r.t[:, None] * d).reshape(RES, RES, 3)[hit]
    np.testing.assert_allclose(pos, want, atol=1e-4)
    np.testing.assert_allclose(ch["iso_value.V"][hit], 0.3, atol=1e-4)
    normal = np.stack([ch["iso_normal.X"], ch["iso_normal.Y"], ch["iso_normal.Z"]], -1)[hit]
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-4)
    assert set(np.unique(ch["iso_level.L"][hit])) <= {0.0, 1.0}


def test03_label_aovs_are_exact_under_the_default_filter(variant, folder):
    """With Mitsuba's default Gaussian filter and 16 random samples a pixel, the AOVs are those
    of the ray through each pixel's centre, unfiltered: level and grid id are whole numbers,
    the finest grid at the hit (the sphere's grid 1, level 1, covers x >= 0.5); depth equals
    :func:`mi_amr.trace` on hits and is ``inf`` on misses. (The filter used to blend ids into
    numbers such as 0.27 along the grids' boundary, and put depth 0 on misses.)"""
    mi = variant
    import mi_amr
    from mi_amr.evaluation.references import pixel_rays
    from mi_amr.plugin.aovs import NAMES
    from mi_amr.plugin.scene import load_scene

    path = folder / "labels.xml"
    integ = ('<integrator type="amr_iso"><string name="filename" value="sphere.npz"/>'
             '<string name="field" value="f"/><float name="isovalue" value="0.3"/></integrator>')
    text = scene_text("", integ).replace(f'value="{SPP}"', 'value="16"')
    path.write_text(text[:text.index("<shape")] + text[text.index("</shape>") + 8:])
    scene = load_scene(path, integrator={"aovs": True}, pixel_format="rgba")
    img = np.array(mi.render(scene, seed=3))
    ch = {name: img[..., 4 + i] for i, name in enumerate(NAMES)}
    ray = pixel_rays(scene.sensors()[0])
    o = np.stack([np.array(ray.o.x), np.array(ray.o.y), np.array(ray.o.z)], axis=1)
    d = np.stack([np.array(ray.d.x), np.array(ray.d.y), np.array(ray.d.z)], axis=1)
    r = mi_amr.trace(mi_amr.load(folder / "sphere.npz"), o, d, field="f", isovalue=0.3)
    hit = r.hit.reshape(RES, RES)
    x = (o + r.t[:, None] * d)[:, 0].reshape(RES, RES)
    want = np.where(hit, (x >= 0.5).astype(np.float32), 0.0)
    assert 0 < want[hit].mean() < 1, "the view must show both grids"
    np.testing.assert_array_equal(ch["iso_grid.G"], want)
    np.testing.assert_array_equal(ch["iso_level.L"], want)
    np.testing.assert_allclose(ch["iso_depth.T"][hit], r.t.reshape(RES, RES)[hit], atol=1e-4)
    assert np.all(ch["iso_depth.T"][~hit] == np.inf)
    # The colour is still filtered and sampled: it differs from seed to seed.
    assert not np.array_equal(img[..., :4], np.array(mi.render(scene, seed=4))[..., :4])
    np.testing.assert_array_equal(img[..., 4:], np.array(mi.render(scene, seed=4))[..., 4:])
