"""Peers side by side: the tools a user would pick instead of mi_amr, run on the same data, with
the same camera, on the same machine and in the same run, scored against the exact reference hit
buffers of :mod:`mi_amr.reference` (``reference/NAME_hits.npz``).

* :func:`marching_cubes_route` -- the mesh route: scikit-image's ``marching_cubes`` on every grid
  of the volume (as a user does it patch by patch), one mesh, rendered by Mitsuba with the scene's
  own camera, light and other shapes.
* :func:`yt_volume_route` -- yt's volume renderer with a narrow Gaussian transfer function
  around the isovalue, the camera of the Mitsuba scene rebuilt as a yt perspective camera.
* :func:`vtk_amr_contour_route` -- VTK's watertight contour of overlapping AMR
  (``vtkAMRContourFilter``, VTK >= 9.7; :mod:`mi_amr.evaluation.peers_vtk`), the vertex values
  per grid as VTK's own test makes them, or shared by all grids of a level; the welded mesh
  rendered by Mitsuba like the marching-cubes one.
* :func:`mi_amr_route` -- our own ``exact`` method, loaded and rendered afresh in the same run,
  so the table compares like with like.

:func:`run_peers` runs all of them per scene and :func:`peers_table` prints the rows. The peers
are optional extras (``pip install 'mi_amr[peers]'``); a missing one becomes a row that says so.

Every route returns one row (a dict):

==============  ==========================================================================
key             meaning
==============  ==========================================================================
scene           reference scene name (:data:`mi_amr.reference.SCENES`)
peer            ``mi_amr exact`` or a key of :data:`ROUTES` (``marching_cubes``,
                ``marching_cubes+ghost``, ``yt_volume``, ``yt_volume+ghost``,
                ``vtk_amr_contour``, ``vtk_amr_contour+shared_vertices``)
time_s          time to image in seconds (what the route must redo for new data or a new
                isovalue; the shared reading of the data is excluded for the peers, see
                ``time_detail``)
time_detail     ``{step: seconds}``: the steps that add up to ``time_s``, then
                ``warm_frame`` (a second frame of the same image, not in ``time_s``),
                for VTK ``new_isovalue`` and ``new_isovalue_frame`` (a new isovalue's
                contour and mesh, then its frame; not in ``time_s``) and ``data_shared``
                (reading the file and deriving the field, which every route needs; in
                ``time_s`` only for mi_amr, whose load includes it)
missed, false   fractions of pixels: reference hit and route none; route hit, reference none
depth_mean/p99  depth error where both hit, in finest cells (NaN where a route has no depth)
normal_mean     normal error where both hit, degrees, up to sign (NaN without normals)
cracks          fraction of pixels that are gaps (reference hits, route does not or sees
                through to a surface behind, see :data:`SEE_THROUGH_CELLS`) within
                :data:`CRACK_CELLS` finest cells of a coarse/fine level boundary (NaN for yt)
notes           how the route was set up, gap counts, anything a reader needs
==============  ==========================================================================

All renders and hit buffers are at the references' resolution (:data:`mi_amr.reference.RESOLUTION`)
with one ray per pixel centre. Timings are wall clock; Mitsuba frames end with ``dr.eval`` and
``dr.sync_thread``.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from mi_amr.evaluation import peers_vtk
from mi_amr.evaluation import references as ref
from mi_amr.core.boxes import intersection_volume, overlap_pairs
from mi_amr.errors import AMRError
from mi_amr.kernels import snapshot
from mi_amr.evaluation.references import pixel_rays

INSTALL_HINT = "pip install 'mi_amr[peers]'"
# The peers run_peers() runs unless told otherwise; "yt_volume+ghost" (yt with ghost zones) is
# left out as it takes minutes on sphere_wake and changes little. The VTK routes take about
# 8 minutes each on sphere_wake (the filter's interface between levels).
PEERS = ("marching_cubes", "marching_cubes+ghost", "yt_volume", "vtk_amr_contour",
         "vtk_amr_contour+shared_vertices")
# Each route is called with the scene's name and whether to print progress.
ROUTES = {"marching_cubes": lambda name, progress: marching_cubes_route(name),
          "marching_cubes+ghost": lambda name, progress: marching_cubes_route(name,
                                                                              ghost_cells=True),
          "yt_volume": lambda name, progress: yt_volume_route(name),
          "yt_volume+ghost": lambda name, progress: yt_volume_route(name, ghost_zones=True),
          "vtk_amr_contour": lambda name, progress: vtk_amr_contour_route(name,
                                                                          progress=progress),
          "vtk_amr_contour+shared_vertices": lambda name, progress: vtk_amr_contour_route(
              name, shared_vertices=True, progress=progress)}
# A gap is a pixel where the reference hits and the route does not, or where the route's first
# hit lies more than SEE_THROUGH_CELLS finest cells behind the reference's (the ray went through
# a gap in the surface and met the surface behind it). A gap is a crack when the reference hit
# point lies within CRACK_CELLS finest cells (Chebyshev distance) of a face between two levels.
CRACK_CELLS = 2.0
SEE_THROUGH_CELLS = 4.0
# yt: Gaussian opacity band of standard deviation YT_SIGMA * (data range) around the isovalue
# (the course report's band width, relative), tabulated with YT_BINS bins so the band spans
# several bins, and opaque enough that a ray crossing it head-on where |grad f| is the median
# near the isosurface gathers optical depth YT_DEPTH.
YT_SIGMA = 0.004
YT_BINS = 1024
YT_DEPTH = 4.0
# VTK: the new isovalue is this factor times the scene's (as bench's frame timings), and the
# filter's progress is printed at most every PROGRESS_SECONDS.
NEW_ISO_FACTOR = 1.1
PROGRESS_SECONDS = 20.0
ROW_KEYS = ("scene", "peer", "time_s", "time_detail", "missed", "false", "depth_mean",
            "depth_p99", "normal_mean", "cracks", "notes")


# ---------------------------------------------------------------------- driver and table

def run_peers(scenes=("sphere_wake", "plt_eb_3d"), *, peers=PEERS, ours: bool = True,
              variant: str = "llvm_ad_rgb", progress: bool = True) -> list:
    """Rows of :func:`mi_amr_route` (when ``ours``) and of each peer in ``peers``, per scene.

    Scenes whose data is not here are left out (with a message). A peer whose package is
    missing gives a row with ``notes = "skipped: pip install ..."`` and NaN numbers.
    """
    import mitsuba as mi

    from mi_amr.workflows import project

    unknown = [n for n in scenes if n not in ref.SCENES]
    if unknown:
        raise AMRError(f"run_peers(): unknown scene(s) {unknown}; choose from {list(ref.SCENES)}")
    bad = [p for p in peers if p not in ROUTES]
    if bad:
        raise AMRError(f"run_peers(): unknown peer(s) {bad}; choose from {list(ROUTES)}")
    mi.set_variant(variant)
    from mi_amr.plugin.integrator import register

    register()
    project.ensure_scene_data(verbose=progress)
    rows = []
    for name in scenes:
        if not ref.available(name):
            print(f"skipping {name}: its data is not here")
            continue
        # Ours first: its "scene load" must not find the volume prepared by a peer.
        todo = (["mi_amr exact"] if ours else []) + list(peers)
        for peer in todo:
            if progress:
                print(f"{name}: {peer} ...", flush=True)
            try:
                row = mi_amr_route(name) if peer == "mi_amr exact" else \
                    ROUTES[peer](name, progress)
            except ImportError as e:
                row = skipped_row(name, peer, e)
            rows.append(row)
            if progress:
                print(f"  {row['time_s']:.2f} s, missed {_pct(row['missed'])}, "
                      f"false {_pct(row['false'])}, cracks {_pct(row['cracks'])}", flush=True)
    return rows


def skipped_row(scene: str, peer: str, error: ImportError) -> dict:
    """The row of a peer whose package could not be imported."""
    missing = getattr(error, "name", None) or str(error)
    return _row(scene, peer, math.nan, {}, None,
                notes=f"skipped: {INSTALL_HINT} (cannot import {missing})")


def peers_table(rows, notes: bool = True) -> str:
    """Markdown table of :func:`run_peers` rows (times in s, rates in % of pixels); without
    ``notes``, the short form the README shows (no per-step times or notes)."""
    head = ("| scene | peer | time to image (s) | " + ("steps (s) | " if notes else "") +
            "missed (%) | false (%) | depth mean (cells) | depth p99 (cells) | normal (deg) | "
            "cracks (%) |" + (" notes |" if notes else ""))
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        steps = ", ".join(f"{k} {v:.2f}" for k, v in r["time_detail"].items())
        lines.append(f"| {r['scene']} | {r['peer']} | {_num(r['time_s'], '.2f')} | " +
                     (f"{steps} | " if notes else "") +
                     f"{_pct(r['missed'])} | {_pct(r['false'])} | "
                     f"{_num(r['depth_mean'], '.2e')} | {_num(r['depth_p99'], '.2e')} | "
                     f"{_num(r['normal_mean'], '.2f')} | {_pct(r['cracks'])} |" +
                     (f" {r['notes'].replace('|', '/')} |" if notes else ""))
    return "\n".join(lines)


def _num(x, fmt) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def _pct(x) -> str:
    return _num(None if x is None else 100.0 * x, ".3f")


def _row(scene, peer, time_s, detail, score, *, cracks=math.nan, notes="") -> dict:
    nan = math.nan
    s = score or {}
    return {"scene": scene, "peer": peer, "time_s": time_s, "time_detail": detail,
            "missed": s.get("missed", nan), "false": s.get("false", nan),
            "depth_mean": s.get("depth_mean", nan), "depth_p99": s.get("depth_p99", nan),
            "normal_mean": s.get("normal_mean", nan), "cracks": cracks, "notes": notes}


# ---------------------------------------------------------------------- our own method

@snapshot.using("off")   # a fresh load: none read back from a snapshot
def mi_amr_route(scene_name: str) -> dict:
    """mi_amr's ``exact`` method, from nothing: scene load (reading, deriving, kd-tree, device
    arrays) plus the first frame is the time to image; the warm frame is reported beside it."""
    import mitsuba as mi

    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import load_scene

    w, h = ref.RESOLUTION
    # A fresh load: forget volumes an earlier scene in this process has prepared.
    register().clear()
    t0 = time.perf_counter()
    scene = load_scene(ref.scene_path(scene_name), resx=w, resy=h, spp=1, method="exact",
                       reconstruction="basis")
    load = time.perf_counter() - t0
    first = _timed_render(mi, scene)
    warm = _timed_render(mi, scene)
    hits = ref.hit_buffers(scene)
    shared = _data_seconds(scene)
    detail = {"load": load, "first_frame": first, "warm_frame": warm, "data_shared": shared}
    # Like the peers' times, leave out reading and deriving the field, which every route shares.
    return _scored_row(scene_name, "mi_amr exact", load - shared + first, detail, hits, scene,
                       notes="exact/basis, 1 spp; time to image = load (kd-tree, device arrays) "
                             "+ first frame, without data_shared; the first frame compiles "
                             "unless Dr.Jit's kernel cache is warm")


def _timed_render(mi, scene, spp: int = 1) -> float:
    import drjit as dr

    t0 = time.perf_counter()
    img = mi.render(scene, spp=spp)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0


def _data_seconds(scene) -> float:
    """Seconds to read the scene's field (and colour field) from disk and derive them: the work
    every route shares, timed here on its own."""
    from mi_amr.core.derive import DERIVED_FIELDS, derive
    from mi_amr.kernels.prepared import fields_to_read
    from mi_amr.readers import available_fields, load

    integ = scene.integrator()
    prep = integ.prep
    path = prep.volume.source
    t0 = time.perf_counter()
    vol = load(path, fields=fields_to_read(prep.field, integ.opt.color_field,
                                           available_fields(path)))
    missing = [f for f in dict.fromkeys([prep.field, integ.opt.color_field])
               if f is not None and f not in vol.field_names and f in DERIVED_FIELDS]
    if missing:
        derive(vol, *missing)
    return time.perf_counter() - t0


# ---------------------------------------------------------------------- shared helpers

def _load_reference_scene(scene_name: str):
    """The scene at the references' resolution, 1 spp, and its reference hit buffers."""
    from mi_amr.plugin.scene import load_scene

    w, h = ref.RESOLUTION
    scene = load_scene(ref.scene_path(scene_name), resx=w, resy=h, spp=1, method="exact",
                       reconstruction="basis")
    ref_hits = ref.HitBuffers.load(ref.reference_path(scene_name, "hits"))
    return scene, ref_hits


@dataclass
class RouteScene:
    """What a peer route reads off the reference scene: the scene (references' resolution,
    1 spp), its reference hit buffers, the integrator, its volume, field and first isovalue
    (field units), and ``to_world`` (4x4, volume space to world)."""

    scene: object
    ref_hits: object
    integ: object
    vol: object
    field: str
    iso: float
    to_world: np.ndarray


def route_scene(scene_name: str) -> RouteScene:
    """The reference scene ``scene_name`` and what the routes read off it."""
    scene, ref_hits = _load_reference_scene(scene_name)
    integ = scene.integrator()
    vol = field_volume(integ)
    return RouteScene(scene=scene, ref_hits=ref_hits, integ=integ, vol=vol,
                       field=integ.prep.field, iso=float(integ.opt.isovalues[0]),
                       to_world=matrix(integ.frame.to_scene))


def field_volume(integ):
    """The volume the integrator ``integ`` shows, holding its field and colour field: its
    preparation's where that keeps them, else its file read again with them (derived where
    they are: a scene of the basis blend keeps the brick pools alone)."""
    from mi_amr.plugin.datafields import load_with_fields

    prep = integ.prep
    if prep.keeps_fields:
        return prep.volume
    names = [f for f in dict.fromkeys([prep.field, prep.color_field]) if f is not None]
    return load_with_fields(prep.volume.source, names,
                            allow_nonfinite=prep.volume.allow_nonfinite)[0]


def _ray_arrays(ray, h, w):
    o = np.stack([ray.o.x.numpy(), ray.o.y.numpy(), ray.o.z.numpy()], axis=-1)
    d = np.stack([ray.d.x.numpy(), ray.d.y.numpy(), ray.d.z.numpy()], axis=-1)
    return o.reshape(h, w, 3).astype(np.float64), d.reshape(h, w, 3).astype(np.float64)


def _occluder_t(scene, ray):
    """Distance to the scene's own shapes along each pixel ray (inf where none)."""
    import drjit as dr

    si = scene.ray_intersect(ray)
    return np.asarray(dr.select(si.is_valid(), si.t, dr.inf).numpy(), dtype=np.float64)


def matrix(transform) -> np.ndarray:
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4)


def _to_volume(points, to_world) -> np.ndarray:
    inv = np.linalg.inv(to_world)
    return points @ inv[:3, :3].T + inv[:3, 3]


def near_level_boundary(volume, points, radius: float) -> np.ndarray:
    """True where a point (``(N, 3)``, volume space) lies within ``radius`` (Chebyshev distance,
    volume units) of a face between two levels: the cube of half-side ``radius`` around it holds
    cells of level ``l`` and cells of level ``l - 1`` not refined to ``l``, for some ``l``."""
    return boundaries_near(volume, points, radius)["level"]


def boundaries_near(volume, points, radius: float) -> dict:
    """Which kinds of boundary lie within ``radius`` (Chebyshev distance, volume units) of each
    point (``(N, 3)``, volume space): boolean arrays ``level`` (a face between two levels, see
    :func:`near_level_boundary`), ``seam`` (a face between two grids of the finest level there)
    and ``domain`` (the outside of the level-0 grids).

    Grids of one level do not overlap and finer levels nest in coarser ones, so the volume of
    the cube around a point inside level ``l`` is the sum of its overlaps with the level's
    grids."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    L, n = volume.num_levels, len(points)
    lo, hi = volume.grid_boxes()
    blo, bhi = points - radius, points + radius
    a, b = overlap_pairs(blo, bhi, lo, hi)
    levels = volume.levels[b]
    inside = np.zeros((L, n))
    np.add.at(inside, (levels, a), intersection_volume(blo[a], bhi[a], lo[b], hi[b]))
    grids = np.zeros((L, n), dtype=np.int64)
    np.add.at(grids, (levels, a), 1)
    eps = 1e-9 * (2.0 * radius) ** 3
    present = inside > eps
    finest = L - 1 - np.argmax(present[::-1], axis=0)
    return {"level": np.any(present[1:] & (inside[:-1] - inside[1:] > eps), axis=0),
            "seam": present.any(axis=0) & (grids[finest, np.arange(n)] > 1),
            "domain": inside[0] < (2.0 * radius) ** 3 - eps}


def _gaps(volume, to_world, ref_hits, hits, o, d, finest: float) -> dict:
    """Gap pixels of ``hits`` (a :class:`~mi_amr.reference.HitBuffers`; see
    :data:`SEE_THROUGH_CELLS`): counts ``missed`` and ``see_through``; of the gaps, ``near``
    (within :data:`CRACK_CELLS` finest cells of a level boundary) and ``near1`` (within 1),
    and, not near a level boundary, ``seam`` (near a seam between grids of one level) and
    ``domain`` (near the domain's faces); ``base_level`` and ``base_seam``: the same shares
    among all reference hits, to read the counts against; ``depth_mean_solid``: the mean depth
    error where both hit, see-through pixels left out."""
    missed = ref_hits.hit & ~hits.hit
    with np.errstate(invalid="ignore"):
        behind = ref_hits.hit & hits.hit & (hits.t - ref_hits.t > SEE_THROUGH_CELLS * ref_hits.cell)
    gaps = missed | behind
    p = o[ref_hits.hit] + ref_hits.t[ref_hits.hit][:, None] * d[ref_hits.hit]
    local = _to_volume(p, to_world)
    base = boundaries_near(volume, local, CRACK_CELLS * finest)
    at_gap = gaps[ref_hits.hit]
    kinds = {k: v[at_gap] for k, v in base.items()}
    near1 = near_level_boundary(volume, local[at_gap], 1.0 * finest)
    other = ~kinds["level"]
    solid = ref_hits.hit & hits.hit & ~behind
    err = np.abs(hits.t[solid] - ref_hits.t[solid]) / ref_hits.cell
    return {"missed": int(missed.sum()), "see_through": int(behind.sum()),
            "near": int(kinds["level"].sum()), "near1": int(near1.sum()),
            "seam": int((other & kinds["seam"]).sum()),
            "domain": int((other & ~kinds["seam"] & kinds["domain"]).sum()),
            "base_level": float(base["level"].mean()) if len(local) else math.nan,
            "base_seam": float((base["seam"] & ~base["level"]).mean()) if len(local) else math.nan,
            "depth_mean_solid": float(err.mean()) if err.size else math.nan}


def _gap_note(g) -> str:
    text = (f"gaps {g['missed'] + g['see_through']} px ({g['missed']} missed, "
            f"{g['see_through']} see-through): {g['near']} within {CRACK_CELLS:g} finest cells "
            f"of a coarse/fine face ({g['near1']} within 1), else {g['seam']} near a seam "
            f"within a level, {g['domain']} near the domain's faces (of all reference hits "
            f"{100 * g['base_level']:.1f}% lie near a coarse/fine face, "
            f"{100 * g['base_seam']:.1f}% near a seam)")
    if g["see_through"] and math.isfinite(g["depth_mean_solid"]):
        text += f"; depth mean without see-through px {g['depth_mean_solid']:.2e} cells"
    return text


def _finest_spacing(volume) -> float:
    return float(volume.level_spacing(volume.num_levels - 1).min())


def _scored_row(scene_name, peer, time_s, detail, hits, scene, *, notes=""):
    """Score ``hits`` (a :class:`~mi_amr.reference.HitBuffers`) against the reference and count
    the gaps near level boundaries."""
    ref_hits = ref.HitBuffers.load(ref.reference_path(scene_name, "hits"))
    integ = scene.integrator()
    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    o, d = _ray_arrays(pixel_rays(sensor), h, w)
    vol = integ.prep.volume
    gaps = _gaps(vol, matrix(integ.frame.to_scene), ref_hits, hits, o, d, _finest_spacing(vol))
    scored = ref.score(hits, ref_hits).as_dict()
    return _row(scene_name, peer, time_s, detail, scored, cracks=gaps["near"] / hits.hit.size,
                notes=f"{notes}; {_gap_note(gaps)}" if notes else _gap_note(gaps))


@contextmanager
def quiet_yt():
    """yt logs every step at INFO; keep the run's output readable and restore the level."""
    from yt.utilities.logger import ytLogger

    old = ytLogger.level
    ytLogger.setLevel(40)
    try:
        yield
    finally:
        ytLogger.setLevel(old)


# ---------------------------------------------------------------------- marching cubes

def marching_cubes_route(scene_name: str, *, ghost_cells: bool = False) -> dict:
    """The mesh route, as a careful user builds it patch by patch.

    For every grid: scikit-image ``marching_cubes`` on the grid's cell-centred array of the
    scene's field at the scene's (first) isovalue, with the grid spacing and the offset
    ``origin + spacing / 2`` (the cell centres are its nodes). Cells covered by finer grids:
    a triangle is dropped when its centroid lies in a covered cell of its grid (the grid's
    ``leaf_mask``), so each region of space is meshed by the finest grid there.

    ``ghost_cells=False``: each grid alone, so the mesh stops half a cell inside every grid
    face -- gaps at seams between grids of one level as well as at level boundaries.
    ``ghost_cells=True``: each grid padded by one layer of ghost cells (the same level's
    neighbours where they exist, else trilinear from the coarser level, else the edge value),
    and a triangle is kept only by the grid whose box holds its centroid; seams within a level
    close, the mismatch at level boundaries stays.

    The pieces are joined into one mesh (vertex normals from marching cubes; vertex colours
    from the colour field), placed with the integrator's ``to_world`` and rendered by Mitsuba's
    ``direct`` integrator with the scene's camera, emitters and other shapes. Time to image =
    marching cubes + mesh building (culling, colours, Mitsuba mesh and scene) + first render.
    """
    import mitsuba as mi
    import scipy.ndimage  # noqa: F401  (imported before the clock starts; colours use it)
    from skimage.measure import marching_cubes

    rs = route_scene(scene_name)
    vol = rs.vol

    # ---- Marching cubes per grid.
    t0 = time.perf_counter()
    arrays = _padded_arrays(vol, rs.field) if ghost_cells else \
        [np.asarray(g.fields[rs.field]) for g in vol.grids]
    t_ghost = time.perf_counter() - t0
    t0 = time.perf_counter()
    pieces = grid_pieces(marching_cubes, vol, arrays, rs.iso, ghost_cells)
    t_mc = time.perf_counter() - t0

    # ---- Mesh building: drop covered triangles, join, colour, place, hand to Mitsuba.
    t0 = time.perf_counter()
    mesh, mesh_scene, triangles = build_mesh_scene(mi, rs, pieces)
    t_mesh = time.perf_counter() - t0

    first = _timed_render(mi, mesh_scene)
    warm = _timed_render(mi, mesh_scene)
    hits = _mesh_hit_buffers(mi, mesh_scene, mesh)

    detail = {"ghost_fill": t_ghost} if ghost_cells else {}
    detail.update({"marching_cubes": t_mc, "mesh": t_mesh, "render": first, "warm_frame": warm,
                   "data_shared": _data_seconds(rs.scene)})
    peer = "marching_cubes+ghost" if ghost_cells else "marching_cubes"
    notes = (f"skimage lewiner per grid ({len(pieces)} of {len(vol.grids)} grids cut), "
             f"{triangles:,} triangles; covered cells: triangle dropped if its centroid is in a "
             f"covered cell; {'1 ghost layer per grid' if ghost_cells else 'no ghost cells'}; "
             f"Mitsuba 'direct', 1 spp")
    return _scored_row(scene_name, peer, t_ghost + t_mc + t_mesh + first, detail, hits,
                       rs.scene, notes=notes)


def grid_pieces(marching_cubes, vol, arrays, iso, ghost_cells) -> list:
    """``marching_cubes`` (scikit-image's) on each grid's cell-centred array in ``arrays``
    (padded by one ghost layer when ``ghost_cells``) at ``iso``: ``(grid index, vertices,
    faces, normals)`` per grid the isovalue cuts, vertices in volume space (the cell centres
    are the nodes)."""
    pieces = []
    # Index 0 of a padded array is the ghost cell centred half a cell outside the grid.
    first_centre = -0.5 if ghost_cells else 0.5
    for gi, (g, arr) in enumerate(zip(vol.grids, arrays)):
        if min(arr.shape) < 2 or not (arr.min() <= iso <= arr.max()):
            continue
        h = np.asarray(g.spacing)
        verts, faces, normals, _ = marching_cubes(arr, level=iso, spacing=tuple(h))
        pieces.append((gi, verts + g.lo + first_centre * h, faces, normals))
    return pieces


def build_mesh_scene(mi, rs, pieces):
    """The per-grid pieces joined into one mesh (:func:`_join_pieces`) and put in a scene
    (:func:`_placed_mesh_scene`). Returns ``(mesh, scene, triangle count)``."""
    V, F, N, C = _join_pieces(rs.vol, pieces, rs.integ)
    mesh, mesh_scene = _placed_mesh_scene(mi, rs, V, F, N, C)
    return mesh, mesh_scene, len(F)


def _placed_mesh_scene(mi, rs, V, F, N, C):
    """A mesh (vertices ``V``, normals ``N`` in volume space, triangles ``F``, linear RGB
    vertex colours ``C``) placed in the scene's world space with the integrator's ``to_world``
    (normals by the inverse transpose), made a Mitsuba mesh and put in a scene with
    ``rs.scene``'s camera, emitters and other shapes. Returns ``(mesh, scene)``."""
    to_world = rs.to_world
    Vw = V @ to_world[:3, :3].T + to_world[:3, 3]
    Nw = N @ np.linalg.inv(to_world[:3, :3])
    Nw /= np.maximum(np.linalg.norm(Nw, axis=1, keepdims=True), 1e-30)
    mesh = _mitsuba_mesh(mi, Vw, F, Nw, C)
    return mesh, mi.load_dict(_scene_dict(rs.scene, mesh))


def _mesh_hit_buffers(mi, mesh_scene, mesh):
    """Hit buffers of ``mesh`` in ``mesh_scene``: one ray per pixel centre against the mesh
    and the scene's other shapes; a pixel is hit where its first intersection is the mesh
    (depth ``t`` in world units along the camera ray, inf elsewhere; world-space shading
    normals, NaN elsewhere)."""
    import drjit as dr

    sensor = mesh_scene.sensors()[0]
    w, h = sensor.film().crop_size()
    ray = pixel_rays(sensor)
    si = mesh_scene.ray_intersect(ray)
    on_iso = si.is_valid() & (si.shape == mi.ShapePtr(mesh))
    n = si.sh_frame.n
    dr.eval(on_iso, si.t, n)
    hit = on_iso.numpy().reshape(h, w).astype(bool)
    t = np.where(hit, si.t.numpy().reshape(h, w), np.inf)
    normal = np.stack([n.x.numpy(), n.y.numpy(), n.z.numpy()], axis=-1).reshape(h, w, 3)
    normal[~hit] = np.nan
    return ref.HitBuffers(t=t, hit=hit, normal=normal, cell=math.nan)


def _padded_arrays(vol, field) -> list:
    """Each grid's array with one layer of ghost cells: the same level's cell where a grid of
    the level has it, else trilinear from the next coarser level (cell centres as nodes), else
    (outside the domain) the nearest value of the grid itself."""
    from mi_amr.core.levels import cell_values, interpolate

    lo_idx, _ = vol.index_boxes()
    out = [np.pad(np.asarray(g.fields[field], dtype=np.float64), 1, mode="edge")
           for g in vol.grids]
    for level in range(vol.num_levels):
        ids = np.flatnonzero(vol.levels == level)
        shells = [_shell(out[i].shape) for i in ids]
        index = np.concatenate([lo_idx[i] - 1 + s for i, s in zip(ids, shells)])
        values, found = cell_values(vol, level, index, [field])
        values = values[0]
        if level > 0 and not found.all():
            h = vol.level_spacing(level)
            centres = vol.anchor + (index[~found] + 0.5) * h
            values[~found] = interpolate(vol, level - 1, centres, [field])[0]
        start = 0
        for i, s in zip(ids, shells):
            v = values[start:start + len(s)]
            start += len(s)
            ok = np.isfinite(v)
            out[i][s[ok, 0], s[ok, 1], s[ok, 2]] = v[ok]
    return out


def _shell(shape) -> np.ndarray:
    """Indices ``(M, 3)`` of the outermost layer of an array of ``shape``."""
    idx = np.indices(shape).reshape(3, -1).T
    n = np.asarray(shape)
    return idx[np.any((idx == 0) | (idx == n - 1), axis=1)]


def _join_pieces(vol, pieces, integ):
    """One mesh from the per-grid pieces: ``(V, F, N, C)`` in volume space (``C``: linear RGB
    per vertex). A triangle stays with the grid whose own cell holds its centroid when that
    cell is a leaf (not covered by a finer grid)."""
    from scipy.ndimage import map_coordinates

    from mi_amr.kernels.colormap import ColorMap

    opt = integ.opt
    cmap = None
    if opt.colormap is not None:
        cmap = ColorMap.parse(opt.colormap, vol.value_range(integ.prep.color_field))
    Vs, Fs, Ns, Cs = [], [], [], []
    offset = 0
    for gi, verts, faces, normals in pieces:
        g = vol.grids[gi]
        h = np.asarray(g.spacing)
        centroid = verts[faces].mean(axis=1)
        cell = np.floor((centroid - g.lo) / h).astype(np.int64)
        inside = np.all((cell >= 0) & (cell < np.asarray(g.shape)), axis=1)
        keep = inside.copy()
        c = cell[inside]
        keep[inside] = vol.leaf_mask(gi)[c[:, 0], c[:, 1], c[:, 2]]
        faces = faces[keep]
        if len(faces) == 0:
            continue
        used = np.unique(faces)
        remap = np.full(len(verts), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        verts, normals = verts[used], normals[used]
        if cmap is not None:
            colour = np.asarray(g.fields[integ.prep.color_field], dtype=np.float64)
            coords = ((verts - g.lo) / h - 0.5).T
            values = map_coordinates(colour, coords, order=1, mode="nearest")
            Cs.append(cmap.numpy(values, opt.color_range))
        else:
            Cs.append(np.tile(np.asarray(opt.iso_colors[0], dtype=np.float64), (len(verts), 1)))
        Vs.append(verts)
        Ns.append(normals)
        Fs.append(remap[faces] + offset)
        offset += len(verts)
    if not Vs:
        raise AMRError(f"marching cubes found no surface at isovalue {opt.isovalues[0]} in "
                       f"field '{integ.prep.field}'")
    return (np.concatenate(Vs), np.concatenate(Fs), np.concatenate(Ns), np.concatenate(Cs))


def _mitsuba_mesh(mi, V, F, N, C):
    """A Mitsuba triangle mesh with vertex normals and a two-sided diffuse BSDF reading vertex
    colours (an isosurface has no outside: the routes' normals point to lower field values,
    which faces away from the camera where the field grows outwards, as on the sphere)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
        "type": "mesh_attribute", "name": "vertex_color"}}})
    mesh = mi.Mesh("isosurface", len(V), len(F), props, has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(V.astype(np.float32).ravel())
    params["vertex_normals"] = mi.Float(N.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(F.astype(np.uint32).ravel())
    params.update()
    mesh.add_attribute("vertex_color", 3, mi.Float(C.astype(np.float32).ravel()))
    return mesh


def _scene_dict(scene, mesh) -> dict:
    """A scene with ``scene``'s camera, emitters and shapes plus ``mesh``."""
    d = {"type": "scene", "integrator": {"type": "direct"}, "sensor": scene.sensors()[0],
         "isosurface": mesh}
    for i, e in enumerate(scene.emitters()):
        d[f"emitter_{i}"] = e
    for i, s in enumerate(scene.shapes()):
        d[f"shape_{i}"] = s
    return d


# ---------------------------------------------------------------------- VTK's AMR contour

def vtk_amr_contour_route(scene_name: str, *, shared_vertices: bool = False,
                          progress: bool = False) -> dict:
    """VTK's watertight contour of overlapping AMR (``vtkAMRContourFilter``, VTK >= 9.7), the
    mesh rendered as the marching-cubes route's (see :mod:`mi_amr.evaluation.peers_vtk`).

    Input: the volume as a ``vtkOverlappingAMR`` (levels, ratios and grid boxes of the volume,
    blanked), the scene's field as vertex values: ``shared_vertices=False`` converts each grid's
    cells with ``vtkCellDataToPointData`` as VTK's own test of the filter does (grids of one
    level that meet disagree on their common face); ``True`` gives every vertex position one
    value per level, the mean of the level's cells around it across grids
    (:func:`~mi_amr.evaluation.peers_vtk.shared_vertex_values`).

    Output: the filter's pieces appended, welded (``vtkCleanPolyData``), given vertex normals
    (``vtkPolyDataNormals``, oriented to lower field values) and vertex colours from the colour
    field, placed with the integrator's ``to_world`` and rendered by Mitsuba's ``direct``
    integrator with the scene's camera, emitters and other shapes.

    Time to image = building the AMR (vertex values included) + first contour (the filter's
    interface between levels, then the contour) + mesh (welding, normals, colours, Mitsuba mesh
    and scene) + first render. ``new_isovalue``: a second contour at :data:`NEW_ISO_FACTOR`
    times the isovalue on the same filter and input (the interface is reused) plus the mesh
    rebuilt; ``new_isovalue_frame`` its first render. ``progress`` prints the filter's progress
    every :data:`PROGRESS_SECONDS` (its first update takes minutes on thousands of grids).
    ``notes`` gives the open edges of the welded mesh (cracks; the surface's cut at the
    domain's faces counted apart)."""
    import mitsuba as mi

    vtk = peers_vtk.require_vtk()
    rs = route_scene(scene_name)
    peer = "vtk_amr_contour+shared_vertices" if shared_vertices else "vtk_amr_contour"
    report = _progress_printer(peer) if progress else None

    # ---- The AMR and the filter, then the first contour and its mesh.
    t0 = time.perf_counter()
    contour = peers_vtk.AMRContour(rs.vol, rs.field, "shared" if shared_vertices else "per_grid",
                                   progress=report)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    first_mesh = contour.mesh(rs.iso)
    t_contour = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh, mesh_scene = _vtk_mesh_scene(mi, rs, first_mesh)
    t_mesh = time.perf_counter() - t0
    first = _timed_render(mi, mesh_scene)
    warm = _timed_render(mi, mesh_scene)
    hits = _mesh_hit_buffers(mi, mesh_scene, mesh)

    # ---- A new isovalue on the same filter and input.
    t0 = time.perf_counter()
    new_mesh = contour.mesh(rs.iso * NEW_ISO_FACTOR)
    _, new_scene = _vtk_mesh_scene(mi, rs, new_mesh)
    t_new = time.perf_counter() - t0
    new_frame = _timed_render(mi, new_scene)

    detail = {"build_amr": t_build, "contour": t_contour, "mesh": t_mesh, "render": first,
              "warm_frame": warm, "new_isovalue": t_new, "new_isovalue_frame": new_frame,
              "data_shared": _data_seconds(rs.scene)}
    return _scored_row(scene_name, peer, t_build + t_contour + t_mesh + first, detail, hits,
                       rs.scene, notes=_vtk_notes(vtk, first_mesh, new_mesh, shared_vertices))


def _vtk_mesh_scene(mi, rs, cm):
    """The Mitsuba mesh and scene of a :class:`~mi_amr.evaluation.peers_vtk.ContourMesh`."""
    colours = _vertex_colours(rs.vol, rs.integ, cm.V)
    return _placed_mesh_scene(mi, rs, cm.V, cm.F, cm.N, colours)


def _vertex_colours(vol, integ, V) -> np.ndarray:
    """Linear RGB per vertex (``V``: ``(N, 3)``, volume space): the colour field through the
    scene's colour map (trilinear at the finest level there), else the first iso colour."""
    from mi_amr.kernels.colormap import ColorMap

    opt = integ.opt
    if opt.colormap is None:
        return np.tile(np.asarray(opt.iso_colors[0], dtype=np.float64), (len(V), 1))
    field = integ.prep.color_field
    cmap = ColorMap.parse(opt.colormap, vol.value_range(field))
    values = peers_vtk.sample_field(vol, field, V)
    return cmap.numpy(np.nan_to_num(values, nan=vol.value_range(field)[0]), opt.color_range)


def _vtk_notes(vtk, first_mesh, new_mesh, shared_vertices) -> str:
    """The VTK routes' notes: VTK's version, the vertex rule, the meshes' sizes and open edges."""
    rule = ("one value per vertex position and level, the mean of the level's cells around "
            "it" if shared_vertices else "vtkCellDataToPointData per grid")

    def edges(cm):
        return (f"{cm.open_edges - cm.open_at_domain:,} open edges off the domain's faces "
                f"(+{cm.open_at_domain:,} at them)")

    return (f"vtkAMRContourFilter (VTK {vtk.vtkVersion.GetVTKVersion()}), vertex values: "
            f"{rule}; {first_mesh.pieces} pieces appended and welded (tolerance "
            f"{peers_vtk.WELD_CELLS:g} finest cells), {len(first_mesh.F):,} triangles, "
            f"{edges(first_mesh)}; new isovalue {new_mesh.iso:.4g}: {len(new_mesh.F):,} "
            f"triangles, {edges(new_mesh)}; vtkPolyDataNormals; Mitsuba 'direct', 1 spp")


def _progress_printer(label: str):
    """A progress callback (fraction in [0, 1]) that prints at most every
    :data:`PROGRESS_SECONDS` seconds."""
    start = time.perf_counter()
    last = [start]

    def report(fraction: float) -> None:
        now = time.perf_counter()
        if now - last[0] >= PROGRESS_SECONDS:
            last[0] = now
            print(f"  {label}: VTK reports {100.0 * fraction:.0f}% after {now - start:.0f} s",
                  flush=True)

    return report


# ---------------------------------------------------------------------- yt volume rendering

def yt_volume_route(scene_name: str, *, ghost_zones: bool = False) -> dict:
    """yt's volume renderer as yt users set it up.

    Data: ``yt.load_amr_grids`` with every grid's level, left/right edges, dimensions and the
    scene's field (volume space = yt's code length), level-0 grids spanning the domain.

    Transfer function: ``ColorTransferFunction((min, max), nbins=YT_BINS, grey_opacity=True)``
    over the field's range (linear, not log) with one Gaussian at the isovalue,
    ``add_gaussian(iso, w, [r, g, b, A])``; yt's ``w`` is ``2 sigma^2`` with
    ``sigma = YT_SIGMA * (max - min)``. yt's opacity per sample is ``dt * A`` with ``dt`` the
    sample's share of the whole ray, so ``A`` is set for optical depth ``YT_DEPTH`` across the
    band at the median ``|grad f|`` near the isosurface. ``grey_opacity`` makes the image's
    alpha the accumulated opacity; the hit mask is ``alpha > 0.5``.

    Camera: a yt perspective lens at the Mitsuba camera's position (taken to volume space),
    looking along its axis with its up vector as north, and ``width`` set so yt's rays (which
    run edge to edge over the image, ``linspace(-0.5, 0.5, N)``) pass through Mitsuba's pixel
    centres: ``width = 2 tan(fov/2) * (N - 1) / N`` at unit depth. yt's image is indexed
    ``[east, north]`` with east = north x forward (the viewer's left); it is flipped into
    Mitsuba's ``[row, column]``. The scene's other shapes (the ball) are given to yt as a depth
    buffer, as an opaque source would be. Needs a ``to_world`` that is a similarity (rotation,
    uniform scale, translation).

    Rays match Mitsuba's exactly for square images (``notes`` gives the largest angle between
    matched rays); yt makes the vertical pixel pitch follow the horizontal one, which differs a
    little from Mitsuba's for other aspect ratios. The Gaussian takes the first isovalue's
    ``iso_color``; a colour field is not mapped (the hit mask does not depend on it).

    ``ghost_zones=True`` turns on yt's ``use_ghost_zones`` (vertex values at grid faces from the
    neighbours, which removes seams, much slower); yt refuses it on a non-periodic domain, so
    ``ds.force_periodicity()`` is called, as yt's error message advises.

    Depth and normals are not available: NaN. Time to image = dataset + scene set-up + render
    (yt builds its kd-tree of bricks during the first render). No warm frame: most of the first
    render is the ray casting a second one repeats.
    """
    import yt
    from yt.visualization.volume_rendering.api import ColorTransferFunction
    from yt.visualization.volume_rendering.zbuffer_array import ZBuffer

    rs = route_scene(scene_name)
    view = _yt_view(rs)
    with quiet_yt():
        # ---- Dataset.
        t0 = time.perf_counter()
        ds = yt_dataset(yt, rs.vol, rs.field)
        if ghost_zones:
            # yt will not fill ghost zones past the faces of a non-periodic domain; its error
            # message advises this (the wrapped values touch only the outermost cells).
            ds.force_periodicity()
        t_ds = time.perf_counter() - t0

        # ---- Scene, transfer function, camera.
        t0 = time.perf_counter()
        setup = _yt_setup(yt, ColorTransferFunction, ZBuffer, ds, rs, view, ghost_zones)
        t_setup = time.perf_counter() - t0

        # ---- Render.
        t0 = time.perf_counter()
        image = np.asarray(setup.source.render(setup.cam, zbuffer=setup.zbuffer))
        t_render = time.perf_counter() - t0
    return _yt_row(scene_name, rs, view, setup, image, (t_ds, t_setup, t_render), ghost_zones)


@dataclass
class _YtView:
    """The Mitsuba view yt must reproduce: the uniform scale of ``to_world`` (world units per
    volume unit), the sensor and its image size ``w x h``, the pixel-centre rays (``o``, ``d``:
    ``(h, w, 3)``, world), the distance ``t_occ`` (world, inf where none) to the scene's other
    shapes along them, the field's range ``vmin``, ``vmax``, the Gaussian's ``sigma`` (field
    units) and the median ``|grad f|`` near the isosurface ``gmed`` (per volume unit)."""

    scale: float
    sensor: object
    w: int
    h: int
    o: np.ndarray
    d: np.ndarray
    t_occ: np.ndarray
    vmin: float
    vmax: float
    sigma: float
    gmed: float


def _yt_view(rs: RouteScene) -> _YtView:
    """Read :class:`_YtView` off the reference scene (AMRError unless ``to_world`` is a
    similarity)."""
    scale = _similarity_scale(rs.to_world)
    sensor = rs.scene.sensors()[0]
    w, h = sensor.film().crop_size()
    ray = pixel_rays(sensor)
    o, d = _ray_arrays(ray, h, w)
    t_occ = _occluder_t(rs.scene, ray).reshape(h, w)
    vmin, vmax = rs.vol.value_range(rs.field)
    sigma = YT_SIGMA * (vmax - vmin)
    gmed = _median_gradient(rs.vol, rs.field, rs.iso)
    return _YtView(scale=scale, sensor=sensor, w=w, h=h, o=o, d=d, t_occ=t_occ, vmin=vmin,
                   vmax=vmax, sigma=sigma, gmed=gmed)


@dataclass
class _YtSetup:
    """yt's scene ``sc`` ready to render: its volume ``source``, the camera ``cam``, the
    camera's ``frame`` (see :func:`yt_camera`), the Gaussian's ``height`` (opacity per unit of
    yt's ray parameter) and the depth buffer of the scene's other shapes."""

    sc: object
    source: object
    cam: object
    frame: dict
    height: float
    zbuffer: object


def _yt_setup(yt, ColorTransferFunction, ZBuffer, ds, rs, view, ghost_zones) -> _YtSetup:
    """yt's scene for dataset ``ds``: a perspective lens on the scene's field (linear, with
    ``ghost_zones`` or not), the Mitsuba camera rebuilt (:func:`yt_camera`), the Gaussian
    transfer function at the isovalue and the scene's other shapes as a depth buffer."""
    sc = yt.create_scene(ds, field=("stream", rs.field), lens_type="perspective")
    source = sc.get_source(0)
    source.log_field = False
    source.set_use_ghost_zones(ghost_zones)
    cam = sc.camera
    frame = yt_camera(ds, cam, view.sensor, rs.to_world, view.w, view.h)
    # Optical depth across the band (head on, gradient gmed): A * sigma sqrt(2 pi) / gmed
    # over the ray's parameter length |vp_dir|, which the sampler's dt is a share of.
    ray_len = float(np.median(np.linalg.norm(frame["vp_dir"], axis=-1)))
    height = YT_DEPTH * view.gmed * ray_len / (view.sigma * math.sqrt(2.0 * math.pi))
    tf = ColorTransferFunction((view.vmin, view.vmax), nbins=YT_BINS, grey_opacity=True)
    colour = list(rs.integ.opt.iso_colors[0])
    tf.add_gaussian(rs.iso, 2.0 * view.sigma ** 2, colour + [height])
    source.set_transfer_function(tf)
    # The scene's other shapes, as the depth at which each yt ray stops (its parameter
    # runs from 0 to 1 along vp_dir).
    t_occ_yt = frame["to_yt"](view.t_occ) / np.linalg.norm(frame["vp_dir"], axis=-1) / \
        view.scale
    zbuffer = ZBuffer(np.zeros((view.w, view.h, 4)),
                      np.where(np.isfinite(t_occ_yt), t_occ_yt, 1.0))
    return _YtSetup(sc=sc, source=source, cam=cam, frame=frame, height=height, zbuffer=zbuffer)


def _yt_row(scene_name, rs, view, setup, image, seconds, ghost_zones) -> dict:
    """The route's row from yt's ``image`` (``(W, H, 4)``, yt's layout): hit where the
    accumulated opacity exceeds 0.5, scored against the reference hit buffers (no depth or
    normals: NaN) with its gaps counted; ``seconds``: dataset, set-up and render times."""
    frame = setup.frame
    alpha = frame["from_yt"](image[..., 3])
    hit = alpha > 0.5
    # No depth or normal from yt: placeholders for score(), whose depth and normal errors are
    # replaced by NaN below.
    hits = ref.HitBuffers(t=np.where(hit, np.nan, np.inf), hit=hit,
                          normal=np.zeros((view.h, view.w, 3)), cell=math.nan)
    scored = ref.score(hits, rs.ref_hits).as_dict()
    for k in ("depth_mean", "depth_p99", "normal_mean"):
        scored[k] = math.nan
    gaps = _gaps(rs.vol, rs.to_world, rs.ref_hits, hits, view.o, view.d,
                 _finest_spacing(rs.vol))
    t_ds, t_setup, t_render = seconds
    detail = {"dataset": t_ds, "setup": t_setup, "render": t_render,
              "data_shared": _data_seconds(rs.scene)}
    notes = (f"perspective lens, max ray angle error {frame['angle_error']:.1e} rad; Gaussian "
             f"sigma {view.sigma:.3g} ({YT_SIGMA:g} of range), {YT_BINS} bins, height "
             f"{setup.height:.3g} (median gradient norm {view.gmed:.3g}); "
             f"{setup.source.num_samples} samples/cell; ghost zones "
             f"{'on' if ghost_zones else 'off'}; hit = alpha > 0.5; {_gap_note(gaps)}")
    peer = "yt_volume+ghost" if ghost_zones else "yt_volume"
    return _row(scene_name, peer, t_ds + t_setup + t_render, detail, scored,
                cracks=math.nan, notes=notes)


def _similarity_scale(m) -> float:
    """The uniform scale of a similarity transform; AMRError for anything else."""
    a = m[:3, :3]
    gram = a.T @ a
    s2 = float(np.mean(np.diag(gram)))
    if not np.allclose(gram, s2 * np.eye(3), rtol=1e-5, atol=1e-6 * s2):
        raise AMRError("yt_volume_route(): the integrator's to_world must be a rotation, a "
                       "uniform scale and a translation; yt's camera cannot show a sheared or "
                       "unevenly scaled volume")
    return math.sqrt(s2)


def _median_gradient(vol, field, iso) -> float:
    """Median ``|grad f|`` (per volume unit) over the leaf cells next to the isosurface (the
    field crosses the isovalue between the cell and a neighbour of its grid); differences
    within each grid (central inside, one-sided at its faces)."""
    mags = []
    for i, g in enumerate(vol.grids):
        arr = np.asarray(g.fields[field], dtype=np.float64)
        if min(arr.shape) < 2:
            continue
        above = arr >= iso
        near = np.zeros(arr.shape, dtype=bool)
        for axis in range(3):
            change = np.diff(above, axis=axis)
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(None, -1), slice(1, None)
            near[tuple(lo)] |= change
            near[tuple(hi)] |= change
        near &= vol.leaf_mask(i)
        if not near.any():
            continue
        grad = np.gradient(arr, *g.spacing)
        mags.append(np.sqrt(sum(c[near] ** 2 for c in grad)))
    if not mags:
        raise AMRError(f"yt_volume_route(): field '{field}' does not cross the isovalue {iso}")
    return float(np.median(np.concatenate(mags)))


def yt_dataset(yt, vol, field):
    lo, hi = vol.bounds
    h0 = vol.level_spacing(0)
    if len(set(vol.ratios)) > 1:
        raise AMRError(f"yt_volume_route(): yt's load_amr_grids takes one refinement ratio; "
                       f"this volume has {vol.ratios}")
    grid_data = [{"left_edge": g.lo, "right_edge": g.hi, "level": g.level,
                  "dimensions": np.asarray(g.shape),
                  field: np.asarray(g.fields[field], dtype=np.float64)} for g in vol.grids]
    dims = np.round((hi - lo) / h0).astype(int)
    return yt.load_amr_grids(grid_data, dims, bbox=np.stack([lo, hi], axis=1),
                             refine_by=vol.ratios[0] if vol.ratios else 2,
                             periodicity=(False, False, False), length_unit=1.0)


def yt_camera(ds, cam, sensor, to_world, w, h) -> dict:
    """Set yt's perspective camera from Mitsuba's sensor; returns the ray directions yt will
    cast (``vp_dir``, ``[i, j]`` = east, north), the maps between yt's ``(W, H)`` images and
    Mitsuba's ``(H, W)`` ones and the largest angle between matched rays."""
    m = matrix(sensor.world_transform())
    inv = np.linalg.inv(to_world)
    # Mitsuba's camera frame: columns left, up, forward, origin.
    left, up, forward, origin = m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3]
    pos = inv[:3, :3] @ origin + inv[:3, 3]
    fwd = inv[:3, :3] @ forward
    north = inv[:3, :3] @ up
    fwd /= np.linalg.norm(fwd)
    north /= np.linalg.norm(north)
    ray = pixel_rays(sensor)
    _, d = _ray_arrays(ray, h, w)
    dl = d @ inv[:3, :3].T
    dl /= np.linalg.norm(dl, axis=-1, keepdims=True)
    # Pixel centres on the image plane at unit depth: first to last centre along a row.
    depth = dl @ fwd
    u = (dl @ (inv[:3, :3] @ left)) / depth / np.linalg.norm(inv[:3, :3] @ left)
    span = abs(u[h // 2, -1] - u[h // 2, 0])
    lo, hi = ds.domain_left_edge.d, ds.domain_right_edge.d
    dist = float(np.linalg.norm(0.5 * (lo + hi) - pos))
    cam.resolution = (w, h)
    cam.set_position(ds.arr(pos, "code_length"), north_vector=north)
    cam.focus = ds.arr(pos + dist * fwd, "code_length")
    cam.width = ds.arr([span * dist, span * dist * h / w, dist], "code_length")
    cam.switch_orientation(normal_vector=fwd, north_vector=north)
    east = np.asarray(cam.unit_vectors[0])
    yt_north = np.asarray(cam.unit_vectors[1])
    vp_dir = np.asarray(cam._get_sampler_params(_NoSource())["vp_dir"], dtype=np.float64)
    vp_dir = vp_dir.reshape(w, h, 3)
    # Mitsuba columns run to the viewer's right (-left), rows downwards (-up).
    flip_i = np.dot(east, inv[:3, :3] @ left) > 0
    flip_j = np.dot(yt_north, north) > 0

    def from_yt(img):
        out = np.asarray(img)
        out = out[::-1] if flip_i else out
        out = out[:, ::-1] if flip_j else out
        return np.swapaxes(out, 0, 1)

    def to_yt(img):
        out = np.swapaxes(np.asarray(img), 0, 1)
        out = out[::-1] if flip_i else out
        return out[:, ::-1] if flip_j else out

    yd = from_yt(vp_dir)
    yd = yd / np.linalg.norm(yd, axis=-1, keepdims=True)
    angle = float(np.max(np.arccos(np.clip(np.sum(yd * dl, axis=-1), -1.0, 1.0))))
    return {"vp_dir": vp_dir, "from_yt": from_yt, "to_yt": to_yt, "angle_error": angle}


class _NoSource:
    """Stands in for a render source when asking yt's lens for its rays (no depth buffer)."""

    zbuffer = None
