"""Volume mode: front-to-back compositing of the opacity band (:mod:`mi_amr.kernels.band`)
around the isovalue, on the same kd-tree walk as the surfaces (:mod:`mi_amr.kernels.traverse`).

Rays ``o + t d`` are in the volume's world space; colours are linear RGB, premultiplied.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.errors import AMRError
from mi_amr.kernels import reconstruct as rec
from mi_amr.kernels import roots
from mi_amr.kernels.band import alpha, combine, corrected, segment_alpha_and_point
from mi_amr.kernels.config import MarchConfig
from mi_amr.kernels.device import lnot
from mi_amr.kernels.transfer2d import SUPPORT_HI, SUPPORT_LO
from mi_amr.kernels.transfer2d import alpha as alpha2d
from mi_amr.kernels.traverse import Walk, clip_to_volume, epsilon, next_dual_plane, seek


@dataclass
class Composite:
    """Result of :func:`composite`: premultiplied colour ``C`` and the transmittance ``T`` left."""

    C: Any
    T: Any
    samples: Any


def composite(dev, cfg: MarchConfig, o, d, t_start, t_end, jitter, color_of, lighting,
              active) -> Composite:
    """Front-to-back compositing of the opacity bands ``cfg.band`` (one around each isovalue)
    along the ray, with early termination when less than :data:`~mi_amr.tolerances.T_MIN` of
    the light gets through.

    ``color_of(shares, value)`` gives the colour (``m.Array3f``) of a stretch where the bands
    hold ``shares`` of the optical depth (a list, one per band) and the colour field is
    ``value``;
    ``lighting(p, gradient, active)`` gives ``(A, S)`` such that the shaded colour of a sample of
    colour ``c`` is ``c * A + S`` (the Phong terms). With ``lighting=None`` only the
    transmittance is computed (shadow rays).

    ``exact``: each cubic piece is cut where the reconstructed value can turn relative to a
    band (at the extrema of ``N - v D`` for each band's low end, centre and high end), and each
    resulting piece contributes the pre-integrated opacity of a linear ramp between its end
    values: the band is never stepped over. The sampling methods take one sample per step with
    opacity correction (or pre-integration between consecutive samples); ``bisect`` moves a
    sample into the band when two samples straddle it (the course report's method).
    """
    m = dev.m
    o, t0, t1, active = clip_to_volume(dev, o, d, t_start, t_end, active)
    if cfg.method == "exact" and cfg.transfer2d is not None:
        raise AMRError("amr_iso: the exact method does not take a 2D transfer function yet "
                       "('transfer2d', 'transfer2d_blobs'); use method uniform, adaptive or "
                       "bisect")
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


def _bands(dev, cfg):
    """The bands' centres (the isovalues) and their ``(lo, hi)`` value ranges."""
    m = dev.m
    centres = [cfg.iso(dev, k) for k in range(cfg.num_iso)]
    bands = [(c + cfg.band.get(m, "lo", k), c + cfg.band.get(m, "hi", k))
             for k, c in enumerate(centres)]
    return centres, bands


def _marks(centres, bands):
    """Each band's low end, centre and high end: where a piece is cut at the extrema of
    ``N - v D`` (a dr.syntax function may not unpack in a comprehension)."""
    return [v for lo_hi, c in zip(bands, centres) for v in (lo_hi[0], c, lo_hi[1])]


def _dominant(points, shares):
    """The entry of ``points`` (one per band) of the band with the largest share."""
    point, best = points[0], shares[0]
    for p, share in zip(points[1:], shares[1:]):
        point = dr.select(share > best, p, point)
        best = dr.maximum(best, share)
    return point


def _band_pieces(dev, cfg, num, den, L, dnorm, have, marks, centres):
    """A cubic piece of length ``L`` cut where the value can turn relative to a band (the
    extrema of ``N - v D`` for each of ``marks``): per sub-piece its pre-integrated opacity,
    the bands' shares of it and where along it half of its opacity is made
    (:func:`~mi_amr.kernels.band.segment_alpha_and_point`; there it takes its colour), and
    that place in the most opaque one with its opacity (there the piece is lit, so a shadow
    ray leaves from where the band's light comes from, not from anywhere in a cell)."""
    m = dev.m
    cuts = []
    for v in marks:
        r1, r2 = roots.extrema([num[i] - v * den[i] for i in range(4)], L)
        cuts += [r1, r2]
    s_pts = [0.0 * L] + _sort(cuts) + [L]
    values = [roots.cubic(num, s) / roots.cubic(den, s) for s in s_pts]
    alphas, shares, mids = [], [], []
    best_alpha = m.Float(0.0)
    s_best = m.Float(0.0)
    for i in range(len(s_pts) - 1):
        dx = (s_pts[i + 1] - s_pts[i]) * dnorm
        per_band = [segment_alpha_and_point(m, cfg.band, k, values[i], values[i + 1], dx, c)
                    for k, c in enumerate(centres)]
        a, share = combine([ab[0] for ab in per_band])
        a = dr.select(have & (dx > 0.0), a, 0.0)
        mid = dr.lerp(s_pts[i], s_pts[i + 1], _dominant([ab[1] for ab in per_band], share))
        alphas.append(a)
        shares.append(share)
        mids.append(mid)
        better = a > best_alpha
        best_alpha = dr.select(better, a, best_alpha)
        s_best = dr.select(better, mid, s_best)
    return alphas, shares, mids, s_best, best_alpha


@dr.syntax
def _composite_exact(dev, cfg, o, d, t0, t1, color_of, lighting, active):
    m = dev.m
    dnorm = dr.norm(d)
    inv_d = dr.select(d != 0.0, dr.rcp(d), dr.inf)
    shade = lighting is not None
    arrays = dev.arrays(cfg.basis, color=True)
    level_masks = dev.leaf_levels if cfg.basis else dev.leaf_owner_levels
    centres, bands = _bands(dev, cfg)
    marks = _marks(centres, bands)
    C = m.Array3f(0.0)
    T = m.Float(1.0)
    w = Walk.start(m, t0)
    samples = m.UInt32(0)
    while active:
        new = w.needs_leaf()
        st = seek(dev, cfg, o, d, w.t, t1, w.node, w.face, m.Float(dr.nan), active & new)
        w = w.adopt(new, st)
        active &= lnot(new) | st.found

        # --- The cubic piece [t, t_b] up to the next dual-cell plane (or the leaf's end).
        eps = epsilon(dev, w.t, dnorm)
        work = m.Bool(active)
        mask = dr.gather(m.UInt32, level_masks, w.leaf, work)
        t_b = dr.minimum(dr.minimum(next_dual_plane(dev, mask, o, d, inv_d, w.t + eps),
                                    w.t_exit), t1)
        t_b = dr.maximum(t_b, w.t + eps)
        L = t_b - w.t
        nums, den = rec.segment_cubic(dev, cfg.basis, w.leaf, dr.fma(d, w.t, o), d, 0.5 * L,
                                      arrays, work)
        samples += dr.select(work, 1, 0)
        have = work & (roots.cubic(den, 0.5 * L) > tol.NO_WEIGHT)
        alphas, shares, mids, s_best, best_alpha = _band_pieces(dev, cfg, nums[0], den, L,
                                                                dnorm, have, marks, centres)

        # --- Light once per piece of the ray, where it is most opaque.
        lit = have & (best_alpha > tol.ALPHA_LIT)
        if dr.hint(shade, mode="scalar"):
            p_best = dr.fma(d, w.t + s_best, o)
            _, grad = rec.reconstruct(dev, cfg.basis, p_best, arrays[:1], lit, leaf=w.leaf)
            A, S = lighting(p_best, grad, lit)
        for i in range(len(alphas)):
            a = alphas[i]
            if dr.hint(shade, mode="scalar"):
                cval = roots.cubic(nums[1], mids[i]) / roots.cubic(den, mids[i])
                C += dr.select(a > 0.0, T * a * (color_of(shares[i], cval) * A + S), 0.0)
            T *= 1.0 - a

        w.t = dr.select(active, t_b, w.t)
        active &= (w.t < t1) & (T > tol.T_MIN)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return Composite(C=C, T=T, samples=samples)


@dataclass
class Sample:
    """One sample of a sampled march in volume mode: at ``t_s`` (ending the sub-interval at
    ``b``), taken where ``take``; the field value ``v``, the colour-field value ``cval`` and
    the gradient ``grad`` there."""

    b: Any
    t_s: Any
    take: Any
    v: Any
    cval: Any
    grad: Any


def _volume_sample(dev, cfg, o, d, dnorm, w: Walk, t1, t_anchor, rho, dt, arrays, active):
    """The next sub-interval (to a step position or the leaf's end) and its sample."""
    m = dev.m
    uniform = cfg.method == "uniform"
    eps = epsilon(dev, w.t, dnorm)
    step = dr.floor((w.t - t_anchor) / dt - rho + tol.LATTICE_SNAP) + 1.0
    b_lattice = t_anchor + (rho + step) * dt
    b = dr.maximum(dr.minimum(dr.minimum(b_lattice, w.t_exit), t1), w.t + eps)
    if uniform:
        t_s = b_lattice
        take = active & (b_lattice <= dr.minimum(w.t_exit, t1))
    else:
        t_s = 0.5 * (w.t + b)
        take = m.Bool(active)
    vals, grad = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_s, o), arrays, take, leaf=w.leaf)
    return Sample(b=b, t_s=t_s, take=take, v=vals[0], cval=vals[1], grad=grad)


def _into_band(dev, cfg, o, d, smp: Sample, t_prev, v_prev, bands, arrays):
    """``bisect``: two samples on either side of a band (``bands``: ``(lo, hi)`` value ranges;
    the first listed that is straddled); move this sample into it if a point in between lies in
    it (course report, section 3.6.2)."""
    m = dev.m
    moved = m.Bool(False)
    t_m = m.Float(smp.t_s)
    for band_lo, band_hi in bands:
        straddle = smp.take & lnot(moved) & (((v_prev < band_lo) & (smp.v > band_hi)) |
                                             ((v_prev > band_hi) & (smp.v < band_lo)))
        t_k, found = _bisect_band(dev, cfg, o, d, t_prev, smp.t_s, v_prev, band_lo, band_hi,
                                  straddle)
        t_m = dr.select(straddle & found, t_k, t_m)
        moved |= straddle & found
    vals_m, grad_m = rec.reconstruct(dev, cfg.basis, dr.fma(d, t_m, o), arrays, moved)
    return Sample(b=smp.b, t_s=dr.select(moved, t_m, smp.t_s), take=smp.take,
                  v=dr.select(moved, vals_m[0], smp.v), cval=dr.select(moved, vals_m[1], smp.cval),
                  grad=dr.select(moved, grad_m, smp.grad))


def _sample_alpha(m, cfg, smp: Sample, t, t_prev, v_prev, dt, dnorm, centres):
    """The opacity of a sample's step. Opacity-correction weight: the step (uniform), the
    sub-interval (adaptive, ExaBricks) or the distance from the previous sample (bisect, course
    report). Pre-integrated: the value runs from the previous sample to this one, integrated
    over that distance (steps tile the ray from one sample to the next; the first, from where
    the ray or the leaf starts, at the first sample's value). Returns the opacity, the
    bands' shares of it and where the step is lit (:func:`_light_point`)."""
    band = cfg.band
    if cfg.method == "uniform":
        dx = dt * dnorm
    elif cfg.method == "adaptive":
        dx = (smp.b - t) * dnorm
    else:
        dx = (smp.t_s - t_prev) * dnorm
    if cfg.transfer2d is not None:
        # The 2D transfer function is the one band: opacity by value and |grad f|.
        a = corrected(cfg.transfer2d, alpha2d(m, cfg.transfer2d, smp.v, dr.norm(smp.grad)), dx)
        return dr.select(smp.take & dr.isfinite(smp.v), a, 0.0), [1.0], smp.t_s
    alphas, points = [], []
    for k, centre in enumerate(centres):
        if cfg.preintegrated:
            span = (smp.t_s - t_prev) * dnorm
            a_ramp, u = segment_alpha_and_point(m, band, k, v_prev, smp.v, span, centre)
            a = dr.select(dr.isfinite(v_prev), a_ramp,
                          corrected(band, alpha(m, band, k, smp.v, centre), span))
            points.append(u)
        else:
            a = corrected(band, alpha(m, band, k, smp.v, centre), dx)
        alphas.append(dr.select(smp.take & dr.isfinite(smp.v), a, 0.0))
    a, shares = combine(alphas)
    return a, shares, _light_point(cfg, smp, t_prev, v_prev, points, shares)


def _light_point(cfg, smp: Sample, t_prev, v_prev, points, shares):
    """Where a sample is lit: the sample, or for a pre-integrated step from the previous sample
    where the band holding most of its opacity has made half of it (``points``: that place per
    band, a fraction of the step)."""
    if not cfg.preintegrated:
        return smp.t_s
    t = dr.lerp(t_prev, smp.t_s, _dominant(points, shares))
    return dr.select(dr.isfinite(v_prev) & dr.isfinite(t), t, smp.t_s)


def _sampled_bands(dev, cfg):
    """:func:`_bands`, or with a 2D transfer function no centres and its value support as the
    one band (``bisect`` moves a sample into it)."""
    tf = cfg.transfer2d
    if tf is None:
        return _bands(dev, cfg)
    return [], [(tf.get(dev.m, SUPPORT_LO), tf.get(dev.m, SUPPORT_HI))]


@dr.syntax
def _composite_sampled(dev, cfg, o, d, t0, t1, jitter, color_of, lighting, active):
    m = dev.m
    dnorm = dr.norm(d)
    shade = lighting is not None
    uniform = cfg.method == "uniform"
    arrays = dev.arrays(cfg.basis, color=True)
    centres, bands = _sampled_bands(dev, cfg)
    # A shadow ray starts inside the band: uniform steps then sample the middle of each step,
    # so its first half step (the most opaque stretch) is not stepped over.
    rho = m.Float(-0.5 if not shade else 0.0) if uniform else jitter
    t_anchor = m.Float(t0)
    w = Walk.start(m, t0)
    dt = m.Float(cfg.step_scale * dev.min_h / dnorm)
    t_prev = m.Float(t0)
    v_prev = m.Float(dr.nan)
    C = m.Array3f(0.0)
    T = m.Float(1.0)
    samples = m.UInt32(0)
    while active:
        # Skipped nodes have no opacity; the sample before them no longer borders the next one:
        # the next step's stretch starts where the leaf does.
        new = w.needs_leaf()
        st = seek(dev, cfg, o, d, w.t, t1, w.node, w.face, m.Float(dr.nan), active & new)
        skipped = new & (st.t > w.t)
        v_prev = dr.select(skipped, dr.nan, v_prev)
        t_prev = dr.select(skipped, st.t, t_prev)
        w = w.adopt(new, st)
        active &= lnot(new) | st.found
        if dr.hint(not uniform, mode="scalar"):
            leaf_h = dr.gather(m.Float, dev.leaf_min_h, w.leaf, active & new)
            dt = dr.select(new, cfg.step_scale * leaf_h / dnorm, dt)

        smp = _volume_sample(dev, cfg, o, d, dnorm, w, t1, t_anchor, rho, dt, arrays, active)
        samples += dr.select(smp.take, 1, 0)
        if dr.hint(cfg.method == "bisect", mode="scalar"):
            smp = _into_band(dev, cfg, o, d, smp, t_prev, v_prev, bands, arrays)
        a, shares, t_light = _sample_alpha(m, cfg, smp, w.t, t_prev, v_prev, dt, dnorm,
                                           centres)
        if dr.hint(shade, mode="scalar"):
            lit = smp.take & (a > tol.ALPHA_LIT)
            A, S = lighting(dr.fma(d, t_light, o), smp.grad, lit)
            C += dr.select(lit, T * a * (color_of(shares, smp.cval) * A + S), 0.0)
        T *= 1.0 - a
        t_prev = dr.select(smp.take, smp.t_s, t_prev)
        v_prev = dr.select(smp.take, smp.v, v_prev)

        w.t = dr.select(active, smp.b, w.t)
        active &= (w.t < t1) & (T > tol.T_MIN)
    T = dr.select(T <= tol.T_MIN, 0.0, T)
    return Composite(C=C, T=T, samples=samples)


@dr.syntax
def _bisect_band(dev, cfg, o, d, t_a, t_b, v_a, band_lo, band_hi, active):
    """A point of ``[t_a, t_b]`` whose value lies in ``(band_lo, band_hi)``, by bisection on the
    side of the band that ``v_a`` is on; returns ``(t, found)``."""
    m = dev.m
    values = dev.arrays(cfg.basis)
    below = v_a < band_lo
    depth = dr.maximum(dr.ceil(dr.log2(cfg.step_scale / tol.BISECT_TARGET)), 1.0)
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
