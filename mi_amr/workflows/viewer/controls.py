"""The page's requests turned into new :class:`~mi_amr.workflows.viewer.state.ViewState`
values, every value checked here with a message the page shows (the server keeps serving).

Requests are JSON objects: ``{"op": "set", "name": NAME, "value": V[, "index": I]}`` for
one control, ``{"op": "camera", "action": "orbit"|"pan"|"zoom"|"reset", ...}``, ``add_isovalue``,
``remove_isovalue`` and ``reset_color_range``. Nothing in a request is evaluated: names are
looked up in :data:`SETTERS`, values are parsed as numbers, choices or colours.

Camera moves are in scene world space; ``dx``, ``dy`` are drags in image widths.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from mi_amr import params
from mi_amr.errors import AMRError
from mi_amr.plugin.camera import Camera

MAX_SPP = 1024
ISO_PALETTE = ((0.8, 0.8, 0.8), (0.9, 0.35, 0.2), (0.2, 0.5, 0.9), (0.3, 0.8, 0.3),
               (0.9, 0.8, 0.2), (0.7, 0.3, 0.8), (0.2, 0.8, 0.8), (0.9, 0.5, 0.7))


@dataclass
class Context:
    """What the checks need to know about the scene on screen."""

    value_range: tuple          # the contoured field's (lo, hi)
    color_data_range: tuple     # the colour field's (lo, hi)
    fields: tuple               # fields the data file holds or can derive
    home: Camera                # the scene file's camera ("reset")
    up: tuple                   # the scene's up (the light's elevation is measured from it)
    resolution: tuple           # the view's (width, height)
    plane: tuple = (0.0, 1.0, 0.0, 1.0)     # a new 2D transfer function's (v0, v1, g0, g1)


# ---------------------------------------------------------------------- values

NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d{1,4})?")
HEX_COLOR = re.compile(r"#[0-9a-fA-F]{6}")
MAX_COLOR = 1e3                 # a linear colour component at most (an emitted glow, not HDR)
SHOWN_CHARS = 40                # of a refused value, in its message


def shown(value) -> str:
    """``value`` for a message: its ``repr``, cut to :data:`SHOWN_CHARS` characters (a refused
    request is never echoed whole: a client could make every reply a megabyte)."""
    if isinstance(value, (str, bytes)) and len(value) > SHOWN_CHARS:
        return repr(value[:SHOWN_CHARS]) + f"... ({len(value)} characters)"
    if isinstance(value, (list, tuple, dict)) and len(value) > 8:
        return f"a {type(value).__name__} of {len(value)} items"
    text = repr(value)
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS] + "..."


def number(value, name: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    """``value`` (a JSON number, or decimal text typed on the page: digits, a point, an
    exponent; no ``_``, ``nan`` or ``inf``) as a finite float in ``[lo, hi]``."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise AMRError(f"{name}: expected a number, got {shown(value)}")
    if isinstance(value, str):
        text = value.strip()
        if len(text) > SHOWN_CHARS or not NUMBER.fullmatch(text):
            raise AMRError(f"{name}: {shown(value)} is not a number")
        value = text
    try:
        x = float(value)
    except (OverflowError, ValueError):
        raise AMRError(f"{name}: {shown(value)} is not a number") from None
    if not math.isfinite(x):
        raise AMRError(f"{name}: {shown(value)} is not a finite number")
    if not lo <= x <= hi:
        raise AMRError(f"{name}: {x:g} is outside [{lo:g}, {hi:g}]")
    return x


def integer(value, name: str, lo: int, hi: int) -> int:
    """``value`` as a whole number in ``[lo, hi]`` (``"4"``, ``4`` or ``4.0``; not ``4.5``)."""
    x = number(value, name, lo, hi)
    if x != int(x):
        raise AMRError(f"{name}: expected a whole number, got {x:g}")
    return int(x)


def single(value, name: str, lo: float = -math.inf, hi: float = math.inf, *,
           above: bool = False) -> float:
    """``number(value, ...)`` as the kernels will hold it, rounded to float32 and checked
    after the rounding (``above``: strictly above ``lo``): what passes here, the integrator
    accepts."""
    x = number(value, name)
    with np.errstate(over="ignore"):
        x32 = float(np.float32(x))
    if not math.isfinite(x32) or not lo <= x32 <= hi or (above and x32 <= lo):
        rounded = f" as a 32-bit float ({x32:.9g})" if x32 != x else ""
        raise AMRError(f"{name}: {x:g} is outside {'(' if above else '['}{lo:g}, {hi:g}]"
                       f"{rounded}")
    return x32


def table_number(value, name: str, param: str) -> float:
    """``value`` checked against the integrator's parameter table (:mod:`mi_amr.params`)
    after rounding to float32, as the integrator checks it."""
    lo, hi = params.float32_bounds(param)
    return single(value, name, lo, hi)


def choice(value, name: str, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        raise AMRError(f"{name}: {shown(value)} is not one of {', '.join(choices)}")
    return value


def text(value, name: str, limit: int = 4096) -> str:
    """``value`` as one line of text (a name, a colour map), stripped."""
    if not isinstance(value, str):
        raise AMRError(f"{name}: expected text, got {shown(value)}")
    if len(value) > limit or any(ord(c) < 32 for c in value):
        raise AMRError(f"{name}: {shown(value)} is not one line of at most {limit} characters")
    return value.strip()


def color(value, name: str) -> tuple:
    """``"#rrggbb"`` (sRGB, as a colour picker gives it) or three linear numbers in
    ``[0, MAX_COLOR]``, as linear RGB."""
    if isinstance(value, str) and HEX_COLOR.fullmatch(value):
        return tuple(srgb_to_linear(int(value[i:i + 2], 16) / 255.0) for i in (1, 3, 5))
    if isinstance(value, (list, tuple)) and len(value) == 3:
        return tuple(single(c, name, 0.0, MAX_COLOR) for c in value)
    raise AMRError(f"{name}: {shown(value)} is not a colour (#rrggbb or three numbers)")


def srgb_to_linear(c: float) -> float:
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def linear_to_hex(rgb) -> str:
    def srgb(c):
        c = min(max(float(c), 0.0), 1.0)
        return 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1 / 2.4) - 0.055
    return "#" + "".join(f"{round(255 * srgb(c)):02x}" for c in rgb)


# ---------------------------------------------------------------------- one control each

def _index(state, msg) -> int:
    i = msg.get("index", 0)
    if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < len(state.isovalues):
        raise AMRError(f"isovalue number {shown(i)} does not exist (there are "
                       f"{len(state.isovalues)})")
    return i


def _put(values: tuple, i: int, v) -> tuple:
    return values[:i] + (v,) + values[i + 1:]


def _set_isovalue(state, msg, ctx):
    lo, hi = ctx.value_range
    v = number(msg.get("value"), "isovalue", lo, hi)
    return state.replace(isovalues=_put(state.isovalues, _index(state, msg), v))


def _set_iso_color(state, msg, ctx):
    c = color(msg.get("value"), "isovalue colour")
    return state.replace(iso_colors=_put(state.iso_colors, _index(state, msg), c))


def _set_iso_opacity(state, msg, ctx):
    a = number(msg.get("value"), "opacity", 0.0, 1.0)
    if a <= 0:
        raise AMRError("opacity: must be above 0 (remove the isovalue to hide it)")
    a = single(a, "opacity", 0.0, 1.0, above=True)
    return state.replace(iso_opacity=_put(state.iso_opacity, _index(state, msg), a))


def _set_band_width(state, msg, ctx):
    lo, hi = ctx.value_range
    w = number(msg.get("value"), "band width", 0.0, max(hi - lo, 1e-30))
    if w <= 0:
        raise AMRError("band width: must be above 0")
    w = single(w, "band width", 0.0, max(hi - lo, 1e-30), above=True)
    k = len(state.isovalues)
    return state.replace(band_width=(w,) * k, band_offsets=((-2.0 * w, 2.0 * w),) * k)


def _set_mode(state, msg, ctx):
    return state.replace(mode=choice(msg.get("value"), "mode", params.MODES))


def _set_field(state, msg, ctx):
    name = text(msg.get("value", ""), "field", 256)
    if name not in ctx.fields:
        raise AMRError(f"field: {shown(name)} does not exist; this data has "
                       f"{', '.join(ctx.fields)}")
    return state.replace(field=name)


def _set_color_field(state, msg, ctx):
    name = msg.get("value")
    if name in (None, "", "none"):
        return state.replace(color_field=None, colormap=None, color_range=None)
    name = text(name, "colour field", 256)
    if name not in ctx.fields:
        raise AMRError(f"colour field: {shown(name)} does not exist; this data has "
                       f"{', '.join(ctx.fields)}")
    return state.replace(color_field=name, colormap=state.colormap or "viridis",
                         color_range=state.color_range or tuple(ctx.color_data_range))


def _set_colormap(state, msg, ctx):
    from mi_amr.kernels.colormap import ColorMap

    if state.colormap is None:
        raise AMRError("colour map: choose a colour field first")
    spec = text(msg.get("value", ""), "colour map", 16384)
    if not spec:
        raise AMRError("colour map: give a matplotlib name (viridis) or 'value: r g b' pairs")
    cmap = ColorMap.parse(spec, ctx.color_data_range)       # raises AMRError with the reason
    if not np.all((cmap.colors >= 0) & (cmap.colors <= MAX_COLOR)):
        raise AMRError(f"colour map: colours must lie in [0, {MAX_COLOR:g}] (linear RGB)")
    lo, hi = (float(v) for v in np.float32(cmap.value_range))
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise AMRError("colour map: the pairs' values must be distinct 32-bit floats")
    return state.replace(colormap=spec)


def _set_color_range(state, msg, ctx):
    if state.colormap is None:
        raise AMRError("colour range: choose a colour field first")
    value = msg.get("value")
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise AMRError("colour range: expected two numbers, low and high")
    lo, hi = (single(v, "colour range") for v in value)
    if not lo < hi:
        raise AMRError(f"colour range: low ({lo:g}) must be below high ({hi:g})")
    return state.replace(color_range=(lo, hi))


def _set_light(state, msg, ctx, part: str):
    if state.light_direction is None:
        raise AMRError("light: the scene has no directional light to steer")
    az, el = light_angles(state.light_direction, ctx.up)
    if part == "strength":
        s = number(msg.get("value"), "light strength", 0.0, 1e6)
        return state.replace(light_irradiance=(s, s, s))
    if part == "azimuth":
        az = number(msg.get("value"), "light azimuth", -360.0, 360.0)
    else:
        el = number(msg.get("value"), "light elevation", -90.0, 90.0)
    return state.replace(light_direction=light_direction(az, el, ctx.up))


def _simple(field, parse):
    def setter(state, msg, ctx):
        return state.replace(**{field: parse(msg.get("value"))})
    return setter


def _flag(value) -> bool:
    if not isinstance(value, bool):
        raise AMRError(f"expected true or false, got {shown(value)}")
    return value


SETTERS = {
    "isovalue": _set_isovalue, "iso_color": _set_iso_color, "iso_opacity": _set_iso_opacity,
    "step_scale": _simple("step_scale", lambda v: table_number(v, "step scale", "step_scale")),
    "shadows": _simple("shadows", _flag),
    "method": _simple("method", lambda v: choice(v, "method", params.METHODS)),
    "reconstruction": _simple("reconstruction",
                              lambda v: choice(v, "reconstruction", params.RECONSTRUCTIONS)),
    "layers": _simple("layers", lambda v: choice(v, "layers", params.LAYER_MODES)),
    "mode": _set_mode, "band_width": _set_band_width, "field": _set_field,
    "color_field": _set_color_field, "colormap": _set_colormap, "color_range": _set_color_range,
    "light_azimuth": lambda s, m, c: _set_light(s, m, c, "azimuth"),
    "light_elevation": lambda s, m, c: _set_light(s, m, c, "elevation"),
    "light_strength": lambda s, m, c: _set_light(s, m, c, "strength"),
    "spp": _simple("spp", lambda v: integer(v, "samples per pixel", 1, MAX_SPP)),
}


# ---------------------------------------------------------------------- requests

def change(state, msg: dict, ctx: Context):
    """The state after the request ``msg`` (an :class:`AMRError` says why it is refused)."""
    op = msg.get("op")
    if op == "set":
        name = msg.get("name")
        if not isinstance(name, str) or name not in SETTERS:
            raise AMRError(f"there is no control {shown(name)}")
        return SETTERS[name](state, msg, ctx)
    if op == "camera":
        return state.replace(camera=move_camera(state.camera, msg, ctx))
    if op == "add_isovalue":
        return _add_isovalue(state, ctx)
    if op == "remove_isovalue":
        if len(state.isovalues) == 1:
            raise AMRError("the last isovalue cannot be removed")
        i = _index(state, msg)
        per_iso = ("isovalues", "iso_colors", "iso_opacity", "band_width", "band_offsets",
                   "band_peak")
        return state.replace(**{n: getattr(state, n)[:i] + getattr(state, n)[i + 1:]
                                for n in per_iso})
    if op == "reset_color_range":
        if state.colormap is None:
            raise AMRError("colour range: choose a colour field first")
        return state.replace(color_range=tuple(ctx.color_data_range))
    raise AMRError(f"unknown request {shown(op)}")


def _add_isovalue(state, ctx):
    k = len(state.isovalues)
    if k >= params.MAX_ISOVALUES:
        raise AMRError(f"at most {params.MAX_ISOVALUES} isovalues")
    lo, hi = ctx.value_range
    v = min(hi, state.isovalues[-1] + 0.1 * (hi - lo))
    return state.replace(isovalues=state.isovalues + (v,),
                         iso_colors=state.iso_colors + (ISO_PALETTE[k % len(ISO_PALETTE)],),
                         iso_opacity=state.iso_opacity + (1.0,),
                         band_width=state.band_width + state.band_width[-1:],
                         band_offsets=state.band_offsets + state.band_offsets[-1:],
                         band_peak=state.band_peak + state.band_peak[-1:])


def move_camera(cam: Camera, msg: dict, ctx: Context) -> Camera:
    """Orbit about the target (``dx``: about the scene's up, ``dy``: up and down, half a
    turn per image width), pan in the image plane, zoom towards the target
    (``amount``: the distance is multiplied by ``exp(amount)``), or reset."""
    action = msg.get("action")
    if action == "reset":
        return ctx.home
    origin, target = np.array(cam.origin), np.array(cam.target)
    up = np.array(cam.up) / np.linalg.norm(cam.up)
    offset = origin - target
    dist = float(np.linalg.norm(offset))
    if action == "zoom":
        f = math.exp(number(msg.get("amount"), "zoom", -5.0, 5.0))
        return _camera(target + offset * f, cam.target, cam)
    dx, dy = (number(msg.get(k, 0.0), k, -10.0, 10.0) for k in ("dx", "dy"))
    forward = -offset / dist
    right = np.cross(forward, up)
    right /= max(np.linalg.norm(right), 1e-12)
    if action == "pan":
        screen_up = np.cross(right, forward)
        shift = (-dx * right + dy * screen_up) * 2.0 * dist * math.tan(math.radians(cam.fov) / 2)
        return _camera(origin + shift, target + shift, cam)
    if action != "orbit":
        raise AMRError(f"camera: unknown action {shown(action)}")
    offset = _rotate(offset, up, -dx * math.pi)
    # Tilt about the right axis, stopping short of the poles so "up" stays meaningful.
    polar = math.acos(np.clip(np.dot(offset / dist, up), -1.0, 1.0))
    # (A positive turn about up x offset moves the camera towards -up: dragging down raises it.)
    tilt = np.clip(-dy * math.pi, math.radians(2) - polar, math.radians(178) - polar)
    offset = _rotate(offset, np.cross(up, offset / dist), tilt)
    return _camera(target + offset, cam.target, cam)


def _camera(origin, target, cam: Camera) -> Camera:
    """``cam`` moved to ``origin`` and ``target`` (as plain floats, which Mitsuba takes)."""
    return Camera(tuple(float(x) for x in origin), tuple(float(x) for x in target), cam.up,
                  cam.fov)


def _rotate(v, axis, angle):
    """Rodrigues' rotation of ``v`` about the unit ``axis`` by ``angle`` radians."""
    axis = axis / max(np.linalg.norm(axis), 1e-12)
    return (v * math.cos(angle) + np.cross(axis, v) * math.sin(angle) +
            axis * np.dot(axis, v) * (1 - math.cos(angle)))


def _basis(up):
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - up * np.dot(a, up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1), up


def light_angles(direction, up) -> tuple:
    """``(azimuth, elevation)`` in degrees of where the light comes from (``-direction``),
    elevation above the plane normal to ``up``."""
    e1, e2, u = _basis(up)
    s = -np.asarray(direction, dtype=np.float64)
    s /= np.linalg.norm(s)
    el = math.degrees(math.asin(float(np.clip(np.dot(s, u), -1.0, 1.0))))
    az = math.degrees(math.atan2(float(np.dot(s, e2)), float(np.dot(s, e1))))
    return az, el


def light_direction(azimuth: float, elevation: float, up) -> tuple:
    """The unit direction light travels along, coming from ``(azimuth, elevation)``."""
    e1, e2, u = _basis(up)
    a, e = math.radians(azimuth), math.radians(elevation)
    s = math.cos(e) * (math.cos(a) * e1 + math.sin(a) * e2) + math.sin(e) * u
    return tuple(float(x) for x in -s)
