"""The ``amr_iso`` Mitsuba integrator: every shipped scene renders, parameter mistakes give the
documented :class:`AMRError` messages, isovalue and step scale change between frames without a
kernel recompile, opacity correction, meshes occluding and shadowing isosurfaces (and the
reverse), and registration across Mitsuba variants.

Runs on ``llvm_ad_rgb``; the scalar checks are tiny. Images are small (32 to 96 pixels a side)
and compared with themselves under a controlled change (a mesh moved, shadows switched off),
so no reference image is needed: colours tell the objects apart (the isosurface green, the
floor blue, the blocking ball red).
"""

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
dr = pytest.importorskip("drjit")

import mi_amr  # noqa: E402
from mi_amr import AMRError  # noqa: E402
from mi_amr.cli import main as cli_main  # noqa: E402
from mi_amr.synthetic import datasets
from mi_amr.workflows import project  # noqa: E402

SCENES = project.scenes_dir()
from mi_amr.plugin.scene import load_scene  # noqa: E402

VARIANT = "llvm_ad_rgb"
if VARIANT not in mi.variants():
    pytest.skip(f"Mitsuba variant {VARIANT} is not available", allow_module_level=True)


@pytest.fixture(scope="module", autouse=True)
def _variant(variant):
    yield


@pytest.fixture(scope="module")
def sphere_file(tmp_path_factory):
    """The analytic sphere dataset (isosurface 0.3: radius 0.3 around (0.5, 0.5, 0.5))."""
    path = tmp_path_factory.mktemp("data") / "sphere.npz"
    datasets.sphere().save(path)
    return path


def render(scene, **kw):
    img = mi.render(scene, seed=0, **kw)
    return np.array(img, dtype=np.float64)


# ---------------------------------------------------------------------- the shipped scenes

SCENE_FILES = sorted(SCENES.glob("*.xml"))
MEMORY_LIMIT = 3 << 30      # bytes of address space for a child (the sphere wake needs 1.5)
TIME_LIMIT = 180            # seconds for a child

# Renders scenes given on the command line at 32 x 32, one JSON line per scene (an image file
# and the mi.traverse keys, or the error), so one scene's failure does not hide the others'.
CHILD = r"""
import json, sys, traceback
import numpy as np
import mitsuba as mi
mi.set_variant(sys.argv[1])
import mi_amr
from mi_amr.plugin.scene import load_scene
out = sys.argv[2]
for i, path in enumerate(sys.argv[3:]):
    try:
        scene = load_scene(path, resx=32, resy=32)
        keys = sorted(mi.traverse(scene).keys())
        np.save(f"{out}/{i}.npy", np.array(mi.render(scene, seed=0), dtype=np.float64))
        print(json.dumps({"path": path, "image": f"{out}/{i}.npy", "keys": keys}), flush=True)
    except Exception as e:
        print(json.dumps({"path": path, "error": f"{type(e).__name__}: {e}",
                          "trace": traceback.format_exc()[-3000:]}), flush=True)
"""


def data_path(path: Path) -> Path:
    """The file or folder the scene's integrator reads (its ``filename``, a ``$name`` taken
    from the scene's ``<default>``, relative to the scene file)."""
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    defaults = {d.get("name"): d.get("value") for d in root.iter("default")}
    for node in root.find("integrator").iter("string"):
        if node.get("name") == "filename":
            value = node.get("value")
            value = defaults[value[1:]] if value.startswith("$") else value
            return (path.parent / value).resolve()
    raise AssertionError(f"{path.name}: no amr_iso filename")


def data_missing(path: Path):
    """Scenes reading AMReX plotfiles from ../shared (outside the repository) are skipped when
    those are absent; the data in scenes_xml/data is made by :func:`scene_data`."""
    data = data_path(path)
    if not data.exists() and (SCENES / "data") not in data.parents:
        return f"{data} not found (see shared/data/amrex/SOURCE.md)"
    return None


def data_size(data: Path) -> int:
    if data.is_dir():
        return sum(f.stat().st_size for f in data.rglob("*") if f.is_file())
    return data.stat().st_size if data.exists() else 0


def render_in_children(paths, workdir):
    """Render ``paths`` in child processes (two at a time), each limited in memory and time:
    a runaway preparation fails its scenes instead of taking the test run down."""
    import json
    import resource
    from concurrent.futures import ThreadPoolExecutor

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))

    groups = {}
    for p in paths:
        groups.setdefault(data_path(p), []).append(p)
    # The largest data first, so the two workers finish together.
    order = sorted(groups, key=data_size, reverse=True)

    def run(index_group):
        index, group = index_group
        out = workdir / str(index)
        out.mkdir()
        try:
            proc = subprocess.run([sys.executable, "-c", CHILD, VARIANT, str(out)] +
                                  [str(p) for p in group], capture_output=True, text=True,
                                  timeout=TIME_LIMIT, preexec_fn=limit)
            stdout, why = proc.stdout, f"exit status {proc.returncode}: {proc.stderr[-2000:]}"
        except subprocess.TimeoutExpired as e:
            stdout, why = e.stdout or "", f"no result within {TIME_LIMIT} s"
            stdout = stdout.decode() if isinstance(stdout, bytes) else stdout
        results = {}
        for line in stdout.splitlines():
            if line.startswith("{"):
                r = json.loads(line)
                results[Path(r["path"])] = r
        return {p: results.get(p, {"error": f"the child died: {why}"}) for p in group}

    results = {}
    with ThreadPoolExecutor(max_workers=2) as pool:
        for part in pool.map(run, enumerate(groups[d] for d in order)):
            results.update(part)
    return results


@pytest.fixture(scope="module")
def scene_files_ready():
    project.ensure_scene_data(verbose=False)


@pytest.fixture(scope="module")
def shipped_renders(scene_files_ready, tmp_path_factory):
    paths = [p for p in SCENE_FILES if not data_missing(p)]
    return render_in_children(paths, tmp_path_factory.mktemp("renders"))


@pytest.fixture(params=SCENE_FILES, ids=[p.stem for p in SCENE_FILES])
def shipped(request, shipped_renders):
    path = request.param
    reason = data_missing(path)
    if reason:
        pytest.skip(reason)
    return path, shipped_renders[path]


def rendered(shipped):
    """The scene's child result, failing the test with the child's error if it has one."""
    path, result = shipped
    assert "error" not in result, f"{path.name}: {result['error']}\n{result.get('trace', '')}"
    return path, result


def test01_the_analytic_scenes_are_shipped():
    names = {p.name for p in SCENE_FILES}
    assert {"analytic_sphere.xml", "analytic_spike.xml", "analytic_torus.xml",
            "sphere_wake.xml", "sphere_wake_volume.xml", "plt_eb_3d.xml"} <= names
    for path in SCENE_FILES:
        text = path.read_text()
        for name in ("spp", "resx", "resy", "method", "reconstruction", "step_scale"):
            assert f'<default name="{name}"' in text, (path.name, name)


def test02_every_scene_renders_without_nan_or_inf(shipped):
    """At 32 x 32 pixels (the scenes' ``resx``/``resy`` defaults overridden) every scene gives
    a finite image in which something is lit."""
    path, result = rendered(shipped)
    img = np.load(result["image"])
    assert img.shape == (32, 32, 3)
    assert np.all(np.isfinite(img)), f"{path.name}: {np.sum(~np.isfinite(img))} NaN/Inf values"
    assert img.max() > 0.05 and img.std() > 0.01, f"{path.name}: the image is blank"


def test03_every_scene_exposes_integrator_isovalue_and_step_scale(shipped):
    """The integrator docstring promises ``integrator.isovalue`` and ``integrator.step_scale``
    in ``mi.traverse(scene)``; Mitsuba names parameters after the object's id, so every scene
    must give its integrator ``id="integrator"``."""
    path, result = rendered(shipped)
    keys = set(result["keys"])
    assert {"integrator.isovalue", "integrator.step_scale"} <= keys, sorted(keys)


def test04_the_render_command_writes_an_image(scene_files_ready, tmp_path):
    """``python -m mi_amr render SCENE -o OUT`` as the README shows it, on a tiny image."""
    out = tmp_path / "sphere.exr"
    proc = subprocess.run([sys.executable, "-m", "mi_amr", "render",
                           str(SCENES / "analytic_sphere.xml"), "-o", str(out),
                           "--resolution", "24", "24"], capture_output=True, text=True,
                          timeout=TIME_LIMIT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    img = np.array(mi.Bitmap(str(out)), dtype=np.float64)
    assert img.shape[:2] == (24, 24)
    assert np.all(np.isfinite(img)) and img[12, 12, :3].sum() > 0.1


# ---------------------------------------------------------------------- parameter mistakes

SENSOR = """
    <sensor type="perspective">
        <transform name="to_world">
            <lookat origin="0.5, 0.5, 3" target="0.5, 0.5, 0.5" up="0, 1, 0"/>
        </transform>
        <film type="hdrfilm">
            <integer name="width" value="8"/>
            <integer name="height" value="8"/>
        </film>
    </sensor>
"""


def write_scene(path, params):
    """A scene file whose amr_iso integrator gets ``params``: name -> (tag, value)."""
    body = "\n".join(f'        <{tag} name="{name}" value="{value}"/>'
                     for name, (tag, value) in params.items())
    path.write_text(f'<scene version="3.0.0">\n    <integrator type="amr_iso">\n{body}\n'
                    f'    </integrator>\n{SENSOR}</scene>\n')
    return path


BASE = {"filename": ("string", "sphere.npz"), "field": ("string", "f"),
        "isovalue": ("float", "0.3")}

MISTAKES = {
    "unknown-parameter": ({"colour": ("string", "red")},
                          r"amr_iso: unknown parameter\(s\) 'colour'( \(did you mean '\w+'\?\))?; "
                          r"allowed: filename, field"),
    "bad-method": ({"method": ("string", "fast")},
                   r"amr_iso: parameter 'method' must be one of exact, bisect, adaptive, "
                   r"uniform; got 'fast'"),
    "bad-reconstruction": ({"reconstruction": ("string", "cubic")},
                           r"parameter 'reconstruction' must be one of basis, finest; "
                           r"got 'cubic'"),
    "bad-mode": ({"mode": ("string", "cloud")},
                 r"amr_iso: parameter 'mode' must be one of surface, volume; got 'cloud'"),
    "step-scale-zero": ({"step_scale": ("float", "0")},
                        r"amr_iso: parameter 'step_scale' must be a number in \[0\.0001, 64\], "
                        r"got 0"),
    "step-scale-negative": ({"step_scale": ("float", "-0.5")},
                            r"parameter 'step_scale' must be a number in \[0\.0001, 64\], "
                            r"got -0\.5"),
    "colormap-short-colour": ({"color_field": ("string", "f"),
                               "colormap": ("string", "0.1: 1 0 0, 0.5: 0 1")},
                              r"colormap: '0\.5: 0 1' needs a value and 3 colour components"),
    "colormap-unreadable": ({"color_field": ("string", "f"),
                             "colormap": ("string", "0.1: 1 0 0, high: 0 1 0")},
                            r"colormap: cannot read 'high: 0 1 0'; expected 'value: r g b' pairs"),
    "colormap-unknown-name": ({"color_field": ("string", "f"),
                               "colormap": ("string", "not_a_map")},
                              r"colormap 'not_a_map' is not a matplotlib colour map"),
    "colormap-without-field": ({"colormap": ("string", "viridis")},
                               r"'color_field' and 'colormap' go together"),
    "isovalue-missing": ({"isovalue": None}, r"amr_iso: parameter 'isovalue' is required"),
    "iso-opacity-above-1": ({"iso_opacity": ("float", "1.5")},
                            r"amr_iso: parameter 'iso_opacity' needs 1 value in \(0, 1\], "
                            r"got 1\.5"),
    "iso-opacity-zero": ({"iso_opacity": ("float", "0")},
                         r"parameter 'iso_opacity' needs 1 value in \(0, 1\]"),
    "missing-data-file": ({"filename": ("string", "data/nothing.npz")},
                          r"amr_iso: parameter 'filename': data/nothing\.npz not found .*"
                          r"'python -m mi_amr data'"),
}


@pytest.mark.parametrize("case", sorted(MISTAKES))
def test05_parameter_mistakes_give_the_documented_messages(tmp_path, sphere_file, case):
    """Each mistake ends as one AMRError naming the parameter and what is allowed (through
    :func:`mi_amr.integrator.load_scene`, which unwraps Mitsuba's plugin error), never as a
    traceback."""
    changes, message = MISTAKES[case]
    (tmp_path / "sphere.npz").symlink_to(sphere_file)
    params = {**BASE, **changes}
    params = {k: v for k, v in params.items() if v is not None}
    path = write_scene(tmp_path / "scene.xml", params)
    with pytest.raises(AMRError, match=message) as info:
        load_scene(path)
    assert "Traceback" not in str(info.value)


def test05b_a_bad_colour_map_is_refused_before_the_volume_is_read(tmp_path, sphere_file,
                                                                   monkeypatch):
    """A colour map that is not one (an unknown name, an unreadable pair) is refused while the
    parameters are read, before a file of perhaps many gigabytes is read and prepared; also
    where the colour field is switched off (``color_field=none``: a typo is a typo, even in a
    map not drawn)."""
    import mi_amr.readers

    (tmp_path / "sphere.npz").symlink_to(sphere_file)
    reads = []
    monkeypatch.setattr(mi_amr.readers, "load", lambda *a, **kw: reads.append(a))
    for field in ("f", "none"):
        for spec in ("not_a_map", "0.1: 1 0 0, high: 0 1 0"):
            params = {**BASE, "color_field": ("string", field), "colormap": ("string", spec)}
            path = write_scene(tmp_path / "scene.xml", params)
            with pytest.raises(AMRError, match="colormap"):
                load_scene(path)
    assert reads == []


def test06_a_valid_scene_file_of_the_same_shape_loads(tmp_path, sphere_file):
    """The baseline of the mistakes above is itself correct (so each error is the mistake's)."""
    (tmp_path / "sphere.npz").symlink_to(sphere_file)
    scene = load_scene(write_scene(tmp_path / "scene.xml", BASE))
    assert "amr_iso" in str(scene.integrator()) or "AMRIso" in str(scene.integrator())


# ---------------------------------------------------------------------- changing parameters

def render_kernels_compiled(scene):
    """Render, returning the image and how many JIT kernels launched during the render were
    compiled (not found in Dr.Jit's kernel cache)."""
    dr.kernel_history()  # clear
    img = render(scene)
    history = dr.kernel_history()
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    assert jit, "no kernel launched"
    return img, sum(1 for k in jit if not k.get("cache_hit", False))


def test07_isovalue_and_step_scale_change_without_recompiling(scene_files_ready):
    """``integrator.isovalue`` and ``integrator.step_scale`` from ``mi.traverse``: a new value
    renders a different image with the kernels already compiled."""
    scene = load_scene(SCENES / "analytic_sphere.xml", resx=32, resy=32, method="adaptive")
    params = mi.traverse(scene)
    assert list(params["integrator.isovalue"]) == pytest.approx([0.3])
    assert list(np.atleast_1d(params["integrator.step_scale"])) == pytest.approx([0.5])
    before = render(scene)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        same, compiled = render_kernels_compiled(scene)
        assert compiled == 0
        np.testing.assert_allclose(same, before, rtol=0, atol=1e-5)

        params["integrator.isovalue"] = mi.Float([0.22])
        params.update()
        smaller, compiled = render_kernels_compiled(scene)
        assert compiled == 0, f"{compiled} kernel(s) compiled after an isovalue change"
        # A smaller sphere: fewer pixels covered.
        assert (smaller.sum(axis=2) > 0).sum() < (before.sum(axis=2) > 0).sum()

        params["integrator.step_scale"] = 2.0
        params.update()
        coarse, compiled = render_kernels_compiled(scene)
        assert compiled == 0, f"{compiled} kernel(s) compiled after a step_scale change"
        assert np.abs(coarse - smaller).max() > 1e-3
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def volume_scene(sphere_file, res=48, **integrator):
    return {
        "type": "scene",
        "integrator": {"type": "amr_iso", "filename": str(sphere_file), "field": "f",
                       "isovalue": 0.3, **integrator},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0.5, 0.5, 3],
                                                             target=[0.5, 0.5, 0.5], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "pixel_format": "rgb", "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "light": {"type": "directional", "direction": [0.3, -0.2, -1],
                  "irradiance": {"type": "rgb", "value": 2.5}},
    }


def test08_opacity_correction_keeps_volume_brightness_when_the_step_changes(sphere_file):
    """Volume mode, adaptive sampling, an opacity band two cells thick: at step scale 0.25 and
    0.1 (2.5 times as many samples in the band) the mean brightness is within 3 %."""
    scene = mi.load_dict(volume_scene(sphere_file, mode="volume", method="adaptive",
                                      band_width=0.02, step_scale=0.25))
    params = mi.traverse(scene)
    coarse = render(scene)
    params["integrator.step_scale"] = 0.1
    params.update()
    fine = render(scene)
    assert np.all(np.isfinite(coarse)) and np.all(np.isfinite(fine))
    assert fine.mean() > 0.05
    assert abs(coarse.mean() / fine.mean() - 1.0) < 0.03, (coarse.mean(), fine.mean())


def test08b_exact_volume_mode_lights_the_band_where_its_light_comes_from(sphere_file):
    """Volume mode with shadows, a band thin against a cell: exact (one pre-integrated piece per
    cell, lit once) agrees with uniform steps of 0.05 cells (each sample lit where it is), to
    within 4 % relative RMSE at the same pixel positions. Lit at the middle of the cell's piece
    instead of where the band makes its opacity, exact was 31 % off. (The shadows exact too:
    the default's correction adds noise that this comparison would measure instead.)"""
    images = {}
    for method, step in (("exact", 0.5), ("uniform", 0.05)):
        scene = mi.load_dict(volume_scene(sphere_file, mode="volume", method=method,
                                          band_width=0.01, step_scale=step,
                                          volume_shadows="exact"))
        images[method] = render(scene)
    err = np.sqrt(np.mean((images["exact"] - images["uniform"]) ** 2))
    rel = err / np.sqrt(np.mean(images["uniform"] ** 2))
    assert images["uniform"].mean() > 0.05
    assert rel < 0.04, rel


def test08c_exact_volume_mode_adds_no_noise_of_its_own(scene_data_ready):
    """The analytic sphere at 64^2, 1 spp, directional light: two renders with different seeds
    differ only where the pixel sample positions move, so volume mode (exact, the default band)
    changes by no more than 1.2 times what surface mode does (measured: 1.16; lit at the
    middle of each cell's piece it was 4.7)."""
    def seed_change(**integrator):
        scene = load_scene(SCENES / "analytic_sphere.xml", resx=64, resy=64, spp=1,
                           integrator=integrator or None)
        a, b = render(scene), np.array(mi.render(scene, seed=1), dtype=np.float64)
        return np.sqrt(np.mean((a - b) ** 2) / np.mean(b ** 2))

    surface, volume = seed_change(), seed_change(mode="volume")
    assert surface > 0.01
    assert volume < 1.2 * surface, (volume, surface)


# ---------------------------------------------------------------------- meshes and isosurfaces

LIGHT = np.array([0.8, 0.0, -1.0])     # direction the light travels: from the upper left (-x)
TOWARDS_LIGHT = -LIGHT / np.linalg.norm(LIGHT)
CENTRE = np.array([0.5, 0.5, 0.5])


def mesh_scene(sphere_file, blocker=None, res=96, **integrator):
    """The analytic sphere isosurface (green) above a blue floor at z = -0.3, seen from above,
    lit by a directional light from the upper left; ``blocker`` = (centre, radius) adds a red
    ball."""
    scene = {
        "type": "scene",
        "integrator": {"type": "amr_iso", "filename": str(sphere_file), "field": "f",
                       "isovalue": 0.3, "iso_color": "0.1 0.8 0.1", **integrator},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0.5, 0.5, 4],
                                                             target=[0.5, 0.5, 0.5], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "pixel_format": "rgb", "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "light": {"type": "directional", "direction": LIGHT.tolist(),
                  "irradiance": {"type": "rgb", "value": 3.0}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0.5, 0.5, -0.3]).scale(3.0),
                  "bsdf": {"type": "diffuse",
                           "reflectance": {"type": "rgb", "value": [0.15, 0.15, 0.8]}}},
    }
    if blocker is not None:
        scene["blocker"] = {"type": "sphere", "center": list(blocker[0]), "radius": blocker[1],
                            "bsdf": {"type": "diffuse",
                                     "reflectance": {"type": "rgb", "value": [0.85, 0.1, 0.1]}}}
    return mi.load_dict(scene)


def dominant(img, channel):
    """Pixels whose ``channel`` (0 red, 1 green, 2 blue) is at least twice each other one."""
    others = [c for c in range(3) if c != channel]
    return np.all(img[..., [channel]] > 2 * img[..., others], axis=-1) & (img[..., channel] > 0)


def luminance(img):
    return img.sum(axis=-1)


def test09_a_mesh_in_front_occludes_the_isosurface(sphere_file):
    """A small red ball between the camera and the isosurface: the pixels of its silhouette
    show the ball alone, where without it they show the isosurface."""
    plain = render(mesh_scene(sphere_file))
    front = render(mesh_scene(sphere_file, blocker=(CENTRE + [0, 0, 0.8], 0.08)))
    ball = dominant(front, 0)
    iso = dominant(plain, 1)
    assert ball.sum() >= 12
    assert np.all(iso[ball]), "the ball covers pixels that are not isosurface without it"
    # Nothing of the green surface shows through the ball.
    assert np.all(front[ball][:, 1] < 0.3 * front[ball][:, 0])
    # The centre of the image is the ball's.
    assert ball[48, 48] and iso[48, 48]


def test10_a_mesh_shadows_the_isosurface(sphere_file):
    """A ball between the light and the isosurface darkens the isosurface pixels in its shadow
    (compared with the ball moved out of the light), and brightens none."""
    spot = CENTRE + 0.3 * TOWARDS_LIGHT              # where the light meets the surface first
    shadowing = render(mesh_scene(sphere_file, blocker=(spot + 0.5 * TOWARDS_LIGHT, 0.08)))
    away = render(mesh_scene(sphere_file, blocker=(spot + 0.5 * TOWARDS_LIGHT - [0, 3, 0], 0.08)))
    iso = dominant(away, 1)
    assert iso.sum() > 300
    darker = iso & (luminance(shadowing) < 0.6 * luminance(away))
    assert darker.sum() >= 4, "no shadow of the ball on the isosurface"
    # The shadowed pixels still show the (green, ambient-lit) isosurface, not the ball.
    assert np.all(dominant(shadowing, 1)[darker])
    assert np.all(luminance(shadowing)[iso] <= luminance(away)[iso] * 1.01 + 1e-6)


def test11_the_isosurface_shadows_the_floor_unless_shadows_are_off(sphere_file):
    """The isosurface casts a shadow onto the floor on the side away from the light; with
    ``shadows=false`` the floor is evenly lit."""
    lit = render(mesh_scene(sphere_file))
    unshadowed = render(mesh_scene(sphere_file, shadows=False))
    floor = dominant(unshadowed, 2)
    iso = dominant(unshadowed, 1)
    assert floor.sum() > 3000 and iso.sum() > 300
    shadow = floor & (luminance(lit) < 0.6 * luminance(unshadowed))
    assert shadow.sum() > 100, "no isosurface shadow on the floor"
    # shadows=false: every floor pixel gets the same light.
    f = luminance(unshadowed)[floor]
    assert f.max() < 1.02 * f.min()
    # The shadow lies on the far side of the surface from the light: compare with the image
    # position of a point of the floor towards the light.
    cols = np.nonzero(shadow)[1].mean() - np.nonzero(iso)[1].mean()
    towards = render(mesh_scene(sphere_file, blocker=(CENTRE + 0.6 * TOWARDS_LIGHT, 0.05)))
    ball = dominant(towards, 0)
    assert ball.sum() > 0
    ball_cols = np.nonzero(ball)[1].mean() - np.nonzero(iso)[1].mean()
    assert cols * ball_cols < 0, (cols, ball_cols)


# ---------------------------------------------------------------------- variants

def test12_importing_after_set_variant_registers_amr_iso(sphere_file):
    """In a fresh interpreter: ``mi.set_variant`` then ``import mi_amr`` is all it takes."""
    code = textwrap.dedent(f"""
        import mitsuba as mi
        mi.set_variant("{VARIANT}")
        import mi_amr
        integrator = mi.load_dict({{"type": "amr_iso", "filename": {str(sphere_file)!r},
                                    "field": "f", "isovalue": 0.3}})
        print(type(integrator).__name__, isinstance(integrator, mi.SamplingIntegrator))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["AMRIsoIntegrator", "True"]


def sphere_scene_dict(sphere_file, res):
    return {
        "type": "scene",
        "integrator": {"type": "amr_iso", "filename": str(sphere_file), "field": "f",
                       "isovalue": 0.3},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0.5, 0.5, 2],
                                                             target=[0.5, 0.5, 0.5], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "pixel_format": "rgb", "rfilter": {"type": "box"}}},
        "light": {"type": "directional", "direction": [0, 0, -1]},
    }


def test13_register_again_after_switching_variants(sphere_file):
    """llvm_ad_rgb -> scalar_rgb -> llvm_ad_rgb, calling :func:`mi_amr.register` after each
    switch: in scalar_rgb the plugin is the integrator's own class (its parameter check runs),
    and back on llvm_ad_rgb a scene renders."""
    if "scalar_rgb" not in mi.variants():
        pytest.skip("scalar_rgb is not available")
    try:
        mi.set_variant("scalar_rgb")
        mi_amr.register()
        with pytest.raises(RuntimeError, match=r"amr_iso: unknown parameter\(s\) 'nope'"):
            mi.load_dict({"type": "amr_iso", "filename": str(sphere_file), "field": "f",
                          "isovalue": 0.3, "nope": 1})
    finally:
        mi.set_variant(VARIANT)
    mi_amr.register()
    img = render(mi.load_dict(sphere_scene_dict(sphere_file, 16)))
    assert np.all(np.isfinite(img)) and img[8, 8].sum() > 0.1


SCALAR_CHILD = """
import sys, json, numpy as np, mitsuba as mi
mi.set_variant("scalar_rgb")
import mi_amr
scene = json.loads(sys.argv[1])
scene["sensor"]["to_world"] = mi.ScalarTransform4f().look_at(**scene["sensor"]["to_world"])
np.save(sys.argv[2], np.array(mi.render(mi.load_dict(scene), seed=0), dtype=np.float64))
"""


def test14_scalar_variant_renders_a_tiny_image(sphere_file, tmp_path):
    """scalar_rgb, 8 x 8 pixels, one ray through each pixel centre (a stratified sampler
    without jitter): the same image as llvm_ad_rgb, since both run the same kernels. (In a
    fresh process: once dr.JitFlag.KernelHistory has been switched on, as other tests here do,
    Mitsuba's scalar variants can no longer find a Python integrator's sample().)"""
    if "scalar_rgb" not in mi.variants():
        pytest.skip("scalar_rgb is not available")
    look = {"origin": [0.5, 0.5, 2], "target": [0.5, 0.5, 0.5], "up": [0, 1, 0]}
    scene = sphere_scene_dict(sphere_file, 8)
    scene["sensor"]["sampler"] = {"type": "stratified", "sample_count": 1, "jitter": False}
    llvm = render(mi.load_dict(scene))
    scene["sensor"]["to_world"] = look
    out = tmp_path / "scalar.npy"
    proc = subprocess.run([sys.executable, "-c", SCALAR_CHILD, json.dumps(scene), str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    scalar = np.load(out)
    assert np.all(np.isfinite(scalar))
    assert (llvm.sum(axis=2) > 0).sum() > 10
    np.testing.assert_allclose(scalar, llvm, atol=2e-3)

# ---------------------------------------------------------------------- scene files and output

def test15_every_scene_reads_filename_from_a_default_and_names_its_light():
    """``-D filename=...`` swaps the data file of any repository scene, and every emitter has
    an ``id``, so ``mi.traverse`` names its parameters ``light.*``, not ``object_1398...``."""
    import xml.etree.ElementTree as ET

    for path in SCENE_FILES:
        root = ET.parse(path).getroot()
        defaults = {d.get("name") for d in root.iter("default")}
        assert "filename" in defaults, path.name
        strings = {s.get("name"): s.get("value") for s in root.find("integrator").iter("string")}
        assert strings["filename"] == "$filename", path.name
        # A light is an emitter, or a shape holding one (an area light): each has an id.
        lights = root.findall("emitter") + [s for s in root.findall("shape")
                                            if s.find("emitter") is not None]
        assert lights and all(e.get("id") for e in lights), path.name


def test16_the_light_is_traversable_by_its_id(shipped):
    path, result = rendered(shipped)
    assert any(k.startswith("light.") for k in result["keys"]), (path.name, result["keys"])


def test17_D_filename_swaps_the_data_file(scene_files_ready, monkeypatch):
    scene = SCENES / "analytic_sphere.xml"
    sphere = render(load_scene(scene, resx=16, resy=16))
    torus_file = SCENES / "data" / "torus.npz"
    torus = render(load_scene(scene, resx=16, resy=16, filename=str(torus_file)))
    assert np.abs(sphere - torus).max() > 0.1
    # A relative name is found from the current folder too.
    monkeypatch.chdir(torus_file.parent)
    again = render(load_scene(scene, resx=16, resy=16, filename=torus_file.name))
    np.testing.assert_allclose(again, torus, atol=1e-5)     # (the same file, maybe loaded anew)


def render_output_cases(tmp_path):
    """``(output, extra arguments, message)`` for image paths that cannot be written."""
    afile = tmp_path / "afile.txt"
    afile.write_text("a file, not a folder")
    folder = tmp_path / "folder.png"
    folder.mkdir()
    existing = tmp_path / "keep.png"
    existing.write_bytes(b"an image")
    return [
        (afile / "out.png", [], f"{afile / 'out.png'}: {afile} is a file, not a folder"),
        (Path("/proc/x.png"), [], "/proc/x.png: cannot write in folder /proc"),
        (Path("/proc/x.png"), ["--force"], "/proc/x.png: cannot write in folder /proc"),
        (folder, ["--force"], f"{folder}: is a folder; give the name of a file to write"),
        (folder, [], f"{folder}: is a folder; give the name of a file to write"),
        (existing, [], f"{existing}: file exists; pass --force to replace it"),
        (tmp_path / "x.jpg", [], f"{tmp_path / 'x.jpg'}: the image must end in .png or .exr"),
    ]


def test18_render_output_paths_are_checked_before_the_work(tmp_path, capsys):
    """One ``error:`` line about the output, before the scene is read (the scene file given
    does not exist, so an error about it would mean the work had started), nothing written."""
    for output, extra, message in render_output_cases(tmp_path):
        before = sorted(tmp_path.rglob("*"))
        code = cli_main(["render", str(tmp_path / "no_such_scene.xml"), "-o",
                                str(output), *extra])
        captured = capsys.readouterr()
        assert code == 2, (output, captured.err)
        lines = captured.err.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {message}"), captured.err
        assert sorted(tmp_path.rglob("*")) == before
    assert (tmp_path / "keep.png").read_bytes() == b"an image"


def test19_a_failed_image_write_leaves_the_old_file(scene_files_ready, tmp_path, monkeypatch):
    """The image goes to a temporary file that is renamed: a write that fails half-way (as
    libpng does after the render) leaves an existing image as it was and no other file."""
    from mi_amr.workflows.render import render_file

    keep = tmp_path / "keep.png"
    render_file(SCENES / "analytic_sphere.xml", keep, resolution=(8, 8), quiet=True)
    before = keep.read_bytes()

    def broken(self, target, *args, **kwargs):
        if isinstance(target, (str, Path)):
            Path(target).write_bytes(b"\x89PNG half an image")
        raise RuntimeError("[bitmap.cpp] Fatal libpng error: Invalid IHDR data")

    monkeypatch.setattr(mi.Bitmap, "write", broken)
    with pytest.raises(AMRError, match=re.escape(f"{keep}: cannot write the image") +
                       r".*libpng.*existing file is unchanged"):
        render_file(SCENES / "analytic_sphere.xml", keep, resolution=(8, 8), overwrite=True,
                    quiet=True)
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]
    assert keep.read_bytes() == before
    with pytest.raises(AMRError, match="cannot write the image"):
        render_file(SCENES / "analytic_sphere.xml", tmp_path / "new.exr", resolution=(8, 8),
                    quiet=True)
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


def test20_png_wider_than_libpng_allows_is_refused_before_rendering(scene_files_ready, tmp_path,
                                                                    monkeypatch):
    """``render S.xml -o keep.png --resolution 2000000 1 --force`` failed inside libpng after
    the render and left keep.png at 0 bytes."""
    from mi_amr.workflows.render import render_file

    keep = tmp_path / "keep.png"
    keep.write_bytes(b"an image")

    def no_render(*args, **kwargs):
        raise AssertionError("rendered before the image size was checked")

    monkeypatch.setattr(mi, "render", no_render)
    message = r"keep\.png: a PNG image can be at most 1,000,000 pixels a side .*2000000x1"
    with pytest.raises(AMRError, match=message):
        render_file(SCENES / "analytic_sphere.xml", keep, resolution=(2000000, 1),
                    overwrite=True, quiet=True)
    with pytest.raises(AMRError, match=message):     # the size from the scene's defaults
        render_file(SCENES / "analytic_sphere.xml", keep, defines={"resx": "2000000",
                                                                   "resy": "1"},
                    overwrite=True, quiet=True)
    assert keep.read_bytes() == b"an image"


def test21_a_write_the_disk_refuses_is_an_error_not_an_empty_image(scene_files_ready,
                                                                   tmp_path):
    """Mitsuba's file writer does not report a write the system refuses: ``render`` wrote an
    empty file in the image's place and said it was done. Here a file size limit of 0 bytes
    (RLIMIT_FSIZE, as a full disk refuses with ENOSPC) refuses the bytes."""
    resource = pytest.importorskip("resource")
    from mi_amr.workflows.render import render_file

    keep = tmp_path / "keep.png"
    render_file(SCENES / "analytic_sphere.xml", keep, resolution=(8, 8), quiet=True)
    before = keep.read_bytes()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    for name in ("keep.png", "new.exr"):
        resource.setrlimit(resource.RLIMIT_FSIZE, (0, hard))
        try:
            with pytest.raises(AMRError, match=re.escape(f"{tmp_path / name}: cannot write "
                                                         "the image")):
                render_file(SCENES / "analytic_sphere.xml", tmp_path / name, resolution=(8, 8),
                            overwrite=True, quiet=True)
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]
    assert keep.read_bytes() == before
