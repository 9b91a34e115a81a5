"""Nominal description of a plenoptic camera, as a spec sheet and a lab notebook give it.

A :class:`CameraSpec` holds only values a user can write down before calibrating: the
main-lens focal length and f-number, the magnification, the sensor and the microlens
array. What calibration measures (the exact lenslet grid, the volumetric mapping) lives in
the calibration file, never here.

Optics model (see ``docs/conventions.md``): a thin main lens images the nominal focal
plane (object distance ``object_distance_mm``) onto the microlens array (image distance
``image_distance_mm``); the sensor sits one microlens focal length behind the array.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import MISSING, asdict, dataclass, fields, replace
from pathlib import Path
from typing import Literal

from .errors import CameraSpecError
from .io import atomic_write_text

__all__ = ["CameraSpec", "PRESETS", "preset", "load_camera", "save_camera"]

GridType = Literal["hex", "rect"]


@dataclass(frozen=True)
class CameraSpec:
    """Nominal plenoptic camera.

    Parameters
    ----------
    focal_length_mm : float
        Main-lens focal length F, mm.
    f_number : float
        Main-lens (object-side, catalogue) f-number N = F / D, D the aperture diameter.
    magnification : float
        Lateral magnification of the nominal focal plane onto the microlens array,
        negative for the usual inverted real image (e.g. -0.5).
    pixel_pitch_um : float
        Sensor pixel pitch, micrometres (square pixels).
    sensor_shape_px : (int, int)
        Sensor size as (rows, cols), pixels.
    microlens_pitch_um : float
        Centre-to-centre spacing of neighbouring microlenses along a lens row, micrometres.
    microlens_focal_length_um : float
        Microlens focal length, equal to its distance from the sensor, micrometres.
    grid_shape : (int, int)
        Number of microlenses as (rows, cols).
    grid_type : {"hex", "rect"}
        Hexagonal (rows horizontal, every other row shifted by half a pitch) or
        rectangular microlens packing.
    bit_depth : int
        Number of significant bits in the raw image (stored in uint16).
    name : str
        Free-form label.
    """

    focal_length_mm: float
    f_number: float
    magnification: float
    pixel_pitch_um: float
    sensor_shape_px: tuple[int, int]
    microlens_pitch_um: float
    microlens_focal_length_um: float
    grid_shape: tuple[int, int]
    grid_type: GridType = "hex"
    bit_depth: int = 12
    name: str = "custom"

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor_shape_px", tuple(int(v) for v in self.sensor_shape_px))
        object.__setattr__(self, "grid_shape", tuple(int(v) for v in self.grid_shape))
        positive = ("focal_length_mm", "f_number", "pixel_pitch_um", "microlens_pitch_um",
                    "microlens_focal_length_um")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise CameraSpecError(f"{name} must be a positive number; got {value!r}")
        if not (math.isfinite(self.magnification) and self.magnification != 0):
            raise CameraSpecError(f"magnification must be non-zero; got {self.magnification!r}")
        if self.grid_type not in ("hex", "rect"):
            raise CameraSpecError(f"grid_type must be 'hex' or 'rect'; got {self.grid_type!r}")
        for name in ("sensor_shape_px", "grid_shape"):
            shape = getattr(self, name)
            if len(shape) != 2 or min(shape) < 1:
                raise CameraSpecError(f"{name} must be two positive integers (rows, cols); got {shape!r}")
        if not 1 <= self.bit_depth <= 16:
            raise CameraSpecError(f"bit_depth must be between 1 and 16; got {self.bit_depth!r}")

    # --- derived first-order optics -------------------------------------------------
    @property
    def image_distance_mm(self) -> float:
        """Main lens to microlens array distance ``s_i = F (1 + |M|)``, mm."""
        return self.focal_length_mm * (1.0 + abs(self.magnification))

    @property
    def object_distance_mm(self) -> float:
        """Main lens to nominal focal plane distance ``s_o = F (1 + 1/|M|)``, mm."""
        return self.focal_length_mm * (1.0 + 1.0 / abs(self.magnification))

    @property
    def aperture_diameter_mm(self) -> float:
        """Main-lens aperture (entrance pupil) diameter D = F / N, mm."""
        return self.focal_length_mm / self.f_number

    @property
    def image_side_f_number(self) -> float:
        """Working f-number on the image side, s_i / D."""
        return self.image_distance_mm / self.aperture_diameter_mm

    @property
    def microlens_f_number(self) -> float:
        """Microlens f-number, focal length / pitch."""
        return self.microlens_focal_length_um / self.microlens_pitch_um

    @property
    def pixels_per_lenslet(self) -> float:
        """Nominal microlens pitch in sensor pixels (microlens images are slightly larger)."""
        return self.microlens_pitch_um / self.pixel_pitch_um

    @property
    def row_pitch_um(self) -> float:
        """Spacing of microlens rows, micrometres (pitch * sqrt(3)/2 for hex)."""
        return self.microlens_pitch_um * (math.sqrt(3) / 2 if self.grid_type == "hex" else 1.0)

    @property
    def sensor_size_mm(self) -> tuple[float, float]:
        """Sensor (height, width), mm."""
        rows, cols = self.sensor_shape_px
        return rows * self.pixel_pitch_um * 1e-3, cols * self.pixel_pitch_um * 1e-3

    @property
    def full_scale(self) -> int:
        """Largest raw value, 2**bit_depth - 1."""
        return (1 << self.bit_depth) - 1

    def image_distance_for_depth(self, z_mm):
        """Thin-lens image distance (mm) of an object at depth ``z_mm`` (z = 0 at focus)."""
        s = self.object_distance_mm + z_mm
        return 1.0 / (1.0 / self.focal_length_mm - 1.0 / s)

    def alpha_for_depth(self, z_mm):
        """Refocus parameter alpha = d(z) / s_i of the plane conjugate to depth ``z_mm``.

        alpha < 1 for objects behind the focal plane (z > 0), > 1 in front of it.
        """
        return self.image_distance_for_depth(z_mm) / self.image_distance_mm

    def depth_for_alpha(self, alpha):
        """Inverse of :meth:`alpha_for_depth`: object depth z (mm) whose image lies at alpha."""
        d = alpha * self.image_distance_mm
        return 1.0 / (1.0 / self.focal_length_mm - 1.0 / d) - self.object_distance_mm

    def with_changes(self, **changes) -> "CameraSpec":
        """Return a copy with some fields replaced (validated again)."""
        return replace(self, **changes)

    def with_magnification(self, magnification: float) -> "CameraSpec":
        """Return the camera refocused to another magnification, aperture re-set to match.

        Changing the magnification moves the main lens away from the sensor, which raises
        the image-side working f-number ``N (1 + |m|)``; a user re-sets the aperture so
        that the microlens images still fill their pitch without overlapping. The
        f-number is scaled so the working f-number stays what it was (rounded to 4
        decimals).

        Parameters
        ----------
        magnification : float
            New lateral magnification (negative for a real, inverted image).

        Returns
        -------
        CameraSpec

        Examples
        --------
        >>> cam = preset("small").with_magnification(-0.3)
        >>> round(cam.image_side_f_number, 2) == round(preset("small").image_side_f_number, 2)
        True
        """
        m = float(magnification)
        if not (math.isfinite(m) and m != 0):
            raise CameraSpecError(f"magnification must be a non-zero number; got {magnification!r}")
        f_number = self.f_number * (1.0 + abs(self.magnification)) / (1.0 + abs(m))
        return replace(self, magnification=m, f_number=round(f_number, 4))

    @property
    def microlens_fill(self) -> float:
        """Microlens-image diameter over the microlens pitch: ``N_microlens / N_working``.

        Above 1 the microlens images overlap and cannot be separated.
        """
        return self.microlens_f_number / self.image_side_f_number

    def to_dict(self) -> dict:
        d = asdict(self)
        d["sensor_shape_px"] = list(self.sensor_shape_px)
        d["grid_shape"] = list(self.grid_shape)
        return d

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "camera description") -> "CameraSpec":
        known = {f.name for f in fields(cls)}
        if not isinstance(data, dict):
            raise CameraSpecError(f"{source}: the camera must be a table of {sorted(known)}; "
                                  f"got {type(data).__name__}")
        unknown = sorted(set(data) - known)
        if unknown:
            raise CameraSpecError(f"{source}: unknown key(s) {unknown}; allowed: {sorted(known)}")
        required = {f.name for f in fields(cls) if f.default is MISSING}
        missing = sorted(k for k in required if k not in data)
        if missing:
            raise CameraSpecError(f"{source}: missing key(s) {missing}")
        try:
            return cls(**data)
        except CameraSpecError as exc:
            raise CameraSpecError(f"{source}: {exc}") from None
        except (TypeError, ValueError) as exc:
            raise CameraSpecError(f"{source}: {exc}") from None


def _matched_f_number(focal_length_mm: float, magnification: float,
                      microlens_pitch_um: float, microlens_focal_length_um: float) -> float:
    """Object-side f-number whose image-side working f-number equals the microlenses'."""
    return (microlens_focal_length_um / microlens_pitch_um) / (1.0 + abs(magnification))


def _hall2019() -> CameraSpec:
    return CameraSpec(
        name="hall2019",
        focal_length_mm=105.0,
        f_number=round(_matched_f_number(105.0, -0.5, 77.0, 308.0), 4),
        magnification=-0.5,
        pixel_pitch_um=5.5,
        sensor_shape_px=(4400, 6600),
        microlens_pitch_um=77.0,
        microlens_focal_length_um=308.0,
        grid_shape=(362, 471),
        grid_type="hex",
    )


def _small() -> CameraSpec:
    base = _hall2019()
    # 64 x 48 lenslets: 64 * 14 px wide, 48 rows of 12.1 px (hex row spacing) high.
    return base.with_changes(name="small", sensor_shape_px=(600, 910), grid_shape=(49, 65))


def _small_rect() -> CameraSpec:
    base = _hall2019()
    return base.with_changes(name="small-rect", grid_type="rect",
                             sensor_shape_px=(700, 910), grid_shape=(50, 65))


PRESETS = {"hall2019": _hall2019, "small": _small, "small-rect": _small_rect}


def preset(name: str) -> CameraSpec:
    """Return a named camera preset: ``hall2019``, ``small`` or ``small-rect``."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise CameraSpecError(f"unknown camera preset {name!r}; choose one of {sorted(PRESETS)}") from None


def load_camera(path: str | Path) -> CameraSpec:
    """Read a ``camera.toml`` file (keys as the :class:`CameraSpec` fields)."""
    path = Path(path)
    if not path.is_file():
        raise CameraSpecError(f"{path}: camera description not found; write one (see README) "
                              "or use a preset")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CameraSpecError(f"{path}: not valid TOML ({exc})") from None
    data = data.get("camera", data)
    return CameraSpec.from_dict(data, source=str(path))


def save_camera(camera: CameraSpec, path: str | Path) -> Path:
    """Write ``camera`` as TOML (atomically) and return the path."""
    import tomli_w

    text = "# plenoptrack nominal camera description (spec-sheet values)\n" + tomli_w.dumps(
        {"camera": camera.to_dict()})
    return atomic_write_text(path, text)
