"""Rendering back-lit particle images by back-tracing rays through the plenoptic camera.

Ray model (camera frame, mm; see :mod:`.optics`). Each pixel carries ``n`` samples from
one fixed low-discrepancy pattern. Sample ``k`` pairs a point ``P`` inside the pixel
with a point ``Q`` uniform inside the aperture cell (hexagon or square) of the microlens
``C`` whose image centre is nearest to ``P``. (Choosing the lens per sample rather than
per pixel keeps the light of pixels straddling two lens cells; with the pixel-centre rule
the microlens-image centroids are biased by up to 0.08 px.) ``P`` lies in
the focal plane of the thin microlens, so the ray leaves ``Q`` with slope
``(C - P) / f_ml`` and crosses the main-lens plane at ``H = Q + (C - P) s_i / f_ml``;
samples with ``|H| > D / 2`` are vignetted. In object space the ray joins ``H`` and the
distorted conjugate of ``Q`` on the focal plane. A sample sees the back-light (radiance
1) unless the ray meets an opaque particle; the pixel irradiance is the lit fraction.
Particles are spheres or, opt-in (``shape == "ellipsoid"``), prolate spheroids; a ray
meets a spheroid when the quadratic in the ray parameter for ``(p - c)^T M (p - c) = 1``
has real roots (:mod:`._kernels`). Spheres keep their own test and arithmetic.
Fragments (``shape == "fragment"``, :mod:`.fragments`) are unions of convex polytopes,
clipped by the Cyrus-Beck slab test.

Particle effects (``optics.realism.particles`` and the truth columns, :mod:`._kernels`
module notes): a particle with a ``transmission`` tau lets a fraction tau of a ray's
light through (the product over every particle the ray meets); with highlights on, the
first surface a ray meets adds a Blinn-Phong term, the sample clipped to the back-light;
a particle with a velocity is tested at ``c + v f t`` (``f`` the exposure fraction, ``t``
the sample's time in [-0.5, 0.5) from the fifth column of :func:`sample_pattern`), so its
image is blurred along its path over the exposure. A sample's value then lies in [0, 1]
and the pixel irradiance is the mean value. Without any of them the code of the opaque
model runs unchanged (same bytes, same speed).

The empty (back-lit only) irradiance is computed once per optics and sample count and
cached. A frame with particles re-traces only the pixels of lenses whose footprint can
meet a particle: for each particle a conservative disc on the focal plane (defocus blur
over the whole aperture plus the particle's projected size) is mapped back to the
microlens plane through the inverse distortion, the enclosing disc is grown by a lens-cell
radius and two pitches (a pixel's samples may use a lens next to the one owning the
pixel centre), and the pixels of the lenses with centres inside are re-traced against
the particles whose boxes contain them. A spheroid is culled by its bounding sphere
(radius = long semi-axis), a fragment by a sphere enclosing its vertices, a moving
particle by that sphere grown by half its path over the exposure, so the bounds stay
conservative and culling stays exact.

Lens effects (``optics.realism.lens``, see :mod:`.optics`) act on the rays themselves:
the microlens distance of a tilted MLA, the Seidel errors of the aim point, the front
stop (cat's-eye vignetting) and the axis offset are traced for every sample (in the white
image, frames and dot cards alike); the footprint discs grow by the largest Seidel error
(before the inverse distortion) and by the largest gap between a ray's point on the
tilted MLA and on the nominal MLA plane, so culling stays exact.

Realism. When ``optics.realism`` switches on effects of the ``blur``, ``illumination``
or ``sensor`` groups, :func:`expose_image` turns the traced irradiance into raw counts in
the order light meets them: back-light field and dust shadows (:mod:`.illumination`),
fill-factor loss, microlens point-spread function and crosstalk (:mod:`.psf`), then the
sensor's fixed patterns with shot and read noise (:mod:`.sensor`). The fill gap also
shrinks the aperture-cell samples ``Q`` of :func:`sample_pattern` to the live part of
each cell. With those groups off the output is bit-identical to the ideal model.
:func:`render_white`, :func:`render_frame`, :func:`render_dark` and
:func:`.dotcard.render_dotcard` all expose through it.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pandas as pd

from .._columns import (DIAMETER_COLUMN, POS_COLUMNS, T_COLUMN, TRANSMISSION_COLUMN,
                        VELOCITY_COLUMNS)
from . import _kernels
from .optics import SimOptics
from .scene import ELLIPSOID, SceneError, _fragments, _shape_arrays
from ..errors import SettingsError
from .illumination import illuminated, image_rng
from .psf import blur_image, live_cell_scale
from .sensor import SensorModel, expose, fixed_pattern

__all__ = ["render_irradiance", "render_white", "render_frame", "render_dark",
           "background_irradiance", "particle_lenses", "expose_image",
           "DEFAULT_SAMPLES_PER_PIXEL"]

DEFAULT_SAMPLES_PER_PIXEL = 16
_PATTERN_SEED = 20190601
_NO_CARD = np.zeros(3)
_KEY_OFFSET = 1 << 20


def _check_optics(optics) -> None:
    if not isinstance(optics, SimOptics):
        raise TypeError(f"optics must be a SimOptics (see make_optics); got {type(optics).__name__}")


def _check_samples(samples_per_pixel) -> int:
    if not (isinstance(samples_per_pixel, (int, np.integer)) and 1 <= samples_per_pixel <= 4096):
        raise SettingsError(f"samples_per_pixel must be an integer in [1, 4096]; got {samples_per_pixel!r}")
    return int(samples_per_pixel)


_TIME_SEED = 20240611
_TIME_DRAWS = 1 << 20


def _sample_times(columns: np.ndarray) -> np.ndarray:
    """Exposure times in [-0.5, 0.5) of a point-symmetric sample pattern.

    Parameters
    ----------
    columns : (n, 4) float ndarray
        The pattern's offsets of ``P`` and ``Q`` (sample ``k + n // 2`` the point reflection
        of sample ``k``, an odd centre sample last).

    Returns
    -------
    (n,) float64 ndarray
        Stratified: the ``n`` times are the stratum centres ``(j + 0.5) / n - 0.5``, each
        used once. Symmetric like the pattern: sample ``k + n // 2`` gets the opposite
        time of sample ``k`` and an odd centre sample 0, so a blurred image has no
        centroid bias. The strata are dealt to the first half by a permutation with
        signs: the best of a fixed set of seeded draws, then improved by sign flips and
        swaps, minimising the largest correlation of the times with the four offsets (a
        time correlated with ``Q`` would shorten or lengthen the blur in one direction).
    """
    n = len(columns)
    half = n // 2
    if half == 0:
        return np.zeros(n)
    mags = (np.arange(half) + 0.5 * (1 - n % 2) + n % 2) / n     # positive stratum centres
    x = columns[:half] / np.maximum(np.sqrt((columns[:half] ** 2).sum(axis=0)), 1e-300)
    rng = np.random.default_rng(_TIME_SEED)
    draws = max(16, _TIME_DRAWS // half)
    if half <= 10:
        # Every sign pattern with each of a set of permutations.
        signs = 1.0 - 2.0 * ((np.arange(1 << half)[:, None] >> np.arange(half)) & 1)
        perm = np.argsort(rng.random((max(1, draws // len(signs)), half)), axis=1)
        cand = (mags[perm][:, None, :] * signs[None]).reshape(-1, half)
    else:
        perm = np.argsort(rng.random((draws, half)), axis=1)
        cand = mags[perm] * rng.choice([-1.0, 1.0], size=(draws, half))
    norm = math.sqrt(float((mags ** 2).sum()))

    def cost(t):
        return np.abs(t @ x).max(axis=-1) / norm

    t = cand[np.argmin(cost(cand))]
    if half <= 256:
        best = cost(t)
        for _ in range(50):
            flips = t[None, :] * np.where(np.eye(half, dtype=bool), -1.0, 1.0)
            i, j = np.triu_indices(half, 1)
            swaps = np.repeat(t[None, :], len(i), axis=0)
            swaps[np.arange(len(i)), i], swaps[np.arange(len(i)), j] = t[j], t[i]
            trial = np.concatenate([flips, swaps])
            c = cost(trial)
            if c.min() >= best:
                break
            t, best = trial[np.argmin(c)], c.min()
    return np.concatenate([t, -t, np.zeros(n % 2)])


@functools.lru_cache(maxsize=16)
def sample_pattern(optics: SimOptics, n: int) -> np.ndarray:
    """The fixed per-pixel sample pattern, ``(n, 5)`` float64, read-only.

    Columns: offset (dX, dY) of ``P`` from the pixel centre and offset (dX, dY) of ``Q``
    from the microlens centre, camera frame, mm; the sample's time within the exposure,
    in [-0.5, 0.5) (:func:`_sample_times`; only motion blur reads it). Half the samples come from a scrambled
    Sobol sequence (Halton when ``n / 2`` is not a power of two) with a fixed seed, the
    other half are their point reflections (``u -> 1 - u`` in all four dimensions), and an
    odd ``n`` adds the centre sample; the pattern is therefore symmetric and the
    microlens images have no centroid bias. The ``Q`` part, uniform on a lattice
    parallelogram, is folded into the lens cell (hexagon or square); with
    ``optics.realism.blur.fill_gap`` it is then scaled by ``1 - fill_gap`` about the lens
    centre, onto the live part of the cell (:func:`.psf.live_cell_scale`; the lost light
    fraction is applied by :func:`expose_image`).
    """
    from scipy.stats import qmc

    half = n // 2
    if half == 0:
        u = np.zeros((0, 4))
    elif half & (half - 1) == 0:
        u = qmc.Sobol(d=4, scramble=True, seed=_PATTERN_SEED).random(half)
    else:
        u = qmc.Halton(d=4, scramble=True, seed=_PATTERN_SEED).random(half)
    # Point-symmetric pairs (u, 1 - u): unbiased centroids of every microlens image.
    u = np.concatenate([u, 1.0 - u, np.full((n % 2, 4), 0.5)])
    pp = optics.pixel_pitch
    e1, e2 = optics.lattice_vectors
    e2s = e2 + optics.odd_row_shift * e1
    v = u[:, 2:3] * e1 + u[:, 3:4] * e2s
    # Fold onto the cell of the lattice point nearest v (cell of lens (0, 0) at the origin).
    off = np.asarray(optics.offset_mm)
    ia = optics.lattice_coords(v + off)
    best = np.full(n, np.inf)
    folded = np.empty_like(v)
    for di in (-1, 0, 1):
        i = np.floor(ia[:, 0] + 0.5).astype(np.int64) + di
        j = np.floor(ia[:, 1] - optics.odd_row_shift * (i & 1) + 0.5).astype(np.int64)
        d = v + off - optics.lens_centers_mm(i, j)
        r2 = (d ** 2).sum(axis=1)
        better = r2 < best
        best[better] = r2[better]
        folded[better] = d[better]
    if optics.realism.blur.fill_gap > 0:
        folded *= live_cell_scale(optics.realism.blur)
    samples = np.column_stack([(u[:, 0] - 0.5) * pp, (u[:, 1] - 0.5) * pp, folded])
    samples = np.column_stack([samples, _sample_times(samples)])
    samples.setflags(write=False)
    return samples


@functools.lru_cache(maxsize=2)
def background_irradiance(optics: SimOptics, samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL
                          ) -> np.ndarray:
    """Back-lit irradiance of the empty camera, ``(rows, cols)`` float32, read-only, cached.

    Each pixel holds the fraction of its samples that pass the main-lens aperture: the
    microlens images are discs (images of the aperture) centred on ``optics.true_grid``.
    """
    _check_optics(optics)
    n = _check_samples(samples_per_pixel)
    rows, cols = optics.camera.sensor_shape_px
    out = _kernels.render_all(_kernels.pack_params(optics), sample_pattern(optics, n),
                              np.zeros((0, 4)), _NO_CARD, 0, rows, 0, cols, False)
    out.setflags(write=False)
    return out


def _particle_table(optics: SimOptics, particles) -> np.ndarray:
    """Validate a particles table; return ``(m, 4)`` occluders (X, Y, Z, r^2), camera frame.

    For ellipsoids ``r`` is the bounding radius (the long semi-axis); their shapes come
    from :func:`_particle_arrays`.
    """
    return _particle_arrays(optics, particles)[0]


def _particle_arrays(optics: SimOptics, particles) -> tuple[np.ndarray, np.ndarray]:
    """Validate a particles table; return the kernels' ``occluders`` and ``shapes``
    (:func:`_particle_geometry` without the culling balls)."""
    return _particle_geometry(optics, particles)[:2]


def _particle_geometry(optics: SimOptics, particles
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate a particles table; return the kernels' ``occluders``, ``shapes`` and
    culling ``balls``.

    Returns
    -------
    occluders : (m, 4) float64 ndarray
        (X, Y, Z, r^2) camera frame, mm; ``r`` is the radius of a sphere, the long
        semi-axis ``a`` (bounding radius) of an ellipsoid, the farthest vertex of a
        fragment; with motion blur, plus half the path over the exposure.
    shapes : (0, 7), (m, 7) or (m, W) float64 ndarray
        Zero rows when every particle is a still, opaque sphere and there are no
        highlights; ``(m, 7)`` when some are ellipsoids: per occluder the ellipsoid flag
        and scaled inverse-shape matrix ``M' = k^2 I + (1 - k^2) v v^T`` (``k`` the
        aspect, ``v`` the unit long axis in the camera frame); ``(m, W)``, ``W >= 16``,
        the extended rows of the particle effects (fragments, transmission, highlights,
        motion), see :mod:`._kernels`.
    balls : (B, 5) float64 ndarray
        Culling balls (X, Y, Z, r^2, occluder index), camera frame, mm
        (:func:`_culling_balls`).

    Notes
    -----
    Optional columns :data:`~plenoptrack._columns.SHAPE_COLUMNS` make rows with
    ``shape == "ellipsoid"`` prolate spheroids of volume-equivalent diameter ``diameter``:
    short semi-axes ``b = (d / 2) k^(-1/3)``, long semi-axis ``a = (d / 2) k^(2/3)``;
    rows with ``shape == "fragment"`` (and ``shape_seed``) irregular fragments
    (:func:`.fragments.fragment_geometry`). ``transmission`` (in [0, 1)) makes particles
    translucent; ``velocity_x, velocity_y, velocity_z`` (mm per frame) blur them over
    ``optics.realism.particles.exposure_fraction`` of the frame interval.
    """
    if particles is None:
        return np.zeros((0, 4)), _kernels.NO_SHAPES, np.zeros((0, 5))
    if not isinstance(particles, pd.DataFrame):
        raise TypeError(f"particles must be a pandas DataFrame; got {type(particles).__name__}")
    needed = [*POS_COLUMNS, DIAMETER_COLUMN]
    missing = [c for c in needed if c not in particles.columns]
    if missing:
        raise SceneError(f"particles table is missing column(s) {missing}; "
                         f"expected {needed} (mm, world frame)")
    if T_COLUMN in particles.columns and particles[T_COLUMN].nunique() > 1:
        raise SceneError("particles table holds several frames "
                         f"({sorted(particles[T_COLUMN].unique())[:5]}...); select one frame first")
    values = particles[needed].to_numpy(dtype=np.float64)
    if not np.isfinite(values).all():
        raise SceneError("particles table contains NaN or infinite positions or diameters")
    diam = values[:, 3]
    if (diam <= 0).any():
        raise SceneError(f"particle diameters must be positive (mm); got min {diam.min()}")
    kind, aspect, axis = _shape_arrays(particles)
    ell = kind == ELLIPSOID
    frags = _fragments(particles, kind, aspect, axis)
    tau = _transmissions(particles)
    sweep = _sweeps(optics, particles)                  # camera frame, mm over the exposure
    big_z = values[:, 2] + optics.s_o
    radius = diam / 2
    if ell.any():
        radius = np.where(ell, radius * aspect ** (2.0 / 3.0), radius)
    centre = np.zeros((len(values), 3))                 # ball centre - particle centre, world
    for r, frag in frags.items():
        centre[r] = frag.ball[:3]
        radius[r] = frag.ball[3] * (1.0 + 1e-9)
    extended = bool(frags or (tau > 0).any() or (sweep != 0).any()
                    or (optics.realism.particles.highlight_strength > 0 and len(values)))
    reach = radius
    if extended:
        reach = radius + 0.5 * np.sqrt((sweep ** 2).sum(axis=1)) * (1.0 + 1e-9)
    behind = big_z + centre[:, 2] - reach <= 0.05 * optics.s_o
    if behind.any():
        raise SceneError(f"particle(s) at z = {values[behind, 2][:3]} mm reach the main lens "
                         f"(the focal plane is {optics.s_o:.1f} mm in front of it); "
                         f"keep z - diameter/2 > {-0.95 * optics.s_o:.1f} mm")
    occ = np.column_stack([-(values[:, 0] + centre[:, 0]), -(values[:, 1] + centre[:, 1]),
                           big_z + centre[:, 2], reach ** 2])
    v = axis * np.array([-1.0, -1.0, 1.0])              # world -> camera frame
    balls = _culling_balls(occ, np.where(ell, aspect, 1.0), v, radius, reach - radius)
    if not ell.any() and not extended:
        return occ, _kernels.NO_SHAPES, balls
    n_planes = max((sum(len(p) for p in f.planes) for f in frags.values()), default=0)
    shapes = np.zeros((len(occ), _kernels.S_PLANES + 4 * n_planes if extended else 7))
    k2 = aspect ** 2
    c = 1.0 - k2
    shapes[:, 0] = ell
    shapes[:, 1] = k2 + c * v[:, 0] * v[:, 0]
    shapes[:, 2] = k2 + c * v[:, 1] * v[:, 1]
    shapes[:, 3] = k2 + c * v[:, 2] * v[:, 2]
    shapes[:, 4] = c * v[:, 0] * v[:, 1]
    shapes[:, 5] = c * v[:, 0] * v[:, 2]
    shapes[:, 6] = c * v[:, 1] * v[:, 2]
    shapes[~ell, 1:7] = 0.0
    if not extended:
        return occ, shapes, balls
    shapes[:, _kernels.S_R2] = radius ** 2
    shapes[:, _kernels.S_TAU] = tau
    shapes[:, _kernels.S_VX:_kernels.S_VZ + 1] = sweep
    flip = np.array([-1.0, -1.0, 1.0, 1.0])             # world -> camera frame
    for r, frag in frags.items():
        shapes[r, 0] = _kernels.FRAGMENT_T
        shapes[r, _kernels.S_NPIECE] = len(frag.planes)
        col = _kernels.S_PLANES
        for p, planes in enumerate(frag.planes):
            shapes[r, _kernels.S_PIECES + p] = len(planes)
            ball = frag.piece_balls[p]
            b0 = _kernels.S_BALLS + 4 * p
            shapes[r, b0:b0 + 3] = (ball[:3] - centre[r]) * flip[:3]
            shapes[r, b0 + 3] = (ball[3] * (1.0 + 1e-9)) ** 2
            # Offsets relative to the ball centre: n . (p - c - b) <= d - n . b.
            rel = np.column_stack([planes[:, :3], planes[:, 3] - planes[:, :3] @ centre[r]])
            shapes[r, col:col + 4 * len(planes)] = (rel * flip).ravel()
            col += 4 * len(planes)
    return occ, shapes, balls


CHAIN_ASPECT = 2.0
"""Spheroids at least this elongated are bounded by a chain of culling balls."""
MAX_CHAIN = 16
"""Most culling balls per spheroid."""


def _culling_balls(occluders: np.ndarray, aspect: np.ndarray, axis: np.ndarray,
                   radius: np.ndarray, sweep_reach: np.ndarray) -> np.ndarray:
    """Spheres that together contain each occluder, for the renderer's culling bounds.

    A prolate spheroid of long semi-axis ``a`` and aspect ``k >= CHAIN_ASPECT`` is covered
    by ``n = min(ceil(k), MAX_CHAIN)`` balls centred on its axis at ``-a + (2 i + 1) h``,
    ``h = a / n``, of radius ``sqrt(h^2 + b^2)``, ``b = a / k``: a point of the body lies
    within ``b`` of the axis and within ``h`` (along it) of a ball centre. For a pin's stem
    (``k`` about 13) each ball's radius is about 0.15 of the bounding sphere's, so far fewer
    lenses, pixels and samples are traced against it.
    Every other occluder keeps one ball, its ``occluders`` row (so renders without such
    spheroids run exactly as before).

    Parameters
    ----------
    occluders : (m, 4) float ndarray
        (X, Y, Z, reach^2) camera frame, mm (:func:`_particle_geometry`).
    aspect : (m,) float ndarray
        ``a / b`` of spheroids, 1 for every other occluder.
    axis : (m, 3) float ndarray
        Unit long axes, camera frame.
    radius : (m,) float ndarray
        Bounding radius without motion (``a`` of a spheroid), mm.
    sweep_reach : (m,) float ndarray
        Half the path over the exposure, mm, added to every ball's radius.

    Returns
    -------
    (B, 5) float64 ndarray
        Rows (X, Y, Z, r^2, occluder index).
    """
    m = len(occluders)
    one = np.column_stack([occluders, np.arange(m, dtype=np.float64)])
    chain = np.flatnonzero(aspect >= CHAIN_ASPECT)
    if len(chain) == 0:
        return one
    rows = [one[aspect < CHAIN_ASPECT]]
    for q in chain:
        a = radius[q]
        n = min(math.ceil(aspect[q]), MAX_CHAIN)
        h = a / n
        r = math.sqrt(h * h + (a / aspect[q]) ** 2) * (1.0 + 1e-9) + sweep_reach[q]
        s = -a + (2 * np.arange(n) + 1) * h
        centres = occluders[q, :3] + s[:, None] * axis[q]
        rows.append(np.column_stack([centres, np.full(n, r * r), np.full(n, float(q))]))
    balls = np.concatenate(rows)
    return balls[np.argsort(balls[:, 4], kind="stable")]


def _transmissions(particles: pd.DataFrame) -> np.ndarray:
    """Per-particle transmission in [0, 1) (0 without the column)."""
    if TRANSMISSION_COLUMN not in particles.columns:
        return np.zeros(len(particles))
    tau = particles[TRANSMISSION_COLUMN].to_numpy(dtype=np.float64)
    bad = ~(np.isfinite(tau) & (tau >= 0) & (tau < 1))
    if bad.any():
        raise SceneError(f"particle {TRANSMISSION_COLUMN} must be in [0, 1); "
                         f"got {tau[bad][:3].tolist()}")
    return tau


def _sweeps(optics: SimOptics, particles: pd.DataFrame) -> np.ndarray:
    """Displacement of each particle over the exposure, ``(n, 3)`` camera frame, mm:
    velocity (mm per frame) times ``optics.realism.particles.exposure_fraction``."""
    present = [c for c in VELOCITY_COLUMNS if c in particles.columns]
    if not present:
        return np.zeros((len(particles), 3))
    if len(present) < 3:
        raise SceneError(f"particle velocity needs all of {list(VELOCITY_COLUMNS)} "
                         f"(mm per frame, world frame); got only {present}")
    vel = particles[list(VELOCITY_COLUMNS)].to_numpy(dtype=np.float64)
    if not np.isfinite(vel).all():
        raise SceneError("particle velocities must be finite (mm per frame)")
    return vel * np.array([-1.0, -1.0, 1.0]) * optics.realism.particles.exposure_fraction


def _footprint_discs(optics: SimOptics, occluders: np.ndarray) -> np.ndarray:
    """Conservative MLA-plane discs ``(m, 3)`` [X, Y, radius] mm of the lens centres a
    particle can shade (see the module notes)."""
    if len(occluders) == 0:
        return np.zeros((0, 3))
    s_o = optics.s_o
    xy = occluders[:, :2]
    big_z = occluders[:, 2]
    r = np.sqrt(occluders[:, 3])
    near = big_z - r
    far = big_z + r
    centre = xy * (s_o / big_z)[:, None]
    blur = optics.aperture_radius * np.maximum(np.abs(1 - s_o / near), np.abs(1 - s_o / far))
    radius = (r * s_o / near + np.hypot(xy[:, 0], xy[:, 1]) * s_o * r / (big_z * near) + blur)
    seidel, tilt = _lens_margins(optics)
    if seidel > 0:
        radius = radius + seidel
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    pts = centre[:, None, :] + radius[:, None, None] * ring[None]
    mla_ring = optics.focal_plane_to_mla(pts)
    mla_centre = optics.focal_plane_to_mla(centre)
    # 64 ring points miss at most 1 - cos(pi / 64) < 0.13 % of the radius: covered by
    # the pitch added to the growth.
    reach = np.hypot(*(mla_ring - mla_centre[:, None, :]).transpose(2, 0, 1)).max(axis=1)
    grow = optics.cell_radius + 2 * optics.pitch
    if tilt > 0:
        grow = grow + tilt
    return np.column_stack([mla_centre, reach * 1.002 + grow])


def _lens_margins(optics: SimOptics) -> tuple[float, float]:
    """Bounds of the lens effects on the footprints (module notes of :mod:`._kernels`).

    Returns ``(seidel, tilt)``: the largest Seidel transverse error on the focal plane of
    any ray that passes the aperture, mm, and the largest distance between a ray's point
    ``Q`` on the tilted MLA and its point on the nominal MLA plane, mm.
    """
    lens = optics.realism.lens
    t = math.hypot(*optics.mla_tilt)
    if not (lens.field_curvature_mm or lens.astigmatism_mm or lens.coma_mm or t):
        return 0.0, 0.0
    r_n = optics.distortion_radius_mm
    q_max = r_n / optics.image_scale + 2 * optics.cell_radius          # |Q| of any sample
    w = t * q_max / (optics.s_i - t * q_max)                             # |delta| / s_l
    u_max = (q_max + math.hypot(*optics.axis_offset_mm)) * (1 + w) + optics.aperture_radius * w
    rho = u_max / r_n
    seidel = ((lens.field_curvature_mm + 1.5 * lens.astigmatism_mm) * optics.aperture_radius
              / optics.s_o * rho ** 2 + lens.coma_mm * rho) * 1.001
    tilt = w * (u_max + optics.aperture_radius) / (1 - w) * 1.001
    return seidel, tilt


def particle_lenses(optics: SimOptics, occluders: np.ndarray):
    """Lenses to re-trace and the spheres to test for each.

    Parameters
    ----------
    optics : SimOptics
    occluders : (m, 4) float ndarray
        Spheres (X, Y, Z, r^2) in the camera frame, mm: the occluders' bounding spheres
        or their culling balls (:func:`_culling_balls`, first four columns).

    Returns
    -------
    lenses : (L, 2) int64 ndarray
        Lens indices (i, j), sorted.
    ptr : (L + 1,) int64 ndarray
        Lens ``k`` is tested against ``occluders[idx[ptr[k]:ptr[k + 1]]]``.
    idx : int64 ndarray
        Row indices into ``occluders``.
    """
    discs = _footprint_discs(optics, occluders)
    keys, owners = [], []
    for p, (x, y, rad) in enumerate(discs):
        corners = np.array([[x - rad, y - rad], [x - rad, y + rad], [x + rad, y - rad],
                            [x + rad, y + rad]])
        ia = optics.lattice_coords(corners)
        i = np.arange(math.floor(ia[:, 0].min()) - 1, math.ceil(ia[:, 0].max()) + 2)
        j = np.arange(math.floor(ia[:, 1].min()) - 2, math.ceil(ia[:, 1].max()) + 2)
        ii, jj = np.meshgrid(i, j, indexing="ij")
        c = optics.lens_centers_mm(ii, jj)
        inside = (c[..., 0] - x) ** 2 + (c[..., 1] - y) ** 2 <= rad ** 2
        keys.append((ii[inside] + _KEY_OFFSET) * (2 * _KEY_OFFSET) + (jj[inside] + _KEY_OFFSET))
        owners.append(np.full(int(inside.sum()), p, dtype=np.int64))
    if not keys:
        return np.zeros((0, 2), np.int64), np.zeros(1, np.int64), np.zeros(0, np.int64)
    keys = np.concatenate(keys)
    owners = np.concatenate(owners)
    order = np.lexsort((owners, keys))
    keys, owners = keys[order], owners[order]
    uniq, start = np.unique(keys, return_index=True)
    lenses = np.column_stack([uniq // (2 * _KEY_OFFSET) - _KEY_OFFSET,
                              uniq % (2 * _KEY_OFFSET) - _KEY_OFFSET]).astype(np.int64)
    ptr = np.append(start, len(keys)).astype(np.int64)
    return lenses, ptr, owners


def render_irradiance(optics: SimOptics, particles: pd.DataFrame | None = None, *,
                      samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                      cull: bool = True) -> np.ndarray:
    """Noise-free irradiance of a back-lit frame with spherical, spheroidal or fragment particles.

    Parameters
    ----------
    optics : SimOptics
        True camera optics.
    particles : DataFrame or None
        One frame of particles, columns ``x, y, z, diameter`` (world frame, mm); optional
        :data:`~plenoptrack._columns.SHAPE_COLUMNS` (``shape, aspect, axis_x, axis_y,
        axis_z``) make rows with ``shape == "ellipsoid"`` prolate spheroids and, with
        ``shape_seed``, rows with ``shape == "fragment"`` irregular fragments
        (``diameter`` then volume-equivalent; see :func:`_particle_arrays`); optional
        ``transmission`` (in [0, 1)) and ``velocity_x, velocity_y, velocity_z`` (mm per
        frame, world frame) make them translucent and blurred over the exposure
        (``optics.realism.particles``, which also switches the highlights).
    samples_per_pixel : int
        Rays per pixel.
    cull : bool
        True (default) re-traces only the lenses a particle can shade, starting from the
        cached empty image; False traces every pixel against every particle (slow, for
        checking). Both give identical results.

    Returns
    -------
    (rows, cols) float32 ndarray
        Fraction of the back-light reaching each sensor pixel, in [0, 1] (with
        highlights, never more than the empty camera's).
    """
    _check_optics(optics)
    n = _check_samples(samples_per_pixel)
    occ, shapes, balls = _particle_geometry(optics, particles)
    par = _kernels.pack_params(optics)
    samples = sample_pattern(optics, n)
    if not cull:
        rows, cols = optics.camera.sensor_shape_px
        return _kernels.render_all(par, samples, occ, _NO_CARD, 0, rows, 0, cols, True,
                                   shapes=shapes, balls=balls)
    out = background_irradiance(optics, n).copy()
    if len(occ):
        lenses, ptr, idx = particle_lenses(optics, balls[:, :4])
        _kernels.render_lenses(out, lenses, ptr, idx, par, samples, occ, _NO_CARD,
                               shapes=shapes, balls=balls)
    return out


def render_white(optics: SimOptics, *, seed: int | np.random.Generator | None = 0,
                 noise: bool = True, samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                 sensor: SensorModel = SensorModel()) -> np.ndarray:
    """Raw white (flat-field) image: the back-light only, exposed at ``sensor.white_level``.

    Parameters
    ----------
    optics : SimOptics
        True camera optics.
    seed : int or numpy.random.Generator
        Noise seed.
    noise : bool
        False gives the rounded expected counts.
    samples_per_pixel : int
        Rays per pixel.
    sensor : SensorModel
        Full well, read noise and exposure levels.

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts, ``camera.bit_depth`` significant bits.

    Examples
    --------
    >>> from plenoptrack import preset
    >>> from plenoptrack.simulate import make_optics
    >>> white = render_white(make_optics(preset("small"), seed=0), seed=0)
    >>> white.shape, white.dtype
    ((600, 910), dtype('uint16'))
    """
    irr = background_irradiance(optics, _check_samples(samples_per_pixel))
    return expose_image(irr, optics, level=sensor.white_level, sensor=sensor, seed=seed,
                        noise=noise, white=True)


def render_frame(optics: SimOptics, particles: pd.DataFrame | None, *,
                 seed: int | np.random.Generator | None = 0, noise: bool = True,
                 samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                 sensor: SensorModel = SensorModel()) -> np.ndarray:
    """Raw image of one frame of particles in front of the back-light.

    Parameters
    ----------
    optics : SimOptics
        True camera optics.
    particles : DataFrame or None
        Columns ``x, y, z, diameter`` (world frame, mm) and the optional shape and effect
        columns of :func:`render_irradiance`; a ``frame`` column, if present, must hold
        a single value.
    seed : int or numpy.random.Generator
        Noise seed; the same inputs and seed give identical bytes.
    noise : bool
        False gives the rounded expected counts.
    samples_per_pixel : int
        Rays per pixel.
    sensor : SensorModel
        Full well, read noise and exposure (``background_level``).

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts.
    """
    return next(render_repeats(optics, particles, [seed], noise=noise,
                               samples_per_pixel=samples_per_pixel, sensor=sensor))


def render_repeats(optics: SimOptics, particles: pd.DataFrame | None, seeds, *,
                   noise: bool = True, samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                   sensor: SensorModel = SensorModel()):
    """Raw images of one unchanged scene, one per noise seed, ray-traced once.

    Repeated exposures of a still scene differ only in the image-domain draws of
    :func:`expose_image` (back-light change, noise), so the scene's irradiance is traced
    once and exposed for each seed. Image ``k`` is bit-identical to
    ``render_frame(optics, particles, seed=seeds[k], ...)``.

    Parameters
    ----------
    optics, particles, noise, samples_per_pixel, sensor
        As :func:`render_frame`.
    seeds : iterable of int or numpy.random.Generator
        One noise seed per image.

    Yields
    ------
    (rows, cols) uint16 ndarray
        The raw counts for each seed in turn; the trace happens at the first one.
    """
    irr = render_irradiance(optics, particles, samples_per_pixel=samples_per_pixel)
    for seed in seeds:
        yield expose_image(irr, optics, level=sensor.background_level, sensor=sensor,
                           seed=seed, noise=noise)


def render_dark(optics: SimOptics, *, seed: int | np.random.Generator | None = 0,
                noise: bool = True, sensor: SensorModel = SensorModel()) -> np.ndarray:
    """Raw dark frame (no light): the sensor's pedestal, offset map, hot pixels and noise.

    Parameters
    ----------
    optics : SimOptics
        True camera optics (``optics.realism.sensor`` gives the fixed patterns).
    seed : int or numpy.random.Generator
        Noise seed.
    noise : bool
        False gives the rounded dark level.
    sensor : SensorModel
        Full well and read noise.

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts; all zero for an ideal sensor without noise.
    """
    _check_optics(optics)
    irr = np.zeros(optics.camera.sensor_shape_px, dtype=np.float32)
    return expose(irr, level=sensor.background_level, bit_depth=optics.camera.bit_depth,
                  sensor=sensor, rng=np.random.default_rng(seed), noise=noise,
                  fixed=fixed_pattern(optics) if optics.realism.sensor.enabled else None)


def expose_image(irradiance: np.ndarray, optics: SimOptics, *, level: float,
                 sensor: SensorModel, seed: int | np.random.Generator | None,
                 noise: bool = True, white: bool = False) -> np.ndarray:
    """Raw counts of a traced irradiance, with the image-domain effects of ``optics.realism``.

    Parameters
    ----------
    irradiance : (rows, cols) float ndarray
        Ray-traced irradiance relative to the back-light (not changed).
    optics : SimOptics
        Camera; ``optics.realism`` groups ``illumination``, ``blur`` and ``sensor`` are
        applied in that order when enabled (see the module notes).
    level : float
        Expected signal of a fully lit pixel as a fraction of full scale.
    sensor : SensorModel
        Full well and read noise.
    seed : int or numpy.random.Generator
        The image's noise seed; a child of it (:func:`.illumination.image_rng`) draws the
        back-light change of a frame, so the noise draws do not depend on it.
    noise : bool
        False gives the rounded expected counts.
    white : bool
        True for the white image: the camera's back-light without a frame change.

    Returns
    -------
    (rows, cols) uint16 ndarray
        Raw counts; bit-identical to :func:`.sensor.expose` of the input when the three
        groups are off.
    """
    real = optics.realism
    rng = np.random.default_rng(seed)
    irr = irradiance
    if real.illumination.enabled:
        irr = illuminated(irr, optics, None if white else image_rng(rng))
    if real.blur.enabled:
        irr = blur_image(irr, optics)
    return expose(irr, level=level, bit_depth=optics.camera.bit_depth, sensor=sensor, rng=rng,
                  noise=noise, fixed=fixed_pattern(optics) if real.sensor.enabled else None)

