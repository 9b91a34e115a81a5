"""The ``plenoptrack`` command: parses arguments, calls the library, reports.

Every command is a thin shell over public library functions; anything done here can be
done from Python. Library errors (:class:`plenoptrack.errors.PlenoptrackError`) are
printed as one line on stderr with exit code 1.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from .errors import PlenoptrackError

app = typer.Typer(
    name="plenoptrack",
    help="3D particle location from plenoptic (light-field) camera images.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
out = Console()


def _error_line(message: str) -> None:
    """Print ``error: message`` on stderr as one line (no wrapping, no markup parsing)."""
    line = Text("error:", style="bold red")
    line.append(" " + " ".join(str(message).split()))
    console.print(line, soft_wrap=True, highlight=False)


def _reports_errors(func):
    """Turn library and file-system errors into one readable line and exit code 1."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except PlenoptrackError as exc:
            _error_line(str(exc))
            raise typer.Exit(code=1) from None
        except OSError as exc:
            name = exc.filename2 or exc.filename  # for a rename, the target is the user's path
            where = f"{name}: " if name else ""
            _error_line(f"{where}{exc.strerror or exc}")
            raise typer.Exit(code=1) from None
        except KeyboardInterrupt:
            console.print("[bold red]interrupted[/]; nothing half-written was kept")
            raise typer.Exit(code=130) from None

    return wrapper


def _camera_from_options(preset_name: str, camera_file: Optional[Path]):
    from .camera import load_camera, preset

    return load_camera(camera_file) if camera_file is not None else preset(preset_name)


def _quantity_table(title: str) -> Table:
    """An empty two-column (quantity, value) table."""
    table = Table(title=title)
    table.add_column("quantity")
    table.add_column("value", justify="right")
    return table


def _grid_table(title: str, grid, measurement) -> Table:
    """Summary of a measured lenslet grid (a :class:`GridMeasurement` gives the fit)."""
    table = _quantity_table(title)
    table.add_row("grid type", grid.grid_type)
    table.add_row("lenslets (rows x cols)", f"{grid.shape[0]} x {grid.shape[1]}")
    table.add_row("pitch, px", f"{grid.pitch_px:.4f}")
    table.add_row("rotation, deg", f"{grid.rotation_deg:.4f}")
    table.add_row("centres detected", f"{measurement.n_detected}")
    table.add_row("grid fit residual RMS, px", f"{measurement.rms_residual_px:.4f}")
    return table


@app.command()
@_reports_errors
def simulate(
    out_dir: Path = typer.Option(Path("sim"), "--out", "-o", help="Output folder."),
    preset_name: Optional[str] = typer.Option(None, "--preset", help="Camera preset: small (default), small-rect, hall2019; with --scene, the scene's camera is used."),
    seed: int = typer.Option(0, "--seed", help="Random seed; the same seed gives the same bytes."),
    particles: int = typer.Option(20, "--particles", min=0, help="Number of particles (random scene)."),
    diameter: Optional[float] = typer.Option(None, "--diameter", help="Particle diameter, mm (default per preset: 0.4 on the small presets, 1.0 on hall2019)."),
    magnification: Optional[float] = typer.Option(None, "--magnification", help="Override the preset magnification (negative, e.g. -0.5)."),
    frames: int = typer.Option(1, "--frames", min=1, help="Number of frames."),
    scene: Optional[Path] = typer.Option(None, "--scene", help="Scene TOML file: its camera, magnification and particles replace --preset, --magnification and the random-scene options."),
    samples: int = typer.Option(16, "--samples", min=1, help="Ray samples per pixel."),
) -> None:
    """Simulate a plenoptic data set: raw frames, white image, dot cards and ground truth."""
    from .camera import preset
    from .simulate import load_scene, simulate_dataset

    scene_obj = None
    if scene is not None:
        scene_obj = load_scene(scene)
        camera = scene_obj.camera
        if preset_name is not None and preset_name != camera.name:
            raise typer.BadParameter(f"the scene file is for camera {camera.name!r}; "
                                     "drop --preset or change the scene's camera", param_hint="--preset")
        if magnification is not None and magnification != camera.magnification:
            raise typer.BadParameter("with --scene, set magnification in the scene file",
                                     param_hint="--magnification")
        magnification = None
    else:
        camera = preset(preset_name or "small")
    t0 = time.perf_counter()
    result = simulate_dataset(camera, out_dir, seed=seed, n_particles=particles,
                              diameter_mm=diameter, magnification=magnification, frames=frames,
                              scene=scene_obj, samples_per_pixel=samples, progress=True)
    console.print(f"wrote {result.out_dir} ({time.perf_counter() - t0:.1f} s)")


@app.command("calibrate-grid")
@_reports_errors
def calibrate_grid_cmd(
    white: Path = typer.Argument(..., help="White (flat-field) image, uint16 TIFF."),
    camera_file: Path = typer.Option(..., "--camera", "-c", help="Nominal camera description (camera.toml)."),
    out_file: Path = typer.Option(Path("calib.json"), "--out", "-o", help="Calibration file to write."),
) -> None:
    """Measure the lenslet grid from a white image and write a calibration file."""
    from .camera import load_camera
    from .calibration import calibrate_from_white, save_calibration

    camera = load_camera(camera_file)
    t0 = time.perf_counter()
    calib, report = calibrate_from_white(white, camera)
    save_calibration(calib, out_file)
    table = _grid_table(f"lenslet grid ({time.perf_counter() - t0:.2f} s)", calib.grid, report)
    out.print(table)
    console.print(f"wrote {out_file}")


@app.command("calibrate")
@_reports_errors
def calibrate_cmd(
    white: Path = typer.Option(..., "--white", "-w", help="White (flat-field) image, uint16 TIFF."),
    dotcards: Path = typer.Option(..., "--dotcards", "-d", help="Dot-card folder with dotcards.toml and one TIFF per depth."),
    camera_file: Path = typer.Option(..., "--camera", "-c", help="Nominal camera description (camera.toml)."),
    out_file: Path = typer.Option(Path("calib.json"), "--out", "-o", help="Calibration file to write."),
    order: int = typer.Option(4, "--order", help="DLFC total polynomial order (1-6)."),
) -> None:
    """Calibrate: lenslet grid from a white image, DLFC from dot cards; write a calibration file."""
    from .calibrate import calibrate, read_dotcards
    from .calibration import save_calibration
    from .camera import load_camera

    camera = load_camera(camera_file)
    cards = read_dotcards(dotcards)
    calib, report = calibrate(white, cards, camera, order=order, progress=True)
    save_calibration(calib, out_file)
    fit = report.fit
    summary = _grid_table(f"calibration ({report.seconds['total']:.1f} s)", calib.grid, report.grid)
    summary.add_row("DLFC order", f"{report.order}")
    summary.add_row("dot cards", f"{len(cards)}")
    summary.add_row("points used", f"{fit.n_points}")
    summary.add_row("points rejected", f"{fit.n_rejected}")
    summary.add_row("DLFC residual RMS, view px", f"{fit.rms_px:.4f}")
    summary.add_row("DLFC residual max, view px", f"{fit.max_px:.4f}")
    out.print(summary)
    per_card = Table(title="DLFC residual per dot card")
    for name in ("card", "z, mm", "views", "points", "rejected", "RMS, view px"):
        per_card.add_column(name, justify="left" if name == "card" else "right")
    for row in report.cards.itertuples():
        per_card.add_row(row.file, f"{row.z_mm:g}", f"{row.n_views}", f"{row.n_points}",
                         f"{row.n_rejected}", f"{row.rms_px:.4f}")
    per_card.add_row("all", "", "", f"{fit.n_points + fit.n_rejected}", f"{fit.n_rejected}",
                     f"{fit.rms_px:.4f}", style="bold")
    out.print(per_card)
    console.print(f"wrote {out_file}")


def _load_frame(raw: Path, frame: int, calib):
    from .io import read_raw

    image = read_raw(raw, frame=frame)
    calib.check_image(image, source=str(raw))
    return image


@app.command()
@_reports_errors
def views(
    raw: Path = typer.Argument(..., help="Raw plenoptic image (uint16 TIFF)."),
    calib_file: Path = typer.Option(..., "--calib", help="Calibration file."),
    out_file: Path = typer.Option(Path("views.tif"), "--out", "-o", help="Multi-page TIFF of all views, page = v * n_u + u."),
    mosaic: Optional[Path] = typer.Option(None, "--mosaic", help="Also write a PNG mosaic of all views."),
    frame: int = typer.Option(0, "--frame", help="Frame of a multi-page raw TIFF."),
) -> None:
    """Decode a raw image and write every perspective view."""
    from .calibration import load_calibration
    from .lightfield import decode, write_mosaic_png, write_views_tiff

    calib = load_calibration(calib_file)
    image = _load_frame(raw, frame, calib)
    t0 = time.perf_counter()
    lf = decode(image, calib.grid, progress=True)
    write_views_tiff(out_file, lf)
    if mosaic is not None:
        try:
            write_mosaic_png(mosaic, lf)
        except BaseException:
            out_file.unlink(missing_ok=True)  # a failed run leaves neither output
            raise
    console.print(f"decoded {lf.data.shape[0]} x {lf.data.shape[1]} views of "
                  f"{lf.data.shape[2]} x {lf.data.shape[3]} samples in {time.perf_counter() - t0:.2f} s; "
                  f"wrote {out_file}" + (f" and {mosaic}" if mosaic is not None else ""))


def _check_depths(camera, depths) -> None:
    """Refuse depths that no real image of the main lens corresponds to."""
    nearest = camera.focal_length_mm - camera.object_distance_mm  # object at the focal point
    for z in depths:
        if not (np.isfinite(z) and z > nearest):
            raise typer.BadParameter(
                f"depth {z:g} mm has no real image; depths must be finite and beyond "
                f"{nearest:g} mm (the main lens's front focal point)", param_hint="--depth/--alpha/--zmin/--zmax")


@app.command()
@_reports_errors
def refocus(
    raw: Path = typer.Argument(..., help="Raw plenoptic image (uint16 TIFF)."),
    calib_file: Path = typer.Option(..., "--calib", help="Calibration file."),
    depth: list[float] = typer.Option([], "--depth", help="Depth z (mm, 0 = focal plane); repeat for several."),
    alpha: list[float] = typer.Option([], "--alpha", help="Refocus parameter alpha = d / s_i; repeat for several."),
    stack: int = typer.Option(0, "--stack", help="Focal stack of this many planes evenly over --zmin..--zmax."),
    zmin: float = typer.Option(-25.0, "--zmin", help="Nearest depth of --stack, mm."),
    zmax: float = typer.Option(25.0, "--zmax", help="Farthest depth of --stack, mm."),
    out_file: Path = typer.Option(Path("refocused.tif"), "--out", "-o", help="Output TIFF (one page per plane)."),
    frame: int = typer.Option(0, "--frame", help="Frame of a multi-page raw TIFF."),
) -> None:
    """Refocus a raw image (shift-and-add) at given depths or alphas, or make a focal stack."""
    from .calibration import load_calibration
    from .io import write_tiff
    from .lightfield import decode, focal_stack

    if not depth and not alpha and stack <= 0:
        raise typer.BadParameter("give --depth, --alpha or --stack")
    for a in alpha:
        if not (np.isfinite(a) and a > 0):
            raise typer.BadParameter(f"alpha must be a positive number; got {a}", param_hint="--alpha")
    calib = load_calibration(calib_file)
    camera = calib.camera
    with np.errstate(divide="ignore", invalid="ignore"):
        depths = list(depth) + [float(camera.depth_for_alpha(np.float64(a))) for a in alpha]
    if stack > 0:
        depths += list(np.linspace(zmin, zmax, stack))
    _check_depths(camera, depths)
    image = _load_frame(raw, frame, calib)
    t0 = time.perf_counter()
    lf = decode(image, calib.grid)
    planes = focal_stack(lf, camera, np.asarray(depths), progress=True)
    write_tiff(out_file, planes.astype(np.float32), compression=None)
    console.print(f"{len(depths)} plane(s) in {time.perf_counter() - t0:.2f} s; wrote {out_file}")


@app.command()
@_reports_errors
def locate(
    raw: list[Path] = typer.Argument(..., help="Raw plenoptic images (uint16 TIFF; multi-page = frames)."),
    calib_file: Path = typer.Option(..., "--calib", help="Calibration file with a DLFC (`plenoptrack calibrate`)."),
    out_file: Path = typer.Option(Path("particles.parquet"), "--out", "-o", help="Particle table (.parquet or .csv)."),
    detections_file: Optional[Path] = typer.Option(None, "--detections", help="Also write every centroid found in every view."),
    window: int = typer.Option(31, "--window", help="Local-threshold window of the segmentation, view pixels."),
    contrast: float = typer.Option(0.15, "--contrast", help="Relative darkness a particle pixel needs."),
    planes: int = typer.Option(10, "--planes", help="Refocus planes of the clustering."),
) -> None:
    """Locate particles in 3D (perspective-shift method) and write a particle table."""
    import warnings

    import pandas as pd
    from rich.progress import Progress

    from .calibration import load_calibration
    from .errors import NoParticlesWarning
    from .io import read_frames, write_table
    from .locate.perspective import PerspectiveLocator, locate_frame

    calib = load_calibration(calib_file)
    calib.dlfc  # refuse a calibration without a DLFC before any work
    locator = PerspectiveLocator(window=window, contrast=contrast, n_planes=planes)
    tables, detections, frame, empty = [], [], 0, 0
    t0 = time.perf_counter()
    with Progress(console=console, transient=True) as bar:
        task = bar.add_task("locating", total=len(raw))
        for path in raw:
            stack = read_frames(path)
            calib.check_image(stack, source=str(path))
            for image in stack:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", NoParticlesWarning)
                    result = locate_frame(image, calib, frame=frame, locator=locator)
                empty += any(issubclass(w.category, NoParticlesWarning) for w in caught)
                tables.append(result.particles)
                if detections_file is not None:
                    detections.append(result.detections)
                frame += 1
            bar.advance(task)
    particles = pd.concat(tables, ignore_index=True)
    write_table(particles, out_file)
    if detections_file is not None:
        write_table(pd.concat(detections, ignore_index=True), detections_file)
    note = f" ({empty} frame(s) without particles)" if empty else ""
    console.print(f"{len(particles)} particles in {frame} frame(s){note}, "
                  f"{time.perf_counter() - t0:.2f} s; wrote {out_file}", highlight=False)


@app.command()
@_reports_errors
def evaluate(
    particles_file: Path = typer.Argument(..., help="Measured particle table (.parquet or .csv)."),
    truth_file: Path = typer.Argument(..., help="True particle table, e.g. a simulator's truth.parquet."),
    tolerance: float = typer.Option(1.0, "--tolerance", help="Largest 3D distance of a match, mm."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of a table."),
) -> None:
    """Match measured particles to the truth (Hungarian, within a tolerance) and report errors."""
    import json

    from .evaluate import evaluate_particles
    from .io import read_table

    ev = evaluate_particles(read_table(particles_file), read_table(truth_file), tolerance_mm=tolerance)
    if as_json:
        print(json.dumps(ev.to_dict()))
        return
    table = _quantity_table(f"{particles_file} against {truth_file} (tolerance {tolerance:g} mm)")
    table.add_row("true / measured / matched", f"{ev.n_true} / {ev.n_measured} / {ev.n_matched}")
    table.add_row("recall", f"{ev.recall:.4f}")
    table.add_row("precision", f"{ev.precision:.4f}")
    for axis in "xyz":
        mean, std = getattr(ev, f"mean_error_{axis}"), getattr(ev, f"std_error_{axis}")
        table.add_row(f"{axis} error mean / sd, mm", f"{mean:+.4f} / {std:.4f}")
    table.add_row("lateral RMS error, mm", f"{ev.rms_error_lateral:.4f}")
    out.print(table)


@app.command()
@_reports_errors
def demo(
    out_dir: Path = typer.Option(Path("plenoptrack-demo"), "--out", "-o", help="Folder for the demo's files."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated scene."),
) -> None:
    """Run the whole pipeline on a small simulated scene and print a summary."""
    from .demo import run_demo

    summary = run_demo(out_dir, seed=seed, progress=True)
    table = Table(title="plenoptrack demo (simulated 'small' camera)")
    table.add_column("step")
    table.add_column("result", justify="right")
    table.add_column("seconds", justify="right")
    for step, result, seconds in summary.rows:
        table.add_row(step, result, f"{seconds:.2f}")
    out.print(table)
    console.print(f"files in {out_dir}")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
