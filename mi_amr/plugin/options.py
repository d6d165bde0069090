"""The amr_iso integrator's parameters: read from a plain mapping, checked once, with messages
that name the parameter and what is allowed. The algorithm never sees Mitsuba's ``Properties``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

from mi_amr.errors import AMRError
from mi_amr.kernels.march import METHODS, RECONSTRUCTIONS

MODES = ("surface", "volume")

# name: (type description, default) -- the parameter table of the plugin's docstring.
PARAMETERS = {
    "filename": ("string", None),
    "field": ("string", None),
    "isovalue": ("float or list", None),
    "iso_color": ("rgb or list", "0.8 0.8 0.8"),
    "iso_opacity": ("float or list", 1.0),
    "color_field": ("string", None),
    "colormap": ("string", None),
    "color_range": ("2 floats", None),
    "mode": ("string", "surface"),
    "method": ("string", "exact"),
    "reconstruction": ("string", "basis"),
    "step_scale": ("float", 0.5),
    "shadows": ("boolean", True),
    "to_world": ("transform", None),
    "ka": ("float", 0.15),
    "kd": ("float", 0.75),
    "ks": ("float", 0.25),
    "shininess": ("float", 32.0),
    "ambient": ("float", 1.0),
    "band_width": ("float", 0.004),
    "band_support": ("2 floats", None),
    "band_peak": ("float", 1.6),
    "preintegrated": ("boolean", False),
    "leaf_cells": ("integer", 4),
    "max_layers": ("integer", 8),
}


@dataclass
class Options:
    filename: str
    field: str
    isovalues: list
    iso_colors: list
    iso_opacity: list
    color_field: Optional[str] = None
    colormap: Optional[str] = None
    color_range: Optional[tuple] = None
    mode: str = "surface"
    method: str = "exact"
    reconstruction: str = "basis"
    step_scale: float = 0.5
    shadows: bool = True
    ka: float = 0.15
    kd: float = 0.75
    ks: float = 0.25
    shininess: float = 32.0
    ambient: float = 1.0
    band_width: float = 0.004
    band_support: Optional[tuple] = None
    band_peak: float = 1.6
    preintegrated: bool = False
    leaf_cells: int = 4
    max_layers: int = 8
    extra: dict = field(default_factory=dict)

    @property
    def translucent(self) -> bool:
        return any(a < 1.0 for a in self.iso_opacity)


def parse(values: dict) -> Options:
    """Check a mapping of parameter values (strings, numbers, booleans as Mitsuba gives them)."""
    unknown = sorted(set(values) - set(PARAMETERS))
    if unknown:
        raise AMRError(f"amr_iso: unknown parameter(s) {unknown}; allowed: "
                       f"{', '.join(PARAMETERS)}")
    for required in ("filename", "field", "isovalue"):
        if required not in values:
            raise AMRError(f"amr_iso: parameter '{required}' is required")
    opt = Options(filename=_string(values, "filename"), field=_string(values, "field"),
                  isovalues=_floats(values, "isovalue"), iso_colors=[], iso_opacity=[])
    k = len(opt.isovalues)
    if not 1 <= k <= 8:
        raise AMRError(f"amr_iso: parameter 'isovalue' needs 1 to 8 values, got {k}")
    opt.iso_colors = _colors(values.get("iso_color", PARAMETERS["iso_color"][1]), k)
    opt.iso_opacity = _floats({"iso_opacity": values.get("iso_opacity", 1.0)}, "iso_opacity")
    if len(opt.iso_opacity) == 1:
        opt.iso_opacity *= k
    if len(opt.iso_opacity) != k or not all(0.0 < a <= 1.0 for a in opt.iso_opacity):
        raise AMRError(f"amr_iso: parameter 'iso_opacity' needs 1 or {k} values in (0, 1], got "
                       f"{values.get('iso_opacity')!r}")
    opt.color_field = values.get("color_field")
    opt.colormap = values.get("colormap")
    if (opt.color_field is None) != (opt.colormap is None):
        raise AMRError("amr_iso: 'color_field' and 'colormap' go together; give both or neither")
    if "color_range" in values:
        opt.color_range = _pair(values, "color_range")
    opt.mode = _choice(values, "mode", MODES)
    opt.method = _choice(values, "method", METHODS)
    opt.reconstruction = _choice(values, "reconstruction", RECONSTRUCTIONS)
    opt.step_scale = _number(values, "step_scale", lo=1e-4, hi=64.0)
    opt.shadows = _bool(values, "shadows")
    opt.ka = _number(values, "ka", lo=0.0, hi=100.0)
    opt.kd = _number(values, "kd", lo=0.0, hi=100.0)
    opt.ks = _number(values, "ks", lo=0.0, hi=100.0)
    opt.shininess = _number(values, "shininess", lo=0.0, hi=1e4)
    opt.ambient = _number(values, "ambient", lo=0.0, hi=1e6)
    opt.band_width = _number(values, "band_width", lo=1e-30, hi=math.inf)
    if "band_support" in values:
        opt.band_support = _pair(values, "band_support")
    opt.band_peak = _number(values, "band_peak", lo=1e-6, hi=1e6)
    opt.preintegrated = _bool(values, "preintegrated")
    opt.leaf_cells = int(_number(values, "leaf_cells", lo=2, hi=256, integer=True))
    opt.max_layers = int(_number(values, "max_layers", lo=1, hi=64, integer=True))
    if opt.mode == "volume" and k != 1:
        raise AMRError(f"amr_iso: mode 'volume' renders one opacity band; give one isovalue, "
                       f"got {k}")
    return opt


def _default(name):
    return PARAMETERS[name][1]


def _string(values, name):
    v = values.get(name, _default(name))
    if not isinstance(v, str) or not v.strip():
        raise AMRError(f"amr_iso: parameter '{name}' must be a non-empty string, got {v!r}")
    return v.strip()


def _choice(values, name, allowed):
    v = values.get(name, _default(name))
    if v not in allowed:
        raise AMRError(f"amr_iso: parameter '{name}' must be one of {', '.join(allowed)}; "
                       f"got {v!r}")
    return v


def _number(values, name, lo, hi, integer=False):
    v = values.get(name, _default(name))
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter '{name}' must be a number, got {v!r}") from None
    if not (lo <= x <= hi) or math.isnan(x) or (integer and x != int(x)):
        kind = "an integer" if integer else "a number"
        raise AMRError(f"amr_iso: parameter '{name}' must be {kind} in [{lo:g}, {hi:g}], got {v!r}")
    return x


def _bool(values, name):
    v = values.get(name, _default(name))
    if isinstance(v, bool):
        return v
    if isinstance(v, str) and v.lower() in ("true", "false"):
        return v.lower() == "true"
    raise AMRError(f"amr_iso: parameter '{name}' must be true or false, got {v!r}")


def _floats(values, name):
    v = values.get(name)
    items = v if isinstance(v, (list, tuple)) else str(v).replace(";", ",").split(",") \
        if isinstance(v, str) else [v]
    try:
        out = [float(x) for x in items]
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter '{name}' must be a number or a comma-separated list "
                       f"of numbers, got {v!r}") from None
    if not out or not all(math.isfinite(x) for x in out):
        raise AMRError(f"amr_iso: parameter '{name}' must hold finite numbers, got {v!r}")
    return out


def _pair(values, name):
    v = values.get(name)
    items = v.replace(",", " ").split() if isinstance(v, str) else list(v)
    try:
        lo, hi = (float(x) for x in items)
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter '{name}' must be two numbers 'low high', "
                       f"got {v!r}") from None
    if not lo < hi:
        raise AMRError(f"amr_iso: parameter '{name}' needs low < high, got {v!r}")
    return (lo, hi)


def _colors(v, k):
    if isinstance(v, str):
        groups = [g.split() for g in v.replace(",", " ").split(";")] if ";" in v else \
            [v.replace(",", " ").split()]
    else:
        try:
            groups = [[v[0], v[1], v[2]]]
        except (TypeError, IndexError):
            groups = [[v]]
    try:
        cols = [[float(x) for x in g] for g in groups]
    except ValueError:
        raise AMRError(f"amr_iso: parameter 'iso_color' must be 'r g b' or 'r g b; r g b; ...', "
                       f"got {v!r}") from None
    if any(len(c) != 3 for c in cols) or len(cols) not in (1, k):
        raise AMRError(f"amr_iso: parameter 'iso_color' needs 1 or {k} colours of 3 components, "
                       f"got {v!r}")
    return cols * k if len(cols) == 1 else cols
