"""The compiled order statistics give numpy's results exactly."""

import numpy as np
import pytest

from plenoptrack.locate._order import median, stable_argsort


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
