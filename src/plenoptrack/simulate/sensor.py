"""Sensor model: irradiance to raw counts with shot and read noise."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..errors import CameraSpecError

__all__ = ["SensorModel", "expose", "POISSON_EXACT_BELOW_E"]

POISSON_EXACT_BELOW_E = 1000.0
"""Expected signals (electrons) below this get exact Poisson draws; above it the shot
noise is drawn from its normal approximation N(mu, mu), whose skewness (1/sqrt(mu) <
3 %) is far below what a 12-bit pixel resolves. This makes a 29-megapixel frame several
times faster to expose."""


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
        Source of the noise: one float32 standard normal per pixel (row-major), then
        Poisson draws for the pixels below :data:`POISSON_EXACT_BELOW_E`. Shot noise is
        Poisson (normal approximation above that threshold), read noise Gaussian.
        Unused when ``noise`` is False.
    noise : bool
        False returns the rounded expected counts.

    Notes
    -----
    Counts are ``floor(electrons * gain + 0.5)`` clipped to the raw range, with
    ``gain = (2**bit_depth - 1) / full_well``.

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts.
    """
    full_scale = (1 << bit_depth) - 1
    irr = np.ascontiguousarray(irradiance, dtype=np.float32)
    to_e = level * sensor.full_well_e
    gain = full_scale / sensor.full_well_e
    if not noise:
        return _quantise(irr, to_e, gain, full_scale)
    if rng is None:
        raise ValueError("rng is required when noise=True")
    z = rng.standard_normal(size=irr.shape, dtype=np.float32)
    out, is_low = _expose_bright(irr, z, to_e, sensor.read_noise_e, gain, full_scale,
                                 POISSON_EXACT_BELOW_E)
    low = np.flatnonzero(is_low)
    mu = irr.ravel()[low].astype(np.float64) * to_e  # the kernel's float64 products
    electrons = rng.poisson(mu) + sensor.read_noise_e * z.ravel()[low].astype(np.float64)
    out.ravel()[low] = np.clip(np.floor(electrons * gain + 0.5), 0, full_scale)
    return out


@njit(parallel=True, cache=True)
def _quantise(irr, to_e, gain, full_scale):
    out = np.empty(irr.shape, dtype=np.uint16)
    for r in prange(irr.shape[0]):
        for c in range(irr.shape[1]):
            out[r, c] = min(max(math.floor(irr[r, c] * to_e * gain + 0.5), 0.0), full_scale)
    return out


@njit(parallel=True, cache=True)
def _expose_bright(irr, z, to_e, read_e, gain, full_scale, threshold):
    """Counts of pixels at or above ``threshold`` electrons, and a mask of the others."""
    out = np.zeros(irr.shape, dtype=np.uint16)
    is_low = np.zeros(irr.shape, dtype=np.bool_)
    read2 = read_e * read_e
    for r in prange(irr.shape[0]):
        for c in range(irr.shape[1]):
            mu = irr[r, c] * to_e
            if mu >= threshold:
                e = mu + math.sqrt(mu + read2) * z[r, c]
                out[r, c] = min(max(math.floor(e * gain + 0.5), 0.0), full_scale)
            else:
                is_low[r, c] = True
    return out, is_low
