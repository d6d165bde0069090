"""The volume and its kd-tree flattened into Dr.Jit arrays that kernels gather from.

Host-side preparation (NumPy) happens once per volume and field; the per-ray code in
:mod:`mi_amr.kernels.reconstruct` and the marching modules only reads these arrays. Everything
is in the volume's **world space** (float32 on the device). Kernels are generic over a Dr.Jit
JIT backend module (``drjit.llvm.ad`` or ``drjit.cuda.ad``; Mitsuba's scalar variants run them
on one-element LLVM arrays).

Every value that differs from one dataset to the next is a kernel *input*, never a literal in
the traced code: the arrays below, and the few per-volume numbers (bounds, root box, lattice
anchor, level spacings, finest cell width), which are opaque one-element arrays. So a new
dataset of the same scene structure (field, mode, method, number of isovalues) reuses every
compiled kernel.

Per grid ``g``: ``grid_origin[g]`` and ``grid_inv_h[g]`` (3 floats each), ``grid_shape[g]``
(3 uints), ``grid_offset[g]`` (first value in the flat value arrays; cell ``(i, j, k)`` is at
``offset + (i * ny + j) * nz + k``) and ``grid_level[g]``. Value arrays: ``values`` (the field
as stored, used by the finest-level reconstruction) and ``color_values``; the basis
reconstruction reads brick pools of *leaf* values (NaN in covered and non-finite cells, so the
blend gives them no weight). Per kd node: its box, code and split, six ropes and the value
range of the field inside it (one per reconstruction, read with the node's code and split in
one load, next to its children's: :meth:`DeviceVolume.node_search`);
per kd leaf: its box, owner grid, range of grid ids (active ones first), the bitmask of active
levels and its finest active cell width.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_amr import tolerances as tol
from mi_amr.core import levels
from mi_amr.core.buffers import ALIGN, aligned_empty
from mi_amr.kernels import bricks, ranges, starts
from mi_amr.kernels.arrays import device_array, mapped_array
from mi_amr.kernels.bricks import BRICK, BRICK_N, NO_BRICK, brick_table  # noqa: F401
from mi_amr.errors import AMRError

NO_GRID = 0xFFFFFFFF
NODE_RECORDS = 3          # per kd node in node_search: its own record and its two children's


def backend_of(float_type):
    """The Dr.Jit backend module (``drjit.llvm.ad``, ``drjit.cuda.ad``) of a Float type."""
    import importlib

    return importlib.import_module(float_type.__module__)


def lnot(mask):
    """Logical not of a Dr.Jit mask or of a plain bool (the masks of Mitsuba's scalar
    variants, where ``~True`` would be the integer -2)."""
    return ~mask if dr.is_array_v(mask) else not mask


def opaque_floats(m, values):
    """``values`` (numbers) as an opaque kernel input: a ``m.Float`` from aligned host memory,
    never a literal (literals of equal value may be merged into one variable, which would make
    the traced program depend on the values)."""
    v = device_array(m.Float, values, np.float32)
    dr.make_opaque(v)
    return v


def opaque_bools(m, values):
    """``values`` as an opaque ``m.Bool`` kernel input (see :func:`opaque_floats`)."""
    v = device_array(m.Bool, values, np.bool_)
    dr.make_opaque(v)
    return v


def opaque_point(m, xyz):
    """A 3-vector as an opaque kernel input (three variables from host memory)."""
    return m.Array3f(*(opaque_floats(m, [x]) for x in np.ravel(xyz)[:3]))


class DeviceVolume:
    """Device copy of ``volume`` + ``tree`` for one ``field`` (and an optional colour field).

    ``m`` is the backend module. Arrays are attributes (never loop state) so kernels capture
    them as constants of the traced program. ``bricks`` (as in :attr:`host_bricks`) skips
    building the brick pools, when a snapshot already holds them.
    """

    def __init__(self, volume, tree, field: str, color_field: str | None = None, m=None,
                 bricks=None):
        self.m = m = m or dr.llvm.ad
        self.volume = volume
        self.tree = tree
        self.field = field
        self.color_field = color_field or field
        self.num_levels = volume.num_levels
        self._constants(volume)

        f32 = lambda a: self._floats(np.asarray(a, dtype=np.float32).ravel())  # noqa: E731
        u32 = lambda a: self._uints(np.asarray(a, dtype=np.uint32).ravel())    # noqa: E731

        # kd-tree nodes (code and split side by side, boxes as 2 x 4 floats) and leaves, made
        # in aligned memory that the device arrays map (no second copy).
        N = tree.num_nodes
        code_split = aligned_empty(N * 2, np.uint32).reshape(N, 2)
        code_split[:, 0] = tree.node_code
        code_split[:, 1] = tree.node_split.astype(np.float32).view(np.uint32)
        self.node_code_split = mapped_array(m.UInt32, code_split, np.uint32)
        self._host_code_split = code_split
        box = aligned_empty(N * 8, np.float32).reshape(N, 2, 4)
        box[:, 0, :3] = tree.node_lo
        box[:, 1, :3] = tree.node_hi
        box[:, :, 3] = 0.0
        self.node_box = mapped_array(m.Float, box, np.float32)
        self.root_lo = self._point(tree.lo)
        self.root_hi = self._point(tree.hi)
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
        min_h = tree.leaf_min_h
        self.leaf_min_h = f32(np.where(np.isfinite(min_h), min_h, self.min_h_host))
        # (grid numbers: int32 bits that are uint32's; the tree's own aligned array, mapped)
        self.leaf_grids = mapped_array(m.UInt32, tree.leaf_grids.view(np.uint32), np.uint32)
        # The tree's own ropes, mapped (they are uint32 and aligned for this).
        self.node_ropes = mapped_array(m.UInt32, tree.node_ropes, np.uint32)
        self.host_ranges, self.on_new_ranges, self._search, self._boxes = {}, None, {}, {}
        self._tables, self._lattice_split = {}, None

        # grids
        glo, _ = volume.grid_boxes()
        h = volume.spacings()
        shapes = volume.shapes()
        offsets = volume.cell_offsets()
        if volume.num_cells >= 2 ** 32:
            raise AMRError(f"{volume.num_cells} cells: more than 2^32 cannot be indexed")
        self.grid_origin = f32(glo)
        self.grid_inv_h = f32(1.0 / h)
        self.grid_shape = u32(shapes)
        self.grid_offset = u32(offsets)
        self.grid_level = u32(volume.levels)

        # Without the fields (a preparation that keeps none, its bricks given): no values.
        held = field in volume.field_names
        self.values = field_values(m, volume, field) if held else None
        self.color_values = self.values if self.color_field == field or not held else \
            field_values(m, volume, self.color_field)
        if bricks is None and not held:
            raise AMRError(f"{volume.source_prefix()}no field '{field}' to fill the brick "
                           f"pools from")
        pooled = [self.values] + ([self.color_values] if self.color_field != field else [])
        self._set_bricks(*(bricks or build_bricks(m, volume, pooled)))

    def _constants(self, volume):
        """The per-volume numbers the kernels read, as opaque one-element arrays (world units):
        ``bounds_lo``/``bounds_hi``, ``anchor`` (the lattice origin), ``level_geom`` (per
        level the cell size and its inverse, 4 floats each: see :meth:`level_h`), ``min_h``
        (the finest cell width), and from it ``step_eps`` (the smallest step along a unit-speed ray) and ``layer_offset`` (how far
        past a crossing the next layer starts). ``min_h_host`` is ``min_h`` as a Python float."""
        h = np.array([volume.level_spacing(l) for l in range(volume.num_levels)], dtype=np.float64)
        self.min_h_host = float(h.min())
        lo, hi = volume.bounds
        self.bounds_lo, self.bounds_hi = self._point(lo), self._point(hi)
        self.anchor = self._point(volume.anchor)
        # Per level 8 floats, h then 1 / h, each padded to 4: one packet load reads either.
        geom = np.zeros((volume.num_levels, 2, 4), dtype=np.float32)
        geom[:, 0, :3], geom[:, 1, :3] = h, 1.0 / h
        self.level_geom = self._floats(geom.ravel())
        self.min_h = self._scalar(self.min_h_host)
        self.step_eps = self._scalar(tol.STEP_EPS_CELLS * self.min_h_host)
        self.layer_offset = self._scalar(tol.LAYER_OFFSET_CELLS * self.min_h_host)

    def level_h(self, level, active=True):
        """Cell size of level ``level`` (``Array3f``, world units; one packet load)."""
        g = dr.gather(self.m.Array4f, self.level_geom, 2 * self.m.UInt32(level), active)
        return self.m.Array3f(g.x, g.y, g.z)

    def level_inv_h(self, level, active=True):
        """Inverse cell size of level ``level`` (``Array3f``, per world unit)."""
        g = dr.gather(self.m.Array4f, self.level_geom, 2 * self.m.UInt32(level) + 1, active)
        return self.m.Array3f(g.x, g.y, g.z)

    def level_bricks(self, level, active=True):
        """``(lo, table_offset, dims)`` of level ``level``'s brick table (two packet loads):
        its first cell (``Array3i``, level index space), where its dense table starts, and
        the table's size in bricks (``Array3u``)."""
        m = self.m
        a = dr.gather(m.Array4u, self.level_table, 2 * m.UInt32(level), active)
        b = dr.gather(m.Array4u, self.level_table, 2 * m.UInt32(level) + 1, active)
        lo = m.Array3i(*(dr.reinterpret_array(m.Int32, c) for c in (a.x, a.y, a.z)))
        return lo, a.w, m.Array3u(b.x, b.y, b.z)

    def _point(self, xyz):
        return opaque_point(self.m, xyz)

    def _scalar(self, value: float):
        return opaque_floats(self.m, [value])

    def arrays(self, basis: bool, color: bool = False) -> list:
        """The value arrays a reconstruction reads: brick pools of leaf values for the basis
        blend, the grids' raw values for the finest level; the field, then the colour field.
        The finest level's of a volume prepared without its values are an error."""
        if basis:
            return [self.brick_values] + ([self.brick_colors] if color else [])
        return [self._values()] + ([self.color_values] if color else [])

    def _values(self):
        """:attr:`values`, or one error where the preparation kept none."""
        if self.values is None:
            raise AMRError(f"{self.volume.source_prefix()}this asks for the field's values "
                           f"(the finest-level reconstruction reads them), which this "
                           f"preparation did not keep (it was made for the basis blend alone: "
                           f"brick pools only); prepare the file again with keep_fields")
        return self.values

    def _set_bricks(self, parts, pools):
        """The device arrays of :func:`build_bricks`'s ``(parts, pools)``: per level
        ``(lo, dims, table, n)`` (see :func:`brick_table`) and the pools of the field and
        colour field (one pool when they are the same field): device arrays as
        :func:`build_bricks` fills them, or host arrays read from a snapshot (aligned, so
        Dr.Jit maps their memory without a copy). Kept as :attr:`host_bricks` (what a
        snapshot writes; a device pool is copied to the host only then)."""
        self.host_bricks = (parts, pools)
        self.brick_table = self._uints(np.concatenate([p[2] for p in parts]))
        # Per level 8 uints: lo (int32 bits) and the table offset, the table's dims and 0.
        table = np.zeros((len(parts), 2, 4), dtype=np.uint32)
        table[:, 0, :3] = np.array([p[0] for p in parts], dtype=np.int32).view(np.uint32)
        table[:, 0, 3] = np.cumsum([0] + [p[2].size for p in parts[:-1]])
        table[:, 1, :3] = np.array([p[1] for p in parts], dtype=np.uint32)
        self.level_table = self._uints(table.ravel())
        self.brick_values = self.m.Float(pools[0])
        self.brick_colors = self.brick_values if len(pools) == 1 else self.m.Float(pools[1])
        self.num_bricks = sum(int(p[3]) for p in parts)

    def _floats(self, a):
        return device_array(self.m.Float, a, np.float32)

    def _uints(self, a):
        return device_array(self.m.UInt32, a, np.uint32)

    def node_ranges(self, basis: bool) -> np.ndarray:
        """Per-node value range of the field for one reconstruction, ``lo, hi`` side by side
        (float32, host; computed on first use: each costs a pass over the cells). A node with
        no data has ``(+inf, -inf)``. The leaves' ranges are those of
        :meth:`KDTree.leaf_ranges <mi_amr.core.kdtree.KDTree.leaf_ranges>`, taken on the device
        (:mod:`mi_amr.kernels.ranges`). Kept in :attr:`host_ranges` (a snapshot may bring them);
        :attr:`on_new_ranges` (if set) is told of each one computed. The kernels read them
        through :meth:`node_search`."""
        key = "basis" if basis else "finest"
        if key not in self.host_ranges:
            if dr.flag(dr.JitFlag.SymbolicScope):
                # First asked for while a symbolic loop is traced, where no kernel may run:
                # the NumPy twin (the same float32 ranges, tests/test_device_prep.py).
                self._values()
                leaf = self.tree.leaf_ranges(self.field, key)
            elif basis and self.values is None:     # (the same numbers, from the pools)
                leaf = ranges.brick_leaf_ranges(self.m, self.tree, self)
            else:
                leaf = ranges.leaf_ranges(self.m, self.tree, self._values(), self.field, key)
            rlo, rhi = self.tree.node_ranges(*leaf)
            self.host_ranges[key] = np.stack([rlo, rhi], axis=1).astype(np.float32).ravel()
            if self.on_new_ranges is not None:
                self.on_new_ranges(key, self.host_ranges[key])
        return self.host_ranges[key]

    def node_search(self, basis: bool):
        """What a step of the leaf search reads of a node: :data:`NODE_RECORDS` records of 4
        uints per node, each one packet load -- the node's own (its code, its split as float32
        bits, and the lo and hi of its value range for one reconstruction as float32 bits; see
        :meth:`node_ranges`), then its lower and upper child's (zeros for a leaf), so a search
        can go down through a node to its child with the loads it started (see
        :class:`~mi_amr.kernels.config.SearchPlan`)."""
        key = "basis" if basis else "finest"
        if key not in self._search:
            bounds = self.node_ranges(basis)   # (first: its temporaries are freed)
            # Made in aligned memory and mapped, not copied: on 10^8 cells it is 0.16 GB.
            n = len(self._host_code_split)
            table = aligned_empty(n * NODE_RECORDS * 4, np.uint32).reshape(n, NODE_RECORDS, 4)
            own = table[:, 0]
            own[:, :2] = self._host_code_split
            own[:, 2:] = bounds.reshape(-1, 2).view(np.uint32)
            table[:, 1:] = 0
            inner = np.flatnonzero((own[:, 0] & 3) != 3)
            first = (own[inner, 0] >> 2).astype(np.int64)
            table[inner, 1] = own[first]
            table[inner, 2] = own[first + 1]
            self._search[key] = mapped_array(self.m.UInt32, table.reshape(-1), np.uint32)
        return self._search[key]

    def active_box(self, isovalues):
        """``(lo, hi)``, opaque points (volume world): a box holding every leaf whose value
        range (the basis blend's, :meth:`node_ranges`) may hold one of ``isovalues`` (host
        floats), widened by a finest cell; the empty box ``(+inf, -inf)`` where no leaf does.
        A continuous field crosses an isovalue only in such leaves, so the exact march may
        clip its rays to this box (:func:`~mi_amr.kernels.config.clip_box`). The ranges are
        taken :data:`~mi_amr.tolerances.ACTIVE_BOX_RANGE_REL` wider than the search reads
        them, so a leaf whose float32 range only just misses an isovalue is kept. The last
        :data:`ACTIVE_BOXES` boxes are kept (a frame of an unchanged isovalue costs a lookup)."""
        def make(iso):
            lo, hi = active_box_host(self.tree, self.node_ranges(True), iso, self.min_h_host)
            return self._point(lo), self._point(hi)

        return _kept(self._boxes, isovalues, make)

    def start_table(self, isovalues, on_device: bool = True):
        """The :class:`~mi_amr.kernels.starts.StartTable` of the leaves :meth:`active_box`
        holds for ``isovalues`` (the last :data:`ACTIVE_BOXES` are kept): its cells' descents
        on the device (:func:`~mi_amr.kernels.starts.start_table_device`), on the host where
        the tree's lattice numbers exceed int32, no leaf is active or a symbolic loop is being
        traced, or not ``on_device`` (a scalar variant: once a kernel has run inside its
        render loop, Mitsuba no longer finds the Python integrator's ``sample``). A kernel
        launched while a frame is traced would change the frame's kernel: the integrator asks
        before the trace (``render``)."""
        def make(iso):
            ranges = self.node_ranges(True)
            active = active_leaves(self.tree, ranges, iso)
            searched = node_holds(ranges, iso, widen=0.0)
            # (Where a symbolic loop is traced no kernel may run: the host's twin then.)
            if len(active) and on_device and self.tree.lattice_int is np.int32 and \
                    not dr.flag(dr.JitFlag.SymbolicScope):
                lo, cell, dims = starts.table_frame(self.tree, active)
                nodes = starts.start_table_device(self.m, self._descent(~searched),
                                                  (lo, cell, dims))
            else:
                lo, cell, dims, host = starts.start_table_host(self.tree, active, ~searched)
                nodes = self._uints(host)
            h = self.tree.h_fine
            return starts.StartTable(
                nodes=nodes, lo=self._point(self.volume.anchor + lo * h),
                inv_cell=self._point(1.0 / (cell * h)), dims=self._point(dims))

        return _kept(self._tables, isovalues, make)

    def _descent(self, stop) -> "starts.Descent":
        """The tree as a start table's descents read it, stopping where ``stop`` (a bool per
        node); its split planes in lattice units are put on the device at the first call."""
        if self._lattice_split is None:
            self._lattice_split = device_array(self.m.Int32, self.tree.lattice_node_split,
                                               np.int32)
        return starts.Descent(self.node_code_split, self._lattice_split,
                              device_array(self.m.Bool, stop, np.bool_))


def field_values(m, volume, name: str):
    """Field ``name`` of every grid of ``volume``, grid after grid, as a device ``m.Float``:
    the aligned float32 buffer the grids' arrays are views of when there is one
    (:func:`mi_amr.core.levels.volume_values`: no copy), else a float32 copy written once."""
    arrays = [g.fields[name] for g in volume.grids]
    flat = levels.volume_values(volume, name)
    if flat is not None and (flat.dtype != np.float32 or flat.ctypes.data % ALIGN):
        flat = None
    if flat is None:
        flat = aligned_empty(sum(a.size for a in arrays), np.float32)
        if arrays:
            np.concatenate([a.ravel() for a in arrays], out=flat, casting="same_kind")
    return m.Float(flat)


def build_bricks(m, volume, values):
    """``(parts, pools)``: per level, the *leaf* cells of all its grids gathered into bricks
    of ``BRICK_N^3`` values (NaN where the level has no leaf cell or the value is not
    finite), found through a dense table of the level's bounding box (:func:`brick_table`),
    and a pool per array of ``values`` (the field, and the colour field where it is another;
    as :func:`field_values` gives them). Brick ``b`` of a level holds the cells ``lo + b *
    BRICK .. lo + b * BRICK + BRICK`` (inclusive) on each axis, so the 8 corners of any dual
    cell lie in the brick of its lower corner: one table lookup finds them whichever grids
    hold them. This is what the basis reconstruction reads."""
    parts, count = [], 0
    for level in range(volume.num_levels):
        parts.append(brick_table(volume, level, count))
        count += parts[-1][3]
    return parts, bricks.build_pools(m, volume, list(values), parts, count)


def _kept(cache: dict, isovalues, make):
    """``make(iso)`` for the float32 isovalues ``iso``, kept in ``cache`` by their bytes with
    the last :data:`ACTIVE_BOXES` others."""
    iso = np.asarray(isovalues, dtype=np.float32).ravel()
    key = iso.tobytes()
    if key not in cache:
        while len(cache) >= ACTIVE_BOXES:
            cache.pop(next(iter(cache)))
        cache[key] = make(iso)
    return cache[key]


# How many active boxes (one per set of isovalues) a DeviceVolume keeps.
ACTIVE_BOXES = 8


def active_box_host(tree, ranges, isovalues, pad: float):
    """:meth:`DeviceVolume.active_box` on the host: ``(lo, hi)`` float64 3-vectors from the
    per-node ``ranges`` (``lo, hi`` side by side, float32) of ``tree``."""
    active = active_leaves(tree, ranges, isovalues)
    if len(active) == 0:
        return np.full(3, np.inf), np.full(3, -np.inf)
    lo, hi = tree.node_boxes(active)
    return lo.min(axis=0) - pad, hi.max(axis=0) + pad


def active_leaves(tree, ranges, isovalues) -> np.ndarray:
    """The kd nodes of the leaves whose range (``ranges``, see :func:`active_box_host`) may
    hold one of ``isovalues`` (:func:`node_holds`)."""
    leaf = (tree.node_code & 3) == 3
    return np.flatnonzero(leaf & node_holds(ranges, isovalues))


def node_holds(ranges, isovalues, widen: float = tol.ACTIVE_BOX_RANGE_REL) -> np.ndarray:
    """Whether each kd node's range (``ranges``), widened by ``widen`` times its largest
    magnitude, holds one of ``isovalues`` (float32 numbers): with ``widen`` 0 exactly the
    nodes the kernels' search does not skip (float32 comparisons, exact in float64)."""
    r = np.asarray(ranges, dtype=np.float64).reshape(-1, 2)
    iso = np.asarray(isovalues, dtype=np.float64)
    with np.errstate(invalid="ignore"):      # an empty range (+inf, -inf) holds nothing
        slack = np.nan_to_num(widen * np.maximum(np.abs(r[:, 0]), np.abs(r[:, 1])))
        holds = (r[:, :1] - slack[:, None] <= iso) & (iso <= r[:, 1:] + slack[:, None])
    return holds.any(axis=1)
