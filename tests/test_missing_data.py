"""Missing data (``allow_nonfinite=True``): near NaN cells the blend's weights vanish, and the
exact method must not turn the zeros of ``N - iso D`` there into surfaces. The surface is drawn
where the cells with values carry at least :data:`mi_amr.tolerances.MIN_COVER` of the full
weight; within the last piece before missing data (under a cell) it is not drawn."""

import numpy as np
import pytest

import mi_amr
from mi_amr import AMRVolume
from mi_amr.synthetic import datasets

pytest.importorskip("drjit")


def sphere_with_a_hole(x_cut=0.47):
    """The analytic sphere with every cell whose centre has x < ``x_cut`` missing (NaN)."""
    grids = []
    for g in datasets.sphere(16).grids:
        f = g.fields["f"].copy()
        f[g.cell_centers()[0] < x_cut] = np.nan
        grids.append({"level": g.level, "origin": g.origin, "spacing": g.spacing,
                      "fields": {"f": f}})
    return AMRVolume.from_grids(grids, allow_nonfinite=True)


@pytest.mark.parametrize("reconstruction", ["basis", "finest"])
def test01_no_surface_is_made_up_at_the_edge_of_missing_data(reconstruction):
    """20,000 rays from a camera: every exact hit lies on the sphere |p - c| = 0.3 (before the
    fix, 191 basis and 92 finest hits lay on the planes x = 0.484 and x = 0.469 where the
    weights of the valid cells vanish, with true values 0.33-0.53)."""
    vol = sphere_with_a_hole()
    rng = np.random.default_rng(0)
    n = 20000
    o = np.tile([1.6, -0.9, 1.4], (n, 1))
    d = rng.random((n, 3)) - o
    r = mi_amr.trace(vol, o, d, field="f", isovalue=0.3, reconstruction=reconstruction)
    p = o[r.hit] + r.t[r.hit, None] * d[r.hit]
    off = np.abs(np.linalg.norm(p - 0.5, axis=1) - 0.3)
    assert r.hit.sum() > 5000
    assert np.all(off < 0.02), f"{np.sum(off >= 0.02)} hits off the surface, e.g. {p[off.argmax()]}"
    # Rays far from the hole see the same surface as without it.
    clean = mi_amr.trace(datasets.sphere(16), o, d, field="f", isovalue=0.3,
                         reconstruction=reconstruction)
    away = clean.hit & (o[:, 0] + clean.t * d[:, 0] > 0.6)
    np.testing.assert_array_equal(r.hit[away], clean.hit[away])
