"""Clustering of particle centroids across views on projected refocus planes.

Each detection ``(u, v, s, t)`` is a ray: it crossed the main-lens aperture at ``U(u, v)``
and the microlens plane at ``X(s, t)``. Projected to the plane ``alpha`` (distance
``alpha * s_i`` from the main lens) it lands at ``X' = U + (X - U) * alpha``. The rays of
one particle converge where the particle is imaged, so at a plane near that depth its
detections from all views form a tight cluster. The clustering runs k-means at a set of
planes, accepts clusters smaller than the size threshold ``T`` of that plane and removes
their members before the next plane (section 2.2 of the reference).

References
----------
E. M. Hall, D. R. Guildenbecher, B. S. Thurow, "Development and uncertainty
characterization of 3D particle location from perspective shifted plenoptic images",
Opt. Express 27 (2019), section 2.2.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numba
import numpy as np
import pandas as pd

from ..errors import NoParticlesWarning, SettingsError
from ._order import median, stable_argsort, unique_rows

__all__ = ["ProjectionGeometry", "Clustering", "plane_alphas", "size_thresholds",
           "project", "cluster_detections"]

CLUSTER_COLUMNS = ("cluster", "alpha", "n", "size_mm", "threshold_mm", "plane_x_mm",
                   "plane_y_mm", "s", "t")
"""Columns of the per-cluster table (see :func:`cluster_detections`)."""


@dataclass(frozen=True)
class ProjectionGeometry:
    """First-order conversion of light-field coordinates to physical ray positions.

    Parameters
    ----------
    aperture_mm_per_u : float
        Signed aperture position per unit of ``u`` (and of ``v``): the ray of view
        ``(u, v)`` crosses the main-lens aperture at ``U = aperture_mm_per_u * (u, v)``,
        mm, camera frame (``X`` along sensor columns). Negative for a plenoptic 1.0
        camera: ``-pixel_pitch * s_i / f_ml`` (see ``docs/conventions.md``).
    mm_per_sample : float
        Spacing of the spatial samples ``(s, t)`` on the microlens-array plane, mm.
    axis_st : (float, float)
        Spatial coordinates ``(s, t)``, view pixels, where the optical axis meets the
        microlens array.
    aperture_diameter_mm : float
        Diameter of the main-lens aperture, mm (``F / N``); sets the size threshold.

    Notes
    -----
    The microlens-plane position of sample ``(s, t)`` is
    ``X = (s - axis_s) * mm_per_sample``, ``Y = (t - axis_t) * mm_per_sample``; the
    sample grid is taken as aligned with the sensor axes (a lattice rotation of a few
    milliradians shifts projected positions by far less than a sample).
    """

    aperture_mm_per_u: float
    mm_per_sample: float
    axis_st: tuple[float, float]
    aperture_diameter_mm: float

    def __post_init__(self) -> None:
        for name in ("mm_per_sample", "aperture_diameter_mm"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise SettingsError(f"{name} must be a positive number; got {value!r}")
            object.__setattr__(self, name, value)
        g = float(self.aperture_mm_per_u)
        if not (math.isfinite(g) and g != 0):
            raise SettingsError(f"aperture_mm_per_u must be a non-zero number; got {g!r}")
        object.__setattr__(self, "aperture_mm_per_u", g)
        axis = tuple(float(x) for x in self.axis_st)
        if len(axis) != 2:
            raise SettingsError(f"axis_st must be a pair (s, t); got {self.axis_st!r}")
        object.__setattr__(self, "axis_st", axis)

    @classmethod
    def from_camera(cls, camera, *, sample_spacing_px: float,
                    axis_st: tuple[float, float]) -> "ProjectionGeometry":
        """Build the geometry from a :class:`~plenoptrack.camera.CameraSpec`.

        Parameters
        ----------
        camera : CameraSpec
            Nominal camera (pixel pitch, main-lens focal length and f-number,
            magnification, microlens focal length).
        sample_spacing_px : float
            Spacing of the spatial samples measured on the sensor, pixels (the spacing of
            microlens-image centres, e.g. ``LightField.sample_spacing_px``).
        axis_st : (float, float)
            ``(s, t)`` of the optical axis, view pixels (e.g. ``LightField.axis_st``).
        """
        pitch_mm = camera.pixel_pitch_um * 1e-3
        f_ml_mm = camera.microlens_focal_length_um * 1e-3
        s_i = camera.image_distance_mm
        return cls(aperture_mm_per_u=-pitch_mm * s_i / f_ml_mm,
                   mm_per_sample=sample_spacing_px * pitch_mm / (1.0 + f_ml_mm / s_i),
                   axis_st=axis_st, aperture_diameter_mm=camera.aperture_diameter_mm)

    @classmethod
    def from_lightfield(cls, lf, camera) -> "ProjectionGeometry":
        """Build the geometry from a decoded light field and its nominal camera."""
        return cls.from_camera(camera, sample_spacing_px=lf.sample_spacing_px,
                               axis_st=lf.axis_st)

    def parallax_per_u(self, alpha) -> np.ndarray:
        """Shift of a point imaged at plane ``alpha`` per unit ``u`` (or ``v``), samples.

        From ``X = U + (X_p - U) / alpha_p`` at the microlens plane:
        ``dX/du = aperture_mm_per_u * (1 - 1 / alpha)``. Positive (towards larger ``s``)
        for a point behind the focal plane (``alpha < 1``) with the usual negative
        ``aperture_mm_per_u``.
        """
        alpha = np.asarray(alpha, dtype=float)
        return self.aperture_mm_per_u * (1.0 - 1.0 / alpha) / self.mm_per_sample


def project(u, v, s, t, alpha: float, geometry: ProjectionGeometry) -> np.ndarray:
    """Project detections to the refocus plane ``alpha``.

    Parameters
    ----------
    u, v : (n,) float ndarray
        View coordinates (sensor pixels from the microlens-image centre).
    s, t : (n,) float ndarray
        Centroids, view pixels (column, row).
    alpha : float
        Plane distance from the main lens in units of ``s_i`` (``alpha = 1`` is the
        microlens plane).
    geometry : ProjectionGeometry

    Returns
    -------
    (n, 2) float64 ndarray
        Positions ``(X', Y')`` on the plane, mm, camera frame:
        ``X' = U + (X - U) * alpha``.
    """
    g = geometry
    U = np.column_stack([np.asarray(u, float), np.asarray(v, float)]) * g.aperture_mm_per_u
    X = (np.column_stack([np.asarray(s, float), np.asarray(t, float)])
         - np.asarray(g.axis_st)) * g.mm_per_sample
    return U + (X - U) * alpha


def plane_alphas(camera, depth_range_mm: tuple[float, float], n_planes: int = 10) -> np.ndarray:
    """Refocus planes evenly spaced in ``alpha`` over a depth range.

    Parameters
    ----------
    camera : CameraSpec
    depth_range_mm : (float, float)
        Nearest and farthest object depth ``z`` of the measurement volume, mm.
    n_planes : int
        Number of planes (the reference uses 10).

    Returns
    -------
    (n_planes,) float64 ndarray
        ``alpha`` values, ascending, from the far end (small alpha) to the near end.
    """
    z0, z1 = (float(z) for z in depth_range_mm)
    if not z1 > z0:
        raise SettingsError(f"depth_range_mm must be (near, far) with far > near; got {depth_range_mm!r}")
    if n_planes < 1:
        raise SettingsError(f"n_planes must be at least 1; got {n_planes!r}")
    a = camera.alpha_for_depth(np.array([z1, z0]))
    return np.linspace(a[0], a[1], int(n_planes))


def size_thresholds(alphas, aperture_diameter_mm: float, *, margin: float = 1.2,
                    floor_mm: float = 0.0) -> np.ndarray:
    """Cluster size threshold ``T`` at every plane, mm.

    Parameters
    ----------
    alphas : (n,) float ndarray
        Ascending plane positions.
    aperture_diameter_mm : float
        Main-lens aperture diameter ``D = F / N``, mm.
    margin : float
        Safety factor (1.2 in the reference).
    floor_mm : float
        Added to every threshold (centroid noise), mm.

    Returns
    -------
    (n,) float64 ndarray

    Notes
    -----
    A point imaged at ``alpha_p`` sends rays through every aperture point ``U`` (``|U|
    <= D / 2``); at plane ``alpha`` they cross at ``U (1 - alpha / alpha_p) + X_p alpha /
    alpha_p``, a disc of diameter ``D |alpha_p - alpha| / alpha_p``. A particle that is
    closer to plane ``alpha_s`` than to a neighbouring plane has ``alpha_p`` between
    ``alpha_s`` and the half-way value ``alpha_1/2``, so its cluster is at most
    ``D |alpha_1/2 - alpha_s| / alpha_1/2`` wide, hence
    ``T = margin * (F / N) * |alpha_1/2 - alpha_s| / alpha_1/2`` -- the reference's form
    with ``alpha`` the geometric (``d / s_i``) plane parameter. Interior planes take the
    larger of their two half-way gaps; a single plane gets ``floor_mm`` only.
    """
    a = np.asarray(alphas, dtype=float)
    if a.ndim != 1 or len(a) == 0 or np.any(np.diff(a) <= 0):
        raise SettingsError("alphas must be a non-empty, strictly ascending 1-D array")
    t = np.zeros(len(a))
    if len(a) > 1:
        half = 0.5 * (a[1:] + a[:-1])
        lower = aperture_diameter_mm * np.abs(half - a[1:]) / half    # toward smaller alpha
        upper = aperture_diameter_mm * np.abs(half - a[:-1]) / half   # toward larger alpha
        t[1:] = lower
        t[:-1] = np.maximum(t[:-1], upper)
    return margin * t + floor_mm


@dataclass(frozen=True)
class Clustering:
    """Result of :func:`cluster_detections`.

    Attributes
    ----------
    detections : pandas.DataFrame
        The input table plus ``cluster`` (int, -1 = unassigned) and ``cluster_alpha``
        (float, plane where the cluster was accepted; NaN if unassigned).
    clusters : pandas.DataFrame
        One row per cluster, columns ``cluster`` (int), ``alpha`` (plane), ``n`` (members),
        ``size_mm`` (largest member distance on the plane), ``threshold_mm`` (``T`` of
        the plane), ``plane_x_mm, plane_y_mm`` (mean member position on the plane, mm,
        camera frame), ``s, t`` (that position in view pixels of an image refocused to
        ``alpha``: ``axis + X' / (alpha * mm_per_sample)``).
    """

    detections: pd.DataFrame
    clusters: pd.DataFrame

    @property
    def n_clusters(self) -> int:
        """Number of accepted clusters."""
        return len(self.clusters)


# --------------------------------------------------------------------------------------
# compiled cores
@numba.njit(cache=True)
def _centre_grid(centres):  # pragma: no cover - compiled
    """Bucket the centres (k, 2) on a square grid over their bounding box.

    Returns ``(start, items, lo_x, lo_y, h, nx, ny, slack)``: cell ``iy * nx + ix`` holds
    ``items[start[cell]:start[cell + 1]]`` (ascending centre indices); cells of side
    ``h`` hold about one centre each; ``slack`` absorbs the rounding of cell positions.
    """
    k = centres.shape[0]
    lo_x = hi_x = lo_y = hi_y = 0.0
    if k > 0:
        lo_x = hi_x = centres[0, 0]
        lo_y = hi_y = centres[0, 1]
    for c in range(1, k):
        lo_x = min(lo_x, centres[c, 0])
        hi_x = max(hi_x, centres[c, 0])
        lo_y = min(lo_y, centres[c, 1])
        hi_y = max(hi_y, centres[c, 1])
    w = hi_x - lo_x
    hh = hi_y - lo_y
    h = max(math.sqrt(w * hh / max(k, 1)), max(w, hh) / max(k, 1))
    if not h > 0:
        h = 1.0
    nx = int(w / h) + 1
    ny = int(hh / h) + 1
    cell = np.empty(k, dtype=np.int64)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for c in range(k):
        ix = min(int((centres[c, 0] - lo_x) / h), nx - 1)
        iy = min(int((centres[c, 1] - lo_y) / h), ny - 1)
        cell[c] = iy * nx + ix
        start[cell[c] + 1] += 1
    for q in range(nx * ny):
        start[q + 1] += start[q]
    items = np.empty(k, dtype=np.int64)
    fill = start[:-1].copy()
    for c in range(k):
        items[fill[cell[c]]] = c
        fill[cell[c]] += 1
    slack = 1e-9 * (abs(lo_x) + abs(lo_y) + (nx + ny + 2) * h)
    return start, items, lo_x, lo_y, h, nx, ny, slack


@numba.njit(cache=True)
def _nearest_two(px, py, centres, grid, skip):  # pragma: no cover - compiled
    """Index of the nearest centre and squared distances to the nearest and second nearest.

    The same as comparing every centre in index order (the lowest index wins a tie;
    the second distance is the smallest over the other centres), with centre ``skip``
    left out (-1: none). Searches the cells of :func:`_centre_grid` in square rings
    around the point's cell until no unvisited cell can be nearer than the second
    nearest centre found.
    """
    start, items, lo_x, lo_y, h, nx, ny, slack = grid
    ci = int(min(max((px - lo_x) / h, 0.0), nx - 1.0))
    cj = int(min(max((py - lo_y) / h, 0.0), ny - 1.0))
    best = 0
    d1 = np.inf
    d2 = np.inf
    r = 0
    while True:
        for iy in range(max(cj - r, 0), min(cj + r, ny - 1) + 1):
            edge_row = iy == cj - r or iy == cj + r
            for ix in range(max(ci - r, 0), min(ci + r, nx - 1) + 1):
                if not edge_row and ix != ci - r and ix != ci + r:
                    continue
                q = iy * nx + ix
                for a in range(start[q], start[q + 1]):
                    c = items[a]
                    if c == skip:
                        continue
                    dx = px - centres[c, 0]
                    dy = py - centres[c, 1]
                    d = dx * dx + dy * dy
                    if d < d1 or (d == d1 and c < best):
                        d2 = d1
                        d1 = d
                        best = c
                    elif d < d2:
                        d2 = d
        # distance from the point to the cells outside the square of rings 0..r
        bound = np.inf
        if ci - r > 0:
            bound = min(bound, px - (lo_x + (ci - r) * h))
        if ci + r < nx - 1:
            bound = min(bound, lo_x + (ci + r + 1) * h - px)
        if cj - r > 0:
            bound = min(bound, py - (lo_y + (cj - r) * h))
        if cj + r < ny - 1:
            bound = min(bound, lo_y + (cj + r + 1) * h - py)
        if bound == np.inf:
            break
        bound -= slack
        if bound > 0 and bound * bound > d2:
            break
        r += 1
    return best, d1, d2


@numba.njit(cache=True)
def _lloyd(points, centres, max_iter):  # pragma: no cover - compiled
    """Lloyd iterations from ``centres`` (modified in place); return labels (n,).

    Each point keeps an upper bound on the distance to its centre and a lower bound on
    the distance to every other centre (Hamerly's bounds); the search for the nearest
    centres runs only for points whose bounds no longer prove the assignment, so the
    labels are those of plain Lloyd iterations at a fraction of the cost. Nearest
    centres come from a grid over the centres (:func:`_nearest_two`), rebuilt when they
    move, so an iteration costs O(n + k), not O(n k). When the centres move, a point's
    lower bound drops by the largest move among the centres that could be its second
    nearest (those of the grid cells around it, :func:`_local_max_shift`), not by the
    largest move of all: a few centres that travel far elsewhere in the plane then do
    not send every point back to the search.
    """
    n = points.shape[0]
    k = centres.shape[0]
    labels = np.full(n, -1, dtype=np.int64)
    upper = np.empty(n)
    lower = np.empty(n)
    sums = np.empty((k, 2))
    counts = np.empty(k)
    shift = np.zeros(k)
    half_gap = np.zeros(k)
    grid = _centre_grid(centres)
    no_skip = np.int64(-1)  # typed, not a literal: one specialisation of _nearest_two
    for it in range(max_iter):
        changed = False
        for i in range(n):
            if it > 0:
                lab = labels[i]
                m = max(half_gap[lab], lower[i])
                if upper[i] <= m:
                    continue
                dx = points[i, 0] - centres[lab, 0]
                dy = points[i, 1] - centres[lab, 1]
                upper[i] = math.sqrt(dx * dx + dy * dy)
                if upper[i] <= m:
                    continue
            best, d1, d2 = _nearest_two(points[i, 0], points[i, 1], centres, grid, no_skip)
            upper[i] = math.sqrt(d1)
            lower[i] = math.sqrt(d2)
            if labels[i] != best:
                labels[i] = best
                changed = True
        if not changed:
            break
        sums[:, :] = 0.0
        counts[:] = 0.0
        for i in range(n):
            sums[labels[i], 0] += points[i, 0]
            sums[labels[i], 1] += points[i, 1]
            counts[labels[i]] += 1.0
        max_shift = 0.0
        for c in range(k):
            shift[c] = 0.0
            if counts[c] > 0:  # an empty cluster keeps its centre
                nx = sums[c, 0] / counts[c]
                ny = sums[c, 1] / counts[c]
                shift[c] = math.sqrt((nx - centres[c, 0]) ** 2 + (ny - centres[c, 1]) ** 2)
                centres[c, 0] = nx
                centres[c, 1] = ny
            if shift[c] > max_shift:
                max_shift = shift[c]
        # Every other centre was at least lower[i] away, and one that moved by s is now
        # at least lower[i] - s away. Only those that were within lower[i] + max_shift
        # can now be nearer than lower[i], and the cells around the point (on the grid
        # of the centres' positions before this move) hold all of them.
        near_shift = _local_max_shift(grid, shift)
        start, items, lo_x, lo_y, h, gx, gy, slack = grid
        for i in range(n):
            upper[i] += shift[labels[i]]
            reach = lower[i] + max_shift + slack
            drop = max_shift
            if reach <= 2.0 * h:
                ci = int(min(max((points[i, 0] - lo_x) / h, 0.0), gx - 1.0))
                cj = int(min(max((points[i, 1] - lo_y) / h, 0.0), gy - 1.0))
                drop = near_shift[0 if reach <= h else 1, cj * gx + ci]
            lower[i] -= drop
        grid = _centre_grid(centres)
        for c in range(k):
            g = _nearest_two(centres[c, 0], centres[c, 1], centres, grid, c)[1]
            half_gap[c] = 0.5 * math.sqrt(g)
    return labels


@numba.njit(cache=True)
def _local_max_shift(grid, shift):  # pragma: no cover - compiled
    """(2, cells) largest ``shift`` of the centres within one and within two cells
    (3 x 3 and 5 x 5 blocks) of each cell of ``grid`` (:func:`_centre_grid`).

    A point in cell ``q`` has every centre within ``r * h`` of it (``h`` the cell side,
    ``r`` = 1 or 2) inside the block of radius ``r`` around ``q``, also when the point
    lies beyond the grid (its cell is the nearest edge cell).
    """
    start, items, lo_x, lo_y, h, nx, ny, slack = grid
    cell = np.zeros(nx * ny)
    for q in range(nx * ny):
        for a in range(start[q], start[q + 1]):
            cell[q] = max(cell[q], shift[items[a]])
    out = np.zeros((2, nx * ny))
    rows = np.empty(nx * ny)
    for r in range(1, 3):   # separable maximum filter: along x, then along y
        for iy in range(ny):
            for ix in range(nx):
                m = 0.0
                for jx in range(max(ix - r, 0), min(ix + r, nx - 1) + 1):
                    m = max(m, cell[iy * nx + jx])
                rows[iy * nx + ix] = m
        for iy in range(ny):
            for ix in range(nx):
                m = 0.0
                for jy in range(max(iy - r, 0), min(iy + r, ny - 1) + 1):
                    m = max(m, rows[jy * nx + ix])
                out[r - 1, iy * nx + ix] = m
    return out


@numba.njit(cache=True)
def _kmeanspp_topup(points, centres, n_extra, uniforms):  # pragma: no cover - compiled
    """Append up to ``n_extra`` k-means++ draws (one uniform each) to ``centres``.

    The distance of each point to the given centres comes from a grid over them
    (:func:`_nearest_two`); each draw then updates every point's distance, O(n) per
    draw.
    """
    n = points.shape[0]
    k0 = centres.shape[0]
    out = np.empty((k0 + n_extra, 2))
    for c in range(k0):
        out[c, 0] = centres[c, 0]
        out[c, 1] = centres[c, 1]
    d2 = np.full(n, np.inf)
    if k0 > 0:
        grid = _centre_grid(centres)
        no_skip = np.int64(-1)
        for i in range(n):
            d2[i] = _nearest_two(points[i, 0], points[i, 1], centres, grid, no_skip)[1]
    if k0 == 0:
        d2[:] = 1.0
    m = k0
    for e in range(n_extra):
        total = 0.0
        for i in range(n):
            total += d2[i]
        if not total > 0:
            break
        target = uniforms[e] * total
        acc = 0.0
        pick = n - 1
        for i in range(n):
            acc += d2[i]
            if acc > target:
                pick = i
                break
        out[m, 0] = points[pick, 0]
        out[m, 1] = points[pick, 1]
        m += 1
        for i in range(n):
            d = (points[i, 0] - points[pick, 0]) ** 2 + (points[i, 1] - points[pick, 1]) ** 2
            if d < d2[i]:
                d2[i] = d
    return out[:m]


@numba.njit(cache=True)
def _evaluate(points, aperture, labels, centres, view, area, n_views, thresh, area_factor,
              min_members, max_trim, line_tol):  # pragma: no cover - compiled
    """Accept k-means clusters that pass the per-view, shape, outlier and size tests.

    Returns ``accepted`` (n,) cluster index or -1, and ``size`` (k,) (NaN if rejected).
    """
    n = points.shape[0]
    k = centres.shape[0]
    accepted = np.full(n, -1, dtype=np.int64)
    size = np.full(k, np.nan)
    order = stable_argsort(labels)
    start = np.zeros(k + 1, dtype=np.int64)
    for i in range(n):
        start[labels[i] + 1] += 1
    for c in range(k):
        start[c + 1] += start[c]
    stamp = np.zeros(n_views, dtype=np.int64)
    for c in range(k):
        m = start[c + 1] - start[c]
        if m < min_members:
            continue
        idx = order[start[c]:start[c + 1]]
        d = np.empty(m)
        for a in range(m):
            dx = points[idx[a], 0] - centres[c, 0]
            dy = points[idx[a], 1] - centres[c, 1]
            d[a] = dx * dx + dy * dy
        by_d = idx[stable_argsort(d)]
        # at most one member per view: the one nearest the centre
        kept = np.empty(m, dtype=np.int64)
        nk = 0
        for a in range(m):
            i = by_d[a]
            if stamp[view[i]] != c + 1:
                stamp[view[i]] = c + 1
                kept[nk] = i
                nk += 1
        if nk < min_members:
            continue
        # area within a factor of the cluster median
        if area_factor > 0:
            med = median(area[kept[:nk]])
            nk2 = 0
            for a in range(nk):
                ar = area[kept[a]]
                if ar * area_factor >= med and ar <= med * area_factor:
                    kept[nk2] = kept[a]
                    nk2 += 1
            nk = nk2
            if nk < min_members:
                continue
        # outliers beyond T/2 of the median centre, if they are few
        mx = median(points[kept[:nk], 0])
        my = median(points[kept[:nk], 1])
        r2 = (0.5 * thresh) ** 2
        n_out = 0
        for a in range(nk):
            dx = points[kept[a], 0] - mx
            dy = points[kept[a], 1] - my
            if dx * dx + dy * dy > r2:
                n_out += 1
        if n_out > max_trim * nk:
            continue
        if n_out > 0:
            nk2 = 0
            for a in range(nk):
                dx = points[kept[a], 0] - mx
                dy = points[kept[a], 1] - my
                if dx * dx + dy * dy <= r2:
                    kept[nk2] = kept[a]
                    nk2 += 1
            nk = nk2
            if nk < min_members:
                continue
        # one point: X' = c + m U with a common slope m; release members off the line
        if line_tol > 0:
            mx = 0.0
            my = 0.0
            mux = 0.0
            muy = 0.0
            for a in range(nk):
                mx += points[kept[a], 0]
                my += points[kept[a], 1]
                mux += aperture[kept[a], 0]
                muy += aperture[kept[a], 1]
            mx /= nk
            my /= nk
            mux /= nk
            muy /= nk
            num = 0.0
            den = 0.0
            for a in range(nk):
                dux = aperture[kept[a], 0] - mux
                duy = aperture[kept[a], 1] - muy
                num += (points[kept[a], 0] - mx) * dux + (points[kept[a], 1] - my) * duy
                den += dux * dux + duy * duy
            slope = num / den if den > 0 else 0.0
            tol2 = line_tol * line_tol
            resid = np.empty(nk)
            n_out = 0
            for a in range(nk):
                rx = points[kept[a], 0] - mx - slope * (aperture[kept[a], 0] - mux)
                ry = points[kept[a], 1] - my - slope * (aperture[kept[a], 1] - muy)
                resid[a] = rx * rx + ry * ry
                if resid[a] > tol2:
                    n_out += 1
            if n_out > max_trim * nk:
                continue
            if n_out > 0:
                nk2 = 0
                for a in range(nk):
                    if resid[a] <= tol2:
                        kept[nk2] = kept[a]
                        nk2 += 1
                nk = nk2
                if nk < min_members:
                    continue
        # size: largest distance between two members
        big = 0.0
        for a in range(nk):
            ax = points[kept[a], 0]
            ay = points[kept[a], 1]
            for b in range(a + 1, nk):
                dx = points[kept[b], 0] - ax
                dy = points[kept[b], 1] - ay
                dd = dx * dx + dy * dy
                if dd > big:
                    big = dd
        big = math.sqrt(big)
        if big <= thresh:
            size[c] = big
            for a in range(nk):
                accepted[kept[a]] = c
    return accepted, size


# --------------------------------------------------------------------------------------
def _max_distance(points: np.ndarray) -> float:
    from scipy.spatial.distance import pdist

    return float(pdist(points).max(initial=0.0)) if len(points) > 1 else 0.0


def _max_per_view(view: np.ndarray, n_views: int) -> int:
    return int(np.bincount(view, minlength=n_views).max(initial=0))


def _initial_centres(points, view, view_r2, k, rng) -> np.ndarray:
    """Projected detections of the fullest view (ties: the most central), topped up by
    k-means++ draws from ``rng`` when ``k`` exceeds that view's count."""
    counts = np.bincount(view)
    best = np.flatnonzero(counts == counts.max())
    seed_view = best[np.argmin(view_r2[best])]
    centres = np.ascontiguousarray(points[view == seed_view][:k], dtype=np.float64)
    if len(centres) < k:
        n_extra = k - len(centres)
        centres = _kmeanspp_topup(np.ascontiguousarray(points, dtype=np.float64), centres,
                                  n_extra, rng.random(n_extra))
    return np.ascontiguousarray(centres, dtype=np.float64)


def _density_clusters(pts, aperture, view, area, n_views, thresh, need, area_factor, max_trim,
                      line_tol) -> list[np.ndarray]:
    """Clusters found around the densest points of one plane (members, index arrays).

    Points are visited from the one with the most neighbours within ``T / 2`` down; the
    unused points within ``T / 2`` of a visited point's neighbourhood mean form a
    candidate, which passes the same tests as a k-means cluster (:func:`_evaluate`).
    """
    from scipy.spatial import cKDTree

    n = len(pts)
    if n < need:
        return []
    tree = cKDTree(pts)
    radius = 0.5 * thresh
    n_near = tree.query_ball_point(pts, radius, return_length=True)
    used = np.zeros(n, dtype=bool)
    found = []
    for i in np.argsort(-n_near, kind="stable"):
        if n_near[i] < need:
            break
        if used[i]:
            continue
        idx = np.asarray(tree.query_ball_point(pts[i], radius), dtype=np.int64)
        idx = idx[~used[idx]]
        if len(np.unique(view[idx])) < need:
            continue
        centre = pts[idx].mean(axis=0)
        idx = np.asarray(tree.query_ball_point(centre, radius), dtype=np.int64)
        idx = idx[~used[idx]]
        if len(idx) < need:
            continue
        acc, size = _evaluate(pts[idx], aperture[idx], np.zeros(len(idx), dtype=np.int64),
                              centre[None].copy(), view[idx], area[idx], n_views, thresh,
                              area_factor, need, max_trim, line_tol)
        if np.isfinite(size[0]):
            members = idx[acc == 0]
            used[members] = True
            found.append(members)
    return found


def cluster_detections(detections: pd.DataFrame, geometry: ProjectionGeometry, alphas, *,
                       margin: float = 1.2, noise_floor_samples: float = 1.0,
                       min_members: int = 5, min_fraction: float = 0.2,
                       area_factor: float = 3.0, max_trim: float = 0.1,
                       line_tol_samples: float = 1.0,
                       max_rounds: int = 4, k_growth: float = 0.25, max_iter: int = 50,
                       density_sweep: bool = True, sweep_min_fraction: float = 0.1,
                       sweep_max_trim: float = 0.3,
                       seed: int | np.random.Generator = 0) -> Clustering:
    """Group the detections of the same particle across views (projected-plane k-means).

    Parameters
    ----------
    detections : pandas.DataFrame
        Detections with at least columns ``u, v, s, t`` (view coordinates; centroid,
        view pixels) and, when ``area_factor > 0``, ``area`` (pixels). One frame.
    geometry : ProjectionGeometry
        Conversion of ``(u, v, s, t)`` to aperture and microlens-plane positions.
    alphas : (n_planes,) float ndarray
        Refocus planes to visit (see :func:`plane_alphas`), strictly ascending.
    margin : float
        Safety factor of the size threshold (1.2 in the reference).
    noise_floor_samples : float
        Added to the size threshold, in samples at the microlens plane scaled by the
        plane's ``alpha``: the spread that centroid noise alone gives a cluster.
    min_members : int
        Smallest accepted cluster.
    min_fraction : float
        A cluster also needs at least this fraction of the views that have detections.
    area_factor : float
        Members whose area differs from the cluster median by more than this factor are
        released before the size test (0 disables).
    max_trim : float
        Members farther than ``T / 2`` from the cluster's median position are released
        when they are at most this fraction of the cluster; otherwise the cluster is
        rejected.
    line_tol_samples : float
        Members of one particle lie on ``X' = c + m U`` (common slope ``m`` for both
        axes, ``m = 1 - alpha / alpha_p``). Members farther than this many samples
        (scaled by ``alpha``) from the least-squares line are released, under the same
        ``max_trim`` rule; this splits apart particles whose rays merely cross near the
        plane. 0 disables.
    max_rounds : int
        Passes over all planes. After the first, ``k`` grows by ``k_growth`` times its
        initial value per pass while centroids remain unassigned.
    k_growth : float
        See ``max_rounds``.
    max_iter : int
        Lloyd iterations per plane.
    density_sweep : bool
        After the k-means passes, visit every plane once more and build clusters
        around the densest remaining projected points (the unused points within
        ``T / 2`` of a neighbourhood's mean), accepted under the same tests.
    sweep_min_fraction : float
        Fraction of the views a cluster of the density sweep needs (``min_fraction``
        for the k-means passes): particles partly hidden behind others are seen alone
        in fewer views.
    sweep_max_trim : float
        ``max_trim`` of the density sweep (the larger of the two is used): centroids of
        regions split from merged images scatter more, and the triangulation rejects
        the outliers that remain.
    seed : int or numpy.random.Generator
        Seed of the k-means++ draws used when ``k`` exceeds the fullest view's count.

    Returns
    -------
    Clustering
        ``detections`` (input plus ``cluster``, ``cluster_alpha``) and the per-cluster
        table ``clusters`` (see :class:`Clustering`).

    Notes
    -----
    At every plane all unassigned detections are projected with
    ``X' = U + (X - U) * alpha`` and clustered by k-means with ``k`` the largest number
    of unassigned detections in one view, started from the projected detections of the
    fullest view (a central view when several tie: in view ``U = 0`` a particle projects
    to the middle of its cluster). A k-means cluster is accepted when, after keeping at
    most one member per view (the one nearest the centre), releasing area outliers,
    a few far outliers and a few members off the single-point line fit, it still has
    enough members and its size (largest distance
    between two members) is at most ``T`` (:func:`size_thresholds`, with ``D`` the
    larger of ``geometry.aperture_diameter_mm`` and the aperture span of the views
    present, which reach slightly past the nominal rim, plus the noise floor). Planes are visited
    from the smallest to the largest ``T``; accepted members leave the pool.
    """
    needed = ["u", "v", "s", "t"] + (["area"] if area_factor > 0 else [])
    missing = [c for c in needed if c not in detections.columns]
    if missing:
        raise SettingsError(f"detections lacks column(s) {missing}; it needs {needed}")
    if "frame" in detections.columns and detections["frame"].nunique() > 1:
        raise SettingsError("detections must hold one frame; cluster each frame separately")
    alphas = np.asarray(alphas, dtype=float)
    if min_members < 2:
        raise SettingsError(f"min_members must be at least 2; got {min_members!r}")
    if not 0 <= max_trim < 1:
        raise SettingsError(f"max_trim must be in [0, 1); got {max_trim!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    g = geometry
    n = len(detections)
    u = detections["u"].to_numpy(float)
    v = detections["v"].to_numpy(float)
    s = detections["s"].to_numpy(float)
    t = detections["t"].to_numpy(float)
    span = 2.0 * abs(g.aperture_mm_per_u) * float(np.sqrt(u * u + v * v).max(initial=0.0))
    thresholds = size_thresholds(alphas, max(g.aperture_diameter_mm, span), margin=margin)
    thresholds = thresholds + noise_floor_samples * g.mm_per_sample * alphas
    plane_order = np.argsort(thresholds, kind="stable")
    area = (detections["area"].to_numpy(float) if area_factor > 0 else np.ones(n))
    uv, view_all, _ = unique_rows(np.column_stack([u, v]))
    n_views = len(uv)
    view_r2 = (uv ** 2).sum(axis=1)
    aperture = np.column_stack([u, v]) * g.aperture_mm_per_u
    need = max(int(min_members), int(math.ceil(min_fraction * n_views)))

    cluster = np.full(n, -1, dtype=np.int64)
    cluster_alpha = np.full(n, np.nan)
    rows = []
    remaining = np.arange(n)
    k0 = _max_per_view(view_all, n_views) if n else 0
    k_extra = 0
    idle_rounds = 0
    for rnd in range(max_rounds):
        found = 0
        for p in plane_order:
            if len(remaining) < need:
                break
            a = alphas[p]
            pts = project(u[remaining], v[remaining], s[remaining], t[remaining], a, g)
            vw = view_all[remaining]
            k = min(len(remaining), _max_per_view(vw, n_views) + k_extra)
            centres = _initial_centres(pts, vw, view_r2, k, rng)
            labels = _lloyd(pts, centres, max_iter)
            acc, size = _evaluate(pts, aperture[remaining], labels, centres, vw,
                                  area[remaining], n_views, thresholds[p],
                                  float(area_factor), need, float(max_trim),
                                  line_tol_samples * g.mm_per_sample * a)
            accepted = np.flatnonzero(np.isfinite(size))
            # members of each accepted cluster, in point order, from one sort
            by_cluster = np.argsort(acc, kind="stable")
            first = np.searchsorted(acc[by_cluster], accepted, side="left")
            last = np.searchsorted(acc[by_cluster], accepted, side="right")
            for c, lo, hi in zip(accepted, first, last):
                members = by_cluster[lo:hi]
                cid = len(rows)
                idx = remaining[members]
                cluster[idx] = cid
                cluster_alpha[idx] = a
                cx, cy = pts[members].mean(axis=0)
                rows.append((cid, a, len(members), size[c], thresholds[p], cx, cy,
                             g.axis_st[0] + cx / (a * g.mm_per_sample),
                             g.axis_st[1] + cy / (a * g.mm_per_sample)))
                found += 1
            remaining = remaining[acc < 0]
        if len(remaining) < need:
            break
        idle_rounds = idle_rounds + 1 if found == 0 else 0
        if idle_rounds >= 2:
            break
        k_extra += max(1, int(math.ceil(k_growth * k0)))

    # Last, clusters around the densest remaining points of each plane: k-means with
    # ``k`` set by the fullest view splits the few clusters left among noise between
    # several centres, none of which then has enough members.
    need_sweep = max(int(min_members), int(math.ceil(sweep_min_fraction * n_views)))
    for p in (plane_order if density_sweep else []):
        if len(remaining) < need_sweep:
            break
        a = alphas[p]
        pts = project(u[remaining], v[remaining], s[remaining], t[remaining], a, g)
        taken = np.zeros(len(remaining), dtype=bool)
        for members in _density_clusters(pts, aperture[remaining], view_all[remaining],
                                         area[remaining], n_views, thresholds[p],
                                         need_sweep, float(area_factor),
                                         max(float(max_trim), sweep_max_trim),
                                         line_tol_samples * g.mm_per_sample * a):
            cid = len(rows)
            idx = remaining[members]
            cluster[idx] = cid
            cluster_alpha[idx] = a
            cx, cy = pts[members].mean(axis=0)
            rows.append((cid, a, len(members), _max_distance(pts[members]), thresholds[p],
                         cx, cy, g.axis_st[0] + cx / (a * g.mm_per_sample),
                         g.axis_st[1] + cy / (a * g.mm_per_sample)))
            taken[members] = True
        remaining = remaining[~taken]

    clusters = pd.DataFrame(rows, columns=list(CLUSTER_COLUMNS)).astype(
        {"cluster": np.int64, "n": np.int64, "alpha": float, "size_mm": float,
         "threshold_mm": float, "plane_x_mm": float, "plane_y_mm": float, "s": float,
         "t": float})
    if len(clusters) == 0:
        warnings.warn("no cluster of detections passed the size threshold at any plane",
                      NoParticlesWarning, stacklevel=2)
    out = detections.assign(cluster=cluster, cluster_alpha=cluster_alpha)
    return Clustering(detections=out, clusters=clusters)
