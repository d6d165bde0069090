"""Reading volume mode's 2D transfer function (``transfer2d``, ``transfer2d_blobs``) into a
:class:`~mi_amr.core.transfer2d.Transfer2D`: a ``.npy`` table with NumPy, a ``.png`` / ``.exr``
image with ``mi.Bitmap``, or the blobs rasterized on the host."""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np

from mi_amr.core.transfer2d import Transfer2D, from_blobs, load_npy
from mi_amr.errors import AMRError

IMAGE_SUFFIXES = (".png", ".exr")


def host_transfer2d(opt):
    """The checked 2D transfer function of the options ``opt``, or None without one."""
    if opt.transfer2d_blobs is not None:
        return from_blobs(opt.transfer2d_blobs)
    if opt.transfer2d is None:
        return None
    path = resolve(opt.transfer2d)
    table = load_npy(path) if path.suffix.lower() == ".npy" else read_image(path)
    return Transfer2D(table, *opt.transfer2d_range, source=f"{path} ('transfer2d')")


def resolve(name: str) -> Path:
    """``name`` resolved like ``filename`` (Mitsuba's file resolver: relative to the scene
    file), with a suffix the reader knows."""
    path = Path(str(mi.file_resolver().resolve(name)))
    if not path.is_file():
        raise AMRError(f"amr_iso: parameter 'transfer2d': {name} not found (looked for {path})")
    if path.suffix.lower() not in (".npy",) + IMAGE_SUFFIXES:
        raise AMRError(f"amr_iso: parameter 'transfer2d': {path} must be a .npy, .png or .exr "
                       f"file")
    return path


def read_image(path: Path) -> np.ndarray:
    """The opacity table of an image: its alpha channel if it has one, else its first channel,
    as stored (8- and 16-bit integers scaled to [0, 1], no sRGB decoding: a grey level of 128
    is an opacity of 128/255); rows flipped, since an image's top row is the highest
    |grad f| (as in the histogram's picture)."""
    try:
        bitmap = mi.Bitmap(str(path))
    except RuntimeError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else "unknown error"
        raise AMRError(f"{path} ('transfer2d'): cannot read the image ({first})") from None
    pixels = np.array(bitmap)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    channel = pixels.shape[-1] - 1 if bitmap.has_alpha() else 0
    table = pixels[..., channel]
    if np.issubdtype(table.dtype, np.integer):
        table = table.astype(np.float64) / np.iinfo(table.dtype).max
    return np.ascontiguousarray(table[::-1], dtype=np.float64)
