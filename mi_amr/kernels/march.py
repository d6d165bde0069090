"""Finding isosurface crossings along rays: one kd-tree traversal shared by four methods.

A ray ``p(t) = o + t d`` (volume world space, ``d`` need not be unit length; ``t`` is the same
parameter as the caller's) is walked through the kd-tree by :func:`seek`: every node carries the
range of the reconstructed values inside it, and a node whose range holds no isovalue (or that
has no data) is skipped whole -- the ray jumps to the node's exit and restarts its descent at the
node's rope. So the consumer only ever sees leaves that may hold a crossing (pbrt's
majorant-segment shape: traversal hands ``[t, t_exit]`` stretches to the method):

* ``exact``: the ray is cut at every dual-cell plane of the levels that contribute (the owner's
  level for ``finest``, all active levels for ``basis``); inside each piece the field is
  ``N(s) / D(s)`` with cubic ``N`` and ``D`` (:func:`mi_amr.reconstruct.segment_cubic`), so each
  isovalue's crossings are the roots of the cubic ``N - iso D``, found without fail by
  :mod:`mi_amr.roots`. A jump of the field across an isovalue between pieces or skipped nodes
  (``finest`` at grid edges) counts as a crossing where the jump is.
* ``uniform``: samples every ``step_scale * h_min`` (``h_min``: the finest cell width of the
  volume) from the ray's entry; a crossing between two samples that straddle an isovalue is put
  where the line through them meets it.
* ``adaptive`` (ExaBricks): the step is ``step_scale`` times the finest cell width active in the
  leaf; step positions, offset by a per-ray random ``jitter`` in ``[0, 1)`` steps (interleaved
  sampling), and leaf boundaries delimit sub-intervals that are sampled at their mid-points.
* ``bisect``: ``adaptive``, then bisection between two straddling samples (the course report's
  "advanced adaptive sampling") down to ``0.005`` cells, then linear interpolation.

Skipping does not change what the sampling methods find: every value in a skipped node lies on
one side of each isovalue, which its range tells. When that side differs from the previous
sample's, the first sample inside the node is taken after all (and interpolated against the
previous one, as without skipping); when the next sample after a skipped node changes side, the
last position before it is evaluated. Uniform sampling is thereby unchanged; the adaptive methods
may place that last sample at the node's end instead of a sub-interval's middle.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels import roots
from mi_amr.kernels.device import NO_GRID, float_from_bits, gather, lnot

METHODS = ("exact", "bisect", "adaptive", "uniform")
RECONSTRUCTIONS = ("basis", "finest")
BISECT_TARGET = 0.005    # cells: bisection stops at this interval (course report, section 3.6.2)


@dataclass
class MarchConfig:
    """What a march looks for. ``method``, ``basis``, the number of isovalues and the band shape
    the kernel; ``isovalues`` (an array of that length) and ``step_scale`` are opaque values
    that may change between frames without recompiling."""

    method: str
    basis: bool
    isovalues: Any
    step_scale: Any
    num_iso: int
    band: Any = None            # volume mode: a shading.OpacityBand around isovalue 0
    band_table: Any = None      # its pre-integration table on the device
    preintegrated: bool = False

    def iso(self, dev, k):
        """Isovalue ``k`` (a Python int, or a per-lane index array)."""
        m = dev.m
        return gather(m.Float, self.isovalues, m.UInt32(k))


@dataclass
class Crossing:
    """Result of :func:`first_crossing`: ``t`` is ``inf`` where ``hit`` is False."""

    hit: Any
    t: Any
    k: Any           # index of the isovalue crossed
    samples: Any     # field evaluations (``exact``: cubic pieces) along the ray


@dataclass
class Stretch:
    """Result of :func:`seek`: the leaf to work on from ``t`` to ``t_exit`` (``found``), or the
    start ``t`` of a skipped node on the other side of an isovalue than ``side`` was
    (``turned``; ``turn_value`` is a value on that node's side). ``side`` is a value on the side
    of every isovalue that the last skipped node lies on (NaN: unknown), and ``t_side`` the end
    of that node."""

    node: Any
    leaf: Any
    t: Any
    t_exit: Any
    face: Any
    found: Any
    turned: Any
    turn_value: Any
    side: Any
    t_side: Any

    def adopt(self, new, node, leaf, face, t_exit, t):
        """The walk's ``(node, leaf, face, t_exit, t)``, taken from this stretch where ``new``
        (the lanes that sought a new leaf) and kept elsewhere."""
        return (dr.select(new, self.node, node), dr.select(new, self.leaf, leaf),
                dr.select(new, self.face, face), dr.select(new, self.t_exit, t_exit),
                dr.select(new, self.t, t))


# ---------------------------------------------------------------------- traversal

def box_interval(lo, hi, o, d):
    """Parametric interval ``(t_in, t_out)`` of the ray inside the box ``[lo, hi]``."""
    inv = dr.rcp(d)
    t_a = (lo - o) * inv
    t_b = (hi - o) * inv
    flat = d == 0.0
    inside = (o >= lo) & (o <= hi)
    near = dr.select(flat, dr.select(inside, -dr.inf, dr.inf), dr.minimum(t_a, t_b))
    far = dr.select(flat, dr.select(inside, dr.inf, -dr.inf), dr.maximum(t_a, t_b))
    return dr.max(near), dr.min(far)


def box_exit(m, lo, hi, o, d):
    """Parameter where the ray leaves the box ``[lo, hi]`` and the face it leaves through
    (``2 * axis + 1`` for the high face of ``axis``, ``2 * axis`` for the low one)."""
    face = dr.select(d > 0.0, hi, lo)
    t = dr.select(d != 0.0, (face - o) / d, dr.inf)
    t_exit = dr.min(t)
    axis = dr.select(t.x == t_exit, m.UInt32(0), dr.select(t.y == t_exit, m.UInt32(1),
                                                             m.UInt32(2)))
    up = dr.select(axis == 0, d.x > 0.0, dr.select(axis == 1, d.y > 0.0, d.z > 0.0))
    return t_exit, 2 * axis + dr.select(up, m.UInt32(1), m.UInt32(0))


def _epsilon(dev, t, dnorm):
    """A step in ``t`` well below a cell yet large enough to move ``t`` in float32."""
    return dr.maximum(1e-4 * dev.min_h / dnorm, dr.abs(t) * 4e-7)


def _holds(dev, cfg, r_lo, r_hi):
    """Can a value range ``[r_lo, r_hi]`` hold a crossing (or band opacity)?"""
    m = dev.m
    if cfg.band is not None:
        centre = cfg.iso(dev, 0)
        return (r_lo < centre + cfg.band.hi) & (r_hi > centre + cfg.band.lo)
    holds = m.Bool(False)
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        holds |= (r_lo <= iso) & (iso <= r_hi)
    return holds


def _sides_differ(dev, cfg, a, b):
    """Does some isovalue lie strictly between values ``a`` and ``b``? (False if one is NaN.)"""
    m = dev.m
    out = m.Bool(False)
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        out |= (a - iso) * (b - iso) < 0.0
    return out


def _node_box(dev, node, active):
    """Box of ``node`` (two packet loads of 4 floats)."""
    m = dev.m
    lo = gather(m.Array4f, dev.node_box, 2 * node, active)
    hi = gather(m.Array4f, dev.node_box, 2 * node + 1, active)
    return m.Array3f(lo.x, lo.y, lo.z), m.Array3f(hi.x, hi.y, hi.z)


def _restart(dev, o, d, t, node, face, active):
    """Where to resume the descent at ``o + t d`` after leaving ``node`` through ``face``: its
    rope when that node holds the point, else the root (also for ``face`` >= 6: no node yet).
    Returns the node and its box."""
    m = dev.m
    p = dr.fma(d, t, o)
    roped = active & (face < 6)
    rope = gather(m.UInt32, dev.node_ropes, node * 6 + dr.minimum(face, 5), roped)
    lo, hi = _node_box(dev, rope, roped)
    inside = roped & dr.all((p >= lo) & (p <= hi))
    root_lo, root_hi = m.Array3f(*dev.root_lo), m.Array3f(*dev.root_hi)
    return (dr.select(inside, rope, m.UInt32(0)), dr.select(inside, lo, root_lo),
            dr.select(inside, hi, root_hi))


@dr.syntax
def seek(dev, cfg, o, d, t, t1, node, face, side, active) -> Stretch:
    """From parameter ``t`` (having left ``node`` through ``face``; ``face`` = 6 at the start)
    walk to the first leaf whose value range may hold a crossing, skipping every node that
    cannot. Stops early at a skipped node on the other side of an isovalue than ``side``.

    One step either goes down one level (the child's box is the parent's, cut at the split, so
    it costs two packet loads: code and split, value range) or skips a node and restarts at its
    rope."""
    m = dev.m
    ranges = dev.node_ranges(cfg.basis)
    dnorm = dr.norm(d)
    t = m.Float(t)
    side = m.Float(side)
    eps = _epsilon(dev, t, dnorm)
    node, b_lo, b_hi = _restart(dev, o, d, t + eps, node, face, active)
    leaf = m.UInt32(0)
    t_exit = m.Float(t)
    face = m.UInt32(6)
    t_side = m.Float(dr.nan)
    found = m.Bool(False)
    turned = m.Bool(False)
    turn_value = m.Float(dr.nan)
    searching = m.Bool(active)
    while searching:
        eps = _epsilon(dev, t, dnorm)
        p = dr.fma(d, t + eps, o)
        cs = gather(m.Array2u, dev.node_code_split, node, searching)
        code = cs.x
        rng = gather(m.Array2f, ranges, node, searching)
        lo, hi = rng.x, rng.y
        t_out, f_out = box_exit(m, b_lo, b_hi, o, d)
        empty = lnot(_holds(dev, cfg, lo, hi))
        rep = dr.select(lo <= hi, 0.5 * (lo + hi), dr.nan)
        is_leaf = (code & 3) == 3

        # --- A leaf worth working on.
        take = searching & lnot(empty) & is_leaf
        found |= take
        leaf = dr.select(take, code >> 2, leaf)
        t_exit = dr.select(take, t_out, t_exit)
        face = dr.select(take, f_out, face)

        # --- An empty node on the other side: let the caller look at its first sample.
        turn = searching & empty & _sides_differ(dev, cfg, side, rep)
        turned |= turn
        turn_value = dr.select(turn, rep, turn_value)

        # --- Skip an empty node: jump to its exit and continue from its rope.
        skip = searching & empty & lnot(turn)
        side = dr.select(skip, rep, side)
        t_side = dr.select(skip, t_out, t_side)
        t_next = dr.maximum(t_out, t + eps)
        r_node, r_lo, r_hi = _restart(dev, o, d, t_next + _epsilon(dev, t_next, dnorm), node,
                                      f_out, skip)

        # --- Otherwise go down to the child holding the point.
        down = searching & lnot(empty) & lnot(is_leaf)
        axis = code & 3
        split = float_from_bits(m, cs.y)
        coord = dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))
        upper = coord >= split
        child = (code >> 2) + dr.select(upper, m.UInt32(1), m.UInt32(0))
        c_lo, c_hi = m.Array3f(b_lo), m.Array3f(b_hi)
        for a in range(3):
            cut = down & (axis == a)
            c_lo[a] = dr.select(cut & upper, split, c_lo[a])
            c_hi[a] = dr.select(cut & lnot(upper), split, c_hi[a])

        node = dr.select(skip, r_node, dr.select(down, child, node))
        b_lo = dr.select(skip, r_lo, c_lo)
        b_hi = dr.select(skip, r_hi, c_hi)
        t = dr.select(skip, t_next, t)
        searching &= lnot(take) & lnot(turn) & (t < t1)
    return Stretch(node=node, leaf=leaf, t=t, t_exit=t_exit, face=face, found=found,
                   turned=turned, turn_value=turn_value, side=side, t_side=t_side)


def next_dual_plane(dev, levels_mask, o, d, inv_d, t_probe):
    """Smallest parameter > ``t_probe`` (up to rounding) at which the ray crosses a plane through
    cell centres of a level in ``levels_mask`` (bit ``l`` for level ``l``); ``inv_d = 1 / d``
    (infinite where ``d`` is 0)."""
    m = dev.m
    p = dr.fma(d, t_probe, o)
    anchor = m.Array3f(*dev.anchor)
    up = d > 0.0
    best = m.Float(dr.inf)
    for level in range(dev.num_levels):
        h = m.Array3f(*dev.level_h[level])
        inv_h = m.Array3f(*[1.0 / x for x in dev.level_h[level]])
        cell = dr.floor(dr.fma(p - anchor, inv_h, -0.5))
        plane = dr.select(up, cell + 1.5, cell + 0.5)
        t = dr.select(d != 0.0, dr.fma(plane, h, anchor - o) * inv_d, dr.inf)
        on = ((levels_mask >> level) & 1) != 0
        best = dr.select(on, dr.minimum(best, dr.min(t)), best)
    return best


def _clip_to_volume(dev, o, d, t_start, t_end, active):
    """The ray's stretch inside the volume's bounds: ``(o, t0, t1, active)``. A ray lying in an
    upper face of the bounds is moved inside by a rounding step: kd points on a split plane go
    to the upper side, which beyond the upper faces holds no data."""
    m = dev.m
    lo = m.Array3f(*dev.bounds_lo)
    hi = m.Array3f(*dev.bounds_hi)
    on_top = (d == 0.0) & (o == hi)
    o = dr.select(on_top, hi - dr.maximum(dr.abs(hi), 1e-30) * 1.2e-7, o)
    t_in, t_out = box_interval(lo, hi, o, d)
    t0 = dr.maximum(t_start, t_in)
    t1 = dr.minimum(t_end, t_out)
    return o, t0, t1, m.Bool(active) & (t0 < t1)


# ---------------------------------------------------------------------- surfaces

def first_crossing(dev, cfg: MarchConfig, o, d, t_start, t_end, jitter, active) -> Crossing:
    """First crossing of any isovalue by the reconstructed field on ``(t_start, t_end)``.

    ``o``, ``d``: ray origin and direction in volume world space (``m.Array3f``); ``jitter``:
    per-ray offset in ``[0, 1)`` for the adaptive methods (ignored by ``exact`` and ``uniform``).
    """
    m = dev.m
    o, t0, t1, active = _clip_to_volume(dev, o, d, t_start, t_end, active)
    if cfg.method == "exact":
        return _march_exact(dev, cfg, o, d, t0, t1, active)
    return _march_sampled(dev, cfg, o, d, t0, t1, m.Float(jitter), active)


@dr.syntax
def _march_exact(dev, cfg, o, d, t0, t1, active):
    m = dev.m
    dnorm = dr.norm(d)
    inv_d = dr.select(d != 0.0, dr.rcp(d), dr.inf)
    values = dev.arrays(cfg.basis)
    level_masks = dev.leaf_levels if cfg.basis else dev.leaf_owner_levels
    t = m.Float(t0)
    node = m.UInt32(0)
    leaf = m.UInt32(0)
    face = m.UInt32(6)
    t_exit = m.Float(-dr.inf)
    v_prev = m.Float(dr.nan)
    samples = m.UInt32(0)
    hit = m.Bool(False)
    jump = m.Bool(False)
    k_jump = m.UInt32(0)
    t_seg = m.Float(0.0)
    # The cubics N, D and length of the piece holding the first crossing.
    n0, n1, n2, n3 = m.Float(0.0), m.Float(0.0), m.Float(0.0), m.Float(0.0)
    d0, d1, d2, d3 = m.Float(0.0), m.Float(0.0), m.Float(0.0), m.Float(0.0)
    L_hit = m.Float(0.0)
    while active:
        # --- Find the next leaf that may hold a crossing (skipping all that cannot).
        new = t >= t_exit
        st = seek(dev, cfg, o, d, t, t1, node, face, v_prev, active & new)
        node, leaf, face, t_exit, t = st.adopt(new, node, leaf, face, t_exit, t)
        v_prev = dr.select(new & dr.isfinite(st.side), st.side, v_prev)
        # A skipped node across an isovalue from what came before: the jump is the crossing.
        turned = new & st.turned
        hit |= turned
        jump = dr.select(turned, True, jump)
        t_seg = dr.select(turned, t, t_seg)
        k_jump = dr.select(turned, _first_between(dev, cfg, v_prev, st.turn_value), k_jump)
        active &= lnot(turned) & (lnot(new) | st.found)

        # --- The piece [t, t_b]: up to the next dual-cell plane of a contributing level.
        eps = _epsilon(dev, t, dnorm)
        mask = gather(m.UInt32, level_masks, leaf, active)
        t_b = dr.minimum(dr.minimum(next_dual_plane(dev, mask, o, d, inv_d, t + eps), t_exit),
                         t1)
        t_b = dr.maximum(t_b, t + eps)
        L = t_b - t
        p0 = dr.fma(d, t, o)
        nums, den = rec.segment_cubic(dev, cfg.basis, leaf, p0, d, 0.5 * L, values, active)
        num = nums[0]
        samples += dr.select(active, 1, 0)
        d_mid = roots.cubic(den, 0.5 * L)
        # The blend is undefined only where no cell has weight (next to missing values, the
        # weights can sum to much less than 1 and the field is still defined).
        have = active & (den[0] > 1e-6) & (roots.cubic(den, L) > 1e-6) & (d_mid > 1e-6)
        v_start = num[0] / den[0]
        v_end = roots.cubic(num, L) / roots.cubic(den, L)
        n_mid = roots.cubic(num, 0.5 * L)

        # --- Crossings: a jump at the piece's start, else a root of N - iso D.
        jumped = m.Bool(False)
        found = m.Bool(False)
        for k in range(cfg.num_iso):
            iso = cfg.iso(dev, k)
            jump_k = have & lnot(jumped) & ((v_prev - iso) * (v_start - iso) < 0.0)
            k_jump = dr.select(jump_k, k, k_jump)
            jumped |= jump_k
            c = [num[i] - iso * den[i] for i in range(4)]
            found_k, _, _ = roots.first_root_bracket(c, L, dr.abs(n_mid) + dr.abs(iso * d_mid))
            found |= have & found_k
        got = active & (jumped | found)
        hit |= got
        jump = dr.select(got, jumped, jump)
        t_seg = dr.select(got, t, t_seg)
        n0 = dr.select(got, num[0], n0)
        n1 = dr.select(got, num[1], n1)
        n2 = dr.select(got, num[2], n2)
        n3 = dr.select(got, num[3], n3)
        d0 = dr.select(got, den[0], d0)
        d1 = dr.select(got, den[1], d1)
        d2 = dr.select(got, den[2], d2)
        d3 = dr.select(got, den[3], d3)
        L_hit = dr.select(got, L, L_hit)

        # --- Advance to the piece's end.
        v_prev = dr.select(active, dr.select(have, v_end, dr.nan), v_prev)
        t = dr.select(active, t_b, t)
        active &= lnot(got) & (t < t1)

    # --- The earliest root among the isovalues in the piece that holds one (refined here, once
    # per ray: roots of different isovalues are compared where they are, not by their pieces).
    num, den = [n0, n1, n2, n3], [d0, d1, d2, d3]
    n_mid = roots.cubic(num, 0.5 * L_hit)
    d_mid = roots.cubic(den, 0.5 * L_hit)
    s_best = m.Float(dr.inf)
    k_hit = m.UInt32(0)
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        c = [num[i] - iso * den[i] for i in range(4)]
        found_k, a, b = roots.first_root_bracket(c, L_hit, dr.abs(n_mid) + dr.abs(iso * d_mid))
        s_k = dr.select(found_k, roots.refine_root(c, a, b), dr.inf)
        # A "root" where no cell has weight (N = D = 0) is not a crossing.
        s_k = dr.select(roots.cubic(den, s_k) > 1e-6, s_k, dr.inf)
        take = hit & lnot(jump) & (s_k < s_best)
        s_best = dr.select(take, s_k, s_best)
        k_hit = dr.select(take, k, k_hit)
    k_hit = dr.select(jump, k_jump, k_hit)
    hit &= jump | (s_best < dr.inf)
    t_hit = dr.select(hit, t_seg + dr.select(jump, 0.0, s_best), dr.inf)
    return Crossing(hit=hit, t=t_hit, k=k_hit, samples=samples)


def _first_between(dev, cfg, a, b):
    """Index of an isovalue strictly between values ``a`` and ``b`` (the first one listed)."""
    m = dev.m
    out = m.UInt32(0)
    for k in range(cfg.num_iso - 1, -1, -1):
        iso = cfg.iso(dev, k)
        out = dr.select((a - iso) * (b - iso) < 0.0, m.UInt32(k), out)
    return out


@dr.syntax
def _march_sampled(dev, cfg, o, d, t0, t1, jitter, active):
    m = dev.m
    dnorm = dr.norm(d)
    values = dev.arrays(cfg.basis)
    uniform = cfg.method == "uniform"
    rho = m.Float(0.0) if uniform else jitter
    t_anchor = m.Float(t0)
    t = m.Float(t0)
    node = m.UInt32(0)
    leaf = m.UInt32(0)
    face = m.UInt32(6)
    t_exit = m.Float(-dr.inf)
    dt = m.Float(cfg.step_scale * dev.min_h / dnorm)
    t_prev = m.Float(dr.nan)
    v_prev = m.Float(dr.nan)
    known = m.Bool(True)          # v_prev is a sample, not a skipped node's representative
    forced = m.Bool(False)        # sample this stretch once although its node was skipped
    samples = m.UInt32(0)
    hit = m.Bool(False)
    k_hit = m.UInt32(0)
    t_a, t_b = m.Float(0.0), m.Float(0.0)
    v_a, v_b = m.Float(0.0), m.Float(0.0)
    while active:
        # --- Find the next leaf that may hold a crossing, or a skipped node across one.
        new = t >= t_exit
        st = seek(dev, cfg, o, d, t, t1, node, face, v_prev, active & new)
        turned = new & st.turned
        # Past skipped nodes the previous sample becomes "their last one", on their side.
        skipped = new & dr.isfinite(st.side)
        if dr.hint(uniform, mode="scalar"):
            t_last = t_anchor + dr.floor((st.t_side - t_anchor) / dt - 1e-4) * dt
        else:
            t_last = st.t_side
        moved_on = skipped & (t_last > t_prev)
        t_prev = dr.select(moved_on, t_last, t_prev)
        v_prev = dr.select(moved_on, st.side, v_prev)
        known = dr.select(moved_on, False, known)
        # A turn: take the first sample of that node after all, in the leaf where it starts.
        at = rec.locate(dev, dr.fma(d, st.t + _epsilon(dev, st.t, dnorm), o), turned)
        at_exit, _ = box_exit(m, gather(m.Array3f, dev.leaf_lo, at, turned),
                              gather(m.Array3f, dev.leaf_hi, at, turned), o, d)
        node = dr.select(new, st.node, node)
        leaf = dr.select(turned, at, dr.select(new, st.leaf, leaf))
        face = dr.select(turned, m.UInt32(6), dr.select(new, st.face, face))
        t_exit = dr.select(turned, at_exit, dr.select(new, st.t_exit, t_exit))
        t = dr.select(new, st.t, t)
        forced = dr.select(new, turned, forced)
        active &= lnot(new) | st.found | turned
        if dr.hint(not uniform, mode="scalar"):
            leaf_h = gather(m.Float, dev.leaf_min_h, leaf, active & new)
            dt = dr.select(new, cfg.step_scale * leaf_h / dnorm, dt)

        # --- The next sub-interval [t, b] ends at a step position or the leaf's end.
        eps = _epsilon(dev, t, dnorm)
        step = dr.floor((t - t_anchor) / dt - rho + 1e-4) + 1.0
        b_lattice = t_anchor + (rho + step) * dt
        limit = dr.minimum(t_exit, t1)
        b = dr.maximum(dr.minimum(b_lattice, limit), t + eps)
        if dr.hint(uniform, mode="scalar"):
            # Uniform samples sit on the step positions themselves (a forced sample is the next
            # one, wherever it falls).
            t_s = b_lattice
            take = active & ((b_lattice <= limit) | forced)
        else:
            t_s = 0.5 * (t + b)
            take = m.Bool(active)
        vals, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_s, o), values, take & lnot(forced),
                                  leaf=leaf)
        vals_f, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_s, o), values, take & forced)
        v = dr.select(forced, vals_f[0], vals[0])
        samples += dr.select(take, 1, 0)

        # --- A straddled isovalue between the previous sample and this one. If the previous
        # one stands for a skipped node, evaluate it where it is first.
        straddle = take & _sides_differ(dev, cfg, v_prev, v)
        fix = straddle & lnot(known)
        vals_p, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_prev, o), values, fix)
        v_prev = dr.select(fix, vals_p[0], v_prev)
        samples += dr.select(fix, 1, 0)
        best = m.Float(dr.inf)
        for k in range(cfg.num_iso):
            iso = cfg.iso(dev, k)
            cross = take & ((v_prev - iso) * (v - iso) <= 0.0) & (v != v_prev)
            where = dr.select(cross, t_prev + (iso - v_prev) / (v - v_prev) * (t_s - t_prev),
                              dr.inf)
            pick = where < best
            best = dr.select(pick, where, best)
            k_hit = dr.select(pick, k, k_hit)
        got = best < dr.inf
        hit |= got
        t_a = dr.select(got, t_prev, t_a)
        t_b = dr.select(got, t_s, t_b)
        v_a = dr.select(got, v_prev, v_a)
        v_b = dr.select(got, v, v_b)
        t_prev = dr.select(take, t_s, t_prev)
        v_prev = dr.select(take, v, v_prev)
        known = dr.select(take, True, known)

        # --- Advance. After a forced sample, the rest of its node is skipped by the next seek.
        t = dr.select(forced & (t_s > b), t_s, b)
        t_exit = dr.select(forced, -dr.inf, t_exit)
        forced = m.Bool(False)
        active &= lnot(got) & (t < t1)

    iso_hit = cfg.iso(dev, k_hit)
    t_hit = dr.select(hit, dr.clip(t_a + (iso_hit - v_a) / (v_b - v_a) * (t_b - t_a),
                                   dr.minimum(t_a, t_b), dr.maximum(t_a, t_b)), dr.inf)
    if dr.hint(cfg.method == "bisect", mode="scalar"):
        t_hit = _bisect(dev, cfg, o, d, t_a, t_b, v_a, k_hit, hit)
    return Crossing(hit=hit, t=t_hit, k=k_hit, samples=samples)


@dr.syntax
def _bisect(dev, cfg, o, d, t_a, t_b, v_a, k, active):
    """Bisection of ``[t_a, t_b]`` (whose ends straddle isovalue ``k``) down to
    :data:`BISECT_TARGET` cells, then linear interpolation in the last interval."""
    m = dev.m
    values = dev.arrays(cfg.basis)
    iso = cfg.iso(dev, k)
    fa = v_a - iso
    depth = dr.maximum(dr.ceil(dr.log2(cfg.step_scale / BISECT_TARGET)), 1.0)
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


# ---------------------------------------------------------------------- volume mode

@dataclass
class Composite:
    """Result of :func:`composite`: premultiplied colour ``C`` and the transmittance ``T`` left."""

    C: Any
    T: Any
    samples: Any


def composite(dev, cfg: MarchConfig, o, d, t_start, t_end, jitter, color_of, lighting,
              active) -> Composite:
    """Front-to-back compositing of the opacity band ``cfg.band`` along the ray, with early
    termination when less than 1 % of the light gets through.

    ``color_of(value)`` gives the colour (``m.Array3f``) for a colour-field value;
    ``lighting(p, gradient, active)`` gives ``(A, S)`` such that the shaded colour of a sample of
    colour ``c`` is ``c * A + S`` (the Phong terms). With ``lighting=None`` only the
    transmittance is computed (shadow rays).

    ``exact``: each cubic piece is cut where the reconstructed value can turn relative to the
    band (at the extrema of ``N - v D`` for the band's low end, centre and high end), and each
    resulting piece contributes the pre-integrated opacity of a linear ramp between its end
    values: the band is never stepped over. The sampling methods take one sample per step with
    opacity correction (or pre-integration between consecutive samples); ``bisect`` moves a
    sample into the band when two samples straddle it (the course report's method).
    """
    m = dev.m
    o, t0, t1, active = _clip_to_volume(dev, o, d, t_start, t_end, active)
    if cfg.method == "exact":
        return _composite_exact(dev, cfg, o, d, t0, t1, color_of, lighting, active)
    return _composite_sampled(dev, cfg, o, d, t0, t1, m.Float(jitter), color_of, lighting, active)


def _sort(values):
    """Odd-even transposition sort of a short list of Dr.Jit values (ascending)."""
    v = list(values)
    for r in range(len(v)):
        for i in range(r % 2, len(v) - 1, 2):
            a, b = v[i], v[i + 1]
            v[i], v[i + 1] = dr.minimum(a, b), dr.maximum(a, b)
    return v


@dr.syntax
def _composite_exact(dev, cfg, o, d, t0, t1, color_of, lighting, active):
    m = dev.m
    band = cfg.band
    dnorm = dr.norm(d)
    inv_d = dr.select(d != 0.0, dr.rcp(d), dr.inf)
    shade = lighting is not None
    arrays = dev.arrays(cfg.basis, color=True)
    level_masks = dev.leaf_levels if cfg.basis else dev.leaf_owner_levels
    centre = cfg.iso(dev, 0)
    marks = [centre + band.lo, centre, centre + band.hi]
    C = m.Array3f(0.0)
    T = m.Float(1.0)
    t = m.Float(t0)
    node = m.UInt32(0)
    leaf = m.UInt32(0)
    t_exit = m.Float(-dr.inf)
    face = m.UInt32(6)
    samples = m.UInt32(0)
    while active:
        new = t >= t_exit
        st = seek(dev, cfg, o, d, t, t1, node, face, m.Float(dr.nan), active & new)
        node, leaf, face, t_exit, t = st.adopt(new, node, leaf, face, t_exit, t)
        active &= lnot(new) | st.found

        eps = _epsilon(dev, t, dnorm)
        work = m.Bool(active)
        mask = gather(m.UInt32, level_masks, leaf, work)
        t_b = dr.minimum(dr.minimum(next_dual_plane(dev, mask, o, d, inv_d, t + eps), t_exit),
                         t1)
        t_b = dr.maximum(t_b, t + eps)
        L = t_b - t
        p0 = dr.fma(d, t, o)
        nums, den = rec.segment_cubic(dev, cfg.basis, leaf, p0, d, 0.5 * L, arrays, work)
        samples += dr.select(work, 1, 0)
        have = work & (roots.cubic(den, 0.5 * L) > 1e-3)

        # --- Pieces on which the value cannot turn back across the band's ends or centre.
        cuts = []
        for v in marks:
            r1, r2 = roots.extrema([nums[0][i] - v * den[i] for i in range(4)], L)
            cuts += [r1, r2]
        s_pts = [0.0 * L] + _sort(cuts) + [L]
        values = [roots.cubic(nums[0], s) / roots.cubic(den, s) for s in s_pts]
        alphas, mids = [], []
        best_alpha = m.Float(0.0)
        s_best = m.Float(0.0)
        for i in range(len(s_pts) - 1):
            dx = (s_pts[i + 1] - s_pts[i]) * dnorm
            a = band.segment_alpha(m, cfg.band_table, values[i], values[i + 1], dx, centre)
            a = dr.select(have & (dx > 0.0), a, 0.0)
            mid = 0.5 * (s_pts[i] + s_pts[i + 1])
            alphas.append(a)
            mids.append(mid)
            better = a > best_alpha
            best_alpha = dr.select(better, a, best_alpha)
            s_best = dr.select(better, mid, s_best)

        # --- Light once per piece of the ray, where it is most opaque.
        lit = have & (best_alpha > 1e-3)
        if dr.hint(shade, mode="scalar"):
            p_best = dr.fma(d, t + s_best, o)
            _, grad = rec.reconstruct(dev, cfg.basis, p_best, arrays[:1], lit, leaf=leaf)
            A, S = lighting(p_best, grad, lit)
        for i in range(len(alphas)):
            a = alphas[i]
            if dr.hint(shade, mode="scalar"):
                cval = roots.cubic(nums[1], mids[i]) / roots.cubic(den, mids[i])
                C += dr.select(a > 0.0, T * a * (color_of(cval) * A + S), 0.0)
            T *= 1.0 - a

        t = dr.select(active, t_b, t)
        active &= (t < t1) & (T > 0.01)
    T = dr.select(T <= 0.01, 0.0, T)
    return Composite(C=C, T=T, samples=samples)


@dr.syntax
def _composite_sampled(dev, cfg, o, d, t0, t1, jitter, color_of, lighting, active):
    m = dev.m
    band = cfg.band
    dnorm = dr.norm(d)
    shade = lighting is not None
    uniform = cfg.method == "uniform"
    arrays = dev.arrays(cfg.basis, color=True)
    centre = cfg.iso(dev, 0)
    band_lo, band_hi = centre + band.lo, centre + band.hi
    # A shadow ray starts inside the band: uniform steps then sample the middle of each step,
    # so its first half step (the most opaque stretch) is not stepped over.
    rho = m.Float(-0.5 if not shade else 0.0) if uniform else jitter
    t_anchor = m.Float(t0)
    t = m.Float(t0)
    node = m.UInt32(0)
    leaf = m.UInt32(0)
    t_exit = m.Float(-dr.inf)
    face = m.UInt32(6)
    dt = m.Float(cfg.step_scale * dev.min_h / dnorm)
    t_prev = m.Float(t0)
    v_prev = m.Float(dr.nan)
    C = m.Array3f(0.0)
    T = m.Float(1.0)
    samples = m.UInt32(0)
    while active:
        # Skipped nodes have no opacity; the sample before them no longer borders the next one.
        new = t >= t_exit
        st = seek(dev, cfg, o, d, t, t1, node, face, m.Float(dr.nan), active & new)
        # After skipped nodes (no opacity) the next step's stretch starts where the leaf does.
        skipped = new & (st.t > t)
        v_prev = dr.select(skipped, dr.nan, v_prev)
        t_prev = dr.select(skipped, st.t, t_prev)
        node, leaf, face, t_exit, t = st.adopt(new, node, leaf, face, t_exit, t)
        active &= lnot(new) | st.found
        eps = _epsilon(dev, t, dnorm)
        if dr.hint(not uniform, mode="scalar"):
            leaf_h = gather(m.Float, dev.leaf_min_h, leaf, active & new)
            dt = dr.select(new, cfg.step_scale * leaf_h / dnorm, dt)

        step = dr.floor((t - t_anchor) / dt - rho + 1e-4) + 1.0
        b_lattice = t_anchor + (rho + step) * dt
        b = dr.maximum(dr.minimum(dr.minimum(b_lattice, t_exit), t1), t + eps)
        if dr.hint(uniform, mode="scalar"):
            t_s = b_lattice
            take = active & (b_lattice <= dr.minimum(t_exit, t1))
        else:
            t_s = 0.5 * (t + b)
            take = m.Bool(active)
        vals, grad = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_s, o), arrays, take, leaf=leaf)
        v = vals[0]
        cval = vals[1]
        samples += dr.select(take, 1, 0)

        if dr.hint(cfg.method == "bisect", mode="scalar"):
            # Two samples on either side of the band: move this sample into it if a point in
            # between lies in the band (course report, section 3.6.2).
            straddle = take & (((v_prev < band_lo) & (v > band_hi)) |
                               ((v_prev > band_hi) & (v < band_lo)))
            t_m, found = _bisect_band(dev, cfg, o, d, t_prev, t_s, v_prev, band_lo, band_hi,
                                      straddle)
            moved = straddle & found
            vals_m, grad_m = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_m, o), arrays, moved)
            t_s = dr.select(moved, t_m, t_s)
            v = dr.select(moved, vals_m[0], v)
            cval = dr.select(moved, vals_m[1], cval)
            grad = dr.select(moved, grad_m, grad)

        # Opacity-correction weight: the step (uniform), the sub-interval (adaptive, ExaBricks)
        # or the distance from the previous sample (bisect, course report).
        if dr.hint(uniform, mode="scalar"):
            dx = dt * dnorm
        elif dr.hint(cfg.method == "adaptive", mode="scalar"):
            dx = (b - t) * dnorm
        else:
            dx = (t_s - t_prev) * dnorm
        if dr.hint(cfg.preintegrated, mode="scalar"):
            # The value runs from the previous sample to this one: integrate over that distance.
            # Steps tile the ray from one sample to the next (the first from where the ray
            # or the leaf starts, at the first sample's value).
            span = (t_s - t_prev) * dnorm
            a = dr.select(dr.isfinite(v_prev),
                          band.segment_alpha(m, cfg.band_table, v_prev, v, span, centre),
                          band.corrected(band.alpha(m, v, centre), span))
        else:
            a = band.corrected(band.alpha(m, v, centre), dx)
        a = dr.select(take & dr.isfinite(v), a, 0.0)
        if dr.hint(shade, mode="scalar"):
            lit = take & (a > 1e-3)
            t_light = t_s
            if dr.hint(cfg.preintegrated, mode="scalar"):
                # The opacity of a pre-integrated step sits where the value ramp passes the
                # band's centre, not at the step's end: light it there.
                f = dr.clip((centre - v_prev) / (v - v_prev), 0.0, 1.0)
                t_light = dr.select(dr.isfinite(f), dr.lerp(t_prev, t_s, f), t_s)
            A, S = lighting(dr.fma(d, t_light, o), grad, lit)
            C += dr.select(lit, T * a * (color_of(cval) * A + S), 0.0)
        T *= 1.0 - a
        t_prev = dr.select(take, t_s, t_prev)
        v_prev = dr.select(take, v, v_prev)

        t = dr.select(active, b, t)
        active &= (t < t1) & (T > 0.01)
    T = dr.select(T <= 0.01, 0.0, T)
    return Composite(C=C, T=T, samples=samples)


@dr.syntax
def _bisect_band(dev, cfg, o, d, t_a, t_b, v_a, band_lo, band_hi, active):
    """A point of ``[t_a, t_b]`` whose value lies in ``(band_lo, band_hi)``, by bisection on the
    side of the band that ``v_a`` is on; returns ``(t, found)``."""
    m = dev.m
    values = dev.arrays(cfg.basis)
    below = v_a < band_lo
    depth = dr.maximum(dr.ceil(dr.log2(cfg.step_scale / BISECT_TARGET)), 1.0)
    i = m.Float(0.0)
    found = m.Bool(False)
    t_found = m.Float(0.0)
    while active & lnot(found) & (i < depth):
        mid = 0.5 * (t_a + t_b)
        vals, _ = rec.reconstruct(dev, cfg.basis, dr.fma(d, mid, o), values, active & lnot(found))
        v = vals[0]
        inside = (v > band_lo) & (v < band_hi)
        found |= inside
        t_found = dr.select(inside, mid, t_found)
        # Still on the starting side: the band lies further on.
        same = dr.select(below, v <= band_lo, v >= band_hi)
        t_a = dr.select(same, mid, t_a)
        t_b = dr.select(same, t_b, mid)
        i += 1.0
    return t_found, found
