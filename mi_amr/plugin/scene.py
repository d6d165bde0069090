"""Loading a Mitsuba scene that uses ``amr_iso``: Mitsuba's loader with amr_iso's mistakes
reported as :class:`~mi_amr.AMRError`, and cameras kept as opaque kernel inputs."""

from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi

from mi_amr.errors import AMRError


def load_scene(path, **params):
    """``mi.load_file`` that reports an amr_iso parameter or data mistake as :class:`AMRError`
    (Mitsuba wraps errors raised while building plugins in a RuntimeError with a traceback)."""
    path = Path(path)
    if not path.is_file():
        raise AMRError(f"{path}: no such scene file")
    try:
        scene = mi.load_file(str(path), **{k: str(v) for k, v in params.items()})
    except RuntimeError as e:
        raise _unwrap(e, path) from None
    _opaque_cameras(scene)
    return scene


def _opaque_cameras(scene) -> None:
    """Write the values a frame is likely to change -- each camera's and emitter's
    ``to_world``, a camera's field of view, an emitter's strength -- back through
    ``mi.traverse`` as new opaque values: Mitsuba traced them as literals at load time, so the
    first change would otherwise compile the rendering kernel again."""
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
