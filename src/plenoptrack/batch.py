"""Many raw images: every frame located on worker processes or a Dask cluster, resumably.

A batch maps one per-frame locating function (chosen by name from :data:`METHODS`) over
the frames of many raw TIFF files and writes each frame's particles as its own Parquet
part in one output folder. It adds no science: a part holds exactly the rows
:func:`plenoptrack.locate.locate_frame` gives for that frame, with the same ``frame``
numbers ``plenoptrack locate`` would give the same files (their frames counted in order).

The output folder::

    results/
      frame-000000.parquet    one part per frame (empty table when no particle)
      frame-000001.parquet
      ...
      _batch.json             the run: method, settings, calibration, white image, version
      _failures.csv           frames that failed: frame, file, page, error, message

reads as one table with ``pandas.read_parquet("results/")`` or
``dask.dataframe.read_parquet("results/")`` (files starting with ``_`` or ``.`` are
skipped by pandas, and dask reads only ``*.parquet``), or with :func:`read_batch`, which
also sorts by frame. Every part
carries the run's provenance (:func:`plenoptrack.provenance.provenance`) in
``df.attrs["plenoptrack"]``, plus its own source file, page and resume key in the Parquet
schema metadata key ``plenoptrack.frame``.

Resuming: a frame is done when its part exists with the same *key*, a digest of the input
file's content (SHA-256), the page, the method, the settings
(:meth:`~plenoptrack.locate.PerspectiveLocator.digest`), the calibration file's and white
image's SHA-256 and the package version. Running the same batch again skips every done
frame (without re-reading it when the file's path, size and modification time are those
the part records) and locates the rest, so a killed batch resumes where it stopped. A part
is written to a hidden ``.frame-NNNNNN.parquet.*.partial`` file beside its target and
renamed into place, so a killed batch leaves no partial part (and no reader sees the
temporary); stale temporaries are removed by the next run. A frame that fails (unreadable or
truncated file, wrong size, any error of the locator) is recorded in
``_failures.csv`` and the batch goes on; a re-run retries it.

Execution: without a Dask client the frames run one after another in this process; with
one (:func:`local_cluster`, or ``distributed.Client("tcp://host:port")`` of any
``dask.distributed`` cluster: dask-jobqueue, dask-kubernetes...) each frame is one task.
A task receives only the file name and page and returns a short summary: the scheduler
never holds image data, the workers read the raw files and write the parts themselves
(so the input and output folders must be visible to every worker under the same path).
Each worker process loads the calibration and decodes the white image once and keeps them
(and numba's compiled kernels) for every later frame.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import hashlib
import json
import os
import re
import time
import uuid
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .errors import InputFileError, PlenoptrackError, UsageError

__all__ = ["METHODS", "FrameTask", "BatchConfig", "FrameOutcome", "BatchResult",
           "plan_frames", "batch_config", "locate_task", "run_batch", "read_batch",
           "read_failures", "local_cluster", "dashboard_link", "part_path", "frame_key",
           "BATCH_FILE", "FAILURES_FILE",
           "FAILURE_COLUMNS"]

BATCH_FILE = "_batch.json"
"""The run record of a batch folder (its provenance and run key)."""

FAILURES_FILE = "_failures.csv"
"""The failed frames of the last run of a batch folder (columns :data:`FAILURE_COLUMNS`)."""

FAILURE_COLUMNS = ("frame", "file", "page", "error", "message")
"""Columns of the failures table: global ``frame`` number, raw ``file``, ``page`` in it,
``error`` (exception type) and ``message``."""

_FRAME_META = b"plenoptrack.frame"
_PART = re.compile(r"^frame-(\d{6,})\.parquet$")
_TEMPORARY = re.compile(r"^\.(frame-\d{6,}\.parquet\..*\.partial|(_batch\.json|_failures\.csv)\..*\.tmp.*)$")


# --- methods: name -> function(image, calibration, *, frame, settings, white) -> DataFrame

def _locate_perspective(image: np.ndarray, calibration, *, frame: int, settings,
                        white) -> pd.DataFrame:
    """Particles of one frame by the perspective-shift method (:func:`locate_frame`)."""
    from .locate.perspective import locate_frame

    return locate_frame(image, calibration, frame=frame, locator=settings, white=white).particles


def _locate_refocus(image: np.ndarray, calibration, *, frame: int, settings,
                    white) -> pd.DataFrame:
    """Particles of one frame by the refocusing baseline (:func:`locate_frame_refocus`)."""
    from .locate.refocusing import locate_frame_refocus

    return locate_frame_refocus(image, calibration, frame=frame, locator=settings,
                                white=white).particles


def _locate_hybrid(image: np.ndarray, calibration, *, frame: int, settings,
                   white) -> pd.DataFrame:
    """Particles of one frame by the hybrid method (:func:`locate_frame_hybrid`)."""
    from .locate.refocusing import locate_frame_hybrid

    return locate_frame_hybrid(image, calibration, frame=frame, locator=settings,
                               white=white).particles


METHODS: dict[str, Callable[..., pd.DataFrame]] = {"perspective": _locate_perspective,
                                                   "refocus": _locate_refocus,
                                                   "hybrid": _locate_hybrid}
"""Locating methods by name. Each is a function ``(image, calibration, *, frame, settings,
white) -> particles DataFrame`` of one raw ``(rows, cols)`` frame, where ``settings`` is the
method's settings object (with ``to_dict()``) and ``white`` the decoded white image or
None."""


def _default_settings(method: str):
    if method == "perspective":
        from .locate import PerspectiveLocator

        return PerspectiveLocator()
    if method in ("refocus", "hybrid"):
        from .locate.refocusing import HybridLocator, RefocusLocator

        return RefocusLocator() if method == "refocus" else HybridLocator()
    raise UsageError(f"method must be one of {sorted(METHODS)}; got {method!r}")


# --- the plan ----------------------------------------------------------------------------

@dataclass(frozen=True)
class FrameTask:
    """One frame to locate.

    Attributes
    ----------
    frame : int
        Global frame number (the table's ``frame`` column): frames of the input files
        counted in order, as ``plenoptrack locate`` counts them.
    path : str
        Raw TIFF file, absolute.
    page : int
        Frame within the file (0 for a single-image file).
    """

    frame: int
    path: str
    page: int


def plan_frames(paths: Iterable[str | Path], *, threads: int = 8
                ) -> tuple[list[FrameTask], list[tuple[FrameTask, str, str]]]:
    """Number the frames of raw TIFF files in order.

    Parameters
    ----------
    paths : iterable of path
        Raw TIFF files, in the order their frames are numbered.
    threads : int
        Files whose headers are read at the same time (file-system latency).

    Returns
    -------
    tasks : list of FrameTask
        One per frame of every readable file.
    unreadable : list of (FrameTask, error, message)
        Files whose header cannot be read: each counts as one frame (page 0), recorded as
        failed.
    """
    from .io import count_frames

    paths = [str(Path(p).resolve()) for p in paths]

    def pages(path):
        try:
            return count_frames(path), None
        except PlenoptrackError as exc:
            return 1, exc

    with concurrent.futures.ThreadPoolExecutor(max(1, threads)) as pool:
        counts = list(pool.map(pages, paths))
    tasks, unreadable, frame = [], [], 0
    for path, (n, exc) in zip(paths, counts):
        for page in range(n):
            task = FrameTask(frame=frame, path=path, page=page)
            if exc is None:
                tasks.append(task)
            else:
                unreadable.append((task, type(exc).__name__, str(exc)))
            frame += 1
    return tasks, unreadable


# --- the run's configuration (what every worker needs) ------------------------------------

@dataclass(frozen=True)
class BatchConfig:
    """Everything a worker needs to locate a frame of a batch; small and picklable.

    Attributes
    ----------
    out_dir : str
        Output folder, absolute.
    method : str
        Name in :data:`METHODS`.
    settings : object
        The method's settings (e.g. :class:`~plenoptrack.locate.PerspectiveLocator`).
    calibration_file : str
        Calibration file, absolute.
    white_file : str or None
        White image to flat-field every frame with, absolute, or None.
    record : dict
        Provenance record of the run, stored with every part.
    run_key : str
        Digest of method, settings, calibration, white image and package version.
    """

    out_dir: str
    method: str
    settings: object
    calibration_file: str
    white_file: str | None
    record: dict
    run_key: str


def batch_config(out_dir: str | Path, calibration_file: str | Path, *,
                 method: str = "perspective", settings=None,
                 white_file: str | Path | None = None) -> BatchConfig:
    """The configuration of a batch run.

    Parameters
    ----------
    out_dir : path
        Output folder.
    calibration_file : path
        Calibration file with a DLFC.
    method : str
        Name in :data:`METHODS`.
    settings : object, optional
        The method's settings; default its defaults.
    white_file : path, optional
        White image to divide every frame by (None: no flat-fielding).
    """
    from . import __version__
    from .calibration import load_calibration
    from .provenance import provenance

    if method not in METHODS:
        raise UsageError(f"method must be one of {sorted(METHODS)}; got {method!r}")
    settings = _default_settings(method) if settings is None else settings
    calibration_file = Path(calibration_file).resolve()
    calibration = load_calibration(calibration_file)
    calibration.dlfc  # refuse a calibration without a DLFC before any work
    white_file = None if white_file is None else Path(white_file).resolve()
    record = provenance(method=method, settings=settings.to_dict(), calibration=calibration,
                        calibration_file=calibration_file, white_file=white_file)
    digest = hashlib.sha256(json.dumps(settings.to_dict(), sort_keys=True,
                                       default=str).encode()).hexdigest()[:16]
    identity = {"method": method, "settings": digest,
                "calibration": record["calibration"]["sha256"],
                "white": None if white_file is None else record["flat_field"]["sha256"],
                "package_version": __version__}
    run_key = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:32]
    record = {**record, "batch": {"run_key": run_key, **identity}}
    return BatchConfig(out_dir=str(Path(out_dir).resolve()), method=method, settings=settings,
                       calibration_file=str(calibration_file),
                       white_file=None if white_file is None else str(white_file),
                       record=record, run_key=run_key)


def frame_key(file_sha256: str, page: int, run_key: str) -> str:
    """The resume key of one frame: its file's content, its page and the run."""
    text = f"{file_sha256}:{page}:{run_key}"
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def part_path(out_dir: str | Path, frame: int) -> Path:
    """The Parquet part of ``frame`` in a batch folder."""
    return Path(out_dir) / f"frame-{frame:06d}.parquet"


# --- one frame, on a worker ---------------------------------------------------------------

@dataclass(frozen=True)
class FrameOutcome:
    """What became of one frame (a task's whole return value: no image data).

    Attributes
    ----------
    frame, path, page
        As in :class:`FrameTask`.
    status : str
        ``"done"`` (located and written), ``"skipped"`` (its part was already there) or
        ``"failed"``.
    n_particles : int
        Particles written (0 unless done).
    seconds : float
        Wall-clock time of the task, s.
    cpu_seconds : float
        CPU time of the worker process during the task (all its threads), s.
    error, message : str
        Exception type and message of a failed frame.
    warnings : tuple of str
        Warnings the locator issued (other than "no particles"), one line each.
    no_particles : bool
        The frame was located and held no particle.
    """

    frame: int
    path: str
    page: int
    status: str
    n_particles: int = 0
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    error: str = ""
    message: str = ""
    warnings: tuple = ()
    no_particles: bool = False


def _part_info(path: Path) -> dict | None:
    """The frame record a part was written with, or None (missing or unreadable part)."""
    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(path).metadata or {}
        return json.loads(meta[_FRAME_META])
    except Exception:  # missing, truncated or foreign file: not done
        return None


@functools.lru_cache(maxsize=2)
def _worker_state(calibration_file: str, white_file: str | None):
    """The calibration and decoded white image, loaded once per worker process."""
    from .calibration import load_calibration
    from .io import read_raw
    from .lightfield import decode

    calibration = load_calibration(calibration_file)
    white = None
    if white_file is not None:
        image = read_raw(white_file)
        calibration.check_image(image, source=white_file)
        white = decode(image, calibration.grid)
    return calibration, white


def locate_task(task: FrameTask, config: BatchConfig) -> FrameOutcome:
    """Locate one frame of a batch and write its part (the function each task runs).

    Hashes the input file; if the frame's part already exists with the same key, does
    nothing (``"skipped"``). Otherwise reads the frame, locates it with the configured
    method and writes the part atomically. Any error becomes a ``"failed"`` outcome.
    """
    from .calibration import file_sha256
    from .errors import NoParticlesWarning
    from .io import read_frames

    t0, c0 = time.perf_counter(), time.process_time()
    base = dict(frame=task.frame, path=task.path, page=task.page)
    try:
        stat = os.stat(task.path)
        key = frame_key(file_sha256(task.path), task.page, config.run_key)
        target = part_path(config.out_dir, task.frame)
        info = _part_info(target)
        if info is not None and info.get("key") == key:
            return FrameOutcome(**base, status="skipped", seconds=time.perf_counter() - t0,
                                cpu_seconds=time.process_time() - c0)
        calibration, white = _worker_state(config.calibration_file, config.white_file)
        stack = read_frames(task.path)
        calibration.check_image(stack, source=task.path)
        if not 0 <= task.page < len(stack):
            raise InputFileError(f"{task.path}: has {len(stack)} frame(s); frame {task.page} "
                                 "does not exist (the file changed while the batch ran)")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            particles = METHODS[config.method](stack[task.page], calibration, frame=task.frame,
                                               settings=config.settings, white=white)
        empty = any(issubclass(w.category, NoParticlesWarning) for w in caught)
        notes = tuple(str(w.message).replace(f"frame {task.frame}: ", "", 1) for w in caught
                      if not issubclass(w.category, NoParticlesWarning))
        _write_part(particles, target, config.record,
                    {"key": key, "frame": task.frame, "file": task.path, "page": task.page,
                     "size": stat.st_size, "mtime_ns": stat.st_mtime_ns,
                     "run_key": config.run_key})
    except Exception as exc:
        return FrameOutcome(**base, status="failed", seconds=time.perf_counter() - t0,
                            cpu_seconds=time.process_time() - c0,
                            error=type(exc).__name__, message=" ".join(str(exc).split()))
    return FrameOutcome(**base, status="done", n_particles=len(particles),
                        seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0,
                        warnings=notes, no_particles=empty)


def _write_part(particles: pd.DataFrame, target: Path, record: dict, frame_info: dict) -> None:
    """Write one frame's table atomically, with the run's provenance and the frame record."""
    import tempfile

    import pyarrow as pa
    import pyarrow.parquet as pq

    from .io import METADATA_KEY, default_file_mode

    table = pa.Table.from_pandas(particles, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"PANDAS_ATTRS"] = json.dumps({METADATA_KEY: record}, default=str).encode()
    meta[_FRAME_META] = json.dumps(frame_info).encode()
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent)
    os.close(fd)
    try:
        pq.write_table(table.replace_schema_metadata(meta), tmp)
        os.chmod(tmp, default_file_mode())
        os.replace(tmp, target)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)


# --- the run ------------------------------------------------------------------------------

@dataclass(frozen=True)
class BatchResult:
    """Summary of a batch run.

    Attributes
    ----------
    out_dir : Path
        The batch folder.
    n_frames : int
        Frames of the inputs.
    done, skipped, failed : int
        Frames located in this run, already done before it, and failed.
    n_particles : int
        Particles of the frames located in this run.
    failures : DataFrame
        The failed frames, columns :data:`FAILURE_COLUMNS` (also in ``_failures.csv``).
    seconds : float
        Wall-clock time of the run, s.
    """

    out_dir: Path
    n_frames: int
    done: int
    skipped: int
    failed: int
    n_particles: int
    failures: pd.DataFrame
    seconds: float


def _failures_table(rows: list[FrameOutcome], record: dict) -> pd.DataFrame:
    from .io import METADATA_KEY

    df = pd.DataFrame({"frame": np.array([r.frame for r in rows], dtype=np.int64),
                       "file": pd.Series([r.path for r in rows], dtype=object),
                       "page": np.array([r.page for r in rows], dtype=np.int64),
                       "error": pd.Series([r.error for r in rows], dtype=object),
                       "message": pd.Series([r.message for r in rows], dtype=object)})
    df = df.sort_values("frame", kind="stable").reset_index(drop=True)
    df.attrs[METADATA_KEY] = record
    return df


def _prepare_folder(config: BatchConfig) -> None:
    """Create the batch folder or check that it holds this batch; remove stale temporaries."""
    from .io import atomic_write_text

    out = Path(config.out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: is a file; give a folder for the batch output")
    marker = out / BATCH_FILE
    if marker.is_file():
        try:
            previous = json.loads(marker.read_text())
            previous_key = previous["batch"]["run_key"]
        except (ValueError, KeyError, TypeError):
            raise InputFileError(f"{marker}: not a readable batch record; give a new output "
                                 "folder") from None
        if previous_key != config.run_key:
            names = {"white": "white image", "package_version": "package version"}
            changed = [names.get(k, k) for k, v in config.record["batch"].items()
                       if k != "run_key" and previous["batch"].get(k) != v]
            raise UsageError(
                f"{out}: holds a batch made with a different {', '.join(changed) or 'run'} "
                "(its parts would not form one table); give a new output folder, or the "
                "settings, calibration and white image of that batch to resume it")
    elif out.is_dir() and any(not p.name.startswith(".") for p in out.iterdir()):
        raise UsageError(f"{out}: is not empty and holds no batch ({BATCH_FILE}); give a new "
                         "or empty folder for the batch output")
    out.mkdir(parents=True, exist_ok=True)
    for stale in out.iterdir():
        if _TEMPORARY.match(stale.name):
            stale.unlink(missing_ok=True)
    if not marker.is_file():
        atomic_write_text(marker, json.dumps(config.record, indent=1, default=str) + "\n")


def _done_frames(config: BatchConfig, tasks: Sequence[FrameTask], *, threads: int = 8
                 ) -> tuple[set[int], list[int]]:
    """Frames whose part records this run, this file and page, and the file's current size
    and modification time (done without re-reading the file); and the part numbers that
    belong to no frame of the plan."""
    out = Path(config.out_dir)
    parts = {int(m.group(1)): out / name for name in os.listdir(out)
             if (m := _PART.match(name))}
    by_frame = {t.frame: t for t in tasks}
    wanted = sorted(f for f in parts if f in by_frame)

    def check(frame: int) -> bool:
        info = _part_info(parts[frame])
        task = by_frame[frame]
        if info is None or info.get("run_key") != config.run_key:
            return False
        if info.get("file") != task.path or info.get("page") != task.page:
            return False
        try:
            stat = os.stat(task.path)
        except OSError:
            return False
        return info.get("size") == stat.st_size and info.get("mtime_ns") == stat.st_mtime_ns

    with concurrent.futures.ThreadPoolExecutor(max(1, threads)) as pool:
        ok = list(pool.map(check, wanted))
    done = {f for f, good in zip(wanted, ok) if good}
    extra = sorted(f for f in parts if f not in by_frame)
    return done, extra


def _serial(tasks: Sequence[FrameTask], config: BatchConfig):
    for task in tasks:
        yield locate_task(task, config)


def _identity(value):
    return value


def _on_cluster(client, tasks: Sequence[FrameTask], config: BatchConfig):
    """Run every task on a Dask cluster; yield the outcomes as they complete.

    The configuration is one small task of its own that every frame depends on (fetched
    by each worker once, recomputed if its holders die); a frame's task that dies with
    its worker too often (``KilledWorker``) becomes a failed frame.
    """
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    shared = client.submit(_identity, config, key=f"batch-config-{token}", pure=False)
    futures = client.map(locate_task, list(tasks), config=shared, pure=False,
                         key=[f"locate-frame-{t.frame:06d}-{token}" for t in tasks])
    by_key = {f.key: t for f, t in zip(futures, tasks)}
    try:
        for future in as_completed(futures):
            task = by_key[future.key]
            try:
                outcome = future.result()
            except Exception as exc:
                outcome = FrameOutcome(frame=task.frame, path=task.path, page=task.page,
                                       status="failed", error=type(exc).__name__,
                                       message=" ".join(str(exc).split()))
            future.release()
            yield outcome
    finally:
        client.cancel(futures + [shared])


def run_batch(inputs: Iterable[str | Path], calibration_file: str | Path,
              out_dir: str | Path, *, method: str = "perspective", settings=None,
              white_file: str | Path | None = None, client=None, progress: bool = False,
              on_outcome: Callable[[FrameOutcome], None] | None = None) -> BatchResult:
    """Locate every frame of many raw images into a resumable batch folder.

    Parameters
    ----------
    inputs : iterable of path
        Raw TIFF files (multi-page: several frames), numbered in this order.
    calibration_file : path
        Calibration file with a DLFC.
    out_dir : path
        Batch folder: new, empty, or one this batch (same method, settings, calibration,
        white image and package version) wrote before, which is then resumed.
    method : str
        Name in :data:`METHODS`.
    settings : object, optional
        The method's settings (default its defaults).
    white_file : path, optional
        White image to divide every frame by (flat-fielding); None: none.
    client : distributed.Client, optional
        Dask client to run the frames on; None runs them one by one in this process.
    progress : bool
        Show a progress bar (rate and time left) on stderr.
    on_outcome : callable, optional
        Called with each :class:`FrameOutcome` as it arrives (skipped frames included).

    Returns
    -------
    BatchResult

    Notes
    -----
    The folder reads as one table with :func:`read_batch`; the failed frames are in
    :func:`read_failures`. Run one batch per folder at a time.
    """
    from .io import write_table

    t0 = time.perf_counter()
    config = batch_config(out_dir, calibration_file, method=method, settings=settings,
                          white_file=white_file)
    tasks, unreadable = plan_frames(inputs)
    n_frames = len(tasks) + len(unreadable)
    _prepare_folder(config)
    done_before, extra = _done_frames(config, tasks)
    if extra:
        warnings.warn(f"{config.out_dir}: {len(extra)} part(s) of frame(s) beyond this run's "
                      f"{n_frames} (e.g. frame {extra[0]}) are kept and read with the table",
                      stacklevel=2)
    failures = [FrameOutcome(frame=t.frame, path=t.path, page=t.page, status="failed",
                             error=err, message=" ".join(msg.split()))
                for t, err, msg in unreadable]
    todo = [t for t in tasks if t.frame not in done_before]
    counts = {"done": 0, "skipped": len(done_before), "failed": 0}
    n_particles = 0
    failures_path = Path(config.out_dir) / FAILURES_FILE
    write_table(_failures_table(failures, config.record), failures_path)
    with _progress_bar(progress, total=n_frames, completed=n_frames - len(todo)) as advance:
        for outcome in failures:
            counts["failed"] += 1
            if on_outcome is not None:
                on_outcome(outcome)
        runner = _serial(todo, config) if client is None else _on_cluster(client, todo, config)
        for outcome in runner:
            counts[outcome.status] += 1
            n_particles += outcome.n_particles
            if outcome.status == "failed":
                failures.append(outcome)
                write_table(_failures_table(failures, config.record), failures_path)
            if on_outcome is not None:
                on_outcome(outcome)
            advance()
    for stale in Path(config.out_dir).iterdir():  # left by a worker killed mid-write
        if _TEMPORARY.match(stale.name) and stale.name.endswith(".partial"):
            stale.unlink(missing_ok=True)
    return BatchResult(out_dir=Path(config.out_dir), n_frames=n_frames, done=counts["done"],
                       skipped=counts["skipped"], failed=counts["failed"],
                       n_particles=n_particles,
                       failures=_failures_table(failures, config.record),
                       seconds=time.perf_counter() - t0)


@contextlib.contextmanager
def _progress_bar(show: bool, *, total: int, completed: int):
    """Yield a function that advances a progress bar by one frame (a no-op when hidden)."""
    if not show:
        yield lambda: None
        return
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)

    class _Rate(TextColumn):
        def render(self, task):
            from rich.text import Text

            speed = task.finished_speed or task.speed
            return Text("" if speed is None else f"{speed:.2f} frames/s")

    with Progress(TextColumn("locating"), BarColumn(), MofNCompleteColumn(), _Rate(""),
                  TimeElapsedColumn(), TextColumn("left"), TimeRemainingColumn(),
                  console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("locating", total=total, completed=completed)  # rate: this run's
        yield lambda: bar.advance(task)


# --- reading a batch folder ---------------------------------------------------------------

def read_batch(out_dir: str | Path) -> pd.DataFrame:
    """Read a batch folder as one particle table, sorted by frame.

    Returns
    -------
    DataFrame
        The rows of every part in frame order (within a frame, in the locator's order),
        with the run's provenance in ``df.attrs["plenoptrack"]``. Same as
        ``pandas.read_parquet(out_dir)`` up to the row order.
    """
    from .io import METADATA_KEY

    out = Path(out_dir)
    names = sorted((int(m.group(1)), name) for name in os.listdir(out) if (m := _PART.match(name)))
    if not names:
        raise InputFileError(f"{out}: holds no batch part (frame-NNNNNN.parquet); run "
                             "`plenoptrack batch` first")
    tables = [pd.read_parquet(out / name) for _, name in names]
    df = pd.concat(tables, ignore_index=True)
    record = json.loads((out / BATCH_FILE).read_text()) if (out / BATCH_FILE).is_file() else None
    df.attrs = {METADATA_KEY: record} if record is not None else dict(tables[0].attrs)
    return df


def read_failures(out_dir: str | Path) -> pd.DataFrame:
    """The failures table of a batch folder (columns :data:`FAILURE_COLUMNS`)."""
    from .io import read_table

    return read_table(Path(out_dir) / FAILURES_FILE)


# --- a cluster on this machine ------------------------------------------------------------

def local_cluster(n_workers: int, *, memory_limit: str | int = "3GB"):
    """A Dask cluster of ``n_workers`` worker processes on this machine (loopback).

    Parameters
    ----------
    n_workers : int
        Worker processes; each runs one frame at a time.
    memory_limit : str or int
        Memory bound of each worker (bytes or e.g. ``"3GB"``): a worker above 95 % of it
        is restarted and its frame retried.

    Returns
    -------
    distributed.LocalCluster

    Notes
    -----
    The scheduler's web server (the dashboard, when ``bokeh`` is installed) listens on a
    free port (:func:`dashboard_link`). Numba's threads in each worker are set to the machine's cores divided by the
    workers (at least one), so that workers do not oversubscribe the cores.
    """
    import logging

    from distributed import LocalCluster

    if n_workers < 1:
        raise UsageError(f"n_workers must be at least 1; got {n_workers}")
    threads = str(max(1, (os.cpu_count() or 1) // n_workers))
    env = {"NUMBA_NUM_THREADS": threads, "OMP_NUM_THREADS": threads,
           "OPENBLAS_NUM_THREADS": threads, "MKL_NUM_THREADS": threads}
    return LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                        host="127.0.0.1", dashboard_address=":0",
                        memory_limit=memory_limit, silence_logs=logging.ERROR, env=env)


def _has_bokeh() -> bool:
    import importlib.util

    return importlib.util.find_spec("bokeh") is not None


def dashboard_link(client) -> str | None:
    """The Dask dashboard address of a client's cluster, or None when it serves none
    (no web server, or no ``bokeh`` on the scheduler to draw it)."""
    try:
        if "dashboard" not in client.scheduler_info().get("services", {}):
            return None
        return client.dashboard_link if client.run_on_scheduler(_has_bokeh) else None
    except Exception:
        return None
