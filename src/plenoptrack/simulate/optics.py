"""The true optics of a simulated camera: the perturbed microlens array and the main lens.

A :class:`SimOptics` is what the simulator knows and a calibration has to recover: the
exact microlens lattice (rotation, sub-pixel offset, pitch error), the radial distortion
of the main lens and, with the ``lens`` effect group of :mod:`.realism`, its Seidel
aberrations, cat's-eye vignetting, an optical axis off the sensor centre and a tilted
microlens array. It is built from a nominal :class:`~plenoptrack.CameraSpec` by
:func:`make_optics`, which draws the perturbation from a seed.

Coordinates follow ``docs/conventions.md``. Camera frame ``(X, Y, Z)`` in mm: ``X`` along
sensor columns, ``Y`` along sensor rows, ``Z`` towards the object, ``Z = 0`` on the
main-lens plane; the origin lies on the normal through the sensor centre. The optical
axis runs parallel to ``Z`` through ``(X, Y) = a`` (:attr:`SimOptics.axis_offset_mm`,
zero unless the ``lens`` group draws it); the main-lens centre is ``(a, 0)``. The
microlens array (MLA) lies at ``Z = -s_i``, the sensor at ``Z = -(s_i + f_ml)``. Sensor
pixel ``(row, col)`` has its centre at ``X = (col - (cols - 1) / 2) * pp``,
``Y = (row - (rows - 1) / 2) * pp``. World and camera frames relate by ``x = -(X - a_x)``,
``y = -(Y - a_y)``, ``z = Z - s_o``: the world origin is on the optical axis, in the
nominal focal plane. Focal-plane points are given relative to the axis
(``(X - a_x, Y - a_y)``), MLA-plane and sensor points in the camera frame.

Microlens model. Physical lens ``(i, j)`` is centred (MLA plane, mm) at::

    C(i, j) = R(theta) @ ((j + shift * (i % 2)) * p', i * row_step) + offset

with ``p'`` the true pitch, ``row_step = p' * sqrt(3) / 2`` and ``shift = 0.5`` for a
hexagonal array, ``row_step = p'`` and ``shift = 0`` for a rectangular one; ``R(theta)``
turns ``+X`` towards ``+Y``. Lens ``(0, 0)`` sits on the sensor-centre normal before the
offset. The image of the main-lens aperture behind lens ``k`` is centred where the ray
from the main-lens centre through ``C_k`` meets the sensor,
``a + (C_k - a) * (s_i + f_ml) / (s_i - delta_k)`` (:meth:`SimOptics.lens_image_centers_px`),
with ``delta_k = 0`` unless the MLA is tilted.

Distortion model. A ray leaving the MLA plane at ``Q`` reaches the nominal focal plane
(``Z = s_o``) at ``-(Q - a) * (s_o / s_i) * (1 + k1 rho^2 + k2 rho^4)`` (relative to the
axis), with ``rho`` the undistorted lateral radius in the focal plane divided by the
half-diagonal of the focal-plane field of view (equivalently ``|Q - a|`` over the sensor
half-diagonal ``R_N``).

Lens effects (:class:`~.realism.LensEffects`; all off in the ideal model).

* Per-camera draws (:func:`make_optics`): ``k1``, ``k2`` perturbed by normal draws of the
  given sigmas; the axis offset ``a`` uniform in a disc of radius ``axis_offset_px``; the
  MLA tilt, a direction uniform in angle and a tilt angle uniform up to ``mla_tilt_deg``.
* Seidel terms are transverse ray errors ``eps`` added to a ray's aim point on the nominal
  focal plane, as functions of the pupil point ``H`` (main-lens plane, relative to the
  axis; ``p = H / (D / 2)``) and of the field vector ``rho = (Q - a) / R_N``. A ray aimed
  at a focal-plane point displaced by ``H dz / s_o`` is the ray of a point focused at
  depth ``dz``, so with ``F`` = ``field_curvature_mm``, ``A`` = ``astigmatism_mm``::

      eps_defocus = [(-F + A / 2) |rho|^2 H - A (H . rho) rho] / s_o

  which puts the best (medial) focus at ``z = -F |rho|^2`` (towards the camera, as the
  Petzval surface of a positive lens), the sagittal focus at ``z = (-F + A/2) |rho|^2``
  and the tangential focus (pupil component along the field direction) at
  ``z = (-F - A/2) |rho|^2``: ``A`` apart at the field edge. Coma, with
  ``c = coma_mm / 3``::

      eps_coma = c [|p|^2 rho + 2 (p . rho) p]

  (``rho`` points away from the focal-plane image of ``Q``: the conjugation inverts). As
  seen from the object side, a point at the field edge imaged through pupil point
  ``p`` appears displaced by ``c [|p|^2 u + 2 (p . u) p]`` (``u`` the outward field
  vector in the focal plane, ``|u| = |rho|``): a comet whose tail points away from the
  axis, ``3 c = coma_mm`` long at the field edge for a ray through the aperture rim in
  the tangential plane (positive coma). The chief ray (``H = 0``) is unaffected, so
  :meth:`SimOptics.world_to_pixels` is unchanged.
* Cat's-eye vignetting: a second circular stop (the front lens rim) of radius ``R_v`` at
  ``Z = L`` on the axis (:attr:`SimOptics.front_stop`). The cone of the field-edge point
  (chief-ray slope ``R_N / s_i``) crosses ``Z = L`` as a disc of radius
  ``D/2 (1 - L / s_o)`` centred ``L R_N / s_i`` off the axis; ``R_v`` is
  ``1 - vignetting_radius_ratio`` times the radius needed to pass all of it. ``L`` is
  chosen so that points within half the field radius are not vignetted (capped at
  ``0.8 s_o``).
* MLA tilt: the array is turned about an axis through the sensor-centre normal, so the
  microlens-to-sensor distance is ``d_k = f_ml + delta_k``, ``delta_k = t . C_k``
  (:attr:`SimOptics.mla_tilt`, slopes), and lens ``k`` lies ``s_i - delta_k`` from the
  main lens. Each microlens is treated as perpendicular to the axis at that distance
  (its own tilt changes its focus by under 0.1 um). The image centres scale by
  ``(s_i + f_ml) / (s_i - delta_k)``: not a lattice any more; the aperture images grow
  with ``d_k`` and blur by the defocus ``delta_k``. :attr:`SimOptics.true_grid` is then
  the least-squares lattice through the exact image centres of all its lenses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..camera import CameraSpec
from ..errors import CalibrationError, CameraSpecError
from ..lightfield.lattice import LensletGrid
from .realism import GROUPS, Realism, SpecEffects, realism_from_dict

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
    axis_offset_mm : (float, float)
        Where the optical axis meets the sensor, relative to the sensor centre, (X, Y) mm
        (camera frame; ``axis_offset_px`` gives (row, col) pixels).
    mla_tilt : (float, float)
        Slopes ``t = (t_X, t_Y)`` of the MLA tilt: the microlens-to-sensor distance grows
        by ``t_X`` per mm of ``X`` and ``t_Y`` per mm of ``Y`` (from the sensor centre).
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
    axis_offset_mm: tuple[float, float] = (0.0, 0.0)
    mla_tilt: tuple[float, float] = (0.0, 0.0)
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
        for name in ("axis_offset_mm", "mla_tilt"):
            pair = tuple(float(v) for v in getattr(self, name))
            if len(pair) != 2 or not all(math.isfinite(v) for v in pair):
                raise CameraSpecError(f"{name} must be two finite numbers (X, Y); "
                                      f"got {getattr(self, name)!r}")
            object.__setattr__(self, name, pair)
        if math.hypot(*self.mla_tilt) > 0.1:
            raise CameraSpecError(f"mla_tilt slopes must be below 0.1 (5.7 degrees); "
                                  f"got {self.mla_tilt}")
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
    def axis_offset_px(self) -> tuple[float, float]:
        """Where the optical axis meets the sensor relative to its centre, (row, col) px."""
        return (self.axis_offset_mm[1] / self.pixel_pitch, self.axis_offset_mm[0] / self.pixel_pitch)

    @property
    def field_edge_slope(self) -> float:
        """Chief-ray slope ``R_N / s_i`` at the field edge (rho = 1) on the object side."""
        return self.distortion_radius_mm / self.s_i

    @property
    def front_stop(self) -> tuple[float, float] | None:
        """Cat's-eye vignetting stop ``(L, R_v)``: distance from the main lens and radius, mm.

        None without vignetting. See the module notes: ``R_v = (1 - v) R_need`` with
        ``R_need = L R_N / s_i + D/2 (1 - L / s_o)`` and ``L`` such that points within half
        the field radius pass unvignetted, ``L = v D/2 / (slope (1/2 - v) + v D/2 / s_o)``,
        capped at ``0.8 s_o``.
        """
        v = self.realism.lens.vignetting_radius_ratio
        if v <= 0:
            return None
        if v >= 1:
            raise CameraSpecError(f"vignetting_radius_ratio must be below 1; got {v}")
        r_ap, slope, s_o = self.aperture_radius, self.field_edge_slope, self.s_o
        den = slope * (0.5 - v) + v * r_ap / s_o
        dist = 0.8 * s_o if den <= 0 else min(v * r_ap / den, 0.8 * s_o)
        need = dist * slope + r_ap * (1.0 - dist / s_o)
        return dist, (1.0 - v) * need

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

        A point ``Q`` (X, Y mm) of the nominal MLA plane ``Z = -s_i`` maps along the ray
        from the main-lens centre to ``a + (Q - a) * (1 + f_ml / s_i)`` on the sensor, the
        scaling that carries lens centres onto their image centres (for a tilted MLA the
        lens centres are off that plane: :meth:`lens_image_centers_px`).
        """
        p = np.asarray(points_mm, dtype=float)
        if self.axis_offset_mm != (0.0, 0.0):
            a = np.asarray(self.axis_offset_mm)
            p = ((p - a) * self.image_scale + a) / self.pixel_pitch
        else:
            p = p * self.image_scale / self.pixel_pitch
        rows, cols = self.camera.sensor_shape_px
        return np.stack([p[..., 1] + (rows - 1) / 2, p[..., 0] + (cols - 1) / 2], axis=-1)

    def pixels_to_sensor_mm(self, points_px) -> np.ndarray:
        """Camera-frame sensor coordinates ``(..., 2)`` (X, Y) mm of pixel positions (row, col)."""
        p = np.asarray(points_px, dtype=float)
        rows, cols = self.camera.sensor_shape_px
        pp = self.pixel_pitch
        return np.stack([(p[..., 1] - (cols - 1) / 2) * pp, (p[..., 0] - (rows - 1) / 2) * pp], axis=-1)

    def mla_delta_mm(self, points_mm) -> np.ndarray:
        """Extra microlens-to-sensor distance ``t . C`` of the tilted MLA at points ``C``, mm."""
        p = np.asarray(points_mm, dtype=float)
        return p[..., 0] * self.mla_tilt[0] + p[..., 1] * self.mla_tilt[1]

    def lens_image_centers_px(self, i, j) -> np.ndarray:
        """Exact sensor centres ``(..., 2)`` (row, col) px of the images behind lenses ``(i, j)``.

        The ray from the main-lens centre through the lens centre meets the sensor at
        ``a + (C - a) (s_i + f_ml) / (s_i - delta)`` (``delta`` of the MLA tilt); with no tilt
        these are the nodes of :attr:`true_grid`.
        """
        c = self.lens_centers_mm(i, j)
        if self.mla_tilt == (0.0, 0.0):
            return self.mla_to_pixels(c)
        scale = (self.s_i + self.f_ml) / (self.s_i - self.mla_delta_mm(c))
        a = np.asarray(self.axis_offset_mm)
        p = ((c - a) * scale[..., None] + a) / self.pixel_pitch
        rows, cols = self.camera.sensor_shape_px
        return np.stack([p[..., 1] + (rows - 1) / 2, p[..., 0] + (cols - 1) / 2], axis=-1)

    @property
    def true_grid(self) -> LensletGrid:
        """Lattice of microlens-image centres on the sensor, covering the whole sensor.

        With a tilted MLA the image centres are not exactly a lattice (module notes): the
        grid is then the least-squares lattice through :meth:`lens_image_centers_px` of
        all its lenses (residuals up to about 0.1 px at the corners of ``hall2019`` with
        the default tilt).
        """
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
            Points of the nominal focal plane relative to the optical axis,
            ``(X - a_x, Y - a_y)``, mm.

        Returns
        -------
        (..., 2) float ndarray
            Points ``Q`` (X, Y) of the nominal MLA plane, camera frame, mm, such that
            ``-(Q - a) * (s_o / s_i) * g(|Q - a|)`` equals the input; found by fixed-point
            iteration.
        """
        target = -np.asarray(points_mm, dtype=float) * (self.s_i / self.s_o)
        radius = np.hypot(target[..., 0], target[..., 1])
        q = radius.copy()
        for _ in range(50):
            q = radius / self.distortion_factor(q)
        scale = np.divide(q, radius, out=np.ones_like(radius), where=radius > 0)
        out = target * scale[..., None]
        if self.axis_offset_mm != (0.0, 0.0):
            out = out + np.asarray(self.axis_offset_mm)
        return out

    def world_to_mla(self, xyz_mm) -> np.ndarray:
        """MLA-plane point of the chief ray (through the aperture centre) of world points.

        Parameters
        ----------
        xyz_mm : (..., 3) float
            World points (x, y, z), mm.

        Returns
        -------
        (..., 2) float ndarray
            (X, Y) in the nominal MLA plane, camera frame, mm. For a point on the focal
            plane (z = 0) every ray from it converges there (apart from the Seidel terms);
            for other depths it is the centre of its blur.
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
            "lens": {
                "axis_offset_mm": list(self.axis_offset_mm),
                "axis_offset_px": list(self.axis_offset_px),
                "mla_tilt": list(self.mla_tilt),
                "mla_tilt_deg": math.degrees(math.atan(math.hypot(*self.mla_tilt))),
                "mla_tilt_direction_deg": math.degrees(math.atan2(self.mla_tilt[1],
                                                                  self.mla_tilt[0])),
                "front_stop_mm": None if self.front_stop is None else list(self.front_stop),
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
                         axis_offset_mm=tuple(data.get("lens", {}).get("axis_offset_mm", (0.0, 0.0))),
                         mla_tilt=tuple(data.get("lens", {}).get("mla_tilt", (0.0, 0.0))),
                         seed=data.get("seed"),
                         realism=realism_from_dict(_stored_realism(data),
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


def _stored_realism(data: dict) -> dict:
    """The ``realism`` table of a :meth:`SimOptics.to_dict` document; groups it lacks were
    written before they existed (nothing of theirs was simulated), so they read as off."""
    stored = data.get("realism", {"mode": "ideal"})
    if not isinstance(stored, dict) or "mode" in stored:
        return stored
    return {**{name: {"scale": 0.0} for name in GROUPS if name not in stored}, **stored}


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
    if optics.mla_tilt != (0.0, 0.0):
        return _fitted_grid(optics, i0, i1, j0, j1)
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


def _fitted_grid(optics: SimOptics, i0: int, i1: int, j0: int, j1: int) -> LensletGrid:
    """Least-squares lattice through the exact image centres of lenses i0..i1, j0..j1."""
    ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
    centres = optics.lens_image_centers_px(ii, jj).reshape(-1, 2)
    a = (jj - j0 + optics.odd_row_shift * (ii & 1)).ravel().astype(float)
    design = np.column_stack([np.ones_like(a), a, (ii - i0).ravel().astype(float)])
    coef, *_ = np.linalg.lstsq(design, centres, rcond=None)
    return LensletGrid(
        grid_type=optics.camera.grid_type,
        shape=(i1 - i0 + 1, j1 - j0 + 1),
        origin_px=(float(coef[0, 0]), float(coef[0, 1])),
        col_step_px=(float(coef[1, 0]), float(coef[1, 1])),
        row_step_px=(float(coef[2, 0]), float(coef[2, 1])),
        odd_row_shift=optics.odd_row_shift,
        sensor_shape_px=optics.camera.sensor_shape_px,
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
        Radial distortion coefficients; with ``realism.lens`` on, the values around which
        the camera's own coefficients are drawn.
    realism : Realism, "ideal", "realistic" or None
        Effects beyond the geometric model (default ideal). With ``realism.spec`` on, the
        true focal lengths and f-number are drawn after the MLA perturbation
        (:func:`true_camera`) and ``camera`` is kept as ``optics.nominal``. With
        ``realism.lens`` on, five more draws follow all of those (so the other draws do
        not change): ``k1`` and ``k2`` offsets (standard normal times
        ``distortion_k1_sigma``, ``distortion_k2_sigma``), the axis offset (radius
        ``axis_offset_px * sqrt(u)`` with ``u`` uniform in [0, 1), then its direction,
        uniform in [0, 2 pi): uniform in the disc), the MLA tilt direction (uniform in
        [0, 2 pi)) and tilt angle (uniform in [0, ``mla_tilt_deg``)).

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
    axis, tilt = (0.0, 0.0), (0.0, 0.0)
    if realism.lens.enabled:
        lens = realism.lens
        dk = rng.standard_normal(2)
        k1 = k1 + lens.distortion_k1_sigma * float(dk[0])
        k2 = k2 + lens.distortion_k2_sigma * float(dk[1])
        radius = lens.axis_offset_px * pp * math.sqrt(rng.random())
        phi = rng.uniform(0.0, 2.0 * math.pi)
        axis = (radius * math.cos(phi), radius * math.sin(phi))
        direction = rng.uniform(0.0, 2.0 * math.pi)
        slope = math.tan(math.radians(rng.uniform(0.0, lens.mla_tilt_deg)))
        tilt = (slope * math.cos(direction), slope * math.sin(direction))
    return SimOptics(camera=true, rotation_deg=sign * magnitude,
                     offset_mm=(float(offset[0]), float(offset[1])),
                     pitch_scale=float(pitch_scale), k1=k1, k2=k2,
                     axis_offset_mm=axis, mla_tilt=tilt,
                     seed=None if recorded is None else int(recorded), realism=realism,
                     nominal=None if true == camera else camera)
