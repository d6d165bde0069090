"""The README's examples run as written.

Every fenced block preceded by a ``<!-- readme-test -->`` marker is run: ``python`` blocks by
this interpreter, ``bash`` blocks by bash with ``python`` meaning this interpreter. A marker may
say what the block needs (``<!-- readme-test: needs=shared,yt,vdb -->``); a block whose needs are
missing is skipped with the reason.

Each block runs in a fresh folder laid out like the repository (``scenes_xml`` linked in, an
empty ``out/``, and ``../shared`` linked to the real one), so the README's relative paths work
and nothing in the checkout is overwritten. ``needs=vdb`` blocks find a ``flow.vdb`` there,
written by OpenVDB itself (``tests/vdb_writer.py``): a vector grid ``v`` at two voxel sizes.
"""

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
SYSTEM_PYTHON = "/usr/bin/python3"
WRITER = Path(__file__).with_name("vdb_writer.py")
MARKER = re.compile(r"<!-- readme-test(?::\s*(?P<opts>[^>]*?))?\s*-->\s*\n```(?P<lang>\w+)\n"
                    r"(?P<code>.*?)\n```", re.S)


def readme_blocks():
    """``(lang, needs, code, line)`` of every marked block of README.md."""
    text = (ROOT / "README.md").read_text()
    blocks = []
    for m in MARKER.finditer(text):
        opts = dict(o.split("=", 1) for o in (m["opts"] or "").split() if "=" in o)
        needs = [n for n in opts.get("needs", "").split(",") if n]
        blocks.append((m["lang"], needs, m["code"], text.count("\n", 0, m.start()) + 1))
    return blocks


BLOCKS = readme_blocks()


def test_readme_has_examples():
    """The markers are found: a README edit that breaks them must not skip every example."""
    langs = [lang for lang, *_ in BLOCKS]
    assert langs.count("python") >= 4 and "bash" in langs


def _openvdb_ok() -> bool:
    code = "try:\n import pyopenvdb\nexcept ImportError:\n import openvdb"
    try:
        run = subprocess.run([SYSTEM_PYTHON, "-c", code], capture_output=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return run.returncode == 0


def _missing(needs):
    """Why a block cannot run here, or None."""
    for need in needs:
        if need == "shared" and not (SHARED / "data" / "amrex").is_dir():
            return f"{SHARED / 'data' / 'amrex'} is absent"
        if need == "yt" and importlib.util.find_spec("yt") is None:
            return "yt is not installed"
        if need == "vdb" and not _openvdb_ok():
            return f"{SYSTEM_PYTHON} cannot import OpenVDB (python3-openvdb)"
    return None


def _workspace(tmp_path, needs) -> Path:
    """A folder laid out like the repository for one block to run in."""
    work = tmp_path / "repo"
    (work / "out").mkdir(parents=True)
    (work / "scenes_xml").symlink_to(ROOT / "scenes_xml", target_is_directory=True)
    if SHARED.is_dir():
        (tmp_path / "shared").symlink_to(SHARED, target_is_directory=True)
    if "vdb" in needs:
        grids = [{"type": "vec3s", "name": "v", "voxel_size": 0.125, "lo": [0, 0, 0],
                  "shape": [8, 8, 8], "tolerance": -1},
                 {"type": "vec3s", "name": "v", "voxel_size": 0.0625, "lo": [4, 4, 4],
                  "shape": [8, 8, 8], "tolerance": -1}]
        (tmp_path / "spec.json").write_text(json.dumps({str(work / "flow.vdb"): grids}))
        run = subprocess.run([SYSTEM_PYTHON, str(WRITER), str(tmp_path / "spec.json")],
                             capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stderr
    return work


@pytest.mark.parametrize("lang,needs,code,line", BLOCKS,
                         ids=[f"README.md:{b[3]}" for b in BLOCKS])
def test_readme_example(tmp_path, lang, needs, code, line):
    why = _missing(needs)
    if why:
        pytest.skip(f"README.md line {line} needs {why}")
    work = _workspace(tmp_path, needs)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if lang == "python":
        script = work / "example.py"
        script.write_text(code + "\n")
        args = [sys.executable, str(script)]
    elif lang == "bash":
        python = re.sub(r"(?m)^python ", f"{sys.executable} ", code)
        args = ["bash", "-euo", "pipefail", "-c", python]
    else:
        pytest.fail(f"README.md line {line}: cannot run a {lang!r} block")
    run = subprocess.run(args, cwd=work, env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, (f"README.md line {line} failed:\n{run.stdout[-3000:]}\n"
                                 f"{run.stderr[-3000:]}")
    for out in re.findall(r"(?:-o |write_bitmap\(\")([\w./]+)", code):
        assert (work / out).stat().st_size > 0, f"README.md line {line} did not write {out}"
