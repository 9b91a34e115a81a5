"""Link 3D particle positions over frames into tracks; velocities, accelerations, statistics.

The pipeline, each step a function that can be called alone:

1. :func:`link_particles` links a particles table (``frame, x, y, z`` mm, with
   ``sigma_x, sigma_y, sigma_z``) with trackpy: 3D positions, an anisotropic search range
   (depth errors of a plenoptic camera are several times the lateral ones), memory for
   frames in which a particle was missed, and :class:`TrackVelocityPredict`, which moves
   every track along its own latest velocity (ballistic motion). Linking runs twice by
   default: the second pass starts every new track with the velocity that the first
   pass measured nearby, so even the first frame pair is linked with a prediction.
2. :func:`plenoptrack.swaps.repair_swaps` exchanges the tails of two tracks that took
   each other's particles, where both then fit their own motion better
   (:mod:`plenoptrack.swaps`), and :func:`plenoptrack.pieces.merge_pieces` joins the
   tracks that are pieces of one body: an irregular body the locator reported as two
   particles leaves two tracks that touch and move together, while separate bodies move
   apart (:mod:`plenoptrack.pieces`).
3. :func:`smooth_tracks` fits, at every point of a track, a weighted local polynomial in
   time (the ``window`` points nearest in time, degree ``order``) to each coordinate,
   each position weighted by ``1 / sigma^2``; points whose residual is far outside the
   track's scatter are rejected iteratively. The fit gives the smoothed position (the
   track-refined depth), velocity and acceleration with their standard uncertainties.
4. :func:`track_statistics` reduces each track to one row: length, mean position, speed,
   velocity, size and shape.

Units: positions mm; velocities mm per frame and accelerations mm per frame^2 (with a
frame interval, speeds also in m/s). Column names follow trackpy (``particle`` is the
track id). Nothing here reads ground truth.

References
----------
D. B. Allan et al., trackpy (Crocker-Grier linking with prediction, memory and anisotropic
search ranges), https://soft-matter.github.io/trackpy.
A. Savitzky and M. J. E. Golay, "Smoothing and differentiation of data by simplified least
squares procedures", Anal. Chem. 36 (1964) 1627-1639 (local polynomial fits).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import warnings
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from ._columns import ID_COLUMN, POS_COLUMNS, SIGMA_COLUMNS, T_COLUMN
from .errors import InputFileError, NoParticlesWarning, SettingsError
from .io import METADATA_KEY
from .pieces import PIECES_COLUMN, merge_pieces, piece_pairs
from .swaps import repair_swaps

__all__ = ["TrackSettings", "TrackVelocityPredict", "link_particles", "smooth_tracks",
           "track_statistics", "track_particles", "TrackResult", "SIGMA_COLUMNS",
           "SMOOTH_COLUMNS", "VELOCITY_COLUMNS", "ACCELERATION_COLUMNS", "depth_scatter_ratio",
           "estimate_drift", "extend_tracks", "tracking_record", "too_uncertain_to_link"]

SMOOTH_COLUMNS = ("x_smooth", "y_smooth", "z_smooth")
"""Track-smoothed position, mm."""
SMOOTH_SIGMA_COLUMNS = ("sigma_x_smooth", "sigma_y_smooth", "sigma_z_smooth")
"""Standard uncertainty of the smoothed position, mm (scaled by the tracks' real scatter)."""
VELOCITY_COLUMNS = ("velocity_x", "velocity_y", "velocity_z")
"""Velocity, mm per frame (the names of the simulator's truth columns)."""
ACCELERATION_COLUMNS = ("acceleration_x", "acceleration_y", "acceleration_z")
"""Acceleration, mm per frame^2."""


@dataclass(frozen=True)
class TrackSettings:
    """Settings of linking and smoothing.

    Attributes
    ----------
    search_range_mm : (float, float)
        Largest distance, mm, between a particle and a track's predicted position,
        laterally (x and y) and in depth (z): an ellipsoidal search region.
    memory : int
        Frames a track may miss and still be continued.
    predict : bool
        Move each track along its latest velocity before linking (:class:`TrackVelocityPredict`).
    passes : int
        Linking passes (1 or 2). With 2 the first pass links with twice the search range
        only to measure the velocity field (new tracks start along the field's most
        common displacement, or at rest if that links more particles); the second starts
        new tracks with the velocity measured near them in the first.
    extend : bool
        After linking, continue every track of at least :data:`EXTEND_MIN_POINTS` points
        at both ends along its own velocity and fill its gaps (:func:`extend_tracks`): a
        point the linking left alone or in a track of one or two points joins the track
        it fits, within the search range widened by the point's own uncertainty,
        ``memory`` frames included.
    max_sigma_ratio : float
        A point whose standard uncertainty on an axis (``sigma_x``, ``sigma_y``,
        ``sigma_z``, where the table has them) exceeds ``max_sigma_ratio`` times the
        search range on that axis is left out of linking and becomes a track of its own:
        its position alone is less certain than the region a track is searched in, so any
        link it made would be chance, and it could carry a track onto the wrong particle
        (a misplaced particle where two images merge). With ``extend`` such a point can
        still fill a track that its position fits. ``inf`` links every point.
    min_length : int
        Tracks with fewer points are dropped from the output.
    window : int
        Points of each local fit (odd numbers centre the window): at least 3 for
        ``order`` 1, ``2 order + 2`` above; the degree is lowered where fewer points are
        available.
    adapt_window : bool
        Choose each coordinate's window among ``window - 2`` (not below the least the
        order needs), ``window``, ``window + 2`` and ``window + 4`` by the smallest
        leave-one-out prediction error of its points (the mean of
        ``((y - fit) / (sigma (1 - h)))^2``, ``h`` a point's weight in its own fit): a
        coordinate that changes slowly (the depth of tracers in a mostly lateral flow)
        is smoothed over more points than one that curves. The choice is stored in the
        tracking record (``windows``).
    order : int
        Degree of the local polynomial (1: constant velocity, 2: constant acceleration).
    clip : float
        Points whose normalised residual exceeds ``clip`` times its robust scale (1.4826
        MAD over all tracks) are rejected from the fits; 0 keeps every point.
    frame_interval_s : float or None
        Time between frames, s; with it, speeds are also given in m/s.
    repair_swaps : bool
        After linking, exchange the tails of two tracks that took each other's particles
        where both then fit their own motion better (:mod:`plenoptrack.swaps`: the
        chi-square about each track's fit of degree ``order`` over the ``window`` frames
        around the exchange drops by more than
        :data:`~plenoptrack.swaps.SWAP_MIN_GAIN`). Needs the points' sigmas.
    merge_pieces : bool
        After linking, merge the tracks that are pieces of one body
        (:mod:`plenoptrack.pieces`): they touch in most of the frames they share, at
        least :data:`~plenoptrack.pieces.MIN_COMMON_FRAMES`, and their velocities agree.
        Needs the points' sigmas.
    piece_touch_sigma : float
        Two points touch when their distance exceeds the sum of their half major axes by
        at most this many standard uncertainties of the distance.
    piece_velocity_p : float
        Two tracks move together when the chi-square of their velocity difference has at
        least this p-value.
    """

    search_range_mm: tuple[float, float] = (1.0, 3.0)
    memory: int = 2
    predict: bool = True
    passes: int = 2
    extend: bool = True
    max_sigma_ratio: float = 1.0
    min_length: int = 3
    window: int = 7
    adapt_window: bool = True
    order: int = 2
    clip: float = 3.5
    frame_interval_s: float | None = None
    repair_swaps: bool = True
    merge_pieces: bool = True
    piece_touch_sigma: float = 2.0
    piece_velocity_p: float = 0.01

    def __post_init__(self) -> None:
        sr = tuple(float(v) for v in np.atleast_1d(self.search_range_mm))
        if len(sr) == 1:
            sr = (sr[0], sr[0])
        if len(sr) != 2 or not all(math.isfinite(v) and v > 0 for v in sr):
            raise SettingsError(f"search_range_mm must be one or two positive lengths (lateral, "
                                f"depth), mm; got {self.search_range_mm!r}")
        object.__setattr__(self, "search_range_mm", sr)
        for name, low in (("memory", 0), ("passes", 1), ("min_length", 1), ("order", 0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and value >= low):
                raise SettingsError(f"{name} must be an integer >= {low}; got {value!r}")
        if self.passes > 2:
            raise SettingsError(f"passes must be 1 or 2; got {self.passes}")
        if not (isinstance(self.window, (int, np.integer)) and self.window >= self.min_window):
            raise SettingsError(f"window must be an integer of at least {self.min_window} points "
                                f"for a fit of order {self.order}; got {self.window!r}")
        if not (self.max_sigma_ratio > 0):        # inf allowed
            raise SettingsError(f"max_sigma_ratio must be positive (inf: link every point); "
                                f"got {self.max_sigma_ratio!r}")
        if not (math.isfinite(self.clip) and self.clip >= 0):
            raise SettingsError(f"clip must be >= 0 (0: no rejection); got {self.clip!r}")
        if self.frame_interval_s is not None and not (
                math.isfinite(self.frame_interval_s) and self.frame_interval_s > 0):
            raise SettingsError(f"frame_interval_s must be positive; got {self.frame_interval_s!r}")
        if not (math.isfinite(self.piece_touch_sigma) and self.piece_touch_sigma >= 0):
            raise SettingsError(f"piece_touch_sigma must be a finite number >= 0; "
                                f"got {self.piece_touch_sigma!r}")
        if not 0 < self.piece_velocity_p < 1:
            raise SettingsError(f"piece_velocity_p must be in (0, 1); "
                                f"got {self.piece_velocity_p!r}")

    @property
    def min_window(self) -> int:
        """Fewest points a fit of ``order`` uses: 1, 3, then ``2 order + 2``."""
        return _min_points(self.order)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


def _min_points(degree: int) -> int:
    """Points with weight a local fit of ``degree`` needs (a constant 1, a line 3, a
    quadratic 6, a cubic 8): fewer leave too few degrees of freedom to average noise."""
    return 1 if degree == 0 else 3 if degree == 1 else 2 * degree + 2


# --------------------------------------------------------------------------------------
# prediction


class TrackVelocityPredict:
    """trackpy predictor: each track continues along its own recent velocity.

    A track with two or more points continues along the median of the velocities
    between its last ``history`` points (mm per frame), from the median of those points
    carried forward to the frame predicted: one point far off (a depth outlier, or a
    ghost on the line of sight of the true particle) then neither bends the prediction
    nor moves its start. A track with one point takes the velocity of the nearest entry
    of a guess field (e.g. the tracks of an earlier linking pass, per frame), else the
    median velocity of the tracks that have one, else ``drift`` (:func:`estimate_drift`).

    Parameters
    ----------
    guess : dict of int to ((n, 3) ndarray, (n, 3) ndarray), optional
        Per frame, positions (mm) and velocities (mm per frame) of a guess field.
    drift : (3,) array_like, optional
        Velocity of tracks with nothing better, mm per frame (default 0).
    pos_columns : sequence of str
        Position columns, in the linker's order.
    history : int
        Latest points of a track that its prediction uses (2 is the plain last-step
        velocity).

    Notes
    -----
    trackpy calls :meth:`predict` with the points of the previous frames (each knows its
    track) and the frame to predict for, and :meth:`observe` with every linked frame.
    """

    def __init__(self, guess: dict | None = None, *, drift=None, pos_columns=POS_COLUMNS,
                 history: int = 4):
        if not (isinstance(history, (int, np.integer)) and history >= 2):
            raise SettingsError(f"history must be an integer of at least 2 points; got {history!r}")
        self.pos_columns = list(pos_columns)
        self.guess = {} if guess is None else dict(guess)
        self.drift = np.zeros(len(self.pos_columns)) if drift is None else np.asarray(drift, float)
        self.history = int(history)
        self._trees = {}
        self._points: dict[int, list[tuple[int, np.ndarray]]] = {}
        self._velocity: dict[int, np.ndarray] = {}

    def __repr__(self) -> str:
        return f"TrackVelocityPredict(guess frames={len(self.guess)}, tracks={len(self._points)})"

    # trackpy's predictor protocol (see trackpy.predict.NullPredict)
    def link_df(self, features: pd.DataFrame, search_range, **kw) -> pd.DataFrame:
        """Link ``features`` (one DataFrame, every frame) with this predictor."""
        from trackpy import linking

        kw["predictor"] = self.predict
        kw["pos_columns"] = self.pos_columns
        frames = (frame for _, frame in features.groupby(T_COLUMN, sort=True))
        out = []
        for linked in linking.link_df_iter(frames, search_range, **kw):
            self.observe(linked)
            out.append(linked)
        return pd.concat(out) if out else features.assign(**{ID_COLUMN: np.int64(0)})[:0]

    def observe(self, frame: pd.DataFrame) -> None:
        """Record the positions of a newly linked frame and update track velocities."""
        t = int(frame[T_COLUMN].iloc[0]) if len(frame) else None
        pos = frame[self.pos_columns].to_numpy(float)
        for pid, p in zip(frame[ID_COLUMN].to_numpy(np.int64), pos):
            points = self._points.setdefault(int(pid), [])
            if points and t <= points[-1][0]:
                continue
            points.append((t, p))
            del points[:-self.history]
            if len(points) >= 2:
                ts = np.array([q[0] for q in points], dtype=float)
                ps = np.array([q[1] for q in points])
                steps = np.diff(ps, axis=0) / np.diff(ts)[:, None]
                self._velocity[int(pid)] = np.median(steps, axis=0)

    def _start(self, track_id: int, t1: int) -> np.ndarray | None:
        """Median of a track's recent points carried forward to ``t1`` by its velocity."""
        points = self._points.get(track_id)
        v = self._velocity.get(track_id)
        if not points or v is None:
            return None
        ts = np.array([q[0] for q in points], dtype=float)
        ps = np.array([q[1] for q in points])
        return np.median(ps + v * (t1 - ts)[:, None], axis=0)

    def _fallback(self, positions: np.ndarray, t_from: np.ndarray) -> np.ndarray:
        out = np.zeros_like(positions)
        if self.guess:
            for t in np.unique(t_from):
                g = self.guess.get(int(t))
                if g is None or len(g[0]) == 0:
                    continue
                tree = self._trees.get(int(t))
                if tree is None:
                    tree = self._trees[int(t)] = cKDTree(g[0])
                sel = t_from == t
                _, k = tree.query(positions[sel])
                out[sel] = g[1][k]
            return out
        if self._velocity:
            out[:] = np.median(np.array(list(self._velocity.values())), axis=0)
        else:
            out[:] = self.drift
        return out

    def predict(self, t1, particles):
        """Predicted positions, mm, of trackpy points ``particles`` in frame ``t1``."""
        particles = list(particles)
        if not particles:
            return np.zeros((0, len(self.pos_columns)))
        pos = np.array([p.pos for p in particles], dtype=float)
        t0 = np.array([p.t for p in particles], dtype=np.int64)
        out = np.full_like(pos, np.nan)
        for i, p in enumerate(particles):
            if p.track is not None:
                start = self._start(p.track.id, t1)
                if start is not None:
                    out[i] = start
        missing = np.isnan(out[:, 0])
        if missing.any():
            vel = self._fallback(pos[missing], t0[missing])
            out[missing] = pos[missing] + vel * (t1 - t0[missing])[:, None]
        return out


# --------------------------------------------------------------------------------------
# linking


def _check_particles(particles) -> pd.DataFrame:
    if not isinstance(particles, pd.DataFrame):
        raise SettingsError(f"particles must be a pandas DataFrame; got {type(particles).__name__}")
    missing = [c for c in (T_COLUMN, *POS_COLUMNS) if c not in particles.columns]
    if missing:
        raise InputFileError(f"particles table has no column(s) {missing}; expected "
                             f"{[T_COLUMN, *POS_COLUMNS]} (frame, mm), as `plenoptrack locate` writes")
    pos = particles[list(POS_COLUMNS)].to_numpy(float)
    if not np.isfinite(pos).all():
        raise InputFileError("particles table has non-finite positions; drop those rows first")
    try:
        frames = particles[T_COLUMN].to_numpy(float)
    except (TypeError, ValueError):
        frames = np.array([np.nan])
    if not (np.isfinite(frames).all() and np.array_equal(frames, np.round(frames))):
        raise InputFileError("particles table has frame numbers that are not whole numbers; "
                             "number the frames 0, 1, 2, ... as `plenoptrack locate` does")
    return particles


def estimate_drift(particles: pd.DataFrame, *, max_displacement_mm: float,
                   bin_mm: float) -> np.ndarray:
    """Most common displacement between the first two frames, mm per frame.

    Every pair of a particle in the first frame and one in the next frame (``frame``
    values, divided by their difference) closer than ``max_displacement_mm`` votes for
    its displacement in a 3D histogram of ``bin_mm`` bins; the mean displacement of the
    pairs in the fullest bin and its 26 neighbours is returned (the displacement
    correlation peak of particle tracking velocimetry). Zero when there are fewer than
    two frames or no pair.
    """
    frames = np.unique(particles[T_COLUMN].to_numpy())
    if len(frames) < 2:
        return np.zeros(3)
    f0, f1 = frames[0], frames[1]
    a = particles.loc[particles[T_COLUMN] == f0, list(POS_COLUMNS)].to_numpy(float)
    b = particles.loc[particles[T_COLUMN] == f1, list(POS_COLUMNS)].to_numpy(float)
    pairs = cKDTree(a).query_ball_tree(cKDTree(b), max_displacement_mm)
    d = np.array([b[j] - a[i] for i, js in enumerate(pairs) for j in js]).reshape(-1, 3)
    if len(d) == 0:
        return np.zeros(3)
    cells = np.floor(d / bin_mm).astype(np.int64)
    keys, counts = np.unique(cells, axis=0, return_counts=True)
    best = keys[np.argmax(counts)]
    near = (np.abs(cells - best) <= 1).all(axis=1)
    return d[near].mean(axis=0) / float(f1 - f0)


def _link_once(particles: pd.DataFrame, settings: TrackSettings, guess,
               drift: np.ndarray | None = None) -> np.ndarray:
    """Track id of every row of ``particles`` (trackpy numbering), one linking pass.

    Without a ``guess`` field the predictor starts new tracks along ``drift`` (mm per
    frame), by default the drift between the first two frames (:func:`estimate_drift`,
    displacements up to ``5 lateral + depth`` search ranges, bins of half the lateral
    range).
    """
    import trackpy

    lateral, depth = settings.search_range_mm
    search = (lateral, lateral, depth)
    feats = particles[[T_COLUMN, *POS_COLUMNS]].copy()
    feats[T_COLUMN] = feats[T_COLUMN].astype(np.int64)
    feats["_row"] = np.arange(len(feats))
    feats = feats.sort_values(T_COLUMN, kind="stable")
    trackpy.quiet()
    if settings.predict:
        if guess is None and drift is None:
            drift = estimate_drift(particles, max_displacement_mm=5 * lateral + depth,
                                   bin_mm=0.5 * lateral)
        predictor = TrackVelocityPredict(guess, drift=drift)
        linked = predictor.link_df(feats, search, memory=settings.memory,
                                   adaptive_stop=0.1 * lateral, adaptive_step=0.9)
    else:
        linked = trackpy.link(feats, search, pos_columns=list(POS_COLUMNS), t_column=T_COLUMN,
                              memory=settings.memory, adaptive_stop=0.1 * lateral,
                              adaptive_step=0.9)
    ids = np.empty(len(feats), dtype=np.int64)
    ids[linked["_row"].to_numpy()] = linked[ID_COLUMN].to_numpy(np.int64)
    return ids


def link_particles(particles: pd.DataFrame, settings: TrackSettings = TrackSettings()) -> pd.DataFrame:
    """Link particles over frames.

    Parameters
    ----------
    particles : DataFrame
        Columns ``frame`` and ``x, y, z`` (mm), e.g. from ``plenoptrack locate``; any
        other columns are kept. Not changed.
    settings : TrackSettings
        Search range, memory, prediction and passes. Rows too uncertain to link
        (:func:`too_uncertain_to_link`) are left out; each gets a track of its own,
        unless extension (``extend``) lets it fill a track its position fits.

    Returns
    -------
    DataFrame
        ``particles`` with a ``particle`` column (track id, from 0, in order of first
        appearance), sorted by ``particle`` then ``frame``; the index is reset.
    """
    particles = _check_particles(particles).reset_index(drop=True)
    if ID_COLUMN in particles.columns:
        particles = particles.drop(columns=[ID_COLUMN])
    if len(particles) == 0:
        warnings.warn("no particles to link", NoParticlesWarning, stacklevel=2)
        return particles.assign(**{ID_COLUMN: pd.Series(dtype=np.int64)})
    unlinkable = too_uncertain_to_link(particles, settings)
    ids = np.empty(len(particles), dtype=np.int64)
    if not unlinkable.all():
        ids[~unlinkable] = _linked_ids(particles[~unlinkable].reset_index(drop=True), settings)
    ids[unlinkable] = ids[~unlinkable].max(initial=-1) + 1 + np.arange(int(unlinkable.sum()))
    if settings.extend:
        ids = extend_tracks(particles, ids, settings)
    # renumber in order of first appearance
    order = pd.DataFrame({"id": ids, "f": particles[T_COLUMN].to_numpy()}).groupby("id")["f"].min()
    first_seen = order.sort_values(kind="stable").index.to_numpy()
    remap = np.empty(ids.max() + 1, dtype=np.int64)
    remap[first_seen] = np.arange(len(first_seen))
    out = particles.assign(**{ID_COLUMN: remap[ids]})
    return out.sort_values([ID_COLUMN, T_COLUMN], kind="stable").reset_index(drop=True)


def too_uncertain_to_link(particles: pd.DataFrame,
                          settings: TrackSettings = TrackSettings()) -> np.ndarray:
    """Rows whose position is less certain than the search region
    (:attr:`TrackSettings.max_sigma_ratio`): ``sigma_x`` or ``sigma_y`` above
    ``max_sigma_ratio`` times the lateral search range, or ``sigma_z`` above that times
    the depth range. A table without sigma columns has none; a NaN sigma counts as
    certain (nothing says otherwise)."""
    lateral, depth = settings.search_range_mm
    out = np.zeros(len(particles), dtype=bool)
    for column, search in zip(SIGMA_COLUMNS, (lateral, lateral, depth), strict=True):
        if column in particles.columns:
            out |= particles[column].to_numpy(float) > settings.max_sigma_ratio * search
    return out


def _linked_ids(particles: pd.DataFrame, settings: TrackSettings) -> np.ndarray:
    """Track id of every row (not yet renumbered): one or two linking passes
    (:func:`link_particles`)."""
    first_pass = settings
    if settings.predict and settings.passes == 2:
        lateral, depth = settings.search_range_mm
        first_pass = dataclasses.replace(settings, search_range_mm=(2 * lateral, 2 * depth))
    ids = _link_once(particles, first_pass, None)
    if settings.predict and settings.passes == 2:
        # The drift is the most common displacement; a field without one (fragments
        # flying out in every direction) still has a peak of chance pairs, which would
        # send every new track the wrong way. Keep whichever start, drift or rest,
        # links more of the particles.
        still = _link_once(particles, first_pass, None, drift=np.zeros(3))
        if len(np.unique(still)) < len(np.unique(ids)):
            ids = still
        first = smooth_tracks(particles.assign(**{ID_COLUMN: ids}),
                              TrackSettings(window=5, order=1, clip=0.0, min_length=2))
        guess = {}
        for t, grp in first.groupby(T_COLUMN):
            ok = np.isfinite(grp[VELOCITY_COLUMNS[0]].to_numpy(float))
            guess[int(t)] = (grp.loc[ok, list(POS_COLUMNS)].to_numpy(float),
                             grp.loc[ok, list(VELOCITY_COLUMNS)].to_numpy(float))
        ids = _link_once(particles, settings, guess)
    return ids


EXTEND_MIN_POINTS = 3
"""Points a track needs before :func:`extend_tracks` continues it: two points give a
velocity but no check of it (one of them may be a ghost)."""


def _slot_prediction(frames: np.ndarray, xyz: np.ndarray, target: int, degree: int,
                     window: int) -> np.ndarray:
    """(3,) position at frame ``target`` of a track's fit (degree ``degree``, at most the
    points minus two) over its ``window`` points nearest ``target`` in time: beyond an
    end the fit over the points nearest that end, in a gap the fit over those around it."""
    near = np.argsort(np.abs(frames - target), kind="stable")[:window]
    deg = min(degree, len(near) - 2)
    coef = np.polynomial.polynomial.polyfit(frames[near] - target, xyz[near], deg)
    return coef[0]


def _missing_frames(have: np.ndarray, reach: int, available) -> list[int]:
    """Frames within ``reach`` of a track's frames ``have`` (sorted) that it has no point
    in, beyond its ends and in its gaps, among those ``available``."""
    span = range(int(have[0]) - reach, int(have[-1]) + reach + 1)
    return [t for t in span
            if t in available and 0 < np.min(np.abs(have - t)) <= reach]


def _search_scales(particles: pd.DataFrame, settings: TrackSettings) -> np.ndarray:
    """(n, 3) half-axes, mm, of the region around a prediction in which each row is a
    candidate: the search range on each axis widened by two of the row's own standard
    uncertainties, added in quadrature (the search range alone where a sigma is missing
    or NaN)."""
    lateral, depth = settings.search_range_mm
    scale = np.tile(np.array([lateral, lateral, depth]), (len(particles), 1))
    for axis, column in enumerate(SIGMA_COLUMNS):
        if column in particles.columns:
            sigma = np.nan_to_num(particles[column].to_numpy(float), nan=0.0)
            scale[:, axis] = np.hypot(scale[:, axis], 2.0 * np.maximum(sigma, 0.0))
    return scale


def extend_tracks(particles: pd.DataFrame, ids: np.ndarray,
                  settings: TrackSettings = TrackSettings()) -> np.ndarray:
    """Continue tracks at both ends along their own velocity and fill their gaps.

    Linking predicts a new track's first step from the velocity field around it; where
    that guess is wrong (a ghost took the first link, particles fly apart in every
    direction) a particle's first or last point ends up alone or in a track of one or
    two points beside its real track. A point too uncertain to link
    (:func:`too_uncertain_to_link`) is alone too. Here every track of at least
    :data:`EXTEND_MIN_POINTS` points predicts its position in each frame it lacks, up to
    ``memory + 1`` frames beyond its ends and in the gaps between its points, from the
    fit (degree ``order``, at least 1 and at most the points minus two) over its
    ``window`` points nearest that frame. The points of tracks shorter than
    :data:`EXTEND_MIN_POINTS` are candidates within the search region of a prediction:
    the ellipsoid of :attr:`TrackSettings.search_range_mm` widened on each axis by two
    of the point's own standard uncertainties (``sigma_x, sigma_y, sigma_z`` where the
    table has them, added in quadrature), so a point whose depth is uncertain joins the
    track its lateral position fits, where the smoothing weights its depth by its sigma.
    Such a point only fills a track that three or more linked points already define; it
    never starts or bridges one. The closest pairs (distance in units of the region) are
    joined first, one point per track and frame and one track per point, and the tracks
    are extended again until no point joins.

    Parameters
    ----------
    particles : DataFrame
        Columns ``frame`` and ``x, y, z`` (mm), optionally ``sigma_x, sigma_y, sigma_z``
        (mm); one row per particle and frame.
    ids : (n,) int ndarray
        Track id of every row, as linking gave it.
    settings : TrackSettings
        ``search_range_mm``, ``memory``, ``window`` and ``order``.

    Returns
    -------
    (n,) int ndarray
        Track ids with the joined points moved to the tracks they continue; a short
        track that gave up a point keeps the rest.
    """
    ids = np.asarray(ids, dtype=np.int64).copy()
    frames = particles[T_COLUMN].to_numpy(np.int64)
    xyz = particles[list(POS_COLUMNS)].to_numpy(float)
    region = _search_scales(particles, settings)
    base = region.min(axis=0)
    reach = settings.memory + 1
    degree = max(1, settings.order)
    window = max(settings.window, EXTEND_MIN_POINTS)
    while True:     # each join takes a point out of the short tracks: this ends
        sizes = np.bincount(ids)
        loose = np.flatnonzero(sizes[ids] < EXTEND_MIN_POINTS)
        if len(loose) == 0:
            break
        candidates = {}   # frame -> (rows, tree in base units, widest region / base)
        for f in np.unique(frames[loose]):
            rows = loose[frames[loose] == f]
            candidates[int(f)] = (rows, cKDTree(xyz[rows] / base),
                                  float(np.max(region[rows] / base)))
        pairs = []   # (distance in region units, (track, frame), row)
        order = np.lexsort((frames, ids))
        long_tracks = np.flatnonzero(sizes >= EXTEND_MIN_POINTS)
        bounds = np.searchsorted(ids[order], long_tracks)
        for track, lo in zip(long_tracks, bounds, strict=True):
            rows = order[lo:lo + sizes[track]]
            for target in _missing_frames(frames[rows], reach, candidates):
                pred = _slot_prediction(frames[rows], xyz[rows], target, degree, window)
                rows_f, tree, widest = candidates[target]
                near = rows_f[tree.query_ball_point(pred / base, widest)]
                dist = np.linalg.norm((xyz[near] - pred) / region[near], axis=1)
                if len(near) and dist.min() <= 1.0:
                    k = int(np.argmin(dist))
                    pairs.append((float(dist[k]), (int(track), target), int(near[k])))
        joined, slots_used, rows_used = 0, set(), set()
        for dist, slot, row in sorted(pairs):
            if slot in slots_used or row in rows_used:
                continue
            slots_used.add(slot)
            rows_used.add(row)
            ids[row] = slot[0]
            joined += 1
        if joined == 0:
            break
    return ids


# --------------------------------------------------------------------------------------
# smoothing


def _windows(frames: np.ndarray, starts: np.ndarray, lengths: np.ndarray, k: int,
             keep: np.ndarray | None = None) -> np.ndarray:
    """For each row, the rows of its track that its local fit uses.

    ``frames`` are sorted within each track. A row with ``k // 2`` points on either side
    uses the ``k`` points centred on it. A row nearer an end of its track, with only
    ``s < k // 2`` points on that side, uses those ``s`` and ``k - 1 - s + 2 (k // 2 - s)``
    points on the other side (a derivative at the end of a one-sided window is far less
    certain than at its centre; the longer window makes up for it). A track of fewer
    points uses all of them. Unused slots hold -1; the array has ``k + 2 (k // 2)``
    columns (``2 k - 1`` for odd ``k``, ``2 k`` for even), the longest end window.

    With ``keep`` (n,) bool, windows are made of kept rows only: each row's window is
    the one it would have among the kept rows of its track, a row not kept standing
    where it lies in time but left out of its own window. Points rejected from the fits
    then leave every window its ``k`` points (a window of 7 that lost three would
    otherwise fit a line to a curved track, and its residuals reject more).
    """
    n = len(frames)
    half = k // 2
    width = k + 2 * half
    out = np.full((n, width), -1, dtype=np.int64)
    for s0, m in zip(starts, lengths):
        rows = np.arange(s0, s0 + m)
        kept = rows if keep is None else rows[keep[s0:s0 + m]]
        for i in range(m):
            row = s0 + i
            pos = i if keep is None else int(np.searchsorted(kept, row))
            alone = keep is not None and not keep[row]
            seq = np.insert(kept, pos, row) if alone else kept
            mm = len(seq)
            left, right = pos, mm - 1 - pos
            if min(left, right) >= half:
                a, b = pos - half, pos - half + k
            else:
                s = min(left, right)
                long = k - 1 - s + 2 * (half - s)
                a, b = (pos - s, pos + long + 1) if left <= right else (pos - long, pos + s + 1)
            chosen = seq[max(a, 0):min(b, mm)]
            if alone:
                chosen = chosen[chosen != row]
            out[row, :len(chosen)] = chosen
    return out


def _window_candidates(settings: TrackSettings, longest: int) -> list[int]:
    """The windows :attr:`TrackSettings.adapt_window` chooses from (only ``window``
    without it): ``window - 2``, ``window``, ``window + 2``, ``window + 4``, none below
    the least the order needs, none beyond the first that holds the longest track."""
    k = settings.window
    if not settings.adapt_window:
        return [k]
    out = []
    for cand in (k - 2, k, k + 2, k + 4):
        if cand >= settings.min_window and (not out or out[-1] < longest):
            out.append(cand)
    return sorted(set(out) | {k})


def _press_window(t: np.ndarray, y: np.ndarray, sigma: np.ndarray, w: np.ndarray,
                  window_idx: dict, order: int) -> int:
    """The window of ``window_idx`` (window: rows of each row's window) whose fits
    predict each kept point (weight ``w > 0``) best when it is left out: the smallest
    mean of ``((y - fit) / (sigma (1 - h)))^2`` (``h`` from :func:`_leverage`); the
    smallest window on a tie or where nothing can be judged."""
    best, best_score = min(window_idx), np.inf
    for k in sorted(window_idx):
        idx = window_idx[k]
        coef, L, _ = _local_fit(t, y, w, idx, order)
        h = _leverage(idx, L)
        ok = (w > 0) & (h < 0.999) & np.isfinite(coef[:, 0])
        if ok.sum() < 3:
            continue
        score = float(np.mean(((y[ok] - coef[ok, 0]) / (sigma[ok] * (1.0 - h[ok]))) ** 2))
        if score < best_score:
            best, best_score = k, score
    return best


def _leverage(idx: np.ndarray, L: np.ndarray) -> np.ndarray:
    """(n,) each row's weight in its own local fit (``L`` (n, k) the fit's weights over
    the rows ``idx`` (n, k) of its window); 0 for a row not in its window."""
    return np.where(idx == np.arange(len(idx))[:, None], L, 0.0).sum(axis=1)


def _kept_windows(idx: np.ndarray, frames: np.ndarray, starts: np.ndarray,
                  lengths: np.ndarray, k: int, keep: np.ndarray) -> np.ndarray:
    """``idx`` (the windows of :func:`_windows`) with the windows of every track that has
    a row not kept made again of its kept rows (:func:`_windows` with ``keep``)."""
    if keep.all():
        return idx
    out = idx.copy()
    dropped = np.add.reduceat((~keep).astype(np.int64), starts) if len(starts) else []
    for s0, m in zip(starts[np.flatnonzero(dropped)], lengths[np.flatnonzero(dropped)]):
        part = _windows(frames[s0:s0 + m], np.array([0]), np.array([m]), k,
                        keep=keep[s0:s0 + m])
        out[s0:s0 + m] = np.where(part >= 0, part + s0, -1)
    return out


def _local_fit(t: np.ndarray, y: np.ndarray, w: np.ndarray, idx: np.ndarray, order: int):
    """Weighted local polynomial fits at every row.

    Parameters
    ----------
    t : (n,) float
        Frame of every row.
    y : (n,) float
        Coordinate, mm.
    w : (n,) float
        Weights (``1 / sigma^2``, 0 rejects a point).
    idx : (n, k) int
        Window rows of each row (-1: none).
    order : int
        Polynomial degree, lowered per row where too few points have weight (a
        quadratic needs 6, a cubic 8, a line 3): fits with few degrees of freedom follow
        the noise.

    Returns
    -------
    coef : (n, order + 1) float
        Polynomial coefficients about each row's own time: value, slope, half curvature.
    smoother : (n, k) float
        Weights ``L`` with ``value = sum(L * y[idx])`` (for the uncertainty).
    slope_row : (n, k) float
        Weights with ``slope = sum(slope_row * y[idx])``.
    """
    n, k = idx.shape
    valid = idx >= 0
    safe = np.where(valid, idx, 0)
    dt = np.where(valid, t[safe] - t[:, None], 0.0)
    ww = np.where(valid, w[safe], 0.0)
    yy = np.where(valid, y[safe], 0.0)
    npts = (ww > 0).sum(axis=1)
    coef = np.full((n, order + 1), np.nan)
    smoother = np.zeros((n, k))
    slope_row = np.zeros((n, k))
    for deg in range(order, -1, -1):
        rows = npts >= _min_points(deg)
        rows &= np.isnan(coef[:, 0])
        if not rows.any():
            continue
        A = dt[rows][:, :, None] ** np.arange(deg + 1)           # (m, k, deg+1)
        W = ww[rows]
        AtW = A.transpose(0, 2, 1) * W[:, None, :]                 # (m, deg+1, k)
        G = AtW @ A
        # scale-free conditioning: a singular normal matrix (repeated times) falls back
        ok = np.abs(np.linalg.det(G)) > 1e-12 * np.prod(np.diagonal(G, axis1=1, axis2=2), axis=1)
        Ginv = np.zeros_like(G)
        Ginv[ok] = np.linalg.inv(G[ok])
        H = Ginv @ AtW                                             # (m, deg+1, k)
        c = np.einsum("mjk,mk->mj", H, yy[rows])
        sel = np.flatnonzero(rows)[ok]
        coef[sel, :deg + 1] = c[ok]
        coef[sel, deg + 1:] = 0.0
        smoother[sel] = H[ok, 0]
        if deg >= 1:
            slope_row[sel] = H[ok, 1]
    return coef, smoother, slope_row


def _robust_line(t: np.ndarray, y: np.ndarray, idx: np.ndarray, order: int) -> np.ndarray:
    """(n,) residual of each row from a robust line through its window (mm): the
    Theil-Sen line (median of the slopes between every two points of the window,
    intercept the median of the points less that slope), or the window's median for
    ``order`` 0. Unlike a least-squares fit it follows the majority of the window even
    when several neighbouring points lie far off. For ``order`` 2 and above the
    window's curvature is taken out first: the median second divided difference of
    every three points times ``dt^2`` (the same idea one degree up), so that a track
    that accelerates is not judged against a straight line (every point of a strongly
    curved track would lie off it). NaN where the window has fewer than two points at
    distinct times."""
    n, k = idx.shape
    valid = idx >= 0
    safe = np.where(valid, idx, 0)
    dt = np.where(valid, t[safe] - t[:, None], np.nan)
    yy = np.where(valid, y[safe], np.nan)
    if order >= 2 and n and k >= 3:
        yy = yy - _robust_half_curvature(dt, yy)[:, None] * dt ** 2
    if order == 0 or n == 0:
        slope = np.zeros(n)
    else:
        a, b = np.triu_indices(k, 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            pair = (yy[:, b] - yy[:, a]) / (dt[:, b] - dt[:, a])
        pair[~np.isfinite(pair)] = np.nan
        usable = np.isfinite(pair).any(axis=1)
        slope = np.full(n, np.nan)
        slope[usable] = np.nanmedian(pair[usable], axis=1)
    with np.errstate(invalid="ignore"):
        line = yy - slope[:, None] * dt
    has = np.isfinite(line).sum(axis=1) >= 2
    intercept = np.full(n, np.nan)
    intercept[has] = np.nanmedian(line[has], axis=1)
    return y - intercept


def _robust_half_curvature(dt: np.ndarray, yy: np.ndarray) -> np.ndarray:
    """(n,) median second divided difference over every three points of each window
    (``dt``, ``yy`` (n, k), their points first and NaN after them, as :func:`_windows`
    lays them out): the window's quadratic coefficient (half its second derivative),
    robust to a minority of far-off points; 0 where no three points are at distinct
    times. Rows are taken in groups of equal point count, each with only its own
    triples."""
    count = np.isfinite(yy).sum(axis=1)
    half = np.zeros(len(dt))
    for c in np.unique(count[count >= 3]):
        rows = np.flatnonzero(count == c)
        a, b, d = (np.array(v) for v in zip(*itertools.combinations(range(int(c)), 3)))
        t, y = dt[rows, :c], yy[rows, :c]
        with np.errstate(invalid="ignore", divide="ignore"):
            first_ab = (y[:, b] - y[:, a]) / (t[:, b] - t[:, a])
            first_bd = (y[:, d] - y[:, b]) / (t[:, d] - t[:, b])
            second = (first_bd - first_ab) / (t[:, d] - t[:, a])
        finite = np.isfinite(second)
        if finite.all():
            half[rows] = np.median(second, axis=1)
            continue
        second[~finite] = np.nan
        usable = finite.any(axis=1)
        half[rows[usable]] = np.nanmedian(second[usable], axis=1)
    return half


def _smoothed_sigma(L: np.ndarray, sigma_window: np.ndarray, scale: float, *,
                    measured: bool = True) -> np.ndarray:
    """(n,) standard error of each smoothed value (mm) from the fit's weights ``L`` (n, k)
    and the locator's sigmas of the window's points ``sigma_window`` (n, k; 0 where
    unused), given the tracks' scatter ``scale`` (their scatter about the fits over the
    locator's sigmas).

    The scatter about a track measures only the part of the error that changes from
    frame to frame. With ``scale >= 1`` that is all of it and the sigmas are rescaled:
    ``scale sqrt(sum L^2 sigma^2)``. With ``scale < 1`` the locator's sigma holds more
    than the track shows (the DLFC's model error, a particle's shape: errors that a
    slowly moving particle keeps from frame to frame); that share, ``1 - scale^2`` of
    the variance, is taken as shared by the window's points and is not averaged away::

        var = scale^2 sum L^2 sigma^2 + (1 - scale^2) (sum L sigma)^2

    ``measured`` False: the sigmas are placeholders (a table without them), in no unit
    of error; they are only rescaled.
    """
    shared = max(1.0 - scale ** 2, 0.0) if measured else 0.0
    var = (scale ** 2 * (L ** 2 * sigma_window ** 2).sum(axis=1)
           + shared * (L * sigma_window).sum(axis=1) ** 2)
    return np.sqrt(var)


TRACK_SCALE_MIN_POINTS = 4
"""Points of a track (residuals in its own fit) that its own robust scale needs."""


def _track_scales(resid: np.ndarray, usable: np.ndarray, pid: np.ndarray,
                  scale: float) -> np.ndarray:
    """(T,) robust scale of each track's normalised residuals (1.4826 MAD about 0 of the
    ``usable`` rows; rows sorted by track ``pid``), never below ``scale``, the scale over
    all tracks; ``scale`` for a track of fewer than :data:`TRACK_SCALE_MIN_POINTS`
    usable rows."""
    a = pd.Series(np.where(usable, np.abs(resid), np.nan))
    g = a.groupby(pid, sort=False)
    own = 1.4826 * g.median().to_numpy()
    enough = g.count().to_numpy() >= TRACK_SCALE_MIN_POINTS
    return np.where(enough & np.isfinite(own), np.maximum(own, scale), scale)


def _rejected(resid: np.ndarray, limit, eligible: np.ndarray, pid: np.ndarray,
              lengths: np.ndarray) -> np.ndarray:
    """Rows of ``eligible`` whose finite ``|resid|`` exceeds ``limit`` (a number or one
    per row), at most the worst third of each track (:func:`_worst_third`)."""
    bad = eligible & np.isfinite(resid) & (np.abs(resid) > limit)
    return _worst_third(bad, np.abs(np.nan_to_num(resid)), pid, lengths)


def _worst_third(bad: np.ndarray, score: np.ndarray, pid: np.ndarray,
                 lengths: np.ndarray) -> np.ndarray:
    """``bad`` limited to the ``floor(n / 3)`` highest-``score`` rows of each track of
    ``n`` rows (rows sorted by track): a track keeps at least two thirds of its points,
    enough for every window to fit its degree."""
    if not bad.any():
        return bad
    n = len(bad)
    order = np.lexsort((-score, pid))            # by track, worst first
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n) - np.repeat(starts, lengths)
    return bad & (rank < np.repeat(lengths // 3, lengths))


def smooth_tracks(linked: pd.DataFrame, settings: TrackSettings = TrackSettings()) -> pd.DataFrame:
    """Smoothed positions, velocities and accelerations along every track.

    Parameters
    ----------
    linked : DataFrame
        Columns ``frame, particle, x, y, z`` (mm) and optionally ``sigma_x, sigma_y,
        sigma_z`` (mm; missing or non-positive sigmas count as equal weights). Not changed.
    settings : TrackSettings
        ``window``, ``order``, ``clip`` and ``min_length``.

    Returns
    -------
    DataFrame
        ``linked`` (tracks shorter than ``min_length`` dropped), sorted by particle and
        frame, with columns ``x_smooth, y_smooth, z_smooth`` (mm), ``sigma_x_smooth``,
        ``sigma_y_smooth``, ``sigma_z_smooth`` (mm), ``velocity_x, velocity_y,
        velocity_z`` (mm per frame), ``acceleration_x, acceleration_y, acceleration_z``
        (mm per frame^2; 0 where the fit is linear), ``speed`` (mm per frame), with a
        frame interval also ``speed_m_per_s``, ``track_length`` (points) and ``outlier``
        (True for points rejected from the fits in any coordinate). Its
        ``attrs["plenoptrack"]`` (the provenance :func:`plenoptrack.io.write_table` stores)
        is that of ``linked`` with a ``tracking`` record added (:func:`tracking_record`).

    Notes
    -----
    For each row the ``window`` points of its track nearest in time (fewer in a shorter
    track) are fitted by weighted least squares with a polynomial of degree ``order``
    in ``frame - frame_row``, weights ``1 / sigma^2``; the constant term is the smoothed
    position, the linear term the velocity, twice the quadratic term the acceleration.
    With ``clip > 0`` the residuals of each coordinate, normalised by
    ``sigma sqrt(1 - h)`` (``h`` the point's weight in its own fit; a point left out by
    its sigma and the fit's uncertainty where it stands), are compared with ``clip``
    times their robust scale: ``s`` (1.4826 MAD over all rows), or the track's own
    where that is larger (from at least :data:`TRACK_SCALE_MIN_POINTS` points: how much
    of a sigma shows as scatter differs from particle to particle); points beyond are
    given weight 0, the windows made up again from the other points (:func:`_windows`
    with ``keep``) and the fits repeated (three rounds). The rounds start from the
    points beyond ``clip`` times the robust scale of their residuals from a Theil-Sen
    line through their window (:func:`_robust_line`), not from an unweighted
    least-squares fit, which two neighbouring far-off points (another particle's, a
    ghost on the line of sight) can pull onto them so that their good neighbours are
    rejected instead; at most a third of a track's points are rejected (the worst), and
    tracks shorter than ``order + 4`` points keep every point. The smoothed sigma is
    ``s sqrt(sum L_j^2 sigma_j^2)`` (``L`` the fit's weights) when ``s >= 1``: ``s``
    rescales the locator's sigmas to the scatter the tracks show. When ``s < 1`` the rest
    of each sigma is error that the track does not show as scatter (kept from frame to
    frame) and is not averaged away
    (:func:`_smoothed_sigma`).
    """
    cols = [T_COLUMN, ID_COLUMN, *POS_COLUMNS]
    missing = [c for c in cols if c not in linked.columns]
    if missing:
        raise InputFileError(f"tracks table has no column(s) {missing}; link particles first "
                             "(`plenoptrack track`)")
    df = linked.sort_values([ID_COLUMN, T_COLUMN], kind="stable").reset_index(drop=True)
    sizes = df.groupby(ID_COLUMN, sort=False)[T_COLUMN].transform("size").to_numpy()
    df = df[sizes >= settings.min_length].reset_index(drop=True)
    pid = df[ID_COLUMN].to_numpy(np.int64)
    t = df[T_COLUMN].to_numpy(float)
    n = len(df)
    change = np.flatnonzero(np.diff(pid)) + 1 if n else np.zeros(0, np.int64)
    starts = np.concatenate([[0], change]).astype(np.int64) if n else np.zeros(0, np.int64)
    lengths = np.diff(np.concatenate([starts, [n]])).astype(np.int64)
    candidates = _window_candidates(settings, int(lengths.max(initial=1)))
    window_idx = {k: _windows(t, starts, lengths, k) for k in candidates}
    idx = window_idx[settings.window]
    chosen = {}
    out = {}
    outlier = np.zeros(n, dtype=bool)
    # too short to tell an outlier from the track: no rejection
    long_track = lengths.repeat(lengths) >= settings.order + 4 if n else np.zeros(0, bool)
    for axis, c in enumerate(POS_COLUMNS):
        y = df[c].to_numpy(float)
        sig_name = SIGMA_COLUMNS[axis]
        sigma = df[sig_name].to_numpy(float) if sig_name in df.columns else np.ones(n)
        good = np.isfinite(sigma) & (sigma > 0)
        fill = np.median(sigma[good]) if good.any() else 1.0
        sigma = np.where(good, sigma, fill)
        w0 = 1.0 / sigma ** 2
        w = w0.copy()
        scale = 1.0
        if settings.clip > 0:
            # Start from a fit that far-off points cannot pull: two neighbouring points on
            # another particle would drag a least-squares start onto them, and their good
            # neighbours would then be the ones rejected.
            start = _robust_line(t, y, idx, settings.order) / sigma
            ok = np.isfinite(start)
            if ok.sum() >= 3:
                s0 = float(1.4826 * np.median(np.abs(start[ok])))
                if s0 > 0:
                    bad = _rejected(start, settings.clip * s0, long_track, pid, lengths)
                    w = np.where(bad, 0.0, w0)
        window = _press_window(t, y, sigma, w, window_idx, settings.order)
        chosen[c] = window
        idx = window_idx[window]
        fitted = None                   # the weights of the latest fit
        for _round in range(3 if settings.clip > 0 else 1):
            idx_fit = _kept_windows(idx, t, starts, lengths, window, w > 0)
            coef, L, _ = _local_fit(t, y, w, idx_fit, settings.order)
            fitted = w
            h = _leverage(idx_fit, L)
            # a point in its own fit scatters about it by sigma sqrt(1 - h); one left out
            # by its own sigma and the fit's uncertainty where it stands
            used = idx_fit >= 0
            fit_var = (L ** 2 * np.where(used, sigma[np.where(used, idx_fit, 0)], 0.0) ** 2
                       ).sum(axis=1)
            resid = (y - coef[:, 0]) / np.where(
                w > 0, sigma * np.sqrt(np.clip(1.0 - h, 1e-3, None)),
                np.sqrt(sigma ** 2 + fit_var))
            fit_ok = np.isfinite(resid) & (w > 0) & (h < 0.999)
            if fit_ok.sum() >= 3:
                scale = float(1.4826 * np.median(np.abs(resid[fit_ok])))
                scale = scale if scale > 0 else 1.0
            if settings.clip <= 0:
                break
            limit = settings.clip * _track_scales(resid, fit_ok, pid, scale).repeat(lengths)
            bad = _rejected(resid, limit, long_track, pid, lengths)
            new_w = np.where(bad, 0.0, w0)
            if np.array_equal(new_w, w):
                break
            w = new_w
        if fitted is not w:             # the last round's rejections: fit without them
            idx_fit = _kept_windows(idx, t, starts, lengths, window, w > 0)
            coef, L, _ = _local_fit(t, y, w, idx_fit, settings.order)
        lost = np.isnan(coef[:, 0])
        if lost.any():     # every point of the window rejected: fit them all, unweighted by it
            coef_all, L_all, _ = _local_fit(t, y, w0, idx, settings.order)
            coef[lost], L[lost] = coef_all[lost], L_all[lost]
            idx_fit = np.where(lost[:, None], idx, idx_fit)
        outlier |= w == 0
        valid = idx_fit >= 0
        sig_win = np.where(valid, sigma[np.where(valid, idx_fit, 0)], 0.0)
        out[SMOOTH_COLUMNS[axis]] = coef[:, 0]
        out[SMOOTH_SIGMA_COLUMNS[axis]] = _smoothed_sigma(L, sig_win, scale,
                                                          measured=sig_name in df.columns)
        out[VELOCITY_COLUMNS[axis]] = coef[:, 1] if coef.shape[1] > 1 else np.zeros(n)
        out[ACCELERATION_COLUMNS[axis]] = 2 * coef[:, 2] if coef.shape[1] > 2 else np.zeros(n)
        out[f"_scale_{c}"] = np.full(n, scale)
    res = df.assign(**{k: v for k, v in out.items() if not k.startswith("_")})
    v = res[list(VELOCITY_COLUMNS)].to_numpy(float)
    res["speed"] = np.sqrt((v ** 2).sum(axis=1))
    if settings.frame_interval_s is not None:
        res["speed_m_per_s"] = res["speed"] / settings.frame_interval_s * 1e-3
    res["track_length"] = lengths.repeat(lengths) if n else np.zeros(0, np.int64)
    res["outlier"] = outlier
    scale = {c: float(out[f"_scale_{c}"][0]) if n else float("nan") for c in POS_COLUMNS}
    res.attrs = {METADATA_KEY: {**(linked.attrs.get(METADATA_KEY) or {}),
                                "tracking": {"settings": settings.to_dict(),
                                             "scatter_scale": scale, "windows": chosen}}}
    return res


def tracking_record(tracks: pd.DataFrame) -> dict:
    """The tracking part of a tracks table's provenance: ``settings`` and
    ``scatter_scale`` (per axis, the tracks' scatter over the locator's sigmas); {} when
    absent."""
    return (tracks.attrs.get(METADATA_KEY) or {}).get("tracking") or {}


def depth_scatter_ratio(tracks: pd.DataFrame) -> float:
    """Estimated per-frame depth scatter over track-smoothed depth scatter (median over rows).

    The per-frame scatter of a row is its ``sigma_z``, times the tracks' scatter scale
    (:func:`tracking_record`) where that is above 1 (where it is below, the rest of the
    sigma is error kept from frame to frame, :func:`smooth_tracks`); the smoothed one is
    ``sigma_z_smooth``. Without ``sigma_z`` every row counts as equally uncertain.
    """
    if len(tracks) == 0:
        return float("nan")
    scale = tracking_record(tracks).get("scatter_scale", {}).get("z", 1.0)
    sig = tracks["sigma_z"].to_numpy(float) if "sigma_z" in tracks.columns else None
    smooth = tracks["sigma_z_smooth"].to_numpy(float)
    if sig is None:
        # equal weights: per-frame scatter is the scale itself (sigma = 1 after filling)
        sig = np.ones(len(tracks))
    else:
        scale = max(scale, 1.0)
    ok = np.isfinite(sig) & np.isfinite(smooth) & (smooth > 0)
    return float(np.median(scale * sig[ok] / smooth[ok])) if ok.any() else float("nan")


# --------------------------------------------------------------------------------------
# statistics


def track_statistics(tracks: pd.DataFrame, *, frame_interval_s: float | None = None) -> pd.DataFrame:
    """One row per track: extent in time, mean position, speed, size and shape.

    Parameters
    ----------
    tracks : DataFrame
        Output of :func:`smooth_tracks`.
    frame_interval_s : float, optional
        Time between frames, s; adds ``speed_m_per_s`` (the mean speed).

    Returns
    -------
    DataFrame
        Columns ``particle``, ``n_frames``, ``first_frame``, ``last_frame``, ``x, y, z``
        (mean smoothed position, mm), ``velocity_x, velocity_y, velocity_z`` (mean, mm
        per frame), ``speed`` (mean, mm per frame), ``speed_sd`` (mm per frame),
        ``acceleration`` (mean magnitude, mm per frame^2), ``n_outliers``; with the
        locator's size columns also ``diameter`` (median equivalent diameter, mm),
        ``major_axis``, ``minor_axis`` (median, mm), ``aspect`` (median major over minor)
        and ``orientation`` (axial mean, rad); with a ``pieces`` column
        (:func:`plenoptrack.pieces.merge_pieces`) also ``pieces``, the most pieces of one
        body found in one frame (1 for a particle always found whole).
    """
    need = [ID_COLUMN, T_COLUMN, *SMOOTH_COLUMNS, *VELOCITY_COLUMNS, "speed"]
    missing = [c for c in need if c not in tracks.columns]
    if missing:
        raise InputFileError(f"tracks table has no column(s) {missing}; make it with "
                             "`plenoptrack track` (or smooth_tracks)")
    df = tracks.copy()
    acc = df[list(ACCELERATION_COLUMNS)].to_numpy(float) if set(ACCELERATION_COLUMNS) <= set(
        df.columns) else np.zeros((len(df), 3))
    df["_acc"] = np.sqrt((acc ** 2).sum(axis=1))
    df["_out"] = df["outlier"].astype(int) if "outlier" in df.columns else 0
    g = df.groupby(ID_COLUMN, sort=True)
    stats = pd.DataFrame({
        "n_frames": g[T_COLUMN].size(), "first_frame": g[T_COLUMN].min(),
        "last_frame": g[T_COLUMN].max(),
        **{c: g[s].mean() for c, s in zip(POS_COLUMNS, SMOOTH_COLUMNS)},
        **{c: g[c].mean() for c in VELOCITY_COLUMNS},
        "speed": g["speed"].mean(), "speed_sd": g["speed"].std(ddof=1).fillna(0.0),
        "acceleration": g["_acc"].mean(), "n_outliers": g["_out"].sum()})
    if frame_interval_s is not None:
        stats["speed_m_per_s"] = stats["speed"] / frame_interval_s * 1e-3
    if "diameter" in df.columns:
        stats["diameter"] = g["diameter"].median()
    if "major_axis" in df.columns and "minor_axis" in df.columns:
        stats["major_axis"] = g["major_axis"].median()
        stats["minor_axis"] = g["minor_axis"].median()
        with np.errstate(divide="ignore", invalid="ignore"):
            df["_aspect"] = df["major_axis"] / df["minor_axis"]
        stats["aspect"] = df.groupby(ID_COLUMN, sort=True)["_aspect"].median()
    if PIECES_COLUMN in df.columns:
        stats[PIECES_COLUMN] = g[PIECES_COLUMN].max()
    if "orientation" in df.columns:
        th = df["orientation"].to_numpy(float)
        df["_c2"], df["_s2"] = np.cos(2 * th), np.sin(2 * th)
        g2 = df.groupby(ID_COLUMN, sort=True)
        stats["orientation"] = 0.5 * np.arctan2(g2["_s2"].mean(), g2["_c2"].mean())
    return stats.reset_index()


# --------------------------------------------------------------------------------------
# the whole step


@dataclass(frozen=True)
class TrackResult:
    """Tracks of a particles table.

    Attributes
    ----------
    tracks : DataFrame
        One row per particle and frame (:func:`smooth_tracks`).
    statistics : DataFrame
        One row per track (:func:`track_statistics`).
    n_input : int
        Rows of the particles table.
    depth_scatter_ratio : float
        Estimated per-frame over smoothed depth scatter (:func:`depth_scatter_ratio`).
    settings : TrackSettings
    n_too_uncertain : int
        Rows of the particles table left out of linking as too uncertain
        (:func:`too_uncertain_to_link`).
    n_pieces_merged : int
        Tracks merged into another as pieces of one body (:mod:`plenoptrack.pieces`).
    n_swaps_repaired : int
        Pairs of tracks whose tails were exchanged (:mod:`plenoptrack.swaps`).
    """

    tracks: pd.DataFrame
    statistics: pd.DataFrame
    n_input: int
    depth_scatter_ratio: float
    settings: TrackSettings
    n_too_uncertain: int = 0
    n_pieces_merged: int = 0
    n_swaps_repaired: int = 0

    def summary(self) -> dict:
        """Numbers for a report: counts, lengths, speeds and the depth refinement."""
        st = self.statistics
        out = {"particles in": self.n_input,
               "too uncertain to link (sigma > search range)": self.n_too_uncertain,
               "tracks": len(st),
               "tracks merged as pieces of one body": self.n_pieces_merged,
               "track tails exchanged (swapped particles)": self.n_swaps_repaired,
               "points in tracks": len(self.tracks),
               "mean track length (frames)": float(st["n_frames"].mean()) if len(st) else 0.0,
               "outliers rejected": int(self.tracks["outlier"].sum()) if len(self.tracks) else 0,
               "median speed (mm/frame)": float(st["speed"].median()) if len(st) else float("nan"),
               "depth scatter, per frame / track-smoothed (estimated)": self.depth_scatter_ratio}
        if self.settings.frame_interval_s is not None and len(st):
            out["median speed (m/s)"] = float(st["speed_m_per_s"].median())
        return out


def track_particles(particles: pd.DataFrame, settings: TrackSettings = TrackSettings()) -> TrackResult:
    """Link, repair swapped tracks, merge the pieces of one body, smooth and summarise:
    :func:`link_particles`, :func:`plenoptrack.swaps.repair_swaps` (with
    ``settings.repair_swaps``), :func:`plenoptrack.pieces.merge_pieces` (with
    ``settings.merge_pieces``), :func:`smooth_tracks`, :func:`track_statistics`.

    Examples
    --------
    >>> import numpy as np, pandas as pd
    >>> f = np.repeat(np.arange(6), 2)
    >>> p = pd.DataFrame({"frame": f, "x": np.tile([0.0, 5.0], 6) + 0.5 * f,
    ...                   "y": 0.0, "z": np.tile([0.0, 2.0], 6)})
    >>> result = track_particles(p)
    >>> len(result.statistics), round(float(result.statistics["speed"].iloc[0]), 3)
    (2, 0.5)
    """
    linked = link_particles(particles, settings)
    n_swaps = 0
    if settings.repair_swaps:
        linked, n_swaps = repair_swaps(linked, search_range_mm=settings.search_range_mm,
                                       degree=settings.order, window=settings.window,
                                       clip=settings.clip)
    n_merged = 0
    if settings.merge_pieces:
        pairs = piece_pairs(linked, touch_sigma=settings.piece_touch_sigma,
                            velocity_p=settings.piece_velocity_p)
        n_tracks = linked[ID_COLUMN].nunique()
        linked = merge_pieces(linked, pairs)
        n_merged = n_tracks - linked[ID_COLUMN].nunique()
    tracks = smooth_tracks(linked, settings)
    stats = track_statistics(tracks, frame_interval_s=settings.frame_interval_s)
    return TrackResult(tracks=tracks, statistics=stats, n_input=len(particles),
                       depth_scatter_ratio=depth_scatter_ratio(tracks), settings=settings,
                       n_too_uncertain=int(too_uncertain_to_link(particles, settings).sum()),
                       n_pieces_merged=n_merged, n_swaps_repaired=n_swaps)
