"""A disk cache of prepared volumes (*snapshots*): loading the same data again is a read.

Preparing a volume (derived fields, kd-tree, brick pools, leaf value ranges) costs about a
hundred times reading the file. A snapshot keeps the result as raw arrays, each with a CRC-32
(:mod:`mi_amr.core.rawarrays`), described by a JSON file (``meta.json``, with a checksum of its
own). Reloading reads the arrays into aligned memory that Dr.Jit maps as it is, checks every
byte against its checksum, and trusts the hierarchy (it was validated when the snapshot was
made). Nothing read from the cache runs code: there is no pickle, and every field of the JSON
is checked for its type and range before it is used.

An entry is a folder named by a key covering everything the preparation depends on: the data's
absolute path, the size and modification time of every file under it, the fields, ``leaf_cells``
and the code itself (a hash of the package's source files). Any change gives another key, so a
stale entry is never used; it is evicted in time. Leaf value ranges are added to the entry when
a render first computes them.

A :class:`SnapshotCache` says where entries live and how much they may hold; its caller owns it
(:func:`~mi_amr.kernels.prepared.prepare_file` builds one from the environment unless given
one): ``$MI_AMR_CACHE`` (a folder; ``off`` turns snapshots off), else
``$XDG_CACHE_HOME/mi_amr/prepared`` (``~/.cache/mi_amr/prepared``), at most ``$MI_AMR_CACHE_GB``
gigabytes (default :data:`DEFAULT_LIMIT_GB`): the least recently used entries are removed first.
An entry is written in a temporary folder (removed again when the write is interrupted) and
renamed into place, so a crash or two processes preparing at once never leave half an entry.
An entry that is damaged (a changed byte, a truncated or planted file, bad JSON) is warned about
by name, removed, and the volume prepared afresh. Only the cache's own folders are ever removed
(:mod:`mi_amr.kernels.snapshot_folder`); nothing outside the cache folder is written or removed.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import os
import secrets
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_amr.core import levels, rawarrays
from mi_amr.core.kdstate import state_problem
from mi_amr.core.rawarrays import BadFile, expect
from mi_amr.core.volume import AMRVolume, Grid
from mi_amr.core.buffers import aligned_parts
from mi_amr.kernels import snapshot_folder as folder
from mi_amr.kernels.snapshot_folder import FORMAT, META

DEFAULT_LIMIT_GB = 8.0
_OFF = ("off", "0", "none", "no", "false", "")
_META_KIND = "mi_amr snapshot"
_MAX_META = 1 << 24         # bytes: a longer meta.json is damage
_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
_log = logging.getLogger("mi_amr.snapshot")


@dataclass(frozen=True)
class SnapshotCache:
    """Where snapshots are read and written (``root``; None: nowhere, snapshots off) and the
    most bytes the cache's own folders there may hold (``limit``)."""

    root: Path | None
    limit: int = int(DEFAULT_LIMIT_GB * 1e9)

    @classmethod
    def from_env(cls, environ=None) -> "SnapshotCache":
        """The cache that ``$MI_AMR_CACHE`` and ``$MI_AMR_CACHE_GB`` describe (see the module
        docstring); ``environ`` defaults to the process's environment."""
        environ = os.environ if environ is None else environ
        env = environ.get("MI_AMR_CACHE")
        if env is not None and env.strip().lower() in _OFF:
            return cls(None, 0)
        if env:
            return cls(Path(env).expanduser(), limit_bytes(environ))
        base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        return cls(Path(base) / "mi_amr" / "prepared", limit_bytes(environ))

    @classmethod
    def off(cls) -> "SnapshotCache":
        """No snapshot read or written."""
        return cls(None, 0)

    @property
    def enabled(self) -> bool:
        return self.root is not None

    def load(self, key: str):
        """``(volume, tree_state, bricks, ranges, meta)`` of entry ``key``, or None when there
        is none. A damaged entry is warned about, removed, and None returned; a folder of that
        name that is not the cache's own is warned about and left alone. Marks the entry as
        recently used."""
        if self.root is None:
            return None
        root_fd = folder.open_root(self.root, create=False)
        if root_fd is None:
            return None
        try:
            return _load(root_fd, self.root / key, key)
        finally:
            os.close(root_fd)

    def holds(self, prepared, copies: int = 1) -> bool:
        """Whether ``copies`` entries the size of ``prepared``'s fit within the limit."""
        return self.root is not None and _entry_bytes(prepared) * max(1, copies) <= self.limit

    def save(self, key: str, prepared) -> bool:
        """Write ``prepared`` (a :class:`PreparedVolume`) as entry ``key``; False (with a
        warning) when it cannot be written. Evicts the least recently used entries beyond the
        limit. Interrupted (Ctrl-C), it removes its temporary folder and lets the interrupt go
        on."""
        if self.root is None:
            return False
        need = _entry_bytes(prepared)
        if need > self.limit:
            warnings.warn(f"mi_amr: no snapshot kept: {prepared.volume.source} prepared takes "
                          f"about {need / 1e9:.2f} GB, more than the snapshot cache's limit of "
                          f"{self.limit / 1e9:.2f} GB (MI_AMR_CACHE_GB)")
            self._sweep(None)                   # a lowered limit holds all the same
            return False
        try:
            root_fd = folder.open_root(self.root, create=True)
            try:
                placed = _save(root_fd, key, prepared)
                folder.sweep(root_fd, self.limit, keep=key)
                placed = placed and _complete(root_fd, key)
            finally:
                os.close(root_fd)
        except (OSError, TypeError) as exc:     # TypeError: a value the format cannot hold
            warnings.warn(f"mi_amr: could not write a snapshot in {self.root} ({exc}); set "
                          f"MI_AMR_CACHE to another folder, or to off")
            return False
        return placed

    def _sweep(self, keep: str | None) -> None:
        """Evict down to the limit (best effort)."""
        with contextlib.suppress(OSError):
            root_fd = folder.open_root(self.root, create=False)
            if root_fd is not None:
                try:
                    folder.sweep(root_fd, self.limit, keep=keep)
                finally:
                    os.close(root_fd)

    def save_ranges(self, key: str, kind: str, host: np.ndarray) -> None:
        """Add leaf value ranges (``kind`` ``basis`` or ``finest``) to entry ``key`` if it
        exists (best effort: a failure only costs recomputing them next time)."""
        if self.root is None or kind not in ("basis", "finest"):
            return
        with contextlib.suppress(OSError, BadFile, ValueError, RecursionError):
            fd = os.open(self.root / key, _DIR)
            try:
                if folder.read_marker(fd) is not None:
                    _add_ranges(fd, key, kind, host)
            finally:
                os.close(fd)
        self._sweep(key)                                # the ranges count too


def limit_bytes(environ=None) -> int:
    """The most the snapshot folder may hold, from ``$MI_AMR_CACHE_GB`` (a number of
    gigabytes of 10^9 bytes; anything else is warned about and the default used)."""
    text = (os.environ if environ is None else environ).get("MI_AMR_CACHE_GB")
    try:
        gb = DEFAULT_LIMIT_GB if text is None else float(text)
        if not gb >= 0.0:
            raise ValueError
    except ValueError:
        warnings.warn(f"mi_amr: MI_AMR_CACHE_GB={text!r} is not a number of gigabytes >= 0; "
                      f"using {DEFAULT_LIMIT_GB}")
        gb = DEFAULT_LIMIT_GB
    return int(min(gb, 1e12) * 1e9)


@contextlib.contextmanager
def using(where):
    """``$MI_AMR_CACHE`` set to ``where`` (a folder, or ``"off"``) while the block runs, for
    the caches built from the environment in this process and in the processes it starts;
    restored afterwards. Also a decorator."""
    saved = os.environ.get("MI_AMR_CACHE")
    os.environ["MI_AMR_CACHE"] = str(where)
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("MI_AMR_CACHE", None)
        else:
            os.environ["MI_AMR_CACHE"] = saved


# ---------------------------------------------------------------------- the key

def entry_key(path, field: str, color_field, leaf_cells: int,
              allow_nonfinite: bool = False, keep_fields: bool = True) -> str:
    """The key of the snapshot of ``path`` prepared for ``field``/``color_field`` (with NaN and
    Inf values kept as missing data where ``allow_nonfinite``: a file refused without it has
    no snapshot to be read back from), keeping the fields' values or not (``keep_fields``:
    an entry without them holds the brick pools alone)."""
    parts = (FORMAT, _code_hash(), os.path.abspath(path), _stamp(path), field, color_field,
             int(leaf_cells), bool(allow_nonfinite)) + (() if keep_fields else ("pools",))
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:32]


def _stamp(path) -> tuple:
    """Size and modification time of ``path`` and of the files beside it whose names extend its
    name (``DD0010`` and its ``DD0010.cpu0000`` ... data files, as Enzo writes them), or of
    every file under it (a plotfile folder). What cannot be stat'ed (a dangling link, a loop of
    links) is left out and named in a debug message: the reader decides whether it matters."""
    if not os.path.isdir(path):
        where, name = os.path.split(os.path.abspath(path))
        names = [n for n in sorted(os.listdir(where)) if n == name or n.startswith(name + ".")]
        return tuple(s for s in (_file_stamp(where, n, n) for n in names) if s)
    out = []

    def unreadable(error):
        _log.debug("snapshot key: skipped %s (%s)", error.filename, error.strerror)

    for where, dirs, files in os.walk(path, onerror=unreadable):
        dirs.sort()
        for name in sorted(files):
            rel = os.path.relpath(os.path.join(where, name), path)
            out.append(_file_stamp(where, name, rel))
    return tuple(s for s in out if s)


def _file_stamp(where: str, name: str, label: str):
    """``(label, size, mtime)`` of the file ``name`` in ``where``, or None (debug message)."""
    try:
        st = os.stat(os.path.join(where, name))
    except OSError as e:
        _log.debug("snapshot key: skipped %s (%s)", os.path.join(where, name), e.strerror)
        return None
    return label, st.st_size, st.st_mtime_ns


@functools.lru_cache(maxsize=1)
def _code_hash() -> str:
    """A hash of every Python source file of the package: new code, new keys."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


# ---------------------------------------------------------------------- reading

def _load(root_fd: int, entry: Path, key: str):
    """:meth:`SnapshotCache.load` in the cache folder open as ``root_fd``."""
    try:
        fd = os.open(key, _DIR, dir_fd=root_fd)
    except FileNotFoundError:
        return None
    except OSError as exc:
        warnings.warn(f"mi_amr: {entry} is not a snapshot of this cache ({exc.strerror}); "
                      f"left alone, the volume is prepared without it")
        return None
    try:
        if folder.read_marker(fd) is None:
            warnings.warn(f"mi_amr: {entry} is not a snapshot of this cache (no marker of "
                          f"format {FORMAT}); left alone, the volume is prepared without it")
            return None
        try:
            with rawarrays.Checks() as checks:
                snap = _read_entry(fd, key, checks)
                checks.verify()
        except (BadFile, OSError, ValueError, TypeError, KeyError, RecursionError) as exc:
            warnings.warn(f"mi_amr: dropping the unreadable snapshot {entry} ({exc}); "
                          f"preparing the volume afresh")
            folder.remove(root_fd, key)
            return None
        with contextlib.suppress(OSError):
            os.utime(META, dir_fd=fd, follow_symlinks=False)
        return snap
    finally:
        os.close(fd)


def _read_meta(fd: int, key: str) -> dict:
    """The checked body of the entry's ``meta.json`` (see :func:`_write_meta`)."""
    with rawarrays.open_regular(fd, META) as f:
        text = f.read(_MAX_META + 1)
    expect(len(text) <= _MAX_META, f"{META}: larger than {_MAX_META} bytes")
    head, sep, body = text.partition(b"\n")
    expect(sep, f"{META}: no header line")
    try:
        header = json.loads(head.decode("utf-8"))
    except ValueError:
        raise BadFile(f"{META}: unreadable header line") from None
    expect(isinstance(header, dict) and set(header) == {"kind", "format", "key", "crc32"} and
           header["kind"] == _META_KIND and header["format"] == FORMAT and
           header["key"] == key, f"{META}: not the metadata of entry {key} of format {FORMAT}")
    expect(header["crc32"] == zlib.crc32(body), f"{META}: checksum mismatch")
    try:
        return _checked_body(json.loads(body.decode("utf-8")))
    except (ValueError, RecursionError) as e:
        raise BadFile(f"{META}: unreadable ({type(e).__name__})") from None


def _read_entry(fd: int, key: str, checks):
    """What :meth:`SnapshotCache.load` returns, read from the entry open as ``fd``; the
    arrays' checksums computed by ``checks`` (a :class:`~mi_amr.core.rawarrays.Checks`,
    verified by the caller)."""
    meta = _read_meta(fd, key)
    records = meta["arrays"]

    def get(name, into=None, now=False):
        """The array ``name`` (or the one a ``{"$array": name}`` reference names); ``now``:
        verified before it is returned (what sizes the other arrays)."""
        name = name["$array"] if isinstance(name, dict) else name
        expect(isinstance(name, str) and name in records, f"no array {name!r}")
        return rawarrays.read_array(fd, records[name], into, None if now else checks)

    vol = meta["volume"]
    volume = _volume(vol, dict(zip(vol["fields"], meta["fields"])), get, records)
    tree = rawarrays.decode(meta["tree"], get)
    problem = state_problem(tree, len(volume.grids))
    expect(problem is None, f"tree: {problem}")
    parts = [(np.array(b["lo"], dtype=np.int64), np.array(b["dims"], dtype=np.int64),
              get(b["table"]), b["count"]) for b in meta["bricks"]]
    pools = [get(r) for r in meta["pools"]]
    ranges = {kind: get(r) for kind, r in meta["ranges"].items()}
    kept = {k: meta[k] for k in ("field", "color_field", "value_ranges") if k in meta}
    return volume, tree, (parts, pools), ranges, kept


def _checked_body(body) -> dict:
    """``body`` when each of its fields has the type and range it should (the arrays are
    checked against their records as they are read); otherwise :class:`BadFile`."""
    keys = {"field", "color_field", "volume", "tree", "bricks", "pools", "fields", "ranges",
            "arrays"}
    expect(isinstance(body, dict) and set(body) - {"value_ranges"} == keys,
           "meta: unexpected fields")
    expect(isinstance(body["arrays"], dict), "meta: arrays")
    for name, record in body["arrays"].items():
        rawarrays.check_record(name, record)
    vol = body["volume"]
    expect(isinstance(vol, dict) and set(vol) == {"level", "origin", "spacing", "shape",
                                                  "index_lo", "anchor", "fields", "ratios",
                                                  "allow_nonfinite", "source"}, "meta: volume")
    names = vol["fields"]
    expect(isinstance(names, list) and len(set(names)) == len(names) and
           all(isinstance(n, str) for n in names), "meta: field names")
    # An entry holds the field and the colour field, or (made for the basis blend alone)
    # none, and their value ranges.
    shown = names or body.get("value_ranges")
    expect(isinstance(shown, (list, dict)) and body["field"] in shown and
           body["color_field"] in shown, "meta: field")
    expect(bool(names) != ("value_ranges" in body) and _value_ranges(body), "meta: value ranges")
    ratios = vol["ratios"]
    expect(isinstance(ratios, list) and len(ratios) < 64 and
           all(type(r) is int and 2 <= r <= 64 for r in ratios), "meta: ratios")
    expect(type(vol["allow_nonfinite"]) is bool, "meta: allow_nonfinite")
    expect(vol["source"] is None or isinstance(vol["source"], str), "meta: source")
    _check_arrays(body, len(ratios) + 1)
    expect(isinstance(body["tree"], dict), "meta: tree")
    return body


def _value_ranges(body: dict) -> bool:
    """Whether ``body``'s value ranges (where it has them) are a pair of floats by name."""
    ranges = body.get("value_ranges", {})
    return isinstance(ranges, dict) and all(
        isinstance(k, str) and isinstance(v, list) and len(v) == 2 and
        all(type(x) is float for x in v) for k, v in ranges.items())


def _check_arrays(body: dict, num_levels: int) -> None:
    """The array references of ``body`` name arrays of the right kinds and shapes."""
    records, vol = body["arrays"], body["volume"]

    def ref(r, dtypes, shape=None):
        expect(isinstance(r, dict) and set(r) == {"$array"} and r["$array"] in records,
               f"meta: bad array reference {r!r}")
        rec = records[r["$array"]]
        expect(rec["dtype"] in dtypes and (shape is None or rec["shape"] == shape),
               f"{rec['file']}: {rec['dtype']} {rec['shape']}, expected {dtypes} {shape}")
        return rec

    ints, f8 = ("<i4", "<i8"), ("<f8",)
    grids = ref(vol["level"], ints)["shape"]
    expect(len(grids) == 1, "meta: level")
    for name, dtypes in (("origin", f8), ("spacing", f8), ("shape", ints),
                         ("index_lo", ints)):
        ref(vol[name], dtypes, [grids[0], 3])
    ref(vol["anchor"], f8, [3])
    fields = body["fields"]
    expect(isinstance(fields, list) and len(fields) == len(vol["fields"]) and
           all(isinstance(f, list) and len(f) == num_levels for f in fields), "meta: fields")
    for per_level in fields:
        dtype = ref(per_level[0], ("<f4", "<f8"))["dtype"]
        for r in per_level:
            ref(r, (dtype,))
    bricks = body["bricks"]
    expect(isinstance(bricks, list) and len(bricks) == num_levels, "meta: bricks")
    for b in bricks:
        expect(isinstance(b, dict) and set(b) == {"lo", "dims", "count", "table"} and
               _ints(b["lo"], -2 ** 40) and _ints(b["dims"], 0) and
               type(b["count"]) is int and b["count"] >= 0, "meta: bricks")
        ref(b["table"], ("<u4", "<i4", "<i8", "<u8"))
    expect(isinstance(body["pools"], list) and 1 <= len(body["pools"]) <= 2, "meta: pools")
    for r in body["pools"]:
        expect(len(ref(r, ("<f4",))["shape"]) == 1, "meta: pool shape")
    expect(isinstance(body["ranges"], dict) and set(body["ranges"]) <= {"basis", "finest"},
           "meta: ranges")
    for r in body["ranges"].values():
        ref(r, ("<f4",))


def _ints(values, lowest: int) -> bool:
    return isinstance(values, list) and len(values) == 3 and \
        all(type(v) is int and lowest <= v < 2 ** 40 for v in values)


def _volume(state: dict, fields: dict, get, records: dict) -> AMRVolume:
    """The volume of a snapshot: grid records whose fields are views of the per-level flat
    arrays (which also become the volume's cached :func:`levels.level_values`)."""
    level, shape = get(state["level"], now=True), get(state["shape"], now=True)
    num_levels = len(state["ratios"]) + 1
    expect(level.size == 0 or (level.min() >= 0 and level.max() < num_levels), "level range")
    expect(shape.size == 0 or shape.min() >= 1, "grid shape")
    counts = np.prod(shape, axis=1)
    sizes = [int(counts[level == lv].sum()) for lv in range(num_levels)]
    flats = {}
    for name, refs in fields.items():
        dtype = np.dtype(records[refs[0]["$array"]]["dtype"])
        for lv, part in enumerate(aligned_parts(sizes, dtype)):
            flats[(lv, name)] = get(refs[lv], into=part)
    grid_fields = [dict() for _ in level]
    for lv in range(num_levels):
        ids = np.flatnonzero(level == lv)
        starts = np.concatenate([[0], np.cumsum(counts[ids])[:-1]])
        for name in fields:
            flat = flats[(lv, name)]
            for g, start in zip(ids, starts):
                n = int(counts[g])
                grid_fields[g][name] = flat[start:start + n].reshape(tuple(shape[g]))
    origin, spacing = get(state["origin"]), get(state["spacing"])
    grids = tuple(Grid(int(lv), tuple(o), tuple(h), tuple(int(n) for n in sh), f)
                  for lv, o, h, sh, f in zip(level, origin.tolist(), spacing.tolist(), shape,
                                             grid_fields))
    # Trusted: the hierarchy was validated by from_grids when the snapshot was made.
    volume = AMRVolume(grids, allow_nonfinite=state["allow_nonfinite"], source=state["source"],
                       index_lo=get(state["index_lo"]),
                       ratios=tuple(state["ratios"]), anchor=get(state["anchor"]))
    for (lv, name), flat in flats.items():
        levels.adopt_level_values(volume, lv, name, flat,
                                  [grid_fields[g][name] for g in np.flatnonzero(level == lv)])
    return volume


# ---------------------------------------------------------------------- writing

def _save(root_fd: int, key: str, prepared) -> bool:
    """Write entry ``key`` in a new temporary folder of the cache folder ``root_fd`` and
    rename it into place; True when the entry is there afterwards (another process may have
    placed it first). Whatever ends the write early, the temporary folder goes with it."""
    tmp = folder.TMP + secrets.token_hex(8)
    os.mkdir(tmp, 0o777, dir_fd=root_fd)            # the umask decides who may read it
    try:
        fd = os.open(tmp, _DIR, dir_fd=root_fd)
        try:
            folder.write_marker(fd)
            _write_entry(fd, key, prepared)
        finally:
            os.close(fd)
        if _exists(root_fd, key):
            folder.remove(root_fd, tmp)
        else:
            os.rename(tmp, key, src_dir_fd=root_fd, dst_dir_fd=root_fd)
    except BaseException:
        folder.remove(root_fd, tmp)
        raise
    return _complete(root_fd, key)


def _entry_bytes(prepared) -> int:
    """About what the entry of ``prepared`` takes on disk: its fields, brick pools, leaf
    ranges and kd-tree arrays (the metadata and tables are small beside them)."""
    parts = [prepared.volume.nbytes]
    parts += [np.asarray(pool).nbytes for pool in prepared.device.host_bricks[1]]
    parts += [np.asarray(host).nbytes for host in prepared.device.host_ranges.values()]
    parts += [np.asarray(a).nbytes for a in prepared.tree.arrays().values()
              if isinstance(a, np.ndarray)]
    return int(sum(parts))


def _exists(root_fd: int, name: str) -> bool:
    try:
        os.stat(name, dir_fd=root_fd, follow_symlinks=False)
    except FileNotFoundError:
        return False
    return True


def _complete(root_fd: int, key: str) -> bool:
    """Entry ``key`` is there, the cache's own, with its metadata."""
    try:
        fd = os.open(key, _DIR, dir_fd=root_fd)
    except OSError:
        return False
    try:
        return folder.read_marker(fd) is not None and _exists(fd, META)
    finally:
        os.close(fd)


def _write_entry(fd: int, key: str, prepared) -> None:
    """The arrays of ``prepared`` and, last, the ``meta.json`` that describes them, in the new
    folder open as ``fd``."""
    records = {}

    def put(name, array):
        records[name] = rawarrays.write_array(fd, name + ".arr", np.asarray(array))

    vol, dev = prepared.volume, prepared.device
    parts, pools = dev.host_bricks
    fields = [[rawarrays.encode(levels.level_values(vol, lv, name), f"field{lv}_{i}", put)
               for lv in range(vol.num_levels)] for i, name in enumerate(vol.field_names)]
    tree_state = prepared.tree.arrays()         # (KDTree.STATE: what from_arrays takes)
    body = {"field": prepared.field, "color_field": prepared.color_field,
            "volume": rawarrays.encode(_volume_state(vol), "volume", put),
            "tree": rawarrays.encode(tree_state, "tree", put), "fields": fields,
            "bricks": [{"lo": [int(v) for v in p[0]], "dims": [int(v) for v in p[1]],
                        "count": int(p[3]), "table": rawarrays.encode(p[2], f"table{lv}", put)}
                       for lv, p in enumerate(parts)],
            "pools": [rawarrays.encode(np.asarray(pool), f"pool{i}", put)
                      for i, pool in enumerate(pools)],
            "ranges": {kind: rawarrays.encode(host, f"ranges_{kind}", put)
                       for kind, host in dev.host_ranges.items()},
            "arrays": records}
    if not vol.field_names:         # (made for the basis blend alone: no values)
        body["value_ranges"] = {name: [float(v) for v in r]
                                for name, r in prepared.value_ranges.items()}
    _write_meta(fd, key, body, META)


def _write_meta(fd: int, key: str, body: dict, name: str) -> None:
    """``meta.json``: a header line (what it is, its format, the entry's key, the CRC-32 of
    the rest) and the JSON ``body``; written as the new file ``name`` in the folder ``fd``."""
    text = json.dumps(body, separators=(",", ":"), allow_nan=True).encode()
    head = json.dumps({"kind": _META_KIND, "format": FORMAT, "key": key,
                       "crc32": zlib.crc32(text)}).encode()
    out = os.open(name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                  0o666, dir_fd=fd)
    with os.fdopen(out, "wb") as f:
        f.write(head + b"\n" + text)


def _volume_state(vol) -> dict:
    return {"level": vol.levels, "origin": vol.grid_boxes()[0],
            "spacing": vol.spacings(), "shape": vol.shapes(),
            "fields": list(vol.field_names), "allow_nonfinite": bool(vol.allow_nonfinite),
            "source": None if vol.source is None else str(vol.source),
            "index_lo": vol.index_boxes()[0], "ratios": [int(r) for r in vol.ratios],
            "anchor": np.asarray(vol.anchor, dtype=np.float64)}


def _add_ranges(fd: int, key: str, kind: str, host: np.ndarray) -> None:
    """Write ``host`` as the ranges of ``kind`` in the entry open as ``fd`` and replace its
    ``meta.json`` by one that lists them (each file new, then renamed over the old one)."""
    body = _read_meta(fd, key)
    token = secrets.token_hex(4)
    name = f"ranges_{kind}.{token}"
    try:
        record = rawarrays.write_array(fd, name + ".arr", np.asarray(host, dtype=np.float32))
        body["arrays"][name] = record
        old = body["ranges"].get(kind)
        old = None if old is None else body["arrays"].pop(old["$array"])
        body["ranges"][kind] = {"$array": name}
        _write_meta(fd, key, body, f"{META}.{token}")
        os.replace(f"{META}.{token}", META, src_dir_fd=fd, dst_dir_fd=fd)
    except BaseException:           # interrupted, or a full disk: leave the entry as it was
        for leftover in (name + ".arr", f"{META}.{token}"):
            with contextlib.suppress(OSError):
                os.unlink(leftover, dir_fd=fd)
        raise
    if old is not None:
        with contextlib.suppress(OSError):
            os.unlink(old["file"], dir_fd=fd)
