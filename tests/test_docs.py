"""The documentation site (docs/): it builds with Sphinx's -W, its links and images resolve, its
pages speak to users in the present tense, and its reference pages follow the code.

The site is built once per run into a temporary folder, exactly as ``make docs`` builds it. The
examples of the pages are run by tests/test_readme.py.
"""

import html
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest

sphinx = pytest.importorskip("sphinx", reason="the docs extra (pip install -e '.[docs]') "
                                              "is not installed")

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
sys.path.insert(0, str(DOCS / "_ext"))
import amr_docs  # noqa: E402

# Wording that dates a page by the development that led to it; history goes to CHANGELOG.md.
HISTORY = ["earlier code", "previously", "used to", "was measured", "were measured", "this stop",
           "last stop", "stop's", "no longer", "the code before", "in the run before",
           "the run before", r"issue \d+"]


def _pages():
    """The sources users read: the README and every page under docs/ (not the build)."""
    pages = [ROOT / "README.md"]
    pages += sorted(p for p in DOCS.rglob("*") if p.suffix in (".md", ".rst")
                    and "_build" not in p.parts)
    return pages


def _build(src: Path, out: Path, extra=()):
    """``sphinx-build -W`` of ``src`` into ``out``; returns the completed process."""
    return subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b",
                           "html", *extra, str(src), str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site as ``make docs`` builds it (fresh doctrees, so every warning shows)."""
    out = tmp_path_factory.mktemp("docs") / "html"
    run = _build(DOCS, out, ["-E"])
    assert run.returncode == 0, f"sphinx -W failed:\n{run.stdout[-4000:]}\n{run.stderr[-4000:]}"
    return out


class _Refs(HTMLParser):
    """The ids, links and image sources of one HTML page."""

    def __init__(self):
        super().__init__()
        self.ids, self.links, self.images = set(), [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if a.get("id"):
            self.ids.add(a["id"])
        if tag == "a" and a.get("href"):
            self.links.append(a["href"])
        if tag == "img" and a.get("src"):
            self.images.append(a["src"])


def _parse(path: Path) -> _Refs:
    refs = _Refs()
    refs.feed(path.read_text(encoding="utf-8"))
    return refs


def test01_the_site_builds_with_warnings_as_errors(site):
    for page in ["index", "performance", "design", "gallery", "reference/parameters",
                 "reference/cli", "reference/api", "guides/installation", "guides/first-render",
                 "guides/your-data", "guides/methods", "guides/volume-rendering",
                 "guides/viewer", "guides/movies", "guides/python", "guides/aovs",
                 "guides/troubleshooting"]:
        assert (site / f"{page}.html").is_file(), page


def test02_every_internal_link_and_image_of_the_site_resolves(site):
    parsed = {p: _parse(p) for p in site.rglob("*.html")}
    broken = []
    for page, refs in parsed.items():
        for ref in refs.links + refs.images:
            parts = urlsplit(ref)
            if parts.scheme or parts.netloc:
                continue                                   # external: not checked offline
            target = (page.parent / unquote(parts.path)).resolve() if parts.path else page
            if not target.exists():
                broken.append(f"{page.relative_to(site)}: {ref}")
            elif parts.fragment and target.suffix == ".html":
                ids = parsed[target].ids if target in parsed else _parse(target).ids
                if unquote(parts.fragment) not in ids:
                    broken.append(f"{page.relative_to(site)}: {ref} (no such anchor)")
    assert broken == []


MD_LINK = re.compile(r"!?\[[^\]]*\]\((?P<target>[^)\s]+)\)")


def test03_every_relative_link_and_image_of_the_sources_exists():
    """The README (read on its own, outside Sphinx) and the pages: each relative link or image
    names a file that exists."""
    missing = []
    for page in _pages():
        text = page.read_text()
        for m in MD_LINK.finditer(text):
            target = m["target"]
            if urlsplit(target).scheme or target.startswith("#"):
                continue
            path = (page.parent / unquote(target.split("#")[0])).resolve()
            if not path.exists():
                missing.append(f"{page.relative_to(ROOT)}: {target}")
    assert missing == []


def test04_no_page_is_written_as_development_history(site):
    pattern = re.compile("|".join(HISTORY), re.I)
    found = []
    for page in _pages():
        for n, line in enumerate(page.read_text().splitlines(), 1):
            if pattern.search(line):
                found.append(f"{page.relative_to(ROOT)}:{n}: {line.strip()}")
    # The generated pages too: docstrings and the parameter table end up in them.
    for page in site.rglob("*.html"):
        text = html.unescape(re.sub(r"<[^>]+>", " ", page.read_text(encoding="utf-8")))
        for m in pattern.finditer(text):
            found.append(f"{page.relative_to(site)}: ...{text[max(0, m.start() - 60):m.end()]}")
    assert found == []


def test05_the_reference_pages_hold_every_parameter_and_command(site):
    from mi_amr import params
    from mi_amr.cli import _parser

    text = html.unescape((site / "reference" / "parameters.html").read_text(encoding="utf-8"))
    for p in params.TABLE:
        assert f'<span class="pre">{p.name}</span>' in text, p.name
    cli = html.unescape((site / "reference" / "cli.html").read_text(encoding="utf-8"))
    for name, _usage, _help, rows in amr_docs.cli_commands(_parser("python -m mi_amr")):
        assert f'id="cli-{name}"' in cli, name
        for invocation, *_ in rows:
            assert invocation.split()[0] in cli, (name, invocation)


def _mini_site(tmp_path, directive: str, modules=None):
    """A one-page Sphinx project that uses only ``directive`` of docs/_ext/amr_docs.py;
    ``modules`` (name -> source) are written beside it, importable while it builds."""
    src = tmp_path / "src"
    src.mkdir()
    for name, text in (modules or {}).items():
        (src / f"{name}.py").write_text(text)
    (src / "conf.py").write_text(f"import sys\nsys.path.insert(0, {str(DOCS / '_ext')!r})\n"
                                 f"sys.path.insert(0, {str(src)!r})\n"
                                 "extensions = ['amr_docs']\n")
    (src / "index.rst").write_text(f"Reference\n=========\n\n{directive}\n")
    return src


def _build_in_process(src: Path, out: Path) -> str:
    from sphinx.application import Sphinx

    app = Sphinx(str(src), str(src), str(out), str(out / ".doctrees"), "html",
                 status=None, warning=None, freshenv=True, warningiserror=True)
    app.build()
    return html.unescape((out / "index.html").read_text(encoding="utf-8"))


def test06_a_parameter_added_to_params_appears_on_the_page(tmp_path):
    """Adding a row to a parameter table is all it takes: the directive reads the table
    (mi_amr.params.TABLE, or the one its argument names) when the page is built."""
    src = _mini_site(tmp_path, ".. amr-params::\n\n.. amr-params:: test06_params:TABLE", {
        "test06_params": "from mi_amr.params import TABLE as BASE, Param\n"
                         "TABLE = BASE + (Param('zz_new_param', 'float', 2.5, 'a parameter "
                         "added by ``test06``', lo=0.0, hi=10.0, traversable=True),)\n"})
    page = _build_in_process(src, tmp_path / "out")
    first, second = page.split("</table>")[:2]
    assert "zz_new_param" not in first and "shininess" in first and "shininess" in second
    row = second[second.index("zz_new_param"):]
    row = re.sub(r"<[^>]+>", " ", row[:row.index("</tr>")])
    assert row.split() == ["zz_new_param", "float", "2.5", "0", "to", "10", "yes", "a",
                           "parameter", "added", "by", "test06"]


def test07_a_flag_added_to_the_cli_appears_on_the_page(tmp_path):
    """A flag added to a parser appears in its command's section: the directive reads the
    parsers (mi_amr.cli's, or the factory its argument names) when the page is built."""
    src = _mini_site(tmp_path, ".. amr-cli:: test07_cli:parser", {
        "test07_cli": "from mi_amr.cli import _parser\n\n\n"
                      "def parser(prog):\n"
                      "    out = _parser(prog)\n"
                      "    sub = next(a for a in out._actions if hasattr(a, 'choices') and "
                      "a.choices)\n"
                      "    sub.choices['render'].add_argument('--zz-new-flag', type=int, "
                      "default=7, help='a flag added by test07')\n"
                      "    return out\n"})
    page = _build_in_process(src, tmp_path / "out")
    section = page[page.index('id="cli-render"'):]
    section = section[:section.index("</section>")]
    assert "--zz-new-flag ZZ_NEW_FLAG" in section and "a flag added by test07" in section


def test08_the_param_rows_show_defaults_ranges_and_choices():
    from mi_amr import params

    rows = {r[0]: r for r in amr_docs.param_rows()}
    assert len(rows) == len(params.TABLE)
    assert rows["isovalue"][2] == "required" and rows["isovalue"][4] == "yes"
    assert rows["method"][3] == "``exact``, ``bisect``, ``adaptive``, ``uniform``"
    assert rows["leaf_cells"][1:4] == ("integer", "4", "2 to 256")
    assert rows["band_width"][3] == ">= 1e-30"
    assert rows["shadows"][2] == "true" and rows["color_field"][2] == "none"
    assert amr_docs.escape_bars("|grad f| in ``a|b``") == "\\|grad f\\| in ``a|b``"
