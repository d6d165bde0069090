"""AMReX plotfiles: a folder with a text ``Header`` and, per level, ``Cell_H`` and ``Cell_D_*`` files.

Layout (AMReX documentation, "Plotfile format"; only what this reader needs):

* ``Header`` -- the version line (``HyperCLaw-V1.1``), the number of fields and their names, the
  dimension (this reader needs 3), the time, the finest level, ``prob_lo`` and ``prob_hi`` (world
  units), the refinement ratios, each level's index domain, each level's step, each level's cell
  size (world units), the coordinate system (0 = Cartesian), the boundary width; then per level:
  ``level ngrids time``, the step, one ``lo hi`` line per grid and axis (world units) and the
  level's data path (``Level_0/Cell``).
* ``Level_N/Cell_H`` -- the VisMF header: version, layout, component count, ghost width, the box
  list ``(N 0`` / ``((lo) (hi) (type))`` ... ``)`` (index space, inclusive corners), one
  ``FabOnDisk: Cell_D_xxxxx offset`` line per box, then per-box min/max tables (not used here).
* ``Level_N/Cell_D_xxxxx`` -- FABs. Each is a text line
  ``FAB ((8, (64 11 52 0 1 12 0 1023)),(8, (8 7 6 5 4 3 2 1)))((lo) (hi) (type)) ncomp``
  followed by ``ncomp`` blocks of reals, one per component, each in Fortran order (x fastest).
  The first tuple is the real format (IEEE double or single), the second the byte order:
  ``(8 7 ... 1)`` is little-endian, ``(1 2 ... 8)`` big-endian.

World placement: the cell with index ``n`` on level ``l`` starts at
``prob_lo + (n - domain_lo[l]) * dx[l]`` (world units), as AMReX's ``Geometry`` places it. Values
are cell-centred; each grid's arrays are indexed ``[i, j, k]`` = x, y, z. Only the requested
components are read from disk: memory grows with the fields asked for, not with the file.
"""

from __future__ import annotations

import math
import os
import re
import stat
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mi_amr.errors import ALLOW_NONFINITE_HOW, AMRError, shown
from mi_amr.core.volume import AMRVolume
from mi_amr.readers.fields import requested

# "HyperCLaw-V1.1" is AMReX's default; codes may pass their own name to WriteMultiLevelPlotfile,
# so any "<name>-V<number>" counts. Checkpoint headers ("Checkpoint version: 1") do not match.
_VERSION_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*-V\d+(\.\d+)*$")
_BOX = (r"\(\s*\(\s*(-?\d+)\s*,\s*(-?\d+)\s*,\s*(-?\d+)\s*\)\s*"
        r"\(\s*(-?\d+)\s*,\s*(-?\d+)\s*,\s*(-?\d+)\s*\)\s*"
        r"\(\s*(\d+)\s*,\s*(\d+)\s*,\s*(\d+)\s*\)\s*\)")
_BOX_RE = re.compile(_BOX)
_FAB_RE = re.compile(r"^FAB\s*\(\s*\(\s*(\d+)\s*,\s*\(([^()]*)\)\s*\)\s*,"
                     r"\s*\(\s*(\d+)\s*,\s*\(([^()]*)\)\s*\)\s*\)\s*" + _BOX + r"\s*(\d+)\s*$")
_FAB_ON_DISK_RE = re.compile(r"^FabOnDisk:\s*(\S+)\s+(\d+)$")
# IEEE-754 layouts in AMReX's RealDescriptor notation, keyed by bytes per real.
_IEEE_FORMATS = {8: (64, 11, 52, 0, 1, 12, 0, 1023), 4: (32, 8, 23, 0, 1, 9, 0, 127)}
# A FAB header line is about 100 bytes; reading more than this means the offset is wrong.
_MAX_FAB_HEADER = 4096
# AMReX stores cell indices as 32-bit ints; larger ones are damage, and would overflow the
# integer arithmetic of the grid checks.
_MAX_INDEX = 2 ** 31 - 1
# Header grid extents are printed text; half a cell separates "rounded" from "a different box".
_EXTENT_TOLERANCE = 0.5


class Box(NamedTuple):
    """An AMReX index box: ``lo`` and ``hi`` are inclusive cell indices of its level, ``itype``
    is 0 per axis for cell-centred data."""

    lo: tuple
    hi: tuple
    itype: tuple

    @property
    def shape(self) -> tuple:
        """Cells per axis (x, y, z)."""
        return tuple(h - l + 1 for l, h in zip(self.lo, self.hi))

    def grow(self, n) -> "Box":
        return Box(tuple(l - g for l, g in zip(self.lo, n)),
                   tuple(h + g for h, g in zip(self.hi, n)), self.itype)

    def __str__(self) -> str:
        def v(t):
            return "(" + ",".join(str(x) for x in t) + ")"
        return f"({v(self.lo)} {v(self.hi)} {v(self.itype)})"


@dataclass(frozen=True)
class LevelEntry:
    """One level's block of the ``Header``: ``extents`` is ``(G, 3, 2)`` world ``lo, hi`` per
    grid and axis, ``data_path`` the MultiFab prefix relative to the plotfile (``Level_0/Cell``)."""

    level: int
    num_grids: int
    time: float
    step: int
    extents: np.ndarray
    data_path: str


@dataclass(frozen=True)
class PlotfileHeader:
    """The parsed ``Header``. Positions and cell sizes are world units; ``domains`` are index
    boxes, one per level; ``ref_ratios[l]`` refines level ``l`` into ``l + 1``."""

    version: str
    field_names: tuple
    time: float
    prob_lo: np.ndarray
    prob_hi: np.ndarray
    ref_ratios: tuple
    domains: tuple
    level_steps: tuple
    cell_sizes: np.ndarray
    coord_sys: int
    levels: tuple

    @property
    def finest_level(self) -> int:
        return len(self.levels) - 1


@dataclass(frozen=True)
class CellHeader:
    """A parsed ``Cell_H``: the level's boxes (index space, without ghost cells), the ghost width
    per axis, and per box the ``Cell_D`` file name and byte offset of its FAB."""

    ncomp: int
    ngrow: tuple
    boxes: tuple
    fabs: tuple


# ---------------------------------------------------------------------- public entry points

def is_plotfile(path) -> bool:
    """True when ``path`` is a folder with a ``Header`` whose first line is a plotfile version."""
    path = Path(path)
    header = path / "Header"
    try:
        if not path.is_dir() or not header.is_file():
            return False
        with open(header, "rb") as f:
            first = f.readline(256)
    except OSError:
        return False
    return bool(_VERSION_RE.match(first.decode("latin-1").strip()))


def load(path, fields=None, *, allow_nonfinite: bool = False) -> AMRVolume:
    """Read the AMReX plotfile folder ``path``; ``fields`` (names) limits what is read from disk.

    Grids get world origins ``prob_lo + (box_lo - domain_lo) * dx`` and the Header's cell sizes;
    8-byte reals become float64 arrays, 4-byte reals float32, in native byte order.
    ``allow_nonfinite=True`` keeps NaN and Inf values as missing data. Raises
    :class:`AMRError` naming the file for anything malformed or missing.
    """
    root = Path(path)
    header = read_header(root)
    wanted = _wanted_fields(root, header.field_names, fields)
    comps = [header.field_names.index(n) for n in wanted]
    grids = []
    for entry in header.levels:
        cell_h = root / (entry.data_path + "_H")
        cell = read_cell_header(cell_h, len(header.field_names))
        _check_boxes(root / "Header", cell_h, header, entry, cell)
        dx = header.cell_sizes[entry.level]
        domain_lo = np.array(header.domains[entry.level].lo)
        data = _read_level(cell_h, cell, len(header.field_names), comps)
        for box, arrays in zip(cell.boxes, data):
            origin = header.prob_lo + (np.array(box.lo) - domain_lo) * dx
            grids.append({"level": entry.level, "origin": origin, "spacing": dx,
                          "fields": {name: arrays[c] for name, c in zip(wanted, comps)}})
    return AMRVolume.from_grids(grids, allow_nonfinite=allow_nonfinite, source=str(root))


class FabStream:
    """Fields of an AMReX plotfile read a FAB at a time, for a pass over their values that
    needs no grid (a colour range): the interface of
    :class:`~mi_amr.readers.native.FieldStream`. ``with FabStream(path, names) as s:`` reads
    the Header and each level's box list (and checks them against each other); ``chunks()``
    yields, per box, the named fields' values (1-D arrays in native byte order, one per name,
    each box's own real type, so ``same_dtype``: a chunk's arrays share one dtype). A value
    that is not finite ends as an AMRError naming the FAB, as :func:`load` refuses it, unless
    ``allow_nonfinite``."""

    same_dtype = True

    def __init__(self, path, names, *, allow_nonfinite: bool = False):
        self.root, self.names = Path(path), list(names)
        self.allow_nonfinite = bool(allow_nonfinite)

    def __enter__(self) -> "FabStream":
        header = read_header(self.root)
        self.names = _wanted_fields(self.root, header.field_names, self.names)
        self._comps = [header.field_names.index(n) for n in self.names]
        self._nfields = len(header.field_names)
        self._levels = []
        for entry in header.levels:
            cell_h = self.root / (entry.data_path + "_H")
            cell = read_cell_header(cell_h, self._nfields)
            _check_boxes(self.root / "Header", cell_h, header, entry, cell)
            self._levels.append((cell_h, cell))
        return self

    def __exit__(self, *exc):
        return False

    def chunks(self):
        for cell_h, cell in self._levels:
            for i, arrays in _fabs(cell_h, cell, self._nfields, self._comps):
                values = [arrays[c].reshape(-1) for c in self._comps]
                for name, a in zip(self.names, values):
                    if not self.allow_nonfinite and not np.isfinite(a).all():
                        raise AMRError(f"{cell_h.parent / cell.fabs[i][0]}: FAB {i}: field "
                                       f"'{name}' has non-finite value(s) (NaN/Inf); clean "
                                       f"the data, or keep them as missing data with "
                                       f"{ALLOW_NONFINITE_HOW}")
                yield values


def read_header(root) -> PlotfileHeader:
    """Parse ``root/Header`` (see the module docstring for its layout)."""
    path = Path(root) / "Header"
    if not path.is_file():
        raise AMRError(f"{path}: missing; an AMReX plotfile folder has a Header file")
    with _reading(path, "the plotfile Header"):
        lines = _Lines(path, path.read_bytes().decode("utf-8", errors="replace"))
        version = lines.next("the plotfile version (e.g. HyperCLaw-V1.1)")
        if not _VERSION_RE.match(version):
            raise lines.fail(f"first line {version[:60]!r} is not an AMReX plotfile version "
                             f"(expected e.g. HyperCLaw-V1.1)")
        (nfields,) = lines.numbers("the number of fields", int, 1)
        if nfields < 1:
            raise lines.fail(f"{nfields} fields; a plotfile needs at least one")
        names = tuple(lines.next(f"field name {i + 1} of {nfields}") for i in range(nfields))
        for i, name in enumerate(names):
            if not name or name in names[:i]:
                raise AMRError(f"{path}: field name {i + 1} ({name!r}) is empty or repeated; "
                               f"fields: {list(names)}")
        (dim,) = lines.numbers("the dimension", int, 1)
        if dim != 3:
            raise lines.fail(f"the plotfile is {dim}-dimensional; mi_amr reads 3-D plotfiles "
                             f"only")
        (time,) = lines.numbers("the time", float, 1)
        (finest,) = lines.numbers("the finest level", int, 1)
        if finest < 0:
            raise lines.fail(f"finest level {finest}; expected 0 or more")
        prob_lo = np.array(lines.numbers("prob_lo (3 numbers)", float, 3))
        prob_hi = np.array(lines.numbers("prob_hi (3 numbers)", float, 3))
        if not (np.all(np.isfinite(prob_lo)) and np.all(np.isfinite(prob_hi))
                and np.all(prob_hi > prob_lo)):
            raise lines.fail(f"domain {shown(prob_lo)} .. {shown(prob_hi)} is not a finite box "
                             f"with prob_hi > prob_lo")
        # Some writers list a ratio for every level up to max_level, not just finest_level.
        ratios = tuple(lines.numbers(f"{finest} refinement ratio(s)", int, finest, extra_ok=True))
        if any(r < 1 for r in ratios):
            raise lines.fail(f"refinement ratios {ratios}; expected positive integers")
        domains = _parse_boxes(lines, lines.next(f"{finest + 1} level domain box(es)"),
                               finest + 1, "level domain")
        steps = tuple(lines.numbers(f"{finest + 1} level step(s)", int, finest + 1))
        cell_sizes = np.array([lines.numbers(f"the cell size of level {lev} (3 numbers)",
                                             float, 3) for lev in range(finest + 1)])
        if not np.all(np.isfinite(cell_sizes) & (cell_sizes > 0)):
            raise AMRError(f"{path}: cell sizes {cell_sizes.tolist()} must be finite and > 0")
        for lev, r in enumerate(ratios):
            with np.errstate(over="ignore"):  # 1e308 / 0.1 is inf, refused below
                actual = cell_sizes[lev] / cell_sizes[lev + 1]
            if not np.allclose(actual, r, rtol=1e-6, atol=0):
                raise AMRError(f"{path}: refinement ratio {r} from level {lev} to {lev + 1} "
                               f"disagrees with the cell sizes {shown(cell_sizes[lev])} and "
                               f"{shown(cell_sizes[lev + 1])}")
        (coord_sys,) = lines.numbers("the coordinate system", int, 1)
        if coord_sys != 0:
            raise lines.fail(f"coordinate system {coord_sys} (1 = cylindrical, 2 = spherical); "
                             f"mi_amr reads Cartesian (0) plotfiles only")
        lines.numbers("the boundary width", int, 1)
        levels = tuple(_parse_level_entry(lines, lev) for lev in range(finest + 1))
    return PlotfileHeader(version, names, time, prob_lo, prob_hi, ratios, tuple(domains), steps,
                          cell_sizes, coord_sys, levels)


def read_cell_header(path, nfields: int) -> CellHeader:
    """Parse one level's ``Cell_H`` (VisMF header version 1: every FAB has its own header)."""
    path = Path(path)
    if not path.is_file():
        raise AMRError(f"{path}: missing; the plotfile Header names this level's data "
                       f"'{path.parent.name}/{path.name[:-2]}', whose box list is this file")
    with _reading(path, "the level's box list"):
        lines = _Lines(path, path.read_bytes().decode("utf-8", errors="replace"))
        (version,) = lines.numbers("the VisMF header version", int, 1)
        if version != 1:
            raise lines.fail(f"VisMF header version {version}; mi_amr reads version 1 (a FAB "
                             f"header before each box's data)")
        lines.numbers("the VisMF layout", int, 1)
        (ncomp,) = lines.numbers("the number of components", int, 1)
        if ncomp != nfields:
            raise lines.fail(f"{ncomp} component(s), but the Header lists {nfields} field(s)")
        ngrow = _parse_ngrow(lines)
        opening = lines.next("the box list '(N 0'")
        m = re.match(r"^\(\s*(\d+)\s+\d+$", opening)
        if not m:
            raise lines.fail(f"expected the box list opening '(N 0', got {opening[:60]!r}")
        nboxes = int(m.group(1))
        boxes = tuple(_parse_boxes(lines, lines.next(f"box {i} of {nboxes}"), 1, f"box {i}")[0]
                      for i in range(nboxes))
        closing = lines.next("')' closing the box list")
        if closing != ")":
            raise lines.fail(f"expected ')' after {nboxes} boxes, got {closing[:60]!r}")
        (nfabs,) = lines.numbers("the number of FabOnDisk entries", int, 1)
        if nfabs != nboxes:
            raise lines.fail(f"{nfabs} FabOnDisk entries for {nboxes} boxes")
        fabs = []
        for i in range(nfabs):
            line = lines.next(f"'FabOnDisk: Cell_D_xxxxx offset' for box {i}")
            m = _FAB_ON_DISK_RE.match(line)
            if not m:
                raise lines.fail(f"expected 'FabOnDisk: Cell_D_xxxxx offset' for box {i}, got "
                                 f"{line[:60]!r}")
            name = m.group(1)
            # FAB files sit next to Cell_H; a path here would read outside the plotfile.
            if "/" in name or "\\" in name or name in (".", ".."):
                raise lines.fail(f"FAB file name {name!r} must be a plain file name")
            fabs.append((name, int(m.group(2))))
    for i, box in enumerate(boxes):
        if box.itype != (0, 0, 0):
            raise AMRError(f"{path}: box {i} {box} is not cell-centred (index type "
                           f"{box.itype}); mi_amr reads cell-centred plotfiles only")
        if min(box.shape) < 1:
            raise AMRError(f"{path}: box {i} {box} is empty (hi < lo)")
    return CellHeader(ncomp, ngrow, boxes, tuple(fabs))


# ---------------------------------------------------------------------- text parsing

class _Lines:
    """A cursor over a text file's lines that names the file and line in every error."""

    def __init__(self, path, text: str):
        self.path = path
        self.lines = text.splitlines()
        self.n = 0

    def next(self, what: str) -> str:
        if self.n >= len(self.lines):
            raise AMRError(f"{self.path}: ends early after {len(self.lines)} line(s); expected "
                           f"{what} on line {self.n + 1} (the file is cut short)")
        self.n += 1
        return self.lines[self.n - 1].strip()

    def numbers(self, what: str, kind, count: int, extra_ok: bool = False) -> list:
        """The line's ``count`` numbers of type ``kind``; ``extra_ok`` drops any that follow."""
        line = self.next(what)
        parts = line.split()
        try:
            values = [kind(p) for p in parts]
        except ValueError:
            raise self.fail(f"expected {what}, got {line[:80]!r}") from None
        if len(values) < count or (len(values) > count and not extra_ok):
            raise self.fail(f"expected {what}, got {len(values)} value(s): {line[:80]!r}")
        return values[:count]

    def fail(self, message: str) -> AMRError:
        return AMRError(f"{self.path}: line {self.n}: {message}")


def _parse_boxes(lines: _Lines, text: str, count: int, what: str) -> list:
    """``count`` index boxes written as ``((lo) (hi) (type))`` on one line."""
    found = list(_BOX_RE.finditer(text))
    rest = _BOX_RE.sub("", text).strip()
    if len(found) != count or rest:
        raise lines.fail(f"expected {count} {what} box(es) '((lo) (hi) (type))', got "
                         f"{text[:80]!r}")
    boxes = []
    for m in found:
        v = [int(x) for x in m.groups()]
        if max(abs(x) for x in v) > _MAX_INDEX:
            raise lines.fail(f"{what} box {text[:80]!r} has an index beyond AMReX's 32-bit "
                             f"range (+-{_MAX_INDEX})")
        boxes.append(Box(tuple(v[0:3]), tuple(v[3:6]), tuple(v[6:9])))
    return boxes


def _parse_ngrow(lines: _Lines) -> tuple:
    """Ghost width: one integer, or ``(gx,gy,gz)`` when it differs per axis."""
    line = lines.next("the ghost width")
    m = re.match(r"^\(\s*(\d+)\s*,\s*(\d+)\s*,\s*(\d+)\s*\)$", line)
    if m:
        return tuple(int(x) for x in m.groups())
    if re.match(r"^\d+$", line):
        return (int(line),) * 3
    raise lines.fail(f"expected the ghost width (an integer or (gx,gy,gz)), got {line[:60]!r}")


def _parse_level_entry(lines: _Lines, level: int) -> LevelEntry:
    lev, ngrids, time = lines.numbers(f"'level ngrids time' of level {level}", float, 3)
    if lev != level or ngrids != int(ngrids) or ngrids < 1:
        raise lines.fail(f"expected level {level} and a grid count >= 1, got level {lev:g} "
                         f"with {ngrids:g} grid(s)")
    ngrids = int(ngrids)
    (step,) = lines.numbers(f"the step of level {level}", int, 1)
    extents = np.array([[lines.numbers(f"'lo hi' of axis {a} of grid {g} of level {level}",
                                       float, 2) for a in range(3)] for g in range(ngrids)])
    data_path = lines.next(f"the data path of level {level} (e.g. Level_{level}/Cell)")
    parts = Path(data_path).parts
    if not data_path or Path(data_path).is_absolute() or ".." in parts:
        raise lines.fail(f"data path {data_path!r} must be relative to the plotfile folder, "
                         f"e.g. Level_{level}/Cell")
    return LevelEntry(level, ngrids, time, step, extents, data_path)


@contextmanager
def _reading(path, what: str):
    """Turn a low-level failure while reading ``path`` into an AMRError that names it."""
    try:
        yield
    except AMRError:
        raise
    except (OSError, ValueError, IndexError, OverflowError, UnicodeError) as e:
        raise AMRError(f"{path}: cannot read {what} ({type(e).__name__}: {e})") from e


# ---------------------------------------------------------------------- checks and data

def _wanted_fields(root: Path, names: tuple, fields) -> list:
    return requested(root, fields, list(names), holder="plotfile")


def _check_boxes(header_path: Path, cell_h: Path, header: PlotfileHeader, entry: LevelEntry,
                 cell: CellHeader) -> None:
    """The Cell_H box list must describe the grids the Header lists for the level."""
    if len(cell.boxes) != entry.num_grids:
        raise AMRError(f"{cell_h}: {len(cell.boxes)} box(es), but {header_path} says level "
                       f"{entry.level} has {entry.num_grids} grid(s)")
    dx = header.cell_sizes[entry.level]
    domain_lo = np.array(header.domains[entry.level].lo)
    lo = np.array([b.lo for b in cell.boxes], dtype=np.float64)
    hi = np.array([b.hi for b in cell.boxes], dtype=np.float64) + 1
    listed = entry.extents
    # Recent AMReX writes the extents relative to the domain's lower index, older versions from
    # index 0; the two agree whenever the domain starts at 0, and either placement is accepted.
    ok = np.zeros(len(cell.boxes), dtype=bool)
    for shift in (domain_lo, np.zeros(3)):
        # Extents such as 1e308 overflow to inf here, and inf is refused just the same.
        with np.errstate(over="ignore", invalid="ignore"):
            cells_lo = (listed[:, :, 0] - header.prob_lo) / dx - (lo - shift)
            cells_hi = (listed[:, :, 1] - header.prob_lo) / dx - (hi - shift)
        ok |= np.all((np.abs(cells_lo) <= _EXTENT_TOLERANCE)
                     & (np.abs(cells_hi) <= _EXTENT_TOLERANCE), axis=1)
    if not np.all(ok):
        i = int(np.flatnonzero(~ok)[0])
        ext = ", ".join(f"[{a:g}, {b:g}]" for a, b in listed[i])
        raise AMRError(f"{cell_h}: box {i} {cell.boxes[i]} does not match grid {i} of level "
                       f"{entry.level} in {header_path} (world extents {ext}); the box list and "
                       f"the Header disagree")


def _read_level(cell_h: Path, cell: CellHeader, nfields: int, comps: list) -> list:
    """Per box, ``{component: array (nx, ny, nz)}`` for the components ``comps`` only."""
    return [arrays for _, arrays in _fabs(cell_h, cell, nfields, comps)]


def _fabs(cell_h: Path, cell: CellHeader, nfields: int, comps: list):
    """Per box of the level, in order, ``(index, {component: array (nx, ny, nz)})`` for the
    components ``comps`` only, read one FAB at a time."""
    folder = cell_h.parent
    limits = _fab_limits(folder, cell_h, cell.fabs)
    files = {}
    try:
        for i, ((name, offset), box) in enumerate(zip(cell.fabs, cell.boxes)):
            d_path = folder / name
            if name not in files:
                with _reading(d_path, "FAB data"):
                    files[name] = open(d_path, "rb")
            with _reading(d_path, f"FAB {i}"):
                arrays = _read_fab(files[name], d_path, cell_h, i, offset, limits[i], box,
                                   cell.ngrow, nfields, comps)
            yield i, arrays
    finally:
        for f in files.values():
            f.close()


def _fab_limits(folder: Path, cell_h: Path, fabs: tuple) -> list:
    """Per FAB, the byte where it must end: the next FAB of the same file, or the file's end."""
    sizes, offsets = {}, {}
    for i, (name, offset) in enumerate(fabs):
        offsets.setdefault(name, []).append(offset)
        if name not in sizes:
            d_path = folder / name
            try:
                st = os.stat(d_path)
            except FileNotFoundError:
                raise AMRError(f"{d_path}: missing; {cell_h} puts FAB {i} in this file") from None
            except OSError as e:
                raise AMRError(f"{d_path}: cannot read FAB data ({e})") from None
            # Opening a FIFO or a device would block or read forever.
            if not stat.S_ISREG(st.st_mode):
                raise AMRError(f"{d_path}: not a regular file; {cell_h} puts FAB {i} in it")
            sizes[name] = st.st_size
    # Sorted offsets per file: the limit of a FAB is the first offset above its own.
    starts = {name: np.unique(found) for name, found in offsets.items()}
    limits = []
    for name, offset in fabs:
        k = int(np.searchsorted(starts[name], offset, side="right"))
        limits.append(int(starts[name][k]) if k < len(starts[name]) else sizes[name])
    return limits


def _read_fab(f, d_path: Path, cell_h: Path, index: int, offset: int, limit: int, box: Box,
              ngrow: tuple, nfields: int, comps: list) -> dict:
    """Read components ``comps`` of the FAB at byte ``offset`` of the open file ``f``.

    Returns ``{component: array}``, each array ``box.shape`` (ghost cells dropped), indexed
    ``[i, j, k]`` = x, y, z, in the file's precision and native byte order.
    """
    where = f"{d_path}: FAB {index} at byte {offset}"
    size = os.fstat(f.fileno()).st_size
    if offset >= size:
        raise AMRError(f"{where}: the file has only {size} bytes (truncated?); {cell_h} puts "
                       f"box {index} {box} here")
    f.seek(offset)
    line = f.readline(_MAX_FAB_HEADER)
    if not line.endswith(b"\n") and offset + len(line) >= size:
        raise AMRError(f"{where}: the file ends inside the FAB header line (truncated?); "
                       f"{cell_h} puts box {index} {box} here")
    m = _FAB_RE.match(line.decode("latin-1").rstrip()) if line.endswith(b"\n") else None
    if not m:
        raise AMRError(f"{where}: expected a FAB header line 'FAB ((8, (64 11 52 ...)),(8, (8 7 "
                       f"6 ...)))((lo) (hi) (type)) ncomp', found {line[:80]!r}")
    dtype = _real_dtype(where, m.group(1), m.group(2), m.group(3), m.group(4))
    v = [int(x) for x in m.groups()[4:13]]
    fab_box = Box(tuple(v[0:3]), tuple(v[3:6]), tuple(v[6:9]))
    expected = box.grow(ngrow)
    if fab_box != expected:
        raise AMRError(f"{where}: FAB box {fab_box} differs from box {index} {expected} of "
                       f"{cell_h}; the box list and the data disagree")
    ncomp = int(m.group(14))
    if ncomp != nfields:
        raise AMRError(f"{where}: the FAB holds {ncomp} component(s), but the plotfile Header "
                       f"lists {nfields} field(s)")
    shape = fab_box.shape
    block = math.prod(shape) * dtype.itemsize
    start = offset + len(line)
    end = start + ncomp * block
    if end > limit:
        if limit == size:
            raise AMRError(f"{where}: truncated; box {fab_box} with {ncomp} component(s) needs "
                           f"bytes up to {end}, the file has {size}")
        raise AMRError(f"{where}: the FAB is shorter than its box {fab_box} needs "
                       f"({ncomp * block} data bytes): {cell_h} puts the next FAB of this file "
                       f"at byte {limit}")
    if end < limit:
        # Data in another precision than the header declares (doubles under a float header)
        # would otherwise be read as wrong values without a word.
        what = "the next FAB of this file starts" if limit < size else "the file ends"
        raise AMRError(f"{where}: the FAB holds {limit - start} data bytes, but its header "
                       f"declares box {fab_box} with {ncomp} component(s) of {dtype.itemsize}-"
                       f"byte reals ({ncomp * block} bytes); {what} at byte {limit}. The real "
                       f"format in the FAB header does not match the data")
    inner = tuple(slice(g, n - g) for g, n in zip(ngrow, shape))
    arrays = {}
    for c in comps:
        f.seek(start + c * block)
        raw = np.fromfile(f, dtype=dtype, count=block // dtype.itemsize)
        if raw.size * dtype.itemsize != block:
            raise AMRError(f"{where}: truncated; component {c} ends early")
        # Fortran order (x fastest) read as C order gives [k, j, i]; the transpose is [i, j, k].
        view = raw.reshape(shape[::-1]).T[inner]
        arr = np.empty(view.shape, dtype=dtype.newbyteorder("="))
        arr[...] = view
        arrays[c] = arr
    return arrays


def _real_dtype(where: str, fmt_count: str, fmt: str, order_count: str, order: str) -> np.dtype:
    """The NumPy dtype of an AMReX RealDescriptor ``((n, (format)),(bytes, (order)))``."""
    try:
        fmt_v = tuple(int(x) for x in fmt.split())
        order_v = tuple(int(x) for x in order.split())
    except ValueError:
        fmt_v = order_v = ()
    nbytes = len(order_v)
    if (len(fmt_v) != int(fmt_count) or nbytes != int(order_count)
            or _IEEE_FORMATS.get(nbytes) != fmt_v):
        raise AMRError(f"{where}: unsupported real format ({fmt_count}, ({fmt})),({order_count}, "
                       f"({order})); expected IEEE doubles (64 11 52 0 1 12 0 1023) or singles "
                       f"(32 8 23 0 1 9 0 127)")
    if order_v == tuple(range(nbytes, 0, -1)):
        return np.dtype(f"<f{nbytes}")
    if order_v == tuple(range(1, nbytes + 1)):
        return np.dtype(f">f{nbytes}")
    raise AMRError(f"{where}: byte order ({order}) is neither little-endian "
                   f"({' '.join(str(i) for i in range(nbytes, 0, -1))}) nor big-endian "
                   f"({' '.join(str(i) for i in range(1, nbytes + 1))})")
