"""The compiled order statistics give numpy's results exactly."""

import numpy as np
import pytest

from plenoptrack.locate._order import median, stable_argsort, unique_rows


@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 64, 1000, 1001])
def test_stable_argsort_is_numpys_stable_order(n):
    rng = np.random.default_rng(n)
    ints = rng.integers(0, max(n // 4, 1), n)          # many ties: stability matters
    assert np.array_equal(stable_argsort(ints), np.argsort(ints, kind="stable"))
    floats = rng.normal(size=n).round(1)               # ties and negative zero
    floats[rng.random(n) < 0.1] = np.nan                # NaN sorts last
    floats[rng.random(n) < 0.05] = -0.0
    assert np.array_equal(stable_argsort(floats), np.argsort(floats, kind="stable"))


@pytest.mark.parametrize("n", [1, 2, 3, 10, 11, 500])
def test_median_is_numpys_median(n):
    rng = np.random.default_rng(100 + n)
    x = rng.normal(size=n) * 10 ** rng.uniform(-3, 3, n)
    assert median(x) == np.median(x)                    # bit for bit, even and odd n
    x[n // 2] = np.nan
    assert np.isnan(median(x))
    assert np.isnan(median(np.zeros(0)))


@pytest.mark.parametrize("shuffled", [False, True])
def test_unique_rows_is_numpys_unique_over_rows(shuffled):
    """The detections of a frame come ordered by view (runs of equal rows); any order
    must give numpy's answer."""
    rng = np.random.default_rng(3)
    views = rng.integers(-7, 8, size=(40, 2)).astype(float) * 1.5
    a = np.repeat(views, rng.integers(1, 30, size=40), axis=0)
    if shuffled:
        a = a[rng.permutation(len(a))]
    rows, inverse, counts = unique_rows(a)
    want_rows, want_inverse, want_counts = np.unique(a, axis=0, return_inverse=True,
                                                     return_counts=True)
    np.testing.assert_array_equal(rows, want_rows)
    np.testing.assert_array_equal(inverse, want_inverse.ravel())
    np.testing.assert_array_equal(counts, want_counts)
    np.testing.assert_array_equal(rows[inverse], a)
    empty = unique_rows(np.zeros((0, 2)))
    assert empty[0].shape == (0, 2) and len(empty[1]) == 0 and len(empty[2]) == 0
