"""Movies (:mod:`mi_amr.workflows.movie`): frame plans checked on camera positions, a time series
rendered on a real Dask LocalCluster of 2 worker processes against the same frames rendered in
this process, skipping and ``force``, a worker killed mid-run, the MP4, and the bad inputs.
Small data, 32 x 32 frames."""

import json
import math
import os
import re
import signal
import textwrap
import threading
import time

import numpy as np
import pytest

from mi_amr import AMRError
from mi_amr.synthetic import datasets
from mi_amr.workflows.movie import spec as S

RES = (32, 32)
pytest.importorskip("drjit")


# ---------------------------------------------------------------------- plans (no rendering)

CAMERA = {"origin": [2.0, 0.0, 0.5], "target": [0.0, 0.0, 0.5], "up": [0.0, 0.0, 1.0],
          "fov": 30.0}


def test01_an_orbit_turns_about_the_target_on_the_up_axis():
    cams = S.orbit(CAMERA, 360, 8)
    for i, c in enumerate(cams):
        a = 2 * math.pi * i / 8
        np.testing.assert_allclose(c["origin"], [2 * math.cos(a), 2 * math.sin(a), 0.5],
                                   atol=1e-12)
        assert c["target"] == CAMERA["target"] and c["fov"] == 30.0
    tilted = dict(CAMERA, up=[1.0, 0.0, 0.0], origin=[0.0, 1.0, 0.5])
    np.testing.assert_allclose(S.orbit(tilted, 180, 2)[1]["origin"], [0.0, 0.0, 1.5], atol=1e-12)


def test02_keyframes_pass_through_their_values_on_a_smooth_path(tmp_path):
    """Origins follow the Catmull-Rom curve through the keyframes (hit exactly at keyframes,
    the analytic midpoint between them), scalars go linearly, and values hold outside."""
    path = tmp_path / "keys.toml"
    path.write_text(textwrap.dedent("""
        [[keyframe]]
        frame = 0
        origin = [0.0, 0.0, 0.0]
        isovalue = 0.1
        [[keyframe]]
        frame = 10
        origin = [1.0, 0.0, 0.0]
        [[keyframe]]
        frame = 20
        origin = [1.0, 1.0, 0.0]
        isovalue = 0.3
        color_range = [0.0, 2.0]
        """))
    keys = S.read_keyframes(path)
    specs = S.plan(25, camera=CAMERA, keyframes=keys)
    assert len(specs) == 25
    for f, want in ((0, [0, 0, 0]), (10, [1, 0, 0]), (20, [1, 1, 0]), (24, [1, 1, 0])):
        np.testing.assert_allclose(specs[f].camera["origin"], want, atol=1e-12)
    # Catmull-Rom between p1 = (0,0,0) and p2 = (1,0,0) (p0 = p1, p3 = (1,1,0)) at u = 1/2:
    # (p1 + p2) / 2 + (p1 + p2 - p0 - p3) / 16.
    p0, p1, p2, p3 = map(np.array, ([0, 0, 0], [0, 0, 0], [1, 0, 0], [1, 1, 0]))
    np.testing.assert_allclose(specs[5].camera["origin"],
                               (p1 + p2) / 2 + (p1 + p2 - p0 - p3) / 16, atol=1e-12)
    assert specs[5].isovalue == pytest.approx(0.15)
    assert specs[15].isovalue == pytest.approx(0.25)
    assert specs[0].color_range == (0.0, 2.0) and specs[24].camera["target"] == CAMERA["target"]


def test03_a_time_series_holds_each_step_and_sorts_naturally(tmp_path):
    for name in ("plt10", "plt9", "plt100", "plt0"):
        (tmp_path / name).write_text("x")
    files = S.expand_files(str(tmp_path / "plt*"))
    assert [os.path.basename(f) for f in files] == ["plt0", "plt9", "plt10", "plt100"]
    specs = S.plan(8, camera=CAMERA, files=files)
    assert [os.path.basename(s.file) for s in specs] == \
        ["plt0", "plt0", "plt9", "plt9", "plt10", "plt10", "plt100", "plt100"]
    assert S.sweep("log:0.01:1", 3) == pytest.approx([0.01, 0.1, 1.0])


@pytest.mark.parametrize("text,message", [
    ('{"keyframe": [{"frame": 0, "origin": [0, 0, 0], "zoom": 2}]}', "unknown key"),
    ('{"keyframe": [{"frame": 5}, {"frame": 3}]}', "must increase"),
    ('{"keyframe": [{"frame": 0, "origin": [0, 0]}]}', "'origin' needs 3"),
    ('{"keyframe": [{"origin": [0, 0, 0]}]}', "needs 'frame'"),
    ("not json", "not a valid JSON"),
])
def test04_bad_keyframe_files_are_refused(tmp_path, text, message):
    path = tmp_path / "k.json"
    path.write_text(text)
    with pytest.raises(AMRError, match=message):
        S.read_keyframes(path)


def test05_keyframes_are_appended_atomically(tmp_path):
    for suffix in (".json", ".toml"):
        path = tmp_path / f"keys{suffix}"
        S.append_keyframe(path, 0, camera=CAMERA, isovalue=0.1)
        S.append_keyframe(path, 12, camera=dict(CAMERA, fov=40.0), color_range=(0, 1))
        keys = S.read_keyframes(path)
        assert [k["frame"] for k in keys] == [0, 12] and keys[1]["fov"] == 40.0
        with pytest.raises(AMRError, match="must come after"):
            S.append_keyframe(path, 12)
        assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]


# ---------------------------------------------------------------------- rendering

SCENE = """
<scene version="3.0.0">
    <default name="filename" value="step0.npz"/>
    <integrator type="amr_iso" id="integrator">
        <string name="filename" value="$filename"/>
        <string name="field" value="f"/>
        <float name="isovalue" value="0.25"/>
        <string name="color_field" value="g"/>
        <string name="colormap" value="viridis"/>
    </integrator>
    <sensor type="perspective" id="sensor">
        <float name="fov" value="35"/>
        <transform name="to_world">
            <lookat origin="1.7, -1.0, 1.3" target="0.5, 0.5, 0.5" up="0, 0, 1"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="32"/><integer name="height" value="32"/>
            <string name="pixel_format" value="rgb"/>
        </film>
    </sensor>
    <emitter type="directional" id="light">
        <vector name="direction" value="-0.4, 0.5, -1.0"/>
        <rgb name="irradiance" value="2.5"/>
    </emitter>
</scene>
"""


def step_volume(t):
    """A sphere moving along x, coloured by a field whose range grows with the step."""
    from mi_amr import AMRVolume

    c = np.array([0.4 + 0.1 * t, 0.5, 0.5])
    vol = datasets.two_levels(lambda p, level: np.linalg.norm(p - c, axis=-1), 8)
    return AMRVolume.from_grids([{"level": g.level, "origin": g.origin, "spacing": g.spacing,
                                  "fields": {"f": g.fields["f"],
                                             "g": (1 + t) * g.fields["f"]}}
                                 for g in vol.grids])


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    folder = tmp_path_factory.mktemp("series")
    for t in range(3):
        step_volume(t).save(folder / f"step{t}.npz")
    (folder / "scene.xml").write_text(SCENE)
    return folder


def read(path):
    import imageio.v2 as imageio

    return np.asarray(imageio.imread(path))


def frames_in(folder):
    return sorted(p for p in folder.iterdir() if p.name.startswith("frame_"))


def wait_for_frames(out, count, thread=None, seconds=120):
    """Wait until ``count`` frames are in ``out`` (while ``thread``, the movie, runs); returns
    the deadline, for the waits after it."""
    deadline = time.time() + seconds
    while len(frames_in(out)) < count if out.exists() else True:
        assert time.time() < deadline, "no frames arrived"
        assert thread is None or thread.is_alive(), "the movie ended before its frames"
        time.sleep(0.05)
    return deadline


def test06_a_time_series_on_two_dask_workers_equals_the_serial_render(series, tmp_path):
    """3 files, 6 frames on a LocalCluster of 2 worker processes; the same frames rendered in
    this process, one worker; a second run skips every frame (files untouched); ``force``
    renders them again."""
    from mi_amr.workflows.movie import render_movie

    files = str(series / "step*.npz")
    serial = render_movie(series / "scene.xml", tmp_path / "serial", files=files, frames=6,
                          progress=False)
    assert len(serial.rendered) == 6 and not serial.failed
    assert [r["compiled"] for r in sorted(serial.rendered, key=lambda r: r["index"])][1:] == \
        [0] * 5, "a new time step compiled a kernel"
    farmed = render_movie(series / "scene.xml", tmp_path / "dask", files=files, frames=6,
                          workers=2, progress=False)
    assert len(farmed.rendered) == 6 and not farmed.failed
    assert len({r["pid"] for r in farmed.rendered}) == 2
    a, b = frames_in(tmp_path / "serial"), frames_in(tmp_path / "dask")
    assert [p.name for p in a] == [f"frame_{i:05d}.png" for i in range(6)] == [p.name for p in b]
    for x, y in zip(a, b):
        np.testing.assert_array_equal(read(x), read(y))
    assert not np.array_equal(read(a[0]), read(a[5]))
    stamps = [p.stat().st_mtime_ns for p in b]
    again = render_movie(series / "scene.xml", tmp_path / "dask", files=files, frames=6,
                         workers=2, progress=False)
    assert len(again.skipped) == 6 and not again.rendered
    assert [p.stat().st_mtime_ns for p in b] == stamps
    forced = render_movie(series / "scene.xml", tmp_path / "dask", files=files, frames=6,
                          force=True, progress=False)
    assert len(forced.rendered) == 6
    assert all(p.stat().st_mtime_ns > s for p, s in zip(b, stamps))


def test07_a_worker_killed_mid_run_loses_no_frame(series, tmp_path):
    """12 frames on our own LocalCluster; once two frames are written one worker process is
    killed; Dask reruns its frame elsewhere and every frame arrives, whole."""
    from dask.distributed import LocalCluster

    from mi_amr.workflows.movie import render_movie

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=50)
    out = tmp_path / "killed"
    result = {}

    def run():
        result["s"] = render_movie(series / "scene.xml", out, files=str(series / "step*.npz"),
                                   frames=12, scheduler=cluster.scheduler_address,
                                   progress=False)

    thread = threading.Thread(target=run)
    try:
        thread.start()
        wait_for_frames(out, 2)
        victim = next(iter(cluster.workers.values()))
        os.kill(victim.process.process.pid, signal.SIGKILL)
        thread.join(240)
        assert not thread.is_alive()
    finally:
        cluster.close()
    summary = result["s"]
    assert not summary.failed, summary.text()
    assert [p.name for p in frames_in(out)] == [f"frame_{i:05d}.png" for i in range(12)]
    assert all(read(p).shape == (32, 32, 4) for p in frames_in(out))   # RGBA, as render writes
    assert not [p for p in out.iterdir() if ".tmp-" in p.name]


def test08_the_mp4_has_every_frame(series, tmp_path):
    import imageio.v3 as iio

    from mi_amr.workflows.movie import render_movie

    mp4 = tmp_path / "orbit.mp4"
    render_movie(series / "scene.xml", tmp_path / "orbit", orbit=360, frames=5, mp4=mp4, fps=10,
                 progress=False)
    frames = iio.imread(mp4, plugin="pyav") if _has_pyav() else \
        np.stack(list(iio.imiter(mp4, plugin="FFMPEG")))
    assert len(frames) == 5 and frames.shape[1:3] == (32, 32)
    with pytest.raises(AMRError, match="file exists"):
        render_movie(series / "scene.xml", tmp_path / "orbit", orbit=360, frames=5, mp4=mp4,
                     progress=False)


def _has_pyav():
    import importlib.util

    return importlib.util.find_spec("av") is not None


def test09_a_corrupt_file_in_the_series_fails_its_frames_only(series, tmp_path):
    folder = tmp_path / "broken"
    folder.mkdir()
    for t in range(3):
        (folder / f"step{t}.npz").write_bytes((series / f"step{t}.npz").read_bytes())
    (folder / "step1.npz").write_bytes(b"PK\x03\x04 not really a zip")
    summary = render_movie_quiet(series / "scene.xml", tmp_path / "out",
                                 files=str(folder / "step*.npz"), frames=6)
    assert sorted(f["index"] for f in summary.failed) == [2, 3]
    assert all("step1.npz" in f["error"] or "step1.npz" in (f["file"] or "")
               for f in summary.failed)
    assert len(summary.rendered) == 4
    assert "step1.npz" in summary.text()


def render_movie_quiet(*a, **kw):
    from mi_amr.workflows.movie import render_movie

    return render_movie(*a, progress=False, **kw)


def test10_bad_inputs_give_one_clear_error(series, tmp_path):
    scene = series / "scene.xml"
    with pytest.raises(AMRError, match="matches no file"):
        render_movie_quiet(scene, tmp_path / "a", files=str(tmp_path / "nothing*.npz"))
    other = tmp_path / "other.npz"
    datasets.sphere(8).save(other)          # holds f but not g
    with pytest.raises(AMRError, match=r"other.npz: has no field\(s\) \['g'\]"):
        render_movie_quiet(scene, tmp_path / "b", files=[str(other)])
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(AMRError, match="is a file, not a folder"):
        render_movie_quiet(scene, afile, frames=1)
    with pytest.raises(AMRError, match="cannot write there"):
        render_movie_quiet(scene, "/proc/mi_amr_movie", frames=1)
    t0 = time.perf_counter()
    with pytest.raises(AMRError, match="cannot reach the Dask scheduler"):
        render_movie_quiet(scene, tmp_path / "c", frames=1, scheduler="tcp://127.0.0.1:9")
    assert time.perf_counter() - t0 < 15
    keys = tmp_path / "k.json"
    keys.write_text(json.dumps({"keyframe": [{"frame": 3}, {"frame": 1}]}))
    with pytest.raises(AMRError, match="must increase"):
        render_movie_quiet(scene, tmp_path / "d", keyframes=keys)
    assert not (tmp_path / "d").exists() or not list((tmp_path / "d").iterdir())


def test11_the_command_line(series, tmp_path):
    """``python -m mi_amr movie``: frames, the summary, and one error line for a mistake."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    run = lambda *a: subprocess.run([sys.executable, "-m", "mi_amr", "movie",  # noqa: E731
                                     str(series / "scene.xml"), *map(str, a)],
                                    capture_output=True, text=True, cwd=root, timeout=300)
    proc = run("-o", tmp_path / "m", "--files", series / "step*.npz", "--frames", "3",
               "--color-range", "series")
    assert proc.returncode == 0, proc.stderr
    assert "3 frame(s) rendered, 0 skipped" in proc.stdout
    assert len(frames_in(tmp_path / "m")) == 3
    proc = run("-o", tmp_path / "n", "--isovalues", "0.1:x")
    assert proc.returncode == 2 and proc.stderr.startswith("error: --isovalues")
    assert "Traceback" not in proc.stderr


def _http_status(port, path):
    """The HTTP status of ``GET http://127.0.0.1:port/path`` (None: nothing listens)."""
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code
    except OSError:
        return None


def test12_the_dask_cluster_of_a_movie_serves_no_pages():
    """The LocalCluster a movie starts serves no dashboard, info, JSON or metrics page, on
    8787 or anywhere, from its scheduler or its workers (issue 33: Dask's HTTP server answered
    on 127.0.0.1:8787 though the dashboard was off)."""
    from mi_amr.workflows.movie.farm import _connect

    client, cluster, _ = _connect(2, None, "llvm_ad_rgb")
    try:
        ports = [cluster.scheduler.http_server.port]
        ports += list(client.run(lambda dask_worker: dask_worker.http_server.port).values())
        assert 8787 not in ports and len(ports) == 3
        for port in ports:
            for path in ("/health", "/metrics", "/info/main/workers.html", "/json/counts.json",
                         "/status"):
                assert _http_status(port, path) in (None, 404), (port, path)
    finally:
        client.close()
        cluster.close()


# ---------------------------------------------------------------------- checks (issue 33)

BAD_KEYFRAMES = {
    "fov0": ({"frame": 0, "fov": 0}, "'fov' is the horizontal field of view"),
    "fov180": ({"frame": 0, "fov": 180}, "'fov' is the horizontal field of view"),
    "huge frame": ({"frame": 2 ** 70}, "a whole number from 0 to 4294967295"),
    "boolean frame": ({"frame": True}, "needs 'frame'"),
    "zero up": ({"frame": 0, "up": [0, 0, 0]}, "'up' must not be the zero vector"),
    "isovalue beyond float32": ({"frame": 0, "isovalue": 1e39}, "'isovalue' needs 1 finite"),
}


@pytest.mark.parametrize("args,says", [
    (["--orbit", "nan"], "--orbit: the turn in degrees must be a finite number, got nan"),
    (["--orbit", "inf"], "--orbit: the turn in degrees must be a finite number, got inf"),
    (["--orbit=-inf", "--files", "step*.npz"], "--orbit: the turn"),
    (["--frames", "0"], "--frames must be a whole number from 1 to 4294967296"),
    (["--frames", str(2 ** 32 + 1)], "--frames must be a whole number from 1 to 4294967296"),
    (["--fps", "0"], "--fps must be a whole number from 1 to 1000"),
    (["--resolution", "0", "8"], "--resolution must be two positive numbers"),
    (["--spp", "0"], "--spp must be >= 1"),
    (["--isovalues", "0:1e39"], "--isovalues: '0:1e39' needs finite numbers"),
    *[(["--keyframes", name], says) for name, (_, says) in BAD_KEYFRAMES.items()],
    (["--keyframes", "latin1"], "not a UTF-8 text file"),
])
def test13_nonsense_movie_values_are_one_line_and_render_nothing(series, tmp_path, capsys,
                                                                 monkeypatch, args, says):
    """Each is one ``error:`` line and exit status 2, before any frame (``--orbit nan`` used
    to render black frames and report success; ``inf``, a keyframe ``fov = 0``, a frame
    number beyond int64 or a Latin-1 keyframe file gave tracebacks or nonsense). A frame
    file that is no image lies in the folder: a run that got past the checks would stop on
    it (kept frames are checked before any is rendered) with another message."""
    from mi_amr.cli import main

    monkeypatch.chdir(series)
    for name, (key, _) in BAD_KEYFRAMES.items():
        (tmp_path / f"{name}.json").write_text(json.dumps({"keyframe": [key]}))
    (tmp_path / "latin1.json").write_bytes('{"keyframe": [{"frame": 0}]} \u00e9'.encode("latin-1"))
    args = [str(tmp_path / f"{a}.json") if a in BAD_KEYFRAMES or a == "latin1" else a
            for a in args]
    out = tmp_path / "out"
    out.mkdir()
    (out / "frame_00000.png").write_bytes(b"no image")
    assert main(["movie", str(series / "scene.xml"), "-o", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and says in err[0], err
    assert [p.name for p in out.iterdir()] == ["frame_00000.png"]
    assert (out / "frame_00000.png").read_bytes() == b"no image"


def test14_a_long_movie_starts_at_once_in_little_memory(series, tmp_path):
    """``frames=10**6``: the movie's plan is made without planning its frames (a lazy
    sequence; 10^8 frames used to take 1.15 GB before the first frame), and the first frames
    are rendered without planning the others first (that plan, stopping the run when its
    fifth frame is asked for, leaves the first three or four: the run takes a frame ahead to
    prepare its data file); the lazy plan gives the frames an eager one does."""
    import tracemalloc

    from mi_amr.workflows import movie

    class Stop(Exception):
        pass

    class FourFrames(S.Plan):
        def _spec(self, i):
            if i >= 4:
                raise Stop
            return super()._spec(i)

    scene = series / "scene.xml"
    tracemalloc.start()
    try:
        long = movie._plan(scene, frames=10 ** 6, files=None, orbit=360, isovalues="0.1:0.4",
                           keyframes=None, color_range=None, defines={}, resolution=None,
                           spp=None, variant="llvm_ad_rgb")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert isinstance(long, S.Plan) and len(long) == 10 ** 6
    assert peak < 20e6, f"{peak / 1e6:.0f} MB traced planning the movie"
    out = tmp_path / "long"
    with pytest.raises(Stop):
        render_movie_quiet(scene, out, specs=FourFrames(**vars(long)))
    names = [p.name for p in frames_in(out)]
    assert names == [f"frame_{i:05d}.png" for i in range(len(names))] and 3 <= len(names) <= 4
    lazy = S.plan(7, camera=CAMERA, orbit_degrees=300, isovalues="log:0.01:1")
    cams, isos = S.orbit(CAMERA, 300, 7), list(np.linspace(0.0, 1.0, 7))
    assert [s.camera for s in lazy] == cams and len(lazy) == 7 and lazy[-1].index == 6
    a, b = math.log(0.01), math.log(1.0)     # the eager sweep's numbers, bit for bit
    assert [s.isovalue for s in lazy] == [float(math.exp(a + (b - a) * u)) for u in isos]
    assert len(S.plan(10 ** 8, camera=CAMERA)) == 10 ** 8


def test15_frames_of_another_size_in_the_folder_are_refused_before_any_work(series, tmp_path):
    """Frames kept from a run at another size would be skipped, then the MP4 failed with a
    traceback and left a temporary file: now one error before rendering, and ``force``
    renders every frame again; the encoder refuses mixed sizes too."""
    from mi_amr.workflows.movie.encode import encode_mp4

    out, mp4 = tmp_path / "frames", tmp_path / "m.mp4"
    render_movie_quiet(series / "scene.xml", out, orbit=90, frames=2)          # 32 x 32
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(AMRError, match=r"frame_00000\.png is 32x32, this movie's frames are "
                                       r"16x16; pass --force"):
        render_movie_quiet(series / "scene.xml", out, orbit=90, frames=3, resolution=(16, 16),
                           mp4=mp4)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert not mp4.exists() and not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
    forced = render_movie_quiet(series / "scene.xml", out, orbit=90, frames=3,
                                resolution=(16, 16), mp4=mp4, force=True)
    assert len(forced.rendered) == 3 and mp4.exists()
    assert {read(p).shape for p in frames_in(out)} == {(16, 16, 4)}
    render_movie_quiet(series / "scene.xml", tmp_path / "big", frames=1)
    with pytest.raises(AMRError, match=r"big/frame_00000.png is 32x32, the frames before it "
                                       r"16x16"):
        encode_mp4([out / "frame_00000.png", tmp_path / "big" / "frame_00000.png"],
                   tmp_path / "mixed.mp4")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith("mixed")]


def test16_frames_are_bit_identical_between_runs_and_worker_counts(series, tmp_path):
    """An orbit with an isovalue sweep: two runs in this process and one on two Dask workers
    write the same pixels (a frame's seed is its number, every value a plain input)."""
    kw = dict(orbit=200, isovalues="0.2:0.3", frames=4)
    render_movie_quiet(series / "scene.xml", tmp_path / "a", **kw)
    render_movie_quiet(series / "scene.xml", tmp_path / "b", **kw)
    farmed = render_movie_quiet(series / "scene.xml", tmp_path / "c", workers=2, **kw)
    assert len(farmed.rendered) == 4 and not farmed.failed
    a, b, c = (frames_in(tmp_path / x) for x in "abc")
    assert len(a) == len(b) == len(c) == 4
    for x, y, z in zip(a, b, c):
        assert read(x).max() > 0
        np.testing.assert_array_equal(read(x), read(y))
        np.testing.assert_array_equal(read(x), read(z))
    assert not np.array_equal(read(a[0]), read(a[1]))


def test17_a_frame_that_cannot_be_written_is_one_line(series, tmp_path, capsys):
    """A frame the disk refuses (here a folder is in the way of each frame's name): each
    frame fails with one line naming it (it used to be a multi-line traceback per frame), the
    run exits with status 1 and no temporary file is left."""
    from pathlib import Path

    from mi_amr.cli import main

    out = tmp_path / "full"
    for i in range(2):
        (out / f"frame_{i:05d}.png" / "kept").mkdir(parents=True)
    assert main(["movie", str(series / "scene.xml"), "-o", str(out), "--frames", "2",
                 "--force"]) == 1
    text = capsys.readouterr().out.strip().splitlines()
    assert text[0].startswith("0 frame(s) rendered, 0 skipped (already there), 2 failed")
    assert len(text) == 3
    for i, line in enumerate(text[1:]):
        frame = out / f"frame_{i:05d}.png"
        assert line.startswith(f"  frame {i}: {frame}: cannot write the frame ([Errno 21] "), line
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == sorted(
        Path(f"frame_{i:05d}.png") / name for i in range(2) for name in ("", "kept"))


def test18_the_next_time_step_is_prepared_while_a_frame_renders(series, tmp_path):
    """In one process each job is told the next frame's data file where it changes; the frame
    renderer prepares that file in a background thread while its frame renders, so the next
    frame prepares nothing itself (and compiles nothing)."""
    from mi_amr.workflows.movie import farm
    from mi_amr.workflows.movie.frames import FrameRenderer
    from mi_amr.workflows.movie.spec import FrameSpec

    names = ["a", "a", "b", None, "c", "c"]
    jobs = [farm.Job(scene="s", spec=FrameSpec(index=i, file=f).as_dict(), path="p",
                     resolution=None, spp=None, defines={}, variant="v")
            for i, f in enumerate(names)]
    told = list(farm.with_next_files(iter(jobs)))
    assert [j.spec["index"] for j in told] == list(range(6))
    assert [j.next_file for j in told] == [None, "b", None, "c", None, None]

    files = [str(series / f"step{t}.npz") for t in range(3)]
    r = FrameRenderer(series / "scene.xml", resolution=RES)
    preps = r.integ.preparations
    heard, old = [], preps.report
    preps.report = lambda text: heard.append(threading.current_thread().name)
    try:
        preps.clear()
        r.render_to(FrameSpec(index=0, file=files[0]), tmp_path / "0.png", next_file=files[1])
        r.prefetch.wait()
        assert "mi_amr-prefetch" in heard, heard
        heard.clear()
        out = r.render_to(FrameSpec(index=1, file=files[1]), tmp_path / "1.png")
        assert heard == [] and out["compiled"] == 0
        assert r.prefetch.finished() == files[1]
    finally:
        preps.report = old


def test18b_a_time_series_keeps_only_the_step_shown_and_the_next(series, tmp_path):
    """A frame renderer moving on through a time series lets go of the steps it has shown
    (their memory is then reused by the next load): after three frames of three files, the
    integrator keeps the last one only, and the first is read again when asked for."""
    from mi_amr.kernels.prepared import LoadOptions
    from mi_amr.workflows.movie.frames import FrameRenderer
    from mi_amr.workflows.movie.spec import FrameSpec

    files = [str(series / f"step{t}.npz") for t in range(3)]
    r = FrameRenderer(series / "scene.xml", resolution=RES)
    preps, opt = r.integ.preparations, r.integ.opt
    heard, old = [], preps.report
    preps.report = heard.append
    try:
        preps.clear()
        for i, f in enumerate(files):
            r.render_to(FrameSpec(index=i, file=f), tmp_path / f"{i}.png",
                        next_file=files[i + 1] if i + 1 < len(files) else None)
            r.prefetch.wait()
        heard.clear()
        how = LoadOptions(opt.leaf_cells, keep_fields=opt.reconstruction != "basis")
        assert preps.prepare(files[2], opt.field, opt.color_field, m=r.integ.m,
                             how=how) is r.integ.prep
        assert heard == []
        preps.prepare(files[0], opt.field, opt.color_field, m=r.integ.m, how=how)
        assert any("read step0.npz" in line for line in heard), heard
    finally:
        preps.report = old


def test18b2_a_series_too_long_for_the_snapshot_cache_writes_no_snapshot(series, tmp_path,
                                                                         monkeypatch):
    """A time series' steps write their snapshots only where all of them fit the cache
    (``MI_AMR_CACHE_GB``): with room for one step's entry but not three, a movie of the three
    files (six frames) writes none (they would evict each other); with room for all three it
    writes all three. A single file's preparation is not affected."""
    import drjit as dr

    from mi_amr.kernels import snapshot
    from mi_amr.kernels.prepared import LoadOptions, Preparations
    from mi_amr.plugin.integrator import register
    from mi_amr.plugin.scene import use_variant
    from mi_amr.workflows.movie import render_movie

    use_variant("llvm_ad_rgb")
    files = [str(series / f"step{t}.npz") for t in range(3)]
    monkeypatch.setenv("MI_AMR_CACHE", "off")
    # A step's entry as the movie's scene (the basis blend) prepares it: without the values.
    step = Preparations().prepare(files[0], "f", "g", m=dr.llvm.ad,
                                  how=LoadOptions(keep_fields=False))
    size = snapshot._entry_bytes(step)

    def entries(cache):
        return sorted(p.name for p in cache.iterdir() if (p / "meta.json").exists()) \
            if cache.exists() else []

    for room, written in ((2.5, 0), (4.0, 3)):
        cache = tmp_path / f"cache{room}"
        monkeypatch.setenv("MI_AMR_CACHE", str(cache))
        monkeypatch.setenv("MI_AMR_CACHE_GB", repr(room * size / 1e9))
        register().clear()
        render_movie(series / "scene.xml", tmp_path / f"out{room}", files=files, frames=6,
                     resolution=RES, workers=1, progress=False)
        assert len(entries(cache)) == written, (room, entries(cache))
        assert register().series_steps == 1        # (this process's later loads as before)
    cache = tmp_path / "single"
    monkeypatch.setenv("MI_AMR_CACHE", str(cache))
    monkeypatch.setenv("MI_AMR_CACHE_GB", repr(2.5 * size / 1e9))
    Preparations().prepare(files[0], "f", "g", m=dr.llvm.ad, how=LoadOptions(keep_fields=False))
    assert len(entries(cache)) == 1


def test18c_a_series_colour_range_of_a_derived_field_is_the_fields_range(tmp_path):
    """``--color-range series`` over files holding a velocity: the speed's range taken
    straight from the velocity (no field written) and the vorticity's (derived) are the
    ranges of the fields the scene derives, over all the files."""
    from mi_amr import AMRVolume
    from mi_amr.core.derive import derive
    from mi_amr.readers import load
    from mi_amr.workflows.movie import series_color_range

    files = []
    for t in range(3):
        vol = step_volume(t)
        path = tmp_path / f"v{t}.npz"
        AMRVolume.from_grids([{"level": g.level, "origin": g.origin, "spacing": g.spacing,
                               "fields": {n: a.astype(np.float32) for n, a in (
                                   ("vx", g.fields["f"]), ("vy", g.fields["g"]),
                                   ("vz", g.fields["f"] * g.fields["g"] - t))}}
                              for g in vol.grids]).save(path)
        files.append(path)
    for colour in ("speed", "vorticity_magnitude"):
        scene = tmp_path / f"{colour}.xml"
        scene.write_text(SCENE.replace('value="f"', 'value="q_criterion"')
                         .replace('value="g"', f'value="{colour}"'))
        ranges = [derive(load(f), colour).value_range(colour) for f in files]
        want = (min(r[0] for r in ranges), max(r[1] for r in ranges))
        assert series_color_range(files, scene) == want


def test18d_a_series_colour_range_reads_mi_amr_files_as_a_stream(tmp_path, monkeypatch):
    """The range of a stored field and of the speed comes from mi_amr files read a stretch
    at a time, no volume loaded: the same numbers as the loaded fields' ranges, over files
    with and without NaN cells; a file with NaN cells that it does not allow is left out, as
    one that cannot be loaded; velocity components of different dtypes take the derivation
    (their speed rounds per grid)."""
    from mi_amr import AMRVolume
    from mi_amr.core.derive import derive
    from mi_amr.readers import load
    from mi_amr.workflows import movie

    def save(t, allow, dtypes=(np.float32, np.float32, np.float32)):
        vol = step_volume(t)
        grids = []
        for i, g in enumerate(vol.grids):
            f, h = g.fields["f"], g.fields["g"]
            comps = [(f - 0.5) * 1e-3, h, f * h - t]
            if allow and i == 1:
                comps[0] = comps[0].copy()
                comps[0].flat[3] = np.nan
            grids.append({"level": g.level, "origin": g.origin, "spacing": g.spacing,
                          "fields": {n: c.astype(d) for n, c, d in
                                     zip(("vx", "vy", "vz"), comps, dtypes)}})
        path = tmp_path / f"v{t}{'n' if allow else ''}{len(set(dtypes))}.npz"
        AMRVolume.from_grids(grids, allow_nonfinite=allow).save(path)
        return path

    files = [save(0, False), save(1, True), save(2, False)]
    mixed = save(3, False, (np.float32, np.float64, np.float32))
    refused = tmp_path / "refused.npz"      # files[1]'s NaN cell, its flag says there is none
    with np.load(files[1]) as archive:
        np.savez(refused, **{**{k: archive[k] for k in archive.files},
                             "allow_nonfinite": np.array(False)})
    want = {f: {"vx": load(f).value_range("vx"),
                "speed": derive(load(f), "speed").value_range("speed")}
            for f in files + [mixed]}
    import mi_amr.readers as readers
    monkeypatch.setattr(readers, "load", lambda *a, **k: pytest.fail("loaded a volume"))
    for name in ("vx", "speed"):
        for f in files:
            assert movie._file_range(f, name) == want[f][name], (f, name)
        with pytest.raises(AMRError, match=f"{refused}: grid 1: field 'vx' has non-finite"):
            movie._file_range(refused, name)
    scene = tmp_path / "speed.xml"
    scene.write_text(SCENE.replace('value="f"', 'value="q_criterion"')
                     .replace('value="g"', 'value="speed"'))
    ranges = [want[f]["speed"] for f in (files[0], files[2])]
    assert movie.series_color_range([files[0], refused, files[2]], scene) == \
        (min(r[0] for r in ranges), max(r[1] for r in ranges))
    monkeypatch.setattr(readers, "load", load)
    assert movie._file_range(mixed, "speed") == want[mixed]["speed"]


def test18e_a_series_colour_range_shows_its_progress(series, capsys):
    """Taking a time series' colour range reads every file before the first frame: with
    ``progress`` a bar on stderr counts the files (a long series would otherwise sit silent
    for minutes); without it, nothing is printed. The range is the same either way."""
    from mi_amr.workflows.movie import series_color_range

    files = [series / f"step{t}.npz" for t in range(3)]
    quiet = series_color_range(files, series / "scene.xml")
    assert capsys.readouterr().err == ""
    shown = series_color_range(files, series / "scene.xml", progress=True)
    err = capsys.readouterr().err
    assert "colour range" in err and "/3 " in err, err
    assert shown == quiet and quiet is not None


@pytest.mark.parametrize("dtype", ["<f8", "<f4"])
def test18f_a_plotfile_streams_its_fields_a_box_at_a_time(tmp_path, dtype, monkeypatch):
    """A time series' colour range of a plotfile is read a box at a time
    (``amrex.FabStream``), no volume loaded: a stored field's range and the speed's are those
    of the loaded (and derived) fields, in doubles and singles; a NaN in a FAB (which
    :func:`load` refuses) ends the stream with an AMRError naming the FAB and the ways to
    keep such values."""
    from amrex_writer import write_plotfile

    from mi_amr.errors import ALLOW_NONFINITE_HOW

    import mi_amr.readers as readers
    from mi_amr.core.derive import derive
    from mi_amr.readers import load
    from mi_amr.workflows import movie

    root = write_plotfile(tmp_path / f"plt{dtype[-1]}", names=("vx", "vy", "vz", "density"),
                          dtype=dtype)
    want = {"density": load(root).value_range("density"),
            "speed": derive(load(root, fields=["vx", "vy", "vz"]), "speed").value_range("speed")}
    with readers.stream_fields(root, ["vy", "density"]) as s:
        chunks = list(s.chunks())
    assert s.names == ["vy", "density"] and len(chunks) == 3      # one per box
    vol = load(root, fields=["vy", "density"])
    for i, name in enumerate(s.names):
        got = np.concatenate([c[i] for c in chunks])
        np.testing.assert_array_equal(np.sort(got), np.sort(np.concatenate(
            [g.fields[name].ravel() for g in vol.grids])))
        assert got.dtype == np.dtype(dtype).newbyteorder("=")
    monkeypatch.setattr(readers, "load", lambda *a, **k: pytest.fail("loaded a volume"))
    for name, value in want.items():
        assert movie._file_range(root, name) == value, name
    fab = root / "Level_1" / "Cell_D_00000"
    data = bytearray(fab.read_bytes())
    at = data.index(b"\n") + 1            # the first value of box 0 of level 1
    data[at:at + np.dtype(dtype).itemsize] = np.array([np.nan], dtype=dtype).tobytes()
    fab.write_bytes(bytes(data))
    with pytest.raises(AMRError, match=re.escape(str(fab)) + ": FAB 0: field 'vx' has non-fin"
                       ) as refused:
        movie._file_range(root, "speed")
    assert ALLOW_NONFINITE_HOW in str(refused.value)      # how to keep them, as load says


def test19_a_movie_whose_cluster_loses_every_worker_stops_with_one_error(series, tmp_path):
    """The movie's own LocalCluster of 2 workers; once a frame is written the cluster is
    scaled to no worker (as when every worker dies and none comes back). The movie stops with
    one AMRError after ``worker_wait`` instead of waiting for ever, and keeps the frames it
    wrote, whole."""
    from distributed import default_client

    from mi_amr.workflows.movie import render_movie

    out = tmp_path / "orphaned"
    result = {}

    def run():
        try:
            result["s"] = render_movie(series / "scene.xml", out, files=str(series / "step*.npz"),
                                       frames=400, workers=2, worker_wait=3.0, progress=False)
        except AMRError as e:
            result["error"] = str(e)

    thread = threading.Thread(target=run, daemon=True)   # (a hang must not hang pytest)
    thread.start()
    wait_for_frames(out, 1, thread)
    default_client().cluster.scale(0)
    thread.join(60)
    assert not thread.is_alive(), "the movie waited for workers that cannot come back"
    assert "every Dask worker" in result.get("error", ""), result
    assert "run the movie again" in result["error"]
    written = frames_in(out)
    assert 0 < len(written) < 400
    assert all(read(p).shape == (32, 32, 4) for p in written)
    assert not [p for p in out.iterdir() if ".tmp-" in p.name]


def test20_a_named_scheduler_without_workers_is_told_once_and_waited_for(series, tmp_path,
                                                                           capsys):
    """A cluster the user names (``scheduler``) scaled to no worker after the first frame: the
    movie says so once on stderr after ``worker_wait`` and keeps waiting; once workers are back
    every frame arrives."""
    from dask.distributed import LocalCluster

    from mi_amr.workflows.movie import render_movie

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=50)
    out = tmp_path / "queued"
    result = {}

    def run():
        result["s"] = render_movie(series / "scene.xml", out, files=str(series / "step*.npz"),
                                   frames=40, scheduler=cluster.scheduler_address,
                                   worker_wait=1.0, progress=False)

    thread = threading.Thread(target=run, daemon=True)
    try:
        thread.start()
        deadline = wait_for_frames(out, 1, thread)
        cluster.scale(0)
        while "no Dask worker" not in capsys.readouterr().err:
            assert time.time() < deadline and thread.is_alive(), "the user was not told"
            time.sleep(0.1)
        assert thread.is_alive()
        cluster.scale(1)
        thread.join(120)
        assert not thread.is_alive()
    finally:
        cluster.close()
    assert not result["s"].failed
    assert len(frames_in(out)) == 40
    assert capsys.readouterr().err.count("no Dask worker") == 0     # told once


def test21_a_result_lost_with_its_worker_is_watched_too():
    """A frame can finish, then lose its result with its worker before the client fetches it
    (the race of test19 when the cluster shrinks between the frame's file and its result): the
    fetch waits for a new worker, and with none for ``worker_wait`` it is the movie's one
    AMRError. A task's own TimeoutError is its error, not a wait; a finished frame whose fetch
    times out (its result lost mid-fetch, computed again elsewhere) is waited for."""
    from mi_amr.workflows.movie.farm import _Watch

    class NoWorkers:
        def scheduler_info(self):
            return {"workers": {}}

    class Lost:
        def __init__(self, done):
            self.finished = done
            self.status = "error" if done else "pending"

        def result(self, timeout):
            time.sleep(min(timeout, 0.02))
            raise TimeoutError("its own" if self.finished else "")

        def done(self):
            return self.finished

    class Refetched:
        """Finished (as Dask still says) but its fetch waits for the frame computed again."""
        status, waits = "finished", 2

        def result(self, timeout):
            if self.waits:
                self.waits -= 1
                raise TimeoutError("")
            return "frame"

        def done(self):
            return True

    def fetch(done):
        raised = []

        def run():
            try:
                _Watch(NoWorkers(), None, worker_wait=0.3).result(Lost(done), 5)
            except Exception as e:      # noqa: BLE001 -- what the fetch raised, checked below
                raised.append(e)

        thread = threading.Thread(target=run, daemon=True)   # (a hang must not hang pytest)
        thread.start()
        thread.join(10)
        assert not thread.is_alive(), "the fetch waited for a worker that never comes"
        return raised[0]

    assert isinstance(fetch(False), AMRError) and "every Dask worker" in str(fetch(False))
    assert isinstance(fetch(True), TimeoutError) and "its own" in str(fetch(True))
    assert _Watch(NoWorkers(), None, worker_wait=30).result(Refetched(), 5) == "frame"
