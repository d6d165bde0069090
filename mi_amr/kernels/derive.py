"""Derived fields from the velocity gradient (Q-criterion, vorticity) computed by Dr.Jit
kernels, whole chunks of a level at a time: the fast path that preparing a volume for
rendering takes.

The numbers are those of :mod:`mi_amr.core.gradient` bit for bit (its whole-level NumPy pass
and its grid-by-grid slow twin; ``tests/test_device_derive.py``): central differences of
float64 values, a neighbour beyond a grid's face (a ghost cell) read from the grid of the same
level that holds it, else trilinearly interpolated from the coarser level (recursively, the
same "complete" interpolation as :func:`levels.interpolate`), else a one-sided difference. The
same-level lookup is :class:`levels.LevelIndex`'s dense block table, gathered from.

Per chunk of a level, three steps: one kernel computes the fields of the cells inside their
grid (no ghost needed: most cells), another those of the cells on a face, with the ghosts the
level itself holds, marking the cells that lack one; for those alone, the missing ghosts are
interpolated from the coarser levels (a few kernels, one a level of recursion); one more kernel
computes those cells again with them. Every per-level number is an opaque kernel input,
so each kernel compiles once per dtype, whatever the level or dataset.

Index coordinates are those of :meth:`AMRVolume.index_boxes`; derivatives are per world unit.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_amr.core import derive as host_derive
from mi_amr.core import levels
from mi_amr.core.buffers import ALIGN, joined
from mi_amr.kernels.arrays import device_table, grid_record, grid_records
from mi_amr.kernels.intmath import quotient

# Cells a chunk of grids holds at least (the last of a level may hold fewer): bounds the
# kernels' outputs and temporaries (~30 bytes a cell), which the next chunk reuses. Smaller
# chunks touch less new memory, the slow part on this project's machines (2^20 was faster than
# 2^22 and needs less memory at its peak; the bench outputs keep the measurements).
CHUNK_CELLS = 1 << 20
LEVEL_CELLS_MAX = 1 << 31   # cells a level may hold: flat positions are 32-bit on the device
PROBES = 64                 # positions of a field's host buffer checked after the kernels wrote it
# NaN bit patterns (by item size) that no arithmetic produces (its NaNs are the quiet default).
_PAYLOAD = {4: np.uint32(0x7FA5A5A5), 8: np.uint64(0x7FF5A5A5A5A5A5A5)}


def derive(volume, *names: str, m, velocity=None, chunk_cells: int = CHUNK_CELLS,
           consume: bool = False):
    """:func:`mi_amr.core.derive.derive` (``consume`` as there) with Q and vorticity computed
    on backend ``m`` (a Dr.Jit module such as ``drjit.llvm.ad``), whole grids of a level
    holding at least ``chunk_cells`` cells at a time. A level too sparse for a dense block
    table (:class:`levels.LevelIndex`) has no device lookup, and one of
    :data:`LEVEL_CELLS_MAX` cells or more would overflow its positions: such a volume is
    derived on the host."""
    tables = [levels.level_index(volume, level) for level in range(volume.num_levels)]
    dense = all(t.table is not None and int(np.prod(t.hi - t.lo, axis=1).sum()) <
                LEVEL_CELLS_MAX for t in tables)
    fill = (lambda vol, comps, wanted, flat, todo:
            _fill(vol, comps, wanted, flat, (m, chunk_cells, todo))) if dense else None
    return host_derive.derive(
        volume, *names, velocity=velocity, gradient_fields=fill, consume=consume,
        speed_field=lambda vol, comps, parts, todo: _speed(vol, comps, parts, (m, todo)))


def _speed(volume, comps, parts, how) -> bool:
    """Write ``sqrt(vx^2 + vy^2 + vz^2)`` of each level of ``todo`` into ``parts[level]`` (one
    kernel a level, scattering into the host buffer: :func:`_written`), in the velocity's own
    dtype as :func:`mi_amr.core.derive._speed` rounds it; True where done. Where the
    components or the levels differ in dtype (the host's promotions then), nothing is done:
    False. ``how``: ``(m, todo)``, the backend and a list of levels."""
    m, todo = how
    values = {level: [levels.level_values(volume, level, n) for n in comps] for level in todo}
    if len({a.dtype for v in values.values() for a in v} | {parts[0].dtype}) != 1:
        return False
    target, record = _written(m, parts, todo)
    starts = _level_starts(parts)
    for level, v in values.items():
        if len(v[0]):
            x, y, z = (_mapped(m, a) for a in v)
            lane = dr.opaque(m.UInt32, int(starts[level])) + dr.arange(m.UInt32, len(v[0]))
            dr.scatter(target, dr.sqrt(x * x + y * y + z * z), lane)
            dr.eval(target)
    _settle(m, target, record)
    return True


def _fill(volume, comps, wanted, flat, how):
    """Write fields ``wanted`` (Q, vorticity: those needing the gradient) of the levels
    ``todo`` into ``flat[name][level]`` (NumPy arrays of the level's values), chunk by chunk
    (at least ``chunk_cells`` cells, :func:`levels.grid_chunks`): the kernels scatter straight
    into the host buffer, which Dr.Jit maps (:func:`_written`). ``how``: ``(m, chunk_cells,
    todo)``. Only the levels up to the finest of ``todo`` are looked up (ghosts come from
    coarser levels), so finer ones may already be gone (:func:`derive`'s ``consume``)."""
    m, chunk_cells, todo = how
    with levels.fields_fixed(volume):
        tables = [_Level(volume, level, comps, m) for level in range(max(todo) + 1)]
        targets = {name: _written(m, flat[name], todo) for name in wanted}
        out = {name: t[0] for name, t in targets.items()}
        starts = _level_starts(flat[wanted[0]])
        for level in todo:
            lv = tables[level]
            dtypes = {name: flat[name][level].dtype for name in wanted}
            for start, stop in levels.grid_chunks(lv.host, chunk_cells):
                _chunk_fields(tables, level, (start, stop), dtypes, out,
                              int(starts[level]) + int(lv.host.offsets[start]))
        for target, record in targets.values():
            _settle(m, target, record)


def _written(m, parts, todo):
    """``(target, record)``: a Dr.Jit array the kernels scatter the levels ``todo`` of a field
    into, and what :func:`_settle` needs. ``parts`` are the field's per-level arrays,
    consecutive slices of one host buffer (:func:`mi_amr.core.derive._level_buffers`): the
    target maps that buffer, so what is scattered lands there. A few probe positions of the
    levels ``todo`` are first set to a NaN payload that no arithmetic gives, to tell
    afterwards that it did. Without one buffer, the target is a new array, whose levels
    ``todo`` are copied over at the end."""
    dtype = parts[0].dtype
    T = _float_type(m, dtype)
    host = joined(parts, dtype)
    if host is None or host.size < 2:
        return dr.empty(T, max(sum(len(a) for a in parts), 2)), (parts, todo, None, None)
    starts = _level_starts(parts)
    probe = np.unique(np.concatenate([np.zeros(0, np.int64)] + [
        np.linspace(starts[level], starts[level + 1] - 1, min(PROBES, len(parts[level])))
        .astype(np.int64) for level in todo]))
    _bits(host)[probe] = _PAYLOAD[dtype.itemsize]
    return _map(T, host), (parts, todo, host, probe)


def _level_starts(parts) -> np.ndarray:
    """Where each level's values begin in a field's buffer (``parts``: its per-level arrays,
    end to end), and the end."""
    return np.concatenate([[0], np.cumsum([len(a) for a in parts])]).astype(np.int64)


def _float_type(m, dtype):
    """The Dr.Jit float type of backend ``m`` for float64 (``Float64``) or else float32."""
    return m.Float64 if np.dtype(dtype) == np.float64 else m.Float32


def _bits(a):
    """Float array ``a`` viewed as unsigned integers of its size (its bit patterns)."""
    return a.view(np.uint64 if a.dtype == np.float64 else np.uint32)


def _map(T, host):
    """``host`` as a Dr.Jit array of type ``T`` over the same memory (Dr.Jit's LLVM backend
    maps NumPy's aligned buffer; another backend may copy it, which :func:`_settle` finds)."""
    return T(host)


def _settle(m, target, record) -> None:
    """Make sure the host holds what the kernels scattered into ``target``: where the target
    did not map the host buffer (no single buffer, or Dr.Jit copied it: a probe still holds
    its payload), the values of the levels written are copied over."""
    parts, todo, host, probe = record
    dr.eval(target)
    dr.sync_thread()
    if host is not None and np.all(_bits(host)[probe] != _PAYLOAD[host.dtype.itemsize]):
        return
    values = target.numpy()
    starts = _level_starts(parts)
    for level in todo:
        parts[level][:] = values[starts[level]:starts[level + 1]]


def _mapped(m, values):
    """A level's flat values as a Dr.Jit array of their own precision, mapped without a copy
    where NumPy's buffer is aligned (:mod:`mi_amr.core.buffers`)."""
    T = _float_type(m, values.dtype)
    a = np.ascontiguousarray(values, dtype=np.float64 if T is m.Float64 else np.float32)
    if a.ctypes.data % ALIGN or a.size < 2:
        return device_table(T, a, a.dtype)
    return T(a)


class _Level:
    """One level's lookup on the device: the values of the velocity components (flat, grid
    after grid as :func:`levels.level_values`), its dense block table and per grid (position in
    :class:`levels.LevelIndex`) its lower index corner, size, cell count, first value and cell
    size; the per-level numbers are opaque one-element arrays."""

    def __init__(self, volume, level, comps, m):
        t = levels.level_index(volume, level)
        self.m, self.host = m, t
        self.values = [_mapped(m, levels.level_values(volume, level, n)) for n in comps]
        self.table = device_table(m.Int32, t.table, np.int32)
        dims = t.hi - t.lo
        self.counts = np.prod(dims, axis=1)         # cells of each grid
        # Per grid a record of its box and first value, and one of 4 float64 (cell size, 0):
        # a kernel reads each with packet loads, not a gather a number.
        self.records = grid_records(m, t, t.offsets)
        h = np.zeros((len(t.grids), 4))
        h[:, :3] = volume.spacings()[t.grids]
        self.h = device_table(m.Float64, h, np.float64)
        self.shift = dr.opaque(m.Int32, int(t.block).bit_length() - 1)
        self.origin = [dr.opaque(m.Int32, int(x)) for x in t.origin]
        self.blocks = [dr.opaque(m.Int32, int(x)) for x in t.dims]
        self.anchor = [dr.opaque(m.Float64, float(x)) for x in volume.anchor]
        self.spacing = [dr.opaque(m.Float64, float(x)) for x in volume.level_spacing(level)]

    def find(self, idx, active):
        """``(p, found)``: the table position of the grid holding level cells ``idx`` (three
        Int32 arrays), where ``found``."""
        m = self.m
        rel = [(idx[a] >> self.shift) - self.origin[a] for a in range(3)]
        inside = m.Bool(active)
        for a in range(3):
            inside &= (rel[a] >= 0) & (rel[a] < self.blocks[a])
        key = m.UInt32((rel[0] * self.blocks[1] + rel[1]) * self.blocks[2] + rel[2])
        p = dr.gather(m.Int32, self.table, key, inside)
        found = inside & (p >= 0)
        return m.UInt32(p), found

    def grid(self, p, active=True):
        """``(lo, n, start)`` of the grids at table positions ``p`` (UInt32): lower index
        corner and size (three Int32 each) and first value in the level's (UInt32)."""
        return grid_record(self.m, self.records, p, active)

    def cell_size(self, p):
        """The cell sizes (three Float64, world units) of the grids at table positions ``p``."""
        h = dr.gather(self.m.Array4f64, self.h, p)
        return [h[0], h[1], h[2]]

    def cell_values(self, idx, active):
        """``(values, found)``: the three components (Float64, NaN where not found) at level
        cells ``idx`` -- :func:`levels.cell_values`."""
        m = self.m
        p, found = self.find(idx, active)
        lo, n, start = self.grid(p, found)
        local = [m.UInt32(idx[a] - lo[a]) for a in range(3)]
        at = start + (local[0] * m.UInt32(n[1]) + local[1]) * m.UInt32(n[2]) + local[2]
        return [dr.select(found, m.Float64(dr.gather(type(v), v, at, found)), dr.nan)
                for v in self.values], found

    def own(self, c, comp, active=True):
        """Component ``comp`` of the level's flat value ``c`` as Float64."""
        v = self.values[comp]
        return self.m.Float64(dr.gather(type(v), v, c, active))


def interpolate(tables, level, points):
    """Trilinear interpolation of level ``level`` at world ``points`` (three Float64 arrays):
    :func:`levels.interpolate` with ``complete=True``; the cells the level lacks interpolated
    from the coarser level (recursively). Three Float64 arrays, NaN where some cell with weight
    lacks data.

    Three passes, none holding a value per corner: which of each point's 8 cells the level
    lacks (a bit each), the coarser level's values for those alone (listed point after point,
    so a corner's place is the point's first plus the lacking corners before it), and one
    kernel blending the 8 corners in order, each read from the level or from that list."""
    lv, m = tables[level], tables[level].m
    n = dr.width(points[0])
    u = [(points[a] - lv.anchor[a]) / lv.spacing[a] - 0.5 for a in range(3)]
    base = [m.Int32(dr.floor(x)) for x in u]
    frac = [u[a] - m.Float64(base[a]) for a in range(3)]
    dr.eval(base, frac)
    lacks, first, coarse = m.UInt32(0), None, None
    if level > 0:
        for k in range(8):
            lacks |= dr.select(lv.find(_corner(m, base, k), True)[1], 0, 1 << k)
        dr.eval(lacks)
        first = dr.prefix_reduce(dr.ReduceOp.Add, dr.popcnt(lacks))     # exclusive
        j = dr.arange(m.UInt32, 8 * n)
        point, corner = j >> 3, j & 7
        pairs = dr.compress(((dr.gather(m.UInt32, lacks, point) >> corner) & 1) == 1)
        if dr.width(pairs):
            at = pairs >> 3
            cells = [dr.gather(m.Int32, base[a], at) + m.Int32((pairs >> (2 - a)) & 1)
                     for a in range(3)]
            centres = [lv.anchor[a] + (m.Float64(cells[a]) + 0.5) * lv.spacing[a]
                       for a in range(3)]
            coarse = interpolate(tables, level - 1, centres)
    return _blend(lv, base, frac, lacks, first, coarse)


def _corner(m, base, k):
    """Level index of corner ``k`` (bits x, y, z from the highest) of the cells ``base``."""
    return [base[a] + ((k >> (2 - a)) & 1) for a in range(3)]


def _blend(lv, base, frac, lacks, first, coarse):
    """The trilinear blend of each point's 8 corners, corner after corner: the level's value,
    or where ``lacks`` has the corner's bit, the coarser level's (``coarse[first + lacking
    corners before it]``); a corner with a non-finite component gets no weight. NaN where the
    weights left sum to less than 1 (up to rounding), as in :func:`levels.interpolate`."""
    m = lv.m
    num = [m.Float64(0.0) for _ in range(3)]
    den = m.Float64(0.0)
    for k in range(8):
        w = m.Float64(1.0)
        for a in range(3):
            w *= frac[a] if (k >> (2 - a)) & 1 else 1.0 - frac[a]
        v, _ = lv.cell_values(_corner(m, base, k), True)
        if coarse is not None:
            use = ((lacks >> k) & 1) == 1
            at = first + dr.popcnt(lacks & ((1 << k) - 1))
            v = [dr.select(use, dr.gather(m.Float64, c, at, use), x) for c, x in zip(coarse, v)]
        ok = dr.isfinite(v[0]) & dr.isfinite(v[1]) & dr.isfinite(v[2])
        w = dr.select(ok, w, 0.0)
        num = [s + dr.select(ok, w * x, 0.0) for s, x in zip(num, v)]
        den += w
    enough = den > 1.0 - 1e-9
    out = [dr.select(enough, s / den, dr.nan) for s in num]
    dr.eval(out)
    return out


class _Cells:
    """Where cells ``c`` (positions in the level's flat values, UInt32) lie: their grid ``p``
    (table position), index in it ``local``, its size ``n`` and lower corner ``lo`` (level
    index), the steps ``stride`` to the next cell along each axis and the grid's cell size
    ``h`` (world units)."""

    def __init__(self, lv, c, p, interior=False):
        m = self.m = lv.m
        self.c, self.p, self.interior = c, p, interior
        lo, n, start = lv.grid(p)
        self.n = [m.UInt32(x) for x in n]
        off = c - start
        plane = self.n[1] * self.n[2]
        # Divisors kept from 0: a vector's lanes past the array's end read 0 from their
        # (masked) gathers, and an integer division by 0 traps even there.
        i = quotient(m, off, dr.maximum(plane, 1))
        rest = off - i * plane
        j = quotient(m, rest, dr.maximum(self.n[2], 1))
        self.local = [i, j, rest - j * self.n[2]]
        self.stride = [plane, self.n[2], m.UInt32(1)]
        self.h = lv.cell_size(p)
        self.lo = lo

    def face(self, axis, side):
        """Cells on the grid's lower (side 0) or upper (side 1) face along ``axis`` (none, as a
        literal that the kernel folds away, for cells known to be ``interior``)."""
        if self.interior:
            return self.m.Bool(False)
        return self.local[axis] == 0 if side == 0 else self.local[axis] == self.n[axis] - 1

    def inside(self):
        """Cells on no face of their grid: all six neighbours in the grid."""
        out = self.m.Bool(True)
        for a in range(3):
            out &= (self.local[a] >= 1) & (self.local[a] + 1 < self.n[a])
        return out

    def ghost(self, axis, side):
        """Level index of the ghost cell beyond that face (three Int32 arrays)."""
        step = -1 if side == 0 else 1
        return [self.lo[a] + self.m.Int32(self.local[a]) + (step if a == axis else 0)
                for a in range(3)]


def _fields(lv, cells, ghost_of, wanted, one_sided=True):
    """Fields ``wanted`` (Float64 arrays, by name) at ``cells`` from the velocity gradient;
    ``ghost_of(axis, side)`` gives the three components beyond each face (NaN where none;
    None for ``interior`` cells, which have no face). Without ``one_sided`` every difference
    is central: right only where every ghost read is finite (the caller computes the others
    again)."""
    grad = [[None] * 3 for _ in range(3)]
    own = [lv.own(cells.c, comp) for comp in range(3)]
    none = [lv.m.Float64(dr.nan)] * 3       # for cells on no face (ghost_of None)
    for axis in range(3):
        faces = cells.face(axis, 0), cells.face(axis, 1)
        ghosts = (ghost_of(axis, 0), ghost_of(axis, 1)) if ghost_of else (none, none)
        s = cells.stride[axis]
        for comp in range(3):
            below = dr.select(faces[0], ghosts[0][comp],
                              lv.own(cells.c - s, comp, ~faces[0]))
            above = dr.select(faces[1], ghosts[1][comp],
                              lv.own(cells.c + s, comp, ~faces[1]))
            grad[comp][axis] = _difference(lv, cells, (axis, comp, own[comp]), below, above,
                                           faces) if one_sided else \
                (above - below) / (2.0 * cells.h[axis])
    out = {}
    if "q_criterion" in wanted:
        q = -0.5 * (grad[0][0] * grad[0][0] + grad[1][1] * grad[1][1] +
                    grad[2][2] * grad[2][2])
        out["q_criterion"] = q - (grad[0][1] * grad[1][0] + grad[0][2] * grad[2][0] +
                                  grad[1][2] * grad[2][1])
    if "vorticity_magnitude" in wanted:
        w = (grad[2][1] - grad[1][2], grad[0][2] - grad[2][0], grad[1][0] - grad[0][1])
        out["vorticity_magnitude"] = dr.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    return out


def _difference(lv, cells, line, below, above, faces):
    """d v / d x of component ``comp`` along ``axis`` (``line``: ``(axis, comp, f0)``, ``f0``
    the cells' own values): central, one-sided on a face whose ghost is missing (the upper
    face's where both are, as :func:`gradient._axis_difference`, which does the lower face
    first, then the upper). One one-sided difference a lane, stepping in from its face: the
    two faces' would each cost their gathers and divisions on every lane of the vector."""
    axis = line[0]
    d = (above - below) / (2.0 * cells.h[axis])
    use_lo = faces[0] & ~dr.isfinite(below)
    use_hi = faces[1] & ~dr.isfinite(above)
    use = use_lo | use_hi
    # (In a symbolic branch: few vectors hold a cell on the domain's boundary.)
    return dr.if_stmt((), use, lambda: dr.select(use, _one_sided(
        lv, cells, line, use_hi, dr.select(use_hi, below, above), use), d), lambda: d)


def _one_sided(lv, cells, line, upper, other, use):
    """:func:`gradient._one_sided` at the lanes ``use`` (``line``: as :func:`_difference`),
    stepping in from the upper face where ``upper``, else from the lower: second order from
    3 cells thick, first order at 2, at 1 the difference to the ``other`` ghost (0 where that
    is missing). The sign is +-1, so its products are exact, as with the host's integer."""
    m = lv.m
    axis, comp, f0 = line
    thick, s, h, c = cells.n[axis], cells.stride[axis], cells.h[axis], cells.c
    sign = dr.select(upper, m.Float64(-1.0), m.Float64(1.0))
    one = dr.select(upper, c - s, c + s)
    two = dr.select(upper, c - 2 * s, c + 2 * s)
    f1 = lv.own(dr.select(thick >= 2, one, c), comp, use)
    f2 = lv.own(dr.select(thick >= 3, two, c), comp, use)
    second = sign * (-3.0 * f0 + 4.0 * f1 - f2) / (2.0 * h)
    first = sign * (f1 - f0) / h
    lone = dr.select(dr.isfinite(other), sign * (other - f0) / h, 0.0)
    return dr.select(thick >= 3, second, dr.select(thick == 2, first, lone))


def _chunk_fields(tables, level, grids, wanted, out, base):
    """Fields ``wanted`` (by name: the dtype of each) of the cells of grids ``start:stop``
    (``grids``) of ``level``, in the order of :func:`levels.level_values`, scattered into
    ``out[name]`` from position ``base`` on. The cells inside their grid are computed by a
    kernel without ghost lookups, those on a face by one with the ghosts their level holds
    and central differences, and the face cells where a ghost read is missing or not finite
    once more, with coarser ghosts and one-sided differences; all are :func:`_fields`, the
    same arithmetic."""
    lv, m = tables[level], tables[level].m
    start, stop = grids
    counts = lv.counts[start:stop]
    first, n = int(lv.host.offsets[start]), int(counts.sum())
    p = _grid_of_cells(m, np.concatenate([[0], np.cumsum(counts)]), start)
    dr.eval(p)
    inside = _Cells(lv, dr.opaque(m.UInt32, first) + dr.arange(m.UInt32, n), p).inside()
    dr.eval(inside)
    at = dr.opaque(m.UInt32, base)
    inner, outer = dr.compress(inside), dr.compress(~inside)
    if dr.width(inner):
        cells = _Cells(lv, dr.opaque(m.UInt32, first) + inner, dr.gather(m.UInt32, p, inner),
                       interior=True)
        for k, v in _fields(lv, cells, None, wanted).items():
            dr.scatter(out[k], _as(m, v, wanted[k]), at + inner)
    need, lacking = m.Bool(False), m.UInt32(0)
    if dr.width(outer):
        need, lacking = _face_cells(tables, level, (first, outer, dr.gather(m.UInt32, p, outer)),
                                    wanted, out, at)
    dr.eval(out, need, lacking)
    redo = again_at = None
    if dr.width(outer):
        again_at = dr.compress(need)
        redo = dr.gather(m.UInt32, outer, again_at)
    if redo is not None and dr.width(redo):
        c, q = dr.opaque(m.UInt32, first) + redo, dr.gather(m.UInt32, p, redo)
        if level > 0:
            again = _with_coarse_ghosts(tables, level, (c, q, dr.gather(m.UInt32, lacking,
                                                                          again_at)), wanted)
        else:                            # (no coarser level: one-sided where none is held)
            cells = _Cells(lv, c, q)
            again = _fields(lv, cells, _same_level_ghosts(lv, cells), wanted)
        for k, v in again.items():
            dr.scatter(out[k], _as(m, v, wanted[k]), at + redo)
        dr.eval(out)


def _face_cells(tables, level, chunk, wanted, out, base):
    """Write :func:`_fields` of the chunk's face cells (``chunk``: ``(first, at, p)``, their
    positions ``at`` from the chunk's ``first`` cell, their grids ``p``) into ``out`` (from
    ``base`` on), with central differences and the ghosts their own level holds. Returns
    ``(need, lacking)``: the cells where one of those ghosts is missing or not finite (most
    of them on a coarse-fine or the domain's boundary, or beside missing data), to be
    computed again with coarser ghosts and one-sided differences, and per cell the faces
    (bit ``2 axis + side``) beyond which the level holds no cell, whose ghosts the coarser
    levels give (:func:`_coarse_ghosts`)."""
    lv, m = tables[level], tables[level].m
    first, at, p = chunk
    cells = _Cells(lv, dr.opaque(m.UInt32, first) + at, p)
    lack, lacking = [m.Bool(False)], [m.UInt32(0)]

    def checked(axis, side):
        face = cells.face(axis, side)
        values, found = _on_face(m, face, lambda: lv.cell_values(cells.ghost(axis, side),
                                                                  face))
        lack[0] |= face & ~(dr.isfinite(values[0]) & dr.isfinite(values[1]) &
                            dr.isfinite(values[2]))
        lacking[0] |= dr.select(face & ~found, m.UInt32(1 << (2 * axis + side)), 0)
        return values

    for k, v in _fields(lv, cells, checked, wanted, one_sided=False).items():
        dr.scatter(out[k], _as(m, v, wanted[k]), base + at)
    return lack[0], lacking[0]


def _same_level_ghosts(lv, cells):
    """``ghost_of(axis, side)`` for :func:`_fields`: the three components of the cells beyond
    each face of ``cells`` that the level itself holds (NaN where it holds none), looked up
    in a symbolic branch (:func:`_on_face`)."""
    def ghost_of(axis, side):
        face = cells.face(axis, side)
        return _on_face(lv.m, face, lambda: lv.cell_values(cells.ghost(axis, side), face))[0]

    return ghost_of


def _on_face(m, face, look):
    """``look()`` (three Float64 arrays, and a Bool) where ``face``, ``(NaN, False)``
    elsewhere, in a symbolic branch: a vector with no lane on that face skips the lookup's
    arithmetic and loads (a chunk's face cells lie on one or two faces of their grid a
    vector at a time)."""
    return dr.if_stmt((), face, look,
                      lambda: ([m.Float64(dr.nan) for _ in range(3)], m.Bool(False)))


def _grid_of_cells(m, offsets, start):
    """Per cell of consecutive grids ``start, start + 1, ...`` (their cells from 0 on,
    ``offsets``: each grid's first cell and the end), the grid's table position (UInt32):
    ``start`` plus the number of grids that begin at or before the cell, a 1 scattered at
    each grid's first cell and summed -- on the device, not a host table of every cell."""
    n = int(offsets[-1])
    marks = dr.zeros(m.UInt32, n)
    begins = np.asarray(offsets[1:-1], dtype=np.int64)
    if len(begins):
        at = device_table(m.UInt32, begins, np.uint32)
        dr.scatter(marks, m.UInt32(1), at, dr.arange(m.UInt32, dr.width(at)) < len(begins))
    return dr.opaque(m.UInt32, int(start)) + dr.prefix_reduce(dr.ReduceOp.Add, marks,
                                                              exclusive=False)


def _as(m, values, dtype):
    """Float64 ``values`` rounded to ``dtype`` (float32 or float64) as the host's buffer holds
    it."""
    return m.Float32(values) if np.dtype(dtype) == np.float32 else values


def _with_coarse_ghosts(tables, level, cells, wanted):
    """:func:`_fields` of the cells ``c`` (grids ``p``; ``cells``: ``(c, p, lacking)``) with
    every ghost: the level's own, else (the faces of ``lacking``, bits as
    :func:`_face_cells` gives them) interpolated from the coarser levels (NaN where that too
    lacks cells)."""
    lv, m = tables[level], tables[level].m
    c, p, lacking = cells
    first, coarse = _coarse_ghosts(tables, level, cells)
    cells = _Cells(lv, c, p)

    def either(axis, side):
        face = cells.face(axis, side)
        bit = 1 << (2 * axis + side)

        def look():
            values, found = lv.cell_values(cells.ghost(axis, side), face)
            use = ((lacking & bit) != 0) & face
            at = first + dr.popcnt(lacking & (bit - 1))
            return [dr.select(use, dr.gather(m.Float64, g, at, use), v)
                    for v, g in zip(values, coarse)], found

        return _on_face(m, face, look)[0]

    return _fields(lv, cells, either, wanted)


def _coarse_ghosts(tables, level, cells):
    """``(first, values)`` for the ``k`` cells ``(c, p, lacking)``: the ghosts the level lacks
    beyond their faces (the bits of ``lacking``, face ``2 axis + side``), interpolated from
    level ``level - 1`` (three Float64 arrays, NaN where that fails too), listed cell after
    cell, face after face: cell ``i``'s ghost beyond face ``f`` is ``values[first[i] +
    popcnt(lacking[i] & (2^f - 1))]``."""
    lv, m = tables[level], tables[level].m
    c, p, lacking = cells
    first = dr.prefix_reduce(dr.ReduceOp.Add, dr.popcnt(lacking))      # exclusive
    j = dr.arange(m.UInt32, 8 * dr.width(c))
    asked = dr.compress(((dr.gather(m.UInt32, lacking, j >> 3) >> (j & 7)) & 1) == 1)
    index = _beyond_face(lv, (c, p), (asked >> 3, asked & 7))
    centres = [lv.anchor[a] + (m.Float64(index[a]) + 0.5) * lv.spacing[a] for a in range(3)]
    values = interpolate(tables, level - 1, centres) if dr.width(asked) else \
        [dr.full(m.Float64, dr.nan, 2) for _ in range(3)]
    dr.eval(first, values)
    return first, values


def _beyond_face(lv, cells, lanes):
    """The level index of the cell beyond face ``face`` (``2 axis + side``) of cell ``lane``
    of ``cells`` (``(c, p)``: the cells' flat positions and grids; ``lanes``: ``(lane,
    face)``, UInt32 each), three Int32 arrays."""
    m = lv.m
    c, p = cells
    lane, face_id = lanes
    cells = _Cells(lv, dr.gather(m.UInt32, c, lane), dr.gather(m.UInt32, p, lane))
    axis, upper = face_id >> 1, (face_id & 1) == 1
    step = dr.select(upper, m.Int32(1), m.Int32(-1))
    return [cells.lo[a] + m.Int32(cells.local[a]) + dr.select(axis == a, step, 0)
            for a in range(3)]
