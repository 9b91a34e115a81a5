"""Why the lateral errors are larger in x than in y: one cell under several cameras.

    python benchmarks/lateral_anisotropy.py                      # development seed 100
    python benchmarks/lateral_anisotropy.py --seeds 100 101 --out results/lateral_anisotropy.md

On the accuracy matrix's sparse cells the located particles' x errors are 1.4-2 times
their y errors, while ``sigma_x`` and ``sigma_y`` are equal, so y is over-covered. This
script locates the same cell (sparse 1 mm spheres, magnification -0.5, 0.005 particles per
microlens of the footprint) under several configurations of the simulated camera and
separates the candidate causes:

- the lattice: the hexagonal ``small`` camera blends two lenses along ``s`` in every sample
  of the decoded light field; ``small-rect`` samples every view on its lens centres;
- the optics: ideal against realistic;
- the simulator's rays per sensor pixel (16 by default, a fixed point-symmetric pattern
  per pixel, :func:`plenoptrack.simulate.render.sample_pattern`): every pixel samples its
  microlens at the same 16 points, so an image edge is quantised alike in every lens.

Each configuration gets its own calibration (white image and dot cards simulated with the
same camera, optics and rays) and its own frames. For the matched particles of each
class (refined: fitted to the view pixels, ``TriangulationFlag.REFINED``; centroid
solutions: the rest) the script prints the robust (1.4826 MAD) standard deviation of the
x and y errors and their ratio, and two properties of the particle's own centroids, in
view pixels: the robust spread over the particles of the mean offset of their centroids
from the positions the true particle predicts (``s`` and ``t``; an offset every view of
the particle shares) and the median per-view scatter of the centroids about the solved
particle. A shared offset larger in ``s`` than in ``t`` with an isotropic per-view
scatter places the anisotropy in what a particle's views have in common, before the
solve.

Takes about 15 seconds per configuration and seed on one core.
Nothing here tunes the locator: the seeds are development seeds of the accuracy matrix.
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

CONFIGS = {
    "hex-ideal-16": ("small", "ideal", 16),
    "rect-ideal-16": ("small-rect", "ideal", 16),
    "hex-ideal-64": ("small", "ideal", 64),
    "hex-realistic-16": ("small", "realistic", 16),
    "hex-realistic-64": ("small", "realistic", 64),
    "rect-realistic-16": ("small-rect", "realistic", 16),
}
MIN_PARTICLES = 80
SPARSE_DENSITY = 0.005   # particles per microlens of the footprint, as the matrix's sparse cells
MIN_CENTROIDS = 10


def _rstd(values) -> float:
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    if not values.size:
        return math.nan
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def locate_config(preset: str, optics: str, rays: int, seed: int, tmp: Path) -> pd.DataFrame:
    """Matched particles of the sparse 1 mm cell under one camera configuration.

    Returns one row per matched particle: ``dx, dy`` (mm), ``refined`` and, from the
    particle's inlier centroids, ``offset_s, offset_t`` (their mean offset from the
    positions the true particle predicts in the same views) and ``scatter_s, scatter_t``
    (their standard deviation about the solved particle's predictions), view pixels.
    """
    from plenoptrack.calibrate import calibrate
    from plenoptrack.evaluate import match_particles
    from plenoptrack.io import read_raw
    from plenoptrack.lightfield import decode
    from plenoptrack.locate.perspective import locate_frame
    from plenoptrack.locate.triangulate import TriangulationFlag
    from plenoptrack.simulate import simulate_dataset

    cell = am._cell("sparse", density=SPARSE_DENSITY, size=1.0, preset=preset)
    realism = am.realism_of(optics)
    folder = tmp / f"{preset}_{optics}_{rays}_{seed}"
    cal = simulate_dataset(preset, folder / "cal", seed=seed, n_particles=0,
                           magnification=cell.magnification, realism=realism,
                           samples_per_pixel=rays)
    calib, _report = calibrate(cal.white_path, cal.out_dir / "dotcards", cal.camera)
    white = decode(read_raw(cal.white_path), calib.grid)
    frames = am.frames_per_seed(cell, MIN_PARTICLES)
    scene = am.make_cell_scene(cell, seed, frames)
    sim = simulate_dataset(preset, folder / "frames", seed=seed, scene=scene,
                           magnification=cell.magnification, realism=realism,
                           dotcard_depths=[], samples_per_pixel=rays)
    tl, tz = am.tolerances(cell.magnification)

    def scaled(df):
        return df.assign(x=df["x"] / tl, y=df["y"] / tl, z=df["z"] / tz)

    rows = []
    for f, path in enumerate(sim.frame_paths):
        truth = sim.truth[sim.truth["frame"] == f].reset_index(drop=True)
        result = locate_frame(read_raw(path), calib, frame=f, white=white)
        found = result.particles.reset_index(drop=True)
        det = result.detections[result.detections["inlier"]]
        pairs = match_particles(scaled(found), scaled(truth), tolerance_mm=1.0)
        for mi, ti in zip(pairs["measured_index"], pairs["truth_index"]):
            mine = det[det["particle"] == mi]
            p, t = found.loc[mi], truth.loc[ti]
            row = {"dx": p["x"] - t["x"], "dy": p["y"] - t["y"],
                   "refined": bool(int(p["flags"]) & int(TriangulationFlag.REFINED))}
            if len(mine) >= MIN_CENTROIDS:
                u, v = mine["u"].to_numpy(float), mine["v"].to_numpy(float)
                ones = np.ones(len(mine))
                true_s, true_t = calib.dlfc.predict(t["x"] * ones, t["y"] * ones,
                                                    t["z"] * ones, u, v)
                fit_s, fit_t = calib.dlfc.predict(p["x"] * ones, p["y"] * ones,
                                                  p["z"] * ones, u, v)
                s, tt = mine["s"].to_numpy(float), mine["t"].to_numpy(float)
                row.update(offset_s=np.mean(s - true_s), offset_t=np.mean(tt - true_t),
                           scatter_s=np.std(s - fit_s), scatter_t=np.std(tt - fit_t))
            rows.append(row)
    shutil.rmtree(folder, ignore_errors=True)
    return pd.DataFrame(rows)


def summary_rows(name: str, pairs: pd.DataFrame) -> list[dict]:
    """One row per particle class (and all) of one configuration."""
    out = []
    for label, part in (("refined", pairs[pairs["refined"]]),
                        ("centroid", pairs[~pairs["refined"]]), ("all", pairs)):
        rx, ry = _rstd(part["dx"]) * 1e3, _rstd(part["dy"]) * 1e3
        out.append({"configuration": name, "particles": label, "n": len(part),
                    "x rsd um": rx, "y rsd um": ry, "x / y": rx / ry if ry > 0 else math.nan,
                    "shared offset s px": _rstd(part.get("offset_s", [])),
                    "shared offset t px": _rstd(part.get("offset_t", [])),
                    "scatter s px": float(np.nanmedian(part["scatter_s"])) if len(part) else math.nan,
                    "scatter t px": float(np.nanmedian(part["scatter_t"])) if len(part) else math.nan})
    return out


def _format(value, column: str) -> str:
    if not isinstance(value, float):
        return str(value)
    return f"{value:.4f}" if column.endswith("px") else f"{value:.2f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[am.DEV_SEEDS[0]])
    ap.add_argument("--configs", nargs="+", choices=list(CONFIGS), default=list(CONFIGS),
                    metavar="NAME", help=f"configurations to run (default all): {list(CONFIGS)}")
    ap.add_argument("--out", type=Path, help="also write the table to this markdown file")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    rows = []
    with tempfile.TemporaryDirectory(prefix="plenoptrack-anisotropy-") as tmp:
        for name in args.configs:
            preset, optics, rays = CONFIGS[name]
            t = time.perf_counter()
            pairs = pd.concat([locate_config(preset, optics, rays, seed, Path(tmp))
                               for seed in args.seeds], ignore_index=True)
            rows += summary_rows(name, pairs)
            print(f"{name}: {len(pairs)} matched particles ({time.perf_counter() - t:.0f} s)",
                  flush=True)
    table = pd.DataFrame(rows)
    lines = am.markdown_table(table, _format)
    print("\n".join(lines))
    if args.out:
        header = (f"`python benchmarks/lateral_anisotropy.py --seeds "
                  f"{' '.join(map(str, args.seeds))}` (commit {am._commit()}):\n\n")
        args.out.write_text(header + "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
