"""Does the locator's sigma cover its error? Coverage of sigma_x/y/z on simulated data.

    python benchmarks/uncertainty_coverage.py --seeds dev          # tuning seeds 100-102
    python benchmarks/uncertainty_coverage.py --seeds validation   # held-back 900-902
    python benchmarks/uncertainty_coverage.py --from-parquet FILE  # summarise saved pairs

Cells (camera ``small``, the cells of ``benchmarks/accuracy_matrix.py`` that the locator is
expected to handle): the base cell (M -0.5, 0.01 particles per microlens, 0.4 mm spheres),
density 0.03, 1 mm spheres, mixed sizes 0.2-1 mm, M -0.75, ellipsoids; both optics modes;
at least 60 particles per cell and seed. Every located particle is matched to the truth
(:func:`accuracy_matrix.match`); for each axis the script prints the fraction of matched
particles within 1 and 2 sigma and beyond 3 sigma (a calibrated Gaussian sigma gives 0.68,
0.95 and 0.003), the robust (1.4826 MAD) and plain standard deviation of the error, and
``k68``: the factor sigma would need for 68 % coverage (1.0 is right). With ``--seeds dev``
it also prints, per optics mode, the least-squares scale ``error_scale`` that gives 68 %
coverage with the DLFC model error in place; claims are made on the validation seeds.
On development seeds 100-102 it was 2.21 for ideal optics before the shared sampling term
(``SolveSettings.sampling_error``). The pairs record the model error the locator used
for each particle (the DLFC's at the particle's measured depth; before 2026-12-02 they
recorded the RMS over all calibration dots, with ideal optics about three times larger
laterally, and the fit wrongly reported that the model error alone covered 68 %). On
2026-12-02 the fit gave 0.58 for ideal optics (0.31-0.33 once ``solve.unexplained_error``
widened the unexplained particles' sigma, the same day), and for realistic optics the model error
alone covers more than 68 % laterally (the floor): the realistic dot cards' print error
(5 um per dot) is in the dots' lateral error and so in the model error. The scale would
trade the core for the tails (3 % to 5 % of errors beyond 3 sigma), so the default 2.3 of
:class:`~plenoptrack.locate.settings.SolveSettings` stays.

The per-particle pairs are written to ``benchmarks/results/uncertainty/pairs_<seeds>.parquet``
and the summary to ``summary_<seeds>.md`` beside them.

    python benchmarks/uncertainty_coverage.py --ablate --seeds dev --optics realistic

``--ablate`` asks what each term of the uncertainty buys: on the acceptance cells of the
accuracy matrix (:func:`accuracy_matrix.acceptance_cells`, 3 frames and 80 particles per
cell and seed at least) every frame is located with the default settings and again with
one term of :class:`~plenoptrack.locate.settings.SolveSettings` changed at a time
(:data:`ABLATIONS`), and the coverage is printed per density band and over all. The terms
change sigma only, so every variant must give the same positions; the script checks that.
Written to ``ablation_<seeds>.md`` (and the pairs to ``ablation_<seeds>.parquet``).
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
import tempfile
import time
import warnings
import zlib
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

SEED_SETS = {"dev": am.DEV_SEEDS, "validation": am.VALIDATION_SEEDS}
MIN_PARTICLES = 60
OUT = Path(__file__).resolve().parent / "results" / "uncertainty"


def cells() -> list:
    return [am._cell("base"), am._cell("density", density=0.03), am._cell("size", size=1.0),
            am._cell("size", size=am.MIXED_SIZE), am._cell("magnification", magnification=-0.75),
            am._cell("shape", shape="ellipsoid")]


def _simulated_cells(runner, cell_list, seeds, optics_modes, tmp: Path, frames_of):
    """Per optics mode, seed and cell (calibrated once per magnification; cells whose
    calibration failed skipped): ``(optics, seed, cell, calib, white, sim)`` with
    ``frames_of(cell)`` frames simulated into ``tmp``, removed once the caller moves on."""
    from plenoptrack.simulate import simulate_dataset

    for optics in optics_modes:
        for seed in seeds:
            calibrations = {}
            for cell in cell_list:
                if cell.magnification not in calibrations:
                    calibrations[cell.magnification] = runner.calibrate(
                        cell.preset, cell.magnification, optics, seed)
                calib, white, _ = calibrations[cell.magnification]
                if calib is None:
                    continue
                scene = am.make_cell_scene(cell, seed, frames_of(cell))
                folder = tmp / f"f_{zlib.crc32(cell.name.encode())}_{optics}_{seed}"
                sim = simulate_dataset(cell.preset, folder, seed=seed, scene=scene,
                                       magnification=cell.magnification,
                                       realism=am.realism_of(optics), dotcard_depths=[])
                try:
                    yield optics, seed, cell, calib, white, sim
                finally:
                    shutil.rmtree(folder, ignore_errors=True)


def gather(seeds, optics_modes, tmp: Path) -> pd.DataFrame:
    """Matched (measured, true) pairs with sigma, for every cell, optics mode and seed."""
    from plenoptrack.io import read_raw
    from plenoptrack.locate import locate_frame
    from plenoptrack.locate.uncertainty import model_error_mm

    runner = am.Runner(tmp, MIN_PARTICLES, time.perf_counter())
    rows = []
    for optics, seed, cell, calib, white, sim in _simulated_cells(
            runner, cells(), seeds, optics_modes, tmp,
            lambda cell: max(1, math.ceil(MIN_PARTICLES / am.n_particles(cell)))):
        for f, path in enumerate(sim.frame_paths):
            truth = sim.truth[sim.truth["frame"] == f]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                found = locate_frame(read_raw(path), calib, frame=f, white=white).particles
            pairs = am.match(found, truth, cell.magnification)
            # the model error total_sigma used: the DLFC's at the measured depth
            model = model_error_mm(calib.dlfc, pairs["z_true"] + pairs["dz"])
            rows.append(pairs.assign(cell=cell.name, optics=optics, seed=seed,
                                     density=cell.density, model_x=model[:, 0],
                                     model_y=model[:, 1], model_z=model[:, 2]))
        print(f"{optics} seed {seed} {cell.name}: {sum(len(r) for r in rows)} pairs",
              flush=True)
    return pd.concat(rows, ignore_index=True)


ABLATIONS = {
    "defaults": {},
    "model_error off": {"model_error": False},
    "sampling_error off": {"sampling_error": False},
    "excess_scatter off": {"excess_scatter": False},
    "unexplained_error off": {"unexplained_error": False},
    "companion_error off": {"companion_error": False},
    "refit_error off": {"refit_error": False},
    "error_scale 1.6": {"error_scale": 1.6},
}
"""``--ablate`` variants: changes to ``SolveSettings`` (the defaults first)."""


def gather_ablation(seeds, optics_modes, tmp: Path) -> pd.DataFrame:
    """Matched pairs of every acceptance cell's frames located with each of
    :data:`ABLATIONS`, with ``variant`` and ``band`` columns.

    Raises
    ------
    RuntimeError
        If a variant moves any particle: the terms are meant to change sigma only.
    """
    from plenoptrack.io import read_raw
    from plenoptrack.locate import locate_frame

    runner = am.Runner(tmp, 80, time.perf_counter(), 3)
    rows = []
    for optics, seed, cell, calib, white, sim in _simulated_cells(
            runner, am.acceptance_cells(), seeds, optics_modes, tmp,
            lambda cell: am.frames_per_seed(cell, 80, 3)):
        base = am.cell_locator(cell)
        band = am.band_of(cell.axis, cell.density)
        for f, path in enumerate(sim.frame_paths):
            raw = read_raw(path)
            truth = sim.truth[sim.truth["frame"] == f]
            positions = None
            for variant, change in ABLATIONS.items():
                locator = base.updated({"solve": change}, source="ablation")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    found = locate_frame(raw, calib, frame=f, white=white,
                                         locator=locator).particles
                xyz = found[["x", "y", "z"]].to_numpy(float)
                if positions is None:
                    positions = xyz
                elif xyz.shape != positions.shape or not np.array_equal(
                        xyz, positions, equal_nan=True):
                    raise RuntimeError(f"{variant} moved particles in {cell.name}, "
                                       f"seed {seed}, frame {f}")
                pairs = am.match(found, truth, cell.magnification)
                rows.append(pairs.assign(variant=variant, cell=cell.name, band=band,
                                         optics=optics, seed=seed, frame=f))
        print(f"{optics} seed {seed} {cell.name}: done", flush=True)
    return pd.concat(rows, ignore_index=True)


def ablation_summary(pairs: pd.DataFrame) -> pd.DataFrame:
    """Coverage per optics mode, variant and band (and ``all``), variants in the order of
    :data:`ABLATIONS`."""
    rows = []
    order = {v: i for i, v in enumerate(ABLATIONS)}
    for (optics, variant), g in pairs.groupby(["optics", "variant"]):
        for band, h in list(g.groupby("band")) + [("all", g)]:
            rows.append({"optics": optics, "variant": variant, "band": band} | coverage(h))
    table = pd.DataFrame(rows)
    return table.sort_values(["optics", "band", "variant"], key=lambda c: c.map(order)
                             if c.name == "variant" else c, kind="stable")


def _robust_std(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else math.nan


def coverage(pairs: pd.DataFrame) -> dict:
    """Coverage and error spread per axis of a set of pairs."""
    out = {"n": len(pairs)}
    for ax in "xyz":
        e = pairs[f"d{ax}"].to_numpy(float)
        s = pairs[f"sigma_{ax}"].to_numpy(float)
        ok = np.isfinite(e) & np.isfinite(s)
        r = np.abs(e[ok]) / s[ok]
        out[f"{ax} 1s"] = float(np.mean(r <= 1)) if len(r) else math.nan
        out[f"{ax} 2s"] = float(np.mean(r <= 2)) if len(r) else math.nan
        out[f"{ax} >3s"] = float(np.mean(r > 3)) if len(r) else math.nan
        out[f"{ax} k68"] = float(np.quantile(r, 0.6827)) if len(r) else math.nan
        out[f"{ax} rstd"] = _robust_std(e[ok])
        out[f"{ax} std"] = float(np.std(e[ok], ddof=1)) if ok.sum() > 1 else math.nan
    return out


def summary(pairs: pd.DataFrame) -> pd.DataFrame:
    """One row per optics mode and cell, and a pooled row per optics mode."""
    rows = []
    for optics, g in pairs.groupby("optics"):
        for cell, h in g.groupby("cell"):
            rows.append({"optics": optics, "cell": cell} | coverage(h))
        for density, h in g.groupby("density"):
            rows.append({"optics": optics, "cell": f"pooled, density {density:g}"} | coverage(h))
        rows.append({"optics": optics, "cell": "pooled"} | coverage(g))
    return pd.DataFrame(rows)


def _variance_factor(pairs: pd.DataFrame, k: float) -> np.ndarray:
    """``(sigma^2 - model^2) / sigma_stat^2`` of each pair for error scale ``k``, as
    :func:`~plenoptrack.locate.uncertainty.total_sigma` forms it (with the excess scatter
    when the settings count it and the pairs record ``chi2``; refined particles' sigma is
    their image fit's). The pairs do not record the typical-scatter size of a refined
    particle's shared sampling error, so for those the factor is the one sized by their
    fit's sigma: an approximation of the refit, not of the reported sigma."""
    from plenoptrack.locate.settings import SolveSettings
    from plenoptrack.locate.triangulate import TriangulationFlag
    from plenoptrack.locate.uncertainty import total_sigma

    settings = SolveSettings()
    chi2 = travel = None
    n_views = pairs["n_views"].to_numpy(float) if "n_views" in pairs else None
    refined = (pairs["flags"].to_numpy(np.int64) & int(TriangulationFlag.REFINED)) > 0
    if settings.excess_scatter and "chi2" in pairs:
        chi2 = pairs["chi2"].to_numpy(float)
    if settings.sampling_error and "travel_px" in pairs:
        travel = pairs["travel_px"].to_numpy(float)
    unit = total_sigma(np.ones((len(pairs), 3)), None, error_scale=k, include_model_error=False,
                       chi2=chi2, n_views=n_views, travel_px=travel, from_centroids=~refined)
    return unit[:, 0] ** 2


def fitted_error_scale(pairs: pd.DataFrame) -> tuple[float, bool]:
    """The error scale ``k`` that gives 68 % coverage, pooled over axes.

    Each pair's ``sigma`` is taken apart into its statistical part and the model error
    ``m`` recorded in the pairs, with the current scale (read from the settings), and
    re-formed for a trial ``k``. Returns ``(k, floor)``: ``floor`` is True when the model
    error alone already covers 68 % on some axis (that axis then counts as
    ``k = 0.1``, the bottom of the search).
    """
    from scipy.optimize import brentq

    from plenoptrack.locate.settings import SolveSettings

    base = _variance_factor(pairs, SolveSettings().error_scale)
    ratios, floor = [], False
    for ax in "xyz":
        sigma = pairs[f"sigma_{ax}"].to_numpy(float)
        model = pairs[f"model_{ax}"].to_numpy(float) if f"model_{ax}" in pairs else np.zeros(len(pairs))
        stat2 = np.maximum(sigma ** 2 - model ** 2, 0.0) / base
        e = np.abs(pairs[f"d{ax}"].to_numpy(float))
        ok = np.isfinite(e) & (stat2 > 0)

        def covered(k, e=e[ok], stat2=stat2[ok], model=model[ok], ok=ok):
            sig = np.sqrt(stat2 * _variance_factor(pairs[ok], k) + model ** 2)
            return np.mean(e <= sig) - 0.6827

        if covered(0.1) >= 0:
            ratios.append(0.1)
            floor = True
        else:
            ratios.append(brentq(covered, 0.1, 100.0))
    return float(np.mean(ratios)), floor


def by_flag(pairs: pd.DataFrame) -> pd.DataFrame:
    """Coverage of the particles that carry each quality flag, and of those that do not,
    per optics mode over all cells; ``share of x >3s`` is the part of all the x errors
    beyond 3 sigma that the flagged particles make up (where the tails come from)."""
    from plenoptrack.locate.triangulate import TriangulationFlag

    rows = []
    for optics, g in pairs.groupby("optics"):
        flags = g["flags"].to_numpy(np.int64)
        tail_x = np.abs(g["dx"].to_numpy(float)) > 3 * g["sigma_x"].to_numpy(float)
        for flag in TriangulationFlag:
            # CONVERGED is the normal case: the row is for the particles without it
            converged = flag is TriangulationFlag.CONVERGED
            sel = ((flags & int(flag)) > 0) != converged
            if sel.any():
                rows.append({"optics": optics,
                             "particles": f"not {flag.name}" if converged else flag.name}
                            | coverage(g[sel])
                            | {"share of x >3s": float(tail_x[sel].sum() / max(tail_x.sum(), 1))})
        clean = (flags & int(TriangulationFlag.CONVERGED)) > 0
        for flag in (TriangulationFlag.SPLIT, TriangulationFlag.UNEXPLAINED):
            clean &= (flags & int(flag)) == 0
        rows.append({"optics": optics, "particles": "converged, neither SPLIT nor UNEXPLAINED"}
                    | coverage(g[clean])
                    | {"share of x >3s": float(tail_x[clean].sum() / max(tail_x.sum(), 1))})
    return pd.DataFrame(rows)


def _markdown(df: pd.DataFrame) -> str:
    return "\n".join(am.markdown_table(df))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", choices=list(SEED_SETS), default="validation")
    parser.add_argument("--optics", nargs="+", choices=am.OPTICS, default=list(am.OPTICS))
    parser.add_argument("--from-parquet", type=Path, nargs="+", default=None,
                        help="summarise saved pairs (several files are pooled)")
    parser.add_argument("--seed-numbers", type=int, nargs="+", default=None,
                        help="run these seeds of the chosen set only (for example one seed per "
                             "process; pool the pairs with --from-parquet)")
    parser.add_argument("--ablate", action="store_true",
                        help="coverage with each uncertainty term turned off in turn, on the "
                             "acceptance cells (module docstring)")
    parser.add_argument("--out", type=Path, default=OUT,
                        help=f"folder of the pairs and summary (default {OUT})")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    if args.ablate:
        return _ablate(args, t0)
    pairs = _pairs(args, gather, "pairs")
    table = summary(pairs)
    pd.set_option("display.width", 250)
    cols = ["optics", "cell", "n"] + [f"{ax} {m}" for ax in "xyz"
                                      for m in ("1s", "2s", ">3s", "k68", "rstd", "std")]
    text = _markdown(table[cols])
    print(text)
    lines = [f"# Uncertainty coverage, {args.seeds} seeds {SEED_SETS[args.seeds]}", "",
             "`python benchmarks/uncertainty_coverage.py --seeds " + args.seeds + "`"
             + (f" (from {', '.join(p.name for p in args.from_parquet)})"
                if args.from_parquet else f", {time.perf_counter() - t0:.0f} s") + ".", "",
             "Columns per axis: fraction within 1 and 2 sigma and beyond 3 sigma (0.68, 0.95 "
             "and 0.003 for a calibrated Gaussian sigma), k68 (the factor sigma would need "
             "for 68 % coverage), robust (1.4826 MAD) and plain standard deviation of the "
             "error, mm.", "", text, ""]
    flagged = by_flag(pairs)
    flag_cols = ["optics", "particles", "n"] + [f"{ax} {m}" for ax in "xyz"
                                                for m in ("1s", ">3s", "k68")] + ["share of x >3s"]
    flag_text = _markdown(flagged[flag_cols])
    print(flag_text)
    lines += ["By quality flag (all cells pooled per optics mode): where the core and the "
              "tails come from.", "", flag_text, ""]
    if args.seeds == "dev":
        for optics in sorted(set(pairs["optics"])):
            k, floor = fitted_error_scale(pairs[pairs["optics"] == optics])
            lines.append(f"- error_scale for 68 % coverage, {optics} optics, pooled cells and "
                         f"axes: {k:.2f}" + (" (an axis's model error alone covers 68 %: it "
                                             "counts as 0.1)" if floor else ""))
            print(lines[-1])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"summary_{_label(args)}.md").write_text("\n".join(lines) + "\n")
    return 0


def _seeds(args) -> tuple[int, ...]:
    """The seeds to run: the chosen set, or the ``--seed-numbers`` of it."""
    chosen = SEED_SETS[args.seeds]
    if args.seed_numbers is None:
        return chosen
    unknown = sorted(set(args.seed_numbers) - set(chosen))
    if unknown:
        raise SystemExit(f"--seed-numbers {unknown} are not {args.seeds} seeds {chosen}")
    return tuple(args.seed_numbers)


def _label(args) -> str:
    """File-name label of a run: the seed set, with the seeds when only some ran."""
    if args.seed_numbers is None:
        return args.seeds
    return args.seeds + "_" + "_".join(str(s) for s in args.seed_numbers)


def _read_pairs(paths: list[Path]) -> pd.DataFrame:
    return pd.concat([pd.read_parquet(p) for p in paths], ignore_index=True)


def _pairs(args, gather_pairs, stem: str) -> pd.DataFrame:
    """The pairs of ``--from-parquet``, or gathered by ``gather_pairs(seeds, optics, tmp)``
    in a temporary folder and saved as ``<stem>_<label>.parquet`` in ``--out``."""
    if args.from_parquet is not None:
        return _read_pairs(args.from_parquet)
    tmp = Path(tempfile.mkdtemp(prefix=f"plenoptrack-{stem}-"))
    try:
        pairs = gather_pairs(_seeds(args), args.optics, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)
    pairs.to_parquet(args.out / f"{stem}_{_label(args)}.parquet")
    return pairs


def _ablate(args, t0: float) -> int:
    """``--ablate``: gather (or read) the variants' pairs, print and write the summary."""
    pairs = _pairs(args, gather_ablation, "ablation")
    cols = ["optics", "band", "variant", "n"] + [f"{ax} {m}" for ax in "xyz"
                                                 for m in ("1s", "2s", ">3s", "k68")]
    text = _markdown(ablation_summary(pairs)[cols])
    print(text)
    lines = [f"# Uncertainty terms, one at a time: {args.seeds} seeds "
             f"{sorted(set(pairs['seed']))}", "",
             f"`python benchmarks/uncertainty_coverage.py --ablate --seeds {args.seeds}"
             f" --optics {' '.join(sorted(set(pairs['optics'])))}`"
             + (f" (from {', '.join(p.name for p in args.from_parquet)})"
                if args.from_parquet else f", {time.perf_counter() - t0:.0f} s") + ".", "",
             "The acceptance cells' frames, each located with the defaults and with one "
             "`solve` setting changed (`variant`); the positions are the same in every "
             "variant. Columns per axis: fraction within 1 and 2 sigma, beyond 3 sigma, and "
             "k68 (the factor sigma would need for 68 % coverage).", "", text, ""]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"ablation_{_label(args)}.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
