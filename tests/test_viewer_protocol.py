"""The viewer's WebSocket protocol and transport without a browser: what a hostile or broken
client can send (malformed requests, huge values, requests it never reads the replies of), which
hosts may drive it (DNS rebinding), and saving images at any size without compiling kernels.

One viewer serves the small scene of ``tests/test_viewer.py`` in its own process, as a user
starts it; the clients are :mod:`mi_amr.evaluation.viewer_client`. A few checks run in this
process on the parts alone (the bounded outgoing queue, the host rules, the tiles).
"""

import asyncio
import json
import re
import time

import numpy as np
import pytest

from test_viewer import RES, SPP, Viewer, write_scene

from mi_amr.evaluation.viewer_client import SilentClient, ViewerClient, handshake, rss_bytes

WAIT_S = 60.0


@pytest.fixture(scope="module")
def viewer(tmp_path_factory, variant):
    folder = tmp_path_factory.mktemp("viewer-protocol")
    v = Viewer(write_scene(folder / "scene"), folder / "out")
    yield v
    v.stop()


@pytest.fixture
def client(viewer):
    c = ViewerClient(viewer.url)
    assert c.until(lambda m: m["type"] == "state", WAIT_S) is not None
    yield c
    c.close()


def error_reply(client, request, timeout: float = WAIT_S) -> str:
    """Send ``request`` and return the error message it gets (fails when none comes)."""
    client.send(request)
    reply = client.until(lambda m: m["type"] == "error", timeout)
    assert reply is not None, f"no error reply to {str(request)[:80]!r}"
    return reply["message"]


def tracebacks(viewer) -> list:
    return [line for line in viewer.output if "Traceback" in line or "internal error" in line]


# ---------------------------------------------------------------------- requests

def test01_error_replies_never_echo_the_request(viewer, client):
    """A refused value is named in at most a few dozen characters: a client cannot make the
    replies as large as its requests (a megabyte echoed per request once grew the server by
    950 MB in 4 s)."""
    big = "9" * 60_000
    for request in ({"op": "set", "name": "isovalue", "value": big},
                    {"op": "set", "name": "isovalue", "value": "x" * 60_000},
                    {"op": "set", "name": "x" * 60_000, "value": 1},
                    {"op": "set", "name": "colormap", "value": "0: 1 1 " + "x" * 60_000},
                    {"op": "set", "name": "field", "value": "f" * 60_000},
                    {"op": "open", "path": "p" * 60_000},
                    {"op": "save_image", "name": "n" * 60_000},
                    {"op": "y" * 60_000},
                    {"op": "set", "name": "isovalue", "value": "v" * 1_000_000}):
        message = error_reply(client, request)
        assert len(message) <= 300, message[:400]
        assert "x" * 60 not in message and "9" * 60 not in message, message
        assert "\n" not in message


MALFORMED = [
    ("nested 100k deep", "[" * 100_000 + "]" * 100_000),
    ("nested objects", '{"a":' * 50_000 + "1" + "}" * 50_000),
    ("a 4000-digit integer", '{"op": "set", "name": "isovalue", "value": ' + "7" * 4000 + "}"),
    ("a 4000-digit index", '{"op": "set", "name": "isovalue", "value": 0.3, "index": '
                           + "1" * 4000 + "}"),
    ("a name sent as a list", {"op": "set", "name": ["isovalue"], "value": 0.3}),
    ("an op sent as a list", {"op": ["set"], "name": "isovalue", "value": 0.3}),
    ("an op sent as an object", {"op": {"a": 1}}),
    ("a path containing NUL", {"op": "open", "path": "data/sphere.npz\x00.png"}),
    ("a save name containing NUL", {"op": "save_image", "name": "a\x00.png"}),
    ("not JSON", "{op: set"),
    ("a JSON list", "[1, 2, 3]"),
    ("NaN", '{"op": "set", "name": "isovalue", "value": NaN}'),
    ("binary", b"\x00\xff" * 100),
    ("an empty text", ""),
    ("a colour as an object", {"op": "set", "name": "iso_color", "value": {"r": 1}}),
    ("a width as a list", {"op": "save_image", "name": "a.png", "width": [1], "height": 2}),
    ("a huge width", {"op": "save_image", "name": "a.png", "width": 1e300, "height": 2}),
    ("a keyframe frame as text", {"op": "add_keyframe", "name": "k.toml", "frame": "1_0"}),
    ("a camera action as a list", {"op": "camera", "action": ["orbit"], "dx": 0.1}),
    ("a colour range of texts", {"op": "set", "name": "color_range", "value": ["a", "b"]}),
]


@pytest.mark.parametrize("case,request_", MALFORMED, ids=[c for c, _ in MALFORMED])
def test02_malformed_requests_get_one_line_errors_and_no_traceback(viewer, client, case,
                                                                   request_):
    """Each malformed request gets one error line (not "internal error"), the socket stays
    open, and the viewer's log shows no traceback."""
    before = len(tracebacks(viewer))
    message = error_reply(client, request_)
    assert "internal error" not in message and "\n" not in message, message
    assert "unknown request" in error_reply(client, {"op": "ping"})  # still answering
    time.sleep(0.1)
    assert len(tracebacks(viewer)) == before, "".join(viewer.output[-40:])


@pytest.mark.parametrize("name,value,expected", [
    ("iso_color", "#-1-1-1", "is not a colour"),
    ("iso_color", "#12345g", "is not a colour"),
    ("iso_color", [-0.5, 0.2, 0.2], "is outside [0, 1000]"),
    ("colormap", "0.1: -1 0 0, 0.5: 1 1 1", "colours must lie in [0, 1000]"),
    ("colormap", "0.1: 1e39 0 0, 0.5: 1 1 1", "colours must lie in [0, 1000]"),
    ("spp", "1_000", "'1_000' is not a number"),
    ("spp", "2.5", "expected a whole number"),
    ("spp", " inf", "is not a number"),
    ("step_scale", "9.9999e-5", "is outside [0.0001, 64] as a 32-bit float"),
    ("iso_opacity", "1e-50", "is outside (0, 1] as a 32-bit float"),
])
def test03_values_are_read_strictly(viewer, client, name, value, expected):
    """Colours, colour maps and numbers are read as written (no negative or overflowing
    colours, no ``1_000``), and numbers the kernels hold as float32 are checked after the
    rounding, as the integrator checks them."""
    assert expected in error_reply(client, {"op": "set", "name": name, "value": value})


def test04_the_smallest_step_scale_the_control_takes_renders(viewer, client):
    """``step_scale 1e-4`` (the table's lower bound) passes the control and the integrator
    alike (its float32 is below 1e-4; once the integrator refused it after the control had
    taken it): a refined frame of the new version comes, and no error."""
    try:
        client.send({"op": "set", "name": "step_scale", "value": "1e-4"})
        state = client.until(lambda m: m["type"] in ("state", "error"), WAIT_S)
        assert state["type"] == "state", state
        version = state["version"]
        frame = client.until(lambda m: m["type"] == "error" or (
            m["type"] == "frame" and m["version"] >= version and m["quality"] == "refined"),
            WAIT_S)
        assert frame is not None and frame["type"] == "frame", frame
    finally:
        client.send({"op": "set", "name": "step_scale", "value": 0.5})
        client.until(lambda m: m["type"] == "state", WAIT_S)


# ---------------------------------------------------------------------- transport

def test05_a_client_that_never_reads_cannot_grow_the_server(viewer):
    """A client floods refused megabyte requests and valid changes and reads nothing: the
    viewer's memory grows by less than 50 MB, it keeps serving other pages, and prints no
    traceback."""
    rss0 = rss_bytes(viewer.proc.pid)
    silent = SilentClient(viewer.url)
    try:
        big = json.dumps({"op": "set", "name": "isovalue", "value": "9" * 1_000_000})
        for i in range(300):
            if not silent.send(big if i % 3 else json.dumps(
                    {"op": "set", "name": "isovalue", "value": 0.25 + 0.0001 * i})):
                break
        grown = rss_bytes(viewer.proc.pid) - rss0
        other = ViewerClient(viewer.url)
        try:
            assert other.until(lambda m: m["type"] == "state", WAIT_S) is not None
        finally:
            other.close()
    finally:
        silent.close()
    assert grown < 50e6, f"the viewer grew by {grown / 1e6:.0f} MB"
    assert not tracebacks(viewer), "".join(viewer.output[-40:])


def test06_the_outgoing_queue_is_bounded_and_a_stalled_page_is_dropped():
    """The hub's queue for one page: the newest state and info replace older ones, and a page
    that lets more than MAX_WAITING messages pile up, or takes none within its send timeout
    (SEND_TIMEOUT_S unless given), is dropped (its pump returns)."""
    from mi_amr.workflows.viewer import hub

    class Stalled:                      # a socket whose sends never finish
        async def send_text(self, text):
            await asyncio.Event().wait()

        send_bytes = send_text

    async def run():
        client = hub.Client(Stalled())
        for v in range(100):
            client.post({"type": "state", "version": v})
            client.post({"type": "info", "n": v})
        assert [m["type"] for m in client.messages] == ["state", "info"]   # newest of each
        assert client.messages[0]["version"] == 99 and client.dropped is None
        for i in range(hub.MAX_WAITING):
            client.post({"type": "error", "message": str(i)})
        assert client.dropped is not None and not client.messages

        stalled = hub.Client(Stalled(), send_timeout_s=0.2)
        stalled.post({"type": "notice", "message": "x"})
        await asyncio.wait_for(stalled.pump(), 10)
        assert stalled.dropped is not None

    asyncio.run(run())


def test06b_a_page_that_closes_during_a_send_ends_the_pump_quietly():
    """A page whose socket closes while a frame is being sent (the server raises its
    disconnect error from the send) ends the pump without an exception: it was left in the
    task, unretrieved, and asyncio printed its traceback on the viewer's stderr (a CI run's
    test05 caught it)."""
    from mi_amr.workflows.viewer import hub

    class Closing:                      # a socket closed by the page mid-send
        async def send_text(self, text):
            raise ConnectionResetError("the page went away")

        send_bytes = send_text

    async def run():
        client = hub.Client(Closing())
        client.post({"type": "notice", "message": "x"})
        client.post_frame(b"frame")
        await asyncio.wait_for(client.pump(), 10)
        assert not client.messages and client.frame is None

    asyncio.run(run())


# ---------------------------------------------------------------------- hosts

def test07_only_named_hosts_and_their_own_origin_may_open_the_socket(tmp_path, variant):
    """With ``--host 0.0.0.0``: a foreign Host is refused even with a matching Origin (DNS
    rebinding), as are a foreign Origin and HTTP requests naming a foreign host; the loopback
    names, this machine's name and ``--allow-host`` names are answered."""
    import socket
    import urllib.error
    import urllib.request

    from mi_amr.evaluation.viewer_client import ViewerProcess

    v = ViewerProcess(write_scene(tmp_path / "scene"), tmp_path / "out", "--host", "0.0.0.0",
                      "--allow-host", "viewer.test", "--resolution", "16", "16")
    try:
        port = v.url.rstrip("/").rsplit(":", 1)[1]
        assert handshake(v.url, f"attacker.example:{port}",
                         f"http://attacker.example:{port}") == 403
        assert handshake(v.url, f"localhost:{port}", "http://evil.example") == 403
        assert handshake(v.url, f"localhost:{port}", f"http://attacker.example:{port}") == 403
        for name in ("127.0.0.1", "localhost", "viewer.test", socket.gethostname()):
            assert handshake(v.url, f"{name}:{port}", f"http://{name}:{port}") == 101, name
        request = urllib.request.Request(v.url + "api/state",
                                         headers={"Host": f"attacker.example:{port}"})
        with pytest.raises(urllib.error.HTTPError, match="400"):
            urllib.request.urlopen(request, timeout=30)
        assert not list((tmp_path / "out").iterdir())
    finally:
        v.stop()


def test08_the_allowed_hosts():
    """The rules alone: the loopback names always; the --host address; with a wildcard host,
    this machine's names and addresses; --allow-host names; ports, case, brackets and a
    trailing dot do not matter; foreign names never."""
    import socket

    from mi_amr.workflows.viewer.server import allowed_hosts, host_of, same_origin

    local = allowed_hosts("127.0.0.1")
    assert {host_of(h) for h in ("127.0.0.1:80", "LOCALHOST.", "[::1]:8080")} <= local
    assert host_of(socket.gethostname()) not in local
    assert "attacker.example" not in local
    wild = allowed_hosts("0.0.0.0", ["Viewer.Test"])
    assert {"viewer.test", socket.gethostname().lower(), "127.0.0.1"} <= wild
    assert host_of("attacker.example:8080") not in wild
    assert allowed_hosts("192.0.2.7") == local | {"192.0.2.7"}
    ok = {"host": "localhost:8080", "origin": "http://localhost:8080"}
    assert same_origin(ok, local)
    assert not same_origin(dict(ok, origin="http://localhost:9999"), local)
    assert not same_origin({"host": "attacker.example:8080",
                            "origin": "http://attacker.example:8080"}, wild)


# ---------------------------------------------------------------------- saving at any size

def test09_saving_images_of_many_sizes_compiles_no_kernel(viewer, client):
    """Saved images are rendered in tiles of the view's size: five sizes (smaller, larger,
    other aspect ratios) compile no kernel in the viewer; each file has its size. (Once each
    size compiled kernels of its own, never freed: +97 MB for 100 sizes.)"""
    import mitsuba as mi

    before = viewer.compiled()
    for i, (w, h) in enumerate([(48, 32), (100, 70), (130, 129), (200, 50), (31, 97)]):
        client.send({"op": "save_image", "name": f"size{i}.png", "width": w, "height": h})
        reply = client.until(lambda m: m["type"] in ("saved", "error"), 300)
        assert reply is not None and reply["type"] == "saved", reply
        assert np.array(mi.Bitmap(str(viewer.out / f"size{i}.png"))).shape[:2] == (h, w)
    after = viewer.compiled()
    assert after["saves"] == before["saves"], (before, after)
    assert sum(after.values()) == sum(before.values()), (before, after)


def test10_a_tiled_image_is_the_image_of_a_whole_render(tmp_path, variant):
    """A 100 x 70 image rendered in 64 x 64 tiles against one render at 100 x 70 (16 spp, other
    noise): mean difference far below a one-pixel shift of the image, and of the blurred
    images within noise."""
    from mi_amr.workflows.viewer.state import Session

    session = Session(write_scene(tmp_path / "scene"), resolution=RES, spp=SPP)
    try:
        tiled = session.render_tiled((100, 70), 16)
        whole = session.render_refined((100, 70), 16)
    finally:
        session.close()
    assert tiled.shape == whole.shape == (70, 100, 4)      # RGBA, as render writes
    shift = np.abs(whole[:, 1:] - whole[:, :-1]).mean()
    assert np.abs(tiled - whole).mean() < 0.15 * shift, (np.abs(tiled - whole).mean(), shift)


def test11_tiles_cover_the_image_once():
    """Every pixel of the image is taken from exactly one tile, from inside its margins."""
    from mi_amr.workflows.viewer import tiles

    for size, tile, edge in [((100, 70), (64, 64), 2), ((31, 97), (64, 64), 2),
                             ((4096, 3), (512, 512), 0), ((5, 5), (5, 5), 2)]:
        if tile[0] - 2 * edge < 1:
            with pytest.raises(ValueError):
                tiles.layout(size, tile, edge)
            continue
        count = np.zeros(size[::-1], dtype=int)
        for t in tiles.layout(size, tile, edge):
            rows, cols = t.taken()
            assert rows.start >= edge and cols.start >= edge
            assert rows.stop <= tile[1] - edge and cols.stop <= tile[0] - edge
            count[t.y_lo:t.y_hi, t.x_lo:t.x_hi] += 1
        assert np.all(count == 1), size


# ---------------------------------------------------------------------- a full disk

def test12_a_full_disk_on_save_is_one_error_line(viewer, tmp_path, variant):
    """Saving where the system refuses the bytes answers one error line, no traceback, and
    leaves no file; the scene file and keyframe writers too. Here a file size limit of 0
    bytes (RLIMIT_FSIZE, while each request runs) refuses them: EFBIG, as a full disk gives
    ENOSPC, and a new empty file is still made, as on a full disk."""
    resource = pytest.importorskip("resource")
    from mi_amr.workflows.viewer import hub as hub_module

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    loop = asyncio.new_event_loop()
    sent = []

    class Page:
        def post(self, message):
            sent.append(message)

    h = hub_module.Hub(viewer.scene, out_dir=tmp_path / "out", resolution=(16, 16))
    h.start()
    try:
        h.attach(loop)
        # The image's kernels compiled first, with no limit: Dr.Jit writes each new kernel
        # into its cache, and under the limit its message about the refused cache write goes
        # to pytest's captured stderr, which refuses it too, and the save never answers.
        loop.run_until_complete(h.handle(Page(), json.dumps({"op": "save_image",
                                                             "name": "warm.png"})))
        end = time.monotonic() + WAIT_S
        while not any(m["type"] == "saved" for m in sent) and time.monotonic() < end:
            loop.run_until_complete(asyncio.sleep(0.05))
        (tmp_path / "out" / "warm.png").unlink()
        for request in ({"op": "save_scene", "name": "v.xml"},
                        {"op": "add_keyframe", "name": "k.toml"},
                        {"op": "save_image", "name": "v.png"}):
            n = len(sent)
            resource.setrlimit(resource.RLIMIT_FSIZE, (0, hard))
            try:
                loop.run_until_complete(h.handle(Page(), json.dumps(request)))
                end = time.monotonic() + WAIT_S
                while not any(m["type"] in ("error", "saved") for m in sent[n:]) and \
                        time.monotonic() < end:
                    loop.run_until_complete(asyncio.sleep(0.05))
            finally:
                resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
            errors = [m for m in sent[n:] if m["type"] == "error"]
            assert errors and re.search("File too large", errors[0]["message"]), sent[n:]
            assert "internal error" not in errors[0]["message"]
        assert not list((tmp_path / "out").iterdir())
    finally:
        h.worker.stop()
        loop.close()
