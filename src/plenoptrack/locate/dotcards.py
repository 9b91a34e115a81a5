"""Dot-card detection and indexing for the Direct Light Field Calibration.

A dot card is a transparent plane at a known depth ``z`` carrying dark dots on a square
grid of known spacing, with dot ``(0, 0)`` on the optical axis. Every view of a dot-card
image sees the grid shifted by the parallax of that depth (the same shift for every dot:
the views are images of one plane with one magnification). The dots are segmented in
every view (:mod:`plenoptrack.locate.segment`), indexed in the most central view by
walking the lattice from the dot nearest the optical axis, and the indices are carried to
the other views in order of their distance from the centre with a parallax model
``shift = P @ (du, dv)`` that is refitted as views are added.

World frame (``docs/conventions.md``): ``x`` grows with the view column ``s`` and ``y``
with the row ``t``, so dot ``(i, j)`` sits at ``x = i * spacing``, ``y = j * spacing``.
"""

from __future__ import annotations

import warnings
from collections import deque

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from ..errors import CalibrationError, NoParticlesWarning
from .segment import segment_array

__all__ = ["DOTCARD_COLUMNS", "index_lattice", "index_dotcard", "dotcard_points"]

DOTCARD_COLUMNS = ("u", "v", "s", "t", "x", "y", "z", "i", "j")
"""Columns of a dot-card table: view, dot centroid (view pixels), dot position (mm) and
grid index."""


def _lattice_basis(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lattice vectors ``a`` (mostly +s) and ``b`` (mostly +t) from nearest neighbours."""
    tree = cKDTree(points)
    d, nb = tree.query(points, k=min(5, len(points)))
    spacing = np.median(d[:, 1])
    vec = (points[nb[:, 1:]] - points[:, None, :]).reshape(-1, 2)
    length = np.hypot(vec[:, 0], vec[:, 1])
    vec = vec[(length > 0.7 * spacing) & (length < 1.3 * spacing)]
    along_s = np.abs(vec[:, 0]) >= np.abs(vec[:, 1])
    a = vec[along_s] * np.sign(vec[along_s, :1])
    b = vec[~along_s] * np.sign(vec[~along_s, 1:])
    if len(a) < 2 or len(b) < 2:
        raise CalibrationError("cannot find a square dot lattice in the central view; check "
                               "the segmentation settings (window, contrast, area_range)")
    return np.median(a, axis=0), np.median(b, axis=0)


def index_lattice(points, origin_st, *, tol: float = 0.3) -> np.ndarray:
    """Grid indices of dots on a roughly square lattice in one view.

    Parameters
    ----------
    points : (n, 2) float ndarray
        Dot centroids as ``(s, t)``, view pixels.
    origin_st : (float, float)
        Predicted ``(s, t)`` of dot ``(0, 0)``.
    tol : float
        Match tolerance as a fraction of the lattice spacing.

    Returns
    -------
    (n, 2) int64 ndarray
        ``(i, j)`` per dot, ``i`` along +s and ``j`` along +t; ``(-2**31, -2**31)`` for
        dots not reached from the origin dot.

    Raises
    ------
    CalibrationError
        No lattice found, or no dot within half a spacing of ``origin_st``.

    Notes
    -----
    The lattice vectors are the medians of the nearest-neighbour vectors closer to the
    s axis (``a``) and to the t axis (``b``), so the grid may be rotated by up to about
    40 degrees. Indices spread breadth-first from the dot nearest ``origin_st``: each
    indexed dot predicts its four neighbours one lattice vector away (so slow lens
    distortion does not accumulate) and takes the nearest dot within ``tol`` spacings.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points must be (n, 2) (s, t); got shape {pts.shape}")
    if len(pts) < 4:
        raise CalibrationError(f"need at least 4 dots to index a lattice; got {len(pts)}")
    a, b = _lattice_basis(pts)
    spacing = min(np.hypot(*a), np.hypot(*b))
    tree = cKDTree(pts)
    d0, start = tree.query(np.asarray(origin_st, dtype=float))
    if d0 > 0.5 * spacing:
        raise CalibrationError(
            f"no dot within half a lattice spacing ({0.5 * spacing:.1f} px) of the predicted "
            f"optical-axis position (s, t) = ({origin_st[0]:.1f}, {origin_st[1]:.1f}); the "
            f"nearest is {d0:.1f} px away. Check the axis position or pass origin_st")
    missing = np.iinfo(np.int32).min
    idx = np.full((len(pts), 2), missing, dtype=np.int64)
    idx[start] = (0, 0)
    queue = deque([start])
    steps = ((1, 0, a), (-1, 0, -a), (0, 1, b), (0, -1, -b))
    while queue:
        p = queue.popleft()
        for di, dj, vec in steps:
            d, q = tree.query(pts[p] + vec)
            if d <= tol * spacing and idx[q, 0] == missing:
                idx[q] = (idx[p, 0] + di, idx[p, 1] + dj)
                queue.append(q)
    return idx


def _unique_rows(idx: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``ok`` with every index pair that occurs more than once switched off."""
    ok = ok.copy()
    if ok.any():
        pairs, inv, counts = np.unique(idx[ok], axis=0, return_inverse=True,
                                       return_counts=True)
        dup = counts[inv.ravel()] > 1
        ok[np.flatnonzero(ok)[dup]] = False
    return ok


def index_dotcard(detections: pd.DataFrame, *, origin_st, parallax_per_u=(0.0, 0.0),
                  tol: float = 0.3) -> pd.DataFrame:
    """Assign grid indices to dot detections in every view of one dot-card image.

    Parameters
    ----------
    detections : pandas.DataFrame
        Columns ``u, v, s, t`` (e.g. from :func:`~plenoptrack.locate.segment.segment_views`).
    origin_st : (float, float)
        ``(s, t)`` of the optical axis; dot ``(0, 0)`` is sought there in the most central
        view.
    parallax_per_u : float or (float, float)
        Predicted shift of the card's image per unit ``u`` along ``s`` and per unit ``v``
        along ``t``, view pixels (see
        :meth:`~plenoptrack.locate.cluster.ProjectionGeometry.parallax_per_u`). The
        prediction must be good to better than ``tol`` spacings between neighbouring
        views; it is refitted from the views already indexed.
    tol : float
        Match tolerance, fraction of the lattice spacing.

    Returns
    -------
    pandas.DataFrame
        The indexed detections: the input columns plus ``i`` and ``j`` (int64); dots that
        could not be indexed unambiguously are dropped.
    """
    missing_cols = [c for c in ("u", "v", "s", "t") if c not in detections.columns]
    if missing_cols:
        raise ValueError(f"detections lacks column(s) {missing_cols}")
    if len(detections) == 0:
        raise CalibrationError("no dots were detected in any view of the dot card")
    par = np.broadcast_to(np.asarray(parallax_per_u, dtype=float), (2,))
    u = detections["u"].to_numpy(float)
    v = detections["v"].to_numpy(float)
    st = detections[["s", "t"]].to_numpy(float)
    views, view_of = np.unique(np.column_stack([u, v]), axis=0, return_inverse=True)
    view_of = view_of.ravel()
    order = np.argsort((views ** 2).sum(axis=1), kind="stable")
    centre = order[0]
    uc, vc = views[centre]
    in_c = np.flatnonzero(view_of == centre)
    origin = np.asarray(origin_st, float) + par * (uc, vc)
    idx_c = index_lattice(st[in_c], origin, tol=tol)
    ok_c = idx_c[:, 0] != np.iinfo(np.int32).min
    ref_idx, ref_pos = idx_c[ok_c], st[in_c][ok_c]
    # affine lattice of the central view, for dots that only other views see
    design = np.column_stack([np.ones(len(ref_idx)), ref_idx])
    coef, *_ = np.linalg.lstsq(design, ref_pos, rcond=None)
    o_c, basis = coef[0], coef[1:].T            # pos = o_c + basis @ (i, j)
    spacing = min(np.hypot(*basis[:, 0]), np.hypot(*basis[:, 1]))
    basis_inv = np.linalg.inv(basis)
    ref_tree = cKDTree(ref_pos)

    out_idx = np.full((len(st), 2), np.iinfo(np.int32).min, dtype=np.int64)
    out_ok = np.zeros(len(st), dtype=bool)
    out_idx[in_c[ok_c]] = ref_idx
    out_ok[in_c[ok_c]] = True
    P = np.diag(par)
    dudv, shifts = [], []
    for w in order[1:]:
        rows = np.flatnonzero(view_of == w)
        duv = views[w] - (uc, vc)
        shift = P @ duv
        pos = st[rows]
        for _ in range(2):  # predict, then re-centre on the median residual
            d, k = ref_tree.query(pos - shift)
            near = d <= tol * spacing
            if near.sum() < 3:
                break
            shift = shift + np.median(pos[near] - shift - ref_pos[k[near]], axis=0)
        d, k = ref_tree.query(pos - shift)
        idx = ref_idx[k]
        ok = d <= tol * spacing
        frac = (pos - shift - o_c) @ basis_inv.T
        rnd = np.rint(frac).astype(np.int64)
        resid = pos - shift - o_c - rnd @ basis.T
        fallback = ~ok & (np.hypot(resid[:, 0], resid[:, 1]) <= tol * spacing)
        idx[fallback] = rnd[fallback]
        ok |= fallback
        ok = _unique_rows(idx, ok)
        out_idx[rows], out_ok[rows] = idx, ok
        if ok.sum() >= 3:
            dudv.append(duv)
            shifts.append(shift)
            A = np.array(dudv)
            if np.linalg.matrix_rank(A) == 2:
                P = np.linalg.lstsq(A, np.array(shifts), rcond=None)[0].T
    res = detections.iloc[np.flatnonzero(out_ok)].assign(
        i=out_idx[out_ok, 0], j=out_idx[out_ok, 1])
    return res.reset_index(drop=True)


def dotcard_points(lf, *, spacing_mm: float, z_mm: float, camera=None,
                   parallax_per_u=None, origin_st=None, tol: float = 0.3,
                   window: int = 31, contrast: float = 0.15,
                   area_range=(2, np.inf), max_eccentricity: float = 0.8) -> pd.DataFrame:
    """Calibration points ``(u, v, s, t) <-> (x, y, z)`` from one dot-card light field.

    Parameters
    ----------
    lf : LightField
        Decoded dot-card image (``data``, ``u``, ``v``, ``view_mask``, ``spatial_mask``,
        ``flat_fielded``, ``axis_st``, ``sample_spacing_px``).
    spacing_mm : float
        Dot spacing on the card, mm.
    z_mm : float
        Card depth, mm (z = 0 at the nominal focal plane).
    camera : CameraSpec, optional
        Nominal camera; gives the predicted parallax of the card when ``parallax_per_u``
        is not given.
    parallax_per_u : float or (float, float), optional
        Predicted card shift per unit ``u`` (``s``) and ``v`` (``t``), view pixels.
        Default from ``camera``, else 0 (only safe for cards near the focal plane).
    origin_st : (float, float), optional
        ``(s, t)`` of the optical axis; default ``lf.axis_st``.
    tol : float
        Match tolerance, fraction of the lattice spacing.
    window, contrast, area_range, max_eccentricity
        Segmentation settings (:func:`~plenoptrack.locate.segment.segment_array`); dots
        touching a view edge or a masked sample are always rejected.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`DOTCARD_COLUMNS`: ``u, v`` view; ``s, t`` dot centroid, view
        pixels; ``x = i * spacing_mm``, ``y = j * spacing_mm``, ``z = z_mm`` (mm, world
        frame); ``i, j`` grid index (int). Sorted by view (v, u) and index (j, i).
    """
    if not spacing_mm > 0:
        raise ValueError(f"spacing_mm must be positive; got {spacing_mm!r}")
    if parallax_per_u is None:
        if camera is not None:
            from .cluster import ProjectionGeometry

            geom = ProjectionGeometry.from_lightfield(lf, camera)
            parallax_per_u = float(geom.parallax_per_u(camera.alpha_for_depth(z_mm)))
        else:
            parallax_per_u = 0.0
    with warnings.catch_warnings():  # an empty result is an error here, not a warning
        warnings.simplefilter("ignore", NoParticlesWarning)
        det = segment_array(lf.data, lf.u, lf.v, view_mask=lf.view_mask,
                            spatial_mask=lf.spatial_mask, window=window, contrast=contrast,
                            area_range=area_range, max_eccentricity=max_eccentricity,
                            exclude_edge=True,
                            zero_invalid=bool(getattr(lf, "flat_fielded", False)))
    if len(det) == 0:
        raise CalibrationError(f"no dots found in the dot card at z = {z_mm} mm; check "
                               "the image and the segmentation settings")
    origin = lf.axis_st if origin_st is None else origin_st
    idx = index_dotcard(det, origin_st=origin, parallax_per_u=parallax_per_u, tol=tol)
    table = pd.DataFrame({
        "u": idx["u"].to_numpy(float), "v": idx["v"].to_numpy(float),
        "s": idx["s"].to_numpy(float), "t": idx["t"].to_numpy(float),
        "x": idx["i"].to_numpy(float) * spacing_mm, "y": idx["j"].to_numpy(float) * spacing_mm,
        "z": np.full(len(idx), float(z_mm)), "i": idx["i"].to_numpy(np.int64),
        "j": idx["j"].to_numpy(np.int64)})
    return table.sort_values(["v", "u", "j", "i"], kind="stable").reset_index(drop=True)
