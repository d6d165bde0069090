"""The small kernels checked against their slow twins or closed forms, without a scene: roots
of cubics, the colour map, the opacity band, the per-ray jitter, Phong's terms and the
front-to-back layering; and the parameter table against the integrator's docstring.
"""

import math

import numpy as np
import pytest

from mi_amr import AMRError, params, tolerances

dr = pytest.importorskip("drjit")
from drjit.llvm.ad import Array3f, Array2f, Bool, Float, UInt32  # noqa: E402

import drjit.llvm.ad as m  # noqa: E402

from mi_amr.kernels import band, colormap, jitter, roots  # noqa: E402


def f(x):
    return Float(np.asarray(x, dtype=np.float32))


# ---------------------------------------------------------------------- roots

def test01_cubic_is_horner_and_extrema_are_the_derivatives_roots():
    rng = np.random.default_rng(1)
    c = rng.normal(size=(4, 64))
    s = rng.random(64) * 2
    want = c[0] + c[1] * s + c[2] * s ** 2 + c[3] * s ** 3
    np.testing.assert_allclose(roots.cubic([f(x) for x in c], f(s)).numpy(), want, rtol=1e-5,
                               atol=1e-5)
    # (s - 0.3)(s - 0.7)(s - 2) has extrema where 3 s^2 - 6 s + 1.81 = 0.
    p = np.polynomial.polynomial.polyfromroots([0.3, 0.7, 2.0])
    r1, r2 = roots.extrema([Float(float(x)) for x in p], Float(1.5))
    ext = np.sort(np.roots([3 * p[3], 2 * p[2], p[1]]).real)
    assert r1.numpy()[0] == pytest.approx(ext[0], abs=1e-5)
    assert r2.numpy()[0] == pytest.approx(1.5)        # the second lies beyond L


@pytest.mark.parametrize("known", [(0.3, 0.7, 2.0), (-0.5, 0.25, 0.9), (0.6, 3.0, 4.0)])
def test02_first_root_is_never_missed_and_is_refined(known):
    """The first root in [0, 1] of a cubic with known roots, bracketed and bisected."""
    p = np.polynomial.polynomial.polyfromroots(known)
    c = [Float(float(x)) for x in p]
    found, a, b = roots.first_root_bracket(c, Float(1.0), Float(float(np.abs(p).sum())))
    first = min([r for r in known if 0 <= r <= 1], default=None)
    assert bool(found.numpy()[0]) == (first is not None)
    if first is not None:
        assert roots.refine_root(c, a, b).numpy()[0] == pytest.approx(first, abs=1e-6)


def test03_a_tangent_counts_as_a_root():
    """(s - 0.4)^2 (s + 2): a double root, no sign change, touched within the tolerance."""
    p = np.polynomial.polynomial.polyfromroots([0.4, 0.4, -2.0])
    c = [Float(float(x)) for x in p]
    found, a, b = roots.first_root_bracket(c, Float(1.0), Float(float(np.abs(p).sum())))
    assert bool(found.numpy()[0])
    # (float32 may put the tangent just below zero: then [0, 0.4] brackets it.)
    assert roots.refine_root(c, a, b).numpy()[0] == pytest.approx(0.4, abs=1e-3)


# ---------------------------------------------------------------------- colour map

def lookup(cmap, x, value_range=None):
    edges, colors = cmap.table()
    rng = np.asarray(cmap.value_range if value_range is None else value_range, np.float32)
    out = colormap.lookup(m, Float(edges), Float(colors), Array2f(float(rng[0]), float(rng[1])),
                          f(x))
    return np.stack([out.x.numpy(), out.y.numpy(), out.z.numpy()], axis=1)


@pytest.mark.parametrize("spec,data_range", [
    ("0.012: 0.03 0.03 1.0, 0.025: 0.03 1.0 0.03, 0.072: 1.0 0.03 0.03", None),
    ("1e-5: 1 0 0, 3e-5: 0 0 1", None),
    ("-1000: 0 0 0, 0: 1 1 1, 2000: 1 0 0", None),
    ("viridis", (0.0, 0.08)),
    ("magma", (-3.0, 5.0))])
def test04_colormap_lookup_matches_its_slow_twin(spec, data_range):
    """The kernel's fixed-depth binary search against ``np.interp`` (float32 rounding apart),
    below, inside and above the range, for pairs at very different scales and named maps."""
    cmap = colormap.ColorMap.parse(spec, data_range)
    lo, hi = cmap.value_range
    x = np.linspace(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), 997)
    np.testing.assert_allclose(lookup(cmap, x), cmap.numpy(x), atol=2e-4)
    stretched = (lo - 1.0, hi + 1.0)
    np.testing.assert_allclose(lookup(cmap, x, stretched), cmap.numpy(x, stretched), atol=2e-4)


def test05_colormap_holds_scale_with_the_pairs():
    """The report's pairs hold +-0.0025 (1/24 of their span); pairs 1e-5 apart hold 1/24 of
    that (not a fixed +-0.0025 that would swallow them); close pairs hold a quarter of their
    gap; equal values are refused."""
    report = colormap.ColorMap.parse("0.012: 0 0 1, 0.025: 0 1 0, 0.072: 1 0 0")
    span = 0.072 - 0.012
    assert (report.edges[1] - report.edges[0]) * span == pytest.approx(0.005)
    tiny = colormap.ColorMap.parse("1e-5: 1 0 0, 2e-5: 0 0 1")
    hold = 1e-5 / 24
    np.testing.assert_allclose(tiny.numpy([1e-5 + 0.9 * hold, 2e-5 - 0.9 * hold]),
                               [[1, 0, 0], [0, 0, 1]], atol=1e-9)
    assert tiny.numpy([1.5e-5])[0] == pytest.approx([0.5, 0, 0.5])
    close = colormap.ColorMap.parse("0: 1 0 0, 0.01: 0 1 0, 1: 0 0 1")
    assert (close.edges[1] - close.edges[0]) == pytest.approx(2 * 0.25 * 0.01)
    with pytest.raises(AMRError, match="must differ"):
        colormap.ColorMap.parse("0.1: 1 0 0, 0.1: 0 1 0")


# ---------------------------------------------------------------------- opacity band

def test06_band_alpha_and_preintegration_match_numpy():
    shape = band.OpacityBand(width=0.01, support=(-0.02, 0.03), peak=1.2, dx0=0.5)
    inputs = shape.inputs(m)
    v = np.linspace(-0.05, 0.05, 301)
    np.testing.assert_allclose(band.alpha(m, inputs, 0, f(v), Float(0.0)).numpy(),
                               shape.alpha_numpy(v, 0.0), atol=1e-6)
    # A linear ramp from a to b over dx: optical depth dx * mean of tau over [a, b].
    a, b, dx = -0.015, 0.02, 0.3
    xs = np.linspace(a, b, 20001)
    tau = -np.log1p(-np.minimum(shape.alpha_numpy(xs, 0.0), tolerances.OPACITY_CAP)) / 0.5
    want = 1.0 - math.exp(-np.trapezoid(tau, xs) / (b - a) * dx)
    ramp = band.Ramp(Float(a), Float(b), Float(dx))
    got = band.segment_alpha(m, inputs, 0, ramp, Float(0.0)).numpy()[0]
    assert got == pytest.approx(want, abs=2e-4)
    # Opacity correction: two half steps compose to one full step.
    half = band.corrected(inputs, Float(0.6), Float(0.25)).numpy()[0]
    assert 1 - (1 - half) ** 2 == pytest.approx(0.6, abs=1e-6)


def test06b_several_bands_keep_their_own_shapes_and_add_optical_depths():
    """Two bands on one device table: each reads its own width, support and table; together
    their opacity is 1 - (1 - a0)(1 - a1), shared in proportion to their optical depths."""
    b0 = band.OpacityBand(width=0.01, support=(-0.02, 0.03), peak=1.2, dx0=0.5)
    b1 = band.OpacityBand(width=0.05, support=(-0.1, 0.1), peak=0.3, dx0=0.5)
    inputs = band.band_inputs(m, [b0, b1])
    v = np.linspace(-0.2, 0.2, 100)     # (no value exactly on a support's end)
    for k, shape in enumerate((b0, b1)):
        np.testing.assert_allclose(band.alpha(m, inputs, k, f(v), Float(0.0)).numpy(),
                                   shape.alpha_numpy(v, 0.0), atol=1e-6)
        ramp = band.Ramp(Float(-0.01), Float(0.02), Float(0.3))
        one = band.segment_alpha(m, shape.inputs(m), 0, ramp, Float(0.0)).numpy()
        two = band.segment_alpha(m, inputs, k, ramp, Float(0.0)).numpy()
        np.testing.assert_allclose(one, two, rtol=1e-6)
    a, shares = band.combine([Float(0.5), Float(0.75)])
    assert a.numpy()[0] == pytest.approx(1 - 0.5 * 0.25, abs=1e-6)
    assert shares[0].numpy()[0] == pytest.approx(np.log(2) / (np.log(2) + np.log(4)), abs=1e-6)


@pytest.mark.parametrize("a, b, dx", [
    (-0.015, 0.02, 0.3),     # through the band, thin to opaque
    (0.02, -0.015, 0.3),     # the same, the other way
    (-0.015, 0.02, 0.001),   # thin: half the optical depth
    (-0.03, 0.05, 4.0),      # wider than the support, opaque: near the front
    (0.004, 0.006, 0.5),     # inside one flank
    (0.005, 0.005, 0.5)])    # flat
def test06c_a_steps_centroid_matches_quadrature(a, b, dx):
    """Where a pre-integrated step is lit and coloured (its centroid, a fraction of the step)
    against float64 quadrature of the same band; the opacity is segment_alpha's."""
    shape = band.OpacityBand(width=0.01, support=(-0.02, 0.03), peak=1.2, dx0=0.5)
    inputs = shape.inputs(m)
    args = (m, inputs, 0, band.Ramp(Float(a), Float(b), Float(dx)), Float(0.0))
    alpha, u = band.segment_alpha_and_centroid(*args)
    ref_alpha, ref_u = shape.centroid_numpy(a, b, dx)
    assert alpha.numpy()[0] == pytest.approx(band.segment_alpha(*args).numpy()[0], abs=1e-7)
    assert alpha.numpy()[0] == pytest.approx(ref_alpha, abs=1e-3)
    assert u.numpy()[0] == pytest.approx(ref_u, abs=tolerances.CENTROID_ABS)


@pytest.mark.parametrize("a, b, dx", [
    (-0.015, 0.02, 0.3), (0.02, -0.015, 0.3), (-0.015, 0.02, 0.001), (-0.03, 0.05, 4.0),
    (0.004, 0.006, 0.5)])
def test06d_where_a_step_makes_half_its_opacity_matches_quadrature(a, b, dx):
    """The place a piece is lit (where half its opacity is made) against its float64 twin."""
    shape = band.OpacityBand(width=0.01, support=(-0.02, 0.03), peak=1.2, dx0=0.5)
    args = (m, shape.inputs(m), 0, band.Ramp(Float(a), Float(b), Float(dx)), Float(0.0))
    _, u = band.segment_alpha_and_point(*args)
    assert u.numpy()[0] == pytest.approx(shape.point_numpy(a, b, dx), abs=5e-4)


def test07_bad_band_shapes_are_refused():
    with pytest.raises(AMRError, match="band_width"):
        band.OpacityBand(width=-1.0)
    with pytest.raises(AMRError, match="band_support"):
        band.OpacityBand(width=0.01, support=(0.01, 0.02))


# ---------------------------------------------------------------------- jitter

def test08_stable_jitter_is_its_numpy_twin_and_spreads_over_0_1():
    n = 4096
    got = jitter.stable_jitter(m, dr.arange(UInt32, n), 7).numpy()
    np.testing.assert_array_equal(got, jitter.stable_jitter_numpy(n, 7).astype(np.float32))
    assert got.min() >= 0.0 and got.max() < 1.0
    counts, _ = np.histogram(got, bins=16, range=(0, 1))
    assert counts.min() > 0.7 * n / 16
    assert not np.array_equal(got, jitter.stable_jitter(m, dr.arange(UInt32, n), 8).numpy())


# ---------------------------------------------------------------------- the parameter table

def test09_the_integrators_docstring_is_the_parameter_table():
    """Every parameter appears in the generated docstring table with its type and default, and
    the options parser knows exactly the table's names."""
    table = params.docstring_table()
    for p in params.TABLE:
        line = next(l for l in table.splitlines() if l.split()[:1] == [p.name])
        assert p.kind.split()[0] in line
    pytest.importorskip("mitsuba")
    from mi_amr.plugin import options

    assert set(options.Options.__dataclass_fields__) | {"to_world", "isovalue", "iso_color"} \
        >= {p.name for p in params.TABLE} - {"isovalue", "iso_color"}
    with pytest.raises(AMRError, match="did you mean 'isovalue'"):
        options.parse({"filename": "x", "field": "f", "isovalue": 1, "isovalu": 2})


def test10_every_tolerance_has_a_reason():
    """tolerances.py: each name is preceded by a comment saying why it has its value."""
    import inspect

    lines = inspect.getsource(tolerances).splitlines()
    names = [i for i, l in enumerate(lines) if l and l[0].isupper() and " = " in l]
    assert len(names) >= 15
    for i in names:
        assert lines[i - 1].startswith("#"), f"no reason given for {lines[i]}"

