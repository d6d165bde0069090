"""The render thread: the only thread that renders and changes the scene (the next step of a
time series is prepared meanwhile in a thread of its own, :mod:`.series`).

It shows the newest state only. A request that arrives while a frame renders replaces any
request still waiting (stale requests are dropped, never queued); the refinement of an image
stops at the next pass when a newer request arrives. Each new state is shown first as a fast
preview (1 spp at ``1 / scale`` of the view's size: ``preview_scale`` to start with, doubled
while a preview takes longer than ``preview_budget_s`` and halved back while one takes under a
sixth of it, see :meth:`RenderWorker.adapt_preview`), then, once no request has come
for ``idle_s`` seconds after the preview went out, refined to the state's ``spp`` at the view's
size in the passes ``python -m mi_amr render`` uses (so a saved scene renders the same pixels).

Compiled kernels are counted per cause (``Session.compiled``): ``warmup`` (the first preview
and refined frames), ``reloads`` (a new structure, up to its first refined frame),
``steps`` (a time step: another data file of the same fields, up to its first refined frame;
it stays 0),
``quality`` (a new refined sample count: Mitsuba's render loop specialises on it),
``preview_sizes`` (the first preview at a size the previews adapted to), ``saves``
(images saved: it stays 0, they are rendered in tiles of the view's film size) and
``controls`` (everything else: it stays 0).
"""

from __future__ import annotations

import threading
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr.errors import AMRError, print_traceback
from mi_amr.workflows.viewer.state import structure

# seconds: the longest a preview may take before the next ones are made smaller (the default of
# ``view --preview-budget``; a slider that answers within about this feels direct).
PREVIEW_BUDGET_S = 0.25
# the smallest preview: 1/8 of the view's side
MAX_PREVIEW_SCALE = 8


def png_bytes(image) -> bytes:
    """8-bit sRGB PNG of a linear RGB float image (the colour of an RGBA one: the page shows
    the film's black background), converted as
    :func:`mi_amr.workflows.movie.output.write_image_atomic` converts it."""
    image = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    bitmap = mi.Bitmap(image, pixel_format=mi.Bitmap.PixelFormat.RGB)
    bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    stream = mi.MemoryStream()
    bitmap.write(stream, mi.Bitmap.FileFormat.PNG, -1)
    return bytes(stream.raw_buffer())


def _compiled(history) -> int:
    """Kernels not found in memory (compiled now or loaded from Dr.Jit's disk cache)."""
    return sum(1 for k in history if k.get("type") == dr.KernelType.JIT and
               (not k.get("cache_hit", True) or k.get("cache_disk", False)))


class RenderWorker:
    """Runs ``make_session()`` and every render in one thread; ``publish(kind, payload,
    data)`` reports to the server (called from the render thread)."""

    def __init__(self, make_session, publish, *, preview_scale: int = 2, idle_s: float = 0.3,
                 preview_budget_s: float = PREVIEW_BUDGET_S):
        """``preview_budget_s``: see :meth:`adapt_preview` (0: the previews keep
        ``preview_scale``)."""
        self._make_session, self.publish = make_session, publish
        self.preview_scale, self.idle_s = max(1, int(preview_scale)), float(idle_s)
        self.preview_budget_s = float(preview_budget_s)
        self.scale = self.preview_scale         # the previews' scale now
        self._sizes = set()                     # the preview sizes rendered so far
        self._cond = threading.Condition()
        self._pending = None            # (state, version): the newest request not yet shown
        self._jobs = []
        self._refine = None             # (state, version) shown as a preview only
        self._preview_sent = 0.0
        self._stop = False
        self._fresh = None
        self.session = None
        self.error = None
        self.frames = {"preview": 0, "refined": 0}
        self.last_refined = None        # (version, image) of the newest refined frame
        self.dropped = 0
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._main, name="mi_amr-view-render", daemon=True)

    # ------------------------------------------------------------------ other threads
    def start(self) -> None:
        """Load the scene and render its first frames; raises the loader's AMRError."""
        self._thread.start()
        self._ready.wait()
        if self.error is not None:
            raise self.error

    def submit(self, state, version: int) -> None:
        with self._cond:
            if self._pending is not None:
                self.dropped += 1
            self._pending = (state, version)
            self._cond.notify()

    def job(self, fn) -> None:
        """Run ``fn(session)`` in the render thread before the next frame."""
        with self._cond:
            self._jobs.append(fn)
            self._cond.notify()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout=30)

    # ------------------------------------------------------------------ the render thread
    def _main(self) -> None:
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            self.session = self._make_session()
            self.fresh("warmup")
        except AMRError as e:
            self.error = e
        except Exception as e:  # reported to the command line, which exits with it
            self.error = AMRError(f"the viewer could not start: {e}")
            print_traceback()
        self._ready.set()
        if self.error is not None:
            return
        while True:
            kind, item = self._next()
            if kind == "stop":
                break
            try:
                if kind == "job":
                    item(self.session)
                elif kind == "show":
                    self._show(*item)
                else:
                    self._refine_now(*item)
            except AMRError as e:
                self.publish("error", {"message": str(e), "state": self.session.state,
                                       "version": item[1] if kind == "show" else None}, None)
            except Exception as e:   # a bug: say so on the page and keep serving
                print_traceback()
                self.publish("error", {"message": f"internal error: {e!r}", "version": None,
                                       "state": self.session.state}, None)
        self.session.close()

    def _next(self):
        """The next thing to do: a job, the newest request, or a due refinement."""
        with self._cond:
            while True:
                if self._stop:
                    return "stop", None
                if self._jobs:
                    return "job", self._jobs.pop(0)
                if self._pending is not None:
                    item, self._pending = self._pending, None
                    return "show", item
                if self._refine is not None:
                    wait = self._preview_sent + self.idle_s - time.perf_counter()
                    if wait <= 0:
                        item, self._refine = self._refine, None
                        return "refine", item
                    self._cond.wait(wait)
                else:
                    self._cond.wait()

    def _news(self) -> bool:
        with self._cond:
            return self._pending is not None or bool(self._jobs) or self._stop

    def counted(self, bucket: str, fn):
        """``fn()``, with the kernels it compiled added to ``session.compiled[bucket]``."""
        dr.kernel_history()
        try:
            return fn()
        finally:
            self.session.compiled[bucket] += _compiled(dr.kernel_history())

    def preview_size(self) -> tuple:
        w, h = self.session.resolution
        return max(1, w // self.scale), max(1, h // self.scale)

    def adapt_preview(self, seconds: float) -> None:
        """The next previews' scale after a preview that rendered in ``seconds`` (compiling
        nothing): doubled, up to :data:`MAX_PREVIEW_SCALE`, where it took longer than the
        budget; halved, down to ``preview_scale``, where it took under a sixth of it (a
        quarter of the pixels takes about a quarter of the time, so it does not swing back)."""
        if self.preview_budget_s <= 0:
            return
        if seconds > self.preview_budget_s:
            self.scale = min(2 * self.scale, MAX_PREVIEW_SCALE)
        elif seconds < self.preview_budget_s / 6:
            self.scale = max(self.scale // 2, self.preview_scale)

    def fresh(self, bucket: str) -> None:
        """Count what compiles from now until the next refined image under ``bucket``: the
        first preview and refined frames after a (re)load or a new sample count compile the
        kernels of their sizes and sample counts (the film size is a traversable value,
        compiled once per size)."""
        self._fresh = bucket

    def _bucket(self) -> str:
        return self._fresh or "controls"

    def ensure(self, state, version) -> None:
        """Show ``state`` now, when the scene does not show it yet (a job that needs it)."""
        if self.session.state != state:
            self._show(state, version)

    def _show(self, state, version) -> None:
        s = self.session
        t0 = time.perf_counter()
        reload = structure(state) != structure(s.state)
        step = state.data_file != s.state.data_file
        if reload:
            self.fresh("reloads")
        elif step:
            # A time step: the same kernels on another volume (counted apart, to show it
            # compiles nothing).
            self.fresh(self._fresh or "steps")
        elif state.spp != s.state.spp:
            self.fresh(self._fresh or "quality")
        how, shown = self.counted(self._bucket(), lambda: s.apply(state))
        if shown != state:
            self.publish("corrected", {"state": shown, "version": version}, None)
        size = self.preview_size()
        bucket = self._bucket() if self._fresh or size in self._sizes else "preview_sizes"
        compiled = sum(s.compiled.values())
        t_render = time.perf_counter()
        image = self.counted(bucket, lambda: s.render(size, 1, preview=True))
        if sum(s.compiled.values()) == compiled:
            self.adapt_preview(time.perf_counter() - t_render)
        self._sizes.add(size)
        self._send(image, version, "preview", 1, time.perf_counter() - t0)
        if reload or step:              # after the frame: a step's image comes first
            self.publish("info", {"how": how, "info": s.describe()}, None)
        s.prefetch_next()
        self._refine = (shown, version)
        self._preview_sent = time.perf_counter()

    def _refine_now(self, state, version) -> None:
        s = self.session
        t0 = time.perf_counter()
        image = self.counted(self._bucket(),
                             lambda: s.render_refined(s.resolution, state.spp, self._news))
        if image is None:
            with self._cond:
                if self._pending is None:       # only a job came: refine after it
                    self._refine = (state, version)
            return
        self.last_refined = (version, image)
        self._fresh = None
        self._send(image, version, "refined", state.spp, time.perf_counter() - t0)

    def _send(self, image, version, quality, spp, seconds) -> None:
        self.frames[quality] += 1
        header = {"version": version, "quality": quality, "spp": spp,
                  "width": int(image.shape[1]), "height": int(image.shape[0]),
                  "seconds": round(seconds, 4), "compiled": dict(self.session.compiled)}
        self.publish("frame", header, png_bytes(image))
