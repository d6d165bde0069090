"""Loading a Mitsuba scene that uses ``amr_iso``: Mitsuba's loader with amr_iso's mistakes
reported as :class:`~mi_amr.AMRError`, and cameras kept as opaque kernel inputs."""

from __future__ import annotations

from pathlib import Path

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
    """Write each camera's ``to_world`` back through ``mi.traverse``: Mitsuba then keeps it as an
    opaque value, so moving the camera later does not recompile the rendering kernel."""
    params = mi.traverse(scene)
    keys = [k[: -len(".film.size")] + ".to_world" for k in params.keys()
            if k.endswith(".film.size")]
    keys = [k for k in keys if k in params]
    for k in keys:
        # The same update a moved camera goes through (a computed transform), so the kernel
        # compiled for the first frame is the one every later camera position reuses.
        params[k] = mi.Transform4f() @ params[k]
    if keys:
        params.update()


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
