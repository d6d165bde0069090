"""The web app (FastAPI on Starlette, served by uvicorn): the page, its static files, one
WebSocket for requests, state and frames, and two small JSON endpoints.

=================  ==========================================================================
``GET /``          the page (``static/index.html``)
``GET /static/*``  its script and style sheet (package data; nothing else is served)
``WS /ws``         requests (JSON text) in; state, info, messages (JSON text) and frames out. A
                   frame is binary: a little-endian uint32 ``n``, ``n`` bytes of JSON header
                   (``version``, ``quality``, ``spp``, size, seconds, kernels compiled), a PNG
``GET /api/state`` the shared state (JSON)
``GET /api/status`` versions, frames rendered and dropped, kernels compiled by cause
=================  ==========================================================================

Only the same origin may open the WebSocket, and requests must name this machine (the
loopback names, or the ``--host`` address): a web page from elsewhere open in the same browser
cannot drive the viewer, also not through DNS rebinding.
"""

# (No "from __future__ import annotations": FastAPI reads the WebSocket parameter's annotation
# at run time, and the class is imported inside create_app.)
import asyncio
import socket
import sys
import threading
import webbrowser
from contextlib import asynccontextmanager
from pathlib import Path
from urllib.parse import urlsplit

from mi_amr.errors import AMRError

STATIC = Path(__file__).with_name("static")
LOOPBACK = ("127.0.0.1", "localhost", "::1", "[::1]")
MAX_MESSAGE = 1 << 20


def host_warning(host: str):
    """The warning printed for a ``--host`` that other machines can reach (None for the
    loopback)."""
    if host in LOOPBACK:
        return None
    return (f"warning: --host {host} serves the viewer to every machine that can reach this "
            f"one: anyone who can connect can change the view and write files in the output "
            f"folder. Prefer the default 127.0.0.1 and an SSH tunnel "
            f"(ssh -L 8080:127.0.0.1:8080 this-machine).")


def create_app(hub, host: str = "127.0.0.1"):
    """The FastAPI application serving ``hub`` (a :class:`~mi_amr.workflows.viewer.hub.Hub`
    already started)."""
    from fastapi import FastAPI, WebSocket
    from fastapi.responses import FileResponse, JSONResponse, Response
    from fastapi.staticfiles import StaticFiles
    from starlette.middleware.trustedhost import TrustedHostMiddleware

    @asynccontextmanager
    async def lifespan(app):
        hub.attach(asyncio.get_running_loop())
        yield
        hub.worker.stop()

    app = FastAPI(lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    wildcard = host in ("0.0.0.0", "::")
    app.add_middleware(TrustedHostMiddleware,
                       allowed_hosts=["*"] if wildcard else [*LOOPBACK, host])
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    no_cache = {"Cache-Control": "no-store"}

    @app.get("/")
    async def page():
        return FileResponse(STATIC / "index.html", headers=no_cache)

    @app.get("/favicon.ico")
    async def favicon():
        return Response(status_code=204)

    @app.get("/api/state")
    async def state():
        return JSONResponse(hub.state_message(), headers=no_cache)

    @app.get("/api/status")
    async def status():
        return JSONResponse(hub.status(), headers=no_cache)

    @app.websocket("/ws")
    async def ws_endpoint(ws: WebSocket):
        if not same_origin(ws.headers):
            await ws.close(code=1008)
            return
        await ws.accept()
        await _serve_client(hub, ws)

    return app


def same_origin(headers) -> bool:
    """A WebSocket handshake from a page of this server (or from a client that sends no
    Origin, which no browser does)."""
    origin = headers.get("origin")
    return origin is None or urlsplit(origin).netloc == headers.get("host")


async def _serve_client(hub, ws) -> None:
    client = hub.connect(ws)
    pump = asyncio.create_task(client.pump())
    try:
        while True:
            message = await ws.receive()
            if message["type"] == "websocket.disconnect":
                break
            await hub.handle(client, message.get("text"))
    except Exception:               # the page went away mid-send
        pass
    finally:
        hub.disconnect(client)
        pump.cancel()


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (``port`` 0: a free one)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as e:
        sock.close()
        raise AMRError(f"cannot listen on {host}:{port} ({e.strerror or e}); try another "
                       f"--port") from None
    sock.listen(64)
    return sock


def serve(scene, *, host: str = "127.0.0.1", port: int = 8080, open_browser: bool = True,
          out_dir="out", files=(), resolution=None, spp: int = 4, preview_scale: int = 2,
          variant: str = "llvm_ad_rgb") -> None:
    """``python -m mi_amr view``: load ``scene``, serve the page until interrupted. ``files``:
    globs or paths (:func:`~mi_amr.workflows.movie.spec.expand_files`) the page may open; their
    data files are the time steps of the scene (:mod:`.series`)."""
    import mitsuba as mi
    import uvicorn

    from mi_amr.plugin.integrator import register
    from mi_amr.workflows.movie.spec import expand_files
    from mi_amr.workflows.viewer.hub import Hub
    from mi_amr.workflows.viewer.series import expand_series

    if variant not in mi.variants():
        raise AMRError(f"variant '{variant}' is not available; choose from {mi.variants()}")
    mi.set_variant(variant)
    register()

    warning = host_warning(host)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    listed = expand_files(list(files)) if files else []
    sock = bind(host, port)
    hub = Hub(scene, out_dir=out_dir, files=listed, resolution=resolution, spp=spp,
              preview_scale=preview_scale, series=expand_series(listed))
    hub.series_spec = ",".join(str(f) for f in files)
    print(f"loading {scene} ...", flush=True)
    hub.start()
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown if host not in ('0.0.0.0', '::') else '127.0.0.1'}:" \
          f"{sock.getsockname()[1]}/"
    print(f"serving {url}  (saving to {hub.rules.out_dir}; Ctrl-C stops)", flush=True)
    if open_browser:
        threading.Timer(0.5, webbrowser.open, [url]).start()
    config = uvicorn.Config(create_app(hub, host), log_level="warning", ws_max_size=MAX_MESSAGE,
                            lifespan="on")
    uvicorn.Server(config).run(sockets=[sock])
