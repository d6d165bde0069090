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

Every request must name this machine in its ``Host`` header (:func:`allowed_hosts`: the
loopback names, the ``--host`` address, the names given with ``--allow-host``, and with
``--host 0.0.0.0`` or ``::`` the machine's own names and addresses), and a WebSocket must come
from a page of the same origin, whose ``Origin`` names an allowed host too. So a web page from
elsewhere, open in the same browser, cannot drive the viewer, also not through DNS rebinding
(a foreign name that resolves to this machine is still a foreign name).
"""

# (No "from __future__ import annotations": FastAPI reads the WebSocket parameter's annotation
# at run time, and the class is imported inside create_app.)
import asyncio
import ipaddress
import re
import socket
import sys
import threading
import webbrowser
from contextlib import asynccontextmanager
from pathlib import Path
from urllib.parse import urlsplit

from mi_amr.errors import AMRError

STATIC = Path(__file__).with_name("static")
LOOPBACK = ("127.0.0.1", "localhost", "::1")
MAX_PORT = 65535            # TCP's largest port number
WILDCARD = ("0.0.0.0", "::")
HOST_NAME = re.compile(r"[a-z0-9_][a-z0-9_.:-]{0,252}")
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


def create_app(hub, host: str = "127.0.0.1", allow_hosts=()):
    """The FastAPI application serving ``hub`` (a :class:`~mi_amr.workflows.viewer.hub.Hub`
    already started) on ``host``, answering requests that name :func:`allowed_hosts`."""
    from fastapi import FastAPI, WebSocket
    from fastapi.responses import FileResponse, JSONResponse, Response
    from fastapi.staticfiles import StaticFiles

    @asynccontextmanager
    async def lifespan(app):
        hub.attach(asyncio.get_running_loop())
        yield
        hub.worker.stop()

    app = FastAPI(lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    allowed = allowed_hosts(host, allow_hosts)
    app.add_middleware(HostCheck, allowed=allowed)
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
        if not same_origin(ws.headers, allowed):
            await ws.close(code=1008)
            return
        await ws.accept()
        await _serve_client(hub, ws)

    return app


def allowed_hosts(host: str, extra=()) -> frozenset:
    """The names a request's ``Host`` may give (lower case, IPv6 without brackets): the
    loopback names, ``host`` and the names in ``extra`` (``--allow-host``); for a wildcard
    ``host`` (0.0.0.0, ::) also this machine's own names and addresses."""
    names = {_bare(n) for n in (*LOOPBACK, *extra)}
    if host in WILDCARD:
        names |= own_addresses()
    else:
        names.add(_bare(host))
    return frozenset(n for n in names if n)


def own_addresses() -> set:
    """This machine's host name, its fully qualified name, and the addresses they and its
    network interfaces have (what another machine could put in ``Host`` to reach it)."""
    names = {socket.gethostname(), socket.getfqdn()}
    for name in list(names):
        try:
            names |= {info[4][0] for info in socket.getaddrinfo(name, None)}
        except OSError:             # a name that does not resolve here
            pass
    names |= _interface_addresses()
    return {_bare(n) for n in names}


def _interface_addresses() -> set:
    """The interfaces' IPv4 and IPv6 addresses (Linux's /proc; elsewhere none: there
    ``--allow-host`` names them)."""
    found = set()
    try:
        trie = Path("/proc/net/fib_trie").read_text().splitlines()
        found |= {prev.split()[-1] for prev, line in zip(trie, trie[1:])
                  if "/32 host LOCAL" in line}
    except OSError:
        pass
    try:
        for line in Path("/proc/net/if_inet6").read_text().splitlines():
            h = line.split()[0]
            found.add(str(ipaddress.IPv6Address(bytes.fromhex(h))))
    except (OSError, ValueError, IndexError):
        pass
    return found


def _bare(name: str) -> str:
    """A host name or address as compared: lower case, no trailing dot, IPv6 without
    brackets."""
    return name.strip().lower().rstrip(".").removeprefix("[").removesuffix("]")


def host_of(value) -> str:
    """The host part of a ``Host`` header (``name``, ``name:port``, ``[v6]:port``), bare;
    "" when it cannot be read."""
    if not value:
        return ""
    try:
        return _bare(urlsplit("//" + value).hostname or "")
    except ValueError:
        return ""


def same_origin(headers, allowed) -> bool:
    """A WebSocket handshake from a page of this server, named by an allowed host (or from a
    client that sends no Origin, which no browser does)."""
    origin = headers.get("origin")
    if origin is None:
        return True
    try:
        parts = urlsplit(origin)
        named = _bare(parts.hostname or "")
    except ValueError:
        return False
    return parts.netloc.lower() == (headers.get("host") or "").lower() and named in allowed


class HostCheck:
    """ASGI middleware: HTTP requests and WebSockets whose ``Host`` is not allowed are
    refused (400, or the WebSocket closed before it opens: 403)."""

    def __init__(self, app, allowed):
        self.app, self.allowed = app, allowed

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        host = dict(scope["headers"]).get(b"host", b"").decode("latin-1")
        if host_of(host) in self.allowed:
            return await self.app(scope, receive, send)
        if scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008})
            return
        body = b"Invalid host header"
        await send({"type": "http.response.start", "status": 400,
                    "headers": [(b"content-type", b"text/plain"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


async def _serve_client(hub, ws) -> None:
    """Requests from one page, handled in order, and what goes to it (:meth:`Client.pump`):
    a page that stops reading is disconnected when the pump gives up."""
    client = hub.connect(ws)
    pump = asyncio.create_task(client.pump())
    try:
        while True:
            receive = asyncio.ensure_future(ws.receive())
            await asyncio.wait({receive, pump}, return_when=asyncio.FIRST_COMPLETED)
            if not receive.done():          # the pump gave up (or failed): drop the page
                receive.cancel()
                break
            message = receive.result()
            if message["type"] == "websocket.disconnect":
                break
            await hub.handle(client, message.get("text", message.get("bytes")))
    except Exception:               # the page went away mid-send
        pass
    finally:
        hub.disconnect(client)
        pump.cancel()
        if client.dropped is not None:
            print(f"viewer: disconnected a page that does not read ({client.dropped})",
                  file=sys.stderr, flush=True)


def check_port(port) -> None:
    """One error unless ``port`` is a whole number from 0 (a free one) to :data:`MAX_PORT`."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= MAX_PORT:
        raise AMRError(f"the port must be a whole number from 0 (a free one) to {MAX_PORT}, "
                       f"got {port!r}")


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (``port`` 0: a free one)."""
    check_port(port)
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
          variant: str = "llvm_ad_rgb", allow_hosts=(), preview_budget_s=None) -> None:
    """``python -m mi_amr view``: load ``scene``, serve the page until interrupted, to
    requests that name an allowed host (:func:`allowed_hosts`; ``allow_hosts``: the names
    given with ``--allow-host``). ``files``: globs or paths
    (:func:`~mi_amr.workflows.movie.spec.expand_files`) the page may open; their data files are
    the time steps of the scene (:mod:`.series`). ``preview_budget_s``: see
    :meth:`~mi_amr.workflows.viewer.worker.RenderWorker.adapt_preview` (None: its default)."""
    import mitsuba as mi
    import uvicorn

    from mi_amr.plugin.integrator import register
    from mi_amr.workflows.movie.spec import expand_files
    from mi_amr.workflows.viewer.hub import Hub
    from mi_amr.workflows.viewer.series import expand_series

    if variant not in mi.variants():
        raise AMRError(f"variant '{variant}' is not available; choose from {mi.variants()}")
    for name in allow_hosts:
        if not HOST_NAME.fullmatch(_bare(name)):
            raise AMRError(f"--allow-host {name!r}: expected a host name or an IP address "
                           f"(letters, digits, '.', '-', ':'), without a port or scheme")
    mi.set_variant(variant)
    register()

    warning = host_warning(host)
    if warning:
        print(warning, file=sys.stderr, flush=True)
        names = ", ".join(sorted(allowed_hosts(host, allow_hosts)))
        print(f"answering requests that name: {names} (more with --allow-host NAME)",
              file=sys.stderr, flush=True)
    listed = expand_files(list(files)) if files else []
    sock = bind(host, port)
    budget = {} if preview_budget_s is None else {"preview_budget_s": preview_budget_s}
    hub = Hub(scene, out_dir=out_dir, files=listed, resolution=resolution, spp=spp,
              preview_scale=preview_scale, series=expand_series(listed), **budget)
    hub.series_spec = ",".join(str(f) for f in files)
    print(f"loading {scene} ...", flush=True)
    hub.start()
    shown = f"[{host}]" if ":" in host else host
    url = f"http://{shown if host not in ('0.0.0.0', '::') else '127.0.0.1'}:" \
          f"{sock.getsockname()[1]}/"
    print(f"serving {url}  (saving to {hub.rules.out_dir}; Ctrl-C stops)", flush=True)
    if open_browser:
        threading.Timer(0.5, webbrowser.open, [url]).start()
    config = uvicorn.Config(create_app(hub, host, allow_hosts), log_level="warning",
                            ws_max_size=MAX_MESSAGE, lifespan="on")
    uvicorn.Server(config).run(sockets=[sock])
