"""``python -m mi_amr bench --volume --quick``: the volume-mode chart's rows, files and the
convergence of the sampled methods towards ``exact``."""

import numpy as np
import pytest

pytest.importorskip("drjit")
pytest.importorskip("matplotlib")

from mi_amr.evaluation import volume_bench as vb  # noqa: E402


@pytest.fixture(scope="module")
def quick(tmp_path_factory, scene_data_ready):
    out = tmp_path_factory.mktemp("volume_bench")
    return out, vb.volume_sweep(out, quick=True, progress=False)


def test01_every_configuration_is_timed_and_scored(quick):
    _, rows = quick
    steps = len(vb.QUICK["step_scales"])
    assert len(rows) == len(vb.SCENES) * (1 + (len(vb.METHODS) - 1) * steps)
    for r in rows:
        assert r["frame_s"] > 0, r
        assert all(np.isfinite(r[k]) for k in ("rmse_ref", "rel_rmse_ref", "rmse_same")), r
        assert r["rmse_ref"] > 0, "a 1-spp frame equal to the 64-spp reference"
        if r["method"] == "exact":
            assert r["rmse_same"] == 0.0, r


def test02_smaller_steps_come_closer_to_exact(quick):
    """On the analytic sphere the sampled methods approach exact as the step shrinks."""
    _, rows = quick
    for method in ("adaptive", "uniform"):
        err = {r["step_scale"]: r["rel_rmse_same"] for r in rows
               if r["scene"] == "analytic_sphere" and r["method"] == method}
        coarse, fine = max(err), min(err)
        assert err[fine] < 0.8 * err[coarse], (method, err)


def test03_the_table_chart_and_csv_are_written_whole(quick):
    out, rows = quick
    assert sorted(p.name for p in out.iterdir()) == ["volume.csv", "volume.md",
                                                     "volume_chart.png"]
    assert (out / "volume_chart.png").stat().st_size > 10_000
    table = (out / "volume.md").read_text()
    # the sweep's rows, then the shading cut's two (exact with and without it)
    assert table.count("| analytic_sphere |") == len(rows) // 2 + 2
    cut = table[table.index("The shading cut"):]
    assert cut.count("| yes |") == cut.count("| no |") == len(vb.SCENES)
    lines = (out / "volume.csv").read_text().splitlines()
    assert lines[0] == ",".join(vb.COLUMNS) and len(lines) == len(rows) + 1


def test04_a_results_folder_that_is_a_file_is_refused_before_any_work(tmp_path, capsys):
    from mi_amr.cli import main

    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    assert main(["bench", "--volume", "--quick", "--out", str(afile)]) == 2
    assert f"--out {afile} is a file, not a folder" in capsys.readouterr().err
    assert afile.read_text() == "mine"
