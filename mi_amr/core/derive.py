"""Derived fields computed from the velocity across levels: speed, Q-criterion, vorticity.

The velocity gradient comes from :mod:`mi_amr.core.gradient` (central differences with ghost
cells across levels, whole levels at a time); the fields are computed on each level's cells at
once and handed back as one array per grid (views of the level's array).

Units: derivatives are per world unit; Q has the units of (velocity / length)^2.
"""

from __future__ import annotations

import numpy as np

from mi_amr.core import extremes, gradient, levels
from mi_amr.core.buffers import aligned_parts
from mi_amr.errors import AMRError

DERIVED_FIELDS = ("speed", "q_criterion", "vorticity_magnitude")
VELOCITY_NAMES = (("vx", "vy", "vz"), ("x_velocity", "y_velocity", "z_velocity"),
                  ("velocity_x", "velocity_y", "velocity_z"), ("x-velocity", "y-velocity",
                                                               "z-velocity"),
                  ("velx", "vely", "velz"), ("v_x", "v_y", "v_z"), ("u", "v", "w"))
SPEED_CHUNK = 1 << 16     # values of a level whose speed is computed at a time


def velocity_fields(volume, velocity=None) -> tuple:
    """The three velocity component names of ``volume``: ``velocity`` if given, else the first
    of :data:`VELOCITY_NAMES` that the volume holds."""
    if velocity is not None:
        velocity = tuple(velocity)
        missing = [n for n in velocity if n not in volume.field_names]
        if len(velocity) != 3 or missing:
            raise AMRError(f"velocity must name 3 fields of the volume, got {velocity}; "
                           f"available: {list(volume.field_names)}")
        return velocity
    for names in VELOCITY_NAMES:
        if all(n in volume.field_names for n in names):
            return names
    raise AMRError(f"{volume.source_prefix()}no velocity components found (looked for "
                   f"{', '.join('/'.join(n) for n in VELOCITY_NAMES)}); available fields: "
                   f"{list(volume.field_names)}")


def derive(volume, *names: str, velocity=None, gradient_fields=None, speed_field=None,
           chunk_cells: int = levels.CHUNK_CELLS, consume: bool = False):
    """A volume with the derived fields ``names`` added (any of :data:`DERIVED_FIELDS`).

    ``velocity`` names the three velocity components; by default they are found by name
    (``vx, vy, vz``, ``x_velocity, ...``). The stored fields are shared, not copied. Each
    derived field has the dtype of its grid's velocity components.

    ``gradient_fields``, when given, computes the fields that need the velocity gradient
    instead of :func:`gradient.map_chunks`: called as ``gradient_fields(volume, comps, names,
    flat, todo)``, it writes field ``name`` of each level ``l`` of ``todo`` (a list of levels)
    into ``flat[name][l]`` (the device path, :mod:`mi_amr.kernels.derive`, gives the same
    numbers). ``speed_field(volume, comps, parts, todo)``, when given, writes the speed of
    each level ``l`` of ``todo`` into ``parts[l]`` the same way and returns True, or returns
    False (the host computes it then).

    ``consume``: the caller gives ``volume`` up. The levels are derived finest first, and
    once a level is done its velocity arrays are dropped from ``volume``
    (:meth:`AMRVolume.drop_level_fields`): a finer level's ghosts come from coarser levels
    only, so no later level reads them, and where nothing else holds them (a file read with a
    buffer per level) their memory is freed during the derivation, not after it. The result
    then holds no velocity, and ``volume`` must not be used again.

    ``chunk_cells`` bounds the host gradient's passes (:func:`gradient.map_chunks`): whole
    grids of a level holding at least that many cells each, which bounds its temporaries;
    the numbers do not depend on it.
    """
    unknown = [n for n in names if n not in DERIVED_FIELDS]
    if unknown:
        raise AMRError(f"cannot derive {unknown}; derived fields are {list(DERIVED_FIELDS)}")
    comps = velocity_fields(volume, velocity)
    flat = _level_buffers(volume, names, comps)
    dtypes = _grid_dtypes(volume, comps)
    every = list(range(volume.num_levels))
    for todo in ([[level] for level in reversed(every)] if consume else [every]):
        _derive_levels(volume, comps, flat, todo, (gradient_fields, speed_field, chunk_cells))
        if consume:
            volume.drop_level_fields(todo[0], comps)
    made = {n: _per_grid(volume, arrays, dtypes) for n, arrays in flat.items()}
    out = volume.with_fields(made)
    for name, arrays in flat.items():
        for level, values in enumerate(arrays):
            ids = np.flatnonzero(out.levels == level)
            levels.adopt_level_values(out, level, name, values, [made[name][g] for g in ids])
    return out


def _derive_levels(volume, comps, flat, todo, how) -> None:
    """Write the fields ``flat`` holds buffers for, of the levels ``todo``, into them; ``how``
    is :func:`derive`'s ``(gradient_fields, speed_field, chunk_cells)``."""
    gradient_fields, speed_field, chunk_cells = how
    if "speed" in flat and not (speed_field and speed_field(volume, comps, flat["speed"], todo)):
        for level in todo:
            _speed([levels.level_values(volume, level, n) for n in comps], flat["speed"][level])
    wanted = [(n, f) for n, f in (("q_criterion", q_criterion),
                                  ("vorticity_magnitude", vorticity_magnitude)) if n in flat]
    if wanted and gradient_fields is not None:
        gradient_fields(volume, comps, [n for n, _ in wanted], flat, todo)
    elif wanted:
        # A few chunks' float64 gradients at a time (9 values a cell), not the whole volume's;
        # each thread writes its chunk's cells of the level arrays.
        def write(level, at, grad):
            for name, of in wanted:
                flat[name][level][at:at + grad.shape[-1]] = of(grad)

        for _ in gradient.map_chunks(volume, comps, write, chunk_cells=chunk_cells, todo=todo):
            pass


def _speed(v, out) -> None:
    """``out = sqrt(vx^2 + vy^2 + vz^2)`` for the flat components ``v``, rounded once to
    ``out``'s dtype, :data:`SPEED_CHUNK` values at a time (the same numbers as the whole-array
    expression, without its temporaries of the level's size: on a large level those are
    fresh memory, the slow part)."""
    for a in range(0, len(out), SPEED_CHUNK):
        part = slice(a, a + SPEED_CHUNK)
        np.sqrt(_squared_speed(v, part), out=out[part], casting="same_kind")


def _squared_speed(v, part):
    """``vx^2 + vy^2 + vz^2`` of the flat components ``v`` at ``part``: each square in its
    component's own dtype, the sums in the widest, as NumPy's ``vx * vx + vy * vy + vz * vz``
    rounds them. A square beyond the dtype's range is +inf (not finite: no speed there), not a
    warning."""
    with np.errstate(over="ignore"):
        total = np.square(v[0][part]).astype(np.result_type(*v), copy=False)
        total += np.square(v[1][part])
        total += np.square(v[2][part])
    return total


def speed_range(volume, velocity=None) -> tuple | None:
    """``(min, max)`` of the finite values of the speed :func:`derive` would give ``volume``
    (world units per time unit, as the velocity), taken from the velocity level by level,
    :data:`SPEED_CHUNK` values at a time, without writing the field: what
    ``derive(volume, "speed").value_range("speed")`` gives, ``(nan, nan)`` where no value is
    finite. None (use :func:`derive`) when the components differ in dtype from grid to grid or
    from one another: the field's roundings then depend on the grid."""
    comps = velocity_fields(volume, velocity)
    dtypes = {volume.grids[0].fields[n].dtype for n in comps}
    if len(dtypes) != 1 or any(g.fields[n].dtype not in dtypes
                               for g in volume.grids for n in comps):
        return None

    def chunks():
        for level in range(volume.num_levels):
            v = [levels.level_values(volume, level, n) for n in comps]
            for a in range(0, len(v[0]), SPEED_CHUNK):
                yield [x[a:a + SPEED_CHUNK] for x in v]

    return speed_range_of_chunks(chunks())


def speed_range_of_chunks(chunks) -> tuple:
    """:func:`speed_range` of a velocity that comes a chunk at a time: ``chunks`` yields lists
    of the three components' values (1-D arrays of one dtype, the same cells each), in any
    order and cut anywhere (a file read a stretch at a time)."""
    def squares():
        for v in chunks:
            # The squared speed as _speed sums it; its square root keeps the order of
            # values, and is finite exactly where the square is (an overflow is not).
            with np.errstate(over="ignore", invalid="ignore"):
                total = _squared_speed(v, slice(None))
            yield total

    lo, hi = extremes.finite_extremes(squares())
    if lo > hi:
        return (np.nan, np.nan)
    return tuple(float(np.sqrt(x)) for x in (lo, hi))


def q_criterion(grad: np.ndarray) -> np.ndarray:
    """Q = (|Omega|^2 - |S|^2) / 2 from ``grad[i][j] = d v_i / d x_j`` (arrays ``(3, 3, ...)``)."""
    q = -0.5 * (grad[0, 0] ** 2 + grad[1, 1] ** 2 + grad[2, 2] ** 2)
    q -= grad[0, 1] * grad[1, 0] + grad[0, 2] * grad[2, 0] + grad[1, 2] * grad[2, 1]
    return q


def vorticity_magnitude(grad: np.ndarray) -> np.ndarray:
    """|curl v| from ``grad[i][j] = d v_i / d x_j``."""
    wx = grad[2, 1] - grad[1, 2]
    wy = grad[0, 2] - grad[2, 0]
    wz = grad[1, 0] - grad[0, 1]
    return np.sqrt(wx * wx + wy * wy + wz * wz)


def velocity_gradient(volume, comps, chunk_cells: int = levels.CHUNK_CELLS) -> list:
    """Per grid, ``(3, 3, nx, ny, nz)`` float64 with ``[i][j] = d v_i / d x_j`` (world units),
    computed in chunks of at least ``chunk_cells`` cells (:func:`gradient.level_gradients`)."""
    grads = [None] * len(volume.grids)
    for grids, grad in gradient.level_gradients(volume, comps, chunk_cells):
        at = 0
        for gi in grids:
            shape = volume.grids[gi].shape
            n = int(np.prod(shape))
            grads[gi] = grad[:, :, at:at + n].reshape((3, 3) + shape)
            at += n
    return grads


def _level_buffers(volume, names, comps) -> dict:
    """Per name, one array per level to compute it into: consecutive slices of a single
    aligned buffer (:mod:`mi_amr.core.buffers`), level after level, so that when the grids are
    in level order the device maps the field's values without copying them. The dtype is that
    of the velocity components (float64 if any level's are)."""
    sizes = [len(levels.level_values(volume, level, comps[0]))
             for level in range(volume.num_levels)]
    dtype = np.result_type(*(_level_dtype(volume, level, comps)
                             for level in range(volume.num_levels)))
    return {name: aligned_parts(sizes, dtype) for name in names}


def _level_dtype(volume, level, comps):
    """The dtype a level's derived values are computed in: that of its velocity components."""
    return np.result_type(*(levels.level_values(volume, level, n).dtype for n in comps))


def _grid_dtypes(volume, comps) -> list:
    """Per grid, the dtype its derived values take: that of its velocity components (the
    widest of them), found once where every grid's components have one dtype."""
    kinds = [{g.fields[n].dtype for g in volume.grids} for n in comps]
    if all(len(k) == 1 for k in kinds):
        return [np.result_type(*(next(iter(k)) for k in kinds))] * len(volume.grids)
    return [np.result_type(*(g.fields[n].dtype for n in comps)) for g in volume.grids]


def _per_grid(volume, level_arrays, dtypes) -> list:
    """One array per grid (a view of its level's flat array, cast to ``dtypes[grid]``, the
    grid's velocity dtype, where a level mixes dtypes) from the per-level flat arrays."""
    out = [None] * len(volume.grids)
    shapes = volume.grid_columns()["shape"]
    for level, flat in enumerate(level_arrays):
        table = levels.level_index(volume, level)
        starts = levels.grid_offsets(volume, level)
        ends = starts + np.prod(shapes[table.grids], axis=1)
        for gi, start, end in zip(table.grids.tolist(), starts.tolist(), ends.tolist()):
            view = flat[start:end].reshape(volume.grids[gi].shape)
            out[gi] = view if dtypes[gi] == view.dtype else view.astype(dtypes[gi])
    return out
