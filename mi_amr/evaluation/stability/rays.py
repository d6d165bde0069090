"""The dense float64 ray reference of the stability suite: the first crossing of the isovalue
along each ray by the reconstructed field, evaluated with :class:`DenseField`
(:class:`mi_amr.core.field64.Field64`).

:func:`dense_reference` samples the field every :data:`REF_STEP` finest cells along each ray
(finer where a case asks, and on both sides of every lattice plane for the finest
reconstruction), brackets the first change of side of the isovalue, searches sampled dips for
crossings hidden between samples, and bisects on float64 values. Rays come as float32 (what the
kernels see).

All positions are the volume's world space; ray parameters ``t`` are in units of the ray's
direction vector (world units for unit directions); field values are float64.
"""

from __future__ import annotations

from dataclasses import dataclass, field as dataclass_field

import numpy as np

from mi_amr import tolerances as tol
from mi_amr.core.field64 import Field64


class DenseField(Field64):
    """The float64 model with the renderer's definition of the field next to missing data:
    undefined where the cells with values weigh less than :data:`~mi_amr.tolerances.MIN_COVER`
    (the basis blend; there the exact method draws no surface)."""

    def __init__(self, volume, field: str, basis: bool):
        super().__init__(volume, field, basis, min_weight=tol.MIN_COVER if basis else 0.0)

MARGIN = 1e-5          # field units: closer to the isovalue than this is undecided in float32
TANGENT = 2e-7         # field units: a ray whose extreme value is this close touches the surface
REF_STEP = 0.1         # finest cells between reference samples
CENTRE = np.array([0.5, 0.5, 0.5])   # world: the middle of the analytic datasets' unit cube


def f32(a) -> np.ndarray:
    """``a`` rounded to float32 (what the kernels see), as float64."""
    return np.asarray(a, dtype=np.float32).astype(np.float64)


def unit(v) -> np.ndarray:
    """``v`` (``(..., 3)``) scaled to unit length along its last axis, float64."""
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def box_interval(lo, hi, o, d):
    """``(t_in, t_out)`` of rays ``o + t d`` (``(N, 3)``, world) in the box ``[lo, hi]``."""
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
    """The reference for rays ``o + t d`` (world, rounded to float32), ``t >= t_start``, inside
    the volume's bounds, at isovalue ``iso`` (field units; ``margin`` too). ``step_cells``:
    finest cells between samples; ``focus = (lo, hi, step_cells)`` adds samples that much finer
    inside the box ``[lo, hi]`` (world; a thin feature). The finest reconstruction jumps at grid
    faces, so there each ray is also sampled just before and after every lattice plane it
    crosses (a dip into the isovalue right before a jump is no local minimum between samples).
    ``twin_points`` points (the crossings and random samples, drawn with ``seed``) are checked
    against the slow twin. See :class:`Reference`."""
    o, d = f32(o), f32(d)
    per_ray = _sample_params(field, o, d, t_start, step_cells, focus)
    counts = np.array([len(t) for t in per_ray])
    rays = np.repeat(np.arange(len(o)), counts)
    t_all = np.concatenate(per_ray) if counts.sum() else np.zeros(0)
    v_all = field(o[rays] + t_all[:, None] * d[rays])
    values = np.split(v_all, np.cumsum(counts)[:-1])

    def value(r, t):
        return field(o[r] + t[:, None] * d[r])

    scan = _Scan.empty(len(o))
    for i, (t, v) in enumerate(zip(per_ray, values)):
        _scan_ray(scan, i, t, v, iso, margin)
    _resolve_dips(scan, value, iso, margin)
    crossed = np.isfinite(scan.a)
    scan.touchy |= crossed & (scan.dmin > -margin)
    t_first = bisect_crossings(value, scan.a, scan.b, iso)
    points = _twin_check_points(o, d, crossed, t_first, rays, t_all, twin_points, seed)
    return Reference(field=field, o=o, d=d, iso=float(iso), t=t_first, t_min=scan.t_min,
                     dmin=scan.dmin, touchy=scan.touchy, undefined=scan.undefined,
                     twin_difference=field.twin_difference(points))


def _sample_params(field: DenseField, o, d, t_start, step_cells, focus) -> list:
    """Per ray, the sorted parameters ``t`` at which :func:`dense_reference` samples the field:
    every ``step_cells`` finest cells over the ray's stretch inside the volume's bounds
    (``t >= t_start``), finer inside the ``focus`` box, and (finest reconstruction) on both
    sides of every lattice plane (:func:`_plane_params`). Empty where the ray misses the
    volume. ``o``, ``d``: ``(N, 3)``, world, already rounded to float32."""
    h = field.h_fine
    t_in, t_out = box_interval(*field.volume.bounds, o, d)
    t_in = np.maximum(t_in, t_start)
    dn = np.linalg.norm(d, axis=1)
    per_ray = []
    for i in range(len(o)):
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
    return per_ray


@dataclass
class _Scan:
    """Per-ray state of :func:`dense_reference` while it reads the samples: the bracket
    ``[a, b]`` of the first crossing (ray parameters; NaN: none yet), ``side`` (sign of
    ``value - iso`` at the first sample that is not on the isovalue), ``touchy``,
    ``undefined``, ``dmin`` and ``t_min`` (see :class:`Reference`; field units and ray
    parameter), and ``dips``: ``(ray, lo, hi, before)`` stretches to minimise (``before``: a
    sampled local minimum before the first sampled crossing; otherwise the deepest sample of
    that crossing)."""

    a: np.ndarray
    b: np.ndarray
    side: np.ndarray
    touchy: np.ndarray
    undefined: np.ndarray
    dmin: np.ndarray
    t_min: np.ndarray
    dips: list = dataclass_field(default_factory=list)

    @classmethod
    def empty(cls, n: int) -> "_Scan":
        return cls(a=np.full(n, np.nan), b=np.full(n, np.nan), side=np.ones(n),
                   touchy=np.zeros(n, dtype=bool), undefined=np.zeros(n, dtype=bool),
                   dmin=np.full(n, np.inf), t_min=np.full(n, np.nan))


def _scan_ray(s: _Scan, i: int, t, v, iso, margin):
    """Read ray ``i``'s samples (parameters ``t``, float64 values ``v``, NaN where undefined)
    into ``s``: its side, the bracket of its first sampled crossing and that crossing's deepest
    sample, whether a gap or the isovalue comes first, and the sampled dips before the
    crossing that could hide one (:func:`_sampled_dips`)."""
    ok = np.isfinite(v)
    if ok.sum() < 2:
        return
    first, last = np.flatnonzero(ok)[[0, -1]]
    holes = ~ok[first:last + 1]
    t, v = t[ok], v[ok]
    nonzero = np.flatnonzero(v != iso)
    if len(nonzero) == 0:
        s.touchy[i] = True
        return
    s.side[i] = np.sign(v[nonzero[0]] - iso)
    dist = (v - iso) * s.side[i]
    s.touchy[i] |= abs(dist[0]) < margin
    change = np.flatnonzero(dist < 0)
    stop = change[0] if len(change) else len(t)
    s.undefined[i] = holes[:stop + 1].any() if len(holes) else False
    if len(change):
        s.a[i], s.b[i] = t[stop - 1], t[stop]
        back = np.flatnonzero(dist[stop:] >= 0)
        end = stop + (back[0] if len(back) else len(t) - stop)
        j = stop + int(np.argmin(dist[stop:end]))
        s.dmin[i], s.t_min[i] = dist[j], t[j]
        s.dips.append((i, t[max(j - 1, 0)], t[min(j + 1, len(t) - 1)], False))
    else:
        j = int(np.argmin(dist))
        s.dmin[i], s.t_min[i] = dist[j], t[j]
    if stop >= 3:
        for j in _sampled_dips(dist, stop, len(t), margin):
            s.dips.append((i, t[j - 1], t[j + 1], True))


def _sampled_dips(dist, stop, count, margin) -> np.ndarray:
    """Indices of the sampled local minima of ``dist`` (distance to the isovalue on the ray's
    side, field units) before sample ``stop`` near enough to the isovalue that the field,
    changing no faster than twice its sampled rate, could reach it between samples."""
    mid = np.arange(1, min(stop, count - 1))
    reach = 2 * np.maximum(np.abs(dist[mid - 1] - dist[mid]),
                           np.abs(dist[mid + 1] - dist[mid]))
    local = (dist[mid] <= dist[mid - 1]) & (dist[mid] <= dist[mid + 1]) & \
        (dist[mid] < reach + margin)
    return mid[local]


def _resolve_dips(s: _Scan, value, iso, margin):
    """Minimise every dip of ``s`` (:func:`minimise`; ``value(rays, t)`` gives the field on the
    rays) and update ``s``: first the depths of the sampled crossings, then the dips before
    them in order of their minima along the ray; a dip that crosses moves the ray's first
    crossing there, one within ``margin`` (field units) of the isovalue before the bracket makes
    the ray touchy."""
    if not s.dips:
        return
    r, lo, hi, before = (np.array(x) for x in zip(*s.dips))
    tm, dm = minimise(value, r, lo, hi, iso, s.side[r])
    for ray, t_d, d_d in zip(r[~before], tm[~before], dm[~before]):
        if d_d < s.dmin[ray]:
            s.dmin[ray], s.t_min[ray] = d_d, t_d
    for j in np.flatnonzero(before)[np.argsort(tm[before], kind="stable")]:
        ray, t_d, d_d = r[j], tm[j], dm[j]
        if d_d < 0 and not t_d >= s.a[ray]:
            # The dip crosses: the first crossing lies before the sampled one.
            s.a[ray], s.b[ray] = lo[j], t_d
            s.dmin[ray], s.t_min[ray] = d_d, t_d
        elif not np.isfinite(s.a[ray]) and d_d < s.dmin[ray]:
            s.dmin[ray], s.t_min[ray] = d_d, t_d
        if abs(d_d) < margin and not t_d > s.a[ray]:
            s.touchy[ray] = True


def _twin_check_points(o, d, crossed, t_first, rays, t_all, twin_points, seed) -> np.ndarray:
    """At most ``twin_points`` points (world) to check against the slow twin: the crossings
    ``o + t_first d`` of the rays ``crossed`` and random samples (ray ``rays[k]`` at
    parameter ``t_all[k]``), drawn with ``seed``."""
    rng = np.random.default_rng(seed)
    check = [o[crossed] + t_first[crossed, None] * d[crossed]]
    if len(t_all):
        pick = rng.choice(len(t_all), size=min(twin_points, len(t_all)), replace=False)
        check.append(o[rays[pick]] + t_all[pick, None] * d[rays[pick]])
    points = np.concatenate(check)
    if len(points) > twin_points:
        points = points[rng.choice(len(points), size=twin_points, replace=False)]
    return points


def _plane_params(field, o, d, t_in, t_out):
    """Parameters just before and after each crossing of a lattice plane (cell faces of every
    level) by the ray ``o + t d`` (world) on ``(t_in, t_out)``; 1e-9 finest cells apart."""
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


def minimise(value, rays, lo, hi, iso, side, iterations=14, k=16):
    """Minimum of ``(value - iso) * side`` on ``[lo, hi]`` (ray parameters) per entry (a
    unimodal stretch; ``value(rays, t)`` gives the field on the rays): ``k + 1`` samples, then
    the stretch between the neighbours of the smallest, ``iterations`` times (each shrinks it
    ``k / 2``-fold). Returns ``(t, minimum)`` (ray parameter, field units)."""
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


def bisect_crossings(value, a, b, iso, k=16):
    """The first crossing of ``iso`` inside ``[a, b]`` (ray parameters) per ray (inf where
    ``a`` is NaN): ``k``-section on float64 values (``value(rays, t)``; ``value(a)`` and
    ``value(b)`` on either side) down to 1e-13 of the stretch."""
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
