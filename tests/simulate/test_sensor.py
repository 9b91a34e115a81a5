"""Sensor noise model: mean and variance against shot + read noise."""

import numpy as np
import pytest

from plenoptrack.simulate.sensor import POISSON_EXACT_BELOW_E, SensorModel, expose


@pytest.mark.parametrize("irradiance", [0.02, 0.5, 1.0])
def test_flat_field_statistics(irradiance):
    sensor = SensorModel()
    level, bits = 0.7, 12
    irr = np.full((300, 300), irradiance, dtype=np.float32)
    counts = expose(irr, level=level, bit_depth=bits, sensor=sensor,
                    rng=np.random.default_rng(0)).astype(float)
    gain = (2 ** bits - 1) / sensor.full_well_e
    mu_e = irradiance * level * sensor.full_well_e
    expected_var = (mu_e + sensor.read_noise_e ** 2) * gain ** 2 + 1 / 12  # + quantisation
    standard_error = np.sqrt(expected_var / counts.size)
    assert counts.mean() == pytest.approx(mu_e * gain, abs=4 * standard_error)
    assert counts.var() == pytest.approx(expected_var, rel=4 * np.sqrt(2 / counts.size))
    if irradiance == 0.02:
        assert mu_e < POISSON_EXACT_BELOW_E  # exercised the exact Poisson branch


def test_noise_free_clips_and_rounds():
    irr = np.array([[0.0, 0.25, 1.0, 2.0]], dtype=np.float32)
    out = expose(irr, level=1.0, bit_depth=12, sensor=SensorModel(), rng=None, noise=False)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, [[0, 1024, 4095, 4095]])


def test_same_seed_same_counts():
    irr = np.random.default_rng(1).random((50, 60)).astype(np.float32)
    a = expose(irr, level=0.7, bit_depth=12, sensor=SensorModel(), rng=np.random.default_rng(3))
    b = expose(irr, level=0.7, bit_depth=12, sensor=SensorModel(), rng=np.random.default_rng(3))
    c = expose(irr, level=0.7, bit_depth=12, sensor=SensorModel(), rng=np.random.default_rng(4))
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()


def test_bad_sensor_model():
    with pytest.raises(ValueError, match="full_well_e"):
        SensorModel(full_well_e=0)
