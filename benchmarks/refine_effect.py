"""The image-model refinement's effect on accuracy: the same frames located with and
without ``check.refine_images``.

    python benchmarks/refine_effect.py                      # validation seeds, realistic
    python benchmarks/refine_effect.py --seeds 100 101 102  # development seeds
    python benchmarks/refine_effect.py --optics ideal --cells base

For each cell (the cells of ``benchmarks/accuracy_matrix.py``: ``base``, ``sparse``
0.003 particles per microlens, ``crowded`` 0.03, ``ellipsoid``, ``m075`` magnification
-0.75, ``mixed`` sizes 0.2-2 mm at 0.003 per microlens, ``large`` 1 mm spheres) and seed, it calibrates as the
matrix does (simulated white image and dot cards), simulates ``--frames`` independent
random scenes and locates each frame twice, refinement off and on. Matching and metrics
are the matrix's (:func:`accuracy_matrix.match`, :func:`accuracy_matrix.metrics`);
printed per cell and setting: matched particles, recall, precision, depth standard
deviation and robust (1.4826 MAD) standard deviation, the fraction of depth errors beyond
0.15 mm, within 1 sigma and beyond 3 sigma (``|dz| / sigma_z``), lateral RMS, and the CPU
seconds of locating.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
import accuracy_matrix as am  # noqa: E402

CELLS = {
    "base": lambda: am._cell("base"),
    "sparse": lambda: am._cell("density", density=0.003),
    "crowded": lambda: am._cell("density", density=0.03),
    "ellipsoid": lambda: am._cell("shape", shape="ellipsoid"),
    "m075": lambda: am._cell("magnification", magnification=-0.75),
    "mixed": lambda: am._cell("size", size=(0.2, 2.0), density=0.003),
    "large": lambda: am._cell("size", size=1.0),
}


def run_cell(runner, cell, optics: str, seeds, frames: int) -> dict[str, dict]:
    """Metrics per setting (``off``, ``on``) pooled over the seeds."""
    from plenoptrack.io import read_raw
    from plenoptrack.locate import PerspectiveLocator, locate_frame
    from plenoptrack.simulate import simulate_dataset

    settings = {"off": PerspectiveLocator.from_dict({"check": {"refine_images": False}}),
                "on": PerspectiveLocator.from_dict({"check": {"refine_images": True}})}
    pairs = {k: [] for k in settings}
    counts = {k: [0, 0, 0.0] for k in settings}   # true, measured, CPU s
    for seed in seeds:
        calib, white, _ = runner.calibrate(cell.preset, cell.magnification, optics, seed)
        if calib is None:
            print(f"  seed {seed}: calibration failed, skipped")
            continue
        scene = am.make_cell_scene(cell, seed, frames)
        folder = runner.tmp / f"frames_{seed}"
        sim = simulate_dataset(cell.preset, folder, seed=seed, scene=scene,
                               magnification=cell.magnification,
                               realism=am.realism_of(optics), dotcard_depths=[])
        for f, path in enumerate(sim.frame_paths):
            truth = sim.truth[sim.truth["frame"] == f].reset_index(drop=True)
            raw = read_raw(path)
            for name, locator in settings.items():
                t0 = time.process_time()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    found = locate_frame(raw, calib, frame=f, white=white,
                                         locator=locator).particles.reset_index(drop=True)
                counts[name][2] += time.process_time() - t0
                counts[name][0] += len(truth)
                counts[name][1] += len(found)
                pairs[name].append(am.match(found, truth, cell.magnification))
    out = {}
    for name in settings:
        pooled = pd.concat(pairs[name], ignore_index=True) if pairs[name] else pd.DataFrame(
            columns=["dx", "dy", "dz", "sigma_x", "sigma_y", "sigma_z", "diameter",
                     "true_diameter"])
        m = am.metrics(pooled, counts[name][0], counts[name][1])
        dz = pooled["dz"].to_numpy(float)
        m["beyond_015"] = float(np.mean(np.abs(dz) > 0.15)) if len(dz) else math.nan
        m["cpu_s"] = counts[name][2]
        out[name] = m
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", nargs="+", choices=list(CELLS), default=list(CELLS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(am.VALIDATION_SEEDS),
                        help="scene and camera seeds (default: the matrix's validation seeds)")
    parser.add_argument("--optics", choices=["ideal", "realistic"], default="realistic")
    parser.add_argument("--frames", type=int, default=4, help="frames per cell and seed")
    args = parser.parse_args(argv)
    print(f"optics {args.optics}, seeds {args.seeds}, {args.frames} frames per cell and seed")
    print(f"{'cell':10s} {'set':4s} {'matched':>7s} {'recall':>6s} {'prec.':>6s} "
          f"{'sd z':>6s} {'rsd z':>6s} {'>0.15':>6s} {'1 sig':>6s} {'>3 sig':>6s} "
          f"{'lat':>7s} {'CPU s':>6s}")
    with tempfile.TemporaryDirectory(prefix="refine_effect_") as tmp:
        runner = am.Runner(Path(tmp), 0, time.perf_counter())
        for name in args.cells:
            result = run_cell(runner, CELLS[name](), args.optics, args.seeds, args.frames)
            for setting, m in result.items():
                print(f"{name:10s} {setting:4s} {m['n_matched']:7d} {m['recall']:6.3f} "
                      f"{m['precision']:6.3f} {m['std_z']:6.3f} {m['rstd_z']:6.3f} "
                      f"{m['beyond_015']:6.3f} {m['cov1_z']:6.2f} {m['out3_z']:6.3f} "
                      f"{m['lat_rms']:7.4f} {m['cpu_s']:6.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
