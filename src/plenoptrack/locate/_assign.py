"""Assigning centroids to particles: the array steps of the perspective-shift locator.

Each function works on plain arrays over the detections of one frame:

- ``st`` (M, 2) float: measured centroids ``(s, t)``, view pixels;
- ``view`` (M,) int: index of each centroid's view into ``views`` (V, 2), the views'
  ``(u, v)``;
- ``owner`` (M,) int: particle row of each centroid, -1 unassigned, :data:`_MERGED` for
  regions held back as merged images of several particles;
- ``positions`` (P, 3) float: particle positions ``(x, y, z)``, mm (NaN rows for
  particles without a solution); ``pred`` (P, V, 2) float: their predicted centroids in
  every view (:func:`_predict_all`).

The steps return updated copies and never modify their inputs.
"""

from __future__ import annotations

import warnings

import numba
import numpy as np
import pandas as pd

from ..errors import NoParticlesWarning
from ._nearby import pairs_within
from .triangulate import triangulate_cluster

_MERGED = -2  # owner of regions taken for merged images of several particles


def _predict_all(dlfc, positions: np.ndarray, views: np.ndarray) -> np.ndarray:
    """(P, V, 2) predicted ``(s, t)`` of every particle in every view; NaN rows for
    particles without a finite position."""
    out = np.full((len(positions), len(views), 2), np.nan)
    ok = np.all(np.isfinite(positions), axis=1)
    if ok.any() and len(views):
        out[ok] = dlfc.predict_in_views(positions[ok], dlfc.view_basis(views[:, 0], views[:, 1]))
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


def _release_unclaimed(dlfc, positions, views, st, view, owner, radius_px, round_,
                       halves=None, tolerance_px: float = 1.0, area=None,
                       max_area_ratio: float = np.inf):
    """Return held regions that no located particle accounts for to the pool.

    A region taken for a merged image (owner ``_MERGED``) that is round and has no
    located particle predicted inside it (within ``radius_px``) is the image of one
    particle near the camera, larger than the typical image; it is released (owner -1)
    so that the next clustering pass can find that particle. A round held region with
    exactly one located particle predicted inside it, within ``tolerance_px`` of its
    centroid and no larger than ``max_area_ratio`` times the median ``area`` of the
    regions the particle owns, is that particle's own image when the particle has more
    such regions than regions of its own (a particle larger than the frame's typical
    one, in a frame of mixed sizes): it joins that particle where the particle has no
    region in its view yet. A held half of a split pair
    (``halves``) is released when no located particle claims it: in each view a particle
    claims the region nearest its prediction, at distance ``d``, and every region within
    ``2 d + tolerance_px`` (among the regions it is predicted inside). One particle
    predicted between the two halves of its own elongated image claims both; the half
    that a located particle predicted on the other half leaves is the image of another
    particle, however close the two images are.
    """
    halves = np.zeros(len(owner), dtype=bool) if halves is None else halves
    rows = np.flatnonzero((owner == _MERGED) & (round_ | halves))
    ok = np.all(np.isfinite(positions), axis=1)
    if len(rows) == 0 or not ok.any():
        return owner
    pred = _predict_all(dlfc, positions[ok], views)                       # (P, V, 2)
    n_p, n_v = pred.shape[:2]
    q, d, dist = pairs_within(st, view, radius_px, pred.reshape(-1, 2),
                              np.tile(np.arange(n_v), n_p))
    inside = np.bincount(q, minlength=len(owner)) > 0
    # Each prediction claims the region nearest it and any region nearly as near: a
    # particle predicted between the two halves of its own elongated image claims both.
    nearest = np.full(n_p * n_v, np.inf)
    np.minimum.at(nearest, d, dist)
    claimed = np.zeros(len(owner), dtype=bool)
    claimed[q[dist <= 2.0 * nearest[d] + tolerance_px]] = True
    released = owner.copy()
    released[rows[np.where(halves[rows], ~claimed[rows], ~inside[rows])]] = -1
    if area is not None:
        region, particle = _own_images(q, np.flatnonzero(ok)[d // n_v], dist, owner, view,
                                       round_ & ~halves, area, max_area_ratio, tolerance_px)
        released[region] = particle
    return released


def _own_images(region, particle, dist, owner, view, round_, area, max_area_ratio: float,
                tolerance_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The held regions that are a located particle's own image (:func:`_release_unclaimed`).

    Parameters
    ----------
    region, particle, dist : (k,) ndarrays
        Every (region, particle predicted inside it) pair, grouped by region, and the
        prediction's distance from the region's centroid, view pixels.
    owner, view, round_, area : (M,) ndarrays
        Owner (``_MERGED`` for held regions), view index, roundness and area of every
        region.

    Returns
    -------
    region, particle : (j,) int ndarrays
        The held round regions with one particle predicted inside them, within
        ``tolerance_px`` of their centroid and no larger than ``max_area_ratio`` times the
        median area of that particle's own regions, for the particles with at least as
        many of them as regions of their own (an image larger than the frame's typical
        one, not one some of whose views merge with another particle's image); at most
        one per particle and view, none where the particle has a region already.
    """
    n_inside = np.bincount(region, minlength=len(owner))
    pick = ((n_inside[region] == 1) & (owner[region] == _MERGED) & round_[region]
            & (dist <= tolerance_px))
    region, particle = region[pick], particle[pick]
    has = owner >= 0
    area = np.asarray(area, dtype=float)
    own_area = pd.Series(area[has]).groupby(owner[has]).median()
    like_own = area[region] <= max_area_ratio * own_area.reindex(particle).to_numpy()
    region, particle = region[like_own], particle[like_own]     # NaN: no regions of its own
    n = int(max(owner.max(initial=-1), particle.max(initial=-1))) + 1
    large = (np.bincount(particle, minlength=n)[particle]
             >= np.bincount(owner[has], minlength=n)[particle])
    region, particle = region[large], particle[large]
    n_v = int(view.max(initial=-1)) + 1
    key = particle * n_v + view[region]
    first = np.zeros(len(key), dtype=bool)
    first[np.unique(key, return_index=True)[1]] = True
    free = first & ~np.isin(key, owner[has] * n_v + view[has])
    return region[free], particle[free]
    return owner


def _explained_away(pred: np.ndarray, st: np.ndarray, view: np.ndarray, owner: np.ndarray,
                    radius_px: np.ndarray, ok: np.ndarray, judged: np.ndarray,
                    limit: np.ndarray, strength: np.ndarray) -> np.ndarray:
    """(P,) bool: the particles made of merged images of others, weakest first.

    A particle is explained away when, in more than ``limit`` (P,) of its views, two
    other particles are predicted inside its region (within ``radius_px`` of its
    centroid): a region where two particles' images merge has its centroid between them,
    and a spurious particle built from such regions has both neighbours predicted on
    nearly all its centroids. Only the particles ``ok`` explain others (none while fewer
    than three do), and only those ``judged`` are judged.

    Several particles on nearly one line of sight can each lie between two of the
    others: one real particle and the ghosts built from what is left of its merged
    image all explain each other, and judged together all of them go. So they are
    judged one at a time, the one with the least ``strength`` (its number of views)
    first: a particle explained away no longer explains the others, and the rest are
    judged again without it (the counts of the centroids it explained updated, not
    recomputed).
    """
    n_p, n_v = pred.shape[:2]
    out = np.zeros(n_p, dtype=bool)
    idx = np.flatnonzero(ok)
    if len(idx) < 3:
        return out
    mine = np.flatnonzero(owner >= 0)
    own = owner[mine]
    q, d, _ = pairs_within(st[mine], view[mine], radius_px[mine], pred[idx].reshape(-1, 2),
                           np.tile(np.arange(n_v), len(idx)))
    by = idx[d // n_v]
    other = by != own[q]
    q, by = q[other], by[other]
    hits = np.bincount(q, minlength=len(mine))            # others predicted on each centroid
    counts = np.maximum(np.bincount(own, minlength=n_p), 1)
    n_hit = np.bincount(own, (hits >= 2).astype(float), minlength=n_p)
    explains = ok.copy()
    order = np.argsort(by, kind="stable")                   # each explainer's centroids
    start = np.searchsorted(by[order], np.arange(n_p + 1))
    while np.count_nonzero(explains) >= 3:
        over = np.flatnonzero(judged & ~out & (n_hit / counts > limit))
        if len(over) == 0:
            return out
        weakest = over[np.lexsort((over, strength[over]))[0]]
        out[weakest] = True
        if not explains[weakest]:
            continue
        explains[weakest] = False
        cents = q[order[start[weakest]:start[weakest + 1]]]
        lost = cents[hits[cents] == 2]                      # they fall below two others
        hits[cents] -= 1
        np.subtract.at(n_hit, own[lost], 1.0)
    return out


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
