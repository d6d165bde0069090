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


def test03_values_spanning_decades_get_a_log_or_symlog_axis():
    """Q-like values (all negative, from -1.4e6 to -1.4) get a symlog axis, positive values
    over decades a log axis, values within a decade a linear one; --log-value and
    --linear-value force the kind. The bin edges are evenly spaced on the axis."""
    from matplotlib.scale import SymmetricalLogTransform

    from mi_amr.workflows.histogram import _value_edges, value_axis

    rng = np.random.default_rng(0)
    q = -np.exp(rng.uniform(np.log(1.4), np.log(1.4e6), 5000))
    kind, thresh = value_axis(q)
    assert kind == "symlog" and 1.4 <= thresh < 10
    assert value_axis(-q) == ("log", None)
    narrow = rng.uniform(300, 1600, 5000)
    assert value_axis(narrow) == ("linear", None)
    assert value_axis(narrow, "log") == ("log", None)
    assert value_axis(q, "linear") == ("linear", None)
    edges = _value_edges(q, 64, kind, thresh)
    steps = np.diff(SymmetricalLogTransform(10, thresh, 1.0).transform(edges))
    assert np.all(np.diff(edges) > 0) and np.allclose(steps, steps[0], rtol=1e-6)
    assert edges[0] == q.min() and edges[-1] == q.max()
    with pytest.raises(AMRError, match="value axis"):
        value_axis(q, "cubic")


def test04_the_command_takes_log_and_linear_value_axes(tmp_path):
    from mi_amr.cli import main

    path = tmp_path / "s.npz"
    datasets.sphere(8).save(path)
    for flag in ("--log-value", "--linear-value"):
        out = tmp_path / f"h{flag}.png"
        assert main(["histogram", str(path), "--field", "f", "-o", str(out), flag]) == 0
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(SystemExit):         # one or the other
        main(["histogram", str(path), "--field", "f", "-o", str(tmp_path / "x.png"),
              "--log-value", "--linear-value"])
