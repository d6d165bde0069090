"""Walking a ray through the kd-tree: leaves that may hold a crossing, skipping every node
that cannot (pbrt's majorant-segment shape: traversal hands ``[t, t_exit]`` stretches to the
method that consumes them).

A ray ``p(t) = o + t d`` (volume world space, ``d`` need not be unit length; ``t`` is the same
parameter as the caller's) is walked by :func:`seek`: every node carries the range of the
reconstructed values inside it, and a node whose range holds no isovalue (or that has no data)
is skipped whole -- the ray jumps to the node's exit and restarts its descent at the node's
rope. :func:`next_dual_plane` cuts a stretch where the reconstruction's cubic pieces end.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels.config import holds, sides_differ, start_table
from mi_amr.kernels.device import NODE_RECORDS, lnot
from mi_amr.kernels.starts import table_start


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


@dataclass
class Walk:
    """Where a ray is in its walk: at parameter ``t`` inside ``leaf`` (reached through
    ``node``), which it leaves at ``t_exit`` through ``face`` (6: no leaf yet). The loop state
    every method carries."""

    node: Any
    leaf: Any
    face: Any
    t_exit: Any
    t: Any

    @staticmethod
    def start(m, t0) -> "Walk":
        return Walk(node=m.UInt32(0), leaf=m.UInt32(0), face=m.UInt32(6),
                    t_exit=m.Float(-dr.inf), t=m.Float(t0))

    def needs_leaf(self):
        """The lanes that have used up their leaf and must :func:`seek` the next."""
        return self.t >= self.t_exit

    def adopt(self, new, st: Stretch) -> "Walk":
        """This walk, moved on to stretch ``st`` where ``new`` (the lanes that sought one)."""
        return Walk(node=dr.select(new, st.node, self.node),
                    leaf=dr.select(new, st.leaf, self.leaf),
                    face=dr.select(new, st.face, self.face),
                    t_exit=dr.select(new, st.t_exit, self.t_exit),
                    t=dr.select(new, st.t, self.t))


# ---------------------------------------------------------------------- boxes

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


def epsilon(dev, t, dnorm):
    """A step in ``t`` well below a cell yet large enough to move ``t`` in float32."""
    return dr.maximum(dev.step_eps / dnorm, dr.abs(t) * tol.STEP_EPS_REL)


def _node_box(dev, node, active):
    """Box of ``node`` (two packet loads of 4 floats)."""
    m = dev.m
    lo = dr.gather(m.Array4f, dev.node_box, 2 * node, active)
    hi = dr.gather(m.Array4f, dev.node_box, 2 * node + 1, active)
    return m.Array3f(lo.x, lo.y, lo.z), m.Array3f(hi.x, hi.y, hi.z)


def _restart(dev, o, d, t, node, face, active, table=None):
    """Where to resume the descent at ``o + t d`` after leaving ``node`` through ``face``: its
    rope when that node holds the point, else the root (also for ``face`` >= 6: no node yet).
    Given a start ``table`` (:mod:`mi_amr.kernels.starts`), the deeper of its node for the
    point and the rope, and the rope is not read where the table's entry is final (a leaf, or
    a node to skip). Returns the node and its box."""
    m = dev.m
    p = dr.fma(d, t, o)
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
    if active:
        rope, lo, hi, inside = _rope(dev, p, node, face, active)
    return rope, lo, hi, inside


@dataclass
class Seeking:
    """A :func:`seek` under way (see :func:`seek_start`, :func:`seek_steps`): the node it is at
    and its box, the parameter ``t``, and what :class:`Stretch` reports so far; ``searching``:
    not finished."""

    node: Any
    b_lo: Any
    b_hi: Any
    t: Any
    side: Any
    t_side: Any
    leaf: Any
    t_exit: Any
    face: Any
    found: Any
    turned: Any
    turn_value: Any
    searching: Any

    def stretch(self) -> Stretch:
        return Stretch(node=self.node, leaf=self.leaf, t=self.t, t_exit=self.t_exit,
                       face=self.face, found=self.found, turned=self.turned,
                       turn_value=self.turn_value, side=self.side, t_side=self.t_side)

    def replaced(self, where, other: "Seeking") -> "Seeking":
        """This search, replaced by ``other`` where ``where``."""
        return Seeking(*(dr.select(where, getattr(other, f.name), getattr(self, f.name))
                         for f in dataclasses.fields(self)))


def seek(dev, cfg, o, d, t, t1, node, face, side, active) -> Stretch:
    """From parameter ``t`` (having left ``node`` through ``face``; ``face`` = 6 at the start)
    walk to the first leaf whose value range may hold a crossing, skipping every node that
    cannot. Stops early at a skipped node on the other side of an isovalue than ``side``.

    One step either goes down one level (the child's box is the parent's, cut at the split, so
    it costs two packet loads: code and split, value range) or skips a node and restarts at its
    rope."""
    return seek_steps(dev, cfg, o, d, t1, seek_start(dev, o, d, t, node, face, side, active),
                      None).stretch()


def seek_part(dev, cfg, o, d, t1, w: Walk, sk: Seeking, side, active):
    """Up to ``cfg.seek_steps`` (:data:`~mi_amr.kernels.config.SEEK_STEPS`) steps of the leaf
    search of the lanes of walk ``w`` that have used up their leaf (starting a search where none
    is under way, from ``side``). Returns the search and the lanes whose search ended now: for
    them ``sk.stretch()`` is what :func:`seek` gives. Lanes still searching must not work on a
    leaf this step. A march whose step costs far more than a search step (volume mode's exact
    pieces, each lit with its own shadow rays) is faster with :func:`seek`, the whole search at
    once: the search's state carried in the loop costs more than the waiting saves there."""
    begin = active & w.needs_leaf() & lnot(sk.searching)
    sk = sk.replaced(begin, seek_start(dev, o, d, w.t, w.node, w.face, side, begin,
                                       start_table(cfg)))
    sk = seek_steps(dev, cfg, o, d, t1, sk, cfg.seek_steps)
    return sk, active & w.needs_leaf() & lnot(sk.searching)


def seek_start(dev, o, d, t, node, face, side, active, table=None) -> Seeking:
    """A :func:`seek` from ``t`` having left ``node`` through ``face``, before its first step
    (from the node of the start ``table`` where it has one and no rope leads on)."""
    m = dev.m
    t = m.Float(t)
    eps = epsilon(dev, t, dr.norm(d))
    node, b_lo, b_hi = _restart(dev, o, d, t + eps, node, face, active, table)
    return Seeking(node=node, b_lo=b_lo, b_hi=b_hi, t=t, side=m.Float(side),
                   t_side=m.Float(dr.nan), leaf=m.UInt32(0), t_exit=m.Float(t),
                   face=m.UInt32(6), found=m.Bool(False), turned=m.Bool(False),
                   turn_value=m.Float(dr.nan), searching=m.Bool(active))


@dr.syntax
def seek_steps(dev, cfg, o, d, t1, sk: Seeking, max_steps) -> Seeking:
    """Up to ``max_steps`` steps of the search ``sk`` (all of them for None)."""
    m = dev.m
    search = dev.node_search(cfg.basis)
    dnorm = dr.norm(d)
    node, b_lo, b_hi, t = sk.node, sk.b_lo, sk.b_hi, sk.t
    side, t_side, leaf, t_exit, face = sk.side, sk.t_side, sk.leaf, sk.t_exit, sk.face
    found, turned, turn_value, searching = sk.found, sk.turned, sk.turn_value, sk.searching
    steps = m.UInt32(0)
    limit = m.UInt32(0xFFFFFFFF if max_steps is None else max_steps)
    going = searching & (steps < limit)
    while going:
        eps = epsilon(dev, t, dnorm)
        p = dr.fma(d, t + eps, o)
        cs = dr.gather(m.Array4u, search, NODE_RECORDS * node, going)
        if dr.hint(cfg.two_levels, mode="scalar"):
            # --- Through a non-empty inner node to its child (what a full step would do): its
            # record holds its children's (:meth:`DeviceVolume.node_search`), so the exit and
            # rope work waits for the child. A camera ray's search is mostly such descents; the
            # steps and their order are one level a turn's (cfg.two_levels False, the twin).
            lo = dr.reinterpret_array(m.Float, cs.z)
            hi = dr.reinterpret_array(m.Float, cs.w)
            through = going & holds(dev, cfg, lo, hi) & ((cs.x & 3) != 3) & (t < t1) & \
                (steps + 1 < limit)
            kids = [dr.gather(m.Array4u, search, NODE_RECORDS * node + 1 + c, through)
                    for c in (0, 1)]
            child, upper, b_lo, b_hi = _child(m, cs, p, b_lo, b_hi, through)
            node = dr.select(through, child, node)
            cs = dr.select(through, dr.select(upper, kids[1], kids[0]), cs)
            steps += dr.select(through, 1, 0)
        code = cs.x
        lo = dr.reinterpret_array(m.Float, cs.z)
        hi = dr.reinterpret_array(m.Float, cs.w)
        t_out, f_out = box_exit(m, b_lo, b_hi, o, d)
        empty = lnot(holds(dev, cfg, lo, hi))
        rep = dr.select(lo <= hi, 0.5 * (lo + hi), dr.nan)
        is_leaf = (code & 3) == 3

        # --- A leaf worth working on.
        take = going & lnot(empty) & is_leaf
        found |= take
        leaf = dr.select(take, code >> 2, leaf)
        t_exit = dr.select(take, t_out, t_exit)
        face = dr.select(take, f_out, face)

        # --- An empty node on the other side: let the caller look at its first sample.
        turn = going & empty & sides_differ(dev, cfg, side, rep)
        turned |= turn
        turn_value = dr.select(turn, rep, turn_value)

        # --- Skip an empty node: jump to its exit and continue from its rope.
        skip = going & empty & lnot(turn)
        side = dr.select(skip, rep, side)
        t_side = dr.select(skip, t_out, t_side)
        t_next = dr.maximum(t_out, t + eps)
        # (A symbolic branch: a packet with no lane skipping jumps over the rope restart and
        # its loads; side by side 1024^2 0.93-0.99 -> 0.84-0.87 s.)
        r_node, r_lo, r_hi = m.UInt32(node), m.Array3f(b_lo), m.Array3f(b_hi)
        if skip:
            r_node, r_lo, r_hi = _restart(dev, o, d, t_next + epsilon(dev, t_next, dnorm), node,
                                          f_out, skip)

        # --- Otherwise go down to the child holding the point.
        down = going & lnot(empty) & lnot(is_leaf)
        child, _, c_lo, c_hi = _child(m, cs, p, b_lo, b_hi, down)

        node = dr.select(skip, r_node, dr.select(down, child, node))
        b_lo = dr.select(skip, r_lo, dr.select(going, c_lo, b_lo))
        b_hi = dr.select(skip, r_hi, dr.select(going, c_hi, b_hi))
        t = dr.select(skip, t_next, t)
        searching &= lnot(going & (take | turn | (t >= t1)))
        steps += 1
        going = searching & (steps < limit)
    return Seeking(node=node, b_lo=b_lo, b_hi=b_hi, t=t, side=side, t_side=t_side, leaf=leaf,
                   t_exit=t_exit, face=face, found=found, turned=turned, turn_value=turn_value,
                   searching=searching)


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


@dr.syntax
def next_dual_plane(dev, levels_mask, o, d, inv_d, t_probe):
    """Smallest parameter > ``t_probe`` (up to rounding) at which the ray crosses a plane through
    cell centres of a level in ``levels_mask`` (bit ``l`` for level ``l``); ``inv_d = 1 / d``
    (infinite where ``d`` is 0). The levels are visited bit by bit, so the traced program is
    the same whatever the number of levels."""
    m = dev.m
    p = dr.fma(d, t_probe, o)
    up = d > 0.0
    best = m.Float(dr.inf)
    mask = m.UInt32(levels_mask)
    while mask != 0:
        level = dr.tzcnt(mask)
        mask &= mask - 1
        h = dev.level_h(level)
        inv_h = dev.level_inv_h(level)
        cell = dr.floor(dr.fma(p - dev.anchor, inv_h, -0.5))
        plane = dr.select(up, cell + 1.5, cell + 0.5)
        t = dr.select(d != 0.0, dr.fma(plane, h, dev.anchor - o) * inv_d, dr.inf)
        best = dr.minimum(best, dr.min(t))
    return best


def clip_to_volume(dev, o, d, t_start, t_end, active, box=None):
    """The ray's stretch inside the volume's bounds (and inside ``box``, ``(lo, hi)``, when
    given: :func:`~mi_amr.kernels.config.clip_box`): ``(o, t0, t1, active)``. A ray lying in
    an upper face of the bounds is moved inside by a rounding step: kd points on a split plane
    go to the upper side, which beyond the upper faces holds no data."""
    m = dev.m
    lo, hi = dev.bounds_lo, dev.bounds_hi
    on_top = (d == 0.0) & (o == hi)
    o = dr.select(on_top, hi - dr.maximum(dr.abs(hi), 1e-30) * tol.UPPER_FACE_REL, o)
    t_in, t_out = box_interval(lo, hi, o, d)
    t0 = dr.maximum(t_start, t_in)
    t1 = dr.minimum(t_end, t_out)
    if box is not None:
        b_in, b_out = box_interval(box[0], box[1], o, d)
        # The empty box (+inf, -inf) would give every ray the whole line.
        b_out = dr.select(dr.all(box[0] <= box[1]), b_out, -dr.inf)
        t0, t1 = dr.maximum(t0, b_in), dr.minimum(t1, b_out)
    return o, t0, t1, m.Bool(active) & (t0 < t1)
