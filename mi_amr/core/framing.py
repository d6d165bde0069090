"""A camera for a data file: a three-quarter view that frames a box in an image of a given
aspect, and a light from over the viewer's shoulder (NumPy only). The box is what the scene
shows where that is known (:func:`value_box`: the cells an isosurface or a band passes
through), else the data's bounds.

Spaces: the volume's world space (the data's own units) is mapped to *scene space* by
:attr:`Framing.to_world`, a scale and a translation that put the bounds' centre at the origin
with the longest side 2 long (so scenes of any data share one set of camera and light numbers).
The camera, its target, its up vector and the light are in scene space.

The camera's distance is solved in closed form: a box corner ``p`` at depth ``p.f + D`` (``f``
the viewing direction, ``D`` the distance) lands at ``x = (p.r) / (p.f + D) / tan(fov_x / 2)``
across the image ([-1, 1] edge to edge), so ``D = max_p |p.r| / (FILL tan(fov_x/2)) - p.f``
(and the same with ``y``) puts the box's farthest corner at :data:`FILL` of the half width or
:data:`FILL_Y` of the half height. The up axis is the data's z unless another axis lets the
box fill more of the width (a tall column in a wide image lies down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mi_amr.core.batches import axis_pairs, flat_field, shape_batches, stacked
from mi_amr.errors import AMRError

FOV_X_DEG = 35.0          # horizontal field of view (Mitsuba's fov_axis "x"), degrees
FILL = 0.8                # the box's farthest corner at this share of the half width ...
FILL_Y = 0.88             # ... and of the half height (an image much wider than the data is
                          # bound by its height: this keeps a cube above 30 % of a 2.5:1 width)
AZIMUTH_DEG = 35.0        # three-quarter view: turned this far from the first side axis ...
ELEVATION_DEG = 25.0      # ... and raised this far above the side axes' plane
WIDE_ENOUGH = 0.4         # take the first up axis whose box fills this share of the width
UP_ORDER = (2, 1, 0)      # up axes tried: z, then y, then x


@dataclass(frozen=True)
class Framing:
    """The camera and light for a box: ``origin``, ``target``, ``up`` (scene space),
    ``fov_x`` (degrees), ``light_direction`` (the direction the light travels, scene space),
    ``to_world`` (4x4, volume world -> scene space) and ``width_fill``/``height_fill`` (the
    share of the image's width and height the box's projection covers)."""

    origin: tuple
    target: tuple
    up: tuple
    fov_x: float
    light_direction: tuple
    to_world: np.ndarray
    width_fill: float
    height_fill: float


def frame_box(lo, hi, aspect: float) -> Framing:
    """The framing of the box ``lo``..``hi`` (volume world units) in an image ``aspect`` =
    width / height wide."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    extent = hi - lo
    if not (np.all(np.isfinite(extent)) and extent.max() > 0 and aspect > 0):
        raise AMRError(f"cannot frame bounds {lo.tolist()} .. {hi.tolist()} at aspect {aspect}")
    scale = 2.0 / extent.max()
    to_world = np.diag([scale, scale, scale, 1.0])
    to_world[:3, 3] = -scale * (lo + hi) / 2
    half = np.maximum(extent * scale / 2, 1e-6)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                       dtype=np.float64) * half
    best = None
    for axis in UP_ORDER:
        view = _view(axis, corners, aspect)
        if view[-2] >= WIDE_ENOUGH:
            best = view
            break
        if best is None or view[-2] > best[-2]:
            best = view
    origin, up, light, width_fill, height_fill = best
    return Framing(origin=tuple(origin.tolist()), target=(0.0, 0.0, 0.0),
                   up=tuple(up.tolist()), fov_x=FOV_X_DEG, light_direction=tuple(light.tolist()),
                   to_world=to_world, width_fill=width_fill, height_fill=height_fill)


def _view(axis: int, corners: np.ndarray, aspect: float):
    """``(origin, up, light direction, width fill, height fill)`` looking at the origin with
    the data axis ``axis`` up."""
    up = np.eye(3)[axis]
    a, b = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
    az, el = math.radians(AZIMUTH_DEG), math.radians(ELEVATION_DEG)
    back = math.cos(el) * (math.cos(az) * a - math.sin(az) * b) + math.sin(el) * up
    forward = -back                                  # from the camera to the target
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    tx = math.tan(math.radians(FOV_X_DEG) / 2)
    ty = tx / aspect
    pf, pr, pu = corners @ forward, corners @ right, corners @ cam_up
    distance = max(np.max(np.abs(pr) / (FILL * tx) - pf), np.max(np.abs(pu) / (FILL_Y * ty) - pf))
    depth = pf + distance
    x, y = pr / depth / tx, pu / depth / ty
    light = -(back + up - 0.5 * right)
    light /= np.linalg.norm(light)
    return (back * distance, up, light, float(x.max() - x.min()) / 2,
            float(y.max() - y.min()) / 2)


def value_box(volume, field: str, lo_value: float, hi_value: float):
    """``(lo, hi)``: the bounds (the volume's world space) of the leaf cells where ``field``
    meets the values ``lo_value``..``hi_value`` -- a cell whose value lies there, and both
    cells of a pair of neighbours (in one grid, along an axis) whose values reach it from
    either side (an isosurface at ``v``, ``v``..``v``, passes between them); None where no
    leaf cell with a finite value does. An isosurface at a value of the range lies inside it,
    to within the cells beside a grid's face (a pair across two grids is not looked at).
    The grids of one shape are taken together (:mod:`mi_amr.core.batches`);
    :func:`value_box_reference` is the slow twin (grid by grid)."""
    box_lo, box_hi = np.full(3, np.inf), np.full(3, -np.inf)
    flat, leaf = flat_field(volume, field), volume.leaf_mask_flat()
    columns = volume.grid_columns()
    for ids, shape in shape_batches(volume):
        f = stacked(flat, columns["offset"], ids, shape)
        keep = stacked(leaf, columns["offset"], ids, shape) & np.isfinite(f)
        hit = keep & (f >= lo_value) & (f <= hi_value)
        for axis in range(3):
            if shape[axis] < 2:
                continue
            a, b = axis_pairs(axis)
            meet = keep[a] & keep[b] & (np.minimum(f[a], f[b]) <= hi_value) & \
                (np.maximum(f[a], f[b]) >= lo_value)
            hit[a] |= meet
            hit[b] |= meet
        _widen(box_lo, box_hi, hit, columns["origin"][ids], columns["spacing"][ids])
    return (box_lo, box_hi) if np.all(box_hi > box_lo) else None


def _widen(box_lo, box_hi, hit, origin, spacing) -> None:
    """Grow the box ``box_lo``..``box_hi`` (world) in place to the cells ``hit`` of a batch
    of grids (``(k, nx, ny, nz)``; their origins and spacings ``(k, 3)``)."""
    if not hit.any():
        return
    if len(hit) > 1:
        rows = hit.reshape(len(hit), -1).any(axis=1)
        hit, origin, spacing = hit[rows], origin[rows], spacing[rows]
    for axis, others in enumerate(((2, 3), (1, 3), (1, 2))):
        on = hit.any(axis=others)
        first = on.argmax(axis=1)
        last = on.shape[1] - 1 - on[:, ::-1].argmax(axis=1)
        box_lo[axis] = min(box_lo[axis], (origin[:, axis] + first * spacing[:, axis]).min())
        box_hi[axis] = max(box_hi[axis],
                           (origin[:, axis] + (last + 1) * spacing[:, axis]).max())


def value_box_reference(volume, field: str, lo_value: float, hi_value: float):
    """Slow twin of :func:`value_box`: grid by grid."""
    box_lo, box_hi = np.full(3, np.inf), np.full(3, -np.inf)
    for i, g in enumerate(volume.grids):
        f = np.asarray(g.fields[field])
        keep = volume.leaf_mask(i) & np.isfinite(f)
        hit = keep & (f >= lo_value) & (f <= hi_value)
        for axis in range(3):
            if f.shape[axis] < 2:
                continue
            a = tuple(slice(0, -1) if k == axis else slice(None) for k in range(3))
            b = tuple(slice(1, None) if k == axis else slice(None) for k in range(3))
            meet = keep[a] & keep[b] & (np.minimum(f[a], f[b]) <= hi_value) & \
                (np.maximum(f[a], f[b]) >= lo_value)
            hit[a] |= meet
            hit[b] |= meet
        if not hit.any():
            continue
        origin, spacing = np.asarray(g.origin, float), np.asarray(g.spacing, float)
        for axis in range(3):
            on = np.flatnonzero(hit.any(axis=tuple(k for k in range(3) if k != axis)))
            box_lo[axis] = min(box_lo[axis], origin[axis] + on[0] * spacing[axis])
            box_hi[axis] = max(box_hi[axis], origin[axis] + (on[-1] + 1) * spacing[axis])
    return (box_lo, box_hi) if np.all(box_hi > box_lo) else None
