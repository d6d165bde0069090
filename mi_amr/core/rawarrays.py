"""Arrays on disk as raw bytes behind a small header, each described by a *record* that carries
its CRC-32, and nested states (dicts, lists, tuples, numbers, strings) written as JSON whose
arrays are such files. What the snapshot cache (:mod:`mi_amr.kernels.snapshot`) stores: read
back without running any code (no pickle) and verified byte for byte.

An array file holds :data:`MAGIC` (8 bytes), the header's length (4 bytes, little-endian), the
header (ASCII JSON ``{"dtype", "shape", "nbytes"}``, padded with spaces so that the data starts
on a :data:`~mi_amr.core.buffers.ALIGN`-byte boundary), then ``nbytes`` bytes of C-ordered
data. Its record, ``{"file", "dtype", "shape", "nbytes", "crc32"}``, is kept by the caller:
reading checks that the header says what the record says, that the file holds exactly the
header and ``nbytes`` bytes, and that the data's CRC-32 is the record's.

Files are opened relative to a folder's descriptor (``dir_fd``), never through a symbolic link,
and only when they are regular files (a planted FIFO or device is refused, not opened).
"""

from __future__ import annotations

import json
import os
import re
import stat
import struct
import zlib
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from mi_amr.core.buffers import ALIGN, aligned_empty

MAGIC = b"MIAMRAR\x01"
# Little-endian numbers and booleans only: never an object array, nothing that runs code.
DTYPES = frozenset(("|b1", "|i1", "|u1", "<i2", "<u2", "<i4", "<u4", "<i8", "<u8", "<f4",
                    "<f8"))
CHUNK = 1 << 22             # bytes read and checksummed at a time (stays in the CPU's cache)
MAX_HEADER = 4096           # bytes: a longer header is damage, not an array
MAX_DIMS = 8
MAX_DEPTH = 32              # nesting of a state: deeper is damage
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,119}")
_READ = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC
_CREATE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


class BadFile(ValueError):
    """An array file, a record or a state that is not what it should be (damage or a planted
    file); the message names the file and what is wrong."""


def expect(condition, what: str) -> None:
    """Raise :class:`BadFile` saying ``what`` unless ``condition``."""
    if not condition:
        raise BadFile(what)


# ---------------------------------------------------------------------- one array

def write_array(dir_fd: int, name: str, array) -> dict:
    """Write ``array`` as the new file ``name`` in the folder open as ``dir_fd`` (created with
    the process's umask; never over an existing file or through a link); returns its record."""
    a = np.ascontiguousarray(array)
    if a.dtype.str not in DTYPES:
        raise TypeError(f"{name}: arrays of {a.dtype} are not stored")
    expect(_NAME.fullmatch(name), f"{name!r} is not an array file name")
    header = json.dumps({"dtype": a.dtype.str, "shape": list(a.shape),
                         "nbytes": a.nbytes}).encode()
    header += b" " * ((-(len(MAGIC) + 4 + len(header))) % ALIGN)
    data = memoryview(a.reshape(-1).view(np.uint8))
    fd = os.open(name, _CREATE, 0o666, dir_fd=dir_fd)
    with os.fdopen(fd, "wb") as f:
        f.write(MAGIC + struct.pack("<I", len(header)) + header)
        f.write(data)
    return {"file": name, "dtype": a.dtype.str, "shape": list(a.shape), "nbytes": a.nbytes,
            "crc32": crc32(data)}


def crc32(data: memoryview) -> int:
    """CRC-32 of ``data`` (bytes), computed :data:`CHUNK` bytes at a time."""
    crc = 0
    for start in range(0, len(data), CHUNK):
        crc = zlib.crc32(data[start:start + CHUNK], crc)
    return crc


def check_record(name: str, record) -> dict:
    """``record`` (as read from JSON) when it describes an array file sensibly: a plain file
    name, a stored dtype, at most :data:`MAX_DIMS` non-negative dimensions, the byte count they
    give and a 32-bit checksum; otherwise :class:`BadFile`."""
    expect(isinstance(record, dict) and set(record) == {"file", "dtype", "shape", "nbytes",
                                                        "crc32"}, f"array {name!r}: bad record")
    expect(isinstance(record["file"], str) and _NAME.fullmatch(record["file"]),
           f"array {name!r}: bad file name")
    expect(record["dtype"] in DTYPES, f"{record['file']}: dtype {record['dtype']!r}")
    shape = record["shape"]
    expect(isinstance(shape, list) and len(shape) <= MAX_DIMS and
           all(_count(n) for n in shape), f"{record['file']}: shape {shape!r}")
    nbytes = int(np.prod(shape, dtype=object)) * np.dtype(record["dtype"]).itemsize
    expect(_count(record["nbytes"]) and record["nbytes"] == nbytes,
           f"{record['file']}: {record['nbytes']!r} bytes for shape {shape}")
    expect(_count(record["crc32"]) and record["crc32"] < 2 ** 32,
           f"{record['file']}: checksum {record['crc32']!r}")
    return record


def _count(n) -> bool:
    return type(n) is int and 0 <= n < 2 ** 48


class Checks:
    """CRC-32s that a worker thread computes while the caller reads on (``zlib.crc32``
    releases the GIL): :func:`read_array` hands it each chunk it has read, :meth:`verify` waits
    for them all. A context manager: leaving it waits for the worker."""

    def __init__(self):
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mi_amr-crc")
        self._files = []        # (file name, the record's CRC, [the CRC so far])

    def start(self, name: str, want: int) -> list:
        self._files.append((name, want, [0]))
        return self._files[-1][2]

    def update(self, state: list, chunk: memoryview) -> None:
        # One worker, first in first out: the chunks of a file are taken in order.
        self._pool.submit(_crc_step, state, chunk)

    def verify(self) -> None:
        """Wait for every checksum; :class:`BadFile` naming the first file that changed."""
        self._pool.shutdown(wait=True)
        for name, want, state in self._files:
            expect(state[0] == want, f"{name}: checksum mismatch (the data changed on disk)")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._pool.shutdown(wait=True)


def _crc_step(state: list, chunk: memoryview) -> None:
    state[0] = zlib.crc32(chunk, state[0])


def read_array(dir_fd: int, record: dict, into: np.ndarray | None = None,
               checks: Checks | None = None) -> np.ndarray:
    """The array of ``record`` (see :func:`check_record`), read from its file in the folder
    open as ``dir_fd`` into new :data:`~mi_amr.core.buffers.ALIGN`-aligned memory, or into
    the flat array ``into`` (which must have its size and dtype); :class:`BadFile` when the
    file is not exactly what the record says (truncated, longer, another header, a changed
    byte). With ``checks``, the checksum is computed there, beside the reading, and compared
    by :meth:`Checks.verify`; without, here (the plain twin)."""
    name = record["file"]
    dtype, size = np.dtype(record["dtype"]), int(np.prod(record["shape"], dtype=np.int64))
    if into is not None:
        expect(into.size == size and into.dtype == dtype and into.flags.c_contiguous,
               f"{name}: {size} values of {dtype}, expected {into.size} of {into.dtype}")
    with open_regular(dir_fd, name) as f:
        start = _read_header(f, record)
        expect(os.fstat(f.fileno()).st_size == start + record["nbytes"],
               f"{name}: {os.fstat(f.fileno()).st_size - start} bytes of data, expected "
               f"{record['nbytes']} (truncated or extended)")
        out = aligned_empty(size, dtype) if into is None else into
        data = memoryview(out.reshape(-1).view(np.uint8))
        state = [0] if checks is None else checks.start(name, record["crc32"])
        for at in range(0, len(data), CHUNK):
            chunk = data[at:at + CHUNK]
            expect(_fill(f, chunk), f"{name}: truncated")
            if checks is None:
                _crc_step(state, chunk)
            else:
                checks.update(state, chunk)
    if checks is None:
        expect(state[0] == record["crc32"],
               f"{name}: checksum mismatch (the data changed on disk)")
    return out.reshape(record["shape"])


def open_regular(dir_fd: int, name: str):
    """``name`` in the folder ``dir_fd`` open for reading, when it is a regular file (not a
    link, FIFO or device: those are refused before anything is read)."""
    fd = os.open(name, _READ, dir_fd=dir_fd)
    try:
        expect(stat.S_ISREG(os.fstat(fd).st_mode), f"{name}: not a regular file")
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return os.fdopen(fd, "rb", buffering=0)


def _read_header(f, record: dict) -> int:
    """Check the header of the array file open as ``f`` against ``record``; returns where
    its data starts (``f`` is left there)."""
    name = record["file"]
    head = f.read(len(MAGIC) + 4)
    expect(len(head) == len(MAGIC) + 4 and head[:len(MAGIC)] == MAGIC,
           f"{name}: not an array file of this format")
    length = struct.unpack("<I", head[len(MAGIC):])[0]
    expect(length <= MAX_HEADER, f"{name}: header of {length} bytes")
    text = f.read(length)
    expect(len(text) == length, f"{name}: truncated header")
    try:
        header = json.loads(text.decode("ascii"))
    except ValueError:
        raise BadFile(f"{name}: unreadable header") from None
    want = {k: record[k] for k in ("dtype", "shape", "nbytes")}
    expect(header == want, f"{name}: header {header} does not match its record {want}")
    return len(head) + length


def _fill(f, view: memoryview) -> bool:
    """Read exactly ``len(view)`` bytes of ``f`` into ``view``; False at the end of the file."""
    done = 0
    while done < len(view):
        got = f.readinto(view[done:])
        if not got:
            return False
        done += got
    return True


# ---------------------------------------------------------------------- nested states

def encode(value, name: str, put):
    """``value`` as JSON data: dicts with string keys, lists, tuples (``{"$tuple": [...]}``),
    ``None``, booleans, numbers and strings as they are (NumPy scalars as Python ones), and each
    array as ``{"$array": NAME}`` after ``put(NAME, array)`` stored it (``NAME`` built from
    ``name`` and the path to the array)."""
    if isinstance(value, np.ndarray):
        put(name, value)
        return {"$array": name}
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        items = [encode(v, f"{name}.{i}", put) for i, v in enumerate(value)]
        return {"$tuple": items} if isinstance(value, tuple) else items
    if isinstance(value, dict) and all(isinstance(k, str) and _NAME.fullmatch(k)
                                       for k in value):
        return {k: encode(v, f"{name}.{k}", put) for k, v in value.items()}
    raise TypeError(f"{name}: {type(value).__name__} values are not stored")


def decode(data, get, depth: int = 0):
    """The value that :func:`encode` turned into ``data``, its arrays ``get(NAME)``;
    :class:`BadFile` for anything :func:`encode` does not write."""
    expect(depth < MAX_DEPTH, "state nested too deep")
    if data is None or isinstance(data, (bool, int, float, str)):
        return data
    if isinstance(data, list):
        return [decode(v, get, depth + 1) for v in data]
    expect(isinstance(data, dict), f"unexpected {type(data).__name__} in a state")
    if set(data) == {"$array"}:
        expect(isinstance(data["$array"], str), "bad array reference")
        return get(data["$array"])
    if set(data) == {"$tuple"}:
        expect(isinstance(data["$tuple"], list), "bad tuple")
        return tuple(decode(v, get, depth + 1) for v in data["$tuple"])
    expect(all(_NAME.fullmatch(k) for k in data), "bad key in a state")
    return {k: decode(v, get, depth + 1) for k, v in data.items()}
