"""How far the calibration's edge-blur estimate lies from the blur of the images.

    python benchmarks/blur_estimator_bias.py
    python benchmarks/blur_estimator_bias.py --sigmas 0.3 0.5 0.7 --radii 1 2 --out blur.md

The calibration measures the views' edge blur on its dot cards
(:func:`plenoptrack.locate.opacity.edge_blur_by_depth`): from a dot image's peak relative
darkness ``p`` and the radius ``r`` of its summed shadow, ``sigma = r / sqrt(-2 ln(1 -
p))``, the Gaussian blur that darkens the centre of an opaque disc of radius ``r`` to
``p``. The darkest *sample* of a view lies up to half a view pixel from the dot's centre,
where the blurred disc is paler, so the estimate reads larger than the blur. This script
draws opaque discs blurred by a known Gaussian ``sigma`` (the darkness of a sample at
distance ``d`` from the centre is ``P(|X| < r)`` with ``X ~ N(d, sigma^2 I)``: a
non-central chi-square with 2 degrees of freedom), sampled on a unit grid with the centre
uniformly random within a pixel, and prints the estimator's median and 16-84 % range per
``(sigma, r)``. The image fits (:mod:`plenoptrack.locate.refine`) evaluate their model at
the samples themselves and want the blur; the opacity of particles
(:mod:`plenoptrack.locate.opacity`) is solved from their own darkest samples, which carry
the same offset as the dots'.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import ncx2

HALF = 8
"""Half-width of the sampled patch, view pixels."""


def sampled_disc(sigma: float, radius: float, centre: np.ndarray) -> np.ndarray:
    """Relative darkness of an opaque disc (``radius`` px) blurred by a Gaussian
    (``sigma`` px) at the samples of a ``(2 HALF + 1)^2`` unit grid, disc centred at
    ``centre`` (2,) px from the middle sample."""
    t, s = np.mgrid[-HALF:HALF + 1, -HALF:HALF + 1].astype(float)
    d2 = (s - centre[0]) ** 2 + (t - centre[1]) ** 2
    return ncx2.cdf(radius ** 2 / sigma ** 2, 2, d2 / sigma ** 2)


def estimates(sigma: float, radius: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) blur estimates of the calibration's estimator on discs with random sub-pixel
    centres."""
    from plenoptrack.locate.opacity import _blur_px

    peak, shadow = np.empty(n), np.empty(n)
    for i in range(n):
        dark = sampled_disc(sigma, radius, rng.uniform(-0.5, 0.5, 2))
        peak[i], shadow[i] = dark.max(), np.sqrt(dark.sum() / np.pi)
    return _blur_px(peak, shadow)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.3, 0.4, 0.5, 0.6, 0.7],
                        help="true Gaussian blur, view pixels")
    parser.add_argument("--radii", type=float, nargs="+", default=[1.0, 1.5, 2.0],
                        help="dot image radius, view pixels")
    parser.add_argument("--n", type=int, default=400, help="discs per (sigma, radius)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    start = time.perf_counter()
    lines = ["| sigma px | dot radius px | estimate, median | 16-84 % | median / sigma |",
             "| --- | --- | --- | --- | --- |"]
    for sigma in args.sigmas:
        for radius in args.radii:
            est = estimates(sigma, radius, args.n, rng)
            est = est[np.isfinite(est)]
            lo, mid, hi = np.percentile(est, [16, 50, 84])
            lines.append(f"| {sigma:g} | {radius:g} | {mid:.3f} | {lo:.3f}-{hi:.3f} | "
                         f"{mid / sigma:.2f} |")
    text = "\n".join(lines)
    print(text)
    print(f"({time.perf_counter() - start:.1f} s)", file=sys.stderr)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
