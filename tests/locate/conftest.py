"""Fixtures shared by the locate tests."""

import pytest


@pytest.fixture(scope="session")
def small_calibrated():
    """Optics (seed 0) of the 'small' preset and a calibration with a DLFC fitted on
    simulated dot cards, built once per test session."""
    try:
        from .test_perspective import _calibrated
    except ImportError:  # tests/locate is not a package
        from test_perspective import _calibrated
    return _calibrated("small")
