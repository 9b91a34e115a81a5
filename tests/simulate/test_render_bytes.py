"""Digests of rendered irradiance with every effect on: the culling and shortcuts of the
ray-tracing kernels may only skip work whose outcome is known, so the traced images keep
their bytes (sha256, first 16 hex digits, of renders made before those kernels changed)."""

import hashlib

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack.simulate import (default_volume, make_optics, random_particles, render_frame,
                                  render_irradiance)


def _digest(image):
    return hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest()[:16]


def test_realistic_irradiance_keeps_its_bytes():
    # Lens group (tilt, Seidel terms, front stop), highlights, a translucent moving sphere.
    o = make_optics(preset("small"), 3, realism="realistic")
    parts = pd.DataFrame([[0.5, -0.3, 2.0, 0.8], [-2.0, 1.0, -6.0, 1.0], [4.0, 2.5, -9.0, 0.9]],
                         columns=["x", "y", "z", "diameter"]).assign(
        transmission=[0.0, 0.05, 0.0], velocity_x=[0.0, 0.3, 0.0], velocity_y=0.0,
        velocity_z=[0.0, 1.0, 0.0])
    irr = render_irradiance(o, parts)
    assert _digest(irr) == "982088e929bb4eb2"
    np.testing.assert_array_equal(irr, render_irradiance(o, parts, cull=False))


@pytest.mark.slow
@pytest.mark.parametrize("mode, irradiance, raw", [
    ("ideal", "acc466c8f3dbc6c8", "1a0d39c17aec912c"),
    ("realistic", "7acf348f5b0089e1", None),        # raw: the blur's rounding changed
])
def test_full_sensor_frame_keeps_its_bytes(mode, irradiance, raw):
    cam = preset("hall2019")
    o = make_optics(cam, 0, realism=mode)
    parts = random_particles(100, volume=default_volume(cam), diameter_mm=1.0, seed=1)
    assert _digest(render_irradiance(o, parts)) == irradiance
    if raw is not None:
        assert _digest(render_frame(o, parts, seed=1)) == raw
