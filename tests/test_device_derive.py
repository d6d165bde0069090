"""The device derivation (mi_amr.kernels.derive: Dr.Jit kernels, whole chunks of a level)
gives the host's numbers (mi_amr.core.derive and its grid-by-grid twin) bit for bit."""

import numpy as np
import pytest

drjit = pytest.importorskip("drjit")

from test_derive import _velocity_hierarchy  # noqa: E402

import mi_amr  # noqa: E402
from mi_amr.core import derive as host_derive, gradient  # noqa: E402

NAMES = ("q_criterion", "vorticity_magnitude", "speed")


@pytest.mark.parametrize("seed,ratios,dtype,holes", [(0, (2, 2), np.float64, False),
                                                     (1, (4, 2), np.float32, False),
                                                     (2, (2, 4), np.float64, True),
                                                     (5, (2, 2), np.float32, True)])
def test01_device_fields_equal_the_grid_by_grid_twin(seed, ratios, dtype, holes):
    """Ghosts from the same level, interpolated from coarser ones (ratios 2 and 4), one-sided
    differences, grids 1 or 2 cells thick, missing data, several chunks a level: the same bits
    as the slow twin's gradient, rounded to the velocity's dtype."""
    from mi_amr.kernels import derive as device_derive

    vol = _velocity_hierarchy(seed, ratios, dtype, holes)
    slow = list(gradient.grid_gradients_reference(vol, ("vx", "vy", "vz")))
    out = device_derive.derive(vol, *NAMES, m=drjit.llvm.ad, chunk_cells=60)
    for g, h, grad in zip(vol.grids, out.grids, slow):
        np.testing.assert_array_equal(h.fields["q_criterion"],
                                      host_derive.q_criterion(grad).astype(dtype))
        np.testing.assert_array_equal(h.fields["vorticity_magnitude"],
                                      host_derive.vorticity_magnitude(grad).astype(dtype))
        assert h.fields["q_criterion"].dtype == dtype
    host = mi_amr.derive(vol, *NAMES)
    for a, b in zip(out.grids, host.grids):
        for name in NAMES:
            np.testing.assert_array_equal(a.fields[name], b.fields[name])


def test01b_cells_that_are_not_cubes_give_the_exact_gradient_of_a_linear_velocity():
    """A velocity linear in world space, on a hierarchy whose cells are stretched differently
    along x, y and z: central, one-sided and interpolated-ghost differences are all exact, so
    Q and the vorticity are the analytic ones everywhere, on the device and the host."""
    from conftest import random_grids, stretched
    from mi_amr import AMRVolume
    from mi_amr.kernels import derive as device_derive

    scale = np.array([1.0, 0.5, 2.0])
    grids = stretched(random_grids(1, ratios=(2, 4), fn=lambda p: p[..., 0]), tuple(scale))
    for g in grids:
        shape = g["fields"].pop("f").shape
        lo, h = np.asarray(g["origin"]), np.asarray(g["spacing"])
        centre = lo + (np.indices(shape).transpose(1, 2, 3, 0) + 0.5) * h
        g["fields"].update(vx=centre[..., 0] * 3.0, vy=centre[..., 1] * -2.0,
                           vz=centre[..., 2] * 0.5 + centre[..., 0])
    vol = AMRVolume.from_grids(grids)
    # grad = [[3, 0, 0], [0, -2, 0], [1, 0, 0.5]] (row: component, column: axis)
    q = -0.5 * (9.0 + 4.0 + 0.25)
    for out in (device_derive.derive(vol, "q_criterion", "vorticity_magnitude",
                                     m=drjit.llvm.ad, chunk_cells=60),
                mi_amr.derive(vol, "q_criterion", "vorticity_magnitude")):
        for g in out.grids:
            np.testing.assert_allclose(g.fields["q_criterion"], q, rtol=1e-12)
            np.testing.assert_allclose(g.fields["vorticity_magnitude"], 1.0, rtol=1e-12)


def _launches(fn):
    """``(fn(), number of Dr.Jit kernels launched while it ran)``."""
    import drjit as dr

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()                         # clear
    try:
        out = fn()
        return out, sum(1 for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test02_a_level_without_a_dense_table_is_derived_on_the_host():
    """Where a level is too sparse for the device lookup (no dense block table), the host
    derives the volume, with the same numbers: no kernel runs (one volume with dense tables
    runs several)."""
    from mi_amr.core import levels
    from mi_amr.kernels import derive as device_derive

    vol = _velocity_hierarchy(1, (2, 2), np.float32, False)
    expected = mi_amr.derive(vol, "q_criterion")
    _, dense = _launches(lambda: device_derive.derive(vol, "q_criterion", m=drjit.llvm.ad))
    vol = _velocity_hierarchy(1, (2, 2), np.float32, False)
    vol.level_caches.dense_blocks = 0           # before any level's table is made
    assert levels.level_index(vol, 0).table is None
    out, sparse = _launches(lambda: device_derive.derive(vol, "q_criterion", m=drjit.llvm.ad))
    assert dense > 0 and sparse == 0
    for a, b in zip(out.grids, expected.grids):
        np.testing.assert_array_equal(a.fields["q_criterion"], b.fields["q_criterion"])


def test03_preparing_a_volume_derives_on_its_backend():
    """PreparedVolume derives Q with the device kernels: the values it maps are the host's."""
    from mi_amr.kernels.prepared import PreparedVolume

    vol = _velocity_hierarchy(0, (2, 2), np.float32, False)
    prep = PreparedVolume(vol, "q_criterion", "speed", m=drjit.llvm.ad)
    host = mi_amr.derive(vol, "q_criterion", "speed")
    for a, b in zip(prep.volume.grids, host.grids):
        np.testing.assert_array_equal(a.fields["q_criterion"], b.fields["q_criterion"])
        np.testing.assert_array_equal(a.fields["speed"], b.fields["speed"])


def test_grid_of_each_cell_is_the_host_repeat():
    """The per-cell grid numbers made on the device (a 1 at each grid's first cell, summed)
    are NumPy's ``repeat`` of the grid numbers by their cell counts, one-cell grids and a
    chunk of one grid included."""
    import drjit as dr

    from mi_amr.kernels.derive import _grid_of_cells

    for counts in ([5], [1], [1, 1], [3, 1, 4, 1, 5, 9, 2, 6], [1000, 1, 37]):
        offsets = np.concatenate([[0], np.cumsum(counts)])
        got = _grid_of_cells(dr.llvm.ad, offsets, 11).numpy()
        np.testing.assert_array_equal(got, np.repeat(np.arange(11, 11 + len(counts)), counts))


@pytest.mark.parametrize("seed,ratios,holes", [(0, (2, 2), False), (2, (2, 4), True),
                                               (1, (4, 2), False)])
def test_device_interpolation_is_the_host_one(seed, ratios, holes):
    """The device's trilinear interpolation (each point's 8 corners blended in one kernel,
    the corners a level lacks from the coarser levels, recursively) gives
    ``levels.interpolate(..., complete=True)`` bit for bit, at points all over the domain and
    on the finest cells' centres and faces, on every level."""
    from mi_amr.core import levels
    from mi_amr.kernels import derive as device_derive

    vol = _velocity_hierarchy(seed, ratios, np.float64, holes)
    m = drjit.llvm.ad
    comps = ("vx", "vy", "vz")
    lo, hi = vol.bounds
    rng = np.random.default_rng(seed)
    h = vol.level_spacing(vol.num_levels - 1)
    lattice = lo + np.round(rng.random((300, 3)) * (hi - lo) / (h / 2)) * (h / 2)
    points = np.concatenate([lo + rng.random((700, 3)) * (hi - lo), lattice])
    with levels.fields_fixed(vol):
        tables = [device_derive._Level(vol, level, comps, m) for level in range(vol.num_levels)]
        for level in range(vol.num_levels):
            got = device_derive.interpolate(tables, level, [m.Float64(points[:, a])
                                                            for a in range(3)])
            want = levels.interpolate(vol, level, points, comps, complete=True)
            for a in range(3):
                np.testing.assert_array_equal(got[a].numpy(), want[a])
            assert np.isfinite(want).any() and (level == 0 or not np.isfinite(want).all())


@pytest.mark.parametrize("how", ["mapped", "copied", "no-buffer"])
def test_kernels_write_the_host_buffers_or_are_copied_over(how):
    """The derivation's kernels scatter into a field's host buffer, mapped (it holds the
    values before anything is copied); where the target turns out not to be that memory (a
    backend that copies it: its probes still hold their payload) or the field's levels are no
    single buffer, :func:`_settle` copies the values over."""
    import drjit as dr

    from mi_amr.core.buffers import aligned_parts
    from mi_amr.kernels import derive as device_derive

    m = drjit.llvm.ad
    sizes = [5, 300, 41]
    parts = [np.empty(n, np.float32) for n in sizes] if how == "no-buffer" else \
        aligned_parts(sizes, np.float32)
    target, record = device_derive._written(m, parts, [0, 1, 2])
    assert (record[2] is None) == (how == "no-buffer")
    if how == "copied":
        target = type(target)(record[2].copy())
    values = np.arange(sum(sizes), dtype=np.float32) * 0.5 - 7.0
    dr.scatter(target, m.Float32(values), dr.arange(m.UInt32, len(values)))
    dr.eval(target)
    dr.sync_thread()            # the LLVM backend runs the scatter asynchronously
    if how == "mapped":
        np.testing.assert_array_equal(np.concatenate(parts), values)
    device_derive._settle(m, target, record)
    np.testing.assert_array_equal(np.concatenate(parts), values)


@pytest.mark.parametrize("device", [True, False])
def test_consumed_velocity_is_freed_level_by_level_with_the_same_numbers(tmp_path, device):
    """``consume``: the levels are derived finest first and each level's velocity buffers
    (read one per level) are freed once it is done, before the next level is derived; the
    fields are the same bits as without, the result holds no velocity (host and device)."""
    import gc
    import weakref

    from mi_amr.core import levels
    from mi_amr.kernels import derive as device_derive
    from mi_amr.readers import native

    vol = _velocity_hierarchy(2, (2, 4), np.float32, True)
    vol.save(tmp_path / "v.npz")
    expected = mi_amr.derive(vol, *NAMES)
    got = native.load(tmp_path / "v.npz", level_buffers={"vx", "vy", "vz"})
    owners = [weakref.ref(levels.level_values(got, level, "vy").base)
              for level in range(got.num_levels)]
    seen = []

    def spy(volume, *args, **kwargs):
        gc.collect()
        seen.append([o() is not None for o in owners])
        return real(volume, *args, **kwargs)

    real = levels.grid_chunks
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(levels, "grid_chunks", spy)
        out = device_derive.derive(got, *NAMES, m=drjit.llvm.ad, consume=True) if device \
            else mi_amr.derive(got, *NAMES, consume=True)
    gc.collect()
    assert not any(o() for o in owners)
    # Each level's chunks were made while its own and the coarser levels' buffers lived and
    # every finer level's were gone already.
    alive = {tuple(x) for x in seen}
    top = got.num_levels - 1
    assert alive == {tuple(k <= level for k in range(top + 1)) for level in range(top + 1)}
    assert set(out.field_names) == set(NAMES)
    for a, b in zip(out.grids, expected.grids):
        for name in NAMES:
            np.testing.assert_array_equal(a.fields[name], b.fields[name])


def test_a_velocity_the_scene_shows_is_not_consumed(tmp_path):
    """Preparing a file whose scene shows a velocity component, coloured by a derived field,
    keeps that component whole (nothing is dropped), with the derived values of a plain
    derivation."""
    from mi_amr.kernels.prepared import prepare_file

    vol = _velocity_hierarchy(0, (2, 2), np.float32, False)
    vol.save(tmp_path / "v.npz")
    expected = mi_amr.derive(vol, "q_criterion")
    prep = prepare_file(tmp_path / "v.npz", "vy", "q_criterion", m=drjit.llvm.ad)
    for a, b, c in zip(prep.volume.grids, expected.grids, vol.grids):
        np.testing.assert_array_equal(a.fields["vy"], c.fields["vy"])
        np.testing.assert_array_equal(a.fields["q_criterion"], b.fields["q_criterion"])
