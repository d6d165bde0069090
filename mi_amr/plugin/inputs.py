"""The integrator's per-frame values: opaque kernel inputs that ``mi.traverse(scene)`` shows as
``integrator.<name>``, checked again whenever they change.

===================  ===========================  ==========================================
traverse name        value                        when
===================  ===========================  ==========================================
isovalue             k floats (field units)       always
iso_color            3 k floats (linear RGB)      always
iso_opacity          k floats in (0, 1]           always
step_scale           1 float (finest cells)       always
shadows              1 bool                       always
ka kd ks             1 float each                 always
shininess ambient    1 float each                 always
to_world             4x4 transform                always (volume world -> scene)
colormap_values      512 edges on [0, 1]          with a colour map (:mod:`.colormap`)
colormap_colors      3 x 512 floats (linear RGB)  with a colour map
color_range          2 floats (field units)       with a colour map
band_width           k floats (field units)       volume mode (one band per isovalue)
band_offsets         2 k floats: support - iso    volume mode
band_peak            k floats                     volume mode
transfer2d_table     rows x cols opacities        with a 2D transfer function (its table,
                     (row-major, rows = |grad f|)  from a file or rasterized blobs)
transfer2d_range     4 floats: v0 v1 g0 g1        with a 2D transfer function
===================  ===========================  ==========================================

``k`` (the number of isovalues) and the table sizes (the 2D table's shape too) are part of the
scene's structure: a change
of size is refused (load the scene again). :func:`colormap_table` makes the two colour-map
arrays from a map name or pairs, e.g. for a viewer.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr.errors import AMRError
from mi_amr.params import BY_NAME, float32_bounds
from mi_amr.kernels.band import band_inputs, band_shape
from mi_amr.kernels.colormap import ColorMap, check_range
from mi_amr.kernels.device import opaque_bools, opaque_floats
from mi_amr.core.transfer2d import Transfer2D
from mi_amr.kernels.transfer2d import transfer2d_inputs

PHONG = ("ka", "kd", "ks", "shininess", "ambient")
FLAGS = mi.ParamFlags.NonDifferentiable


def colormap_table(spec: str, data_range=None, color_range=None):
    """``(colormap_values, colormap_colors, color_range)`` for a colour map given as in a scene
    (pairs, or a matplotlib name over ``data_range``), ready to assign through ``mi.traverse``
    (NumPy arrays). ``color_range`` overrides the map's own range."""
    cmap = ColorMap.parse(spec, data_range)
    edges, colors = cmap.table()
    rng = cmap.value_range if color_range is None else check_range(color_range, "color_range")
    return edges, colors, np.array(rng, dtype=np.float32)


class FrameInputs:
    """The values listed in the module docstring, on the kernels' backend ``m``.

    ``values`` are the arrays ``mi.traverse`` hands out and writes into (whatever a user
    assigns: a literal, a computed array). The kernels read ``self[name]``: copies that
    :meth:`refresh` makes from host memory after every change, opaque and never literals, so
    the traced program is the same whatever the values and however they were assigned."""

    def __init__(self, opt, m, color_data_range, min_h: float, transfer2d=None):
        self.m, self.k, self.min_h = m, len(opt.isovalues), float(min_h)
        self.transfer2d_host = transfer2d
        self.values = {
            "isovalue": m.Float(opt.isovalues),
            "iso_color": m.Float(np.ravel(opt.iso_colors)),
            "iso_opacity": m.Float(opt.iso_opacity),
            "step_scale": m.Float(opt.step_scale),
            "shadows": m.Bool(opt.shadows),
        }
        self.values.update({name: m.Float(getattr(opt, name)) for name in PHONG})
        if opt.colormap is not None:
            edges, colors, rng = colormap_table(opt.colormap, color_data_range, opt.color_range)
            self.values.update(colormap_values=m.Float(edges), colormap_colors=m.Float(colors),
                               color_range=m.Float(rng))
        if opt.mode == "volume":
            offsets = [(-2.0 * w, 2.0 * w) for w in opt.band_width] \
                if opt.band_support is None else \
                [(lo - iso, hi - iso) for (lo, hi), iso in zip(opt.band_support, opt.isovalues)]
            self.values.update(band_width=m.Float(opt.band_width),
                               band_offsets=m.Float(np.ravel(offsets)),
                               band_peak=m.Float(opt.band_peak))
        if transfer2d is not None:
            self._t2d_shape = transfer2d.shape
            self.values.update(
                transfer2d_table=m.Float(transfer2d.table.ravel()),
                transfer2d_range=m.Float([transfer2d.v0, transfer2d.v1, transfer2d.g0,
                                          transfer2d.g1]))
        self._sizes = {name: dr.width(v) for name, v in self.values.items()}
        self.refresh()

    def __getitem__(self, name):
        return self._kernel[name]

    @property
    def has_colormap(self) -> bool:
        return "colormap_values" in self.values

    def put(self, callback) -> None:
        """Hand every value to ``mi.traverse``'s callback."""
        for name, value in self.values.items():
            callback.put(name, value, FLAGS)

    def refresh(self) -> None:
        """Check the values (after a change through ``mi.traverse``), rebuild what depends on
        them (the band's table; the 2D transfer function's inputs, for the finest cell width of
        this volume) and make them all opaque."""
        for name, value in self.values.items():
            if dr.width(value) != self._sizes[name]:
                raise AMRError(f"amr_iso: '{name}' must keep {self._sizes[name]} value(s); load "
                               f"the scene again to change how many")
        host = {name: np.asarray(v.numpy(), dtype=np.float64) for name, v in self.values.items()}
        _check(host)
        self.host = host
        m = self.m
        self._kernel = {name: opaque_floats(m, v) for name, v in host.items() if name != "shadows"}
        self._kernel["shadows"] = opaque_bools(m, host["shadows"] != 0)
        self.band = None
        self.transfer2d = None
        if "transfer2d_table" in host:
            self.transfer2d_host = Transfer2D(host["transfer2d_table"].reshape(self._t2d_shape),
                                              *host["transfer2d_range"],
                                              source="amr_iso: 'transfer2d_table'")
            self.transfer2d = transfer2d_inputs(m, self.transfer2d_host, self.min_h)
        if "band_width" in host:
            offsets = host["band_offsets"].reshape(-1, 2)
            self.band = band_inputs(m, [band_shape(float(w), tuple(map(float, o)), float(p),
                                                   self.min_h)
                                        for w, o, p in zip(host["band_width"], offsets,
                                                           host["band_peak"])])


def _check(host: dict) -> None:
    """The checks of :mod:`mi_amr.plugin.options`, on values set through ``mi.traverse``."""
    def bad(name, what):
        raise AMRError(f"amr_iso: '{name}' {what}, got {host[name].tolist()}")

    for name, v in host.items():
        if name != "shadows" and not np.all(np.isfinite(v)):
            bad(name, "must hold finite numbers")
    if not np.all((host["iso_opacity"] > 0) & (host["iso_opacity"] <= 1)):
        bad("iso_opacity", "must lie in (0, 1]")
    lo, hi = float32_bounds("step_scale")
    if not lo <= host["step_scale"][0] <= hi:
        bad("step_scale", f"must lie in [{BY_NAME['step_scale'].lo:g}, "
                          f"{BY_NAME['step_scale'].hi:g}]")
    for name in PHONG:
        if host[name][0] < 0:
            bad(name, "must be >= 0")
    if "color_range" in host:
        check_range(host["color_range"], "color_range")
        if np.any(np.diff(host["colormap_values"]) < 0):
            bad("colormap_values", "must not decrease")
    if "band_width" in host:
        offsets = host["band_offsets"].reshape(-1, 2)
        if not np.all(host["band_width"] > 0):
            bad("band_width", "must be > 0")
        if not np.all((offsets[:, 0] < 0) & (offsets[:, 1] > 0)):
            bad("band_offsets", "must be (low < 0 < high) offsets from each isovalue")
        if not np.all(host["band_peak"] > 0):
            bad("band_peak", "must be > 0")
        _check_disjoint(host["isovalue"], offsets)


def _check_disjoint(isovalues, offsets) -> None:
    """Volume mode's bands may not overlap: each value holds the opacity of one band at most,
    so the exact method composites the bands a ramp meets in the order it meets them."""
    spans = sorted((iso + lo, iso + hi, k) for k, (iso, (lo, hi)) in
                   enumerate(zip(isovalues, offsets)))
    for (lo_a, hi_a, a), (lo_b, hi_b, b) in zip(spans, spans[1:]):
        if lo_b < hi_a:
            raise AMRError(f"amr_iso: the opacity bands of isovalues {isovalues[a]:g} "
                           f"([{lo_a:g}, {hi_a:g}]) and {isovalues[b]:g} ([{lo_b:g}, {hi_b:g}]) "
                           f"overlap; narrow 'band_width' or 'band_support' so that no value "
                           f"lies in two bands")
