"""3D particle location from clustered view detections through the DLFC.

Each particle is seen as a cluster of centroids ``(u_i, v_i, s_i, t_i)``, one per view
it was found in. Its object-space position solves the non-linear least-squares problem::

    min over (x, y, z) of  sum_i | P(x, y, z, u_i, v_i) - (s_i, t_i) |^2

with ``P = (P_s, P_t)`` the Direct Light Field Calibration (:mod:`.dlfc`). Centroids whose
reprojection error is far above the others' are rejected and the position re-solved
until none is rejected (section 2.3 of the method paper). Each particle then gets
standard uncertainties from the Jacobian at the solution, its residuals, and the
confidence value of the paper's eq. (3).

Two solvers give the same answers: ``"lm"`` (default) runs a Levenberg-Marquardt
iteration on all particles at once; each particle's 3 x 3 normal equations come from
moments of its view monomials (the DLFC regrouped as a polynomial in ``(u, v)``), so an
iteration costs the same however many views a particle has; ``"scipy"`` calls :func:`scipy.optimize.least_squares` once per particle
with the analytic Jacobian (about 100 times slower for 200 particles seen in 149
views: ~15 s against ~0.1 s; kept as a reference).

References
----------
Development and uncertainty characterization of 3D particle location from perspective
shifted plenoptic images (Optical Society of America, 2019), sections 2.3 and 2.4.
"""

from __future__ import annotations

import enum
import warnings
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from .._columns import LF_COLUMNS, POS_COLUMNS
from ..errors import NoParticlesWarning, SettingsError
from ._order import median
from .dlfc import DLFC, _coefficients_one

__all__ = [
    "Triangulation", "TriangulationFlag", "FLAG_DESCRIPTIONS", "triangulate_cluster",
    "triangulate_clusters", "predict_detection", "confidence",
]

_MAD_TO_SIGMA = 1.4826   # MAD of a normal distribution times this is its sigma
_SINGULAR_COND = 1e12    # condition number of J^T J above which sigma is not reported


class TriangulationFlag(enum.IntFlag):
    """Quality bits of a triangulated particle (``Triangulation.flags``, uint8)."""

    CONVERGED = 1
    TOO_FEW_VIEWS = 2
    OUTLIERS_REMOVED = 4
    AT_VOLUME_EDGE = 8
    SINGULAR = 16
    REFINED = 32
    UNEXPLAINED = 64
    SPLIT = 128


FLAG_DESCRIPTIONS = {
    TriangulationFlag.CONVERGED: "the least-squares solve met its step tolerance",
    TriangulationFlag.TOO_FEW_VIEWS: "fewer centroids than min_views (no outlier rejection); "
                                     "with fewer than 2 the position is NaN",
    TriangulationFlag.OUTLIERS_REMOVED: "at least one centroid was rejected as an outlier",
    TriangulationFlag.AT_VOLUME_EDGE: "the position lies outside the x, y or z range the DLFC "
                                      "was fitted on (the polynomial extrapolates)",
    TriangulationFlag.SINGULAR: "J^T J is (nearly) singular or there are no residual degrees "
                                "of freedom: sigma is NaN",
    TriangulationFlag.REFINED: "position and sigma come from the image-model refinement "
                               "(the particle's image was fitted to the view pixels), not "
                               "from the centroid solve",
    TriangulationFlag.UNEXPLAINED: "an image fit could not explain the pixels around the "
                                   "particle (model error above "
                                   "check.refine_max_model_error) and no split took them "
                                   "apart: an unseen or merged neighbour is likely; the "
                                   "position is the centroid solve's, its sigma widened "
                                   "by the model error",
    TriangulationFlag.SPLIT: "one of two particles on nearly one line of sight that had been "
                             "taken for one: the image-model refinement separated them "
                             "(check.split_merged); position, sigma and size come from "
                             "the two-particle image fit",
}
"""What each :class:`TriangulationFlag` bit means."""


@dataclass(frozen=True, eq=False)
class Triangulation:
    """Triangulated particles, one row per cluster.

    Attributes
    ----------
    clusters : (N,) ndarray
        Cluster label of each particle, sorted ascending.
    positions : (N, 3) float64 ndarray
        Position as columns x, y, z, mm (NaN when it could not be solved).
    sigma : (N, 3) float64 ndarray
        Standard uncertainties of x, y, z, mm, from ``cov = s^2 (J^T J)^-1`` with
        ``s^2 = SSR / (2 n - 3)`` over the kept centroids.
    residual_px : (N,) float64 ndarray
        RMS reprojection error ``sqrt(mean_i |r_i|^2)`` over the kept centroids,
        view pixels (``r_i`` = measured minus predicted ``(s, t)``).
    mean_residual_px : (N,) float64 ndarray
        Mean reprojection error ``mean_i |r_i|`` (the ``d`` of the confidence).
    n_views : (N,) int64 ndarray
        Number of centroids kept.
    confidence : (N,) float64 ndarray
        Confidence of eq. (3), see :func:`confidence`; NaN if not requested.
    flags : (N,) uint8 ndarray
        Bitmask of :class:`TriangulationFlag`.
    inliers : (M,) bool ndarray
        For every input detection (in input order), whether it was kept.
    """

    clusters: np.ndarray
    positions: np.ndarray
    sigma: np.ndarray
    residual_px: np.ndarray
    mean_residual_px: np.ndarray
    n_views: np.ndarray
    confidence: np.ndarray
    flags: np.ndarray
    inliers: np.ndarray

    def __len__(self) -> int:
        return len(self.clusters)

    def to_frame(self) -> pd.DataFrame:
        """One row per particle.

        Returns
        -------
        DataFrame
            Columns ``cluster``; ``x, y, z`` (mm); ``sigma_x, sigma_y, sigma_z`` (mm);
            ``n_views``; ``residual_px`` and ``mean_residual_px`` (view pixels);
            ``confidence``; ``flags`` (uint8, :class:`TriangulationFlag`).
        """
        x, y, z = POS_COLUMNS
        return pd.DataFrame({
            "cluster": self.clusters,
            x: self.positions[:, 0], y: self.positions[:, 1], z: self.positions[:, 2],
            f"sigma_{x}": self.sigma[:, 0], f"sigma_{y}": self.sigma[:, 1],
            f"sigma_{z}": self.sigma[:, 2],
            "n_views": self.n_views, "residual_px": self.residual_px,
            "mean_residual_px": self.mean_residual_px, "confidence": self.confidence,
            "flags": self.flags,
        })


# --- public functions ----------------------------------------------------------------

def predict_detection(dlfc: DLFC, xyz, u, v) -> tuple[np.ndarray, np.ndarray]:
    """Where particle(s) at ``xyz`` appear in view(s) ``(u, v)``.

    Used to add centroids to a particle in views where clustering found none: compare
    the prediction with the unassigned detections of each view.

    Parameters
    ----------
    dlfc : DLFC
        Volumetric calibration.
    xyz : (..., 3) array_like
        Positions as x, y, z, mm.
    u, v : array_like
        Views, sensor pixels; broadcast against ``xyz[..., 0]``, e.g. ``xyz[:, None]``
        with ``u[None, :]`` predicts every particle in every view.

    Returns
    -------
    s, t : float ndarray
        Predicted in-view column and row, view pixels, of the broadcast shape.
    """
    xyz = np.asarray(xyz, dtype=float)
    if xyz.shape[-1:] != (3,):
        raise SettingsError(f"xyz must have shape (..., 3) (x, y, z in mm); got {xyz.shape}")
    return dlfc.predict(xyz[..., 0], xyz[..., 1], xyz[..., 2], u, v)


def confidence(n_views, n_possible_views, mean_residual_px, z_mm, volume_depth_mm, *,
               z_floor: float = 0.05, d_floor_px: float = 1e-3) -> np.ndarray:
    """Confidence of a triangulated particle, eq. (3) of the method paper.

    ``C = (n_v / n_p) / (d / z_n)`` with ``n_v`` the centroids kept, ``n_p`` the views
    available, ``d`` the mean reprojection error (view pixels) and ``z_n`` the depth from
    the nominal focal plane divided by the volume depth.

    Parameters
    ----------
    n_views : array_like of int
        Centroids kept per particle, ``n_v``.
    n_possible_views : int or array_like
        Views in which the particle could have been found, ``n_p``.
    mean_residual_px : array_like of float
        Mean reprojection error ``d``, view pixels.
    z_mm : array_like of float
        Depth, mm (``z = 0`` at the nominal focal plane).
    volume_depth_mm : float
        Depth extent of the measurement volume, mm.
    z_floor : float, default 0.05
        Smallest ``z_n`` used (fraction of the volume depth).
    d_floor_px : float, default 1e-3
        Smallest ``d`` used, view pixels.

    Returns
    -------
    float ndarray
        ``C``, of the broadcast shape (larger is better; NaN where an input is NaN).

    Notes
    -----
    Taken literally the formula is singular: ``z_n`` vanishes on the nominal focal
    plane, so every in-focus particle would get ``C = 0`` however good its data (and
    ``C`` changes sign with ``z``), while ``d -> 0`` (noise-free data) sends ``C`` to
    infinity. The paper's motive is that centroid scatter grows away from focus, so
    ``d`` is compared with ``|z|``. Here ``z_n = max(|z| / volume_depth, z_floor)`` and
    ``d`` is replaced by ``max(d, d_floor_px)``: particles within
    ``z_floor * volume_depth`` of focus are all ranked as if they sat at that distance,
    and ``C`` is always finite and non-negative. ``C`` is only meaningful for ranking
    particles of one image (as the paper uses it, to order centroid addition); its
    absolute value depends on these floors and on the volume depth.
    """
    z_n = np.maximum(np.abs(np.asarray(z_mm, dtype=float)) / float(volume_depth_mm), z_floor)
    d = np.maximum(np.asarray(mean_residual_px, dtype=float), d_floor_px)
    fraction = np.asarray(n_views, dtype=float) / np.asarray(n_possible_views, dtype=float)
    return fraction / (d / z_n)


def triangulate_cluster(dlfc: DLFC, u, v, s, t, x0, *, n_possible_views: int | None = None,
                        volume_depth_mm: float | None = None, reject_k: float = 3.0,
                        min_views: int = 4, min_threshold_px: float = 0.05,
                        max_iter: int = 50, solver: Literal["lm", "scipy"] = "lm"
                        ) -> Triangulation:
    """Locate one particle from its centroids in several views.

    Parameters
    ----------
    dlfc : DLFC
        Volumetric calibration.
    u, v : (n,) array_like
        Views of the centroids, sensor pixels from the microlens-image centre.
    s, t : (n,) array_like
        Measured in-view centroid column and row, view pixels.
    x0 : (3,) array_like
        Initial guess x, y, z, mm (e.g. from the refocus plane of the cluster).
    n_possible_views, volume_depth_mm, reject_k, min_views, min_threshold_px, max_iter, solver
        As for :func:`triangulate_clusters`.

    Returns
    -------
    Triangulation
        One particle (cluster label 0); ``inliers`` has one entry per centroid.
    """
    u, v, s, t = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (u, v, s, t))
    _check_same_length(u=u, v=v, s=s, t=t)
    x0 = np.asarray(x0, dtype=float)
    if x0.shape != (3,):
        raise SettingsError(f"x0 must be 3 numbers (x, y, z in mm); got shape {x0.shape}")
    labels = np.zeros(len(u), dtype=np.int64)
    return _triangulate(dlfc, u, v, s, t, labels, np.array([0]), x0[None], n_possible_views,
                        volume_depth_mm, reject_k, min_views, min_threshold_px, max_iter, solver)


def triangulate_clusters(dlfc: DLFC, detections: pd.DataFrame, initial_xyz, *,
                         cluster_column: str = "cluster", n_possible_views: int | None = None,
                         volume_depth_mm: float | None = None, reject_k: float = 3.0,
                         min_views: int = 4, min_threshold_px: float = 0.05,
                         max_iter: int = 50, solver: Literal["lm", "scipy"] = "lm"
                         ) -> Triangulation:
    """Locate every clustered particle of a detections table.

    Parameters
    ----------
    dlfc : DLFC
        Volumetric calibration.
    detections : DataFrame
        One row per centroid with columns ``u, v`` (sensor pixels), ``s, t`` (view
        pixels) and ``cluster_column``. Rows with a missing or negative cluster label
        (unassigned centroids) are ignored.
    initial_xyz : DataFrame or (K, 3) array_like
        Starting positions, mm: a DataFrame indexed by cluster label with columns
        ``x, y, z``, or an array with one row per cluster in ascending label order.
    cluster_column : str, default "cluster"
        Column holding the cluster label of each centroid.
    n_possible_views : int, optional
        Views available to find a particle in (``n_p`` of the confidence). Without it the
        confidence is NaN.
    volume_depth_mm : float, optional
        Depth extent of the measurement volume for the confidence; defaults to the z
        range of the DLFC fit.
    reject_k : float, default 3
        A centroid is an outlier if its reprojection error exceeds
        ``max(median + reject_k * 1.4826 * MAD, min_threshold_px)`` over the particle's
        kept centroids. ``inf`` disables rejection.
    min_views : int, default 4
        Rejection never leaves fewer centroids than this (the worst go first); clusters
        with fewer are solved without rejection and flagged ``TOO_FEW_VIEWS``.
    min_threshold_px : float, default 0.05
        Smallest rejection threshold, view pixels, so that nearly noise-free clusters do
        not lose good centroids to a tiny MAD.
    max_iter : int, default 50
        Iteration limit of each least-squares solve.
    solver : {"lm", "scipy"}, default "lm"
        Batched Levenberg-Marquardt over all particles, or one
        :func:`scipy.optimize.least_squares` call per particle.

    Returns
    -------
    Triangulation
        One row per cluster, ascending label; ``inliers`` is aligned with the rows of
        ``detections`` (ignored rows are False). An empty table gives an empty result
        and a :class:`~plenoptrack.errors.NoParticlesWarning`.
    """
    missing = [c for c in (*LF_COLUMNS, cluster_column) if c not in detections.columns]
    if missing:
        raise SettingsError(f"detections lack column(s) {missing}; need u, v, s, t and "
                         f"{cluster_column!r}")
    raw_labels = detections[cluster_column].to_numpy()
    usable = pd.notna(raw_labels)
    if np.issubdtype(np.asarray(raw_labels).dtype, np.number):
        usable &= np.asarray(raw_labels, dtype=float) >= 0
    rows = np.flatnonzero(usable)
    uniq, labels = np.unique(raw_labels[rows], return_inverse=True)
    x0 = _initial_positions(initial_xyz, uniq)
    u, v, s, t = (detections[c].to_numpy(dtype=float)[rows] for c in LF_COLUMNS)
    result = _triangulate(dlfc, u, v, s, t, labels, uniq, x0, n_possible_views,
                          volume_depth_mm, reject_k, min_views, min_threshold_px, max_iter,
                          solver)
    inliers = np.zeros(len(detections), dtype=bool)
    inliers[rows] = result.inliers
    return Triangulation(**{**result.__dict__, "inliers": inliers})


# --- argument checks ---------------------------------------------------------------

def _check_same_length(**arrays) -> None:
    lengths = {k: len(a) for k, a in arrays.items()}
    if len(set(lengths.values())) != 1:
        raise SettingsError(f"u, v, s and t must have the same length; got {lengths}")


def _initial_positions(initial_xyz, labels: np.ndarray) -> np.ndarray:
    """(K, 3) starting positions in the order of ``labels``."""
    if isinstance(initial_xyz, pd.DataFrame):
        absent = [lab for lab in labels.tolist() if lab not in initial_xyz.index]
        if absent:
            raise SettingsError(f"initial_xyz has no row for cluster(s) {absent[:10]}; index it "
                             "by cluster label")
        return initial_xyz.loc[labels, list(POS_COLUMNS)].to_numpy(dtype=float)
    x0 = np.asarray(initial_xyz, dtype=float)
    if x0.shape != (len(labels), 3):
        raise SettingsError(f"initial_xyz must have shape ({len(labels)}, 3), one row per "
                         f"cluster in ascending label order; got {x0.shape}")
    return x0


# --- the solve -----------------------------------------------------------------------

def _triangulate(dlfc, u, v, s, t, labels, cluster_ids, x0, n_possible_views,
                 volume_depth_mm, reject_k, min_views, min_threshold_px, max_iter, solver):
    """Solve, reject outliers and re-solve until stable; then uncertainty and flags."""
    if solver not in ("lm", "scipy"):
        raise SettingsError(f"solver must be 'lm' or 'scipy'; got {solver!r}")
    if min_views < 2:
        raise SettingsError(f"min_views must be at least 2 (3 unknowns, 2 equations per view); "
                         f"got {min_views}")
    if not reject_k > 0:
        raise SettingsError(f"reject_k must be positive (np.inf disables rejection); got {reject_k!r}")
    n_k = len(cluster_ids)
    bad_start = ~np.all(np.isfinite(x0), axis=1)
    if bad_start.any():
        raise SettingsError(f"initial position is NaN or infinite for cluster(s) "
                         f"{np.asarray(cluster_ids)[bad_start][:10].tolist()}; give a finite "
                         "starting guess (x, y, z in mm) for every cluster")
    if n_k == 0:
        warnings.warn("no clustered detections to triangulate; returning an empty result",
                      NoParticlesWarning, stacklevel=3)
    obs = np.column_stack([s, t]) if len(s) else np.zeros((0, 2))
    keep = np.ones(len(u), dtype=bool)
    n_start = np.bincount(labels, minlength=n_k)
    solvable = n_start >= 2
    positions = np.where(solvable[:, None], x0, np.nan)
    converged = np.zeros(n_k, dtype=bool)
    active = solvable.copy()
    rejected_any = np.zeros(n_k, dtype=bool)
    can_reject = n_start > min_views
    model = _ClusterModel(dlfc, u, v, obs, labels, n_k)
    err = np.full(len(u), np.nan)
    while active.any():
        p, conv = _SOLVERS[solver](model, keep, positions, active, max_iter)
        positions[active] = p[active]
        converged[active] = conv[active]
        # Only the clusters just solved can lose centroids: the others kept their
        # positions and centroids, and found no outlier last round.
        clusters = np.flatnonzero(active)
        rows = model.rows_of(clusters)
        err[rows] = np.hypot(*model.residuals(positions, clusters, rows).T)
        out = _outliers(err, model, keep, clusters, rows, reject_k, min_views,
                        min_threshold_px)
        out = out[can_reject[labels[out]]]
        if len(out) == 0:
            break
        keep[out] = False
        active = np.bincount(labels[out], minlength=n_k) > 0
        rejected_any |= active
    return _summarise(model, cluster_ids, positions, keep, converged, solvable, rejected_any,
                      min_views, n_possible_views, volume_depth_mm)


@numba.njit(cache=True)
def _robust_thresholds(err, order, bounds, keep, clusters, k_sigma, floor):  # pragma: no cover
    """Per-cluster ``max(median + k_sigma * MAD, floor)`` of ``err`` over kept rows, for
    ``clusters`` (NaN for the others, for clusters without kept rows or with a NaN
    median)."""
    n_k = len(bounds) - 1
    out = np.full(n_k, np.nan)
    buf = np.empty(len(err))
    for k in clusters:
        m = 0
        for r in range(bounds[k], bounds[k + 1]):
            i = order[r]
            if keep[i]:
                buf[m] = err[i]
                m += 1
        if m == 0:
            continue
        med = median(buf[:m])
        if np.isnan(med):
            continue
        mad = median(np.abs(buf[:m] - med))
        out[k] = max(med + k_sigma * mad, floor)
    return out


def _outliers(err, model, keep, clusters, rows, reject_k, min_views,
              min_threshold_px) -> np.ndarray:
    """Kept centroids of ``clusters`` to reject now, never leaving fewer than ``min_views``.

    ``rows`` are the rows of ``clusters`` (:meth:`_ClusterModel.rows_of`). Returns row
    indices, worst first within each cluster.
    """
    labels = model.labels
    threshold = _robust_thresholds(err, model.order, model.bounds, keep, clusters,
                                   reject_k * _MAD_TO_SIGMA, min_threshold_px)
    lab = labels[rows]
    with np.errstate(invalid="ignore"):
        cand = rows[keep[rows] & (err[rows] > threshold[lab])]
    if cand.size == 0:
        return cand
    allowed = np.maximum(np.bincount(lab[keep[rows]], minlength=model.n_k) - min_views, 0)
    # Worst first within each cluster; rows come grouped by cluster and ascending within,
    # so ties keep the ascending row order.
    order = np.lexsort((-err[cand], labels[cand]))
    cand = cand[order]
    cl = labels[cand]
    first = np.searchsorted(cl, cl, side="left")
    rank = np.arange(len(cand)) - first
    return cand[rank < allowed[cl]]


@numba.njit(cache=True)
def _normal_one(pos, k, mom, wo, oo, ref, xyz_e, tensor, centre, scale, powers, c, dc, mdc,
                jtj, jtr):  # pragma: no cover - compiled
    """J^T J and J^T r of cluster ``k`` at ``pos`` (written into ``jtj``, ``jtr``); returns
    the residual sum of squares."""
    n_b = tensor.shape[1]
    _coefficients_one(pos, xyz_e, tensor, centre, scale, powers, c, dc)
    c[0, 0] -= ref[k, 0]
    c[0, 1] -= ref[k, 1]
    ssr = oo[k]
    for d in range(3):
        jtr[d] = 0.0
    for b in range(n_b):
        for ch in range(2):
            mc = 0.0
            for b2 in range(n_b):
                mc += mom[k, b, b2] * c[b2, ch]
            ssr += c[b, ch] * (mc - 2.0 * wo[k, b, ch])
            g = mc - wo[k, b, ch]
            for d in range(3):
                jtr[d] += dc[d, b, ch] * g
    for d in range(3):
        for b in range(n_b):
            for ch in range(2):
                acc = 0.0
                for b2 in range(n_b):
                    acc += mom[k, b, b2] * dc[d, b2, ch]
                mdc[d, b, ch] = acc
    for d in range(3):
        for e in range(d, 3):
            acc = 0.0
            for b in range(n_b):
                for ch in range(2):
                    acc += dc[d, b, ch] * mdc[e, b, ch]
            jtj[d, e] = acc
            jtj[e, d] = acc
    return max(ssr, 0.0)


@numba.njit(cache=True)
def _normal_kernel(positions, idx, mom, wo, oo, ref, xyz_e, tensor, centre,
                   scale):  # pragma: no cover - compiled
    """J^T J (k, 3, 3), J^T r (k, 3) and SSR (k,) of clusters ``idx`` at ``positions``."""
    n_b = tensor.shape[1]
    top = xyz_e.max()
    powers = np.empty((3, top + 1))
    c = np.empty((n_b, 2))
    dc = np.empty((3, n_b, 2))
    mdc = np.empty((3, n_b, 2))
    jtj = np.zeros((len(idx), 3, 3))
    jtr = np.zeros((len(idx), 3))
    ssr = np.zeros(len(idx))
    for r in range(len(idx)):
        ssr[r] = _normal_one(positions[r], idx[r], mom, wo, oo, ref, xyz_e, tensor, centre,
                             scale, powers, c, dc, mdc, jtj[r], jtr[r])
    return jtj, jtr, ssr


@numba.njit(cache=True)
def _solve3(a, b):  # pragma: no cover - compiled
    """Solution of the 3 x 3 system ``a x = b`` (Gaussian elimination, partial pivoting)."""
    m = a.copy()
    x = b.copy()
    for col in range(3):
        piv = col
        for r in range(col + 1, 3):
            if abs(m[r, col]) > abs(m[piv, col]):
                piv = r
        if piv != col:
            for j in range(3):
                m[col, j], m[piv, j] = m[piv, j], m[col, j]
            x[col], x[piv] = x[piv], x[col]
        for r in range(col + 1, 3):
            f = m[r, col] / m[col, col]
            for j in range(col, 3):
                m[r, j] -= f * m[col, j]
            x[r] -= f * x[col]
    for r in range(2, -1, -1):
        acc = x[r]
        for j in range(r + 1, 3):
            acc -= m[r, j] * x[j]
        x[r] = acc / m[r, r]
    return x


@numba.njit(cache=True)
def _lm_kernel(p, idx, mom, wo, oo, ref, xyz_e, tensor, centre, scale, max_iter, xtol,
               ftol, converged):  # pragma: no cover - compiled
    """Levenberg-Marquardt on each cluster of ``idx`` from ``p[k]`` (updated in place)."""
    n_b = tensor.shape[1]
    top = xyz_e.max()
    powers = np.empty((3, top + 1))
    c = np.empty((n_b, 2))
    dc = np.empty((3, n_b, 2))
    mdc = np.empty((3, n_b, 2))
    jtj = np.empty((3, 3))
    jtr = np.empty(3)
    t_jtj = np.empty((3, 3))
    t_jtr = np.empty(3)
    damped = np.empty((3, 3))
    trial = np.empty(3)
    for k in idx:
        cost = _normal_one(p[k], k, mom, wo, oo, ref, xyz_e, tensor, centre, scale, powers,
                           c, dc, mdc, jtj, jtr)
        lam = 1e-3
        for _ in range(max_iter):
            tr = jtj[0, 0] + jtj[1, 1] + jtj[2, 2]
            for i in range(3):
                for j in range(3):
                    damped[i, j] = jtj[i, j]
                damped[i, i] += lam * jtj[i, i] + 1e-12 * tr + 1e-300
            step = -_solve3(damped, jtr)
            for j in range(3):
                trial[j] = p[k, j] + step[j]
            t_cost = _normal_one(trial, k, mom, wo, oo, ref, xyz_e, tensor, centre, scale,
                                 powers, c, dc, mdc, t_jtj, t_jtr)
            if t_cost <= cost:
                gain = cost - t_cost
                cost = t_cost
                for i in range(3):
                    p[k, i] = trial[i]
                    jtr[i] = t_jtr[i]
                    for j in range(3):
                        jtj[i, j] = t_jtj[i, j]
                lam /= 10.0
                big = max(abs(step[0]), abs(step[1]), abs(step[2]))
                if big <= xtol or gain <= ftol * max(cost, 1e-300):
                    converged[k] = True
                    break
            else:
                lam *= 10.0
                if lam > 1e12:
                    break


@numba.njit(cache=True)
def _moments_kernel(w, obs, labels, keep, rows, n_k):  # pragma: no cover - compiled
    """``M`` (K, B, B), ``b`` (K, B, 2), ``sum |o|^2`` (K,) over the kept centroids among
    ``rows`` (zero for clusters without any)."""
    n_b = w.shape[1]
    mom = np.zeros((n_k, n_b, n_b))
    wo = np.zeros((n_k, n_b, 2))
    oo = np.zeros(n_k)
    for i in rows:
        k = labels[i]
        if not keep[i]:
            continue
        o0, o1 = obs[i, 0], obs[i, 1]
        oo[k] += o0 * o0 + o1 * o1
        for b in range(n_b):
            wb = w[i, b]
            wo[k, b, 0] += wb * o0
            wo[k, b, 1] += wb * o1
            for b2 in range(b, n_b):
                mom[k, b, b2] += wb * w[i, b2]
    for k in range(n_k):
        for b in range(n_b):
            for b2 in range(b + 1, n_b):
                mom[k, b2, b] = mom[k, b, b2]
    return mom, wo, oo


@numba.njit(cache=True)
def _residual_kernel(positions, clusters, rows, w, obs, labels, ref, xyz_e, tensor, centre,
                     scale):  # pragma: no cover - compiled
    """(len(rows), 2) measured minus predicted ``(s, t)`` of the centroids ``rows``, all of
    which belong to ``clusters``."""
    n_k = positions.shape[0]
    n_b = tensor.shape[1]
    top = xyz_e.max()
    powers = np.empty((3, top + 1))
    coef = np.empty((n_k, n_b, 2))
    no_deriv = np.empty((0, n_b, 2))
    for k in clusters:
        _coefficients_one(positions[k], xyz_e, tensor, centre, scale, powers, coef[k],
                          no_deriv)
        coef[k, 0, 0] -= ref[k, 0]
        coef[k, 0, 1] -= ref[k, 1]
    out = np.empty((len(rows), 2))
    for r in range(len(rows)):
        i = rows[r]
        k = labels[i]
        for ch in range(2):
            acc = 0.0
            for b in range(n_b):
                acc += w[i, b] * coef[k, b, ch]
            out[r, ch] = obs[i, ch] - acc
    return out


class _ClusterModel:
    """Per-cluster least-squares problem in the view-factorised form of the DLFC.

    With ``P_c = sum_ab G[a, b, c] X_a(xyz) V_b(u, v)`` (see
    :attr:`DLFC.view_factorisation`), the residuals of cluster ``k`` are
    ``r_i = W_i C_k - o_i`` with ``W_i = V(u_i, v_i)`` fixed per centroid and
    ``C_k = X(p_k) G``. The sums over centroids then reduce to moments
    ``M_k = sum_i W_i W_i^T``, ``b_k = sum_i W_i o_i`` and ``sum_i |o_i|^2``, formed once
    per set of kept centroids, and every iteration costs ``O(K)`` small products however
    many views each particle has. Observations are taken relative to each cluster's mean
    so that the moment form of the residual sum of squares does not cancel digits. The
    products run in compiled kernels, one cluster at a time.
    """

    def __init__(self, dlfc: DLFC, u, v, obs, labels, n_k):
        self.dlfc, self.labels, self.n_k = dlfc, labels, n_k
        self.u, self.v, self.raw_obs = u, v, obs
        xyz_e, _, tensor = dlfc.view_factorisation
        self.xyz_e = np.ascontiguousarray(xyz_e, dtype=np.int64)
        self.tensor = np.ascontiguousarray(tensor, dtype=np.float64)
        self.centre = np.ascontiguousarray(dlfc.centre[:3], dtype=np.float64)
        self.scale = np.ascontiguousarray(dlfc.scale[:3], dtype=np.float64)
        self.w = dlfc.view_basis(u, v)                                     # (M, B)
        counts = np.bincount(labels, minlength=n_k)
        self.ref = np.stack([np.bincount(labels, obs[:, c], minlength=n_k) for c in (0, 1)],
                            axis=1) / np.maximum(counts, 1)[:, None]
        self.obs = np.ascontiguousarray(obs - self.ref[labels])
        self.labels = np.ascontiguousarray(labels, dtype=np.int64)
        self.order = np.argsort(labels, kind="stable")
        self.bounds = np.searchsorted(labels[self.order], np.arange(n_k + 1))

    def rows_of(self, clusters: np.ndarray) -> np.ndarray:
        """Rows of the centroids of ``clusters`` (ascending labels), grouped by cluster
        in the order of ``clusters`` and ascending within each."""
        clusters = np.asarray(clusters, dtype=np.int64)
        lo = self.bounds[clusters]
        n = self.bounds[clusters + 1] - lo
        offset = np.repeat(lo - (np.cumsum(n) - n), n)
        return self.order[offset + np.arange(offset.size)]

    def moments(self, keep: np.ndarray, clusters: np.ndarray):
        """``M`` (K, B, B), ``b`` (K, B, 2), ``sum |o|^2`` (K,) over kept centroids of
        ``clusters`` (zero for the other clusters)."""
        return _moments_kernel(self.w, self.obs, self.labels, np.asarray(keep, dtype=bool),
                               self.rows_of(clusters), self.n_k)

    def normal_equations(self, positions, idx, moments):
        """J^T J (k, 3, 3), J^T r (k, 3) and SSR (k,) of clusters ``idx``.

        ``positions`` (k, 3) are the positions of those clusters; ``moments`` come from
        :meth:`moments` (all clusters).
        """
        mom, wo, oo = moments
        return _normal_kernel(np.ascontiguousarray(positions, dtype=np.float64),
                              np.asarray(idx, dtype=np.int64), mom, wo, oo, self.ref,
                              self.xyz_e, self.tensor, self.centre, self.scale)

    def residuals(self, positions, clusters=None, rows=None) -> np.ndarray:
        """Measured minus predicted (s, t), view pixels: (M, 2) for every centroid, or
        (len(rows), 2) for ``rows``, the rows of ``clusters`` (:meth:`rows_of`)."""
        if clusters is None:
            clusters, rows = np.arange(self.n_k), np.arange(len(self.labels))
        return _residual_kernel(np.ascontiguousarray(positions, dtype=np.float64),
                                np.asarray(clusters, dtype=np.int64),
                                np.asarray(rows, dtype=np.int64), self.w, self.obs,
                                self.labels, self.ref, self.xyz_e, self.tensor,
                                self.centre, self.scale)


def _solve_lm(model: _ClusterModel, keep, start, active, max_iter, *,
              xtol_mm: float = 1e-6, ftol: float = 1e-10):
    """Levenberg-Marquardt on each cluster marked ``active``.

    Each iteration takes the damped step ``(A + lam diag(A)) d = -g`` from the
    cluster's 3 x 3 normal equations and keeps it where the cost drops (``lam / 10``)
    or undoes it (``lam * 10``). A cluster stops when an accepted step is below
    ``xtol_mm`` in every coordinate or lowers the cost by less than ``ftol`` relative.
    """
    idx = np.flatnonzero(active).astype(np.int64)
    moments = model.moments(keep, idx)
    p = np.ascontiguousarray(start, dtype=np.float64).copy()
    converged = np.zeros(len(start), dtype=bool)
    _lm_kernel(p, idx, *moments, model.ref, model.xyz_e, model.tensor, model.centre,
               model.scale, int(max_iter), float(xtol_mm), float(ftol), converged)
    return p, converged


def _solve_scipy(model: _ClusterModel, keep, start, active, max_iter):
    """One :func:`scipy.optimize.least_squares` call per active cluster (reference)."""
    dlfc, u, v, obs = model.dlfc, model.u, model.v, model.raw_obs
    p = start.copy()
    converged = np.zeros(len(start), dtype=bool)
    for k in np.flatnonzero(active):
        rows = model.order[model.bounds[k]:model.bounds[k + 1]]
        rows = rows[keep[rows]]
        uk, vk, ok = u[rows], v[rows], obs[rows]

        def fun(x, uk=uk, vk=vk, ok=ok):
            s, t = dlfc.predict(x[0], x[1], x[2], uk, vk)
            return np.concatenate([s - ok[:, 0], t - ok[:, 1]])

        def jac(x, uk=uk, vk=vk):
            j = dlfc.jacobian_xyz(x[0], x[1], x[2], uk, vk)
            return np.concatenate([j[:, 0, :], j[:, 1, :]])

        sol = least_squares(fun, start[k], jac=jac, method="lm", xtol=1e-12, ftol=1e-12,
                            gtol=1e-12, max_nfev=max_iter * 10)
        p[k] = sol.x
        converged[k] = sol.status > 0
    return p, converged


_SOLVERS = {"lm": _solve_lm, "scipy": _solve_scipy}


def _summarise(model: _ClusterModel, cluster_ids, positions, keep, converged, solvable,
               rejected_any, min_views, n_possible_views, volume_depth_mm) -> Triangulation:
    """Uncertainties, residuals, confidence and flags at the final positions."""
    dlfc, labels = model.dlfc, model.labels
    n_k = len(cluster_ids)
    idx = np.flatnonzero(solvable)
    jtj = np.zeros((n_k, 3, 3))
    ssr = np.zeros(n_k)
    if idx.size:
        jtj[idx], _, ssr[idx] = model.normal_equations(positions[idx], idx,
                                                       model.moments(keep, idx))
    n_views = np.bincount(labels[keep], minlength=n_k)
    err = np.hypot(*model.residuals(np.nan_to_num(positions)).T)
    sum_err = np.bincount(labels[keep], err[keep], minlength=n_k)
    with np.errstate(invalid="ignore", divide="ignore"):
        dof = 2 * n_views - 3
        s2 = np.where(dof > 0, ssr / np.maximum(dof, 1), np.nan)
        cov_diag, singular = _inverse_diagonal(jtj)
        sigma = np.sqrt(s2[:, None] * cov_diag)
        residual = np.sqrt(ssr / n_views)
        mean_residual = sum_err / n_views
    singular |= dof <= 0
    sigma[singular | ~solvable] = np.nan
    residual[~solvable] = np.nan
    mean_residual[~solvable] = np.nan
    lo, hi = dlfc.bounds[:, :3]
    outside = np.any((positions < lo) | (positions > hi), axis=1) & solvable
    flags = (converged * TriangulationFlag.CONVERGED
             | (n_views < min_views) * TriangulationFlag.TOO_FEW_VIEWS
             | rejected_any * TriangulationFlag.OUTLIERS_REMOVED
             | outside * TriangulationFlag.AT_VOLUME_EDGE
             | singular * TriangulationFlag.SINGULAR).astype(np.uint8)
    if n_possible_views is None:
        conf = np.full(n_k, np.nan)
    else:
        depth = volume_depth_mm if volume_depth_mm is not None else 2 * dlfc.scale[2]
        conf = confidence(n_views, n_possible_views, mean_residual, positions[:, 2], depth)
    return Triangulation(clusters=np.asarray(cluster_ids), positions=positions, sigma=sigma,
                         residual_px=residual, mean_residual_px=mean_residual,
                         n_views=n_views.astype(np.int64), confidence=conf, flags=flags,
                         inliers=keep.copy())


def _inverse_diagonal(jtj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Diagonal of (J^T J)^-1 per cluster (K, 3) and a (K,) mask of singular systems."""
    n_k = len(jtj)
    diag = np.full((n_k, 3), np.nan)
    if n_k == 0:
        return diag, np.zeros(0, dtype=bool)
    finite = np.all(np.isfinite(jtj), axis=(1, 2))
    cond = np.full(n_k, np.inf)
    cond[finite] = np.linalg.cond(jtj[finite]) if finite.any() else cond[finite]
    ok = cond < _SINGULAR_COND
    if ok.any():
        diag[ok] = np.einsum("kii->ki", np.linalg.inv(jtj[ok]))
    return diag, ~ok
