"""The first isosurface crossing along rays, by four methods on one kd-tree walk
(:mod:`mi_amr.kernels.traverse`).

* ``exact``: the ray is cut at every dual-cell plane of the levels that contribute (the owner's
  level for ``finest``, all active levels for ``basis``); inside each piece the field is
  ``N(s) / D(s)`` with cubic ``N`` and ``D`` (:func:`mi_amr.kernels.reconstruct.segment_cubic`),
  so each isovalue's crossings are the roots of the cubic ``N - iso D``, found without fail by
  :mod:`mi_amr.kernels.roots` (Marchesin et al. 2009). A jump of the field across an isovalue
  between pieces or skipped nodes (``finest`` at grid edges) counts as a crossing where the jump
  is.
* ``uniform``: samples every ``step_scale * h_min`` (``h_min``: the finest cell width of the
  volume) from the ray's entry; a crossing between two samples that straddle an isovalue is put
  where the line through them meets it.
* ``adaptive`` (ExaBricks): the step is ``step_scale`` times the finest cell width active in the
  leaf; step positions, offset by a per-ray ``jitter`` in ``[0, 1)`` steps (interleaved
  sampling), and leaf boundaries delimit sub-intervals that are sampled at their mid-points.
* ``bisect``: ``adaptive``, then bisection between two straddling samples (the course report's
  "advanced adaptive sampling") down to :data:`~mi_amr.tolerances.BISECT_TARGET` cells, then
  linear interpolation.

Skipping does not change what the sampling methods find: every value in a skipped node lies on
one side of each isovalue, which its range tells. When that side differs from the previous
sample's, the first sample inside the node is taken after all (and interpolated against the
previous one, as without skipping); when the next sample after a skipped node changes side, the
last position before it is evaluated. Uniform sampling is thereby unchanged; the adaptive methods
may place that last sample at the node's end instead of a sub-interval's middle.

Rays ``o + t d`` are in the volume's world space; ``t`` is the caller's parameter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels import roots
from mi_amr.kernels.config import MarchConfig, clip_box, first_between, sides_differ
from mi_amr.kernels.device import lnot
from mi_amr.kernels.traverse import (Walk, box_exit, clip_to_volume, epsilon, next_dual_plane,
                                     seek_part, seek_start)


@dataclass
class Crossing:
    """Result of :func:`first_crossing`: ``t`` is ``inf`` where ``hit`` is False."""

    hit: Any
    t: Any
    k: Any           # index of the isovalue crossed
    samples: Any     # field evaluations (``exact``: cubic pieces) along the ray
    after: Any = None  # sampling methods: a value just past the isovalue, on the far side


def first_crossing(dev, cfg: MarchConfig, o, d, t_start, t_end, jitter, active,
                   v_before=None) -> Crossing:
    """First crossing of any isovalue by the reconstructed field on ``(t_start, t_end)``.

    ``o``, ``d``: ray origin and direction in volume world space (``m.Array3f``); ``jitter``:
    per-ray offset in ``[0, 1)`` for the adaptive methods (ignored by ``exact`` and ``uniform``).
    ``v_before``: the field's value just before ``t_start`` (NaN or None: unknown). For
    ``exact`` a jump from it across an isovalue where the search starts is a crossing; the
    sampling methods take it as a sample at the march's start (an isovalue between it and the
    first sample is crossed).
    """
    m = dev.m
    o, t0, t1, active = clip_to_volume(dev, o, d, t_start, t_end, active,
                                       clip_box(cfg))
    if cfg.method == "exact":
        v = m.Float(dr.nan) if v_before is None else m.Float(v_before)
        c, _ = _march_exact(dev, cfg, o, d, Walk.start(m, t0), v, t1, active)
        return c
    return _march_sampled(dev, cfg, o, d, t0, t1, m.Float(jitter), active, v_before)


def crossings(dev, cfg: MarchConfig, o, d, t_start, t_end, jitter, active, resume=True):
    """The crossings on ``(t_start, t_end)`` one after the other (translucent layers): returns
    ``(state, after)``, where ``after(state, alive) -> (Crossing, state)`` finds the next
    crossing, at least ``dev.layer_offset`` (in finest-cell units of length) past the one
    before.

    ``exact`` goes on with the crossed isovalue as the value before, so that a jump of the
    field across several isovalues (``finest`` at grid edges) is one layer per isovalue, and
    resumes its kd-tree walk where the last crossing was: the same pieces, roots and leaves as
    a new :func:`first_crossing` from just past it, which is what ``resume=False`` does (the
    slow twin) and what the sampled methods always do: their step positions are anchored at
    the march's start, and their previous sample there is a value just past the crossed
    isovalue (``Crossing.after``), so that every isovalue two samples straddle is a layer."""
    m = dev.m
    step = dev.layer_offset / dr.norm(d)
    no_value = m.Float(dr.nan)

    def past(c, v):
        return dr.select(c.hit, cfg.iso(dev, c.k) if c.after is None else c.after, v)

    if cfg.method == "exact" and resume:
        o_in, t0, t1, inside = clip_to_volume(dev, o, d, t_start, t_end, active,
                                              clip_box(cfg))

        def resumed(state, alive):
            w, v = state
            c, w = _march_exact(dev, cfg, o_in, d, w, v, t1, inside & alive & (w.t < t1))
            w.t = dr.select(c.hit, c.t + step, w.t)
            return c, (w, past(c, v))

        return (Walk.start(m, t0), no_value), resumed

    def restarted(state, alive):
        t, v = state
        c = first_crossing(dev, cfg, o, d, t, t_end, jitter, alive, v_before=v)
        return c, (dr.select(c.hit, c.t + step, t), past(c, v))

    return (m.Float(t_start), no_value), restarted


# ---------------------------------------------------------------------- exact

@dataclass
class PieceHit:
    """The piece holding the first crossing: where it starts (``t_seg``), its cubics ``num``
    and ``den`` (4 coefficients each, in ``s = t - t_seg``) and length ``L``; ``jump``: the
    crossing is a jump of the field at ``t_seg`` instead of a root."""

    jump: Any
    t_seg: Any
    num: list
    den: list
    L: Any

    @staticmethod
    def empty(m) -> "PieceHit":
        return PieceHit(jump=m.Bool(False), t_seg=m.Float(0.0), num=[m.Float(0.0)] * 4,
                        den=[m.Float(0.0)] * 4, L=m.Float(0.0))

    def keep(self, got, jump, t, num, den, L) -> "PieceHit":
        """This record, replaced where ``got`` by the piece ``(jump, t, num, den, L)``."""
        return PieceHit(jump=dr.select(got, jump, self.jump), t_seg=dr.select(got, t, self.t_seg),
                        num=[dr.select(got, a, b) for a, b in zip(num, self.num)],
                        den=[dr.select(got, a, b) for a, b in zip(den, self.den)],
                        L=dr.select(got, L, self.L))


def cubic_piece(dev, cfg, o, d, inv_d, dnorm, w: Walk, t1, level_masks, values, active):
    """The piece ``[t, t_b]`` from the walk's ``t`` to the next dual-cell plane of a level that
    contributes in the leaf (or the leaf's end): ``(t_b, L, nums, den)`` with the cubics of
    the reconstruction along it."""
    m = dev.m
    eps = epsilon(dev, w.t, dnorm)
    mask = dr.gather(m.UInt32, level_masks, w.leaf, active)
    t_b = dr.minimum(dr.minimum(next_dual_plane(dev, mask, o, d, inv_d, w.t + eps), w.t_exit), t1)
    t_b = dr.maximum(t_b, w.t + eps)
    L = t_b - w.t
    p0 = dr.fma(d, w.t, o)
    nums, den = rec.segment_cubic(dev, cfg.basis, w.leaf, p0, d, 0.5 * L, values, active)
    return t_b, L, nums, den


def _piece_crossings(dev, cfg, num, den, L, v_prev, k_jump, active):
    """Crossings in a piece: ``(have, v_end, jumped, k_jump, found)``. ``have``: the field is
    defined on it (some cell has weight; next to missing values the weights can sum to much
    less than 1 and the field is still defined); ``jumped``: the value jumped across isovalue
    ``k_jump`` (the first met, when it jumped across several) from ``v_prev`` at its start;
    ``found``: a root of ``N - iso D`` in it."""
    m = dev.m
    d_mid = roots.cubic(den, 0.5 * L)
    have = active & (den[0] > tol.NO_WEIGHT) & (roots.cubic(den, L) > tol.NO_WEIGHT) & \
        (d_mid > tol.NO_WEIGHT)
    v_start = num[0] / den[0]
    v_end = roots.cubic(num, L) / roots.cubic(den, L)
    n_mid = roots.cubic(num, 0.5 * L)
    jumped = have & sides_differ(dev, cfg, v_prev, v_start)
    k_jump = dr.select(jumped, first_between(dev, cfg, v_prev, v_start), k_jump)
    found = m.Bool(False)
    for k in range(cfg.num_iso):
        found_k, _, _ = _bracket(num, den, cfg.iso(dev, k), L, n_mid, d_mid)
        found |= have & found_k
    return have, v_end, jumped, k_jump, found


def _bracket(num, den, iso, L, n_mid, d_mid):
    """The first root bracket ``(found, a, b)`` of ``N - iso D`` on ``[0, L]``, for the field
    ``N / D``. Next to missing data ``D`` falls to 0, and ``N - iso D`` with it, which is no
    crossing of the field: an end whose weight is below :data:`~mi_amr.tolerances.MIN_COVER`
    (none but rounding) is moved :data:`~mi_amr.tolerances.COVER_NUDGE` of the bracket
    inside, and the signs there must still differ (a tangent needs the weight where it
    touches)."""
    c = [num[i] - iso * den[i] for i in range(4)]
    found, a, b = roots.first_root_bracket(c, L, dr.abs(n_mid) + dr.abs(iso * d_mid))
    thin_a = roots.cubic(den, a) < tol.MIN_COVER
    thin_b = roots.cubic(den, b) < tol.MIN_COVER
    nudge = tol.COVER_NUDGE * (b - a)
    a2 = dr.select(thin_a, a + nudge, a)
    b2 = dr.select(thin_b, b - nudge, b)
    crosses = (roots.cubic(c, a2) > 0.0) != (roots.cubic(c, b2) > 0.0)
    touch = (a == b) & lnot(thin_a)
    keep = dr.select(thin_a | thin_b, crosses | touch, True)
    return found & keep, a2, b2


@dr.syntax
def _march_exact(dev, cfg, o, d, w: Walk, v_before, t1, active):
    """The first crossing from walk ``w`` on (``v_before``: the value before it, NaN if
    unknown) up to ``t1``, and the walk where it stopped: ``(Crossing, Walk)``."""
    m = dev.m
    dnorm = dr.norm(d)
    inv_d = dr.select(d != 0.0, dr.rcp(d), dr.inf)
    values = dev.arrays(cfg.basis)
    level_masks = dev.leaf_levels if cfg.basis else dev.leaf_owner_levels
    w = Walk(w.node, w.leaf, w.face, w.t_exit, w.t)
    v_prev = m.Float(v_before)
    samples = m.UInt32(0)
    hit = m.Bool(False)
    k_jump = m.UInt32(0)
    piece = PieceHit.empty(m)
    sk = seek_start(dev, o, d, w.t, w.node, w.face, v_prev, m.Bool(False))
    while active:
        # --- Find the next leaf that may hold a crossing (skipping all that cannot), a few
        # steps of the search per piece, so that the lanes with a leaf wait less.
        sk, new = seek_part(dev, cfg, o, d, t1, w, sk, v_prev, active)
        st = sk.stretch()
        w = w.adopt(new, st)
        v_prev = dr.select(new & dr.isfinite(st.side), st.side, v_prev)
        # A skipped node across an isovalue from what came before: the jump is the crossing.
        turned = new & st.turned
        hit |= turned
        piece = piece.keep(turned, True, w.t, piece.num, piece.den, piece.L)
        k_jump = dr.select(turned, first_between(dev, cfg, v_prev, st.turn_value), k_jump)
        active &= lnot(turned) & (lnot(new) | st.found)
        work = active & lnot(sk.searching)

        # --- The piece [t, t_b] and its crossings: a jump at its start, or a root.
        t_b, L, nums, den = cubic_piece(dev, cfg, o, d, inv_d, dnorm, w, t1, level_masks, values,
                                        work)
        samples += dr.select(work, 1, 0)
        have, v_end, jumped, k_jump, found = _piece_crossings(dev, cfg, nums[0], den, L, v_prev,
                                                              k_jump, work)
        got = work & (jumped | found)
        hit |= got
        piece = piece.keep(got, jumped, w.t, nums[0], den, L)

        # --- Advance to the piece's end.
        v_prev = dr.select(work, dr.select(have, v_end, dr.nan), v_prev)
        w.t = dr.select(work, t_b, w.t)
        active &= lnot(got) & (w.t < t1)
    return _refine_exact(dev, cfg, piece, hit, k_jump, samples), w


def _refine_exact(dev, cfg, piece: PieceHit, hit, k_jump, samples) -> Crossing:
    """The earliest root among the isovalues in the piece that holds one (refined here, once
    per ray: roots of different isovalues are compared where they are, not by their pieces)."""
    m = dev.m
    num, den, L = piece.num, piece.den, piece.L
    n_mid = roots.cubic(num, 0.5 * L)
    d_mid = roots.cubic(den, 0.5 * L)
    s_best = m.Float(dr.inf)
    k_hit = m.UInt32(0)
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        c = [num[i] - iso * den[i] for i in range(4)]
        found_k, a, b = _bracket(num, den, iso, L, n_mid, d_mid)
        s_k = dr.select(found_k, roots.refine_root(c, a, b), dr.inf)
        # A "root" where no cell has weight (N = D = 0) is not a crossing.
        s_k = dr.select(roots.cubic(den, s_k) > tol.NO_WEIGHT, s_k, dr.inf)
        take = hit & lnot(piece.jump) & (s_k < s_best)
        s_best = dr.select(take, s_k, s_best)
        k_hit = dr.select(take, k, k_hit)
    k_hit = dr.select(piece.jump, k_jump, k_hit)
    hit &= piece.jump | (s_best < dr.inf)
    t_hit = dr.select(hit, piece.t_seg + dr.select(piece.jump, 0.0, s_best), dr.inf)
    return Crossing(hit=hit, t=t_hit, k=k_hit, samples=samples)


# ---------------------------------------------------------------------- sampled

@dataclass
class Trail:
    """What a sampled march remembers of the ray behind it: the previous sample ``(t_prev,
    v_prev)`` (``known``: a sample, not a skipped node's representative value), whether the
    next sample is ``forced`` (a skipped node's first, across an isovalue), the step ``dt``,
    and the bracket ``(t_a, v_a)``-``(t_b, v_b)`` of the crossing found (``hit``, isovalue
    ``k_hit``)."""

    t_prev: Any
    v_prev: Any
    known: Any
    forced: Any
    dt: Any
    hit: Any
    k_hit: Any
    t_a: Any
    t_b: Any
    v_a: Any
    v_b: Any

    @staticmethod
    def start(m, dt, t0=None, v_before=None) -> "Trail":
        """No sample yet (``t_prev`` is -inf: nodes skipped before the first sample still
        leave their side as the previous value), or the value ``v_before`` at ``t0`` as the
        previous sample (where finite)."""
        t_prev, v_prev = m.Float(-dr.inf), m.Float(dr.nan)
        if v_before is not None:
            v_prev = m.Float(v_before)
            t_prev = dr.select(dr.isfinite(v_prev), m.Float(t0), t_prev)
        return Trail(t_prev=t_prev, v_prev=v_prev, known=m.Bool(True),
                     forced=m.Bool(False), dt=m.Float(dt), hit=m.Bool(False),
                     k_hit=m.UInt32(0), t_a=m.Float(0.0), t_b=m.Float(0.0), v_a=m.Float(0.0),
                     v_b=m.Float(0.0))


def _next_leaf_sampled(dev, cfg, o, d, dnorm, w: Walk, tr: Trail, sk, t1, t_anchor, active):
    """Seek the next leaf that may hold a crossing, or a skipped node across one (whose first
    sample is then taken after all, in the leaf where that node starts), a few search steps at
    a time (:func:`~mi_amr.kernels.traverse.seek_part`). Returns the new walk, trail and
    search, the lanes still marching and those of them that take a sample now."""
    m = dev.m
    uniform = cfg.method == "uniform"
    sk, new = seek_part(dev, cfg, o, d, t1, w, sk, tr.v_prev, active)
    st = sk.stretch()
    turned = new & st.turned
    # Past skipped nodes the previous sample becomes "their last one", on their side.
    skipped = new & dr.isfinite(st.side)
    if uniform:
        t_last = t_anchor + dr.floor((st.t_side - t_anchor) / tr.dt - tol.LATTICE_SNAP) * tr.dt
    else:
        t_last = st.t_side
    moved_on = skipped & (t_last > tr.t_prev)
    tr.t_prev = dr.select(moved_on, t_last, tr.t_prev)
    tr.v_prev = dr.select(moved_on, st.side, tr.v_prev)
    tr.known = dr.select(moved_on, False, tr.known)
    at = rec.locate(dev, dr.fma(d, st.t + epsilon(dev, st.t, dnorm), o), turned)
    at_exit, _ = box_exit(m, dr.gather(m.Array3f, dev.leaf_lo, at, turned),
                          dr.gather(m.Array3f, dev.leaf_hi, at, turned), o, d)
    w = Walk(node=dr.select(new, st.node, w.node),
             leaf=dr.select(turned, at, dr.select(new, st.leaf, w.leaf)),
             face=dr.select(turned, m.UInt32(6), dr.select(new, st.face, w.face)),
             t_exit=dr.select(turned, at_exit, dr.select(new, st.t_exit, w.t_exit)),
             t=dr.select(new, st.t, w.t))
    tr.forced = dr.select(new, turned, tr.forced)
    active &= lnot(new) | st.found | turned
    if not uniform:
        leaf_h = dr.gather(m.Float, dev.leaf_min_h, w.leaf, active & new)
        tr.dt = dr.select(new, cfg.step_scale * leaf_h / dnorm, tr.dt)
    return w, tr, sk, active, active & lnot(sk.searching)


def _sample(dev, cfg, o, d, dnorm, w: Walk, tr: Trail, t1, t_anchor, rho, values, active):
    """The next sub-interval ``[t, b]`` (up to a step position or the leaf's end) and its
    sample: ``(b, t_s, v, take)``."""
    uniform = cfg.method == "uniform"
    eps = epsilon(dev, w.t, dnorm)
    step = dr.floor((w.t - t_anchor) / tr.dt - rho + tol.LATTICE_SNAP) + 1.0
    b_lattice = t_anchor + (rho + step) * tr.dt
    limit = dr.minimum(w.t_exit, t1)
    b = dr.maximum(dr.minimum(b_lattice, limit), w.t + eps)
    if uniform:
        # Uniform samples sit on the step positions themselves (a forced sample is the next
        # one, wherever it falls).
        t_s = b_lattice
        take = active & ((b_lattice <= limit) | tr.forced)
    else:
        t_s = 0.5 * (w.t + b)
        take = dev.m.Bool(active)
    vals, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_s, o), values, take & lnot(tr.forced),
                              leaf=w.leaf)
    vals_f, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_s, o), values, take & tr.forced)
    v = dr.select(tr.forced, vals_f[0], vals[0])
    return b, t_s, v, take


def _straddle(dev, cfg, o, d, tr: Trail, t_s, v, take, values):
    """A straddled isovalue between the previous sample and this one (if the previous one
    stands for a skipped node, it is evaluated where it is first). Returns the trail with the
    bracket kept, whether a crossing was found, and the extra samples taken."""
    m = dev.m
    straddle = take & sides_differ(dev, cfg, tr.v_prev, v)
    fix = straddle & lnot(tr.known)
    vals_p, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, tr.t_prev, o), values, fix)
    tr.v_prev = dr.select(fix, vals_p[0], tr.v_prev)
    best = m.Float(dr.inf)
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        cross = take & ((tr.v_prev - iso) * (v - iso) <= 0.0) & (v != tr.v_prev)
        where = dr.select(cross, tr.t_prev + (iso - tr.v_prev) / (v - tr.v_prev) *
                          (t_s - tr.t_prev), dr.inf)
        pick = where < best
        best = dr.select(pick, where, best)
        tr.k_hit = dr.select(pick, k, tr.k_hit)
    got = best < dr.inf
    tr.hit |= got
    tr.t_a = dr.select(got, tr.t_prev, tr.t_a)
    tr.t_b = dr.select(got, t_s, tr.t_b)
    tr.v_a = dr.select(got, tr.v_prev, tr.v_a)
    tr.v_b = dr.select(got, v, tr.v_b)
    tr.t_prev = dr.select(take, t_s, tr.t_prev)
    tr.v_prev = dr.select(take, v, tr.v_prev)
    tr.known = dr.select(take, True, tr.known)
    return tr, got, dr.select(fix, 1, 0)


@dr.syntax
def _march_sampled(dev, cfg, o, d, t0, t1, jitter, active, v_before=None):
    """The first crossing on ``(t0, t1)`` by a sampling method; ``v_before``: the value of a
    previous sample at ``t0`` (NaN or None: none)."""
    m = dev.m
    dnorm = dr.norm(d)
    values = dev.arrays(cfg.basis)
    rho = m.Float(0.0) if cfg.method == "uniform" else jitter
    t_anchor = m.Float(t0)
    w = Walk.start(m, t0)
    tr = Trail.start(m, cfg.step_scale * dev.min_h / dnorm, t0, v_before)
    samples = m.UInt32(0)
    sk = seek_start(dev, o, d, w.t, w.node, w.face, tr.v_prev, m.Bool(False))
    while active:
        w, tr, sk, active, work = _next_leaf_sampled(dev, cfg, o, d, dnorm, w, tr, sk, t1,
                                                     t_anchor, active)
        b, t_s, v, take = _sample(dev, cfg, o, d, dnorm, w, tr, t1, t_anchor, rho, values,
                                  work)
        forced = tr.forced
        tr, got, extra = _straddle(dev, cfg, o, d, tr, t_s, v, take, values)
        samples += dr.select(take, 1, 0) + extra
        # --- Advance. After a forced sample, the rest of its node is skipped by the next seek.
        w.t = dr.select(work, dr.select(forced & (t_s > b), t_s, b), w.t)
        w.t_exit = dr.select(work & forced, -dr.inf, w.t_exit)
        tr.forced = m.Bool(False)
        active &= lnot(got) & (w.t < t1)

    iso_hit = cfg.iso(dev, tr.k_hit)
    t_hit = dr.select(tr.hit, dr.clip(tr.t_a + (iso_hit - tr.v_a) / (tr.v_b - tr.v_a) *
                                      (tr.t_b - tr.t_a), dr.minimum(tr.t_a, tr.t_b),
                                      dr.maximum(tr.t_a, tr.t_b)), dr.inf)
    if dr.hint(cfg.method == "bisect", mode="scalar"):
        t_hit = _bisect(dev, cfg, o, d, tr.t_a, tr.t_b, tr.v_a, tr.k_hit, tr.hit)
    # Just past the isovalue, towards the bracket's far sample (that sample itself where the
    # step is lost to rounding).
    after = dr.fma(tr.v_b - iso_hit, tol.RESUME_REL, iso_hit)
    after = dr.select(after == iso_hit, tr.v_b, after)
    return Crossing(hit=tr.hit, t=t_hit, k=tr.k_hit, samples=samples, after=after)


@dr.syntax
def _bisect(dev, cfg, o, d, t_a, t_b, v_a, k, active):
    """Bisection of ``[t_a, t_b]`` (whose ends straddle isovalue ``k``) down to
    :data:`~mi_amr.tolerances.BISECT_TARGET` cells, then linear interpolation in the last
    interval."""
    m = dev.m
    values = dev.arrays(cfg.basis)
    iso = cfg.iso(dev, k)
    fa = v_a - iso
    depth = dr.maximum(dr.ceil(dr.log2(cfg.step_scale / tol.BISECT_TARGET)), 1.0)
    i = m.Float(0.0)
    while active & (i < depth):
        mid = 0.5 * (t_a + t_b)
        vals, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, mid, o), values, active)
        f = vals[0] - iso
        left = (f * fa) <= 0.0
        t_b = dr.select(left, mid, t_b)
        t_a = dr.select(left, t_a, mid)
        fa = dr.select(left, fa, f)
        i += 1.0
    vals, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_b, o), values, active)
    fb = vals[0] - iso
    t = t_a + fa / (fa - fb) * (t_b - t_a)
    # Where a value is missing (NaN data) the last interval may not straddle: stay inside it.
    inside = dr.isfinite(t) & (t >= dr.minimum(t_a, t_b)) & (t <= dr.maximum(t_a, t_b))
    return dr.select(active, dr.select(inside, t, 0.5 * (t_a + t_b)), dr.inf)
