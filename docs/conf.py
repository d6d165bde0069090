"""Sphinx configuration of mi_amr's documentation (``make docs``: docs/_build/html).

The pages are MyST Markdown (guides, performance, design, gallery) and reStructuredText (the
reference pages, whose tables come from the local extension ``_ext/amr_docs.py``: the
integrator's parameters from :mod:`mi_amr.params`, the command line from the argparse parsers in
:mod:`mi_amr.cli`). Images come straight from ``reference/readme/``.
"""

import os
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(DOCS / "_ext"))
os.environ.setdefault("MI_AMR_CACHE", "off")

import mi_amr  # noqa: E402

project = "mi_amr"
author = "the mi_amr developers"
copyright = "the mi_amr developers"
release = version = mi_amr.__version__

extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon", "amr_docs"]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]
myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3
# Options and code are quoted as typed: no curly quotes or dashes made from "--".
smartquotes = False

autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "undoc-members": False}

try:
    import furo  # noqa: F401
    html_theme = "furo"
except ImportError:      # the docs extra brings furo; alabaster ships with Sphinx
    html_theme = "alabaster"
html_title = f"mi_amr {release}"
html_static_path = []
