"""mi_amr: exact and fast isosurfaces of adaptive-mesh-refinement volumes in Mitsuba 3.

The data model (:class:`AMRVolume`), readers (:func:`load`), the kd-tree (:class:`KDTree`) and
derived fields (:func:`derive`) need only NumPy. The Mitsuba integrator ``amr_iso`` is registered
by :func:`register` (called on import when a Mitsuba variant is already set).
"""

from .errors import AMRError
from .volume import AMRVolume, Grid
from .kdtree import KDTree
from .readers import load
from .derive import derive
from . import datasets

__all__ = ["AMRError", "AMRVolume", "Grid", "KDTree", "load", "derive", "datasets"]
__version__ = "0.1.0"
