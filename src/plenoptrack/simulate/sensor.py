"""Sensor model: irradiance to raw counts with shot and read noise."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import CameraSpecError

__all__ = ["SensorModel", "expose"]


@dataclass(frozen=True)
class SensorModel:
    """Exposure and noise of the simulated sensor.

    Parameters
    ----------
    full_well_e : float
        Full-well capacity, electrons; it maps to the largest raw value ``2**bit_depth - 1``.
    read_noise_e : float
        Gaussian read noise, electrons RMS.
    background_level : float
        Expected signal of a fully lit pixel in particle frames and dot cards, as a
        fraction of full scale.
    white_level : float
        Same for the white (flat-field) image, which is exposed longer.
    """

    full_well_e: float = 20000.0
    read_noise_e: float = 10.0
    background_level: float = 0.7
    white_level: float = 0.9

    def __post_init__(self) -> None:
        for name in ("full_well_e", "background_level", "white_level"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise CameraSpecError(f"sensor {name} must be a positive number; got {value!r}")
        if not (math.isfinite(self.read_noise_e) and self.read_noise_e >= 0):
            raise CameraSpecError(f"sensor read_noise_e must be >= 0; got {self.read_noise_e!r}")


def expose(irradiance: np.ndarray, *, level: float, bit_depth: int, sensor: SensorModel,
           rng: np.random.Generator | None, noise: bool = True) -> np.ndarray:
    """Turn relative irradiance into raw counts.

    Parameters
    ----------
    irradiance : (rows, cols) float ndarray
        Fraction of the back-light radiance reaching each pixel, in [0, 1].
    level : float
        Expected signal of a fully lit pixel as a fraction of full scale.
    bit_depth : int
        Raw bit depth; counts are clipped to ``[0, 2**bit_depth - 1]``.
    sensor : SensorModel
        Full well and read noise.
    rng : numpy.random.Generator
        Source of the noise draws (Poisson shot noise, then Gaussian read noise, both
        over the whole image in row-major order). Unused when ``noise`` is False.
    noise : bool
        False returns the rounded expected counts.

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts.
    """
    full_scale = (1 << bit_depth) - 1
    electrons = np.asarray(irradiance, dtype=np.float64) * (level * sensor.full_well_e)
    if noise:
        if rng is None:
            raise ValueError("rng is required when noise=True")
        electrons = rng.poisson(electrons).astype(np.float64)
        if sensor.read_noise_e > 0:
            electrons += rng.normal(0.0, sensor.read_noise_e, size=electrons.shape)
    counts = np.rint(electrons * (full_scale / sensor.full_well_e))
    np.clip(counts, 0, full_scale, out=counts)
    return counts.astype(np.uint16)
