"""Ground-truth scenes: particle positions and sizes over frames.

A scene is a truth table (columns :data:`plenoptrack._columns.TRUTH_COLUMNS`: ``frame,
particle, x, y, z, diameter`` (world frame, mm), ``projected_area`` (mm^2) and
``orientation`` (rad) of the silhouette along the optical axis, see
:func:`particle_silhouettes`) for a camera. Opt-in ellipsoid scenes (``shape="ellipsoid"``)
hold prolate spheroids and add ``shape, aspect, axis_x, axis_y, axis_z``
(:data:`~plenoptrack._columns.SHAPE_COLUMNS`); ``diameter`` is then the volume-equivalent
diameter. Opt-in fragment scenes (``shape="fragment"``) hold irregular bodies
(:mod:`.fragments`) and add ``shape_seed`` too. Random scenes place
non-overlapping spheres uniformly in a measurement volume, of one diameter or of diameters
drawn log-uniformly from a range (a polydisperse scene); multi-frame scenes move every
particle with a constant velocity so that tracking has ground truth.

Scene files (TOML)
------------------
::

    camera = "small"                    # preset name, or a [camera] table (CameraSpec fields)
    magnification = -0.5                # optional override of the camera's magnification
                                        # (f-number re-set to keep the working f-number)
    seed = 7                            # optional, default 0: governs the whole simulation
                                        # (particles, optics, noise)
    frames = 3                          # optional, default 1
    velocity_mm_per_frame = [0.1, 0.0, 0.2]   # optional, default [0, 0, 0]

    [optics]                            # optional: optics mode and effect sizes
    mode = "realistic"                  # or "ideal" (see plenoptrack.simulate.realism)
    [optics.particles]                  # optional: translucency, highlights, motion blur
    exposure_fraction = 0.05            # shutter open 5 % of the frame interval

    [volume]                            # optional: defaults from the camera (see default_volume)
    depth_mm = 20.0

    [random]                            # either a random set ...
    n = 20
    diameter_mm = 1.0                   # optional, default per preset (default_diameter_mm);
                                        # [min, max] draws each diameter log-uniformly
    shape = "ellipsoid"                 # optional, default "sphere"; or "fragment"
    max_aspect = 3.0                    # optional: largest aspect ratio of ellipsoids and
                                        # fragments

    [[particles]]                       # ... or explicit particles at frame 0
    x = 0.0
    y = 0.0
    z = 0.0
    diameter = 1.0
    velocity_mm_per_frame = [0.0, 0.0, 0.5]   # optional, replaces the scene velocity

Positions and diameters are in mm, world frame (see ``docs/conventions.md``).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .._columns import (ASPECT_COLUMN, AXIS_COLUMNS, DIAMETER_COLUMN, ID_COLUMN,
                        OPTIONAL_TRUTH_COLUMNS, ORIENTATION_COLUMN, PARTICLE_TABLE_COLUMNS,
                        POS_COLUMNS, PROJECTED_AREA_COLUMN, SHAPE_COLUMN, SHAPE_COLUMNS,
                        SHAPE_SEED_COLUMN, T_COLUMN, TRANSMISSION_COLUMN, TRUTH_COLUMNS,
                        VELOCITY_COLUMNS)
from ..camera import CameraSpec, preset
from ..errors import InputFileError, PlenoptrackError, SettingsError
from .fragments import FRAGMENT_REACH, fragment_geometry, fragment_silhouette
from .realism import ParticleEffects, Realism, realism_from_dict

__all__ = ["SceneError", "Volume", "Scene", "VOLUME_DEPTH_MM", "DIAMETER_MM", "volume_depth_mm",
           "default_diameter_mm", "diameter_range", "default_volume", "random_particles",
           "moving_particles", "make_scene", "load_scene", "particle_silhouettes",
           "with_particle_effects", "SHAPES"]

VOLUME_DEPTH_MM = {"hall2019": 50.0, "small": 20.0, "small-rect": 20.0}
"""Default measurement-volume depth per camera preset at the preset's magnification, mm
(at another magnification it scales like the depth of field, :func:`volume_depth_mm`)."""

DIAMETER_MM = {"hall2019": 1.0, "small": 0.4, "small-rect": 0.4}
"""Default particle diameter per camera preset, mm. The small presets see a 10 x 6.6 mm
field (hexagonal) through 64 x 48 lenslets: 1 mm spheres, blurred over up to 1.3 mm at
the volume faces, would overlap in most views."""


class SceneError(PlenoptrackError, ValueError):
    """A scene is invalid: particles outside the volume, overlapping, or bad sizes."""


def volume_depth_mm(camera: CameraSpec) -> float:
    """Default volume depth for ``camera``, mm: the preset table, else 15 % of s_o.

    A preset used at another magnification ``M`` (:meth:`CameraSpec.with_magnification`)
    gets the table's depth times ``(M_preset / M)**2``: the depth of field, and the depth
    resolution, scale as ``1 / M**2``, so the volume keeps its place within the depth of
    field (``hall2019`` at M -1: 12.5 mm, against a plenoptic depth of field of -4.2 to
    +4.4 mm; 50 mm would leave most particles far out of focus, and the blur at the
    volume's faces would leave it 2.6 mm wide on ``small``).
    """
    if camera.name not in VOLUME_DEPTH_MM:
        return round(0.15 * camera.object_distance_mm, 1)
    scale = (preset(camera.name).magnification / camera.magnification) ** 2
    return round(VOLUME_DEPTH_MM[camera.name] * scale, 1)


def default_diameter_mm(camera: CameraSpec) -> float:
    """Default particle diameter for ``camera``: the preset table, else 1 mm."""
    return DIAMETER_MM.get(camera.name, 1.0)


@dataclass(frozen=True)
class Volume:
    """Axis-aligned measurement volume, world frame, mm.

    Parameters
    ----------
    x_mm, y_mm, z_mm : (float, float)
        (min, max) along each axis, mm.
    """

    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]

    def __post_init__(self) -> None:
        for name in ("x_mm", "y_mm", "z_mm"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise SceneError(f"volume {name} must be (min, max) with min < max; got {(lo, hi)}")
            object.__setattr__(self, name, (lo, hi))

    @property
    def bounds(self) -> np.ndarray:
        """(3, 2) array of (min, max) for x, y, z, mm."""
        return np.array([self.x_mm, self.y_mm, self.z_mm])

    def contains(self, xyz: np.ndarray) -> np.ndarray:
        """Boolean mask of the points ``(n, 3)`` (x, y, z mm) inside the volume."""
        xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
        b = self.bounds
        return ((xyz >= b[:, 0]) & (xyz <= b[:, 1])).all(axis=1)


def default_volume(camera: CameraSpec, *, depth_mm: float | None = None,
                   diameter_mm: float | None = None) -> Volume:
    """Measurement volume filling the camera's field of view.

    Depth ``depth_mm`` (default :func:`volume_depth_mm`) centred on the focal plane.
    Laterally: the field of view at the near face (the focal-plane field scaled by
    ``(s_o + z_near) / s_o``) minus, on each side, half the largest defocus blur radius
    in the volume projected to the focal plane (``D/4 |1 - s_o / (s_o + z)|``) and one
    diameter (default :func:`default_diameter_mm`). A particle near the side faces is
    then cut off in the views through the far side of the aperture but seen whole
    through the rest, which is enough to locate it.
    """
    depth = volume_depth_mm(camera) if depth_mm is None else float(depth_mm)
    diameter_mm = default_diameter_mm(camera) if diameter_mm is None else float(diameter_mm)
    s_o = camera.object_distance_mm
    if not (math.isfinite(depth) and 0 < depth < 1.8 * s_o):
        raise SceneError(f"volume depth_mm must be positive and below {1.8 * s_o:.0f} mm; "
                         f"got {depth_mm!r}")
    half_z = depth / 2
    h, w = camera.sensor_size_mm
    m = abs(camera.magnification)
    near = (s_o - half_z) / s_o
    blur = camera.aperture_diameter_mm / 2 * max(abs(1 - s_o / (s_o - half_z)),
                                                 abs(1 - s_o / (s_o + half_z)))
    half_x = w / m / 2 * near - blur / 2 - diameter_mm
    half_y = h / m / 2 * near - blur / 2 - diameter_mm
    if half_x <= 0 or half_y <= 0:
        raise SceneError(f"a {depth:g} mm deep volume leaves no lateral room on camera "
                         f"{camera.name!r}; choose a smaller depth_mm or diameter")
    return Volume((-half_x, half_x), (-half_y, half_y), (-half_z, half_z))


SHAPES = ("sphere", "ellipsoid", "fragment")
"""Particle shapes: spheres, prolate spheroids (``shape`` column ``"ellipsoid"``) or
irregular fragments (``"fragment"``, :mod:`.fragments`)."""

SPHERE, ELLIPSOID, FRAGMENT = range(3)
"""Shape codes of :func:`_shape_arrays` (index into :data:`SHAPES`)."""


def _empty_truth(shapes: bool = False, fragments: bool = False) -> pd.DataFrame:
    cols = {T_COLUMN: pd.Series(dtype=np.int64), ID_COLUMN: pd.Series(dtype=np.int64),
            **{c: pd.Series(dtype=float) for c in (*POS_COLUMNS, DIAMETER_COLUMN,
                                                   PROJECTED_AREA_COLUMN, ORIENTATION_COLUMN)}}
    if shapes:
        cols |= {SHAPE_COLUMN: pd.Series(dtype=object),
                 **{c: pd.Series(dtype=float) for c in (ASPECT_COLUMN, *AXIS_COLUMNS)}}
    if fragments:
        cols |= {SHAPE_SEED_COLUMN: pd.Series(dtype=np.int64)}
    return pd.DataFrame(cols)


def _check_shape(shape, max_aspect) -> float:
    if shape not in SHAPES:
        raise SceneError(f"shape must be one of {SHAPES}; got {shape!r}")
    try:
        k = float(max_aspect)
    except (TypeError, ValueError):
        k = math.nan
    if not (math.isfinite(k) and k >= 1):
        raise SceneError(f"max_aspect must be a finite number >= 1; got {max_aspect!r}")
    return k


def _shape_arrays(particles: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shapes of a particles table: ``(kind, aspect, axis)``.

    ``kind`` (n,) int holds :data:`SPHERE`, :data:`ELLIPSOID` or :data:`FRAGMENT`;
    ``aspect`` (n,) float the aspect of ellipsoids and fragments (1 for spheres); ``axis``
    (n, 3) float their unit long axis, world frame ((0, 0, 1) for spheres). A table
    without a ``shape`` column holds spheres. Raises :class:`SceneError` for unknown
    shapes, aspects below 1, zero axes or fragments without a valid ``shape_seed``.
    """
    n = len(particles)
    kind = np.zeros(n, dtype=np.int64)
    aspect = np.ones(n)
    axis = np.tile([0.0, 0.0, 1.0], (n, 1))
    if SHAPE_COLUMN not in particles.columns:
        return kind, aspect, axis
    shape = particles[SHAPE_COLUMN].to_numpy(dtype=object)
    bad = ~np.isin(shape, SHAPES)
    if bad.any():
        raise SceneError(f"particle shape must be one of {SHAPES}; got {shape[bad][:3].tolist()}")
    kind[shape == "ellipsoid"] = ELLIPSOID
    kind[shape == "fragment"] = FRAGMENT
    ell = kind != SPHERE
    if not ell.any():
        return kind, aspect, axis
    what = "ellipsoidal" if (kind[ell] == ELLIPSOID).all() else "ellipsoidal and fragment"
    missing = [c for c in (ASPECT_COLUMN, *AXIS_COLUMNS) if c not in particles.columns]
    if missing:
        raise SceneError(f"{what} particles need column(s) {missing} "
                         f"(aspect >= 1 and a long-axis vector, world frame)")
    k = particles[ASPECT_COLUMN].to_numpy(dtype=np.float64)[ell]
    u = particles[list(AXIS_COLUMNS)].to_numpy(dtype=np.float64)[ell]
    if not (np.isfinite(k).all() and (k >= 1).all()):
        raise SceneError(f"ellipsoid aspect must be finite and >= 1; got min {np.nanmin(k)}")
    norm = np.sqrt((u ** 2).sum(axis=1))
    if not (np.isfinite(norm).all() and (norm > 0).all()):
        raise SceneError("ellipsoid axis (axis_x, axis_y, axis_z) must be finite and non-zero")
    aspect[ell] = k
    axis[ell] = u / norm[:, None]
    if (kind == FRAGMENT).any():
        _shape_seeds(particles, kind)
    return kind, aspect, axis


def _shape_seeds(particles: pd.DataFrame, kind: np.ndarray) -> np.ndarray:
    """``shape_seed`` of every row as int64 (-1 where the table has none); validated for
    the fragment rows."""
    frag = kind == FRAGMENT
    if SHAPE_SEED_COLUMN not in particles.columns:
        if frag.any():
            raise SceneError(f"fragment particles need column {SHAPE_SEED_COLUMN!r} "
                             "(integer seed >= 0 of the irregular geometry)")
        return np.full(len(particles), -1, dtype=np.int64)
    raw = particles[SHAPE_SEED_COLUMN].to_numpy()
    seeds = np.asarray(raw, dtype=np.float64)
    good = np.isfinite(seeds) & (seeds >= 0) & (seeds == np.floor(seeds)) & (seeds < 2.0 ** 53)
    if not good[frag].all():
        raise SceneError(f"fragment {SHAPE_SEED_COLUMN} must be an integer >= 0; "
                         f"got {raw[frag & ~good][:3].tolist()}")
    return np.where(frag, seeds, -1).astype(np.int64)


def _fragments(particles: pd.DataFrame, kind: np.ndarray, aspect: np.ndarray,
               axis: np.ndarray) -> dict:
    """``{row: Fragment}`` of the fragment rows of a validated table."""
    rows = np.flatnonzero(kind == FRAGMENT)
    if len(rows) == 0:
        return {}
    seeds = _shape_seeds(particles, kind)
    d = particles[DIAMETER_COLUMN].to_numpy(dtype=np.float64)
    return {int(r): fragment_geometry(seeds[r], d[r], aspect[r], axis[r]) for r in rows}


def _bounding_radii(particles: pd.DataFrame) -> np.ndarray:
    """Radius of each particle's bounding sphere about its centre, mm: ``d / 2`` for a
    sphere, the long semi-axis ``(d / 2) k^(2/3)`` for a spheroid, the farthest vertex for
    a fragment."""
    kind, aspect, axis = _shape_arrays(particles)
    d = particles[DIAMETER_COLUMN].to_numpy(dtype=np.float64)
    radius = d / 2 * aspect ** (2.0 / 3.0)
    for r, frag in _fragments(particles, kind, aspect, axis).items():
        radius[r] = frag.bounding_radius
    return radius


def particle_silhouettes(particles: pd.DataFrame) -> pd.DataFrame:
    """Silhouettes of particles seen along the optical axis (orthographic projection).

    Parameters
    ----------
    particles : DataFrame
        Columns ``diameter`` (mm; volume-equivalent for ellipsoids and fragments) and
        optionally :data:`~plenoptrack._columns.SHAPE_COLUMNS` (and ``shape_seed`` for
        fragments).

    Returns
    -------
    DataFrame
        Same index; ``projected_area`` (mm^2) and ``orientation`` (rad, long axis of the
        silhouette from +x towards +y, in [-pi/2, pi/2); 0 for circular silhouettes).

    Notes
    -----
    A prolate spheroid of aspect ``k``, semi-axes ``a = (d/2) k^(2/3)`` along the unit axis
    ``u`` and ``b = (d/2) k^(-1/3)``, projects along z onto an ellipse of semi-axes ``b``
    and ``a_perp = sqrt(a^2 (1 - u_z^2) + b^2 u_z^2)``, area ``pi b a_perp``, long axis
    along ``(u_x, u_y)``. Spheres: ``pi d^2 / 4`` and 0. A fragment's silhouette is the
    union of its pieces' projected convex polygons: exact area, and the long axis of its
    second moments of area (:func:`.fragments.fragment_silhouette`); for a spheroid that
    is the long axis of the projected ellipse, so the convention is the same.
    """
    d = particles[DIAMETER_COLUMN].to_numpy(dtype=np.float64)
    kind, k, u = _shape_arrays(particles)
    ell = kind == ELLIPSOID
    area = math.pi * d ** 2 / 4
    orientation = np.zeros(len(d))
    if ell.any():
        r = d / 2
        b = r * k ** (-1.0 / 3.0)
        a = r * k ** (2.0 / 3.0)
        uz2 = np.minimum(u[:, 2] ** 2, 1.0)
        a_perp = np.sqrt(a ** 2 * (1.0 - uz2) + b ** 2 * uz2)
        area = np.where(ell, math.pi * b * a_perp, area)
        theta = np.arctan2(u[:, 1], u[:, 0])
        theta = (theta + math.pi / 2) % math.pi - math.pi / 2
        round_ = (k == 1.0) | ((u[:, 0] == 0.0) & (u[:, 1] == 0.0))
        orientation = np.where(ell & ~round_, theta, 0.0)
    for r, frag in _fragments(particles, kind, k, u).items():
        area[r], orientation[r] = fragment_silhouette(frag)
    return pd.DataFrame({PROJECTED_AREA_COLUMN: area, ORIENTATION_COLUMN: orientation},
                        index=particles.index)


def diameter_range(diameter_mm, *, name: str = "diameter_mm") -> tuple[float, float]:
    """``(min, max)`` diameters of a scene, mm, from one diameter or a ``(min, max)`` pair.

    Raises :class:`SceneError` unless both are finite, positive and ``min <= max``.
    """
    if isinstance(diameter_mm, (str, bytes)):
        raise SceneError(f"{name} must be a number or a (min, max) pair in mm; got {diameter_mm!r}")
    try:
        values = [float(v) for v in np.atleast_1d(np.asarray(diameter_mm, dtype=float))]
    except (TypeError, ValueError):
        raise SceneError(f"{name} must be a number or a (min, max) pair in mm; "
                         f"got {diameter_mm!r}") from None
    if len(values) not in (1, 2) or np.ndim(diameter_mm) > 1:
        raise SceneError(f"{name} must be a number or a (min, max) pair in mm; got {diameter_mm!r}")
    lo, hi = values[0], values[-1]
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
        what = "must be positive" if len(values) == 1 else "must be (min, max) with 0 < min <= max"
        raise SceneError(f"{name} {what}; got {diameter_mm!r}")
    return lo, hi


MAX_PACKING_FRACTION = 0.3
"""Largest volume fraction :func:`random_particles` attempts (random sequential placement
of equal spheres jams near 0.38)."""


def random_particles(n: int, *, volume: Volume,
                     diameter_mm: float | tuple[float, float] = 1.0,
                     seed: int | np.random.Generator | None = 0,
                     shape: str = "sphere", max_aspect: float = 3.0) -> pd.DataFrame:
    """Non-overlapping spheres, spheroids or fragments placed uniformly at random (frame 0).

    Parameters
    ----------
    n : int
        Number of particles.
    volume : Volume
        Region for the particle centres, mm.
    diameter_mm : float or (float, float)
        Particle diameter, mm; or a ``(min, max)`` range, mm, from which each particle's
        diameter is drawn log-uniformly (uniform in ``log d``).
    seed : int or numpy.random.Generator
        Seed of the draws: with a range, first the ``n`` diameters; for ellipsoids and
        fragments then the ``n`` aspects and ``n`` axes, for fragments then ``n`` shape
        seeds; then the positions. Sphere scenes make no shape draws, so a seed gives the
        same spheres as before shapes existed.
    shape : {"sphere", "ellipsoid", "fragment"}
        ``"ellipsoid"``: prolate spheroids with ``diameter`` the volume-equivalent
        diameter, aspect (long over short semi-axis) uniform in ``[1, max_aspect]`` and
        long axis uniform on the unit sphere. ``"fragment"``: irregular bodies
        (:mod:`.fragments`) of that volume-equivalent diameter whose equivalent ellipsoid
        has that aspect and long axis; each has a ``shape_seed`` (uniform in
        ``[0, 2^31)``) that fixes its geometry, with a random roll about the axis.
    max_aspect : float
        Largest aspect of the spheroids or fragments (>= 1); ignored for spheres.

    Returns
    -------
    DataFrame
        Columns ``frame`` (0), ``particle`` (0..n-1), ``x, y, z`` (mm), ``diameter`` (mm),
        ``projected_area`` (mm^2), ``orientation`` (rad) (:func:`particle_silhouettes`);
        for ellipsoids also ``shape``, ``aspect`` and ``axis_x, axis_y, axis_z``; for
        fragments also ``shape_seed``.

    Notes
    -----
    Random sequential placement: each candidate centre is drawn uniformly in the volume
    and kept when it lies at least ``(d_i + d_j) / 2`` from every placed particle ``j``
    (for spheroids ``d`` is the bounding diameter ``d k^(2/3)``, twice the long
    semi-axis; for fragments twice the distance of the farthest vertex). With a range, the particles are placed largest first (the small ones fit
    into the gaps); the table keeps the order in which the diameters were drawn.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 0):
        raise SceneError(f"n must be a non-negative integer; got {n!r}")
    lo, hi = diameter_range(diameter_mm)
    k_max = _check_shape(shape, max_aspect)
    rng = np.random.default_rng(seed)
    if lo == hi:
        diameters = np.full(n, lo)
        label = f"{lo:g} mm"
    else:
        diameters = np.exp(rng.uniform(math.log(lo), math.log(hi), size=n))
        label = f"{lo:g}-{hi:g} mm"
    shape_cols = {}
    extent = diameters                      # bounding diameters used for placement
    if shape == "ellipsoid":
        aspect = rng.uniform(1.0, k_max, size=n)
        u = rng.standard_normal((n, 3))
        u /= np.sqrt((u ** 2).sum(axis=1))[:, None]
        extent = diameters * aspect ** (2.0 / 3.0)
        hi = hi * k_max ** (2.0 / 3.0)
        shape_cols = {SHAPE_COLUMN: np.full(n, "ellipsoid", dtype=object), ASPECT_COLUMN: aspect,
                      **{c: u[:, i] for i, c in enumerate(AXIS_COLUMNS)}}
    elif shape == "fragment":
        aspect = rng.uniform(1.0, k_max, size=n)
        u = rng.standard_normal((n, 3))
        u /= np.sqrt((u ** 2).sum(axis=1))[:, None]
        seeds = rng.integers(0, 2 ** 31, size=n, dtype=np.int64)
        shape_cols = {SHAPE_COLUMN: np.full(n, "fragment", dtype=object), ASPECT_COLUMN: aspect,
                      **{c: u[:, i] for i, c in enumerate(AXIS_COLUMNS)},
                      SHAPE_SEED_COLUMN: seeds}
        extent = 2.0 * _bounding_radii(pd.DataFrame({DIAMETER_COLUMN: diameters, **shape_cols}))
        hi = float(extent.max()) if n else hi
    b = volume.bounds
    fill = (math.pi / 6 * float((extent ** 3).sum())
            / max(float(np.prod(b[:, 1] - b[:, 0])), 1e-300))
    if fill > MAX_PACKING_FRACTION:
        raise SceneError(f"{n} particles of {label} would fill {fill:.0%} of the volume; "
                         f"random placement stops near {MAX_PACKING_FRACTION:.0%}: lower n or "
                         "the diameter")
    order = np.argsort(-extent, kind="stable")
    placed = np.empty((n, 3))
    # Spatial hash with cells one largest diameter wide: a new particle can only overlap
    # particles in its own or the 26 neighbouring cells.
    cell = hi
    cells: dict[tuple[int, int, int], list[int]] = {}
    count = attempts = 0
    while count < n:
        attempts += 1
        if attempts > 200 * (n + 10):
            raise SceneError(f"could not place {n} non-overlapping particles of {label} "
                             f"in the volume (placed {count}); lower n or the diameter")
        p = rng.uniform(b[:, 0], b[:, 1])
        d = extent[order[count]]
        ci, cj, ck = (int(math.floor(c / cell)) for c in p)
        near = [k for di in (-1, 0, 1) for dj in (-1, 0, 1) for dk in (-1, 0, 1)
                for k in cells.get((ci + di, cj + dj, ck + dk), ())]
        if near:
            gap2 = (d + extent[order[near]]) ** 2 / 4
            if (((placed[near] - p) ** 2).sum(axis=1) < gap2).any():
                continue
        placed[count] = p
        cells.setdefault((ci, cj, ck), []).append(count)
        count += 1
    if n == 0:
        return _empty_truth(shapes=shape != "sphere", fragments=shape == "fragment")
    xyz = np.empty((n, 3))
    xyz[order] = placed
    out = pd.DataFrame({T_COLUMN: np.zeros(n, np.int64), ID_COLUMN: np.arange(n, dtype=np.int64),
                        "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                        DIAMETER_COLUMN: diameters.astype(float), **shape_cols})
    return _with_silhouettes(out)


def _with_silhouettes(particles: pd.DataFrame) -> pd.DataFrame:
    """``particles`` with the silhouette columns, in truth column order."""
    sil = particle_silhouettes(particles)
    out = particles.assign(**{c: sil[c].to_numpy() for c in sil.columns})
    return out[_truth_order(out)]


def _truth_order(table: pd.DataFrame) -> list[str]:
    """Truth columns of ``table`` in file order: :data:`TRUTH_COLUMNS`, then the optional
    ones it has (:data:`~plenoptrack._columns.OPTIONAL_TRUTH_COLUMNS`; shape columns as a
    group)."""
    cols = list(TRUTH_COLUMNS)
    if SHAPE_COLUMN in table.columns:
        cols += list(SHAPE_COLUMNS)
    return cols + [c for c in OPTIONAL_TRUTH_COLUMNS
                   if c in table.columns and c not in SHAPE_COLUMNS]


def moving_particles(particles: pd.DataFrame, *, frames: int,
                     velocity_mm_per_frame=(0.0, 0.0, 0.0)) -> pd.DataFrame:
    """Repeat frame-0 particles over ``frames`` frames with constant velocities.

    Parameters
    ----------
    particles : DataFrame
        Frame-0 truth (``particle, x, y, z, diameter``; optional columns, if any, are kept:
        :data:`~plenoptrack._columns.OPTIONAL_TRUTH_COLUMNS`).
    frames : int
        Number of frames (>= 1).
    velocity_mm_per_frame : (3,) or (n, 3) array-like
        Displacement (dx, dy, dz) per frame, mm, for all particles or per particle.

    Returns
    -------
    DataFrame
        Truth table with :data:`~plenoptrack._columns.TRUTH_COLUMNS` (silhouette columns
        recomputed by :func:`particle_silhouettes`) and the optional columns of
        ``particles``; sorted by frame then particle.
    """
    if not (isinstance(frames, (int, np.integer)) and frames >= 1):
        raise SceneError(f"frames must be a positive integer; got {frames!r}")
    v = np.asarray(velocity_mm_per_frame, dtype=float)
    if v.shape not in ((3,), (len(particles), 3)) or not np.isfinite(v).all():
        raise SceneError(f"velocity_mm_per_frame must be 3 finite numbers or one row per particle; "
                         f"got shape {v.shape}")
    v = np.broadcast_to(v, (len(particles), 3))
    base = particles[list(POS_COLUMNS)].to_numpy(dtype=float)
    if SHAPE_COLUMN in particles.columns:
        _shape_arrays(particles)  # validate
    extra = {c: particles[c].to_numpy() for c in OPTIONAL_TRUTH_COLUMNS if c in particles.columns}
    parts = []
    for f in range(frames):
        pos = base + f * v
        parts.append(pd.DataFrame({T_COLUMN: np.full(len(particles), f, np.int64),
                                   ID_COLUMN: particles[ID_COLUMN].to_numpy(np.int64),
                                   "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
                                   DIAMETER_COLUMN: particles[DIAMETER_COLUMN].to_numpy(float),
                                   **extra}))
    shaped = SHAPE_COLUMN in particles.columns
    out = pd.concat(parts, ignore_index=True) if parts else _empty_truth(
        shapes=shaped, fragments=SHAPE_SEED_COLUMN in particles.columns)
    return _with_silhouettes(out)


@dataclass(frozen=True)
class Scene:
    """A camera, a volume and the ground truth of every frame.

    Attributes
    ----------
    camera : CameraSpec
        Nominal camera the scene is meant for.
    volume : Volume
        Measurement volume, mm.
    truth : DataFrame
        ``frame, particle, x, y, z, diameter`` (mm) for every frame.
    seed : int
        Seed of the scene (also the default simulation seed).
    realism : Realism or None
        Optics mode and effect sizes from the scene file's ``[optics]`` table (see
        :mod:`.realism`); None when the file has none (the simulation's default applies).
    velocity : DataFrame or None
        Columns ``particle`` and :data:`~plenoptrack._columns.VELOCITY_COLUMNS` (mm per
        frame, world frame): the velocity of every particle, which blurs its image over
        the exposure (:class:`~.realism.ParticleEffects`). None: taken from the first two
        frames when there are several, else every particle is still.
    """

    camera: CameraSpec
    volume: Volume
    truth: pd.DataFrame
    seed: int = 0
    realism: Realism | None = None
    velocity: pd.DataFrame | None = field(default=None, repr=False, compare=False)

    @property
    def frames(self) -> int:
        """Number of frames."""
        return int(self.truth[T_COLUMN].max()) + 1 if len(self.truth) else 1

    def particle_velocities(self) -> pd.DataFrame:
        """``particle`` and :data:`~plenoptrack._columns.VELOCITY_COLUMNS` of every
        particle, mm per frame (see ``velocity``)."""
        if self.velocity is not None:
            return self.velocity[[ID_COLUMN, *VELOCITY_COLUMNS]].reset_index(drop=True)
        ids = np.unique(self.truth[ID_COLUMN].to_numpy(np.int64))
        v = np.zeros((len(ids), 3))
        if self.frames > 1:
            pos = self.truth.set_index([T_COLUMN, ID_COLUMN])[list(POS_COLUMNS)]
            f0, f1 = pos.loc[0], pos.loc[1]
            both = f0.index.intersection(f1.index)
            step = (f1.loc[both] - f0.loc[both]).reindex(ids).fillna(0.0)
            v = step.to_numpy(dtype=float)
        return pd.DataFrame({ID_COLUMN: ids, **{c: v[:, i] for i, c in enumerate(VELOCITY_COLUMNS)}})


def _velocity_table(ids, velocity_mm_per_frame) -> pd.DataFrame:
    """``particle`` and velocity columns from one (3,) or per-particle (n, 3) velocity."""
    ids = np.asarray(ids, dtype=np.int64)
    v = np.broadcast_to(np.asarray(velocity_mm_per_frame, dtype=float), (len(ids), 3))
    return pd.DataFrame({ID_COLUMN: ids, **{c: v[:, i].copy() for i, c in enumerate(VELOCITY_COLUMNS)}})


def with_particle_effects(truth: pd.DataFrame, effects: ParticleEffects, *,
                          seed: int | np.random.Generator | None,
                          velocity: pd.DataFrame | None = None) -> pd.DataFrame:
    """A truth table with the per-particle columns the particle effects need.

    Parameters
    ----------
    truth : DataFrame
        Truth of every frame (not changed).
    effects : ParticleEffects
        With ``max_transmission > 0`` and no ``transmission`` column, each particle gets a
        transmission drawn uniformly in ``[0, max_transmission]`` (one per ``particle``
        id, the same in every frame, in id order). With ``exposure_fraction > 0`` and no
        velocity columns, each row gets its particle's ``velocity`` (mm per frame).
    seed : int or numpy.random.Generator
        Seed of the transmission draws (a data set uses ``[seed, 6]``).
    velocity : DataFrame, optional
        ``particle`` and :data:`~plenoptrack._columns.VELOCITY_COLUMNS`
        (:meth:`Scene.particle_velocities`); None: still particles.

    Returns
    -------
    DataFrame
        ``truth`` with :data:`~plenoptrack._columns.TRANSMISSION_COLUMN` and
        :data:`~plenoptrack._columns.VELOCITY_COLUMNS` added as above, in truth column
        order; ``truth`` itself when neither applies.
    """
    if not isinstance(effects, ParticleEffects):
        raise SettingsError(f"effects must be a ParticleEffects; got {type(effects).__name__}")
    add = {}
    ids = truth[ID_COLUMN].to_numpy(np.int64)
    if effects.max_transmission > 0 and TRANSMISSION_COLUMN not in truth.columns:
        uniq, inverse = np.unique(ids, return_inverse=True)
        tau = np.random.default_rng(seed).uniform(0.0, effects.max_transmission, len(uniq))
        add[TRANSMISSION_COLUMN] = tau[inverse]
    if effects.exposure_fraction > 0 and not set(VELOCITY_COLUMNS) & set(truth.columns):
        table = _velocity_table(np.unique(ids), (0.0, 0.0, 0.0)) if velocity is None else velocity
        v = table.set_index(ID_COLUMN)[list(VELOCITY_COLUMNS)].reindex(ids).fillna(0.0)
        add |= {c: v[c].to_numpy(dtype=float) for c in VELOCITY_COLUMNS}
    if not add:
        return truth
    out = truth.assign(**add)
    return out[_truth_order(out)]


def check_particles(particles: pd.DataFrame, volume: Volume, *, where: str = "scene") -> None:
    """Raise :class:`SceneError` for bad diameters, overlaps or centres outside ``volume``."""
    missing = [c for c in PARTICLE_TABLE_COLUMNS if c not in particles.columns]
    if missing:
        raise SceneError(f"{where}: particles are missing column(s) {missing}")
    values = particles[[*POS_COLUMNS, DIAMETER_COLUMN]].to_numpy(dtype=float)
    if not np.isfinite(values).all():
        raise SceneError(f"{where}: particle positions and diameters must be finite")
    bad = values[:, 3] <= 0
    if bad.any():
        raise SceneError(f"{where}: particle diameters must be positive (mm); "
                         f"got {values[bad, 3][:3].tolist()}")
    extent = 2.0 * _bounding_radii(particles)      # bounding diameters (spheres: d)
    particles = particles.assign(_extent=extent)
    outside = ~volume.contains(values[:, :3])
    if outside.any():
        first = values[outside][0]
        raise SceneError(f"{where}: {int(outside.sum())} particle(s) outside the volume, e.g. "
                         f"(x, y, z) = ({first[0]:.3g}, {first[1]:.3g}, {first[2]:.3g}) mm; volume "
                         f"x {volume.x_mm}, y {volume.y_mm}, z {volume.z_mm} mm")
    for _, grp in particles.groupby(T_COLUMN):
        xyz = grp[list(POS_COLUMNS)].to_numpy(dtype=float)
        d = grp["_extent"].to_numpy(dtype=float)
        if len(xyz) > 1:
            from scipy.spatial import cKDTree

            pairs = cKDTree(xyz).query_pairs(float(d.max()), output_type="ndarray")
            if len(pairs):
                gap = np.linalg.norm(xyz[pairs[:, 0]] - xyz[pairs[:, 1]], axis=1)
                overlap = gap < (d[pairs[:, 0]] + d[pairs[:, 1]]) / 2
                if overlap.any():
                    a, b = pairs[overlap][0]
                    raise SceneError(f"{where}: particles {int(grp[ID_COLUMN].iloc[a])} and "
                                     f"{int(grp[ID_COLUMN].iloc[b])} overlap")


def make_scene(camera: CameraSpec, *, n_particles: int = 20,
               diameter_mm: float | tuple[float, float] | None = None,
               frames: int = 1, velocity_mm_per_frame=(0.0, 0.0, 0.0),
               volume: Volume | None = None, seed: int = 0, shape: str = "sphere",
               max_aspect: float = 3.0) -> Scene:
    """Random scene: ``n_particles`` spheres in the volume, moving at constant velocity.

    The diameter defaults to :func:`default_diameter_mm` of the camera; a ``(min, max)``
    pair draws each particle's diameter log-uniformly in that range (see
    :func:`random_particles`; the truth records each particle's diameter). The volume
    (default :func:`default_volume`, with the margin of the largest diameter) bounds the
    frame-0 positions; later frames may leave it. ``shape="ellipsoid"`` makes prolate
    spheroids of aspect up to ``max_aspect`` (:func:`random_particles`), ``"fragment"``
    irregular fragments (:mod:`.fragments`); the default volume's margin is then the
    largest bounding diameter (for fragments its bound,
    :data:`~.fragments.FRAGMENT_REACH` times the spheroid's). The scene records the
    velocity (:attr:`Scene.velocity`).
    """
    if diameter_mm is None:
        diameter_mm = default_diameter_mm(camera)
    lo, hi = diameter_range(diameter_mm)
    k_max = _check_shape(shape, max_aspect)
    diameter_mm = lo if lo == hi else (lo, hi)
    margin = hi if shape == "sphere" else hi * k_max ** (2.0 / 3.0)
    if shape == "fragment":
        margin *= FRAGMENT_REACH
    volume = default_volume(camera, diameter_mm=margin) if volume is None else volume
    first = random_particles(n_particles, volume=volume, diameter_mm=diameter_mm,
                             seed=np.random.default_rng([seed, 1]), shape=shape,
                             max_aspect=max_aspect)
    truth = moving_particles(first, frames=frames, velocity_mm_per_frame=velocity_mm_per_frame)
    return Scene(camera=camera, volume=volume, truth=truth, seed=seed,
                 velocity=_velocity_table(first[ID_COLUMN], velocity_mm_per_frame))


_SCENE_KEYS = {"camera", "magnification", "seed", "frames", "velocity_mm_per_frame", "volume",
               "random", "particles", "optics"}


def load_scene(path: str | Path) -> Scene:
    """Read a scene TOML file (schema in the module notes)."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: scene file not found")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: not valid TOML ({exc})") from None
    unknown = sorted(set(data) - _SCENE_KEYS)
    if unknown:
        raise InputFileError(f"{path}: unknown key(s) {unknown}; allowed: {sorted(_SCENE_KEYS)}")
    cam = data.get("camera")
    if isinstance(cam, str):
        camera = preset(cam)
    elif isinstance(cam, dict):
        camera = CameraSpec.from_dict(cam, source=str(path))
    else:
        raise InputFileError(f"{path}: 'camera' must be a preset name or a [camera] table")
    if "magnification" in data:
        try:
            camera = camera.with_magnification(float(data["magnification"]))
        except (TypeError, ValueError) as exc:
            raise InputFileError(f"{path}: magnification: {exc}") from None
    seed = data.get("seed", 0)
    frames = data.get("frames", 1)
    try:
        realism = None if "optics" not in data else realism_from_dict(
            data["optics"], source=f"{path} [optics]")
    except SettingsError as exc:
        raise InputFileError(str(exc)) from None
    velocity = data.get("velocity_mm_per_frame", [0.0, 0.0, 0.0])
    if ("random" in data) == ("particles" in data):
        raise InputFileError(f"{path}: give exactly one of a [random] table or [[particles]]")
    try:
        vol = data.get("volume", {})
        depth = vol.get("depth_mm")
        if "random" in data:
            spec = data["random"]
            lo, hi = diameter_range(spec.get("diameter_mm", default_diameter_mm(camera)),
                                    name="[random] diameter_mm")
            diameter = lo if lo == hi else (lo, hi)
            volume = default_volume(camera, depth_mm=depth, diameter_mm=hi)
            scene = make_scene(camera, n_particles=int(spec["n"]), diameter_mm=diameter,
                               frames=frames, velocity_mm_per_frame=velocity, volume=volume,
                               seed=seed, shape=spec.get("shape", "sphere"),
                               max_aspect=float(spec.get("max_aspect", 3.0)))
            return dataclasses.replace(scene, realism=realism)
        rows = data["particles"]
        first = pd.DataFrame({
            T_COLUMN: np.zeros(len(rows), np.int64), ID_COLUMN: np.arange(len(rows)),
            **{c: [float(r[c]) for r in rows] for c in (*POS_COLUMNS, DIAMETER_COLUMN)}})
        vel = np.array([r.get("velocity_mm_per_frame", velocity) for r in rows], dtype=float)
        volume = default_volume(camera, depth_mm=depth,
                                diameter_mm=float(first[DIAMETER_COLUMN].max()) if len(rows)
                                else None)
        check_particles(first, volume, where=str(path))
        truth = moving_particles(first, frames=frames,
                                 velocity_mm_per_frame=vel if len(rows) else velocity)
        return Scene(camera=camera, volume=volume, truth=truth, seed=int(seed), realism=realism,
                     velocity=_velocity_table(first[ID_COLUMN], vel if len(rows) else velocity))
    except KeyError as exc:
        raise InputFileError(f"{path}: missing key {exc}") from None
    except (TypeError, ValueError) as exc:
        if isinstance(exc, PlenoptrackError):
            raise
        raise InputFileError(f"{path}: bad value ({exc})") from None
