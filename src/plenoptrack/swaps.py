"""Tracks that took each other's particles: tails exchanged where both tracks fit better.

Linking decides one frame at a time. A track whose last depths were poor (a depth sigma
of millimetres, as on an irregular fragment seen along its length, with pieces of it on
its line of sight) can be predicted onto a neighbour's particle, and the neighbour's
track then goes on with the first track's particle: two tracks each made of two
particles. Seen whole, each such track fits its own motion badly, and the two fit well
with their tails exchanged.

After linking, :func:`repair_swaps` tests every pair of tracks whose points in one frame
lie within one search range of each other (the ellipsoid of ``search_range_mm``: the
pairs the linking could have confused). The test exchanges their tails from that frame
on and compares the sum of the two tracks' chi-squares about their own polynomial fits
(:func:`track_chi2`: degree ``order``, weights ``1 / sigma^2``, each point's term capped
at ``clip^2`` so that one outlier cannot decide), over the ``window`` frames around the
exchange: the smoother's local model. Over a long curved path no low polynomial fits,
and cutting it anywhere would seem to help. The exchange that lowers the sum the most is
made when it lowers it by more than :data:`SWAP_MIN_GAIN`, and the search is repeated
until none does. Only tracks
with at least ``order + 2`` points in that span before and after the exchange take part:
both assignments then hold the same points with the same degrees of freedom, and the gain
in chi-square is twice the log of the likelihood ratio between them (a track too short to
be fitted has no chi-square and would take any points for free).

The sigmas are first scaled to the scatter the tracks show, where they understate it
(:func:`sigma_scale`), so that the threshold means what it says; and an exchange once made
is not undone. The chi-squares need the points' sigmas (``sigma_x, sigma_y, sigma_z``): a
table without them is returned as it is. Nothing here reads ground truth.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from ._columns import ID_COLUMN, POS_COLUMNS, SIGMA_COLUMNS, T_COLUMN

__all__ = ["SWAP_MIN_GAIN", "sigma_scale", "track_chi2", "repair_swaps"]

SWAP_MIN_GAIN = 2.0 * np.log(100.0)
"""Least drop of the two tracks' summed chi-square for an exchange of their tails (9.2:
the exchanged assignment 100 times as likely as the linked one)."""


def sigma_scale(tracks: dict) -> np.ndarray:
    """How many times the points' sigmas their tracks' own scatter is, per axis (at least 1).

    The second difference of three consecutive points of a track, ``x[f+1] - 2 x[f] +
    x[f-1]``, is noise alone for a particle that moves steadily, with variance
    ``sigma[f+1]^2 + 4 sigma[f]^2 + sigma[f-1]^2``; the robust (1.4826 MAD) spread of the
    normalised differences over all tracks is the factor by which the sigmas understate
    the scatter (a curving track only adds to it; sigmas larger than the scatter are left
    as they are)."""
    normalised = []
    for track in tracks.values():
        f, x, s = track["frames"], track["xyz"], track["sigma"]
        steady = np.flatnonzero((f[2:] - f[1:-1] == 1) & (f[1:-1] - f[:-2] == 1))
        if len(steady) == 0:
            continue
        second = x[steady + 2] - 2 * x[steady + 1] + x[steady]
        var = s[steady + 2] ** 2 + 4 * s[steady + 1] ** 2 + s[steady] ** 2
        normalised.append(second / np.sqrt(var))
    if not normalised:
        return np.ones(3)
    d = np.concatenate(normalised)
    out = np.ones(3)
    for axis in range(3):
        v = d[:, axis][np.isfinite(d[:, axis])]
        if len(v) >= 10:
            out[axis] = max(1.0, 1.4826 * float(np.median(np.abs(v - np.median(v)))))
    return out


def track_chi2(frames: np.ndarray, xyz: np.ndarray, sigma: np.ndarray, *, degree: int,
               cap: float, scale=(1.0, 1.0, 1.0)) -> float:
    """Chi-square of one track's points about its own polynomial fits in time.

    Parameters
    ----------
    frames : (n,) ndarray
        Frame of each point.
    xyz, sigma : (n, 3) float ndarray
        Positions and their standard uncertainties, mm. Points whose sigma on an axis is
        missing or not positive are left out on that axis.
    degree : int
        Polynomial degree per axis. An axis with fewer than ``degree + 2`` points (no
        degree of freedom left) adds nothing.
    cap : float
        Largest contribution of one point on one axis (``clip^2``).
    scale : (3,) float
        Factor on every sigma, per axis (:func:`sigma_scale`).
    """
    total = 0.0
    t = np.asarray(frames, dtype=float)
    for axis in range(3):
        s = sigma[:, axis]
        ok = np.isfinite(s) & (s > 0) & np.isfinite(xyz[:, axis])
        if ok.sum() < degree + 2:
            continue
        coef = np.polyfit(t[ok], xyz[ok, axis], degree, w=1.0 / s[ok])
        r = (xyz[ok, axis] - np.polyval(coef, t[ok])) / (s[ok] * scale[axis])
        total += float(np.minimum(r * r, cap).sum())
    return total


def _split(track: dict, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """Row masks of a track's points up to ``frame`` and after it."""
    head = track["frames"] <= frame
    return head, ~head


def _joined(head_track: dict, head: np.ndarray, tail_track: dict, tail: np.ndarray) -> dict:
    return {key: np.concatenate([head_track[key][head], tail_track[key][tail]])
            for key in ("frames", "xyz", "sigma", "rows")}


def _within(track: dict, first: int, last: int) -> dict:
    """The track's points of frames ``first`` to ``last``."""
    keep = (track["frames"] >= first) & (track["frames"] <= last)
    return {key: value[keep] for key, value in track.items()}


def repair_swaps(linked: pd.DataFrame, *, search_range_mm: tuple[float, float],
                 degree: int, window: int, clip: float = 3.5,
                 min_gain: float = SWAP_MIN_GAIN) -> tuple[pd.DataFrame, int]:
    """Exchange the tails of tracks that took each other's particles (module notes).

    Parameters
    ----------
    linked : DataFrame
        Linked particles (:func:`plenoptrack.track.link_particles`): ``frame, particle,
        x, y, z, sigma_x, sigma_y, sigma_z``. Not changed.
    search_range_mm : (float, float)
        Lateral and depth half-axes, mm, of the ellipsoid within which two tracks' points
        in one frame make them candidates.
    degree : int
        Polynomial degree of the fits (the smoother's ``order``).
    window : int
        Frames the fits span (the smoother's ``window``): an exchange at frame ``f`` is
        judged on the tracks' points of frames ``f - h`` to ``f + h - 1``, with
        ``h = max(window // 2, degree + 2)``.
    clip : float
        A point's contribution to a fit's chi-square is at most ``clip^2`` per axis
        (0: no cap).
    min_gain : float
        Least drop of the summed chi-square for an exchange.

    Returns
    -------
    linked : DataFrame
        The table with the exchanged points' ``particle`` changed (rows, order and every
        other column as given).
    n_swaps : int
        Exchanges made.
    """
    needed = [T_COLUMN, ID_COLUMN, *POS_COLUMNS, *SIGMA_COLUMNS]
    if len(linked) < 4 or any(c not in linked.columns for c in needed):
        return linked, 0
    lateral, depth = search_range_mm
    cap = float(clip) ** 2 if clip > 0 else np.inf
    half = max(int(window) // 2, degree + 2)
    ids = linked[ID_COLUMN].to_numpy(np.int64)
    frames = linked[T_COLUMN].to_numpy(np.int64)
    xyz = linked[list(POS_COLUMNS)].to_numpy(float)
    sigma = linked[list(SIGMA_COLUMNS)].to_numpy(float)
    order = np.lexsort((frames, ids))
    starts = np.flatnonzero(np.r_[True, ids[order][1:] != ids[order][:-1]])
    tracks = {}
    for rows in np.split(order, starts[1:]):
        tracks[ids[rows[0]]] = {"frames": frames[rows], "xyz": xyz[rows],
                                "sigma": sigma[rows], "rows": rows}

    scale = sigma_scale(tracks)

    def chi2(track):
        return track_chi2(track["frames"], track["xyz"], track["sigma"], degree=degree,
                          cap=cap, scale=scale)

    # candidates: pairs of points of one frame within the search ellipsoid (after the
    # first frame); each is judged with the tracks that own its points at the time
    scaled = xyz / np.array([lateral, lateral, depth])
    pairs = [np.zeros((0, 2), dtype=np.int64)]
    finite = np.all(np.isfinite(scaled), axis=1)
    for frame in np.unique(frames)[1:]:
        at = np.flatnonzero((frames == frame) & finite)
        if len(at) > 1:
            pairs.append(at[cKDTree(scaled[at]).query_pairs(1.0, output_type="ndarray")])
    pairs = np.concatenate(pairs)
    owner = ids.copy()
    done = set()

    def exchange(pair):
        """(gain, a, b, new a, new b) of exchanging the tails of the pair's tracks."""
        a, b = owner[pair[0]], owner[pair[1]]
        frame = frames[pair[0]]
        if a == b or (frame, min(a, b), max(a, b)) in done:   # no exchange undone
            return -np.inf, a, b, None, None
        first, last = frame - half, frame + half - 1
        local = [_within(tracks[a], first, last), _within(tracks[b], first, last)]
        # every local track checkable (at least one degree of freedom): both assignments
        # then leave the same degrees of freedom and the chi-squares compare; a track too
        # short to fit would take any points for free
        if min(len(t["frames"]) for t in local) < degree + 2:
            return -np.inf, a, b, None, None
        before = chi2(local[0]) + chi2(local[1])
        if before <= min_gain:             # the gain cannot exceed what is there to lose
            return -np.inf, a, b, None, None
        head_a, tail_a = _split(tracks[a], frame - 1)
        head_b, tail_b = _split(tracks[b], frame - 1)
        new_a = _joined(tracks[a], head_a, tracks[b], tail_b)
        new_b = _joined(tracks[b], head_b, tracks[a], tail_a)
        local = [_within(new_a, first, last), _within(new_b, first, last)]
        if min(len(t["frames"]) for t in local) < degree + 2:
            return -np.inf, a, b, None, None
        return before - chi2(local[0]) - chi2(local[1]), a, b, new_a, new_b

    gains = np.array([exchange(pair)[0] for pair in pairs])
    n_swaps = 0
    for _ in range(len(pairs)):
        if len(pairs) == 0 or not gains.max() > min_gain:
            break
        best = pairs[int(np.argmax(gains))]
        _, a, b, new_a, new_b = exchange(best)
        done.add((frames[best[0]], min(a, b), max(a, b)))
        tracks[a], tracks[b] = new_a, new_b
        owner[new_a["rows"]], owner[new_b["rows"]] = a, b
        n_swaps += 1
        touched = np.isin(owner[pairs], [a, b]).any(axis=1)
        gains[touched] = [exchange(pair)[0] for pair in pairs[touched]]
    if n_swaps == 0:
        return linked, 0
    return linked.assign(**{ID_COLUMN: owner}), n_swaps
