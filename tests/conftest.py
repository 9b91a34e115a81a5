"""Shared fixtures: small simulated cameras with fixed seeds."""

import os

import pytest

# Commands run by the tests compile this processor's kernels as they always did: no seed
# cache and no background warm-up (tests/test_kernel_mode.py covers those).
os.environ.setdefault("PLENOPTRACK_KERNELS", "host")

from plenoptrack import preset


@pytest.fixture(scope="module")
def small_optics():
    """True optics of the 'small' hexagonal preset, seed 0."""
    from plenoptrack.simulate import make_optics

    return make_optics(preset("small"), seed=0)


@pytest.fixture(scope="module")
def small_rect_optics():
    """True optics of the 'small-rect' rectangular preset, seed 1."""
    from plenoptrack.simulate import make_optics

    return make_optics(preset("small-rect"), seed=1)
