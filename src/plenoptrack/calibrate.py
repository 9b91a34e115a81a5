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
import warnings
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd

from .calibration import Calibration, calibrate_from_white
from .camera import CameraSpec
from .errors import CalibrationError, CardDepthWarning, InputFileError, SettingsError
from .io import check_image_shape, read_raw
from .lightfield.decode import WHITE_FLOOR, _flat_field, decode
from .lightfield.grid import GridMeasurement
from .lightfield.lattice import LensletGrid
from .locate.cluster import ProjectionGeometry
from .locate.dlfc import DLFC, INPUT_VARIABLES, FitReport, _check_order, fit_dlfc, n_monomials
from .locate.dotcards import (CardLattice, OriginConsensus, card_lattice, consistent_origins,
                              dotcard_points)
from .locate.opacity import edge_blur_by_depth
from .locate.pixel_locking import pattern_from_dots

__all__ = ["CARD_DEPTH_TOL", "CARD_DEPTH_TOL_MM", "DEFAULT_REJECT_K", "DEPTH_SCALE_RANGE",
           "DOTCARDS_FILE", "ORIGIN_TOL", "CalibrationReport", "CardDepthWarning", "DepthCheck",
           "DotCardImage", "DotCardSet", "MAX_CARD_TILT_DEG", "TILT_SIGNIFICANCE", "calibrate",
           "card_tilts", "check_card_depths", "dlfc_points", "implied_depths", "read_dotcards"]

DOTCARDS_FILE = "dotcards.toml"
"""Name of the dot-card description inside a dot-card folder."""

DEFAULT_REJECT_K = 5.0
"""Default robust-rejection threshold of :func:`calibrate`: dots whose residual exceeds
``median + k * 1.4826 * MAD`` of all residual lengths are dropped and the DLFC refitted
(see :func:`~plenoptrack.locate.dlfc.fit_dlfc`). For normally distributed centroid errors
this is about 4.5 standard deviations, so only mis-measured dots (clipped by a view edge,
merged with a neighbour, mis-indexed) are removed."""

ORIGIN_TOL = 0.25
"""Cards agree on the position of dot ``(0, 0)`` when they place it within this many dot
spacings of each other (:func:`~plenoptrack.locate.dotcards.consistent_origins`); a card
whose lattice has no node this close to the consensus is refused. On simulated data sets
(``benchmarks/calibration_seeds.py``: 210 seeds of ``small``, 100 of ``small-rect``, one
of ``hall2019``) every card's lattice passes within 0.002 spacings of the common dot
``(0, 0)``."""

DEPTH_SCALE_RANGE = (0.67, 1.5)
"""Accepted range of the scale ``a`` of ``z_implied = a * z_mm + b`` (card depths implied
by the dots' parallax against the depths stated in ``dotcards.toml``). Outside it (or for
``a <= 0``) :func:`calibrate` refuses the cards: the stated depths are in the wrong unit or
sign, or the nominal camera is far from the real one. On simulated data sets, whose
nominal camera is exact, ``a`` is 0.982 to 0.984 (``small``, ``small-rect`` and
``hall2019`` alike; ``b`` within 0.03 mm of 0). A nominal magnification 3 % off moves
``a`` by 6 %, a microlens focal length 3 % off by 3 %, the main-lens focal length
hardly at all; a traverse zero away from the focal plane moves only ``b``. The range
leaves room for a nominal magnification about 15 % off and still refuses depths in cm
(``a`` near 10), in inches (near 25), reversed, or off by a factor of 2."""

CARD_DEPTH_TOL = 0.2
"""A card whose implied depth is further than this fraction of the median step between
neighbouring card depths (and at least :data:`CARD_DEPTH_TOL_MM`) from the fit
``a * z_mm + b`` gets a :class:`CardDepthWarning`: 0.4 mm for the 2 mm steps of
``small``, 1 mm for the 5 mm steps of ``hall2019``. On simulated data sets single cards
deviate from the fit by at most 0.043 mm (``small``), 0.013 mm (``small-rect``) and
0.03 mm (``hall2019``), ten to thirty times less; a mix-up of cards or a mistyped depth
is typically a whole step."""

CARD_DEPTH_TOL_MM = 0.2
"""Lower bound of the single-card depth tolerance, mm (see :data:`CARD_DEPTH_TOL`)."""


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
                origin_st=None, progress: bool = False) -> pd.DataFrame:
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
    origin_st : (float, float), optional
        Predicted ``(s, t)`` of the optical axis in the view ``u = v = 0``, view pixels;
        default the sensor centre (``LightField.axis_st``). It need only be right to
        within half a dot spacing: it picks which dot is ``(0, 0)``.
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
        No dot lattice could be found in a card, or a card's lattice has no dot where the
        other cards see dot ``(0, 0)``; the message names the card file.

    Notes
    -----
    Each card is indexed on its own, with ``(0, 0)`` at the lattice node nearest
    ``origin_st`` in its most central view
    (:func:`~plenoptrack.locate.dotcards.dotcard_points`). Dot ``(0, 0)`` lies on the
    optical axis, so at ``u = v = 0`` its image is the same for every card depth; the
    cards are then re-indexed to agree on that position
    (:func:`~plenoptrack.locate.dotcards.consistent_origins`), which repairs a card
    whose origin came out a whole dot away (dot ``(0, 0)`` not detected, or the axis
    prediction off by nearly half a spacing).
    """
    return _measure_cards(dotcards, grid, camera, white=white, origin_st=origin_st,
                          progress=progress).points


@dataclass(frozen=True)
class _CardMeasurements:
    """Everything :func:`_measure_cards` measured: the DLFC points, each card's lattice
    and parallax, the origin consensus and the nominal projection geometry."""

    points: pd.DataFrame
    lattices: tuple[CardLattice, ...]
    consensus: OriginConsensus
    geometry: ProjectionGeometry


def _measure_cards(dotcards, grid: LensletGrid, camera: CameraSpec, *, white=None,
                   origin_st=None, progress: bool = False) -> _CardMeasurements:
    cards = _as_dotcards(dotcards)
    if not isinstance(grid, LensletGrid):
        raise CalibrationError(f"grid must be a LensletGrid; got {type(grid).__name__}")
    shape = tuple(grid.sensor_shape_px)
    white_lf = None
    if white is not None:
        white_lf = decode(_read_image(white, shape, "white image"), grid)
    tables, geometry = [], None
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
            if geometry is None:
                geometry = ProjectionGeometry.from_lightfield(lf, camera)
            if white_lf is not None:
                valid = _flat_field(lf.data, white_lf.data, lf.spatial_mask, WHITE_FLOOR)
                lf = replace(lf, valid_fraction=np.minimum(lf.valid_fraction, valid),
                             flat_fielded=True)
            try:
                table = dotcard_points(lf, spacing_mm=cards.spacing_mm, z_mm=card.z_mm,
                                       camera=camera, origin_st=origin_st)
            except CalibrationError as exc:
                raise CalibrationError(f"{card.path}: {exc}") from None
            del lf
            tables.append(table)
            advance(f"dot card {k + 1}/{len(cards)}")
    lattices = []
    for card, table in zip(cards.cards, tables):
        try:
            lattices.append(card_lattice(table))
        except CalibrationError as exc:
            raise CalibrationError(f"{card.path}: {exc}") from None
    axis = geometry.axis_st if origin_st is None else origin_st
    consensus = consistent_origins(lattices, origin_st=axis, tol=ORIGIN_TOL)
    _check_origins(cards, consensus)
    for k, (di, dj) in enumerate(consensus.shifts):
        if di or dj:
            i, j = tables[k]["i"] - di, tables[k]["j"] - dj
            tables[k] = tables[k].assign(i=i, j=j, x=i * cards.spacing_mm,
                                         y=j * cards.spacing_mm)
            lat = lattices[k]
            lattices[k] = replace(lat, origin_st=lat.origin_st + lat.basis @ (di, dj))
    points = pd.concat([t.assign(card=np.int64(k)) for k, t in enumerate(tables)],
                       ignore_index=True)
    return _CardMeasurements(points=points, lattices=tuple(lattices), consensus=consensus,
                             geometry=geometry)


def _check_origins(cards: DotCardSet, consensus: OriginConsensus) -> None:
    """Refuse cards whose lattice has no dot where the others see dot ``(0, 0)``."""
    bad = np.flatnonzero(consensus.miss > ORIGIN_TOL)
    if not len(bad):
        return
    k = bad[np.argmax(consensus.miss[bad])]
    s, t = consensus.axis_st
    others = "" if len(bad) == 1 else (
        f" (so do {', '.join(cards.cards[m].path.name for m in bad if m != k)})")
    raise CalibrationError(
        f"{cards.cards[k].path}: the dot lattice of this card (z_mm = {cards.cards[k].z_mm:g}) "
        f"has no dot where {consensus.n_agree} of the {len(cards)} cards see dot (0, 0), on "
        f"the optical axis at (s, t) = ({s:.2f}, {t:.2f}) view px; its nearest dot position "
        f"is {consensus.miss[k]:.2f} dot spacings away{others}. Dot (0, 0) of every card "
        "must lie on the optical axis: check that the card was not moved sideways on the "
        f"traverse and that the image belongs to this set, or remove it from "
        f"{cards.source.name}")


# --- card tilts ----------------------------------------------------------------------

MAX_CARD_TILT_DEG = 3.0
"""A card whose dots' parallax puts it further than this from perpendicular to the optical
axis gets a :class:`CardDepthWarning` (a card is mounted within about half a degree; a
larger figure points at a nominal camera far from the real one or at mis-indexed dots)."""

TILT_SIGNIFICANCE = 3.0
"""A card's measured slope is applied to its dots' depths only when it is at least this
many standard errors from 0 (:func:`calibrate`): on a small field of view the parallax of
a few dozen dots measures a slope to a few 1e-3, as large as a real card's tilt, and a
slope that is only noise would tilt an untilted card."""


def card_tilts(points: pd.DataFrame, geometry: ProjectionGeometry, camera: CameraSpec, *,
               scale: float = 1.0, min_views: int = 12, min_dots: int = 10,
               clip: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Each dot card's tilt from the parallax of its dots, through the nominal camera.

    A card tilted about an in-plane axis puts its dots at depths that change linearly
    across it, and a dot's image shifts across the views by a parallax that grows with
    its depth. Each dot's parallax is the slope of its centroid over the views (``s``
    against ``u`` and ``t`` against ``v``, least squares over its views, averaged), turned
    into a depth by the nominal camera (:func:`implied_depths`); a plane plus a radial
    term ``z = a + b x + c y + d (x^2 + y^2)`` is fitted to each card's dots (least
    squares, repeated with the dots within ``clip`` times the residuals' 1.4826 MAD; the
    radial term takes up the field curvature's change of parallax across the field), and
    ``(b, c) / scale`` are its slopes, with standard errors from the scatter of the
    dots kept about the fit. The radial term is centred on the optical axis, which the
    cards show as the point their central-view images expand about from card to card
    (:func:`_expansion_centre`): field curvature about an axis off the card's dot
    ``(0, 0)`` would otherwise read as a tilt common to every card.

    Parameters
    ----------
    points : pandas.DataFrame
        Calibration points (:func:`dlfc_points`): ``card``, ``i, j``, ``u, v``, ``s, t``,
        ``x, y`` (mm) per dot and view.
    geometry : ProjectionGeometry
        Nominal projection geometry of the cards' light fields.
    camera : CameraSpec
        Nominal camera.
    scale : float
        ``a`` of ``implied = a * stated + b`` over the cards (:class:`DepthCheck`): the
        nominal camera's depth scale against the true one, by which implied depths, and
        so their slopes across a card, are stretched.
    min_views, min_dots : int
        A dot needs this many views, a card this many such dots; NaN slopes otherwise.
    clip : float
        Robust-refit threshold, in units of the residuals' 1.4826 MAD.

    Returns
    -------
    slopes, standard_errors : (n_cards, 2) float64 ndarray
        ``dz/dx`` and ``dz/dy`` of each card and their standard errors (rows in the
        order of ``card``, 0 to its largest value), dimensionless; NaN where not
        measured.

    Notes
    -----
    On the simulated ``hall2019`` data set of the vortex-ring scene (realistic optics,
    11 cards tilted by up to 0.5 degrees) the slopes came within 0.0003 of the cards'
    true tilts (0.0003 to 0.0082), about 0.02 degrees.
    """
    n_cards = int(points["card"].max()) + 1 if len(points) else 0
    out = np.full((n_cards, 2), np.nan)
    error = np.full((n_cards, 2), np.nan)
    if n_cards == 0:
        return out, error
    card, x, y, at_centre, parallax = _dot_parallax(points, min_views)
    depth = implied_depths(parallax, geometry, camera)
    cx, cy = _expansion_centre(card, x, y, at_centre[:, 0], at_centre[:, 1])
    for k in range(n_cards):
        mine = (card == k) & np.isfinite(depth)
        if mine.sum() < min_dots:
            continue
        radial = (x[mine] - cx) ** 2 + (y[mine] - cy) ** 2
        plane = np.stack([np.ones(mine.sum()), x[mine], y[mine], radial], axis=1)
        fitted = _clipped_fit(plane, depth[mine], clip=clip, min_points=min_dots)
        if fitted is not None:
            out[k] = fitted[0][1:3] / scale
            error[k] = fitted[1][1:3] / scale
    return out, error


def _dot_parallax(points: pd.DataFrame, min_views: int):
    """Per dot (one row per ``card, i, j``): its card, ``x, y`` (mm), its centroid at
    ``u = v = 0`` (``(n, 2)`` view pixels) and its parallax, the mean of ``ds/du`` and
    ``dt/dv`` from least squares ``s = s0 + a u + b v`` (and ``t`` alike) over its views;
    NaN for dots seen in fewer than ``min_views`` views."""
    key = points[["card", "i", "j"]].to_numpy(np.int64)
    dots, dot = np.unique(key, axis=0, return_inverse=True)
    dot = dot.ravel()
    u, v = points["u"].to_numpy(float), points["v"].to_numpy(float)
    design = np.stack([np.ones_like(u), u, v], axis=1)                  # (N, 3)
    gram = np.zeros((len(dots), 3, 3))
    np.add.at(gram, dot, design[:, :, None] * design[:, None, :])
    rhs = np.zeros((len(dots), 3, 2))
    st = points[["s", "t"]].to_numpy(float)
    np.add.at(rhs, dot, design[:, :, None] * st[:, None, :])
    n_views = np.bincount(dot, minlength=len(dots))
    ok = (n_views >= min_views) & (np.abs(np.linalg.det(gram)) > 1e-9)
    coef = np.full((len(dots), 3, 2), np.nan)
    if ok.any():
        coef[ok] = np.linalg.solve(gram[ok], rhs[ok])
    first = np.zeros(len(dots), dtype=np.int64)
    first[dot[::-1]] = np.arange(len(dot))[::-1]
    return (dots[:, 0], points["x"].to_numpy(float)[first], points["y"].to_numpy(float)[first],
            coef[:, 0, :], 0.5 * (coef[:, 1, 0] + coef[:, 2, 1]))


def _clipped_fit(design: np.ndarray, values: np.ndarray, *, clip: float, min_points: int):
    """Least squares ``values ~ design``, refitted (at most 5 times) to the points within
    ``clip`` times the residuals' 1.4826 MAD: ``(coefficients, standard errors)`` from the
    kept points' scatter, or None when fewer points than coefficients plus one remain."""
    inside = np.ones(len(values), dtype=bool)
    for _ in range(5):
        fit, *_ = np.linalg.lstsq(design[inside], values[inside], rcond=None)
        residual = values - design @ fit
        spread = 1.4826 * np.median(np.abs(residual[inside]))
        keep = np.abs(residual) <= clip * spread if spread > 0 else inside
        if keep.sum() < min_points or np.array_equal(keep, inside):
            break
        inside = keep
    dof = int(inside.sum()) - design.shape[1]
    if dof < 1:
        return None
    variance = float(np.sum(residual[inside] ** 2)) / dof
    with np.errstate(invalid="ignore"):
        cov = variance * np.linalg.pinv(design[inside].T @ design[inside])
    return fit, np.sqrt(np.diag(cov))


# --- card depths ---------------------------------------------------------------------

def implied_depths(parallax_per_u, geometry: ProjectionGeometry, camera: CameraSpec) -> np.ndarray:
    """Card depths implied by their measured parallax, through the nominal camera.

    Parameters
    ----------
    parallax_per_u : (n,) float array-like
        Measured shift of each card's image per unit ``u`` (and ``v``), view pixels
        (:attr:`~plenoptrack.locate.dotcards.CardLattice.parallax_per_u`).
    geometry : ProjectionGeometry
        Nominal projection geometry of the light fields.
    camera : CameraSpec
        Nominal camera.

    Returns
    -------
    (n,) float64 ndarray
        Depth ``z``, mm (0 at the nominal focal plane, positive away from the camera);
        NaN where the parallax is beyond any real depth.

    Notes
    -----
    Inverts :meth:`~plenoptrack.locate.cluster.ProjectionGeometry.parallax_per_u`,
    ``p = g (1 - 1 / alpha) / m`` (``g`` aperture mm per unit ``u``, ``m`` mm per
    sample), to ``alpha = 1 / (1 - p m / g)`` and that through
    :meth:`~plenoptrack.camera.CameraSpec.depth_for_alpha`.
    """
    p = np.asarray(parallax_per_u, dtype=float)
    inv_alpha = 1.0 - p * geometry.mm_per_sample / geometry.aperture_mm_per_u
    with np.errstate(divide="ignore", invalid="ignore"):
        z = camera.depth_for_alpha(1.0 / inv_alpha)
    return np.where((inv_alpha > 0) & np.isfinite(z), z, np.nan)


@dataclass(frozen=True)
class DepthCheck:
    """Stated card depths against the depths their parallax implies (:func:`check_card_depths`).

    Attributes
    ----------
    stated_mm, implied_mm : (n,) float ndarray
        Depths from ``dotcards.toml`` and from the parallax (:func:`implied_depths`), mm.
    scale, offset_mm : float
        ``a`` and ``b`` of the fit ``implied = a * stated + b`` over the cards that agree.
    residual_mm : (n,) float ndarray
        ``implied - (a * stated + b)``, mm.
    tol_mm : float
        Single-card tolerance on ``|residual_mm|``, mm.
    outliers : (n,) bool ndarray
        Cards beyond ``tol_mm``.
    """

    stated_mm: np.ndarray
    implied_mm: np.ndarray
    scale: float
    offset_mm: float
    residual_mm: np.ndarray
    tol_mm: float
    outliers: np.ndarray

    @property
    def refit_mm(self) -> np.ndarray:
        """Each card's depth on the stated scale as its parallax reads it,
        ``(implied - b) / a``, mm: the likely right entry for an outlier card."""
        return (self.implied_mm - self.offset_mm) / self.scale


def _depth_line(z: np.ndarray, zi: np.ndarray, tol_mm: float) -> tuple[float, float]:
    """Robust ``(a, b)`` of ``zi = a z + b``: repeated medians, then least squares over
    the cards within ``tol_mm`` of that line (if at least two of them)."""
    from scipy.stats import siegelslopes

    if len(z) == 2:
        a = (zi[1] - zi[0]) / (z[1] - z[0])
        return float(a), float(zi[0] - a * z[0])
    a, b = siegelslopes(zi, z)
    inl = np.abs(zi - (a * z + b)) <= tol_mm
    if inl.sum() >= 2 and np.ptp(z[inl]) > 0:
        a, b = np.polyfit(z[inl], zi[inl], 1)
    return float(a), float(b)


def _unit_hint(factor: float) -> str:
    """``"stated depths are F times too small/large"`` with a guess at the unit."""
    if factor >= 1:
        hints = {10.0: "are they in cm?", 25.4: "are they in inches?"}
        what = f"about {factor:.3g} times too small"
    else:
        factor = 1.0 / factor
        hints = {1000.0: "are they in micrometres?", 10.0: "are they in tenths of a mm?"}
        what = f"about {factor:.3g} times too large"
    hint = next((h for f, h in hints.items() if abs(np.log(factor / f)) < 0.25),
                "are they in mm?")
    return f"{what} ({hint})"


def check_card_depths(stated_mm, implied_mm, *, source="dotcards.toml", files=None,
                      scale_range=DEPTH_SCALE_RANGE, tol: float = CARD_DEPTH_TOL,
                      tol_mm: float = CARD_DEPTH_TOL_MM) -> DepthCheck:
    """Check the card depths stated in ``dotcards.toml`` against their parallax.

    Parameters
    ----------
    stated_mm, implied_mm : (n,) float array-like
        Stated depths and the depths implied by each card's parallax
        (:func:`implied_depths`), mm; NaN implied depths are ignored.
    source : str or Path
        The dot-card description, named in messages.
    files : sequence of str, optional
        Card file names, for messages (default ``card 0``, ``card 1``, ...).
    scale_range : (float, float)
        Accepted range of the scale ``a`` (:data:`DEPTH_SCALE_RANGE`).
    tol : float
        Single-card tolerance as a fraction of the median step between neighbouring
        stated depths (:data:`CARD_DEPTH_TOL`).
    tol_mm : float
        Lower bound of the single-card tolerance, mm (:data:`CARD_DEPTH_TOL_MM`).

    Returns
    -------
    DepthCheck

    Raises
    ------
    CalibrationError
        Fewer than two cards with a usable parallax, or the scale ``a`` is not positive
        (depths reversed in sign) or outside ``scale_range`` (wrong unit, or a nominal
        camera far from the real one).

    Warns
    -----
    CardDepthWarning
        Single cards further than the tolerance from the fit.

    Notes
    -----
    The fit ``implied = a * stated + b`` allows for a nominal camera a few per cent off
    the true optics (``a``) and for a traverse zero that is not the focal plane (``b``).
    It is robust (Siegel's repeated medians, then least squares over the cards within
    the tolerance), so that one wrongly entered card neither hides itself nor moves the
    others out of tolerance.
    """
    z = np.asarray(stated_mm, dtype=float)
    zi = np.asarray(implied_mm, dtype=float)
    if z.shape != zi.shape or z.ndim != 1:
        raise SettingsError(f"stated_mm and implied_mm must be 1-D of one length; got shapes "
                         f"{z.shape} and {zi.shape}")
    names = list(files) if files is not None else [f"card {k}" for k in range(len(z))]
    ok = np.isfinite(zi)
    if ok.sum() < 2 or np.unique(z[ok]).size < 2:
        raise CalibrationError(f"{source}: only {int(ok.sum())} card(s) with a measurable "
                               "parallax; at least two at different depths are needed to "
                               "check the card depths (or pass check_depths=False)")
    steps = np.diff(np.unique(z))
    tol_abs = max(tol * float(np.median(steps)), tol_mm) if len(steps) else tol_mm
    a, b = _depth_line(z[ok], zi[ok], tol_abs)
    order = np.argsort(z)
    shown = [k for k in dict.fromkeys([order[0], order[len(order) // 2], order[-1]]) if ok[k]]
    table = ", ".join(f"{names[k]} stated {z[k]:g} mm, implied {zi[k]:.2f} mm"
                      for k in shown)
    lo, hi = scale_range
    if not a > 0:
        raise CalibrationError(
            f"{source}: the card depths look reversed in sign: the dots' parallax puts the "
            f"cards at implied = {a:.3g} * z_mm {b:+.3g} mm ({table}). z is positive away "
            "from the camera; negate every z_mm in the file (or pass check_depths=False "
            "if you are sure of them)")
    if not lo <= a <= hi:
        raise CalibrationError(
            f"{source}: the card depths look {_unit_hint(a)}: the dots' parallax puts the "
            f"cards at implied = {a:.3g} * z_mm {b:+.3g} mm, a scale outside the accepted "
            f"{lo:g} to {hi:g} ({table}). Give z_mm in millimetres, or check that the "
            "nominal camera (focal length, magnification, f-number, microlens focal length) "
            "describes this camera (or pass check_depths=False if you are sure of them)")
    resid = zi - (a * z + b)
    outliers = ok & (np.abs(resid) > tol_abs)
    check = DepthCheck(stated_mm=z, implied_mm=zi, scale=a, offset_mm=b, residual_mm=resid,
                       tol_mm=tol_abs, outliers=outliers)
    if outliers.any():
        refit = check.refit_mm
        listed = "; ".join(f"{names[k]} z_mm = {z[k]:g} reads as {refit[k]:.2f}"
                           for k in np.flatnonzero(outliers))
        warnings.warn(
            f"{source}: {int(outliers.sum())} card(s) disagree with the depth their dots' "
            f"parallax gives on the scale of the other cards (implied = {a:.3g} * z_mm "
            f"{b:+.3g} mm, tolerance {tol_abs:.2g} mm): {listed}. Check these z_mm entries "
            "and that each file is the image taken at its depth", CardDepthWarning,
            stacklevel=2)
    return check


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
        length of the kept points, view pixels), ``model_error_lateral_mm`` and
        ``model_error_z_mm`` (the DLFC's model error at the card's depth, lateral
        ``hypot(e_x, e_y)`` and in depth, mm: the dots' position error beyond their own
        centroid noise, :attr:`~plenoptrack.locate.dlfc.FitReport.model_error_by_depth_mm`;
        NaN when not measured), ``z_implied_mm`` (depth implied by the
        card's parallax through the nominal camera, mm; see :func:`calibrate`),
        ``tilt_x, tilt_y`` (the card's slopes ``dz/dx, dz/dy`` from its dots' parallax,
        :func:`card_tilts`; NaN when not measured), ``tilt_x_error, tilt_y_error`` (their
        standard errors), ``tilt_x_applied, tilt_y_applied`` (the slopes given to the
        dots' depths: those at least :data:`TILT_SIGNIFICANCE` standard errors from 0,
        0 otherwise and with ``card_tilt=False``), ``reindexed`` (bool: the card's dot
        ``(0, 0)`` was moved a whole dot to agree with the other cards) and
        ``origin_miss`` (distance of the card's nearest dot position from the cards'
        common dot ``(0, 0)``, dot spacings).
    order : int
        DLFC polynomial order.
    seconds : dict
        Wall-clock time of the steps ``grid``, ``dots`` (measuring and checking the
        cards), ``fit`` and ``total``, seconds.
    depth_check : DepthCheck or None
        Stated against implied card depths (scale, offset, per-card residuals); None when
        the check was switched off.
    """

    grid: GridMeasurement
    fit: FitReport
    cards: pd.DataFrame = field(repr=False)
    order: int
    seconds: dict = field(default_factory=dict)
    depth_check: DepthCheck | None = field(default=None, repr=False)

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
              check_depths: bool = True, card_tilt: bool = False, origin_st=None,
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
    check_depths : bool, default True
        Check the stated card depths against the depths the dots' parallax implies (see
        Notes); False skips the check (the implied depths are still reported).
    card_tilt : bool, default False
        Fit the DLFC to the dots where each card's tilt, measured from its dots' parallax
        (:func:`card_tilts`), puts them (see Notes); False (the default) takes every card
        as perpendicular to the optical axis. The tilts are measured and reported either
        way.
    origin_st : (float, float), optional
        Predicted ``(s, t)`` of the optical axis in the view ``u = v = 0``, view pixels;
        default the sensor centre. Needed only when the axis is more than half a dot
        spacing from it (see :func:`dlfc_points`).
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
        The grid or a card's dot lattice cannot be measured, a card does not have a dot
        where the others see dot ``(0, 0)``, the stated card depths disagree with their
        parallax in sign or scale (see Notes), or the dots do not determine a DLFC of
        this order (too few cards, dot rows or columns).

    Warns
    -----
    CardDepthWarning
        Single cards whose stated depth disagrees with their parallax (see Notes).

    Notes
    -----
    The fit groups residuals by card depth; ``report.cards`` gives the RMS per card. Dot
    positions are ``(x, y) = (m, n) * spacing_mm`` with dot ``(0, 0)`` on the optical
    axis, so the DLFC maps world coordinates in that frame; the cards are indexed so that
    they agree on where dot ``(0, 0)`` is (:func:`dlfc_points`).

    *Card-depth check.* The DLFC takes the stated depths as the truth, and fits cards with
    reversed or mis-scaled depths just as well, so every later depth would be wrong. The
    images measure depth on their own, though: a card's image shifts across views by its
    parallax, which the nominal camera turns into a depth relative to focus
    (:func:`implied_depths`; ``report.cards["z_implied_mm"]``). The implied depths are
    fitted as ``a * z_mm + b`` (:func:`check_card_depths`): ``b`` absorbs a traverse zero
    that is not the focal plane, ``a`` the difference between the nominal and the true
    optics. The cards are refused when ``a <= 0`` (depths reversed in sign) or ``a`` is
    outside :data:`DEPTH_SCALE_RANGE` (0.67 to 1.5: depths in the wrong unit, or a
    nominal camera far off); a :class:`CardDepthWarning` names single cards further than
    :data:`CARD_DEPTH_TOL` of the median card step (at least :data:`CARD_DEPTH_TOL_MM`)
    from the fit. On simulated data sets (exact nominal optics) ``a`` is 0.982 to 0.984
    and single cards deviate from the fit by at most 0.043 mm.

    *Card tilt.* A card is mounted on the traverse within about half a degree of
    perpendicular, and a card tilted by 0.005 (0.3 degrees) has its edge dots 0.1 mm off
    the stated depth on a 40 mm card. The DLFC fitted to the stated depths learns that
    tilt as part of the camera, and every particle measured at that depth carries it. The
    parallax of a card's dots shows the tilt through the nominal optics
    (:func:`card_tilts`; ``report.cards`` columns ``tilt_x, tilt_y``). With
    ``card_tilt=True`` each dot is placed at ``z_mm + tx * x + ty * y`` before the fit,
    the card pivoting about the optical axis, with each slope that stands at least
    :data:`TILT_SIGNIFICANCE` standard errors from 0 (columns ``tilt_x_applied,
    tilt_y_applied``). On the simulated ``hall2019`` camera (realistic optics, a 72 mm
    field, cards tilted by up to 0.47 degrees) the slopes came within 0.0003 of the true
    tilts and the robust depth error of 300 vortex-ring tracers over 12 frames fell from
    0.042 to 0.034 mm. On the ``small`` camera (a 16 mm field) the realistic optics bias
    the slopes by 0.002-0.005, as much as the tilts themselves, and by up to 0.05 on the
    cards furthest from focus, so the correction is off by default. Cards further than
    :data:`MAX_CARD_TILT_DEG` from perpendicular get a :class:`CardDepthWarning`.

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
    measured = _measure_cards(cards, calibration.grid, camera,
                              white=white if flat_field else None, origin_st=origin_st,
                              progress=progress)
    points = measured.points
    implied = implied_depths([lat.parallax_per_u for lat in measured.lattices],
                             measured.geometry, camera)
    depth_check = None
    if check_depths:
        depth_check = check_card_depths(cards.depths_mm, implied, source=cards.source,
                                        files=[c.path.name for c in cards.cards])
    tilts, tilt_errors = _measured_tilts(cards, points, measured, camera, implied,
                                         depth_check)
    _warn_tilted_cards(cards, tilts, tilt_errors, applied=card_tilt)
    significant = np.abs(tilts) >= TILT_SIGNIFICANCE * tilt_errors     # False for NaN
    applied = np.where(significant & card_tilt, tilts, 0.0)
    t_dots = time.perf_counter()
    _check_determined(points, order)
    fit_points = points
    if card_tilt:
        slope = applied[points["card"].to_numpy()]
        fit_points = points.assign(
            z_card=points["z"], z=points["z"] + slope[:, 0] * points["x"]
            + slope[:, 1] * points["y"])
    dlfc = fit_dlfc(fit_points, order=order, group_by="z_card" if card_tilt else "z",
                    reject_k=reject_k)
    t_fit = time.perf_counter()
    table = _card_table(cards, points, dlfc).assign(
        z_implied_mm=implied, tilt_x=tilts[:, 0], tilt_y=tilts[:, 1],
        tilt_x_error=tilt_errors[:, 0], tilt_y_error=tilt_errors[:, 1],
        tilt_x_applied=applied[:, 0], tilt_y_applied=applied[:, 1],
        reindexed=(measured.consensus.shifts != 0).any(axis=1),
        origin_miss=measured.consensus.miss)
    report = CalibrationReport(
        grid=grid_measurement, fit=dlfc.report, cards=table, order=order,
        seconds={"grid": t_grid - t0, "dots": t_dots - t_grid, "fit": t_fit - t_dots,
                 "total": t_fit - t0}, depth_check=depth_check)
    calibration = calibration.with_dlfc(dlfc)
    blur = edge_blur_by_depth(points)
    if blur:
        calibration = calibration.with_edge_blur(blur)
    locking = pattern_from_dots(fit_points, dlfc, calibration.grid)
    if locking is not None:
        calibration = calibration.with_locking_pattern(locking)
    return calibration, report


def _expansion_centre(card: np.ndarray, x: np.ndarray, y: np.ndarray, s0: np.ndarray,
                      t0: np.ndarray) -> tuple[float, float]:
    """``(x, y)`` (mm, card coordinates) that every card images at the same central-view
    position: each card's dots at ``s0 = A_k + m_k x`` (and ``t0 = B_k + n_k y``), so the
    point ``x*`` with ``A_k + m_k x*`` the same for all cards is minus the slope of
    ``A_k`` against ``m_k``. ``(0, 0)`` with fewer than two cards of distinct
    magnification."""
    out = []
    for pos, image in ((x, s0), (y, t0)):
        intercept, gain = [], []
        for k in np.unique(card):
            mine = (card == k) & np.isfinite(image)
            if mine.sum() >= 3 and np.ptp(pos[mine]) > 0:
                g, a = np.polyfit(pos[mine], image[mine], 1)
                gain.append(g)
                intercept.append(a)
        if len(gain) >= 2 and np.ptp(gain) > 0:
            out.append(-float(np.polyfit(gain, intercept, 1)[0]))
        else:
            out.append(0.0)
    return out[0], out[1]


def _measured_tilts(cards: DotCardSet, points: pd.DataFrame, measured: _CardMeasurements,
                    camera: CameraSpec, implied: np.ndarray,
                    depth_check: DepthCheck | None) -> tuple[np.ndarray, np.ndarray]:
    """(n_cards, 2) slopes of each card and their standard errors (:func:`card_tilts`),
    on the stated depth scale (``a`` of the depth check, or of the same line fitted here
    when the check is off)."""
    nan = np.full((len(cards), 2), np.nan)
    if depth_check is not None:
        scale = depth_check.scale
    else:
        ok = np.isfinite(implied)
        scale = (_depth_line(np.asarray(cards.depths_mm, float)[ok], implied[ok], np.inf)[0]
                 if ok.sum() >= 2 else math.nan)
    if not DEPTH_SCALE_RANGE[0] <= scale <= DEPTH_SCALE_RANGE[1]:
        return nan, nan.copy()       # the nominal camera cannot judge them
    tilts, errors = card_tilts(points, measured.geometry, camera, scale=scale)
    tilts = np.vstack([tilts, nan[len(tilts):]])
    errors = np.vstack([errors, nan[len(errors):]])
    return tilts, errors


def _warn_tilted_cards(cards: DotCardSet, tilts: np.ndarray, errors: np.ndarray, *,
                       applied: bool) -> None:
    """A :class:`CardDepthWarning` for each card tilted beyond :data:`MAX_CARD_TILT_DEG`
    by more than :data:`TILT_SIGNIFICANCE` standard errors of its measured tilt.

    The far cards of a small field of view are measured from few, blurred dots: on the
    simulated ``small`` camera (realistic optics, cards within 0.5 degrees) their slopes
    came out up to 0.13 +- 0.03, which is no evidence of a tilt beyond the limit.
    ``applied`` says whether the calibration gives the measured tilts to the dots
    (``card_tilt``), which decides what the user can do about it.
    """
    slope = np.hypot(tilts[:, 0], tilts[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        error = np.hypot(tilts[:, 0] * errors[:, 0], tilts[:, 1] * errors[:, 1]) / slope
    degrees = np.degrees(np.arctan(slope))
    at_least = np.degrees(np.arctan(slope - TILT_SIGNIFICANCE * error))
    fix = ("check the card's mount, or calibrate without --card-tilt if the nominal camera "
           "is far off" if applied else
           "the calibration takes every card as perpendicular: check the card's mount, or "
           "calibrate with --card-tilt to give the dots the measured tilt")
    for k in np.flatnonzero(at_least > MAX_CARD_TILT_DEG):    # False for NaN
        warnings.warn(f"{cards.cards[k].path}: the dots' parallax puts this card "
                      f"{degrees[k]:.1f} degrees (at least {at_least[k]:.1f}) from "
                      "perpendicular to the optical axis (a card is mounted within about "
                      f"0.5); {fix}", CardDepthWarning, stacklevel=3)



def _card_table(cards: DotCardSet, points: pd.DataFrame, dlfc: DLFC) -> pd.DataFrame:
    fit = dlfc.report
    kept = dict(zip(fit.group_keys, fit.group_n_points))
    rms = dict(zip(fit.group_keys, fit.group_rms_px))
    model_rows = np.asarray(fit.model_error_by_depth_mm, dtype=float).reshape(-1, 4)

    # a card's row sits at the mean depth of its dots, off the stated depth when the
    # card is tilted: the nearest row within a quarter of the smallest card step
    steps = np.diff(np.unique(cards.depths_mm))
    tol = 0.25 * float(steps.min()) if len(steps) else math.inf

    def model_error(z_mm: float) -> tuple[float, float]:
        if not len(model_rows):
            return math.nan, math.nan
        at = int(np.argmin(np.abs(model_rows[:, 0] - z_mm)))
        if not abs(model_rows[at, 0] - z_mm) <= tol:
            return math.nan, math.nan
        _, ex, ey, ez = model_rows[at]
        return math.hypot(ex, ey), float(ez)

    found = points.groupby("card").size()
    views = points.groupby("card")[["u", "v"]].apply(lambda g: len(g.drop_duplicates()))
    rows = []
    for k, card in enumerate(cards.cards):
        n = int(found.get(k, 0))
        lateral, depth = model_error(card.z_mm)
        rows.append({"card": k, "file": card.path.name, "z_mm": card.z_mm,
                     "n_views": int(views.get(k, 0)), "n_points": n,
                     "n_rejected": n - int(kept.get(card.z_mm, 0)),
                     "rms_px": float(rms.get(card.z_mm, np.nan)),
                     "model_error_lateral_mm": lateral, "model_error_z_mm": depth})
    return pd.DataFrame(rows)

