"""The scene made for a data file: ``amr_iso`` showing one field's isosurface, a camera that
frames it from a three-quarter view (:mod:`mi_amr.core.framing`: the bounds of the cells the
isosurface passes through, or in volume mode its band within one width of the isovalue, where
the field's values are read; else the data's bounds), one
directional light over the viewer's shoulder plus the integrator's ambient term, and nothing
behind (the film's alpha is 0 there: a PNG shows the page's own background).

The same scene comes as a dict for ``mi.load_dict`` (:meth:`DataScene.as_dict`, which
:func:`scene` returns) and as Mitsuba XML (:meth:`DataScene.xml`, what ``--save-scene``
writes): both give the same numbers to Mitsuba, so both render the same pixels. The XML has
``<default>`` values ``filename``, ``isovalue``, ``color_field`` (``none``: off), ``colormap``,
``spp``, ``resx`` and ``resy``, so ``render -D``, ``--spp``, ``--resolution`` and ``movie``
(which swaps ``filename``) apply to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from mi_amr.core.framing import Framing, frame_box, value_box
from mi_amr.core.suggest import finite_leaf_values, suggest_band_width, suggest_isovalues
from mi_amr.errors import AMRError
from mi_amr.plugin.options import boolean

RESOLUTION = (768, 576)      # pixels (width, height) unless asked otherwise
SPP = 4
ISO_COLOR = "0.78 0.74 0.68"  # linear RGB: a light neutral, lit by the one light
IRRADIANCE = 1.6             # the directional light's irradiance (linear RGB, all channels)
COLORMAP = "viridis"         # the map a colour field gets (-D color_field=NAME turns it on)
# widths of a band each side of its isovalue that the camera frames: where its opacity is at
# least exp(-1/2) of its peak (its support, two widths, takes in a faint haze, which in a field
# with large flat regions, a volume fraction's 0 and 1, would frame them all).
BAND_FRAMED_WIDTHS = 1.0
# The integrator's parameters the XML takes from <default>s (so -D sets them).
DEFAULTS = ("filename", "isovalue", "color_field", "colormap")
XML_DEFAULTS = DEFAULTS + ("spp", "resx", "resy")      # every <default> of the XML


@dataclass
class DataScene:
    """The scene of ``path`` (absolute) showing ``field`` at ``isovalue`` (``picked``: chosen
    from the histogram, with ``suggested`` the other candidates), at ``resolution`` (width,
    height) and ``spp``; ``params`` are further ``amr_iso`` parameters (``band_width`` among
    them where ``band_picked``: volume mode's band, picked from the histogram). ``framed``:
    the box the camera frames (volume world), and what it is (``"isosurface"``, ``"band"``,
    ``"isosurfaces"`` (a sweep's): the cells they pass through; ``"data"``: the data's
    bounds)."""

    path: str
    field: str
    isovalue: float
    picked: bool
    suggested: list
    resolution: tuple
    spp: int
    framing: Framing
    params: dict = dc_field(default_factory=dict)
    band_picked: bool = False
    framed: tuple = ()

    def integrator_values(self) -> dict:
        """The amr_iso parameters except ``to_world`` (Python values, written as typed)."""
        return {"filename": self.path, "field": self.field, "isovalue": repr(self.isovalue),
                "iso_color": ISO_COLOR, "color_field": "none", "colormap": COLORMAP,
                **self.params}

    def as_dict(self) -> dict:
        """The scene for ``mi.load_dict`` (needs a Mitsuba variant)."""
        import mitsuba as mi

        f = self.framing
        look = mi.ScalarTransform4d().look_at(origin=list(f.origin), target=list(f.target),
                                              up=list(f.up))
        integrator = {"type": "amr_iso", **self.integrator_values(),
                      "to_world": _single(mi, mi.ScalarTransform4d(f.to_world.tolist()))}
        sensor = {"type": "perspective", "fov": f.fov_x, "fov_axis": "x",
                  "to_world": _single(mi, look),
                  "sampler": {"type": "independent", "sample_count": self.spp},
                  "film": {"type": "hdrfilm", "width": self.resolution[0],
                           "height": self.resolution[1], "pixel_format": "rgba"}}
        light = {"type": "directional", "direction": list(f.light_direction),
                 "irradiance": {"type": "rgb", "value": IRRADIANCE}}
        return {"type": "scene", "integrator": integrator, "sensor": sensor, "light": light}

    def xml(self) -> str:
        """The scene as Mitsuba XML (see the module docstring)."""
        f = self.framing
        values = self.integrator_values()
        defaults = {k: values.pop(k) for k in DEFAULTS}
        defaults.update(spp=self.spp, resx=self.resolution[0], resy=self.resolution[1])
        how = " (picked from the histogram)" if self.picked else ""
        band = f", band width {self.params['band_width']!r} (picked from the histogram)" \
            if self.band_picked and self.params.get("mode") == "volume" else ""
        framed = {"isosurface": "the isosurface's cells", "band": "the band's cells",
                  "isosurfaces": "the cells of the isovalues swept",
                  "data": "the data's bounds"}.get(self.framed[2] if self.framed else "data")
        lines = ['<scene version="3.0.0">',
                 f"    <!-- Made by mi_amr for {_comment(self.path)}: field {_comment(self.field)}"
                 f", isovalue {self.isovalue!r}{how}{band}; the camera frames {framed}. -->"]
        lines += [f"    <default name={quoteattr(k)} value={quoteattr(str(v))}/>"
                  for k, v in defaults.items()]
        lines += ['', '    <integrator type="amr_iso" id="integrator">']
        lines += [f'        <string name="{k}" value="${k}"/>' for k in DEFAULTS]
        lines += [f"        {_tag(k, v)}" for k, v in values.items()]
        matrix = " ".join(repr(float(x)) for x in f.to_world.ravel())
        lines += ['        <transform name="to_world">', f'            <matrix value="{matrix}"/>',
                  '        </transform>', '    </integrator>', '',
                  '    <sensor type="perspective" id="sensor">',
                  f'        <float name="fov" value="{f.fov_x!r}"/>',
                  '        <string name="fov_axis" value="x"/>',
                  '        <transform name="to_world">',
                  f'            <lookat origin="{_vec(f.origin)}" target="{_vec(f.target)}" '
                  f'up="{_vec(f.up)}"/>', '        </transform>',
                  '        <sampler type="independent">',
                  '            <integer name="sample_count" value="$spp"/>', '        </sampler>',
                  '        <film type="hdrfilm">',
                  '            <integer name="width" value="$resx"/>',
                  '            <integer name="height" value="$resy"/>',
                  '            <string name="pixel_format" value="rgba"/>', '        </film>',
                  '    </sensor>', '', '    <emitter type="directional" id="light">',
                  f'        <vector name="direction" value="{_vec(f.light_direction)}"/>',
                  f'        <rgb name="irradiance" value="{IRRADIANCE!r}"/>', '    </emitter>',
                  '</scene>', '']
        return "\n".join(lines)


def _single(mi, transform):
    """A double-precision transform in single precision, matrix and inverse each rounded, as
    Mitsuba's XML parser makes them (a transform built in single precision inverts in single
    precision: other last bits, other pixels)."""
    import numpy as np

    return mi.ScalarTransform4f(
        mi.ScalarMatrix4f(np.array(transform.matrix, dtype=np.float32)),
        mi.ScalarMatrix4f(np.array(transform.inverse_transpose, dtype=np.float32)))


def _vec(v) -> str:
    return ", ".join(repr(float(x)) for x in v)


def _comment(text: str) -> str:
    return str(text).replace("--", "- -")


def _tag(name: str, value) -> str:
    if isinstance(value, bool):
        return f"<boolean name={quoteattr(name)} value=\"{'true' if value else 'false'}\"/>"
    if isinstance(value, int):
        return f"<integer name={quoteattr(name)} value=\"{value}\"/>"
    if isinstance(value, float):
        return f"<float name={quoteattr(name)} value=\"{value!r}\"/>"
    return f"<string name={quoteattr(name)} value={quoteattr(str(value))}/>"


def data_scene(source, field=None, isovalue=None, *, resolution=RESOLUTION, spp: int = SPP,
               framed_values=None, offer=None, **params) -> DataScene:
    """The scene of the data file (or :class:`~mi_amr.AMRVolume` read from one) ``source``
    showing ``field`` (stored, or derived from the velocity: ``q_criterion``, ``speed``,
    ``vorticity`` / ``vorticity_magnitude``; default: the first stored field) at
    ``isovalue`` (default: picked from the field's histogram,
    :func:`mi_amr.core.suggest.suggest_isovalues`). ``params`` are further ``amr_iso``
    parameters (e.g. ``color_field="speed", colormap="viridis"``); ``allow_nonfinite``, which
    a volume that keeps NaN or Inf values as missing data sets, reads the file so here too.
    Without ``band_width`` or a 2D transfer function, volume mode's band width is picked from
    the histogram about the isovalue (:func:`mi_amr.core.suggest.suggest_band_width`) where
    ``mode="volume"``, or where the isovalue is picked too (so that the viewer's switch to
    volume mode shows a band): the parameter's default is in the units of the sphere wake's
    Q, a band too thin to see in most other fields. ``framed_values``: ``(lo, hi)``, the
    values whose isosurfaces the camera frames together (a movie's isovalue sweep) instead of
    the isovalue's alone, or ``"data"``: the data's bounds (a time series, whose later steps'
    surfaces may lie elsewhere). ``offer``: a callable (as
    :meth:`~mi_amr.kernels.prepared.Preparations.offer`) handed the volume of the field read
    from the file here, ``offer(path, volume, allow_nonfinite)``, so that the scene's load
    need not read it again; not called for a volume given as ``source``."""
    if isovalue is not None:
        isovalue = _finite(isovalue)
    path, volume = _source(source)
    given = volume
    if volume is not None and volume.allow_nonfinite:
        params.setdefault("allow_nonfinite", True)
    width, height = (int(x) for x in resolution)
    if width < 1 or height < 1 or int(spp) < 1:
        raise AMRError(f"resolution and spp must be positive, got {resolution} and {spp}")
    bands_set = any(k in params for k in ("band_width", "transfer2d", "transfer2d_blobs"))
    need_values = isovalue is None or (params.get("mode") == "volume" and not bands_set)
    pick_band = need_values and not bands_set
    field, volume = _field_volume(path, volume, field, need_values=need_values,
                                  allow_nonfinite=boolean(params, "allow_nonfinite"))
    values = finite_leaf_values(volume, field) if need_values else None
    suggested = [] if isovalue is not None else suggest_isovalues(volume, field, values)
    value = isovalue if isovalue is not None else suggested[0]
    if pick_band:
        params["band_width"] = suggest_band_width(values, value)
    lo, hi, what = (*volume.bounds, "data") if framed_values == "data" else \
        _shown_box(volume, field, framed_values or (value, value), params)
    if offer is not None and given is None and field in volume.field_names:
        offer(path, volume.select_fields([field]), boolean(params, "allow_nonfinite"))
    return DataScene(path=path, field=field, isovalue=value, picked=isovalue is None,
                     suggested=suggested, resolution=(width, height), spp=int(spp),
                     framing=frame_box(lo, hi, width / height), params=dict(params),
                     band_picked=pick_band, framed=(lo, hi, what))


def _finite(isovalue) -> float:
    """The isovalue as a float; one error where it is not a finite number."""
    try:
        value = float(isovalue)
    except (TypeError, ValueError):
        value = float("nan")
    if not np.isfinite(value):
        raise AMRError(f"isovalue must be a finite number, got {isovalue!r}")
    return value


def _shown_box(volume, field: str, values: tuple, params: dict) -> tuple:
    """``(lo, hi, what)``: the box the camera frames (see :class:`DataScene`'s ``framed``): the
    cells of the isosurfaces of ``values`` (``(lo, hi)``: one isovalue, or the ends of a
    sweep), or of their bands' :data:`BAND_FRAMED_WIDTHS` beyond them. Where the field's values
    were not read (a derived field at a given isovalue), or for a 2D transfer function or
    bands of their own supports, the data's bounds."""
    span = (float(min(values)), float(max(values)))
    if params.get("mode") == "volume":
        try:
            width = float(params["band_width"])
        except (KeyError, TypeError, ValueError):       # (several bands, a 2D function)
            width = None
        if width is None or any(k in params for k in ("band_offsets", "transfer2d",
                                                      "transfer2d_blobs")):
            span = None
        else:
            span = (span[0] - BAND_FRAMED_WIDTHS * width, span[1] + BAND_FRAMED_WIDTHS * width)
    box = value_box(volume, field, *span) \
        if span is not None and field in volume.field_names else None
    if box is None:
        return (*volume.bounds, "data")
    return (*box, "band" if params.get("mode") == "volume" else
            "isosurface" if values[0] == values[1] else "isosurfaces")


def scene(source, field=None, isovalue=None, **params) -> dict:
    """The scene of :func:`data_scene` as a dict for ``mi.load_dict`` (set a Mitsuba variant
    first). ``resolution`` and ``spp`` are keywords too."""
    import mitsuba as mi

    if mi.variant() is None:
        raise AMRError("mi_amr.scene(): set a Mitsuba variant first (mi.set_variant(...))")
    from mi_amr.plugin.integrator import register

    register()
    return data_scene(source, field, isovalue, **params).as_dict()


def _source(source):
    """``(absolute path, volume or None)`` of a path or a volume read from a file."""
    from mi_amr.core.volume import AMRVolume
    from mi_amr.readers import available_fields

    if isinstance(source, AMRVolume):
        if not source.source or not Path(source.source).exists():
            raise AMRError("a scene reads its data from a file, and this volume has none; "
                           "save it first (volume.save('data.npz')) and pass the path")
        return str(Path(source.source).resolve()), source
    available_fields(source)                 # one clear error for a missing or odd file
    return str(Path(source).resolve()), None


def _field_volume(path: str, volume, field, need_values: bool, allow_nonfinite: bool):
    """``(field name, volume holding it)``; the field is checked against the file (default:
    the first stored field), read with NaN and Inf values as missing data where
    ``allow_nonfinite``."""
    from mi_amr.plugin.datafields import load_with_fields
    from mi_amr.readers import available_fields

    if field is None:
        stored = available_fields(path)
        if not stored:
            raise AMRError(f"{path}: holds no fields")
        field = stored[0]
    if volume is not None and field in volume.field_names:
        return field, volume
    volume, names = load_with_fields(path, [field], derive_them=need_values,
                                     allow_nonfinite=allow_nonfinite)
    return names[0], volume
