"""Output files: the path is checked before any work starts, and the file is replaced in one
step (a temporary file in the same folder, then ``os.replace``), so a failed or interrupted
write never leaves half a file under the user's name and never destroys the file it replaces.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

from mi_amr.errors import AMRError


def check_output(path, *, suffixes=(), overwrite: bool = False, make_folders: bool = False,
                 exists_hint: str = "pass --force to replace it") -> Path:
    """Refuse an output ``path`` that cannot be written, before any work is done.

    Refused with an :class:`AMRError` naming the path: a name not ending in one of ``suffixes``
    (when given; compared in lower case), an existing folder, an existing file unless
    ``overwrite`` (``exists_hint`` says how to allow it), something that is not a regular file,
    a missing folder unless ``make_folders`` (then the nearest existing folder above must be
    writable), a file where a folder should be, and a folder in which no file can be created.
    """
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise AMRError(f"{path}: the output must end in {' or '.join(suffixes)}")
    if os.path.isdir(path):
        raise AMRError(f"{path}: is a folder; give the name of a file to write")
    if os.path.lexists(path):
        if not overwrite:
            raise AMRError(f"{path}: file exists; {exists_hint}")
        if not os.path.isfile(path):
            raise AMRError(f"{path}: exists and is not a regular file; refusing to replace it")
    folder = path.parent
    existing = folder
    while not os.path.exists(existing) and existing != existing.parent:
        existing = existing.parent
    if not os.path.isdir(existing):
        raise AMRError(f"{path}: {existing} is a file, not a folder")
    if existing != folder and not make_folders:
        raise AMRError(f"{path}: folder {folder} does not exist")
    _probe(path, existing)
    return path


@contextmanager
def replacing(path):
    """``with replacing(path) as tmp:`` write ``tmp`` (a new empty file in ``path``'s folder
    with the same extension, so writers that choose the format from it still work); on success
    ``tmp`` replaces ``path``, on any failure it is removed and ``path`` is left as it was."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f"{path.stem}.tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a written file is a normal file
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _probe(path: Path, folder: Path) -> None:
    """Create and remove a file in ``folder``: the one test of writability that also holds for
    root, read-only mounts and pseudo file systems such as /proc."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".mi_amr-probe-", dir=folder)
    except OSError as e:
        raise AMRError(f"{path}: cannot write in folder {folder} (creating a file there "
                       f"fails: {e.strerror or e})") from None
    os.close(fd)
    os.unlink(tmp)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
