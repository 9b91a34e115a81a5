"""First-run time of ``plenoptrack demo``: an empty numba cache against a filled one.

A fresh installation has no numba cache, so its first ``plenoptrack demo`` compiles every
kernel it runs. This script gives each run an empty cache folder of its own
(``NUMBA_CACHE_DIR``), which is what a fresh installation sees, and times, in one
invocation and each in a fresh output folder:

1. ``baseline``: first run with ``PLENOPTRACK_PRECOMPILE=0`` (every kernel compiled in
   the main process when it is first called);
2. ``first``: first run as shipped (the calibrate and locate kernels compiled by a second
   process while the main one simulates);
3. ``later``: the same command again with the cache that run 2 filled.

Wall time and the CPU time of the process tree are printed with the ratios against the
baseline. Timings on a shared machine are noisy: repeat with ``--repeat`` and compare
the medians.

Usage::

    python benchmarks/bench_first_run.py [--repeat N]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(cache_dir: Path, work: Path, *, precompile: bool) -> tuple[float, float]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir),
               PLENOPTRACK_PRECOMPILE="1" if precompile else "0")
    out = work / f"demo-{time.monotonic_ns()}"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "plenoptrack", "demo", "--out", str(out)], env=env,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1, help="rounds of the three runs")
    args = parser.parse_args()
    rows: dict[str, list[tuple[float, float]]] = {"baseline": [], "first": [], "later": []}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for i in range(args.repeat):
            rows["baseline"].append(_run(tmp / f"cache-base-{i}", tmp, precompile=False))
            rows["first"].append(_run(tmp / f"cache-first-{i}", tmp, precompile=True))
            rows["later"].append(_run(tmp / f"cache-first-{i}", tmp, precompile=True))
            print(f"round {i + 1}: " + ", ".join(f"{k} {v[-1][0]:.1f} s" for k, v in rows.items()),
                  flush=True)
    base_wall = statistics.median(w for w, _ in rows["baseline"])
    print(f"{os.cpu_count()} CPU(s), load average {os.getloadavg()[0]:.1f} at the end, "
          f"{args.repeat} round(s), medians")
    print(f"{'run':10s} {'wall s':>8s} {'CPU s':>8s} {'wall vs baseline':>18s}")
    for name, values in rows.items():
        wall = statistics.median(w for w, _ in values)
        cpu = statistics.median(c for _, c in values)
        print(f"{name:10s} {wall:8.1f} {cpu:8.1f} {base_wall / wall:17.2f}x")


if __name__ == "__main__":
    main()
