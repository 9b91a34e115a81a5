"""Time and memory of locating particles in one full-sensor hall2019 raw image.

    python benchmarks/bench_locate.py                  # hall2019, 100 particles of 1 mm
    python benchmarks/bench_locate.py --preset small --particles 20
    python benchmarks/bench_locate.py --scaling        # 100, 400, 1000 particles of 0.5 mm

The calibration (lenslet grid from a simulated white image, DLFC from seven simulated
dot cards) and the raw image are simulated once, in a child process (the heap a
simulation leaves behind would count in the peak memory), and cached in ``--workdir`` (a
few minutes on the full sensor; the raw image is keyed by preset, particle count and
seed); later runs reuse them. The compiled kernels are warmed up on the same image before
timing.

Stages are those :func:`~plenoptrack.locate.perspective.locate_frame` reports in
``LocateResult.stage_seconds`` for the fastest of ``--repeat`` calls on the raw image:
decode (raw to light field); segment (every view, merged regions shared out between
their dark cores); cluster (every clustering pass); triangulate + addition (solves, duplicate
merging, centroid addition); checks (final consistency checks, last solve, table);
refine (the image-model refinement of overlapped particles); total (the whole call). The
same call with the refinement switched the other way (``check.refine_images``) is timed
too (best of ``--repeat``) and printed as a ratio; so is the same call with the
decode's sampling geometry and lens centres computed afresh on every call, as they were
before they were cached per grid (``tests/locate/_previous.py``; medians of ``--repeat``
calls alternating with the default's). Peak memory is the process's ``VmHWM``.

The baseline is the same call with the triangulation solved by one
:func:`scipy.optimize.least_squares` call per particle (``solver="scipy"``), run once on
the same image; the ratios are baseline time over plenoptrack time for the
triangulate + addition + checks stages and for the whole call.

``--scaling`` measures how the cost grows with the number of particles: on ideal optics,
for each of ``--counts`` particles (default 100, 400 and 1000 of ``--diameter`` 0.5 mm:
1000 particles of 1 mm overlap in most views of the default volume, and the locator
then finds only about three quarters of them) and each scene seed of ``--seeds``, it
times one call with one numba thread and reads the peak memory of that call
(``VmHWM``, reset before it). The baseline is the same call, in the same run, with the
steps that compared every particle with every other particle, centroid or k-means centre
put back as they were (``tests/locate/_previous.py``: duplicate merging, centroid
addition, the merged-region and explained-centroid checks, the trimmed refit, Lloyd
iterations, k-means++ seeding, the triangulation that re-tested every centroid in
every outlier-rejection round, and the split and hidden-particle checks that compared
every particle's images with every other's in every view), and the image fits' noise
level taken with two ``np.median`` calls; both must give the same particles and
detections tables. Printed per count: recall, the plain and robust (1.4826 MAD) standard deviation
of the depth error of the particles matched within 1 mm (pooled over the seeds; 1000
particles on hall2019 are 0.006 per microlens, the sparse bound of the locator's
acceptance, where the plain one must stay at or below 0.05 mm), seconds per frame and per
particle (mean over the seeds), peak MB (largest over the seeds), the per-stage seconds
of both, and the ratio baseline over plenoptrack.

``--kernels`` times single kernels (:data:`KERNELS_TIMED`: the decode's gather, the
segmentation of every view, the refinement's patch masks, the k-means Lloyd iterations,
the refinement's image fits) on the calls one locate of the image makes, recorded and
replayed, against the same functions of a baseline revision
(:data:`KERNEL_BASELINE_REV`, :data:`VIEWS_BASELINE_REV`, :data:`FIT_VECTOR_BASELINE_REV`
or :data:`DECODE_BASELINE_REV`, read with ``git show`` and imported beside the current
modules), alternating, best of ``--repeat`` each, with ``--threads`` numba threads
(default 1), and says whether the outputs are identical. ``--only WORD...`` times the
kernels whose label holds one of the words; a kernel whose baseline cannot take today's
call (an argument added since) is skipped with a note.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib.util
import inspect
import sys
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np


def _vm_hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _reset_hwm() -> None:
    """Give freed memory back to the system, then reset the process's peak resident
    memory (``VmHWM``) to its current size (Linux; elsewhere a no-op)."""
    import ctypes
    import gc

    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def _prepare(preset_name: str, n: int, seed: int, workdir: Path,
             diameter_mm: float | None = None):
    import pandas as pd

    from plenoptrack import preset
    from plenoptrack.calibration import calibrate_from_white, load_calibration, save_calibration
    from plenoptrack.lightfield import decode
    from plenoptrack.locate.dlfc import fit_dlfc
    from plenoptrack.locate.dotcards import dotcard_points
    from plenoptrack.simulate import (default_dotcard, make_optics, make_scene, render_dotcard,
                                      render_frame, render_white)
    from plenoptrack.simulate.scene import volume_depth_mm

    camera = preset(preset_name)
    workdir.mkdir(parents=True, exist_ok=True)
    calib_path = workdir / f"{preset_name}_calibration.json"
    size = "" if diameter_mm is None else f"_d{diameter_mm:g}"
    raw_path = workdir / f"{preset_name}_{n}_seed{seed}{size}_raw.npy"
    optics = make_optics(camera, seed=0, realism="ideal")
    if not calib_path.exists():
        t0 = time.perf_counter()
        white = render_white(optics, seed=np.random.default_rng([0, 2]))
        calib, _ = calibrate_from_white(white, camera)
        card = default_dotcard(camera)
        half = volume_depth_mm(camera) / 2
        points = []
        for k, z in enumerate(np.linspace(-half, half, 7)):
            image = render_dotcard(optics, float(z), card=card,
                                   seed=np.random.default_rng([0, 4, k]))
            points.append(dotcard_points(decode(image, calib.grid), spacing_mm=card.spacing_mm,
                                         z_mm=float(z), camera=camera))
        dlfc = fit_dlfc(pd.concat(points, ignore_index=True), order=4, group_by="z", reject_k=5)
        save_calibration(calib.with_dlfc(dlfc), calib_path)
        print(f"simulated and calibrated in {time.perf_counter() - t0:.0f} s -> {calib_path}")
    scene = make_scene(camera, n_particles=n, seed=seed, diameter_mm=diameter_mm)
    if not raw_path.exists():
        np.save(raw_path, render_frame(optics, scene.truth, seed=np.random.default_rng([seed, 3, 0])))
    return load_calibration(calib_path), np.load(raw_path), scene.truth


def _prepare_apart(preset_name: str, n: int, seed: int, workdir: Path,
                   diameter_mm: float | None = None) -> None:
    """Simulate what :func:`_prepare` would in a child process, so that the heap the
    simulation leaves behind (which ``malloc_trim`` does not always return) is not counted
    in this process's peak memory."""
    args = [sys.executable, str(Path(__file__).resolve()), "--prepare-only", "--preset",
            preset_name, "--particles", str(n), "--seed", str(seed), "--workdir", str(workdir)]
    if diameter_mm is not None:
        args += ["--diameter", str(diameter_mm)]
    subprocess.run(args, check=True)


def _best(fn, repeat: int) -> tuple[float, object]:
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _load_previous():
    """The previous versions of the replaced steps, kept with the tests."""
    path = Path(__file__).resolve().parents[1] / "tests" / "locate" / "_previous.py"
    spec = importlib.util.spec_from_file_location("_previous", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # numba's cache finds compiled kernels by module name
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _previous_steps(previous, only=None):
    """Put the previous steps back into the locator for the duration of the block (those
    of the modules ``only`` when given)."""
    swaps = [(importlib.import_module(module), name)
             for module, names in previous.REPLACED.items() for name in names
             if only is None or module in only]
    saved = [(mod, name, getattr(mod, name)) for mod, name in swaps]
    try:
        for mod, name in swaps:
            setattr(mod, name, getattr(previous, name))
        yield
    finally:
        for mod, name, fn in saved:
            setattr(mod, name, fn)


def _timed_call(fn) -> tuple[float, float, object]:
    """Seconds and peak MB (``VmHWM`` reset before) of one call, and its result."""
    _reset_hwm()
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, _vm_hwm_mb(), out


def scaling(args) -> None:
    """Time per frame, per particle and peak memory against the previous steps."""
    import numba

    from plenoptrack.evaluate import evaluate_particles
    from plenoptrack.locate.perspective import locate_frame

    numba.set_num_threads(1)
    for n in args.counts:
        for seed in args.seeds:
            _prepare_apart(args.preset, n, seed, args.workdir, args.diameter)
    previous = _load_previous()
    stages = ("decode", "segment", "cluster", "triangulate", "checks", "refine")
    rows = []
    warm = False
    for n in args.counts:
        acc = {"new": [], "old": [], "new_mb": [], "old_mb": [], "recall": [], "dz": [],
               "new_st": np.zeros(len(stages)), "old_st": np.zeros(len(stages))}
        for seed in args.seeds:
            calib, raw, truth = _prepare(args.preset, n, seed, args.workdir, args.diameter)
            call = functools.partial(locate_frame, raw, calib)
            if not warm:  # compile (or load) the kernels of both versions
                call()
                with _previous_steps(previous):
                    call()
                warm = True
            t_new, mb_new, new = _timed_call(call)
            with _previous_steps(previous):
                t_old, mb_old, old = _timed_call(call)
            if not (new.particles.equals(old.particles)
                    and new.detections.equals(old.detections)):
                raise SystemExit(f"{n} particles, seed {seed}: the previous steps give a "
                                 "different result")
            acc["new"].append(t_new)
            acc["old"].append(t_old)
            acc["new_mb"].append(mb_new)
            acc["old_mb"].append(mb_old)
            acc["new_st"] += [new.stage_seconds[k] for k in stages]
            acc["old_st"] += [old.stage_seconds[k] for k in stages]
            acc["recall"].append(evaluate_particles(new.particles, truth,
                                                    tolerance_mm=2.0).recall)
            acc["dz"].append(_depth_errors(new.particles, truth))
            print(f"  {n} particles, seed {seed}: {len(new.particles)} located, "
                  f"{t_new:.2f} s ({mb_new:.0f} MB) vs previous {t_old:.2f} s "
                  f"({mb_old:.0f} MB), same particles table", flush=True)
            del new, old, raw, call
        k = len(args.seeds)
        dz = np.concatenate(acc["dz"])
        rows.append((n, np.mean(acc["new"]), max(acc["new_mb"]), np.mean(acc["old"]),
                     max(acc["old_mb"]), np.mean(acc["recall"]), dz, acc["new_st"] / k,
                     acc["old_st"] / k))

    print(f"\n{args.preset}, ideal optics, particles of {args.diameter:g} mm, seeds "
          f"{list(args.seeds)}, one numba thread; mean over the seeds (peak: largest)")
    print(f"{'particles':>9} {'recall':>6} {'sd z mm':>7} {'robust':>6} | {'s/frame':>8} "
          f"{'ms/part':>8} {'peak MB':>8} | {'previous s':>11} {'ms/part':>8} {'peak MB':>8} | "
          f"{'ratio':>6}")
    for n, t_new, mb_new, t_old, mb_old, recall, dz, _, _ in rows:
        print(f"{n:>9} {recall:>6.3f} {_sd(dz):>7.4f} {_robust_sd(dz):>6.4f} | {t_new:>8.2f} "
              f"{1e3 * t_new / n:>8.2f} {mb_new:>8.0f} | {t_old:>11.2f} {1e3 * t_old / n:>8.2f} "
              f"{mb_old:>8.0f} | {t_old / t_new:>5.1f}x")
    print("sd z: plain standard deviation of the depth error of the particles matched within "
          "1 mm (Hungarian), over the seeds; robust: 1.4826 MAD")
    print("\nstage seconds (plenoptrack / previous): " + ", ".join(stages))
    for n, *_, st_new, st_old in rows:
        print(f"{n:>9}  " + "  ".join(f"{a:6.2f} / {b:6.2f}" for a, b in zip(st_new, st_old,
                                                                        strict=True)))


def _depth_errors(particles, truth) -> np.ndarray:
    """Measured minus true depth (mm) of the particles matched to the truth within 1 mm
    (:func:`plenoptrack.evaluate.match_particles`)."""
    from plenoptrack.evaluate import match_particles

    pairs = match_particles(particles, truth, tolerance_mm=1.0)
    return (particles.loc[pairs["measured_index"], "z"].to_numpy(float)
            - truth.loc[pairs["truth_index"], "z"].to_numpy(float))


def _sd(values: np.ndarray) -> float:
    return float(np.std(values, ddof=1)) if len(values) > 1 else float("nan")


def _robust_sd(values: np.ndarray) -> float:
    """1.4826 MAD (:func:`scipy.stats.median_abs_deviation` with the normal scale)."""
    from scipy.stats import median_abs_deviation

    return float(median_abs_deviation(values, scale="normal")) if len(values) else float("nan")


KERNEL_BASELINE_REV = "ab05a35c462d9afa5dba85e356132be9c85f0935"
"""Revision whose kernels are the baseline of ``--kernels``: before the decode's gather
interpolated rows then columns, segmentation visited only the pixels in and around
regions after labelling and reused one work space per thread, and the patch masks
computed the held neighbours' image only on the fitted pixels, with ``sqrt`` for
``hypot``."""

def _fitted_part(out):
    """The patch masks the fit reads: ``near``, ``fit`` and the held image on ``fit``."""
    fixed, near, fit = out
    return np.where(fit, fixed, 1.0), near, fit


def _fit_params(out):
    """What the locator reads of an image fit: its parameters and sigmas (None: no fit)."""
    return (np.full(1, np.nan),) * 2 if out is None else (out.params, out.sigma)


VIEWS_BASELINE_REV = "8d3ba72"
"""Revision before the k-means lower bounds dropped by the moves of nearby centres only
and before the image fits predicted in the DLFC's view-factorised form."""

FIT_VECTOR_BASELINE_REV = "996abc3"
"""Revision before the image fits' kernels were compiled with numpy's error model (no
zero-divisor branch in the per-pixel passes, which the compiler then vectorises) and took
their exponentials in a vectorised pass of their own (``refine._exp_neg_squares``). The
fits' previous baseline, 5770203, preceded their listing of their pixels once per fit."""

DECODE_BASELINE_REV = "a24c564"
"""Revision before the decode's gather computed each lens's interpolated image once
for the (about two) samples that blend it, instead of once per sample."""

KERNELS_TIMED = (("decode gather", "lightfield.decode", "_gather", None, DECODE_BASELINE_REV),
                 ("segmentation", "locate.segment", "_region_stats", None, None),
                 ("refinement patch masks", "locate.refine", "_patch_masks", _fitted_part, None),
                 ("k-means Lloyd", "locate.cluster", "_lloyd", None, VIEWS_BASELINE_REV),
                 ("refinement image fits", "locate.refine", "fit_images", _fit_params,
                  FIT_VECTOR_BASELINE_REV))
"""``(label, module under plenoptrack, function, what to compare, baseline revision)``
timed by ``--kernels``; ``what to compare`` maps an output to the part the locator reads
(None: all of it); the baseline revision is :data:`KERNEL_BASELINE_REV` when None. A
function that fills an output argument (the decode's ``_gather``) is compared on that
argument. The calls of a function in :data:`MOVES_ARGUMENTS` are recorded and replayed
on copies of their array arguments."""

MOVES_ARGUMENTS = frozenset({"k-means Lloyd"})
"""Functions that change an argument in place (the k-means moves its centres)."""


def _baseline_module(name: str, rev: str = KERNEL_BASELINE_REV):
    """Module ``plenoptrack.<name>`` (e.g. ``locate.segment``) of ``rev``, imported as a
    sibling of the current module (its relative imports resolve to the current package)."""
    root = Path(__file__).resolve().parents[1]
    package, _, leaf = f"plenoptrack.{name}".rpartition(".")
    relpath = f"src/plenoptrack/{name.replace('.', '/')}.py"
    src = subprocess.run(["git", "show", f"{rev}:{relpath}"], cwd=root,
                         capture_output=True, text=True, check=True).stdout
    path = Path(tempfile.mkdtemp(prefix="bench_kernels_")) / f"_{leaf}_baseline.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(f"{package}._{leaf}_baseline", path)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = package
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _without_new_keywords(fn):
    """``fn``, ignoring keyword arguments it does not take (options added since its
    revision, e.g. a value computed once by the caller instead of in every call)."""
    if hasattr(fn, "py_func"):   # a compiled kernel: positional arguments only
        return fn
    names = set(inspect.signature(fn).parameters)

    @functools.wraps(fn)
    def call(*a, **k):
        return fn(*a, **{key: v for key, v in k.items() if key in names})

    return call


def _copied(args: tuple) -> tuple:
    """``args`` with every array copied."""
    return tuple(a.copy() if isinstance(a, np.ndarray) else a for a in args)


def _same(a, b) -> bool:
    if isinstance(a, tuple):
        return all(_same(x, y) for x, y in zip(a, b))
    return np.array_equal(a, b)


def _close(a, b) -> float:
    """Largest absolute difference between two (nested tuples of) arrays."""
    if isinstance(a, tuple):
        return max(_close(x, y) for x, y in zip(a, b))
    return float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float)), initial=0.0))


def _n_params(fn) -> int:
    """Number of positional parameters of a (compiled) function."""
    import inspect

    return len(inspect.signature(getattr(fn, "py_func", fn)).parameters)


def bench_kernels(args) -> None:
    """Each kernel of :data:`KERNELS_TIMED` now and at :data:`KERNEL_BASELINE_REV`, on the
    calls one locate of the image makes (recorded, then replayed)."""
    import importlib

    import numba

    from plenoptrack.locate.perspective import locate_frame

    calib, raw, _ = _prepare(args.preset, args.particles, args.seed, args.workdir, args.diameter)
    numba.set_num_threads(args.threads)
    modules = {name: importlib.import_module(f"plenoptrack.{name}")
               for _, name, _, _, _ in KERNELS_TIMED}
    calls = {label: [] for label, *_ in KERNELS_TIMED}
    originals = {}
    for label, name, func, _, _ in KERNELS_TIMED:
        current = getattr(modules[name], func)
        originals[label] = current

        def spy(*a, _current=current, _calls=calls[label], _copy=label in MOVES_ARGUMENTS, **k):
            _calls.append((_copied(a) if _copy else a, k))
            return _current(*a, **k)

        setattr(modules[name], func, spy)
    try:
        locate_frame(raw, calib)
    finally:
        for label, name, func, _, _ in KERNELS_TIMED:
            setattr(modules[name], func, originals[label])
    print(f"{args.preset}: {args.particles} particles (seed {args.seed}), {args.threads} "
          f"thread(s); the calls of one locate replayed, best of {args.repeat}, alternating")
    for label, name, func, part, rev in KERNELS_TIMED:
        if args.only and not any(word in label for word in args.only):
            continue
        rev = rev or KERNEL_BASELINE_REV
        now = originals[label]
        base = _without_new_keywords(getattr(_baseline_module(name, rev), func))
        replay = calls[label]
        part = part or (lambda out: out)
        fills = label == "decode gather"          # writes into its last argument
        buffers = [np.empty_like(a[-1]) for a, _ in replay] if fills else None

        def run(fn, i, a, k, keep=False):
            if fills:
                # the gather now decodes only the views of its mask (argument 5); a
                # baseline without that argument decodes all, compared on the same views
                use = a[5]
                if fn is base and len(a) > _n_params(base):
                    fn(*a[:5], *a[6:-1], buffers[i], **k)
                else:
                    fn(*a[:-1], buffers[i], **k)
                return np.where(use[:, :, None, None], buffers[i], 0.0) if keep else None
            return fn(*(_copied(a) if label in MOVES_ARGUMENTS else a), **k)

        ours = [part(run(now, i, a, k, True)) for i, (a, k) in enumerate(replay)]  # compiles
        try:
            theirs = [part(run(base, i, a, k, True)) for i, (a, k) in enumerate(replay)]
        except TypeError as err:       # the call has arguments the baseline lacks
            print(f"  {label:<24} skipped: the baseline ({rev[:7]}) cannot take today's "
                  f"call ({err})")
            continue
        outs = list(zip(ours, theirs))
        same = all(_same(x, y) for x, y in outs)
        diff = max(_close(x, y) for x, y in outs)
        t_now, t_base = [], []
        for _ in range(args.repeat):
            t_now.append(_best(lambda: [run(now, i, a, k) for i, (a, k) in enumerate(replay)],
                               1)[0])
            t_base.append(_best(lambda: [run(base, i, a, k) for i, (a, k) in enumerate(replay)],
                                1)[0])
        print(f"  {label:<24} {len(replay):4d} calls: now {min(t_now):.3f} s, baseline "
              f"({rev[:7]}) {min(t_base):.3f} s, speed-up {min(t_base) / min(t_now):.2f}x; "
              + ("identical outputs" if same else f"outputs differ by at most {diff:.2g}"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="hall2019")
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "plenoptrack-bench")
    ap.add_argument("--scaling", action="store_true",
                    help="time --counts particles against the previous steps")
    ap.add_argument("--counts", type=int, nargs="+", default=[100, 400, 1000])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--diameter", type=float, default=None,
                    help="particle diameter, mm (default: the preset's; 0.5 with --scaling)")
    ap.add_argument("--kernels", action="store_true",
                    help="time single kernels (KERNELS_TIMED) against their baseline revisions")
    ap.add_argument("--threads", type=int, default=1, help="numba threads for --kernels")
    ap.add_argument("--only", nargs="+", default=None, metavar="WORD",
                    help="with --kernels: time only the kernels whose label holds one of these")
    ap.add_argument("--prepare-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.prepare_only:
        _prepare(args.preset, args.particles, args.seed, args.workdir, args.diameter)
        return
    if args.kernels:
        bench_kernels(args)
        return
    if args.scaling:
        if args.diameter is None:
            args.diameter = 0.5
        scaling(args)
        return

    from plenoptrack.evaluate import evaluate_particles
    from plenoptrack.locate.perspective import PerspectiveLocator, locate_frame

    _prepare_apart(args.preset, args.particles, args.seed, args.workdir, args.diameter)
    calib, raw, truth = _prepare(args.preset, args.particles, args.seed, args.workdir,
                                 args.diameter)
    base_mb = _vm_hwm_mb()
    locator = PerspectiveLocator()
    locate_frame(raw, calib, locator=locator)  # warm-up (compiled kernels)

    t_total, result = _best(lambda: locate_frame(raw, calib, locator=locator), args.repeat)
    peak_mb = _vm_hwm_mb()
    st = result.stage_seconds
    t_solve = st["triangulate"] + st["checks"]
    t0 = time.perf_counter()
    base = locate_frame(raw, calib, locator=PerspectiveLocator.from_dict({"solve": {"solver": "scipy"}}))
    t_base = time.perf_counter() - t0
    b_solve = base.stage_seconds["triangulate"] + base.stage_seconds["checks"]

    ev = evaluate_particles(result.particles, truth, tolerance_mm=2.0)
    n_det = len(result.detections)
    print(f"{args.preset}: raw {raw.shape}, {args.particles} particles (seed {args.seed}), "
          f"{n_det} detections, {len(result.particles)} located (recall {ev.recall:.3f}, "
          f"precision {ev.precision:.3f}, z error {ev.mean_error_z:+.4f} +- "
          f"{ev.std_error_z:.4f} mm, lateral RMS {ev.rms_error_lateral:.4f} mm)")
    for name, key in (("decode", "decode"), ("segment", "segment"), ("cluster", "cluster"),
                      ("triangulate + addition", "triangulate"), ("checks", "checks"),
                      ("refine", "refine")):
        print(f"  {name:<23}{st[key]:7.3f} s")
    print(f"  {'total':<23}{t_total:7.3f} s")
    print(f"  peak memory (VmHWM)    {peak_mb:7.0f} MB (after loading inputs: {base_mb:.0f} MB)")
    print(f"  baseline (solver='scipy', same image, one run): triangulate + addition + checks "
          f"{b_solve:.3f} s vs {t_solve:.3f} s, ratio {b_solve / t_solve:.1f}x; whole call "
          f"{t_base:.3f} s vs {t_total:.3f} s, ratio {t_base / t_total:.1f}x")
    other = not locator.check.refine_images
    flipped = PerspectiveLocator.from_dict({"check": {"refine_images": other}})
    t_flip, flip = _best(lambda: locate_frame(raw, calib, locator=flipped), args.repeat)
    ev_flip = evaluate_particles(flip.particles, truth, tolerance_mm=2.0)
    print(f"  refinement {'on' if other else 'off'} (check.refine_images = "
          f"{str(other).lower()}, same image, best of {args.repeat}): {t_flip:.3f} s, "
          f"the default {t_total / t_flip:.2f}x that; recall {ev_flip.recall:.3f}, z error "
          f"{ev_flip.mean_error_z:+.4f} +- {ev_flip.std_error_z:.4f} mm, lateral RMS "
          f"{ev_flip.rms_error_lateral:.4f} mm")
    # the decode's sampling geometry and lens centres computed afresh on every call, as
    # before they were cached per grid (the pixel-locking correction asks for them too);
    # alternating with the default call, medians (single calls of either vary by up to a
    # few tenths of a second, most of it in the decode stage)
    previous = _load_previous()
    runs = {"cached": [], "afresh": []}
    for _ in range(args.repeat):
        for key in runs:
            with (_previous_steps(previous, only=("plenoptrack.lightfield.decode",))
                  if key == "afresh" else contextlib.nullcontext()):
                t0 = time.perf_counter()
                out = locate_frame(raw, calib, locator=locator)
                runs[key].append((time.perf_counter() - t0, out.stage_seconds["decode"]
                                  + out.stage_seconds["checks"]))
            if key == "afresh" and not out.particles.equals(result.particles):
                raise SystemExit("the sampling geometry computed afresh gives other particles")
    med = {key: np.median(np.array(v), axis=0) for key, v in runs.items()}
    print(f"  sampling geometry cached per grid / computed afresh on every call (medians of "
          f"{args.repeat} alternating calls, same particles): {med['cached'][0]:.3f} / "
          f"{med['afresh'][0]:.3f} s, ratio {med['afresh'][0] / med['cached'][0]:.2f}x; "
          f"decode + checks stages {med['cached'][1]:.3f} / {med['afresh'][1]:.3f} s")

if __name__ == "__main__":
    main()
