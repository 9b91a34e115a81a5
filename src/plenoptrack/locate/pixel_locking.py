"""Pixel-locking correction of the view centroids, learned from the frame itself.

A view pixel is one microlens: it integrates the particle's image over the lens's cell,
and a centroid of a few such samples is pulled towards the nearest lens centre by an
amount that repeats with the lens lattice, a function of where the image centre lies in
the lattice cell (its *phase*). Far from the focal plane a particle's image crosses many
lens cells from one side of the aperture to the other, the views sample every phase and
the solve averages the bias out. Near focus every view sees the image at about the same
phase; the bias then changes slowly and almost linearly across the aperture, which is
what a change of depth looks like, and the particle's depth is off by a fixed amount
that depends on its place on the grid (``benchmarks/near_focus_pattern.py``: about
80 um at 1 mm from focus on the `small` camera's hexagonal lattice).

The bias is measured on the frame's own particles whose image travels across at least
``min_travel_px`` view pixels over the aperture: their centroids scatter about their
solution by the bias at each view's phase, which the solve did not absorb. Each of the
two residual components ``(s, t)`` is fitted as a Fourier series in the two lattice
phases (:func:`lattice_phase`) up to ``harmonics``, its amplitudes linear in the image's
travel (a sharp image near focus is pulled harder than a blurred one), with three rounds
of rejection at 3 robust standard deviations (overlapping images, wrong members); the
constant is left out of the correction (a common offset is not a locking effect). Every
centroid of the frame is then corrected by the pattern at its own phase and its
particle's travel.

Nothing of the ground truth enters: the pattern is learned only from the scatter of
centroids about the particles located from them. The calibration measures the same
pattern on its dot cards (:func:`pattern_from_dots`), each dot's centroids about the
DLFC's prediction of its known place; with ``solve.locking_from_calibration`` a frame
with too few particles far from focus uses it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["LockingPattern", "lattice_phase", "fourier_terms", "fit_locking_pattern",
           "pattern_from_dots", "SIZE_FACTOR"]

_MAD_TO_SIGMA = 1.4826

SIZE_FACTOR = 2.0
"""A pattern measured on images of one size (a calibration's dots) is used on images up to
this factor smaller or larger (:meth:`LockingPattern.applies_to`): larger images are
pulled less, and a 1-2 mm particle given a 0.4 mm dot's pull would gain the error the
correction takes from the dots."""


def lattice_phase(grid, st: np.ndarray) -> np.ndarray:
    """Place of each view position in the lens lattice's cell.

    Parameters
    ----------
    grid : LensletGrid
        The calibration's lenslet grid (``calibration.grid``); view positions map to
        the sensor as ``decode(raw, grid)`` samples them.
    st : (M, 2) float ndarray
        View positions ``(s, t)``, view pixels.

    Returns
    -------
    (M, 2) float ndarray
        Fractional lattice coordinates in ``[0, 1)``: along the lens rows' step
        between rows (``row_step_px``, which a hexagonal lattice's odd-row shift makes
        a primitive vector) and along the rows (``col_step_px``).
    """
    from ..lightfield.decode import _sampling

    st = np.asarray(st, dtype=float).reshape(-1, 2)
    samp = _sampling(grid, max(1, int(math.floor(grid.pitch_px / 2.0))))
    sensor = (np.asarray(samp.origin_px) + st[:, :1] * np.asarray(samp.s_step_px)
              + st[:, 1:] * np.asarray(samp.t_step_px))
    ij = grid.lattice_coords(sensor).reshape(-1, 2)
    a = ij[:, 0]
    b = ij[:, 1] - grid.odd_row_shift * a
    return np.column_stack([a % 1.0, b % 1.0])


def _orders(harmonics: int) -> list[tuple[int, int]]:
    """Integer wave vectors ``(m, n)`` up to ``harmonics``, one of each +- pair."""
    return [(m, n) for m in range(-harmonics, harmonics + 1) for n in range(harmonics + 1)
            if n > 0 or m > 0]


def fourier_terms(phase: np.ndarray, harmonics: int) -> np.ndarray:
    """(M, K) cosines and sines of ``2 pi (m a + n b)`` for the phases ``(a, b)``
    ``phase`` (M, 2), over the integer wave vectors ``(m, n)`` up to ``harmonics`` (one
    of each +- pair); ``K = 4 h (h + 1)`` for ``h`` harmonics."""
    phase = np.asarray(phase, dtype=float).reshape(-1, 2)
    cols = []
    for m, n in _orders(harmonics):
        arg = 2.0 * math.pi * (m * phase[:, 0] + n * phase[:, 1])
        cols += [np.cos(arg), np.sin(arg)]
    return np.column_stack(cols) if cols else np.zeros((len(phase), 0))


@dataclasses.dataclass(frozen=True)
class LockingPattern:
    """A frame's pixel-locking bias as a function of lattice phase and image travel
    (:func:`fit_locking_pattern`).

    The bias at phase ``p`` of an image that travels ``T`` view pixels across the
    aperture is ``(c + d T) . F(p)``, ``F`` the :func:`fourier_terms`: a sharp image near
    focus is pulled harder than a blurred one far from it. ``T`` is held within the
    range the pattern was fitted on.

    Attributes
    ----------
    coef : (2, 2, K) float ndarray
        ``[c, d]`` of the ``s`` and ``t`` bias (view pixels, and view pixels per view
        pixel of travel).
    harmonics : int
        Harmonics of the series.
    travel_range : (float, float)
        Least and largest travel of the fitted residuals' particles, view pixels.
    n_residuals : int
        Centroid residuals the fit kept.
    rms_px : (2,) float ndarray
        RMS of the fitted bias over the kept residuals, ``s`` and ``t``, view pixels.
    image_diameter_px : float
        Median equivalent diameter ``2 sqrt(dark_area / pi)`` of the images the pattern
        was measured on, view pixels (a calibration's dots; NaN when not recorded): the
        pull depends on the image's size, so a pattern is only used on images within a
        factor :data:`SIZE_FACTOR` of it (:meth:`applies_to`).
    """

    coef: np.ndarray
    harmonics: int
    travel_range: tuple[float, float]
    n_residuals: int
    rms_px: np.ndarray
    image_diameter_px: float = math.nan

    def applies_to(self, dark_area: np.ndarray) -> np.ndarray:
        """(M,) bool: the images of summed darkness ``dark_area`` (px) whose equivalent
        diameter is within :data:`SIZE_FACTOR` of :attr:`image_diameter_px` (all of them
        when that is not recorded)."""
        dark_area = np.asarray(dark_area, dtype=float)
        if not np.isfinite(self.image_diameter_px):
            return np.ones(dark_area.shape, dtype=bool)
        d = 2.0 * np.sqrt(np.maximum(dark_area, 0.0) / math.pi)
        ratio = d / self.image_diameter_px
        return (ratio >= 1.0 / SIZE_FACTOR) & (ratio <= SIZE_FACTOR)

    def to_dict(self) -> dict:
        """JSON-ready form (a calibration file's ``locking_pattern`` section)."""
        out = {"harmonics": self.harmonics, "travel_range_px": list(self.travel_range),
               "coef_px": np.asarray(self.coef).tolist(), "n_residuals": self.n_residuals,
               "rms_px": np.asarray(self.rms_px).tolist()}
        if np.isfinite(self.image_diameter_px):
            out["image_diameter_px"] = float(self.image_diameter_px)
        return out

    @classmethod
    def from_dict(cls, data, *, source: str = "locking pattern") -> "LockingPattern":
        """Read :meth:`to_dict` output; :class:`~plenoptrack.errors.CalibrationError`
        naming ``source`` when it is not a valid pattern."""
        from ..errors import CalibrationError

        try:
            harmonics = int(data["harmonics"])
            lo, hi = (float(v) for v in data["travel_range_px"])
            coef = np.asarray(data["coef_px"], dtype=float)
            n = int(data["n_residuals"])
            rms = np.asarray(data["rms_px"], dtype=float)
            diameter = float(data.get("image_diameter_px", math.nan))
        except (KeyError, TypeError, ValueError, AttributeError):
            raise CalibrationError(f"{source}: corrupt pixel-locking pattern; re-run "
                                   "`plenoptrack calibrate`") from None
        k = 4 * harmonics * (harmonics + 1)
        if (not 1 <= harmonics <= 4 or coef.shape != (2, 2, k) or not np.all(np.isfinite(coef))
                or not (0 <= lo <= hi < np.inf) or rms.shape != (2,)
                or (math.isfinite(diameter) and diameter <= 0) or math.isinf(diameter)):
            raise CalibrationError(f"{source}: corrupt pixel-locking pattern; re-run "
                                   "`plenoptrack calibrate`")
        return cls(coef=coef, harmonics=harmonics, travel_range=(lo, hi), n_residuals=n,
                   rms_px=rms, image_diameter_px=diameter)

    def bias(self, phase: np.ndarray, travel) -> np.ndarray:
        """(M, 2) bias ``(s, t)`` at the phases ``phase`` (M, 2) of images that travel
        ``travel`` (scalar or (M,), view pixels; NaN: the middle of the fitted range),
        view pixels: what to subtract from centroids there."""
        terms = fourier_terms(phase, self.harmonics)
        lo, hi = self.travel_range
        travel = np.broadcast_to(np.asarray(travel, dtype=float), (len(terms),))
        travel = np.clip(np.where(np.isfinite(travel), travel, 0.5 * (lo + hi)), lo, hi)
        return np.column_stack([terms @ self.coef[c, 0] + travel * (terms @ self.coef[c, 1])
                                for c in range(2)])


def fit_locking_pattern(residual: np.ndarray, phase: np.ndarray, travel: np.ndarray, *,
                        harmonics: int = 1, min_per_term: int = 40) -> LockingPattern | None:
    """Fit the bias of centroids as a Fourier series in their lattice phase whose
    amplitudes change linearly with the image's travel.

    Parameters
    ----------
    residual : (M, 2) float ndarray
        Centroids minus their particles' predictions ``(s, t)``, view pixels, of
        particles whose images travel across many lens cells.
    phase : (M, 2) float ndarray
        :func:`lattice_phase` of those centroids.
    travel : (M,) float ndarray
        Travel of each centroid's particle across the aperture, view pixels
        (:func:`~plenoptrack.locate.uncertainty.image_travel_px`).
    harmonics : int
        Highest harmonic of the series (1: 8 terms per component and amplitude).
    min_per_term : int
        At least this many residuals per fitted term, or no pattern (None): with fewer,
        the fitted pattern's own noise (about ``sd sqrt(K / M)``) approaches the bias
        it corrects.

    Returns
    -------
    LockingPattern or None
    """
    residual = np.asarray(residual, dtype=float).reshape(-1, 2)
    phase = np.asarray(phase, dtype=float).reshape(-1, 2)
    travel = np.asarray(travel, dtype=float).ravel()
    ok = (np.all(np.isfinite(residual), axis=1) & np.all(np.isfinite(phase), axis=1)
          & np.isfinite(travel))
    residual, phase, travel = residual[ok], phase[ok], travel[ok]
    terms = fourier_terms(phase, harmonics)
    k = terms.shape[1]
    design = np.column_stack([np.ones(len(phase)), travel, terms, terms * travel[:, None]])
    if len(residual) < min_per_term * design.shape[1]:
        return None
    keep = np.ones(len(residual), dtype=bool)
    for _round in range(3):
        # normal equations: the design has 18 columns and tens of thousands of rows;
        # twice as fast as lstsq's SVD of it (benchmarks/bench_locking_fit.py)
        kept = design[keep]
        coef = np.linalg.lstsq(kept.T @ kept, kept.T @ residual[keep], rcond=None)[0].T
        misfit = residual - design @ coef.T
        scale = _MAD_TO_SIGMA * np.median(np.abs(misfit[keep]), axis=0)
        keep = np.all(np.abs(misfit) <= 3.0 * np.maximum(scale, 1e-12), axis=1)
        if keep.sum() < min_per_term * design.shape[1]:
            return None
    pattern = LockingPattern(coef=np.stack([coef[:, 2:2 + k], coef[:, 2 + k:]], axis=1),
                             harmonics=int(harmonics),
                             travel_range=(float(travel[keep].min()),
                                           float(travel[keep].max())),
                             n_residuals=int(keep.sum()), rms_px=np.zeros(2))
    bias = pattern.bias(phase[keep], travel[keep])
    return dataclasses.replace(pattern, rms_px=np.sqrt(np.mean(bias ** 2, axis=0)))


def pattern_from_dots(points, dlfc, grid, *, harmonics: int = 1) -> LockingPattern | None:
    """The pixel-locking pattern of a calibration's dot cards.

    Each dot's centroids scatter about the fitted DLFC's predictions of its known place
    by the pull at each view's phase (the polynomial, fitted on dots at every phase, does
    not follow it); cards near focus show the pattern at small travel directly.

    Parameters
    ----------
    points : DataFrame
        The dots' centroids as the DLFC was fitted on them: columns ``u, v, s, t, x, y,
        z`` and, to tell the dots apart, ``card, i, j`` (else ``z, i, j``).
    dlfc : DLFC
        The DLFC fitted on ``points``.
    grid : LensletGrid
        The lenslet grid the cards were decoded with.
    harmonics : int
        See :func:`fit_locking_pattern`.

    Returns
    -------
    LockingPattern or None
        None when the dots are too few for the fit.
    """
    from .uncertainty import image_travel_px

    keys = [c for c in ("card", "i", "j") if c in points.columns]
    if keys != ["card", "i", "j"]:
        keys = ["z", "i", "j"]
    dot = points.groupby(keys, sort=False).ngroup().to_numpy()
    xyz = points[["x", "y", "z"]].to_numpy(float)
    uv = points[["u", "v"]].to_numpy(float)
    first = np.unique(dot, return_index=True)[1]
    travel = image_travel_px(dlfc, xyz[first], dot, uv)[dot]
    s, t = dlfc.predict(xyz[:, 0], xyz[:, 1], xyz[:, 2], uv[:, 0], uv[:, 1])
    pred = np.column_stack([s, t])
    residual = points[["s", "t"]].to_numpy(float) - pred
    pattern = fit_locking_pattern(residual, lattice_phase(grid, pred), travel,
                                  harmonics=harmonics)
    if pattern is None or "dark_area" not in points.columns:
        return pattern
    area = points["dark_area"].to_numpy(float)
    area = area[np.isfinite(area) & (area > 0)]
    if len(area) == 0:
        return pattern
    return dataclasses.replace(pattern,
                               image_diameter_px=float(2.0 * np.sqrt(np.median(area) / math.pi)))
