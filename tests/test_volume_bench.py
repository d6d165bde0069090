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


def test05_the_speed_table_times_every_scene_beside_surface_mode_and_yt(tmp_path,
                                                                         scene_data_ready):
    """``bench --volume --speed --quick``: every scene timed at the quick size, each frame
    related to surface mode's and the one band's, yt beside the three bands (when installed),
    both files written."""
    import json

    from mi_amr.evaluation import volume_speed_bench as vs

    rows = vs.volume_speed(tmp_path, quick=True, progress=False)
    ours = [r for r in rows if r["renderer"] == "mi_amr"]
    assert [r["scene"] for r in ours] == [row[0] for row in vs.SCENES]
    for r in ours:
        assert r["frame_s"] > 0 and r["first_s"] > 0, r
        assert r["x_surface"] == pytest.approx(r["frame_s"] / ours[0]["frame_s"])
        assert r["x_one_band"] == pytest.approx(r["frame_s"] / ours[1]["frame_s"])
    yt_rows = [r for r in rows if r["renderer"] == "yt"]
    assert [r["scene"] for r in yt_rows] == list(vs.QUICK["yt_scenes"])
    try:
        import yt  # noqa: F401
    except ImportError:
        assert all("skipped" in r for r in yt_rows)
    else:
        shells = next(r for r in ours if r["scene"] == "3 bands")
        for r in yt_rows:
            assert r["frame_s"] > 0 and r["opaque_pixels"] > 0, r     # yt drew the bands
            assert r["mi_amr_over_yt"] == pytest.approx(shells["frame_s"] / r["frame_s"])
    table = (tmp_path / "volume_speed.md").read_text()
    assert table.count("| mi_amr |") == len(ours) and table.count("| yt |") == len(yt_rows)
    assert json.loads((tmp_path / "volume_speed.json").read_text())[0]["scene"] == "surface mode"


def test06_speed_or_shadows_without_volume_is_a_cli_error(tmp_path, capsys):
    from mi_amr.cli import main

    assert main(["bench", "--speed", "--out", str(tmp_path)]) == 2
    assert "--volume" in capsys.readouterr().err
    assert main(["bench", "--volume", "--speed", "--shadows", "--out", str(tmp_path)]) == 2
    assert "pick one" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
