"""The 2D transfer function on the device: a bilinear lookup of opacity by the field's value and
gradient magnitude (the table of :class:`mi_amr.core.transfer2d.Transfer2D`).

Everything about the table -- its entries, its shape, its ranges -- is an opaque kernel input,
so a new table (of any shape) or new ranges compile no kernel. Opacities are per step of length
``dx0`` (world units, the finest cell width), as the 1D band's, so
:func:`mi_amr.kernels.band.corrected` applies to them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels.band import optical_depth
from mi_amr.kernels.device import opaque_floats

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Float

# Entries of :attr:`Transfer2DInputs.header`.
V0, V1, G0, G1, ROWS, COLS, SUPPORT_LO, SUPPORT_HI = range(8)


@dataclass
class Transfer2DInputs:
    """``table``: the opacities row after row (row ``j`` = gradient magnitude, ascending);
    ``integral``: the same layout, each row's extinction integrated over the values
    (:meth:`~mi_amr.core.transfer2d.Transfer2D.row_integrals`, for the exact method);
    ``header``: ``v0 v1 g0 g1 rows cols lo hi`` (``lo, hi``: the value support, see
    :meth:`~mi_amr.core.transfer2d.Transfer2D.value_support`); ``dx0``: the step length the
    opacities are for (world). All opaque."""

    table: Float
    header: Float
    dx0: Float
    integral: Optional[Float] = None

    def get(self, m, k: int):
        return dr.gather(m.Float, self.header, m.UInt32(k))


def transfer2d_inputs(m, tf, dx0: float) -> Transfer2DInputs:
    """The device values of the host table ``tf`` (a ``Transfer2D``) for steps of ``dx0``."""
    rows, cols = tf.shape
    lo, hi = tf.value_support()
    return Transfer2DInputs(table=opaque_floats(m, tf.table.ravel()),
                            header=opaque_floats(m, [tf.v0, tf.v1, tf.g0, tf.g1, rows, cols,
                                                     lo, hi]),
                            dx0=opaque_floats(m, [dx0]),
                            integral=opaque_floats(m, tf.row_integrals(dx0, tol.OPACITY_CAP)
                                                   .ravel()))


def _bilinear(m, tf: Transfer2DInputs, values, v, gmag, active):
    """Bilinear lookup of ``values`` (a table of :attr:`Transfer2DInputs.table`'s layout) at
    value ``v`` (clamped to ``[v0, v1]``) and gradient magnitude ``gmag`` (clamped to
    ``[g0, g1]``)."""
    v0, v1, g0, g1 = (tf.get(m, k) for k in (V0, V1, G0, G1))
    rows, cols = tf.get(m, ROWS), tf.get(m, COLS)
    u = dr.clip(dr.select(dr.isnan(v), 0.0, (v - v0) / (v1 - v0)), 0.0, 1.0) * (cols - 1.0)
    w = (gmag - g0) / (g1 - g0)
    w = dr.clip(dr.select(dr.isnan(w), 0.0, w), 0.0, 1.0) * (rows - 1.0)
    i = dr.clip(dr.floor(u), 0.0, cols - 2.0)
    j = dr.clip(dr.floor(w), 0.0, rows - 2.0)
    fu, fw = u - i, w - j
    base = m.UInt32(j) * m.UInt32(cols) + m.UInt32(i)
    up = base + m.UInt32(cols)

    def at(index):
        return dr.gather(m.Float, values, index, active)

    low = dr.lerp(at(base), at(base + 1), fu)
    high = dr.lerp(at(up), at(up + 1), fu)
    return dr.lerp(low, high, fw)


def alpha(m, tf: Transfer2DInputs, v, gmag):
    """Opacity for one step of length ``dx0`` at value ``v`` (field units) and gradient
    magnitude ``gmag`` (field units per volume-world unit): bilinear in the table, 0 outside
    ``[v0, v1]`` (and where ``v`` is NaN), ``gmag`` clamped to ``[g0, g1]``."""
    inside = (v >= tf.get(m, V0)) & (v <= tf.get(m, V1))
    return dr.select(inside, _bilinear(m, tf, tf.table, v, gmag, inside), 0.0)


def segment_alpha(m, tf: Transfer2DInputs, a, b, dx, gmag):
    """Pre-integrated opacity over a step of length ``dx`` (world) along which the value runs
    linearly from ``a`` to ``b`` at gradient magnitude ``gmag``: the row integrals' difference
    over the value change; a ramp shorter than a column takes the opacity at its middle."""
    cols = tf.get(m, COLS)
    short = dr.abs(b - a) * (cols - 1.0) < tf.get(m, V1) - tf.get(m, V0)
    mid = optical_depth(alpha(m, tf, 0.5 * (a + b), gmag)) / tf.dx0
    active = m.Bool(True)
    Ia = _bilinear(m, tf, tf.integral, a, gmag, active)
    Ib = _bilinear(m, tf, tf.integral, b, gmag, active)
    tau = dr.select(short, mid, (Ib - Ia) / dr.select(short, 1.0, b - a))
    return 1.0 - dr.exp(-dr.maximum(tau, 0.0) * dx)
