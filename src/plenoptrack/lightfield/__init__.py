"""Light-field decoding: lenslet grid, 4D light field, perspective views, refocusing."""

from .decode import VIEW_MASK_THRESHOLD, LightField, decode
from .grid import GridMeasurement, calibrate_grid, measure_grid
from .lattice import LensletGrid
from .refocus import (best_focus_depth, focal_stack, refocus, refocus_shifts, sharpness,
                      view_shift_per_u)
from .views import (perspective_views, scale_to_uint8, view, view_mosaic, write_mosaic_png,
                    write_views_tiff)

__all__ = [
    "LensletGrid", "GridMeasurement", "measure_grid", "calibrate_grid",
    "LightField", "decode", "VIEW_MASK_THRESHOLD",
    "perspective_views", "view", "view_mosaic", "scale_to_uint8", "write_views_tiff",
    "write_mosaic_png",
    "refocus", "focal_stack", "refocus_shifts", "view_shift_per_u", "sharpness",
    "best_focus_depth",
]
