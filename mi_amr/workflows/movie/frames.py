"""Rendering a movie's frames in one process: the scene is loaded once, and each frame only
changes kernel inputs through ``mi.traverse`` (camera, first isovalue, colour range) or points
the integrator at the frame's data file, so after the first frame nothing compiles. Told the
next frame's data file, the renderer prepares it in the background while this frame renders
(:class:`~mi_amr.workflows.prefetch.Prefetcher`).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError
from mi_amr.workflows.movie.output import write_image_atomic
from mi_amr.workflows.movie.spec import FrameSpec
from mi_amr.workflows.prefetch import Prefetcher


class FrameRenderer:
    """The scene ``scene_path`` at ``resolution`` ``(W, H)`` and ``spp``, with ``defines`` (as
    ``-D``) applied, on Mitsuba variant ``variant``."""

    def __init__(self, scene_path, *, resolution=None, spp=None, defines=None,
                 variant: str = "llvm_ad_rgb", series: int = 1):
        """``series``: the data files the movie shows (see :meth:`render_to`)."""
        import mitsuba as mi

        from mi_amr.plugin.scene import load_scene, use_variant

        use_variant(variant)
        from mi_amr.plugin.camera import scene_camera
        from mi_amr.plugin.integrator import register

        register().series_steps = max(1, int(series))     # (the scene's load prepares a step)
        self.mi = mi
        params = dict(defines or {})
        self.scene_path = Path(scene_path)
        # RGBA frames; size and samples set on the film and sampler, so the scene need not
        # have resx/resy/spp defaults.
        self.scene = load_scene(scene_path, pixel_format="rgba", film_size=resolution,
                                sample_count=spp, **params)
        self.integ = self.scene.integrator()
        if not hasattr(self.integ, "load_volume"):
            raise AMRError(f"{scene_path}: the scene's integrator is not amr_iso")
        self.params = mi.traverse(self.scene)
        self.camera = scene_camera(scene_path, params, self.scene).as_dict()
        self.file = None
        self.prefetch = Prefetcher()

    def base_camera(self) -> dict:
        """The scene's own camera (``origin``, ``target``, ``up``, ``fov``)."""
        return dict(self.camera)

    def show(self, spec: FrameSpec) -> dict:
        """Set the scene to frame ``spec``; returns the seconds the data file took to load (with
        its steps: read, derive, tree, device, ranges), or ``{}`` when it was already there."""
        from mi_amr.plugin.camera import Camera, set_camera

        timings = {}
        if spec.file is not None and spec.file != self.file:
            t0 = time.perf_counter()
            self.prefetch.wait()                    # it may be preparing this very file
            self.integ.load_volume(spec.file)       # its leaf ranges too (search_ready)
            timings = dict(self.integ.prep.timings, load=time.perf_counter() - t0)
            self.file = spec.file
            # A movie moves on through its files: what the steps shown before hold is freed
            # for the next step's load to reuse (a file shown again is loaded again).
            self.integ.preparations.retain([spec.file])
        p = self.params
        set_camera(p, Camera.from_dict(spec.camera or self.camera))
        if spec.isovalue is not None:
            iso = np.array(p["integrator.isovalue"]).ravel()
            iso[0] = spec.isovalue
            p["integrator.isovalue"] = self.mi.Float(iso.astype(np.float32))
        if spec.color_range is not None and "integrator.color_range" in p:
            p["integrator.color_range"] = self.mi.Float(np.asarray(spec.color_range, np.float32))
        p.update()
        return timings

    def render(self, spec: FrameSpec) -> np.ndarray:
        """Frame ``spec`` as a linear RGBA ``(H, W, 4)`` array; the sampler's seed is the frame
        number, so a frame is the same wherever it is rendered."""
        import drjit as dr

        self.show(spec)
        img = self.mi.render(self.scene, seed=spec.index)
        dr.eval(img)
        dr.sync_thread()
        return np.array(img, dtype=np.float32)

    def prepare_next(self, path) -> None:
        """Start preparing the data file ``path`` (the next frame's) in the background, unless
        it is the one shown or None."""
        if path is not None and str(path) != self.file:
            self.prefetch.start(self.integ, path)

    def render_to(self, spec: FrameSpec, path, next_file=None, series: int = 1) -> dict:
        """Render frame ``spec`` to ``path`` (written atomically), preparing ``next_file`` (the
        next frame's data file, if any) meanwhile; returns its timings (seconds: ``load`` and
        its steps when the data file changed -- what was left of it when it was prepared in
        the background --, ``frame``, ``write``) and the number of kernels compiled.
        ``series``: the movie's data files (a step's snapshot is written only where that many
        fit the cache: :class:`~mi_amr.kernels.prepared.Preparations`)."""
        import drjit as dr

        self.integ.preparations.series_steps = max(1, int(series))
        t0 = time.perf_counter()
        timings = self.show(spec)
        self.prepare_next(next_file)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        t1 = time.perf_counter()
        img = self.mi.render(self.scene, seed=spec.index)
        dr.eval(img)
        dr.sync_thread()
        image = np.array(img, dtype=np.float32)
        t2 = time.perf_counter()
        history = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        write_image_atomic(path, image)
        t3 = time.perf_counter()
        compiled = sum(1 for k in history if k["type"] == dr.KernelType.JIT and
                       (not k.get("cache_hit", False) or k.get("cache_disk", False)))
        return dict(timings, set=t1 - t0 - timings.get("load", 0.0), frame=t2 - t1,
                    write=t3 - t2, compiled=compiled)
