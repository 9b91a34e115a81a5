"""The calibration file: everything measured once per camera set-up.

A calibration file is JSON with a format tag and a version, the nominal camera it was
made for, the lenslet grid measured from a white image and, once fitted, the volumetric
(DLFC) calibration in a ``dlfc`` section (with its own format tag and version, see
:meth:`plenoptrack.locate.dlfc.DLFC.to_dict`). It is validated on load: a corrupt file
or DLFC section, a file of another format version, or a file made for another camera is
refused with a message that says what to do. The whole workflow, white image and dot
cards to calibration file, is :func:`plenoptrack.calibrate.calibrate`. A
``white_image`` section records the white image (path and SHA-256, :func:`record_white`)
so that ``plenoptrack locate`` can flat-field the frames with it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .camera import CameraSpec
from .errors import CalibrationError, CameraSpecError
from .io import atomic_write_text
from .lightfield.lattice import LensletGrid
from .locate.dlfc import DLFC

__all__ = ["Calibration", "load_calibration", "save_calibration", "record_white",
           "find_white", "file_sha256", "FORMAT", "VERSION", "WHITE_KEY"]

FORMAT = "plenoptrack-calibration"
VERSION = 1
EDGE_BLUR_KEY = "edge_blur_by_depth_px"
LOCKING_KEY = "locking_pattern"


@dataclass(frozen=True)
class Calibration:
    """Calibration of one camera set-up.

    Parameters
    ----------
    camera : CameraSpec
        Nominal camera the calibration was made with.
    grid : LensletGrid
        Microlens-image centres measured from a white image.
    vignetting : (n_v, n_u) float ndarray or None
        Relative brightness of each angular sample in the white image (1 = unvignetted),
        used to flag vignetted views.
    extra : dict
        Further sections, stored as JSON; ``extra["dlfc"]`` is the volumetric calibration
        (:meth:`DLFC.to_dict` output), read through :attr:`dlfc` and set with
        :meth:`with_dlfc`; ``extra["edge_blur_by_depth_px"]`` the views' edge blur
        measured on the dot cards, read through :attr:`edge_blur_by_depth` and set with
        :meth:`with_edge_blur`; ``extra["locking_pattern"]`` the dot cards' pixel-locking
        pattern, read through :attr:`locking_pattern` and set with
        :meth:`with_locking_pattern`.
    """

    camera: CameraSpec
    grid: LensletGrid
    vignetting: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def has_dlfc(self) -> bool:
        """True when the calibration holds a volumetric (DLFC) calibration."""
        return "dlfc" in self.extra

    @property
    def dlfc(self) -> DLFC:
        """The Direct Light Field Calibration stored in ``extra["dlfc"]``.

        Raises
        ------
        CalibrationError
            If there is none (a grid-only calibration) or the section is corrupt.
        """
        if not self.has_dlfc:
            raise CalibrationError("calibration file has no DLFC; run `plenoptrack calibrate` "
                                   "with dot cards")
        return DLFC.from_dict(self.extra["dlfc"], source="calibration [dlfc]")

    def with_dlfc(self, dlfc: DLFC) -> "Calibration":
        """A copy of this calibration holding ``dlfc`` (replacing any earlier one).

        Parameters
        ----------
        dlfc : DLFC
            Fitted volumetric calibration (:func:`plenoptrack.locate.dlfc.fit_dlfc`).
        """
        if not isinstance(dlfc, DLFC):
            raise TypeError(f"dlfc must be a DLFC; got {type(dlfc).__name__}")
        return replace(self, extra={**self.extra, "dlfc": dlfc.to_dict()})

    @property
    def edge_blur_by_depth(self) -> np.ndarray | None:
        """The views' edge blur per dot-card depth: (K, 2) rows ``(z mm, sigma px)``
        (:func:`~plenoptrack.locate.opacity.edge_blur_by_depth`), or None when the
        calibration has none (made without dot cards, or by an older version)."""
        rows = self.extra.get(EDGE_BLUR_KEY)
        return None if not rows else np.asarray(rows, dtype=float).reshape(-1, 2)

    def with_edge_blur(self, rows) -> "Calibration":
        """A copy of this calibration holding the edge blur ``rows`` ``(z, sigma_px)``."""
        rows = _edge_blur_rows(rows, source="edge blur")
        return replace(self, extra={**self.extra, EDGE_BLUR_KEY: rows.tolist()})

    @property
    def locking_pattern(self):
        """The pull of view centroids towards the lens centres measured on the dot cards
        (:class:`~plenoptrack.locate.pixel_locking.LockingPattern`), or None when the
        calibration has none (made without dot cards, or by an older version). The
        locator uses it in frames too sparse to show their own."""
        from .locate.pixel_locking import LockingPattern

        data = self.extra.get(LOCKING_KEY)
        return None if data is None else LockingPattern.from_dict(data, source="calibration")

    def with_locking_pattern(self, pattern) -> "Calibration":
        """A copy of this calibration holding the pixel-locking ``pattern``."""
        return replace(self, extra={**self.extra, LOCKING_KEY: pattern.to_dict()})

    def check_camera(self, camera: CameraSpec, *, source: str = "calibration") -> None:
        """Raise :class:`CalibrationError` if ``camera`` is not the camera calibrated."""
        mine, theirs = self.camera.to_dict(), camera.to_dict()
        mine.pop("name", None)
        theirs.pop("name", None)
        diff = sorted(k for k in mine if mine[k] != theirs.get(k))
        if diff:
            raise CalibrationError(
                f"{source}: calibration was made for another camera (differs in {', '.join(diff)}); "
                "calibrate this camera with `plenoptrack calibrate-grid`")

    def check_image(self, image: np.ndarray, *, source: str = "image") -> None:
        """Raise :class:`CalibrationError` if ``image`` is not the calibrated sensor size."""
        if tuple(image.shape[-2:]) != tuple(self.grid.sensor_shape_px):
            r, c = self.grid.sensor_shape_px
            raise CalibrationError(
                f"{source}: image is {image.shape[-2]} x {image.shape[-1]} pixels but the "
                f"calibration is for a {r} x {c} sensor; use the calibration of this camera")

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "camera": self.camera.to_dict(),
            "lenslet_grid": self.grid.to_dict(),
            "vignetting": None if self.vignetting is None else np.asarray(self.vignetting).tolist(),
            **self.extra,
        }

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "calibration") -> "Calibration":
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise CalibrationError(f"{source}: not a plenoptrack calibration file "
                                   "(missing format tag); make one with `plenoptrack calibrate-grid`")
        version = data.get("version")
        if version != VERSION:
            raise CalibrationError(f"{source}: calibration format version {version!r} is not "
                                   f"supported (this plenoptrack reads version {VERSION}); "
                                   "re-run the calibration")
        for key in ("camera", "lenslet_grid"):
            if key not in data:
                raise CalibrationError(f"{source}: calibration file has no '{key}' section; "
                                       "re-run the calibration")
        try:
            camera = CameraSpec.from_dict(data["camera"], source=f"{source} [camera]")
        except CameraSpecError as exc:
            raise CalibrationError(str(exc)) from None
        grid = LensletGrid.from_dict(data["lenslet_grid"], source=source)
        if tuple(grid.sensor_shape_px) != tuple(camera.sensor_shape_px):
            raise CalibrationError(f"{source}: lenslet grid was measured on a "
                                   f"{grid.sensor_shape_px} sensor but the camera has "
                                   f"{camera.sensor_shape_px}; re-run the calibration")
        vignetting = data.get("vignetting")
        if vignetting is not None:
            try:
                vignetting = np.asarray(vignetting, dtype=float)
            except (TypeError, ValueError):
                vignetting = np.full(1, np.nan)
            if vignetting.ndim != 2 or not np.all(np.isfinite(vignetting)):
                raise CalibrationError(f"{source}: corrupt vignetting table; re-run the calibration")
        known = {"format", "version", "camera", "lenslet_grid", "vignetting"}
        extra = {k: v for k, v in data.items() if k not in known}
        if "dlfc" in extra:  # validate now, so that a corrupt file is refused on load
            DLFC.from_dict(extra["dlfc"], source=f"{source} [dlfc]")
        if EDGE_BLUR_KEY in extra:
            _edge_blur_rows(extra[EDGE_BLUR_KEY], source=source)
        if LOCKING_KEY in extra:
            from .locate.pixel_locking import LockingPattern

            LockingPattern.from_dict(extra[LOCKING_KEY], source=source)
        return cls(camera=camera, grid=grid, vignetting=vignetting, extra=extra)


def _edge_blur_rows(rows, *, source: str) -> np.ndarray:
    """``rows`` as a (K, 2) float array of ``(z, sigma)`` with finite values and positive
    sigma; :class:`CalibrationError` otherwise."""
    try:
        out = np.asarray(rows, dtype=float)
    except (TypeError, ValueError):
        out = np.full((1, 2), np.nan)
    if (out.ndim != 2 or out.shape[1] != 2 or not np.all(np.isfinite(out))
            or not np.all(out[:, 1] > 0)):
        raise CalibrationError(f"{source}: corrupt edge blur table ('{EDGE_BLUR_KEY}': rows "
                               "of depth and positive blur); re-run the calibration")
    return out


def save_calibration(calibration: Calibration, path: str | Path) -> Path:
    """Write ``calibration`` as JSON, atomically; return the path."""
    return atomic_write_text(path, json.dumps(calibration.to_dict(), indent=1) + "\n")


def load_calibration(path: str | Path, *, camera: CameraSpec | None = None) -> Calibration:
    """Read and validate a calibration file.

    Parameters
    ----------
    path : str or Path
        JSON file written by :func:`save_calibration`.
    camera : CameraSpec, optional
        If given, refuse a calibration made for a different camera.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file not found; make one with "
                               "`plenoptrack calibrate-grid`")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: calibration file is corrupt (not valid JSON: {exc}); "
                               "re-run the calibration") from None
    calibration = Calibration.from_dict(data, source=str(path))
    if camera is not None:
        calibration.check_camera(camera, source=str(path))
    return calibration


WHITE_KEY = "white_image"
"""Section of the calibration file recording the white image: ``file`` (its path,
relative to the calibration file's folder when it lies below it) and ``sha256``."""


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def record_white(calibration: Calibration, white_path: str | Path, *,
                 calibration_path: str | Path) -> Calibration:
    """A copy of ``calibration`` that records the white image used to make it.

    ``plenoptrack locate`` finds the white image through this record and flat-fields
    every frame with it (see :func:`find_white`).

    Parameters
    ----------
    calibration : Calibration
    white_path : str or Path
        The white (flat-field) image file.
    calibration_path : str or Path
        Where the calibration file will be written: the record is relative to its folder
        (so that a folder holding both can be moved), or absolute if the white image lies
        elsewhere.
    """
    white = Path(white_path).resolve()
    folder = Path(calibration_path).resolve().parent
    try:
        name = white.relative_to(folder).as_posix()
    except ValueError:
        name = str(white)
    return replace(calibration, extra={**calibration.extra,
                                       WHITE_KEY: {"file": name, "sha256": file_sha256(white)}})


def find_white(calibration: Calibration, calibration_path: str | Path) -> tuple[Path | None, str]:
    """The white image a calibration file records, if it is still there unchanged.

    Returns
    -------
    path : Path or None
        The white image, or None.
    why : str
        Empty when ``path`` is found; otherwise why not, as one sentence naming the file.
    """
    record = calibration.extra.get(WHITE_KEY)
    if not isinstance(record, dict) or not isinstance(record.get("file"), str):
        return None, f"{calibration_path} records no white image"
    path = Path(record["file"])
    if not path.is_absolute():
        path = Path(calibration_path).parent / path
    if not path.is_file():
        return None, f"the white image {path} recorded in {calibration_path} is not there"
    if record.get("sha256") != file_sha256(path):
        return None, (f"the white image {path} changed since {calibration_path} was made "
                      "(SHA-256 differs)")
    return path, ""


def calibrate_from_white(white, camera: CameraSpec, *, progress: bool = False):
    """Measure the lenslet grid and vignetting of ``camera`` from a white image.

    Parameters
    ----------
    white : str, Path or (rows, cols) ndarray
        White (flat-field) image taken through the microlens array, or its TIFF file.
    camera : CameraSpec
        Nominal camera; its grid type and sensor size are checked against the image.

    Returns
    -------
    calibration : Calibration
        Camera, lenslet grid and per-view vignetting.
    measurement : GridMeasurement
        Detected centres and fit residuals, for reporting.
    """
    from .io import check_image_shape, read_raw
    from .lightfield.decode import decode
    from .lightfield.grid import measure_grid

    source = "white image"
    if isinstance(white, (str, Path)):
        source = str(white)
        white = read_raw(white)
    white = np.asarray(white)
    check_image_shape(white, camera.sensor_shape_px, source=source)
    measurement = measure_grid(white, grid_type=camera.grid_type,
                               pitch_px=camera.pixels_per_lenslet, progress=progress)
    # Decoding the white image against itself limits each view's valid fraction by its
    # measured brightness: views a smaller-than-matched aperture leaves dark drop out.
    vignetting = decode(white, measurement.grid, white=white).valid_fraction
    return Calibration(camera=camera, grid=measurement.grid, vignetting=vignetting), measurement
