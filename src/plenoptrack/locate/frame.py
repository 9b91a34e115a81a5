"""What the stages of the perspective-shift locator share for one frame.

The frame's fixed data (decoded light field, detections, views, projection geometry) is a
:class:`FrameContext`; what the stages change is a :class:`ParticleState`: which
detection belongs to which particle and each particle's solution
(:mod:`~plenoptrack.locate.perspective` runs the stages over them). The state's table
carries, besides the columns of the particles table, the working columns named here
(``_FIT_ERROR`` and the like) that one stage leaves for the next.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..lightfield.decode import LightField
from ._assign import _MERGED
from ._order import unique_rows
from ._regions import _single_image_area
from .cluster import ProjectionGeometry, plane_alphas
from .refine import ImageEdge
from .settings import PerspectiveLocator, SegmentSettings, SolveSettings

__all__ = ["FrameContext", "ParticleState", "SolveMemo", "MIN_VIEW_FRACTION"]


@dataclass(frozen=True)
class FrameContext:
    """What every stage reads about one frame and never changes.

    Attributes
    ----------
    lf : LightField
        The decoded frame.
    dlfc : DLFC
        The calibration's Direct Light Field Calibration.
    camera : CameraSpec
        The calibration's nominal camera.
    detections : DataFrame
        The segmented regions of every view
        (:func:`~plenoptrack.locate.perspective.segment_frame`), M rows.
    st : (M, 2) float ndarray
        Their centroids ``(s, t)``, view pixels.
    view : (M,) int ndarray
        Index of each detection's view into ``views``.
    views : (V, 2) float ndarray
        ``(u, v)`` of the views that have detections.
    radius_px : (M,) float ndarray
        Half the major axis of each region plus the grow tolerance, view pixels: a
        particle predicted within it is seen in the region.
    round_ : (M,) bool ndarray
        Regions round enough to be one particle's image near the camera, or halves of a
        split pair.
    geometry : ProjectionGeometry
        Conversion of view coordinates to the aperture and the microlens plane.
    alphas : (n_planes,) float ndarray
        Refocus planes of the clustering.
    n_possible : int
        Valid views of the light field.
    volume_depth_mm : float
        Depth of the clustered volume, mm.
    merge_px : float
        Distance under which two particles' predictions coincide, view pixels.
    tolerance_px : float
        How far a centroid may lie from a particle's prediction and still be its image
        (``grow.add_tolerance_px``), view pixels.
    edge_blur : (K, 2) float ndarray or None
        The views' edge blur per depth ``(z mm, sigma px)`` the calibration measured on
        its dot cards (:attr:`~plenoptrack.calibration.Calibration.edge_blur_by_depth`);
        None when it has none.
    max_area_ratio : float
        A region larger than this times one particle's image is a merged image
        (``segment.max_area_ratio``).
    large_image_px : float
        Equivalent shadow diameter (view pixels) above which an image is left out of
        position solves and image fits in the views the aperture rim cuts: twice the
        calibration's dot images (``solve.rim_min_valid``); inf when the calibration did
        not record its dots' size.
    rim_min_valid : float
        ``solve.rim_min_valid``: views with a smaller share of valid samples are cut by
        the aperture rim.
    """

    lf: LightField
    dlfc: object
    camera: object
    detections: pd.DataFrame
    st: np.ndarray
    view: np.ndarray
    views: np.ndarray
    radius_px: np.ndarray
    round_: np.ndarray
    geometry: ProjectionGeometry
    alphas: np.ndarray
    n_possible: int
    volume_depth_mm: float
    merge_px: float
    tolerance_px: float
    edge_blur: np.ndarray | None = None
    max_area_ratio: float = math.inf
    large_image_px: float = math.inf
    rim_min_valid: float = 0.0

    def rim_cut(self, view_rc: np.ndarray) -> np.ndarray:
        """(V,) bool: the views (``(v, u)`` indices into the light field) that the
        aperture rim cuts (valid share below :attr:`rim_min_valid`)."""
        view_rc = np.asarray(view_rc, dtype=np.int64).reshape(-1, 2)
        return self.lf.valid_fraction[view_rc[:, 0], view_rc[:, 1]] < self.rim_min_valid

    def rim_detections(self) -> np.ndarray:
        """(M,) bool: the detections in views the aperture rim cuts."""
        rc = np.c_[np.searchsorted(self.lf.v, self.views[:, 1]),
                   np.searchsorted(self.lf.u, self.views[:, 0])]
        return self.rim_cut(rc)[self.view]

    @property
    def image_edge(self) -> ImageEdge:
        """Edge blur of particle images along ``s`` and ``t`` for the image fits
        (:class:`~plenoptrack.locate.refine.ImageEdge`): the lattice's resampling and
        ``edge_blur``."""
        return ImageEdge.of_frame(self.lf.grid_type, self.edge_blur)

    def fit_images(self, views, free_xyz, free_rc, held_xyz, held_rc, **options):
        """Fit free particles to this frame's view pixels, neighbours held
        (:func:`~plenoptrack.locate.refine.fit_images` with the frame's calibration, light
        field and :attr:`image_edge`).

        Parameters
        ----------
        views : ((V, 2) float ndarray, (V, 2) int ndarray)
            ``(u, v)`` of the views to fit in and their ``(v, u)`` index into the light
            field (:func:`_fit_views`, or a subset of them).
        free_xyz, free_rc, held_xyz, held_rc
            Starting positions (mm) and ``(radius px, contrast)`` of the particles to fit,
            and those of the neighbours drawn at fixed places.
        **options
            The other keywords of :func:`~plenoptrack.locate.refine.fit_images`
            (``max_depth_shift``, ``reference``, ``view_basis``, ...).

        Returns
        -------
        ImageFit or None
        """
        from . import refine

        views_uv, view_rc = views
        free_rc = np.asarray(free_rc, dtype=float)
        if len(free_rc) and np.any(2.0 * free_rc[:, 0] > self.large_image_px):
            # a large image's centroid in a view the rim cuts does not follow the DLFC
            # (FrameContext.large_image_px): fit it without those views
            whole = ~self.rim_cut(view_rc)
            if 6 <= whole.sum() < len(whole):
                views_uv, view_rc = views_uv[whole], view_rc[whole]
                if options.get("view_basis") is not None:
                    options["view_basis"] = options["view_basis"][whole]
        return refine.fit_images(self.dlfc, views_uv, view_rc, self.lf.data, free_xyz,
                                 free_rc, held_xyz, held_rc, edge=self.image_edge, **options)

    @classmethod
    def build(cls, lf: LightField, calibration, detections: pd.DataFrame,
              locator: PerspectiveLocator) -> "FrameContext":
        """The context of a frame from its light field and non-empty detections."""
        dlfc, camera = calibration.dlfc, calibration.camera
        view, views = _view_index(detections)
        elongation = (detections["major_axis_px"].to_numpy(float)
                      / np.maximum(detections["minor_axis_px"].to_numpy(float), 1e-9))
        z_lo, z_hi = (locator.cluster.depth_range_mm
                      if locator.cluster.depth_range_mm is not None
                      else (float(dlfc.bounds[0, 2]), float(dlfc.bounds[1, 2])))
        merge_px = (locator.grow.merge_distance_px
                    if locator.grow.merge_distance_px is not None
                    else 0.5 * float(detections["diameter_px"].median()))
        return cls(lf=lf, dlfc=dlfc, camera=camera, detections=detections,
                   st=detections[["s", "t"]].to_numpy(float), view=view, views=views,
                   radius_px=(0.5 * detections["major_axis_px"].to_numpy(float)
                              + locator.grow.add_tolerance_px),
                   round_=(elongation <= locator.segment.merged_elongation) | _split(detections),
                   geometry=ProjectionGeometry.from_lightfield(lf, camera),
                   alphas=plane_alphas(camera, (z_lo, z_hi), locator.cluster.n_planes),
                   n_possible=int(lf.view_mask.sum()), volume_depth_mm=z_hi - z_lo,
                   merge_px=merge_px, tolerance_px=locator.grow.add_tolerance_px,
                   edge_blur=getattr(calibration, "edge_blur_by_depth", None),
                   max_area_ratio=locator.segment.max_area_ratio,
                   large_image_px=_large_image_px(calibration),
                   rim_min_valid=locator.solve.rim_min_valid)


@dataclass(frozen=True, eq=False)
class SolveMemo:
    """What the last :func:`~plenoptrack.locate.perspective.solve_particles` call solved,
    so that the next one solves only the particles whose centroids changed.

    A particle whose centroids are those of its last solve, on the same frame context and
    settings, would be solved again from its own solution and return it (within about
    1e-7 mm): its row of ``table`` and the outcome for its centroids in ``owner_out`` are
    taken instead. Most particles are in that case in the later solve rounds of a frame
    (95-98 % of 1000 particles on a hall2019 frame).

    Attributes
    ----------
    context : FrameContext
        The context solved on (its detections, views and calibration).
    settings : SolveSettings
    owner_in, owner_out : (M,) int ndarray
        Each detection's owner before and after that solve (after: outliers released).
    table : DataFrame
        The solve's table, one row per particle (index 0..P-1).
    """

    context: "FrameContext"
    settings: SolveSettings
    owner_in: np.ndarray
    owner_out: np.ndarray
    table: pd.DataFrame

    def to_solve(self, ctx: "FrameContext", settings: SolveSettings,
                 owner: np.ndarray, n_particles: int) -> np.ndarray:
        """(P,) bool: the particles whose centroids (``owner``) differ from their last
        solve's, or that are new since; all of them when anything else changed."""
        if (self.context is not ctx or self.settings != settings
                or len(self.owner_in) != len(owner) or len(self.table) > n_particles):
            return np.ones(n_particles, dtype=bool)
        redo = np.zeros(n_particles, dtype=bool)
        redo[len(self.table):] = True
        differ = owner != self.owner_in
        for labels in (owner[differ], self.owner_in[differ]):
            redo[labels[labels >= 0]] = True
        return redo


@dataclass(frozen=True)
class ParticleState:
    """Which detection belongs to which particle, and each particle's solution.

    Attributes
    ----------
    owner : (M,) int ndarray
        Particle row of each detection; -1 unassigned; ``_MERGED`` (-2) for regions held
        back as merged images of several particles.
    initial : (P, 3) float ndarray
        Starting position of each particle's next solve, mm.
    positions : (P, 3) float ndarray
        Solved positions ``(x, y, z)``, mm; NaN rows for particles without a solution.
    table : DataFrame
        P rows: the solution of each particle (columns of
        :meth:`~plenoptrack.locate.triangulate.Triangulation.to_frame`).
    solved : SolveMemo or None
        What the last :func:`~plenoptrack.locate.perspective.solve_particles` solved (None
        before the first).
    """

    owner: np.ndarray
    initial: np.ndarray
    positions: np.ndarray
    table: pd.DataFrame
    solved: SolveMemo | None = None

    @classmethod
    def start(cls, ctx: FrameContext, segment: SegmentSettings) -> "ParticleState":
        """No particles yet; large regions and split halves are held back as merged."""
        area = ctx.detections["area"].to_numpy(float)
        owner = np.full(len(area), -1, dtype=np.int64)
        owner[area > segment.max_area_ratio * _single_image_area(ctx.detections)] = _MERGED
        # Halves of split merged images wait, like merged regions, until particles have
        # been located: only those no located particle accounts for join the pool.
        owner[_split(ctx.detections)] = _MERGED
        empty = np.zeros((0, 3))
        return cls(owner=owner, initial=empty, positions=empty, table=pd.DataFrame())

    @property
    def n_particles(self) -> int:
        return len(self.initial)

    def live(self, min_views: int) -> np.ndarray:
        """(P,) bool: the particles with a finite position seen in at least
        ``min_views`` views."""
        return ((self.table["n_views"].to_numpy(float) >= min_views)
                & np.all(np.isfinite(self.positions), axis=1))


def _split(detections: pd.DataFrame) -> np.ndarray:
    """(M,) bool: the detections that are halves of a split pair of merged images."""
    if "split_pair" in detections.columns:
        return detections["split_pair"].to_numpy(bool)
    return np.zeros(len(detections), dtype=bool)


MIN_VIEW_FRACTION = 0.5
"""Smallest valid fraction of a view that any stage of the locator reads (the image fits'
views, :func:`_fit_views`, and the image coverage,
:func:`~plenoptrack.locate.crowding.image_coverage`); the views below it are not decoded."""


_FIT_ERROR = "_fit_model_error"
_HIDDEN = "_hidden"
_FIT_RADIUS = "_fit_radius_px"
_SPLIT_OF = "_split_of"
_FIT_CONTRAST = "_fit_contrast"
_COMPANION = ("_companion_dx", "_companion_dy", "_companion_dz")
"""State-table columns: the offset (mm) from a particle to the darkness beside it that the
hidden-particle search found and could not take apart from it
(:func:`~plenoptrack.locate.hidden._note_companion`)."""
_CENTROID_SOLUTION = ("_centroid_x", "_centroid_y", "_centroid_z")
"""State-table columns: a particle's centroid solution (mm) from before the image-model
refinement first moved it (:func:`~plenoptrack.locate.perspective.refine_particles`); NaN
for a particle never moved, and for one put back by its image, whose centroids held
merged images (:func:`~plenoptrack.locate.split.keep_centroids_on_images`)."""


def _large_image_px(calibration) -> float:
    """Twice the equivalent diameter of the calibration's dot images, view pixels
    (:attr:`FrameContext.large_image_px`); inf when the calibration has no record of it."""
    from .pixel_locking import SIZE_FACTOR

    pattern = getattr(calibration, "locking_pattern", None)
    diameter = float(getattr(pattern, "image_diameter_px", math.nan))
    return SIZE_FACTOR * diameter if math.isfinite(diameter) else math.inf


def _fit_views(ctx: FrameContext) -> tuple[np.ndarray, np.ndarray]:
    """The views an image fit uses (more than half of their samples valid): their
    ``(u, v)`` (V, 2) and their ``(v, u)`` index into the light field (V, 2)."""
    vi = np.searchsorted(ctx.lf.v, ctx.views[:, 1])
    ui = np.searchsorted(ctx.lf.u, ctx.views[:, 0])
    usable = _usable_views(ctx)
    return ctx.views[usable], np.c_[vi, ui][usable]


def _usable_views(ctx: FrameContext) -> np.ndarray:
    """(len(ctx.views),) bool: the views of :func:`_fit_views`."""
    lf = ctx.lf
    return (lf.valid_fraction[np.searchsorted(lf.v, ctx.views[:, 1]),
                              np.searchsorted(lf.u, ctx.views[:, 0])] > MIN_VIEW_FRACTION)


def _member_diameter(detections: pd.DataFrame, owner: np.ndarray, n: int, *,
                     shadow: bool = False) -> np.ndarray:
    """(n,) median equivalent diameter (view pixels) of each particle's regions: of its
    whole regions when it has at least 3, else of all; NaN for particles without any.
    With ``shadow``, the equivalent diameter of each region's shadow,
    ``sqrt(4 dark_area / pi)`` (the opaque disc of the same summed darkness: smaller than
    the thresholded region by about the blur of its edge)."""
    mine = owner >= 0
    diameter = (np.sqrt(4.0 * np.maximum(detections["dark_area"].to_numpy(float), 0.0) / math.pi)
                if shadow else detections["diameter_px"].to_numpy(float))
    d = pd.DataFrame({"owner": owner[mine], "diameter": diameter[mine],
                      "whole": detections["whole"].to_numpy(bool)[mine]})
    every = d.groupby("owner")["diameter"].median()
    grouped = d[d["whole"]].groupby("owner")["diameter"]
    whole = grouped.median()[grouped.size() >= 3]
    out = np.full(n, np.nan)
    out[every.index.to_numpy()] = every.to_numpy()
    out[whole.index.to_numpy()] = whole.to_numpy()
    return out


def _view_index(detections: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Index of each detection's view and the (n_views, 2) table of view ``(u, v)``."""
    views, idx, _ = unique_rows(detections[["u", "v"]].to_numpy(float))
    return idx, views.reshape(-1, 2)
