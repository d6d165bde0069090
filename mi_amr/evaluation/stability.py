"""Stability where methods fail (issue 5): the inputs that break isosurface methods, and every
method measured on each.

:func:`run` builds each case, computes a dense float64 reference for its rays and traces them
with every method (``exact``, ``bisect``, ``adaptive``, ``uniform``) and, where the two differ,
both reconstructions. It returns one row per (case, method, reconstruction);
:func:`stability_table` turns the rows into a Markdown table, one row per case and one column
per method.

>>> from mi_amr import stability
>>> rows = stability.run(quick=True)          # under a minute; quick=False: a few minutes
>>> print(stability.stability_table(rows))

Cases (keys of :data:`CASES`):

* ``thin_spike``, ``thin_sheet``: the one-cell spike at isovalue 0.75; a sheet
  ``exp(-(s / w)^2)`` (``s`` the distance to a tilted plane, ``w`` a finest cell) at isovalue
  0.85, a slab thinner than a step. Sampled methods step one finest cell.
* ``grazing``: rays just inside and just outside the tangent of the sphere's reconstructed
  surface (the tangent offset searched on the reference).
* ``tangent``, ``spike_maximum``: the isovalue at a local extremum: the tangent rays
  themselves (their minimum of the field is the isovalue), and rays through the spike's centre
  at isovalue 1.0, the field's maximum. A touching ray must be hit.
* ``level_boundary``: sphere and torus rays across the level boundary x = 0.5; cracks of the
  finest reconstruction (hits on the walls that close them, depths apart from basis).
  ``boundary_crossing``: the ramp's surface meeting the boundary plane exactly.
* ``planes``: rays along the axes exactly on cell faces, cell-centre planes, the level
  boundary and kd split planes; diagonal rays inside such planes. ``lower_faces``,
  ``upper_faces``: rays lying in the domain's faces.
* ``inside``: rays starting inside the volume and inside the surface; ``inside_ball``: a
  camera inside the ball of the sphere_wake scene (Mitsuba).
* ``out_of_range``: no hit, and a frame far faster than a normal one (Mitsuba).
* ``step_scale``: the sampling methods from 0.001 to 8 cells per step.
* ``nan``, ``nan_centre_lines``: a few NaN cells on the sphere's surface (missing data): rays
  through them, and rays along the lines through their centres, where the basis blend's
  weights vanish.
* ``many_grids``: the sphere on 10^4 level-1 grids of 2^3 cells.
* ``temporal``: a camera orbit around the torus (Mitsuba), each position rendered twice with
  different jitter (flicker), and the hit masks of consecutive positions compared.

Rows: ``case``, ``method``, ``reconstruction``, ``rays``, ``missed`` (rays the reference
crosses that get no hit, or only one beyond the first crossing), ``false`` (hits on rays the
reference does not cross, or before its first crossing), ``max_depth_error_cells`` (finest
cells, over the rays hit where expected), ``notes``, and ``expected`` (rays the reference
crosses) and ``metrics`` (case-specific numbers: cracks, timings, flicker). The Mitsuba cases
have no ray reference: their ``missed`` and ``false`` are ``None``.

The reference (:func:`dense_reference`) samples the reconstructed field every
:data:`REF_STEP` finest cells along each ray (finer where a case asks), brackets the first
change of side of the isovalue, searches sampled dips for crossings hidden between samples, and
bisects on float64 values. The values come from :class:`DenseField`, a vectorised float64 copy of
the sums computed by the slow twins :func:`~mi_amr.reconstruct.basis_point_reference` and
:func:`~mi_amr.reconstruct.finest_point_reference`, which are evaluated too at the crossings
and a sample of points (``metrics["twin_difference"]``). Rays come as float32 (what the kernels
see); a ray passing the isovalue within :data:`MARGIN` without clearly crossing it is
"touchy" and left out of the counts, except in the extremum cases, where a ray touching the
surface (within :data:`TANGENT`) must be hit.

All positions are the volume's world space; depth errors are in finest cells.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np

from mi_amr.synthetic import datasets
from mi_amr.core.kdtree import KDTree
from mi_amr.params import METHODS
from mi_amr.kernels.trace import trace
from mi_amr.core.field64 import Field64 as DenseField
from mi_amr.core.volume import AMRVolume

MARGIN = 1e-5          # field units: closer to the isovalue than this is undecided in float32
TANGENT = 2e-7         # field units: a ray whose extreme value is this close touches the surface
REF_STEP = 0.1         # finest cells between reference samples
EXACT_DEPTH_TOL = 1e-3  # finest cells: what exact must meet on clear crossings
SAMPLED = ("bisect", "adaptive", "uniform")
CENTRE = np.array([0.5, 0.5, 0.5])


# ---------------------------------------------------------------------- the dense reference

def f32(a) -> np.ndarray:
    """``a`` rounded to float32 (what the kernels see), as float64."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def box_interval(lo, hi, o, d):
    """``(t_in, t_out)`` of rays ``o + t d`` (``(N, 3)``) in the box ``[lo, hi]``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_a = (lo - o) / d
        t_b = (hi - o) / d
    inside = (o >= lo) & (o <= hi)
    near = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t_a, t_b))
    far = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t_a, t_b))
    return near.max(axis=1), far.min(axis=1)


@dataclass
class Reference:
    """The first crossing of the isovalue along each ray by the float64 field.

    Per ray: ``t`` (inf: none); ``dmin``, the extreme of ``(value - iso) * side`` (``side``:
    the sign at the ray's first sample) up to the end of the first crossing, with ``t_min``
    where it is (negative: how deep the ray gets past the isovalue; positive: how close it
    comes without crossing); ``touchy``: the ray comes within ``margin`` of the isovalue
    before crossing it, starts on it, or crosses it by less; ``undefined``: the field has a gap
    (NaN) inside the volume before the first crossing. ``twin_difference``: largest
    difference from the slow twin at the crossings and a sample of points.
    """

    field: DenseField
    o: np.ndarray
    d: np.ndarray
    iso: float
    t: np.ndarray
    t_min: np.ndarray
    dmin: np.ndarray
    touchy: np.ndarray
    undefined: np.ndarray
    twin_difference: float

    @property
    def crossed(self) -> np.ndarray:
        return np.isfinite(self.t)

    @property
    def clear(self) -> np.ndarray:
        return ~self.touchy & ~self.undefined


def dense_reference(field: DenseField, o, d, iso: float, *, margin: float = MARGIN,
                    step_cells: float = REF_STEP, t_start: float = 0.0, focus=None,
                    twin_points: int = 48, seed: int = 0) -> Reference:
    """The reference for rays ``o + t d`` (rounded to float32), ``t >= t_start``, inside the
    volume's bounds. ``focus = (lo, hi, step_cells)`` adds samples that much finer inside the
    box ``[lo, hi]`` (a thin feature). The finest reconstruction jumps at grid faces, so there
    each ray is also sampled just before and after every lattice plane it crosses (a dip into
    the isovalue right before a jump is no local minimum between samples). See
    :class:`Reference`."""
    o, d = f32(o), f32(d)
    n = len(o)
    h = field.h_fine
    t_in, t_out = box_interval(*field.volume.bounds, o, d)
    t_in = np.maximum(t_in, t_start)
    dn = np.linalg.norm(d, axis=1)
    per_ray = []
    for i in range(n):
        if not t_in[i] < t_out[i]:
            per_ray.append(np.zeros(0))
            continue
        count = int(np.ceil((t_out[i] - t_in[i]) * dn[i] / (step_cells * h))) + 1
        ts = np.linspace(t_in[i], t_out[i], count)
        if focus is not None:
            a, b = box_interval(focus[0], focus[1], o[i:i + 1], d[i:i + 1])
            a, b = max(a[0], t_in[i]), min(b[0], t_out[i])
            if a < b:
                extra = int(np.ceil((b - a) * dn[i] / (focus[2] * h))) + 1
                ts = np.unique(np.concatenate([ts, np.linspace(a, b, extra)]))
        if not field.basis:
            ts = np.unique(np.concatenate([ts, _plane_params(field, o[i], d[i], t_in[i],
                                                             t_out[i])]))
        per_ray.append(ts)
    counts = np.array([len(t) for t in per_ray])
    rays = np.repeat(np.arange(n), counts)
    t_all = np.concatenate(per_ray) if counts.sum() else np.zeros(0)
    v_all = field(o[rays] + t_all[:, None] * d[rays])
    values = np.split(v_all, np.cumsum(counts)[:-1])

    def value(r, t):
        return field(o[r] + t[:, None] * d[r])

    a_br, b_br = np.full(n, np.nan), np.full(n, np.nan)
    side = np.ones(n)
    touchy = np.zeros(n, dtype=bool)
    undefined = np.zeros(n, dtype=bool)
    dmin, t_min = np.full(n, np.inf), np.full(n, np.nan)
    dips = []          # (ray, lo, hi, before the first sampled crossing?)
    for i, (t, v) in enumerate(zip(per_ray, values)):
        ok = np.isfinite(v)
        if ok.sum() < 2:
            continue
        first, last = np.flatnonzero(ok)[[0, -1]]
        holes = ~ok[first:last + 1]
        t, v = t[ok], v[ok]
        nonzero = np.flatnonzero(v != iso)
        if len(nonzero) == 0:
            touchy[i] = True
            continue
        side[i] = np.sign(v[nonzero[0]] - iso)
        dist = (v - iso) * side[i]
        touchy[i] |= abs(dist[0]) < margin
        change = np.flatnonzero(dist < 0)
        stop = change[0] if len(change) else len(t)
        undefined[i] = holes[:stop + 1].any() if len(holes) else False
        if len(change):
            a_br[i], b_br[i] = t[stop - 1], t[stop]
            back = np.flatnonzero(dist[stop:] >= 0)
            end = stop + (back[0] if len(back) else len(t) - stop)
            j = stop + int(np.argmin(dist[stop:end]))
            dmin[i], t_min[i] = dist[j], t[j]
            dips.append((i, t[max(j - 1, 0)], t[min(j + 1, len(t) - 1)], False))
        else:
            j = int(np.argmin(dist))
            dmin[i], t_min[i] = dist[j], t[j]
        # Sampled local minima before the crossing near enough to the isovalue that the field,
        # changing no faster than twice its sampled rate, could reach it between samples.
        if stop >= 3:
            mid = np.arange(1, min(stop, len(t) - 1))
            reach = 2 * np.maximum(np.abs(dist[mid - 1] - dist[mid]),
                                   np.abs(dist[mid + 1] - dist[mid]))
            local = (dist[mid] <= dist[mid - 1]) & (dist[mid] <= dist[mid + 1]) & \
                (dist[mid] < reach + margin)
            for j in mid[local]:
                dips.append((i, t[j - 1], t[j + 1], True))
    if dips:
        r, lo, hi, before = (np.array(x) for x in zip(*dips))
        tm, dm = _minimise(value, r, lo, hi, iso, side[r])
        # First the depths of the sampled crossings, then the dips before them, in order.
        for ray, t_d, d_d in zip(r[~before], tm[~before], dm[~before]):
            if d_d < dmin[ray]:
                dmin[ray], t_min[ray] = d_d, t_d
        for j in np.flatnonzero(before)[np.argsort(tm[before], kind="stable")]:
            ray, t_d, d_d = r[j], tm[j], dm[j]
            if d_d < 0 and not t_d >= a_br[ray]:
                # The dip crosses: the first crossing lies before the sampled one.
                a_br[ray], b_br[ray] = lo[j], t_d
                dmin[ray], t_min[ray] = d_d, t_d
            elif not np.isfinite(a_br[ray]) and d_d < dmin[ray]:
                dmin[ray], t_min[ray] = d_d, t_d
            if abs(d_d) < margin and not t_d > a_br[ray]:
                touchy[ray] = True
    crossed = np.isfinite(a_br)
    touchy |= crossed & (dmin > -margin)
    t_first = _bisect(value, a_br, b_br, iso)
    # The twin at the crossings and at a few samples.
    rng = np.random.default_rng(seed)
    check = [o[crossed] + t_first[crossed, None] * d[crossed]]
    if len(t_all):
        pick = rng.choice(len(t_all), size=min(twin_points, len(t_all)), replace=False)
        check.append(o[rays[pick]] + t_all[pick, None] * d[rays[pick]])
    points = np.concatenate(check)
    if len(points) > twin_points:
        points = points[rng.choice(len(points), size=twin_points, replace=False)]
    return Reference(field=field, o=o, d=d, iso=float(iso), t=t_first, t_min=t_min, dmin=dmin,
                     touchy=touchy, undefined=undefined,
                     twin_difference=field.twin_difference(points))


def _plane_params(field, o, d, t_in, t_out):
    """Parameters just before and after each crossing of a lattice plane (cell faces of every
    level) by the ray ``o + t d`` on ``(t_in, t_out)``."""
    out = []
    for h in field.level_spacings:
        for a in range(3):
            if d[a] == 0.0:
                continue
            ends = (np.array([o[a] + t_in * d[a], o[a] + t_out * d[a]]) - field.anchor[a]) / h[a]
            k = np.arange(np.floor(ends.min()), np.ceil(ends.max()) + 1)
            out.append((field.anchor[a] + k * h[a] - o[a]) / d[a])
    if not out:
        return np.zeros(0)
    t = np.concatenate(out)
    t = t[(t > t_in) & (t < t_out)]
    eps = 1e-9 * field.h_fine / np.linalg.norm(d)
    return np.clip(np.concatenate([t - eps, t + eps]), t_in, t_out)


def _minimise(value, rays, lo, hi, iso, side, iterations=14, k=16):
    """Minimum of ``(value - iso) * side`` on ``[lo, hi]`` per entry (a unimodal stretch):
    ``k + 1`` samples, then the stretch between the neighbours of the smallest, ``iterations``
    times (each shrinks it ``k / 2``-fold). Returns ``(t, minimum)``."""
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    frac = np.linspace(0.0, 1.0, k + 1)
    for _ in range(iterations):
        ts = lo[:, None] + (hi - lo)[:, None] * frac[None, :]
        f = (value(np.repeat(rays, k + 1), ts.ravel()).reshape(ts.shape) - iso) * side[:, None]
        j = np.argmin(np.where(np.isnan(f), np.inf, f), axis=1)
        lanes = np.arange(len(rays))
        lo, hi = ts[lanes, np.maximum(j - 1, 0)], ts[lanes, np.minimum(j + 1, k)]
    t = 0.5 * (lo + hi)
    return t, (value(rays, t) - iso) * side


def _bisect(value, a, b, iso, k=16):
    """The first crossing of ``iso`` inside ``[a, b]`` per ray (inf where ``a`` is NaN):
    ``k``-section on float64 values (``value(a)`` and ``value(b)`` on either side) down to
    1e-13 of the stretch."""
    out = np.full(len(a), np.inf)
    todo = np.flatnonzero(np.isfinite(a))
    if len(todo) == 0:
        return out
    A, B = a[todo], b[todo]
    s_a = np.sign(value(todo, A) - iso)
    frac = np.linspace(0.0, 1.0, k + 1)
    lanes = np.arange(len(todo))
    for _ in range(12):
        ts = A[:, None] + (B - A)[:, None] * frac[None, :]
        f = value(np.repeat(todo, k + 1), ts.ravel()).reshape(ts.shape) - iso
        other = np.sign(f) != s_a[:, None]
        other[:, -1] = True
        j = np.argmax(other[:, 1:], axis=1) + 1
        A, B = ts[lanes, j - 1], ts[lanes, j]
    out[todo] = 0.5 * (A + B)
    return out


# ---------------------------------------------------------------------- scoring

def _trace(volume, ref, method, reconstruction, step_scale, **kw):
    return trace(volume, ref.o, ref.d, field="f", isovalue=ref.iso, method=method,
                 reconstruction=reconstruction, step_scale=step_scale, **kw)


def _late_tolerance(volume, method, step_scale) -> float:
    """Finest cells past the reference's crossing that still count as finding it: a step of
    the coarsest level (the adaptive methods step by the leaf's cells) plus one cell."""
    ratio = volume.level_spacing(0).max() / volume.level_spacing(volume.num_levels - 1).min()
    return 1.0 + (0.0 if method == "exact" else step_scale * ratio)


def score(case, volume, ref: Reference, res, method, reconstruction, step_scale, *,
          touch_must_hit=False, notes="", metrics=None) -> dict:
    """One row: ``res`` (a :class:`~mi_amr.rays.TraceResult`) against ``ref``.

    Rays the reference clearly crosses must be hit at the first crossing (a hit more than
    :func:`_late_tolerance` beyond it counts as missed, one as far before it as false); rays it
    clearly does not cross must not be hit. With ``touch_must_hit`` a ray touching the surface
    (``|dmin| <= TANGENT``) must be hit too, where it touches."""
    h = volume.level_spacing(volume.num_levels - 1).min()
    tol = _late_tolerance(volume, method, step_scale) * h
    t_ref = ref.t.copy()
    must = ref.crossed & ref.clear
    must_not = ~ref.crossed & ref.clear
    if touch_must_hit:
        touch = (np.abs(ref.dmin) <= TANGENT) & ~ref.undefined
        t_ref = np.where(touch & ~np.isfinite(t_ref), ref.t_min, t_ref)
        must |= touch
        must_not &= ~touch
    late = must & res.hit & (res.t > t_ref + tol)
    early = must & res.hit & (res.t < t_ref - tol)
    missed = must & (~res.hit | late)
    false = (must_not & res.hit) | early
    good = must & res.hit & ~late & ~early
    err = np.abs(res.t[good] - t_ref[good]) / h
    nonfinite = int(np.sum(np.isnan(res.t) | (res.hit & ~np.all(np.isfinite(res.normal), axis=1))))
    # A hit must lie on the ray inside the volume (the traces start at t = 0).
    t_in, t_out = box_interval(*volume.bounds, ref.o, ref.d)
    slack = 1e-3 * h / np.linalg.norm(ref.d, axis=1)
    outside = int(np.sum(res.hit & ((res.t < np.maximum(t_in, 0.0) - slack) |
                                    (res.t > t_out + slack))))
    excluded = int(np.sum(~(must | must_not)))
    parts = [notes] if notes else []
    if method != "exact":
        parts.append(f"step_scale={step_scale:g}")
    if excluded:
        parts.append(f"{excluded} touchy/undefined rays not counted")
    if late.any():
        parts.append(f"{int(late.sum())} hit a later crossing")
    if early.any():
        parts.append(f"{int(early.sum())} hit before the surface")
    if nonfinite:
        parts.append(f"{nonfinite} non-finite outputs")
    if outside:
        parts.append(f"{outside} hits outside the volume (t out of the ray's range)")
    m = {"expected": int(must.sum()), "late": int(late.sum()), "early": int(early.sum()),
         "excluded": excluded, "nonfinite": nonfinite, "outside": outside,
         "touch_must_hit": touch_must_hit,
         "twin_difference": ref.twin_difference, "step_scale": step_scale,
         "missed_rays": np.flatnonzero(missed).tolist()[:20],
         "false_rays": np.flatnonzero(false).tolist()[:20]}
    m.update(metrics or {})
    return row(case, method, reconstruction, len(ref.t), int(missed.sum()), int(false.sum()),
               float(err.max()) if err.size else 0.0, "; ".join(parts), expected=int(must.sum()),
               metrics=m)


def row(case, method, reconstruction, rays, missed, false, depth, notes, *, expected=None,
        metrics=None) -> dict:
    return {"case": case, "method": method, "reconstruction": reconstruction, "rays": rays,
            "missed": missed, "false": false, "max_depth_error_cells": depth, "notes": notes,
            "expected": expected, "metrics": dict(metrics or {})}


def measure(case, volume, o, d, iso, *, reconstructions=("basis", "finest"), methods=METHODS,
            step_scale=0.5, touch_must_hit=False, notes="", ref_kw=None, trace_kw=None,
            extra=None) -> list:
    """Rows for every method and reconstruction on rays ``o + t d`` at ``iso``. ``extra(ref,
    res, method, reconstruction)`` may add metrics to a row."""
    rows = []
    for rec in reconstructions:
        ref = dense_reference(DenseField(volume, "f", rec == "basis"), o, d, iso,
                              **(ref_kw or {}))
        for method in methods:
            res = _trace(volume, ref, method, rec, step_scale, **(trace_kw or {}))
            metrics = extra(ref, res, method, rec) if extra else None
            rows.append(score(case, volume, ref, res, method, rec, step_scale,
                              touch_must_hit=touch_must_hit, notes=notes, metrics=metrics))
    return rows


# ---------------------------------------------------------------------- volumes and rays

def random_rays(rng, n, spread, centre=CENTRE, distance=2.0):
    """Rays from ``distance`` away through random points within ``spread`` of ``centre``."""
    targets = centre + (rng.random((n, 3)) - 0.5) * 2 * spread
    d = unit(rng.normal(size=(n, 3)))
    return f32(targets - distance * d), f32(d)


def spike_centre(volume):
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
    """Minimum of ``value - iso`` along each ray over ``[t_lo, t_hi]`` (dense samples, then
    :func:`_minimise` around the smallest); returns ``(t, minimum)``."""
    n = len(o)
    count = int(np.ceil((t_hi - t_lo) / (step_cells * field.h_fine))) + 1
    ts = np.linspace(t_lo, t_hi, count)
    v = field((o[:, None, :] + ts[None, :, None] * d[:, None, :]).reshape(-1, 3)).reshape(n, -1)
    j = np.nanargmin(v, axis=1)
    lo, hi = ts[np.maximum(j - 1, 0)], ts[np.minimum(j + 1, count - 1)]
    return _minimise(lambda r, t: field(o[r] + t[:, None] * d[r]), np.arange(n), lo, hi, iso,
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
            res = _trace(field.volume, ref, method, rec, 0.5)
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
    """Points and outward normals of :func:`mi_amr.datasets.torus`'s analytic surface."""
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


# ---------------------------------------------------------------------- cases: Mitsuba

def _mitsuba(variant="llvm_ad_rgb"):
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    return mi


def _camera_key(params):
    return [k for k in params.keys() if k.endswith("to_world") and
            k.rsplit(".", 1)[0] + ".x_fov" in params][0]


def _render(mi, scene, seed=0):
    import drjit as dr

    img = mi.render(scene, spp=1, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return np.array(img, dtype=np.float64)


def _scene_file(name, quick, folder=None):
    """``scenes_xml/NAME.xml`` after :func:`mi_amr.cli.scene_data`; for a quick sphere_wake, a
    copy of that file in ``folder`` reading the ``small`` dataset instead of the default one,
    whose preparation alone (some 13 s) takes a good part of the quick version's minute."""
    from pathlib import Path

    from mi_amr.workflows import project
    from mi_amr.evaluation.references import scene_path

    project.ensure_scene_data(verbose=False)
    path = scene_path(name)
    if name != "sphere_wake" or not quick:
        return path
    folder = Path(folder)
    data = folder / "sphere_wake_small.npz"
    datasets.sphere_wake("small", progress=False).save(data)
    text = path.read_text()
    for stored, target in (("data/sphere_wake.npz", data.resolve()),
                           ("data/ball.ply", (path.parent / "data" / "ball.ply").resolve())):
        text = text.replace(f'value="{stored}"', f'value="{target}"')
    copy = folder / "sphere_wake.xml"
    copy.write_text(text)
    return copy


def case_inside_ball(quick):
    """The sphere_wake scene with the camera inside the ball (at its centre looking
    downstream, and off-centre looking back), moved through ``mi.traverse``: the render
    completes and every pixel is finite. (Quick: the scene file reads the ``small``
    dataset, see :func:`_scene_file`.)"""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="mi_amr_stability_") as folder:
        return _inside_ball(_scene_file("sphere_wake", quick, folder), 16 if quick else 48)


def _inside_ball(path, res):
    mi = _mitsuba()
    from mi_amr.plugin.scene import load_scene

    rows = []
    for method in METHODS:
        t0 = time.perf_counter()
        scene = load_scene(path, resx=res, resy=res, spp=1, method=method)
        params = mi.traverse(scene)
        key = _camera_key(params)
        bad = 0
        lit = []
        for origin, target in (((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),
                               ((0.1, 0.05, -0.05), (-1.0, 0.2, 0.1))):
            params[key] = mi.Transform4f(mi.ScalarTransform4f().look_at(
                origin=origin, target=target, up=(0, 0, 1)))
            params.update()
            img = _render(mi, scene)
            bad += int(np.sum(~np.isfinite(img)))
            lit.append(float(np.mean(img)))
        seconds = time.perf_counter() - t0
        data = "default data" if path.parent.name == "scenes_xml" else "copy, small data"
        notes = (f"{path.name} ({data}), {res}x{res}, 2 cameras; mean radiance "
                 + ", ".join(f"{x:.3g}" for x in lit))
        if bad:
            notes += f"; {bad} non-finite pixel values"
        rows.append(row("inside: camera inside the ball (sphere_wake)", method, "basis",
                        2 * res * res, None, None, None, notes,
                        metrics={"nonfinite": bad, "mean": lit, "seconds": seconds,
                                 "headline": "finite" if bad == 0 else f"{bad} NaN"}))
    return rows


def case_out_of_range(quick):
    """Isovalues above and below the sphere's data range: no ray is hit (every method), and a
    frame of the analytic sphere scene costs a small fraction of a normal frame (timed after
    a warm-up frame, with the isovalue changed through ``mi.traverse``, no recompilation)."""
    vol = datasets.sphere()
    vmin, vmax = vol.value_range("f")
    rng = np.random.default_rng(71)
    o, d = random_rays(rng, 256, 0.45)
    rows = []
    mi = _mitsuba()
    from mi_amr.plugin.scene import load_scene

    path = _scene_file("analytic_sphere", quick)
    res = 384 if quick else 512
    frames = 3
    for method in METHODS:
        hits = 0
        for iso in (vmax + 1.0, vmin - 1.0):
            for rec in ("basis", "finest"):
                r = trace(vol, o, d, field="f", isovalue=iso, method=method, reconstruction=rec)
                hits += int(r.hit.sum())
        scene = load_scene(path, resx=res, resy=res, spp=1, method=method)
        params = mi.traverse(scene)
        times = {}
        images = {}
        for label, iso in (("normal", datasets.ISOVALUES["sphere"]), ("out", vmax + 1.0)):
            params["integrator.isovalue"] = mi.Float([iso])
            params.update()
            _render(mi, scene)              # warm-up: compile, or reuse the kernel
            t0 = time.perf_counter()
            for k in range(frames):
                images[label] = _render(mi, scene, seed=k + 1)
            times[label] = (time.perf_counter() - t0) / frames
        ratio = times["out"] / times["normal"]
        # Nothing but the background: no pixel of the out-of-range frame is lit.
        blank = bool(np.all(images["out"] == 0.0))
        notes = (f"{4 * len(o)} rays + {res}x{res} frame; frame {times['out'] * 1e3:.1f} ms vs "
                 f"{times['normal'] * 1e3:.1f} ms (ratio {ratio:.2f}); image "
                 f"{'blank' if blank else 'NOT blank'}")
        rows.append(row("iso outside the data range", method, "both", 4 * len(o), 0, hits, 0.0,
                        notes, expected=0,
                        metrics={"frame_ratio": ratio, "frame_ms": times["out"] * 1e3,
                                 "normal_ms": times["normal"] * 1e3, "blank": blank,
                                 "headline": f"{hits} hits, {'blank' if blank else 'NOT blank'},"
                                             f" frame x{ratio:.2f}"}))
    return rows


def _orbit(t, radius=1.75, height=1.0):
    a = 2 * np.pi * t
    return (0.5 + radius * np.cos(a), 0.5 + radius * np.sin(a), 0.5 + height)


def case_temporal(quick):
    """A 16-frame camera orbit around the analytic torus (22.5 degrees per frame). Camera rays
    through the pixel centres come from the scene's sensor, moved through ``mi.traverse``;
    all frames' rays then go through the integrator at once, twice, with different jitter
    (sampler seeds 1 and 2): its hit depths (its kernels, as in
    :func:`mi_amr.reference.hit_buffers`) and its shaded colours (its ``sample``) must not
    change for exact, the jittered methods flicker. Also the fraction of pixels whose hit
    mask changes between consecutive frames."""
    import drjit as dr

    mi = _mitsuba()
    from mi_amr.plugin.scene import load_scene
    from mi_amr.kernels.surface import first_crossing

    path = _scene_file("analytic_torus", quick)
    res = 48 if quick else 96
    frames = 16
    n = res * res
    rows = []
    for method in METHODS:
        scene = load_scene(path, resx=res, resy=res, spp=1, method=method)
        integ = scene.integrator()
        sensor = scene.sensors()[0]
        params = mi.traverse(scene)
        key = _camera_key(params)
        m = integ.m
        cell = integ.dev.min_h_host
        idx = dr.arange(mi.UInt32, n)
        pos = mi.Vector2f(mi.Float(idx % res) + 0.5, mi.Float(idx // res) + 0.5) / res
        origins, directions = [], []
        for f in range(frames):
            params[key] = mi.Transform4f(mi.ScalarTransform4f().look_at(
                origin=_orbit(f / frames), target=(0.5, 0.5, 0.5), up=(0, 0, 1)))
            params.update()
            ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5), pos, mi.Point2f(0.5, 0.5))
            origins.append(np.array(ray.o).T)        # Mitsuba's arrays are (3, N)
            directions.append(np.array(ray.d).T)
        o_np = np.concatenate(origins).astype(np.float32)
        d_np = np.concatenate(directions).astype(np.float32)
        ray = mi.Ray3f(mi.Point3f(o_np[:, 0], o_np[:, 1], o_np[:, 2]),
                       mi.Vector3f(d_np[:, 0], d_np[:, 1], d_np[:, 2]))
        o, dv = integ.frame.ray_to_volume(integ.m, ray.o, ray.d)
        out = []
        for seed in (1, 2):
            sampler = sensor.sampler().fork()
            sampler.seed(seed, frames * n)
            jitter = m.Float(sampler.next_1d())
            c = first_crossing(integ.dev, integ.config(), o, dv, m.Float(0.0), m.Float(dr.inf),
                               jitter, m.Bool(True))
            sampler = sensor.sampler().fork()
            sampler.seed(seed, frames * n)
            L, _, _ = integ.sample(scene, sampler, ray)
            dr.eval(c.t, c.hit, L)
            hit = c.hit.numpy().astype(bool).reshape(frames, n)
            t = np.where(hit, c.t.numpy().reshape(frames, n), np.inf)
            img = np.stack([L.x.numpy(), L.y.numpy(), L.z.numpy()], axis=-1).reshape(frames, n, 3)
            out.append((hit, t, img))
        (h1, t1, i1), (h2, t2, i2) = out
        both = h1 & h2
        changed = (h1 != h2) | (both & (t1 != t2))
        depth = np.abs(np.where(both, t1, 0.0) - np.where(both, t2, 0.0)) / cell
        finite = bool(np.all(np.isfinite(i1)) and np.all(np.isfinite(i2)))
        mask_change = np.mean(h1 != np.roll(h1, -1, axis=0), axis=1)
        metrics = {"flicker_pixels": float(changed.mean()),
                   "flicker_depth_cells": float(depth[changed & both].mean())
                   if np.any(changed & both) else 0.0,
                   "flicker_depth_max_cells": float(depth.max()),
                   "flicker_image": float(np.abs(i1 - i2).mean()),
                   "images_finite": finite,
                   "mask_change_mean": float(mask_change.mean()),
                   "mask_change_max": float(mask_change.max()),
                   "hit_fraction": float(h1.mean())}
        notes = (f"{frames} frames {res}x{res}: two jitters differ on "
                 f"{100 * metrics['flicker_pixels']:.2f}% of pixels (depth change there "
                 f"{metrics['flicker_depth_cells']:.3g} cells on average, at most "
                 f"{metrics['flicker_depth_max_cells']:.3g}; image "
                 f"{metrics['flicker_image']:.3g}); consecutive frames' hit masks change on "
                 f"{100 * metrics['mask_change_mean']:.1f}% (max "
                 f"{100 * metrics['mask_change_max']:.1f}%)")
        if not finite:
            notes += "; NON-FINITE pixels"
        metrics["headline"] = f"flicker {100 * metrics['flicker_pixels']:.2f}% px"
        rows.append(row("temporal: torus orbit, two jitters per frame", method, "basis",
                        frames * n, None, None, None, notes, metrics=metrics))
    return rows


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
            res = _trace(vol, ref, method, "basis", s)
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


# ---------------------------------------------------------------------- running and reporting

CASES = {
    "thin_spike": case_thin_spike,
    "thin_sheet": case_thin_sheet,
    "grazing": case_grazing,
    "tangent": case_tangent,
    "spike_maximum": case_spike_maximum,
    "level_boundary": case_level_boundary,
    "boundary_crossing": case_boundary_crossing,
    "planes": case_planes,
    "lower_faces": functools.partial(case_domain_faces, 0.0),
    "upper_faces": functools.partial(case_domain_faces, 1.0),
    "inside": case_inside,
    "inside_ball": case_inside_ball,
    "out_of_range": case_out_of_range,
    "step_scale": case_step_scale,
    "nan": case_nan,
    "nan_centre_lines": case_nan_centre_lines,
    "many_grids": case_many_grids,
    "temporal": case_temporal,
}


def run(quick: bool = True, cases=None, progress: bool = False) -> list:
    """Measure every method on every case (or the named ones of :data:`CASES`); ``quick``
    uses fewer rays and smaller images (under a minute), the full version a few minutes.
    Returns the rows described in the module docstring; each row's ``metrics["case_seconds"]``
    is its case's run time."""
    rows = []
    for name in (cases or CASES):
        t0 = time.perf_counter()
        out = CASES[name](quick)
        seconds = time.perf_counter() - t0
        for r in out:
            r["metrics"]["case_seconds"] = seconds
            r["metrics"]["case_key"] = name
        if progress:
            print(f"{name}: {seconds:.1f} s", flush=True)
        rows += out
    return rows


def _cell(r) -> str:
    if "headline" in r["metrics"]:
        return r["metrics"]["headline"]
    text = f"{r['missed']}/{r['expected']}"
    if r["expected"]:
        text += f" ({100 * r['missed'] / r['expected']:.0f}%)"
    if r["false"]:
        text += f", {r['false']} false"
    return text


def stability_table(rows) -> str:
    """Markdown: one row per case (and reconstruction), one column per method: missed / rays
    that must be hit (rate), and false hits when there are any; for the Mitsuba cases their
    headline numbers (non-finite pixels; hits, blank image and frame time relative to a
    normal frame; pixels that change with the jitter)."""
    methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    keys = []
    cells = {}
    for r in rows:
        key = r["case"] + (" (finest)" if r["reconstruction"] == "finest" else "")
        if key not in cells:
            keys.append(key)
            cells[key] = {}
        cells[key][r["method"]] = _cell(r)
    lines = ["| case | " + " | ".join(methods) + " |",
             "|---|" + "---|" * len(methods)]
    for key in keys:
        lines.append(f"| {key} | " + " | ".join(cells[key].get(m, "") for m in methods) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m mi_amr.stability",
                                description="Measure every method on the failure cases.")
    p.add_argument("--full", action="store_true", help="the full version (a few minutes)")
    p.add_argument("--case", action="append", choices=list(CASES), help="only these cases")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    rows = run(quick=not args.full, cases=args.case, progress=True)
    print(stability_table(rows))
    print()
    for r in rows:
        print(f"{r['case']} / {r['method']} / {r['reconstruction']}: {r['notes']}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
