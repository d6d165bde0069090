"""Pre-integrated colour and opacity of the exact volume method (Marchesin et al. 2009,
sections 3.1-3.2) against brute-force float64 quadrature of the same model.

On a field that is linear along the ray (``f = 2x`` on one grid over the unit cube, which both
reconstructions reproduce exactly; next to a level boundary neither does) the piecewise-linear model of the exact method *is* the
field, so the kernel's colour and transmittance of a whole ray through three bands (a capped
one, a faint one and a narrow capped one, met in both orders) must equal the integral
``C = int E(t) tau(t) exp(-int_0^t tau) dt`` taken with two million steps in float64, where the
shaded colour ``E`` is each band's colour, linear in the value, and ``tau`` the bands'
extinction. Per step, :func:`~mi_amr.kernels.band.segment_alpha_and_centroid` against
:meth:`~mi_amr.kernels.band.OpacityBand.centroid_numpy` over random ramps.
"""

import drjit as dr
import numpy as np
import pytest

from mi_amr import AMRVolume
from mi_amr import tolerances as tol
from mi_amr.kernels import band
from mi_amr.kernels.composite import Shading, composite
from mi_amr.kernels.config import MarchConfig
from mi_amr.kernels.device import opaque_floats
from mi_amr.kernels.prepared import PreparedVolume
from mi_amr.kernels.ray import RayContext

M = dr.llvm.ad
# the three bands: (isovalue, width, peak); supports +- 2 widths, disjoint
BANDS = ((0.5, 0.004, 1.6), (1.0, 0.01, 0.3), (1.5, 0.006, 1.2))
BASE = (np.array([1.0, 0.3, 0.1]), np.array([0.2, 1.0, 0.3]), np.array([0.1, 0.4, 1.0]))
MATCH = 1e-4     # the bound on colour and transmittance


def band_color(k, v):
    """Band ``k``'s colour at value ``v``: linear in the value (float64 or kernel)."""
    return [float(c) * (0.5 + 0.25 * v) for c in BASE[k]]


class FlatLight:
    """A lighting object of the compositing that shades every point with ``A = 1, S = 0``, so
    a point's shaded colour is its band colour."""

    corrects = False

    def sample(self, p, lit, visible, near=None):
        return None

    def terms(self, ctx, grad, lit):
        return M.Array3f(1.0), M.Array3f(0.0)

    def lambert(self, ctx, grad):
        return 0.0 * grad[0]


def color_of(shares, value):
    out = M.Array3f(0.0)
    for k, share in enumerate(shares):
        if share:
            out += share * M.Array3f(*band_color(k, value))
    return out


def linear_cube(n=32, stretched=False):
    """``f = 2x`` on one grid over the unit cube: ``n^3`` cubic cells, or (``stretched``)
    cells half as tall along y and twice as deep along z (``n x 2n x n/2`` of them)."""
    counts = (n, 2 * n, n // 2) if stretched else (n, n, n)
    h = tuple(1.0 / c for c in counts)
    x = (np.arange(n) + 0.5) * h[0]
    f = np.broadcast_to(2.0 * x[:, None, None], counts).copy()
    return AMRVolume.from_grids([{"level": 0, "origin": (0.0, 0.0, 0.0), "spacing": h,
                                  "fields": {"f": f}}])


@pytest.fixture(scope="module", params=["finest", "basis", "basis, stretched cells"])
def setup(request):
    vol = linear_cube(stretched="stretched" in request.param)
    dev = PreparedVolume(vol, "f", m=M).device
    # The cubes' cell width for every grid: the stretched cells see the same bands.
    assert float(dev.min_h.numpy()[0]) == (1.0 / 64 if "stretched" in request.param else 1.0 / 32)
    shapes = [band.OpacityBand(width=w, peak=p, dx0=1.0 / 32) for _, w, p in BANDS]
    cfg = MarchConfig(method="exact", basis=request.param != "finest",
                      isovalues=opaque_floats(M, [c for c, _, _ in BANDS]),
                      step_scale=opaque_floats(M, [0.5]), num_iso=len(BANDS),
                      band=band.band_inputs(M, shapes), shading_extrema=False)
    return dev, cfg, shapes


def quadrature(shapes, o, d, t1, n=2_000_000, colour=lambda v: v):
    """``(C, T)`` of the ray ``o + t d``, ``t`` in ``[0, t1]``, by the midpoint rule in
    float64; the bands' colours at the colour field's value ``colour(v)`` where the field
    is ``v``."""
    t = (np.arange(n) + 0.5) * (t1 / n)
    v = 2.0 * (o[0] + t * d[0])
    tau = np.zeros(n)
    E = np.zeros((n, 3))
    for k, (shape, (c, _, _)) in enumerate(zip(shapes, BANDS)):
        x = v - c
        tau_k = np.where((x > shape.lo) & (x < shape.hi), shape.extinction_numpy(x), 0.0)
        tau += tau_k
        E += tau_k[:, None] * np.stack(band_color(k, colour(v)), axis=-1)
    depth = np.linalg.norm(d) * t1 / n * tau
    front = np.exp(-(np.cumsum(depth) - depth))
    light = front[:, None] * (-np.expm1(-depth))[:, None] * \
        np.divide(E, tau[:, None], out=np.zeros_like(E), where=tau[:, None] > 0)
    return light.sum(axis=0), float(np.exp(-depth.sum()))


@pytest.mark.parametrize("direction", [+1.0, -1.0])
def test01_a_ray_through_three_bands_matches_float64_quadrature(setup, direction):
    dev, cfg, shapes = setup
    start = 0.02 if direction > 0 else 0.98
    o = np.array([start, 0.37, 0.41])
    d = np.array([direction * 0.9, 0.05, -0.03])
    t1 = 0.96 / 0.9
    o_k, d_k = M.Array3f(*map(float, o)), M.Array3f(*map(float, d))
    dr.make_opaque(o_k, d_k)     # (one kernel for both directions)
    res = composite(RayContext(dev, cfg, o_k, d_k, M.Float(0.0), M.Float(t1), M.Bool(True)),
                    M.Float(0.5), Shading(color_of, FlatLight()))
    C_ref, T_ref = quadrature(shapes, o, d, t1)
    C = np.array([res.C.x.numpy()[0], res.C.y.numpy()[0], res.C.z.numpy()[0]])
    assert T_ref > tol.T_MIN * 3     # no early termination: the whole ray counts
    assert C_ref.max() > 0.2
    np.testing.assert_allclose(C, C_ref, atol=MATCH, rtol=0)
    assert res.T.numpy()[0] == pytest.approx(T_ref, abs=MATCH)


@pytest.mark.parametrize("basis", [True, False], ids=["basis", "finest"])
def test01d_the_colour_comes_from_the_colour_field(basis):
    """With a colour field other than the field (``c = 3 - 2x`` beside ``f = 2x``), each
    band's colour follows ``c``: the march reads the colour field only for the pieces it
    shades, and its cubic there is the colour's, not the field's."""
    vol = linear_cube()
    vol = vol.with_fields({"c": [3.0 - g.fields["f"] for g in vol.grids]})
    dev = PreparedVolume(vol, "f", "c", m=M).device
    shapes = [band.OpacityBand(width=w, peak=p, dx0=1.0 / 32) for _, w, p in BANDS]
    cfg = MarchConfig(method="exact", basis=basis,
                      isovalues=opaque_floats(M, [c for c, _, _ in BANDS]),
                      step_scale=opaque_floats(M, [0.5]), num_iso=len(BANDS),
                      band=band.band_inputs(M, shapes), shading_extrema=False)
    o, d, t1 = np.array([0.02, 0.37, 0.41]), np.array([0.9, 0.05, -0.03]), 0.96 / 0.9
    res = composite(RayContext(dev, cfg, M.Array3f(*map(float, o)), M.Array3f(*map(float, d)),
                               M.Float(0.0), M.Float(t1), M.Bool(True)),
                    M.Float(0.5), Shading(color_of, FlatLight()))
    C_ref, T_ref = quadrature(shapes, o, d, t1, n=400_000, colour=lambda v: 3.0 - v)
    C_field, _ = quadrature(shapes, o, d, t1, n=400_000)
    assert np.abs(C_ref - C_field).max() > 20 * MATCH      # the two colourings differ
    C = np.array([res.C.x.numpy()[0], res.C.y.numpy()[0], res.C.z.numpy()[0]])
    np.testing.assert_allclose(C, C_ref, atol=MATCH, rtol=0)
    assert res.T.numpy()[0] == pytest.approx(T_ref, abs=MATCH)


@pytest.mark.parametrize("inside", [-0.6, 0.6])
def test01b_rays_that_start_inside_a_band_match_float64_quadrature(setup, inside):
    """Rays that start inside each band, a fraction ``inside`` of the way from its isovalue
    to its support's end, and leave it both ways: the first piece's values then cover only
    part of the band (the march skips a band by the piece's value range, see
    ``composite._met_band_opacities``), and the rest of the ray the other bands."""
    dev, cfg, shapes = setup
    rows = []
    for (c, _, _), shape in zip(BANDS, shapes):
        x0 = 0.5 * (c + inside * (shape.hi if inside > 0 else -shape.lo))
        for direction in (1.0, -1.0):
            rows.append((np.array([x0, 0.37, 0.41]), np.array([direction * 0.9, 0.05, -0.03])))
    o = np.array([r[0] for r in rows])
    d = np.array([r[1] for r in rows])
    # each ray runs to its side of the cube, a little short of it
    t1 = np.where(d[:, 0] > 0, (0.99 - o[:, 0]) / d[:, 0], (0.01 - o[:, 0]) / d[:, 0])
    o_k, d_k = M.Array3f(*(o[:, i] for i in range(3))), M.Array3f(*(d[:, i] for i in range(3)))
    res = composite(RayContext(dev, cfg, o_k, d_k, M.Float(np.zeros(len(rows))),
                               M.Float(t1), M.Bool(np.ones(len(rows), bool))),
                    M.Float(0.5), Shading(color_of, FlatLight()))
    C = np.stack([res.C.x.numpy(), res.C.y.numpy(), res.C.z.numpy()], axis=-1)
    for i, (oi, di) in enumerate(rows):
        C_ref, T_ref = quadrature(shapes, oi, di, t1[i], n=400_000)
        assert T_ref < 0.999     # the ray meets opacity in its first band
        np.testing.assert_allclose(C[i], C_ref, atol=MATCH, rtol=0, err_msg=f"ray {i}")
        assert res.T.numpy()[i] == pytest.approx(T_ref, abs=MATCH), i


def test02_a_steps_opacity_and_centroid_match_quadrature():
    """Random ramps (long and short, in and out of the support, both ways, thin to opaque) on
    a capped and an uncapped band: the opacity to 5e-5 and the light's error per unit of
    colour difference across the step, ``alpha |u_bar - u_ref|``, within
    :data:`~mi_amr.tolerances.CENTROID_ABS`; its 90th percentile a tenth of that."""
    rng = np.random.default_rng(7)
    for shape in (band.OpacityBand(width=0.01, support=(-0.02, 0.03), peak=1.2, dx0=0.5),
                  band.OpacityBand(width=0.01, peak=0.3, dx0=0.5)):
        n = 200
        a = rng.uniform(shape.lo * 1.3, shape.hi * 1.3, n)
        b = np.where(rng.random(n) < 0.3, a + rng.normal(0.0, 0.1 * shape.width, n),
                     rng.uniform(shape.lo * 1.3, shape.hi * 1.3, n))
        dx = shape.dx0 * np.exp(rng.uniform(np.log(0.01), np.log(5.0), n))
        ramp = band.Ramp(M.Float(a), M.Float(b), M.Float(dx))
        alpha, u = band.segment_alpha_and_centroid(M, shape.inputs(M), 0, ramp, M.Float(0.0))
        ref = np.array([shape.centroid_numpy(*q, n=100001) for q in zip(a, b, dx)])
        np.testing.assert_allclose(alpha.numpy(), ref[:, 0], atol=5e-5)
        err = np.abs(u.numpy() - ref[:, 1]) * ref[:, 0]
        assert err.max() < tol.CENTROID_ABS, err.max()
        assert np.quantile(err, 0.9) < 0.1 * tol.CENTROID_ABS


def saddle_cube():
    """One grid of 2^3 cells over the unit cube whose field ``f`` is ``u + v - 2 u v`` between
    the cell centres (``u``, ``v``: x and y from the first centre to the last, 0 to 1), so
    that along the diagonal ``u = v = s`` it rises to 0.5 at ``s = 1/2`` and falls back; the
    colour field ``c`` is ``x``."""
    u = np.array([0.0, 1.0])
    f = (u[:, None] + u[None, :] - 2.0 * u[:, None] * u[None, :])[:, :, None] * np.ones(2)
    c = np.broadcast_to(np.array([0.25, 0.75])[:, None, None], (2, 2, 2)).copy()
    return AMRVolume.from_grids([{"level": 0, "origin": (0.0, 0.0, 0.0), "spacing": 0.5,
                                  "fields": {"f": f, "c": c}}])


def test01c_a_piece_that_turns_inside_the_band_shades_both_of_its_sides():
    """A piece whose value rises into the band and falls back (two sub-pieces with opacity,
    the colour field different on each): its light equals that of the same ray cut at the
    turn into two rays, each composited on its own (``C1 + T1 C2``), where each side is
    shaded as a piece's first sub-piece. Giving the second sub-piece the first's colours
    fails it."""
    vol = saddle_cube()
    dev = PreparedVolume(vol, "f", "c", m=M).device
    shape = band.OpacityBand(width=0.03, peak=0.5, dx0=float(dev.min_h.numpy()[0]))
    cfg = MarchConfig(method="exact", basis=False, isovalues=opaque_floats(M, [0.45]),
                      step_scale=opaque_floats(M, [0.5]), num_iso=1,
                      band=band.band_inputs(M, [shape]), shading_extrema=False)
    o, d = M.Array3f(0.25, 0.25, 0.5), M.Array3f(0.5, 0.5, 0.0)
    # the whole diagonal of the cell between the centres, its half to the turn, the rest
    t0, t1 = M.Float([1e-4, 1e-4, 0.5]), M.Float([1.0 - 1e-4, 0.5, 1.0 - 1e-4])
    res = composite(RayContext(dev, cfg, M.Array3f(o), M.Array3f(d), t0, t1,
                               M.Bool([True] * 3)),
                    M.Float(0.5), Shading(lambda shares, value: M.Array3f(value, 1.0 - value, 0.0),
                                          FlatLight()))
    C = np.stack([res.C.x.numpy(), res.C.y.numpy()], axis=-1)
    T = res.T.numpy()
    # both sides lit, in colours (x : 1 - x) of their own
    assert T[1] < 0.97 and T[2] < 0.97
    assert C[2, 0] / C[2, 1] - C[1, 0] / C[1, 1] > 0.1, C
    np.testing.assert_allclose(C[0], C[1] + T[1] * C[2], atol=MATCH)
    assert T[0] == pytest.approx(T[1] * T[2], abs=MATCH)
