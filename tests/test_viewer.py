"""The browser explorer (``python -m mi_amr view``), driven in a real browser: Debian's chromium
through Playwright's Python package (never a downloaded browser).

One viewer serves a small scene (the analytic sphere at 64 x 64, coloured by its own field)
for the whole file, started as a user starts it, in its own process; its kernels are counted
there (``GET /api/status``). The tests share it, in order, like one person using the page.
Images are compared as the page shows them (8-bit sRGB PNG, decoded) with the reference
tolerance of ``tests/test_references.py``.

Skipped, with the reason, only where chromium is not installed (``.ci/setup`` installs it with
apt-get; Playwright itself is part of the test extra).
"""

import base64
import json
import re
import subprocess
import sys
import textwrap
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from test_references import RMSE

from mi_amr.evaluation.viewer_bench import CHROMIUM, ViewerProcess, chromium

RES = (64, 64)
SPP = 4
WAIT_MS = 60_000

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).is_file(),
    reason=f"Debian's chromium is not installed ({CHROMIUM} is missing; .ci/setup installs it "
           f"with apt-get, which could not install it on this machine)")

IMAGE = "[data-testid=image]"


# ---------------------------------------------------------------------- the viewer and browser

def write_scene(folder: Path) -> Path:
    """The analytic sphere (f = |p - c|, isosurface 0.3 a sphere of radius 0.3) coloured by f
    with a matplotlib map, with a directional light and shadows."""
    from mi_amr.synthetic import datasets

    (folder / "data").mkdir(parents=True)
    datasets.sphere(16).save(folder / "data" / "sphere.npz")
    datasets.sphere(8).save(folder / "data" / "sphere_coarse.npz")
    datasets.sphere(8).save(folder.parent / "secret.npz")
    text = f"""
    <scene version="3.0.0">
        <default name="spp" value="{SPP}"/>
        <default name="resx" value="{RES[0]}"/>
        <default name="resy" value="{RES[1]}"/>
        <default name="isovalue" value="0.3"/>
        <integrator type="amr_iso">
            <string name="filename" value="data/sphere.npz"/>
            <string name="field" value="f"/>
            <string name="isovalue" value="$isovalue"/>
            <string name="color_field" value="f"/>
            <string name="colormap" value="viridis"/>
            <string name="color_range" value="0.1 0.5"/>
        </integrator>
        <sensor type="perspective">
            <float name="fov" value="30"/>
            <transform name="to_world">
                <lookat origin="1.6, -0.9, 1.4" target="0.5, 0.5, 0.5" up="0, 0, 1"/>
            </transform>
            <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
            <film type="hdrfilm">
                <integer name="width" value="$resx"/><integer name="height" value="$resy"/>
                <string name="pixel_format" value="rgb"/>
            </film>
        </sensor>
        <emitter type="directional">
            <vector name="direction" value="-0.4, 0.5, -1.0"/>
            <rgb name="irradiance" value="2.5"/>
        </emitter>
    </scene>"""
    path = folder / "scene.xml"
    path.write_text(textwrap.dedent(text))
    return path


class Viewer(ViewerProcess):
    """``python -m mi_amr view`` running in its own process (the benchmark's launcher), at the
    tests' resolution and samples per pixel."""

    def __init__(self, scene: Path, out: Path):
        super().__init__(scene, out, "--resolution", str(RES[0]), str(RES[1]), "--spp", str(SPP))
        self.scene, self.out = scene, out

    def get(self, path: str):
        with urllib.request.urlopen(self.url + path, timeout=30) as r:
            return json.loads(r.read().decode())

    def state(self) -> dict:
        return self.get("api/state")

    def compiled(self) -> dict:
        return self.status()["compiled"]


@pytest.fixture(scope="module")
def viewer(tmp_path_factory, variant):
    folder = tmp_path_factory.mktemp("viewer")
    scene = write_scene(folder / "scene")
    v = Viewer(scene, folder / "out")
    yield v
    v.stop()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        context = chromium(p, tmp_path_factory.mktemp("chromium-profile"))
        yield context
        context.close()


@pytest.fixture(scope="module")
def page(browser, viewer):
    page = browser.new_page()
    page.set_default_timeout(WAIT_MS)
    page.goto(viewer.url)
    try:
        wait_frame(page, -1)
    except Exception as exc:  # say what the server and the page saw
        code = viewer.proc.poll()
        state = "is running" if code is None else f"exited with {code}"
        raise AssertionError(
            f"no first frame in the page; the viewer process {state} and printed:\n"
            f"{''.join(viewer.output[-80:])}\nthe page's messages: "
            f"{page.evaluate('() => window.messages || []')}") from exc
    return page


# ---------------------------------------------------------------------- helpers

def shown_version(page) -> int:
    return int(page.get_attribute(IMAGE, "data-version"))


def wait_frame(page, newer_than: int, quality: str = "refined", timeout: int = WAIT_MS) -> int:
    """Wait until the page shows a ``quality`` frame of a version above ``newer_than``."""
    page.wait_for_function(
        """([v, q]) => { const i = document.querySelector('[data-testid=image]');
                         return +i.dataset.version > v && i.dataset.quality === q; }""",
        arg=[newer_than, quality], timeout=timeout)
    return shown_version(page)


def wait_message(page, pattern: str, kind: str = None) -> str:
    """Wait until the page shows a message matching ``pattern`` (a regular expression; of
    ``kind``, "error" or "notice", when given), and return it. Messages shown by earlier
    calls do not count: each call waits for a new one."""
    seen = page.evaluate("() => window.consumed || 0")
    found = page.wait_for_function(
        """([p, kind, seen]) => { const all = window.messages.slice(seen);
             const i = all.findIndex(m => new RegExp(p).test(m.text) &&
                                          (kind === null || m.kind === kind));
             if (i < 0) return false; window.consumed = seen + i + 1; return all[i].text; }""",
        arg=[pattern, kind, seen], timeout=WAIT_MS)
    return found.json_value()


def settled(page, viewer, tries: int = 50) -> dict:
    """The server's state once the page shows its refined frame and no input is still on its
    way (the last key presses may reach the server after a first look at its state): the
    state's version is the same before and after the page has shown it."""
    for _ in range(tries):
        state = viewer.state()
        version = state["version"]
        page.wait_for_function(
            f"+document.querySelector('{IMAGE}').dataset.version >= {version} "
            f"&& document.querySelector('{IMAGE}').dataset.quality === 'refined'")
        if viewer.state()["version"] == version and shown_version(page) == version:
            return state
    raise AssertionError("the viewer's state did not settle")


def page_png(page) -> bytes:
    """The bytes of the image the page shows."""
    data = page.evaluate("""async () => {
        const r = await fetch(document.querySelector('[data-testid=image]').src);
        const b = new Uint8Array(await r.arrayBuffer());
        let s = ''; for (const x of b) s += String.fromCharCode(x); return btoa(s); }""")
    return base64.b64decode(data)


def decode_png(data: bytes, tmp_path) -> np.ndarray:
    """An 8-bit PNG as linear RGB floats (the inverse of the sRGB curve)."""
    import mitsuba as mi

    path = tmp_path / "decoded.png"
    path.write_bytes(data)
    srgb = np.array(mi.Bitmap(str(path)), dtype=np.float64)[..., :3] / 255.0
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)


def as_shown(image, tmp_path) -> np.ndarray:
    """A linear float image as the page would show it (encoded as the server encodes)."""
    from mi_amr.workflows.viewer.worker import png_bytes

    return decode_png(png_bytes(np.asarray(image, dtype=np.float32)), tmp_path)


def rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def send(page, message: dict) -> None:
    """A request exactly as the page's controls send it (for requests no control can make,
    such as a path with '../' typed by hand, the page's own send() is used)."""
    page.evaluate("m => send(m)", message)


def drag(page, dx: int, dy: int, shift: bool = False) -> None:
    box = page.locator(IMAGE).bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    if shift:
        page.keyboard.down("Shift")
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + dx / 2, y + dy / 2, steps=3)
    page.mouse.move(x + dx, y + dy, steps=3)
    page.mouse.up()
    if shift:
        page.keyboard.up("Shift")


def type_into(page, testid: str, text: str) -> None:
    field = page.get_by_test_id(testid)
    field.fill(text)
    field.press("Enter")


# ---------------------------------------------------------------------- tests

def test01_the_page_loads(page, viewer):
    """The page, its controls (by data-testid), the first refined frame and the histogram."""
    assert page.title() == "mi_amr view"
    for testid in ("isovalue", "image", "save-image", "save-scene", "add-keyframe", "method",
                   "colormap"):
        assert page.get_by_test_id(testid).count() == 1, testid
    assert page.get_attribute(IMAGE, "data-quality") == "refined"
    assert page.text_content("[data-testid=connection]") == "connected"
    # The histogram of the field is drawn behind the slider (some bars are not background).
    lit = page.evaluate("""() => { const c = document.getElementById('histogram');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0; for (let i = 3; i < d.length; i += 4) n += d[i] > 0; return n; }""")
    assert lit > 100
    assert page.get_by_test_id("method").input_value() == "exact"
    assert page.get_by_test_id("colormap").input_value() == "viridis"


def test02_the_isovalue_slider_changes_the_image_to_a_direct_render(page, viewer, tmp_path):
    """Moving the slider with the keyboard sends input events; the refined image that comes
    back is a new image, and equals ``mi.render`` of the scene at that isovalue (rendered
    here, in the test process) within the reference tolerance."""
    from mi_amr.workflows.render import render_file

    before, v0 = page_png(page), shown_version(page)
    slider = page.get_by_test_id("isovalue")
    slider.focus()
    for _ in range(40):
        slider.press("ArrowLeft")
    state = settled(page, viewer)
    assert shown_version(page) > v0
    after = page_png(page)
    assert after != before
    iso = state["state"]["isovalues"][0]
    assert iso < 0.3
    direct = render_file(viewer.scene, tmp_path / "direct.exr", spp=SPP, resolution=RES,
                         defines={"isovalue": repr(iso)}, quiet=True)
    shown = decode_png(after, tmp_path)
    assert rmse(shown, as_shown(direct, tmp_path)) <= RMSE
    assert rmse(shown, decode_png(before, tmp_path)) > 10 * RMSE


def test03_an_orbit_drag_moves_the_camera(page, viewer):
    """A drag turns the camera about its target (same distance, same target), and turning the
    wheel away (scrolling up) moves it closer; the image follows."""
    cam0 = viewer.state()["state"]["camera"]
    v0, before = shown_version(page), page_png(page)
    drag(page, 20, 8)
    v1 = wait_frame(page, v0)
    cam1 = viewer.state()["state"]["camera"]
    o0, o1, t = (np.array(x) for x in (cam0["origin"], cam1["origin"], cam0["target"]))
    assert np.linalg.norm(o1 - o0) > 0.05
    assert cam1["target"] == cam0["target"]
    assert abs(np.linalg.norm(o1 - t) - np.linalg.norm(o0 - t)) < 1e-6
    assert page_png(page) != before
    page.locator(IMAGE).hover()
    page.mouse.wheel(0, -200)
    wait_frame(page, v1)
    cam2 = viewer.state()["state"]["camera"]
    assert np.linalg.norm(np.array(cam2["origin"]) - t) < np.linalg.norm(o1 - t)


def test04_a_saved_scene_renders_to_the_pages_image(page, viewer, tmp_path):
    """"Save scene", then ``python -m mi_amr render`` of the saved file: the page's image.
    Saving again asks before replacing the file; declined, the file stays as it was."""
    type_into(page, "colormap", "magma")
    page.get_by_test_id("light-elevation").fill("30")
    settled(page, viewer)
    shown = page_png(page)
    page.get_by_test_id("save-scene").click()
    wait_message(page, "Saved the scene")
    saved = viewer.out / "view.xml"
    assert saved.is_file()
    out = tmp_path / "render.png"
    run = subprocess.run([sys.executable, "-m", "mi_amr", "render", str(saved), "-o", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    page_image, rendered = decode_png(shown, tmp_path), decode_png(out.read_bytes(), tmp_path)
    assert rendered.shape == page_image.shape
    assert rmse(page_image, rendered) <= RMSE
    assert np.max(np.abs(page_image - rendered)) < 0.02
    # Saving again: the page asks; "no" keeps the file.
    text = saved.read_text()
    page.once("dialog", lambda d: d.dismiss())
    page.get_by_test_id("save-scene").click()
    wait_message(page, "Not saved")
    assert saved.read_text() == text
    page.once("dialog", lambda d: d.accept())
    page.get_by_test_id("save-scene").click()
    wait_message(page, "Saved the scene")


def test05_two_tabs_at_once(page, browser, viewer):
    """A second tab shows the same view; a change in either reaches both."""
    other = browser.new_page()
    other.set_default_timeout(WAIT_MS)
    try:
        other.goto(viewer.url)
        wait_frame(other, -1)
        v = viewer.state()["version"]
        other.get_by_test_id("isovalue").fill("0.33")
        wait_frame(other, v)
        wait_frame(page, v)
        typed = page.get_by_test_id("isovalue-text").input_value()
        assert typed == other.get_by_test_id("isovalue-text").input_value()
        assert float(typed) == pytest.approx(viewer.state()["state"]["isovalues"][0], rel=1e-5)
        assert abs(float(typed) - 0.33) < 0.002
        assert page_png(page) == page_png(other)
        v = viewer.state()["version"]
        type_into(page, "isovalue-text", "0.31")
        wait_frame(page, v)
        wait_frame(other, v)
        assert float(other.get_by_test_id("isovalue-text").input_value()) == 0.31
    finally:
        other.close()


def test06_bad_values_show_a_message_and_the_server_keeps_serving(page, viewer):
    """Typed values that are not numbers, out of range, or name a field that does not exist
    (and a colour map that does not exist) each show a message; then the page still works."""
    v = viewer.state()["version"]
    for testid, text, message in [
            ("isovalue-text", "abc", "'abc' is not a number"),
            ("isovalue-text", "1e9", "is outside"),
            ("field", "no_such_field", "'no_such_field' does not exist"),
            ("step-scale", "-1", "step scale: -1 is outside"),
            ("colormap", "no_such_map", "not a matplotlib colour map"),
            ("color-lo", "0.9", "must be below high")]:
        type_into(page, testid, text)
        wait_message(page, re.escape(message), "error")
        assert message in page.text_content("[data-testid=message]")
        assert "error" in page.get_attribute("[data-testid=message]", "class")
    assert viewer.state()["version"] == v
    assert viewer.get("api/status")["clients"] >= 1
    page.get_by_test_id("isovalue").fill("0.29")
    assert wait_frame(page, v) > v


def test07_ten_control_changes_compile_no_kernel(page, viewer):
    """Ten controls, each changed once (and the image refined after each): 0 kernels compiled
    in the viewer's process."""
    before = viewer.compiled()
    changes = [
        lambda: page.get_by_test_id("isovalue").fill("0.27"),
        lambda: type_into(page, "isovalue-text", "0.28"),
        lambda: type_into(page, "step-scale", "0.25"),
        lambda: page.get_by_test_id("shadows").click(),
        lambda: type_into(page, "colormap", "0.1: 0 0 1, 0.3: 0 1 0, 0.5: 1 0 0"),
        lambda: type_into(page, "color-hi", "0.45"),
        lambda: page.get_by_test_id("reset-color-range").click(),
        lambda: drag(page, -15, 5),
        lambda: drag(page, 10, -6, shift=True),
        lambda: page.get_by_test_id("light-azimuth").fill("60"),
    ]
    for change in changes:
        v = viewer.state()["version"]
        change()
        wait_frame(page, v)
    after = viewer.compiled()
    assert after["controls"] == before["controls"] == 0, (before, after)


def test08_paths_leaving_the_scene_folder_are_refused(page, viewer):
    """``../`` (and an absolute path elsewhere) in an open request and in a file name to save
    are refused with a message; the static files cannot be left either; a WebSocket from
    another origin is turned away."""
    for path in ("../secret.npz", "data/../../secret.npz", str(viewer.scene.parent.parent /
                                                             "secret.npz")):
        page.get_by_test_id("open-path").fill(path)
        page.get_by_test_id("open").click()
        wait_message(page, "outside the scene's folder")
    assert viewer.state()["state"]["data_file"] == "data/sphere.npz"
    for name in ("../evil.png", "sub/evil.png", ".hidden.png"):
        send(page, {"op": "save_image", "name": name})
        wait_message(page, "not a plain file name")
    assert not (viewer.out.parent / "evil.png").exists()
    for url in ("static/../pyproject.toml", "static/%2e%2e/%2e%2e/pyproject.toml"):
        with pytest.raises(urllib.error.HTTPError):
            viewer.get(url)
    from websockets.sync.client import connect

    with pytest.raises(Exception, match="403"):
        with connect(viewer.url.replace("http", "ws") + "ws", origin="http://evil.example"):
            pass


def test09_images_keyframes_and_data_files(page, viewer):
    """Save the image as PNG and EXR at a chosen size, append two keyframes that the movie
    command reads, and open another data file of the scene's folder."""
    import mitsuba as mi

    from mi_amr.workflows.movie.spec import read_keyframes

    for name, w, h in (("small.png", "48", "32"), ("small.exr", "40", "30")):
        page.get_by_test_id("image-name").fill(name)
        page.get_by_test_id("image-width").fill(w)
        page.get_by_test_id("image-height").fill(h)
        page.get_by_test_id("save-image").click()
        wait_message(page, f"Saved {w}x{h}")
        assert np.array(mi.Bitmap(str(viewer.out / name))).shape[:2] == (int(h), int(w))
    for _ in range(2):
        page.get_by_test_id("add-keyframe").click()
        wait_message(page, "Added keyframe")
    keys = read_keyframes(viewer.out / "keyframes.toml")
    assert [k["frame"] for k in keys] == [0, 24]
    assert keys[-1]["origin"] == pytest.approx(viewer.state()["state"]["camera"]["origin"])
    v = viewer.state()["version"]
    page.get_by_test_id("open-path").fill("data/sphere_coarse.npz")
    page.get_by_test_id("open").click()
    wait_frame(page, v)
    assert viewer.state()["state"]["data_file"] == "data/sphere_coarse.npz"


def test10_a_new_method_or_isovalue_count_loads_the_scene_again(page, viewer):
    """Method, layers and the number of isovalues change the kernels' structure: the page
    says the scene is loaded again, the new view comes, and the controls' count stays 0."""
    v = viewer.state()["version"]
    page.get_by_test_id("method").select_option("adaptive")
    wait_message(page, "Loading the scene again")
    v = wait_frame(page, v)
    assert viewer.state()["state"]["method"] == "adaptive"
    page.get_by_test_id("layers").select_option("stochastic")
    wait_message(page, "Loading the scene again")
    v = wait_frame(page, v)
    assert viewer.state()["state"]["layers"] == "stochastic"
    page.get_by_test_id("add-isovalue").click()
    v = wait_frame(page, v)
    assert len(viewer.state()["state"]["isovalues"]) == 2
    assert page.locator("#isolist li").count() == 2
    page.get_by_test_id("iso-remove-1").click()
    wait_frame(page, v)
    assert len(viewer.state()["state"]["isovalues"]) == 1
    assert viewer.compiled()["controls"] == 0


def test11_only_the_loopback_by_default():
    """``--host`` defaults to 127.0.0.1; another address prints a warning."""
    from mi_amr.workflows.viewer.server import host_warning

    run = subprocess.run([sys.executable, "-m", "mi_amr", "view", "--help"],
                         capture_output=True, text=True, timeout=60)
    assert "default 127.0.0.1" in run.stdout
    assert host_warning("127.0.0.1") is None
    assert "warning" in host_warning("0.0.0.0")


def plain_state():
    """A view state of a stand-in scene (the render thread's tests)."""
    from mi_amr.plugin.camera import Camera
    from mi_amr.workflows.viewer.state import ViewState

    return ViewState(data_file="a.npz", field="f", color_field=None, colormap=None,
                     color_range=None, isovalues=(0.3,), iso_colors=((1.0, 1.0, 1.0),),
                     iso_opacity=(1.0,), mode="surface", method="exact", reconstruction="basis",
                     layers="composite",
                     step_scale=0.5, band_width=(0.01,), band_offsets=((-0.02, 0.02),),
                     band_peak=(1.6,), shadows=True,
                     camera=Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 30.0),
                     light_direction=None, light_irradiance=None, spp=2)


def test12_the_newest_request_wins(variant):
    """The render thread alone, with a slow stand-in scene: requests that arrive while a frame
    renders replace each other, so the stale ones are never rendered (not queued), and the
    stale frame is not refined."""
    import threading
    import time

    from mi_amr.workflows.viewer.worker import RenderWorker

    base = plain_state()

    class SlowScene:
        resolution = (8, 8)
        compiled = {"warmup": 0, "controls": 0, "reloads": 0, "quality": 0, "saves": 0,
                    "steps": 0, "preview_sizes": 0}

        def __init__(self):
            self.state, self.applied = base, []

        def apply(self, state):
            self.applied.append(state.step_scale)
            self.state = state
            return "traverse", state

        def render(self, size, spp, seed=0, preview=False):
            time.sleep(0.2)
            return np.zeros((size[1], size[0], 3), dtype=np.float32)

        def render_refined(self, size, spp, before_pass=None):
            return None if before_pass and before_pass() else self.render(size, spp)

        def prefetch_next(self):            # no time series
            pass

        def close(self):
            pass

    frames, done = [], threading.Event()

    def publish(kind, payload, data):
        if kind == "frame":
            frames.append((payload["version"], payload["quality"]))
            if (payload["version"], payload["quality"]) == (5, "refined"):
                done.set()

    worker = RenderWorker(SlowScene, publish, idle_s=0.05)
    worker.start()
    try:
        worker.submit(base.replace(step_scale=0.1), 1)
        time.sleep(0.05)                    # version 1 is rendering now
        for v in (2, 3, 4, 5):
            worker.submit(base.replace(step_scale=0.1 * v), v)
        assert done.wait(10)
    finally:
        worker.stop()
    assert frames == [(1, "preview"), (5, "preview"), (5, "refined")]
    assert worker.session.applied == [0.1, pytest.approx(0.5)]
    assert worker.dropped == 3


def test12b_slow_previews_get_smaller_and_grow_back(variant):
    """The render thread alone, with a stand-in scene whose frames take time in proportion
    to their pixels: a preview over the budget makes the next ones half the side (each size
    counted once under ``preview_sizes``), one under a sixth of it twice the side again, never
    beyond the ``preview_scale`` asked for; with a budget of 0 the scale stays."""
    import threading
    import time

    from mi_amr.workflows.viewer.worker import PREVIEW_BUDGET_S, RenderWorker

    class Scene:
        resolution = (64, 64)
        per_pixel = 0.6 / 32 ** 2           # a 32 x 32 preview: 0.6 s
        state = plain_state()

        def __init__(self):
            self.compiled = {"warmup": 0, "controls": 0, "reloads": 0, "quality": 0,
                             "saves": 0, "steps": 0, "preview_sizes": 0}

        def apply(self, state):
            self.state = state
            return "traverse", state

        def render(self, size, spp, seed=0, preview=False):
            time.sleep(self.per_pixel * size[0] * size[1])
            return np.zeros((size[1], size[0], 3), dtype=np.float32)

        def render_refined(self, size, spp, before_pass=None):
            return np.zeros((size[1], size[0], 3), dtype=np.float32)

        def prefetch_next(self):
            pass

        def close(self):
            pass

    def run(budget, moves):
        sizes, shown = [], threading.Event()

        def publish(kind, payload, data):
            if kind == "frame" and payload["quality"] == "preview":
                sizes.append(payload["width"])
                shown.set()

        worker = RenderWorker(Scene, publish, idle_s=60.0, preview_budget_s=budget)
        worker.start()
        try:
            for version, fast in enumerate(moves):
                if fast:
                    worker.session.per_pixel = 1e-7
                shown.clear()
                worker.submit(plain_state().replace(step_scale=0.1 + 0.1 * version), version)
                assert shown.wait(10)
        finally:
            worker.stop()
        return sizes, worker

    sizes, worker = run(PREVIEW_BUDGET_S, [False, False, False, True, True, True])
    # 32 (0.6 s: over budget) -> 16 (0.15 s: within) stays -> fast at 16, so 32 next, and
    # 32 again (never 64, beyond the preview scale asked for)
    assert sizes == [32, 16, 16, 16, 32, 32], sizes
    assert worker.session.compiled == dict.fromkeys(worker.session.compiled, 0)
    sizes, worker = run(0.0, [False, False])
    assert sizes == [32, 32] and worker.scale == worker.preview_scale == 2


def test12c_a_bug_the_render_thread_cannot_print_still_gets_an_answer(variant, monkeypatch):
    """A job that fails while stderr cannot be written (a full disk, a file size limit) is
    still answered on the page, and the render thread goes on with the next job (it used to
    die printing the traceback, and every later request waited for ever)."""
    import sys
    import threading

    from mi_amr.workflows.viewer.worker import RenderWorker

    class Scene:
        resolution = (8, 8)
        state = plain_state()
        compiled = {"warmup": 0, "controls": 0, "reloads": 0, "quality": 0, "saves": 0,
                    "steps": 0, "preview_sizes": 0}

        def render(self, size, spp, seed=0, preview=False):
            return np.zeros((size[1], size[0], 3), dtype=np.float32)

        def render_refined(self, size, spp, before_pass=None):
            return self.render(size, spp)

        def prefetch_next(self):
            pass

        def close(self):
            pass

    class Unwritable:
        def write(self, text):
            raise OSError(27, "File too large")

        def flush(self):
            raise OSError(27, "File too large")

    errors, later = [], threading.Event()

    def publish(kind, payload, data):
        if kind == "error":
            errors.append(payload["message"])

    def broken(session):
        raise RuntimeError("a bug")

    worker = RenderWorker(Scene, publish, idle_s=60.0)
    worker.start()
    try:
        monkeypatch.setattr(sys, "stderr", Unwritable())
        worker.job(broken)
        worker.job(lambda session: later.set())
        assert later.wait(10), "the render thread stopped after the failed job"
    finally:
        monkeypatch.undo()
        worker.stop()
    assert errors == ["internal error: RuntimeError('a bug')"]


def test13_a_frame_ready_before_the_server_runs_is_kept(tmp_path):
    """The first frame can be rendered before the server's event loop runs (the render thread
    starts first): the hub keeps the render thread's reports until the loop is attached, then
    handles them in order, before any that come after. (It once dropped them: a page that
    connected then waited for a first frame that never came.)"""
    import asyncio
    import threading

    from mi_amr.workflows.viewer.hub import Hub

    hub = Hub(write_scene(tmp_path / "scene"), out_dir=tmp_path / "out")
    seen = []
    hub._report = lambda kind, payload, data: seen.append((kind, data))
    hub.from_worker("frame", {"version": 0}, b"first")
    hub.from_worker("reply", {"n": 1}, None)

    def server():                   # the server's loop, in a thread of its own
        loop = asyncio.new_event_loop()
        hub.attach(loop)
        hub.from_worker("frame", {"version": 1}, b"second")
        loop.run_until_complete(asyncio.sleep(0.05))
        loop.close()

    thread = threading.Thread(target=server)
    thread.start()
    thread.join()
    assert seen == [("frame", b"first"), ("reply", None), ("frame", b"second")]


def test14_the_saved_scene_keeps_the_layers_of_surfaces():
    """``layers`` is written for surfaces and left out in volume mode (which composites its
    band and refuses the parameter)."""
    from mi_amr.plugin.camera import Camera
    from mi_amr.workflows.viewer.sceneio import integrator_values
    from mi_amr.workflows.viewer.state import ViewState

    state = ViewState(data_file="a.npz", field="f", color_field=None, colormap=None,
                      color_range=None, isovalues=(0.3,), iso_colors=((1.0, 1.0, 1.0),),
                      iso_opacity=(0.5,), mode="surface", method="exact",
                      reconstruction="basis", layers="stochastic", step_scale=0.5,
                      band_width=(0.01,), band_offsets=((-0.02, 0.02),), band_peak=(1.6,),
                      shadows=True,
                      camera=Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 30.0),
                      light_direction=None, light_irradiance=None, spp=2)
    assert integrator_values(state)["layers"] == "stochastic"
    assert integrator_values(state.replace(mode="volume"))["layers"] is None
