"""Settings of the perspective-shift locator: one object, one section per stage.

:class:`PerspectiveLocator` holds every setting of the locator, grouped by the stage that
uses it (:class:`SegmentSettings`, :class:`ClusterSettings`, :class:`SolveSettings`,
:class:`GrowSettings`, :class:`CheckSettings`). It reads and writes the same layout as a
TOML file, one table per section, so that a run can be repeated from the settings stored
in its output table (``plenoptrack locate --config locate.toml``)::

    [segment]
    window = 41
    contrast = 0.2

    [cluster]
    n_planes = 20

Keys left out keep their defaults; a setting whose default is derived from the image or
the calibration (``depth_range_mm``, ``merge_distance_px``) is left out to keep that
derivation; ``core_contrast = false`` and ``max_view_ratio = false`` switch those steps
off. Every section validates its values when it is made and raises
:class:`~plenoptrack.errors.SettingsError` naming the setting, the accepted range and the
value it got.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
import tomllib
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from ..errors import InputFileError, SettingsError

__all__ = ["PerspectiveLocator", "SegmentSettings", "ClusterSettings", "SolveSettings",
           "GrowSettings", "CheckSettings", "read_settings", "settings_toml"]


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _require(ok: bool, name: str, expected: str, value) -> None:
    if not ok:
        raise SettingsError(f"{name} must be {expected}; got {value!r}")


def _require_switches(section) -> None:
    """Every ``bool`` setting of ``section`` must be true or false (not a string or a
    number: a TOML ``"yes"`` or ``1`` would otherwise pass as a switch silently)."""
    for f in fields(section):
        if f.type in ("bool", bool):
            value = getattr(section, f.name)
            _require(isinstance(value, (bool, np.bool_)), f.name, "true or false", value)


def _pair(name: str, value, what: str = "(low, high)") -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise SettingsError(f"{name} must be a pair {what}; got {value!r}") from None
    return lo, hi


@dataclass(frozen=True)
class SegmentSettings:
    """Finding particle images in every perspective view (the ``[segment]`` section).

    Parameters
    ----------
    window : int
        Side of the local-threshold window in each view, view pixels.
    contrast : float
        A particle pixel is darker than its local background by at least this fraction.
    core_contrast : float or None
        A second, higher threshold finds the dark cores of the particle images: pixels at
        least this fraction as dark as the darkest pixel of their region (as an opaque
        shadow, whichever is lighter), so that translucent particles have cores too. A
        region that holds two or more cores is the merged image of touching particles, and its
        pixels are shared out between its cores (each pixel to the nearest core along
        paths within the region), one detection per core. None disables the split.
        A region's peak is its darkest particle's; a touching neighbour that passes a
        fraction ``tau`` of the light has a plateau of ``1 - tau`` of it, so a core
        threshold above ``1 - tau`` loses that neighbour: 0.85 keeps particles passing
        up to about 10 % (0.9 less blur and noise). Chosen on the development seeds of
        the accuracy matrix among 0.85, 0.89 and 0.93 (realistic optics, 0.03 per
        microlens: recall 0.93, 0.86, 0.76).
    min_core_ratio : float
        A core of a single pixel does not count as another particle when the largest core
        in its region has more than ``1 / min_core_ratio`` pixels: the ridge of a thin
        appendage (a pin's stem) breaks into such flecks where it crosses the pixel
        grid, and noise makes them on a dark plateau. Cores of two or more pixels always
        count (in a crowded region the largest core is often the fused core of several
        particles, and judging the others against it lost them: recall 0.44 to 0.19 at
        magnification -1 on the development seeds when every core was judged so). 0
        counts every core. Chosen on the development seeds of the accuracy matrix.
    centroid_clip : float
        A pixel counts in its image's darkness-weighted centroid with at most this
        fraction of the largest weight in its region, in regions with a plateau above
        that level (some pixel above it with its four neighbours); in (0, 1], 1 leaves
        the weights as they are. The parts of a region shared out between its cores
        keep their weights. An opaque particle's image is a dark plateau with a soft
        edge, and the edge tells where it is; a bright spot on the plateau (a specular
        glint, light let through the body) pulls an uncapped centroid away from itself,
        the same way in every view. Capped, the plateau weighs evenly. A small image has
        no plateau (its peak is its edge) and is left alone: capping it only pulls its
        centroid towards the pixel grid. 0.7 was chosen against 0.85 and 1 on the
        realistic development frames of the accuracy matrix (glints lit from one side):
        the median lateral error of 1 mm spheres went from (-2.3, -1.2) to (-1.1, 0.0)
        um and their robust lateral error down by 23-36 % (2 mm: 27-44 %), 0.4 mm
        images were unchanged and crowds nearly so (see the uncertainty guide).
    area_range : (float, float)
        Accepted region areas in a view, view pixels.
    max_eccentricity : float
        Regions more elongated than this are ignored (1 keeps all).
    max_view_ratio : float or None
        Views with more than this multiple of the median number of regions per view are
        dominated by noise (dim rim views) and are not used; None keeps every view.
    max_area_ratio : float
        Regions larger than this multiple of the median region area of the frame are
        taken for merged images of several particles: they are neither clustered nor
        added to particles until the located particles show whether they are.
    merged_elongation : float
        Large regions no more elongated than this (major over minor axis) are candidates
        for single particles near the camera; more elongated ones for two merged images.
    split_pairs : bool
        Replace large regions more elongated than ``merged_elongation`` by two half
        regions placed from their second moments (the merged image of two particles);
        otherwise such regions are left out.
    """

    window: int = 31
    contrast: float = 0.15
    core_contrast: float | None = 0.85
    min_core_ratio: float = 0.08
    centroid_clip: float = 0.7
    area_range: tuple[float, float] = (2.0, math.inf)
    max_eccentricity: float = 1.0
    max_view_ratio: float | None = 2.0
    max_area_ratio: float = 1.3
    merged_elongation: float = 1.25
    split_pairs: bool = True

    def __post_init__(self) -> None:
        _require_switches(self)
        _require(_is_int(self.window) and self.window >= 3, "window",
                 "an integer of at least 3 view pixels", self.window)
        _require(0 < self.contrast < 1, "contrast", "between 0 and 1", self.contrast)
        _require(self.core_contrast is None or self.contrast < self.core_contrast < 1,
                 "core_contrast", f"None or between contrast ({self.contrast}) and 1",
                 self.core_contrast)
        _require(0 <= self.min_core_ratio < 1, "min_core_ratio", "in [0, 1)",
                 self.min_core_ratio)
        _require(0 < self.centroid_clip <= 1, "centroid_clip", "in (0, 1]",
                 self.centroid_clip)
        lo, hi = _pair("area_range", self.area_range)
        _require(0 <= lo < hi, "area_range", "(low, high) with 0 <= low < high", self.area_range)
        object.__setattr__(self, "area_range", (lo, hi))
        _require(0 < self.max_eccentricity <= 1, "max_eccentricity", "in (0, 1]",
                 self.max_eccentricity)
        _require(self.max_view_ratio is None or self.max_view_ratio > 1, "max_view_ratio",
                 "None or above 1", self.max_view_ratio)
        _require(self.max_area_ratio > 1, "max_area_ratio", "above 1", self.max_area_ratio)
        _require(self.merged_elongation >= 1, "merged_elongation", "at least 1",
                 self.merged_elongation)


@dataclass(frozen=True)
class ClusterSettings:
    """Grouping the centroids of one particle across views (the ``[cluster]`` section).

    The clustering parameters of
    :func:`~plenoptrack.locate.cluster.cluster_detections` (same names and defaults; see
    its documentation), plus the refocus planes it visits.

    Parameters
    ----------
    n_planes : int
        Refocus planes of the clustering (10 in the paper).
    depth_range_mm : (float, float) or None
        Depth range to cluster over, mm; None: the z range of the DLFC's dot cards.
    margin, noise_floor_samples, min_fraction, area_factor, max_trim, line_tol_samples,
    max_rounds, k_growth, max_iter, density_sweep, sweep_min_fraction, sweep_max_trim
        See :func:`~plenoptrack.locate.cluster.cluster_detections`.
    seed : int
        Seed of the k-means initialisation.
    """

    n_planes: int = 10
    depth_range_mm: tuple[float, float] | None = None
    margin: float = 1.2
    noise_floor_samples: float = 1.0
    min_fraction: float = 0.2
    area_factor: float = 3.0
    max_trim: float = 0.1
    line_tol_samples: float = 1.0
    max_rounds: int = 4
    k_growth: float = 0.25
    max_iter: int = 50
    density_sweep: bool = True
    sweep_min_fraction: float = 0.1
    sweep_max_trim: float = 0.3
    seed: int = 0

    def __post_init__(self) -> None:
        _require_switches(self)
        _require(_is_int(self.n_planes) and self.n_planes >= 2, "n_planes",
                 "an integer of at least 2", self.n_planes)
        if self.depth_range_mm is not None:
            near, far = _pair("depth_range_mm", self.depth_range_mm)
            _require(far > near, "depth_range_mm", "(near, far) with far > near",
                     self.depth_range_mm)
            object.__setattr__(self, "depth_range_mm", (near, far))
        _require(self.margin > 0, "margin", "positive", self.margin)
        _require(self.noise_floor_samples >= 0, "noise_floor_samples", "at least 0",
                 self.noise_floor_samples)
        for name in ("min_fraction", "max_trim", "sweep_min_fraction", "sweep_max_trim"):
            value = getattr(self, name)
            _require(0 <= value < 1, name, "in [0, 1)", value)
        _require(self.area_factor >= 0, "area_factor", "at least 0 (0 disables)",
                 self.area_factor)
        _require(self.line_tol_samples > 0, "line_tol_samples", "positive", self.line_tol_samples)
        _require(self.max_rounds >= 1, "max_rounds", "at least 1", self.max_rounds)
        _require(self.k_growth > 0, "k_growth", "positive", self.k_growth)
        _require(self.max_iter >= 1, "max_iter", "at least 1", self.max_iter)


@dataclass(frozen=True)
class SolveSettings:
    """Solving each particle's position through the DLFC (the ``[solve]`` section).

    Parameters
    ----------
    reject_k : float
        Outlier threshold of the triangulation, in robust standard deviations.
    min_views : int
        Fewest centroids a particle needs to be reported (also the smallest cluster).
    solver : {"lm", "scipy"}
        Least-squares solver (see
        :func:`~plenoptrack.locate.triangulate.triangulate_clusters`).
    error_scale : float
        The least-squares standard errors are multiplied by this: the square root of the
        number of views whose centroid errors move together (they share pixels and
        image biases). Measured on the development seeds of the validation matrix; see
        :mod:`~plenoptrack.locate.uncertainty`.
    model_error : bool
        Add the DLFC's model error (the error of the fitted mapping that its calibration
        dots show and that reaches a particle,
        :attr:`~plenoptrack.locate.dlfc.FitReport.model_error_by_depth_mm`) to the
        uncertainty in quadrature.
    excess_scatter : bool
        Count a particle's centroid scatter beyond the frame's typical scatter (reduced
        chi-square above what chance gives, :func:`~plenoptrack.locate.uncertainty.chance_chi2`:
        an overlapping or merged image) as shared by all its views instead of averaging it
        over them (:mod:`~plenoptrack.locate.uncertainty`).
    sampling_error : bool
        Count the sampling error that views share when a particle's image moves by less
        than a few view pixels across them (near the focal plane the views see it through
        the same microlenses; :mod:`~plenoptrack.locate.uncertainty`).
    unexplained_error : bool
        Scale the statistical uncertainty of a particle whose image fit leaves its pixels
        unexplained (model error ``e`` above ``check.refine_max_model_error``: a split
        group the pixels still do not fit, or an image fit given up for the centroid
        solution) by ``e / check.refine_max_model_error``
        (:func:`~plenoptrack.locate.uncertainty.with_unexplained_pixels`).
    companion_error : bool
        Add to the uncertainty of a particle beside which the hidden-particle search found
        darkness it could not take apart from it (a candidate outside its body whose
        images merge with its own without parallax, or that a joint fit could not
        separate) the RMS of a shift towards that darkness by up to half the offset,
        ``offset / (2 sqrt 3)`` per axis
        (:func:`~plenoptrack.locate.uncertainty.with_offset_range`).
    refit_error : bool
        Add to the uncertainty of a particle refitted to the view pixels the RMS of a
        shift by anything from none to the disagreement between its image fit and the
        centroid solution it had before, ``|fit - centroid| / sqrt 3`` per axis (not for
        the halves of a split or a particle put back by its image;
        :func:`~plenoptrack.locate.uncertainty.with_offset_range`).
    shape_error : float
        Standard uncertainty of where an irregular particle's centre of mass lies relative
        to the centre its silhouettes show, per axis, as a fraction of its measured
        equivalent diameter; added to sigma in quadrature. 0 (the default) for bodies
        symmetric about their centre (spheres, droplets, ellipsoids); about 0.02 for
        fragments (measured on simulated fragments;
        :mod:`~plenoptrack.locate.uncertainty`).
    size_error : (float, float)
        Standard uncertainty of a particle's position that grows with its image, as
        fractions of its measured equivalent diameter: ``(lateral, depth)``, added to
        sigma in quadrature (x and y take the first). A large image's centroid is biased
        by its sampling on the lenslet grid, glints and the light it lets through, and
        that bias moves with the image; measured on the development seeds of the
        validation matrix (:mod:`~plenoptrack.locate.uncertainty`). ``(0, 0)`` turns
        it off.
    opacity : bool
        Report the diameter of each particle's body rather than of its shadow: the
        shadow's equivalent diameter divided by the square root of the particle's opacity,
        found from its images' peak darkness and the views' edge blur that the
        calibration measured on its dot cards (:mod:`~plenoptrack.locate.opacity`). A
        particle that passes 10 % of the light otherwise reads 5 % small. No effect with
        a calibration that has no edge blur (re-run ``plenoptrack calibrate``).
    locking_correction : bool
        Correct every centroid for the pixel-locking bias the frame's own particles
        show (:mod:`~plenoptrack.locate.pixel_locking`): a view pixel is one microlens,
        and a centroid is pulled towards the lens centres by an amount that repeats with
        the lattice; near the focal plane that bias moves a particle's depth. Learned
        from the centroid residuals of the particles whose image travels across at least
        ``locking_min_travel_px`` view pixels, as a Fourier series in the lattice phase
        up to ``locking_harmonics``, after the consistency checks; every particle is then
        solved again. A frame with too few such residuals (40 per fitted term) is left
        as it is, unless ``locking_from_calibration``.
    locking_from_calibration : bool
        In a frame too sparse to show its own pattern, correct the centroids with the
        pattern the calibration measured on its dot cards
        (:attr:`~plenoptrack.calibration.Calibration.locking_pattern`), on images within
        a factor 2 of the dots' size. Off by default: on frames of three 0.4 mm spheres
        near focus it cut the depth RMS from 0.055 to 0.036 mm, but on a pin-head field
        near focus (the study test's, heads with stems) the worst depth standard
        deviation rose from 0.14 to 0.64 mm (docs: uncertainty).
    locking_min_travel_px : float
        See ``locking_correction``: particles whose image moves less than this across
        the aperture (view pixels) see too few phases to show the bias.
    locking_harmonics : int
        See ``locking_correction``.
    rim_min_valid : float
        Views whose share of valid samples is below this are cut by the rim of the
        aperture (:attr:`~plenoptrack.lightfield.decode.LightField.valid_fraction`). In
        them the centroid of an image much larger than the calibration's dots does not
        follow the relation the DLFC learned from the dots, and its depth comes out too
        near the focal plane. The position of a particle whose images are more than
        twice the dots' equivalent diameter
        (:attr:`~plenoptrack.locate.pixel_locking.LockingPattern.image_diameter_px`) is
        therefore solved, and its images fitted, without those views
        (:func:`~plenoptrack.locate.perspective.solve_large_images`,
        :meth:`~plenoptrack.locate.frame.FrameContext.fit_images`). 0 keeps every view;
        no effect with a calibration that did not record its dots' size. Chosen on the
        development seeds of the validation matrix (0.8, 0.9 and 0.97 tried; docs:
        uncertainty).
    """

    reject_k: float = 3.0
    min_views: int = 6
    solver: str = "lm"
    error_scale: float = 2.3
    model_error: bool = True
    excess_scatter: bool = True
    sampling_error: bool = True
    unexplained_error: bool = True
    companion_error: bool = True
    refit_error: bool = True
    shape_error: float = 0.0
    size_error: tuple[float, float] = (0.002, 0.01)
    opacity: bool = True
    locking_correction: bool = True
    locking_min_travel_px: float = 2.0
    locking_harmonics: int = 1
    locking_from_calibration: bool = False
    rim_min_valid: float = 0.9

    def __post_init__(self) -> None:
        _require_switches(self)
        _require(isinstance(self.rim_min_valid, numbers.Real)
                 and not isinstance(self.rim_min_valid, bool) and 0 <= self.rim_min_valid <= 1,
                 "rim_min_valid", "a fraction from 0 to 1", self.rim_min_valid)
        _require(self.reject_k > 0, "reject_k", "positive", self.reject_k)
        _require(isinstance(self.locking_min_travel_px, numbers.Real)
                 and not isinstance(self.locking_min_travel_px, bool)
                 and self.locking_min_travel_px >= 0, "locking_min_travel_px",
                 "a number of view pixels of at least 0", self.locking_min_travel_px)
        _require(_is_int(self.locking_harmonics) and 1 <= self.locking_harmonics <= 4,
                 "locking_harmonics", "a whole number from 1 to 4", self.locking_harmonics)
        _require(isinstance(self.shape_error, numbers.Real)
                 and not isinstance(self.shape_error, bool) and 0 <= self.shape_error < 1,
                 "shape_error", "a fraction from 0 to below 1", self.shape_error)
        lateral, depth = _pair("size_error", self.size_error, "(lateral, depth)")
        _require(0 <= lateral < 1 and 0 <= depth < 1, "size_error",
                 "two fractions (lateral, depth) from 0 to below 1", self.size_error)
        object.__setattr__(self, "size_error", (lateral, depth))
        _require(_is_int(self.min_views) and self.min_views >= 2, "min_views",
                 "an integer of at least 2", self.min_views)
        _require(self.solver in ("lm", "scipy"), "solver", "'lm' or 'scipy'", self.solver)
        _require(self.error_scale >= 1, "error_scale", "at least 1", self.error_scale)


@dataclass(frozen=True)
class GrowSettings:
    """Adding centroids a particle predicts and merging duplicates (the ``[grow]`` section).

    Parameters
    ----------
    passes : int
        Rounds of "cluster the unassigned centroids, solve, add centroids".
    add_tolerance_px : float
        A centroid is added to a particle when it lies within this distance (view
        pixels) of where the particle's position predicts it, or within 3 times the
        particle's RMS residual if that is larger.
    merge_distance_px : float or None
        Two particles whose predicted positions lie within this distance (view pixels)
        of each other in most views are one particle and are merged; None: half the
        median equivalent diameter of the frame's detections.
    """

    passes: int = 2
    add_tolerance_px: float = 1.0
    merge_distance_px: float | None = None

    def __post_init__(self) -> None:
        _require_switches(self)
        _require(_is_int(self.passes) and self.passes >= 1, "passes",
                 "an integer of at least 1", self.passes)
        _require(self.add_tolerance_px > 0, "add_tolerance_px", "positive",
                 self.add_tolerance_px)
        _require(self.merge_distance_px is None or self.merge_distance_px > 0,
                 "merge_distance_px", "None or positive", self.merge_distance_px)


@dataclass(frozen=True)
class CheckSettings:
    """Final consistency checks of every particle (the ``[check]`` section).

    Parameters
    ----------
    max_residual_ratio : float
        Particles whose RMS residual exceeds this multiple of the median over the frame
        (and the grow section's ``add_tolerance_px``) are dropped, or refitted on their
        best half of centroids when they are seen in many views.
    min_aperture_spread : float
        Particles whose views span less than this fraction of the aperture (RMS
        distance of their views' ``(u, v)`` from its mean, against that of all valid
        views) are dropped: their depth rests on a narrow baseline.
    max_explained : float
        Particles for which, in more than this fraction of their views, two other
        particles are predicted on the centroid are dropped (built from merged images),
        those seen in the fewest views first: a particle dropped no longer counts for
        the others.
    max_explained_strong : float
        The same limit for particles seen in at least a quarter of the valid views. A
        phantom made of merged images exists only in the views where the images merge
        (a part of the aperture, fractions near 1); a real particle in line with two
        others in depth can be overlapped in three quarters of its many views.
    refine_images : bool
        Refit the particles whose images overlap others' to the view pixels around them
        (:func:`~plenoptrack.locate.perspective.refine_particles`); their positions and
        sigmas become the image fit's. On by default: on the validation seeds of the
        accuracy matrix it lowers the depth error standard deviation and the fraction of
        depth errors beyond 0.15 mm in every cell measured (realistic optics, base cell:
        20.5 % to 11.5 %), at 1.3-5 times the CPU time of locating a small frame (docs:
        locating). ``false`` for speed.
    refine_min_overlap : float
        A particle is refitted when another's predicted image overlaps its own in at
        least this fraction of the views.
    refine_pair_overlap : float
        ... and jointly with that neighbour when they overlap in at least this fraction.
    refine_max_model_error : float
        A particle's refit is kept only when its last fit explains the pixels around it
        to within this RMS fraction of the local background, beyond the pixel noise
        (:attr:`~plenoptrack.locate.refine.ImageFit.model_error`); otherwise its
        centroid solution stands. Where the model is wrong (a neighbour missed or
        misplaced in a crowd, an elongated image) the refit is worse than the centroid
        solve. Chosen on the development seeds of the accuracy matrix.
    refine_sweeps : int
        Passes of that refit over the particles; each refits a particle beside its
        neighbours' latest fits. A second pass changed little: on hall2019 frames of
        1000 particles of 0.5 mm (ideal optics) the depth error sd was the same to
        0.5 um and the frame took 1.1-1.4 s longer; on the acceptance envelope's
        validation seeds (realistic optics) one pass gave recall 0.992 / 0.748 / 0.350 at
        0.025 / 0.05 / 0.1 per microlens against 0.996 / 0.744 / 0.320 with two, the
        sparse cells unchanged but one (magnification -1, ideal optics: recall 0.996 ->
        0.983, 3 of 240 particles).
    split_merged : bool
        Try to separate each particle whose refit could not explain the pixels into two
        particles on nearly one line of sight, which the centroids had taken for one
        (:func:`~plenoptrack.locate.split.split_merged_particles`): a joint fit of
        two images started one view pixel of image travel either side of it in depth
        (once more a third of its image radius apart when that fit runs off).
        Needs ``refine_images``.
    split_max_model_error : float
        A particle is tried as two when its last image fit leaves more than this RMS
        fraction of the local background unexplained (beyond the pixel noise); the two
        must explain the pixels better in mean square by the square of the split bar
        (this, or the next setting's floor) less the square of the frame's median fit
        error (what sets a candidate apart from a
        typical image; :func:`~plenoptrack.locate.perspective.split_gain_bar`), or by
        ``split_min_gain``, and while a split group leaves more than this unexplained
        a third image is tried. Lower than ``refine_max_model_error``: one disc fitted
        to two images that merge in every view can come close to explaining them. Chosen
        on the development seeds; on the accuracy matrix (0.05 against 0.08, the
        refinement's bar, before): recall
        summed over the development cells +0.30, validation cells +0.31, precision
        +0.03 and +0.08, plain depth standard deviation lower in most cells.
    split_floor_ratio : float
        ... or, when larger, this multiple of the frame's median image-fit model error
        (:func:`~plenoptrack.locate.split.split_bar`): one disc never explains an
        image exactly, and how far from exact the explained images of a frame typically
        are differs between cameras (about 0.04 on the ``small`` camera, realistic
        optics; 0.05 on hall2019, where 386 of 1000 particles of 0.5 mm fitted in
        (0.05, 0.08] and trying them all as splits cost 3.6 s for one more particle
        found); never above ``refine_max_model_error``. 0: the fixed bar alone, and a
        split must lower the mean-square model error by its full square.
    split_min_contrast : float
        ... kept only when both fitted images block at least this fraction of the
        background light at their centre (an opaque particle's image: about 1; a disc
        fitted to a blurred edge or to what the model misses is faint) ...
    split_min_gain : float
        ... and the two-particle fit leaves at most ``1 / split_min_gain`` of the single
        fit's model error (both RMS beyond the pixel noise).
    split_max_images : int
        A particle is split into at most this many images on nearly one line of sight:
        while the split images still leave the pixels unexplained (model error above
        ``split_max_model_error``), one of them is split again under the same tests
        (three large particles in line). 2: pairs only.
    split_trial_stride : int
        The one- and two-image fits that decide a split use every
        ``split_trial_stride``-th usable view in ``u`` and in ``v`` (a regular sub-grid
        through the central view spanning the whole aperture; all views when that leaves
        fewer than 12); a split that passes is refitted on all the views. 1: every fit on
        all the views. Most candidates are not split, and the decision rests on how well
        each model explains the pixels, not on the last digit of the fit: a quarter of
        the views decides it at a quarter of the cost.
    find_hidden : bool
        Search the frame again with the located particles' images divided out
        (:func:`~plenoptrack.locate.perspective.find_hidden_particles`): a particle whose
        images merge with a larger neighbour's in most views gives no region of its own
        until that neighbour is taken away. A particle found there is kept only when,
        fitted to the frame's own pixels beside the located particles, it is opaque
        enough (``split_min_contrast``) and explains them better by
        ``refine_max_model_error**2`` in mean square; the frame is then
        refined and split again. It runs only in frames where a located particle's fit
        leaves more than ``refine_max_model_error`` unexplained, or where regions no
        particle owns and no located image covers are seen in half as many views as a
        located particle typically is (regions freed when the checks drop a particle).
        On the accuracy matrix's validation cells it adds +0.45 recall and +0.16
        precision summed over the cells, at 1.18 times the time per frame (docs:
        locating). Needs ``refine_images``.
    hidden_rounds : int
        At most this many rounds of that search, each on the residual of every particle
        located so far (found in the rounds before included), as iterative particle
        reconstruction repeats its residual triangulation: a particle found in one
        round takes its images out of the next, which can uncover the particles its
        images hid. The rounds stop early at the first that keeps no particle more.
        At 0.1 particles per microlens (`small`, realistic optics, the accuracy
        matrix's frames), 8 rounds against 4: recall 0.375 -> 0.394 on the development
        seeds and 0.382 -> 0.404 on the validation seeds, precision 0.766 -> 0.768, 1.4
        times the time per frame there; at 0.05 the same or a few more particles
        (development 401 / 407 -> 401 / 412 matched, validation unchanged); at 0.025
        and below, on the study's pin images and on the sparse hall2019 frames the
        rounds stop before the fifth and nothing changes. 1: one search.
    hidden_floor : float
        Pixels the located particles' model lets through less than this fraction of the
        back-light are set to the background in that search: nothing behind an opaque
        image can be seen, and dividing there would only amplify the noise.
    hidden_joint : bool
        In that search, a particle found in the residual whose images coincide with one
        located particle's is fitted together with it instead of being dropped: the
        located particle's fit may have grown its disc over both images (a fitted radius
        up to 3 times its own shadow's in crowded frames). The pair starts from the
        located particle's own shadow radius and is kept under the tests of a split
        (``split_min_contrast``, ``split_min_gain`` or the split's gain bar, parallax of
        at least a view pixel, neither image one with another particle's). On the
        accuracy matrix's validation seeds (`small`, realistic optics) recall 0.992 /
        0.748 / 0.350 -> 0.996 / 0.782 / 0.390 at 0.025 / 0.05 / 0.1 particles per
        microlens, precision equal or higher, 1 mm particles 0.952 -> 0.968; crowded
        frames take 1.4-1.8 times as long (docs: locating).
    drop_duplicates : bool
        Drop a particle seen in fewer than a quarter of the valid views whose image fit
        leaves its pixels unexplained, whose images meet only one other particle's, a
        strongly seen one, and nearly coincide with them, unless it still explains its
        pixels when fitted beside the others
        (:func:`~plenoptrack.locate.hidden.drop_duplicate_particles`): pieces of a
        particle's image that the segmentation cut off in a few views, clustered into a
        particle of their own. On the accuracy matrix's development seeds (`small`,
        realistic optics) precision 0.990 -> 0.997 with mixed sizes 0.2-2 mm (recall
        0.981 -> 0.980); the 0.4 mm ellipsoid, 1 mm, 2 mm, 0.025 and 0.05 per microlens
        cells as before. Needs ``refine_images``.
    merge_pieces : bool
        Merge two particles that are pieces of one body
        (:mod:`~plenoptrack.locate.bodies`): bodies that overlap (centres closer than
        the sum of their radii) with images at one depth (their
        offset changes by less than a view pixel across the views). Two solid particles
        cannot overlap, and nothing in the images tells such a pair from one silhouette
        a glint or an elongated outline cut in two.
    """

    max_residual_ratio: float = 4.0
    min_aperture_spread: float = 0.4
    max_explained: float = 0.5
    max_explained_strong: float = 0.85
    refine_images: bool = True
    refine_min_overlap: float = 0.1
    refine_pair_overlap: float = 0.5
    refine_max_model_error: float = 0.08
    refine_sweeps: int = 1
    split_merged: bool = True
    split_max_model_error: float = 0.05
    split_floor_ratio: float = 1.2
    split_min_contrast: float = 0.5
    split_min_gain: float = 1.5
    split_max_images: int = 3
    split_trial_stride: int = 2
    find_hidden: bool = True
    hidden_rounds: int = 8
    hidden_floor: float = 0.5
    hidden_joint: bool = True
    drop_duplicates: bool = True
    merge_pieces: bool = True

    def __post_init__(self) -> None:
        _require_switches(self)
        _require(self.max_residual_ratio > 1, "max_residual_ratio", "above 1",
                 self.max_residual_ratio)
        _require(0 <= self.min_aperture_spread < 1, "min_aperture_spread", "in [0, 1)",
                 self.min_aperture_spread)
        _require(0 < self.max_explained <= 1, "max_explained", "in (0, 1]", self.max_explained)
        _require(0 < self.max_explained_strong <= 1, "max_explained_strong", "in (0, 1]",
                 self.max_explained_strong)
        _require(0 < self.refine_min_overlap <= 1, "refine_min_overlap", "in (0, 1]",
                 self.refine_min_overlap)
        _require(0 < self.refine_pair_overlap <= 1, "refine_pair_overlap", "in (0, 1]",
                 self.refine_pair_overlap)
        _require(self.refine_max_model_error > 0, "refine_max_model_error", "above 0",
                 self.refine_max_model_error)
        _require(_is_int(self.refine_sweeps) and self.refine_sweeps >= 1, "refine_sweeps",
                 "a whole number of at least 1", self.refine_sweeps)
        _require(self.split_max_model_error > 0, "split_max_model_error", "above 0",
                 self.split_max_model_error)
        _require(self.split_floor_ratio >= 0, "split_floor_ratio", "at least 0",
                 self.split_floor_ratio)
        _require(0 < self.split_min_contrast <= 1, "split_min_contrast", "in (0, 1]",
                 self.split_min_contrast)
        _require(self.split_min_gain >= 1, "split_min_gain", "at least 1",
                 self.split_min_gain)
        _require(_is_int(self.split_max_images) and self.split_max_images >= 2,
                 "split_max_images", "a whole number of at least 2", self.split_max_images)
        _require(_is_int(self.split_trial_stride) and self.split_trial_stride >= 1,
                 "split_trial_stride", "a whole number of at least 1", self.split_trial_stride)
        _require(0 < self.hidden_floor < 1, "hidden_floor", "in (0, 1)", self.hidden_floor)
        _require(_is_int(self.hidden_rounds) and self.hidden_rounds >= 1, "hidden_rounds",
                 "a whole number of at least 1", self.hidden_rounds)


_SECTIONS = {"segment": SegmentSettings, "cluster": ClusterSettings, "solve": SolveSettings,
             "grow": GrowSettings, "check": CheckSettings}


@dataclass(frozen=True)
class PerspectiveLocator:
    """Every setting of the perspective-shift locator, one section per stage.

    Call :meth:`locate` (or :func:`~plenoptrack.locate.perspective.locate_frame`) with a
    raw image and a calibration that holds a DLFC.

    Parameters
    ----------
    segment : SegmentSettings
    cluster : ClusterSettings
    solve : SolveSettings
    grow : GrowSettings
    check : CheckSettings

    Examples
    --------
    >>> from plenoptrack.locate import PerspectiveLocator
    >>> locator = PerspectiveLocator.from_dict({"segment": {"window": 41}})
    >>> locator.segment.window, locator.cluster.n_planes
    (41, 10)
    >>> locator.updated({"cluster": {"n_planes": 20}}).cluster.n_planes
    20
    """

    segment: SegmentSettings = field(default_factory=SegmentSettings)
    cluster: ClusterSettings = field(default_factory=ClusterSettings)
    solve: SolveSettings = field(default_factory=SolveSettings)
    grow: GrowSettings = field(default_factory=GrowSettings)
    check: CheckSettings = field(default_factory=CheckSettings)

    def __post_init__(self) -> None:
        for name, kind in _SECTIONS.items():
            if not isinstance(getattr(self, name), kind):
                raise SettingsError(f"{name} must be a {kind.__name__}; "
                                    f"got {type(getattr(self, name)).__name__}")

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "settings") -> "PerspectiveLocator":
        """Settings from a nested mapping ``{section: {key: value}}``; missing keys keep
        their defaults. Raises :class:`SettingsError` for an unknown section or key."""
        return cls().updated(data, source=source)

    def updated(self, data: dict, *, source: str = "settings") -> "PerspectiveLocator":
        """A copy with the values of the nested mapping ``{section: {key: value}}``."""
        if not isinstance(data, dict):
            raise SettingsError(f"{source}: settings must be a mapping of sections; got "
                                f"{type(data).__name__}")
        unknown = set(data) - set(_SECTIONS)
        if unknown:
            raise SettingsError(f"{source}: unknown section(s) {sorted(unknown)}; the sections "
                                f"are {list(_SECTIONS)}")
        changes = {}
        for name, values in data.items():
            kind = _SECTIONS[name]
            if not isinstance(values, dict):
                raise SettingsError(f"{source}: [{name}] must be a table of settings; got "
                                    f"{values!r}")
            known = {f.name for f in fields(kind)}
            bad = set(values) - known
            if bad:
                raise SettingsError(f"{source}: unknown setting(s) {sorted(bad)} in [{name}]; "
                                    f"known: {sorted(known)}")
            values = {k: (tuple(v) if isinstance(v, list)
                          else None if v is False and k in _OFF_WITH_FALSE else v)
                      for k, v in values.items()}
            try:
                changes[name] = dataclasses.replace(getattr(self, name), **values)
            except SettingsError as exc:
                raise SettingsError(f"{source}: [{name}] {exc}") from None
            except TypeError as exc:
                raise SettingsError(f"{source}: [{name}] {exc}") from None
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """The settings as a nested plain dict ``{section: {key: value}}``."""
        return {name: asdict(getattr(self, name)) for name in _SECTIONS}

    def settings(self) -> dict:
        """The settings as a nested plain dict (for provenance in output metadata)."""
        return self.to_dict()

    def digest(self) -> str:
        """Short SHA-256 of the settings (the same settings give the same digest)."""
        text = json.dumps(self.to_dict(), sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def locate(self, raw_or_lf, calibration, *, frame: int = 0, white=None):
        """Locate the particles of one frame; see
        :func:`~plenoptrack.locate.perspective.locate_frame`."""
        from .perspective import locate_frame

        return locate_frame(raw_or_lf, calibration, frame=frame, locator=self, white=white)


def read_settings(path: str | Path, *, base: PerspectiveLocator | None = None
                  ) -> PerspectiveLocator:
    """Read locator settings from a TOML file (sections as in :class:`PerspectiveLocator`).

    Parameters
    ----------
    path : str or Path
        TOML file with any of the tables ``[segment]``, ``[cluster]``, ``[solve]``,
        ``[grow]``, ``[check]``.
    base : PerspectiveLocator, optional
        Settings the file's values are applied to; default the defaults.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: settings file not found; check the path "
                             "(`plenoptrack settings --out FILE` writes one with every default)")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SettingsError(f"{path}: not a valid TOML settings file ({exc})") from None
    return (base or PerspectiveLocator()).updated(data, source=str(path))


def settings_toml(locator: PerspectiveLocator) -> str:
    """The settings as TOML text, one table per section.

    Settings left to their derived default (None) appear as comments, so that the text
    read back (:func:`read_settings`) gives the same settings.
    """
    lines = []
    for name, values in locator.to_dict().items():
        lines.append(f"[{name}]")
        for key, value in values.items():
            if value is None and key in _OFF_WITH_FALSE:
                lines.append(f"{key} = false  # off")
            elif value is None:
                lines.append(f"# {key} = ...  (left out: {_DERIVED.get(key, 'derived')})")
            else:
                lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


_DERIVED = {
    "depth_range_mm": "the z range of the calibration's dot cards, [near, far] in mm",
    "merge_distance_px": "half the median equivalent diameter of the frame's regions",
}

_OFF_WITH_FALSE = {"core_contrast", "max_view_ratio"}
"""Settings that None switches off; TOML has no None, so files write them ``false``."""


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, float):
        return ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    return str(value)
