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
   (:func:`search_hidden_rounds`, :mod:`~plenoptrack.locate.hidden`); last
   (``check.drop_duplicates``), drop weakly seen particles that are one neighbour's
   image found again (:func:`~plenoptrack.locate.hidden.drop_duplicate_particles`);
   finally solve the particles whose images are much larger than the calibration's dots
   again without the views the aperture rim cuts (:func:`solve_large_images`);
6. :func:`measure_particles` -- uncertainties (least-squares errors scaled for
   view-correlated centroid errors, plus the DLFC's model error;
   :mod:`~plenoptrack.locate.uncertainty`), in-plane size and shape from the member
   regions, converted to mm with the local magnification of the calibration.

The frame's fixed data (detections, views, geometry) is a :class:`FrameContext`; what the
stages change is a :class:`ParticleState`: which detection belongs to which particle and
each particle's solution (both defined in :mod:`plenoptrack.locate.frame`). Every
stage takes its own settings section of
:class:`~plenoptrack.locate.settings.PerspectiveLocator`.

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
from ..errors import CrowdedFrameWarning, NoParticlesWarning, SettingsError
from ..io import warn_exposure
from ..lightfield.decode import LightField, decode
from ._assign import (_MERGED, _add_centroids, _explained_away, _merge_duplicates,
                      _predict_all, _release_unclaimed, _trim_refit)
from ._nearby import ImageSpans, pairs_within
from ._order import unique_rows
from .frame import (_CENTROID_SOLUTION, _COMPANION, _FIT_CONTRAST, _FIT_ERROR, _FIT_RADIUS,
                     _HIDDEN, _SPLIT_OF, MIN_VIEW_FRACTION, FrameContext, ParticleState,
                     SolveMemo, _fit_views, _member_diameter, _split)
from ._regions import _region_shape, _split_pairs
from .bodies import merge_bodies, one_body_pairs
from .crowding import CROWDED_COVERAGE, image_coverage
from .opacity import blur_at, opacity
from .cluster import cluster_detections
from .hidden import (STRONG_VIEW_FRACTION, EarlierRounds, _drop_unexplained_hidden,
                     drop_duplicate_particles, search_residual)
from .segment import segment_views
from .split import keep_centroids_on_images, split_merged_particles
from .settings import (CheckSettings, ClusterSettings, GrowSettings, PerspectiveLocator,
                       SegmentSettings, SolveSettings)
from .triangulate import TriangulationFlag, triangulate_clusters
from .uncertainty import (centroid_geometry, image_travel_px, reduced_chi2, total_sigma,
                          typical_scatter_px2, with_offset_range, with_shape_error,
                          with_unexplained_pixels)

__all__ = ["PerspectiveLocator", "PARTICLE_COLUMNS", "locate_frame", "LocateResult",
           "FrameContext", "ParticleState", "segment_frame", "cluster_unassigned",
           "solve_particles", "grow_particles", "check_particles", "refine_particles",
           "solve_large_images", "measure_particles"]

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

    Raises
    ------
    SettingsError
        ``solve.locking_from_calibration`` is set and the calibration holds no
        pixel-locking pattern.
    """
    locator = PerspectiveLocator() if locator is None else locator
    if (locator.solve.locking_from_calibration
            and getattr(calibration, "locking_pattern", None) is None):
        raise SettingsError("solve.locking_from_calibration is set but the calibration holds "
                            "no pixel-locking pattern; calibrate again with plenoptrack "
                            "calibrate (it records the dots' pattern) or leave the setting off")
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
        state = solve_large_images(ctx, state, locator.solve)
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
    if "whole" not in detections.columns:          # no core splitting: every region whole
        detections = detections.assign(whole=True)
    if len(detections) and settings.split_pairs:
        detections = _split_pairs(detections, settings.max_area_ratio,
                                  settings.merged_elongation)
    if "split_pair" not in detections.columns:
        detections = detections.assign(split_pair=False)
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


def _triangulate_owned(ctx: FrameContext, solving: np.ndarray, start: np.ndarray,
                       used: np.ndarray, settings: SolveSettings):
    """Triangulate the particles ``used`` from the detections ``solving`` assigns them
    (particle row per detection, -1 none), starting from ``start`` (len(used), 3) mm,
    with the solve settings' outlier rejection."""
    initial = pd.DataFrame(start, index=used, columns=list(POS_COLUMNS))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        return triangulate_clusters(ctx.dlfc, ctx.detections.assign(_owner=solving), initial,
                                    cluster_column="_owner", n_possible_views=ctx.n_possible,
                                    volume_depth_mm=ctx.volume_depth_mm,
                                    reject_k=settings.reject_k,
                                    min_views=min(4, settings.min_views), solver=settings.solver)


def solve_particles(ctx: FrameContext, state: ParticleState,
                    settings: SolveSettings) -> ParticleState:
    """Stage 3: solve every particle that owns centroids, with outlier rejection.

    Centroids rejected as outliers are released (owner -1); particles without centroids
    get NaN positions and ``n_views`` 0. A particle whose centroids are those of the
    previous solve keeps that solve's result (:class:`~plenoptrack.locate.frame.SolveMemo`).
    """
    owner = state.owner
    n = state.n_particles
    memo = state.solved
    redo = (np.ones(n, dtype=bool) if memo is None
            else memo.to_solve(ctx, settings, owner, n))
    mine = owner >= 0
    solving = np.where(mine & redo[np.maximum(owner, 0)], owner, -1)
    used = np.unique(solving[solving >= 0])
    tri = _triangulate_owned(ctx, solving, state.initial[used], used, settings)
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


_SOLVE_FLAGS = int(TriangulationFlag.CONVERGED | TriangulationFlag.TOO_FEW_VIEWS
                   | TriangulationFlag.OUTLIERS_REMOVED | TriangulationFlag.AT_VOLUME_EDGE
                   | TriangulationFlag.SINGULAR)
"""The flags a centroid solve sets (the others come from later stages and are kept)."""


def solve_large_images(ctx: FrameContext, state: ParticleState,
                       settings: SolveSettings) -> ParticleState:
    """Stage 5e: solve again, without the views the aperture rim cuts, the particles
    solved from centroids whose images are more than twice the calibration's dots.

    The DLFC relates the centroids of its dot images to positions. In a view that the
    rim of the aperture cuts (valid share below ``settings.rim_min_valid``) each sample
    sees an off-centre part of its sub-aperture, and there the centroid of an image much
    larger than a dot leaves the DLFC's relation by up to about 0.1 view pixel, away from
    the centre of the aperture on one side of focus and towards it on the other, so the
    depth comes out nearer the focal plane (measured on simulated spheres; how the cut
    moves a large image differently from a dot is not pinned down; docs: uncertainty).
    Particles refitted to
    the view pixels leave those views out in their image fits
    (:meth:`FrameContext.fit_images`); this stage does the same for the others. Their
    centroids in those views stay theirs (for size and shape); a particle left with
    fewer than ``settings.min_views`` centroids in the other views keeps its solution.
    """
    n = state.n_particles
    if n == 0 or not math.isfinite(ctx.large_image_px) or settings.rim_min_valid <= 0:
        return state
    table, owner = state.table, state.owner
    flags = table["flags"].fillna(0).to_numpy(np.int64)
    from_fit = (flags & int(TriangulationFlag.REFINED | TriangulationFlag.SPLIT)) > 0
    if _HIDDEN in table.columns:
        from_fit |= table[_HIDDEN].fillna(False).to_numpy(bool)
    diameter = _member_diameter(ctx.detections, owner, n, shadow=True)
    pick = ((diameter > ctx.large_image_px) & ~from_fit
            & np.all(np.isfinite(state.positions), axis=1))
    mine = owner >= 0
    solving = np.where(mine & pick[np.maximum(owner, 0)] & ~ctx.rim_detections(), owner, -1)
    pick &= np.bincount(solving[solving >= 0], minlength=n) >= settings.min_views
    solving = np.where((solving >= 0) & pick[np.maximum(solving, 0)], solving, -1)
    if not pick.any():
        return state
    used = np.flatnonzero(pick)
    tri = _triangulate_owned(ctx, solving, state.positions[used], used, settings)
    rows = tri.to_frame().set_index("cluster").reindex(used)
    rows = rows[np.all(np.isfinite(rows[list(POS_COLUMNS)].to_numpy(float)), axis=1)]
    used = rows.index.to_numpy()
    table = table.copy()
    columns = [c for c in rows.columns if c in table.columns and c != "flags"]
    table.loc[used, columns] = rows[columns].to_numpy()
    table.loc[used, "flags"] = ((flags[used] & ~_SOLVE_FLAGS)
                                | rows["flags"].to_numpy(np.int64))
    # the rejected centroids are released as a solve releases them
    new_owner = np.where((solving >= 0) & ~tri.inliers, -1, owner)
    return dataclasses.replace(state, owner=new_owner,
                               positions=table[list(POS_COLUMNS)].to_numpy(float), table=table,
                               solved=None)


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
    is discarded, unless no neighbour is held beside it and a fit with the whole volume
    depth open explains the pixels (model error at most
    ``check.refine_max_model_error``): the centroids of two images merged on nearly one
    line of sight put a particle between the two, which a joint fit with the other,
    seen alone in a few views, takes to its own depth; it keeps only the centroids on
    its new image (:func:`~plenoptrack.locate.split.keep_centroids_on_images`). A
    particle whose last fit leaves more than
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
    from .refine import overlap_fraction

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
    put_back = set()       # moved further than max_shift by a fit that explains them
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
            fitted = ctx.fit_images((views_uv, view_rc), pos[free], rc[free], pos[held],
                                    rc[held], max_depth_shift=max_shift, view_basis=basis)
            if fitted is None and len(held) == 0:
                # It ran off in depth (or had too few views). Alone in its patch, one
                # that goes further counts where it explains the pixels: a particle
                # whose centroids merged two images on nearly one line of sight, fitted
                # with the other. Beside other images a fit given the whole depth can
                # explain pixels by taking over theirs (at 0.1 particles per microlens
                # it cost recall).
                far = ctx.fit_images((views_uv, view_rc), pos[free], rc[free], pos[held],
                                     rc[held], max_depth_shift=ctx.volume_depth_mm,
                                     view_basis=basis)
                if far is not None and far.model_error <= settings.refine_max_model_error:
                    fitted = far
                    put_back.update(np.asarray(free)[np.abs(far.params[:, 2] - pos[free, 2])
                                                     > max_shift].tolist())
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
    # the centroid solution of each particle moved for the first time, to be compared
    # with its fit (measure_particles)
    before = (table[list(_CENTROID_SOLUTION)].to_numpy(float, copy=True)
              if _CENTROID_SOLUTION[0] in table.columns else np.full((n, 3), np.nan))
    first = changed & np.isnan(before[:, 0])
    before[first] = state.positions[first]
    table[list(_CENTROID_SOLUTION)] = before
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
    # a particle put back by its image keeps only the centroids on that image (the
    # others were regions merged with another's), as in the split stage
    owner, table = keep_centroids_on_images(
        ctx, state.owner, table, sorted(m for m in put_back if not unexplained[m]), pos)
    return dataclasses.replace(state, owner=owner, positions=pos, table=table)


def find_hidden_particles(ctx: FrameContext, state: ParticleState,
                          locator: PerspectiveLocator, calibration, *,
                          frame: int = 0, elongated: bool = True,
                          earlier: EarlierRounds | None = None
                          ) -> tuple[FrameContext, ParticleState, int]:
    """Stage 5d: search again with the located particles' images divided out, the
    residual segmented, clustered, solved and checked as the frame was
    (:func:`~plenoptrack.locate.hidden.search_residual`; ``elongated``: elongated
    particles divided out with their regions' ellipse too; ``earlier``: what the
    frame's earlier rounds did, :class:`~plenoptrack.locate.hidden.EarlierRounds`).
    Returns the frame context over both sets of regions, the joined state and the
    number of particles added."""
    return search_residual(ctx, state, locator, calibration,
                           lambda residual: _locate_again(residual, calibration, locator,
                                                          frame=frame),
                           elongated=elongated, earlier=earlier)


def _locate_again(lf: LightField, calibration, locator: PerspectiveLocator, *,
                  frame: int = 0) -> tuple[pd.DataFrame, FrameContext, ParticleState] | None:
    """Stages 1-5 up to the consistency checks on another light field of the frame (the
    hidden-particle search's residual): its detections, context and checked state; None
    when it holds no regions or no particle."""
    found = segment_frame(lf, locator.segment, frame=frame)
    if len(found) == 0:
        return None
    ctx = FrameContext.build(lf, calibration, found, locator)
    state = _cluster_and_solve(ctx, ParticleState.start(ctx, locator.segment), locator)
    if state.n_particles == 0:
        return None
    return found, ctx, check_particles(ctx, state, locator)


def search_hidden_rounds(ctx: FrameContext, state: ParticleState, locator: PerspectiveLocator,
                         calibration, *, frame: int = 0) -> tuple[FrameContext, ParticleState]:
    """Stage 5d repeated: up to ``check.hidden_rounds`` rounds of
    :func:`find_hidden_particles`, each followed by a refit (and split trial) of the
    particles found and of those their images touch; the particles found whose refit
    leaves their pixels unexplained are dropped again. The rounds stop at the first that
    keeps no particle more than the frame had before it (a particle found and dropped
    again in every round would otherwise repeat the same search). A candidate an
    earlier round fitted and turned down is not fitted again unless its images come
    near a particle the round before found, refitted or dropped (:func:`_changed_images`,
    :class:`~plenoptrack.locate.hidden.EarlierRounds`). Elongated particles are
    divided out with their regions' ellipse as well as their disc, so that the rest of a
    thin body is not found again piece by piece, round after round (a head measured
    together with its stem has its disc on the head already:
    :func:`~plenoptrack.locate.split.split_merged_particles` fits an elongated image
    from its ends)."""
    earlier = EarlierRounds()
    for _round in range(locator.check.hidden_rounds):
        n_live = _n_live(state, locator.solve.min_views)
        ctx, state, n_hidden = find_hidden_particles(ctx, state, locator, calibration,
                                                     frame=frame, earlier=earlier)
        if not n_hidden:
            break
        # only the particles found and those their images touch are refitted (and
        # tried as splits) again
        n_before = state.n_particles - n_hidden
        near = _near_particles(ctx, state, np.arange(n_before, state.n_particles))
        found = state
        state = refine_particles(ctx, state, locator, only=near)
        if locator.check.split_merged:
            state = split_merged_particles(ctx, state, locator.check, only=near)
        state = _drop_unexplained_hidden(ctx, state, n_before, n_hidden, locator)
        if _n_live(state, locator.solve.min_views) <= n_live:
            break
        earlier.forget_near(ctx.dlfc, _fit_views(ctx)[0],
                            *_changed_images(ctx, found, state, near))
    return ctx, state


def _changed_images(ctx: FrameContext, found: ParticleState, state: ParticleState,
                    near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions (F, 3), mm, and image radii (F,), view pixels, of what a round of the
    hidden search changed, from ``found`` (the state with the round's particles just
    found) to ``state`` (after their refit, split trials and drops): the particles
    ``near`` (bool over the rows of ``found``) and every other one whose position,
    image fit or regions changed (a split refits the neighbours of the particles it
    splits), where they were and where they are, and the particles the split trials
    added; particles without a position left out."""
    n = found.n_particles
    changed = np.asarray(near, dtype=bool).copy()
    changed |= ~_same_rows(found.positions, state.positions[:n])
    for column in (_FIT_RADIUS, _FIT_CONTRAST):
        if column in state.table.columns:
            before = (found.table[column].to_numpy(float) if column in found.table.columns
                      else np.full(n, np.nan))
            changed |= ~_same_rows(before[:, None], state.table[column].to_numpy(float)[:n, None])
    moved = found.owner != state.owner
    owners = np.concatenate([found.owner[moved], state.owner[moved]])
    changed[owners[(owners >= 0) & (owners < n)]] = True
    rows = np.flatnonzero(changed)
    added = np.arange(n, state.n_particles)
    xyz = np.vstack([found.positions[rows], state.positions[rows], state.positions[added]])
    radius = np.concatenate([_image_radius(ctx, found)[rows],
                             _image_radius(ctx, state)[np.r_[rows, added]]])
    keep = np.all(np.isfinite(xyz), axis=1) & np.isfinite(radius)
    return xyz[keep], radius[keep]


def _same_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) bool: rows of ``a`` and ``b`` (n, k) equal value for value, NaN equal to NaN."""
    return np.all((a == b) | (np.isnan(a) & np.isnan(b)), axis=1)


def _image_radius(ctx: FrameContext, state: ParticleState) -> np.ndarray:
    """(P,) each particle's image radius, view pixels: its image fit's, else half its
    regions' diameter; NaN for neither."""
    n = state.n_particles
    radius = (state.table[_FIT_RADIUS].to_numpy(float) if _FIT_RADIUS in state.table.columns
              else np.full(n, np.nan))
    return np.where(np.isfinite(radius), radius,
                    0.5 * _member_diameter(ctx.detections, state.owner, n))


def _n_live(state: ParticleState, min_views: int) -> int:
    """Particles with a finite position seen in at least ``min_views`` views."""
    return int(state.live(min_views).sum())


def _near_particles(ctx: FrameContext, state: ParticleState, rows: np.ndarray) -> np.ndarray:
    """(P,) bool: the particles ``rows`` and those whose images come within 4 view
    pixels of theirs in some view (radius from the image fit, else the regions)."""
    n = state.n_particles
    radius = np.nan_to_num(_image_radius(ctx, state), nan=0.0)
    views_uv, _ = _fit_views(ctx)
    pred = _predict_all(ctx.dlfc, state.positions, views_uv)                  # (P, V, 2)
    spans = ImageSpans(pred)
    out = np.zeros(n, dtype=bool)
    out[rows] = True
    for q in rows:
        out |= spans.meet(pred, pred[q], radius + radius[q] + 4.0)
    return out


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
    (:func:`~plenoptrack.locate.uncertainty.with_offset_range`), with
    ``solve.refit_error`` the disagreement between a refitted particle's image fit and its
    centroid solution (the same function) and, with ``solve.shape_error``,
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
        # the particle may have taken in up to half of the offset to the darkness
        particles[sigma] = with_offset_range(
            particles[sigma].to_numpy(float),
            0.5 * table.loc[keep, list(_COMPANION)].to_numpy(float))
    if solve.refit_error and _CENTROID_SOLUTION[0] in table.columns:
        # the truth anywhere between the image fit and the centroid solution before it
        disagreement = (particles[list(POS_COLUMNS)].to_numpy(float)
                        - table.loc[keep, list(_CENTROID_SOLUTION)].to_numpy(float))
        disagreement[~refined | split] = np.nan
        particles[sigma] = with_offset_range(particles[sigma].to_numpy(float), disagreement)
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
    longer counting for the rest (:func:`~plenoptrack.locate._assign._explained_away`);
    or when it is seen in fewer than :data:`~plenoptrack.locate.hidden.STRONG_VIEW_FRACTION`
    of the valid views, only through halves of regions split as pairs, in the same views
    as another such particle (:func:`_pieces_of_one_region`).
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
    bad |= _pieces_of_one_region(ctx, owner, ok & ~strong)
    bad |= _explained_away(pred, ctx.st, view, owner, ctx.radius_px, ok & ~bad & ~res_bad, ok,
                           np.where(strong, settings.max_explained_strong,
                                    settings.max_explained), n_v)
    return bad | res_bad, res_bad & ~bad & strong


def _pieces_of_one_region(ctx: FrameContext, owner: np.ndarray, weak: np.ndarray) -> np.ndarray:
    """(P,) bool: the ``weak`` particles made only of halves of regions split as pairs
    (:func:`~plenoptrack.locate._regions._split_pairs`) that come two or more to the same
    views: one region cut in two in those views, not particles of their own.

    The halves are placed along the region's axis where two equal images would lie, not
    measured. A pin's head and stem, merged into one region in most views and cut in two
    in a few, gave two particles made of the halves of those few views, one of them 2.6
    mm off in depth, which then took the pin's own particle for their merged image.
    Every weakly seen particle made only of halves was dropped at first: in crowded
    frames (0.1 particles per microlens, development seeds, ideal optics) that cost 0.04
    of recall summed over the three seeds, while a real particle seen only through
    halves is seldom seen in exactly the views of another."""
    out = np.zeros(len(weak), dtype=bool)
    mine = np.flatnonzero(owner >= 0)
    halves = _split(ctx.detections)[mine]
    n_halves = np.bincount(owner[mine], halves.astype(float), minlength=len(weak))
    n_all = np.bincount(owner[mine], minlength=len(weak))
    rows = np.flatnonzero(weak & (n_all > 0) & (n_halves == n_all))
    if len(rows) < 2:
        return out
    by_views: dict[tuple, list] = {}
    for r in rows:
        by_views.setdefault(tuple(np.sort(ctx.view[mine[owner[mine] == r]])), []).append(r)
    for group in by_views.values():
        if len(group) > 1:
            out[group] = True
    return out


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
