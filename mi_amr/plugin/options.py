"""The amr_iso integrator's parameters: read from a plain mapping, checked once against the
parameter table (:mod:`mi_amr.params`), with messages that name the parameter and what is
allowed. The algorithm never sees Mitsuba's ``Properties``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

from mi_amr import params
from mi_amr.core.transfer2d import parse_blobs, parse_range
from mi_amr.errors import AMRError, did_you_mean
from mi_amr.kernels.colormap import ColorMap

FLOAT32_MAX = 3.4028234663852886e38
NO_COLOR_FIELD = ("none", "")    # color_field values that mean "no colour field"


@dataclass
class Options:
    """Checked parameter values (names as in :data:`mi_amr.params.TABLE`; ``isovalues``,
    ``iso_colors`` and ``iso_opacity`` hold one entry per isovalue); ``given``: the names of
    the parameters the scene set (the others hold their defaults)."""

    filename: str
    field: str
    isovalues: list
    iso_colors: list
    iso_opacity: list
    color_field: Optional[str]
    colormap: Optional[str]
    color_range: Optional[tuple]
    mode: str
    method: str
    reconstruction: str
    jitter: str
    step_scale: float
    shadows: bool
    volume_shadows: str
    ka: float
    kd: float
    ks: float
    shininess: float
    ambient: float
    band_width: list
    band_support: Optional[list]
    band_peak: list
    preintegrated: bool
    shading_extrema: bool
    transfer2d: Optional[str]
    transfer2d_range: Optional[tuple]
    transfer2d_blobs: Optional[list]
    aovs: bool
    leaf_cells: int
    max_layers: int
    allow_nonfinite: bool
    layers: str
    given: frozenset = frozenset()


def parse(values: dict) -> Options:
    """Check a mapping of parameter values (strings, numbers, booleans as Mitsuba gives them;
    ``to_world`` is read by the integrator itself)."""
    unknown = sorted(set(values) - set(params.BY_NAME))
    if unknown:
        hints = [f"'{u}'{did_you_mean(u, params.BY_NAME)}" for u in unknown]
        raise AMRError(f"amr_iso: unknown parameter(s) {', '.join(hints)}; allowed: "
                       f"{', '.join(params.BY_NAME)}")
    for p in params.TABLE:
        if p.required and p.name not in values:
            raise AMRError(f"amr_iso: parameter '{p.name}' is required")
    isovalues = _floats(values, "isovalue")
    k = len(isovalues)
    if not 1 <= k <= params.MAX_ISOVALUES:
        raise AMRError(f"amr_iso: parameter 'isovalue' needs 1 to {params.MAX_ISOVALUES} values, "
                       f"got {k}")
    read = {p.name: _READERS[p.kind](values, p.name) for p in params.TABLE
            if p.kind in _READERS and p.name not in ("isovalue", "iso_color", "iso_opacity")}
    opt = Options(isovalues=isovalues, iso_colors=_colors(values, k),
                  iso_opacity=_opacities(values, k), band_width=_per_iso(values, "band_width", k),
                  band_peak=_per_iso(values, "band_peak", k),
                  band_support=_supports(values, isovalues),
                  transfer2d_range=_range4(values), given=frozenset(values), **read)
    _check_transfer2d(opt, values)
    if opt.colormap is not None:
        # A bad map is one error before the volume's load, drawn or not (a typo is a typo).
        ColorMap.parse(opt.colormap)
    if opt.color_field is not None and opt.color_field.strip().lower() in NO_COLOR_FIELD:
        # "none" switches the colour field off (-D color_field=none), with its map and range.
        opt.color_field = opt.colormap = opt.color_range = None
    if (opt.color_field is None) != (opt.colormap is None):
        raise AMRError("amr_iso: 'color_field' and 'colormap' go together; give both or neither")
    if opt.layers != "composite" and opt.mode != "surface":
        raise AMRError(f"amr_iso: parameter 'layers' ({opt.layers!r}) picks translucent "
                       f"surfaces' layers; mode {opt.mode!r} composites its band, give mode "
                       "'surface' or leave 'layers' out")
    opt.leaf_cells, opt.max_layers = int(opt.leaf_cells), int(opt.max_layers)
    return opt


def _range4(values):
    v = values.get("transfer2d_range")
    return None if v is None else parse_range(v)


def _check_transfer2d(opt: Options, values) -> None:
    """A 2D transfer function (a table file with its range, or blobs) goes with volume mode,
    a sampling method, one isovalue and no band parameters; the blobs are parsed here."""
    table, blobs = opt.transfer2d is not None, opt.transfer2d_blobs is not None
    if table and blobs:
        raise AMRError("amr_iso: parameters 'transfer2d' and 'transfer2d_blobs' exclude each "
                       "other; give a table file or blobs")
    if table != (opt.transfer2d_range is not None):
        raise AMRError("amr_iso: parameter 'transfer2d_range' (\"v0 v1 g0 g1\") goes with "
                       "'transfer2d' (blobs set their own range); give both or neither")
    if not (table or blobs):
        return
    name = "transfer2d" if table else "transfer2d_blobs"
    if opt.mode != "volume":
        raise AMRError(f"amr_iso: parameter '{name}' needs mode 'volume', got {opt.mode!r}")
    if opt.preintegrated:
        raise AMRError(f"amr_iso: parameter '{name}': pre-integration ('preintegrated') is not "
                       f"supported with a 2D transfer function")
    if len(opt.isovalues) != 1:
        raise AMRError(f"amr_iso: parameter '{name}' replaces the bands: give one isovalue "
                       f"(its crossings are the AOVs), got {len(opt.isovalues)}")
    given = [b for b in ("band_width", "band_support", "band_peak") if b in values]
    if given:
        raise AMRError(f"amr_iso: parameter(s) {', '.join(repr(b) for b in given)} do not "
                       f"apply with '{name}' (the 2D transfer function sets the opacity)")
    if blobs:
        opt.transfer2d_blobs = parse_blobs(opt.transfer2d_blobs)


def _per_iso(values, name, k):
    """A number or one per isovalue (each checked against the table's range)."""
    p = params.BY_NAME[name]
    out = _floats({name: values.get(name, p.default)}, name)
    if len(out) not in (1, k) or not all(p.lo <= x <= p.hi for x in out):
        counts = "1 value" if k == 1 else f"1 or {k} values"
        raise AMRError(f"amr_iso: parameter '{name}' needs {counts} in [{p.lo:g}, {p.hi:g}], "
                       f"got {values.get(name)!r}")
    return out * k if len(out) == 1 else out


def _supports(values, isovalues):
    """``band_support``: one ``lo hi`` pair, or one per isovalue, each around its isovalue."""
    v = values.get("band_support")
    if v is None:
        return None
    groups = v.split(";") if isinstance(v, str) else [v]
    pairs = [_pair({"band_support": g}, "band_support") for g in groups]
    k = len(isovalues)
    if len(pairs) not in (1, k):
        raise AMRError(f"amr_iso: parameter 'band_support' needs 1 or {k} 'lo hi' pairs, "
                       f"got {v!r}")
    pairs = pairs * k if len(pairs) == 1 else pairs
    for (lo, hi), iso in zip(pairs, isovalues):
        if not lo < iso < hi:
            raise AMRError(f"amr_iso: parameter 'band_support' ({lo:g}, {hi:g}) must contain "
                           f"its isovalue {iso:g}")
    return pairs


def _value(values, name):
    return values.get(name, params.default(name))


def _string(values, name):
    v = _value(values, name)
    if v is None and not params.BY_NAME[name].required:
        return None
    if not isinstance(v, str) or not v.strip():
        raise AMRError(f"amr_iso: parameter '{name}' must be a non-empty string, got {v!r}")
    v = v.strip()
    choices = params.BY_NAME[name].choices
    if choices and v not in choices:
        raise AMRError(f"amr_iso: parameter '{name}' must be one of {', '.join(choices)}; "
                       f"got {v!r}")
    return v


def _number(values, name, integer=False):
    p = params.BY_NAME[name]
    v = _value(values, name)
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter '{name}' must be a number, got {v!r}") from None
    if not (p.lo <= x <= p.hi) or math.isnan(x) or (integer and x != int(x)):
        kind = "an integer" if integer else "a number"
        raise AMRError(f"amr_iso: parameter '{name}' must be {kind} in [{p.lo:g}, {p.hi:g}], "
                       f"got {v!r}")
    return x


def boolean(values, name) -> bool:
    """Parameter ``name`` of ``values`` (its default where absent) as the scene reads a
    ``boolean``: True, False, or the strings ``true``/``false``; anything else is refused."""
    v = _value(values, name)
    if isinstance(v, bool):
        return v
    if isinstance(v, str) and v.lower() in ("true", "false"):
        return v.lower() == "true"
    raise AMRError(f"amr_iso: parameter '{name}' must be true or false, got {v!r}")


def _floats(values, name):
    v = values.get(name, params.default(name))
    items = v if isinstance(v, (list, tuple)) else str(v).replace(";", ",").split(",") \
        if isinstance(v, str) else [v]
    try:
        out = [float(x) for x in items]
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter '{name}' must be a number or a comma-separated list "
                       f"of numbers, got {v!r}") from None
    if not out or not all(math.isfinite(x) for x in out):
        raise AMRError(f"amr_iso: parameter '{name}' must hold finite numbers, got {v!r}")
    if any(abs(x) > FLOAT32_MAX for x in out):
        raise AMRError(f"amr_iso: parameter '{name}' must fit in float32 (|x| <= 3.4e38), "
                       f"got {v!r}")
    return out


def _pair(values, name):
    v = values.get(name)
    if v is None:
        return None
    items = v.replace(",", " ").split() if isinstance(v, str) else list(v)
    try:
        lo, hi = (float(x) for x in items)
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter '{name}' must be two numbers 'low high', "
                       f"got {v!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise AMRError(f"amr_iso: parameter '{name}' needs finite low < high, got {v!r}")
    return (lo, hi)


def _opacities(values, k):
    out = _floats({"iso_opacity": values.get("iso_opacity", params.default("iso_opacity"))},
                  "iso_opacity")
    if len(out) == 1:
        out *= k
    if len(out) != k or not all(0.0 < a <= 1.0 for a in out):
        counts = "1 value" if k == 1 else f"1 or {k} values"
        raise AMRError(f"amr_iso: parameter 'iso_opacity' needs {counts} in (0, 1], got "
                       f"{values.get('iso_opacity')!r}")
    return out


def _colors(values, k):
    v = values.get("iso_color", params.default("iso_color"))
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
    except (TypeError, ValueError):
        raise AMRError(f"amr_iso: parameter 'iso_color' must be 'r g b' or 'r g b; r g b; ...', "
                       f"got {v!r}") from None
    if any(len(c) != 3 for c in cols) or len(cols) not in (1, k) or \
            not all(math.isfinite(x) for c in cols for x in c):
        counts = "1 colour" if k == 1 else f"1 or {k} colours"
        raise AMRError(f"amr_iso: parameter 'iso_color' needs {counts} of 3 finite components, "
                       f"got {v!r}")
    return cols * k if len(cols) == 1 else cols


_READERS = {
    "string": _string,
    "float": _number,
    "integer": lambda values, name: _number(values, name, integer=True),
    "boolean": boolean,
    "2 floats": _pair,
}


def warn_outside(prep, isovalues) -> None:
    """A warning (Mitsuba's log) for isovalues outside the field's range: the image would show
    no isosurface, and nothing else would say why."""
    import mitsuba as mi

    lo, hi = prep.value_range(prep.field)
    outside = [v for v in isovalues if not lo <= v <= hi]
    if outside:
        mi.Log(mi.LogLevel.Warn, f"amr_iso: isovalue(s) {', '.join(f'{v:g}' for v in outside)} "
               f"outside the range [{lo:g}, {hi:g}] of field '{prep.field}': no isosurface")
