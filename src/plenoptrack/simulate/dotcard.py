"""Dot-card calibration targets: a transparent plane with a square grid of opaque dots.

A dot card stands perpendicular to the optical axis at depth ``z`` (world frame, mm),
in front of the back-light. Its dots are dark discs of diameter ``dot_diameter_mm`` at
world ``(x, y) = (m * spacing_mm, n * spacing_mm)`` for all integers ``m, n``: dot
``(0, 0)`` lies on the optical axis. Each traced ray is intersected with the plane and
is dark if it lands inside a dot.

A real target is not that perfect (:class:`~.realism.TargetEffects`, drawn per data set
by :func:`draw_card_placements` into one :class:`CardPlacement` per card): the traverse
that moves the card has an unknown zero offset (up to 0.5 mm by default) and a position
error per card (10 um RMS, a typical lead-screw stage); each card is tilted by up to
0.5 degrees (mounting); dots are printed off their lattice points (5 um RMS, a
photo-plotted film or laser print); and dot (0, 0) sits up to 0.3 mm from the optical
axis (the card is centred by eye). The calibration sees none of this: ``dotcards.toml``
states the nominal depths and the ideal lattice.

A card without a fiducial mark cannot say which of its dots is ``(0, 0)``. The
calibration makes it the dot imaged nearest the sensor centre, which it takes for the
optical axis (in the central view the image of a point on the axis stays put from card to
card); the simulator's truth frame does the same (:func:`origin_dot_mm`). With a card
centred more than half a spacing off, or an optical axis off the sensor centre
(:attr:`~.optics.SimOptics.axis_offset_mm`), that is not always the dot the card was
printed around.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..camera import CameraSpec
from . import _kernels
from .optics import SimOptics
from .realism import TargetEffects
from .render import (DEFAULT_SAMPLES_PER_PIXEL, _check_optics, _check_samples,
                     background_irradiance, expose_image, sample_pattern)
from .scene import SceneError, volume_depth_mm
from .sensor import SensorModel

__all__ = ["DotCard", "CardPlacement", "draw_card_placements", "origin_dot_mm",
           "sensor_centre_aim_mm", "default_dotcard", "default_dotcard_depths", "render_dotcard",
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


@dataclass(frozen=True)
class CardPlacement:
    """Where a dot card really is, against where the traverse and the design say.

    Parameters
    ----------
    depth_error_mm : float
        True depth minus stated depth of the card's centre, mm: the traverse's unknown
        zero offset (common to every card of a set) plus its position error.
    tilt : (float, float)
        Slopes (a_x, a_y) of the card plane in the world frame: the card's depth grows by
        ``a_x`` per mm of x and ``a_y`` per mm of y (``tan`` of the tilt angles).
    centre_mm : (float, float)
        World (x, y) of dot (0, 0), mm (0, 0 on the optical axis).
    print_sigma_mm : float
        Standard deviation of each dot's printed position, mm, along x and y.
    print_seed : int
        Seed of the per-dot print errors (the card's own: every card is another print).
    """

    depth_error_mm: float = 0.0
    tilt: tuple[float, float] = (0.0, 0.0)
    centre_mm: tuple[float, float] = (0.0, 0.0)
    print_sigma_mm: float = 0.0
    print_seed: int = 0

    @property
    def is_perfect(self) -> bool:
        """Whether the card is exactly where and as the design says."""
        return (self.depth_error_mm == 0 and self.tilt == (0.0, 0.0)
                and self.centre_mm == (0.0, 0.0) and self.print_sigma_mm == 0)

    def to_dict(self) -> dict:
        return {"depth_error_mm": self.depth_error_mm, "tilt": list(self.tilt),
                "centre_mm": list(self.centre_mm), "print_sigma_mm": self.print_sigma_mm,
                "print_seed": self.print_seed}


def draw_card_placements(effects: TargetEffects, n_cards: int,
                         seed: int | np.random.Generator) -> tuple[float, tuple[float, float],
                                                                  list[CardPlacement]]:
    """Draw the imperfections of a set of dot cards moved by one traverse.

    Parameters
    ----------
    effects : TargetEffects
        Sizes of the imperfections (:mod:`.realism`).
    n_cards : int
        Cards in the set.
    seed : int or numpy.random.Generator
        Draws, in order: the traverse zero offset (uniform in +-``zero_offset_mm``), the
        card centre offset (x, y, uniform in a disc of radius ``centre_offset_mm``), then
        per card the depth error (normal, ``depth_sigma_um``), the tilt (direction
        uniform, angle uniform up to ``tilt_deg``) and a print seed.

    Returns
    -------
    zero_offset_mm : float
        The common traverse zero offset, mm (true depth = stated depth + this + error).
    centre_mm : (float, float)
        World (x, y) of dot (0, 0), mm.
    placements : list of CardPlacement
        One per card.
    """
    rng = np.random.default_rng(seed)
    zero = float(rng.uniform(-1.0, 1.0) * effects.zero_offset_mm)
    r = effects.centre_offset_mm * math.sqrt(rng.random())
    phi = rng.uniform(0.0, 2.0 * math.pi)
    centre = (float(r * math.cos(phi)), float(r * math.sin(phi)))
    placements = []
    for _ in range(int(n_cards)):
        error = float(rng.normal() * effects.depth_sigma_um * 1e-3)
        direction = rng.uniform(0.0, 2.0 * math.pi)
        slope = math.tan(math.radians(rng.uniform(0.0, effects.tilt_deg)))
        placements.append(CardPlacement(
            depth_error_mm=zero + error,
            tilt=(float(slope * math.cos(direction)), float(slope * math.sin(direction))),
            centre_mm=centre, print_sigma_mm=effects.print_sigma_um * 1e-3,
            print_seed=int(rng.integers(0, 2**31 - 1))))
    return zero, centre, placements


def origin_dot_mm(centre_mm: tuple[float, float], spacing_mm: float,
                  near_mm: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float]:
    """World ``(x, y)`` of the card dot nearest a point of the card plane, mm.

    Parameters
    ----------
    centre_mm : (float, float)
        World ``(x, y)`` of the dot the card was printed around (``CardPlacement.centre_mm``),
        mm.
    spacing_mm : float
        Dot spacing, mm.
    near_mm : (float, float)
        The point, world ``(x, y)`` mm: where the sensor centre's chief ray meets the
        card (:func:`sensor_centre_aim_mm`), whose nearest dot the calibration makes its
        ``(0, 0)``.

    Returns
    -------
    (float, float)
        ``centre_mm`` moved by whole spacings to within half a spacing of ``near_mm`` on
        each axis: the origin of the calibration's frame (see the module notes).

    Examples
    --------
    >>> origin_dot_mm((0.3, -0.1), 0.5)
    (-0.2, -0.1)
    >>> origin_dot_mm((0.3, -0.1), 0.5, near_mm=(0.1, 0.0))
    (0.3, -0.1)
    """
    c = np.asarray(centre_mm, dtype=float)
    dot = c - spacing_mm * np.rint((c - np.asarray(near_mm, dtype=float)) / spacing_mm)
    return float(round(dot[0], 12)), float(round(dot[1], 12))


def sensor_centre_aim_mm(optics: SimOptics) -> tuple[float, float]:
    """World ``(x, y)`` in the focal plane that the sensor centre images, mm.

    The world origin is on the optical axis, which meets the sensor
    ``optics.axis_offset_mm`` from its centre; the sensor centre therefore sees the point
    ``-axis_offset_mm / |M|`` (world ``x = -(X - a_x)``, see :mod:`.optics`; distortion
    vanishes this near the axis). ``(0, 0)`` when the axis is centred.
    """
    a = np.asarray(optics.axis_offset_mm, dtype=float)
    aim = -a / abs(optics.camera.magnification)
    return float(aim[0]), float(aim[1])


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


def dot_grid(optics: SimOptics, z_mm: float, card: DotCard,
             placement: CardPlacement | None = None) -> pd.DataFrame:
    """Dots of a card at depth ``z_mm`` whose chief-ray image falls on the sensor.

    With a ``placement`` the dots are where that card really puts them: shifted by its
    centre and print errors, at the depth of the tilted plane there.

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
    z = np.full_like(x, z_mm)
    if placement is not None and not placement.is_perfect:
        if placement.print_sigma_mm > 0:
            err = np.array([_kernels._hash_normal(a, b, float(placement.print_seed))
                            for a, b in zip(m.ravel(), n.ravel())]).reshape(-1, 2)
            x = x + placement.print_sigma_mm * err[:, 0]
            y = y + placement.print_sigma_mm * err[:, 1]
        x = x + placement.centre_mm[0]
        y = y + placement.centre_mm[1]
        z = z + placement.depth_error_mm + placement.tilt[0] * x + placement.tilt[1] * y
    px = optics.world_to_pixels(np.column_stack([x, y, z]))
    on = (px[:, 0] >= 0) & (px[:, 0] <= rows - 1) & (px[:, 1] >= 0) & (px[:, 1] <= cols - 1)
    return pd.DataFrame({"m": m.ravel()[on], "n": n.ravel()[on], "x": x[on], "y": y[on],
                         "z": z[on], "row": px[on, 0], "col": px[on, 1]})


def _card_vector(optics: SimOptics, z_mm: float, card: DotCard,
                 placement: CardPlacement | None = None) -> np.ndarray:
    if not math.isfinite(z_mm) or optics.s_o + z_mm <= 0.05 * optics.s_o:
        raise SceneError(f"dot card depth z_mm must be finite and in front of the lens "
                         f"(z > {-0.95 * optics.s_o:.1f} mm); got {z_mm!r}")
    if placement is None or placement.is_perfect:
        return np.array([optics.s_o + z_mm, card.spacing_mm, (card.dot_diameter_mm / 2) ** 2])
    # world z = z_c + a_x x + a_y y with x = -X, y = -Y: camera Z = Z_c - a_x X - a_y Y
    ax, ay = placement.tilt
    return np.array([optics.s_o + z_mm + placement.depth_error_mm, card.spacing_mm,
                     (card.dot_diameter_mm / 2) ** 2, placement.centre_mm[0],
                     placement.centre_mm[1], -ax, -ay, placement.print_sigma_mm,
                     float(placement.print_seed)])


def dotcard_irradiance(optics: SimOptics, z_mm: float, *, card: DotCard | None = None,
                       samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                       exact: bool = False,
                       placement: CardPlacement | None = None) -> np.ndarray:
    """Noise-free irradiance of a dot card at depth ``z_mm``, ``(rows, cols)`` float32.

    ``exact`` True traces every sample (reference for tests); the default starts from the
    cached background irradiance (:func:`.render.background_irradiance`, traced once per
    optics) and re-traces only the pixels whose rays may land on a dot, with identical
    results. ``placement`` moves, tilts and misprints the card (:class:`CardPlacement`;
    default perfect).
    """
    _check_optics(optics)
    card = default_dotcard(optics.camera) if card is None else card
    vec = _card_vector(optics, float(z_mm), card, placement)
    n = _check_samples(samples_per_pixel)
    par = _kernels.pack_params(optics)
    samples = sample_pattern(optics, n)
    if exact:
        rows, cols = optics.camera.sensor_shape_px
        return _kernels.render_all(par, samples, np.zeros((0, 4)), vec, 0, rows, 0, cols, True)
    out = background_irradiance(optics, n).copy()
    _kernels.render_card(out, par, samples, vec)
    return out


def render_dotcard(optics: SimOptics, z_mm: float, *, card: DotCard | None = None,
                   seed: int | np.random.Generator | None = 0, noise: bool = True,
                   samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                   sensor: SensorModel = SensorModel(),
                   placement: CardPlacement | None = None) -> np.ndarray:
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
    placement : CardPlacement, optional
        The card's real depth error, tilt, centre and print errors (default perfect).

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts.
    """
    irr = dotcard_irradiance(optics, z_mm, card=card, samples_per_pixel=samples_per_pixel,
                             placement=placement)
    return expose_image(irr, optics, level=sensor.background_level, sensor=sensor, seed=seed,
                        noise=noise)
