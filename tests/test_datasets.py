"""Synthetic datasets: the sphere wake is refined where the flow turns, nested, deterministic;
the analytic fields hold their closed forms on two levels whose boundary x = 0.5 cuts the
isosurface; both are written and refused like any other volume."""

from pathlib import Path

import numpy as np
import pytest

import mi_amr
from mi_amr import AMRError
from mi_amr.synthetic import datasets
from mi_amr.synthetic import flow
from mi_amr.cli import main


@pytest.fixture(scope="module")
def wake():
    return datasets.sphere_wake("small", progress=False)


def centres_of(g):
    return np.stack(np.meshgrid(*g.cell_centers(), indexing="ij"), axis=-1)


# ---------------------------------------------------------------------- the sphere wake

def test01_wake_has_at_least_three_levels_of_ratio_2(wake):
    assert wake.num_levels >= 3
    assert set(wake.ratios) == {2}
    assert wake.field_names == ("vx", "vy", "vz")
    assert all(g.fields["vx"].dtype == np.float32 for g in wake.grids)
    np.testing.assert_allclose(wake.bounds[0], flow.DOMAIN_LO)
    np.testing.assert_allclose(wake.bounds[1], flow.DOMAIN_HI)
    assert all(np.sum(wake.levels == level) >= 1 for level in range(wake.num_levels))


def test02_wake_fine_grids_nest_in_the_coarser_level(wake):
    """Every cell of the level above that a fine grid covers is inside some grid of that level
    (checked at the coarse cells' centres)."""
    lo, hi = wake.grid_boxes()
    for i, g in enumerate(wake.grids):
        if g.level == 0:
            continue
        coarse_h = wake.level_spacing(g.level - 1)
        axes = [np.arange(g.lo[a] + coarse_h[a] / 2, g.hi[a], coarse_h[a]) for a in range(3)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        parents = np.flatnonzero(wake.levels == g.level - 1)
        inside = np.zeros(len(centres), dtype=bool)
        for p in parents:
            inside |= np.all((centres > lo[p]) & (centres < hi[p]), axis=1)
        assert inside.all(), f"grid {i} (level {g.level}) is not nested"


def test03_wake_is_refined_where_the_vorticity_is(wake):
    derived = mi_amr.derive(wake, "vorticity_magnitude")
    for level in range(wake.num_levels - 1):
        covered, uncovered = [], []
        for i in np.flatnonzero(wake.levels == level):
            w = derived.grids[i].fields["vorticity_magnitude"]
            leaf = wake.leaf_mask(i)
            covered.append(w[~leaf])
            uncovered.append(w[leaf])
        covered, uncovered = np.concatenate(covered), np.concatenate(uncovered)
        assert covered.size and uncovered.size
        assert covered.mean() > 10 * uncovered.mean(), f"level {level}"


def test04_wake_far_field_upstream_is_not_refined(wake):
    lo, _ = wake.grid_boxes()
    assert np.all(lo[wake.levels > 0, 0] >= -1.5)
    # Far upstream the air streams at the free-stream speed along +x (the ball's dipole field
    # falls off as (R / r)^3, under 10 % there).
    g = wake.grids[0]
    c = centres_of(g)
    up = c[..., 0] < -1.5
    assert up.any()
    np.testing.assert_allclose(g.fields["vx"][up], flow.FREESTREAM, rtol=0.1)
    assert np.abs(g.fields["vy"][up]).max() < 0.1 * flow.FREESTREAM
    assert np.abs(g.fields["vz"][up]).max() < 0.1 * flow.FREESTREAM


def test05_wake_is_still_inside_the_ball(wake):
    checked = 0
    for g in wake.grids:
        inside = np.linalg.norm(centres_of(g), axis=-1) < flow.BALL_RADIUS
        for n in wake.field_names:
            assert np.all(g.fields[n][inside] == 0.0)
        checked += int(inside.sum())
    assert checked > 0
    # Just outside the ball's boundary layer the air moves.
    g = wake.grids[-1]
    r = np.linalg.norm(centres_of(g), axis=-1)
    near = (r > flow.BALL_RADIUS + 3 * flow.BOUNDARY_LAYER)
    speed = np.sqrt(sum(g.fields[n].astype(np.float64) ** 2 for n in wake.field_names))
    assert np.all(speed[near] > 0)


def test06_wake_is_deterministic_for_a_seed_and_differs_across_seeds(wake):
    again = datasets.sphere_wake("small", seed=0, progress=False)
    assert len(again.grids) == len(wake.grids)
    for g, h in zip(wake.grids, again.grids):
        assert (g.level, g.origin, g.shape) == (h.level, h.origin, h.shape)
        for n in wake.field_names:
            np.testing.assert_array_equal(g.fields[n], h.fields[n])
    # Level 0 is one grid for every seed; the seed moves the vortices, so its values differ.
    other = datasets.sphere_wake("small", seed=1, progress=False)
    assert other.grids[0].shape == wake.grids[0].shape
    assert not np.array_equal(other.grids[0].fields["vx"], wake.grids[0].fields["vx"])


def test06b_another_seeds_flow_on_a_wakes_grids_keeps_its_grids(wake):
    """``sphere_wake_on``: the grids of the wake given, the flow of the seed asked; its own
    seed gives back the wake's values bit for bit, another seed other values (the flow of that
    seed at the same cell centres)."""
    same = datasets.sphere_wake_on(wake, 0)
    assert same.same_hierarchy(wake)
    for g, h in zip(wake.grids, same.grids):
        for n in ("vx", "vy", "vz"):
            np.testing.assert_array_equal(h.fields[n], g.fields[n])
    other = datasets.sphere_wake_on(wake, 1)
    assert other.same_hierarchy(wake)
    g = other.grids[-1]
    want = flow.SphereWakeFlow(1).velocity(centres_of(g).reshape(-1, 3)).astype(np.float32)
    np.testing.assert_array_equal(g.fields["vz"].ravel(), want[:, 2])
    assert not np.array_equal(g.fields["vx"], wake.grids[-1].fields["vx"])


def test07_unknown_wake_size_is_refused():
    with pytest.raises(AMRError, match=r"size must be one of \['small', 'default', 'large', "
                       r"'xlarge', 'xxlarge'\], got 'huge'"):
        datasets.sphere_wake("huge", progress=False)


# ---------------------------------------------------------------------- analytic fields

@pytest.mark.parametrize("name", sorted(datasets.ANALYTIC))
def test08_analytic_datasets_have_two_levels_split_at_x_half(name):
    vol = datasets.ANALYTIC[name]()
    assert vol.num_levels == 2 and vol.ratios == (2,)
    lo, hi = vol.grid_boxes()
    np.testing.assert_array_equal(lo, [[0, 0, 0], [0.5, 0, 0]])
    np.testing.assert_array_equal(hi, [[1, 1, 1], [1, 1, 1]])
    np.testing.assert_array_equal(vol.level_spacing(0), [1 / 16] * 3)
    # Level-0 leaf cells are exactly those with x < 0.5.
    x = centres_of(vol.grids[0])[..., 0]
    np.testing.assert_array_equal(vol.leaf_mask(0), x < 0.5)


@pytest.mark.parametrize("name", ["sphere", "torus", "ramp"])
def test09_level_boundary_cuts_the_isosurface(name):
    """Cells on both sides of the iso value sit next to x = 0.5 on both levels: the last leaf
    column of level 0 and the first column of level 1."""
    vol = datasets.ANALYTIC[name]()
    iso = datasets.ISOVALUES[name]
    for column in (vol.grids[0].fields["f"][7], vol.grids[1].fields["f"][0]):
        assert (column < iso).any() and (column > iso).any()


def test10_analytic_fields_hold_their_closed_forms():
    for g in datasets.sphere().grids:
        np.testing.assert_allclose(g.fields["f"], np.linalg.norm(centres_of(g) - 0.5, axis=-1),
                                   rtol=0, atol=1e-15)
    for g in datasets.ramp().grids:
        np.testing.assert_allclose(g.fields["f"], (centres_of(g) - 0.5) @ datasets.RAMP_NORMAL,
                                   rtol=0, atol=1e-15)
    # Torus: the distance to a circle of radius 0.27 about an axis tilted by 0.5 rad in the x-z
    # plane through the cube's centre. Brute force over n points of the circle: the nearest
    # circle point is within s = pi * 0.27 / n (half a sample spacing) of a sample, so the
    # sampled distance exceeds the true one by at most s.
    n = 2000
    axis = np.array([np.sin(0.5), 0.0, np.cos(0.5)])
    u = np.array([0.0, 1.0, 0.0])
    v = np.cross(axis, u)
    theta = np.linspace(0, 2 * np.pi, n, endpoint=False)
    circle = 0.5 + 0.27 * (np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v)
    g = datasets.torus().grids[0]
    c = centres_of(g).reshape(-1, 3)
    sampled = np.sqrt(((c[:, None, :] - circle[None]) ** 2).sum(axis=-1)).min(axis=1)
    excess = sampled - g.fields["f"].ravel()
    assert excess.min() > -1e-12 and excess.max() <= np.pi * 0.27 / n


def test11_spike_has_exactly_one_nonzero_cell_next_to_the_level_boundary():
    vol = datasets.spike()
    assert not vol.grids[0].fields["f"].any()
    fine = vol.grids[1]
    nonzero = np.argwhere(fine.fields["f"] != 0)
    assert nonzero.tolist() == [[datasets.SPIKE_CELL[0] - 16, *datasets.SPIKE_CELL[1:]]]
    assert fine.fields["f"][tuple(nonzero[0])] == 1.0 > datasets.ISOVALUES["spike"]
    # SPIKE_CELL counts level-1 cells from the cube's corner; its centre is 1.5 cells from x=0.5.
    centre = (np.array(datasets.SPIKE_CELL) + 0.5) / 32
    np.testing.assert_allclose(centres_of(fine)[tuple(nonzero[0])], centre, rtol=0, atol=1e-15)
    assert 0.5 < centre[0] < 0.5 + 2 / 32


# ---------------------------------------------------------------------- writing datasets

def test12_make_writes_a_loadable_file_and_refuses_to_overwrite(tmp_path):
    path = tmp_path / "sphere.npz"
    assert datasets.make("sphere", path, progress=False) == [path]
    vol = mi_amr.load(path)
    want = datasets.sphere()
    for g, h in zip(vol.grids, want.grids):
        np.testing.assert_array_equal(g.fields["f"], h.fields["f"])
    before = path.read_bytes()
    with pytest.raises(AMRError, match="file exists"):
        datasets.make("ramp", path, progress=False)
    assert path.read_bytes() == before
    datasets.make("ramp", path, overwrite=True, progress=False)
    assert mi_amr.load(path).value_range("f") == datasets.ramp().value_range("f")
    with pytest.raises(AMRError, match=r"unknown dataset 'cube'; available: \['sphere_wake'"):
        datasets.make("cube", tmp_path / "cube.npz")


def test13_every_analytic_dataset_can_be_made(tmp_path):
    for name in datasets.ANALYTIC:
        datasets.make(name, tmp_path / f"{name}.npz", progress=False)
        assert mi_amr.load(tmp_path / f"{name}.npz").num_levels == 2


def test14_cli_dataset_command(tmp_path, capsys):
    path = tmp_path / "s.npz"
    assert main(["dataset", "sphere", "-o", str(path)]) == 0
    assert capsys.readouterr().out.startswith(f"wrote {path} in ")
    assert mi_amr.load(path).num_cells == datasets.sphere().num_cells
    assert main(["dataset", "sphere", "-o", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"error: {path}: file exists; pass overwrite=True (--force on "
                                f"the command line) to replace it"]
    assert main(["dataset", "torus", "-o", str(path), "--force"]) == 0
    capsys.readouterr()
    np.testing.assert_array_equal(mi_amr.load(path).grids[1].fields["f"],
                                  datasets.torus().grids[1].fields["f"])


# ---------------------------------------------------------------------- output paths

def output_cases(tmp_path):
    """``(output path, extra arguments, expected message)`` for paths that cannot be written."""
    tmp_path.mkdir(exist_ok=True)
    afile = tmp_path / "afile.txt"
    afile.write_text("a file, not a folder")
    folder = tmp_path / "folder.npz"
    folder.mkdir()
    return [
        (afile / "out.npz", [], f"{afile / 'out.npz'}: {afile} is a file, not a folder"),
        (afile / "sub" / "out.npz", [], f"{afile / 'sub' / 'out.npz'}: {afile} is a file, "
                                        f"not a folder"),
        (Path("/proc/x.npz"), [], "/proc/x.npz: cannot write in folder /proc"),
        (folder, ["--force"], f"{folder}: is a folder; give the name of a file to write"),
        (tmp_path / "missing" / "x.npz", [], f"{tmp_path / 'missing' / 'x.npz'}: folder "
                                             f"{tmp_path / 'missing'} does not exist"),
        (tmp_path / "x.png", [], f"{tmp_path / 'x.png'}: the output must end in .npz"),
    ]


def test15_dataset_output_paths_are_checked_before_the_work(tmp_path, capsys):
    """Each bad output path is one ``error:`` line, before the dataset is built (building
    sphere_wake shows its progress bar on stderr: there is none), and nothing is written."""
    for name in ("sphere", "sphere_wake"):
        work = tmp_path / name
        for path, extra, message in output_cases(work):
            before = sorted(work.rglob("*"))
            assert main(["dataset", name, "-o", str(path), "--size", "small", *extra]) == 2, \
                path
            captured = capsys.readouterr()
            assert captured.err.splitlines()[0].startswith(f"error: {message}"), captured.err
            assert len(captured.err.splitlines()) == 1, captured.err
            assert sorted(work.rglob("*")) == before


def test16_dataset_to_a_png_name_is_refused(tmp_path):
    with pytest.raises(AMRError, match=r"x\.png: the output must end in \.npz"):
        datasets.make("sphere", tmp_path / "x.png", progress=False)
    assert list(tmp_path.iterdir()) == []
    # Upper case is the same extension.
    datasets.make("sphere", tmp_path / "X.NPZ", progress=False)
    assert mi_amr.load(tmp_path / "X.NPZ").num_levels == 2


def test17_ball_mesh_is_written_atomically(tmp_path, monkeypatch):
    """A failed mesh export leaves an existing ball.ply as it was, and no temporary file."""
    import trimesh

    path = tmp_path / "ball.ply"
    datasets.write_ball_mesh(path, subdivisions=1)
    before = path.read_bytes()

    def broken(self, file_obj=None, file_type=None, **kw):
        Path(file_obj).write_bytes(b"ply\nhalf a mesh")
        raise OSError("disk full")

    monkeypatch.setattr(trimesh.Trimesh, "export", broken)
    with pytest.raises(OSError, match="disk full"):
        datasets.write_ball_mesh(path, subdivisions=1)
    assert [p.name for p in tmp_path.iterdir()] == ["ball.ply"]
    assert path.read_bytes() == before


def test18_dataset_keeps_an_existing_ball_mesh_without_force(tmp_path, capsys):
    """``dataset sphere_wake`` writes ``ball.ply`` beside its output: an existing one (another
    run's, or the user's) is kept, with one ``error:`` line before any work, unless --force."""
    ball = tmp_path / "ball.ply"
    ball.write_bytes(b"the user's mesh")
    out = tmp_path / "wake.npz"
    assert main(["dataset", "sphere_wake", "-o", str(out), "--size", "small"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [f"error: {ball}: file exists; pass overwrite=True (--force on the command "
                   f"line) to replace it"]
    assert ball.read_bytes() == b"the user's mesh" and not out.exists()
    assert main(["dataset", "sphere_wake", "-o", str(out), "--size", "small", "--force"]) == 0
    capsys.readouterr()
    assert ball.read_bytes().startswith(b"ply") and out.exists()
