"""Depth error of isolated particles against their place on the microlens grid.

    python benchmarks/near_focus_pattern.py                     # small camera, ideal optics
    python benchmarks/near_focus_pattern.py --preset small-rect # square lattice: no resampling
    python benchmarks/near_focus_pattern.py --optics realistic --fit

Eight spheres (``--size``, default 0.4 mm) at the depths ``--depths``, far apart on a
4 x 2 grid, are moved sideways together in ``--steps`` steps of ``--step-um`` along
``--axis`` (default x, along the lens rows; 24 steps of 14 um: 2.2 microlens pitches in
object space at magnification -0.5), on ``--lines`` lines offset across the steps by
equal fractions of the lattice's repeat distance that way (one line crosses the
lattice's cell at one place only), each position rendered ``--repeats`` times with fresh
noise, and located with the default locator on the accuracy matrix's calibration of the camera (simulated white image
and dot cards, ``calibrate`` defaults). A particle's depth error then splits into the
part its noise draws share (the same at the same place: sampling by the microlenses) and
the rest (noise). With ``--fit`` every located particle is also refitted alone to its
view pixels with the image model (one blurred disc,
:func:`plenoptrack.locate.refine.fit_images`), which the locator otherwise does only for
particles whose images overlap.

Per depth the script prints and writes (``--out``): the spread over the positions of the
error the draws share (``fixed sd``), of the rest (``noise sd``), the correlation of the
draws, the mean error, and the share of the fixed error's variance at the object-space
lattice's repeat distance along the steps and its second harmonic (``at lattice``: 1 for
a pattern that repeats with the lens grid; the repeat is the microlens pitch along x, and
along y the pitch on a square lattice and two lens rows, 1.73 pitches, on a hexagonal
one).
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

DEPTHS = (-7.5, -5.0, -2.5, -1.0, 1.0, 2.5, 5.0, 7.5)


def scene_truth(volume, size: float, depths, steps: int, step_mm: float, repeats: int,
                seed: int, axis: str = "x", lines: int = 1,
                across_mm: float = 0.0) -> pd.DataFrame:
    """One frame per (line, repeat, step): the particles at ``depths`` on a 4 x 2 grid
    filling 60-70 % of the volume's cross-section, shifted by ``step * step_mm`` along
    ``axis`` (``"x"``, along the lens rows, or ``"y"``) and, for line ``i`` of
    ``lines``, by ``i / lines * across_mm`` across it (each line crosses the lattice's
    cell at another place)."""
    from plenoptrack.simulate import random_particles

    n = len(depths)
    cols = int(np.ceil(n / 2))
    b = volume.bounds
    room_x = steps * step_mm if axis == "x" else across_mm
    room_y = steps * step_mm if axis == "y" else across_mm
    xs = np.linspace(0.7 * b[0, 0], 0.7 * b[0, 1] - room_x, cols)
    ys = np.linspace(0.6 * b[1, 0], 0.6 * b[1, 1] - room_y, 2)
    gx, gy = (a.ravel()[:n] for a in np.meshgrid(xs, ys))
    base = random_particles(n, volume=volume, diameter_mm=size,
                            seed=np.random.default_rng([seed, 77]))
    base = base.assign(x=gx, y=gy, z=np.asarray(depths, dtype=float))
    other = "y" if axis == "x" else "x"
    frames = []
    for line in range(lines):
        for r in range(repeats):
            for k in range(steps):
                f = len(frames)
                shift = {axis: base[axis].to_numpy() + k * step_mm,
                         other: base[other].to_numpy() + line / lines * across_mm}
                frames.append(base.assign(**shift, frame=f, particle=np.arange(n) + n * f,
                                          slot=np.arange(n), step=k, repeat=r, line=line))
    return pd.concat(frames, ignore_index=True)


def locate_all(sim, truth: pd.DataFrame, calib, white, magnification: float,
               fit: bool, locking_from_calibration: bool = False) -> pd.DataFrame:
    """Depth error (mm) of each particle at each frame: the located position's and, with
    ``fit``, the lone image fit's."""
    from plenoptrack.evaluate import match_particles
    from plenoptrack.io import read_raw
    from plenoptrack.locate import PerspectiveLocator, locate_frame
    from plenoptrack.locate.frame import FrameContext, _fit_views
    from plenoptrack.locate.perspective import _decoded, segment_frame
    from plenoptrack.locate.refine import fit_images

    locator = PerspectiveLocator().updated(
        {"solve": {"locking_from_calibration": bool(locking_from_calibration)}},
        source="near_focus_pattern")
    tl, tz = am.tolerances(magnification)
    rows = []
    for f, path in enumerate(sim.frame_paths):
        t = truth[truth.frame == f].reset_index(drop=True)
        lf = _decoded(read_raw(path), calib, f, white)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            found = locate_frame(lf, calib, frame=f, locator=locator).particles
        if len(found) == 0:
            continue
        pairs = match_particles(found.assign(x=found.x / tl, y=found.y / tl, z=found.z / tz),
                                t.assign(x=t.x / tl, y=t.y / tl, z=t.z / tz), tolerance_mm=1.0)
        ctx = views_uv = view_rc = None
        if fit:
            ctx = FrameContext.build(lf, calib, segment_frame(lf, locator.segment, frame=f),
                                     locator)
            views_uv, view_rc = _fit_views(ctx)
        for m, i in zip(pairs["measured_index"], pairs["truth_index"]):
            p, true = found.iloc[m], t.iloc[i]
            row = {"slot": int(true["slot"]), "line": int(true["line"]),
                   "step": int(true["step"]), "repeat": int(true["repeat"]),
                   "z_true": float(true["z"]), "located": float(p["z"] - true["z"])}
            if fit:
                xyz = p[["x", "y", "z"]].to_numpy(float)[None]
                radius = 0.5 * float(p.diameter) * float(ctx.dlfc.local_magnification(*xyz.T)[0])
                lone = fit_images(ctx.dlfc, views_uv, view_rc, lf.data, xyz,
                                  np.array([[radius, 0.9]]), np.zeros((0, 3)), np.zeros((0, 2)))
                row["image fit"] = float(lone.params[0, 2] - true["z"]) if lone is not None else np.nan
            rows.append(row)
    return pd.DataFrame(rows)


def lattice_share(values: np.ndarray, step_mm: float, repeat_mm: float) -> float:
    """Share of the variance of ``values`` (one per step) that sinusoids at the
    lattice's object-space repeat distance and its second harmonic explain: ``R^2`` of
    their least-squares fit with a constant."""
    y = np.asarray(values, dtype=float)
    ok = np.isfinite(y)
    if ok.sum() < 6:
        return float("nan")
    x = np.arange(len(y))[ok] * step_mm
    y = y[ok]
    w = 2 * np.pi / repeat_mm
    design = np.column_stack([np.ones_like(x), np.cos(w * x), np.sin(w * x),
                              np.cos(2 * w * x), np.sin(2 * w * x)])
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    total = float(np.sum((y - y.mean()) ** 2))
    left = float(np.sum((y - design @ coef) ** 2))
    return 1.0 - left / total if total > 0 else float("nan")


def summarise(errors: pd.DataFrame, step_mm: float, repeat_mm: float) -> pd.DataFrame:
    """Per depth and solution, over the lines: fixed sd (RMS over the lines, and the
    least and largest line's), noise sd (RMS), correlation of the draws and share at the
    lattice's repeat distance (means over the lines), mean error; um where a length."""
    per_line = _per_line(errors, step_mm, repeat_mm)
    rows = []
    for (z, col), g in per_line.groupby(["z_mm", "solution"]):
        rows.append({"z_mm": z, "solution": col, "lines": len(g),
                     "positions": int(g["positions"].sum()),
                     "mean_um": float(g["mean_um"].mean()),
                     "fixed_sd_um": float(np.sqrt(np.mean(g["fixed_sd_um"] ** 2))),
                     "fixed_sd_lines_um": f"{g['fixed_sd_um'].min():.0f}-"
                                          f"{g['fixed_sd_um'].max():.0f}",
                     "noise_sd_um": float(np.sqrt(np.mean(g["noise_sd_um"] ** 2))),
                     "draws_corr": float(g["draws_corr"].mean()),
                     "at_lattice": float(g["at_lattice"].mean())})
    return pd.DataFrame(rows).sort_values(["solution", "z_mm"]).reset_index(drop=True)


def _per_line(errors: pd.DataFrame, step_mm: float, repeat_mm: float) -> pd.DataFrame:
    """:func:`summarise`'s figures for each particle's line."""
    rows = []
    columns = [c for c in ("located", "image fit") if c in errors.columns]
    for (slot, line, z), g in errors.groupby(["slot", "line", "z_true"]):
        for col in columns:
            table = g.pivot_table(index="step", columns="repeat", values=col)
            if table.shape[1] < 2:
                continue
            a, b = table.iloc[:, 0].to_numpy(), table.iloc[:, 1].to_numpy()
            both = np.isfinite(a) & np.isfinite(b)
            fixed = table.mean(axis=1).to_numpy()
            noise = (a - b)[both] / np.sqrt(2)
            rows.append({"z_mm": z, "solution": col, "positions": int(both.sum()),
                         "mean_um": 1e3 * float(np.nanmean(fixed)),
                         "fixed_sd_um": 1e3 * float(np.nanstd(fixed, ddof=1)),
                         "noise_sd_um": 1e3 * float(np.std(noise, ddof=1)),
                         "draws_corr": float(np.corrcoef(a[both], b[both])[0, 1]),
                         "at_lattice": lattice_share(fixed, step_mm, repeat_mm)})
    return pd.DataFrame(rows)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="small", choices=("small", "small-rect"))
    parser.add_argument("--optics", default="ideal", choices=am.OPTICS)
    parser.add_argument("--seed", type=int, default=am.DEV_SEEDS[0])
    parser.add_argument("--size", type=float, default=0.4, help="sphere diameter, mm")
    parser.add_argument("--depths", type=float, nargs="+", default=list(DEPTHS),
                        help="one particle at each depth, mm (at most 8)")
    parser.add_argument("--steps", type=int, default=24)
    parser.add_argument("--step-um", type=float, default=14.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--axis", default="x", choices=("x", "y"),
                        help="direction of the steps (x runs along the lens rows)")
    parser.add_argument("--lines", type=int, default=3,
                        help="lines of steps, offset across the steps by equal fractions "
                             "of the lattice's repeat distance across them")
    parser.add_argument("--fit", action="store_true",
                        help="also refit each particle alone with the image model")
    parser.add_argument("--locking-from-calibration", action="store_true",
                        help="locate with solve.locking_from_calibration: frames too "
                             "sparse for their own pixel-locking pattern use the "
                             "calibration's")
    parser.add_argument("--out", type=Path, default=None,
                        help="markdown file (default benchmarks/results/"
                             "near_focus_pattern_PRESET_OPTICS.md)")
    args = parser.parse_args(argv)
    if (not 1 <= len(args.depths) <= 8 or args.steps < 6 or args.repeats < 2
            or args.lines < 1):
        parser.error("give 1-8 depths, at least 6 steps, at least 2 repeats and 1 line")
    if args.size <= 0 or args.step_um <= 0:
        parser.error("--size and --step-um must be positive")
    out = args.out or (Path(__file__).parent / "results"
                       / f"near_focus_pattern_{args.preset}_{args.optics}"
                          f"{'' if args.axis == 'x' else '_y'}.md")
    from plenoptrack.simulate import simulate_dataset
    from plenoptrack.simulate.scene import Scene

    cell = am._cell("size", preset=args.preset, size=args.size, density=0.001)
    camera, volume = am._camera(cell), am._volume(cell)
    step_mm = args.step_um / 1000
    pitch_mm = camera.microlens_pitch_um / 1000 / abs(camera.magnification)
    hex_rows = pitch_mm * math.sqrt(3.0)      # two lens rows of a hexagonal lattice
    repeat_mm = hex_rows if args.axis == "y" and camera.grid_type == "hex" else pitch_mm
    across_mm = hex_rows if args.axis == "x" and camera.grid_type == "hex" else pitch_mm
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        runner = am.Runner(Path(tmp), 80, t0)
        calib, white, _ = runner.calibrate(cell.preset, cell.magnification, args.optics,
                                           args.seed)
        if calib is None:
            raise SystemExit(f"calibration failed for seed {args.seed}")
        truth = scene_truth(volume, args.size, args.depths, args.steps, step_mm,
                            args.repeats, args.seed, args.axis, args.lines, across_mm)
        scene = Scene(camera=camera, volume=volume,
                      truth=truth.drop(columns=["slot", "step", "repeat", "line"]),
                      seed=args.seed)
        sim = simulate_dataset(cell.preset, Path(tmp) / "frames", seed=args.seed, scene=scene,
                               magnification=cell.magnification,
                               realism=am.realism_of(args.optics), dotcard_depths=[])
        # the data set's truth is in the calibration's frame (the traverse zero and the
        # dot grid's origin), row for row the scene's
        target = sim.truth.reset_index(drop=True).assign(
            slot=truth["slot"].to_numpy(), step=truth["step"].to_numpy(),
            repeat=truth["repeat"].to_numpy(), line=truth["line"].to_numpy())
        errors = locate_all(sim, target, calib, white, cell.magnification, args.fit,
                            args.locking_from_calibration)
    wall = time.perf_counter() - t0
    table = summarise(errors, step_mm, repeat_mm)
    pd.set_option("display.width", 200)
    print(table.round(3).to_string(index=False))
    command = " ".join(["python benchmarks/near_focus_pattern.py", *(argv or sys.argv[1:])])
    text = ["# Depth error of isolated particles against their place on the microlens grid",
             "", f"`{command}` ({wall:.0f} s): `{args.preset}` camera, {args.optics} optics, "
             f"magnification {cell.magnification:g}, spheres of {args.size:g} mm, "
             f"{args.steps} steps of {args.step_um:g} um along {args.axis} (object-space microlens "
             f"pitch {1e3 * pitch_mm:.0f} um) on {args.lines} lines offset across them by "
             f"1/{args.lines} of {1e3 * across_mm:.0f} um, {args.repeats} noise draws per "
             f"step, seed {args.seed}. `fixed sd`: spread over the positions of the error the "
             "draws share (RMS over the lines; `fixed sd lines`: the least and largest "
             "line's); `noise sd`: of the rest; `at lattice`: share of the fixed error's "
             f"variance at the lattice's repeat distance along {args.axis} "
             f"({1e3 * repeat_mm:.0f} um) and its second harmonic.", "",
             *am.markdown_table(table, lambda v, c: f"{v:.3g}" if isinstance(v, float)
                                else str(v)), ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(text))
    print(f"wrote {out} ({wall:.0f} s)")


if __name__ == "__main__":
    main()
