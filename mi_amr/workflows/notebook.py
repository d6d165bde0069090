"""Jupyter (JupyterLab, VS Code's notebooks, anything that shows ``_repr_png_`` and
``_repr_html_``): :func:`show` renders a scene or a data file into an :class:`Image` the
notebook draws inline, and :func:`explore` serves the viewer (:mod:`mi_amr.workflows.viewer`,
the same page and controls as ``python -m mi_amr view``) from a background thread and shows it
in the output cell as an iframe of its URL.
"""

from __future__ import annotations

import contextlib
import threading
from pathlib import Path

import numpy as np

from mi_amr.errors import AMRError

RESOLUTION = (512, 384)       # pixels (width, height) of show()
IFRAME_HEIGHT = 720           # pixels: the viewer page's controls and image
START_TIMEOUT_S = 60.0        # the server thread has this long to listen


class Image:
    """A rendered image: linear RGBA float32 pixels ``(height, width, 4)``, alpha the
    coverage by surfaces. A notebook shows it as an 8-bit sRGB PNG with alpha."""

    def __init__(self, pixels: np.ndarray):
        self._pixels = np.ascontiguousarray(pixels, dtype=np.float32)

    def numpy(self) -> np.ndarray:
        """The linear RGBA pixels, ``(height, width, 4)`` float32 (a copy)."""
        return self._pixels.copy()

    @property
    def size(self) -> tuple:
        """``(width, height)`` in pixels."""
        return self._pixels.shape[1], self._pixels.shape[0]

    def png(self) -> bytes:
        """The image as PNG bytes (8-bit sRGB, alpha kept), as ``render -o x.png`` writes."""
        import mitsuba as mi

        bitmap = mi.Bitmap(self._pixels, pixel_format=mi.Bitmap.PixelFormat.RGBA)
        bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGBA, mi.Struct.Type.UInt8,
                                srgb_gamma=True)
        stream = mi.MemoryStream()
        bitmap.write(stream, mi.Bitmap.FileFormat.PNG, -1)
        return bytes(stream.raw_buffer())

    def _repr_png_(self) -> bytes:
        return self.png()

    def __repr__(self) -> str:
        return f"Image({self.size[0]}x{self.size[1]} RGBA)"


def _refuse_data_options(scene, given: dict) -> None:
    """One error where ``scene`` (a scene, or its file) was given with any of ``given``: the
    keyword arguments only a data file's scene takes (None, or False for a switch: not
    given)."""
    named = [k for k, v in given.items() if v is not None and v is not False]
    if named:
        verb = "applies" if len(named) == 1 else "apply"
        raise AMRError(f"{scene}: {', '.join(n + '=' for n in named)} {verb} to data files "
                       f"only; a scene renders with its own values (its amr_iso parameters, "
                       f"or mi.traverse on the loaded scene)")


def _variant(variant):
    """Set ``variant`` (default: the one set, else ``llvm_ad_rgb``) and register amr_iso."""
    import mitsuba as mi

    from mi_amr.plugin.integrator import register

    variant = variant or mi.variant() or "llvm_ad_rgb"
    if variant not in mi.variants():
        raise AMRError(f"variant '{variant}' is not available; choose from {mi.variants()}")
    if mi.variant() != variant:
        mi.set_variant(variant)
    register()
    return mi


def show(scene_or_file, field=None, isovalue=None, resolution=None, spp: int = 4, *,
         variant=None, **params) -> Image:
    """Render ``scene_or_file`` and return the :class:`Image`. It may be a loaded Mitsuba
    scene or a scene dict (rendered with their own camera and film), a scene ``.xml`` file
    (its own camera, its film at ``resolution`` (width, height) where given), or a data file
    or :class:`~mi_amr.AMRVolume` read from one, which gets the scene of :func:`mi_amr.scene`
    (``field``, ``isovalue``, ``resolution``, default :data:`RESOLUTION`, and ``params``
    apply to it; to a scene they are refused, as they would change nothing). ``spp`` samples
    per pixel, in the passes ``render`` takes (so the pixels are the command line's)."""
    mi = _variant(variant)
    import drjit as dr

    from mi_amr.plugin.scene import load_dict, load_scene
    from mi_amr.workflows.datafile import is_scene_file
    from mi_amr.workflows.render import render_passes

    if int(spp) < 1:
        raise AMRError(f"spp must be >= 1, got {spp}")
    data_only = dict(field=field, isovalue=isovalue, **params)
    if isinstance(scene_or_file, (mi.Scene, dict)):
        _refuse_data_options("a scene", dict(data_only, resolution=resolution))
        scene = scene_or_file if isinstance(scene_or_file, mi.Scene) else \
            load_dict(scene_or_file)
    elif isinstance(scene_or_file, (str, Path)) and is_scene_file(scene_or_file):
        _refuse_data_options(scene_or_file, data_only)
        scene = load_scene(scene_or_file, pixel_format="rgba", film_size=resolution)
    else:
        from mi_amr.plugin.integrator import register
        from mi_amr.workflows.datafile import make_scene

        # (The field read for the isovalue pick goes on to the scene's load: read once.)
        made = make_scene(scene_or_file, field=field, isovalue=isovalue,
                          resolution=resolution or RESOLUTION, spp=spp,
                          sets_isovalue="isovalue=", offer=register().offer, **params)
        scene = load_dict(made.as_dict())
    pixels = render_passes(mi, dr, np, scene, int(spp), quiet=True)
    if pixels.shape[-1] == 3:           # a film without alpha: every pixel counts as covered
        pixels = np.concatenate([pixels, np.ones_like(pixels[..., :1])], axis=-1)
    return Image(pixels[..., :4])


class Explorer:
    """The viewer served from a background thread: :attr:`url`, shown in a notebook as an
    iframe; :meth:`close` stops the server (and removes the scene made for a data file)."""

    def __init__(self, url: str, server, thread, cleanup):
        self.url, self._server, self._thread, self._cleanup = url, server, thread, cleanup

    def _repr_html_(self) -> str:
        from html import escape

        return (f'<iframe src="{escape(self.url)}" width="100%" height="{IFRAME_HEIGHT}" '
                f'style="border:0"></iframe><p><a href="{escape(self.url)}" '
                f'target="_blank">{escape(self.url)}</a></p>')

    def __repr__(self) -> str:
        return f"Explorer({self.url})"

    def close(self) -> None:
        """Stop serving (the page's connection closes; nothing saved is touched)."""
        self._server.should_exit = True
        self._thread.join(timeout=30)
        self._cleanup.close()


def explore(scene_or_file, field=None, isovalue=None, *, port: int = 0,
            host: str = "127.0.0.1", out_dir="out", resolution=None, spp: int = 4,
            preview_scale: int = 2, variant=None, allow_nonfinite: bool = False,
            mode: str | None = None) -> Explorer:
    """Serve the viewer of ``scene_or_file`` (a scene ``.xml`` or a data file, which gets the
    scene of :func:`mi_amr.scene`, with NaN and Inf values kept as missing data where
    ``allow_nonfinite``, in ``mode`` ``"volume"`` where asked: a band about the isovalue, its
    width picked from the histogram) on ``host:port`` (``port`` 0: a free one) in a background
    thread, print its URL and return the :class:`Explorer` (a notebook shows the page). The
    page saves into ``out_dir`` as ``view --out`` does."""
    _variant(variant)
    import uvicorn

    from mi_amr.workflows.datafile import asked_params, is_scene_file, scene_file
    from mi_amr.workflows.viewer.hub import Hub
    from mi_amr.workflows.viewer.server import (MAX_MESSAGE, bind, check_port, create_app,
                                                host_warning)

    check_port(port)

    if is_scene_file(scene_or_file):
        _refuse_data_options(scene_or_file, dict(field=field, isovalue=isovalue, mode=mode,
                                                 allow_nonfinite=allow_nonfinite))
    cleanup = contextlib.ExitStack()
    try:
        scene = cleanup.enter_context(scene_file(scene_or_file, field=field, isovalue=isovalue,
                                                 sets_isovalue="isovalue=",
                                                 **asked_params(allow_nonfinite, mode)))
        warning = host_warning(host)
        if warning:
            print(warning, flush=True)
        sock = bind(host, port)
        cleanup.callback(sock.close)
        hub = Hub(scene, out_dir=out_dir, resolution=resolution, spp=spp,
                  preview_scale=preview_scale)
        hub.start()
        config = uvicorn.Config(create_app(hub, host), log_level="warning",
                                ws_max_size=MAX_MESSAGE, lifespan="on")
        server = uvicorn.Server(config)
        thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]},
                                  name="mi_amr-explore", daemon=True)
        thread.start()
        _wait_started(server, thread)
    except BaseException:
        cleanup.close()
        raise
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown}:{sock.getsockname()[1]}/"
    print(f"mi_amr viewer: {url}", flush=True)
    return Explorer(url, server, thread, cleanup)


def _wait_started(server, thread) -> None:
    import time

    deadline = time.monotonic() + START_TIMEOUT_S
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            server.should_exit = True
            raise AMRError("explore: the viewer's server did not start")
        time.sleep(0.02)
