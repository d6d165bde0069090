"""The Dr.Jit reconstructions (``finest`` and the ``basis`` blend) against things they do not use:
a trilinear polynomial and an independent trilinear interpolator on one level, the NumPy slow
twins (a brute-force sum over every leaf cell; the finest grid found by testing every grid) on
3-level hierarchies with ratios 2 and 4, central finite differences for the analytic gradients,
and the point reconstruction for the per-piece cubics of ``segment_cubic``.

The kernels work in float32 and the twins in float64, so points are rounded to float32 before
either sees them and tolerances are a few float32 roundings of the value range.
"""

import drjit as dr
import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from mi_amr import AMRVolume
from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels.prepared import PreparedVolume
from mi_amr.core.field64 import basis_point_reference, finest_point_reference
from conftest import grid, random_grids, reference_grids, stretched

M = dr.llvm.ad


# ---------------------------------------------------------------------- helpers

def random_values(seed):
    """Cell values: independent normal samples (no structure a bug could hide behind)."""
    rng = np.random.default_rng(seed)
    return lambda centres: rng.normal(size=centres.shape[:-1])


HIERARCHIES = {
    "reference-2-2": lambda: reference_grids((2, 2), fn=random_values(1)),
    "reference-4-2": lambda: reference_grids((4, 2), fn=random_values(2)),
    "reference-2-4": lambda: reference_grids((2, 4), fn=random_values(3)),
    "random0-2-4": lambda: random_grids(0, ratios=(2, 4), fn=random_values(4)),
    "random1-4-2": lambda: random_grids(1, ratios=(4, 2), fn=random_values(5)),
    "random2-2-2": lambda: random_grids(2, ratios=(2, 2), fn=random_values(6)),
    "anisotropic-2-4": lambda: stretched(random_grids(0, ratios=(2, 4), fn=random_values(7))),
}


@pytest.fixture(scope="module", params=sorted(HIERARCHIES))
def hierarchy(request):
    """``(volume, device arrays)`` of one 3-level hierarchy with random cell values."""
    vol = AMRVolume.from_grids(HIERARCHIES[request.param]())
    assert vol.num_levels == 3
    return vol, PreparedVolume(vol, "f", m=M).device


def f32(a):
    """``a`` rounded to float32 (what the kernels see), as float64."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def array3(points):
    p = np.asarray(points, dtype=np.float32)
    return M.Array3f(*(M.Float(np.ascontiguousarray(p[:, a])) for a in range(3)))


def numpy3(v):
    return np.stack([v.x.numpy(), v.y.numpy(), v.z.numpy()], axis=1).astype(np.float64)


def evaluate(dev, basis, points):
    """Values and gradients of the Dr.Jit reconstruction at ``points`` (float64 arrays)."""
    arrays = dev.arrays(basis)
    active = dr.full(M.Bool, True, len(points))
    vals, grad = rec.reconstruct(dev, basis, array3(points), arrays, active)
    dr.eval(vals[0], grad)
    return vals[0].numpy().astype(np.float64), numpy3(grad)


def sample_points(vol, rng, n):
    """Random points in the volume's box, half of them within one coarse cell of a fine grid's
    faces (where levels meet), rounded to float32."""
    lo, hi = vol.bounds
    uniform = lo + rng.random((n // 2, 3)) * (hi - lo)
    glo, ghi = vol.grid_boxes()
    h = vol.spacings()
    fine = np.flatnonzero(vol.levels > 0)
    g = rng.choice(fine, n - n // 2)
    near = glo[g] + rng.random((len(g), 3)) * (ghi[g] - glo[g])
    axis = rng.integers(0, 3, len(g))
    side = np.where(rng.random(len(g)) < 0.5, glo[g, axis], ghi[g, axis])
    coarse = np.array([vol.level_spacing(vol.levels[i] - 1)[0] for i in g])
    near[np.arange(len(g)), axis] = side + (rng.random(len(g)) * 2 - 1) * coarse
    pts = np.clip(np.concatenate([uniform, near]), lo, hi)
    return f32(pts)


def dual_plane_distance(vol, points, levels=None):
    """World distance from each point to the nearest plane through cell centres of the given
    levels (all by default): where hat functions have kinks, so gradients jump."""
    levels = range(vol.num_levels) if levels is None else levels
    best = np.full(len(points), np.inf)
    for level in levels:
        h = vol.level_spacing(level)
        u = (points - vol.anchor) / h - 0.5
        best = np.minimum(best, (np.abs(u - np.round(u)) * h).min(axis=1))
    return best


def face_distance(vol, points):
    """World distance from each point to the nearest plane holding a face of some grid."""
    glo, ghi = vol.grid_boxes()
    planes = np.concatenate([glo, ghi])
    return np.min(np.abs(points[:, None, :] - planes[None, :, :]), axis=(1, 2))


def trilinear_polynomial(rng):
    """A random ``a + b x + c y + d z + e xy + f yz + g xz + k xyz`` and its gradient."""
    c = rng.normal(size=8)

    def value(p):
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        return (c[0] + c[1] * x + c[2] * y + c[3] * z + c[4] * x * y + c[5] * y * z
                + c[6] * x * z + c[7] * x * y * z)

    def gradient(p):
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        return np.stack([c[1] + c[4] * y + c[6] * z + c[7] * y * z,
                         c[2] + c[4] * x + c[5] * z + c[7] * x * z,
                         c[3] + c[5] * y + c[6] * x + c[7] * x * y], axis=-1)

    return value, gradient


# ---------------------------------------------------------------------- one level

def test01_basis_and_finest_reproduce_a_trilinear_polynomial_on_one_level():
    """Between the first and last cell centres both reconstructions are trilinear
    interpolation, which is exact for a trilinear polynomial (values and gradients)."""
    rng = np.random.default_rng(10)
    value, gradient = trilinear_polynomial(rng)
    h = 0.25
    vol = AMRVolume.from_grids([grid(0, (-1, 0, 0.5), (1, 1.5, 2), h, value)])
    dev = PreparedVolume(vol, "f", m=M).device
    pts = f32((-1 + h / 2, h / 2, 0.5 + h / 2)
              + rng.random((500, 3)) * (np.array([2, 1.5, 1.5]) - h))
    scale = np.abs(value(pts)).max()
    for basis in (True, False):
        v, g = evaluate(dev, basis, pts)
        np.testing.assert_allclose(v, value(pts), rtol=0, atol=2e-6 * scale)
        np.testing.assert_allclose(g, gradient(pts), rtol=0, atol=2e-5 * scale / h)


def test02_basis_on_one_level_is_clamped_trilinear_interpolation():
    """Random values on one grid: the basis blend equals SciPy's trilinear interpolation of
    the cell-centre values, extended as a constant in the outer half cells."""
    rng = np.random.default_rng(11)
    h = 0.5
    g = grid(0, (0, 0, 0), (3, 2.5, 4), h, random_values(12))
    vol = AMRVolume.from_grids([g])
    dev = PreparedVolume(vol, "f", m=M).device
    axes = vol.grids[0].cell_centers()
    interp = RegularGridInterpolator(axes, g["fields"]["f"], method="linear")
    pts = f32(rng.random((800, 3)) * np.array([3, 2.5, 4]))
    clamped = np.stack([np.clip(pts[:, a], axes[a][0], axes[a][-1]) for a in range(3)], axis=1)
    expected = interp(clamped)
    v, _ = evaluate(dev, True, pts)
    np.testing.assert_allclose(v, expected, rtol=0, atol=5e-6 * np.abs(expected).max())


# ---------------------------------------------------------------------- against the slow twins

def test03_basis_equals_the_brute_force_sum_over_leaf_cells(hierarchy):
    """Across level boundaries (3 levels, several grids, ratios 2 and 4) the blend over the kd
    leaf's grids equals the sum over every leaf cell of the volume; so do the gradients,
    away from the planes through cell centres where they jump."""
    vol, dev = hierarchy
    pts = sample_points(vol, np.random.default_rng(20), 300)
    v, g = evaluate(dev, True, pts)
    v_ref, g_ref = basis_point_reference(vol, pts, "f")
    assert np.all(np.isfinite(v_ref))
    scale = np.abs(v_ref).max()
    np.testing.assert_allclose(v, v_ref, rtol=0, atol=1e-5 * scale)
    smooth = dual_plane_distance(vol, pts) > 1e-4 * vol.spacings().min()
    assert smooth.sum() > 250
    h_min = vol.spacings().min()
    np.testing.assert_allclose(g[smooth], g_ref[smooth], rtol=0, atol=1e-4 * scale / h_min)


def test04_basis_skips_missing_cells_like_the_brute_force_sum():
    """NaN cells (allowed as missing data) get no weight, in the kernel as in the twin."""
    grids = reference_grids((2, 2), fn=random_values(7))
    rng = np.random.default_rng(21)
    for g in grids:
        arr = g["fields"]["f"]
        arr[rng.random(arr.shape) < 0.15] = np.nan
    vol = AMRVolume.from_grids(grids, allow_nonfinite=True)
    dev = PreparedVolume(vol, "f", m=M).device
    pts = sample_points(vol, rng, 300)
    v, _ = evaluate(dev, True, pts)
    v_ref, _ = basis_point_reference(vol, pts, "f")
    assert np.isfinite(v_ref).sum() > 250
    np.testing.assert_array_equal(np.isfinite(v), np.isfinite(v_ref))
    ok = np.isfinite(v_ref)
    np.testing.assert_allclose(v[ok], v_ref[ok], rtol=0, atol=1e-5 * np.abs(v_ref[ok]).max())


def test05_finest_equals_its_slow_twin(hierarchy):
    """Trilinear in the finest grid holding the point (clamped in its outer half cells):
    values and gradients equal the twin's, away from grid faces (where the owner changes)."""
    vol, dev = hierarchy
    pts = sample_points(vol, np.random.default_rng(22), 300)
    pts = pts[face_distance(vol, pts) > 1e-4 * vol.spacings().min()]
    v, g = evaluate(dev, False, pts)
    v_ref, g_ref = finest_point_reference(vol, pts, "f")
    scale = np.abs(v_ref).max()
    np.testing.assert_allclose(v, v_ref, rtol=0, atol=1e-5 * scale)
    smooth = dual_plane_distance(vol, pts) > 1e-4 * vol.spacings().min()
    h_min = vol.spacings().min()
    np.testing.assert_allclose(g[smooth], g_ref[smooth], rtol=0, atol=1e-4 * scale / h_min)


# ---------------------------------------------------------------------- gradients

def finite_differences(dev, basis, pts, eps):
    """Central differences of the Dr.Jit reconstruction, divided by the float32 distance of
    the two points actually evaluated (so rounding of ``p +- eps`` does not count)."""
    out = np.zeros_like(pts)
    for a in range(3):
        step = np.zeros(3)
        step[a] = eps
        hi, lo = f32(pts + step), f32(pts - step)
        v_hi, _ = evaluate(dev, basis, hi)
        v_lo, _ = evaluate(dev, basis, lo)
        out[:, a] = (v_hi - v_lo) / (hi[:, a] - lo[:, a])
    return out


@pytest.mark.parametrize("basis", [True, False], ids=["basis", "finest"])
def test06_analytic_gradient_equals_central_differences(hierarchy, basis):
    """The analytic gradient (quotient rule for the blend, trilinear derivative for finest)
    equals central differences of the value, at points whose difference stencil crosses no
    plane through cell centres (kinks) and, for finest, no grid face (jumps)."""
    vol, dev = hierarchy
    h_min = vol.spacings().min()
    eps = 1e-2 * h_min
    pts = sample_points(vol, np.random.default_rng(23), 400)
    lo, hi = vol.bounds
    keep = (dual_plane_distance(vol, pts) > 2 * eps) & np.all((pts - eps > lo) & (pts + eps < hi),
                                                              axis=1)
    if not basis:
        keep &= face_distance(vol, pts) > 2 * eps
    pts = pts[keep]
    assert len(pts) > 100
    _, g = evaluate(dev, basis, pts)
    fd = finite_differences(dev, basis, pts, eps)
    scale = np.abs(g).max()
    np.testing.assert_allclose(g, fd, rtol=0, atol=2e-3 * scale)


# ---------------------------------------------------------------------- cubics along a ray

def piece_around(vol, tree, points, dirs):
    """For rays ``p + t d`` the interval ``(t_lo, t_hi)`` around ``t = 0`` that crosses no plane
    through cell centres (any level), no grid face and no face of the kd leaf holding ``p``:
    one piece on which the reconstruction is a ratio of two fixed cubics."""
    planes = []
    for level in range(vol.num_levels):
        h = vol.level_spacing(level)
        u = (points - vol.anchor) / h - 0.5
        for k in (np.floor(u) - 1, np.floor(u), np.floor(u) + 1, np.floor(u) + 2):
            planes.append(vol.anchor + (k + 0.5) * h)
    glo, ghi = vol.grid_boxes()
    leaf = tree.locate(points)
    t_lo = np.full(len(points), -np.inf)
    t_hi = np.full(len(points), np.inf)
    candidates = planes + [tree.leaf_lo[leaf], tree.leaf_hi[leaf]]
    candidates += [np.broadcast_to(b, points.shape) for b in np.concatenate([glo, ghi])]
    for plane in candidates:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (plane - points) / dirs
        t = np.where(np.isfinite(t), t, np.nan)
        t_hi = np.fmin(t_hi, np.nanmin(np.where(t > 0, t, np.nan), axis=1, initial=np.inf))
        t_lo = np.fmax(t_lo, np.nanmax(np.where(t < 0, t, np.nan), axis=1, initial=-np.inf))
    return t_lo, t_hi


def horner(c, s):
    return ((c[3] * s + c[2]) * s + c[1]) * s + c[0]


def pieces(vol, dev, basis, n=300, seed=24):
    """Random pieces inside the volume (rays around random points, cut to the piece around
    each, :func:`piece_around`, less a margin) and their cubics: ``(p0, dirs, length, seg,
    nums, den)`` (float64 NumPy values of what the kernels got; ``seg`` and the cubics are
    the kernels' own)."""
    rng = np.random.default_rng(seed)
    h_min = vol.spacings().min()
    lo, hi = vol.bounds
    mids = f32(lo + 0.02 + rng.random((n, 3)) * (hi - lo - 0.04))
    dirs = rng.normal(size=(n, 3))
    dirs = f32(dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    t_lo, t_hi = piece_around(vol, dev.tree, mids, dirs)
    margin = 1e-3 * (t_hi - t_lo)
    # Grid faces bound every piece, so a piece around an inner point stays in the volume.
    keep = np.isfinite(t_lo) & np.isfinite(t_hi) & (t_hi - t_lo > 0.05 * h_min)
    mids, dirs, t_lo, t_hi, margin = mids[keep], dirs[keep], t_lo[keep], t_hi[keep], margin[keep]
    assert len(mids) > 100
    p0 = f32(mids + (t_lo + margin)[:, None] * dirs)
    length = f32(t_hi - t_lo - 2 * margin)

    active = dr.full(M.Bool, True, len(p0))
    leaf = rec.locate(dev, array3(mids), active)
    seg = rec.Segment(leaf=leaf, p0=array3(p0), d=array3(dirs),
                      s_mid=M.Float(0.5 * length.astype(np.float32)))
    nums, den = rec.segment_cubic(dev, basis, seg, dev.arrays(basis), active)
    dr.eval(nums, den)
    return p0, dirs, length, seg, nums, den


FRACTIONS = np.array([0.0, 0.1, 0.35, 0.5, 0.8, 1.0])     # points of a piece checked


@pytest.mark.parametrize("basis", [True, False], ids=["basis", "finest"])
def test07_segment_cubic_equals_the_point_reconstruction_inside_one_piece(hierarchy, basis):
    """``N(s) / D(s)`` from :func:`segment_cubic` equals the Dr.Jit point reconstruction and
    the slow twin at points along the ray inside one piece."""
    vol, dev = hierarchy
    p0, dirs, length, _, nums, den = pieces(vol, dev, basis)
    n = [c.numpy().astype(np.float64) for c in nums[0]]
    d = [c.numpy().astype(np.float64) for c in den]
    s = length[:, None] * FRACTIONS[None, :]
    cubic_value = horner(n, s.T).T / horner(d, s.T).T
    pts = (p0[:, None, :] + s[:, :, None] * dirs[:, None, :]).reshape(-1, 3)
    kernel, _ = evaluate(dev, basis, pts)
    twin = basis_point_reference if basis else finest_point_reference
    slow, _ = twin(vol, pts, "f")
    scale = np.abs(slow).max()
    np.testing.assert_allclose(cubic_value.ravel(), kernel, rtol=0, atol=2e-5 * scale)
    np.testing.assert_allclose(cubic_value.ravel(), slow, rtol=0, atol=2e-5 * scale)


@pytest.mark.parametrize("basis", [True, False], ids=["basis", "finest"])
def test07b_segment_gradient_equals_the_point_gradient_inside_one_piece(hierarchy, basis):
    """The gradient along a piece from its cells read once (:func:`segment_gradient`, the
    quotient rule on quadratics of the sums' gradients and the piece's cubics) equals the point
    reconstruction's analytic gradient and the float64 twin's, at points of the piece,
    its ends included."""
    vol, dev = hierarchy
    p0, dirs, length, seg, nums, den = pieces(vol, dev, basis)
    active = dr.full(M.Bool, True, len(p0))
    quadratics = rec.segment_gradient(dev, basis, seg, dev.arrays(basis), active)
    got = []
    for f in FRACTIONS:
        g = quadratics.at(M.Float(np.float32(f) * length.astype(np.float32)), nums[0], den)
        dr.eval(g)
        got.append(numpy3(g))
    got = np.stack(got, axis=1).reshape(-1, 3)
    s = length[:, None] * FRACTIONS[None, :]
    pts = (p0[:, None, :] + s[:, :, None] * dirs[:, None, :]).reshape(-1, 3)
    _, kernel = evaluate(dev, basis, pts)
    twin = basis_point_reference if basis else finest_point_reference
    _, slow = twin(vol, pts, "f")
    scale = np.abs(slow).max()
    assert scale > 0
    np.testing.assert_allclose(got, kernel, rtol=0, atol=1e-4 * scale)
    np.testing.assert_allclose(got, slow, rtol=0, atol=1e-4 * scale)


@pytest.mark.parametrize("basis", [True, False], ids=["basis", "finest"])
def test07c_shading_read_gives_the_colour_cubic_of_the_whole_read(hierarchy, basis):
    """Where a volume march reads the colour field only for the pieces it shades
    (:func:`segment_shading`: the gradient's cells read once for the field's gradient and the
    colour's cubic), the colour's cubic numerator is the one :func:`segment_cubic` gives when
    it reads both fields for every piece (its slow twin), and the gradient is
    :func:`segment_gradient`'s."""
    vol, _ = hierarchy
    vol = vol.with_fields({"c": [np.cos(3.0 * g.fields["f"]) for g in vol.grids]})
    dev = PreparedVolume(vol, "f", "c", m=M).device
    arrays = dev.arrays(basis, color=True)
    assert arrays[1] is not arrays[0]
    p0, dirs, length, seg, _, _ = pieces(vol, dev, basis)
    active = dr.full(M.Bool, True, len(p0))
    nums, den = rec.segment_cubic(dev, basis, seg, arrays, active)
    gradient, cnum = rec.segment_shading(dev, basis, seg, arrays, active)
    alone = rec.segment_gradient(dev, basis, seg, arrays, active)
    dr.eval(nums, den, cnum, gradient.gn, gradient.gd, alone.gn, alone.gd)
    want = np.stack([c.numpy() for c in nums[1]])
    scale = np.abs(want).max()
    assert scale > 0 and not np.allclose(want, np.stack([c.numpy() for c in nums[0]]))
    np.testing.assert_allclose(np.stack([c.numpy() for c in cnum]), want, rtol=0,
                               atol=1e-6 * scale)
    for got, ref in ((gradient.gn, alone.gn), (gradient.gd, alone.gd)):
        np.testing.assert_array_equal(np.array([[c.numpy() for c in q] for q in got]),
                                      np.array([[c.numpy() for c in q] for q in ref]))


@pytest.mark.parametrize("dense", [True, False])
@pytest.mark.parametrize("hierarchy", sorted(HIERARCHIES))
def test08_brick_pools_equal_their_slow_twin(hierarchy, dense):
    """The device pull of leaf cells into bricks (each slot finds its cell's grid through the
    level's dense block table, or ``dense=False`` a binary search of its sorted blocks) builds
    the same tables and pools as the grid-by-grid, brick-by-brick slow twin, NaN for covered,
    missing and apron cells included, with two fields."""
    from mi_amr.core import levels
    from mi_amr.kernels import bricks

    grids = HIERARCHIES[hierarchy]()
    for g in grids:
        f = g["fields"]["f"]
        g["fields"]["c"] = np.where(f > 1.5, np.nan, np.cos(f))
    vol = AMRVolume.from_grids(grids, allow_nonfinite=True)
    if not dense:
        vol.level_caches.dense_blocks = 0       # before any level's table is made
    first = 3
    for level in range(vol.num_levels):
        assert (levels.level_index(vol, level).table is not None) == dense
        fast = bricks.level_bricks(vol, level, ["f", "c"], first)
        slow = bricks.level_bricks_reference(vol, level, ["f", "c"], first)
        for a, b in zip(fast[:3], slow[:3]):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(fast[3], slow[3]):
            np.testing.assert_array_equal(a, b)
            assert np.isnan(a).any() and np.isfinite(a).any()
        first += len(fast[3][0]) // bricks.BRICK_N ** 3


@pytest.mark.parametrize("hierarchy", sorted(HIERARCHIES))
def test08b_device_volume_pools_leave_no_slot_unwritten(hierarchy):
    """:func:`bricks.build_pools` allocates its pools unset and fills every slot: all levels'
    pools are the slow twin's, level after level, though the memory they get was last filled
    with a value no brick holds."""
    import drjit as dr

    from mi_amr.core.kdtree import KDTree
    from mi_amr.kernels import bricks
    from mi_amr.kernels.device import DeviceVolume

    grids = HIERARCHIES[hierarchy]()
    for g in grids:
        g["fields"]["c"] = np.cos(g["fields"]["f"])
    vol = AMRVolume.from_grids(grids)
    slow, first = [], 0
    for level in range(vol.num_levels):
        part = bricks.level_bricks_reference(vol, level, ["f", "c"], first)
        slow.append(part[3])
        first += len(part[3][0]) // bricks.BRICK_N ** 3
    want = [np.concatenate([p[k] for p in slow]).ravel() for k in range(2)]
    for _ in range(2):      # memory recycled from an array of a sentinel value, freed
        dr.eval(dr.full(dr.llvm.ad.Float, 12345.0, len(want[0])))
    device = DeviceVolume(vol, KDTree(vol), "f", "c")
    got = [np.asarray(p.numpy()) for p in device.host_bricks[1]]
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)
