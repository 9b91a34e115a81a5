"""Dot-card calibration targets: a transparent plane with a square grid of opaque dots.

A dot card stands perpendicular to the optical axis at depth ``z`` (world frame, mm),
in front of the back-light. Its dots are dark discs of diameter ``dot_diameter_mm`` at
world ``(x, y) = (m * spacing_mm, n * spacing_mm)`` for all integers ``m, n``: dot
``(0, 0)`` lies on the optical axis. Each traced ray is intersected with the plane and
is dark if it lands inside a dot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..camera import CameraSpec
from . import _kernels
from .optics import SimOptics
from .render import DEFAULT_SAMPLES_PER_PIXEL, _check_optics, _check_samples, sample_pattern
from .scene import SceneError, volume_depth_mm
from .sensor import SensorModel, expose

__all__ = ["DotCard", "default_dotcard", "default_dotcard_depths", "render_dotcard",
           "dotcard_irradiance", "dot_grid"]


@dataclass(frozen=True)
class DotCard:
    """Layout of a dot card.

    Parameters
    ----------
    spacing_mm : float
        Centre-to-centre distance of neighbouring dots along x and y, mm.
    dot_diameter_mm : float
        Dot diameter, mm; must be less than the spacing.
    """

    spacing_mm: float
    dot_diameter_mm: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.spacing_mm) and self.spacing_mm > 0):
            raise SceneError(f"dot card spacing_mm must be positive; got {self.spacing_mm!r}")
        if not (math.isfinite(self.dot_diameter_mm) and 0 < self.dot_diameter_mm < self.spacing_mm):
            raise SceneError("dot card dot_diameter_mm must be positive and below spacing_mm "
                             f"({self.spacing_mm}); got {self.dot_diameter_mm!r}")


def default_dotcard(camera: CameraSpec) -> DotCard:
    """Dot layout suited to a camera.

    The spacing is 13 object-space lenslet widths (``microlens pitch / |M|``, the pixel
    size of a perspective view), capped so that at least 8 dots span the focal-plane
    field of view, rounded down to 0.25 mm; the dots are 30 % of the spacing wide
    (rounded to 0.05 mm). ``hall2019``: 2.0 mm spacing, 0.6 mm dots; ``small``: 1.25 mm
    and 0.4 mm. Dots are then about 4 view pixels wide and 9 apart.
    """
    lenslet_obj = camera.microlens_pitch_um * 1e-3 / abs(camera.magnification)
    fov_w = camera.sensor_size_mm[1] / abs(camera.magnification)
    spacing = min(13 * lenslet_obj, fov_w / 8)
    spacing = max(math.floor(spacing * 4) / 4, 0.25)
    dot = max(round(0.3 * spacing * 20) / 20, 0.05)
    return DotCard(spacing_mm=spacing, dot_diameter_mm=dot)


def default_dotcard_depths(camera: CameraSpec, n: int = 11) -> np.ndarray:
    """``n`` card depths (mm) evenly spanning the camera's default volume depth."""
    half = volume_depth_mm(camera) / 2
    return np.linspace(-half, half, n)


def dot_grid(optics: SimOptics, z_mm: float, card: DotCard) -> pd.DataFrame:
    """Dots of a card at depth ``z_mm`` whose chief-ray image falls on the sensor.

    Returns
    -------
    DataFrame
        Columns ``m, n`` (dot indices), ``x, y, z`` (world, mm) and ``row, col``
        (sensor pixels of the chief ray, through the aperture centre, i.e. the position
        in the central view), one row per dot.
    """
    rows, cols = optics.camera.sensor_shape_px
    scale = (optics.s_o + z_mm) / optics.s_o
    half_x = 0.6 * cols * optics.pixel_pitch * optics.s_o / optics.s_i * scale
    half_y = 0.6 * rows * optics.pixel_pitch * optics.s_o / optics.s_i * scale
    mx = np.arange(-math.ceil(half_x / card.spacing_mm), math.ceil(half_x / card.spacing_mm) + 1)
    ny = np.arange(-math.ceil(half_y / card.spacing_mm), math.ceil(half_y / card.spacing_mm) + 1)
    m, n = np.meshgrid(mx, ny, indexing="xy")
    x = m.ravel() * card.spacing_mm
    y = n.ravel() * card.spacing_mm
    px = optics.world_to_pixels(np.column_stack([x, y, np.full_like(x, z_mm)]))
    on = (px[:, 0] >= 0) & (px[:, 0] <= rows - 1) & (px[:, 1] >= 0) & (px[:, 1] <= cols - 1)
    return pd.DataFrame({"m": m.ravel()[on], "n": n.ravel()[on], "x": x[on], "y": y[on],
                         "z": float(z_mm), "row": px[on, 0], "col": px[on, 1]})


def _card_vector(optics: SimOptics, z_mm: float, card: DotCard) -> np.ndarray:
    if not math.isfinite(z_mm) or optics.s_o + z_mm <= 0.05 * optics.s_o:
        raise SceneError(f"dot card depth z_mm must be finite and in front of the lens "
                         f"(z > {-0.95 * optics.s_o:.1f} mm); got {z_mm!r}")
    return np.array([optics.s_o + z_mm, card.spacing_mm, (card.dot_diameter_mm / 2) ** 2])


def dotcard_irradiance(optics: SimOptics, z_mm: float, *, card: DotCard | None = None,
                       samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                       exact: bool = False) -> np.ndarray:
    """Noise-free irradiance of a dot card at depth ``z_mm``, ``(rows, cols)`` float32.

    ``exact`` True traces every sample (reference for tests); the default skips pixels
    whose rays provably miss every dot, with identical results.
    """
    _check_optics(optics)
    card = default_dotcard(optics.camera) if card is None else card
    vec = _card_vector(optics, float(z_mm), card)
    n = _check_samples(samples_per_pixel)
    rows, cols = optics.camera.sensor_shape_px
    return _kernels.render_all(_kernels.pack_params(optics), sample_pattern(optics, n),
                               np.zeros((0, 4)), vec, 0, rows, 0, cols, exact)


def render_dotcard(optics: SimOptics, z_mm: float, *, card: DotCard | None = None,
                   seed: int | np.random.Generator | None = 0, noise: bool = True,
                   samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                   sensor: SensorModel = SensorModel()) -> np.ndarray:
    """Raw image of a dot card at depth ``z_mm`` (world frame, mm).

    Parameters
    ----------
    optics : SimOptics
        True camera optics.
    z_mm : float
        Card depth, mm (0 = nominal focal plane, positive away from the camera).
    card : DotCard, optional
        Dot layout; :func:`default_dotcard` of the camera by default.
    seed : int or numpy.random.Generator
        Noise seed.
    noise : bool
        False gives the rounded expected counts.
    samples_per_pixel : int
        Rays per pixel.
    sensor : SensorModel
        Exposure (``background_level``) and noise.

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts.
    """
    irr = dotcard_irradiance(optics, z_mm, card=card, samples_per_pixel=samples_per_pixel)
    return expose(irr, level=sensor.background_level, bit_depth=optics.camera.bit_depth,
                  sensor=sensor, rng=np.random.default_rng(seed), noise=noise)
