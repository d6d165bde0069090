"""A disk cache of prepared volumes (*snapshots*): loading the same data again is a read.

Preparing a volume (derived fields, kd-tree, brick pools, leaf value ranges) costs about a
hundred times reading the file. A snapshot keeps the result as raw arrays; reloading reads
them into aligned memory that Dr.Jit maps as it is, and trusts the hierarchy (it was validated
when the snapshot was made).

An entry is a folder named by a key covering everything the preparation depends on: the data's
absolute path, the size and modification time of every file under it, the fields, ``leaf_cells``
and the code itself (a hash of the package's source files). Any change gives another key, so a
stale entry is never used; it is evicted in time. Leaf value ranges are added to the entry when
a render first computes them.

Where: ``$MI_AMR_CACHE`` (a folder; ``off`` turns snapshots off), else
``$XDG_CACHE_HOME/mi_amr/prepared`` (``~/.cache/mi_amr/prepared``). At most ``$MI_AMR_CACHE_GB``
gigabytes (default :data:`DEFAULT_LIMIT_GB`): the least recently used entries are removed first.
An entry is written in a temporary folder and renamed into place, so a crash or two processes
preparing at once never leave half an entry; an entry that cannot be read is removed and the
volume prepared afresh. Nothing outside the cache folder is ever written or removed.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import pickle
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from mi_amr.core import levels
from mi_amr.core.volume import AMRVolume, Grid
from mi_amr.core.buffers import aligned_empty, aligned_parts

FORMAT = 1                  # bump when the layout below changes
# False: no snapshot is read or written in this process (benchmarks of first loads set it).
ENABLED = True
DEFAULT_LIMIT_GB = 8.0
_META = "meta.pkl"
_STALE_TMP_S = 3600.0       # a temporary folder older than this was left by a crash


def cache_root() -> Path | None:
    """The snapshot folder, or None when ``$MI_AMR_CACHE`` is ``off`` (or ``0``, ``none``) or
    :data:`ENABLED` is False."""
    if not ENABLED:
        return None
    env = os.environ.get("MI_AMR_CACHE")
    if env is not None and env.strip().lower() in ("off", "0", "none", "no", "false", ""):
        return None
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mi_amr" / "prepared"


@contextlib.contextmanager
def using(folder):
    """Snapshots in ``folder`` (or none for ``"off"``) while the block runs, in this process
    and in the processes it starts (``$MI_AMR_CACHE``, :data:`ENABLED`); restored afterwards."""
    global ENABLED
    saved = os.environ.get("MI_AMR_CACHE"), ENABLED
    os.environ["MI_AMR_CACHE"], ENABLED = str(folder), True
    try:
        yield
    finally:
        ENABLED = saved[1]
        if saved[0] is None:
            os.environ.pop("MI_AMR_CACHE", None)
        else:
            os.environ["MI_AMR_CACHE"] = saved[0]


def limit_bytes() -> int:
    """The most the snapshot folder may hold, from ``$MI_AMR_CACHE_GB`` (a number of
    gigabytes; anything else is warned about and the default used)."""
    text = os.environ.get("MI_AMR_CACHE_GB")
    try:
        gb = DEFAULT_LIMIT_GB if text is None else float(text)
        if not gb >= 0.0:
            raise ValueError
    except ValueError:
        warnings.warn(f"mi_amr: MI_AMR_CACHE_GB={text!r} is not a number of gigabytes >= 0; "
                      f"using {DEFAULT_LIMIT_GB}")
        gb = DEFAULT_LIMIT_GB
    return int(gb * 2 ** 30)


def entry_key(path, field: str, color_field, leaf_cells: int) -> str:
    """The key of the snapshot of ``path`` prepared for ``field``/``color_field``."""
    parts = (FORMAT, _code_hash(), os.path.abspath(path), _stamp(path), field, color_field,
             int(leaf_cells))
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:32]


def _stamp(path) -> tuple:
    """Size and modification time of ``path`` and of the files beside it whose names extend its
    name (``DD0010`` and its ``DD0010.cpu0000`` ... data files, as Enzo writes them), or of
    every file under it (a plotfile folder)."""
    if not os.path.isdir(path):
        folder, name = os.path.split(os.path.abspath(path))
        out = []
        for other in sorted(os.listdir(folder)):
            if other == name or other.startswith(name + "."):
                st = os.stat(os.path.join(folder, other))
                out.append((other, st.st_size, st.st_mtime_ns))
        return tuple(out)
    out = []
    for folder, dirs, files in os.walk(path):
        dirs.sort()
        for name in sorted(files):
            st = os.stat(os.path.join(folder, name))
            out.append((os.path.relpath(os.path.join(folder, name), path), st.st_size,
                        st.st_mtime_ns))
    return tuple(out)


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

def load(key: str):
    """``(volume, tree_state, bricks, ranges, meta)`` of entry ``key``, or None when there is
    none (or it cannot be read: then it is removed). Marks the entry as recently used."""
    root = cache_root()
    if root is None:
        return None
    entry = root / key
    if not (entry / _META).is_file():
        return None
    try:
        with open(entry / _META, "rb") as f:
            meta = pickle.load(f)
        if meta.get("format") != FORMAT:
            raise ValueError(f"format {meta.get('format')}")
        volume = _volume(entry, meta["volume"])
        parts = [(lo, dims, _read(entry / f"table{level}.npy"), n)
                 for level, (lo, dims, n) in enumerate(meta["bricks"])]
        pools = [_read(entry / f"pool{i}.npy") for i in range(meta["pools"])]
        ranges = {kind: _read(entry / f"ranges_{kind}.npy") for kind in ("basis", "finest")
                  if (entry / f"ranges_{kind}.npy").is_file()}
        os.utime(entry / _META)
    except Exception as exc:  # noqa: BLE001 - any unreadable entry is dropped, never fatal
        warnings.warn(f"mi_amr: dropping the unreadable snapshot {entry} ({exc})")
        shutil.rmtree(entry, ignore_errors=True)
        return None
    return volume, meta["tree"], (parts, pools), ranges, meta


def _read(path, into=None) -> np.ndarray:
    """A ``.npy`` file read straight into new :data:`~mi_amr.core.buffers.ALIGN`-aligned memory,
    or into the flat array ``into`` (which must have its size and dtype)."""
    with open(path, "rb") as f:
        shape, fortran, dtype = _header(f)
        if fortran or dtype.hasobject:
            raise ValueError(f"{path.name}: not a plain C-ordered array")
        size = int(np.prod(shape))
        if into is not None and (into.size != size or into.dtype != dtype):
            raise ValueError(f"{path.name}: {size} values of {dtype}, expected {into.size} of "
                             f"{into.dtype}")
        out = aligned_empty(size, dtype) if into is None else into
        if f.readinto(memoryview(out.view(np.uint8))) != out.nbytes:
            raise ValueError(f"{path.name}: truncated")
    return out.reshape(shape)


def _header(f):
    """``(shape, fortran_order, dtype)`` of the ``.npy`` file open in ``f`` (left at its data)."""
    version = np.lib.format.read_magic(f)
    header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
        np.lib.format.read_array_header_2_0
    return header(f)


def _field_levels(entry: Path, state: dict, name: str) -> list:
    """Field ``name``'s per-level flat arrays, read into consecutive slices of one aligned
    buffer (level after level), so that the device maps it as it is when the grids are in
    level order (:func:`mi_amr.core.buffers.joined`)."""
    num_levels = len(state["ratios"]) + 1
    counts = np.prod(state["shape"], axis=1)
    sizes = [int(counts[state["level"] == level].sum()) for level in range(num_levels)]
    with open(entry / f"field0_{name}.npy", "rb") as f:
        dtype = _header(f)[2]
    return [_read(entry / f"field{level}_{name}.npy", into=part)
            for level, part in enumerate(aligned_parts(sizes, dtype))]


def _volume(entry: Path, state: dict) -> AMRVolume:
    """The volume of a snapshot: grid records whose fields are views of the per-level flat
    arrays (which also become the volume's cached :func:`levels.level_values`)."""
    flats = {(level, name): flat for name in state["fields"]
             for level, flat in enumerate(_field_levels(entry, state, name))}
    fields = [dict() for _ in state["level"]]
    for level in range(len(state["ratios"]) + 1):
        ids = np.flatnonzero(state["level"] == level)
        counts = np.prod(state["shape"][ids], axis=1)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        for name in state["fields"]:
            flat = flats[(level, name)]
            for g, start, n in zip(ids, starts, counts):
                fields[g][name] = flat[start:start + n].reshape(tuple(state["shape"][g]))
    grids = tuple(Grid(int(lv), tuple(o), tuple(h), tuple(int(n) for n in sh), f)
                  for lv, o, h, sh, f in zip(state["level"], state["origin"].tolist(),
                                             state["spacing"].tolist(), state["shape"], fields))
    # Trusted: the hierarchy was validated by from_grids when the snapshot was made.
    volume = AMRVolume(grids, allow_nonfinite=state["allow_nonfinite"], source=state["source"],
                       index_lo=state["index_lo"], ratios=state["ratios"],
                       anchor=state["anchor"])
    for (level, name), flat in flats.items():
        levels.share_level_values(volume, level, name, flat)
    return volume


# ---------------------------------------------------------------------- writing

def save(key: str, prepared) -> bool:
    """Write ``prepared`` (a :class:`PreparedVolume`) as entry ``key``; False (with a warning)
    when it cannot be written. Evicts the least recently used entries beyond the limit."""
    root = cache_root()
    if root is None:
        return False
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=root))
        try:
            _write(tmp, prepared)
            os.rename(tmp, root / key)
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if not (root / key / _META).is_file():
                raise
        evict(root, limit_bytes(), keep=key)
    except OSError as exc:
        warnings.warn(f"mi_amr: could not write a snapshot in {root} ({exc}); set MI_AMR_CACHE "
                      f"to another folder, or to off")
        return False
    return True


def _write(folder: Path, prepared) -> None:
    vol, dev = prepared.volume, prepared.device
    parts, pools = dev.host_bricks
    for level in range(vol.num_levels):
        for name in vol.field_names:
            np.save(folder / f"field{level}_{name}.npy", levels.level_values(vol, level, name))
    for level, part in enumerate(parts):
        np.save(folder / f"table{level}.npy", part[2])
    for i, pool in enumerate(pools):
        np.save(folder / f"pool{i}.npy", pool)
    for kind, host in dev.host_ranges.items():
        np.save(folder / f"ranges_{kind}.npy", host)
    tree_state = {k: v for k, v in prepared.tree.__dict__.items() if k != "volume"}
    meta = {"format": FORMAT, "field": prepared.field, "color_field": prepared.color_field,
            "volume": _volume_state(vol), "tree": tree_state, "pools": len(pools),
            "bricks": [(p[0], p[1], int(p[3])) for p in parts]}
    # meta.pkl last: an entry is complete when it has one.
    with open(folder / _META, "wb") as f:
        pickle.dump(meta, f, protocol=pickle.HIGHEST_PROTOCOL)


def _volume_state(vol) -> dict:
    return {"level": vol.levels, "origin": vol.grid_boxes()[0],
            "spacing": vol.spacings(), "shape": vol.shapes(),
            "fields": list(vol.field_names), "allow_nonfinite": vol.allow_nonfinite,
            "source": vol.source, "index_lo": vol.index_boxes()[0], "ratios": vol.ratios,
            "anchor": vol.anchor}


def save_ranges(key: str, kind: str, host: np.ndarray) -> None:
    """Add leaf value ranges (``kind`` ``basis`` or ``finest``) to entry ``key`` if it exists
    (best effort: a failure only costs recomputing them next time)."""
    root = cache_root()
    if root is None or not (root / key / _META).is_file():
        return
    try:
        with tempfile.NamedTemporaryFile(dir=root / key, suffix=".npy", delete=False) as f:
            np.save(f, host)
        os.replace(f.name, root / key / f"ranges_{kind}.npy")
    except OSError:
        pass


def evict(root: Path, limit: int, keep: str | None = None) -> None:
    """Remove the least recently used entries of ``root`` until it holds at most ``limit``
    bytes (never ``keep``), and temporary folders a crash left behind."""
    now = time.time()
    entries = []
    for entry in root.iterdir():
        if entry.name.startswith(".tmp-"):
            if now - entry.stat().st_mtime > _STALE_TMP_S:
                shutil.rmtree(entry, ignore_errors=True)
            continue
        if not entry.is_dir():
            continue
        size = sum(f.stat().st_size for f in entry.iterdir())
        meta = entry / _META
        used = meta.stat().st_mtime if meta.is_file() else 0.0
        entries.append((used, size, entry))
    total = sum(size for _, size, _ in entries)
    for used, size, entry in sorted(entries, key=lambda e: e[0]):
        if total <= limit:
            break
        if entry.name != keep:
            shutil.rmtree(entry, ignore_errors=True)
            total -= size
