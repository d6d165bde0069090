"""The viewer's one shared state and the pages connected to it (every tab shows the same view
and sees every change), the page's requests, and the files it saves.

Runs in the server's event loop; Mitsuba work goes to the render thread
(:class:`~mi_amr.workflows.viewer.worker.RenderWorker`), whose reports come back through
:meth:`Hub.from_worker`. Each accepted change gets the next version number; frames carry the
version they show, so a page never replaces a newer image by an older one.
"""

from __future__ import annotations

import asyncio
import json
import re
import struct
import threading
from collections import deque
from pathlib import Path

from mi_amr.errors import AMRError, print_traceback
from mi_amr.workflows.viewer import bands, controls, tf2d
from mi_amr.workflows.viewer.paths import FileRules
from mi_amr.workflows.viewer.sceneio import MARK, scene_text, write_table
from mi_amr.workflows.viewer.series import step as step_to
from mi_amr.workflows.viewer.state import Session, structure
from mi_amr.workflows.viewer.worker import PREVIEW_BUDGET_S, RenderWorker

CHANGES = ("set", "camera", "add_isovalue", "remove_isovalue", "reset_color_range")
# The transfer-function editor's requests (volume mode: bands, the 2D transfer function).
EDITS = {"band": bands.change, "tf2d": tf2d.change}
COLORMAPS = ("viridis", "magma", "inferno", "plasma", "cividis", "turbo", "coolwarm",
             "RdBu_r", "Spectral_r", "gray")
KEYFRAME_STEP = 24
COALESCED = ("state", "info")   # only the newest of these is worth sending
MAX_WAITING = 64                # messages waiting for a page before it is disconnected
SEND_TIMEOUT_S = 20.0           # a page that takes no message for this long is disconnected
MAX_REQUEST = 1 << 16           # characters of one request
MAX_NESTING = 8                 # lists and objects inside one another in a request
MAX_DIGITS = 24                 # of an integer in a request
MAX_REPLY = 300                 # characters of an error message sent back
_BRACKETS = re.compile(r"[\[\]{}]")
MAX_SIDE = 4096                 # a saved image's side: one render pass must fit in memory


class Client:
    """One connected page and what waits to be sent to it, bounded: the newest state and info
    replace any not sent yet (newest state wins), at most one frame waits (a newer frame
    replaces it), and at most :data:`MAX_WAITING` other messages. A page that lets more pile
    up, or does not take a message within ``send_timeout_s`` seconds (default
    :data:`SEND_TIMEOUT_S`), is not reading: it is disconnected (:meth:`pump` returns)."""

    def __init__(self, ws, send_timeout_s: float = SEND_TIMEOUT_S):
        self.ws = ws
        self.send_timeout_s = send_timeout_s
        self.messages = deque()
        self.frame = None
        self.wake = asyncio.Event()
        self.dropped = None         # why the page was disconnected (None: it was not)

    def post(self, message: dict) -> None:
        if self.dropped is not None:
            return
        if message.get("type") in COALESCED:
            kind = message["type"]
            self.messages = deque(m for m in self.messages if m.get("type") != kind)
        self.messages.append(message)
        if len(self.messages) > MAX_WAITING:
            self.drop(f"more than {MAX_WAITING} messages waiting")
        self.wake.set()

    def post_frame(self, data: bytes) -> None:
        if self.dropped is None:
            self.frame = data
            self.wake.set()

    def drop(self, why: str) -> None:
        """Stop sending to this page (:meth:`pump` returns; the server closes it)."""
        self.dropped = why
        self.messages.clear()
        self.frame = None
        self.wake.set()

    async def pump(self) -> None:
        """Send what waits, in order, until the page is dropped or gone; each send must finish
        within :attr:`send_timeout_s` (a page that does not read stops the sends: the socket's
        buffer fills). A send that fails (the page closed its socket meanwhile) ends the pump
        quietly: the page's own request loop sees the close."""
        while self.dropped is None:
            await self.wake.wait()
            self.wake.clear()
            while self.dropped is None and (self.messages or self.frame is not None):
                if self.messages:
                    send = self.ws.send_text(json.dumps(self.messages.popleft()))
                else:
                    data, self.frame = self.frame, None
                    send = self.ws.send_bytes(data)
                try:
                    await asyncio.wait_for(send, self.send_timeout_s)
                except asyncio.TimeoutError:
                    self.drop(f"a message not taken within {self.send_timeout_s:g} s")
                except Exception:       # (the server's disconnect or closed-socket error)
                    self.messages.clear()
                    self.frame = None
                    return


class Hub:
    """The viewer of ``scene_path``: file rules, the render thread, the shared state."""

    def __init__(self, scene_path, *, out_dir="out", files=(), resolution=None, spp: int = 4,
                 preview_scale: int = 2, idle_s: float = 0.3, series=(),
                 preview_budget_s: float = PREVIEW_BUDGET_S):
        self.rules = FileRules(scene_path, files, out_dir)
        self.series = [str(f) for f in series]
        self.series_spec = ""           # the series as given on the command line (for hints)
        self.worker = RenderWorker(lambda: Session(scene_path, resolution=resolution, spp=spp,
                                                   series=self.series),
                                   self.from_worker, preview_scale=preview_scale, idle_s=idle_s,
                                   preview_budget_s=preview_budget_s)
        self.clients = set()
        self.loop = None
        self._early = []                # reports that came before the event loop ran
        self._loop_lock = threading.Lock()
        self.version = 0
        self.last_frame = None          # the newest frame sent, for a page that connects

    def start(self) -> None:
        """Load the scene and render its first frames (in the render thread)."""
        self.worker.start()
        session = self.worker.session
        self.state = session.state
        self._set_info(session.describe())
        self.worker.submit(self.state, self.version)

    def _set_info(self, info: dict) -> None:
        self.info = info
        self.ctx = controls.Context(
            value_range=info["value_range"], color_data_range=info["color_data_range"],
            fields=info["fields"], home=info["home"], up=info["up"],
            resolution=info["resolution"], plane=tf2d.plane_of(info))

    # ------------------------------------------------------------------ what pages see
    def state_message(self) -> dict:
        s = self.state
        light = None
        if s.light_direction is not None:
            az, el = controls.light_angles(s.light_direction, self.ctx.up)
            light = {"azimuth": az, "elevation": el, "strength": max(s.light_irradiance)}
        return {"type": "state", "version": self.version, "state": {
            "data_file": self._shown_path(s.data_file), "field": s.field,
            "color_field": s.color_field, "colormap": s.colormap,
            "color_range": s.color_range, "isovalues": s.isovalues,
            "iso_colors": [controls.linear_to_hex(c) for c in s.iso_colors],
            "iso_opacity": s.iso_opacity, "mode": s.mode, "method": s.method,
            "reconstruction": s.reconstruction, "layers": s.layers, "step_scale": s.step_scale,
            "band_width": s.band_width[0], "bands": {
                "width": s.band_width, "offsets": s.band_offsets, "peak": s.band_peak},
            "shadows": s.shadows, "camera": s.camera.as_dict(),
            "light": light, "spp": s.spp, "structure": list(structure(s)),
            "tf2d": None if s.tf2d is None else s.tf2d.as_dict()}}

    def info_message(self) -> dict:
        from mi_amr import params

        i = self.info
        return {"type": "info", "scene": self._shown_path(i["scene"]),
                "value_range": i["value_range"], "color_data_range": i["color_data_range"],
                "histogram": i["histogram"], "fields": i["fields"],
                "quantiles": i["quantiles"], "slider_scale": i["slider_scale"],
                "histogram2d": i["histogram2d"],
                "methods": params.METHODS, "reconstructions": params.RECONSTRUCTIONS,
                "layer_modes": params.LAYER_MODES,
                "modes": params.MODES, "colormaps": COLORMAPS, "files": self.rules.listing(),
                "out_dir": str(self.rules.out_dir), "resolution": i["resolution"],
                "preview_scale": self.worker.preview_scale,
                "preview_budget_s": self.worker.preview_budget_s,
                "max_isovalues": params.MAX_ISOVALUES,
                "series": [self._shown_path(f) for f in self.series]}

    def status(self) -> dict:
        session = self.worker.session
        return {"version": self.version, "compiled": dict(session.compiled),
                "preview_scale": self.worker.scale,
                "frames": dict(self.worker.frames), "dropped": self.worker.dropped,
                "clients": len(self.clients), "resolution": list(session.resolution),
                "prepared": session.prefetch.finished()}

    def _shown_path(self, path) -> str:
        p = Path(path)
        try:
            return str(p.relative_to(self.rules.root))
        except ValueError:
            return str(p)

    def broadcast(self, message: dict) -> None:
        for c in list(self.clients):
            c.post(message)

    # ------------------------------------------------------------------ connections
    def connect(self, ws) -> Client:
        client = Client(ws)
        self.clients.add(client)
        client.post(self.info_message())
        client.post(self.state_message())
        if self.last_frame is not None:
            client.post_frame(self.last_frame)
        return client

    def disconnect(self, client: Client) -> None:
        self.clients.discard(client)

    async def handle(self, client: Client, text) -> None:
        """One request from a page; a mistake is answered with a one-line message that does
        not repeat the request, never a crash."""
        msg = {}
        try:
            msg = parse_request(text)
            op = msg.get("op")
            if not isinstance(op, str):
                raise AMRError(f"a request needs an 'op' (text), got {controls.shown(op)}")
            if op in CHANGES:
                self._change(controls.change(self.state, msg, self.ctx))
            elif op in EDITS:
                self._change(EDITS[op](self.state, msg, self.ctx))
            elif op in ACTIONS:
                ACTIONS[op](self, client, msg)
            else:
                raise AMRError(f"unknown request {controls.shown(op)}")
        except AMRError as e:
            client.post(error_message(e))
        except (OSError, UnicodeError) as e:     # the disk, or a file that is not text
            client.post(error_message(f"{msg.get('op')}: {type(e).__name__}: {e}"))
        except Exception as e:           # a bug: report it and keep serving
            print_traceback()
            client.post(error_message(f"internal error: {type(e).__name__}"))

    def _change(self, new) -> None:
        if new == self.state:
            return
        if structure(new) != structure(self.state):
            self.broadcast({"type": "notice", "message":
                            "Loading the scene again: method, reconstruction, layers, mode, fields and "
                            "the number of isovalues are part of the kernels' structure, so "
                            "this compiles them once (a few seconds)."})
        self.version += 1
        self.state = new
        self.worker.submit(new, self.version)
        self.broadcast(self.state_message())

    def _adopt(self, state) -> None:
        self.state = state
        self.broadcast(self.state_message())

    # ------------------------------------------------------------------ the render thread
    def from_worker(self, kind: str, payload: dict, data) -> None:
        """A report from the render thread (called there): handled in the event loop, or kept
        until it runs (the first frame can be ready before the server has started)."""
        with self._loop_lock:
            loop = self.loop
            if loop is None:
                self._early.append((kind, payload, data))
                return
        loop.call_soon_threadsafe(self._report, kind, payload, data)

    def attach(self, loop) -> None:
        """Handle the render thread's reports in ``loop`` (the server's, from within it), the
        ones kept before it ran first."""
        with self._loop_lock:
            self.loop = loop
            early, self._early = self._early, []
        for report in early:
            loop.call_soon(self._report, *report)

    def _report(self, kind, payload, data) -> None:
        if kind == "frame":
            head = json.dumps(payload).encode()
            frame = struct.pack("<I", len(head)) + head + data
            self.last_frame = frame
            for c in list(self.clients):
                c.post_frame(frame)
        elif kind == "reply":
            payload["client"].post(payload["message"])
        elif kind == "opened":
            self._set_info(payload["info"])
            self.broadcast(self.info_message())
            self._adopt(payload["state"])
            self.version += 1
            self.worker.submit(self.state, self.version)
        elif kind == "corrected" and payload["version"] == self.version:
            self._adopt(payload["state"])
        elif kind == "error":
            # The newest change failed: the pages go back to what the scene shows.
            if payload["version"] == self.version:
                self._adopt(payload["state"])
            self.broadcast(error_message(payload["message"]))
        elif kind == "info":
            self._set_info(payload["info"])
            self.broadcast(self.info_message())
            if payload["how"] == "reload":
                self.broadcast({"type": "notice", "message": "Scene loaded again; its first "
                                "frames compile the kernels of the new structure."})


# ---------------------------------------------------------------------- requests

class _Refused(ValueError):
    """A request refused while it is parsed (the reason is the message)."""


def _integer(text: str) -> int:
    if len(text.lstrip("-")) > MAX_DIGITS:
        raise _Refused(f"a number has {len(text)} digits (at most {MAX_DIGITS})")
    return int(text)


def _constant(name: str):
    raise _Refused(f"{name} is not a JSON number")


def parse_request(text) -> dict:
    """A page's request: a JSON object of at most :data:`MAX_REQUEST` characters, lists and
    objects at most :data:`MAX_NESTING` deep, integers of at most :data:`MAX_DIGITS` digits
    (checked before or while parsing, so no request costs more than its size). An
    :class:`AMRError` says why a request is refused."""
    if not isinstance(text, str):
        raise AMRError("a request must be a JSON object sent as text")
    if len(text) > MAX_REQUEST:
        raise AMRError(f"a request has {len(text)} characters (at most {MAX_REQUEST})")
    # Brackets bound the nesting before the parser (which recurses) sees it.
    if text.count("[") + text.count("{") > MAX_REQUEST // 64:
        raise AMRError(f"a request holds more than {MAX_REQUEST // 64} lists and objects")
    if _depth(text) > MAX_NESTING:
        raise AMRError(f"a request may nest lists and objects {MAX_NESTING} deep at most")
    try:
        msg = json.loads(text, parse_int=_integer, parse_constant=_constant)
    except _Refused as e:
        raise AMRError(f"a request was refused: {e}") from None
    except (ValueError, RecursionError):
        raise AMRError("a request must be a JSON object (text)") from None
    if not isinstance(msg, dict):
        raise AMRError("a request must be a JSON object (text)")
    return msg


def _depth(text: str) -> int:
    """How deep brackets nest in ``text`` (brackets inside JSON strings count too: a bound,
    not a parse)."""
    depth = deepest = 0
    for m in _BRACKETS.finditer(text):
        depth += 1 if m.group() in "[{" else -1
        deepest = max(deepest, depth)
    return deepest


def error_message(error) -> dict:
    """The ``error`` message for a page: one line of at most :data:`MAX_REPLY` characters."""
    text = " ".join(str(error).split())
    if len(text) > MAX_REPLY:
        text = text[:MAX_REPLY - 3] + "..."
    return {"type": "error", "message": text}


# ---------------------------------------------------------------------- files

def _confirm(client, msg, path) -> bool:
    """True when ``path`` may be written: it does not exist, or the page confirmed."""
    if path.exists() and msg.get("overwrite") is not True:
        request = {k: msg[k] for k in ("op", "name", "width", "height") if k in msg}
        client.post({"type": "confirm", "request": dict(request, overwrite=True),
                     "message": f"{path.name} exists in {path.parent}. Replace it?"})
        return False
    return True


def _size(msg, hub) -> tuple:
    w, h = msg.get("width"), msg.get("height")
    if w in (None, "") and h in (None, ""):
        return tuple(hub.worker.session.resolution)
    return (controls.integer(w, "width", 1, MAX_SIDE),
            controls.integer(h, "height", 1, MAX_SIDE))


def save_scene(hub: Hub, client: Client, msg: dict) -> None:
    from mi_amr.core.atomic import check_output, replacing

    path = hub.rules.output(msg.get("name"), (".xml",))
    size = _size(msg, hub)
    if not _confirm(client, msg, path):
        return
    check_output(path, overwrite=True)
    text = scene_text(hub.worker.session.base_path, hub.state, spp=hub.state.spp,
                      resolution=size, tf2d_file=write_table(path, hub.state))
    try:
        with replacing(path) as tmp:
            tmp.write_text(text)
    except OSError as e:
        raise AMRError(f"save: cannot write {path} ({e.strerror or e}); any existing file is "
                       f"unchanged") from None
    client.post({"type": "saved", "what": "scene", "path": str(path),
                 "message": f"Saved the scene to {path}; render it with: python -m mi_amr "
                            f"render {path} -o image.png"})


def save_image(hub: Hub, client: Client, msg: dict) -> None:
    from mi_amr.core.atomic import check_output
    from mi_amr.workflows.movie.output import write_image_atomic

    path = hub.rules.output(msg.get("name"), (".png", ".exr"))
    size = _size(msg, hub)
    if not _confirm(client, msg, path):
        return
    check_output(path, overwrite=True)
    state, version, worker = hub.state, hub.version, hub.worker

    def job(session):
        worker.ensure(state, version)
        last = getattr(worker, "last_refined", None)
        if last is not None and last[0] == version and size == tuple(session.resolution):
            image = last[1]
        else:
            image = worker.counted("saves", lambda: session.render_tiled(size, state.spp))
        try:
            write_image_atomic(path, image, "image")
        except AMRError as e:           # a full disk; the writer's message names the file
            worker.publish("reply", {"client": client, "message": error_message(
                f"save: {e}; any existing file is unchanged")}, None)
            return
        worker.publish("reply", {"client": client, "message": {
            "type": "saved", "what": "image", "path": str(path),
            "message": f"Saved {size[0]}x{size[1]} at {state.spp} spp to {path}"}}, None)

    client.post({"type": "notice", "message": f"Rendering {path.name} ..."})
    worker.job(job)


def add_keyframe(hub: Hub, client: Client, msg: dict) -> None:
    from mi_amr.workflows.movie.spec import append_keyframe, read_keyframes

    path = hub.rules.output(msg.get("name"), (".toml", ".json"))
    frame = msg.get("frame")
    if frame in (None, ""):
        keys = read_keyframes(path) if path.exists() else []
        frame = keys[-1]["frame"] + KEYFRAME_STEP if keys else 0
    frame = controls.integer(frame, "keyframe frame", 0, 10 ** 7)
    s = hub.state
    scene = keyframe_scene(hub, path)
    step = hub.series.index(s.data_file) if s.data_file in hub.series else None
    try:
        append_keyframe(path, frame, camera=s.camera.as_dict(), isovalue=s.isovalues[0],
                        color_range=s.color_range, step=step)
    except OSError as e:
        raise AMRError(f"keyframe: cannot write {path} ({e.strerror or e})") from None
    files = f" --files '{hub.series_spec}'" if step is not None and hub.series_spec else ""
    client.post({"type": "saved", "what": "keyframe", "path": str(path),
                 "next_frame": frame + KEYFRAME_STEP,
                 "message": f"Added keyframe {frame} to {path}; {scene.name} beside it holds "
                            f"the view's colours and styling (python -m mi_amr movie {scene} "
                            f"--keyframes {path}{files} -o movie)"})


def keyframe_scene(hub: Hub, keyframes: Path) -> Path:
    """Write the view as a scene beside the keyframe file (``keyframes.toml`` ->
    ``keyframes.xml``): what the keyframes do not record (colour map, styling, bands, method)
    is the page's, so ``movie`` on this scene renders the colours the page showed. A file of
    that name that the viewer did not write is kept (refused)."""
    from mi_amr.core.atomic import replacing

    path = keyframes.with_suffix(".xml")
    if path.exists() and MARK not in path.read_text(errors="replace")[:2000]:
        raise AMRError(f"{path} exists and was not written by the viewer; it is kept. Name "
                       f"the keyframe file otherwise")
    text = scene_text(hub.worker.session.base_path, hub.state, spp=hub.state.spp,
                      resolution=tuple(hub.worker.session.resolution),
                      tf2d_file=write_table(path, hub.state))
    with replacing(path) as tmp:
        tmp.write_text(text)
    return path


def open_file(hub: Hub, client: Client, msg: dict) -> None:
    path = hub.rules.openable(msg.get("path"))
    if path.suffix.lower() != ".xml":
        hub._change(hub.state.replace(data_file=str(path)))
        return
    worker, spp = hub.worker, hub.state.spp

    def job(session):
        session.open(path, resolution=session.resolution, spp=spp)
        worker.fresh("reloads")
        worker.publish("opened", {"state": session.state, "info": session.describe()}, None)

    hub.broadcast({"type": "notice", "message": f"Opening {path.name} ..."})
    worker.job(job)


ACTIONS = {"save_scene": save_scene, "save_image": save_image, "add_keyframe": add_keyframe,
           "open": open_file, "step": step_to}
