"""Decoding a raw plenoptic image into a 4D light field ``L[v, u, t, s]``.

Every microlens image is sampled on a common grid of angular coordinates ``(u, v)``
(integer sensor-pixel offsets ``-R ... R`` from its sub-pixel centre, ``R =
floor(pitch_px / 2)``) by bilinear interpolation of the raw image. A hexagonal lattice is
then resampled onto a rectangular spatial grid ``(s, t)``: every lens row becomes one
``t`` row and each row is resampled by linear interpolation between neighbouring lenses
at a spacing equal to the row spacing, so that spatial samples are square. A rectangular
lattice needs no resampling (``s`` = lens column, ``t`` = lens row).

Both steps are fused into one compiled gather (8 raw pixels per output value), parallel
over ``t`` rows; no Python loop runs over lenses, views or pixels.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numba
import numpy as np

from ..errors import CalibrationError, ImageSizeError, InputFileError, SettingsError
from ..io import check_image_shape
from .lattice import LensletGrid

__all__ = ["LightField", "decode", "VIEW_MASK_THRESHOLD", "WHITE_FLOOR"]

VIEW_MASK_THRESHOLD = 0.6
"""A view is *valid* (:attr:`LightField.view_mask`) when at least this fraction of it is
unvignetted (:attr:`LightField.valid_fraction`). Views on the rim of the microlens image
(e.g. ``u = +-R, v = 0`` when the pitch is just over ``2 R`` pixels) have about half of
their pixel footprint outside the lens's own image and pick up light from the
neighbouring lens; 0.6 excludes them."""

WHITE_FLOOR = 0.1
"""Default for ``decode(..., white_floor=)``: flat-field division happens only where the
decoded white light field exceeds this fraction of its brightest view's mean level."""


@dataclass(frozen=True, eq=False)
class LightField:
    """A decoded 4D light field on rectangular angular and spatial grids.

    Parameters
    ----------
    data : (n_v, n_u, n_t, n_s) float32 ndarray
        Radiance ``L[v, u, t, s]``. Raw counts, or a fraction of the white image's level
        when decoded with a white image (then ~1 on an unobstructed background).
    u, v : (n_u,), (n_v,) float64 ndarray
        Angular coordinates of the view columns / rows, sensor pixels from the
        microlens-image centre along sensor columns (``u``) and rows (``v``); the
        integer grid ``-R ... R``.
    valid_fraction : (n_v, n_u) float64 ndarray
        Fraction of each view that is unvignetted, in [0, 1] (1 for the central views,
        0 for views entirely outside the microlens image): the fraction of the view's
        pixel footprint inside the microlens-image disc, or, with a white image, the
        smaller of that and the view's mean white level relative to the brightest view.
    spatial_mask : (n_t, n_s) bool ndarray
        True where the sample stands for lenses whose whole image lies on the sensor.
    origin_px : (2,) float
        Sensor position (row, col), pixels, of the microlens-image centre that sample
        ``(t, s) = (0, 0)`` stands for.
    s_step_px, t_step_px : (2,) float
        Sensor step (drow, dcol), pixels, from sample ``(t, s)`` to ``(t, s + 1)`` and to
        ``(t + 1, s)``. The sample at ``(t, s)`` stands for sensor position
        ``origin_px + s * s_step_px + t * t_step_px`` (see :meth:`to_sensor`).
    sensor_shape_px : (int, int)
        Sensor (rows, cols) of the raw image that was decoded.
    grid_type : {"hex", "rect"}
        Lattice of the lenslet grid that was decoded.
    flat_fielded : bool
        True when the data were divided by a decoded white image.

    Notes
    -----
    Positions are microlens-*image* centres on the sensor. The corresponding position on
    the microlens-array plane, measured from the optical axis, is the sensor position
    minus the axis point ``((rows - 1) / 2, (cols - 1) / 2)``, divided by
    ``1 + f_ml / s_i`` (see ``docs/conventions.md``).
    """

    data: np.ndarray
    u: np.ndarray
    v: np.ndarray
    valid_fraction: np.ndarray
    spatial_mask: np.ndarray
    origin_px: tuple[float, float]
    s_step_px: tuple[float, float]
    t_step_px: tuple[float, float]
    sensor_shape_px: tuple[int, int]
    grid_type: str = "hex"
    flat_fielded: bool = False

    def __post_init__(self) -> None:
        data = self.data
        if not isinstance(data, np.ndarray) or data.ndim != 4:
            raise SettingsError("LightField data must be a 4-D array (v, u, t, s); got "
                             f"{getattr(data, 'shape', type(data).__name__)}")
        n_v, n_u, n_t, n_s = data.shape
        u = np.asarray(self.u, dtype=float)
        v = np.asarray(self.v, dtype=float)
        if u.shape != (n_u,) or v.shape != (n_v,):
            raise SettingsError(f"LightField u and v must have {n_u} and {n_v} entries to match "
                             f"data {data.shape}; got {u.shape} and {v.shape}")
        vf = np.asarray(self.valid_fraction, dtype=float)
        if vf.shape != (n_v, n_u):
            raise SettingsError(f"LightField valid_fraction must be ({n_v}, {n_u}); got {vf.shape}")
        sm = np.asarray(self.spatial_mask, dtype=bool)
        if sm.shape != (n_t, n_s):
            raise SettingsError(f"LightField spatial_mask must be ({n_t}, {n_s}); got {sm.shape}")
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "v", v)
        object.__setattr__(self, "valid_fraction", vf)
        object.__setattr__(self, "spatial_mask", sm)
        for name in ("origin_px", "s_step_px", "t_step_px"):
            object.__setattr__(self, name, tuple(float(x) for x in getattr(self, name)))
        object.__setattr__(self, "sensor_shape_px", tuple(int(x) for x in self.sensor_shape_px))

    # --- sizes ----------------------------------------------------------------------
    @property
    def n_u(self) -> int:
        """Number of view columns."""
        return self.data.shape[1]

    @property
    def n_v(self) -> int:
        """Number of view rows."""
        return self.data.shape[0]

    @property
    def n_s(self) -> int:
        """Number of spatial samples per view row (view width)."""
        return self.data.shape[3]

    @property
    def n_t(self) -> int:
        """Number of spatial sample rows (view height)."""
        return self.data.shape[2]

    @property
    def n_views(self) -> int:
        """Total number of views, ``n_v * n_u``."""
        return self.n_v * self.n_u

    @property
    def view_shape(self) -> tuple[int, int]:
        """Shape ``(n_t, n_s)`` of one perspective view."""
        return self.n_t, self.n_s

    @property
    def view_mask(self) -> np.ndarray:
        """``(n_v, n_u)`` bool: views with ``valid_fraction >= VIEW_MASK_THRESHOLD`` (0.6)."""
        return self.valid_fraction >= VIEW_MASK_THRESHOLD

    @property
    def sample_spacing_px(self) -> float:
        """Spatial sample spacing in sensor pixels (square root of the sample cell area)."""
        return float(math.sqrt(abs(np.linalg.det(self.step_matrix))))

    @property
    def step_matrix(self) -> np.ndarray:
        """``(2, 2)`` matrix ``A`` with ``(row, col) = origin_px + A @ (t, s)``."""
        return np.array([self.t_step_px, self.s_step_px], dtype=float).T

    # --- coordinates ----------------------------------------------------------------
    def index_of(self, u: float, v: float) -> tuple[int, int]:
        """Array indices ``(v_idx, u_idx)`` of the view with coordinates ``(u, v)``."""
        iu = np.flatnonzero(np.isclose(self.u, u))
        iv = np.flatnonzero(np.isclose(self.v, v))
        if len(iu) != 1 or len(iv) != 1:
            raise SettingsError(f"no view at (u, v) = ({u}, {v}); u and v run over "
                             f"{self.u.min():g} ... {self.u.max():g} in steps of 1")
        return int(iv[0]), int(iu[0])

    def view(self, u: float, v: float) -> np.ndarray:
        """Perspective view at angular coordinates ``(u, v)``, ``(n_t, n_s)`` float32."""
        iv, iu = self.index_of(u, v)
        return self.data[iv, iu]

    def to_sensor(self, s, t) -> np.ndarray:
        """Sensor positions ``(..., 2)`` as (row, col) pixels of spatial samples ``(s, t)``.

        ``s`` and ``t`` may be fractional; the result is the microlens-image centre the
        sample stands for (the position of the ``u = v = 0`` ray on the sensor).
        """
        st = np.stack(np.broadcast_arrays(np.asarray(t, float), np.asarray(s, float)), axis=-1)
        return np.asarray(self.origin_px) + st @ self.step_matrix.T

    def from_sensor(self, points_px) -> np.ndarray:
        """Inverse of :meth:`to_sensor`: ``(..., 2)`` (row, col) pixels to ``(..., 2)`` (s, t)."""
        p = np.asarray(points_px, dtype=float) - np.asarray(self.origin_px)
        ts = np.linalg.solve(self.step_matrix, p.reshape(-1, 2).T).T
        return ts[:, ::-1].reshape(p.shape)

    @property
    def axis_st(self) -> tuple[float, float]:
        """Spatial coordinates ``(s, t)`` where the optical axis meets the sensor (its
        centre pixel ``((rows - 1) / 2, (cols - 1) / 2)``)."""
        rows, cols = self.sensor_shape_px
        s, t = self.from_sensor([(rows - 1) / 2.0, (cols - 1) / 2.0])
        return float(s), float(t)


# --------------------------------------------------------------------------------------
# compiled gather


@numba.njit(inline="always")
def _corner(pos, hi):  # pragma: no cover - compiled
    """Top-left tap index and weight of the second tap for bilinear sampling at ``pos``
    on an axis of pixels ``0 ... hi + 1`` (positions outside replicate the edge)."""
    pos = min(max(pos, 0.0), float(hi) + 1.0)
    i = min(int(math.floor(pos)), hi)
    return i, pos - i


@numba.njit(inline="always")
def _lens_block(raw, pr, pc, n_ang, use, rows, block):  # pragma: no cover - compiled
    """``block[v, u]`` = the raw image bilinearly interpolated at ``(pr + v, pc + u)``
    (every tap on the sensor) for the views ``use[v, u]``: rows first into ``rows``,
    then columns."""
    r0 = int(math.floor(pr))
    c0 = int(math.floor(pc))
    fr = pr - r0
    fc = pc - c0
    for iv in range(n_ang):
        if not use[iv].any():
            continue
        for k in range(n_ang + 1):
            rows[iv, k] = (1.0 - fr) * raw[r0 + iv, c0 + k] + fr * raw[r0 + iv + 1, c0 + k]
        for iu in range(n_ang):
            if use[iv, iu]:
                block[iv, iu] = (1.0 - fc) * rows[iv, iu] + fc * rows[iv, iu + 1]


@numba.njit(parallel=True, cache=True, nogil=True)
def _gather(raw, cen, j0s, ws, rad, use, t_lo, t_hi, out):  # pragma: no cover - compiled
    """out[v, u, t, s] = (1-w) * bilin(raw, c0 + (v, u)) + w * bilin(raw, c1 + (v, u))
    for the views ``use[v, u]`` (the others are left as they are).

    ``c0, c1`` are the centres of lenses ``j0`` and ``j0 + 1`` of lens row ``t``; taps
    beyond the sensor edge replicate the edge pixels. A lens's interpolated image is the
    same for every sample that blends it, so it is computed once and held while the
    samples of its row pass it (``j0`` never decreases along a row): on a hexagonal grid
    about 1.15 samples per lens each blend two lenses.
    """
    n_ang = 2 * rad + 1
    n_s = out.shape[3]
    n_lens = cen.shape[1]
    hi_r = raw.shape[0] - 2
    hi_c = raw.shape[1] - 2
    for t in numba.prange(t_lo, t_hi):
        rows = np.empty((n_ang, n_ang + 1))
        blocks = np.empty((2, n_ang, n_ang))   # two lens images held ...
        held = np.full(2, -1, dtype=np.int64)  # ... and the lenses they are of
        for s in range(n_s):
            j0 = j0s[t, s]
            w1 = ws[t, s]
            w0 = 1.0 - w1
            j1 = j0 + 1 if (w1 > 0.0 and j0 + 1 < n_lens) else j0
            pr0 = cen[t, j0, 0] - rad
            pc0 = cen[t, j0, 1] - rad
            pr1 = cen[t, j1, 0] - rad
            pc1 = cen[t, j1, 1] - rad
            inside = (min(pr0, pr1) >= 0.0 and max(pr0, pr1) + 2 * rad <= hi_r
                      and min(pc0, pc1) >= 0.0 and max(pc0, pc1) + 2 * rad <= hi_c)
            if inside:  # fast path: no clamping
                if held[0] == j0:
                    k0 = 0
                elif held[1] == j0:
                    k0 = 1
                else:  # not into the slot that holds j1
                    k0 = 1 if held[0] == j1 else 0
                    _lens_block(raw, pr0, pc0, n_ang, use, rows, blocks[k0])
                    held[k0] = j0
                if w1 == 0.0:  # on a lens centre (every sample of a rectangular grid)
                    for iv in range(n_ang):
                        for iu in range(n_ang):
                            if use[iv, iu]:
                                out[iv, iu, t, s] = w0 * blocks[k0, iv, iu]
                    continue
                k1 = 1 - k0
                if held[k1] != j1:
                    _lens_block(raw, pr1, pc1, n_ang, use, rows, blocks[k1])
                    held[k1] = j1
                for iv in range(n_ang):
                    for iu in range(n_ang):
                        if use[iv, iu]:
                            out[iv, iu, t, s] = (w0 * blocks[k0, iv, iu]
                                                 + w1 * blocks[k1, iv, iu])
            else:  # lens image reaches past the sensor edge: clamp every tap
                for iv in range(n_ang):
                    ra, fra = _corner(pr0 + iv, hi_r)
                    rb, frb = _corner(pr1 + iv, hi_r)
                    for iu in range(n_ang):
                        if not use[iv, iu]:
                            continue
                        ca, fca = _corner(pc0 + iu, hi_c)
                        cb, fcb = _corner(pc1 + iu, hi_c)
                        va = ((1.0 - fra) * ((1.0 - fca) * raw[ra, ca] + fca * raw[ra, ca + 1])
                              + fra * ((1.0 - fca) * raw[ra + 1, ca] + fca * raw[ra + 1, ca + 1]))
                        vb = ((1.0 - frb) * ((1.0 - fcb) * raw[rb, cb] + fcb * raw[rb, cb + 1])
                              + frb * ((1.0 - fcb) * raw[rb + 1, cb] + fcb * raw[rb + 1, cb + 1]))
                        out[iv, iu, t, s] = w0 * va + w1 * vb


# --------------------------------------------------------------------------------------
# geometry of the spatial resampling


@dataclass(frozen=True)
class _Sampling:
    j0: np.ndarray          # (n_t, n_s) int64, left lens of each sample in its lens row
    w: np.ndarray           # (n_t, n_s) float64, weight of the right lens
    mask: np.ndarray        # (n_t, n_s) bool
    origin_px: np.ndarray   # (2,)
    s_step_px: np.ndarray   # (2,)
    t_step_px: np.ndarray   # (2,)


@functools.lru_cache(maxsize=8)
def _sampling(grid: LensletGrid, rad: int) -> _Sampling:
    """Where every spatial sample sits among the lenses of its lens row.

    Cached per grid (a frozen, hashable value) and ``rad``: every frame of a run decodes
    with the same grid, and the pixel-locking correction asks again for each frame (on a
    29-megapixel sensor about 15 ms a call). The arrays are shared between the calls:
    read them, never write to them (they are not flagged read-only, which would make
    numba compile the kernels that take them once more)."""
    n_rows, n_cols = grid.shape
    a = np.asarray(grid.col_step_px)
    b = np.asarray(grid.row_step_px)
    sh = grid.odd_row_shift
    t = np.arange(n_rows)
    if grid.grid_type == "rect":
        q, kappa = 1.0, 0.0
        t_step = b
        j_start, n_s = 0.0, n_cols
    else:
        # t steps perpendicular to the lens rows; kappa = component of the row step along them.
        kappa = float(a @ b / (a @ a))
        t_step = b - kappa * a
        q = grid.row_spacing_px / grid.pitch_px
        row_off = kappa * t + sh * (t % 2)           # lens j of row t sits at j + row_off
        j_start = float(row_off.max())               # first position every row covers
        j_end = float((n_cols - 1) + row_off.min())  # last position every row covers
        if j_end < j_start:
            raise CalibrationError("lenslet grid rows are sheared so much that no column of "
                                   "samples is covered by every lens row; re-calibrate the grid")
        n_s = int(math.floor((j_end - j_start) / q + 1e-9)) + 1
    s = np.arange(n_s)
    jj = j_start + q * s[None, :] - (kappa * t + sh * (t % 2))[:, None]
    jj = np.clip(jj, 0.0, n_cols - 1)
    j0 = np.minimum(np.floor(jj + 1e-9).astype(np.int64), n_cols - 1)
    w = np.clip(jj - j0, 0.0, 1.0)
    w[w < 1e-9] = 0.0

    # a lens is usable when every bilinear tap of every (u, v) sample lies on the sensor
    cen = _lens_centres(grid)
    rows, cols = grid.sensor_shape_px
    ok = ((cen[..., 0] - rad >= 0) & (cen[..., 0] + rad <= rows - 1)
          & (cen[..., 1] - rad >= 0) & (cen[..., 1] + rad <= cols - 1))
    tt = np.broadcast_to(t[:, None], j0.shape)
    j1 = np.minimum(j0 + 1, n_cols - 1)
    mask = ok[tt, j0] & (ok[tt, j1] | (w == 0))

    origin = np.asarray(grid.origin_px) + j_start * a
    return _Sampling(j0=j0, w=w, mask=mask, origin_px=origin, s_step_px=q * a,
                     t_step_px=np.asarray(t_step, dtype=float))


@functools.lru_cache(maxsize=8)
def _lens_centres(grid: LensletGrid) -> np.ndarray:
    """``grid.centers()``, cached per grid and shared like :func:`_sampling`'s arrays."""
    return grid.centers()


def _disc_fraction(u: np.ndarray, v: np.ndarray, radius: float, n_sub: int = 32) -> np.ndarray:
    """Fraction of each pixel footprint ``[v +- 0.5] x [u +- 0.5]`` inside a disc of
    ``radius`` about the origin, ``(n_v, n_u)``, by ``n_sub**2`` point supersampling."""
    off = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    vv = v[:, None, None, None] + off[None, None, :, None]
    uu = u[None, :, None, None] + off[None, None, None, :]
    return ((vv ** 2 + uu ** 2) <= radius ** 2).mean(axis=(2, 3))


def _check_raw(image, grid: LensletGrid, name: str) -> np.ndarray:
    if not isinstance(image, np.ndarray):
        image = np.asarray(image)
    if image.ndim != 2:
        raise ImageSizeError(f"{name} must be a 2-D (rows, cols) image; got an array of shape "
                             f"{image.shape}; pass one frame at a time")
    if not (np.issubdtype(image.dtype, np.integer) or np.issubdtype(image.dtype, np.floating)):
        raise InputFileError(f"{name} must hold integer or float pixel values; got dtype {image.dtype}")
    check_image_shape(image, grid.sensor_shape_px, source=name, what="the lenslet grid")
    if image.dtype not in (np.uint16, np.float32):
        image = image.astype(np.float32)
    return np.ascontiguousarray(image)


def _decode_array(raw: np.ndarray, grid: LensletGrid, samp: _Sampling, rad: int,
                  progress: bool, label: str, use: np.ndarray | None = None) -> np.ndarray:
    """The light field ``(n_v, n_u, n_t, n_s)`` of the views ``use`` (all when None;
    the others zero)."""
    cen = _lens_centres(grid)
    n_ang = 2 * rad + 1
    n_t, n_s = samp.j0.shape
    if use is None:
        use = np.ones((n_ang, n_ang), dtype=np.bool_)
        out = np.empty((n_ang, n_ang, n_t, n_s), dtype=np.float32)
    else:
        use = np.ascontiguousarray(use, dtype=np.bool_)
        out = np.zeros((n_ang, n_ang, n_t, n_s), dtype=np.float32)  # pages of unused views
    if not progress:                                                 # are never touched
        _gather(raw, cen, samp.j0, samp.w, rad, use, 0, n_t, out)
        return out
    from rich.progress import Progress

    chunk = max(1, -(-n_t // 20))
    with Progress(transient=True) as bar:
        task = bar.add_task(label, total=n_t)
        for lo in range(0, n_t, chunk):
            hi = min(n_t, lo + chunk)
            _gather(raw, cen, samp.j0, samp.w, rad, use, lo, hi, out)
            bar.update(task, advance=hi - lo)
    return out


def decode(raw: np.ndarray, grid: LensletGrid, *, white: "np.ndarray | LightField | None" = None,
           white_floor: float = WHITE_FLOOR, progress: bool = False,
           min_view_fraction: float = 0.0) -> LightField:
    """Decode a raw plenoptic image into a light field ``L[v, u, t, s]``.

    Parameters
    ----------
    raw : (rows, cols) ndarray, uint16 or float
        Raw sensor image, pixel centres at integer (row, col); its shape must equal
        ``grid.sensor_shape_px``.
    grid : LensletGrid
        Microlens-image centres (from :func:`plenoptrack.lightfield.calibrate_grid`).
    white : (rows, cols) ndarray or LightField, optional
        White (flat-field) image of the same camera, raw or already decoded with this
        grid and without a white (``decode(white, grid)``: decode it once when
        flat-fielding many frames). When given, the light field is divided by the decoded
        white light field wherever the latter exceeds ``white_floor`` times the mean
        level of its brightest view, and set to zero (invalid: dead pixels, dark rims)
        elsewhere; valid samples are at least 1e-6, so that a black one is not taken
        for an invalid one. Division removes what the frames share with the white image: the
        back-light's shape, pixel gains, dust shadows on the sensor window.
        ``valid_fraction`` is the fraction of each view's pixel footprint inside the disc
        of radius ``grid.pitch_px / 2`` (the microlens image of a matched main lens); with
        a white image it is further limited to the view's mean white level relative to
        the brightest view (vignetting by a smaller aperture). The white level alone
        would not do: rim views interpolate pixels of the neighbouring lens, which are
        lit too.
    white_floor : float
        See ``white``; between 0 and 1.
    progress : bool
        Show a progress bar (rich) while decoding.
    min_view_fraction : float
        Views whose valid fraction (the disc footprint, and with a white image its
        level) is below this are not decoded: their samples are 0 and their valid
        fraction 0. The default 0 decodes every view; a caller that reads only the
        better-lit views (the locator: 0.5) saves their time.

    Returns
    -------
    LightField
        ``data`` is ``(n_v, n_u, n_t, n_s)`` float32 with ``n_v = n_u = 2 R + 1``,
        ``R = floor(grid.pitch_px / 2)``. For a hexagonal grid ``n_t`` is the number of
        lens rows and ``n_s`` the number of samples, spaced by the lens-row spacing, that
        every lens row covers; for a rectangular grid ``(n_t, n_s) = grid.shape``.

    Raises
    ------
    ImageSizeError
        ``raw`` or ``white`` is not 2-D or not of the grid's sensor shape.
    InputFileError
        An image has a non-numeric dtype.
    CalibrationError
        The grid is too fine to decode (pitch under 2 pixels).

    Notes
    -----
    View ``(u, v)`` of lens ``k`` is the raw image bilinearly interpolated at
    ``centre_k + (v, u)`` (row, col). On a hexagonal lattice the sample ``(t, s)`` lies
    on lens row ``t`` between two neighbouring lenses and is their linear blend. The
    sensor position each sample stands for is ``LightField.to_sensor(s, t)``.

    Examples
    --------
    >>> from plenoptrack import preset
    >>> from plenoptrack.simulate import make_optics, render_white
    >>> optics = make_optics(preset("small"), seed=0)
    >>> white = render_white(optics, seed=0)
    >>> lf = decode(white, optics.true_grid, white=white)
    >>> lf.data.shape[:2], int(lf.view_mask.sum())
    ((15, 15), 145)
    """
    if not isinstance(grid, LensletGrid):
        raise CalibrationError(f"grid must be a LensletGrid; got {type(grid).__name__}")
    raw = _check_raw(raw, grid, "raw image")
    if isinstance(white, LightField):
        if white.flat_fielded or tuple(white.sensor_shape_px) != tuple(grid.sensor_shape_px):
            raise CalibrationError("a decoded white image must be decoded with the same grid "
                                   "and without a white image: decode(white, grid)")
    elif white is not None:
        white = _check_raw(white, grid, "white image")
    if not 0.0 < white_floor < 1.0:
        raise SettingsError(f"white_floor must be between 0 and 1; got {white_floor!r}")
    rad = int(math.floor(grid.pitch_px / 2.0))
    if rad < 1:
        raise CalibrationError(f"lenslet pitch {grid.pitch_px:.2f} px is too small to decode; "
                               "each microlens image must span at least 2 pixels")
    if not 0.0 <= min_view_fraction <= 1.0:
        raise SettingsError(f"min_view_fraction must be between 0 and 1; got "
                            f"{min_view_fraction!r}")
    samp = _sampling(grid, rad)
    ang = np.arange(-rad, rad + 1, dtype=float)
    valid = _disc_fraction(ang, ang, grid.pitch_px / 2.0)
    shape = (len(ang), len(ang), *samp.j0.shape)
    wdata = None
    if isinstance(white, LightField):
        if white.data.shape != shape:
            raise CalibrationError(f"decoded white light field has shape {white.data.shape} "
                                   f"but the frame decodes to {shape}; decode the white "
                                   "image with the same grid")
        wdata = white.data
    elif white is not None:
        wdata = _decode_array(white, grid, samp, rad, progress, "decoding white")
    if wdata is not None:
        level, brightest = _white_level(wdata, samp.mask)
        valid = np.minimum(valid, level)
    use = valid >= min_view_fraction if min_view_fraction > 0 else None
    data = _decode_array(raw, grid, samp, rad, progress, "decoding", use)
    if wdata is not None:
        _divide_by_white(data, wdata, white_floor * brightest, use)
    del wdata
    if use is not None:
        valid = np.where(use, valid, 0.0)
    # the light field gets its own copies of the cached sampling's arrays
    return LightField(data=data, u=ang, v=ang.copy(), valid_fraction=valid,
                      spatial_mask=samp.mask.copy(), origin_px=samp.origin_px.copy(),
                      s_step_px=samp.s_step_px.copy(), t_step_px=samp.t_step_px.copy(),
                      sensor_shape_px=grid.sensor_shape_px, grid_type=grid.grid_type,
                      flat_fielded=white is not None)


_VALID_FLOOR = np.float32(1e-6)
"""Smallest value of a valid flat-fielded sample (0 is reserved for invalid ones)."""


def _flat_field(data: np.ndarray, wdata: np.ndarray, mask: np.ndarray, floor: float) -> np.ndarray:
    """Divide ``data`` by ``wdata`` in place where bright enough (above ``floor`` times the
    brightest view's level); return the views' relative white levels (valid fractions)."""
    level, brightest = _white_level(wdata, mask)
    _divide_by_white(data, wdata, floor * brightest)
    return level


def _white_level(wdata: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """Mean level of each view of a decoded white image over the spatial mask: relative
    to the brightest view's ``(n_v, n_u)`` in [0, 1], and that brightest level."""
    n_v, n_u = wdata.shape[:2]
    weights = (mask if mask.any() else np.ones_like(mask)).ravel().astype(np.float32)
    level = (wdata.reshape(n_v * n_u, -1) @ weights).astype(np.float64).reshape(n_v, n_u)
    level /= float(weights.sum())
    ref = float(level.max())
    if not ref > 0:
        raise InputFileError("white image is dark everywhere under the lenslets; "
                             "check the white image and the lenslet grid")
    return np.clip(level / ref, 0.0, 1.0), ref


def _divide_by_white(data: np.ndarray, wdata: np.ndarray, threshold: float,
                     use: np.ndarray | None = None) -> None:
    """Divide ``data`` by ``wdata`` in place where the white image exceeds ``threshold``
    and set it to 0 elsewhere, in the views ``use`` (all when None)."""
    thresh = np.float32(threshold)
    n_v, n_u = data.shape[:2]
    for iv in range(n_v):  # per view keeps the temporaries small
        for iu in range(n_u):
            if use is not None and not use[iv, iu]:
                continue
            w = wdata[iv, iu]
            bright = w > thresh
            d = data[iv, iu]
            np.divide(d, w, out=d, where=bright)
            # 0 marks the samples without light in the white image; a black sample that
            # is valid (a perfectly opaque particle on a sensor without a dark level) is
            # kept just above it, or segmentation would take it for a hole in the data.
            np.maximum(d, _VALID_FLOOR, out=d, where=bright)
            d[~bright] = 0.0
