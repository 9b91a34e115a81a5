"""Time and memory of the decode path on a simulated raw image.

    python benchmarks/bench_decode.py                 # full hall2019 sensor (6600 x 4400)
    python benchmarks/bench_decode.py --preset small  # quick check

Steps: grid calibration from the white image, decode (without and with flat field), all
perspective views, and the view mosaic. Each step runs in its own child process that
loads the simulated images from ``.npy`` files and warms the compiled kernels up on a
small image first, so its peak resident memory (``ru_maxrss``) covers that step alone
(plus the interpreter, libraries and the input images, reported as ``base``; measured as
``VmHWM``); the Python-level peak allocation of the step (``tracemalloc``) is printed
beside it. Times: the first run in the process and the best of ``--repeat`` runs (the
first includes faulting in fresh memory, slow on some virtual machines).

The baseline is a straightforward decode: per lens, ``scipy.ndimage.map_coordinates``
(bilinear) at ``centre + (v, u)`` for every view, timed on a subset of lenses and scaled
to the whole lattice (it does not even include the hex-to-rectangular resampling).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

STEPS = ("calibrate_grid", "decode", "decode_white", "views", "mosaic", "baseline")


def _simulate(preset_name: str, folder: Path, seed: int) -> dict:
    import pandas as pd

    from plenoptrack import preset
    from plenoptrack.simulate import make_optics, render_frame, render_white

    cam = preset(preset_name)
    optics = make_optics(cam, seed)
    rng = np.random.default_rng(seed)
    n = 200
    h, w = cam.sensor_size_mm
    particles = pd.DataFrame({
        "x": rng.uniform(-0.4, 0.4, n) * w / abs(cam.magnification),
        "y": rng.uniform(-0.4, 0.4, n) * h / abs(cam.magnification),
        "z": rng.uniform(-25, 25, n),
        "diameter": rng.uniform(0.3, 0.8, n),
    })
    t0 = time.perf_counter()
    white = render_white(optics, seed=seed)
    raw = render_frame(optics, particles, seed=seed + 1)
    elapsed = time.perf_counter() - t0
    np.save(folder / "white.npy", white)
    np.save(folder / "raw.npy", raw)
    (folder / "grid.json").write_text(json.dumps(optics.true_grid.to_dict()))
    return {"simulate_s": elapsed, "shape": list(raw.shape)}


def _warm_up(grid) -> None:
    """Compile (or load from cache) the kernels on a tiny crop of the same lattice."""
    from plenoptrack.lightfield import LensletGrid, decode, view_mosaic

    small = LensletGrid(grid.grid_type, (6, 6), grid.origin_px, grid.col_step_px,
                        grid.row_step_px, grid.odd_row_shift, (100, 100))
    img = np.ones((100, 100), np.uint16)
    view_mosaic(decode(img, small, white=img))


def _hwm_mb() -> float:
    """Peak resident memory of this process image, MB (``VmHWM``; unlike ``ru_maxrss``
    it is not inherited from the parent across ``exec``)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _step(step, raw, white, grid, lf, n_baseline, info):
    from plenoptrack.lightfield import decode, perspective_views, view_mosaic

    if step == "calibrate_grid":
        from scipy.spatial import cKDTree

        from plenoptrack.lightfield.grid import calibrate_grid
        found = calibrate_grid(white)
        true_c = grid.centers().reshape(-1, 2)
        rows, cols = grid.sensor_shape_px
        inside = ((true_c >= 20) & (true_c <= np.array([rows, cols]) - 21)).all(axis=1)
        dist, _ = cKDTree(found.centers().reshape(-1, 2)).query(true_c[inside])
        info["centre_rms_px"] = round(float(np.sqrt(np.mean(dist ** 2))), 4)
    elif step == "decode":
        out = decode(raw, grid)
        info["lf_shape"] = list(out.data.shape)
        info["lf_mb"] = round(out.data.nbytes / 2**20, 1)
    elif step == "decode_white":
        info["valid_views"] = int(decode(raw, grid, white=white).view_mask.sum())
    elif step == "views":
        views = perspective_views(lf)
        info["n_views"] = int(views.shape[0] * views.shape[1])
    elif step == "mosaic":
        info["mosaic_shape"] = list(view_mosaic(lf).shape)
    elif step == "baseline":
        from scipy import ndimage
        rad = int(grid.pitch_px // 2)
        vv, uu = np.mgrid[-rad:rad + 1, -rad:rad + 1]
        centres = grid.centers().reshape(-1, 2)
        rng = np.random.default_rng(0)
        subset = centres[rng.choice(len(centres), size=min(n_baseline, len(centres)), replace=False)]
        rawf = raw.astype(np.float32)
        out = np.empty((len(subset), 2 * rad + 1, 2 * rad + 1), np.float32)
        t0 = time.perf_counter()
        for k, (r, c) in enumerate(subset):
            out[k] = ndimage.map_coordinates(rawf, [r + vv, c + uu], order=1, mode="nearest")
        info["lenses_timed"] = len(subset)
        return (time.perf_counter() - t0) * len(centres) / len(subset)
    return None


def _child(step: str, folder: Path, n_baseline: int, repeat: int) -> dict:
    from plenoptrack.lightfield import LensletGrid, decode

    raw = np.load(folder / "raw.npy")
    white = np.load(folder / "white.npy")
    grid = LensletGrid.from_dict(json.loads((folder / "grid.json").read_text()))
    _warm_up(grid)
    if step == "calibrate_grid":
        from plenoptrack.lightfield.grid import calibrate_grid
        calibrate_grid(white[:600, :900])  # warm up its kernels too
    lf = decode(raw, grid) if step in ("views", "mosaic") else None
    base = _hwm_mb()
    info: dict = {}
    times = []
    n = 1 if step in ("calibrate_grid", "baseline") else repeat
    for k in range(n):
        if k == 0:
            tracemalloc.start()
        t0 = time.perf_counter()
        scaled = _step(step, raw, white, grid, lf, n_baseline, info)
        times.append(scaled if scaled is not None else time.perf_counter() - t0)
        if k == 0:
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            hwm = _hwm_mb()
    return {"step": step, "first_s": times[0], "best_s": min(times), "traced_peak_mb": peak / 2**20,
            "base_mb": base, "peak_mb": hwm, **info}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="hall2019")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--baseline-lenses", type=int, default=3000)
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per step (best is shown)")
    ap.add_argument("--keep", type=Path, default=None, help="folder for the simulated images")
    ap.add_argument("--child", nargs=2, metavar=("STEP", "FOLDER"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:
        print(json.dumps(_child(args.child[0], Path(args.child[1]), args.baseline_lenses,
                                args.repeat)))
        return 0

    import numba

    tmp = tempfile.TemporaryDirectory(prefix="bench_decode_")
    folder = args.keep or Path(tmp.name)
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "raw.npy").exists():
        sim = _simulate(args.preset, folder, args.seed)
        print(f"simulated {args.preset} {sim['shape'][1]} x {sim['shape'][0]} white + raw "
              f"in {sim['simulate_s']:.1f} s (not part of the timings below)")
    print(f"cores: {os.cpu_count()}, numba threads: {numba.config.NUMBA_NUM_THREADS}")
    have_grid = True
    try:
        import plenoptrack.lightfield.grid  # noqa: F401
    except ImportError:
        have_grid = False
    results = {}
    print(f"{'step':<15}{'first s':>8}{'best s':>8}{'peak MB':>9}{'base MB':>9}{'traced MB':>10}  notes")
    for step in STEPS:
        if step == "calibrate_grid" and not have_grid:
            print(f"{step:<15}  (plenoptrack.lightfield.grid not available; skipped)")
            continue
        proc = subprocess.run([sys.executable, __file__, "--baseline-lenses",
                               str(args.baseline_lenses), "--repeat", str(args.repeat),
                               "--child", step, str(folder)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"{step:<15}  failed: {proc.stderr.strip().splitlines()[-1:]}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        results[step] = r
        notes = {k: v for k, v in r.items() if k not in
                 ("step", "first_s", "best_s", "traced_peak_mb", "base_mb", "peak_mb")}
        print(f"{step:<15}{r['first_s']:8.3f}{r['best_s']:8.3f}{r['peak_mb']:9.0f}{r['base_mb']:9.0f}"
              f"{r['traced_peak_mb']:10.0f}  {notes}")
    if "decode" in results and "views" in results:
        d, v = results["decode"], results["views"]
        print(f"decode + all views: first {d['first_s'] + v['first_s']:.3f} s, best "
              f"{d['best_s'] + v['best_s']:.3f} s; peak memory {max(d['peak_mb'], v['peak_mb']):.0f} MB "
              f"({max(d['peak_mb'], v['peak_mb']) - d['base_mb']:.0f} MB above the loaded inputs)")
    if "decode" in results and "baseline" in results:
        ratio = results["baseline"]["best_s"] / results["decode"]["best_s"]
        print(f"speed-up over a per-lens map_coordinates decode (scaled from "
              f"{results['baseline']['lenses_timed']} lenses, no hex resampling): {ratio:.0f}x")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
