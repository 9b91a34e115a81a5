"""Time and memory of the decode path on a simulated raw image.

    python benchmarks/bench_decode.py                 # full hall2019 sensor (6600 x 4400)
    python benchmarks/bench_decode.py --preset small  # quick check

Steps: grid calibration from the white image, decode (without and with flat field), all
perspective views, and the view mosaic. Each step runs in its own child process that
loads the simulated images from ``.npy`` files and warms the compiled kernels up on a
small image first, so its peak resident memory (``ru_maxrss``) covers that step alone
(plus the interpreter, libraries and the input images, reported as ``base``); the
Python-level peak allocation of the step (``tracemalloc``) is printed beside it.

The baseline is a straightforward decode: per lens, ``scipy.ndimage.map_coordinates``
(bilinear) at ``centre + (v, u)`` for every view, timed on a subset of lenses and scaled
to the whole lattice (it does not even include the hex-to-rectangular resampling).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

STEPS = ("calibrate_grid", "decode", "decode_white", "views", "mosaic", "baseline")


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _current_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


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


def _child(step: str, folder: Path, n_baseline: int) -> dict:
    from plenoptrack.lightfield import LensletGrid, decode, perspective_views, view_mosaic

    raw = np.load(folder / "raw.npy")
    white = np.load(folder / "white.npy")
    grid = LensletGrid.from_dict(json.loads((folder / "grid.json").read_text()))
    _warm_up(grid)
    if step == "calibrate_grid":
        from plenoptrack.lightfield.grid import calibrate_grid
        calibrate_grid(white[:600, :900])  # warm up its kernels too
    lf = decode(raw, grid) if step in ("views", "mosaic") else None
    base = _current_rss_mb()
    info: dict = {}
    tracemalloc.start()
    t0 = time.perf_counter()
    if step == "calibrate_grid":
        from plenoptrack.lightfield.grid import calibrate_grid
        found = calibrate_grid(white)
        from scipy.spatial import cKDTree
        true_c = grid.centers().reshape(-1, 2)
        rows, cols = grid.sensor_shape_px
        inside = ((true_c >= 20) & (true_c <= np.array([rows, cols]) - 21)).all(axis=1)
        dist, _ = cKDTree(found.centers().reshape(-1, 2)).query(true_c[inside])
        info["centre_rms_px"] = round(float(np.sqrt(np.mean(dist ** 2))), 4)
    elif step == "decode":
        lf = decode(raw, grid)
        info["lf_shape"] = list(lf.data.shape)
        info["lf_mb"] = lf.data.nbytes / 2**20
    elif step == "decode_white":
        lf = decode(raw, grid, white=white)
        info["valid_views"] = int(lf.view_mask.sum())
    elif step == "views":
        views = perspective_views(lf)
        info["n_views"] = int(views.shape[0] * views.shape[1])
        info["checksum"] = float(views[7, 7].mean())
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
        t0 = time.perf_counter()  # the float conversion is not charged to the baseline
        for k, (r, c) in enumerate(subset):
            out[k] = ndimage.map_coordinates(rawf, [r + vv, c + uu], order=1, mode="nearest")
        info["lenses_timed"] = len(subset)
        info["scale"] = len(centres) / len(subset)
    elapsed = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    if step == "baseline":
        elapsed *= info["scale"]
    return {"step": step, "seconds": elapsed, "traced_peak_mb": peak / 2**20,
            "base_rss_mb": base, "peak_rss_mb": _rss_mb(), **info}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="hall2019")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--baseline-lenses", type=int, default=3000)
    ap.add_argument("--keep", type=Path, default=None, help="folder for the simulated images")
    ap.add_argument("--child", nargs=2, metavar=("STEP", "FOLDER"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.child:
        print(json.dumps(_child(args.child[0], Path(args.child[1]), args.baseline_lenses)))
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
    print(f"{'step':<16}{'seconds':>9}{'peak RSS MB':>13}{'base MB':>9}{'traced MB':>11}  notes")
    for step in STEPS:
        if step == "calibrate_grid" and not have_grid:
            print(f"{step:<16}  (plenoptrack.lightfield.grid not available; skipped)")
            continue
        proc = subprocess.run([sys.executable, __file__, "--baseline-lenses",
                               str(args.baseline_lenses), "--child", step, str(folder)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"{step:<16}  failed: {proc.stderr.strip().splitlines()[-1:]}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        results[step] = r
        notes = {k: v for k, v in r.items() if k not in
                 ("step", "seconds", "traced_peak_mb", "base_rss_mb", "peak_rss_mb")}
        print(f"{step:<16}{r['seconds']:9.3f}{r['peak_rss_mb']:13.0f}{r['base_rss_mb']:9.0f}"
              f"{r['traced_peak_mb']:11.0f}  {notes}")
    if "decode" in results and "views" in results:
        total = results["decode"]["seconds"] + results["views"]["seconds"]
        print(f"decode + all views: {total:.3f} s, peak RSS "
              f"{max(results['decode']['peak_rss_mb'], results['views']['peak_rss_mb']):.0f} MB")
    if "decode" in results and "baseline" in results:
        ratio = results["baseline"]["seconds"] / results["decode"]["seconds"]
        print(f"speed-up over per-lens map_coordinates decode (scaled from "
              f"{results['baseline']['lenses_timed']} lenses): {ratio:.0f}x")
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
