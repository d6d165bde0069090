"""Derived fields across levels: speed, Q-criterion and vorticity magnitude of velocity fields
whose values are known in closed form.

Why linear fields are exact: a central difference of a linear function is exact, so is the
second-order one-sided difference used at the domain's edge, and trilinear interpolation (used
for ghost cells taken from a coarser level) reproduces linear functions. So for v = A x + b
every cell, on every level, must give grad v = A to rounding.
"""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import mi_amr
from mi_amr import AMRError, AMRVolume
from mi_amr.core.derive import DERIVED_FIELDS, velocity_gradient
from conftest import random_grids

# Level-0 cells of 0.5 over [0, 8] x [0, 4] x [0, 4] in two grids sharing x = 4. Level-1 grids:
# one spanning that face, one in the domain corner at the origin, one in the opposite corner.
# Level-2 grids: one inside the first (away from every edge), one in each domain corner.
DERIVE_BOXES = [
    [((0, 0, 0), (4, 4, 4)), ((4, 0, 0), (8, 4, 4))],
    [((2, 1, 1), (6, 3, 3)), ((0, 0, 0), (2, 2, 2)), ((6, 2, 2), (8, 4, 4))],
    [((3, 1.5, 1.5), (4, 2.5, 2.5)), ((0, 0, 0), (1, 1, 1)), ((7, 3, 3), (8, 4, 4))],
]
H0 = 0.5


def velocity_grid(level, lo, hi, h, velocity, names=("vx", "vy", "vz"), dtype=np.float64):
    """A grid record over the world box ``[lo, hi]`` with ``velocity(centres) -> (..., 3)``
    sampled at its cell centres."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    axes = [lo[a] + (np.arange(round((hi[a] - lo[a]) / h)) + 0.5) * h for a in range(3)]
    v = velocity(np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1))
    return {"level": level, "origin": tuple(lo), "spacing": h,
            "fields": {n: v[..., c].astype(dtype) for c, n in enumerate(names)}}


def velocity_volume(velocity, ratios=(2, 2), names=("vx", "vy", "vz"), dtype=np.float64,
                    num_levels=3):
    """The hierarchy above with ``velocity`` sampled at cell centres."""
    h = [H0, H0 / ratios[0], H0 / (ratios[0] * ratios[1])]
    return AMRVolume.from_grids([velocity_grid(level, lo, hi, h[level], velocity, names, dtype)
                                 for level in range(num_levels)
                                 for lo, hi in DERIVE_BOXES[level]])


def centres_of(g):
    return np.stack(np.meshgrid(*g.cell_centers(), indexing="ij"), axis=-1)


def q_exact(grad):
    """Q = -tr(grad^2) / 2 for ``grad[..., i, j] = d v_i / d x_j``."""
    return -0.5 * np.einsum("...ij,...ji->...", grad, grad)


def vorticity_exact(grad):
    w = np.stack([grad[..., 2, 1] - grad[..., 1, 2], grad[..., 0, 2] - grad[..., 2, 0],
                  grad[..., 1, 0] - grad[..., 0, 1]], axis=-1)
    return np.linalg.norm(w, axis=-1)


RNG = np.random.default_rng(42)
A = RNG.normal(size=(3, 3))
B = RNG.normal(size=3)


def linear(p):
    return p @ A.T + B


# ---------------------------------------------------------------------- linear fields: exact

@pytest.mark.parametrize("ratios", [(2, 2), (4, 2), (2, 4)])
def test01_q_of_a_linear_field_is_exact_on_every_level(ratios):
    vol = mi_amr.derive(velocity_volume(linear, ratios), "q_criterion", "vorticity_magnitude")
    q = -0.5 * np.trace(A @ A)
    w = vorticity_exact(A)
    assert abs(q) > 0.1 and w > 0.1
    for i, g in enumerate(vol.grids):
        np.testing.assert_allclose(g.fields["q_criterion"], q, rtol=0, atol=1e-12,
                                   err_msg=f"grid {i} (level {g.level})")
        np.testing.assert_allclose(g.fields["vorticity_magnitude"], w, rtol=0, atol=1e-12,
                                   err_msg=f"grid {i} (level {g.level})")


def test02_velocity_gradient_of_a_linear_field_is_a_everywhere():
    vol = velocity_volume(linear)
    grads = velocity_gradient(vol, ("vx", "vy", "vz"))
    for i, (g, grad) in enumerate(zip(vol.grids, grads)):
        assert grad.shape == (3, 3) + g.shape
        np.testing.assert_allclose(np.moveaxis(grad, (0, 1), (-2, -1)),
                                   np.broadcast_to(A, g.shape + (3, 3)), rtol=0, atol=1e-12,
                                   err_msg=f"grid {i} (level {g.level})")


def test03_solid_body_rotation_about_z():
    omega, centre = 0.7, np.array([4.1, 1.9, 0.0])

    def rotation(p):
        d = p - centre
        return omega * np.stack([-d[..., 1], d[..., 0], np.zeros(d.shape[:-1])], axis=-1)

    vol = mi_amr.derive(velocity_volume(rotation), "q_criterion", "vorticity_magnitude", "speed")
    for g in vol.grids:
        np.testing.assert_allclose(g.fields["q_criterion"], omega ** 2, rtol=0, atol=1e-12)
        np.testing.assert_allclose(g.fields["vorticity_magnitude"], 2 * omega, rtol=0, atol=1e-12)
        rho = np.linalg.norm((centres_of(g) - centre)[..., :2], axis=-1)
        np.testing.assert_allclose(g.fields["speed"], omega * rho, rtol=1e-12, atol=1e-14)


def test04_pure_strain_has_negative_q_and_no_vorticity():
    # v = (x, -y, 0) about (4, 2, 2): Q = -(1 + 1) / 2 = -1, curl v = 0.
    vol = mi_amr.derive(velocity_volume(lambda p: (p - [4, 2, 2]) * [1, -1, 0]),
                        "q_criterion", "vorticity_magnitude")
    for g in vol.grids:
        np.testing.assert_allclose(g.fields["q_criterion"], -1.0, rtol=0, atol=1e-12)
        np.testing.assert_allclose(g.fields["vorticity_magnitude"], 0.0, rtol=0, atol=1e-12)


def test05_speed_is_the_norm_of_the_stored_velocity():
    vol = velocity_volume(linear, dtype=np.float32)
    out = mi_amr.derive(vol, "speed")
    for g, h in zip(vol.grids, out.grids):
        v = np.stack([g.fields[n] for n in ("vx", "vy", "vz")], axis=-1)
        assert h.fields["speed"].dtype == np.float32
        np.testing.assert_array_equal(h.fields["speed"], np.sqrt((v * v).sum(axis=-1)))


def test06_one_sided_differences_at_the_domain_edge_are_exact_for_linear_fields():
    # One level only: every grid face on the domain's edge uses the one-sided difference.
    vol = mi_amr.derive(velocity_volume(linear, num_levels=1), "q_criterion")
    for g in vol.grids:
        np.testing.assert_allclose(g.fields["q_criterion"], -0.5 * np.trace(A @ A),
                                   rtol=0, atol=1e-12)
    # Grids only 2 cells thick along an axis take a first-order difference there: still exact.
    thin = AMRVolume.from_grids([velocity_grid(0, (0, 0, 0), (1, 2, 2), 0.5, linear)])
    q = mi_amr.derive(thin, "q_criterion").grids[0].fields["q_criterion"]
    np.testing.assert_allclose(q, -0.5 * np.trace(A @ A), rtol=0, atol=1e-12)
    # A grid one cell thick on the domain's edge differences towards its neighbour grid.
    for lo, hi in (((0, 0, 0), (0.5, 2, 2)), ((1.5, 0, 0), (2, 2, 2))):
        slab = AMRVolume.from_grids([velocity_grid(0, lo, hi, 0.5, linear),
                                     velocity_grid(0, (0.5, 0, 0), (1.5, 2, 2), 0.5, linear)])
        for g in mi_amr.derive(slab, "q_criterion").grids:
            np.testing.assert_allclose(g.fields["q_criterion"], -0.5 * np.trace(A @ A),
                                       rtol=0, atol=1e-12)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), ratios=st.sampled_from([(2, 2), (2, 4), (4, 2), (4, 4)]))
def test07_linear_fields_are_exact_on_random_hierarchies(seed, ratios):
    """Random grids (level-0 slabs down to one cell thick, fine grids touching each other and
    the domain's edge anywhere): grad v = A in every cell."""
    grids = random_grids(seed, ratios=ratios)
    for g in grids:
        lo = np.array(g["origin"])
        hi = lo + np.array(g["fields"]["f"].shape) * g["spacing"]
        g["fields"] = velocity_grid(g["level"], lo, hi, g["spacing"], linear)["fields"]
    vol = AMRVolume.from_grids(grids)
    for i, (g, grad) in enumerate(zip(vol.grids, velocity_gradient(vol, ("vx", "vy", "vz")))):
        np.testing.assert_allclose(np.moveaxis(grad, (0, 1), (-2, -1)),
                                   np.broadcast_to(A, g.shape + (3, 3)), rtol=0, atol=1e-11,
                                   err_msg=f"grid {i} (level {g.level}, origin {g.origin})")


# ---------------------------------------------------------------------- quadratic fields

# v_i = A x + x^T C_i x / 2 (x relative to the domain centre): grad v_i = A_i + C_i x.
C = RNG.normal(size=(3, 3, 3)) * 0.05
C = 0.5 * (C + np.swapaxes(C, 1, 2))
CENTRE = np.array([4.0, 2.0, 2.0])


def quadratic(p):
    x = p - CENTRE
    return x @ A.T + 0.5 * np.einsum("...j,ijk,...k->...i", x, C, x)


def quadratic_grad(p):
    return A + np.einsum("ijk,...k->...ij", C, p - CENTRE)


def quadratic_q_tolerance(level, grad, ratios=(2, 2)):
    """A bound on the Q error of level-``level`` cells whose exact gradient is ``grad``
    (``(..., 3, 3)``), from ghost cells interpolated from coarser levels.

    Trilinear interpolation of a quadratic is off by at most h^2/8 * sum_a |d^2 v_i / dx_a^2|
    per level it passes through (a level-2 ghost may come from a level-1 value that was itself
    interpolated from level 0); the central difference divides that by 2 h_level. With every
    gradient entry off by at most dG, Q = -sum_ij G_ij G_ji / 2 is off by at most
    sum_ij |G_ji| dG + 9 dG^2 / 2. Level 0 takes no interpolated ghost: exact up to rounding.
    """
    curv = np.abs(np.einsum("ikk->ik", C)).sum(axis=1).max()
    h = [H0, H0 / ratios[0], H0 / (ratios[0] * ratios[1])]
    dG = sum(hc ** 2 for hc in h[:level]) / 8 * curv / (2 * h[level])
    return np.abs(grad).sum(axis=(-2, -1)) * dG + 4.5 * dG ** 2 + 1e-10


def test08_quadratic_field_is_exact_away_from_level_edges_and_close_near_them():
    vol = mi_amr.derive(velocity_volume(quadratic), "q_criterion")
    for i, g in enumerate(vol.grids):
        centres = centres_of(g)
        grad = quadratic_grad(centres)
        want = q_exact(grad)
        got = g.fields["q_criterion"]
        tol = quadratic_q_tolerance(g.level, grad)
        assert np.all(tol < 0.2 * np.abs(want).max())
        assert np.all(np.abs(got - want) <= tol), f"grid {i}"
        # Cells whose neighbours along all axes lie in the same grid or beyond the domain's edge
        # need no interpolated ghost: central and one-sided differences of a quadratic are exact.
        h = np.asarray(g.spacing)
        inner = np.all((centres - h > g.lo) | (np.isclose(g.lo, 0)), axis=-1) & \
            np.all((centres + h < g.hi) | (np.isclose(g.hi, [8, 4, 4])), axis=-1)
        assert inner.any()
        np.testing.assert_allclose(got[inner], want[inner], rtol=0, atol=1e-10,
                                   err_msg=f"grid {i}")


def test09_q_is_continuous_across_a_level_boundary():
    """Along x through the level-1 grid spanning x in [2, 6], the derived Q of the last coarse
    cell and the first fine cell differ as the exact Q at their centres does."""
    vol = mi_amr.derive(velocity_volume(quadratic, num_levels=2), "q_criterion")
    coarse, fine = vol.grids[0], vol.grids[2]        # level 0 [0, 4]^3; level 1 from x = 2
    for j, k in ((2, 2), (3, 5), (0, 7)):           # fine-cell rows in y, z
        yc, zc = fine.cell_centers()[1][j], fine.cell_centers()[2][k]
        # The coarse cell left of x = 2 holding (yc, zc), and the fine cell right of it.
        ci, cj, ck = 3, int(yc // H0), int(zc // H0)
        q_c = coarse.fields["q_criterion"][ci, cj, ck]
        q_f = fine.fields["q_criterion"][0, j, k]
        grad_c = quadratic_grad(np.array([1.75, (cj + 0.5) * H0, (ck + 0.5) * H0]))
        grad_f = quadratic_grad(np.array([2.125, yc, zc]))
        tol = quadratic_q_tolerance(0, grad_c) + quadratic_q_tolerance(1, grad_f)
        assert abs((q_f - q_c) - (q_exact(grad_f) - q_exact(grad_c))) <= tol
    # And the coarse cell under the fine grid's corner (x, y, z in [2, 2.5] x [1, 1.5]^2)
    # agrees with the 8 fine cells it holds.
    under = coarse.fields["q_criterion"][4, 2, 2]
    fine_q = fine.fields["q_criterion"][0:2, 0:2, 0:2]
    grad_f = quadratic_grad(centres_of(fine)[0:2, 0:2, 0:2])
    exact_under = q_exact(quadratic_grad(np.array([2.25, 1.25, 1.25])))
    assert abs((under - fine_q.mean()) - (exact_under - q_exact(grad_f).mean())) <= \
        quadratic_q_tolerance(1, grad_f).max()


# ---------------------------------------------------------------------- names and errors

def test10_unknown_derived_field_is_refused():
    vol = velocity_volume(linear, num_levels=1)
    with pytest.raises(AMRError, match=r"cannot derive \['helicity'\]; derived fields are " +
                       r"\['speed', 'q_criterion', 'vorticity_magnitude'\]"):
        mi_amr.derive(vol, "speed", "helicity")
    assert DERIVED_FIELDS == ("speed", "q_criterion", "vorticity_magnitude")


def test11_missing_velocity_components_are_refused():
    vol = velocity_volume(linear, num_levels=1, names=("vx", "vy", "density"))
    with pytest.raises(AMRError, match=r"no velocity components found .*vx/vy/vz.*"
                       r"available fields: \['vx', 'vy', 'density'\]"):
        mi_amr.derive(vol, "q_criterion")
    with pytest.raises(AMRError, match=r"velocity must name 3 fields of the volume, got "
                       r"\('vx', 'vy', 'vw'\)"):
        mi_amr.derive(vol, "speed", velocity=("vx", "vy", "vw"))
    with pytest.raises(AMRError, match="velocity must name 3 fields"):
        mi_amr.derive(vol, "speed", velocity=("vx", "vy"))


@pytest.mark.parametrize("names", [("vx", "vy", "vz"), ("x_velocity", "y_velocity", "z_velocity"),
                                   ("velocity_x", "velocity_y", "velocity_z"), ("u", "v", "w")])
def test12_velocity_names_are_detected(names):
    vol = mi_amr.derive(velocity_volume(linear, names=names, num_levels=2), "q_criterion")
    assert vol.field_names == names + ("q_criterion",)
    for g in vol.grids:
        np.testing.assert_allclose(g.fields["q_criterion"], -0.5 * np.trace(A @ A),
                                   rtol=0, atol=1e-12)


def test13_explicit_velocity_names_and_shared_fields():
    vol = velocity_volume(linear, names=("a", "b", "c"), num_levels=2, dtype=np.float32)
    out = mi_amr.derive(vol, "q_criterion", "speed", velocity=("a", "b", "c"))
    assert out.field_names[:3] == ("a", "b", "c")
    assert set(out.field_names[3:]) == {"q_criterion", "speed"}
    for g, h in zip(vol.grids, out.grids):
        assert h.fields["a"] is g.fields["a"]
        assert h.fields["q_criterion"].dtype == np.float32
        np.testing.assert_allclose(h.fields["q_criterion"], -0.5 * np.trace(A @ A), atol=1e-4)
    # The input volume is unchanged.
    assert vol.field_names == ("a", "b", "c")


def test30_cell_values_match_their_slow_twin():
    """One gather per field across a level's grids gives what the grid-by-grid lookup gives,
    including cells no grid of the level holds (NaN, not found)."""
    from conftest import random_grids
    from mi_amr import AMRVolume
    from mi_amr.core import levels

    vol = AMRVolume.from_grids(random_grids(5, fn=lambda p: p[..., 0] * 3 + p[..., 1]))
    rng = np.random.default_rng(1)
    for level in range(vol.num_levels):
        lo, hi = vol.index_boxes()
        sel = vol.levels == level
        idx = rng.integers(lo[sel].min(axis=0) - 2, hi[sel].max(axis=0) + 2, size=(500, 3))
        a, fa = levels.cell_values(vol, level, idx, ["f"])
        b, fb = levels.cell_values_reference(vol, level, idx, ["f"])
        np.testing.assert_array_equal(fa, fb)
        np.testing.assert_array_equal(a, b)
        assert fa.any() and not fa.all()


def test31_level_index_dense_table_and_binary_search_agree():
    """LevelIndex.find by its dense block table and by the sorted keys (the fallback for
    huge levels) give the same grids, -1 outside."""
    from conftest import random_grids
    from mi_amr import AMRVolume
    from mi_amr.core.levels import LevelIndex

    vol = AMRVolume.from_grids(random_grids(7))
    rng = np.random.default_rng(2)
    for level in range(vol.num_levels):
        dense = LevelIndex(vol, level)
        assert dense.table is not None
        sparse = LevelIndex(vol, level)
        sparse.table = None
        lo, hi = vol.index_boxes()
        idx = rng.integers(lo.min(axis=0) - 3, hi.max(axis=0) * 4 + 3, size=(2000, 3))
        np.testing.assert_array_equal(dense.find(idx), sparse.find(idx))


@pytest.mark.parametrize("complete", [False, True])
def test32_interpolation_matches_its_slow_twin(complete):
    """Sharing the 8 cells of a base cell among points gives, bit for bit, what interpolating
    point by point gives, for points inside, at the edge of and outside the domain."""
    from mi_amr.core import levels

    vol = AMRVolume.from_grids(random_grids(3, ratios=(2, 4),
                                            fn=lambda p: np.sin(3 * p[..., 0]) * p[..., 1]))
    lo, hi = vol.bounds
    rng = np.random.default_rng(4)
    points = rng.uniform(lo - 1.6, hi + 1.6, size=(100, 3))
    points[:40] = np.round(points[:40] * 4) / 4        # many points sharing base cells
    for level in range(vol.num_levels):
        fast = levels.interpolate(vol, level, points, ["f"], complete=complete)
        slow = levels.interpolate_reference(vol, level, points, ["f"], complete=complete)
        np.testing.assert_array_equal(fast, slow)
        assert np.isfinite(fast).any() and np.isnan(fast).any()


def _velocity_hierarchy(seed, ratios, dtype, holes):
    """A random hierarchy with a smooth non-linear velocity (``dtype``); ``holes`` puts NaN
    (missing data) into a few cells."""
    grids = random_grids(seed, ratios=ratios, fn=lambda p: np.sin(p[..., 0] * 3) * p[..., 1])
    rng = np.random.default_rng(seed)
    for g in grids:
        f = g["fields"].pop("f")
        v = {"vx": f, "vy": f * f + g["origin"][2], "vz": np.cos(f)}
        if holes:
            v["vy"].ravel()[rng.integers(0, f.size, max(1, f.size // 20))] = np.nan
        g["fields"].update({n: a.astype(dtype) for n, a in v.items()})
    return AMRVolume.from_grids(grids, allow_nonfinite=holes)


@pytest.mark.parametrize("seed,ratios,dtype,holes", [(0, (2, 2), np.float64, False),
                                                     (1, (4, 2), np.float32, False),
                                                     (2, (2, 4), np.float64, True),
                                                     (5, (2, 2), np.float32, True)])
def test33_whole_level_gradients_match_the_grid_by_grid_twin(seed, ratios, dtype, holes):
    """The level-wide gradient (index arithmetic, one ghost pass per chunk, here chunks of a
    few grids) equals the grid-by-grid twin (padded grids, array slices) bit for bit, one-sided
    and one- or two-cell-thick cases included; so do the derived fields."""
    from mi_amr.core import derive as derive_mod, gradient, levels

    chunk = 40
    vol = _velocity_hierarchy(seed, ratios, dtype, holes)
    chunks = [list(levels.grid_chunks(levels.level_index(vol, level), chunk))
              for level in range(vol.num_levels)]
    assert all(len(c) > 1 for c in chunks) and any(b - a > 1 for c in chunks for a, b in c)
    comps = ("vx", "vy", "vz")
    thin = [g for g in vol.grids if min(g.shape) <= 2]
    assert thin and len({n for g in vol.grids for n in g.shape}) > 2
    fast = derive_mod.velocity_gradient(vol, comps, chunk_cells=chunk)
    slow = list(gradient.grid_gradients_reference(vol, comps))
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(a, b)
    out = mi_amr.derive(vol, "q_criterion", "vorticity_magnitude", "speed", chunk_cells=chunk)
    for g, h, grad in zip(vol.grids, out.grids, slow):
        np.testing.assert_array_equal(h.fields["q_criterion"],
                                      derive_mod.q_criterion(grad).astype(dtype))
        np.testing.assert_array_equal(h.fields["vorticity_magnitude"],
                                      derive_mod.vorticity_magnitude(grad).astype(dtype))
        vx, vy, vz = (g.fields[n] for n in comps)
        np.testing.assert_array_equal(h.fields["speed"], np.sqrt(vx * vx + vy * vy + vz * vz))
        assert h.fields["q_criterion"].dtype == dtype


def test34_the_thread_map_keeps_order_and_bounds_what_is_in_flight():
    """parallel.map_ordered yields in order with any number of threads, and never has more than
    two items a thread started and not yet handed back."""
    import threading

    from mi_amr.core import parallel

    started, lock = [], threading.Lock()

    def work(i):
        with lock:
            started.append(i)
        return i * i

    for threads in (1, 2, 3):
        started.clear()
        out = []
        for x in parallel.map_ordered(work, range(50), threads):
            out.append(x)
            assert len(started) <= len(out) + 2 * threads
        assert out == [i * i for i in range(50)]
    assert 1 <= parallel.thread_count() <= parallel.MAX_THREADS


def test05b_chunked_speed_rounds_as_the_whole_array_expression():
    # The slow twin is NumPy's one-line expression over the whole level; mixed dtypes and a
    # length that is not a whole number of chunks included.
    from mi_amr.core.derive import SPEED_CHUNK, _speed

    rng = np.random.default_rng(3)
    n = 2 * SPEED_CHUNK + 17
    for dtypes in [(np.float32,) * 3, (np.float64,) * 3, (np.float32, np.float64, np.float32)]:
        v = [rng.normal(size=n).astype(d) for d in dtypes]
        for out_dtype in (np.float32, np.float64):
            got, want = np.empty(n, out_dtype), np.empty(n, out_dtype)
            _speed(v, got)
            np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2], out=want, casting="same_kind")
            np.testing.assert_array_equal(got, want)


@pytest.mark.filterwarnings("error::RuntimeWarning")     # (an overflow is +inf, not a warning)
@pytest.mark.parametrize("seed,dtype,holes", [(0, np.float64, False), (1, np.float32, True),
                                              (5, np.float32, False)])
def test05c_speed_range_without_the_field_is_the_derived_fields_range(seed, dtype, holes,
                                                                       monkeypatch):
    """:func:`speed_range` (a time series' colour range: the squared speed's extremes, no
    field written) gives what ``derive(..., "speed").value_range`` gives, bit for bit: NaN
    holes, an overflowing square (+inf: not finite) and a level in several chunks included;
    (nan, nan) with no finite value; None for components of mixed dtypes."""
    from mi_amr.core import derive as derive_mod

    monkeypatch.setattr(derive_mod, "SPEED_CHUNK", 7)
    vol = _velocity_hierarchy(seed, (2, 2), dtype, holes)
    g = vol.grids[-1].fields
    g["vz"].ravel()[3] = np.finfo(dtype).max             # its square overflows
    vol = AMRVolume.from_grids(vol.grids, allow_nonfinite=holes)
    want = mi_amr.derive(vol, "speed").value_range("speed")
    got = derive_mod.speed_range(vol)
    assert got == want and all(type(x) is float for x in got), (got, want)
    for g in vol.grids:
        for n in ("vx", "vy", "vz"):
            g.fields[n][...] = np.nan
    nothing = AMRVolume.from_grids(vol.grids, allow_nonfinite=True)
    assert np.isnan(derive_mod.speed_range(nothing)).all()
    assert np.isnan(mi_amr.derive(nothing, "speed").value_range("speed")).all()
    mixed = _velocity_hierarchy(seed, (2, 2), dtype, holes)
    mixed.grids[0].fields["vx"] = mixed.grids[0].fields["vx"].astype(np.float16)
    assert derive_mod.speed_range(mixed) is None


def test40_each_grid_derives_in_its_own_velocitys_dtype():
    """Derived values take each grid's velocity dtype: float32 grids give float32 and a grid
    whose components are float64 (or mixed) gives float64, whether every grid agrees (one
    dtype found once) or not (found grid by grid)."""
    from mi_amr.core.derive import derive

    def field(c):
        return lambda p: np.stack([np.sin(p[..., 0] + c), p[..., 1] * p[..., 2], p[..., 0] ** 2],
                                  axis=-1)

    grids = [velocity_grid(level, lo, hi, [H0, H0 / 2, H0 / 4][level], field(i), dtype=np.float32)
             for i, (level, (lo, hi)) in enumerate(
                 (lv, box) for lv in range(3) for box in DERIVE_BOXES[lv])]
    same = derive(AMRVolume.from_grids(grids), "q_criterion", "speed")
    assert {g.fields[n].dtype for g in same.grids for n in ("q_criterion", "speed")} == \
        {np.dtype(np.float32)}
    grids[1]["fields"]["vy"] = grids[1]["fields"]["vy"].astype(np.float64)
    grids[4]["fields"] = {n: a.astype(np.float64) for n, a in grids[4]["fields"].items()}
    mixed = derive(AMRVolume.from_grids(grids), "q_criterion", "speed")
    for i, g in enumerate(mixed.grids):
        want = np.float64 if i in (1, 4) else np.float32
        assert g.fields["q_criterion"].dtype == want and g.fields["speed"].dtype == want, i
