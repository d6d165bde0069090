"""``python -m mi_amr histogram``: value against gradient magnitude over the leaf cells."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mi_amr import AMRError
from mi_amr.synthetic import datasets
from mi_amr.workflows.histogram import histogram_figure, value_and_gradient

pytest.importorskip("matplotlib")
ROOT = Path(__file__).resolve().parents[1]


def test01_the_distance_field_has_unit_gradient():
    """f = |p - c|: every leaf cell once, and |grad f| = 1 away from the centre."""
    vol = datasets.sphere(16)
    v, g = value_and_gradient(vol, "f")
    assert len(v) == vol.num_leaf_cells()
    far = v > 0.15
    np.testing.assert_allclose(np.median(g[far]), 1.0, atol=0.01)


def test02_the_command_writes_its_picture_and_refuses_mistakes(tmp_path):
    path = tmp_path / "s.npz"
    datasets.sphere(8).save(path)
    out = tmp_path / "h.png"
    proc = subprocess.run([sys.executable, "-m", "mi_amr", "histogram", str(path), "--field", "f",
                           "-o", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(AMRError, match="file exists"):
        histogram_figure(path, "f", out)
    with pytest.raises(AMRError, match="unknown field"):
        histogram_figure(path, "nope", tmp_path / "x.png")
