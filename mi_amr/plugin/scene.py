"""Loading a Mitsuba scene that uses ``amr_iso``: Mitsuba's loader with amr_iso's mistakes
reported as :class:`~mi_amr.AMRError`, and cameras kept as opaque kernel inputs."""

from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi

from mi_amr.errors import AMRError


def load_scene(path, *, integrator=None, pixel_format=None, **params):
    """``mi.load_file`` that reports an amr_iso parameter or data mistake as :class:`AMRError`
    (Mitsuba wraps errors raised while building plugins in a RuntimeError with a traceback).

    ``params`` set the scene's ``<default>`` values (as ``-D``). ``integrator`` (a mapping)
    sets parameters of the ``amr_iso`` integrator that the file may not mention (e.g.
    ``{"aovs": True}``) and ``pixel_format`` the films' format (e.g. ``"rgba"``), without
    touching the file."""
    path = Path(path)
    if not path.is_file():
        raise AMRError(f"{path}: no such scene file")
    values = {k: str(v) for k, v in params.items()}
    try:
        if integrator or pixel_format:
            scene = _load_edited(path, integrator or {}, pixel_format, values)
        else:
            scene = mi.load_file(str(path), **values)
    except RuntimeError as e:
        if _interrupted(e):
            raise KeyboardInterrupt from None
        raise _unwrap(e, path) from None
    _opaque_cameras(scene)
    return scene


def _load_edited(path, integrator: dict, pixel_format, values):
    """The scene file with the amr_iso integrator's and films' settings changed in memory,
    loaded with the file's folder first on the file resolver (relative paths as before)."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(str(path)).getroot()
    except ET.ParseError as e:
        raise AMRError(f"{path}: not a valid scene file ({e})") from None
    node = root.find("integrator[@type='amr_iso']")
    if node is None and integrator:
        raise AMRError(f"{path}: the scene has no amr_iso integrator")
    for name, value in integrator.items():
        for old in node.findall(f"*[@name='{name}']"):
            node.remove(old)
        kind = "boolean" if isinstance(value, bool) else "string"
        text = str(value).lower() if isinstance(value, bool) else str(value)
        ET.SubElement(node, kind, name=name, value=text)
    for film in root.iter("film") if pixel_format else ():
        for old in film.findall("*[@name='pixel_format']"):
            film.remove(old)
        ET.SubElement(film, "string", name="pixel_format", value=pixel_format)
    resolver = mi.file_resolver()
    saved = [str(resolver[i]) for i in range(len(resolver))]
    resolver.prepend(str(path.resolve().parent))
    try:
        return mi.load_string(ET.tostring(root, encoding="unicode"), **values)
    finally:
        resolver.clear()
        for folder in saved:
            resolver.append(folder)


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
