"""Ray queries without a scene: the integrator's kernels on NumPy rays.

>>> r = mi_amr.trace(vol, origins, directions, field="f", isovalue=0.3)
>>> r.t, r.hit, r.normal, r.samples
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import numpy as np

from mi_amr import params
from mi_amr.errors import AMRError, shown
from mi_amr.kernels.config import MarchConfig, clips
from mi_amr.kernels.device import device_array, lnot, opaque_floats
from mi_amr.kernels.jitter import stable_jitter
from mi_amr.kernels.prepared import PreparedVolume
from mi_amr.kernels.reconstruct import reconstruct
from mi_amr.kernels.ray import RayContext
from mi_amr.kernels.surface import first_crossing
from mi_amr.params import METHODS, RECONSTRUCTIONS


@dataclass
class TraceResult:
    """Per ray: ``t`` (inf where no hit; the hit point is ``origin + t * direction``), ``hit``,
    ``normal`` (unit gradient of the reconstructed field at the hit, pointing towards increasing
    values; facing the ray where the gradient is zero; NaN where no hit), ``samples`` (field evaluations along the ray; for ``exact`` the
    number of cubic pieces examined) and ``iso_index`` (which isovalue was crossed)."""

    t: np.ndarray
    hit: np.ndarray
    normal: np.ndarray
    samples: np.ndarray
    iso_index: np.ndarray


@dataclass
class TraceOptions:
    """The keyword options of :func:`trace` besides ``field`` and ``isovalue``."""

    method: str = params.default("method")
    reconstruction: str = params.default("reconstruction")
    step_scale: float = params.default("step_scale")
    jitter: object = None
    leaf_cells: int = params.default("leaf_cells")
    t_max: object = np.inf
    backend: object = None
    active_box: bool = True
    start_table: bool = True

    @staticmethod
    def of(options: dict) -> "TraceOptions":
        """The options given by name, refused with one :class:`AMRError` naming an unknown
        one."""
        known = TraceOptions.__dataclass_fields__
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise AMRError(f"trace() has no option {unknown[0]!r}; expected field, isovalue "
                           f"or one of {', '.join(known)}")
        return TraceOptions(**options)


def trace(volume, origins, directions, *, field: str, isovalue, **options) -> TraceResult:
    """First crossing of ``isovalue`` (a number or a list) by each ray, in the volume's world
    space. ``origins`` and ``directions`` are ``(N, 3)``; directions need not be unit length.
    ``jitter`` (``(N,)`` in [0, 1)) offsets the adaptive methods' steps; by default
    :func:`~mi_amr.kernels.jitter.stable_jitter` of the ray index. ``backend`` is a Dr.Jit
    module (default ``drjit.llvm.ad``). Where the integrator would (``exact`` on the basis
    blend), the rays are clipped to the isovalues' active box; ``active_box=False`` walks the
    whole volume instead (the slow twin: the same crossings). There the leaf searches start
    from the box's start table (:mod:`mi_amr.kernels.starts`); ``start_table=False`` starts
    them at the root and the ropes (the slow twin: the same crossings). Defaults come from
    :mod:`mi_amr.params`. Raises
    :class:`AMRError` for an isovalue that is not a finite number (in float32, the kernels'
    precision) and for rays with a non-finite origin or a zero or non-finite direction.
    ``options``: those of :class:`TraceOptions` (``method``, ``reconstruction``,
    ``step_scale``, ``jitter``, ``leaf_cells``, ``t_max``, ``backend``, ``active_box``,
    ``start_table``)."""
    opt = TraceOptions.of(options)
    method, reconstruction, step_scale = opt.method, opt.reconstruction, opt.step_scale
    jitter, leaf_cells, t_max, backend = opt.jitter, opt.leaf_cells, opt.t_max, opt.backend
    active_box, start_table = opt.active_box, opt.start_table
    if method not in METHODS:
        raise AMRError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if reconstruction not in RECONSTRUCTIONS:
        raise AMRError(f"reconstruction must be one of {', '.join(RECONSTRUCTIONS)}, "
                       f"got {reconstruction!r}")
    if not step_scale > 0:
        raise AMRError(f"step_scale must be > 0, got {step_scale}")
    origins, directions = _rays(origins, directions)
    isovalues = _isovalues(isovalue)
    m = backend or dr.llvm.ad
    prep = _prepared(volume, field, leaf_cells, m)
    dev = prep.device
    n = len(origins)
    iso = opaque_floats(m, isovalues)
    scale = opaque_floats(m, [step_scale])
    cfg = MarchConfig(method=method, basis=reconstruction == "basis", isovalues=iso,
                      step_scale=scale, num_iso=len(isovalues))
    if active_box and clips(cfg):
        cfg.active_box = dev.active_box(isovalues)
        if start_table:
            cfg.start_table = dev.start_table(isovalues)
    dev.node_search(cfg.basis)           # the leaf ranges, before the march is traced
    o = _array3(m, origins)
    d = _array3(m, directions)
    rho = stable_jitter(m, dr.arange(m.UInt32, n)) if jitter is None else \
        device_array(m.Float, jitter, np.float32)
    t_end = device_array(m.Float, np.broadcast_to(np.asarray(t_max, dtype=np.float32), (n,)),
                         np.float32)
    c = first_crossing(RayContext(dev, cfg, o, d, m.Float(0.0), t_end, m.Bool(True)), rho)
    arrays = dev.arrays(cfg.basis)
    _, grad = reconstruct(dev, cfg.basis, dr.fma(d, c.t, o), arrays, c.hit)
    # Where the gradient vanishes (the walls that close finest's cracks are flat in the field)
    # the normal faces the ray instead.
    flat = lnot(dr.squared_norm(grad) > 0.0)
    normal = dr.normalize(dr.select(flat, -d, grad))
    dr.eval(c.t, c.hit, c.samples, c.k, normal)
    hit = c.hit.numpy().astype(bool)
    t = np.where(hit, c.t.numpy().astype(np.float64), np.inf)
    nrm = np.stack([normal.x.numpy(), normal.y.numpy(), normal.z.numpy()], axis=1).astype(
        np.float64)
    nrm[~hit] = np.nan
    return TraceResult(t=t, hit=hit, normal=nrm, samples=c.samples.numpy().astype(np.int64),
                       iso_index=np.where(hit, c.k.numpy().astype(np.int64), -1))


def _rays(origins, directions):
    """``(N, 3)`` float64 origins and directions, or an AMRError: a ray whose origin is not
    finite, or whose direction is zero or not finite, has no defined path."""
    try:
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise AMRError(f"origins and directions must be (N, 3) arrays of numbers ({e})") from None
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise AMRError(f"origins and directions must both be (N, 3) arrays, got "
                       f"{origins.shape} and {directions.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(origins), axis=1))
    if len(bad):
        raise AMRError(f"origins: {len(bad)} ray(s) have a NaN or infinite origin (first: ray "
                       f"{bad[0]}, {shown(origins[bad[0]])})")
    # A direction that float32 (the kernels' precision) turns into zero or inf counts as well.
    with np.errstate(over="ignore", invalid="ignore"):
        d32 = directions.astype(np.float32)
        usable = np.all(np.isfinite(d32), axis=1) & np.any(d32 != 0, axis=1) \
            & np.isfinite(np.sum(d32.astype(np.float64) ** 2, axis=1))
    bad = np.flatnonzero(~usable)
    if len(bad):
        raise AMRError(f"directions: {len(bad)} ray(s) have a zero, NaN or infinite direction "
                       f"(first: ray {bad[0]}, {shown(directions[bad[0]])}); every ray needs a "
                       f"finite, non-zero direction")
    return origins, directions


def _isovalues(isovalue) -> list:
    """``isovalue`` (a number or a list of numbers) as floats that stay finite in float32."""
    if isinstance(isovalue, (str, bytes)):
        raise AMRError(f"isovalue must be a number or a list of numbers, got the text "
                       f"{isovalue!r}")
    try:
        isovalues = [float(x) for x in np.atleast_1d(np.asarray(isovalue, dtype=object))]
    except (TypeError, ValueError):
        raise AMRError(f"isovalue must be a number or a list of numbers, got "
                       f"{shown(isovalue)}") from None
    if not isovalues:
        raise AMRError("isovalue must hold at least one number, got an empty list")
    limit = float(np.finfo(np.float32).max)
    if not all(math.isfinite(x) and abs(x) <= limit for x in isovalues):
        raise AMRError(f"isovalue must hold finite numbers within float32's range "
                       f"(+-{limit:.3g}), got {shown(isovalue)}")
    return isovalues


def _prepared(volume, field, leaf_cells, m) -> PreparedVolume:
    """One PreparedVolume per (volume, field, leaf size, backend), kept on the volume (its
    ``trace_preparations``)."""
    cache = volume.trace_preparations
    key = (field, leaf_cells, m.__name__)
    if key not in cache:
        cache[key] = PreparedVolume(volume, field, leaf_cells=leaf_cells, m=m)
    return cache[key]


def _array3(m, a):
    a = np.asarray(a, dtype=np.float32)
    return m.Array3f(*(device_array(m.Float, a[:, i], np.float32) for i in range(3)))
