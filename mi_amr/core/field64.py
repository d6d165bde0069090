"""The float64 reference model of the reconstruction: what the Dr.Jit kernels compute, in
NumPy and double precision, for the tests, the stability suite and the reference images' checks.

* :class:`Field64` -- the model, vectorised over points (the one to call).
* :func:`basis_point_reference`, :func:`finest_point_reference` -- the same sums written out
  cell by cell and point by point (slow and obvious); they check :class:`Field64` and the
  kernels on small volumes (:meth:`Field64.twin_difference`).

Positions are the volume's world space; values are float64; gradients are per world unit.
The two reconstructions are those of :mod:`mi_amr.kernels.reconstruct`.
"""

from __future__ import annotations

import numpy as np

from mi_amr.core.points import finest_grid_bruteforce


class Field64:
    """The reconstruction of ``field`` in float64, vectorised over points.

    The same sums as the slow twins: ``basis`` is the blend of the leaf cells of every level
    (only the 8 cells around a point have weight on each level, looked up in a per-level table
    of leaf values, NaN where no leaf cell or a non-finite value), otherwise trilinear
    interpolation with clamped indices in the finest grid containing the point (closed boxes;
    among grids of one level the first listed), NaN outside every grid or next to a non-finite
    value. :meth:`twin_difference` measures the agreement with the twins.
    """

    def __init__(self, volume, field: str, basis: bool, min_weight: float = 0.0):
        self.volume, self.field, self.basis = volume, field, basis
        # basis: the field is undefined (NaN) where the cells with values weigh less than this
        # (0: wherever some cell has weight); see mi_amr.tolerances.MIN_COVER.
        self.min_weight = float(min_weight)
        self.anchor = np.asarray(volume.anchor, dtype=np.float64)
        self.h_fine = float(volume.level_spacing(volume.num_levels - 1).min())
        lo, hi = volume.index_boxes()
        levels = volume.levels
        self._tables = []
        for level in range(volume.num_levels):
            ids = np.flatnonzero(levels == level)
            base, top = lo[ids].min(axis=0), hi[ids].max(axis=0)
            table = np.full(tuple(top - base), np.nan if basis else -1,
                            dtype=np.float64 if basis else np.int64)
            for g in ids:
                box = tuple(slice(a, b) for a, b in zip(lo[g] - base, hi[g] - base))
                if basis:
                    values = volume.grids[g].fields[field].astype(np.float64)
                    table[box] = np.where(volume.leaf_mask(g), values, np.nan)
                else:
                    table[box] = g
            self._tables.append((volume.level_spacing(level), base, table))
        self.level_spacings = [h for h, _, _ in self._tables]
        if not basis:
            grids = volume.grids
            self._flat = np.concatenate([g.fields[field].astype(np.float64).ravel()
                                         for g in grids])
            shapes = np.array([g.shape for g in grids], dtype=np.int64)
            self._shape = shapes
            self._offset = np.concatenate([[0], np.cumsum(np.prod(shapes, axis=1))[:-1]])
            self._origin = np.array([g.origin for g in grids], dtype=np.float64)
            self._spacing = volume.spacings()

    def __call__(self, points) -> np.ndarray:
        """Values at ``points`` ``(N, 3)`` (world), float64; NaN where undefined."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self._basis(points) if self.basis else self._finest(points)

    def _basis(self, p):
        num, den = self.basis_sums(p)
        defined = den >= self.min_weight if self.min_weight > 0 else den > 0.0
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(defined, num / den, np.nan)

    def basis_sums(self, p):
        """The blend's numerator and denominator (the weight of the cells with values; 1 where
        every cell has one) at points ``p`` ``(N, 3)``."""
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        num = np.zeros(len(p))
        den = np.zeros(len(p))
        for h, base, table in self._tables:
            u = (p - self.anchor) / h - 0.5 - base
            i0 = np.floor(u).astype(np.int64)
            f = u - i0
            for corner in range(8):
                b = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
                idx = i0 + b
                ok = np.all((idx >= 0) & (idx < table.shape), axis=1)
                v = np.full(len(p), np.nan)
                v[ok] = table[idx[ok, 0], idx[ok, 1], idx[ok, 2]]
                w = np.prod(np.where(b == 1, f, 1.0 - f), axis=1)
                has = np.isfinite(v) & (w > 0.0)
                num += np.where(has, w, 0.0) * np.where(has, v, 0.0)
                den += np.where(has, w, 0.0)
        return num, den

    def owner(self, p) -> np.ndarray:
        """Finest grid whose closed box holds each point (the first listed among one level's);
        -1 outside all grids. Same rule as :func:`mi_amr.core.points.finest_grid_bruteforce`."""
        if self.basis:
            raise ValueError("owner() is for the finest reconstruction")
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(p), -1, dtype=np.int64)
        none = np.iinfo(np.int64).max
        for h, base, table in reversed(self._tables):
            u = (p - self.anchor) / h - base
            below = np.floor(u)
            # A point on a cell face belongs to the cells on both sides.
            cands = (below.astype(np.int64),
                     np.where(u == below, below - 1, below).astype(np.int64))
            best = np.full(len(p), none)
            for corner in range(8):
                idx = np.stack([cands[(corner >> (2 - a)) & 1][:, a] for a in range(3)], axis=1)
                ok = np.all((idx >= 0) & (idx < table.shape), axis=1)
                g = np.full(len(p), -1, dtype=np.int64)
                g[ok] = table[idx[ok, 0], idx[ok, 1], idx[ok, 2]]
                best = np.where(g >= 0, np.minimum(best, g), best)
            new = (out < 0) & (best < none)
            out[new] = best[new]
        return out

    def _finest(self, p):
        out = np.full(len(p), np.nan)
        g = self.owner(p)
        sel = np.flatnonzero(g >= 0)
        g, q = g[sel], p[sel]
        n = self._shape[g]
        u = (q - self._origin[g]) / self._spacing[g] - 0.5
        uc = np.clip(u, 0.0, n - 1)
        i0 = np.minimum(np.floor(uc).astype(np.int64), np.maximum(n, 2) - 2)
        i1 = np.minimum(i0 + 1, n - 1)
        f = uc - i0
        val = np.zeros(len(q))
        for corner in range(8):
            b = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            idx = np.where(b == 1, i1, i0)
            flat = self._offset[g] + (idx[:, 0] * n[:, 1] + idx[:, 1]) * n[:, 2] + idx[:, 2]
            val += np.prod(np.where(b == 1, f, 1.0 - f), axis=1) * self._flat[flat]
        out[sel] = val
        return out

    def twin_difference(self, points) -> float:
        """Largest difference from the slow twin at ``points`` (inf where exactly one of the
        two is NaN)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(points) == 0:
            return 0.0
        twin = basis_point_reference if self.basis else finest_point_reference
        if self.basis and self.min_weight > 0:
            points = points[self.basis_sums(points)[1] >= self.min_weight]
        a = twin(self.volume, points, self.field)[0]
        b = self(points)
        if np.any(np.isnan(a) != np.isnan(b)):
            return float("inf")
        both = np.isfinite(a)
        return float(np.max(np.abs(a[both] - b[both]), initial=0.0))


def finest_point_reference(volume, points, field):
    """Slow twin of :func:`mi_amr.kernels.reconstruct.finest_point`: finest grid by brute force, then trilinear with
    clamped indices. Returns ``(values, gradients)`` (float64); NaN outside all grids."""
    points = np.asarray(points, dtype=np.float64)
    owner = finest_grid_bruteforce(volume, points)
    values = np.full(len(points), np.nan)
    grads = np.full((len(points), 3), np.nan)
    for i, (p, g) in enumerate(zip(points, owner)):
        if g < 0:
            continue
        grid = volume.grids[g]
        arr = grid.fields[field].astype(np.float64)
        n = np.array(grid.shape)
        u = (p - np.array(grid.origin)) / np.array(grid.spacing) - 0.5
        uc = np.clip(u, 0, n - 1)
        i0 = np.minimum(np.floor(uc).astype(int), np.maximum(n, 2) - 2)
        i1 = np.minimum(i0 + 1, n - 1)
        f = uc - i0
        live = (u >= 0) & (u <= n - 1)
        val, grad = 0.0, np.zeros(3)
        for corner in range(8):
            b = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            idx = np.where(b == 1, i1, i0)
            w = np.where(b == 1, f, 1 - f)
            v = arr[idx[0], idx[1], idx[2]]
            val += np.prod(w) * v
            for a in range(3):
                others = np.prod(np.delete(w, a))
                grad[a] += (1 if b[a] else -1) * others * v
        values[i] = val
        grads[i] = grad / np.array(grid.spacing) * live
    return values, grads


def basis_point_reference(volume, points, field):
    """Slow twin of :func:`mi_amr.kernels.reconstruct.basis_point`: the sum over *every* leaf cell of the volume.
    Returns ``(values, gradients)`` (float64); NaN where no cell has weight."""
    points = np.asarray(points, dtype=np.float64)
    num = np.zeros(len(points))
    den = np.zeros(len(points))
    dnum = np.zeros((len(points), 3))
    dden = np.zeros((len(points), 3))
    for gi, g in enumerate(volume.grids):
        leaf = volume.leaf_mask(gi)
        arr = g.fields[field].astype(np.float64)
        keep = leaf & np.isfinite(arr)
        centres = np.stack(np.meshgrid(*g.cell_centers(), indexing="ij"), axis=-1)[keep]
        vals = arr[keep]
        w = np.array(g.spacing)
        for i, p in enumerate(points):
            r = (p - centres) / w
            h = np.maximum(0.0, 1.0 - np.abs(r))
            H = np.prod(h, axis=1)
            sel = H > 0
            if not sel.any():
                continue
            num[i] += np.sum(H[sel] * vals[sel])
            den[i] += np.sum(H[sel])
            for a in range(3):
                others = np.prod(np.delete(h[sel], a, axis=1), axis=1)
                dh = -np.sign(r[sel, a]) / w[a]
                dnum[i, a] += np.sum(dh * others * vals[sel])
                dden[i, a] += np.sum(dh * others)
    with np.errstate(invalid="ignore", divide="ignore"):
        values = np.where(den > 0, num / den, np.nan)
        grads = (dnum * den[:, None] - dden * num[:, None]) / (den[:, None] ** 2)
    return values, grads
