"""Reconstruction of a continuous field from AMR cells, with analytic gradients.

Two methods, both in world space (positions ``p``; gradients per world unit):

* **finest** -- trilinear interpolation in the finest grid containing ``p`` (the kd leaf's
  owner). Cell centres are the interpolation nodes. Grid edges: within the outer half cell of a
  grid the cell index is clamped to the grid, i.e. the value is extended as a constant along the
  axis (and the gradient's component along that axis is zero). Neighbouring grids are not
  consulted, so values jump at grid and level boundaries -- the cracks this method is known for.
* **basis** -- Wald et al.'s basis blend (course report, section 3.5):
  ``B(p) = sum_C H_C(p) v_C / sum_C H_C(p)`` over *leaf* cells ``C`` (cells no finer cell
  covers), ``H_C(p) = prod_a max(0, 1 - |c_a - p_a| / w_a)`` with ``c`` the cell centre and ``w``
  its width. Continuous across levels; on a single level it is trilinear interpolation. The
  gradient is the quotient rule applied to the two sums (section 3.10, with the correct sign:
  ``dH/dp_a = -sign(p_a - c_a) / w_a * prod_{b != a} h_b``).

Along a ray ``p(s) = p0 + s d`` inside one region where the contributing cells and the side of
each cell centre are fixed, every ``H_C`` is a product of three linear functions of ``s``, so
both sums are cubics in ``s``: :func:`segment_cubic` returns their coefficients (Marchesin et
al. 2009 for one trilinear cell; the same holds for the blend).

The Dr.Jit functions are generic over the backend module ``dev.m``. Their float64 references
(the vectorised model and the brute-force sums) are in :mod:`mi_amr.core.field64`.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from mi_amr.kernels import roots
from mi_amr.kernels.device import BRICK, BRICK_N, NO_BRICK, NO_GRID, backend_of

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Array3f, Float, UInt32


# ---------------------------------------------------------------------- kd-tree point location

@dr.syntax
def locate(dev, p, active, start=None):
    """Index of the kd leaf containing world point ``p`` (a point on a split plane goes up),
    descending from node ``start`` (the root by default), which must contain ``p``."""
    m = dev.m
    node = m.UInt32(0) if start is None else m.UInt32(start)
    cs = dr.gather(m.Array2u, dev.node_code_split, node, active)
    while dr.hint(active & ((cs.x & 3) != 3), label="locate", exclude=[active, dev, m, p]):
        axis = cs.x & 3
        split = dr.reinterpret_array(m.Float, cs.y)
        coord = dr.select(axis == 0, p.x, dr.select(axis == 1, p.y, p.z))
        node = (cs.x >> 2) + dr.select(coord >= split, m.UInt32(1), m.UInt32(0))
        cs = dr.gather(m.Array2u, dev.node_code_split, node, active)
    return cs.x >> 2


def grid_frame(dev, g, active):
    """Origin, inverse cell size, shape and first value index of grid ``g``."""
    m = dev.m
    o = dr.gather(m.Array3f, dev.grid_origin, g, active)
    ih = dr.gather(m.Array3f, dev.grid_inv_h, g, active)
    n = dr.gather(m.Array3u, dev.grid_shape, g, active)
    off = dr.gather(m.UInt32, dev.grid_offset, g, active)
    return o, ih, n, off


def _cell_index(n, off, i, j, k):
    return off + (i * n.y + j) * n.z + k


# ---------------------------------------------------------------------- point reconstruction

def finest_point(dev, leaf, p, arrays, active):
    """Trilinear reconstruction in the owner grid of ``leaf`` at ``p``.

    ``arrays`` are flat value arrays (the field, maybe a colour field). Returns
    ``(values, gradient_of_first)``; values are NaN where the leaf has no owner. Corners holding
    a missing value (NaN) get no weight and the others are renormalised, as in
    :func:`finest_cubic`, so a crossing found next to missing data has a value and a normal.
    """
    m = dev.m
    g = dr.gather(m.UInt32, dev.leaf_owner, leaf, active)
    ok = active & (g != NO_GRID)
    o, ih, n, off = grid_frame(dev, g, ok)
    nf = m.Array3f(n)
    u = (p - o) * ih - 0.5
    uc = dr.clip(u, 0.0, nf - 1.0)
    i0 = dr.minimum(m.Array3u(dr.floor(uc)), dr.maximum(n, 2) - 2)
    i1 = dr.minimum(i0 + 1, n - 1)
    f = uc - m.Array3f(i0)
    # Along an axis where p is in the clamped outer half cell the value is constant.
    live = m.Array3f(dr.select((u >= 0.0) & (u <= nf - 1.0), 1.0, 0.0))
    num = [m.Float(0.0) for _ in arrays]
    den = m.Float(0.0)
    dnum = m.Array3f(0.0)
    dden = m.Array3f(0.0)
    for corner in range(8):
        bx, by, bz = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
        idx = _cell_index(n, off, i1.x if bx else i0.x, i1.y if by else i0.y,
                          i1.z if bz else i0.z)
        wx = f.x if bx else 1.0 - f.x
        wy = f.y if by else 1.0 - f.y
        wz = f.z if bz else 1.0 - f.z
        dw = m.Array3f((1.0 if bx else -1.0) * wy * wz, (1.0 if by else -1.0) * wx * wz,
                       (1.0 if bz else -1.0) * wx * wy)
        vals = [dr.gather(m.Float, arr, idx, ok) for arr in arrays]
        has = ok & dr.isfinite(vals[0])
        w = dr.select(has, wx * wy * wz, 0.0)
        dw = dr.select(has, dw, 0.0)
        den += w
        dden += dw
        for a in range(len(arrays)):
            num[a] += w * dr.select(has, vals[a], 0.0)
        dnum += dw * dr.select(has, vals[0], 0.0)
    inv = dr.select(ok & (den > 0.0), dr.rcp(den), dr.nan)
    values = [x * inv for x in num]
    grad = (dnum * den - dden * num[0]) * (inv * inv) * ih * live
    return values, grad


def brick_cell(dev, level, i0, active):
    """Position in the brick pool of level ``level``'s cell ``i0`` (``Array3i``, level index
    space) and whether it exists; the other 7 corners of the dual cell starting at ``i0`` are at
    the offsets of :func:`corner_offset`."""
    m = dev.m
    lo, toff, dims = dev.level_bricks(level, active)
    rel = i0 - lo
    inside = dr.all(rel >= 0)
    r = m.Array3u(dr.maximum(rel, 0))
    b = r // BRICK
    inside &= dr.all(b < dims)
    brick = dr.gather(m.UInt32, dev.brick_table, toff + (b.x * dims.y + b.y) * dims.z + b.z,
                   active & inside)
    ok = active & inside & (brick != NO_BRICK)
    local = r - b * BRICK
    base = brick * (BRICK_N ** 3) + (local.x * BRICK_N + local.y) * BRICK_N + local.z
    return base, ok


def corner_offset(bx, by, bz):
    """Offset in the brick pool from a dual cell's lower corner to corner ``(bx, by, bz)``."""
    return (bx * BRICK_N + by) * BRICK_N + bz


def _level_frame(dev, level, p, active):
    """Local coordinate of ``p`` in level ``level``'s cell-centre lattice and its inverse cell
    size: ``u = (p - anchor) / h - 0.5`` (cell ``i`` has its centre at ``u = i``)."""
    m = dev.m
    ih = dev.level_inv_h(level, active)
    return (p - dev.anchor) * ih - 0.5, ih


@dr.syntax
def basis_point(dev, leaf, p, arrays, active):
    """Basis-blend reconstruction at ``p``: the leaf cells of every level active in ``leaf``.

    ``arrays`` (one or two) are brick pools of *leaf values* (NaN = no weight). Returns
    ``(values, gradient_of_first)``; NaN where no cell has weight.
    """
    m = dev.m
    levels = dr.gather(m.UInt32, dev.leaf_levels, leaf, active)
    second = arrays[1] if len(arrays) > 1 else arrays[0]
    # (num1 None with one array: a loop variable that never changes makes Dr.Jit trace the
    # loop again without it.)
    num0, den = m.Float(0.0), m.Float(0.0)
    num1 = m.Float(0.0) if len(arrays) > 1 else None
    dnum, dden = m.Array3f(0.0), m.Array3f(0.0)
    while dr.hint(active & (levels != 0), label="levels",
                  exclude=[active, arrays, dev, m, p, second]):
        level = dr.tzcnt(levels)
        levels &= levels - 1
        u, ih = _level_frame(dev, level, p, active)
        base_f = dr.floor(u)
        f = u - base_f
        base, ok = brick_cell(dev, level, m.Array3i(base_f), active)
        for corner in range(8):
            b = (corner >> 2) & 1, (corner >> 1) & 1, corner & 1
            idx = base + corner_offset(*b)
            wx = f.x if b[0] else 1.0 - f.x
            wy = f.y if b[1] else 1.0 - f.y
            wz = f.z if b[2] else 1.0 - f.z
            dw = m.Array3f((1.0 if b[0] else -1.0) * wy * wz, (1.0 if b[1] else -1.0) * wx * wz,
                           (1.0 if b[2] else -1.0) * wx * wy) * ih
            v0 = dr.gather(m.Float, arrays[0], idx, ok)
            has = ok & dr.isfinite(v0)
            v0 = dr.select(has, v0, 0.0)
            w = dr.select(has, wx * wy * wz, 0.0)
            dw = dr.select(has, dw, 0.0)
            den += w
            dden += dw
            num0 += w * v0
            dnum += dw * v0
            if dr.hint(len(arrays) > 1, mode="scalar"):
                num1 += w * dr.select(has, dr.gather(m.Float, second, idx, has), 0.0)
    ok = den > 0.0
    inv = dr.select(ok, dr.rcp(den), dr.nan)
    values = [num0 * inv] + ([num1 * inv] if len(arrays) > 1 else [])
    grad = (dnum * den - dden * num0) * (inv * inv)
    return values, grad


def reconstruct(dev, basis: bool, p, arrays, active, leaf=None):
    """Values (one per array) and the gradient of the first at world ``p``; locates the leaf
    unless given. ``arrays`` come from :meth:`DeviceVolume.arrays` for the same ``basis``."""
    if leaf is None:
        leaf = locate(dev, p, active)
    if basis:
        return basis_point(dev, leaf, p, arrays, active)
    return finest_point(dev, leaf, p, arrays, active)


# ---------------------------------------------------------------------- cubic along a ray

def _clamped_factors(m, ua, du, um, n, ih):
    """Finest-level rule along one axis: the two corners' weights ``alpha + beta * s``, their
    (clamped) indices and the weights' derivatives along the axis (world). ``ua``/``du``: local
    coordinate at s = 0 and its rate; ``um``: at the segment's middle (chooses the dual cell);
    ``ih``: the inverse cell size along the axis."""
    last = m.Float(n) - 1.0
    below = um < 0.0
    above = um > last
    i0 = dr.minimum(m.UInt32(dr.maximum(dr.floor(um), 0.0)), dr.maximum(n, 2) - 2)
    i1 = dr.minimum(i0 + 1, n - 1)
    e = ua - m.Float(i0)
    flat = below | above        # (the clamped outer half cell: constant along the axis)
    a0 = dr.select(below, 1.0, dr.select(above, 0.0, 1.0 - e))
    b0 = dr.select(flat, 0.0, -du)
    a1 = dr.select(below, 0.0, dr.select(above, 1.0, e))
    b1 = dr.select(flat, 0.0, du)
    slope = dr.select(flat, 0.0, ih)
    return (a0, b0, i0, -slope), (a1, b1, i1, slope)


def _cubics(m, fx, fy, fz, fetch, count):
    """Cubic coefficients of ``sum_C w_C(s) v_C`` (one per value array) and of ``sum_C w_C(s)``
    over the 8 corners, with ``w_C`` the product of the corners' linear factors (``fx`` etc.:
    two ``(alpha, beta, index)`` per axis) and ``fetch(ix, iy, iz) -> (values, has)``."""
    num = [[m.Float(0.0) for _ in range(4)] for _ in range(count)]
    den = [m.Float(0.0) for _ in range(4)]
    for ax, bx, ix, _ in fx:
        for ay, by, iy, _ in fy:
            # (ax + bx s)(ay + by s) = q0 + q1 s + q2 s^2
            q0, q1, q2 = ax * ay, ax * by + bx * ay, bx * by
            lin_num = [[m.Float(0.0), m.Float(0.0)] for _ in range(count)]
            lin_den = [m.Float(0.0), m.Float(0.0)]
            for az, bz, iz, _ in fz:
                vals, has = fetch(ix, iy, iz)
                wa = dr.select(has, az, 0.0)
                wb = dr.select(has, bz, 0.0)
                lin_den = [lin_den[0] + wa, lin_den[1] + wb]
                for a in range(count):
                    v = dr.select(has, vals[a], 0.0)
                    lin_num[a] = [lin_num[a][0] + wa * v, lin_num[a][1] + wb * v]
            for target, lin in [(den, lin_den)] + [(num[a], lin_num[a]) for a in range(count)]:
                target[0] += q0 * lin[0]
                target[1] += q0 * lin[1] + q1 * lin[0]
                target[2] += q1 * lin[1] + q2 * lin[0]
                target[3] += q2 * lin[1]
    return num, den


def _gradient_quadratics(m, fx, fy, fz, fetch):
    """Quadratic coefficients (in ``s``) of the gradients (world) of ``sum_C w_C(s) v_C`` (the
    first value array) and of ``sum_C w_C(s)``, per axis: ``dw_C / dx`` is the x factor's
    slope times the y and z factors, linear each (``fx`` etc. as :func:`_cubics` takes them,
    with each factor's derivative along its axis)."""
    gn = [[m.Float(0.0) for _ in range(3)] for _ in range(3)]
    gd = [[m.Float(0.0) for _ in range(3)] for _ in range(3)]
    for x in fx:
        for y in fy:
            for z in fz:
                vals, has = fetch(x[2], y[2], z[2])
                v = dr.select(has, vals[0], 0.0)
                for axis, (f, g, h) in enumerate(((x, y, z), (y, x, z), (z, x, y))):
                    # d/d(axis): the slope of f times (g0 + g1 s)(h0 + h1 s)
                    slope = dr.select(has, f[3], 0.0)
                    q = (slope * g[0] * h[0], slope * (g[0] * h[1] + g[1] * h[0]),
                         slope * g[1] * h[1])
                    for c in range(3):
                        gd[axis][c] += q[c]
                        gn[axis][c] = dr.fma(q[c], v, gn[axis][c])
    return gn, gd


@dataclass
class GradientPiece:
    """The gradient of the reconstruction ``N / D`` along a segment ``p0 + s d``: the
    quadratics (in ``s``; 3 coefficients each) of the gradients of its numerator ``gn[axis]``
    and of its denominator ``gd[axis]``, world units (:func:`segment_gradient`)."""

    gn: list
    gd: list

    def at(self, s, num, den):
        """The gradient of ``N / D`` at ``s`` (world, per world unit), given the cubics ``num``
        and ``den`` of the same segment (:func:`segment_cubic`): the quotient rule; NaN where
        no cell has weight, as :func:`basis_point` gives."""
        def quad(c):
            return dr.fma(dr.fma(c[2], s, c[1]), s, c[0])

        n, d = roots.cubic(num, s), roots.cubic(den, s)
        inv = dr.select(d > 0.0, dr.rcp(d), dr.nan)
        g = [(quad(self.gn[a]) * d - n * quad(self.gd[a])) * (inv * inv) for a in range(3)]
        return backend_of(type(n)).Array3f(*g)


@dataclass
class Segment:
    """A segment ``p0 + s d`` of a ray (volume world space) inside kd leaf ``leaf``, whose
    middle is at ``s = s_mid``: what :func:`segment_cubic` takes."""

    leaf: UInt32
    p0: Array3f
    d: Array3f
    s_mid: Float


def _finest_factors(dev, g, seg: Segment, arrays, active):
    """The finest-level rule in grid ``g`` along the segment ``seg``: the factors of each axis
    (:func:`_clamped_factors`) and ``fetch(i, j, k) -> (values, has)`` of the grid's cells."""
    m = dev.m
    p0, d, s_mid = seg.p0, seg.d, seg.s_mid
    o, ih, n, off = grid_frame(dev, g, active)
    ua = (p0 - o) * ih - 0.5
    du = d * ih
    um = ua + s_mid * du
    fx = _clamped_factors(m, ua.x, du.x, um.x, n.x, ih.x)
    fy = _clamped_factors(m, ua.y, du.y, um.y, n.y, ih.y)
    fz = _clamped_factors(m, ua.z, du.z, um.z, n.z, ih.z)

    def fetch(i, j, k):
        idx = _cell_index(n, off, i, j, k)
        vals = [dr.gather(m.Float, arr, idx, active) for arr in arrays]
        return vals, active & dr.isfinite(vals[0])

    return fx, fy, fz, fetch


def finest_cubic(dev, g, seg: Segment, arrays, active):
    """Cubic coefficients (in ``s``, along ``seg.p0 + s seg.d``) of the finest-level
    reconstruction in grid ``g`` for the segment ``seg``: ``num[a]`` per value array and
    ``den`` (1 unless a value is missing)."""
    return _cubics(dev.m, *_finest_factors(dev, g, seg, arrays, active), len(arrays))


def _level_factors(dev, level, seg: Segment, arrays, active):
    """The basis sums of one level's leaf cells along the segment ``seg``: the two corners'
    factors of each axis (weights ``alpha + beta s``, brick offsets, derivatives along the
    axis) and ``fetch(bx, by, bz) -> (values, has)`` of the dual cell's corners in the brick
    pools (a corner with no leaf cell has none)."""
    m = dev.m
    p0, d, s_mid = seg.p0, seg.d, seg.s_mid
    ua, ih = _level_frame(dev, level, p0, active)
    du = d * ih
    base_f = dr.floor(ua + s_mid * du)
    e = ua - base_f
    base, ok = brick_cell(dev, level, m.Array3i(base_f), active)
    fx = [(1.0 - e.x, -du.x, 0, -ih.x), (e.x, du.x, 1, ih.x)]
    fy = [(1.0 - e.y, -du.y, 0, -ih.y), (e.y, du.y, 1, ih.y)]
    fz = [(1.0 - e.z, -du.z, 0, -ih.z), (e.z, du.z, 1, ih.z)]

    def fetch(bx, by, bz):
        idx = base + corner_offset(bx, by, bz)
        vals = [dr.gather(m.Float, arr, idx, ok) for arr in arrays]
        return vals, ok & dr.isfinite(vals[0])

    return fx, fy, fz, fetch


def level_cubic(dev, level, seg: Segment, arrays, active):
    """Cubic coefficients of the basis sums of one level's leaf cells along the segment
    ``seg`` (corners with no leaf cell get no weight)."""
    return _cubics(dev.m, *_level_factors(dev, level, seg, arrays, active), len(arrays))


def segment_cubic(dev, basis: bool, seg: Segment, arrays, active):
    """Cubics ``num[a](s)`` and ``den(s)`` of the reconstruction along the segment ``seg``
    (the field is ``num / den``)."""
    if basis:
        return _basis_segment_cubic(dev, seg, arrays, active)
    g = dr.gather(dev.m.UInt32, dev.leaf_owner, seg.leaf, active)
    return finest_cubic(dev, g, seg, arrays, active & (g != NO_GRID))


def segment_gradient(dev, basis: bool, seg: Segment, arrays, active) -> GradientPiece:
    """The gradient of the reconstruction of the first of ``arrays`` along the segment
    ``seg``, which must lie in one dual cell of every level it blends (a cubic piece does):
    the same cells as :func:`segment_cubic`, read once for every point of the segment
    (:meth:`GradientPiece.at`), where :func:`reconstruct` reads them per point."""
    return segment_shading(dev, basis, seg, arrays[:1], active)[0]


def segment_shading(dev, basis: bool, seg: Segment, arrays, active):
    """``(gradient, cnum)``: :func:`segment_gradient` of the first of ``arrays`` along
    ``seg`` and, where a second array is given, that array's cubic numerator over the
    denominator that :func:`segment_cubic` gives (its ``num[1]``; None with one array). Each
    corner is read once for both, so a march can take the field's cubic alone for every
    piece and read the colour field only where a piece is shaded."""
    if basis:
        return _basis_segment_shading(dev, seg, arrays, active)
    g = dr.gather(dev.m.UInt32, dev.leaf_owner, seg.leaf, active)
    ok = active & (g != NO_GRID)
    return _shading_parts(dev.m, _finest_factors(dev, g, seg, arrays, ok), len(arrays) > 1)


def _shading_parts(m, factors, color: bool):
    """The :class:`GradientPiece` of the first array of ``factors`` (``(fx, fy, fz, fetch)``,
    as :func:`_cubics` takes them) and, where ``color``, the second array's cubic numerator
    (None otherwise); each corner fetched once for both."""
    fx, fy, fz, fetch = factors
    seen = {}

    def once(*corner):
        # (By identity: a finest-level corner index is a Dr.Jit array; the factors hold each
        # one for the whole call.)
        key = tuple(id(i) for i in corner)
        if key not in seen:
            seen[key] = fetch(*corner)
        return seen[key]

    gradient = GradientPiece(*_gradient_quadratics(m, fx, fy, fz, once))
    if not color:
        return gradient, None

    def second(*corner):
        vals, has = once(*corner)
        return vals[1:2], has

    return gradient, _cubics(m, fx, fy, fz, second, 1)[0][0]


def _added(sums, gradient: GradientPiece):
    """``sums`` (18 Floats) plus the coefficients of ``gradient``'s quadratics, in order."""
    return [a + c for a, c in zip(sums, [c for q in gradient.gn + gradient.gd for c in q])]


@dr.syntax
def _basis_segment_shading(dev, seg: Segment, arrays, active):
    m = dev.m
    color = len(arrays) > 1
    levels = dr.gather(m.UInt32, dev.leaf_levels, seg.leaf, active)
    sums = [m.Float(0.0) for _ in range(18)]       # gn, then gd: 3 axes x 3 coefficients
    # (None without a colour array: a loop variable that never changes makes Dr.Jit trace
    # the loop again without it.)
    cnum = [m.Float(0.0) for _ in range(4)] if color else None
    while dr.hint(active & (levels != 0), label="level_gradients",
                  exclude=[active, arrays, dev, m, seg]):
        level = dr.tzcnt(levels)
        levels &= levels - 1
        gradient, c = _shading_parts(m, _level_factors(dev, level, seg, arrays, active), color)
        sums = _added(sums, gradient)
        if dr.hint(color, mode="scalar"):
            cnum = [cnum[i] + c[i] for i in range(4)]
    return GradientPiece(gn=[sums[3 * a:3 * a + 3] for a in range(3)],
                         gd=[sums[9 + 3 * a:12 + 3 * a] for a in range(3)]), cnum


@dr.syntax
def _basis_segment_cubic(dev, seg: Segment, arrays, active):
    m = dev.m
    levels = dr.gather(m.UInt32, dev.leaf_levels, seg.leaf, active)
    n0, n1, n2, n3 = m.Float(0.0), m.Float(0.0), m.Float(0.0), m.Float(0.0)
    two = len(arrays) > 1
    # (None without a second array: a loop variable that never changes makes Dr.Jit trace
    # the loop again without it.)
    c0, c1, c2, c3 = (m.Float(0.0), m.Float(0.0), m.Float(0.0), m.Float(0.0)) if two else \
        (None, None, None, None)
    d0, d1, d2, d3 = m.Float(0.0), m.Float(0.0), m.Float(0.0), m.Float(0.0)
    while dr.hint(active & (levels != 0), label="level_cubics", exclude=[active, arrays, dev, seg]):
        level = dr.tzcnt(levels)
        levels &= levels - 1
        num, den = level_cubic(dev, level, seg, arrays, active)
        n0, n1, n2, n3 = n0 + num[0][0], n1 + num[0][1], n2 + num[0][2], n3 + num[0][3]
        if dr.hint(two, mode="scalar"):
            c0, c1, c2, c3 = c0 + num[1][0], c1 + num[1][1], c2 + num[1][2], c3 + num[1][3]
        d0, d1, d2, d3 = d0 + den[0], d1 + den[1], d2 + den[2], d3 + den[3]
    nums = [[n0, n1, n2, n3]] + ([[c0, c1, c2, c3]] if two else [])
    return nums, [d0, d1, d2, d3]
