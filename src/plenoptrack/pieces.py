"""Pieces of one body that were tracked apart: touching tracks that move together, merged.

The locator can report one irregular body as two or more particles: an elongated
fragment tilted in depth is cut into its two ends, each solved at its own depth, and a
glint leaves a dark rim that is solved as a particle beside the rest of the body. In a
single frame nothing tells such pieces from separate bodies that touch
(:mod:`plenoptrack.locate.bodies` merges only the pairs that lie at one depth). Over
frames the difference shows. The pieces of one rigid body keep their offset, so their
velocities agree; separate bodies move apart however close they are. Two fragments of one
explosion differ in velocity by tens of per cent, and two tracers in a flow by the
velocity gradient across the distance between them.

Two tracks are taken as pieces of one body (:func:`piece_pairs`) when, over the frames
in which both have a point (at least :data:`MIN_COMMON_FRAMES`),

- **they touch**: in at least half of those frames the distance ``d`` between their
  centres exceeds the sum of their half major axes (half diameters where a major axis is
  missing) by at most ``touch_sigma`` standard uncertainties of ``d``, from both points'
  sigmas along the line between them;
- **they move together**: the difference of their velocities is consistent with zero.
  Each velocity comes from a weighted straight-line fit over the whole track (weights
  ``1 / sigma^2``), and the chi-square of the difference (3 degrees of freedom, with the
  fits' standard errors) must have a p-value of at least ``velocity_p``.

Both tests need the points' sigmas (``sigma_x, sigma_y, sigma_z``): a table without them
has no pairs.

The tracks of each group of pieces (pairs chained) become one track (:func:`merge_pieces`).
In every frame in which any piece has a point, the body's centre ``c(f)`` comes from the
least-squares fit of ``x_p(f) = c(f) + o_p`` to all the pieces' points, per axis, with
weights ``1 / sigma^2``. Here ``o_p`` is piece ``p``'s constant offset, and the
area-weighted offsets sum to zero, so that ``c`` is the centroid of the pieces'
silhouettes. The sigma of ``c(f)`` is the fit's standard error. A frame in which a piece
was missed therefore keeps the body's centre, not the centre of the pieces that happened
to be found. The merged row's ``diameter`` is the equivalent diameter of the union of
the pieces' discs seen along the optical axis (:func:`union_diameter`: each disc at
``c(f) + o_p`` laterally, a missing piece with its median diameter), the body's
silhouette as far as its pieces show it; the column ``pieces`` counts the pieces found in
that frame (1 on every other row).

Nothing here reads ground truth.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ._columns import DIAMETER_COLUMN, ID_COLUMN, POS_COLUMNS, SIGMA_COLUMNS, T_COLUMN
from .errors import SettingsError

__all__ = ["MIN_COMMON_FRAMES", "PIECES_COLUMN", "track_velocities", "piece_pairs",
           "merge_pieces", "union_diameter"]

MIN_COMMON_FRAMES = 3
"""Frames in which two tracks must both have a point before they can be taken as pieces
of one body: two frames give no check of a common velocity."""
PIECES_COLUMN = "pieces"
"""Pieces of one body merged into a row (:func:`merge_pieces`); 1 for a particle found
whole."""

_WEIGHTED_MEAN_COLUMNS = ("confidence", "residual_px", "travel_px")
"""Per-point quality columns a merged row takes as the pieces' area-weighted mean."""


def _weights(sigma: np.ndarray) -> np.ndarray:
    """``1 / sigma^2``; 0 where sigma is missing, non-finite or not positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1.0 / sigma ** 2
    return np.where(np.isfinite(w) & (sigma > 0), w, 0.0)


def track_velocities(linked: pd.DataFrame) -> pd.DataFrame:
    """Velocity of every track from a weighted straight-line fit over all its points.

    Parameters
    ----------
    linked : DataFrame
        Columns ``frame, particle, x, y, z, sigma_x, sigma_y, sigma_z`` (mm). Points
        whose sigma on an axis is missing or not positive are left out on that axis.

    Returns
    -------
    DataFrame
        Index ``particle``; ``velocity_x, velocity_y, velocity_z`` (mm per frame) and their
        standard errors ``sigma_vx, sigma_vy, sigma_vz`` (from the sigmas: ``sqrt(1 /
        sum w (f - mean f)^2)``); NaN on an axis with fewer than two weighted frames.
    """
    f = linked[T_COLUMN].to_numpy(float)
    ids = linked[ID_COLUMN].to_numpy()
    out = {}
    for axis, sigma_column in zip(POS_COLUMNS, SIGMA_COLUMNS, strict=True):
        w = _weights(linked[sigma_column].to_numpy(float))
        y = np.where(w > 0, linked[axis].to_numpy(float), 0.0)
        sums = pd.DataFrame({"s": w, "sf": w * f, "sff": w * f * f, "sy": w * y,
                             "sfy": w * f * y, "n": (w > 0).astype(float)}).groupby(ids).sum()
        with np.errstate(divide="ignore", invalid="ignore"):
            det = sums["s"] * sums["sff"] - sums["sf"] ** 2
            usable = (sums["n"] >= 2) & (det > 1e-12 * sums["s"] ** 2)
            slope = (sums["s"] * sums["sfy"] - sums["sf"] * sums["sy"]) / det
            error = np.sqrt(sums["s"] / det)
        out[f"velocity_{axis}"] = slope.where(usable)
        out[f"sigma_v{axis}"] = error.where(usable)
    table = pd.DataFrame(out)
    table.index.name = ID_COLUMN
    return table


def _reach(table: pd.DataFrame) -> np.ndarray:
    """Half the major axis of each row (half the diameter where it has none), mm; 0
    where neither is known."""
    n = len(table)
    major = table["major_axis"].to_numpy(float) if "major_axis" in table else np.full(n, np.nan)
    diameter = (table[DIAMETER_COLUMN].to_numpy(float) if DIAMETER_COLUMN in table
                else np.full(n, np.nan))
    reach = 0.5 * np.where(np.isfinite(major), major, diameter)
    return np.where(np.isfinite(reach), reach, 0.0)


def _touching(frame_rows: pd.DataFrame, touch_sigma: float) -> np.ndarray:
    """Track-id pairs ``(a < b)`` (K, 2) of the points of one frame that touch within
    ``touch_sigma`` standard uncertainties of their distance."""
    xyz = frame_rows[list(POS_COLUMNS)].to_numpy(float)
    sigma = frame_rows[list(SIGMA_COLUMNS)].to_numpy(float)
    reach = _reach(frame_rows)
    finite = np.all(np.isfinite(xyz), axis=1)
    rows = np.flatnonzero(finite)
    if len(rows) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    largest_sigma = np.nanmax(np.where(np.isfinite(sigma[rows]), sigma[rows], np.nan),
                              initial=0.0)
    radius = 2.0 * reach[rows].max() + touch_sigma * np.sqrt(2.0) * largest_sigma
    pairs = rows[cKDTree(xyz[rows]).query_pairs(max(radius, 1e-9), output_type="ndarray")]
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    offset = xyz[i] - xyz[j]
    d = np.linalg.norm(offset, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = np.where(d[:, None] > 0, offset / d[:, None], 1.0 / np.sqrt(3.0))
    sigma_d = np.sqrt(np.sum(unit ** 2 * (sigma[i] ** 2 + sigma[j] ** 2), axis=1))
    touch = d - (reach[i] + reach[j]) <= touch_sigma * sigma_d    # NaN sigma: False
    ids = frame_rows[ID_COLUMN].to_numpy(np.int64)
    a, b = ids[i[touch]], ids[j[touch]]
    return np.c_[np.minimum(a, b), np.maximum(a, b)]


def piece_pairs(linked: pd.DataFrame, *, touch_sigma: float = 2.0,
                velocity_p: float = 0.01) -> np.ndarray:
    """Pairs of tracks that are pieces of one body (module notes).

    Parameters
    ----------
    linked : DataFrame
        Linked particles (:func:`plenoptrack.track.link_particles`): ``frame, particle,
        x, y, z`` and ``sigma_x, sigma_y, sigma_z`` (mm); ``major_axis`` or ``diameter``
        (mm) give each point's reach (0 without them).
    touch_sigma : float
        How far apart, in standard uncertainties of their distance, two points may lie
        beyond touching and still count as touching.
    velocity_p : float
        Least p-value of the chi-square of the two tracks' velocity difference.

    Returns
    -------
    (K, 2) int ndarray
        Track ids ``a < b``, sorted.
    """
    if not (np.isfinite(touch_sigma) and touch_sigma >= 0):
        raise SettingsError(f"touch_sigma must be a finite number >= 0; got {touch_sigma!r}")
    if not 0 < velocity_p < 1:
        raise SettingsError(f"velocity_p must be in (0, 1); got {velocity_p!r}")
    empty = np.zeros((0, 2), dtype=np.int64)
    needed = [T_COLUMN, ID_COLUMN, *POS_COLUMNS, *SIGMA_COLUMNS]
    if len(linked) < 2 or any(c not in linked.columns for c in needed):
        return empty
    touching = [_touching(rows, touch_sigma) for _, rows in linked.groupby(T_COLUMN, sort=False)]
    touching = np.concatenate([empty, *touching])
    if len(touching) == 0:
        return empty
    pairs, n_touch = np.unique(touching, axis=0, return_counts=True)
    frames = linked.groupby(ID_COLUMN)[T_COLUMN].agg(lambda f: frozenset(f.tolist()))
    n_common = np.array([len(frames[a] & frames[b]) for a, b in pairs])
    keep = (n_common >= MIN_COMMON_FRAMES) & (2 * n_touch >= n_common)
    pairs = pairs[keep]
    if len(pairs) == 0:
        return empty
    velocity = track_velocities(linked)
    va = velocity.loc[pairs[:, 0]].to_numpy(float)
    vb = velocity.loc[pairs[:, 1]].to_numpy(float)
    dv = va[:, 0::2] - vb[:, 0::2]
    var = va[:, 1::2] ** 2 + vb[:, 1::2] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2 = np.sum(dv ** 2 / var, axis=1)           # NaN where a velocity is missing
    together = stats.chi2.sf(chi2, 3) >= velocity_p
    return pairs[together].astype(np.int64)


def _body_centre(frame_idx: np.ndarray, piece_idx: np.ndarray, y: np.ndarray, w: np.ndarray,
                 area: np.ndarray, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``y = c[frame] + o[piece]`` with ``sum area o = 0`` (weights ``w``):
    ``(c, sigma_c)`` per frame, NaN for frames without a weighted point."""
    n_pieces = len(area)
    seen = np.bincount(frame_idx, weights=w, minlength=n_frames) > 0
    fitted = np.flatnonzero(seen)
    col = np.full(n_frames, -1, dtype=np.int64)
    col[fitted] = np.arange(len(fitted))
    use = (w > 0) & seen[frame_idx]
    n_c = len(fitted)
    n = n_c + n_pieces
    design = np.zeros((int(use.sum()), n))
    rows = np.arange(len(design))
    design[rows, col[frame_idx[use]]] = 1.0
    design[rows, n_c + piece_idx[use]] = 1.0
    normal = design.T @ (design * w[use, None])
    kkt = np.zeros((n + 1, n + 1))
    kkt[:n, :n] = normal
    kkt[n, n_c:n] = kkt[n_c:n, n] = area / area.sum()
    rhs = np.zeros(n + 1)
    rhs[:n] = design.T @ (w[use] * y[use])
    centre = np.full(n_frames, np.nan)
    sigma = np.full(n_frames, np.nan)
    try:
        inverse = np.linalg.inv(kkt)
    except np.linalg.LinAlgError:
        return centre, sigma
    solution = inverse @ rhs
    centre[fitted] = solution[:n_c]
    sigma[fitted] = np.sqrt(np.maximum(np.diag(inverse)[:n_c], 0.0))
    return centre, sigma


def union_diameter(centres_mm: np.ndarray, diameters_mm: np.ndarray, *,
                   cells: int = 200) -> float:
    """Equivalent diameter ``sqrt(4 A / pi)`` of the union ``A`` of discs, mm.

    Parameters
    ----------
    centres_mm : (P, 2) float ndarray
        Disc centres (x, y), mm.
    diameters_mm : (P,) float ndarray
        Disc diameters, mm; discs with a diameter that is not positive and finite are
        left out.
    cells : int
        Grid cells along the longer side of the discs' bounding box on which the union
        is counted (the area to about ``1 / cells`` of the discs' size).
    """
    centres_mm = np.asarray(centres_mm, dtype=float).reshape(-1, 2)
    radius = 0.5 * np.asarray(diameters_mm, dtype=float).ravel()
    ok = np.isfinite(radius) & (radius > 0) & np.all(np.isfinite(centres_mm), axis=1)
    centres_mm, radius = centres_mm[ok], radius[ok]
    if len(radius) == 0:
        return float("nan")
    if len(radius) == 1:
        return float(2.0 * radius[0])
    lo = (centres_mm - radius[:, None]).min(axis=0)
    hi = (centres_mm + radius[:, None]).max(axis=0)
    step = float((hi - lo).max()) / cells
    gx = lo[0] + step * (np.arange(int(np.ceil((hi[0] - lo[0]) / step))) + 0.5)
    gy = lo[1] + step * (np.arange(int(np.ceil((hi[1] - lo[1]) / step))) + 0.5)
    inside = np.zeros((len(gy), len(gx)), dtype=bool)
    for (cx, cy), r in zip(centres_mm, radius, strict=True):
        inside |= ((gx[None, :] - cx) ** 2 + (gy[:, None] - cy) ** 2) <= r * r
    return float(np.sqrt(4.0 * inside.sum() * step * step / np.pi))


def _piece_medians(values: np.ndarray, piece_idx: np.ndarray, n_pieces: int) -> np.ndarray:
    """Median of ``values`` per piece (NaN where a piece has none)."""
    return (pd.Series(values).groupby(piece_idx).median().reindex(range(n_pieces))
            .to_numpy(float))


def _body_track(rows: pd.DataFrame, piece_idx: np.ndarray, frame_idx: np.ndarray,
                area: np.ndarray, n_frames: int) -> tuple[dict, np.ndarray]:
    """The body's centre and its sigma per frame (``{"x": ..., "sigma_x": ..., ...}``,
    :func:`_body_centre` per axis) and each piece's lateral offset from it, (P, 2) mm.

    A frame without a weighted point takes the mean of its pieces' points moved by
    their offsets, with no sigma."""
    merged = {}
    offsets = np.zeros((len(area), 3))
    for k, (axis, sigma_column) in enumerate(zip(POS_COLUMNS, SIGMA_COLUMNS, strict=True)):
        y = rows[axis].to_numpy(float)
        w = _weights(rows[sigma_column].to_numpy(float))
        w = np.where(np.isfinite(y), w, 0.0)
        centre, sigma = _body_centre(frame_idx, piece_idx, y, w, area, n_frames)
        residual = y - centre[frame_idx]
        ok = np.isfinite(residual) & (w > 0)
        offsets[:, k] = (pd.Series(residual[ok]).groupby(piece_idx[ok]).mean()
                         .reindex(range(len(area))).fillna(0.0).to_numpy())
        lone = ~np.isfinite(centre)
        if lone.any():
            shifted = pd.Series(y - offsets[piece_idx, k]).groupby(frame_idx).mean()
            centre[lone] = shifted.reindex(range(n_frames)).to_numpy()[lone]
        merged[axis], merged[sigma_column] = centre, sigma
    return merged, offsets[:, :2]


def _body_size(rows: pd.DataFrame, piece_idx: np.ndarray, frame_idx: np.ndarray,
               centre_xy: np.ndarray, offsets: np.ndarray, n_frames: int) -> dict:
    """``diameter``, ``major_axis`` and ``minor_axis`` of the body per frame (those of
    the columns ``rows`` has): the union of the pieces' discs, each at the body's centre
    plus its offset (a missing piece with its median size); the longest extent of a
    piece's major axis beyond the centre, doubled; the largest minor axis."""
    n_pieces = len(offsets)
    out = {}

    def per_frame(column):
        values = rows[column].to_numpy(float)
        median = _piece_medians(values, piece_idx, n_pieces)
        now = np.tile(median, (n_frames, 1))
        now[frame_idx, piece_idx] = np.where(np.isfinite(values), values, median[piece_idx])
        return now

    if DIAMETER_COLUMN in rows:
        diameters = per_frame(DIAMETER_COLUMN)
        centres = centre_xy[:, None, :] + offsets[None, :, :]
        out[DIAMETER_COLUMN] = [union_diameter(centres[k], diameters[k])
                                for k in range(n_frames)]
    if "major_axis" in rows:
        spread = 2.0 * np.linalg.norm(offsets, axis=1)
        with np.errstate(invalid="ignore"):
            out["major_axis"] = np.nanmax(spread[None, :] + per_frame("major_axis"), axis=1)
    if "minor_axis" in rows:
        out["minor_axis"] = (pd.Series(rows["minor_axis"].to_numpy(float))
                             .groupby(frame_idx).max().to_numpy())
    return out


def _body_quality(rows: pd.DataFrame, frame_idx: np.ndarray, weight: np.ndarray,
                  n_frames: int) -> dict:
    """Per frame: the quality columns of ``rows`` as the pieces' ``weight``-ed mean
    (:data:`_WEIGHTED_MEAN_COLUMNS`), ``n_views`` the most, ``flags`` all bits, ``chi2``
    and ``orientation`` NaN (no single fit or long axis describes the body)."""
    out = {}
    for column in _WEIGHTED_MEAN_COLUMNS:
        if column in rows:
            values = rows[column].to_numpy(float)
            ok = np.isfinite(values)
            num = np.bincount(frame_idx[ok], weights=(weight * values)[ok], minlength=n_frames)
            den = np.bincount(frame_idx[ok], weights=weight[ok], minlength=n_frames)
            with np.errstate(divide="ignore", invalid="ignore"):
                out[column] = np.where(den > 0, num / den, np.nan)
    if "n_views" in rows:
        out["n_views"] = rows.groupby(frame_idx)["n_views"].max().to_numpy()
    if "flags" in rows:
        combined = np.zeros(n_frames, dtype=np.int64)
        np.bitwise_or.at(combined, frame_idx, rows["flags"].to_numpy(np.int64))
        out["flags"] = combined.astype(rows["flags"].dtype)
    for column in ("chi2", "orientation"):
        if column in rows:
            out[column] = np.nan
    return out


def _merge_group(rows: pd.DataFrame, pieces: np.ndarray) -> pd.DataFrame:
    """One track from the tracks ``pieces`` (sorted ids) of one body (module notes)."""
    piece_idx = np.searchsorted(pieces, rows[ID_COLUMN].to_numpy())
    frames, frame_idx = np.unique(rows[T_COLUMN].to_numpy(), return_inverse=True)
    n_f = len(frames)
    diameter = (rows[DIAMETER_COLUMN].to_numpy(float) if DIAMETER_COLUMN in rows
                else np.full(len(rows), np.nan))
    median_d = np.nan_to_num(_piece_medians(diameter, piece_idx, len(pieces)))
    area = median_d ** 2 if median_d.sum() > 0 else np.ones(len(pieces))
    position, offsets = _body_track(rows, piece_idx, frame_idx, area, n_f)
    point_d = np.where(np.isfinite(diameter), diameter, median_d[piece_idx])
    # per frame, the row of its largest piece carries the columns not computed here
    order = np.lexsort((-point_d, frame_idx))
    first = order[np.r_[True, frame_idx[order][1:] != frame_idx[order][:-1]]]
    out = rows.iloc[first].copy().reset_index(drop=True)
    out[ID_COLUMN] = pieces[0]
    out[T_COLUMN] = frames
    weight = point_d ** 2 if np.any(point_d > 0) else np.ones(len(rows))
    centre_xy = np.c_[position["x"], position["y"]]
    for column, values in {**position,
                           **_body_size(rows, piece_idx, frame_idx, centre_xy, offsets, n_f),
                           **_body_quality(rows, frame_idx, weight, n_f)}.items():
        out[column] = values
    out[PIECES_COLUMN] = np.bincount(frame_idx, minlength=n_f).astype(np.int64)
    return out


def merge_pieces(linked: pd.DataFrame, pairs: np.ndarray) -> pd.DataFrame:
    """Merge the tracks joined by ``pairs`` (chains included) into one track each.

    Parameters
    ----------
    linked : DataFrame
        Linked particles (:func:`plenoptrack.track.link_particles`). Not changed.
    pairs : (K, 2) int ndarray
        Track ids that are pieces of one body (:func:`piece_pairs`).

    Returns
    -------
    DataFrame
        ``linked`` with each group's rows replaced by one row per frame (module notes),
        under the group's smallest track id, and a column ``pieces``; track ids
        renumbered from 0 in order of first appearance; sorted by ``particle`` then
        ``frame``, index reset. A merged row's ``major_axis`` is twice the longest reach
        of a piece's major axis from the body's centre, its ``minor_axis`` the largest
        of the pieces', ``confidence``, ``residual_px`` and ``travel_px`` the pieces'
        area-weighted means, ``n_views`` the most, ``flags`` every piece's bits,
        ``chi2`` and ``orientation`` NaN; other columns are the largest piece's.
    """
    table = linked.reset_index(drop=True)
    ids = table[ID_COLUMN].to_numpy(np.int64)
    out = table.assign(**{PIECES_COLUMN: np.ones(len(table), dtype=np.int64)})
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) and len(table):
        n = int(ids.max()) + 1
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, group = connected_components(graph, directed=False)
        sizes = np.bincount(group)
        in_group = sizes[group[ids]] > 1
        merged = [_merge_group(table[in_group & (group[ids] == g)],
                               np.flatnonzero(group == g))
                  for g in np.flatnonzero(sizes > 1)]
        out = pd.concat([out[~in_group], *merged], ignore_index=True)
    first = out.groupby(ID_COLUMN)[T_COLUMN].min().sort_values(kind="stable")
    renumber = pd.Series(np.arange(len(first)), index=first.index)
    out[ID_COLUMN] = renumber.loc[out[ID_COLUMN].to_numpy()].to_numpy(np.int64)
    out.attrs = dict(linked.attrs)
    return out.sort_values([ID_COLUMN, T_COLUMN], kind="stable").reset_index(drop=True)
