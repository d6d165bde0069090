"""Every tolerance in mi_amr, named once, each with the reason for its value.

Units: "cells" are finest cell widths of the volume (world units along a ray are found by
multiplying with :attr:`mi_amr.kernels.device.DeviceVolume.min_h`); "relative" means relative to
the magnitude of the quantity compared; "field" is the unit of the field's values.
"""

# ---------------------------------------------------------------------- the data model (host)

# cells of the grid's level: a grid corner this close to the lattice is on it. Float rounding
# of origins such as 0.1 * k must pass; a real misalignment of a quarter cell must not.
LATTICE = 1e-3
# relative: the spacings of one level's grids agree to this (float64 rounding of h / r^l).
SPACING_REL = 1e-6
# relative: the ratio between two levels' spacings is a whole number to this.
RATIO_REL = 1e-6
# weight: levels.interpolate(complete=True) needs the weights to sum to 1 within rounding.
COMPLETE_WEIGHT = 1e-9
# |det| of the 3x3 part of ``to_world`` below this: the transform cannot be inverted in float32.
SINGULAR_DET = 1e-12

# ---------------------------------------------------------------------- stepping along a ray

# cells: the smallest step along a ray -- well below a cell, so no piece of the field is
# stepped over, ...
STEP_EPS_CELLS = 1e-4
# relative to |t|: ... and large enough to move ``t`` in float32 (about 3.4 ulps).
STEP_EPS_REL = 4e-7
# relative: a ray lying in an upper face of the bounds is moved inside by about one ulp (kd
# points on a split plane belong to the upper side, which beyond the upper faces holds no data).
UPPER_FACE_REL = 1.2e-7
# steps: a position this close to a point of the step lattice counts as on it (so rounding
# does not take a step twice or skip one).
LATTICE_SNAP = 1e-4
# relative to a leaf's value range: the exact march's active box (the leaves that may hold a
# crossing, :meth:`DeviceVolume.active_box`) takes the float32 ranges this much wider, so a
# leaf whose rounded range only just misses an isovalue still lies inside it. It only makes the
# box larger (slower, never wrong).
ACTIVE_BOX_RANGE_REL = 1e-5
# cells: a translucent layer, or a shadow ray leaving an isosurface, starts this far past the
# crossing it came from, so the same crossing is not found again; far below any feature that
# the reconstruction can resolve.
LAYER_OFFSET_CELLS = 1e-3
# of the value change across a bracket: the sampling methods' next layer starts from a value
# this far past the isovalue crossed (on the far side), as its previous sample.
RESUME_REL = 1e-4
# cells: bisection (the ``bisect`` method) stops at this interval (course report, 3.6.2).
BISECT_TARGET = 0.005

# ---------------------------------------------------------------------- the exact method

# weight: where the blend's denominator (the sum of the cells' hat weights, 1 where every cell
# has a value) is below this, no cell has weight and the field is undefined. Next to missing
# values the weights can sum to much less than 1 while the field is still defined.
NO_WEIGHT = 1e-6
# weight (the full weight is 1): an end of a root's bracket with less has no weight at all but
# float32 rounding (seen up to 3e-6 where the valid cells' hats end next to missing data): there N - iso D is zero with D and has roots that are
# no crossing of the field. A real weight, however small (1.7e-4 beside a missing cell), is
# well above it.
MIN_COVER = 2e-5
# of a bracket: such an end is moved this far inside, where the weights tell the side; a
# crossing within that sliver next to missing data is not drawn.
COVER_NUDGE = 0.01
# relative to the size of the terms: a cubic's extremum this close to zero touches it (a
# tangent or grazing hit, an isovalue at a local extremum of the field).
TANGENT_REL = 2e-6
# relative to the size of the terms: counting crossings without finding them (shadow rays,
# mi_amr.kernels.transmit), a value of N - iso D this close to zero has no sure side. Where two
# cubic pieces meet, their values at the shared end differ by float32 rounding (1e-5 of the
# terms seen), which must not make a crossing there count two or three times.
SIGN_SURE_REL = 1e-4
# relative to the size of the terms: a volume piece's cheap value bound (the Bernstein
# coefficients' ratios, mi_amr.kernels.composite) is widened by this much for the float32
# rounding of those coefficients (a few 1e-7 of the terms), so that it never leaves out a
# value that the piece's exact range, itself rounded, holds.
VALUE_BOUND_REL = 1e-5
# a cubic's leading coefficient below this: its derivative is linear (float32 has no
# meaningful quadratic term left).
QUADRATIC_EPS = 1e-30

# ---------------------------------------------------------------------- compositing

# transmittance: a ray whose transmittance falls below this stops (early termination, the
# rest would change a pixel by less than 1 %), and what is left counts as opaque.
T_MIN = 0.01
# transmittance: a shadow ray of stochastic layers whose transmittance falls below this plays
# Russian roulette (it stops with the probability of the share lost, else counts as this):
# the frame 0.456 -> 0.423 s against exact transmittances, squared error per pixel 1.23e-3 ->
# 1.26e-3 (three translucent isovalues, 256^2, 4 spp; at 0.5: 0.434 s, 1.42e-3; at 1, a
# 0-or-1 sample: 0.397 s, 2.51e-3).
ROULETTE_T = 0.25
# opacity: a piece or sample more transparent than this is not shaded (it changes an 8-bit
# pixel by less than one level).
ALPHA_LIT = 1e-3
# opacity: alpha is capped here, since alpha = 1 means infinite extinction in the
# pre-integrated table.
OPACITY_CAP = 1.0 - 1e-4
# optical depth below which a step is thin: where its opacity is made is taken from the
# series in the depth (the closed form's float32 rounding error would exceed the series').
THIN_DEPTH = 0.05
# relative to a band's whole integral: a value ramp holding less than this of it is short:
# its depth is Simpson's rule of the extinction and its centroid takes the extinction as
# linear (a float32 difference of integrals keeps ~1e-4 of its digits here, and the ramp
# spans ~4 cells of the inverse table).
SHORT_RAMP_DEPTH = 1e-3
# fraction of a step, times its opacity: how far a step's centroid
# (band.segment_alpha_and_centroid) may lie from float64 quadrature, in tests; reached next to
# a capped band's plateau, where the extinction rises like a logarithm.
CENTROID_ABS = 5e-3

# ---------------------------------------------------------------------- volume shadows

# points: the most a transmittance cache holds per light (volume_shadows="cache",
# mi_amr.kernels.shadow_grid), 4 MiB of float32. Beyond it the grid is coarsened evenly. Its
# build is one exact shadow ray per point, so the cap bounds the first frame and the frame
# after a new light or band too, and a coarser grid blurs the shadows that small vortices cast
# and the edge of a band's shadow on itself. At 128^2, 16 multi-jittered spp, against exact at
# 64 spp, relative RMSE 0.020 / 0.018 / 0.017 (one band) and 0.017 / 0.013 / 0.010 (shells)
# at 2^19 / 2^20 / 2^21; the build's work about doubles with each doubling of the points, and
# 2^20 is the smallest cap that keeps both scenes clear of 0.02.
SHADOW_CACHE_POINTS = 2 ** 20
# points: the viewer builds a full-size cache in wavefronts of at most this many points and
# looks for a newer request between them, so a control moved while it builds waits for one
# wavefront, not the whole build. Each wavefront is traced again, so fewer, larger ones cost
# less in all; the report's scenes need about 0.4 million points, seven wavefronts.
SHADOW_CACHE_BUILD_CHUNK = 2 ** 16
# finest cells of the band's leaves: the longest stretch of a lit piece's shadow ray that is
# taken apart from its cache before the cache is read (mi_amr.kernels.shadow_grid: one cache cell,
# which at the full size is under 3 finest cells on the report's scenes); it bounds that
# stretch for the viewer's coarse preview caches.
SHADOW_REACH_CELLS = 4.0
# share of a pixel: a lit piece (or sample) whose light makes more of its pixel than this (the
# transmittance from the eye to it times its opacity) takes its first stretch apart from the
# cache (mi_amr.kernels.near); a fainter one reads the cache at itself. The faint haze of the
# shells scene holds most lit pieces, and its shadow on itself changes slowly: at 0.1, 16 spp,
# 128^2, against exact at the same samples, relative RMSE 0.017 (one band) and 0.016 (shells)
# with the near ramp, 0.016 and 0.016 with that stretch composited exactly, 0.016 and 0.014
# exactly everywhere, 0.065 and 0.038 with none.
SHADOW_NEAR_WEIGHT = 0.1
# |cos|: a lit piece's shadow ray whose direction makes less than this with the value's
# gradient (it runs within about 17 degrees of the band's surface) bends its near ramp to the
# value reconstructed at the stretch's end (mi_amr.kernels.near); the reconstruction is the
# ramp's dear part, so the other rays keep it straight. On a thin band (width 0.005,
# tests/test_volume_shadows.py) the straight ramp's mean |error| against the exact stretch is
# 0.03-0.06 at such rays, the bent one's 0.01-0.02; at rays that leave the band faster both
# are within 0.003-0.025, and on the report's rougher Q field the straight one is the closer
# (0.004 against 0.007).
NEAR_RAMP_GRAZING = 0.3
# transmittance: mean |ramp - exact| of a lit point's first stretch on a thin band (width
# 0.005, tests/test_volume_shadows.py test13) over the points whose shadow ray runs within
# NEAR_RAMP_GRAZING of the band, and half of it over all points; measured 0.014 and 0.011
# there for the two lights (0.011 and 0.010 over all), 0.042 with the ramp kept straight.
NEAR_RAMP_MEAN_ABS = 0.025
# points: the cache of the viewer's previews (mi_amr.workflows.viewer), a 128th of the full
# one: a slider that moves a band builds the cache again for each preview, and at the full size
# that build would take longer than the preview's frame itself.
PREVIEW_SHADOW_CACHE_POINTS = 2 ** 13
# relative RMSE: a volume image shadowed through the transmittance caches against the same
# image with exact per-piece shadow rays (tests/test_volume_shadows.py: two bands of an
# ellipsoid field, a directional and a point light, 32^2; measured 0.014, 0.017 with the
# grid read at the lit point itself, and 0.026 with the trilinear weights of two axes
# swapped); the lookup smooths each band's shadow within one cache cell.
SHADOW_CACHE_REL_RMSE = 0.022
# transmittance: mean |cached - exact| at random points of the leaves that hold opacity
# (same scene; measured 0.022 for either light, 0.042 with two axes swapped): the error of
# trilinear interpolation inside a cache cell, where the band's shadow on itself changes
# fastest.
SHADOW_CACHE_MEAN_ABS = 0.03
# transmittance: mean |cached - exact| on a thin band itself (width 0.002, same scene), where
# a lit piece's cached shadow composites the first grid cell exactly and reads the grid beyond
# (tests/test_volume_shadows.py test09; measured 0.026, and 0.059 for the grid read at the
# point itself: what is left is the grid's smoothing of the other band's shadow).
SHADOW_NEAR_MEAN_ABS = 0.035
# relative RMSE: the same scene with bands of width 0.005 at 4 spp, cached against exact
# (tests/test_volume_shadows.py test11; measured 0.0103 with the near ramp, 0.0097 with the
# first stretch composited exactly instead, 0.0105 with that for every lit piece, 0.0163 with
# none, 0.0123 with it only for the pieces too faint to count).
SHADOW_THIN_REL_RMSE = 0.0115
# relative RMSE: a volume image with corrected shadows (volume_shadows="corrected": the cache
# and one exact shadow ray per camera sample) against the exact image of the same seed, at
# 64 spp (same scene; measured 0.0030 with method exact and 0.0035 with adaptive, where the
# cache alone gives 0.013 and 0.014; its noise falls as 1 / sqrt(spp): 0.0059 and 0.0066 at
# 16 spp).
SHADOW_CORRECTED_REL_RMSE = 0.006
