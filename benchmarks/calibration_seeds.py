"""Calibration success rate, DLFC residual and card-depth check over many simulated seeds.

    python benchmarks/calibration_seeds.py --preset small --seeds 100 --start 7000
    python benchmarks/calibration_seeds.py --preset hall2019 --seeds 3 --csv hall.csv

For every seed ``start, start + 1, ..., start + seeds - 1`` a data set without particles
(white image, default dot cards, nominal ``camera.toml``) is simulated into a temporary
folder with :func:`plenoptrack.simulate.simulate_dataset` and calibrated with
:func:`plenoptrack.calibrate.calibrate` at its defaults, in this one process. One line is
printed per seed (status, DLFC RMS residual, seconds to simulate and to calibrate, the
card-depth check: the scale ``a`` and offset ``b`` of the fit ``z_implied = a * z + b`` and
the largest single-card deviation from it, and how many cards were re-indexed to agree on
dot (0, 0) and how far the worst card's lattice lies from that common dot); the summary
gives the success count, every failure with its reason, every warning, the median and
maximum RMS residual and the spread of ``a``, ``b`` and of the per-card deviations over the
successful seeds. ``--csv`` also writes the per-seed rows, rewritten (atomically) after
every seed, so an interrupted run keeps the seeds it finished. The images are written
without TIFF compression (``--zlib`` compresses them as ``plenoptrack simulate`` does):
the data sets are deleted right after calibrating, and compressing a 29-megapixel image
costs several seconds, more than rendering it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd


def _depth_fit(cards: pd.DataFrame) -> tuple[float, float, float]:
    """``(a, b, max |deviation| mm)`` of ``z_implied_mm = a * z_mm + b``, or NaNs."""
    if "z_implied_mm" not in cards.columns:
        return np.nan, np.nan, np.nan
    z = cards["z_mm"].to_numpy(float)
    zi = cards["z_implied_mm"].to_numpy(float)
    ok = np.isfinite(zi)
    if ok.sum() < 2:
        return np.nan, np.nan, np.nan
    a, b = np.polyfit(z[ok], zi[ok], 1)
    return float(a), float(b), float(np.abs(zi[ok] - (a * z[ok] + b)).max())


def run_seed(preset: str, seed: int, folder: Path, compression: str | None = None) -> dict:
    """Simulate and calibrate one seed; a dict of what was measured."""
    from plenoptrack.calibrate import calibrate
    from plenoptrack.errors import PlenoptrackError
    from plenoptrack.simulate import simulate_dataset

    t0 = time.perf_counter()
    out = simulate_dataset(preset, folder, seed=seed, n_particles=0, realism="ideal",
                           compression=compression)
    t1 = time.perf_counter()
    row = {"seed": seed, "ok": False, "reason": "", "rms_px": np.nan, "sim_s": t1 - t0,
           "cal_s": np.nan, "a": np.nan, "b": np.nan, "max_dev_mm": np.nan,
           "n_reindexed": 0, "origin_miss": np.nan, "warnings": ""}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            _, report = calibrate(out.white_path, out.out_dir / "dotcards", out.camera)
        except PlenoptrackError as exc:
            row["reason"] = f"{type(exc).__name__}: {exc}"
        else:
            row.update(ok=True, rms_px=report.rms_px)
            row["a"], row["b"], row["max_dev_mm"] = _depth_fit(report.cards)
            if "reindexed" in report.cards.columns:
                row["n_reindexed"] = int(report.cards["reindexed"].sum())
                row["origin_miss"] = float(report.cards["origin_miss"].max())
    row["cal_s"] = time.perf_counter() - t1
    row["warnings"] = "; ".join(sorted({f"{w.category.__name__}: {w.message}"
                                        for w in caught}))
    return row


def _summary(table: pd.DataFrame, preset: str) -> str:
    ok = table[table["ok"]]
    lines = [(f"{preset}: {len(ok)}/{len(table)} seeds calibrated "
              f"(seeds {table['seed'].min()}-{table['seed'].max()})")]
    for row in table[~table["ok"]].itertuples():
        lines.append(f"  FAILED seed {row.seed}: {row.reason}")
    warned = table[table["warnings"] != ""]
    for row in warned.itertuples():
        lines.append(f"  warning, seed {row.seed}: {row.warnings}")
    if len(ok):
        lines.append(f"  DLFC RMS residual: median {ok['rms_px'].median():.4f} px, "
                     f"max {ok['rms_px'].max():.4f} px")
    lines.append(f"  time per seed: simulate {table['sim_s'].median():.1f} s, calibrate "
                 f"{table['cal_s'].median():.1f} s (medians; calibrate max "
                 f"{table['cal_s'].max():.1f} s)")
    a = ok["a"].dropna()
    if len(a):
        lines.append(f"  card depths, z_implied = a * z + b: a median {a.median():.4f}, "
                     f"range [{a.min():.4f}, {a.max():.4f}]; b range "
                     f"[{ok['b'].min():.3f}, {ok['b'].max():.3f}] mm; largest single-card "
                     f"deviation from the fit: median {ok['max_dev_mm'].median():.3f} mm, "
                     f"max {ok['max_dev_mm'].max():.3f} mm")
    if len(ok) and ok["origin_miss"].notna().any():
        lines.append(f"  dot (0, 0): cards re-indexed to agree {int(ok['n_reindexed'].sum())} "
                     f"times; largest distance of a card's lattice from the common dot (0, 0) "
                     f"{ok['origin_miss'].max():.4f} dot spacings")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="small", help="camera preset (default small)")
    parser.add_argument("--seeds", type=int, default=20, help="number of seeds (default 20)")
    parser.add_argument("--start", type=int, default=0, help="first seed (default 0)")
    parser.add_argument("--csv", type=Path, help="also write the per-seed rows here")
    parser.add_argument("--zlib", action="store_true",
                        help="write zlib-compressed TIFFs (default: uncompressed)")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error(f"--seeds must be at least 1; got {args.seeds}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="calib_seeds_") as tmp:
        for seed in range(args.start, args.start + args.seeds):
            folder = Path(tmp) / f"seed_{seed}"
            row = run_seed(args.preset, seed, folder, "zlib" if args.zlib else None)
            shutil.rmtree(folder, ignore_errors=True)
            rows.append(row)
            status = "ok  " if row["ok"] else "FAIL"
            print(f"{args.preset} seed {seed:6d} {status} rms {row['rms_px']:.4f} px  "
                  f"sim {row['sim_s']:5.1f} s  cal {row['cal_s']:5.1f} s  a {row['a']:.4f}  "
                  f"b {row['b']:+.3f} mm  max card dev {row['max_dev_mm']:.3f} mm  "
                  f"reindexed {row['n_reindexed']}  origin miss {row['origin_miss']:.4f}"
                  + (f"  {row['reason']}" if not row["ok"] else ""), flush=True)
            if args.csv:
                part = args.csv.with_name(args.csv.name + ".part")
                pd.DataFrame(rows).to_csv(part, index=False)
                os.replace(part, args.csv)
    table = pd.DataFrame(rows)
    print(_summary(table, args.preset))
    return 0 if table["ok"].all() else 1


if __name__ == "__main__":
    sys.exit(main())
