"""Reading and writing the files of the plenoptrack file contract.

Raw images are single-channel uint16 TIFF (a multi-page TIFF holds several frames);
tables are Parquet, or CSV when the path ends in ``.csv``. Every writer is atomic: it
writes a temporary file beside the target and renames it, so a failed run never leaves a
half-written result. Every reader turns a bad file into an :class:`InputFileError` that
names the file and says what to do.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

from .errors import ImageSizeError, InputFileError

__all__ = [
    "atomic_path", "atomic_write_text", "read_raw", "read_frames", "count_frames",
    "write_tiff", "read_table", "write_table", "check_image_shape",
]


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The parent folder is created if needed. If the body raises, the temporary file is
    removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def _open_tiff(path: Path):
    import tifffile

    if not path.exists():
        raise InputFileError(f"{path}: file not found; check the path")
    if path.is_dir():
        raise InputFileError(f"{path}: is a folder, expected a TIFF image file")
    try:
        return tifffile.TiffFile(path)
    except (tifffile.TiffFileError, ValueError, OSError, IndexError, KeyError) as exc:
        raise InputFileError(f"{path}: not a readable TIFF image ({exc}); "
                             "save raw images as single-channel uint16 TIFF") from None


def read_frames(path: str | Path) -> np.ndarray:
    """Read every frame of a raw TIFF.

    Parameters
    ----------
    path : str or Path
        Single- or multi-page single-channel uint16 TIFF.

    Returns
    -------
    frames : (n_frames, rows, cols) uint16 ndarray
        Raw sensor counts; pixel (row, col) centres at integer coordinates.
    """
    path = Path(path)
    with _open_tiff(path) as tif:
        try:
            data = tif.asarray()
        except Exception as exc:  # tifffile raises many kinds on truncated data
            raise InputFileError(f"{path}: TIFF data could not be read, the file may be "
                                 f"truncated ({type(exc).__name__}: {exc})") from None
    if data.dtype != np.uint16:
        raise InputFileError(f"{path}: raw images must be uint16; got {data.dtype}. "
                             "Convert with e.g. tifffile.imwrite(path, img.astype('uint16'))")
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3:
        raise InputFileError(f"{path}: expected a single-channel image or a stack of them; "
                             f"got an array of shape {data.shape}")
    return data


def read_raw(path: str | Path, *, frame: int = 0) -> np.ndarray:
    """Read one raw frame, ``(rows, cols)`` uint16, from a TIFF file."""
    frames = read_frames(path)
    if not -len(frames) <= frame < len(frames):
        raise InputFileError(f"{path}: has {len(frames)} frame(s); frame {frame} does not exist")
    return frames[frame]


def count_frames(path: str | Path) -> int:
    """Number of frames (pages) in a TIFF without reading the pixels."""
    path = Path(path)
    with _open_tiff(path) as tif:
        return len(tif.series[0].shape) == 3 and tif.series[0].shape[0] or 1


def write_tiff(path: str | Path, image: np.ndarray, *, compression: str | None = "zlib") -> Path:
    """Write a ``(rows, cols)`` image or ``(n, rows, cols)`` stack as TIFF, atomically."""
    import tifffile

    image = np.asarray(image)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, image, compression=compression, photometric="minisblack")
    return Path(path)


def check_image_shape(image: np.ndarray, expected: tuple[int, int], *, source: str = "image",
                      what: str = "the camera description") -> None:
    """Raise :class:`ImageSizeError` if ``image.shape[-2:]`` differs from ``expected``."""
    if tuple(image.shape[-2:]) != tuple(expected):
        raise ImageSizeError(
            f"{source}: image is {image.shape[-2]} x {image.shape[-1]} pixels but {what} "
            f"expects {expected[0]} x {expected[1]}; use the matching camera or calibration")


def read_table(path: str | Path) -> pd.DataFrame:
    """Read a Parquet table, or CSV when the path ends in ``.csv``."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: table not found; check the path")
    try:
        if path.suffix.lower() == ".csv":
            return pd.read_csv(path)
        return pd.read_parquet(path)
    except Exception as exc:
        kind = "CSV" if path.suffix.lower() == ".csv" else "Parquet"
        raise InputFileError(f"{path}: not a readable {kind} table ({type(exc).__name__}: {exc})") from None


def write_table(df: pd.DataFrame, path: str | Path) -> Path:
    """Write ``df`` atomically as Parquet, or CSV when the path ends in ``.csv``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".csv":
            df.to_csv(tmp, index=False)
        else:
            df.to_parquet(tmp, index=False)
    return path
