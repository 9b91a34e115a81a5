"""Fixed-radius neighbours of the same view against a dense all-pairs comparison."""

import numpy as np
import pytest

from plenoptrack.locate._nearby import pairs_within


def _dense(query, query_view, radius, data, data_view):
    """Every pair from the full (n, m) distance matrix, in (query, data) order."""
    radius = np.broadcast_to(radius, (len(query),))
    dist = np.hypot(query[:, None, 0] - data[None, :, 0], query[:, None, 1] - data[None, :, 1])
    qi, di = np.nonzero((dist <= radius[:, None]) & (query_view[:, None] == data_view[None, :]))
    return qi, di, dist[qi, di]


def _sorted(pairs):
    qi, di, dist = pairs
    order = np.lexsort((di, qi))
    return qi[order], di[order], dist[order]


def _points(rng, n, on_grid):
    """Points on an integer grid (many ties and exact boundary distances) or scattered."""
    return (rng.integers(0, 8, (n, 2)).astype(float) if on_grid
            else rng.uniform(-20.0, 20.0, (n, 2)))


@pytest.mark.parametrize("seed", range(12))
def test_pairs_match_the_dense_comparison(seed):
    for case in range(25):
        rng = np.random.default_rng([seed, case])
        n, m, n_views = (int(x) for x in rng.integers([0, 0, 1], [50, 50, 5]))
        on_grid = bool(case % 2)
        query, data = _points(rng, n, on_grid), _points(rng, m, on_grid)
        query[rng.random((n, 2)) < 0.05] = np.nan
        data[rng.random((m, 2)) < 0.05] = np.nan
        radius = (rng.choice([0.0, 1.0, 2.0, 3.5, np.inf, np.nan, -1.0], n) if case % 3
                  else float(rng.uniform(0, 6)))
        query_view = rng.integers(0, n_views + 1, n)      # some views without data
        data_view = rng.integers(0, n_views, m)
        got = pairs_within(query, query_view, radius, data, data_view)
        assert np.all(np.diff(got[0]) >= 0)               # grouped by query
        for a, b in zip(_sorted(got), _dense(query, query_view, radius, data, data_view),
                        strict=True):
            assert np.array_equal(a, b), (seed, case)


def test_far_apart_coordinates_and_huge_radii():
    rng = np.random.default_rng(5)
    data = np.vstack([rng.uniform(-1e6, 1e6, (30, 2)), rng.uniform(0, 3, (30, 2))])
    query = np.vstack([data[::3] + 0.5, [[1e9, -1e9], [0.0, 0.0]]])
    view = np.zeros(len(data), dtype=np.int64)
    q_view = np.zeros(len(query), dtype=np.int64)
    for radius in (1.0, 1e7, np.inf):
        got = pairs_within(query, q_view, radius, data, view)
        want = _dense(query, q_view, radius, data, view)
        assert all(np.array_equal(a, b) for a, b in zip(_sorted(got), want, strict=True))


def test_empty_inputs():
    none = np.zeros((0, 2))
    one = np.array([[1.0, 2.0]])
    for args in ((none, [], 1.0, one, [0]), (one, [0], 1.0, none, []),
                 (one, [0], np.nan, one, [0]), (np.full((1, 2), np.nan), [0], 1.0, one, [0])):
        qi, di, dist = pairs_within(*args)
        assert len(qi) == len(di) == len(dist) == 0
        assert qi.dtype == di.dtype == np.int64
