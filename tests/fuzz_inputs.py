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

A third kind, ``protocol``, runs against a viewer (``python -m mi_amr view``, its own process)
instead: fixed malformed messages (JSON nested 100k deep, 4000-digit integers, names as lists,
NUL in paths, megabyte values, parsing quirks), random requests with boundary values, each
followed by a probe the viewer must answer at once, and a client that floods and never reads
(the viewer must grow less than 50 MB and keep serving). A traceback or "internal error" in its
log or replies, an unanswered probe, or a file written outside its output folder fails a case.

Usage: ``python tests/fuzz_inputs.py --cases N --seed S`` (N of each kind unless
Usage: ``python tests/fuzz_inputs.py --cases N --seed S`` (N of each kind unless
``--header-cases`` or ``--cache-cases`` says otherwise). Prints the cases run and the number of
non-AMRError exceptions, hangs, crashes, tracebacks, wrong results, pickles run and files touched;
exits 1 when any of those is not zero. ``--keep DIR`` keeps the failing inputs;
``--protocol-cases N`` adds the protocol kind. ``tests/test_fuzz.py`` runs a small fixed set of
seeds.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
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
# What a case's process runs: read the input as `info` does, then stream every field as a
# time series' colour range does, and say how it ended (amrerror: either refused it).
CHILD = r"""
import sys
from mi_amr import AMRError, load
from mi_amr.readers import available_fields, stream_fields

def streamed(path):
    stream = stream_fields(path, available_fields(path))
    if stream is not None:
        with stream:
            for _ in stream.chunks():
                pass

try:
    status = "ok"
    for step in (lambda: load(sys.argv[1]).summary(), lambda: streamed(sys.argv[1])):
        try:
            step()
        except AMRError:
            status = "amrerror"
    print(f"RESULT {status}")
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


# ---------------------------------------------------------------------- the viewer's protocol
# (A section of its own: requests sent to a running viewer, not files read by a new process.)

PROTOCOL_TIMEOUT = 30.0         # seconds the viewer may take to answer a request
SLOW_READER_GROWTH = 50e6       # bytes the viewer may grow while a client floods, never reading
VIEWER_OPS = ("set", "camera", "add_isovalue", "remove_isovalue", "reset_color_range",
              "save_image", "save_scene", "add_keyframe", "open")
CONTROL_NAMES = ("isovalue", "iso_color", "iso_opacity", "step_scale", "shadows", "method",
                 "reconstruction", "layers", "mode", "band_width", "field", "color_field",
                 "colormap", "color_range", "light_azimuth", "light_elevation",
                 "light_strength", "spp")
BOUNDARY_VALUES = (None, True, 0, -1, 1, 0.5, 1e-4, 9.9999e-5, 1e-50, 1e39, 1e308, -1e308,
                   "", " ", "abc", "1_000", "0x10", "nan", "inf", "-0", "1e999", "#-1-1-1",
                   "#ffffff", "#zzzzzz", "0: -1 0 0, 1: 1 1 1", "0: 1e39 0 0, 1: 1 1 1",
                   "viridis", "surface", "volume", "exact", "a\x00b", "../../etc/passwd",
                   "/etc/passwd", "x" * 5000, "\u202e\ud7ff", [], [1], [1, 2], [1, 2, 3],
                   ["a", "b", "c"], [[1]], {}, {"a": 1}, 10 ** 30)
FIXED_MESSAGES = (
    "[" * 100_000 + "]" * 100_000,
    '{"a":' * 50_000 + "1" + "}" * 50_000,
    '{"op": "set", "name": "isovalue", "value": ' + "7" * 4000 + "}",
    '{"op": "set", "name": "isovalue", "value": 0.3, "index": ' + "1" * 4000 + "}",
    '{"op": "set", "name": ["isovalue"], "value": 0.3}',
    '{"op": ["set"]}',
    '{"op": "open", "path": "data/sphere.npz\\u0000.png"}',
    '{"op": "save_image", "name": "a\\u0000.png"}',
    '{"op": "set", "name": "isovalue", "value": "' + "9" * 1_000_000 + '"}',
    '{"op": "set", "name": "isovalue", "value": NaN}',
    "{op: set", "[1, 2, 3]", "", "null", '"text"', "1e999",
    '{"op": "set", "name": "iso_color", "value": "#-1-1-1"}',
    '{"op": "set", "name": "colormap", "value": "0.1: -1 0 0, 0.5: 1 1 1"}',
    '{"op": "set", "name": "spp", "value": "1_000"}',
    '{"op": "set", "name": "step_scale", "value": 1e-4}',
    '{"op": "save_image", "name": "big.png", "width": 1e300, "height": 1}',
    '{"op": "add_keyframe", "name": "k.toml", "frame": 1e30}',
)


def random_request(rng: random.Random):
    """One request: a random op and control name with boundary values in its fields, now and
    then cut, with characters changed, or sent as bytes."""
    msg = {"op": rng.choice(VIEWER_OPS + ("x", ""))}
    for key in rng.sample(("name", "value", "index", "action", "dx", "dy", "amount", "path",
                           "width", "height", "frame", "overwrite"), rng.randint(0, 4)):
        msg[key] = rng.choice(BOUNDARY_VALUES)
    if msg["op"] == "set" and rng.random() < 0.8:
        msg["name"] = rng.choice(CONTROL_NAMES)
    if msg["op"] in ("save_image", "save_scene", "add_keyframe") and rng.random() < 0.5:
        msg["name"] = rng.choice(("fuzz.png", "fuzz.exr", "fuzz.xml", "fuzz.toml", "../up.png",
                                  "a/b.png", ".png"))
    text = json.dumps(msg)
    r = rng.random()
    if r < 0.1:
        return text[:rng.randrange(len(text) + 1)]
    if r < 0.2:
        k = rng.randrange(len(text))
        return text[:k] + chr(rng.randrange(0, 0x3000)) + text[k + 1:]
    if r < 0.25:
        return text.encode()
    return text


def protocol_case(client, viewer, request) -> str:
    """Send ``request``; then a probe the viewer must answer at once ("unknown request"):
    ``ok``, ``exception`` (a traceback or "internal error" in the viewer's log or a reply),
    ``hang`` (no answer to the probe) or ``crash`` (the viewer exited)."""
    from websockets.exceptions import ConnectionClosed

    seen = len(viewer.output)
    try:
        client.send(request)
        client.send({"op": "fuzz-probe"})
    except ConnectionClosed:
        pass                        # told apart below: the socket is closed
    probe = client.until(lambda m: m["type"] == "error" and "fuzz-probe" in m["message"],
                         PROTOCOL_TIMEOUT)
    if viewer.proc.poll() is not None:
        return "crash"
    if client.ws.close_code is not None or client.ws.state.name == "CLOSED":
        return "exception"          # the viewer dropped the socket
    if probe is None:
        return "hang"
    bad = [ln for ln in viewer.output[seen:] if "Traceback" in ln or "internal error" in ln]
    bad += [m["message"] for m in client.texts if m["type"] == "error" and
            ("internal error" in m["message"] or len(m["message"]) > 300)]
    client.texts.clear()
    return "exception" if bad else "ok"


def slow_reader_case(viewer, requests: int = 300) -> tuple:
    """A client that floods refused megabyte requests and valid changes and never reads:
    ``(status, detail)``, ``ok`` when the viewer grew less than :data:`SLOW_READER_GROWTH` and
    still serves a new page."""
    from mi_amr.evaluation.viewer_client import SilentClient, ViewerClient, rss_bytes

    rss0 = rss_bytes(viewer.proc.pid)
    silent = SilentClient(viewer.url)
    big = json.dumps({"op": "set", "name": "isovalue", "value": "9" * 1_000_000})
    sent = 0
    for i in range(requests):
        change = json.dumps({"op": "set", "name": "isovalue", "value": 0.25 + 1e-4 * i})
        if not silent.send(change if i % 3 == 0 else big):
            break
        sent += 1
    time.sleep(1.0)                 # what the viewer took in, it has handled
    grown = rss_bytes(viewer.proc.pid) - rss0
    other = ViewerClient(viewer.url)
    served = other.until(lambda m: m["type"] == "state", PROTOCOL_TIMEOUT) is not None
    other.close()
    silent.close()
    detail = f"{sent} requests taken, grew {grown / 1e6:.1f} MB, a new page served: {served}"
    if viewer.proc.poll() is not None:
        return "crash", detail
    return ("ok" if served and grown < SLOW_READER_GROWTH else "hang"), detail


def fuzz_protocol(cases: int, seeds, *, keep: Path | None = None) -> dict:
    """The fixed malformed messages, ``cases`` random requests per seed and a slow reader,
    against one viewer of a small scene; returns ``{"protocol": Tally}``. Files the requests
    save must stay in the viewer's output folder: anything new elsewhere in the work folder
    counts as an exception."""
    from test_viewer import Viewer, write_scene

    from mi_amr.evaluation.viewer_client import ViewerClient

    tally = Tally()
    with tempfile.TemporaryDirectory(prefix="mi_amr_fuzz_view_") as folder:
        work = Path(folder)
        viewer = Viewer(write_scene(work / "scene"), work / "out")
        before = {p for p in work.rglob("*") if "out" not in p.relative_to(work).parts}
        try:
            client = ViewerClient(viewer.url)
            todo = [(f"fixed {i}", m) for i, m in enumerate(FIXED_MESSAGES)]
            for seed in seeds:
                rng = random.Random(f"protocol:{seed}")
                todo += [(f"protocol seed {seed} case {i}", random_request(rng))
                         for i in range(cases)]
            for name, request in todo:
                status = protocol_case(client, viewer, request)
                tally.add(Outcome("protocol", name, status, str(request)[:200]))
                if status == "crash":
                    break
                if status == "exception":       # the socket may be gone: a new one
                    client.close()
                    client = ViewerClient(viewer.url)
            client.close()
            status, detail = slow_reader_case(viewer)
            tally.add(Outcome("protocol", "slow reader", status, detail))
        finally:
            viewer.stop()
        after = {p for p in work.rglob("*") if "out" not in p.relative_to(work).parts}
        for p in sorted(after - before):
            tally.add(Outcome("protocol", "files", "exception", f"written outside out/: {p}"))
        if keep is not None and tally.failures:
            keep.mkdir(parents=True, exist_ok=True)
            (keep / "viewer.log").write_text("".join(viewer.output))
    return {"protocol": tally}


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
    p.add_argument("--protocol-cases", type=int, default=0,
                   help="also this many random viewer requests (with the fixed malformed "
                        "ones and a slow reader) against a running viewer (default 0: none)")
    args = p.parse_args(argv)
    header = args.cases if args.header_cases is None else args.header_cases
    cache = args.cases if args.cache_cases is None else args.cache_cases
    tallies = fuzz(args.cases, header, [args.seed], cache=cache, jobs=args.jobs,
                   timeout=args.timeout, keep=args.keep)
    if args.protocol_cases:
        tallies.update(fuzz_protocol(args.protocol_cases, [args.seed], keep=args.keep))
    print(report(tallies))
    bad = sum(t.exceptions + t.hangs + t.crashes + t.others for t in tallies.values())
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
