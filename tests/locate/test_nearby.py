"""Fixed-radius neighbours of the same view against a dense all-pairs comparison."""

import numpy as np
import pytest

from plenoptrack.locate._nearby import ImageSpans, pairs_within


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


def _images(rng, n, n_views):
    """(n, V, 2) image centres of particles that move linearly across the views (as a
    particle's images do), some without any image and some with images in part of the
    views only."""
    start = rng.uniform(0.0, 60.0, (n, 1, 2))
    travel = rng.normal(0.0, 3.0, (n, 1, 2)) * rng.uniform(-1.0, 1.0, (1, n_views, 1))
    pred = start + travel + rng.normal(0.0, 0.2, (n, n_views, 2))
    pred[rng.random(n) < 0.1] = np.nan
    part = rng.random(n) < 0.1
    pred[part, : n_views // 2] = np.nan
    return pred


def _meet(pred_q, pred, reach):
    """(P,) whether any image ``pred_q`` (k, V, 2) comes within ``reach`` (k, P) of a
    particle's image in some view: every view compared."""
    gap = np.hypot(*(pred_q[:, None] - pred[None]).transpose(3, 0, 1, 2))   # (k, P, V)
    with np.errstate(invalid="ignore"):
        return np.any(gap < np.broadcast_to(reach, gap.shape[:2])[..., None], axis=(0, 2))


@pytest.mark.parametrize("seed", range(6))
def test_image_spans_name_every_particle_whose_image_comes_near(seed):
    rng = np.random.default_rng(seed)
    n_views = int(rng.integers(1, 30))
    pred = _images(rng, 200, n_views)
    spans = ImageSpans(pred)
    n_ruled_out = 0
    for q in range(0, 200, 7):
        for k in (1, 2):
            pred_q = pred[q:q + k]
            reach = rng.choice([0.0, 1.5, 4.0, np.nan], (k, 200)) + rng.uniform(0, 3, (k, 200))
            near = spans.near(pred_q, reach)
            exact = _meet(pred_q, pred, reach)
            assert not np.any(exact & ~near)           # nothing that meets is ruled out
            np.testing.assert_array_equal(spans.meet(pred, pred[q], reach[0]),
                                          _meet(pred[q:q + 1], pred, reach[0]))
            n_ruled_out += int(np.sum(~near))
    assert n_ruled_out > 0.5 * 29 * 2 * 200            # and most that do not are


def test_image_spans_follow_changed_added_and_selected_particles():
    rng = np.random.default_rng(7)
    pred = _images(rng, 40, 9)
    spans = ImageSpans(pred[:30])
    pred[[3, 4]] = _images(rng, 2, 9)
    spans.set_rows([3, 4], pred[[3, 4]])
    spans = spans.extended(pred[30:])
    whole = ImageSpans(pred)
    np.testing.assert_array_equal(spans.centre, whole.centre)
    np.testing.assert_array_equal(spans.spread, whole.spread)
    rows = np.array([5, 31, 2])
    np.testing.assert_array_equal(spans.subset(rows).centre, whole.centre[rows])
    assert len(spans) == 40 and len(spans.subset(rows)) == 3
    # a particle without any image is near nothing
    nowhere = np.full((1, 9, 2), np.nan)
    assert not spans.near(nowhere, np.inf).any()
    assert not ImageSpans(nowhere).near(pred[:1], np.inf).any()
