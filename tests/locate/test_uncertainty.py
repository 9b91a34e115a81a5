"""The reported uncertainty: scaled least-squares errors plus the DLFC's model error."""

import numpy as np
import pytest

from plenoptrack.locate.uncertainty import model_error_mm, reduced_chi2, total_sigma


class _Report:
    position_rms_mm = (0.003, 0.004, 0.02)


class _DLFC:
    report = _Report()


def test_total_sigma_adds_the_model_error_in_quadrature():
    stat = np.array([[0.001, 0.002, 0.01], [np.nan, 0.0, 0.0]])
    out = total_sigma(stat, _DLFC(), error_scale=2.0)
    np.testing.assert_allclose(out[0], np.hypot(2 * stat[0], [0.003, 0.004, 0.02]))
    assert np.isnan(out[1, 0])
    np.testing.assert_allclose(out[1, 1:], [0.004, 0.02])
    plain = total_sigma(stat, _DLFC(), error_scale=1.0, include_model_error=False)
    np.testing.assert_array_equal(plain, stat)


def test_model_error_of_a_dlfc_without_it_is_zero():
    class Bare:
        report = None
    np.testing.assert_array_equal(model_error_mm(Bare()), np.zeros(3))
    np.testing.assert_array_equal(model_error_mm(_DLFC()), [0.003, 0.004, 0.02])


def test_reduced_chi2_finds_the_particle_with_twice_the_noise():
    rng = np.random.default_rng(0)
    n = rng.integers(20, 120, 200)
    noise = np.full(200, 0.1)
    noise[17] = 0.2
    residual = np.array([np.sqrt(np.mean(rng.normal(0, s, (k, 2)) ** 2) * 2)
                         for s, k in zip(noise, n)])
    chi2 = reduced_chi2(residual, n)
    assert np.median(chi2) == pytest.approx(1.0)
    assert chi2[17] == pytest.approx(4.0, rel=0.35)
    others = np.delete(chi2, 17)
    assert chi2[17] > others.max()
    assert np.isnan(reduced_chi2(np.array([0.1]), np.array([1]))).all()
