"""The snapshot cache's folder: which of its subfolders are the cache's own, how one is removed,
and keeping the folder within its size limit (:mod:`mi_amr.kernels.snapshot` fills it).

The cache folder may hold other things (``$MI_AMR_CACHE`` may name a shared folder): only a
subfolder that carries the cache's :data:`MARKER` file of this :data:`FORMAT` is the cache's
own (an entry, named by its 32-digit key; a temporary folder being written, ``.tmp-*``; or one
being removed, ``.del-*``). An entry of the previous format (a key-named folder holding exactly
``meta.pkl`` and that format's ``.npy`` files) is recognised as well, never read, and removed
in turn. Everything else is left as it is and not counted. Nothing is looked at or removed
through a symbolic link: folders are opened with ``O_NOFOLLOW`` and emptied through their
descriptors, so a link inside an entry is removed as a link, its target untouched.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import socket
import stat
import time
from dataclasses import dataclass
from pathlib import Path

FORMAT = 2                  # of an entry's files (mi_amr.kernels.snapshot); in the marker
MARKER = ".mi_amr-snapshot"
KIND = "mi_amr snapshot cache entry"
META = "meta.json"          # an entry is complete when it has one (written last)
TMP, TRASH = ".tmp-", ".del-"
STALE_TMP_S = 3600.0        # a temporary folder untouched this long was left by a crash
KEY = re.compile(r"[0-9a-f]{32}")
_OLD_FILES = re.compile(r"meta\.pkl|field\d+_.+\.npy|table\d+\.npy|pool\d+\.npy|"
                        r"ranges_(basis|finest)\.npy|tmp[a-z0-9_]{8}\.npy")
_OLD_TMP = re.compile(r"\.tmp-[a-z0-9_]{8}")    # tempfile.mkdtemp's names, format 1
_DIR = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
_MAX_MARKER = 4096


def open_root(root: Path, create: bool) -> int | None:
    """A descriptor of the cache folder ``root`` (a link the user gave is followed), or None
    when there is none. With ``create``, a missing folder is made ``0700`` (only this user:
    a shared cache is a folder made beforehand, see the docs), its parents with the umask."""
    try:
        return os.open(root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError as e:
        if not create:
            return None
        if not isinstance(e, FileNotFoundError):
            raise
    root.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.mkdir(root, 0o700)
    except FileExistsError:
        pass            # made meanwhile by another process
    return os.open(root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)


def write_marker(dir_fd: int) -> None:
    """Mark the new folder open as ``dir_fd`` as the cache's own (with this process's host and
    id, so that a folder a killed process left is known as such)."""
    text = json.dumps({"kind": KIND, "format": FORMAT, "host": socket.gethostname(),
                       "pid": os.getpid()})
    fd = os.open(MARKER, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC,
                 0o666, dir_fd=dir_fd)
    with os.fdopen(fd, "w") as f:
        f.write(text)


def read_marker(dir_fd: int) -> dict | None:
    """The marker of the folder open as ``dir_fd`` when it is the cache's own of this format
    (a small regular file, not a link); else None."""
    try:
        fd = os.open(MARKER, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC,
                     dir_fd=dir_fd)
    except OSError:
        return None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        text = f.read(_MAX_MARKER + 1)
    try:
        marker = json.loads(text.decode("utf-8")) if len(text) <= _MAX_MARKER else None
    except (ValueError, RecursionError):
        return None
    if not isinstance(marker, dict) or marker.get("kind") != KIND or \
            type(marker.get("format")) is not int or marker["format"] != FORMAT:
        return None
    return marker


@dataclass
class Item:
    """One of the cache's own subfolders: ``kind`` (``entry``, ``old`` (the previous
    format), ``temp``, ``old_temp``, ``trash``), its ``size`` in bytes, when it was last
    ``used`` (an entry's :data:`META` time, or the newest time in it) and whether a temporary
    folder is ``stale`` (left by a process that is gone)."""

    name: str
    kind: str
    size: int
    used: float
    stale: bool = False


def inspect(root_fd: int, name: str, now: float) -> Item | None:
    """The cache's own subfolder ``name`` of the folder ``root_fd``, or None when it is not
    one of them (anything else: a user's folder, a link, a file) or is gone."""
    try:
        fd = os.open(name, _DIR, dir_fd=root_fd)
    except OSError:
        return None
    try:
        kind, marker = _kind(fd, name)
        if kind is None:
            return None
        size, newest = _measure(fd)
        used = newest
        if kind in ("entry", "old"):
            meta = META if kind == "entry" else "meta.pkl"
            try:
                used = os.stat(meta, dir_fd=fd, follow_symlinks=False).st_mtime
            except OSError:
                used = 0.0      # incomplete: the first to go
        stale = kind == "old_temp" and now - newest > STALE_TMP_S
        if kind == "temp":
            stale = now - newest > STALE_TMP_S or _gone(marker)
        return Item(name, kind, size, used, stale)
    except OSError:
        return None
    finally:
        os.close(fd)


def _kind(fd: int, name: str):
    """``(kind, marker)`` of the folder ``name`` open as ``fd`` (see :class:`Item`), or
    ``(None, None)`` when it is not the cache's."""
    marker = read_marker(fd)
    if marker is not None:
        if KEY.fullmatch(name):
            return "entry", marker
        if name.startswith(TMP):
            return "temp", marker
        if name.startswith(TRASH):
            return "trash", marker
        return None, None
    if KEY.fullmatch(name) and _old_files(fd, entry=True):
        return "old", None
    if _OLD_TMP.fullmatch(name) and _old_files(fd, entry=False):
        return "old_temp", None
    return None, None


def _old_files(fd: int, entry: bool) -> bool:
    """The folder ``fd`` holds only regular files named as the previous format named them
    (and, for an ``entry``, its ``meta.pkl``)."""
    names = []
    for child in os.scandir(fd):
        if not child.is_file(follow_symlinks=False) or not _OLD_FILES.fullmatch(child.name):
            return False
        names.append(child.name)
    return "meta.pkl" in names if entry else True


def _measure(fd: int, depth: int = 0) -> tuple:
    """``(bytes, newest modification time)`` of what the folder ``fd`` holds (links counted as
    links, subfolders through their own descriptors)."""
    size, newest = 0, os.fstat(fd).st_mtime
    for child in os.scandir(fd):
        st = child.stat(follow_symlinks=False)
        newest = max(newest, st.st_mtime)
        if stat.S_ISDIR(st.st_mode) and depth < 8:
            sub = os.open(child.name, _DIR, dir_fd=fd)
            try:
                more, when = _measure(sub, depth + 1)
            finally:
                os.close(sub)
            size, newest = size + more, max(newest, when)
        else:
            size += st.st_size
    return size, newest


def _gone(marker: dict) -> bool:
    """The process that wrote ``marker`` ran on this host and has ended."""
    pid = marker.get("pid")
    if marker.get("host") != socket.gethostname() or type(pid) is not int or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False        # alive, another user's
    return False


def remove(root_fd: int, name: str) -> bool:
    """Remove the cache's own subfolder ``name`` (see :func:`inspect`), never through a link;
    an entry is first renamed out of readers' way. False (nothing removed) when it is not the
    cache's own; partly removed when the files cannot all be (a shared folder without the
    permissions: the docs say what it needs)."""
    try:
        fd = os.open(name, _DIR, dir_fd=root_fd)
    except OSError:
        return False
    try:
        kind, _ = _kind(fd, name)
        if kind is None:
            return False
        if kind == "entry":
            name = _rename_away(root_fd, fd, name)
            if name is None:
                return False
        _empty(fd)
        os.rmdir(name, dir_fd=root_fd)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def _rename_away(root_fd: int, fd: int, name: str) -> str | None:
    """Rename the entry ``name`` (open as ``fd``) to a ``.del-`` name; that name, or None when
    what was renamed is not that folder (it was swapped meanwhile: renamed back)."""
    trash = TRASH + secrets.token_hex(8)
    os.rename(name, trash, src_dir_fd=root_fd, dst_dir_fd=root_fd)
    moved, held = os.stat(trash, dir_fd=root_fd, follow_symlinks=False), os.fstat(fd)
    if (moved.st_dev, moved.st_ino) != (held.st_dev, held.st_ino):
        os.rename(trash, name, src_dir_fd=root_fd, dst_dir_fd=root_fd)
        return None
    return trash


def _empty(fd: int) -> None:
    """Remove what the folder ``fd`` holds, its marker last (so that a removal cut short leaves
    a folder still known as the cache's own); links are removed, never followed."""
    for child in list(os.scandir(fd)):
        if child.name == MARKER:
            continue
        if child.is_dir(follow_symlinks=False):
            shutil.rmtree(child.name, dir_fd=fd)
        else:
            os.unlink(child.name, dir_fd=fd)
    try:
        os.unlink(MARKER, dir_fd=fd)
    except FileNotFoundError:
        pass


def sweep(root_fd: int, limit: int, keep: str | None = None) -> None:
    """Keep the cache folder ``root_fd`` within ``limit`` bytes: remove what removals cut
    short left and stale temporary folders, then the least recently used entries (``keep``,
    the entry just written, last: only when it does not fit by itself) until the cache's own
    folders, temporary ones being written included, hold at most ``limit`` bytes."""
    now = time.time()
    total, entries = 0, []
    for child in list(os.scandir(root_fd)):
        item = inspect(root_fd, child.name, now)
        if item is None:
            continue
        if item.kind == "trash" or item.stale:
            remove(root_fd, item.name)
            continue
        total += item.size
        if item.kind in ("entry", "old"):
            entries.append(item)
    for item in sorted(entries, key=lambda e: (e.name == keep, e.used)):
        if total <= limit:
            break
        if remove(root_fd, item.name):
            total -= item.size
