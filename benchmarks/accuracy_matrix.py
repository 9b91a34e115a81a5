"""Accuracy matrix of the perspective-shift locator on simulated data with ground truth.

    python benchmarks/accuracy_matrix.py                  # default matrix, ~20-30 min on 2 cores
    python benchmarks/accuracy_matrix.py --quick          # fewer seeds and cells, < 5 min
    python benchmarks/accuracy_matrix.py --hall           # also the hall2019 cells (slow)
    python benchmarks/accuracy_matrix.py --shapes sphere ellipsoid   # unknown shapes are skipped
    python benchmarks/accuracy_matrix.py --no-effects     # without the one-effect-at-a-time cells

This is the yardstick on which the locator is judged (``DESIGN.md``, Validation). Claims
about accuracy quote the **validation** rows of the **realistic** optics.

Design
------
Not the full Cartesian product: a base cell and one-axis-at-a-time sweeps around it, each
cell run with both optics modes (``ideal``: the exact geometric model; ``realistic``:
diffraction, crosstalk, aberrations, fixed patterns, irregular particles, imperfect dot
cards, spec-sheet values that differ from the truth; see
:mod:`plenoptrack.simulate.realism`).

* base: camera preset ``small`` (49 x 65 hexagonal microlenses), magnification -0.5,
  density 0.01 particles per microlens (32 particles), spheres of 0.4 mm;
* density sweep: 0.003, 0.01, 0.03, 0.1 particles per microlens (n = density x the
  number of microlenses), also reported as source density N_s (below);
* size sweep: single sizes 0.2, 0.4, 0.5, 1, 2 mm and a mixed cell, diameters
  log-uniform in 0.2-1 mm (a size whose particles would fill more than ``MAX_FILL`` of the
  default volume at the base density runs at the largest density of the 1-2-5 series that
  fits, and says so in its name);
* magnification sweep: -0.3, -0.5, -0.75, -1.0, f-number matched to the microlenses
  (:meth:`CameraSpec.with_magnification`); the volume depth, and the dot cards with it,
  scale like the depth of field, as ``1/M**2`` (55.6, 20, 8.9 and 5 mm:
  :func:`~plenoptrack.simulate.scene.volume_depth_mm`; before 2026-12-02 every
  magnification used 20 mm, at M -1 five times the plenoptic depth of field, where the
  far dot cards could not be measured and the faces' blur left the volume 2.6 x 1 mm
  wide);
* shape sweep: ``ellipsoid`` (prolate spheroids, aspect ratio log-uniform in 1-3, random
  orientation) and ``fragment`` (irregular convex or star-shaped bodies), at the base size
  (volume-equivalent diameter) and density; shapes the simulator does not know are skipped
  with a message. Fragments are located with ``solve.shape_error = FRAGMENT_SHAPE_ERROR``
  (the uncertainty of an irregular body's centre of mass, which an experimenter imaging
  fragments sets: ``plenoptrack locate --shape-error 0.02``); every other cell with the
  defaults;
* effect sweep (not with ``--no-effects`` or ``--quick``): the base cell with the ideal
  optics plus *one* group of :class:`~plenoptrack.simulate.realism.Realism` at its realistic
  size (optics ``ideal+blur``, ``ideal+lens``, ...), each with its own calibration, on the
  first development and the first validation seed only: which effect costs how much
  accuracy;
* ``--acceptance``: instead of the sweeps above, the envelope the locator is accepted on
  (the targets are printed with each measured value and PASS or FAIL in the report's
  section "Acceptance"): sparse cells at ``ACCEPTANCE_SPARSE`` particles per microlens
  (the 1-2-5 series value at or below the sparse bound 0.006) for every size, the
  mixed sizes 0.2-2 mm, every magnification and ellipsoids; and the base cell at
  ``ACCEPTANCE_DENSITIES``. A sparse cell's density counts the microlenses its volume
  covers (``footprint``), not the whole array: large particles shrink the default volume
  laterally (to 13 % of the field of view for 2 mm particles on ``small``), and 16
  particles there (0.005 over the whole array) crowd their field as 0.038 would (before
  2026-12-03 they did, and the mixed-size "sparse" cell had a higher source density than
  the 0.025 band). The density cells keep the whole-array count of the sweeps. Coverage is pooled over the cells and per density band
  (sparse, 0.025, 0.05, 0.1);
* ``--hall``: the ``hall2019`` preset (362 x 471 microlenses) at magnification -0.5 with
  1 mm spheres at density 0.003 (511 particles) and 2 mm spheres at density 0.001 (171
  particles), on the first development and the first validation seed only (each data
  set takes minutes).

Seeds
-----
Fixed here, before any tuning: development seeds ``DEV_SEEDS`` (tuning allowed) and
validation seeds ``VALIDATION_SEEDS`` (never tuned on), reported separately. ``--quick``
uses the first of each. A seed fixes the true optics (``make_optics(camera, seed,
realism)`` depends on nothing else), the dot cards and the noise; the particle scenes of a
cell are drawn from ``[seed, crc32(cell name), frame]``.

Calibration
-----------
Once per (magnification, optics mode, seed): a data set of the white image and the default
dot cards (no particles) is simulated with :func:`~plenoptrack.simulate.simulate_dataset`
and calibrated with :func:`~plenoptrack.calibrate.calibrate` at its defaults; its white
image, decoded once, flat-fields every frame located with that calibration (as
``plenoptrack locate`` does with the white image the calibration file records). The frames of
every cell with that magnification are then simulated with the same camera, optics mode
and seed but ``dotcard_depths=[]`` (no cards rendered twice); the script checks that their
true optics equal those of the calibration data set. Each cell gets
``max(min_frames, ceil(min_particles / n))`` frames (``--min-particles``,
``--min-frames``), each frame an independent random scene, so that sparse cells still hold
enough particles. ``--acceptance`` takes at least 3 frames per cell and seed: the recall of
a crowded cell swings by a few hundredths from frame to frame with any change to the
locator, and one frame per seed left its targets unreadable.

Metrics (per cell, optics mode and seed set; matched pairs pooled over the seeds)
-------------------------------------------------------------------------------
Matching: one-to-one (Hungarian, :func:`plenoptrack.evaluate.match_particles`) within an
ellipsoid of half-axes ``TOL_LATERAL_MM * (0.5/|M|)`` in x and y and
``TOL_DEPTH_MM * (0.5/|M|)**2`` in z (0.5 mm and 1.5 mm at M = -0.5: lateral errors
scale with the object-side pixel, ~1/|M|, depth errors with the depth resolution,
~1/M^2), by matching coordinates divided by the half-axes at tolerance 1.
``chance`` is the expected number of true particles inside one tolerance ellipsoid
placed at random in the volume (a false positive can match by chance that often).

recall, precision; ``hidden``: fraction of the true particles hidden in every view the
locator reads (:func:`plenoptrack.evaluate.hidden_particles`: each view's image wholly
inside another particle's; no locator can see them, so ``1 - hidden`` bounds the
recall) and ``rec. seen``, the recall of the others; depth bias (mean dz), depth std (ddof 1) and robust std (1.4826 MAD
about the median); ``>3sz``: fraction of matched particles with |dz| > 3 sigma_z;
``1s``/``2s``: fraction with |d| <= 1 and 2 sigma for x, y and z (a calibrated sigma gives
0.68 and 0.95); lateral RMS error; diameter ratio: median of measured diameter over the
true silhouette's equivalent diameter ``sqrt(4 A / pi)`` (``A`` the truth's
``projected_area``: what the locator's shadow-based ``diameter`` measures; for a sphere
its diameter, for an ellipsoid or a fragment larger than its volume-equivalent
``diameter``);
seconds per frame of :func:`~plenoptrack.locate.perspective.locate_frame` on the raw
image (decode included, reading and simulating excluded, after one warm-up call).

Source density N_s: the sum, over the particles of a frame, of the areas of their images
in the central perspective view, over the view's area (the microlens array). A particle
of diameter d at depth z (object distance s_o + z) images on the array with diameter
``|M| (d s_o / (s_o + z) + (D / n_u) |z| / (s_o + z))``: its geometric image through the
centre of the aperture plus the defocus blur of one view's sub-aperture (the aperture D
over ``n_u`` = pixels per lenslet views across it). Nominal optics, truth positions;
overlaps are counted twice, so N_s can exceed 1.

Output (``--out``, default ``benchmarks/results/accuracy_matrix/``): ``report.md``,
``rows.json`` (every row: cell parameters, optics, seed set, metrics; per-seed rows and
calibrations too) and PNG figures: ``lines_<axis>.png`` (recall, precision, depth errors
along each axis, ideal vs realistic, development vs validation) and ``heatmap.png``.
Simulated data go to a temporary folder that is removed. Results are deterministic (the
timings are not).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

DEV_SEEDS = (100, 101, 102)
"""Development seeds: tuning on these is allowed."""
VALIDATION_SEEDS = (900, 901, 902)
"""Validation seeds: never tune on these."""

BASE = {"preset": "small", "magnification": -0.5, "density": 0.01, "size": 0.4,
        "shape": "sphere"}
DENSITIES = (0.003, 0.01, 0.03, 0.1)
SIZES = (0.2, 0.4, 0.5, 1.0, 2.0)
MIXED_SIZE = (0.2, 1.0)
MAGNIFICATIONS = (-0.3, -0.5, -0.75, -1.0)
SHAPES = ("sphere", "ellipsoid", "fragment")
OPTICS = ("ideal", "realistic")
HALL_CELLS = ({"density": 0.003, "size": 1.0}, {"density": 0.001, "size": 2.0})
ACCEPTANCE_SPARSE = 0.005
"""Particles per microlens of the acceptance envelope's sparse cells (bound: 0.006)."""
ACCEPTANCE_DENSITIES = (0.025, 0.05, 0.1)
ACCEPTANCE_MIXED = (0.2, 2.0)
ACCEPTANCE_SPARSE_MAX = 0.006

TOL_LATERAL_MM = 0.5
"""Lateral half-axis of the matching ellipsoid at magnification -0.5, mm."""
TOL_DEPTH_MM = 1.5
"""Depth half-axis of the matching ellipsoid at magnification -0.5, mm."""
FRAGMENT_SHAPE_ERROR = 0.02
"""``solve.shape_error`` of the fragment cells (:mod:`plenoptrack.locate.uncertainty`)."""
MAX_FILL = 0.1
"""Cells whose particles would fill more of the default volume than this are skipped."""


@dataclass(frozen=True)
class Cell:
    """One point of the matrix."""

    name: str
    axis: str     # "base", "density", "size", "magnification", "shape", "effect", "hall"
    preset: str
    magnification: float
    density: float                 # particles per microlens
    size: float | tuple[float, float]   # mm, or (min, max) log-uniform
    shape: str = "sphere"
    optics: str | None = None      # only this optics (effect cells); None: every mode run

    @property
    def size_label(self) -> str:
        return (f"{self.size[0]:g}-{self.size[1]:g} log-unif" if isinstance(self.size, tuple)
                else f"{self.size:g}")

    def params(self) -> dict:
        d = dataclasses.asdict(self)
        d["size"] = list(self.size) if isinstance(self.size, tuple) else self.size
        return d


def _cell(axis: str, optics: str | None = None, **changes) -> Cell:
    p = {**BASE, **changes}
    size = p["size"]
    size_txt = f"{size[0]:g}-{size[1]:g}mm" if isinstance(size, tuple) else f"{size:g}mm"
    name = (f"{p['preset']} M{p['magnification']:g} d{p['density']:g} {size_txt} {p['shape']}"
            + (f" {optics}" if optics else ""))
    return Cell(name=name, axis=axis, preset=p["preset"], magnification=p["magnification"],
                density=p["density"], size=size, shape=p["shape"], optics=optics)


def effect_groups() -> tuple[str, ...]:
    """Names of the :class:`~plenoptrack.simulate.realism.Realism` groups."""
    from plenoptrack.simulate.realism import Realism

    return tuple(f.name for f in dataclasses.fields(Realism))


def realism_of(optics: str):
    """``"ideal"``, ``"realistic"``, ``"ideal+GROUP"`` (ideal optics with one group of
    effects at its realistic size) or ``"ideal+GROUP.FIELD"`` (only that field of the
    group, the group's others as in ideal optics) as a Realism (or the name)."""
    if optics in OPTICS:
        return optics
    from plenoptrack.simulate.realism import Realism

    group, _, field = optics.removeprefix("ideal+").partition(".")
    if not optics.startswith("ideal+") or group not in effect_groups():
        raise ValueError(f"unknown optics {optics!r}")
    ideal, realistic = Realism.ideal(), Realism.realistic()
    effects = getattr(realistic, group)
    if field:
        names = [f.name for f in dataclasses.fields(effects)]
        if field not in names:
            raise ValueError(f"unknown optics {optics!r}: group {group!r} has the fields "
                             f"{', '.join(names)}")
        effects = dataclasses.replace(getattr(ideal, group), **{field: getattr(effects, field)})
    return dataclasses.replace(ideal, **{group: effects})


def _fitting_density(cell: Cell) -> float | None:
    """The largest density of the 1-2-5 series at or below the cell's whose particles fit
    the volume (``MAX_FILL``), or None if none down to 1e-4 does."""
    for exp in range(5):
        for mant in (5, 2, 1):
            d = mant * 10.0 ** (-exp - 1)
            if d > cell.density:
                continue
            trial = dataclasses.replace(cell, density=d)
            if not _does_not_fit(trial):
                return d
    return None


def acceptance_cells() -> list[Cell]:
    """The acceptance envelope (module notes, ``--acceptance``): axis ``sparse`` for the
    cells at ``ACCEPTANCE_SPARSE``, ``density`` for the crowded ones."""
    sparse = {"density": ACCEPTANCE_SPARSE}
    cells = [_cell("sparse", **sparse)]
    cells += [_cell("sparse", size=s, **sparse) for s in SIZES if s != BASE["size"]]
    cells += [_cell("sparse", size=ACCEPTANCE_MIXED, **sparse)]
    cells += [_cell("sparse", magnification=m, **sparse) for m in MAGNIFICATIONS
              if m != BASE["magnification"]]
    cells += [_cell("sparse", shape="ellipsoid", **sparse)]
    cells += [_cell("density", density=d) for d in ACCEPTANCE_DENSITIES]
    return cells


def build_cells(*, quick: bool, hall: bool, shapes, effects: bool = True,
                acceptance: bool = False) -> tuple[list[Cell], list[str]]:
    """The cells to run and the messages for the cells skipped or moved."""
    from plenoptrack.simulate.scene import SHAPES as KNOWN_SHAPES

    if acceptance:
        return _fitting(acceptance_cells())
    base = _cell("base")
    if quick:
        densities, sizes, mags = (0.1,), (0.2, 1.0), (-1.0,)
    else:
        densities = tuple(d for d in DENSITIES if d != BASE["density"])
        sizes = tuple(s for s in SIZES if s != BASE["size"])
        mags = tuple(m for m in MAGNIFICATIONS if m != BASE["magnification"])
    cells = [base]
    cells += [_cell("density", density=d) for d in densities]
    cells += [_cell("size", size=s) for s in sizes] + [_cell("size", size=MIXED_SIZE)]
    cells += [_cell("magnification", magnification=m) for m in mags]
    skipped = []
    for shape in shapes:
        if shape == BASE["shape"]:
            continue
        if shape not in KNOWN_SHAPES:
            skipped.append(f"shape {shape!r}: the simulator has no such particle shape "
                           f"(known: {', '.join(KNOWN_SHAPES)}); its cell is skipped")
            continue
        cells.append(_cell("shape", shape=shape))
    if effects and not quick:
        cells += [_cell("effect", optics=f"ideal+{g}") for g in effect_groups()]
    if hall:
        cells += [_cell("hall", preset="hall2019", **c) for c in HALL_CELLS]
    cells, moved = _fitting(cells)
    return cells, skipped + moved


def _fitting(cells: list[Cell]) -> tuple[list[Cell], list[str]]:
    """The cells whose particles fit their volume; a size cell that does not runs at the
    largest density of the 1-2-5 series that fits. With the messages."""
    skipped = []
    kept = []
    for cell in cells:
        why = _does_not_fit(cell)
        if why and cell.axis in ("size", "sparse"):
            d = _fitting_density(cell)
            if d is not None:
                moved = _cell(cell.axis, preset=cell.preset, magnification=cell.magnification,
                              density=d, size=cell.size, shape=cell.shape)
                skipped.append(f"{cell.name}: {why}; run at density {d:g} instead")
                kept.append(moved)
                continue
        if why:
            skipped.append(f"{cell.name}: {why}; skipped")
        else:
            kept.append(cell)
    return kept, skipped


def _camera(cell: Cell):
    from plenoptrack import preset

    return preset(cell.preset).with_magnification(cell.magnification)


def n_microlenses(camera) -> int:
    rows, cols = camera.grid_shape
    return int(rows * cols)


def footprint_fraction(cell: Cell) -> float:
    """Fraction of the focal-plane field of view the volume's cross-section covers: the
    share of the microlenses its particles image onto. Large particles shrink the
    default volume laterally (:func:`~plenoptrack.simulate.scene.default_volume`), so at
    one density over the whole array they crowd a smaller field: the local density is
    the cell's over this fraction."""
    camera = _camera(cell)
    b = _volume(cell).bounds
    h, w = camera.sensor_size_mm
    m = abs(camera.magnification)
    return min(1.0, float((b[0, 1] - b[0, 0]) * (b[1, 1] - b[1, 0]) / (w / m * h / m)))


def n_particles(cell: Cell) -> int:
    """Particles per frame: the density times the microlenses of the whole array; for the
    acceptance envelope's sparse cells, times the microlenses the volume covers
    (:func:`footprint_fraction`), so that a sparse cell is as sparse where its particles
    are as its density says, whatever their size."""
    lenses = n_microlenses(_camera(cell))
    if cell.axis == "sparse":
        lenses *= footprint_fraction(cell)
    return max(1, int(round(cell.density * lenses)))


def _volume(cell: Cell):
    from plenoptrack.simulate.scene import default_volume

    hi = max(cell.size) if isinstance(cell.size, tuple) else cell.size
    return default_volume(_camera(cell), diameter_mm=hi)


def _does_not_fit(cell: Cell) -> str:
    from plenoptrack.simulate import SceneError

    try:
        vol = _volume(cell)
    except SceneError as exc:
        return str(exc)
    lo, hi = cell.size if isinstance(cell.size, tuple) else (cell.size, cell.size)
    # Mean d^3 of the log-uniform law: (hi^3 - lo^3) / (3 ln(hi/lo)).
    mean_d3 = lo ** 3 if lo == hi else (hi ** 3 - lo ** 3) / (3 * math.log(hi / lo))
    b = vol.bounds
    fill = n_particles(cell) * math.pi / 6 * mean_d3 / float(np.prod(b[:, 1] - b[:, 0]))
    if fill > MAX_FILL:
        return (f"{n_particles(cell)} particles of {cell.size_label} mm would fill "
                f"{fill:.0%} of the {cell.preset} volume at M {cell.magnification:g} "
                f"(limit {MAX_FILL:.0%})")
    return ""


def tolerances(magnification: float) -> tuple[float, float]:
    """(lateral, depth) half-axes of the matching ellipsoid, mm."""
    k = 0.5 / abs(magnification)
    return TOL_LATERAL_MM * k, TOL_DEPTH_MM * k * k


def source_density(truth: pd.DataFrame, camera) -> float:
    """Sum of the particle-image areas in the central view over the view area (module
    notes; :func:`plenoptrack.locate.crowding.source_density`)."""
    from plenoptrack.locate.crowding import source_density as density

    return density(truth, camera)


def frames_per_seed(cell: Cell, min_particles: int, min_frames: int = 1) -> int:
    """Frames of a cell per seed: at least ``min_frames`` and ``min_particles`` particles."""
    return max(1, int(min_frames), math.ceil(min_particles / n_particles(cell)))


def make_cell_scene(cell: Cell, seed: int, frames: int):
    """Independent random scenes, one per frame, in one :class:`Scene`."""
    from plenoptrack.simulate import random_particles
    from plenoptrack.simulate.scene import Scene

    camera, volume, n = _camera(cell), _volume(cell), n_particles(cell)
    key = zlib.crc32(cell.name.encode())
    # Independent scenes: each frame's particles get ids of their own, so that nothing
    # takes a particle of one frame for the same particle moved in the next (the
    # simulator would blur it along that made-up path during the exposure).
    parts = [random_particles(n, volume=volume, diameter_mm=cell.size, shape=cell.shape,
                              seed=np.random.default_rng([seed, key, f]))
             .assign(frame=f, particle=lambda d, f=f: d["particle"] + f * n)
             for f in range(frames)]
    truth = pd.concat(parts, ignore_index=True)
    return Scene(camera=camera, volume=volume, truth=truth, seed=seed)


def cell_locator(cell: Cell):
    """The locator settings of a cell: the defaults, with the shape error for fragments."""
    from plenoptrack.locate import PerspectiveLocator

    locator = PerspectiveLocator()
    if cell.shape == "fragment":
        locator = locator.updated({"solve": {"shape_error": FRAGMENT_SHAPE_ERROR}},
                                  source="accuracy matrix")
    return locator


def _silhouette_diameter(truth: pd.DataFrame) -> pd.Series:
    """Equivalent diameter of each true particle's silhouette in the x-y plane, mm:
    ``sqrt(4 projected_area / pi)``, or ``diameter`` where the truth has no
    ``projected_area``."""
    if "projected_area" not in truth.columns:
        return truth["diameter"]
    area = truth["projected_area"].to_numpy(float)
    return pd.Series(np.where(np.isfinite(area), np.sqrt(4.0 * area / math.pi),
                              truth["diameter"].to_numpy(float)), index=truth.index)


def match(measured: pd.DataFrame, truth: pd.DataFrame, magnification: float) -> pd.DataFrame:
    """Pairs within the tolerance ellipsoid, with the measured and true columns needed
    (``hidden`` from the truth's column of that name, False without one)."""
    from plenoptrack.evaluate import match_particles

    tl, tz = tolerances(magnification)

    def scaled(df):
        return df.assign(x=df["x"] / tl, y=df["y"] / tl, z=df["z"] / tz)

    pairs = match_particles(scaled(measured), scaled(truth), tolerance_mm=1.0)
    m = measured.loc[pairs["measured_index"]].reset_index(drop=True)
    t = truth.loc[pairs["truth_index"]].reset_index(drop=True)
    return pd.DataFrame({
        "dx": m["x"] - t["x"], "dy": m["y"] - t["y"], "dz": m["z"] - t["z"],
        "sigma_x": m["sigma_x"], "sigma_y": m["sigma_y"], "sigma_z": m["sigma_z"],
        "diameter": m["diameter"], "true_diameter": _silhouette_diameter(t),
        "x_true": t["x"], "y_true": t["y"], "z_true": t["z"],
        "hidden": (t["hidden"].to_numpy(bool) if "hidden" in t
                   else np.zeros(len(t), dtype=bool)),
        **{c: m[c] for c in ("chi2", "travel_px", "n_views", "flags") if c in m}})


def metrics(pairs: pd.DataFrame, n_true: int, n_measured: int, n_hidden: int = 0) -> dict:
    """The metrics of the module notes from pooled pairs (``n_hidden`` of the ``n_true``
    particles hidden in every view)."""
    n = len(pairs)
    n_seen = n_true - n_hidden
    matched_seen = n - int(pairs["hidden"].sum()) if "hidden" in pairs else n
    out = {"n_true": int(n_true), "n_measured": int(n_measured), "n_matched": n,
           "recall": n / n_true if n_true else math.nan,
           "precision": n / n_measured if n_measured else math.nan,
           "n_hidden": int(n_hidden), "hidden": n_hidden / n_true if n_true else math.nan,
           "recall_seen": matched_seen / n_seen if n_seen else math.nan}
    nan = math.nan
    if n == 0:
        return out | {k: nan for k in ("bias_z", "std_z", "rstd_z", "out3_x", "out3_y",
                                       "out3_z", "lat_rms",
                                       "cov1_x", "cov1_y", "cov1_z", "cov2_x", "cov2_y",
                                       "cov2_z", "diameter_ratio")}
    dz = pairs["dz"].to_numpy(float)
    out["bias_z"] = float(dz.mean())
    out["std_z"] = float(dz.std(ddof=1)) if n > 1 else nan
    out["rstd_z"] = float(1.4826 * np.median(np.abs(dz - np.median(dz))))
    for ax in "xyz":
        out[f"out3_{ax}"] = float(np.mean(np.abs(pairs[f"d{ax}"].to_numpy(float))
                                          > 3 * pairs[f"sigma_{ax}"].to_numpy(float)))
    out["lat_rms"] = float(np.sqrt(np.mean(pairs["dx"] ** 2 + pairs["dy"] ** 2)))
    for k in (1, 2):
        for ax in "xyz":
            out[f"cov{k}_{ax}"] = float(np.mean(np.abs(pairs[f"d{ax}"].to_numpy(float))
                                                <= k * pairs[f"sigma_{ax}"].to_numpy(float)))
    ratio = pairs["diameter"].to_numpy(float) / pairs["true_diameter"].to_numpy(float)
    ratio = ratio[np.isfinite(ratio)]
    out["diameter_ratio"] = float(np.median(ratio)) if len(ratio) else nan
    return out


def _clean(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, float):
        return float(f"{value:.6g}")
    if isinstance(value, (np.floating, np.integer)):
        return _clean(value.item())
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


class Runner:
    """Calibrates once per (magnification, optics, seed) and runs the cells on it."""

    def __init__(self, tmp: Path, min_particles: int, t0: float, min_frames: int = 1):
        self.tmp = tmp
        self.min_particles = min_particles
        self.min_frames = min_frames
        self.t0 = t0
        self.warm = False
        self.calibrations: list[dict] = []

    def calibrate(self, preset_name: str, magnification: float, optics: str, seed: int):
        from plenoptrack.calibrate import calibrate
        from plenoptrack.errors import PlenoptrackError
        from plenoptrack.io import read_raw
        from plenoptrack.lightfield import decode
        from plenoptrack.simulate import simulate_dataset

        folder = self.tmp / f"cal_{preset_name}_{magnification:g}_{optics}_{seed}"
        t = time.perf_counter()
        sim = simulate_dataset(preset_name, folder, seed=seed, n_particles=0,
                               magnification=magnification, realism=realism_of(optics))
        t_sim = time.perf_counter() - t
        row = {"preset": preset_name, "magnification": magnification, "optics": optics,
               "seed": seed, "ok": False, "rms_px": math.nan, "simulate_s": t_sim,
               "calibrate_s": math.nan, "warnings": "", "error": ""}
        calib = white = None
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t = time.perf_counter()
            try:
                calib, report = calibrate(sim.white_path, sim.out_dir / "dotcards", sim.camera)
                row.update(ok=True, rms_px=float(report.rms_px))
                white = decode(read_raw(sim.white_path), calib.grid)   # decoded once
            except (PlenoptrackError, ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
                # A failed calibration is a result of the matrix (its cells are reported
                # as skipped), not a reason to lose the rest of the run.
                row["error"] = f"{type(exc).__name__}: {exc}"
            row["calibrate_s"] = time.perf_counter() - t
        row["warnings"] = "; ".join(sorted({f"{w.category.__name__}: {w.message}"
                                            for w in caught}))
        shutil.rmtree(folder, ignore_errors=True)
        self.calibrations.append(row)
        status = (f"DLFC RMS {row['rms_px']:.3f} px" if row["ok"] else f"FAILED {row['error']}")
        print(f"calibrated {preset_name} M {magnification:g} {optics} seed {seed}: {status} "
              f"({t_sim:.0f} + {row['calibrate_s']:.0f} s)", flush=True)
        return calib, white, sim.optics

    def run_cell(self, cell: Cell, optics: str, seed: int, calib, white, cal_optics) -> dict:
        from plenoptrack.evaluate import hidden_particles
        from plenoptrack.io import read_raw
        from plenoptrack.locate.perspective import locate_frame
        from plenoptrack.simulate import simulate_dataset

        n = n_particles(cell)
        frames = frames_per_seed(cell, self.min_particles, self.min_frames)
        scene = make_cell_scene(cell, seed, frames)
        folder = self.tmp / f"frames_{zlib.crc32(cell.name.encode())}_{optics}_{seed}"
        sim = simulate_dataset(cell.preset, folder, seed=seed, scene=scene,
                               magnification=cell.magnification, realism=realism_of(optics),
                               dotcard_depths=[])
        if sim.optics != cal_optics:
            raise RuntimeError(f"{cell.name} {optics} seed {seed}: the frames' optics differ "
                               "from the calibration's; the calibration cannot be reused")
        locator = cell_locator(cell)
        truth_all = sim.truth.assign(hidden=hidden_particles(sim.truth, calib.dlfc,
                                                             _read_views(white)))
        pairs, n_measured, seconds, caught_all = [], 0, [], set()
        for f, path in enumerate(sim.frame_paths):
            raw = read_raw(path)
            truth = truth_all[truth_all["frame"] == f]
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                if not self.warm:
                    locate_frame(raw, calib, frame=f, white=white,   # warm-up, untimed
                                 locator=locator)
                    self.warm = True
                t = time.perf_counter()
                found = locate_frame(raw, calib, frame=f, white=white,
                                     locator=locator).particles
                seconds.append(time.perf_counter() - t)
            caught_all |= {w.category.__name__ for w in caught}
            n_measured += len(found)
            pairs.append(match(found, truth, cell.magnification))
        shutil.rmtree(folder, ignore_errors=True)
        tl, tz = tolerances(cell.magnification)
        b = scene.volume.bounds
        chance = n * (4 / 3 * math.pi * tl * tl * tz) / float(np.prod(b[:, 1] - b[:, 0]))
        ns = [source_density(scene.truth[scene.truth["frame"] == f], scene.camera)
              for f in range(frames)]
        return {"pairs": pd.concat(pairs, ignore_index=True), "n_true": len(sim.truth),
                "n_hidden": int(truth_all["hidden"].sum()),
                "n_measured": n_measured, "frames": frames, "seconds": seconds,
                "source_density": float(np.mean(ns)), "chance": chance,
                "warnings": sorted(caught_all)}


def add_one_camera_arguments(parser: argparse.ArgumentParser) -> None:
    """``--optics``, ``--seed``, ``--workdir`` and ``--out`` of a study on one calibrated
    camera (the matrix's calibration of a development seed by default)."""
    parser.add_argument("--optics", default="ideal", help="ideal, realistic or ideal+GROUP")
    parser.add_argument("--seed", type=int, default=DEV_SEEDS[0])
    parser.add_argument("--workdir", type=Path, default=None,
                        help="where the simulated data go (default: a temporary folder)")
    parser.add_argument("--out", type=Path, default=None, help="write the table here (markdown)")


@contextlib.contextmanager
def one_camera_runner(workdir: Path | None, t0: float):
    """``(Runner, folder)`` for a study on one camera: in ``workdir``, or in a temporary
    folder removed afterwards."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = workdir or Path(tmp)
        yield Runner(folder, 1, t0), folder


def _read_views(white) -> np.ndarray:
    """(V, 2) ``(u, v)`` of the views the locator reads (more than half their samples
    valid), from the decoded white image."""
    from plenoptrack.locate.perspective import MIN_VIEW_FRACTION

    u, v = np.meshgrid(white.u, white.v)
    usable = white.valid_fraction > MIN_VIEW_FRACTION
    return np.c_[u[usable], v[usable]]


def aggregate(results: list[dict], keys: tuple[str, ...]) -> list[dict]:
    """Pool the pairs of per-seed results sharing ``keys`` into one metric row each."""
    groups: dict[tuple, list[dict]] = {}
    for r in results:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    rows = []
    for group in groups.values():
        first = group[0]
        pairs = pd.concat([g["pairs"] for g in group], ignore_index=True)
        row = {k: first[k] for k in keys} | {
            "cell_params": first["cell_params"], "seeds": [g["seed"] for g in group],
            "frames": int(sum(g["frames"] for g in group)),
            "source_density": float(np.mean([g["source_density"] for g in group])),
            "chance": first["chance"],
            "tolerance_mm": list(tolerances(first["cell_params"]["magnification"])),
            "s_per_frame": float(np.mean(np.concatenate([g["seconds"] for g in group]))),
            "warnings": sorted({w for g in group for w in g["warnings"]})}
        row |= metrics(pairs, sum(g["n_true"] for g in group),
                       sum(g["n_measured"] for g in group),
                       sum(g.get("n_hidden", 0) for g in group))
        rows.append(row)
    return rows


def band_of(cell_axis: str, density: float) -> str:
    """Density band of an acceptance cell: ``"sparse"`` or its density."""
    return "sparse" if cell_axis == "sparse" else f"{density:g}"


ACCEPTANCE_RECALL = {"sparse": (0.98, 0.99), "0.025": (0.95, 0.97), "0.05": (0.9, None),
                     "0.1": (0.75, 0.95)}
"""Least recall and precision per density band (None: no target)."""
ACCEPTANCE_COVERAGE = (0.60, 0.76, 0.92, 0.01)
"""Within 1 sigma between the first two, within 2 sigma at least the third, beyond 3
sigma at most the fourth, for x, y and z."""
ACCEPTANCE_DEPTH_SD_MM = 0.06
"""Plain depth error standard deviation on the sparse base cell, ideal optics."""
ACCEPTANCE_DIAMETER = (0.95, 1.05)


def acceptance_checks(rows: list[dict], bands: list[dict]) -> list[dict]:
    """Each acceptance target against the validation rows (realistic optics unless the
    target names the ideal): ``{"target", "where", "value", "pass"}``."""
    out = []

    def check(target, where, value, ok):
        good = value is not None and np.isfinite(value) and ok(value)
        out.append({"target": target, "where": where, "value": value, "pass": bool(good)})

    val = [r for r in rows if r["seed_set"] == "validation"]
    for r in val:
        if r["optics"] != "realistic":
            continue
        band = band_of(r["axis"], r["cell_params"]["density"])
        least_recall, least_precision = ACCEPTANCE_RECALL.get(band, (None, None))
        if least_recall is not None:
            check(f"recall >= {least_recall}", r["cell"], r["recall"],
                  lambda v, t=least_recall: v >= t)
        if least_precision is not None:
            check(f"precision >= {least_precision}", r["cell"], r["precision"],
                  lambda v, t=least_precision: v >= t)
    lo, hi, two, three = ACCEPTANCE_COVERAGE
    for b in bands:
        if b["seed_set"] != "validation" or b["optics"] != "realistic":
            continue
        where = f"band {b['band']} ({b['n_matched']} particles)"
        for ax in "xyz":
            check(f"{lo:.2f} <= within 1 sigma_{ax} <= {hi:.2f}", where, b[f"cov1_{ax}"],
                  lambda v: lo <= v <= hi)
            check(f"within 2 sigma_{ax} >= {two:.2f}", where, b[f"cov2_{ax}"],
                  lambda v: v >= two)
            check(f"beyond 3 sigma_{ax} <= {three:.2f}", where, b[f"out3_{ax}"],
                  lambda v: v <= three)
    for r in val:
        if r["optics"] == "ideal" and _is_base(r) and r["axis"] == "sparse":
            check(f"depth error sd <= {ACCEPTANCE_DEPTH_SD_MM} mm (ideal optics)", r["cell"],
                  r["std_z"], lambda v: v <= ACCEPTANCE_DEPTH_SD_MM)
    lo_d, hi_d = ACCEPTANCE_DIAMETER
    for r in val:
        check(f"{lo_d} <= median diameter ratio <= {hi_d}", f"{r['cell']}, {r['optics']}",
              r["diameter_ratio"], lambda v: lo_d <= v <= hi_d)
    return out


def _acceptance_lines(doc: dict) -> list[str]:
    checks = doc.get("acceptance") or []
    if not checks:
        return []
    n_pass = sum(c["pass"] for c in checks)
    lines = ["## Acceptance", "",
             f"{n_pass} of {len(checks)} targets met on the validation seeds (realistic "
             "optics unless the target says otherwise). Sparse cells at "
             f"{ACCEPTANCE_SPARSE:g} particles per microlens of their footprint (bound "
             f"{ACCEPTANCE_SPARSE_MAX:g}); coverage pooled over the cells of each density "
             "band and over all (`band all`). Not measured here: the depth error sd on "
             "hall2019 and the scaling curve (`benchmarks/bench_locate.py`).", "",
             "| target | where | value | met |", "| --- | --- | --- | --- |"]
    for c in checks:
        lines.append(f"| {c['target']} | {c['where']} | {_fmt(c['value'], '{:.3f}')} | "
                     f"{'yes' if c['pass'] else '**no**'} |")
    return lines + [""]


# --------------------------------------------------------------------------- report

_TABLE_COLS = [("recall", "recall", "{:.2f}"), ("hidden", "hidden", "{:.3f}"),
               ("recall_seen", "rec. seen", "{:.2f}"), ("precision", "prec.", "{:.2f}"),
               ("bias_z", "dz bias", "{:+.3f}"), ("std_z", "dz std", "{:.3f}"),
               ("rstd_z", "dz rstd", "{:.3f}"), ("lat_rms", "lat RMS", "{:.3f}"),
               ("out3_z", ">3sz", "{:.2f}"), ("cov1_x", "1s x", "{:.2f}"),
               ("cov1_y", "1s y", "{:.2f}"), ("cov1_z", "1s z", "{:.2f}"),
               ("cov2_x", "2s x", "{:.2f}"), ("cov2_y", "2s y", "{:.2f}"),
               ("cov2_z", "2s z", "{:.2f}"), ("diameter_ratio", "d ratio", "{:.2f}"),
               ("s_per_frame", "s/frame", "{:.2f}")]


def _fmt(value, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and not math.isfinite(value)) \
        else spec.format(value)


def emit_report(lines: list[str], out: Path | None) -> None:
    """Print the report ``lines`` and, with ``out``, write them there too (the one-camera
    studies' output)."""
    text = "\n".join(lines) + "\n"
    print(text)
    if out:
        out.write_text(text)


def markdown_table(df: pd.DataFrame, fmt=None) -> list[str]:
    """The lines of a markdown table of ``df``'s columns; each value through ``fmt(value,
    column)`` (default: floats to 3 significant digits, anything else as ``str``)."""
    def default(v, _column):
        return f"{v:.3g}" if isinstance(v, float) else str(v)
    fmt = fmt or default
    cols = [str(c) for c in df.columns]
    return (["| " + " | ".join(cols) + " |", "|" + " --- |" * len(cols)]
            + ["| " + " | ".join(fmt(v, c) for v, c in zip(row, cols)) + " |"
               for row in df.itertuples(index=False)])


def _table(rows: list[dict]) -> list[str]:
    head = ["preset", "axis", "optics", "M", "dens.", "N_s", "size mm", "seeds", "n true",
            "FP/frame", *[h for _, h, _ in _TABLE_COLS]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        p = r["cell_params"]
        size = (f"{p['size'][0]:g}-{p['size'][1]:g} lu" if isinstance(p["size"], list)
                else f"{p['size']:g}")
        fp = (r["n_measured"] - r["n_matched"]) / max(r["frames"], 1)
        cells = [p["preset"], r["axis"], r["optics"], f"{p['magnification']:g}",
                 f"{p['density']:g}", f"{r['source_density']:.3f}", size, str(len(r["seeds"])),
                 str(r["n_true"]), f"{fp:.1f}", *[_fmt(r.get(k), s) for k, _, s in _TABLE_COLS]]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _costs(rows: list[dict], seed_set: str, optics: str) -> list[str]:
    """Cells ranked by their loss against the base cell, for one seed set and optics."""
    sel = [r for r in rows if r["seed_set"] == seed_set and r["optics"] == optics]
    base = next((r for r in sel if r["axis"] == "base"), None)
    if base is None:
        return []
    lines = [f"Against the base cell ({optics}, {seed_set} seeds: recall {base['recall']:.2f}, "
             f"depth robust std {_fmt(base['rstd_z'], '{:.3f}')} mm, "
             f"lateral RMS {_fmt(base['lat_rms'], '{:.3f}')} mm):", ""]
    others = [r for r in sel if r["axis"] != "base"]
    by_recall = sorted(others, key=lambda r: r["recall"])
    lines.append("- lowest recall: " + "; ".join(
        f"{r['cell']} {r['recall']:.2f}" for r in by_recall[:4]))
    ratio = [(r["rstd_z"] / base["rstd_z"], r) for r in others
             if r["rstd_z"] is not None and math.isfinite(r["rstd_z"] or math.nan)
             and base["rstd_z"]]
    ratio.sort(key=lambda t: -t[0])
    lines.append("- largest depth robust std relative to base: " + "; ".join(
        f"{r['cell']} x{q:.1f} ({r['rstd_z']:.3f} mm)" for q, r in ratio[:4]))
    worst_bias = sorted(others, key=lambda r: -abs(r["bias_z"] or 0))
    lines.append("- largest |depth bias|: " + "; ".join(
        f"{r['cell']} {r['bias_z']:+.3f} mm" for r in worst_bias[:3] if r["bias_z"] is not None))
    return lines + [""]


def _effect_costs(rows: list[dict], per_seed: list[dict]) -> list[str]:
    """The one-effect cells against the ideal base cell of the same seed, worst first, per
    seed set."""
    lines = []
    for seed_set in ("validation", "development"):
        sel = [r for r in rows if r["seed_set"] == seed_set and r["axis"] == "effect"]
        if not sel:
            continue
        seed = sel[0]["seeds"][0]
        base = next((r for r in per_seed if r["seed"] == seed and r["axis"] == "base"
                     and r["optics"] == "ideal"), None)
        realistic = next((r for r in per_seed if r["seed"] == seed and r["axis"] == "base"
                          and r["optics"] == "realistic"), None)
        if base is None:
            continue
        sel = sel + ([dict(realistic, optics="ideal+all (realistic)")] if realistic else [])
        lines += [f"One effect group at a time on the base cell ({seed_set} seed {seed}), "
                  f"against the ideal base of that seed: recall {base['recall']:.2f}, precision "
                  f"{base['precision']:.2f}, depth robust std "
                  f"{_fmt(base['rstd_z'], '{:.3f}')} mm, 1s z {_fmt(base['cov1_z'], '{:.2f}')}. "
                  "Sorted by the rise in depth robust std:", "",
                  "| effect group | recall | precision | dz rstd mm (x ideal) | dz bias mm | "
                  "lat RMS mm | 1s z | d ratio |", "|---|---|---|---|---|---|---|---|"]

        def rise(r):
            v = r["rstd_z"]
            return -(v if v is not None and math.isfinite(v) else math.inf)

        for r in sorted(sel, key=rise):
            q = (r["rstd_z"] / base["rstd_z"] if r["rstd_z"] is not None and base["rstd_z"]
                 else math.nan)
            lines.append(f"| {r['optics'].removeprefix('ideal+')} | {r['recall']:.2f} | "
                         f"{_fmt(r['precision'], '{:.2f}')} | {_fmt(r['rstd_z'], '{:.3f}')} "
                         f"(x{_fmt(q, '{:.2f}')}) | {_fmt(r['bias_z'], '{:+.3f}')} | "
                         f"{_fmt(r['lat_rms'], '{:.3f}')} | {_fmt(r['cov1_z'], '{:.2f}')} | "
                         f"{_fmt(r['diameter_ratio'], '{:.2f}')} |")
        lines.append("")
    return lines


def write_report(out: Path, doc: dict) -> Path:
    meta = doc["meta"]
    rows = doc["rows"]
    lines = ["# Accuracy matrix of the perspective-shift locator", "",
             f"plenoptrack {meta['version']} (commit {meta['commit']}, source "
             f"{meta.get('source_sha256', '?')}), "
             f"{'quick' if meta['quick'] else 'acceptance' if meta.get('acceptance') else 'default'}"
             f" matrix, run {meta['date']}, "
             f"wall time {meta['wall_s'] / 60:.1f} min on {meta['cpus']} CPU(s).", "",
             "Generated by `benchmarks/accuracy_matrix.py`; the design (cells, seeds, matching "
             "tolerance, metric definitions) is in its module docstring. Claims quote the "
             "**validation** rows of the **realistic** optics.", "",
             "## Design", "",
             f"- development seeds (tuning allowed): {meta['dev_seeds']}; validation seeds "
             f"(never tuned on): {meta['validation_seeds']}",
             (f"- acceptance envelope: the base cell {meta['base']} at "
              f"{ACCEPTANCE_SPARSE:g} particles per microlens with every size, the mixed "
              f"sizes {ACCEPTANCE_MIXED[0]:g}-{ACCEPTANCE_MIXED[1]:g} mm, every "
              f"magnification and ellipsoids, and at densities "
              f"{', '.join(f'{d:g}' for d in ACCEPTANCE_DENSITIES)}; every cell with optics "
              "ideal and realistic" if meta.get("acceptance") else
              f"- base cell: {meta['base']}; one-axis sweeps around it; every cell with "
              f"optics ideal and realistic, the effect cells with the ideal optics plus one "
              f"group of effects"),
             f"- at least {meta['min_particles']} particles and "
             f"{meta.get('min_frames', 1)} frames per cell and seed (independent "
             "random scenes, one per frame)",
             f"- matching: Hungarian within an ellipsoid of half-axes {TOL_LATERAL_MM} mm "
             f"(x, y) x 0.5/|M| and {TOL_DEPTH_MM} mm (z) x (0.5/|M|)^2; `chance` = expected "
             "true particles in one tolerance ellipsoid",
             "- calibration: once per (magnification, optics, seed), simulated white image "
             "and default dot cards, `calibrate` defaults; frames flat-fielded with that "
             "white image",
             f"- locator settings: `{json.dumps(meta['locator'])}`; fragment cells with "
             f"`solve.shape_error = {FRAGMENT_SHAPE_ERROR}` (the uncertainty of an irregular "
             "body's centre of mass, which an experimenter imaging fragments sets)", ""]
    if meta["skipped"]:
        lines += ["Skipped:", ""] + [f"- {s}" for s in meta["skipped"]] + [""]
    lines += ["Cells (`footprint`: share of the field of view the volume covers; large "
              "particles shrink the volume, so their particles crowd a smaller field at the "
              "same density; the acceptance envelope's sparse cells count their density "
              "over the footprint):", "",
              "| cell | axis | n particles | frames per seed | tolerance x,y / z mm "
              "| chance | footprint |", "|---|---|---|---|---|---|---|"]
    for c in doc["cells"]:
        lines.append(f"| {c['name']} | {c['axis']} | {c['n_particles']} | {c['frames']} | "
                     f"{c['tolerance_mm'][0]:.3g} / {c['tolerance_mm'][1]:.3g} | "
                     f"{c['chance']:.3f} | {_fmt(c.get('footprint'), '{:.2f}')} |")
    lines += ["", "Columns: `dens.` particles per microlens; `N_s` source density (central-view "
              "image area over view area); `seeds` seeds whose calibration succeeded (of "
              f"{len(meta['dev_seeds'])}); `FP/frame` unmatched measured particles per frame; `dz` measured minus true depth, mm (`rstd` = 1.4826 "
              "MAD); `lat RMS` lateral RMS error, mm; `>3sz` fraction with |dz| > 3 sigma_z; "
              "`1s`/`2s` fraction within 1 / 2 sigma (ideal 0.68 / 0.95); `d ratio` median "
              "measured/true diameter; `s/frame` locate time.", ""]
    lines += _acceptance_lines(doc)
    for seed_set in ("validation", "development"):
        lines += [f"## Results, {seed_set} seeds", ""]
        sel = [r for r in rows if r["seed_set"] == seed_set]
        lines += _table(sel) + [""]
    lines += ["## What costs the most accuracy", ""]
    for seed_set in ("validation", "development"):
        for optics in OPTICS:
            lines += _costs(rows, seed_set, optics)
    lines += _effect_costs(rows, doc.get("per_seed", []))
    lines += ["## Calibrations", "", "| preset | M | optics | seed | ok | DLFC RMS px | "
              "simulate s | calibrate s | warnings / error |", "|---|---|---|---|---|---|---|---|---|"]
    for c in doc["calibrations"]:
        lines.append(f"| {c['preset']} | {c['magnification']:g} | {c['optics']} | {c['seed']} "
                     f"| {c['ok']} | {_fmt(c['rms_px'], '{:.3f}')} | {c['simulate_s']:.1f} | "
                     f"{_fmt(c['calibrate_s'], '{:.1f}')} | {c['error'] or c['warnings']} |")
    lines += ["", "## Figures", ""]
    for fig in doc["figures"]:
        lines.append(f"![{fig}]({fig})")
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _save(fig, path: Path) -> None:
    """PNG with a 64-colour palette: a third of the size, no visible loss on line plots."""
    import io

    import matplotlib.pyplot as plt
    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, dpi=72, format="png")
    plt.close(fig)
    buf.seek(0)
    Image.open(buf).convert("RGB").quantize(64).save(path, optimize=True)


def _is_base(row: dict) -> bool:
    """The base cell, or in the acceptance envelope its sparse twin (base parameters at
    ``ACCEPTANCE_SPARSE``): the point every sweep shares."""
    p = row["cell_params"]
    return row["axis"] == "base" or (
        row["axis"] == "sparse" and p["size"] == BASE["size"] and p["shape"] == BASE["shape"]
        and p["magnification"] == BASE["magnification"] and p["preset"] == BASE["preset"])


def write_figures(out: Path, rows: list[dict]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    names = []
    colours = {"ideal": "tab:blue", "realistic": "tab:red"}
    styles = {"development": "--", "validation": "-"}
    base = [r for r in rows if _is_base(r)]
    for axis, key, label, log in (("density", "density", "particles per microlens", True),
                                  ("size", "size", "particle diameter, mm", True),
                                  ("magnification", "magnification", "magnification |M|", False)):
        sel = [r for r in rows if r["axis"] == axis
               and not isinstance(r["cell_params"]["size"], list)] + base
        if len([r for r in sel if r["axis"] == axis]) == 0:
            continue
        fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), constrained_layout=True)
        for optics in OPTICS:
            for seed_set in ("development", "validation"):
                pts = sorted((abs(r["cell_params"][key]), r) for r in sel
                             if r["optics"] == optics and r["seed_set"] == seed_set)
                if not pts:
                    continue
                x = [p for p, _ in pts]
                kw = dict(color=colours[optics], ls=styles[seed_set], marker="o", ms=4,
                          label=f"{optics}, {seed_set}")

                def val(r, k):
                    v = r[k]
                    return np.nan if v is None else v

                axes[0, 0].plot(x, [val(r, "recall") for _, r in pts], **kw)
                axes[0, 1].plot(x, [val(r, "precision") for _, r in pts], **kw)
                axes[1, 0].plot(x, [val(r, "rstd_z") for _, r in pts], **kw)
                axes[1, 1].plot(x, [val(r, "bias_z") for _, r in pts], **kw)
                axes[0, 2].plot(x, [val(r, "diameter_ratio") for _, r in pts], **kw)
                axes[1, 2].plot(x, [val(r, "cov1_z") for _, r in pts], **kw)
        for a, title in zip(axes.flat, ("recall", "precision", "median diameter ratio",
                                        "depth robust std, mm", "depth bias, mm",
                                        "within 1 sigma_z (calibrated: 0.68)")):
            a.set_title(title)
            a.set_xlabel(label)
            if log:
                a.set_xscale("log")
            ticks = sorted({abs(r["cell_params"][key]) for r in sel})
            a.set_xticks(ticks, [f"{t:g}" for t in ticks])
            a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            a.grid(alpha=0.3)
        axes[0, 0].set_ylim(0, 1.02)
        axes[0, 1].set_ylim(0, 1.02)
        axes[1, 0].set_yscale("log")
        axes[1, 0].yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.2g"))
        axes[1, 0].yaxis.set_minor_formatter(matplotlib.ticker.FuncFormatter(_two_and_five))
        axes[1, 1].axhline(0, color="k", lw=0.5)
        axes[0, 0].legend(fontsize=8)
        fig.suptitle(f"Accuracy along the {axis} axis (other axes at the base cell)")
        name = f"lines_{axis}.png"
        _save(fig, out / name)
        names.append(name)

    cell_names = list(dict.fromkeys(r["cell"] for r in rows))
    modes = list(OPTICS) + (["one effect"] if any(r["optics"] not in OPTICS for r in rows)
                            else [])
    columns = [(o, s) for o in modes for s in ("development", "validation")]
    fig, axes = plt.subplots(1, 3, figsize=(14, 0.45 * len(cell_names) + 2),
                             constrained_layout=True)
    for a, (key, title, cmap) in zip(axes, (("recall", "recall", "viridis"),
                                            ("rstd_z", "depth robust std, mm", "magma_r"),
                                            ("cov1_z", "fraction |dz| <= 1 sigma_z", "viridis"))):
        grid = np.full((len(cell_names), len(columns)), np.nan)
        for r in rows:
            v = r[key]
            mode = r["optics"] if r["optics"] in OPTICS else "one effect"
            grid[cell_names.index(r["cell"]), columns.index((mode, r["seed_set"]))] = (
                np.nan if v is None else v)
        im = a.imshow(grid, aspect="auto", cmap=cmap)
        for i in range(grid.shape[0]):
            for j in range(grid.shape[1]):
                if np.isfinite(grid[i, j]):
                    r, g, b_, _ = im.cmap(im.norm(grid[i, j]))
                    a.text(j, i, f"{grid[i, j]:.2f}", ha="center", va="center", fontsize=7,
                           color="k" if 0.299 * r + 0.587 * g + 0.114 * b_ > 0.5 else "w")
        a.set_xticks(range(len(columns)), [f"{o}\n{s[:3]}" for o, s in columns], fontsize=8)
        a.set_yticks(range(len(cell_names)),
                     cell_names if a is axes[0] else [""] * len(cell_names), fontsize=8)
        a.set_title(title)
        fig.colorbar(im, ax=a, shrink=0.6)
    _save(fig, out / "heatmap.png")
    names.append("heatmap.png")
    return names


# --------------------------------------------------------------------------- main

def _write_json(path: Path, doc: dict) -> None:
    """One line per row, calibration and cell: readable and small."""
    parts = []
    for key, value in doc.items():
        if isinstance(value, list) and value and isinstance(value[0], dict):
            body = ",\n  ".join(json.dumps(v, default=str) for v in value)
            parts.append(f"{json.dumps(key)}: [\n  {body}\n ]")
        else:
            parts.append(f"{json.dumps(key)}: {json.dumps(value, default=str)}")
    path.write_text("{\n " + ",\n ".join(parts) + "\n}\n")


def _from_json(path: Path, out: Path) -> int:
    """Rebuild the report and figures of an earlier run from its ``rows.json``."""
    doc = json.loads(path.read_text())
    out.mkdir(parents=True, exist_ok=True)
    doc["figures"] = write_figures(out, doc["rows"])
    if path.resolve() != (out / "rows.json").resolve():
        _write_json(out / "rows.json", doc)
    print(f"rebuilt {write_report(out, doc)} and {len(doc['figures'])} figures from {path}")
    return 0


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _source_hash() -> str:
    """SHA-256 (12 hex digits) of the package's source files as imported: the commit alone
    does not pin a run made from a working tree with uncommitted edits."""
    import hashlib

    import plenoptrack

    root = Path(plenoptrack.__file__).parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:12]


def _two_and_five(value, _position=None) -> str:
    """Label of a minor tick of a log axis: only 2 and 5 times a power of ten, so that the
    labels of a decade spanning a short axis do not run into each other."""
    if not value > 0:
        return ""
    mantissa = round(value / 10 ** math.floor(math.log10(value)), 6)
    return f"{value:.2g}" if mantissa in (2.0, 5.0) else ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="one development and one validation seed, fewer cells (< 5 min)")
    parser.add_argument("--hall", action="store_true",
                        help="add the hall2019 cells (first dev and validation seed; slow)")
    parser.add_argument("--shapes", nargs="+", default=list(SHAPES),
                        help="particle shapes (default sphere, ellipsoid and fragment; shapes "
                             "the simulator does not know are skipped)")
    parser.add_argument("--acceptance", action="store_true",
                        help="run the acceptance envelope instead of the sweeps (sparse cells "
                             "of every size, mixed size, magnification and ellipsoids; "
                             "densities 0.025-0.1) and report each target met or not")
    parser.add_argument("--no-effects", action="store_true",
                        help="leave out the one-effect-at-a-time cells")
    parser.add_argument("--optics", nargs="+", choices=OPTICS, default=list(OPTICS),
                        help="optics modes (default both)")
    parser.add_argument("--min-particles", type=int, default=None,
                        help="fewest particles per cell and seed (default 80, quick 40)")
    parser.add_argument("--min-frames", type=int, default=None,
                        help="fewest frames per cell and seed (default 1, acceptance 3)")
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).parent / "results" / "accuracy_matrix",
                        help="output folder (default benchmarks/results/accuracy_matrix/)")
    parser.add_argument("--from-json", type=Path, metavar="ROWS_JSON",
                        help="only rebuild the report and figures from an earlier rows.json")
    args = parser.parse_args(argv)
    if args.from_json is not None:
        return _from_json(args.from_json, args.out)
    min_particles = args.min_particles or (40 if args.quick else 80)
    if min_particles < 1:
        parser.error(f"--min-particles must be at least 1; got {min_particles}")
    min_frames = args.min_frames or (3 if args.acceptance else 1)
    if min_frames < 1:
        parser.error(f"--min-frames must be at least 1; got {min_frames}")

    import plenoptrack
    from plenoptrack.locate.perspective import PerspectiveLocator

    t0 = time.perf_counter()
    commit, source_hash = _commit(), _source_hash()   # at the start: the tree may change later
    if args.acceptance and (args.quick or args.hall):
        parser.error("--acceptance runs its own cells; leave out --quick and --hall")
    cells, skipped = build_cells(quick=args.quick, hall=args.hall, shapes=args.shapes,
                                 effects=not args.no_effects, acceptance=args.acceptance)
    for s in skipped:
        print(f"skip: {s}", flush=True)
    seed_sets = {"development": DEV_SEEDS[:1] if args.quick else DEV_SEEDS,
                 "validation": VALIDATION_SEEDS[:1] if args.quick else VALIDATION_SEEDS}
    jobs = []   # (preset, magnification, optics, seed_set, seed) -> cells
    modes = list(dict.fromkeys(args.optics + [c.optics for c in cells if c.optics]))
    for optics in modes:
        mine = [c for c in cells if (c.optics == optics if c.optics else optics in args.optics)]
        for seed_set, seeds in seed_sets.items():
            for i, seed in enumerate(seeds):
                for key in dict.fromkeys((c.preset, c.magnification) for c in mine):
                    todo = [c for c in mine if (c.preset, c.magnification) == key
                            and (c.axis not in ("hall", "effect") or i == 0)]
                    if todo:
                        jobs.append((key[0], key[1], optics, seed_set, seed, todo))
    total = sum(len(j[-1]) for j in jobs)
    print(f"{len(cells)} cells x optics {args.optics} x seeds {seed_sets}: {len(jobs)} "
          f"calibrations, {total} cell runs", flush=True)
    results = []
    done = 0
    with tempfile.TemporaryDirectory(prefix="accuracy_matrix_") as tmp:
        runner = Runner(Path(tmp), min_particles, t0, min_frames)
        for preset_name, mag, optics, seed_set, seed, todo in jobs:
            calib, white, cal_optics = runner.calibrate(preset_name, mag, optics, seed)
            for cell in todo:
                done += 1
                if calib is None:
                    print(f"[{done:3d}/{total}] {cell.name} {optics} seed {seed}: no calibration, "
                          "skipped", flush=True)
                    continue
                r = runner.run_cell(cell, optics, seed, calib, white, cal_optics)
                r |= {"cell": cell.name, "axis": cell.axis, "cell_params": cell.params(),
                      "optics": optics, "seed_set": seed_set, "seed": seed}
                results.append(r)
                m = metrics(r["pairs"], r["n_true"], r["n_measured"], r["n_hidden"])
                print(f"[{done:3d}/{total}] {optics:9s} {seed_set[:3]} seed {seed} {cell.name}: "
                      f"n {r['n_true']} N_s {r['source_density']:.3f} recall {m['recall']:.2f} "
                      f"precision {m['precision']:.2f} dz bias {_fmt(m['bias_z'], '{:+.3f}')} "
                      f"rstd {_fmt(m['rstd_z'], '{:.3f}')} mm, 1s z {_fmt(m['cov1_z'], '{:.2f}')}, "
                      f"{np.mean(r['seconds']):.2f} s/frame "
                      f"(elapsed {time.perf_counter() - t0:.0f} s)", flush=True)
    rows = aggregate(results, ("cell", "axis", "optics", "seed_set"))
    order = {c.name: i for i, c in enumerate(cells)}
    rows.sort(key=lambda r: (r["seed_set"] != "validation", order[r["cell"]],
                             r["optics"] != "ideal", r["optics"]))
    bands, checks = [], []
    if args.acceptance:
        for r in results:
            r["band"] = band_of(r["axis"], r["cell_params"]["density"])
        bands = aggregate(results, ("band", "optics", "seed_set"))
        bands += [row | {"band": "all"} for row in aggregate(results, ("optics", "seed_set"))]
        checks = acceptance_checks(rows, bands)
    per_seed = [{k: v for k, v in r.items() if k not in ("pairs", "seconds", "cell_params")}
                | {"s_per_frame": float(np.mean(r["seconds"]))}
                | metrics(r["pairs"], r["n_true"], r["n_measured"], r["n_hidden"]) for r in results]
    args.out.mkdir(parents=True, exist_ok=True)
    figures = write_figures(args.out, rows)
    wall = time.perf_counter() - t0
    doc = {"meta": {"version": plenoptrack.__version__, "commit": commit,
                    "source_sha256": source_hash,
                    "date": time.strftime("%Y-%m-%d %H:%M"), "quick": args.quick,
                    "hall": args.hall, "acceptance": args.acceptance, "wall_s": wall, "cpus": len(__import__("os").sched_getaffinity(0)),
                    "dev_seeds": list(seed_sets["development"]),
                    "validation_seeds": list(seed_sets["validation"]),
                    "base": BASE, "min_particles": min_particles, "min_frames": min_frames,
                    "tolerance": {"lateral_mm_at_M0.5": TOL_LATERAL_MM,
                                  "depth_mm_at_M0.5": TOL_DEPTH_MM},
                    "locator": PerspectiveLocator().settings(), "skipped": skipped,
                    "python": sys.version.split()[0]},
           "cells": [c.params() | {"n_particles": n_particles(c),
                                   "footprint": footprint_fraction(c),
                                   "frames": frames_per_seed(c, min_particles, min_frames),
                                   "tolerance_mm": list(tolerances(c.magnification)),
                                   "chance": next((r["chance"] for r in results
                                                   if r["cell"] == c.name), math.nan)}
                     for c in cells],
           "calibrations": runner.calibrations, "rows": rows, "per_seed": per_seed,
           "figures": figures, "bands": bands, "acceptance": checks}
    doc = _clean(doc)
    _write_json(args.out / "rows.json", doc)
    report = write_report(args.out, doc)
    print(f"wrote {report}, {args.out / 'rows.json'} and {len(figures)} figures; "
          f"wall time {wall / 60:.1f} min", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
