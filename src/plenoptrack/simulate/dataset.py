"""Write a complete simulated data set: the folder a real experiment would produce.

Folder layout (the simulator part of the file contract in ``DESIGN.md``)::

    out_dir/
      raw/frame_0000.tif ...     one uint16 TIFF per frame
      white.tif                  white (flat-field) image, no particles
      dotcards/card_00.tif ...   one dot-card image per depth
      dotcards/dotcards.toml     spacing_mm, dot_diameter_mm, [[cards]] file + z_mm
      camera.toml                nominal camera description (what a user would write)
      truth.parquet              frame, particle, x, y, z, diameter (world frame, mm)
      truth_optics.json          true lenslet grid, MLA perturbation and distortion

``truth.parquet`` and ``truth_optics.json`` are ground truth for tests and evaluation;
nothing on the locating path reads them.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .._columns import T_COLUMN
from ..camera import CameraSpec, preset, save_camera
from ..io import atomic_write_text, write_table, write_tiff
from .dotcard import DotCard, default_dotcard, default_dotcard_depths, render_dotcard
from .optics import SimOptics, make_optics
from .render import DEFAULT_SAMPLES_PER_PIXEL, render_frame, render_white
from .scene import Scene, SceneError, make_scene
from .sensor import SensorModel

__all__ = ["SimulationResult", "simulate_dataset"]


@dataclass(frozen=True)
class SimulationResult:
    """What :func:`simulate_dataset` wrote.

    Attributes
    ----------
    out_dir : Path
        Output folder.
    camera : CameraSpec
        Nominal camera written to ``camera.toml``.
    optics : SimOptics
        True optics used for rendering.
    truth : DataFrame
        ``frame, particle, x, y, z, diameter`` (mm), as in ``truth.parquet``.
    frame_paths : tuple of Path
        Raw frames, in frame order.
    white_path, camera_path, truth_path, optics_path, dotcards_path : Path
        The other files; ``dotcards_path`` is ``dotcards/dotcards.toml``.
    dotcard_paths : tuple of Path
        Dot-card images, in the order of ``dotcard_depths_mm``.
    dotcard_depths_mm : tuple of float
        Card depths, mm.
    dotcard : DotCard
        Dot layout of every card.
    """

    out_dir: Path
    camera: CameraSpec
    optics: SimOptics
    truth: pd.DataFrame = field(repr=False)
    frame_paths: tuple[Path, ...]
    white_path: Path
    dotcard_paths: tuple[Path, ...]
    dotcard_depths_mm: tuple[float, ...]
    dotcard: DotCard
    camera_path: Path
    truth_path: Path
    optics_path: Path
    dotcards_path: Path


def _progress(enabled: bool):
    if not enabled:
        return contextlib.nullcontext(None)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(),
                    TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn())


def simulate_dataset(camera: CameraSpec | str, out_dir: str | Path, *, seed: int = 0,
                     n_particles: int = 20, diameter_mm: float | None = None,
                     magnification: float | None = None, frames: int = 1,
                     velocity_mm_per_frame=(0.0, 0.0, 0.0), scene: Scene | None = None,
                     samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                     dotcard_depths=None, dotcard: DotCard | None = None,
                     sensor: SensorModel = SensorModel(),
                     progress: bool = False) -> SimulationResult:
    """Simulate raw frames, a white image and dot cards, with ground truth, into a folder.

    Parameters
    ----------
    camera : CameraSpec or str
        Nominal camera or preset name (``hall2019``, ``small``, ``small-rect``).
    out_dir : str or Path
        Output folder (created; existing files of the layout are replaced).
    seed : int
        Master seed: the optics are ``make_optics(camera, seed)``; particle positions and
        every noise draw use generators seeded from ``[seed, purpose, index]``.
    n_particles, diameter_mm : int, float
        Random scene (ignored when ``scene`` is given): particles and their diameter, mm
        (default per camera preset, :func:`~plenoptrack.simulate.scene.default_diameter_mm`:
        0.4 mm on the small presets, 1 mm otherwise).
    magnification : float, optional
        Replaces the camera's magnification (also in ``camera.toml``).
    frames : int
        Number of frames of the random scene.
    velocity_mm_per_frame : (3,) array-like
        Constant displacement per frame of the random scene, mm.
    scene : Scene, optional
        Explicit scene (e.g. from :func:`load_scene`); its camera must equal ``camera``
        after the magnification override.
    samples_per_pixel : int
        Rays per pixel.
    dotcard_depths : sequence of float, optional
        Dot-card depths, mm; default :func:`default_dotcard_depths` (11 planes spanning
        the volume depth); an empty sequence writes no cards.
    dotcard : DotCard, optional
        Dot layout; default :func:`default_dotcard`.
    sensor : SensorModel
        Exposure and noise.
    progress : bool
        Show progress bars.

    Returns
    -------
    SimulationResult
    """
    camera = preset(camera) if isinstance(camera, str) else camera
    if not isinstance(camera, CameraSpec):
        raise TypeError(f"camera must be a CameraSpec or a preset name; got {type(camera).__name__}")
    if magnification is not None:
        camera = camera.with_changes(magnification=float(magnification))
    if scene is None:
        scene = make_scene(camera, n_particles=n_particles, diameter_mm=diameter_mm,
                           frames=frames, velocity_mm_per_frame=velocity_mm_per_frame, seed=seed)
    elif scene.camera != camera:
        raise SceneError(f"the scene was made for camera {scene.camera.name!r} "
                         f"(magnification {scene.camera.magnification}); pass scene.camera")
    depths = default_dotcard_depths(camera) if dotcard_depths is None else np.asarray(
        dotcard_depths, dtype=float).reshape(-1)
    card = default_dotcard(camera) if dotcard is None else dotcard
    out = Path(out_dir)
    optics = make_optics(camera, seed)
    truth = scene.truth.reset_index(drop=True)
    n_frames = scene.frames

    with _progress(progress) as bar:
        task = bar.add_task("simulating", total=2 + n_frames + len(depths)) if bar else None

        def step(description: str) -> None:
            if bar is not None:
                bar.update(task, advance=1, description=description)

        camera_path = save_camera(camera, out / "camera.toml")
        optics_doc = optics.to_dict() | {"samples_per_pixel": samples_per_pixel,
                                         "sensor": asdict(sensor)}
        optics_path = atomic_write_text(out / "truth_optics.json", json.dumps(optics_doc, indent=2))
        truth_path = write_table(truth, out / "truth.parquet")
        white_path = write_tiff(out / "white.tif", render_white(
            optics, seed=np.random.default_rng([seed, 2]), samples_per_pixel=samples_per_pixel,
            sensor=sensor))
        step("white image")
        frame_paths = []
        for f in range(n_frames):
            particles = truth[truth[T_COLUMN] == f]
            image = render_frame(optics, particles, seed=np.random.default_rng([seed, 3, f]),
                                 samples_per_pixel=samples_per_pixel, sensor=sensor)
            frame_paths.append(write_tiff(out / "raw" / f"frame_{f:04d}.tif", image))
            step(f"frame {f + 1}/{n_frames}")
        card_paths = []
        for k, z in enumerate(depths):
            image = render_dotcard(optics, float(z), card=card,
                                   seed=np.random.default_rng([seed, 4, k]),
                                   samples_per_pixel=samples_per_pixel, sensor=sensor)
            card_paths.append(write_tiff(out / "dotcards" / f"card_{k:02d}.tif", image))
            step(f"dot card {k + 1}/{len(depths)}")
        import tomli_w

        cards_doc = {"spacing_mm": card.spacing_mm, "dot_diameter_mm": card.dot_diameter_mm,
                     "cards": [{"file": p.name, "z_mm": float(z)} for p, z in zip(card_paths, depths)]}
        dotcards_path = atomic_write_text(
            out / "dotcards" / "dotcards.toml",
            "# dot grid: dot (m, n) at world (x, y) = (m, n) * spacing_mm; dot (0, 0) on the axis\n"
            + tomli_w.dumps(cards_doc))
        _remove_stale(out / "raw", "frame_*.tif", frame_paths)
        _remove_stale(out / "dotcards", "card_*.tif", card_paths)
        step("done")
    return SimulationResult(out_dir=out, camera=camera, optics=optics, truth=truth,
                            frame_paths=tuple(frame_paths), white_path=white_path,
                            dotcard_paths=tuple(card_paths),
                            dotcard_depths_mm=tuple(float(z) for z in depths), dotcard=card,
                            camera_path=camera_path, truth_path=truth_path,
                            optics_path=optics_path, dotcards_path=dotcards_path)


def _remove_stale(folder: Path, pattern: str, written) -> None:
    """Delete files of this layout left in ``folder`` by an earlier, larger simulation,
    so that the folder matches ``truth.parquet`` and ``dotcards.toml``."""
    keep = {Path(p).name for p in written}
    for path in folder.glob(pattern):
        if path.name not in keep:
            path.unlink()
