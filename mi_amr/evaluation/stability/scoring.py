"""Scoring the methods against the dense reference: one row per (case, method,
reconstruction) (see :mod:`mi_amr.evaluation.stability` for the rows' keys).

Ray parameters and positions are the volume's world space; depth errors and tolerances are in
finest cells; field values and :data:`~mi_amr.evaluation.stability.rays.TANGENT` in field units.
"""

from __future__ import annotations

import numpy as np

from mi_amr.evaluation.stability.rays import TANGENT, DenseField, Reference, box_interval, \
    dense_reference
from mi_amr.kernels.trace import trace
from mi_amr.params import METHODS

EXACT_DEPTH_TOL = 1e-3  # finest cells: what exact must meet on clear crossings
SAMPLED = ("bisect", "adaptive", "uniform")


def trace_reference(volume, ref: Reference, method, reconstruction, step_scale, **kw):
    """:func:`~mi_amr.kernels.trace.trace` of field ``f`` on the reference's rays (world,
    float32 values) at its isovalue; ``step_scale`` in finest cells."""
    return trace(volume, ref.o, ref.d, field="f", isovalue=ref.iso, method=method,
                 reconstruction=reconstruction, step_scale=step_scale, **kw)


def _late_tolerance(volume, method, step_scale) -> float:
    """Finest cells past the reference's crossing that still count as finding it: a step of
    the coarsest level (the adaptive methods step by the leaf's cells) plus one cell."""
    ratio = volume.level_spacing(0).max() / volume.level_spacing(volume.num_levels - 1).min()
    return 1.0 + (0.0 if method == "exact" else step_scale * ratio)


def score(case, volume, ref: Reference, res, method, reconstruction, step_scale, *,
          touch_must_hit=False, notes="", metrics=None) -> dict:
    """One row: ``res`` (a :class:`~mi_amr.kernels.trace.TraceResult`) against ``ref``.

    Rays the reference clearly crosses must be hit at the first crossing (a hit more than
    :func:`_late_tolerance` beyond it counts as missed, one as far before it as false); rays it
    clearly does not cross must not be hit. With ``touch_must_hit`` a ray touching the surface
    (``|dmin| <= TANGENT``) must be hit too, where it touches."""
    h = volume.level_spacing(volume.num_levels - 1).min()
    tol = _late_tolerance(volume, method, step_scale) * h
    t_ref = ref.t.copy()
    must = ref.crossed & ref.clear
    must_not = ~ref.crossed & ref.clear
    if touch_must_hit:
        touch = (np.abs(ref.dmin) <= TANGENT) & ~ref.undefined
        t_ref = np.where(touch & ~np.isfinite(t_ref), ref.t_min, t_ref)
        must |= touch
        must_not &= ~touch
    late = must & res.hit & (res.t > t_ref + tol)
    early = must & res.hit & (res.t < t_ref - tol)
    missed = must & (~res.hit | late)
    false = (must_not & res.hit) | early
    good = must & res.hit & ~late & ~early
    err = np.abs(res.t[good] - t_ref[good]) / h
    nonfinite = int(np.sum(np.isnan(res.t) | (res.hit & ~np.all(np.isfinite(res.normal), axis=1))))
    # A hit must lie on the ray inside the volume (the traces start at t = 0).
    t_in, t_out = box_interval(*volume.bounds, ref.o, ref.d)
    slack = 1e-3 * h / np.linalg.norm(ref.d, axis=1)
    outside = int(np.sum(res.hit & ((res.t < np.maximum(t_in, 0.0) - slack) |
                                    (res.t > t_out + slack))))
    excluded = int(np.sum(~(must | must_not)))
    parts = [notes] if notes else []
    if method != "exact":
        parts.append(f"step_scale={step_scale:g}")
    if excluded:
        parts.append(f"{excluded} touchy/undefined rays not counted")
    if late.any():
        parts.append(f"{int(late.sum())} hit a later crossing")
    if early.any():
        parts.append(f"{int(early.sum())} hit before the surface")
    if nonfinite:
        parts.append(f"{nonfinite} non-finite outputs")
    if outside:
        parts.append(f"{outside} hits outside the volume (t out of the ray's range)")
    m = {"expected": int(must.sum()), "late": int(late.sum()), "early": int(early.sum()),
         "excluded": excluded, "nonfinite": nonfinite, "outside": outside,
         "touch_must_hit": touch_must_hit,
         "twin_difference": ref.twin_difference, "step_scale": step_scale,
         "missed_rays": np.flatnonzero(missed).tolist()[:20],
         "false_rays": np.flatnonzero(false).tolist()[:20]}
    m.update(metrics or {})
    return row(case, method, reconstruction, len(ref.t), int(missed.sum()), int(false.sum()),
               float(err.max()) if err.size else 0.0, "; ".join(parts), expected=int(must.sum()),
               metrics=m)


def row(case, method, reconstruction, rays, missed, false, depth, notes, *, expected=None,
        metrics=None) -> dict:
    """A row of the suite (``depth``: the largest depth error, finest cells)."""
    return {"case": case, "method": method, "reconstruction": reconstruction, "rays": rays,
            "missed": missed, "false": false, "max_depth_error_cells": depth, "notes": notes,
            "expected": expected, "metrics": dict(metrics or {})}


def measure(case, volume, o, d, iso, *, reconstructions=("basis", "finest"), methods=METHODS,
            step_scale=0.5, touch_must_hit=False, notes="", ref_kw=None, trace_kw=None,
            extra=None) -> list:
    """Rows for every method and reconstruction on rays ``o + t d`` (world) at ``iso`` (field
    units); ``step_scale`` in finest cells. ``extra(ref, res, method, reconstruction)`` may add
    metrics to a row."""
    rows = []
    for rec in reconstructions:
        ref = dense_reference(DenseField(volume, "f", rec == "basis"), o, d, iso,
                              **(ref_kw or {}))
        for method in methods:
            res = trace_reference(volume, ref, method, rec, step_scale, **(trace_kw or {}))
            metrics = extra(ref, res, method, rec) if extra else None
            rows.append(score(case, volume, ref, res, method, rec, step_scale,
                              touch_must_hit=touch_must_hit, notes=notes, metrics=metrics))
    return rows
