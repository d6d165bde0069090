"""Loading a Mitsuba scene that uses ``amr_iso``: Mitsuba's loader with amr_iso's mistakes
reported as :class:`~mi_amr.AMRError`, and cameras kept as opaque kernel inputs."""

from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi

from mi_amr.errors import AMRError


def use_variant(variant: str) -> None:
    """``mi.set_variant(variant)``, or one :class:`AMRError` when this Mitsuba lacks it or this
    machine cannot run it (a CUDA variant without a CUDA device or driver)."""
    if variant not in mi.variants():
        raise AMRError(f"variant '{variant}' is not available; choose from {mi.variants()}")
    try:
        mi.set_variant(variant)
    except (ImportError, RuntimeError) as e:
        first = (str(e).strip().splitlines() or ["unknown error"])[0]
        raise AMRError(f"variant '{variant}' cannot run on this machine ({first}); try "
                       f"--variant llvm_ad_rgb") from None


def load_scene(path, *, integrator=None, pixel_format=None, film_size=None,
               sample_count=None, **params):
    """``mi.load_file`` that reports an amr_iso parameter or data mistake as :class:`AMRError`
    (Mitsuba wraps errors raised while building plugins in a RuntimeError with a traceback).

    ``params`` set the scene's ``<default>`` values (as ``-D``). ``integrator`` (a mapping)
    sets parameters of the ``amr_iso`` integrator that the file may not mention (e.g.
    ``{"aovs": True}``), ``pixel_format`` the films' format (e.g. ``"rgba"``), ``film_size``
    ``(W, H)`` the films' size in pixels and ``sample_count`` the samplers' samples per pixel,
    without touching the file and whether or not it has ``<default>``s for them. A sensor
    without a ``<film>`` (or ``<sampler>``) that these change gets Mitsuba's default one
    (``hdrfilm``, ``independent``). A scene without a sensor, or with a film of no pixels, is
    refused."""
    path = Path(path)
    if not path.is_file():
        raise AMRError(f"{path}: no such scene file")
    values = {k: str(v) for k, v in params.items()}
    edits = {"pixel_format": pixel_format, "film_size": film_size,
             "sample_count": sample_count}
    try:
        if integrator or any(v is not None for v in edits.values()):
            scene = _load_edited(path, integrator or {}, edits, values)
        else:
            scene = mi.load_file(str(path), **values)
    except RuntimeError as e:
        if _interrupted(e):
            raise KeyboardInterrupt from None
        raise _unwrap(e, path) from None
    _check_sensors(scene, path)
    _opaque_cameras(scene)
    return scene


def load_dict(scene: dict):
    """``mi.load_dict`` that reports an amr_iso mistake as :class:`AMRError` and keeps the
    cameras opaque, as :func:`load_scene` does (so a dict and its XML render the same
    pixels)."""
    try:
        loaded = mi.load_dict(scene)
    except RuntimeError as e:
        raise _unwrap(e, "the scene") from None
    _opaque_cameras(loaded)
    return loaded


def _check_sensors(scene, path) -> None:
    """Refuse a scene that has nothing to render from, or a film of no pixels."""
    if not scene.sensors():
        raise AMRError(f"{path}: the scene has no <sensor>; add one, e.g. <sensor "
                       f"type=\"perspective\"> with a <transform name=\"to_world\"><lookat "
                       f".../></transform> and a <film type=\"hdrfilm\">")
    for sensor in scene.sensors():
        w, h = (int(x) for x in sensor.film().size())
        if w < 1 or h < 1:
            raise AMRError(f"{path}: the film is {w}x{h} pixels; its width and height (the "
                           f"'resx'/'resy' defaults, or --resolution) must be >= 1")


def _load_edited(path, integrator: dict, edits: dict, values):
    """The scene file with the amr_iso integrator's, films' and samplers' settings changed in
    memory (``edits``: see :func:`load_scene`), loaded with the file's folder first on the file
    resolver (relative paths as before)."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(str(path)).getroot()
    except ET.ParseError as e:
        raise AMRError(f"{path}: not a valid scene file ({e})") from None
    node = root.find("integrator[@type='amr_iso']")
    if node is None and integrator:
        raise AMRError(f"{path}: the scene has no amr_iso integrator")
    for name, value in integrator.items():
        _set(node, "boolean" if isinstance(value, bool) else "string", name,
             str(value).lower() if isinstance(value, bool) else str(value))
    _edit_sensors(root, edits)
    resolver = mi.file_resolver()
    saved = [str(resolver[i]) for i in range(len(resolver))]
    resolver.prepend(str(path.resolve().parent))
    try:
        return mi.load_string(ET.tostring(root, encoding="unicode"), **values)
    finally:
        resolver.clear()
        for folder in saved:
            resolver.append(folder)


def _set(node, kind: str, name: str, value: str) -> None:
    """Give the XML element ``node`` the one property ``<kind name=name value=value/>``."""
    import xml.etree.ElementTree as ET

    for old in node.findall(f"*[@name='{name}']"):
        node.remove(old)
    ET.SubElement(node, kind, name=name, value=value)


def _edit_sensors(root, edits: dict) -> None:
    """Apply ``pixel_format``, ``film_size`` and ``sample_count`` of ``edits`` (when not None)
    to every sensor's film and sampler, adding Mitsuba's defaults where the sensor has none (so
    the film's format is the one asked for, not the default film's RGB)."""
    import xml.etree.ElementTree as ET

    film_edits = edits["pixel_format"] is not None or edits["film_size"] is not None
    for sensor in root.iter("sensor"):
        film = sensor.find("film")
        if film is None and film_edits:
            film = ET.SubElement(sensor, "film", type="hdrfilm")
        if edits["pixel_format"] is not None:
            _set(film, "string", "pixel_format", edits["pixel_format"])
        if edits["film_size"] is not None:
            _set(film, "integer", "width", str(int(edits["film_size"][0])))
            _set(film, "integer", "height", str(int(edits["film_size"][1])))
        if edits["sample_count"] is not None:
            sampler = sensor.find("sampler")
            if sampler is None:
                sampler = ET.SubElement(sensor, "sampler", type="independent")
            _set(sampler, "integer", "sample_count", str(int(edits["sample_count"])))


def _opaque_cameras(scene) -> None:
    """Write the values a frame is likely to change -- each camera's and emitter's
    ``to_world``, a camera's field of view, an emitter's strength -- back through
    ``mi.traverse`` as new opaque values: Mitsuba traced them as literals at load time, so the
    first change would otherwise compile the rendering kernel again.

    Mitsuba's perspective camera has two kernels of its own: one after an update that changed
    its field of view, one after an update of its ``to_world`` alone (each compiled once, on
    first use). The camera and field of view are written here together, as
    :func:`mi_amr.plugin.camera.set_camera` always writes them, so moving the camera that way
    never compiles; moving it by ``to_world`` alone compiles once. Scalar variants compile
    nothing: there it does nothing."""
    if not dr.is_jit_v(mi.Float):
        return
    params = mi.traverse(scene)
    prefixes = [s.id() for s in scene.sensors()] + [e.id() for e in scene.emitters()]
    suffixes = (".to_world", ".x_fov", ".irradiance.value", ".radiance.value",
                ".intensity.value")
    keys = [p + s for p in prefixes for s in suffixes if p + s in params]
    for k in keys:
        value = params[k]
        if isinstance(value, mi.Transform4f):
            # The same update a moved camera goes through (a computed transform).
            params[k] = mi.Transform4f() @ value
        elif k.endswith(".x_fov"):
            # Assigned as a number, as a user would: Mitsuba makes the camera's derived values
            # opaque from then on.
            params[k] = float(value.numpy()[0])
        else:
            params[k] = _fresh(value)
    if keys:
        params.update()


def _fresh(value):
    """A new evaluated copy of a Mitsuba float or colour (from aligned host memory)."""
    import numpy as np

    from mi_amr.kernels.device import device_array

    if dr.depth_v(value) > 1:
        return type(value)(*(device_array(mi.Float, c.numpy(), np.float32) for c in value))
    return device_array(type(value), value.numpy(), np.float32)


def _interrupted(error: RuntimeError) -> bool:
    """Ctrl-C while a plugin was being built: Mitsuba wraps the KeyboardInterrupt raised in
    amr_iso's constructor (its snapshot write cleaned up after itself) in a RuntimeError."""
    lines = [l.strip() for l in str(error).strip().splitlines() if l.strip()]
    return bool(lines) and lines[-1].split(":")[0] == "KeyboardInterrupt"


def _unwrap(error: RuntimeError, path) -> AMRError:
    text = str(error)
    marker = "AMRError: "
    if marker in text:
        return AMRError(text[text.rindex(marker) + len(marker):].strip())
    lines = [l for l in text.strip().splitlines() if l.strip()]
    first = lines[0] if lines else "unknown error"
    # A Python exception inside a plugin ends with "Type: message"; keep that too.
    cause = lines[-1].strip() if len(lines) > 1 else ""
    return AMRError(f"{path}: Mitsuba could not load the scene: {first}" +
                    (f" ... {cause}" if cause and cause != first else ""))


def resolve_data_file(filename: str) -> str:
    """``filename`` resolved by Mitsuba's file resolver (relative to the scene file)."""
    resolved = Path(str(mi.file_resolver().resolve(filename)))
    if not resolved.exists():
        raise AMRError(f"amr_iso: parameter 'filename': {filename} not found (looked for "
                       f"{resolved}); the scenes' data files are made by 'make demo' or "
                       f"'python -m mi_amr data'")
    return str(resolved)
