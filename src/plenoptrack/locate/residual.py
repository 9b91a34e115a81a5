"""Particles hidden by others: a second search with the located particles divided out.

A particle whose image overlaps a brighter-contrast or larger neighbour's in most views
gives no region of its own there: the segmentation sees one merged region, the
clustering one particle. Once the neighbours are located and their images fitted
(:func:`~plenoptrack.locate.perspective.refine_particles`), their model
(:mod:`~plenoptrack.locate.refine`: a product of blurred discs, one per particle and
view, or an ellipse where a particle's image is elongated) says how much of the
back-light each view pixel would receive without the hidden particle. Dividing the
light field by it leaves the hidden particle's shadow where its image stands free of
theirs (iterative particle reconstruction, IPR, for shadow images).
Where a located particle blocks most of the light (model transmission below
``floor``) nothing behind it can be seen: those pixels are set to the view's background
level, so neither the located particle nor a half-hidden one reads as dark there.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from ..lightfield import LightField
from .refine import EDGE_PX, _edge_argument, _half_erfc

__all__ = ["transmission_model", "residual_light_field", "divide_out_particles"]


@numba.njit(cache=True, inline="always")
def _box(s, t, r, edge, n_t, n_s):  # pragma: no cover - compiled
    """Pixel box ``(i0, i1, j0, j1)`` (inclusive) an image of radius ``r`` centred on
    ``(s, t)`` darkens, rim blur of the wider edge width ``edge`` included."""
    reach = r + 4.0 * edge
    return (max(0, int(math.floor(t - reach))), min(n_t - 1, int(math.ceil(t + reach))),
            max(0, int(math.floor(s - reach))), min(n_s - 1, int(math.ceil(s + reach))))


@numba.njit(cache=True, inline="always")
def _multiply_image(out, s, t, a, b, angle, c, w_s, w_t):  # pragma: no cover - compiled
    """``out *= 1 - c D`` over the image's box (``out`` one view): ``D`` the blurred
    ellipse of semi-axes ``a >= b`` (view pixels) whose long axis makes ``angle``
    (radians, from ``s`` toward ``t``) centred on ``(s, t)``, a disc when ``a == b``;
    edge widths ``w_s`` and ``w_t`` along ``s`` and ``t``.

    An ellipse is the disc of radius ``a`` in coordinates turned onto its axes and
    stretched by ``a / b`` across them (the edge widths with them)."""
    edge = max(w_s, w_t)
    i0, i1, j0, j1 = _box(s, t, a, edge, out.shape[0], out.shape[1])
    cos, sin, stretch = math.cos(angle), math.sin(angle), a / b
    w_l = math.sqrt((w_s * cos) ** 2 + (w_t * sin) ** 2)            # along the long axis
    w_c = math.sqrt((w_s * sin) ** 2 + (w_t * cos) ** 2) * stretch  # across it, stretched
    edge = max(w_l, w_c)
    # erfc is within 6e-5 of 2 or 0 beyond 4 edge widths of the rim:
    # only the rim's band is evaluated
    inner, outer = max(a - 4.0 * edge, 0.0) ** 2, (a + 4.0 * edge) ** 2
    for i in range(i0, i1 + 1):
        for j in range(j0, j1 + 1):
            along = cos * (j - s) + sin * (i - t)
            across = (cos * (i - t) - sin * (j - s)) * stretch
            rho2 = along * along + across * across
            if rho2 >= outer:
                continue
            if rho2 <= inner:
                out[i, j] *= 1.0 - c
            else:
                x = _edge_argument(along, across, math.sqrt(rho2), a, w_l, w_c)[0]
                out[i, j] *= 1.0 - c * _half_erfc(x, math.exp(-x * x))


@numba.njit(cache=True)
def _divide_out(data, view_rc, pred, axes, contrast, edge, floor, background,
                has_background):  # pragma: no cover - compiled
    """In place: each modelled view of ``data`` (n_v, n_u, n_t, n_s) divided by the
    particles' transmission, pixels below ``floor`` set to the view's background;
    ``axes`` (P, 3) each image's semi-axes and angle (:func:`_multiply_image`).

    Only the particles' boxes are visited: a view-sized transmission buffer holds 1
    everywhere between particles' boxes, and each pixel is put back to 1 once divided,
    so a pixel where boxes overlap is divided once, by the product of all its discs.
    """
    n_t, n_s = data.shape[2], data.shape[3]
    trans = np.ones((n_t, n_s), dtype=np.float32)
    for v in range(view_rc.shape[0]):
        if not has_background[v]:
            continue
        view = data[view_rc[v, 0], view_rc[v, 1]]
        for p in range(pred.shape[0]):
            s, t = pred[p, v, 0], pred[p, v, 1]
            if np.isfinite(s) and np.isfinite(t) and axes[p, 1] > 0.0 and contrast[p] > 0.0:
                _multiply_image(trans, s, t, axes[p, 0], axes[p, 1], axes[p, 2], contrast[p],
                               edge[p, 0], edge[p, 1])
        bg = background[v]
        for p in range(pred.shape[0]):
            s, t = pred[p, v, 0], pred[p, v, 1]
            if not (np.isfinite(s) and np.isfinite(t) and axes[p, 1] > 0.0
                    and contrast[p] > 0.0):
                continue
            i0, i1, j0, j1 = _box(s, t, axes[p, 0], max(edge[p, 0], edge[p, 1]), n_t, n_s)
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    tr = trans[i, j]
                    if tr == 1.0:   # outside every disc, or divided already
                        continue
                    x = view[i, j]
                    if tr < floor:
                        if np.isfinite(x):
                            view[i, j] = bg
                    else:
                        view[i, j] = x / tr
                    trans[i, j] = 1.0


@numba.njit(cache=True)
def _transmission(n_t, n_s, pred, axes, contrast, edge, out):  # pragma: no cover - compiled
    """Product over particles of ``1 - c D`` in each view: ``pred`` (P, V, 2) image
    centres ``(s, t)``, ``axes`` (P, 3) semi-axes and angle (:func:`_multiply_image`),
    ``contrast`` (P,); into ``out`` (V, n_t, n_s), filled with 1 first; ``edge`` (P, 2)
    edge widths ``(w_s, w_t)``."""
    for v in range(out.shape[0]):
        out[v] = 1.0
        for p in range(pred.shape[0]):
            s, t = pred[p, v, 0], pred[p, v, 1]
            if np.isfinite(s) and np.isfinite(t) and axes[p, 1] > 0.0 and contrast[p] > 0.0:
                _multiply_image(out[v], s, t, axes[p, 0], axes[p, 1], axes[p, 2], contrast[p],
                               edge[p, 0], edge[p, 1])


def _edge_widths(edge, n: int) -> np.ndarray:
    """``edge`` (a float, or (n, 2) widths) as (n, 2) contiguous float64 widths."""
    widths = np.asarray(edge, dtype=np.float64)
    if widths.ndim == 0:
        widths = np.full((n, 2), float(widths))
    if widths.shape != (n, 2):
        raise ValueError(f"edge must be a float or ({n}, 2) widths; got shape {widths.shape}")
    return np.ascontiguousarray(widths)


def _image_axes(radius: np.ndarray, axes: np.ndarray | None) -> np.ndarray:
    """(P, 3) contiguous semi-axes and angle of each image: ``axes`` (P, 3), or discs of
    ``radius`` (P,) when None."""
    if axes is None:
        radius = np.asarray(radius, dtype=np.float64)
        return np.ascontiguousarray(np.c_[radius, radius, np.zeros_like(radius)])
    axes = np.ascontiguousarray(axes, dtype=np.float64)
    if axes.ndim != 2 or axes.shape[1] != 3:
        raise ValueError(f"axes must be (P, 3) semi-axes and angle; got shape {axes.shape}")
    return axes


def transmission_model(n_t: int, n_s: int, pred: np.ndarray, radius: np.ndarray,
                       contrast: np.ndarray, edge: float | np.ndarray = EDGE_PX, *,
                       axes: np.ndarray | None = None) -> np.ndarray:
    """The fraction of the back-light the modelled particles let through, per view pixel.

    Parameters
    ----------
    n_t, n_s : int
        View size, pixels (rows ``t``, columns ``s``).
    pred : (P, V, 2) float ndarray
        Each particle's image centre ``(s, t)`` in each of ``V`` views, view pixels; NaN
        where it has none.
    radius, contrast : (P,) float ndarray
        Image radius (view pixels) and contrast (1: opaque) of each particle.
    edge : float or (P, 2) float ndarray
        Edge blur (standard deviation, view pixels): one width for every image and
        direction, or each particle's ``(w_s, w_t)``
        (:meth:`~plenoptrack.locate.refine.ImageEdge.widths`).
    axes : (P, 3) float ndarray, optional
        Elliptical images in place of the discs of ``radius``: semi-major and semi-minor
        axis (view pixels) and the long axis's angle (radians, from ``s`` toward ``t``).

    Returns
    -------
    (V, n_t, n_s) float32 ndarray
        ``prod_p (1 - c_p D(|x - mu_p|; r_p))``, the model of
        :mod:`~plenoptrack.locate.refine`.

    Examples
    --------
    >>> t = transmission_model(9, 9, np.array([[[4.0, 4.0]]]), np.array([2.0]),
    ...                        np.array([1.0]))
    >>> round(float(t[0, 4, 4]), 3), round(float(t[0, 0, 0]), 3)
    (0.0, 1.0)
    """
    pred = np.ascontiguousarray(pred, dtype=np.float64)
    out = np.empty((pred.shape[1], int(n_t), int(n_s)), dtype=np.float32)
    _transmission(int(n_t), int(n_s), pred, _image_axes(radius, axes),
                  np.ascontiguousarray(contrast, dtype=np.float64),
                  _edge_widths(edge, pred.shape[0]), out)
    return out


def residual_light_field(lf: LightField, view_rc: np.ndarray, transmission: np.ndarray,
                         *, floor: float = 0.5) -> LightField:
    """The light field with modelled particles divided out.

    Parameters
    ----------
    lf : LightField
        The frame.
    view_rc : (V, 2) int ndarray
        ``(v, u)`` index into ``lf.data`` of each modelled view.
    transmission : (V, n_t, n_s) float ndarray
        :func:`transmission_model` in those views.
    floor : float
        Pixels transmitting less than this are set to their view's background (the
        median of a sample of its valid pixels): behind an opaque image nothing can be
        seen, and dividing there would only amplify the noise.

    Returns
    -------
    LightField
        A copy of ``lf`` whose modelled views are divided by ``transmission``; views not
        modelled are unchanged.
    """
    data = lf.data.copy()
    background, has_background = _view_backgrounds(data, view_rc)
    for k, (vi, ui) in enumerate(np.asarray(view_rc, dtype=np.int64)):
        if not has_background[k]:
            continue
        view = data[vi, ui]
        t = transmission[k]
        blocked = t < floor
        np.divide(view, t, out=view, where=~blocked)
        view[blocked & np.isfinite(view)] = background[k]
    return dataclasses.replace(lf, data=data)


def divide_out_particles(lf: LightField, view_rc: np.ndarray, pred: np.ndarray,
                         radius: np.ndarray, contrast: np.ndarray, *, floor: float = 0.5,
                         edge: float | np.ndarray = EDGE_PX,
                         axes: np.ndarray | None = None,
                         out: np.ndarray | None = None) -> LightField:
    """:func:`residual_light_field` of :func:`transmission_model`, in one pass over the
    particles' images only.

    Equal to ``residual_light_field(lf, view_rc, transmission_model(n_t, n_s, pred,
    radius, contrast, edge, axes=axes), floor=floor)``, value for value, without the view-sized
    transmission of every view: its cost grows with the particles' image area, not with
    the light field's size (besides the copy of ``lf.data``).

    Parameters
    ----------
    lf : LightField
        The frame.
    view_rc : (V, 2) int ndarray
        ``(v, u)`` index into ``lf.data`` of each modelled view.
    pred : (P, V, 2) float ndarray
        Each particle's image centre ``(s, t)`` in each of the ``V`` views, view pixels;
        NaN where it has none.
    radius, contrast : (P,) float ndarray
        Image radius (view pixels) and contrast (1: opaque) of each particle.
    floor : float
        See :func:`residual_light_field`.
    edge : float or (P, 2) float ndarray
        See :func:`transmission_model`.
    axes : (P, 3) float ndarray, optional
        See :func:`transmission_model`.
    out : ndarray, optional
        An array of ``lf.data``'s shape and dtype (not ``lf.data`` itself) that the
        residual is written into, its contents replaced; a new array when None. A caller
        that divides out again and again (the hidden-particle search's rounds) saves
        the cost of mapping a new array of the light field's size each time (0.17 s on
        hall2019, more than the copy itself).

    Returns
    -------
    LightField
        A copy of ``lf`` with the modelled particles divided out (its data ``out`` when
        given).
    """
    view_rc = np.ascontiguousarray(view_rc, dtype=np.int64).reshape(-1, 2)
    if out is None:
        data = lf.data.copy()
    elif out.shape != lf.data.shape or out.dtype != lf.data.dtype or out is lf.data:
        raise ValueError(f"out must be a separate array of the light field's shape "
                         f"{lf.data.shape} and dtype {lf.data.dtype}; got {out.shape} "
                         f"{out.dtype}" + (" (the light field's own)" if out is lf.data else ""))
    else:
        np.copyto(out, lf.data)
        data = out
    background, has_background = _view_backgrounds(data, view_rc)
    _divide_out(data, view_rc, np.ascontiguousarray(pred, dtype=np.float64),
                _image_axes(radius, axes),
                np.ascontiguousarray(contrast, dtype=np.float64),
                _edge_widths(edge, len(radius)), float(floor), background, has_background)
    return dataclasses.replace(lf, data=data)


def _view_backgrounds(data: np.ndarray, view_rc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Background level of each view of ``view_rc`` (the median of a sample of its valid
    pixels, float32) and whether it has any valid pixel."""
    view_rc = np.asarray(view_rc, dtype=np.int64).reshape(-1, 2)
    background = np.zeros(len(view_rc), dtype=np.float32)
    has_background = np.zeros(len(view_rc), dtype=np.bool_)
    for k, (vi, ui) in enumerate(view_rc):
        sample = data[vi, ui, ::3, ::3]
        sample = sample[np.isfinite(sample) & (sample > 0)]
        if sample.size:
            background[k] = np.float32(np.median(sample))
            has_background[k] = True
    return background, has_background
