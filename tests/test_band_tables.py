"""Every band's table lookups (:mod:`mi_amr.kernels.band`), for bands k >= 1 as for band 0.

Several bands share one :class:`~mi_amr.kernels.band.BandInputs`: their integral tables and
their inverses lie one after another, band ``k``'s from ``k * (size + 1)``. Each band's
integral, inverse, pre-integrated opacity, point and centroid, looked up as band ``k`` of three
bands of different shapes, are what the same band alone gives, bit for bit, and agree with the
band's float64 twins (:meth:`~mi_amr.kernels.band.OpacityBand.integral_numpy`,
:meth:`~mi_amr.kernels.band.OpacityBand.inverse_numpy`,
:meth:`~mi_amr.kernels.band.OpacityBand.point_numpy`,
:meth:`~mi_amr.kernels.band.OpacityBand.centroid_numpy`). Runs on every present variant.
"""

import numpy as np
import pytest

from mi_amr import tolerances as tol

pytest.importorskip("drjit")

from mi_amr.kernels import band  # noqa: E402

# Three shapes of one dx0: capped and symmetric, faint with a lopsided support, capped with
# the other lopsided support (their tables differ everywhere, so a lookup in the wrong band's
# table shows).
SHAPES = (dict(width=0.004, peak=1.6), dict(width=0.01, support=(-0.02, 0.03), peak=0.3),
          dict(width=0.006, support=(-0.015, 0.01), peak=1.2))
CENTRES = (0.5, 1.0, 1.5)
DX0 = 0.5
INTEGRAL_REL = 2e-5   # of the band's total integral: float32 tables, linear interpolation
INVERSE_REL = 2e-4    # of the support's width: linear interpolation where T is flat (its ends)


@pytest.fixture(scope="module")
def shapes():
    return [band.OpacityBand(dx0=DX0, **kw) for kw in SHAPES]


def lookups(m, inputs, k, shape, rng):
    """Band ``k``'s integral, inverse, opacity with point and centroid, as NumPy arrays, at
    offsets, integrals and ramps drawn by ``rng`` for ``shape``."""
    x = np.concatenate([np.linspace(1.1 * shape.lo, 1.1 * shape.hi, 3001), [shape.lo, shape.hi]])
    total = shape.integral_numpy(shape.hi)
    T = total * np.concatenate([np.linspace(0.0, 1.0, 3001), [1e-6, 1e-4, 1e-3, 1 - 1e-4]])
    a, b, dx = ramps(shape, rng)
    c = CENTRES[k]
    F = lambda v: m.Float(np.asarray(v, dtype=np.float32))  # noqa: E731
    ramp = band.Ramp(a=F(a + c), b=F(b + c), dx=F(dx))
    alpha_p, point = band.segment_alpha_and_point(m, inputs, k, ramp, m.Float(c), r=0.5)
    alpha_c, centroid = band.segment_alpha_and_centroid(m, inputs, k, ramp, m.Float(c))
    out = (band.integral(m, inputs, k, F(x)), band.integral_inverse(m, inputs, k, F(T)),
           alpha_p, point, alpha_c, centroid)
    return (x, T, (a, b, dx)), [np.array(v) for v in out]


def ramps(shape, rng, n=40):
    """Ramps of value offsets ``a -> b`` over lengths ``dx``: across the band, into and out
    of it, short ones, both ways, thin to opaque."""
    a = rng.uniform(1.3 * shape.lo, 1.3 * shape.hi, n)
    b = np.where(rng.random(n) < 0.3, a + rng.normal(0.0, 0.1 * shape.width, n),
                 rng.uniform(1.3 * shape.lo, 1.3 * shape.hi, n))
    dx = DX0 * np.exp(rng.uniform(np.log(0.01), np.log(5.0), n))
    return a, b, dx


def test01_a_band_among_others_looks_up_what_it_looks_up_alone(backend, shapes):
    """Band ``k`` of three (integral, inverse, opacity, point, centroid) is band 0 of itself
    alone, bit for bit."""
    m = backend
    together = band.band_inputs(m, shapes)
    for k, shape in enumerate(shapes):
        _, mixed = lookups(m, together, k, shape, np.random.default_rng(k))
        alone_inputs = band.band_inputs(m, [shape] * (k + 1))    # the same table at k
        _, alone = lookups(m, alone_inputs, k, shape, np.random.default_rng(k))
        for name, got, want in zip(("integral", "inverse", "alpha", "point", "alpha",
                                    "centroid"), mixed, alone):
            np.testing.assert_array_equal(got, want, err_msg=f"band {k}: {name}")


def test02_every_band_matches_its_float64_twins(backend, shapes):
    """Each band's lookups against its shape's float64 twins: the integral to
    :data:`INTEGRAL_REL` of its total, the inverse to :data:`INVERSE_REL` of the support, the
    opacity to 5e-5, the point and the centroid (weighted by the step's opacity, as the light
    they place) within :data:`~mi_amr.tolerances.CENTROID_ABS`."""
    m = backend
    inputs = band.band_inputs(m, shapes)
    for k, shape in enumerate(shapes):
        (x, T, ramp), (integ, inv, alpha_p, point, alpha_c, centroid) = \
            lookups(m, inputs, k, shape, np.random.default_rng(10 + k))
        total = shape.integral_numpy(shape.hi)
        assert np.abs(integ - shape.integral_numpy(x)).max() < INTEGRAL_REL * total, k
        width = shape.hi - shape.lo
        assert np.abs(inv - shape.inverse_numpy(T)).max() < INVERSE_REL * width, k
        ref_c = np.array([shape.centroid_numpy(*q, n=40001) for q in zip(*ramp)])
        ref_p = np.array([shape.point_numpy(*q, n=40001) for q in zip(*ramp)])
        np.testing.assert_allclose(alpha_p, ref_c[:, 0], atol=5e-5, err_msg=f"band {k}")
        np.testing.assert_allclose(alpha_c, ref_c[:, 0], atol=5e-5, err_msg=f"band {k}")
        assert (np.abs(centroid - ref_c[:, 1]) * ref_c[:, 0]).max() < tol.CENTROID_ABS, k
        assert (np.abs(point - ref_p) * ref_c[:, 0]).max() < tol.CENTROID_ABS, k
