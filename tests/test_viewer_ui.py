"""The viewer's time slider, transfer-function editor and isovalue scale, in Debian's chromium
through Playwright (as ``tests/test_viewer.py``, whose helpers these tests use).

A series of three small files (a sphere whose centre moves) is shown with
``view SCENE --files 'data/step*.npz'``: each step shows new data, compiles no kernel, and comes
back about as fast as a frame of a control change, since the next step is prepared while the
current one is shown.
"""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from test_references import RMSE
from test_viewer import (CHROMIUM, RES, SPP, WAIT_MS, Viewer, decode_png, page_png, rmse,
                         settled, wait_frame, wait_message)

from mi_amr.evaluation.viewer_bench import chromium

pytestmark = pytest.mark.skipif(
    not Path(CHROMIUM).is_file(),
    reason=f"Debian's chromium is not installed ({CHROMIUM} is missing)")

CENTRES = ((0.42, 0.5, 0.5), (0.5, 0.5, 0.5), (0.58, 0.5, 0.5))

# One input event on a page control, timed in the page until the next frame is shown.
TIMED_INPUT = """async ([testid, value]) => {
    const img = document.querySelector('[data-testid=image]');
    const before = +img.dataset.version;
    const shown = new Promise((resolve) => {
        const watch = new MutationObserver(() => {
            if (+img.dataset.version > before) { watch.disconnect(); resolve(); } });
        watch.observe(img, {attributes: true, attributeFilter: ['data-version']}); });
    const el = document.querySelector(`[data-testid=${testid}]`);
    const t0 = performance.now();
    el.value = value;
    el.dispatchEvent(new Event('input', {bubbles: true}));
    await shown;
    return (performance.now() - t0) / 1e3; }"""


def moving_sphere(centre, base: int = 16):
    from mi_amr.synthetic import datasets

    c = np.asarray(centre)
    return datasets.two_levels(lambda p, level: np.linalg.norm(p - c, axis=-1), base)


def series_scene(folder: Path, mode: str = "surface") -> Path:
    """A scene of the first step (directional light), and the three steps: surfaces coloured by
    f, or volume mode's band of width 0.04 in its own colour."""
    (folder / "data").mkdir(parents=True)
    for i, c in enumerate(CENTRES):
        moving_sphere(c).save(folder / "data" / f"step{i}.npz")
    band = '<string name="band_width" value="0.04"/>' if mode == "volume" else \
        '<string name="color_field" value="f"/><string name="colormap" value="viridis"/>' \
        '<string name="color_range" value="0.1 0.5"/>'

    text = f"""
    <scene version="3.0.0">
        <default name="spp" value="{SPP}"/>
        <default name="resx" value="{RES[0]}"/>
        <default name="resy" value="{RES[1]}"/>
        <integrator type="amr_iso">
            <string name="filename" value="data/step0.npz"/>
            <string name="field" value="f"/>
            <string name="isovalue" value="0.3"/>
            <string name="mode" value="{mode}"/>
            <string name="iso_color" value="0.9 0.5 0.2"/>
            {band}
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


class SeriesViewer(Viewer):
    def __init__(self, scene: Path, out: Path, *extra):
        from mi_amr.evaluation.viewer_bench import ViewerProcess

        ViewerProcess.__init__(self, scene, out, "--resolution", str(RES[0]), str(RES[1]),
                               "--spp", str(SPP), *extra)
        self.scene, self.out = scene, out


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        context = chromium(p, tmp_path_factory.mktemp("chromium-profile"))
        yield context
        context.close()


def open_page(browser, viewer):
    page = browser.new_page()
    page.set_default_timeout(WAIT_MS)
    page.goto(viewer.url)
    try:
        wait_frame(page, -1)
    except Exception as exc:
        raise AssertionError(f"no first frame; the viewer printed:\n"
                             f"{''.join(viewer.output[-80:])}") from exc
    return page


@pytest.fixture(scope="module")
def series(tmp_path_factory, variant):
    folder = tmp_path_factory.mktemp("series")
    scene = series_scene(folder / "scene")
    v = SeriesViewer(scene, folder / "out", "--files", str(scene.parent / "data" / "step*.npz"))
    yield v
    v.stop()


@pytest.fixture(scope="module")
def series_page(browser, series):
    page = open_page(browser, series)
    yield page
    page.close()


def wait_prepared(viewer, name: str, tries: int = 600) -> None:
    """Until the viewer's background thread has prepared the step ``name``."""
    import time

    for _ in range(tries):
        prepared = viewer.status().get("prepared")
        if prepared and Path(prepared).name == name:
            return
        time.sleep(0.05)
    raise AssertionError(f"{name} was not prepared in the background")


# ---------------------------------------------------------------------- time steps

def test01_a_series_steps_with_new_data_and_no_kernel(series_page, series, tmp_path):
    """Three steps: each shows its own data (the header names it, the image changes), keeps the
    camera, isovalue and colour range, compiles no kernel, and comes back within twice the time
    of a frame of a control change, since it was prepared while the previous step was shown."""
    page, viewer = series_page, series
    assert page.is_visible("[data-testid=timeline]")
    assert page.get_attribute("[data-testid=time-step]", "max") == "2"
    assert page.text_content("[data-testid=data-name]").endswith("step0.npz")
    settled(page, viewer)
    # A frame of a control change: the isovalue moved, timed in the page.
    frames = [page.evaluate(TIMED_INPUT, ["isovalue", v]) for v in (0.29, 0.3, 0.29)]
    before = settled(page, viewer)["state"]
    images = [decode_png(page_png(page), tmp_path)]
    steps = []
    for k in (1, 2, 0):
        wait_prepared(viewer, f"step{k}.npz")
        steps.append(page.evaluate(TIMED_INPUT, ["time-step", k]))
        state = settled(page, viewer)["state"]
        assert state["data_file"].endswith(f"step{k}.npz")
        assert page.text_content("[data-testid=data-name]").endswith(f"step{k}.npz")
        assert page.text_content("[data-testid=time-label]") == f"step {k + 1} of 3"
        for kept in ("camera", "isovalues", "color_range", "colormap", "iso_colors"):
            assert state[kept] == before[kept], kept
        images.append(decode_png(page_png(page), tmp_path))
        assert rmse(images[-1], images[-2]) > 0.01, f"step {k} shows the same image"
    # (Medians of three: the machine is shared, a single round trip may wait for the CPU.)
    assert np.median(steps) <= 2 * np.median(frames), (f"steps took {steps} s, frames of a "
                                                       f"control change {frames} s")
    compiled = viewer.compiled()
    assert compiled["steps"] == 0 and compiled["controls"] == 0, compiled


def test02_play_loops_through_the_steps_and_pauses(series_page, series):
    """Play steps on by itself (past the last step back to the first); Pause stops it."""
    page, viewer = series_page, series
    start = viewer.state()["state"]["data_file"]
    page.get_by_test_id("play").click()
    seen = {start}
    for _ in range(200):
        seen.add(viewer.state()["state"]["data_file"])
        if len(seen) == 3:
            break
        page.wait_for_timeout(100)
    page.get_by_test_id("play").click()
    assert len(seen) == 3, seen
    assert page.text_content("[data-testid=play]") == "Play"
    settled(page, viewer)
    v = viewer.state()["version"]
    page.wait_for_timeout(1500)
    assert viewer.state()["version"] == v, "still stepping after Pause"
    assert viewer.compiled()["steps"] == 0


def test03_keyframes_record_the_step_and_the_scene_beside_them(series_page, series):
    """"Add keyframe" records the time step, and writes the view as a scene beside the
    keyframe file; the hint names both and the series. The movie's plan replays the steps."""
    from mi_amr.workflows.movie.spec import plan, read_keyframes

    page, viewer = series_page, series
    for k in (0, 2):
        page.evaluate("k => stepTo(k)", k)
        settled(page, viewer)
        page.get_by_test_id("add-keyframe").click()
        hint = wait_message(page, "Added keyframe")
    keys = read_keyframes(viewer.out / "keyframes.toml")
    assert [k["step"] for k in keys] == [0, 2]
    scene = viewer.out / "keyframes.xml"
    assert scene.is_file() and "viridis" in scene.read_text()
    assert str(scene) in hint and "--files" in hint and "step*.npz" in hint
    files = [f"step{i}.npz" for i in range(3)]
    specs = plan(None, camera={"origin": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0],
                               "fov": 30.0}, files=files, keyframes=keys)
    # Frames 0 to 24, the step going from 0 to 2: frames 6 to 17 show step 1.
    assert [s.file for s in specs] == ["step0.npz"] * 6 + ["step1.npz"] * 12 + \
        ["step2.npz"] * 7


def test04_keyframes_with_steps_need_the_files():
    """A keyframe file with steps but no --files, or a step past the files: one AMRError."""
    from mi_amr.errors import AMRError
    from mi_amr.workflows.movie.spec import plan

    camera = {"origin": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0], "fov": 30.0}
    keys = [{"frame": 0, "step": 0.0}, {"frame": 4, "step": 3.0}]
    with pytest.raises(AMRError, match="pass the time series with --files"):
        plan(None, camera=camera, keyframes=keys)
    with pytest.raises(AMRError, match="time step 3, but --files gives 2"):
        plan(None, camera=camera, files=["a", "b"], keyframes=keys)


def test05_bad_series_get_one_error(tmp_path):
    """A glob matching nothing, and files of different fields in one series: one line naming
    it, no traceback."""
    from mi_amr import AMRVolume
    from mi_amr.errors import AMRError
    from mi_amr.workflows.viewer.series import check_series, expand_series

    scene = series_scene(tmp_path / "scene")
    run = subprocess.run([sys.executable, "-m", "mi_amr", "view", str(scene), "--no-browser",
                          "--port", "0", "--files", str(tmp_path / "nothing*.npz")],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode != 0
    assert "nothing*.npz' matches no file" in run.stderr and "Traceback" not in run.stderr
    other = tmp_path / "scene" / "data" / "other.npz"
    vol = moving_sphere(CENTRES[0])
    AMRVolume.from_grids([{"level": g.level, "origin": g.origin, "spacing": g.spacing,
                           "fields": {"g": g.fields["f"]}} for g in vol.grids]).save(other)
    files = expand_series([str(tmp_path / "scene" / "data" / "*.npz")])
    with pytest.raises(AMRError, match=r"step0.npz holds the fields \['f'\], but \S+other.npz "
                                       r"holds \['g'\]"):
        check_series(files, "f", None)
    with pytest.raises(AMRError, match=r"has no field\(s\) \['h'\]"):
        check_series(files[1:], "h", None)


# ---------------------------------------------------------------------- transfer function

@pytest.fixture(scope="module")
def volume(tmp_path_factory, variant):
    folder = tmp_path_factory.mktemp("volume")
    v = SeriesViewer(series_scene(folder / "scene", mode="volume"), folder / "out")
    yield v
    v.stop()


@pytest.fixture(scope="module")
def volume_page(browser, volume):
    page = open_page(browser, volume)
    yield page
    page.close()


def drag_on_page(page, start, dx: float, dy: float) -> None:
    """A mouse drag from ``start`` (viewport pixels: scroll the target into view first)."""
    x, y = start
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + dx / 2, y + dy / 2, steps=3)
    page.mouse.move(x + dx, y + dy, steps=3)
    page.mouse.up()


def test06_dragging_a_band_changes_the_image_and_compiles_nothing(volume_page, volume,
                                                                  tmp_path):
    """Drag the band's body (moves it), its side (widens it), its top (raises its peak), and
    pick its colour: each changes the state and the image, and no kernel compiles."""
    page, viewer = volume_page, volume
    assert page.is_visible("[data-testid=tf-editor]")
    assert page.text_content("[data-testid=band-color-note]") == ""
    before = settled(page, viewer)["state"]
    compiled = viewer.compiled()
    image = decode_png(page_png(page), tmp_path)
    for handle, dx, dy, check in [
            ("center", 12, 0, lambda s: s["isovalues"][0] > before["isovalues"][0]),
            ("side", 8, 0, lambda s: s["bands"]["width"][0] > before["bands"]["width"][0]),
            ("peak", 0, -25, lambda s: s["bands"]["peak"][0] > before["bands"]["peak"][0])]:
        page.locator("[data-testid=tf-editor]").scroll_into_view_if_needed()
        drag_on_page(page, page.evaluate("() => bandHandles()[0]")[handle], dx, dy)
        state = settled(page, viewer)["state"]
        assert check(state), (handle, before, state)
        shown = decode_png(page_png(page), tmp_path)
        assert rmse(shown, image) > 1e-3, f"dragging the band's {handle} left the image as it was"
        image, before = shown, state
    page.get_by_test_id("iso-color-0").fill("#2060ff")
    state = settled(page, viewer)["state"]
    assert state["iso_colors"][0] == "#2060ff"
    assert rmse(decode_png(page_png(page), tmp_path), image) > 1e-3
    after = viewer.compiled()
    assert after["controls"] == compiled["controls"] == 0, (compiled, after)
    assert after["reloads"] == compiled["reloads"]


def test07_a_saved_volume_scene_renders_to_the_pages_image(volume_page, volume, tmp_path):
    """"Save scene" after the band edits: ``python -m mi_amr render`` of the saved file gives the
    page's image (the bands are in the scene)."""
    page, viewer = volume_page, volume
    settled(page, viewer)
    shown = page_png(page)
    page.get_by_test_id("scene-file").fill("bands.xml")
    page.get_by_test_id("save-scene").click()
    wait_message(page, "Saved the scene")
    saved = viewer.out / "bands.xml"
    assert "band_support" in saved.read_text()
    out = tmp_path / "render.png"
    run = subprocess.run([sys.executable, "-m", "mi_amr", "render", str(saved), "-o", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    page_image, rendered = decode_png(shown, tmp_path), decode_png(out.read_bytes(), tmp_path)
    assert rmse(page_image, rendered) <= RMSE
    assert np.max(np.abs(page_image - rendered)) < 0.02


def test08_band_requests_are_checked():
    """Band requests out of range, overlapping bands, or outside volume mode: one message."""
    from mi_amr.errors import AMRError
    from mi_amr.plugin.camera import Camera
    from mi_amr.workflows.viewer import bands
    from mi_amr.workflows.viewer.controls import Context
    from mi_amr.workflows.viewer.state import ViewState

    state = ViewState(data_file="a.npz", field="f", color_field=None, colormap=None,
                      color_range=None, isovalues=(0.3, 0.5), iso_colors=((1.0, 1.0, 1.0),) * 2,
                      iso_opacity=(1.0, 1.0), mode="volume", method="exact",
                      reconstruction="basis", layers="composite", step_scale=0.5,
                      band_width=(0.01, 0.01), band_offsets=((-0.02, 0.02),) * 2,
                      band_peak=(1.6, 1.6), shadows=True,
                      camera=Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 30.0),
                      light_direction=None, light_irradiance=None, spp=2)
    ctx = Context(value_range=(0.0, 1.0), color_data_range=(0.0, 1.0), fields=("f",),
                  home=state.camera, up=(0.0, 0.0, 1.0), resolution=(8, 8))
    moved = bands.change(state, {"op": "band", "index": 1, "center": 0.6, "peak": 2.0}, ctx)
    assert moved.isovalues == (0.3, 0.6) and moved.band_peak == (1.6, 2.0)
    wide = bands.change(state, {"op": "band", "index": 0, "width": 0.03}, ctx)
    assert wide.band_offsets[0] == (-0.06, 0.06)
    for msg, message in [({"index": 2, "peak": 1}, "number 2 does not exist"),
                         ({"index": 0, "center": 2.0}, "outside"),
                         ({"index": 0, "width": -1}, "outside"),
                         ({"index": 0, "peak": 0}, "must be above 0"),
                         ({"index": 0, "color": "red"}, "not a colour"),
                         ({"index": 0, "center": 0.49}, "would overlap"),
                         ({"index": 0}, "give center")]:
        with pytest.raises(AMRError, match=message):
            bands.change(state, dict(msg, op="band"), ctx)
    with pytest.raises(AMRError, match="volume mode"):
        bands.change(state.replace(mode="surface"), {"op": "band", "peak": 1.0}, ctx)


# ---------------------------------------------------------------------- the isovalue scale

def test09_the_slider_scale_is_chosen_from_the_histogram():
    """Values crammed at one end of their range (like Q: -1.4e6 to -1.4, most near 0) get the
    percentile scale; evenly spread values the linear one."""
    from mi_amr.workflows.viewer.state import QUANTILES, slider_scale

    rng = np.random.default_rng(0)
    q_like = np.concatenate([-1.4 * np.exp(rng.exponential(2.0, 10_000)), [-1.4e6]])
    level = np.linspace(0.0, 1.0, QUANTILES)
    assert slider_scale(np.quantile(q_like, level)) == "percentile"
    assert slider_scale(np.quantile(rng.uniform(0, 1, 10_000), level)) == "linear"


def test10_the_percentile_slider_moves_through_the_cells(series_page, series):
    """On the percentile scale the slider's middle is the median leaf value; on symlog, the
    slider maps back to the isovalue it shows; linear is the scale of evenly spread data."""
    page, viewer = series_page, series
    assert page.get_by_test_id("isovalue-scale").input_value() == "linear"
    page.get_by_test_id("isovalue-scale").select_option("percentile")
    quantiles = page.evaluate("() => info.quantiles")
    v = viewer.state()["version"]
    page.get_by_test_id("isovalue").fill("500")
    wait_frame(page, v)
    iso = settled(page, viewer)["state"]["isovalues"][0]
    assert iso == pytest.approx(quantiles[len(quantiles) // 2], rel=1e-4)
    page.get_by_test_id("isovalue-scale").select_option("symlog")
    position = float(page.get_by_test_id("isovalue").input_value())
    assert page.evaluate("p => toValue(p)", position) == pytest.approx(iso, rel=1e-6)
    page.get_by_test_id("isovalue-scale").select_option("linear")
    lo, hi = page.evaluate("() => info.value_range")
    # (A linear slider snaps to its step, a thousandth of the range.)
    assert abs(float(page.get_by_test_id("isovalue").input_value()) - iso) <= (hi - lo) / 1e3


def test11_the_2d_transfer_function_editor(volume_page, volume, tmp_path):
    """"2D transfer function" loads the scene once with a table over the value x |grad f|
    histogram and a first blob; moving the blob changes the image and compiles nothing, a
    blob drawn on the histogram is added, and the saved scene (with its table beside it)
    renders to the page's image."""
    page, viewer = volume_page, volume
    v = viewer.state()["version"]
    page.get_by_test_id("tf2d-toggle").click()
    wait_message(page, "Loading the scene again")
    # (The new structure's kernels compile once: a minute or more on a busy machine.)
    wait_frame(page, v, timeout=10 * WAIT_MS)
    state = settled(page, viewer)["state"]
    assert state["tf2d"] is not None and len(state["tf2d"]["blobs"]) == 1
    assert page.is_visible("[data-testid=tf2d-editor]")
    assert not page.is_visible("[data-testid=tf-editor]")
    compiled = viewer.compiled()
    image = decode_png(page_png(page), tmp_path)
    page.locator("[data-testid=tf2d-editor]").scroll_into_view_if_needed()
    drag_on_page(page, page.evaluate("() => blobCentres()[0]"), 20, 12)
    # (The page's last request may reach the server after a first look at its state.)
    page.wait_for_function("v => state.tf2d.blobs[0][0] !== v",
                           arg=state["tf2d"]["blobs"][0][0])
    moved = settled(page, viewer)["state"]["tf2d"]["blobs"]
    assert moved[0][0] > state["tf2d"]["blobs"][0][0] and moved[0][1] < \
        state["tf2d"]["blobs"][0][1], moved
    assert rmse(decode_png(page_png(page), tmp_path), image) > 1e-3
    box = page.locator("[data-testid=tf2d-editor]").bounding_box()
    drag_on_page(page, (box["x"] + 0.05 * box["width"], box["y"] + 0.6 * box["height"]),
                 0.12 * box["width"], 0.2 * box["height"])
    page.wait_for_function("() => state.tf2d.blobs.length === 2")
    blobs = settled(page, viewer)["state"]["tf2d"]["blobs"]
    assert len(blobs) == 2 and blobs[1][0] < blobs[0][0]
    after = viewer.compiled()
    assert after["controls"] == compiled["controls"] == 0, (compiled, after)
    assert after["reloads"] == compiled["reloads"]
    shown = page_png(page)
    page.get_by_test_id("scene-file").fill("tf2d.xml")
    page.get_by_test_id("save-scene").click()
    wait_message(page, "Saved the scene")
    saved = viewer.out / "tf2d.xml"
    assert "transfer2d" in saved.read_text() and (viewer.out / "tf2d.tf2d.npy").is_file()
    out = tmp_path / "render.png"
    run = subprocess.run([sys.executable, "-m", "mi_amr", "render", str(saved), "-o", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    page_image, rendered = decode_png(shown, tmp_path), decode_png(out.read_bytes(), tmp_path)
    assert rmse(page_image, rendered) <= RMSE
    assert np.max(np.abs(page_image - rendered)) < 0.02
