"""What the viewer shows (:class:`ViewState`, an immutable snapshot) and the loaded scene that
shows it (:class:`Session`): how each control becomes ``mi.traverse`` updates.

==========================  =====================================================  ==========
control                     ``mi.traverse`` key(s)                                 compiles
==========================  =====================================================  ==========
isovalue(s)                 ``integrator.isovalue``                                no
iso colour / opacity        ``integrator.iso_color`` / ``integrator.iso_opacity``  no
step scale, shadows         ``integrator.step_scale``, ``integrator.shadows``      no
colour map, colour range    ``integrator.colormap_values``, ``colormap_colors``,   no
                            ``color_range`` (:func:`~mi_amr.plugin.inputs.
                            colormap_table`)
band width (volume mode)    ``integrator.band_width``, ``band_offsets``            no
camera                      the sensor's ``to_world`` and ``x_fov``                no
                            (:func:`~mi_amr.plugin.camera.set_camera`)
light                       the directional emitter's ``to_world`` and             no
                            ``irradiance.value``
preview size                the film's ``size``                                    once a size
saved image, any size       tiles of the view's film size (:mod:`.tiles`): the     no
                            ``x_fov`` and ``principal_point_offset_x/y``
data file (time step)       ``integrator.load_volume`` (same fields; the next      no
                            step prepared meanwhile, :mod:`.series`)
method, reconstruction,     the scene is loaded again (:func:`structure`)          yes (once)
layers, mode, field, colour
field, number of isovalues
==========================  =====================================================  ==========

Positions and directions are scene world space; the light's ``direction`` is the way its light
travels (Mitsuba's ``direction`` of a ``directional`` emitter), a unit vector. Colours are
linear RGB. A Session is used from one thread only (the render worker's).
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr import tolerances as tol
from mi_amr.core.suggest import (leaf_values, sorted_histogram, sorted_quantile,
                                 suggest_band_widths)
from mi_amr.errors import AMRError
from mi_amr.plugin.camera import Camera, scene_camera, sensor_key, set_camera
from mi_amr.plugin.inputs import colormap_table
from mi_amr.plugin.scene import load_scene
from mi_amr.workflows.render import Pass, render_pass, scene_passes
from mi_amr.workflows.viewer import tiles

HISTOGRAM_BINS = 128
QUANTILES = 201                 # the isovalue slider's percentile scale: every half percent
MIN_TILE_KEPT = 32              # pixels a tile keeps per side at least, inside its margins


@dataclass(frozen=True)
class ViewState:
    """One complete view: every value the page can change (see the module docstring)."""

    data_file: str                  # absolute path of the volume shown
    field: str
    color_field: Optional[str]      # None: each isovalue has its own colour
    colormap: Optional[str]         # pairs "v: r g b, ..." or a matplotlib name
    color_range: Optional[tuple]    # (lo, hi) field units, with a colour map
    isovalues: tuple
    iso_colors: tuple               # one (r, g, b) per isovalue, linear
    iso_opacity: tuple
    mode: str
    method: str
    reconstruction: str
    layers: str                     # translucent surfaces: composite or stochastic
    step_scale: float
    band_width: tuple               # volume mode: one per isovalue (field units)
    band_offsets: tuple             # one (lo, hi) per isovalue: its band's support minus it
    band_peak: tuple                # one per isovalue
    shadows: bool
    camera: Camera
    light_direction: Optional[tuple]    # None: the scene has no directional light
    light_irradiance: Optional[tuple]   # (r, g, b)
    spp: int                        # samples per pixel of the refined image
    tf2d: Optional[object] = None   # volume mode's 2D transfer function (:class:`.tf2d.TF2D`)

    def replace(self, **changes) -> "ViewState":
        return dataclasses.replace(self, **changes)


def structure(state: ViewState) -> tuple:
    """What the kernels' structure depends on: a change of any of these loads the scene
    again (and compiles its kernels once); every other change is an ``mi.traverse`` update."""
    return (state.field, state.color_field, state.colormap is None, state.mode, state.method,
            state.reconstruction, state.layers, len(state.isovalues), state.tf2d is None)


class Session:
    """The scene on screen: loaded from ``scene_path``, shown at ``resolution`` (pixels,
    ``(width, height)``), changed to each new :class:`ViewState` by :meth:`apply`.
    ``series``: data files (absolute paths) shown as the time steps of the scene (the first
    one at start; see :mod:`.series`)."""

    def __init__(self, scene_path, *, resolution=None, spp: int = 4, series=()):
        from mi_amr.plugin.integrator import register
        from mi_amr.workflows.prefetch import Prefetcher

        register().keep_fields = True       # (the histograms and value ranges read them)
        self.workdir = Path(tempfile.mkdtemp(prefix="mi_amr-view-"))
        self.compiled = {"warmup": 0, "controls": 0, "reloads": 0, "quality": 0, "saves": 0,
                         "steps": 0, "preview_sizes": 0}
        self._reload_count = 0
        self._values = (None, None, None)   # the volume (weakly), field, its sorted leaf values
        self.series = [str(f) for f in series]
        self.prefetch = Prefetcher()
        self.open(scene_path, resolution=resolution, spp=spp)

    # ------------------------------------------------------------------ loading
    def open(self, scene_path, *, resolution=None, spp: int = 4) -> ViewState:
        """Show the scene file ``scene_path`` as it is written (its own state). On an
        :class:`AMRError` the session keeps showing what it showed."""
        self.prefetch.wait()
        saved = dict(self.__dict__)
        try:
            return self._open(scene_path, resolution, spp)
        except BaseException:
            self.__dict__.clear()
            self.__dict__.update(saved)
            raise

    def _open(self, scene_path, resolution, spp: int) -> ViewState:
        scene_path = Path(scene_path).resolve()
        scene = load_scene(scene_path, pixel_format="rgba")    # saves are RGBA, as render's
        self._adopt(scene, scene_path)
        self.base_path = scene_path
        film = tuple(int(x) for x in self.params[self._film_key])
        self.resolution = tuple(resolution) if resolution else \
            (512, max(1, round(512 * film[1] / film[0])))
        self.home_camera = scene_camera(scene_path, None, scene)
        self.state = self._read_state(scene_path, spp)
        if self.series:
            self._first_step()
        self.up = np.asarray(self.home_camera.up, dtype=np.float64)
        self._write_all()
        return self.state

    def _first_step(self) -> None:
        """With a series: its files are checked against the scene, and its first step is
        shown (unless the scene shows one of its steps already)."""
        from mi_amr.workflows.viewer.series import check_series

        opt = self.integrator.opt
        check_series(self.series, opt.field, opt.color_field)
        if self.state.data_file not in self.series:
            self.integrator.load_volume(self.series[0])
            self.state = self.state.replace(data_file=self.series[0])

    def prefetch_next(self) -> None:
        """Prepare the step after the one shown in the background (see :mod:`.series`); the
        render thread calls it once a step's first frame is out, so that the preparation does
        not slow that frame down."""
        from mi_amr.workflows.viewer.series import next_step

        following = next_step(self.series, self.state.data_file)
        if following is not None:
            self.prefetch.start(self.integrator, following)

    def _write_all(self) -> None:
        """Assign every value once, as later changes will: the first update in a process
        compiles a small kernel of the integrator's input checks, here rather than at the
        first control change (and the light gets the frame its saved scene gives it)."""
        self._write(self.state, None)
        self.params.update()

    def _adopt(self, scene, path) -> None:
        """Find the keys the controls write in a newly loaded ``scene`` (file ``path``)."""
        integrator = scene.integrator()
        if not hasattr(integrator, "opt") or not hasattr(integrator, "inputs"):
            raise AMRError(f"{path}: the viewer needs a scene rendered by the amr_iso "
                           f"integrator")
        self.scene, self.integrator = scene, integrator
        self.params = params = mi.traverse(scene)
        self._ikey = next(k[: -len("isovalue")] for k in params.keys()
                          if k.endswith(".isovalue") and k[: -len("isovalue")] + "step_scale"
                          in params)
        self._film_key = f"{sensor_key(params)}.film.size"
        self._film = None
        self._tiling = _tiling(scene, params, sensor_key(params))
        # A directional light has an irradiance; others (point, area) are not steered.
        lights = [k[: -len(".irradiance.value")] for k in params.keys()
                  if k.endswith(".irradiance.value") and
                  k[: -len(".irradiance.value")] + ".to_world" in params]
        self._light = lights[0] if lights else None

    def _read_state(self, scene_path, spp: int) -> ViewState:
        opt, p, k = self.integrator.opt, self.params, self._ikey
        filename = Path(opt.filename)
        data_file = filename if filename.is_absolute() else scene_path.parent / filename
        if not data_file.exists():
            data_file = Path(str(mi.file_resolver().resolve(opt.filename)))

        def floats(name):
            return tuple(float(x) for x in np.ravel(p[k + name].numpy()))

        colors = np.reshape(floats("iso_color"), (-1, 3))
        # (A surface scene without bands gets them from the histogram for a switch to volume
        # mode: band_width's default is in the sphere wake's units.)
        band = _bands(floats("band_width"), floats("band_offsets"), floats("band_peak")) \
            if opt.mode == "volume" else _default_bands(opt, None if "band_width" in opt.given
                                                         else self._leaf_values())
        direction = irradiance = None
        if self._light:
            m = np.array(p[f"{self._light}.to_world"].matrix, dtype=np.float64).reshape(4, 4)
            d = m[:3, 2]
            direction = tuple(float(x) for x in d / np.linalg.norm(d))
            irradiance = tuple(float(x) for x in np.ravel(p[f"{self._light}.irradiance.value"]))
        return ViewState(
            data_file=str(Path(data_file).resolve()), field=opt.field,
            color_field=opt.color_field, colormap=opt.colormap,
            color_range=floats("color_range") if opt.colormap is not None else None,
            isovalues=floats("isovalue"), iso_colors=tuple(tuple(c) for c in colors),
            iso_opacity=floats("iso_opacity"), mode=opt.mode, method=opt.method,
            reconstruction=opt.reconstruction, layers=opt.layers, step_scale=floats("step_scale")[0],
            band_width=band[0], band_offsets=band[1], band_peak=band[2],
            shadows=bool(p[k + "shadows"].numpy()[0]), camera=self.home_camera,
            light_direction=direction, light_irradiance=irradiance, spp=int(spp))

    # ------------------------------------------------------------------ changes
    def apply(self, state: ViewState) -> tuple:
        """Show ``state``: returns ``(how, shown)``, ``how`` one of ``"same"``, ``"traverse"``,
        ``"reload"``, and ``shown`` the state now on screen (after a reload the isovalues and
        the colour range are moved into a new field's range). On an :class:`AMRError` the
        scene keeps showing the previous state."""
        old = self.state
        if state == old:
            return "same", old
        if structure(state) != structure(old):
            return "reload", self._reload(state)
        if state.data_file != old.data_file:
            self.prefetch.wait()
            self.integrator.load_volume(state.data_file)
        try:
            self._write(state, old)
            self.params.update()
        except AMRError:
            self._write(old, None)
            self.params.update()
            raise
        self.state = state
        return "traverse", state

    def _write(self, state: ViewState, old: Optional[ViewState]) -> None:
        """Assign what differs between ``state`` and ``old`` (everything when ``old`` is None)
        through ``mi.traverse`` (then ``params.update()``)."""
        p, k = self.params, self._ikey

        def changed(*names):
            return old is None or any(getattr(state, n) != getattr(old, n) for n in names)

        if changed("isovalues"):
            p[k + "isovalue"] = mi.Float(state.isovalues)
        if changed("iso_colors"):
            p[k + "iso_color"] = mi.Float(np.ravel(state.iso_colors))
        if changed("iso_opacity"):
            p[k + "iso_opacity"] = mi.Float(state.iso_opacity)
        if changed("step_scale"):
            p[k + "step_scale"] = mi.Float(state.step_scale)
        if changed("shadows"):
            p[k + "shadows"] = mi.Bool(state.shadows)
        if state.colormap is not None and changed("colormap", "color_range", "data_file"):
            edges, colors, rng = colormap_table(state.colormap, self.color_data_range(),
                                                state.color_range)
            p[k + "colormap_values"], p[k + "colormap_colors"] = mi.Float(edges), mi.Float(colors)
            p[k + "color_range"] = mi.Float(rng)
        if state.tf2d is not None and changed("tf2d"):
            p[k + "transfer2d_table"] = mi.Float(np.ravel(state.tf2d.table()))
            p[k + "transfer2d_range"] = mi.Float(state.tf2d.plane)
        if state.mode == "volume" and changed("band_width", "band_offsets", "band_peak"):
            p[k + "band_width"] = mi.Float(state.band_width)
            p[k + "band_offsets"] = mi.Float(np.ravel(state.band_offsets))
            p[k + "band_peak"] = mi.Float(state.band_peak)
        if changed("camera"):
            self._write_sensor(state.camera, self._film or self.resolution)
        if self._light and changed("light_direction", "light_irradiance"):
            p[f"{self._light}.to_world"] = light_transform(state.light_direction)
            p[f"{self._light}.irradiance.value"] = mi.Color3f(*state.light_irradiance)

    def _write_sensor(self, camera: Camera, size) -> None:
        """The camera and the film size, always written together: Mitsuba's perspective
        camera traces other kernels after an update of only one of them (one more kernel per
        size and kind of update); written together, each film size has one kernel."""
        p = self.params
        p[self._film_key] = mi.ScalarVector2u(int(size[0]), int(size[1]))
        set_camera(p, camera)

    def _reload(self, state: ViewState) -> ViewState:
        """Load the scene again for a new kernel structure, from the XML that "save scene"
        would write (so the two cannot drift apart)."""
        from mi_amr.workflows.viewer.sceneio import scene_text, write_table

        self._reload_count += 1
        path = self.workdir / f"reload_{self._reload_count}.xml"
        path.write_text(scene_text(self.base_path, state, spp=state.spp,
                                   resolution=self.resolution,
                                   tf2d_file=write_table(path, state)))
        self.prefetch.wait()
        scene = load_scene(path, pixel_format="rgba")
        saved = dict(self.__dict__)
        try:
            self._adopt(scene, path)
            old, self.state = self.state, state
            self._write_all()
            fixed = self._into_range(state, old)
            if fixed != state:
                self._write(fixed, state)
                self.params.update()
                self.state = fixed
        except BaseException:
            self.__dict__.clear()
            self.__dict__.update(saved)
            raise
        return self.state

    def _into_range(self, state: ViewState, old: ViewState) -> ViewState:
        """After a new field: isovalues outside its range go to the middle of it, and the
        bands' widths (in the old field's units) are picked from its histogram about them
        (:func:`~mi_amr.core.suggest.suggest_band_widths`, supports of two widths each side);
        after a new colour field: the colour range is its data range."""
        lo, hi = self.value_range()
        changes = {}
        if state.field != old.field and not all(lo <= v <= hi for v in state.isovalues):
            k = len(state.isovalues)
            changes["isovalues"] = tuple(float(lo + (hi - lo) * (i + 1) / (k + 1))
                                         for i in range(k))
        values = self._leaf_values() if state.field != old.field else None
        if values is not None and values.size:
            widths = tuple(_picked_widths(values, changes.get("isovalues", state.isovalues)))
            changes.update(band_width=widths,
                           band_offsets=tuple((-2.0 * w, 2.0 * w) for w in widths))
        if state.colormap is not None and state.color_field != old.color_field:
            changes["color_range"] = tuple(self.color_data_range())
        return state.replace(**changes) if changes else state

    # ------------------------------------------------------------------ what the page needs
    def value_range(self, field: Optional[str] = None) -> tuple:
        """``(lo, hi)`` of the contoured field (field units)."""
        volume = self.integrator.prep.volume
        lo, hi = volume.value_range(field or self.integrator.prep.field)
        return (float(lo), float(hi)) if math.isfinite(lo) else (0.0, 1.0)

    def fields(self) -> tuple:
        """Fields the data file holds, and those that can be derived from its velocity."""
        from mi_amr.core.derive import DERIVED_FIELDS, VELOCITY_NAMES
        from mi_amr.readers import available_fields

        try:
            stored = tuple(available_fields(self.state.data_file))
        except AMRError:            # a source that cannot list its fields: the scene's own
            return tuple(f for f in dict.fromkeys([self.state.field, self.state.color_field])
                         if f is not None)
        velocity = any(all(n in stored for n in names) for names in VELOCITY_NAMES)
        return stored + (tuple(f for f in DERIVED_FIELDS if f not in stored) if velocity else ())

    def describe(self) -> dict:
        """What the page and the checks need to know about the scene on screen."""
        values = self._leaf_values()
        quantiles = sorted_quantile(values, np.linspace(0.0, 1.0, QUANTILES)).tolist() \
            if values.size else list(np.linspace(*self.value_range(), QUANTILES))
        return {"scene": str(self.base_path), "value_range": self.value_range(),
                "color_data_range": self.color_data_range(), "histogram": self.histogram(),
                "quantiles": quantiles, "slider_scale": slider_scale(quantiles),
                "histogram2d": self.histogram2d(),
                "fields": self.fields(), "home": self.home_camera,
                "up": tuple(float(x) for x in self.up), "resolution": tuple(self.resolution)}

    def color_data_range(self) -> tuple:
        prep = self.integrator.prep
        return self.value_range(prep.color_field)

    def histogram(self) -> list:
        """Counts of the field's leaf-cell values (cells no finer grid covers) in
        :data:`HISTOGRAM_BINS` equal bins over :meth:`value_range`."""
        lo, hi = self.value_range()
        return sorted_histogram(self._leaf_values(), HISTOGRAM_BINS,
                                (lo, hi if hi > lo else lo + 1.0)).tolist()

    def histogram2d(self):
        """Volume mode: the value x |grad f| histogram (:func:`.tf2d.histogram2d`)."""
        from mi_amr.workflows.viewer.tf2d import histogram2d

        if self.state.mode != "volume":
            return None
        prep = self.integrator.prep
        return histogram2d(prep.volume, prep.field, self.value_range())

    def _leaf_values(self) -> np.ndarray:
        """The field's finite values in the leaf cells (cells no finer grid covers), sorted,
        float64: gathered once for the volume and field on screen (opening a scene reads them
        for its bands, its histogram and the slider's quantiles)."""
        volume, field = self.integrator.prep.volume, self.integrator.prep.field
        held, held_field, values = self._values
        if held is None or held() is not volume or held_field != field:
            values = np.sort(leaf_values(volume, field))
            self._values = (weakref.ref(volume), field, values)
        return values

    # ------------------------------------------------------------------ rendering
    def render(self, size, spp: int, seed: int = 0, preview: bool = False,
               part=(0, 0)) -> np.ndarray:
        """One ``mi.render`` of the current state at ``size`` pixels ``(width, height)``: a
        linear RGBA float32 array ``(height, width, 4)`` (alpha: coverage by surfaces);
        ``part``: ``(first, count)`` of a :class:`~mi_amr.workflows.render.Pass`.
        ``preview``: volume mode's shadow caches at
        :data:`~mi_amr.tolerances.PREVIEW_SHADOW_CACHE_POINTS` (built again for the next
        frame that is not a preview)."""
        size = (int(size[0]), int(size[1]))
        if size != self._film:
            self._write_sensor(self.state.camera, size)
            self.params.update()
            self._film = size
        caches = getattr(self.scene.integrator(), "shadow_caches", None)
        if caches is not None:
            caches.max_points = tol.PREVIEW_SHADOW_CACHE_POINTS if preview else \
                tol.SHADOW_CACHE_POINTS
        image = render_pass(mi, self.scene, Pass(seed, spp, *part))
        dr.eval(image)
        dr.sync_thread()
        return np.array(image, dtype=np.float32)

    def render_refined(self, size, spp: int, before_pass=None) -> Optional[np.ndarray]:
        """The ``spp``-sample image, in the passes that ``python -m mi_amr render`` takes
        (:func:`~mi_amr.workflows.render.scene_passes`), so a saved scene renders to the same
        pixels (``tests/test_viewer.py`` checks it); None when ``before_pass()`` returns True
        (a newer request: the rest is dropped). Volume mode's shadow caches are built first, in
        wavefronts with ``before_pass()`` asked between them."""
        caches = getattr(self.integrator, "shadow_caches", None)
        if caches is not None and before_pass is not None:
            caches.max_points = tol.SHADOW_CACHE_POINTS
            self.integrator.config()        # (what the build reads, as a render sets it)
            if caches.grids(self.integrator, self.scene, stop=before_pass) is None:
                return None
        accum = None
        for p in scene_passes(self.scene, spp):
            if before_pass is not None and before_pass():
                return None
            part = self.render(size, p.spp, p.seed, part=(p.first, p.count)) * p.spp
            accum = part if accum is None else accum + part
        return (accum / spp).astype(np.float32)

    def tile_size(self) -> tuple:
        """The film size saved images are rendered in (:meth:`render_tiled`): the view's own,
        whose kernels the refined frames compiled, or, for a view too small to keep anything
        inside the filter's margin, a larger one (compiled once)."""
        edge = tiles.margin(self._tiling["radius"])
        return tuple(max(n, 2 * edge + MIN_TILE_KEPT) for n in self.resolution)

    def render_tiled(self, size, spp: int) -> np.ndarray:
        """The ``spp``-sample image at ``size`` pixels ``(width, height)``, linear RGBA
        ``(height, width, 4)`` (RGB where the film is RGB), rendered in tiles of :meth:`tile_size` (:mod:`.tiles`): an
        image of any size compiles no kernel of its own. At the tile size itself, the image
        of :meth:`render_refined` (the pixels ``python -m mi_amr render`` gives). Each tile
        has seeds of its own, so the tiles' noise does not repeat."""
        size, tile = (int(size[0]), int(size[1])), self.tile_size()
        if size == tile or self._tiling["principal"] is None:
            return self.render_refined(size, spp)
        edge = tiles.margin(self._tiling["radius"])
        passes = scene_passes(self.scene, spp)
        image = None
        try:
            for k, t in enumerate(tiles.layout(size, tile, edge)):
                self._aim_tile(size, tile, (t.x0, t.y0))
                accum = sum(self._pass(tile, dataclasses.replace(
                    p, seed=p.seed + k * len(passes))) * p.spp for p in passes)
                if image is None:
                    image = np.zeros((size[1], size[0], accum.shape[-1]), dtype=np.float32)
                rows, cols = t.taken()
                image[t.y_lo:t.y_hi, t.x_lo:t.x_hi] = (accum / spp)[rows, cols]
        finally:
            self._aim_tile(None, tile, None)
        return image

    def _aim_tile(self, size, tile, corner) -> None:
        """Film ``tile``, and the camera of the tile at ``corner`` of a ``size`` image
        (:func:`.tiles.tile_camera`); ``size`` None: the view's own camera again."""
        p, key, principal = self.params, self._tiling["sensor"], self._tiling["principal"]
        camera = self.state.camera
        if size is not None:
            fov, principal = tiles.tile_camera(camera.fov, principal, size, tile, corner)
            camera = dataclasses.replace(camera, fov=fov)
        self._write_sensor(camera, tile)
        p[f"{key}.principal_point_offset_x"] = float(principal[0])
        p[f"{key}.principal_point_offset_y"] = float(principal[1])
        self.params.update()
        self._film = tile

    def _pass(self, size, p: Pass) -> np.ndarray:
        """Pass ``p`` at the film size already written (a tile's camera kept)."""
        image = render_pass(mi, self.scene, p)
        dr.eval(image)
        dr.sync_thread()
        return np.array(image, dtype=np.float32)[..., :4]      # colour and alpha, no AOVs

    def close(self) -> None:
        import shutil

        self.prefetch.wait()
        shutil.rmtree(self.workdir, ignore_errors=True)


def slider_scale(quantiles) -> str:
    """The isovalue slider's scale for a field with these quantiles (evenly spaced, from the
    minimum to the maximum): ``"percentile"`` when the middle 90 % of the leaf cells span less
    than a tenth of the range (Q's useful values sit at the far edge of a linear slider),
    else ``"linear"``."""
    q = np.asarray(quantiles, dtype=np.float64)
    span = q[-1] - q[0]
    n = len(q) - 1
    middle = q[int(round(0.95 * n))] - q[int(round(0.05 * n))]
    return "percentile" if span > 0 and middle < 0.1 * span else "linear"


def _tiling(scene, params, sensor: str) -> dict:
    """What :meth:`Session.render_tiled` needs of the scene's camera: its key in ``params``,
    its principal point offset (None: a camera without one, which is not tiled) and its
    film's reconstruction filter radius (pixels)."""
    keys = [f"{sensor}.principal_point_offset_{a}" for a in "xy"]
    principal = tuple(float(np.ravel(params[k])[0]) for k in keys) \
        if all(k in params for k in keys) else None
    return {"sensor": sensor, "principal": principal,
            "radius": float(scene.sensors()[0].film().rfilter().radius())}


def _bands(widths, offsets, peaks) -> tuple:
    """``(band_width, band_offsets, band_peak)`` as the state holds them (per isovalue)."""
    pairs = tuple(tuple(o) for o in np.reshape(offsets, (-1, 2)).tolist())
    return tuple(widths), pairs, tuple(peaks)


def _default_bands(opt, values=None) -> tuple:
    """The bands a surface scene would get in volume mode: its band widths (one, or one per
    isovalue), or where ``values`` (the field's finite leaf values, sorted) are given, widths
    picked from them (:func:`~mi_amr.core.suggest.suggest_band_widths`); its peaks, and
    supports of +- 2 widths."""
    k = len(opt.isovalues)

    def per_iso(v):
        v = [float(x) for x in np.atleast_1d(v)]
        return v * k if len(v) == 1 else v

    widths = per_iso(opt.band_width) if values is None or not values.size else \
        _picked_widths(values, opt.isovalues)
    return _bands(widths, [(-2.0 * w, 2.0 * w) for w in widths], per_iso(opt.band_peak))


def _picked_widths(values, isovalues) -> list:
    """:func:`~mi_amr.core.suggest.suggest_band_widths` of ``isovalues`` from the sorted leaf
    ``values``, rounded to float32 as the scene's parameters hold them."""
    return [float(np.float32(w)) for w in suggest_band_widths(values, isovalues)]


def light_transform(direction) -> "mi.Transform4f":
    """The ``to_world`` Mitsuba's ``directional`` emitter builds from ``direction`` (the same
    frame about the axis, so a saved scene lights exactly as the view)."""
    d = mi.ScalarVector3f(*(float(x) for x in direction))
    up, _ = mi.coordinate_system(dr.normalize(d))
    return mi.Transform4f().look_at(origin=[0.0, 0.0, 0.0], target=list(d), up=list(up))

