"""Fixed-radius neighbours among points of perspective views, view by view.

Points are in-view positions ``(s, t)`` (view pixels) tagged with the index of their
view; points of different views are never neighbours. :func:`pairs_within` finds, for
every query point, the data points of its view within the query's own radius, in time
proportional to the number of points and of pairs found (not to their product), so that
the steps of the locator that compare particles with centroids or with each other stay
linear in the number of particles.

:class:`ImageSpans` does the same for whole particles: from where each particle's
images lie across the views (their mean position and the farthest any of them lies
from it) it names the particles whose image can come within a distance of another's
in some view, so that the exact test over every view runs only for those.
"""

from __future__ import annotations

import numba
import numpy as np

from ._order import stable_argsort

__all__ = ["pairs_within", "ImageSpans"]

_SLACK = 1e-9            # relative widening of the search box; the exact test follows


@numba.njit(cache=True)
def _bucket(cell, s, n_cells):  # pragma: no cover - compiled
    """Order of the data by cell and, within a cell, by ``s``; cell ``c`` holds
    ``order[start[c]:start[c + 1]]``."""
    n = len(cell)
    start = np.zeros(n_cells + 1, dtype=np.int64)
    for i in range(n):
        start[cell[i] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    order = np.empty(n, dtype=np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    for c in range(n_cells):
        if start[c + 1] - start[c] > 1:
            seg = order[start[c]:start[c + 1]].copy()
            by_s = stable_argsort(s[seg])
            for a in range(len(seg)):
                order[start[c] + a] = seg[by_s[a]]
    return order, start


@numba.njit(cache=True)
def _scan(q_s, q_t, q_view, reach, start, s_sorted, t_sorted, t_min, height,
          n_bands):  # pragma: no cover - compiled
    """Query and (sorted) data indices of the data points inside each query's box
    ``|ds| <= reach``, ``|dt| <= reach`` in its view.

    The data are sorted by cell ``view * n_bands + band`` (bands of height ``height`` in
    ``t`` from ``t_min``), cell ``c`` holding ``start[c]:start[c + 1]``, and then by
    ``s``: a query visits the cells its box covers and, in each, the run of ``s`` inside
    the box found by bisection.
    """
    n_views = (len(start) - 1) // n_bands
    cap = max(16, len(q_s))
    out_q = np.empty(cap, dtype=np.int64)
    out_d = np.empty(cap, dtype=np.int64)
    n = 0
    for i in range(len(q_s)):
        if q_view[i] >= n_views:
            continue
        r = reach[i]
        lo = (q_t[i] - r - t_min) / height
        hi = (q_t[i] + r - t_min) / height
        if hi < 0.0 or lo >= n_bands:
            continue
        lo = max(lo, 0.0)
        hi = min(hi, n_bands - 1.0)
        s_lo = q_s[i] - r
        s_hi = q_s[i] + r
        for cell in range(q_view[i] * n_bands + int(lo), q_view[i] * n_bands + int(hi) + 1):
            b0 = start[cell]
            b1 = start[cell + 1]
            if b0 == b1:
                continue
            j = b0 + np.searchsorted(s_sorted[b0:b1], s_lo)
            while j < b1 and s_sorted[j] <= s_hi:
                if abs(t_sorted[j] - q_t[i]) <= r:
                    if n == cap:
                        cap *= 2
                        grown_q = np.empty(cap, dtype=np.int64)
                        grown_d = np.empty(cap, dtype=np.int64)
                        for a in range(n):
                            grown_q[a] = out_q[a]
                            grown_d[a] = out_d[a]
                        out_q, out_d = grown_q, grown_d
                    out_q[n] = i
                    out_d[n] = j
                    n += 1
                j += 1
    return out_q[:n], out_d[:n]


def pairs_within(query_st: np.ndarray, query_view: np.ndarray, radius,
                 data_st: np.ndarray, data_view: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (query, data) pair of one view whose distance is at most the query's radius.

    Parameters
    ----------
    query_st : (n, 2) float ndarray
        Query points ``(s, t)``, view pixels.
    query_view : (n,) int ndarray
        View index (>= 0) of each query point.
    radius : float or (n,) float ndarray
        Search radius of each query point, view pixels.
    data_st : (m, 2) float ndarray
        Data points ``(s, t)``, view pixels.
    data_view : (m,) int ndarray
        View index (>= 0) of each data point.

    Returns
    -------
    query_index, data_index : (k,) int64 ndarray
        The pairs, grouped by query index in ascending order (data in no set order).
    distance : (k,) float64 ndarray
        ``np.hypot`` of the coordinate differences (query minus data), view pixels.

    Notes
    -----
    A pair is returned exactly when ``distance <= radius`` with ``distance`` computed as
    above, as a dense ``(n, m)`` comparison would decide it: points with a non-finite
    coordinate and queries with a NaN or negative radius have no neighbours, and an
    infinite radius reaches every finite point of the view. The data are sorted once by
    view, band of ``t`` (about the median radius high) and ``s``; each query bisects the
    bands its box covers, and the candidates in the box are then tested exactly.
    """
    query_st = np.asarray(query_st, dtype=np.float64).reshape(-1, 2)
    data_st = np.asarray(data_st, dtype=np.float64).reshape(-1, 2)
    query_view = np.asarray(query_view, dtype=np.int64)
    data_view = np.asarray(data_view, dtype=np.int64)
    radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(query_st),))
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    q_ok = np.flatnonzero(np.all(np.isfinite(query_st), axis=1) & (radius >= 0))
    d_ok = np.flatnonzero(np.all(np.isfinite(data_st), axis=1))
    if len(q_ok) == 0 or len(d_ok) == 0:
        return empty
    d_st = data_st[d_ok]
    d_view = data_view[d_ok]
    t_min, t_max = float(d_st[:, 1].min()), float(d_st[:, 1].max())
    # No two points are farther apart than 4 * scale: a larger radius reaches them all.
    # The box is widened a little; it only picks the candidates of the exact test below.
    scale = float(max(np.abs(d_st).max(), np.abs(query_st[q_ok]).max(), 1.0))
    reach = np.minimum(radius[q_ok], 4.0 * scale) * (1.0 + _SLACK) + _SLACK * scale
    n_views = int(d_view.max()) + 1
    # Bands about a radius high, but no more cells than a few per data point.
    height = max(float(np.median(reach)),
                 (t_max - t_min) * n_views / (4 * len(d_ok) + n_views), 1e-300)
    n_bands = int((t_max - t_min) / height) + 1
    band = np.minimum(((d_st[:, 1] - t_min) / height).astype(np.int64), n_bands - 1)
    order, start = _bucket(d_view * n_bands + band, d_st[:, 0], n_views * n_bands)
    qi, di = _scan(query_st[q_ok, 0].copy(), query_st[q_ok, 1].copy(), query_view[q_ok],
                   reach, start, d_st[order, 0].copy(), d_st[order, 1].copy(), t_min,
                   height, n_bands)
    qi = q_ok[qi]
    di = d_ok[order[di]]
    dist = np.hypot(query_st[qi, 0] - data_st[di, 0], query_st[qi, 1] - data_st[di, 1])
    keep = dist <= radius[qi]
    return qi[keep], di[keep], dist[keep]


class ImageSpans:
    """Where each particle's images lie across the views, to rule out pairs of images
    that cannot come near each other in any view.

    Parameters
    ----------
    pred : (P, V, 2) float ndarray
        Image centre ``(s, t)`` of every particle in every view, view pixels; NaN where
        a particle has no image.

    Notes
    -----
    A particle's ``centre`` is the mean of its image centres over the views where it has
    one and its ``spread`` the farthest any of them lies from that mean. In a view where
    both have an image, two particles' images are at least ``|centre_a - centre_b| -
    spread_a - spread_b`` apart, so :meth:`near` names every particle whose image comes
    within the distance asked of the query's in some view (and a few more): a test that
    compares them view by view gives the same answer on those alone. A particle without
    any image is near nothing.
    """

    def __init__(self, pred: np.ndarray) -> None:
        pred = np.asarray(pred, dtype=np.float64)
        self.centre, self.spread = _spans(pred)

    @classmethod
    def _of(cls, centre: np.ndarray, spread: np.ndarray) -> "ImageSpans":
        out = cls.__new__(cls)
        out.centre, out.spread = centre, spread
        return out

    def set_rows(self, rows, pred: np.ndarray) -> None:
        """Take the images ``pred`` (len(rows), V, 2) of the particles ``rows``."""
        self.centre[rows], self.spread[rows] = _spans(np.asarray(pred, dtype=np.float64))

    def extended(self, pred: np.ndarray) -> "ImageSpans":
        """These spans and those of the particles with images ``pred`` (n, V, 2) after
        them."""
        centre, spread = _spans(np.asarray(pred, dtype=np.float64))
        return ImageSpans._of(np.concatenate([self.centre, centre]),
                              np.concatenate([self.spread, spread]))

    def subset(self, rows) -> "ImageSpans":
        """The spans of the particles ``rows`` (an index array or a boolean mask)."""
        return ImageSpans._of(self.centre[rows], self.spread[rows])

    def near(self, pred: np.ndarray, reach) -> np.ndarray:
        """(P,) bool: the particles whose image may come within ``reach`` of one of the
        images ``pred`` (k, V, 2) in some view.

        ``reach`` (view pixels) is a scalar, one value per particle (P,), or one per
        particle and image (k, P). Every particle whose image does is True; NaN reaches
        none.
        """
        pred = np.asarray(pred, dtype=np.float64)
        centre, spread = _spans(pred.reshape(-1, *pred.shape[-2:]))
        gap = np.hypot(self.centre[None, :, 0] - centre[:, None, 0],
                       self.centre[None, :, 1] - centre[:, None, 1])          # (k, P)
        bound = np.asarray(reach, dtype=np.float64) + self.spread[None] + spread[:, None]
        with np.errstate(invalid="ignore"):
            # a little slack: the exact tests that follow decide the pairs
            return np.any(gap <= bound * (1.0 + 1e-9) + 1e-9, axis=0)

    def meet(self, pred: np.ndarray, image: np.ndarray, reach) -> np.ndarray:
        """(P,) bool: the particles whose image comes closer than ``reach`` (scalar or
        (P,), view pixels) to ``image`` (V, 2) in some view, ``pred`` (P, V, 2) being
        the images these spans were taken of; decided view by view for the particles
        :meth:`near` does not rule out."""
        reach = np.broadcast_to(np.asarray(reach, dtype=np.float64), (len(self),))
        out = self.near(image, reach)
        rows = np.flatnonzero(out)
        gap = np.hypot(*(pred[rows] - np.asarray(image)[None]).transpose(2, 0, 1))   # (p, V)
        with np.errstate(invalid="ignore"):
            out[rows] = np.any(gap < reach[rows, None], axis=1)
        return out

    def __len__(self) -> int:
        return len(self.centre)


def _spans(pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean image centre (n, 2) over the views with an image and the farthest image
    from it (n,) of images ``pred`` (n, V, 2); NaN for a particle without any."""
    centre = np.full((len(pred), 2), np.nan)
    spread = np.full(len(pred), np.nan)
    if pred.shape[1] == 0:
        return centre, spread
    whole = np.all(np.isfinite(pred), axis=(1, 2))
    if whole.any():
        centre[whole] = pred[whole].mean(axis=1)
        spread[whole] = np.max(np.hypot(*(pred[whole] - centre[whole, None]).transpose(2, 0, 1)),
                               axis=1)
    part = np.flatnonzero(~whole & np.any(np.all(np.isfinite(pred), axis=2), axis=1))
    for i in part:                                     # rare: images in some views only
        seen = pred[i][np.all(np.isfinite(pred[i]), axis=1)]
        centre[i] = seen.mean(axis=0)
        spread[i] = np.max(np.hypot(*(seen - centre[i]).T))
    return centre, spread
