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

__all__ = ["match_particles", "evaluate_particles", "Evaluation"]


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
