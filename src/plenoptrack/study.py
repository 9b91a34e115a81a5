"""Translation-stage uncertainty study: accuracy and precision of depth against depth.

The experiment of section 3 of the method paper, simulated: a rigid field of pin heads
(spheres with a stem, specular highlights, random orientation) is moved along the optical
axis by a traverse in steps of ``step_mm`` over ``travel_mm``, and imaged ``repeats``
times at every position with fresh sensor noise. The traverse zero sits an unknown
distance from the focal plane, as on a real bench. Every image is located with each
method; each particle is matched across positions by its lateral position (the field is
rigid); per particle, measured ``z`` against traverse position ``p`` is fitted by a line of
slope 1 with a free intercept ``b``; the residual ``z - p - b`` is the depth displacement
error. Binned by depth (``p + b``), its mean is the accuracy and its standard deviation
the precision, each with 99 % confidence bounds; both are also given normalised (depth by
the near and far limits of the plenoptic depth of field, error by the object-space
microlens pitch), as in figures 9-11 of the paper.

Layers: :func:`study_field` (the rigid field), :func:`traverse_positions`,
:func:`depth_errors` (matching and the slope-1 fit), :func:`binned_statistics`
(accuracy and precision per bin), :func:`summarise`; :func:`run_study` simulates,
calibrates and locates (local Dask worker processes, resumable) and writes
``summary.json``, ``comparison.md`` and the figures.

Nothing here is on the locate path: the study builds its data with the simulator and
locates it with the public locators, which never see the truth.

References
----------
E. M. Hall, D. R. Guildenbecher, B. S. Thurow, Opt. Express 27 (2019) (``seeds/001``),
section 3 and figures 9-11.
"""

from __future__ import annotations

import itertools
import json
import math
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from ._columns import ID_COLUMN, T_COLUMN
from .camera import CameraSpec, _matched_f_number
from .errors import NoParticlesWarning, SettingsError
from .io import atomic_write_text, read_table, write_table

__all__ = ["StudyConfig", "METHODS", "PAPER", "paper_grid", "study_field",
           "traverse_positions", "coarse_to_fine", "depth_errors", "binned_statistics", "summarise",
           "comparison_table", "run_study", "report_study", "locate_image"]

METHODS = ("perspective", "refocus", "hybrid")
"""Locating methods of the study."""

PAPER = {
    "perspective": {"worst_abs_mean_mm": 0.1, "worst_std_mm": 0.4, "seconds_per_image": 10.0,
                    "memory_gb": 0.2, "relative_accuracy": 0.002},
    "refocus": {"worst_abs_mean_mm": 0.2, "worst_std_mm": 1.8, "seconds_per_image": 3600.0,
                "memory_gb": 2.0, "relative_accuracy": 0.004},
}
"""The paper's figures (section 3-4 of ``seeds/001``): accuracy within 0.1 mm (0.2 % of
50 mm) against about 0.4 % (0.2 mm), precision within 0.4 mm against up to 1.8 mm,
about 10 s and 0.2 GB per image against about an hour and 2 GB (MATLAB, 12 cores)."""


@dataclass(frozen=True)
class StudyConfig:
    """One configuration of the study.

    Parameters
    ----------
    camera : CameraSpec
        Nominal camera (magnification, object distance, particle-size scale).
    travel_mm, step_mm : float
        Traverse travel and step, mm (positions ``0, step, ..., travel``).
    repeats : int
        Images per position (fresh noise each).
    refocus_repeats : int, optional
        Repeats located with the refocusing and hybrid methods (the first ones); default
        ``repeats``. The refocusing method is the slow one.
    methods : tuple of str
        Subset of :data:`METHODS`.
    n_particles : int
        Pin heads in the field.
    diameter_mm : float, optional
        Head diameter, mm; default the camera preset's particle size.
    stems : bool
        Give every head a stem (a thin prolate spheroid behind it, random direction
        within 60 degrees of the optical axis); False: bare spheres.
    field_depth_mm : float
        Depth extent of the field itself, mm.
    realism : {"realistic", "ideal"}
        Simulator optics.
    seed : int
        Master seed (field, zero offset, optics, noise).
    bin_mm : float, optional
        Width of the depth bins, mm; default ``max(step, travel / 25)``.
    name : str, optional
        Label of the configuration; default from the camera.
    card_tilt : bool
        Calibrate with each dot card's tilt on its mount measured from its dots' parallax
        and applied (:func:`~plenoptrack.calibrate.calibrate` ``card_tilt``); the
        simulated cards are tilted by up to 0.5 degrees with realistic optics.
    """

    camera: CameraSpec
    travel_mm: float = 50.0
    step_mm: float = 1.0
    repeats: int = 5
    refocus_repeats: int | None = None
    methods: tuple[str, ...] = ("perspective", "refocus")
    n_particles: int = 40
    diameter_mm: float | None = None
    stems: bool = True
    field_depth_mm: float = 6.0
    realism: str = "realistic"
    seed: int = 0
    bin_mm: float | None = None
    name: str | None = None
    card_tilt: bool = False

    def __post_init__(self) -> None:
        if not (self.travel_mm > 0 and self.step_mm > 0 and self.step_mm <= self.travel_mm):
            raise SettingsError(f"travel and step must be positive with step <= travel; got "
                                f"travel {self.travel_mm}, step {self.step_mm}")
        if self.repeats < 1:
            raise SettingsError(f"repeats must be at least 1; got {self.repeats}")
        if self.refocus_repeats is not None and not 1 <= self.refocus_repeats <= self.repeats:
            raise SettingsError(f"refocus repeats must be between 1 and repeats ({self.repeats}); "
                                f"got {self.refocus_repeats}")
        bad = [m for m in self.methods if m not in METHODS]
        if bad or not self.methods:
            raise SettingsError(f"methods must be a non-empty subset of {METHODS}; got "
                                f"{list(self.methods)}")
        if self.n_particles < 1:
            raise SettingsError(f"n_particles must be at least 1; got {self.n_particles}")
        if self.realism not in ("realistic", "ideal"):
            raise SettingsError(f"realism must be 'realistic' or 'ideal'; got {self.realism!r}")
        if not self.field_depth_mm >= 0:
            raise SettingsError(f"field_depth_mm must be >= 0; got {self.field_depth_mm}")

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        suffix = f"_M{abs(self.camera.magnification):g}_F{self.camera.focal_length_mm:g}"
        if self.camera.name.endswith(suffix):  # a camera of paper_grid is named so already
            return self.camera.name
        return self.camera.name + suffix

    @property
    def n_repeats(self) -> dict:
        """Repeats located per method."""
        slow = self.repeats if self.refocus_repeats is None else self.refocus_repeats
        return {m: (self.repeats if m == "perspective" else slow) for m in self.methods}

    @property
    def bin_width_mm(self) -> float:
        return self.bin_mm if self.bin_mm is not None else max(self.step_mm, self.travel_mm / 25)

    @property
    def head_diameter_mm(self) -> float:
        from .simulate.scene import default_diameter_mm
        return self.diameter_mm if self.diameter_mm is not None else default_diameter_mm(self.camera)

    @property
    def calibration_depth_mm(self) -> tuple[float, float]:
        """Depth range the dot cards span: every position of every head, plus a margin."""
        half = 0.5 * (self.travel_mm + self.field_depth_mm) + 2.0
        return (-half, half)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["camera"] = self.camera.to_dict()
        d["methods"] = list(self.methods)
        return d

    @classmethod
    def from_dict(cls, data: dict) -> "StudyConfig":
        """Inverse of :meth:`to_dict` (e.g. a study folder's ``config.json``)."""
        d = dict(data)
        d["camera"] = CameraSpec.from_dict(d["camera"], source="study config")
        d["methods"] = tuple(d["methods"])
        return cls(**d)


def paper_grid(camera: CameraSpec, *, magnifications=(0.25, 0.4, 0.5, 0.75),
               focal_lengths_mm=(85.0, 105.0, 135.0)) -> list[CameraSpec]:
    """The paper's 12 configurations: 4 magnifications (up to 0.75) at 3 object distances.

    The object distance is changed through the main-lens focal length at each
    magnification (``s_o = F (1 + 1/|M|)``), with the f-number matched to the
    microlenses; the paper's exact distances are not in its text, so these focal
    lengths are a stand-in spanning a similar range.
    """
    out = []
    for f in focal_lengths_mm:
        for m in magnifications:
            c = camera.with_changes(focal_length_mm=float(f), magnification=-float(m),
                                    f_number=round(_matched_f_number(
                                        float(f), -float(m), camera.microlens_pitch_um,
                                        camera.microlens_focal_length_um), 4),
                                    name=f"{camera.name}_M{m:g}_F{f:g}")
            out.append(c)
    return out


# --- the rigid field ------------------------------------------------------------------

def coarse_to_fine(n: int) -> np.ndarray:
    """Indices ``0`` to ``n - 1`` ordered coarse to fine (the ends, the middle, the quarters,
    ...), so that any leading part of the order spans the whole range evenly."""
    order, seen = [], set()
    step = 1 << max(n - 1, 1).bit_length()
    while step >= 1:
        for i in range(0, n, step):
            if i not in seen:
                seen.add(i)
                order.append(i)
        if step == 1:
            break
        step //= 2
    if n - 1 not in seen and n > 0:
        order.insert(1, n - 1)
    return np.array(order, dtype=np.int64)


def traverse_positions(travel_mm: float, step_mm: float) -> np.ndarray:
    """Traverse positions ``0, step, ..., travel`` (mm)."""
    n = int(math.floor(travel_mm / step_mm + 1e-9)) + 1
    return np.arange(n) * step_mm


def study_field(config: StudyConfig) -> tuple[pd.DataFrame, float]:
    """The rigid field at traverse position 0 and the traverse zero offset.

    Returns
    -------
    field : DataFrame
        Columns ``particle, x, y, z, diameter`` (mm, world frame, with the zero offset
        applied) and the shape columns ``shape, aspect, axis_x, axis_y, axis_z``; heads
        are spheres (ids ``0 .. n-1``), stems prolate spheroids (ids ``n ..``). At
        traverse position ``p`` every z is ``z + p``.
    zero_offset_mm : float
        Distance of the traverse zero from its nominal place (unknown to the analysis).
    """
    from .simulate.scene import default_volume

    rng = np.random.default_rng([config.seed, 71])
    cam = config.camera
    d = config.head_diameter_mm
    lo, hi = config.calibration_depth_mm
    vol = default_volume(cam, depth_mm=hi - lo, diameter_mm=d)
    offset = float(rng.uniform(-1.0, 1.0))
    half_field = 0.5 * config.field_depth_mm
    spacing = 3.0 * d
    heads = []
    for _ in range(200 * config.n_particles):
        if len(heads) == config.n_particles:
            break
        # stay a stem length inside the lateral limits
        x = rng.uniform(vol.x_mm[0] * 0.85, vol.x_mm[1] * 0.85)
        y = rng.uniform(vol.y_mm[0] * 0.85, vol.y_mm[1] * 0.85)
        if heads and np.min(np.hypot(np.array(heads)[:, 0] - x, np.array(heads)[:, 1] - y)) < spacing:
            continue
        heads.append((x, y, rng.uniform(-half_field, half_field)))
    if len(heads) < config.n_particles:
        raise SettingsError(f"only {len(heads)} of {config.n_particles} pin heads fit in the field "
                            f"at a lateral spacing of {spacing:g} mm; ask for fewer particles")
    heads = np.array(heads)
    z0 = heads[:, 2] - 0.5 * config.travel_mm + offset
    n = len(heads)
    field = pd.DataFrame({ID_COLUMN: np.arange(n), "x": heads[:, 0], "y": heads[:, 1], "z": z0,
                          "diameter": d, "shape": "sphere", "aspect": 1.0,
                          "axis_x": 0.0, "axis_y": 0.0, "axis_z": 1.0})
    if config.stems:
        # a pin: stem 0.3 head diameters thick, 4 head diameters long, pointing away
        # from the camera into the foam within 60 degrees of the axis
        theta = np.arccos(rng.uniform(math.cos(math.radians(60)), 1.0, n))
        phi = rng.uniform(0, 2 * math.pi, n)
        axis = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                                np.cos(theta)])
        a = 2.0 * d            # long semi-axis
        b = 0.15 * d           # short semi-axes
        centre = np.column_stack([heads[:, 0], heads[:, 1], z0]) + axis * (0.45 * d + a)
        stems = pd.DataFrame({ID_COLUMN: n + np.arange(n), "x": centre[:, 0], "y": centre[:, 1],
                              "z": centre[:, 2], "diameter": 2.0 * (a * b * b) ** (1 / 3),
                              "shape": "ellipsoid", "aspect": a / b, "axis_x": axis[:, 0],
                              "axis_y": axis[:, 1], "axis_z": axis[:, 2]})
        field = pd.concat([field, stems], ignore_index=True)
    from .simulate.scene import particle_silhouettes

    sil = particle_silhouettes(field)
    return field.assign(**{c: sil[c].to_numpy() for c in sil.columns}), offset


def _frame_particles(field: pd.DataFrame, position_mm: float, frame: int) -> pd.DataFrame:
    out = field.assign(z=field["z"] + position_mm)
    out.insert(0, T_COLUMN, frame)
    return out


# --- analysis ---------------------------------------------------------------------------

def depth_errors(measured: pd.DataFrame, *, match_mm: float, min_positions: int = 3,
                 depth_scale_mm: float | None = None) -> pd.DataFrame:
    """Match particles across positions and fit ``z = p + b`` per particle.

    Parameters
    ----------
    measured : DataFrame
        One row per located particle: ``position_mm`` (traverse position), ``repeat``,
        ``x, y, z`` (mm).
    match_mm : float
        Two measurements are the same particle when their lateral positions lie within
        this distance (the field is rigid and moves along z only).
    min_positions : int
        Particles measured at fewer distinct positions are dropped.
    depth_scale_mm : float, optional
        Largest difference between a measurement's ``z - p`` and its particle's, mm, the
        depth half-axis of the matching ellipsoid (see Notes); default ``3 * match_mm``.

    Returns
    -------
    DataFrame
        The input rows kept, with ``particle`` (matched identity), ``intercept_mm`` (its
        fitted ``b``), ``depth_mm`` (``position_mm + b``, the line's depth at that
        position) and ``error_mm`` (``z - position_mm - b``).

    Notes
    -----
    Matching takes two passes. The first builds the particles from lateral positions
    alone: the images are visited from the one with the most measurements down, and each
    measurement joins the nearest particle within ``match_mm`` that no nearer
    measurement of its image took, or starts a new one. The second gives each particle
    of at least ``min_positions`` positions its median lateral position and its median
    ``z - p``, and matches every image's measurements to these particles one to one
    (:func:`scipy.optimize.linear_sum_assignment`) at the cost ``(lateral distance /
    match_mm)^2 + (depth difference / depth_scale_mm)^2``, within the ellipsoid where
    that cost is at most 1 (as the accuracy matrix matches measured to true particles).
    Where two measurements lie at one particle's lateral position (a ghost on its line
    of sight, or a piece of it), the one whose depth agrees with the particle's line is
    its measurement, not the one that happens to lie a hundredth of a millimetre nearer,
    and a ghost millimetres off in depth is not taken as the measurement of a particle
    beside it that the image lacks. The depth half-axis (4.5 mm for the 1.5 mm of the
    hall2019 study) is many times the method's precision (0.1-0.3 mm), so only blunders
    fall outside it. Measurements no particle takes are dropped.
    """
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    cols = ["position_mm", "repeat", "x", "y", "z"]
    if measured.empty:
        return measured.assign(particle=pd.Series(dtype=np.int64), intercept_mm=np.nan,
                               depth_mm=np.nan, error_mm=np.nan)
    depth_scale = 3.0 * match_mm if depth_scale_mm is None else float(depth_scale_mm)
    df = measured.dropna(subset=["x", "y", "z"]).reset_index(drop=True)
    ident = np.full(len(df), -1, dtype=np.int64)
    refs = np.zeros((0, 2))
    counts = np.zeros(0)
    groups = sorted(df.groupby(["position_mm", "repeat"]).groups.items(),
                    key=lambda kv: -len(kv[1]))
    for _, rows in groups:
        rows = np.asarray(rows)
        xy = df.loc[rows, ["x", "y"]].to_numpy(float)
        taken = np.zeros(len(refs), dtype=bool)
        if len(refs):
            dist, j = cKDTree(refs).query(xy, distance_upper_bound=match_mm)
            order = np.argsort(dist)
            for k in order:
                if np.isfinite(dist[k]) and not taken[j[k]]:
                    taken[j[k]] = True
                    ident[rows[k]] = j[k]
                    refs[j[k]] = (refs[j[k]] * counts[j[k]] + xy[k]) / (counts[j[k]] + 1)
                    counts[j[k]] += 1
        new = rows[ident[rows] < 0]
        if len(new):
            ident[new] = len(refs) + np.arange(len(new))
            refs = np.vstack([refs, df.loc[new, ["x", "y"]].to_numpy(float)])
            counts = np.concatenate([counts, np.ones(len(new))])
    # second pass: each image matched one to one to the particles found, lateral position
    # and depth along the particle's line weighed together
    first = df.assign(particle=ident, offset=df["z"] - df["position_mm"])
    n_pos = first.groupby("particle")["position_mm"].nunique()
    particles = first[first["particle"].isin(n_pos.index[n_pos >= min_positions])].groupby(
        "particle")[["x", "y", "offset"]].median()
    ident = np.full(len(df), -1, dtype=np.int64)
    if len(particles):
        ref_xy = particles[["x", "y"]].to_numpy(float)
        ref_offset = particles["offset"].to_numpy(float)
        tree = cKDTree(ref_xy)
        for _, rows in groups:
            rows = np.asarray(rows)
            xy = df.loc[rows, ["x", "y"]].to_numpy(float)
            near = tree.sparse_distance_matrix(cKDTree(xy), match_mm, output_type="ndarray")
            if len(near) == 0:
                continue
            ref_used, row_used = np.unique(near["i"]), np.unique(near["j"])
            offset = (df.loc[rows[near["j"]], "z"].to_numpy(float)
                      - df.loc[rows[near["j"]], "position_mm"].to_numpy(float))
            pair_cost = ((near["v"] / match_mm) ** 2
                         + ((offset - ref_offset[near["i"]]) / depth_scale) ** 2)
            cost = np.full((len(ref_used), len(row_used)), np.inf)
            cost[np.searchsorted(ref_used, near["i"]), np.searchsorted(row_used, near["j"])] = (
                np.where(pair_cost <= 1.0, pair_cost, np.inf))      # inside the ellipsoid
            finite = np.where(np.isfinite(cost), cost, 1e12)      # assignment needs numbers
            r, c = linear_sum_assignment(finite)
            ok = np.isfinite(cost[r, c])
            ident[rows[row_used[c[ok]]]] = particles.index.to_numpy()[ref_used[r[ok]]]
    df = df.assign(particle=ident)
    df = df[df["particle"] >= 0]
    n_pos = df.groupby("particle")["position_mm"].nunique()
    df = df[df["particle"].isin(n_pos.index[n_pos >= min_positions])].copy()
    b = (df["z"] - df["position_mm"]).groupby(df["particle"]).transform("mean")
    df["intercept_mm"] = b
    df["depth_mm"] = df["position_mm"] + b
    df["error_mm"] = df["z"] - df["position_mm"] - b
    return df[[*cols, *[c for c in df.columns if c not in cols]]].reset_index(drop=True)


def binned_statistics(errors: pd.DataFrame, *, bin_mm: float, depth_limits_mm: tuple[float, float],
                      pitch_mm: float, confidence: float = 0.99, min_count: int = 5) -> pd.DataFrame:
    """Accuracy and precision per depth bin with confidence bounds.

    Parameters
    ----------
    errors : DataFrame
        From :func:`depth_errors` (``depth_mm``, ``error_mm``).
    bin_mm : float
        Bin width, mm; bins are aligned to multiples of ``bin_mm``.
    depth_limits_mm : (float, float)
        Near (< 0) and far (> 0) depth-of-field limits: depth is normalised by ``-near``
        below 0 and by ``far`` above (so the limits map to -1 and +1).
    pitch_mm : float
        Object-space microlens pitch: errors are normalised by it.
    confidence : float
        Two-sided confidence of the bounds (0.99: 99 %).
    min_count : int
        Bins with fewer measurements are left out.

    Returns
    -------
    DataFrame
        One row per bin: ``depth_mm`` (bin centre), ``n``, ``mean_mm`` and its bounds
        ``mean_lo_mm, mean_hi_mm`` (Student t), ``std_mm`` and its bounds ``std_lo_mm,
        std_hi_mm`` (chi-square), ``depth_norm`` and the normalised ``mean_norm``,
        ``mean_lo_norm``, ``mean_hi_norm``, ``std_norm``, ``std_lo_norm``, ``std_hi_norm``.
    """
    near, far = depth_limits_mm
    cols = ["depth_mm", "n", "mean_mm", "mean_lo_mm", "mean_hi_mm", "std_mm", "std_lo_mm",
            "std_hi_mm"]
    if errors.empty:
        return pd.DataFrame(columns=cols + ["depth_norm"])
    k = np.floor(errors["depth_mm"].to_numpy(float) / bin_mm + 0.5).astype(np.int64)
    g = errors.groupby(k)["error_mm"]
    out = pd.DataFrame({"depth_mm": g.mean().index.to_numpy() * bin_mm, "n": g.size().to_numpy(),
                        "mean_mm": g.mean().to_numpy(), "std_mm": g.std(ddof=1).to_numpy()})
    out = out[out["n"] >= min_count].reset_index(drop=True)
    n = out["n"].to_numpy(float)
    a = 1 - confidence
    half = stats.t.ppf(1 - a / 2, n - 1) * out["std_mm"] / np.sqrt(n)
    out["mean_lo_mm"] = out["mean_mm"] - half
    out["mean_hi_mm"] = out["mean_mm"] + half
    var = out["std_mm"] ** 2 * (n - 1)
    out["std_lo_mm"] = np.sqrt(var / stats.chi2.ppf(1 - a / 2, n - 1))
    out["std_hi_mm"] = np.sqrt(var / stats.chi2.ppf(a / 2, n - 1))
    z = out["depth_mm"].to_numpy(float)
    out["depth_norm"] = np.where(z < 0, z / -near, z / far)
    for c in ("mean", "mean_lo", "mean_hi", "std", "std_lo", "std_hi"):
        out[f"{c}_norm"] = out[f"{c}_mm"] / pitch_mm
    return out[cols + [c for c in out.columns if c not in cols]]


def summarise(errors: pd.DataFrame, bins: pd.DataFrame, images: pd.DataFrame) -> dict:
    """The summary of one method in one configuration.

    ``images`` has one row per located image: ``n`` (particles found), ``seconds``,
    ``peak_mb``. Returns worst ``|mean|`` and worst standard deviation over the depth
    bins (mm; bins with at least ``min_count`` measurements), the depth range of all
    matched measurements (mm), matched particles, detections per position (mean over
    images), images, seconds and peak memory per image.
    """
    def worst(col):
        return float(bins[col].abs().max()) if len(bins) else float("nan")

    def at_worst(col):
        return float(bins["depth_mm"].iloc[int(bins[col].abs().argmax())]) if len(bins) else float("nan")

    return {
        "worst_abs_mean_mm": worst("mean_mm"), "worst_abs_mean_at_mm": at_worst("mean_mm"),
        "worst_std_mm": worst("std_mm"), "worst_std_at_mm": at_worst("std_mm"),
        "worst_abs_mean_norm": worst("mean_norm") if "mean_norm" in bins else float("nan"),
        "worst_std_norm": worst("std_norm") if "std_norm" in bins else float("nan"),
        "depth_range_mm": ([float(errors["depth_mm"].min()), float(errors["depth_mm"].max())]
                           if len(errors) else None),
        "matched_particles": int(errors["particle"].nunique()) if len(errors) else 0,
        "measurements": int(len(errors)),
        "detections_per_position": float(images["n"].mean()) if len(images) else 0.0,
        "images": int(len(images)),
        "seconds_per_image": float(images["seconds"].mean()) if len(images) else float("nan"),
        "peak_mb_per_image": float(images["peak_mb"].max()) if len(images) else float("nan"),
    }


def comparison_table(summary: dict) -> str:
    """Markdown table of the study's figures next to the paper's."""
    lines = ["| configuration | method | repeats | worst abs(mean) mm | paper | worst std mm | "
             "paper | depth range mm | detections/position | s/image | paper s/image | "
             "peak MB/image | paper MB | std / perspective std (median, min over common bins) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for cfg, methods in summary["configurations"].items():
        for m, s in methods["methods"].items():
            p = PAPER.get(m, {})
            rng = s["depth_range_mm"]
            lines.append(
                f"| {cfg} | {m} | {s['repeats']} | {s['worst_abs_mean_mm']:.3f} | "
                f"{p.get('worst_abs_mean_mm', float('nan')):g} | {s['worst_std_mm']:.3f} | "
                f"{p.get('worst_std_mm', float('nan')):g} | "
                f"{'-' if rng is None else f'{rng[0]:.1f} to {rng[1]:.1f}'} | "
                f"{s['detections_per_position']:.1f} | {s['seconds_per_image']:.2f} | "
                f"{p.get('seconds_per_image', float('nan')):g} | {s['peak_mb_per_image']:.0f} | "
                f"{1000 * p['memory_gb'] if 'memory_gb' in p else float('nan'):g} | "
                + (f"{s['std_ratio_to_perspective']['median']:.1f}, "
                   f"{s['std_ratio_to_perspective']['min']:.1f} "
                   f"({s['std_ratio_to_perspective']['common_bins']} bins) |"
                   if "std_ratio_to_perspective" in s else "- |"))
    return "\n".join(lines) + "\n"


# --- per-image work (runs in worker processes) -----------------------------------------

_CACHE: dict = {}


def _peak_rss_mb() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _reset_peak() -> None:
    import contextlib
    import ctypes
    import gc

    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def _setup(config_dir: str, config: StudyConfig):
    key = config_dir
    if key not in _CACHE:
        from .calibration import load_calibration
        from .io import read_raw
        from .lightfield import decode
        from .simulate import make_optics, with_particle_effects

        optics = make_optics(config.camera, config.seed, realism=config.realism)
        calib = load_calibration(Path(config_dir) / "calibration.json")
        white = decode(read_raw(Path(config_dir) / "data" / "white.tif"), calib.grid)
        field, _ = study_field(config)
        eff = optics.realism.particles
        if eff.enabled:
            field = with_particle_effects(field.assign(frame=0), eff,
                                          seed=np.random.default_rng([config.seed, 6]),
                                          velocity=None).drop(columns=[T_COLUMN])
        _CACHE.clear()
        _CACHE[key] = (optics, calib, white, field)
    return _CACHE[key]


def locate_image(raw, calibration, method: str, *, white=None, frame: int = 0) -> pd.DataFrame:
    """Particles of one raw image by ``method`` (:data:`METHODS`)."""
    from .locate import locate_frame
    from .locate.refocusing import locate_frame_hybrid, locate_frame_refocus

    fn = {"perspective": locate_frame, "refocus": locate_frame_refocus,
          "hybrid": locate_frame_hybrid}[method]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoParticlesWarning)
        return fn(raw, calibration, frame=frame, white=white).particles


def _image_name(index: int, repeat: int) -> str:
    return f"p{index:03d}_r{repeat:02d}.parquet"


def _position_task(config_dir: str, config: StudyConfig, index: int, repeats: list[int],
                   one_thread: bool) -> list[str]:
    """Simulate and locate the images ``repeats`` of traverse position ``index``; write one
    table per image; return their file names.

    The field does not move between repeats, so it is ray-traced once and exposed with
    each repeat's noise seed (:func:`~plenoptrack.simulate.render_repeats`): the images
    are the same as simulating each one on its own.
    """
    if one_thread:
        import numba
        numba.set_num_threads(1)
    from .simulate import render_repeats

    images = Path(config_dir) / "images"
    repeats = [r for r in repeats if not (images / _image_name(index, r)).exists()]
    if not repeats:
        return []
    optics, calib, white, field = _setup(config_dir, config)
    p = float(traverse_positions(config.travel_mm, config.step_mm)[index])
    seeds = [np.random.default_rng([config.seed, 72, index, r]) for r in repeats]
    names = []
    for repeat, raw in zip(repeats, render_repeats(optics, _frame_particles(field, p, 0), seeds)):
        tables = []
        for method, n_rep in config.n_repeats.items():
            if repeat >= n_rep:
                continue
            _reset_peak()
            t0 = time.perf_counter()
            found = locate_image(raw, calib, method, white=white)
            sec = time.perf_counter() - t0
            peak = _peak_rss_mb()
            tables.append(found.assign(method=method, position_mm=p, repeat=repeat,
                                       seconds=sec, peak_mb=peak, n_found=len(found)))
            if len(found) == 0:   # keep the image's timing even when nothing was found
                tables[-1] = pd.DataFrame({"method": [method], "position_mm": [p],
                                           "repeat": [repeat], "seconds": [sec],
                                           "peak_mb": [peak], "n_found": [0], "x": [np.nan],
                                           "y": [np.nan], "z": [np.nan]})
        write_table(pd.concat(tables, ignore_index=True), images / _image_name(index, repeat))
        names.append(_image_name(index, repeat))
    return names


def _prepare(config_dir: Path, config: StudyConfig, progress) -> None:
    """Simulate the white image and dot cards of a configuration and calibrate it
    (skipped when its calibration exists)."""
    from .calibrate import calibrate
    from .calibration import save_calibration
    from .simulate import simulate_dataset

    cal = config_dir / "calibration.json"
    if cal.exists():
        return
    lo, hi = config.calibration_depth_mm
    n_cards = max(11, int(round((hi - lo) / 5)) + 1)
    data = config_dir / "data"
    simulate_dataset(config.camera, data, seed=config.seed, n_particles=1, frames=1,
                     dotcard_depths=np.linspace(lo, hi, n_cards), realism=config.realism,
                     diameter_mm=config.head_diameter_mm)
    calib, _ = calibrate(data / "white.tif", data / "dotcards", config.camera,
                         card_tilt=config.card_tilt, progress=progress is not None)
    save_calibration(calib, cal)


# --- the whole study --------------------------------------------------------------------

def _analyse(config_dir: Path, config: StudyConfig) -> tuple[dict, dict]:
    from .locate.refocusing import depth_of_field_mm

    files = sorted((config_dir / "images").glob("p*_r*.parquet"))
    table = pd.concat([read_table(f) for f in files], ignore_index=True) if files else pd.DataFrame()
    near, far = depth_of_field_mm(config.camera)
    pitch = config.camera.microlens_pitch_um * 1e-3 / abs(config.camera.magnification)
    out, curves = {}, {}
    for method in config.methods:
        rows = table[table["method"] == method] if len(table) else table
        images = (rows.groupby(["position_mm", "repeat"]).agg(
            n=("n_found", "first"), seconds=("seconds", "first"), peak_mb=("peak_mb", "first"))
            .reset_index() if len(rows) else pd.DataFrame(columns=["n", "seconds", "peak_mb"]))
        errs = depth_errors(rows.dropna(subset=["z"]) if len(rows) else rows,
                            match_mm=max(0.5, 1.5 * config.head_diameter_mm))
        bins = binned_statistics(errs, bin_mm=config.bin_width_mm, depth_limits_mm=(near, far),
                                 pitch_mm=pitch)
        s = summarise(errs, bins, images)
        s["repeats"] = config.n_repeats[method]
        out[method] = s
        curves[method] = bins
    meta = {"depth_of_field_mm": [near, far], "object_space_pitch_mm": pitch,
            "magnification": abs(config.camera.magnification),
            "object_distance_mm": config.camera.object_distance_mm,
            "positions": len(traverse_positions(config.travel_mm, config.step_mm)),
            "config": config.to_dict()}
    if "perspective" in curves:
        base = curves["perspective"].set_index("depth_mm")["std_mm"]
        for method, bins in curves.items():
            if method == "perspective":
                continue
            common = bins.set_index("depth_mm")["std_mm"].to_frame("m").join(base, how="inner")
            ratio = common["m"] / common["std_mm"]
            out[method]["std_ratio_to_perspective"] = {
                "common_bins": int(len(ratio)),
                "median": float(ratio.median()) if len(ratio) else float("nan"),
                "min": float(ratio.min()) if len(ratio) else float("nan")}
    return {"methods": out, **meta}, curves


def run_study(configs: list[StudyConfig], out_dir: str | Path, *, workers: int = 1,
              progress: bool = True) -> dict:
    """Run (or resume) the study for every configuration and write its results.

    Parameters
    ----------
    configs : list of StudyConfig
        Configurations (one, or the 12 of :func:`paper_grid`).
    out_dir : str or Path
        Output folder: per configuration a sub-folder with ``data/`` (white image, dot
        cards), ``calibration.json`` and ``images/`` (one table per located image); at
        the top ``summary.json``, ``comparison.md``, ``bins.csv`` and the figures
        ``accuracy.png``, ``precision.png``, ``precision_normalised.png``. Images already
        located are skipped, so an interrupted study resumes where it stopped.
    workers : int
        Local Dask worker processes (one thread each); 0 runs in this process.

    Returns
    -------
    dict
        The summary written to ``summary.json``.
    """
    from contextlib import nullcontext

    from rich.progress import Progress

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if workers < 0:
        raise SettingsError(f"workers must be >= 0; got {workers}")
    jobs = []
    bar_ctx = Progress(transient=False) if progress else nullcontext()
    with bar_ctx as bar:
        for cfg in configs:
            study_field(cfg)          # refuse a field that does not fit before any work
        for cfg in configs:
            cdir = out / cfg.label
            (cdir / "images").mkdir(parents=True, exist_ok=True)
            atomic_write_text(cdir / "config.json", json.dumps(cfg.to_dict(), indent=1))
            if bar is not None:
                prep = bar.add_task(f"calibrating {cfg.label}", total=None)
            _prepare(cdir, cfg, bar)
            if bar is not None:
                bar.remove_task(prep)
            # one job per position and its missing repeats (traced once, exposed per repeat)
            n_rep = max(cfg.n_repeats.values())
            order = coarse_to_fine(len(traverse_positions(cfg.travel_mm, cfg.step_mm)))
            todo = [(int(i), [r for r in range(n_rep)
                              if not (cdir / "images" / _image_name(i, r)).exists()])
                    for i in order]
            jobs.append([(str(cdir), cfg, i, missing) for i, missing in todo if missing])
        # interleave the configurations so that a study stopped early covers all of them
        jobs = [job for group in itertools.zip_longest(*jobs) for job in group if job is not None]
        total = sum(len(job[3]) for job in jobs)
        task = bar.add_task("study images", total=total) if bar is not None else None
        if workers == 0:
            for job in jobs:
                _position_task(*job, False)
                if bar is not None:
                    bar.update(task, advance=len(job[3]))
        elif jobs:
            from dask.distributed import Client, LocalCluster, as_completed

            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                              dashboard_address=None) as cluster, Client(cluster) as client:
                futures = {client.submit(_position_task, *job, workers > 1, pure=False): job
                           for job in jobs}
                for fut in as_completed(futures):
                    fut.result()
                    if bar is not None:
                        bar.update(task, advance=len(futures[fut][3]))
    return report_study(configs, out)


def report_study(configs: list[StudyConfig], out_dir: str | Path) -> dict:
    """Analyse the images located so far and write ``summary.json``, ``comparison.md``,
    ``bins.csv`` and the figures into ``out_dir`` (see :func:`run_study`); returns the
    summary. Useful on a study stopped early: it reports the images that exist."""
    out = Path(out_dir)
    summary = {"configurations": {}}
    all_bins = []
    for cfg in configs:
        s, curves = _analyse(out / cfg.label, cfg)
        summary["configurations"][cfg.label] = s
        for m, b in curves.items():
            all_bins.append(b.assign(configuration=cfg.label, method=m))
    summary["paper"] = PAPER
    summary["note"] = ("refocus and hybrid use the first refocus_repeats repeats of each position; "
                       "timings are wall-clock seconds per image on a shared machine")
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1, default=float))
    atomic_write_text(out / "comparison.md", comparison_table(summary))
    bins = pd.concat(all_bins, ignore_index=True) if all_bins else pd.DataFrame()
    write_table(bins, out / "bins.csv")
    if len(bins):
        from .plots import plot_study
        plot_study(bins, out, dof=summary["configurations"])
    return summary

