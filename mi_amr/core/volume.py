"""The AMR data model: a hierarchy of rectangular grids of cell-centred values.

Coordinate conventions used throughout mi_amr:

* **World space** is the space the grids are given in (``origin`` and ``spacing`` are world
  units). The integrator's ``to_world`` places this space in a Mitsuba scene.
* A grid is a box of ``shape = (nx, ny, nz)`` cells; array index ``[i, j, k]`` is ``x, y, z``.
  Values are **cell-centred**: cell ``(i, j, k)`` has its centre at
  ``origin + (i + 0.5, j + 0.5, k + 0.5) * spacing`` and covers
  ``[origin + (i, j, k) * spacing, origin + (i + 1, j + 1, k + 1) * spacing]``.
* Level 0 is the coarsest. Level ``l`` cells are ``ratio`` times smaller than level ``l - 1``
  cells (``ratio`` is 2 or 4, the same on all axes, and may differ from level to level).
* All grids sit on one **lattice**: level-0 grids are whole numbers of level-0 cells apart, a fine
  grid starts and ends on a cell face of the level above. Integer **index boxes** of a grid are its
  cells in its level's lattice, counted from the ``anchor`` (the origin of the first level-0 grid).
* A cell is a **leaf** when no cell of the next finer level covers it; the basis reconstruction
  uses leaf cells only.
"""

from __future__ import annotations

import contextlib
import gc
import itertools
import math
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np

from mi_amr.core import extremes, levels
from mi_amr.core.boxes import intersection_volume, overlap_pairs
from mi_amr.core.buffers import aligned_full
from mi_amr.errors import ALLOW_NONFINITE_HOW, AMRError, shown

ALLOWED_RATIOS = (2, 4)
# How far (in cells) a grid corner may sit from the lattice and still count as aligned: float
# rounding of origins such as 0.1 * k must pass, a real misalignment of a quarter cell must not.
LATTICE_TOLERANCE = 1e-3
# How far (in cells of the level above) a grid may lie from the lattice anchor. Index boxes are
# int64 and the kd-tree scales them to the finest level (4^11 = 2^22 at most), so 2^40 leaves
# room; beyond it the cast to integers overflows and a grid would land somewhere else.
MAX_LATTICE_OFFSET = float(2 ** 40)
# Leaf masks (_leaf_masks): covered boxes of up to MASK_BOX_CELLS cells are cleared together
# through flat cell indices, in blocks of about MASK_CHUNK_CELLS cells (temporaries that stay
# small reuse memory); bigger boxes are cleared one at a time with a slice.
MASK_BOX_CELLS = 4096
# Blocks (levels.LevelBlocks) of a level up to which its overlaps are found through them (which
# its level table then reuses); a level of more, or of blocks of one cell, is checked box
# against box.
CHECK_BLOCKS = 1 << 22
# Field values are checked for NaN/Inf in blocks of grids of about this many cells.
FINITE_CHECK_CELLS = 1 << 16
MASK_CHUNK_CELLS = 1 << 17


@dataclass(frozen=True, eq=False)
class Grid:
    """One rectangular patch of cells at one refinement level (see the module docstring).

    ``origin`` is the world position of the lower corner, ``spacing`` the cell size per axis in
    world units, ``shape`` the number of cells per axis and ``fields`` maps a name to a
    cell-centred array of that shape. Item access (``grid["level"]``) works too, so code written
    for the mapping form accepted by :meth:`AMRVolume.from_grids` reads records unchanged.
    """

    level: int
    origin: tuple
    spacing: tuple
    shape: tuple
    fields: Mapping[str, np.ndarray]

    @property
    def lo(self) -> np.ndarray:
        """World position of the lower corner, shape ``(3,)``."""
        return np.asarray(self.origin, dtype=np.float64)

    @property
    def hi(self) -> np.ndarray:
        """World position of the upper corner, shape ``(3,)``."""
        return self.lo + np.asarray(self.shape) * np.asarray(self.spacing)

    @property
    def num_cells(self) -> int:
        nx, ny, nz = self.shape          # plain ints: np.prod of a tuple costs microseconds
        return int(nx) * int(ny) * int(nz)

    def cell_centers(self):
        """World coordinates of the cell centres along x, y and z (three 1-D arrays)."""
        return tuple(self.origin[a] + (np.arange(self.shape[a]) + 0.5) * self.spacing[a]
                     for a in range(3))

    def as_dict(self) -> dict:
        return {"level": self.level, "origin": self.origin, "spacing": self.spacing,
                "fields": dict(self.fields)}

    def __getitem__(self, key):
        if key not in ("level", "origin", "spacing", "shape", "fields"):
            raise KeyError(key)
        return getattr(self, key)

    def describe(self, index: int) -> str:
        """Short label for messages: ``grid 3 (level 1, origin (0, 0.5, 0))``."""
        origin = ", ".join(f"{x:g}" for x in self.origin)
        return f"grid {index} (level {self.level}, origin ({origin}))"


class AMRVolume:
    """A validated AMR hierarchy. Build it with :meth:`from_grids` (or :func:`mi_amr.load`).

    ``grids`` is the tuple of :class:`Grid` records, in the order given, so
    ``AMRVolume.from_grids(vol.grids)`` rebuilds the same volume.
    """

    def __init__(self, grids: tuple, *, allow_nonfinite: bool, source: str | None,
                 index_lo: np.ndarray, ratios: tuple, anchor: np.ndarray):
        # Private: from_grids() validates and computes the lattice data passed in here.
        self.grids = grids
        self.allow_nonfinite = allow_nonfinite
        self.source = source
        self.ratios = ratios
        self.anchor = anchor
        self._index_lo = index_lo
        self._leaf_flat = None   # every grid's leaf mask, flat, grid after grid (_leaf_masks)
        self._partly = None
        self._columns = None     # per-grid arrays (grid_columns), built once
        self._nesting = None     # per finer level, its (coarser, finer) grid pairs that overlap
        self._ranges = {}
        # Work derived from this volume that is kept with it: the level tables and flat level
        # values (mi_amr.core.levels), and mi_amr.trace's preparations of it by field, leaf
        # size and backend (mi_amr.kernels.trace).
        self.level_caches = levels.LevelCaches()
        self.trace_preparations = {}

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_grids(cls, grids: Iterable, *, allow_nonfinite: bool = False,
                   source: str | None = None) -> "AMRVolume":
        """Validate a hierarchy and build the volume.

        ``grids`` is a sequence of mappings (or :class:`Grid` records) with ``level`` (int >= 0),
        ``origin`` (3 floats, world), ``spacing`` (a float or 3 floats, world) and ``fields``
        (name -> array ``(nx, ny, nz)``). ``allow_nonfinite=True`` accepts NaN/Inf values and
        treats those cells as *missing data*: they get no weight in the reconstruction and are
        left out of value ranges. ``source`` (a file name) prefixes error messages.

        Raises :class:`AMRError` naming the offending grids for: ``grids`` that is not a
        sequence, an empty hierarchy, a malformed record, zero-size grids, fields that are
        missing or disagree in shape, non-finite values, levels with a gap or mixed spacings,
        refinement ratios other than 2 or 4, grids off the lattice or too far from it for
        integer cell indices (:data:`MAX_LATTICE_OFFSET`), overlapping grids of one level, and
        fine grids outside the coarser level.
        """
        prefix = f"{source}: " if source else ""
        if isinstance(grids, (str, bytes, Mapping)) or not isinstance(grids, Iterable):
            raise AMRError(f"{prefix}grids must be a sequence of grid records (mappings with "
                           f"level, origin, spacing and fields), got {type(grids).__name__}")
        with _collector_paused():
            records = [_parse_plain(g) or _parse_record(g, i, prefix)
                       for i, g in enumerate(grids)]
        if not records:
            raise AMRError(f"{prefix}empty hierarchy: at least one level-0 grid is needed")
        _check_fields(records, prefix, allow_nonfinite)
        return cls._checked(records, _record_columns(records), allow_nonfinite, source)

    @classmethod
    def from_columns(cls, columns: Mapping, fields: Mapping, flat: Mapping, *,
                     allow_nonfinite: bool = False, source: str | None = None) -> "AMRVolume":
        """:meth:`from_grids` for a hierarchy a reader holds as columns: ``columns`` has
        ``level`` ``(G,)`` integers, ``origin`` and ``spacing`` ``(G, 3)`` numbers (world) and
        ``shape`` ``(G, 3)`` integers >= 1; ``fields`` maps a name to its ``G`` arrays (one
        per grid, of its shape); ``flat`` maps a name to arrays that together hold every value
        of the field (a reader's level buffers), where its values are checked for NaN/Inf at
        once. The same volume as ``from_grids`` of the same records, with the same checks of
        the hierarchy; without the per-grid parsing of records of any type. Where a column is
        not plain (a negative level, a non-finite origin or spacing, a spacing <= 0, a field
        that is not of floats) or a value is not finite where that is not allowed, it is
        :meth:`from_grids` that runs, so that its messages name the grid."""
        level = np.asarray(columns["level"])
        origin = np.asarray(columns["origin"], dtype=np.float64)
        spacing = np.asarray(columns["spacing"], dtype=np.float64)
        shape = np.asarray(columns["shape"], dtype=np.int64)
        names = list(fields)
        records = None
        if (len(level) > 0 and level.dtype.kind in "iu" and names and level.min() >= 0 and
                np.isfinite(origin).all() and np.isfinite(spacing).all() and
                (spacing > 0).all()):
            records = _column_records(level, (origin, spacing, shape), fields)
        if records is None or not (allow_nonfinite or _all_finite_flat(_flat_parts(flat))):
            return cls.from_grids(
                [{"level": int(level[i]), "origin": tuple(origin[i].tolist()),
                  "spacing": tuple(spacing[i].tolist()),
                  "fields": {n: fields[n][i] for n in names}} for i in range(len(level))],
                allow_nonfinite=allow_nonfinite, source=source)
        return cls._checked(records, {"level": level.astype(np.int64), "origin": origin,
                                      "spacing": spacing, "shape": shape},
                            allow_nonfinite, source)

    @classmethod
    def _checked(cls, records, columns, allow_nonfinite: bool, source) -> "AMRVolume":
        """The volume of parsed ``records`` (and their ``columns``) once the hierarchy's
        checks pass: levels, lattice, overlap and nesting."""
        prefix = f"{source}: " if source else ""
        ratios = _check_levels(records, columns, prefix)
        anchor, index_lo = _check_lattice(records, columns, ratios, prefix)
        nesting, blocks = _check_overlap_and_nesting(records, columns, index_lo, ratios, prefix)
        volume = cls(tuple(records), allow_nonfinite=allow_nonfinite, source=source,
                     index_lo=index_lo, ratios=ratios, anchor=anchor)
        volume._nesting = nesting
        volume.level_caches.blocks = blocks        # (the level tables take them)
        # Levels are now known to be 0..L-1; the volume keeps the columns (grid_columns).
        volume._columns = {**columns, "level": columns["level"].astype(np.int32),
                           "offset": _cell_offsets(columns["shape"])}
        return volume

    def with_fields(self, new_fields: Mapping[str, Sequence[np.ndarray]]) -> "AMRVolume":
        """A volume with extra (or replaced) fields: ``{name: [array per grid]}``.

        The existing arrays are shared, not copied; the hierarchy is not validated again.
        """
        for name, arrays in new_fields.items():
            if len(arrays) != len(self.grids):
                raise AMRError(f"field '{name}': {len(arrays)} arrays for {len(self.grids)} grids")
            for i, (g, arr) in enumerate(zip(self.grids, arrays)):
                if tuple(arr.shape) != g.shape:
                    raise AMRError(f"field '{name}' of {g.describe(i)} has shape {arr.shape}, "
                                   f"expected {g.shape}")
        grids = tuple(Grid(g.level, g.origin, g.spacing, g.shape,
                           {**g.fields, **{n: np.asarray(a[i]) for n, a in new_fields.items()}})
                      for i, g in enumerate(self.grids))
        out = AMRVolume(grids, allow_nonfinite=self.allow_nonfinite, source=self.source,
                        index_lo=self._index_lo, ratios=self.ratios, anchor=self.anchor)
        out._leaf_flat, out._partly = self._leaf_flat, self._partly
        out._columns, out._nesting = self._columns, self._nesting      # the same hierarchy
        levels.adopt_caches(out, self)
        return out

    def select_fields(self, names: Sequence[str]) -> "AMRVolume":
        """A volume holding only the named fields (arrays shared, not copied)."""
        missing = [n for n in names if n not in self.field_names]
        if missing:
            raise AMRError(f"{self.source_prefix()}unknown field(s) {missing}; "
                           f"available: {list(self.field_names)}")
        grids = tuple(Grid(g.level, g.origin, g.spacing, g.shape, {n: g.fields[n] for n in names})
                      for g in self.grids)
        out = AMRVolume(grids, allow_nonfinite=self.allow_nonfinite, source=self.source,
                        index_lo=self._index_lo, ratios=self.ratios, anchor=self.anchor)
        out._leaf_flat, out._partly = self._leaf_flat, self._partly
        out._columns, out._nesting = self._columns, self._nesting      # the same hierarchy
        levels.adopt_caches(out, self)
        return out

    def same_hierarchy(self, other: "AMRVolume") -> bool:
        """Whether ``other`` has exactly this volume's grids, grid for grid in the same order:
        the same levels, origins, spacings (world units, compared exactly) and shapes, whatever
        fields they hold. What is made from the hierarchy alone (leaf masks, level tables, the
        kd-tree) is then the same for both."""
        if other is self:
            return True
        if len(self.grids) != len(other.grids):
            return False
        mine, theirs = self.grid_columns(), other.grid_columns()
        return all(np.array_equal(mine[k], theirs[k])
                   for k in ("level", "shape", "origin", "spacing"))

    def adopt_hierarchy(self, other: "AMRVolume") -> bool:
        """Take the leaf masks and level tables that ``other``, a volume of the
        :meth:`same_hierarchy` (another time step of unchanged grids), has made, instead of
        making them again; True where it is one (nothing is taken otherwise)."""
        if not self.same_hierarchy(other):
            return False
        if self._leaf_flat is None and other._leaf_flat is not None:
            self._leaf_flat, self._partly = other._leaf_flat, other._partly
        if self._nesting is None:
            self._nesting = other._nesting
        levels.adopt_index(self, other)
        return True

    def drop_level_fields(self, level: int, names: Sequence[str]) -> None:
        """Drop fields ``names`` from every grid of ``level`` and from the level's cached flat
        values, so that their memory is freed where nothing else holds it. The volume is left
        holding those fields on some levels only: for a volume given up to
        :func:`mi_amr.core.derive.derive` (``consume``), which drops every level's."""
        for i in np.flatnonzero(self.levels == level):
            for name in names:
                self.grids[i].fields.pop(name, None)
        levels.forget_level_values(self, level, names)

    # ------------------------------------------------------------------ hierarchy queries
    @property
    def field_names(self) -> tuple:
        return tuple(self.grids[0].fields)

    @property
    def num_levels(self) -> int:
        return len(self.ratios) + 1

    @property
    def num_cells(self) -> int:
        columns = self.grid_columns()
        return int(columns["offset"][-1]) + int(np.prod(columns["shape"][-1]))

    @property
    def nbytes(self) -> int:
        """Bytes held by the field arrays."""
        return sum(a.nbytes for g in self.grids for a in g.fields.values())

    def level_spacing(self, level: int) -> np.ndarray:
        """Cell size of ``level`` per axis (world units), shape ``(3,)``."""
        first = np.flatnonzero(self.grid_columns()["level"] == level)[:1]
        if len(first):
            return np.asarray(self.grids[first[0]].spacing, dtype=np.float64)
        raise AMRError(f"{self.source_prefix()}no level {level}; levels are 0..{self.num_levels - 1}")

    @property
    def bounds(self):
        """World-space bounding box of all grids: ``(lo, hi)``, each shape ``(3,)``."""
        lo, hi = self.grid_boxes()
        return lo.min(axis=0), hi.max(axis=0)

    @property
    def levels(self) -> np.ndarray:
        """Level of every grid, shape ``(G,)``."""
        return self.grid_columns()["level"].copy()

    def grid_boxes(self):
        """World-space boxes of all grids: ``(lo, hi)``, each shape ``(G, 3)``."""
        lo = self.grid_columns()["origin"].copy()
        hi = lo + self.shapes() * self.spacings()
        return lo, hi

    def spacings(self) -> np.ndarray:
        """Cell size of every grid, shape ``(G, 3)`` (world units)."""
        return self.grid_columns()["spacing"].copy()

    def shapes(self) -> np.ndarray:
        """Cells per axis of every grid, shape ``(G, 3)`` int64."""
        return self.grid_columns()["shape"].copy()

    def cell_offsets(self) -> np.ndarray:
        """Where each grid's cells start in the flat array of all cells (grid after grid, each
        raveled in C order), shape ``(G,)`` int64."""
        return self.grid_columns()["offset"].copy()

    def index_boxes(self):
        """Integer index boxes ``(lo, hi)`` of all grids, each ``(G, 3)`` int64, half-open, in
        cells of each grid's own level counted from :attr:`anchor`."""
        return self._index_lo, self._index_lo + self.grid_columns()["shape"]

    def grid_columns(self) -> dict:
        """Per-grid arrays gathered from the records once (the records never change): level
        ``(G,)`` int32, origin and spacing ``(G, 3)`` float64 (world), shape ``(G, 3)`` int64
        and the offset of each grid's cells in the flat array of all cells ``(G,)`` int64.
        The arrays are this volume's own, shared: read them, never write (the accessors above
        give copies)."""
        if self._columns is None:
            shape = np.array([g.shape for g in self.grids], dtype=np.int64).reshape(-1, 3)
            self._columns = {
                "level": np.array([g.level for g in self.grids], dtype=np.int32),
                "origin": np.array([g.origin for g in self.grids], dtype=np.float64),
                "spacing": np.array([g.spacing for g in self.grids], dtype=np.float64),
                "shape": shape,
                "offset": _cell_offsets(shape)}
        return self._columns

    def leaf_mask(self, grid: int) -> np.ndarray:
        """Boolean array of the grid's shape: True where no finer cell covers the cell."""
        flat = self.leaf_mask_flat()
        g = self.grids[grid]
        start = int(self.grid_columns()["offset"][grid])
        return flat[start:start + g.num_cells].reshape(g.shape)

    def leaf_mask_flat(self) -> np.ndarray:
        """Every grid's :meth:`leaf_mask`, raveled and concatenated grid after grid (offsets:
        :meth:`cell_offsets`), one boolean array over all cells."""
        if self._leaf_flat is None:
            self._leaf_flat, self._partly = _leaf_masks(self)
        return self._leaf_flat

    def partly_covered(self) -> np.ndarray:
        """Boolean per grid: True where some of the grid's cells are covered by a finer grid
        (its leaf mask is not all True)."""
        if self._leaf_flat is None:
            self._leaf_flat, self._partly = _leaf_masks(self)
        return self._partly

    def num_leaf_cells(self) -> int:
        return int(np.count_nonzero(self.leaf_mask_flat()))

    def value_range(self, field: str, grid: int | None = None):
        """``(min, max)`` of the finite values of ``field``, over all grids or one grid.

        A grid (or volume) with no finite value gives ``(nan, nan)``.
        """
        if field not in self.field_names:
            raise AMRError(f"{self.source_prefix()}unknown field '{field}'; "
                           f"available: {list(self.field_names)}")
        if field not in self._ranges:
            self._ranges[field] = np.array([extremes.finite_range((g.fields[field],))
                                            for g in self.grids])
        ranges = self._ranges[field]
        if grid is not None:
            if not 0 <= grid < len(self.grids):
                raise AMRError(f"{self.source_prefix()}no grid {grid}; grids are 0..{len(self.grids) - 1}")
            return tuple(float(x) for x in ranges[grid])
        with np.errstate(all="ignore"):
            if np.all(np.isnan(ranges[:, 0])):
                return (math.nan, math.nan)
            return float(np.nanmin(ranges[:, 0])), float(np.nanmax(ranges[:, 1]))

    # ------------------------------------------------------------------ output
    def summary(self) -> str:
        """Human-readable description: levels, grids, cells, memory, field ranges."""
        lo, hi = self.bounds
        lines = []
        if self.source:
            lines.append(f"source: {self.source}")
        lines.append(f"AMR volume: {self.num_levels} level(s), {len(self.grids):,} grid(s), "
                     f"{self.num_cells:,} cells ({self.num_leaf_cells():,} leaf cells), "
                     f"{_format_bytes(self.nbytes)} of field data")
        lines.append(f"bounds: ({', '.join(f'{x:g}' for x in lo)}) .. "
                     f"({', '.join(f'{x:g}' for x in hi)})")
        levels = self.levels
        spacings = ["(" + ", ".join(f"{x:.4g}" for x in self.level_spacing(level)) + ")"
                    for level in range(self.num_levels)]
        # The spacing column is as wide as its longest entry, so the columns after it line up.
        width = max(len("spacing"), *(len(s) for s in spacings)) + 2
        lines.append(f"{'level':>5}  {'ratio':>5}  {'spacing':<{width}}{'grids':>8}{'cells':>14}"
                     f"{'leaf cells':>14}")
        for level, spacing in enumerate(spacings):
            ids = np.flatnonzero(levels == level)
            cells = sum(self.grids[i].num_cells for i in ids)
            leaf = sum(int(self.leaf_mask(i).sum()) for i in ids)
            ratio = "-" if level == 0 else str(self.ratios[level - 1])
            lines.append(f"{level:>5}  {ratio:>5}  {spacing:<{width}}{len(ids):>8,}{cells:>14,}"
                         f"{leaf:>14,}")
        lines.append("fields:")
        for name in self.field_names:
            vmin, vmax = self.value_range(name)
            dtype = self.grids[0].fields[name].dtype
            lines.append(f"  {name:<20} {str(dtype):<8} [{vmin:.6g}, {vmax:.6g}]")
        if self.allow_nonfinite:
            lines.append("non-finite values allowed (treated as missing data)")
        return "\n".join(lines)

    def save(self, path, *, overwrite: bool = False) -> None:
        """Write the volume to one ``.npz`` file (see :mod:`mi_amr.core.npz`)."""
        from mi_amr.core.npz import save
        save(self, path, overwrite=overwrite)

    def __repr__(self) -> str:
        return (f"AMRVolume({len(self.grids)} grids, {self.num_levels} levels, "
                f"{self.num_cells} cells, fields={list(self.field_names)})")

    def source_prefix(self) -> str:
        """``"<source>: "`` to begin a message about this volume (empty without a source)."""
        return f"{self.source}: " if self.source else ""


def _flat_parts(flat: Mapping):
    """Every array of the mapping ``flat`` (name -> list of arrays)."""
    for arrays in flat.values():
        yield from arrays


def _column_records(level, boxes, fields) -> list | None:
    """The :class:`Grid` records of :meth:`AMRVolume.from_columns`, or None where a field's
    array is not what :func:`_parse_plain` takes (C-contiguous 3-D floats of its grid's
    shape)."""
    origin, spacing, shape = boxes
    names = list(fields)
    shapes = [tuple(row) for row in shape.tolist()]
    for n in names:
        if any(a.dtype.kind != "f" or not a.flags.c_contiguous or a.shape != sh
               for a, sh in zip(fields[n], shapes)) or len(fields[n]) != len(shapes):
            return None
    with _collector_paused():
        return [Grid(lv, o, h, sh, dict(zip(names, arrays)))
                for lv, o, h, sh, arrays in zip(level.tolist(), map(tuple, origin.tolist()),
                                                map(tuple, spacing.tolist()), shapes,
                                                zip(*(fields[n] for n in names)))]


def _all_finite_flat(arrays, block: int = FINITE_CHECK_CELLS) -> bool:
    """Whether every value of ``arrays`` is finite, each tested :data:`FINITE_CHECK_CELLS`
    values at a time (small temporaries that stay in cache, not one of a level's size)."""
    for a in arrays:
        flat = a.reshape(-1)
        for at in range(0, flat.size, block):
            if not np.isfinite(flat[at:at + block]).all():
                return False
    return True


def _cell_offsets(shape) -> np.ndarray:
    """Where each grid's cells start in the flat array of all cells, for grid shapes
    ``(G, 3)``: ``(G,)`` int64."""
    sizes = np.prod(shape, axis=1)
    return np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)


# ---------------------------------------------------------------------- validation helpers

@contextlib.contextmanager
def _collector_paused():
    """Pause Python's cyclic garbage collector (if it runs) while records are parsed: the
    collections that the many new Grid objects and dicts trigger traverse every object alive,
    the caller's records included, and took a third of the parsing time for 10^5 grids. The
    records hold no cycles, so nothing is left for the collector."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


# Exact types the fast path (_parse_plain) reads as numbers; anything else takes the full checks.
_PLAIN_NUMBERS = (float, int, np.float64)


def _parse_plain(g) -> Grid | None:
    """The :class:`Grid` of a record in the common plain form, or None to run the full checks
    of :func:`_parse_record` (which then name what is wrong): a ``dict`` (or a Grid) with an
    ``int`` level >= 0, origin and spacing as 3 finite plain numbers (spacing > 0, or one
    number) and a ``dict`` of C-contiguous real 3-D ``ndarray`` fields of one non-empty shape.
    Gives the same Grid as :func:`_parse_record` for those, several times faster."""
    kind = type(g)
    if kind is dict:
        try:
            level, origin, spacing, fields = g["level"], g["origin"], g["spacing"], g["fields"]
        except KeyError:
            return None
    elif kind is Grid:
        level, origin, spacing, fields = g.level, g.origin, g.spacing, g.fields
    else:
        return None
    if type(level) is not int or level < 0 or type(fields) is not dict or not fields:
        return None
    origin = _plain3(origin)
    spacing = _plain3((spacing,) * 3 if type(spacing) in _PLAIN_NUMBERS else spacing)
    if origin is None or spacing is None or not min(spacing) > 0:
        return None
    shape = None
    for name, arr in fields.items():
        if (type(name) is not str or not name or type(arr) is not np.ndarray
                or arr.dtype.kind != "f" or arr.ndim != 3 or not arr.flags.c_contiguous):
            return None
        if shape is None:
            shape = arr.shape
            if min(shape) == 0:
                return None
        elif arr.shape != shape:
            return None
    return Grid(level, origin, spacing, shape, dict(fields))


def _plain3(value) -> tuple | None:
    """``value`` as 3 finite floats when it is a tuple or list of 3 plain numbers, else None."""
    if (type(value) is not tuple and type(value) is not list) or len(value) != 3:
        return None
    x, y, z = value
    if (type(x) not in _PLAIN_NUMBERS or type(y) not in _PLAIN_NUMBERS
            or type(z) not in _PLAIN_NUMBERS):
        return None
    out = (float(x), float(y), float(z))
    if not (math.isfinite(out[0]) and math.isfinite(out[1]) and math.isfinite(out[2])):
        return None
    return out


def _parse_record(g, index: int, prefix: str) -> Grid:
    """Turn one user mapping into a :class:`Grid`, checking types and shapes."""
    where = f"{prefix}grid {index}"
    if isinstance(g, Grid):
        g = g.as_dict()
    if not isinstance(g, (dict, Mapping)):
        raise AMRError(f"{where}: expected a mapping with level, origin, spacing and fields, "
                       f"got {type(g).__name__}")
    missing = [k for k in ("level", "origin", "spacing", "fields") if k not in g]
    if missing:
        raise AMRError(f"{where}: missing key(s) {missing}")
    level = g["level"]
    if isinstance(level, (bool, np.bool_)) or not isinstance(level, (int, np.integer)) or level < 0:
        raise AMRError(f"{where}: level must be an integer >= 0, got {shown(level)}")
    origin = _float3(g["origin"], f"{where}: origin", positive=False)
    spacing = _float3(g["spacing"], f"{where}: spacing", positive=True)
    fields = g["fields"]
    if not isinstance(fields, (dict, Mapping)) or not fields:
        raise AMRError(f"{where}: fields must be a non-empty mapping of name -> array")

    def label():
        return prefix + Grid(int(level), origin, spacing, (0, 0, 0), {}).describe(index)

    arrays, shape, first = {}, None, None
    for name, arr in fields.items():
        if not isinstance(name, str) or not name:
            raise AMRError(f"{label()}: field names must be non-empty strings, got {name!r}")
        arr = np.asarray(arr)
        if arr.dtype.kind in "biu":
            arr = arr.astype(np.float64)
        if arr.dtype.kind != "f":
            raise AMRError(f"{label()}: field '{name}' has dtype {arr.dtype}, expected real "
                           f"numbers")
        if arr.ndim != 3:
            raise AMRError(f"{label()}: field '{name}' has {arr.ndim} dimension(s), expected an "
                           f"(nx, ny, nz) array")
        if min(arr.shape) == 0:
            raise AMRError(f"{label()}: field '{name}' has zero-size shape {arr.shape}; "
                           f"every grid needs at least one cell per axis")
        if shape is None:
            shape, first = arr.shape, name
        elif arr.shape != shape:
            raise AMRError(f"{label()}: field '{name}' has shape {arr.shape} but field "
                           f"'{first}' has {shape}; all fields of a grid must agree")
        arrays[name] = arr if arr.flags.c_contiguous else np.ascontiguousarray(arr)
    return Grid(int(level), origin, spacing, tuple(int(n) for n in shape), arrays)


def _float3(value, what: str, positive: bool) -> tuple:
    if positive and isinstance(value, (int, float, np.integer, np.floating)) \
            and not isinstance(value, bool):
        value = (value, value, value)
    if isinstance(value, (str, bytes)):
        raise AMRError(f"{what} must be {'a number or ' if positive else ''}3 numbers, "
                       f"got the text {value!r}")
    try:
        out = tuple(map(float, value))
    except (TypeError, ValueError):
        raise AMRError(f"{what} must be {'a number or ' if positive else ''}3 numbers, "
                       f"got {shown(value)}") from None
    if len(out) != 3:
        raise AMRError(f"{what} must be {'a number or ' if positive else ''}3 numbers, "
                       f"got {shown(value)}")
    if not all(map(math.isfinite, out)) or (positive and min(out) <= 0):
        raise AMRError(f"{what} must be finite{' and > 0' if positive else ''}, got "
                       f"{shown(value)}")
    return out


def _record_columns(records) -> dict:
    """Per-record arrays for the checks: level ``(G,)`` (int64, or object for absurd levels the
    checks then refuse), origin and spacing ``(G, 3)`` float64 (world), shape ``(G, 3)``
    int64."""
    def rows(key, dtype):
        flat = itertools.chain.from_iterable(getattr(g, key) for g in records)
        return np.fromiter(flat, dtype=dtype, count=3 * len(records)).reshape(-1, 3)

    return {"level": np.array([g.level for g in records]),
            "origin": rows("origin", np.float64), "spacing": rows("spacing", np.float64),
            "shape": rows("shape", np.int64)}


def _check_fields(records, prefix: str, allow_nonfinite: bool,
                  block_cells: int = FINITE_CHECK_CELLS) -> None:
    """Every grid holds the fields of grid 0, all finite unless ``allow_nonfinite``. Grids are
    checked in blocks of about ``block_cells`` cells, the values of a block at once;
    a block with a bad grid is checked again grid by grid (:func:`_check_grid_fields`), so the
    first bad grid is reported as a one-by-one check would."""
    names = list(records[0].fields)
    wanted = set(names)
    start = 0
    while start < len(records):
        stop, cells = start, 0
        while stop < len(records) and cells < block_cells:
            n = records[stop].shape
            cells += n[0] * n[1] * n[2]
            stop += 1
        block = records[start:stop]
        same = [g.fields.keys() == wanted for g in block]
        clean = same.index(False) if False in same else len(block)
        arrays = [a for g in block[:clean] for a in g.fields.values()]
        if clean < len(block) or not (allow_nonfinite or _all_finite(arrays, block_cells)):
            for i in range(start, stop):
                _check_grid_fields(records[i], i, names, prefix, allow_nonfinite)
        start = stop


def _all_finite(arrays, block_cells: int = FINITE_CHECK_CELLS) -> bool:
    """Whether every value of ``arrays`` is finite; the arrays smaller than ``block_cells``
    are tested together."""
    small = [a.reshape(-1) for a in arrays if a.size < block_cells]
    if small and not np.isfinite(np.concatenate(small)).all():
        return False
    return all(np.isfinite(a).all() for a in arrays if a.size >= block_cells)


def _check_grid_fields(g, i: int, names, prefix: str, allow_nonfinite: bool) -> None:
    """One grid of :func:`_check_fields`: the fields of grid 0 (``names``), finite values."""
    if set(g.fields) != set(names):
        lacking = sorted(set(names) - set(g.fields))
        extra = sorted(set(g.fields) - set(names))
        detail = (f"missing field(s) {lacking}" if lacking else "") + \
                 ("; " if lacking and extra else "") + \
                 (f"has extra field(s) {extra}" if extra else "")
        raise AMRError(f"{prefix}{g.describe(i)}: {detail}; every grid must hold the same "
                       f"fields as grid 0 ({names})")
    if not allow_nonfinite:
        for name, arr in g.fields.items():
            bad = arr.size - int(np.count_nonzero(np.isfinite(arr)))
            if bad:
                raise AMRError(f"{prefix}{g.describe(i)}: field '{name}' has {bad} non-finite "
                               f"value(s) (NaN/Inf); clean the data, or keep them as missing "
                               f"data with {ALLOW_NONFINITE_HOW}")


def _check_levels(records, columns, prefix: str) -> tuple:
    """Levels 0..L-1 all present, one spacing per level, integer ratios 2 or 4 between them."""
    levels, spacings = columns["level"], columns["spacing"]
    present = np.unique(levels)
    if present[0] != 0:
        raise AMRError(f"{prefix}no level-0 grid: the coarsest level must be 0, got levels "
                       f"{present.tolist()}")
    if present[-1] != len(present) - 1:
        # The missing levels, without enumerating up to a (possibly absurd) finest level.
        gaps = [int(level) for a, b in zip(present[:-1], present[1:])
                for level in range(a + 1, min(b, a + 4))][:8]
        raise AMRError(f"{prefix}level(s) {gaps}{' ...' if len(gaps) == 8 else ''} have no "
                       f"grids but finer levels do; levels must be contiguous")
    first = np.array([np.flatnonzero(levels == level)[0] for level in present])
    ref = spacings[first[levels]]
    bad = np.flatnonzero(np.any(np.abs(spacings - ref) > 1e-6 * ref, axis=1))
    if len(bad):
        i, j = bad[0], first[levels[bad[0]]]
        raise AMRError(f"{prefix}{records[i].describe(i)}: spacing {records[i].spacing} differs "
                       f"from {records[j].describe(j)} with spacing {records[j].spacing}; all "
                       f"grids of a level share one cell size")
    ratios = []
    for level in range(1, present[-1] + 1):
        r = spacings[first[level - 1]] / spacings[first[level]]
        rounded = np.round(r)
        if (not np.allclose(r, rounded, rtol=1e-6, atol=0) or len(set(rounded)) != 1
                or int(rounded[0]) not in ALLOWED_RATIOS):
            raise AMRError(f"{prefix}refinement ratio from level {level - 1} to {level} is "
                           f"{tuple(float(x) for x in r)}; expected 2 or 4, the same on all axes")
        ratios.append(int(rounded[0]))
    return tuple(ratios)


def _check_lattice(records, columns, ratios, prefix: str):
    """Every grid starts and ends on a cell face of the level above (level 0: of level 0)."""
    levels, origins = columns["level"], columns["origin"]
    spacings, shapes = columns["spacing"], columns["shape"]
    first0 = int(np.flatnonzero(levels == 0)[0])
    anchor = origins[first0]
    ratio = np.array((1,) + tuple(ratios), dtype=np.int64)[levels]
    with np.errstate(over="ignore", invalid="ignore"):
        offset = (origins - anchor) / (spacings * ratio[:, None])
    far = np.flatnonzero(~np.all(np.abs(offset) <= MAX_LATTICE_OFFSET, axis=1))
    if len(far):
        i = far[0]
        g = records[i]
        raise AMRError(f"{prefix}{g.describe(i)}: origin is {shown(tuple(np.round(offset[i])))} "
                       f"cells of level {max(g.level - 1, 0)} from the level-0 lattice anchored "
                       f"at {shown(tuple(anchor))}; mi_amr indexes cells with integers up to "
                       f"{MAX_LATTICE_OFFSET:.0e}, so the grids cannot lie this far apart")
    rounded = np.round(offset)
    bad = np.flatnonzero(np.any(np.abs(offset - rounded) > LATTICE_TOLERANCE, axis=1))
    if len(bad):
        i = bad[0]
        g = records[i]
        raise AMRError(f"{prefix}{g.describe(i)}: origin is not on a cell face of level "
                       f"{max(g.level - 1, 0)} (offset {shown(tuple(np.round(offset[i], 4)))} "
                       f"cells from the level-0 lattice anchored at {shown(tuple(anchor))}); "
                       f"grids must align with the coarser level's cells")
    bad = np.flatnonzero(np.any(shapes % ratio[:, None], axis=1))
    if len(bad):
        i = bad[0]
        g = records[i]
        raise AMRError(f"{prefix}{g.describe(i)}: shape {g.shape} is not a multiple of the "
                       f"refinement ratio {ratio[i]}, so it does not end on a cell face of "
                       f"level {g.level - 1}")
    return anchor, rounded.astype(np.int64) * ratio[:, None]


def _check_overlap_and_nesting(records, columns, index_lo, ratios, prefix: str):
    """Refuse grids of one level that overlap, and grids not inside the coarser level. Returns
    ``(nesting, blocks)``: per level with a coarser one, the (coarser grid, grid) pairs that
    overlap (grid numbers, sorted by the coarser grid, then the grid): the leaf masks' covered
    boxes (:func:`_covered_boxes`); and the levels' :class:`levels.LevelBlocks` where they
    were listed to find overlaps (see :data:`CHECK_BLOCKS`)."""
    levels_of, shapes = columns["level"], columns["shape"]
    index_hi = index_lo + shapes
    nesting, blocks = [], {}
    for level in range(len(ratios) + 1):
        ids = np.flatnonzero(levels_of == level)
        clash = _first_overlap(index_lo[ids], index_hi[ids], blocks, level)
        if clash is not None:
            i, j = ids[clash[0]], ids[clash[1]]
            raise AMRError(f"{prefix}{records[i].describe(i)} and {records[j].describe(j)} "
                           f"overlap; grids of one level must not overlap")
        if level == 0:
            continue
        ratio = ratios[level - 1]
        parents = np.flatnonzero(levels_of == level - 1)
        flo, fhi = index_lo[ids] // ratio, index_hi[ids] // ratio
        fa, pb = overlap_pairs(flo, fhi, index_lo[parents], index_hi[parents])
        order = np.lexsort((fa, pb))
        nesting.append((parents[pb[order]], ids[fa[order]]))
        covered = np.zeros(len(ids), dtype=np.int64)
        np.add.at(covered, fa, intersection_volume(flo[fa], fhi[fa], index_lo[parents][pb],
                                                   index_hi[parents][pb]))
        need = np.prod(fhi - flo, axis=1)
        bad = np.flatnonzero(covered != need)
        if len(bad):
            i = ids[bad[0]]
            share = covered[bad[0]] / need[bad[0]]
            raise AMRError(f"{prefix}{records[i].describe(i)} is not inside the level-{level - 1} "
                           f"grids (only {share:.0%} of it is covered); a fine grid must lie "
                           f"within the coarser level (proper nesting)")
    return nesting, blocks


def _first_overlap(lo, hi, blocks: dict, level: int, most: int = CHECK_BLOCKS):
    """The first pair ``(i, j)``, ``i < j``, of the boxes ``lo``, ``hi`` (one level's grids)
    that overlap, or None. Through the level's blocks (:class:`levels.LevelBlocks`: grids that
    overlap share one), kept in ``blocks[level]`` for the level's index, where they number at
    most ``most`` and an eighth of the cells (blocks of one cell would hold 16 bytes a cell
    until the index takes them); else from the boxes' overlapping pairs."""
    cells = int(np.prod(hi - lo, axis=1).sum())
    if levels.LevelBlocks.count(lo, hi) <= min(most, cells // 8):
        blocks[level] = levels.LevelBlocks.of(lo, hi)
        return blocks[level].first_overlap()
    a, b = overlap_pairs(lo, hi, lo, hi)
    clash = np.flatnonzero(a < b)
    return (int(a[clash[0]]), int(b[clash[0]])) if len(clash) else None


def _leaf_masks(volume: AMRVolume, box_cells: int = MASK_BOX_CELLS,
                chunk_cells: int = MASK_CHUNK_CELLS):
    """Every grid's leaf mask (True where no cell of the next finer level covers the cell),
    flat over all cells grid after grid (see :meth:`AMRVolume.cell_offsets`); and per grid,
    whether any of its cells is covered. :func:`_leaf_masks_reference` is the slow twin.

    The covered index boxes (cells of the coarse grid, from its lower corner) of all (coarse,
    fine) pairs of a level are cleared at once through their flat cell indices, in blocks of
    pairs of about ``chunk_cells`` cells; boxes of more than ``box_cells`` cells are cleared one
    by one with a slice."""
    shapes = volume.grid_columns()["shape"]
    offsets = volume.grid_columns()["offset"]
    # Aligned: the brick fill and the leaf ranges map it on the device, not copy it.
    flat = aligned_full(int(np.prod(shapes, axis=1).sum()), True, np.bool_)
    partly = np.zeros(len(shapes), dtype=bool)
    for c, a, b in _covered_boxes(volume):
        partly[c] = True
        cells = np.prod(b - a, axis=1)
        for q in np.flatnonzero(cells > box_cells):
            n = shapes[c[q]]
            mask = flat[offsets[c[q]]:offsets[c[q]] + int(np.prod(n))].reshape(n)
            mask[a[q, 0]:b[q, 0], a[q, 1]:b[q, 1], a[q, 2]:b[q, 2]] = False
        small = np.flatnonzero(cells <= box_cells)
        # Blocks of consecutive pairs holding about chunk_cells cells between them (at most
        # box_cells more) keep temporaries small, however small each box.
        ends = np.cumsum(cells[small])
        cuts = np.searchsorted(ends, np.arange(chunk_cells, int(ends[-1]) if len(ends) else 0,
                                               chunk_cells), side="right")
        bounds = np.unique(np.concatenate([[0], cuts, [len(small)]]))
        for start, stop in zip(bounds[:-1], bounds[1:]):
            q = small[start:stop]
            flat[_box_cell_indices(offsets[c[q]], shapes[c[q]], a[q], b[q])] = False
    return flat, partly


def _box_cell_indices(offset, shape, a, b) -> np.ndarray:
    """Flat indices (into the array of all cells) of the cells of the half-open index boxes
    ``[a, b)`` (rows, cells of each box's grid) of grids with the given cell ``offset`` and
    ``shape`` (rows)."""
    # A box's rows along z are runs of consecutive cells: the rows listed (a point each),
    # then widened to their runs.
    rows, box = levels.box_points(np.stack([a[:, 0], a[:, 1], np.zeros_like(a[:, 2])], axis=1),
                                  np.stack([b[:, 0], b[:, 1], np.ones_like(b[:, 2])], axis=1))
    run = (b[:, 2] - a[:, 2])[box]
    start = offset[box] + (rows[:, 0] * shape[box, 1] + rows[:, 1]) * shape[box, 2] + a[box, 2]
    return np.arange(int(run.sum())) + np.repeat(start - (np.cumsum(run) - run), run)


def _leaf_masks_reference(volume: AMRVolume):
    """Slow twin of :func:`_leaf_masks`: one (coarse, fine) pair at a time, a slice of the
    coarse grid's mask (one array per grid) is cleared. Returns the list of masks and the
    per-grid ``partly`` flags."""
    masks = [np.ones(g.shape, dtype=bool) for g in volume.grids]
    partly = np.zeros(len(masks), dtype=bool)
    for cs, los, his in _covered_boxes(volume, kept=False):     # (its own pairs)
        for c, a, b in zip(cs, los, his):
            masks[c][a[0]:b[0], a[1]:b[1], a[2]:b[2]] = False
            partly[c] = True
    return masks, partly


def _covered_boxes(volume: AMRVolume, kept: bool = True):
    """Per level with a finer one, ``(c, a, b)``: for each (coarse grid, finer grid) pair that
    overlaps, the coarse grid ``c`` and the half-open index box ``[a, b)`` (its own cells,
    from its lower corner) the finer grid covers. The pairs are the nesting check's where the
    volume kept them (:func:`_check_overlap_and_nesting`) and ``kept``, else found again."""
    levels = volume.grid_columns()["level"]
    lo, hi = volume.index_boxes()
    for level, ratio in enumerate(volume.ratios):
        if kept and volume._nesting is not None:
            c, f = volume._nesting[level]
        else:
            coarse = np.flatnonzero(levels == level)
            fine = np.flatnonzero(levels == level + 1)
            ca, fb = overlap_pairs(lo[coarse], hi[coarse], lo[fine] // ratio, hi[fine] // ratio)
            c, f = coarse[ca], fine[fb]
        flo, fhi = lo[f] // ratio, hi[f] // ratio
        yield c, np.maximum(lo[c], flo) - lo[c], np.minimum(hi[c], fhi) - lo[c]


def _format_bytes(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{n} B"
        n /= 1024
    return f"{n} B"
