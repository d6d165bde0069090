"""Where the volume sits in the scene: ``scene_from_volume`` (the integrator's ``to_world``)
and its inverse, as opaque kernel inputs that ``mi.traverse`` may change between frames."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_amr import tolerances as tol
from mi_amr.errors import AMRError
from mi_amr.kernels.device import backend_of, opaque_floats
from mi_amr.plugin import bridge


class VolumeFrame:
    """``scene_from_volume`` maps the volume's world space into the scene (the value
    ``mi.traverse`` shows as ``integrator.to_world``); ``to_scene`` and ``to_volume`` are the
    transforms the kernels read, rebuilt from it by :meth:`refresh`, and ``host`` its matrix
    (float64, 4 x 4)."""

    def __init__(self, to_world=None):
        matrix = np.eye(4) if to_world is None else _host(to_world)
        self.scene_from_volume = mi.Transform4f(_checked(matrix).astype(np.float32))
        self.refresh()

    def refresh(self) -> None:
        """Check the transform (after a change through ``mi.traverse``) and rebuild both
        directions from it on the host (float64 inverse), as opaque values. Built the same way
        every time, so the kernels traced with them are the same every time."""
        matrix = _checked(_host(self.scene_from_volume))
        # (Kept: reading a transform assigned as literals runs a kernel of their values.)
        self.host = matrix
        self.to_scene = _transform(matrix)
        self.to_volume = _transform(np.linalg.inv(matrix))

    def scale(self) -> float:
        """The smallest stretch of a volume-space length in the scene."""
        return float(np.linalg.norm(_host(self.to_scene)[:3, :3], axis=0).min())

    def ray_to_volume(self, m, o, d):
        """A scene ray ``(o, d)`` in the volume's world space, as kernel arrays (``d`` keeps its
        length change: ``t`` means the same on both sides)."""
        return bridge.to_kernel3(m, self.to_volume @ o), bridge.to_kernel3(m, self.to_volume @ d)


def _host(transform) -> np.ndarray:
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4)


def _transform(matrix):
    """A Mitsuba transform of ``matrix``; in vectorised variants each entry its own opaque
    variable from aligned memory (entries of equal value stay apart, see
    :func:`~mi_amr.kernels.device.opaque_floats`)."""
    if not bridge.vectorised():
        return mi.Transform4f(matrix.astype(np.float32))
    m = backend_of(mi.Float)
    t = mi.Transform4f(mi.Matrix4f(*(opaque_floats(m, [x]) for x in matrix.ravel())))
    dr.make_opaque(t)
    return t


def _checked(matrix):
    if not np.all(np.isfinite(matrix)) or abs(np.linalg.det(matrix[:3, :3])) < tol.SINGULAR_DET:
        raise AMRError("amr_iso: parameter 'to_world' must be an invertible transform")
    return matrix
