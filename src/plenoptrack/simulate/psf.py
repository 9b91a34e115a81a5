"""Blur of the microlens images on the sensor: diffraction, defocus, aberration, crosstalk,
fill factor (the ``blur`` group of :class:`~.realism.Realism`).

The ray tracer (:mod:`.render`) treats the microlenses as perfect thin lenses with the
sensor exactly in their focal plane. This module adds what a real microlens array does
on top, as image-domain operations on the noise-free irradiance, in the order light
meets them. Every effect is switched off by a size of 0 in
:class:`~.realism.BlurEffects` (``optics.realism.blur``); with all of them 0 nothing here
runs and rendering is bit-identical to the ideal model.

Effects
-------
fill factor (``fill_gap``, default 0.02)
    A microlens cell has a dead border (the gap between lenses and the rolled-off lens
    edge); light meeting the MLA there is lost. ``fill_gap`` is the dead fraction of the
    cell width, so the live part of each cell is the cell scaled by ``1 - fill_gap``
    about the lens centre. It is implemented where it physically acts, in the ray
    sampling: :func:`live_cell_scale` shrinks the aperture-cell samples ``Q`` of
    :func:`.render.sample_pattern` to the live cell (so the edges of the microlens
    images follow the smaller cell), and :func:`blur_image` multiplies by the live area
    fraction :func:`fill_transmission` ``= (1 - fill_gap)**2`` (the samples are uniform
    on the live cell, so this is the exact integral over the whole cell). Default: 3.96 %
    of the light is lost.
diffraction (``wavelength_nm``, default 550 nm)
    Each microlens (width = pitch, focal length ``f_ml``) has working f-number
    ``N = camera.microlens_f_number``; a point of the aperture image is spread into an
    Airy pattern ``I(r) = (2 J1(x) / x)**2``, ``x = pi r / (lambda N)``, first zero at
    ``1.22 lambda N`` (2.68 um for ``hall2019``: half a 5.5 um pixel).
defocus (``microlens_defocus_um``, default 8 um)
    A sensor ``delta`` away from the microlens focal plane blurs the aperture image by a
    uniform disc of diameter ``delta / N`` (geometric cone of the lens).
aberration (``microlens_aberration_um``, default 1 um)
    Residual (mostly spherical) aberration, modelled as an isotropic Gaussian of RMS
    radius ``a`` (standard deviation ``a / sqrt(2)`` per axis).
crosstalk (``crosstalk``, default 0.01)
    Light scattered at the lens edges and in the cover glass that lands behind a
    neighbouring lens: a fraction ``crosstalk`` of every microlens image is moved, in
    equal parts, onto the images of its 6 (hexagonal) or 4 (rectangular) nearest
    neighbours, i.e. copies of the image shifted by the image-lattice vectors (bilinear
    sub-pixel shift). Light is conserved.

The three blurs are combined into one kernel (:func:`psf_kernel`): Airy pattern,
convolved with the disc and the Gaussian on a fine grid (step at most a quarter of
``lambda N``), then integrated over the pixel area (sum over the ``os x os`` fine samples
of each pixel). The kernel extends to ``10 lambda N + delta / (2 N) + 4 sigma`` (Airy
encircled energy there about 98 %) and is normalised to sum 1, so the truncated Airy
tail is put back inside that radius and blurring conserves light. Kernel and crosstalk
are applied together as one transfer function (FFT with zero padding, cached per camera,
:func:`apply_transfer`): light blurred or scattered off the sensor edge is
lost, none comes in from outside. :func:`blur_image` sums a kernel of up to
:data:`DIRECT_MAX_TAPS` taps directly instead (:func:`convolve_direct`: the kernel over
the image grown by its radius, then the crosstalk taps; the same light, up to float32
rounding), which is faster for the small kernels of real microlenses (11 x 11 pixels for
``hall2019``).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit, prange

from ..errors import SettingsError
from .realism import BlurEffects

__all__ = ["airy_intensity", "psf_kernel", "convolve_psf", "crosstalk_shifts",
           "apply_crosstalk", "apply_transfer", "convolve_direct", "shift_taps", "live_cell_scale",
           "fill_transmission", "blur_image", "AIRY_FIRST_ZERO", "DIRECT_MAX_TAPS"]

AIRY_FIRST_ZERO = 1.2196698912665045
"""First zero of ``J1(pi x)`` over pi: the Airy first-zero radius in units of lambda N."""

_AIRY_EXTENT = 10.0      # kernel radius, in lambda N, given to the Airy tail
_MAX_OVERSAMPLE = 41
_WORKERS = 2             # FFT threads


def airy_intensity(r_um, wavelength_nm: float, f_number: float) -> np.ndarray:
    """Airy pattern ``(2 J1(x) / x)**2``, ``x = pi r / (lambda N)``, peak 1.

    Parameters
    ----------
    r_um : array_like
        Radius from the pattern centre, um.
    wavelength_nm : float
        Wavelength, nm.
    f_number : float
        Working f-number of the lens.

    Returns
    -------
    float64 ndarray
        Relative intensity, same shape as ``r_um``.
    """
    from scipy.special import j1

    x = np.pi * np.asarray(r_um, dtype=float) / (wavelength_nm * 1e-3 * f_number)
    safe = np.where(x == 0, 1.0, x)
    return np.where(x == 0, 1.0, (2.0 * j1(safe) / safe) ** 2)


def _disc(radius_um: float, h: float, m: int) -> np.ndarray:
    """Uniform disc of ``radius_um`` on an ``m x m`` grid of step ``h`` um (area-weighted
    by 5 x 5 supersampling), sum 1."""
    c = (m - 1) / 2
    sub = (np.arange(5) - 2) / 5
    x = ((np.arange(m) - c)[:, None] + sub[None, :]).ravel() * h
    inside = (x[:, None] ** 2 + x[None, :] ** 2) <= radius_um ** 2
    w = inside.reshape(m, 5, m, 5).mean(axis=(1, 3))
    if w.sum() == 0:
        w[m // 2, m // 2] = 1.0
    return w / w.sum()


@functools.lru_cache(maxsize=32)
def psf_kernel(blur: BlurEffects, *, f_number: float, pixel_pitch_um: float) -> np.ndarray:
    """Pixel-integrated point-spread function of a microlens, ``(2R+1, 2R+1)`` float64.

    Parameters
    ----------
    blur : BlurEffects
        ``wavelength_nm`` (diffraction), ``microlens_defocus_um`` and
        ``microlens_aberration_um`` are used; 0 switches each off.
    f_number : float
        Working f-number ``N`` of the microlenses (``camera.microlens_f_number``).
    pixel_pitch_um : float
        Sensor pixel pitch, um.

    Returns
    -------
    (2R+1, 2R+1) float64 ndarray, read-only
        Fraction of the light of a point at the centre of pixel ``(R, R)`` that each pixel
        ``(R + drow, R + dcol)`` collects; sums to 1. ``[[1.0]]`` when all three blurs
        are off.

    Notes
    -----
    Computed on a fine grid with ``os`` (odd) samples per pixel and step
    ``h = pitch / os <= min(lambda N / 4, disc diameter / 8, sigma / 2)``: Airy pattern
    sampled at the fine points, convolved with the disc (area-weighted) and the Gaussian,
    then summed over each pixel's ``os x os`` samples (pixel-area integration).
    """
    if not (math.isfinite(f_number) and f_number > 0):
        raise SettingsError(f"f_number must be positive; got {f_number!r}")
    if not (math.isfinite(pixel_pitch_um) and pixel_pitch_um > 0):
        raise SettingsError(f"pixel_pitch_um must be positive; got {pixel_pitch_um!r}")
    from scipy.signal import fftconvolve

    lam_n = blur.wavelength_nm * 1e-3 * f_number           # um
    disc_r = 0.5 * blur.microlens_defocus_um / f_number     # um
    sigma = blur.microlens_aberration_um / math.sqrt(2.0)   # um per axis
    if lam_n == 0 and disc_r == 0 and sigma == 0:
        k = np.ones((1, 1))
        k.setflags(write=False)
        return k
    extent = (_AIRY_EXTENT * lam_n if lam_n > 0 else 0.0) + disc_r + 4.0 * sigma
    rad = max(1, math.ceil(extent / pixel_pitch_um - 1e-9))
    h_target = min(v for v in (lam_n / 4 if lam_n else math.inf, disc_r / 4 if disc_r else math.inf,
                               sigma / 2 if sigma else math.inf))
    os_ = max(1, math.ceil(pixel_pitch_um / h_target))
    os_ = min(os_ + (1 - os_ % 2), _MAX_OVERSAMPLE)
    h = pixel_pitch_um / os_
    m = (2 * rad + 1) * os_
    x = (np.arange(m) - (m - 1) / 2) * h
    if lam_n > 0:
        fine = airy_intensity(np.hypot(x[:, None], x[None, :]), blur.wavelength_nm, f_number)
    else:
        fine = np.zeros((m, m))
        fine[m // 2, m // 2] = 1.0
    if disc_r > 0:
        fine = fftconvolve(fine, _disc(disc_r, h, min(m, 2 * math.ceil(disc_r / h) + 3)),
                           mode="same")
    if sigma > 0:
        half = min(m // 2, math.ceil(4 * sigma / h))
        g = np.exp(-0.5 * ((np.arange(-half, half + 1) * h) / sigma) ** 2)
        g /= g.sum()
        fine = fftconvolve(fine, g[:, None], mode="same")
        fine = fftconvolve(fine, g[None, :], mode="same")
    k = np.clip(fine, 0, None).reshape(2 * rad + 1, os_, 2 * rad + 1, os_).sum(axis=(1, 3))
    k = (k + k[::-1] + k[:, ::-1] + k[::-1, ::-1]) / 4     # exact symmetry
    k /= k.sum()
    k.setflags(write=False)
    return k


def _transfer(shape, kernel, shifts, fraction):
    """Transfer function (rfft2 layout, complex64) of the kernel followed by crosstalk."""
    ny, nx = shape
    r = (kernel.shape[0] - 1) / 2
    c = (kernel.shape[1] - 1) / 2
    fy = np.fft.fftfreq(ny)
    fx = np.fft.rfftfreq(nx)
    ey = np.exp(-2j * np.pi * fy[:, None] * (np.arange(kernel.shape[0]) - r)[None, :])
    ex = np.exp(-2j * np.pi * (np.arange(kernel.shape[1]) - c)[:, None] * fx[None, :])
    h = (ey.astype(np.complex64) @ kernel.astype(np.complex64)) @ ex.astype(np.complex64)
    if fraction > 0:
        t = np.full(h.shape, 1.0 - fraction, dtype=np.complex64)
        w = fraction / len(shifts)
        for dy, dx in shifts:
            t += np.outer((w * _bilinear_shift(fy, dy)).astype(np.complex64),
                          _bilinear_shift(fx, dx).astype(np.complex64))
        h *= t
    return h


def _bilinear_shift(f, d):
    """Transfer function of a shift by ``d`` pixels with linear interpolation (2 taps)."""
    n = math.floor(d)
    a = d - n
    return (1.0 - a) * np.exp(-2j * np.pi * f * n) + a * np.exp(-2j * np.pi * f * (n + 1))


def _fft_shape(shape, kernel, shifts):
    import scipy.fft

    reach = np.abs(shifts).max(axis=0) if len(shifts) else np.zeros(2)
    pad_r = kernel.shape[0] // 2 + int(math.ceil(reach[0])) + 3
    pad_c = kernel.shape[1] // 2 + int(math.ceil(reach[1])) + 3
    return (scipy.fft.next_fast_len(shape[0] + pad_r, real=True),
            scipy.fft.next_fast_len(shape[1] + pad_c, real=True))


def apply_transfer(image: np.ndarray, kernel: np.ndarray, shifts: np.ndarray = np.zeros((0, 2)),
                   fraction: float = 0.0, *, transfer: np.ndarray | None = None) -> np.ndarray:
    """Convolve with a point-spread kernel, then move ``fraction`` of the light by ``shifts``.

    Parameters
    ----------
    image : (rows, cols) float ndarray
        Irradiance, any units.
    kernel : (2R+1, 2S+1) float ndarray
        Point-spread kernel (centre at ``(R, S)``), e.g. :func:`psf_kernel`.
    shifts : (n, 2) float ndarray
        Crosstalk shifts (drow, dcol), pixels, e.g. :func:`crosstalk_shifts`.
    fraction : float
        Fraction of the light moved, in equal parts, by the shifts (sub-pixel shifts by
        bilinear interpolation: a positive 2 x 2 kernel, no ringing).
    transfer : complex ndarray, optional
        Precomputed transfer function of these arguments (internal cache).

    Returns
    -------
    (rows, cols) float32 ndarray
        ``(1 - fraction) * (k * image) + fraction / n * sum_s (k * image)(p - shift_s)``,
        computed with zero padding (FFT, 2 workers): light leaving the image is lost,
        none comes in; values are clipped at 0 (FFT round-off, ~1e-7 of the maximum).
    """
    import scipy.fft

    if not 0 <= fraction <= 1:
        raise SettingsError(f"crosstalk fraction must be in [0, 1]; got {fraction!r}")
    img = np.asarray(image, dtype=np.float32)
    kernel = np.asarray(kernel, dtype=np.float64)
    shifts = np.asarray(shifts, dtype=np.float64).reshape(-1, 2)
    shape = _fft_shape(img.shape, kernel, shifts)
    if transfer is None:
        transfer = _transfer(shape, kernel, shifts, fraction)
    spec = scipy.fft.rfft2(img, s=shape, workers=_WORKERS)
    spec *= transfer
    out = scipy.fft.irfft2(spec, s=shape, workers=_WORKERS, overwrite_x=True)
    del spec
    out = np.ascontiguousarray(out[:img.shape[0], :img.shape[1]])
    np.maximum(out, 0, out=out)
    return out


def convolve_psf(image: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Convolve an irradiance image with a point-spread kernel (zero outside the image).

    Parameters
    ----------
    image : (rows, cols) float ndarray
        Irradiance, any units.
    kernel : (2R+1, 2S+1) float ndarray
        Kernel from :func:`psf_kernel` (centre at ``(R, S)``).

    Returns
    -------
    (rows, cols) float32 ndarray
        Blurred image; light spread beyond the image edge is lost.
    """
    return apply_transfer(image, kernel)


def crosstalk_shifts(optics) -> np.ndarray:
    """Image-lattice vectors to the nearest neighbours of a microlens image, ``(n, 2)``.

    Returns (drow, dcol) sensor pixels: 6 vectors for a hexagonal array, 4 for a
    rectangular one (``±e1, ±(e2 ± e1/2)`` resp. ``±e1, ±e2`` of the physical lattice,
    scaled to the sensor by ``image_scale / pixel_pitch``).
    """
    e1, e2 = optics.lattice_vectors
    if optics.camera.grid_type == "hex":
        vecs = [e1, e2 + 0.5 * e1, e2 - 0.5 * e1]
    else:
        vecs = [e1, e2]
    k = optics.image_scale / optics.pixel_pitch
    out = []
    for v in vecs:
        out.append((v[1] * k, v[0] * k))
        out.append((-v[1] * k, -v[0] * k))
    return np.array(out)


def apply_crosstalk(image: np.ndarray, shifts: np.ndarray, fraction: float) -> np.ndarray:
    """Move ``fraction`` of the light of every pixel, in equal parts, by each shift.

    Parameters
    ----------
    image : (rows, cols) float ndarray
        Irradiance.
    shifts : (n, 2) float ndarray
        (drow, dcol) pixels, e.g. :func:`crosstalk_shifts`.
    fraction : float
        Fraction of the light moved, in [0, 1].

    Returns
    -------
    (rows, cols) float32 ndarray
        ``(1 - fraction) * image + fraction / n * sum_k image(p - shift_k)``, bilinear;
        light shifted beyond the image edge is lost.
    """
    if not 0 <= fraction <= 1:
        raise SettingsError(f"crosstalk must be in [0, 1]; got {fraction!r}")
    return apply_transfer(image, np.ones((1, 1)), shifts, fraction)


def live_cell_scale(blur: BlurEffects) -> float:
    """Linear size of the live part of a microlens cell over the cell: ``1 - fill_gap``."""
    if blur.fill_gap >= 1:
        raise SettingsError(f"fill_gap must be below 1 (the dead fraction of the cell width); "
                            f"got {blur.fill_gap!r}")
    return 1.0 - blur.fill_gap


def fill_transmission(blur: BlurEffects) -> float:
    """Fraction of the light meeting a microlens cell that passes its live part, ``(1-g)**2``."""
    return live_cell_scale(blur) ** 2


def blur_image(irradiance: np.ndarray, optics) -> np.ndarray:
    """Apply the ``blur`` effects of ``optics.realism`` to a noise-free irradiance.

    Parameters
    ----------
    irradiance : (rows, cols) float ndarray
        Ray-traced irradiance (traced with the fill-gap sample pattern of
        :func:`.render.sample_pattern`), relative to the back-light.
    optics : SimOptics
        Camera; ``optics.realism.blur`` sets the effects, ``optics.camera`` the microlens
        f-number and pixel pitch.

    Returns
    -------
    (rows, cols) float32 ndarray
        Irradiance times the fill transmission, convolved with :func:`psf_kernel`, with
        crosstalk (a new array; the input is not changed).

    Notes
    -----
    A kernel of at most :data:`DIRECT_MAX_TAPS` taps is applied directly
    (:func:`convolve_direct`, float32 sums: the same result as the FFT of
    :func:`apply_transfer` up to float32 rounding, about 1e-7 of the back-light, and
    several times faster on a full sensor); a larger one through the FFT.
    """
    blur = optics.realism.blur
    cam = optics.camera
    k = psf_kernel(blur, f_number=cam.microlens_f_number, pixel_pitch_um=cam.pixel_pitch_um)
    if k.shape == (1, 1) and blur.crosstalk == 0:
        out = np.array(irradiance, dtype=np.float32, copy=True)
        if blur.fill_gap > 0:
            out *= np.float32(fill_transmission(blur))
        return out
    if k.size <= DIRECT_MAX_TAPS:
        scale = fill_transmission(blur) if blur.fill_gap > 0 else 1.0
        return convolve_direct(irradiance, k * scale, crosstalk_shifts(optics), blur.crosstalk)
    # the fill transmission is folded into the cached transfer function
    return apply_transfer(irradiance, k, crosstalk_shifts(optics), blur.crosstalk,
                          transfer=_optics_transfer(optics))


DIRECT_MAX_TAPS = 15 * 15
"""Largest point-spread kernel (taps) that :func:`blur_image` applies directly."""


def shift_taps(shifts: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The crosstalk of :func:`apply_transfer` as pixel taps.

    Returns ``(drow, dcol, weight)``: ``out(p) = (1 - fraction) in(p) + sum_t weight_t
    in(p - (drow_t, dcol_t))``, four bilinear taps per shift (a shift by ``n + a`` pixels
    takes ``1 - a`` of ``in(p - n)`` and ``a`` of ``in(p - n - 1)``, the transfer function
    of :func:`_bilinear_shift`), each shift carrying ``fraction / n_shifts``.
    """
    shifts = np.asarray(shifts, dtype=np.float64).reshape(-1, 2)
    dr, dc, wt = [], [], []
    if fraction > 0 and len(shifts):
        w = fraction / len(shifts)
        for sy, sx in shifts:
            ny, nx = math.floor(sy), math.floor(sx)
            ay, ax = sy - ny, sx - nx
            for ty, wy in ((ny, 1.0 - ay), (ny + 1, ay)):
                for tx, wx in ((nx, 1.0 - ax), (nx + 1, ax)):
                    if wy * wx > 0:
                        dr.append(ty)
                        dc.append(tx)
                        wt.append(w * wy * wx)
    return (np.array(dr, dtype=np.int64), np.array(dc, dtype=np.int64),
            np.array(wt, dtype=np.float32))


def convolve_direct(image: np.ndarray, kernel: np.ndarray, shifts: np.ndarray = np.zeros((0, 2)),
                    fraction: float = 0.0) -> np.ndarray:
    """:func:`apply_transfer` by direct summation over the kernel and crosstalk taps.

    Parameters
    ----------
    image : (rows, cols) float ndarray
        Irradiance, any units.
    kernel : (2R+1, 2S+1) float ndarray
        Point-spread kernel (centre at ``(R, S)``), e.g. :func:`psf_kernel`.
    shifts : (n, 2) float ndarray
        Crosstalk shifts (drow, dcol), pixels (:func:`crosstalk_shifts`).
    fraction : float
        Fraction of the light moved, in equal parts, by the shifts (bilinear,
        :func:`shift_taps`).

    Returns
    -------
    (rows, cols) float32 ndarray
        As :func:`apply_transfer` (zero outside the image, clipped at 0), summed in
        float32 on up to two threads; it differs from the FFT only by rounding.
    """
    if not 0 <= fraction <= 1:
        raise SettingsError(f"crosstalk fraction must be in [0, 1]; got {fraction!r}")
    img = np.ascontiguousarray(image, dtype=np.float32)
    k = np.ascontiguousarray(kernel, dtype=np.float32)
    if k.ndim != 2 or k.shape[0] % 2 == 0 or k.shape[1] % 2 == 0:
        raise SettingsError(f"kernel must have odd sides; got shape {k.shape}")
    dr, dc, wt = shift_taps(shifts, fraction)
    if not len(wt):
        return _convolve_rows(img, k, 0, 0)
    # The blurred light just outside the image can still be scattered back into it.
    rad_r, rad_c = k.shape[0] // 2, k.shape[1] // 2
    wide = _convolve_rows(img, k, rad_r, rad_c)
    return _crosstalk_rows(wide, rad_r, rad_c, img.shape[0], img.shape[1], dr, dc, wt,
                           np.float32(1.0 - fraction))


_TILE = 512
"""Columns summed at a time by the direct convolution (the partial sums stay in cache)."""


@njit(parallel=True, cache=True)
def _convolve_rows(img, k, mr, mc):
    """``out(p) = sum_d k[R + d] img(p - d)`` (zero outside the image), float32, on the
    image grown by ``mr`` rows and ``mc`` columns on every side (``out[mr, mc]`` is
    pixel (0, 0)); row by row and :data:`_TILE` columns at a time, taps in row-major
    kernel order."""
    rows, cols = img.shape
    kr, kc = k.shape
    rad_r = kr // 2
    rad_c = kc // 2
    width = cols + 2 * mc
    out = np.empty((rows + 2 * mr, width), dtype=np.float32)
    n_tiles = (width + _TILE - 1) // _TILE
    for job in prange((rows + 2 * mr) * n_tiles):
        re = job // n_tiles
        t0 = (job % n_tiles) * _TILE
        t1 = min(width, t0 + _TILE)
        r = re - mr
        acc = np.zeros(_TILE, dtype=np.float32)
        for a in range(kr):
            sr = r - (a - rad_r)
            if sr < 0 or sr >= rows:
                continue
            src = img[sr]
            for b in range(kc):
                off = mc + (b - rad_c)              # out column of src column 0
                w = k[a, b]
                c0 = max(t0, off)
                c1 = min(t1, off + cols)
                if c1 <= c0:
                    continue
                dst = acc[c0 - t0:c1 - t0]
                seg = src[c0 - off:c1 - off]
                for m in range(dst.shape[0]):
                    dst[m] += w * seg[m]
        row = out[re]
        for m in range(t1 - t0):
            row[t0 + m] = max(acc[m], np.float32(0.0))
    return out


@njit(parallel=True, cache=True)
def _crosstalk_rows(y, mr, mc, rows, cols, dr, dc, wt, keep):
    """``out(p) = keep y(p) + sum_t wt_t y(p - (dr_t, dc_t))`` for the ``(rows, cols)``
    image of ``y`` (grown by ``mr``, ``mc``; zero beyond), float32."""
    out = np.empty((rows, cols), dtype=np.float32)
    big_r, big_c = y.shape
    for r in prange(rows):
        acc = np.empty(cols, dtype=np.float32)
        here = y[r + mr]
        for m in range(cols):
            acc[m] = keep * here[m + mc]
        for t in range(wt.shape[0]):
            sr = r - dr[t] + mr
            if sr < 0 or sr >= big_r:
                continue
            src = y[sr]
            off = dc[t] - mc                        # out column of y column 0
            w = wt[t]
            c0 = max(0, off)
            c1 = min(cols, off + big_c)
            dst = acc[c0:c1]
            seg = src[c0 - off:c1 - off]
            for m in range(dst.shape[0]):
                dst[m] += w * seg[m]
        row = out[r]
        for m in range(cols):
            row[m] = max(acc[m], np.float32(0.0))
    return out


@functools.lru_cache(maxsize=2)
def _optics_transfer(optics) -> np.ndarray:
    """Cached transfer function of :func:`blur_image` for one camera (complex64), times
    the fill transmission."""
    blur = optics.realism.blur
    cam = optics.camera
    k = psf_kernel(blur, f_number=cam.microlens_f_number, pixel_pitch_um=cam.pixel_pitch_um)
    shifts = crosstalk_shifts(optics)
    h = _transfer(_fft_shape(cam.sensor_shape_px, k, shifts), k, shifts, blur.crosstalk)
    if blur.fill_gap > 0:
        h *= np.float32(fill_transmission(blur))
    h.setflags(write=False)
    return h
