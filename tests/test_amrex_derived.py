"""mi_amr.derive against the fields an AMReX code derived itself: example_plt_3d stores the
vorticity magnitude (``mag_vort``) and the enstrophy beside the velocity it came from.

The sample (../shared/data/amrex/example_plt_3d, see SOURCE.md there) is a flat premixed flame in
a 16 mm box: level 2 (32^3 cells of 0.5 mm) covers the whole domain, the flow lies in the y-z
plane (x_velocity is ~1e-13, noise) and does not vary along x. Without the sample the module is
skipped.
"""

from pathlib import Path

import numpy as np
import pytest

import mi_amr
from mi_amr.core.derive import q_criterion, velocity_gradient

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "amrex"
SAMPLE = DATA / "example_plt_3d"
if not SAMPLE.is_dir():
    pytest.skip(f"AMReX sample plotfile not found at {SAMPLE} (see shared/data/amrex/SOURCE.md)",
                allow_module_level=True)

VELOCITY = ("x_velocity", "y_velocity", "z_velocity")


@pytest.fixture(scope="module")
def volume():
    vol = mi_amr.load(SAMPLE, fields=[*VELOCITY, "mag_vort", "enstrophy", "density"])
    return mi_amr.derive(vol, "vorticity_magnitude", "q_criterion")


def away_from_walls(volume, i):
    """Cells of grid ``i`` at least one cell from the domain's y and z faces.

    On those faces the code took the missing neighbour from its boundary conditions (inflow,
    outflow, walls), mi_amr from a one-sided difference inside the data; the two differ there
    by design (on level 2's 3,968 face cells the median relative difference is 99.6%: the
    code's wall values make steeper gradients). Along x the flow is uniform, so both give 0
    for d/dx on the x faces, which are kept.
    """
    lo, hi = volume.index_boxes()
    g = volume.grids[i]
    n = np.round((volume.bounds[1] - volume.bounds[0]) / np.asarray(g.spacing)).astype(int)
    idx = np.meshgrid(*[np.arange(a, b) for a, b in zip(lo[i], hi[i])], indexing="ij")
    return (idx[1] > 0) & (idx[1] < n[1] - 1) & (idx[2] > 0) & (idx[2] < n[2] - 1)


def test01_vorticity_magnitude_matches_the_stored_mag_vort(volume):
    # Both are central differences of the same velocity on the same cells (level-2 grids
    # take their neighbours from each other, the code from its filled ghost cells), so away
    # from the y/z faces they agree to rounding: the largest relative difference seen is
    # 4e-13 on level 2 (28,800 cells), 4e-14 on level 1 and 1e-14 on level 0.
    for level in range(volume.num_levels):
        rel = []
        for i in np.flatnonzero(volume.levels == level):
            g = volume.grids[i]
            keep = away_from_walls(volume, i)
            mine, stored = g.fields["vorticity_magnitude"], g.fields["mag_vort"]
            rel.append((np.abs(mine - stored) / stored)[keep])
        rel = np.concatenate(rel)
        assert rel.size > 0
        assert np.median(rel) < 1e-12, level
        assert rel.max() < 1e-9, level


def test02_stored_enstrophy_is_density_weighted(volume):
    # The code's enstrophy is rho |omega|^2 / 2 (not |omega|^2 / 2): the ratio to its own
    # mag_vort is the density in every cell, including the faces.
    for g in volume.grids:
        expected = 0.5 * g.fields["density"] * g.fields["mag_vort"] ** 2
        np.testing.assert_allclose(g.fields["enstrophy"], expected, rtol=1e-12, atol=0)


def test03_q_criterion_agrees_with_the_stored_enstrophy(volume):
    # With G = grad v, S = (G + G^T) / 2 and Omega = (G - G^T) / 2, Q = (|Omega|^2 - |S|^2) / 2
    # (Frobenius norms). Omega holds the vorticity twice: |Omega|^2 = |omega|^2 / 2. So
    #     Q = |omega|^2 / 4 - |S|^2 / 2 = enstrophy / (2 rho) - |S|^2 / 2
    # with the stored, density-weighted enstrophy = rho |omega|^2 / 2 (test02). Only |S|^2
    # comes from mi_amr's gradient here; the vorticity part comes from the code.
    grads = velocity_gradient(volume, VELOCITY)
    worst = 0.0
    for i, (g, G) in enumerate(zip(volume.grids, grads)):
        keep = away_from_walls(volume, i)
        S = 0.5 * (G + G.transpose(1, 0, 2, 3, 4))
        s2 = np.sum(S * S, axis=(0, 1))
        vort_part = g.fields["enstrophy"] / (2.0 * g.fields["density"])
        expected = vort_part - 0.5 * s2
        # Cancellation: compare with the size of the two terms, not with Q itself.
        scale = vort_part + 0.5 * s2
        np.testing.assert_allclose(q_criterion(G), g.fields["q_criterion"], rtol=1e-12, atol=0)
        err = np.abs(g.fields["q_criterion"] - expected) / scale
        worst = max(worst, float(err[keep].max()))
    assert worst < 1e-9  # 6e-16 seen


def test04_the_flame_is_strain_dominated_everywhere(volume):
    # Why the example scene contours a negative Q: in this flow no cell has Q > 0. Expansion
    # through the flame (dilatation) and the shear of the accelerated burnt gas dominate the
    # weak in-plane rotation; Q is most negative in the flame (about -1e5 /s^2).
    hi = max(volume.value_range("q_criterion", i)[1] for i in range(len(volume.grids)))
    assert hi < 0.0
