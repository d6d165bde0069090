"""Host arrays handed to the kernels: copied into aligned memory first (see
:func:`host_aligned`), so that the code Dr.Jit compiles for them does not depend on where NumPy
put them, or mapped as they are where they already lie aligned (:func:`mapped_array`)."""

from __future__ import annotations

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
