"""Integer arithmetic of kernel indices that the CPU backend does not vectorise.

A vector integer division has no instruction on x86 (LLVM splits it into one division a lane);
a float64 division has one, and is exact enough: for integers below 2^53 the rounded quotient
never reaches the next whole number, so its floor is the integer quotient.
"""

from __future__ import annotations

import drjit as dr


def quotient(m, a, b):
    """``a // b`` of UInt32 arrays (``b >= 1``) on backend ``m``, through a float64
    division."""
    return m.UInt32(dr.floor(m.Float64(a) / m.Float64(b)))
