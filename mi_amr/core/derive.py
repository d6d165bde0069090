"""Derived fields computed from the velocity across levels: speed, Q-criterion, vorticity.

Derivatives are central differences on each grid. The neighbour a difference needs beyond the
grid's edge (a *ghost cell*, one cell of the grid's level) comes from the grid of the same level
that holds it; failing that, from trilinear interpolation of the coarser level at the ghost
cell's centre; failing that (outside the domain, or so near its edge that the interpolation
would lack cells) the difference is one-sided, second order.
This is what keeps Q continuous across level boundaries (the course report, section 4.1, saw it
jump when every grid used one-sided differences at its own edges).

Units: derivatives are per world unit; Q has the units of (velocity / length)^2.
"""

from __future__ import annotations

import numpy as np

from mi_amr.core import levels
from mi_amr.errors import AMRError

DERIVED_FIELDS = ("speed", "q_criterion", "vorticity_magnitude")
VELOCITY_NAMES = (("vx", "vy", "vz"), ("x_velocity", "y_velocity", "z_velocity"),
                  ("velocity_x", "velocity_y", "velocity_z"), ("x-velocity", "y-velocity",
                                                               "z-velocity"),
                  ("velx", "vely", "velz"), ("v_x", "v_y", "v_z"), ("u", "v", "w"))


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
    raise AMRError(f"{volume._label()}no velocity components found (looked for "
                   f"{', '.join('/'.join(n) for n in VELOCITY_NAMES)}); available fields: "
                   f"{list(volume.field_names)}")


def derive(volume, *names: str, velocity=None):
    """A volume with the derived fields ``names`` added (any of :data:`DERIVED_FIELDS`).

    ``velocity`` names the three velocity components; by default they are found by name
    (``vx, vy, vz``, ``x_velocity, ...``). The stored fields are shared, not copied.
    """
    unknown = [n for n in names if n not in DERIVED_FIELDS]
    if unknown:
        raise AMRError(f"cannot derive {unknown}; derived fields are {list(DERIVED_FIELDS)}")
    comps = velocity_fields(volume, velocity)
    out = {}
    if "speed" in names:
        out["speed"] = [_speed(g, comps) for g in volume.grids]
    wanted = [(n, f) for n, f in (("q_criterion", q_criterion),
                                  ("vorticity_magnitude", vorticity_magnitude)) if n in names]
    for name, _ in wanted:
        out[name] = []
    # One grid's float64 gradient at a time (9 values a cell), not the whole volume's.
    if wanted:
        for G, g in zip(_gradients(volume, comps), volume.grids):
            for name, of in wanted:
                out[name].append(_cast(of(G), g, comps))
    return volume.with_fields(out)


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


def velocity_gradient(volume, comps) -> list:
    """Per grid, ``(3, 3, nx, ny, nz)`` float64 with ``[i][j] = d v_i / d x_j`` (world units)."""
    return list(_gradients(volume, comps))


def _gradients(volume, comps):
    """:func:`velocity_gradient` one grid at a time (a generator)."""
    ghosts = _ghost_layers(volume, comps)
    for gi, g in enumerate(volume.grids):
        grad = np.empty((3, 3) + g.shape)
        for c, name in enumerate(comps):
            v = g.fields[name].astype(np.float64)
            for axis in range(3):
                lo_ghost, hi_ghost = ghosts[gi][axis]
                grad[c, axis] = _difference(v, lo_ghost[c], hi_ghost[c], axis, g.spacing[axis])
        yield grad


def _speed(g, comps):
    vx, vy, vz = (g.fields[n] for n in comps)
    return np.sqrt(vx * vx + vy * vy + vz * vz)


def _cast(arr, g, comps):
    dtype = np.result_type(*(g.fields[n].dtype for n in comps))
    return arr.astype(dtype, copy=False)


def _ghost_layers(volume, comps) -> list:
    """Per grid and axis, the ghost layers below and above: ``(3, ...)`` arrays shaped like a
    one-cell slab of the grid along that axis, NaN where no level has data."""
    lo, _ = volume.index_boxes()
    result = [[None] * 3 for _ in volume.grids]
    for level in range(volume.num_levels):
        ids = np.flatnonzero(volume.levels == level)
        cells, where = [], []
        for gi in ids:
            shape = volume.grids[gi].shape
            for axis in range(3):
                slab = list(shape)
                slab[axis] = 1
                grid_idx = np.stack(np.meshgrid(*[np.arange(n) for n in slab], indexing="ij"),
                                    axis=-1).reshape(-1, 3)
                for side, pos in ((0, -1), (1, shape[axis])):
                    idx = grid_idx.copy()
                    idx[:, axis] = pos
                    cells.append(idx + lo[gi])
                    where.append((gi, axis, side, tuple(slab), len(idx)))
        if not cells:
            continue
        cells = np.concatenate(cells)
        values, found = levels.cell_values(volume, level, cells, comps)
        if level > 0 and not found.all():
            missing = np.flatnonzero(~found)
            centres = volume.anchor + (cells[missing] + 0.5) * volume.level_spacing(level)
            values[:, missing] = levels.interpolate(volume, level - 1, centres, comps,
                                                    complete=True)
        at = 0
        for gi, axis, side, slab, n in where:
            layer = values[:, at:at + n].reshape((3,) + slab)
            at += n
            if result[gi][axis] is None:
                result[gi][axis] = [None, None]
            result[gi][axis][side] = layer
    return result


def _difference(v, lo_ghost, hi_ghost, axis, h):
    """d v / d x along ``axis``: central differences using the ghost layers, one-sided (second
    order where the grid has 3 cells or more) where a ghost value is missing (NaN)."""
    ext = np.concatenate([lo_ghost, v, hi_ghost], axis=axis)
    n = v.shape[axis]
    take = lambda a, i: np.take(a, i, axis=axis)  # noqa: E731
    d = (take(ext, np.arange(2, n + 2)) - take(ext, np.arange(0, n))) / (2.0 * h)
    # The side picks the ghost layers, not ``end``: with one cell, both ends are cell 0.
    for end, sign, ghost, other in ((0, 1, lo_ghost, hi_ghost), (n - 1, -1, hi_ghost, lo_ghost)):
        missing = ~np.isfinite(np.take(ghost, 0, axis=axis))
        if not missing.any():
            continue
        if n >= 3:
            f0, f1, f2 = (take(v, end + sign * k) for k in range(3))
            one_sided = sign * (-3.0 * f0 + 4.0 * f1 - f2) / (2.0 * h)
        elif n == 2:
            one_sided = sign * (take(v, end + sign) - take(v, end)) / h
        else:
            g = np.take(other, 0, axis=axis)
            one_sided = np.where(np.isfinite(g), sign * (g - take(v, 0)) / h, 0.0)
        idx = [slice(None)] * 3
        idx[axis] = end
        d[tuple(idx)] = np.where(missing, one_sided, d[tuple(idx)])
    return d
