"""What a march looks for, and the value tests that decide which kd nodes it may skip.

A :class:`MarchConfig` holds two kinds of things. The *structure* (``method``, ``basis``,
``num_iso``, whether there is a band or a 2D transfer function, ``preintegrated``,
``shading_extrema``) shapes the traced program: changing it compiles other kernels. Everything
else (the isovalues, the step scale, the band's shape, the 2D transfer function's table) is an
opaque device value that may change between frames without compiling anything.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import drjit as dr

from mi_amr import tolerances as tol
from mi_amr.kernels.band import BandInputs
from mi_amr.kernels.starts import StartTable
from mi_amr.kernels.transfer2d import SUPPORT_HI, SUPPORT_LO, Transfer2DInputs
from mi_amr.params import METHODS, RECONSTRUCTIONS  # noqa: F401  (re-exported)

# Annotation names: the backend's arrays have these names in drjit.llvm.ad and drjit.cuda.ad
# (Dr.Jit reads a dataclass's annotations but converts nothing by them).
from drjit.llvm.ad import Float


# Steps of a leaf search per step of the march that waits for it: a SIMD packet runs a loop as
# long as its slowest lane, so a whole search nested in the march made every lane wait for the
# longest search in the packet. A few steps at a time let the lanes with a leaf work meanwhile.
SEEK_STEPS = 6


@dataclass
class SearchPlan:
    """How the traversal (:meth:`~mi_amr.kernels.traverse.March.next`) takes its leaf
    searches: ``steps`` of a search per step of the march (None: each search whole), and
    ``two_levels``: a turn of the search first goes down through a non-empty inner node
    without its exit and rope work (its record holds its children's,
    :meth:`~mi_amr.kernels.device.DeviceVolume.node_search`), then takes the full step on the
    child. The crossings and the steps are the same, in the same order, for every plan (the
    plans besides the default are the slow twins, for tests)."""

    steps: Optional[int] = SEEK_STEPS
    two_levels: bool = True


@dataclass
class MarchConfig:
    """``isovalues``: a device array of ``num_iso`` values; ``step_scale``: a one-element
    device array (finest cells per step of the sampling methods); ``band``: volume mode's
    :class:`~mi_amr.kernels.band.BandInputs`, one band around each isovalue, or None for
    surfaces; ``transfer2d``: volume mode's
    :class:`~mi_amr.kernels.transfer2d.Transfer2DInputs`, which then replaces the bands
    (every method); ``active_box``: ``(lo, hi)`` opaque points (volume world) holding every
    leaf whose range holds an isovalue (:meth:`~mi_amr.kernels.device.DeviceVolume.active_box`),
    or None; see :func:`clip_box`; ``search``: how leaf searches are taken (structure)."""

    method: str
    basis: bool
    isovalues: Float
    step_scale: Float
    num_iso: int
    band: Optional[BandInputs] = None
    preintegrated: bool = False
    shading_extrema: bool = True
    transfer2d: Optional[Transfer2DInputs] = None
    active_box: Optional[tuple] = None
    start_table: Optional[StartTable] = None
    search: SearchPlan = field(default_factory=SearchPlan)

    def iso(self, dev, k):
        """Isovalue ``k`` (a Python int, or a per-lane index array)."""
        m = dev.m
        return dr.gather(m.Float, self.isovalues, m.UInt32(k))


def clip_box(cfg: MarchConfig):
    """The box an exact march of isosurfaces may clip its rays to (besides the volume's
    bounds): ``cfg.active_box``, where the field is continuous (the basis blend), so that it
    crosses an isovalue only inside a leaf whose range holds it; else None. The finest level
    jumps at grid edges, where a crossing lies between two skipped nodes, and the sampling
    methods take the side of the nodes skipped before their first sample: neither clips."""
    return cfg.active_box if clips(cfg) else None


def start_table(cfg: MarchConfig):
    """The :class:`~mi_amr.kernels.starts.StartTable` a leaf search may start from: where the
    rays clip to the active box (:func:`clip_box`), ``cfg.start_table``, else None (a search
    that starts from a deeper node skips smaller nodes, which changes the sides the sampling
    methods see)."""
    return cfg.start_table if clips(cfg) else None


def clips(cfg: MarchConfig) -> bool:
    """Does :func:`clip_box` use ``cfg.active_box``: the exact method on the basis blend,
    looking for isosurfaces (no band, no 2D transfer function)?"""
    plain = cfg.band is None and cfg.transfer2d is None
    return cfg.method == "exact" and cfg.basis and plain


def holds(dev, cfg: MarchConfig, r_lo, r_hi):
    """Can a value range ``[r_lo, r_hi]`` hold a crossing (or band opacity)?"""
    m = dev.m
    out = m.Bool(False)
    if cfg.transfer2d is not None:
        lo, hi = (cfg.transfer2d.get(m, k) for k in (SUPPORT_LO, SUPPORT_HI))
        return (r_lo <= hi) & (r_hi >= lo) & (lo < hi)
    if cfg.band is not None:
        for k in range(cfg.num_iso):
            centre = cfg.iso(dev, k)
            out |= (r_lo < centre + cfg.band.get(m, "hi", k)) & \
                (r_hi > centre + cfg.band.get(m, "lo", k))
        return out
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        out |= (r_lo <= iso) & (iso <= r_hi)
    return out


def sides_differ(dev, cfg: MarchConfig, a, b):
    """Does some isovalue lie strictly between values ``a`` and ``b``? (False if one is NaN.)"""
    m = dev.m
    out = m.Bool(False)
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        out |= (a - iso) * (b - iso) < 0.0
    return out


def first_between(dev, cfg: MarchConfig, a, b):
    """Index of the isovalue strictly between values ``a`` and ``b`` that lies nearest to
    ``a`` (the first one met going from ``a`` to ``b``; the first listed among equals)."""
    m = dev.m
    out = m.UInt32(0)
    best = m.Float(dr.inf)
    for k in range(cfg.num_iso):
        iso = cfg.iso(dev, k)
        near = ((a - iso) * (b - iso) < 0.0) & (dr.abs(iso - a) < best)
        out = dr.select(near, m.UInt32(k), out)
        best = dr.select(near, dr.abs(iso - a), best)
    return out


def bisect_depth(cfg: MarchConfig):
    """How many halvings take a bracket of one step (``cfg.step_scale`` finest cells) down to
    :data:`~mi_amr.tolerances.BISECT_TARGET` cells (at least one)."""
    return dr.maximum(dr.ceil(dr.log2(cfg.step_scale / tol.BISECT_TARGET)), 1.0)
