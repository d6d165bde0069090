"""Writing a movie's files: every file appears whole or not at all (written under a temporary
name in its folder, then renamed), and nothing is replaced without ``force``."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from mi_amr.core.atomic import replacing
from mi_amr.errors import AMRError

FORMATS = ("png", "exr")


def frame_path(out_dir, index: int, fmt: str = "png") -> Path:
    """``DIR/frame_00042.png``."""
    return Path(out_dir) / f"frame_{index:05d}.{fmt}"


def check_out_dir(out_dir) -> Path:
    """The output folder, made if missing; an :class:`AMRError` when it is a file or cannot be
    written (checked before any work starts)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise AMRError(f"-o {out}: is a file, not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=out, prefix=".mi_amr-write-test-", delete=True)
        probe.close()
    except OSError as e:
        raise AMRError(f"-o {out}: cannot write there ({e.strerror or e})") from None
    return out


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to ``path`` whole or not at all."""
    with replacing(path) as tmp:
        Path(tmp).write_bytes(data)


def write_image_atomic(path, image: np.ndarray) -> None:
    """Write a linear RGBA (or RGB) float image ``(H, W, 4 or 3)`` as 8-bit sRGB PNG or float
    EXR (by the suffix), whole or not at all; alpha stays alpha (the film's coverage, as
    ``render`` writes it)."""
    import mitsuba as mi

    fmt = mi.Bitmap.PixelFormat.RGBA if image.shape[-1] == 4 else mi.Bitmap.PixelFormat.RGB
    bitmap = mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32), pixel_format=fmt)
    if Path(path).suffix.lower() == ".png":
        bitmap = bitmap.convert(fmt, mi.Struct.Type.UInt8, srgb_gamma=True)
    with replacing(path) as tmp:
        bitmap.write(str(tmp))
