"""Where a large particle's centroids leave the calibration: per-view residuals by ring.

    python benchmarks/rim_view_offset.py                      # ideal optics, seed 100
    python benchmarks/rim_view_offset.py --optics realistic

One sphere at the centre of the ``small`` camera (magnification -0.5, the accuracy
matrix's calibration: simulated white image and dot cards, ``calibrate`` defaults) at
each of ``--depths``, for each of ``--sizes``. Every view's detection nearest the
DLFC's prediction at the sphere's *true* position gives a centroid residual (measured
minus predicted, view pixels); its component along the view's direction from the centre
of the aperture (radial, positive outwards) is averaged over three groups of views: the
views the aperture rim cuts (valid share below ``--cut``), the other views of the outer
half of the aperture, and the inner views. A depth error towards the focal plane shows
as radial residuals of opposite sign at negative and positive depth. Prints and writes
(``--out``) the table; the uncertainty guide quotes it (``solve.rim_min_valid``).
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


def residuals(runner, size: float, optics: str, seed: int, depths, workdir: Path) -> pd.DataFrame:
    """One row per view and depth: the view's valid share, its offset from the aperture
    centre and the radial centroid residual, view pixels."""
    from plenoptrack.io import read_raw
    from plenoptrack.locate import PerspectiveLocator
    from plenoptrack.locate.perspective import _decoded, segment_frame
    from plenoptrack.simulate import random_particles, simulate_dataset
    from plenoptrack.simulate.scene import Scene

    cell = am._cell("size", size=size, density=0.001)
    calib, white, _ = runner.calibrate(cell.preset, cell.magnification, optics, seed)
    if calib is None:
        raise SystemExit(f"calibration failed for seed {seed}")
    camera, volume = am._camera(cell), am._volume(cell)
    one = random_particles(1, volume=volume, diameter_mm=size,
                           seed=np.random.default_rng([seed, int(size * 1000)]))
    truth = pd.concat([one] * len(depths), ignore_index=True).assign(
        frame=np.arange(len(depths)), particle=np.arange(len(depths)), x=0.0, y=0.0,
        z=np.asarray(depths, dtype=float))
    sim = simulate_dataset(cell.preset, workdir / f"d{size:g}", seed=seed,
                           scene=Scene(camera=camera, volume=volume, truth=truth, seed=seed),
                           magnification=cell.magnification, realism=am.realism_of(optics),
                           dotcard_depths=[])
    segment = PerspectiveLocator().segment
    rows = []
    for f, path in enumerate(sim.frame_paths):
        true = sim.truth[sim.truth.frame == f].iloc[0]
        lf = _decoded(read_raw(path), calib, f, white)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            det = segment_frame(lf, segment, frame=f)
        u, v = det["u"].to_numpy(float), det["v"].to_numpy(float)
        n = len(det)
        s, t = calib.dlfc.predict(np.full(n, true.x), np.full(n, true.y), np.full(n, true.z),
                                  u, v)
        det = det.assign(rs=det["s"] - s, rt=det["t"] - t,
                         miss=np.hypot(det["s"] - s, det["t"] - t))
        det = det[det["miss"] < 1.5].sort_values("miss").drop_duplicates(["u", "v"])
        valid = lf.valid_fraction[np.searchsorted(lf.v, det["v"].to_numpy(float)),
                                  np.searchsorted(lf.u, det["u"].to_numpy(float))]
        rows.append(pd.DataFrame({"size_mm": size, "z_mm": float(true.z),
                                  "du": det["u"].to_numpy(float), "dv": det["v"].to_numpy(float),
                                  "valid": valid, "rs": det["rs"].to_numpy(float),
                                  "rt": det["rt"].to_numpy(float)}))
    out = pd.concat(rows, ignore_index=True)
    # offsets from the centre of the aperture (the mean view of the frame)
    out["du"] -= out["du"].mean()
    out["dv"] -= out["dv"].mean()
    return out


def groups(table: pd.DataFrame, cut: float) -> np.ndarray:
    """Group of each row's view: cut by the rim, whole in the outer half, inner."""
    r = np.hypot(table["du"], table["dv"])
    return np.where(table["valid"] < cut, "cut", np.where(r > np.median(r), "outer, whole",
                                                          "inner"))


def summary(table: pd.DataFrame, cut: float) -> pd.DataFrame:
    """Mean radial residual per size, depth and group of views, view pixels."""
    r = np.hypot(table["du"], table["dv"])
    radial = (table["rs"] * table["du"] + table["rt"] * table["dv"]) / np.where(r > 0, r, np.inf)
    frame = table.assign(radial=radial, group=groups(table, cut))
    return frame.pivot_table(index=["size_mm", "z_mm"], columns="group", values="radial",
                             aggfunc="mean").reset_index()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[0.2, 1.0, 2.0])
    parser.add_argument("--depths", type=float, nargs="+", default=[-7.0, -3.5, 3.5, 7.0])
    parser.add_argument("--cut", type=float, default=0.97,
                        help="views with a smaller valid share count as cut by the rim")
    am.add_one_camera_arguments(parser)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    with am.one_camera_runner(args.workdir, t0) as (runner, workdir):
        table = pd.concat([residuals(runner, size, args.optics, args.seed, args.depths, workdir)
                           for size in args.sizes], ignore_index=True)
    result = summary(table, args.cut)
    first = table[(table["size_mm"] == table["size_mm"].iloc[0])
                  & (table["z_mm"] == table["z_mm"].iloc[0])]
    names, counts = np.unique(groups(first, args.cut), return_counts=True)
    views = ", ".join(f"{name} {count}" for name, count in zip(names, counts))
    lines = [f"# Radial centroid residuals by group of views, {args.optics} optics",
             "",
             f"`python benchmarks/rim_view_offset.py --optics {args.optics} --seed {args.seed}"
             f" --cut {args.cut:g}`"
             f" ({time.perf_counter() - t0:.0f} s): one sphere at the centre of the `small`"
             " camera (M -0.5) per depth; mean radial residual (measured minus the DLFC's"
             " prediction at the true position, positive away from the aperture centre),"
             f" view pixels. Views with a detection ({views}); cut: valid share below"
             f" {args.cut:g}; outer: the outer half of the views by distance from the"
             " aperture centre.", ""]
    lines += am.markdown_table(result, lambda v, c: f"{v:+.4f}" if isinstance(v, float)
                               and c not in ("size_mm", "z_mm") else f"{v:g}")
    am.emit_report(lines, args.out)


if __name__ == "__main__":
    main()
