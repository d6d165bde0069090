"""Fuzz cases for the snapshot cache (mi_amr.kernels.snapshot): damaged, planted and linked
entries must end as a warning and a fresh preparation -- never another exception, a traceback,
a hang, a different result, code run from the cache, or a file written or removed outside it.

Each case copies a cache that holds one good entry of a small volume (and folders of a user's
beside it), applies one to three of :data:`MUTATIONS`, and prepares the volume in a new process
(``prepare_file`` with that cache, then the leaf ranges, as a render does). The case passes when
that process ends normally with the arrays a preparation without any cache gives (everything the
kernels read, hashed: the same inputs, the same image), the planted pickle's marker file does not
exist (it would if the pickle had been loaded), and every file outside the cache's own folders
(the user's folders in the cache, the folder outside it that links point to) is as it was.

Run by ``tests/fuzz_inputs.py --cache-cases N`` and, a few cases, by ``tests/test_fuzz.py``.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import random
import shutil
import subprocess
import sys
import zlib
from pathlib import Path

HERE = Path(__file__).resolve().parent
MUTATIONS = ("flip", "flip", "flip", "truncate", "extend", "pickle", "plant", "bad_json",
             "typed_json", "foreign", "link_file", "link_entry", "link_tmp", "fifo", "limit",
             "delete")
# What a case's process runs: prepare the volume as a render does, print a hash of what the
# kernels read. $MI_AMR_FUZZ_PLANT (Python run first, in the cases only, never in the setup)
# plants a bug to see the harness catch it: a change to the package's source would change the
# snapshot keys, so that no case read its entry.
CHILD = r"""
import hashlib, os, sys, warnings
exec(os.environ.get("MI_AMR_FUZZ_PLANT", ""))
import numpy as np
import drjit as dr
from mi_amr.kernels import prepared
warnings.simplefilter("ignore")
try:
    # As a render of the default scene (the basis blend) prepares it: its entry holds no
    # field values (tests/test_snapshot.py tampers with entries that hold them).
    how = prepared.LoadOptions(keep_fields=False)
    p = prepared.prepare_file(sys.argv[1], "a", "b", m=dr.llvm.ad, how=how)
    p.device.node_ranges(True)
    d = p.device
    h = hashlib.sha256()
    for name in ("brick_values", "brick_colors", "brick_table", "level_table",
                 "node_code_split", "node_box", "leaf_lo", "leaf_grids",
                 "node_ropes", "grid_offset", "level_geom"):
        h.update(np.ascontiguousarray(np.array(getattr(d, name))).tobytes())
    h.update(repr(sorted(p.value_ranges.items())).encode())
    h.update(np.asarray(d.node_ranges(True)).tobytes())
    print("RESULT ok", h.hexdigest(), "snapshot" in p.timings)
except BaseException as e:
    print(f"RESULT exception {type(e).__name__}: {str(e)[:300]}")
"""


class Payload:
    """A pickle that makes the folder ``path`` when it is loaded (it never should be)."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (os.mkdir, (self.path,))


def run_child(data: Path, cache: str, timeout: float, limit_gb: str | None = None,
              plant: bool = True):
    """``(status, detail)`` of preparing ``data`` with the cache ``cache`` in a new process."""
    env = dict(os.environ, MI_AMR_CACHE=cache, PYTHONPATH=os.pathsep.join(
        [str(HERE.parent), os.environ.get("PYTHONPATH", "")]))
    env.pop("MI_AMR_CACHE_GB", None)
    if not plant:
        env.pop("MI_AMR_FUZZ_PLANT", None)
    if limit_gb is not None:
        env["MI_AMR_CACHE_GB"] = limit_gb
    try:
        proc = subprocess.run([sys.executable, "-c", CHILD, str(data)], capture_output=True,
                              text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return "hang", f"no result within {timeout:g} s"
    result = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not result:
        return "crash", f"exit status {proc.returncode}: {proc.stderr.strip()[-500:]}"
    if "Traceback" in proc.stderr:
        return "traceback", proc.stderr.strip()[-500:]
    status, _, detail = result[-1][len("RESULT "):].partition(" ")
    return status, detail


def listing(folder: Path, skip=()) -> dict:
    """Every path under ``folder`` (links not followed, ``skip``ped names at the top left out)
    with what it is and its contents' hash."""
    out = {}
    for dirpath, dirs, files in os.walk(folder):
        if Path(dirpath) == folder:
            dirs[:] = [d for d in dirs if d not in skip]
            files = [f for f in files if f not in skip]
        for name in dirs + files:
            p = os.path.join(dirpath, name)
            if os.path.islink(p):
                out[p] = ("link", os.readlink(p))
            elif os.path.isfile(p):
                out[p] = ("file", hashlib.sha256(Path(p).read_bytes()).hexdigest())
            else:
                out[p] = ("dir",)
    return out


class Setup:
    """The small volume, the hash of its preparation without a cache, and a cache holding its
    one good entry (made once per run)."""

    def __init__(self, work: Path, timeout: float):
        from fuzz_inputs import small_volume

        self.data = work / "data" / "small.npz"
        self.data.parent.mkdir(parents=True)
        small_volume().save(self.data, overwrite=True)
        status, ref = run_child(self.data, "off", timeout, plant=False)
        self.pristine = work / "pristine"
        made, again = (run_child(self.data, str(self.pristine), timeout, plant=False)
                       for _ in range(2))
        if status != "ok" or made[0] != "ok" or again[1].split() != [ref.split()[0], "True"]:
            raise RuntimeError(f"cache fuzz setup failed: {status} {ref} {made} {again}")
        self.reference = ref.split()[0]
        (self.key,) = [p.name for p in self.pristine.iterdir()]


def mutate(case: Path, setup: Setup, rng: random.Random) -> dict:
    """Copy the pristine cache into ``case``/cache and damage it; returns what the check needs:
    ``cache``, ``outside`` (a folder links point into), ``sentinel`` (made by a loaded pickle),
    ``limit`` (``$MI_AMR_CACHE_GB`` or None), ``done`` (the mutations)."""
    cache, outside = case / "cache", case / "outside"
    shutil.copytree(setup.pristine, cache, symlinks=True)
    outside.mkdir()
    (outside / "precious.txt").write_text("the user's")
    (outside / "data").mkdir()
    (outside / "data" / "run.bin").write_bytes(bytes(range(256)) * 64)
    ctx = {"cache": cache, "outside": outside, "sentinel": case / "pwned", "limit": None,
           "done": [], "old": []}
    entry = cache / setup.key
    for _ in range(rng.randint(1, 3)):
        op = rng.choice(MUTATIONS)
        ctx["done"].append(op)
        _apply(op, entry, ctx, rng)
    return ctx


def _files(entry: Path) -> list:
    return sorted(p for p in entry.iterdir() if p.is_file() and not p.is_symlink()) \
        if entry.is_dir() and not entry.is_symlink() else []


def _apply(op: str, entry: Path, ctx: dict, rng: random.Random) -> None:  # noqa: C901
    cache, outside = ctx["cache"], ctx["outside"]
    files = _files(entry)
    # Half the time a file every render reads (most of the kd-tree's arrays are used only
    # while it is built: a change there changes no image).
    read = [f for f in files if f.name.startswith(("pool", "field", "table", "volume", "meta",
                                                    "ranges", "tree.node", "tree.leaf"))]
    target = rng.choice(read if read and rng.random() < 0.5 else files) if files else None
    if op in ("flip", "truncate", "extend") and target is not None:
        raw = bytearray(target.read_bytes())
        if op == "flip" and raw:
            start = min(len(raw) - 1, 128) if rng.random() < 0.5 else 0     # past a header
            for _ in range(rng.randint(1, 4)):
                raw[rng.randrange(start, len(raw))] ^= 1 << rng.randrange(8)
        elif op == "truncate":
            del raw[rng.randrange(len(raw) + 1):]
        else:
            raw += bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
        target.write_bytes(bytes(raw))
    elif op == "pickle":
        evil = pickle.dumps(Payload(ctx["sentinel"]))
        if entry.is_dir():
            (entry / "meta.pkl").write_bytes(evil)
        old = cache / ("%032x" % rng.getrandbits(128))
        ctx["old"].append(old.name)         # an entry of the previous format: the cache's
        old.mkdir()
        (old / "meta.pkl").write_bytes(evil)
        (old / "pool0.npy").write_bytes(b"\x93NUMPY" + evil)
    elif op == "plant" and entry.is_dir():
        name = rng.choice(("x.arr", "pool7.arr", "meta.json.1234", "notes", ".hidden"))
        (entry / name).write_bytes(bytes(rng.randrange(256) for _ in range(100)))
    elif op == "bad_json" and entry.is_dir():
        meta = entry / "meta.json"
        text = meta.read_bytes() if meta.is_file() else b""
        meta.unlink(missing_ok=True)
        meta.write_bytes(rng.choice((text[:rng.randrange(len(text) + 1)], b"[" * 50_000,
                                     b'{"kind": 1}\n{}', b"\xff\xfe\x00",
                                     text.replace(b'"format":2', b'"format":1e999'),
                                     b"9" * 5000 + b"\n{}")))
    elif op == "typed_json" and (entry / "meta.json").is_file():
        _retype(entry / "meta.json", rng)
    elif op == "foreign":
        (cache / "sim").mkdir(exist_ok=True)
        (cache / "sim" / "checkpoint.bin").write_bytes(b"\1" * 10_000)
        (cache / ("%032x" % rng.getrandbits(128))).mkdir()
        (cache / ".tmp-mine").mkdir(exist_ok=True)
        os.utime(cache / ".tmp-mine", (0, 0))
        (cache / "notes.txt").write_text("mine")
        ctx["limit"] = "0"          # the cache evicts all it may, when it writes an entry
        (entry / "meta.json").unlink(missing_ok=True)
    elif op == "link_file" and target is not None:
        target.unlink()
        target.symlink_to(outside / rng.choice(("precious.txt", "data/run.bin", "nowhere")))
    elif op == "link_entry" and entry.is_dir() and not entry.is_symlink():
        away = outside / "moved_entry"
        if not away.exists():
            shutil.move(str(entry), away)
            entry.symlink_to(away, target_is_directory=True)
    elif op == "link_tmp":
        marked = outside / "marked"
        if not marked.exists():             # a marked folder outside, a link to it inside
            marked.mkdir()
            for f in _files(entry):
                shutil.copy(f, marked / f.name)
        (cache / ".tmp-evil").unlink(missing_ok=True)
        (cache / ".tmp-evil").symlink_to(marked, target_is_directory=True)
        (cache / ".del-evil").unlink(missing_ok=True)
        (cache / ".del-evil").symlink_to(outside / "data", target_is_directory=True)
    elif op == "fifo" and target is not None:
        target.unlink()
        os.mkfifo(target)
    elif op == "limit":
        ctx["limit"] = rng.choice(("0", "0.000001", "-1", "nan", "lots"))
    elif op == "delete" and target is not None:
        target.unlink()


def _retype(meta: Path, rng: random.Random) -> None:
    """Change one value of ``meta.json``'s body into another type or range, and sign it
    anew (only the type checks can catch it)."""
    head, _, body = meta.read_bytes().partition(b"\n")
    try:
        parsed, header = json.loads(body), json.loads(head)
    except ValueError:
        return
    paths = []

    def walk(node, path):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, path + [k])
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, path + [i])
        paths.append(path)

    walk(parsed, [])
    path = rng.choice(paths[:-1] or [[]])
    if not path:
        return
    holder = parsed
    for step in path[:-1]:
        holder = holder[step]
    holder[path[-1]] = rng.choice((None, -1, 2 ** 70, 0.5, "x", [], {}, {"$array": "nope"},
                                   {"$tuple": 3}, True, "../../outside/precious.txt"))
    text = json.dumps(parsed).encode()
    header["crc32"] = zlib.crc32(text)
    meta.write_bytes(json.dumps(header).encode() + b"\n" + text)


def check(ctx: dict, setup: Setup, before: dict, timeout: float):
    """``(status, detail)`` of one case (see the module docstring)."""
    status, detail = run_child(setup.data, str(ctx["cache"]), timeout, ctx["limit"])
    if status != "ok":
        return status, detail
    if detail.split()[0] != setup.reference:
        return "wrong", "the preparation differs from one made without a cache"
    if ctx["sentinel"].exists():
        return "ran_code", "a pickle from the cache was loaded"
    after = _outside_cache(ctx)
    changed = sorted(p for p in set(before) | set(after) if before.get(p) != after.get(p))
    if changed:
        return "touched", f"changed outside the cache's own folders: {changed[:5]}"
    return "ok", "read back" if detail.split()[1] == "True" else "prepared afresh"


def _outside_cache(ctx: dict) -> dict:
    """What is not the cache's own: the outside folder, and everything in the cache folder
    but the entries, temporary and removed folders the cache made."""
    ours = [p.name for p in ctx["cache"].iterdir()
            if p.is_dir() and not p.is_symlink() and (p / ".mi_amr-snapshot").is_file()]
    return listing(ctx["outside"]) | listing(ctx["cache"], skip=ours + ctx["old"])


def cache_cases(work: Path, count: int, seed: int, setup: Setup):
    """``(case name, context, listing before)`` of ``count`` mutated caches."""
    for i in range(count):
        rng = random.Random(f"cache:{seed}:{i}")
        case = work / f"cache-{seed}-{i}"
        case.mkdir()
        ctx = mutate(case, setup, rng)
        yield f"cache seed {seed} case {i} ({', '.join(ctx['done'])})", ctx, \
            _outside_cache(ctx)
