"""Per-ray jitter in ``[0, 1)`` for the sampling methods' step offsets (interleaved sampling),
made one way for :func:`mi_amr.trace`, the benchmarks, the reference hit buffers and the
integrator's ``jitter="stable"`` mode: a hash of the ray's index and a seed, the same from one
frame to the next, so a still camera does not flicker.
"""

from __future__ import annotations

import drjit as dr
import numpy as np


def _pcg_hash(m, x):
    """PCG's output permutation of a uint32 (a well-mixed, invertible hash)."""
    state = x * 747796405 + 2891336453
    word = ((state >> ((state >> 28) + 4)) ^ state) * 277803737
    return (word >> 22) ^ word


def stable_jitter(m, index, seed=0):
    """Jitter of rays ``index`` (``m.UInt32``) for ``seed``: a Float in ``[0, 1)``."""
    h = _pcg_hash(m, _pcg_hash(m, m.UInt32(index)) ^ m.UInt32(seed))
    return m.Float(h >> 8) * (1.0 / (1 << 24))


def stable_jitter_numpy(n: int, seed: int = 0) -> np.ndarray:
    """The same values for rays ``0 .. n-1`` as float64 (slow twin of :func:`stable_jitter`)."""
    def pcg(x):
        state = (x * np.uint64(747796405) + np.uint64(2891336453)) & np.uint64(0xFFFFFFFF)
        word = (((state >> ((state >> np.uint64(28)) + np.uint64(4))) ^ state) *
                np.uint64(277803737)) & np.uint64(0xFFFFFFFF)
        return (word >> np.uint64(22)) ^ word

    h = pcg(pcg(np.arange(n, dtype=np.uint64)) ^ np.uint64(seed))
    return (h >> np.uint64(8)).astype(np.float64) / float(1 << 24)
