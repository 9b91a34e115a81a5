"""The perspective-shift particle locator: one raw image to a table of 3D particles.

Composes the steps of section 2 of the method paper:

1. decode the raw image and segment dark particles in every valid perspective view
   (:mod:`~plenoptrack.locate.segment`); split regions holding several dark cores into
   those cores and large elongated regions into the two particle images their second
   moments imply; ignore views dominated by noise;
2. group the centroids of each particle across views by k-means on projected refocus
   planes, finished by a density sweep (:mod:`~plenoptrack.locate.cluster`); large
   regions and split halves wait until particles are located and join the pool only
   where no located particle accounts for them;
3. solve each particle's (x, y, z) through the Direct Light Field Calibration with
   outlier rejection (:mod:`~plenoptrack.locate.triangulate`);
4. from the most confident particle down, add unassigned centroids that the particle's
   position predicts in views where it has none, and solve again; cluster whatever
   remains unassigned and repeat; drop particles that fail the consistency checks;
5. measure in-plane size and shape from the member regions, converted to mm with the
   local magnification of the calibration.

References
----------
E. M. Hall, D. R. Guildenbecher, B. S. Thurow, "Development and uncertainty
characterization of 3D particle location from perspective shifted plenoptic images",
Opt. Express 27 (2019).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import asdict, dataclass, field

import numba
import numpy as np
import pandas as pd

from .._columns import POS_COLUMNS, T_COLUMN
from ..errors import NoParticlesWarning, SettingsError
from ..io import warn_exposure
from ..lightfield.decode import LightField, decode
from ._nearby import pairs_within
from .cluster import ProjectionGeometry, cluster_detections, plane_alphas
from .segment import segment_views
from .triangulate import triangulate_cluster, triangulate_clusters

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
    stage_seconds : dict
        Wall-clock time of each stage of the call, s: ``decode``, ``segment``,
        ``cluster`` (every clustering pass), ``triangulate`` (solves, duplicate merging
        and centroid addition) and ``checks`` (final consistency checks and the table).
    """

    particles: pd.DataFrame
    detections: pd.DataFrame
    stage_seconds: dict = field(default_factory=dict, compare=False)


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
    core_contrast : float or None
        A second segmentation at this (higher) contrast finds the dark cores of the
        particle images; a region that holds two or more cores is the merged image of
        touching particles and is replaced by its cores. None disables the split.
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
    merge_distance_px : float or None
        Two particles whose predicted positions lie within this distance (view pixels)
        of each other in most views (median over views) are one particle and are merged;
        default half the median equivalent diameter of the detections.
    max_residual_ratio : float
        Particles whose RMS residual exceeds this multiple of the median over the frame
        (and ``add_tolerance_px``) are dropped.
    min_aperture_spread : float
        Particles whose views span less than this fraction of the aperture (RMS
        distance of their views' ``(u, v)`` from its mean, against that of all valid
        views) are dropped: their depth rests on a narrow baseline.
    max_area_ratio : float
        Regions larger than this multiple of the median region area of the frame are
        taken for merged images of several particles: they are neither clustered nor
        added to particles (their centroids lie between the particles).
    merged_elongation : float
        After the first pass, large regions no more elongated than this (major over
        minor axis) on which no located particle is predicted are returned to the pool:
        they are single particles near the camera, imaged at a higher magnification.
    split_pairs : bool
        Replace regions larger than ``max_area_ratio`` times the median and more
        elongated than ``merged_elongation`` by two half regions placed from their
        second moments (the merged image of two particles); otherwise such regions are
        left out.
    max_explained : float
        Particles for which, in more than this fraction of their views, two other
        particles are predicted on the centroid are dropped (built from merged images).
    max_explained_strong : float
        The same limit for particles seen in at least a quarter of the valid views. A
        phantom made of merged images exists only in the views where the images merge
        (a part of the aperture, fractions near 1); a real particle in line with two
        others in depth can be overlapped in three quarters of its many views.
    max_view_ratio : float or None
        Views with more than this multiple of the median number of regions per view are
        dominated by noise (dim rim views) and are not used; None keeps every view.
    solver : {"lm", "scipy"}
        Least-squares solver of the triangulation (see
        :func:`~plenoptrack.locate.triangulate.triangulate_clusters`).
    seed : int
        Seed of the k-means initialisation.
    """

    window: int = 31
    contrast: float = 0.15
    core_contrast: float | None = 0.93
    area_range: tuple[float, float] = (2.0, math.inf)
    max_eccentricity: float = 1.0
    n_planes: int = 10
    depth_range_mm: tuple[float, float] | None = None
    reject_k: float = 3.0
    min_views: int = 6
    add_tolerance_px: float = 1.0
    passes: int = 2
    merge_distance_px: float | None = None
    max_residual_ratio: float = 4.0
    min_aperture_spread: float = 0.4
    max_explained: float = 0.5
    max_explained_strong: float = 0.85
    max_area_ratio: float = 1.3
    merged_elongation: float = 1.25
    split_pairs: bool = True
    max_view_ratio: float | None = 2.0
    solver: str = "lm"
    seed: int = 0

    def __post_init__(self) -> None:
        if self.window < 3:
            raise SettingsError(f"window must be at least 3 view pixels; got {self.window}")
        if not 0 < self.contrast < 1:
            raise SettingsError(f"contrast must be between 0 and 1; got {self.contrast}")
        if self.core_contrast is not None and not self.contrast < self.core_contrast < 1:
            raise SettingsError(f"core_contrast must be None or between contrast "
                             f"({self.contrast}) and 1; got {self.core_contrast}")
        if self.n_planes < 2:
            raise SettingsError(f"n_planes must be at least 2; got {self.n_planes}")
        if self.min_views < 2:
            raise SettingsError(f"min_views must be at least 2; got {self.min_views}")
        if self.solver not in ("lm", "scipy"):
            raise SettingsError(f"solver must be 'lm' or 'scipy'; got {self.solver!r}")
        if self.max_view_ratio is not None and not self.max_view_ratio > 1:
            raise SettingsError(f"max_view_ratio must be None or above 1; got {self.max_view_ratio}")
        if self.passes < 1:
            raise SettingsError(f"passes must be at least 1; got {self.passes}")
        if self.depth_range_mm is not None and not self.depth_range_mm[1] > self.depth_range_mm[0]:
            raise SettingsError(f"depth_range_mm must be (near, far) with far > near; got {self.depth_range_mm}")

    def settings(self) -> dict:
        """The settings as a plain dict (for provenance in output metadata)."""
        return asdict(self)

    def locate(self, raw_or_lf, calibration, *, frame: int = 0, white=None) -> LocateResult:
        """Locate the particles of one frame; see :func:`locate_frame`."""
        return locate_frame(raw_or_lf, calibration, frame=frame, locator=self, white=white)


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


_MERGED = -2  # owner of regions taken for merged images of several particles


def _view_index(detections: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Index of each detection's view and the (n_views, 2) table of view ``(u, v)``."""
    uv = detections[["u", "v"]].to_numpy(float)
    views, idx = np.unique(uv, axis=0, return_inverse=True)
    return idx.ravel().astype(np.int64), views.reshape(-1, 2)


def _predict_all(dlfc, positions: np.ndarray, views: np.ndarray) -> np.ndarray:
    """(P, V, 2) predicted ``(s, t)`` of every particle in every view; NaN rows for
    particles without a finite position."""
    out = np.full((len(positions), len(views), 2), np.nan)
    ok = np.all(np.isfinite(positions), axis=1)
    if ok.any() and len(views):
        p = positions[ok]
        s, t = dlfc.predict(p[:, None, 0], p[:, None, 1], p[:, None, 2],
                            views[None, :, 0], views[None, :, 1])
        out[ok, :, 0] = s
        out[ok, :, 1] = t
    return out


def _add_centroids(pred: np.ndarray, st: np.ndarray, view: np.ndarray, owner: np.ndarray,
                   residual: np.ndarray, confidence: np.ndarray,
                   tolerance_px: float) -> np.ndarray:
    """Give unassigned centroids to the particle that predicts them (most confident first).

    Parameters
    ----------
    pred : (P, V, 2) float ndarray
        Predicted ``(s, t)`` of every particle in every view (:func:`_predict_all`).
    st : (M, 2) float ndarray
        Measured centroids ``(s, t)``, view pixels.
    view : (M,) int ndarray
        View index of each centroid.
    owner : (M,) int ndarray
        Particle row of each detection, -1 for unassigned.
    residual, confidence : (P,) float ndarray
        RMS reprojection error (view pixels) and confidence of each particle.

    Returns
    -------
    (M,) int ndarray
        Updated owners: an unassigned centroid joins the most confident particle that has
        no centroid in its view yet and predicts it within the tolerance; a particle takes
        at most one centroid per view (the nearest; the lowest row on a tie).

    Notes
    -----
    The candidate (particle, centroid) pairs of each view come from a spatial search
    (:func:`~plenoptrack.locate._nearby.pairs_within`); the greedy choice then runs over
    the pairs ordered by particle rank, view, distance and row.
    """
    owner = owner.copy()
    n_p, n_v = pred.shape[:2]
    ok = np.all(np.isfinite(pred[:, 0]), axis=1)
    free = np.flatnonzero(owner == -1)
    if not ok.any() or len(free) == 0:
        return owner
    has = np.zeros((n_p, n_v), dtype=bool)
    mine = owner >= 0
    has[owner[mine], view[mine]] = True
    tol = np.maximum(tolerance_px, 3.0 * np.nan_to_num(residual, nan=tolerance_px))
    rank = np.argsort(-np.nan_to_num(confidence, nan=-np.inf), kind="stable")
    place = np.empty(n_p, dtype=np.int64)
    place[rank] = np.arange(n_p)
    has_free = np.bincount(view[free], minlength=n_v) > 0
    part, w = np.nonzero(ok[:, None] & ~has & has_free[None, :])
    q, f, dist = pairs_within(pred[part, w], w, tol[part], st[free], view[free])
    if len(q) == 0:
        return owner
    part, w, rows = part[q], w[q], free[f]
    order = np.lexsort((rows, dist, w, place[part]))
    part, w, rows = part[order], w[order], rows[order]
    first = np.flatnonzero(np.r_[True, (part[1:] != part[:-1]) | (w[1:] != w[:-1])])
    pick = _first_untaken(np.r_[first, len(rows)], rows, len(owner))
    pick = pick[pick >= 0]
    owner[rows[pick]] = part[pick]
    return owner


@numba.njit(cache=True)
def _first_untaken(start, rows, n_rows):  # pragma: no cover - compiled
    """Greedy choice over groups of candidate rows in preference order.

    Group ``g`` is ``rows[start[g]:start[g + 1]]``; groups are visited in order and each
    takes its first row that no earlier group took. Returns the position (in ``rows``)
    of each group's choice, -1 when every candidate was taken.
    """
    taken = np.zeros(n_rows, dtype=np.bool_)
    pick = np.full(len(start) - 1, -1, dtype=np.int64)
    for g in range(len(start) - 1):
        for i in range(start[g], start[g + 1]):
            if not taken[rows[i]]:
                taken[rows[i]] = True
                pick[g] = i
                break
    return pick


def _merge_duplicates(pred: np.ndarray, st: np.ndarray, view: np.ndarray, owner: np.ndarray,
                      n_views: np.ndarray, merge_px: float) -> np.ndarray:
    """Merge particles whose predictions coincide in most views.

    Two particles are the same when the median distance between their predicted
    positions over all views is at most ``merge_px``. From the particle with most
    centroids down, each particle not yet merged absorbs the same particles that have no
    more centroids than it and have not been merged: the centroids of both are pooled
    and, in each view, the one nearest the surviving particle's prediction is kept (the
    others are released).

    Returns
    -------
    (M,) int ndarray
        Updated owners.
    """
    ok = np.flatnonzero(np.all(np.isfinite(pred[:, 0]), axis=1) & (n_views > 0))
    if len(ok) < 2:
        return owner
    a, b = _coincident_pairs(pred[ok], merge_px)
    if len(a) == 0:
        return owner
    # Both directions, each particle's partners in ascending order.
    src, dst = np.r_[a, b], np.r_[b, a]
    by = np.lexsort((dst, src))
    start = np.searchsorted(src[by], np.arange(len(ok) + 1))
    strength = n_views[ok]
    into = _absorb(np.argsort(-strength, kind="stable"), start, dst[by], strength)
    target = np.arange(len(pred))
    target[ok] = ok[into]
    owner = owner.copy()
    mine = owner >= 0
    owner[mine] = target[owner[mine]]
    survivor = np.zeros(len(pred), dtype=bool)
    survivor[target[target != np.arange(len(pred))]] = True
    rows = np.flatnonzero(mine)
    rows = rows[survivor[owner[rows]]]
    k, vw = owner[rows], view[rows]
    dist = np.hypot(st[rows, 0] - pred[k, vw, 0], st[rows, 1] - pred[k, vw, 1])
    order = np.lexsort((dist, vw, k))
    rows, k, vw = rows[order], k[order], vw[order]
    first = np.r_[True, (k[1:] != k[:-1]) | (vw[1:] != vw[:-1])]
    owner[rows[~first]] = -1
    return owner


def _coincident_pairs(pred: np.ndarray, merge_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Pairs ``a < b`` of particles whose median predicted distance is <= ``merge_px``.

    Parameters
    ----------
    pred : (K, V, 2) float ndarray
        Predicted ``(s, t)`` of each particle in each view, view pixels.
    merge_px : float
        Largest median distance over the ``V`` views, view pixels.

    Returns
    -------
    a, b : (n,) int64 ndarray
        Row indices into ``pred``, ``a < b``, sorted by ``a`` then ``b``.

    Notes
    -----
    The median of ``V`` distances is at most ``merge_px`` only if at least
    ``ceil(V / 2)`` of them are (for even ``V`` the lower of the two middle values is),
    so such a pair is within ``merge_px`` in at least one of any ``V - ceil(V / 2) + 1``
    views. The pairs within ``merge_px`` in the first that many views come from a
    spatial search; the exact median over all views (NaN, hence no merge, when a view's
    distance is NaN) is taken for those pairs only.
    """
    n_k, n_v = pred.shape[:2]
    n_probe = n_v - (n_v + 1) // 2 + 1
    probe = pred[:, :n_probe].reshape(-1, 2)
    views = np.tile(np.arange(n_probe), n_k)
    q, d, _ = pairs_within(probe, views, merge_px, probe, views)
    a, b = q // n_probe, d // n_probe
    key = np.unique(a[a < b] * n_k + b[a < b])
    a, b = key // n_k, key % n_k
    median = np.median(np.hypot(pred[a, :, 0] - pred[b, :, 0], pred[a, :, 1] - pred[b, :, 1]),
                       axis=1)
    close = median <= merge_px
    return a[close], b[close]


@numba.njit(cache=True)
def _absorb(order, start, partner, strength):  # pragma: no cover - compiled
    """Greedy merging: ``target[i]`` is the particle that particle ``i`` merges into.

    Particles are visited in ``order``; one that has not been merged takes each of its
    partners ``partner[start[i]:start[i + 1]]`` that has not been merged and whose
    ``strength`` does not exceed its own.
    """
    target = np.arange(len(strength))
    for a in order:
        if target[a] != a:
            continue
        for j in range(start[a], start[a + 1]):
            b = partner[j]
            if target[b] == b and strength[b] <= strength[a]:
                target[b] = a
    return target


def _release_single_large(dlfc, positions, views, st, view, owner, radius_px, round_):
    """Return large round regions that no located particle is predicted on to the pool.

    A region taken for a merged image (owner ``_MERGED``) that is round and has no
    located particle predicted inside it (within ``radius_px``) is the image of one
    particle near the camera, larger than the typical image; it is released (owner -1)
    so that the next clustering pass can find that particle.
    """
    rows = np.flatnonzero((owner == _MERGED) & round_)
    ok = np.all(np.isfinite(positions), axis=1)
    if len(rows) == 0 or not ok.any():
        return owner
    pred = _predict_all(dlfc, positions[ok], views)                       # (P, V, 2)
    n_p, n_v = pred.shape[:2]
    q, _, _ = pairs_within(st[rows], view[rows], radius_px[rows], pred.reshape(-1, 2),
                           np.tile(np.arange(n_v), n_p))
    empty = np.bincount(q, minlength=len(rows)) == 0
    owner = owner.copy()
    owner[rows[empty]] = -1
    return owner


def _explained_by_others(pred: np.ndarray, st: np.ndarray, view: np.ndarray,
                         owner: np.ndarray, radius_px: np.ndarray, ok: np.ndarray
                         ) -> np.ndarray:
    """Fraction of each particle's centroids that two other particles' predictions fall on.

    A region where the images of two particles merge has its centroid between them; a
    spurious particle built from such regions has both neighbours predicted inside
    (within ``radius_px``, the region radius) of nearly all its centroids. Only the
    particles marked ``ok`` count as neighbours; with fewer than three every fraction
    is 0.
    """
    n_p, n_v = pred.shape[:2]
    frac = np.zeros(n_p)
    idx = np.flatnonzero(ok)
    if len(idx) < 3:
        return frac
    mine = np.flatnonzero(owner >= 0)
    own = owner[mine]
    q, d, _ = pairs_within(st[mine], view[mine], radius_px[mine], pred[idx].reshape(-1, 2),
                           np.tile(np.arange(n_v), len(idx)))
    other = idx[d // n_v] != own[q]
    hit = np.bincount(q[other], minlength=len(mine)) >= 2
    counts = np.bincount(own, minlength=n_p)
    frac = np.bincount(own, hit.astype(float), minlength=n_p) / np.maximum(counts, 1)
    return frac


def _split_merged(coarse: pd.DataFrame, cores: pd.DataFrame) -> pd.DataFrame:
    """Replace regions that hold two or more dark cores by those cores.

    ``coarse`` are regions at the segmentation contrast, ``cores`` regions of the same
    views at the (higher) core contrast. Each core joins the nearest coarse region of
    its view within half the region's major axis plus a pixel; a coarse region with
    several cores is the merged image of several particles.
    """
    if len(coarse) == 0 or len(cores) == 0:
        return coarse
    from scipy.spatial import cKDTree

    def key(df):
        return np.column_stack([df["s"].to_numpy() + 1e4 * (df["u"].to_numpy() + 100),
                                df["t"].to_numpy() + 1e4 * (df["v"].to_numpy() + 100)])

    dist, nearest = cKDTree(key(coarse)).query(key(cores))
    reach = 0.5 * coarse["major_axis_px"].to_numpy()[np.minimum(nearest, len(coarse) - 1)] + 1.0
    inside = np.isfinite(dist) & (dist <= reach)
    n_cores = np.bincount(nearest[inside], minlength=len(coarse))
    merged = n_cores >= 2
    if not merged.any():
        return coarse
    replacement = cores[inside & merged[np.minimum(nearest, len(coarse) - 1)]]
    out = pd.concat([coarse[~merged], replacement.assign(whole=False)], ignore_index=True)
    out["whole"] = out["whole"].fillna(True).astype(bool)
    return out.sort_values(["v", "u"], kind="stable").reset_index(drop=True)


def _region_shape(detections: pd.DataFrame, owner: np.ndarray, n: int) -> pd.DataFrame:
    """In-plane size and shape per particle from its member regions, view pixels.

    The diameter is the median over members of the equivalent diameter of the region's
    shadow, ``sqrt(4 dark_area / pi)`` (summed relative darkness: an opaque object's
    area, nearly independent of defocus blur and of the threshold); the axes are the
    members' second-moment axes scaled by the same shadow-to-threshold ratio; the
    orientation is the axial mean of the members'. Whole regions are preferred over the
    cores and halves that merged images were split into, which under-size a particle.
    """
    empty = pd.DataFrame({"diameter_px": np.full(n, np.nan), "major_px": np.full(n, np.nan),
                          "minor_px": np.full(n, np.nan), "orientation": np.full(n, np.nan)})
    mask = owner >= 0
    if not mask.any():
        return empty
    d = detections.loc[mask, ["diameter_px", "major_axis_px", "minor_axis_px", "orientation",
                              "dark_area"]].copy()
    d["owner"] = owner[mask]
    d["whole"] = (detections.loc[mask, "whole"].to_numpy(bool) if "whole" in detections.columns
                  else True)
    shadow = np.sqrt(4.0 * np.maximum(d["dark_area"].to_numpy(float), 0.0) / math.pi)
    ratio = shadow / np.maximum(d["diameter_px"].to_numpy(float), 1e-9)
    d["diameter_px"] = shadow
    d["major_axis_px"] *= ratio
    d["minor_axis_px"] *= ratio
    # Orientation is axial (theta ~ theta + pi): average the doubled angle.
    d["c2"] = np.cos(2 * d["orientation"])
    d["s2"] = np.sin(2 * d["orientation"])
    has_whole = d.groupby("owner")["whole"].transform("any").to_numpy(bool)
    g = d[d["whole"].to_numpy(bool) | ~has_whole].groupby("owner")
    med = g[["diameter_px", "major_axis_px", "minor_axis_px"]].median()
    out = empty.copy()
    idx = med.index.to_numpy()
    out.loc[idx, "diameter_px"] = med["diameter_px"].to_numpy()
    out.loc[idx, "major_px"] = med["major_axis_px"].to_numpy()
    out.loc[idx, "minor_px"] = med["minor_axis_px"].to_numpy()
    out.loc[idx, "orientation"] = 0.5 * np.arctan2(g["s2"].mean(), g["c2"].mean()).to_numpy()
    return out


def _solve(dlfc, detections, owner, initial, n_possible, volume_depth, locator):
    """Triangulate every particle that owns centroids; returns the per-particle table and
    the inlier mask of the detections."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        tri = triangulate_clusters(dlfc, detections.assign(_owner=owner), initial,
                                   cluster_column="_owner", n_possible_views=n_possible,
                                   volume_depth_mm=volume_depth, reject_k=locator.reject_k,
                                   min_views=min(4, locator.min_views), solver=locator.solver)
    return tri


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
    dlfc = calibration.dlfc
    camera = calibration.camera
    clock = {"decode": 0.0, "segment": 0.0, "cluster": 0.0, "triangulate": 0.0, "checks": 0.0}
    t_last = time.perf_counter()

    def lap(stage):
        nonlocal t_last
        now = time.perf_counter()
        clock[stage] += now - t_last
        t_last = now

    if isinstance(raw_or_lf, LightField):
        lf = raw_or_lf
    else:
        image = np.asarray(raw_or_lf)
        calibration.check_image(image)
        warn_exposure(image, camera.full_scale, source=f"frame {frame}")
        lf = decode(image, calibration.grid, white=white)
    if calibration.vignetting is not None and calibration.vignetting.shape == lf.valid_fraction.shape:
        # Views the white image showed to be vignetted are not searched.
        lf = dataclasses.replace(lf, valid_fraction=np.minimum(lf.valid_fraction,
                                                               calibration.vignetting))

    lap("decode")
    detections = _segment(lf, frame, locator)
    lap("segment")
    if len(detections) == 0:
        return _finish_empty(detections, frame, clock)
    view, views = _view_index(detections)
    st = detections[["s", "t"]].to_numpy(float)
    owner = np.full(len(detections), -1, dtype=np.int64)
    area = detections["area"].to_numpy(float)
    elongation = (detections["major_axis_px"].to_numpy(float)
                  / np.maximum(detections["minor_axis_px"].to_numpy(float), 1e-9))
    owner[area > locator.max_area_ratio * np.median(area)] = _MERGED
    # Halves of split merged images wait, like merged regions, until particles have
    # been located: only those no located particle accounts for join the pool.
    split = (detections["split_pair"].to_numpy(bool) if "split_pair" in detections.columns
             else np.zeros(len(detections), dtype=bool))
    owner[split] = _MERGED
    z_lo, z_hi = (locator.depth_range_mm if locator.depth_range_mm is not None
                  else (float(dlfc.bounds[0, 2]), float(dlfc.bounds[1, 2])))
    volume_depth = z_hi - z_lo
    alphas = plane_alphas(camera, (z_lo, z_hi), locator.n_planes)
    geometry = ProjectionGeometry.from_lightfield(lf, camera)
    n_possible = int(lf.view_mask.sum())
    radius_px = 0.5 * detections["major_axis_px"].to_numpy(float) + locator.add_tolerance_px
    merge_px = (locator.merge_distance_px if locator.merge_distance_px is not None
                else 0.5 * float(detections["diameter_px"].median()))

    def solve(owner, initial):
        tri = _solve(dlfc, detections, owner, _initial_frame(initial, owner), n_possible,
                     volume_depth, locator)
        positions, table = _gather(tri, len(initial))
        return np.where(tri.inliers | (owner == _MERGED), owner, -1), positions, table

    def grow(owner, positions, table):
        pred = _predict_all(dlfc, positions, views)
        n_v = table["n_views"].to_numpy().astype(np.int64)
        owner = _merge_duplicates(pred, st, view, owner, n_v, merge_px)
        return _add_centroids(pred, st, view, owner, table["residual_px"].to_numpy(),
                              table["confidence"].to_numpy(), locator.add_tolerance_px)

    positions = np.zeros((0, 3))
    initial = np.zeros((0, 3))
    for _ in range(locator.passes):
        if len(positions):
            owner = _release_single_large(dlfc, positions, views, st, view, owner, radius_px,
                                          (elongation <= locator.merged_elongation)
                                          | split)
        free = np.flatnonzero(owner == -1)
        if len(free) < locator.min_views:
            break
        lap("triangulate")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NoParticlesWarning)
            clustering = cluster_detections(detections.iloc[free], geometry, alphas,
                                            min_members=locator.min_views, seed=locator.seed)
        lap("cluster")
        if clustering.n_clusters == 0:
            break
        start = len(positions)
        labels = clustering.detections["cluster"].to_numpy()
        owner[free[labels >= 0]] = labels[labels >= 0] + start
        init_new = _initial_positions(clustering.clusters, camera).to_numpy()
        initial = np.vstack([initial, init_new])
        # Solve, merge duplicates, grow particles with the centroids they predict.
        for _grow in range(3):
            owner, positions, table = solve(owner, initial)
            owner = grow(owner, positions, table)
            initial = np.where(np.isfinite(positions), positions, initial)
    lap("triangulate")
    if len(positions) == 0:
        return _finish_empty(detections, frame, clock)

    # Final checks: drop particles built from merged regions, too few or clustered
    # views, or residuals far above the typical one; release their centroids to the
    # others and solve once more.
    owner, positions, table = solve(owner, initial)
    tried = np.zeros(len(positions), dtype=bool)
    for _check in range(3):
        bad, refit = _inconsistent(positions, table, owner, view, views, st, radius_px,
                                   lf.view_mask, lf.u, lf.v, dlfc, locator)
        # A particle seen in many views whose only fault is a high residual has part of
        # its centroids pulled by overlapping images: refit it on its best half first.
        refit &= ~tried
        if refit.any():
            tried |= refit
            owner, positions = _trim_refit(dlfc, st, view, views, owner, positions,
                                           np.flatnonzero(refit), locator.min_views,
                                           locator.add_tolerance_px)
            table.loc[refit, "residual_px"] = np.nan   # grow within add_tolerance_px only
            bad &= ~refit
        if not bad.any() and not refit.any():
            break
        owner = np.where(bad[np.maximum(owner, 0)] & (owner >= 0), -1, owner)
        positions = np.where(bad[:, None], np.nan, positions)
        table.loc[bad, "n_views"] = 0
        owner = grow(owner, positions, table)
        initial = np.where(np.isfinite(positions), positions, initial)
        owner, positions, table = solve(owner, initial)
    keep = ((table["n_views"].to_numpy() >= locator.min_views)
            & np.all(np.isfinite(positions), axis=1))
    owner = np.where(keep[np.maximum(owner, 0)] & (owner >= 0), owner, -1)
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
    lap("checks")
    if len(particles) == 0:
        return _finish_empty(detections, frame, clock)
    return LocateResult(particles=particles, detections=detections, stage_seconds=clock)


def _segment(lf, frame: int, locator: PerspectiveLocator) -> pd.DataFrame:
    """Detections of every valid view, merged regions split into their dark cores."""
    kw = dict(frame=frame, window=locator.window, area_range=locator.area_range,
              max_eccentricity=locator.max_eccentricity)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        detections = segment_views(lf, contrast=locator.contrast, **kw)
        if locator.core_contrast is not None and len(detections):
            cores = segment_views(lf, contrast=locator.core_contrast,
                                  **{**kw, "area_range": (1.0, math.inf),
                                     "max_eccentricity": 1.0})
            detections = _split_merged(detections, cores)
    if len(detections) and locator.max_view_ratio is not None:
        # A view with far more regions than the typical view is dominated by noise (a
        # dim, partly vignetted rim view): its regions would only inflate k and the
        # pool of false centroids.
        _, view_of, counts = np.unique(detections[["v", "u"]].to_numpy(float), axis=0,
                                       return_inverse=True, return_counts=True)
        noisy = counts > locator.max_view_ratio * np.median(counts)
        if noisy.any():
            detections = detections[~noisy[view_of.ravel()]]
    if len(detections) and locator.split_pairs:
        detections = _split_pairs(detections, locator.max_area_ratio,
                                  locator.merged_elongation)
    return detections.reset_index(drop=True)


def _split_pairs(detections: pd.DataFrame, max_area_ratio: float,
                 elongation: float) -> pd.DataFrame:
    """Replace large elongated regions by the two particle images they are made of.

    A region larger than ``max_area_ratio`` times the median area and more elongated
    than ``elongation`` (major over minor axis) is taken for the merged image of two
    equal particles. Two discs of radius ``r`` with centres ``c +- a e`` have second
    moments ``r^2 / 4 + a^2`` along ``e`` and ``r^2 / 4`` across it, so
    ``a = sqrt(l1 - l2)`` from the region's moments (``l = (axis / 4)^2``), ``e`` is its
    major axis and ``2 r`` its minor axis. Each half gets half the area and a round
    shape of the minor-axis diameter.
    """
    if "whole" not in detections.columns:
        detections = detections.assign(whole=True)
    area = detections["area"].to_numpy(float)
    major = detections["major_axis_px"].to_numpy(float)
    minor = detections["minor_axis_px"].to_numpy(float)
    pair = (area > max_area_ratio * np.median(area)) & (major > elongation * minor)
    if not pair.any():
        return detections.assign(split_pair=False)
    src = detections[pair]
    half = np.sqrt(np.maximum((major[pair] / 4) ** 2 - (minor[pair] / 4) ** 2, 0.0))
    theta = src["orientation"].to_numpy(float)
    ds, dt = half * np.cos(theta), half * np.sin(theta)
    halves = []
    for sign in (-1.0, 1.0):
        h = src.copy()
        h["s"] = src["s"].to_numpy(float) + sign * ds
        h["t"] = src["t"].to_numpy(float) + sign * dt
        h["area"] = np.maximum(np.round(src["area"].to_numpy(float) / 2), 1).astype(
            detections["area"].dtype)
        h["diameter_px"] = np.sqrt(4.0 * h["area"].to_numpy(float) / math.pi)
        h["major_axis_px"] = minor[pair]
        h["eccentricity"] = 0.0
        h["dark_area"] = src["dark_area"].to_numpy(float) / 2
        h["split_pair"] = True
        h["whole"] = False
        halves.append(h)
    out = pd.concat([detections[~pair].assign(split_pair=False), *halves], ignore_index=True)
    return out.sort_values(["v", "u"], kind="stable").reset_index(drop=True)


def _inconsistent(positions, table, owner, view, views, st, radius_px, view_mask, u_all,
                  v_all, dlfc, locator) -> np.ndarray:
    """(P,) mask of particles that fail the final consistency checks.

    A particle fails when it has fewer than ``min_views`` centroids; when the views of
    its centroids span less than ``min_aperture_spread`` of the aperture (RMS distance
    from their mean ``(u, v)`` against that of all valid views); when its RMS residual
    exceeds ``max_residual_ratio`` times the median over all particles; or when, in
    more than ``max_explained`` of its views, two other particles are predicted on its
    centroid (a particle made of merged images of two others).
    """
    n_v = table["n_views"].to_numpy()
    ok = np.all(np.isfinite(positions), axis=1) & (n_v > 0)
    bad = ok & (n_v < locator.min_views)
    mine = owner >= 0
    own = owner[mine]
    cnt = np.maximum(np.bincount(own, minlength=len(positions)), 1)
    uu = views[view[mine], 0]
    vv = views[view[mine], 1]
    mu = np.bincount(own, uu, minlength=len(positions)) / cnt
    mv = np.bincount(own, vv, minlength=len(positions)) / cnt
    spread = np.sqrt(np.bincount(own, (uu - mu[own]) ** 2 + (vv - mv[own]) ** 2,
                                 minlength=len(positions)) / cnt)
    vg, ug = np.meshgrid(v_all, u_all, indexing="ij")
    ua, va = ug[view_mask], vg[view_mask]
    full = np.sqrt(np.mean((ua - ua.mean()) ** 2 + (va - va.mean()) ** 2))
    bad |= ok & (spread < locator.min_aperture_spread * full)
    res = table["residual_px"].to_numpy()
    typical = np.nanmedian(res[ok]) if ok.any() else np.nan
    res_bad = ok & (res > max(locator.max_residual_ratio * typical, locator.add_tolerance_px))
    pred = _predict_all(dlfc, positions, views)
    frac = _explained_by_others(pred, st, view, owner, radius_px, ok & ~bad & ~res_bad)
    strong = n_v >= 0.25 * view_mask.sum()
    bad |= ok & (frac > np.where(strong, locator.max_explained_strong, locator.max_explained))
    return bad | res_bad, res_bad & ~bad & strong


def _trim_refit(dlfc, st, view, views, owner, positions, particles, min_views: int,
                tolerance_px: float):
    """Refit particles on the better half of their centroids (least trimmed squares).

    From the current position, the half of a particle's centroids (at least
    ``min_views``) nearest their predictions are solved for a new position, and the
    step is repeated until the position settles. Centroids farther than
    ``tolerance_px`` from the final predictions are released (owner -1).

    Returns
    -------
    owner : (M,) int ndarray
    positions : (P, 3) float ndarray
        Updated copies.
    """
    owner = owner.copy()
    positions = positions.copy()
    # Rows of each listed particle, found once (a refit releases only its own rows).
    members = np.flatnonzero(np.isin(owner, particles))
    members = members[np.argsort(owner[members], kind="stable")]
    first = np.searchsorted(owner[members], particles, side="left")
    last = np.searchsorted(owner[members], particles, side="right")
    for k, lo, hi in zip(particles, first, last, strict=True):
        rows = members[lo:hi]
        pos = positions[k].copy()
        if len(rows) < 2 * min_views or not np.all(np.isfinite(pos)):
            continue
        uv = views[view[rows]]
        n_keep = max(min_views, len(rows) // 2)
        for _ in range(8):
            s, t = dlfc.predict(pos[0], pos[1], pos[2], uv[:, 0], uv[:, 1])
            best = np.argsort(np.hypot(st[rows, 0] - s, st[rows, 1] - t))[:n_keep]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", NoParticlesWarning)
                tri = triangulate_cluster(dlfc, uv[best, 0], uv[best, 1], st[rows[best], 0],
                                          st[rows[best], 1], pos, reject_k=np.inf,
                                          min_views=min_views)
            new = tri.positions[0]
            if not np.all(np.isfinite(new)):
                break
            settled = np.max(np.abs(new - pos)) < 1e-4
            pos = new
            if settled:
                break
        s, t = dlfc.predict(pos[0], pos[1], pos[2], uv[:, 0], uv[:, 1])
        owner[rows[np.hypot(st[rows, 0] - s, st[rows, 1] - t) > tolerance_px]] = -1
        positions[k] = pos
    return owner, positions


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


def _finish_empty(detections: pd.DataFrame, frame: int, clock=None) -> LocateResult:
    warnings.warn(f"frame {frame}: no particles found", NoParticlesWarning, stacklevel=3)
    detections = detections.assign(particle=np.full(len(detections), -1, dtype=np.int64),
                                   inlier=np.zeros(len(detections), dtype=bool))
    return LocateResult(particles=_empty_particles(), detections=detections,
                        stage_seconds=dict(clock or {}))
