"""Grid-based datasets that yt reads (Enzo, FLASH, Chombo, AMReX, Athena, GAMER, ...) as volumes.

yt is optional (``pip install 'mi_amr[yt]'``) and imported only when one of these functions
runs, so ``import mi_amr`` never imports it. :func:`from_yt` converts a dataset that is already
open; :func:`open_dataset` is the last thing :func:`mi_amr.load` tries for a path that none of
mi_amr's own readers recognises.

Conversion: every grid of ``ds.index.grids`` becomes one :class:`~mi_amr.volume.Grid` with
``level = grid.Level``, ``origin = grid.LeftEdge`` and ``spacing = grid.dds`` (world = yt's
``code_length``, as plain floats), the shape ``grid.ActiveDimensions`` and each field's values
``grid[field]`` as float64, indexed ``[i, j, k]`` = x, y, z, cell-centred, in the units yt gives
the field (on-disk fields: the code units they are stored in, unchanged). yt's fine grids
overlap the coarse cells they refine; the data model keeps every grid, as it does for any AMR
hierarchy.
"""

from __future__ import annotations

import importlib.util
import logging
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.core.volume import AMRVolume

INSTALL_HINT = "pip install 'mi_amr[yt]'"


def installed() -> bool:
    """True when yt can be imported (checked without importing it)."""
    return importlib.util.find_spec("yt") is not None


def from_yt(ds, fields=None, *, source: str | None = None,
            allow_nonfinite: bool = False) -> AMRVolume:
    """Convert the grid-based yt dataset ``ds`` into an :class:`~mi_amr.AMRVolume`.

    ``fields`` lists what to read: yt field tuples such as ``("boxlib", "x_velocity")`` or
    ``("gas", "density")`` (derived fields work too), or plain names, which mean the on-disk
    field of that name (``"x_velocity"`` is ``("boxlib", "x_velocity")`` for AMReX). ``None``
    reads every on-disk grid field. A field is named in the volume by its plain name. Only the
    requested fields are read; each grid's cached yt data is released once copied.
    ``source`` labels error messages (default: the dataset's file name).
    ``allow_nonfinite=True`` keeps NaN and Inf values as missing data.

    Raises :class:`~mi_amr.AMRError` when yt is not installed, ``ds`` is not a yt dataset, is
    not a 3-D Cartesian grid dataset (particles only, an octree, an unstructured mesh), a
    field is unknown (the message lists the available ones), or the hierarchy does not
    validate (:meth:`AMRVolume.from_grids`).
    """
    _import_yt()
    from yt.data_objects.static_output import Dataset

    if not isinstance(ds, Dataset):
        raise AMRError(f"from_yt: expected a yt dataset (yt.load(path)), got "
                       f"{type(ds).__name__}; for a path use mi_amr.load(path)")
    label = str(source or getattr(ds, "parameter_filename", None) or ds)
    _check_grid_based(ds, label)
    with _reading(label, "its grid index"):
        yt_grids = ds.index.grids
    chosen = _resolve_fields(ds, fields, label)
    grids = []
    for g in yt_grids:
        shape = tuple(int(n) for n in g.ActiveDimensions)
        arrays = {}
        for name, field in chosen:
            with _reading(label, f"field {field} of yt grid {g.id}"):
                arr = np.asarray(_plain(g[field]), dtype=np.float64)
            if arr.shape != shape:
                raise AMRError(f"{label}: yt grid {g.id} (level {g.Level}): field {field} has "
                               f"shape {arr.shape}, expected the grid's {shape}; is it a "
                               f"grid field?")
            arrays[name] = arr
        # The arrays above are ours now; yt's per-grid cache would double the memory.
        g.clear_data()
        grids.append({"level": int(g.Level), "origin": _code_length(g.LeftEdge),
                      "spacing": _code_length(g.dds), "fields": arrays})
    return AMRVolume.from_grids(grids, allow_nonfinite=allow_nonfinite, source=label)


def open_dataset(path, **options):
    """``yt.load(path, **options)`` with its index built, or ``None`` when yt is not
    installed, does not recognise ``path``, or ``path`` is a folder with an AMReX ``Header``
    (mi_amr's own AMReX reader has the last word there: yt's accepts any folder with a file
    named Header, without checking that it is a plotfile). yt's other failures become
    :class:`~mi_amr.AMRError`. yt's log messages below errors are silenced meanwhile."""
    path = Path(path)
    if not installed() or (path / "Header").exists():
        return None
    yt = _import_yt()
    from yt.utilities.exceptions import YTUnidentifiedDataType

    with _quiet(), _reading(str(path), "it"):
        try:
            ds = yt.load(str(path), **options)
        except YTUnidentifiedDataType:
            return None
        # Checked before the index is built: a particle index can take minutes to build.
        _check_grid_based(ds, str(path))
        ds.index  # built here so that its errors, too, name the path
    return ds


def why_not(path) -> str:
    """Why :func:`open_dataset` gave ``None`` for ``path``, for the 'unrecognised format'
    message of :func:`mi_amr.load`."""
    if not installed():
        return (f"install yt ({INSTALL_HINT}) to read the grid-based formats yt reads "
                f"(Enzo, FLASH, Chombo, Athena, GAMER, ...)")
    if (Path(path) / "Header").exists():
        return "its Header is not an AMReX plotfile header, so yt is not asked either"
    return "yt does not recognise it either"


def field_names(ds) -> list:
    """Plain names of the on-disk grid fields of ``ds`` (yt's ``field_list`` without particle
    fields), in yt's order."""
    return list(dict.fromkeys(name for _, name in _on_disk(ds)))


# ---------------------------------------------------------------------- helpers

def _import_yt():
    try:
        import yt
    except ImportError as e:
        raise AMRError(f"yt is not installed or does not import ({e}); install it with "
                       f"{INSTALL_HINT}") from None
    return yt


def _check_grid_based(ds, label: str) -> None:
    from yt.geometry.grid_geometry_handler import GridIndex
    from yt.geometry.oct_geometry_handler import OctreeIndex
    from yt.geometry.particle_geometry_handler import ParticleIndex
    from yt.geometry.unstructured_mesh_handler import UnstructuredIndex

    # The index class, not ds.index: building a particle index can take minutes and write
    # files next to the data.
    index_class = getattr(ds, "_index_class", None)
    if not isinstance(index_class, type):
        index_class = type(ds.index)
    if not issubclass(index_class, GridIndex):
        kinds = ((ParticleIndex, "particles only"), (OctreeIndex, "an octree (RAMSES, ART, ...)"),
                 (UnstructuredIndex, "an unstructured mesh"))
        kind = next((k for c, k in kinds if issubclass(index_class, c)), index_class.__name__)
        raise AMRError(f"{label}: the yt dataset ({type(ds).__name__}) holds {kind}, not grids; "
                       f"mi_amr reads grid-based (patch) AMR data")
    geometry = getattr(ds.geometry, "value", ds.geometry)
    if ds.dimensionality != 3 or geometry != "cartesian":
        raise AMRError(f"{label}: the yt dataset is {ds.dimensionality}-D {geometry}; mi_amr "
                       f"reads 3-D Cartesian grids only")


def _on_disk(ds) -> list:
    """On-disk grid fields of ``ds``: ``(ftype, name)`` tuples of ``ds.field_list`` whose type
    is not a particle type."""
    particle_types = set(ds.particle_types) | set(getattr(ds, "particle_types_raw", ()))
    return [f for f in ds.field_list if f[0] not in particle_types]


def _resolve_fields(ds, fields, label: str) -> list:
    """``[(name in the volume, yt field tuple)]`` for the requested ``fields``."""
    on_disk = _on_disk(ds)
    if fields is None:
        chosen = [(name, (ftype, name)) for ftype, name in on_disk]
        if not chosen:
            raise AMRError(f"{label}: the yt dataset has no on-disk grid fields")
    else:
        # One name, yt field tuple or yt field object may stand for a list of one.
        if (isinstance(fields, str) or _is_field_tuple(getattr(fields, "name", None))
                or (_is_field_tuple(fields) and tuple(fields) in _known(ds))):
            fields = [fields]
        chosen = [_resolve_one(ds, f, on_disk, label) for f in fields]
        if not chosen:
            raise AMRError(f"{label}: no fields requested")
    names = [name for name, _ in chosen]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise AMRError(f"{label}: requested fields {[f for _, f in chosen]} give the name(s) "
                       f"{twice} more than once; a volume names each field once")
    return chosen


def _resolve_one(ds, field, on_disk: list, label: str):
    # A yt field object (ds.fields.gas.density) carries its tuple as .name.
    if not isinstance(field, (str, tuple)) and _is_field_tuple(getattr(field, "name", None)):
        field = field.name
    available = f"on-disk fields: {field_names(ds)}"
    if isinstance(field, str):
        matches = [f for f in on_disk if f[1] == field]
        if len(matches) == 1:
            return field, matches[0]
        if len(matches) > 1:
            raise AMRError(f"{label}: field '{field}' is on disk as {matches}; pass one of these "
                           f"tuples")
        derived = [f for f in ds.derived_field_list if f[1] == field
                   and f[0] not in ds.particle_types]
        hint = f"; yt derives {derived[:4]}, which you may pass as a tuple" if derived else \
            "; yt's derived fields are passed as tuples such as ('gas', 'density')"
        raise AMRError(f"{label}: unknown field '{field}'; {available}{hint}")
    if _is_field_tuple(field):
        field = tuple(field)
        if field[0] in ds.particle_types:
            raise AMRError(f"{label}: field {field} is a particle field; mi_amr reads grid "
                           f"fields ({available})")
        if field not in _known(ds):
            raise AMRError(f"{label}: unknown field {field}; on-disk fields: {on_disk}; yt "
                           f"derives more (ds.derived_field_list)")
        return field[1], field
    raise AMRError(f"{label}: a field must be a name or a yt field tuple (type, name), got "
                   f"{field!r}")


def _known(ds) -> set:
    return set(ds.field_list) | set(ds.derived_field_list)


def _is_field_tuple(value) -> bool:
    return (isinstance(value, tuple) and len(value) == 2
            and all(isinstance(v, str) for v in value))


def _plain(arr):
    """The NumPy array inside a yt/unyt array (a plain array stays as it is)."""
    return arr.d if hasattr(arr, "d") else arr


def _code_length(arr) -> tuple:
    if hasattr(arr, "to_value"):
        arr = arr.to_value("code_length")
    return tuple(float(x) for x in np.asarray(arr))


def _first_line(error: Exception) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else "no message"


@contextmanager
def _reading(label: str, what: str):
    """yt's errors while reading ``what`` as :class:`AMRError` naming the dataset."""
    try:
        yield
    except AMRError:
        raise
    except Exception as e:  # yt's frontends raise many types for data they cannot parse
        raise AMRError(f"{label}: yt could not read {what} ({type(e).__name__}: "
                       f"{_first_line(e)})") from None


@contextmanager
def _quiet():
    """yt logs every parameter it reads at INFO level; for mi_amr.load that is noise."""
    logger = logging.getLogger("yt")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)
