"""Write a complete simulated data set: the folder a real experiment would produce.

Folder layout (the simulator part of the file contract in ``DESIGN.md``)::

    out_dir/
      raw/frame_0000.tif ...     one uint16 TIFF per frame
      white.tif                  white (flat-field) image, no particles
      dotcards/card_00.tif ...   one dot-card image per depth
      dotcards/dotcards.toml     spacing_mm, dot_diameter_mm, [[cards]] file + z_mm
      camera.toml                nominal camera description (what a user would write)
      truth.parquet              frame, particle, x, y, z, diameter (world frame, mm),
                                 projected_area (mm^2), orientation (rad); ellipsoid
                                 scenes add shape, aspect, axis_x, axis_y, axis_z,
                                 fragment scenes also shape_seed; the particle effects
                                 add transmission and velocity_x, velocity_y,
                                 velocity_z (mm per frame)
      truth_optics.json          true lenslet grid, MLA perturbation and distortion
      scene.toml                 built-in scenes only: the scene's parameters (name, frame
                                 interval, ...); ``--scene scene.toml`` repeats the run

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
from ..errors import SettingsError
from ..io import atomic_folder, atomic_write_text, write_table, write_tiff
from .dotcard import (DotCard, default_dotcard, default_dotcard_depths,
                      draw_card_placements, origin_dot_mm, render_dotcard,
                      sensor_centre_aim_mm)
from .optics import SimOptics, make_optics
from .realism import Realism
from .render import DEFAULT_SAMPLES_PER_PIXEL, render_frame, render_white
from .scene import Scene, SceneError, make_scene, with_particle_effects
from .sensor import SensorModel

__all__ = ["SimulationResult", "simulate_dataset", "foreign_files", "DATASET_LAYOUT"]


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


DATASET_LAYOUT = {
    ".": ("raw", "white.tif", "dotcards", "camera.toml", "truth.parquet", "truth_optics.json",
          "scene.toml"),
    "raw": ("frame_*.tif",),
    "dotcards": ("card_*.tif", "dotcards.toml"),
}
"""Names a simulated data set consists of, per sub-folder (glob patterns)."""

MAX_MICROLENS_FILL = 1.05
"""Largest microlens-image diameter over pitch that still gives a measurable lenslet grid."""


def foreign_files(folder: str | Path) -> list[Path]:
    """Files and folders in ``folder`` that are not part of a simulated data set.

    Parameters
    ----------
    folder : str or Path
        An existing folder (a missing one has none).

    Returns
    -------
    list of Path
        Everything that :data:`DATASET_LAYOUT` does not name, sorted.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    foreign = []
    for sub, patterns in DATASET_LAYOUT.items():
        base = folder / sub
        if not base.is_dir():
            continue
        for entry in base.iterdir():
            if sub == "." and entry.name in DATASET_LAYOUT and not entry.is_dir():
                foreign.append(entry)
            elif not any(entry.match(pattern) for pattern in patterns) or (
                    sub != "." and entry.is_dir()):
                foreign.append(entry)
    return sorted(foreign)


def _check_out_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise SceneError(f"{out}: is a file; give a folder for the simulated data set")
    foreign = foreign_files(out)
    if foreign:
        names = ", ".join(str(p.relative_to(out)) for p in foreign[:3])
        more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        raise SceneError(f"{out}: holds files that are not part of a simulated data set "
                         f"({names}{more}); it would be replaced as a whole, so choose a new "
                         "or empty folder, or move those files out")


def _check_fill(camera: CameraSpec) -> None:
    fill = camera.microlens_fill
    if fill > MAX_MICROLENS_FILL:
        matched = camera.f_number * fill
        raise SceneError(
            f"at f/{camera.f_number:g} and magnification {camera.magnification:g} the microlens "
            f"images are {fill:.2f} times their pitch and overlap, so no lenslet grid could be "
            f"measured; use f/{matched:.2f} or a larger f-number")


def simulate_dataset(camera: CameraSpec | str, out_dir: str | Path, *, seed: int | None = None,
                     n_particles: int = 20,
                     diameter_mm: float | tuple[float, float] | None = None,
                     magnification: float | None = None, frames: int = 1,
                     velocity_mm_per_frame=(0.0, 0.0, 0.0), scene: Scene | None = None,
                     samples_per_pixel: int = DEFAULT_SAMPLES_PER_PIXEL,
                     dotcard_depths=None, dotcard: DotCard | None = None,
                     sensor: SensorModel = SensorModel(),
                     realism: Realism | str | None = None,
                     progress: bool = False, shape: str = "sphere",
                     max_aspect: float = 3.0,
                     compression: str | None = "zlib",
                     scene_params: dict | None = None) -> SimulationResult:
    """Simulate raw frames, a white image and dot cards, with ground truth, into a folder.

    Parameters
    ----------
    camera : CameraSpec or str
        Nominal camera or preset name (``hall2019``, ``small``, ``small-rect``).
    out_dir : str or Path
        Output folder. The data set is built in a temporary folder beside it and swapped
        in whole at the end: an existing data set there is replaced only when the new one
        is complete (on an error or Ctrl-C it stays as it was). A folder holding anything
        else (:func:`foreign_files`) is refused.
    seed : int, optional
        Master seed: the optics are ``make_optics(camera, seed)``; particle positions and
        every noise draw use generators seeded from ``[seed, purpose, index]``. Default:
        the scene's seed when ``scene`` is given (so a scene file's seed governs the whole
        simulation), else 0.
    n_particles, diameter_mm : int, float or (float, float)
        Random scene (ignored when ``scene`` is given): particles and their diameter, mm
        (default per camera preset, :func:`~plenoptrack.simulate.scene.default_diameter_mm`:
        0.4 mm on the small presets, 1 mm otherwise), or a ``(min, max)`` range, mm, from
        which each particle's diameter is drawn log-uniformly (the truth records each).
    magnification : float, optional
        Replaces the camera's magnification (also in ``camera.toml``), with the f-number
        re-set to keep the working f-number (:meth:`CameraSpec.with_magnification`), as a
        user re-sets the aperture after refocusing.
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
    realism : Realism, "ideal", "realistic" or None
        Effects beyond the geometric model (:mod:`.realism`); default the scene's
        ``[optics]`` when it has one, else ``"realistic"`` (every effect on: a data set
        as imperfect as a real camera's; ``"ideal"`` gives the exact geometric model). With
        ``realism.spec`` the true optics differ from ``camera.toml``; with
        ``realism.target`` the dot cards are tilted, misprinted, off-centre and at depths
        off their stated ones by a common traverse zero offset and a per-card error; with
        ``realism.particles`` each particle gets a transmission (drawn from
        ``[seed, 6]``) and its velocity (:meth:`.Scene.particle_velocities`) in the truth
        (:func:`~.scene.with_particle_effects`), the frames show specular highlights and
        motion blur over ``exposure_fraction`` of the frame interval.
    progress : bool
        Show progress bars.
    shape : {"sphere", "ellipsoid", "fragment"}
        Particle shape of the random scene (ignored when ``scene`` is given); see
        :func:`~plenoptrack.simulate.scene.random_particles`.
    max_aspect : float
        Largest aspect (long over short semi-axis) of random ellipsoids or fragments, >= 1.
    compression : {"zlib", None}
        TIFF compression of the images (the pixels are the same either way). zlib makes
        a noisy ``hall2019`` image about 44 MB instead of 58 MB but takes about 2 s per
        image to write and 0.6 s to read back; None writes and reads it in a fraction of
        a second (for data sets that are used once and deleted).
    scene_params : dict, optional
        Parameters of a built-in scene (:func:`~.scenes.builtin_scene`), written to
        ``scene.toml``.

    Returns
    -------
    SimulationResult

    Notes
    -----
    ``truth.parquet`` is in the frame the calibration target defines, as an
    experimenter's truth would be: x and y from the card dot imaged nearest the sensor
    centre (the calibration's dot (0, 0); :func:`~.dotcard.origin_dot_mm`), z from the
    traverse zero. With perfect cards that is the world frame of the camera (z = 0 at the
    nominal focal plane); with ``realism.target`` it is shifted by the card centre offset
    (less whole dot spacings) and the traverse zero offset, recorded in
    ``truth_optics.json`` under ``"target_frame"``.

    Raises
    ------
    SceneError
        ``out_dir`` holds other files, is a file, or the camera's microlens images would
        overlap (main-lens f-number too small for the magnification).
    """
    camera = preset(camera) if isinstance(camera, str) else camera
    if not isinstance(camera, CameraSpec):
        raise TypeError(f"camera must be a CameraSpec or a preset name; got {type(camera).__name__}")
    if magnification is not None:
        camera = camera.with_magnification(magnification)
    _check_fill(camera)
    if compression not in ("zlib", None):
        raise SettingsError(f"compression must be 'zlib' or None; got {compression!r}")
    if seed is None:
        seed = scene.seed if scene is not None else 0
    if realism is None and scene is not None:
        realism = scene.realism
    if realism is None:
        realism = "realistic"
    out = Path(out_dir)
    _check_out_dir(out)
    if scene is None:
        scene = make_scene(camera, n_particles=n_particles, diameter_mm=diameter_mm,
                           frames=frames, velocity_mm_per_frame=velocity_mm_per_frame, seed=seed,
                           shape=shape, max_aspect=max_aspect)
    elif scene.camera != camera:
        raise SceneError(f"the scene was made for camera {scene.camera.name!r} "
                         f"(magnification {scene.camera.magnification}); pass scene.camera")
    depths = default_dotcard_depths(camera) if dotcard_depths is None else np.asarray(
        dotcard_depths, dtype=float).reshape(-1)
    card = default_dotcard(camera) if dotcard is None else dotcard
    optics = make_optics(camera, seed, realism=realism)
    truth = scene.truth.reset_index(drop=True)  # world frame, for rendering
    effects = optics.realism.particles
    if effects.enabled:
        truth = with_particle_effects(
            truth, effects, seed=np.random.default_rng([seed, 6]),
            velocity=scene.particle_velocities() if effects.exposure_fraction > 0 else None)
    zero_mm, centre_mm, placements = 0.0, (0.0, 0.0), [None] * len(depths)
    if optics.realism.target.enabled:
        zero_mm, centre_mm, placements = draw_card_placements(
            optics.realism.target, len(depths), np.random.default_rng([seed, 5]))
    # the calibration's dot (0, 0): the dot the sensor centre sees, or nearest to it
    origin_xy = origin_dot_mm(centre_mm, card.spacing_mm, sensor_centre_aim_mm(optics))
    target_truth = truth.assign(x=truth["x"] - origin_xy[0], y=truth["y"] - origin_xy[1],
                                z=truth["z"] - zero_mm)
    n_frames = scene.frames
    frame_names = [Path("raw") / f"frame_{f:04d}.tif" for f in range(n_frames)]
    card_names = [Path("dotcards") / f"card_{k:02d}.tif" for k in range(len(depths))]

    with _progress(progress) as bar, atomic_folder(out) as tmp:
        task = bar.add_task("simulating", total=2 + n_frames + len(depths)) if bar else None

        def step(description: str) -> None:
            if bar is not None:
                bar.update(task, advance=1, description=description)

        save_camera(camera, tmp / "camera.toml")
        optics_doc = optics.to_dict() | {
            "samples_per_pixel": samples_per_pixel, "sensor": asdict(sensor),
            "target_frame": {"origin_world_mm": [origin_xy[0], origin_xy[1], zero_mm],
                             "note": "truth.parquet = world position - origin_world_mm"},
            "dotcards": [{"z_stated_mm": float(z), **(p.to_dict() if p is not None else {})}
                         for z, p in zip(depths, placements)]}
        atomic_write_text(tmp / "truth_optics.json", json.dumps(optics_doc, indent=2))
        write_table(target_truth, tmp / "truth.parquet")
        if scene_params is not None:
            import tomli_w

            atomic_write_text(tmp / "scene.toml", tomli_w.dumps(scene_params))
        write_tiff(tmp / "white.tif", render_white(
            optics, seed=np.random.default_rng([seed, 2]), samples_per_pixel=samples_per_pixel,
            sensor=sensor), compression=compression)
        step("white image")
        (tmp / "raw").mkdir()
        for f in range(n_frames):
            particles = truth[truth[T_COLUMN] == f]
            image = render_frame(optics, particles, seed=np.random.default_rng([seed, 3, f]),
                                 samples_per_pixel=samples_per_pixel, sensor=sensor)
            write_tiff(tmp / frame_names[f], image, compression=compression)
            step(f"frame {f + 1}/{n_frames}")
        for k, z in enumerate(depths):
            image = render_dotcard(optics, float(z), card=card,
                                   seed=np.random.default_rng([seed, 4, k]),
                                   samples_per_pixel=samples_per_pixel, sensor=sensor,
                                   placement=placements[k])
            write_tiff(tmp / card_names[k], image, compression=compression)
            step(f"dot card {k + 1}/{len(depths)}")
        import tomli_w

        cards_doc = {"spacing_mm": card.spacing_mm, "dot_diameter_mm": card.dot_diameter_mm,
                     "cards": [{"file": p.name, "z_mm": float(z)} for p, z in zip(card_names, depths)]}
        atomic_write_text(
            tmp / "dotcards" / "dotcards.toml",
            "# dot grid: dot (m, n) at world (x, y) = (m, n) * spacing_mm; dot (0, 0) on the axis\n"
            + tomli_w.dumps(cards_doc))
        step("done")
    return SimulationResult(out_dir=out, camera=camera, optics=optics, truth=target_truth,
                            frame_paths=tuple(out / p for p in frame_names),
                            white_path=out / "white.tif",
                            dotcard_paths=tuple(out / p for p in card_names),
                            dotcard_depths_mm=tuple(float(z) for z in depths), dotcard=card,
                            camera_path=out / "camera.toml", truth_path=out / "truth.parquet",
                            optics_path=out / "truth_optics.json",
                            dotcards_path=out / "dotcards" / "dotcards.toml")
