"""Per-image time and peak memory of the perspective-shift and refocusing locators.

Both locators (and the hybrid) are timed in one run, on the same images, one after the
other: every image of the study's pin-head field is rendered once, then located by each
method with the process's peak resident memory (``VmHWM``) reset before the call. Each
method is run once first to compile its kernels; the figures are the median seconds
and the largest peak over the timed images. Printed: seconds and peak MB per image and
the ratios refocus / perspective (the paper, MATLAB on 12 cores: about an hour against
about 10 s, 360 times; 2 GB against 0.2 GB, 10 times). The baseline of the ratios is the
perspective method measured in the same run.

Usage::

    python benchmarks/bench_study.py --study-dir STUDY/hall2019_M0.5_F105 --images 3
    python benchmarks/bench_study.py --preset small --images 3      # calibrates first
    python benchmarks/bench_study.py --raw sim/raw/frame_0000.tif --calib calib.json \
        --white sim/white.tif --images 2                             # any calibrated frame

``--raw`` times the locators on one existing frame (``--images`` timed runs after the
warm-up run) with its calibration and white image. ``--study-dir`` reuses the calibration and field of a ``plenoptrack study`` configuration
folder (``config.json``, ``calibration.json``, ``data/white.tif``); without it a
configuration is calibrated in a temporary folder (slow on hall2019). ``--threads``
sets the numba threads (default 1, as in a study worker). Timings on a shared machine are
noisy; compare ratios measured in the same run.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _vm_hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _vm_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _reset_hwm() -> None:
    import ctypes
    import gc

    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def study_configuration(stack: contextlib.ExitStack, study_dir: Path | None,
                        preset_name: str):
    """The study configuration folder and its :class:`~plenoptrack.study.StudyConfig`:
    ``study_dir`` as it is, or (None) the ``preset_name`` camera's 10 mm study calibrated
    in a temporary folder that ``stack`` removes."""
    from plenoptrack import preset
    from plenoptrack.study import StudyConfig, _prepare

    if study_dir is not None:
        config = json.loads((study_dir / "config.json").read_text())
        return study_dir, StudyConfig.from_dict(config)
    cdir = Path(stack.enter_context(tempfile.TemporaryDirectory()))
    cfg = StudyConfig(preset(preset_name), travel_mm=10, step_mm=1, repeats=1)
    print(f"calibrating {cfg.label} in {cdir} ...", flush=True)
    _prepare(cdir, cfg, None)
    return cdir, cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study-dir", type=Path, help="a study configuration folder to reuse")
    ap.add_argument("--preset", default="small", help="camera preset when no --study-dir")
    ap.add_argument("--images", type=int, default=3, help="timed images (traverse positions)")
    ap.add_argument("--threads", type=int, default=1, help="numba threads")
    ap.add_argument("--methods", default="perspective,refocus,hybrid")
    ap.add_argument("--raw", type=Path, help="an existing raw frame to time on")
    ap.add_argument("--calib", type=Path, help="its calibration file (with --raw)")
    ap.add_argument("--white", type=Path, help="its white image (with --raw)")
    args = ap.parse_args()

    import numba

    numba.set_num_threads(args.threads)
    from plenoptrack.simulate import render_frame
    from plenoptrack.study import _frame_particles, _setup, locate_image, traverse_positions

    with contextlib.ExitStack() as stack:
        if args.raw is not None:
            from plenoptrack.calibration import load_calibration
            from plenoptrack.io import read_raw
            from plenoptrack.lightfield import decode

            calib = load_calibration(args.calib)
            white = decode(read_raw(args.white), calib.grid) if args.white else None
            raws = [read_raw(args.raw)] * (args.images + 1)

            class _Label:
                label = f"{calib.camera.name} ({args.raw})"
                camera = calib.camera
            cfg = _Label()
        else:
            cdir, cfg = study_configuration(stack, args.study_dir, args.preset)
        if args.raw is None:
            optics, calib, white, field = _setup(str(cdir), cfg)
            pos = traverse_positions(cfg.travel_mm, cfg.step_mm)
            picks = pos[np.linspace(0, len(pos) - 1, args.images + 1).round().astype(int)]
            raws = [render_frame(optics, _frame_particles(field, float(p), 0),
                                 seed=np.random.default_rng([cfg.seed, 99, k]))
                    for k, p in enumerate(picks)]
        methods = [m.strip() for m in args.methods.split(",")]
        for m in methods:                                   # compile, warm caches
            locate_image(raws[0], calib, m, white=white)
        rows = {m: [] for m in methods}
        for raw in raws[1:]:
            for m in methods:
                _reset_hwm()
                base = _vm_rss_mb()
                t0 = time.perf_counter()
                found = locate_image(raw, calib, m, white=white)
                sec = time.perf_counter() - t0
                rows[m].append((sec, _vm_hwm_mb(), _vm_hwm_mb() - base, len(found)))
    print(f"{cfg.label}: {args.images} images, numba threads {args.threads}, "
          f"sensor {cfg.camera.sensor_shape_px[0]} x {cfg.camera.sensor_shape_px[1]}")
    print(f"{'method':<12} {'s/image':>9} {'peak MB':>9} {'+MB':>8} {'particles':>10}")
    med = {}
    for m in methods:
        r = np.array(rows[m])
        med[m] = (np.median(r[:, 0]), r[:, 1].max(), r[:, 2].max())
        print(f"{m:<12} {med[m][0]:9.2f} {med[m][1]:9.0f} {med[m][2]:8.0f} {r[:, 3].mean():10.1f}")
    if "perspective" in med:
        for m in methods:
            if m == "perspective":
                continue
            print(f"{m} / perspective: time {med[m][0] / med['perspective'][0]:.1f}x, peak memory "
                  f"{med[m][1] / med['perspective'][1]:.2f}x (increment "
                  f"{med[m][2] / max(med['perspective'][2], 1e-9):.1f}x)")
        print("paper (MATLAB, 12 cores): refocus / perspective time ~360x (1 h / 10 s), "
              "memory 10x (2 GB / 0.2 GB)")


if __name__ == "__main__":
    main()
