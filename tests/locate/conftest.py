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


def _clustered_and_solved(raw, calibration, locator=None):
    """One raw frame through the locator's first stages (decode without a white image,
    segment, cluster, solve and grow): ``(FrameContext, ParticleState)``, warnings
    silenced. Tests of the later stages run those on the state themselves."""
    import warnings

    from plenoptrack.locate import perspective
    from plenoptrack.locate.settings import PerspectiveLocator

    locator = PerspectiveLocator() if locator is None else locator
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lf = perspective._decoded(raw, calibration, 0, None)
        detections = perspective.segment_frame(lf, locator.segment, frame=0)
        ctx = perspective.FrameContext.build(lf, calibration, detections, locator)
        state = perspective._cluster_and_solve(
            ctx, perspective.ParticleState.start(ctx, locator.segment), locator)
    return ctx, state


@pytest.fixture(scope="session")
def clustered_and_solved():
    """:func:`_clustered_and_solved`: ``f(raw, calibration, locator=None) -> (ctx,
    state)``."""
    return _clustered_and_solved
