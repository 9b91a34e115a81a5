"""The end-to-end demonstration behind ``plenoptrack demo``.

Simulates a small back-lit particle scene with the ``small`` camera, calibrates the
lenslet grid and the DLFC from the simulated white image and dot cards, locates the
particles of the raw frame with the perspective-shift method and compares them with the
ground truth. Everything is written to one folder so each step can be inspected or
re-run from the shell.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

__all__ = ["DemoSummary", "run_demo"]

DEMO_CARDS = 7
"""Dot cards the demo simulates and calibrates from (evenly spanning the volume)."""


@dataclass
class DemoSummary:
    """What the demo did.

    Attributes
    ----------
    rows : list of (str, str, float)
        One row per step: name, result in words, seconds.
    particles : DataFrame
        Located particles (mm).
    truth : DataFrame
        True particles (mm).
    evaluation : Evaluation
        Recall, precision and position errors.
    """

    rows: list[tuple[str, str, float]] = field(default_factory=list)
    particles: pd.DataFrame | None = None
    truth: pd.DataFrame | None = None
    evaluation: object = None


def run_demo(out_dir: str | Path, *, seed: int = 0, n_particles: int = 20,
             diameter_mm: float | None = None, progress: bool = False) -> DemoSummary:
    """Simulate, calibrate, locate and evaluate a small scene.

    Parameters
    ----------
    out_dir : str or Path
        Folder for the simulated data, the calibration file and the particle table.
    seed : int
        Seed of the simulated optics, scene and noise.
    n_particles : int
        Particles in the scene.
    diameter_mm : float, optional
        Particle diameter, mm; default the simulator's default for the ``small`` camera.
    progress : bool
        Show progress bars.

    Returns
    -------
    DemoSummary
    """
    from ._precompile import finish_background, start_background
    from .calibrate import calibrate
    from .calibration import record_white, save_calibration
    from .camera import preset
    from .evaluate import evaluate_particles
    from .io import read_raw, write_table
    from .locate.perspective import locate_frame
    from .simulate import simulate_dataset
    from .simulate.dotcard import default_dotcard_depths

    out_dir = Path(out_dir)
    summary = DemoSummary()
    camera = preset("small")

    # On a first run, the kernels of calibrating and locating are compiled by a second
    # process while this one simulates (see plenoptrack._precompile).
    steps = ("calibrate", "locate")
    child = start_background(steps)
    t0 = time.perf_counter()
    kwargs = {} if diameter_mm is None else {"diameter_mm": diameter_mm}
    try:
        # Seven cards span the volume as well as the eleven of a full data set for a
        # fourth-order DLFC, and uncompressed TIFFs skip the zlib encoding: the demo
        # stays short without changing what it shows.
        sim = simulate_dataset(camera, out_dir / "sim", seed=seed, n_particles=n_particles,
                               dotcard_depths=default_dotcard_depths(camera, DEMO_CARDS),
                               compression=None, progress=progress, **kwargs)
    except BaseException:
        if child is not None:
            child.kill()
            child.wait()
        raise
    summary.rows.append(("simulate", f"{len(sim.truth)} particles, {len(sim.dotcard_paths)} dot cards",
                         time.perf_counter() - t0))

    t0 = time.perf_counter()
    finish_background(child, steps)
    calib, report = calibrate(sim.white_path, sim.dotcards_path.parent, sim.camera, progress=progress)
    calib = record_white(calib, sim.white_path, calibration_path=out_dir / "calib.json")
    save_calibration(calib, out_dir / "calib.json")
    summary.rows.append(("calibrate", f"grid {calib.grid.shape[0]} x {calib.grid.shape[1]}, "
                         f"DLFC order {calib.dlfc.order}, residual {calib.dlfc.report.rms_px:.3f} px",
                         time.perf_counter() - t0))

    t0 = time.perf_counter()
    raw = read_raw(sim.frame_paths[0])
    result = locate_frame(raw, calib, frame=0, white=read_raw(sim.white_path))
    write_table(result.particles, out_dir / "particles.parquet")
    summary.rows.append(("locate", f"{len(result.particles)} particles from "
                         f"{len(result.detections)} centroids", time.perf_counter() - t0))

    t0 = time.perf_counter()
    ev = evaluate_particles(result.particles, sim.truth, tolerance_mm=1.0)
    summary.rows.append(("evaluate", f"recall {ev.recall:.3f}, precision {ev.precision:.3f}",
                         time.perf_counter() - t0))
    summary.rows.append(("  depth error", f"mean {ev.mean_error_z:+.3f} mm, sd {ev.std_error_z:.3f} mm", 0.0))
    summary.rows.append(("  lateral error", f"RMS {ev.rms_error_lateral:.4f} mm", 0.0))
    summary.particles = result.particles
    summary.truth = sim.truth
    summary.evaluation = ev
    return summary
