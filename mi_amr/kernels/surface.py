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

Shape: :func:`first_crossing` and :func:`crossings` take a
:class:`~mi_amr.kernels.ray.RayContext`. Every method consumes the one traversal
(:class:`~mi_amr.kernels.traverse.March`; :meth:`~mi_amr.kernels.traverse.March.next` per step
of its loop): ``exact`` takes :func:`~mi_amr.kernels.traverse.cubic_piece` pieces and keeps
the one holding the crossing (:class:`PieceHit`), refined once at the end; the sampling
methods take sub-intervals of a :class:`~mi_amr.kernels.traverse.Lattice`
(:func:`~mi_amr.kernels.traverse.sub_interval`) and keep the :class:`Bracket` of samples that
straddles an isovalue. Rays ``o + t d`` are in the volume's world space; ``t`` is the caller's
parameter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels import roots
from mi_amr.kernels.config import bisect_depth, clip_box, first_between, sides_differ
from mi_amr.kernels.device import lnot
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.traverse import (CubicPiece, Lattice, March, Walk, box_exit, cubic_piece,
                                     sub_interval)

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Bool, Float, UInt32


@dataclass
class Crossing:
    """Result of :func:`first_crossing`: ``t`` is ``inf`` where ``hit`` is False."""

    hit: Bool
    t: Float
    k: UInt32                  # index of the isovalue crossed
    samples: Optional[UInt32]  # field evaluations (``exact``: cubic pieces) along the ray
    after: Optional[Float] = None  # sampling methods: a value just past the isovalue


def first_crossing(ray: RayContext, jitter, v_before=None) -> Crossing:
    """First crossing of any isovalue by the reconstructed field on ``(ray.t0, ray.t1)``.

    ``jitter``: per-ray offset in ``[0, 1)`` for the adaptive methods (ignored by ``exact``
    and ``uniform``). ``v_before``: the field's value just before ``ray.t0`` (NaN or None:
    unknown). For ``exact`` a jump from it across an isovalue where the search starts is a
    crossing; the sampling methods take it as a sample at the march's start (an isovalue
    between it and the first sample is crossed).
    """
    m = ray.m
    ray = ray.clipped(clip_box(ray.cfg))
    if ray.cfg.method == "exact":
        v = m.Float(dr.nan) if v_before is None else m.Float(v_before)
        c, _ = _march_exact(ray, Walk.start(m, ray.t0), v, ray.active)
        return c
    return _march_sampled(ray, m.Float(jitter), v_before)


def crossings(ray: RayContext, jitter, resume=True):
    """The crossings on ``(ray.t0, ray.t1)`` one after the other (translucent layers): returns
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
    m, cfg = ray.m, ray.cfg
    step = ray.dev.layer_offset / ray.dnorm
    no_value = m.Float(dr.nan)

    def past(c, v):
        return dr.select(c.hit, cfg.iso(ray.dev, c.k) if c.after is None else c.after, v)

    if cfg.method == "exact" and resume:
        inside = ray.clipped(clip_box(cfg))

        def resumed(state, alive):
            w, v = state
            c, w = _march_exact(inside, w, v, inside.active & alive & (w.t < inside.t1))
            w.t = dr.select(c.hit, c.t + step, w.t)
            return c, (w, past(c, v))

        return (Walk.start(m, inside.t0), no_value), resumed

    def restarted(state, alive):
        t, v = state
        c = first_crossing(ray.replaced(t0=t, active=alive), jitter, v_before=v)
        return c, (dr.select(c.hit, c.t + step, t), past(c, v))

    return (m.Float(ray.t0), no_value), restarted


# ---------------------------------------------------------------------- exact

@dataclass
class PieceHit:
    """The piece holding the first crossing: where it starts (``t_seg``), its cubics ``num``
    and ``den`` (4 coefficients each, in ``s = t - t_seg``) and its ``length``; ``jump``: the
    crossing is a jump of the field at ``t_seg`` instead of a root."""

    jump: Bool
    t_seg: Float
    num: list
    den: list
    length: Float

    @staticmethod
    def empty(m) -> "PieceHit":
        return PieceHit(jump=m.Bool(False), t_seg=m.Float(0.0), num=[m.Float(0.0)] * 4,
                        den=[m.Float(0.0)] * 4, length=m.Float(0.0))


def _piece_crossings(ray: RayContext, piece: CubicPiece, v_prev, k_jump, active):
    """Crossings in a piece: ``(have, v_end, jumped, k_jump, found)``. ``have``: the field is
    defined on it (:meth:`~mi_amr.kernels.traverse.CubicPiece.defined`); ``jumped``: the value
    jumped across isovalue ``k_jump`` (the first met, when it jumped across several) from
    ``v_prev`` at its start; ``found``: a root of ``N - iso D`` in it."""
    m, dev, cfg = ray.m, ray.dev, ray.cfg
    num, den = piece.num, piece.den
    n_mid, d_mid = piece.mid()
    have = piece.defined(active, d_mid)
    v_start = num[0] / den[0]
    v_end = piece.value_at_end()
    jumped = have & sides_differ(dev, cfg, v_prev, v_start)
    k_jump = dr.select(jumped, first_between(dev, cfg, v_prev, v_start), k_jump)
    found = m.Bool(False)
    for k in range(cfg.num_iso):
        found_k, _, _ = _bracket(num, den, cfg.iso(dev, k), piece.length, n_mid, d_mid)
        found |= have & found_k
    return have, v_end, jumped, k_jump, found


def _bracket(num, den, iso, length, n_mid, d_mid):
    """The first root bracket ``(found, a, b)`` of ``N - iso D`` on ``[0, length]``, for the
    field ``N / D``. Next to missing data ``D`` falls to 0, and ``N - iso D`` with it, which is
    no crossing of the field: an end whose weight is below
    :data:`~mi_amr.tolerances.MIN_COVER` (none but rounding) is moved
    :data:`~mi_amr.tolerances.COVER_NUDGE` of the bracket inside, and the signs there must
    still differ (a tangent needs the weight where it touches)."""
    c = [num[i] - iso * den[i] for i in range(4)]
    found, a, b = roots.first_root_bracket(c, length, dr.abs(n_mid) + dr.abs(iso * d_mid))
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
def _march_exact(ray: RayContext, walk: Walk, v_before, active):
    """The first crossing from ``walk`` on (``v_before``: the value before it, NaN if
    unknown) up to ``ray.t1``, and the walk where it stopped: ``(Crossing, Walk)``."""
    m, dev, cfg = ray.m, ray.dev, ray.cfg
    values = dev.arrays(cfg.basis)
    march = March.start(ray, walk=Walk(walk.node, walk.leaf, walk.face, walk.t_exit, walk.t))
    v_prev = m.Float(v_before)        # the field's value where the walk is (NaN: none)
    samples = m.UInt32(0)             # cubic pieces taken
    hit = m.Bool(False)
    k_jump = m.UInt32(0)              # the isovalue a jump crossed
    piece = PieceHit.empty(m)         # the piece holding the crossing
    while dr.hint(active, label="first_crossing", exclude=[cfg, dev, m, ray, values]):
        # --- The next leaf that may hold a crossing (skipping all that cannot), a few steps
        # of the search per piece, so that the lanes with a leaf wait less.
        march, leg = march.next(ray, v_prev, active)
        skips = leg.stretch.skips
        v_prev = dr.select(leg.new & dr.isfinite(skips.side), skips.side, v_prev)
        # A skipped node across an isovalue from what came before: the jump is the crossing.
        turned = leg.new & skips.turned
        hit |= turned
        piece = dr.select(turned, PieceHit(jump=m.Bool(True), t_seg=march.walk.t,
                                           num=piece.num, den=piece.den,
                                           length=piece.length), piece)
        k_jump = dr.select(turned, first_between(dev, cfg, v_prev, skips.turn_value), k_jump)
        active &= lnot(turned) & leg.onward
        work = active & lnot(leg.searching)

        # --- The piece [t, t_b] and its crossings: a jump at its start, or a root.
        cp = cubic_piece(ray, march.walk, values, work)
        samples += dr.select(work, 1, 0)
        have, v_end, jumped, k_jump, found = _piece_crossings(ray, cp, v_prev, k_jump, work)
        got = work & (jumped | found)
        hit |= got
        piece = dr.select(got, PieceHit(jump=jumped, t_seg=cp.t, num=cp.num, den=cp.den,
                                        length=cp.length), piece)

        # --- Advance to the piece's end.
        v_prev = dr.select(work, dr.select(have, v_end, dr.nan), v_prev)
        march.walk.t = dr.select(work, cp.end, march.walk.t)
        active &= lnot(got) & (march.walk.t < ray.t1)
    return _refine_exact(ray, piece, hit, k_jump, samples), march.walk


def _refine_exact(ray: RayContext, piece: PieceHit, hit, k_jump, samples) -> Crossing:
    """The earliest root among the isovalues in the piece that holds one (refined here, once
    per ray: roots of different isovalues are compared where they are, not by their pieces)."""
    m, cfg = ray.m, ray.cfg
    num, den, length = piece.num, piece.den, piece.length
    n_mid = roots.cubic(num, 0.5 * length)
    d_mid = roots.cubic(den, 0.5 * length)
    s_best = m.Float(dr.inf)
    k_hit = m.UInt32(0)
    for k in range(cfg.num_iso):
        iso = cfg.iso(ray.dev, k)
        c = [num[i] - iso * den[i] for i in range(4)]
        found_k, a, b = _bracket(num, den, iso, length, n_mid, d_mid)
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
class Bracket:
    """The samples ``(t_a, v_a)``-``(t_b, v_b)`` that straddle the crossing found (``hit``,
    isovalue ``k_hit``)."""

    hit: Bool
    k_hit: UInt32
    t_a: Float
    t_b: Float
    v_a: Float
    v_b: Float


@dataclass
class Trail:
    """What a sampled march remembers of the ray behind it: the previous sample ``(t_prev,
    v_prev)`` (``known``: a sample, not a skipped node's representative value), whether the
    next sample is ``forced`` (a skipped node's first, across an isovalue: known within a
    step only, None between steps, so that it is no loop state), the step ``dt`` (None for
    ``uniform``, whose step never changes), and the :class:`Bracket` of the crossing found."""

    t_prev: Float
    v_prev: Float
    known: Bool
    forced: Optional[Bool]
    dt: Optional[Float]
    bracket: Bracket

    @staticmethod
    def start(m, dt, t0=None, v_before=None) -> "Trail":
        """No sample yet (``t_prev`` is -inf: nodes skipped before the first sample still
        leave their side as the previous value), or the value ``v_before`` at ``t0`` as the
        previous sample (where finite)."""
        t_prev, v_prev = m.Float(-dr.inf), m.Float(dr.nan)
        if v_before is not None:
            v_prev = m.Float(v_before)
            t_prev = dr.select(dr.isfinite(v_prev), m.Float(t0), t_prev)
        zero = m.Float(0.0)
        bracket = Bracket(hit=m.Bool(False), k_hit=m.UInt32(0), t_a=zero, t_b=m.Float(0.0),
                          v_a=m.Float(0.0), v_b=m.Float(0.0))
        return Trail(t_prev=t_prev, v_prev=v_prev, known=m.Bool(True), forced=None,
                     dt=None if dt is None else m.Float(dt), bracket=bracket)


@dataclass
class Sample:
    """A sample of a sampled march: the sub-interval's end ``b``, the sample's place ``t_s``
    and value ``v``, taken where ``take``."""

    b: Float
    t_s: Float
    v: Float
    take: Bool


def _next_leaf_sampled(ray: RayContext, march: March, tr: Trail, lattice: Lattice, active):
    """The walk moved on to the next leaf that may hold a crossing, or a skipped node across
    one (whose first sample is then taken after all, in the leaf where that node starts), a
    few search steps at a time (:meth:`~mi_amr.kernels.traverse.March.next`). Returns the
    march, the trail, the lanes still marching and those of them that take a sample now."""
    m, dev = ray.m, ray.dev
    uniform = ray.cfg.method == "uniform"
    march, leg = march.next(ray, tr.v_prev, active)
    st, skips = leg.stretch, leg.stretch.skips
    turned = leg.new & skips.turned
    # Past skipped nodes the previous sample becomes "their last one", on their side.
    skipped = leg.new & dr.isfinite(skips.side)
    t_last = lattice.before(skips.t_side) if uniform else skips.t_side
    moved_on = skipped & (t_last > tr.t_prev)
    tr.t_prev = dr.select(moved_on, t_last, tr.t_prev)
    tr.v_prev = dr.select(moved_on, skips.side, tr.v_prev)
    tr.known = dr.select(moved_on, False, tr.known)
    t = st.walk.t
    at = rec.locate(dev, ray.at(t + ray.eps(t)), turned)
    at_exit, _ = box_exit(m, dr.gather(m.Array3f, dev.leaf_lo, at, turned),
                          dr.gather(m.Array3f, dev.leaf_hi, at, turned), ray.o, ray.d)
    w = march.walk
    march.walk = dr.select(turned, Walk(node=w.node, leaf=at, face=m.UInt32(6),
                                        t_exit=at_exit, t=w.t), w)
    tr.forced = leg.new & turned
    active &= leg.onward | turned
    if not uniform:
        leaf_h = dr.gather(m.Float, dev.leaf_min_h, march.walk.leaf, active & leg.new)
        tr.dt = dr.select(leg.new, ray.cfg.step_scale * leaf_h / ray.dnorm, tr.dt)
    return march, tr, active, active & lnot(leg.searching)


def _sample(ray: RayContext, walk: Walk, tr: Trail, lattice: Lattice, values, active) -> Sample:
    """The next sub-interval ``[t, b]`` (up to a step position or the leaf's end) and its
    sample."""
    b, b_lattice, on_lattice = sub_interval(ray, walk, lattice)
    if ray.cfg.method == "uniform":
        # Uniform samples sit on the step positions themselves (a forced sample is the next
        # one, wherever it falls).
        t_s = b_lattice
        take = active & (on_lattice | tr.forced)
    else:
        t_s = 0.5 * (walk.t + b)
        take = ray.m.Bool(active)
    basis = ray.cfg.basis
    vals, _ = rec.reconstruct(ray.dev, basis, ray.at(t_s), values, take & lnot(tr.forced),
                              leaf=walk.leaf)
    vals_f, _ = rec.reconstruct(ray.dev, basis, ray.at(t_s), values, take & tr.forced)
    return Sample(b=b, t_s=t_s, v=dr.select(tr.forced, vals_f[0], vals[0]), take=take)


def _straddle(ray: RayContext, tr: Trail, smp: Sample, values):
    """A straddled isovalue between the previous sample and this one (if the previous one
    stands for a skipped node, it is evaluated where it is first). Returns the trail with the
    bracket kept, whether a crossing was found, and the extra samples taken."""
    m, cfg = ray.m, ray.cfg
    t_s, v, take = smp.t_s, smp.v, smp.take
    straddle = take & sides_differ(ray.dev, cfg, tr.v_prev, v)
    fix = straddle & lnot(tr.known)
    vals_p, _ = rec.reconstruct(ray.dev, cfg.basis, ray.at(tr.t_prev), values, fix)
    tr.v_prev = dr.select(fix, vals_p[0], tr.v_prev)
    best = m.Float(dr.inf)
    k_hit = tr.bracket.k_hit
    for k in range(cfg.num_iso):
        iso = cfg.iso(ray.dev, k)
        cross = take & ((tr.v_prev - iso) * (v - iso) <= 0.0) & (v != tr.v_prev)
        where = dr.select(cross, tr.t_prev + (iso - tr.v_prev) / (v - tr.v_prev) *
                          (t_s - tr.t_prev), dr.inf)
        pick = where < best
        best = dr.select(pick, where, best)
        k_hit = dr.select(pick, k, k_hit)
    got = best < dr.inf
    found = Bracket(hit=m.Bool(True), k_hit=k_hit, t_a=tr.t_prev, t_b=t_s, v_a=tr.v_prev,
                    v_b=v)
    tr.bracket = dr.select(got, found, Bracket(hit=tr.bracket.hit, k_hit=k_hit,
                                               t_a=tr.bracket.t_a, t_b=tr.bracket.t_b,
                                               v_a=tr.bracket.v_a, v_b=tr.bracket.v_b))
    tr.t_prev = dr.select(take, t_s, tr.t_prev)
    tr.v_prev = dr.select(take, v, tr.v_prev)
    tr.known = dr.select(take, True, tr.known)
    return tr, got, dr.select(fix, 1, 0)


@dr.syntax
def _march_sampled(ray: RayContext, jitter, v_before=None):
    """The first crossing on ``(ray.t0, ray.t1)`` by a sampling method; ``v_before``: the
    value of a previous sample at ``t0`` (NaN or None: none)."""
    m, cfg = ray.m, ray.cfg
    values = ray.dev.arrays(cfg.basis)
    uniform = cfg.method == "uniform"
    rho = m.Float(0.0) if uniform else jitter
    t_anchor = m.Float(ray.t0)
    march = March.start(ray)
    dt_fixed = m.Float(cfg.step_scale * ray.dev.min_h / ray.dnorm)
    tr = Trail.start(m, None if uniform else dt_fixed, ray.t0, v_before)
    samples = m.UInt32(0)
    active = m.Bool(ray.active)
    while dr.hint(active, label="first_crossing_sampled",
                  exclude=[m, cfg, dt_fixed, ray, rho, t_anchor, uniform, values]):
        march, tr, active, work = _next_leaf_sampled(
            ray, march, tr, Lattice(t_anchor, rho, dt_fixed if uniform else tr.dt), active)
        smp = _sample(ray, march.walk, tr, Lattice(t_anchor, rho, dt_fixed if uniform else tr.dt),
                      values, work)
        forced = tr.forced
        tr, got, extra = _straddle(ray, tr, smp, values)
        samples += dr.select(smp.take, 1, 0) + extra
        # --- Advance. After a forced sample, the rest of its node is skipped by the next seek.
        w = march.walk
        w.t = dr.select(work, dr.select(forced & (smp.t_s > smp.b), smp.t_s, smp.b), w.t)
        w.t_exit = dr.select(work & forced, -dr.inf, w.t_exit)
        march.walk = w
        tr.forced = None
        active &= lnot(got) & (w.t < ray.t1)
    return _sampled_crossing(ray, tr.bracket, samples)


def _sampled_crossing(ray: RayContext, br: Bracket, samples) -> Crossing:
    """The crossing in the bracket found: where the line through its samples meets the
    isovalue (``bisect``: after bisecting it)."""
    iso_hit = ray.cfg.iso(ray.dev, br.k_hit)
    t_hit = dr.select(br.hit, dr.clip(br.t_a + (iso_hit - br.v_a) / (br.v_b - br.v_a) *
                                      (br.t_b - br.t_a), dr.minimum(br.t_a, br.t_b),
                                      dr.maximum(br.t_a, br.t_b)), dr.inf)
    if ray.cfg.method == "bisect":
        t_hit = _bisect(ray, br)
    # Just past the isovalue, towards the bracket's far sample (that sample itself where the
    # step is lost to rounding).
    after = dr.fma(br.v_b - iso_hit, tol.RESUME_REL, iso_hit)
    after = dr.select(after == iso_hit, br.v_b, after)
    return Crossing(hit=br.hit, t=t_hit, k=br.k_hit, samples=samples, after=after)


@dr.syntax
def _bisect(ray: RayContext, br: Bracket):
    """Bisection of the bracket (whose ends straddle isovalue ``br.k_hit``) down to
    :data:`~mi_amr.tolerances.BISECT_TARGET` cells, then linear interpolation in the last
    interval."""
    m, cfg = ray.m, ray.cfg
    values = ray.dev.arrays(cfg.basis)
    active = br.hit
    t_a, t_b = br.t_a, br.t_b
    iso = cfg.iso(ray.dev, br.k_hit)
    fa = br.v_a - iso
    depth = bisect_depth(cfg)
    i = m.Float(0.0)
    while dr.hint(active & (i < depth), label="bisect",
                  exclude=[active, cfg, depth, iso, m, ray, values]):
        mid = 0.5 * (t_a + t_b)
        vals, _ = rec.reconstruct(ray.dev, cfg.basis, ray.at(mid), values, active)
        f = vals[0] - iso
        left = (f * fa) <= 0.0
        t_b = dr.select(left, mid, t_b)
        t_a = dr.select(left, t_a, mid)
        fa = dr.select(left, fa, f)
        i += 1.0
    vals, _ = rec.reconstruct(ray.dev, cfg.basis, ray.at(t_b), values, active)
    fb = vals[0] - iso
    t = t_a + fa / (fa - fb) * (t_b - t_a)
    # Where a value is missing (NaN data) the last interval may not straddle: stay inside it.
    inside = dr.isfinite(t) & (t >= dr.minimum(t_a, t_b)) & (t <= dr.maximum(t_a, t_b))
    return dr.select(active, dr.select(inside, t, 0.5 * (t_a + t_b)), dr.inf)
