"""Volume mode's transmittance caches (``volume_shadows="cache"``): per directional, point or
spot light of the scene, a grid (:mod:`mi_amr.kernels.shadow_grid`) of the transmittance
through the bands from each grid point towards the light.

A cache is filled with the same exact compositing that a per-piece shadow ray runs
(:meth:`~mi_amr.plugin.integrator._AMRIso.iso_transmittance`, ``composite`` without shading),
one wavefront of rays from the grid's points. It is built again when what it depends on
changes: the volume, the bands (isovalues, widths, supports, peaks) or the 2D transfer
function, the volume's placement in the scene, or the light; never for a camera move. A lit
piece's shadow (:class:`CachedShadow`) is the transmittance over the first grid cell of its
shadow ray (the band's shadow on itself: from the value around the piece, or composited
exactly, see :mod:`mi_amr.kernels.near`) times the cache read beyond it. The meshes' shadows
are not in it: a lit piece still tests them with Mitsuba's shadow ray. Lights
whose direction depends on the light sample (area lights, environments) have no cache and
keep exact shadow rays.

The integrator asks for its caches before it traces a frame (``render``), so that a frame's
program is the same whether or not it built them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr import tolerances as tol
from mi_amr.kernels.arrays import device_array
from mi_amr.kernels.near import NearStretch
from mi_amr.kernels.device import opaque_floats
from mi_amr.kernels.shadow_grid import (GridPlan, TransmittanceGrid, band_leaves, lookup,
                                        needed_points, plan, point_positions)
from mi_amr.plugin import bridge, shading

# The inputs whose values a cache depends on (besides the volume, its placement, the lights).
BAND_INPUTS = ("isovalue", "band_width", "band_offsets", "band_peak", "transfer2d_table",
               "transfer2d_range")
# A grid that holds no shadow: where shadows are off or no leaf holds opacity (the frame's
# program stays the same, the lookups are masked or find 1).
EMPTY = GridPlan(lo=np.zeros(3), cell=np.ones(3), dims=np.array([2, 2, 2]))


def cacheable(emitter) -> bool:
    """Does ``emitter`` send its light from one direction or one point (directional, point,
    spot), the same for every light sample at a point?"""
    flags = emitter.flags()
    return mi.has_flag(flags, mi.EmitterFlags.DeltaDirection) or \
        mi.has_flag(flags, mi.EmitterFlags.DeltaPosition)


class ShadowCaches:
    """The caches of one integrator, for the last scene and inputs it rendered
    (:meth:`grids`); ``builds`` counts how often they were filled; ``max_points``: the most
    points a cache holds (a coarser cache for a quick preview: the next frame builds it at the
    new size)."""

    def __init__(self):
        self._key = None
        self._grids = []
        self._dev = None     # the device volume the key names (kept, so its id stays its own)
        self.builds = 0
        self.max_points = tol.SHADOW_CACHE_POINTS

    def grids(self, integ, scene, stop: Optional[Callable[[], bool]] = None):
        """Per emitter of ``scene``, its :class:`TransmittanceGrid`, or None where it keeps
        exact shadow rays (every emitter where ``integ`` does not cache: surface mode,
        ``volume_shadows="exact"``, scalar variants). Built again where the key changed;
        with ``stop``, in wavefronts of at most ``SHADOW_CACHE_BUILD_CHUNK`` points, asking
        ``stop()`` before each: None (nothing kept) once it says True."""
        emitters = scene.emitters()
        if not uses_cache(integ):
            return [None] * len(emitters)
        key = (_key(integ, emitters), self.max_points)
        if key != self._key and dr.flag(dr.JitFlag.SymbolicScope):
            # (Asked first inside a symbolic loop, where no kernel may run: exact shadows.)
            return [None] * len(emitters)
        if key != self._key:
            grids = build_all(integ, emitters, self.max_points, stop)
            if grids is None:
                return None
            self._grids, self._key, self._dev = grids, key, integ.dev
            self.builds += 1
        return self._grids


def uses_cache(integ) -> bool:
    """Does ``integ`` light its band through transmittance caches?"""
    opt = integ.opt
    return bridge.vectorised() and opt.mode == "volume" and \
        opt.volume_shadows in ("cache", "corrected")


def _key(integ, emitters) -> tuple:
    """What the caches depend on, as bytes: the device volume, the band inputs, the
    placement, whether shadows are on, and each emitter's parameters."""
    host = integ.inputs.host
    bands = tuple(host[n].tobytes() for n in BAND_INPUTS if n in host)
    frame = integ.frame.host.tobytes()
    return (id(integ.dev), bands, frame, bool(host["shadows"][0]),
            tuple(_emitter_key(e) for e in emitters))


def _emitter_key(emitter) -> tuple:
    """An emitter's traversable values as bytes (its direction, position, radiance ...)."""
    params = mi.traverse(emitter)
    out = []
    for name in sorted(params.keys()):
        value = params[name]
        value = value.matrix if isinstance(value, mi.Transform4f) else value
        try:
            out.append((name, np.asarray(value, dtype=np.float64).tobytes()))
        except (TypeError, ValueError):
            out.append((name, repr(value)))
    return tuple(out)


def build_all(integ, emitters, max_points: int = tol.SHADOW_CACHE_POINTS, stop=None):
    """Fill one grid per cacheable emitter (None for the others), each of at most
    ``max_points`` points; ``stop``: as :meth:`ShadowCaches.grids` (None when it stopped)."""
    m = integ.m
    leaves = opacity_leaves(integ)
    shadows = bool(integ.inputs.host["shadows"][0])
    if not shadows or len(leaves) == 0:
        empty = TransmittanceGrid.of(m, EMPTY, opaque_floats(m, np.ones(EMPTY.size)))
        return [empty if cacheable(e) else None for e in emitters]
    grid = plan(integ.dev.tree, leaves, max_points)
    # (From aligned memory: the kernel's loads of a misaligned array compile otherwise.)
    index = device_array(m.UInt32, needed_points(grid, integ.dev.tree, leaves), np.uint32)
    out = []
    for e in emitters:
        out.append(_build(integ, e, grid, index, stop) if cacheable(e) else None)
        if cacheable(e) and out[-1] is None:
            return None
    return out


def opacity_leaves(integ) -> np.ndarray:
    """The kd leaves where the bands (or the 2D transfer function) may have opacity."""
    inputs, dev = integ.inputs, integ.dev
    host = inputs.host
    if inputs.transfer2d is not None:
        bands = [inputs.transfer2d_host.value_support()]
    else:
        offsets = host["band_offsets"].reshape(-1, 2)
        bands = [(iso + lo, iso + hi) for iso, (lo, hi) in zip(host["isovalue"], offsets)]
    ranges = dev.node_ranges(integ.opt.reconstruction == "basis")
    return band_leaves(dev.tree, ranges, bands)


def _build(integ, emitter, grid: GridPlan, index, stop=None) -> Optional[TransmittanceGrid]:
    """The transmittance from each needed point (flat ``index``) of ``grid`` towards
    ``emitter``: the exact shadow ray of a lit piece there (its mesh test aside), one
    wavefront, or with ``stop`` one per ``SHADOW_CACHE_BUILD_CHUNK`` points (the same values;
    None once ``stop()`` says True). The other points hold 1 (no lookup reads them)."""
    m = integ.m
    values = dr.full(m.Float, 1.0, grid.size)
    n = dr.width(index)
    step = n if stop is None else tol.SHADOW_CACHE_BUILD_CHUNK
    for start in range(0, n, max(step, 1)):
        if stop is not None and stop():
            return None
        # (An opaque start: each wavefront is the same kernel.)
        lanes = dr.opaque(m.UInt32, start) + dr.arange(m.UInt32, min(step, n - start))
        part = index if step >= n else dr.gather(m.UInt32, index, lanes)
        _transmittances(integ, emitter, (grid, part), values)
        dr.eval(values)
        if stop is not None:
            dr.sync_thread()            # (launched, a wavefront runs on: wait for it)
    # (In scene units: a volume-space stretch of the reach is at most this long in the scene.)
    stretch = float(np.linalg.svd(integ.frame.host[:3, :3], compute_uv=False).max())
    return TransmittanceGrid.of(m, grid, values, grid.reach * stretch)


def _transmittances(integ, emitter, points, values) -> None:
    """Scatter into ``values`` the transmittance towards ``emitter`` from the points
    ``points`` (``(grid, flat index)``): 1 where the emitter does not light them."""
    grid, index = points
    p = point_positions(integ.m, grid, index)
    P = integ.frame.to_scene @ bridge.to_mi3(p, mi.Point3f)
    it = dr.zeros(mi.Interaction3f, dr.width(index))
    it.p = P
    ds, _ = emitter.sample_direction(it, mi.Point2f(0.5), True)
    lit = ds.pdf > 0.0
    T = integ.iso_transmittance(shading.shadow_ray(P, ds), True, lit)
    dr.scatter(values, bridge.to_kernel(integ.m, dr.select(lit, T, 1.0)), index)


@dataclass(frozen=True)
class CachedShadow:
    """The band's transmittance towards one cached light, at scene points: that of the first
    ``grid.reach`` of the shadow ray, times the ``grid`` read where that stretch ends;
    ``to_volume`` takes scene points to the volume's world space and ``m`` is the kernels'
    backend. The first stretch is ``near``'s (a :class:`~mi_amr.kernels.near.NearStretch`):
    taken only on the lanes whose light counts (the others read the grid at the point
    itself), from the value around the point where it has a ramp, else composited by
    ``transmittance`` (``(ray, from_iso, active)``, the exact shadow compositing, see
    :meth:`~mi_amr.plugin.integrator._AMRIso.iso_transmittance`) from the camera ray's leaf;
    without ``near``: composited everywhere, searched from the root."""

    m: Any
    grid: TransmittanceGrid
    transmittance: Callable
    to_volume: Any
    near: Optional[NearStretch] = None

    def __call__(self, P, ds, active):
        """The transmittance (a Mitsuba ``Float``) from scene points ``P`` towards the light
        samples ``ds``, where ``active``."""
        ray = shading.shadow_ray(P, ds)
        exact = mi.Bool(active) if self.near is None else active & mi.Bool(self.near.where)
        reach = dr.select(exact, bridge.to_mi(self.grid.reach, mi.Float), 0.0)
        beyond = active & (ray.maxt > reach)
        ray.maxt = dr.minimum(ray.maxt, reach)
        if self.near is not None and self.near.ramp is not None:
            seg = bridge.to_kernel3(self.m, self.to_volume @ (ds.d * ray.maxt))
            near = bridge.to_mi(self.near.ramp.transmittance(seg, self.m.Bool(exact)), mi.Float)
        else:
            near = self.transmittance(ray, True, exact,
                                      start=None if self.near is None else self.near.walk)
        far = bridge.to_kernel3(self.m, self.to_volume @ (P + ds.d * reach))
        return near * bridge.to_mi(lookup(self.m, self.grid, far, self.m.Bool(beyond)),
                                   mi.Float)
