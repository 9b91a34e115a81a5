"""Full-sensor hall2019 renders (slow: run with ``pytest -m slow``)."""

import numpy as np
import pytest

from plenoptrack import preset
from plenoptrack.simulate import (default_volume, make_optics, random_particles, render_frame,
                                  render_irradiance)
from plenoptrack.simulate import _kernels
from plenoptrack.simulate.render import _particle_table, sample_pattern

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def hall():
    camera = preset("hall2019")
    optics = make_optics(camera, seed=0)
    particles = random_particles(100, volume=default_volume(camera), diameter_mm=1.0, seed=1)
    return optics, particles


def test_full_frame_matches_brute_force_on_windows(hall):
    optics, particles = hall
    irr = render_irradiance(optics, particles)
    occ = _particle_table(optics, particles)
    par = _kernels.pack_params(optics)
    samples = sample_pattern(optics, 16)
    for r0, c0 in [(2000, 3000), (0, 0), (4000, 6200), (1500, 800)]:
        brute = _kernels.render_all(par, samples, occ, np.zeros(3), r0, r0 + 300, c0, c0 + 400, True)
        np.testing.assert_array_equal(irr[r0:r0 + 300, c0:c0 + 400], brute)


def test_full_frame_deterministic(hall):
    optics, particles = hall
    a = render_frame(optics, particles, seed=3)
    b = render_frame(optics, particles, seed=3)
    assert a.shape == (4400, 6600) and a.tobytes() == b.tobytes()
