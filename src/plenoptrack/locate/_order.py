"""Order statistics for the compiled kernels: a stable argsort and a median; and the
unique rows of a table whose equal rows come in runs.

numba's ``np.argsort(..., kind="mergesort")`` and ``np.median`` compile large generic
implementations into the first kernel that uses them; on a fresh installation they were
about a fifth of the time spent compiling the kernels of calibrating and locating. These
two small functions give exactly the same results (numpy's stable order, NaN last; the
median of numpy, NaN when any value is NaN) and compile in a fraction of the time.
Both run in O(n log n).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["stable_argsort", "median", "unique_rows"]


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(a, axis=0, return_inverse=True, return_counts=True)`` for a 2-D array
    whose equal rows mostly come in runs (the detections of a frame, ordered by view):
    only the first row of each run is sorted, so a table of a hundred thousand rows in a
    few hundred runs takes a millisecond instead of a sort of all its rows.

    Returns
    -------
    rows : (K, m) ndarray
        The distinct rows, sorted lexicographically.
    inverse : (N,) int64 ndarray
        Index into ``rows`` of each row of ``a``.
    counts : (K,) int64 ndarray
        How often each distinct row occurs.
    """
    a = np.asarray(a)
    if len(a) == 0:
        return a.reshape(0, *a.shape[1:]), np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.r_[0, np.flatnonzero(np.any(a[1:] != a[:-1], axis=1)) + 1]
    rows, run_row = np.unique(a[starts], axis=0, return_inverse=True)
    inverse = np.repeat(run_row.ravel().astype(np.int64), np.diff(np.r_[starts, len(a)]))
    return rows, inverse, np.bincount(inverse, minlength=len(rows)).astype(np.int64)


@numba.njit(cache=True)
def _before(a, b):  # pragma: no cover - compiled
    """True when ``a`` sorts strictly before ``b`` (NaN after every number)."""
    return a < b or (a == a and b != b)


@numba.njit(cache=True)
def stable_argsort(x):  # pragma: no cover - compiled
    """Indices that sort the 1-D array ``x`` ascending, equal values in index order
    (``np.argsort(x, kind="stable")``); a bottom-up merge sort."""
    n = len(x)
    idx = np.arange(n)
    buf = np.empty(n, dtype=np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid = min(lo + width, n)
            hi = min(lo + 2 * width, n)
            i, j, k = lo, mid, lo
            while i < mid and j < hi:
                if _before(x[idx[j]], x[idx[i]]):
                    buf[k] = idx[j]
                    j += 1
                else:
                    buf[k] = idx[i]
                    i += 1
                k += 1
            while i < mid:
                buf[k] = idx[i]
                i += 1
                k += 1
            while j < hi:
                buf[k] = idx[j]
                j += 1
                k += 1
        idx, buf = buf, idx
        width *= 2
    return idx


@numba.njit(cache=True)
def median(x):  # pragma: no cover - compiled
    """Median of the 1-D array ``x`` as ``np.median`` gives it: the mean of the two middle
    values for an even length, NaN when ``x`` is empty or holds a NaN."""
    n = len(x)
    if n == 0:
        return np.nan
    for i in range(n):
        if x[i] != x[i]:
            return np.nan
    order = stable_argsort(x)
    h = n // 2
    if n % 2 == 1:
        return x[order[h]]
    return (x[order[h - 1]] + x[order[h]]) / 2
