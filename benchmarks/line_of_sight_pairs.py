"""Depth separation of two large particles on nearly one line of sight.

    python benchmarks/line_of_sight_pairs.py                      # ideal optics, seed 100
    python benchmarks/line_of_sight_pairs.py --optics realistic

Two spheres of ``--size`` mm (2 by default) whose images overlap in every view, one
behind the other: ``--lateral`` offsets (mm) between their centres across the line of
sight, four depth pairs 5.5-6.5 mm apart, two pairs per frame 4.4 mm apart laterally, on
the ``small`` camera at magnification -0.5 (the accuracy matrix's calibration: simulated
white image and dot cards, ``calibrate`` defaults). Each frame is located with the
default locator; each true sphere is matched to the nearest located particle (lateral
distance plus a tenth of the depth difference). Per lateral offset: the error of the
measured depth separation (far minus near, measured minus true; mean, least and largest
over the four pairs), the mean of the two spheres' depth errors, and the median sigma_z.
Prints and writes (``--out``) the table; the locating guide quotes it (the image model
of two overlapping images, :mod:`plenoptrack.locate.refine`).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
import accuracy_matrix as am  # noqa: E402

DEPTH_PAIRS = [(-4.0, 2.0), (-1.0, 5.0), (1.0, 7.0), (-6.0, 0.5)]
"""Depths (mm, before the scene's own offset) of the near and far sphere of each pair."""

CENTRES = [(-2.2, 0.0), (2.2, 0.0)]
"""Lateral centres (mm) of the two pairs of a frame."""


def scene_truth(size: float, lateral, volume, seed: int) -> pd.DataFrame:
    """One row per sphere: two pairs per frame, the frames running through ``lateral``
    and the two halves of :data:`DEPTH_PAIRS`; columns of the simulator's truth plus
    ``pair``, ``member`` (0 near, 1 far) and ``lateral``."""
    from plenoptrack.simulate import random_particles

    rows = []
    frame = 0
    for offset in lateral:
        for half in range(2):
            for k, (cx, cy) in enumerate(CENTRES):
                near, far = DEPTH_PAIRS[2 * half + k]
                angle = 0.7 * k + offset           # a different direction for each pair
                rows.append(dict(frame=frame, x=cx, y=cy, z=near, pair=2 * half + k,
                                 member=0, lateral=offset))
                rows.append(dict(frame=frame, x=cx + offset * np.cos(angle),
                                 y=cy + offset * np.sin(angle), z=far, pair=2 * half + k,
                                 member=1, lateral=offset))
            frame += 1
    layout = pd.DataFrame(rows)
    one = random_particles(1, volume=volume, diameter_mm=size,
                           seed=np.random.default_rng([seed, int(size * 1000)]))
    truth = pd.concat([one] * len(layout), ignore_index=True)
    truth[["frame", "x", "y", "z"]] = layout[["frame", "x", "y", "z"]].to_numpy()
    truth["frame"] = truth["frame"].astype(int)
    truth["particle"] = np.arange(len(layout))
    return truth, layout


def measure(runner, size: float, optics: str, seed: int, lateral, workdir: Path) -> pd.DataFrame:
    """One row per true sphere: its pair, lateral offset and the nearest located
    particle's errors (mm) and sigma_z."""
    from plenoptrack.io import read_raw
    from plenoptrack.locate.perspective import locate_frame
    from plenoptrack.simulate import simulate_dataset
    from plenoptrack.simulate.scene import Scene, default_volume

    cell = am._cell("size", size=size, density=0.001)
    calib, white, _ = runner.calibrate(cell.preset, cell.magnification, optics, seed)
    if calib is None:
        raise SystemExit(f"calibration failed for seed {seed}")
    camera = am._camera(cell)
    volume = default_volume(camera, diameter_mm=0.4)     # room for pairs 4.4 mm apart
    truth, layout = scene_truth(size, lateral, volume, seed)
    sim = simulate_dataset(cell.preset, workdir / "pairs", seed=seed,
                           scene=Scene(camera=camera, volume=volume, truth=truth, seed=seed),
                           magnification=cell.magnification, realism=am.realism_of(optics),
                           dotcard_depths=[])
    rows = []
    for frame, path in enumerate(sim.frame_paths):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            found = locate_frame(read_raw(path), calib, frame=frame, white=white).particles
        true = sim.truth[sim.truth["frame"] == frame]
        for index, t in true.iterrows():
            miss = (np.hypot(found["x"] - t.x, found["y"] - t.y)
                    + np.abs(found["z"] - t.z) / 10.0).to_numpy()
            m = found.iloc[int(np.argmin(miss))]
            rows.append(dict(lateral=layout.at[index, "lateral"], frame=frame,
                             pair=layout.at[index, "pair"], member=layout.at[index, "member"],
                             z=t.z, dx=m.x - t.x, dy=m.y - t.y, dz=m.z - t.z,
                             sigma_z=m.sigma_z, flags=int(m["flags"])))
    return pd.DataFrame(rows)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Per lateral offset: the depth-separation error of the pairs (mean, least,
    largest), the mean depth error of their spheres and the median sigma_z, mm."""
    pairs = table.sort_values("member").groupby(["lateral", "frame", "pair"])
    per_pair = pairs.apply(lambda p: pd.Series({
        "separation": p["dz"].iloc[1] - p["dz"].iloc[0], "mean": p["dz"].mean()}),
        include_groups=False).reset_index()
    out = per_pair.groupby("lateral").agg(
        separation_error=("separation", "mean"), least=("separation", "min"),
        largest=("separation", "max"), mean_depth_error=("mean", "mean"))
    out["median_sigma_z"] = table.groupby("lateral")["sigma_z"].median()
    return out.reset_index()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=float, default=2.0, help="sphere diameter, mm")
    parser.add_argument("--lateral", type=float, nargs="+",
                        default=[0.1, 0.2, 0.3, 0.4, 0.5, 0.7, 0.9, 1.2],
                        help="lateral offsets between a pair's centres, mm")
    am.add_one_camera_arguments(parser)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    with am.one_camera_runner(args.workdir, t0) as (runner, workdir):
        table = measure(runner, args.size, args.optics, args.seed, args.lateral, workdir)
    result = summary(table)
    lines = [f"# Depth separation of {args.size:g} mm spheres on nearly one line of sight, "
             f"{args.optics} optics", "",
             f"`python benchmarks/line_of_sight_pairs.py --optics {args.optics} --seed "
             f"{args.seed} --size {args.size:g}` ({time.perf_counter() - t0:.0f} s): per "
             "lateral offset (mm) of a pair's centres, four pairs 5.5-6.5 mm apart in depth "
             "on the `small` camera (M -0.5); error of the measured depth separation (far "
             "minus near; mean, least and largest over the pairs), mean depth error of "
             "the spheres and median sigma_z, mm.", ""]
    def cell(value, column):
        if column == "lateral":
            return f"{value:g}"
        return f"{value:.3f}" if column == "median_sigma_z" else f"{value:+.3f}"

    lines += am.markdown_table(result, cell)
    am.emit_report(lines, args.out)


if __name__ == "__main__":
    main()
