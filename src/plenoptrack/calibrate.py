"""The calibration workflow: white image and dot cards to a calibration file.

Two measurements make up the calibration of one camera set-up:

1. the **lenslet grid** (microlens-image centres) from a white image
   (:func:`plenoptrack.calibration.calibrate_from_white`);
2. the **Direct Light Field Calibration** (DLFC) from dot-card images at known depths:
   every card is decoded into a light field, its dots are found and indexed in every view
   (:func:`plenoptrack.locate.dotcards.dotcard_points`), and the polynomials
   ``(s, t) = P(x, y, z, u, v)`` are fitted to all cards at once with robust rejection
   of mis-measured dots (:func:`plenoptrack.locate.dlfc.fit_dlfc`).

:func:`calibrate` does both and returns a :class:`~plenoptrack.calibration.Calibration`
holding the grid and the DLFC (write it with
:func:`~plenoptrack.calibration.save_calibration`) and a :class:`CalibrationReport`.

Dot-card folder (file contract of ``DESIGN.md``)::

    dotcards/
      dotcards.toml        spacing_mm, [dot_diameter_mm], [[cards]] file + z_mm
      card_00.tif ...      one uint16 TIFF per card depth

``dotcards.toml``::

    spacing_mm = 1.25           # dot (m, n) sits at world (x, y) = (m, n) * spacing_mm
    dot_diameter_mm = 0.4       # optional, for the record
    cards = [
        { file = "card_00.tif", z_mm = -10.0 },
        { file = "card_01.tif", z_mm = -8.0 },
    ]

Card files are relative to the folder of ``dotcards.toml``. Dot ``(0, 0)`` lies on the
optical axis; ``z`` is the world depth of the card, mm (0 at the nominal focal plane,
positive away from the camera; ``docs/conventions.md``).

References
----------
Hall et al., Volumetric calibration of a plenoptic camera (Applied Optics, 2018): the
DLFC and its dot-card procedure.
"""

from __future__ import annotations

import contextlib
import math
import time
import tomllib
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from .calibration import Calibration, calibrate_from_white
from .camera import CameraSpec
from .errors import CalibrationError, InputFileError
from .io import check_image_shape, read_raw
from .lightfield.decode import WHITE_FLOOR, _flat_field, decode
from .lightfield.grid import GridMeasurement
from .lightfield.lattice import LensletGrid
from .locate.dlfc import DLFC, INPUT_VARIABLES, FitReport, _check_order, fit_dlfc, n_monomials
from .locate.dotcards import dotcard_points

__all__ = ["DotCardImage", "DotCardSet", "CalibrationReport", "read_dotcards", "dlfc_points",
           "calibrate", "DOTCARDS_FILE", "DEFAULT_REJECT_K"]

DOTCARDS_FILE = "dotcards.toml"
"""Name of the dot-card description inside a dot-card folder."""

DEFAULT_REJECT_K = 5.0
"""Default robust-rejection threshold of :func:`calibrate`: dots whose residual exceeds
``median + k * 1.4826 * MAD`` of all residual lengths are dropped and the DLFC refitted
(see :func:`~plenoptrack.locate.dlfc.fit_dlfc`). For normally distributed centroid errors
this is about 4.5 standard deviations, so only mis-measured dots (clipped by a view edge,
merged with a neighbour, mis-indexed) are removed."""


# --- dot-card folder ----------------------------------------------------------------

@dataclass(frozen=True)
class DotCardImage:
    """One dot-card image.

    Attributes
    ----------
    path : Path
        The card's raw image, uint16 TIFF.
    z_mm : float
        Depth of the card, mm (world frame, 0 at the nominal focal plane).
    """

    path: Path
    z_mm: float


@dataclass(frozen=True)
class DotCardSet:
    """A validated dot-card folder (:func:`read_dotcards`).

    Attributes
    ----------
    source : Path
        The ``dotcards.toml`` file read.
    spacing_mm : float
        Centre-to-centre dot spacing along x and y, mm.
    cards : tuple of DotCardImage
        The cards in file order.
    dot_diameter_mm : float or None
        Dot diameter, mm, when given.
    """

    source: Path
    spacing_mm: float
    cards: tuple[DotCardImage, ...]
    dot_diameter_mm: float | None = None

    def __len__(self) -> int:
        return len(self.cards)

    @property
    def depths_mm(self) -> np.ndarray:
        """Card depths, mm, ``(n_cards,)`` float64, in file order."""
        return np.array([c.z_mm for c in self.cards], dtype=float)


def _finite_number(value, *, source: Path, key: str, fix: str, positive: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and positive:
        ok = value > 0
    if not ok:
        kind = "a positive number" if positive else "a finite number"
        raise InputFileError(f"{source}: {key} must be {kind}; got {value!r}. {fix}")
    return float(value)


def read_dotcards(folder: str | Path) -> DotCardSet:
    """Read and validate a dot-card folder.

    Parameters
    ----------
    folder : str or Path
        Folder holding ``dotcards.toml`` and the card images, or the path of the TOML file
        itself.

    Returns
    -------
    DotCardSet
        Spacing and cards, with card paths resolved against the TOML file's folder.

    Raises
    ------
    InputFileError
        The folder or ``dotcards.toml`` is missing or not valid TOML; ``spacing_mm`` is
        missing or not positive; there are no cards; a card lacks ``file`` or ``z_mm``,
        has a non-finite depth or shares its depth with another card; a card file does not
        exist.

    Examples
    --------
    >>> import tempfile
    >>> from plenoptrack.simulate import simulate_dataset
    >>> out = simulate_dataset("small", tempfile.mkdtemp(), n_particles=0,
    ...                        dotcard_depths=[-5.0, 0.0, 5.0])
    >>> cards = read_dotcards(out.out_dir / "dotcards")
    >>> cards.spacing_mm, cards.depths_mm.tolist()
    (1.25, [-5.0, 0.0, 5.0])
    """
    folder = Path(folder)
    path = folder if folder.suffix.lower() == ".toml" else folder / DOTCARDS_FILE
    fix = "See plenoptrack.calibrate for the dotcards.toml layout"
    if not path.parent.is_dir():
        raise InputFileError(f"{path.parent}: dot-card folder not found; check the path")
    if not path.is_file():
        raise InputFileError(f"{path}: dot-card description not found; write a dotcards.toml "
                             "beside the card images with spacing_mm and [[cards]] file, z_mm")
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputFileError(f"{path}: not valid TOML ({exc}); {fix}") from None
    if "spacing_mm" not in doc:
        raise InputFileError(f"{path}: spacing_mm (dot spacing, mm) is missing; add e.g. "
                             "`spacing_mm = 2.0`")
    spacing = _finite_number(doc["spacing_mm"], source=path, key="spacing_mm", fix=fix,
                             positive=True)
    diameter = doc.get("dot_diameter_mm")
    if diameter is not None:
        diameter = _finite_number(diameter, source=path, key="dot_diameter_mm", fix=fix,
                                  positive=True)
    entries = doc.get("cards")
    if not isinstance(entries, list) or not entries:
        raise InputFileError(f"{path}: lists no dot cards; add one entry per card image, "
                             'e.g. cards = [{ file = "card_00.tif", z_mm = -10.0 }, ...]')
    cards = []
    for k, entry in enumerate(entries):
        where = f"cards[{k}]"
        if not isinstance(entry, dict) or "file" not in entry or "z_mm" not in entry:
            raise InputFileError(f"{path}: {where} must have `file` and `z_mm`; got {entry!r}")
        if not isinstance(entry["file"], str) or not entry["file"]:
            raise InputFileError(f"{path}: {where}.file must be a file name; got {entry['file']!r}")
        z = _finite_number(entry["z_mm"], source=path, key=f"{where}.z_mm", fix=fix)
        card_path = path.parent / entry["file"]
        if not card_path.is_file():
            raise InputFileError(f"{card_path}: dot-card image listed in {path.name} ({where}) "
                                 "not found; add the file or remove the entry")
        cards.append(DotCardImage(path=card_path, z_mm=z))
    depths = [c.z_mm for c in cards]
    dup = sorted({z for z in depths if depths.count(z) > 1})
    if dup:
        raise InputFileError(f"{path}: several cards at z_mm = {dup}; give each card its own "
                             "depth (one image per depth)")
    return DotCardSet(source=path, spacing_mm=spacing, cards=tuple(cards),
                      dot_diameter_mm=diameter)


def _as_dotcards(dotcards) -> DotCardSet:
    if isinstance(dotcards, DotCardSet):
        return dotcards
    if isinstance(dotcards, (str, Path)):
        return read_dotcards(dotcards)
    raise TypeError(f"dotcards must be a DotCardSet or a folder path; got "
                    f"{type(dotcards).__name__}")


# --- calibration points -------------------------------------------------------------

@contextlib.contextmanager
def _card_progress(enabled: bool, total: int) -> Iterator:
    """Yield an ``advance(description)`` callable drawing a rich bar on stderr."""
    if not enabled:
        yield lambda description: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("{task.description}"), BarColumn(),
                  TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(),
                  console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task("dot cards", total=total)
        yield lambda description: bar.update(task, advance=1, description=description)


def _read_image(image, shape: tuple[int, int], source: str) -> np.ndarray:
    if isinstance(image, (str, Path)):
        source = str(image)
        image = read_raw(image)
    image = np.asarray(image)
    check_image_shape(image, shape, source=source, what="the lenslet grid")
    return image


def dlfc_points(dotcards, grid: LensletGrid, camera: CameraSpec, *, white=None,
                progress: bool = False) -> pd.DataFrame:
    """Calibration points ``(u, v, s, t) <-> (x, y, z)`` of every dot card.

    Parameters
    ----------
    dotcards : DotCardSet, str or Path
        Cards (:func:`read_dotcards`), or their folder.
    grid : LensletGrid
        Lenslet grid of the camera (from the white image).
    camera : CameraSpec
        Nominal camera; predicts each card's parallax across views to index its dots.
    white : (rows, cols) ndarray, str or Path, optional
        White image. When given, every card is divided by it after decoding (as
        ``decode(card, grid, white=white)`` does, with the white image decoded once),
        which evens out the microlens vignetting so that dots in rim views are segmented
        as well as central ones.
    progress : bool
        Show a progress bar (rich, stderr).

    Returns
    -------
    pandas.DataFrame
        One row per dot per view: the columns of
        :data:`~plenoptrack.locate.dotcards.DOTCARD_COLUMNS` (``u, v`` view, sensor
        pixels; ``s, t`` dot centroid, view pixels; ``x, y, z`` dot position, mm;
        ``i, j`` dot index) and ``card`` (int64, position of the card in ``dotcards``).

    Raises
    ------
    InputFileError, ImageSizeError
        A card image is unreadable or not of the grid's sensor size.
    CalibrationError
        No dot lattice could be found in a card; the message names the card file.
    """
    cards = _as_dotcards(dotcards)
    if not isinstance(grid, LensletGrid):
        raise CalibrationError(f"grid must be a LensletGrid; got {type(grid).__name__}")
    shape = tuple(grid.sensor_shape_px)
    white_lf = None
    if white is not None:
        white_lf = decode(_read_image(white, shape, "white image"), grid)
    tables = []
    # the next card is read (TIFF decompression releases the GIL) while one is processed
    with _card_progress(progress, len(cards)) as advance, \
            ThreadPoolExecutor(max_workers=1) as reader:
        pending = reader.submit(_read_image, cards.cards[0].path, shape, "")
        for k, card in enumerate(cards.cards):
            raw = pending.result()
            if k + 1 < len(cards):
                pending = reader.submit(_read_image, cards.cards[k + 1].path, shape, "")
            lf = decode(raw, grid)
            del raw
            if white_lf is not None:
                valid = _flat_field(lf.data, white_lf.data, lf.spatial_mask, WHITE_FLOOR)
                lf = replace(lf, valid_fraction=np.minimum(lf.valid_fraction, valid),
                             flat_fielded=True)
            try:
                table = dotcard_points(lf, spacing_mm=cards.spacing_mm, z_mm=card.z_mm,
                                       camera=camera)
            except CalibrationError as exc:
                raise CalibrationError(f"{card.path}: {exc}") from None
            del lf
            tables.append(table.assign(card=np.int64(k)))
            advance(f"dot card {k + 1}/{len(cards)}")
    return pd.concat(tables, ignore_index=True)


# --- the workflow -------------------------------------------------------------------

@dataclass(frozen=True)
class CalibrationReport:
    """What :func:`calibrate` measured, for reporting.

    Attributes
    ----------
    grid : GridMeasurement
        Lenslet-grid measurement (detected centres, fit residual).
    fit : FitReport
        DLFC fit residuals (view pixels) over the kept points, grouped by card depth.
    cards : pandas.DataFrame
        One row per card: ``card`` (int), ``file`` (str), ``z_mm`` (mm), ``n_views``
        (views in which dots were found), ``n_points`` (dot measurements found),
        ``n_rejected`` (of those, dropped by the robust refit), ``rms_px`` (RMS residual
        length of the kept points, view pixels).
    order : int
        DLFC polynomial order.
    seconds : dict
        Wall-clock time of the steps ``grid``, ``dots``, ``fit`` and ``total``, seconds.
    """

    grid: GridMeasurement
    fit: FitReport
    cards: pd.DataFrame = field(repr=False)
    order: int
    seconds: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        """Dot measurements used in the final DLFC fit."""
        return self.fit.n_points

    @property
    def rms_px(self) -> float:
        """Overall RMS residual length of the DLFC fit, view pixels."""
        return self.fit.rms_px


def _check_determined(points: pd.DataFrame, order: int) -> None:
    """Refuse data that cannot determine an order-``order`` polynomial, with the reason."""
    needed = n_monomials(order)
    if len(points) <= needed:
        raise CalibrationError(f"only {len(points)} dot measurements for the {needed} "
                               f"coefficients of an order-{order} DLFC; use more or larger "
                               "dot cards, or a lower --order")
    what = {"x": ("dot columns (x)", "a finer dot spacing"),
            "y": ("dot rows (y)", "a finer dot spacing"),
            "z": ("card depths (z)", "more cards"),
            "u": ("view columns (u)", "a check of the lenslet grid"),
            "v": ("view rows (v)", "a check of the lenslet grid")}
    for name in INPUT_VARIABLES:
        distinct = int(np.unique(points[name].to_numpy()).size)
        if distinct <= order:
            label, fix = what[name]
            raise CalibrationError(
                f"the dot cards show only {distinct} distinct {label}; an order-{order} DLFC "
                f"needs at least {order + 1}: use {fix} or a lower --order "
                f"(at most {max(distinct - 1, 1)})")


def calibrate(white, dotcards, camera: CameraSpec, *, order: int = 4,
              reject_k: float | None = DEFAULT_REJECT_K, flat_field: bool = True,
              progress: bool = False) -> tuple[Calibration, CalibrationReport]:
    """Calibrate a camera set-up: lenslet grid from a white image, DLFC from dot cards.

    Parameters
    ----------
    white : (rows, cols) ndarray, str or Path
        White (flat-field) image, or its TIFF file.
    dotcards : DotCardSet, str or Path
        Dot cards (:func:`read_dotcards`) or their folder.
    camera : CameraSpec
        Nominal camera; its grid type and sensor size are checked against the images.
    order : int, default 4
        DLFC total polynomial order (see :data:`plenoptrack.locate.dlfc.SUPPORTED_ORDERS`).
    reject_k : float or None, default :data:`DEFAULT_REJECT_K`
        Robust-rejection threshold of the DLFC fit; None keeps every dot.
    flat_field : bool, default True
        Divide the cards by the white image while decoding (see :func:`dlfc_points`).
    progress : bool
        Show progress bars (rich, stderr).

    Returns
    -------
    calibration : Calibration
        Camera, lenslet grid, vignetting and DLFC; save it with
        :func:`~plenoptrack.calibration.save_calibration`.
    report : CalibrationReport
        Grid and DLFC residuals, per-card statistics and timings.

    Raises
    ------
    InputFileError, ImageSizeError
        An image or the dot-card description is missing, unreadable or of the wrong size.
    CalibrationError
        The grid or a card's dot lattice cannot be measured, or the dots do not determine
        a DLFC of this order (too few cards, dot rows or columns).

    Notes
    -----
    The fit groups residuals by card depth; ``report.cards`` gives the RMS per card. Dot
    positions are ``(x, y) = (m, n) * spacing_mm`` with dot ``(0, 0)`` on the optical
    axis, so the DLFC maps world coordinates in that frame.

    Examples
    --------
    >>> import tempfile
    >>> from plenoptrack.simulate import simulate_dataset
    >>> out = simulate_dataset("small", tempfile.mkdtemp(), n_particles=0,
    ...                        dotcard_depths=[-10.0, -5.0, 0.0, 5.0, 10.0])
    >>> calib, report = calibrate(out.white_path, out.out_dir / "dotcards", out.camera)
    >>> calib.dlfc.order, report.rms_px < 0.1
    (4, True)
    """
    t0 = time.perf_counter()
    if not isinstance(camera, CameraSpec):
        raise TypeError(f"camera must be a CameraSpec; got {type(camera).__name__}")
    cards = _as_dotcards(dotcards)
    order = _check_order(order, source="calibrate")
    distinct_z = int(np.unique(cards.depths_mm).size)
    if distinct_z <= order:
        raise CalibrationError(f"{cards.source}: {distinct_z} card depth(s) cannot determine an "
                               f"order-{order} DLFC (needs at least {order + 1}); add cards "
                               "or lower --order")
    if isinstance(white, (str, Path)):
        white = read_raw(white)  # read once: for the grid and for flat-fielding the cards
    calibration, grid_measurement = calibrate_from_white(white, camera, progress=progress)
    t_grid = time.perf_counter()
    points = dlfc_points(cards, calibration.grid, camera,
                         white=white if flat_field else None, progress=progress)
    t_dots = time.perf_counter()
    _check_determined(points, order)
    dlfc = fit_dlfc(points, order=order, group_by="z", reject_k=reject_k)
    t_fit = time.perf_counter()
    report = CalibrationReport(
        grid=grid_measurement, fit=dlfc.report, cards=_card_table(cards, points, dlfc),
        order=order, seconds={"grid": t_grid - t0, "dots": t_dots - t_grid,
                              "fit": t_fit - t_dots, "total": t_fit - t0})
    return calibration.with_dlfc(dlfc), report


def _card_table(cards: DotCardSet, points: pd.DataFrame, dlfc: DLFC) -> pd.DataFrame:
    fit = dlfc.report
    kept = dict(zip(fit.group_keys, fit.group_n_points))
    rms = dict(zip(fit.group_keys, fit.group_rms_px))
    found = points.groupby("card").size()
    views = points.groupby("card")[["u", "v"]].apply(lambda g: len(g.drop_duplicates()))
    rows = []
    for k, card in enumerate(cards.cards):
        n = int(found.get(k, 0))
        rows.append({"card": k, "file": card.path.name, "z_mm": card.z_mm,
                     "n_views": int(views.get(k, 0)), "n_points": n,
                     "n_rejected": n - int(kept.get(card.z_mm, 0)),
                     "rms_px": float(rms.get(card.z_mm, np.nan))})
    return pd.DataFrame(rows)

