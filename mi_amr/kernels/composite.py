"""Volume mode: front-to-back compositing of the opacity band (:mod:`mi_amr.kernels.band`)
around the isovalue, on the same kd-tree walk as the surfaces (:mod:`mi_amr.kernels.traverse`).

Shape: :func:`composite` takes a :class:`~mi_amr.kernels.ray.RayContext` and, for camera rays,
a :class:`Shading`; both marches consume the one traversal
(:class:`~mi_amr.kernels.traverse.March`): ``exact`` with whole leaf searches and
:func:`~mi_amr.kernels.traverse.cubic_piece` pieces, split into sub-pieces where the value
turns relative to a band; the sampling methods with sub-intervals of a
:class:`~mi_amr.kernels.traverse.Lattice`. Rays ``o + t d`` are in the volume's world space;
colours are linear RGB, premultiplied.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional, Protocol

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels import roots
from mi_amr.kernels.band import (Ramp, alpha, combine, corrected, cut_point, depth_fraction,
                                 flat_centroid, in_order, optical_depth, segment_alpha,
                                 segment_alpha_and_centroid, segment_alpha_and_point)
from mi_amr.kernels.config import bisect_depth, holds
from mi_amr.kernels.device import lnot
from mi_amr.kernels.near import NearRamp, NearStretch
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.transfer2d import SUPPORT_HI, SUPPORT_LO
from mi_amr.kernels.transfer2d import alpha as alpha2d
from mi_amr.kernels.transfer2d import segment_alpha as segment_alpha2d
from mi_amr.kernels.traverse import CubicPiece, Lattice, March, Walk, cubic_piece, sub_interval

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Array3f, Bool, Float, UInt32

# Fixed-point iterations of a piece's value extrema (roots.rational_extrema): each squares the
# error, and the basis reconstruction's denominator varies slowly along a piece.
EXTREMUM_ITERATIONS = 2


@dataclass
class Composite:
    """Result of :func:`composite`: premultiplied colour ``C`` and the transmittance ``T`` left."""

    C: Array3f
    T: Float
    samples: UInt32
    pick: Optional["Pick"] = None


@dataclass
class Pick:
    """The lit piece that a camera ray's correcting shadow ray leaves from (a lighting that
    ``corrects``, see :func:`composite`): picked among the ray's lit pieces with probability
    proportional to the luminance of their unshadowed direct light ``T D`` (``T``: the ray's
    transmittance up to the piece; ``D``: the piece's light from the correcting light when
    the band casts no shadow on it). ``p``: its lit place (volume world); ``D``: ``T D``
    divided by that probability (so ``D (V - cached)`` is an unbiased estimate of the
    ray's sum of ``T D (V - cached)`` over its pieces); ``cached``: the light's cached
    transmittance there; ``u``: the uniform number left for the next pick; ``total``: the
    sum of the weights so far; ``picked``: whether a piece was picked."""

    p: Array3f
    D: Array3f
    cached: Float
    u: Float
    total: Float
    picked: Bool

    @staticmethod
    def start(m, u) -> "Pick":
        return Pick(p=m.Array3f(0.0), D=m.Array3f(0.0), cached=m.Float(0.0), u=m.Float(u),
                    total=m.Float(0.0), picked=m.Bool(False))

    def offer(self, T, piece: "PieceLight") -> "Pick":
        """This pick after it is offered the piece ``piece`` behind transmittance ``T``
        (streaming weighted reservoir sampling with one uniform number: the piece is taken
        with probability ``w / total``, and the number left is rescaled to stay uniform)."""
        TD = T * piece.D
        w = dr.maximum(luminance(TD), 0.0)
        total = self.total + w
        share = dr.select(total > 0.0, w / total, 0.0)
        take = (share > 0.0) & (self.u < share)
        u = dr.select(take, self.u / dr.maximum(share, tol.NO_WEIGHT),
                      (self.u - share) / dr.maximum(1.0 - share, tol.NO_WEIGHT))
        return Pick(p=dr.select(take, piece.p, self.p),
                    D=dr.select(take, TD / dr.maximum(w, tol.NO_WEIGHT), self.D),
                    cached=dr.select(take, piece.cached, self.cached),
                    u=dr.clip(u, 0.0, 1.0), total=total, picked=self.picked | take)

    def estimate_weight(self) -> Array3f:
        """``D`` of the picked piece as an estimate: its ``T D`` over its probability."""
        return dr.select(self.picked, self.D * self.total, 0.0)


@dataclass
class PieceLight:
    """A lit piece's offer to a :class:`Pick`: its lit place ``p`` (volume world), its light
    ``D`` from the correcting light alone, unshadowed by the band, and that light's cached
    transmittance ``cached`` there."""

    p: Array3f
    D: Array3f
    cached: Float

    @staticmethod
    def none(m) -> "PieceLight":
        """The offer of a piece without light: never picked."""
        return PieceLight(p=m.Array3f(0.0), D=m.Array3f(0.0), cached=m.Float(1.0))


def luminance(c):
    """Rec. 709 luminance of the linear RGB ``c``: the weight by which a pick prefers the
    pieces that give more light."""
    return 0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z


class Lighting(Protocol):
    """What volume mode lights with (see :func:`composite`; the plugin's lighting). Where
    ``corrects`` is true it also gives, per piece, the correcting light's unshadowed terms
    (``direct_terms``) and its cached transmittance (``cached``), and ``pick_u``, each ray's
    uniform number for the pick."""

    corrects: bool

    def sample(self, p, lit, visible: bool, near: Optional[NearStretch] = None) -> Any: ...

    def terms(self, ctx, gradient, lit) -> tuple: ...

    def direct_terms(self, ctx, gradient, lit) -> tuple: ...

    def cached(self, ctx) -> Float: ...

    def lambert(self, ctx, gradient) -> Float: ...


@dataclass
class Shading:
    """How volume mode colours its light (see :func:`composite`): ``color_of(shares, value)``
    and the ``lighting``."""

    color_of: Callable
    lighting: Lighting


def composite(ray: RayContext, jitter, shading: Optional[Shading] = None,
              start: Optional[Walk] = None) -> Composite:
    """Front-to-back compositing of the opacity bands ``cfg.band`` (one around each isovalue)
    or of the 2D transfer function ``cfg.transfer2d`` along the ray, with early termination
    when less than :data:`~mi_amr.tolerances.T_MIN` of the light gets through.

    ``shading`` (None for shadow rays: only the transmittance is computed):
    ``shading.color_of(shares, value)`` gives the colour (``m.Array3f``) of a stretch where the
    bands hold ``shares`` of the optical depth (a list, one per band) and the colour field is
    ``value``; an attribute ``same_for_all_bands`` says it ignores ``shares``.
    ``shading.lighting`` has
    ``sample(p, lit, visible, near)``, the light samples at volume point ``p`` (with shadow
    rays where ``visible``; ``near``: its :class:`NearStretch`, or None),
    ``terms(ctx, gradient, lit)``, ``(A, S)`` such that the shaded colour
    of a point of colour ``c`` and gradient ``gradient`` lit by those samples is ``c * A + S``
    (the Phong terms), and ``lambert(ctx, gradient)``, the first light's unnormalised diffuse
    term (linear in the gradient).

    ``start`` (the exact method's shadow rays): the walk of the camera ray whose lit piece
    the ray starts from; the march begins in that piece's leaf (:meth:`Walk.within`) instead
    of searching from the root. The sampling methods start from the root.

    ``exact``: each cubic piece is cut where the reconstructed value turns (the extrema of
    ``N / D``, one search for all bands) and where the diffuse term turns (Marchesin et al.
    2009, sections 3.1-3.2); a piece whose value range cannot hold band opacity
    (:func:`~mi_amr.kernels.config.holds`, the walk's own test) costs no more; on each resulting
    sub-piece the value is taken as a linear ramp, its opacity is each band's integral over
    it, and its light the opacity times the shaded colour at the centroid of its most opaque
    band (exact where the shaded colour runs linearly along it), the bands met in the ramp's
    order. The two most opaque sub-pieces of a piece are shaded so, the others take the first
    one's colours; the piece is lit (shadow rays) where it has made half its opacity. With a
    2D transfer function a sub-piece's opacity is the table row of its gradient magnitude
    integrated along the ramp. The band is never stepped over and no step size or jitter
    enters. The sampling methods take one sample per
    step with opacity correction (or pre-integration between consecutive samples); ``bisect``
    moves a sample into the band when two samples straddle it (the course report's method).
    """
    ray = ray.clipped()
    if ray.cfg.method == "exact":
        return _composite_exact(ray, shading, start)
    return _composite_sampled(ray, ray.m.Float(jitter), shading)


def _sort(values):
    """Odd-even transposition sort of a short list of Dr.Jit values (ascending)."""
    v = list(values)
    for r in range(len(v)):
        for i in range(r % 2, len(v) - 1, 2):
            a, b = v[i], v[i + 1]
            v[i], v[i + 1] = dr.minimum(a, b), dr.maximum(a, b)
    return v


def _bands(dev, cfg):
    """The bands' centres (the isovalues) and their ``(lo, hi)`` value ranges."""
    m = dev.m
    centres = [cfg.iso(dev, k) for k in range(cfg.num_iso)]
    bands = [(c + cfg.band.get(m, "lo", k), c + cfg.band.get(m, "hi", k))
             for k, c in enumerate(centres)]
    return centres, bands


def _dominant(points, shares):
    """The entry of ``points`` (one per band) of the band with the largest share."""
    point, best = points[0], shares[0]
    for p, share in zip(points[1:], shares[1:]):
        point = dr.select(share > best, p, point)
        best = dr.maximum(best, share)
    return point


def _quadratic_extremum(q, length):
    """Where in ``[0, length]`` the quadratic through ``q`` (at 0, the middle and the end)
    turns; ``length`` if it does not inside."""
    q0, qm, q1 = q
    curv = 2.0 * (q0 + q1) - 4.0 * qm
    x = -(4.0 * qm - 3.0 * q0 - q1) / (2.0 * curv)
    inside = (dr.abs(curv) > tol.QUADRATIC_EPS) & (x > 0.0) & (x < 1.0)
    return dr.select(inside, x, 1.0) * length


@dataclass
class Piece:
    """A cubic piece ``[0, length]`` split at ``s_pts`` (sorted, from 0 to ``length``) and the
    field's values there; where it is shaded, the colour field's cubic numerator ``cnum``, the
    shared denominator ``den`` and ``gradient(s)``, the gradient at piece parameter ``s``."""

    s_pts: list
    values: list
    cnum: Optional[list] = None
    den: Optional[list] = None
    gradient: Optional[Callable] = None

    def shading_inputs(self, s):
        """The colour-field value and the gradient at piece parameter ``s``."""
        return roots.cubic(self.cnum, s) / roots.cubic(self.den, s), self.gradient(s)


def _value_cuts(cp: CubicPiece):
    """Where the value of the cubic piece ``cp`` turns
    (:func:`~mi_amr.kernels.roots.rational_extrema`), and the piece's points ``0``, those and
    ``length`` with the values there: on each part the value is monotone, so it meets each end
    of each band at most once whatever the number of bands, and the values give the piece's
    value range exactly."""
    turns = list(roots.rational_extrema(cp.num, cp.den, cp.length, EXTREMUM_ITERATIONS))
    s_pts = [0.0 * cp.length] + turns + [cp.length]
    return turns, [roots.cubic(cp.num, s) / roots.cubic(cp.den, s) for s in s_pts]


def _bernstein(c, length):
    """The Bernstein coefficients on ``[0, length]`` of the cubic ``c`` (power basis in ``s``),
    and the size of its terms there (the sum of their magnitudes)."""
    a1, a2 = c[1] * length, c[2] * length * length
    a3 = c[3] * length * length * length
    size = dr.abs(c[0]) + dr.abs(a1) + dr.abs(a2) + dr.abs(a3)
    third = 1.0 / 3.0
    return [c[0], dr.fma(a1, third, c[0]), c[0] + (2.0 * a1 + a2) * third,
            c[0] + a1 + a2 + a3], size


def _value_bound(cp: CubicPiece):
    """A range ``(lo, hi)`` that holds every value of the piece ``cp``, for much less work
    than its exact range (:func:`_value_cuts`). Where the Bernstein coefficients ``d_i`` of
    the denominator on ``[0, length]`` are all positive, ``N / D`` is the mean of the
    coefficients' ratios ``n_i / d_i`` weighted by ``d_i B_i / D`` (non-negative, summing to
    1), so it lies between the least ratio and the greatest; widened for rounding by
    :data:`~mi_amr.tolerances.VALUE_BOUND_REL` of the size of the terms. Elsewhere the whole
    line."""
    n, n_size = _bernstein(cp.num, cp.length)
    d, d_size = _bernstein(cp.den, cp.length)
    d_min = dr.minimum(dr.minimum(d[0], d[1]), dr.minimum(d[2], d[3]))
    ratios = [a / b for a, b in zip(n, d)]
    lo, hi = _value_range(ratios)
    positive = d_min > 0.0
    slack = tol.VALUE_BOUND_REL * (n_size + dr.maximum(dr.abs(lo), dr.abs(hi)) * d_size) / \
        dr.select(positive, d_min, 1.0)
    return dr.select(positive, lo - slack, -dr.inf), dr.select(positive, hi + slack, dr.inf)


@dr.syntax
def _value_cuts_where(cp: CubicPiece, near):
    """:func:`_value_cuts` where ``near``; elsewhere no turn and the piece's start value
    throughout (never read: such a piece is not composited). A packet with no lane ``near``
    skips the search for the turns (a symbolic branch)."""
    turns = [cp.length, cp.length]
    start = cp.num[0] / cp.den[0]
    values = [start, start, start, start]
    if dr.hint(near, label="value_cuts"):
        turns, values = _value_cuts(cp)
    return turns, values


def _value_range(values):
    """The range ``(lo, hi)`` of a piece whose values at its cuts are ``values`` (monotone
    between them)."""
    v_lo, v_hi = values[0], values[0]
    for v in values[1:]:
        v_lo, v_hi = dr.minimum(v_lo, v), dr.maximum(v_hi, v)
    return v_lo, v_hi


@dataclass
class SubPiece:
    """One sub-piece of a cubic piece: each band's pre-integrated opacity ``alphas``, their
    total ``alpha``, and the most opaque band ``k`` (a lane index) with its isovalue
    ``centre``."""

    alphas: list
    alpha: Float
    k: UInt32
    centre: Float


def _sub_pieces(ray: RayContext, piece: Piece, have, centres):
    """Per sub-piece its :class:`SubPiece`."""
    m, cfg = ray.m, ray.cfg
    dxs = [(piece.s_pts[i + 1] - piece.s_pts[i]) * ray.dnorm
           for i in range(len(piece.s_pts) - 1)]
    if cfg.transfer2d is not None:
        per_band = [[_opacity2d(ray, piece, i, dx) for i, dx in enumerate(dxs)]]
    elif len(centres) == 1:
        per_band = [_band_opacities(ray, piece, dxs, (0, centres[0]))]
    else:
        v_lo, v_hi = _value_range(piece.values)
        per_band = [_met_band_opacities(ray, piece, dxs, (k, c), (v_lo, v_hi))
                    for k, c in enumerate(centres)]
    out = []
    for i, dx in enumerate(dxs):
        alphas = [dr.select(have & (dx > 0.0), band[i], 0.0) for band in per_band]
        k_best, c_best, best = m.UInt32(0), centres[0], alphas[0]
        trans = 1.0 - alphas[0]
        for k in range(1, len(alphas)):
            better = alphas[k] > best
            k_best = dr.select(better, k, k_best)
            c_best = dr.select(better, centres[k], c_best)
            best = dr.maximum(best, alphas[k])
            trans *= 1.0 - alphas[k]
        out.append(SubPiece(alphas=alphas, alpha=1.0 - trans, k=k_best, centre=c_best))
    return out


def _band_opacities(ray: RayContext, piece: Piece, dxs, band):
    """Band ``band`` (its index and isovalue)'s pre-integrated opacity on each sub-piece
    (their values run from ``piece.values[i]`` to the next, over lengths ``dxs``, world); the
    cuts' :func:`~mi_amr.kernels.band.cut_point` shared by the sub-pieces on either side."""
    m, cfg = ray.m, ray.cfg
    k, c = band
    ints = [cut_point(m, cfg.band, k, v - c) for v in piece.values]
    return [segment_alpha(m, cfg.band, k, Ramp(piece.values[i], piece.values[i + 1], dx), c,
                          (ints[i], ints[i + 1]))
            for i, dx in enumerate(dxs)]


@dr.syntax
def _met_band_opacities(ray: RayContext, piece: Piece, dxs, band, value_range):
    """:func:`_band_opacities`, 0 on every sub-piece where the piece's values
    (``value_range``: their ``(lo, hi)``) miss the band's support, as they give there; a
    packet whose lanes all miss it skips it (a symbolic branch: a piece seldom meets more
    than one band of several)."""
    m, cfg = ray.m, ray.cfg
    k, c = band
    v_lo, v_hi = value_range
    meets = (v_lo < c + cfg.band.get(m, "hi", k)) & (v_hi > c + cfg.band.get(m, "lo", k))
    out = [m.Float(0.0) for _ in dxs]
    if dr.hint(meets, label="band_met"):
        out = _band_opacities(ray, piece, dxs, band)
    return out


def _opacity2d(ray: RayContext, piece: Piece, i, dx):
    """The 2D transfer function's opacity on sub-piece ``i`` (its values run from
    ``piece.values[i]`` to the next, over length ``dx``, world), at the gradient magnitude of
    the sub-piece's middle."""
    mid = 0.5 * (piece.s_pts[i] + piece.s_pts[i + 1])
    return segment_alpha2d(ray.m, ray.cfg.transfer2d, piece.values[i], piece.values[i + 1], dx,
                           dr.norm(piece.gradient(mid)))


def _two_most_opaque(m, subs):
    """The indices of the most and the second most opaque sub-pieces (lane values), and the
    second's opacity."""
    i1, i2 = m.UInt32(0), m.UInt32(0)
    a1, a2 = m.Float(-1.0), m.Float(-1.0)
    for i, sub in enumerate(subs):
        first = sub.alpha > a1
        second = lnot(first) & (sub.alpha > a2)
        i2 = dr.select(first, i1, dr.select(second, i, i2))
        a2 = dr.select(first, a1, dr.select(second, sub.alpha, a2))
        i1 = dr.select(first, i, i1)
        a1 = dr.select(first, sub.alpha, a1)
    return i1, i2, a2


def _pick(piece: Piece, subs, dnorm, i):
    """Sub-piece ``i`` (a lane index): its end values, length (world), most opaque band and
    isovalue, its ends (piece parameter) and its opacity."""
    zero = 0.0 * piece.s_pts[0]
    out = [zero, zero, zero, dr.zeros(type(subs[0].k), dr.width(zero)), zero, zero, zero, zero]
    for j, sub in enumerate(subs):
        s0, s1 = piece.s_pts[j], piece.s_pts[j + 1]
        now = [piece.values[j], piece.values[j + 1], (s1 - s0) * dnorm, sub.k, sub.centre,
               s0, s1, sub.alpha]
        out = [dr.select(i == j, x, y) for x, y in zip(now, out)]
    return out


@dataclass
class Lit:
    """How a piece is lit: the ``shading``, the light samples ``ctx`` (with their shadow
    rays) where ``lit``, and the bands' centres."""

    shading: Shading
    ctx: Any
    lit: Bool
    centres: list


def _light_place(ray: RayContext, piece: Piece, subs, centres):
    """Where the piece is lit (a piece parameter): where it has made half its opacity (the
    median of its light), found on the sub-piece where that happens, in its most opaque band
    (:func:`~mi_amr.kernels.band.segment_alpha_and_point`). A shadow ray from there gets the
    band's shadow on itself right for light from the viewer's side; from the band's middle,
    or anywhere in a cell, the band would shadow itself at random. Also the piece's opacity."""
    m, cfg = ray.m, ray.cfg
    trans = [m.Float(1.0)]
    for sub in subs:
        trans.append(trans[-1] * (1.0 - sub.alpha))
    target = 0.5 * (1.0 - trans[-1])
    i_half = m.UInt32(0)
    r = m.Float(0.0)
    for i in range(len(subs)):
        made_before, made_after = 1.0 - trans[i], 1.0 - trans[i + 1]
        here = (made_before < target) & (target <= made_after)
        i_half = dr.select(here, i, i_half)
        r = dr.select(here, (target - made_before) /
                      dr.maximum(made_after - made_before, tol.NO_WEIGHT), r)
    a, b, dx, k, c, s0, s1, alpha_i = _pick(piece, subs, ray.dnorm, i_half)
    if cfg.transfer2d is None:
        _, u = segment_alpha_and_point(m, cfg.band, k, Ramp(a, b, dx), c, r)
    else:   # (its extinction taken as even along the sub-piece)
        u = depth_fraction(r, optical_depth(alpha_i))
    return dr.lerp(s0, s1, u), 1.0 - trans[-1]


def _shaded_colors(ray: RayContext, piece: Piece, subs, i, lit: Lit):
    """Each band's shaded colour ``c * A + S`` at the centroid of sub-piece ``i``'s most opaque
    band (the one-point rule of the sub-piece's light: exact where the shaded colour runs
    linearly along it, and close where it curves, as a highlight does). Where the lighting
    ``corrects``, a second list: the same with the correcting light's unshadowed terms."""
    m, cfg = ray.m, ray.cfg
    color_of = lit.shading.color_of
    lighting = lit.shading.lighting
    nb = len(lit.centres)
    same = getattr(color_of, "same_for_all_bands", nb == 1)
    a, b, dx, k, c, s0, s1, alpha_i = _pick(piece, subs, ray.dnorm, i)
    if cfg.transfer2d is None:
        _, u = segment_alpha_and_centroid(m, cfg.band, k, Ramp(a, b, dx), c)
    else:   # (its extinction taken as even along the sub-piece)
        u = flat_centroid(optical_depth(alpha_i))
    cval, grad = piece.shading_inputs(dr.lerp(s0, s1, u))
    colors = [color_of(_one_hot(nb, 0 if same else j), cval) for j in range(nb)]
    A, S = lighting.terms(lit.ctx, grad, lit.lit)
    shaded = [col * A + S for col in colors]
    if not lighting.corrects:
        return shaded, None
    A_d, S_d = lighting.direct_terms(lit.ctx, grad, lit.lit)
    return shaded, [col * A_d + S_d for col in colors]


def _piece_light(ray: RayContext, piece: Piece, subs, lit: Lit):
    """The light and transmittance of a piece, lit by ``lit``: the two most opaque
    sub-pieces are each shaded at their centroid (:func:`_shaded_colors`), the others (a band
    seldom reaches more than two) take the most opaque one's colours; on each the bands are
    met in the order of the value ramp. Also the piece's light from the correcting light
    alone, unshadowed by the band (None where the lighting does not correct)."""
    m = ray.m
    i1, i2, a2 = _two_most_opaque(m, subs)
    first = _shaded_colors(ray, piece, subs, i1, lit)
    second = _second_colors(ray, piece, subs, (i2, a2), (lit, first))
    kinds = 1 if first[1] is None else 2
    C = [m.Array3f(0.0) for _ in range(kinds)]
    T = m.Float(1.0)
    for i, sub in enumerate(subs):
        rising = piece.values[i + 1] > piece.values[i]
        for kind in range(kinds):
            colors = [dr.select(i2 == i, e2, e1)
                      for e1, e2 in zip(first[kind], second[kind])]
            # (no light where a band is not met: the colour of a piece without weight is
            # NaN)
            lights = [dr.select(a > 0.0, a * e, 0.0) for a, e in zip(sub.alphas, colors)]
            light, trans = in_order(m, sub.alphas, lights, lit.centres, rising)
            C[kind] += T * light
        T *= trans
    return C[0], T, (C[1] if kinds == 2 else None)


@dr.syntax
def _second_colors(ray: RayContext, piece: Piece, subs, second, shaded):
    """:func:`_shaded_colors` of the second most opaque sub-piece (``second``: its index and
    opacity), or the first's (``shaded``: the :class:`Lit` and the first's colours) where it
    has no opacity: it then adds no light whatever its colours, so a packet whose lanes all
    have none skips its shading (a symbolic branch)."""
    i2, a2 = second
    lit, out = shaded
    if dr.hint(a2 > 0.0, label="second_shade"):
        out = _shaded_colors(ray, piece, subs, i2, lit)
    return out


def _one_hot(n, k):
    return [1.0 if j == k else 0.0 for j in range(n)]


def _piece(ray: RayContext, cp: CubicPiece, leaf, turns, lighting, have):
    """The cubic piece ``cp`` (in kd leaf ``leaf``) split for compositing: where the value
    turns (``turns``, from :func:`_value_cuts`) and, where it is shaded with
    ``cfg.shading_extrema``, where the first light's diffuse term turns (Marchesin et al. 2009,
    section 3.2; inside a trilinear cell that term is close to a quadratic in ``t``, whose
    extremum is found from its values at the piece's front, middle and back). The gradient,
    where shading or a 2D transfer function needs it, comes from the piece's cells read once
    (:func:`~mi_amr.kernels.reconstruct.segment_shading`), at any point of the piece; where
    it is shaded, so does the colour field's cubic (the march reads the field alone)."""
    cfg, length = ray.cfg, cp.length
    extra, gradient, cnum = [], None, cp.nums[0]
    if lighting is not None or cfg.transfer2d is not None:
        arrays = ray.dev.arrays(cfg.basis, color=lighting is not None)
        seg = rec.Segment(leaf=leaf, p0=ray.at(cp.t), d=ray.d, s_mid=0.5 * length)
        quadratics, colour = rec.segment_shading(ray.dev, cfg.basis, seg,
                                                 _distinct(arrays), have)
        cnum = cnum if colour is None else colour

        def gradient(s):
            return quadratics.at(s, cp.num, cp.den)

    if lighting is not None and cfg.shading_extrema:
        ctx = lighting.sample(ray.at(cp.t + 0.5 * length), have, False)
        extra = [_quadratic_extremum([lighting.lambert(ctx, gradient(f * length))
                                      for f in (0.0, 0.5, 1.0)], length)]

    s_pts = [0.0 * length] + _sort(list(turns) + extra) + [length]
    values = [roots.cubic(cp.num, s) / roots.cubic(cp.den, s) for s in s_pts]
    if lighting is None:
        return Piece(s_pts=s_pts, values=values, gradient=gradient)
    return Piece(s_pts=s_pts, values=values, cnum=cnum, den=cp.den, gradient=gradient)


def _distinct(arrays):
    """``arrays`` without a colour array that is the field's own (nothing to read twice)."""
    return arrays[:1] if len(arrays) > 1 and arrays[1] is arrays[0] else arrays


@dataclass
class Bands:
    """What the exact march composites: the bands' centres (the isovalues; for a 2D transfer
    function its value support's middle) and the ``shading`` (None: the transmittance
    alone)."""

    centres: list
    shading: Optional[Shading]

    @staticmethod
    def of(ray: RayContext, shading: Optional[Shading]) -> "Bands":
        tf, m = ray.cfg.transfer2d, ray.m
        if tf is None:
            return Bands(_bands(ray.dev, ray.cfg)[0], shading)
        return Bands([0.5 * (tf.get(m, SUPPORT_LO) + tf.get(m, SUPPORT_HI))], shading)


@dataclass
class Along:
    """Where a piece lies on its camera ray: the ray's ``walk`` (its leaf holds the piece) and
    the transmittance ``T`` in front of the piece."""

    walk: Walk
    T: Float


def _piece_colour(ray: RayContext, cp: CubicPiece, along: Along, turns, have, bands: Bands):
    """The light (premultiplied) and transmittance of the cubic piece ``cp`` (in the kd leaf
    of ``along.walk``, behind ``along.T``, its value turning at ``turns``): split, each part's
    opacity pre-integrated and, where it is shaded, lit once where the piece has made half its
    opacity and shaded at its two most opaque parts. Third, its :class:`PieceLight`
    (:meth:`PieceLight.none` where the lighting does not correct)."""
    m, shading = ray.m, bands.shading
    lighting = shading.lighting if shading is not None else None
    piece = _piece(ray, cp, along.walk.leaf, turns, lighting, have)
    subs = _sub_pieces(ray, piece, have, bands.centres)
    if shading is None:
        T_p = m.Float(1.0)
        for sub in subs:
            T_p *= 1.0 - sub.alpha
        return m.Array3f(0.0), T_p, PieceLight.none(m)
    s_best, best_alpha = _light_place(ray, piece, subs, bands.centres)
    lit = have & (best_alpha > tol.ALPHA_LIT)
    p_lit = ray.at(cp.t + s_best)
    ramp = NearRamp.at(ray, cp, piece.gradient, s_best, bands.centres)
    ctx = lighting.sample(p_lit, lit, True,
                          NearStretch.of(along.walk, lit, along.T, best_alpha, ramp))
    C_p, T_p, D_p = _piece_light(ray, piece, subs, Lit(shading, ctx, lit, bands.centres))
    if D_p is None:
        return C_p, T_p, PieceLight.none(m)
    return C_p, T_p, PieceLight(p=p_lit, D=dr.select(lit, D_p, 0.0),
                                cached=lighting.cached(ctx))


@dr.syntax
def _composite_exact(ray: RayContext, shading: Optional[Shading], start: Optional[Walk]):
    m, cfg = ray.m, ray.cfg
    # The field alone along the march: the colour field is read where a piece is shaded
    # (:func:`_piece`), with the cells its gradient reads.
    arrays = ray.dev.arrays(cfg.basis)
    bands = Bands.of(ray, shading)
    corrects = shading is not None and shading.lighting.corrects
    # (No light, no pick, where nothing is shaded or corrected: a loop variable that never
    # changes makes Dr.Jit trace the loop again without it.)
    C = m.Array3f(0.0) if shading is not None else None
    T = m.Float(1.0)
    pick = Pick.start(m, shading.lighting.pick_u) if corrects else None
    # Each leaf search whole: this march's pieces cost far more than search steps.
    march = March.start(ray, whole=True,
                        walk=None if start is None else Walk.within(ray, start))
    samples = m.UInt32(0)
    active = m.Bool(ray.active)
    while dr.hint(active, label="composite", exclude=[arrays, bands, cfg, m, ray]):
        # --- The next leaf with opacity.
        march, leg = march.next(ray, m.Float(dr.nan), active)
        active &= leg.onward

        # --- The cubic piece [t, t_b] up to the next dual-cell plane (or the leaf's end).
        work = m.Bool(active)
        cp = cubic_piece(ray, march.walk, arrays, work)
        samples += dr.select(work, 1, 0)
        # (The middle's weight alone: a piece that ends at missing data still has its band's
        # opacity up to there.)
        have = cp.defined(work, cp.mid()[1], ends=False)
        # --- Only a piece whose values meet a band is split, integrated and lit (a leaf's
        # range holds a band's values, most of its pieces' do not): first by a cheap bound
        # on its values, then by their exact range.
        near = have & holds(ray.dev, cfg, *_value_bound(cp))
        turns, values = _value_cuts_where(cp, near)
        near &= holds(ray.dev, cfg, *_value_range(values))
        C_p, T_p = m.Array3f(0.0), m.Float(1.0)
        offer = PieceLight.none(m)
        if dr.hint(near, label="piece", exclude=[T, bands, cp, march, ray, turns]):
            C_p, T_p, offer = _piece_colour(ray, cp, Along(march.walk, T), turns, near, bands)
        if dr.hint(corrects, mode="scalar"):
            pick = pick.offer(T, offer)
        if dr.hint(shading is not None, mode="scalar"):
            C += T * C_p
        T *= T_p

        march.walk.t = dr.select(work, cp.end, march.walk.t)
        active &= (march.walk.t < ray.t1) & (T > tol.T_MIN)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return Composite(C=m.Array3f(0.0) if C is None else C, T=T, samples=samples, pick=pick)


@dataclass
class Sample:
    """One sample of a sampled march in volume mode: at ``t_s`` (ending the sub-interval at
    ``b``), taken where ``take``; the field value ``v``, the colour-field value ``cval`` and
    the gradient ``grad`` there."""

    b: Float
    t_s: Float
    take: Bool
    v: Float
    cval: Float
    grad: Array3f


@dataclass
class Previous:
    """The sample before: its place ``t`` and value ``v`` (NaN: none that borders the next
    step)."""

    t: Float
    v: Float


def _volume_sample(ray: RayContext, walk: Walk, lattice: Lattice, arrays, active) -> Sample:
    """The next sub-interval (to a step position or the leaf's end) and its sample."""
    b, b_lattice, on_lattice = sub_interval(ray, walk, lattice)
    if ray.cfg.method == "uniform":
        t_s = b_lattice
        take = active & on_lattice
    else:
        t_s = 0.5 * (walk.t + b)
        take = ray.m.Bool(active)
    vals, grad = rec.reconstruct(ray.dev, ray.cfg.basis, ray.at(t_s), arrays, take,
                                 leaf=walk.leaf)
    return Sample(b=b, t_s=t_s, take=take, v=vals[0], cval=vals[1], grad=grad)


def _into_band(ray: RayContext, smp: Sample, prev: Previous, bands, arrays) -> Sample:
    """``bisect``: two samples on either side of a band (``bands``: ``(lo, hi)`` value ranges;
    the first listed that is straddled); move this sample into it if a point in between lies in
    it (course report, section 3.6.2)."""
    m = ray.m
    moved = m.Bool(False)
    t_m = m.Float(smp.t_s)
    for band in bands:
        band_lo, band_hi = band
        straddle = smp.take & lnot(moved) & (((prev.v < band_lo) & (smp.v > band_hi)) |
                                             ((prev.v > band_hi) & (smp.v < band_lo)))
        t_k, found = _bisect_band(ray, prev, smp.t_s, band, straddle)
        t_m = dr.select(straddle & found, t_k, t_m)
        moved |= straddle & found
    vals_m, grad_m = rec.reconstruct(ray.dev, ray.cfg.basis, ray.at(t_m), arrays, moved)
    return Sample(b=smp.b, t_s=dr.select(moved, t_m, smp.t_s), take=smp.take,
                  v=dr.select(moved, vals_m[0], smp.v), cval=dr.select(moved, vals_m[1], smp.cval),
                  grad=dr.select(moved, grad_m, smp.grad))


def _sample_alpha(ray: RayContext, smp: Sample, t, prev: Previous, dt, centres):
    """The opacity of a sample's step (from ``t``, the step ``dt``). Opacity-correction
    weight: the step (uniform), the sub-interval (adaptive, ExaBricks) or the distance from
    the previous sample (bisect, course report). Pre-integrated: the value runs from the
    previous sample to this one, integrated over that distance (steps tile the ray from one
    sample to the next; the first, from where the ray or the leaf starts, at the first
    sample's value). Returns the opacity, the bands' shares of it and where the step is lit
    (:func:`_light_point`)."""
    m, cfg, dnorm = ray.m, ray.cfg, ray.dnorm
    band = cfg.band
    if cfg.method == "uniform":
        dx = dt * dnorm
    elif cfg.method == "adaptive":
        dx = (smp.b - t) * dnorm
    else:
        dx = (smp.t_s - prev.t) * dnorm
    if cfg.transfer2d is not None:
        # The 2D transfer function is the one band: opacity by value and |grad f|.
        a = corrected(cfg.transfer2d, alpha2d(m, cfg.transfer2d, smp.v, dr.norm(smp.grad)), dx)
        return dr.select(smp.take & dr.isfinite(smp.v), a, 0.0), [1.0], smp.t_s
    alphas, points = [], []
    for k, centre in enumerate(centres):
        if cfg.preintegrated:
            span = (smp.t_s - prev.t) * dnorm
            a_ramp, u = segment_alpha_and_point(m, band, k, Ramp(prev.v, smp.v, span),
                                                      centre)
            a = dr.select(dr.isfinite(prev.v), a_ramp,
                          corrected(band, alpha(m, band, k, smp.v, centre), span))
            points.append(u)
        else:
            a = corrected(band, alpha(m, band, k, smp.v, centre), dx)
        alphas.append(dr.select(smp.take & dr.isfinite(smp.v), a, 0.0))
    a, shares = combine(alphas)
    return a, shares, _light_point(cfg, smp, prev, points, shares)


def _light_point(cfg, smp: Sample, prev: Previous, points, shares):
    """Where a sample is lit: the sample, or for a pre-integrated step from the previous sample
    where the band holding most of its opacity has made half of it (``points``: that place per
    band, a fraction of the step)."""
    if not cfg.preintegrated:
        return smp.t_s
    t = dr.lerp(prev.t, smp.t_s, _dominant(points, shares))
    return dr.select(dr.isfinite(prev.v) & dr.isfinite(t), t, smp.t_s)


def _sampled_bands(dev, cfg):
    """:func:`_bands`, or with a 2D transfer function no centres and its value support as the
    one band (``bisect`` moves a sample into it)."""
    tf = cfg.transfer2d
    if tf is None:
        return _bands(dev, cfg)
    return [], [(tf.get(dev.m, SUPPORT_LO), tf.get(dev.m, SUPPORT_HI))]


@dr.syntax
def _composite_sampled(ray: RayContext, jitter, shading: Optional[Shading]):
    m, cfg = ray.m, ray.cfg
    shade = shading is not None
    corrects = shade and shading.lighting.corrects
    uniform = cfg.method == "uniform"
    arrays = ray.dev.arrays(cfg.basis, color=True)
    centres, bands = _sampled_bands(ray.dev, cfg)
    # A shadow ray starts inside the band: uniform steps then sample the middle of each step,
    # so its first half step (the most opaque stretch) is not stepped over.
    rho = m.Float(-0.5 if not shade else 0.0) if uniform else jitter
    t_anchor = m.Float(ray.t0)
    march = March.start(ray)
    dt_fixed = m.Float(cfg.step_scale * ray.dev.min_h / ray.dnorm)
    # (The uniform step never changes: None, no loop state, which Dr.Jit would trace again.)
    dt = None if uniform else dt_fixed
    prev = Previous(t=m.Float(ray.t0), v=m.Float(dr.nan))
    C = m.Array3f(0.0) if shade else None      # (no loop variable that never changes)
    T = m.Float(1.0)
    pick = Pick.start(m, shading.lighting.pick_u) if corrects else None
    samples = m.UInt32(0)
    active = m.Bool(ray.active)
    while dr.hint(active, label="composite_sampled",
                  exclude=[arrays, bands, centres, cfg, dt_fixed, m, ray, rho, shading,
                           t_anchor, uniform]):
        # Skipped nodes have no opacity; the sample before them no longer borders the next one:
        # the next step's stretch starts where the leaf does.
        t_before = march.walk.t
        march, leg = march.next(ray, m.Float(dr.nan), active)
        skipped = leg.new & (leg.stretch.walk.t > t_before)
        prev = dr.select(skipped, Previous(t=leg.stretch.walk.t, v=m.Float(dr.nan)), prev)
        active &= leg.onward
        work = active & lnot(leg.searching)
        if dr.hint(not uniform, mode="scalar"):
            leaf_h = dr.gather(m.Float, ray.dev.leaf_min_h, march.walk.leaf, active & leg.new)
            dt = dr.select(leg.new, cfg.step_scale * leaf_h / ray.dnorm, dt)

        step = dt_fixed if uniform else dt
        smp = _volume_sample(ray, march.walk, Lattice(t_anchor, rho, step), arrays, work)
        samples += dr.select(smp.take, 1, 0)
        if dr.hint(cfg.method == "bisect", mode="scalar"):
            smp = _into_band(ray, smp, prev, bands, arrays)
        a, shares, t_light = _sample_alpha(ray, smp, march.walk.t, prev, step, centres)
        if dr.hint(shade, mode="scalar"):
            lit = smp.take & (a > tol.ALPHA_LIT)
            # (a symbolic branch: a packet whose samples are all too faint to shade skips
            # the light samples and the shading)
            if dr.hint(lit, label="shade_sample",
                       exclude=[T, a, march, ray, shading, shares, smp, t_light]):
                lighting = shading.lighting
                p_lit = ray.at(t_light)
                ctx = lighting.sample(p_lit, lit, True, NearStretch.of(march.walk, lit, T, a))
                A, S = lighting.terms(ctx, smp.grad, lit)
                color = shading.color_of(shares, smp.cval)
                C += dr.select(lit, T * a * (color * A + S), 0.0)
                if dr.hint(corrects, mode="scalar"):
                    A_d, S_d = lighting.direct_terms(ctx, smp.grad, lit)
                    pick = pick.offer(T, PieceLight(p=p_lit,
                                                    D=dr.select(lit, a * (color * A_d + S_d), 0.0),
                                                    cached=lighting.cached(ctx)))
        T = dr.select(work, T * (1.0 - a), T)
        prev = dr.select(smp.take, Previous(t=smp.t_s, v=smp.v), prev)

        march.walk.t = dr.select(work, smp.b, march.walk.t)
        active &= (march.walk.t < ray.t1) & (T > tol.T_MIN)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return Composite(C=m.Array3f(0.0) if C is None else C, T=T, samples=samples, pick=pick)


@dr.syntax
def _bisect_band(ray: RayContext, prev: Previous, t_b, band, active):
    """A point of ``[prev.t, t_b]`` whose value lies in the band's value range ``(lo, hi)``,
    by bisection on the side of the band that ``prev.v`` is on; returns ``(t, found)``."""
    m, cfg = ray.m, ray.cfg
    band_lo, band_hi = band
    values = ray.dev.arrays(cfg.basis)
    t_a = prev.t
    below = prev.v < band_lo
    depth = bisect_depth(cfg)
    i = m.Float(0.0)
    found = m.Bool(False)
    t_found = m.Float(0.0)
    while dr.hint(active & lnot(found) & (i < depth), label="bisect_band",
                  exclude=[active, band_hi, band_lo, below, cfg, depth, m, ray, values]):
        mid = 0.5 * (t_a + t_b)
        vals, _ = rec.reconstruct(ray.dev, cfg.basis, ray.at(mid), values, active & lnot(found))
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
