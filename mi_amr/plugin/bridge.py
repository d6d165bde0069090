"""Values between Mitsuba's types (``mi.*``) and the kernels' (a Dr.Jit JIT backend ``m``).

In the vectorised variants they are the same types and nothing is converted. In Mitsuba's
scalar variants Mitsuba works on Python numbers while the kernels run on one-element LLVM
arrays: numbers going in are made opaque (a Python number would enter a kernel as a literal,
and the loops need variables), and results come back as numbers.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def vectorised() -> bool:
    """Whether the active variant is a JIT one (``llvm_*``, ``cuda_*``)."""
    return dr.is_jit_v(mi.Float)


def to_mi(x, T):
    """A kernel value as Mitsuba type ``T`` (a scalar one)."""
    if vectorised():
        return T(x)
    dr.eval(x)
    return T(x.numpy()[0])


def to_mi3(v, T):
    """A kernel 3-vector as Mitsuba type ``T`` (``mi.Color3f``, ``mi.Normal3f`` ...)."""
    if vectorised():
        return T(v.x, v.y, v.z)
    dr.eval(v)
    return T(float(v.x.numpy()[0]), float(v.y.numpy()[0]), float(v.z.numpy()[0]))


def to_kernel(m, x):
    """A Mitsuba float as a kernel Float."""
    v = m.Float(x)
    if not vectorised():
        dr.make_opaque(v)
    return v


def to_kernel3(m, v):
    """A Mitsuba 3-vector as a kernel ``Array3f``."""
    out = m.Array3f(v.x, v.y, v.z)
    if not vectorised():
        dr.make_opaque(out)
    return out
