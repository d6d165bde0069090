"""OpenVDB files (``.vdb``): every grid of the file is one AMR patch.

Layout (OpenVDB's ``io::Archive`` and ``io::File``, file format 222 to 225, i.e. OpenVDB 3.0 and
later; all numbers little-endian, a *string* is a ``uint32`` length and that many bytes):

* Header -- ``int64`` magic ``0x56444220``, ``uint32`` file format version, ``uint32`` library
  major and minor version, one byte "has grid offsets" (0 in streams written by ``io::Stream``),
  the UUID as 36 ASCII characters, the file's metadata, the ``int32`` grid count.
* Metadata (of the file or of a grid) -- ``uint32`` count, then per item a name string, a type
  string, a ``uint32`` byte size and that many bytes.
* Grid descriptor -- the unique name (a repeated name gets ``"\\x1e"`` and a number appended),
  the tree type (``Tree_float_5_4_3``; ``_HalfFloat`` appended when the values are stored as
  16-bit floats), the name of the grid whose tree this grid shares ("instance parent", usually
  empty), and three ``int64`` byte offsets: the grid's record, its leaf buffers and its end. In a
  file with grid offsets the next descriptor starts at the end offset, so a grid that is not
  wanted is never read; in a stream the offsets are 0 and the record follows the descriptor.
* Grid record -- ``uint32`` compression flags (``0x1`` zip = zlib, ``0x2`` active-mask, ``0x4``
  Blosc), the grid's metadata, the transform (a map type string and its data), then, unless the
  grid is an instance, the tree: ``int32`` buffer count (1), the *topology* and the *buffers*.
* Topology -- the root node: background value, ``uint32`` tile and child counts, tiles
  (``int32`` origin x, y, z, value, one active byte; a root tile covers 4096^3 voxels), children
  (``int32`` origin, then the child's topology). An internal node (32^3 slots of 128^3 voxels,
  or 16^3 slots of 8^3 voxels): child mask, value (active) mask, the slot values written as
  *compressed values*, then its children in slot order. A leaf (8^3 voxels): its value mask.
  Masks are ``uint64`` words, bit ``n`` of the mask is slot ``n``; slot ``n`` of a node with
  ``2^L`` slots per axis is ``(x, y, z) = (n >> 2L, (n >> L) & (2^L - 1), n & (2^L - 1))``.
* Buffers -- per leaf, in topology order: the value mask again, then its 512 voxel values as
  compressed values.
* Compressed values (``io::writeCompressedValues``) -- one byte saying how inactive values are
  stored (0: background, 1: minus background, 2: one stored value, 3/4/5: a selection mask
  between two of them, 6: every value stored), the stored inactive values (full precision), the
  selection mask, then the data: with active-mask compression only the active values, else all;
  zip or Blosc data is an ``int64`` byte count (negative: that many raw bytes follow) and the
  compressed bytes. Values are ``float32`` (``float16`` in ``_HalfFloat`` grids; no data at all
  when a half grid has nothing to store); tile, background and inactive values are always full
  precision.

Placement: a grid's transform must be a scale ``s`` (one voxel size, or one per axis) plus a
translation ``t`` (any of OpenVDB's scale/translate maps, or an affine map of that form). VDB
index space is cell-centred: voxel ``(i, j, k)`` has its centre at world ``s * (i, j, k) + t``
(per axis) and covers ``s`` around it, so a grid whose active voxels span index ``lo .. hi``
(inclusive) becomes an AMR grid with origin ``s * (lo - 0.5) + t``, spacing ``s`` and shape
``hi - lo + 1``; arrays are indexed ``[i, j, k]`` = x, y, z.

Values: the AMR grid is the bounding box of the grid's *active* voxels (and active tiles). Each
cell takes the value OpenVDB itself returns for that voxel (``getValue``, as ``copyToArray``
does): inactive voxels inside the box keep the inactive value stored in the file, which is the
grid's background unless the writer stored something else. A patch written with
``copyFromArray`` therefore reads back exactly, even where its values equal the background (those
voxels are inactive), as long as its outermost voxels are not all equal to the background (the
box would shrink; ``copyFromArray(..., tolerance=-1)`` keeps every voxel active).

Patches and levels: the coarsest voxel size in the file is level 0; every finer voxel size must be
2 or 4 times smaller than the next coarser one, by the same factor on every axis. Grids with the
same name at several voxel sizes (or several grids of one name at one size) are the patches of
one field; grids of different names at the same voxel size with identical boxes are the fields
of one patch. A ``vec3s`` grid ``v`` gives the fields ``v_x``, ``v_y``, ``v_z``; float grids
keep their names.

Refused with an :class:`~mi_amr.AMRError` naming the file and the grid: other grid types (read
the supported ones with ``fields=[...]``), rotated, sheared or frustum transforms,
grids without active voxels, files older than format 222, and truncated or corrupt data. Blosc
data (OpenVDB's default compression) needs the ``blosc`` package (``pip install blosc``).
"""

from __future__ import annotations

import math
import mmap
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.core.volume import AMRVolume
from mi_amr.readers.fields import requested

MAGIC = 0x56444220
# 222 (OpenVDB 3.0) moved the compression flags into each grid and mask-compressed internal
# nodes; older layouts are not parsed here. 225 is the newest format known to this reader.
MIN_FILE_VERSION = 222
NEWEST_FILE_VERSION = 225

COMPRESS_ZIP, COMPRESS_ACTIVE_MASK, COMPRESS_BLOSC = 0x1, 0x2, 0x4
# Tree type -> components per value; all supported trees are 5-4-3 trees of 32-bit floats.
TREE_TYPES = {"Tree_float_5_4_3": 1, "Tree_vec3s_5_4_3": 3}
HALF_SUFFIX = "_HalfFloat"
NAME_SEPARATOR = "\x1e"
VECTOR_SUFFIXES = ("_x", "_y", "_z")
# Map type -> number of float64 values in its serialisation (see the module docstring).
MAP_SIZES = {"UniformScaleMap": 15, "ScaleMap": 15, "UniformScaleTranslateMap": 18,
             "ScaleTranslateMap": 18, "TranslationMap": 3, "AffineMap": 16}
# Off-diagonal terms of an affine map below this (relative to its scale) count as none, and
# voxel sizes of one map that differ by less count as one: OpenVDB stores the map in doubles,
# so only a real rotation, shear or anisotropy exceeds it.
SCALE_TOLERANCE = 1e-9
# Voxel sizes within this (relative) of each other are one level.
LEVEL_TOLERANCE = 1e-6
# Edge lengths (voxels) of a root tile, a slot of the upper internal node and of the lower one.
ROOT_TILE, UPPER_SLOT, LOWER_SLOT = 4096, 128, 8
# A dense box beyond this many cells is refused rather than allocated: an active root tile
# alone is 4096^3 voxels.
MAX_DENSE_CELLS = 1 << 31


@dataclass(frozen=True)
class GridDescriptor:
    """One grid of a VDB file: names, tree type and the byte range of its record.

    ``grid_pos`` .. ``end_pos`` is the record (file offsets; for streams, found by walking the
    file). ``instance_parent`` is the unique name of the grid whose tree this grid shares.
    """

    index: int
    unique_name: str
    name: str
    tree_type: str
    half: bool
    instance_parent: str
    grid_pos: int
    block_pos: int
    end_pos: int

    @property
    def supported(self) -> bool:
        return self.tree_type in TREE_TYPES

    @property
    def field_names(self) -> tuple:
        """The AMR fields this grid gives: its name, or ``name_x/_y/_z`` for a vector grid."""
        if TREE_TYPES.get(self.tree_type) == 3:
            return tuple(self.name + s for s in VECTOR_SUFFIXES)
        return (self.name,)

    def describe(self) -> str:
        """``grid 'v[1]' (#3, Tree_vec3s_5_4_3)``: the display name OpenVDB's tools use."""
        shown = self.unique_name.replace(NAME_SEPARATOR, "[") + \
            ("]" if NAME_SEPARATOR in self.unique_name else "")
        half = HALF_SUFFIX if self.half else ""
        return f"grid '{shown}' (#{self.index}, {self.tree_type}{half})"


@dataclass(frozen=True)
class VDBHeader:
    """The file header and the descriptors of all grids, in file order."""

    file_version: int
    library_version: tuple
    has_grid_offsets: bool
    uuid: str
    grids: tuple


@dataclass(frozen=True)
class VDBGrid:
    """One decoded grid: its voxel size (per axis, ``(3,)``) and translation (world units), the
    inclusive index box of its active voxels, and the dense values over that box,
    ``(nx, ny, nz, ncomp)`` float32 indexed ``[i, j, k]`` = x, y, z."""

    descriptor: GridDescriptor
    voxel_size: np.ndarray
    translation: np.ndarray
    index_lo: np.ndarray
    index_hi: np.ndarray
    values: np.ndarray

    @property
    def origin(self) -> np.ndarray:
        """World position of the lower corner of the box (voxel centres sit at integers)."""
        return self.voxel_size * (self.index_lo - 0.5) + self.translation

    @property
    def shape(self) -> tuple:
        return tuple(int(n) for n in self.index_hi - self.index_lo + 1)

    def fields(self) -> dict:
        """Field name -> contiguous ``(nx, ny, nz)`` array."""
        d = self.descriptor
        return {name: np.ascontiguousarray(self.values[..., c])
                for c, name in enumerate(d.field_names)}


# ---------------------------------------------------------------------- public entry points

def is_vdb(path) -> bool:
    """True when ``path`` is a regular file that starts with the OpenVDB magic number (other
    files are not opened: reading a FIFO or a device would block)."""
    try:
        if not Path(path).is_file():
            return False
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return False
    return len(head) == 8 and struct.unpack("<q", head)[0] == MAGIC


def field_names(path) -> list:
    """Names of the fields the grids of ``path`` give, from the header only (no voxel data is
    read from files with grid offsets). Grids of unsupported types are left out."""
    return field_names_of(read_header(path))


def load(path, fields=None, *, allow_nonfinite: bool = False) -> AMRVolume:
    """Read the VDB file ``path``; ``fields`` (names) limits the grids read from disk.

    Every grid (of a wanted field) becomes one dense AMR grid over the box of its active voxels
    (see the module docstring for placement, values and levels). Values are float32;
    ``allow_nonfinite=True`` keeps NaN and Inf values as missing data. Raises
    :class:`AMRError` naming the file and the grid for unsupported grid types or transforms,
    voxel sizes that are not a 2/4 chain, grids of one patch whose boxes differ, and truncated
    or corrupt files.
    """
    path = Path(path)
    header = read_header(path)
    chosen = _choose_grids(path, header, fields)
    with _mapped(path) as data:
        grids = [read_grid(path, data, header, d) for d in chosen]
    records = _patches(path, grids, _levels(path, grids))
    if fields is not None:
        wanted = [fields] if isinstance(fields, str) else list(dict.fromkeys(fields))
        for r in records:
            r["fields"] = {n: r["fields"][n] for n in wanted}
    return AMRVolume.from_grids(records, allow_nonfinite=allow_nonfinite, source=str(path))


def read_header(path) -> VDBHeader:
    """Parse the header and every grid descriptor of ``path``.

    With grid offsets this reads a few bytes per grid; a stream (no offsets) is walked grid by
    grid without decompressing anything.
    """
    path = Path(path)
    if not path.is_file():
        raise AMRError(f"{path}: not a regular file" if path.exists() else f"{path}: no such file")
    with _mapped(path) as data:
        cur = _Cursor(data, 0, len(data), f"{path}: header")
        if len(data) < 8 or struct.unpack("<q", cur.take(8, "the magic number"))[0] != MAGIC:
            raise AMRError(f"{path}: not an OpenVDB file (expected the magic number "
                           f"0x{MAGIC:08X} in the first 8 bytes)")
        version = cur.u32("the file format version")
        if version < MIN_FILE_VERSION:
            raise AMRError(f"{path}: VDB file format {version} is older than {MIN_FILE_VERSION} "
                           f"(OpenVDB 3.0); re-save the file with a newer OpenVDB")
        if version > NEWEST_FILE_VERSION:
            raise AMRError(f"{path}: VDB file format {version} is newer than this reader knows "
                           f"({NEWEST_FILE_VERSION})")
        library = (cur.u32("the library major version"), cur.u32("the library minor version"))
        has_offsets = cur.u8("the grid-offsets flag") != 0
        uuid = cur.take(36, "the file UUID").decode("latin-1")
        _skip_metadata(cur, "the file metadata")
        count = cur.i32("the grid count")
        if count < 0:
            raise cur.fail(f"grid count {count} is negative")
        grids = []
        for index in range(count):
            d = _read_descriptor(cur, index)
            if has_offsets:
                # An instance has no tree, and OpenVDB leaves its block offset at 0.
                block = d.block_pos if not d.instance_parent else d.grid_pos
                if not (cur.pos <= d.grid_pos <= block <= d.end_pos <= len(data)):
                    raise AMRError(f"{path}: {d.describe()}: byte offsets {d.grid_pos}, "
                                   f"{d.block_pos}, {d.end_pos} do not fit in the file "
                                   f"({len(data)} bytes; truncated or corrupt)")
                cur.pos = d.end_pos
            else:
                d = _walk_stream_grid(path, data, cur, d)
            grids.append(d)
    return VDBHeader(version, library, has_offsets, uuid, tuple(grids))


def read_grid(path, data, header: VDBHeader, d: GridDescriptor) -> VDBGrid:
    """Decode the grid ``d`` of ``path`` (``data`` is the file's bytes, e.g. a memory map)."""
    where = f"{path}: {d.describe()}"
    if not d.supported:
        raise AMRError(f"{where}: unsupported grid type; mi_amr reads FloatGrid "
                       f"(Tree_float_5_4_3) and Vec3SGrid (Tree_vec3s_5_4_3) grids, optionally "
                       f"saved as half floats")
    cur = _Cursor(data, d.grid_pos, d.end_pos, where)
    compression = cur.u32("the compression flags")
    _skip_metadata(cur, "the grid metadata")
    scale, translation = _read_transform(cur)
    tree_owner = _instance_parent(path, header, d) if d.instance_parent else d
    if tree_owner is not d:
        owner_cur = _Cursor(data, tree_owner.grid_pos, tree_owner.end_pos, where +
                            f", tree of {tree_owner.describe()}")
        compression = owner_cur.u32("the compression flags")
        _skip_metadata(owner_cur, "the grid metadata")
        _read_map(owner_cur)
        cur = owner_cur
    tree = _TreeReader(cur, TREE_TYPES[d.tree_type], compression, tree_owner.half,
                       decode=True).read()
    lo, hi = _active_box(where, tree)
    values = _dense(where, tree, lo, hi)
    return VDBGrid(d, scale, translation, lo, hi, values)


# ---------------------------------------------------------------------- byte-level reading

class _Cursor:
    """Little-endian reads from ``data[pos:end]``; reading past ``end`` raises an AMRError that
    names ``where``, what was expected and the byte offset."""

    def __init__(self, data, pos: int, end: int, where: str):
        self.data, self.pos, self.end, self.where = data, pos, end, where

    def take(self, n: int, what: str) -> bytes:
        if n < 0 or self.pos + n > self.end:
            raise AMRError(f"{self.where}: ends early at byte {self.pos}: expected {what} "
                           f"({n} bytes, {self.end - self.pos} left; truncated or corrupt)")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def skip(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > self.end:
            self.take(n, what)  # raises, naming what was expected
        self.pos += n

    def u8(self, what: str) -> int:
        return self.take(1, what)[0]

    def i32(self, what: str) -> int:
        return struct.unpack("<i", self.take(4, what))[0]

    def u32(self, what: str) -> int:
        return struct.unpack("<I", self.take(4, what))[0]

    def i64(self, what: str) -> int:
        return struct.unpack("<q", self.take(8, what))[0]

    def string(self, what: str) -> str:
        return self.take(self.u32(f"the length of {what}"), what).decode("utf-8", "replace")

    def array(self, dtype, count: int, what: str) -> np.ndarray:
        dtype = np.dtype(dtype)
        return np.frombuffer(self.take(count * dtype.itemsize, what), dtype=dtype)

    def mask(self, size: int, what: str) -> np.ndarray:
        """A node mask of ``size`` bits as a bool array (bit ``n`` of the words is slot ``n``)."""
        raw = np.frombuffer(self.take(size // 8, what), dtype=np.uint8)
        return np.unpackbits(raw, bitorder="little").view(bool)

    def fail(self, message: str) -> AMRError:
        return AMRError(f"{self.where}: byte {self.pos}: {message}")


class _mapped:
    """Context manager: the file's bytes as a read-only memory map (``b""`` when empty)."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        self.map = None
        try:
            with open(self.path, "rb") as f:
                if self.path.stat().st_size:
                    # The map stays valid after the file is closed.
                    self.map = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError) as e:
            raise AMRError(f"{self.path}: cannot read ({e})") from None
        return self.map if self.map is not None else b""

    def __exit__(self, *exc):
        if self.map is not None:
            self.map.close()


def _skip_metadata(cur: _Cursor, what: str) -> None:
    for i in range(cur.u32(f"the item count of {what}")):
        cur.string(f"the name of item {i} of {what}")
        cur.string(f"the type of item {i} of {what}")
        cur.skip(cur.u32(f"the size of item {i} of {what}"), f"the value of item {i} of {what}")


def _read_descriptor(cur: _Cursor, index: int) -> GridDescriptor:
    unique = cur.string(f"the name of grid #{index}")
    tree_type = cur.string(f"the type of grid #{index}")
    parent = cur.string(f"the instance parent of grid #{index}")
    grid_pos, block_pos, end_pos = (cur.i64(f"the byte offsets of grid #{index}")
                                    for _ in range(3))
    half = tree_type.endswith(HALF_SUFFIX)
    if half:
        tree_type = tree_type[:-len(HALF_SUFFIX)]
    return GridDescriptor(index, unique, unique.split(NAME_SEPARATOR)[0], tree_type, half,
                          parent, grid_pos, block_pos, end_pos)


def _walk_stream_grid(path: Path, data, cur: _Cursor, d: GridDescriptor) -> GridDescriptor:
    """In a stream the record follows its descriptor: walk over it without decoding values and
    return the descriptor with the record's byte range filled in."""
    start = cur.pos
    where = f"{path}: {d.describe()}"
    if not d.supported and not d.instance_parent:
        raise AMRError(f"{where}: unsupported grid type in a file without grid offsets (a VDB "
                       f"stream), so the grids after it cannot be found; mi_amr reads FloatGrid "
                       f"and Vec3SGrid grids")
    walker = _Cursor(data, start, len(data), where)
    compression = walker.u32("the compression flags")
    _skip_metadata(walker, "the grid metadata")
    _read_map(walker)
    block = 0  # as OpenVDB records it for an instance, which has no tree
    if not d.instance_parent:
        tree = _TreeReader(walker, TREE_TYPES[d.tree_type], compression, d.half, decode=False)
        tree.read()
        block = tree.buffers_pos
    cur.pos = walker.pos
    return GridDescriptor(d.index, d.unique_name, d.name, d.tree_type, d.half, d.instance_parent,
                          start, block, walker.pos)


def _instance_parent(path: Path, header: VDBHeader, d: GridDescriptor) -> GridDescriptor:
    for other in header.grids:
        if other.unique_name == d.instance_parent and not other.instance_parent:
            if other.tree_type != d.tree_type:
                break
            return other
    raise AMRError(f"{path}: {d.describe()} shares the tree of grid "
                   f"'{d.instance_parent}', which the file does not hold (or of another type)")


def _read_map(cur: _Cursor):
    """The map of a grid's transform: ``(map type, its float64 values)``."""
    map_type = cur.string("the transform's map type")
    if map_type not in MAP_SIZES:
        raise cur.fail(f"transform map '{map_type}' is not supported; mi_amr needs axis-aligned "
                       f"voxels of one size (a uniform scale and a translation: "
                       f"{', '.join(MAP_SIZES)})")
    return map_type, cur.array("<f8", MAP_SIZES[map_type], f"the {map_type} data") \
        .astype(np.float64)


def _read_transform(cur: _Cursor):
    """The grid's transform as ``(voxel size (3,), translation (3,))``, world units: world
    position of the centre of voxel ``ijk`` is ``voxel size * ijk + translation`` (per axis)."""
    map_type, v = _read_map(cur)
    translation = np.zeros(3)
    if map_type in ("UniformScaleMap", "ScaleMap"):
        scale = v[0:3]
    elif map_type in ("UniformScaleTranslateMap", "ScaleTranslateMap"):
        translation, scale = v[0:3], v[3:6]
    elif map_type == "TranslationMap":
        translation, scale = v[0:3], np.ones(3)
    else:
        m = v.reshape(4, 4)  # row-major; world = (i, j, k, 1) @ m
        scale, translation = np.diag(m)[:3].copy(), m[3, :3]
        off = m[:3, :3] - np.diag(scale)
        if (np.any(np.abs(off) > SCALE_TOLERANCE * np.max(np.abs(scale)))
                or np.any(m[:3, 3] != 0) or m[3, 3] != 1):
            raise cur.fail(f"AffineMap {m.tolist()} rotates, shears or projects; mi_amr needs "
                           f"a scale along the axes and a translation")
    if not (np.all(np.isfinite(scale)) and np.all(np.isfinite(translation)) and
            np.all(scale > 0)):
        raise cur.fail(f"{map_type} with scale {tuple(float(x) for x in scale)} and translation "
                       f"{tuple(float(x) for x in translation)}: mi_amr needs a positive voxel "
                       f"size on every axis")
    # One size on all axes, bit for bit, where the map says so up to its rounding.
    if np.all(np.abs(scale - scale[0]) <= SCALE_TOLERANCE * scale[0]):
        scale = np.full(3, scale[0])
    return np.asarray(scale, dtype=np.float64), np.asarray(translation, dtype=np.float64)


# ---------------------------------------------------------------------- the tree

@dataclass
class _Tree:
    """A decoded tree: ``leaf_origins (L, 3)``, ``leaf_masks (L, 512)`` (active voxels),
    ``leaf_values (L, 512, C)``; tiles that matter (active, or not equal to the background) as
    ``tile_origins (T, 3)``, ``tile_sizes (T,)`` (edge in voxels), ``tile_values (T, C)``,
    ``tile_active (T,)``; the ``background (C,)``. Coordinates are VDB index space."""

    background: np.ndarray
    leaf_origins: np.ndarray
    leaf_masks: np.ndarray
    leaf_values: np.ndarray
    tile_origins: np.ndarray
    tile_sizes: np.ndarray
    tile_values: np.ndarray
    tile_active: np.ndarray


def _slot_coords(log2: int) -> np.ndarray:
    """Local ``(x, y, z)`` of every slot of a node with ``2^log2`` slots per axis, ``(N, 3)``."""
    n = np.arange(1 << (3 * log2))
    m = (1 << log2) - 1
    return np.stack([n >> (2 * log2), (n >> log2) & m, n & m], axis=1)


_UPPER_COORDS = _slot_coords(5) * UPPER_SLOT
_LOWER_COORDS = _slot_coords(4) * LOWER_SLOT


class _TreeReader:
    """Walks one tree (topology, then buffers) from ``cur``. With ``decode=False`` it only moves
    the cursor past the tree (for streams), decompressing nothing."""

    def __init__(self, cur: _Cursor, ncomp: int, compression: int, half: bool, decode: bool):
        self.cur, self.ncomp, self.half, self.decode = cur, ncomp, half, decode
        self.masked = bool(compression & COMPRESS_ACTIVE_MASK)
        self.blosc = bool(compression & COMPRESS_BLOSC)
        self.zip = bool(compression & COMPRESS_ZIP) and not self.blosc
        self.value_dtype = np.dtype(("<f4", (ncomp,)))
        self.leaf_origins, self.leaf_masks = [], []
        self.tiles = []  # (origins (n, 3), size, values (n, C), active (n,))
        self._decompress = None
        if decode and self.blosc:
            self._decompress = _blosc_decompressor(cur.where)

    def read(self) -> _Tree | None:
        cur = self.cur
        buffers = cur.i32("the tree's buffer count")
        if buffers != 1:
            raise cur.fail(f"tree buffer count {buffers}; OpenVDB 3+ trees have exactly 1")
        self.background = cur.array(self.value_dtype, 1, "the background value")[0] \
            .astype(np.float32)
        num_tiles = cur.u32("the root's tile count")
        num_children = cur.u32("the root's child count")
        tile_dtype = np.dtype([("xyz", "<i4", (3,)), ("value", "<f4", (self.ncomp,)),
                               ("active", "u1")])
        tiles = cur.array(tile_dtype, num_tiles, f"{num_tiles} root tiles")
        if self.decode and num_tiles:
            self._add_tiles(tiles["xyz"].astype(np.int64), ROOT_TILE, tiles["value"],
                            tiles["active"] != 0)
        for i in range(num_children):
            origin = np.array(struct.unpack("<3i", cur.take(12, f"the origin of root child {i}")),
                              dtype=np.int64) & ~np.int64(ROOT_TILE - 1)
            self._internal(origin, log2=5)
        self.buffers_pos = cur.pos
        masks = self._leaf_buffers()
        if not self.decode:
            return None
        return self._assemble(masks)

    def _internal(self, origin: np.ndarray, log2: int) -> None:
        cur = self.cur
        size = 1 << (3 * log2)
        node = f"the internal node at {_ints(origin)}"
        child_mask = cur.mask(size, f"the child mask of {node}")
        value_mask = cur.mask(size, f"the value mask of {node}")
        values = self._values(size, value_mask, f"the tile values of {node}")
        coords = origin + (_UPPER_COORDS if log2 == 5 else _LOWER_COORDS)
        if self.decode:
            tile = ~child_mask
            self._add_tiles(coords[tile], UPPER_SLOT if log2 == 5 else LOWER_SLOT,
                            values[tile], value_mask[tile])
        for slot in np.flatnonzero(child_mask):
            if log2 == 5:
                self._internal(coords[slot], log2=4)
            else:
                self.leaf_origins.append(coords[slot])
                self.leaf_masks.append(cur.take(64, f"the value mask of leaf "
                                                    f"{len(self.leaf_masks)} in {node}"))

    def _add_tiles(self, origins, size, values, active) -> None:
        bg = self.background
        differs = np.any((values != bg) & ~(np.isnan(values) & np.isnan(bg)), axis=1)
        keep = active | differs
        if np.any(keep):
            self.tiles.append((origins[keep], size, values[keep].astype(np.float32),
                               active[keep]))

    def _leaf_buffers(self) -> np.ndarray:
        """Read every leaf's buffer; returns the leaf masks ``(L, 512)`` (from the topology)."""
        cur = self.cur
        n = len(self.leaf_masks)
        masks = np.unpackbits(np.frombuffer(b"".join(self.leaf_masks), dtype=np.uint8),
                              bitorder="little").view(bool).reshape(n, 512)
        self.leaf_values = np.empty((n, 512, self.ncomp), dtype=np.float32) if self.decode \
            else None
        for i in range(n):
            where = f"the buffer of leaf {i} of {n}"
            cur.skip(64, f"the value mask of {where}")
            values = self._values(512, masks[i], where)
            if self.decode:
                self.leaf_values[i] = values
        return masks

    def _values(self, count: int, active: np.ndarray, what: str):
        """One block of compressed values (``io::readCompressedValues``): ``(count, C)`` float32,
        inactive values restored; ``None`` when not decoding."""
        cur = self.cur
        flag = cur.u8(f"the compression byte of {what}")
        if flag > 6:
            raise cur.fail(f"compression byte {flag} of {what}; expected 0 to 6 (corrupt file?)")
        inactive0 = self.background if flag == 0 else -self.background
        inactive1 = self.background
        if flag in (2, 4, 5):
            inactive0 = cur.array(self.value_dtype, 1, f"an inactive value of {what}")[0]
        if flag == 5:
            inactive1 = cur.array(self.value_dtype, 1, f"an inactive value of {what}")[0]
        selection = cur.mask(count, f"the selection mask of {what}") if flag in (3, 4, 5) \
            else None
        stored = int(np.count_nonzero(active)) if self.masked and flag != 6 else count
        data = self._data(stored, what)
        if not self.decode:
            return None
        if stored == count:
            return data
        out = np.empty((count, self.ncomp), dtype=np.float32)
        out[:] = inactive0
        if selection is not None:
            out[selection] = inactive1
        out[active] = data
        return out

    def _data(self, count: int, what: str):
        """``count`` values, decompressed: ``(count, C)`` float32 (``None`` when not decoding)."""
        cur = self.cur
        itemsize = (2 if self.half else 4) * self.ncomp
        nbytes = count * itemsize
        if self.half and count == 0:
            return np.empty((0, self.ncomp), dtype=np.float32) if self.decode else None
        if self.blosc or self.zip:
            size = cur.i64(f"the compressed size of {what}")
            if size <= 0:
                if -size != nbytes:
                    raise cur.fail(f"{what} holds {-size} raw bytes; expected {nbytes}")
                raw = cur.take(nbytes, what)
            else:
                packed = cur.take(size, what)
                if not self.decode or nbytes == 0:
                    raw = b""
                else:
                    raw = self._unpack(packed, nbytes, what)
        else:
            raw = cur.take(nbytes, what)
        if not self.decode:
            return None
        dtype = "<f2" if self.half else "<f4"
        return np.frombuffer(raw, dtype=dtype).reshape(count, self.ncomp).astype(np.float32)

    def _unpack(self, packed: bytes, nbytes: int, what: str) -> bytes:
        try:
            raw = self._decompress(packed) if self.blosc else zlib.decompress(packed)
        except AMRError:
            raise
        except Exception as e:  # zlib.error, blosc's RuntimeError/ValueError
            raise self.cur.fail(f"cannot decompress {what} ({type(e).__name__}: {e}); the file "
                                f"is corrupt") from None
        if len(raw) != nbytes:
            raise self.cur.fail(f"{what} decompresses to {len(raw)} bytes; expected {nbytes}")
        return raw

    def _assemble(self, masks: np.ndarray) -> _Tree:
        n = len(self.leaf_origins)
        origins = np.array(self.leaf_origins, dtype=np.int64).reshape(n, 3)
        if self.tiles:
            t_origins = np.concatenate([t[0] for t in self.tiles]).astype(np.int64)
            t_sizes = np.concatenate([np.full(len(t[0]), t[1]) for t in self.tiles])
            t_values = np.concatenate([t[2] for t in self.tiles])
            t_active = np.concatenate([t[3] for t in self.tiles])
        else:
            t_origins = np.zeros((0, 3), dtype=np.int64)
            t_sizes = np.zeros(0, dtype=np.int64)
            t_values = np.zeros((0, self.ncomp), dtype=np.float32)
            t_active = np.zeros(0, dtype=bool)
        return _Tree(self.background, origins, masks, self.leaf_values, t_origins, t_sizes,
                     t_values, t_active)


def _blosc_decompressor(where: str):
    try:
        import blosc
    except ImportError:
        raise AMRError(f"{where}: the grid is Blosc-compressed (OpenVDB's default compression) "
                       f"and the Python package 'blosc' is not installed; install it with: "
                       f"pip install blosc") from None
    return blosc.decompress


# ---------------------------------------------------------------------- dense boxes

def _active_box(where: str, tree: _Tree):
    """Inclusive index box ``(lo, hi)`` of the active voxels and active tiles."""
    los, his = [], []
    m = tree.leaf_masks.reshape(-1, 8, 8, 8)
    any_on = m.any(axis=(1, 2, 3))
    if np.any(any_on):
        m, origins = m[any_on], tree.leaf_origins[any_on]
        # Per leaf and axis, the first and last voxel layer holding an active voxel.
        proj = np.stack([m.any(axis=(2, 3)), m.any(axis=(1, 3)), m.any(axis=(1, 2))], axis=1)
        first = np.argmax(proj, axis=2)
        last = 7 - np.argmax(proj[:, :, ::-1], axis=2)
        los.append((origins + first).min(axis=0))
        his.append((origins + last).max(axis=0))
    act = tree.tile_active
    if np.any(act):
        o, s = tree.tile_origins[act], tree.tile_sizes[act]
        los.append(o.min(axis=0))
        his.append((o + s[:, None] - 1).max(axis=0))
    if not los:
        raise AMRError(f"{where}: no active voxels; an empty grid gives no AMR patch")
    lo = np.min(los, axis=0).astype(np.int64)
    hi = np.max(his, axis=0).astype(np.int64)
    cells = math.prod(int(n) for n in hi - lo + 1)  # Python ints: 2^32 per axis overflows int64
    if cells > MAX_DENSE_CELLS:
        raise AMRError(f"{where}: the active voxels span the index box {_ints(lo)} .. "
                       f"{_ints(hi)} ({cells:,} voxels), too big for one dense AMR grid "
                       f"(limit {MAX_DENSE_CELLS:,}); active tiles cover whole 8^3, 128^3 or "
                       f"4096^3 blocks")
    return lo, hi


def _dense(where: str, tree: _Tree, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The values over ``lo .. hi`` (inclusive), ``(nx, ny, nz, C)`` float32: background first,
    then tiles and leaves, which cover disjoint regions."""
    # Work on a box aligned to 8 so that leaves and 8^3 tiles are whole blocks of it.
    blo = (lo // 8) * 8
    bhi = ((hi + 1 + 7) // 8) * 8
    nblocks = (bhi - blo) // 8
    ncomp = tree.background.shape[0]
    try:
        out = np.empty(tuple(int(n) for n in bhi - blo) + (ncomp,), dtype=np.float32)
    except MemoryError:
        raise AMRError(f"{where}: not enough memory for its dense box {_ints(lo)} .. "
                       f"{_ints(hi)}") from None
    out[...] = tree.background
    big = tree.tile_sizes > LOWER_SLOT
    for o, s, v in zip(tree.tile_origins[big], tree.tile_sizes[big], tree.tile_values[big]):
        a = np.maximum(o, blo) - blo
        b = np.minimum(o + s, bhi) - blo
        if np.all(b > a):
            out[a[0]:b[0], a[1]:b[1], a[2]:b[2]] = v
    blocks = out.reshape(nblocks[0], 8, nblocks[1], 8, nblocks[2], 8, ncomp) \
        .transpose(0, 2, 4, 1, 3, 5, 6)
    small = ~big
    for origins, values in ((tree.tile_origins[small],
                             np.broadcast_to(tree.tile_values[small][:, None, None, None, :],
                                             (int(small.sum()), 8, 8, 8, ncomp))),
                            (tree.leaf_origins, tree.leaf_values.reshape(-1, 8, 8, 8, ncomp))):
        b = (origins - blo) // 8
        inside = np.all((b >= 0) & (b < nblocks), axis=1)
        if np.any(inside):
            b = b[inside]
            blocks[b[:, 0], b[:, 1], b[:, 2]] = values[inside]
    a, b = lo - blo, hi + 1 - blo
    return np.ascontiguousarray(out[a[0]:b[0], a[1]:b[1], a[2]:b[2]])


# ---------------------------------------------------------------------- grids -> AMR patches

def _choose_grids(path: Path, header: VDBHeader, fields) -> list:
    """The descriptors to read: all grids, or those giving one of ``fields``."""
    producers = {}
    for d in header.grids:
        for name in d.field_names:
            producers.setdefault(name, []).append(d)
    for name, ds in producers.items():
        kinds = {TREE_TYPES.get(d.tree_type, 1) == 3 for d in ds}
        if len(kinds) > 1:
            labels = ", ".join(d.describe() for d in ds)
            raise AMRError(f"{path}: field '{name}' is given both by a float grid and by a "
                           f"component of a vector grid ({labels}); rename one of them")
    if not header.grids:
        raise AMRError(f"{path}: the file holds no grids")
    if fields is None:
        for d in header.grids:
            if not d.name:
                raise AMRError(f"{path}: {d.describe()} has no name; name every grid (its name "
                               f"is the field name)")
            if not d.supported:
                readable = field_names_of(header)
                hint = (f"; read the others with fields={readable}" if readable else "")
                raise AMRError(f"{path}: {d.describe()} has an unsupported grid type; mi_amr "
                               f"reads FloatGrid (Tree_float_5_4_3) and Vec3SGrid "
                               f"(Tree_vec3s_5_4_3) grids{hint}")
        return list(header.grids)
    wanted = requested(path, fields, producers, field_names_of(header))
    return [d for d in header.grids if any(n in wanted for n in d.field_names)]


def field_names_of(header: VDBHeader) -> list:
    """Field names of the readable grids of a parsed header, in file order."""
    return list(dict.fromkeys(n for d in header.grids if d.supported and d.name
                              for n in d.field_names))


def _levels(path: Path, grids: list) -> list:
    """Level of every grid from its voxel size: coarsest is 0, each finer size 2 or 4 times
    smaller than the one before, by the same factor on every axis."""
    sizes = []  # distinct voxel sizes, coarsest first, each with the grids that have it
    for g in sorted(grids, key=lambda g: -float(g.voxel_size.max())):
        if sizes and np.all(np.abs(sizes[-1][0] - g.voxel_size) <=
                            LEVEL_TOLERANCE * g.voxel_size):
            sizes[-1][1].append(g)
        else:
            sizes.append((g.voxel_size, [g]))
    for (coarse, cg), (fine, fg) in zip(sizes, sizes[1:]):
        ratio = coarse / fine
        if not any(np.all(np.abs(ratio - r) <= LEVEL_TOLERANCE * r) for r in (2, 4)):
            raise AMRError(f"{path}: voxel size {_size_text(fine)} ({fg[0].descriptor.describe()})"
                           f" is {_size_text(ratio, '.6g')} times smaller than the next coarser "
                           f"voxel size {_size_text(coarse)} ({cg[0].descriptor.describe()}); each "
                           f"finer voxel size must be 2 or 4 times smaller, by the same factor on "
                           f"every axis, so the voxel sizes "
                           f"{', '.join(_size_text(v) for v, _ in sizes)} are not an AMR hierarchy")
    level = {}
    for lev, (_, gs) in enumerate(sizes):
        for g in gs:
            level[id(g)] = lev
    return [level[id(g)] for g in grids]


def _patches(path: Path, grids: list, levels: list) -> list:
    """Group the grids into AMR grid records: grids of one level with the same box are the
    fields of one patch; boxes of one level that overlap without being equal are an error."""
    patches = []  # [level, voxel size, lo, hi, fields, members]
    for g, level in zip(grids, levels):
        s = g.voxel_size
        lo, hi = g.origin, g.origin + np.array(g.shape) * s
        tol = 1e-3 * s
        for p in patches:
            if p[0] != level:
                continue
            same = np.all(np.abs(p[2] - lo) <= tol) and np.all(np.abs(p[3] - hi) <= tol)
            overlap = np.all(np.minimum(p[3], hi) - np.maximum(p[2], lo) > tol)
            if same:
                clash = [n for n in g.descriptor.field_names if n in p[4]]
                if clash:
                    raise AMRError(f"{path}: {g.descriptor.describe()} and "
                                   f"{p[5][0].descriptor.describe()} both give field(s) {clash} "
                                   f"on the same box {_box_text(lo, hi)}; each field has one "
                                   f"grid per patch")
                p[4].update(g.fields())
                p[5].append(g)
                break
            if overlap:
                other = p[5][0]
                raise AMRError(f"{path}: {g.descriptor.describe()} (active box "
                               f"{_box_text(lo, hi)}) and {other.descriptor.describe()} (active "
                               f"box {_box_text(p[2], p[3])}) have voxel size {_size_text(s)} and "
                               f"overlap without having the same box; grids of one voxel size "
                               f"must either be one patch (identical active bounding boxes) or "
                               f"not overlap. "
                               f"Voxels equal to the background are inactive after "
                               f"copyFromArray; write with tolerance=-1 to keep them")
        else:
            patches.append([level, s, lo, hi, dict(g.fields()), [g]])
    names = list(dict.fromkeys(n for g in grids for n in g.descriptor.field_names))
    for p in patches:
        missing = [n for n in names if n not in p[4]]
        if missing:
            members = ", ".join(g.descriptor.describe() for g in p[5])
            raise AMRError(f"{path}: the patch {_box_text(p[2], p[3])} at voxel size "
                           f"{_size_text(p[1])} "
                           f"({members}) has no grid for field(s) {missing}; every field needs "
                           f"a grid with the same active box on every patch")
    return [{"level": p[0], "origin": tuple(float(x) for x in p[2]),
             "spacing": tuple(float(x) for x in p[1]),
             "fields": {n: p[4][n] for n in names}} for p in patches]


def _size_text(size, fmt: str = "g") -> str:
    """A voxel size (or a ratio of them), ``(3,)``: one number where the axes agree, else
    ``(x, y, z)``."""
    if np.all(size == size[0]):
        return f"{size[0]:{fmt}}"
    return "(" + ", ".join(f"{x:{fmt}}" for x in size) + ")"


def _box_text(lo, hi) -> str:
    """``[0..0.4, 0..0.4, 0..0.3]``; rounding noise such as -7e-18 printed as 0."""
    def text(x):
        return f"{np.round(x, 12) + 0.0:g}"
    return "[" + ", ".join(f"{text(a)}..{text(b)}" for a, b in zip(lo, hi)) + "]"


def _ints(v) -> tuple:
    return tuple(int(x) for x in v)
