"""Time and memory of locating particles in one full-sensor hall2019 raw image.

    python benchmarks/bench_locate.py                  # hall2019, 100 particles of 1 mm
    python benchmarks/bench_locate.py --preset small --particles 20

The calibration (lenslet grid from a simulated white image, DLFC from seven simulated
dot cards) and the raw image are simulated once and cached in ``--workdir`` (a few
minutes on the full sensor); later runs reuse them. The compiled kernels are warmed up
on the same image before timing.

Stages, each timed on its own (best of ``--repeat``): decode (raw to light field);
segment (every view, merged regions split into their dark cores); cluster (the first
k-means pass over all detections); triangulate + addition (the rest of
:func:`~plenoptrack.locate.perspective.locate_frame`: solves, duplicate merging, centroid
addition, final checks; the whole call minus segmentation and first-pass clustering);
total (``locate_frame`` on the raw image). Peak memory is the process's ``VmHWM``.

The baseline is the same pipeline with the triangulation solved by one
:func:`scipy.optimize.least_squares` call per particle (``solver="scipy"``); the ratio
is baseline time over plenoptrack time for the triangulate + addition stage and for the
whole call.
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


def _prepare(preset_name: str, n: int, workdir: Path):
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
    raw_path = workdir / f"{preset_name}_{n}_raw.npy"
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
    scene = make_scene(camera, n_particles=n, seed=0)
    if not raw_path.exists():
        np.save(raw_path, render_frame(optics, scene.truth, seed=np.random.default_rng([0, 3, 0])))
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
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "plenoptrack-bench")
    args = ap.parse_args()

    from plenoptrack.evaluate import evaluate_particles
    from plenoptrack.lightfield import decode
    from plenoptrack.locate.cluster import ProjectionGeometry, cluster_detections, plane_alphas
    from plenoptrack.locate.perspective import PerspectiveLocator, _segment, locate_frame

    calib, raw, truth = _prepare(args.preset, args.particles, args.workdir)
    base_mb = _vm_hwm_mb()
    locator = PerspectiveLocator()
    locate_frame(raw, calib, locator=locator)  # warm-up (compiled kernels)

    t_decode, lf = _best(lambda: decode(raw, calib.grid), args.repeat)
    t_segment, det = _best(lambda: _segment(lf, 0, locator), args.repeat)
    dlfc, camera = calib.dlfc, calib.camera
    alphas = plane_alphas(camera, (dlfc.bounds[0, 2], dlfc.bounds[1, 2]), locator.n_planes)
    geometry = ProjectionGeometry.from_lightfield(lf, camera)
    area = det["area"].to_numpy()
    pool = det[area <= locator.max_area_ratio * np.median(area)]
    t_cluster, _ = _best(lambda: cluster_detections(pool, geometry, alphas,
                                                    min_members=locator.min_views), args.repeat)
    t_from_lf, _ = _best(lambda: locate_frame(lf, calib, locator=locator), args.repeat)
    t_total, result = _best(lambda: locate_frame(raw, calib, locator=locator), args.repeat)
    t_tri = t_from_lf - t_segment - t_cluster
    peak_mb = _vm_hwm_mb()

    scipy_locator = PerspectiveLocator(solver="scipy")
    t_base_lf, _ = _best(lambda: locate_frame(lf, calib, locator=scipy_locator), 1)
    t_base_tri = t_base_lf - t_segment - t_cluster

    ev = evaluate_particles(result.particles, truth, tolerance_mm=2.0)
    print(f"{args.preset}: raw {raw.shape}, {args.particles} particles, {len(det)} detections, "
          f"{len(result.particles)} located (recall {ev.recall:.3f}, precision {ev.precision:.3f})")
    print(f"  decode                 {t_decode:7.3f} s")
    print(f"  segment                {t_segment:7.3f} s")
    print(f"  cluster (first pass)   {t_cluster:7.3f} s")
    print(f"  triangulate + addition {t_tri:7.3f} s")
    print(f"  total                  {t_total:7.3f} s")
    print(f"  peak memory (VmHWM)    {peak_mb:7.0f} MB (after loading inputs: {base_mb:.0f} MB)")
    print(f"  baseline (solver='scipy'): triangulate + addition {t_base_tri:.3f} s, "
          f"ratio {t_base_tri / t_tri:.1f}x; whole call from the light field "
          f"{t_base_lf:.3f} s vs {t_from_lf:.3f} s, ratio {t_base_lf / t_from_lf:.1f}x")


if __name__ == "__main__":
    main()
