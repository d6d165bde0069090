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
        assert r["walked"] > 0, r
    # Faint shells let a ray through more pieces than the same shells made opaque.
    walked = {r["scene"]: r["walked"] for r in ours}
    assert walked["3 bands"] > walked["3 bands, each at 1 band's peak"]
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


def test07_the_shadow_bench_times_and_scores_every_design(tmp_path, scene_data_ready):
    """``bench --volume --shadows`` (tiny): a speed row per scene and design, and an accuracy
    row per scene and design, ``exact`` against itself at the same samples being 0."""
    from mi_amr.evaluation import shadow_bench as sb

    rows = sb.shadow_sweep(tmp_path, res=16, frames=1, accuracy=(16, 2, 4), progress=False)
    speed = [r for r in rows if "frame_s" in r]
    scored = [r for r in rows if "spp" in r]
    assert [(r["scene"], r["shadows"]) for r in speed[1:]] == \
        [(s, d) for s in sb.SCENES for d in sb.DESIGNS]
    assert all(r["frame_s"] > 0 for r in speed)
    for r in speed:
        assert ("rel_rmse_exact" in r) == (r["shadows"] in ("cache", "corrected")), r
        assert ("build_s" in r) == (r["shadows"] in ("cache", "corrected")), r
    assert [(r["scene"], r["shadows"]) for r in scored] == \
        [(s, d) for s in sb.SCENES for d in ("exact", "cache", "corrected")]
    for r in scored:
        assert np.isfinite(r["rel_rmse_reference"]) and r["rel_rmse_reference"] > 0, r
        assert (r["rel_rmse_same_seed"] == 0.0) == (r["shadows"] == "exact"), r
    table = (tmp_path / "shadows.md").read_text()
    assert table.count("| sphere_wake_shells |") == len(sb.DESIGNS) + 3
    assert (tmp_path / "shadows.csv").read_text().count("\n") == len(rows) + 1


def test08_bench_viewer_takes_one_scene(tmp_path, capsys):
    """``bench --viewer --scene``: a scene of ``scenes_xml/`` by name (with or without
    ``.xml``) or a file; anything else, or two, is one CLI error before a browser starts."""
    from mi_amr import cli
    from mi_amr.workflows import project

    shells = project.scenes_dir() / "sphere_wake_shells.xml"
    assert cli._viewer_scene(None) is None
    assert cli._viewer_scene(["sphere_wake_shells"]) == shells
    assert cli._viewer_scene(["sphere_wake_shells.xml"]) == shells
    assert cli._viewer_scene([str(shells)]) == shells
    for scenes, message in ((["no_such_scene"], "'no_such_scene' is neither"),
                            (["sphere_wake", "sphere_wake_shells"], "give one --scene")):
        args = ["bench", "--viewer", "--out", str(tmp_path)]
        for s in scenes:
            args += ["--scene", s]
        assert cli.main(args) == 2
        assert message in capsys.readouterr().err
