"""The stability suite's ray cases: volumes and ray families that break isosurface methods,
each measured on every method against the dense float64 reference (:mod:`.rays`, scored by
:func:`~mi_amr.evaluation.stability.scoring.measure`). Each ``case_*(quick)`` returns its rows;
``quick`` uses fewer rays.

All positions are the volume's world space (the analytic datasets fill the unit cube); ray
parameters are in units of the ray's direction; cell counts are finest cells unless said.
"""

from __future__ import annotations

import functools
import time

import numpy as np

from mi_amr.core.kdtree import KDTree
from mi_amr.core.volume import AMRVolume
from mi_amr.evaluation.stability.rays import CENTRE, DenseField, dense_reference, f32, \
    minimise, unit
from mi_amr.evaluation.stability.scoring import measure, score, trace_reference
from mi_amr.kernels.trace import trace
from mi_amr.params import METHODS
from mi_amr.synthetic import datasets


# ---------------------------------------------------------------------- volumes and rays

def random_rays(rng, n, spread, centre=CENTRE, distance=2.0):
    """Rays from ``distance`` away through random points within ``spread`` of ``centre``."""
    targets = centre + (rng.random((n, 3)) - 0.5) * 2 * spread
    d = unit(rng.normal(size=(n, 3)))
    return f32(targets - distance * d), f32(d)


def spike_centre(volume):
    """The spike dataset's one non-zero level-1 cell: its centre (world) and its size."""
    g = volume.grids[1]
    i, j, k = np.argwhere(g.fields["f"] != 0)[0]
    return np.array([c[n] for c, n in zip(g.cell_centers(), (i, j, k))]), g.spacing[0]


# ---------------------------------------------------------------------- cases: thin features

def case_thin_spike(quick):
    """The one-cell spike (iso 0.75): rays through random points within 0.3 cells of its
    centre, and some within 1.5 cells (mostly misses). Step: one finest cell."""
    vol = datasets.spike()
    c, h = spike_centre(vol)
    rng = np.random.default_rng(11)
    n = 48 if quick else 192
    o1, d1 = random_rays(rng, n, 0.3 * h, centre=c)
    o2, d2 = random_rays(rng, n // 4, 1.5 * h, centre=c)
    o, d = np.concatenate([o1, o2]), np.concatenate([d1, d2])
    return measure("thin: one-cell spike", vol, o, d, datasets.ISOVALUES["spike"],
                   step_scale=1.0, ref_kw={"focus": (c - h, c + h, 0.01), "margin": 1e-4})


SHEET_NORMAL = unit([0.35, 1.0, 0.2])
SHEET_ISO = 0.85


def sheet_volume(base=16, width_cells=1.0):
    """A sheet ``exp(-(s / w)^2)``, ``s`` the distance to the plane through the cube's centre
    with normal :data:`SHEET_NORMAL`, ``w`` = ``width_cells`` finest cells, crossing the level
    boundary. At :data:`SHEET_ISO` its surface is a slab at most 0.3 finest cells thick (where
    a cell centre lies close enough to the plane; elsewhere it has holes, as a Q-criterion
    sheet would)."""
    w = width_cells / (2 * base)
    return datasets.two_levels(
        lambda p, level: np.exp(-(((p - CENTRE) @ SHEET_NORMAL) / w) ** 2), base)


def case_thin_sheet(quick):
    """Rays through random points of the sheet (iso :data:`SHEET_ISO`) from random
    directions. Step: one finest cell."""
    vol = sheet_volume()
    rng = np.random.default_rng(12)
    n = 64 if quick else 256
    # Targets on the sheet's plane, within 0.3 of the centre.
    t = (rng.random((n, 3)) - 0.5) * 0.6
    t -= (t @ SHEET_NORMAL)[:, None] * SHEET_NORMAL
    d = unit(rng.normal(size=(n, 3)))
    o, d = f32(CENTRE + t - 2.0 * d), f32(d)
    return measure("thin: sheet thinner than a step", vol, o, d, SHEET_ISO, step_scale=1.0,
                   ref_kw={"step_cells": 0.05})


# ---------------------------------------------------------------------- cases: tangents, extrema

def _ray_minimum(field, o, d, iso, t_lo, t_hi, step_cells=0.05):
    """Minimum of ``value - iso`` (field units) along each ray over ``[t_lo, t_hi]`` (dense
    samples ``step_cells`` finest cells apart, then :func:`.rays.minimise` around the
    smallest); returns ``(t, minimum)``."""
    n = len(o)
    count = int(np.ceil((t_hi - t_lo) / (step_cells * field.h_fine))) + 1
    ts = np.linspace(t_lo, t_hi, count)
    v = field((o[:, None, :] + ts[None, :, None] * d[:, None, :]).reshape(-1, 3)).reshape(n, -1)
    j = np.nanargmin(v, axis=1)
    lo, hi = ts[np.maximum(j - 1, 0)], ts[np.minimum(j + 1, count - 1)]
    return minimise(lambda r, t: field(o[r] + t[:, None] * d[r]), np.arange(n), lo, hi, iso,
                    np.ones(n))


def tangent_offsets(field, iso, dirs, sides, lo=0.22, hi=0.36, iterations=13, k=8):
    """Offsets ``b`` at which rays ``CENTRE + b * side + (t - 2) * d`` touch the reconstructed
    surface (their minimum of the field is ``iso``): ``k``-section on ``b`` (the minimum is
    below ``iso`` at ``lo``, above at ``hi``)."""
    n = len(dirs)
    lo, hi = np.full(n, lo), np.full(n, hi)
    frac = np.linspace(0.0, 1.0, k + 1)[1:-1]
    lanes = np.arange(n)
    for _ in range(iterations):
        b = lo[:, None] + (hi - lo)[:, None] * frac[None, :]
        o = (CENTRE + b[..., None] * sides[:, None, :] - 2.0 * dirs[:, None, :]).reshape(-1, 3)
        _, m = _ray_minimum(field, o, np.repeat(dirs, len(frac), axis=0), iso, 1.6, 2.4)
        above = np.concatenate([m.reshape(n, -1) >= 0, np.ones((n, 1), dtype=bool)], axis=1)
        j = np.argmax(above, axis=1)
        edges = np.concatenate([lo[:, None], b, hi[:, None]], axis=1)
        lo, hi = edges[lanes, j], edges[lanes, j + 1]
    return 0.5 * (lo + hi)


def _grazing_rays(field, n, seed, deltas):
    """Per direction: rays at the tangent offset (float32) and ``deltas`` inside and outside
    it. Returns ``(o_tangent, d_tangent, o_near, d_near)``."""
    rng = np.random.default_rng(seed)
    dirs = unit(rng.normal(size=(n, 3)))
    sides = unit(np.cross(dirs, rng.normal(size=(n, 3))))
    b = tangent_offsets(field, datasets.ISOVALUES["sphere"], dirs, sides)
    ray = lambda off: (CENTRE + off[:, None] * sides - 2.0 * dirs, dirs)  # noqa: E731
    o_t, d_t = ray(b)
    near = [ray(b + s * delta) for delta in deltas for s in (-1.0, 1.0)]
    return (f32(o_t), f32(d_t), f32(np.concatenate([x[0] for x in near])),
            f32(np.concatenate([x[1] for x in near])))


@functools.lru_cache(maxsize=4)
def _grazing_family(reconstruction, n):
    """The sphere's grazing rays for ``n`` directions (see :func:`_grazing_rays`), shared by
    the grazing and tangent cases."""
    field = DenseField(datasets.sphere(), "f", reconstruction == "basis")
    return field, _grazing_rays(field, n, 21, (3e-3, 3e-4, 3e-5))


def _grazing_rows(label, quick, tangent):
    iso = datasets.ISOVALUES["sphere"]
    rows = []
    for rec in ("basis", "finest"):
        field, (o_t, d_t, o_n, d_n) = _grazing_family(rec, 6 if quick else 24)
        o, d = (o_t, d_t) if tangent else (o_n, d_n)
        ref = dense_reference(field, o, d, iso, focus=(CENTRE - 0.4, CENTRE + 0.4, 0.02))
        for method in METHODS:
            res = trace_reference(field.volume, ref, method, rec, 0.5)
            rows.append(score(label, field.volume, ref, res, method, rec, 0.5,
                              touch_must_hit=tangent))
    return rows


def case_grazing(quick):
    """Rays 3e-3, 3e-4 and 3e-5 (world units; 0.1 to 1e-3 finest cells) inside and outside
    the tangent of the sphere's reconstructed surface, the tangent offset searched on the
    reference per direction: inside ones must be hit, outside ones not."""
    return _grazing_rows("grazing: sphere, just inside/outside the tangent", quick, False)


def case_tangent(quick):
    """The sphere's tangent rays themselves (see :func:`case_grazing`), whose minimum of the
    field equals the isovalue within :data:`TANGENT` after rounding to float32: the
    isovalue is a local extremum of the field along the ray, and exact must find the
    touching point."""
    return _grazing_rows("extremum: iso = minimum along the ray (tangent rays)", quick, True)


def case_spike_maximum(quick):
    """Isovalue 1.0, the spike's maximum: rays through the spike cell's centre (exactly, in
    float32: origins ``c - 0.5 k`` and directions ``k`` for small integer vectors ``k``) touch
    the surface there and must be hit; rays passing 0.01 cells beside it must not."""
    vol = datasets.spike()
    c, h = spike_centre(vol)
    ks = np.array([(x, y, z) for x in range(-2, 3) for y in range(-2, 3) for z in range(-2, 3)
                   if (x, y, z) != (0, 0, 0)], dtype=np.float64)
    if quick:
        ks = ks[np.random.default_rng(31).choice(len(ks), 24, replace=False)]
    o = c - 0.5 * ks
    beside = unit(np.cross(ks, [0.3, 0.5, 0.7])) * 0.01 * h
    o = np.concatenate([o, o + beside])
    d = np.concatenate([ks, ks])
    return measure("extremum: iso = spike maximum 1.0", vol, o, d, 1.0, step_scale=1.0,
                   touch_must_hit=True, ref_kw={"focus": (c - h, c + h, 0.01)})


# ---------------------------------------------------------------------- cases: level boundary

def torus_surface(theta, phi):
    """Points and outward normals of :func:`mi_amr.synthetic.datasets.torus`'s analytic surface."""
    axis = np.array([np.sin(0.5), 0.0, np.cos(0.5)])
    e1 = np.array([np.cos(0.5), 0.0, -np.sin(0.5)])
    e2 = np.cross(axis, e1)
    ring = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    normal = np.cos(phi)[:, None] * ring + np.sin(phi)[:, None] * axis
    return CENTRE + 0.27 * ring + 0.1 * normal, normal


def _boundary_points(name, rng, n, spread):
    """Points of the analytic surface of dataset ``name`` within ``spread`` of the plane
    x = 0.5, on the surface's outer side (so a ray coming in along the normal sees them)."""
    if name == "sphere":
        s = (rng.random(n) - 0.5) * 2 * spread
        phi = rng.random(n) * 2 * np.pi
        r = np.sqrt(0.09 - s ** 2)
        normal = np.stack([s / 0.3, r / 0.3 * np.cos(phi), r / 0.3 * np.sin(phi)], axis=1)
        return CENTRE + 0.3 * normal, normal
    pts, nrm = [], []
    while sum(len(p) for p in pts) < n:
        p, nm = torus_surface(rng.random(4096) * 2 * np.pi, (rng.random(4096) - 0.5) * 2.4)
        keep = np.abs(p[:, 0] - 0.5) < spread
        pts.append(p[keep])
        nrm.append(nm[keep])
    return np.concatenate(pts)[:n], np.concatenate(nrm)[:n]


def wall_hits(field: DenseField, o, d, t, hit) -> np.ndarray:
    """Hits on a jump of the field: the crack between two grids that the ``finest``
    reconstruction leaves, which the methods close with a wall (a jump across the isovalue
    counts as a crossing). The field changes across ``[t - e, t + e]`` (``e``: 1e-4 finest
    cells) by more than 10 times its change over each neighbouring ``e``."""
    out = np.zeros(len(t), dtype=bool)
    sel = np.flatnonzero(hit & np.isfinite(t))
    if len(sel) == 0:
        return out
    e = 1e-4 * field.h_fine / np.linalg.norm(d[sel], axis=1)
    f = [field(o[sel] + (t[sel] + k * e)[:, None] * d[sel]) for k in (-2, -1, 1, 2)]
    smooth = np.abs(f[1] - f[0]) + np.abs(f[3] - f[2])
    out[sel] = np.abs(f[2] - f[1]) > 10.0 * smooth + 1e-7
    return out


def crack_count(volume, iso, reconstruction, method, points, normals, *, rays=65,
                width_cells=4.0, iterations=12, step_scale=0.5) -> dict:
    """Depth discontinuities and holes of the surface across x = 0.5 seen by ``method``: per
    surface point, a line of parallel rays (coming in along the normal, tilted towards +x)
    whose targets run across the level boundary, ``width_cells`` finest cells long. Every pair
    of neighbouring rays is refined ``iterations`` times (keeping the half whose depths differ
    more); a pair whose depths still differ by more than 0.005 finest cells, or of which one
    ray is hit and the other not, is a discontinuity (see-through crack or step), not a
    slope."""
    h = volume.level_spacing(volume.num_levels - 1).min()
    x = np.array([1.0, 0.0, 0.0])
    d = unit(-normals + 0.3 * x)
    across = unit(x - (d @ x)[:, None] * d)
    offsets = np.linspace(-0.5, 0.5, rays) * width_cells * h
    base = points - 1.5 * d

    def hits(origin, direction):
        r = trace(volume, f32(origin), f32(direction), field="f", isovalue=iso, method=method,
                  reconstruction=reconstruction, step_scale=step_scale)
        return r.hit, r.t

    o = (base[:, None, :] + offsets[None, :, None] * across[:, None, :]).reshape(-1, 3)
    hit, t = hits(o, np.repeat(d, rays, axis=0))
    hit, t = hit.reshape(len(points), rays), t.reshape(len(points), rays)
    line = np.repeat(np.arange(len(points)), rays - 1)
    lo, hi = np.tile(offsets[:-1], len(points)), np.tile(offsets[1:], len(points))
    h_lo, h_hi = hit[:, :-1].ravel(), hit[:, 1:].ravel()
    t_lo, t_hi = t[:, :-1].ravel(), t[:, 1:].ravel()

    def gap(h1, t1, h2, t2):
        return np.where(h1 != h2, np.inf, np.where(h1 & h2, np.abs(t1 - t2), 0.0))

    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        hm, tm = hits(base[line] + mid[:, None] * across[line], d[line])
        left = gap(h_lo, t_lo, hm, tm) >= gap(hm, tm, h_hi, t_hi)
        hi, h_hi, t_hi = (np.where(left, mid, hi), np.where(left, hm, h_hi),
                          np.where(left, tm, t_hi))
        lo, h_lo, t_lo = (np.where(left, lo, mid), np.where(left, h_lo, hm),
                          np.where(left, t_lo, tm))
    final = gap(h_lo, t_lo, h_hi, t_hi)
    return {"discontinuities": int(np.sum(final > 0.005 * h)), "pairs": int(len(final)),
            "holes": int(np.sum(~hit))}


def crack_lines(name, lines, count, h, seed=43):
    """Rays along +-x (alternating per line) through the level boundary plane x = 0.5: per
    line, ``count`` points spread over one finest cell ``h`` across the surface's section by
    that plane (along the section's normal). Where the two levels' surfaces do not meet there,
    some of these rays pass through the crack between them."""
    p, nrm = _boundary_points(name, np.random.default_rng(seed), lines, 0.02 * h)
    p[:, 0] = 0.5
    nrm[:, 0] = 0.0
    nrm = unit(nrm)
    offsets = np.linspace(-0.5, 0.5, count) * h
    q = (p[:, None, :] + offsets[None, :, None] * nrm[:, None, :]).reshape(-1, 3)
    sign = np.repeat(np.where(np.arange(lines) % 2 == 0, 1.0, -1.0), count)
    d = np.zeros_like(q)
    d[:, 0] = sign
    return q - 0.75 * d, d


def case_level_boundary(quick):
    """Sphere and torus rays aimed at surface points within 1.5 finest cells of the level
    boundary x = 0.5, coming in near the normal, and rays along +-x through the boundary
    plane next to the surface (:func:`crack_lines`): every method against the reference of
    each reconstruction. Cracks: hits on a jump of the field (:func:`wall_hits`: the crack
    between levels, closed by a wall) per method; for exact, ``finest`` against ``basis`` ray
    by ray (no hit, or a depth more than 0.05 finest cells apart); in the full version also
    the depth discontinuities and holes between neighbouring rays (:func:`crack_count`)."""
    rows = []
    for name in ("sphere", "torus"):
        vol = datasets.ANALYTIC[name]()
        iso = datasets.ISOVALUES[name]
        h = vol.level_spacing(1).min()
        rng = np.random.default_rng(41)
        n = 96 if quick else 384
        p, nrm = _boundary_points(name, rng, n, 1.5 * h)
        d = unit(-nrm + 0.4 * rng.normal(size=nrm.shape))
        o1, d1 = p - 1.5 * d, d
        o2, d2 = crack_lines(name, 8 if quick else 24, 25 if quick else 49, h)
        o, d = f32(np.concatenate([o1, o2])), f32(np.concatenate([d1, d2]))
        exact = {r: trace(vol, o, d, field="f", isovalue=iso, method="exact", reconstruction=r)
                 for r in ("basis", "finest")}
        both = exact["basis"].hit & exact["finest"].hit
        missing = exact["basis"].hit != exact["finest"].hit
        apart = np.abs(np.where(both, exact["basis"].t, 0.0) - np.where(both, exact["finest"].t,
                                                                          0.0))
        jumps = apart > 0.05 * h
        versus = {"finest_vs_basis_missing": int(missing.sum()),
                  "finest_vs_basis_jumps": int(jumps.sum()),
                  "finest_vs_basis_max_cells": float(apart.max() / h)}
        q, qn = _boundary_points(name, np.random.default_rng(42), 12, 0.25 * h)

        def extra(ref, res, method, rec):
            walls = wall_hits(ref.field, ref.o, ref.d, res.t, res.hit)
            out = {"cracks": int(walls.sum())}
            if method == "exact":
                out.update(versus)
            if not quick:
                out.update(crack_count(vol, iso, rec, method, q, qn))
            return out

        out = measure(f"level boundary: {name}", vol, o, d, iso, extra=extra)
        for r in out:
            m = r["metrics"]
            text = f"{m['cracks']} hits on a crack wall"
            if "discontinuities" in m:
                text += (f", {m['discontinuities']} depth discontinuities and {m['holes']} "
                         f"holes in {m['pairs']} neighbour pairs")
            if r["method"] == "exact" and r["reconstruction"] == "finest":
                text += (f"; vs basis: {versus['finest_vs_basis_missing']} hit/miss differ, "
                         f"{versus['finest_vs_basis_jumps']} depths > 0.05 cells apart (max "
                         f"{versus['finest_vs_basis_max_cells']:.2f})")
            r["notes"] = "; ".join(filter(None, [r["notes"], text]))
        rows += out
    return rows


# ---------------------------------------------------------------------- cases: planes, inside

def _plane_rays(vol, rng, count):
    """Rays along +-x, +-y, +-z lying on two planes at once (cell faces and cell-centre planes
    of both levels, the level boundary x = 0.5, kd split planes inside the domain), and
    diagonal rays inside one such plane."""
    tree = KDTree(vol.select_fields(["f"]), leaf_cells=4)
    inner = (tree.node_code & 3) != 3
    splits = [np.unique(tree.node_split[inner & ((tree.node_code & 3) == a)]) for a in range(3)]
    lo, hi = vol.bounds
    planes = []
    for a in range(3):
        # Cell faces and cell-centre planes of every level: multiples of half a cell.
        lattice = [lo[a] + np.arange(0.0, (hi[a] - lo[a]) / (h[a] / 2) + 0.5) * (h[a] / 2)
                   for h in (vol.level_spacing(l) for l in range(vol.num_levels))]
        p = np.unique(np.concatenate(lattice + [splits[a], [0.5]]))
        # Not the domain's faces: those have a case of their own (case_domain_faces).
        planes.append(p[(p > lo[a]) & (p < hi[a])])
    o, d = [], []
    for _ in range(count):
        a = rng.integers(3)
        b, c = [x for x in range(3) if x != a]
        start = np.zeros(3)
        # Near the middle most of the time, so most rays meet the surface.
        for axis in (b, c):
            near = planes[axis][np.abs(planes[axis] - 0.5) < 0.35]
            pool = near if rng.random() < 0.85 else planes[axis]
            start[axis] = rng.choice(pool)
        sign = rng.choice([-1.0, 1.0])
        start[a] = 0.5 - sign * 1.5
        direction = np.zeros(3)
        direction[a] = sign
        o.append(start)
        d.append(direction)
    for _ in range(count // 3):
        a = rng.integers(3)
        start = CENTRE + (rng.random(3) - 0.5) * 0.5
        start[a] = rng.choice(planes[a][np.abs(planes[a] - 0.5) < 0.35])
        direction = rng.normal(size=3)
        direction[a] = 0.0
        o.append(start - 1.5 * unit(direction))
        d.append(unit(direction))
    # Along the level boundary x = 0.5.
    for y in np.linspace(0.2, 0.8, 4):
        o.append([0.5, y, -1.0])
        d.append([0.0, 0.0, 1.0])
    return f32(o), f32(d)


def case_planes(quick):
    """Rays exactly on grid planes and along the axes (sphere, torus, ramp)."""
    rows = []
    names = ("sphere", "ramp") if quick else ("sphere", "torus", "ramp")
    for name in names:
        vol = datasets.ANALYTIC[name]()
        o, d = _plane_rays(vol, np.random.default_rng(51), 36 if quick else 150)
        rows += measure(f"planes: axis rays on grid planes ({name})", vol, o, d,
                        datasets.ISOVALUES[name])
    return rows


def face_rays(side, count=4):
    """Rays lying in the domain's lower (``side`` 0) or upper (1) faces x, y, z = ``side``,
    along each of the two other axes, both ways, through the ramp's surface."""
    o, d = [], []
    for a in range(3):
        for b in range(3):
            if b == a:
                continue
            c = 3 - a - b
            for u in np.linspace(0.3, 0.7, count):
                for sign in (1.0, -1.0):
                    start = np.zeros(3)
                    start[a] = side
                    start[c] = u
                    start[b] = 0.5 - 1.5 * sign
                    direction = np.zeros(3)
                    direction[b] = sign
                    o.append(start)
                    d.append(direction)
    return f32(o), f32(d)


def case_domain_faces(side, quick):
    """Rays lying exactly in the faces of the domain (the unit cube), through the ramp's
    tilted plane, which meets every face: the reconstructed field is defined on the closed
    domain (the slow twins give values there), so the crossings on the lower faces
    (x, y, z = 0, ``side`` 0) and on the upper faces (x, y, z = 1, ``side`` 1) must both be
    found."""
    o, d = face_rays(side, 2 if quick else 6)
    label = "lower" if side == 0 else "upper"
    return measure(f"planes: rays in the domain's {label} faces (ramp)", datasets.ramp(), o, d,
                   datasets.ISOVALUES["ramp"])


def case_boundary_crossing(quick):
    """Rays through the cube's centre, where the ramp's surface meets the level boundary
    x = 0.5, along small integer directions ``k`` (origins ``c - 0.5 k``, exact in float32).
    The basis reconstruction is continuous there. The finest one jumps at x = 0.5 from
    exactly 0 (the isovalue: the coarse level's trilinear interpolation of a linear field is
    exact) to 0.0125 (the fine grid's clamped outer half cell): the jump is the crossing."""
    ks = np.array([(x, y, z) for x in (-2, -1, 1, 2) for y in range(-2, 3) for z in range(-2, 3)],
                  dtype=np.float64)
    if quick:
        ks = ks[np.random.default_rng(111).choice(len(ks), 32, replace=False)]
    return measure("level boundary: crossing exactly on the boundary plane (ramp)",
                   datasets.ramp(), CENTRE - 0.5 * ks, ks, datasets.ISOVALUES["ramp"])


def case_inside(quick):
    """Rays starting inside the volume (outside the surface, near the cube's corners) and
    inside the sphere's surface: at its centre, on a cell centre, on the level boundary, on a
    cell face, and at random points."""
    vol = datasets.sphere()
    rng = np.random.default_rng(61)
    n = 16 if quick else 64
    outside = rng.choice([0.06, 0.94], size=(n, 3)) + rng.normal(scale=0.02, size=(n, 3))
    d_out = unit(CENTRE + rng.normal(scale=0.1, size=(n, 3)) - outside)
    inside = CENTRE + (rng.random((n, 3)) - 0.5) * 0.4
    inside[:4] = [CENTRE, [17.5 / 32, 15.5 / 32, 16.5 / 32], [0.5, 0.45, 0.55],
                  [0.4375, 0.5, 0.5625]]
    d_in = unit(rng.normal(size=(n, 3)))
    d_in[:3] = [[1, 0, 0], [0, -1, 0], [0, 0, 1]]
    o = f32(np.concatenate([outside, inside]))
    d = f32(np.concatenate([d_out, d_in]))
    return measure("inside: rays start inside the volume / the surface", vol, o, d,
                   datasets.ISOVALUES["sphere"])


# ---------------------------------------------------------------------- cases: parameters, data

def case_step_scale(quick):
    """The sampling methods from 0.001 to 8 finest cells per step on random sphere rays:
    every call returns, hit depths are finite, and the misses grow with the step."""
    vol = datasets.sphere()
    rng = np.random.default_rng(81)
    o, d = random_rays(rng, 48 if quick else 192, 0.4)
    steps = (0.001, 1.0, 8.0) if quick else (0.001, 0.01, 0.1, 0.5, 1.0, 2.0, 4.0, 8.0)
    rows = []
    ref = dense_reference(DenseField(vol, "f", True), o, d, datasets.ISOVALUES["sphere"])
    for s in steps:
        for method in METHODS:
            t0 = time.perf_counter()
            res = trace_reference(vol, ref, method, "basis", s)
            seconds = time.perf_counter() - t0
            bad = int(np.sum(res.hit & ~np.isfinite(res.t)))
            rows.append(score(f"step_scale {s:g}", vol, ref, res, method, "basis", s,
                              notes=f"{seconds:.2f} s, max {res.samples.max()} samples/ray",
                              metrics={"seconds": seconds, "infinite_hit_t": bad,
                                       "max_samples": int(res.samples.max())}))
    return rows


def nan_volume(seed=0, count=8):
    """The sphere dataset with ``count`` NaN cells whose centres lie within 0.3 cells of the
    isosurface (leaf cells of both levels, no two neighbours); returns the volume and the
    cells' centres."""
    vol = datasets.sphere()
    rng = np.random.default_rng(seed)
    iso = datasets.ISOVALUES["sphere"]
    grids = [g.as_dict() for g in vol.grids]
    centres = []
    for gi, g in enumerate(vol.grids):
        f = g.fields["f"].copy()
        h = g.spacing[0]
        cand = np.argwhere((np.abs(f - iso) < 0.3 * h) & vol.leaf_mask(gi))
        chosen = []
        for ijk in cand[rng.permutation(len(cand))]:
            if all(np.max(np.abs(ijk - c)) > 2 for c in chosen):
                chosen.append(ijk)
            if len(chosen) == count // 2:
                break
        for i, j, k in chosen:
            f[i, j, k] = np.nan
            centres.append([c[x] for c, x in zip(g.cell_centers(), (i, j, k))])
        grids[gi]["fields"] = {"f": f}
    return AMRVolume.from_grids(grids, allow_nonfinite=True), np.array(centres)


def case_nan(quick):
    """NaN cells on the sphere's surface (missing data): rays through the NaN cells and
    random rays. No crash, finite outputs, exact agrees with the reference (basis: the cells
    get no weight; finest: rays whose reference meets a NaN value are not counted), and no hit
    more than 2 cells from a NaN cell that the reference does not have."""
    vol, nan_centres = nan_volume()
    rng = np.random.default_rng(91)
    k = 4 if quick else 16
    targets = np.repeat(nan_centres, k, axis=0)
    targets += rng.normal(scale=0.01, size=targets.shape)
    dirs = unit(rng.normal(size=(len(targets), 3)))
    o1, d1 = f32(targets - 2.0 * dirs), f32(dirs)
    o2, d2 = random_rays(rng, 32 if quick else 128, 0.4)
    o, d = np.concatenate([o1, o2]), np.concatenate([d1, d2])
    h = vol.level_spacing(0).max()

    def extra(ref, res, method, rec):
        p = ref.o + np.where(res.hit, res.t, 0.0)[:, None] * ref.d
        far = np.min(np.linalg.norm(p[:, None, :] - nan_centres[None], axis=2), axis=1) > 2 * h
        false_far = res.hit & far & ~ref.crossed & ~ref.touchy
        return {"false_far": int(false_far.sum()), "nan_cells": len(nan_centres)}

    rows = measure("NaN cells on the surface", vol, o, d, datasets.ISOVALUES["sphere"],
                   extra=extra)
    for r in rows:
        r["notes"] = "; ".join(filter(None, [r["notes"], f"{r['metrics']['false_far']} false "
                                             f"hits > 2 cells from NaN"]))
    return rows


def case_nan_centre_lines(quick):
    """Rays along +-x, +-y, +-z through the NaN cells' centres and 1e-5 or 1e-4 cells beside
    those lines (sampled methods: jitter 0). On such a line only the cells in line with the
    NaN cell have weight, so the basis blend's denominator goes to 0 at the NaN cell's centre:
    exactly on the line the field is undefined there (the reference leaves those rays out),
    beside it the field is defined, and it changes side of the isovalue across the NaN cell
    when the cells before and after it lie on different sides."""
    vol, nan_centres = nan_volume()
    h = vol.level_spacing(0).max()
    o, d = [], []
    for c in nan_centres:
        for a in range(3):
            b, e = [x for x in range(3) if x != a]
            for eps in (0.0, 1e-5, 1e-4):
                for sign in (1.0, -1.0):
                    start = c.copy()
                    start[b] += eps * h
                    start[e] += 0.7 * eps * h
                    start[a] = c[a] - sign * 1.5
                    direction = np.zeros(3)
                    direction[a] = sign
                    o.append(start)
                    d.append(direction)
    o, d = f32(o), f32(d)
    return measure("NaN cells: rays along the lines through their centres", vol, o, d,
                   datasets.ISOVALUES["sphere"], trace_kw={"jitter": np.zeros(len(o))})


def many_grids_volume(shape=(25, 20, 20), h0=0.05):
    """``prod(shape)`` level-1 grids of 2^3 cells, one in each cell of a level-0 grid of
    ``shape`` cells of size ``h0``, carrying the sphere distance around the middle of the
    box (isovalue 0.3)."""
    centre = np.array(shape) * h0 / 2

    def values(origin, n, h):
        axes = [origin[a] + (np.arange(n[a]) + 0.5) * h for a in range(3)]
        p = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        return np.linalg.norm(p - centre, axis=-1)

    grids = [{"level": 0, "origin": (0.0, 0.0, 0.0), "spacing": h0,
              "fields": {"f": values((0.0, 0.0, 0.0), shape, h0)}}]
    for i in range(shape[0]):
        for j in range(shape[1]):
            for k in range(shape[2]):
                origin = (i * h0, j * h0, k * h0)
                grids.append({"level": 1, "origin": origin, "spacing": h0 / 2,
                              "fields": {"f": values(origin, (2, 2, 2), h0 / 2)}})
    return AMRVolume.from_grids(grids), centre


def case_many_grids(quick):
    """The sphere on >= 10^4 tiny grids: random rays through the sphere and rays grazing it.
    (``finest`` is discontinuous at every grid face here: each 2^3 grid is extended as a
    constant over its outer half cells.)"""
    vol, centre = many_grids_volume()
    rng = np.random.default_rng(101)
    n = 96 if quick else 200
    o1, d1 = random_rays(rng, n, 0.35, centre=centre)
    o2, d2 = random_rays(rng, n // 2, 0.6, centre=centre)
    o, d = np.concatenate([o1, o2]), np.concatenate([d1, d2])
    return measure(f"10^4 grids ({len(vol.grids)} grids of 2^3 cells)", vol, o, d, 0.3,
                   ref_kw={"twin_points": 6 if quick else 12})


