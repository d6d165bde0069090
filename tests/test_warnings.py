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
