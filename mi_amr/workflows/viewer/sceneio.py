"""The viewer's state written as a Mitsuba scene: the scene file it started from with the
integrator's parameters, the camera, the light, ``spp`` and the resolution replaced, and every
relative ``filename`` made absolute, so ``python -m mi_amr render`` reproduces the view from
any folder. The viewer also loads the scene again from this text when the kernels' structure
changes, so what it shows and what it saves cannot drift apart.
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from mi_amr.errors import AMRError

MARK = "Written by 'python -m mi_amr view'"     # the first comment of a scene it writes
# The integrator's parameters the viewer owns: (name, XML tag).
OWNED = (("filename", "string"), ("field", "string"), ("isovalue", "string"),
         ("iso_color", "string"), ("iso_opacity", "string"), ("color_field", "string"),
         ("colormap", "string"), ("color_range", "string"), ("mode", "string"),
         ("method", "string"), ("reconstruction", "string"), ("step_scale", "float"),
         ("shadows", "boolean"), ("band_width", "string"), ("band_support", "string"),
         ("band_peak", "string"), ("layers", "string"))


def num(x) -> str:
    """A float written so that reading it back gives the same double (and float32)."""
    return repr(float(x))


def integrator_values(state) -> dict:
    """The owned parameters' values as scene text (None: leave the parameter out)."""
    # (a 2D transfer function replaces the bands: the integrator refuses band parameters)
    volume = state.mode == "volume" and state.tf2d is None
    support = "; ".join(f"{num(iso + lo)} {num(iso + hi)}"
                        for iso, (lo, hi) in zip(state.isovalues, state.band_offsets))
    return {
        "filename": state.data_file, "field": state.field,
        "isovalue": ", ".join(num(v) for v in state.isovalues),
        "iso_color": "; ".join(" ".join(num(c) for c in rgb) for rgb in state.iso_colors),
        "iso_opacity": ", ".join(num(a) for a in state.iso_opacity),
        "color_field": state.color_field, "colormap": state.colormap,
        "color_range": None if state.color_range is None else
        " ".join(num(v) for v in state.color_range),
        "mode": state.mode, "method": state.method, "reconstruction": state.reconstruction,
        "step_scale": num(state.step_scale), "shadows": "true" if state.shadows else "false",
        "band_width": ", ".join(num(w) for w in state.band_width) if volume else None,
        "band_support": support if volume else None,
        "band_peak": ", ".join(num(a) for a in state.band_peak) if volume else None,
        # (volume mode composites its band: the scene then leaves the layers out)
        "layers": None if volume else state.layers,
    }


def scene_text(base_path, state, *, spp: int, resolution, tf2d_file=None) -> str:
    """The scene file ``base_path`` showing ``state`` at ``resolution`` ``(width, height)``
    pixels and ``spp`` samples per pixel (as the ``spp``, ``resx`` and ``resy`` defaults, so
    ``render --spp/--resolution`` still apply). With a 2D transfer function, ``tf2d_file`` is
    its table (written by :func:`write_table`)."""
    base_path = Path(base_path)
    try:
        tree = ET.parse(str(base_path), parser=ET.XMLParser(
            target=ET.TreeBuilder(insert_comments=True)))
    except (OSError, ET.ParseError) as e:
        raise AMRError(f"{base_path}: cannot read the scene file ({e})") from None
    root = tree.getroot()
    defaults = {d.get("name"): d.get("value") for d in root.iter("default")}
    integrator = next((e for e in root.iter("integrator") if e.get("type") == "amr_iso"), None)
    if integrator is None:
        raise AMRError(f"{base_path}: no amr_iso integrator")
    linked = _linked_defaults(integrator, defaults)
    _absolute_filenames(root, base_path.resolve().parent, defaults)
    values = integrator_values(state)
    for name, tag in OWNED:
        _set_child(integrator, tag, name, values[name])
    # A parameter the file gave as "$name" stays so, its <default> holding the view's value:
    # -D name=... still applies to the saved scene.
    for name, default in linked.items():
        if values[name] is not None:
            _set_child(integrator, dict(OWNED)[name], name, f"${default}")
            _set_defaults(root, {default: str(values[name])})
    if state.tf2d is not None:
        if tf2d_file is None:
            raise AMRError("the view's 2D transfer function needs its table file")
        _set_child(integrator, "string", "transfer2d_blobs", None)
        _set_child(integrator, "string", "transfer2d", str(Path(tf2d_file).resolve()))
        _set_child(integrator, "string", "transfer2d_range",
                   " ".join(num(x) for x in state.tf2d.plane))
    _set_sensor(root, state.camera)
    if state.light_direction is not None:
        _set_light(root, state.light_direction, state.light_irradiance)
    _set_defaults(root, {"spp": str(int(spp)), "resx": str(int(resolution[0])),
                         "resy": str(int(resolution[1]))})
    _drop_unused_defaults(root, keep=("spp", "resx", "resy"))
    root.insert(0, ET.Comment(f" {MARK} from {base_path.resolve()} "))
    ET.indent(tree, space="    ")
    return ET.tostring(root, encoding="unicode") + "\n"


def _linked_defaults(integrator, defaults: dict) -> dict:
    """``{parameter: default name}`` for the owned parameters the file gives as exactly
    ``"$name"`` of one of its ``<default>``s."""
    owned = dict(OWNED)
    linked = {}
    for child in integrator:
        m = re.fullmatch(r"\$(\w+)", child.get("value", "").strip())
        if child.get("name") in owned and m and m.group(1) in defaults:
            linked[child.get("name")] = m.group(1)
    return linked


def _drop_unused_defaults(root, keep=()) -> None:
    """Remove the ``<default>``s nothing in the scene refers to any more (the viewer wrote the
    values in their place): left in, ``-D`` would accept their names and change nothing."""
    used = set(keep)
    for e in root.iter():
        if e.tag != "default":
            for value in e.attrib.values():
                used.update(re.findall(r"\$(\w+)", value))
    for d in [d for d in root.findall("default") if d.get("name") not in used]:
        root.remove(d)


def write_table(scene_path, state):
    """The 2D transfer function's table of ``state`` written beside the scene file
    ``scene_path`` (``NAME.tf2d.npy``, atomically); None without one."""
    import numpy as np

    from mi_amr.core.atomic import replacing

    if state.tf2d is None:
        return None
    path = Path(scene_path).with_suffix(".tf2d.npy")
    with replacing(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, state.tf2d.table(), allow_pickle=False)
    return path


def _absolute_filenames(root, folder: Path, defaults: dict) -> None:
    """``<string name="filename">`` values (``$name`` defaults resolved) relative to the scene's
    folder, made absolute."""
    for e in root.iter("string"):
        if e.get("name") != "filename":
            continue
        value = re.sub(r"\$(\w+)", lambda m: defaults.get(m.group(1), m.group(0)),
                       e.get("value", ""))
        if value and not os.path.isabs(value) and (folder / value).exists():
            value = os.path.abspath(folder / value)
        e.set("value", value)


def _set_child(parent, tag: str, name: str, value) -> None:
    """Replace ``parent``'s children named ``name`` by one ``<tag name value>`` (none when
    ``value`` is None), where the first one was."""
    old = [c for c in parent if c.get("name") == name]
    where = list(parent).index(old[0]) if old else len(parent)
    for c in old:
        parent.remove(c)
    if value is not None:
        parent.insert(where, ET.Element(tag, name=name, value=str(value)))


def _set_sensor(root, camera) -> None:
    sensor = root.find("sensor")
    if sensor is None:
        raise AMRError("the scene has no <sensor>")
    for name in ("focal_length",):
        _set_child(sensor, "string", name, None)
    # The viewer's field of view is Mitsuba's x_fov: say so, whatever the file said.
    _set_child(sensor, "string", "fov_axis", "x")
    _set_child(sensor, "float", "fov", num(camera.fov))
    transform = ET.Element("transform", name="to_world")
    ET.SubElement(transform, "lookat", origin=", ".join(num(x) for x in camera.origin),
                  target=", ".join(num(x) for x in camera.target),
                  up=", ".join(num(x) for x in camera.up))
    old = [c for c in sensor if c.get("name") == "to_world"]
    where = list(sensor).index(old[0]) if old else 0
    for c in old:
        sensor.remove(c)
    sensor.insert(where, transform)
    sampler = sensor.find("sampler")
    if sampler is not None:
        _set_child(sampler, "integer", "sample_count", "$spp")
    film = sensor.find("film")
    if film is not None:
        _set_child(film, "integer", "width", "$resx")
        _set_child(film, "integer", "height", "$resy")


def _set_light(root, direction, irradiance) -> None:
    """The first directional emitter (the one the viewer steers) gets ``direction`` and
    ``irradiance`` (its ``to_world`` is dropped: the direction says all of it)."""
    light = next((e for e in root.iter("emitter") if e.get("type") == "directional"), None)
    if light is None:
        return
    _set_child(light, "transform", "to_world", None)
    _set_child(light, "vector", "direction", ", ".join(num(x) for x in direction))
    _set_child(light, "rgb", "irradiance", " ".join(num(x) for x in irradiance))


def _set_defaults(root, values: dict) -> None:
    for name, value in values.items():
        existing = [d for d in root.findall("default") if d.get("name") == name]
        for d in existing:
            d.set("value", value)
        if not existing:
            root.insert(0, ET.Element("default", name=name, value=value))
