"""Time the simulator: full-sensor background and 100-particle frame, and a small frame.

Each culled render is compared with a brute-force render of the same frame (every
sample of every pixel tested against every particle, no bounding boxes or shortcuts)
measured in the same run. For the full sensor the brute force is timed on a central
window holding 1/100 of the pixels and scaled by 100.

A last section times a full-sensor frame with the image-domain realism effects
(back-light, dust, microlens blur and crosstalk, sensor fixed patterns), with the lens
group, and with both, against the ideal frame and against the code of
:data:`FRAME_BASELINE_REV` in the same run, caches warm (``--realism`` runs only that
section). Peak memory of each mode: run
``python benchmarks/bench_simulate.py --memory ideal`` (or ``realistic``), which renders a
white image and three frames and prints the peak resident set size.

``--dataset [N]`` times what one calibration data set costs (``calibration_seeds.py``:
a white image and N = 11 dot cards of ``hall2019``, ideal optics): the kernels of
:data:`BASELINE_REV` (read with ``git show`` and imported beside the current ones) against
the current dot-card path (cards re-trace only the pixels whose rays may land on a dot, over
the cached background) in the same run, alternating, and requires identical images; then
one card's exposure and TIFF write and read with and without zlib. Wall-clock and
process CPU time (all threads) are both printed: on a shared machine the CPU time is the
steadier of the two.

``--tiff`` times writing a full-sensor image as TIFF with zlib at the level
:func:`~plenoptrack.io.write_tiff` uses, against tifffile's default level and no
compression, in the same run.

``--pins`` times the irradiance of the translation-stage study's pin field (stems of
aspect 13) culled with chains of small balls along each stem against its bounding sphere,
in the same run.

Run: ``python benchmarks/bench_simulate.py``.
"""

from __future__ import annotations

import importlib.util
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

from plenoptrack import preset
from plenoptrack.simulate import (default_volume, make_optics, random_particles,
                                  render_frame, render_irradiance)
from plenoptrack.simulate import _kernels
from plenoptrack.simulate.render import (_particle_table, background_irradiance,
                                         sample_pattern)
from plenoptrack.simulate.sensor import SensorModel, expose


def _timed(fn, *args, **kwargs):
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t


def _brute_window(optics, particles, frac_side):
    rows, cols = optics.camera.sensor_shape_px
    h, w = int(rows * frac_side), int(cols * frac_side)
    r0, c0 = (rows - h) // 2, (cols - w) // 2
    occ = _particle_table(optics, particles)
    _, dt = _timed(_kernels.render_all, _kernels.pack_params(optics), sample_pattern(optics, 16),
                   occ, np.zeros(3), r0, r0 + h, c0, c0 + w, True)
    return dt * (rows * cols) / (h * w)


def bench(name, n_particles, brute_side):
    camera = preset(name)
    optics = make_optics(camera, seed=0)
    particles = random_particles(n_particles, volume=default_volume(camera), diameter_mm=1.0,
                                 seed=1)
    _, t_bg = _timed(background_irradiance, optics)
    render_irradiance(optics, particles.iloc[:1])           # warm caches
    irr, t_irr = _timed(render_irradiance, optics, particles)
    _, t_exp = _timed(expose, irr, level=0.7, bit_depth=camera.bit_depth, sensor=SensorModel(),
                      rng=np.random.default_rng(0))
    _, t_frame = _timed(render_frame, optics, particles, seed=0)
    t_brute = _brute_window(optics, particles, brute_side)
    rows, cols = camera.sensor_shape_px
    print(f"{name} ({rows} x {cols} px, {n_particles} particles of 1 mm, "
          f"{numba.get_num_threads()} threads)")
    print(f"  background (cached once per optics) : {t_bg:7.2f} s")
    print(f"  frame irradiance, culled            : {t_irr:7.2f} s")
    print(f"  exposure and noise                  : {t_exp:7.2f} s")
    print(f"  render_frame total                  : {t_frame:7.2f} s")
    how = ("measured" if brute_side == 1
           else f"timed on a central 1/{round(1 / brute_side ** 2)} window, scaled")
    print(f"  brute-force irradiance ({how}): {t_brute:7.2f} s")
    print(f"  speed-up of culling vs brute force  : {t_brute / t_irr:7.1f} x")


FRAME_BASELINE_REV = "19952299fa8daf5d4ead718af16e9620dc732a39"
"""Revision whose kernels, back-light code and FFT blur are the baseline of ``--realism``
(before the shadow discs of ``render_lenses``, the direct blur and the fused back-light)."""


def _baseline_module(rev, relpath, name):
    """Module ``relpath`` (under ``src/plenoptrack/simulate``) of revision ``rev``, imported
    from a temporary folder as a sibling of the current package (its relative imports
    resolve to the current modules)."""
    root = Path(__file__).resolve().parents[1]
    src = subprocess.run(["git", "show", f"{rev}:src/plenoptrack/simulate/{relpath}"],
                         cwd=root, capture_output=True, text=True, check=True).stdout
    folder = Path(tempfile.mkdtemp(prefix="bench_base_"))
    path = folder / f"{name}.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location(f"plenoptrack.simulate.{name}", path)
    module = importlib.util.module_from_spec(spec)
    module.__package__ = "plenoptrack.simulate"
    spec.loader.exec_module(module)
    return module


def _baseline_frame(base, optics, particles, seed):
    """:func:`render_frame` as at :data:`FRAME_BASELINE_REV`: the baseline kernels' trace,
    copy then back-light in place, FFT blur, the same exposure."""
    from plenoptrack.simulate.illumination import image_rng
    from plenoptrack.simulate.psf import (_optics_transfer, apply_transfer, crosstalk_shifts,
                                          psf_kernel)
    from plenoptrack.simulate.render import _NO_CARD, _particle_arrays, particle_lenses
    from plenoptrack.simulate.sensor import fixed_pattern

    kernels, illumination = base
    occ, shapes = _particle_arrays(optics, particles)
    irr = background_irradiance(optics, 16).copy()
    lenses, ptr, idx = particle_lenses(optics, occ)
    kernels.render_lenses(irr, lenses, ptr, idx, kernels.pack_params(optics),
                          sample_pattern(optics, 16), occ, _NO_CARD, shapes=shapes)
    real, sensor, cam = optics.realism, SensorModel(), optics.camera
    rng = np.random.default_rng(seed)
    if real.illumination.enabled:
        irr = np.array(irr, dtype=np.float32, copy=True)
        illumination.illuminate(irr, optics, image_rng(rng))
    if real.blur.enabled:
        k = psf_kernel(real.blur, f_number=cam.microlens_f_number,
                       pixel_pitch_um=cam.pixel_pitch_um)
        irr = apply_transfer(irr, k, crosstalk_shifts(optics), real.blur.crosstalk,
                             transfer=_optics_transfer(optics))
    return expose(irr, level=sensor.background_level, bit_depth=cam.bit_depth, sensor=sensor,
                  rng=rng, fixed=fixed_pattern(optics) if real.sensor.enabled else None)


def bench_realism(name, n_particles, repeats=3):
    """Frame time, ideal vs realistic effects (spec and target off: same first-order optics).

    ``lens`` adds the lens group (drawn distortion, Seidel terms, cat's-eye vignetting, axis
    offset, MLA tilt) to the geometry, so its background is traced anew; the last row has
    every image and lens effect. Each mode is timed now and with the code of
    :data:`FRAME_BASELINE_REV` (:func:`_baseline_frame`), alternating, in the same run; the
    traced irradiance must be identical, and so must the raw frame where the blur is off
    (with it on the direct blur differs from the FFT by float32 rounding, which moves some
    dark pixels' Poisson draws and so the later draws: the largest difference in counts
    is printed). ``os.getloadavg`` is printed before and after.
    """
    from dataclasses import replace

    from plenoptrack.simulate.realism import Realism

    base = (_baseline_module(FRAME_BASELINE_REV, "_kernels.py", "_kernels_frame_base"),
            _baseline_module(FRAME_BASELINE_REV, "illumination.py", "_illumination_base"))
    camera = preset(name)
    off = Realism.ideal()
    image = replace(Realism.realistic(), spec=off.spec, target=off.target, lens=off.lens)
    lens = replace(off, lens=Realism.realistic().lens)
    full = replace(Realism.realistic(), spec=off.spec, target=off.target)
    particles = random_particles(n_particles, volume=default_volume(camera), diameter_mm=1.0,
                                 seed=1)
    times, old, backgrounds, diffs = {}, {}, {}, {}
    modes = (("ideal", "ideal"), ("image", image), ("lens", lens), ("realistic", full))
    load0 = os.getloadavg()
    for mode, realism in modes:
        optics = make_optics(camera, seed=0, realism=realism)
        backgrounds[mode] = _timed(background_irradiance, optics)[1]
        a = render_frame(optics, particles, seed=0)         # caches: background, maps
        b = _baseline_frame(base, optics, particles, 0)
        diffs[mode] = int(np.abs(a.astype(np.int32) - b).max())
        if not optics.realism.blur.enabled and diffs[mode]:
            raise AssertionError(f"{mode}: the frame differs from the baseline's")
        t_new, t_old = [], []
        for s in range(1, repeats + 1):
            t_new.append(_clocked(render_frame, optics, particles, seed=s)[1:])
            t_old.append(_clocked(_baseline_frame, base, optics, particles, s)[1:])
        times[mode], old[mode] = np.min(t_new, axis=0), np.min(t_old, axis=0)
    print(f"{name}: render_frame with {n_particles} particles, best of {repeats}, now and "
          f"at {FRAME_BASELINE_REV[:7]} alternating (background traced once per optics); "
          f"wall s / process CPU s (all threads)")
    labels = {"ideal": "ideal", "image": "blur, illumination, sensor",
              "lens": "lens group only", "realistic": "all of them"}
    for mode, _ in modes:
        (w, c), (wo, co) = times[mode], old[mode]
        print(f"  {labels[mode]:26s}: now {w:5.2f} / {c:5.2f} ({w / times['ideal'][0]:.2f} x "
              f"ideal), baseline {wo:5.2f} / {co:5.2f}, speed-up {wo / w:.2f} x wall, "
              f"{co / c:.2f} x CPU; background {backgrounds[mode]:5.2f} s; largest count "
              f"difference {diffs[mode]}")
    print(f"  load average (1, 5, 15 min) before {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}, "
          "after {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))


BASELINE_REV = "035107c4e8abbd31e49957593e72d3fc95aab4f1"
"""Revision whose ``simulate/_kernels.py`` is the baseline of ``--dataset`` (before the
straddling-pixel shortcuts and the dot cards over the background)."""


def _baseline_kernels(rev=BASELINE_REV):
    """The kernels module of revision ``rev``, imported from a temporary folder."""
    root = Path(__file__).resolve().parents[1]
    src = subprocess.run(["git", "show", f"{rev}:src/plenoptrack/simulate/_kernels.py"],
                         cwd=root, capture_output=True, text=True, check=True).stdout
    folder = Path(tempfile.mkdtemp(prefix="bench_kernels_"))
    path = folder / "_kernels_baseline.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("_kernels_baseline", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _clocked(fn, *args, **kwargs):
    """``(result, wall s, process CPU s)``."""
    w, c = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - w, time.process_time() - c


def bench_dataset(name="hall2019", seed=16, n_cards=11):
    """White image and dot cards of one calibration data set: baseline kernels vs now."""
    from plenoptrack.io import write_tiff
    from plenoptrack.simulate import expose_image
    from plenoptrack.simulate.dotcard import (_card_vector, default_dotcard,
                                              default_dotcard_depths, dotcard_irradiance)

    base = _baseline_kernels()
    camera = preset(name)
    small = make_optics(preset("small"), seed=0, realism="ideal")   # compile both
    sp = _kernels.pack_params(small)
    base.render_all(sp, sample_pattern(small, 16), np.zeros((0, 4)),
                    _card_vector(small, 1.0, default_dotcard(small.camera)), 0, 600, 0, 910, False)
    dotcard_irradiance(small, 1.0)
    optics = make_optics(camera, seed=seed, realism="ideal")
    par = _kernels.pack_params(optics)
    samples = sample_pattern(optics, 16)
    rows, cols = camera.sensor_shape_px
    none = np.zeros((0, 4))
    old, new = np.zeros(2), np.zeros(2)
    b, *t_old = _clocked(base.render_all, par, samples, none, np.zeros(3), 0, rows, 0, cols,
                         False)
    background_irradiance.cache_clear()
    a, *t_new = _clocked(background_irradiance, optics, 16)     # the cards' cache key
    if not np.array_equal(a, b):
        raise AssertionError("white image differs from the baseline")
    print(f"{name} seed {seed}, ideal optics, {numba.get_num_threads()} threads; "
          "wall s / CPU s (all threads)")
    print(f"  white image irradiance  : baseline {t_old[0]:6.2f} / {t_old[1]:6.2f}   "
          f"now {t_new[0]:6.2f} / {t_new[1]:6.2f}   ({t_old[1] / t_new[1]:.2f} x CPU)")
    old += t_old
    new += t_new
    depths = default_dotcard_depths(camera)[:n_cards]
    card = default_dotcard(camera)
    for k, z in enumerate(depths):
        vec = _card_vector(optics, float(z), card)
        runs = [lambda: _clocked(base.render_all, par, samples, none, vec, 0, rows, 0, cols, False),
                lambda: _clocked(dotcard_irradiance, optics, float(z))]
        if k % 2:
            (a, *t_new), (b, *t_old) = runs[1](), runs[0]()
        else:
            (b, *t_old), (a, *t_new) = runs[0](), runs[1]()
        if not np.array_equal(a, b):
            raise AssertionError(f"dot card at {z} mm differs from the baseline")
        print(f"  dot card {z:+6.1f} mm      : baseline {t_old[0]:6.2f} / {t_old[1]:6.2f}   "
              f"now {t_new[0]:6.2f} / {t_new[1]:6.2f}   ({t_old[1] / t_new[1]:.2f} x CPU)",
              flush=True)
        old += t_old
        new += t_new
    print(f"  white + {len(depths)} cards, identical : baseline {old[0]:6.1f} / {old[1]:6.1f}   "
          f"now {new[0]:6.1f} / {new[1]:6.1f}   speed-up {old[0] / new[0]:.2f} x wall, "
          f"{old[1] / new[1]:.2f} x CPU")
    image, *t_exp = _clocked(expose_image, a, optics, level=0.7, sensor=SensorModel(), seed=1)
    print(f"  exposure of one card    : {t_exp[0]:6.2f} / {t_exp[1]:6.2f}")
    import tifffile

    with tempfile.TemporaryDirectory() as tmp:
        for comp in ("zlib", None):
            path = Path(tmp) / f"card_{comp}.tif"
            _, *t_w = _clocked(write_tiff, path, image, compression=comp)
            back, *t_r = _clocked(tifffile.imread, path)
            assert np.array_equal(back, image)
            print(f"  TIFF {str(comp):4s} write / read  : {t_w[0]:6.2f} / {t_w[1]:6.2f} s, "
                  f"{t_r[0]:6.2f} / {t_r[1]:6.2f} s, {path.stat().st_size / 1e6:5.1f} MB")


def peak_memory(mode, name="hall2019"):
    camera = preset(name)
    optics = make_optics(camera, seed=0, realism=mode)
    particles = random_particles(100, volume=default_volume(camera), diameter_mm=1.0, seed=1)
    from plenoptrack.simulate import render_white
    render_white(optics, seed=0)
    for s in range(3):
        render_frame(optics, particles, seed=s + 1)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{name} {mode}: white + 3 frames, peak RSS {rss:.0f} MB")


def bench_pins(positions=(0, 25, 50), threads=1):
    """Irradiance of the translation-stage study's pin field (40 heads, 40 stems of aspect
    13, ``hall2019``, realistic optics) culled with the stems' chains of culling balls
    against culled with their bounding spheres (``balls=None``, as before the chains), in
    the same run, alternating, identical images required; ``threads`` numba threads (the
    study's workers use one)."""
    from plenoptrack.simulate import with_particle_effects
    from plenoptrack.simulate.render import _NO_CARD, _particle_geometry, particle_lenses
    from plenoptrack.study import StudyConfig, _frame_particles, study_field, traverse_positions

    numba.set_num_threads(threads)
    cfg = StudyConfig(camera=preset("hall2019"))
    optics = make_optics(cfg.camera, cfg.seed, realism=cfg.realism)
    field, _ = study_field(cfg)
    field = with_particle_effects(field.assign(frame=0), optics.realism.particles,
                                  seed=np.random.default_rng([cfg.seed, 6]),
                                  velocity=None).drop(columns=["frame"])
    par, samples = _kernels.pack_params(optics), sample_pattern(optics, 16)
    background = background_irradiance(optics, 16)

    def render(parts, chains):
        occ, shapes, balls = _particle_geometry(optics, parts)
        bounds = balls if chains else occ
        out = background.copy()
        lenses, ptr, idx = particle_lenses(optics, bounds[:, :4])
        _kernels.render_lenses(out, lenses, ptr, idx, par, samples, occ, _NO_CARD,
                               shapes=shapes, balls=balls if chains else None)
        return out, len(lenses)

    render(_frame_particles(field, 0.0, 0), True)          # compiles
    pos = traverse_positions(cfg.travel_mm, cfg.step_mm)
    print(f"study pin field, hall2019 realistic, {threads} numba thread(s)")
    print(f"{'position mm':>11s} {'spheres s':>10s} {'chains s':>9s} {'lenses':>15s} {'speed-up':>9s}")
    for i in positions:
        parts = _frame_particles(field, float(pos[i]), 0)
        (a, la), ta = _timed(render, parts, False)
        (b, lb), tb = _timed(render, parts, True)
        if not np.array_equal(a, b):
            raise SystemExit(f"position {pos[i]}: chained culling changed the image")
        print(f"{pos[i]:11.1f} {ta:10.2f} {tb:9.2f} {la:7d}/{lb:7d} {ta / tb:8.2f}x")


def bench_tiff(name="hall2019", depth_mm=0.0, repeats=3):
    """Writing one full-sensor dot-card image (realistic optics, with noise) as TIFF: zlib
    at :data:`~plenoptrack.io.ZLIB_LEVEL` (``write_tiff``) against zlib at tifffile's
    default level and uncompressed, alternating, best of ``repeats``; file sizes and a
    read back of each."""
    import tifffile

    from plenoptrack.io import ZLIB_LEVEL, write_tiff
    from plenoptrack.simulate import expose_image
    from plenoptrack.simulate.dotcard import dotcard_irradiance

    optics = make_optics(preset(name), seed=0, realism="realistic")
    image = expose_image(dotcard_irradiance(optics, depth_mm), optics, level=0.7,
                         sensor=SensorModel(), seed=1)
    ways = {f"zlib level {ZLIB_LEVEL} (write_tiff)":
            lambda path: write_tiff(path, image),
            "zlib default level (tifffile)":
            lambda path: tifffile.imwrite(path, image, compression="zlib",
                                          photometric="minisblack"),
            "none": lambda path: write_tiff(path, image, compression=None)}
    best = dict.fromkeys(ways, np.inf)
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            for k, (way, write) in enumerate(ways.items()):
                path = Path(tmp) / f"{k}.tif"
                _, t = _timed(write, path)
                best[way] = min(best[way], t)
        print(f"{name} {image.shape[1]} x {image.shape[0]} px dot card, realistic optics; "
              f"write, best of {repeats}")
        base = best["zlib default level (tifffile)"]
        for k, way in enumerate(ways):
            path = Path(tmp) / f"{k}.tif"
            back, t_read = _timed(tifffile.imread, path)
            if not np.array_equal(back, image):
                raise AssertionError(f"{way}: pixels differ on reading back")
            print(f"  {way:32s} write {best[way]:6.2f} s ({base / best[way]:5.2f} x the "
                  f"default level)  read {t_read:5.2f} s  {path.stat().st_size / 1e6:6.1f} MB")


def main():
    if len(sys.argv) == 2 and sys.argv[1] == "--tiff":
        bench_tiff()
        return
    if len(sys.argv) == 2 and sys.argv[1] == "--pins":
        bench_pins()
        return
    if len(sys.argv) == 3 and sys.argv[1] == "--memory":
        peak_memory(sys.argv[2])
        return
    if len(sys.argv) in (2, 3) and sys.argv[1] == "--dataset":
        bench_dataset(n_cards=int(sys.argv[2]) if len(sys.argv) == 3 else 11)
        return
    if len(sys.argv) == 2 and sys.argv[1] == "--realism":
        bench_realism("small", 5, repeats=1)                # compiles the kernels
        bench_realism("hall2019", 100)
        return
    bench("small", 20, 1.0)            # compiles the kernels on a first run
    print()
    bench("hall2019", 100, 0.1)
    print()
    bench_realism("hall2019", 100)


if __name__ == "__main__":
    main()
