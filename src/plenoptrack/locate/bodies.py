"""One body found as two particles: pieces of one silhouette merged back.

Two solid particles cannot share space. The locator can still report two particles
for one body: a glint across a metal fragment leaves a dark rim that is segmented,
clustered and solved as a particle of its own beside the rest of the body, and an
elongated image can be clustered as two halves. Such a pair has

- bodies that overlap: centres closer than the sum of their radii (half their
  measured diameters), mm, in 3D;
- images that keep their offset across the views: the offset between the two images
  changes by less than ``max_parallax_px`` view pixels from view to view
  (:func:`parallax_px`), i.e. the two lie at one depth
  as far as the views resolve. Two particles one behind the other on one line of
  sight overlap laterally, but their images move apart across the views; two
  touching particles at one depth show no parallax, but their measured centres lie
  further apart than their radii add up to (up to the depth error).

Nothing in the images tells such a pair from one body whose silhouette was cut in two
(the hidden-particle search rejects a candidate on the same test), and two solid
bodies cannot overlap: the pair is merged. The merged particle stands at the
area-weighted mean of the two (area as diameter squared: the centroid of the joined
silhouette), its diameter is that of the two shadows added (``sqrt(d1^2 + d2^2)``),
its sigma the weighted combination of theirs, its flags both particles' flags.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["parallax_px", "one_body_pairs", "merge_bodies"]


def parallax_px(offset: np.ndarray) -> np.ndarray:
    """How far the offset ``(..., V, 2)`` between two particles' images changes across
    the views: ``sqrt(8 (var ds + var dt))``, view pixels (as
    :func:`~plenoptrack.locate.uncertainty.image_travel_px`); 0 for two particles at one
    depth. Views where either has no image (NaN) are left out."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)              # all-NaN rows
        return np.sqrt(8.0 * np.nansum(np.nanvar(offset, axis=-2), axis=-1))


def one_body_pairs(xyz_mm: np.ndarray, diameter_mm: np.ndarray, pred_px: np.ndarray, *,
                   max_parallax_px: float = 1.0) -> np.ndarray:
    """Pairs of particles that are pieces of one body (module notes).

    Parameters
    ----------
    xyz_mm : (N, 3) float ndarray
        Positions, mm.
    diameter_mm : (N,) float ndarray
        Measured diameters, mm (NaN: never paired).
    pred_px : (N, V, 2) float ndarray
        Each particle's image centre in ``V`` views, view pixels (NaN where it has none).
    max_parallax_px : float
        Largest change of the two images' offset across the views for one depth.

    Returns
    -------
    (K, 2) int ndarray
        Row pairs ``i < j``.
    """
    xyz_mm = np.asarray(xyz_mm, dtype=float)
    diameter_mm = np.asarray(diameter_mm, dtype=float)
    ok = np.all(np.isfinite(xyz_mm), axis=1) & np.isfinite(diameter_mm) & (diameter_mm > 0)
    rows = np.flatnonzero(ok)
    if len(rows) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    tree = cKDTree(xyz_mm[rows])
    pairs = tree.query_pairs(float(diameter_mm[rows].max()), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    i, j = rows[pairs[:, 0]], rows[pairs[:, 1]]
    apart = np.linalg.norm(xyz_mm[i] - xyz_mm[j], axis=1)
    touching = apart < 0.5 * (diameter_mm[i] + diameter_mm[j])
    i, j = i[touching], j[touching]
    if len(i) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    offset = pred_px[i] - pred_px[j]                                  # (K, V, 2)
    seen = np.sum(np.all(np.isfinite(offset), axis=-1), axis=-1) >= 3
    parallax = parallax_px(offset)
    keep = seen & (parallax < max_parallax_px)
    out = np.c_[np.minimum(i, j), np.maximum(i, j)][keep]
    return out.astype(np.int64)


def merge_bodies(particles: pd.DataFrame, pairs: np.ndarray) -> tuple[pd.DataFrame, np.ndarray]:
    """Merge the particles joined by ``pairs`` (chains included) into one row each.

    Parameters
    ----------
    particles : DataFrame
        A particles table (:data:`~plenoptrack.locate.perspective.PARTICLE_COLUMNS`).
    pairs : (K, 2) int ndarray
        Row pairs that are pieces of one body (:func:`one_body_pairs`).

    Returns
    -------
    merged : DataFrame
        The table with each group of pieces replaced by one row (at the row of its
        first piece; the others removed), index 0..n-1.
    new_row : (N,) int ndarray
        Row of ``merged`` each input row went to.
    """
    n = len(particles)
    if len(pairs) == 0 or n == 0:
        return particles.reset_index(drop=True), np.arange(n)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    table = particles.reset_index(drop=True).copy()
    d = table["diameter"].to_numpy(float)
    area = np.where(np.isfinite(d), d ** 2, 0.0)
    keep = np.ones(n, dtype=bool)
    for g in np.flatnonzero(np.bincount(group) > 1):
        rows = np.flatnonzero(group == g)
        w = area[rows] / area[rows].sum()
        first = rows[0]
        for axis in ("x", "y", "z"):
            table.loc[first, axis] = float(np.dot(w, table.loc[rows, axis]))
            sigma = table.loc[rows, f"sigma_{axis}"].to_numpy(float)
            table.loc[first, f"sigma_{axis}"] = float(np.sqrt(np.dot(w ** 2, sigma ** 2)))
        table.loc[first, "diameter"] = float(np.sqrt(area[rows].sum()))
        table.loc[first, "major_axis"] = float(np.nanmax(table.loc[rows, "major_axis"]))
        table.loc[first, "minor_axis"] = float(np.nanmax(table.loc[rows, "minor_axis"]))
        table.loc[first, "orientation"] = np.nan
        table.loc[first, "n_views"] = int(table.loc[rows, "n_views"].max())
        for column in ("confidence", "travel_px"):
            table.loc[first, column] = float(np.dot(w, table.loc[rows, column]))
        table.loc[first, "residual_px"] = float(np.dot(w, table.loc[rows, "residual_px"]))
        table.loc[first, "chi2"] = np.nan
        table.loc[first, "flags"] = int(np.bitwise_or.reduce(
            table.loc[rows, "flags"].to_numpy(np.int64)))
        keep[rows[1:]] = False
    _, first_of = np.unique(group, return_index=True)      # first row of each group
    new_index = np.cumsum(keep) - 1
    new_row = new_index[first_of[group]]
    merged = table[keep].reset_index(drop=True)
    merged["n_views"] = merged["n_views"].astype(np.int64)
    merged["flags"] = merged["flags"].astype(np.uint8)
    return merged, new_row
