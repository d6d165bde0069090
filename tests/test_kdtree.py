"""The kd-tree over grid supports: point queries equal their brute-force twins (faces, edges and
corners included), leaves partition the tree's box with one owner each, respect the size bound,
list exactly the active grids, and carry conservative value ranges."""


import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mi_amr import AMRError, AMRVolume, KDTree
from mi_amr.synthetic import datasets
from mi_amr.core.kdtree import (CHUNK, _box_sum, leaf_count_tables,
                                leaf_count_tables_reference, _window_min_max,
                                _window_min_max_reference, finest_grid_bruteforce,
                                support_grids_bruteforce)
from conftest import random_grids, reference_grids, stretched

def random_field(seed):
    """Cell values: independent normal samples (so every cell's value is distinct)."""
    rng = np.random.default_rng(seed)
    return lambda centres: rng.normal(size=centres.shape[:-1])


HIERARCHIES = {
    "ratio2": lambda: reference_grids((2, 2), fn=random_field(1)),
    "ratio4-2": lambda: reference_grids((4, 2), fn=random_field(2)),
    "ratio2-4": lambda: reference_grids((2, 4), fn=random_field(3)),
    "random0": lambda: random_grids(0, ratios=(2, 4), fn=random_field(4)),
    "random1": lambda: random_grids(1, ratios=(4, 2), fn=random_field(5)),
    "random2": lambda: random_grids(2, ratios=(2, 2), fn=random_field(6)),
    "anisotropic": lambda: stretched(random_grids(0, ratios=(2, 4), fn=random_field(4))),
}


@pytest.fixture(scope="module", params=sorted(HIERARCHIES))
def tree(request):
    return KDTree(AMRVolume.from_grids(HIERARCHIES[request.param]()))


def boundary_points(vol, rng):
    """Points exactly on the faces, edges and corners of every grid box and every support box
    (box grown by one cell), plus random points on the finest level's half-cell lattice (cell
    faces and centres)."""
    lo, hi = vol.grid_boxes()
    h = vol.spacings()
    pts = []
    for blo, bhi in ((lo, hi), (lo - h, hi + h)):
        for corner in range(8):
            bits = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], dtype=bool)
            pts.append(np.where(bits, bhi, blo))
        for a in range(3):
            for side in (blo, bhi):
                face = blo + rng.random(blo.shape) * (bhi - blo)
                face[:, a] = side[:, a]
                pts.append(face)
                b = (a + 1) % 3
                for side2 in (blo, bhi):
                    edge = face.copy()
                    edge[:, b] = side2[:, b]
                    pts.append(edge)
    vlo, vhi = vol.bounds
    half = vol.level_spacing(vol.num_levels - 1) / 2
    steps = np.round((vhi - vlo) / half).astype(int)
    lattice = vlo + rng.integers(-2, steps + 3, size=(2000, 3)) * half
    return np.concatenate(pts + [lattice])


def random_points(vol, rng, n=3000, margin=1.0):
    vlo, vhi = vol.bounds
    return vlo - margin + rng.random((n, 3)) * (vhi - vlo + 2 * margin)


def leaf_grid_lists(tree):
    """Per leaf: (every listed grid, the active ones)."""
    out = []
    for leaf in range(tree.num_leaves):
        start = tree.leaf_start[leaf]
        listed = tree.leaf_grids[start:start + tree.leaf_nsupport[leaf]]
        out.append((listed, listed[:tree.leaf_nactive[leaf]]))
    return out


def hat_overlap(tree, g, cells=None):
    """``(L, N)``: does the open hat support (centre +- one cell) of cell ``n`` of grid ``g``
    overlap leaf ``l`` with positive volume? ``cells`` selects cells by a boolean mask."""
    grid = tree.volume.grids[g]
    centres = np.stack(np.meshgrid(*grid.cell_centers(), indexing="ij"), axis=-1)
    centres = centres[cells] if cells is not None else centres.reshape(-1, 3)
    h = np.asarray(grid.spacing)
    lo = np.maximum(tree.leaf_lo[:, None, :], centres[None] - h)
    hi = np.minimum(tree.leaf_hi[:, None, :], centres[None] + h)
    return np.all(hi > lo, axis=2)


# ---------------------------------------------------------------------- point queries

def test01_finest_grid_equals_bruteforce(tree):
    rng = np.random.default_rng(1)
    vol = tree.volume
    pts = np.concatenate([boundary_points(vol, rng), random_points(vol, rng)])
    np.testing.assert_array_equal(tree.finest_grid(pts), finest_grid_bruteforce(vol, pts))


def test02_support_grids_equal_bruteforce(tree):
    rng = np.random.default_rng(2)
    vol = tree.volume
    pts = np.concatenate([boundary_points(vol, rng), random_points(vol, rng)])
    got = tree.support_grids(pts)
    want = support_grids_bruteforce(vol, pts)
    assert len(got) == len(want) == len(pts)
    for p, a, b in zip(pts, got, want):
        np.testing.assert_array_equal(a, b, err_msg=f"point {p}")


def test03_bruteforce_twins_agree_with_hand_derived_answers():
    vol = AMRVolume.from_grids(reference_grids())
    tree = KDTree(vol)
    pts = np.array([
        [0.5, 0.5, 0.5],      # level-0 grid 0 only
        [4.0, 0.5, 0.5],      # on the face shared by grids 0 and 1: lowest index wins
        [4.0, 2.25, 3.0],     # level-1 grid 2 spans that face; on grid 5's support boundary
        [3.5, 3.0, 3.0],      # level-2 grid 5
        [3.5, 3.5, 3.0],      # face shared by level-2 grids 5 and 6; on grid 3's support boundary
        [8.0, 8.0, 8.0],      # the volume's far corner
        [8.5, 4.0, 4.0],      # outside every grid, inside grid 1's support (h = 1)
        [9.0, 4.0, 4.0],      # on grid 1's support boundary (open): nothing
    ])
    want_finest = [0, 0, 2, 5, 5, 1, -1, -1]
    want_support = [[0], [0, 1], [0, 1, 2], [0, 1, 2, 5], [0, 1, 2, 5, 6], [1], [1], []]
    for finest in (tree.finest_grid(pts), finest_grid_bruteforce(vol, pts)):
        assert finest.tolist() == want_finest
    for support in (tree.support_grids(pts), support_grids_bruteforce(vol, pts)):
        assert [s.tolist() for s in support] == want_support


def test04_far_outside_points_have_no_grid(tree):
    vlo, vhi = tree.volume.bounds
    pts = np.array([vlo - 5, vhi + 5, [vlo[0] - 5, vhi[1] / 2, vhi[2] / 2]])
    assert tree.finest_grid(pts).tolist() == [-1, -1, -1]
    assert all(len(s) == 0 for s in tree.support_grids(pts))


# ---------------------------------------------------------------------- leaf invariants

def test05_every_leaf_is_inside_or_outside_each_grid_box(tree):
    glo, ghi = tree.volume.grid_boxes()
    llo, lhi = tree.leaf_lo[:, None, :], tree.leaf_hi[:, None, :]
    inside = np.all((glo[None] <= llo) & (lhi <= ghi[None]), axis=2)
    outside = np.any((lhi <= glo[None]) | (ghi[None] <= llo), axis=2)
    assert np.all(inside | outside)
    assert np.all(tree.leaf_hi > tree.leaf_lo)


def test06_leaves_tile_the_tree_box(tree):
    total = np.prod(tree.hi - tree.lo)
    volumes = np.prod(tree.leaf_hi - tree.leaf_lo, axis=1)
    assert volumes.sum() == pytest.approx(total, rel=1e-12)
    # The tree box holds every support, its middle is the low corner of the grids, and it spans
    # a power of two of the finest cells along each axis (so every midpoint cut lands on the
    # lattice of power-of-two blocks from that corner).
    assert np.all(tree.lo <= tree.support_lo.min(axis=0) + 1e-12)
    assert np.all(tree.hi >= tree.support_hi.max(axis=0) - 1e-12)
    np.testing.assert_allclose(0.5 * (tree.lo + tree.hi), tree.grid_lo.min(axis=0), rtol=0,
                               atol=1e-12)
    cells = (tree.hi - tree.lo) / tree.h_fine
    np.testing.assert_allclose(2.0 ** np.round(np.log2(cells)), cells, rtol=1e-12)
    rng = np.random.default_rng(6)
    pts = tree.lo + rng.random((4000, 3)) * (tree.hi - tree.lo)
    inside = np.all((pts[:, None, :] >= tree.leaf_lo[None]) &
                    (pts[:, None, :] <= tree.leaf_hi[None]), axis=2)
    assert np.all(inside.sum(axis=1) == 1)
    np.testing.assert_array_equal(tree.locate(pts), np.argmax(inside, axis=1))


def test07_locate_finds_a_leaf_holding_the_point_even_on_faces(tree):
    rng = np.random.default_rng(7)
    pts = boundary_points(tree.volume, rng)
    pts = pts[np.all((pts >= tree.lo) & (pts <= tree.hi), axis=1)]
    leaf = tree.locate(pts)
    assert np.all((pts >= tree.leaf_lo[leaf]) & (pts <= tree.leaf_hi[leaf]))


def test08_leaf_owner_is_the_finest_grid_containing_the_leaf(tree):
    vol = tree.volume
    glo, ghi = vol.grid_boxes()
    G = len(vol.grids)
    contains = np.all((glo[None] <= tree.leaf_lo[:, None, :]) &
                      (tree.leaf_hi[:, None, :] <= ghi[None]), axis=2)
    # Finest level first, then the lowest index.
    score = np.where(contains, vol.levels[None] * G + (G - 1 - np.arange(G))[None], -1)
    want = np.where(score.max(axis=1) >= 0, G - 1 - score.max(axis=1) % G, -1)
    np.testing.assert_array_equal(tree.leaf_owner, want)
    # The same answer from the point-query twin at each leaf's centre.
    centres = 0.5 * (tree.leaf_lo + tree.leaf_hi)
    np.testing.assert_array_equal(tree.leaf_owner, finest_grid_bruteforce(vol, centres))
    assert np.any(tree.leaf_owner == -1) and np.any(tree.leaf_owner >= 0)


def assert_leaf_size_bound(tree):
    """Leaves with an owner span at most ``leaf_cells`` cells, on every axis, of the finest
    level whose support reaches into the leaf."""
    vol = tree.volume
    reach = np.all(np.minimum(tree.leaf_hi[:, None], tree.support_hi[None]) >
                   np.maximum(tree.leaf_lo[:, None], tree.support_lo[None]), axis=2)
    finest = np.where(reach, vol.levels[None], -1).max(axis=1)
    h = np.array([vol.level_spacing(level) for level in range(vol.num_levels)])
    owned = tree.leaf_owner >= 0
    assert np.all(finest[owned] >= 0)
    cells = (tree.leaf_hi - tree.leaf_lo)[owned] / h[finest[owned]]
    assert cells.max() <= tree.leaf_cells


@pytest.mark.parametrize("leaf_cells", [2, 8, 16])
def test09_leaf_size_bound_in_cells_of_the_finest_support(leaf_cells):
    for name in ("ratio2", "ratio4-2", "random0", "random1"):
        assert_leaf_size_bound(KDTree(AMRVolume.from_grids(HIERARCHIES[name]()),
                                      leaf_cells=leaf_cells))


def test10_leaf_lists_hold_the_supports_active_first(tree):
    vol = tree.volume
    support = np.all(np.minimum(tree.leaf_hi[:, None], tree.support_hi[None]) >
                     np.maximum(tree.leaf_lo[:, None], tree.support_lo[None]), axis=2)
    # Active: some leaf cell of the grid has a hat support overlapping the leaf.
    active = np.stack([hat_overlap(tree, g, vol.leaf_mask(g)).any(axis=1)
                       for g in range(len(vol.grids))], axis=1)
    assert active.any() and not active.all()
    assert np.all(support[active])
    for leaf, (listed, act) in enumerate(leaf_grid_lists(tree)):
        assert sorted(listed.tolist()) == np.flatnonzero(support[leaf]).tolist()
        assert sorted(act.tolist()) == np.flatnonzero(active[leaf]).tolist()
        assert len(set(listed.tolist())) == len(listed)
    # The per-leaf summaries of the active grids.
    levels = sum((1 << level) * active[:, vol.levels == level].any(axis=1)
                 for level in range(vol.num_levels))
    np.testing.assert_array_equal(tree.leaf_levels, levels)
    min_h = np.where(active, vol.spacings().min(axis=1)[None], np.inf).min(axis=1)
    np.testing.assert_array_equal(tree.leaf_min_h, min_h)


def test11_covered_cells_do_not_make_a_grid_active():
    # A leaf inside level-2 grid 5: the level-0 grids' supports reach it, but their cells
    # near it are all covered by level 1, so only finer grids are active there.
    grids = reference_grids()
    vol = AMRVolume.from_grids(grids)
    tree = KDTree(vol)
    leaf = tree.locate(np.array([[4.0, 3.0, 3.0]]))[0]     # inside level-2 grid 5
    listed, act = leaf_grid_lists(tree)[leaf]
    assert {0, 1, 2, 5} <= set(listed.tolist())
    assert 0 not in act and 1 not in act and 5 in act


# ---------------------------------------------------------------------- value ranges

def cells_reaching(tree, field):
    """Brute-force ranges: min and max of ``field`` over every cell, of any grid, whose open hat
    support overlaps the leaf; NaN/Inf cells left out."""
    vol = tree.volume
    lo = np.full(tree.num_leaves, np.inf)
    hi = np.full(tree.num_leaves, -np.inf)
    for g, grid in enumerate(vol.grids):
        values = grid.fields[field].ravel()
        ok = np.isfinite(values)
        reach, v = hat_overlap(tree, g)[:, ok], values[ok][None]
        lo = np.minimum(lo, np.where(reach, v, np.inf).min(axis=1, initial=np.inf))
        hi = np.maximum(hi, np.where(reach, v, -np.inf).max(axis=1, initial=-np.inf))
    no_owner = tree.leaf_owner < 0
    lo[no_owner], hi[no_owner] = np.inf, -np.inf
    return lo, hi


def test12_leaf_ranges_hold_every_cell_reaching_the_leaf(tree):
    lo, hi = tree.leaf_ranges("f")
    want_lo, want_hi = cells_reaching(tree, "f")
    assert np.all(lo <= want_lo) and np.all(hi >= want_hi)
    owned = tree.leaf_owner >= 0
    assert np.all(np.isfinite(lo[owned]) & (lo[owned] <= hi[owned]))
    assert np.all((lo[~owned] == np.inf) & (hi[~owned] == -np.inf))
    # Never looser than the listed grids' values.
    vmin, vmax = tree.volume.value_range("f")
    assert np.all(lo[owned] >= vmin) and np.all(hi[owned] <= vmax)


def test13_leaf_ranges_contain_the_cells_reaching_the_leaf_and_little_more():
    """Ranges are computed over power-of-two blocks of cells, so they may include a few cells
    beyond the window; they must contain the exact range and stay within the grids' range."""
    tree = KDTree(AMRVolume.from_grids(HIERARCHIES["ratio2"]()))
    lo, hi = tree.leaf_ranges("f")
    want_lo, want_hi = cells_reaching(tree, "f")
    has = np.isfinite(want_lo)
    assert np.all(lo[has] <= want_lo[has]) and np.all(hi[has] >= want_hi[has])
    vmin, vmax = tree.volume.value_range("f")
    assert np.all(lo[has] >= vmin) and np.all(hi[has] <= vmax)


def test14_trilinear_values_inside_a_leaf_lie_in_its_range(tree):
    """Sample points in each owned leaf; wherever a grid has all 8 cells around a point, its
    trilinear interpolation there must lie inside the leaf's range."""
    vol = tree.volume
    lo, hi = tree.leaf_ranges("f")
    rng = np.random.default_rng(13)
    owned = np.flatnonzero(tree.leaf_owner >= 0)
    leaf = np.repeat(owned, 8)
    pts = tree.leaf_lo[leaf] + rng.random((len(leaf), 3)) * (tree.leaf_hi - tree.leaf_lo)[leaf]
    checked = 0
    for g, grid in enumerate(vol.grids):
        h = np.asarray(grid.spacing)
        u = (pts - grid.lo) / h - 0.5
        base = np.floor(u).astype(int)
        ok = np.all((base >= 0) & (base + 1 < np.array(grid.shape)), axis=1)
        if not ok.any():
            continue
        frac, base = u[ok] - base[ok], base[ok]
        value = np.zeros(len(base))
        for corner in range(8):
            bits = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            idx = base + bits
            w = np.prod(np.where(bits == 1, frac, 1 - frac), axis=1)
            value += w * grid.fields["f"][idx[:, 0], idx[:, 1], idx[:, 2]]
        at = leaf[ok]
        assert np.all((lo[at] <= value + 1e-12) & (value - 1e-12 <= hi[at])), f"grid {g}"
        checked += len(value)
    # Points within half a cell of the domain's edge have no 8 cells around them in any grid.
    assert checked > len(pts) // 2


def test15_leaf_ranges_skip_missing_data_and_unowned_leaves():
    grids = reference_grids(fn=random_field(14))
    grids[0]["fields"]["f"][1, 1, 1] = np.nan
    grids[2]["fields"]["f"][:, 0, :] = np.inf           # a whole layer of a level-1 grid
    grids[5]["fields"]["f"][:] = np.nan                 # a whole level-2 grid
    tree = KDTree(AMRVolume.from_grids(grids, allow_nonfinite=True))
    lo, hi = tree.leaf_ranges("f")
    want_lo, want_hi = cells_reaching(tree, "f")
    assert np.all(lo <= want_lo) and np.all(hi >= want_hi)
    owned = tree.leaf_owner >= 0
    assert np.all(np.isfinite(lo[owned]) & np.isfinite(hi[owned]))
    assert np.all((lo[~owned] == np.inf) & (hi[~owned] == -np.inf))


@pytest.mark.parametrize("seed", range(4))
def test15b_block_extremes_equal_their_slow_twin(seed):
    """The stacked sparse tables give exactly the per-box result of the slow twin, for random
    boxes of every size (empty-of-finite ones included) in grids of several shapes."""
    vol = AMRVolume.from_grids(random_grids(seed, ratios=(2, 2), fn=random_field(seed)))
    rng = np.random.default_rng(seed)
    values = np.concatenate([g.fields["f"].ravel() for g in vol.grids])
    values[rng.random(len(values)) < 0.2] = np.nan  # missing cells are left out
    grid = rng.integers(len(vol.grids), size=400)
    shape = np.array([vol.grids[g].shape for g in grid])
    a = rng.integers(0, shape)
    b = rng.integers(0, shape)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    got = _window_min_max(vol, values, grid, lo, hi)
    want = _window_min_max_reference(vol, values, grid, lo, hi)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize("seed", range(4))
def test15b2_leaf_count_tables_equal_their_slow_twin(seed):
    """Summed-area tables of the leaf masks, stacked per grid shape, give the same box sums as
    the slow twin's tables (one grid at a time) and as summing the mask directly, for random
    boxes (empty ones included) of the partly covered grids of random hierarchies."""
    vol = AMRVolume.from_grids(random_grids(seed, ratios=((2, 4), (4, 2))[seed % 2]))
    grids = np.flatnonzero(vol.partly_covered())
    assert len(grids) > 1
    rng = np.random.default_rng(seed)
    grid = grids[rng.integers(len(grids), size=300)]
    shape = vol.shapes()[grid]
    lo = rng.integers(0, shape)
    hi = rng.integers(-1, shape)
    want = np.array([vol.leaf_mask(g)[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1].sum()
                     if np.all(b >= a) else 0 for g, a, b in zip(grid, lo, hi)])
    for tables in (leaf_count_tables, leaf_count_tables_reference):
        sat, offsets = tables(vol, grids)
        np.testing.assert_array_equal(_box_sum(sat, offsets[grid], shape, lo, hi), want)


@pytest.mark.parametrize("seed", range(3))
def test15b3_blocks_of_pairs_and_boxes_do_not_change_the_tree(seed):
    """The build, the active lists and the leaf value ranges work through (node, grid) pairs
    ``chunk`` (default CHUNK) at a time and descend boxes ``box_block`` (BOX_BLOCK) at a time;
    tiny blocks (many of them, with leaves and runs of pairs cut across blocks) give the same
    tree and ranges as the default ones."""
    vol = AMRVolume.from_grids(random_grids(seed, ratios=((2, 2), (4, 2), (2, 4))[seed],
                                            fn=random_field(seed)))
    want = KDTree(vol, leaf_cells=4)
    got = KDTree(vol, leaf_cells=4, chunk=5, box_block=3)
    assert len(got.leaf_grids) > 10 * got.chunk and len(vol.grids) > 3 * got.box_block
    for name in ("node_code", "node_split", "node_lo", "node_hi", "leaf_owner", "leaf_grids",
                 "leaf_nsupport", "leaf_nactive", "leaf_levels", "leaf_min_h", "node_ropes"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    for reconstruction in (None, "basis", "finest"):
        for a, b in zip(got.leaf_windows("f", reconstruction),
                        want.leaf_windows("f", reconstruction)):
            np.testing.assert_array_equal(a, b)
    for reconstruction in (None, "basis", "finest"):
        for a, b in zip(got.leaf_ranges("f", reconstruction), want.leaf_ranges("f", reconstruction)):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", range(4))
def test15b4_listed_pairs_equal_their_slow_twin(seed):
    """The leaves' grid lists come from the build's own (node, grid) pairs, kept in order of
    node and grid at every depth, with no second descent and no sort. They equal the slow
    twin: every leaf overlapping each grid's support, found by descending the built tree,
    sorted; and ordering the twin's pairs (active first) gives the same lists and windows."""
    vol = AMRVolume.from_grids(random_grids(seed, ratios=((2, 2), (4, 2), (2, 4), (4, 4))[seed],
                                            fn=random_field(seed)))
    tree = KDTree(vol, leaf_cells=(2, 4)[seed % 2], chunk=(7, CHUNK)[seed % 2])
    pl, pg = tree._listed_by_descent()
    assert len(pl) > 100 and tree.leaf_nactive.sum() < len(pl)     # some inactive pairs
    built_leaf = np.repeat(np.arange(tree.num_leaves), tree.leaf_nsupport)
    order = np.lexsort((tree.leaf_grids, built_leaf))
    np.testing.assert_array_equal(built_leaf[order], pl)
    np.testing.assert_array_equal(tree.leaf_grids[order], pg)
    names = ("leaf_grids", "leaf_nsupport", "leaf_nactive", "leaf_start", "leaf_levels",
             "leaf_min_h")
    built = {name: getattr(tree, name).copy() for name in names}
    field = vol.field_names[0]
    windows = [tree.leaf_windows(field, r) for r in (None, "basis")]
    tree._order_active(pl, pg)
    for name in names:
        np.testing.assert_array_equal(getattr(tree, name), built[name], err_msg=name)
    for r, want in zip((None, "basis"), windows):
        for a, b in zip(tree.leaf_windows(field, r), want):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", range(3))
def test15b5_leaf_windows_are_the_listed_pairs_each_reconstruction_reads(seed):
    """leaf_windows picks, leaf by leaf, the pairs the reconstruction reads: of an owned leaf,
    its active grids (basis) or all its listed grids (None), those whose cell window is not
    empty, with the windows of :meth:`KDTree._windows`. The slow twin walks the leaves one
    by one."""
    vol = AMRVolume.from_grids(random_grids(seed, ratios=((2, 2), (4, 2), (2, 4))[seed],
                                            fn=random_field(seed)))
    tree = KDTree(vol, leaf_cells=4)
    for reconstruction, count in (("basis", tree.leaf_nactive), (None, tree.leaf_nsupport)):
        want = []
        for leaf in np.flatnonzero(tree.leaf_owner >= 0):
            start = tree.leaf_start[leaf]
            for grid in tree.leaf_grids[start:start + count[leaf]]:
                lo, hi = (w[0] for w in tree._windows(np.array([leaf]), np.array([grid])))
                if np.all(hi >= lo):
                    want.append((leaf, grid, *lo, *hi))
        pl, pg, lo, hi = tree.leaf_windows("f", reconstruction)
        got = np.column_stack([pl, pg, lo, hi])
        assert 0 < len(got) < tree.leaf_nsupport.sum() * 1.01
        np.testing.assert_array_equal(got, np.array(want), err_msg=str(reconstruction))


def test15c_ropes_equal_their_slow_twin(tree):
    """Ropes built top-down from the parents' equal the descents of every face from the root."""
    np.testing.assert_array_equal(tree.node_ropes, tree._ropes_from_root())


@pytest.mark.parametrize("seed", range(6))
def test15d_cell_windows_equal_their_world_space_twin(seed):
    """The windows of the cells reaching each leaf, computed on the integer lattice, equal the
    world-space computation on random hierarchies (whose faces do not fall on rounding
    ties), for every (grid, leaf) pair with overlapping supports."""
    tree = KDTree(AMRVolume.from_grids(random_grids(seed)), leaf_cells=4)
    pg, pl = tree.overlapping_leaves(tree.support_lo, tree.support_hi)
    assert len(pl) > 100
    for fast, slow in zip(tree._windows(pl, pg), tree._windows_world(pl, pg)):
        np.testing.assert_array_equal(fast, slow)


@pytest.mark.parametrize("seed", range(6))
def test15e_active_pairs_equal_their_window_twin(seed):
    """A (leaf, grid) pair is active where the grid's cell window in the leaf is not empty and
    holds a leaf cell. ``_active`` tells an empty window by a box test (the grid's box grown
    by half a cell) and counts leaf cells from summed-area tables; the twin takes each
    pair's window in world coordinates and sums the grid's leaf mask over it. The random
    hierarchies have pairs whose leaf lies in the grid's support but beyond the half
    cell."""
    vol = AMRVolume.from_grids(random_grids(seed, ratios=((2, 2), (4, 2), (2, 4))[seed % 3]))
    tree = KDTree(vol, leaf_cells=(2, 4)[seed % 2])
    pl, pg = tree._listed_by_descent()
    lo, hi = tree._windows_world(pl, pg)
    empty = np.any(hi < lo, axis=1)
    want = np.array([not e and vol.leaf_mask(g)[a[0]:b[0] + 1, a[1]:b[1] + 1,
                                                 a[2]:b[2] + 1].any()
                     for e, g, a, b in zip(empty, pg, lo, hi)])
    assert empty.sum() > 10 and (~empty & ~want).sum() > 10     # both kinds of inactive pair
    np.testing.assert_array_equal(tree._active(pl, pg), want)


def test16_bad_arguments_are_refused():
    vol = AMRVolume.from_grids(reference_grids())
    with pytest.raises(AMRError, match="leaf_cells must be >= 2, got 1"):
        KDTree(vol, leaf_cells=1)
    tree = KDTree(vol)
    with pytest.raises(AMRError, match="unknown field 'g'"):
        tree.leaf_ranges("g")
    with pytest.raises(AMRError, match=r"points must be an \(N, 3\) array, got shape \(3,\)"):
        tree.finest_grid([1.0, 2.0, 3.0])


# ---------------------------------------------------------------------- random hierarchies

@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), ratios=st.sampled_from([(2, 2), (2, 4), (4, 2), (4, 4)]),
       leaf_cells=st.sampled_from([4, 8]))
def test17_random_hierarchies_keep_every_invariant(seed, ratios, leaf_cells):
    vol = AMRVolume.from_grids(random_grids(seed, ratios=ratios, fn=random_field(seed)))
    tree = KDTree(vol, leaf_cells=leaf_cells)
    pts = boundary_points(vol, np.random.default_rng(seed))
    np.testing.assert_array_equal(tree.finest_grid(pts), finest_grid_bruteforce(vol, pts))
    for a, b in zip(tree.support_grids(pts), support_grids_bruteforce(vol, pts)):
        np.testing.assert_array_equal(a, b)
    test05_every_leaf_is_inside_or_outside_each_grid_box(tree)
    test06_leaves_tile_the_tree_box(tree)
    test08_leaf_owner_is_the_finest_grid_containing_the_leaf(tree)
    assert_leaf_size_bound(tree)
    test10_leaf_lists_hold_the_supports_active_first(tree)
    test12_leaf_ranges_hold_every_cell_reaching_the_leaf(tree)


# ---------------------------------------------------------------------- scale

def test18_ten_thousand_grids_agree_with_brute_force():
    """10^4 grids (build times are the benchmark's: python -m mi_amr bench --kdtree)."""
    vol = AMRVolume.from_grids(datasets.many_grids(per_axis=20, fine=2000))
    tree = KDTree(vol)
    assert len(vol.grids) == 10_000
    rng = np.random.default_rng(16)
    pts = np.concatenate([random_points(vol, rng, n=200), rng.integers(0, 81, (200, 3)) / 2.0])
    np.testing.assert_array_equal(tree.finest_grid(pts), finest_grid_bruteforce(vol, pts))
    lo, hi = tree.leaf_ranges("f")
    owned = tree.leaf_owner >= 0
    # Values are 0 on level 0 and 1 on level 1: leaves reached by a level-1 cell span [0, 1]
    # (a level-1 grid sits inside a level-0 grid whose zeros reach the same leaves), others 0.
    assert set(zip(lo[owned], hi[owned])) == {(0.0, 0.0), (0.0, 1.0)}


# ---------------------------------------------------------------------- KDTree.check()

@pytest.mark.parametrize("seed", range(4))
def test30_check_passes_on_random_hierarchies(seed):
    """The invariant checker finds nothing wrong with trees of random valid hierarchies (all
    leaves' owners, every rope, the ranges of both reconstructions at sampled points)."""
    from conftest import random_grids

    vol = AMRVolume.from_grids(random_grids(seed, fn=lambda p: np.sin(p.sum(axis=-1))))
    tree = KDTree(vol)
    for reconstruction in ("basis", "finest"):
        done = tree.check("f", reconstruction=reconstruction, sample=512)
        assert done["owners"] == min(tree.num_leaves, 512)
        assert done["ropes"] == 6 * tree.num_nodes and done["ranges"] == 512


def test31_check_finds_a_broken_tree():
    """Each invariant, broken on purpose in a copy of a good tree, is reported."""
    import copy

    vol = datasets.sphere(8)
    good = KDTree(vol)
    good.check("f")
    breakers = {
        "tiling": lambda t: t.lattice_node_split.__setitem__(0, t.lattice_node_split[0] + 1),
        "owned by": lambda t: t.leaf_owner.__setitem__(np.flatnonzero(t.leaf_owner >= 0)[0], -1),
        "rope": lambda t: t.node_ropes.__setitem__((1, 1), 0),
        "range": lambda t: t.__setattr__("leaf_ranges", lambda *a, **k: (
            np.zeros(t.num_leaves), np.zeros(t.num_leaves))),
    }
    for what, breaker in breakers.items():
        t = copy.deepcopy(good)
        breaker(t)
        with pytest.raises(AssertionError, match=what if what != "tiling" else "child"):
            t.check("f", sample=4096)


def test32_a_tree_made_from_its_arrays_is_the_tree(reference_volume):
    """:meth:`KDTree.from_arrays` of :meth:`KDTree.arrays` (what a snapshot keeps) is the
    built tree: every attribute a build sets is in ``KDTree.STATE`` (a new one missing there
    would be lost by a snapshot), equal, and the tree passes its check. Besides, a tree holds
    its volume and the block sizes it works through (this process's, not the tree's)."""
    built = KDTree(reference_volume, leaf_cells=4)
    assert set(vars(built)) == set(KDTree.STATE) | {"volume", "chunk", "box_block"}
    again = KDTree.from_arrays(reference_volume, built.arrays())
    assert again.volume is reference_volume
    for name in KDTree.STATE:
        a, b = getattr(built, name), getattr(again, name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b or a is b, name
    again.check()
    with pytest.raises(AMRError, match="lacks"):
        KDTree.from_arrays(reference_volume, {"depth": 3})
