"""The integrator's parts without a scene: Phong's terms, the shading normal, shadow rays and
the front-to-back layering (with made-up layers), against closed forms."""

import numpy as np
import pytest


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


def test01_phong_terms_are_the_lecture_formula(variant):
    mi = variant
    from mi_amr.plugin.shading import Phong, phong_terms

    ph = Phong(ka=0.1, kd=0.7, ks=0.3, shininess=16.0, ambient=1.0)
    n = mi.Vector3f(0, 0, 1)
    to_light = mi.Vector3f(float(np.sin(0.5)), 0, float(np.cos(0.5)))
    to_eye = mi.Vector3f(float(-np.sin(0.2)), 0, float(np.cos(0.2)))
    d, s = phong_terms(ph, n, to_light, to_eye, mi.Color3f(2.0))
    h = np.array([np.sin(0.5) - np.sin(0.2), 0, np.cos(0.5) + np.cos(0.2)])
    h /= np.linalg.norm(h)
    assert np.array(d)[0, 0] == pytest.approx(0.7 * 2 * np.cos(0.5), rel=1e-5)
    assert np.array(s)[0, 0] == pytest.approx(0.3 * 2 * h[2] ** 16, rel=1e-4)
    # From behind: no diffuse light.
    d, _ = phong_terms(ph, n, mi.Vector3f(0, 0, -1), to_eye, mi.Color3f(2.0))
    assert np.array(d)[0, 0] == 0.0


def test02_the_shading_normal_faces_the_viewer(variant):
    """The gradient taken to the scene (a scale: normals use the inverse transpose), turned
    towards the viewer, and the viewer's direction where the gradient is zero."""
    mi = variant
    from mi_amr.plugin.shading import facing_normal

    to_world = mi.Transform4f().scale([2.0, 1.0, 1.0])
    # Three lanes: a gradient along x seen along +x, one along (1, 1, 0) seen along +y (its
    # scene normal is (1, 2, 0) / sqrt(5) under the scale), and no gradient seen along -z.
    grads = np.array([[1, 0, 0], [1, 1, 0], [0, 0, 0]], dtype=np.float32)
    dirs = np.array([[1, 0, 0], [0, 1, 0], [0, 0, -1]], dtype=np.float32)
    grad = mi.Normal3f(*(mi.Float(grads[:, a]) for a in range(3)))
    ray_d = mi.Vector3f(*(mi.Float(dirs[:, a]) for a in range(3)))
    n = np.array(facing_normal(to_world, grad, ray_d))       # (xyz, lanes)
    want = np.array([[-1, 0, 0], [-1 / np.sqrt(5), -2 / np.sqrt(5), 0], [0, 0, 1]])
    np.testing.assert_allclose(n.T, want, atol=1e-6)      # (lanes, xyz)


def test03_a_shadow_ray_stops_before_the_light(variant):
    """From a point off every mesh: the light sample's direction, ending just short of it."""
    mi = variant
    from mi_amr.plugin.shading import shadow_ray

    ds = mi.DirectionSample3f()
    ds.p = mi.Point3f(0, 0, 10)
    ds.d = mi.Vector3f(0, 0, 1)
    ds.dist = mi.Float(10.0)
    ray = shadow_ray(mi.Point3f(0, 0, 0), ds)
    assert np.array(ray.maxt)[0] < 10.0
    assert np.array(ray.maxt)[0] > 10.0 * (1 - 1e-3)


def test04_front_to_back_composites_made_up_layers(variant):
    """Three layers of opacity 0.5, 0.5 and 1 with radiance 1, 2 and 4: L = 0.5 + 0.5 + 1 =
    2, T = 0; with max_layers 2 the third is never reached (T = 0.25); transmittance alone
    needs no shading."""
    mi = variant
    from mi_amr.plugin.layers import front_to_back

    alphas = [0.5, 0.5, 1.0]
    radiance = [1.0, 2.0, 4.0]

    def crossing(t, alive):
        k = mi.UInt32(mi.Float(t))          # layer k sits at t = k + 0.5
        hit = alive & (k < 3)
        return hit, mi.Float(k), mi.Float(k) + 1.0, k     # the state: where to look next

    def opacity(k):
        return dr.select(k == 0, alphas[0], dr.select(k == 1, alphas[1], alphas[2]))

    def shade(hit, where, k):
        return mi.Spectrum(dr.select(k == 0, radiance[0], dr.select(k == 1, radiance[1],
                                                                   radiance[2])))

    import drjit as dr

    L, T = front_to_back(mi.Float(0.0), crossing, opacity, shade, 8, mi.Bool(True))
    assert np.array(L)[0, 0] == pytest.approx(2.0)
    assert np.array(T)[0] == 0.0
    L, T = front_to_back(mi.Float(0.0), crossing, opacity, shade, 2, mi.Bool(True))
    assert np.array(L)[0, 0] == pytest.approx(1.0)
    assert np.array(T)[0] == pytest.approx(0.25)
    _, T = front_to_back(mi.Float(0.0), crossing, opacity, None, 8, mi.Bool(True))
    assert np.array(T)[0] == 0.0
