"""Time of the pixel-locking pattern fit against its per-component SVD baseline.

    python benchmarks/bench_locking_fit.py
    python benchmarks/bench_locking_fit.py --residuals 5000 20000 60000 --repeat 5

:func:`~plenoptrack.locate.pixel_locking.fit_locking_pattern` fits each frame's centroid
residuals (``s`` and ``t``) as a Fourier series in the lattice phase whose amplitudes
change linearly with the image's travel: a design of 18 columns (one harmonic) and one
row per kept centroid (tens of thousands on a full hall2019 frame), three rounds of
3-sigma rejection. The fit solves the 18 x 18 normal equations of both components at
once. The baseline is the same fit with ``numpy.linalg.lstsq`` (an SVD of the tall
design) per component and round, as it was first written. Both run on the same synthetic
residuals (a known pattern, Student-t noise so that the rejection works) in the same
process; the script prints the best of ``--repeat`` times, the ratio and the largest
difference between the two fits' coefficients.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from plenoptrack.locate.pixel_locking import _MAD_TO_SIGMA, fit_locking_pattern, fourier_terms


def residuals(n: int, seed: int = 0):
    """Synthetic centroid residuals (n, 2), lattice phases (n, 2) and travels (n,)."""
    rng = np.random.default_rng(seed)
    phase = rng.random((n, 2))
    travel = rng.uniform(2.0, 10.0, n)
    a, b = 2 * np.pi * phase[:, 0], 2 * np.pi * phase[:, 1]
    bias = np.c_[0.05 * np.cos(a) + 0.01 * travel * np.sin(b), 0.03 * np.sin(a + b)]
    return bias + 0.05 * rng.standard_t(3, (n, 2)), phase, travel


def baseline_coefficients(residual, phase, travel, harmonics: int = 1) -> np.ndarray:
    """The fit's coefficients (2, 2, K) by ``lstsq`` per component and round."""
    terms = fourier_terms(phase, harmonics)
    k = terms.shape[1]
    design = np.column_stack([np.ones(len(phase)), travel, terms, terms * travel[:, None]])
    keep = np.ones(len(residual), dtype=bool)
    coef = np.zeros((2, design.shape[1]))
    for _round in range(3):
        for c in range(2):
            coef[c] = np.linalg.lstsq(design[keep], residual[keep, c], rcond=None)[0]
        misfit = residual - design @ coef.T
        scale = _MAD_TO_SIGMA * np.median(np.abs(misfit[keep]), axis=0)
        keep = np.all(np.abs(misfit) <= 3.0 * np.maximum(scale, 1e-12), axis=1)
    return np.stack([coef[:, 2:2 + k], coef[:, 2 + k:]], axis=1)


def best_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--residuals", type=int, nargs="+", default=[5000, 20000, 60000])
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    print(f"{'residuals':>10} {'lstsq ms':>10} {'normal eq. ms':>14} {'ratio':>7} "
          f"{'max coef diff':>14}")
    for n in args.residuals:
        data = residuals(n)
        base = best_time(lambda: baseline_coefficients(*data), args.repeat)
        new = best_time(lambda: fit_locking_pattern(*data), args.repeat)
        diff = np.abs(baseline_coefficients(*data) - fit_locking_pattern(*data).coef).max()
        print(f"{n:>10} {1e3 * base:>10.1f} {1e3 * new:>14.1f} {base / new:>7.1f} "
              f"{diff:>14.1e}")


if __name__ == "__main__":
    main()
