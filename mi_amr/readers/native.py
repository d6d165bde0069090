"""Reading mi_amr's own ``.npz`` files (layout: :mod:`mi_amr.core.npz`); only the requested
fields are read from disk."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.core.npz import MAGIC, VERSION
from mi_amr.core.volume import AMRVolume


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
    """Read a file written by :func:`mi_amr.core.npz.save`; ``fields`` (names) limits what is read from disk."""
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
