"""Encoding a movie's frames as an MP4 with imageio and the ffmpeg that the imageio-ffmpeg
wheel brings (no system ffmpeg needed)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from mi_amr.core.atomic import replacing
from mi_amr.errors import AMRError

MAX_FPS = 1000      # frames a second in the MP4 (H.264 players stop far below)


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


def check_mp4(mp4, fps, *, force: bool = False) -> Path:
    """The ``--mp4`` and ``--fps`` values, checked before any frame is rendered."""
    mp4 = Path(mp4)
    if mp4.suffix.lower() != ".mp4":
        raise AMRError(f"--mp4 {mp4}: the movie must end in .mp4")
    if mp4.exists() and not force:
        raise AMRError(f"--mp4 {mp4}: file exists; pass --force to replace it")
    check_fps(fps)
    return mp4


def check_fps(fps) -> None:
    """``--fps``: a whole number from 1 to :data:`MAX_FPS`."""
    if isinstance(fps, bool) or not isinstance(fps, int) or not 1 <= fps <= MAX_FPS:
        raise AMRError(f"--fps must be a whole number from 1 to {MAX_FPS}, got {fps!r}")


def encode_mp4(frames, mp4, fps: int = 24, *, force: bool = False) -> Path:
    """Write the image files ``frames`` (an iterable, in order; all of one size) to ``mp4``
    (H.264), atomically: a frame of another size is one :class:`AMRError` naming it, and
    leaves no file behind."""
    mp4 = check_mp4(mp4, fps, force=force)
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401  (the encoder binary)
    except ImportError:
        raise AMRError("--mp4 needs imageio and imageio-ffmpeg: pip install 'mi_amr[movie]'") \
            from None
    frames = iter(frames)
    first = next(frames, None)
    if first is None:
        raise AMRError("--mp4: there are no frames to encode")
    with replacing(mp4) as tmp:
        mismatch = None
        with imageio.get_writer(str(tmp), fps=fps, codec="libx264", quality=8,
                                macro_block_size=2, ffmpeg_log_level="error") as writer:
            shape = None
            for f in itertools.chain([first], frames):
                image = _read(Path(f))
                if shape is not None and image.shape != shape:
                    mismatch = (f, image.shape, shape)
                    break
                shape = image.shape
                writer.append_data(image)
        # Raised after the writer has closed normally: raised inside, ffmpeg went on to write
        # the temporary file after it had been removed.
        if mismatch is not None:
            f, have, want = mismatch
            raise AMRError(f"--mp4: {f} is {have[1]}x{have[0]}, the frames before it "
                           f"{want[1]}x{want[0]}; render the frames again with --force")
    return mp4
