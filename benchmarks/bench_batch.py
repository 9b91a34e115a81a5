"""Throughput of ``plenoptrack batch`` on full-sensor hall2019 images: 1 against 2 workers.

    python benchmarks/bench_batch.py                      # 8 frames, 3 rounds
    python benchmarks/bench_batch.py --frames 16 --rounds 5

The calibration (lenslet grid and a DLFC from seven simulated dot cards, ideal optics) is
the one ``bench_locate.py`` simulates and caches in ``--workdir``; this script adds a
simulated white image and ``--distinct`` raw frames of ``--particles`` particles of 1 mm,
written as uncompressed uint16 TIFF files (a camera's 58 MB) and cycled to ``--frames``
files. Everything is cached in ``--workdir``.

Measured, all in the same run:

- the floor any pipeline pays: reading one raw TIFF (``plenoptrack.io.read_frames``, page
  cache warm) and hashing it (SHA-256, the resume key);
- rounds of batches on a local Dask cluster (:func:`plenoptrack.batch.local_cluster`),
  interleaved so that the machine's changing load hits every configuration alike: 1
  worker with one numba thread, 1 worker with numba threads on every core (what
  ``--workers 1`` gives), and 2 workers with one thread each. Each cluster is started
  and warmed up (one frame located into a scratch folder: imports, compiled kernels,
  calibration and white image loaded) before its batch is timed, from submission to the
  last part written, into a new folder;
- per frame, the time a worker spends on it (hash, read, locate, write), wall-clock and
  CPU (the worker process's, all threads), and each worker's peak resident memory
  (``VmHWM``) over its whole life.

On a machine shared with other work the wall-clock ratios measure the share of the
cores the batch gets as much as the batch (with Linux's autogroup scheduling a session
gets one share however many processes it runs); the CPU time per frame of 1 worker alone
against 2 workers side by side shows what running two frames at once costs each
(memory bandwidth, caches), and 2 x their ratio is the throughput ratio two free cores
would give.

Printed: frames per second of each configuration per round, the throughput ratio of 2
workers over 1 worker (one thread) per round with its spread, time per image over the
read floor, the peak memory per worker, and the projected wall time of 30,000 images on
2 cores (measured 2-worker throughput) and on a 100-core cluster (100 one-thread
workers, each at the measured per-frame time of the 1-worker run).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _vm_hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _prepare(args) -> tuple[Path, Path, list[Path]]:
    """Calibration file, white image and the raw TIFF files of the benchmark."""
    import tifffile

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_locate import _prepare as prepare_locate

    from plenoptrack import preset
    from plenoptrack.calibration import record_white, save_calibration
    from plenoptrack.simulate import make_optics, render_white

    work = args.workdir
    calib, raw0, _ = prepare_locate("hall2019", args.particles, 0, work)
    white_path = work / "hall2019_white.tif"
    if not white_path.exists():
        optics = make_optics(preset("hall2019"), seed=0, realism="ideal")
        tifffile.imwrite(white_path, render_white(optics, seed=np.random.default_rng([0, 2])))
    calib_path = work / "hall2019_batch_calibration.json"
    if not calib_path.exists():
        save_calibration(record_white(calib, white_path, calibration_path=calib_path), calib_path)
    sources = []
    for seed in range(args.distinct):
        path = work / f"hall2019_{args.particles}_seed{seed}.tif"
        if not path.exists():
            raw = raw0 if seed == 0 else prepare_locate("hall2019", args.particles, seed, work)[1]
            tifffile.imwrite(path, raw)  # uncompressed, like a camera's file
        sources.append(path)
    raw_dir = work / f"batch_raw_{args.particles}_{args.frames}"
    raw_dir.mkdir(exist_ok=True)
    files = []
    for j in range(args.frames):
        target = raw_dir / f"frame_{j:05d}.tif"
        if not target.exists():
            shutil.copyfile(sources[j % len(sources)], target)
        files.append(target)
    return calib_path, white_path, files


def _floor(files: list[Path]) -> tuple[float, float]:
    """Median seconds to read one raw TIFF and to hash one (page cache warm)."""
    from plenoptrack.calibration import file_sha256
    from plenoptrack.io import read_frames

    for f in files:  # warm the page cache
        read_frames(f)
    reads, hashes = [], []
    for f in files:
        t0 = time.perf_counter()
        read_frames(f)
        reads.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        file_sha256(f)
        hashes.append(time.perf_counter() - t0)
    return statistics.median(reads), statistics.median(hashes)


def _one_run(n_workers: int, threads: int, calib: Path, white: Path, files: list[Path],
             scratch: Path) -> dict:
    """Start a cluster, warm it up, time one batch over ``files``; return the figures."""
    from distributed import Client, LocalCluster

    from plenoptrack.batch import run_batch

    env = {k: str(threads) for k in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS",
                                     "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    import logging

    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                      host="127.0.0.1", dashboard_address=":0", memory_limit="4GB",
                      silence_logs=logging.ERROR, env=env) as cluster, Client(cluster) as client:
        warm = Path(tempfile.mkdtemp(dir=scratch))
        # one frame per worker, so that every worker has loaded everything
        run_batch(files[:n_workers], calib, warm / "out", white_file=white, client=client)
        out = Path(tempfile.mkdtemp(dir=scratch)) / "out"
        outcomes = []
        t0 = time.perf_counter()
        result = run_batch(files, calib, out, white_file=white, client=client,
                           on_outcome=outcomes.append)
        wall = time.perf_counter() - t0
        peaks = list(client.run(_vm_hwm_mb).values())
    assert result.done == len(files) and result.failed == 0, result
    return {"wall": wall, "fps": len(files) / wall,
            "per_frame": statistics.median(o.seconds for o in outcomes),
            "cpu_per_frame": statistics.median(o.cpu_seconds for o in outcomes),
            "peak_mb": max(peaks), "particles": result.n_particles}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=8, help="Frames per batch.")
    ap.add_argument("--distinct", type=int, default=4, help="Distinct simulated frames.")
    ap.add_argument("--particles", type=int, default=100, help="Particles per frame.")
    ap.add_argument("--rounds", type=int, default=3, help="Interleaved rounds.")
    ap.add_argument("--workdir", type=Path,
                    default=Path(tempfile.gettempdir()) / "plenoptrack-bench")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    print(f"load average at start: {os.getloadavg()}, {os.cpu_count()} cores")
    calib, white, files = _prepare(args)
    read_s, hash_s = _floor(files)
    size_mb = files[0].stat().st_size / 1e6
    print(f"{len(files)} frames of {size_mb:.0f} MB; read one raw TIFF {read_s:.3f} s, "
          f"SHA-256 of it {hash_s:.3f} s (medians, page cache warm)")
    configs = [("1 worker x 1 thread", 1, 1), ("1 worker x all threads", 1, os.cpu_count() or 1),
               ("2 workers x 1 thread", 2, 1)]
    rows: dict[str, list[dict]] = {name: [] for name, _, _ in configs}
    with tempfile.TemporaryDirectory(dir=args.workdir) as scratch:
        for r in range(args.rounds):
            for name, n, threads in configs:
                row = _one_run(n, threads, calib, white, files, Path(scratch))
                rows[name].append(row)
                print(f"round {r + 1} {name:24s} {row['fps']:.3f} frames/s "
                      f"({row['wall']:.1f} s for {len(files)}; {row['per_frame']:.2f} s, CPU "
                      f"{row['cpu_per_frame']:.2f} s per frame on a worker; peak "
                      f"{row['peak_mb']:.0f} MB per worker; "
                      f"load {os.getloadavg()[0]:.1f})", flush=True)
    one, all1, two = (rows[name] for name, _, _ in configs)
    ratios = [b["fps"] / a["fps"] for a, b in zip(one, two)]
    ratios_all = [b["fps"] / a["fps"] for a, b in zip(all1, two)]
    print()
    print(f"2 workers / 1 worker (1 thread): throughput ratio per round "
          f"{', '.join(f'{x:.2f}' for x in ratios)}; median {statistics.median(ratios):.2f}, "
          f"spread {min(ratios):.2f}-{max(ratios):.2f}")
    print(f"2 workers / 1 worker (all threads): "
          f"{', '.join(f'{x:.2f}' for x in ratios_all)}; median {statistics.median(ratios_all):.2f}")
    cpu1 = statistics.median(row["cpu_per_frame"] for row in one)
    cpu2 = statistics.median(row["cpu_per_frame"] for row in two)
    print(f"CPU time per frame: {cpu1:.2f} s alone, {cpu2:.2f} s with two workers side by "
          f"side; two workers on two free cores would give {2 * cpu1 / cpu2:.2f} x the "
          "throughput of one (the machine's load does not enter this figure)")
    per_frame = statistics.median(row["per_frame"] for row in one)
    print(f"time per image on one worker (hash, read, locate, write): {per_frame:.2f} s = "
          f"{per_frame / read_s:.1f} x reading the raw TIFF ({read_s:.3f} s); hashing "
          f"{hash_s / per_frame:.1%} of it")
    peak = max(row["peak_mb"] for rs in rows.values() for row in rs)
    print(f"peak resident memory per worker: {peak:.0f} MB (largest over every run)")
    fps2 = statistics.median(row["fps"] for row in two)
    n_paper = 30000
    print(f"projected 30,000 images on this 2-core machine: {n_paper / fps2 / 3600:.1f} h "
          f"({fps2:.3f} frames/s, 2 workers, median of {args.rounds} rounds)")
    cluster_s = n_paper * per_frame / 100
    print(f"projected 30,000 images on 100 cores (100 one-thread workers at {per_frame:.2f} s "
          f"per frame): {cluster_s / 60:.1f} min, reading "
          f"{100 * size_mb / per_frame:.0f} MB/s from storage")
    # the same from CPU time (what the frames cost when the cores are free), with the
    # per-frame cost of frames run side by side
    print(f"from CPU time per frame ({cpu2:.2f} s side by side): 30,000 images on 2 free cores "
          f"{n_paper * cpu2 / 2 / 3600:.1f} h, on 100 cores {n_paper * cpu2 / 100 / 60:.1f} min "
          f"(reading {100 * size_mb / cpu2:.0f} MB/s from storage)")


if __name__ == "__main__":
    main()
