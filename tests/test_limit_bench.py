"""``bench --limit``'s parts on tiny images: the translucent-against-opaque timing runs all five
scenes (and leaves the fast paths on), and the tables show every measured column. Speed itself
is the benchmark's business, not a test's."""

import math

import pytest

pytest.importorskip("mitsuba")

from mi_amr.evaluation import limit_bench  # noqa: E402


def test01_translucent_against_opaque_times_eight_scenes(scene_data_ready, tmp_path):
    row = limit_bench.translucent_against_opaque(frames=1, size=32, spp=1, out_dir=tmp_path)
    for key in ("opaque_s", "translucent_s", "stochastic_s", "translucent_slow_s", "ratio",
                "ratio_slow", "ratio_stochastic", "opaque_unshadowed_s",
                "translucent_unshadowed_s", "stochastic_unshadowed_s", "ratio_unshadowed",
                "ratio_stochastic_unshadowed", "translucent_mse", "stochastic_mse",
                "one_shadow_s", "ratio_one_shadow", "one_shadow_mse"):
        assert math.isfinite(row[key]) and row[key] > 0, key
    assert row["ratio"] == pytest.approx(row["translucent_s"] / row["opaque_s"])
    assert row["ratio_stochastic"] == pytest.approx(row["stochastic_s"] / row["opaque_s"])
    assert row["ratio_unshadowed"] == pytest.approx(row["translucent_unshadowed_s"] /
                                                    row["opaque_unshadowed_s"])
    # One layer a sample is noisier than all of them at the same samples per pixel.
    assert row["stochastic_mse"] > row["translucent_mse"]
    table = limit_bench._layers_table(row)
    for key in ("translucent_s", "stochastic_s", "one_shadow_s", "translucent_unshadowed_s",
                "stochastic_unshadowed_s"):
        assert f"{row[key]:.3f}" in table, key
    assert f"{row['ratio_slow']:.1f}x" in table and f"{row['stochastic_mse']:.2e}" in table
    # The reference and a frame of each mode, side by side.
    import mitsuba as mi
    import numpy as np

    strip = np.array(mi.Bitmap(str(tmp_path / "translucent_modes.png")))
    assert strip.shape[:2] == (32, 4 * 32)


def test02_the_frame_table_shows_the_time_without_shadow_rays():
    frames = [{"size": 256, "mi_amr_s": 0.5, "mesh_s": 0.1, "ratio": 5.0, "no_shadows_s": 0.3,
               "triangles": 1000}]
    loads = [{"file": "a.npz", "cells": 10, "raw_s": 0.01, "load_s": 1.0, "ratio": 100.0,
              "steps": {"read": 0.1, "derive": 0.5, "tree": 0.2, "device": 0.1, "ranges": 0.1},
              "snapshot_s": 0.05, "snapshot_ratio": 5.0}]
    table = limit_bench._table(frames, loads)
    assert "| 256x256 | 0.500 | 0.100 | 5.0x | 0.300 |" in table
    assert "| a.npz | 10 | 0.010 | 1.00 | 100x |" in table
    assert "| 0.050 | 5.0x |" in table


def test03_the_load_rows_time_a_snapshot_read_back_and_leave_the_setting_alone(tmp_path,
                                                                              variant):
    """A first load and a read back from a snapshot in a temporary folder; the process's own
    snapshot setting (off in the tests) is as it was afterwards."""
    import os

    from mi_amr.kernels import snapshot
    from mi_amr.synthetic import datasets

    path = tmp_path / "wake.npz"
    vol = datasets.sphere_wake("small", progress=False)
    vol.select_fields(["vx", "vy", "vz"]).save(path)
    (row,) = limit_bench.load_against_read([path])
    assert row["cells"] == vol.num_cells
    for key in ("raw_s", "load_s", "snapshot_write_s", "snapshot_s"):
        assert math.isfinite(row[key]) and row[key] > 0, key
    assert row["snapshot_ratio"] == pytest.approx(row["snapshot_s"] / row["raw_s"])
    assert os.environ["MI_AMR_CACHE"] == "off"


def test04_the_scaling_table_shows_the_peak_memory_of_each_load(tmp_path):
    """The peak resident memory grows when a load allocates and is measured afresh after a
    reset, the resident memory now falls when it frees; the table shows the peak and the
    bytes a cell above the load's start, or a dash where they could not be measured."""
    import sys

    import numpy as np

    from mi_amr.evaluation import bench

    if not sys.platform.startswith("linux"):
        assert bench.peak_rss_gb() is None
        return
    assert bench.reset_peak_rss()
    before = bench.peak_rss_gb()
    block = np.ones(2 ** 28 // 8)              # 256 MiB, written
    grown = bench.peak_rss_gb()
    assert grown >= before + 0.2
    now = bench.rss_gb()
    assert grown - 0.05 <= now <= grown + 0.05      # the block is resident now
    del block
    assert bench.rss_gb() < now - 0.2
    assert bench.reset_peak_rss() and bench.peak_rss_gb() < grown
    rows = [{"what": "cells", "value": "10 (tiny)", "resolution": 64, "load_s": 0.5,
             "peak_gb": 1.234, "frame_s": 0.1, "per_cell": 21.04},
            {"what": "cells", "value": "20 (tiny)", "resolution": 64, "load_s": 0.6,
             "peak_gb": None, "frame_s": 0.2, "per_cell": None}]
    bench._scaling_table(tmp_path, rows)
    table = (tmp_path / "scaling.md").read_text()
    assert "peak resident while loading (GB)" in table and "(bytes a cell)" in table
    assert "| 0.5 | 1.23 | 21.0 | 0.10 |" in table and "| 0.6 | - | - | 0.20 |" in table
