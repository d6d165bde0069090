"""The volume and its kd-tree flattened into Dr.Jit arrays that kernels gather from.

Host-side preparation (NumPy) happens once per volume and field; the per-ray code in
:mod:`mi_amr.reconstruct` and :mod:`mi_amr.march` only reads these arrays. Everything is in the
volume's **world space** (float32 on the device). Kernels are generic over a Dr.Jit backend
module (``drjit.llvm.ad``, ``drjit.cuda.ad``, or ``drjit.scalar`` for Mitsuba's scalar variants).

Per grid ``g``: ``origin[g]`` and ``inv_h[g]`` (3 floats each), ``shape[g]`` (3 uints),
``offset[g]`` (first value in the flat value arrays; cell ``(i, j, k)`` is at
``offset + (i * ny + j) * nz + k``) and ``level[g]``. Value arrays: ``values`` (the field as
stored, used by the finest-level reconstruction), ``leaf_values`` (the same with NaN in covered
and non-finite cells, so the basis reconstruction gives them no weight), and the same pair for
the colour field. Per kd node: its box, its six ropes and the value range of the field inside it
(one per reconstruction, see :meth:`DeviceVolume.node_ranges`); per kd leaf: its box, owner
grid, range of grid ids (active ones first), the bitmask of active levels and its finest active
cell width.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

NO_GRID = 0xFFFFFFFF


def backend_of(float_type):
    """The Dr.Jit backend module (``drjit.llvm.ad``, ``drjit.scalar`` ...) of a Float type."""
    import importlib

    if float_type is float:
        return dr.scalar
    return importlib.import_module(float_type.__module__)


def gather(T, source, index, active=True):
    """``dr.gather`` that also works for the scalar backend (Python numbers, static arrays)."""
    if dr.is_jit_v(source):
        return dr.gather(T, source, index, active)
    if not active:
        return T(0)
    if dr.is_array_v(T):
        n = dr.size_v(T)
        return T(*[source[int(index) * n + i] for i in range(n)])
    return T(source[int(index)])


class DeviceVolume:
    """Device copy of ``volume`` + ``tree`` for one ``field`` (and an optional colour field).

    ``m`` is the backend module. Arrays are attributes (never loop state) so kernels capture
    them as constants of the traced program.
    """

    def __init__(self, volume, tree, field: str, color_field: str | None = None, m=None):
        self.m = m = m or dr.llvm.ad
        self.volume = volume
        self.tree = tree
        self.field = field
        self.color_field = color_field or field
        self.num_levels = volume.num_levels
        self.anchor = tuple(float(x) for x in volume.anchor)
        self.level_h = [tuple(float(x) for x in volume.level_spacing(l))
                        for l in range(volume.num_levels)]
        self.min_h = float(min(min(h) for h in self.level_h))
        lo, hi = volume.bounds
        self.bounds_lo = tuple(float(x) for x in lo)
        self.bounds_hi = tuple(float(x) for x in hi)

        f32 = lambda a: self._floats(np.asarray(a, dtype=np.float32).ravel())  # noqa: E731
        u32 = lambda a: self._uints(np.asarray(a, dtype=np.uint32).ravel())    # noqa: E731

        # kd-tree nodes and leaves
        self.node_code = u32(tree.node_code)
        self.node_split = f32(tree.node_split)
        self.leaf_lo = f32(tree.leaf_lo)
        self.leaf_hi = f32(tree.leaf_hi)
        self.leaf_owner = u32(np.where(tree.leaf_owner >= 0, tree.leaf_owner, NO_GRID))
        self.leaf_start = u32(tree.leaf_start)
        self.leaf_nactive = u32(tree.leaf_nactive)
        # Levels whose dual planes split a ray into cubic pieces: all active levels for the
        # basis blend, the owner's level for the finest-level reconstruction.
        self.leaf_levels = u32(tree.leaf_levels)
        owner_level = np.where(tree.leaf_owner >= 0, volume.levels[np.maximum(tree.leaf_owner, 0)], 0)
        self.leaf_owner_levels = u32(np.where(tree.leaf_owner >= 0, 1 << owner_level, 0))
        min_h = tree.leaf_min_h.min(axis=1)
        self.leaf_min_h = f32(np.where(np.isfinite(min_h), min_h, self.min_h))
        self.leaf_grids = u32(tree.leaf_grids)
        self.node_ropes = u32(tree.node_ropes)
        self.node_lo = f32(tree.node_lo)
        self.node_hi = f32(tree.node_hi)
        self.tree_depth = int(tree.depth)
        self._ranges = {}

        # grids
        glo, _ = volume.grid_boxes()
        h = volume.spacings()
        shapes = np.array([g.shape for g in volume.grids], dtype=np.int64)
        counts = np.prod(shapes, axis=1)
        offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
        if counts.sum() >= 2 ** 32:
            from .errors import AMRError
            raise AMRError(f"{volume.num_cells} cells: more than 2^32 cannot be indexed")
        self.grid_origin = f32(glo)
        self.grid_inv_h = f32(1.0 / h)
        self.grid_shape = u32(shapes)
        self.grid_offset = u32(offsets)
        self.grid_level = u32(volume.levels)

        self.values, self.leaf_values = self._field_arrays(field)
        if self.color_field == field:
            self.color_values, self.color_leaf_values = self.values, self.leaf_values
        else:
            self.color_values, self.color_leaf_values = self._field_arrays(self.color_field)

    def _field_arrays(self, name):
        vol = self.volume
        raw = np.concatenate([g.fields[name].ravel() for g in vol.grids]).astype(np.float32)
        leaf = np.concatenate([np.where(vol.leaf_mask(i), g.fields[name], np.nan).ravel()
                               for i, g in enumerate(vol.grids)]).astype(np.float32)
        return self._floats(raw), self._floats(leaf)

    def _floats(self, a):
        m = self.m
        return dr.scalar.ArrayXf(a) if m is dr.scalar else m.Float(a)

    def _uints(self, a):
        m = self.m
        return dr.scalar.ArrayXu(a) if m is dr.scalar else m.UInt32(a)

    def node_ranges(self, basis: bool):
        """Per-node value range ``(lo, hi)`` of the field for one reconstruction (computed on
        first use: each costs a pass over the cells). A leaf with no data has ``(+inf, -inf)``."""
        key = "basis" if basis else "finest"
        if key not in self._ranges:
            rlo, rhi = self.tree.node_ranges(*self.tree.leaf_ranges(self.field, key))
            self._ranges[key] = (self._floats(rlo.astype(np.float32)),
                                 self._floats(rhi.astype(np.float32)))
        return self._ranges[key]
