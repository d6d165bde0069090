"""What each frame of a movie shows: a :class:`FrameSpec` per frame (its data file, camera,
first isovalue and colour range), planned from a time series, an orbit, an isovalue sweep or a
keyframe file. NumPy and the standard library only: specs travel to Dask workers as plain dicts.

Keyframe files (UTF-8 TOML or JSON) list keyframes with a ``frame`` number (increasing, 0 to
2^32 - 1: a frame's number is its sampler's 32-bit seed) and any of ``origin``, ``target``,
``up`` (3 numbers, scene world space; ``up`` not zero), ``fov`` (degrees, between 0 and 180),
``isovalue``, ``color_range`` (2 numbers, low < high) and ``step`` (the time step: an index into
``--files``, from 0), every number finite within float32::

    [[keyframe]]
    frame = 0
    origin = [-2.6, -6.2, 3.4]
    target = [2.2, 0.0, -0.2]
    isovalue = 0.05

    [[keyframe]]
    frame = 48
    origin = [4.0, -6.0, 2.0]
    isovalue = 0.08
    step = 3

(JSON: ``{"keyframe": [{...}, ...]}`` or a plain list.) Between keyframes the camera's origin
and target follow Catmull-Rom curves through the keyframes' values (a smooth path), ``up``,
``fov`` and the scalars go linearly; before the first and after the last keyframe values hold.
A value no keyframe gives is the scene's own. ``step`` goes linearly too, to the nearest step:
keyframes with steps replay a path through time (and need ``--files``), without them the files
are spread evenly over the frames.
"""

from __future__ import annotations

import glob
import json
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from mi_amr.errors import AMRError

KEYFRAME_KEYS = ("frame", "origin", "target", "up", "fov", "isovalue", "color_range", "step")
VECTORS = ("origin", "target", "up")
# A frame's number is its sampler's seed, a 32-bit unsigned integer: frames 0 .. 2^32 - 1.
MAX_FRAMES = 2 ** 32
# Isovalues and colour ranges reach the kernels as float32.
FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class FrameSpec:
    """One frame: ``index`` (0-based), ``file`` (data file; None: the scene's own), ``camera``
    (``{"origin", "target", "up", "fov"}``; None: the scene's), ``isovalue`` (the first
    isovalue; None: the scene's) and ``color_range`` (``(lo, hi)``; None: the scene's)."""

    index: int
    file: Optional[str] = None
    camera: Optional[dict] = None
    isovalue: Optional[float] = None
    color_range: Optional[tuple] = None

    def as_dict(self) -> dict:
        return {"index": self.index, "file": self.file, "camera": self.camera,
                "isovalue": self.isovalue,
                "color_range": None if self.color_range is None else list(self.color_range)}

    @staticmethod
    def from_dict(d: dict) -> "FrameSpec":
        rng = d.get("color_range")
        return FrameSpec(index=int(d["index"]), file=d.get("file"), camera=d.get("camera"),
                         isovalue=d.get("isovalue"),
                         color_range=None if rng is None else tuple(float(x) for x in rng))


# ---------------------------------------------------------------------- files

def natural_key(path) -> list:
    """Sort key putting ``plt9`` before ``plt10`` (digit runs compare as numbers)."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", str(path))]


def expand_files(spec) -> list:
    """The time series named by ``spec``: a glob pattern, a comma-separated list, or a list of
    paths (each may be a glob), in natural order. Raises :class:`AMRError` when nothing
    matches or a listed file is missing."""
    items = spec if isinstance(spec, (list, tuple)) else [s for s in str(spec).split(",") if s]
    out = []
    for item in items:
        item = os.path.expanduser(str(item).strip())
        if glob.has_magic(item):
            found = glob.glob(item)
            if not found:
                raise AMRError(f"--files: '{item}' matches no file")
            out += found
        elif os.path.exists(item):
            out.append(item)
        else:
            raise AMRError(f"--files: {item}: no such file or folder")
    if not out:
        raise AMRError("--files: no files given")
    return sorted(dict.fromkeys(out), key=natural_key)


# ---------------------------------------------------------------------- paths and sweeps

def orbit(camera: dict, degrees: float, count: int) -> list:
    """``count`` cameras turning ``camera`` about its target, on its up axis, ``degrees`` in
    all: frame ``i`` is turned by ``degrees * i / count`` (a full turn loops without a repeated
    frame)."""
    return [orbit_camera(camera, degrees, i, count) for i in range(count)]


def orbit_camera(camera: dict, degrees: float, i: int, count: int) -> dict:
    """Frame ``i``'s camera of :func:`orbit` (computed alone, for planning lazily)."""
    origin, target = np.asarray(camera["origin"], float), np.asarray(camera["target"], float)
    axis = np.asarray(camera["up"], float)
    axis = axis / np.linalg.norm(axis)
    a = math.radians(degrees * i / count)
    v = origin - target
    # Rodrigues' rotation of v about axis.
    v = (v * math.cos(a) + np.cross(axis, v) * math.sin(a) +
         axis * np.dot(axis, v) * (1 - math.cos(a)))
    return dict(camera, origin=[float(x) for x in target + v])


def sweep(spec: str, count: int) -> list:
    """``count`` values from ``"START:STOP"`` (both ends included), evenly or, with a ``log:``
    prefix, evenly in the logarithm (both ends must then have the same sign)."""
    ends = parse_sweep(spec)
    return [sweep_value(ends, i, count) for i in range(count)]


def parse_sweep(spec: str) -> tuple:
    """``(start, stop, log)`` of an ``--isovalues`` value, checked: finite numbers that fit
    float32, of one non-zero sign for a log sweep."""
    text = str(spec).strip()
    log = text.startswith("log:")
    try:
        start, stop = (float(x) for x in text[4 if log else 0:].split(":"))
    except ValueError:
        raise AMRError(f"--isovalues: expected START:STOP or log:START:STOP, got '{spec}'") \
            from None
    if not all(math.isfinite(x) and abs(x) <= FLOAT32_MAX for x in (start, stop)):
        raise AMRError(f"--isovalues: '{spec}' needs finite numbers (within float32)")
    if log and start * stop <= 0:
        raise AMRError(f"--isovalues: a log sweep needs two non-zero ends of one sign, got "
                       f"'{spec}'")
    return start, stop, log


def sweep_value(ends: tuple, i: int, count: int) -> float:
    """Value ``i`` of ``count`` of the sweep ``ends`` (:func:`parse_sweep`); the same numbers as
    ``np.linspace(0, 1, count)`` would give."""
    start, stop, log = ends
    u = 0.0 if count <= 1 else 1.0 if i == count - 1 else i * (1.0 / (count - 1))
    if not log:
        return float(start + (stop - start) * u)
    sign = math.copysign(1.0, start)
    a, b = math.log(abs(start)), math.log(abs(stop))
    return float(sign * math.exp(a + (b - a) * u))


# ---------------------------------------------------------------------- keyframes

def read_keyframes(path) -> list:
    """The keyframes of a TOML or JSON file (see the module docstring), checked: known keys,
    increasing frame numbers, numbers of the right shape."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise AMRError(f"{path}: cannot read the keyframe file ({e.strerror})") from None
    except UnicodeDecodeError as e:
        raise AMRError(f"{path}: not a UTF-8 text file (byte {e.start}); a keyframe file is "
                       f"TOML or JSON text") from None
    try:
        if path.suffix.lower() == ".toml":
            import tomllib

            data = tomllib.loads(text)
        else:
            data = json.loads(text)
    except ValueError as e:
        raise AMRError(f"{path}: not a valid {path.suffix[1:].upper() or 'JSON'} file ({e})") \
            from None
    keys = data.get("keyframe", data.get("keyframes")) if isinstance(data, dict) else data
    if not isinstance(keys, list) or not keys:
        raise AMRError(f"{path}: expected a list of keyframes ([[keyframe]] tables)")
    return _monotonic(path, [_check_keyframe(path, i, k) for i, k in enumerate(keys)])


def _check_keyframe(path, i, k) -> dict:
    if not isinstance(k, dict):
        raise AMRError(f"{path}: keyframe {i + 1} is not a table of values")
    unknown = sorted(set(k) - set(KEYFRAME_KEYS))
    if unknown:
        raise AMRError(f"{path}: keyframe {i + 1}: unknown key(s) {unknown}; allowed: "
                       f"{', '.join(KEYFRAME_KEYS)}")
    frame = k.get("frame")
    if not _whole(frame) or not 0 <= frame < MAX_FRAMES:
        raise AMRError(f"{path}: keyframe {i + 1} needs 'frame', a whole number from 0 to "
                       f"{MAX_FRAMES - 1}, got {_short(frame)}")
    out = {"frame": frame}
    for name in k:
        if name == "frame":
            continue
        want = 3 if name in VECTORS else 2 if name == "color_range" else 1
        v = k[name] if want > 1 else [k[name]]
        if not isinstance(v, list) or len(v) != want or not all(_number(x) for x in v):
            raise AMRError(f"{path}: keyframe {i + 1}: '{name}' needs {want} finite number(s), "
                           f"got {_short(k[name])}")
        out[name] = [float(x) for x in v] if want > 1 else float(v[0])
    if "color_range" in out and not out["color_range"][0] < out["color_range"][1]:
        raise AMRError(f"{path}: keyframe {i + 1}: 'color_range' needs low < high")
    if "fov" in out and not 0.0 < out["fov"] < 180.0:
        raise AMRError(f"{path}: keyframe {i + 1}: 'fov' is the horizontal field of view in "
                       f"degrees, between 0 and 180 (both excluded), got {out['fov']:g}")
    if "up" in out and not any(out["up"]):
        raise AMRError(f"{path}: keyframe {i + 1}: 'up' must not be the zero vector")
    if "step" in out and not (out["step"] >= 0 and out["step"] == int(out["step"])):
        raise AMRError(f"{path}: keyframe {i + 1}: 'step' needs a whole number >= 0 (an index "
                       f"into --files), got {k['step']!r}")
    return out


def _whole(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _number(x) -> bool:
    """A finite number within float32 (what the kernels take), not a boolean."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(float(x)) and abs(float(x)) <= FLOAT32_MAX
    except OverflowError:           # an int beyond float64
        return False


def _short(value) -> str:
    """``repr(value)``, cut to 60 characters (a value may be a 4000-digit number)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _monotonic(path, keys) -> list:
    frames = [k["frame"] for k in keys]
    for a, b in zip(frames, frames[1:]):
        if b <= a:
            raise AMRError(f"{path}: keyframe frame numbers must increase, got {a} then {b}")
    return keys


def _catmull_rom(points, frames, t):
    """The uniform Catmull-Rom curve through ``points`` (at parameters ``frames``) at ``t``."""
    i = int(np.clip(np.searchsorted(frames, t, side="right") - 1, 0, len(frames) - 2))
    u = (t - frames[i]) / (frames[i + 1] - frames[i])
    p0 = points[max(i - 1, 0)]
    p1, p2 = points[i], points[i + 1]
    p3 = points[min(i + 2, len(points) - 1)]
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u * u +
                  (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3)


def keyframe_value(keys, name, t, default):
    """The value of ``name`` at frame ``t``: interpolated between the keyframes that give it
    (Catmull-Rom for origin and target, linear otherwise), held beyond them."""
    have = [k for k in keys if name in k]
    if not have:
        return default
    frames = np.array([k["frame"] for k in have], dtype=float)
    values = np.array([np.atleast_1d(k[name]) for k in have], dtype=float)
    if len(have) == 1 or t <= frames[0]:
        v = values[0]
    elif t >= frames[-1]:
        v = values[-1]
    elif name in ("origin", "target"):
        v = _catmull_rom(values, frames, t)
    else:
        v = np.array([np.interp(t, frames, values[:, c]) for c in range(values.shape[1])])
    return [float(x) for x in v] if values.shape[1] > 1 else float(v[0])


def append_keyframe(path, frame: int, camera: dict | None = None, isovalue=None,
                    color_range=None, step=None) -> dict:
    """Add a keyframe to the file ``path`` (JSON, or TOML by its suffix; made when missing) and
    write it atomically. The frame number must be above the file's last one."""
    path = Path(path)
    keys = read_keyframes(path) if path.exists() else []
    if keys and frame <= keys[-1]["frame"]:
        raise AMRError(f"{path}: keyframe frame {frame} must come after {keys[-1]['frame']}")
    new = {"frame": int(frame)}
    if camera is not None:
        new.update({k: [float(x) for x in camera[k]] for k in VECTORS})
        new["fov"] = float(camera["fov"])
    if isovalue is not None:
        new["isovalue"] = float(isovalue)
    if color_range is not None:
        new["color_range"] = [float(x) for x in color_range]
    if step is not None:
        new["step"] = int(step)
    keys.append(_check_keyframe(path, len(keys), new))
    text = _toml(keys) if path.suffix.lower() == ".toml" else json.dumps({"keyframe": keys},
                                                                         indent=2) + "\n"
    from mi_amr.workflows.movie.output import write_bytes_atomic

    write_bytes_atomic(path, text.encode())
    return new


def _toml(keys) -> str:
    def value(k, v):
        if isinstance(v, list):
            return "[" + ", ".join(repr(float(x)) for x in v) + "]"
        return str(int(v)) if isinstance(v, int) or k == "step" else repr(float(v))

    blocks = ["[[keyframe]]\n" + "".join(f"{k} = {value(k, v)}\n" for k, v in key.items())
              for key in keys]
    return "\n".join(blocks)


# ---------------------------------------------------------------------- planning

def plan(frames: int | None, *, camera: dict, files=None, orbit_degrees=None, isovalues=None,
         keyframes=None, color_range=None) -> "Plan":
    """The frames of a movie (see the module docstring), checked here and computed one by one
    as they are asked for (:class:`Plan`). ``frames`` defaults to the last keyframe + 1 when the
    keyframes give time steps, else to the number of files, else to the last keyframe + 1, else
    to 60. With more frames than files each time step is held for several frames."""
    files = list(files or [])
    stepped = _check_steps(keyframes, files)
    if frames is None:
        frames = keyframes[-1]["frame"] + 1 if stepped else \
            len(files) or (keyframes[-1]["frame"] + 1 if keyframes else 60)
    check_frames(frames)
    check_orbit(orbit_degrees)
    if orbit_degrees and not any(camera["up"]):
        raise AMRError("--orbit: the camera's up vector is zero; give the scene's <lookat> an up")
    return Plan(frames, camera, files, orbit_degrees,
                parse_sweep(isovalues) if isovalues else None, keyframes, color_range, stepped)


def check_frames(frames) -> None:
    """``--frames``: a whole number from 1 to :data:`MAX_FRAMES`."""
    if not _whole(frames) or not 1 <= frames <= MAX_FRAMES:
        raise AMRError(f"--frames must be a whole number from 1 to {MAX_FRAMES} (a frame's "
                       f"number is its 32-bit seed), got {_short(frames)}")


def check_orbit(degrees) -> None:
    """``--orbit``: None, or a finite number of degrees."""
    if degrees is None:
        return
    if isinstance(degrees, bool) or not isinstance(degrees, (int, float)) or \
            not math.isfinite(degrees) or abs(degrees) > FLOAT32_MAX:
        raise AMRError(f"--orbit: the turn in degrees must be a finite number, got "
                       f"{_short(degrees)}")


class Plan(Sequence):
    """The :class:`FrameSpec`\\ s of :func:`plan`, each made when it is asked for: a movie of
    10^8 frames starts rendering at once, in constant memory. ``files``: the time series."""

    def __init__(self, count, camera, files, orbit_degrees, sweep_ends, keyframes,
                 color_range, stepped=False):
        self.count, self.camera, self.files = count, camera, files
        self.orbit_degrees, self.sweep_ends = orbit_degrees, sweep_ends
        self.keyframes, self.color_range = keyframes, color_range
        self.stepped = stepped      # the keyframes give the time step of each frame

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self.count))]
        if not -self.count <= i < self.count:
            raise IndexError(i)
        return self._spec(i % self.count)

    def _spec(self, i: int) -> FrameSpec:
        n, files, keys = self.count, self.files, self.keyframes
        cam = orbit_camera(self.camera, self.orbit_degrees, i, n) if self.orbit_degrees \
            else dict(self.camera)
        iso = sweep_value(self.sweep_ends, i, n) if self.sweep_ends else None
        rng = self.color_range
        if keys:
            cam = {k: keyframe_value(keys, k, i, cam[k]) for k in (*VECTORS, "fov")}
            iso = keyframe_value(keys, "isovalue", i, iso)
            rng = keyframe_value(keys, "color_range", i, rng)
        if self.stepped:
            step = files[int(math.floor(keyframe_value(keys, "step", i, 0.0) + 0.5))]
        else:
            step = files[min(i * len(files) // n, len(files) - 1)] if files else None
        return FrameSpec(index=i, file=step, camera=cam, isovalue=iso,
                         color_range=None if rng is None else tuple(rng))


def _check_steps(keyframes, files) -> bool:
    """Whether the keyframes give time steps (then each one must name one of ``files``)."""
    steps = [int(k["step"]) for k in keyframes or () if "step" in k]
    if not steps:
        return False
    if not files:
        raise AMRError("the keyframes give time steps ('step'): pass the time series with "
                       "--files (the files the viewer stepped through, in the same order)")
    if max(steps) >= len(files):
        raise AMRError(f"a keyframe shows time step {max(steps)}, but --files gives "
                       f"{len(files)} file(s) (steps 0 to {len(files) - 1})")
    return True
