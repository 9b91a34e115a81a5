"""Dot-card detection and indexing for the Direct Light Field Calibration.

A dot card is a transparent plane at a known depth ``z`` carrying dark dots on a square
grid of known spacing, with dot ``(0, 0)`` on the optical axis. Every view of a dot-card
image sees the grid shifted by the parallax of that depth (the same shift for every dot:
the views are images of one plane with one magnification). The dots are segmented in
every view (:mod:`plenoptrack.locate.segment`), indexed in the most central view by
walking the lattice and putting ``(0, 0)`` at the lattice node nearest the predicted
optical axis (detected there or not), and the indices are carried to the other views in
order of their distance from the centre with a parallax model ``shift = P @ (du, dv)``
that is refitted as views are added.

Across cards, :func:`card_lattice` measures each card's parallax and its lattice at
``u = v = 0``, and :func:`consistent_origins` makes the cards agree on dot ``(0, 0)``:
on the optical axis its image at ``u = v = 0`` is the same for every depth.

World frame (``docs/conventions.md``): ``x`` grows with the view column ``s`` and ``y``
with the row ``t``, so dot ``(i, j)`` sits at ``x = i * spacing``, ``y = j * spacing``.
"""

from __future__ import annotations

import warnings
from collections import deque
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from ..errors import CalibrationError, NoParticlesWarning, SettingsError
from .segment import segment_array

__all__ = ["DOTCARD_COLUMNS", "CardLattice", "OriginConsensus", "card_lattice",
           "consistent_origins", "dotcard_points", "fit_lattice", "index_dotcard", "index_lattice"]

DOTCARD_COLUMNS = ("u", "v", "s", "t", "x", "y", "z", "i", "j", "darkness", "dark_area")
"""Columns of a dot-card table: view, dot centroid (view pixels), dot position (mm) and
grid index."""

_MISSING = np.iinfo(np.int32).min
"""Index pair ``(_MISSING, _MISSING)`` marks a dot that could not be indexed."""


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


def _walk_lattice(pts: np.ndarray, tree: cKDTree, start: int, steps, tol_px: float,
                  idx: np.ndarray) -> list[int]:
    """Breadth-first walk from dot ``start`` (given index (0, 0)) over lattice neighbours.

    Fills ``idx`` in place for the dots reached and returns them in visiting order.
    """
    idx[start] = (0, 0)
    reached, queue = [start], deque([start])
    while queue:
        p = queue.popleft()
        for di, dj, vec in steps:
            d, q = tree.query(pts[p] + vec)
            if d <= tol_px and idx[q, 0] == _MISSING:
                idx[q] = (idx[p, 0] + di, idx[p, 1] + dj)
                queue.append(q)
                reached.append(q)
    return reached


def fit_lattice(points, indices, *, near=(0.0, 0.0), n_near: int = 25):
    """Local affine lattice ``(s, t) = origin + basis @ (i, j)`` around one node.

    Parameters
    ----------
    points : (n, 2) float ndarray
        Dot centroids ``(s, t)``, view pixels.
    indices : (n, 2) int ndarray
        Grid index ``(i, j)`` of each dot; rows with the missing marker (``-2**31``) are
        ignored.
    near : (float, float)
        Index ``(i, j)`` around which to fit: the ``n_near`` indexed dots nearest to it in
        index space are used, so that lens distortion far from it does not bend the fit.
    n_near : int
        Number of dots to fit (at least 3 needed).

    Returns
    -------
    origin : (2,) float ndarray
        ``(s, t)`` of lattice node ``(0, 0)``, view pixels, whether or not a dot was
        detected there.
    basis : (2, 2) float ndarray
        Columns are the lattice vectors along ``i`` and along ``j``, view pixels.

    Raises
    ------
    CalibrationError
        Fewer than 3 indexed dots, or all of them on one line.
    """
    pts = np.asarray(points, dtype=float)
    idx = np.asarray(indices)
    ok = idx[:, 0] != _MISSING
    pts, idx = pts[ok], idx[ok].astype(float)
    if len(pts) >= 3:
        dist = np.hypot(idx[:, 0] - near[0], idx[:, 1] - near[1])
        sel = np.argsort(dist, kind="stable")[:max(n_near, 3)]
        design = np.column_stack([np.ones(len(sel)), idx[sel]])
        if np.linalg.matrix_rank(design) == 3:
            coef, *_ = np.linalg.lstsq(design, pts[sel], rcond=None)
            return coef[0], coef[1:].T
    raise CalibrationError(f"cannot fit a dot lattice: only {len(pts)} indexed dot(s), or "
                           "all in one row; check the dot-card image and the segmentation "
                           "settings")


def index_lattice(points, origin_st, *, tol: float = 0.3) -> np.ndarray:
    """Grid indices of dots on a roughly square lattice in one view.

    Parameters
    ----------
    points : (n, 2) float ndarray
        Dot centroids as ``(s, t)``, view pixels.
    origin_st : (float, float)
        Predicted ``(s, t)`` of dot ``(0, 0)``, view pixels.
    tol : float
        Match tolerance as a fraction of the lattice spacing.

    Returns
    -------
    (n, 2) int64 ndarray
        ``(i, j)`` per dot, ``i`` along +s and ``j`` along +t, with ``(0, 0)`` the lattice
        node nearest ``origin_st``; ``(-2**31, -2**31)`` for dots not connected to the
        main lattice.

    Raises
    ------
    CalibrationError
        Fewer than 4 dots, or no square lattice found among them.

    Notes
    -----
    The lattice vectors are the medians of the nearest-neighbour vectors closer to the
    s axis (``a``) and to the t axis (``b``), so the grid may be rotated by up to about
    40 degrees. Indices spread breadth-first over the lattice: each indexed dot predicts
    its four neighbours one lattice vector away (so slow lens distortion does not
    accumulate) and takes the nearest dot within ``tol`` spacings. The walk starts at the
    dot nearest ``origin_st`` and is repeated from dots it did not reach; the largest
    connected set of dots is kept (the one found first on a tie). An affine lattice
    fitted to the indexed dots nearest ``origin_st`` (:func:`fit_lattice`) then gives
    the fractional index of ``origin_st``; rounding it picks node ``(0, 0)``, so dot
    ``(0, 0)`` need not have been detected, and ``origin_st`` need only be right to
    within half a spacing (a card-to-card check of the choice is
    :func:`consistent_origins`).
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise SettingsError(f"points must be (n, 2) (s, t); got shape {pts.shape}")
    if len(pts) < 4:
        raise CalibrationError(f"need at least 4 dots to index a lattice; got {len(pts)}")
    origin = np.asarray(origin_st, dtype=float)
    a, b = _lattice_basis(pts)
    spacing = min(np.hypot(*a), np.hypot(*b))
    tree = cKDTree(pts)
    steps = ((1, 0, a), (-1, 0, -a), (0, 1, b), (0, -1, -b))
    idx = np.full((len(pts), 2), _MISSING, dtype=np.int64)
    best: list[int] = []
    n_left = len(pts)
    for start in np.argsort(np.hypot(*(pts - origin).T), kind="stable"):
        if len(best) >= n_left:
            break  # no set still to be walked can be larger
        if idx[start, 0] != _MISSING:
            continue
        part = _walk_lattice(pts, tree, start, steps, tol * spacing, idx)
        n_left -= len(part)
        if len(part) > len(best):
            best = part
    out = np.full_like(idx, _MISSING)
    out[best] = idx[best]
    sel = np.asarray(best)[np.argsort(np.hypot(*(pts[best] - origin).T), kind="stable")[:25]]
    o, basis = fit_lattice(pts[sel], out[sel], n_near=len(sel))
    frac = np.linalg.solve(basis, origin - o)
    out[best] -= np.rint(frac).astype(np.int64)
    return out


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
        ``(s, t)`` of the optical axis at ``u = v = 0``; dot ``(0, 0)`` is the lattice node
        nearest it (plus the predicted parallax) in the most central view
        (:func:`index_lattice`).
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

    Raises
    ------
    CalibrationError
        No dots, no lattice in the central view, or a predicted parallax of more than
        half the dot spacing per view (neighbouring views would alias).
    """
    missing_cols = [c for c in ("u", "v", "s", "t") if c not in detections.columns]
    if missing_cols:
        raise SettingsError(f"detections lacks column(s) {missing_cols}")
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
    ok_c = idx_c[:, 0] != _MISSING
    ref_idx, ref_pos = idx_c[ok_c], st[in_c][ok_c]
    # affine lattice of the central view, for dots that only other views see
    design = np.column_stack([np.ones(len(ref_idx)), ref_idx])
    coef, *_ = np.linalg.lstsq(design, ref_pos, rcond=None)
    o_c, basis = coef[0], coef[1:].T            # pos = o_c + basis @ (i, j)
    spacing = min(np.hypot(*basis[:, 0]), np.hypot(*basis[:, 1]))
    if np.abs(par).max() > 0.5 * spacing:
        raise CalibrationError(
            f"the card's predicted parallax, ({par[0]:.2f}, {par[1]:.2f}) view px per unit "
            f"(u, v), is more than half the dot spacing in the central view "
            f"({0.5 * spacing:.2f} px), so neighbouring views cannot be matched "
            "unambiguously; check the card depth z_mm (millimetres from the focal plane) "
            "and the nominal camera, or use a card with a coarser dot grid")
    basis_inv = np.linalg.inv(basis)
    ref_tree = cKDTree(ref_pos)

    out_idx = np.full((len(st), 2), _MISSING, dtype=np.int64)
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
        frame); ``i, j`` grid index (int); ``darkness, dark_area`` the dot image's peak
        and summed relative darkness (:func:`~plenoptrack.locate.segment.segment_array`),
        from which the calibration measures the views' edge blur
        (:func:`~plenoptrack.locate.opacity.edge_blur_by_depth`). Sorted by view (v, u)
        and index (j, i).
    """
    if not spacing_mm > 0:
        raise SettingsError(f"spacing_mm must be positive; got {spacing_mm!r}")
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
        "j": idx["j"].to_numpy(np.int64), "darkness": idx["darkness"].to_numpy(float),
        "dark_area": idx["dark_area"].to_numpy(float)})
    return table.sort_values(["v", "u", "j", "i"], kind="stable").reset_index(drop=True)


# --- whole cards ------------------------------------------------------------------------

@dataclass(frozen=True)
class CardLattice:
    """The dot lattice of one card, measured over all views (:func:`card_lattice`).

    Attributes
    ----------
    origin_st : (2,) float ndarray
        ``(s, t)`` of dot ``(0, 0)`` extrapolated to view ``u = v = 0``, view pixels
        (from the dots around it, whether or not it was detected itself).
    basis : (2, 2) float ndarray
        Columns: the lattice vectors along ``i`` and along ``j`` at ``u = v = 0``,
        view pixels per index step.
    parallax : (2, 2) float ndarray
        ``d(s, t) / d(u, v)``: shift of the card's image per unit view coordinate, view
        pixels; ``parallax[0, 0]`` is ``ds/du`` and ``parallax[1, 1]`` is ``dt/dv``.
    n_dots : int
        Dots (distinct indices) measured.
    rms_px : float
        RMS residual length of the linear parallax model over the kept measurements,
        view pixels.
    """

    origin_st: np.ndarray
    basis: np.ndarray
    parallax: np.ndarray
    n_dots: int
    rms_px: float

    @property
    def spacing_px(self) -> float:
        """Shorter of the two lattice vectors, view pixels."""
        return float(min(np.hypot(*self.basis[:, 0]), np.hypot(*self.basis[:, 1])))

    @property
    def parallax_per_u(self) -> float:
        """Mean of ``ds/du`` and ``dt/dv``, view pixels per unit ``u`` (compare
        :meth:`~plenoptrack.locate.cluster.ProjectionGeometry.parallax_per_u`)."""
        return float(0.5 * (self.parallax[0, 0] + self.parallax[1, 1]))


def card_lattice(table: pd.DataFrame, *, reject_px: float = 0.3) -> CardLattice:
    """Measure one card's parallax and its dot lattice at ``u = v = 0``.

    Parameters
    ----------
    table : pandas.DataFrame
        Indexed dots of one card in all views: columns ``u, v, s, t, i, j`` (e.g. from
        :func:`dotcard_points`).
    reject_px : float
        Measurements further than ``max(reject_px, median + 5 * 1.4826 * MAD)`` view
        pixels from the linear model are dropped once and the model refitted.

    Returns
    -------
    CardLattice

    Notes
    -----
    A card is a plane: every dot ``(i, j)`` is seen at
    ``(s, t) = c_ij + parallax @ (u, v)`` (first order), with one ``2 x 2`` parallax for
    the whole card and one intercept ``c_ij`` per dot. The parallax is the pooled
    least-squares slope (each dot's measurements minus their own means); the intercepts
    are the dots' positions in a view at ``u = v = 0``, and an affine lattice fitted to
    the 25 of them nearest ``(0, 0)`` (:func:`fit_lattice`) gives ``origin_st`` and
    ``basis``.
    """
    missing = [c for c in ("u", "v", "s", "t", "i", "j") if c not in table.columns]
    if missing:
        raise SettingsError(f"table lacks column(s) {missing}")
    ij = table[["i", "j"]].to_numpy(np.int64)
    uv = table[["u", "v"]].to_numpy(float)
    st = table[["s", "t"]].to_numpy(float)
    keys, group = np.unique(ij, axis=0, return_inverse=True)
    group = group.ravel()
    keep = np.ones(len(table), dtype=bool)
    for attempt in range(2):
        count = np.bincount(group[keep], minlength=len(keys)).astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_uv = np.column_stack([np.bincount(group[keep], uv[keep, c], len(keys))
                                       for c in range(2)]) / count[:, None]
            mean_st = np.column_stack([np.bincount(group[keep], st[keep, c], len(keys))
                                       for c in range(2)]) / count[:, None]
        duv, dst = uv - mean_uv[group], st - mean_st[group]
        if np.linalg.matrix_rank(duv[keep]) < 2:
            raise CalibrationError("the dot card is seen in too few views to measure its "
                                   "parallax; check the light field's view mask")
        coef, *_ = np.linalg.lstsq(duv[keep], dst[keep], rcond=None)  # rows du, dv
        r = np.hypot(*(dst - duv @ coef).T)
        if attempt == 0:
            med = np.median(r)
            keep = r <= max(reject_px, med + 5.0 * 1.4826 * np.median(np.abs(r - med)))
    intercept = mean_st - mean_uv @ coef
    seen = count >= 3
    origin, basis = fit_lattice(intercept[seen], keys[seen], near=(0, 0), n_near=25)
    return CardLattice(origin_st=origin, basis=basis, parallax=coef.T,
                       n_dots=int(seen.sum()), rms_px=float(np.sqrt(np.mean(r[keep] ** 2))))


@dataclass(frozen=True)
class OriginConsensus:
    """Where the cards agree dot ``(0, 0)`` lies (:func:`consistent_origins`).

    Attributes
    ----------
    axis_st : (2,) float ndarray
        Consensus ``(s, t)`` of dot ``(0, 0)`` at ``u = v = 0``, view pixels.
    shifts : (n_cards, 2) int64 ndarray
        Index change per card: subtract it from the card's ``(i, j)`` so that its dot
        ``(0, 0)`` lies at ``axis_st``; ``(0, 0)`` for cards that already agreed.
    miss : (n_cards,) float ndarray
        Distance from ``axis_st`` to the nearest node of each card's lattice, in units of
        that card's dot spacing (0 for a perfect card; above the tolerance the card has
        no dot on the axis and cannot be re-indexed).
    n_agree : int
        Cards whose dot ``(0, 0)`` was at ``axis_st`` before re-indexing.
    """

    axis_st: np.ndarray
    shifts: np.ndarray
    miss: np.ndarray
    n_agree: int


def consistent_origins(lattices, *, origin_st, tol: float = 0.25) -> OriginConsensus:
    """Make every card's dot ``(0, 0)`` the same dot: the one on the optical axis.

    Parameters
    ----------
    lattices : sequence of CardLattice
        One per card (:func:`card_lattice`).
    origin_st : (float, float)
        Predicted ``(s, t)`` of the optical axis at ``u = v = 0``, view pixels; breaks
        ties between equally large groups of agreeing cards.
    tol : float
        Two cards agree when their dots ``(0, 0)`` are within ``tol`` dot spacings.

    Returns
    -------
    OriginConsensus

    Notes
    -----
    Dot ``(0, 0)`` lies on the optical axis, and in a view at ``u = v = 0`` the image of a
    point on the axis is the same for every depth; the other dots move with the
    magnification of their depth. Each card's index origin was chosen on its own (the
    lattice node nearest the predicted axis), so when the prediction is off by nearly
    half a spacing, or the dot there was missed, cards can disagree by a whole step. The
    largest group of cards whose ``(0, 0)`` coincide (on a tie, the group nearest
    ``origin_st``) defines ``axis_st``, their median; every card is re-indexed to its
    lattice node nearest ``axis_st``. ``miss`` above ``tol`` means a card's lattice has
    no node there: that card does not fit the others.
    """
    lattices = list(lattices)
    if not lattices:
        raise SettingsError("lattices is empty; measure at least one card")
    pos = np.array([lat.origin_st for lat in lattices], dtype=float)
    spacing = np.array([lat.spacing_px for lat in lattices])
    dist = np.hypot(*(pos[:, None, :] - pos[None, :, :]).transpose(2, 0, 1))
    agree = dist <= tol * spacing[None, :]          # [k, m]: card m agrees with card k
    support = agree.sum(axis=1)
    to_origin = np.hypot(*(pos - np.asarray(origin_st, float)).T)
    best = np.lexsort((to_origin, -support))[0]
    axis = np.median(pos[agree[best]], axis=0)
    shifts = np.zeros((len(lattices), 2), dtype=np.int64)
    miss = np.zeros(len(lattices))
    for k, lat in enumerate(lattices):
        frac = np.linalg.solve(lat.basis, axis - lat.origin_st)
        node = np.rint(frac)
        shifts[k] = node.astype(np.int64)
        miss[k] = np.hypot(*(lat.basis @ (frac - node))) / lat.spacing_px
    return OriginConsensus(axis_st=axis, shifts=shifts, miss=miss,
                           n_agree=int(support[best]))
