"""The ``plenoptrack`` command: parses arguments, calls the library, reports.

Every command is a thin shell over public library functions; anything done here can be
done from Python. Whatever goes wrong is printed as one line on stderr, ``error: ...``,
and the exit code says what kind of problem it was:

- 2: a usage error (an unknown option, a value out of range, an output that would
  overwrite an input) - fix the command line;
- 1: a data error (a missing, corrupt or implausible file; a failed calibration) - fix the
  data;
- 130: interrupted with Ctrl-C; nothing half-written is kept (outputs that were already
  complete when the interrupt came are named).

``plenoptrack --debug COMMAND ...`` (or ``PLENOPTRACK_DEBUG=1``) prints the full traceback
as well, for bug reports. Warnings are printed as one ``warning: ...`` line each.

No command ever writes over one of its inputs, and a command with several outputs writes
them all or none: outputs are written beside their targets and renamed into place only
when the whole command has succeeded.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import sys
import time
import traceback
import warnings
from pathlib import Path
from typing import Optional

import numpy as np
import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text
from typer.core import TyperGroup

from .errors import PlenoptrackError, UsageError

console = Console(stderr=True)
out = Console()
_state = {"debug": False}


def _debug() -> bool:
    return _state["debug"] or os.environ.get("PLENOPTRACK_DEBUG", "") not in ("", "0")


def _one_line(prefix: str, message: str, style: str) -> None:
    """Print ``prefix message`` on stderr as one line (no wrapping, no markup parsing)."""
    line = Text(prefix, style=style)
    line.append(" " + " ".join(str(message).split()))
    console.print(line, soft_wrap=True, highlight=False)


def _error_line(message: str) -> None:
    _one_line("error:", message, "bold red")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    _one_line("warning:", str(message), "bold yellow")


# click's base of usage errors, whether typer bundles click or uses the installed one
_ClickException = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


class _OneLineErrors(TyperGroup):
    """The command group: usage errors of the parser become one line and exit code 2."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True,
             **extra):
        try:
            rv = super().main(args=args, prog_name=prog_name, complete_var=complete_var,
                              standalone_mode=False, **extra)
        except _ClickException as exc:
            ctx = getattr(exc, "ctx", None)
            hint = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
            _error_line(exc.format_message() + hint)
            sys.exit(exc.exit_code)
        except (typer.Abort, KeyboardInterrupt):
            _error_line(_interrupt_message())
            sys.exit(130)
        sys.exit(rv if isinstance(rv, int) else 0)


app = typer.Typer(
    name="plenoptrack",
    cls=_OneLineErrors,
    help="3D particle location from plenoptic (light-field) camera images.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        from . import __version__

        out.print(f"plenoptrack {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _options(
    debug: bool = typer.Option(False, "--debug", envvar="PLENOPTRACK_DEBUG",
                               help="Show the full traceback of an error (for bug reports)."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """3D particle location from plenoptic (light-field) camera images."""
    _state["debug"] = debug


def _interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is, or was caused by, Ctrl-C (compiled kernels wrap it in SystemError)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _interrupt_message(shown: int = 3) -> str:
    """What a Ctrl-C left behind: nothing half-written, and which outputs were complete.

    Ctrl-C is held back while outputs are renamed into place, so an interrupt that lands
    there (or just after) ends the command with its new outputs complete; say so.
    """
    from .io import committed_outputs

    done = [str(p) for p in committed_outputs()]
    message = "interrupted; nothing half-written was kept"
    if not done:
        return message
    more = f" and {len(done) - shown} more" if len(done) > shown else ""
    return f"{message}; complete before the interrupt: wrote {', '.join(done[:shown])}{more}"


def _reports_errors(func):
    """Turn every failure into one readable line and an exit code (2 usage, 1 data, 130 Ctrl-C)."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        from .io import forget_committed_outputs

        forget_committed_outputs()
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            try:
                return func(*args, **kwargs)
            except (typer.Exit, typer.Abort):
                raise
            except BaseException as exc:
                code, message = _describe(exc)
                if _debug() and code != 130:
                    console.print(Text("".join(traceback.format_exception(exc))), highlight=False)
                _error_line(message)
                raise typer.Exit(code=code) from None

    return wrapper


def _describe(exc: BaseException) -> tuple[int, str]:
    """Exit code and one-line message for an exception that ended a command."""
    if _interrupted(exc):
        return 130, _interrupt_message()
    if isinstance(exc, _ClickException):  # typer.BadParameter raised in a command body
        hint = ""
        ctx = getattr(exc, "ctx", None)
        if ctx is not None:
            hint = f" (see `{ctx.command_path} --help`)"
        return exc.exit_code, exc.format_message() + hint
    if isinstance(exc, PlenoptrackError):
        return (2 if isinstance(exc, UsageError) else 1), str(exc)
    if isinstance(exc, MemoryError):
        return 1, "out of memory; process fewer frames at a time or use a larger machine"
    if isinstance(exc, OSError):
        name = exc.filename2 or exc.filename  # for a rename, the target is the user's path
        where = f"{name}: " if name else ""
        return 1, f"{where}{exc.strerror or exc}"
    return 1, (f"internal error ({type(exc).__name__}: {exc}); please report it with the "
               "output of `plenoptrack --debug ...`")


# --- option checks at the boundary --------------------------------------------------------

def _finite(*, positive: bool = False, at_least: float | None = None,
            below: float | None = None):
    """A typer callback refusing NaN, infinity and values outside a range."""
    def check(value):
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if v is None:
                continue
            if not math.isfinite(v):
                raise typer.BadParameter(f"must be a finite number; got {v}")
            if positive and not v > 0:
                raise typer.BadParameter(f"must be positive; got {v:g}")
            if at_least is not None and v < at_least:
                raise typer.BadParameter(f"must be at least {at_least:g}; got {v:g}")
            if below is not None and not v < below:
                raise typer.BadParameter(f"must be below {below:g}; got {v:g}")
        return value
    return check


def _diameter(value: str | None):
    """``--diameter``: one diameter or ``MIN:MAX``, mm, as a float or a (min, max) pair."""
    if value is None:
        return None
    parts = value.split(":")
    try:
        numbers = [float(p) for p in parts]
    except ValueError:
        raise typer.BadParameter(f"must be a diameter in mm or a range MIN:MAX; got {value!r}") from None
    if len(numbers) > 2 or not all(math.isfinite(d) and d > 0 for d in numbers):
        raise typer.BadParameter(f"must be a positive diameter in mm or a range MIN:MAX of "
                                 f"positive diameters; got {value!r}")
    if len(numbers) == 2 and numbers[0] > numbers[1]:
        raise typer.BadParameter(f"range MIN:MAX needs MIN <= MAX; got {value!r}")
    return numbers[0] if len(numbers) == 1 else (numbers[0], numbers[1])


def _outputs(outputs: dict, inputs: dict, *, folders=()):
    """Refuse outputs that clash with inputs (before any work), then stage the files."""
    from .io import check_outputs, staged_outputs

    check_outputs(outputs, inputs, folders=folders)
    return staged_outputs(*outputs.values())


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
    out_dir: Path = typer.Option(Path("sim"), "--out", "-o", help="Output folder; an existing simulated data set there is replaced only when the new one is complete."),
    preset_name: Optional[str] = typer.Option(None, "--preset", help="Camera preset: small (default), small-rect, hall2019; with --scene, the scene's camera is used."),
    seed: Optional[int] = typer.Option(None, "--seed", help="Random seed of optics, particles and noise (default 0, or the scene file's seed); the same seed gives the same bytes."),
    particles: int = typer.Option(20, "--particles", min=0, help="Number of particles (random scene)."),
    diameter: Optional[str] = typer.Option(None, "--diameter", callback=_diameter, help="Particle diameter, mm (default per preset: 0.4 on the small presets, 1.0 on hall2019), or a range MIN:MAX drawn log-uniformly, e.g. 0.2:2."),
    shape: str = typer.Option("sphere", "--shape", help="Particle shape of the random scene: sphere, ellipsoid (prolate, random orientation, aspect ratio up to --max-aspect) or fragment (irregular faceted body, random orientation, aspect ratio of its equivalent ellipsoid up to --max-aspect)."),
    max_aspect: float = typer.Option(3.0, "--max-aspect", callback=_finite(at_least=1.0), help="Largest aspect ratio (long over short axis) of ellipsoids and fragments."),
    magnification: Optional[float] = typer.Option(None, "--magnification", callback=_finite(), help="Override the preset magnification (negative, e.g. -0.5); the f-number is re-set to keep the microlens images filled, and the default volume depth and dot-card depths scale like the depth of field, as 1/M^2 (small at -1: 5 mm instead of 20)."),
    frames: Optional[int] = typer.Option(None, "--frames", min=1, help="Number of frames (default 1, or the scene's)."),
    scene: Optional[Path] = typer.Option(None, "--scene", help="Scene TOML file: its camera, magnification, seed and particles replace --preset, --magnification, --seed and the random-scene options. Or a built-in scene, 'fragments' (an expanding ring of metal fragments) or 'vortex-ring' (tracers in Hill's vortex), or a TOML file with scene = 'NAME' whose keys override that scene's parameters (a data set's scene.toml is one)."),
    samples: int = typer.Option(16, "--samples", min=1, max=4096, help="Ray samples per pixel."),
    optics_mode: Optional[str] = typer.Option(None, "--optics", help="realistic (default: spec-sheet errors, imperfect dot cards, diffraction, aberrations, dust, sensor defects and the other effects of plenoptrack.simulate.realism) or ideal (the exact geometric model); the optics table of a scene file applies when not given."),
) -> None:
    """Simulate a plenoptic data set: raw frames, white image, dot cards and ground truth."""
    from .camera import preset
    from .io import check_outputs
    from .simulate import load_scene, simulate_dataset
    from .simulate.scenes import builtin_scene, read_scene_spec

    if magnification == 0:
        raise typer.BadParameter("must be non-zero (negative for a real, inverted image)",
                                 param_hint="--magnification")
    if shape not in ("sphere", "ellipsoid", "fragment"):
        raise typer.BadParameter(f"must be 'sphere', 'ellipsoid' or 'fragment'; got {shape!r}",
                                 param_hint="--shape")
    if optics_mode not in (None, "ideal", "realistic"):
        raise typer.BadParameter(f"must be 'ideal' or 'realistic'; got {optics_mode!r}",
                                 param_hint="--optics")
    check_outputs({"--out": out_dir}, {"--scene": scene}, folders=["--out"])
    scene_obj = scene_params = None
    builtin = read_scene_spec(scene) if scene is not None else None
    if builtin is not None:
        name, overrides = builtin
        overrides = {**overrides, **({"seed": seed} if seed is not None else {}),
                     **({"frames": frames} if frames is not None else {}),
                     **({"optics": optics_mode} if optics_mode is not None else {}),
                     **({"camera": preset_name} if preset_name is not None else {})}
        if magnification is not None:
            raise typer.BadParameter("built-in scenes use their camera's magnification",
                                     param_hint="--magnification")
        scene_obj, scene_params = builtin_scene(name, overrides)
        camera, seed, optics_mode = scene_obj.camera, scene_obj.seed, None
    elif scene is not None:
        scene_obj = load_scene(scene)
        camera = scene_obj.camera
        if preset_name is not None and preset_name != camera.name:
            raise typer.BadParameter(f"the scene file is for camera {camera.name!r}; "
                                     "drop --preset or change the scene's camera", param_hint="--preset")
        if magnification is not None and magnification != camera.magnification:
            raise typer.BadParameter("with --scene, set magnification in the scene file",
                                     param_hint="--magnification")
        if seed is not None and seed != scene_obj.seed:
            raise typer.BadParameter(f"the scene file's seed ({scene_obj.seed}) governs the whole "
                                     "simulation; change it in the file instead", param_hint="--seed")
        magnification = None
    else:
        camera = preset(preset_name or "small")
    t0 = time.perf_counter()
    result = simulate_dataset(camera, out_dir, seed=seed, n_particles=particles,
                              diameter_mm=diameter, magnification=magnification,
                              frames=frames or 1, scene=scene_obj, samples_per_pixel=samples,
                              realism=optics_mode, shape=shape, max_aspect=max_aspect,
                              progress=True, scene_params=scene_params)
    if magnification is not None:
        console.print(f"magnification {result.camera.magnification:g}: main lens set to "
                      f"f/{result.camera.f_number:g} (working f-number "
                      f"{result.camera.image_side_f_number:.2f}, matched to the microlenses)",
                      highlight=False)
    console.print(f"wrote {result.out_dir} ({time.perf_counter() - t0:.1f} s)", highlight=False)


@app.command("calibrate-grid")
@_reports_errors
def calibrate_grid_cmd(
    white: Path = typer.Argument(..., help="White (flat-field) image, uint16 TIFF."),
    camera_file: Path = typer.Option(..., "--camera", "-c", help="Nominal camera description (camera.toml)."),
    out_file: Path = typer.Option(Path("calib.json"), "--out", "-o", help="Calibration file to write."),
) -> None:
    """Measure the lenslet grid from a white image and write a calibration file."""
    from .camera import load_camera
    from .calibration import calibrate_from_white, record_white, save_calibration

    with _outputs({"--out": out_file}, {"WHITE": white, "--camera": camera_file}) as (tmp,):
        camera = load_camera(camera_file)
        t0 = time.perf_counter()
        calib, report = calibrate_from_white(white, camera)
        save_calibration(record_white(calib, white, calibration_path=out_file), tmp)
    table = _grid_table(f"lenslet grid ({time.perf_counter() - t0:.2f} s)", calib.grid, report)
    out.print(table)
    console.print(f"wrote {out_file}", highlight=False)


@app.command("calibrate")
@_reports_errors
def calibrate_cmd(
    white: Path = typer.Option(..., "--white", "-w", help="White (flat-field) image, uint16 TIFF."),
    dotcards: Path = typer.Option(..., "--dotcards", "-d", help="Dot-card folder with dotcards.toml and one TIFF per depth."),
    camera_file: Path = typer.Option(..., "--camera", "-c", help="Nominal camera description (camera.toml)."),
    out_file: Path = typer.Option(Path("calib.json"), "--out", "-o", help="Calibration file to write."),
    order: int = typer.Option(4, "--order", min=1, max=6, help="DLFC total polynomial order (1-6)."),
    check_depths: bool = typer.Option(True, "--check-depths/--no-check-depths", help="Check the card depths of dotcards.toml against the depths the dots' parallax shows (refuse a wrong sign or unit, warn about single cards)."),
    card_tilt: bool = typer.Option(False, "--card-tilt/--no-card-tilt", help="Fit the DLFC to where each card's tilt on its mount, measured from its dots' parallax, puts its dots (default: every card perpendicular to the optical axis; the tilts are printed either way). Reliable on a wide field of view (hall2019: within 0.0003); on a small one the optics bias the measured tilts."),
) -> None:
    """Calibrate: lenslet grid from a white image, DLFC from dot cards; write a calibration file.

    The card depths in dotcards.toml are checked against the depths the dots' parallax
    across views shows; a sign or scale error is refused.
    """
    from .calibrate import calibrate, read_dotcards
    from .calibration import record_white, save_calibration
    from .camera import load_camera

    cards = read_dotcards(dotcards)
    inputs = {"--white": white, "--camera": camera_file, "--dotcards": dotcards,
              "dotcards.toml": cards.source, "a dot-card image": [c.path for c in cards.cards]}
    with _outputs({"--out": out_file}, inputs) as (tmp,):
        camera = load_camera(camera_file)
        calib, report = calibrate(white, cards, camera, order=order, check_depths=check_depths,
                                  card_tilt=card_tilt, progress=True)
        save_calibration(record_white(calib, white, calibration_path=out_file), tmp)
    _print_calibration_report(calib, cards, report)
    console.print(f"wrote {out_file}", highlight=False)


def _print_calibration_report(calib, cards, report) -> None:
    fit = report.fit
    summary = _grid_table(f"calibration ({report.seconds['total']:.1f} s)", calib.grid, report.grid)
    summary.add_row("DLFC order", f"{report.order}")
    summary.add_row("dot cards", f"{len(cards)}")
    summary.add_row("points used", f"{fit.n_points}")
    summary.add_row("points rejected", f"{fit.n_rejected}")
    summary.add_row("DLFC residual RMS, view px", f"{fit.rms_px:.4f}")
    summary.add_row("DLFC residual max, view px", f"{fit.max_px:.4f}")
    out.print(summary)
    implied = "z_implied_mm" in report.cards.columns
    tilted = "tilt_x" in report.cards.columns
    per_card = Table(title="DLFC residual per dot card")
    names = (["card", "z, mm"] + (["z from parallax, mm"] if implied else [])
             + (["tilt x, y, mrad (* applied)"] if tilted else [])
             + ["views", "points", "rejected", "RMS, view px"])
    for name in names:
        per_card.add_column(name, justify="left" if name == "card" else "right")
    for row in report.cards.itertuples():
        depth = [f"{row.z_implied_mm:.2f}"] if implied else []
        tilt = [", ".join(f"{1e3 * t:+.2f}{'*' if a != 0 else ''}" for t, a in
                          ((row.tilt_x, row.tilt_x_applied), (row.tilt_y, row.tilt_y_applied)))
                ] if tilted else []
        per_card.add_row(row.file, f"{row.z_mm:g}", *depth, *tilt, f"{row.n_views}",
                         f"{row.n_points}", f"{row.n_rejected}", f"{row.rms_px:.4f}")
    per_card.add_row("all", "", *([""] if implied else []), *([""] if tilted else []), "",
                     f"{fit.n_points + fit.n_rejected}", f"{fit.n_rejected}",
                     f"{fit.rms_px:.4f}", style="bold")
    out.print(per_card)
    measured = report.cards["model_error_z_mm"].notna()
    if measured.any():
        model = Table(title="DLFC model error per dot card (beyond the dots' own noise)")
        for name in ("card", "z, mm", "lateral, um", "depth, um"):
            model.add_column(name, justify="left" if name == "card" else "right")
        for row in report.cards[measured].itertuples():
            model.add_row(row.file, f"{row.z_mm:g}", f"{1e3 * row.model_error_lateral_mm:.1f}",
                          f"{1e3 * row.model_error_z_mm:.1f}")
        out.print(model)


def _load_frame(raw: Path, frame: int, calib):
    from .io import read_raw, warn_exposure

    image = read_raw(raw, frame=frame)
    calib.check_image(image, source=str(raw))
    warn_exposure(image, calib.camera.full_scale, source=f"{raw} frame {frame}")
    return image


@app.command()
@_reports_errors
def views(
    raw: Path = typer.Argument(..., help="Raw plenoptic image (uint16 TIFF)."),
    calib_file: Path = typer.Option(..., "--calib", help="Calibration file."),
    out_file: Path = typer.Option(Path("views.tif"), "--out", "-o", help="Multi-page TIFF of all views, page = v * n_u + u."),
    mosaic: Optional[Path] = typer.Option(None, "--mosaic", help="Also write a PNG mosaic of all views."),
    frame: int = typer.Option(0, "--frame", help="Frame of a multi-page raw TIFF (negative counts from the end)."),
) -> None:
    """Decode a raw image and write every perspective view."""
    from .calibration import load_calibration
    from .lightfield import decode, write_mosaic_png, write_views_tiff

    with _outputs({"--out": out_file, "--mosaic": mosaic},
                  {"RAW": raw, "--calib": calib_file}) as (views_tmp, mosaic_tmp):
        calib = load_calibration(calib_file)
        image = _load_frame(raw, frame, calib)
        t0 = time.perf_counter()
        lf = decode(image, calib.grid, progress=True)
        write_views_tiff(views_tmp, lf)
        if mosaic is not None:
            write_mosaic_png(mosaic_tmp, lf)
    console.print(f"decoded {lf.data.shape[0]} x {lf.data.shape[1]} views of "
                  f"{lf.data.shape[2]} x {lf.data.shape[3]} samples in {time.perf_counter() - t0:.2f} s; "
                  f"wrote {out_file}" + (f" and {mosaic}" if mosaic is not None else ""),
                  highlight=False)


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
    depth: list[float] = typer.Option([], "--depth", callback=_finite(), help="Depth z (mm, 0 = focal plane); repeat for several."),
    alpha: list[float] = typer.Option([], "--alpha", callback=_finite(positive=True), help="Refocus parameter alpha = d / s_i; repeat for several."),
    stack: int = typer.Option(0, "--stack", min=0, help="Focal stack of this many planes evenly over --zmin..--zmax."),
    zmin: float = typer.Option(-25.0, "--zmin", callback=_finite(), help="Nearest depth of --stack, mm."),
    zmax: float = typer.Option(25.0, "--zmax", callback=_finite(), help="Farthest depth of --stack, mm."),
    out_file: Path = typer.Option(Path("refocused.tif"), "--out", "-o", help="Output TIFF (one page per plane)."),
    frame: int = typer.Option(0, "--frame", help="Frame of a multi-page raw TIFF (negative counts from the end)."),
) -> None:
    """Refocus a raw image (shift-and-add) at given depths or alphas, or make a focal stack."""
    from .calibration import load_calibration
    from .io import write_tiff
    from .lightfield import decode, focal_stack

    if not depth and not alpha and stack <= 0:
        raise typer.BadParameter("give --depth, --alpha or --stack")
    if stack > 1 and not zmin < zmax:
        raise typer.BadParameter(f"--zmin ({zmin:g}) must be below --zmax ({zmax:g})",
                                 param_hint="--zmin/--zmax")
    with _outputs({"--out": out_file}, {"RAW": raw, "--calib": calib_file}) as (tmp,):
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
        write_tiff(tmp, planes.astype(np.float32), compression=None)
    console.print(f"{len(depths)} plane(s) in {time.perf_counter() - t0:.2f} s; wrote {out_file}",
                  highlight=False)


@app.command()
@_reports_errors
def locate(
    raw: list[Path] = typer.Argument(..., help="Raw plenoptic images (uint16 TIFF; multi-page = frames)."),
    calib_file: Path = typer.Option(..., "--calib", help="Calibration file with a DLFC (`plenoptrack calibrate`)."),
    out_file: Path = typer.Option(Path("particles.parquet"), "--out", "-o", help="Particle table (.parquet or .csv)."),
    detections_file: Optional[Path] = typer.Option(None, "--detections", help="Also write every centroid found in every view."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Locator settings (TOML, one table per stage; `plenoptrack settings` writes every default)."),
    window: Optional[int] = typer.Option(None, "--window", min=3, help="Local-threshold window of the segmentation, view pixels (at least 3; default 31). Overrides --config."),
    contrast: Optional[float] = typer.Option(None, "--contrast", callback=_finite(positive=True, below=1.0), help="Relative darkness a particle pixel needs (between 0 and 1; default 0.15). Overrides --config."),
    planes: Optional[int] = typer.Option(None, "--planes", min=2, help="Refocus planes of the clustering (at least 2; default 10). Overrides --config."),
    shape_error: Optional[float] = typer.Option(None, "--shape-error", callback=_finite(at_least=0.0, below=1.0), help="Uncertainty of an irregular particle's centre of mass, per axis, as a fraction of its diameter, added to sigma (default 0 for spheres, droplets and ellipsoids; about 0.02 for fragments). Overrides --config."),
    white: Optional[Path] = typer.Option(None, "--white", "-w", help="White (flat-field) image to divide every frame by (default: the one the calibration file records)."),
    flat_field: bool = typer.Option(True, "--flat-field/--no-flat-field", help="Divide every frame by the white image (recommended: dust shadows and dead pixels are otherwise taken for particles)."),
    partial: bool = typer.Option(False, "--partial", help="On Ctrl-C, keep the frames already located (default: write nothing)."),
    method: str = typer.Option("perspective", "--method", help="perspective (perspective-shift method), refocus (the refocusing baseline: dense focal stack, minimum intensity, maximum edge sharpness) or hybrid (perspective-shift positions, depth refined by a local focal stack near focus)."),
    stack_planes: int = typer.Option(100, "--stack-planes", min=3, help="Focal-stack planes of --method refocus (at least 3)."),
) -> None:
    """Locate particles in 3D (perspective-shift method by default) and write a particle table.

    Every frame is divided by the white image (flat-fielded) first: by default the white
    image the calibration file records, if it is still there unchanged. The table's
    metadata records the settings, the calibration and the package version
    (`plenoptrack settings --from-table TABLE` writes its settings back as TOML).
    """
    from rich.progress import Progress

    from .calibration import load_calibration
    from .io import count_frames, read_frames
    if white is not None and not flat_field:
        raise typer.BadParameter("--white and --no-flat-field contradict each other; give one",
                                 param_hint="--white")
    locator = _locator_settings(config, window=window, contrast=contrast, planes=planes,
                                shape_error=shape_error)
    locator = _method_locator(method, locator, stack_planes)
    with _outputs({"--out": out_file, "--detections": detections_file},
                  {"RAW": raw, "--calib": calib_file, "--white": white, "--config": config}
                  ) as (out_tmp, det_tmp):
        calib = load_calibration(calib_file)
        calib.dlfc  # refuse a calibration without a DLFC before any work
        n_frames = sum(count_frames(path) for path in raw)  # every input readable, up front
        white_file, white_lf = (_flat_field_white(calib, calib_file, white) if flat_field
                                else (None, None))
        tables, detections, frame, empty = [], [], 0, 0
        interrupted = False
        t0 = time.perf_counter()
        try:
            with Progress(console=console, transient=True) as bar:
                task = bar.add_task("locating", total=n_frames)
                for path in raw:
                    stack = read_frames(path)
                    calib.check_image(stack, source=str(path))
                    for k, image in enumerate(stack):
                        result, no_particles = _locate_one(image, calib, frame, locator,
                                                           source=f"{path} frame {k}",
                                                           white=white_lf)
                        empty += no_particles
                        tables.append(result.particles)
                        if det_tmp is not None:
                            detections.append(result.detections)
                        frame += 1
                        bar.advance(task)
        except BaseException as exc:
            if not (partial and _interrupted(exc) and tables):
                raise
            interrupted = True
        from .provenance import provenance

        record = provenance(method=method, settings=locator.to_dict(), calibration=calib,
                            calibration_file=calib_file, white_file=white_file,
                            inputs=[p.resolve() for p in raw])
        particles = _write_particles(tables, detections, out_tmp, det_tmp, record)
    if interrupted:
        _error_line(f"interrupted after {frame} of {n_frames} frame(s); --partial: wrote "
                    f"their {len(particles)} particles to {out_file}")
        raise typer.Exit(code=130)
    note = f" ({empty} frame(s) without particles)" if empty else ""
    console.print(f"{len(particles)} particles in {frame} frame(s){note}, "
                  f"{time.perf_counter() - t0:.2f} s; wrote {out_file}", highlight=False)


def _locator_settings(config: Path | None, **flags):
    """Locator settings: the defaults, then the --config file, then the given flags."""
    from .locate import PerspectiveLocator, read_settings

    locator = read_settings(config) if config is not None else PerspectiveLocator()
    sections = {"window": "segment", "contrast": "segment", "planes": "cluster",
                "shape_error": "solve"}
    names = {"planes": "n_planes"}
    changes: dict = {}
    for flag, value in flags.items():
        if value is not None:
            changes.setdefault(sections[flag], {})[names.get(flag, flag)] = value
    return locator.updated(changes, source="command line")


def _white_image(calib, calib_file: Path, white: Path | None):
    """The white image to flat-field with, read and checked against the calibration: the
    given file or the one the calibration records; (None, None) with a warning when the
    recorded one is missing or changed."""
    from .calibration import find_white
    from .errors import FlatFieldWarning
    from .io import read_raw, warn_exposure

    if white is None:
        white, why = find_white(calib, calib_file)
        if white is None:
            warnings.warn(f"{why}: frames are not flat-fielded, so dust shadows and dead "
                          "pixels may be taken for particles; pass the white image with "
                          "--white (or --no-flat-field to locate without one)",
                          FlatFieldWarning, stacklevel=3)
            return None, None
    image = read_raw(white)
    calib.check_image(image, source=str(white))
    warn_exposure(image, calib.camera.full_scale, source=f"white image {white}")
    return white, image


def _flat_field_white(calib, calib_file: Path, white: Path | None):
    """The white image file and its decoded light field to flat-field the frames with, or
    (None, None) (warned)."""
    from .lightfield import decode

    white, image = _white_image(calib, calib_file, white)
    return (None, None) if white is None else (white, decode(image, calib.grid))


def _method_locator(method: str, perspective, stack_planes: int):
    """The locator of ``--method``, built on the perspective settings."""
    from .locate.refocusing import HybridLocator, RefocusLocator

    if method == "perspective":
        return perspective
    if method == "refocus":
        return RefocusLocator(n_planes=stack_planes, window=perspective.segment.window,
                              contrast=perspective.segment.contrast)
    if method == "hybrid":
        return HybridLocator(perspective=perspective, contrast=perspective.segment.contrast)
    raise typer.BadParameter(f"must be perspective, refocus or hybrid; got {method!r}",
                             param_hint="--method")


def _locate_one(image, calib, frame: int, locator, *, source: str, white=None):
    """Locate one frame; return the result and whether it had no particles.

    Warnings other than "no particles" are shown, prefixed with the file and frame.
    """
    from .errors import NoParticlesWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = locator.locate(image, calib, frame=frame, white=white)
    empty = False
    for w in caught:
        if issubclass(w.category, NoParticlesWarning):
            empty = True
        else:
            message = str(w.message).replace(f"frame {frame}: ", "", 1)
            _show_warning(f"{source}: {message}", w.category, w.filename, w.lineno)
    return result, empty


def _write_particles(tables, detections, out_tmp, det_tmp, record: dict):
    import pandas as pd

    from .io import METADATA_KEY, write_table

    particles = pd.concat(tables, ignore_index=True)
    particles.attrs[METADATA_KEY] = record
    write_table(particles, out_tmp)
    if det_tmp is not None:
        det = pd.concat(detections, ignore_index=True)
        det.attrs[METADATA_KEY] = record
        write_table(det, det_tmp)
    return particles


@app.command()
@_reports_errors
def batch(
    raw: list[str] = typer.Argument(..., help="Raw images (uint16 TIFF; multi-page = frames): files or quoted glob patterns such as \"raw/*.tif\", each pattern's files in sorted order; frames are numbered in that order."),
    calib_file: Path = typer.Option(..., "--calib", help="Calibration file with a DLFC (`plenoptrack calibrate`)."),
    out_dir: Path = typer.Option(Path("results"), "--out", "-o", help="Batch folder: one Parquet part per frame; re-running resumes it."),
    workers: Optional[int] = typer.Option(None, "--workers", "-n", min=1, help="Worker processes of a local Dask cluster (default: one per core)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Use the running dask.distributed cluster at this address (tcp://HOST:PORT) instead of a local one."),
    memory_limit: str = typer.Option("3GB", "--memory-limit", help="Memory bound of each local worker; a worker above it is restarted and its frame retried."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Locator settings (TOML; `plenoptrack settings` writes every default)."),
    method: str = typer.Option("perspective", "--method", help="Locating method: perspective, refocus or hybrid (as for `locate`)."),
    stack_planes: int = typer.Option(100, "--stack-planes", min=3, help="Focal-stack planes of --method refocus (at least 3)."),
    white: Optional[Path] = typer.Option(None, "--white", "-w", help="White (flat-field) image to divide every frame by (default: the one the calibration file records)."),
    flat_field: bool = typer.Option(True, "--flat-field/--no-flat-field", help="Divide every frame by the white image."),
    track_result: bool = typer.Option(False, "--track", help="When every frame is done, link the whole result into 3D tracks (`plenoptrack track` defaults) and write OUT-tracks.parquet beside the folder."),
) -> None:
    """Locate the particles of many images on a Dask cluster, resumably, one part per frame.

    Gives the rows `plenoptrack locate` gives the same files. Re-running skips the frames
    already done (same file content, calibration and settings); a frame that fails is
    recorded in OUT/_failures.csv and the others go on (exit code 1 if any failed).
    Read the result with pandas.read_parquet(OUT) or plenoptrack.batch.read_batch(OUT).
    """
    import contextlib
    import glob

    from . import batch as batch_mod
    from .calibration import load_calibration
    from .io import check_outputs

    if white is not None and not flat_field:
        raise typer.BadParameter("--white and --no-flat-field contradict each other; give one",
                                 param_hint="--white")
    if workers is not None and scheduler is not None:
        raise typer.BadParameter("give --workers (a local cluster) or --scheduler, not both",
                                 param_hint="--workers")
    if method not in batch_mod.METHODS:
        raise typer.BadParameter(f"must be one of {', '.join(batch_mod.METHODS)}; got {method!r}",
                                 param_hint="--method")
    files: list[Path] = []
    for pattern in raw:
        matches = sorted(glob.glob(pattern)) if glob.has_magic(pattern) else [pattern]
        if not matches:
            raise typer.BadParameter(f"{pattern!r} matches no file", param_hint="RAW")
        files += [Path(m) for m in matches]
    tracks_file = out_dir.with_name(out_dir.name + "-tracks.parquet") if track_result else None
    check_outputs({"--out": out_dir, "--track": tracks_file},
                  {"RAW": files, "--calib": calib_file, "--white": white, "--config": config},
                  folders=["--out"])
    locator = _method_locator(method, _locator_settings(config), stack_planes)
    calib = load_calibration(calib_file)
    calib.dlfc  # refuse a calibration without a DLFC before any work
    if flat_field:
        white, _ = _white_image(calib, calib_file, white)   # workers decode it themselves

    def report(outcome) -> None:
        for note in outcome.warnings:
            _show_warning(f"{outcome.path} frame {outcome.page}: {note}", UserWarning, "", 0)
        if outcome.status == "failed":
            _show_warning(f"{outcome.path} frame {outcome.page} failed: {outcome.message}",
                          UserWarning, "", 0)

    with contextlib.ExitStack() as stack:
        from distributed import Client

        if scheduler is not None:
            try:
                client = stack.enter_context(Client(scheduler, timeout="20s"))
            except OSError as exc:
                raise UsageError(f"--scheduler {scheduler}: no Dask scheduler answers there "
                                 f"({exc})") from None
        else:
            n = workers or os.cpu_count() or 1
            cluster = stack.enter_context(batch_mod.local_cluster(n, memory_limit=memory_limit))
            client = stack.enter_context(Client(cluster))
        link = batch_mod.dashboard_link(client)
        n_workers = len(client.scheduler_info().get("workers", {}))
        console.print(f"{n_workers} worker(s)" + (f"; dashboard {link}" if link else ""),
                      highlight=False, soft_wrap=True)
        result = batch_mod.run_batch(files, calib_file, out_dir, method=method, settings=locator,
                                     white_file=white, client=client, progress=True,
                                     on_outcome=report)
    summary = (f"{result.n_frames} frame(s): {result.done} located ({result.n_particles} "
               f"particles), {result.skipped} already done, {result.failed} failed; "
               f"{result.seconds:.1f} s; wrote {out_dir}")
    if result.failed:
        _error_line(f"{summary}; the failed frames are listed in {out_dir / batch_mod.FAILURES_FILE}"
                    + ("; not tracked" if track_result else ""))
        raise typer.Exit(code=1)
    console.print(summary, highlight=False, soft_wrap=True)
    if tracks_file is not None:
        from .io import write_table
        from .track import track_particles

        tracks = track_particles(batch_mod.read_batch(out_dir)).tracks
        write_table(tracks, tracks_file)
        n_tracks = tracks["particle"].nunique() if len(tracks) else 0
        console.print(f"{n_tracks} track(s); wrote {tracks_file}", highlight=False,
                      soft_wrap=True)


@app.command("settings")
@_reports_errors
def settings_cmd(
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Start from this settings file (TOML) instead of the defaults."),
    from_table: Optional[Path] = typer.Option(None, "--from-table", help="Take the settings a particle table was made with (its metadata)."),
    out_file: Optional[Path] = typer.Option(None, "--out", "-o", help="Write the TOML here instead of printing it."),
) -> None:
    """Print (or write) the locator settings as TOML, ready for `locate --config`.

    Without options: every default, one table per stage of the locator.
    """
    from .io import atomic_write_text, check_outputs, read_table
    from .locate import PerspectiveLocator, read_settings, settings_toml
    from .provenance import table_provenance

    if config is not None and from_table is not None:
        raise typer.BadParameter("give --config or --from-table, not both", param_hint="--config")
    check_outputs({"--out": out_file}, {"--config": config, "--from-table": from_table})
    if from_table is not None:
        record = table_provenance(read_table(from_table)) or {}
        if "settings" not in record:
            raise UsageError(f"{from_table}: the table records no locator settings (not written "
                             "by `plenoptrack locate`, or by an older version)")
        locator = PerspectiveLocator.from_dict(record["settings"], source=str(from_table))
    else:
        locator = read_settings(config) if config is not None else PerspectiveLocator()
    text = settings_toml(locator)
    if out_file is None:
        print(text, end="")
    else:
        atomic_write_text(out_file, text)
        console.print(f"wrote {out_file}", highlight=False)


@app.command()
@_reports_errors
def study(
    out_dir: Path = typer.Option(..., "--out", "-o", help="Output folder (created; a re-run resumes it, skipping the images already located)."),
    preset_name: str = typer.Option("hall2019", "--preset", help="Camera preset: hall2019 (default), small, small-rect."),
    camera_file: Optional[Path] = typer.Option(None, "--camera", help="Your own camera.toml (replaces --preset): the study for your camera, magnification and particle size."),
    travel: float = typer.Option(50.0, "--travel", callback=_finite(positive=True), help="Traverse travel, mm."),
    step: float = typer.Option(1.0, "--step", callback=_finite(positive=True), help="Traverse step, mm."),
    repeats: int = typer.Option(5, "--repeats", min=1, help="Images per traverse position (fresh noise each)."),
    refocus_repeats: Optional[int] = typer.Option(None, "--refocus-repeats", min=1, help="Repeats located with the refocus and hybrid methods (default --repeats; refocusing is slow)."),
    methods: str = typer.Option("perspective,refocus", "--methods", help="Comma-separated methods: perspective, refocus, hybrid."),
    workers: int = typer.Option(1, "--workers", min=0, help="Local Dask worker processes (0: this process)."),
    grid: Optional[str] = typer.Option(None, "--grid", help="paper: the 12 configurations of the paper (4 magnifications up to 0.75 at 3 object distances)."),
    particles: int = typer.Option(40, "--particles", min=1, help="Pin heads in the rigid field."),
    diameter: Optional[float] = typer.Option(None, "--diameter", callback=_finite(positive=True), help="Pin-head diameter, mm (default per preset)."),
    seed: int = typer.Option(0, "--seed", help="Master seed (field, traverse zero offset, optics, noise)."),
    optics_mode: str = typer.Option("realistic", "--optics", help="realistic (default) or ideal."),
    card_tilt: bool = typer.Option(False, "--card-tilt", help="Calibrate with the dot cards' tilts on their mounts measured from their parallax and applied (as calibrate --card-tilt)."),
) -> None:
    """Translation-stage uncertainty study: depth accuracy and precision against depth for
    each method (a simulated rigid field of pin heads moved along the optical axis)."""
    from .io import check_outputs
    from .study import StudyConfig, paper_grid, run_study

    if grid not in (None, "paper"):
        raise typer.BadParameter(f"must be 'paper'; got {grid!r}", param_hint="--grid")
    check_outputs({"--out": out_dir}, {"--camera": camera_file}, folders=["--out"])
    camera = _camera_from_options(preset_name, camera_file)
    cameras = paper_grid(camera) if grid == "paper" else [camera]
    chosen = tuple(m.strip() for m in methods.split(",") if m.strip())
    configs = [StudyConfig(c, travel_mm=travel, step_mm=step, repeats=repeats,
                           refocus_repeats=refocus_repeats, methods=chosen, n_particles=particles,
                           diameter_mm=diameter, seed=seed, realism=optics_mode,
                           card_tilt=card_tilt)
               for c in cameras]
    t0 = time.perf_counter()
    summary = run_study(configs, out_dir, workers=workers, progress=True)
    for label, cfg in summary["configurations"].items():
        for m, s in cfg["methods"].items():
            console.print(f"{label} {m}: worst |mean| {s['worst_abs_mean_mm']:.3f} mm, worst std "
                          f"{s['worst_std_mm']:.3f} mm, {s['seconds_per_image']:.1f} s/image",
                          highlight=False)
    console.print(f"wrote {out_dir} ({time.perf_counter() - t0:.0f} s)", highlight=False)


@app.command()
@_reports_errors
def evaluate(
    particles_file: Path = typer.Argument(..., help="Measured particle table (.parquet or .csv)."),
    truth_file: Path = typer.Argument(..., help="True particle table, e.g. a simulator's truth.parquet."),
    tolerance: float = typer.Option(1.0, "--tolerance", callback=_finite(positive=True), help="Largest 3D distance of a match, mm."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of a table."),
) -> None:
    """Match measured particles to the truth (Hungarian, within a tolerance) and report errors.

    A tracks table (`plenoptrack track`) against a truth with particle ids and velocities
    also gets link recovery, velocity errors and the depth error before and after track
    smoothing.
    """
    import json

    from .evaluate import evaluate_particles
    from .io import read_table

    measured, truth = read_table(particles_file), read_table(truth_file)
    ev = evaluate_particles(measured, truth, tolerance_mm=tolerance)
    tracks_ev = None
    if {"particle", "z_smooth", "velocity_x"} <= set(measured.columns) and {
            "particle", "velocity_x"} <= set(truth.columns):
        from .evaluate import evaluate_tracks

        tracks_ev = evaluate_tracks(measured, truth, tolerance_mm=tolerance)
    if as_json:
        print(json.dumps(ev.to_dict() | ({"tracks": tracks_ev.to_dict()} if tracks_ev else {})))
        return
    table = _quantity_table(f"{particles_file} against {truth_file} (tolerance {tolerance:g} mm)")
    table.add_row("true / measured / matched", f"{ev.n_true} / {ev.n_measured} / {ev.n_matched}")
    table.add_row("recall", f"{ev.recall:.4f}")
    table.add_row("precision", f"{ev.precision:.4f}")
    for axis in "xyz":
        mean, std = getattr(ev, f"mean_error_{axis}"), getattr(ev, f"std_error_{axis}")
        table.add_row(f"{axis} error mean / sd, mm", f"{mean:+.4f} / {std:.4f}")
    table.add_row("lateral RMS error, mm", f"{ev.rms_error_lateral:.4f}")
    if tracks_ev is not None:
        table.add_row("true links recovered", f"{tracks_ev.n_recovered_links} / "
                      f"{tracks_ev.n_true_links} ({tracks_ev.link_recovery:.2%})")
        table.add_row("false links", f"{tracks_ev.n_false_links}")
        table.add_row("velocity RMS error / mean speed", f"{tracks_ev.velocity_rms_error:.4f} / "
                      f"{tracks_ev.mean_speed:.4f} mm/frame")
        table.add_row("z error sd, per frame / smoothed, mm",
                      f"{tracks_ev.z_std_frame:.4f} / {tracks_ev.z_std_smooth:.4f}")
        table.add_row("z error robust sd, per frame / smoothed, mm",
                      f"{tracks_ev.z_rstd_frame:.4f} / {tracks_ev.z_rstd_smooth:.4f}")
    out.print(table)


@app.command()
@_reports_errors
def track(
    particles_file: Path = typer.Argument(..., help="Particle table of several frames (`plenoptrack locate` output, .parquet or .csv)."),
    out_file: Path = typer.Option(Path("tracks.parquet"), "--out", "-o", help="Tracks table: one row per particle and frame with its track id (particle), smoothed position, velocity and acceleration."),
    stats_file: Optional[Path] = typer.Option(None, "--stats", help="Also write one row per track (length, mean position, speed, size, shape)."),
    search_range: float = typer.Option(1.0, "--search-range", callback=_finite(positive=True), help="Lateral (x, y) search range around each track's predicted position, mm."),
    search_depth: float = typer.Option(3.0, "--search-depth", callback=_finite(positive=True), help="Depth (z) search range, mm (depth errors exceed lateral ones)."),
    memory: int = typer.Option(2, "--memory", min=0, help="Frames a track may miss and still be continued."),
    min_length: int = typer.Option(3, "--min-length", min=1, help="Drop tracks with fewer points."),
    max_sigma_ratio: float = typer.Option(1.0, "--max-sigma-ratio", help="Leave out of linking each point whose sigma on an axis exceeds this multiple of the search range on that axis (its own track, unless extension fills a track its position fits); inf links every point."),
    window: int = typer.Option(7, "--window", min=2, help="Points of each local fit along a track."),
    order: int = typer.Option(2, "--order", min=0, max=3, help="Degree of the local fit: 1 constant velocity (ballistic), 2 constant acceleration."),
    frame_interval: Optional[float] = typer.Option(None, "--frame-interval", callback=_finite(positive=True), help="Time between frames, s (adds speeds in m/s); a simulated data set's scene.toml gives it."),
    no_predict: bool = typer.Option(False, "--no-predict", help="Link without the velocity predictor."),
    no_extend: bool = typer.Option(False, "--no-extend", help="Do not continue tracks at both ends along their own velocity, nor fill their gaps, after linking (a lone point or a track of one or two points that fits a track's prediction joins it)."),
    fixed_window: bool = typer.Option(False, "--fixed-window", help="Smooth every coordinate over --window points (by default each coordinate's window is chosen among --window -2, +0, +2 and +4 by its leave-one-out prediction error)."),
    no_repair_swaps: bool = typer.Option(False, "--no-repair-swaps", help="Keep the tracks as linked: by default two tracks whose points in one frame lie within a search range of each other exchange their tails from that frame on when both then fit their own motion much better (chi-square about each track's fit, 100:1 likelihood)."),
    no_merge_pieces: bool = typer.Option(False, "--no-merge-pieces", help="Keep as separate tracks the pieces of one body: by default two tracks that touch in most of the frames they share (at least 3) and whose velocities agree within their uncertainty are merged into one track (an irregular particle the locator reported as two)."),
) -> None:
    """Link particles over frames into 3D tracks; velocities, accelerations, track-refined depth."""
    from .io import read_table, write_table
    from .track import TrackSettings, track_particles

    minimum = TrackSettings(order=order, window=64).min_window
    if window < minimum:
        raise typer.BadParameter(f"a fit of --order {order} needs at least {minimum} points; "
                                 f"got {window}", param_hint="--window")
    settings = TrackSettings(search_range_mm=(search_range, search_depth), memory=memory,
                             min_length=min_length, max_sigma_ratio=max_sigma_ratio,
                             window=window, order=order,
                             frame_interval_s=frame_interval, predict=not no_predict,
                             passes=1 if no_predict else 2, extend=not no_extend,
                             adapt_window=not fixed_window, merge_pieces=not no_merge_pieces,
                             repair_swaps=not no_repair_swaps)
    with _outputs({"--out": out_file, "--stats": stats_file},
                  {"PARTICLES": particles_file}) as (out_tmp, stats_tmp):
        t0 = time.perf_counter()
        result = track_particles(read_table(particles_file), settings)
        write_table(result.tracks, out_tmp)
        if stats_tmp is not None:
            write_table(result.statistics, stats_tmp)
    table = _quantity_table(f"tracks of {particles_file}")
    for name, value in result.summary().items():
        table.add_row(name, f"{value:.3g}" if isinstance(value, float) else f"{value}")
    out.print(table)
    console.print(f"{len(result.statistics)} tracks in {time.perf_counter() - t0:.2f} s; "
                  f"wrote {out_file}" + (f" and {stats_file}" if stats_file else ""),
                  highlight=False)


def _figure_outputs(png: Path) -> tuple[Path, Path]:
    """A PNG path and the PDF beside it (same name, suffix .pdf)."""
    if png.suffix.lower() != ".png":
        raise typer.BadParameter(f"must end in .png (a .pdf is written beside it); got {png}",
                                 param_hint="--out/--tracks-out")
    return png, png.with_suffix(".pdf")


@app.command()
@_reports_errors
def plot(
    table_file: Path = typer.Argument(..., help="Particle table (`locate`) or tracks table (`track`)."),
    out_file: Optional[Path] = typer.Option(Path("fragments.png"), "--out", "-o", help="Figure of one frame in the layout of the seed paper's Fig. 12 (PNG; a PDF is written beside it)."),
    tracks_out: Optional[Path] = typer.Option(None, "--tracks-out", help="Also a figure of the tracks coloured by speed (tracks table only; PNG and PDF)."),
    frame: Optional[int] = typer.Option(None, "--frame", help="Frame of the Fig. 12 figure (default: the frame with the most particles)."),
    raw: Optional[Path] = typer.Option(None, "--raw", help="Raw image of that frame: its central view is drawn under the outlines (needs --calib)."),
    calib_file: Optional[Path] = typer.Option(None, "--calib", help="Calibration file with a DLFC, to decode --raw and place the outlines."),
    raw_frame: int = typer.Option(0, "--raw-frame", help="Frame of a multi-page --raw TIFF."),
) -> None:
    """Draw the fragment-field figure (central view, top, side and isometric views) and tracks."""
    import matplotlib

    matplotlib.use("Agg")
    from .io import read_table
    from .plots import plot_fragment_field, plot_tracks

    if (raw is None) != (calib_file is None):
        raise typer.BadParameter("--raw and --calib go together", param_hint="--raw/--calib")
    outputs = {}
    if out_file is not None:
        outputs["--out"], outputs["--out (pdf)"] = _figure_outputs(out_file)
    if tracks_out is not None:
        outputs["--tracks-out"], outputs["--tracks-out (pdf)"] = _figure_outputs(tracks_out)
    if not outputs:
        raise typer.BadParameter("nothing to draw: give --out or --tracks-out")
    with _outputs(outputs, {"TABLE": table_file, "--raw": raw, "--calib": calib_file}) as tmps:
        targets = dict(zip(outputs, tmps))
        table = read_table(table_file)
        if tracks_out is not None and "particle" not in table.columns:
            raise typer.BadParameter(f"{table_file} has no tracks; run `plenoptrack track` first",
                                     param_hint="--tracks-out")
        if out_file is not None:
            if "frame" in table.columns and len(table):
                if frame is None:
                    frame = int(table["frame"].value_counts().idxmax())
                one = table[table["frame"] == frame]
                if len(one) == 0:
                    raise typer.BadParameter(f"no particles in frame {frame}", param_hint="--frame")
            else:
                one = table
            view = dlfc = None
            if raw is not None:
                from .calibration import load_calibration
                from .lightfield import decode

                calib = load_calibration(calib_file)
                dlfc = calib.dlfc
                view = decode(_load_frame(raw, raw_frame, calib), calib.grid).view(0, 0)
            fig = plot_fragment_field(one, view=view, dlfc=dlfc)
            fig.savefig(targets["--out"], dpi=150, format="png")
            fig.savefig(targets["--out (pdf)"], format="pdf")
        if tracks_out is not None:
            unit = "m/s" if "speed_m_per_s" in table.columns else "mm/frame"
            fig = plot_tracks(table, speed_unit=unit)
            fig.savefig(targets["--tracks-out"], dpi=150, format="png")
            fig.savefig(targets["--tracks-out (pdf)"], format="pdf")
    console.print("wrote " + ", ".join(str(p) for p in outputs.values()), highlight=False)


@app.command()
@_reports_errors
def report(
    table_file: Path = typer.Argument(..., help="Particle table (`locate`) or tracks table (`track`)."),
    out_file: Path = typer.Option(Path("report.html"), "--out", "-o", help="Self-contained HTML file (plotly.js embedded; opens without network)."),
    color_by: str = typer.Option("depth", "--color-by", help="Colour of the 3D view: depth or speed (tracks only)."),
    title: str = typer.Option("plenoptrack report", "--title", help="Page title."),
) -> None:
    """Write an interactive HTML report: rotatable 3D particles and tracks, summary table."""
    from .io import read_table
    from .report import report_html

    if color_by not in ("depth", "speed"):
        raise typer.BadParameter(f"must be 'depth' or 'speed'; got {color_by!r}",
                                 param_hint="--color-by")
    with _outputs({"--out": out_file}, {"TABLE": table_file}) as (tmp,):
        table = read_table(table_file)
        tmp.write_text(report_html(table, color_by=color_by, title=title,
                                   extra_rows=[("table", str(table_file))]), encoding="utf-8")
    console.print(f"wrote {out_file}", highlight=False)


@app.command()
@_reports_errors
def demo(
    out_dir: Path = typer.Option(Path("plenoptrack-demo"), "--out", "-o", help="Folder for the demo's files."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated scene."),
) -> None:
    """Run the whole pipeline on a small simulated scene and print a summary."""
    from .demo import run_demo

    from .io import check_outputs

    check_outputs({"--out": out_dir}, {}, folders=["--out"])
    summary = run_demo(out_dir, seed=seed, progress=True)
    table = Table(title="plenoptrack demo (simulated 'small' camera)")
    table.add_column("step")
    table.add_column("result", justify="right")
    table.add_column("seconds", justify="right")
    for step, result, seconds in summary.rows:
        table.add_row(step, result, f"{seconds:.2f}")
    out.print(table)
    console.print(f"files in {out_dir}")


def _unraisable(hook):
    """An unraisable-exception hook that turns a swallowed Ctrl-C into a pending interrupt,
    and keeps quiet about the compiler's half-built objects that such a Ctrl-C leaves to
    the garbage collector (their finalizers fail: an ``Exception ignored in ...
    ObjectRef.__del__`` traceback that says nothing to the user)."""

    def unraisable(info) -> None:
        if isinstance(info.exc_value, KeyboardInterrupt):
            from .io import note_lost_interrupt

            note_lost_interrupt()  # no traceback; the next commit of an output raises it
            return
        if getattr(info.object, "__module__", "").startswith("llvmlite."):
            return
        hook(info)

    return unraisable


def _excepthook(hook):
    """An exception hook that turns a Ctrl-C printed and dropped by compiled code into a
    pending interrupt, without its traceback.

    Cython functions that cannot raise (scipy's, while a module initialises) print the
    exception through :data:`sys.excepthook` before passing it to the unraisable hook;
    the command line's own handling of Ctrl-C never reaches this hook, so a
    ``KeyboardInterrupt`` here is always such a dropped one."""

    def excepthook(exc_type, exc_value, exc_tb) -> None:
        if issubclass(exc_type, KeyboardInterrupt):
            from .io import note_lost_interrupt

            note_lost_interrupt()
            return
        hook(exc_type, exc_value, exc_tb)

    return excepthook


def main() -> None:
    """Console entry point: run a command; a Ctrl-C once it has finished changes nothing."""
    import signal

    # Ctrl-C while numba compiles a kernel can land in a C callback, which prints and drops
    # the KeyboardInterrupt: record it instead, so that no output is committed after it.
    sys.unraisablehook = _unraisable(sys.unraisablehook)
    sys.excepthook = _excepthook(sys.excepthook)
    if not _choose_kernels(sys.argv[1:]):
        sys.exit(2)
    try:
        # The click command itself rather than ``app()``: Typer's ``__call__`` would put its
        # own exception hook in place of the one above.
        typer.main.get_command(app)()
    except SystemExit as exc:
        # The command is over and its outputs are committed (or it failed cleanly): ignore
        # a late Ctrl-C so that it cannot end the process by signal during shutdown.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if exc.code == 130:
            _exit_interrupted()
        raise
    except KeyboardInterrupt:  # between the command's end and the line above
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        _error_line(_interrupt_message())
        _exit_interrupted()


# Commands that run compiled kernels: they choose the kernel mode before numba is imported.
_KERNEL_COMMANDS = frozenset({"simulate", "calibrate-grid", "calibrate", "views", "refocus",
                              "locate", "batch", "study", "demo"})


def _choose_kernels(argv: list[str]) -> bool:
    """Set up the numba kernels for a command (see :mod:`plenoptrack._kernel_mode`).

    Returns False after printing one line when ``PLENOPTRACK_KERNELS`` is not a known mode.
    """
    from . import _kernel_mode

    setting = _kernel_mode.read_setting(os.environ)
    if setting not in _kernel_mode.MODES:
        _error_line(f"{_kernel_mode.ENV}={os.environ[_kernel_mode.ENV]!r} is not a kernel mode: "
                    f"set it to one of {', '.join(_kernel_mode.MODES)} or unset it")
        return False
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in _KERNEL_COMMANDS and not {"--help", "-h"} & set(argv):
        _kernel_mode.prepare()
    return True


def _exit_interrupted() -> None:
    """Exit with code 130 now, after a Ctrl-C that the command has handled.

    When the ``KeyboardInterrupt`` passed through code that the interpreter ran with
    ``PyRun_*`` (some compiled extensions do), the interpreter would end the process by
    SIGINT at shutdown whatever exit code was asked for. Cleanup has already run, so
    leave without the interpreter's shutdown.
    """
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(130)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
