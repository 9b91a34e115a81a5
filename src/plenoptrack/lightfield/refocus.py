"""Shift-and-add refocusing of a light field, focal stacks and a focus (sharpness) metric.

Refocusing to the virtual image plane at ``alpha`` times the image distance ``s_i``
(``alpha = d / s_i``, ``docs/conventions.md``) samples every view at

    X = X' / alpha + U (1 - 1/alpha)

(positions on the microlens-array plane measured from the optical axis, ``U`` the view's
aperture position) and averages the views: each view is shifted by ``U (1 - 1/alpha)``
and the sum is magnified by ``1/alpha`` about the axis (the seed paper's eq. 1-2, with
the geometric definition of ``alpha``). In sensor pixels, the shift of view ``(u, v)``
is ``-(u, v) (s_i + f_ml) / f_ml (1 - 1/alpha)`` (column, row); it is converted to
spatial samples with the light field's sample geometry.

References
----------
"Development and uncertainty characterization of 3D particle location from perspective
shifted plenoptic images" (``seeds/001``), eq. 1-2, and Ng, R. (2005), "Fourier slice
photography", ACM Trans. Graph. 24(3).
"""

from __future__ import annotations

import math
from typing import Literal

import numba
import numpy as np
from scipy import ndimage

from ..camera import CameraSpec
from ..errors import CameraSpecError, ImageSizeError, SettingsError
from .decode import LightField
from .views import _view_selection

__all__ = ["refocus", "focal_stack", "refocus_shifts", "view_shift_per_u", "sharpness",
           "best_focus_depth"]


def _check(lf, camera) -> None:
    if not isinstance(lf, LightField):
        raise TypeError(f"lf must be a LightField; got {type(lf).__name__}")
    if not isinstance(camera, CameraSpec):
        raise CameraSpecError(f"camera must be a CameraSpec; got {type(camera).__name__}")
    if tuple(camera.sensor_shape_px) != tuple(lf.sensor_shape_px):
        raise ImageSizeError(
            f"the light field was decoded from a {lf.sensor_shape_px[0]} x {lf.sensor_shape_px[1]} "
            f"sensor but the camera description has {camera.sensor_shape_px[0]} x "
            f"{camera.sensor_shape_px[1]}; use the matching camera description")


def view_shift_per_u(camera: CameraSpec, alpha) -> np.ndarray:
    """Sensor-pixel displacement, on the microlens-image-centre scale, of a point's image
    per unit ``u`` (or ``v``) for an object whose image lies at ``alpha``.

    Equals ``-(s_i + f_ml) / f_ml * (1 - 1/alpha)``: positive (towards larger column /
    ``s``) for ``alpha < 1`` (behind the focal plane), negative in front, 0 at focus.
    Divide by the light field's sample spacing for spatial samples per ``u``.
    """
    alpha = np.asarray(alpha, dtype=float)
    s_i = camera.image_distance_mm
    f_ml = camera.microlens_focal_length_um * 1e-3
    return -(s_i + f_ml) / f_ml * (1.0 - 1.0 / alpha)


def refocus_shifts(lf: LightField, camera: CameraSpec, alpha: float) -> np.ndarray:
    """Position of a point's image in every view relative to the central view.

    Parameters
    ----------
    lf : LightField
    camera : CameraSpec
    alpha : float
        Refocus parameter of the point's image plane.

    Returns
    -------
    shifts : (n_v, n_u, 2) float64 ndarray
        ``(dt, ds)`` in spatial samples: a point imaged at plane ``alpha`` appears in
        view ``(iv, iu)`` displaced by ``shifts[iv, iu]`` (before the ``1/alpha``
        magnification about the axis). Refocusing to ``alpha`` samples view ``(iv, iu)``
        at these offsets.
    """
    _check(lf, camera)
    k = view_shift_per_u(camera, alpha)  # sensor px per unit u
    d_rc = np.stack(np.broadcast_arrays(lf.v[:, None] * k, lf.u[None, :] * k), axis=-1)
    inv = np.linalg.inv(lf.step_matrix)
    return d_rc @ inv.T  # (row, col) -> (t, s)


@numba.njit(parallel=True, cache=True, nogil=True)
def _shift_add(data, mask, sel, dts, ax_t, ax_s, inv_alpha, out):  # pragma: no cover - compiled
    n_t = out.shape[0]
    n_s = out.shape[1]
    src_t = data.shape[2]
    src_s = data.shape[3]
    n_w = sel.shape[0]
    for t in numba.prange(n_t):
        acc = np.zeros(n_s)
        wsum = np.zeros(n_s)
        tb = ax_t + (t - ax_t) * inv_alpha
        for k in range(n_w):
            iv = sel[k, 0]
            iu = sel[k, 1]
            tq = tb + dts[k, 0]
            t0 = int(math.floor(tq))
            if t0 < -1 or t0 > src_t - 1:
                continue
            ft = tq - t0
            for s in range(n_s):
                sq = ax_s + (s - ax_s) * inv_alpha + dts[k, 1]
                s0 = int(math.floor(sq))
                if s0 < -1 or s0 > src_s - 1:
                    continue
                fs = sq - s0
                for dt in range(2):
                    ti = t0 + dt
                    if ti < 0 or ti >= src_t:
                        continue
                    wt = ft if dt else 1.0 - ft
                    for ds in range(2):
                        si = s0 + ds
                        if si < 0 or si >= src_s:
                            continue
                        w = wt * (fs if ds else 1.0 - fs) * mask[ti, si]
                        acc[s] += w * data[iv, iu, ti, si]
                        wsum[s] += w
        for s in range(n_s):
            out[t, s] = acc[s] / wsum[s] if wsum[s] > 1e-6 else 0.0


def _resolve_alpha(camera: CameraSpec, alpha, depth_mm) -> float:
    if (alpha is None) == (depth_mm is None):
        raise SettingsError("give exactly one of alpha or depth_mm")
    if alpha is None:
        alpha = float(camera.alpha_for_depth(float(depth_mm)))
    alpha = float(alpha)
    if not (math.isfinite(alpha) and alpha > 0):
        raise SettingsError(f"alpha must be a positive finite number; got {alpha!r}"
                         + ("" if depth_mm is None else f" (from depth_mm={depth_mm!r})"))
    return alpha


def _selection(lf: LightField, views) -> np.ndarray:
    if isinstance(views, str) and views == "all":
        show = lf.valid_fraction > 0
    else:
        show = _view_selection(lf, views)
    sel = np.argwhere(show).astype(np.int64)
    if len(sel) == 0:
        raise SettingsError("no views selected for refocusing (all valid fractions are 0 or the "
                         "selection is empty)")
    return sel


def _refocus_one(lf, camera, alpha, sel, mask, out) -> np.ndarray:
    shifts = refocus_shifts(lf, camera, alpha)
    dts = np.ascontiguousarray(shifts[sel[:, 0], sel[:, 1]])
    ax_s, ax_t = lf.axis_st
    _shift_add(lf.data, mask, sel, dts, ax_t, ax_s, 1.0 / alpha, out)
    return out


def refocus(lf: LightField, camera: CameraSpec, *, alpha: float | None = None,
            depth_mm: float | None = None, views: str | np.ndarray = "valid") -> np.ndarray:
    """Refocus a light field to one plane by shift-and-add.

    Parameters
    ----------
    lf : LightField
        Decoded light field (ideally flat-fielded).
    camera : CameraSpec
        Nominal camera (``s_i``, ``f_ml``, pixel pitch); its sensor must match ``lf``.
    alpha : float, optional
        Refocus parameter ``d / s_i`` (1 = nominal focal plane).
    depth_mm : float, optional
        Object depth ``z`` (mm, 0 at the focal plane, positive away from the camera);
        converted with ``camera.alpha_for_depth``. Give exactly one of ``alpha`` and
        ``depth_mm``.
    views : {"valid", "all"} or (n_v, n_u) bool ndarray
        Views to add: ``"valid"`` uses ``lf.view_mask``, ``"all"`` every view with a
        non-zero valid fraction.

    Returns
    -------
    image : (n_t, n_s) float32 ndarray
        Refocused image on the light field's spatial grid: the mean over views of the
        (bilinearly interpolated, spatially masked) samples; 0 where no view contributes.
        Pixel ``(t, s)`` shows the plane point whose magnified (by ``1/alpha`` about the
        axis) position is sample ``(t, s)``.

    Examples
    --------
    >>> import pandas as pd
    >>> from plenoptrack import preset
    >>> from plenoptrack.lightfield import decode
    >>> from plenoptrack.simulate import make_optics, render_frame, render_white
    >>> camera = preset("small")
    >>> optics = make_optics(camera, seed=0)
    >>> particle = pd.DataFrame({"x": [0.0], "y": [0.0], "z": [8.0], "diameter": [0.5]})
    >>> lf = decode(render_frame(optics, particle, seed=1), optics.true_grid,
    ...             white=render_white(optics, seed=2))
    >>> image = refocus(lf, camera, depth_mm=8.0)
    >>> image.shape == lf.view_shape
    True
    """
    _check(lf, camera)
    alpha = _resolve_alpha(camera, alpha, depth_mm)
    sel = _selection(lf, views)
    mask = lf.spatial_mask.astype(np.float32)
    out = np.empty(lf.view_shape, dtype=np.float32)
    return _refocus_one(lf, camera, alpha, sel, mask, out)


def focal_stack(lf: LightField, camera: CameraSpec, depths_mm, *, views: str | np.ndarray = "valid",
                progress: bool = False) -> np.ndarray:
    """Refocus to many depths.

    Parameters
    ----------
    lf : LightField
    camera : CameraSpec
    depths_mm : (n,) array_like
        Object depths ``z``, mm.
    views : see :func:`refocus`
    progress : bool
        Show a progress bar.

    Returns
    -------
    stack : (n, n_t, n_s) float32 ndarray
        ``stack[k]`` is ``refocus(lf, camera, depth_mm=depths_mm[k])``.
    """
    _check(lf, camera)
    depths = np.atleast_1d(np.asarray(depths_mm, dtype=float))
    if depths.ndim != 1:
        raise SettingsError(f"depths_mm must be 1-D; got shape {depths.shape}")
    alphas = [_resolve_alpha(camera, None, z) for z in depths]
    sel = _selection(lf, views)
    mask = lf.spatial_mask.astype(np.float32)
    stack = np.empty((len(depths), *lf.view_shape), dtype=np.float32)
    if not progress:
        for k, a in enumerate(alphas):
            _refocus_one(lf, camera, a, sel, mask, stack[k])
        return stack
    from rich.progress import Progress

    with Progress(transient=True) as bar:
        task = bar.add_task("refocusing", total=len(alphas))
        for k, a in enumerate(alphas):
            _refocus_one(lf, camera, a, sel, mask, stack[k])
            bar.update(task, advance=1)
    return stack


def sharpness(images: np.ndarray, *, center: tuple[float, float] | None = None,
              half_width: int | None = None,
              method: Literal["laplacian", "gradient"] = "laplacian") -> np.ndarray:
    """Focus metric of one image or a stack, optionally in a square window.

    Parameters
    ----------
    images : (..., n_t, n_s) ndarray
        One image or a stack (e.g. from :func:`focal_stack`).
    center : (s, t), optional
        Window centre in spatial samples (rounded); requires ``half_width``.
    half_width : int, optional
        The window spans ``center +- half_width`` samples (clipped to the image).
    method : {"laplacian", "gradient"}
        ``"laplacian"``: variance of the discrete Laplacian; ``"gradient"``: mean squared
        Sobel gradient magnitude (gradient energy).

    Returns
    -------
    float64 ndarray of shape ``images.shape[:-2]`` (0-d for one image)
        Larger is sharper.
    """
    img = np.asarray(images, dtype=np.float64)
    if img.ndim < 2:
        raise SettingsError(f"images must be at least 2-D (..., t, s); got shape {img.shape}")
    if (center is None) != (half_width is None):
        raise SettingsError("give both center and half_width, or neither")
    lead = img.shape[:-2]
    img = img.reshape(-1, *img.shape[-2:])
    if center is not None:
        hw = int(half_width)
        if hw < 1:
            raise SettingsError(f"half_width must be >= 1; got {half_width!r}")
        s_c, t_c = (int(round(c)) for c in center)
        # one extra sample each side so the filter sees real neighbours at the window edge
        t0, t1 = max(t_c - hw - 1, 0), min(t_c + hw + 2, img.shape[1])
        s0, s1 = max(s_c - hw - 1, 0), min(s_c + hw + 2, img.shape[2])
        if t1 - t0 < 3 or s1 - s0 < 3:
            raise SettingsError(f"window centred at (s, t) = {center} lies outside the "
                             f"{img.shape[1]} x {img.shape[2]} image")
        img = img[:, t0:t1, s0:s1]
    if method == "laplacian":
        f = np.stack([ndimage.laplace(im, mode="nearest") for im in img])
        crop = f[:, 1:-1, 1:-1]
        out = crop.reshape(len(f), -1).var(axis=1)
    elif method == "gradient":
        g = np.stack([ndimage.sobel(im, 0, mode="nearest") ** 2 + ndimage.sobel(im, 1, mode="nearest") ** 2
                      for im in img])
        out = g[:, 1:-1, 1:-1].reshape(len(g), -1).mean(axis=1)
    else:
        raise SettingsError(f"method must be 'laplacian' or 'gradient'; got {method!r}")
    return out.reshape(lead)


def best_focus_depth(stack: np.ndarray, depths_mm, *, center: tuple[float, float] | None = None,
                     half_width: int | None = None,
                     method: Literal["laplacian", "gradient"] = "laplacian") -> float:
    """Depth of maximum :func:`sharpness` in a focal stack, refined by a parabola through
    the peak and its two neighbours (mm; the plain peak depth at the stack ends)."""
    depths = np.asarray(depths_mm, dtype=float)
    stack = np.asarray(stack)
    if stack.ndim != 3 or len(depths) != len(stack):
        raise SettingsError(f"stack must be (n, n_t, n_s) with n = len(depths_mm) = {len(depths)}; "
                         f"got shape {stack.shape}")
    curve = sharpness(stack, center=center, half_width=half_width, method=method)
    k = int(np.argmax(curve))
    if 0 < k < len(curve) - 1:
        y0, y1, y2 = curve[k - 1: k + 2]
        den = y0 - 2 * y1 + y2
        if den < 0:
            off = 0.5 * (y0 - y2) / den
            step = 0.5 * (depths[k + 1] - depths[k - 1])
            return float(depths[k] + np.clip(off, -1, 1) * step)
    return float(depths[k])
