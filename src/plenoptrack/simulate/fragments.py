"""Irregular particle fragments: geometry from a seed, exact volume moments and silhouettes.

A fragment is the union of one to three random convex polytopes, each the intersection of
8-14 half-spaces ``n . (p - c) <= d`` (``n`` a unit normal, ``d`` mm). All pieces contain
one common core point, so the union is star-shaped about it; one piece is a convex
fragment. The body is built in four steps from its ``shape_seed``:

1. Base pieces about the core point: each piece is a randomly rotated octahedron (8
   planes at distances 0.55-1, so it is bounded) cut by 0-6 further random planes (at
   distances 0.4-1); the second and third pieces are stretched by 1.5-2.5 along a random
   direction, so the union can be elongated, bent or cross-shaped.
2. Exact volume moments of the union (inclusion-exclusion over the pieces' intersections,
   each a convex polytope; its moments from the tetrahedra of its hull): volume, centroid,
   covariance.
3. A linear map that turns the covariance into that of a prolate spheroid of aspect
   ``aspect`` (principal axes scaled), then a scale that makes the volume ``pi d^3 / 6``
   (``d = diameter``), then a rotation that takes the long principal axis to ``axis`` with
   a roll about it drawn from the seed.
4. The centroid becomes the particle centre (the truth position).

So ``diameter`` is the volume-equivalent diameter, ``aspect`` the long over short semi-axis
of the *equivalent ellipsoid* (same volume second moments) and ``axis`` its long axis, the
meanings these columns have for spheroids; a spheroid is its own equivalent ellipsoid.
The facets and the non-convex union make the body irregular at any aspect.

The silhouette along the optical axis is the union of the pieces' projected convex
polygons; its area and second moments are exact (inclusion-exclusion over polygon
intersections by Sutherland-Hodgman clipping).
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FRAGMENT_REACH", "MAX_PIECES", "MAX_PLANES_PER_PIECE", "Fragment",
           "fragment_geometry", "fragment_silhouette"]

MAX_PIECES = 3
"""Largest number of convex pieces of a fragment."""
MAX_PLANES_PER_PIECE = 14
"""Largest number of half-spaces of one piece."""
FRAGMENT_REACH = 1.6
"""Upper bound of a fragment's bounding radius over ``(d / 2) aspect^(2/3)`` (the long
semi-axis of the spheroid of the same diameter and aspect); a body that would reach further
is redrawn (from the next sub-seed), so placement margins can rely on it."""

_OCTANT = np.array(list(itertools.product((-1.0, 1.0), repeat=3))) / math.sqrt(3.0)


@dataclass(frozen=True, eq=False)
class Fragment:
    """Geometry of one fragment, world frame, relative to its centre (volume centroid).

    Attributes
    ----------
    planes : tuple of (k, 4) float64 ndarray
        One array per convex piece: rows ``(n_x, n_y, n_z, d)``, unit outward normal and
        offset, mm; the piece is ``{p : n . (p - centre) <= d}``.
    vertices : tuple of (v, 3) float64 ndarray
        Vertices of each piece relative to the centre, mm.
    bounding_radius : float
        Largest distance of a vertex from the centre, mm.
    volume : float
        Volume of the union, mm^3 (``pi d^3 / 6``).
    ball : (4,) float64 ndarray
        A small sphere enclosing the fragment: centre relative to the particle centre and
        radius, mm (within a few per cent of the smallest; the renderer culls with it).
    piece_balls : (p, 4) float64 ndarray
        The same for each piece (the renderer's first test of a piece).
    """

    planes: tuple
    vertices: tuple
    bounding_radius: float
    volume: float
    ball: np.ndarray
    piece_balls: np.ndarray


def _unit_rows(a: np.ndarray) -> np.ndarray:
    return a / np.sqrt((a ** 2).sum(axis=1))[:, None]


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _base_pieces(rng: np.random.Generator) -> list[np.ndarray]:
    """Half-spaces ``(n, d)`` of 1-3 pieces about the core point (step 1 of the notes)."""
    pieces = []
    for p in range(int(rng.integers(1, MAX_PIECES + 1))):
        normals = _OCTANT @ _random_rotation(rng).T
        offsets = rng.uniform(0.55, 1.0, len(normals))
        extra = int(rng.integers(0, MAX_PLANES_PER_PIECE - 8 + 1))
        normals = np.concatenate([normals, _unit_rows(rng.standard_normal((extra, 3)))])
        offsets = np.concatenate([offsets, rng.uniform(0.4, 1.0, extra)])
        if p > 0:
            # Stretch x -> (I + (f - 1) w w^T) x: normals map by the inverse transpose.
            w = _unit_rows(rng.standard_normal((1, 3)))[0]
            f = rng.uniform(1.5, 2.5)
            normals = normals + (1.0 / f - 1.0) * np.outer(normals @ w, w)
            norm = np.sqrt((normals ** 2).sum(axis=1))
            normals, offsets = normals / norm[:, None], offsets / norm
        pieces.append(np.column_stack([normals, offsets]))
    return pieces


def _polytope_vertices(planes: np.ndarray) -> np.ndarray:
    """Vertices of ``{p : n . p <= d}`` (every ``d`` > 0: the origin is inside)."""
    from scipy.spatial import HalfspaceIntersection

    hs = np.column_stack([planes[:, :3], -planes[:, 3]])
    return HalfspaceIntersection(hs, np.zeros(3)).intersections


def _hull_moments(vertices: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume, first moment (3,) and second moment (3, 3) about the origin of the convex
    hull of ``vertices`` (origin inside): the sum over the tetrahedra (origin, facet)."""
    from scipy.spatial import ConvexHull

    tri = vertices[ConvexHull(vertices).simplices]            # (f, 3, 3)
    vol = np.abs(np.linalg.det(tri)) / 6.0
    s = tri.sum(axis=1)
    first = (vol[:, None] * s).sum(axis=0) / 4.0
    outer = np.einsum("fij,fik->fjk", tri, tri) + np.einsum("fj,fk->fjk", s, s)
    second = (vol[:, None, None] * outer).sum(axis=0) / 20.0
    return float(vol.sum()), first, second


def _union_moments(pieces: list[np.ndarray]):
    """Volume moments of the union of convex pieces (inclusion-exclusion)."""
    vol, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    for size in range(1, len(pieces) + 1):
        sign = 1.0 if size % 2 else -1.0
        for subset in itertools.combinations(pieces, size):
            v, f, s = _hull_moments(_polytope_vertices(np.concatenate(subset)))
            vol += sign * v
            first = first + sign * f
            second = second + sign * s
    return vol, first, second


def _orientation_matrix(axis: np.ndarray, roll: float) -> np.ndarray:
    """Rotation taking +x to ``axis`` (unit), then turned by ``roll`` about it."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e2 = np.cross(axis, ref)
    e2 /= np.linalg.norm(e2)
    e3 = np.cross(axis, e2)
    c, s = math.cos(roll), math.sin(roll)
    return np.column_stack([axis, c * e2 + s * e3, -s * e2 + c * e3])


def _enclosing_ball(points: np.ndarray) -> np.ndarray:
    """``(cx, cy, cz, r)``: a sphere enclosing ``points`` (v, 3), near the smallest one
    (Badoiu-Clarkson iterations from the box centre; ``r`` the exact farthest distance)."""
    c = 0.5 * (points.min(axis=0) + points.max(axis=0))
    for i in range(1, 400):
        far = points[np.argmax(((points - c) ** 2).sum(axis=1))]
        c = c + (far - c) / (i + 1)
    r = float(np.sqrt(((points - c) ** 2).sum(axis=1)).max())
    return np.array([*c, r])


def _build(rng: np.random.Generator, diameter: float, aspect: float, axis: np.ndarray) -> Fragment:
    pieces = _base_pieces(rng)
    roll = rng.uniform(0.0, 2.0 * math.pi)
    vol, first, second = _union_moments(pieces)
    centroid = first / vol
    cov = second / vol - np.outer(centroid, centroid)
    lam, vec = np.linalg.eigh(cov)
    lam, vec = lam[::-1], vec[:, ::-1]
    # Deterministic eigenvector signs: largest component positive.
    vec = vec * np.sign(vec[np.abs(vec).argmax(axis=0), np.arange(3)])
    g = np.array([aspect, 1.0, 1.0]) / np.sqrt(lam)
    scale = (math.pi / 6.0 * diameter ** 3 / (vol * float(np.prod(g)))) ** (1.0 / 3.0)
    rot = _orientation_matrix(axis, roll)
    lin = scale * rot @ np.diag(g) @ vec.T                     # core frame -> world frame
    inv_t = rot @ np.diag(1.0 / g) @ vec.T / scale             # lin^-T
    planes, verts = [], []
    for piece in pieces:
        n = piece[:, :3] @ inv_t.T
        d = piece[:, 3] - piece[:, :3] @ centroid
        norm = np.sqrt((n ** 2).sum(axis=1))
        planes.append(np.column_stack([n / norm[:, None], d / norm]))
        verts.append((_polytope_vertices(piece) - centroid) @ lin.T)
    reach = max(float(np.sqrt((v ** 2).sum(axis=1)).max()) for v in verts)
    return Fragment(planes=tuple(planes), vertices=tuple(verts), bounding_radius=reach,
                    volume=math.pi / 6.0 * diameter ** 3,
                    ball=_enclosing_ball(np.concatenate(verts)),
                    piece_balls=np.array([_enclosing_ball(v) for v in verts]))


@functools.lru_cache(maxsize=4096)
def _cached_geometry(shape_seed: int, diameter: float, aspect: float,
                     axis: tuple[float, float, float]) -> Fragment:
    u = np.asarray(axis, dtype=float)
    u = u / np.linalg.norm(u)
    limit = FRAGMENT_REACH * diameter / 2.0 * aspect ** (2.0 / 3.0)
    for attempt in range(100):
        frag = _build(np.random.default_rng([shape_seed, attempt]), diameter, aspect, u)
        if frag.bounding_radius <= limit:
            return frag
    raise RuntimeError(f"no fragment within the reach bound for shape_seed {shape_seed}")


def fragment_geometry(shape_seed: int, diameter: float, aspect: float, axis) -> Fragment:
    """The fragment of a truth row: the same inputs always give the same body.

    Parameters
    ----------
    shape_seed : int
        Seed of the irregular geometry (>= 0).
    diameter : float
        Volume-equivalent diameter, mm.
    aspect : float
        Long over short semi-axis of the equivalent ellipsoid (>= 1).
    axis : (3,) array-like
        Long axis of the equivalent ellipsoid, world frame (normalised here).

    Returns
    -------
    Fragment
        Planes and vertices relative to the centre, world frame, mm (cached).
    """
    return _cached_geometry(int(shape_seed), float(diameter), float(aspect),
                            tuple(float(v) for v in np.asarray(axis, dtype=float).reshape(3)))


def _convex_polygon(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull (v, 2) of 2-D points."""
    from scipy.spatial import ConvexHull

    return points[ConvexHull(points).vertices]


def _clip(subject: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the part of convex polygon ``subject`` inside convex
    counter-clockwise ``clipper``; (0, 2) when they do not overlap."""
    out = subject
    for k in range(len(clipper)):
        if len(out) == 0:
            break
        a, b = clipper[k], clipper[(k + 1) % len(clipper)]
        e = b - a
        side = e[0] * (out[:, 1] - a[1]) - e[1] * (out[:, 0] - a[0])   # >= 0: inside
        nxt = np.roll(out, -1, axis=0)
        side_n = np.roll(side, -1)
        pts = []
        for p, q, sp, sq in zip(out, nxt, side, side_n):
            if sp >= 0:
                pts.append(p)
            if (sp >= 0) != (sq >= 0):
                pts.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(pts).reshape(-1, 2)
    return out


def _polygon_moments(poly: np.ndarray) -> np.ndarray:
    """``(A, Sx, Sy, Ixx, Iyy, Ixy)``: area and first and second moments about the origin
    of a counter-clockwise polygon (zeros for fewer than 3 vertices)."""
    if len(poly) < 3:
        return np.zeros(6)
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    c = x * yn - xn * y
    return np.array([c.sum() / 2.0,
                     ((x + xn) * c).sum() / 6.0,
                     ((y + yn) * c).sum() / 6.0,
                     ((x * x + x * xn + xn * xn) * c).sum() / 12.0,
                     ((y * y + y * yn + yn * yn) * c).sum() / 12.0,
                     ((x * yn + 2 * x * y + 2 * xn * yn + xn * y) * c).sum() / 24.0])


def fragment_silhouette(fragment: Fragment) -> tuple[float, float]:
    """Area and orientation of a fragment's silhouette along the optical axis.

    Returns
    -------
    area : float
        Area of the union of the pieces' projected convex polygons, mm^2 (exact).
    orientation : float
        Long axis of the silhouette (from its second moments of area), rad from world +x
        towards +y, in [-pi/2, pi/2); 0 when the moments are isotropic.
    """
    polys = [_convex_polygon(v[:, :2]) for v in fragment.vertices]
    m = np.zeros(6)
    for size in range(1, len(polys) + 1):
        sign = 1.0 if size % 2 else -1.0
        for subset in itertools.combinations(polys, size):
            inter = subset[0]
            for other in subset[1:]:
                inter = _clip(inter, other)
            m += sign * _polygon_moments(inter)
    area = float(m[0])
    cx, cy = m[1] / area, m[2] / area
    mxx = m[3] / area - cx * cx
    myy = m[4] / area - cy * cy
    mxy = m[5] / area - cx * cy
    if abs(mxx - myy) + abs(mxy) <= 1e-12 * (mxx + myy):
        return area, 0.0
    theta = 0.5 * math.atan2(2.0 * mxy, mxx - myy)
    return area, (theta + math.pi / 2) % math.pi - math.pi / 2
