"""The examples of the README and of the documentation's pages (docs/**/*.md) run as written.

Every fenced block preceded by a ``<!-- readme-test -->`` marker is run: ``python`` blocks by
this interpreter, ``bash`` blocks by bash with ``python`` meaning this interpreter. A marker may
say what the block needs (``<!-- readme-test: needs=shared,yt,vdb -->``); a block whose needs are
missing is skipped with the reason. A ``python`` or ``bash`` block that cannot run here (it
serves until stopped, or needs a SLURM cluster) says why in a ``<!-- readme-skip: WHY -->``
marker instead; a block with neither marker fails test03.

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
DOC_FILES = [ROOT / "README.md"] + sorted(p for p in (ROOT / "docs").rglob("*.md")
                                          if "_build" not in p.parts)
SHARED = ROOT.parent / "shared"
SYSTEM_PYTHON = "/usr/bin/python3"
WRITER = Path(__file__).with_name("vdb_writer.py")
MARKER = re.compile(r"<!-- readme-test(?::\s*(?P<opts>[^>]*?))?\s*-->\s*\n```(?P<lang>\w+)\n"
                    r"(?P<code>.*?)\n```", re.S)
FENCE = re.compile(r"^```(?P<lang>\w+)[ \t]*$", re.M)
SKIP = re.compile(r"<!-- readme-skip: \S[^>]*-->\s*$")
RUNNABLE = ("python", "bash")


def _name(path: Path) -> str:
    return str(path.relative_to(ROOT))


def doc_blocks(path: Path):
    """``(page, lang, needs, code, line)`` of every marked block of one page."""
    text = path.read_text()
    blocks = []
    for m in MARKER.finditer(text):
        opts = dict(o.split("=", 1) for o in (m["opts"] or "").split() if "=" in o)
        needs = [n for n in opts.get("needs", "").split(",") if n]
        blocks.append((_name(path), m["lang"], needs, m["code"],
                       text.count("\n", 0, m.start()) + 1))
    return blocks


BLOCKS = [b for page in DOC_FILES for b in doc_blocks(page)]
# The guides whose pages show no runnable example, and why (their workflows run elsewhere).
NOT_RUNNABLE = {"viewer.md": "the viewer serves until stopped; tests/test_viewer.py drives it "
                             "in chromium"}


def test_readme_has_examples():
    """The markers are found: a README edit that breaks them must not skip every example."""
    langs = [lang for page, lang, *_ in BLOCKS if page == "README.md"]
    assert langs.count("python") >= 4 and "bash" in langs


def test02_every_guide_runs_an_example():
    """Each guide page has at least one executed example (or is listed with the reason)."""
    pages = {p.name for p in (ROOT / "docs" / "guides").glob("*.md")}
    assert len(pages) >= 10, sorted(pages)
    runs = {Path(page).name for page, *_ in BLOCKS if page.startswith("docs/guides/")}
    assert sorted(pages - runs - set(NOT_RUNNABLE)) == []


def test03_every_code_block_is_run_or_says_why():
    """A python or bash block of the README or a page is run, or its skip marker says why."""
    unmarked = []
    for path in DOC_FILES:
        text = path.read_text()
        for m in FENCE.finditer(text):          # opening fences: a closing one names no language
            if m["lang"] not in RUNNABLE:
                continue
            before = text[:m.start()].rstrip("\n").rsplit("\n", 1)[-1]
            if not (before.startswith("<!-- readme-test") or SKIP.search(before)):
                unmarked.append(f"{_name(path)}:{text.count(chr(10), 0, m.start()) + 1}")
    assert unmarked == []


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


@pytest.mark.parametrize("page,lang,needs,code,line", BLOCKS,
                         ids=[f"{b[0]}:{b[4]}" for b in BLOCKS])
def test_readme_example(tmp_path, page, lang, needs, code, line):
    why = _missing(needs)
    if why:
        pytest.skip(f"{page} line {line} needs {why}")
    work = _workspace(tmp_path, needs)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if lang == "python":
        script = work / "example.py"
        script.write_text(code + "\n")
        args = [sys.executable, str(script)]
    elif lang == "bash":
        # `python` is this interpreter wherever it stands (also after `VAR=value`).
        bin_dir = tmp_path / "bin"
        bin_dir.mkdir()
        (bin_dir / "python").write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
        (bin_dir / "python").chmod(0o755)
        env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
        args = ["bash", "-euo", "pipefail", "-c", code]
    else:
        pytest.fail(f"{page} line {line}: cannot run a {lang!r} block")
    run = subprocess.run(args, cwd=work, env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, (f"{page} line {line} failed:\n{run.stdout[-3000:]}\n"
                                 f"{run.stderr[-3000:]}")
    for out in re.findall(r"(?:-o |write_bitmap\(\")([\w./]+)", code):
        assert (work / out).stat().st_size > 0, f"{page} line {line} did not write {out}"
