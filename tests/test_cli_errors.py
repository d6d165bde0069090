"""Scene and command-line mistakes that used to end in a raw Mitsuba error or a traceback
(issue 33, items 8, 9 and 11): each is now one ``error:`` line (exit status 2), or is mended the
way Mitsuba itself would."""

import numpy as np
import pytest

from mi_amr.cli import main
from mi_amr.synthetic import datasets

pytest.importorskip("drjit")

INTEGRATOR = """
    <integrator type="amr_iso">
        <string name="filename" value="s.npz"/><string name="field" value="f"/>
        <float name="isovalue" value="0.25"/>
    </integrator>"""
CAMERA = """
        <float name="fov" value="35"/>
        <transform name="to_world">
            <lookat origin="1.7, -1.0, 1.3" target="0.5, 0.5, 0.5" up="0, 0, 1"/>
        </transform>"""
SCENES = {
    # A sensor without a film or sampler: Mitsuba's defaults (hdrfilm 768 x 576, 4 spp).
    "nofilm": f'<scene version="3.0.0">{INTEGRATOR}<sensor type="perspective">{CAMERA}'
              f'</sensor></scene>',
    "nosensor": f'<scene version="3.0.0">{INTEGRATOR}</scene>',
    # Fixed numbers, no <default>s: --resolution and --spp still apply.
    "fixed": f'<scene version="3.0.0">{INTEGRATOR}<sensor type="perspective">{CAMERA}'
             f'<sampler type="independent"><integer name="sample_count" value="1"/></sampler>'
             f'<film type="hdrfilm"><integer name="width" value="32"/>'
             f'<integer name="height" value="32"/></film></sensor></scene>',
}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory, variant):
    folder = tmp_path_factory.mktemp("scenes")
    datasets.sphere(8).save(folder / "s.npz")
    for name, text in SCENES.items():
        (folder / f"{name}.xml").write_text(text)
    return folder


def one_error(capsys, argv, starts):
    """Run ``argv``; it must fail with exactly one line ``error: <starts>...``."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {starts}"), err
    return err[0]


def test01_a_sensor_without_a_film_renders_with_mitsubas_default_film(scenes, tmp_path,
                                                                      capsys):
    """The render asks its films for RGBA; a sensor without a film got Mitsuba's RGB default
    film, and the image failed to be written after the render."""
    import imageio.v2 as imageio

    from mi_amr.plugin.scene import load_scene

    film = load_scene(scenes / "nofilm.xml", pixel_format="rgba").sensors()[0].film()
    assert list(film.size()) == [768, 576] and film.base_channels_count() == 4
    out = tmp_path / "x.png"
    assert main(["render", str(scenes / "nofilm.xml"), "-o", str(out),
                 "--resolution", "24", "16"]) == 0, capsys.readouterr().err
    assert imageio.imread(out).shape == (16, 24, 4)


def test02_a_scene_without_a_sensor_is_one_line(scenes, tmp_path, capsys):
    line = one_error(capsys, ["render", str(scenes / "nosensor.xml"), "-o",
                              str(tmp_path / "x.png")], f"{scenes / 'nosensor.xml'}: ")
    assert "has no <sensor>" in line and not (tmp_path / "x.png").exists()


def test03_resolution_and_spp_apply_to_a_scene_without_their_defaults(scenes, tmp_path,
                                                                       capsys):
    """``--resolution`` and ``--spp`` set the film and sampler directly (they used to be passed
    as resx/resy/spp defaults, which Mitsuba refused as "unused parameters")."""
    import imageio.v2 as imageio

    out = tmp_path / "x.png"
    assert main(["render", str(scenes / "fixed.xml"), "-o", str(out), "--resolution", "20",
                 "10", "--spp", "2"]) == 0, capsys.readouterr().err
    assert "at 2 spp" in capsys.readouterr().out
    img = imageio.imread(out)
    assert img.shape == (10, 20, 4) and img[..., 3].max() == 255


def test04_a_film_of_no_pixels_is_one_line(scenes, tmp_path, capsys):
    from mi_amr.workflows import project

    scene = project.scenes_dir() / "analytic_sphere.xml"
    project.ensure_scene_data(verbose=False)
    line = one_error(capsys, ["render", str(scene), "-o", str(tmp_path / "x.png"),
                              "-D", "resx=0", "-D", "resy=0"], f"{scene}: the film is 0x0")
    assert "must be >= 1" in line


def test05_an_image_too_large_to_render_is_one_line_before_loading(scenes, tmp_path, capsys):
    line = one_error(capsys, ["render", str(scenes / "fixed.xml"), "-o",
                              str(tmp_path / "x.exr"), "--resolution", "100000", "100000"],
                     f"{scenes / 'fixed.xml'}: a 100000x100000 image")
    assert "smaller --resolution" in line
    # The same size reached through -D is refused after loading, before rendering.
    from mi_amr.workflows import project

    scene = project.scenes_dir() / "analytic_sphere.xml"
    project.ensure_scene_data(verbose=False)
    one_error(capsys, ["render", str(scene), "-o", str(tmp_path / "x.exr"), "-D",
                       "resx=100000", "-D", "resy=100000"], f"{scene}: a 100000x100000 image")


def test06_a_variant_this_machine_cannot_run_is_one_line(scenes, tmp_path, capsys,
                                                          monkeypatch):
    """What ``mi.set_variant("cuda_ad_rgb")`` raises on a machine without CUDA (simulated here,
    so the test means the same on a machine with a GPU)."""
    import mitsuba as mi

    real = mi.set_variant

    def no_cuda(name, *rest):
        if name.startswith("cuda"):
            raise ImportError("jit_init_thread_state(): the CUDA backend hasn't been "
                              "initialized. Make sure to call jit_init(JitBackend::CUDA)")
        return real(name, *rest)

    monkeypatch.setattr(mi, "set_variant", no_cuda)
    monkeypatch.setattr(mi, "variants", lambda: ["scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb"])
    line = one_error(capsys, ["render", str(scenes / "fixed.xml"), "-o",
                              str(tmp_path / "x.png"), "--variant", "cuda_ad_rgb"],
                     "variant 'cuda_ad_rgb' cannot run on this machine")
    assert "--variant llvm_ad_rgb" in line and not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("bins", ["1000000", "1"])
def test07_histogram_bins_out_of_range_is_one_line(scenes, tmp_path, capsys, bins):
    one_error(capsys, ["histogram", str(scenes / "s.npz"), "--field", "f", "-o",
                       str(tmp_path / "h.png"), "--bins", bins], "--bins must be ")
    assert not (tmp_path / "h.png").exists()



@pytest.mark.parametrize("port", ["99999", "-1"])
def test07b_a_port_out_of_range_is_one_line_before_loading(scenes, capsys, port):
    """(A port past 65535 ended in a traceback from the socket's bind, after the scene had
    loaded.)"""
    one_error(capsys, ["view", str(scenes / "s.npz"), "--field", "f", "--no-browser",
                       "--port", port], f"view: --port must be 0 (a free one) to 65535, got {port}")


def test07c_explore_refuses_a_port_out_of_range(scenes):
    import mi_amr
    from mi_amr.errors import AMRError
    from mi_amr.workflows.viewer.server import bind

    for port in (70000, -3, 1.5, True):
        with pytest.raises(AMRError, match="port must be a whole number from 0"):
            mi_amr.explore(scenes / "s.npz", field="f", port=port)
        with pytest.raises(AMRError, match="port must be a whole number from 0"):
            bind("127.0.0.1", port)


def test07d_a_data_files_request_is_checked_before_its_scene_is_made(scenes, tmp_path, capsys):
    """A bad output, sample count or -D name of a data file's render is refused before the
    scene is made (its isovalue pick reads the whole file: nothing is printed of it), and -D
    names the parameters a data file's scene takes (not the temporary XML made for it)."""
    data = str(scenes / "s.npz")
    jpg = str(tmp_path / "x.jpg")
    for argv, starts in [(["render", data, "-o", jpg], f"{jpg}: the image must end in"),
                         (["render", data, "-o", str(tmp_path / "x.png"), "--spp", "0"],
                          "--spp must be >= 1"),
                         (["render", data, "-o", str(tmp_path / "x.png"), "-D", "band_width=1"],
                          "-D band_width: a data file's scene takes -D for filename, isovalue"),
                         (["movie", data, "-o", str(tmp_path / "m"), "-D", "isovalu=0.3"],
                          "-D isovalu: a data file's scene")]:
        assert main(argv + ["--field", "f"]) == 2
        out, err = capsys.readouterr()
        err = err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"error: {starts}"), err
        assert "picked from the histogram" not in out, out      # (no pick was made)
    assert "did you mean 'isovalue'?" in err[0] and "--save-scene" in err[0]
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "m").exists()


def test07e_d_isovalue_of_a_data_file_is_its_isovalue(scenes, tmp_path, capsys):
    """``-D isovalue=...`` on a data file makes its scene for that isovalue (the first of a
    list): no other is picked and printed, and the camera frames the isovalues it lists."""
    from mi_amr.plugin.autoscene import data_scene

    data, xml = str(scenes / "s.npz"), tmp_path / "s.xml"
    assert main(["render", data, "--field", "f", "-D", "isovalue=0.3, 0.6", "--resolution",
                 "16", "12", "--spp", "1", "-o", str(tmp_path / "s.png"),
                 "--save-scene", str(xml)]) == 0
    out = capsys.readouterr().out
    assert "isovalue 0.3 (given)" in out and "picked" not in out, out
    # (The framed box sets the volume's placement: its scale differs from the pick's.)
    matrix = [line for line in xml.read_text().splitlines() if "<matrix" in line]
    scale = [float(data_scene(data, "f", v, resolution=(16, 12), framed_values=framed)
                   .framing.to_world[0, 0])
             for v, framed in ((0.3, (0.3, 0.6)), (0.3, None))]
    assert scale[0] != scale[1], scale
    assert matrix and f'value="{scale[0]!r} ' in matrix[0], matrix
    one_error(capsys, ["render", data, "--field", "f", "--isovalue", "0.3", "-D",
                       "isovalue=0.4", "-o", str(tmp_path / "t.png")],
              "--isovalue and -D isovalue both set")
    for text in ("x", "0.3, x", ""):
        one_error(capsys, ["render", data, "--field", "f", "-D", f"isovalue={text}", "-o",
                           str(tmp_path / "t.png")], "-D isovalue: expected a number")

def test08_a_scene_saved_by_the_viewer_keeps_no_stale_defaults(tmp_path, variant, capsys):
    """The viewer writes its values into the scene: a parameter the file gave as ``$name``
    stays so, with the ``<default>`` holding the view's value (``-D`` still applies); a default
    nothing refers to any more is dropped (it used to stay, with the file's old value, and
    ``-D`` accepted its name and changed nothing)."""
    import mitsuba as mi

    from mi_amr.plugin.camera import Camera
    from mi_amr.plugin.scene import load_scene
    from mi_amr.workflows import project
    from mi_amr.workflows.viewer.sceneio import scene_text
    from mi_amr.workflows.viewer.state import ViewState

    project.ensure_scene_data(verbose=False)
    base = project.scenes_dir() / "analytic_sphere.xml"
    text = base.read_text().replace('<float name="fov" value="22"/>',
                                    '<float name="fov" value="$fov"/>')
    text = text.replace('<default name="spp"', '<default name="fov" value="22"/>\n'
                                               '    <default name="spp"')
    scene = tmp_path / "with_fov.xml"
    scene.write_text(text)
    state = ViewState(data_file=str((base.parent / "data" / "sphere.npz").resolve()),
                      field="f", color_field=None, colormap=None, color_range=None,
                      isovalues=(0.2,), iso_colors=((1.0, 0.5, 0.25),), iso_opacity=(1.0,),
                      mode="surface", method="bisect", reconstruction="basis",
                      layers="composite", step_scale=0.25, band_width=(0.01,),
                      band_offsets=((-0.02, 0.02),), band_peak=(1.6,), shadows=True,
                      camera=Camera((1.6, -0.9, 1.4), (0.5, 0.5, 0.5), (0.0, 0.0, 1.0), 30.0),
                      light_direction=None, light_irradiance=None, spp=2)
    saved = tmp_path / "saved.xml"
    saved.write_text(scene_text(scene, state, spp=2, resolution=(16, 12)))
    import xml.etree.ElementTree as ET

    root = ET.parse(str(saved)).getroot()
    defaults = {d.get("name"): d.get("value") for d in root.iter("default")}
    assert defaults == {"filename": state.data_file, "spp": "2", "resx": "16", "resy": "12",
                        "isovalue": "0.2", "method": "bisect", "reconstruction": "basis",
                        "step_scale": "0.25"}
    integ = root.find("integrator")
    assert integ.find("*[@name='isovalue']").get("value") == "$isovalue"
    loaded = load_scene(saved, isovalue="0.25")
    assert float(np.array(mi.traverse(loaded)["integrator.isovalue"]).ravel()[0]) == 0.25
    one_error(capsys, ["render", str(saved), "-o", str(tmp_path / "x.png"), "-D", "fov=10"],
              f"-D fov: the scene {saved} has no default 'fov'")
