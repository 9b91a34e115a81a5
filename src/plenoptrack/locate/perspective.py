"""The perspective-shift particle locator: one raw image to a table of 3D particles.

Composes the steps of section 2 of the method paper:

1. decode the raw image and segment dark particles in every valid perspective view
   (:mod:`~plenoptrack.locate.segment`);
2. group the centroids of each particle across views by k-means on projected refocus
   planes (:mod:`~plenoptrack.locate.cluster`);
3. solve each particle's (x, y, z) through the Direct Light Field Calibration with
   outlier rejection (:mod:`~plenoptrack.locate.triangulate`);
4. from the most confident particle down, add unassigned centroids that the particle's
   position predicts in views where it has none, and solve again; cluster whatever
   remains unassigned and repeat;
5. measure in-plane size and shape from the member regions, converted to mm with the
   local magnification of the calibration.

References
----------
E. M. Hall, D. R. Guildenbecher, B. S. Thurow, "Development and uncertainty
characterization of 3D particle location from perspective shifted plenoptic images",
Opt. Express 27 (2019).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field

import numpy as np
import pandas as pd

from .._columns import POS_COLUMNS, T_COLUMN
from ..errors import NoParticlesWarning
from ..lightfield.decode import LightField, decode
from .cluster import ProjectionGeometry, cluster_detections, plane_alphas
from .segment import segment_views
from .triangulate import TriangulationFlag, predict_detection, triangulate_clusters

__all__ = ["PerspectiveLocator", "PARTICLE_COLUMNS", "locate_frame", "LocateResult"]

PARTICLE_COLUMNS = (T_COLUMN, *POS_COLUMNS, "sigma_x", "sigma_y", "sigma_z", "n_views",
                    "confidence", "residual_px", "diameter", "major_axis", "minor_axis",
                    "orientation", "flags")
"""Columns of a particles table: ``frame``; ``x, y, z`` and their standard uncertainties
``sigma_*`` (mm); ``n_views`` (centroids used); ``confidence`` (eq. 3 of the paper);
``residual_px`` (RMS reprojection error, view pixels); ``diameter`` (equivalent diameter),
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
    """

    particles: pd.DataFrame
    detections: pd.DataFrame


@dataclass(frozen=True)
class PerspectiveLocator:
    """Settings of the perspective-shift locator.

    Call :meth:`locate` (or :func:`locate_frame`) with a raw image and a calibration that
    holds a DLFC.

    Parameters
    ----------
    window : int
        Side of the local-threshold window in each view, view pixels.
    contrast : float
        A particle pixel is darker than its local background by at least this fraction.
    area_range : (float, float)
        Accepted region areas in a view, view pixels.
    max_eccentricity : float
        Regions more elongated than this are ignored (1 keeps all).
    n_planes : int
        Refocus planes of the clustering (10 in the paper).
    depth_range_mm : (float, float), optional
        Depth range to cluster over, mm; default the z range of the DLFC's dot cards.
    reject_k : float
        Outlier threshold of the triangulation, in robust standard deviations.
    min_views : int
        Fewest centroids a particle needs to be reported.
    add_tolerance_px : float
        A centroid is added to a particle when it lies within this distance (view
        pixels) of where the particle's position predicts it, or within 3 times the
        particle's RMS residual if that is larger.
    passes : int
        Rounds of "cluster the unassigned centroids, triangulate, add centroids".
    merge_distance_px : float
        Two particles whose predicted positions in the central view are closer than this
        (view pixels) and whose depths agree within their combined uncertainty are merged.
    seed : int
        Seed of the k-means initialisation.
    """

    window: int = 31
    contrast: float = 0.15
    area_range: tuple[float, float] = (2.0, math.inf)
    max_eccentricity: float = 1.0
    n_planes: int = 10
    depth_range_mm: tuple[float, float] | None = None
    reject_k: float = 3.0
    min_views: int = 6
    add_tolerance_px: float = 1.0
    passes: int = 2
    merge_distance_px: float = 1.0
    seed: int = 0
    extra: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.window < 3:
            raise ValueError(f"window must be at least 3 view pixels; got {self.window}")
        if not 0 < self.contrast < 1:
            raise ValueError(f"contrast must be between 0 and 1; got {self.contrast}")
        if self.n_planes < 2:
            raise ValueError(f"n_planes must be at least 2; got {self.n_planes}")
        if self.min_views < 2:
            raise ValueError(f"min_views must be at least 2; got {self.min_views}")
        if self.passes < 1:
            raise ValueError(f"passes must be at least 1; got {self.passes}")
        if self.depth_range_mm is not None and not self.depth_range_mm[1] > self.depth_range_mm[0]:
            raise ValueError(f"depth_range_mm must be (near, far) with far > near; got {self.depth_range_mm}")

    def settings(self) -> dict:
        """The settings as a plain dict (for provenance in output metadata)."""
        d = asdict(self)
        d.pop("extra")
        return d

    def locate(self, raw_or_lf, calibration, *, frame: int = 0) -> LocateResult:
        """Locate the particles of one frame; see :func:`locate_frame`."""
        return locate_frame(raw_or_lf, calibration, frame=frame, locator=self)


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


def _add_centroids(dlfc, detections: pd.DataFrame, owner: np.ndarray, positions: np.ndarray,
                   residual: np.ndarray, confidence: np.ndarray, tolerance_px: float) -> np.ndarray:
    """Give unassigned centroids to the particle that predicts them (most confident first).

    Parameters
    ----------
    detections : DataFrame
        Columns ``u, v, s, t``.
    owner : (M,) int ndarray
        Particle row of each detection, -1 for unassigned.
    positions : (P, 3) float ndarray
        Particle positions, mm.
    residual, confidence : (P,) float ndarray
        RMS reprojection error (view pixels) and confidence of each particle.

    Returns
    -------
    (M,) int ndarray
        Updated owners: an unassigned centroid joins the most confident particle that has
        no centroid in its view yet and predicts it within the tolerance; a particle takes
        at most one centroid per view (the nearest).
    """
    owner = owner.copy()
    ok = np.all(np.isfinite(positions), axis=1)
    if not ok.any():
        return owner
    u = detections["u"].to_numpy(float)
    v = detections["v"].to_numpy(float)
    s = detections["s"].to_numpy(float)
    t = detections["t"].to_numpy(float)
    view_key = np.round(u).astype(np.int64) * 1000 + np.round(v).astype(np.int64)
    tol = np.maximum(tolerance_px, 3.0 * np.nan_to_num(residual, nan=tolerance_px))
    rank = np.argsort(-np.nan_to_num(confidence, nan=-np.inf), kind="stable")
    for key in np.unique(view_key[owner < 0]):
        in_view = view_key == key
        free = np.flatnonzero(in_view & (owner < 0))
        taken = np.unique(owner[in_view & (owner >= 0)])
        candidates = np.setdiff1d(np.flatnonzero(ok), taken)
        if len(candidates) == 0:
            continue
        ps, pt = predict_detection(dlfc, positions[candidates], u[free[0]], v[free[0]])
        dist = np.hypot(s[free][:, None] - ps[None, :], t[free][:, None] - pt[None, :])
        within = dist <= tol[candidates][None, :]
        if not within.any():
            continue
        order = np.argsort(np.argsort(rank))[candidates]  # confidence rank of candidates
        for c in np.argsort(order):  # most confident particle first
            hits = np.flatnonzero(within[:, c] & (owner[free] < 0))
            if len(hits):
                owner[free[hits[np.argmin(dist[hits, c])]]] = candidates[c]
    return owner


def _region_shape(detections: pd.DataFrame, owner: np.ndarray, n: int) -> pd.DataFrame:
    """Median equivalent diameter and axes (view pixels) and mean orientation per particle."""
    mask = owner >= 0
    if not mask.any():
        return pd.DataFrame({"diameter_px": np.full(n, np.nan), "major_px": np.full(n, np.nan),
                             "minor_px": np.full(n, np.nan), "orientation": np.full(n, np.nan)})
    d = detections.loc[mask, ["diameter_px", "major_axis_px", "minor_axis_px", "orientation"]].copy()
    d["owner"] = owner[mask]
    # Orientation is axial (theta ~ theta + pi): average the doubled angle.
    d["c2"] = np.cos(2 * d["orientation"])
    d["s2"] = np.sin(2 * d["orientation"])
    g = d.groupby("owner")
    med = g[["diameter_px", "major_axis_px", "minor_axis_px"]].median()
    ang = 0.5 * np.arctan2(g["s2"].mean(), g["c2"].mean())
    out = pd.DataFrame(index=np.arange(n))
    out["diameter_px"] = med["diameter_px"]
    out["major_px"] = med["major_axis_px"]
    out["minor_px"] = med["minor_axis_px"]
    out["orientation"] = ang
    return out


def _solve(dlfc, detections, owner, initial, n_possible, volume_depth, locator):
    """Triangulate every particle that owns centroids; returns the per-particle table and
    the inlier mask of the detections."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        tri = triangulate_clusters(dlfc, detections.assign(_owner=owner), initial,
                                   cluster_column="_owner", n_possible_views=n_possible,
                                   volume_depth_mm=volume_depth, reject_k=locator.reject_k,
                                   min_views=min(4, locator.min_views))
    return tri


def locate_frame(raw_or_lf, calibration, *, frame: int = 0,
                 locator: PerspectiveLocator | None = None) -> LocateResult:
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

    Returns
    -------
    LocateResult
        ``particles`` (columns :data:`PARTICLE_COLUMNS`, mm) and ``detections``. An image
        with no particles gives an empty table and a :class:`NoParticlesWarning`.
    """
    locator = PerspectiveLocator() if locator is None else locator
    dlfc = calibration.dlfc
    camera = calibration.camera
    if isinstance(raw_or_lf, LightField):
        lf = raw_or_lf
    else:
        image = np.asarray(raw_or_lf)
        calibration.check_image(image)
        lf = decode(image, calibration.grid)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        detections = segment_views(lf, frame=frame, window=locator.window,
                                   contrast=locator.contrast, area_range=locator.area_range,
                                   max_eccentricity=locator.max_eccentricity)
    detections = detections.reset_index(drop=True)
    owner = np.full(len(detections), -1, dtype=np.int64)
    z_lo, z_hi = (locator.depth_range_mm if locator.depth_range_mm is not None
                  else (float(dlfc.bounds[0, 2]), float(dlfc.bounds[1, 2])))
    volume_depth = z_hi - z_lo
    alphas = plane_alphas(camera, (z_lo, z_hi), locator.n_planes)
    geometry = ProjectionGeometry.from_lightfield(lf, camera)
    n_possible = int(lf.view_mask.sum())

    positions = np.zeros((0, 3))
    for _ in range(locator.passes):
        free = np.flatnonzero(owner < 0)
        if len(free) < locator.min_views:
            break
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NoParticlesWarning)
            clustering = cluster_detections(detections.iloc[free], geometry, alphas,
                                            min_members=locator.min_views, seed=locator.seed)
        if clustering.n_clusters == 0:
            break
        start = len(positions)
        labels = clustering.detections["cluster"].to_numpy()
        owner[free[labels >= 0]] = labels[labels >= 0] + start
        init_new = _initial_positions(clustering.clusters, camera).to_numpy()
        initial = np.vstack([positions, init_new])
        # Solve, then grow clusters with the centroids their particles predict, solve again.
        for _grow in range(2):
            tri = _solve(dlfc, detections, owner, _initial_frame(initial, owner), n_possible,
                         volume_depth, locator)
            positions, table = _gather(tri, len(initial))
            owner = np.where(tri.inliers, owner, -1)
            owner = _add_centroids(dlfc, detections, owner, positions,
                                   table["residual_px"].to_numpy(),
                                   table["confidence"].to_numpy(), locator.add_tolerance_px)
            initial = np.where(np.isfinite(positions), positions, initial)
    if len(positions) == 0:
        return _finish_empty(detections, frame)

    tri = _solve(dlfc, detections, owner, _initial_frame(initial, owner), n_possible,
                 volume_depth, locator)
    positions, table = _gather(tri, len(initial))
    owner = np.where(tri.inliers, owner, -1)
    keep = (table["n_views"].to_numpy() >= locator.min_views) & np.all(np.isfinite(positions), axis=1)
    shape = _region_shape(detections, owner, len(positions))
    mag = dlfc.local_magnification(*positions[keep].T) if keep.any() else np.zeros(0)
    particles = table.loc[keep, ["x", "y", "z", "sigma_x", "sigma_y", "sigma_z", "n_views",
                                 "confidence", "residual_px", "flags"]].copy()
    particles.insert(0, T_COLUMN, frame)
    particles["diameter"] = shape.loc[keep, "diameter_px"].to_numpy() / mag
    particles["major_axis"] = shape.loc[keep, "major_px"].to_numpy() / mag
    particles["minor_axis"] = shape.loc[keep, "minor_px"].to_numpy() / mag
    particles["orientation"] = shape.loc[keep, "orientation"].to_numpy()
    # Renumber particles 0..n-1 and point the detections at the kept rows.
    new_index = np.full(len(positions), -1, dtype=np.int64)
    new_index[np.flatnonzero(keep)] = np.arange(int(keep.sum()))
    particle_of = np.where(owner >= 0, new_index[np.maximum(owner, 0)], -1)
    particles = particles[list(PARTICLE_COLUMNS)].reset_index(drop=True)
    particles["n_views"] = particles["n_views"].astype(np.int64)
    particles["flags"] = particles["flags"].astype(np.uint8)
    detections = detections.assign(particle=particle_of, inlier=particle_of >= 0)
    if len(particles) == 0:
        return _finish_empty(detections, frame)
    return LocateResult(particles=particles, detections=detections)


def _initial_frame(initial: np.ndarray, owner: np.ndarray) -> pd.DataFrame:
    """Starting positions indexed by particle row, for the rows that own centroids."""
    used = np.unique(owner[owner >= 0])
    return pd.DataFrame(initial[used], index=used, columns=list(POS_COLUMNS))


def _gather(tri, n: int) -> tuple[np.ndarray, pd.DataFrame]:
    """Scatter a triangulation (rows = particles owning centroids) into ``n`` rows."""
    table = tri.to_frame().set_index("cluster").reindex(np.arange(n))
    table["n_views"] = table["n_views"].fillna(0)
    table["flags"] = table["flags"].fillna(0)
    positions = table[list(POS_COLUMNS)].to_numpy(float)
    return positions, table


def _finish_empty(detections: pd.DataFrame, frame: int) -> LocateResult:
    warnings.warn(f"frame {frame}: no particles found", NoParticlesWarning, stacklevel=3)
    detections = detections.assign(particle=np.full(len(detections), -1, dtype=np.int64),
                                   inlier=np.zeros(len(detections), dtype=bool))
    return LocateResult(particles=_empty_particles(), detections=detections)


def flags_text(flags: int) -> str:
    """Names of the :class:`TriangulationFlag` bits set in ``flags``."""
    return "|".join(f.name for f in TriangulationFlag if flags & f) or "-"
