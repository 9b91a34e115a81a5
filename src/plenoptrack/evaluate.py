"""Compare measured particles with ground truth.

Matching is optimal and one-to-one per frame: the Hungarian algorithm
(:func:`scipy.optimize.linear_sum_assignment`) on 3D distances, pairs farther apart than a
tolerance are left unmatched. From the matches: recall (matched / true), precision
(matched / measured) and the mean and standard deviation of the x, y and z errors.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from ._columns import POS_COLUMNS, T_COLUMN
from .errors import InputFileError, SettingsError

__all__ = ["match_particles", "evaluate_particles", "Evaluation", "match_track_points",
           "evaluate_tracks", "TrackEvaluation", "hidden_particles"]


@dataclass(frozen=True)
class Evaluation:
    """Detection and position-error metrics of a measurement against ground truth.

    Errors are measured minus true, in mm, over matched pairs.
    """

    n_true: int
    n_measured: int
    n_matched: int
    recall: float
    precision: float
    tolerance_mm: float
    mean_error_x: float
    mean_error_y: float
    mean_error_z: float
    std_error_x: float
    std_error_y: float
    std_error_z: float
    rms_error_lateral: float

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                for k, v in asdict(self).items()}


def _check_columns(df: pd.DataFrame, name: str) -> None:
    missing = [c for c in POS_COLUMNS if c not in df.columns]
    if missing:
        raise InputFileError(f"{name} table has no column(s) {missing}; expected {list(POS_COLUMNS)} in mm")


def match_particles(measured: pd.DataFrame, truth: pd.DataFrame, *, tolerance_mm: float = 1.0) -> pd.DataFrame:
    """Pair measured particles with true ones, one-to-one within each frame.

    Parameters
    ----------
    measured, truth : DataFrame
        Columns ``x, y, z`` in mm and optionally ``frame`` (missing means one frame).
    tolerance_mm : float
        Largest 3D distance of an accepted pair, mm.

    Returns
    -------
    pairs : DataFrame
        One row per matched pair: ``frame``, ``measured_index`` and ``truth_index`` (the
        index labels of the input rows), ``dx, dy, dz`` (measured minus true, mm) and
        ``distance`` (mm).
    """
    _check_columns(measured, "measured")
    _check_columns(truth, "truth")
    if not tolerance_mm > 0:
        raise SettingsError(f"tolerance_mm must be positive; got {tolerance_mm}")
    m_frames = measured[T_COLUMN] if T_COLUMN in measured else pd.Series(0, index=measured.index)
    t_frames = truth[T_COLUMN] if T_COLUMN in truth else pd.Series(0, index=truth.index)
    rows = []
    for frame in np.intersect1d(m_frames.unique(), t_frames.unique()):
        m = measured[(m_frames == frame).to_numpy()]
        t = truth[(t_frames == frame).to_numpy()]
        pm = m[list(POS_COLUMNS)].to_numpy(float)
        pt = t[list(POS_COLUMNS)].to_numpy(float)
        # Only pairs within the tolerance can match: a sparse cost keeps big frames cheap.
        cost = np.full((len(pm), len(pt)), 1e6)
        tree = cKDTree(pt)
        for i, neighbours in enumerate(tree.query_ball_point(pm, tolerance_mm)):
            if neighbours:
                cost[i, neighbours] = np.linalg.norm(pt[neighbours] - pm[i], axis=1)
        ri, ci = linear_sum_assignment(cost)
        ok = cost[ri, ci] <= tolerance_mm
        ri, ci = ri[ok], ci[ok]
        d = pm[ri] - pt[ci]
        rows.append(pd.DataFrame({
            T_COLUMN: frame, "measured_index": m.index[ri], "truth_index": t.index[ci],
            "dx": d[:, 0], "dy": d[:, 1], "dz": d[:, 2], "distance": np.linalg.norm(d, axis=1)}))
    if not rows:
        return pd.DataFrame({T_COLUMN: pd.Series(dtype=int), "measured_index": pd.Series(dtype=int),
                             "truth_index": pd.Series(dtype=int), "dx": pd.Series(dtype=float),
                             "dy": pd.Series(dtype=float), "dz": pd.Series(dtype=float),
                             "distance": pd.Series(dtype=float)})
    return pd.concat(rows, ignore_index=True)


def evaluate_particles(measured: pd.DataFrame, truth: pd.DataFrame, *,
                       tolerance_mm: float = 1.0) -> Evaluation:
    """Recall, precision and position errors of ``measured`` against ``truth``.

    See :func:`match_particles` for the inputs. With no matches, the error statistics
    are NaN.
    """
    pairs = match_particles(measured, truth, tolerance_mm=tolerance_mm)
    n = len(pairs)

    def stat(values, fn):
        return float(fn(values)) if len(values) else float("nan")

    std = (lambda a: np.std(a, ddof=1)) if n > 1 else (lambda a: np.nan)
    return Evaluation(
        n_true=len(truth), n_measured=len(measured), n_matched=n,
        recall=n / len(truth) if len(truth) else float("nan"),
        precision=n / len(measured) if len(measured) else float("nan"),
        tolerance_mm=float(tolerance_mm),
        mean_error_x=stat(pairs.dx, np.mean), mean_error_y=stat(pairs.dy, np.mean),
        mean_error_z=stat(pairs.dz, np.mean),
        std_error_x=stat(pairs.dx, std), std_error_y=stat(pairs.dy, std),
        std_error_z=stat(pairs.dz, std),
        rms_error_lateral=stat(np.hypot(pairs.dx, pairs.dy), lambda a: np.sqrt(np.mean(a ** 2))),
    )


_DISC_POINTS = np.concatenate([
    [[0.0, 0.0]],
    0.5 * np.c_[np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)],
    np.c_[np.cos(np.arange(16) * np.pi / 8), np.sin(np.arange(16) * np.pi / 8)]])
"""Sample points of a unit disc (25, 2): the centre, 8 at half the radius, 16 on the rim.
A particle's image is covered when all of them are."""


def hidden_particles(truth: pd.DataFrame, dlfc, views_uv, *,
                     step_mm: float = 0.01) -> np.ndarray:
    """Which true particles no view shows: in every view the particle's image lies wholly
    inside another particle's image of the same frame.

    A back-lit camera sees an opaque particle only as its shadow, so one hidden inside a
    larger or nearer particle's shadow in every view leaves no trace in the light field:
    no locator can find it, and it bounds the recall any method can reach. Images are
    discs of the particle's silhouette area (``projected_area``, else ``diameter``) at the
    image centre the calibration predicts, scaled by the calibration's local view pixels
    per mm; an image counts as covered when each of :data:`_DISC_POINTS` (its centre and
    rings at half and the full radius) lies inside another image, so several
    neighbours together can hide a particle.

    Parameters
    ----------
    truth : DataFrame
        Ground truth with ``x, y, z`` (mm), ``diameter`` (mm), optionally
        ``projected_area`` (mm^2) and ``frame``.
    dlfc : DLFC
        The camera's calibration.
    views_uv : (V, 2) float array_like
        ``(u, v)`` of the views to consider (e.g. those a locator reads).
    step_mm : float
        Lateral step of the finite difference that gives view pixels per mm.

    Returns
    -------
    (len(truth),) bool ndarray
        True where the particle is hidden in every view.
    """
    views_uv = np.asarray(views_uv, dtype=float).reshape(-1, 2)
    hidden = np.zeros(len(truth), dtype=bool)
    if len(truth) == 0 or len(views_uv) == 0:
        return hidden
    basis = dlfc.view_basis(views_uv[:, 0], views_uv[:, 1])
    diameter = truth["diameter"].to_numpy(float)
    if "projected_area" in truth.columns:
        area = truth["projected_area"].to_numpy(float)
        diameter = np.where(np.isfinite(area), np.sqrt(4.0 * area / np.pi), diameter)
    frames = (truth[T_COLUMN].to_numpy() if T_COLUMN in truth.columns
              else np.zeros(len(truth), dtype=int))
    xyz_all = truth[list(POS_COLUMNS)].to_numpy(float)
    for frame in np.unique(frames):
        rows = np.flatnonzero(frames == frame)
        if len(rows) < 2:
            continue
        xyz = xyz_all[rows]
        st = dlfc.predict_in_views(xyz, basis)                               # (n, V, 2)
        moved = dlfc.predict_in_views(xyz + [step_mm, 0.0, 0.0], basis)
        radius = 0.5 * diameter[rows, None] * np.hypot(*(moved - st).T).T / step_mm
        covered = np.ones(len(rows), dtype=bool)
        others = ~np.eye(len(rows), dtype=bool)[:, None, :]                 # (n, 1, n)
        for view in range(len(views_uv)):
            # every sample point of image i inside the image of some j other than i
            points = st[:, None, view] + radius[:, None, view, None] * _DISC_POINTS
            gap = np.linalg.norm(points[:, :, None] - st[None, None, :, view], axis=-1)
            inside = (gap <= radius[None, None, :, view]) & others            # (n, P, n)
            covered &= inside.any(axis=2).all(axis=1)
            if not covered.any():
                break
        hidden[rows] = covered
    return hidden


@dataclass(frozen=True)
class TrackEvaluation:
    """Tracks measured against ground truth with particle identities.

    Attributes
    ----------
    n_true_links : int
        Pairs of consecutive detections of one true particle (both matched, at most
        ``max_gap`` frames apart).
    n_recovered_links : int
        Of those, pairs that one track joins.
    link_recovery : float
        ``n_recovered_links / n_true_links``.
    n_false_links : int
        Consecutive points of a track that are matched to different true particles.
    velocity_rms_error : float
        RMS of the 3D velocity error over matched track points, mm per frame.
    mean_speed : float
        Mean true speed over those points, mm per frame.
    z_std_frame, z_std_smooth : float
        Standard deviation of the depth error (measured minus true, mm) per frame and
        after track smoothing, over the same points.
    z_rstd_frame, z_rstd_smooth : float
        The same as 1.4826 times the median absolute deviation, mm.
    n_points : int
        Matched track points.
    """

    n_true_links: int
    n_recovered_links: int
    link_recovery: float
    n_false_links: int
    velocity_rms_error: float
    mean_speed: float
    z_std_frame: float
    z_std_smooth: float
    z_rstd_frame: float
    z_rstd_smooth: float
    n_points: int

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v)
                for k, v in asdict(self).items()}


def match_track_points(tracks: pd.DataFrame, truth: pd.DataFrame, *,
                       tolerance_mm: float = 1.0, depth_ratio: float = 3.0) -> pd.Series:
    """True particle id of every row of ``tracks`` (-1 where none lies within the tolerance).

    Rows are matched per frame, one to one (:func:`match_particles`), on the measured
    ``x, y`` and ``z / depth_ratio``: within an ellipsoid of half-axes ``tolerance_mm``
    laterally and ``depth_ratio * tolerance_mm`` in depth, depth differences counting
    ``1 / depth_ratio`` as much as lateral ones (a plenoptic camera's depth errors are
    several times its lateral ones; matching on plain 3D distance pairs a point with a
    large depth error with the particle in front of or behind its own). ``truth`` needs
    ``frame, particle, x, y, z``.
    """
    from ._columns import ID_COLUMN

    if not depth_ratio > 0:
        raise SettingsError(f"depth_ratio must be positive; got {depth_ratio!r}")
    pairs = match_particles(tracks.assign(z=tracks["z"] / depth_ratio),
                            truth.assign(z=truth["z"] / depth_ratio), tolerance_mm=tolerance_mm)
    ids = pd.Series(-1, index=tracks.index, dtype=np.int64)
    ids.loc[pairs["measured_index"].to_numpy()] = truth.loc[
        pairs["truth_index"].to_numpy(), ID_COLUMN].to_numpy(np.int64)
    return ids


def _rstd(a: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(a - np.median(a)))) if len(a) else float("nan")


def evaluate_tracks(tracks: pd.DataFrame, truth: pd.DataFrame, *, tolerance_mm: float = 1.0,
                    depth_ratio: float = 3.0, max_gap: int = 3) -> TrackEvaluation:
    """Link recovery, velocity and depth errors of ``tracks`` against ``truth``.

    Parameters
    ----------
    tracks : DataFrame
        ``plenoptrack track`` output: ``frame, particle`` (track id), ``x, y, z``,
        ``z_smooth`` (mm) and ``velocity_x, velocity_y, velocity_z`` (mm per frame).
    truth : DataFrame
        ``frame, particle`` (true id), ``x, y, z`` (mm) and
        ``velocity_x, velocity_y, velocity_z`` (mm per frame), e.g. a simulator truth.
    tolerance_mm, depth_ratio : float
        Matching ellipsoid: half-axes ``tolerance_mm`` laterally and ``depth_ratio``
        times that in depth (:func:`match_track_points`).
    max_gap : int
        Largest frame difference of a true link (the tracker's memory plus one).
    """
    from ._columns import ID_COLUMN, VELOCITY_COLUMNS

    true_id = match_track_points(tracks, truth, tolerance_mm=tolerance_mm,
                                 depth_ratio=depth_ratio).to_numpy()
    t = tracks.assign(_true=true_id)
    m = t[t["_true"] >= 0].sort_values(["_true", T_COLUMN], kind="stable")
    tid = m["_true"].to_numpy()
    fr = m[T_COLUMN].to_numpy()
    track = m[ID_COLUMN].to_numpy()
    same = (tid[1:] == tid[:-1]) & (fr[1:] - fr[:-1] <= max_gap)
    n_true = int(same.sum())
    n_rec = int((same & (track[1:] == track[:-1])).sum())
    s = t.sort_values([ID_COLUMN, T_COLUMN], kind="stable")
    st, sid = s[ID_COLUMN].to_numpy(), s["_true"].to_numpy()
    consecutive = st[1:] == st[:-1]
    n_false = int((consecutive & (sid[1:] >= 0) & (sid[:-1] >= 0) & (sid[1:] != sid[:-1])).sum())
    tv = truth.set_index([T_COLUMN, ID_COLUMN])
    key = pd.MultiIndex.from_arrays([m[T_COLUMN].to_numpy(), tid])
    v_true = tv.loc[key, list(VELOCITY_COLUMNS)].to_numpy(float)
    v_meas = m[list(VELOCITY_COLUMNS)].to_numpy(float)
    ok = np.isfinite(v_meas).all(axis=1)
    err = np.sqrt(((v_meas - v_true)[ok] ** 2).sum(axis=1))
    z_true = tv.loc[key, "z"].to_numpy(float)
    dz = m["z"].to_numpy(float) - z_true
    dzs = m["z_smooth"].to_numpy(float) - z_true
    both = np.isfinite(dz) & np.isfinite(dzs)
    dz, dzs = dz[both], dzs[both]
    n = len(dz)
    std = (lambda a: float(np.std(a, ddof=1))) if n > 1 else (lambda a: float("nan"))
    return TrackEvaluation(
        n_true_links=n_true, n_recovered_links=n_rec,
        link_recovery=n_rec / n_true if n_true else float("nan"), n_false_links=n_false,
        velocity_rms_error=float(np.sqrt(np.mean(err ** 2))) if len(err) else float("nan"),
        mean_speed=float(np.sqrt((v_true[ok] ** 2).sum(axis=1)).mean()) if ok.any() else float("nan"),
        z_std_frame=std(dz), z_std_smooth=std(dzs), z_rstd_frame=_rstd(dz),
        z_rstd_smooth=_rstd(dzs), n_points=n)
