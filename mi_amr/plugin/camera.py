"""The scene's camera as four numbers a person can read -- where it is, what it looks at, which
way is up, and its horizontal field of view -- read from a scene file and written into a loaded
scene through ``mi.traverse``, without compiling a kernel.

Positions are scene world space; ``fov`` is in degrees (Mitsuba's ``x_fov``).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from mi_amr.errors import AMRError


@dataclass(frozen=True)
class Camera:
    origin: tuple
    target: tuple
    up: tuple
    fov: float

    def as_dict(self) -> dict:
        return {"origin": list(self.origin), "target": list(self.target), "up": list(self.up),
                "fov": self.fov}

    @staticmethod
    def from_dict(d: dict) -> "Camera":
        return Camera(tuple(float(x) for x in d["origin"]), tuple(float(x) for x in d["target"]),
                      tuple(float(x) for x in d["up"]), float(d["fov"]))


def sensor_key(params) -> str:
    """The ``mi.traverse`` prefix of the scene's first perspective camera."""
    for k in params.keys():
        if k.endswith(".x_fov"):
            return k[: -len(".x_fov")]
    raise AMRError("the scene has no perspective camera (a sensor with a field of view)")


def set_camera(params, camera: Camera) -> None:
    """Move the scene's camera to ``camera`` (then ``params.update()``). The position and the
    field of view are written together every time: Mitsuba's perspective camera compiles its
    kernel again when one of them changes after the other did. The transform is computed in
    double precision and rounded once, as Mitsuba's scene loader does for a ``<lookat>``, so
    a scene file written with this camera renders the same pixels."""
    key = sensor_key(params)
    params[f"{key}.to_world"] = lookat_as_loaded(camera)
    params[f"{key}.x_fov"] = float(camera.fov)


def lookat_as_loaded(camera: Camera):
    """``camera``'s ``to_world`` as a scene file's ``<lookat>`` gives it (double precision,
    then float32)."""
    m = mi.ScalarTransform4d().look_at(origin=list(camera.origin), target=list(camera.target),
                                       up=list(camera.up)).matrix
    return mi.Transform4f(np.array(m, dtype=np.float64).astype(np.float32))


def _defaults(root, defines: dict) -> dict:
    out = {d.get("name"): d.get("value") for d in root.iter("default")}
    out.update({k: str(v) for k, v in (defines or {}).items()})
    return out


def _vector(text: str, values: dict, what: str) -> tuple:
    text = re.sub(r"\$(\w+)", lambda m: values.get(m.group(1), m.group(0)), text or "")
    try:
        out = tuple(float(x) for x in text.replace(",", " ").split())
    except ValueError:
        raise AMRError(f"camera: cannot read {what} '{text}'") from None
    if len(out) != 3:
        raise AMRError(f"camera: {what} '{text}' needs 3 numbers")
    return out


def scene_camera(path, defines: dict | None = None, scene=None) -> Camera:
    """The camera of the scene file ``path``: its ``<lookat>`` (``$name`` defaults resolved,
    ``defines`` as with ``-D``). When the camera is given as a matrix, its origin and up are
    read from the loaded ``scene`` and the target is the point on its view axis nearest the
    centre of the scene's shapes (:func:`_scene_centre`)."""
    try:
        root = ET.parse(str(path)).getroot()
    except (OSError, ET.ParseError) as e:
        raise AMRError(f"{path}: cannot read the scene file ({e})") from None
    values = _defaults(root, defines)
    sensor = root.find("sensor")
    if sensor is None:
        raise AMRError(f"{path}: the scene has no <sensor>")
    fov = sensor.find("float[@name='fov']")
    fov_value = float(re.sub(r"\$(\w+)", lambda m: values.get(m.group(1), "nan"),
                             fov.get("value"))) if fov is not None else float("nan")
    look = sensor.find("transform[@name='to_world']/lookat")
    if look is not None:
        cam = Camera(_vector(look.get("origin"), values, "origin"),
                     _vector(look.get("target"), values, "target"),
                     _vector(look.get("up", "0 1 0"), values, "up"), fov_value)
    elif scene is not None:
        cam = _camera_of(scene)
    else:
        raise AMRError(f"{path}: the camera has no <lookat>; load the scene to read it")
    if not math.isfinite(cam.fov):
        cam = Camera(cam.origin, cam.target, cam.up, _camera_of(scene).fov if scene else 39.3)
    return cam


def _camera_of(scene) -> Camera:
    """The camera of a loaded scene (see :func:`scene_camera`)."""
    params = mi.traverse(scene)
    key = sensor_key(params)
    m = np.array(params[f"{key}.to_world"].matrix, dtype=np.float64).reshape(4, 4)
    origin, forward, up = m[:3, 3], m[:3, 2], m[:3, 1]
    centre = _scene_centre(scene)
    reach = 1.0 if centre is None else max(float(np.dot(centre - origin, forward)), 1e-3)
    return Camera(tuple(origin), tuple(origin + reach * forward), tuple(up),
                  float(np.array(params[f"{key}.x_fov"]).ravel()[0]))


def _scene_centre(scene):
    """The centre (scene space) of the scene's shapes' bounding box; of the ``amr_iso``
    volume's bounds placed by its ``to_world`` where the scene has no shape (its bounding box
    is empty then); None where it has neither."""
    bbox = scene.bbox()
    lo, hi = (np.array(b, dtype=np.float64).ravel() for b in (bbox.min, bbox.max))
    if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi):
        return 0.5 * (lo + hi)
    integ = scene.integrator()
    prep, frame = getattr(integ, "prep", None), getattr(integ, "frame", None)
    if prep is None or frame is None:
        return None
    lo, hi = prep.volume.bounds
    return (frame.host @ np.append(0.5 * (np.asarray(lo) + np.asarray(hi)), 1.0))[:3]
