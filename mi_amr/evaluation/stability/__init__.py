"""Stability where methods fail (issue 5): the inputs that break isosurface methods, and every
method measured on each.

:func:`run` builds each case, computes a dense float64 reference for its rays and traces them
with every method (``exact``, ``bisect``, ``adaptive``, ``uniform``) and, where the two differ,
both reconstructions. It returns one row per (case, method, reconstruction);
:func:`stability_table` turns the rows into a Markdown table, one row per case and one column
per method.

>>> from mi_amr.evaluation import stability
>>> rows = stability.run(quick=True)          # under a minute; quick=False: a few minutes
>>> print(stability.stability_table(rows))

Cases (keys of :data:`CASES`):

* ``thin_spike``, ``thin_sheet``: the one-cell spike at isovalue 0.75; a sheet
  ``exp(-(s / w)^2)`` (``s`` the distance to a tilted plane, ``w`` a finest cell) at isovalue
  0.85, a slab thinner than a step. Sampled methods step one finest cell.
* ``grazing``: rays just inside and just outside the tangent of the sphere's reconstructed
  surface (the tangent offset searched on the reference).
* ``tangent``, ``spike_maximum``: the isovalue at a local extremum: the tangent rays
  themselves (their minimum of the field is the isovalue), and rays through the spike's centre
  at isovalue 1.0, the field's maximum. A touching ray must be hit.
* ``level_boundary``: sphere and torus rays across the level boundary x = 0.5; cracks of the
  finest reconstruction (hits on the walls that close them, depths apart from basis).
  ``boundary_crossing``: the ramp's surface meeting the boundary plane exactly.
* ``planes``: rays along the axes exactly on cell faces, cell-centre planes, the level
  boundary and kd split planes; diagonal rays inside such planes. ``lower_faces``,
  ``upper_faces``: rays lying in the domain's faces.
* ``inside``: rays starting inside the volume and inside the surface; ``inside_ball``: a
  camera inside the ball of the sphere_wake scene (Mitsuba).
* ``out_of_range``: no hit, and a frame far faster than a normal one (Mitsuba).
* ``step_scale``: the sampling methods from 0.001 to 8 cells per step.
* ``nan``, ``nan_centre_lines``: a few NaN cells on the sphere's surface (missing data): rays
  through them, and rays along the lines through their centres, where the basis blend's
  weights vanish.
* ``many_grids``: the sphere on 10^4 level-1 grids of 2^3 cells.
* ``temporal``: a camera orbit around the torus (Mitsuba), each position rendered twice with
  different jitter (flicker), and the hit masks of consecutive positions compared.

Rows: ``case``, ``method``, ``reconstruction``, ``rays``, ``missed`` (rays the reference
crosses that get no hit, or only one beyond the first crossing), ``false`` (hits on rays the
reference does not cross, or before its first crossing), ``max_depth_error_cells`` (finest
cells, over the rays hit where expected), ``notes``, and ``expected`` (rays the reference
crosses) and ``metrics`` (case-specific numbers: cracks, timings, flicker). The Mitsuba cases
have no ray reference: their ``missed`` and ``false`` are ``None``.

The reference (:func:`dense_reference`) samples the reconstructed field every
:data:`REF_STEP` finest cells along each ray (finer where a case asks), brackets the first
change of side of the isovalue, searches sampled dips for crossings hidden between samples, and
bisects on float64 values. The values come from :class:`DenseField`, a vectorised float64 copy of
the sums computed by the slow twins :func:`~mi_amr.core.field64.basis_point_reference` and
:func:`~mi_amr.core.field64.finest_point_reference`, which are evaluated too at the crossings
and a sample of points (``metrics["twin_difference"]``). Rays come as float32 (what the kernels
see); a ray passing the isovalue within :data:`MARGIN` without clearly crossing it is
"touchy" and left out of the counts, except in the extremum cases, where a ray touching the
surface (within :data:`TANGENT`) must be hit.

All positions are the volume's world space; depth errors are in finest cells.

Modules, by job:

* :mod:`.rays` -- the dense float64 ray reference (:func:`dense_reference`, :class:`Reference`,
  :class:`DenseField`, :func:`f32`, :func:`unit`, :func:`box_interval`, the tolerances).
* :mod:`.scoring` -- a trace against the reference: :func:`score`, :func:`row`,
  :func:`measure`.
* :mod:`.cases_rays` -- the cases traced ray by ray, with their volumes and ray families.
* :mod:`.cases_mitsuba` -- the cases rendered with Mitsuba (``inside_ball``,
  ``out_of_range``, ``temporal``).
* :mod:`.suite` -- :data:`CASES`, :func:`run`, :func:`stability_table`, :func:`main`.

This package re-exports their public names.
"""

from mi_amr.evaluation.stability.rays import CENTRE, MARGIN, REF_STEP, TANGENT, DenseField, \
    Reference, bisect_crossings, box_interval, dense_reference, f32, minimise, unit
from mi_amr.evaluation.stability.scoring import EXACT_DEPTH_TOL, SAMPLED, measure, row, score, \
    trace_reference
from mi_amr.evaluation.stability.cases_rays import SHEET_ISO, SHEET_NORMAL, \
    case_boundary_crossing, case_domain_faces, case_grazing, case_inside, case_level_boundary, \
    case_many_grids, case_nan, case_nan_centre_lines, case_planes, case_spike_maximum, \
    case_step_scale, case_tangent, case_thin_sheet, case_thin_spike, crack_count, crack_lines, \
    face_rays, many_grids_volume, nan_volume, random_rays, sheet_volume, spike_centre, \
    tangent_offsets, torus_surface, wall_hits
from mi_amr.evaluation.stability.cases_mitsuba import case_inside_ball, case_out_of_range, \
    case_temporal
from mi_amr.evaluation.stability.suite import CASES, main, run, stability_table

__all__ = [
    "CASES", "CENTRE", "DenseField", "EXACT_DEPTH_TOL", "MARGIN", "REF_STEP", "Reference",
    "SAMPLED", "SHEET_ISO", "SHEET_NORMAL", "TANGENT", "bisect_crossings", "box_interval",
    "case_boundary_crossing", "case_domain_faces", "case_grazing", "case_inside",
    "case_inside_ball", "case_level_boundary", "case_many_grids", "case_nan",
    "case_nan_centre_lines", "case_out_of_range", "case_planes", "case_spike_maximum",
    "case_step_scale", "case_tangent", "case_temporal", "case_thin_sheet", "case_thin_spike",
    "crack_count", "crack_lines", "dense_reference", "f32", "face_rays", "main",
    "many_grids_volume", "measure", "minimise", "nan_volume", "random_rays", "row", "run",
    "score", "sheet_volume", "spike_centre", "stability_table", "tangent_offsets",
    "torus_surface", "trace_reference", "unit", "wall_hits",
]
