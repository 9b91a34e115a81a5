"""3D particle location from clustered view detections through the DLFC.

Each particle is seen as a cluster of centroids ``(u_i, v_i, s_i, t_i)``, one per view
it was found in. Its object-space position solves the non-linear least-squares problem

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

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from .._columns import LF_COLUMNS, POS_COLUMNS
from ..errors import NoParticlesWarning
from .dlfc import DLFC

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


FLAG_DESCRIPTIONS = {
    TriangulationFlag.CONVERGED: "the least-squares solve met its step tolerance",
    TriangulationFlag.TOO_FEW_VIEWS: "fewer centroids than min_views (no outlier rejection); "
                                     "with fewer than 2 the position is NaN",
    TriangulationFlag.OUTLIERS_REMOVED: "at least one centroid was rejected as an outlier",
    TriangulationFlag.AT_VOLUME_EDGE: "the position lies outside the x, y or z range the DLFC "
                                      "was fitted on (the polynomial extrapolates)",
    TriangulationFlag.SINGULAR: "J^T J is (nearly) singular or there are no residual degrees "
                                "of freedom: sigma is NaN",
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
        raise ValueError(f"xyz must have shape (..., 3) (x, y, z in mm); got {xyz.shape}")
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
        raise ValueError(f"x0 must be 3 numbers (x, y, z in mm); got shape {x0.shape}")
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
        raise ValueError(f"detections lack column(s) {missing}; need u, v, s, t and "
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
        raise ValueError(f"u, v, s and t must have the same length; got {lengths}")


def _initial_positions(initial_xyz, labels: np.ndarray) -> np.ndarray:
    """(K, 3) starting positions in the order of ``labels``."""
    if isinstance(initial_xyz, pd.DataFrame):
        absent = [lab for lab in labels.tolist() if lab not in initial_xyz.index]
        if absent:
            raise ValueError(f"initial_xyz has no row for cluster(s) {absent[:10]}; index it "
                             "by cluster label")
        return initial_xyz.loc[labels, list(POS_COLUMNS)].to_numpy(dtype=float)
    x0 = np.asarray(initial_xyz, dtype=float)
    if x0.shape != (len(labels), 3):
        raise ValueError(f"initial_xyz must have shape ({len(labels)}, 3), one row per "
                         f"cluster in ascending label order; got {x0.shape}")
    return x0


# --- the solve -----------------------------------------------------------------------

def _triangulate(dlfc, u, v, s, t, labels, cluster_ids, x0, n_possible_views,
                 volume_depth_mm, reject_k, min_views, min_threshold_px, max_iter, solver):
    """Solve, reject outliers and re-solve until stable; then uncertainty and flags."""
    if solver not in ("lm", "scipy"):
        raise ValueError(f"solver must be 'lm' or 'scipy'; got {solver!r}")
    if min_views < 2:
        raise ValueError(f"min_views must be at least 2 (3 unknowns, 2 equations per view); "
                         f"got {min_views}")
    if not reject_k > 0:
        raise ValueError(f"reject_k must be positive (np.inf disables rejection); got {reject_k!r}")
    n_k = len(cluster_ids)
    bad_start = ~np.all(np.isfinite(x0), axis=1)
    if bad_start.any():
        raise ValueError(f"initial position is NaN or infinite for cluster(s) "
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
    while active.any():
        p, conv = _SOLVERS[solver](model, keep, positions, active, max_iter)
        positions[active] = p[active]
        converged[active] = conv[active]
        err = np.hypot(*model.residuals(positions).T)
        new_out = _outliers(err, labels, keep, n_k, reject_k, min_views, min_threshold_px)
        new_out &= can_reject[labels]
        if not new_out.any():
            break
        keep &= ~new_out
        active = np.bincount(labels[new_out], minlength=n_k) > 0
        rejected_any |= active
    return _summarise(model, cluster_ids, positions, keep, converged, solvable, rejected_any,
                      min_views, n_possible_views, volume_depth_mm)


def _group_median(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """Median of ``values`` within each group (NaN for empty groups)."""
    order = np.lexsort((values, groups))
    counts = np.bincount(groups, minlength=n_groups)
    starts = np.cumsum(counts) - counts
    med = np.full(n_groups, np.nan)
    has = counts > 0
    sv = values[order]
    lo = starts[has] + (counts[has] - 1) // 2
    hi = starts[has] + counts[has] // 2
    med[has] = 0.5 * (sv[lo] + sv[hi])
    return med


def _outliers(err, labels, keep, n_k, reject_k, min_views, min_threshold_px) -> np.ndarray:
    """(M,) mask of kept centroids to reject now, never leaving fewer than ``min_views``."""
    idx = np.flatnonzero(keep)
    lab = labels[idx]
    e = err[idx]
    med = _group_median(e, lab, n_k)
    mad = _group_median(np.abs(e - med[lab]), lab, n_k)
    threshold = np.maximum(med + reject_k * _MAD_TO_SIGMA * mad, min_threshold_px)
    cand = idx[e > threshold[lab]]
    if cand.size == 0:
        return np.zeros(len(err), dtype=bool)
    allowed = np.maximum(np.bincount(lab, minlength=n_k) - min_views, 0)
    order = np.lexsort((-err[cand], labels[cand]))      # worst first within each cluster
    cand = cand[order]
    cl = labels[cand]
    first = np.searchsorted(cl, cl, side="left")
    rank = np.arange(len(cand)) - first
    out = np.zeros(len(err), dtype=bool)
    out[cand[rank < allowed[cl]]] = True
    return out


def _powers(values: np.ndarray, top: int) -> np.ndarray:
    """``values ** j`` for ``j = 0 .. top`` along a new last axis, by repeated products."""
    out = np.empty((*values.shape, top + 1))
    out[..., 0] = 1.0
    for j in range(1, top + 1):
        out[..., j] = out[..., j - 1] * values
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
    so that the moment form of the residual sum of squares does not cancel digits.
    """

    def __init__(self, dlfc: DLFC, u, v, obs, labels, n_k):
        self.dlfc, self.labels, self.n_k = dlfc, labels, n_k
        self.u, self.v, self.raw_obs = u, v, obs
        self.xyz_e, uv_e, self.tensor = dlfc.view_factorisation
        un = (u - dlfc.centre[3]) / dlfc.scale[3]
        vn = (v - dlfc.centre[4]) / dlfc.scale[4]
        top = int(uv_e.max())
        self.w = _powers(un, top)[:, uv_e[:, 0]] * _powers(vn, top)[:, uv_e[:, 1]]  # (M, B)
        counts = np.bincount(labels, minlength=n_k)
        self.ref = np.stack([np.bincount(labels, obs[:, c], minlength=n_k) for c in (0, 1)],
                            axis=1) / np.maximum(counts, 1)[:, None]
        self.obs = obs - self.ref[labels]
        self.order = np.argsort(labels, kind="stable")
        self.bounds = np.searchsorted(labels[self.order], np.arange(n_k + 1))

    def moments(self, keep: np.ndarray, clusters: np.ndarray):
        """``M`` (K, B, B), ``b`` (K, B, 2), ``sum |o|^2`` (K,) over kept centroids."""
        n_b = self.w.shape[1]
        mom = np.zeros((self.n_k, n_b, n_b))
        wo = np.zeros((self.n_k, n_b, 2))
        oo = np.zeros(self.n_k)
        for k in clusters:
            rows = self.order[self.bounds[k]:self.bounds[k + 1]]
            rows = rows[keep[rows]]
            wk, ok = self.w[rows], self.obs[rows]
            mom[k] = wk.T @ wk
            wo[k] = wk.T @ ok
            oo[k] = np.sum(ok * ok)
        return mom, wo, oo

    def coefficients(self, positions: np.ndarray, idx: np.ndarray):
        """``C`` (k, B, 2) and ``dC/d(x, y, z)`` (k, 3, B, 2) of clusters ``idx``.

        ``positions`` (k, 3), mm, are the positions of those clusters.
        """
        dlfc, e = self.dlfc, self.xyz_e
        qn = (positions - dlfc.centre[:3]) / dlfc.scale[:3]
        top = int(e.max())
        powers = _powers(qn, top)                                               # (K, 3, n+1)
        f = [powers[:, j, e[:, j]] for j in range(3)]                          # (K, A) each
        df = [e[:, j] * powers[:, j, np.maximum(e[:, j] - 1, 0)] / dlfc.scale[j]
              for j in range(3)]
        x_mono = f[0] * f[1] * f[2]
        dx_mono = np.stack([df[0] * f[1] * f[2], f[0] * df[1] * f[2], f[0] * f[1] * df[2]], 1)
        c = np.einsum("ka,abc->kbc", x_mono, self.tensor)
        c[:, 0, :] -= self.ref[idx]
        dc = np.einsum("kda,abc->kdbc", dx_mono, self.tensor)
        return c, dc

    def normal_equations(self, positions, idx, moments):
        """J^T J (k, 3, 3), J^T r (k, 3) and SSR (k,) of clusters ``idx``.

        ``positions`` (k, 3) and ``moments`` belong to those clusters.
        """
        mom, wo, oo = moments
        c, dc = self.coefficients(positions, idx)
        mc = np.einsum("kij,kjc->kic", mom, c)                                  # M C
        ssr = np.einsum("kic,kic->k", c, mc - 2 * wo) + oo
        g = mc - wo                                                              # M C - b
        jtr = np.einsum("kdic,kic->kd", dc, g)
        jtj = np.einsum("kdic,kij,kejc->kde", dc, mom, dc, optimize=True)
        return jtj, jtr, np.maximum(ssr, 0.0)

    def residuals(self, positions) -> np.ndarray:
        """(M, 2) measured minus predicted (s, t) of every centroid, view pixels."""
        c, _ = self.coefficients(positions, np.arange(self.n_k))
        return self.obs - np.einsum("mb,mbc->mc", self.w, c[self.labels])


def _solve_lm(model: _ClusterModel, keep, start, active, max_iter, *,
              xtol_mm: float = 1e-6, ftol: float = 1e-10):
    """Batched Levenberg-Marquardt on the clusters marked ``active``.

    Each iteration takes the damped step ``(A + lam diag(A)) d = -g`` from each
    cluster's 3 x 3 normal equations and keeps it where the cost drops (``lam / 10``)
    or undoes it (``lam * 10``). A cluster stops when an accepted step is below
    ``xtol_mm`` in every coordinate or lowers the cost by less than ``ftol`` relative.
    """
    n_k = len(start)
    idx_active = np.flatnonzero(active)
    moments = model.moments(keep, idx_active)
    p = start.copy()
    lam = np.full(n_k, 1e-3)
    running = active.copy()
    converged = np.zeros(n_k, dtype=bool)
    sub = idx_active
    mom_sub = tuple(m[sub] for m in moments)
    jtj, jtr, cost = (np.zeros((n_k, 3, 3)), np.zeros((n_k, 3)), np.zeros(n_k))
    jtj[sub], jtr[sub], cost[sub] = model.normal_equations(p[sub], sub, mom_sub)
    for _ in range(max_iter):
        idx = np.flatnonzero(running)
        if idx.size == 0:
            break
        a = jtj[idx]
        diag = np.einsum("kii->ki", a)
        damping = lam[idx, None] * diag + 1e-12 * diag.sum(1, keepdims=True) + 1e-300
        step = -np.linalg.solve(a + damping[:, :, None] * np.eye(3), jtr[idx][:, :, None])[..., 0]
        trial = p[idx] + step
        t_jtj, t_jtr, t_cost = model.normal_equations(trial, idx,
                                                      tuple(m[idx] for m in moments))
        better = t_cost <= cost[idx]
        acc = idx[better]
        p[acc], jtj[acc], jtr[acc] = trial[better], t_jtj[better], t_jtr[better]
        gain = cost[acc] - t_cost[better]
        cost[acc] = t_cost[better]
        lam[idx] = np.where(better, lam[idx] / 10, lam[idx] * 10)
        done = np.zeros(n_k, dtype=bool)
        done[acc] = (np.abs(step[better]).max(axis=1) <= xtol_mm) \
            | (gain <= ftol * np.maximum(cost[acc], 1e-300))
        converged |= done
        running &= ~done & (lam <= 1e12)
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
        moments = tuple(m[idx] for m in model.moments(keep, idx))
        jtj[idx], _, ssr[idx] = model.normal_equations(positions[idx], idx, moments)
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
