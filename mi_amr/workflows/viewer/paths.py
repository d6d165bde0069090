"""Which files the page may open and where it may write.

* Open: a file inside the scene's folder (its subfolders included), or one of the files named
  on the command line. Paths are resolved (``..`` and symbolic links followed) before the
  check, so no path the page sends leaves them.
* Write: a plain file name (letters, digits, ``._-``; no folder part) in the output folder
  given on the command line, with one of the allowed suffixes. An existing file is replaced
  only when the page confirmed it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from mi_amr.errors import AMRError

OPENABLE = (".xml", ".npz", ".vdb", ".h5", ".hdf5")
MAX_LISTED = 200
MAX_PATH = 4096                 # characters of a path the page sends
NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}")


class FileRules:
    """The rules above for a viewer started on ``scene_path`` with ``extra_files`` and the
    output folder ``out_dir`` (made when missing)."""

    def __init__(self, scene_path, extra_files=(), out_dir="out"):
        self.root = Path(scene_path).resolve().parent
        self.extra = tuple(Path(f).resolve() for f in extra_files)
        missing = [str(f) for f in self.extra if not f.exists()]
        if missing:
            raise AMRError(f"--files: no such file(s): {', '.join(missing)}")
        self.out_dir = Path(out_dir).resolve()
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise AMRError(f"--out {out_dir}: is a file, not a folder")
        self.out_dir.mkdir(parents=True, exist_ok=True)

    def openable(self, text) -> Path:
        """The file the page asks for, when the rules allow it (else an :class:`AMRError`)."""
        if not isinstance(text, str) or not text.strip():
            raise AMRError("open: give a file name")
        if len(text) > MAX_PATH or any(ord(c) < 32 for c in text):
            raise AMRError(f"open: {_shown(text)} is not a path (at most {MAX_PATH} "
                           f"characters, no control characters)")
        given = Path(text.strip())
        try:
            path = (given if given.is_absolute() else self.root / given).resolve()
        except (OSError, RuntimeError) as e:        # a link loop, say
            raise AMRError(f"open: {_shown(text)} cannot be resolved ({e})") from None
        if path not in self.extra and not _inside(path, self.root):
            raise AMRError(f"open: {_shown(text)} is outside the scene's folder {self.root} "
                           f"and not one of the files given on the command line; refused")
        if not path.exists():
            raise AMRError(f"open: {_shown(text)} does not exist")
        return path

    def listing(self) -> list:
        """Names the page offers to open: scene files and data files in the scene's folder and
        one level below, then the command line's files (absolute)."""
        found = []
        for folder in [self.root] + sorted(p for p in self.root.iterdir() if p.is_dir()):
            for p in sorted(folder.iterdir()):
                if (p.suffix.lower() in OPENABLE and p.is_file()) or (p / "Header").is_file():
                    found.append(os.path.relpath(p, self.root))
        return found[:MAX_LISTED] + [str(p) for p in self.extra]

    def output(self, name, suffixes) -> Path:
        """The output path for the file name the page sends."""
        if not isinstance(name, str) or not NAME.fullmatch(name) or ".." in name:
            raise AMRError(f"save: {_shown(name)} is not a plain file name (letters, digits and "
                           f"'._-', no folders); files are written to {self.out_dir}")
        if Path(name).suffix.lower() not in suffixes:
            raise AMRError(f"save: {_shown(name)} must end in {' or '.join(suffixes)}")
        return self.out_dir / name


def _shown(value) -> str:
    """``value`` quoted for a message, cut short (a refused request is never echoed whole)."""
    text = repr(value)
    return text if len(text) <= 80 else text[:80] + f"... ({len(text)} characters)"


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.relative_to(folder)
    except ValueError:
        return False
    return True
