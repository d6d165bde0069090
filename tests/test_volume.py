"""The data model: AMRVolume.from_grids builds valid hierarchies, answers queries, and refuses
every malformed one with an AMRError naming the grid(s) and field involved."""

import math
import re

import numpy as np
import pytest

from mi_amr import AMRError, AMRVolume, Grid
from conftest import LEVEL0, LEVEL1, LEVEL2, grid, random_grids, reference_grids


def cube(level=0, origin=(0, 0, 0), n=4, h=1.0, value=0.0, **fields):
    """A grid record of ``n**3`` cells; ``fields`` overrides the default field ``f``."""
    arrays = fields or {"f": np.full((n, n, n), value, dtype=np.float64)}
    return {"level": level, "origin": origin, "spacing": h, "fields": arrays}


def two_levels(fine_origin=(1, 1, 1), fine_shape=(4, 4, 4), ratio=2):
    """A level-0 grid of 4^3 unit cells and one level-1 grid."""
    fine = {"level": 1, "origin": fine_origin, "spacing": 1.0 / ratio,
            "fields": {"f": np.zeros(fine_shape)}}
    return [cube(), fine]


def grid_label(index, level):
    return re.escape(f"grid {index} (level {level}")


# ---------------------------------------------------------------------- building and round trip

def test01_valid_hierarchy_builds(reference_volume):
    vol = reference_volume
    assert len(vol.grids) == len(LEVEL0) + len(LEVEL1) + len(LEVEL2)
    assert vol.num_levels == 3
    assert vol.levels.tolist() == [0] * len(LEVEL0) + [1] * len(LEVEL1) + [2] * len(LEVEL2)
    assert vol.field_names == ("f",)
    assert all(isinstance(g, Grid) for g in vol.grids)
    assert vol.grids[0]["level"] == 0 and vol.grids[2]["shape"] == (8, 4, 4)


def test02_from_grids_of_a_volume_round_trips():
    rng = np.random.default_rng(1)
    vol = AMRVolume.from_grids(reference_grids(names=("a", "b"),
                                               fn=lambda c: rng.normal(size=c.shape[:-1])))
    again = AMRVolume.from_grids(vol.grids)
    assert len(again.grids) == len(vol.grids)
    assert again.ratios == vol.ratios
    np.testing.assert_array_equal(again.anchor, vol.anchor)
    for g, h in zip(vol.grids, again.grids):
        assert (h.level, h.origin, h.spacing, h.shape) == (g.level, g.origin, g.spacing, g.shape)
        assert list(h.fields) == list(g.fields)
        for name in g.fields:
            np.testing.assert_array_equal(h.fields[name], g.fields[name])
    for i in range(len(vol.grids)):
        np.testing.assert_array_equal(again.leaf_mask(i), vol.leaf_mask(i))


def test03_spacing_is_a_float_or_three_floats():
    as_float = AMRVolume.from_grids(two_levels())
    as_tuple = AMRVolume.from_grids([{**g, "spacing": (g["spacing"],) * 3}
                                     for g in two_levels()])
    for g, h in zip(as_float.grids, as_tuple.grids):
        assert g.spacing == h.spacing == (g.spacing[0],) * 3
    # Anisotropic cells: the ratio is still 2 on every axis.
    aniso = AMRVolume.from_grids([
        {"level": 0, "origin": (0, 0, 0), "spacing": (1.0, 2.0, 0.5),
         "fields": {"f": np.zeros((4, 4, 4))}},
        {"level": 1, "origin": (1, 2, 0.5), "spacing": np.array([0.5, 1.0, 0.25]),
         "fields": {"f": np.zeros((2, 2, 2))}}])
    assert aniso.ratios == (2,)
    np.testing.assert_array_equal(aniso.level_spacing(1), [0.5, 1.0, 0.25])
    np.testing.assert_array_equal(aniso.bounds[1], [4.0, 8.0, 2.0])


def test04_integer_fields_become_float64():
    vol = AMRVolume.from_grids([cube(f=np.arange(64).reshape(4, 4, 4))])
    assert vol.grids[0].fields["f"].dtype == np.float64
    assert vol.value_range("f") == (0.0, 63.0)


# ---------------------------------------------------------------------- queries

def test05_bounds_are_the_union_of_the_grid_boxes(reference_volume):
    lo, hi = reference_volume.bounds
    np.testing.assert_array_equal(lo, [0, 0, 0])
    np.testing.assert_array_equal(hi, [8, 8, 8])
    glo, ghi = reference_volume.grid_boxes()
    expected = [box for boxes in (LEVEL0, LEVEL1, LEVEL2) for box in boxes]
    np.testing.assert_array_equal(glo, [b[0] for b in expected])
    np.testing.assert_array_equal(ghi, [b[1] for b in expected])
    # A volume that does not start at the origin.
    shifted = AMRVolume.from_grids([cube(origin=(-3, 1.5, 2), h=0.5)])
    np.testing.assert_array_equal(shifted.bounds[0], [-3, 1.5, 2])
    np.testing.assert_array_equal(shifted.bounds[1], [-1, 3.5, 4])


@pytest.mark.parametrize("ratios", [(2, 2), (4, 2), (2, 4), (4, 4)])
def test06_levels_spacings_and_ratios(ratios):
    vol = AMRVolume.from_grids(reference_grids(ratios))
    assert vol.num_levels == 3
    assert vol.ratios == ratios
    np.testing.assert_array_equal(vol.level_spacing(0), [1, 1, 1])
    np.testing.assert_array_equal(vol.level_spacing(1), [1 / ratios[0]] * 3)
    np.testing.assert_array_equal(vol.level_spacing(2), [1 / (ratios[0] * ratios[1])] * 3)
    with pytest.raises(AMRError, match="no level 3; levels are 0..2"):
        vol.level_spacing(3)


def test07_index_boxes_are_integer_cells_from_the_anchor():
    vol = AMRVolume.from_grids(reference_grids((4, 2)))
    lo, hi = vol.index_boxes()
    assert lo.dtype == hi.dtype == np.int64
    # Level-1 grid 2 spans world [2, 6] x [2, 4] x [2, 4] in cells of 1/4; level-2 grid 5 spans
    # [3, 5] x [2.5, 3.5] x [2.5, 3.5] in cells of 1/8.
    assert (lo[2].tolist(), hi[2].tolist()) == ([8, 8, 8], [24, 16, 16])
    assert (lo[5].tolist(), hi[5].tolist()) == ([24, 20, 20], [40, 28, 28])
    np.testing.assert_array_equal(vol.anchor, [0, 0, 0])
    # One level only, anchored at the first grid's origin.
    single = AMRVolume.from_grids([cube(origin=(-1, 0, 0)), cube(origin=(-5, 0, 0))])
    lo, hi = single.index_boxes()
    assert lo.dtype == hi.dtype == np.int64
    assert lo.tolist() == [[0, 0, 0], [-4, 0, 0]] and hi.tolist() == [[4, 4, 4], [0, 4, 4]]


def leaf_masks_bruteforce(vol):
    """A cell is a leaf when no grid of a finer level contains its centre. (Fine grids end on
    faces of coarser cells, so a finer grid covers a cell entirely or not at all.)"""
    lo, hi = vol.grid_boxes()
    out = []
    for g in vol.grids:
        centres = np.stack(np.meshgrid(*g.cell_centers(), indexing="ij"), axis=-1)
        covered = np.zeros(g.shape, dtype=bool)
        for j in np.flatnonzero(vol.levels > g.level):
            covered |= np.all((centres > lo[j]) & (centres < hi[j]), axis=-1)
        out.append(~covered)
    return out


@pytest.mark.parametrize("ratios", [(2, 2), (4, 2)])
def test08_leaf_mask_matches_world_box_bruteforce(ratios):
    vol = AMRVolume.from_grids(reference_grids(ratios))
    expected = leaf_masks_bruteforce(vol)
    for i, mask in enumerate(expected):
        np.testing.assert_array_equal(vol.leaf_mask(i), mask, err_msg=f"grid {i}")
    # Finest grids are all leaves; some cells of every coarser grid here are covered.
    assert all(vol.leaf_mask(i).all() for i in np.flatnonzero(vol.levels == 2))
    assert not any(vol.leaf_mask(i).all() for i in np.flatnonzero(vol.levels == 0))
    # Leaf cells tile the domain: their volumes add up to the level-0 volume (8^3).
    leaf_volume = sum(vol.leaf_mask(i).sum() * np.prod(g.spacing) for i, g in enumerate(vol.grids))
    assert leaf_volume == pytest.approx(8.0 ** 3, rel=1e-12)
    assert vol.num_leaf_cells() == sum(int(m.sum()) for m in expected)


def test09_leaf_mask_of_random_hierarchies():
    for seed in range(4):
        vol = AMRVolume.from_grids(random_grids(seed, ratios=(2, 4)))
        for i, mask in enumerate(leaf_masks_bruteforce(vol)):
            np.testing.assert_array_equal(vol.leaf_mask(i), mask, err_msg=f"seed {seed} grid {i}")


@pytest.mark.parametrize("box_cells, chunk_cells", [(4096, 1 << 16), (0, 1 << 16), (8, 1)])
def test09b_leaf_masks_equal_their_slow_twin(box_cells, chunk_cells):
    """The flat leaf masks, cleared through flat cell indices in blocks of about
    ``chunk_cells`` cells (or box by box with slices above ``box_cells``), equal the slow
    twin's per-pair slices on random and reference hierarchies, ratio 4 included; so do the
    volume's own (the default sizes), cleared from the (coarse, fine) pairs its nesting check
    found, where the twin finds its own."""
    from mi_amr.core import volume as volume_module

    hierarchies = [random_grids(seed, ratios=ratios) for seed in range(4)
                   for ratios in ((2, 2), (4, 2), (2, 4))] + [reference_grids((4, 2))]
    for grids in hierarchies:
        vol = AMRVolume.from_grids(grids)
        assert vol._nesting is not None
        masks, partly = volume_module._leaf_masks_reference(vol)
        want = np.concatenate([m.ravel() for m in masks])
        flat, got_partly = volume_module._leaf_masks(vol, box_cells, chunk_cells)
        np.testing.assert_array_equal(got_partly, partly)
        np.testing.assert_array_equal(flat, want)
        np.testing.assert_array_equal(vol.partly_covered(), partly)
        for i, mask in enumerate(masks):
            np.testing.assert_array_equal(vol.leaf_mask(i), mask, err_msg=f"grid {i}")
        np.testing.assert_array_equal(vol.leaf_mask_flat(), want)


def test10_value_range_global_and_per_grid():
    # f = 10 * level + x: known per-grid minima and maxima at the extreme cell centres.
    grids = reference_grids()
    for g in grids:
        lo = np.array(g["origin"])
        n = g["fields"]["f"].shape
        x = lo[0] + (np.arange(n[0]) + 0.5) * g["spacing"]
        g["fields"]["f"] = np.broadcast_to(10.0 * g["level"] + x[:, None, None], n).copy()
    vol = AMRVolume.from_grids(grids)
    for i, g in enumerate(vol.grids):
        h = g.spacing[0]
        expected = (10.0 * g.level + g.origin[0] + h / 2, 10.0 * g.level + g.hi[0] - h / 2)
        assert vol.value_range("f", i) == pytest.approx(expected, abs=1e-12)
    # Level 0 holds the global minimum (x = 0.5); level 2 the maximum (grid 7: x up to 6.5).
    assert vol.value_range("f") == pytest.approx((0.5, 20.0 + 6.5 - 0.125), abs=1e-12)
    with pytest.raises(AMRError, match="unknown field 'g'; available: \\['f'\\]"):
        vol.value_range("g")


def test11_summary_mentions_levels_grids_cells_and_fields():
    grids = reference_grids(names=("density", "vx"))
    vol = AMRVolume.from_grids(grids, source="demo.npz")
    text = vol.summary()
    assert "source: demo.npz" in text
    assert "3 level(s)" in text
    assert f"{len(grids)} grid(s)" in text
    assert f"{vol.num_cells:,} cells" in text
    assert f"({vol.num_leaf_cells():,} leaf cells)" in text
    assert "density" in text and "vx" in text
    # One table row per level: level number, ratio, grid count.
    rows = [line.split() for line in text.splitlines() if re.match(r"\s+[0-2]\s+(-|2)\s", line)]
    assert [(r[0], r[1]) for r in rows] == [("0", "-"), ("1", "2"), ("2", "2")]
    assert [int(r[-3]) for r in rows] == [len(LEVEL0), len(LEVEL1), len(LEVEL2)]
    assert f"{len(grids)} grids" in repr(vol)


# ---------------------------------------------------------------------- malformed records

def test11b_plain_record_fast_path_equals_the_full_checks():
    """_parse_plain (the fast path for plain records) gives the same Grid as _parse_record for
    every form it takes, and declines (None) every other record, valid or not, which the full
    checks then parse or refuse."""
    from mi_amr.core.volume import _parse_plain, _parse_record

    f = np.arange(8.0).reshape(2, 2, 2)
    plain = [cube(), cube(level=3, origin=[0.5, 1, np.float64(2)], h=(0.5, 0.25, 1), n=2),
             {"level": 1, "origin": (0, 0, 0), "spacing": np.float64(0.5),
              "fields": {"a": f, "b": f.astype(np.float32)}},
             Grid(2, (0.0, 1.0, 2.0), (1.0, 1.0, 1.0), (2, 2, 2), {"f": f})]
    for g in plain:
        fast, full = _parse_plain(g), _parse_record(g, 0, "")
        assert fast is not None
        assert (fast.level, fast.origin, fast.spacing, fast.shape) == \
            (full.level, full.origin, full.spacing, full.shape)
        assert all(type(x) is float for x in fast.origin + fast.spacing)
        assert list(fast.fields) == list(full.fields)
        assert all(fast.fields[n] is full.fields[n] for n in full.fields)
    other = [cube(level=np.int64(1)), cube(origin=np.zeros(3)), cube(h=np.float32(1)),
             cube(f=np.zeros((4, 4, 4), dtype=np.int32)), cube(f=np.zeros((4, 4, 8))[:, :, ::2]),
             {**cube(), "fields": {"f": [[[0.0]]]}}, cube(level=True), cube(level=-1),
             cube(origin=(0, 0)), cube(origin=(0, math.nan, 0)), cube(h=0.0), cube(h=(1, 1, -1)),
             cube(f=np.zeros((0, 2, 2))), cube(f=np.zeros((2, 2))), cube(f=np.zeros(8, "U1")),
             {**cube(), "fields": {}}, {"level": 0, "origin": (0, 0, 0), "spacing": 1.0},
             cube(f=np.zeros((2, 2, 2)), g=np.zeros((2, 2, 4))), cube(**{"": np.zeros((2, 2, 2))}),
             [("level", 0)]]
    for g in other:
        assert _parse_plain(g) is None


def test12_empty_hierarchy_is_refused():
    with pytest.raises(AMRError, match="empty hierarchy"):
        AMRVolume.from_grids([])


def test13_record_that_is_not_a_mapping_is_refused():
    with pytest.raises(AMRError, match="grid 1: expected a mapping .* got list"):
        AMRVolume.from_grids([cube(), [0, (0, 0, 0), 1.0]])


@pytest.mark.parametrize("key", ["level", "origin", "spacing", "fields"])
def test14_missing_key_is_refused(key):
    record = cube()
    del record[key]
    with pytest.raises(AMRError, match=f"grid 0: missing key\\(s\\) \\['{key}'\\]"):
        AMRVolume.from_grids([record])


@pytest.mark.parametrize("level", [-1, 1.0, "0", True, None])
def test15_level_must_be_a_non_negative_integer(level):
    with pytest.raises(AMRError, match="grid 0: level must be an integer >= 0, got " +
                       re.escape(repr(level))):
        AMRVolume.from_grids([cube(level=level)])


def test16_numpy_integer_level_is_accepted():
    vol = AMRVolume.from_grids([cube(level=np.int64(0))])
    assert vol.grids[0].level == 0 and type(vol.grids[0].level) is int


@pytest.mark.parametrize("origin, message", [
    ((0, 0), "origin must be 3 numbers"),
    ((0, 0, 0, 0), "origin must be 3 numbers"),
    (5.0, "origin must be 3 numbers"),
    ((0, "a", 0), "origin must be 3 numbers"),
    ((0, math.nan, 0), "origin must be finite"),
    ((math.inf, 0, 0), "origin must be finite"),
])
def test17_bad_origin_is_refused(origin, message):
    with pytest.raises(AMRError, match="grid 1: " + message):
        AMRVolume.from_grids([cube(), cube(origin=origin)])


@pytest.mark.parametrize("spacing", [0.0, -1.0, (1, 0, 1), (1, -0.5, 1), math.nan,
                                     (1, 1, math.inf)])
def test18_spacing_must_be_positive_and_finite(spacing):
    with pytest.raises(AMRError, match="grid 0: spacing must be finite and > 0"):
        AMRVolume.from_grids([cube(h=spacing)])


def test19_spacing_of_wrong_length_is_refused():
    with pytest.raises(AMRError, match="grid 0: spacing must be a number or 3 numbers"):
        AMRVolume.from_grids([cube(h=(1.0, 1.0))])


@pytest.mark.parametrize("fields", [{}, None, [np.zeros((2, 2, 2))]])
def test20_fields_must_be_a_non_empty_mapping(fields):
    record = {**cube(), "fields": fields}
    with pytest.raises(AMRError, match="grid 0: fields must be a non-empty mapping"):
        AMRVolume.from_grids([record])


@pytest.mark.parametrize("shape", [(0, 4, 4), (4, 0, 4), (4, 4, 0)])
def test21_zero_size_grid_is_refused(shape):
    with pytest.raises(AMRError, match=grid_label(0, 0) + r".*field 'f' has zero-size shape"):
        AMRVolume.from_grids([cube(f=np.zeros(shape))])


@pytest.mark.parametrize("shape", [(4,), (4, 4), (4, 4, 4, 1)])
def test22_field_of_wrong_dimension_is_refused(shape):
    with pytest.raises(AMRError, match=grid_label(1, 0) +
                       f".*field 'f' has {len(shape)} dimension"):
        AMRVolume.from_grids([cube(), cube(origin=(4, 0, 0), f=np.zeros(shape))])


def test23_non_numeric_field_is_refused():
    with pytest.raises(AMRError, match=grid_label(0, 0) + ".*field 'f' has dtype"):
        AMRVolume.from_grids([cube(f=np.full((2, 2, 2), "x"))])


def test24_fields_of_one_grid_must_agree_in_shape():
    with pytest.raises(AMRError, match=grid_label(0, 0) + r".*field 'g' has shape \(4, 4, 2\) "
                       r"but field 'f' has \(4, 4, 4\)"):
        AMRVolume.from_grids([cube(f=np.zeros((4, 4, 4)), g=np.zeros((4, 4, 2)))])


def test25_every_grid_holds_the_same_fields():
    a = cube(f=np.zeros((4, 4, 4)), g=np.zeros((4, 4, 4)))
    b = cube(origin=(4, 0, 0), f=np.zeros((4, 4, 4)))
    with pytest.raises(AMRError, match=grid_label(1, 0) + r".*missing field\(s\) \['g'\]"):
        AMRVolume.from_grids([a, b])
    c = cube(origin=(4, 0, 0), f=np.zeros((4, 4, 4)), g=np.zeros((4, 4, 4)), p=np.zeros((4, 4, 4)))
    with pytest.raises(AMRError, match=grid_label(1, 0) + r".*has extra field\(s\) \['p'\]"):
        AMRVolume.from_grids([a, c])


@pytest.mark.parametrize("block_cells", [1, 64, 1 << 16])
def test25b_the_first_bad_grid_is_named_whatever_the_check_blocks(block_cells):
    """Fields are checked in blocks of grids (``block_cells`` cells, FINITE_CHECK_CELLS when
    a volume is made); the error still names the first bad grid in order, a missing field and
    a NaN in any order and in any block, as the grid-by-grid check (_check_grid_fields)
    would."""
    from mi_amr.core import volume as volume_module

    def check(grids, allow_nonfinite=False):
        """The field check of ``AMRVolume.from_grids`` on these grids, blocks of block_cells."""
        records = [Grid(g["level"], tuple(map(float, g["origin"])), (1.0, 1.0, 1.0),
                        next(iter(g["fields"].values())).shape, g["fields"]) for g in grids]
        volume_module._check_fields(records, "", allow_nonfinite, block_cells)

    n = 40

    def row(nan_at=None, lacking_at=None):
        out = []
        for i in range(n):
            values = np.zeros((2, 2, 2))
            if i == nan_at:
                values[1, 0, 1] = math.nan
            fields = {"f": values} if i == lacking_at else {"f": values, "g": values + 1}
            out.append(cube(origin=(2 * i, 0, 0), n=2, **fields))
        return out

    for nan_at, lacking_at in ((7, 30), (30, 7), (31, None), (None, 31), (9, 9)):
        first = min(i for i in (nan_at, lacking_at) if i is not None)
        what = "missing field" if first == lacking_at else "non-finite"
        with pytest.raises(AMRError, match=grid_label(first, 0) + f".*{what}"):
            check(row(nan_at, lacking_at))
        with pytest.raises(AMRError, match=grid_label(first, 0) + f".*{what}"):
            AMRVolume.from_grids(row(nan_at, lacking_at))
    check(row(nan_at=5), allow_nonfinite=True)
    vol = AMRVolume.from_grids(row(nan_at=5), allow_nonfinite=True)
    assert len(vol.grids) == n


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test26_non_finite_values_are_refused(bad):
    values = np.zeros((4, 4, 4))
    values[1, 2, 3] = bad
    with pytest.raises(AMRError, match=grid_label(1, 0) + r".*field 'f' has 1 non-finite value"
                       r".*allow_nonfinite=True"):
        AMRVolume.from_grids([cube(), cube(origin=(4, 0, 0), f=values)])


def test27_allow_nonfinite_accepts_them_and_value_range_ignores_them():
    values = np.arange(64, dtype=np.float64).reshape(4, 4, 4)
    values[0, 0, 0] = math.nan           # would be the minimum
    values[3, 3, 3] = math.inf           # would be the maximum
    values[3, 3, 2] = -math.inf
    all_nan = np.full((4, 4, 4), math.nan)
    vol = AMRVolume.from_grids([cube(f=values), cube(origin=(4, 0, 0), f=all_nan)],
                               allow_nonfinite=True)
    assert vol.allow_nonfinite
    assert vol.value_range("f", 0) == (1.0, 61.0)
    assert all(math.isnan(x) for x in vol.value_range("f", 1))
    assert vol.value_range("f") == (1.0, 61.0)
    assert "non-finite values allowed" in vol.summary()
    nothing = AMRVolume.from_grids([cube(f=all_nan)], allow_nonfinite=True)
    assert all(math.isnan(x) for x in nothing.value_range("f"))


def test28_source_prefixes_the_messages():
    with pytest.raises(AMRError, match=r"^run7\.npz: grid 0: missing key"):
        AMRVolume.from_grids([{"level": 0}], source="run7.npz")


# ---------------------------------------------------------------------- levels and ratios

def test29_level_0_is_required():
    with pytest.raises(AMRError, match=r"no level-0 grid.*got levels \[1, 2\]"):
        AMRVolume.from_grids([cube(level=1), cube(level=2, h=0.5)])


def test30_levels_must_be_contiguous():
    with pytest.raises(AMRError, match=r"level\(s\) \[1\] have no grids but finer levels do"):
        AMRVolume.from_grids([cube(), cube(level=2, origin=(1, 1, 1), n=4, h=0.25)])


def test31_one_spacing_per_level():
    with pytest.raises(AMRError, match=grid_label(1, 0) + r".*spacing \(0\.5, 0\.5, 0\.5\) differs "
                       r"from " + grid_label(0, 0)):
        AMRVolume.from_grids([cube(), cube(origin=(4, 0, 0), h=0.5)])


@pytest.mark.parametrize("ratio", [3, 8, 1.5, 1])
def test32_refinement_ratio_other_than_2_or_4_is_refused(ratio):
    fine = {"level": 1, "origin": (0, 0, 0), "spacing": 1.0 / ratio,
            "fields": {"f": np.zeros((12, 12, 12))}}
    with pytest.raises(AMRError, match="refinement ratio from level 0 to 1 is .*expected 2 or 4"):
        AMRVolume.from_grids([cube(n=12), fine])


@pytest.mark.parametrize("ratio", [2, 4])
def test33_refinement_ratios_2_and_4_are_accepted(ratio):
    vol = AMRVolume.from_grids(two_levels(fine_origin=(1, 1, 1), fine_shape=(2 * ratio,) * 3,
                                          ratio=ratio))
    assert vol.ratios == (ratio,)
    # The fine grid covers level-0 cells 1..2 on each axis.
    expected = np.ones((4, 4, 4), dtype=bool)
    expected[1:3, 1:3, 1:3] = False
    np.testing.assert_array_equal(vol.leaf_mask(0), expected)


def test34_ratio_must_be_the_same_on_all_axes():
    fine = {"level": 1, "origin": (0, 0, 0), "spacing": (0.5, 0.5, 0.25),
            "fields": {"f": np.zeros((4, 4, 8))}}
    with pytest.raises(AMRError, match=r"ratio from level 0 to 1 is \(2\.0, 2\.0, 4\.0\)"):
        AMRVolume.from_grids([cube(), fine])


# ---------------------------------------------------------------------- lattice, overlap, nesting

@pytest.mark.parametrize("origin", [(1.5, 1, 1), (1, 1.25, 1), (1, 1, 0.99)])
def test35_fine_origin_off_the_coarse_lattice_is_refused(origin):
    # Half a level-0 cell is a whole level-1 cell, but not a level-0 face.
    with pytest.raises(AMRError, match=grid_label(1, 1) + r".*origin is not on a cell face of "
                       r"level 0"):
        AMRVolume.from_grids(two_levels(fine_origin=origin))


def test36_level_0_grids_share_one_lattice():
    with pytest.raises(AMRError, match=grid_label(1, 0) + r".*origin is not on a cell face"):
        AMRVolume.from_grids([cube(), cube(origin=(4.5, 0, 0))])


def test37_origin_rounding_within_the_lattice_tolerance_passes():
    # 0.1 * 3 is not exactly 0.3; such origins must still count as aligned.
    vol = AMRVolume.from_grids([cube(h=0.1), cube(origin=(0.1 * 4, 0, 0), h=0.1),
                                cube(level=1, origin=(0.1 * 3, 0.1, 0.1), n=2, h=0.05)])
    assert vol.ratios == (2,)
    assert vol.index_boxes()[0][2].tolist() == [6, 2, 2]


@pytest.mark.parametrize("shape", [(3, 4, 4), (4, 5, 4), (4, 4, 1)])
def test38_fine_shape_not_a_multiple_of_the_ratio_is_refused(shape):
    with pytest.raises(AMRError, match=grid_label(1, 1) + ".*" + re.escape(f"shape {shape}") +
                       r".* not a multiple of the refinement ratio 2"):
        AMRVolume.from_grids(two_levels(fine_shape=shape))


def test39_overlapping_grids_of_one_level_are_refused():
    with pytest.raises(AMRError, match=grid_label(0, 0) + r".* and " + grid_label(1, 0) +
                       r".* overlap"):
        AMRVolume.from_grids([cube(), cube(origin=(3, 3, 3))])
    # At level 1, and with the clashing grids not first in the list.
    grids = reference_grids()
    grids.append(grid(1, (3, 3, 3), (4, 4, 4), 0.5))
    with pytest.raises(AMRError, match=grid_label(2, 1) + r".* and " + grid_label(8, 1) +
                       r".* overlap"):
        AMRVolume.from_grids(grids)


@pytest.mark.parametrize("seed", range(12))
def test39b_overlaps_found_through_blocks_or_boxes_name_the_first_pair(seed):
    """A level's overlaps are found through its blocks (which its level table then reuses) or,
    for a level of too many blocks, box against box: either way the first pair (lowest grid,
    then its lowest partner) of a brute-force search over every pair."""
    from mi_amr.core import levels
    from mi_amr.core.volume import _first_overlap

    rng = np.random.default_rng(seed)
    step = int(rng.choice([1, 2, 4, 8]))
    lo = rng.integers(0, 12, size=(int(rng.integers(2, 30)), 3)) * step
    hi = lo + rng.integers(1, 5, size=lo.shape) * step
    inter = np.minimum(hi[:, None], hi[None]) > np.maximum(lo[:, None], lo[None])
    pairs = [(i, j) for i in range(len(lo)) for j in range(i + 1, len(lo))
             if inter[i, j].all()]
    expected = pairs[0] if pairs else None
    blocks = {}
    assert _first_overlap(lo, hi, blocks, 0) == expected
    assert _first_overlap(lo, hi, {}, 0, most=0) == expected
    listed = levels.LevelBlocks.of(lo, hi)
    assert len(listed.keys) == levels.LevelBlocks.count(lo, hi)
    assert listed.first_overlap() == expected
    # Blocks are kept (for the level's index) where they hold 8 cells or more each.
    assert (0 in blocks) == (listed.block >= 2)
    if blocks:
        assert np.array_equal(blocks[0].keys, listed.keys)


def test39c_a_level_table_takes_the_blocks_the_check_listed():
    """The level tables of a checked volume are those made from nothing: the blocks its check
    listed are taken (and dropped from the cache), not listed again."""
    from mi_amr.core import levels

    vol = AMRVolume.from_grids(reference_grids())
    assert sorted(vol.level_caches.blocks) == list(range(vol.num_levels))
    taken = [vol.level_caches.blocks[level].keys for level in range(vol.num_levels)]
    fresh = AMRVolume.from_grids(reference_grids())
    fresh.level_caches.blocks = {}
    for level in range(vol.num_levels):
        made, again = levels.level_index(vol, level), levels.level_index(fresh, level)
        assert made.keys is taken[level]
        for name in ("keys", "owner", "origin", "dims", "table"):
            assert np.array_equal(getattr(made, name), getattr(again, name)), name
        assert made.block == again.block
    assert vol.level_caches.blocks == {}


def test40_fine_grid_outside_the_coarser_level_is_refused():
    # Half of the fine grid pokes out of the level-0 grid.
    with pytest.raises(AMRError, match=grid_label(1, 1) + r".* is not inside the level-0 grids "
                       r"\(only 50% of it is covered\)"):
        AMRVolume.from_grids(two_levels(fine_origin=(3, 0, 0)))


def test41_fine_grid_must_nest_in_the_union_not_just_the_bounds():
    # Two level-0 grids in an L; the fine grid fills the corner the L lacks.
    grids = [cube(), cube(origin=(4, 0, 0)), cube(origin=(0, 4, 0)),
             grid(1, (3, 3, 0), (5, 5, 1), 0.5)]
    with pytest.raises(AMRError, match=grid_label(3, 1) + r".* not inside the level-0 grids "
                       r"\(only 75%"):
        AMRVolume.from_grids(grids)
    # A level-2 grid inside level 0 but outside every level-1 grid.
    grids = reference_grids() + [grid(2, (0, 0, 0), (1, 1, 1), 0.25)]
    with pytest.raises(AMRError, match=grid_label(8, 2) + r".* not inside the level-1 grids"):
        AMRVolume.from_grids(grids)


def test42_grids_sharing_faces_edges_or_corners_are_allowed():
    vol = AMRVolume.from_grids([cube(), cube(origin=(4, 0, 0)), cube(origin=(4, 4, 0)),
                                cube(origin=(0, 4, 4)),
                                # A fine grid spanning the face x = 4 of two coarse grids.
                                grid(1, (3, 1, 1), (5, 2, 2), 0.5)])
    assert len(vol.grids) == 5
    assert (~vol.leaf_mask(0)).sum() == 1 and (~vol.leaf_mask(1)).sum() == 1


# ---------------------------------------------------------------------- far-off grids, odd input

@pytest.mark.parametrize("records, where", [
    # A fine grid at x = 1e21, far outside level 0: the int64 cast of its index overflowed and
    # the nesting check passed.
    (two_levels(fine_origin=(1e21, 0, 0)), grid_label(1, 1)),
    # A level-0 grid at y = -1.25e23, where a damaged plotfile Header put it.
    ([cube(), cube(origin=(0, -1.25e23, 0))], grid_label(1, 0)),
])
def test43_grids_too_far_from_the_lattice_anchor_are_refused(records, where):
    with pytest.raises(AMRError, match=where + r".*cells of level 0 from the level-0 lattice "
                       r"anchored at \(0\.0, 0\.0, 0\.0\)"):
        with np.errstate(all="raise"):
            AMRVolume.from_grids(records)


def test44_grids_that_are_not_a_sequence_of_records_are_refused():
    for grids, kind in ((None, "NoneType"), (3, "int"), (cube(), "dict"), ("grid", "str")):
        with pytest.raises(AMRError, match=f"grids must be a sequence of grid records .*got "
                                           f"{kind}"):
            AMRVolume.from_grids(grids)


@pytest.mark.parametrize("records, message", [
    ([cube(level=np.int64(-1))], "level must be an integer >= 0, got -1"),
    ([cube(origin=(np.float64(0), np.float64(math.nan), 0))],
     "origin must be finite, got (0.0, nan, 0)"),
    ([cube(h=np.array([1.0, 1.0]))], "spacing must be a number or 3 numbers, got [1.0, 1.0]"),
    ([cube(), cube(origin=(np.float64(4.5), 0, 0))],
     "offset (4.5, 0.0, 0.0) cells from the level-0 lattice anchored at (0.0, 0.0, 0.0)"),
])
def test45_messages_show_plain_numbers_not_numpy_reprs(records, message):
    with pytest.raises(AMRError) as info:
        AMRVolume.from_grids(records)
    assert message in str(info.value)
    assert "np." not in str(info.value) and "array(" not in str(info.value)


def test46_summary_columns_line_up_for_long_spacings():
    """Spacings such as 0.000625 (the plt_eb_3d plotfile) are wider than the old fixed column;
    every row of the level table must still end where its heading does."""
    h = 0.00125
    vol = AMRVolume.from_grids([cube(h=h), grid(1, (h, h, h), (3 * h, 3 * h, 3 * h), h / 2)])
    lines = vol.summary().splitlines()
    start = next(i for i, line in enumerate(lines) if line.lstrip().startswith("level"))
    table = lines[start:start + 1 + vol.num_levels]
    assert "(0.000625, 0.000625, 0.000625)" in table[2]
    assert len({len(line) for line in table}) == 1, table
    for column in ("grids", "cells"):
        end = table[0].index(column) + len(column)
        assert all(line[end - 1] != " " and (end == len(line) or line[end] == " ")
                   for line in table[1:]), (column, table)


def test47_an_absurd_finest_level_is_refused_at_once():
    """Levels 0 and 10^12: the contiguity check must not enumerate the missing levels (that
    took all memory). In a child with a memory limit, so a regression fails instead of
    swapping."""
    import subprocess
    import sys

    code = ("import resource, numpy as np\n"
            "resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))\n"
            "from mi_amr import AMRVolume, AMRError\n"
            "f = {'f': np.zeros((2, 2, 2))}\n"
            "try:\n"
            "    AMRVolume.from_grids([{'level': 0, 'origin': (0, 0, 0), 'spacing': 1.0, "
            "'fields': f}, {'level': 10**12, 'origin': (0, 0, 0), 'spacing': 0.5, 'fields': f}])\n"
            "except AMRError as e:\n"
            "    print(e)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert run.stdout.startswith("level(s) [1, 2, 3] ... have no grids") or \
        run.stdout.startswith("level(s) [1, 2, 3] have no grids"), run.stdout + run.stderr
