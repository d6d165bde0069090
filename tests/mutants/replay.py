"""Replay the hand-made mutants of ``tests/mutants/README.md``: each applied to a temporary copy
of the checkout, its test files run there, and whether a test caught it reported.

    python tests/mutants/replay.py              # every mutant
    python tests/mutants/replay.py band-inverse-base roots-tangent-r1
    python tests/mutants/replay.py --list

Not part of ``make test`` (pytest does not collect this folder). Exit status 1 where a mutant
survived or could not be applied (its code changed: update the mutant).
"""

from __future__ import annotations

import argparse
import glob
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
COPIED = ("mi_amr", "tests", "scenes_xml", "reference", "pyproject.toml")
TIME_LIMIT = 1800   # seconds for one mutant's tests


@dataclass(frozen=True)
class Mutant:
    """``edits``: ``(old, new, count)`` replacements in ``path`` (``count`` occurrences of
    ``old`` expected); ``tests``: test files (globs, relative to the checkout) that should
    catch it."""

    name: str
    path: str
    edits: tuple
    tests: tuple
    why: str


MUTANTS = (
    Mutant("band-inverse-base", "mi_amr/kernels/band.py",
           (("    base = k * (INVERSE_SIZE + 1)", "    base = k * INVERSE_SIZE", 1),),
           ("tests/test_band_tables.py", "tests/test_preintegrated.py"),
           "band k's inverse table read one cell per band too early (band 0's for its first)"),
    Mutant("band-integral-base", "mi_amr/kernels/band.py",
           (("k * (TABLE_SIZE + 1)", "k * TABLE_SIZE", 4),),
           ("tests/test_band_tables.py", "tests/test_preintegrated.py"),
           "every integral-table lookup of band k (and its total) starts k cells early"),
    Mutant("band-total-of-band-0", "mi_amr/kernels/band.py",
           (("m.UInt32(k * (TABLE_SIZE + 1) + TABLE_SIZE)", "m.UInt32(TABLE_SIZE)", 2),),
           ("tests/test_band_tables.py", "tests/test_preintegrated.py"),
           "every band scales its inverse and short-ramp test by band 0's total integral"),
    Mutant("band-cap-of-band-0", "mi_amr/kernels/band.py",
           (('    cap = band.get(m, "cap", k)', '    cap = band.get(m, "cap", 0)', 1),),
           ("tests/test_band_tables.py", "tests/test_preintegrated.py"),
           "the centroid splits every band's steps at band 0's plateau"),
    Mutant("rope-plus-z", "mi_amr/kernels/traverse.py",
           (("dr.minimum(face, 5)", "dr.minimum(face, 4)", 1),),
           ("tests/test_traversal.py",),
           "the +z rope reads the -z one: the walk falls back to the root (only speed changes)"),
    Mutant("roots-tangent-r1", "mi_amr/kernels/roots.py",
           (("touch1 = (r1 < L) & (dr.abs(f1) <= tol)", "touch1 = (r1 < L) & (dr.abs(f1) < 0.0)",
             1),),
           ("tests/test_roots.py", "tests/test_kernels_small.py"),
           "a tangent at the first interior extremum is no root"),
    Mutant("roots-tangent-r2", "mi_amr/kernels/roots.py",
           (("touch2 = (r2 < L) & (dr.abs(f2) <= tol)", "touch2 = (r2 < L) & (dr.abs(f2) < 0.0)",
             1),),
           ("tests/test_roots.py", "tests/test_kernels_small.py"),
           "a tangent at the second interior extremum is no root"),
    Mutant("roots-tangent-end", "mi_amr/kernels/roots.py",
           (("touch3 = dr.abs(f3) <= tol", "touch3 = dr.abs(f3) < 0.0", 1),),
           ("tests/test_roots.py", "tests/test_kernels_small.py"),
           "a tangent at the interval's end is no root"),
    Mutant("packet-u-one-stream", "mi_amr/plugin/wavefront.py",
           (("stable_jitter(m, pos // (spp_u * PACKET), key + 1)",
             "stable_jitter(m, pos // (spp_u * PACKET), key)", 1),),
           ("tests/test_packet_picks.py",),
           "the stratum's turn and the packet's number drawn from one hash stream"),
    Mutant("skip-restarts-at-root", "mi_amr/kernels/traverse.py",
           (("_restart(ray, t_next + ray.eps(t_next), at.node, f_out, skip)",
             "_restart(ray, t_next + ray.eps(t_next), at.node, f_out * 0 + 6, skip)", 1),),
           ("tests/test_traversal.py",),
           "a skipped node's search restarts at the root instead of its rope (only slower)"),
    Mutant("dual-plane-skipped", "mi_amr/kernels/traverse.py",
           (("plane = dr.select(up, cell + 1.5, cell + 0.5)",
             "plane = dr.select(up, cell + 2.5, cell + 0.5)", 1),),
           ("tests/test_march.py",),
           "a ray going up a coordinate skips every other dual-cell plane: pieces span two "
           "cells, so their cubic is wrong"),
)


def copy_checkout(dest: str) -> None:
    for name in COPIED:
        src = os.path.join(ROOT, name)
        if os.path.isdir(src):
            shutil.copytree(src, os.path.join(dest, name),
                            ignore=shutil.ignore_patterns("__pycache__", ".pytest_cache"))
        elif os.path.exists(src):
            shutil.copy2(src, os.path.join(dest, name))


def apply(mutant: Mutant, dest: str) -> str | None:
    """Edit the copy; the reason it cannot be applied, else None."""
    path = os.path.join(dest, mutant.path)
    with open(path) as f:
        text = f.read()
    for old, new, count in mutant.edits:
        found = text.count(old)
        if found != count:
            return f"{mutant.path}: {old!r} found {found} times, expected {count}"
        text = text.replace(old, new)
    with open(path, "w") as f:
        f.write(text)
    return None


def replay(mutant: Mutant) -> tuple:
    """``(verdict, detail)``: caught, survived, no tests, stale or error."""
    with tempfile.TemporaryDirectory(prefix=f"mutant-{mutant.name}-") as dest:
        copy_checkout(dest)
        reason = apply(mutant, dest)
        if reason:
            return "stale", reason
        files = sorted({f for g in mutant.tests for f in glob.glob(os.path.join(dest, g))})
        if not files:
            return "no tests", "none of " + ", ".join(mutant.tests) + " exists"
        env = dict(os.environ, PYTHONPATH=dest)
        cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *files]
        try:
            proc = subprocess.run(cmd, cwd=dest, env=env, capture_output=True, text=True,
                                  timeout=TIME_LIMIT)
        except subprocess.TimeoutExpired:
            return "error", f"tests ran past {TIME_LIMIT} s"
        tail = [ln for ln in proc.stdout.splitlines() if ln.strip()][-1:] or [""]
        names = ", ".join(os.path.relpath(f, dest) for f in files)
        verdict = {0: "survived", 1: "caught"}.get(proc.returncode, "error")
        first = next((ln for ln in proc.stdout.splitlines() if ln.startswith("FAILED")), "")
        return verdict, f"{names}: {tail[0]} {first}".strip()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="mutants to replay (default: all)")
    parser.add_argument("--list", action="store_true", help="list the mutants and stop")
    args = parser.parse_args(argv)
    by_name = {m.name: m for m in MUTANTS}
    unknown = [n for n in args.names if n not in by_name]
    if unknown:
        parser.error(f"unknown mutant(s) {unknown}; known: {', '.join(by_name)}")
    chosen = [by_name[n] for n in args.names] or list(MUTANTS)
    if args.list:
        for m in chosen:
            print(f"{m.name:22s} {m.path}: {m.why}")
        return 0
    bad = 0
    for m in chosen:
        t0 = time.perf_counter()
        verdict, detail = replay(m)
        bad += verdict != "caught"
        print(f"{m.name:22s} {verdict:9s} ({time.perf_counter() - t0:.0f} s) {detail}",
              flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
