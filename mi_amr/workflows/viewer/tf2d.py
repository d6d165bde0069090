"""The 2D transfer function in the viewer (volume mode): Gaussian blobs drawn on the field's
value x |grad f| histogram, rasterized into a table of fixed shape (:data:`SHAPE`) over a fixed
plane (:class:`TF2D`), so every edit is an ``mi.traverse`` update of
``integrator.transfer2d_table`` (nothing compiles). Turning it on or off changes the kernels'
structure (the scene is loaded again, once).

Requests: ``{"op": "tf2d", "action": "start"}`` (one isovalue needed; a first blob at the
isovalue), ``{"op": "tf2d", "action": "stop"}`` (back to the bands), and ``{"op": "tf2d",
"blobs": [[v, g, sigma_v, sigma_g, peak], ...]}`` (at most :data:`MAX_BLOBS`; ``v`` and
``sigma_v`` in field units, ``g`` and ``sigma_g`` in field per volume-world unit, ``peak`` the
opacity scale, each blob's opacity ``min(1, sum)`` as in
:func:`mi_amr.core.transfer2d.blobs_numpy`). "Save scene" writes the table beside the scene
(``NAME.tf2d.npy``) and names it with ``transfer2d`` and ``transfer2d_range``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.workflows.viewer.controls import number

SHAPE = (48, 96)                # the table's rows (|grad f|) and columns (value)
MAX_BLOBS = 16
HIST_SHAPE = (48, 96)           # the page's value x |grad f| histogram (rows, columns)
GRAD_QUANTILE = 0.995           # the plane's top: this quantile of the leaf cells' |grad f|


@dataclass(frozen=True)
class TF2D:
    """The plane ``(v0, v1, g0, g1)`` (field; field per world unit) and the blobs on it."""

    plane: tuple
    blobs: tuple                # of (v, g, sigma_v, sigma_g, peak)

    def table(self) -> np.ndarray:
        """The opacities on :data:`SHAPE` samples of the plane (rows: |grad f| ascending)."""
        from mi_amr.core.transfer2d import blobs_numpy

        v0, v1, g0, g1 = self.plane
        vs = np.linspace(v0, v1, SHAPE[1])
        gs = np.linspace(g0, g1, SHAPE[0])
        if not self.blobs:
            return np.zeros(SHAPE)
        return blobs_numpy(self.blobs, vs[None, :], gs[:, None])

    def as_dict(self) -> dict:
        return {"plane": list(self.plane), "blobs": [list(b) for b in self.blobs]}


def plane_of(describe: dict) -> tuple:
    """The plane of the scene on screen (its value range, |grad f| from 0 to the top)."""
    lo, hi = describe["value_range"]
    top = describe["histogram2d"]["plane"][3] if describe.get("histogram2d") else 1.0
    return (float(lo), float(hi), 0.0, float(top))


def change(state, msg: dict, ctx):
    """The state after the request ``msg`` (an :class:`AMRError` says why it is refused)."""
    if state.mode != "volume":
        raise AMRError("2D transfer function: it works in volume mode (Mode: volume)")
    action = msg.get("action")
    if action == "start":
        if len(state.isovalues) != 1:
            raise AMRError("2D transfer function: it replaces the bands of one isovalue; remove "
                           "isovalues down to one first")
        v0, v1, g0, g1 = ctx.plane
        first = (state.isovalues[0], 0.5 * g1, (v1 - v0) / 20, g1 / 6, 1.0)
        return state.replace(tf2d=TF2D(ctx.plane, (first,)))
    if action == "stop":
        return state.replace(tf2d=None)
    if action is not None:
        raise AMRError(f"2D transfer function: unknown action {action!r} (start or stop)")
    if state.tf2d is None:
        raise AMRError("2D transfer function: start it first")
    return state.replace(tf2d=TF2D(state.tf2d.plane, _blobs(msg.get("blobs"), state.tf2d)))


def _blobs(value, tf: TF2D) -> tuple:
    if not isinstance(value, list) or len(value) > MAX_BLOBS:
        raise AMRError(f"2D transfer function: 'blobs' must be a list of at most {MAX_BLOBS} "
                       f"blobs [v, g, sigma_v, sigma_g, peak]")
    v0, v1, g0, g1 = tf.plane
    span_v, span_g = v1 - v0, g1 - g0
    out = []
    for i, b in enumerate(value):
        if not isinstance(b, list) or len(b) != 5:
            raise AMRError(f"2D transfer function: blob {i + 1} must be [v, g, sigma_v, "
                           f"sigma_g, peak]")
        name = f"blob {i + 1}"
        out.append((number(b[0], f"{name} value", v0 - span_v, v1 + span_v),
                    number(b[1], f"{name} |grad f|", 0.0, g1 + span_g),
                    _positive(b[2], f"{name} sigma_v", span_v),
                    _positive(b[3], f"{name} sigma_g", span_g),
                    _positive(b[4], f"{name} peak", 1e3)))
    return tuple(out)


def _positive(value, name: str, hi: float) -> float:
    x = number(value, name, 0.0, hi)
    if x <= 0:
        raise AMRError(f"{name}: must be above 0")
    return x


def histogram2d(volume, field: str, value_range) -> dict:
    """Log counts of the leaf cells in :data:`HIST_SHAPE` bins of value x |grad f| (rows:
    |grad f| ascending from 0), and the plane they cover."""
    from mi_amr.workflows.histogram import value_and_gradient

    v, g = value_and_gradient(volume, field)
    lo, hi = value_range
    top = float(np.quantile(g, GRAD_QUANTILE)) if g.size else 1.0
    top = top if math.isfinite(top) and top > 0 else 1.0
    counts, _, _ = np.histogram2d(g, v, bins=HIST_SHAPE,
                                  range=((0.0, top), (lo, hi if hi > lo else lo + 1.0)))
    return {"counts": np.log1p(counts).round(3).tolist(), "plane": [lo, hi, 0.0, top]}
