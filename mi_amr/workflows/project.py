"""Where a checkout of mi_amr keeps its scenes and reference images.

The commands that render the repository's scenes (``demo``, ``data``, ``bench``, ``reference``)
need the checkout's ``scenes_xml/`` and ``reference/`` folders. They are found from
``$MI_AMR_HOME``, else from the current folder or one above it, else from the source tree this
package was imported from (an editable install). Nothing is ever looked for or written inside
an installed package.
"""

from __future__ import annotations

import os
from pathlib import Path

from mi_amr.errors import AMRError


def _is_checkout(path: Path) -> bool:
    return (path / "scenes_xml").is_dir() and (path / "pyproject.toml").is_file()


def checkout() -> Path:
    """The checkout's top folder (holding ``scenes_xml/`` and ``pyproject.toml``)."""
    home = os.environ.get("MI_AMR_HOME")
    if home:
        if not _is_checkout(Path(home)):
            raise AMRError(f"MI_AMR_HOME={home}: not a checkout of mi_amr (no scenes_xml/ and "
                           f"pyproject.toml there)")
        return Path(home).resolve()
    here = Path.cwd().resolve()
    for folder in (here, *here.parents):
        if _is_checkout(folder):
            return folder
    source = Path(__file__).resolve().parents[2]
    if _is_checkout(source) and "site-packages" not in source.parts:
        return source
    raise AMRError("this command uses the scenes of a checkout of mi_amr: run it inside one, "
                   "or set MI_AMR_HOME to one")


def scenes_dir() -> Path:
    """``scenes_xml/`` of the checkout."""
    return checkout() / "scenes_xml"


def data_dir() -> Path:
    """``scenes_xml/data/``: the data files the scenes refer to (made by ``mi_amr data``)."""
    return scenes_dir() / "data"


def reference_dir() -> Path:
    """``reference/``: the exact reference images and hit buffers."""
    return checkout() / "reference"


def shared_dir() -> Path:
    """``../shared`` beside the checkout (real plotfiles, papers); may not exist."""
    return checkout().parent / "shared"


def ensure_scene_data(verbose: bool = True) -> list:
    """Make the data files of the checkout's scenes that are missing (see
    :func:`mi_amr.synthetic.scenes.scene_data`)."""
    from mi_amr.synthetic.scenes import scene_data

    return scene_data(data_dir(), verbose=verbose)
