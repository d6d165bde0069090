"""Saving an image of any size with the kernels of one film size: the image is rendered in
tiles of that size, each through the part of the view's perspective frustum it covers.

Mitsuba compiles a kernel for each film size (the film's size and crop are literals in the
traced program), while the camera's field of view and principal point are opaque inputs. A
tile of ``tile`` pixels at pixel ``(x0, y0)`` of a ``size`` image is the same camera with a
narrower field of view and a shifted principal point (:func:`tile_camera`), so every tile,
whatever the image's size, runs the kernels of the one film size.

Pixels are in image space: ``x`` to the right, ``y`` down, ``(0, 0)`` the top left corner, as
Mitsuba's film and NumPy's ``image[y, x]`` index them. The reconstruction filter spreads each
sample over the pixels within its radius, so tiles overlap by ``margin`` pixels on each side
and only their inner part is kept: a kept pixel has every sample around it that a render of
the whole image gives it (only the image's own border pixels also see samples from beyond
it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Tile:
    """One tile: its top left corner ``(x0, y0)`` in the image's pixels (may lie outside the
    image), and the image window ``[x_lo, x_hi) x [y_lo, y_hi)`` taken from it."""

    x0: int
    y0: int
    x_lo: int
    x_hi: int
    y_lo: int
    y_hi: int

    def taken(self) -> tuple:
        """``(rows, columns)`` slices of the tile's image that go into the image."""
        return (slice(self.y_lo - self.y0, self.y_hi - self.y0),
                slice(self.x_lo - self.x0, self.x_hi - self.x0))


def margin(filter_radius: float) -> int:
    """Pixels a tile's edge loses to the filter: a pixel's centre ``i + 0.5`` needs every
    sample within ``filter_radius`` of it, inside the tile."""
    return max(0, math.ceil(filter_radius - 0.5))


def layout(size, tile, edge: int) -> list:
    """The tiles of ``tile = (tw, th)`` pixels that cover an image of ``size = (w, h)``, each
    keeping its inner part (``edge`` pixels from each side left out), in rows from the top."""
    (w, h), (tw, th) = size, tile
    sx, sy = tw - 2 * edge, th - 2 * edge
    if sx < 1 or sy < 1:
        raise ValueError(f"a tile of {tw}x{th} keeps nothing with a margin of {edge}")
    return [Tile(i * sx - edge, j * sy - edge, i * sx, min((i + 1) * sx, w),
                 j * sy, min((j + 1) * sy, h))
            for j in range(math.ceil(h / sy)) for i in range(math.ceil(w / sx))]


def tile_camera(fov: float, principal, size, tile, corner) -> tuple:
    """``(x_fov, (px, py))`` of the camera that renders the tile of ``tile`` pixels whose top
    left corner is pixel ``corner`` of the ``size`` image a camera of horizontal field of
    view ``fov`` (degrees) and principal point offset ``principal`` (Mitsuba's
    ``principal_point_offset_x/y``, fractions of the film's width and height) renders.

    The tile's frustum is the image's, cut: the same angle per pixel (``tan`` of half the
    field of view scales with the width), and the principal point moved so that the tile's
    pixel ``(i, j)`` looks along the image's pixel ``corner + (i, j)``."""
    (w, h), (tw, th), (x0, y0), (px, py) = size, tile, corner, principal
    half = math.tan(math.radians(fov) / 2) * tw / w
    return (math.degrees(2 * math.atan(half)),
            ((tw - w + 2 * x0 + 2 * px * w) / (2 * tw), (th - h + 2 * y0 + 2 * py * h) / (2 * th)))
