"""Stochastic layers with numbers shared by a SIMD packet (``Twins.packet_picks``).

* The wavefront by sample (:func:`mi_amr.plugin.wavefront.tiled_lanes`): every pixel's every
  sample once, a packet of 16 lanes holding one sample index of 16 pixels of the tile order.
* :func:`~mi_amr.plugin.wavefront.packet_u`: one number per packet, stratified over a pixel's
  samples, uniform over the frame, other numbers for other seeds and streams.
* The shadow rays' Russian roulette (:func:`mi_amr.kernels.transmit.transmittance_exact` with
  ``u``): averaged over evenly spread ``u`` it is the exact transmittance, to the spread's
  step; where that is at least :data:`~mi_amr.tolerances.ROULETTE_T`, every ``u`` gives it.
* The per-lane twin (``Twins(packet_picks=False)``) renders what it rendered before; both converge
  to the composited image (``tests/test_stochastic_layers.py`` test02 checks the default).

The scene is sphere_wake.xml with three isovalues of opacity 0.4, 0.5 and 0.6.
"""

from types import SimpleNamespace

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

from mi_amr.plugin.twins import Twins, with_twins  # noqa: E402
from mi_amr.plugin.scene import load_scene  # noqa: E402
from mi_amr.workflows import project  # noqa: E402

TRANSLUCENT = {"isovalue": "0.02, 0.05, 0.1", "iso_opacity": "0.4, 0.5, 0.6"}
SPREAD = 200          # evenly spread u per shadow ray


def lanes(width, height, spp, by_sample):
    from mi_amr.plugin import wavefront

    order = mi.UInt32(wavefront.pixel_order(width, height))
    return np.array(wavefront.tiled_lanes(order, width * height * spp, spp, by_sample))


@pytest.mark.parametrize("shape", [(8, 8, 4), (5, 7, 3), (4, 4, 1), (6, 3, 2)])
def test01_a_wavefront_by_sample_takes_each_sample_once_a_packet_one_sample(variant, shape):
    from mi_amr.plugin import wavefront

    width, height, spp = shape
    n, npix = width * height * spp, width * height
    order = wavefront.pixel_order(width, height)
    pos = np.arange(n)
    np.testing.assert_array_equal(lanes(*shape, False), order[pos // spp] * spp + pos % spp)
    by_sample = lanes(*shape, True)
    np.testing.assert_array_equal(np.sort(by_sample), pos)
    sample, pixel = by_sample % spp, by_sample // spp
    group = wavefront.PACKET * spp
    for start in range(0, n, group):                 # a group: its pixels' samples in turn
        size = min(wavefront.PACKET, npix - start // spp)
        g_pixels = order[start // spp:start // spp + size]
        for s in range(spp):
            span = slice(start + s * size, start + (s + 1) * size)
            assert (sample[span] == s).all()
            np.testing.assert_array_equal(pixel[span], g_pixels)


def by_sample_lanes(width, height, spp, seed):
    """The :class:`~mi_amr.plugin.wavefront.Lanes` that
    :func:`~mi_amr.plugin.wavefront.render` hands the samples of a wavefront by sample."""
    from mi_amr.plugin import wavefront

    order = mi.UInt32(wavefront.pixel_order(width, height))
    lane = wavefront.tiled_lanes(order, width * height * spp, spp, True)
    return wavefront.Lanes(lane, (mi.UInt32(spp), mi.UInt32(seed)))


def packet_numbers(lanes, salt):
    from mi_amr.kernels.device import backend_of
    from mi_amr.plugin import wavefront

    ray = SimpleNamespace(o=mi.Point3f(dr.zeros(mi.Float, dr.width(lanes.lane))))
    return np.array(wavefront.packet_u(backend_of(mi.Float), lanes, ray, salt))


def test02_a_packet_shares_its_number_stratified_over_a_pixels_samples(variant):
    from mi_amr.plugin import wavefront

    width, height, spp = 64, 64, 4
    lanes = by_sample_lanes(width, height, spp, seed=5)
    u = packet_numbers(lanes, salt=0)
    assert u.min() >= 0.0 and u.max() < 1.0
    packets = u.reshape(-1, wavefront.PACKET)          # 64^2 pixels: full groups only
    assert (packets == packets[:, :1]).all()
    # Per pixel one sample in each stratum [s / spp, (s + 1) / spp).
    lane = np.array(lanes.lane)
    strata = np.empty((width * height, spp), dtype=np.int64)
    strata[lane // spp, lane % spp] = np.floor(u * spp)
    np.testing.assert_array_equal(np.sort(strata, axis=1), np.tile(np.arange(spp), (4096, 1)))
    # Which stratum a sample index gets varies from group to group (a pixel's sample 0 is not
    # always the smallest number: the camera's and the shadow rays' streams stay independent).
    assert len(np.unique(strata[:, 0])) == spp
    # Uniform over the frame (1024 packets: 10 bins within 5 standard deviations).
    counts = np.histogram(packets[:, 0], bins=10, range=(0, 1))[0]
    assert np.abs(counts - 102.4).max() < 5 * np.sqrt(102.4)
    # Other streams and seeds: other numbers.
    other_salt = packet_numbers(lanes, salt=1)
    other_seed = packet_numbers(by_sample_lanes(width, height, spp, seed=6), salt=0)
    for v in (other_salt, other_seed):
        assert np.mean(np.abs(v - u) > 1e-3) > 0.9
        assert abs(np.corrcoef(v, u)[0, 1]) < 0.1


def test09_a_groups_turn_is_independent_of_every_packets_number(variant):
    """The turn that rotates a group's strata (which sample index gets which stratum) and
    the packets' numbers ``xi`` come from two hash streams: drawn from one, group ``G``'s
    turn would be packet ``G``'s ``xi`` times ``spp``, rounded down, every time."""
    from mi_amr.plugin import wavefront

    width, height, spp = 64, 64, 4
    lanes = by_sample_lanes(width, height, spp, seed=5)
    u = packet_numbers(lanes, salt=0).astype(np.float64)
    lane = np.array(lanes.lane)
    packet, group = wavefront.PACKET, wavefront.PACKET * spp
    xi = (u[::packet] * spp) % 1.0                                # per packet
    first = np.arange(0, len(u), group)                           # each group's first lane
    turn = (np.floor(u[first] * spp).astype(np.int64) - lane[first] % spp) % spp
    same = np.floor(xi[:len(turn)] * spp).astype(np.int64) == turn
    assert len(turn) == 256 and len(np.unique(turn)) == spp
    assert same.mean() < 0.4, same.mean()                         # 1 / spp expected


def test03_no_shared_numbers_outside_a_wavefront_by_sample(variant):
    from mi_amr.kernels.device import backend_of
    from mi_amr.plugin import wavefront

    m = backend_of(mi.Float)
    lanes = by_sample_lanes(8, 8, 2, seed=0)
    narrow = SimpleNamespace(o=mi.Point3f(dr.zeros(mi.Float, 10)))
    assert wavefront.packet_u(m, lanes, narrow, 0) is None
    wide = SimpleNamespace(o=mi.Point3f(dr.zeros(mi.Float, 128)))
    assert wavefront.packet_u(m, lanes, wide, 0) is not None
    assert wavefront.packet_u(m, wavefront.Lanes(lanes.lane), wide, 0) is None
    assert wavefront.packet_u(m, None, wide, 0) is None


@pytest.fixture(scope="module")
def translucent(scene_data_ready):
    return load_scene(project.scenes_dir() / "sphere_wake.xml", resx=32, resy=32, spp=2,
                      integrator=dict(TRANSLUCENT, layers="stochastic"))


def test04_the_roulette_averages_to_the_exact_transmittance(translucent):
    from test_translucent import random_rays

    from mi_amr import tolerances as tol
    from mi_amr.plugin import surfaces

    integ = translucent.integrator()
    m = integ.m
    o, d = random_rays(integ, n=1500, seed=4)
    O, D = np.repeat(o, SPREAD, axis=0), np.repeat(d, SPREAD, axis=0)
    u = np.tile((np.arange(SPREAD) + 0.5) / SPREAD, len(o)).astype(np.float32)

    def shadow(o, d, u):
        return np.array(surfaces.transmittance(
            integ, integ.config(), m.Array3f(*o.T), m.Array3f(*d.T), m.Float(0.0),
            m.Float(50.0), mi.Bool(True), None if u is None else mi.Float(u)), dtype=np.float64)

    exact = shadow(o, d, None)
    sampled = shadow(O, D, u).reshape(len(o), SPREAD)
    # (measured: 21 % of the rays cross a layer, 8.5 % end between 0 and ROULETTE_T)
    assert np.mean(exact < 0.99) > 0.15 and np.mean((exact < tol.ROULETTE_T) & (exact > 0)) > 0.04
    # Each sample is 0, the exact transmittance, or ROULETTE_T where that is below it.
    assert np.isin(sampled, [0.0, tol.ROULETTE_T]).all(axis=1)[exact < tol.ROULETTE_T].all()
    above = exact >= tol.ROULETTE_T
    np.testing.assert_array_equal(sampled[above], np.repeat(exact[above], SPREAD).reshape(-1,
                                                                                       SPREAD))
    np.testing.assert_allclose(sampled.mean(axis=1), exact, rtol=0,
                               atol=tol.ROULETTE_T / SPREAD + 1e-6)


def test05_the_per_lane_twin_and_the_packets_converge_to_one_image(translucent):
    """Means of 24 frames (32^2, 2 spp): per pixel and channel, the packets' and the per-lane
    twin's differ by what their noise gives (measured: 3.8e-4 against the noise's 4.1e-4,
    two seeds of each 4.0e-4 and 4.2e-4; image means 0.2445 and 0.2440)."""
    integ = translucent.integrator()

    def mean_image(seeds, integrator=None):
        return np.mean([np.array(mi.render(translucent, seed=s, integrator=integrator),
                                 dtype=np.float64) for s in seeds], axis=0)

    shared = mean_image(range(24))
    per_lane = with_twins(integ, Twins(packet_picks=False))
    lanes_a, lanes_b = mean_image(range(24), per_lane), mean_image(range(100, 124), per_lane)
    shared_b = mean_image(range(200, 224))
    noise = (np.mean((lanes_a - lanes_b) ** 2) + np.mean((shared - shared_b) ** 2)) / 2
    assert shared.mean() > 0.05
    assert np.mean((shared - lanes_a) ** 2) < 1.3 * noise
    assert abs(shared.mean() - lanes_a.mean()) < 0.01 * shared.mean()


def test06_at_one_sample_per_pixel_lanes_keep_their_own_numbers(scene_data_ready):
    """(A number shared by 16 pixels of one sample each would show as 4 x 4 blocks of noise.)
    The same image with and without ``packet_picks``, up to the film's atomic adds."""
    sc = load_scene(project.scenes_dir() / "sphere_wake.xml", resx=32, resy=32, spp=1,
                    integrator=dict(TRANSLUCENT, layers="stochastic"))
    shared = np.array(mi.render(sc, seed=2))
    own = np.array(mi.render(sc, seed=2,
                             integrator=with_twins(sc.integrator(), Twins(packet_picks=False))))
    assert shared.mean() > 0.05
    np.testing.assert_allclose(shared, own, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("least", [1, 4])
def test07_passes_of_stochastic_layers_take_several_samples(least):
    """The render workflow's and the viewer's passes (``pass_samples``): every sample once, at
    most 16 a pass, and with stochastic layers (``least`` 4) passes of 2 or more spp, where
    packets share their numbers; with 1 the layout before, one sample a pass up to 16."""
    from mi_amr.workflows.render import pass_samples

    for total in (1, 2, 3, 5, 8, 16, 17, 40, 100, 256, 1000):
        spp = pass_samples(total, least)
        assert sum(spp) == total and max(spp) <= 16 and len(spp) <= max(16, -(-total // 16))
        if least == 1:
            passes = max(min(total, 16), -(-total // 16))
            assert len(spp) == passes and max(spp) - min(spp) <= 1
        elif total >= 2:
            assert min(spp) >= 2


def test08_the_render_workflow_asks_stochastic_layers_for_passes_of_4(translucent,
                                                                      scene_data_ready):
    from mi_amr.workflows.render import STOCHASTIC_PASS_SPP, least_pass_spp

    assert least_pass_spp(translucent.integrator()) == STOCHASTIC_PASS_SPP == 4
    composited = load_scene(project.scenes_dir() / "sphere_wake.xml", resx=8, resy=8, spp=1,
                            integrator=TRANSLUCENT)
    assert least_pass_spp(composited.integrator()) == 1
    assert least_pass_spp(object()) == 1
