"""The calibration's model error against the error of its mapping measured with perfect cards.

    python benchmarks/model_error_truth.py                            # small, M -0.5, seeds 100 101
    python benchmarks/model_error_truth.py --seeds 100 --optics ideal --depths 41

The locator adds the DLFC's model error to every particle's sigma
(:func:`plenoptrack.locate.uncertainty.model_error_mm`, from the calibration report's
``model_error_by_depth_mm``, interpolated in depth). That estimate comes from the
calibration dots' own errors: what the dots' noise does not explain, per card, split into
the part neighbouring dots share and each dot's own
(:func:`plenoptrack.locate.dlfc.model_error_by_depth`). This script checks it against a
direct measurement a real bench cannot make: per seed, a data set without particles is
simulated (``--optics``; the default realistic cards are tilted, misprinted and off their
stated depths) and calibrated with ``calibrate``'s defaults; then ``--depths`` *perfect*
dot cards (no tilt, print or depth error; the same traverse zero and card centre, so the
same frame) are rendered with the same optics at depths spanning the calibrated range,
at and between the calibration's cards, measured with ``dlfc_points`` (flat-fielded with
the white image) and solved through the calibration's DLFC
(:func:`~plenoptrack.locate.dlfc.dot_position_errors`). Their errors are the mapping's own
at that depth, plus each dot's centroid noise, which the solve's least-squares sigma
measures and is subtracted in quadrature. Views whose dot lies far from the mapping's
prediction are left out first, by the calibration fit's own robust rule (median + 5
MAD of the distances).

Printed per seed and depth: the perfect dots' mean error (the part every particle at that
depth shares) and their RMS error beyond their noise, per axis, um, against the model
error the locator adds there; then, pooled over the seeds, the RMS over depths of each
and the ratio measured / estimated, for all depths, the calibration's card depths and the
depths between them. A dot is not a particle: the locator corrects particles' centroids
for pixel locking (``solve.locking_correction``) and adds a sampling term near the focal
plane, neither of which the dots get here, so near focus the measured error includes what
those terms cover.

``--loco`` also refits the DLFC without each calibration card in turn (the calibration's
own points, order and robust rule) and solves that card's dots through it: the error of
the mapping where it has no card, from the calibration data alone, printed per card
beside the perfect dots' error at that depth and at the depths between cards.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pandas as pd


def _perfect_cards(sim, depths, folder: Path, seed: int) -> None:
    """Render perfect cards at ``depths`` with the data set's optics into ``folder``."""
    import tomli_w

    from plenoptrack.io import write_tiff
    from plenoptrack.simulate import CardPlacement, render_dotcard

    doc = json.loads(sim.optics_path.read_text())
    zero = float(doc["target_frame"]["origin_world_mm"][2])
    centre = tuple(doc["dotcards"][0].get("centre_mm", (0.0, 0.0))) if doc["dotcards"] else (0, 0)
    placement = CardPlacement(depth_error_mm=zero, centre_mm=centre)
    folder.mkdir()
    cards = []
    for k, z in enumerate(depths):
        image = render_dotcard(sim.optics, float(z), card=sim.dotcard, placement=placement,
                               seed=np.random.default_rng([seed, 40, k]))
        write_tiff(folder / f"card_{k:02d}.tif", image, compression=None)
        cards.append({"file": f"card_{k:02d}.tif", "z_mm": float(z)})
    (folder / "dotcards.toml").write_text(tomli_w.dumps(
        {"spacing_mm": sim.dotcard.spacing_mm, "dot_diameter_mm": sim.dotcard.dot_diameter_mm,
         "cards": cards}))


def run_seed(preset: str, magnification: float, optics: str, seed: int, n_depths: int,
             workdir: Path, loco: bool = False) -> pd.DataFrame:
    """One row per perfect-card depth: measured and estimated model error, mm (and with
    ``loco`` the leave-one-card-out error at the card depths)."""
    from plenoptrack.calibrate import calibrate, dlfc_points
    from plenoptrack.locate.dlfc import dot_position_errors
    from plenoptrack.locate.uncertainty import model_error_mm
    from plenoptrack.simulate import simulate_dataset

    sim = simulate_dataset(preset, workdir / "calibration", seed=seed, n_particles=0,
                           magnification=magnification, realism=optics, compression=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        calib, _ = calibrate(sim.white_path, sim.out_dir / "dotcards", sim.camera)
    card_z = np.asarray(sim.dotcard_depths_mm)
    depths = np.linspace(card_z.min(), card_z.max(), n_depths)
    _perfect_cards(sim, depths, workdir / "perfect", seed)
    points = dlfc_points(workdir / "perfect", calib.grid, sim.camera, white=sim.white_path)
    pts = points[["x", "y", "z", "u", "v", "s", "t"]].to_numpy(float)
    kept = _robust_views(calib.dlfc, pts)
    errors = dot_position_errors(calib.dlfc, pts[kept])
    print(f"seed {seed}: {np.count_nonzero(~kept)} of {len(kept)} perfect-card points left out "
          f"(the calibration's fit left out {calib.dlfc.report.n_rejected})", flush=True)
    rows = []
    for z, dots in errors.groupby("z"):
        estimate = model_error_mm(calib.dlfc, np.array([z]))[0]
        at_card = bool(np.min(np.abs(card_z - z)) < 1e-6)
        rows.append({"seed": seed, "z": float(z), "at_card": at_card, "n_dots": len(dots),
                     **{f"mean_{a}": float(v)
                        for a, v in zip("xyz", dots[["dx", "dy", "dz"]].mean())},
                     **{f"excess_{a}": float(v) for a, v in zip("xyz", _excess_error(dots))},
                     **{f"estimate_{a}": float(v) for a, v in zip("xyz", estimate)}})
    table = pd.DataFrame(rows)
    if loco:
        cal_points = dlfc_points(sim.out_dir / "dotcards", calib.grid, sim.camera,
                                 white=sim.white_path)
        left_out = _leave_one_card_out(cal_points, calib.dlfc.order)
        table = (table.assign(key=table["z"].round(6))
                 .merge(left_out.assign(key=left_out["z"].round(6)).drop(columns="z"),
                        on="key", how="left").drop(columns="key"))
    return table


def _excess_error(dots: pd.DataFrame) -> np.ndarray:
    """RMS error of solved dots beyond their least-squares noise, per axis (mm): the
    mean square of ``dx, dy, dz`` less that of ``sigma_x, sigma_y, sigma_z``, floored at 0."""
    err = dots[["dx", "dy", "dz"]].to_numpy(float)
    noise = dots[["sigma_x", "sigma_y", "sigma_z"]].to_numpy(float)
    return np.sqrt(np.maximum(np.mean(err ** 2, axis=0) - np.nanmean(noise ** 2, axis=0), 0.0))


def _robust_views(dlfc, pts: np.ndarray) -> np.ndarray:
    """The calibration fit's robust rule on points ``(N, 7)``: views whose dot lies further
    from the mapping's prediction than median + k MAD of those distances are left out."""
    from plenoptrack.calibrate import DEFAULT_REJECT_K
    from plenoptrack.locate.dlfc import _robust_threshold

    s, t = dlfc.predict(*pts[:, :5].T)
    miss = np.hypot(pts[:, 5] - s, pts[:, 6] - t)
    return miss <= _robust_threshold(miss, DEFAULT_REJECT_K)


def _leave_one_card_out(points: pd.DataFrame, order: int) -> pd.DataFrame:
    """Per calibration card: the RMS error beyond noise (mm, per axis, columns
    ``loco_x, loco_y, loco_z``) of its dots solved through the DLFC fitted to the other
    cards."""
    from plenoptrack.calibrate import DEFAULT_REJECT_K
    from plenoptrack.locate.dlfc import dot_position_errors, fit_dlfc

    cols = ["x", "y", "z", "u", "v", "s", "t"]
    rows = []
    for z in np.unique(points["z"]):
        mine = (points["z"] == z).to_numpy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            dlfc = fit_dlfc(points.loc[~mine, cols], order=order, group_by="z",
                            reject_k=DEFAULT_REJECT_K)
        pts = points.loc[mine, cols].to_numpy(float)
        dots = dot_position_errors(dlfc, pts[_robust_views(dlfc, pts)])
        rows.append({"z": float(z),
                     **{f"loco_{a}": float(v) for a, v in zip("xyz", _excess_error(dots))}})
    return pd.DataFrame(rows)


def _rms(values) -> float:
    values = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(values ** 2))) if len(values) else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--magnification", type=float, default=-0.5)
    ap.add_argument("--optics", default="realistic", choices=("realistic", "ideal"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[100, 101])
    ap.add_argument("--depths", type=int, default=21, help="perfect cards over the card range")
    ap.add_argument("--csv", type=Path, help="write the per-depth rows here")
    ap.add_argument("--loco", action="store_true",
                    help="also the error of the DLFC refitted without each card, at that card")
    args = ap.parse_args()

    tables = []
    for seed in args.seeds:
        work = Path(tempfile.mkdtemp(prefix="model_error_truth_"))
        try:
            table = run_seed(args.preset, args.magnification, args.optics, seed, args.depths,
                             work, loco=args.loco)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        tables.append(table)
        print(f"\nseed {seed}: per depth, um (mean error of the perfect dots | their RMS "
              "beyond noise | the model error the locator adds), x / y / z")
        for r in table.itertuples():
            cells = "  ".join(f"{1e3 * getattr(r, 'mean_' + a):+6.1f} | "
                              f"{1e3 * getattr(r, 'excess_' + a):5.1f} | "
                              f"{1e3 * getattr(r, 'estimate_' + a):5.1f}" for a in "xyz")
            loco = ("" if not args.loco or not r.at_card else "   loco " + " ".join(
                f"{1e3 * getattr(r, 'loco_' + a):5.1f}" for a in "xyz"))
            print(f"  z {r.z:+6.2f}{' card' if r.at_card else '     '} n {r.n_dots:3d}  {cells}"
                  f"{loco}", flush=True)
    rows = pd.concat(tables, ignore_index=True)
    if args.csv:
        rows.to_csv(args.csv, index=False)
    print(f"\n{args.preset}, magnification {args.magnification:g}, {args.optics} optics, seeds "
          f"{args.seeds}: RMS over depths, um (measured = the perfect dots' RMS error beyond "
          "their noise; estimate = the model error the locator adds)")
    for label, sel in (("all depths", rows.index == rows.index),
                       ("card depths", rows["at_card"]), ("between cards", ~rows["at_card"])):
        part = rows[sel]
        parts = []
        for a in "xyz":
            measured = _rms(part[f"excess_{a}"])
            estimate = _rms(part[f"estimate_{a}"])
            parts.append(f"{a} {1e3 * measured:5.1f} vs {1e3 * estimate:5.1f} "
                         f"({measured / estimate if estimate else float('nan'):.2f}x)")
        print(f"  {label:13s} ({len(part):3d} depths): " + "   ".join(parts))
    if args.loco:
        cards = rows[rows["at_card"]]
        print("  leave one card out, at the card depths: " + "   ".join(
            f"{a} {1e3 * _rms(cards[f'loco_{a}']):5.1f}" for a in "xyz")
              + "  (compare the perfect dots between cards above)")


if __name__ == "__main__":
    main()
