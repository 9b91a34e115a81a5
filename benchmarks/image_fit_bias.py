"""Depth offset of the image-model fit against the centroid solution, on isolated spheres.

    python benchmarks/image_fit_bias.py                         # 0.4, 1 and 2 mm, ideal
    python benchmarks/image_fit_bias.py --sizes 2 --edges 0.3 0.6 1.2
    python benchmarks/image_fit_bias.py --optics realistic --seed 101

The locator solves an isolated particle from the centroids of its images; a particle
whose images overlap a neighbour's is refitted to the view pixels with blurred discs
(:func:`plenoptrack.locate.refine.fit_images`, flags ``REFINED`` and ``SPLIT``). The
calibration (DLFC) relates image *centroids* to positions. This script measures how far
the disc fit's depth lies from the truth where the centroid solution's does not: one
sphere per frame at ``--depths`` depths spread over 95 % of the volume of the ``small``
camera at magnification -0.5 (the accuracy matrix's calibration: simulated white image
and dot cards, ``calibrate`` defaults), located with the default locator, then fitted
alone (no neighbours) with one disc from the located position, at each model edge width
of ``--edges`` (round, view pixels) and with the locator's own edge (``locator edge``:
:class:`~plenoptrack.locate.refine.ImageEdge`, wider along s on a hexagonal grid and
the calibration's blur at each depth), on the views more
than ``--min-valid`` valid (the locator's bar, 0.5, by default). Prints and writes
(``--out``) a table of the depth errors per size and depth, and per size the mean error
at negative and at positive depth.
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


def measure_size(runner, size: float, optics: str, seed: int, depths: int,
                 edges, workdir: Path, min_valid: float = 0.5) -> pd.DataFrame:
    """Depth errors (mm) of the centroid solution and of the disc fit at each edge width,
    one row per depth."""
    from plenoptrack.io import read_raw
    from plenoptrack.locate import PerspectiveLocator, locate_frame
    from plenoptrack.locate import refine
    from plenoptrack.locate.frame import FrameContext, _fit_views
    from plenoptrack.locate.perspective import _decoded, segment_frame
    from plenoptrack.simulate import random_particles, simulate_dataset
    from plenoptrack.simulate.scene import Scene

    cell = am._cell("size", size=size, density=0.001)
    calib, white, _ = runner.calibrate(cell.preset, cell.magnification, optics, seed)
    if calib is None:
        raise SystemExit(f"calibration failed for seed {seed}")
    camera, volume = am._camera(cell), am._volume(cell)
    z = np.linspace(0.95 * volume.bounds[2, 0], 0.95 * volume.bounds[2, 1], depths)
    rng = np.random.default_rng([seed, int(size * 1000)])
    # spheres of the simulator's own table (every truth column), placed by hand
    one = random_particles(1, volume=volume, diameter_mm=size, seed=rng)
    truth = pd.concat([one] * depths, ignore_index=True).assign(
        frame=np.arange(depths), particle=np.arange(depths),
        x=rng.uniform(-0.3, 0.3, depths), y=rng.uniform(-0.3, 0.3, depths), z=z)
    scene = Scene(camera=camera, volume=volume, truth=truth, seed=seed)
    sim = simulate_dataset(cell.preset, workdir / f"d{size:g}", seed=seed, scene=scene,
                           magnification=cell.magnification, realism=am.realism_of(optics),
                           dotcard_depths=[])
    locator = PerspectiveLocator()
    rows = []
    for f, path in enumerate(sim.frame_paths):
        true = sim.truth[sim.truth.frame == f].iloc[0]
        lf = _decoded(read_raw(path), calib, f, white)       # decoded once for both
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            found = locate_frame(lf, calib, frame=f, locator=locator).particles
        row = {"size_mm": size, "z_true": float(true.z)}
        if len(found):
            near = int(np.argmin(np.hypot(found.x - true.x, found.y - true.y)))
            p = found.iloc[near]
            row["centroid"] = float(p.z - true.z)
            ctx = FrameContext.build(lf, calib, segment_frame(lf, locator.segment, frame=f),
                                     locator)
            views_uv, view_rc = _fit_views(ctx)
            full = lf.valid_fraction[view_rc[:, 0], view_rc[:, 1]] > min_valid
            views_uv, view_rc = views_uv[full], view_rc[full]
            xyz = p[["x", "y", "z"]].to_numpy(float)[None]
            radius = 0.5 * float(p.diameter) * float(ctx.dlfc.local_magnification(*xyz.T)[0])
            default_edge = refine.EDGE_PX
            for edge in edges:
                refine.EDGE_PX = edge          # the model's edge width, read at each call
                try:
                    fit = refine.fit_images(ctx.dlfc, views_uv, view_rc, lf.data, xyz,
                                            np.array([[radius, 0.9]]), np.zeros((0, 3)),
                                            np.zeros((0, 2)))
                finally:
                    refine.EDGE_PX = default_edge
                row[f"fit edge {edge:g}"] = (float(fit.params[0, 2] - true.z)
                                             if fit is not None else np.nan)
            # the locator's own edge: wider along s on a hexagonal grid, the calibration's
            # blur at the particle's depth (refine.ImageEdge)
            fit = refine.fit_images(ctx.dlfc, views_uv, view_rc, lf.data, xyz,
                                    np.array([[radius, 0.9]]), np.zeros((0, 3)),
                                    np.zeros((0, 2)), edge=ctx.image_edge)
            row["fit locator edge"] = (float(fit.params[0, 2] - true.z)
                                       if fit is not None else np.nan)
        rows.append(row)
    return pd.DataFrame(rows)


def _is_error(column) -> bool:
    """Whether ``column`` holds depth errors (the centroid solution's or a fit's)."""
    return column == "centroid" or str(column).startswith("fit")


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Mean depth error per size at negative and at positive depth, mm."""
    cols = [c for c in table.columns if _is_error(c)]
    side = np.where(table["z_true"] < 0, "z < 0", "z >= 0")
    return table.groupby(["size_mm", side])[cols].mean()


def _markdown(table: pd.DataFrame) -> list[str]:
    """A markdown table of ``table``: depth errors signed to 4 decimals, other numbers
    as ``%g``."""
    def cell(v, column):
        if isinstance(v, (float, np.floating)):
            return f"{v:+.4f}" if _is_error(column) else f"{v:g}"
        return str(v)
    return am.markdown_table(table, cell)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=float, nargs="+", default=[0.4, 1.0, 2.0])
    parser.add_argument("--optics", default="ideal",
                        help="ideal, realistic, ideal+GROUP (one group of the simulator's "
                             "Realism, as in the accuracy matrix's effect rows) or "
                             "ideal+GROUP.FIELD (one effect of a group)")
    parser.add_argument("--seed", type=int, default=am.DEV_SEEDS[0])
    parser.add_argument("--depths", type=int, default=15)
    parser.add_argument("--edges", type=float, nargs="+", default=[0.6])
    parser.add_argument("--min-valid", type=float, default=0.5,
                        help="fit only the views with more than this fraction of valid "
                             "samples (the locator's: 0.5; 0.95 leaves out the views "
                             "the aperture's rim cuts)")
    parser.add_argument("--workdir", type=Path, default=None,
                        help="where simulated data go (default: a temporary folder)")
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).parent / "results" / "image_fit_bias.md")
    args = parser.parse_args(argv)
    try:
        am.realism_of(args.optics)
    except ValueError as exc:
        parser.error(f"--optics: {exc}; groups: {', '.join(am.effect_groups())}")
    import tempfile

    if args.depths < 2 or min(args.sizes) <= 0 or min(args.edges) <= 0:
        parser.error("--depths must be at least 2, --sizes and --edges positive")
    if not 0 <= args.min_valid < 1:
        parser.error(f"--min-valid must be in [0, 1); got {args.min_valid}")
    from plenoptrack.simulate import SceneError

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = args.workdir or Path(tmp)
        runner = am.Runner(workdir, 80, t0)
        try:
            table = pd.concat([measure_size(runner, s, args.optics, args.seed, args.depths,
                                            args.edges, workdir, args.min_valid)
                               for s in args.sizes], ignore_index=True)
        except SceneError as exc:
            parser.error(str(exc))
    wall = time.perf_counter() - t0
    pd.set_option("display.width", 200)
    print(table.round(4).to_string(index=False))
    print(summary(table).round(4).to_string())
    lines = ["# Depth offset of the image-model fit on isolated spheres", "",
             f"`python benchmarks/image_fit_bias.py --sizes {' '.join(f'{s:g}' for s in args.sizes)}"
             f" --optics {args.optics} --seed {args.seed} --depths {args.depths} --edges "
             f"{' '.join(f'{e:g}' for e in args.edges)} --min-valid {args.min_valid:g}` "
             f"({wall:.0f} s): `small` camera, "
             "magnification -0.5, one sphere per frame. Depth error (measured minus true, "
             "mm) of the centroid solution and of one disc fitted alone from it, per model "
             "edge width (view pixels).", "",
             "Mean error at negative and positive depth:", "",
             *_markdown(summary(table).reset_index().rename(columns={"level_1": "side"})),
             "", "Every depth:", "", *_markdown(table), ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print(f"wrote {args.out} ({wall:.0f} s)")


if __name__ == "__main__":
    main()
