"""mi_amr.peers: the mesh route (scikit-image marching cubes per grid) and yt's volume renderer,
run on the analytic sphere and scored against its exact reference hit buffers (VTK's AMR
contour routes: tests/test_peers_vtk.py).

The sphere (radius 0.3 around (0.5, 0.5, 0.5)) is cut in half by the coarse/fine boundary at
x = 0.5, so a mesh built grid by grid must crack there and mi_amr must not. The peers are
optional (``pip install 'mi_amr[peers]'``): their checks skip when the package is missing, and
run_peers must report a missing package as a row, not fail.
"""

import importlib.util
import math
import sys

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

import mi_amr  # noqa: E402
from mi_amr.evaluation import peers  # noqa: E402
from mi_amr.workflows import project  # noqa: E402
from mi_amr.synthetic.datasets import sphere  # noqa: E402

VARIANT = "llvm_ad_rgb"
if VARIANT not in mi.variants():
    pytest.skip(f"Mitsuba variant {VARIANT} is not available", allow_module_level=True)

SCENE = "analytic_sphere"
needs_skimage = pytest.mark.skipif(importlib.util.find_spec("skimage") is None,
                                   reason=f"scikit-image is not installed ({peers.INSTALL_HINT})")
needs_yt = pytest.mark.skipif(importlib.util.find_spec("yt") is None,
                              reason=f"yt is not installed ({peers.INSTALL_HINT})")


@pytest.fixture(scope="module", autouse=True)
def _variant(scene_data_ready):
    yield


@pytest.fixture(scope="module")
def mesh_row():
    return peers.marching_cubes_route(SCENE)


def test01_near_level_boundary_is_the_coarse_fine_face():
    # The sphere's level 1 covers x > 0.5 of the unit cube; its other faces are domain faces.
    vol = sphere()
    h = peers._finest_spacing(vol)
    points = np.array([[0.5 - 0.5 * h, 0.5, 0.5], [0.5 + 1.5 * h, 0.3, 0.7],
                       [0.5 + 2.5 * h, 0.5, 0.5], [0.2, 0.5, 0.5], [0.25, 0.5 * h, 0.5],
                       [0.75, 0.5, 1.0 - 0.5 * h]])
    near = peers.near_level_boundary(vol, points, 2.0 * h)
    assert near.tolist() == [True, True, False, False, False, False]
    kinds = peers.boundaries_near(vol, points, 2.0 * h)
    assert kinds["domain"].tolist() == [False, False, False, False, True, True]
    assert not kinds["seam"].any()


def test02_seams_within_a_level(reference_volume):
    # conftest's hierarchy: two level-0 grids share the face x = 4, two level-1 grids the face
    # y = 4 (for x in [2, 4]); (4.1, 3, 3) lies deep inside one level-2 grid.
    points = np.array([[4.1, 7.0, 7.0], [4.1, 3.0, 3.0], [2.5, 4.0, 3.0], [1.0, 7.0, 7.0]])
    kinds = peers.boundaries_near(reference_volume, points, 0.25)
    assert kinds["seam"].tolist() == [True, False, True, False]
    assert kinds["level"].tolist() == [False, False, False, False]


@needs_skimage
def test03_marching_cubes_mask_agrees_with_the_reference(mesh_row):
    assert mesh_row["scene"] == SCENE and mesh_row["peer"] == "marching_cubes"
    agree = 1.0 - mesh_row["missed"] - mesh_row["false"]
    assert agree > 0.97, mesh_row
    # Trilinear triangles are not the exact surface: small, but not zero.
    assert 0.0 < mesh_row["depth_mean"] < 1.0, mesh_row
    assert mesh_row["normal_mean"] > 0.0
    assert mesh_row["time_s"] > 0.0 and set(mesh_row) == set(peers.ROW_KEYS)
    assert set(mesh_row["time_detail"]) >= {"marching_cubes", "mesh", "render"}


@needs_skimage
def test04_marching_cubes_cracks_at_the_level_boundary(mesh_row):
    assert mesh_row["cracks"] > 0.0, mesh_row
    ghost = peers.marching_cubes_route(SCENE, ghost_cells=True)
    # Ghost cells close what a grid alone leaves open, not the mismatch between levels.
    assert 0.0 < ghost["cracks"] <= mesh_row["cracks"], (ghost, mesh_row)


def test05_mi_amr_route_has_no_cracks():
    row = peers.mi_amr_route(SCENE)
    assert row["peer"] == "mi_amr exact"
    assert row["missed"] == 0.0 and row["false"] == 0.0 and row["cracks"] == 0.0, row
    assert row["depth_p99"] < 1e-3
    assert {"load", "first_frame", "warm_frame"} <= set(row["time_detail"])


@needs_yt
def test06_yt_mask_matches_with_its_camera():
    row = peers.yt_volume_route(SCENE)
    # The camera maps onto Mitsuba's pixel centres: a shifted or mirrored image would miss
    # and falsely hit far more than the Gaussian band's rim of a pixel or two.
    assert row["missed"] < 0.01 and row["false"] < 0.05, row
    assert all(math.isnan(row[k]) for k in ("depth_mean", "depth_p99", "normal_mean", "cracks"))


def test07_run_peers_reports_missing_packages(monkeypatch):
    hidden = ("skimage", "yt", "vtk", "vtkmodules")
    for name in list(sys.modules):
        if name.split(".")[0] in hidden:
            monkeypatch.delitem(sys.modules, name)
    for name in hidden:
        monkeypatch.setitem(sys.modules, name, None)
    rows = peers.run_peers((SCENE,), ours=False, progress=False)
    assert [r["peer"] for r in rows] == list(peers.PEERS)
    for r in rows:
        assert r["notes"].startswith(f"skipped: {peers.INSTALL_HINT}"), r
        assert math.isnan(r["time_s"]) and math.isnan(r["missed"])
    table = peers.peers_table(rows).splitlines()
    assert len(table) == 2 + len(rows) and "skipped" in table[-1]
