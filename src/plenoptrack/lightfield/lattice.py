"""The lenslet lattice: where every microlens image is centred on the sensor.

A :class:`LensletGrid` is an affine lattice in sensor pixel coordinates (row, col), pixel
centres at integer coordinates. Lens ``(i, j)`` (row ``i``, column ``j``) is centred at::

    centre(i, j) = origin_px + (j + odd_row_shift * (i % 2)) * col_step_px + i * row_step_px

``col_step_px`` joins neighbours along a lens row (nearly horizontal), ``row_step_px``
joins consecutive rows. For a hexagonal grid ``odd_row_shift`` is +0.5 or -0.5 (odd rows
shifted by half a pitch along the row), for a rectangular grid it is 0.

These centres are the centres of the microlens *images* (the images of the main-lens
aperture centre), which is what a white image shows and what decoding needs. They lie on
a lattice slightly larger than the physical microlens array.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import CalibrationError

__all__ = ["LensletGrid"]


@dataclass(frozen=True)
class LensletGrid:
    """Affine lattice of microlens-image centres.

    Parameters
    ----------
    grid_type : {"hex", "rect"}
        Lattice packing.
    shape : (int, int)
        Number of lenslets as (rows, cols) that the lattice indexes; lenses whose image
        centre falls off the sensor may be included (decoding masks them).
    origin_px : (2,) float
        Centre of lens (0, 0) as (row, col), sensor pixels.
    col_step_px : (2,) float
        Step (drow, dcol) from lens (i, j) to lens (i, j + 1), pixels.
    row_step_px : (2,) float
        Step (drow, dcol) from lens (i, j) to lens (i + 1, j), before the odd-row shift.
    odd_row_shift : float
        Shift of odd rows along ``col_step_px``, in units of that step (+-0.5 hex, 0 rect).
    sensor_shape_px : (int, int)
        Sensor (rows, cols) the grid was measured on.
    """

    grid_type: str
    shape: tuple[int, int]
    origin_px: tuple[float, float]
    col_step_px: tuple[float, float]
    row_step_px: tuple[float, float]
    odd_row_shift: float
    sensor_shape_px: tuple[int, int]

    def __post_init__(self) -> None:
        if self.grid_type not in ("hex", "rect"):
            raise CalibrationError(f"grid_type must be 'hex' or 'rect'; got {self.grid_type!r}")
        for name in ("origin_px", "col_step_px", "row_step_px"):
            value = tuple(float(x) for x in getattr(self, name))
            if len(value) != 2 or not all(math.isfinite(x) for x in value):
                raise CalibrationError(f"lenslet grid {name} must be two finite numbers; got {value!r}")
            object.__setattr__(self, name, value)
        for name in ("shape", "sensor_shape_px"):
            value = tuple(int(x) for x in getattr(self, name))
            if len(value) != 2 or min(value) < 1:
                raise CalibrationError(f"lenslet grid {name} must be two positive integers; got {value!r}")
            object.__setattr__(self, name, value)
        object.__setattr__(self, "odd_row_shift", float(self.odd_row_shift))
        if self.grid_type == "rect" and self.odd_row_shift != 0:
            raise CalibrationError("a rectangular lenslet grid must have odd_row_shift = 0")
        if self.grid_type == "hex" and abs(abs(self.odd_row_shift) - 0.5) > 1e-9:
            raise CalibrationError("a hexagonal lenslet grid must have odd_row_shift = +-0.5; "
                                   f"got {self.odd_row_shift}")
        if abs(np.linalg.det(self.basis)) < 1.0:
            raise CalibrationError("lenslet grid steps are degenerate (lenslets under one pixel apart)")

    # --- derived quantities -------------------------------------------------------
    @property
    def basis(self) -> np.ndarray:
        """(2, 2) array, rows are ``col_step_px`` and ``row_step_px``."""
        return np.array([self.col_step_px, self.row_step_px], dtype=float)

    @property
    def pitch_px(self) -> float:
        """Centre spacing along a lens row, pixels."""
        return float(np.hypot(*self.col_step_px))

    @property
    def row_spacing_px(self) -> float:
        """Perpendicular distance between consecutive lens rows, pixels."""
        a, b = np.asarray(self.col_step_px), np.asarray(self.row_step_px)
        return float(abs(a[0] * b[1] - a[1] * b[0]) / np.hypot(*a))

    @property
    def rotation_deg(self) -> float:
        """Angle of lens rows from the sensor column axis, degrees (positive: rows
        descend, i.e. row index increases, as column increases)."""
        dr, dc = self.col_step_px
        return float(np.degrees(np.arctan2(dr, dc)))

    def centers(self) -> np.ndarray:
        """Centres of all lenslets, ``(rows, cols, 2)`` float64 as (row, col) pixels."""
        i, j = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return self.centers_of(i, j)

    def centers_of(self, i, j) -> np.ndarray:
        """Centres of lenslets with integer indices ``i`` (row) and ``j`` (col), ``(..., 2)``."""
        i = np.asarray(i, dtype=float)
        j = np.asarray(j, dtype=float)
        jj = j + self.odd_row_shift * (np.asarray(i, dtype=int) % 2)
        o = np.asarray(self.origin_px)
        return (o + jj[..., None] * np.asarray(self.col_step_px)
                + i[..., None] * np.asarray(self.row_step_px))

    def lattice_coords(self, points_px: np.ndarray) -> np.ndarray:
        """Map (row, col) pixel positions to continuous lattice coordinates (i, j).

        The odd-row shift is not removed: ``j`` is measured along ``col_step_px`` from the
        row-0 origin, so the centre of lens (i, j) maps to (i, j + odd_row_shift * (i % 2)).
        """
        p = np.asarray(points_px, dtype=float) - np.asarray(self.origin_px)
        jj_i = np.linalg.solve(self.basis.T, p.reshape(-1, 2).T).T  # columns (j, i)
        return jj_i[:, ::-1].reshape(p.shape)

    # --- serialisation --------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "grid_type": self.grid_type,
            "shape": list(self.shape),
            "origin_px": list(self.origin_px),
            "col_step_px": list(self.col_step_px),
            "row_step_px": list(self.row_step_px),
            "odd_row_shift": self.odd_row_shift,
            "sensor_shape_px": list(self.sensor_shape_px),
        }

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "lenslet grid") -> "LensletGrid":
        keys = ("grid_type", "shape", "origin_px", "col_step_px", "row_step_px",
                "odd_row_shift", "sensor_shape_px")
        if not isinstance(data, dict):
            raise CalibrationError(f"{source}: lenslet grid must be a table of {list(keys)}; "
                                   f"got {type(data).__name__}; re-run `plenoptrack calibrate-grid`")
        missing = [k for k in keys if k not in data]
        if missing:
            raise CalibrationError(f"{source}: lenslet grid is missing {missing}; "
                                   "re-run `plenoptrack calibrate-grid`")
        try:
            return cls(**{k: data[k] for k in keys})
        except CalibrationError as exc:
            raise CalibrationError(f"{source}: {exc}") from None
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{source}: corrupt lenslet grid ({exc})") from None
