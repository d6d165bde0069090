"""Reading mi_amr's own ``.npz`` files (layout: :mod:`mi_amr.core.npz`); only the requested
fields are read from disk.

Every way a file can be damaged (a cut-off or corrupt zip archive, an unsupported compression
method, a broken ``.npy`` header, entries of the wrong type, shape or size) ends as an
:class:`~mi_amr.AMRError` naming the file, before any array is allocated from a size the file
merely claims.
"""

from __future__ import annotations

import math
import struct
import tokenize
import zipfile
import zlib
from itertools import accumulate
from pathlib import Path

import numpy as np

from mi_amr.core import levels
from mi_amr.core.buffers import ALIGN, aligned_empty
from mi_amr.errors import ALLOW_NONFINITE_HOW, AMRError
from mi_amr.readers.fields import requested
from mi_amr.core.npz import MAGIC, VERSION
from mi_amr.core.volume import AMRVolume

# The marker is the first entry the writer stores, so even a file cut off before its zip
# directory starts with a local header naming it.
_MARKER_MEMBER = b"mi_amr_format.npy"
_LOCAL_HEADER = struct.Struct("<4s22xHH")
# What reading a damaged archive or .npy entry raises, besides OSError: the zip module
# (BadZipFile, NotImplementedError for compression methods it lacks, zlib/lzma/bz2 errors,
# EOFError), NumPy's .npy header parser (ValueError, and tokenize's or ast's own errors), and
# sizes no array can have.
_DAMAGE = (OSError, EOFError, ValueError, KeyError, OverflowError,
           MemoryError, RecursionError, SyntaxError, NotImplementedError, UnicodeError,
           struct.error, zlib.error, zipfile.BadZipFile, tokenize.TokenError)
# The largest grid extent per axis (as in AMReX, whose indices are 32-bit).
_MAX_CELLS_PER_AXIS = 2 ** 31 - 1
_READ_CHUNK = 1 << 18     # bytes of a field entry read at a time (as np.load reads)
_STREAM_VALUES = 1 << 18  # values of each field a FieldStream chunk holds


def is_native(path) -> bool:
    """True when ``path`` is a regular file that is a zip archive holding the mi_amr marker, or
    one that starts like the files mi_amr writes (its first entry is the marker), so that a
    truncated file is reported as damaged rather than unrecognised."""
    path = Path(path)
    try:
        if not path.is_file():
            return False
        with open(path, "rb") as f:
            head = f.read(_LOCAL_HEADER.size + len(_MARKER_MEMBER))
    except OSError:
        return False
    if len(head) == _LOCAL_HEADER.size + len(_MARKER_MEMBER):
        signature, name_len, _ = _LOCAL_HEADER.unpack(head[:_LOCAL_HEADER.size])
        if signature == b"PK\x03\x04" and name_len == len(_MARKER_MEMBER) \
                and head[_LOCAL_HEADER.size:] == _MARKER_MEMBER:
            return True
    try:
        with zipfile.ZipFile(path) as z:
            return _MARKER_MEMBER.decode() in z.namelist()
    except _DAMAGE:
        return False


def field_names(path) -> list:
    """The field names stored in an mi_amr file (reads only the small index entry)."""
    path = Path(path)
    with _archive(path) as archive, _damage(path):
        return _names(path, _entry(path, archive, "field_names"))


def load(path, fields=None, *, level_buffers=(), allow_nonfinite: bool = False) -> AMRVolume:
    """Read a file written by :func:`mi_amr.core.npz.save`; ``fields`` (a name or a list of
    names) limits what is read from disk. Each field is read into one buffer, its levels
    aligned slices of it; a field named in ``level_buffers`` gets a buffer per level instead,
    so that a level's arrays, once dropped, free their memory on their own (the velocity that
    :func:`mi_amr.core.derive.derive` consumes level by level). NaN and Inf values are kept as
    missing data where the file was saved so or ``allow_nonfinite`` is True."""
    path = Path(path)
    with _archive(path) as archive, _damage(path):
        index = _read_index(path, archive)
        wanted = _wanted(path, fields, index["names"])
        layout = _level_layout(index)
        data = {n: _field(path, archive, n, index["offsets"][-1], (layout, n in level_buffers))
                for n in wanted}
    offsets, shape = index["offsets"], index["shape"]
    _, (rank, within), _ = layout
    shapes = [tuple(row) for row in shape.tolist()]
    fields = {n: [data[n][r][a:a + b - c].reshape(sh) for r, a, b, c, sh in
                  zip(rank, within, offsets[1:], offsets, shapes)] for n in wanted}
    volume = AMRVolume.from_columns(
        {k: index[k] for k in ("level", "origin", "spacing", "shape")}, fields, data,
        allow_nonfinite=index["allow_nonfinite"] or allow_nonfinite, source=str(path))
    # Each level's buffer holds its grids in file order, which is the level tables' order.
    by_level = np.asarray(index["level"])
    for r, level in enumerate(np.unique(by_level)):
        ids = np.flatnonzero(by_level == level)
        for n in wanted:
            levels.adopt_level_values(volume, int(level), n, data[n][r],
                                      [fields[n][g] for g in ids])
    return volume


# ---------------------------------------------------------------------- reading the archive

class _archive:
    """``with _archive(path) as archive``: the open ``np.load`` archive, or an AMRError."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        if not self.path.is_file():
            raise AMRError(f"{self.path}: not a regular file")
        try:
            self.archive = np.load(self.path, allow_pickle=False)
        except _DAMAGE as e:
            raise AMRError(f"{self.path}: damaged mi_amr volume: not a readable zip archive "
                           f"({_why(e)}); the file may be truncated") from None
        if not isinstance(self.archive, np.lib.npyio.NpzFile):
            raise AMRError(f"{self.path}: not an mi_amr volume (not a zip archive of arrays)")
        return self.archive

    def __exit__(self, *exc):
        self.archive.close()


class _damage:
    """Turn a failure while reading entries (bad CRC, cut-off entry, broken header) into an
    AMRError; a damaged archive often fails only when an entry is read."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        return self

    def __exit__(self, kind, e, tb):
        if kind is None or issubclass(kind, AMRError):
            return False
        if issubclass(kind, KeyError):
            raise AMRError(f"{self.path}: mi_amr volume is missing entry {e}") from None
        if issubclass(kind, _DAMAGE):
            raise AMRError(f"{self.path}: damaged mi_amr volume ({_why(e)})") from None
        return False


def _level_layout(index) -> tuple:
    """Where each grid's values go in the buffer a field is read into: ``(runs, (rank,
    within), spans)``, with ``runs`` the ``(first, stop, at, rank)`` element ranges of the
    file's field row (consecutive grids of one level), where each begins within its level and
    the rank of that level; per grid the rank of its level and its first element within the
    level (``rank``, ``within``: lists); and ``spans`` the ``(start, size)`` of each level in
    one buffer. Levels lie one after the other there, each starting on an
    :data:`~mi_amr.core.buffers.ALIGN` byte boundary (for 1-byte values) and its grids in file
    order, so every level's values are one aligned slice that the device maps without a copy
    (:func:`mi_amr.core.levels.level_values`)."""
    level = np.asarray(index["level"], dtype=np.int64)
    if len(level) == 0:
        return [], ([], []), []
    offsets = np.asarray(index["offsets"], dtype=np.int64)
    counts = np.diff(offsets)
    # Levels ranked (so that a bad level number is left for the volume's checks to name).
    rank = np.unique(level, return_inverse=True)[1].ravel()
    sizes = np.bincount(rank, weights=counts).astype(np.int64)
    level_start = np.concatenate([[0], np.cumsum(-(-sizes // ALIGN) * ALIGN)[:-1]])
    within = np.zeros(len(level), dtype=np.int64)      # elements before the grid in its level
    for r in range(len(sizes)):
        mine = np.flatnonzero(rank == r)
        within[mine] = np.cumsum(counts[mine]) - counts[mine]
    cut = np.flatnonzero(np.diff(level) != 0) + 1
    runs = [(int(offsets[a]), int(offsets[b]), int(within[a]), int(rank[a]))
            for a, b in zip(np.concatenate([[0], cut]), np.concatenate([cut, [len(level)]]))]
    spans = [(int(a), int(n)) for a, n in zip(level_start, sizes)]
    return runs, (rank.tolist(), within.tolist()), spans


def _field(path: Path, archive, name: str, total: int, how) -> list:
    """Field ``name`` (one row of every grid's values in the file), one array per level (see
    :func:`load`), the zip entry streamed (CRC checked) into its places a chunk at a time, as
    ``np.load`` reads an entry: the same one copy. ``how``: ``(layout, split)``, the
    :func:`_level_layout` and whether each level gets a buffer of its own (else the levels
    are aligned slices of one new aligned buffer)."""
    (runs, _, spans), split = how
    key = f"field:{name}"
    info, dtype, header_size = _field_entry(path, archive, name, total)
    if split:
        out = [aligned_empty(size, dtype) for _, size in spans]
    else:
        whole = aligned_empty(max((at + size for at, size in spans), default=0), dtype)
        out = [whole[at:at + size] for at, size in spans]
    step = dtype.itemsize
    with archive.zip.open(info) as f:
        f.read(header_size)
        for first, stop, at, rank in runs:
            raw = out[rank].view(np.uint8)
            _read_into(f, raw[at * step:(at + stop - first) * step])
        if f.read(1):           # the whole entry read, so that its CRC was checked
            raise AMRError(f"{path}: damaged mi_amr volume: entry '{key}' is longer than "
                           f"its header says")
    return out


def _field_entry(path: Path, archive, name: str, total: int):
    """``(info, dtype, header_size)`` of field ``name``'s entry, checked to be one row of
    ``total`` real numbers (every grid's values)."""
    info, shape, dtype, header_size = _entry_header(path, archive, f"field:{name}")
    if len(shape) != 1:
        raise AMRError(f"{path}: field '{name}' has shape {shape}; the file stores each field "
                       f"as one row of every grid's values")
    if shape[0] != total:
        raise AMRError(f"{path}: field '{name}' holds {shape[0]} values, the grids need {total}")
    if dtype.hasobject or dtype.itemsize == 0:
        raise AMRError(f"{path}: field '{name}' has dtype {dtype}, expected real numbers")
    return info, dtype, header_size


class FieldStream:
    """Fields of an mi_amr file read a stretch at a time, for a pass over their values that
    needs no grid (a colour range): no buffer of a field's size is made, and the grids'
    boxes are not checked (:func:`load` checks them). ``with FieldStream(path, names) as s:``
    opens the archive and checks the index and the fields' entries; ``s.allow_nonfinite`` is
    the file's flag or the ``allow_nonfinite`` given, ``s.dtypes`` the fields' dtypes
    (``s.same_dtype``: all one), and
    ``s.chunks()`` yields lists of 1-D
    arrays, one per name, each the same stretch of at most ``chunk_values`` values of that
    field's row of every grid's values (file order). The arrays are read-only and valid until
    the next chunk. Damage found while reading ends as an AMRError naming the file."""

    def __init__(self, path, names, chunk_values: int = _STREAM_VALUES, *,
                 allow_nonfinite: bool = False):
        self.path, self.names, self.chunk_values = Path(path), list(names), int(chunk_values)
        self.allow_nonfinite = bool(allow_nonfinite)

    def __enter__(self) -> "FieldStream":
        self._archive = _archive(self.path)
        archive = self._archive.__enter__()
        try:
            with _damage(self.path):
                index = _read_index(self.path, archive)
                self.names = _wanted(self.path, self.names, index["names"])
                self._offsets = index["offsets"]
                self.total = self._offsets[-1]
                self._entries = [_field_entry(self.path, archive, n, self.total)
                                 for n in self.names]
        except BaseException:
            self._archive.__exit__(None, None, None)
            raise
        self.allow_nonfinite = index["allow_nonfinite"] or self.allow_nonfinite
        self.dtypes = [dtype for _, dtype, _ in self._entries]
        self.same_dtype = len(set(self.dtypes)) == 1
        return self

    def __exit__(self, *exc):
        self._archive.__exit__(*exc)

    def chunks(self):
        zip_file = self._archive.archive.zip
        with _damage(self.path):
            opened = [zip_file.open(info) for info, _, _ in self._entries]
            try:
                for f, (_, _, header_size) in zip(opened, self._entries):
                    f.read(header_size)
                for at in range(0, self.total, self.chunk_values):
                    n = min(self.chunk_values, self.total - at)
                    values = [_read_values(f, dtype, n)
                              for f, (_, dtype, _) in zip(opened, self._entries)]
                    if not self.allow_nonfinite:
                        self._check_finite(at, values)
                    yield values
                for f, name in zip(opened, self.names):
                    if f.read(1):       # the whole entry read, so that its CRC was checked
                        raise AMRError(f"{self.path}: damaged mi_amr volume: entry "
                                       f"'field:{name}' is longer than its header says")
            finally:
                for f in opened:
                    f.close()

    def _check_finite(self, at: int, values) -> None:
        """As :func:`load` does for a file that does not allow them: no NaN or infinity in
        the chunk beginning at value ``at`` of the row."""
        for name, a in zip(self.names, values):
            finite = np.isfinite(a)
            if not finite.all():
                bad = np.flatnonzero(~finite)
                grid = int(np.searchsorted(self._offsets, at + bad[0], side="right")) - 1
                raise AMRError(f"{self.path}: grid {grid}: field '{name}' has non-finite "
                               f"value(s) (NaN/Inf); clean the data, or keep them as "
                               f"missing data with {ALLOW_NONFINITE_HOW}")


def _read_values(f, dtype, n: int) -> np.ndarray:
    """The next ``n`` values of dtype ``dtype`` from the open zip entry ``f``."""
    raw = f.read(n * dtype.itemsize)
    if len(raw) != n * dtype.itemsize:
        raise EOFError("entry cut off")
    return np.frombuffer(raw, dtype=dtype)


def _read_into(f, dst: np.ndarray) -> None:
    """Fill the bytes ``dst`` from the open zip entry ``f``, a chunk at a time."""
    at = 0
    while at < len(dst):
        chunk = f.read(min(_READ_CHUNK, len(dst) - at))
        if not chunk:
            raise EOFError("entry cut off")
        dst[at:at + len(chunk)] = np.frombuffer(chunk, dtype=np.uint8)
        at += len(chunk)


def _entry_header(path: Path, archive, key: str):
    """``(info, shape, dtype, header_size)`` of the archive's ``.npy`` entry ``key``, after
    checking that the size its header declares is the size the zip entry holds (so no array
    is allocated from a damaged size)."""
    name = f"{key}.npy"
    if name not in archive.zip.namelist():
        raise KeyError(key)
    info = archive.zip.getinfo(name)
    if info.compress_type == zipfile.ZIP_STORED and info.compress_size != info.file_size:
        raise AMRError(f"{path}: damaged mi_amr volume: entry '{key}' is stored with "
                       f"{info.compress_size} bytes but claims {info.file_size}")
    with archive.zip.open(info) as f:
        version = np.lib.format.read_magic(f)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                       (2, 0): np.lib.format.read_array_header_2_0}.get(version)
        if read_header is None:
            raise AMRError(f"{path}: entry '{key}' is .npy version {version}; mi_amr writes 1.0")
        shape, _, dtype = read_header(f)
        header_size = f.tell()
    if any(n < 0 for n in shape):
        raise AMRError(f"{path}: damaged mi_amr volume: entry '{key}' has shape {shape}")
    need = header_size + math.prod(shape) * dtype.itemsize
    if need != info.file_size:
        raise AMRError(f"{path}: damaged mi_amr volume: entry '{key}' declares shape {shape} "
                       f"of {dtype} ({need} bytes with its header), the archive holds "
                       f"{info.file_size} bytes")
    return info, shape, dtype, header_size


def _entry(path: Path, archive, key: str) -> np.ndarray:
    """The array ``key`` of the archive, its header checked first (:func:`_entry_header`)."""
    _entry_header(path, archive, key)
    return archive[key]


def _read_index(path: Path, archive) -> dict:
    """The marker, version and per-grid arrays, each checked for its kind and shape."""
    if "mi_amr_format.npy" not in archive.zip.namelist():
        raise AMRError(f"{path}: not an mi_amr volume (no 'mi_amr_format' marker); "
                       f"write one with AMRVolume.save or 'python -m mi_amr dataset'")
    marker = _entry(path, archive, "mi_amr_format")
    if marker.shape != () or marker.dtype.kind != "U" or str(marker) != MAGIC:
        raise AMRError(f"{path}: not an mi_amr volume (its 'mi_amr_format' marker is not "
                       f"{MAGIC!r})")
    version = _entry(path, archive, "version")
    if version.shape != () or version.dtype.kind not in "iu":
        raise AMRError(f"{path}: entry 'version' must be one integer, got {version.dtype} "
                       f"shape {version.shape}")
    if int(version) != VERSION:
        raise AMRError(f"{path}: mi_amr volume format version {int(version)}, this mi_amr reads "
                       f"version {VERSION}")
    level = _checked(path, _entry(path, archive, "level"), "level", "iu", 1)
    count = len(level)
    origin = _checked(path, _entry(path, archive, "origin"), "origin", "fiu", 2, count)
    spacing = _checked(path, _entry(path, archive, "spacing"), "spacing", "fiu", 2, count)
    shape = _checked(path, _entry(path, archive, "shape"), "shape", "iu", 2, count)
    if shape.size and not (shape.min() >= 1 and shape.max() <= _MAX_CELLS_PER_AXIS):
        i = int(np.flatnonzero(np.any((shape < 1) | (shape > _MAX_CELLS_PER_AXIS), axis=1))[0])
        raise AMRError(f"{path}: grid {i} has shape {shape[i].tolist()}; every grid needs 1 to "
                       f"{_MAX_CELLS_PER_AXIS} cells per axis")
    allow = _entry(path, archive, "allow_nonfinite")
    if allow.shape != () or allow.dtype.kind != "b":
        raise AMRError(f"{path}: entry 'allow_nonfinite' must be one boolean, got {allow.dtype} "
                       f"shape {allow.shape}")
    names = _names(path, _entry(path, archive, "field_names"))
    return {"level": level, "origin": origin, "spacing": spacing, "shape": shape,
            "offsets": _offsets(shape), "names": names,
            "allow_nonfinite": bool(allow)}


def _offsets(shape) -> list:
    """Where each grid's values begin in a field's row, and the end (Python ints): from NumPy's
    products where the total cannot overflow int64, else from Python's (a damaged index's
    huge shapes, which the entries' sizes then refuse)."""
    if float(np.prod(shape.astype(np.float64), axis=1).sum()) < 2.0 ** 62:
        return [0, *np.cumsum(np.prod(shape.astype(np.int64), axis=1)).tolist()]
    return [0, *accumulate(math.prod(int(n) for n in row) for row in shape)]


def _checked(path: Path, a: np.ndarray, key: str, kinds: str, ndim: int, count=None):
    """``a`` of a dtype kind in ``kinds``, shaped ``(G,)`` (``ndim`` 1) or ``(G, 3)``, where
    ``G`` is ``count`` (the length of ``level``) when given."""
    want = "(G,)" if ndim == 1 else "(G, 3)"
    if a.dtype.kind not in kinds or a.ndim != ndim or (ndim == 2 and a.shape[1] != 3):
        kind = "integers" if kinds == "iu" else "numbers"
        raise AMRError(f"{path}: entry '{key}' must be {kind} shaped {want}, got {a.dtype} "
                       f"shape {a.shape}")
    if count is not None and len(a) != count:
        raise AMRError(f"{path}: entry '{key}' has {len(a)} row(s) but 'level' has {count}; "
                       f"every per-grid entry needs one row per grid")
    return a


def _names(path: Path, names: np.ndarray) -> list:
    if names.ndim != 1 or names.dtype.kind != "U":
        raise AMRError(f"{path}: entry 'field_names' must be a list of names, got {names.dtype} "
                       f"shape {names.shape}")
    return [str(n) for n in names]


def _wanted(path: Path, fields, names: list) -> list:
    """The requested field names: all (``None``), one name, or a list of names."""
    return requested(path, fields, names)


def _why(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0][:200]}" if text else type(e).__name__
