"""Fuzz the readers: damaged inputs must end as an AMRError, never as another exception, a hang
or a crash.

Two kinds of cases, each read in its own process (``mi_amr.load`` then ``summary()``, what
``python -m mi_amr info`` does) with a time limit, a memory limit and NumPy's RuntimeWarnings
(overflow in a cast, say) turned into errors:

* ``npz`` -- raw byte mutations (bit flips, bytes set to boundary values, insertions,
  deletions, duplicated chunks, truncation) of a small ``.npz`` written by ``AMRVolume.save``;
  half of them aimed at the zip and ``.npy`` headers, where damage reaches the parser;
* ``header`` -- mutations of the ``Header`` of a small AMReX plotfile (tests/amrex_writer.py):
  numbers replaced by boundary values (0, -1, 2^31, 1e26, a 27-digit integer, nan, inf, ...),
  lines deleted, duplicated, swapped or replaced by junk, characters changed, the text cut;
* ``cache`` -- a snapshot cache with flipped bits, truncated or extended arrays, planted files
  and pickles, bad or retyped metadata, a user's folders, links pointing outside it, FIFOs
  (tests/fuzz_cache.py): each must end as a fresh preparation with the right result, with no
  code run and nothing outside the cache's own folders touched.

Usage: ``python tests/fuzz_inputs.py --cases N --seed S`` (N of each kind unless
``--header-cases`` or ``--cache-cases`` says otherwise). Prints the cases run and the number of
non-AMRError exceptions, hangs, crashes, tracebacks, wrong results, pickles run and files touched;
exits 1 when any of those is not zero. ``--keep DIR`` keeps the
failing inputs. ``tests/test_fuzz.py`` runs a small fixed set of seeds.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from amrex_writer import write_plotfile  # noqa: E402

TIMEOUT = 20.0                  # seconds a case may take
MEMORY_LIMIT = 4 << 30          # bytes of address space for a case's process
# What a case's process runs: read the input as `info` does, and say how it ended.
CHILD = r"""
import sys
from mi_amr import AMRError, load
try:
    load(sys.argv[1]).summary()
    print("RESULT ok")
except AMRError:
    print("RESULT amrerror")
except BaseException as e:
    text = str(e).splitlines()[0][:300] if str(e).strip() else ""
    print(f"RESULT exception {type(e).__name__}: {text}")
"""
BOUNDARY_BYTES = (0x00, 0x01, 0x7F, 0x80, 0xFE, 0xFF)
BOUNDARY_NUMBERS = ("0", "-1", "1", "2", "3", "4", "7", "8", "2147483647", "2147483648",
                    "-2147483649", "9223372036854775808", "100000000000000000000000000",
                    "1e26", "-1e26", "1e308", "1e-308", "1e400", "nan", "inf", "-inf", "0.5",
                    "3.7", "-0", "", "x")
JUNK_LINES = ("((x", "-1", "", "((0,0,0) (7,7,7) (0,0,0))", "Level_0/Cell", "../../etc/passwd",
              "1 1 1 1 1 1", "(((((((((((((((((((((((((((((", "\x00\x01\x02")


@dataclass
class Outcome:
    """What happened to a case: ``ok``, ``amrerror``, ``exception``, ``hang`` or ``crash``."""

    kind: str
    case: str
    status: str
    detail: str = ""


# How a case may fail: the readers' cases end as ``exception``, ``hang`` or ``crash``; the
# cache's also as ``traceback`` (printed, though the process went on), ``wrong`` (another
# result than without a cache), ``ran_code`` (a pickle was loaded) or ``touched`` (a file
# outside the cache's own folders changed or went).
FAILURES = ("exception", "hang", "crash", "traceback", "wrong", "ran_code", "touched")


@dataclass
class Tally:
    cases: int = 0
    exceptions: int = 0
    hangs: int = 0
    crashes: int = 0
    others: int = 0             # the cache's failures: traceback, wrong, ran_code, touched
    statuses: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)
    outcomes: list = field(default_factory=list)

    def add(self, o: Outcome) -> None:
        self.cases += 1
        self.outcomes.append(o)
        self.statuses[o.status] = self.statuses.get(o.status, 0) + 1
        if o.status == "exception":
            self.exceptions += 1
        elif o.status == "hang":
            self.hangs += 1
        elif o.status == "crash":
            self.crashes += 1
        elif o.status in FAILURES:
            self.others += 1
        if o.status in FAILURES:
            self.failures.append(o)


# ---------------------------------------------------------------------- the inputs

def small_volume():
    """Two levels, three grids, a float32 and a float64 field (a few KiB on disk)."""
    from mi_amr import AMRVolume

    rng = np.random.default_rng(0)

    def grid(level, origin, h, n):
        return {"level": level, "origin": origin, "spacing": h,
                "fields": {"a": rng.normal(size=n).astype(np.float32), "b": rng.normal(size=n)}}
    return AMRVolume.from_grids([grid(0, (0, 0, 0), 1.0, (4, 4, 4)),
                                 grid(0, (4, 0, 0), 1.0, (4, 4, 4)),
                                 grid(1, (2, 1, 1), 0.5, (4, 4, 2))])


def npz_regions(data: bytes, path: Path) -> list:
    """Byte ranges where damage reaches a parser: each entry's local header and ``.npy``
    header, the central directory and its end record."""
    with zipfile.ZipFile(path) as z:
        regions = [(i.header_offset, i.header_offset + 30 + len(i.filename) + 128)
                   for i in z.infolist()]
    directory = data.find(b"PK\x01\x02")
    if directory >= 0:
        regions.append((directory, len(data)))
    return [(max(0, a), min(len(data), b)) for a, b in regions if a < len(data)]


def mutate_bytes(data: bytes, regions: list, rng: random.Random) -> bytes:
    """One to six random byte-level mutations of ``data``."""
    out = bytearray(data)
    for _ in range(rng.randint(1, 6)):
        if not out:
            break
        if regions and rng.random() < 0.5:
            a, b = rng.choice(regions)
            pos = rng.randrange(a, max(a + 1, min(b, len(out))))
        else:
            pos = rng.randrange(len(out))
        pos = min(pos, len(out) - 1)
        op = rng.choice(("flip", "set", "insert", "delete", "duplicate", "truncate", "word"))
        if op == "flip":
            out[pos] ^= 1 << rng.randrange(8)
        elif op == "set":
            out[pos] = rng.choice(BOUNDARY_BYTES + (rng.randrange(256),))
        elif op == "insert":
            out[pos:pos] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        elif op == "delete":
            del out[pos:pos + rng.randint(1, 64)]
        elif op == "duplicate":
            out[pos:pos] = out[pos:pos + rng.randint(1, 64)]
        elif op == "truncate" and rng.random() < 0.3:
            del out[pos:]
        elif op == "word":
            word = rng.choice((b"\xff\xff\xff\xff", b"\x00\x00\x00\x00", b"\xff\xff\xff\x7f",
                               b"\x00\x00\x00\x80"))
            out[pos:pos + 4] = word
    return bytes(out)


def mutate_header(text: str, rng: random.Random) -> str:
    """One to four random mutations of a plotfile Header's lines, numbers or characters."""
    lines = text.splitlines()
    for _ in range(rng.randint(1, 4)):
        if not lines:
            lines = [""]
        i = rng.randrange(len(lines))
        op = rng.choice(("number", "number", "number", "delete", "duplicate", "swap", "junk",
                         "char", "cut"))
        if op == "number":
            tokens = list(re.finditer(r"-?\d+(\.\d*)?(e-?\d+)?", lines[i]))
            if tokens:
                m = rng.choice(tokens)
                lines[i] = lines[i][:m.start()] + rng.choice(BOUNDARY_NUMBERS) + lines[i][m.end():]
        elif op == "delete":
            del lines[i]
        elif op == "duplicate":
            lines.insert(i, lines[i])
        elif op == "swap":
            j = rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "junk":
            lines[i] = rng.choice(JUNK_LINES)
        elif op == "char" and lines[i]:
            k = rng.randrange(len(lines[i]))
            lines[i] = lines[i][:k] + chr(rng.randrange(32, 127)) + lines[i][k + 1:]
        elif op == "cut":
            joined = "\n".join(lines)
            return joined[:rng.randrange(len(joined) + 1)]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- running cases

def run_case(kind: str, case: str, path: Path, timeout: float) -> Outcome:
    """Read ``path`` in a new process; classify how it ended."""
    def limit():
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))

    env = dict(os.environ, PYTHONPATH=str(HERE.parent) + os.pathsep +
               os.environ.get("PYTHONPATH", ""))
    try:
        # NumPy's overflow warnings become errors: a silent overflow is a wrong value.
        proc = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-c", CHILD,
                               str(path)], capture_output=True, text=True, timeout=timeout,
                              preexec_fn=limit, env=env)
    except subprocess.TimeoutExpired:
        return Outcome(kind, case, "hang", f"no result within {timeout:g} s")
    result = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode < 0 or not result:
        return Outcome(kind, case, "crash", f"exit status {proc.returncode}: "
                                            f"{proc.stderr.strip()[-500:]}")
    status, _, detail = result[-1][len("RESULT "):].partition(" ")
    return Outcome(kind, case, status, detail)


def npz_cases(work: Path, count: int, seed: int):
    """``(case name, path)`` of ``count`` mutated copies of the small ``.npz``."""
    original = work / "original.npz"
    small_volume().save(original, overwrite=True)
    data = original.read_bytes()
    regions = npz_regions(data, original)
    for i in range(count):
        rng = random.Random(f"npz:{seed}:{i}")
        path = work / f"npz-{seed}-{i}.npz"
        path.write_bytes(mutate_bytes(data, regions, rng))
        yield f"npz seed {seed} case {i}", path


def header_cases(work: Path, count: int, seed: int):
    """``(case name, path)`` of ``count`` copies of the small plotfile with a mutated Header."""
    original = write_plotfile(work / "original_plt")
    text = (original / "Header").read_text()
    for i in range(count):
        rng = random.Random(f"header:{seed}:{i}")
        root = work / f"plt-{seed}-{i}"
        shutil.copytree(original, root)
        (root / "Header").write_text(mutate_header(text, rng))
        yield f"header seed {seed} case {i}", root


def fuzz(npz: int, header: int, seeds, *, cache: int = 0, jobs: int = 2,
         timeout: float = TIMEOUT, keep: Path | None = None) -> dict:
    """Run ``npz`` byte-mutation, ``header`` Header-mutation and ``cache`` snapshot-cache
    cases for each seed; returns ``{"npz": Tally, "header": Tally}``, and ``"cache": Tally``
    when ``cache``."""
    tallies = {"npz": Tally(), "header": Tally()} | ({"cache": Tally()} if cache else {})
    with tempfile.TemporaryDirectory(prefix="mi_amr_fuzz_") as folder:
        work = Path(folder)
        todo = []
        for seed in seeds:
            todo += [("npz", c, p) for c, p in npz_cases(work, npz, seed)]
            todo += [("header", c, p) for c, p in header_cases(work, header, seed)]
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            outcomes = list(pool.map(lambda t: run_case(*t, timeout), todo))
            if cache:
                outcomes += _cache_outcomes(work, cache, seeds, pool, timeout)
        for (kind, _, path), o in zip(todo, outcomes):
            tallies[kind].add(o)
        for o in outcomes[len(todo):]:
            tallies["cache"].add(o)
            if keep is not None and o.status in ("exception", "hang", "crash"):
                keep.mkdir(parents=True, exist_ok=True)
                target = keep / path.name
                if path.is_dir():
                    shutil.copytree(path, target, dirs_exist_ok=True)
                else:
                    shutil.copy(path, target)
    return tallies


def _cache_outcomes(work: Path, count: int, seeds, pool, timeout: float) -> list:
    """Outcomes of ``count`` snapshot-cache cases per seed (tests/fuzz_cache.py)."""
    import fuzz_cache

    setup = fuzz_cache.Setup(work / "cache-setup", timeout)
    cases = [c for seed in seeds for c in fuzz_cache.cache_cases(work, count, seed, setup)]

    def one(case):
        name, ctx, before = case
        return Outcome("cache", name, *fuzz_cache.check(ctx, setup, before, timeout))
    return list(pool.map(one, cases))


def report(tallies: dict) -> str:
    lines = []
    for kind, t in tallies.items():
        lines.append(f"{kind}: {t.cases} cases, {t.exceptions} non-AMRError exceptions, "
                     f"{t.hangs} hangs, {t.crashes} crashes, {t.others} tracebacks / wrong "
                     f"results / pickles run / files touched (outcomes {t.statuses})")
    total = [sum(getattr(t, a) for t in tallies.values())
             for a in ("cases", "exceptions", "hangs", "crashes", "others")]
    lines.append(f"total: {total[0]} cases, {total[1]} non-AMRError exceptions, {total[2]} "
                 f"hangs, {total[3]} crashes, {total[4]} tracebacks / wrong results / pickles "
                 f"run / files touched")
    for t in tallies.values():
        for o in t.failures[:20]:
            lines.append(f"  {o.status}: {o.case}: {o.detail}")
    cache = [o for o in tallies.get("cache", Tally()).outcomes if o.status == "ok"]
    if cache:
        afresh = sum(o.detail == "prepared afresh" for o in cache)
        lines.append(f"cache: {afresh} of the {len(cache)} good cases prepared afresh, "
                     f"{len(cache) - afresh} read their entry back")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", type=int, default=100, help="cases of each kind (default 100)")
    p.add_argument("--header-cases", type=int, help="Header cases (default: --cases)")
    p.add_argument("--cache-cases", type=int, help="snapshot-cache cases (default: --cases)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=2, help="cases run at once (default 2)")
    p.add_argument("--timeout", type=float, default=TIMEOUT, help="seconds per case")
    p.add_argument("--keep", type=Path, help="copy failing inputs into this folder")
    args = p.parse_args(argv)
    header = args.cases if args.header_cases is None else args.header_cases
    cache = args.cases if args.cache_cases is None else args.cache_cases
    tallies = fuzz(args.cases, header, [args.seed], cache=cache, jobs=args.jobs,
                   timeout=args.timeout, keep=args.keep)
    print(report(tallies))
    bad = sum(t.exceptions + t.hangs + t.crashes + t.others for t in tallies.values())
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
