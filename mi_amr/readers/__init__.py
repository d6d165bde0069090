"""Readers: each turns one file format into an :class:`~mi_amr.volume.AMRVolume` and nothing else.

:func:`load` is the one entry point; it recognises the format from the path.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import AMRError
from . import native


def load(path, fields=None, **options):
    """Read an AMR volume from ``path``.

    Recognised: mi_amr's ``.npz`` files (see :mod:`mi_amr.readers.native`). ``fields`` (a list
    of names) reads only those fields from disk. Derived fields (``speed``, ``q_criterion``) are
    not read here; see :func:`mi_amr.derive`. Raises :class:`~mi_amr.AMRError` for a missing
    file or an unrecognised format.
    """
    path = Path(path)
    if not path.exists():
        raise AMRError(f"{path}: no such file or folder")
    if native.is_native(path):
        if options:
            raise AMRError(f"{path}: unknown option(s) {sorted(options)} for an mi_amr .npz file")
        return native.load(path, fields)
    raise AMRError(f"{path}: unrecognised format; mi_amr reads its own .npz volumes")
