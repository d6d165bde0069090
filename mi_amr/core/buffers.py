"""Flat NumPy buffers that the device maps as they are: aligned allocation, and finding the one
buffer that per-grid arrays are consecutive views of.

Dr.Jit's LLVM backend maps host memory instead of copying it when the array is aligned to
:data:`ALIGN` bytes. A field computed straight into such a buffer (one per field, grid after
grid; :mod:`mi_amr.core.derive` makes them) is then read by the kernels without any copy, so a
large volume holds its values once, not once per grid and once more on the device.
"""

from __future__ import annotations

import numpy as np

from mi_amr.core import parallel

ALIGN = 64                # bytes: Dr.Jit's LLVM backend wants arrays this aligned


def aligned_empty(size: int, dtype) -> np.ndarray:
    """A new flat array of ``size`` elements of ``dtype`` starting on an :data:`ALIGN` byte
    boundary (contents undefined)."""
    itemsize = np.dtype(dtype).itemsize
    buf = np.empty(size * itemsize + ALIGN, dtype=np.uint8)
    start = (-buf.ctypes.data) % ALIGN
    return buf[start:start + size * itemsize].view(dtype)


def aligned_copy(values, dtype) -> np.ndarray:
    """``values`` (any shape) copied into a new :func:`aligned_empty` array of ``dtype``, of
    the same shape."""
    values = np.asarray(values)
    out = aligned_empty(values.size, dtype).reshape(values.shape)
    out[...] = values
    return out


def aligned_parts(sizes, dtype) -> list:
    """Flat arrays of ``sizes`` elements of ``dtype``, consecutive slices of one new
    :func:`aligned_empty` buffer, end to end in this order (what :func:`joined` finds again)."""
    ends = np.cumsum([0] + [int(n) for n in sizes])
    buf = aligned_empty(int(ends[-1]), dtype)
    return [buf[a:b] for a, b in zip(ends[:-1], ends[1:])]


FILL_CHUNK = 1 << 21      # elements a thread fills at a time in aligned_full


def aligned_full(size: int, value, dtype) -> np.ndarray:
    """:func:`aligned_empty`, every element ``value``, filled by all the CPUs (the first write
    to new memory is most of the cost: a large brick pool took a tenth of a load on one)."""
    out = aligned_empty(size, dtype)

    def fill(start):
        out[start:start + FILL_CHUNK] = value

    parallel.for_each(fill, range(0, size, FILL_CHUNK))
    return out


def joined(arrays, dtype, aligned: bool = True):
    """The flat array of ``dtype`` that ``arrays`` (C-contiguous, of that dtype) are
    consecutive views of, in this order, end to end -- what ``np.concatenate([a.ravel() for a
    in arrays])`` would copy -- or None when there is none (or, for ``aligned``, when it does
    not start on an :data:`ALIGN` byte boundary)."""
    arrays = list(arrays)
    if not arrays:
        return None
    owner = arrays[0].base
    while isinstance(owner, np.ndarray) and owner.base is not None:
        owner = owner.base
    if not isinstance(owner, np.ndarray) or owner.ndim != 1 or not owner.flags.c_contiguous:
        return None
    start = arrays[0].ctypes.data
    at = start
    for a in arrays:
        if a.dtype != dtype or not a.flags.c_contiguous or a.ctypes.data != at:
            return None
        at += a.nbytes
    begin, end = owner.ctypes.data, owner.ctypes.data + owner.nbytes
    if (aligned and start % ALIGN) or start < begin or at > end:
        return None
    whole = owner.view(np.uint8)
    return whole[start - begin:at - begin].view(dtype)
