"""mi_amr's own file format: one ``.npz`` file (NumPy zip archive, no pickled objects).

Keys: ``mi_amr_format`` (the text ``"mi_amr-volume"``), ``version`` (1), ``level`` (G,),
``origin`` (G, 3), ``spacing`` (G, 3), ``shape`` (G, 3), ``field_names`` (unicode array),
``allow_nonfinite`` and one ``field:NAME`` array per field holding every grid's cells, grid after
grid, each in C order of its ``(nx, ny, nz)`` array. Loading reads only the requested fields.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.core.volume import AMRVolume

MAGIC = "mi_amr-volume"
VERSION = 1


def save(volume: AMRVolume, path, *, overwrite: bool = False) -> None:
    """Write ``volume`` to ``path`` atomically; refuse to replace a file unless ``overwrite``."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise AMRError(f"{path}: file exists; pass overwrite=True (or --force) to replace it")
    if not path.parent.exists():
        raise AMRError(f"{path}: folder {path.parent} does not exist")
    grids = volume.grids
    arrays = {
        "mi_amr_format": np.array(MAGIC),
        "version": np.array(VERSION),
        "level": np.array([g.level for g in grids], dtype=np.int32),
        "origin": np.array([g.origin for g in grids], dtype=np.float64),
        "spacing": np.array([g.spacing for g in grids], dtype=np.float64),
        "shape": np.array([g.shape for g in grids], dtype=np.int64),
        "field_names": np.array(volume.field_names, dtype=str),
        "allow_nonfinite": np.array(volume.allow_nonfinite),
    }
    for name in volume.field_names:
        arrays[f"field:{name}"] = np.concatenate([g.fields[name].ravel() for g in grids])
    # Write next to the target and rename, so an interrupted save never leaves half a file
    # under the user's name (and never destroys the file it replaces).
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a saved file is a normal file
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def is_native(path) -> bool:
    """True when ``path`` is a zip archive holding the mi_amr marker."""
    path = Path(path)
    if not path.is_file() or not zipfile.is_zipfile(path):
        return False
    with zipfile.ZipFile(path) as z:
        return "mi_amr_format.npy" in z.namelist()


def field_names(path) -> list:
    """The field names stored in an mi_amr file (reads only the small index entry)."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            return [str(n) for n in archive["field_names"]]
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as e:
        raise AMRError(f"{path}: cannot read the field names ({e})") from None


def load(path, fields=None) -> AMRVolume:
    """Read a file written by :func:`save`; ``fields`` (names) limits what is read from disk."""
    path = Path(path)
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise AMRError(f"{path}: not a readable .npz file ({e})") from None
    # A damaged archive (bad CRC, truncated member, object arrays) fails only when a member is
    # read, so the reads are guarded too, not just np.load.
    try:
        with archive:
            if "mi_amr_format" not in archive.files or str(archive["mi_amr_format"]) != MAGIC:
                raise AMRError(f"{path}: not an mi_amr volume (no 'mi_amr_format' marker); "
                               f"write one with AMRVolume.save or 'python -m mi_amr dataset'")
            version = int(archive["version"])
            if version != VERSION:
                raise AMRError(f"{path}: mi_amr volume format version {version}, this mi_amr reads "
                               f"version {VERSION}")
            level = archive["level"]
            origin = archive["origin"]
            spacing = archive["spacing"]
            shape = archive["shape"]
            names = [str(n) for n in archive["field_names"]]
            allow_nonfinite = bool(archive["allow_nonfinite"])
            wanted = names if fields is None else list(fields)
            unknown = [n for n in wanted if n not in names]
            if unknown:
                raise AMRError(f"{path}: unknown field(s) {unknown}; the file holds {names}")
            counts = np.prod(shape, axis=1)
            offsets = np.concatenate([[0], np.cumsum(counts)])
            data = {}
            for n in wanted:
                flat = archive[f"field:{n}"]
                if flat.size != offsets[-1]:
                    raise AMRError(f"{path}: field '{n}' holds {flat.size} values, the grids need "
                                   f"{offsets[-1]}")
                data[n] = flat
    except AMRError:
        raise
    except KeyError as e:
        raise AMRError(f"{path}: mi_amr volume is missing entry {e}") from None
    except (OSError, EOFError, ValueError, zipfile.BadZipFile) as e:
        raise AMRError(f"{path}: damaged mi_amr volume ({e})") from None
    grids = [{"level": int(level[i]), "origin": origin[i], "spacing": spacing[i],
              "fields": {n: data[n][offsets[i]:offsets[i + 1]].reshape(shape[i]) for n in wanted}}
             for i in range(len(level))]
    return AMRVolume.from_grids(grids, allow_nonfinite=allow_nonfinite, source=str(path))
