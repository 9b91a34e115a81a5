"""A particle's opacity from its images, and the diameter of its body rather than its shadow.

The measured diameter is that of an opaque disc with the particle's shadow (the summed
relative darkness of its images, :mod:`~plenoptrack.locate.segment`). A particle that
passes a fraction ``tau`` of the light casts a shadow ``c = 1 - tau`` as dark, and that disc
is ``sqrt(c)`` of its true diameter: 5 % small at ``tau = 0.1``. A large image shows ``c``
as the darkness of its plateau; a small one never reaches its plateau, because the views'
edge blur lowers its peak darkness to

    p = c (1 - exp(-r^2 / (2 sigma^2)))

the centre of a disc of radius ``r`` blurred by a Gaussian of standard deviation ``sigma``
(view pixels). The blur comes from the calibration: its dot cards are opaque discs
(``c = 1``), so each dot image gives ``sigma = r / sqrt(-2 ln(1 - p))`` from its shadow
radius and peak darkness; the median per card depth is stored with the calibration
(:func:`edge_blur_by_depth`; it grows away from the focal plane, where a view's small
aperture blurs the image). A particle's opacity follows from its median peak darkness and
shadow radius ``r_s = r sqrt(c)`` (:func:`opacity`), and its diameter is ``2 r_s /
sqrt(c)``.

On the accuracy matrix's base cell (0.4 mm spheres passing 0-10 % of the light on
realistic optics) the median diameter ratio went from 0.951 to 0.995 on the development
seeds and from 0.942 to 0.993 on the validation seeds; with ideal optics (opaque
particles) 0.993 to 0.994 and 0.984 to 0.994. Simulated `small` frames with every
particle passing 15 % (30 %) of the light read 0.99-1.00 instead of 0.92 (0.83).

The smaller an image is against its blur, the more its peak depends on the blur:
``s = |d ln c / d ln sigma| = 2 q / (1 - q)`` with ``q = x / (e^x - 1)`` and ``x = r^2 / (2
sigma^2)``. Up to :data:`MAX_BLUR_SENSITIVITY` (1: a 10 % error in the blur moves the
opacity by at most 10 %; images whose blurred peak reaches about 0.85 of their opacity)
the solution is used as it is. Beyond, the correction is damped in its logarithm::

    ln c_used = (MAX_BLUR_SENSITIVITY / s)^2 ln c

so that the opacity used moves by about ``MAX^2 / s`` per unit relative error of the
blur (the damping taken as fixed): less than at the bar, the less the more the image is
blurred. A peak darker than an opaque disc
gives (two overlapping images) is taken as opaque.

History, development seeds of the accuracy matrix: the correction was first applied down
to a blurred peak of half the opacity, and 0.4 mm spheres at magnification -0.3 (images
1.6 px across) read 1.050 of their diameter with ideal optics (opaque particles), 0.987
without the correction. It was then cut off at the bar, the images beyond it taken as
opaque. Damped beyond the bar instead, on the acceptance matrix
(``benchmarks/accuracy_matrix.py --acceptance``; development seeds, then validation
seeds), median diameter ratios:

============================  =====================  =====================
cell                          cut off at the bar     damped
============================  =====================  =====================
0.4 mm, M -0.3, realistic     0.944, 0.949           0.954, 0.959
0.4 mm, M -0.3, ideal         0.990, 0.989           1.002, 1.000
0.2 mm, M -0.5, realistic     0.945, 0.949           0.955, 0.960
0.2 mm, M -0.5, ideal         0.989, 0.989           1.012, 1.011
============================  =====================  =====================

(realistic optics: particles passing 0-10 % of the light; ideal: opaque). No other row
of that matrix changed.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

__all__ = ["edge_blur_by_depth", "blur_at", "opacity", "blur_sensitivity",
           "MAX_BLUR_SENSITIVITY"]

MAX_BLUR_SENSITIVITY = 1.0
"""Largest change of the opacity used, per cent per per cent of error in the blur: beyond
it (:func:`blur_sensitivity` above this) the correction is damped (module notes); the
peak then depends more on the blur than on the particle."""

_MIN_DOTS = 5


_MAX_DOT_PEAK = 0.99
"""A dot image darker than this at its peak only bounds the blur: it is taken at this."""


def _blur_px(peak, shadow_radius_px) -> np.ndarray:
    """Edge blur ``r / sqrt(-2 ln(1 - p))`` of opaque disc images (NaN where undefined);
    a peak above :data:`_MAX_DOT_PEAK` (an image much larger than its blur, whose peak
    says only that the blur is small) gives that bound, ``r / 3.03``."""
    p = np.asarray(peak, dtype=float)
    r = np.asarray(shadow_radius_px, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = r / np.sqrt(-2.0 * np.log1p(-np.minimum(p, _MAX_DOT_PEAK)))
    return np.where((p > 0.1) & (r > 0) & np.isfinite(sigma), sigma, np.nan)


def edge_blur_by_depth(dots: pd.DataFrame) -> tuple:
    """The views' edge blur per dot-card depth, from the dots' images.

    Parameters
    ----------
    dots : DataFrame
        One row per dot image: card depth ``z`` (mm), peak relative darkness ``darkness``
        and summed relative darkness ``dark_area`` (view pixels), as the segmentation
        gives them for the calibration's dot cards (opaque discs).

    Returns
    -------
    tuple of (z, sigma_px)
        One row per depth with at least 5 usable dot images: the median of ``r /
        sqrt(-2 ln(1 - p))`` with ``r = sqrt(dark_area / pi)``, view pixels; sorted by
        ``z``. Empty when no depth has enough.
    """
    if len(dots) == 0:
        return ()
    z = dots["z"].to_numpy(float)
    r = np.sqrt(np.maximum(dots["dark_area"].to_numpy(float), 0.0) / math.pi)
    sigma = _blur_px(dots["darkness"].to_numpy(float), r)
    rows = []
    for depth in np.unique(z[np.isfinite(z)]):
        mine = sigma[(z == depth) & np.isfinite(sigma)]
        if len(mine) >= _MIN_DOTS:
            rows.append((float(depth), float(np.median(mine))))
    return tuple(rows)


def blur_at(rows, z) -> np.ndarray:
    """Edge blur at depths ``z`` (mm) from :func:`edge_blur_by_depth` rows, view pixels:
    interpolated linearly between the card depths, constant beyond; NaN without rows."""
    z = np.asarray(z, dtype=float)
    rows = np.asarray(rows, dtype=float).reshape(-1, 2)
    if len(rows) == 0:
        return np.full(z.shape, np.nan)
    out = np.interp(z, rows[:, 0], rows[:, 1])
    return np.where(np.isfinite(z), out, np.nan)


def opacity(peak, shadow_radius_px, blur_px, *, iterations: int = 40) -> np.ndarray:
    """Opacity ``c`` of particles from their images' peak darkness and shadow radius.

    Solves ``p = c (1 - exp(-r_s^2 / (2 sigma^2 c)))`` for ``c`` (module notes); the
    left side grows with ``c``, so bisection on ``[p, 1]`` finds it.

    Parameters
    ----------
    peak : (N,) float array_like
        Median peak relative darkness of each particle's images.
    shadow_radius_px : (N,) float array_like
        Radius of the opaque disc with the same shadow, view pixels.
    blur_px : (N,) float array_like or float
        Edge blur at each particle's depth, view pixels (:func:`blur_at`).
    iterations : int
        Bisection steps (40 resolve ``c`` to 1e-12).

    Returns
    -------
    (N,) float ndarray
        ``c`` in ``(0, 1]``: 1 where the peak reaches what an opaque disc of that shadow
        gives; where the solution's :func:`blur_sensitivity` ``s`` exceeds
        :data:`MAX_BLUR_SENSITIVITY`, the solution damped towards 1 as
        ``c^((MAX / s)^2)`` (module notes); NaN where an input is missing.
    """
    p = np.asarray(peak, dtype=float)
    r2 = np.asarray(shadow_radius_px, dtype=float) ** 2
    s2 = np.asarray(blur_px, dtype=float) ** 2
    p, r2, s2 = np.broadcast_arrays(p, r2, s2)
    ok = np.isfinite(p) & np.isfinite(r2) & np.isfinite(s2) & (p > 0) & (r2 > 0) & (s2 > 0)
    a = np.where(ok, r2 / (2.0 * np.where(ok, s2, 1.0)), 1.0)

    def peak_of(c):
        return c * -np.expm1(-a / c)

    lo, hi = np.where(ok, np.minimum(p, 1.0), 1.0), np.ones(p.shape)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        below = peak_of(mid) < p
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    c = 0.5 * (lo + hi)
    # ln c moves by s times the blur's relative error: beyond MAX_BLUR_SENSITIVITY the
    # correction is damped by (MAX / s)^2, continuing the full correction below it
    s = blur_sensitivity(a / c)
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = np.where(s > MAX_BLUR_SENSITIVITY, (MAX_BLUR_SENSITIVITY / s) ** 2, 1.0)
    c = np.where(peak_of(np.ones(p.shape)) <= p, 1.0, c ** np.nan_to_num(weight))
    return np.where(ok, c, np.nan)


def blur_sensitivity(x) -> np.ndarray:
    """``|d ln c / d ln sigma|`` of the opacity found from a peak (module notes).

    Parameters
    ----------
    x : float array_like
        ``r^2 / (2 sigma^2)`` of the body's radius ``r`` and the blur ``sigma``.

    Returns
    -------
    float ndarray
        ``2 q / (1 - q)`` with ``q = x / (e^x - 1)``: 0.23 for a disc of radius 1.5 px
        blurred by 0.56 px, 1 at ``x = 1.90`` (a blurred peak of 0.85 of the opacity),
        growing without bound as the image shrinks against its blur.
    """
    x = np.asarray(x, dtype=float)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        q = np.where(x > 0, x / np.expm1(np.maximum(x, 1e-300)), 1.0)
        return np.where(q < 1, 2 * q / (1 - q), np.inf)
