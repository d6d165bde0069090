"""Encoding a movie's frames as an MP4 with imageio and the ffmpeg that the imageio-ffmpeg
wheel brings (no system ffmpeg needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_amr.core.atomic import replacing
from mi_amr.errors import AMRError


def _srgb8(image: np.ndarray) -> np.ndarray:
    """A linear float image as 8-bit sRGB (for EXR frames)."""
    x = np.clip(image, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255).astype(np.uint8)


def _read(path: Path) -> np.ndarray:
    if path.suffix.lower() == ".exr":
        import mitsuba as mi

        return _srgb8(np.array(mi.Bitmap(str(path)), dtype=np.float32)[..., :3])
    import imageio.v2 as imageio

    return np.asarray(imageio.imread(path))[..., :3]


def encode_mp4(frames, mp4, fps: int = 24, *, force: bool = False) -> Path:
    """Write the image files ``frames`` (in order) to ``mp4`` (H.264), atomically."""
    mp4 = Path(mp4)
    if mp4.exists() and not force:
        raise AMRError(f"--mp4 {mp4}: file exists; pass --force to replace it")
    if mp4.suffix.lower() != ".mp4":
        raise AMRError(f"--mp4 {mp4}: the movie must end in .mp4")
    if not fps >= 1:
        raise AMRError(f"--fps must be >= 1, got {fps}")
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the encoder binary)
    except ImportError:
        raise AMRError("--mp4 needs imageio and imageio-ffmpeg: pip install 'mi_amr[movie]'") \
            from None
    frames = [Path(f) for f in frames]
    if not frames:
        raise AMRError("--mp4: there are no frames to encode")
    with replacing(mp4) as tmp:
        with imageio.get_writer(str(tmp), fps=fps, codec="libx264", quality=8,
                                macro_block_size=2, ffmpeg_log_level="error") as writer:
            for f in frames:
                writer.append_data(_read(f))
    return mp4
