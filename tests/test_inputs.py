"""Inputs to the Python API and the command line that used to slip through: ray queries with
a text, NaN or out-of-range isovalue or with zero/NaN directions, and the program name the
command line's usage line shows."""

import subprocess
import sys

import numpy as np
import pytest

import mi_amr
from mi_amr import AMRError
from mi_amr.cli import main
from mi_amr.synthetic import datasets


@pytest.fixture(scope="module")
def sphere():
    pytest.importorskip("drjit")
    return datasets.sphere()


def two_rays():
    """Two rays along +z through the sphere's centre column; both hit the isosurface 0.3."""
    return np.array([[0.5, 0.5, -1.0], [0.5, 0.5, -1.0]]), np.array([[0, 0, 1.0], [0, 0, 1.0]])


def test01_trace_accepts_numbers_numpy_numbers_and_lists(sphere):
    o, d = two_rays()
    t = mi_amr.trace(sphere, o, d, field="f", isovalue=0.3).t
    assert np.all(np.isfinite(t))
    np.testing.assert_array_equal(mi_amr.trace(sphere, o, d, field="f",
                                               isovalue=np.float32(0.3)).t, t)
    r = mi_amr.trace(sphere, o, d, field="f", isovalue=[0.3, 0.2])
    assert np.all(r.hit)


@pytest.mark.parametrize("isovalue, message", [
    ("abc", r"isovalue must be a number or a list of numbers, got the text 'abc'"),
    (None, r"isovalue must be a number or a list of numbers, got None"),
    ([0.3, "x"], r"isovalue must be a number or a list of numbers, got \[0\.3, 'x'\]"),
    ([], r"isovalue must hold at least one number"),
    (float("nan"), r"isovalue must hold finite numbers .*got nan"),
    (1e39, r"isovalue must hold finite numbers within float32's range .*got 1e\+39"),
    (np.float64(np.inf), r"isovalue must hold finite numbers .*got inf$"),
])
def test02_trace_refuses_isovalues_that_are_not_finite_numbers(sphere, isovalue, message):
    o, d = two_rays()
    with pytest.raises(AMRError, match=message):
        mi_amr.trace(sphere, o, d, field="f", isovalue=isovalue)


@pytest.mark.parametrize("column, value, what", [
    ("d", (0.0, 0.0, 0.0), "directions"),
    ("d", (np.nan, 0.0, 1.0), "directions"),
    ("d", (1e300, 0.0, 1.0), "directions"),      # infinite in float32
    ("o", (np.inf, 0.5, -1.0), "origins"),
])
def test03_trace_refuses_rays_without_a_defined_path(sphere, column, value, what):
    """Zero or NaN directions used to come back as silent misses."""
    o, d = two_rays()
    (d if column == "d" else o)[1] = value
    with pytest.raises(AMRError, match=rf"{what}: 1 ray\(s\) have .* \(first: ray 1, "):
        mi_amr.trace(sphere, o, d, field="f", isovalue=0.3)


def test04_trace_refuses_ray_arrays_of_the_wrong_shape_or_type(sphere):
    o, d = two_rays()
    with pytest.raises(AMRError, match=r"must both be \(N, 3\) arrays"):
        mi_amr.trace(sphere, o[:, :2], d[:, :2], field="f", isovalue=0.3)
    with pytest.raises(AMRError, match=r"\(N, 3\) arrays of numbers"):
        mi_amr.trace(sphere, [["a", "b", "c"]], [[0, 0, 1]], field="f", isovalue=0.3)


def test05_usage_names_the_program_as_it_was_started(capsys):
    """The installed script is ``mi-amr``; ``python -m mi_amr`` says so itself."""
    with pytest.raises(SystemExit):
        main(["--help"])
    assert capsys.readouterr().out.startswith("usage: mi-amr ")
    run = subprocess.run([sys.executable, "-m", "mi_amr", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.startswith("usage: python -m mi_amr "), run.stderr
