"""Writing a movie's files: every file appears whole or not at all (written under a temporary
name in its folder, then renamed), and nothing is replaced without ``force``."""

from __future__ import annotations

import os
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


def existing_frames(out_dir, fmt: str) -> dict:
    """The frames already in ``out_dir``: ``{index: path}`` (the folder listed once, not a
    look-up per frame)."""
    found = {}
    prefix, suffix = "frame_", f".{fmt}"
    with os.scandir(out_dir) as entries:
        for entry in entries:
            name = entry.name
            digits = name[len(prefix):-len(suffix)]
            if name.startswith(prefix) and name.endswith(suffix) and digits.isdigit():
                index = int(digits)
                if name == frame_path(out_dir, index, fmt).name:
                    found[index] = Path(entry.path)
    return found


def image_size(path):
    """``(width, height)`` of a PNG (from its header) or EXR frame; None when it cannot be
    read as one."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".png":
            with open(path, "rb") as f:
                head = f.read(24)
            if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
                return None
            return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        import mitsuba as mi

        return tuple(int(v) for v in mi.Bitmap(str(path)).size())
    except (OSError, RuntimeError):
        return None


def write_bytes_atomic(path, data: bytes) -> None:
    """Write ``data`` to ``path`` whole or not at all."""
    with replacing(path) as tmp:
        Path(tmp).write_bytes(data)


def write_image_atomic(path, image: np.ndarray, what: str = "frame") -> None:
    """Write a linear RGBA (or RGB) float image ``(H, W, 4 or 3)`` as 8-bit sRGB PNG or float
    EXR (by the suffix), whole or not at all; alpha stays alpha (the film's coverage, as
    ``render`` writes it). A write that fails raises :class:`AMRError`, one line naming the
    file and calling it ``what``."""
    import mitsuba as mi

    fmt = mi.Bitmap.PixelFormat.RGBA if image.shape[-1] == 4 else mi.Bitmap.PixelFormat.RGB
    bitmap = mi.Bitmap(np.ascontiguousarray(image, dtype=np.float32), pixel_format=fmt)
    png = Path(path).suffix.lower() == ".png"
    if png:
        bitmap = bitmap.convert(fmt, mi.Struct.Type.UInt8, srgb_gamma=True)
    try:
        # Encoded in memory, the bytes written by Python: Mitsuba's file writer does not
        # report a write the disk refuses (a full disk left an empty file in the frame's place).
        stream = mi.MemoryStream()
        bitmap.write(stream, mi.Bitmap.FileFormat.PNG if png else mi.Bitmap.FileFormat.OpenEXR)
        write_bytes_atomic(path, stream.raw_buffer())
    except (RuntimeError, OSError) as e:
        # A full disk: one line per frame (the frame is not there; a rerun renders it).
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise AMRError(f"{path}: cannot write the {what} ({first})") from None
