"""The layout of mi_amr's own file format, one ``.npz`` file (NumPy zip archive, no pickled
objects), and writing it. Reading it is :mod:`mi_amr.readers.native`.

Keys: ``mi_amr_format`` (the text ``"mi_amr-volume"``), ``version`` (1), ``level`` (G,),
``origin`` (G, 3), ``spacing`` (G, 3), ``shape`` (G, 3), ``field_names`` (unicode array),
``allow_nonfinite`` and one ``field:NAME`` array per field holding every grid's cells, grid after
grid, each in C order of its ``(nx, ny, nz)`` array.
"""

from __future__ import annotations

import numpy as np

from mi_amr.core.atomic import check_output, replacing

MAGIC = "mi_amr-volume"
VERSION = 1


def save(volume, path, *, overwrite: bool = False) -> None:
    """Write ``volume`` to ``path`` atomically (see :mod:`mi_amr.core.atomic`); refuse to
    replace a file unless ``overwrite``, and refuse paths that cannot be written."""
    path = check_output(path, overwrite=overwrite,
                        exists_hint="pass overwrite=True (or --force) to replace it")
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
    with replacing(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
