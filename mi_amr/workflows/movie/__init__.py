"""Movies: a camera orbit, an isovalue sweep, keyframes or a time series of data files, one
frame per task, rendered in this process or on Dask, every per-frame value a kernel input.

>>> from mi_amr.workflows.movie import render_movie
>>> summary = render_movie("scenes_xml/sphere_wake.xml", "out/orbit", orbit=360, frames=48,
...                        resolution=(512, 512), workers=2, mp4="out/orbit.mp4")

The frame specs (:mod:`.spec`) are plain values: build them with :func:`plan` (a lazy
sequence: each frame is planned as it is rendered) or by hand, and pass them as ``specs``;
the viewer's "add keyframe" button appends to a keyframe file with :func:`append_keyframe`.
"""

from __future__ import annotations

import time
import xml.etree.ElementTree as ET
from pathlib import Path

from mi_amr.errors import AMRError
from mi_amr.workflows.movie.farm import WORKER_WAIT, Summary, jobs_for, run_jobs
from mi_amr.workflows.movie.output import (FORMATS, check_out_dir, existing_frames,
                                           frame_path, image_size)
from mi_amr.workflows.movie.spec import (FrameSpec, Plan, append_keyframe, check_frames,
                                         check_orbit, expand_files, plan, read_keyframes)

__all__ = ["render_movie", "plan", "FrameSpec", "append_keyframe", "read_keyframes",
           "expand_files", "series_color_range", "Summary", "Plan", "check_values"]


def series_color_range(files, scene_path, defines=None, progress: bool = False) -> tuple:
    """One colour range for a whole time series: the smallest and largest value of the scene's
    colour field over every file (each file read once, that field only, or what it is derived
    from). A file that cannot be read is left out here; its frames fail, naming it. Files read
    a stretch at a time (:func:`_streamed_range`) are read side by side on the CPUs, the others
    loaded one at a time (each holds a volume); ``progress``: a bar on stderr, a step a file."""
    from tqdm import tqdm

    from mi_amr.core import parallel

    field, color_field = _scene_fields(scene_path, defines)
    if color_field is None:
        return None
    wanted = (color_field, _scene_allows_nonfinite(scene_path, defines))
    lo, hi = float("inf"), float("-inf")
    streamed = parallel.map_ordered(lambda f: _quick_range(f, wanted), files)
    with tqdm(total=len(files), desc="colour range", unit="file", disable=not progress,
              leave=False) as bar:
        for f, got in zip(files, streamed):
            if got is _LOAD:
                got = _guarded(_loaded_range, f, *wanted)
            bar.update()
            if got is not None:
                lo, hi = min(lo, got[0]), max(hi, got[1])
    return (lo, hi) if lo < hi else None


_LOAD = object()    # what _quick_range gives for a file whose range needs it loaded


def _guarded(fn, *args):
    """``fn(*args)``, None where it raises an AMRError (a file that cannot be read)."""
    try:
        return fn(*args)
    except AMRError:
        return None


def _quick_range(path, wanted):
    """:func:`_file_range` of ``wanted`` (``(name, allow_nonfinite)``) where the file can be
    read a stretch at a time, :data:`_LOAD` where it must be loaded, None where it cannot be
    read."""
    name, allow_nonfinite = wanted
    try:
        got = _streamed_range(path, name, _names_to_read(path, name), allow_nonfinite)
    except AMRError:
        return None
    return _LOAD if got is None else got


def _names_to_read(path, name) -> list:
    from mi_amr.kernels.prepared import fields_to_read
    from mi_amr.readers import available_fields

    return fields_to_read(name, None, available_fields(path), path)


def _file_range(path, name, allow_nonfinite: bool = False) -> tuple:
    """``(min, max)`` of the finite values of field ``name`` of data file ``path``, derived
    from what it holds where it is not stored (the speed straight from the velocity, without
    writing the field); NaN and Inf values refused unless ``allow_nonfinite``, as the frames
    load the file."""
    got = _streamed_range(path, name, _names_to_read(path, name), allow_nonfinite)
    return _loaded_range(path, name, allow_nonfinite) if got is None else got


def _loaded_range(path, name, allow_nonfinite: bool = False) -> tuple:
    """:func:`_file_range` from the file loaded (the field derived where it is not stored)."""
    from mi_amr.core.derive import DERIVED_FIELDS, derive, speed_range
    from mi_amr.readers import load

    names = _names_to_read(path, name)
    vol = load(path, fields=names, level_buffers=names, allow_nonfinite=allow_nonfinite)
    if name not in vol.field_names and name in DERIVED_FIELDS:
        got = speed_range(vol) if name == "speed" else None
        if got is not None:
            return got
        vol = derive(vol, name)
    return vol.value_range(name)


def _streamed_range(path, name, names, allow_nonfinite: bool = False):
    """:func:`_file_range` from the file read a stretch at a time where its format allows
    (no field-sized buffer, no grids built: the frame that loads the file checks them), for
    a stored field and the speed; None otherwise."""
    from mi_amr.core.derive import speed_range_of_chunks
    from mi_amr.core.extremes import finite_range
    from mi_amr.readers import stream_fields

    if names != [name] and name != "speed":
        return None
    stream = stream_fields(path, names, allow_nonfinite)
    if stream is None:
        return None
    with stream:
        if names == [name]:
            return finite_range(values[0] for values in stream.chunks())
        if stream.same_dtype:       # (else each grid's roundings: derive's path)
            return speed_range_of_chunks(stream.chunks())
    return None


def _scene_fields(scene_path, defines):
    """``(field, color_field)`` of the scene's amr_iso integrator, read from its XML."""
    from mi_amr.plugin.options import NO_COLOR_FIELD

    value = _scene_values(scene_path, defines)
    color = value("color_field") if value("colormap") else None
    off = color is not None and color.strip().lower() in NO_COLOR_FIELD
    return value("field"), None if off else color


def _scene_allows_nonfinite(scene_path, defines) -> bool:
    """Does the scene's amr_iso integrator keep NaN and Inf values as missing data
    (``allow_nonfinite``)?"""
    allow = _scene_values(scene_path, defines)("allow_nonfinite")
    return allow is not None and allow.strip().lower() == "true"


def _scene_values(scene_path, defines):
    """``value(name)``: the scene's amr_iso parameter ``name`` as its XML writes it, its
    ``$default`` references filled in (``defines`` over the scene's ``<default>``s), or None
    where the integrator does not set it."""
    import re

    try:
        root = ET.parse(str(scene_path)).getroot()
    except (OSError, ET.ParseError) as e:
        raise AMRError(f"{scene_path}: cannot read the scene file ({e})") from None
    values = {d.get("name"): d.get("value") for d in root.iter("default")}
    values.update(defines or {})
    integ = root.find("integrator[@type='amr_iso']")
    if integ is None:
        raise AMRError(f"{scene_path}: the scene has no amr_iso integrator")

    def value(name):
        node = integ.find(f"*[@name='{name}']")
        if node is None:
            return None
        return re.sub(r"\$(\w+)", lambda m: str(values.get(m.group(1), m.group(0))),
                      node.get("value"))

    return value


def _has_filename_default(scene_path) -> bool:
    root = ET.parse(str(scene_path)).getroot()
    return any(d.get("name") == "filename" for d in root.iter("default"))


def _check_fields(files, scene_path, defines):
    """Every file holds what the scene shows (stored, or what it is derived from)."""
    from mi_amr.kernels.prepared import fields_to_read
    from mi_amr.readers import available_fields

    field, color_field = _scene_fields(scene_path, defines)
    for f in files:
        try:
            have = available_fields(f)
            need = fields_to_read(field, color_field, have, f)
        except AMRError:
            continue                # unreadable: that frame fails, naming the file
        missing = [n for n in need if n not in have]
        if missing:
            raise AMRError(f"{f}: has no field(s) {missing} that the scene shows; it holds "
                           f"{list(have)}")


def render_movie(scene, out, *, frames=None, files=None, orbit=None, isovalues=None,
                 keyframes=None, color_range=None, resolution=None, spp=None, fmt="png",
                 workers: int = 1, scheduler=None, mp4=None, fps: int = 24, force=False,
                 defines=None, variant="llvm_ad_rgb", specs=None, progress=True,
                 worker_wait: float = WORKER_WAIT) -> Summary:
    """Render a movie of ``scene`` into the folder ``out`` (``frame_00000.png`` ...) and return
    what happened. ``color_range``: ``(lo, hi)``, ``"series"`` (one range over all ``files``;
    the default for a time series) or None (the scene's). See the module docstring and
    ``python -m mi_amr movie --help`` for the rest; ``worker_wait``: seconds the Dask cluster
    may have no worker with frames left before the movie's own cluster gives up (AMRError) or
    a ``scheduler``'s user is told (see :func:`~mi_amr.workflows.movie.farm.run_jobs`)."""
    t0 = time.perf_counter()
    scene = Path(scene)
    if not scene.is_file():
        raise AMRError(f"{scene}: no such scene file")
    if fmt not in FORMATS:
        raise AMRError(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    check_values(frames=frames, orbit=orbit, resolution=resolution, spp=spp, fps=fps, mp4=mp4,
                 force=force)
    from mi_amr.plugin.scene import use_variant

    use_variant(variant)
    out = check_out_dir(out)
    defines = dict(defines or {})
    if specs is None:
        specs = _plan(scene, frames, files, orbit, isovalues, keyframes, color_range, defines,
                      resolution, spp, variant, progress=progress)
    first_file = _first_file(specs)
    if first_file and _has_filename_default(scene):
        defines.setdefault("filename", str(Path(first_file).resolve()))
    existing = {} if force else _existing(out, fmt, specs)
    _check_existing(out, existing, _frame_size(scene, defines, resolution))
    jobs = jobs_for(scene, specs, out, fmt, resolution=resolution, spp=spp, defines=defines,
                    variant=variant, force=force, existing=existing)
    summary = Summary(skipped=sorted(existing))
    from mi_amr.plugin.integrator import register

    preparations = register()
    series_steps = preparations.series_steps      # (frames rendered here set it: restored)
    try:
        for r in run_jobs(jobs, workers=workers, scheduler=scheduler, progress=progress,
                          variant=variant, total=len(specs) - len(existing),
                          worker_wait=worker_wait):
            (summary.failed if "error" in r else summary.rendered).append(r)
    finally:
        preparations.series_steps = series_steps
        # A worker killed while writing leaves its temporary file (never a frame's name).
        for tmp in out.glob(f"frame_*.tmp-*.{fmt}"):
            tmp.unlink(missing_ok=True)
    if mp4 is not None and not summary.failed:
        from mi_amr.workflows.movie.encode import encode_mp4

        encode_mp4((frame_path(out, s.index, fmt) for s in specs), mp4, fps, force=force)
    summary.seconds = time.perf_counter() - t0
    return summary


def check_values(*, frames=None, orbit=None, resolution=None, spp=None, fps=24, mp4=None,
                 force=False) -> None:
    """The movie's numbers and its MP4's path, checked before anything is read or planned
    (keyframe values are checked as their file is read)."""
    from mi_amr.workflows.movie.encode import check_fps, check_mp4
    from mi_amr.workflows.render import JIT_MAX_ENTRIES

    if frames is not None:
        check_frames(frames)
    check_orbit(orbit)
    if resolution is not None:
        if len(resolution) != 2 or min(resolution) < 1:
            raise AMRError(f"--resolution must be two positive numbers, got {resolution}")
        if resolution[0] * resolution[1] * 4 > JIT_MAX_ENTRIES:
            raise AMRError(f"--resolution {resolution[0]} {resolution[1]}: too large to render "
                           f"at once (Dr.Jit arrays hold fewer than 2^32 values)")
    if spp is not None and spp < 1:
        raise AMRError(f"--spp must be >= 1, got {spp}")
    check_fps(fps)
    if mp4 is not None:
        check_mp4(mp4, fps, force=force)


def _first_file(specs):
    """The first data file the frames show (None: the scene's own), without planning every
    frame of a lazy :class:`Plan`."""
    if isinstance(specs, Plan):
        return specs.files[0] if specs.files else None
    return next((s.file for s in specs if s.file), None)


def _existing(out, fmt, specs) -> dict:
    """``{index: path}`` of this movie's frames already in ``out``."""
    found = existing_frames(out, fmt)
    if isinstance(specs, Plan):
        return {i: p for i, p in found.items() if i < len(specs)}
    wanted = {s.index for s in specs}
    return {i: p for i, p in found.items() if i in wanted}


def _check_existing(out, existing: dict, size) -> None:
    """Frames kept from an earlier run must be of this movie's size (else the MP4 cannot be
    made of them): one error before any work, naming the first that is not."""
    if size is None:
        return
    for index in sorted(existing):
        have = image_size(existing[index])
        if have != size:
            what = "not a readable image" if have is None else f"{have[0]}x{have[1]}"
            raise AMRError(f"-o {out}: {existing[index].name} is {what}, this movie's frames "
                           f"are {size[0]}x{size[1]}; pass --force to render every frame "
                           f"again, or choose another folder")


def _frame_size(scene_path, defines, resolution):
    """The frames' ``(width, height)``: ``resolution``, else the scene's film (``$name``
    defaults and ``defines`` resolved; Mitsuba's 768 x 576 where it gives none); None where
    the file does not say in plain numbers."""
    import re

    if resolution is not None:
        return (int(resolution[0]), int(resolution[1]))
    try:
        root = ET.parse(str(scene_path)).getroot()
    except (OSError, ET.ParseError):
        return None
    values = {d.get("name"): d.get("value") for d in root.iter("default")}
    values.update(defines or {})
    film = root.find("sensor/film")
    size = []
    for name, default in (("width", "768"), ("height", "576")):
        node = film.find(f"*[@name='{name}']") if film is not None else None
        text = default if node is None else re.sub(
            r"\$(\w+)", lambda m: str(values.get(m.group(1), m.group(0))), node.get("value", ""))
        if not text.strip().isdigit():
            return None
        size.append(int(text))
    return tuple(size)


def _plan(scene, frames, files, orbit, isovalues, keyframes, color_range, defines, resolution,
          spp, variant, progress=False):
    """The frame specs of the options (reading the camera from the scene file); ``progress``:
    a bar while a time series' colour range is taken."""
    files = expand_files(files) if files else []
    if files:
        _check_fields(files, scene, defines)
    keys = read_keyframes(keyframes) if keyframes else None
    if color_range == "series":
        color_range = series_color_range(files, scene, defines, progress) if files else None
    elif color_range is None and files:
        color_range = series_color_range(files, scene, defines, progress)
    camera = _scene_camera(scene, defines)
    return plan(frames, camera=camera, files=files, orbit_degrees=orbit, isovalues=isovalues,
                keyframes=keys, color_range=color_range)


def _scene_camera(scene, defines) -> dict:
    import mitsuba  # noqa: F401  (plugin.camera needs a variant for matrix cameras only)

    from mi_amr.plugin.camera import scene_camera

    try:
        return scene_camera(scene, defines).as_dict()
    except AMRError:
        raise AMRError(f"{scene}: a movie needs the camera given as <lookat origin target up> "
                       f"in the scene file") from None
