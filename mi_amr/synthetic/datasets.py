"""Synthetic datasets: the course report's sphere wake, and analytic fields with known isosurfaces.

Each dataset is a function returning an :class:`~mi_amr.volume.AMRVolume`; :data:`DATASETS`
lists them for ``python -m mi_amr dataset NAME -o PATH``.

* :func:`sphere_wake` -- air flow around a ball (see :mod:`mi_amr.flow`), refined where the
  vorticity is strong: tagged cells are clustered into boxes (Berger-Rigoutsos), so fine grids
  cover the wake and the ball's surroundings, not the empty far field. Fields ``vx, vy, vz``.
  :func:`sphere_wake_on` puts another seed's flow on one wake's grids.
* :func:`sphere`, :func:`torus`, :func:`ramp`, :func:`spike` -- a field ``f`` whose isosurface
  at :data:`ISOVALUES` ``[name]`` is known, on two levels whose boundary (the plane x = 0.5) cuts
  through the surface.
* :func:`boundary_and_blob` -- the value 0.5 crossed both at a sharp boundary and across a broad
  smooth region (the case a 2D transfer function tells apart).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_amr.synthetic import flow
from mi_amr.synthetic.cluster import berger_rigoutsos
from mi_amr.errors import AMRError
from mi_amr.core.atomic import check_output, replacing
from mi_amr.core.volume import AMRVolume, Grid

SIZES = {
    # base cells (x, y, z), levels, per-level tag thresholds on |vorticity| * h / U
    "small": ((32, 16, 16), 3, (0.3, 0.45)),
    "default": ((64, 32, 32), 4, (0.2, 0.3, 0.45)),
    "large": ((128, 64, 64), 4, (0.08, 0.13, 0.2)),
    "xlarge": ((128, 64, 64), 4, (0.055, 0.09, 0.14)),
    # 105M cells (1.3 GB on disk), the largest: its scene load peaks at 4.9 GB resident
    "xxlarge": ((128, 64, 64), 4, (0.021, 0.035, 0.055)),
}
RATIO = 2
BLOCKING = 4          # fine grids start and end on multiples of 4 fine cells
MAX_GRID = 32         # cells per side of a grid, at most
BUFFER = 2            # tagged regions are grown by this many cells before clustering


def sphere_wake(size: str = "default", seed: int = 0, progress: bool = True) -> AMRVolume:
    """The flow around a ball moving through still air, in the ball's frame (world units; the
    ball of radius :data:`mi_amr.flow.BALL_RADIUS` sits at the origin and air streams in +x).

    ``size`` is ``small`` (tests, about a second), ``default`` (4M cells, 4 s), ``large``
    (27M cells, 26 s), ``xlarge`` (46M cells, 42 s) or ``xxlarge`` (105M cells, 95 s). Levels
    refine by 2; a level-``l`` cell is tagged for refinement where ``|curl v| * h_l / U``
    exceeds a threshold, so refinement follows the vortices.
    """
    if size not in SIZES:
        raise AMRError(f"size must be one of {list(SIZES)}, got {size!r}")
    base, num_levels, thresholds = SIZES[size]
    model = flow.SphereWakeFlow(seed)
    lo = np.array(flow.DOMAIN_LO)
    h0 = (np.array(flow.DOMAIN_HI) - lo) / np.array(base)
    bar = _progress(progress, total=num_levels, desc=f"sphere_wake ({size})")
    boxes = _chop([((0, 0, 0), tuple(base))], MAX_GRID)
    grids = []
    for level in range(num_levels):
        h = h0 / RATIO ** level
        level_grids = []
        for blo, bhi in boxes:
            shape = tuple(int(b - a) for a, b in zip(blo, bhi))
            origin = tuple(lo + np.array(blo) * h)
            centres = np.stack(np.meshgrid(*Grid(level, origin, tuple(h), shape, {}).cell_centers(),
                                           indexing="ij"), axis=-1).reshape(-1, 3)
            v = model.velocity(centres).astype(np.float32).reshape(shape + (3,))
            level_grids.append({"level": level, "origin": origin, "spacing": tuple(h),
                                "fields": {"vx": v[..., 0].copy(), "vy": v[..., 1].copy(),
                                           "vz": v[..., 2].copy()}})
        grids.extend(level_grids)
        if level + 1 < num_levels:
            tags = _tag(level_grids, boxes, base, level, thresholds[level], h)
            boxes = _refine(tags, boxes)
        bar.update(1)
    bar.close()
    return AMRVolume.from_grids(grids, source=f"sphere_wake({size})")


def sphere_wake_on(volume: AMRVolume, seed: int) -> AMRVolume:
    """The flow of :func:`sphere_wake` ``seed`` on the grids of ``volume`` (another
    sphere_wake), not refined after it: the time steps of a simulation whose grids stay put
    (static refinement, or the steps between two regrids). Fields ``vx, vy, vz``."""
    model = flow.SphereWakeFlow(seed)
    grids = []
    for g in volume.grids:
        centres = np.stack(np.meshgrid(*g.cell_centers(), indexing="ij"), axis=-1)
        v = model.velocity(centres.reshape(-1, 3)).astype(np.float32).reshape(g.shape + (3,))
        grids.append({"level": g.level, "origin": g.origin, "spacing": g.spacing,
                      "fields": {n: v[..., a].copy() for a, n in enumerate(("vx", "vy", "vz"))}})
    return AMRVolume.from_grids(grids, source=f"sphere_wake_on(seed={seed})")


def write_ball_mesh(path, subdivisions: int = 4) -> Path:
    """Write the ball (radius :data:`mi_amr.flow.BALL_RADIUS`, at the origin) as a PLY mesh."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=flow.BALL_RADIUS)
    path = Path(path)
    with replacing(path) as tmp:
        mesh.export(tmp, file_type="ply")
    return path


# ---------------------------------------------------------------------- refinement

def _tag(level_grids, boxes, base, level, threshold, h):
    """Boolean tag array over the level's whole index space (cells of this level)."""
    shape = tuple(int(n) * RATIO ** level for n in base)
    tags = np.zeros(shape, dtype=bool)
    coverage = np.zeros(shape, dtype=bool)
    for g, (blo, bhi) in zip(level_grids, boxes):
        vel = [g["fields"][c].astype(np.float64) for c in ("vx", "vy", "vz")]
        grads = [np.gradient(c, *h) if min(c.shape) > 1 else [np.zeros_like(c)] * 3 for c in vel]
        wx = grads[2][1] - grads[1][2]
        wy = grads[0][2] - grads[2][0]
        wz = grads[1][0] - grads[0][1]
        vort = np.sqrt(wx * wx + wy * wy + wz * wz) * h.min() / flow.FREESTREAM
        sl = tuple(slice(a, b) for a, b in zip(blo, bhi))
        tags[sl] = vort > threshold
        coverage[sl] = True
    # Grow the tags so the fine level reaches beyond the vortex cores.
    for axis in range(3):
        tags = _dilate(tags, axis, BUFFER)
    return tags & coverage


def _dilate(mask, axis, n):
    out = mask.copy()
    for shift in range(1, n + 1):
        fwd = [slice(None)] * 3
        src = [slice(None)] * 3
        fwd[axis], src[axis] = slice(shift, None), slice(None, -shift)
        out[tuple(fwd)] |= mask[tuple(src)]
        out[tuple(src)] |= mask[tuple(fwd)]
    return out


def _refine(tags, parent_boxes):
    """Boxes of the next level (in its own index space) covering the tags, aligned to the
    blocking factor and inside the parent boxes."""
    b = BLOCKING // RATIO
    shape = tuple(-(-n // b) for n in tags.shape)
    padded = np.zeros(tuple(n * b for n in shape), dtype=bool)
    padded[:tags.shape[0], :tags.shape[1], :tags.shape[2]] = tags
    blocks = padded.reshape(shape[0], b, shape[1], b, shape[2], b).any(axis=(1, 3, 5))
    clusters = berger_rigoutsos(blocks, efficiency=0.7, max_size=MAX_GRID // BLOCKING)
    p_lo = np.array([lo for lo, _ in parent_boxes], dtype=np.int64).reshape(-1, 3)
    p_hi = np.array([hi for _, hi in parent_boxes], dtype=np.int64).reshape(-1, 3)
    out = []
    for clo, chi in clusters:
        # The cluster cut by every parent box at once (in the parents' order).
        lo = np.maximum(np.array(clo) * b, p_lo)
        hi = np.minimum(np.array(chi) * b, p_hi)
        for i in np.flatnonzero(np.all(hi > lo, axis=1)):
            out.append((tuple(lo[i] * RATIO), tuple(hi[i] * RATIO)))
    return _chop(out, MAX_GRID)


def _chop(boxes, max_size):
    """Split boxes so no side exceeds ``max_size`` (halving, keeping blocking alignment)."""
    out, todo = [], list(boxes)
    while todo:
        lo, hi = (np.array(x) for x in todo.pop())
        size = hi - lo
        axis = int(np.argmax(size))
        if size[axis] <= max_size:
            out.append((tuple(int(x) for x in lo), tuple(int(x) for x in hi)))
            continue
        cut = lo[axis] + (size[axis] // 2 // BLOCKING) * BLOCKING or lo[axis] + size[axis] // 2
        mid_hi, mid_lo = hi.copy(), lo.copy()
        mid_hi[axis] = cut
        mid_lo[axis] = cut
        todo += [(lo, mid_hi), (mid_lo, hi)]
    return out


def _progress(enabled, total, desc):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="level", disable=not enabled, leave=False)


# ---------------------------------------------------------------------- analytic fields

ISOVALUES = {"sphere": 0.3, "torus": 0.1, "ramp": 0.0, "spike": 0.75}
SPIKE_POINT = (0.546875, 0.421875, 0.484375)   # world point inside the spike's cell
SPIKE_CELL = (17, 13, 15)     # that level-1 cell (i, j, k), counted from the cube's corner,
                              # for the default base of 16 cells


def two_levels(fn, base: int = 16):
    """Unit cube, level 0 of ``base`` cells per side, level 1 (ratio 2) over x >= 0.5, as the
    analytic datasets; ``fn(centres, level)`` maps cell centres ``(..., 3)`` (world) to
    values."""
    grids = []
    for level, origin, shape in ((0, (0.0, 0.0, 0.0), (base,) * 3),
                                 (1, (0.5, 0.0, 0.0), (base, 2 * base, 2 * base))):
        h = 1.0 / (base * 2 ** level)
        centres = np.stack(np.meshgrid(*Grid(level, origin, (h,) * 3, shape, {}).cell_centers(),
                                       indexing="ij"), axis=-1)
        grids.append({"level": level, "origin": origin, "spacing": h,
                      "fields": {"f": fn(centres, level).astype(np.float64)}})
    return AMRVolume.from_grids(grids)


def sphere(base: int = 16) -> AMRVolume:
    """``f = |p - (0.5, 0.5, 0.5)|``; isosurface 0.3 is a sphere cut by the level boundary."""
    return two_levels(lambda p, level: np.linalg.norm(p - 0.5, axis=-1), base)


def torus(base: int = 16) -> AMRVolume:
    """Distance to a circle of radius 0.27 around an axis tilted in the x-z plane; isosurface
    0.1 is a torus crossing the level boundary."""
    c = np.array([0.5, 0.5, 0.5])
    axis = np.array([np.sin(0.5), 0.0, np.cos(0.5)])

    def f(p, level):
        d = p - c
        z = d @ axis
        rho = np.linalg.norm(d - z[..., None] * axis, axis=-1)
        return np.sqrt((rho - 0.27) ** 2 + z ** 2)

    return two_levels(f, base)


RAMP_NORMAL = np.array([0.8, 0.36, 0.48])


def ramp(base: int = 16) -> AMRVolume:
    """A linear ramp ``f = n . (p - (0.5, 0.5, 0.5))``; isosurface 0 is a tilted plane."""
    return two_levels(lambda p, level: (p - 0.5) @ RAMP_NORMAL, base)


def spike(base: int = 16) -> AMRVolume:
    """Zero everywhere but one level-1 cell (:data:`SPIKE_CELL`, next to the level boundary)
    holding 1; isosurface 0.75 is a blob half a cell across, thinner than any fixed step."""

    def f(p, level):
        out = np.zeros(p.shape[:-1])
        if level == 1:
            # The level-1 cell holding SPIKE_POINT; the level-1 grid starts at x = 0.5, which is
            # level-1 cell ``base`` (for base 16 the cell is SPIKE_CELL).
            cell = np.floor(np.array(SPIKE_POINT) * 2 * base).astype(int)
            out[cell[0] - base, cell[1], cell[2]] = 1.0
        return out

    return two_levels(f, base)


# boundary_and_blob: the sharp ball (centre, radius, tanh width; on the fine level x >= 0.5) and
# the smooth Gaussian blob (centre, sigma, peak; on the coarse level).
BALL = ((0.73, 0.5, 0.5), 0.15, 0.01)
BLOB = ((0.27, 0.5, 0.5), 0.15, 0.8)


def boundary_and_blob(base: int = 24) -> AMRVolume:
    """``f = ball + blob`` on :func:`two_levels`: a ball of value 1 whose edge (a tanh of width
    0.01, under one fine cell) crosses 0.5 at ``|p - c1| = 0.15`` with ``|grad f|`` about 50,
    and a Gaussian blob ``0.8 exp(-|p - c2|^2 / (2 0.15^2))`` that crosses 0.5 at
    ``|p - c2| = 0.146`` with ``|grad f| = 3.2`` (:data:`BALL`, :data:`BLOB`; world units of
    the unit cube). A 1D band around 0.5 draws both; a material boundary is only the ball."""
    (c1, r1, w1), (c2, s2, peak2) = BALL, BLOB

    def f(p, level):
        ball = 0.5 * (1.0 + np.tanh((r1 - np.linalg.norm(p - np.asarray(c1), axis=-1)) / w1))
        d2 = np.sum((p - np.asarray(c2)) ** 2, axis=-1)
        return ball + peak2 * np.exp(-0.5 * d2 / s2 ** 2)

    return two_levels(f, base)


ANALYTIC = {"sphere": sphere, "torus": torus, "ramp": ramp, "spike": spike}
DATASETS = {"sphere_wake": sphere_wake, **ANALYTIC, "boundary_and_blob": boundary_and_blob}


def make(name: str, path, *, size: str = "default", seed: int = 0, overwrite: bool = False,
         progress: bool = True) -> list:
    """Build dataset ``name`` and write it to ``path`` (``.npz``); for ``sphere_wake`` also write
    the ball mesh ``ball.ply`` next to it. Returns the paths written. The paths are checked
    (see :func:`mi_amr.core.atomic.check_output`) before the dataset is built: an existing
    ``.npz`` or ``ball.ply`` is replaced only with ``overwrite``."""
    if name not in DATASETS:
        raise AMRError(f"unknown dataset '{name}'; available: {list(DATASETS)}")
    path = check_output(path, suffixes=(".npz",), overwrite=overwrite,
                        exists_hint="pass overwrite=True (--force on the command line) to "
                                    "replace it")
    if name == "sphere_wake":
        # The mesh shares a folder (and often a name) with other runs' data: same rule as .npz.
        check_output(path.parent / "ball.ply", overwrite=overwrite,
                     exists_hint="pass overwrite=True (--force on the command line) to "
                                 "replace it")
    if name == "sphere_wake":
        vol = sphere_wake(size=size, seed=seed, progress=progress)
    else:
        vol = DATASETS[name]()
    vol.save(path, overwrite=overwrite)
    written = [path]
    if name == "sphere_wake":
        written.append(write_ball_mesh(path.parent / "ball.ply"))
    return written


def split_grids(volume: AMRVolume, max_cells: int) -> AMRVolume:
    """The same cells cut into grids of at most ``max_cells`` per side (cuts stay on the coarser
    level's cell faces), for measuring how rendering scales with the number of grids."""
    if max_cells < 2 or max_cells % 2:
        raise AMRError(f"max_cells must be an even number >= 2, got {max_cells}")
    out = []
    for g in volume.grids:
        step = max_cells
        for i in range(0, g.shape[0], step):
            for j in range(0, g.shape[1], step):
                for k in range(0, g.shape[2], step):
                    sl = (slice(i, i + step), slice(j, j + step), slice(k, k + step))
                    origin = tuple(o + n * h for o, n, h in zip(g.origin, (i, j, k), g.spacing))
                    out.append({"level": g.level, "origin": origin, "spacing": g.spacing,
                                "fields": {n: a[sl] for n, a in g.fields.items()}})
    return AMRVolume.from_grids(out, allow_nonfinite=volume.allow_nonfinite,
                                source=volume.source)


def many_grids(per_axis: int = 20, fine: int = 2000, seed: int = 0) -> list:
    """Grid records (for :meth:`AMRVolume.from_grids`) of a hierarchy with very many tiny grids:
    ``per_axis^3`` level-0 grids of 2^3 cells (size 1) tiling a box ``2 per_axis`` wide, and
    ``fine`` level-1 grids of 2^3 cells (size 1/2), each filling one random octant of a
    distinct level-0 grid. Field ``f``: 0 on level 0, 1 on level 1. For the kd-tree's scaling
    (``per_axis=40, fine=36000`` gives 10^5 grids)."""
    if fine > per_axis ** 3:
        raise AMRError(f"fine ({fine}) must not exceed the number of level-0 grids "
                       f"({per_axis ** 3})")
    rng = np.random.default_rng(seed)
    coarse_values, fine_values = np.zeros((2, 2, 2)), np.ones((2, 2, 2))
    axis = np.arange(per_axis)
    origins = 2.0 * np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    grids = [{"level": 0, "origin": tuple(o), "spacing": 1.0, "fields": {"f": coarse_values}}
             for o in origins]
    parents = rng.choice(len(origins), fine, replace=False)
    for o in origins[parents] + rng.integers(0, 2, (fine, 3)):
        grids.append({"level": 1, "origin": tuple(o), "spacing": 0.5,
                      "fields": {"f": fine_values}})
    return grids
