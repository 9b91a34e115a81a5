"""The locator steps as they were before they were made linear in the number of
particles (copied unchanged): the steps that compare every particle with every other
particle, every centroid or every k-means centre (the check for particles made of
merged images recomputing every fraction over all pairs after each particle it drops),
and the triangulation that re-tests every centroid in every outlier-rejection round. :class:`ImageSpans` rules out no
particle, so that the split and hidden-particle checks compare every particle's images
with every other's in every view, as they did; :func:`_robust_sd` takes
:func:`numpy.median` twice, as it did; the decode's sampling geometry and lens centres
are computed afresh on every call, as they were before they were cached per grid.

They are the independent reference of ``test_perspective_steps.py``,
``test_cluster.py`` and ``test_triangulate.py`` and the baseline of
``benchmarks/bench_locate.py --scaling``.
"""
# ruff: noqa: PLR1730

import importlib
import math
import warnings

import numba
import numpy as np

from plenoptrack.errors import NoParticlesWarning, SettingsError
from plenoptrack.locate._assign import _MERGED, _predict_all
from plenoptrack.locate.triangulate import (
    _MAD_TO_SIGMA,
    _SOLVERS,
    _ClusterModel,
    _summarise,
    triangulate_cluster,
)

REPLACED = {
    "plenoptrack.locate.perspective": ("_add_centroids", "_merge_duplicates",
                                       "_release_unclaimed", "_explained_away",
                                       "_trim_refit", "ImageSpans"),
    "plenoptrack.locate.refine": ("_robust_sd",),
    "plenoptrack.lightfield.decode": ("_sampling", "_lens_centres"),
    "plenoptrack.locate.cluster": ("_lloyd", "_kmeanspp_topup"),
    "plenoptrack.locate.triangulate": ("_triangulate",),
}
"""Module -> names of the locator that this module's versions of the same name replace
(the tests and the benchmark put back all of them)."""


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
        at most one centroid per view (the nearest).
    """
    owner = owner.copy()
    n_p, n_v = pred.shape[:2]
    ok = np.all(np.isfinite(pred[:, 0]), axis=1)
    if not ok.any():
        return owner
    has = np.zeros((n_p, n_v), dtype=bool)
    mine = owner >= 0
    has[owner[mine], view[mine]] = True
    tol = np.maximum(tolerance_px, 3.0 * np.nan_to_num(residual, nan=tolerance_px))
    rank = np.argsort(-np.nan_to_num(confidence, nan=-np.inf), kind="stable")
    rank = rank[ok[rank]]
    free = np.flatnonzero(owner == -1)
    order = np.argsort(view[free], kind="stable")
    free = free[order]
    bounds = np.searchsorted(view[free], np.arange(n_v + 1))
    for w in np.unique(view[free]):
        rows = free[bounds[w]:bounds[w + 1]]
        cand = rank[~has[rank, w]]
        if len(cand) == 0:
            continue
        d = np.hypot(st[rows, None, 0] - pred[None, cand, w, 0],
                     st[rows, None, 1] - pred[None, cand, w, 1])
        within = d <= tol[cand][None, :]
        if not within.any():
            continue
        taken = np.zeros(len(rows), dtype=bool)
        for c in np.flatnonzero(within.any(axis=0)):  # most confident particle first
            hits = np.flatnonzero(within[:, c] & ~taken)
            if len(hits):
                h = hits[np.argmin(d[hits, c])]
                taken[h] = True
                owner[rows[h]] = cand[c]
    return owner

def _merge_duplicates(pred: np.ndarray, st: np.ndarray, view: np.ndarray, owner: np.ndarray,
                      n_views: np.ndarray, merge_px: float) -> np.ndarray:
    """Merge particles whose predictions coincide in most views.

    Two particles are the same when the median distance between their predicted
    positions over all views is at most ``merge_px``. The one with fewer centroids is
    merged into the other: the centroids of both are pooled and, in each view, the one
    nearest the surviving particle's prediction is kept (the others are released).

    Returns
    -------
    (M,) int ndarray
        Updated owners.
    """
    ok = np.flatnonzero(np.all(np.isfinite(pred[:, 0]), axis=1) & (n_views > 0))
    if len(ok) < 2:
        return owner
    p = pred[ok]
    d = np.median(np.hypot(p[:, None, :, 0] - p[None, :, :, 0],
                           p[:, None, :, 1] - p[None, :, :, 1]), axis=2)
    np.fill_diagonal(d, np.inf)
    if not (d <= merge_px).any():
        return owner
    owner = owner.copy()
    target = np.arange(len(pred))
    strength = n_views[ok]
    for a in np.argsort(-strength, kind="stable"):
        if target[ok[a]] != ok[a]:
            continue
        for b in np.flatnonzero(d[a] <= merge_px):
            if target[ok[b]] == ok[b] and strength[b] <= strength[a]:
                target[ok[b]] = ok[a]
    merged = np.flatnonzero(target != np.arange(len(pred)))
    survivors = np.unique(target[merged])
    mine = owner >= 0
    owner[mine] = target[owner[mine]]
    for k in survivors:
        rows = np.flatnonzero(owner == k)
        dist = np.hypot(st[rows, 0] - pred[k, view[rows], 0], st[rows, 1] - pred[k, view[rows], 1])
        order = np.lexsort((dist, view[rows]))
        rows, vw = rows[order], view[rows][order]
        first = np.r_[True, vw[1:] != vw[:-1]]
        owner[rows[~first]] = -1
    return owner

def _release_unclaimed(dlfc, positions, views, st, view, owner, radius_px, round_,
                          halves=None, tolerance_px=1.0, area=None, max_area_ratio=np.inf):
    """Return held regions that no located particle accounts for to the pool.

    A region taken for a merged image (owner ``_MERGED``) that is round and has no
    located particle predicted inside it (within ``radius_px``) is the image of one
    particle near the camera, larger than the typical image; it is released (owner -1)
    so that the next clustering pass can find that particle. A held half of a split pair
    is released when no prediction claims it (the region nearest a prediction, at
    ``d``, and every region within ``2 d + tolerance_px`` that it lies inside).
    """
    halves = np.zeros(len(owner), dtype=bool) if halves is None else halves
    rows = np.flatnonzero((owner == _MERGED) & (round_ | halves))
    ok = np.all(np.isfinite(positions), axis=1)
    if len(rows) == 0 or not ok.any():
        return owner
    pred = _predict_all(dlfc, positions[ok], views)                      # (P, V, 2)
    claimed = np.zeros(len(owner), dtype=bool)
    any_inside = np.zeros(len(owner), dtype=bool)
    for v in range(len(views)):   # every region against every prediction, view by view
        here = np.flatnonzero(view == v)
        d = np.hypot(st[here, None, 0] - pred[None, :, v, 0],
                     st[here, None, 1] - pred[None, :, v, 1])                # (M_v, P)
        inside = d <= radius_px[here, None]
        near = np.where(inside, d, np.inf).min(axis=0, initial=np.inf)
        claimed[here] = (inside & (d <= 2.0 * near + tolerance_px)).any(axis=1)
        any_inside[here] = inside.any(axis=1)
    release = np.zeros(len(owner), dtype=bool)
    release[rows] = np.where(halves[rows], ~claimed[rows], ~any_inside[rows])
    owner_in = owner
    owner = owner.copy()
    owner[release] = -1
    if area is None:
        return owner
    # a round held region with one particle predicted inside, on its centroid, of that
    # particle's own regions' size: its own image (when it has more of them than own)
    located = np.flatnonzero(ok)
    candidate = {}
    for r in np.flatnonzero((owner_in == _MERGED) & round_ & ~halves):
        d = np.hypot(st[r, 0] - pred[:, view[r], 0], st[r, 1] - pred[:, view[r], 1])
        inside = np.flatnonzero(d <= radius_px[r])
        if len(inside) != 1 or d[inside[0]] > tolerance_px:
            continue
        p = located[inside[0]]
        own = owner_in == p
        if own.any() and area[r] <= max_area_ratio * np.median(area[own]):
            candidate[r] = p
    for r, p in candidate.items():
        n_held = sum(1 for q in candidate.values() if q == p)
        taken = np.any((owner == p) & (view == view[r]))
        if n_held >= np.sum(owner_in == p) and not taken:
            owner[r] = p
    return owner

def _explained_by_others(pred: np.ndarray, st: np.ndarray, view: np.ndarray,
                         owner: np.ndarray, radius_px: np.ndarray, ok: np.ndarray
                         ) -> np.ndarray:
    """Fraction of each particle's centroids that two other particles' predictions fall on.

    A region where the images of two particles merge has its centroid between them; a
    spurious particle built from such regions has both neighbours predicted inside
    (within ``radius_px``, the region radius) of nearly all its centroids.
    """
    n_p = len(pred)
    frac = np.zeros(n_p)
    idx = np.flatnonzero(ok)
    if len(idx) < 3:
        return frac
    mine = np.flatnonzero(owner >= 0)
    own = owner[mine]
    d = np.hypot(st[mine, None, 0] - pred[idx][:, view[mine], 0].T,
                 st[mine, None, 1] - pred[idx][:, view[mine], 1].T)       # (m, K)
    near = d <= radius_px[mine, None]
    near[own[:, None] == idx[None, :]] = False
    hit = near.sum(axis=1) >= 2
    counts = np.bincount(own, minlength=n_p)
    frac = np.bincount(own, hit.astype(float), minlength=n_p) / np.maximum(counts, 1)
    return frac

def _explained_away(pred, st, view, owner, radius_px, ok, judged, limit, strength):
    """Particles explained away (:func:`plenoptrack.locate._assign._explained_away`),
    every fraction computed again over all pairs after each particle that goes."""
    out = np.zeros(len(pred), dtype=bool)
    explains = np.asarray(ok, dtype=bool).copy()
    while True:
        frac = _explained_by_others(pred, st, view, owner, radius_px, explains)
        over = np.flatnonzero(judged & ~out & (frac > limit))
        if len(over) == 0:
            return out
        weakest = over[np.lexsort((over, strength[over]))[0]]
        out[weakest] = True
        explains[weakest] = False


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
    for k in particles:
        rows = np.flatnonzero(owner == k)
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


@numba.njit(cache=True)
def _nearest_two(px, py, centres):  # pragma: no cover - compiled
    """Index of the nearest centre and distances to the nearest and second nearest."""
    best = 0
    d1 = np.inf
    d2 = np.inf
    for c in range(centres.shape[0]):
        dx = px - centres[c, 0]
        dy = py - centres[c, 1]
        d = dx * dx + dy * dy
        if d < d1:
            d2 = d1
            d1 = d
            best = c
        elif d < d2:
            d2 = d
    return best, math.sqrt(d1), math.sqrt(d2)


@numba.njit(cache=True)
def _lloyd(points, centres, max_iter):  # pragma: no cover - compiled
    """Lloyd iterations from ``centres`` (modified in place); return labels (n,).

    Each point keeps an upper bound on the distance to its centre and a lower bound on
    the distance to every other centre (Hamerly's bounds); the full search over the
    centres runs only for points whose bounds no longer prove the assignment, so the
    labels are those of plain Lloyd iterations at a fraction of the cost.
    """
    n = points.shape[0]
    k = centres.shape[0]
    labels = np.full(n, -1, dtype=np.int64)
    upper = np.empty(n)
    lower = np.empty(n)
    sums = np.empty((k, 2))
    counts = np.empty(k)
    shift = np.zeros(k)
    half_gap = np.zeros(k)
    for it in range(max_iter):
        changed = False
        for i in range(n):
            if it > 0:
                lab = labels[i]
                m = max(half_gap[lab], lower[i])
                if upper[i] <= m:
                    continue
                dx = points[i, 0] - centres[lab, 0]
                dy = points[i, 1] - centres[lab, 1]
                upper[i] = math.sqrt(dx * dx + dy * dy)
                if upper[i] <= m:
                    continue
            best, d1, d2 = _nearest_two(points[i, 0], points[i, 1], centres)
            upper[i] = d1
            lower[i] = d2
            if labels[i] != best:
                labels[i] = best
                changed = True
        if not changed:
            break
        sums[:, :] = 0.0
        counts[:] = 0.0
        for i in range(n):
            sums[labels[i], 0] += points[i, 0]
            sums[labels[i], 1] += points[i, 1]
            counts[labels[i]] += 1.0
        max_shift = 0.0
        for c in range(k):
            shift[c] = 0.0
            if counts[c] > 0:  # an empty cluster keeps its centre
                nx = sums[c, 0] / counts[c]
                ny = sums[c, 1] / counts[c]
                shift[c] = math.sqrt((nx - centres[c, 0]) ** 2 + (ny - centres[c, 1]) ** 2)
                centres[c, 0] = nx
                centres[c, 1] = ny
            if shift[c] > max_shift:
                max_shift = shift[c]
        for c in range(k):
            g = np.inf
            for c2 in range(k):
                if c2 != c:
                    d = (centres[c, 0] - centres[c2, 0]) ** 2 + (centres[c, 1] - centres[c2, 1]) ** 2
                    if d < g:
                        g = d
            half_gap[c] = 0.5 * math.sqrt(g)
        for i in range(n):
            upper[i] += shift[labels[i]]
            lower[i] -= max_shift
    return labels


@numba.njit(cache=True)
def _kmeanspp_topup(points, centres, n_extra, uniforms):  # pragma: no cover - compiled
    """Append up to ``n_extra`` k-means++ draws (one uniform each) to ``centres``."""
    n = points.shape[0]
    k0 = centres.shape[0]
    out = np.empty((k0 + n_extra, 2))
    out[:k0] = centres
    d2 = np.full(n, np.inf)
    for i in range(n):
        for c in range(k0):
            d = (points[i, 0] - centres[c, 0]) ** 2 + (points[i, 1] - centres[c, 1]) ** 2
            if d < d2[i]:
                d2[i] = d
    if k0 == 0:
        d2[:] = 1.0
    m = k0
    for e in range(n_extra):
        total = 0.0
        for i in range(n):
            total += d2[i]
        if not total > 0:
            break
        target = uniforms[e] * total
        acc = 0.0
        pick = n - 1
        for i in range(n):
            acc += d2[i]
            if acc > target:
                pick = i
                break
        out[m, 0] = points[pick, 0]
        out[m, 1] = points[pick, 1]
        m += 1
        for i in range(n):
            d = (points[i, 0] - points[pick, 0]) ** 2 + (points[i, 1] - points[pick, 1]) ** 2
            if d < d2[i]:
                d2[i] = d
    return out[:m]


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
    while active.any():
        p, conv = _SOLVERS[solver](model, keep, positions, active, max_iter)
        positions[active] = p[active]
        converged[active] = conv[active]
        err = np.hypot(*model.residuals(positions).T)
        new_out = _outliers(err, model, keep, n_k, reject_k, min_views, min_threshold_px)
        new_out &= can_reject[labels]
        if not new_out.any():
            break
        keep &= ~new_out
        active = np.bincount(labels[new_out], minlength=n_k) > 0
        rejected_any |= active
    return _summarise(model, cluster_ids, positions, keep, converged, solvable, rejected_any,
                      min_views, n_possible_views, volume_depth_mm)


@numba.njit(cache=True)
def _robust_thresholds(err, order, bounds, keep, k_sigma, floor):  # pragma: no cover
    """Per-cluster ``max(median + k_sigma * MAD, floor)`` of ``err`` over kept rows
    (NaN for clusters without kept rows or with a NaN median)."""
    n_k = len(bounds) - 1
    out = np.full(n_k, np.nan)
    buf = np.empty(len(err))
    for k in range(n_k):
        m = 0
        for r in range(bounds[k], bounds[k + 1]):
            i = order[r]
            if keep[i]:
                buf[m] = err[i]
                m += 1
        if m == 0:
            continue
        med = np.median(buf[:m])
        if np.isnan(med):
            continue
        mad = np.median(np.abs(buf[:m] - med))
        out[k] = max(med + k_sigma * mad, floor)
    return out


def _outliers(err, model, keep, n_k, reject_k, min_views, min_threshold_px) -> np.ndarray:
    """(M,) mask of kept centroids to reject now, never leaving fewer than ``min_views``."""
    labels = model.labels
    threshold = _robust_thresholds(err, model.order, model.bounds, keep,
                                   reject_k * _MAD_TO_SIGMA, min_threshold_px)
    with np.errstate(invalid="ignore"):
        cand = np.flatnonzero(keep & (err > threshold[labels]))
    if cand.size == 0:
        return np.zeros(len(err), dtype=bool)
    allowed = np.maximum(np.bincount(labels[keep], minlength=n_k) - min_views, 0)
    order = np.lexsort((-err[cand], labels[cand]))      # worst first within each cluster
    cand = cand[order]
    cl = labels[cand]
    first = np.searchsorted(cl, cl, side="left")
    rank = np.arange(len(cand)) - first
    out = np.zeros(len(err), dtype=bool)
    out[cand[rank < allowed[cl]]] = True
    return out


class ImageSpans:
    """:class:`plenoptrack.locate._nearby.ImageSpans` that rules out nothing: every
    particle is near every image, so its callers compare every view of every pair."""

    def __init__(self, pred):
        self.n = len(pred)

    def set_rows(self, rows, pred):
        pass

    def extended(self, pred):
        out = ImageSpans(())
        out.n = self.n + len(pred)
        return out

    def subset(self, rows):
        out = ImageSpans(())
        out.n = len(np.arange(self.n)[rows])
        return out

    def near(self, pred, reach):
        return np.ones(self.n, dtype=bool)

    def meet(self, pred, image, reach):
        reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), (self.n,))
        gap = np.hypot(*(np.asarray(pred) - np.asarray(image)[None]).transpose(2, 0, 1))
        with np.errstate(invalid="ignore"):
            return np.any(gap < reach[:, None], axis=1)

    def __len__(self):
        return self.n


def _robust_sd(values: np.ndarray) -> float:
    """``median(|x - median(x)|) / 0.6745`` of a 1-D array: the standard deviation of a
    normal sample, robust to outliers (scipy's ``median_abs_deviation(x, scale="normal")``
    without its per-call overhead, which is most of the cost on patch-sized arrays)."""
    return float(np.median(np.abs(values - np.median(values))) / 0.6744897501960817)


_sampling = importlib.import_module("plenoptrack.lightfield.decode")._sampling.__wrapped__
"""The decode's sampling geometry without its per-grid cache."""


def _lens_centres(grid):
    """Every lens centre of ``grid``, computed afresh."""
    return grid.centers()
