"""Running independent NumPy passes (chunks of cells, grids of one shape) on all the CPUs.

NumPy lets go of the interpreter inside its array operations, so threads working on separate
chunks run side by side. Each job must write only its own part of any shared output.
"""

from __future__ import annotations

import os
from collections import deque
from concurrent.futures import ThreadPoolExecutor

MAX_THREADS = 8     # at most this many threads: each holds its chunk's temporaries


def thread_count() -> int:
    """Threads to use: the CPUs this process may run on, at most :data:`MAX_THREADS`."""
    affinity = getattr(os, "sched_getaffinity", None)     # not on macOS
    cpus = len(affinity(0)) if affinity else (os.cpu_count() or 1)
    return max(1, min(MAX_THREADS, cpus))


def map_ordered(fn, items, threads: int | None = None):
    """``fn(item)`` for each of ``items``, yielded in order, computed on ``threads`` threads
    (default :func:`thread_count`) with at most two items a thread in flight, so memory stays
    bounded however many items there are. One thread: a plain loop."""
    threads = threads or thread_count()
    if threads <= 1:
        for item in items:
            yield fn(item)
        return
    with ThreadPoolExecutor(threads) as pool:
        pending = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= 2 * threads:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def for_each(fn, items, threads: int | None = None) -> None:
    """``fn(item)`` for each of ``items`` side by side (as :func:`map_ordered`), for jobs that
    write their own part of a shared output and return nothing."""
    for _ in map_ordered(fn, items, threads):
        pass
