"""What the command line says when a render would otherwise come out blank without a word."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("iso,code,says", [
    ("99", 0, "outside the range [0.0270633, 0.838962] of field 'f'"),
    ("1e39", 2, "error: amr_iso: parameter 'isovalue' must fit in float32")])
def test01_an_isovalue_outside_the_data_is_warned_about(tmp_path, iso, code, says,
                                                        scene_data_ready):
    """``-D isovalue=99`` renders an empty image and stderr gives the field's range; 1e39
    (inf in float32) is refused."""
    out = tmp_path / "x.png"
    proc = subprocess.run([sys.executable, "-m", "mi_amr", "render",
                           str(ROOT / "scenes_xml" / "analytic_sphere.xml"), "-o", str(out),
                           "--resolution", "8", "8", "-D", f"isovalue={iso}"],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    text = proc.stdout + proc.stderr
    assert proc.returncode == code, text
    assert says in text


def cli(*args, timeout=300):
    proc = subprocess.run([sys.executable, "-m", "mi_amr", *map(str, args)],
                          capture_output=True, text=True, cwd=ROOT, timeout=timeout)
    return proc.returncode, proc.stdout + proc.stderr


SPHERE = ROOT / "scenes_xml" / "analytic_sphere.xml"


def test02_an_unknown_define_gets_a_did_you_mean_before_loading(tmp_path, scene_data_ready):
    code, text = cli("render", SPHERE, "-o", tmp_path / "x.png", "-D", "isovalu=0.2")
    assert code == 2
    assert "error: -D isovalu: the scene" in text and "(did you mean 'isovalue'?)" in text
    assert "loading" not in text and not (tmp_path / "x.png").exists()


def test03_render_shows_the_load_step_by_step_and_writes_alpha(tmp_path, scene_data_ready):
    """The load prints each step as it ends; the PNG is RGBA with alpha = coverage (the sphere
    on black: transparent corners, opaque centre)."""
    import imageio.v2 as imageio

    out = tmp_path / "x.png"
    code, text = cli("render", SPHERE, "-o", out, "--resolution", "16", "16")
    assert code == 0, text
    assert "kd-tree in" in text and "device arrays in" in text
    img = imageio.imread(out)
    assert img.shape == (16, 16, 4)
    assert img[0, 0, 3] == 0 and img[8, 8, 3] == 255


def test04_render_aovs_writes_the_isosurface_channels(tmp_path, scene_data_ready, variant):
    mi = variant

    out = tmp_path / "x.exr"
    code, text = cli("render", SPHERE, "-o", out, "--resolution", "16", "16", "--aovs")
    assert code == 0, text
    names = {f.name for f in mi.Bitmap(str(out)).struct_()}
    assert {"R", "G", "B", "A", "iso_depth.T", "iso_normal.X", "iso_value.V", "iso_level.L",
            "iso_grid.G"} <= names
    code, text = cli("render", SPHERE, "-o", tmp_path / "x.png", "--aovs")
    assert code == 2 and "--aovs writes a multichannel EXR" in text
