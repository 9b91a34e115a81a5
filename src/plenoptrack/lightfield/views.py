"""Perspective (sub-aperture) views of a decoded light field.

A perspective view ``E_uv(s, t) = L[v, u, t, s]`` collects, from every microlens, the
pixel at the same offset ``(u, v)`` from the microlens-image centre: the scene seen
through one small region of the main-lens aperture (``docs/conventions.md``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_path, write_tiff
from ..errors import SettingsError
from .decode import LightField

__all__ = ["perspective_views", "view", "view_mosaic", "scale_to_uint8",
           "write_views_tiff", "write_mosaic_png"]


def _check_lf(lf) -> LightField:
    if not isinstance(lf, LightField):
        raise TypeError(f"lf must be a LightField (see plenoptrack.lightfield.decode); "
                        f"got {type(lf).__name__}")
    return lf


def perspective_views(lf: LightField) -> np.ndarray:
    """All perspective views.

    Parameters
    ----------
    lf : LightField

    Returns
    -------
    views : (n_v, n_u, n_t, n_s) float32 ndarray
        ``views[iv, iu]`` is the view at ``(u, v) = (lf.u[iu], lf.v[iv])``. This is
        ``lf.data`` itself (no copy): do not write into it.
    """
    return _check_lf(lf).data


def view(lf: LightField, u: float, v: float) -> np.ndarray:
    """Perspective view at angular coordinates ``(u, v)`` (sensor pixels), ``(n_t, n_s)``."""
    return _check_lf(lf).view(u, v)


def view_mosaic(lf: LightField, *, views: str | np.ndarray = "all", gap: int = 0,
                fill: float = 0.0) -> np.ndarray:
    """Tile all perspective views into one image.

    Parameters
    ----------
    lf : LightField
    views : {"all", "valid"} or (n_v, n_u) bool ndarray
        Which views to show; the others are filled with ``fill``.
    gap : int
        Pixels of ``fill`` between neighbouring tiles.
    fill : float
        Value of gaps and hidden views.

    Returns
    -------
    mosaic : (n_v * (n_t + gap) - gap, n_u * (n_s + gap) - gap) float32 ndarray
        View ``(iv, iu)`` occupies rows ``iv * (n_t + gap) ...`` and columns
        ``iu * (n_s + gap) ...``: ``v`` grows downwards, ``u`` to the right, as on the sensor.
    """
    lf = _check_lf(lf)
    show = _view_selection(lf, views)
    gap = int(gap)
    if gap < 0:
        raise SettingsError(f"gap must be >= 0; got {gap}")
    n_v, n_u, n_t, n_s = lf.data.shape
    tiles = np.full((n_v, n_t + gap, n_u, n_s + gap), fill, dtype=np.float32)
    tiles[:, :n_t, :, :n_s] = lf.data.transpose(0, 2, 1, 3)
    if not show.all():
        tiles.transpose(0, 2, 1, 3)[~show] = fill
    mosaic = tiles.reshape(n_v * (n_t + gap), n_u * (n_s + gap))
    if gap:
        mosaic = np.ascontiguousarray(mosaic[:-gap, :-gap])
    return mosaic


def _view_selection(lf: LightField, views) -> np.ndarray:
    if isinstance(views, str):
        if views == "all":
            return np.ones((lf.n_v, lf.n_u), dtype=bool)
        if views == "valid":
            return lf.view_mask
        raise SettingsError(f"views must be 'all', 'valid' or a boolean (n_v, n_u) array; got {views!r}")
    sel = np.asarray(views)
    if sel.shape != (lf.n_v, lf.n_u) or sel.dtype != bool:
        raise SettingsError(f"views must be a boolean array of shape ({lf.n_v}, {lf.n_u}); "
                         f"got {sel.dtype} array of shape {sel.shape}")
    return sel


def scale_to_uint8(image: np.ndarray, *, percentiles: tuple[float, float] = (0.5, 99.5),
                   mask: np.ndarray | None = None) -> np.ndarray:
    """Scale an image linearly to uint8 between two percentiles of its values.

    Parameters
    ----------
    image : (rows, cols) ndarray
    percentiles : (float, float)
        Values at these percentiles map to 0 and 255 (clipped beyond).
    mask : (rows, cols) bool ndarray, optional
        Pixels whose values set the percentiles (default: all finite pixels).

    Returns
    -------
    (rows, cols) uint8 ndarray
    """
    image = np.asarray(image, dtype=np.float32)
    sel = np.isfinite(image) if mask is None else (np.asarray(mask, bool) & np.isfinite(image))
    values = image[sel]
    if values.size > 1_000_000:  # percentiles of a regular subsample are plenty
        values = values[:: values.size // 1_000_000]
    if values.size == 0:
        return np.zeros(image.shape, dtype=np.uint8)
    lo, hi = np.percentile(values, percentiles)
    if not hi > lo:
        hi = lo + 1.0
    out = (image - lo) * np.float32(255.0 / (hi - lo))
    np.clip(out, 0, 255, out=out)
    out[~np.isfinite(out)] = 0
    return np.rint(out).astype(np.uint8)


def write_views_tiff(path: str | Path, lf: LightField, *, views: str | np.ndarray = "all") -> Path:
    """Write perspective views as a multi-page float32 TIFF, atomically.

    Parameters
    ----------
    path : str or Path
        Output ``.tif`` file.
    lf : LightField
    views : {"all", "valid"} or (n_v, n_u) bool ndarray
        Views to write, in row-major ``(v, u)`` order (``v`` slowest).

    Returns
    -------
    Path
        The path written. Page ``k`` holds the ``k``-th selected view, ``(n_t, n_s)``.
    """
    lf = _check_lf(lf)
    sel = _view_selection(lf, views)
    stack = lf.data[sel]  # (n_selected, n_t, n_s)
    return write_tiff(path, stack, compression=None)


def write_mosaic_png(path: str | Path, lf: LightField, *, views: str | np.ndarray = "all",
                     gap: int = 2, percentiles: tuple[float, float] = (0.5, 99.5)) -> Path:
    """Write :func:`view_mosaic` as an 8-bit greyscale PNG, atomically.

    Grey levels are scaled between the given percentiles of the shown views' values.
    """
    from PIL import Image

    lf = _check_lf(lf)
    sel = _view_selection(lf, views)
    mosaic = view_mosaic(lf, views=sel, gap=gap, fill=np.nan)
    img = scale_to_uint8(mosaic, percentiles=percentiles)
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(img).save(tmp, format="PNG")
    return path
