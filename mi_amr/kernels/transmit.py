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

Shape: :func:`transmittance_exact` takes a :class:`~mi_amr.kernels.ray.RayContext` and consumes
the one traversal (:class:`~mi_amr.kernels.traverse.March`): per step of its loop,
:meth:`~mi_amr.kernels.traverse.March.next` moves the walk on and reports the skipped nodes'
sides, :func:`~mi_amr.kernels.traverse.cubic_piece` gives the piece to count crossings on, and
:class:`Shadow` (transmittance and layers) takes in the counts. Rays ``o + t d`` are in the
volume's world space; ``t`` is the caller's parameter.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels import roots
from mi_amr.kernels.config import clip_box
from mi_amr.kernels.device import lnot
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.traverse import CubicPiece, March, cubic_piece

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Float, UInt32

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


@dataclass
class Shadow:
    """What a shadow ray has met: its transmittance ``T`` and the ``layers`` crossed."""

    T: Float
    layers: UInt32

    def past(self, ray: RayContext, opacity, max_layers: int, counts) -> "Shadow":
        """This shadow after ``counts[k]`` crossings of each isovalue ``k`` (at most
        :data:`MAX_PER_PIECE`), up to ``max_layers`` layers in all (``opacity``: device
        array, one per isovalue)."""
        m = ray.m
        T, layers = self.T, self.layers
        for k in range(ray.cfg.num_iso):
            n = dr.minimum(counts[k], max_layers - dr.minimum(layers, max_layers))
            f = 1.0 - dr.gather(m.Float, opacity, m.UInt32(k))
            for j in range(1, MAX_PER_PIECE + 1):
                T = dr.select(n >= j, T * f, T)
            layers += n
        return Shadow(T=T, layers=layers)


@dr.syntax
def transmittance_exact(ray: RayContext, opacity, max_layers: int, u=None):
    """Transmittance of the isosurfaces on ``(ray.t0, ray.t1)``: the product of ``1 -
    opacity[k]`` over the crossings of isovalue ``k`` (``opacity``: device array, one per
    isovalue), at most ``max_layers`` of them; 0 once it falls to
    :data:`~mi_amr.tolerances.T_MIN` (as front-to-back compositing gives).

    With ``u`` (uniform in ``[0, 1)`` per ray) an unbiased sample of it instead (Russian
    roulette below :data:`~mi_amr.tolerances.ROULETTE_T`, ``R``): the walk stops where the
    transmittance falls to ``R u`` (0); one that ends above it gives its transmittance, or
    ``R`` where that is below ``R`` (which it stays above with probability ``T / R``)."""
    m, cfg = ray.m, ray.cfg
    ray = ray.clipped(clip_box(cfg))
    values = ray.dev.arrays(cfg.basis)
    march = March.start(ray)
    v_prev = m.Float(dr.nan)               # the field's value where the walk is (NaN: none)
    sides = Sides.start(m, cfg.num_iso)    # per isovalue, the side of the last sure value
    shadow = Shadow(T=m.Float(1.0), layers=m.UInt32(0))
    T_end = m.Float(tol.T_MIN if u is None else dr.maximum(tol.ROULETTE_T * u, tol.T_MIN))
    active = m.Bool(ray.active)
    while dr.hint(active, label="transmit",
                  exclude=[T_end, cfg, max_layers, opacity, ray, values]):
        # --- The next leaf that may hold a crossing (a few search steps at a time). Skipped
        # nodes tell their side; one across isovalues from the value before ends the search
        # (then it is skipped next).
        march, leg = march.next(ray, v_prev, active)
        skips = leg.stretch.skips
        skipped = leg.new & dr.isfinite(skips.side)
        turned = leg.new & skips.turned
        counts = [sides.see(k, skips.side - cfg.iso(ray.dev, k), skipped) +
                  sides.see(k, skips.turn_value - cfg.iso(ray.dev, k), turned)
                  for k in range(cfg.num_iso)]
        shadow = shadow.past(ray, opacity, max_layers, counts)
        v_prev = dr.select(turned, skips.turn_value, dr.select(skipped, skips.side, v_prev))
        searching = active & leg.searching
        work = active & lnot(turned) & leg.onward & lnot(searching)

        # --- The piece [t, t_b]: the sides along it.
        piece = cubic_piece(ray, march.walk, values, work)
        have, v_end, counts = _piece_counts(ray, sides, piece, work)
        shadow = shadow.past(ray, opacity, max_layers, counts)
        v_prev = dr.select(work, dr.select(have, v_end, dr.nan), v_prev)
        march.walk.t = dr.select(work, piece.end, march.walk.t)
        active = (work | turned | searching) & (march.walk.t < ray.t1) & \
            (shadow.T > T_end) & (shadow.layers < max_layers)
    T = shadow.T
    return dr.select(T <= T_end, 0.0, T if u is None else dr.maximum(T, tol.ROULETTE_T))


def _piece_counts(ray: RayContext, sides: Sides, piece: CubicPiece, active):
    """``(have, v_end, counts)`` of a piece: whether the field is defined on it
    (:meth:`~mi_amr.kernels.traverse.CubicPiece.defined`), its value at the end, and per
    isovalue the crossings on it, a jump at its start included."""
    mid = piece.mid()
    have = piece.defined(active, mid[1])
    sides.forget(active & lnot(have))
    v_end = piece.value_at_end()
    counts = [_count(sides, k, piece, ray.cfg.iso(ray.dev, k), mid, have)
              for k in range(ray.cfg.num_iso)]
    return have, v_end, counts


def _count(sides: Sides, k: int, piece: CubicPiece, iso, mid, active):
    """Crossings of isovalue ``k`` (value ``iso``) on the piece: ``c = N - iso D`` seen at the
    start, at its extrema inside and at the end (``mid``: ``(N, D)`` at the piece's middle).
    An end whose weight is below :data:`~mi_amr.tolerances.MIN_COVER` is moved
    :data:`~mi_amr.tolerances.COVER_NUDGE` of the piece inside (missing data is no crossing);
    an extremum there is left out."""
    num, den, length = piece.num, piece.den, piece.length
    n_mid, d_mid = mid
    c = [num[i] - iso * den[i] for i in range(4)]
    r1, r2 = roots.extrema(c, length)
    nudge = tol.COVER_NUDGE * length
    a = dr.select(roots.cubic(den, 0.0 * length) < tol.MIN_COVER, nudge, 0.0 * length)
    b = dr.select(roots.cubic(den, length) < tol.MIN_COVER, length - nudge, length)
    sure_at = tol.SIGN_SURE_REL * (dr.abs(n_mid) + dr.abs(iso * d_mid))
    count = 0
    for s, inside in ((a, active), (r1, active & (r1 > a) & (r1 < b)),
                      (r2, active & (r2 > a) & (r2 < b)), (b, active)):
        g = roots.cubic(c, s)
        count += sides.see(k, g, inside & (dr.abs(g) > sure_at) &
                           (roots.cubic(den, s) >= tol.MIN_COVER))
    return count
