"""The perspective-shift particle locator: one raw image to a table of 3D particles.

:func:`locate_frame` is a short pipeline of named stages over one explicit state
(section 2 of the method paper):

1. :func:`segment_frame` -- decode the raw image and segment dark particles in every
   valid perspective view (:mod:`~plenoptrack.locate.segment`); share out the pixels of
   regions holding several dark cores between those cores, and split large elongated
   regions into the two particle images their second moments imply; ignore views
   dominated by noise;
2. :func:`cluster_unassigned` -- group the unassigned centroids of each particle across
   views by k-means on projected refocus planes, finished by a density sweep
   (:mod:`~plenoptrack.locate.cluster`); large regions and split halves wait until
   particles are located and join the pool only where no located particle accounts for
   them;
3. :func:`solve_particles` -- solve each particle's (x, y, z) through the Direct Light
   Field Calibration with outlier rejection (:mod:`~plenoptrack.locate.triangulate`);
4. :func:`grow_particles` -- merge particles that are one, and from the most confident
   particle down add unassigned centroids that its position predicts in views where it
   has none; stages 2-4 repeat (``grow.passes``);
5. :func:`check_particles` -- drop particles that fail the consistency checks (too few
   or clustered views, residuals far above the typical one, built from merged images),
   refit those whose centroids are partly pulled by overlapping images, and solve again;
   correct every centroid for the pull towards the lens centres that the frame's
   particles far from focus show, and solve again (``solve.locking_correction``,
   :func:`correct_pixel_locking`, :mod:`~plenoptrack.locate.pixel_locking`);
   then (``check.refine_images``, on by default) refit particles whose images overlap
   others' to the view pixels themselves (:func:`refine_particles`,
   :mod:`~plenoptrack.locate.refine`), and (``check.split_merged``) refit as two the
   particles whose pixels one image cannot explain, two particles on nearly one line
   of sight taken for one (:func:`~plenoptrack.locate.split.split_merged_particles`), and
   search the frame again with the located particles' images divided out, in rounds
   (:func:`search_hidden_rounds`); last (``check.drop_duplicates``), drop weakly seen
   particles that are one neighbour's image found again (:func:`drop_duplicate_particles`);
6. :func:`measure_particles` -- uncertainties (least-squares errors scaled for
   view-correlated centroid errors, plus the DLFC's model error;
   :mod:`~plenoptrack.locate.uncertainty`), in-plane size and shape from the member
   regions, converted to mm with the local magnification of the calibration.

The frame's fixed data (detections, views, geometry) is a :class:`FrameContext`; what the
stages change is a :class:`ParticleState`: which detection belongs to which particle and
each particle's solution (both defined in :mod:`plenoptrack.locate._frame`). Every stage takes its
own settings section of :class:`~plenoptrack.locate.settings.PerspectiveLocator`.

References
----------
E. M. Hall, D. R. Guildenbecher, B. S. Thurow, "Development and uncertainty
characterization of 3D particle location from perspective shifted plenoptic images",
Opt. Express 27 (2019).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .._columns import POS_COLUMNS, SIGMA_COLUMNS, T_COLUMN
from ..errors import CrowdedFrameWarning, NoParticlesWarning
from ..io import warn_exposure
from ..lightfield.decode import LightField, decode
from ._assign import (_MERGED, _add_centroids, _explained_away, _merge_duplicates,
                      _predict_all, _release_unclaimed, _trim_refit)
from ._nearby import ImageSpans, pairs_within
from ._order import unique_rows
from ._frame import (_COMPANION, _FIT_CONTRAST, _FIT_ERROR, _FIT_RADIUS, _HIDDEN, _SPLIT_OF,
                     MIN_VIEW_FRACTION, FrameContext, ParticleState, SolveMemo,
                     _fit_views, _member_diameter, _split, _usable_views)
from ._regions import _region_shape, _split_pairs
from .bodies import merge_bodies, one_body_pairs, parallax_px
from .crowding import CROWDED_COVERAGE, image_coverage
from .opacity import blur_at, opacity
from .cluster import cluster_detections
from .segment import segment_views
from .split import (_coincides, _coinciding, _explains_more, _two_images, split_gain_bar,
                    split_merged_particles)
from .settings import (CheckSettings, ClusterSettings, GrowSettings, PerspectiveLocator,
                       SegmentSettings, SolveSettings)
from .triangulate import TriangulationFlag, triangulate_clusters
from .uncertainty import (centroid_geometry, image_travel_px, reduced_chi2, total_sigma,
                          typical_scatter_px2, with_shape_error, with_unexplained_pixels,
                          with_unresolved_companion)

__all__ = ["PerspectiveLocator", "PARTICLE_COLUMNS", "locate_frame", "LocateResult",
           "FrameContext", "ParticleState", "segment_frame", "cluster_unassigned",
           "solve_particles", "grow_particles", "check_particles", "refine_particles",
           "measure_particles"]

PARTICLE_COLUMNS = (T_COLUMN, *POS_COLUMNS, "sigma_x", "sigma_y", "sigma_z", "n_views",
                    "confidence", "residual_px", "chi2", "travel_px", "diameter", "major_axis",
                    "minor_axis", "orientation", "flags")
"""Columns of a particles table: ``frame``; ``x, y, z`` and their standard uncertainties
``sigma_*`` (mm); ``n_views`` (centroids used); ``confidence`` (eq. 3 of the paper);
``residual_px`` (RMS reprojection error, view pixels); ``chi2`` (fit quality: the reduced
chi-square of the particle's centroids against the frame's typical centroid scatter, about
1 for a clean fit, large when overlapping images pull some centroids); ``travel_px`` (how
far the particle's image moves across its views, view pixels: small near the focal plane,
where depth is least determined); ``diameter`` (equivalent diameter),
``major_axis``, ``minor_axis`` (mm, in the x-y plane); ``orientation`` (rad, major axis
from +x towards +y); ``flags`` (:class:`~plenoptrack.locate.triangulate.TriangulationFlag`)."""


@dataclass(frozen=True)
class LocateResult:
    """Everything the locator found in one frame.

    Attributes
    ----------
    particles : DataFrame
        One row per particle, columns :data:`PARTICLE_COLUMNS`.
    detections : DataFrame
        Every centroid found in every view with its ``particle`` row index (-1 when it was
        not used) and ``inlier`` flag.
    stage_seconds : dict
        Wall-clock time of each stage of the call, s: ``decode``, ``segment``,
        ``cluster`` (every clustering pass), ``triangulate`` (solves, duplicate merging
        and centroid addition), ``checks`` (final consistency checks and the table) and
        ``refine`` (the image-model refinement; 0 when it is off).
    image_coverage : float
        Share of each view the particle images cover (median over the views,
        :func:`~plenoptrack.locate.crowding.image_coverage`): it follows the source
        density, which sets how many particles the locator can tell apart. Above
        :data:`~plenoptrack.locate.crowding.CROWDED_COVERAGE` the frame is crowded.
        NaN where the method does not measure it.
    """

    particles: pd.DataFrame
    detections: pd.DataFrame
    stage_seconds: dict = field(default_factory=dict, compare=False)
    image_coverage: float = math.nan


def locate_frame(raw_or_lf, calibration, *, frame: int = 0,
                 locator: PerspectiveLocator | None = None, white=None) -> LocateResult:
    """Locate particles in 3D in one raw plenoptic image (perspective-shift method).

    Parameters
    ----------
    raw_or_lf : (rows, cols) ndarray or LightField
        Raw sensor image (any numeric dtype; dark particles on a bright back-light) or an
        already decoded light field.
    calibration : Calibration
        Calibration with the lenslet grid and a DLFC (``plenoptrack calibrate``).
    frame : int
        Frame index written to the ``frame`` column.
    locator : PerspectiveLocator, optional
        Settings; default ``PerspectiveLocator()``.
    white : (rows, cols) ndarray or LightField, optional
        White (flat-field) image of the camera, raw or decoded once with
        ``decode(white, calibration.grid)``. Recommended: the raw frame is divided by it
        (:func:`~plenoptrack.lightfield.decode`), so dust shadows, dead pixels and gain
        patterns the frames share with the white image are not taken for particles.
        Ignored when ``raw_or_lf`` is already a light field.

    Returns
    -------
    LocateResult
        ``particles`` (columns :data:`PARTICLE_COLUMNS`, mm) and ``detections``. An image
        with no particles gives an empty table and a :class:`NoParticlesWarning`; a black
        or saturated raw frame also an :class:`~plenoptrack.errors.ExposureWarning`.
    """
    locator = PerspectiveLocator() if locator is None else locator
    clock = _StageClock()
    with clock("decode"):
        lf = _decoded(raw_or_lf, calibration, frame, white)
    with clock("segment"):
        detections = segment_frame(lf, locator.segment, frame=frame)
    coverage = image_coverage(detections, lf)
    if coverage > CROWDED_COVERAGE:
        warnings.warn(f"frame {frame}: particle images cover {100 * coverage:.0f} % of each "
                      f"view (above {100 * CROWDED_COVERAGE:.0f} %); expect to miss particles "
                      "whose images merge with others' (on simulated frames recall was 0.87 "
                      "at 21 % and 0.55 at 38 %); a lower seeding density, smaller "
                      "magnification or thinner volume keeps more", CrowdedFrameWarning,
                      stacklevel=2)
    if len(detections) == 0:
        return _finish_empty(detections, frame, clock.seconds, coverage)
    ctx = FrameContext.build(lf, calibration, detections, locator)
    state = _cluster_and_solve(ctx, ParticleState.start(ctx, locator.segment), locator, clock)
    if state.n_particles == 0:
        return _finish_empty(detections, frame, clock.seconds, coverage)
    with clock("checks"):
        state = check_particles(ctx, state, locator)
        if locator.solve.locking_correction:
            ctx, state = correct_pixel_locking(ctx, state, locator, calibration)
    if locator.check.refine_images:
        with clock("refine"):
            state = refine_particles(ctx, state, locator)
            if locator.check.split_merged:
                state = split_merged_particles(ctx, state, locator.check)
            if locator.check.find_hidden:
                ctx, state = search_hidden_rounds(ctx, state, locator, calibration,
                                                  frame=frame)
            if locator.check.drop_duplicates:
                state = drop_duplicate_particles(ctx, state, locator)
    with clock("checks"):
        particles, detections = measure_particles(
            ctx, state, locator.solve, frame=frame,
            max_model_error=locator.check.refine_max_model_error,
            merge_pieces=locator.check.merge_pieces)
    if len(particles) == 0:
        return _finish_empty(detections, frame, clock.seconds, coverage)
    return LocateResult(particles=particles, detections=detections,
                        stage_seconds=clock.seconds, image_coverage=coverage)


def _cluster_and_solve(ctx: FrameContext, state: ParticleState, locator: PerspectiveLocator,
                       clock: "_StageClock | None" = None) -> ParticleState:
    """Stages 2-4 in their passes: cluster the unassigned regions into new particles,
    then solve and grow them (three rounds), until a pass adds none or
    ``grow.passes`` are done. ``clock`` times the ``cluster`` and ``triangulate``
    stages."""
    timed = clock if clock is not None else (lambda _name: contextlib.nullcontext())
    for _ in range(locator.grow.passes):
        with timed("cluster"):
            state, n_new = cluster_unassigned(ctx, state, locator.cluster,
                                              min_views=locator.solve.min_views)
        if n_new == 0:
            break
        with timed("triangulate"):
            for _round in range(3):
                state = solve_particles(ctx, state, locator.solve)
                state = grow_particles(ctx, state, locator.grow)
    return state


def _decoded(raw_or_lf, calibration, frame: int, white) -> LightField:
    """The frame's light field, with the views the white image showed vignetted masked."""
    if isinstance(raw_or_lf, LightField):
        lf = raw_or_lf
    else:
        image = np.asarray(raw_or_lf)
        calibration.check_image(image)
        warn_exposure(image, calibration.camera.full_scale, source=f"frame {frame}")
        lf = decode(image, calibration.grid, white=white, min_view_fraction=MIN_VIEW_FRACTION)
    vignetting = calibration.vignetting
    if vignetting is not None and vignetting.shape == lf.valid_fraction.shape:
        lf = dataclasses.replace(lf, valid_fraction=np.minimum(lf.valid_fraction, vignetting))
    return lf


def segment_frame(lf: LightField, settings: SegmentSettings, *, frame: int = 0) -> pd.DataFrame:
    """Stage 1: detections of every valid view, merged images split into particles.

    Parameters
    ----------
    lf : LightField
        Decoded frame.
    settings : SegmentSettings
    frame : int
        Written to the ``frame`` column.

    Returns
    -------
    DataFrame
        :data:`~plenoptrack.locate.segment.DETECTION_COLUMNS` plus ``whole`` (False for
        the cores and halves of split regions) and ``split_pair`` (halves of a pair
        split from its second moments); index 0..M-1, sorted by view.
    """
    kw = dict(frame=frame, window=settings.window, area_range=settings.area_range,
              max_eccentricity=settings.max_eccentricity)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        detections = segment_views(lf, contrast=settings.contrast,
                                   core_contrast=settings.core_contrast,
                                   min_core_ratio=settings.min_core_ratio,
                                   centroid_clip=settings.centroid_clip, **kw)
    if len(detections) and settings.max_view_ratio is not None:
        # A view with far more regions than the typical view is dominated by noise (a
        # dim, partly vignetted rim view): its regions would only inflate k and the
        # pool of false centroids.
        _, view_of, counts = unique_rows(detections[["v", "u"]].to_numpy(float))
        noisy = counts > settings.max_view_ratio * np.median(counts)
        if noisy.any():
            detections = detections[~noisy[view_of]]
    if len(detections) and settings.split_pairs:
        detections = _split_pairs(detections, settings.max_area_ratio,
                                  settings.merged_elongation)
    return detections.reset_index(drop=True)


def cluster_unassigned(ctx: FrameContext, state: ParticleState, settings: ClusterSettings, *,
                       min_views: int) -> tuple[ParticleState, int]:
    """Stage 2: new particles from the centroids no particle owns.

    Large round regions on which no located particle is predicted are released to the
    pool first (single particles near the camera, imaged larger than the rest). The pool
    is clustered (:func:`~plenoptrack.locate.cluster.cluster_detections`); each cluster
    becomes a particle with a thin-lens starting position.

    Returns
    -------
    state : ParticleState
        With the new particles appended (no solution yet: NaN positions).
    n_new : int
        Number of new particles; 0 when the pool is too small or nothing clustered.
    """
    owner = state.owner
    if state.n_particles:
        owner = _release_unclaimed(ctx.dlfc, state.positions, ctx.views, ctx.st, ctx.view,
                                      owner, ctx.radius_px, ctx.round_,
                                      halves=_split(ctx.detections),
                                      tolerance_px=ctx.tolerance_px,
                                      area=ctx.detections["area"].to_numpy(float),
                                      max_area_ratio=ctx.max_area_ratio)
    free = np.flatnonzero(owner == -1)
    if len(free) < min_views:
        return dataclasses.replace(state, owner=owner), 0
    kw = dataclasses.asdict(settings)
    for name in ("n_planes", "depth_range_mm"):
        kw.pop(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        clustering = cluster_detections(ctx.detections.iloc[free], ctx.geometry, ctx.alphas,
                                        min_members=min_views, **kw)
    if clustering.n_clusters == 0:
        return dataclasses.replace(state, owner=owner), 0
    start = state.n_particles
    labels = clustering.detections["cluster"].to_numpy()
    owner = owner.copy()
    owner[free[labels >= 0]] = labels[labels >= 0] + start
    initial = np.vstack([state.initial,
                         _initial_positions(clustering.clusters, ctx.camera).to_numpy()])
    n = len(initial)
    positions = np.vstack([state.positions, np.full((n - start, 3), np.nan)])
    return ParticleState(owner=owner, initial=initial, positions=positions,
                         table=state.table.reindex(np.arange(n)),
                         solved=state.solved), n - start


def solve_particles(ctx: FrameContext, state: ParticleState,
                    settings: SolveSettings) -> ParticleState:
    """Stage 3: solve every particle that owns centroids, with outlier rejection.

    Centroids rejected as outliers are released (owner -1); particles without centroids
    get NaN positions and ``n_views`` 0. A particle whose centroids are those of the
    previous solve keeps that solve's result (:class:`~plenoptrack.locate._frame.SolveMemo`).
    """
    owner = state.owner
    n = state.n_particles
    memo = state.solved
    redo = (np.ones(n, dtype=bool) if memo is None
            else memo.to_solve(ctx, settings, owner, n))
    mine = owner >= 0
    solving = np.where(mine & redo[np.maximum(owner, 0)], owner, -1)
    used = np.unique(solving[solving >= 0])
    initial = pd.DataFrame(state.initial[used], index=used, columns=list(POS_COLUMNS))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        tri = triangulate_clusters(ctx.dlfc, ctx.detections.assign(_owner=solving), initial,
                                   cluster_column="_owner", n_possible_views=ctx.n_possible,
                                   volume_depth_mm=ctx.volume_depth_mm,
                                   reject_k=settings.reject_k,
                                   min_views=min(4, settings.min_views), solver=settings.solver)
    rows = tri.to_frame().set_index("cluster")
    new_owner = np.where(tri.inliers | (owner == _MERGED), owner, -1)
    if not redo.all():
        kept = np.flatnonzero(~redo)
        rows = pd.concat([memo.table.loc[kept], rows]) if len(rows) else memo.table.loc[kept]
        same = mine & ~redo[np.maximum(owner, 0)]
        new_owner[same] = memo.owner_out[same]
    table = rows.reindex(np.arange(n))
    table["n_views"] = table["n_views"].fillna(0)
    table["flags"] = table["flags"].fillna(0)
    positions = table[list(POS_COLUMNS)].to_numpy(float)
    # copies: the memo must not change with a later stage's owner arrays
    solved = SolveMemo(context=ctx, settings=settings, owner_in=owner.copy(),
                       owner_out=new_owner.copy(), table=table)
    return dataclasses.replace(state, owner=new_owner, positions=positions, table=table,
                               solved=solved)


def grow_particles(ctx: FrameContext, state: ParticleState,
                   settings: GrowSettings) -> ParticleState:
    """Stage 4: merge particles that are one, then add the centroids each one predicts.

    Two particles whose predictions coincide in most views (``ctx.merge_px``) are merged;
    then, from the most confident particle down, an unassigned centroid within
    ``add_tolerance_px`` (or 3 times the particle's residual) of a particle's prediction
    in a view where it has none joins it. The solved positions become the starting
    positions of the next solve.
    """
    pred = _predict_all(ctx.dlfc, state.positions, ctx.views)
    n_views = state.table["n_views"].to_numpy().astype(np.int64)
    owner = _merge_duplicates(pred, ctx.st, ctx.view, state.owner, n_views, ctx.merge_px)
    owner = _add_centroids(pred, ctx.st, ctx.view, owner, state.table["residual_px"].to_numpy(),
                           state.table["confidence"].to_numpy(), settings.add_tolerance_px)
    initial = np.where(np.isfinite(state.positions), state.positions, state.initial)
    return dataclasses.replace(state, owner=owner, initial=initial)


def check_particles(ctx: FrameContext, state: ParticleState,
                    locator: PerspectiveLocator) -> ParticleState:
    """Stage 5: drop inconsistent particles, refit overlapped ones, solve again.

    Particles that fail a check (:func:`_inconsistent`) lose their centroids to the
    others. A particle seen in many views whose only fault is a high residual has part
    of its centroids pulled by overlapping images: it is refitted on its best half first
    (once). Up to three rounds, each followed by growing and solving.
    """
    state = solve_particles(ctx, state, locator.solve)
    tried = np.zeros(state.n_particles, dtype=bool)
    for _round in range(3):
        bad, refit = _inconsistent(ctx, state, locator.check, min_views=locator.solve.min_views,
                                   tolerance_px=locator.grow.add_tolerance_px)
        refit &= ~tried
        owner, positions, table = state.owner, state.positions, state.table.copy()
        if refit.any():
            tried |= refit
            owner, positions = _trim_refit(ctx.dlfc, ctx.st, ctx.view, ctx.views, owner,
                                           positions, np.flatnonzero(refit),
                                           locator.solve.min_views,
                                           locator.grow.add_tolerance_px)
            table.loc[refit, "residual_px"] = np.nan   # grow within add_tolerance_px only
            bad &= ~refit
        if not bad.any() and not refit.any():
            break
        owner = np.where(bad[np.maximum(owner, 0)] & (owner >= 0), -1, owner)
        positions = np.where(bad[:, None], np.nan, positions)
        table.loc[bad, "n_views"] = 0
        state = dataclasses.replace(state, owner=owner, positions=positions, table=table)
        state = grow_particles(ctx, state, locator.grow)
        state = solve_particles(ctx, state, locator.solve)
    return state


def correct_pixel_locking(ctx: FrameContext, state: ParticleState,
                          locator: PerspectiveLocator,
                          calibration) -> tuple[FrameContext, ParticleState]:
    """Stage 5a: correct every centroid for the frame's pixel-locking bias and solve
    again (:mod:`~plenoptrack.locate.pixel_locking`).

    The bias is learned from the kept centroids of the particles whose image travels
    across at least ``solve.locking_min_travel_px`` view pixels
    (:func:`learn_pixel_locking`); when they are too few for ``solve.locking_harmonics``
    and ``solve.locking_from_calibration`` is set, the calibration's pattern from its dot
    cards is used
    (:attr:`~plenoptrack.calibration.Calibration.locking_pattern`) on the images within
    a factor 2 of the dots' size
    (:meth:`~plenoptrack.locate.pixel_locking.LockingPattern.applies_to`), and without
    one the frame is returned unchanged. Each centroid is corrected at its particle's
    travel (one of no particle at the middle of the fitted range). The detections'
    ``s, t`` become the corrected centroids.
    """
    from .pixel_locking import lattice_phase

    pattern, travel = learn_pixel_locking(ctx, state, locator.solve, calibration.grid)
    applies = np.ones(len(ctx.st), dtype=bool)
    if pattern is None and locator.solve.locking_from_calibration:
        # the dots' pattern, on images of about the dots' size only
        pattern = getattr(calibration, "locking_pattern", None)
        if pattern is not None:
            applies = pattern.applies_to(ctx.detections["dark_area"].to_numpy(float))
    if pattern is None or not applies.any():
        return ctx, state
    owner = state.owner
    own_travel = np.where(owner >= 0, travel[np.clip(owner, 0, max(len(travel) - 1, 0))],
                          np.nan)
    bias = pattern.bias(lattice_phase(calibration.grid, ctx.st), own_travel)
    corrected = ctx.st - np.where(applies[:, None], bias, 0.0)
    detections = ctx.detections.assign(s=corrected[:, 0], t=corrected[:, 1])
    ctx = FrameContext.build(ctx.lf, calibration, detections, locator)
    return ctx, solve_particles(ctx, state, locator.solve)


def learn_pixel_locking(ctx: FrameContext, state: ParticleState, settings: SolveSettings,
                        grid):
    """The frame's pixel-locking pattern
    (:class:`~plenoptrack.locate.pixel_locking.LockingPattern`, or None when too few
    centroids show it) from the kept centroids of its particles whose image travels at
    least ``settings.locking_min_travel_px`` view pixels, and every particle's travel
    (P,), view pixels."""
    from .pixel_locking import fit_locking_pattern, lattice_phase

    n = state.n_particles
    travel = image_travel_px(ctx.dlfc, state.positions, state.owner, ctx.views[ctx.view])
    live = state.live(settings.min_views)
    with np.errstate(invalid="ignore"):
        learn = live & (travel >= settings.locking_min_travel_px)
    rows = np.flatnonzero((state.owner >= 0) & learn[np.clip(state.owner, 0, max(n - 1, 0))])
    if len(rows) == 0:
        return None, travel
    pred = _predict_all(ctx.dlfc, np.where(learn[:, None], state.positions, np.nan),
                        ctx.views)[state.owner[rows], ctx.view[rows]]        # (m, 2)
    pattern = fit_locking_pattern(ctx.st[rows] - pred, lattice_phase(grid, pred),
                                  travel[state.owner[rows]],
                                  harmonics=settings.locking_harmonics)
    return pattern, travel


def refine_particles(ctx: FrameContext, state: ParticleState,
                     locator: PerspectiveLocator, *,
                     only: np.ndarray | None = None) -> ParticleState:
    """Stage 5b: refit particles whose images overlap others' to the view pixels.

    Each particle kept by the checks whose image another particle's overlaps in at least
    ``check.refine_min_overlap`` of the valid views is fitted to the pixels around it
    (:func:`~plenoptrack.locate.refine.fit_images`), with its neighbours held; jointly
    with its strongest neighbour when they overlap in at least
    ``check.refine_pair_overlap`` of the views. Image radii start from the particles'
    whole regions. A fit that moves a particle by more than a tenth of the volume depth
    is discarded; a particle whose last fit leaves more than
    ``check.refine_max_model_error`` of the background unexplained (RMS, beyond the
    pixel noise) gets its centroid solution back. ``check.refine_sweeps`` passes over
    the particles.
    A refitted particle's position and its statistical uncertainty are the image fit's
    (standard errors robust to correlated pixel errors within a view,
    :class:`~plenoptrack.locate.refine.ImageFit`), to which :func:`measure_particles`
    applies the same view-correlation scale and DLFC model error as to a centroid
    solve.
    """
    from ._assign import _predict_all
    from .refine import fit_images, overlap_fraction

    settings = locator.check
    table = state.table.copy()
    pos = state.positions.copy()
    n = state.n_particles
    keep = state.live(locator.solve.min_views)
    radius = 0.5 * _member_diameter(ctx.detections, state.owner, n)
    keep &= np.isfinite(radius)
    # the particles that may be refitted (all by default); the others are drawn as held
    # neighbours at their current solution
    may_fit = keep if only is None else keep & np.asarray(only, dtype=bool)
    lf = ctx.lf
    views_uv, view_rc = _fit_views(ctx)
    basis = ctx.dlfc.view_basis(views_uv[:, 0], views_uv[:, 1])
    # The image model's disc starts at (and a neighbour never fitted is drawn with) the
    # particle's shadow; the thresholded regions, larger by their blurred edge, decide
    # which images overlap.
    shadow = 0.5 * _member_diameter(ctx.detections, state.owner, n, shadow=True)
    rc = np.c_[np.where(np.isfinite(shadow) & (shadow > 0), shadow, radius), np.full(n, 0.9)]
    centroid_sigma = table[list(SIGMA_COLUMNS)].to_numpy(float)
    sigma = centroid_sigma.copy()
    model_error = np.full(n, np.nan)   # of each particle's last fit
    max_shift = 0.1 * ctx.volume_depth_mm
    for _sweep in range(settings.refine_sweeps):
        pred = _predict_all(ctx.dlfc, np.where(keep[:, None], pos, np.nan), views_uv)
        r = np.where(keep, radius, np.nan)
        overlap = overlap_fraction(pred, r)
        nearby = overlap_fraction(pred, r, gap_px=4.0) > 0
        fitted_pairs = set()
        for a in np.flatnonzero(may_fit & (overlap.max(axis=1, initial=0.0)
                                           >= settings.refine_min_overlap)):
            b = int(np.argmax(overlap[a]))
            free = ([a, b] if overlap[a, b] >= settings.refine_pair_overlap and may_fit[b]
                    else [a])
            if len(free) == 2:
                if (b, a) in fitted_pairs:   # refitted together with b a moment ago
                    continue
                fitted_pairs.add((a, b))
            held = np.setdiff1d(np.flatnonzero(nearby[free].any(axis=0) & keep), free)
            fitted = fit_images(ctx.dlfc, views_uv, view_rc, lf.data, pos[free], rc[free],
                                pos[held], rc[held], max_depth_shift=max_shift,
                                view_basis=basis, edge=ctx.image_edge)
            if fitted is None or not np.all(np.isfinite(fitted.params)):
                continue
            theta = fitted.params
            pos[free] = theta[:, :3]
            rc[free] = theta[:, 3:]
            sigma[free] = np.where(np.isfinite(fitted.sigma), fitted.sigma, sigma[free])
            model_error[free] = fitted.model_error
    # A particle whose last fit its model could not explain keeps its centroid solution.
    # Earlier fits are left to run their course: a neighbour's refit is what lets the
    # last fit explain the pixels.
    unexplained = model_error > settings.refine_max_model_error
    pos[unexplained] = state.positions[unexplained]
    sigma[unexplained] = centroid_sigma[unexplained]
    changed = keep & np.any(pos != state.positions, axis=1)
    table.loc[changed, list(POS_COLUMNS)] = pos[changed]
    table.loc[changed, list(SIGMA_COLUMNS)] = sigma[changed]
    flags = table["flags"].fillna(0).to_numpy(np.int64).copy()
    fitted = keep & np.isfinite(model_error)
    flags[changed] |= int(TriangulationFlag.REFINED)
    flags[fitted & ~unexplained] &= ~int(TriangulationFlag.UNEXPLAINED)
    flags[keep & unexplained] |= int(TriangulationFlag.UNEXPLAINED)
    table["flags"] = flags
    # what the split stage reads: how well each particle's last fit explained its pixels,
    # and the image radius and contrast it found (an earlier refinement's where this one
    # did not fit the particle)
    for column, value in ((_FIT_ERROR, model_error), (_FIT_RADIUS, rc[:, 0]),
                          (_FIT_CONTRAST, rc[:, 1])):
        before = (table[column].to_numpy(float) if column in table.columns
                  else np.full(n, np.nan))
        table[column] = np.where(fitted, value, before)
    return dataclasses.replace(state, positions=pos, table=table)


def find_hidden_particles(ctx: FrameContext, state: ParticleState,
                          locator: PerspectiveLocator, calibration, *,
                          frame: int = 0) -> tuple[FrameContext, ParticleState, int]:
    """Stage 5d: search again with the located particles' images divided out.

    The model of every located particle's image (its fitted radius and contrast, or its
    regions' shadow and contrast 0.9) is divided out of the light field
    (:func:`~plenoptrack.locate.residual.divide_out_particles`, pixels a located image
    blocks set to the background), and the residual is segmented, clustered, solved and
    checked as the frame was. A particle found there whose images coincide with a located
    particle's (:func:`~plenoptrack.locate.split._coincides`: what the model did not quite
    explain of that image) is dropped, unless it coincides with one located particle alone and
    ``check.hidden_joint`` is on: that particle's image fit may have grown its disc over
    both images, and the two are fitted together (the located one started from its own
    shadow's radius) and kept under the tests of a split (opaque enough, explaining the
    pixels better than the located particle alone by ``check.split_min_gain`` or the
    split's gain bar, images that move apart by a view pixel across the views and stand
    apart in some view or in space, neither one with another particle's image); the
    located particle then takes the pair's fit. Each other one, best seen first, is
    fitted to the frame's own pixels (:func:`~plenoptrack.locate.refine.fit_images`)
    beside the particles located (and those of this search already kept), and kept when
    its image is opaque (``check.split_min_contrast``), explains the pixels better than
    the model without it by ``check.refine_max_model_error**2`` in mean square (the
    split's test, :func:`~plenoptrack.locate.split.split_merged_particles`), and neither
    lies inside a located particle nor overlaps one with images that keep their offset across the
    views (nothing tells those from one elongated image). The kept ones join the frame with
    their regions, their position, sigma and image from the fit (``REFINED``; their size
    too, in :func:`measure_particles`: their regions were cut by the images divided out).
    Nothing is searched when every located particle's last image fit explains its pixels
    to within ``check.refine_max_model_error``, the gain a particle found must bring (one
    whose images merge with a located particle's would have spoilt that one's fit), and
    no more than a few views hold regions no located image covers
    (:func:`_may_hide_particles`). Returns
    the frame context over both sets of regions, the joined state and the number of
    particles added.
    """
    from .refine import fit_images
    from .residual import divide_out_particles

    table = state.table
    n = state.n_particles
    live = state.live(locator.solve.min_views)
    if not live.any():
        return ctx, state, 0
    fit_radius = (table[_FIT_RADIUS].to_numpy(float) if _FIT_RADIUS in table.columns
                  else np.full(n, np.nan))
    shadow = 0.5 * _member_diameter(ctx.detections, state.owner, n, shadow=True)
    radius = np.where(np.isfinite(fit_radius), fit_radius, shadow)
    contrast = (np.nan_to_num(table[_FIT_CONTRAST].to_numpy(float), nan=0.9)
                if _FIT_CONTRAST in table.columns else np.full(n, 0.9))
    live &= np.isfinite(radius) & (radius > 0)
    fit_error = (table[_FIT_ERROR].to_numpy(float) if _FIT_ERROR in table.columns
                 else np.full(n, np.nan))
    views_uv, view_rc = _fit_views(ctx)
    pred = _predict_all(ctx.dlfc, np.where(live[:, None], state.positions, np.nan), views_uv)
    if not _may_hide_particles(ctx, state, live, fit_error, pred, radius, locator):
        return ctx, state, 0
    lf = ctx.lf
    residual = divide_out_particles(lf, view_rc, pred[live], radius[live], contrast[live],
                                    floor=locator.check.hidden_floor,
                                    edge=ctx.image_edge.widths(state.positions[live, 2]))
    found = segment_frame(residual, locator.segment, frame=frame)
    if len(found) == 0:
        return ctx, state, 0
    ctx2 = FrameContext.build(residual, calibration, found, locator)
    state2 = _cluster_and_solve(ctx2, ParticleState.start(ctx2, locator.segment), locator)
    if state2.n_particles == 0:
        return ctx, state, 0
    state2 = check_particles(ctx2, state2, locator)
    new = state2.live(locator.solve.min_views)
    radius2 = 0.5 * _member_diameter(found, state2.owner, state2.n_particles)
    pred2 = _predict_all(ctx.dlfc, state2.positions, views_uv)
    live_spans = ImageSpans(pred[live])
    live_rows = np.flatnonzero(live)
    shared = {}       # candidate -> the one located particle (live index) it coincides with
    for q in np.flatnonzero(new):
        if not np.isfinite(radius2[q]) or _coincides(pred2[[q]], radius2[[q]], pred[live],
                                                     radius[live], live_spans):
            new[q] = False
            if np.isfinite(radius2[q]) and locator.check.hidden_joint:
                one = _coinciding(pred2[[q]], radius2[[q]], pred[live], radius[live],
                                  live_spans)
                if len(one) == 1:
                    shared[q] = int(one[0])
    # A particle found in the residual must explain the frame's own pixels: fitted to
    # them beside the located particles, it must be opaque enough and explain them
    # better than those particles alone by the split's gain
    # (check.refine_max_model_error**2 in mean square).
    positions2 = state2.positions.copy()
    fits = {}                                     # the fit that admitted each one
    companions = {}            # located row -> offset to darkness not taken apart from it
    held_pos, held_rc = state.positions[live], np.c_[radius[live], contrast[live]]
    held_pred, settings = pred[live], locator.check
    held_spans = live_spans
    # best-seen first: a hidden particle cut into two regions by a located one's image
    # can be found twice, and the second is then held beside the first
    order = np.flatnonzero(new)[np.argsort(-state2.table["n_views"].to_numpy(float)[new],
                                           kind="stable")]
    for q in order:
        near = held_spans.meet(held_pred, pred2[q], held_rc[:, 0] + radius2[q] + 4.0)
        start = np.array([[radius2[q], 0.9]])
        fit = fit_images(ctx.dlfc, views_uv, view_rc, lf.data, positions2[[q]], start,
                         held_pos[near], held_rc[near],
                         max_depth_shift=0.1 * ctx.volume_depth_mm,
                         reference=np.array([[*positions2[q], radius2[q], 0.0]]),
                         edge=ctx.image_edge)
        if not _one_image_explains(fit, settings):
            new[q] = False
            continue
        # Where the fit took it into a particle already located (their bodies overlap in
        # space), or beside one with images that keep their offset across the views
        # (nothing tells those two from one elongated image), it was that particle's
        # image the model had not quite explained.
        fitted_pred = _predict_all(ctx.dlfc, fit.params[:, :3], views_uv)
        inside = _inside_bodies(ctx.dlfc, fit.params[0, :4], held_pos, held_rc[:, 0])
        # merged images need their centres within the sum of the radii in some view
        close = held_spans.near(fitted_pred, fit.params[0, 3] + held_rc[:, 0])
        offset = fitted_pred - held_pred[close]                                # (l, V, 2)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)                   # all-NaN rows
            dist = np.nanmedian(np.hypot(offset[..., 0], offset[..., 1]), axis=1)
        merged = ((dist < fit.params[0, 3] + held_rc[close, 0])
                  & (parallax_px(offset) < 1.0))
        if np.any(inside) or np.any(merged):
            # beside a particle, not inside its body (that was its own image), and not
            # taken apart from it: darkness its fit may have taken in
            for jl in np.flatnonzero(close)[merged]:
                if jl < len(live_rows) and not inside[jl]:
                    _note_companion(companions, live_rows[jl],
                                    fit.params[0, :3] - held_pos[jl])
            new[q] = False
            continue
        positions2[q] = fit.params[0, :3]
        fits[q] = _OneImage(fit, 0)
        held_pos = np.vstack([held_pos, fit.params[:, :3]])
        held_rc = np.vstack([held_rc, fit.params[:, 3:]])
        held_pred = np.concatenate([held_pred, fitted_pred])
        held_spans = held_spans.extended(fitted_pred)
    # A candidate that coincides with one located particle can be a particle that one's
    # image fit swallowed (its disc grown over both images): the two are fitted together,
    # the located one started from its own shadow's radius, and the pair is kept when it
    # passes the tests of a split (opaque, explains the pixels better than the located
    # particle alone, two images apart by their parallax).
    joint = {}                                    # located row -> the pair's fit
    gain_bar = split_gain_bar(fit_error, settings)
    order = [q for q in np.argsort(-state2.table["n_views"].to_numpy(float), kind="stable")
             if q in shared]
    for q in order:
        jl = shared[q]
        j = int(live_rows[jl])
        if j in joint:
            continue
        own = (shadow[j] if np.isfinite(shadow[j]) and shadow[j] < held_rc[jl, 0]
               else held_rc[jl, 0])
        others = np.flatnonzero(held_spans.meet(held_pred, pred2[q],
                                                held_rc[:, 0] + radius2[q] + 4.0)
                                | held_spans.meet(held_pred, held_pred[jl],
                                                  held_rc[:, 0] + held_rc[jl, 0] + 4.0))
        others = others[others != jl]
        fit = fit_images(ctx.dlfc, views_uv, view_rc, lf.data,
                         np.vstack([held_pos[jl], positions2[q]]),
                         np.array([[own, held_rc[jl, 1]], [radius2[q], 0.9]]),
                         held_pos[others], held_rc[others],
                         max_depth_shift=ctx.volume_depth_mm,
                         reference=np.array([[*held_pos[jl], *held_rc[jl]]]),
                         edge=ctx.image_edge)
        apart = (fit is not None and np.all(np.isfinite(fit.params))
                 and np.all(np.isfinite(fit.sigma))
                 and fit.params[:, 4].min() >= settings.split_min_contrast
                 and _explains_more(fit, fit.reference_error, settings, gain_bar))
        if apart:
            fitted_pred = _predict_all(ctx.dlfc, fit.params[:, :3], views_uv)
            rest = np.setdiff1d(np.arange(len(held_pos)), [jl])
            apart = (_two_images(ctx.dlfc, fit.params, fitted_pred)
                     and not _coincides(fitted_pred, fit.params[:, 3], held_pred[rest],
                                        held_rc[rest, 0], held_spans.subset(rest)))
        if not apart:
            if not _inside_bodies(ctx.dlfc, np.r_[positions2[q], radius2[q]],
                                  held_pos[[jl]], held_rc[[jl], 0])[0]:
                _note_companion(companions, j, positions2[q] - held_pos[jl])
            continue
        joint[j] = fit
        held_pos[jl], held_rc[jl] = fit.params[0, :3], fit.params[0, 3:]
        held_pred[jl] = fitted_pred[0]
        held_spans.set_rows([jl], fitted_pred[[0]])
        positions2[q] = fit.params[1, :3]
        fits[q] = _OneImage(fit, 1)
        new[q] = True
        held_pos = np.vstack([held_pos, fit.params[1:, :3]])
        held_rc = np.vstack([held_rc, fit.params[1:, 3:]])
        held_pred = np.concatenate([held_pred, fitted_pred[1:]])
        held_spans = held_spans.extended(fitted_pred[1:])
    state = _with_companions(state, companions)
    table = state.table
    if not new.any():
        return ctx, state, 0
    if joint:
        # the located particles refitted with a particle they had swallowed
        table = table.copy()
        positions = state.positions.copy()
        rows = np.array(sorted(joint))
        positions[rows] = [joint[j].params[0, :3] for j in rows]
        table.loc[rows, list(POS_COLUMNS)] = positions[rows]
        table.loc[rows, list(SIGMA_COLUMNS)] = np.array([joint[j].sigma[0] for j in rows])
        table.loc[rows, _FIT_ERROR] = [joint[j].model_error for j in rows]
        table.loc[rows, _FIT_RADIUS] = [joint[j].params[0, 3] for j in rows]
        table.loc[rows, _FIT_CONTRAST] = [joint[j].params[0, 4] for j in rows]
        flags = table.loc[rows, "flags"].fillna(0).to_numpy(np.int64)
        table.loc[rows, "flags"] = ((flags & ~int(TriangulationFlag.UNEXPLAINED))
                                    | int(TriangulationFlag.REFINED))
        state = dataclasses.replace(state, positions=positions, table=table)
    # their position, sigma and image are the fit's (REFINED), as a refined particle's
    added = state2.table.copy()
    rows = np.flatnonzero(new)
    added.loc[rows, list(POS_COLUMNS)] = positions2[rows]
    added.loc[rows, list(SIGMA_COLUMNS)] = np.array([fits[q].sigma for q in rows])
    added.loc[rows, _FIT_ERROR] = [fits[q].model_error for q in rows]
    added.loc[rows, _FIT_RADIUS] = [fits[q].radius for q in rows]
    added.loc[rows, _FIT_CONTRAST] = [fits[q].contrast for q in rows]
    added.loc[rows, "flags"] = (added.loc[rows, "flags"].fillna(0).to_numpy(np.int64)
                                | int(TriangulationFlag.REFINED))
    added[_HIDDEN] = True
    state2 = dataclasses.replace(state2, positions=positions2, table=added)
    # the new particles and their regions join the frame
    index = np.full(state2.n_particles, -1, dtype=np.int64)
    index[new] = n + np.arange(int(new.sum()))
    # The residual's other regions belong to no one. Not even held as merged images:
    # a located particle's image cut by the model divided out would otherwise count
    # toward its size (_size_members).
    owner2 = np.where(state2.owner >= 0, index[np.maximum(state2.owner, 0)], -1)
    detections = pd.concat([ctx.detections, found], ignore_index=True)
    joined = ParticleState(
        owner=np.concatenate([state.owner, owner2]),
        initial=np.vstack([state.initial, state2.initial[new]]),
        positions=np.vstack([state.positions, state2.positions[new]]),
        table=pd.concat([table.assign(**{_HIDDEN: False}), state2.table.loc[new]],
                        ignore_index=True))
    return (FrameContext.build(lf, calibration, detections, locator), joined,
            int(new.sum()))


def _note_companion(companions: dict, row: int, offset: np.ndarray) -> None:
    """Record in ``companions`` (row -> (3,) offset, mm) darkness at ``offset`` from the
    located particle ``row`` that the hidden-particle search found in the residual and
    could not take apart from it, keeping the farthest (laterally) for each particle."""
    row, offset = int(row), np.asarray(offset, dtype=float)
    if not np.all(np.isfinite(offset)):
        return
    known = companions.get(row)
    if known is None or np.hypot(*offset[:2]) > np.hypot(*known[:2]):
        companions[row] = offset


def _with_companions(state: ParticleState, companions: dict) -> ParticleState:
    """``state`` with each particle's companion offset
    (:data:`~plenoptrack.locate._frame._COMPANION` columns) set to the one ``companions`` holds for
    it where that is farther (laterally) than the one an earlier round of the search recorded."""
    if not companions:
        return state
    table = state.table.copy()
    for column in _COMPANION:
        if column not in table.columns:
            table[column] = np.nan
    rows = sorted(companions)
    kept = dict(companions)
    for row, known in zip(rows, table.loc[rows, list(_COMPANION)].to_numpy(float)):
        _note_companion(kept, row, known)          # the farther of the two stays
    table.loc[rows, list(_COMPANION)] = np.array([kept[r] for r in rows])
    return dataclasses.replace(state, table=table)


def _may_hide_particles(ctx: FrameContext, state: ParticleState, live: np.ndarray,
                        fit_error: np.ndarray, pred: np.ndarray, radius: np.ndarray,
                        locator: PerspectiveLocator) -> bool:
    """Whether the frame can hide a particle the search would find: some ``live``
    particle's last image fit leaves more than ``check.refine_max_model_error``
    unexplained (one whose images merge with a located particle's in most views spoils
    that one's fit), or regions no located image covers (``pred`` (P, V, 2), ``radius``
    (P,)) are seen in at least half as many views as a located particle typically is
    (its median ``n_views``, and at least ``solve.min_views``): regions freed when a
    particle built from merged images was dropped are never clustered again, while
    noise specks, seen in a few noisy views, are not worth a search."""
    if not live.any():
        return False                        # nothing to divide out
    if np.any(live & (fit_error > locator.check.refine_max_model_error)):
        return True
    n_views = state.table["n_views"].to_numpy(float)
    enough = max(locator.solve.min_views, 0.5 * float(np.median(n_views[live])))
    return _n_uncovered_views(ctx, state.owner, pred[live], radius[live]) >= enough


def _n_uncovered_views(ctx: FrameContext, owner: np.ndarray, pred: np.ndarray,
                       radius: np.ndarray) -> int:
    """The number of (fit) views holding a region no particle owns (``owner`` < 0,
    unassigned or held back as merged) whose centroid lies inside none of the images
    ``pred`` (P, V, 2) of radius ``radius`` (P,), view pixels, widened by the grow
    tolerance."""
    usable = _usable_views(ctx)
    fit_view = np.cumsum(usable) - 1                 # ctx.views index -> _fit_views index
    free = np.flatnonzero((owner < 0) & usable[ctx.view])
    if len(free) == 0:
        return 0
    if len(pred) == 0:
        return len(np.unique(ctx.view[free]))
    n_v = pred.shape[1]
    reach = radius + ctx.tolerance_px
    q, d, dist = pairs_within(ctx.st[free], fit_view[ctx.view[free]], float(reach.max()),
                              pred.reshape(-1, 2), np.tile(np.arange(n_v), len(pred)))
    covered = np.zeros(len(free), dtype=bool)
    covered[q[dist <= reach[d // n_v]]] = True
    return len(np.unique(ctx.view[free[~covered]]))


def search_hidden_rounds(ctx: FrameContext, state: ParticleState, locator: PerspectiveLocator,
                         calibration, *, frame: int = 0) -> tuple[FrameContext, ParticleState]:
    """Stage 5d repeated: up to ``check.hidden_rounds`` rounds of
    :func:`find_hidden_particles`, each followed by a refit (and split trial) of the
    particles found and of those their images touch; the particles found whose refit
    leaves their pixels unexplained are dropped again. The rounds stop at the first that
    keeps no particle more than the frame had before it (a particle found and dropped
    again in every round would otherwise repeat the same search)."""
    for _round in range(locator.check.hidden_rounds):
        n_live = _n_live(state, locator.solve.min_views)
        ctx, state, n_hidden = find_hidden_particles(ctx, state, locator, calibration,
                                                     frame=frame)
        if not n_hidden:
            break
        # only the particles found and those their images touch are refitted (and
        # tried as splits) again
        n_before = state.n_particles - n_hidden
        near = _near_particles(ctx, state, np.arange(n_before, state.n_particles))
        state = refine_particles(ctx, state, locator, only=near)
        if locator.check.split_merged:
            state = split_merged_particles(ctx, state, locator.check, only=near)
        state = _drop_unexplained_hidden(ctx, state, n_before, n_hidden, locator)
        if _n_live(state, locator.solve.min_views) <= n_live:
            break
    return ctx, state


def _n_live(state: ParticleState, min_views: int) -> int:
    """Particles with a finite position seen in at least ``min_views`` views."""
    return int(state.live(min_views).sum())


def _near_particles(ctx: FrameContext, state: ParticleState, rows: np.ndarray) -> np.ndarray:
    """(P,) bool: the particles ``rows`` and those whose images come within 4 view
    pixels of theirs in some view (radius from the image fit, else the regions)."""
    n = state.n_particles
    radius = (state.table[_FIT_RADIUS].to_numpy(float) if _FIT_RADIUS in state.table.columns
              else np.full(n, np.nan))
    radius = np.where(np.isfinite(radius), radius,
                      0.5 * _member_diameter(ctx.detections, state.owner, n))
    radius = np.nan_to_num(radius, nan=0.0)
    views_uv, _ = _fit_views(ctx)
    pred = _predict_all(ctx.dlfc, state.positions, views_uv)                  # (P, V, 2)
    spans = ImageSpans(pred)
    out = np.zeros(n, dtype=bool)
    out[rows] = True
    for q in rows:
        out |= spans.meet(pred, pred[q], radius + radius[q] + 4.0)
    return out


def _drop_unexplained_hidden(ctx: FrameContext, state: ParticleState, first: int, n: int,
                             locator: PerspectiveLocator) -> ParticleState:
    """The particles ``first .. first + n - 1`` (found by :func:`find_hidden_particles`)
    whose refit beside all the others leaves their pixels unexplained are tested again as
    they were admitted, and dropped unless they pass: fitted to the pixels beside every
    other particle where it now is, the particle must still be opaque enough
    (``check.split_min_contrast``) and explain the pixels better than the model without
    it by ``check.refine_max_model_error**2`` in mean square. What admitted it was a fit
    that explained the pixels; a neighbour's refit since can take that away (the
    particle was the neighbour's image not quite explained), or leave the place
    unexplained for all of them (three particles whose images merge, where the two
    fitted as a pair are off): only in the second case does the particle still earn
    its place. A particle kept this way stays ``UNEXPLAINED``, its position the fit's
    that admitted it."""
    flags = state.table["flags"].fillna(0).to_numpy(np.int64)
    rows = np.arange(first, first + n)
    bad = rows[(flags[rows] & int(TriangulationFlag.UNEXPLAINED)) > 0]
    return _dropped(state, bad[~_still_explains_more(ctx, state, bad, locator)])


def _dropped(state: ParticleState, rows: np.ndarray) -> ParticleState:
    """``state`` without the particles ``rows``: no position, no views, their centroids
    owned by none."""
    if len(rows) == 0:
        return state
    table = state.table.copy()
    table.loc[rows, "n_views"] = 0
    positions = state.positions.copy()
    positions[rows] = np.nan
    owner = np.where(np.isin(state.owner, rows), -1, state.owner)
    return dataclasses.replace(state, owner=owner, positions=positions, table=table)


def drop_duplicate_particles(ctx: FrameContext, state: ParticleState,
                             locator: PerspectiveLocator) -> ParticleState:
    """Stage 5e: drop weakly seen particles that are one neighbour's image found again.

    In a few views the segmentation can cut one particle's image in two (a highlight
    dividing its dark core): the particle keeps one piece in each, and the other pieces,
    a little off its image on every side, can cluster into a particle of their own, near
    the same line of sight and a fraction of a millimetre off in depth. Such a particle is
    seen in few views, its centroids scatter, and its image fit leaves the pixels
    unexplained. A particle is tested here when it is seen in fewer than
    :data:`STRONG_VIEW_FRACTION` of the valid views, carries ``UNEXPLAINED``, and its
    images come within 4 view pixels of exactly one other particle's, one seen in at least
    that fraction, with the two images nearly one (median distance over the views
    below the larger radius); it is dropped unless, fitted to the pixels beside every
    other particle, it still explains them (:func:`_still_explains_more`: the tests a
    particle found in the residual passes). A particle whose images meet several others'
    is not tested: in a crowd the model beside it is less exact, and real particles fail
    the test there (on the accuracy matrix's development seeds at 0.05 particles per
    microlens, testing every such particle with one coinciding neighbour dropped 5 true
    particles, testing those with none 17).
    """
    table = state.table
    flags = table["flags"].fillna(0).to_numpy(np.int64)
    live = state.live(locator.solve.min_views)
    strong = table["n_views"].to_numpy(float) >= STRONG_VIEW_FRACTION * ctx.lf.view_mask.sum()
    candidates = np.flatnonzero(live & ~strong
                                & ((flags & int(TriangulationFlag.UNEXPLAINED)) > 0))
    if len(candidates) == 0:
        return state
    radius = _drawn_radius(ctx, state)
    drawn = live & np.isfinite(radius) & (radius > 0)
    views_uv, _ = _fit_views(ctx)
    pred = _predict_all(ctx.dlfc, np.where(drawn[:, None], state.positions, np.nan), views_uv)
    spans = ImageSpans(pred)
    duplicates = []
    for q in candidates[drawn[candidates]]:
        meet = drawn & spans.meet(pred, pred[q], np.nan_to_num(radius) + radius[q] + 4.0)
        meet[q] = False
        if np.count_nonzero(meet) != 1:
            continue
        p = int(np.flatnonzero(meet)[0])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)            # no common view
            dist = np.nanmedian(np.hypot(*(pred[q] - pred[p]).T))
        if strong[p] and dist < max(radius[q], radius[p]):
            duplicates.append(q)
    duplicates = np.asarray(duplicates, dtype=np.int64)
    return _dropped(state, duplicates[~_still_explains_more(ctx, state, duplicates, locator)])


STRONG_VIEW_FRACTION = 0.25
"""A particle with centroids in at least this fraction of the valid views is seen
strongly: the checks of merged images (``check.max_explained_strong``) and of
duplicates (:func:`drop_duplicate_particles`) treat it as real."""


def _drawn_radius(ctx: FrameContext, state: ParticleState) -> np.ndarray:
    """(P,) image radius (view pixels) each particle is drawn with beside others: its
    last image fit's, else its regions' shadow."""
    radius = state.table[_FIT_RADIUS].to_numpy(float)
    shadow = 0.5 * _member_diameter(ctx.detections, state.owner, state.n_particles,
                                    shadow=True)
    return np.where(np.isfinite(radius), radius, shadow)


def _still_explains_more(ctx: FrameContext, state: ParticleState, rows: np.ndarray,
                         locator: PerspectiveLocator) -> np.ndarray:
    """(len(rows),) bool: particle ``rows[i]``, fitted to the view pixels beside every
    other live particle at its current position and image, is opaque enough, lowers
    the mean-square model error of its pixels by ``check.refine_max_model_error**2``
    against the same model without it and stays out of every other particle's body (the
    admission tests of :func:`find_hidden_particles`)."""
    from .refine import fit_images

    out = np.zeros(len(rows), dtype=bool)
    if len(rows) == 0:
        return out
    settings = locator.check
    table = state.table
    live = state.live(locator.solve.min_views)
    radius = _drawn_radius(ctx, state)
    contrast = np.nan_to_num(table[_FIT_CONTRAST].to_numpy(float), nan=0.9)
    views_uv, view_rc = _fit_views(ctx)
    drawn = live & np.isfinite(radius) & (radius > 0)
    pred = _predict_all(ctx.dlfc, np.where(drawn[:, None], state.positions, np.nan), views_uv)
    spans = ImageSpans(pred)
    for i, q in enumerate(rows):
        xyz, r = state.positions[q], radius[q]
        if not (np.all(np.isfinite(xyz)) and np.isfinite(r) and r > 0):
            continue
        held = drawn & spans.meet(pred, pred[q], np.nan_to_num(radius) + r + 4.0)
        held[q] = False
        fit = fit_images(ctx.dlfc, views_uv, view_rc, ctx.lf.data, xyz[None],
                         np.array([[r, contrast[q]]]), state.positions[held],
                         np.c_[radius[held], contrast[held]],
                         max_depth_shift=0.1 * ctx.volume_depth_mm,
                         reference=np.array([[*xyz, r, 0.0]]), edge=ctx.image_edge)
        # a fit that moved into a neighbour's body explains that neighbour's pixels
        out[i] = (_one_image_explains(fit, settings)
                  and not _inside_bodies(ctx.dlfc, fit.params[0, :4], state.positions[held],
                                         radius[held]).any())
    return out


def _one_image_explains(fit, settings: CheckSettings) -> bool:
    """A one-image fit of a particle found in the residual (``fit_images`` with the
    model without it as reference) is usable, opaque enough
    (``check.split_min_contrast``) and explains its pixels better than the model without
    it by ``check.refine_max_model_error**2`` in mean square."""
    return bool(fit is not None and np.all(np.isfinite(fit.params))
                and fit.params[0, 4] >= settings.split_min_contrast
                and (fit.reference_error ** 2 - fit.model_error ** 2
                     >= settings.refine_max_model_error ** 2))


def _inside_bodies(dlfc, xyzr: np.ndarray, held_xyz: np.ndarray,
                   held_radius_px: np.ndarray) -> np.ndarray:
    """(m,) bool: the particle ``xyzr`` (x, y, z mm and image radius, view pixels) and each
    held particle lie closer in space than the sum of their radii (mm, through the local
    magnification)."""
    both = np.vstack([xyzr[None, :4], np.c_[held_xyz, held_radius_px]])
    radius_mm = both[:, 3] / dlfc.local_magnification(*both[:, :3].T)
    return (np.linalg.norm(held_xyz - xyzr[:3], axis=1) < radius_mm[0] + radius_mm[1:])


@dataclass(frozen=True)
class _OneImage:
    """Image ``k`` of an image fit: its sigma (x, y, z), the fit's model error, its
    radius and contrast."""

    fit: object
    k: int

    @property
    def sigma(self) -> np.ndarray:
        s = self.fit.sigma[self.k]
        return np.where(np.isfinite(s), s, np.nan)

    @property
    def model_error(self) -> float:
        return self.fit.model_error

    @property
    def radius(self) -> float:
        return float(self.fit.params[self.k, 3])

    @property
    def contrast(self) -> float:
        return float(self.fit.params[self.k, 4])


def measure_particles(ctx: FrameContext, state: ParticleState, solve: SolveSettings, *,
                      frame: int, max_model_error: float = math.inf,
                      merge_pieces: bool = False) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Stage 6: the particle table (positions, uncertainties, size and shape in mm).

    Particles with at least ``solve.min_views`` centroids and a finite position are kept
    and renumbered 0..n-1; their uncertainties are the least-squares ones scaled for
    view-correlated errors (with ``solve.excess_scatter``, scatter beyond the frame's
    typical scatter counted as shared by all views; with ``solve.unexplained_error``
    scaled first where the particle's image fit left its pixels unexplained, model error
    above ``max_model_error``,
    :func:`~plenoptrack.locate.uncertainty.with_unexplained_pixels`) plus the DLFC's model
    error (:func:`~plenoptrack.locate.uncertainty.total_sigma`), with
    ``solve.companion_error`` the offset to darkness beside them that the hidden-particle
    search could not take apart from them
    (:func:`~plenoptrack.locate.uncertainty.with_unresolved_companion`) and, with
    ``solve.shape_error``,
    the uncertainty of an irregular body's centre
    (:func:`~plenoptrack.locate.uncertainty.with_shape_error`); size and shape come from their
    member regions (:func:`~plenoptrack.locate._regions._region_shape`) divided by the
    DLFC's local magnification at their position. With ``merge_pieces``, two particles
    that are pieces of one body (bodies overlapping in space, images at one depth:
    :mod:`~plenoptrack.locate.bodies`) are merged into one.

    Returns
    -------
    particles : DataFrame
        Columns :data:`PARTICLE_COLUMNS`.
    detections : DataFrame
        The frame's detections with ``particle`` (row in ``particles``, -1 unused) and
        ``inlier``.
    """
    positions, table, owner = state.positions, state.table, state.owner
    keep = ((table["n_views"].to_numpy() >= solve.min_views)
            & np.all(np.isfinite(positions), axis=1))
    owner = np.where(keep[np.maximum(owner, 0)] & (owner >= 0), owner, -1)
    shape = _region_shape(ctx.detections, _size_members(ctx, state.owner, owner, positions, keep),
                          len(positions))
    mag = ctx.dlfc.local_magnification(*positions[keep].T) if keep.any() else np.zeros(0)
    particles = table.loc[keep, ["x", "y", "z", "sigma_x", "sigma_y", "sigma_z", "n_views",
                                 "confidence", "residual_px", "flags"]].copy()
    sigma = ["sigma_x", "sigma_y", "sigma_z"]
    n_views = particles["n_views"].to_numpy(float)
    # the frame's typical scatter from the centroids of the frame itself: a hidden
    # particle's were measured in the light field with the others divided out
    hidden = (table.loc[keep, _HIDDEN].fillna(False).to_numpy(bool)
              if _HIDDEN in table.columns else np.zeros(len(particles), dtype=bool))
    chi2 = reduced_chi2(particles["residual_px"].to_numpy(float), n_views, typical_of=~hidden)
    split = (particles["flags"].to_numpy(np.int64) & int(TriangulationFlag.SPLIT)) > 0
    # A split's added half owns no centroids; its images lie in the views of its pair's.
    centroid_owner, centroid_uv = _with_pair_centroids(table, owner, ctx.views[ctx.view], keep)
    travel = image_travel_px(ctx.dlfc, positions, centroid_owner, centroid_uv)[keep]
    # A refined particle's sigma is its image fit's, not its centroids'. Its centroids'
    # excess scatter still counts: it marks a disturbance (an unseen neighbour, an image
    # that is not a disc) that the fit's residuals within each view do not reveal. A
    # split particle's is that of the merged pair's centroids (both halves), shown as NaN.
    refined = (particles["flags"].to_numpy(np.int64) & int(TriangulationFlag.REFINED)) > 0
    sigma_stat = particles[sigma].to_numpy(float)
    # The sampling error a refined particle's images share near focus, sized as a centroid
    # solve's: the frame's typical centroid scatter through the particle's own views.
    typical_sigma = None
    if solve.sampling_error and refined.any():
        s0_squared = typical_scatter_px2(particles["residual_px"].to_numpy(float), n_views,
                                         typical_of=~hidden)
        of_refined = np.where(np.isin(centroid_owner, np.flatnonzero(keep)[refined]),
                              centroid_owner, -1)
        geometry = centroid_geometry(ctx.dlfc, positions, of_refined, centroid_uv)[keep]
        typical_sigma = np.sqrt(s0_squared * geometry)
    if solve.unexplained_error and _FIT_ERROR in table.columns:
        sigma_stat = with_unexplained_pixels(
            sigma_stat, table.loc[keep, _FIT_ERROR].to_numpy(float), max_model_error)
    particles[sigma] = total_sigma(sigma_stat, ctx.dlfc,
                                   error_scale=solve.error_scale,
                                   include_model_error=solve.model_error,
                                   chi2=chi2 if solve.excess_scatter else None,
                                   n_views=n_views, z=particles["z"].to_numpy(float),
                                   travel_px=travel if solve.sampling_error else None,
                                   from_centroids=~refined, typical_sigma=typical_sigma)
    if solve.companion_error and _COMPANION[0] in table.columns:
        particles[sigma] = with_unresolved_companion(
            particles[sigma].to_numpy(float),
            table.loc[keep, list(_COMPANION)].to_numpy(float))
    particles["chi2"] = np.where(split, np.nan, chi2)
    particles["travel_px"] = travel
    particles.insert(0, T_COLUMN, frame)
    # the shadow's disc, or with solve.opacity the body's: shadow / sqrt(opacity)
    scale = mag * np.sqrt(_opacity(ctx, shape.loc[keep], particles["z"].to_numpy(float))
                          if solve.opacity else 1.0)
    particles["diameter"] = shape.loc[keep, "diameter_px"].to_numpy() / scale
    particles["major_axis"] = shape.loc[keep, "major_px"].to_numpy() / scale
    particles["minor_axis"] = shape.loc[keep, "minor_px"].to_numpy() / scale
    particles["orientation"] = shape.loc[keep, "orientation"].to_numpy()
    # A split particle's regions are the merged pair's, a hidden one's were cut by the
    # images divided out: their size comes from the image fit, the disc that casts the
    # fitted image's shadow (with solve.opacity its contrast is the body's opacity).
    from_fit = split.copy()
    if _HIDDEN in table.columns:
        radius_fit = table.loc[keep, _FIT_RADIUS].to_numpy(float)
        from_fit |= (table.loc[keep, _HIDDEN].fillna(False).to_numpy(bool)
                     & np.isfinite(radius_fit))
    if from_fit.any():
        rows = table.loc[keep][from_fit]
        fitted = 2.0 * ctx.image_edge.area_radius(rows[_FIT_RADIUS].to_numpy(float),
                                                  rows["z"].to_numpy(float)) / mag[from_fit]
        if not solve.opacity:
            fitted *= np.sqrt(np.clip(rows[_FIT_CONTRAST].to_numpy(float), 0.0, 1.0))
        for column in ("diameter", "major_axis", "minor_axis"):
            particles.loc[particles.index[from_fit], column] = fitted
        particles.loc[particles.index[from_fit], "orientation"] = np.nan
    # Renumber particles 0..n-1 and point the detections at the kept rows.
    new_index = np.full(len(positions), -1, dtype=np.int64)
    new_index[np.flatnonzero(keep)] = np.arange(int(keep.sum()))
    particle_of = np.where(owner >= 0, new_index[np.maximum(owner, 0)], -1)
    particles = particles[list(PARTICLE_COLUMNS)].reset_index(drop=True)
    particles["n_views"] = particles["n_views"].astype(np.int64)
    particles["flags"] = particles["flags"].astype(np.uint8)
    if merge_pieces and len(particles) > 1:
        views_uv, _ = _fit_views(ctx)
        pred = _predict_all(ctx.dlfc, particles[list(POS_COLUMNS)].to_numpy(float), views_uv)
        pairs = one_body_pairs(particles[list(POS_COLUMNS)].to_numpy(float),
                               particles["diameter"].to_numpy(float), pred)
        if len(pairs):
            particles, new_row = merge_bodies(particles, pairs)
            particle_of = np.where(particle_of >= 0, new_row[np.maximum(particle_of, 0)], -1)
    # a large image's centroid bias, and an irregular body's centre (of the whole body
    # where pieces were merged)
    lateral, depth = solve.size_error
    particles[sigma] = with_shape_error(particles[sigma].to_numpy(float),
                                        particles["diameter"].to_numpy(float),
                                        np.hypot((lateral, lateral, depth), solve.shape_error))
    detections = ctx.detections.assign(particle=particle_of, inlier=particle_of >= 0)
    return particles, detections


def _with_pair_centroids(table: pd.DataFrame, owner: np.ndarray, uv: np.ndarray,
                         keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid owners and views with each kept half of a split that owns no centroid
    given a copy of its pair's (``_split_of``): the views its images lie in, for the
    image travel and the centroid geometry of its uncertainty. ``owner`` (M,) and ``uv``
    (M, 2) come back unchanged when there is none."""
    if _SPLIT_OF not in table.columns:
        return owner, uv
    split_of = table[_SPLIT_OF].to_numpy(float)
    counts = np.bincount(owner[owner >= 0], minlength=len(table))
    halves = np.flatnonzero(keep & np.isfinite(split_of) & (counts == 0))
    if len(halves) == 0:
        return owner, uv
    pair = split_of[halves].astype(np.int64)
    mine = [np.flatnonzero(owner == q) for q in pair]
    extra_owner = np.concatenate([np.full(len(m), h) for h, m in zip(halves, mine)])
    extra_uv = np.concatenate([uv[m] for m in mine])
    return np.r_[owner, extra_owner].astype(owner.dtype), np.vstack([uv, extra_uv])


def _opacity(ctx: FrameContext, shape: pd.DataFrame, z: np.ndarray) -> np.ndarray:
    """Opacity of each particle from its images' median peak darkness and shadow radius
    (:func:`~plenoptrack.locate.opacity.opacity`) against the calibration's edge blur at
    its depth; 1 where it cannot be found (no edge blur in the calibration, no peak)."""
    if ctx.edge_blur is None or len(shape) == 0:
        return np.ones(len(shape))
    c = opacity(shape["peak"].to_numpy(float), 0.5 * shape["diameter_px"].to_numpy(float),
                blur_at(ctx.edge_blur, z))
    return np.where(np.isfinite(c), c, 1.0)


def _size_members(ctx: FrameContext, held_owner: np.ndarray, owner: np.ndarray,
                  positions: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Owners for measuring size: each kept particle's regions, plus the regions held back
    as merged images (owner ``_MERGED`` in ``held_owner``) in which it is the only kept
    particle predicted.

    An ordinary single image can exceed ``max_area_ratio`` times the median whole
    region (a larger particle, or one further from focus); it is held back and the
    particle would be left with its other regions. A held-back region that exactly one
    located particle accounts for is that particle's whole image, so its size counts.
    """
    held = np.flatnonzero(held_owner == _MERGED)
    if len(held) == 0 or not keep.any():
        return owner
    kept = np.flatnonzero(keep)
    pred = _predict_all(ctx.dlfc, positions[kept], ctx.views)              # (K, V, 2)
    n_k, n_v = pred.shape[:2]
    q, d, _ = pairs_within(ctx.st[held], ctx.view[held], ctx.radius_px[held],
                           pred.reshape(-1, 2), np.tile(np.arange(n_v), n_k))
    alone = np.bincount(q, minlength=len(held))[q] == 1
    out = owner.copy()
    out[held[q[alone]]] = kept[d[alone] // n_v]
    return out


def _inconsistent(ctx: FrameContext, state: ParticleState, settings: CheckSettings, *,
                  min_views: int, tolerance_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(P,) masks of the particles that fail the consistency checks, and of those to
    refit on their best centroids instead.

    A particle fails when it has fewer than ``min_views`` centroids; when the views of
    its centroids span less than ``min_aperture_spread`` of the aperture (RMS distance
    from their mean ``(u, v)`` against that of all valid views); when its RMS residual
    exceeds ``max_residual_ratio`` times the median over all particles (and
    ``tolerance_px``); or when, in more than ``max_explained`` of its views, two other
    particles are predicted on its centroid (a particle made of merged images of two
    others), judged from the particle seen in the fewest views up, each one dropped no
    longer counting for the rest (:func:`~plenoptrack.locate._assign._explained_away`).
    Particles seen in at least a quarter of the valid views whose only fault is
    the residual are to be refitted.
    """
    positions, table, owner, view, views = (state.positions, state.table, state.owner,
                                            ctx.view, ctx.views)
    n_v = table["n_views"].to_numpy()
    ok = np.all(np.isfinite(positions), axis=1) & (n_v > 0)
    bad = ok & (n_v < min_views)
    mine = owner >= 0
    own = owner[mine]
    cnt = np.maximum(np.bincount(own, minlength=len(positions)), 1)
    uu = views[view[mine], 0]
    vv = views[view[mine], 1]
    mu = np.bincount(own, uu, minlength=len(positions)) / cnt
    mv = np.bincount(own, vv, minlength=len(positions)) / cnt
    spread = np.sqrt(np.bincount(own, (uu - mu[own]) ** 2 + (vv - mv[own]) ** 2,
                                 minlength=len(positions)) / cnt)
    lf = ctx.lf
    vg, ug = np.meshgrid(lf.v, lf.u, indexing="ij")
    ua, va = ug[lf.view_mask], vg[lf.view_mask]
    full = np.sqrt(np.mean((ua - ua.mean()) ** 2 + (va - va.mean()) ** 2))
    bad |= ok & (spread < settings.min_aperture_spread * full)
    res = table["residual_px"].to_numpy()
    typical = np.nanmedian(res[ok]) if ok.any() else np.nan
    res_bad = ok & (res > max(settings.max_residual_ratio * typical, tolerance_px))
    pred = _predict_all(ctx.dlfc, positions, views)
    strong = n_v >= STRONG_VIEW_FRACTION * lf.view_mask.sum()
    bad |= _explained_away(pred, ctx.st, view, owner, ctx.radius_px, ok & ~bad & ~res_bad, ok,
                           np.where(strong, settings.max_explained_strong,
                                    settings.max_explained), n_v)
    return bad | res_bad, res_bad & ~bad & strong


def _empty_particles() -> pd.DataFrame:
    cols = {c: pd.Series(dtype=float) for c in PARTICLE_COLUMNS}
    cols[T_COLUMN] = pd.Series(dtype=np.int64)
    cols["n_views"] = pd.Series(dtype=np.int64)
    cols["flags"] = pd.Series(dtype=np.uint8)
    return pd.DataFrame(cols)


def _initial_positions(clusters: pd.DataFrame, camera) -> pd.DataFrame:
    """Thin-lens start for each cluster from its plane and mean projected position.

    A cluster accepted at plane ``alpha`` with mean position ``X'`` (mm, camera frame,
    on that plane) is imaged at ``d = alpha s_i``; its object lies at ``s_o + z`` with
    ``z`` from the thin-lens equation, laterally at ``x = X' (s_o + z) / d`` (world
    frame: the camera-frame inversion cancels the lens's).
    """
    alpha = clusters["alpha"].to_numpy(float)
    z = camera.depth_for_alpha(alpha)
    d = alpha * camera.image_distance_mm
    scale = (camera.object_distance_mm + z) / d
    return pd.DataFrame({"x": clusters["plane_x_mm"].to_numpy(float) * scale,
                         "y": clusters["plane_y_mm"].to_numpy(float) * scale,
                         "z": z}, index=clusters["cluster"].to_numpy())


class _StageClock:
    """Wall-clock seconds per named stage: ``with clock("segment"): ...``."""

    def __init__(self) -> None:
        self.seconds = {"decode": 0.0, "segment": 0.0, "cluster": 0.0, "triangulate": 0.0,
                        "checks": 0.0, "refine": 0.0}

    @contextlib.contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - t0


def _finish_empty(detections: pd.DataFrame, frame: int, clock=None,
                  coverage: float = math.nan) -> LocateResult:
    warnings.warn(f"frame {frame}: no particles found", NoParticlesWarning, stacklevel=3)
    detections = detections.assign(particle=np.full(len(detections), -1, dtype=np.int64),
                                   inlier=np.zeros(len(detections), dtype=bool))
    return LocateResult(particles=_empty_particles(), detections=detections,
                        stage_seconds=dict(clock or {}), image_coverage=coverage)
