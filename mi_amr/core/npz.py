"""The layout of mi_amr's own file format, one ``.npz`` file (NumPy zip archive, no pickled
objects), and writing it. Reading it is :mod:`mi_amr.readers.native`.

Keys: ``mi_amr_format`` (the text ``"mi_amr-volume"``), ``version`` (1), ``level`` (G,),
``origin`` (G, 3), ``spacing`` (G, 3), ``shape`` (G, 3), ``field_names`` (unicode array),
``allow_nonfinite`` and one ``field:NAME`` array per field holding every grid's cells, grid after
grid, each in C order of its ``(nx, ny, nz)`` array.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError

MAGIC = "mi_amr-volume"
VERSION = 1


def save(volume, path, *, overwrite: bool = False) -> None:
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
