"""Time and memory of locating particles in one full-sensor hall2019 raw image.

    python benchmarks/bench_locate.py                  # hall2019, 100 particles of 1 mm
    python benchmarks/bench_locate.py --preset small --particles 20

The calibration (lenslet grid from a simulated white image, DLFC from seven simulated
dot cards) and the raw image are simulated once and cached in ``--workdir`` (a few
minutes on the full sensor; the raw image is keyed by preset, particle count and seed);
later runs reuse them. The compiled kernels are warmed up on the same image before
timing.

Stages are those :func:`~plenoptrack.locate.perspective.locate_frame` reports in
``LocateResult.stage_seconds`` for the fastest of ``--repeat`` calls on the raw image:
decode (raw to light field); segment (every view, merged regions split into their dark
cores); cluster (every clustering pass); triangulate + addition (solves, duplicate
merging, centroid addition); checks (final consistency checks, last solve, table);
total (the whole call). Peak memory is the process's ``VmHWM``.

The baseline is the same call with the triangulation solved by one
:func:`scipy.optimize.least_squares` call per particle (``solver="scipy"``), run once on
the same image; the ratios are baseline time over plenoptrack time for the
triangulate + addition + checks stages and for the whole call.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def _vm_hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _prepare(preset_name: str, n: int, seed: int, workdir: Path):
    import pandas as pd

    from plenoptrack import preset
    from plenoptrack.calibration import calibrate_from_white, load_calibration, save_calibration
    from plenoptrack.lightfield import decode
    from plenoptrack.locate.dlfc import fit_dlfc
    from plenoptrack.locate.dotcards import dotcard_points
    from plenoptrack.simulate import (default_dotcard, make_optics, make_scene, render_dotcard,
                                      render_frame, render_white)
    from plenoptrack.simulate.scene import volume_depth_mm

    camera = preset(preset_name)
    workdir.mkdir(parents=True, exist_ok=True)
    calib_path = workdir / f"{preset_name}_calibration.json"
    raw_path = workdir / f"{preset_name}_{n}_seed{seed}_raw.npy"
    optics = make_optics(camera, seed=0)
    if not calib_path.exists():
        t0 = time.perf_counter()
        white = render_white(optics, seed=np.random.default_rng([0, 2]))
        calib, _ = calibrate_from_white(white, camera)
        card = default_dotcard(camera)
        half = volume_depth_mm(camera) / 2
        points = []
        for k, z in enumerate(np.linspace(-half, half, 7)):
            image = render_dotcard(optics, float(z), card=card,
                                   seed=np.random.default_rng([0, 4, k]))
            points.append(dotcard_points(decode(image, calib.grid), spacing_mm=card.spacing_mm,
                                         z_mm=float(z), camera=camera))
        dlfc = fit_dlfc(pd.concat(points, ignore_index=True), order=4, group_by="z", reject_k=5)
        save_calibration(calib.with_dlfc(dlfc), calib_path)
        print(f"simulated and calibrated in {time.perf_counter() - t0:.0f} s -> {calib_path}")
    scene = make_scene(camera, n_particles=n, seed=seed)
    if not raw_path.exists():
        np.save(raw_path, render_frame(optics, scene.truth, seed=np.random.default_rng([seed, 3, 0])))
    return load_calibration(calib_path), np.load(raw_path), scene.truth


def _best(fn, repeat: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="hall2019")
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "plenoptrack-bench")
    args = ap.parse_args()

    from plenoptrack.evaluate import evaluate_particles
    from plenoptrack.locate.perspective import PerspectiveLocator, locate_frame

    calib, raw, truth = _prepare(args.preset, args.particles, args.seed, args.workdir)
    base_mb = _vm_hwm_mb()
    locator = PerspectiveLocator()
    locate_frame(raw, calib, locator=locator)  # warm-up (compiled kernels)

    t_total, result = _best(lambda: locate_frame(raw, calib, locator=locator), args.repeat)
    peak_mb = _vm_hwm_mb()
    st = result.stage_seconds
    t_solve = st["triangulate"] + st["checks"]
    t0 = time.perf_counter()
    base = locate_frame(raw, calib, locator=PerspectiveLocator(solver="scipy"))
    t_base = time.perf_counter() - t0
    b_solve = base.stage_seconds["triangulate"] + base.stage_seconds["checks"]

    ev = evaluate_particles(result.particles, truth, tolerance_mm=2.0)
    n_det = len(result.detections)
    print(f"{args.preset}: raw {raw.shape}, {args.particles} particles (seed {args.seed}), "
          f"{n_det} detections, {len(result.particles)} located (recall {ev.recall:.3f}, "
          f"precision {ev.precision:.3f}, z error {ev.mean_error_z:+.4f} +- "
          f"{ev.std_error_z:.4f} mm, lateral RMS {ev.rms_error_lateral:.4f} mm)")
    for name, key in (("decode", "decode"), ("segment", "segment"), ("cluster", "cluster"),
                      ("triangulate + addition", "triangulate"), ("checks", "checks")):
        print(f"  {name:<23}{st[key]:7.3f} s")
    print(f"  {'total':<23}{t_total:7.3f} s")
    print(f"  peak memory (VmHWM)    {peak_mb:7.0f} MB (after loading inputs: {base_mb:.0f} MB)")
    print(f"  baseline (solver='scipy', same image, one run): triangulate + addition + checks "
          f"{b_solve:.3f} s vs {t_solve:.3f} s, ratio {b_solve / t_solve:.1f}x; whole call "
          f"{t_base:.3f} s vs {t_total:.3f} s, ratio {t_base / t_total:.1f}x")


if __name__ == "__main__":
    main()
