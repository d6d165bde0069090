"""First root of a cubic on an interval, never missed (Marchesin et al. 2009).

A cubic ``f(s) = c0 + c1 s + c2 s^2 + c3 s^3`` on ``[0, L]`` is split at the roots of its
derivative (at most two) into at most three monotonic pieces. A monotonic piece holds a root
exactly when its end values differ in sign, and then exactly one, which bisection finds. An
extremum that touches zero without a sign change (a tangent, grazing hit, or an isovalue equal to
a local extremum of the field) is reported as a root at the extremum when ``|f|`` there is below
a tolerance relative to the size of the terms.

Generic over Dr.Jit array types (the Float type of ``c0``) and Python floats.
"""

from __future__ import annotations

import drjit as dr


def cubic(c, s):
    """``f(s)`` by Horner's rule; ``c = (c0, c1, c2, c3)``."""
    return dr.fma(dr.fma(dr.fma(c[3], s, c[2]), s, c[1]), s, c[0])


def extrema(c, L):
    """The derivative's real roots in ``[0, L]``, sorted: ``(r1, r2)``; a missing root is put at
    ``L`` so the pieces ``[0, r1], [r1, r2], [r2, L]`` always cover the interval."""
    a, b, k = 3.0 * c[3], 2.0 * c[2], c[1]
    disc = b * b - 4.0 * a * k
    real = disc >= 0.0
    sq = dr.sqrt(dr.maximum(disc, 0.0))
    # Numerically stable pair of roots (no cancellation between b and the square root).
    q = -0.5 * (b + dr.copysign(sq, b))
    quad = dr.abs(a) > 1e-30
    r_a = dr.select(quad, q / a, dr.inf)
    r_b = dr.select(q != 0.0, k / q, dr.inf)
    # Degenerate derivative (a = 0): the single root of b s + k.
    lin = dr.select(b != 0.0, -k / b, dr.inf)
    r1 = dr.select(quad, dr.minimum(r_a, r_b), lin)
    r2 = dr.select(quad, dr.maximum(r_a, r_b), dr.inf)
    inside1 = real & (r1 > 0.0) & (r1 < L)
    inside2 = real & (r2 > 0.0) & (r2 < L)
    r1, r2 = dr.select(inside1, r1, L), dr.select(inside2, r2, L)
    return dr.minimum(r1, r2), dr.maximum(r1, r2)


def rational_extrema(num, den, L, iterations=2):
    """Where ``f = num / den`` (two cubics, ``den > 0``) turns in ``[0, L]``: the roots of
    ``num' den - num den'``, found as the fixed points of ``v -> f(s_v)``, ``s_v`` an extremum
    of the cubic ``num - v den`` (at a fixed point ``num' = v den'`` with ``v = f``). The map's
    slope is ``f'`` there, zero at the answer, so each iteration squares the error; where
    ``den`` is constant the first one is exact. Returns ``(r1, r2)`` as :func:`extrema` does:
    sorted, a missing one at ``L``."""
    def shifted(v):
        return [num[i] - v * den[i] for i in range(4)]

    mid = 0.5 * L
    v = cubic(num, mid) / cubic(den, mid)
    r1, r2 = extrema(shifted(v), L)
    for _ in range(iterations):
        r1 = extrema(shifted(cubic(num, r1) / cubic(den, r1)), L)[0]
        r2 = extrema(shifted(cubic(num, r2) / cubic(den, r2)), L)[1]
    return dr.minimum(r1, r2), dr.maximum(r1, r2)


def first_root_bracket(c, L, scale, rel_tol=2e-6):
    """Locate the first root of the cubic ``c`` in ``[0, L]``.

    ``scale`` is the magnitude of the terms that make up ``f`` (for the tangent tolerance).
    Returns ``(found, a, b)``: the first monotonic piece ``[a, b]`` whose ends differ in sign,
    or ``a = b`` at a tangent extremum (or at ``L`` where ``f`` touches zero there).
    """
    r1, r2 = extrema(c, L)
    f0, f1, f2, f3 = cubic(c, 0.0 * L), cubic(c, r1), cubic(c, r2), cubic(c, L)
    tol = rel_tol * scale
    pos0, pos1, pos2, pos3 = f0 > 0.0, f1 > 0.0, f2 > 0.0, f3 > 0.0
    cross1 = pos0 != pos1
    cross2 = pos1 != pos2
    cross3 = pos2 != pos3
    # A tangent at an interior extremum (r < L), or at the interval's end: there the cubic of
    # the next interval takes over, so an extremum of the field on the boundary (a ray through
    # a cell centre at the field's maximum, a tangent on a dual plane) shows up only as |f(L)|
    # near zero without a sign change. (The interval's start is the previous one's end.)
    touch1 = (r1 < L) & (dr.abs(f1) <= tol)
    touch2 = (r2 < L) & (dr.abs(f2) <= tol)
    touch3 = dr.abs(f3) <= tol
    found = cross1 | touch1 | cross2 | touch2 | cross3 | touch3
    a = dr.select(cross1, 0.0 * L, dr.select(touch1, r1, dr.select(cross2, r1,
                  dr.select(touch2, r2, dr.select(cross3, r2, L)))))
    b = dr.select(cross1, r1, dr.select(touch1, r1, dr.select(cross2, r2,
                  dr.select(touch2, r2, L))))
    return found, a, b


@dr.syntax
def refine_root(c, a, b, iterations: int = 24):
    """Bisection for the root of a cubic that is monotonic on ``[a, b]`` and changes sign there
    (a tangent with ``a == b`` returns ``a``). Returns the root."""
    fa = cubic(c, a)
    up = fa <= 0.0
    i = 0
    while dr.hint(i < iterations, mode="scalar"):
        mid = 0.5 * (a + b)
        below = (cubic(c, mid) <= 0.0) == up
        a = dr.select(below, mid, a)
        b = dr.select(below, b, mid)
        i += 1
    return 0.5 * (a + b)
