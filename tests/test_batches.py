"""Per-grid NumPy passes taken by shape (:mod:`mi_amr.core.batches`): the isovalue pick's leaf
values and neighbour pairs, and the camera's value box, equal their grid-by-grid slow twins bit
for bit, whatever the batches."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from conftest import random_grids
from mi_amr import AMRVolume
from mi_amr.core import batches, framing, suggest


def _volume(seed, dtype, holes: bool):
    """A random hierarchy whose field ``f`` holds a few repeated values (pairs of equal values,
    and values equal to the ranges' ends) and, with ``holes``, NaN and Inf cells."""
    rng = np.random.default_rng(seed)
    grids = random_grids(seed, ratios=((2, 2), (2, 4), (4, 2))[seed % 3])
    for g in grids:
        f = np.round(rng.normal(size=g["fields"]["f"].shape), 1)
        if holes:
            f[rng.random(f.shape) < 0.05] = np.nan
            f[rng.random(f.shape) < 0.02] = np.inf
        g["fields"] = {"f": f.astype(dtype)}
    return AMRVolume.from_grids(grids, allow_nonfinite=holes)


def test01_batches_hold_every_grid_once_each_of_one_shape():
    vol = _volume(3, np.float32, False)
    offsets = vol.cell_offsets()
    flat = batches.flat_field(vol, "f")
    seen = []
    for ids, shape in batches.shape_batches(vol, cells=40):
        assert np.all(np.diff(ids) > 0) and len(ids) >= 1
        assert len(ids) == 1 or len(ids) * np.prod(shape) <= 40
        block = batches.stacked(flat, offsets, ids, shape)
        for j, g in enumerate(ids):
            assert vol.grids[g].shape == shape
            np.testing.assert_array_equal(block[j], vol.grids[g].fields["f"])
        seen += list(ids)
    assert sorted(seen) == list(range(len(vol.grids)))


def test01b_grids_end_to_end_are_a_view_others_a_copy():
    """Grids one after the other in the flat array are read in place; others are gathered."""
    grids = [{"level": 0, "origin": (2.0 * i, 0.0, 0.0), "spacing": 1.0,
              "fields": {"f": np.arange(8.0).reshape(2, 2, 2) + 10 * i}} for i in range(4)]
    vol = AMRVolume.from_grids(grids)
    flat, offsets = batches.flat_field(vol, "f"), vol.cell_offsets()
    for ids, view in (([1, 2, 3], True), ([0, 2], False), ([3], True)):
        block = batches.stacked(flat, offsets, np.array(ids), (2, 2, 2))
        assert np.shares_memory(block, flat) == view, ids
        for j, g in enumerate(ids):
            np.testing.assert_array_equal(block[j], vol.grids[g].fields["f"])


@pytest.mark.filterwarnings("error::RuntimeWarning")   # (NumPy's inf - inf warning printed)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), dtype=st.sampled_from([np.float32, np.float64]),
       holes=st.booleans(), batch=st.sampled_from([1, 64, 1 << 20]),
       max_pairs=st.sampled_from([4, 50, 1 << 21]))
def test02_the_pick_and_the_box_equal_their_grid_by_grid_twins(seed, dtype, holes, batch,
                                                              max_pairs, monkeypatch_module):
    monkeypatch_module.setattr(batches, "BATCH_CELLS", batch)
    monkeypatch_module.setattr(suggest, "MAX_PAIRS", max_pairs)
    vol = _volume(seed, dtype, holes)
    for level in (None, *range(vol.num_levels)):
        fast, slow = suggest.leaf_values(vol, "f", level), \
            suggest.leaf_values_reference(vol, "f", level)
        assert fast.dtype == slow.dtype == np.float64
        np.testing.assert_array_equal(fast, slow)
    values = suggest.finite_leaf_values(vol, "f")
    candidates = np.unique(np.concatenate([values[::7], [0.0, 0.05, values[-1]]]))
    for span in (0.0, 0.1, 0.35):
        fast = suggest._crossings(vol, "f", candidates, span)
        slow = suggest._crossings_reference(vol, "f", candidates, span)
        assert fast.dtype == slow.dtype
        np.testing.assert_array_equal(fast, slow)
    for lo, hi in ((0.0, 0.0), (0.05, 0.05), (-0.3, 0.2), (1.5, 9.0), (50.0, 60.0)):
        fast, slow = framing.value_box(vol, "f", lo, hi), \
            framing.value_box_reference(vol, "f", lo, hi)
        assert (fast is None) == (slow is None), (lo, hi)
        if fast is not None:
            np.testing.assert_array_equal(fast[0], slow[0])
            np.testing.assert_array_equal(fast[1], slow[1])


@pytest.fixture(scope="module")
def monkeypatch_module():
    with pytest.MonkeyPatch.context() as mp:
        yield mp
