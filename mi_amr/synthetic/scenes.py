"""The data files that the repository's scenes (``scenes_xml/*.xml``) refer to."""

from __future__ import annotations

import time
from pathlib import Path

from mi_amr.synthetic.datasets import ANALYTIC, make


def scene_data(data_dir, verbose: bool = True) -> list:
    """Create in ``data_dir`` the data files the scenes refer to (``sphere_wake.npz`` with
    ``ball.ply``, and the analytic datasets), skipping those already present. Returns the paths
    written."""
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    wanted = [("sphere_wake", data_dir / "sphere_wake.npz")]
    wanted += [(name, data_dir / f"{name}.npz") for name in ANALYTIC]
    made = []
    for name, path in wanted:
        extra = [data_dir / "ball.ply"] if name == "sphere_wake" else []
        if path.exists() and all(p.exists() for p in extra):
            continue
        t0 = time.perf_counter()
        made += make(name, path, size="default", overwrite=True, progress=verbose)
        if verbose:
            print(f"made {path} in {time.perf_counter() - t0:.1f} s")
    return made
