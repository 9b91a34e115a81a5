"""Lenslet-grid calibration: find every microlens-image centre in a white image.

A white (flat-field) image taken through the microlens array shows one bright disc per
microlens, the image of the main-lens aperture. :func:`measure_grid` turns such an image
into a :class:`~plenoptrack.lightfield.lattice.LensletGrid`, fully automatically:

1. **Coarse lattice.** The autocorrelation of a central crop has a peak at every lattice
   vector. The nearest peaks give the pitch, the orientation and the packing (hexagonal:
   the second vector is 60 degrees from the first; rectangular: 90 degrees).
2. **Phase.** Folding the crop onto one lattice cell (averaging the pixels that share the
   same fractional lattice coordinates) gives the mean microlens image; its centre of
   symmetry (the brightest of the four the lattice allows) places one reference lens.
3. **Centres.** Each microlens image, together with the light its neighbours spill
   around it, is centrally symmetric about its centre, so the centre is the point about
   which the image equals its own point reflection. Around each predicted centre a
   Lucas-Kanade step between the window and its reflection (through a half-pixel point,
   so pixels map onto pixels) estimates the offset; the window moves until it sits on the
   nearest half pixel, and steps that reflect about the estimate itself (bilinear
   interpolation) remove the error of the first-order model. The estimate needs no
   model of the disc profile, vignetting or background, and is unbiased where the image
   is symmetric.
4. **Fit.** An affine lattice (origin and two steps) is fitted to all centres by linear
   least squares with 3-sigma (MAD) rejection of outliers (defects, dust, clipped edge
   lenses). The fit starts on the lenses near the reference, whose windows are placed
   from the coarse lattice, and grows to the whole sensor, each stage placing its
   windows from the previous fit, so small errors of the coarse lattice never accumulate
   over hundreds of lenses.

Coordinates follow ``docs/conventions.md``: (row, col) sensor pixels, pixel centres at
integer coordinates.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Iterator

import numba
import numpy as np
from scipy import ndimage

from ..errors import CalibrationError, InputFileError
from .lattice import LensletGrid

__all__ = ["GridMeasurement", "measure_grid", "calibrate_grid"]

#: Side of the central crop used for the coarse lattice, pixels.
_CROP_PX = 512
#: Smallest and largest pitch searched when no nominal pitch is given, pixels.
_MIN_PITCH_PX = 4.0
#: Largest relative difference between the measured and the nominal pitch.
_PITCH_TOLERANCE = 0.25
#: Normalised autocorrelation a lattice peak must reach to count as periodic structure.
_MIN_PEAK_CORRELATION = 0.15
#: Fewest lenses a white image must show for a meaningful lattice fit.
_MIN_LENSES = 16
#: Radius of the symmetry window in pitches, and its cosine taper in pixels.
_WINDOW_RADIUS = 0.5
_WINDOW_TAPER_PX = 1.0
#: A symmetry step this small (pixels) leaves the window where it is.
_SETTLED_PX = 0.27
#: Interpolated refinement steps once a lens centre has settled.
_REFINE_STEPS = 2
#: Most symmetry steps per lens and pass.
_MAX_STEPS = 6
#: Radii (in pitches) of the successive fitting regions around the reference lens.
_STAGE_RADII = (6.0, 40.0, math.inf)
#: Centroid / fit passes per region.
_PASSES = (2, 2, 1)
#: Outlier threshold in robust standard deviations.
_REJECT_SIGMA = 3.0
#: Lenses whose window is less bright (above the gaps) than this fraction of the median
#: lens are taken as unlit.
_MIN_LEVEL_FRACTION = 0.05

_NO_GRID = ("no lenslet grid found in the white image; is it a white (flat-field) image "
            "taken through the microlens array?")


@dataclass(frozen=True)
class GridMeasurement:
    """Result of :func:`measure_grid`.

    Attributes
    ----------
    grid : LensletGrid
        Fitted affine lattice covering every lens whose image centre lies on the sensor.
    centres_px : (N, 2) float64 ndarray
        Measured microlens-image centres as (row, col), sensor pixels, of the lenses kept
        in the final fit.
    indices : (N, 2) int64 ndarray
        Lattice indices (i, j) of those lenses in ``grid`` (row, column of the lattice).
    residuals_px : (N, 2) float64 ndarray
        Measured minus fitted centre, (drow, dcol) pixels.
    rms_residual_px : float
        Root-mean-square length of the residuals, pixels.
    n_detected : int
        Number of lenses kept in the final fit (N).
    """

    grid: LensletGrid
    centres_px: np.ndarray
    indices: np.ndarray
    residuals_px: np.ndarray
    rms_residual_px: float
    n_detected: int


def calibrate_grid(white, *, grid_type: str | None = None, pitch_px: float | None = None,
                   progress: bool = False) -> LensletGrid:
    """Measure the lenslet grid from a white image; see :func:`measure_grid`.

    Returns
    -------
    grid : LensletGrid
        The fitted lattice of microlens-image centres.
    """
    return measure_grid(white, grid_type=grid_type, pitch_px=pitch_px, progress=progress).grid


def measure_grid(white, *, grid_type: str | None = None, pitch_px: float | None = None,
                 progress: bool = False) -> GridMeasurement:
    """Measure the lattice of microlens-image centres from a white image.

    Parameters
    ----------
    white : (rows, cols) array_like
        White (flat-field) image taken through the microlens array, any real dtype;
        ``white[row, col]``.
    grid_type : {"hex", "rect"}, optional
        Packing of the microlens array. Detected from the image when omitted; when given,
        it must agree with the image.
    pitch_px : float, optional
        Nominal lens pitch in sensor pixels (e.g. ``CameraSpec.pixels_per_lenslet``). The
        measured pitch must then lie within 25 % of it. Measured in any case.
    progress : bool
        Show a progress bar on stderr.

    Returns
    -------
    GridMeasurement
        The fitted :class:`LensletGrid` and the per-lens detections and residuals.

    Raises
    ------
    InputFileError
        If ``white`` is not a 2-D array of finite real numbers.
    CalibrationError
        If the image is blank, shows no periodic lenslet pattern, shows the other packing
        than ``grid_type``, or shows too few lenses for a fit.

    Notes
    -----
    The lattice indices follow :class:`LensletGrid`: lens (0, 0) is the left-most lens of
    the top-most lens row whose centre lies on the sensor, rows run down the sensor and
    columns to the right. For a hexagonal grid the sign of ``odd_row_shift`` is chosen
    so that the lattice needs as few columns as possible, i.e. so that odd rows start
    where the sensor edge lets them. ``grid.shape`` covers every lens whose centre lies on
    the sensor, including partially visible edge lenses; lenses in the bounding index
    range whose centre falls off the sensor are included too (decoding masks them).
    """
    if grid_type is not None and grid_type not in ("hex", "rect"):
        raise CalibrationError(f"grid_type must be 'hex', 'rect' or None; got {grid_type!r}")
    if pitch_px is not None and not (math.isfinite(pitch_px) and pitch_px >= _MIN_PITCH_PX):
        raise CalibrationError(f"pitch_px must be a number >= {_MIN_PITCH_PX} pixels; "
                               f"got {pitch_px!r}")
    image = _validate_white(white)

    with _progress_bar(progress, total=1 + sum(_PASSES)) as advance:
        crop, crop_origin = _central_crop(image, _CROP_PX)
        col_step, row_step, found_type = _coarse_lattice(crop, pitch_px=pitch_px)
        if grid_type is not None and found_type != grid_type:
            raise CalibrationError(f"the white image shows a {found_type} lenslet grid but "
                                   f"grid_type={grid_type!r} was asked for; check the camera "
                                   "description")
        shift = 0.5 if found_type == "hex" else 0.0
        reference = crop_origin + _lattice_phase(crop, col_step, row_step, shift)
        advance()
        lattice = np.array([reference, col_step, row_step])
        radius = _WINDOW_RADIUS * float(np.hypot(*col_step))
        background = _background_level(crop)
        for stage_radius, passes in zip(_STAGE_RADII, _PASSES):
            for _ in range(passes):
                fit = _measure_and_fit(image, lattice, shift, stage_radius, radius, background)
                lattice = fit.lattice
                advance()

    grid, indices = _sensor_grid(lattice, shift, image.shape, fit.lens_rows, fit.lens_cols,
                                 found_type)
    residuals = fit.centres - fit.predicted
    return GridMeasurement(
        grid=grid,
        centres_px=fit.centres,
        indices=indices,
        residuals_px=residuals,
        rms_residual_px=float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1)))),
        n_detected=int(len(fit.centres)),
    )


# --- input ------------------------------------------------------------------------------

_KERNEL_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)


def _validate_white(white) -> np.ndarray:
    """Return ``white`` as a C-contiguous 2-D array the centroid kernel accepts."""
    image = np.asarray(white)
    if image.ndim != 2:
        raise InputFileError(f"white image must be 2-D (rows, cols); got shape {image.shape}")
    if not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)
            or image.dtype == bool):
        raise InputFileError(f"white image must hold real numbers; got dtype {image.dtype}")
    if image.dtype.type not in _KERNEL_DTYPES:
        image = image.astype(np.float32)
    image = np.ascontiguousarray(image)
    if image.dtype.kind == "f" and not np.isfinite(image).all():
        raise InputFileError("white image contains NaN or infinite values")
    if image.size == 0 or image.min() == image.max():
        raise CalibrationError("white image is blank (every pixel has the same value); "
                               "take the white image with the microlens array lit")
    return image


def _central_crop(image: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Central ``size`` x ``size`` crop (or smaller) as float64, and its (row, col) offset.

    The crop is clipped to its 1st-99th percentile range so that a few hot pixels or
    specks cannot dominate the coarse lattice estimate.
    """
    rows, cols = image.shape
    h, w = min(size, rows), min(size, cols)
    r0, c0 = (rows - h) // 2, (cols - w) // 2
    crop = image[r0:r0 + h, c0:c0 + w].astype(np.float64)
    return np.clip(crop, *np.percentile(crop, [1.0, 99.0])), np.array([r0, c0], dtype=float)


def _background_level(crop: np.ndarray) -> float:
    """Dark level between the discs: the 2nd percentile of the crop, image units."""
    return float(np.percentile(crop, 2.0))


# --- coarse lattice -------------------------------------------------------------------

def _autocorrelation(crop: np.ndarray) -> np.ndarray:
    """Normalised circular autocorrelation of the mean-free crop, zero lag at the centre."""
    x = crop - crop.mean()
    spectrum = np.fft.rfft2(x)
    acf = np.fft.irfft2(spectrum * spectrum.conj(), s=x.shape)
    acf /= acf[0, 0]
    return np.fft.fftshift(acf)


def _acf_peaks(acf: np.ndarray, min_lag: float, max_lag: float) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel local maxima of ``acf`` with lag in [min_lag, max_lag].

    Returns
    -------
    lags : (K, 2) float ndarray
        Peak positions relative to zero lag, (drow, dcol) pixels, nearest first.
    heights : (K,) float ndarray
        Normalised correlation at each peak.
    """
    centre = np.array(acf.shape) // 2
    is_peak = (acf == ndimage.maximum_filter(acf, size=3, mode="nearest"))
    is_peak &= acf >= _MIN_PEAK_CORRELATION
    is_peak[[0, -1], :] = False
    is_peak[:, [0, -1]] = False
    r, c = np.nonzero(is_peak)
    lag = np.stack([r - centre[0], c - centre[1]], axis=1).astype(float)
    length = np.hypot(lag[:, 0], lag[:, 1])
    keep = (length >= min_lag) & (length <= max_lag)
    r, c, lag, length = r[keep], c[keep], lag[keep], length[keep]
    # separable parabolic refinement around each integer maximum
    f0 = acf[r, c]
    d_row = _parabola_vertex(acf[r - 1, c], f0, acf[r + 1, c])
    d_col = _parabola_vertex(acf[r, c - 1], f0, acf[r, c + 1])
    lag = lag + np.stack([d_row, d_col], axis=1)
    order = np.argsort(np.hypot(lag[:, 0], lag[:, 1]))
    return lag[order], f0[order]


def _parabola_vertex(fm: np.ndarray, f0: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Offset of the vertex of the parabola through (-1, fm), (0, f0), (1, fp)."""
    curvature = fm - 2.0 * f0 + fp
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(curvature < 0, 0.5 * (fm - fp) / curvature, 0.0)
    return np.clip(offset, -0.5, 0.5)


def _coarse_lattice(crop: np.ndarray, *, pitch_px: float | None
                    ) -> tuple[np.ndarray, np.ndarray, str]:
    """Estimate the lattice steps and packing from the crop's autocorrelation.

    The nearest of the strongest peaks is a lattice vector; with a nominal ``pitch_px``
    it must lie within ``_PITCH_TOLERANCE`` of it.

    Returns
    -------
    col_step, row_step : (2,) float ndarray
        (drow, dcol) pixels, as in :class:`LensletGrid` (``row_step`` before the odd-row
        shift of +0.5 for a hexagonal grid).
    grid_type : {"hex", "rect"}
    """
    min_lag, max_lag = _MIN_PITCH_PX, min(crop.shape) / 4.0
    if pitch_px is not None:
        max_lag = max(max_lag, 1.5 * pitch_px)
    if max_lag < min_lag:
        raise CalibrationError(f"white image is {crop.shape[0]} x {crop.shape[1]} pixels, too "
                               "small to show several lenslets")
    lags, heights = _acf_peaks(_autocorrelation(crop), min_lag, 1.5 * max_lag)
    # lattice vectors correlate best; weaker peaks come from the pattern of the gaps
    if len(lags):
        strong = heights >= 0.8 * heights.max()
        lags, heights = lags[strong], heights[strong]
    lengths = np.hypot(lags[:, 0], lags[:, 1])
    nearest = lengths[lengths <= max_lag]
    if len(nearest) < 4:
        raise CalibrationError(_NO_GRID)
    pitch = nearest[0]
    if pitch_px is not None and abs(pitch / pitch_px - 1.0) > _PITCH_TOLERANCE:
        raise CalibrationError(f"the white image shows lenslets {pitch:.2f} px apart but "
                               f"pitch_px={pitch_px:g} was given; check the camera description")
    # first step: the nearest peak closest to the sensor row direction, pointing right
    candidates = lags[lengths < 1.1 * pitch]
    col_step = candidates[np.argmax(np.abs(candidates[:, 1]) / np.hypot(*candidates.T))]
    col_step = col_step if col_step[1] > 0 else -col_step
    if abs(col_step[0]) > abs(col_step[1]) * math.tan(math.radians(30)):
        raise CalibrationError(_NO_GRID)
    # second step: nearest peak off the first step's line, pointing down
    unit = col_step / np.hypot(*col_step)
    cross = np.abs(lags[:, 0] * unit[1] - lags[:, 1] * unit[0])
    off_line = lags[(cross > 0.5 * lengths * math.sin(math.radians(30))) & (lags[:, 0] > 0)]
    if len(off_line) == 0:
        raise CalibrationError(_NO_GRID)
    second_length = np.hypot(*off_line[0])
    ties = off_line[np.hypot(off_line[:, 0], off_line[:, 1]) < 1.1 * second_length]
    second = ties[np.argmax(ties @ unit)]  # the 60-degree neighbour on a hex grid
    angle = math.degrees(math.acos(np.clip(second @ unit / second_length, -1, 1)))
    ratio = second_length / np.hypot(*col_step)
    if abs(angle - 60.0) < 8.0 and abs(ratio - 1.0) < 0.1:
        return col_step, second - 0.5 * col_step, "hex"
    if abs(angle - 90.0) < 8.0:
        return col_step, second, "rect"
    raise CalibrationError(_NO_GRID)


def _lattice_phase(crop: np.ndarray, col_step: np.ndarray, row_step: np.ndarray,
                   shift: float, bins: int = 32) -> np.ndarray:
    """Position (row, col) in the crop of one lens centre near the crop centre.

    The crop pixels are folded onto one primitive lattice cell by their fractional
    lattice coordinates, giving the mean cell image ``M``. A lattice of centrally
    symmetric images is symmetric about its lens centres and about the midpoints between
    them; the periodic self-convolution of ``M`` peaks at twice any of these symmetry
    centres, which gives them to a fraction of a bin. Of the four candidates (a centre
    plus half lattice vectors) the lens centre is the brightest.
    """
    primitive = np.array([col_step, row_step + shift * col_step])  # rows: two lattice vectors
    centre = (np.array(crop.shape) - 1) / 2.0
    rr, cc = np.indices(crop.shape, dtype=float)
    offsets = np.stack([rr.ravel() - centre[0], cc.ravel() - centre[1]])
    frac = np.linalg.solve(primitive.T, offsets) % 1.0  # (2, npix): coefficients of the vectors
    cell = np.minimum((frac * bins).astype(np.int64), bins - 1)
    flat = cell[0] * bins + cell[1]
    sums = np.bincount(flat, weights=crop.ravel(), minlength=bins * bins)
    counts = np.bincount(flat, minlength=bins * bins)
    mean = (sums / np.maximum(counts, 1)).reshape(bins, bins)
    mean -= mean.mean()
    spectrum = np.fft.fft2(mean)
    self_conv = np.fft.ifft2(spectrum * spectrum).real
    k0, k1 = np.unravel_index(np.argmax(self_conv), self_conv.shape)
    f0 = self_conv[k0, k1]
    d0 = _parabola_vertex(self_conv[k0 - 1, k1], f0, self_conv[(k0 + 1) % bins, k1])
    d1 = _parabola_vertex(self_conv[k0, k1 - 1], f0, self_conv[k0, (k1 + 1) % bins])
    # bin b covers fractional coordinates [b, b + 1) / bins: its centre is (b + 0.5) / bins,
    # so a convolution index s stands for the sum of two coordinates (s + 1) / bins
    doubled = (np.array([k0 + d0, k1 + d1]) + 1.0) / bins
    candidates = (doubled / 2.0 + np.array([[0, 0], [0.5, 0], [0, 0.5], [0.5, 0.5]])) % 1.0
    smooth = ndimage.gaussian_filter(mean, sigma=1.0, mode="wrap")
    pick = np.minimum((candidates * bins).astype(np.int64), bins - 1)
    phase = candidates[np.argmax(smooth[pick[:, 0], pick[:, 1]])]
    return centre + phase @ primitive


# --- centroids and lattice fit ---------------------------------------------------------

def _window_tables(radius: float, taper: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-window offsets and weights of the symmetry window, for each half-pixel parity.

    A window centred on ``q`` (integer or half-integer in each axis) covers pixels
    ``x = q + d``; the point reflection pairs ``d`` with ``-d``, so only one of each pair
    is listed (the centre pixel, its own reflection, carries no information). Offsets are
    in doubled pixel units so that they are integers. The weight is 1 out to
    ``radius - taper`` pixels and falls to 0 at ``radius`` as a raised cosine.

    Returns
    -------
    offsets : (4, K, 2) int64 ndarray
        Doubled offsets ``2 d`` (rows, cols) for parity index ``2 * (2 q_row % 2) +
        (2 q_col % 2)``; rows beyond ``counts`` are unused.
    weights : (4, K) float64 ndarray
    counts : (4,) int64 ndarray
    """
    half = int(math.ceil(radius)) + 1
    tables = []
    for parity_r in (0, 1):
        for parity_c in (0, 1):
            # 2 d has the parity of 2 q, so that q + d is a pixel centre
            d2r, d2c = np.meshgrid(np.arange(-2 * half - parity_r, 2 * half + parity_r + 1, 2),
                                   np.arange(-2 * half - parity_c, 2 * half + parity_c + 1, 2),
                                   indexing="ij")
            d2r, d2c = d2r.ravel(), d2c.ravel()
            dist = 0.5 * np.hypot(d2r, d2c)
            first = (d2r > 0) | ((d2r == 0) & (d2c > 0))
            keep = first & (dist < radius)
            w = np.clip((radius - dist[keep]) / taper, 0.0, 1.0)
            w = 0.5 - 0.5 * np.cos(np.pi * w)
            tables.append((np.stack([d2r[keep], d2c[keep]], axis=1), w))
    size = max(len(w) for _, w in tables)
    offsets = np.zeros((4, size, 2), dtype=np.int64)
    weights = np.zeros((4, size))
    counts = np.zeros(4, dtype=np.int64)
    for index, (off, w) in enumerate(tables):
        offsets[index, :len(w)] = off
        weights[index, :len(w)] = w
        counts[index] = len(w)
    return offsets, weights, counts


@numba.njit(cache=True)
def _symmetry_step(image, q2r, q2c, offsets, weights, counts):  # pragma: no cover - compiled
    """Offset of the centre of point symmetry from the half-pixel position ``q``.

    ``q = (q2r, q2c) / 2``. With the patch ``P(x)`` and its point reflection
    ``F(x) = P(2q - x)``, to first order in the offset ``e`` of the symmetry centre from
    ``q``, ``P - F = -2 e . grad M`` with ``M = (P + F) / 2``. ``e`` is the weighted
    least-squares solution of that relation: a Lucas-Kanade step between the patch and
    its own reflection.

    Returns (e_row, e_col, mean window intensity, A_rr, A_rc, A_cc), NaN offsets when the
    window leaves the image or holds no structure; ``A`` is the normal matrix (weighted
    sums of gradient products), which :func:`_reflected_step` reuses.
    """
    rows, cols = image.shape
    table = 2 * (q2r & 1) + (q2c & 1)
    arr = arc = acc = br = bc = sw = sm = 0.0
    for m in range(counts[table]):
        d2r = offsets[table, m, 0]
        d2c = offsets[table, m, 1]
        r = (q2r + d2r) // 2
        c = (q2c + d2c) // 2
        rr = (q2r - d2r) // 2
        cc = (q2c - d2c) // 2
        if min(r, rr) < 1 or max(r, rr) > rows - 2 or min(c, cc) < 1 or max(c, cc) > cols - 2:
            return np.nan, np.nan, np.nan, 0.0, 0.0, 0.0
        w = weights[table, m]
        p = float(image[r, c])
        f = float(image[rr, cc])
        gr = 0.25 * (float(image[r + 1, c]) - float(image[r - 1, c])
                     + float(image[rr - 1, cc]) - float(image[rr + 1, cc]))
        gc = 0.25 * (float(image[r, c + 1]) - float(image[r, c - 1])
                     + float(image[rr, cc - 1]) - float(image[rr, cc + 1]))
        d = p - f
        arr += w * gr * gr
        arc += w * gr * gc
        acc += w * gc * gc
        br += w * d * gr
        bc += w * d * gc
        sw += w
        sm += w * (p + f)
    det = arr * acc - arc * arc
    if sw == 0.0 or det <= 1e-12 * (arr + acc) * (arr + acc):
        return np.nan, np.nan, np.nan, 0.0, 0.0, 0.0
    er = -0.5 * (acc * br - arc * bc) / det
    ec = -0.5 * (arr * bc - arc * br) / det
    return er, ec, 0.5 * sm / sw, arr, arc, acc


@numba.njit(cache=True)
def _bilinear(image, r, c, fr, fc):  # pragma: no cover - compiled
    """Image at (r + fr, c + fc), bilinear, for integer r, c and 0 <= fr, fc < 1."""
    top = (1.0 - fc) * float(image[r, c]) + fc * float(image[r, c + 1])
    bottom = (1.0 - fc) * float(image[r + 1, c]) + fc * float(image[r + 1, c + 1])
    return (1.0 - fr) * top + fr * bottom


@numba.njit(cache=True)
def _reflected_step(image, q2r, q2c, er, ec, offsets, weights, counts, arr, arc, acc
                    ):  # pragma: no cover - compiled
    """Correction to a centre ``c = q + e`` found by :func:`_symmetry_step`.

    Compares each window pixel with the image reflected about ``c`` itself (bilinear
    interpolation), which removes the error of the first-order model when ``e`` is a
    sizeable fraction of a pixel. The normal matrix ``A`` of that step is reused.
    Returns the (row, col) correction, NaN off the image.
    """
    rows, cols = image.shape
    table = 2 * (q2r & 1) + (q2c & 1)
    sr = 2.0 * er
    sc = 2.0 * ec
    ir = int(math.floor(sr))
    ic = int(math.floor(sc))
    fr = sr - ir
    fc = sc - ic
    br = bc = 0.0
    for m in range(counts[table]):
        d2r = offsets[table, m, 0]
        d2c = offsets[table, m, 1]
        r = (q2r + d2r) // 2
        c = (q2c + d2c) // 2
        rr = (q2r - d2r) // 2
        cc = (q2c - d2c) // 2
        lo_r = min(r, rr) + min(ir, 0)
        hi_r = max(r, rr) + max(ir + 1, 0)
        lo_c = min(c, cc) + min(ic, 0)
        hi_c = max(c, cc) + max(ic + 1, 0)
        if lo_r < 1 or hi_r > rows - 2 or lo_c < 1 or hi_c > cols - 2:
            return np.nan, np.nan
        w = weights[table, m]
        # the reflection about c of x = q + d is (q - d) + 2e, that of q - d is x + 2e
        d1 = float(image[r, c]) - _bilinear(image, rr + ir, cc + ic, fr, fc)
        d2 = float(image[rr, cc]) - _bilinear(image, r + ir, c + ic, fr, fc)
        gr = 0.25 * (float(image[r + 1, c]) - float(image[r - 1, c])
                     + float(image[rr - 1, cc]) - float(image[rr + 1, cc]))
        gc = 0.25 * (float(image[r, c + 1]) - float(image[r, c - 1])
                     + float(image[rr, cc - 1]) - float(image[rr, cc + 1]))
        d = 0.5 * (d1 - d2)
        br += w * d * gr
        bc += w * d * gc
    det = arr * acc - arc * arc
    return -0.5 * (acc * br - arc * bc) / det, -0.5 * (arr * bc - arc * br) / det


@numba.njit(parallel=True, cache=True)
def _symmetry_centres(image, predicted, offsets, weights, counts, reach, max_steps, refine
                      ):  # pragma: no cover - compiled
    """Centre of point symmetry of the image near each predicted centre.

    Repeats :func:`_symmetry_step`, moving the window to the half pixel nearest the
    centre found, until the centre lies within ``_SETTLED_PX`` of the window centre (at
    most ``max_steps`` times).

    Parameters
    ----------
    image : (rows, cols) ndarray
    predicted : (N, 2) float64 ndarray
        Starting positions (row, col), pixels.
    offsets, weights, counts : ndarray
        Window tables from :func:`_window_tables`.
    reach : float
        Centres farther than this from their prediction (pixels) are dropped.
    max_steps : int

    Returns
    -------
    centres : (N, 2) float64 ndarray
        (row, col) pixels; NaN where the window left the image, the patch held no
        structure, the steps did not settle or the centre wandered beyond ``reach``.
    level : (N,) float64 ndarray
        Mean intensity in the final window.
    """
    n = predicted.shape[0]
    out = np.full((n, 2), np.nan)
    level = np.full(n, np.nan)
    for k in numba.prange(n):
        q2r = int(round(2.0 * predicted[k, 0]))
        q2c = int(round(2.0 * predicted[k, 1]))
        for _ in range(max_steps):
            er, ec, mean, arr, arc, acc = _symmetry_step(image, q2r, q2c, offsets, weights,
                                                         counts)
            if not math.isfinite(er):
                break
            cr = 0.5 * q2r + er
            cc = 0.5 * q2c + ec
            if abs(er) <= _SETTLED_PX and abs(ec) <= _SETTLED_PX:
                for _ in range(refine):
                    dr, dc = _reflected_step(image, q2r, q2c, cr - 0.5 * q2r, cc - 0.5 * q2c,
                                             offsets, weights, counts, arr, arc, acc)
                    if math.isfinite(dr) and abs(dr) < 0.5 and abs(dc) < 0.5:
                        cr += dr
                        cc += dc
                if math.hypot(cr - predicted[k, 0], cc - predicted[k, 1]) < reach:
                    out[k, 0] = cr
                    out[k, 1] = cc
                    level[k] = mean
                break
            q2r = int(round(2.0 * cr))
            q2c = int(round(2.0 * cc))
    return out, level


def _lenses_in_box(lattice: np.ndarray, shift: float, box: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Lattice indices (n, k) of every lens whose centre lies inside ``box``.

    Parameters
    ----------
    lattice : (3, 2) float ndarray
        Rows: position of lens (0, 0), column step, row step, (row, col) pixels.
    shift : float
        Odd-row shift: lens (n, k) sits at ``origin + (k + shift * (n % 2)) * col_step +
        n * row_step``.
    box : (2, 2) float ndarray
        ``[[row_min, col_min], [row_max, col_max]]``, pixels, inclusive.

    Returns
    -------
    n, k : (M,) int64 ndarrays
    """
    origin, col_step, row_step = lattice
    corners = np.array([[box[i, 0], box[j, 1]] for i in (0, 1) for j in (0, 1)])
    basis = np.array([col_step, row_step]).T
    n_corner = np.linalg.solve(basis, (corners - origin).T)[1]
    n = np.arange(math.floor(n_corner.min()) - 1, math.ceil(n_corner.max()) + 2)
    # along row n the centre is base + t * col_step; intersect the box constraints on t
    base = origin + n[:, None] * row_step + (shift * (n % 2))[:, None] * col_step
    t_lo = np.full(len(n), -np.inf)
    t_hi = np.full(len(n), np.inf)
    for axis in (0, 1):
        step = col_step[axis]
        if abs(step) < 1e-12:
            inside = (base[:, axis] >= box[0, axis]) & (base[:, axis] <= box[1, axis])
            t_hi[~inside] = -np.inf
            continue
        a = (box[0, axis] - base[:, axis]) / step
        b = (box[1, axis] - base[:, axis]) / step
        t_lo = np.maximum(t_lo, np.minimum(a, b))
        t_hi = np.minimum(t_hi, np.maximum(a, b))
    k_lo = np.ceil(t_lo - 1e-9)
    k_hi = np.floor(t_hi + 1e-9)
    count = np.where(np.isfinite(k_lo) & np.isfinite(k_hi), k_hi - k_lo + 1, 0)
    count = np.maximum(count, 0).astype(np.int64)
    rows = np.repeat(n, count)
    starts = np.repeat(np.where(count > 0, k_lo, 0).astype(np.int64), count)
    within = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    return rows, starts + within


def _lens_positions(lattice: np.ndarray, shift: float, n: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Centres (M, 2) of lenses (n, k) under ``lattice`` (see :func:`_lenses_in_box`)."""
    return _design(n, k, shift) @ lattice


def _design(n: np.ndarray, k: np.ndarray, shift: float) -> np.ndarray:
    """Design matrix (M, 3) of the affine lattice: columns 1, k + shift (n % 2), n."""
    return np.stack([np.ones(len(n)), k + shift * (n % 2), n.astype(float)], axis=1)


@dataclass(frozen=True)
class _Fit:
    lattice: np.ndarray      # (3, 2): origin, col_step, row_step
    lens_rows: np.ndarray    # (N,) lattice row n of kept lenses
    lens_cols: np.ndarray    # (N,) lattice column k of kept lenses
    centres: np.ndarray      # (N, 2) measured centres
    predicted: np.ndarray    # (N, 2) fitted centres


def _measure_and_fit(image: np.ndarray, lattice: np.ndarray, shift: float,
                     stage_radius: float, window_radius: float, background: float) -> _Fit:
    """Measure the centres of the lenses near the reference lens and refit the lattice.

    Lenses within ``stage_radius`` pitches of the reference (all when infinite) whose
    window lies on the image are measured; unlit ones (window level above the gaps below
    ``_MIN_LEVEL_FRACTION`` of the median) and the fit's outliers are dropped.
    """
    pitch = float(np.hypot(*lattice[1]))
    margin = math.ceil(window_radius) + 1
    box = np.array([[margin, margin], [image.shape[0] - 1 - margin, image.shape[1] - 1 - margin]],
                   dtype=float)
    if math.isfinite(stage_radius):
        reach = stage_radius * pitch
        box = np.clip(lattice[0] + np.array([[-reach], [reach]]), box[0], box[1])
    n, k = _lenses_in_box(lattice, shift, box)
    if len(n) < _MIN_LENSES:
        raise CalibrationError(f"the white image shows only {len(n)} whole lenslets; at least "
                               f"{_MIN_LENSES} are needed to fit the grid")
    predicted = _lens_positions(lattice, shift, n, k)
    tables = _window_tables(window_radius, _WINDOW_TAPER_PX)
    centres, level = _symmetry_centres(image, predicted, *tables, window_radius, _MAX_STEPS,
                                       _REFINE_STEPS)
    ok = np.isfinite(centres[:, 0])
    level = level - background
    ok[ok] = level[ok] > _MIN_LEVEL_FRACTION * np.median(level[ok])
    n, k, centres = n[ok], k[ok], centres[ok]
    if len(n) < _MIN_LENSES:
        raise CalibrationError(f"only {len(n)} lenslets are lit in the white image; at least "
                               f"{_MIN_LENSES} are needed to fit the grid")
    design = _design(n, k, shift)
    lattice, inlier = _robust_lstsq(design, centres)
    n, k, centres = n[inlier], k[inlier], centres[inlier]
    return _Fit(lattice, n, k, centres, design[inlier] @ lattice)


def _robust_lstsq(design: np.ndarray, targets: np.ndarray, rounds: int = 3
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``design @ params = targets`` with iterative 3-sigma MAD rejection.

    Returns the (3, 2) parameters and the (M,) bool inlier mask.
    """
    inlier = np.ones(len(design), dtype=bool)
    for _ in range(rounds):
        params = np.linalg.lstsq(design[inlier], targets[inlier], rcond=None)[0]
        residual = targets - design @ params
        median = np.median(residual[inlier], axis=0)
        sigma = 1.4826 * np.median(np.abs(residual[inlier] - median), axis=0)
        sigma = np.maximum(sigma, 1e-3)
        new = np.all(np.abs(residual - median) <= _REJECT_SIGMA * sigma, axis=1)
        if new.sum() < max(_MIN_LENSES, design.shape[1]) or np.array_equal(new, inlier):
            break
        inlier = new
    params = np.linalg.lstsq(design[inlier], targets[inlier], rcond=None)[0]
    return params, inlier


# --- sensor indexing ------------------------------------------------------------------

def _sensor_grid(lattice: np.ndarray, shift: float, sensor_shape: tuple[int, int],
                 n: np.ndarray, k: np.ndarray, grid_type: str
                 ) -> tuple[LensletGrid, np.ndarray]:
    """Express the fitted lattice as a :class:`LensletGrid` covering the sensor.

    ``lattice`` indexes lenses (n, k) relative to the reference lens with odd-row shift
    ``shift`` on odd ``n``. The result re-indexes them so that (0, 0) is the top-left lens
    on the sensor, choosing the sign of the hexagonal shift that needs fewest columns.

    Returns the grid and the (M, 2) indices (i, j) of the lenses (n, k).
    """
    sensor = np.array([[-0.5, -0.5], [sensor_shape[0] - 0.5, sensor_shape[1] - 0.5]])
    origin, col_step, row_step = lattice
    best = None
    # Both signs of a hexagonal shift describe the same centres (lens (n, k) with shift
    # +0.5 is lens (n, k + n % 2) with shift -0.5); they differ in where rows start.
    for s in ((0.5, -0.5) if shift else (0.0,)):
        on_n, on_k = _lenses_in_box(lattice, s, sensor)
        if len(on_n) == 0:
            raise CalibrationError(_NO_GRID)
        n0, k0 = int(on_n.min()), int(on_k.min())
        shape = (int(on_n.max()) - n0 + 1, int(on_k.max()) - k0 + 1)
        if best is None or shape[1] < best[1][1]:
            best = (s, shape, n0, k0)
    s, shape, n0, k0 = best
    grid_shift = (s if n0 % 2 == 0 else -s) + 0.0  # never -0.0
    grid_origin = origin + (k0 + s * (n0 % 2)) * col_step + n0 * row_step
    grid = LensletGrid(grid_type, shape, tuple(grid_origin), tuple(col_step), tuple(row_step),
                       grid_shift, tuple(sensor_shape))
    k_in_s = k + (shift - s) * (n % 2)  # fitted column index re-expressed with shift s
    indices = np.stack([n - n0, np.rint(k_in_s).astype(np.int64) - k0], axis=1).astype(np.int64)
    return grid, indices


# --- progress ---------------------------------------------------------------------------

@contextlib.contextmanager
def _progress_bar(enabled: bool, total: int) -> Iterator:
    """Yield an ``advance()`` callable, drawing a rich progress bar when ``enabled``."""
    if not enabled:
        yield lambda: None
        return
    from rich.progress import Progress

    with Progress(transient=True) as bar:
        task = bar.add_task("lenslet grid", total=total)
        yield lambda: bar.advance(task)
