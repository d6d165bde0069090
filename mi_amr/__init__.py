"""mi_amr: exact and fast isosurfaces of adaptive-mesh-refinement volumes in Mitsuba 3.

The data model (:class:`AMRVolume`), readers (:func:`load`; :func:`from_yt` for a dataset yt
has opened, importing yt only when called), the kd-tree (:class:`KDTree`) and derived fields
(:func:`derive`) need only NumPy: ``import mi_amr`` imports neither Dr.Jit nor Mitsuba.
:func:`trace` (ray queries, Dr.Jit), :func:`load_scene` and :func:`scene` (the scene made for a
data file, a dict for ``mi.load_dict``; Mitsuba), and :func:`show` and :func:`explore`
(Jupyter: an inline image, the viewer in an output cell) are imported on first use.
The Mitsuba integrator ``amr_iso`` is registered by :func:`register` (called on import when a
Mitsuba variant is already set).

The package's layers, each importing only those before it (``tests/test_layers.py``): ``errors``,
``params``, ``tolerances``; ``core`` (NumPy); ``readers`` and ``synthetic``; ``kernels``
(Dr.Jit); ``plugin`` (Mitsuba); ``workflows``; ``evaluation``; ``cli``.
"""

import sys as _sys

from mi_amr.errors import AMRError
from mi_amr.core.volume import AMRVolume, Grid
from mi_amr.core.kdtree import KDTree
from mi_amr.core.derive import derive
from mi_amr.readers import load
from mi_amr.readers.ytsource import from_yt
from mi_amr.synthetic import datasets

_LAZY = {"trace": "mi_amr.kernels.trace", "TraceResult": "mi_amr.kernels.trace",
         "load_scene": "mi_amr.plugin.scene", "scene": "mi_amr.plugin.autoscene",
         "show": "mi_amr.workflows.notebook", "explore": "mi_amr.workflows.notebook"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'mi_amr' has no attribute {name!r}")


def register():
    """Register the ``amr_iso`` integrator for the active Mitsuba variant (again after a switch)."""
    from mi_amr.plugin.integrator import register as _register

    _register()


def _register_if_variant_set():
    mi = _sys.modules.get("mitsuba")
    if mi is not None and mi.variant() is not None:
        register()


_register_if_variant_set()

__all__ = ["AMRError", "AMRVolume", "Grid", "KDTree", "load", "from_yt", "derive", "datasets",
           "register", "trace", "TraceResult", "load_scene", "scene", "show", "explore"]
__version__ = "0.1.0"
