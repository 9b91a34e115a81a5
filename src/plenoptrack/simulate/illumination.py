"""Back-light non-uniformity and dust shadows (the ``illumination`` group of
:class:`~.realism.Realism`).

Both act on the noise-free irradiance as multiplicative maps, before the microlens blur
(:mod:`.psf`) and the sensor (:mod:`.sensor`). Sizes come from
:class:`~.realism.IlluminationEffects` (``optics.realism.illumination``); a size of 0
switches an effect off, and with the whole group off nothing here runs.

Effects
-------
back-light non-uniformity (``backlight_nonuniformity``, default 0.10)
    An LED panel behind a diffuser is not uniform: its brightness varies smoothly across
    the field. Modelled as ``B(u, v) = 1 + s (f(u, v) - mid) / (max f - min f)`` with
    ``f = sum a_pq P_p(v) P_q(u)`` over the Legendre polynomials of total degree 1 to 3
    (9 modes) in normalised sensor coordinates ``u, v`` in [-1, 1] (pixel-centre
    columns and rows), coefficients ``a_pq ~ N(0, 1) / (p + q)`` drawn from the camera
    seed (:func:`.sensor.camera_rng`), and ``mid`` the middle of the range of ``f``: the
    field's peak-to-valley over the sensor is exactly ``s`` (0.1 = +-5 %). It is fixed
    per camera: the white image shows exactly this field.
back-light change (``backlight_frame_change``, default 0.03)
    The lamp drifts and the diffuser moves between the white image and the frames: each
    frame and each dot card is lit by ``B`` times a further field of the same form and
    peak-to-valley ``backlight_frame_change``, drawn from that image's own noise seed (a
    child of its generator, so the noise draws are unchanged). Frame over white image is
    therefore smooth with exactly that peak-to-valley.
dust (``dust_particles`` 6, ``dust_diameter_um`` 40, ``dust_opacity`` 0.5,
``window_distance_mm`` 0.7)
    Dust on the sensor's cover window, ``window_distance_mm`` in front of the sensor
    (here in front of the microlenses when it exceeds ``f_ml``). Each particle is a disc
    (diameter within a factor two of ``dust_diameter_um``, log-uniform; opacity uniform
    in ``[dust_opacity / 2, dust_opacity]``) at a uniform position over the sensor,
    drawn from the camera seed. Its shadow is traced with the ray model of
    :mod:`.render` (64 samples per pixel): each lit sample ray of a pixel is followed
    from the sensor through its microlens point ``Q`` towards the main-lens point ``H``
    up to the window plane, and the pixel's transmission is the mean over those rays of
    ``1 - opacity`` (inside the disc) or 1. The blur of the shadow therefore follows
    from the window distance and the cone of light (working f-number) and it falls on
    different parts of neighbouring microlens images, as a real shadow in front of an
    MLA does. The map is fixed on the sensor: identical in the white image, frames and
    dot cards, so flat-fielding removes it. Shadows of different particles multiply.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from . import _kernels
from .sensor import camera_rng

__all__ = ["backlight_field", "backlight_coefficients", "dust_table", "dust_patches",
           "illuminate", "illuminated", "image_rng", "DUST_SAMPLES_PER_PIXEL"]

DUST_SAMPLES_PER_PIXEL = 64
"""Rays per pixel used to trace the dust shadows (once per camera)."""

_MODES = np.array([(p, q) for p in range(4) for q in range(4) if 0 < p + q <= 3])
_BACKLIGHT, _DUST = 1, 2     # purposes of camera_rng


def _legendre(x: np.ndarray, p: int) -> np.ndarray:
    return (np.ones_like(x), x, 1.5 * x * x - 0.5, 2.5 * x ** 3 - 1.5 * x)[p]


def _bases(shape, n_grid=None):
    """Row and column bases ``(9, rows)``, ``(9, cols)`` (or on an ``n_grid`` grid)."""
    rows, cols = shape if n_grid is None else (n_grid, n_grid)
    v = np.linspace(-1.0, 1.0, rows) if rows > 1 else np.zeros(1)
    u = np.linspace(-1.0, 1.0, cols) if cols > 1 else np.zeros(1)
    rb = np.array([_legendre(v, p) for p, _ in _MODES])
    cb = np.array([_legendre(u, q) for _, q in _MODES])
    return rb, cb


def backlight_coefficients(size: float, rng: np.random.Generator) -> tuple[float, np.ndarray]:
    """Draw a smooth field of peak-to-valley ``size``: ``(b0, a)`` with ``B = b0 + sum a_k
    P_pk(v) P_qk(u)``.

    Draws 9 standard normals (always, whatever ``size``); mode ``(p, q)`` gets
    ``N(0, 1) / (p + q)``. The range of the field is measured on a 129 x 129 grid of
    ``[-1, 1]^2`` (the maximum of a cubic between grid points exceeds the grid maximum by
    far less than 1e-3 of the range).
    """
    a = rng.standard_normal(len(_MODES)) / _MODES.sum(axis=1)
    rb, cb = _bases(None, n_grid=129)
    f = np.einsum("k,kr,kc->rc", a, rb, cb)
    lo, hi = f.min(), f.max()
    scale = size / (hi - lo)
    return 1.0 - scale * 0.5 * (hi + lo), a * scale


@functools.lru_cache(maxsize=4)
def _camera_backlight(optics) -> tuple[float, np.ndarray]:
    return backlight_coefficients(optics.realism.illumination.backlight_nonuniformity,
                                  camera_rng(optics, _BACKLIGHT))


def image_rng(rng: np.random.Generator) -> np.random.Generator:
    """Child generator of an image's noise generator for its back-light change.

    Spawned from the generator's seed sequence, so the generator's own stream (the
    noise) is not advanced.
    """
    return rng.spawn(1)[0]


def _frame_backlight(optics, rng: np.random.Generator | None):
    size = optics.realism.illumination.backlight_frame_change
    if rng is None or size == 0:
        return 1.0, np.zeros(len(_MODES))
    return backlight_coefficients(size, rng)


def backlight_field(optics, rng: np.random.Generator | None = None) -> np.ndarray:
    """The back-light of one image relative to a uniform one, ``(rows, cols)`` float32.

    Parameters
    ----------
    optics : SimOptics
        Camera (its seed fixes the camera's field).
    rng : numpy.random.Generator or None
        None: the white image's field (the camera's). Otherwise the frame's generator
        from :func:`image_rng`: the camera field times the frame's change.

    Returns
    -------
    (rows, cols) float32 ndarray
        Multiplicative illumination map (1 = nominal back-light).
    """
    out = np.ones(optics.camera.sensor_shape_px, dtype=np.float32)
    _apply_backlight(out, optics, rng)
    return out


def _apply_backlight(img, optics, rng, src=None):
    """Multiply by the back-light field, into ``img`` (from ``src``, default ``img``
    itself). Returns False, writing nothing, when the field is uniform."""
    eff = optics.realism.illumination
    if eff.backlight_nonuniformity == 0 and (rng is None or eff.backlight_frame_change == 0):
        return False
    b0, a = ((1.0, np.zeros(len(_MODES))) if eff.backlight_nonuniformity == 0
             else _camera_backlight(optics))
    f0, fa = _frame_backlight(optics, rng)
    rb, cb = _bases(img.shape)
    src = (img if src is None else src).view()
    src.flags.writeable = False  # one compiled specialisation, whether src is img or not
    _multiply_fields(src, img, rb, cb, b0, a, f0, fa)
    return True


@njit(parallel=True, cache=True)
def _multiply_fields(src, img, rb, cb, b0, a, f0, fa):
    """``img = src * B * F`` with ``B = b0 + sum_m a_m rb[m, row] cb[m, col]`` and ``F`` the
    same with ``f0, fa`` (float64 sums in the order of the modes, one pixel at a time;
    computed a row at a time so that the column loops vectorise)."""
    rows, cols = img.shape
    k = a.shape[0]
    for r in prange(rows):
        s1 = np.empty(cols)
        s2 = np.empty(cols)
        for c in range(cols):
            s1[c] = b0
            s2[c] = f0
        for m in range(k):
            am = a[m] * rb[m, r]
            fm = fa[m] * rb[m, r]
            for c in range(cols):
                s1[c] += am * cb[m, c]
                s2[c] += fm * cb[m, c]
        for c in range(cols):
            img[r, c] = src[r, c] * (s1[c] * s2[c])


@functools.lru_cache(maxsize=4)
def dust_table(optics) -> np.ndarray:
    """The dust particles on the sensor window, ``(n, 4)`` float64, read-only.

    Columns: X, Y (camera frame, mm, in the window plane), radius (mm), opacity. Drawn
    from :func:`.sensor.camera_rng` (purpose dust): per particle, in order, X and Y
    uniform over the sensor area, the diameter ``dust_diameter_um * 2**U(-1, 1)`` and
    the opacity ``dust_opacity * U(0.5, 1)``.
    """
    eff = optics.realism.illumination
    n = int(round(eff.dust_particles))
    rng = camera_rng(optics, _DUST)
    u = rng.random((n, 4))
    rows, cols = optics.camera.sensor_shape_px
    pp = optics.pixel_pitch
    out = np.column_stack([(u[:, 0] - 0.5) * cols * pp, (u[:, 1] - 0.5) * rows * pp,
                           0.5e-3 * eff.dust_diameter_um * 2.0 ** (2 * u[:, 2] - 1),
                           eff.dust_opacity * (0.5 + 0.5 * u[:, 3])])
    out.setflags(write=False)
    return out


@njit(parallel=True, cache=True)
def _dust_patch(par, samples, r0, c0, h, w, dust, d_win):
    """Mean transmission over the lit sample rays of pixels [r0, r0+h) x [c0, c0+w)."""
    out = np.ones((h, w), dtype=np.float32)
    tan_s = par[_kernels.S_I] / par[_kernels.F_ML]
    f_ml = par[_kernels.F_ML]
    s_i = par[_kernels.S_I]
    dx0, dy0, rad, opac = dust[0], dust[1], dust[2], dust[3]
    for rr in prange(h):
        y0 = (r0 + rr - (par[_kernels.ROWS] - 1.0) * 0.5) * par[_kernels.PP]
        for cc in range(w):
            x0 = (c0 + cc - (par[_kernels.COLS] - 1.0) * 0.5) * par[_kernels.PP]
            lit = 0
            trans = 0.0
            for k in range(samples.shape[0]):
                px = x0 + samples[k, 0]
                py = y0 + samples[k, 1]
                i, j = _kernels._nearest_lens(px * par[_kernels.INV_SCALE],
                                              py * par[_kernels.INV_SCALE], par)
                cx, cy = _kernels._lens_center(i, j, par)
                qx = cx + samples[k, 2]
                qy = cy + samples[k, 3]
                hx = qx + (cx - px) * tan_s
                hy = qy + (cy - py) * tan_s
                if hx * hx + hy * hy > par[_kernels.R_AP2]:
                    continue
                if d_win <= f_ml:
                    t = d_win / f_ml
                    wx = px + (qx - px) * t
                    wy = py + (qy - py) * t
                else:
                    t = (d_win - f_ml) / s_i
                    wx = qx + (hx - qx) * t
                    wy = qy + (hy - qy) * t
                lit += 1
                if (wx - dx0) ** 2 + (wy - dy0) ** 2 < rad * rad:
                    trans += 1.0 - opac
                else:
                    trans += 1.0
            if lit > 0:
                out[rr, cc] = trans / lit
    return out


@functools.lru_cache(maxsize=4)
def dust_patches(optics) -> tuple:
    """Transmission maps of the dust shadows, cached per camera.

    Returns
    -------
    tuple of (row0, col0, (h, w) float32 ndarray)
        Pixels ``[row0, row0 + h) x [col0, col0 + w)`` have their irradiance multiplied by
        the patch (1 where the shadow does not reach). Patches are clipped to the sensor.
    """
    from .render import sample_pattern

    eff = optics.realism.illumination
    table = dust_table(optics)
    if len(table) == 0 or eff.dust_opacity == 0 or eff.dust_diameter_um == 0:
        return ()
    par = _kernels.pack_params(optics)
    samples = sample_pattern(optics, DUST_SAMPLES_PER_PIXEL)
    rows, cols = optics.camera.sensor_shape_px
    d = eff.window_distance_mm
    reach_mm = (2 * optics.pitch + optics.cell_radius
                + (optics.aperture_radius + optics.cell_radius) * max(d - optics.f_ml, 0) / optics.s_i)
    patches = []
    for dust in table:
        centre = optics.mla_to_pixels(dust[:2])
        half = (dust[2] + reach_mm) * optics.image_scale / optics.pixel_pitch + 2
        r0 = max(0, int(math.floor(centre[0] - half)))
        r1 = min(rows, int(math.ceil(centre[0] + half)) + 1)
        c0 = max(0, int(math.floor(centre[1] - half)))
        c1 = min(cols, int(math.ceil(centre[1] + half)) + 1)
        if r1 <= r0 or c1 <= c0:
            continue
        patch = _dust_patch(par, samples, r0, c0, r1 - r0, c1 - c0,
                            np.ascontiguousarray(dust), float(d))
        patch.setflags(write=False)
        patches.append((r0, c0, patch))
    return tuple(patches)


def illuminate(irradiance: np.ndarray, optics, rng: np.random.Generator | None) -> np.ndarray:
    """Apply the back-light field and dust shadows to an irradiance image, in place.

    Parameters
    ----------
    irradiance : (rows, cols) float32 ndarray
        Noise-free irradiance relative to a uniform back-light; changed in place.
    optics : SimOptics
        Camera; ``optics.realism.illumination`` sets the effects.
    rng : numpy.random.Generator or None
        None for the white image; the frame's :func:`image_rng` generator otherwise
        (draws the frame's back-light change).

    Returns
    -------
    (rows, cols) float32 ndarray
        ``irradiance`` (the same array).
    """
    _apply_backlight(irradiance, optics, rng)
    _apply_dust(irradiance, optics)
    return irradiance


def illuminated(irradiance: np.ndarray, optics, rng: np.random.Generator | None) -> np.ndarray:
    """:func:`illuminate` into a new float32 array (the input is not changed).

    The same pixels as a copy followed by :func:`illuminate`, without the separate pass
    of the copy.
    """
    src = np.ascontiguousarray(irradiance, dtype=np.float32)
    out = np.empty_like(src)
    if not _apply_backlight(out, optics, rng, src=src):
        out[...] = src
    _apply_dust(out, optics)
    return out


def _apply_dust(irradiance, optics):
    if optics.realism.illumination.dust_particles >= 0.5:
        for r0, c0, patch in dust_patches(optics):
            irradiance[r0:r0 + patch.shape[0], c0:c0 + patch.shape[1]] *= patch
