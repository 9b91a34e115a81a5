"""How far the simulated camera departs from the ideal one: every effect, its size, its switch.

The simulator has two optics modes. ``ideal`` is the exact geometric model (thin main lens
with a fixed radial distortion, perfect microlenses, uniform back-light, a perfect sensor
apart from shot and read noise, perfect dot cards whose depths the spec sheet states
exactly); unit tests of geometry use it. ``realistic`` switches on every effect below at
values taken from the seed paper's camera and typical data sheets; accuracy claims are
made on it.

Each group is a small frozen dataclass whose fields are the physical sizes of its effects;
a size of zero switches an effect off, and :meth:`Realism.scaled` multiplies every size of
one group (or of all) by a factor. A scene TOML sets them in an ``[optics]`` table::

    [optics]
    mode = "realistic"              # or "ideal": the base values
    scale = 1.0                     # optional: multiply every effect
    [optics.sensor]
    gain_sigma = 0.02               # any field of a group replaces the base value
    [optics.illumination]
    scale = 0.5                     # optional: multiply this group's effects
    [optics.particles]
    exposure_fraction = 0.1         # motion blur over a tenth of the frame interval

=========================  =================================================================
group                      effects
=========================  =================================================================
``blur``                   diffraction (Airy pattern at the working f-number), microlens
                           focus error and aberration, light crossing into neighbouring
                           microlens images, microlens fill factor
``lens``                   main-lens distortion drawn per camera, field curvature,
                           astigmatism and coma (Seidel terms), off-axis (cat's-eye)
                           vignetting, optical axis off the sensor centre, tilted
                           microlens array
``illumination``           smooth non-uniform back-light, different for the white image and
                           each frame; dust shadows fixed on the sensor window
``sensor``                 pixel gain (PRNU) and offset (DSNU) maps fixed per camera, hot
                           and dead pixels, a dead column, gain mismatch between the readout
                           outputs of a multi-output CCD, a dark pedestal
``target``                 dot-card tilt, traverse depth error per card and unknown common
                           offset of its zero, dot print-position error, card centre off
                           the axis
``spec``                   true focal lengths that differ from the spec sheet's
                           (``camera.toml`` keeps nominal values), f-number not exactly
                           matched
``particles``              partial translucency of the particles, specular highlights on
                           them, motion blur over the exposure
=========================  =================================================================
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields, replace
from typing import Literal

from ..errors import SettingsError

__all__ = ["BlurEffects", "LensEffects", "IlluminationEffects", "SensorEffects", "TargetEffects",
           "SpecEffects", "ParticleEffects", "Realism", "GROUPS", "realism_from_dict"]


def _check_non_negative(obj) -> None:
    for f in fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SettingsError(f"{type(obj).__name__}.{f.name} must be a number; got {value!r}")
        if not (math.isfinite(value) and value >= 0):
            raise SettingsError(f"{type(obj).__name__}.{f.name} must be a finite number >= 0; "
                                f"got {value!r}")


class _Group:
    """Shared behaviour of the effect groups: validation, scaling, switching off."""

    # fields that are not effect sizes (kept when scaling); each group names its own
    _fixed: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        _check_non_negative(self)

    def scaled(self, factor: float):
        """A copy with every effect size multiplied by ``factor`` (0 switches all off)."""
        if not (math.isfinite(factor) and factor >= 0):
            raise SettingsError(f"scale must be a finite number >= 0; got {factor!r}")
        return replace(self, **{f.name: getattr(self, f.name) * factor
                                for f in fields(self) if f.name not in self._fixed})

    @property
    def enabled(self) -> bool:
        """Whether any effect of the group has a non-zero size."""
        return any(getattr(self, f.name) != 0 for f in fields(self) if f.name not in self._fixed)


@dataclass(frozen=True)
class BlurEffects(_Group):
    """Blur of the light field on the sensor by the microlenses and diffraction.

    Attributes
    ----------
    wavelength_nm : float
        Wavelength of the back-light, nm (550: a white LED weighted by a monochrome
        sensor). Diffraction makes an Airy pattern of first-zero radius
        ``1.22 * wavelength * N`` at the working f-number ``N`` of the microlenses.
        0 switches diffraction off.
    microlens_defocus_um : float
        Distance between the sensor and the microlens focal plane, um (assembly
        tolerance); blurs each microlens image by a disc of diameter ``defocus / N``.
        (Scaling the blur group also scales ``wavelength_nm``, and so the diffraction.)
    microlens_aberration_um : float
        RMS radius of the residual (mostly spherical) aberration blur of a microlens, um.
    crosstalk : float
        Fraction of the light behind one microlens that lands in the images of its
        neighbours (scatter at the lens edges and the sensor cover glass).
    fill_gap : float
        Fraction of each microlens cell's width that is dead (gaps and edge roll-off of the
        lens profile); light there is lost: a fraction ``1 - (1 - fill_gap)**2`` of it.
        A linear fill factor of 0.98 is ``fill_gap = 0.02``.
    """

    wavelength_nm: float = 550.0
    microlens_defocus_um: float = 8.0
    microlens_aberration_um: float = 1.0
    crosstalk: float = 0.01
    fill_gap: float = 0.02


@dataclass(frozen=True)
class LensEffects(_Group):
    """Departures of the main lens and the microlens array from the thin-lens model.

    Attributes
    ----------
    distortion_k1_sigma, distortion_k2_sigma : float
        Standard deviations of the radial distortion coefficients drawn per camera seed
        around the fixed values of :func:`~.optics.make_optics` (the same lens model type
        differs from copy to copy and with focus).
    field_curvature_mm : float
        Petzval field curvature: axial distance of the best-focus surface from the
        nominal focal plane at the edge of the field, mm (object side).
    astigmatism_mm : float
        Axial separation of the sagittal and tangential foci at the field edge, mm.
    coma_mm : float
        Transverse coma at the field edge for a ray through the aperture rim, mm
        (object side, in the focal plane).
    vignetting_radius_ratio : float
        Cat's-eye vignetting: 1 - (radius of the front lens opening / radius it would
        need to pass the whole aperture cone at the field edge); 0 means no
        vignetting, 0.1 clips the cone of the field-edge points by a tenth.
    axis_offset_px : float
        Largest distance of the optical axis from the sensor centre, sensor pixels
        (drawn per camera seed in a disc).
    mla_tilt_deg : float
        Largest tilt of the microlens array about an axis in its plane, degrees (drawn
        per camera seed): microlens-to-sensor distance varies across the sensor.
    """

    distortion_k1_sigma: float = 0.01
    distortion_k2_sigma: float = 0.003
    field_curvature_mm: float = 0.5
    astigmatism_mm: float = 0.3
    coma_mm: float = 0.01
    vignetting_radius_ratio: float = 0.1
    axis_offset_px: float = 20.0
    mla_tilt_deg: float = 0.02


@dataclass(frozen=True)
class IlluminationEffects(_Group):
    """The back-light and what lies on the sensor window.

    Attributes
    ----------
    backlight_nonuniformity : float
        Peak-to-valley relative variation of a smooth back-light across the field (LED
        panel behind a diffuser): 0.1 is +-5 %.
    backlight_frame_change : float
        Relative peak-to-valley change of that pattern between the white image and each
        frame (a lamp that drifts, a diffuser that moved): a few per cent.
    dust_particles : float
        Number of dust particles on the sensor cover window (rounded); their shadows are
        fixed on the sensor, in the white image and in every frame.
    dust_diameter_um : float
        Typical dust diameter, um (each drawn within a factor two of it).
    dust_opacity : float
        Largest fraction of light a dust particle blocks (each drawn between half of it
        and it).
    window_distance_mm : float
        Distance of the cover window's dust from the sensor, mm; sets how blurred the
        shadows are. Not an effect size: kept when scaling.
    """

    backlight_nonuniformity: float = 0.10
    backlight_frame_change: float = 0.03
    dust_particles: float = 6.0
    dust_diameter_um: float = 40.0
    dust_opacity: float = 0.5
    window_distance_mm: float = 0.7

    _fixed = ("window_distance_mm",)


@dataclass(frozen=True)
class SensorEffects(_Group):
    """Fixed-pattern defects of the sensor, the same in every image of one camera.

    Attributes
    ----------
    gain_sigma : float
        Relative standard deviation of the pixel gain (photo-response non-uniformity).
    offset_sigma_counts : float
        Standard deviation of the pixel dark offset (dark-signal non-uniformity), counts.
    pedestal_counts : float
        Mean dark offset added to every pixel (black level), counts.
    hot_fraction : float
        Fraction of hot pixels (stuck near full scale).
    dead_fraction : float
        Fraction of dead pixels (stuck near zero).
    dead_columns : float
        Number of dead columns (rounded).
    output_gain_mismatch : float
        Relative standard deviation of the gain of each readout output (tap) of a
        multi-output CCD; the outputs read the sensor's quadrants.
    outputs : float
        Number of readout outputs: 1, 2 (left and right halves) or 4 (quadrants). Not an
        effect size: kept when scaling.
    """

    gain_sigma: float = 0.01
    offset_sigma_counts: float = 1.5
    pedestal_counts: float = 16.0
    hot_fraction: float = 1e-4
    dead_fraction: float = 5e-5
    dead_columns: float = 1.0
    output_gain_mismatch: float = 0.01
    outputs: float = 4.0

    _fixed = ("outputs",)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.outputs not in (1, 2, 4):
            raise SettingsError(f"SensorEffects.outputs must be 1, 2 or 4 readout outputs; "
                                f"got {self.outputs!r}")


@dataclass(frozen=True)
class TargetEffects(_Group):
    """Imperfections of the dot cards and of the traverse that moves them.

    Attributes
    ----------
    tilt_deg : float
        Largest tilt of a card about an in-plane axis, degrees (each card drawn up to it).
    depth_sigma_um : float
        Standard deviation of the traverse position error of each card, um.
    zero_offset_mm : float
        Largest unknown offset of the traverse zero from the nominal focal plane, mm
        (common to all cards of a data set; drawn in +-this).
    print_sigma_um : float
        Standard deviation of each dot's print position, um.
    centre_offset_mm : float
        Largest offset of the card's dot (0, 0) from the optical axis, mm.
    """

    tilt_deg: float = 0.5
    depth_sigma_um: float = 10.0
    zero_offset_mm: float = 0.5
    print_sigma_um: float = 5.0
    centre_offset_mm: float = 0.3


@dataclass(frozen=True)
class SpecEffects(_Group):
    """How far the true optics differ from the spec-sheet values of ``camera.toml``.

    Attributes
    ----------
    focal_length_error : float
        Largest relative error of the main-lens focal length (drawn in +-this).
    microlens_focal_length_error : float
        Largest relative error of the microlens focal length (drawn in +-this).
    f_number_mismatch : float
        Largest relative error of the set f-number against the matched value.
    """

    focal_length_error: float = 0.02
    microlens_focal_length_error: float = 0.05
    f_number_mismatch: float = 0.05


@dataclass(frozen=True)
class ParticleEffects(_Group):
    """How the particles themselves depart from opaque, matt, still bodies.

    Attributes
    ----------
    max_transmission : float
        Largest transmission of a particle, in [0, 1): each particle of a simulated data
        set gets a transmission ``tau`` drawn uniformly in ``[0, max_transmission]`` from
        the scene seed, recorded in the truth column ``transmission``. A ray that meets a
        particle keeps the fraction ``tau`` of its back-light (the product over every
        particle it meets). Thin glass, polymer or ice fragments pass a few per cent of a
        diffuse back-light around their rims and through their bodies.
    highlight_strength : float
        Peak radiance of a specular highlight relative to the back-light. A ray that meets
        a particle adds ``highlight_strength * max(0, n . h)**highlight_exponent`` (Blinn-
        Phong) at its first surface point, ``n`` the outward normal there (the entry facet's
        normal on a fragment), ``h`` the unit half vector between the light direction and
        the direction back to the camera; the sample is clipped to the unoccluded
        back-light. Metal pins, polished beads and wet particles glint in room or lamp
        light that reaches them from the camera side.
    highlight_exponent : float
        Blinn-Phong exponent (> 0): 50 gives a glint of about 10 degrees of normal (polished
        metal 50-200, plastic 5-20). Not an effect size: kept when scaling.
    light_elevation_deg : float
        Angle of the direction towards the light from the direction towards the camera
        (world ``-z``), degrees, in [0, 90]. Not an effect size.
    light_azimuth_deg : float
        Azimuth of that direction in the x-y plane, degrees from world ``+x`` towards ``+y``,
        in [0, 360). Not an effect size.
    exposure_fraction : float
        Fraction of the frame interval the shutter is open, in [0, 1]: a particle with a
        velocity ``v`` (mm per frame; truth columns ``velocity_x, velocity_y, velocity_z``)
        moves by ``v * exposure_fraction`` during the exposure and its image is blurred
        along that path, centred on its truth position (mid-exposure). 0.05 is a 1 ms
        exposure at 50 frames per second.
    """

    max_transmission: float = 0.1
    highlight_strength: float = 0.5
    highlight_exponent: float = 50.0
    light_elevation_deg: float = 45.0
    light_azimuth_deg: float = 45.0
    exposure_fraction: float = 0.05

    _fixed = ("highlight_exponent", "light_elevation_deg", "light_azimuth_deg")

    def __post_init__(self) -> None:
        super().__post_init__()
        checks = (("max_transmission", self.max_transmission < 1, "in [0, 1)"),
                  ("highlight_exponent", self.highlight_exponent > 0, "> 0"),
                  ("light_elevation_deg", self.light_elevation_deg <= 90, "in [0, 90]"),
                  ("light_azimuth_deg", self.light_azimuth_deg < 360, "in [0, 360)"),
                  ("exposure_fraction", self.exposure_fraction <= 1, "in [0, 1]"))
        for name, ok, what in checks:
            if not ok:
                raise SettingsError(f"ParticleEffects.{name} must be {what}; "
                                    f"got {getattr(self, name)!r}")

    @property
    def light_direction(self) -> tuple[float, float, float]:
        """Unit vector from a particle towards the light, world frame (x, y, z)."""
        e = math.radians(self.light_elevation_deg)
        a = math.radians(self.light_azimuth_deg)
        return (math.sin(e) * math.cos(a), math.sin(e) * math.sin(a), -math.cos(e))


GROUPS = {"blur": BlurEffects, "lens": LensEffects, "illumination": IlluminationEffects,
          "sensor": SensorEffects, "target": TargetEffects, "spec": SpecEffects,
          "particles": ParticleEffects}
"""Effect groups of :class:`Realism` by field name."""


@dataclass(frozen=True)
class Realism:
    """Every departure of the simulated camera from the ideal model.

    Build with :meth:`ideal`, :meth:`realistic` or :func:`realism_from_dict`; change a
    group with :func:`dataclasses.replace` or :meth:`scaled`.

    Examples
    --------
    >>> Realism.realistic().sensor.gain_sigma
    0.01
    >>> Realism.ideal().enabled
    False
    >>> Realism.realistic().scaled(0.5, group="target").target.tilt_deg
    0.25
    """

    blur: BlurEffects = BlurEffects()
    lens: LensEffects = LensEffects()
    illumination: IlluminationEffects = IlluminationEffects()
    sensor: SensorEffects = SensorEffects()
    target: TargetEffects = TargetEffects()
    spec: SpecEffects = SpecEffects()
    particles: ParticleEffects = ParticleEffects()

    @classmethod
    def realistic(cls) -> "Realism":
        """Every effect on at its default size."""
        return cls()

    @classmethod
    def ideal(cls) -> "Realism":
        """Every effect off: the exact geometric model."""
        return cls().scaled(0.0)

    @classmethod
    def of(cls, mode: "Realism | Literal['ideal', 'realistic'] | None") -> "Realism":
        """``mode`` as a Realism: a name, a Realism, or None for ideal."""
        if mode is None or mode == "ideal":
            return cls.ideal()
        if mode == "realistic":
            return cls.realistic()
        if isinstance(mode, cls):
            return mode
        raise SettingsError(f"optics must be 'ideal', 'realistic' or a Realism; got {mode!r}")

    def scaled(self, factor: float, *, group: str | None = None) -> "Realism":
        """Multiply the effect sizes of one group (or of all) by ``factor``."""
        if group is not None and group not in GROUPS:
            raise SettingsError(f"unknown effect group {group!r}; choose one of {sorted(GROUPS)}")
        names = [group] if group is not None else list(GROUPS)
        return replace(self, **{n: getattr(self, n).scaled(factor) for n in names})

    @property
    def enabled(self) -> bool:
        """Whether any effect is on."""
        return any(getattr(self, n).enabled for n in GROUPS)

    @property
    def name(self) -> str:
        """``"ideal"``, ``"realistic"`` or ``"custom"``."""
        if self == Realism.ideal():
            return "ideal"
        return "realistic" if self == Realism.realistic() else "custom"

    def to_dict(self) -> dict:
        """``{group: {field: value}}``, the inverse of :func:`realism_from_dict`."""
        return {n: {f.name: getattr(getattr(self, n), f.name) for f in fields(GROUPS[n])}
                for n in GROUPS}


def realism_from_dict(data: dict | None, *, source: str = "[optics]") -> Realism:
    """Build a :class:`Realism` from a scene file's ``[optics]`` table.

    Parameters
    ----------
    data : dict or None
        ``mode`` (``"ideal"`` or ``"realistic"``, default ``"realistic"``), ``scale``
        (multiplies every effect) and one sub-table per group with field values and an
        optional ``scale`` of its own. None gives :meth:`Realism.realistic`.
    source : str
        Name used in error messages.

    Raises
    ------
    SettingsError
        Unknown keys or groups, values that are not finite non-negative numbers.
    """
    if data is None:
        return Realism.realistic()
    if not isinstance(data, dict):
        raise SettingsError(f"{source}: must be a table; got {type(data).__name__}")
    unknown = sorted(set(data) - {"mode", "scale", *GROUPS})
    if unknown:
        raise SettingsError(f"{source}: unknown key(s) {unknown}; allowed: mode, scale, "
                            f"{', '.join(sorted(GROUPS))}")
    mode = data.get("mode", "realistic")
    if mode not in ("ideal", "realistic"):
        raise SettingsError(f"{source}: mode must be 'ideal' or 'realistic'; got {mode!r}")
    base = Realism.of(mode)
    groups = {}
    for name, cls in GROUPS.items():
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise SettingsError(f"{source}.{name}: must be a table; got {table!r}")
        allowed = {f.name for f in fields(cls)}
        bad = sorted(set(table) - allowed - {"scale"})
        if bad:
            raise SettingsError(f"{source}.{name}: unknown key(s) {bad}; allowed: "
                                f"{', '.join(sorted(allowed))}, scale")
        try:
            group = replace(getattr(base, name), **{k: v for k, v in table.items() if k != "scale"})
            if "scale" in table:
                group = group.scaled(table["scale"])
        except SettingsError as exc:
            raise SettingsError(f"{source}.{name}: {exc}") from None
        groups[name] = group
    realism = Realism(**groups)
    if "scale" in data:
        realism = realism.scaled(data["scale"])
    return realism


def load_realism(text: str, *, source: str = "scene file") -> Realism:
    """Parse the ``[optics]`` table of a scene TOML text (realistic when absent)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SettingsError(f"{source}: not valid TOML ({exc})") from None
    return realism_from_dict(doc.get("optics"), source=f"{source} [optics]")
