"""Built-in multi-frame scenes with known motion: a fragment field and a vortex ring.

``plenoptrack simulate --scene fragments`` and ``--scene vortex-ring`` build these scenes
from the defaults below; a TOML file of the same keys (``--scene-params FILE``) overrides
any of them. Both write the parameters they used to ``scene.toml`` in the data set, so a
run can be repeated and its frame interval is known to ``plenoptrack track``.

fragments
    The seed paper's motivating application: the case of a lab-scale detonator breaks
    into irregular opaque metal fragments that fly out radially. The fragments start on
    a cylinder (radius ``cylinder_radius_mm``, length ``cylinder_length_mm``) whose axis
    is tilted by ``tilt_deg`` from the optical axis so that the upper part of the ring
    (``y < 0``) lies farther from the camera (``z > 0``), as in the paper's Fig. 12. Each
    fragment moves in a straight line (no drag over a few microseconds) at a speed drawn
    uniformly in ``speed_m_per_s``, radially in the ring plane, tipped out of it by an
    angle drawn uniformly in ``+- spread_deg``; frames are ``frame_interval_s`` apart, the
    first at ``first_frame_s`` after break-up, and each is blurred over ``exposure_s``.
    Fragments have volume-equivalent diameters drawn log-uniformly in ``diameter_mm``,
    random shape (:mod:`.fragments`) and orientation; they do not tumble.

vortex-ring
    Tracer particles in Hill's spherical vortex (an analytic vortex ring: a sphere of
    radius ``radius_mm`` of rotational fluid moving through still fluid at
    ``speed_mm_per_frame`` along ``axis``), convected by a uniform stream
    ``stream_mm_per_frame``. ``n_particles`` tracers are seeded uniformly in a sphere of
    ``seed_radius_factor`` times the vortex radius around its starting centre and advected
    by the exact velocity field (fourth-order Runge-Kutta, ``substeps`` steps per frame).
    The truth velocity of every row is the field at that position, mm per frame.

``camera`` is a preset name or the path of a ``camera.toml``.

Velocities are in the truth's ``velocity_x, velocity_y, velocity_z`` columns, mm per
frame (world frame); with ``frame_interval_s`` a speed of ``v`` mm per frame is
``v / frame_interval_s / 1000`` m/s.

References
----------
M. J. M. Hill, "On a spherical vortex", Phil. Trans. R. Soc. Lond. A 185 (1894) 213-245.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .._columns import (AXIS_COLUMNS, ASPECT_COLUMN, DIAMETER_COLUMN, ID_COLUMN, POS_COLUMNS,
                        SHAPE_COLUMN, SHAPE_SEED_COLUMN, T_COLUMN, VELOCITY_COLUMNS)
from ..camera import PRESETS, CameraSpec, load_camera, preset
from ..errors import InputFileError, SettingsError
from .fragments import fragment_geometry
from .realism import Realism
from .scene import Scene, _with_silhouettes, default_volume

__all__ = ["BUILTIN_SCENES", "FragmentField", "VortexRing", "fragment_field_scene",
           "vortex_ring_scene", "hill_vortex_velocity", "builtin_scene", "scene_params",
           "read_scene_spec"]


@dataclass(frozen=True)
class FragmentField:
    """Parameters of the fragment-field scene (see the module notes); lengths in mm."""

    camera: str = "hall2019"
    seed: int = 0
    frames: int = 6
    n_fragments: int = 24
    diameter_mm: tuple[float, float] = (0.5, 5.0)
    max_aspect: float = 2.5
    cylinder_radius_mm: float = 3.0
    cylinder_length_mm: float = 10.0
    tilt_deg: float = 30.0
    centre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    speed_m_per_s: tuple[float, float] = (500.0, 1000.0)
    spread_deg: float = 8.0
    frame_interval_s: float = 2.5e-6
    first_frame_s: float = 6e-6
    exposure_s: float = 1e-7
    optics: str = "realistic"

    def __post_init__(self) -> None:
        _check_common(self)
        lo, hi = self.diameter_mm
        if not (0 < lo <= hi):
            raise SettingsError(f"diameter_mm must be (min, max) with 0 < min <= max; got {self.diameter_mm}")
        vlo, vhi = self.speed_m_per_s
        if not (0 <= vlo <= vhi):
            raise SettingsError(f"speed_m_per_s must be (min, max) with 0 <= min <= max; got {self.speed_m_per_s}")
        for name in ("cylinder_radius_mm", "cylinder_length_mm", "frame_interval_s", "max_aspect"):
            if not getattr(self, name) > 0:
                raise SettingsError(f"{name} must be positive; got {getattr(self, name)}")
        if self.max_aspect < 1:
            raise SettingsError(f"max_aspect must be at least 1; got {self.max_aspect}")
        if not (0 <= self.exposure_s < self.frame_interval_s):
            raise SettingsError(f"exposure_s must be in [0, frame_interval_s); got {self.exposure_s}")
        if self.n_fragments < 1:
            raise SettingsError(f"n_fragments must be at least 1; got {self.n_fragments}")

    @property
    def exposure_fraction(self) -> float:
        """Exposure over frame interval (the motion blur of :class:`~.realism.ParticleEffects`)."""
        return self.exposure_s / self.frame_interval_s


@dataclass(frozen=True)
class VortexRing:
    """Parameters of the vortex-ring scene (see the module notes); lengths in mm."""

    camera: str = "hall2019"
    seed: int = 0
    frames: int = 12
    n_particles: int = 300
    diameter_mm: float = 0.5
    radius_mm: float = 12.0
    speed_mm_per_frame: float = 0.4
    axis: tuple[float, float, float] = (0.9, 0.0, 0.45)
    stream_mm_per_frame: tuple[float, float, float] = (3.0, 0.0, 0.0)
    start_mm: tuple[float, float, float] = (-18.0, 0.0, -4.0)
    seed_radius_factor: float = 1.25
    substeps: int = 10
    frame_interval_s: float = 1e-3
    exposure_fraction: float = 0.0
    optics: str = "realistic"

    def __post_init__(self) -> None:
        _check_common(self)
        for name in ("radius_mm", "diameter_mm", "seed_radius_factor", "frame_interval_s"):
            if not getattr(self, name) > 0:
                raise SettingsError(f"{name} must be positive; got {getattr(self, name)}")
        if self.n_particles < 0:
            raise SettingsError(f"n_particles must be >= 0; got {self.n_particles}")
        if self.substeps < 1:
            raise SettingsError(f"substeps must be at least 1; got {self.substeps}")
        if not np.linalg.norm(self.axis) > 0:
            raise SettingsError(f"axis must be a non-zero vector; got {self.axis}")
        if not (0 <= self.exposure_fraction < 1):
            raise SettingsError(f"exposure_fraction must be in [0, 1); got {self.exposure_fraction}")


def _camera(spec: str) -> CameraSpec:
    """A preset name, or the path of a ``camera.toml`` (a camera of one's own)."""
    if spec in PRESETS or not Path(spec).is_file():
        return preset(spec)
    return load_camera(spec)


def _check_common(params) -> None:
    if params.frames < 1:
        raise SettingsError(f"frames must be at least 1; got {params.frames}")
    if params.optics not in ("ideal", "realistic"):
        raise SettingsError(f"optics must be 'ideal' or 'realistic'; got {params.optics!r}")


def _realism(mode: str, exposure_fraction: float, *, opaque: bool) -> Realism:
    base = Realism.realistic() if mode == "realistic" else Realism.ideal()
    particles = dataclasses.replace(base.particles, exposure_fraction=float(exposure_fraction),
                                    **({"max_transmission": 0.0} if opaque else {}))
    return dataclasses.replace(base, particles=particles)


def _ring_frame(tilt_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors ``(e1, e2, axis)`` of the ring plane and the cylinder axis.

    ``e1 = +x``; ``e2`` is ``+y`` tipped so that ``-e2`` (up on the sensor) points away
    from the camera; ``axis = e1 x e2`` leans towards the camera's ``-y`` side.
    """
    t = math.radians(tilt_deg)
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.array([0.0, math.cos(t), -math.sin(t)])
    return e1, e2, np.cross(e1, e2)


def fragment_field_scene(params: FragmentField = FragmentField()) -> Scene:
    """The expanding fragment ring of ``params`` as a :class:`~.scene.Scene`.

    Returns
    -------
    Scene
        Truth columns ``frame, particle, x, y, z, diameter, projected_area, orientation``,
        the shape columns, ``shape_seed`` and ``velocity_x, velocity_y, velocity_z`` (mm
        per frame); the realism has the scene's exposure fraction and opaque fragments.

    Notes
    -----
    Fragments are drawn one at a time and kept when their bounding spheres clear every
    fragment kept so far in every frame and their frame-0 centre lies in the camera's
    default volume; up to 200 draws per fragment. Later frames may leave the field of
    view, as fast fragments do.
    """
    camera = _camera(params.camera)
    rng = np.random.default_rng([params.seed, 11])
    e1, e2, axis = _ring_frame(params.tilt_deg)
    centre = np.asarray(params.centre_mm, dtype=float)
    lo, hi = params.diameter_mm
    volume = default_volume(camera, diameter_mm=hi)
    times = params.first_frame_s + params.frame_interval_s * np.arange(params.frames)
    kept, paths, radii = [], [], []
    attempts = 0
    while len(kept) < params.n_fragments:
        attempts += 1
        if attempts > 200 * params.n_fragments:
            raise SettingsError(f"could only place {len(kept)} of {params.n_fragments} fragments "
                                "without overlap; lower n_fragments or the sizes")
        d = math.exp(rng.uniform(math.log(lo), math.log(hi)))
        aspect = rng.uniform(1.0, params.max_aspect)
        u = rng.standard_normal(3)
        u /= np.linalg.norm(u)
        shape_seed = int(rng.integers(0, 2 ** 31))
        phi = rng.uniform(0.0, 2 * math.pi)
        h = rng.uniform(-0.5, 0.5) * params.cylinder_length_mm
        speed = rng.uniform(*params.speed_m_per_s)          # m/s = mm/ms
        tip = math.radians(rng.uniform(-params.spread_deg, params.spread_deg))
        radial = math.cos(phi) * e1 + math.sin(phi) * e2
        direction = math.cos(tip) * radial + math.sin(tip) * axis
        start = centre + h * axis + params.cylinder_radius_mm * radial
        v_mm_per_s = speed * 1e3 * direction
        path = start + times[:, None] * v_mm_per_s                # (frames, 3) mm
        radius = fragment_geometry(shape_seed, d, aspect, u).bounding_radius
        if not volume.contains(path[:1]).all():
            continue
        if any((np.linalg.norm(path - p, axis=1) < radius + r).any()
               for p, r in zip(paths, radii)):
            continue
        paths.append(path)
        radii.append(radius)
        kept.append({DIAMETER_COLUMN: d, SHAPE_COLUMN: "fragment", ASPECT_COLUMN: aspect,
                     **{c: u[i] for i, c in enumerate(AXIS_COLUMNS)},
                     SHAPE_SEED_COLUMN: shape_seed,
                     **{c: v_mm_per_s[i] * params.frame_interval_s
                        for i, c in enumerate(VELOCITY_COLUMNS)}})
    rows = []
    for f in range(params.frames):
        for pid, (frag, path) in enumerate(zip(kept, paths)):
            rows.append({T_COLUMN: f, ID_COLUMN: pid, **dict(zip(POS_COLUMNS, path[f])), **frag})
    truth = _with_silhouettes(pd.DataFrame(rows).astype({T_COLUMN: np.int64, ID_COLUMN: np.int64,
                                                         SHAPE_SEED_COLUMN: np.int64}))
    velocity = truth[truth[T_COLUMN] == 0][[ID_COLUMN, *VELOCITY_COLUMNS]].reset_index(drop=True)
    return Scene(camera=camera, volume=volume, truth=truth.reset_index(drop=True),
                 seed=params.seed,
                 realism=_realism(params.optics, params.exposure_fraction, opaque=True),
                 velocity=velocity)


def hill_vortex_velocity(points, *, radius_mm: float, speed: float, axis) -> np.ndarray:
    """Velocity of Hill's spherical vortex moving at ``speed`` along ``axis`` through still fluid.

    Parameters
    ----------
    points : (n, 3) float ndarray
        Positions relative to the vortex centre, mm.
    radius_mm : float
        Vortex radius ``a``, mm.
    speed : float
        Speed ``U`` of the vortex through the fluid (any length per time unit).
    axis : (3,) array_like
        Direction of travel (normalised here).

    Returns
    -------
    (n, 3) float ndarray
        Fluid velocity relative to the fluid at infinity (which is at rest), same unit as
        ``speed``.

    Notes
    -----
    In the vortex's frame, with ``x`` along ``-axis``, ``rho`` the distance from the axis
    and ``r^2 = x^2 + rho^2``, the fluid streams past at ``U`` along ``+x``; Stokes stream
    function ``psi = -(3U/4) rho^2 (1 - r^2/a^2)`` inside and
    ``(U/2) rho^2 (1 - a^3/r^3)`` outside, ``u_x = psi_rho / rho``,
    ``u_rho = -psi_x / rho``. Inside: ``u_x = -(3U/2)(1 - (2 rho^2 + x^2)/a^2)``,
    ``u_rho = -(3U/2) x rho / a^2``; outside: ``u_x = U (1 - a^3/r^3 + 3 a^3 rho^2 / (2 r^5))``,
    ``u_rho = -(3U/2) a^3 x rho / r^5``. Both are continuous at ``r = a``. Adding ``-U``
    along ``+x`` (i.e. ``U`` along ``axis``) gives the field in the frame of the still
    fluid.
    """
    p = np.atleast_2d(np.asarray(points, dtype=float))
    e = -np.asarray(axis, dtype=float) / np.linalg.norm(axis)    # +x of the formulas
    a, U = float(radius_mm), float(speed)
    x = p @ e
    radial = p - x[:, None] * e
    rho = np.linalg.norm(radial, axis=1)
    r2 = x ** 2 + rho ** 2
    inside = r2 < a ** 2
    r = np.sqrt(r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux_out = U * (1 - a ** 3 / r ** 3 + 1.5 * a ** 3 * rho ** 2 / r ** 5)
        urho_out = -1.5 * U * a ** 3 * x * rho / r ** 5
        unit = np.where(rho[:, None] > 0, radial / rho[:, None], 0.0)
    ux = np.where(inside, -1.5 * U * (1 - (2 * rho ** 2 + x ** 2) / a ** 2), ux_out)
    urho = np.where(inside, -1.5 * U * x * rho / a ** 2, urho_out)
    return (ux - U)[:, None] * e + urho[:, None] * unit


def vortex_ring_scene(params: VortexRing = VortexRing()) -> Scene:
    """Tracers advected by the vortex ring of ``params`` as a :class:`~.scene.Scene`.

    Returns
    -------
    Scene
        Truth columns ``frame, particle, x, y, z, diameter, projected_area, orientation``
        and ``velocity_x, velocity_y, velocity_z`` (mm per frame: the field at each row's
        position and frame). Tracers that leave the camera's default volume stay in the
        truth (they are simply not imaged).

    Notes
    -----
    The lab-frame field is ``w(p - c(t)) + stream`` with :func:`hill_vortex_velocity`
    ``w`` and centre ``c(t) = start + (stream + U axis) t`` (t in frames).
    Tracers are seeded by random sequential placement at least one diameter apart.
    """
    camera = _camera(params.camera)
    rng = np.random.default_rng([params.seed, 12])
    axis = np.asarray(params.axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    stream = np.asarray(params.stream_mm_per_frame, dtype=float)
    start = np.asarray(params.start_mm, dtype=float)
    drift = stream + params.speed_mm_per_frame * axis
    volume = default_volume(camera, diameter_mm=params.diameter_mm)
    n = params.n_particles
    reach = params.seed_radius_factor * params.radius_mm
    pts = np.empty((0, 3))
    attempts = 0
    while len(pts) < n:
        attempts += 1
        if attempts > 200 * (n + 10):
            raise SettingsError(f"could not seed {n} tracers of {params.diameter_mm} mm in a "
                                f"sphere of {reach:g} mm; lower n_particles")
        cand = rng.uniform(-reach, reach, size=(4 * (n - len(pts)) + 8, 3))
        cand = cand[np.linalg.norm(cand, axis=1) <= reach]
        for c in cand:
            if len(pts) == n:
                break
            if len(pts) == 0 or np.min(np.linalg.norm(pts - c, axis=1)) >= params.diameter_mm:
                pts = np.vstack([pts, c])
    pos = start + pts

    def field_at(p, t):
        return hill_vortex_velocity(p - (start + drift * t), radius_mm=params.radius_mm,
                                    speed=params.speed_mm_per_frame, axis=axis) + stream

    h = 1.0 / params.substeps
    rows = []
    t = 0.0
    for f in range(params.frames):
        vel = field_at(pos, float(f))
        rows.append(pd.DataFrame({T_COLUMN: np.full(n, f, np.int64),
                                  ID_COLUMN: np.arange(n, dtype=np.int64),
                                  **{c: pos[:, i] for i, c in enumerate(POS_COLUMNS)},
                                  DIAMETER_COLUMN: np.full(n, params.diameter_mm),
                                  **{c: vel[:, i] for i, c in enumerate(VELOCITY_COLUMNS)}}))
        for k in range(params.substeps):
            t = f + k * h
            k1 = field_at(pos, t)
            k2 = field_at(pos + 0.5 * h * k1, t + 0.5 * h)
            k3 = field_at(pos + 0.5 * h * k2, t + 0.5 * h)
            k4 = field_at(pos + h * k3, t + h)
            pos = pos + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    truth = _with_silhouettes(pd.concat(rows, ignore_index=True))
    velocity = truth[truth[T_COLUMN] == 0][[ID_COLUMN, *VELOCITY_COLUMNS]].reset_index(drop=True)
    return Scene(camera=camera, volume=volume, truth=truth, seed=params.seed,
                 realism=_realism(params.optics, params.exposure_fraction, opaque=False),
                 velocity=velocity)


BUILTIN_SCENES = {"fragments": (FragmentField, fragment_field_scene),
                  "vortex-ring": (VortexRing, vortex_ring_scene)}
"""Built-in scenes by name: (parameter class, builder)."""


def scene_params(name: str, overrides: dict | str | Path | None = None):
    """Parameters of built-in scene ``name`` with ``overrides`` (a dict or a TOML file).

    Raises
    ------
    SettingsError
        Unknown scene name, unknown key or a bad value.
    InputFileError
        The TOML file is missing or not valid TOML.
    """
    if name not in BUILTIN_SCENES:
        raise SettingsError(f"scene must be one of {sorted(BUILTIN_SCENES)}; got {name!r}")
    cls, _ = BUILTIN_SCENES[name]
    source = "overrides"
    if isinstance(overrides, (str, Path)):
        path = Path(overrides)
        if not path.is_file():
            raise InputFileError(f"{path}: scene parameter file not found")
        try:
            overrides = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputFileError(f"{path}: not valid TOML ({exc})") from None
        source = str(path)
    overrides = dict(overrides or {})
    overrides.pop("scene", None)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - set(fields))
    if unknown:
        raise SettingsError(f"{source}: unknown key(s) {unknown} for scene {name!r}; "
                            f"allowed: {sorted(fields)}")
    values = {}
    for key, value in overrides.items():
        default = getattr(cls(), key)
        try:
            if isinstance(default, tuple):
                value = tuple(float(v) for v in value)
                if len(value) != len(default):
                    raise ValueError(f"needs {len(default)} numbers")
            elif isinstance(default, bool) or isinstance(default, str):
                value = type(default)(value)
            elif isinstance(default, int):
                if float(value) != int(value):
                    raise ValueError("must be an integer")
                value = int(value)
            else:
                value = float(value)
        except (TypeError, ValueError) as exc:
            raise SettingsError(f"{source}: {key} = {value!r}: {exc}") from None
        values[key] = value
    return cls(**values)


def read_scene_spec(spec: str | Path) -> tuple[str, dict] | None:
    """``(name, overrides)`` when ``spec`` names a built-in scene or a TOML file with a
    ``scene = "NAME"`` key (the file's other keys override the defaults); else None.

    A data set's ``scene.toml`` is such a file, so ``--scene sim/scene.toml`` repeats a run.
    """
    if str(spec) in BUILTIN_SCENES and not Path(spec).is_file():
        return str(spec), {}
    path = Path(spec)
    if not path.is_file():
        return None
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError):
        return None
    name = data.get("scene")
    if not isinstance(name, str):
        return None
    if name not in BUILTIN_SCENES:
        raise InputFileError(f"{path}: scene must be one of {sorted(BUILTIN_SCENES)}; got {name!r}")
    return name, data


def builtin_scene(name: str, overrides: dict | str | Path | None = None) -> tuple[Scene, dict]:
    """Build built-in scene ``name``; return it and the parameters used (for ``scene.toml``).

    Parameters
    ----------
    name : {"fragments", "vortex-ring"}
        Scene name.
    overrides : dict, str or Path, optional
        Parameter values that replace the defaults (:class:`FragmentField`,
        :class:`VortexRing`), or a TOML file of them.

    Returns
    -------
    scene : Scene
    params : dict
        ``scene = name`` and every parameter, as written to ``scene.toml``.
    """
    params = scene_params(name, overrides)
    _, build = BUILTIN_SCENES[name]
    scene = build(params)
    doc = {"scene": name, **{k: (list(v) if isinstance(v, tuple) else v)
                             for k, v in dataclasses.asdict(params).items()}}
    return scene, doc

