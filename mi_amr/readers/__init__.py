"""Readers: each turns one file format into an :class:`~mi_amr.volume.AMRVolume` and nothing else.

:func:`load` is the one entry point; it recognises the format from the path.
"""

from __future__ import annotations

import stat
from pathlib import Path

from mi_amr.errors import AMRError
from mi_amr.readers import amrex, native, vdb, ytsource


def load(path, fields=None, *, level_buffers=(), allow_nonfinite: bool = False, **options):
    """Read an AMR volume from ``path``.

    Recognised: mi_amr's ``.npz`` files (see :mod:`mi_amr.readers.native`), AMReX plotfile
    folders (a ``Header`` plus ``Level_N/`` data; see :mod:`mi_amr.readers.amrex`) and OpenVDB
    ``.vdb`` files, one grid per patch (see :mod:`mi_amr.readers.vdb`); last, when yt is
    installed, every grid-based format yt reads (see :mod:`mi_amr.readers.ytsource`; the
    ``options`` go to ``yt.load``). ``fields``
    (a name or a list of names) reads only those fields from disk. ``level_buffers``: fields
    that mi_amr's ``.npz`` reader gives a buffer per level (see :func:`native.load`); the
    other readers ignore it. ``allow_nonfinite=True`` keeps NaN and Inf values as missing data
    (see :meth:`AMRVolume.from_grids`) in any format; an mi_amr ``.npz`` file saved with it
    keeps them without being asked. Derived fields (``speed``, ``q_criterion``) are not read here;
    see :func:`mi_amr.derive`. Raises
    :class:`~mi_amr.AMRError` for a missing file, something that is neither a regular file nor
    a folder (a FIFO or a device, which would block or never end), an unrecognised format or a
    malformed file.
    """
    path = _existing(path)
    if isinstance(fields, str):
        fields = [fields]
    if native.is_native(path):
        _no_options(path, options, "an mi_amr .npz file")
        return native.load(path, fields, level_buffers=level_buffers,
                           allow_nonfinite=allow_nonfinite)
    if amrex.is_plotfile(path):
        _no_options(path, options, "an AMReX plotfile")
        return amrex.load(path, fields, allow_nonfinite=allow_nonfinite)
    if vdb.is_vdb(path):
        _no_options(path, options, "an OpenVDB file")
        return vdb.load(path, fields, allow_nonfinite=allow_nonfinite)
    ds = ytsource.open_dataset(path, **options)
    if ds is not None:
        return ytsource.from_yt(ds, fields, source=str(path), allow_nonfinite=allow_nonfinite)
    raise AMRError(f"{path}: unrecognised format; mi_amr reads its own .npz volumes, AMReX "
                   f"plotfile folders (a folder with a Header whose first line is e.g. "
                   f"HyperCLaw-V1.1) and OpenVDB .vdb files; {ytsource.why_not(path)}")


def available_fields(path) -> list:
    """Names of the fields stored in ``path``, without reading their data."""
    path = _existing(path)
    if native.is_native(path):
        return native.field_names(path)
    if amrex.is_plotfile(path):
        return list(amrex.read_header(path).field_names)
    if vdb.is_vdb(path):
        return vdb.field_names(path)
    ds = ytsource.open_dataset(path)
    if ds is not None:
        return ytsource.field_names(ds)
    return list(load(path).field_names)


def stream_fields(path, names, allow_nonfinite: bool = False):
    """Fields ``names`` of ``path`` to read a stretch at a time (no field-sized buffer, no
    grid built): :class:`native.FieldStream` for mi_amr's ``.npz`` files,
    :class:`amrex.FabStream` (a box at a time) for AMReX plotfiles; None for the other formats
    (use :func:`load`). ``allow_nonfinite``: NaN and Inf values pass, as :func:`load` takes
    it (else they end the reading with an AMRError)."""
    path = _existing(path)
    if native.is_native(path):
        return native.FieldStream(path, names, allow_nonfinite=allow_nonfinite)
    if amrex.is_plotfile(path):
        return amrex.FabStream(path, names, allow_nonfinite=allow_nonfinite)
    return None


def _existing(path) -> Path:
    """``path`` as a Path, when it is a regular file or a folder; the format probes below open
    files, and opening a FIFO or a device blocks or reads forever."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise AMRError(f"{path}: no such file or folder") from None
    except OSError as e:
        raise AMRError(f"{path}: cannot read ({e.strerror or e})") from None
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise AMRError(f"{path}: not a regular file or a folder (a FIFO, socket or device); "
                       f"mi_amr reads data files and plotfile folders")
    return path


def _no_options(path: Path, options: dict, what: str) -> None:
    if options:
        raise AMRError(f"{path}: unknown option(s) {sorted(options)} for {what}")
