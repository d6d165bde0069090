"""Walking a ray through the kd-tree and its cells: the one traversal every march consumes
(pbrt-v4's majorant-segment shape, ``SampleRay``: the walk hands pieces of the ray to the code
that consumes them, which never walks the tree itself).

A :class:`March` is the walk's state; a consumer (first crossings and layers,
:mod:`mi_amr.kernels.surface`; compositing, :mod:`mi_amr.kernels.composite`; shadow
transmittance, :mod:`mi_amr.kernels.transmit`) calls :meth:`March.next` once per step of its
loop. That moves the lanes that have used up their leaf on to the next leaf whose value range
may hold a crossing, skipping every node that cannot, and reports what the skipped nodes told
(:class:`Leg`). The consumer then takes a piece of the leaf from the walk's ``t``: a cubic
piece up to the next dual-cell plane (:func:`piece_end`) or a sample up to the next lattice
position (:class:`Lattice`), and moves the walk's ``t`` to its end.

The leaf search (:func:`seek_steps`): every node carries the range of the reconstructed values
inside it, and a node whose range holds no isovalue (or that has no data) is skipped whole --
the ray jumps to the node's exit and restarts its descent at the node's rope. Rays are in the
volume's world space (:class:`~mi_amr.kernels.ray.RayContext`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels import roots
from mi_amr.kernels.config import holds, sides_differ, start_table
from mi_amr.kernels.device import NODE_RECORDS, lnot
from mi_amr.kernels.ray import RayContext, box_interval  # noqa: F401  (box_interval re-exported)
from mi_amr.kernels.starts import table_start

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Array3f, Bool, Float, UInt32


@dataclass
class Walk:
    """Where a ray is in its walk: at parameter ``t`` inside ``leaf`` (reached through
    ``node``), which it leaves at ``t_exit`` through ``face`` (6: no leaf yet)."""

    node: UInt32
    leaf: UInt32
    face: UInt32
    t_exit: Float
    t: Float

    @staticmethod
    def start(m, t0) -> "Walk":
        return Walk(node=m.UInt32(0), leaf=m.UInt32(0), face=m.UInt32(6),
                    t_exit=m.Float(-dr.inf), t=m.Float(t0))

    def needs_leaf(self):
        """The lanes that have used up their leaf and must seek the next."""
        return self.t >= self.t_exit

    @staticmethod
    def within(ray, held: "Walk") -> "Walk":
        """A walk from ``ray.t0`` in the leaf of another ray's walk ``held`` (its ``node`` and
        ``leaf``), which holds this ray's start: a lit piece's shadow ray begins in the piece's
        own leaf, with no search from the root. Where the start lies outside that leaf's box
        after all (rounding), its exit is behind the start and the first search begins at the
        leaf's rope, or else at the root."""
        lo, hi = _node_box(ray.dev, held.node, ray.active)
        t_exit, face = box_exit(ray.m, lo, hi, ray.o, ray.d)
        return Walk(node=ray.m.UInt32(held.node), leaf=ray.m.UInt32(held.leaf), face=face,
                    t_exit=t_exit, t=ray.m.Float(ray.t0))


@dataclass
class Skips:
    """What the nodes a leaf search skipped told: ``side``, a value on the side of every
    isovalue that the last skipped node lies on (NaN: unknown), and ``t_side`` the end of that
    node; ``turned``: the search stopped at the start of a skipped node on the other side of an
    isovalue than the side it started from, ``turn_value`` a value on that node's side."""

    side: Float
    t_side: Float
    turned: Bool
    turn_value: Float


@dataclass
class Stretch:
    """What a leaf search found: the walk at the leaf to work on from ``walk.t`` to
    ``walk.t_exit`` (``found``), or at the start of the skipped node it turned at (``skips``);
    ``walk.node`` is the node it ended at."""

    walk: Walk
    found: Bool
    skips: Skips


@dataclass
class Seeking:
    """A leaf search under way (see :func:`seek_start`, :func:`seek_steps`): the
    :class:`Stretch` so far (``stretch.walk.node`` and ``stretch.walk.t``: the node it is at
    and the parameter), that node's box ``[lo, hi]``, and whether it goes on (``searching``)."""

    stretch: Stretch
    lo: Array3f
    hi: Array3f
    searching: Bool


@dataclass
class Leg:
    """What :meth:`March.next` reports. ``new``: the lanes whose search ended now (their walk
    moved on to ``stretch``); ``searching``: a search still under way (no leaf to work on this
    step); ``onward``: not a search that ended without a leaf (at the end of the ray);
    ``steps``: the search steps (nodes visited) taken."""

    new: Bool
    stretch: Stretch
    searching: Bool
    onward: Bool
    steps: UInt32


@dataclass
class March:
    """The one traversal of a ray: its :class:`Walk` and the leaf search under way
    (``search``; None where each search is taken whole, see :meth:`start`)."""

    walk: Walk
    search: Optional[Seeking]

    @staticmethod
    def start(ray: RayContext, t=None, whole=False, walk=None) -> "March":
        """A walk from ``t`` (default ``ray.t0``), or going on with ``walk``. ``whole``: each
        leaf search is taken at once instead of ``ray.cfg.search.steps`` steps per call of
        :meth:`next`; a consumer whose step costs far more than a search step (volume mode's
        exact pieces, each lit with its own shadow rays) is faster so, as the search's state
        then is no loop state."""
        m = ray.m
        walk = Walk.start(m, ray.t0 if t is None else t) if walk is None else walk
        if whole:
            return March(walk=walk, search=None)
        return March(walk=walk, search=seek_start(ray, walk, m.Float(dr.nan), m.Bool(False)))

    def next(self, ray: RayContext, side, active):
        """The walk moved on, where ``active`` lanes have used up their leaf, towards the next
        leaf that may hold a crossing (stopping early at a skipped node on the other side of
        an isovalue than the value ``side``): ``(march, leg)``."""
        needs = active & self.walk.needs_leaf()
        if self.search is None:
            sk, steps = seek_steps(ray, seek_start(ray, self.walk, side, needs), None)
            new = needs
        else:
            begin = needs & lnot(self.search.searching)
            sk = dr.select(begin, seek_start(ray, self.walk, side, begin, start_table(ray.cfg)),
                           self.search)
            sk, steps = seek_steps(ray, sk, ray.cfg.search.steps)
            new = needs & lnot(sk.searching)
        st = sk.stretch
        walk = dr.select(new, st.walk, self.walk)
        leg = Leg(new=new, stretch=st, searching=sk.searching, onward=lnot(new) | st.found,
                  steps=steps)
        return March(walk=walk, search=None if self.search is None else sk), leg


# ---------------------------------------------------------------------- boxes

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


def _node_box(dev, node, active):
    """Box of ``node`` (two packet loads of 4 floats)."""
    m = dev.m
    lo = dr.gather(m.Array4f, dev.node_box, 2 * node, active)
    hi = dr.gather(m.Array4f, dev.node_box, 2 * node + 1, active)
    return m.Array3f(lo.x, lo.y, lo.z), m.Array3f(hi.x, hi.y, hi.z)


def _restart(ray: RayContext, t, node, face, active, table=None):
    """Where to resume the descent at ``o + t d`` after leaving ``node`` through ``face``: its
    rope when that node holds the point, else the root (also for ``face`` >= 6: no node yet).
    Given a start ``table`` (:mod:`mi_amr.kernels.starts`), the deeper of its node for the
    point and the rope, and the rope is not read where the table's entry is final (a leaf, or
    a node to skip). Returns the node and its box."""
    dev, m = ray.dev, ray.m
    p = ray.at(t)
    roped = active & (face < 6)
    if table is None:
        rope, lo, hi, inside = _rope(dev, p, node, face, roped)
        return (dr.select(inside, rope, m.UInt32(0)), dr.select(inside, lo, dev.root_lo),
                dr.select(inside, hi, dev.root_hi))
    t_node, t_lo, t_hi, found, final = table_start(dev, table, p, active)
    rope, lo, hi, inside = _rope_unless(dev, p, node, face, roped & lnot(found & final))
    # Both hold the point, so one holds the other: the smaller box is the deeper node.
    inside &= lnot(found) | (dr.sum(hi - lo) < dr.sum(t_hi - t_lo))
    start = dr.select(inside, rope, dr.select(found, t_node, m.UInt32(0)))
    s_lo = dr.select(inside, lo, dr.select(found, t_lo, dev.root_lo))
    s_hi = dr.select(inside, hi, dr.select(found, t_hi, dev.root_hi))
    return start, s_lo, s_hi


def _rope(dev, p, node, face, active):
    """``(rope, lo, hi, inside)``: the rope of ``node``'s ``face``, its box, and whether it
    holds the point ``p`` -- half open, as the descent goes (a point on a split plane belongs
    to the upper node; a closed test let a rope lying below such a point hold it, whose
    descent then met a leaf only touching it)."""
    m = dev.m
    rope = dr.gather(m.UInt32, dev.node_ropes, node * 6 + dr.minimum(face, 5), active)
    lo, hi = _node_box(dev, rope, active)
    return rope, lo, hi, active & dr.all((p >= lo) & (p < hi))


@dr.syntax
def _rope_unless(dev, p, node, face, active):
    """:func:`_rope` in a symbolic branch: a packet with no lane needing its rope skips the
    loads (``inside`` False there)."""
    m = dev.m
    rope, lo, hi, inside = m.UInt32(0), m.Array3f(0.0), m.Array3f(0.0), m.Bool(False)
    if dr.hint(active, label="rope"):
        rope, lo, hi, inside = _rope(dev, p, node, face, active)
    return rope, lo, hi, inside


# ---------------------------------------------------------------------- the leaf search

def seek_start(ray: RayContext, walk: Walk, side, active, table=None) -> Seeking:
    """A leaf search from ``walk.t`` having left ``walk.node`` through ``walk.face`` (6: no
    node yet), before its first step (from the node of the start ``table`` where it has one
    and no rope leads on); ``side``: a value on the side of the isovalues the ray comes
    from (NaN: unknown)."""
    m = ray.m
    t = m.Float(walk.t)
    node, lo, hi = _restart(ray, t + ray.eps(t), walk.node, walk.face, active, table)
    at = Walk(node=node, leaf=m.UInt32(0), face=m.UInt32(6), t_exit=m.Float(t), t=t)
    skips = Skips(side=m.Float(side), t_side=m.Float(dr.nan), turned=m.Bool(False),
                  turn_value=m.Float(dr.nan))
    return Seeking(stretch=Stretch(walk=at, found=m.Bool(False), skips=skips), lo=lo, hi=hi,
                   searching=m.Bool(active))


@dr.syntax
def seek_steps(ray: RayContext, sk: Seeking, max_steps):
    """Up to ``max_steps`` steps of the search ``sk`` (all of them for None): ``(sk, steps)``,
    ``steps`` the nodes it visited. One step either goes down one level (the child's box is
    the parent's, cut at the split, so it costs two packet loads: code and split, value range)
    or skips a node and restarts at its rope."""
    m = ray.m
    records = ray.dev.node_search(ray.cfg.basis)
    steps = m.UInt32(0)
    limit = m.UInt32(0xFFFFFFFF if max_steps is None else max_steps)
    going = sk.searching & (steps < limit)
    while dr.hint(going, label="seek", exclude=[limit, m, ray, records]):
        cs = dr.gather(m.Array4u, records, NODE_RECORDS * sk.stretch.walk.node, going)
        # A camera ray's search is mostly descents through non-empty inner nodes: two levels
        # a turn (:class:`~mi_amr.kernels.config.SearchPlan`).
        if dr.hint(ray.cfg.search.two_levels, mode="scalar"):
            sk, cs, steps = _through(ray, records, sk, cs, going & (steps + 1 < limit), steps)
        sk = _seek_step(ray, sk, cs, going)
        steps += 1
        going = sk.searching & (steps < limit)
    return sk, steps


def _through(ray: RayContext, records, sk: Seeking, cs, going, steps):
    """Through a non-empty inner node to its child (what a full step would do):
    ``(sk, cs, steps)`` with the child's record."""
    m = ray.m
    at = sk.stretch.walk
    p = ray.at(at.t + ray.eps(at.t))
    lo = dr.reinterpret_array(m.Float, cs.z)
    hi = dr.reinterpret_array(m.Float, cs.w)
    through = going & holds(ray.dev, ray.cfg, lo, hi) & ((cs.x & 3) != 3) & (at.t < ray.t1)
    kids = [dr.gather(m.Array4u, records, NODE_RECORDS * at.node + 1 + c, through)
            for c in (0, 1)]
    child, upper, sk.lo, sk.hi = _child(m, cs, p, sk.lo, sk.hi, through)
    at.node = dr.select(through, child, at.node)
    cs = dr.select(through, dr.select(upper, kids[1], kids[0]), cs)
    return sk, cs, steps + dr.select(through, 1, 0)


@dr.syntax
def _seek_step(ray: RayContext, sk: Seeking, cs, going) -> Seeking:
    """One full step of the search at the node of record ``cs``: take a leaf worth working
    on, stop at an empty node across an isovalue, skip an empty node, or go down."""
    m, st = ray.m, sk.stretch
    at, skips = st.walk, st.skips
    eps = ray.eps(at.t)
    p = ray.at(at.t + eps)
    code = cs.x
    lo = dr.reinterpret_array(m.Float, cs.z)
    hi = dr.reinterpret_array(m.Float, cs.w)
    t_out, f_out = box_exit(m, sk.lo, sk.hi, ray.o, ray.d)
    empty = lnot(holds(ray.dev, ray.cfg, lo, hi))
    rep = dr.select(lo <= hi, 0.5 * (lo + hi), dr.nan)
    is_leaf = (code & 3) == 3

    # --- A leaf worth working on.
    take = going & lnot(empty) & is_leaf
    st.found |= take
    at.leaf = dr.select(take, code >> 2, at.leaf)
    at.t_exit = dr.select(take, t_out, at.t_exit)
    at.face = dr.select(take, f_out, at.face)

    # --- An empty node on the other side: let the caller look at its first sample.
    turn = going & empty & sides_differ(ray.dev, ray.cfg, skips.side, rep)
    skips.turned |= turn
    skips.turn_value = dr.select(turn, rep, skips.turn_value)

    # --- Skip an empty node: jump to its exit and continue from its rope.
    skip = going & empty & lnot(turn)
    skips.side = dr.select(skip, rep, skips.side)
    skips.t_side = dr.select(skip, t_out, skips.t_side)
    t_next = dr.maximum(t_out, at.t + eps)
    # A symbolic branch: a packet with no lane skipping jumps over the rope restart's loads.
    r_node, r_lo, r_hi = m.UInt32(at.node), m.Array3f(sk.lo), m.Array3f(sk.hi)
    if dr.hint(skip, label="skip"):
        r_node, r_lo, r_hi = _restart(ray, t_next + ray.eps(t_next), at.node, f_out, skip)

    # --- Otherwise go down to the child holding the point.
    down = going & lnot(empty) & lnot(is_leaf)
    child, _, c_lo, c_hi = _child(m, cs, p, sk.lo, sk.hi, down)

    at.node = dr.select(skip, r_node, dr.select(down, child, at.node))
    sk.lo = dr.select(skip, r_lo, dr.select(going, c_lo, sk.lo))
    sk.hi = dr.select(skip, r_hi, dr.select(going, c_hi, sk.hi))
    at.t = dr.select(skip, t_next, at.t)
    sk.searching &= lnot(going & (take | turn | (at.t >= ray.t1)))
    return sk


def _child(m, cs, p, b_lo, b_hi, down):
    """The child of the inner node with record ``cs`` (box ``[b_lo, b_hi]``) holding the point
    ``p`` (a point on the split goes up), whether it is the upper one, and its box: ``(child,
    upper, c_lo, c_hi)``, the box being the node's where ``down`` is False."""
    axis = cs.x & 3
    split = dr.reinterpret_array(m.Float, cs.y)
    coord = dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))
    upper = coord >= split
    child = (cs.x >> 2) + dr.select(upper, m.UInt32(1), m.UInt32(0))
    c_lo, c_hi = m.Array3f(b_lo), m.Array3f(b_hi)
    for a in range(3):
        cut = down & (axis == a)
        c_lo[a] = dr.select(cut & upper, split, c_lo[a])
        c_hi[a] = dr.select(cut & lnot(upper), split, c_hi[a])
    return child, upper, c_lo, c_hi


# ---------------------------------------------------------------------- pieces of a leaf

@dr.syntax
def next_dual_plane(ray: RayContext, levels_mask, t_probe):
    """Smallest parameter > ``t_probe`` (up to rounding) at which the ray crosses a plane through
    cell centres of a level in ``levels_mask`` (bit ``l`` for level ``l``). The levels are
    visited bit by bit, so the traced program is the same whatever the number of levels."""
    dev, m, o, d = ray.dev, ray.m, ray.o, ray.d
    p = dr.fma(d, t_probe, o)
    up = d > 0.0
    best = m.Float(dr.inf)
    mask = m.UInt32(levels_mask)
    while dr.hint(mask != 0, label="dual_planes", exclude=[d, dev, o, p, ray, up]):
        level = dr.tzcnt(mask)
        mask &= mask - 1
        h = dev.level_h(level)
        inv_h = dev.level_inv_h(level)
        cell = dr.floor(dr.fma(p - dev.anchor, inv_h, -0.5))
        plane = dr.select(up, cell + 1.5, cell + 0.5)
        t = dr.select(d != 0.0, dr.fma(plane, h, dev.anchor - o) * ray.inv_d, dr.inf)
        best = dr.minimum(best, dr.min(t))
    return best


def piece_end(ray: RayContext, walk: Walk, active):
    """The end of the cubic piece of the ray from ``walk.t``: the next dual-cell plane of a
    level that contributes in the walk's leaf, the leaf's end or ``ray.t1`` (at least a
    rounding step on)."""
    eps = ray.eps(walk.t)
    mask = dr.gather(ray.m.UInt32, ray.level_masks, walk.leaf, active)
    t_b = dr.minimum(dr.minimum(next_dual_plane(ray, mask, walk.t + eps), walk.t_exit), ray.t1)
    return dr.maximum(t_b, walk.t + eps)


@dataclass
class Lattice:
    """The step positions of a sampling method: ``anchor + (rho + i) dt`` for integers ``i``
    (``rho``: the per-ray offset in steps, ``dt``: the step in ``t``)."""

    anchor: Float
    rho: Float
    dt: Float

    def after(self, t):
        """The first step position past ``t`` (up to :data:`~mi_amr.tolerances.LATTICE_SNAP`
        of a step)."""
        step = dr.floor((t - self.anchor) / self.dt - self.rho + tol.LATTICE_SNAP) + 1.0
        return self.anchor + (self.rho + step) * self.dt

    def before(self, t):
        """The last step position (of offset 0) before ``t``."""
        return self.anchor + dr.floor((t - self.anchor) / self.dt - tol.LATTICE_SNAP) * self.dt


def sub_interval(ray: RayContext, walk: Walk, lattice: Lattice):
    """The sub-interval of a sampling method from ``walk.t``: up to the next step position or
    the leaf's (or ray's) end, at least a rounding step. Returns its end ``b``, the step
    position ``b_lattice`` and whether that lies inside the leaf and the ray."""
    b_lattice = lattice.after(walk.t)
    limit = dr.minimum(walk.t_exit, ray.t1)
    b = dr.maximum(dr.minimum(b_lattice, limit), walk.t + ray.eps(walk.t))
    return b, b_lattice, b_lattice <= limit


@dataclass
class CubicPiece:
    """A piece of the ray from ``t`` to ``end`` (``length = end - t``) inside one leaf, between
    dual-cell planes, on which the reconstruction is ``N(s) / D(s)`` with ``s = t' - t``:
    ``nums`` the numerator cubics (the field's, then the colour field's where asked for) and
    ``den`` the shared denominator, 4 coefficients each
    (:func:`mi_amr.kernels.reconstruct.segment_cubic`)."""

    t: Float
    end: Float
    length: Float
    nums: list
    den: list

    @property
    def num(self) -> list:
        """The field's numerator."""
        return self.nums[0]

    def mid(self):
        """``(N, D)`` at the piece's middle."""
        half = 0.5 * self.length
        return roots.cubic(self.num, half), roots.cubic(self.den, half)

    def defined(self, active, d_mid, ends=True):
        """Is the field defined on the piece: some cell has weight at its middle (``d_mid``:
        ``D`` there) and, with ``ends``, at its start and end. Next to missing values the
        weights can sum to much less than 1 and the field is still defined."""
        out = active & (d_mid > tol.NO_WEIGHT)
        if ends:
            out &= (self.den[0] > tol.NO_WEIGHT) & \
                (roots.cubic(self.den, self.length) > tol.NO_WEIGHT)
        return out

    def value_at_end(self):
        """The field's value ``N / D`` at the piece's end."""
        return roots.cubic(self.num, self.length) / roots.cubic(self.den, self.length)


def cubic_piece(ray: RayContext, walk: Walk, arrays, active) -> CubicPiece:
    """The piece from the walk's ``t`` to :func:`piece_end`, with the cubics of the value
    ``arrays`` (:meth:`~mi_amr.kernels.device.DeviceVolume.arrays`) along it."""
    t_b = piece_end(ray, walk, active)
    length = t_b - walk.t
    nums, den = rec.segment_cubic(ray.dev, ray.cfg.basis,
                                  rec.Segment(leaf=walk.leaf, p0=ray.at(walk.t), d=ray.d,
                                              s_mid=0.5 * length), arrays, active)
    return CubicPiece(t=walk.t, end=t_b, length=length, nums=nums, den=den)


@dr.syntax
def walk_counts(ray: RayContext, ropes: bool = True):
    """What the one traversal visits along the rays, for tests and benchmarks (a diagnostic:
    no march calls it): the march of :meth:`March.next` with whole leaf searches and the cubic
    pieces of :func:`piece_end` (what shadow transmittance and volume compositing walk),
    counted per ray: ``(nodes, leaves, pieces)``, the kd nodes its leaf searches visit, the
    leaves it works on and the pieces it takes. ``ropes=False`` restarts every search after
    a leaf at the root instead of the leaf's rope (the slow twin of the ropes: the same
    leaves and pieces, more nodes)."""
    m = ray.m
    march = March.start(ray, whole=True)
    nodes, leaves, pieces = m.UInt32(0), m.UInt32(0), m.UInt32(0)
    active = m.Bool(ray.active)
    while dr.hint(active, label="walk_counts"):
        if dr.hint(not ropes, mode="scalar"):
            march.walk.face = dr.select(march.walk.needs_leaf(), 6, march.walk.face)
        march, leg = march.next(ray, m.Float(dr.nan), active)
        nodes += leg.steps
        leaves += dr.select(leg.new & leg.stretch.found, 1, 0)
        active &= leg.onward
        t_b = piece_end(ray, march.walk, active)
        pieces += dr.select(active, 1, 0)
        march.walk.t = dr.select(active, t_b, march.walk.t)
        active &= march.walk.t < ray.t1
    return nodes, leaves, pieces
