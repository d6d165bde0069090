"""The one table of ``amr_iso``'s parameters: name, type, default, allowed values and meaning.

:mod:`mi_amr.plugin.options` checks a scene's values against it, the integrator's docstring
table is generated from it (:func:`docstring_table`), and the parameters marked
``traversable`` are the ones ``mi.traverse(scene)`` shows as ``integrator.<name>``: changing
them renders the next frame without compiling a kernel. :func:`mi_amr.trace` takes its defaults
from here too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

METHODS = ("exact", "bisect", "adaptive", "uniform")
RECONSTRUCTIONS = ("basis", "finest")
MODES = ("surface", "volume")
LAYER_MODES = ("composite", "one_shadow", "stochastic")
VOLUME_SHADOWS = ("cache", "corrected", "exact")
MAX_ISOVALUES = 8
REQUIRED = object()          # the default of a parameter that must be given


@dataclass(frozen=True)
class Param:
    """One parameter. ``kind`` is how it is written in a scene (the docstring's type column);
    ``lo``/``hi`` bound a number (inclusive), ``choices`` a string."""

    name: str
    kind: str
    default: Any
    meaning: str
    lo: float = -math.inf
    hi: float = math.inf
    choices: tuple = ()
    traversable: bool = False

    @property
    def required(self) -> bool:
        return self.default is REQUIRED


TABLE = (
    Param("filename", "string", REQUIRED,
          "anything :func:`mi_amr.load` reads; relative to the scene file"),
    Param("field", "string", REQUIRED,
          "field to contour; stored, or derived (``q_criterion``, ``speed``, "
          "``vorticity_magnitude``) from the velocity"),
    Param("isovalue", "float / list", REQUIRED,
          f"one or up to {MAX_ISOVALUES} isovalues, ``\"0.05, 0.1\"``", traversable=True),
    Param("iso_color", "rgb / list", "0.8 0.8 0.8",
          "colour per isovalue, ``\"r g b; r g b\"`` (linear RGB)", traversable=True),
    Param("iso_opacity", "float / list", 1.0,
          "opacity per isovalue in (0, 1]; below 1 the surfaces are composited front to back",
          lo=0.0, hi=1.0, traversable=True),
    Param("color_field", "string", None,
          "colour the surface by this field (``none``: no colour field; a colour map "
          "given is still checked) ..."),
    Param("colormap", "string", None,
          "... with ``\"v: r g b, ...\"`` pairs (each holds its colour over 1/24 of the "
          "pairs' span, at most a quarter of the gap to its neighbours) or a matplotlib map "
          "name; traversable as ``colormap_values`` and ``colormap_colors``", traversable=True),
    Param("color_range", "2 floats", None,
          "field values mapped to the colour map's ends; default: the data's range (named "
          "map) or the first and last pair's values (pairs, which it stretches)",
          traversable=True),
    Param("mode", "string", "surface", "``surface`` or ``volume``", choices=MODES),
    Param("method", "string", "exact", "``exact``, ``bisect``, ``adaptive``, ``uniform``",
          choices=METHODS),
    Param("reconstruction", "string", "basis", "``basis`` (Wald et al.) or ``finest``",
          choices=RECONSTRUCTIONS),
    Param("jitter", "string", "stable",
          "sampling methods' step offset per pixel sample: ``stable`` (a hash of the sample's "
          "index: the same every frame, so a still camera does not flicker) or ``random`` "
          "(from the sampler)", choices=("stable", "random")),
    Param("step_scale", "float", 0.5, "step in finest cells (sampling methods)",
          lo=1e-4, hi=64.0, traversable=True),
    Param("shadows", "boolean", True, "shadow rays test meshes and isosurfaces",
          traversable=True),
    Param("volume_shadows", "string", "cache",
          "volume mode: how a lit piece of the band finds its shadow. ``cache``: a grid per "
          "directional, point or spot light holding the transmittance through the bands "
          "towards it, built with the exact shadow compositing when the light, the bands or "
          "the transfer function change (not when the camera moves); a lit piece whose light "
          "counts takes the first grid cell of its shadow ray from the value around it (a "
          "ramp along the ray, pre-integrated as a step of the band is, bent to the value at "
          "its end where the ray runs along the band) and reads the grid (one trilinear "
          "lookup) beyond it; meshes still cast theirs by a shadow ray, and other lights "
          "(area, environment) keep exact shadow rays. ``corrected``: the "
          "cache, and per camera sample one exact shadow ray from one lit piece (or sample), "
          "picked by its light, that corrects the cache's error: unbiased, its noise going "
          "down with the samples per pixel. ``exact``: a shadow ray per lit piece "
          "composites the bands on its way to each light (cost grows with the square of the "
          "pieces a ray meets)", choices=VOLUME_SHADOWS),
    Param("to_world", "transform", None,
          "places the volume's world space in the scene (default: identity)", traversable=True),
    Param("ka", "float", 0.15, "Phong ambient coefficient", lo=0.0, hi=100.0, traversable=True),
    Param("kd", "float", 0.75, "Phong diffuse coefficient", lo=0.0, hi=100.0, traversable=True),
    Param("ks", "float", 0.25, "Phong specular coefficient", lo=0.0, hi=100.0,
          traversable=True),
    Param("shininess", "float", 32.0, "Phong exponent", lo=0.0, hi=1e4, traversable=True),
    Param("ambient", "float", 1.0, "ambient light level", lo=0.0, hi=1e6, traversable=True),
    Param("band_width", "float / list", 0.004,
          "volume mode: Gaussian width of the opacity band centred on each isovalue (field; "
          "one, or one per isovalue)", lo=1e-30, traversable=True),
    Param("band_support", "pairs", None,
          "volume mode: where each band's opacity is non-zero, ``\"lo hi\"`` or ``\"lo hi; lo "
          "hi\"`` (field; default isovalue +- 2 widths)", traversable=True),
    Param("band_peak", "float / list", 1.6,
          "volume mode: each band's opacity scale (clamped to 1)", lo=1e-6, hi=1e6,
          traversable=True),
    Param("preintegrated", "boolean", False,
          "volume mode: pre-integrated opacity per step (sampling methods)"),
    Param("shading_extrema", "boolean", True,
          "volume mode, exact: also cut each cell's piece of the ray where the diffuse term "
          "turns (Marchesin et al. 2009, section 3.2)"),
    Param("transfer2d", "string", None,
          "volume mode: a 2D transfer function, opacity by value and "
          "|grad f|: a ``.npy`` table (rows = |grad f| ascending, columns = value) or a "
          "``.png``/``.exr`` image (alpha, else first channel; top row = highest |grad f|); "
          "relative to the scene file; replaces the bands; traversable as "
          "``transfer2d_table`` (the opacities, row-major) and ``transfer2d_range``",
          traversable=True),
    Param("transfer2d_range", "4 floats", None,
          "with ``transfer2d``: ``\"v0 v1 g0 g1\"``, the values across its columns (field) "
          "and the |grad f| across its rows (field per volume-world unit)"),
    Param("transfer2d_blobs", "string", None,
          "volume mode: a 2D transfer function of Gaussian blobs in the "
          "(value, |grad f|) plane, ``\"v g sigma_v sigma_g peak; ...\"``; opacity min(1, sum "
          "of the blobs), per finest-cell step; not with ``transfer2d``"),
    Param("aovs", "boolean", False,
          "report the isosurface's depth, normal, position, values, level and grid as AOVs "
          "(:mod:`mi_amr.plugin.aovs`)"),
    Param("leaf_cells", "integer", 4, "kd leaf size in cells (empty-space skipping)",
          lo=2, hi=256),
    Param("max_layers", "integer", 8, "translucent surfaces composited per ray, at most",
          lo=1, hi=64),
    Param("layers", "string", "composite",
          "translucent surfaces: ``composite`` (each sample shades every layer it meets, "
          "weighted by the light reaching it, each with its own shadow rays), ``one_shadow`` "
          "(every layer shaded, one shadow ray per light and sample, from a layer picked by "
          "its share of that light: the same image in expectation, noisy only where a pixel's "
          "layers see the light differently) or ``stochastic`` (one layer per sample, picked "
          "with the probability of that weight, as Mitsuba's ``mask`` BSDF does: the same "
          "image in expectation, noisier per sample, shading one layer instead of every one; "
          "from 2 spp on, the numbers that pick are shared by 16 pixels and stratified over a "
          "pixel's samples, and shadow rays play Russian roulette where under a quarter of the "
          "light gets through; alpha is then the share of samples that stop at a layer)",
          choices=LAYER_MODES),
    Param("allow_nonfinite", "boolean", False,
          "keep the file's NaN and Inf values as missing data (no weight, as "
          ":func:`mi_amr.load` with ``allow_nonfinite=True``); without it such a file is "
          "refused, naming the grid and field"),
)
BY_NAME = {p.name: p for p in TABLE}
TRAVERSABLE = tuple(p.name for p in TABLE if p.traversable)


def default(name: str):
    """The default of parameter ``name`` (:data:`REQUIRED` when it must be given)."""
    return BY_NAME[name].default


def float32_bounds(name: str) -> tuple:
    """``(lo, hi)`` of parameter ``name`` rounded to float32, the type the kernels hold every
    traversable number in: a value is checked after the same rounding as its bounds, so the
    table's own limits are accepted (``float32(1e-4)`` is just below ``1e-4``)."""
    import numpy as np

    p = BY_NAME[name]
    return float(np.float32(p.lo)), float(np.float32(p.hi))


def _shown(p: Param) -> str:
    if p.required:
        return "(required)"
    if p.default is None:
        return "none"
    if isinstance(p.default, bool):
        return "true" if p.default else "false"
    return f"{p.default:g}" if isinstance(p.default, float) else str(p.default)


def docstring_table(width: int = 52) -> str:
    """The parameter table as reStructuredText (the integrator's docstring shows it)."""
    import textwrap

    heads = ("Parameter", "Type", "Meaning", "Default")
    rows = [(p.name, p.kind, p.meaning + (" [traversable]" if p.traversable else ""),
             _shown(p)) for p in TABLE]
    widths = [max(len(heads[0]), *(len(r[0]) for r in rows)),
              max(len(heads[1]), *(len(r[1]) for r in rows)), width,
              max(len(heads[3]), *(len(r[3]) for r in rows))]
    rule = "  ".join("=" * w for w in widths)
    lines = [rule, "  ".join(h.ljust(w) for h, w in zip(heads, widths)).rstrip(), rule]
    for r in rows:
        wrapped = textwrap.wrap(r[2], width) or [""]
        for i, text in enumerate(wrapped):
            cells = (r[0], r[1], text, r[3]) if i == 0 else ("", "", text, "")
            lines.append("  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip())
    lines.append(rule)
    return "\n".join(lines)
