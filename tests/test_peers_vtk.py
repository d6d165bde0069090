"""mi_amr.evaluation.peers_vtk and the vtk_amr_contour peer routes: VTK's watertight contour of
overlapping AMR (vtkAMRContourFilter, VTK >= 9.7) on the analytic sphere.

The sphere ``f = |p - (0.5, 0.5, 0.5)|`` (isosurface 0.3) is cut by the coarse/fine face
x = 0.5. Split into two grids per level at planes off the sphere's centre, its grids of one
level meet at seams where vertex values made grid by grid disagree: the per-grid route must
crack there, the shared-vertex one must not, and the filter must close the level boundary in
both. VTK is optional (``pip install 'mi_amr[peers]'``): the whole file skips without it.
"""

import numpy as np
import pytest

from mi_amr.core.volume import AMRVolume
from mi_amr.errors import AMRError
from mi_amr.evaluation import peers_vtk
from mi_amr.synthetic.datasets import sphere

try:
    peers_vtk.require_vtk()
except ImportError as e:
    pytest.skip(f"VTK >= 9.7 with vtkAMRContourFilter is not installed "
                f"(pip install 'mi_amr[peers]'): {e}", allow_module_level=True)

BASE = 8
ISO = 0.3
CENTRE = np.array([0.5, 0.5, 0.5])


def split_sphere(base: int = BASE) -> AMRVolume:
    """:func:`sphere` with each level's grid cut in two, level 0 across y and level 1 across z,
    3/8 of the way along (off the centre, so that the cells either side of a seam differ)."""
    grids = []
    for g in sphere(base).grids:
        f = np.asarray(g.fields["f"])
        h = np.asarray(g.spacing)
        axis = 1 if g.level == 0 else 2
        cut = 3 * f.shape[axis] // 8
        # Level-1 grids start on a level-0 cell face.
        cut -= cut % 2 if g.level == 1 else 0
        for part, cells in ((0, slice(0, cut)), (1, slice(cut, None))):
            index = [slice(None)] * 3
            index[axis] = cells
            origin = np.array(g.origin, dtype=np.float64)
            origin[axis] += part * cut * h[axis]
            grids.append({"level": g.level, "origin": tuple(origin), "spacing": tuple(h),
                          "fields": {"f": f[tuple(index)].copy()}})
    return AMRVolume.from_grids(grids)


def shared_values_brute_force(vol, field):
    """Slow twin of shared_vertex_values: for every vertex of every grid, the mean of all the
    level's cells (any grid) that have the vertex as a corner."""
    lo_idx, hi_idx = vol.index_boxes()
    out = []
    for gi, g in enumerate(vol.grids):
        same = np.flatnonzero(vol.levels == g.level)
        vals = np.zeros(tuple(np.asarray(g.shape) + 1))
        for v in np.ndindex(*vals.shape):
            position = lo_idx[gi] + np.asarray(v)
            cells = []
            for j in same:
                # Cells c with c <= position <= c + 1 inside grid j.
                clo = np.maximum(position - 1, lo_idx[j])
                chi = np.minimum(position, hi_idx[j] - 1)
                if np.all(clo <= chi):
                    local = [slice(a - lo_idx[j][k], b - lo_idx[j][k] + 1)
                             for k, (a, b) in enumerate(zip(clo, chi))]
                    cells.append(np.asarray(vol.grids[j].fields[field])[tuple(local)].ravel())
            vals[v] = np.concatenate(cells).mean()
        out.append(vals)
    return out


@pytest.fixture(scope="module")
def meshes():
    """``{(volume, rule): ContourMesh at ISO}`` for the sphere and its split twin."""
    vols = {"sphere": sphere(BASE), "split": split_sphere()}
    return {(name, rule): peers_vtk.AMRContour(vol, "f", rule).mesh(ISO)
            for name, vol in vols.items() for rule in peers_vtk.VERTEX_RULES}


def test01_shared_vertex_values_are_the_level_mean_around_each_vertex():
    vol = split_sphere(4)
    fast = peers_vtk.shared_vertex_values(vol, "f")
    slow = shared_values_brute_force(vol, "f")
    for a, b in zip(fast, slow):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    # Splitting a grid changes no vertex value: the seam's vertices see both sides.
    whole = peers_vtk.shared_vertex_values(sphere(4), "f")
    np.testing.assert_allclose(np.concatenate([fast[0], fast[1][:, 1:]], axis=1), whole[0],
                               atol=1e-12)


def test02_per_grid_values_crack_at_seams_shared_values_do_not(meshes):
    per_grid, shared = meshes["split", "per_grid"], meshes["split", "shared"]
    # The sphere lies inside the domain: every open edge is a crack.
    assert per_grid.open_at_domain == 0 and shared.open_at_domain == 0
    assert per_grid.open_edges > 0, per_grid.open_edges
    assert shared.open_edges == 0
    # The filter closes the coarse/fine face whatever the vertex values.
    assert meshes["sphere", "per_grid"].open_edges == 0
    assert meshes["sphere", "shared"].open_edges == 0
    # Shared values do not depend on how a level is cut into grids, so neither does the
    # surface, but for the filter's interface cells next to a seam (its Shepard-interpolated
    # face and cell centres): the same triangles, vertices within a small part of a cell.
    from scipy.spatial import cKDTree

    whole = meshes["sphere", "shared"]
    assert len(shared.F) == len(whole.F)
    distance, _ = cKDTree(whole.V).query(shared.V)
    fine = 0.5 / BASE
    assert np.mean(distance < 1e-6) > 0.95 and distance.max() < 0.05 * fine, distance.max()


@pytest.mark.parametrize("name", ["sphere", "split"])
@pytest.mark.parametrize("rule", peers_vtk.VERTEX_RULES)
def test03_vertices_lie_near_the_sphere_normals_point_inwards(meshes, name, rule):
    cm = meshes[name, rule]
    r = np.linalg.norm(cm.V - CENTRE, axis=1)
    coarse = 1.0 / BASE
    # Vertex values are means of 8 cells, so the surface is a little inside the sphere; one
    # grid's values at its faces lean further (one-sided means).
    assert np.max(np.abs(r - ISO)) < (0.5 if rule == "shared" else 1.0) * coarse
    # Oriented to lower values of f = |p - c|: towards the centre, close to radial.
    cos = np.sum(cm.N * (CENTRE - cm.V), axis=1) / r
    assert np.all(cos > 0.0), cos.min()
    assert np.median(cos) > 0.99
    np.testing.assert_allclose(np.linalg.norm(cm.N, axis=1), 1.0, atol=1e-6)


def test04_a_new_isovalue_reuses_the_interface():
    # The filter reports the interface as the first half of its progress (after the
    # pipeline's 0 at the start): a new isovalue on the same input reports none of it.
    seen = []
    contour = peers_vtk.AMRContour(split_sphere(), "f", "shared", progress=seen.append)
    first = contour.mesh(ISO)
    assert any(0.0 < f < 0.5 for f in seen), seen
    seen.clear()
    second = contour.mesh(1.1 * ISO)
    assert seen and not any(0.0 < f < 0.5 for f in seen), seen
    r = np.linalg.norm(second.V - CENTRE, axis=1)
    assert abs(np.median(r) - 1.1 * ISO) < 0.25 / BASE
    assert second.open_edges == 0 and len(second.F) > len(first.F)


def test05_user_mistakes_raise_amr_error():
    vol = sphere(4)
    with pytest.raises(AMRError, match="no surface at isovalue 5"):
        peers_vtk.AMRContour(vol, "f", "shared").mesh(5.0)
    with pytest.raises(AMRError, match="rule must be one of"):
        peers_vtk.overlapping_amr(vol, "f", "nodal")
    with pytest.raises(AMRError, match="no field 'g'"):
        peers_vtk.overlapping_amr(vol, "g", "shared")


def test06_open_edges_of_a_square_and_a_closed_tetrahedron():
    square = np.array([[0, 1, 2], [0, 2, 3]])
    assert peers_vtk.open_edges(square).tolist() == [[0, 1], [0, 3], [1, 2], [2, 3]]
    tetrahedron = np.array([[0, 1, 2], [0, 3, 1], [1, 3, 2], [0, 2, 3]])
    assert len(peers_vtk.open_edges(tetrahedron)) == 0


@pytest.mark.parametrize("shared", [False, True])
def test07_routes_render_and_score_like_the_other_peers(scene_data_ready, shared):
    from mi_amr.evaluation import peers

    row = peers.vtk_amr_contour_route("analytic_sphere", shared_vertices=shared)
    assert set(row) == set(peers.ROW_KEYS)
    assert row["peer"] == ("vtk_amr_contour+shared_vertices" if shared else "vtk_amr_contour")
    assert 1.0 - row["missed"] - row["false"] > 0.97, row
    assert 0.0 < row["depth_mean"] < 1.0 and row["normal_mean"] < 10.0, row
    steps = row["time_detail"]
    assert {"build_amr", "contour", "mesh", "render", "warm_frame", "new_isovalue",
            "new_isovalue_frame", "data_shared"} == set(steps)
    assert row["time_s"] == pytest.approx(steps["build_amr"] + steps["contour"] +
                                          steps["mesh"] + steps["render"])
    # Two grids, no seams: watertight either way.
    assert "triangles, 0 open edges off the domain's faces (+0 at them); new" in row["notes"], \
        row["notes"]
