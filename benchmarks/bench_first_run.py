"""First-run time of ``plenoptrack demo`` after a fresh installation, and of later runs.

A fresh installation has no numba cache of its own. plenoptrack ships a seed cache of the
demo's kernels compiled for the generic x86-64 processor (:mod:`plenoptrack._kernel_mode`):
the first run loads them instead of compiling, and starts a low-priority warm-up process
that compiles this processor's kernels for later runs.

This script builds a wheel of the checkout, installs it into a new virtual environment in
a temporary folder (or uses ``--venv``), and times, in one invocation, each run in a fresh
output folder:

1. ``baseline``: a first run with ``PLENOPTRACK_KERNELS=host`` on an empty cache: every
   kernel compiled on this machine (the calibrate and locate kernels in a second process
   while the demo simulates), which is what a first run cost before the seed cache;
2. ``first``: a first run as shipped, on an emptied cache (generic kernels from the seed
   cache; the warm-up starts);
3. ``second``: the next run, started at once, while the warm-up is still compiling;
4. ``later``: a run after the warm-up has finished (this processor's kernels);
5. ``generic``: a run with ``PLENOPTRACK_KERNELS=generic`` (what the generic kernels cost
   against ``later`` once nothing compiles).

"Emptied" means every numba cache file and the warm-up's marker removed from the
installed package. Wall time and the CPU time of the run's own process tree are printed
(the detached warm-up's CPU time is not in ``first``), with the wall-clock ratios against
the baseline. Timings on a shared machine are noisy: repeat with ``--repeat`` and compare
the medians.

Usage::

    python benchmarks/bench_first_run.py [--repeat N] [--venv PATH]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _install(tmp: Path) -> Path:
    """A new virtual environment in ``tmp`` with a wheel of the checkout installed."""
    dist, venv = tmp / "dist", tmp / "venv"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(dist),
                    str(ROOT)], check=True)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    wheel = next(dist.glob("plenoptrack-*.whl"))
    subprocess.run([str(venv / "bin" / "pip"), "install", "-q", str(wheel)], check=True)
    return venv


def _package_dir(venv: Path) -> Path:
    out = subprocess.run([str(venv / "bin" / "python"), "-c",
                          "import os, plenoptrack; print(os.path.dirname(plenoptrack.__file__))"],
                         check=True, capture_output=True, text=True)
    return Path(out.stdout.strip())


def _empty_cache(package: Path) -> None:
    """Remove every numba cache file and the warm-up's state from an installed package."""
    for path in package.rglob("__pycache__"):
        for item in path.iterdir():
            if item.suffix in (".nbi", ".nbc") or item.name.startswith("host-kernels"):
                item.unlink()
        shutil.rmtree(path / "numba-generic", ignore_errors=True)


def _wait_for_warm_up(package: Path, timeout_s: float = 900) -> float:
    """Seconds until the warm-up's lock is gone (its marker must then exist)."""
    t0 = time.perf_counter()
    lock = package / "__pycache__" / "host-kernels.lock"
    while lock.exists():
        if time.perf_counter() - t0 > timeout_s:
            raise TimeoutError("the warm-up did not finish")
        time.sleep(0.5)
    if not (package / "__pycache__" / "host-kernels.json").exists():
        raise RuntimeError("the warm-up ended without writing its marker")
    return time.perf_counter() - t0


def _run(venv: Path, work: Path, mode: str | None) -> tuple[float, float]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "NUMBA_CPU_NAME", "PLENOPTRACK_KERNELS",
                        "PLENOPTRACK_PRECOMPILE")}
    if mode is not None:
        env["PLENOPTRACK_KERNELS"] = mode
    out = work / f"demo-{time.monotonic_ns()}"
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([str(venv / "bin" / "plenoptrack"), "demo", "--out", str(out)], env=env,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1, help="rounds of the five runs")
    parser.add_argument("--venv", type=Path, default=None,
                        help="an environment with plenoptrack installed (not editable) to "
                             "use instead of a new one; its numba cache is emptied")
    args = parser.parse_args()
    names = ("baseline", "first", "second", "later", "generic")
    rows: dict[str, list[tuple[float, float]]] = {k: [] for k in names}
    warm_up_s = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        venv = args.venv or _install(tmp)
        if args.venv is None:
            print(f"installed a wheel into a new environment in {time.perf_counter() - t0:.0f} s")
        package = _package_dir(venv)
        for i in range(args.repeat):
            _empty_cache(package)
            rows["baseline"].append(_run(venv, tmp, "host"))
            _empty_cache(package)
            rows["first"].append(_run(venv, tmp, None))
            rows["second"].append(_run(venv, tmp, None))
            warm_up_s.append(_wait_for_warm_up(package))
            rows["later"].append(_run(venv, tmp, None))
            rows["generic"].append(_run(venv, tmp, "generic"))
            print(f"round {i + 1}: " + ", ".join(f"{k} {v[-1][0]:.1f} s" for k, v in rows.items())
                  + f"; the warm-up ran {warm_up_s[-1]:.0f} s more after the second run",
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
