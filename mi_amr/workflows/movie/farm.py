"""Farming a movie's frames out: in this process (one worker), on a Dask ``LocalCluster`` of
worker processes, or on an existing Dask cluster by its scheduler's address (dask-jobqueue on
SLURM or PBS, Kubernetes, ``dask scheduler`` by hand).

Each frame is one task. A task runs :func:`render_task` on a worker: the worker keeps one
:class:`~mi_amr.workflows.movie.frames.FrameRenderer` per scene (Mitsuba plugins are registered
per process, by :class:`MiAmrSetup` when a worker starts), and the loaded volumes of recent
time steps, and sends back the frame's path and timings, never the pixels. A frame whose worker
dies is retried elsewhere; since frames are written atomically, no half-written frame is left.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import sys
import time
import traceback
from dataclasses import dataclass, field

from mi_amr.errors import AMRError
from mi_amr.workflows.movie.output import frame_path
from mi_amr.workflows.movie.spec import FrameSpec

CONNECT_TIMEOUT = "10s"
RETRIES = 2
QUEUED = 4          # frames submitted ahead per worker
WORKER_WAIT = 120.0  # seconds a cluster may have no worker, with frames left, before it is told
POLL = 0.05          # seconds between looks while no frame finishes (a local read)
RESULT_WAIT = 1.0    # seconds between looks while a finished frame's result is fetched


@dataclass
class Job:
    """What a worker needs to render one frame (plain values: it is pickled to the worker)."""

    scene: str
    spec: dict
    path: str
    resolution: tuple | None
    spp: int | None
    defines: dict
    variant: str
    next_file: str | None = None    # the next frame's data file, prepared while this renders
    series: int = 1                 # the movie's data files (snapshots: Preparations.series_steps)


@dataclass
class Summary:
    """How a run went: frames rendered (with their timings), skipped and failed."""

    rendered: list = field(default_factory=list)
    skipped: list = field(default_factory=list)
    failed: list = field(default_factory=list)
    seconds: float = 0.0

    def text(self) -> str:
        lines = [f"{len(self.rendered)} frame(s) rendered, {len(self.skipped)} skipped (already "
                 f"there), {len(self.failed)} failed, in {self.seconds:.1f} s"]
        lines += [f"  frame {f['index']}" + (f" ({f['file']})" if f.get("file") else "") +
                  f": {f['error']}" for f in sorted(self.failed, key=lambda f: f["index"])]
        return "\n".join(lines)


class Renderers:
    """The frame renderer of the scene this process renders: one scene at a time (its
    volumes are large), made when a job of another scene, size, samples, defines or variant
    comes. A run in this process holds one; on Dask each worker's :class:`MiAmrSetup` does."""

    def __init__(self):
        self._key, self._renderer = None, None

    def get(self, job: Job):
        from mi_amr.workflows.movie.frames import FrameRenderer

        key = (job.scene, job.resolution, job.spp, tuple(sorted(job.defines.items())),
               job.variant)
        if key != self._key:
            self._key, self._renderer = None, None      # the old scene goes first
            self._renderer = FrameRenderer(job.scene, resolution=job.resolution, spp=job.spp,
                                           defines=job.defines, variant=job.variant,
                                           series=job.series)
            self._key = key
        return self._renderer


def _worker_renderers() -> Renderers:
    """The renderers of the Dask worker this task runs on (its :class:`MiAmrSetup`)."""
    from dask.distributed import get_worker

    return get_worker().plugins[MiAmrSetup.name].renderers


def render_task(job: Job, renderers: Renderers | None = None) -> dict:
    """Render one frame where this runs, with ``renderers`` (None: the Dask worker's); a user
    mistake (a bad file in the series) comes back as ``{"error": ...}`` instead of an
    exception, so the other frames go on."""
    spec = FrameSpec.from_dict(job.spec)
    out = {"index": spec.index, "file": spec.file, "path": job.path, "pid": os.getpid()}
    try:
        renderer = (renderers or _worker_renderers()).get(job)
        out.update(renderer.render_to(spec, job.path, next_file=job.next_file,
                                      series=job.series))
    except AMRError as e:
        out["error"] = str(e)
    except Exception as e:              # noqa: BLE001 -- reported per frame, not a crash
        out["error"] = f"{type(e).__name__}: {e} ({traceback.format_exc(limit=2).strip()})"
    return out


class MiAmrSetup:
    """Dask worker plugin: on each worker at start, pick the Mitsuba variant, register
    ``amr_iso`` and give Dr.Jit a fair share of the machine's cores."""

    name = "mi_amr-setup"

    def __init__(self, variant: str, threads: int | None):
        self.variant, self.threads = variant, threads
        self.renderers = None

    def setup(self, worker=None):
        import drjit as dr
        import mitsuba as mi

        if self.threads:
            dr.set_thread_count(self.threads)
        mi.set_variant(self.variant)
        from mi_amr.plugin.integrator import register

        register()
        self.renderers = Renderers()


def jobs_for(scene, specs, out_dir, fmt, *, resolution, spp, defines, variant, force,
             existing=()):
    """The jobs still to do, made one by one as they are asked for: a frame whose index is
    in ``existing`` (frames already in the folder) is skipped unless ``force``. Each job
    knows how many data files the movie shows."""
    series = _series_files(specs)
    for spec in specs:
        if spec.index in existing and not force:
            continue
        yield Job(scene=str(scene), spec=spec.as_dict(),
                  path=str(frame_path(out_dir, spec.index, fmt)),
                  resolution=None if resolution is None else tuple(resolution), spp=spp,
                  defines=dict(defines), variant=variant, series=series)


def _series_files(specs) -> int:
    """How many data files the frames ``specs`` show (at least 1): a plan's own list of files
    (its frames are made only when asked for), else the frames' files."""
    files = getattr(specs, "files", None)
    if files is None:
        files = [spec.file for spec in specs]
    return max(1, len({f for f in files if f is not None}))


def with_next_files(jobs):
    """``jobs`` (taken one ahead), each told the next job's data file where it differs from
    its own, so that one process prepares the next time step while this frame renders. (On
    Dask the next frame usually goes to another worker, which would prepare it again: there
    jobs go as they are.)"""
    previous = None
    for job in jobs:
        if previous is not None:
            yield _told(previous, job)
        previous = job
    if previous is not None:
        yield previous


def _told(job: Job, following: Job) -> Job:
    file, next_file = job.spec.get("file"), following.spec.get("file")
    if next_file is None or next_file == file:
        return job
    return dataclasses.replace(job, next_file=next_file)


def run_jobs(jobs, *, workers: int = 1, scheduler: str | None = None, progress: bool = True,
             variant: str = "llvm_ad_rgb", total: int | None = None,
             worker_wait: float = WORKER_WAIT):
    """Run ``jobs`` (an iterable, taken as it goes): in this process with one worker and no
    scheduler, else on Dask. Yields the tasks' results as they finish; the progress bar
    (``total`` jobs) moves from the first frame. When the cluster has had no worker for
    ``worker_wait`` seconds with frames left, the movie's own cluster raises
    :class:`AMRError` (its workers died and none came back) and a scheduler the user named
    gets one line on stderr (its workers may still be queued)."""
    from tqdm import tqdm

    bar = tqdm(total=total, unit="frame", disable=not progress, smoothing=0.1)
    try:
        if scheduler is None and workers <= 1:
            renderers = Renderers()
            for job in with_next_files(jobs):
                yield render_task(job, renderers)
                bar.update(1)
        else:
            yield from _run_dask(jobs, workers, scheduler, bar, variant, worker_wait)
    finally:
        bar.close()


def _connect(workers, scheduler, variant):
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise AMRError("farming frames out needs Dask: pip install 'mi_amr[movie]' (or run "
                       "with --workers 1)") from None
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as e:
            raise AMRError(f"--scheduler {scheduler}: cannot reach the Dask scheduler within "
                           f"{CONNECT_TIMEOUT} ({e})") from None
        return client, None, None
    import dask

    # dashboard_address=None turns off the dashboard's pages, but Dask still starts an HTTP
    # server (on 8787, with its info, JSON and metrics pages; dask/distributed#7207). Give it
    # no routes, and a free loopback port, in the scheduler and in every worker (a worker's
    # nanny hands the configuration set here to its process).
    no_pages = {"distributed.scheduler.http.routes": [], "distributed.worker.http.routes": []}
    with dask.config.set(no_pages):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None,
                               scheduler_kwargs={"dashboard": False,
                                                 "dashboard_address": "127.0.0.1:0"},
                               silence_logs=40)
    threads = max(1, (os.cpu_count() or 1) // workers)
    return Client(cluster), cluster, threads


def _run_dask(jobs, workers, scheduler, bar, variant, worker_wait):
    """Yield the results of ``jobs`` run on Dask (``scheduler`` None: a cluster of our own of
    ``workers``), with at most :data:`QUEUED` tasks a worker submitted at a time (a long movie
    is not planned up front)."""
    from dask.distributed import as_completed

    client, cluster, threads = _connect(workers, scheduler, variant)
    try:
        client.register_plugin(_worker_plugin(variant, threads))
        jobs = iter(jobs)
        queued = QUEUED * max(workers, len(client.scheduler_info().get("workers", {})), 1)
        pending, running = {}, as_completed()

        def submit(count):
            for job in itertools.islice(jobs, count):
                future = client.submit(render_task, job, pure=False, retries=RETRIES,
                                       key=f"mi_amr-frame-{job.spec['index']}-"
                                           f"{time.time_ns()}")
                pending[future] = job
                running.add(future)

        submit(queued)
        watch = _Watch(client, scheduler, worker_wait)
        for future in watch.finished(running):
            job = pending.pop(future)
            try:
                yield watch.result(future, len(pending) + 1)
            except AMRError:
                raise                   # the cluster has no worker left: the whole movie
            except Exception as e:      # noqa: BLE001 -- a task lost after its retries
                spec = job.spec
                yield {"index": spec["index"], "file": spec.get("file"), "path": job.path,
                       "error": f"{type(e).__name__}: {e}"}
            bar.update(1)
            submit(1)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


@dataclass
class _Watch:
    """Hands out the finished futures of a Dask run and their results, and watches that the
    cluster still has a worker while it waits (see :func:`run_jobs`). A finished frame's
    result can be lost with its worker and wait for a new one, so its fetch is watched too."""

    client: object
    scheduler: str | None
    worker_wait: float
    told: bool = False
    since: float | None = None     # when the cluster was first seen without a worker

    def finished(self, running):
        """The futures of the ``as_completed`` set ``running`` as they finish."""
        while not running.is_empty():
            batch = running.next_batch(block=False)
            if batch:
                self.since = None
                yield from batch
                continue
            self._look(running.count())
            time.sleep(POLL)

    def result(self, future, left: int):
        """``future.result()``, watching the workers while it waits (``left``: the frames
        unfinished, for the message)."""
        while True:
            try:
                return future.result(timeout=RESULT_WAIT)
            except TimeoutError:
                # The task's own TimeoutError, not the wait's. (A finished future can still be
                # waiting: its result was lost with its worker while being fetched, and is
                # computed again elsewhere; its status changes only when the scheduler says.)
                if future.status == "error":
                    raise
                self._look(left)

    def _look(self, left: int) -> None:
        if self._workers() > 0:
            self.since = None
            return
        self.since = time.monotonic() if self.since is None else self.since
        if time.monotonic() - self.since > self.worker_wait:
            self._no_workers(left)

    def _workers(self) -> int:
        try:
            return len(self.client.scheduler_info().get("workers", {}))
        except Exception:   # noqa: BLE001 -- the scheduler is busy or gone: no answer yet
            return 0

    def _no_workers(self, left: int) -> None:
        wait = f"{self.worker_wait:g} s"
        if self.scheduler is None:
            raise AMRError(f"movie: every Dask worker of the movie's cluster is gone and none "
                           f"came back within {wait} ({left} frame(s) unfinished); the frames "
                           f"written are kept: run the movie again to render the rest")
        if not self.told:
            self.told = True
            print(f"movie: no Dask worker at --scheduler {self.scheduler} for {wait} with "
                  f"{left} frame(s) unfinished; still waiting (Ctrl-C stops; the frames "
                  f"written are kept)", file=sys.stderr, flush=True)


def _worker_plugin(variant, threads):
    from dask.distributed import WorkerPlugin

    class _Setup(MiAmrSetup, WorkerPlugin):
        pass

    return _Setup(variant, threads)
