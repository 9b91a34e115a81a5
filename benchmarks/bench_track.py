"""Time `plenoptrack track` on a simulated vortex ring: linking and smoothing.

    python benchmarks/bench_track.py [--particles 1000] [--frames 40] [--repeats 3]

Tracers of the simulator's vortex-ring scene (truth positions, no rendering) with the
locator's typical noise (lateral 0.04 mm, depth 0.12 mm, 5 % depth outliers, 10 % of the
points missed; the noise of ``tests/test_track.py``), linked and smoothed with the default
settings. Prints the seconds of each step (best of ``--repeats``) and, as the baseline
measured in the same run, the smoother with the robust start's curvature taken over every
three points of the widest window (the form before it took only each window's own
points); the two smoothed tables must be identical. The search for swapped tracks
(:mod:`plenoptrack.swaps`) and for pieces of one body (:mod:`plenoptrack.pieces`: pairs,
then the merge) are timed against the linking they follow.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

from plenoptrack import track
from plenoptrack.pieces import merge_pieces, piece_pairs
from plenoptrack.swaps import repair_swaps
from plenoptrack.simulate.scenes import VortexRing, vortex_ring_scene
from plenoptrack.track import TrackSettings, link_particles, smooth_tracks

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_track import noisy  # noqa: E402


def _all_triples_half_curvature(dt: np.ndarray, yy: np.ndarray) -> np.ndarray:
    """The baseline: every three columns of the window array, NaN-aware median."""
    a, b, c = (np.array(v) for v in zip(*itertools.combinations(range(dt.shape[1]), 3)))
    with np.errstate(invalid="ignore", divide="ignore"):
        first_ab = (yy[:, b] - yy[:, a]) / (dt[:, b] - dt[:, a])
        first_bc = (yy[:, c] - yy[:, b]) / (dt[:, c] - dt[:, b])
        second = (first_bc - first_ab) / (dt[:, c] - dt[:, a])
    second[~np.isfinite(second)] = np.nan
    usable = np.isfinite(second).any(axis=1)
    half = np.zeros(len(dt))
    half[usable] = np.nanmedian(second[usable], axis=1)
    return half


def _best(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", type=int, default=1000)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    truth = vortex_ring_scene(VortexRing(n_particles=args.particles, frames=args.frames)).truth
    points = noisy(truth, seed=0)
    settings = TrackSettings()
    t_link, linked = _best(lambda: link_particles(points, settings), args.repeats)
    t_swaps, (_, n_swaps) = _best(lambda: repair_swaps(
        linked, search_range_mm=settings.search_range_mm, degree=settings.order,
        window=settings.window, clip=settings.clip), args.repeats)
    t_pairs, pairs = _best(lambda: piece_pairs(linked), args.repeats)
    t_merge, _ = _best(lambda: merge_pieces(linked, pairs), args.repeats)
    t_smooth, smoothed = _best(lambda: smooth_tracks(linked, settings), args.repeats)
    current = track._robust_half_curvature
    track._robust_half_curvature = _all_triples_half_curvature
    try:
        t_base, baseline = _best(lambda: smooth_tracks(linked, settings), args.repeats)
    finally:
        track._robust_half_curvature = current
    same = baseline.equals(smoothed)
    print(f"{len(points)} points ({args.particles} tracers x {args.frames} frames), "
          f"best of {args.repeats}:")
    print(f"  link    {t_link:7.2f} s")
    print(f"  swaps   {t_swaps:7.2f} s  ({n_swaps} exchanged; "
          f"{t_swaps / t_link:.3f} of the linking time)")
    print(f"  pieces  {t_pairs + t_merge:7.2f} s  ({len(pairs)} pairs merged; "
          f"{(t_pairs + t_merge) / t_link:.3f} of the linking time)")
    print(f"  smooth  {t_smooth:7.2f} s  (baseline {t_base:.2f} s: {t_base / t_smooth:.2f}x; "
          f"identical output: {same})")
    if not same:
        raise SystemExit("the smoother's output differs from the baseline's")


if __name__ == "__main__":
    main()
