"""Standard uncertainty of a located particle: view-correlated centroid errors and the
DLFC's own model error.

The least-squares solve gives ``sigma_stat = sqrt(s^2 diag (J^T J)^-1)`` from the scatter
of a particle's centroids about their predictions (``s^2`` over ``2n - 3`` degrees of
freedom). That figure assumes ``n`` independent centroid errors. They are not
independent: neighbouring views share raw pixels (bilinear and hexagonal resampling), one
overlapping image or occluder disturbs a patch of the aperture, and an image's centroid
bias changes slowly from view to view. Errors shared by many views move the solution
without showing in the residuals, so ``sigma_stat`` is too small by about the square root
of the number of views that move together. The reported uncertainty is

    sigma = sqrt((k * sigma_stat)^2 + sigma_model^2 + (f * d)^2)

per axis, with

- ``k`` (``SolveSettings.error_scale``): the square root of the number of views whose
  errors move together (``n_eff = n / k^2``), measured on the development seeds of the
  validation matrix (``benchmarks/accuracy_matrix.py``) and checked on its validation
  seeds (docs: fraction of particles within 1, 2 and 3 sigma);
- ``sigma_model``: the DLFC's own error in object space at the particle's depth
  (:attr:`~plenoptrack.locate.dlfc.FitReport.model_error_by_depth_mm`, interpolated
  linearly between the calibration depths, constant beyond them): of the calibration
  dots' position error beyond their own centroid noise, the part neighbouring dots share
  (a misplaced or tilted card) whole, and each dot's own part (a misprinted dot) only as
  far as the fit takes it up (:func:`~plenoptrack.locate.dlfc.model_error_by_depth`). A
  calibration written without it gives the dots' whole RMS position error
  (:attr:`~plenoptrack.locate.dlfc.FitReport.position_rms_mm`), which counts their noise
  and print errors too; 0 for a DLFC without either. On the realistic `small` camera
  the dots' 5 um print error made up almost all of their lateral excess, and counted
  whole it was 3 times what reaches a particle;
- ``f * d`` (``SolveSettings.size_error``, added by :func:`with_shape_error` after
  :func:`total_sigma`): a fraction of the particle's measured diameter, lateral and in
  depth. A large image's centroid carries biases that grow with the image and that every
  view shares (its sampling by the lenslet grid, a glint, the light it lets through); on
  the development seeds of the matrix the errors of 2 mm particles were 2-3 times those
  of 0.4 mm ones while the rest of sigma was not.

Scatter beyond the frame's typical scatter. A particle whose centroids scatter more than
the frame's median particle (reduced chi-square ``chi2 = s^2 / s0^2 > 1``,
:func:`reduced_chi2`) carries an error source the others do not: most often another
particle's image overlapping its own, or two particles taken for one. Such an error moves
the centroids of a whole region of the aperture together, so it does not average down
over the views as the typical scatter does. When :func:`total_sigma` is given ``chi2``
(``SolveSettings.excess_scatter``, on by default) the typical part ``s0^2`` keeps the
factor ``k^2`` and the excess ``s^2 - s0^2`` is counted as shared by all ``n`` views::

    sigma^2 = sigma_stat^2 (k^2 min(1, 1 / chi2) + n max(0, 1 - c / chi2)) + sigma_model^2

which equals the formula above for ``chi2 <= c`` and is never smaller than it (a
particle of fewer than ``k^2`` views keeps the plain form). On the development seeds of the
validation matrix this halves the fraction of errors beyond 3 sigma (realistic optics:
x 0.14 -> 0.08, z 0.064 -> 0.044); the figures on the validation seeds are in the
uncertainty guide.

Only the excess beyond chance counts: ``c = 1 + 2 sqrt(2 k^2 / (2n - 3))``
(:data:`EXCESS_SIGNIFICANCE` standard errors; :func:`chance_chi2`). ``chi2`` is the ratio of
two scatters, and the particle's own is measured with ``(2n - 3) / k^2`` independent
degrees of freedom (its views' errors move together in groups of ``k^2``), so a particle
of typical scatter reads ``chi2 = 1 +- sqrt(2 k^2 / (2n - 3))`` (0.23 for 100 views), and
half of the frame's particles read above 1 by construction. Counted as shared by all ``n``
views, that noise alone doubled the sigma of a particle at ``chi2 = 1.2``. On the
development seeds of the validation matrix (realistic optics, sparse cells at 0.005 per
microlens, 1712 particles) the particles with ``chi2`` of 1-2 had sigma_z about twice
their errors' spread (median ``|dz| / sigma_z`` 0.44 / 0.6745 against 0.72 below 1);
counting the excess from ``c`` the fraction within 1 sigma went from 0.72 / 0.86 / 0.85
(x / y / z) to 0.68 / 0.84 / 0.81 with the fraction beyond 3 sigma unchanged
(0.006 / 0.005 / 0.001 -> 0.007 / 0.005 / 0.001).

The excess counts for a particle refitted to the view pixels too
(:func:`~plenoptrack.locate.perspective.refine_particles`), whose ``sigma_stat`` comes
from that image fit. Its centroids' excess scatter marks a disturbance (an unseen
neighbour, an image that is not a disc, two particles taken for one) that the fit's
residuals, judged view by view, do not reveal: on the development seeds, the refined
particles with ``chi2 > 5`` had 16 % of their lateral and 10 % of their depth errors
beyond 3 sigma when the excess was left out for them, 11 % and 2 % with it.

Sampling error shared near the focal plane. A view pixel is one microlens; a centroid is
biased towards the nearest view-pixel centre (pixel-locking) by an amount set by the
image's sub-pixel phase. The image of a particle moves across its views by
``travel_px`` view pixels (:func:`image_travel_px`: 0 at the focal plane, growing with
defocus). Views whose images lie within :data:`SAMPLING_CELL_PX` (half a view pixel) of
each other see it at about the same phase and share the bias, so there are only
``g = (1 + travel / 0.5)^2`` independent groups (:func:`sampling_groups`). Near focus
``g`` is 1-4: every view carries the same bias, the residuals do not show it and the
particle's own scatter ``s^2`` understates the per-view error. With
``SolveSettings.sampling_error`` (on by default) the variance factor gains ``n / g``
times the frame's typical scatter (``1 / chi2`` in units of the particle's own)::

    k^2  ->  k^2 + (n / g) / chi2        (chi2 taken as 1 when unknown)

A refined particle's ``sigma_stat`` is its image fit's, set by the pixel noise; it says
nothing of the sampling error. Its shared part is sized as its centroid solve's would be,
``(n / g) s0^2 diag (J^T J)^-1``: the frame's typical per-view centroid variance
(:func:`typical_scatter_px2`) through the particle's own views (:func:`centroid_geometry`).
Sized by the fit's sigma, the refined particles within one view pixel of travel had 10.8 %
of their x errors beyond 3 sigma on the development seeds (realistic optics, 0.4 mm spheres
at 0.005-0.05 per microlens); sized by the typical scatter, 1.0 %.

On the development seeds of the validation matrix, before this term, the particles whose
image moved by less than 0.75 view pixels (ideal optics, base cell: abs(z) < 0.9 mm) had a
robust depth spread of about 0.065 mm against a median sigma_z of 0.041 mm, and 3 of the
15 lay beyond 3 sigma; pooled over the coverage cells, the term takes the fraction beyond
3 sigma in z from 0.042 to 0.023 (ideal) and from 0.028 to 0.021 (realistic), and makes the
1-sigma coverage about the same at every travel.

Pixels the image model leaves unexplained. A particle refitted to the view pixels
(:func:`~plenoptrack.locate.perspective.refine_particles`) is fitted with one blurred
disc per image; the fit's model error ``e`` is the RMS of what that model leaves in the
pixels beyond their noise. Where ``e`` exceeds ``CheckSettings.refine_max_model_error``
(``e_max``, what a fit that explains its pixels leaves) the pixels hold something the
model lacks: a neighbour never located, a third particle on the line of sight, an image
that is not a disc. The fit then either stays unexplained (the particle keeps its
centroid solution, flagged ``UNEXPLAINED``) or is the best split into particles on one
line of sight that still does not explain everything (``SPLIT``). Either way that
structure is the same in neighbouring views and moves the solution coherently, which
neither the centroids' nor the image fit's scatter shows. With
``SolveSettings.unexplained_error`` (on by default) :func:`with_unexplained_pixels`
scales such a particle's statistical uncertainty by ``e / e_max``: no new constant, and
1 for every particle whose pixels are explained. On the development seeds of the
validation matrix it took the split particles' errors beyond 3 sigma from 14-20 % to
8-10 % laterally and from 9-10 % to 0-1.4 % in depth; on the validation seeds, pooled,
the fraction beyond 3 sigma in z fell from 0.016 to 0.009 (ideal) and from 0.020 to
0.011 (realistic), laterally from 0.030-0.040 to 0.023-0.029.

Darkness beside a particle that could not be taken apart from it. In a crowd, two or
three particles can lie on nearly one line of sight, 0.1-0.3 mm apart laterally, their
images merged in every view and moving apart by less than a view pixel across the
aperture. The locator finds one of them; its image fit takes in part of the other's
darkness and settles between the two, while explaining the pixels well enough that
neither the fit's residuals nor the centroids' scatter show it. The hidden-particle
search (:func:`~plenoptrack.locate.perspective.search_hidden_rounds`) sees that darkness
in the residual light field: a candidate whose images merge with the located particle's
without parallax, or that a joint fit cannot take apart from it, and whose body does not
overlap the located particle's in space (then it was that particle's own image, not
quite modelled). The particle may have moved towards that candidate by anything from
nothing to half of the offset between them (the two images taken in as one), so with
``SolveSettings.companion_error`` (on by default) :func:`with_offset_range` adds
the RMS of that range (up to ``offset / 2``), ``offset / (2 sqrt 3)`` per axis, in
quadrature. No constant is tuned. On the development seeds of the validation matrix
(realistic optics, 0.4 mm spheres) 5 % of the particles at 0.025 per microlens and 24 %
at 0.05 had such a companion; 30 % and 16 % of them lay beyond 3 sigma laterally,
against 2.1 % and 2.0 % of the others, and 6.7 % and 1.0 % with the term. The fraction
of all particles beyond 3 sigma went from 0.024 / 0.027 / 0.005 (x / y / z) to 0.016 /
0.015 / 0.001 at 0.025 and from 0.030 / 0.042 / 0.005 to 0.007 / 0.015 / 0.000 at 0.05;
within 1 sigma rose by 0.01-0.07. Elongated images leave darkness at their ends that a
disc does not model: 30 % of the sparse 0.4 mm ellipsoids had a companion, within 1
sigma went from 0.61 / 0.68 to 0.71 / 0.76 in x / y and beyond 3 sigma stayed at 0.042.

An image fit and a centroid solution that disagree. A particle refitted to the view
pixels (:func:`~plenoptrack.locate.perspective.refine_particles`) has two measurements of
its place: the centroid solution from before the refit and the fit itself. The refit
exists because a neighbour's image overlaps the particle's, which pulls the centroids;
the fit models that neighbour, but not one it was never told of, nor an image that is
not a disc, and those pull the fit while leaving its residuals, judged view by view,
small. Where the two disagree by far more than their uncertainties, nothing in the
frame says which is right, so the truth is taken to lie anywhere between them: with
``SolveSettings.refit_error`` (on by default) :func:`with_offset_range` adds the RMS of a
shift by anything from none to the whole disagreement, ``|fit - centroid| / sqrt 3``
per axis, in quadrature. No constant is tuned. It does not reach a half of a split
(whose centroids are the merged pair's) or a particle put back by its image (whose
centroids held merged images). On the development seeds of the validation matrix
(realistic optics), the refitted particles beyond 3 sigma laterally had a disagreement of
4.0-4.2 of their sigma (median), the others 0.6; the fraction of particles beyond 3 sigma
went, in x / y, from 0.012 / 0.014 to 0.006 / 0.005 in the sparse cells (0.005 per
microlens, 0.4-2 mm spheres and 0.4 mm ellipsoids), from 0.013 / 0.016 to 0.009 / 0.013
at 0.025 and from 0.017 / 0.014 to 0.015 / 0.012 at 0.05, while the share within 1
sigma rose by 0.01-0.08. On the validation seeds (acceptance matrix, realistic optics,
pooled over the bands) from 0.016 / 0.014 to 0.014 / 0.012, in the sparse band from
0.006 / 0.005 to 0.003 / 0.002.

The centre of an irregular body. Every view shows a particle's silhouette, and the
solve finds where the silhouettes' centroids come from. For a body symmetric about its
centre (a sphere, a droplet, an ellipsoid) that is its centre of mass. For an irregular
one (a fragment) the centroid of its silhouette lies off the projection of its centre of
mass, by an amount that no image of it shows: on the simulator's random fragments
(convex pieces, aspect up to 3) 2.0 % of the volume-equivalent diameter RMS per lateral
axis, the same at every measured elongation (1.0-1.2: 2.0 %, above 1.7: 2.5 %; 274
fragments of 0.4 mm, development seeds of the matrix's fragment cell, ideal optics).
There the median lateral error was 11 um against a median sigma of 3.7 um, and
removing each fragment's true silhouette offset took it to 3 um. With
``SolveSettings.shape_error`` set (a fraction of the measured diameter, 0 by default for
symmetric particles; about 0.02 for fragments) :func:`with_shape_error` adds that
fraction of each particle's measured diameter to its sigma on every axis.
"""

from __future__ import annotations

import numpy as np

__all__ = ["total_sigma", "model_error_mm", "reduced_chi2", "typical_scatter_px2",
           "centroid_geometry", "image_travel_px", "sampling_groups", "with_shape_error",
           "with_unexplained_pixels", "with_offset_range", "chance_chi2"]

SAMPLING_CELL_PX = 0.5
"""Views whose images of a particle lie within this distance of each other (view pixels)
share its sampling error (module notes)."""

EXCESS_SIGNIFICANCE = 2.0
"""A particle's centroid scatter counts as excess only beyond this many standard errors of
the reduced chi-square of a particle of typical scatter (:func:`chance_chi2`)."""


def chance_chi2(n_views: np.ndarray, error_scale: float) -> np.ndarray:
    """(N,) reduced chi-square (:func:`reduced_chi2`) up to which a particle's centroid
    scatter is taken for the typical scatter: ``1 + EXCESS_SIGNIFICANCE sqrt(2 k^2 /
    (2n - 3))`` for ``n`` centroids and ``k = error_scale`` (the scatter is measured with
    ``(2n - 3) / k^2`` independent degrees of freedom; module notes). Infinite where
    ``2n - 3 <= 0``."""
    dof = 2.0 * np.asarray(n_views, dtype=float) - 3.0
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(dof > 0, 1.0 + EXCESS_SIGNIFICANCE
                        * np.sqrt(2.0 * float(error_scale) ** 2 / dof), np.inf)


def model_error_mm(dlfc, z=None) -> np.ndarray:
    """The DLFC's model error in x, y, z, mm (zeros when not measured).

    Parameters
    ----------
    dlfc : DLFC
    z : (N,) float array_like, optional
        Depths, mm, at which to give the error.

    Returns
    -------
    (3,) float ndarray, or (N, 3) with ``z``
        Without ``z``, the RMS position error over all calibration dots (model error and
        the dots' noise). With ``z``, the per-depth model error interpolated linearly at
        each depth (constant beyond the first and last depth); that overall RMS where
        the calibration has no per-depth values or ``z`` is NaN.
    """
    report = getattr(dlfc, "report", None)
    rms = getattr(report, "position_rms_mm", ()) if report is not None else ()
    overall = np.asarray(rms, dtype=float) if len(rms) == 3 else np.zeros(3)
    if z is None:
        return overall
    z = np.asarray(z, dtype=float).ravel()
    out = np.tile(overall, (len(z), 1))
    rows = np.asarray(getattr(report, "model_error_by_depth_mm", ()) if report is not None
                      else (), dtype=float).reshape(-1, 4)
    finite = np.isfinite(z)
    if len(rows) and finite.any():
        for axis in range(3):
            out[finite, axis] = np.interp(z[finite], rows[:, 0], rows[:, 1 + axis])
    return out


def total_sigma(sigma_stat: np.ndarray, dlfc, *, error_scale: float,
                include_model_error: bool = True, chi2: np.ndarray | None = None,
                n_views: np.ndarray | None = None, z: np.ndarray | None = None,
                travel_px: np.ndarray | None = None,
                from_centroids: np.ndarray | None = None,
                typical_sigma: np.ndarray | None = None) -> np.ndarray:
    """Reported standard uncertainties from the least-squares ones.

    Parameters
    ----------
    sigma_stat : (N, 3) float ndarray
        ``sqrt(s^2 diag (J^T J)^-1)`` per particle, x, y, z, mm (NaN when singular).
    dlfc : DLFC
        The calibration the particles were solved with.
    error_scale : float
        ``k``: sigma_stat is scaled by it (square root of the number of views whose
        errors move together).
    include_model_error : bool
        Add the DLFC's model error in quadrature.
    chi2, n_views : (N,) float ndarrays, optional
        Reduced chi-square (:func:`reduced_chi2`) and number of centroids of each
        particle: the scatter beyond the frame's typical scatter (and beyond chance,
        :func:`chance_chi2`) is counted as shared by all views (module notes). NaN in
        ``chi2`` (no degrees of freedom) means no excess. None: no excess at all.
    z : (N,) float ndarray, optional
        Depth of each particle, mm: the model error is taken at it
        (:func:`model_error_mm`). None: the RMS over all calibration dots.
    travel_px : (N,) float ndarray, optional
        How far each particle's image moves over its views (:func:`image_travel_px`),
        view pixels; with ``n_views``, the sampling error shared by the views of
        :func:`sampling_groups` is added (module notes). NaN: none added.
    from_centroids : (N,) bool ndarray, optional
        True where ``sigma_stat`` comes from the scatter of the particle's centroids (the
        centroid solve), False where it comes from elsewhere (an image-model fit). With
        ``chi2``, the shared sampling error is sized by the frame's typical scatter
        (``1 / chi2`` of the particle's own) only where True, and by ``sigma_stat``
        itself where False (or by ``typical_sigma`` where given); the excess scatter is
        counted for both. None: all True.
    typical_sigma : (N, 3) float ndarray, optional
        The statistical uncertainty each particle's centroid solve would have with the
        frame's typical centroid scatter, ``s0 sqrt(diag (J^T J)^-1)``, mm
        (:func:`typical_scatter_px2`, :func:`centroid_geometry`). Where
        ``from_centroids`` is False and it is finite it sizes the shared sampling error
        in place of ``sigma_stat``: an image fit's statistical uncertainty comes from the
        pixel noise and says nothing of the sampling bias its images share near focus
        (module notes).

    Returns
    -------
    (N, 3) float ndarray
        ``sqrt((k sigma_stat)^2 + sigma_model^2)``, mm, or with ``chi2`` the excess form
        of the module notes; NaN where sigma_stat is NaN.
    """
    sigma_stat = np.asarray(sigma_stat, dtype=float)
    model = model_error_mm(dlfc, z) if include_model_error else np.zeros(3)
    n = len(sigma_stat)
    factor = np.full((n, 3), float(error_scale) ** 2)    # per axis: the sampling term is
    chi2 = None if chi2 is None else np.asarray(chi2, dtype=float)
    n_views = None if n_views is None else np.asarray(n_views, dtype=float)
    if travel_px is not None:
        shared = np.repeat((n_views / sampling_groups(travel_px))[:, None], 3, axis=1)
        if chi2 is not None:
            # the shared error is sized by the frame's typical scatter s0^2 = s^2 / chi2:
            # near focus the particle's own residuals do not show it
            with np.errstate(divide="ignore", invalid="ignore"):
                typical = 1.0 / chi2
            usable = np.isfinite(typical) & (chi2 > 0)
            fitted = np.zeros(n, dtype=bool)
            if from_centroids is not None:
                fitted = ~np.asarray(from_centroids, dtype=bool)
                usable &= ~fitted
            size = np.where(usable, typical, 1.0)[:, None] * np.ones(3)
            if typical_sigma is not None:
                with np.errstate(divide="ignore", invalid="ignore"):
                    ratio = (np.asarray(typical_sigma, dtype=float) / sigma_stat) ** 2
                size = np.where(fitted[:, None] & np.isfinite(ratio), ratio, size)
            shared = shared * size
        factor = factor + np.where(np.isfinite(shared), shared, 0.0)
    if chi2 is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = (1.0 / chi2)[:, None]
            beyond = 1.0 - chance_chi2(n_views, error_scale)[:, None] * inv
            excess = factor * inv + n_views[:, None] * np.maximum(beyond, 0.0)
        factor = np.where((np.isfinite(chi2) & (chi2 > 1.0))[:, None],
                          np.maximum(excess, factor), factor)
    return np.sqrt(sigma_stat ** 2 * factor + model ** 2)


def with_unexplained_pixels(sigma_stat: np.ndarray, fit_model_error: np.ndarray,
                            max_model_error: float) -> np.ndarray:
    """Scale the statistical uncertainty of particles whose pixels their image fit
    leaves unexplained (module notes).

    Parameters
    ----------
    sigma_stat : (N, 3) float ndarray
        Statistical standard uncertainties in x, y, z, mm (before
        :func:`total_sigma`).
    fit_model_error : (N,) float ndarray
        Model error of each particle's last image fit
        (:attr:`~plenoptrack.locate.refine.ImageFit.model_error`, in units of the local
        background); NaN for a particle never fitted to its pixels.
    max_model_error : float
        Model error of a fit that explains its pixels
        (``CheckSettings.refine_max_model_error``).

    Returns
    -------
    (N, 3) float ndarray
        ``sigma_stat * max(1, e / max_model_error)``; unchanged where ``e`` is NaN.
    """
    sigma_stat = np.asarray(sigma_stat, dtype=float)
    ratio = np.asarray(fit_model_error, dtype=float) / float(max_model_error)
    scale = np.where(np.isfinite(ratio), np.maximum(ratio, 1.0), 1.0)
    return sigma_stat * scale[:, None]


def with_offset_range(sigma: np.ndarray, offset_mm: np.ndarray) -> np.ndarray:
    """Add the uncertainty of a shift by anything from none to ``offset_mm``, in
    quadrature (module notes: darkness beside a particle that could not be taken apart
    from it; an image fit and a centroid solution that disagree).

    Parameters
    ----------
    sigma : (N, 3) float ndarray
        Standard uncertainties in x, y, z, mm.
    offset_mm : (N, 3) float ndarray
        The largest shift each coordinate may have taken, mm; NaN where there is none.

    Returns
    -------
    (N, 3) float ndarray
        ``sqrt(sigma^2 + offset^2 / 3)`` per axis: the RMS of a shift spread evenly over
        ``[0, offset]``; unchanged where the offset is NaN.
    """
    sigma = np.asarray(sigma, dtype=float)
    offset = np.asarray(offset_mm, dtype=float).reshape(sigma.shape)
    extra = np.where(np.isfinite(offset), np.abs(offset), 0.0) / np.sqrt(3.0)
    return np.sqrt(sigma ** 2 + extra ** 2)


def with_shape_error(sigma: np.ndarray, diameter_mm: np.ndarray, fraction) -> np.ndarray:
    """Add an uncertainty proportional to each particle's diameter to its sigma, in
    quadrature.

    Parameters
    ----------
    sigma : (N, 3) float ndarray
        Standard uncertainties in x, y, z, mm (:func:`total_sigma`).
    diameter_mm : (N,) float ndarray
        Measured equivalent diameter, mm; NaN adds nothing.
    fraction : float or (3,) array_like
        Standard uncertainty as a fraction of the diameter, on every axis or per axis
        x, y, z: ``SolveSettings.shape_error`` (the centre of an irregular body) or
        ``SolveSettings.size_error`` (a large image's centroid bias; module notes).

    Returns
    -------
    (N, 3) float ndarray
        ``sqrt(sigma^2 + (fraction * diameter)^2)`` per axis, mm.
    """
    sigma = np.asarray(sigma, dtype=float)
    fraction = np.broadcast_to(np.asarray(fraction, dtype=float), (3,))
    if not fraction.any():
        return sigma
    diameter = np.asarray(diameter_mm, dtype=float)
    extra = np.where(np.isfinite(diameter), diameter, 0.0)[:, None] * fraction[None, :]
    return np.sqrt(sigma ** 2 + extra ** 2)


def typical_scatter_px2(residual_px: np.ndarray, n_views: np.ndarray, *,
                        typical_of: np.ndarray | None = None) -> float:
    """The frame's typical per-coordinate centroid variance ``s0^2``, view pixels^2.

    The median over the particles of ``s^2 = SSR / (2n - 3)`` (:func:`reduced_chi2`
    divides each particle's ``s^2`` by it).

    Parameters
    ----------
    residual_px, n_views, typical_of
        As for :func:`reduced_chi2`.

    Returns
    -------
    float
        ``s0^2``; NaN where no particle has residual degrees of freedom.
    """
    s2 = _scatter_px2(residual_px, n_views)
    finite = np.isfinite(s2)
    if not finite.any():
        return float("nan")
    if typical_of is not None and (finite & np.asarray(typical_of, dtype=bool)).any():
        finite &= np.asarray(typical_of, dtype=bool)
    return float(np.median(s2[finite]))


def centroid_geometry(dlfc, positions: np.ndarray, owner: np.ndarray,
                      uv: np.ndarray) -> np.ndarray:
    """``diag (J^T J)^-1`` of each particle's centroid solve, mm^2 per view pixel^2.

    ``J`` stacks ``d(s, t) / d(x, y, z)`` over the views of the particle's centroids;
    times a per-coordinate centroid variance (view pixels^2) it gives the variance of a
    position solved from those centroids.

    Parameters
    ----------
    dlfc : DLFC
        The calibration the particles were solved with.
    positions : (P, 3) float ndarray
        Particle positions ``(x, y, z)``, mm.
    owner : (M,) int ndarray
        Particle row of each centroid (negative: none).
    uv : (M, 2) float ndarray
        View ``(u, v)`` of each centroid, sensor pixels.

    Returns
    -------
    (P, 3) float ndarray
        NaN for a particle with fewer than two centroids or a singular ``J^T J``.
    """
    positions = np.asarray(positions, dtype=float)
    owner = np.asarray(owner)
    n = len(positions)
    out = np.full((n, 3), np.nan)
    mine = owner >= 0
    if not mine.any():
        return out
    who = owner[mine]
    p = positions[who]
    jac = dlfc.jacobian_xyz(p[:, 0], p[:, 1], p[:, 2], uv[mine, 0], uv[mine, 1])
    jtj = np.zeros((n, 3, 3))
    np.add.at(jtj, who, np.einsum("mij,mik->mjk", jac, jac))
    count = np.bincount(who, minlength=n)
    ok = (count >= 2) & np.all(np.isfinite(jtj), axis=(1, 2))
    ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], jtj, np.eye(3)))) > 0
    if ok.any():
        out[ok] = np.diagonal(np.linalg.inv(jtj[ok]), axis1=1, axis2=2)
    return out


def image_travel_px(dlfc, positions: np.ndarray, owner: np.ndarray,
                    uv: np.ndarray) -> np.ndarray:
    """How far each particle's image moves across the views it was measured in.

    Parameters
    ----------
    dlfc : DLFC
        The calibration the particles were solved with.
    positions : (P, 3) float ndarray
        Particle positions ``(x, y, z)``, mm.
    owner : (M,) int ndarray
        Particle row of each centroid (-1 or another negative value: none).
    uv : (M, 2) float ndarray
        View ``(u, v)`` of each centroid, sensor pixels.

    Returns
    -------
    (P,) float ndarray
        ``sqrt(8 (var s + var t))`` of the particle's predicted in-view positions over its
        centroids' views, view pixels: the diameter of the disc the image sweeps over a
        round aperture (0 at the focal plane, where every view sees the image through the
        same microlenses). NaN for a particle without centroids.
    """
    positions = np.asarray(positions, dtype=float)
    owner = np.asarray(owner)
    n = len(positions)
    mine = owner >= 0
    if not mine.any():
        return np.full(n, np.nan)
    who = owner[mine]
    p = positions[who]
    s, t = dlfc.predict(p[:, 0], p[:, 1], p[:, 2], uv[mine, 0], uv[mine, 1])
    count = np.bincount(who, minlength=n).astype(float)
    var = np.zeros(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        for w in (s, t):
            mean = np.bincount(who, w, minlength=n) / count
            var += np.bincount(who, (w - mean[who]) ** 2, minlength=n) / count
    return np.sqrt(8.0 * var)


def sampling_groups(travel_px: np.ndarray) -> np.ndarray:
    """Number of groups of views whose sampling errors are independent.

    ``(1 + travel / SAMPLING_CELL_PX)^2``: views whose images of the particle lie within
    half a view pixel of each other see it through the same microlenses at the same
    sub-pixel phase and share its sampling (pixel-locking) error; across the swept disc
    there are about ``travel / 0.5`` such groups along each axis.

    Parameters
    ----------
    travel_px : (N,) float ndarray
        :func:`image_travel_px`, view pixels.

    Returns
    -------
    (N,) float ndarray
        At least 1; NaN where ``travel_px`` is NaN.
    """
    travel = np.maximum(np.asarray(travel_px, dtype=float), 0.0)
    return (1.0 + travel / SAMPLING_CELL_PX) ** 2


def reduced_chi2(residual_px: np.ndarray, n_views: np.ndarray, *,
                 typical_of: np.ndarray | None = None) -> np.ndarray:
    """Fit quality of each particle: reduced chi-square against the frame's typical scatter.

    Parameters
    ----------
    residual_px : (N,) float ndarray
        RMS reprojection error ``sqrt(SSR / n)`` of each particle, view pixels.
    n_views : (N,) float ndarray
        Centroids ``n`` of each particle (``2n`` equations, 3 unknowns).
    typical_of : (N,) bool ndarray, optional
        The particles whose median scatter is the typical one (default all; none of
        them finite: all).

    Returns
    -------
    (N,) float ndarray
        ``s_i^2 / median_j s_j^2`` with ``s^2 = SSR / (2n - 3)`` the per-coordinate
        centroid variance about the fit. The frame's particles share the camera, the
        noise and the calibration, so their median scatter is the typical centroid noise;
        a particle far above 1 has centroids that disagree with its position more than
        usual (overlapping images, a merged image taken for one particle). NaN where
        ``2n - 3 <= 0``; all 1 for a frame of one particle.
    """
    s2 = _scatter_px2(residual_px, n_views)
    if not np.isfinite(s2).any():
        return s2
    typical = typical_scatter_px2(residual_px, n_views, typical_of=typical_of)
    return s2 / typical if typical > 0 else np.full_like(s2, np.nan)


def _scatter_px2(residual_px, n_views) -> np.ndarray:
    """Each particle's per-coordinate centroid variance ``SSR / (2n - 3)``, view px^2."""
    residual_px = np.asarray(residual_px, dtype=float)
    n_views = np.asarray(n_views, dtype=float)
    dof = 2 * n_views - 3
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(dof > 0, residual_px ** 2 * n_views / dof, np.nan)
