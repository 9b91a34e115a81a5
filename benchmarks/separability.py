"""How many particles of a crowded frame can be told apart at all: recall bounds from the
true scenes of the acceptance matrix.

A particle whose image overlaps another particle's image in every view leaves no view
where it stands on its own. Its images can still be told apart where they merge (two
dark cores, an image-model fit of two discs), but a locator that works from regions
in the views cannot split them with certainty, and two particles whose image centres
stay within one radius of each other in every view look like one slightly larger image
everywhere. This script measures, on the scenes the acceptance matrix locates (the same
cells, seeds and particles, ``accuracy_matrix.make_cell_scene``), the share of particles
that such pairs leave:

- ``touch``: particles joined (chains included) by pairs whose images overlap in every
  view, centres closer than the sum of their radii, count as one; the bound is the
  number of such groups over the number of particles;
- ``core``: the same with pairs whose image centres stay within the larger radius of
  each other in every view: a locator that splits merged images down to that limit
  could reach this bound.

The image centres come from each seed's calibration (simulated white image and dot
cards, calibrated as the matrix does) and the radius from the true diameter and the
DLFC's local magnification; a view counts when the white image shows it at least half
lit. Nothing here is used by the locator: the bounds only say how far the measured
recall (``benchmarks/results/accuracy_acceptance/rows.json``) is from what the images
allow.

Run::

    python benchmarks/separability.py [--seeds 100 101 102 900 901 902] [--out DIR]

and it prints, per density cell and seed set, both bounds beside the recall of the
acceptance matrix (realistic optics) and writes ``separability.md`` to ``--out``
(default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as A  # noqa: E402

DEV, VALIDATION = (100, 101, 102), (900, 901, 902)
MIN_LIT = 0.5
"""Views whose white-image level is at least this share of the brightest view's count."""


def group_share(pairs: np.ndarray, n: int) -> float:
    """Connected groups of ``n`` particles joined by ``pairs`` (K, 2), over ``n``."""
    if n == 0:
        return math.nan
    if len(pairs) == 0:
        return 1.0
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[0] / n


def frame_bounds(centres_px: np.ndarray, radius_px: np.ndarray, xy_mm: np.ndarray,
                 reach_mm: float) -> dict[str, float]:
    """Both bounds of one frame.

    Parameters
    ----------
    centres_px : (P, V, 2) float ndarray
        Each particle's image centre in each view, view pixels.
    radius_px : (P,) float ndarray
        Image radius of each particle, view pixels.
    xy_mm : (P, 2) float ndarray
        Lateral positions, mm: only pairs within ``reach_mm`` are compared.
    reach_mm : float
        Largest lateral distance at which two images can meet in some view, mm.

    Returns
    -------
    dict
        ``touch`` and ``core`` (module notes).
    """
    n = len(radius_px)
    pairs = cKDTree(xy_mm).query_pairs(reach_mm, output_type="ndarray")
    if len(pairs) == 0:
        return {"touch": 1.0, "core": 1.0}
    i, j = pairs[:, 0], pairs[:, 1]
    sep = np.hypot(*(centres_px[i] - centres_px[j]).transpose(2, 0, 1))        # (K, V)
    touch = np.all(sep < (radius_px[i] + radius_px[j])[:, None], axis=1)
    core = np.all(sep < np.maximum(radius_px[i], radius_px[j])[:, None], axis=1)
    return {"touch": group_share(pairs[touch], n), "core": group_share(pairs[core], n)}


def cell_bounds(cell, seed: int, calib, white) -> dict[str, float]:
    """Bounds pooled over the frames the matrix locates for ``cell`` and ``seed``
    (weighted by particles)."""
    n = A.n_particles(cell)
    frames = max(1, math.ceil(80 / n))
    truth = A.make_cell_scene(cell, seed, frames).truth
    lit = white.valid_fraction >= MIN_LIT * white.valid_fraction.max()
    vi, ui = np.nonzero(lit)
    dlfc = calib.dlfc
    basis = dlfc.view_basis(white.u[ui], white.v[vi])
    out = {"touch": 0.0, "core": 0.0, "n": 0}
    for _, tr in truth.groupby("frame"):
        xyz = tr[["x", "y", "z"]].to_numpy(float)
        centres = np.asarray(dlfc.predict_in_views(xyz, basis))
        radius = 0.5 * tr["diameter"].to_numpy(float) * dlfc.local_magnification(*xyz.T)
        # two images can meet only if their parallax across the aperture can close the
        # gap: the largest image travel over the volume plus both diameters, in mm
        travel = np.ptp(centres, axis=1).max() / dlfc.local_magnification(*xyz.T).min()
        reach = float(travel + 2.0 * tr["diameter"].max())
        b = frame_bounds(centres, radius, xyz[:, :2], reach)
        for key in ("touch", "core"):
            out[key] += b[key] * len(tr)
        out["n"] += len(tr)
    return {"touch": out["touch"] / out["n"], "core": out["core"] / out["n"], "n": out["n"]}


def measured_recall(rows_path: Path) -> dict[tuple[str, str], float]:
    """Recall of the acceptance matrix per (cell, seed set), realistic optics."""
    if not rows_path.exists():
        return {}
    rows = json.loads(rows_path.read_text())["rows"]
    return {(r["cell"], r["seed_set"]): r["recall"] for r in rows
            if r["optics"] == "realistic"}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[*DEV, *VALIDATION])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    every = A.acceptance_cells()
    cells = [every[0]] + [c for c in every if c.axis == "density"]   # base cell, then crowds
    recall = measured_recall(Path(__file__).parent / "results" / "accuracy_acceptance"
                             / "rows.json")
    rows = []
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        runner = A.Runner(Path(tmp), 80, time.time())
        for seed in args.seeds:
            calib, white, _ = runner.calibrate("small", cells[0].magnification, "realistic",
                                               seed)
            if calib is None:
                continue
            for cell in cells:
                b = cell_bounds(cell, seed, calib, white)
                rows.append({"cell": cell.name, "density": cell.density, "seed": seed,
                             "seed_set": "validation" if seed in VALIDATION else "development",
                             **b})
                print(f"{cell.name:34s} seed {seed}: touch {b['touch']:.3f} core "
                      f"{b['core']:.3f} ({b['n']} particles)", flush=True)
    df = pd.DataFrame(rows)
    lines = ["# Separability of crowded frames: recall bounds from the true scenes", "",
             f"`python benchmarks/separability.py --seeds {' '.join(map(str, args.seeds))}`, "
             f"{time.perf_counter() - t0:.0f} s. Module notes of `benchmarks/separability.py`: "
             "`touch` counts particles whose images overlap another's in every view as one "
             "(groups over particles), `core` does so only for images whose centres stay "
             "within the larger radius of each other in every view. Measured recall: the "
             "acceptance matrix (`benchmarks/results/accuracy_acceptance/rows.json`), "
             "realistic optics.", "",
             "| cell | seeds | particles | bound `touch` | bound `core` | measured recall |",
             "| --- | --- | --- | --- | --- | --- |"]
    for (name, seed_set), g in df.groupby(["cell", "seed_set"], sort=False):
        w = g["n"].to_numpy(float)
        touch = float(np.dot(w, g["touch"]) / w.sum())
        core = float(np.dot(w, g["core"]) / w.sum())
        rec = recall.get((name, seed_set), math.nan)
        lines.append(f"| {name} | {seed_set} | {int(w.sum())} | {touch:.3f} | {core:.3f} | "
                     f"{rec:.3f} |")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "separability.md"
    tmp_path = path.with_suffix(".md.tmp")
    tmp_path.write_text("\n".join(lines) + "\n")
    tmp_path.replace(path)
    print("\n".join(lines[-(len(lines) - 6):]))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
