"""The refocusing-based particle locator (the baseline the perspective-shift method replaced),
and the hybrid that refines perspective-shift depths with a local focal stack.

Refocusing method (Hall et al. 2018, the method paper's ref. [20]):

1. decode the raw image and refocus it to a dense stack of planes spanning the volume
   (at least 100 by default) by shift-and-add over the valid views (compiled, parallel);
2. find particles in plane by **minimum intensity**: the per-pixel minimum over the stack
   is segmented for dark regions (each particle is darkest in its in-focus plane);
3. find each particle's depth by **maximum edge sharpness**: the gradient energy (squared
   Sobel magnitude) summed in a window around the particle, in every plane; the peak,
   refined by a parabola, gives the in-focus plane;
4. measure the in-focus image: the dark region at the in-focus plane gives the in-plane
   centroid and the size;
5. convert to object space through the calibration (DLFC): the in-focus plane and
   centroid define the ray of the particle in every view (its position in view
   ``(u, v)`` is the centroid shifted by the refocus parallax of that plane), and the
   DLFC triangulation turns those rays into ``(x, y, z)`` (mm).

A particle whose focus curve has no interior peak (the sharpest plane is an end of the
stack) or whose peak does not stand out of the curve (peak sharpness below
``min_peak_ratio`` times the curve's median: it cannot be brought into focus) gives no
measurement, as in the original method far outside the depth of field.

The stack is refocused without the ``1/alpha`` magnification of
:func:`~plenoptrack.lightfield.refocus.refocus` (views are shifted only): a particle's
image then stays at its central-view position in every plane, so its sharpness window
does not drift across the stack. Sample ``(t, s)`` of every plane is sample ``(t, s)`` of
the central view ``u = v = 0``.

References
----------
E. M. Hall, D. R. Guildenbecher, B. S. Thurow, "Uncertainty characterization of particle
location from refocused plenoptic images", Opt. Express 25 (2017); and "Development and
uncertainty characterization of 3D particle location from perspective shifted plenoptic
images", Opt. Express 27 (2019) (``seeds/001``), sections 3-4.
J. T. Bolan et al. / E. Deem et al. (2016) on the depth of field of refocused plenoptic
images: the extended depth of field is that of one perspective view.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import asdict, dataclass

import numba
import numpy as np
import pandas as pd
from scipy import ndimage

from .._columns import POS_COLUMNS, T_COLUMN
from ..errors import NoParticlesWarning, SettingsError
from ..lightfield.decode import LightField
from ..lightfield.refocus import view_shift_per_u
from .perspective import (PARTICLE_COLUMNS, LocateResult, PerspectiveLocator, _decoded,
                          locate_frame)
from .segment import segment_array
from .triangulate import triangulate_clusters

__all__ = ["RefocusLocator", "HybridLocator", "locate_frame_refocus", "locate_frame_hybrid",
           "window_stack", "parallax_per_u", "alpha_for_parallax", "depth_of_field_mm",
           "focus_peaks"]


# --- geometry -------------------------------------------------------------------------

def depth_of_field_mm(camera, *, extended: bool = True) -> tuple[float, float]:
    """Near and far depth-of-field limits of a plenoptic camera, mm (z, 0 at focus).

    A point is in focus while its blur on the microlens array is at most one microlens
    pitch. Through the whole aperture (``extended=False``) that is the depth of field of
    the main lens; a refocused or perspective image has the depth of field of one
    sub-aperture, ``n_u`` (microlens pitch in pixels) times smaller, so ``extended=True``
    (the default, the plenoptic depth of field used to normalise depth in the
    uncertainty study) uses the aperture diameter ``D / n_u``.

    Returns
    -------
    (near, far) : (float, float)
        ``near < 0`` (towards the camera), ``far > 0``, mm.
    """
    d_ap = camera.aperture_diameter_mm
    if extended:
        d_ap = d_ap / camera.pixels_per_lenslet
    ratio = camera.microlens_pitch_um * 1e-3 / d_ap
    near = float(camera.depth_for_alpha(1.0 / (1.0 - ratio))) if ratio < 1 else -math.inf
    far = float(camera.depth_for_alpha(1.0 / (1.0 + ratio)))
    return near, far


def parallax_per_u(lf: LightField, camera, alpha) -> np.ndarray:
    """Parallax of a point imaged at ``alpha``: in-view displacement per unit ``u``
    (and ``v``), view pixels (:func:`~plenoptrack.lightfield.refocus.view_shift_per_u`
    over the sample spacing)."""
    return view_shift_per_u(camera, alpha) / lf.sample_spacing_px


def alpha_for_parallax(lf: LightField, camera, parallax) -> np.ndarray:
    """Inverse of :func:`parallax_per_u`: the refocus parameter of a parallax (view px
    per unit ``u``)."""
    k = np.asarray(parallax, dtype=float) * lf.sample_spacing_px
    s_i = camera.image_distance_mm
    f_ml = camera.microlens_focal_length_um * 1e-3
    return 1.0 / (1.0 + k * f_ml / (s_i + f_ml))


def _view_offsets(lf: LightField, sel: np.ndarray, parallax: np.ndarray) -> np.ndarray:
    """(n_planes, n_sel, 2) offsets ``(dt, ds)`` in view pixels of each selected view for
    each plane's parallax (view pixels per unit u), through the sample geometry."""
    u = lf.u[sel[:, 1]]
    v = lf.v[sel[:, 0]]
    # parallax is along (row, col) on the sensor; map to (t, s) samples with the step matrix
    k = parallax[:, None] * lf.sample_spacing_px          # sensor px per unit u
    d_rc = np.stack([v[None, :] * k, u[None, :] * k], axis=-1)
    inv = np.linalg.inv(lf.step_matrix)
    return np.ascontiguousarray(d_rc @ inv.T)


# --- compiled windowed focal stack ----------------------------------------------------

@numba.njit(parallel=True, cache=True, nogil=True)
def _window_stack(data, mask, sel, dts, ax_t, ax_s, inv_alpha, t0, s0, out):  # pragma: no cover
    n_p = out.shape[0]
    n_t = out.shape[1]
    n_s = out.shape[2]
    src_t = data.shape[2]
    src_s = data.shape[3]
    n_w = sel.shape[0]
    for job in numba.prange(n_p * n_t):
        p = job // n_t
        t = t0 + job % n_t
        acc = np.zeros(n_s)
        wsum = np.zeros(n_s)
        ia = inv_alpha[p]
        tb = ax_t + (t - ax_t) * ia
        for k in range(n_w):
            iv = sel[k, 0]
            iu = sel[k, 1]
            tq = tb + dts[p, k, 0]
            ti0 = int(math.floor(tq))
            if ti0 < -1 or ti0 > src_t - 1:
                continue
            ft = tq - ti0
            for j in range(n_s):
                sq = ax_s + (s0 + j - ax_s) * ia + dts[p, k, 1]
                si0 = int(math.floor(sq))
                if si0 < -1 or si0 > src_s - 1:
                    continue
                fs = sq - si0
                for dt in range(2):
                    ti = ti0 + dt
                    if ti < 0 or ti >= src_t:
                        continue
                    wt = ft if dt else 1.0 - ft
                    for ds in range(2):
                        si = si0 + ds
                        if si < 0 or si >= src_s:
                            continue
                        w = wt * (fs if ds else 1.0 - fs) * mask[ti, si]
                        acc[j] += w * data[iv, iu, ti, si]
                        wsum[j] += w
        for j in range(n_s):
            out[p, t - t0, j] = acc[j] / wsum[j] if wsum[j] > 1e-6 else 0.0


@numba.njit(parallel=True, cache=True, nogil=True)
def _shift_stack(dm, mask, sel, dts, t0, s0, out):  # pragma: no cover - compiled
    """Shift-only stack: every view is shifted by a constant, so the bilinear weights are
    the same along a row and each tap is a run over contiguous samples. ``dm`` is the
    light field times the spatial mask."""
    n_p = out.shape[0]
    n_t = out.shape[1]
    n_s = out.shape[2]
    src_t = dm.shape[2]
    src_s = dm.shape[3]
    n_w = sel.shape[0]
    for job in numba.prange(n_p * n_t):
        p = job // n_t
        t = t0 + job % n_t
        acc = np.zeros(n_s)
        wsum = np.zeros(n_s)
        for k in range(n_w):
            iv = sel[k, 0]
            iu = sel[k, 1]
            tq = t + dts[p, k, 0]
            ti0 = int(math.floor(tq))
            ft = tq - ti0
            sq = s0 + dts[p, k, 1]
            si0 = int(math.floor(sq))
            fs = sq - si0
            for dt in range(2):
                ti = ti0 + dt
                if ti < 0 or ti >= src_t:
                    continue
                wt = ft if dt else 1.0 - ft
                if wt == 0.0:
                    continue
                for ds in range(2):
                    w = wt * (fs if ds else 1.0 - fs)
                    if w == 0.0:
                        continue
                    off = si0 + ds
                    j0 = max(0, -off)
                    j1 = min(n_s, src_s - off)
                    for j in range(j0, j1):
                        acc[j] += w * dm[iv, iu, ti, j + off]
                        wsum[j] += w * mask[ti, j + off]
        for j in range(n_s):
            out[p, t - t0, j] = acc[j] / wsum[j] if wsum[j] > 1e-6 else 0.0


def window_stack(lf: LightField, camera, alphas, *, origin_ts=(0, 0), shape_ts=None,
                 views: np.ndarray | None = None, magnify: bool = False) -> np.ndarray:
    """Focal stack of a window of the view grid, by compiled shift-and-add.

    Parameters
    ----------
    lf : LightField
        Decoded (ideally flat-fielded) light field.
    camera : CameraSpec
        Nominal camera (``s_i``, ``f_ml``).
    alphas : (n,) array_like
        Refocus parameters of the planes.
    origin_ts : (int, int)
        First sample ``(t, s)`` of the window.
    shape_ts : (int, int), optional
        Window size ``(rows, cols)``; default the rest of the view.
    views : (n_v, n_u) bool ndarray, optional
        Views to add; default ``lf.view_mask``.
    magnify : bool
        False (default): views are only shifted, so sample ``(t, s)`` of every plane is
        sample ``(t, s)`` of the central view. True: also magnified by ``1/alpha`` about
        the axis, as :func:`~plenoptrack.lightfield.refocus.refocus` does (then the full
        window equals :func:`~plenoptrack.lightfield.refocus.focal_stack`).

    Returns
    -------
    (n, rows, cols) float32 ndarray
        Mean over the views of the bilinearly interpolated, spatially masked samples;
        0 where no view contributes.
    """
    alphas = np.atleast_1d(np.asarray(alphas, dtype=float))
    if alphas.ndim != 1 or not np.all(np.isfinite(alphas) & (alphas > 0)):
        raise SettingsError(f"alphas must be a 1-D array of positive numbers; got {alphas!r}")
    show = lf.view_mask if views is None else np.asarray(views, dtype=bool)
    sel = np.argwhere(show).astype(np.int64)
    if len(sel) == 0:
        raise SettingsError("no views selected for refocusing")
    t0, s0 = (int(c) for c in origin_ts)
    if shape_ts is None:
        shape_ts = (lf.view_shape[0] - t0, lf.view_shape[1] - s0)
    h, w = (int(c) for c in shape_ts)
    if h < 1 or w < 1:
        raise SettingsError(f"shape_ts must be positive; got {shape_ts}")
    dts = _view_offsets(lf, sel, parallax_per_u(lf, camera, alphas))
    ax_s, ax_t = lf.axis_st
    mask = lf.spatial_mask.astype(np.float32)
    out = np.empty((len(alphas), h, w), dtype=np.float32)
    if magnify:
        _window_stack(lf.data, mask, sel, dts, float(ax_t), float(ax_s), 1.0 / alphas, t0, s0,
                      out)
    else:
        _shift_stack(_masked(lf), mask, sel, dts, t0, s0, out)
    return out


_MASKED: dict = {}


def _masked(lf: LightField) -> np.ndarray:
    """``lf.data`` times the spatial mask (float32), kept for the last light field."""
    key = id(lf.data)
    hit = _MASKED.get("key")
    if hit is None or hit[0] != key or hit[1] is not lf.data:
        _MASKED["key"] = (key, lf.data, lf.data * lf.spatial_mask.astype(np.float32))
    return _MASKED["key"][2]


# --- focus measure --------------------------------------------------------------------

def _gradient_energy(stack: np.ndarray, smooth_px: float = 1.0) -> np.ndarray:
    """Squared Sobel gradient magnitude of every plane after a Gaussian of ``smooth_px``
    (pixels) in-plane, (n, rows, cols) float32.

    The smoothing evens out the interpolation blur of shift-and-add, which changes with
    the fractional part of the view shifts: unsmoothed, planes where the shifts are
    near-integer (around the focal plane) look sharper than their neighbours whatever
    their content, and pull focus peaks towards them.
    """
    st = np.asarray(stack, dtype=np.float32)
    if smooth_px > 0:
        st = ndimage.gaussian_filter(st, (0, smooth_px, smooth_px), mode="nearest")
    gt = ndimage.correlate1d(ndimage.correlate1d(st, [-1.0, 0.0, 1.0], axis=1, mode="nearest"),
                             [1.0, 2.0, 1.0], axis=2, mode="nearest")
    gs = ndimage.correlate1d(ndimage.correlate1d(st, [-1.0, 0.0, 1.0], axis=2, mode="nearest"),
                             [1.0, 2.0, 1.0], axis=1, mode="nearest")
    return gt * gt + gs * gs


def focus_peaks(curves: np.ndarray, positions) -> pd.DataFrame:
    """Peak of each focus curve, refined by a parabola, and the curve's width.

    Parameters
    ----------
    curves : (n_particles, n_planes) float ndarray
        Sharpness of each particle in each plane (larger is sharper).
    positions : (n_planes,) float ndarray
        Coordinate of each plane (e.g. alpha or nominal depth), monotonic.

    Returns
    -------
    DataFrame
        ``index`` (int, plane of the maximum), ``peak`` (refined coordinate, NaN when
        the maximum is at either end), ``interior`` (bool), ``ratio`` (peak over the
        curve's median) and ``fwhm`` (full width at half maximum above the curve's
        minimum, in the units of ``positions``, from linear interpolation on each side).
    """
    c = np.asarray(curves, dtype=float)
    x = np.asarray(positions, dtype=float)
    n, m = c.shape
    k = np.argmax(c, axis=1) if m else np.zeros(n, dtype=int)
    interior = (k > 0) & (k < m - 1)
    kk = np.clip(k, 1, max(m - 2, 1))
    rows = np.arange(n)
    y0, y1, y2 = c[rows, kk - 1], c[rows, kk], c[rows, kk + 1]
    den = y0 - 2 * y1 + y2
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.where(den < 0, 0.5 * (y0 - y2) / den, 0.0)
    off = np.clip(off, -0.5, 0.5)
    frac = np.where(interior, k + off, np.nan)
    peak = np.interp(np.nan_to_num(frac), np.arange(m), x)
    peak = np.where(interior, peak, np.nan)
    lo = c.min(axis=1)
    hi = c[rows, k]
    half = lo + 0.5 * (hi - lo)
    width = np.full(n, np.nan)
    for i in range(n):
        above = c[i] >= half[i]
        left = k[i]
        while left > 0 and above[left - 1]:
            left -= 1
        right = k[i]
        while right < m - 1 and above[right + 1]:
            right += 1
        if left == 0 or right == m - 1:
            continue
        # linear crossing between (left-1, left) and (right, right+1)
        fl = (half[i] - c[i, left - 1]) / (c[i, left] - c[i, left - 1])
        fr = (c[i, right] - half[i]) / (c[i, right] - c[i, right + 1])
        xl = np.interp(left - 1 + fl, np.arange(m), x)
        xr = np.interp(right + fr, np.arange(m), x)
        width[i] = abs(xr - xl)
    med = np.median(c, axis=1) if m else np.zeros(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(med > 0, hi / med, np.inf)
    return pd.DataFrame({"index": k.astype(np.int64), "peak": peak, "interior": interior,
                         "ratio": ratio, "fwhm": width})


def _window_curves(energy: np.ndarray, centres_ts: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Gradient energy summed over a square window per particle, (n_particles, n_planes)."""
    n_t, n_s = energy.shape[1:]
    out = np.empty((len(centres_ts), energy.shape[0]))
    for i, ((t, s), hw) in enumerate(zip(centres_ts, half)):
        t, s, hw = int(round(t)), int(round(s)), int(hw)
        win = energy[:, max(t - hw, 0):min(t + hw + 1, n_t), max(s - hw, 0):min(s + hw + 1, n_s)]
        out[i] = win.sum(axis=(1, 2))
    return out


# --- settings -------------------------------------------------------------------------

@dataclass(frozen=True)
class RefocusLocator:
    """Settings of the refocusing-based locator.

    Parameters
    ----------
    n_planes : int
        Planes of the focal stack (at least 2; the method needs a dense stack, default
        100), evenly spaced in nominal depth over ``depth_range_mm``.
    depth_range_mm : (float, float), optional
        Nominal depth range of the stack, mm; default the z range of the DLFC's dot
        cards.
    window : int
        Side of the local-background window of the in-plane segmentation, pixels.
    contrast : float
        A particle pixel of the minimum-intensity image (and of the in-focus image) is
        darker than its local background by at least this fraction.
    area_range : (float, float)
        Accepted region areas in the minimum-intensity image, pixels.
    window_margin_px : float
        The sharpness window spans the particle's region plus this margin each side.
    min_peak_ratio : float
        A focus curve whose peak is below this multiple of its median has no usable
        focus (the particle cannot be brought into focus): no measurement.
    """

    n_planes: int = 100
    depth_range_mm: tuple[float, float] | None = None
    window: int = 31
    contrast: float = 0.15
    area_range: tuple[float, float] = (2.0, math.inf)
    window_margin_px: float = 3.0
    min_peak_ratio: float = 1.5

    def __post_init__(self) -> None:
        if self.n_planes < 3:
            raise SettingsError(f"n_planes must be at least 3; got {self.n_planes}")
        if self.window < 3:
            raise SettingsError(f"window must be at least 3 pixels; got {self.window}")
        if not 0 < self.contrast < 1:
            raise SettingsError(f"contrast must be between 0 and 1; got {self.contrast}")
        if self.depth_range_mm is not None and not self.depth_range_mm[1] > self.depth_range_mm[0]:
            raise SettingsError(f"depth_range_mm must be (near, far) with far > near; got "
                                f"{self.depth_range_mm}")
        if not self.min_peak_ratio >= 1:
            raise SettingsError(f"min_peak_ratio must be at least 1; got {self.min_peak_ratio}")
        if not self.window_margin_px >= 0:
            raise SettingsError(f"window_margin_px must be >= 0; got {self.window_margin_px}")

    def to_dict(self) -> dict:
        """The settings as nested plain data (for provenance in output metadata)."""
        return asdict(self)

    def settings(self) -> dict:
        """Same as :meth:`to_dict`."""
        return self.to_dict()

    def locate(self, raw_or_lf, calibration, *, frame: int = 0, white=None) -> LocateResult:
        """Locate the particles of one frame; see :func:`locate_frame_refocus`."""
        return locate_frame_refocus(raw_or_lf, calibration, frame=frame, locator=self,
                                    white=white)


@dataclass(frozen=True)
class HybridLocator:
    """Settings of the hybrid locator: perspective-shift positions whose depth is refined
    by a local focal stack around each particle where refocusing is sharp.

    Parameters
    ----------
    perspective : PerspectiveLocator
        Settings of the perspective-shift step.
    n_planes : int
        Planes of each particle's local stack.
    half_range_sigma : float
        The local stack spans the perspective depth +- this many ``sigma_z`` (clipped to
        ``half_range_mm``).
    half_range_mm : (float, float)
        Smallest and largest half range of the local stack, nominal mm.
    max_depth_fraction : float
        Depths are refined only for particles whose perspective depth lies within this
        fraction of the plenoptic depth of field (:func:`depth_of_field_mm`), where a
        refocused particle is sharp; elsewhere the perspective depth is kept.
    contrast, window_margin_px, min_peak_ratio
        As in :class:`RefocusLocator`.
    """

    perspective: PerspectiveLocator = dataclasses.field(default_factory=PerspectiveLocator)
    n_planes: int = 41
    half_range_sigma: float = 4.0
    half_range_mm: tuple[float, float] = (0.5, 4.0)
    max_depth_fraction: float = 0.5
    contrast: float = 0.15
    window_margin_px: float = 3.0
    min_peak_ratio: float = 1.5

    def __post_init__(self) -> None:
        if self.n_planes < 5:
            raise SettingsError(f"n_planes must be at least 5; got {self.n_planes}")
        if not 0 < self.half_range_mm[0] <= self.half_range_mm[1]:
            raise SettingsError(f"half_range_mm must be (min, max) with 0 < min <= max; got "
                                f"{self.half_range_mm}")
        if not self.max_depth_fraction >= 0:
            raise SettingsError(f"max_depth_fraction must be >= 0; got {self.max_depth_fraction}")

    def to_dict(self) -> dict:
        """The settings as nested plain data (the perspective step's by stage)."""
        d = asdict(self)
        d["perspective"] = self.perspective.to_dict()
        return d

    def settings(self) -> dict:
        """Same as :meth:`to_dict`."""
        return self.to_dict()

    def locate(self, raw_or_lf, calibration, *, frame: int = 0, white=None) -> LocateResult:
        """Locate the particles of one frame; see :func:`locate_frame_hybrid`."""
        return locate_frame_hybrid(raw_or_lf, calibration, frame=frame, locator=self,
                                   white=white)


# --- shared steps ---------------------------------------------------------------------

def _to_object(dlfc, lf: LightField, ts: np.ndarray, parallax: np.ndarray, initial: np.ndarray):
    """Object positions of particles seen at central-view sample ``ts`` (n, 2: t, s)
    with in-view parallax ``parallax`` (n,), view px per unit u: the rays through every
    valid view, triangulated through the DLFC. Returns the Triangulation."""
    sel = np.argwhere(lf.view_mask)
    off = _view_offsets(lf, sel, parallax)                    # (n, n_sel, 2) (dt, ds)
    n, n_sel = off.shape[:2]
    t = ts[:, None, 0] + off[..., 0]
    s = ts[:, None, 1] + off[..., 1]
    det = pd.DataFrame({"u": np.tile(lf.u[sel[:, 1]], n), "v": np.tile(lf.v[sel[:, 0]], n),
                        "s": s.ravel(), "t": t.ravel(),
                        "cluster": np.repeat(np.arange(n), n_sel)})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        return triangulate_clusters(dlfc, det, initial, reject_k=math.inf, min_views=4,
                                    n_possible_views=n_sel)


def _initial_xyz(camera, lf: LightField, ts: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Thin-lens start positions from central-view samples and refocus parameters."""
    rc = lf.to_sensor(ts[:, 1], ts[:, 0]).reshape(-1, 2)
    axis = (np.asarray(lf.sensor_shape_px, dtype=float) - 1) / 2
    pitch = camera.pixel_pitch_um * 1e-3
    s_i = camera.image_distance_mm
    f_ml = camera.microlens_focal_length_um * 1e-3
    mla = (rc - axis) * pitch / (1 + f_ml / s_i)                # (row, col) mm on the MLA
    z = camera.depth_for_alpha(alpha)
    # the ray through the lens centre: a point imaged at d crosses the MLA at
    # X_mla = -X_obj s_i / (s_o + z); the world frame un-inverts (x = -X_obj)
    scale = (camera.object_distance_mm + z) / s_i
    return np.column_stack([mla[:, 1] * scale, mla[:, 0] * scale, z])


def _in_focus_regions(planes: np.ndarray, window: int, contrast: float) -> pd.DataFrame:
    """Dark regions of a stack of small in-focus windows (one per particle), the region
    nearest each window's centre: centroid (t, s), area and axes in pixels; NaN where
    none."""
    rows = []
    for img in planes:
        h, w = img.shape
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NoParticlesWarning)
            det = segment_array(img[None, None].astype(np.float32), np.zeros(1), np.zeros(1),
                                window=window, contrast=contrast, area_range=(1.0, math.inf),
                                exclude_edge=False, zero_invalid=True)
        if len(det) == 0:
            rows.append((np.nan,) * 6)
            continue
        d = np.hypot(det["t"].to_numpy() - (h - 1) / 2, det["s"].to_numpy() - (w - 1) / 2)
        r = det.iloc[int(np.argmin(d))]
        rows.append((r["t"], r["s"], r["area"], r["diameter_px"], r["major_axis_px"],
                     r["minor_axis_px"]) + ())
    out = pd.DataFrame(rows, columns=["t", "s", "area", "diameter_px", "major_px", "minor_px"])
    return out


def _empty(frame: int, clock: dict, detections=None) -> LocateResult:
    warnings.warn(f"frame {frame}: no particles found", NoParticlesWarning, stacklevel=3)
    cols = {c: pd.Series(dtype=float) for c in PARTICLE_COLUMNS}
    cols[T_COLUMN] = pd.Series(dtype=np.int64)
    cols["n_views"] = pd.Series(dtype=np.int64)
    cols["flags"] = pd.Series(dtype=np.uint8)
    det = detections if detections is not None else pd.DataFrame()
    return LocateResult(particles=pd.DataFrame(cols), detections=det, stage_seconds=clock)


# --- the refocusing locator -----------------------------------------------------------

def locate_frame_refocus(raw_or_lf, calibration, *, frame: int = 0,
                         locator: RefocusLocator | None = None, white=None) -> LocateResult:
    """Locate particles in 3D in one raw plenoptic image by refocusing (baseline method).

    Parameters
    ----------
    raw_or_lf : (rows, cols) ndarray or LightField
        Raw sensor image (dark particles on a bright back-light) or a decoded light field.
    calibration : Calibration
        Calibration with the lenslet grid and a DLFC.
    frame : int
        Frame index written to the ``frame`` column.
    locator : RefocusLocator, optional
        Settings; default ``RefocusLocator()``.
    white : (rows, cols) ndarray or LightField, optional
        White image for flat-fielding (see
        :func:`~plenoptrack.locate.perspective.locate_frame`).

    Returns
    -------
    LocateResult
        ``particles`` with the columns of
        :data:`~plenoptrack.locate.perspective.PARTICLE_COLUMNS`:

        - ``x, y, z`` (mm) through the DLFC;
        - ``sigma_z`` (mm): the focus curve's full width at half maximum over 2.3548
          (the width of the depth over which the particle looks sharp, not a
          statistical uncertainty), scaled from nominal to calibrated depth;
          ``sigma_x, sigma_y``: NaN (the method gives no lateral uncertainty);
        - ``n_views``: views added in the stack; ``confidence``: the focus peak over the
          curve's median; ``residual_px``: RMS distance (view px) between the
          refocusing rays and the DLFC's prediction of the solved position; ``chi2``:
          NaN (no centroids are fitted);
        - ``diameter, major_axis, minor_axis`` (mm), ``orientation`` (NaN) from the
          dark region of the in-focus image; ``flags``: triangulation flags.

        ``detections`` holds the candidates of the minimum-intensity image (``s, t,
        area``, ...) with the ``particle`` row each became (-1 when it gave no
        measurement). ``stage_seconds``: ``decode``, ``stack``, ``detect``, ``focus``,
        ``convert``.
    """
    locator = RefocusLocator() if locator is None else locator
    dlfc = calibration.dlfc
    camera = calibration.camera
    clock = {"decode": 0.0, "stack": 0.0, "detect": 0.0, "focus": 0.0, "convert": 0.0}
    last = time.perf_counter()

    def lap(stage):
        nonlocal last
        now = time.perf_counter()
        clock[stage] += now - last
        last = now

    lf = _decoded(raw_or_lf, calibration, frame, white)
    lap("decode")
    z_lo, z_hi = (locator.depth_range_mm if locator.depth_range_mm is not None
                  else (float(dlfc.bounds[0, 2]), float(dlfc.bounds[1, 2])))
    depths = np.linspace(z_lo, z_hi, locator.n_planes)
    alphas = np.asarray(camera.alpha_for_depth(depths), dtype=float)
    stack = window_stack(lf, camera, alphas)
    lap("stack")
    minimum = stack.min(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        cand = segment_array(minimum[None, None], np.zeros(1), np.zeros(1),
                             spatial_mask=lf.spatial_mask, frame=frame, window=locator.window,
                             contrast=locator.contrast, area_range=locator.area_range,
                             zero_invalid=True)
    lap("detect")
    if len(cand) == 0:
        return _empty(frame, clock, cand)
    cand = cand.drop(columns=[c for c in ("u", "v") if c in cand.columns])
    ts = cand[["t", "s"]].to_numpy(float)
    half = np.ceil(0.5 * cand["major_axis_px"].to_numpy(float) + locator.window_margin_px)
    energy = _gradient_energy(stack)
    curves = _window_curves(energy, ts, half)
    peaks = focus_peaks(curves, depths)
    ok = peaks["interior"].to_numpy() & (peaks["ratio"].to_numpy() >= locator.min_peak_ratio)
    # in-focus image of each particle: its window in the sharpest plane
    idx = np.flatnonzero(ok)
    size = []
    for i in idx:
        t, s = (int(round(c)) for c in ts[i])
        hw = int(max(half[i], 4) * 2)
        k = int(peaks["index"].iat[i])
        t0, s0 = max(t - hw, 0), max(s - hw, 0)
        size.append(stack[k, t0:t + hw + 1, s0:s + hw + 1])
    focus = _in_focus_regions(size, max(locator.window, 2 * int(half.max()) + 1),
                              locator.contrast) if len(idx) else pd.DataFrame(
        columns=["t", "s", "area", "diameter_px", "major_px", "minor_px"])
    del energy
    if len(idx):
        origin = np.array([[max(int(round(ts[i, 0])) - int(max(half[i], 4) * 2), 0),
                            max(int(round(ts[i, 1])) - int(max(half[i], 4) * 2), 0)] for i in idx])
        focus_ts = focus[["t", "s"]].to_numpy(float) + origin
        found = np.all(np.isfinite(focus_ts), axis=1)
        ok[idx[~found]] = False
        idx, focus_ts, focus = idx[found], focus_ts[found], focus[found].reset_index(drop=True)
    lap("focus")
    if len(idx) == 0:
        return _empty(frame, clock, cand.assign(particle=-1))
    z_nom = peaks["peak"].to_numpy()[idx]
    alpha = np.asarray(camera.alpha_for_depth(z_nom), dtype=float)
    par = parallax_per_u(lf, camera, alpha)
    tri = _to_object(dlfc, lf, focus_ts, par, _initial_xyz(camera, lf, focus_ts, alpha))
    pos = tri.positions
    # depth per nominal depth from the DLFC solution of two neighbouring planes
    dz = 0.5 * (depths[1] - depths[0])
    tri_hi = _to_object(dlfc, lf, focus_ts, parallax_per_u(
        lf, camera, np.asarray(camera.alpha_for_depth(z_nom + dz), dtype=float)), pos)
    scale = np.abs(tri_hi.positions[:, 2] - pos[:, 2]) / dz
    lap("convert")
    mag = dlfc.local_magnification(*pos.T)
    particles = pd.DataFrame({
        T_COLUMN: frame, "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
        "sigma_x": np.nan, "sigma_y": np.nan,
        "sigma_z": peaks["fwhm"].to_numpy()[idx] / 2.3548 * scale,
        "n_views": int(lf.view_mask.sum()), "confidence": peaks["ratio"].to_numpy()[idx],
        "residual_px": tri.residual_px, "chi2": np.nan, "travel_px": np.nan,
        "diameter": focus["diameter_px"].to_numpy(float) / mag,
        "major_axis": focus["major_px"].to_numpy(float) / mag,
        "minor_axis": focus["minor_px"].to_numpy(float) / mag,
        "orientation": np.nan, "flags": tri.flags.astype(np.uint8)})
    good = np.all(np.isfinite(pos), axis=1)
    particles = particles[good].reset_index(drop=True)[list(PARTICLE_COLUMNS)]
    particles["n_views"] = particles["n_views"].astype(np.int64)
    particle_of = np.full(len(cand), -1, dtype=np.int64)
    particle_of[idx[good]] = np.arange(int(good.sum()))
    detections = cand.assign(particle=particle_of)
    if len(particles) == 0:
        return _empty(frame, clock, detections)
    return LocateResult(particles=particles, detections=detections, stage_seconds=clock)


# --- the hybrid -----------------------------------------------------------------------

def _fitted_parallax(dlfc, lf: LightField, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-view sample (t, s) and parallax (view px per unit u) the DLFC predicts for
    each position: least-squares line of the predicted positions over the valid views."""
    sel = np.argwhere(lf.view_mask)
    u = lf.u[sel[:, 1]]
    v = lf.v[sel[:, 0]]
    s, t = dlfc.predict(pos[:, None, 0], pos[:, None, 1], pos[:, None, 2], u[None], v[None])
    # offsets of view (u, v) from the central view in (t, s) for unit parallax
    unit = _view_offsets(lf, sel, np.ones(1))[0]               # (n_sel, 2)
    a = np.column_stack([np.ones(len(sel)), unit[:, 0]])
    b = np.column_stack([np.ones(len(sel)), unit[:, 1]])
    # joint fit: t = t_c + p * unit_t, s = s_c + p * unit_s
    n = len(sel)
    design = np.zeros((2 * n, 3))
    design[:n, 0] = 1.0
    design[n:, 1] = 1.0
    design[:n, 2] = a[:, 1]
    design[n:, 2] = b[:, 1]
    rhs = np.concatenate([t, s], axis=1).T                      # (2n, P)
    coef, *_ = np.linalg.lstsq(design, rhs, rcond=None)
    return np.column_stack([coef[0], coef[1]]), coef[2]


def locate_frame_hybrid(raw_or_lf, calibration, *, frame: int = 0,
                        locator: HybridLocator | None = None, white=None) -> LocateResult:
    """Perspective-shift location with depths refined by refocusing near focus.

    Each particle of :func:`~plenoptrack.locate.perspective.locate_frame` whose depth
    lies within ``max_depth_fraction`` of the plenoptic depth of field gets a local focal
    stack (``n_planes`` planes over its depth +- ``half_range_sigma`` sigma_z, a window
    around the central-view position the DLFC predicts); the sharpest plane, converted
    through the DLFC as in :func:`locate_frame_refocus`, replaces ``z`` when its focus
    curve has an interior peak that stands out (``min_peak_ratio``). ``x, y``, the
    uncertainties and the other columns are the perspective method's.

    Returns
    -------
    LocateResult
        As :func:`~plenoptrack.locate.perspective.locate_frame`; ``stage_seconds`` adds
        ``refine``. The detections table is the perspective one.
    """
    locator = HybridLocator() if locator is None else locator
    lf = _decoded(raw_or_lf, calibration, frame, white)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        base = locate_frame(lf, calibration, frame=frame, locator=locator.perspective)
    t_start = time.perf_counter()
    parts = base.particles
    if len(parts) == 0:
        return _empty(frame, dict(base.stage_seconds), base.detections)
    camera = calibration.camera
    dlfc = calibration.dlfc
    near, far = depth_of_field_mm(camera)
    z = parts["z"].to_numpy(float)
    lim = np.where(z < 0, -near, far) * locator.max_depth_fraction
    todo = np.flatnonzero(np.abs(z) <= lim)
    new_z = z.copy()
    if len(todo):
        pos = parts[list(POS_COLUMNS)].to_numpy(float)[todo]
        ts_c, par0 = _fitted_parallax(dlfc, lf, pos)
        alpha0 = alpha_for_parallax(lf, camera, par0)
        z0 = np.asarray(camera.depth_for_alpha(alpha0), dtype=float)
        sig = parts["sigma_z"].to_numpy(float)[todo]
        half_z = np.clip(np.nan_to_num(locator.half_range_sigma * sig,
                                       nan=locator.half_range_mm[1]), *locator.half_range_mm)
        diam_px = (parts["major_axis"].to_numpy(float)[todo]
                   * dlfc.local_magnification(*pos.T))
        half = np.ceil(0.5 * np.nan_to_num(diam_px, nan=4.0) + locator.window_margin_px)
        for j, i in enumerate(todo):
            zs = np.linspace(z0[j] - half_z[j], z0[j] + half_z[j], locator.n_planes)
            alphas = np.asarray(camera.alpha_for_depth(zs), dtype=float)
            hw = int(half[j]) + 1
            t0 = int(round(ts_c[j, 0])) - hw
            s0 = int(round(ts_c[j, 1])) - hw
            if t0 < 0 or s0 < 0 or t0 + 2 * hw + 1 > lf.view_shape[0] \
                    or s0 + 2 * hw + 1 > lf.view_shape[1]:
                continue
            local = window_stack(lf, camera, alphas, origin_ts=(t0, s0),
                                 shape_ts=(2 * hw + 1, 2 * hw + 1))
            energy = _gradient_energy(local)[:, 1:-1, 1:-1]
            curve = energy.reshape(len(zs), -1).sum(axis=1)[None]
            peak = focus_peaks(curve, zs)
            if not (peak["interior"].iat[0] and peak["ratio"].iat[0] >= locator.min_peak_ratio):
                continue
            a = float(camera.alpha_for_depth(float(peak["peak"].iat[0])))
            tri = _to_object(dlfc, lf, ts_c[j:j + 1], parallax_per_u(lf, camera, np.array([a])),
                             pos[j:j + 1])
            if np.isfinite(tri.positions[0, 2]):
                new_z[i] = tri.positions[0, 2]
    clock = dict(base.stage_seconds)
    clock["refine"] = time.perf_counter() - t_start
    return LocateResult(particles=parts.assign(z=new_z), detections=base.detections,
                        stage_seconds=clock, image_coverage=base.image_coverage)
