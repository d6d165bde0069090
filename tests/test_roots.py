"""The first root of a cubic (:mod:`mi_amr.kernels.roots`) on its hard cases, in float32 and
with no way around them: tangents (an extremum touching zero without a sign change) and double
roots, at the first extremum, the second and the interval's end.

The cubics are built from roots and offsets that float32 holds exactly, and their extrema and
values there come out exact in float32 (checked below), so each case takes the path it names:
a value of exactly 0 at an extremum counts as a sign change, a tiny positive value does not
and must be caught by the tangent tolerance. Runs on every present variant.
"""

import numpy as np
import pytest

pytest.importorskip("drjit")

from mi_amr.kernels import roots  # noqa: E402

TINY = 2.0 ** -20           # far inside the tangent tolerance (2e-6 of the terms' size)


def poly(double, simple, lead=1.0, lift=0.0):
    """Coefficients ``(c0, c1, c2, c3)`` of ``lead (s - double)^2 (s - simple) + lift``."""
    p = lead * np.polynomial.polynomial.polyfromroots([double, double, simple])
    p[0] += lift
    assert np.array_equal(p.astype(np.float32).astype(np.float64), p)   # float32 holds it
    return p


def first_root(m, p, L=1.0):
    """``(found, root, r1, r2, f(r1), f(r2))`` of the kernels for the cubic ``p`` on
    ``[0, L]``, in float32."""
    c = [m.Float(np.float32(x)) for x in p]
    L = m.Float(np.float32(L))
    scale = m.Float(np.float32(np.abs(p).sum()))
    found, a, b = roots.first_root_bracket(c, L, scale)
    r1, r2 = roots.extrema(c, L)
    out = (found, roots.refine_root(c, a, b), r1, r2, roots.cubic(c, r1), roots.cubic(c, r2))
    return [np.array(v)[0] for v in out]


# (double root, simple root, lead, lift, expected first root in [0, 1], the extremum it is at,
#  f there in float32)
CASES = {
    # A tangent from above at the first extremum (a maximum of -(...)); nothing else in [0, 1].
    "tangent above at r1": (0.5, -2.0, 1.0, TINY, 0.5, "r1", TINY),
    # The same from below (a negative leading term).
    "tangent below at r1": (0.5, -2.0, -1.0, -TINY, 0.5, "r1", -TINY),
    # A tangent from above at the second extremum, the first one lying before it in [0, 1].
    "tangent above at r2": (0.75, -0.25, 1.0, TINY, 0.75, "r2", TINY),
    # A double root at the first extremum (f there exactly 0), then a simple root at 0.75:
    # the first root is the double one, not the crossing after it.
    "double root, then a crossing": (0.25, 0.75, 1.0, 0.0, 0.25, "r1", 0.0),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test01_tangents_and_double_roots_are_first_roots(backend, case):
    double, simple, lead, lift, want, where, f_there = CASES[case]
    found, root, r1, r2, f1, f2 = first_root(backend, poly(double, simple, lead, lift))
    # The case is what it says in float32: the extremum exact, the value there as built.
    extremum, value = (r1, f1) if where == "r1" else (r2, f2)
    assert extremum == np.float32(want) and value == np.float32(f_there)
    assert found
    assert root == np.float32(want)


@pytest.mark.parametrize("lead", [1.0, -1.0])
def test02_a_near_miss_beyond_the_tolerance_is_no_root(backend, lead):
    """The tangent cubic of test01 lifted off zero by 4x the tolerance: no root."""
    p = poly(0.5, -2.0, lead, 0.0)
    lift = lead * np.float32(2.0 ** -14)             # 6.1e-5 > 4 * 2e-6 * sum |c| (3.4e-5)
    assert lift * lead > 4 * 2e-6 * np.abs(p).sum()
    found, *_ = first_root(backend, poly(0.5, -2.0, lead, float(lift)))
    assert not found


def test03_a_tangent_at_the_intervals_end_is_a_root(backend):
    """A double root at ``L`` (f(L) tiny, no sign change on [0, L]) is found at ``L``: the
    next interval's cubic takes over from there."""
    p = poly(0.5, -2.0, 1.0, TINY)
    found, root, *_ = first_root(backend, p, L=0.5)
    assert found and root == np.float32(0.5)


def _rational_cases(n=200, seed=4):
    """``n`` pieces ``N / D`` on ``[0, 1]``: ``N`` with extrema at two random places, ``D`` a
    positive cubic that varies by up to a third (a basis reconstruction's weight sum)."""
    rng = np.random.default_rng(seed)
    e = np.sort(rng.uniform(0.1, 0.9, (n, 2)), axis=1)
    num = np.stack([rng.uniform(-1, 1, n), 3 * e[:, 0] * e[:, 1], -1.5 * e.sum(1),
                    np.ones(n)], axis=1)
    den = np.concatenate([np.ones((n, 1)), rng.uniform(-0.1, 0.1, (n, 3))], axis=1)
    return num, den


def _true_extrema(num, den):
    """The roots of ``N' D - N D'`` in ``(0, 1)``, float64."""
    P = np.polynomial.polynomial
    q = P.polysub(P.polymul(P.polyder(num), den), P.polymul(num, P.polyder(den)))
    r = P.polyroots(q)
    r = np.sort(r[(np.abs(r.imag) < 1e-9) & (r.real > 0.0) & (r.real < 1.0)].real)
    return r


def test04_a_rational_pieces_extrema_are_where_its_value_turns(backend):
    """:func:`roots.rational_extrema` against the float64 roots of ``N' D - N D'``, on
    pieces whose denominator varies (where it is constant the first step is exact): each
    within 1e-5 of the interval, a missing one at ``L``."""
    num, den = _rational_cases()
    m = backend
    c_num = [m.Float(num[:, i].astype(np.float32)) for i in range(4)]
    c_den = [m.Float(den[:, i].astype(np.float32)) for i in range(4)]
    r1, r2 = roots.rational_extrema(c_num, c_den, m.Float(1.0))
    got = np.stack([np.array(r1), np.array(r2)], axis=1)
    inside = 0
    for i in range(len(num)):
        want = _true_extrema(num[i].astype(np.float32), den[i].astype(np.float32))
        inside += len(want)
        want = np.concatenate([want, np.ones(2 - len(want))])
        assert np.abs(got[i] - want).max() < 1e-5, (i, got[i], want)
    assert inside > 1.5 * len(num)      # the cases have extrema to find


def _bound_cases(seed=7):
    """Pieces ``N / D`` on ``[0, L]`` for :func:`test05_...`: those of :func:`_rational_cases`
    stretched to random lengths (the same functions of ``s / L``), and as many with a
    denominator that comes near zero or below it inside the piece (missing data)."""
    rng = np.random.default_rng(seed)
    num, den = _rational_cases(seed=seed)
    n = len(num)
    L = rng.uniform(0.05, 4.0, n)
    bad = den.copy()
    bad[:, 0] = rng.uniform(-0.05, 0.05, n)            # D(0) near 0, of either sign
    power = L[:, None] ** -np.arange(4)[None]
    num, den, bad = num * power, den * power, bad * power
    return (np.concatenate([num, num]), np.concatenate([den, bad]),
            np.concatenate([L, L]), np.repeat([True, False], n))


def test05_a_volume_pieces_cheap_value_bound_holds_its_values(backend):
    """The volume march skips the search for a piece's extrema where a cheap bound on its
    values (:func:`composite._value_bound`: the ratios of the Bernstein coefficients of ``N``
    and ``D``) misses every band. The bound must hold every value of the piece (float64 at
    2001 points of the float32 cubics) and the exact range the march would take
    (:func:`composite._value_cuts`); it is the whole line where ``D``'s coefficients are not
    all positive, and finite where they are, and then seldom much wider than the true range."""
    from mi_amr.kernels import composite
    from mi_amr.kernels.traverse import CubicPiece

    m = backend
    num, den, L, positive = _bound_cases()
    num, den, L = num.astype(np.float32), den.astype(np.float32), L.astype(np.float32)
    f = lambda a: m.Float(np.ascontiguousarray(a))  # noqa: E731
    cp = CubicPiece(t=f(np.zeros_like(L)), end=f(L), length=f(L),
                    nums=[[f(num[:, i]) for i in range(4)]], den=[f(den[:, i]) for i in range(4)])
    lo, hi = (np.array(x) for x in composite._value_bound(cp))
    exact = [np.array(x) for x in composite._value_range(composite._value_cuts(cp)[1])]
    P = np.polynomial.polynomial
    d_coef = den.astype(np.float64)
    ratio = []
    for i in np.flatnonzero(positive):
        s = np.linspace(0.0, float(L[i]), 2001)
        d = P.polyval(s, d_coef[i])
        assert d.min() > 0.0
        values = P.polyval(s, num[i].astype(np.float64)) / d
        assert np.isfinite(lo[i]) and np.isfinite(hi[i]), i
        assert lo[i] <= values.min() and values.max() <= hi[i], (i, lo[i], hi[i])
        assert lo[i] <= exact[0][i] and exact[1][i] <= hi[i], (i, lo[i], hi[i])
        ratio.append((hi[i] - lo[i]) / (values.max() - values.min()))
    assert np.median(ratio) < 2.0           # (1.48 on these cases: close enough to skip)
    # Where a Bernstein coefficient of D is not positive: no bound.
    bernstein_d = np.stack([d_coef[:, 0], d_coef[:, 0] + d_coef[:, 1] * L / 3,
                            d_coef[:, 0] + (2 * d_coef[:, 1] * L + d_coef[:, 2] * L * L) / 3,
                            P.polyval(L, d_coef.T, tensor=False)], axis=1)
    unbounded = ~positive & (bernstein_d.min(axis=1) <= 0.0)
    assert unbounded.sum() > 50
    assert np.all(lo[unbounded] == -np.inf) and np.all(hi[unbounded] == np.inf)
