"""Asking the allocators to touch fresh memory less during a load.

A load makes and frees many arrays of a few to a few tens of megabytes (chunks of the
derivation, a depth's pairs in the kd-tree, the leaf ranges' windows). glibc's malloc gives
such arrays fresh pages from the system and returns them when they are freed, and the first
write to a fresh page is slow on virtual machines (it costs more than the arithmetic done
in it). With the two settings below, arrays up to :data:`MMAP_THRESHOLD` come from the heap and
up to :data:`TRIM_THRESHOLD` of freed heap is kept, so the next array reuses pages already
touched. The peak memory of a load is unchanged; the process may hold up to
:data:`TRIM_THRESHOLD` more afterwards. A load of :data:`RELEASE_CELLS` cells or more hands the
freed memory back (:func:`release_freed_memory`) before its brick pools, which cannot reuse it.

NumPy advises the kernel to back its large arrays with transparent huge pages. Where the kernel
compacts memory to find a huge page when a page of such an array is first written (its
``transparent_hugepage/defrag`` policy ``madvise``, the common default, or ``always``), a
fragmented machine stalls on that write, far longer than the write takes, while a load
writes most of its memory once and in order, where huge pages gain little (the frames that
follow were measured the same either way). A load therefore turns the advice off
(:func:`keep_freed_memory`), for the process, as it does the glibc settings.

``MI_AMR_KEEP_MEMORY=0`` leaves the allocators as they are. Elsewhere than glibc (macOS, musl)
the glibc settings do nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys

MMAP_THRESHOLD = 32 << 20    # bytes; glibc's ceiling for this setting on 64-bit systems
TRIM_THRESHOLD = 64 << 20    # bytes of freed memory kept at the heap's top (twice MMAP_THRESHOLD)
# Cells from which a load hands its freed memory back before the brick pools
# (release_freed_memory): below it the memory at stake is small, and a render running beside
# the load (a movie's next step, the viewer's) would lose the cached buffers it reuses.
RELEASE_CELLS = 1 << 24
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3     # mallopt's parameter numbers (malloc.h)


def keep_freed_memory() -> bool:
    """Set the two thresholds and turn NumPy's huge-page advice off (see the module
    docstring); True where the thresholds were set. Calling it again sets the same values."""
    if not _left_alone():
        huge_page_advice(False)
    mallopt = _glibc("mallopt")
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and \
        bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))


def huge_page_advice(on: bool):
    """Make NumPy advise transparent huge pages for its new arrays (``on``, its default) or
    not; returns the setting before, or None where this NumPy has no such switch
    (``NUMPY_MADVISE_HUGEPAGE`` is the same switch, read when NumPy is imported)."""
    import numpy as np

    core = getattr(np, "_core", None)          # NumPy 2 (np.core warns there); 1.x below
    switch = getattr(getattr(core if core is not None else np.core, "multiarray", None),
                     "_set_madvise_hugepage", None)
    return None if switch is None else bool(switch(bool(on)))


def release_freed_memory() -> bool:
    """Give the freed memory that glibc's heap holds (anywhere in the heap, not only at its
    top) back to the system; True where it did. A large load calls it before arrays that
    cannot reuse that memory (the brick pools, each a new mapping), which it would otherwise
    add to the load's peak."""
    trim = _glibc("malloc_trim")
    if trim is None:
        return False
    trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
    trim(0)
    return True


def _glibc(name: str):
    """The process's C library function ``name``; None with ``MI_AMR_KEEP_MEMORY=0``, off
    Linux, or where the C library has no such function (not glibc)."""
    if _left_alone() or not sys.platform.startswith("linux"):
        return None
    try:
        return getattr(ctypes.CDLL(None), name)     # the process's own C library
    except (OSError, AttributeError):
        return None


def _left_alone() -> bool:
    """True where ``MI_AMR_KEEP_MEMORY=0`` asks to leave the allocators as they are."""
    return os.environ.get("MI_AMR_KEEP_MEMORY", "1").strip() == "0"
