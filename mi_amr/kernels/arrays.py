"""Host arrays handed to the kernels: copied into aligned memory first (see
:func:`host_aligned`), so that the code Dr.Jit compiles for them does not depend on where NumPy
put them, or mapped as they are where they already lie aligned (:func:`mapped_array`); and a
level's per-grid records, which kernels read with packet loads (:func:`grid_records`)."""

from __future__ import annotations

import drjit as dr
import numpy as np

from mi_amr.core.buffers import ALIGN, aligned_copy


def host_aligned(values, dtype) -> np.ndarray:
    """``values`` flattened into a new NumPy array of ``dtype`` starting on an
    :data:`~mi_amr.core.buffers.ALIGN` byte boundary. Dr.Jit maps NumPy memory instead of
    copying it, and compiles other code (unaligned loads, no packet gathers) for an array that
    is not aligned: with arrays at whatever address NumPy gave them, the same scene would
    compile different kernels from one load to the next."""
    return aligned_copy(values, dtype).reshape(-1)


def device_array(T, values, dtype):
    """A Dr.Jit array of type ``T`` holding ``values`` (see :func:`host_aligned`)."""
    return T(host_aligned(values, dtype))


def mapped_array(T, values, dtype):
    """A Dr.Jit array of type ``T`` mapping ``values`` itself (no copy) where it is a contiguous
    array of ``dtype`` starting on an :data:`~mi_amr.core.buffers.ALIGN` byte boundary (as
    :func:`~mi_amr.core.buffers.aligned_empty` makes them), else :func:`device_array`'s
    copy. The caller leaves ``values`` unchanged while the device array is in use."""
    a = np.asarray(values)
    if a.dtype == np.dtype(dtype) and a.flags.c_contiguous and a.ctypes.data % ALIGN == 0:
        return T(a.reshape(-1))
    return device_array(T, values, dtype)


def device_table(T, values, dtype):
    """:func:`device_array` for a table that kernels gather from, padded to at least 2 entries
    (the pad is never read): Dr.Jit compiles a gather from a one-entry array into a broadcast,
    so a level with one grid or one brick would compile other code than the next level."""
    a = np.ascontiguousarray(values, dtype=dtype).ravel()
    if a.size < 2:
        a = np.concatenate([a, np.zeros(2 - a.size, dtype=dtype)])
    return device_array(T, a, dtype)


def grid_records(m, index, first):
    """Per grid of one level (``index``: its :class:`~mi_amr.core.levels.LevelIndex`) a
    record of 8 int32 on backend ``m``: its lower corner (level index), its size, ``first``
    (its first value in the array the kernel reads; uint32 bits) and 0, read by
    :func:`grid_record` with two packet loads instead of a gather a number."""
    rec = np.zeros((len(index.grids), 8), dtype=np.int32)
    rec[:, :3], rec[:, 3:6] = index.lo, index.hi - index.lo
    rec[:, 6] = np.asarray(first, dtype=np.int64).astype(np.uint32).view(np.int32)
    return device_table(m.Int32, rec, np.int32)


def grid_record(m, records, p, active=True):
    """``(lo, n, first)`` of the grids at positions ``p`` (UInt32) of :func:`grid_records`:
    lower corner and size (three Int32 each) and first value (UInt32)."""
    a = dr.gather(m.Array4i, records, 2 * p, active)
    b = dr.gather(m.Array4i, records, 2 * p + 1, active)
    return [a[0], a[1], a[2]], [a[3], b[0], b[1]], dr.reinterpret_array(m.UInt32, b[2])
