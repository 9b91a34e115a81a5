"""Reading and writing the files of the plenoptrack file contract.

Raw images are single-channel uint16 TIFF (a multi-page TIFF holds several frames);
tables are Parquet, or CSV when the path ends in ``.csv``. Every writer is atomic: it
writes a temporary file beside the target and renames it, so a failed run never leaves a
half-written result. Every reader turns a bad file into an :class:`InputFileError` that
names the file and says what to do.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
import threading
import warnings
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import ExposureWarning, ImageSizeError, InputFileError, OutputConflictError

__all__ = [
    "check_outputs", "staged_outputs", "atomic_path", "atomic_folder", "atomic_write_text",
    "default_file_mode", "interrupts_deferred", "exposure_problem", "warn_exposure", "read_raw", "read_frames", "count_frames",
    "write_tiff", "read_table", "write_table", "check_image_shape", "METADATA_KEY",
]


# --- safe writing -------------------------------------------------------------------
#
# A user's data is never destroyed: an output may not be one of the inputs, a file is
# written beside its target and renamed over it only when complete, several outputs of
# one command are committed together, and a folder (a simulated data set) is built beside
# its target and swapped in whole. Ctrl-C is held back during the renames themselves.


def _umask() -> int:
    mask = os.umask(0o022)  # the only way to read it is to set it
    os.umask(mask)
    return mask


def default_file_mode() -> int:
    """Permission bits a newly created file gets from the process umask (e.g. 0o644)."""
    return 0o666 & ~_umask()


_lost_interrupts: list[int] = []


def note_lost_interrupt() -> None:
    """Record a Ctrl-C that compiled or C code swallowed instead of raising it.

    A ``KeyboardInterrupt`` raised inside a C callback (llvmlite calls back into Python
    while numba compiles a kernel) is printed and ignored by the C caller, so the command
    would run on and commit its outputs as if the user had not pressed Ctrl-C. The command
    line records such interrupts here (from :data:`sys.unraisablehook`); every commit of an
    output raises the ``KeyboardInterrupt`` instead of committing.
    """
    _lost_interrupts.append(signal.SIGINT)


def _raise_lost_interrupt() -> None:
    if _lost_interrupts:
        raise KeyboardInterrupt


_committed: list[Path] = []
_staging = threading.local()  # .depth: how many staged outputs enclose the current code


@contextlib.contextmanager
def _staging_level() -> Iterator[bool]:
    """Yield whether this staged output is the outermost one (the user's, not a helper's)."""
    depth = getattr(_staging, "depth", 0)
    _staging.depth = depth + 1
    try:
        yield depth == 0
    finally:
        _staging.depth = depth


def committed_outputs() -> list[Path]:
    """Outputs committed (renamed into place, complete) since :func:`forget_committed_outputs`.

    A Ctrl-C that arrives while, or just after, a command commits its outputs ends the
    command with the new outputs already in place; the command line names them in its
    message instead of claiming that nothing was kept.
    """
    return list(_committed)


def forget_committed_outputs() -> None:
    """Start a new record for :func:`committed_outputs` (at the start of each command)."""
    _committed.clear()


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back Ctrl-C (SIGINT) for the body, then raise the ``KeyboardInterrupt``.

    Used around the few renames that commit an output, so that an interrupt cannot leave
    a half-committed set of files. Only possible in the main thread; elsewhere the body
    runs unprotected.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if received:
            if callable(previous):
                previous(signal.SIGINT, None)
            elif previous == signal.SIG_DFL:
                raise KeyboardInterrupt


def _same_path(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name the same file (symbolic and hard links included)."""
    try:
        if os.path.samefile(a, b):
            return True
    except OSError:
        pass
    return Path(os.path.realpath(a)) == Path(os.path.realpath(b))


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` lies inside ``folder`` (after resolving links)."""
    path, folder = Path(os.path.realpath(path)), Path(os.path.realpath(folder))
    return folder in path.parents


def _as_paths(value) -> list[Path]:
    if value is None:
        return []
    if isinstance(value, (str, os.PathLike)):
        return [Path(value)]
    return [Path(v) for v in value if v is not None]


def check_outputs(outputs: Mapping[str, str | Path | None],
                  inputs: Mapping[str, object] | None = None, *,
                  folders: Iterable[str] = ()) -> None:
    """Refuse outputs that would overwrite an input, each other, or a folder.

    Parameters
    ----------
    outputs : mapping of str to path or None
        Output paths by the name the user knows them under (e.g. ``"--out"``); None
        entries are skipped.
    inputs : mapping of str to path, sequence of paths or None, optional
        Input files or folders by name.
    folders : iterable of str
        Names in ``outputs`` that are folders written as a unit (e.g. a simulated data
        set): no input may lie inside them.

    Raises
    ------
    OutputConflictError
        An output is the same file as an input (symbolic and hard links included), two
        outputs are the same file, a folder output holds an input, or a file output is
        an existing folder.
    """
    folders = set(folders)
    named_inputs = [(name, p) for name, value in (inputs or {}).items() for p in _as_paths(value)]
    seen: list[tuple[str, Path]] = []
    for name, value in outputs.items():
        if value is None:
            continue
        out = Path(value)
        for in_name, inp in named_inputs:
            if _same_path(out, inp):
                raise OutputConflictError(
                    f"{out}: {name} is also the input {in_name}; writing it would destroy the "
                    "input. Give the output another name")
            if name in folders and _inside(inp, out):
                raise OutputConflictError(
                    f"{out}: {name} would replace a folder holding the input {in_name} "
                    f"({inp}); write the output to another folder")
        for other_name, other in seen:
            if _same_path(out, other):
                raise OutputConflictError(f"{out}: given for both {other_name} and {name}; "
                                          "give each output its own file")
        if name not in folders and out.is_dir():
            raise OutputConflictError(f"{out}: {name} is a folder; give a file name for the output")
        if name in folders and out.exists() and not out.is_dir():
            raise OutputConflictError(f"{out}: {name} is a file; give a folder for the output")
        seen.append((name, out))


def _make_parents(path: Path) -> list[Path]:
    """Create the missing parent folders of ``path``; return those created, outermost first."""
    missing = []
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        missing.append(parent)
        parent = parent.parent
    created = []
    for folder in reversed(missing):
        folder.mkdir()
        created.append(folder)
    return created


def _remove_empty(folders: Iterable[Path]) -> None:
    for folder in sorted(folders, key=lambda f: len(f.parts), reverse=True):
        with contextlib.suppress(OSError):
            folder.rmdir()


def _temporary_beside(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    return Path(tmp)


def _commit(pairs: list[tuple[Path, Path]], *, outermost: bool) -> None:
    """Rename every temporary onto its target; on any failure restore every old target.

    ``outermost`` records the targets for :func:`committed_outputs` (a file written into
    another output's temporary is not one of the user's outputs).
    """
    mode = default_file_mode()
    backups: list[tuple[Path, Path | None]] = []
    _raise_lost_interrupt()
    with interrupts_deferred():
        try:
            for tmp, target in pairs:
                os.chmod(tmp, mode)
                backup = None
                if target.exists():
                    backup = _temporary_beside(target)
                    os.replace(target, backup)
                backups.append((target, backup))
                os.replace(tmp, target)
            if outermost:
                _committed.extend(target for _, target in pairs)
        except BaseException:
            for target, backup in reversed(backups):
                if backup is not None:
                    os.replace(backup, target)
                else:
                    target.unlink(missing_ok=True)
            raise
        for _, backup in backups:
            if backup is not None:
                backup.unlink(missing_ok=True)


@contextlib.contextmanager
def staged_outputs(*targets: str | Path | None) -> Iterator[list[Path | None]]:
    """Write several output files as one: all are replaced, or none is touched.

    Yields one temporary path beside each target (None for a None target) after creating
    them, so an unwritable location fails before any work. When the body succeeds every
    temporary is renamed onto its target (old targets are restored if a rename fails);
    when it raises, or on Ctrl-C, the temporaries and any folder created for them are
    removed and existing targets stay as they were. Files get the umask's usual mode.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> with staged_outputs(folder / "a.txt", None, folder / "b.txt") as (a, none, b):
    ...     _ = a.write_text("A"); _ = b.write_text("B")
    >>> sorted(p.name for p in folder.iterdir())
    ['a.txt', 'b.txt']
    """
    paths = [None if t is None else Path(t) for t in targets]
    created: list[Path] = []
    temporaries: list[Path] = []
    try:
        # held back so that Ctrl-C cannot land between a temporary's creation and its
        # entry in the list the cleanup below removes
        with interrupts_deferred():
            for path in paths:
                if path is not None:
                    created += _make_parents(path)
                    temporaries.append(_temporary_beside(path))
        staged = iter(temporaries)
        with _staging_level() as outermost:
            yield [None if p is None else next(staged) for p in paths]
        _commit([(tmp, p) for tmp, p in zip(temporaries, [p for p in paths if p is not None])],
                outermost=outermost)
    finally:
        with interrupts_deferred():
            for tmp in temporaries:
                tmp.unlink(missing_ok=True)
            _remove_empty(created)  # only those left empty by a failure


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The parent folder is created if needed. If the body raises, the temporary file (and
    any folder created for it) is removed and ``path`` is left as it was. The file gets
    the usual mode of the process umask.
    """
    with staged_outputs(path) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_folder(path: str | Path) -> Iterator[Path]:
    """Build a folder beside ``path`` and swap it in whole when the body succeeds.

    Parameters
    ----------
    path : str or Path
        Folder to write. An existing folder is replaced as a unit, only on success: the
        caller must have checked that nothing else in it needs keeping.

    Yields
    ------
    Path
        An empty temporary folder beside ``path`` to write into.

    Notes
    -----
    On failure or Ctrl-C the temporary folder is removed and ``path`` is untouched. The
    swap is two renames with Ctrl-C held back between them.
    """
    path = Path(path)
    created = _make_parents(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    committed = False
    try:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it 0700
        with _staging_level() as outermost:
            yield tmp
        _raise_lost_interrupt()
        with interrupts_deferred():
            old = None
            if path.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
                os.replace(path, old / path.name)
            try:
                os.replace(tmp, path)
            except BaseException:
                if old is not None:
                    os.replace(old / path.name, path)
                raise
            committed = True
            if outermost:
                _committed.append(path)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
    finally:
        if not committed:
            with interrupts_deferred():
                shutil.rmtree(tmp, ignore_errors=True)
                _remove_empty(created)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def _open_tiff(path: Path):
    import tifffile

    if not path.exists():
        raise InputFileError(f"{path}: file not found; check the path")
    if path.is_dir():
        raise InputFileError(f"{path}: is a folder, expected a TIFF image file")
    try:
        return tifffile.TiffFile(path)
    except Exception as exc:  # tifffile raises many kinds (struct.error, ValueError...) on bad bytes
        raise InputFileError(f"{path}: not a readable TIFF image ({exc}); "
                             "save raw images as single-channel uint16 TIFF") from None


def _refuse_colour(tif, path: Path) -> None:
    """Raise :class:`InputFileError` for a colour (RGB, palette, several samples) TIFF."""
    page = tif.pages[0] if len(tif.pages) else None
    if page is None:
        raise InputFileError(f"{path}: TIFF holds no image; save raw images as single-channel "
                             "uint16 TIFF")
    samples = int(getattr(page, "samplesperpixel", 1) or 1)
    photometric = getattr(getattr(page, "photometric", None), "name", "")
    # Samples stored as separate planes are how tifffile writes a stack of 3 or 4 greyscale
    # frames by default; they are read as frames. Interleaved samples are a colour image.
    planar = getattr(getattr(page, "planarconfig", None), "name", "") == "SEPARATE"
    if (samples > 1 and not planar) or photometric in ("PALETTE", "YCBCR", "CIELAB"):
        kind = {"PALETTE": "palette"}.get(photometric, f"{samples}-channel ({photometric or 'colour'})")
        raise InputFileError(
            f"{path}: is a {kind} colour image; plenoptrack needs the camera's raw "
            "single-channel (greyscale) uint16 sensor image, not a colour rendering: export "
            "the raw frame from the camera software")


def read_frames(path: str | Path) -> np.ndarray:
    """Read every frame of a raw TIFF.

    Parameters
    ----------
    path : str or Path
        Single- or multi-page single-channel uint16 TIFF.

    Returns
    -------
    frames : (n_frames, rows, cols) uint16 ndarray
        Raw sensor counts; pixel (row, col) centres at integer coordinates.
    """
    path = Path(path)
    with _open_tiff(path) as tif:
        try:
            _refuse_colour(tif, path)
            data = tif.asarray()
        except InputFileError:
            raise
        except Exception as exc:  # tifffile raises many kinds on truncated data
            raise InputFileError(f"{path}: TIFF data could not be read, the file may be "
                                 f"truncated ({type(exc).__name__}: {exc})") from None
    if data.dtype != np.uint16:
        raise InputFileError(f"{path}: raw images must be uint16; got {data.dtype}. "
                             "Convert with e.g. tifffile.imwrite(path, img.astype('uint16'))")
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3:
        raise InputFileError(f"{path}: expected a single-channel image or a stack of them; "
                             f"got an array of shape {data.shape}")
    return data


def read_raw(path: str | Path, *, frame: int = 0) -> np.ndarray:
    """Read one raw frame, ``(rows, cols)`` uint16, from a TIFF file."""
    frames = read_frames(path)
    if not -len(frames) <= frame < len(frames):
        raise InputFileError(f"{path}: has {len(frames)} frame(s); frame {frame} does not exist")
    return frames[frame]


def count_frames(path: str | Path) -> int:
    """Number of frames (pages) in a TIFF without reading the pixels."""
    path = Path(path)
    with _open_tiff(path) as tif:
        try:
            _refuse_colour(tif, path)
            shape = tif.series[0].shape
        except InputFileError:
            raise
        except Exception as exc:
            raise InputFileError(f"{path}: TIFF header could not be read, the file may be "
                                 f"truncated ({type(exc).__name__}: {exc})") from None
        return shape[0] if len(shape) == 3 else 1


ZLIB_LEVEL = 1
"""Deflate level of the zlib-compressed TIFFs :func:`write_tiff` writes. Sensor noise
leaves little for a higher level to find: on a simulated full-sensor ``hall2019`` dot-card
image (realistic optics), zlib's default level (6) wrote a file 0.7 % smaller in 2.2 times
the time: 4.4 against 2.0 s (``benchmarks/bench_simulate.py --tiff``)."""


def write_tiff(path: str | Path, image: np.ndarray, *, compression: str | None = "zlib") -> Path:
    """Write a ``(rows, cols)`` image or ``(n, rows, cols)`` stack as TIFF, atomically.

    ``compression`` is ``"zlib"`` (deflate at :data:`ZLIB_LEVEL`), None, or another
    name :func:`tifffile.imwrite` knows (at its default level)."""
    import tifffile

    image = np.asarray(image)
    level = {"compressionargs": {"level": ZLIB_LEVEL}} if compression == "zlib" else {}
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, image, compression=compression, photometric="minisblack",
                         **level)
    return Path(path)


BLACK_FRACTION = 0.02
"""A raw frame with 99 % of its pixels below this fraction of full scale is black."""

SATURATED_FRACTION = 0.5
"""A raw frame with more than this fraction of its pixels at full scale is saturated."""


def exposure_problem(image: np.ndarray, full_scale: int) -> str | None:
    """Say whether a raw frame is black or saturated, and so cannot show particles.

    Parameters
    ----------
    image : (rows, cols) ndarray
        Raw sensor counts.
    full_scale : int
        Largest raw value of the camera, counts (``CameraSpec.full_scale``).

    Returns
    -------
    str or None
        ``"black"`` when 99 % of the pixels are below :data:`BLACK_FRACTION` of full
        scale (no back-light, lens cap, missed trigger), ``"saturated"`` when more than
        :data:`SATURATED_FRACTION` of the pixels are at full scale (over-exposed), else
        None. A back-lit particle image is bright almost everywhere, so neither happens
        in a usable frame.
    """
    sample = np.asarray(image)[::3, ::3]  # a lattice of pixels is enough for a fraction
    if sample.size == 0:
        return None
    # a count, not a percentile: no sort of millions of pixels for every frame
    if np.count_nonzero(sample < BLACK_FRACTION * full_scale) >= 0.99 * sample.size:
        return "black"
    if np.count_nonzero(sample >= full_scale) > SATURATED_FRACTION * sample.size:
        return "saturated"
    return None


def warn_exposure(image: np.ndarray, full_scale: int, *, source: str = "raw frame") -> str | None:
    """Issue an :class:`ExposureWarning` if :func:`exposure_problem` finds one; return it."""
    problem = exposure_problem(image, full_scale)
    if problem == "black":
        warnings.warn(f"{source}: the frame is black (99 % of pixels below "
                      f"{BLACK_FRACTION:.0%} of full scale): no back-light reached the sensor, "
                      "so no particle can be found; check the light source and trigger",
                      ExposureWarning, stacklevel=2)
    elif problem == "saturated":
        warnings.warn(f"{source}: the frame is saturated (over {SATURATED_FRACTION:.0%} of "
                      f"pixels at full scale {full_scale}): particles are washed out; shorten "
                      "the exposure or dim the back-light", ExposureWarning, stacklevel=2)
    return problem


def check_image_shape(image: np.ndarray, expected: tuple[int, int], *, source: str = "image",
                      what: str = "the camera description") -> None:
    """Raise :class:`ImageSizeError` if ``image.shape[-2:]`` differs from ``expected``."""
    if tuple(image.shape[-2:]) != tuple(expected):
        raise ImageSizeError(
            f"{source}: image is {image.shape[-2]} x {image.shape[-1]} pixels but {what} "
            f"expects {expected[0]} x {expected[1]}; use the matching camera or calibration")


METADATA_KEY = "plenoptrack"
"""Key of a table's provenance in ``DataFrame.attrs`` (settings, calibration, package
version; see :func:`plenoptrack.provenance.provenance`)."""

_CSV_METADATA_PREFIX = "# plenoptrack-metadata: "


def read_table(path: str | Path) -> pd.DataFrame:
    """Read a Parquet table, or CSV when the path ends in ``.csv``.

    The provenance a table was written with (:func:`write_table`) comes back in
    ``df.attrs["plenoptrack"]``: Parquet keeps it in the file's schema metadata, CSV in a
    first comment line ``# plenoptrack-metadata: {json}``.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(f"{path}: table not found; check the path")
    try:
        if path.suffix.lower() == ".csv":
            meta = _csv_metadata(path)
            df = pd.read_csv(path, comment="#" if meta is not None else None)
            if meta is not None:
                df.attrs[METADATA_KEY] = meta
            return df
        return pd.read_parquet(path)
    except Exception as exc:
        kind = "CSV" if path.suffix.lower() == ".csv" else "Parquet"
        raise InputFileError(f"{path}: not a readable {kind} table ({type(exc).__name__}: {exc})") from None


def _csv_metadata(path: Path) -> dict | None:
    """The provenance of a CSV table from its first comment line, or None."""
    with open(path, encoding="utf-8", errors="replace") as f:
        first = f.readline()
    if not first.startswith(_CSV_METADATA_PREFIX):
        return None
    return json.loads(first[len(_CSV_METADATA_PREFIX):])


def write_table(df: pd.DataFrame, path: str | Path) -> Path:
    """Write ``df`` atomically as Parquet, or CSV when the path ends in ``.csv``.

    ``df.attrs["plenoptrack"]`` (the provenance of the table), if present, is stored with
    it: in the Parquet schema metadata, or as a first comment line of a CSV file
    (``pandas.read_csv(path, comment="#")`` skips it).
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.suffix.lower() == ".csv":
            with open(tmp, "w", encoding="utf-8", newline="") as f:
                meta = df.attrs.get(METADATA_KEY)
                if meta is not None:
                    f.write(_CSV_METADATA_PREFIX + json.dumps(meta, default=str) + "\n")
                df.to_csv(f, index=False)
        else:
            df.to_parquet(tmp, index=False)
    return path
