"""Isosurface crossings along rays (:func:`mi_amr.trace`) on the analytic datasets, against a
dense float64 reference built here on the float64 model of the reconstruction,
:class:`~mi_amr.core.field64.Field64`.

The reference samples the model (basis or finest) densely along each ray (all rays' samples in
one call), brackets the first sign change of ``value - isovalue`` and bisects it on the model
down to 1e-9; where the samples come close to
the isovalue without crossing it, a ternary search finds how close the ray really gets. Rays
that only just touch the surface are told apart by how far they get past the isovalue: a ray
that crosses clearly must be hit within 1e-4 of a finest cell of the reference; one that
clearly stays off must not be hit; in between (float32 cannot decide), a hit must lie on the
isosurface.

The sphere and torus use 8 level-0 cells per side (chosen when this reference ran on the slow
twins, whose cost grows with the cell count); the level boundary x = 0.5 still cuts both
surfaces. The spike is the dataset as made. Normals are checked against the gradient of the slow
twin :func:`~mi_amr.core.field64.basis_point_reference` (:class:`Field64` gives values only).
"""

import numpy as np
import pytest

import mi_amr
from mi_amr.synthetic import datasets
from mi_amr.core.field64 import Field64, basis_point_reference
from mi_amr.evaluation.stability import rays
from mi_amr.evaluation.stability.rays import f32, unit

DEPTH_TOL = 1e-4     # finest cells: exact vs the reference
STEP = 0.2           # finest cells between reference samples (0.1 inside the spike's support)


# ---------------------------------------------------------------------- the dense reference

def box_interval(lo, hi, o, d):
    """``(t_in, t_out)`` of rays ``o + t d`` in the box ``[lo, hi]``, ``t_in`` clamped at 0."""
    near, far = rays.box_interval(lo, hi, o, d)
    return np.maximum(near, 0.0), far


class Reference:
    """First crossing of any isovalue along each ray by the float64 model (:class:`Field64` of
    field ``f``, basis or finest), from samples ``t_samples`` (per ray, sorted).

    Per isovalue, the ray's side of it is taken at its first sample. A sign change between two
    samples brackets a crossing. A dip towards the isovalue between samples shows as a sampled
    local minimum of the distance to it; each one before the first bracket that is close
    enough to matter is minimised by ternary search on the model, so a crossing hidden between
    two samples is bracketed too.
    Brackets are bisected on the model down to 1e-9.

    ``t`` (inf: none) and ``k`` (isovalue index, -1: none) give the first crossing of any
    isovalue; ``touchy`` marks rays that come within ``margin`` of an isovalue, crossing it or
    not, before their first crossing: whether float32 sees them cross is not decided.
    """

    def __init__(self, volume, o, d, isovalues, basis, t_samples, margin):
        self.volume, self.basis = volume, basis
        self.field = Field64(volume, "f", basis)
        self.isovalues = np.asarray(isovalues, dtype=np.float64)
        self.o, self.d = f32(o), f32(d)
        n = len(o)
        counts = np.array([len(t) for t in t_samples])
        pts = np.concatenate([self.o[i] + t[:, None] * self.d[i]
                              for i, t in enumerate(t_samples) if len(t)])
        per_ray = np.split(self.field(pts), np.cumsum(counts)[:-1])
        # Samples where the model is undefined (NaN: outside every grid, as an end sample that
        # rounding puts just outside the volume can be) are dropped.
        t_samples = [t[np.isfinite(v)] for t, v in zip(t_samples, per_ray)]
        per_ray = [v[np.isfinite(v)] for v in per_ray]
        self.t = np.full(n, np.inf)
        self.k = np.full(n, -1)
        self.touchy = np.zeros(n, dtype=bool)
        for k, iso in enumerate(self.isovalues):
            a, b = np.full(n, np.nan), np.full(n, np.nan)
            dips = []      # (ray, t_left, t_right, side) around sampled local minima
            shallow = np.zeros(n, dtype=bool)
            for i, (t, v) in enumerate(zip(t_samples, per_ray)):
                if len(t) < 2:
                    continue
                dist = (v - iso) * np.sign(v[0] - iso)
                change = np.flatnonzero(dist < 0)
                stop = change[0] if len(change) else len(t)
                if len(change):
                    a[i], b[i] = t[stop - 1], t[stop]
                    # A shallow crossing: the ray gets less than margin past the isovalue.
                    back = np.flatnonzero(dist[stop:] >= 0)
                    run = dist[stop:stop + back[0]] if len(back) else dist[stop:]
                    shallow[i] = run.min() > -margin
                for j in range(1, min(stop, len(t) - 1)):
                    # A local minimum near enough to the isovalue that the field, changing no
                    # faster than twice its sampled rate, could reach it between samples.
                    reach = 2 * max(abs(dist[j - 1] - dist[j]), abs(dist[j + 1] - dist[j]))
                    if dist[j] <= min(dist[j - 1], dist[j + 1]) and dist[j] < reach + margin:
                        dips.append((i, t[j - 1], t[j + 1], np.sign(v[0] - iso)))
            # Minimise each dip; one that reaches the other side brackets an earlier crossing.
            if dips:
                rays, lo, hi, side = (np.array(x) for x in zip(*dips))
                t_min, dist_min = self._minimise(rays, lo, hi, iso, side)
                for r, l, tm, dm in zip(rays, lo, t_min, dist_min):
                    if dm < 0 and not tm >= a[r]:
                        a[r], b[r] = l, tm
                        shallow[r] = dm > -margin
                    elif abs(dm) < margin:
                        self.touchy[r] = True
            t_k = self._bisect(a, b, iso)
            take = t_k < self.t
            self.t = np.where(take, t_k, self.t)
            self.k = np.where(take, k, self.k)
            # Only what happens before the first crossing of any isovalue counts.
            self.touchy |= shallow & take

    def _minimise(self, rays, lo, hi, iso, side):
        """Ternary search for the minimum of ``(value - iso) * side`` on ``[lo, hi]``."""
        for _ in range(45):
            m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
            f = self.value(np.concatenate([rays, rays]), np.concatenate([m1, m2]))
            f1, f2 = (f[:len(rays)] - iso) * side, (f[len(rays):] - iso) * side
            hi = np.where(f1 < f2, m2, hi)
            lo = np.where(f1 < f2, lo, m1)
        t = 0.5 * (lo + hi)
        return t, (self.value(rays, t) - iso) * side

    def _bisect(self, a, b, iso):
        out = np.full(len(a), np.inf)
        todo = np.flatnonzero(np.isfinite(a))
        if len(todo) == 0:
            return out
        A, B = a[todo], b[todo]
        f_a = self.value(todo, A) - iso
        while np.max(B - A) > 1e-9:
            mid = 0.5 * (A + B)
            f_m = self.value(todo, mid) - iso
            left = np.sign(f_m) != np.sign(f_a)
            A, B = np.where(left, A, mid), np.where(left, mid, B)
            f_a = np.where(left, f_a, f_m)
        out[todo] = 0.5 * (A + B)
        return out

    def value(self, rays, t):
        """Float64 model's value at ``o + t d`` of the given rays."""
        return self.field(self.o[rays] + t[:, None] * self.d[rays])


def samples_in_box(o, d, lo, hi, step):
    """Per ray, parameters every ``step`` (world) through the box ``[lo, hi]`` (ends included)."""
    o, d = f32(o), f32(d)
    t_in, t_out = box_interval(lo, hi, o, d)
    out = []
    for a, b, dn in zip(t_in, t_out, np.linalg.norm(d, axis=1)):
        out.append(np.linspace(a, b, int(np.ceil((b - a) * dn / step)) + 1) if a < b
                   else np.zeros(0))
    return out


def dense_reference(volume, o, d, isovalues, basis, margin, extra=None):
    """The reference with samples every :data:`STEP` finest cells over the volume, plus the
    parameters in ``extra`` (per ray) where a ray needs a finer look."""
    h = volume.level_spacing(volume.num_levels - 1)[0]
    t = samples_in_box(o, d, *volume.bounds, STEP * h)
    if extra is not None:
        t = [np.unique(np.concatenate([a, b])) if len(a) else a for a, b in zip(t, extra)]
    return Reference(volume, o, d, np.atleast_1d(isovalues), basis, t, margin)


def check_exact(volume, ref, result, margin, label):
    """Exact against the reference. Rays that cross without coming within ``margin`` of the
    isovalue first are hit at the reference's depth (within :data:`DEPTH_TOL` finest cells)
    and isovalue; rays that stay more than ``margin`` away are not hit; every hit, touchy
    rays' included, lies on the isosurface (within ``margin``)."""
    h = volume.level_spacing(volume.num_levels - 1)[0]
    crossed = np.isfinite(ref.t)
    clear = crossed & ~ref.touchy
    missed = np.flatnonzero(clear & ~result.hit)
    assert len(missed) == 0, f"{label}: exact misses rays {missed.tolist()}"
    err = np.abs(result.t[clear] - ref.t[clear]) / h
    worst = np.flatnonzero(clear)[err.argmax()]
    assert err.max() < DEPTH_TOL, \
        f"{label}: depth error {err.max():.2e} cells on ray {worst}: exact t = " \
        f"{result.t[worst]!r}, reference t = {ref.t[worst]!r}"
    np.testing.assert_array_equal(result.iso_index[clear], ref.k[clear])
    false = np.flatnonzero(~crossed & ~ref.touchy & result.hit)
    assert len(false) == 0, f"{label}: exact hits rays {false.tolist()} that stay off the surface"
    # On the isosurface: the value there is the isovalue, or (a jump of ``finest`` at a grid
    # face) the values just before and after lie on either side of it.
    hits = np.flatnonzero(result.hit)
    iso = ref.isovalues[result.iso_index[hits]]
    t = result.t[hits]
    residual = np.abs(ref.value(hits, t) - iso)
    step = 1e-3 * h / np.linalg.norm(ref.d[hits], axis=1)
    straddle = (ref.value(hits, t - step) - iso) * (ref.value(hits, t + step) - iso) < 0
    off = ~(residual < margin) & ~straddle
    assert not off.any(), f"{label}: hits off the isosurface on rays {hits[off].tolist()} " \
        f"(|value - iso| = {residual[off].tolist()})"


# ---------------------------------------------------------------------- rays and datasets

CENTRE = np.array([0.5, 0.5, 0.5])


@pytest.fixture(scope="module")
def sphere():
    return datasets.sphere(base=8)


@pytest.fixture(scope="module")
def torus():
    return datasets.torus(base=8)


@pytest.fixture(scope="module")
def spike():
    return datasets.spike()


def random_rays(rng, n, spread, centre=CENTRE, distance=2.0):
    """Rays from outside the unit cube through random points within ``spread`` of ``centre``."""
    targets = centre + (rng.random((n, 3)) - 0.5) * 2 * spread
    d = unit(rng.normal(size=(n, 3)))
    return f32(targets - distance * d), f32(d)


def axis_rays():
    """Rays along +-x, +-y, +-z, some in the level-boundary plane x = 0.5 or in planes through
    cell centres (x = 0.53125 on level 1, z = 0.4375 on level 0), some along the boundary."""
    o, d = [], []
    for x, z in [(0.5, 0.5), (0.5, 0.4375), (0.53125, 0.5), (0.3, 0.6), (0.62, 0.41)]:
        o += [(x, -1.0, z), (x, 2.0, z)]
        d += [(0, 1, 0), (0, -1, 0)]
    for y, z in [(0.5, 0.5), (0.55, 0.45), (0.4375, 0.5625), (0.7, 0.52)]:
        o += [(-1.0, y, z), (2.0, y, z)]
        d += [(1, 0, 0), (-1, 0, 0)]
    for x, y in [(0.5, 0.5), (0.45, 0.58), (0.65, 0.35)]:
        o += [(x, y, -1.0), (x, y, 2.0)]
        d += [(0, 0, 1), (0, 0, -1)]
    return f32(o), f32(d)


def inner_rays(rng):
    """Rays starting inside the volume: outside the surface (near the cube's corners) and
    inside it (within 0.15 of the centre, one at the centre itself)."""
    outside = f32(rng.choice([0.06, 0.94], size=(10, 3)) + rng.normal(scale=0.02, size=(10, 3)))
    d_out = unit(CENTRE + rng.normal(scale=0.1, size=(10, 3)) - outside)
    inside = f32(CENTRE + (rng.random((10, 3)) - 0.5) * 0.3)
    inside[0] = CENTRE
    d_in = unit(rng.normal(size=(10, 3)))
    return f32(np.concatenate([outside, inside])), f32(np.concatenate([d_out, d_in]))


def rays_past_centre(b, d, side):
    """Rays along ``d`` passing the sphere's centre at distance ``b`` on the ``side`` unit
    vector (perpendicular to ``d``), starting 2 before the closest approach, and extra
    reference samples every 0.05 finest cells within 0.15 of that approach."""
    o, d = f32(CENTRE + b[:, None] * side - 2.0 * d), f32(d)
    t_c = np.sum((CENTRE - o) * d, axis=1)
    extra = [np.linspace(t - 0.15, t + 0.15, int(0.3 / (0.05 / 16)) + 1) for t in t_c]
    return o, d, extra


def random_sides(rng, n):
    d = unit(rng.normal(size=(n, 3)))
    return d, unit(np.cross(d, rng.normal(size=(n, 3))))


def grazing_rays(rng, n=24):
    """Rays passing the sphere's centre at distances around the isosurface radius 0.3 (so
    they touch, barely cross or barely miss the reconstructed surface)."""
    d, side = random_sides(rng, n)
    return rays_past_centre(np.linspace(0.26, 0.31, n), d, side)


def tangent_rays(sphere, rng, n=4, offsets=(-3e-4, -3e-5, -3e-6, 0.0, 3e-6, 3e-5, 3e-4)):
    """For ``n`` directions, the distance ``b*`` from the centre at which a ray is tangent to
    the *reconstructed* isosurface (bisection on ``b`` of the ray's minimum value, found by
    ternary search on the float64 model of the basis reconstruction), and rays at
    ``b* + offsets``: they dip below the isovalue by about ``-offset``."""
    d, side = random_sides(rng, n)
    field = Field64(sphere, "f", True)

    def lowest(b):
        o, dd, _ = rays_past_centre(b, d, side)
        t_c = np.sum((CENTRE - o) * dd, axis=1)
        lo, hi = t_c - 0.05, t_c + 0.05
        for _ in range(40):
            m1, m2 = lo + (hi - lo) / 3, hi - (hi - lo) / 3
            f1, f2 = (field(o + m[:, None] * dd) for m in (m1, m2))
            hi, lo = np.where(f1 < f2, m2, hi), np.where(f1 < f2, lo, m1)
        return field(o + (0.5 * (lo + hi))[:, None] * dd)

    b_lo, b_hi = np.full(n, 0.28), np.full(n, 0.31)
    assert np.all(lowest(b_lo) < 0.3) and np.all(lowest(b_hi) > 0.3)
    for _ in range(24):
        mid = 0.5 * (b_lo + b_hi)
        below = lowest(mid) < 0.3
        b_lo, b_hi = np.where(below, mid, b_lo), np.where(below, b_hi, mid)
    b = (0.5 * (b_lo + b_hi))[:, None] + np.asarray(offsets)[None, :]
    k = len(offsets)
    return rays_past_centre(b.ravel(), np.repeat(d, k, axis=0), np.repeat(side, k, axis=0))


# ---------------------------------------------------------------------- exact, analytic datasets

@pytest.fixture(scope="module")
def sphere_rays():
    rng = np.random.default_rng(1)
    sets = [random_rays(rng, 60, 0.35), axis_rays(), inner_rays(rng)]
    return f32(np.concatenate([s[0] for s in sets])), f32(np.concatenate([s[1] for s in sets]))


@pytest.mark.parametrize("reconstruction", ["basis", "finest"])
def test01_exact_finds_every_sphere_crossing_across_the_level_boundary(sphere, sphere_rays,
                                                                         reconstruction):
    """Random rays from outside, axis-aligned rays (some in the level-boundary plane) and
    rays starting inside the volume or inside the surface: exact hits every ray the
    reference crosses, within 1e-4 of a finest cell."""
    o, d = sphere_rays
    basis = reconstruction == "basis"
    ref = dense_reference(sphere, o, d, 0.3, basis, 1e-4)
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, method="exact",
                       reconstruction=reconstruction)
    assert np.isfinite(ref.t).sum() > 60
    # Rays starting inside the surface cross it on the way out.
    assert np.all(np.isfinite(ref.t[-10:])) and np.all(res.hit[-10:])
    check_exact(sphere, ref, res, 1e-4, f"sphere/{reconstruction}")
    assert ref.touchy.sum() <= 3


@pytest.mark.parametrize("name", ["sphere", "torus"])
def test01b_exact_on_cells_that_are_not_cubes(name):
    """The sphere and the torus on cells stretched 1 : 0.5 : 2 along x, y and z (the lattice,
    the kd-tree, the brick pools and the cubic pieces all work per axis): exact hits every ray
    the reference crosses and no other, with both reconstructions, as on cubes."""
    scale = np.array([1.0, 0.5, 2.0])
    cubes = datasets.ANALYTIC[name]()
    vol = mi_amr.AMRVolume.from_grids([
        dict(level=g.level, origin=tuple(np.multiply(g.origin, scale)),
             spacing=tuple(np.multiply(g.spacing, scale)), fields=dict(g.fields))
        for g in cubes.grids])
    lo, hi = vol.bounds
    o, d = random_rays(np.random.default_rng(3), 80, 0.35 * (hi - lo), centre=(lo + hi) / 2,
                       distance=3.0)
    iso = datasets.ISOVALUES[name]
    for reconstruction in ("basis", "finest"):
        ref = dense_reference(vol, o, d, iso, reconstruction == "basis", 1e-4)
        res = mi_amr.trace(vol, o, d, field="f", isovalue=iso, method="exact",
                           reconstruction=reconstruction)
        assert np.isfinite(ref.t).sum() > 30
        check_exact(vol, ref, res, 1e-4, f"stretched {name}/{reconstruction}")


def test02_finest_jump_at_the_level_boundary_is_a_crossing(sphere):
    """``finest`` jumps at the level boundary x = 0.5; rays along +-x that pass the isovalue
    only in that jump are hit exactly at the boundary, as the reference (which brackets the
    jump) finds."""
    r = np.linspace(0.285, 0.305, 41)
    o = np.stack([np.full_like(r, -1.0), 0.5 + r * np.cos(0.7), 0.5 + r * np.sin(0.7)], axis=1)
    o = f32(np.concatenate([o, o * [-1, 1, 1] + [2, 0, 0]]))
    d = f32(np.repeat([[1.0, 0, 0], [-1.0, 0, 0]], len(r), axis=0))
    ref = dense_reference(sphere, o, d, 0.3, False, 1e-4)
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, reconstruction="finest")
    at_boundary = np.abs(o[:, 0] + ref.t * d[:, 0] - 0.5) < 1e-6
    assert at_boundary.sum() >= 5
    check_exact(sphere, ref, res, 1e-4, "finest jump")


def test03_exact_on_grazing_rays(sphere):
    """Rays tangent to the isosurface or nearly so -- a family around the radius, and rays
    within 3e-4 .. 3e-6 of tangency to the reconstructed surface: clear crossings are found
    at the right depth, clear misses stay misses, and a touch, when reported, lies on the
    surface."""
    rng = np.random.default_rng(2)
    sets = [grazing_rays(rng), tangent_rays(sphere, rng)]
    o = np.concatenate([s[0] for s in sets])
    d = np.concatenate([s[1] for s in sets])
    extra = sets[0][2] + sets[1][2]
    ref = dense_reference(sphere, o, d, 0.3, True, 1e-4, extra)
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, method="exact")
    # Both sides of tangency, and rays too close to it to call, are present.
    crossed = np.isfinite(ref.t)
    assert (crossed & ~ref.touchy).sum() >= 10 and (~crossed & ~ref.touchy).sum() >= 8
    assert ref.touchy.sum() >= 8
    check_exact(sphere, ref, res, 1e-4, "grazing")


def test04_exact_finds_every_torus_crossing(torus):
    """Random rays through the torus (a hole, two surfaces per ray, across the level
    boundary)."""
    rng = np.random.default_rng(3)
    o, d = random_rays(rng, 70, 0.4)
    ref = dense_reference(torus, o, d, datasets.ISOVALUES["torus"], True, 1e-4)
    res = mi_amr.trace(torus, o, d, field="f", isovalue=datasets.ISOVALUES["torus"],
                       method="exact")
    assert np.isfinite(ref.t).sum() > 30
    check_exact(torus, ref, res, 1e-4, "torus")


def spike_centre(volume):
    g = volume.grids[1]
    i, j, k = np.argwhere(g.fields["f"] != 0)[0]
    return np.array([c[n] for c, n in zip(g.cell_centers(), (i, j, k))]), g.spacing[0]


@pytest.fixture(scope="module")
def spike_rays(spike):
    """Rays through random points within 0.2 cells of the one-cell spike, and where the field
    can differ from zero (inside the spike cell's hat support) the reference's samples."""
    c, h = spike_centre(spike)
    rng = np.random.default_rng(4)
    o, d = random_rays(rng, 64, 0.2 * h, centre=c)
    return o, d, samples_in_box(o, d, c - h, c + h, 0.1 * h)


@pytest.mark.parametrize("reconstruction", ["basis", "finest"])
def test05_exact_finds_the_one_cell_spike(spike, spike_rays, reconstruction):
    """A blob half a cell across: every ray through it is hit at the reference's depth.
    Outside the spike cell's hat support every cell holds 0, so the reference samples only
    that box."""
    o, d, t_samples = spike_rays
    iso = datasets.ISOVALUES["spike"]
    ref = Reference(spike, o, d, [iso], reconstruction == "basis", t_samples, 1e-3)
    res = mi_amr.trace(spike, o, d, field="f", isovalue=iso, method="exact",
                       reconstruction=reconstruction)
    assert (np.isfinite(ref.t) & ~ref.touchy).sum() > 30
    check_exact(spike, ref, res, 1e-3, f"spike/{reconstruction}")


def test06_uniform_steps_miss_the_spike_exact_does_not(spike, spike_rays):
    """At one sample per finest cell, uniform sampling steps over the blob on many rays that
    exact hits."""
    o, d, _ = spike_rays
    iso = datasets.ISOVALUES["spike"]
    exact = mi_amr.trace(spike, o, d, field="f", isovalue=iso, method="exact")
    uniform = mi_amr.trace(spike, o, d, field="f", isovalue=iso, method="uniform",
                           step_scale=1.0)
    assert exact.hit.sum() > 30
    missed = exact.hit & ~uniform.hit
    assert missed.sum() >= 0.4 * exact.hit.sum(), (missed.sum(), exact.hit.sum())
    assert not np.any(uniform.hit & ~exact.hit)


# ---------------------------------------------------------------------- the sampling methods

@pytest.mark.parametrize("method", ["uniform", "adaptive", "bisect"])
def test07_sampling_methods_converge_to_exact_as_the_step_shrinks(sphere, method):
    """Rays well inside the sphere's silhouette: every method hits what exact hits, within
    a quarter of a step; bisection within its 0.005-cell target. The error shrinks."""
    rng = np.random.default_rng(6)
    o, d = random_rays(rng, 120, 0.17)
    h = 1 / 16
    exact = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, method="exact")
    assert exact.hit.all()
    errors = []
    for s in (1.0, 0.5, 0.25, 0.125):
        res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, method=method, step_scale=s)
        np.testing.assert_array_equal(res.hit, exact.hit)
        err = np.abs(res.t - exact.t).max() / h
        tol = 0.005 if method == "bisect" else 0.25 * s
        assert err < tol, f"{method} at step_scale {s}: error {err:.3g} cells > {tol:.3g}"
        errors.append(err)
    if method != "bisect":
        assert errors[-1] < 0.25 * errors[0], errors


@pytest.mark.parametrize("method", ["exact", "bisect", "adaptive", "uniform"])
def test08_samples_count_the_work_done(sphere, method):
    """A ray that finds the surface has evaluated the field at least once; a ray that only
    crosses kd leaves whose value range cannot hold the isovalue (near the cube's edges, far
    from the sphere; which ones is read off the tree that ``trace`` builds) is answered by the
    traversal alone and evaluates nothing."""
    rng = np.random.default_rng(7)
    o, d = random_rays(rng, 40, 0.45)
    # Rays along the twelve edges of the unit cube, 0.02 inside its faces.
    edges_o, edges_d = [], []
    for axis in range(3):
        for a in (0.02, 0.98):
            for b in (0.02, 0.98):
                start = np.empty(3)
                start[axis] = -1.0
                start[(axis + 1) % 3], start[(axis + 2) % 3] = a, b
                edges_o.append(start)
                edges_d.append(np.eye(3)[axis])
    o = np.concatenate([o, f32(edges_o)])
    d = np.concatenate([d, f32(edges_d)])
    t_in, t_out = box_interval(*sphere.bounds, o, d)
    assert np.all(t_in < t_out)
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, method=method, step_scale=0.5)
    assert res.hit[:40].sum() > 5
    assert np.all(res.samples[res.hit] > 0)
    assert not res.hit[40:].any()

    tree = mi_amr.KDTree(sphere, leaf_cells=4)          # what trace uses
    lo, hi = tree.leaf_ranges("f", "basis")
    t = np.linspace(0.0, 3.0, 30001)
    skippable = []
    for k in range(40, len(o)):
        p = o[k] + t[:, None] * d[k]
        p = p[np.all((p > tree.lo) & (p < tree.hi), axis=1)]
        leaves = np.unique(tree.locate(p))
        skippable.append(not np.any((lo[leaves] <= 0.3) & (0.3 <= hi[leaves])))
    skippable = np.array(skippable)
    assert skippable.sum() >= 4
    np.testing.assert_array_equal(res.samples[40:][skippable], 0)


# ---------------------------------------------------------------------- normals, isovalues, misses

def test09_normals_are_unit_and_point_to_increasing_values(sphere, torus):
    """On the sphere the normal is close to the radial direction (the field grows outwards)
    and equals the slow twin's normalised gradient; on the torus it points along the twin's
    gradient. (The twin, not :class:`Field64`, which gives no gradients.)"""
    rng = np.random.default_rng(9)
    o, d = random_rays(rng, 60, 0.3)
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, method="exact")
    hits = np.flatnonzero(res.hit)
    assert len(hits) > 30
    n = res.normal[hits]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    p = o[hits] + res.t[hits, None] * d[hits]
    radial = unit(p - CENTRE)
    cos = np.sum(n * radial, axis=1)
    assert cos.min() > 0.95 and cos.mean() > 0.99, (cos.min(), cos.mean())
    _, g = basis_point_reference(sphere, f32(p), "f")
    np.testing.assert_allclose(n, unit(g), atol=1e-3)
    assert np.all(np.isnan(res.normal[~res.hit]))

    o, d = random_rays(rng, 60, 0.4)
    res = mi_amr.trace(torus, o, d, field="f", isovalue=datasets.ISOVALUES["torus"])
    hits = np.flatnonzero(res.hit)
    assert len(hits) > 20
    p = f32(o[hits] + res.t[hits, None] * d[hits])
    _, g = basis_point_reference(torus, p, "f")
    np.testing.assert_allclose(np.linalg.norm(res.normal[hits], axis=1), 1.0, atol=1e-5)
    assert np.all(np.sum(res.normal[hits] * unit(g), axis=1) > 0.999)


def test10_first_crossing_of_several_isovalues_with_its_index(sphere):
    """Isovalues 0.3, 0.32, 0.28 (unsorted, close enough to be crossed within one cubic
    piece): from outside the first shell met is 0.32; from between the shells it is 0.28 or
    0.3 depending on direction. Index and depth match the reference's first crossing of any
    isovalue."""
    rng = np.random.default_rng(10)
    isos = [0.3, 0.32, 0.28]
    o1, d1 = random_rays(rng, 30, 0.3)
    # Starts between the shells: at radius 0.29 (inwards the first crossing is 0.28, outwards
    # 0.3) and 0.31 (inwards 0.3, outwards 0.32), half of them heading for the centre.
    radial = unit(rng.normal(size=(20, 3)))
    shell = CENTRE + radial * np.repeat([0.29, 0.31], 10)[:, None]
    d2 = unit(rng.normal(size=(20, 3)))
    d2[::2] = -radial[::2]
    o = f32(np.concatenate([o1, shell]))
    d = f32(np.concatenate([d1, d2]))
    ref = dense_reference(sphere, o, d, isos, True, 1e-4)
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=isos, method="exact")
    assert set(ref.k[np.isfinite(ref.t)]) == {0, 1, 2}
    check_exact(sphere, ref, res, 1e-4, "three isovalues")


@pytest.mark.parametrize("method", ["exact", "bisect", "adaptive", "uniform"])
def test11_rays_missing_the_volume_return_inf(sphere, method):
    """Rays that pass beside the unit cube, point away from it, or run along a face plane
    outside it: no hit, t = inf, no samples."""
    o = f32([[-1, 2, 0.5], [2, 0.5, 0.5], [0.5, 0.5, -0.5], [-1, 1.5, 1.5], [-0.5, -0.5, 0.5],
             [0.5, 1.0 + 1e-3, -1]])
    d = f32(unit([[1, 0, 0], [1, 0, 0], [0, 1, -1], [1, 1, 1], [1, -1, 0], [0, 0, 1]]))
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3, method=method)
    assert not res.hit.any()
    assert np.all(np.isinf(res.t)) and np.all(res.t > 0)
    np.testing.assert_array_equal(res.samples, 0)


def test12_rays_without_a_hit_have_no_isovalue_index(sphere):
    o, d = f32([[-1, 2, 0.5], [-1, 0.5, 0.5]]), f32([[1, 0, 0], [1, 0, 0]])
    res = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3)
    assert res.hit.tolist() == [False, True]
    assert res.iso_index.tolist() == [-1, 0]


@pytest.mark.parametrize("method", ["uniform", "adaptive", "bisect"])
@pytest.mark.parametrize("step_scale", [2.0, 4.0])
def test09_nodes_skipped_before_the_first_sample_leave_their_side(method, step_scale):
    """A ramp ``f = x`` rising through the isovalue just inside a kd leaf, past empty ones:
    with steps of a few cells the first sample in that leaf is already across the isovalue,
    so the crossing is bracketed by the skipped nodes' side (evaluated where the last step
    before them falls). With no sample before them, those nodes once left no side and the
    crossing was missed at steps of 2 cells and more (uniform). Linear interpolation is exact
    on the ramp."""
    from conftest import grid
    from mi_amr.core.volume import AMRVolume

    vol = AMRVolume.from_grids([grid(0, (0, 0, 0), (1, 0.5, 0.5), 1 / 32,
                                     fn=lambda c: c[..., 0])])
    rng = np.random.default_rng(1)
    n = 100
    o = np.stack([-0.5 + 0.1 * rng.random(n), 0.2 + 0.1 * rng.random(n),
                  0.2 + 0.1 * rng.random(n)], axis=1)
    d = np.stack([np.ones(n), 0.05 * rng.normal(size=n), 0.05 * rng.normal(size=n)], axis=1)
    res = mi_amr.trace(vol, o, d, field="f", isovalue=0.3, method=method,
                       step_scale=step_scale)
    assert res.hit.all()
    np.testing.assert_allclose(o[:, 0] + res.t * d[:, 0], 0.3, atol=1e-4)
