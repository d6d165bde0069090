"""Which grids hold a point, the slow, obvious way (every grid against every point): the
twins of :meth:`mi_amr.core.kdtree.KDTree.finest_grid` and ``support_grids``, and the rule
both share (the finest level wins; among grids of one level, the first listed). World space.
"""

from __future__ import annotations

import numpy as np

from mi_amr.core.boxes import contains_points
from mi_amr.errors import AMRError


def as_points(points) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise AMRError(f"points must be an (N, 3) array, got shape {points.shape}")
    return points


def finest_of(points, pi, gi, level) -> np.ndarray:
    G = len(level)
    best = np.full(len(points), -1, dtype=np.int64)
    np.maximum.at(best, pi, level[gi].astype(np.int64) * G + (G - 1 - gi))
    return np.where(best >= 0, G - 1 - best % G, -1)


def finest_grid_bruteforce(volume, points) -> np.ndarray:
    """Slow twin of :meth:`KDTree.finest_grid`: tests every grid against every point."""
    points = as_points(points)
    lo, hi = volume.grid_boxes()
    pi, gi = np.meshgrid(np.arange(len(points)), np.arange(len(lo)), indexing="ij")
    pi, gi = pi.ravel(), gi.ravel()
    inside = contains_points(lo[gi], hi[gi], points[pi])
    return finest_of(points, pi[inside], gi[inside], volume.levels)


def support_grids_bruteforce(volume, points) -> list:
    """Slow twin of :meth:`KDTree.support_grids`."""
    points = as_points(points)
    lo, hi = volume.grid_boxes()
    h = volume.spacings()
    out = []
    for p in points:
        inside = np.all((p > lo - h) & (p < hi + h), axis=1)
        out.append(np.flatnonzero(inside))
    return out
