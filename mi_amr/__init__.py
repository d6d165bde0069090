"""mi_amr: exact and fast isosurfaces of adaptive-mesh-refinement volumes in Mitsuba 3.

The data model (:class:`AMRVolume`), readers (:func:`load`; :func:`from_yt` for a dataset yt
has opened, importing yt only when called), the kd-tree (:class:`KDTree`) and
derived fields (:func:`derive`) need only NumPy. The Mitsuba integrator ``amr_iso`` is registered
by :func:`register` (called on import when a Mitsuba variant is already set).
"""

from .errors import AMRError
from .volume import AMRVolume, Grid
from .kdtree import KDTree
from .readers import load
from .readers.ytsource import from_yt
from .derive import derive
from .rays import TraceResult, trace
from . import datasets



def register():
    """Register the ``amr_iso`` integrator for the active Mitsuba variant (again after a switch)."""
    from .integrator import register as _register
    _register()


def _register_if_variant_set():
    import sys
    mi = sys.modules.get("mitsuba")
    if mi is not None and mi.variant() is not None:
        register()


_register_if_variant_set()

__all__ = ["AMRError", "AMRVolume", "Grid", "KDTree", "load", "from_yt", "derive", "datasets",
           "register", "trace"]
__version__ = "0.1.0"
