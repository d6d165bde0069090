"""The parts of ``python -m mi_amr bench --soak`` that can be checked quickly (the soak runs
themselves take minutes and are not part of ``make test``)."""

import os
import signal
import subprocess
import sys
import time

from mi_amr.evaluation import soak


def test01_the_movie_part_finds_the_worker_processes_below_the_movie():
    """The processes a killed worker is picked from: those below the movie's process with no
    children (Dask's workers), not the process itself nor a parent of others."""
    child = ("import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', "
             "'import time; time.sleep(60)']); time.sleep(60)")
    top = subprocess.Popen([sys.executable, "-c", child])
    try:
        end = time.monotonic() + 30
        leaves = []
        while not leaves and time.monotonic() < end:
            time.sleep(0.2)
            leaves = soak._worker_processes(top.pid)
        assert len(leaves) == 1 and leaves[0] != top.pid
    finally:
        for pid in soak._worker_processes(top.pid):     # the one this test started
            os.kill(pid, signal.SIGTERM)
        top.kill()
        top.wait()


def test02_the_table_says_whether_the_memory_target_is_met():
    viewer = {"changes": 2000, "memory_growth_mb": 2.4, "memory_baseline_mb": 171.0,
              "memory_end_mb": 173.4, "compiled_after_warmup": {"saves": 0, "controls": 0},
              "compiled_total": {"warmup": 3, "reloads": 2}, "images_saved": 17,
              "error_count": 0, "files_left_behind": []}
    text = soak.soak_table({"viewer": viewer, "movie": {"frames_lost": 0}})
    assert "+2.4 MB" in text and "met)" in text and "NOT met" not in text
    assert "| movie | frames lost | 0 |" in text
    text = soak.soak_table({"viewer": dict(viewer, memory_growth_mb=60.0)})
    assert "NOT met" in text
