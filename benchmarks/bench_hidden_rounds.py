"""Time of the hidden-particle search's rounds with and without refitting candidates that
an earlier round turned down where nothing has changed since.

From its second round on, the search (:func:`~plenoptrack.locate.perspective.search_hidden_rounds`)
does not fit again a candidate whose images coincide with one an earlier round fitted and
turned down, unless a particle changed near it since
(:class:`~plenoptrack.locate.hidden.EarlierRounds`). The baseline, in the same run, is
the same locator with that test switched off (every candidate of every round fitted, as
before the change): both are timed on the same images, alternating, best of
``--repeat`` each. Printed per image: seconds of each and their ratio, the particles
found, the candidates fitted (:meth:`_ResidualSearch.admit` and
:meth:`_ResidualSearch.fit_jointly` calls) and the pin heads matched within 0.3 mm
laterally and 1.5 mm in depth; then the totals.

Usage::

    python benchmarks/bench_hidden_rounds.py --study-dir STUDY/hall2019_M0.5_F105
    python benchmarks/bench_hidden_rounds.py --preset small        # calibrates first

``--study-dir`` reuses the calibration and pin field of a ``plenoptrack study``
configuration folder (``config.json``, ``calibration.json``, ``data/white.tif``; the
positions are traverse positions of its configuration, mm); without it the ``small``
preset's study configuration is calibrated in a temporary folder. The images are
rendered with the study's optics at ``--positions`` (default 10, 20, 25 and 40 mm of the
50 mm traverse: the most expensive images of the hall2019 study lie between 10 and
25 mm). One numba thread by default, as in a study worker.
"""

from __future__ import annotations

import argparse
import contextlib
import time
import warnings
from pathlib import Path

import numpy as np


def _every_candidate(self, rows):
    """The baseline: no candidate counts as turned down before."""
    return np.zeros(len(rows), dtype=bool)


def heads_matched(found, field, position_mm: float) -> int:
    """Pin heads of ``field`` (at traverse position ``position_mm``) with a particle of
    ``found`` within 0.3 mm laterally and 1.5 mm in depth."""
    heads = field[field["shape"] == "sphere"]
    hx, hy = heads["x"].to_numpy(), heads["y"].to_numpy()
    hz = heads["z"].to_numpy() + position_mm
    if len(found) == 0:
        return 0
    fx, fy, fz = (found[c].to_numpy()[:, None] for c in ("x", "y", "z"))
    close = (np.hypot(fx - hx, fy - hy) < 0.3) & (np.abs(fz - hz) < 1.5)
    return int(close.any(axis=0).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study-dir", type=Path, help="a study configuration folder to reuse")
    ap.add_argument("--preset", default="small", help="camera preset when no --study-dir")
    ap.add_argument("--positions", type=float, nargs="+", default=[10.0, 20.0, 25.0, 40.0],
                    help="traverse positions, mm")
    ap.add_argument("--repeat", type=int, default=2, help="timed calls per variant and image")
    ap.add_argument("--threads", type=int, default=1, help="numba threads")
    args = ap.parse_args()

    import numba

    numba.set_num_threads(args.threads)
    from bench_study import study_configuration   # this folder: run as a script
    from plenoptrack.locate import hidden, locate_frame
    from plenoptrack.simulate import render_frame
    from plenoptrack.study import _frame_particles, _setup

    search = hidden._ResidualSearch
    skipping = search.turned_down_before
    variants = {"every candidate": _every_candidate, "skipping": skipping}
    fits = {"n": 0}
    for name in ("admit", "fit_jointly"):
        method = getattr(search, name)

        def counted(self, q, _method=method):
            fits["n"] += 1
            return _method(self, q)
        setattr(search, name, counted)

    with contextlib.ExitStack() as stack:
        cdir, cfg = study_configuration(stack, args.study_dir, args.preset)
        if args.study_dir is None:
            args.positions = [p for p in args.positions if p <= cfg.travel_mm] or [5.0]
        optics, calib, white, field = _setup(str(cdir), cfg)
        print(f"{cfg.label}: numba threads {args.threads}, best of {args.repeat}", flush=True)
        total = {v: 0.0 for v in variants}
        warm = True
        for k, p in enumerate(args.positions):
            raw = render_frame(optics, _frame_particles(field, p, 0),
                               seed=np.random.default_rng([cfg.seed, 98, k]))
            best = {v: np.inf for v in variants}
            seen = {}
            for _ in range(args.repeat + warm):
                for v, test in variants.items():
                    search.turned_down_before = test
                    fits["n"] = 0
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        t0 = time.perf_counter()
                        found = locate_frame(raw, calib, white=white).particles
                        sec = time.perf_counter() - t0
                    if not warm:
                        best[v] = min(best[v], sec)
                    seen[v] = (len(found), fits["n"], heads_matched(found, field, p))
                warm = False
            search.turned_down_before = skipping
            for v in variants:
                total[v] += best[v]
            print(f"{p:5.1f} mm: " + ", ".join(
                f"{v} {best[v]:.2f} s ({seen[v][0]} particles, {seen[v][1]} fits, "
                f"{seen[v][2]} heads)" for v in variants)
                + f"; ratio {best['every candidate'] / best['skipping']:.2f}", flush=True)
    print(f"total: every candidate {total['every candidate']:.2f} s, skipping "
          f"{total['skipping']:.2f} s, ratio "
          f"{total['every candidate'] / total['skipping']:.2f}")


if __name__ == "__main__":
    main()
