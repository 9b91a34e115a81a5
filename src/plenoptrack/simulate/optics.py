"""The true optics of a simulated camera: the perturbed microlens array and lens distortion.

A :class:`SimOptics` is what the simulator knows and a calibration has to recover: the
exact microlens lattice (rotation, sub-pixel offset, pitch error) and the radial
distortion of the main lens. It is built from a nominal :class:`~plenoptrack.CameraSpec`
by :func:`make_optics`, which draws the perturbation from a seed.

Coordinates follow ``docs/conventions.md``. Camera frame ``(X, Y, Z)`` in mm: origin at
the main-lens centre, ``X`` along sensor columns, ``Y`` along sensor rows, ``Z`` towards
the object. The microlens array (MLA) lies at ``Z = -s_i``, the sensor at
``Z = -(s_i + f_ml)``. Sensor pixel ``(row, col)`` has its centre at
``X = (col - (cols - 1) / 2) * pp``, ``Y = (row - (rows - 1) / 2) * pp``.
World and camera frames relate by ``x = -X``, ``y = -Y``, ``z = Z - s_o``.

Microlens model. Physical lens ``(i, j)`` is centred (MLA plane, mm) at::

    C(i, j) = R(theta) @ ((j + shift * (i % 2)) * p', i * row_step) + offset

with ``p'`` the true pitch, ``row_step = p' * sqrt(3) / 2`` and ``shift = 0.5`` for a
hexagonal array, ``row_step = p'`` and ``shift = 0`` for a rectangular one; ``R(theta)``
turns ``+X`` towards ``+Y``. Lens ``(0, 0)`` sits on the optical axis before the offset.
The image of the main-lens aperture behind lens ``k`` is centred at
``C_k * (1 + f_ml / s_i)`` on the sensor (:attr:`SimOptics.true_grid`).

Distortion model. A ray leaving the MLA plane at ``Q`` reaches the nominal focal plane
(``Z = s_o``) at ``-Q * (s_o / s_i) * (1 + k1 rho^2 + k2 rho^4)``, with ``rho`` the
undistorted lateral radius in the focal plane divided by the half-diagonal of the
focal-plane field of view (equivalently ``|Q|`` over the sensor half-diagonal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..camera import CameraSpec
from ..errors import CalibrationError, CameraSpecError
from ..lightfield.lattice import LensletGrid
from .realism import Realism, SpecEffects, realism_from_dict

__all__ = ["SimOptics", "make_optics", "true_camera", "ROTATION_RANGE_DEG", "OFFSET_RANGE_PX",
           "PITCH_ERROR_RANGE"]

ROTATION_RANGE_DEG = (0.05, 0.5)
"""Range of the magnitude of the drawn MLA rotation, degrees (the sign is random)."""
OFFSET_RANGE_PX = 0.5
"""The drawn MLA offset is uniform in +-this many sensor pixels on each axis."""
PITCH_ERROR_RANGE = 0.002
"""The drawn relative pitch error is uniform in +-this (0.2 %)."""

_FORMAT_VERSION = 1


@dataclass(frozen=True)
class SimOptics:
    """True optics of a simulated plenoptic camera.

    Parameters
    ----------
    camera : CameraSpec
        Nominal camera; its first-order optics (F, N, M, pixel and microlens values) are
        taken as exact, only the microlens array placement and the distortion differ.
    rotation_deg : float
        Rotation theta of the MLA about the optical axis, degrees; positive turns lens
        rows so that the sensor row index grows with the column index.
    offset_mm : (float, float)
        Translation (X, Y) of the MLA in its plane, camera frame, mm.
    pitch_scale : float
        True microlens pitch over the nominal pitch (1.001 = 0.1 % larger).
    k1, k2 : float
        Radial distortion coefficients of the main lens (see module notes).
    seed : int or None
        Seed the perturbation was drawn from; also seeds the fixed patterns of the
        camera (sensor maps, dust) when ``realism`` enables them.
    realism : Realism
        Effects beyond the geometric model that rendering applies (see
        :mod:`.realism`); default ideal.
    nominal : CameraSpec or None
        The spec-sheet camera a user would write into ``camera.toml`` when it differs
        from the true ``camera`` (focal lengths and f-number off by a few per cent); None
        when they agree.
    """

    camera: CameraSpec
    rotation_deg: float = 0.0
    offset_mm: tuple[float, float] = (0.0, 0.0)
    pitch_scale: float = 1.0
    k1: float = 0.0
    k2: float = 0.0
    seed: int | None = field(default=None)
    realism: Realism = field(default_factory=Realism.ideal)
    nominal: CameraSpec | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.camera, CameraSpec):
            raise CameraSpecError(f"camera must be a CameraSpec; got {type(self.camera).__name__}")
        off = tuple(float(v) for v in self.offset_mm)
        if len(off) != 2 or not all(math.isfinite(v) for v in off):
            raise CameraSpecError(f"offset_mm must be two finite numbers (X, Y); got {self.offset_mm!r}")
        object.__setattr__(self, "offset_mm", off)
        for name in ("rotation_deg", "pitch_scale", "k1", "k2"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise CameraSpecError(f"{name} must be finite; got {value!r}")
            object.__setattr__(self, name, value)
        if not 0.9 < self.pitch_scale < 1.1:
            raise CameraSpecError(f"pitch_scale must be within 10 % of 1; got {self.pitch_scale}")
        if abs(self.rotation_deg) > 10:
            raise CameraSpecError(f"rotation_deg must be within +-10 degrees; got {self.rotation_deg}")
        if not isinstance(self.realism, Realism):
            raise CameraSpecError(f"realism must be a Realism; got {type(self.realism).__name__}")
        if self.nominal is not None and not isinstance(self.nominal, CameraSpec):
            raise CameraSpecError(f"nominal must be a CameraSpec or None; got {type(self.nominal).__name__}")

    @property
    def nominal_camera(self) -> CameraSpec:
        """The spec-sheet camera (``camera.toml``): ``nominal`` if set, else ``camera``."""
        return self.camera if self.nominal is None else self.nominal

    # --- first-order optics, mm ---------------------------------------------------------
    @property
    def s_i(self) -> float:
        """Main lens to MLA distance, mm."""
        return self.camera.image_distance_mm

    @property
    def s_o(self) -> float:
        """Main lens to nominal focal plane distance, mm."""
        return self.camera.object_distance_mm

    @property
    def f_ml(self) -> float:
        """Microlens focal length (MLA to sensor distance), mm."""
        return self.camera.microlens_focal_length_um * 1e-3

    @property
    def aperture_radius(self) -> float:
        """Main-lens aperture radius D / 2, mm."""
        return 0.5 * self.camera.aperture_diameter_mm

    @property
    def pixel_pitch(self) -> float:
        """Sensor pixel pitch, mm."""
        return self.camera.pixel_pitch_um * 1e-3

    @property
    def pitch(self) -> float:
        """True microlens pitch p' along a lens row, mm."""
        return self.camera.microlens_pitch_um * 1e-3 * self.pitch_scale

    @property
    def row_step(self) -> float:
        """Distance between consecutive lens rows, mm."""
        return self.pitch * (math.sqrt(3) / 2 if self.camera.grid_type == "hex" else 1.0)

    @property
    def odd_row_shift(self) -> float:
        """Shift of odd lens rows along a row, in pitches (0.5 hex, 0 rect)."""
        return 0.5 if self.camera.grid_type == "hex" else 0.0

    @property
    def image_scale(self) -> float:
        """Scale 1 + f_ml / s_i from physical lens centres to their image centres."""
        return 1.0 + self.f_ml / self.s_i

    @property
    def cell_radius(self) -> float:
        """Circumradius of a microlens cell (hexagon or square), mm."""
        return self.pitch / (math.sqrt(3) if self.camera.grid_type == "hex" else math.sqrt(2))

    @property
    def distortion_radius_mm(self) -> float:
        """MLA-plane radius at which rho = 1 (the sensor half-diagonal), mm."""
        rows, cols = self.camera.sensor_shape_px
        return 0.5 * math.hypot(rows, cols) * self.pixel_pitch

    @property
    def lattice_vectors(self) -> tuple[np.ndarray, np.ndarray]:
        """Physical lattice steps ``(e1, e2)`` as (X, Y) mm: along a lens row, to the next row."""
        t = math.radians(self.rotation_deg)
        c, s = math.cos(t), math.sin(t)
        e1 = np.array([c, s]) * self.pitch
        e2 = np.array([-s, c]) * self.row_step
        return e1, e2

    # --- lattice ------------------------------------------------------------------------
    def lens_centers_mm(self, i, j) -> np.ndarray:
        """Physical centres of lenses ``(i, j)`` in the MLA plane, ``(..., 2)`` as (X, Y) mm."""
        i = np.asarray(i, dtype=np.int64)
        j = np.asarray(j, dtype=np.int64)
        e1, e2 = self.lattice_vectors
        a = j + self.odd_row_shift * (i & 1)
        return a[..., None] * e1 + i[..., None] * e2 + np.asarray(self.offset_mm)

    def lattice_coords(self, points_mm) -> np.ndarray:
        """Continuous lattice coordinates ``(i, a)`` of MLA-plane points ``(..., 2)`` (X, Y) mm.

        ``i`` counts lens rows, ``a`` pitches along a row (odd-row shift not removed).
        """
        p = np.asarray(points_mm, dtype=float) - np.asarray(self.offset_mm)
        e1, e2 = self.lattice_vectors
        a = p @ e1 / self.pitch ** 2
        i = p @ e2 / self.row_step ** 2
        return np.stack([i, a], axis=-1)

    def mla_to_pixels(self, points_mm) -> np.ndarray:
        """Sensor position ``(..., 2)`` (row, col) px of the image of MLA-plane points.

        An MLA-plane point ``Q`` (X, Y mm) maps to ``Q * (1 + f_ml / s_i)`` on the sensor,
        the scaling that carries lens centres onto their image centres.
        """
        p = np.asarray(points_mm, dtype=float) * self.image_scale / self.pixel_pitch
        rows, cols = self.camera.sensor_shape_px
        return np.stack([p[..., 1] + (rows - 1) / 2, p[..., 0] + (cols - 1) / 2], axis=-1)

    def pixels_to_sensor_mm(self, points_px) -> np.ndarray:
        """Camera-frame sensor coordinates ``(..., 2)`` (X, Y) mm of pixel positions (row, col)."""
        p = np.asarray(points_px, dtype=float)
        rows, cols = self.camera.sensor_shape_px
        pp = self.pixel_pitch
        return np.stack([(p[..., 1] - (cols - 1) / 2) * pp, (p[..., 0] - (rows - 1) / 2) * pp], axis=-1)

    @property
    def true_grid(self) -> LensletGrid:
        """Lattice of microlens-image centres on the sensor, covering the whole sensor."""
        return _true_grid(self)

    # --- object space -------------------------------------------------------------------
    def distortion_factor(self, q_radius_mm):
        """``1 + k1 rho^2 + k2 rho^4`` for an MLA-plane radius ``|Q|`` (mm)."""
        rho2 = (np.asarray(q_radius_mm, dtype=float) / self.distortion_radius_mm) ** 2
        return 1.0 + self.k1 * rho2 + self.k2 * rho2 * rho2

    def focal_plane_to_mla(self, points_mm) -> np.ndarray:
        """Invert the distorted conjugation: MLA-plane points of focal-plane points.

        Parameters
        ----------
        points_mm : (..., 2) float
            Points (X, Y) of the nominal focal plane, camera frame, mm.

        Returns
        -------
        (..., 2) float ndarray
            Points ``Q`` (X, Y) of the MLA plane, mm, such that
            ``-Q * (s_o / s_i) * g(|Q|)`` equals the input; found by fixed-point iteration.
        """
        target = -np.asarray(points_mm, dtype=float) * (self.s_i / self.s_o)
        radius = np.hypot(target[..., 0], target[..., 1])
        q = radius.copy()
        for _ in range(50):
            q = radius / self.distortion_factor(q)
        scale = np.divide(q, radius, out=np.ones_like(radius), where=radius > 0)
        return target * scale[..., None]

    def world_to_mla(self, xyz_mm) -> np.ndarray:
        """MLA-plane point of the chief ray (through the aperture centre) of world points.

        Parameters
        ----------
        xyz_mm : (..., 3) float
            World points (x, y, z), mm.

        Returns
        -------
        (..., 2) float ndarray
            (X, Y) in the MLA plane, mm. For a point on the focal plane (z = 0) every ray
            from it converges there; for other depths it is the centre of its blur.
        """
        xyz = np.asarray(xyz_mm, dtype=float)
        big_z = xyz[..., 2] + self.s_o
        focal = np.stack([-xyz[..., 0], -xyz[..., 1]], axis=-1) * (self.s_o / big_z)[..., None]
        return self.focal_plane_to_mla(focal)

    def world_to_pixels(self, xyz_mm) -> np.ndarray:
        """Sensor position (row, col) px predicted for world points, ``(..., 2)``.

        Chief ray to the MLA plane (:meth:`world_to_mla`), then the image-centre scaling
        (:meth:`mla_to_pixels`): where the particle shows up in the central view.
        """
        return self.mla_to_pixels(self.world_to_mla(xyz_mm))

    # --- serialisation ------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-ready description of the true optics (the ``truth_optics.json`` content)."""
        return {
            "format": "plenoptrack-sim-optics",
            "version": _FORMAT_VERSION,
            "camera": self.camera.to_dict(),
            "nominal_camera": self.nominal_camera.to_dict(),
            "seed": self.seed,
            "realism": self.realism.to_dict(),
            "mla": {
                "rotation_deg": self.rotation_deg,
                "offset_mm": list(self.offset_mm),
                # (row, col) pixels: Y then X
                "offset_px": [self.offset_mm[1] / self.pixel_pitch,
                              self.offset_mm[0] / self.pixel_pitch],
                "pitch_scale": self.pitch_scale,
                "pitch_mm": self.pitch,
                "image_scale": self.image_scale,
            },
            "distortion": {
                "k1": self.k1, "k2": self.k2,
                "radius_mla_mm": self.distortion_radius_mm,
                "radius_focal_plane_mm": self.distortion_radius_mm * self.s_o / self.s_i,
            },
            "true_grid": self.true_grid.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "simulator optics") -> "SimOptics":
        """Rebuild from :meth:`to_dict` output; checks the stored grid agrees."""
        try:
            if data.get("format") != "plenoptrack-sim-optics":
                raise KeyError("format")
            mla, dist = data["mla"], data["distortion"]
            optics = cls(camera=CameraSpec.from_dict(data["camera"], source=source),
                         rotation_deg=mla["rotation_deg"], offset_mm=tuple(mla["offset_mm"]),
                         pitch_scale=mla["pitch_scale"], k1=dist["k1"], k2=dist["k2"],
                         seed=data.get("seed"),
                         realism=realism_from_dict(data.get("realism", {"mode": "ideal"}),
                                                   source=f"{source} realism"),
                         nominal=None if "nominal_camera" not in data else
                         CameraSpec.from_dict(data["nominal_camera"], source=source))
            if optics.nominal == optics.camera:
                optics = replace(optics, nominal=None)
        except (KeyError, TypeError, AttributeError) as exc:
            raise CalibrationError(f"{source}: not a simulator optics description "
                                   f"(missing or bad {exc})") from None
        if "true_grid" in data:
            stored = LensletGrid.from_dict(data["true_grid"], source=source)
            if not np.allclose(stored.origin_px, optics.true_grid.origin_px, atol=1e-9):
                raise CalibrationError(f"{source}: stored true_grid does not match the MLA "
                                       "parameters; the file was edited or is corrupt")
        return optics


def _true_grid(optics: SimOptics) -> LensletGrid:
    cam = optics.camera
    rows, cols = cam.sensor_shape_px
    # Sensor corners (half a pixel out) mapped back to the physical MLA lattice.
    corners_px = np.array([[-0.5, -0.5], [-0.5, cols - 0.5], [rows - 0.5, -0.5],
                           [rows - 0.5, cols - 0.5]])
    corners = optics.pixels_to_sensor_mm(corners_px) / optics.image_scale
    ia = optics.lattice_coords(corners)
    i0 = int(math.floor(ia[:, 0].min()))
    i0 -= i0 & 1  # even first row: the odd-row shift keeps its meaning on the grid
    i1 = int(math.ceil(ia[:, 0].max()))
    j0 = int(math.floor(ia[:, 1].min())) - 1
    j1 = int(math.ceil(ia[:, 1].max())) + 1
    e1, e2 = optics.lattice_vectors
    k = optics.image_scale / optics.pixel_pitch
    origin = optics.mla_to_pixels(optics.lens_centers_mm(i0, j0))
    return LensletGrid(
        grid_type=cam.grid_type,
        shape=(i1 - i0 + 1, j1 - j0 + 1),
        origin_px=tuple(origin),
        col_step_px=(e1[1] * k, e1[0] * k),
        row_step_px=(e2[1] * k, e2[0] * k),
        odd_row_shift=optics.odd_row_shift,
        sensor_shape_px=(rows, cols),
    )


def true_camera(nominal: CameraSpec, spec: SpecEffects, rng: np.random.Generator) -> CameraSpec:
    """Draw the true first-order optics of a camera whose spec sheet says ``nominal``.

    The main-lens and microlens focal lengths are drawn uniformly within the relative
    errors of ``spec``; the magnification (set by focusing on a target) and everything on
    the sensor side stay nominal. The aperture is set as a user sets it, by looking at a
    white image: from the f-number at which the true microlens images just touch, stopped
    down by up to ``f_number_mismatch`` (never wider: the images would overlap). Draws, in order: focal length and microlens focal length (uniform in [-1, 1)),
    f-number (uniform in [0, 1)); always three, whatever the sizes.
    """
    e = rng.uniform(-1.0, 1.0, size=2)
    stop = rng.uniform(0.0, 1.0)
    f_ml = nominal.microlens_focal_length_um * (1.0 + spec.microlens_focal_length_error * e[1])
    matched = (f_ml / nominal.microlens_pitch_um) / (1.0 + abs(nominal.magnification))
    return nominal.with_changes(
        focal_length_mm=nominal.focal_length_mm * (1.0 + spec.focal_length_error * e[0]),
        microlens_focal_length_um=f_ml,
        f_number=matched * (1.0 + spec.f_number_mismatch * stop))


def make_optics(camera: CameraSpec, seed: int | np.random.Generator | None = 0, *,
                k1: float = 0.02, k2: float = -0.005,
                realism: "Realism | str | None" = None) -> SimOptics:
    """Draw the true optics of a simulated camera.

    Parameters
    ----------
    camera : CameraSpec
        Nominal camera description.
    seed : int or numpy.random.Generator
        Seed of ``numpy.random.default_rng``; the draws are, in order, the rotation
        magnitude (uniform in :data:`ROTATION_RANGE_DEG`, degrees), its sign, the offset
        along X then Y (uniform in +-:data:`OFFSET_RANGE_PX` pixels) and the relative pitch
        error (uniform in +-:data:`PITCH_ERROR_RANGE`).
    k1, k2 : float
        Radial distortion coefficients (not drawn).
    realism : Realism, "ideal", "realistic" or None
        Effects beyond the geometric model (default ideal). With ``realism.spec`` on, the
        true focal lengths and f-number are drawn after the MLA perturbation
        (:func:`true_camera`) and ``camera`` is kept as ``optics.nominal``.

    Returns
    -------
    SimOptics
        The perturbed optics; ``optics.true_grid`` is the lattice of microlens-image
        centres a grid calibration should find.

    Examples
    --------
    >>> from plenoptrack import preset
    >>> optics = make_optics(preset("small"), seed=1)
    >>> 0.05 <= abs(optics.rotation_deg) <= 0.5
    True
    """
    if not isinstance(camera, CameraSpec):
        raise CameraSpecError(f"camera must be a CameraSpec; got {type(camera).__name__}")
    rng = np.random.default_rng(seed)
    magnitude = rng.uniform(*ROTATION_RANGE_DEG)
    sign = 1.0 if rng.random() < 0.5 else -1.0
    pp = camera.pixel_pitch_um * 1e-3
    offset = rng.uniform(-OFFSET_RANGE_PX, OFFSET_RANGE_PX, size=2) * pp
    pitch_scale = 1.0 + rng.uniform(-PITCH_ERROR_RANGE, PITCH_ERROR_RANGE)
    recorded = seed if isinstance(seed, (int, np.integer)) else None
    realism = Realism.of(realism)
    true = camera
    if realism.spec.enabled:
        true = true_camera(camera, realism.spec, rng)
    return SimOptics(camera=true, rotation_deg=sign * magnitude,
                     offset_mm=(float(offset[0]), float(offset[1])),
                     pitch_scale=float(pitch_scale), k1=k1, k2=k2,
                     seed=None if recorded is None else int(recorded), realism=realism,
                     nominal=None if true == camera else camera)
