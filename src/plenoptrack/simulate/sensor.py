"""Sensor model: irradiance to raw counts with shot and read noise, and the fixed-pattern
defects of a real sensor (the ``sensor`` group of :class:`~.realism.Realism`).

:func:`expose` turns relative irradiance into counts: signal ``mu = E * level *
full_well`` electrons, Poisson shot noise (normal approximation above
:data:`POISSON_EXACT_BELOW_E`), Gaussian read noise, ``gain = (2**bits - 1) / full_well``
counts per electron, rounding and clipping. With a :class:`FixedPattern` (built by
:func:`fixed_pattern` from ``optics.realism.sensor`` and the camera seed ``optics.seed``)
it also applies the defects below; they are fixed per camera, never drawn from an image's
noise seed, so the white image, frames, dot cards and dark frames of one camera share
them exactly. Each is switched off by a size of 0 in :class:`~.realism.SensorEffects`.

Effects
-------
PRNU (``gain_sigma``, default 0.01)
    Photo-response non-uniformity: each pixel's signal is multiplied by
    ``1 + gain_sigma * N(0, 1)`` before shot noise (a gain map).
DSNU (``offset_sigma_counts``, default 1.5 counts)
    Dark-signal non-uniformity: each pixel adds ``offset_sigma_counts * N(0, 1)`` counts.
pedestal (``pedestal_counts``, default 16 counts)
    Black level added to every pixel (so that read noise around zero is not clipped).
hot pixels (``hot_fraction``, default 1e-4)
    ``round(hot_fraction * pixels)`` pixels at uniform positions have a dark level drawn
    uniformly in [0.9, 1.0] of full scale: they read near (or at) full scale.
dead pixels (``dead_fraction``, default 5e-5)
    ``round(dead_fraction * pixels)`` pixels have gain 0: they read only their dark level
    (pedestal + DSNU + read noise).
dead columns (``dead_columns``, default 1)
    ``round(dead_columns)`` columns, uniform over the sensor, have gain 0.
output gain mismatch (``output_gain_mismatch``, default 0.01; ``outputs``, default 4)
    A multi-output CCD reads ``outputs`` regions through separate amplifiers: 1 (whole
    sensor), 2 (left and right halves, split at ``cols // 2``) or 4 (quadrants, split at
    ``rows // 2`` and ``cols // 2``; order top-left, top-right, bottom-left,
    bottom-right). Each output's gain is ``1 + output_gain_mismatch * N(0, 1)``.

Every map has its own random stream, ``camera_rng(optics, purpose)``, so switching one
effect on or off does not change the others.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..errors import CameraSpecError, SettingsError

__all__ = ["SensorModel", "expose", "POISSON_EXACT_BELOW_E", "FixedPattern", "fixed_pattern",
           "camera_rng"]

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
           rng: np.random.Generator | None, noise: bool = True,
           fixed: "FixedPattern | None" = None) -> np.ndarray:
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
        Source of the noise: one float32 standard normal per pixel
        (:func:`standard_normal_image`), then Poisson draws for the pixels below
        :data:`POISSON_EXACT_BELOW_E`. Shot noise is
        Poisson (normal approximation above that threshold), read noise Gaussian.
        Unused when ``noise`` is False.
    noise : bool
        False returns the rounded expected counts.
    fixed : FixedPattern, optional
        Fixed-pattern defects of the camera (:func:`fixed_pattern`): the signal is
        multiplied by ``fixed.gain`` before the noise and ``fixed.offset`` counts are
        added after it. None (default): a perfect sensor.

    Notes
    -----
    Counts are ``floor(electrons * gain + offset + 0.5)`` clipped to the raw range, with
    ``gain = (2**bit_depth - 1) / full_well`` and ``offset = 0`` without ``fixed``. The
    random draws are the same with and without ``fixed``.

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts.
    """
    full_scale = (1 << bit_depth) - 1
    irr = np.ascontiguousarray(irradiance, dtype=np.float32)
    if fixed is not None:
        return _expose_fixed(irr, level=level, full_scale=full_scale, sensor=sensor, rng=rng,
                             noise=noise, fixed=fixed)
    to_e = level * sensor.full_well_e
    gain = full_scale / sensor.full_well_e
    if not noise:
        return _quantise(irr, to_e, gain, full_scale)
    if rng is None:
        raise ValueError("rng is required when noise=True")
    z = standard_normal_image(rng, irr.shape)
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


# --- fixed-pattern defects ---------------------------------------------------------------
_PRNU, _DSNU, _HOT, _DEAD, _DEAD_COLUMNS, _OUTPUTS = range(11, 17)   # camera_rng purposes


def camera_rng(optics, purpose: int) -> np.random.Generator:
    """Generator of one fixed pattern of a camera: ``default_rng([seed, 7919, purpose])``.

    ``seed`` is ``optics.seed`` (the camera seed of :func:`.optics.make_optics`); when it is
    None, 32-bit words of the drawn MLA rotation, offset and pitch scale stand in, so the
    patterns are still fixed per camera. Never an image's noise seed.
    """
    if optics.seed is not None:
        entropy = [int(optics.seed), 7919, int(purpose)]
    else:
        words = np.array([optics.rotation_deg, *optics.offset_mm, optics.pitch_scale])
        entropy = [*np.frombuffer(words.tobytes(), dtype=np.uint32).tolist(), 7919, int(purpose)]
    return np.random.default_rng(entropy)


@dataclass(frozen=True, eq=False)
class FixedPattern:
    """Fixed-pattern defects of one simulated sensor (see the module notes).

    Attributes
    ----------
    gain : (rows, cols) float32 ndarray or None
        Signal multiplier of each pixel (PRNU times output gain; 0 for dead pixels and
        columns). None: 1 everywhere.
    offset : (rows, cols) float32 ndarray or None
        Dark level of each pixel, counts (pedestal + DSNU; hot pixels near full scale).
        None: 0 everywhere.
    output_gains : (outputs,) float64 ndarray
        Gain of each readout output (regions in the order of the module notes).
    hot : int64 ndarray
        Flat (row-major) indices of the hot pixels.
    dead : int64 ndarray
        Flat indices of the dead pixels.
    dead_columns : int64 ndarray
        Dead column indices.
    """

    gain: np.ndarray | None
    offset: np.ndarray | None
    output_gains: np.ndarray
    hot: np.ndarray
    dead: np.ndarray
    dead_columns: np.ndarray


def output_regions(shape: tuple[int, int], outputs: int) -> list[tuple[slice, slice]]:
    """(row, col) slices of the readout regions of a sensor with 1, 2 or 4 outputs."""
    rows, cols = shape
    h, w = rows // 2, cols // 2
    if outputs == 1:
        return [(slice(0, rows), slice(0, cols))]
    if outputs == 2:
        return [(slice(0, rows), slice(0, w)), (slice(0, rows), slice(w, cols))]
    if outputs == 4:
        return [(slice(0, h), slice(0, w)), (slice(0, h), slice(w, cols)),
                (slice(h, rows), slice(0, w)), (slice(h, rows), slice(w, cols))]
    raise SettingsError(f"sensor outputs must be 1, 2 or 4 (whole sensor, halves, quadrants); "
                        f"got {outputs!r}")


def _positions(rng, n_pixels, fraction):
    k = int(round(fraction * n_pixels))
    if k == 0:
        return np.zeros(0, dtype=np.int64)
    return np.sort(rng.choice(n_pixels, size=min(k, n_pixels), replace=False)).astype(np.int64)


@functools.lru_cache(maxsize=2)
def fixed_pattern(optics) -> FixedPattern:
    """The fixed-pattern defects of a camera, drawn from ``optics.seed``, cached.

    Parameters
    ----------
    optics : SimOptics
        Camera; ``optics.realism.sensor`` gives the sizes, ``optics.camera`` the sensor
        shape and bit depth.

    Returns
    -------
    FixedPattern
        Read-only maps (``hall2019``: two 116 MB float32 maps when all effects are on).
    """
    eff = optics.realism.sensor
    cam = optics.camera
    shape = cam.sensor_shape_px
    n_pix = shape[0] * shape[1]
    full_scale = (1 << cam.bit_depth) - 1
    outputs = int(round(eff.outputs))
    regions = output_regions(shape, outputs)
    out_gains = 1.0 + eff.output_gain_mismatch * camera_rng(optics, _OUTPUTS).standard_normal(outputs)
    dead = _positions(camera_rng(optics, _DEAD), n_pix, eff.dead_fraction)
    n_cols = min(int(round(eff.dead_columns)), shape[1])
    dead_cols = np.sort(camera_rng(optics, _DEAD_COLUMNS).choice(shape[1], n_cols, replace=False)
                        ).astype(np.int64)
    hot = _positions(camera_rng(optics, _HOT), n_pix, eff.hot_fraction)
    gain = None
    if eff.gain_sigma > 0 or eff.output_gain_mismatch > 0 or len(dead) or len(dead_cols):
        if eff.gain_sigma > 0:
            gain = camera_rng(optics, _PRNU).standard_normal(shape, dtype=np.float32)
            gain *= np.float32(eff.gain_sigma)
            gain += np.float32(1.0)
        else:
            gain = np.ones(shape, dtype=np.float32)
        if eff.output_gain_mismatch > 0:
            for g, (rs, cs) in zip(out_gains, regions):
                gain[rs, cs] *= np.float32(g)
        gain.ravel()[dead] = 0.0
        gain[:, dead_cols] = 0.0
        gain.setflags(write=False)
    offset = None
    if eff.offset_sigma_counts > 0 or eff.pedestal_counts > 0 or len(hot):
        if eff.offset_sigma_counts > 0:
            offset = camera_rng(optics, _DSNU).standard_normal(shape, dtype=np.float32)
            offset *= np.float32(eff.offset_sigma_counts)
            offset += np.float32(eff.pedestal_counts)
        else:
            offset = np.full(shape, eff.pedestal_counts, dtype=np.float32)
        hot_rng = camera_rng(optics, _HOT + 100)
        offset.ravel()[hot] = (full_scale * hot_rng.uniform(0.9, 1.0, len(hot))).astype(np.float32)
        offset.setflags(write=False)
    out_gains.setflags(write=False)
    return FixedPattern(gain=gain, offset=offset, output_gains=out_gains, hot=hot, dead=dead,
                        dead_columns=dead_cols)


NOISE_CHUNKS = 8
"""An image's standard normals are drawn in this many contiguous chunks, each from its own
child of the image's generator (:meth:`numpy.random.Generator.spawn`), on up to as many
threads; a fixed number, so the bytes do not depend on the machine's core count."""

_CHUNKED_ABOVE = 1 << 20


def standard_normal_image(rng: np.random.Generator, shape) -> np.ndarray:
    """One float32 standard normal per pixel, drawn on several threads.

    Images of at least 2**20 pixels are filled in :data:`NOISE_CHUNKS` row-major chunks
    from ``rng.spawn(NOISE_CHUNKS)`` (numpy releases the GIL while filling, so the threads
    run in parallel); smaller ones with ``rng.standard_normal``. ``rng`` itself is not
    advanced by the chunked draw.
    """
    size = int(np.prod(shape))
    if size < _CHUNKED_ABOVE:
        return rng.standard_normal(size=shape, dtype=np.float32)
    from concurrent.futures import ThreadPoolExecutor

    out = np.empty(size, dtype=np.float32)
    children = rng.spawn(NOISE_CHUNKS)
    edges = np.linspace(0, size, NOISE_CHUNKS + 1).astype(np.int64)

    def fill(k: int) -> None:
        children[k].standard_normal(dtype=np.float32, out=out[edges[k]:edges[k + 1]])

    workers = min(NOISE_CHUNKS, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                  else (os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(fill, range(NOISE_CHUNKS)))
    return out.reshape(shape)


_ONE = np.ones((1, 1), dtype=np.float32)
_ZERO = np.zeros((1, 1), dtype=np.float32)


def _expose_fixed(irr, *, level, full_scale, sensor, rng, noise, fixed):
    to_e = level * sensor.full_well_e
    gain = full_scale / sensor.full_well_e
    has_g = fixed.gain is not None
    has_o = fixed.offset is not None
    gmap = fixed.gain if has_g else _ONE
    omap = fixed.offset if has_o else _ZERO
    for name, m in (("gain", fixed.gain), ("offset", fixed.offset)):
        if m is not None and m.shape != irr.shape:
            raise SettingsError(f"fixed-pattern {name} map has shape {m.shape} but the image "
                                f"{irr.shape}; build it with fixed_pattern(optics) of this camera")
    if not noise:
        return _quantise_fixed(irr, gmap, omap, has_g, has_o, to_e, gain, full_scale)
    if rng is None:
        raise ValueError("rng is required when noise=True")
    z = standard_normal_image(rng, irr.shape)
    out, is_low = _expose_bright_fixed(irr, gmap, omap, has_g, has_o, z, to_e, sensor.read_noise_e,
                                       gain, full_scale, POISSON_EXACT_BELOW_E)
    low = np.flatnonzero(is_low)
    mu = irr.ravel()[low].astype(np.float64) * to_e
    if has_g:
        mu *= gmap.ravel()[low]
    electrons = rng.poisson(mu) + sensor.read_noise_e * z.ravel()[low].astype(np.float64)
    counts = electrons * gain + 0.5
    if has_o:
        counts += omap.ravel()[low]
    out.ravel()[low] = np.clip(np.floor(counts), 0, full_scale)
    return out


@njit(parallel=True, cache=True)
def _quantise_fixed(irr, gmap, omap, has_g, has_o, to_e, gain, full_scale):
    out = np.empty(irr.shape, dtype=np.uint16)
    for r in prange(irr.shape[0]):
        for c in range(irr.shape[1]):
            mu = irr[r, c] * to_e
            if has_g:
                mu *= gmap[r, c]
            v = mu * gain + 0.5
            if has_o:
                v += omap[r, c]
            out[r, c] = min(max(math.floor(v), 0.0), full_scale)
    return out


@njit(parallel=True, cache=True)
def _expose_bright_fixed(irr, gmap, omap, has_g, has_o, z, to_e, read_e, gain, full_scale,
                         threshold):
    """As :func:`_expose_bright` with a gain map before and an offset map after the noise."""
    out = np.zeros(irr.shape, dtype=np.uint16)
    is_low = np.zeros(irr.shape, dtype=np.bool_)
    read2 = read_e * read_e
    for r in prange(irr.shape[0]):
        for c in range(irr.shape[1]):
            mu = irr[r, c] * to_e
            if has_g:
                mu *= gmap[r, c]
            if mu >= threshold:
                e = mu + math.sqrt(mu + read2) * z[r, c]
                v = e * gain + 0.5
                if has_o:
                    v += omap[r, c]
                out[r, c] = min(max(math.floor(v), 0.0), full_scale)
            else:
                is_low[r, c] = True
    return out, is_low
