"""VTK's watertight contour of an overlapping AMR volume (``vtkAMRContourFilter``, VTK >= 9.7) on
an :class:`~mi_amr.core.volume.AMRVolume`, handed back as NumPy meshes: the machinery of the
``vtk_amr_contour`` peer routes of :mod:`mi_amr.evaluation.peers`, which time, render and score
them. Nothing here imports Mitsuba, and VTK is imported only when a contour is built.

The filter contours *point* data (values at the grid vertices); AMR data are cell-centred, so
the vertex values come from one of two rules (:data:`VERTEX_RULES`):

* ``"per_grid"`` -- ``vtkCellDataToPointData`` grid by grid, as VTK's own test of the filter
  does: a vertex value is the mean of the grid's own cells around the vertex. Two grids of one
  level that meet see different cells at their common face, so they disagree there and the
  contour cracks along the seam.
* ``"shared"`` -- one value per vertex position and level (:func:`shared_vertex_values`): the
  mean of all the level's cells around the position, whichever grid holds them (cells covered by
  a finer level included; at the domain's faces, the cells the level has). Every grid of a level
  sees the same value at a common vertex, so seams within a level close.

Between levels the filter builds the interface itself (``vtkAMRInterfaceFilter``: tetrahedra and
pyramids joining coarse and fine vertices, values from the finer grid where it has them); that
is what makes its contour watertight. The interface step scans the grids for every lookup and
takes minutes on thousands of grids, so :class:`AMRContour` keeps one filter on one input, and a
new isovalue reuses the interface (the filter caches it while its input is unchanged).

Positions are volume space (the grids' own world coordinates), as the marching-cubes route's
pieces, so a mesh goes through the integrator's ``to_world`` the same way.

Measured on VTK 9.7.1: ``vtkAMRUtilities.BlankCells`` must run on the filter's input (without
it the filter crashes); the output is a ``vtkPartitionedDataSet`` whose pieces are appended and
welded; points come out in float32, so the weld takes a tolerance (:data:`WELD_CELLS`); the
filter's normals differ from piece to piece where pieces meet, so the welded mesh gets its own
(:func:`_welded`, :func:`orient_normals`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_amr.core.levels import cell_values, interpolate, level_index
from mi_amr.errors import AMRError

VERTEX_RULES = ("per_grid", "shared")
# Points closer than this many finest cells are one point when the pieces are welded: float32
# positions of one vertex computed in two grids (different origins) differ by rounding only.
WELD_CELLS = 1e-4


def require_vtk():
    """The ``vtk`` module, ImportError unless it has ``vtkAMRContourFilter`` (VTK >= 9.7)."""
    import vtk
    from vtkmodules.vtkFiltersAMR import vtkAMRContourFilter  # noqa: F401  (VTK >= 9.7)

    return vtk


# ---------------------------------------------------------------------- input

def shared_vertex_values(vol, field: str) -> list:
    """Vertex values of every grid by the ``"shared"`` rule: per grid an array of shape
    ``(nx + 1, ny + 1, nz + 1)`` (node-centred, ``[i, j, k]`` = x, y, z, vertex ``i`` at
    ``origin + i * spacing``), the mean of the finite values of the level's cells that touch the
    vertex, read across all grids of the level (NaN where none is finite)."""
    lo_idx, _ = vol.index_boxes()
    # Each grid's cells with one layer of the level's neighbouring cells (NaN where the level
    # has none): the 2 x 2 x 2 cells around vertex v are padded cells v and v + 1 per axis.
    padded = [np.pad(np.asarray(g.fields[field], dtype=np.float64), 1, constant_values=np.nan)
              for g in vol.grids]
    for level in range(vol.num_levels):
        ids = np.flatnonzero(vol.levels == level)
        shells = [_shell(padded[i].shape) for i in ids]
        values, _ = cell_values(vol, level, np.concatenate(
            [lo_idx[i] - 1 + s for i, s in zip(ids, shells)]), [field])
        start = 0
        for i, s in zip(ids, shells):
            padded[i][s[:, 0], s[:, 1], s[:, 2]] = values[0, start:start + len(s)]
            start += len(s)
    return [_corner_means(p) for p in padded]


def _shell(shape) -> np.ndarray:
    """Indices ``(M, 3)`` of the outermost layer of an array of ``shape``."""
    idx = np.indices(shape).reshape(3, -1).T
    return idx[np.any((idx == 0) | (idx == np.asarray(shape) - 1), axis=1)]


def _corner_means(padded) -> np.ndarray:
    """Mean of the finite ones of the 8 padded cells around each vertex."""
    n = np.asarray(padded.shape) - 1
    total = np.zeros(tuple(n))
    count = np.zeros(tuple(n))
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                cells = padded[a:a + n[0], b:b + n[1], c:c + n[2]]
                ok = np.isfinite(cells)
                total += np.where(ok, cells, 0.0)
                count += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def overlapping_amr(vol, field: str, rule: str):
    """The volume as a ``vtkOverlappingAMR`` whose grids carry ``field`` as point data by
    ``rule`` (:data:`VERTEX_RULES`), blanked (``vtkAMRUtilities.BlankCells``) and ready for
    ``vtkAMRContourFilter``. Level spacings, refinement ratios and grid boxes are the volume's;
    the AMR origin is the volume's lattice anchor, so grid boxes are its index boxes."""
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkCommonDataModel import vtkAMRUtilities
    from vtkmodules.vtkFiltersCore import vtkCellDataToPointData

    if rule not in VERTEX_RULES:
        raise AMRError(f"overlapping_amr(): rule must be one of {list(VERTEX_RULES)}, "
                       f"got {rule!r}")
    if field not in vol.field_names:
        raise AMRError(f"overlapping_amr(): the volume has no field '{field}'; it has "
                       f"{list(vol.field_names)}")
    amr, grids = _amr_skeleton(vol)
    values = shared_vertex_values(vol, field) if rule == "shared" else \
        [np.asarray(g.fields[field], dtype=np.float64) for g in vol.grids]
    for ug, arr in zip(grids, values):
        # VTK's arrays run x fastest.
        data = numpy_support.numpy_to_vtk(np.ascontiguousarray(arr.ravel(order="F")), deep=True)
        data.SetName(field)
        (ug.GetPointData() if rule == "shared" else ug.GetCellData()).AddArray(data)
    if rule == "per_grid":
        to_points = vtkCellDataToPointData()
        to_points.SetInputData(amr)
        to_points.Update()
        amr = to_points.GetOutputDataObject(0)
    vtkAMRUtilities.BlankCells(amr)
    return amr


def _amr_skeleton(vol):
    """A ``vtkOverlappingAMR`` of the volume's levels and grids (no arrays yet) and its
    ``vtkUniformGrid`` per grid of the volume, in the volume's order."""
    from vtkmodules.vtkCommonDataModel import (vtkAMRBox, vtkOverlappingAMR, vtkStructuredData,
                                               vtkUniformGrid)

    levels = vol.levels
    amr = vtkOverlappingAMR()
    amr.Initialize([int((levels == level).sum()) for level in range(vol.num_levels)])
    amr.SetOrigin([float(x) for x in vol.anchor])
    amr.SetGridDescription(vtkStructuredData.VTK_STRUCTURED_XYZ_GRID)
    for level in range(vol.num_levels):
        # Spacing before the boxes, as VTK's own tests set them.
        amr.SetSpacing(level, [float(x) for x in vol.level_spacing(level)])
        if level + 1 < vol.num_levels:
            amr.SetRefinementRatio(level, int(vol.ratios[level]))
    lo_idx, hi_idx = vol.index_boxes()
    slot = [0] * vol.num_levels
    grids = []
    for gi, g in enumerate(vol.grids):
        block = slot[g.level]
        slot[g.level] += 1
        ug = vtkUniformGrid()
        ug.SetOrigin([float(x) for x in g.origin])
        ug.SetSpacing([float(x) for x in g.spacing])
        # Point dimensions: one more than cells.
        ug.SetDimensions([int(n) + 1 for n in g.shape])
        # Cell index boxes, inclusive upper corner.
        amr.SetAMRBox(g.level, block, vtkAMRBox([int(x) for x in lo_idx[gi]],
                                                [int(x) - 1 for x in hi_idx[gi]]))
        amr.SetDataSet(g.level, block, ug)
        grids.append(ug)
    return amr, grids


# ---------------------------------------------------------------------- contour

@dataclass
class ContourMesh:
    """One welded contour: vertices ``V`` ``(N, 3)`` (volume space), triangles ``F`` ``(M, 3)``,
    unit vertex normals ``N`` ``(N, 3)`` pointing to lower field values (as scikit-image's
    marching cubes), the isovalue (field units), the number of pieces the filter gave,
    ``open_edges`` (edges of one triangle only: cracks, and where the surface is cut by the
    domain's faces) and ``open_at_domain`` (those of them lying in a face of the domain)."""

    V: np.ndarray
    F: np.ndarray
    N: np.ndarray
    iso: float
    pieces: int
    open_edges: int
    open_at_domain: int


class AMRContour:
    """``vtkAMRContourFilter`` on one input (:func:`overlapping_amr`), kept so that a new
    isovalue reuses the filter's interface between levels.

    ``progress(fraction)``, when given, is called as the filter reports progress (fraction of the
    whole update; the interface is the first half when it is built).
    """

    def __init__(self, vol, field: str, rule: str, progress=None):
        from vtkmodules.vtkCommonDataModel import vtkDataObject
        from vtkmodules.vtkFiltersAMR import vtkAMRContourFilter

        self.vol, self.field, self.rule = vol, field, rule
        self.amr = overlapping_amr(vol, field, rule)
        self.filter = vtkAMRContourFilter()
        self.filter.SetInputData(self.amr)
        self.filter.SetInputArrayToProcess(0, 0, 0, vtkDataObject.FIELD_ASSOCIATION_POINTS, field)
        # Normals come from the welded mesh (_welded): the filter's differ from piece to piece.
        self.filter.ComputeNormalsOff()
        self.filter.ComputeScalarsOff()
        if progress is not None:
            self.filter.AddObserver("ProgressEvent",
                                    lambda obj, _event: progress(obj.GetProgress()))

    def mesh(self, iso: float) -> ContourMesh:
        """The contour at ``iso`` (field units), pieces appended, welded and oriented; AMRError
        when it is empty."""
        self.filter.SetValue(0, float(iso))
        self.filter.Update()
        output = self.filter.GetOutputDataObject(0)
        pieces = [output.GetPartition(i) for i in range(output.GetNumberOfPartitions())]
        pieces = [p for p in pieces if p is not None and p.GetNumberOfCells() > 0]
        if not pieces:
            raise AMRError(f"vtkAMRContourFilter found no surface at isovalue {iso} in field "
                           f"'{self.field}'")
        tolerance = WELD_CELLS * _finest_spacing(self.vol)
        V, F, N = _welded(pieces, tolerance)
        N = orient_normals(self.vol, self.field, V, N)
        edges = open_edges(F)
        lo, hi = self.vol.bounds
        on_face = (np.abs(V - lo) <= tolerance) | (np.abs(V - hi) <= tolerance)
        at_domain = np.any(on_face[edges[:, 0]] & on_face[edges[:, 1]], axis=1)
        return ContourMesh(V=V, F=F, N=N, iso=float(iso), pieces=len(pieces),
                           open_edges=len(edges), open_at_domain=int(at_domain.sum()))


def _welded(pieces, tolerance: float):
    """The pieces (``vtkPolyData`` of triangles) appended and welded (``vtkCleanPolyData``,
    absolute ``tolerance``, volume units), with vertex normals of the welded mesh
    (``vtkPolyDataNormals``: no splitting, windings made consistent, orientation left to
    :func:`orient_normals`): ``(V, F, N)`` as float64/int64 arrays."""
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkFiltersCore import vtkAppendPolyData, vtkCleanPolyData, vtkPolyDataNormals

    append = vtkAppendPolyData()
    for p in pieces:
        append.AddInputData(p)
    clean = vtkCleanPolyData()
    clean.SetInputConnection(append.GetOutputPort())
    clean.ToleranceIsAbsoluteOn()
    clean.SetAbsoluteTolerance(tolerance)
    normals = vtkPolyDataNormals()
    normals.SetInputConnection(clean.GetOutputPort())
    normals.SplittingOff()
    normals.ConsistencyOn()
    normals.ComputePointNormalsOn()
    normals.ComputeCellNormalsOff()
    normals.Update()
    mesh = normals.GetOutput()
    V = numpy_support.vtk_to_numpy(mesh.GetPoints().GetData()).astype(np.float64)
    polys = mesh.GetPolys()
    offsets = numpy_support.vtk_to_numpy(polys.GetOffsetsArray())
    conn = numpy_support.vtk_to_numpy(polys.GetConnectivityArray()).astype(np.int64)
    if np.any(np.diff(offsets) != 3):
        raise AMRError("vtkAMRContourFilter gave polygons that are not triangles")
    N = numpy_support.vtk_to_numpy(mesh.GetPointData().GetArray("Normals")).astype(np.float64)
    return V, conn.reshape(-1, 3), N


def open_edges(F) -> np.ndarray:
    """The edges ``(K, 2)`` (vertex indices, smaller first) of the triangles ``F`` ``(M, 3)``
    that belong to one triangle only."""
    F = np.asarray(F, dtype=np.int64)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


def orient_normals(vol, field: str, V, N) -> np.ndarray:
    """Unit normals ``N`` flipped where needed so that each points to lower values of ``field``:
    the field (:func:`sample_field`) is compared half a finest cell either side of the vertex
    along the normal. Zero normals (a vertex of degenerate triangles only) become the field's
    negative gradient there, by central differences of the same half cell."""
    V = np.asarray(V, dtype=np.float64)
    N = np.array(N, dtype=np.float64)
    delta = 0.5 * _finest_spacing(vol)
    missing = np.linalg.norm(N, axis=1) < 1e-12
    if missing.any():
        grad = np.stack([sample_field(vol, field, V[missing] + delta * e) -
                         sample_field(vol, field, V[missing] - delta * e)
                         for e in np.eye(3)], axis=1)
        N[missing] = -grad
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)
    ahead = sample_field(vol, field, V + delta * N) - sample_field(vol, field, V - delta * N)
    return np.where((ahead > 0)[:, None], -N, N)


def sample_field(vol, field: str, points) -> np.ndarray:
    """``field`` at world ``points`` ``(N, 3)`` (volume space): trilinear between the cell
    centres of the finest level that has the cell holding the point
    (:func:`mi_amr.core.levels.interpolate`; level 0 outside all grids)."""
    points = np.asarray(points, dtype=np.float64)
    out = np.full(len(points), np.nan)
    todo = np.arange(len(points))
    for level in reversed(range(vol.num_levels)):
        if level > 0:
            index = np.floor((points[todo] - vol.anchor) / vol.level_spacing(level))
            here = level_index(vol, level).find(index.astype(np.int64)) >= 0
        else:
            here = np.ones(len(todo), dtype=bool)
        at = todo[here]
        if len(at):
            out[at] = interpolate(vol, level, points[at], [field])[0]
        todo = todo[~here]
    return out


def _finest_spacing(vol) -> float:
    return float(vol.level_spacing(vol.num_levels - 1).min())
