"""Light passing translucent isosurfaces along a ray, in one walk (shadow rays of ``exact``).

Front-to-back compositing (:func:`mi_amr.plugin.layers.front_to_back` without shading) finds the
layers one at a time, each root refined and the walk resumed just past it. A shadow ray needs
only the product of ``1 - opacity`` over the crossings it meets, so :func:`transmittance_exact`
walks the ray once and counts them: per isovalue, the changes of side of the field along the
values the walk evaluates anyway -- each cubic piece's ends and the extrema of ``N - iso D``
inside it (monotonic in between: one root per change), and the value ranges of skipped kd
nodes. A jump of the field between pieces or across a skipped node is such a change too. No
root is refined and no ray waits in an inner loop for its neighbours' layers.

A value within :data:`~mi_amr.tolerances.SIGN_SURE_REL` of the terms of an isovalue has no sure
side and leaves the side as it was: a crossing on the shared end of two pieces counts once, not
once per piece and once more for the rounding jump between them. Where the data is missing the
side is forgotten (no crossing across a hole, as in the first-crossing search).

Front-to-back compositing is its slow twin (``tests/test_translucent.py``). They differ by
design only where the field comes within :data:`~mi_amr.tolerances.SIGN_SURE_REL` of an
isovalue and turns back (a grazing touch counts none here, one there; a dip across it and
back, two there unless closer than ``dev.layer_offset``), and where ``max_layers`` falls inside
a piece with crossings of several isovalues (taken in isovalue order here, in ray order
there).

Rays ``o + t d`` are in the volume's world space; ``t`` is the caller's parameter.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels import roots
from mi_amr.kernels.config import clip_box
from mi_amr.kernels.device import lnot
from mi_amr.kernels.surface import cubic_piece
from mi_amr.kernels.traverse import Walk, clip_to_volume, seek_part, seek_start

MAX_PER_PIECE = 4      # changes of side per isovalue in one piece: its start and 3 intervals


@dataclass
class Sides:
    """Per isovalue ``k``: the side of the last value sure of its side (``up[k]``: above) and
    whether there is one (``known[k]``)."""

    up: list
    known: list

    @staticmethod
    def start(m, n: int) -> "Sides":
        return Sides([m.Bool(False) for _ in range(n)], [m.Bool(False) for _ in range(n)])

    def see(self, k: int, g, sure):
        """Take in the value ``g`` (of field minus isovalue ``k``) where ``sure`` of its side;
        returns 1 where that makes a crossing, else 0."""
        up = g > 0.0
        change = sure & self.known[k] & (up != self.up[k])
        self.up[k] = dr.select(sure, up, self.up[k])
        self.known[k] |= sure
        return dr.select(change, 1, 0)

    def forget(self, active):
        """No value (missing data) where ``active``: no side is known past it."""
        for k in range(len(self.up)):
            self.known[k] &= lnot(active)


@dr.syntax
def transmittance_exact(dev, cfg, opacity, o, d, t_start, t_end, max_layers: int, active,
                        u=None):
    """Transmittance of the isosurfaces on ``(t_start, t_end)``: the product of ``1 -
    opacity[k]`` over the crossings of isovalue ``k`` (``opacity``: device array, one per
    isovalue), at most ``max_layers`` of them; 0 once it falls to
    :data:`~mi_amr.tolerances.T_MIN` (as front-to-back compositing gives).

    With ``u`` (uniform in ``[0, 1)`` per ray) an unbiased sample of it instead (Russian
    roulette below :data:`~mi_amr.tolerances.ROULETTE_T`, ``R``): the walk stops where the
    transmittance falls to ``R u`` (0); one that ends above it gives its transmittance, or
    ``R`` where that is below ``R`` (which it stays above with probability ``T / R``)."""
    m = dev.m
    o, t0, t1, active = clip_to_volume(dev, o, d, t_start, t_end, active,
                                       clip_box(cfg))
    dnorm = dr.norm(d)
    inv_d = dr.select(d != 0.0, dr.rcp(d), dr.inf)
    values = dev.arrays(cfg.basis)
    level_masks = dev.leaf_levels if cfg.basis else dev.leaf_owner_levels
    w = Walk.start(m, t0)
    v_prev = m.Float(dr.nan)
    sides = Sides.start(m, cfg.num_iso)
    T = m.Float(1.0)
    T_end = m.Float(tol.T_MIN if u is None else dr.maximum(tol.ROULETTE_T * u, tol.T_MIN))
    layers = m.UInt32(0)
    sk = seek_start(dev, o, d, w.t, w.node, w.face, v_prev, m.Bool(False))
    while active:
        # --- The next leaf that may hold a crossing (a few search steps at a time). Skipped
        # nodes tell their side; one across isovalues from the value before ends the search
        # (then it is skipped next).
        sk, new = seek_part(dev, cfg, o, d, t1, w, sk, v_prev, active)
        st = sk.stretch()
        w = w.adopt(new, st)
        skipped = new & dr.isfinite(st.side)
        turned = new & st.turned
        counts = [sides.see(k, st.side - cfg.iso(dev, k), skipped) +
                  sides.see(k, st.turn_value - cfg.iso(dev, k), turned)
                  for k in range(cfg.num_iso)]
        T, layers = _pass(dev, cfg, opacity, T, layers, max_layers, counts)
        v_prev = dr.select(turned, st.turn_value, dr.select(skipped, st.side, v_prev))
        searching = active & sk.searching
        march = active & lnot(turned) & (lnot(new) | st.found) & lnot(searching)

        # --- The piece [t, t_b]: the sides along it.
        t_b, L, nums, den = cubic_piece(dev, cfg, o, d, inv_d, dnorm, w, t1, level_masks,
                                        values, march)
        have, v_end, counts = _piece_counts(dev, cfg, sides, nums[0], den, L, march)
        T, layers = _pass(dev, cfg, opacity, T, layers, max_layers, counts)
        v_prev = dr.select(march, dr.select(have, v_end, dr.nan), v_prev)
        w.t = dr.select(march, t_b, w.t)
        active = (march | turned | searching) & (w.t < t1) & (T > T_end) & \
            (layers < max_layers)
    return dr.select(T <= T_end, 0.0, T if u is None else dr.maximum(T, tol.ROULETTE_T))


def _pass(dev, cfg, opacity, T, layers, max_layers: int, counts):
    """``(T, layers)`` after ``counts[k]`` crossings of each isovalue ``k`` (at most
    :data:`MAX_PER_PIECE`), up to ``max_layers`` layers in all."""
    m = dev.m
    for k in range(cfg.num_iso):
        n = dr.minimum(counts[k], max_layers - dr.minimum(layers, max_layers))
        f = 1.0 - dr.gather(m.Float, opacity, m.UInt32(k))
        for j in range(1, MAX_PER_PIECE + 1):
            T = dr.select(n >= j, T * f, T)
        layers += n
    return T, layers


def _piece_counts(dev, cfg, sides: Sides, num, den, L, active):
    """``(have, v_end, counts)`` of a piece of length ``L`` with cubics ``num``, ``den``:
    whether the field is defined on it (as :mod:`mi_amr.kernels.surface` decides), its value
    at the end, and per isovalue the crossings on it, a jump at its start included."""
    d_mid = roots.cubic(den, 0.5 * L)
    have = active & (den[0] > tol.NO_WEIGHT) & (roots.cubic(den, L) > tol.NO_WEIGHT) & \
        (d_mid > tol.NO_WEIGHT)
    sides.forget(active & lnot(have))
    v_end = roots.cubic(num, L) / roots.cubic(den, L)
    n_mid = roots.cubic(num, 0.5 * L)
    counts = [_count(sides, k, num, den, cfg.iso(dev, k), L, n_mid, d_mid, have)
              for k in range(cfg.num_iso)]
    return have, v_end, counts


def _count(sides: Sides, k: int, num, den, iso, L, n_mid, d_mid, active):
    """Crossings of isovalue ``k`` (value ``iso``) on the piece ``[0, L]``: ``c = N - iso D``
    seen at the start, at its extrema inside and at the end. An end whose weight is below
    :data:`~mi_amr.tolerances.MIN_COVER` is moved :data:`~mi_amr.tolerances.COVER_NUDGE` of
    the piece inside (missing data is no crossing); an extremum there is left out."""
    c = [num[i] - iso * den[i] for i in range(4)]
    r1, r2 = roots.extrema(c, L)
    nudge = tol.COVER_NUDGE * L
    a = dr.select(roots.cubic(den, 0.0 * L) < tol.MIN_COVER, nudge, 0.0 * L)
    b = dr.select(roots.cubic(den, L) < tol.MIN_COVER, L - nudge, L)
    sure_at = tol.SIGN_SURE_REL * (dr.abs(n_mid) + dr.abs(iso * d_mid))
    count = 0
    for s, inside in ((a, active), (r1, active & (r1 > a) & (r1 < b)),
                      (r2, active & (r2 > a) & (r2 < b)), (b, active)):
        g = roots.cubic(c, s)
        count += sides.see(k, g, inside & (dr.abs(g) > sure_at) &
                           (roots.cubic(den, s) >= tol.MIN_COVER))
    return count
