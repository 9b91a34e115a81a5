"""plenoptrack: 3D particle location, sizing and tracking from plenoptic camera images."""

from .camera import CameraSpec, load_camera, preset, save_camera
from .errors import (CalibrationError, CameraSpecError, ImageSizeError, InputFileError,
                     NoParticlesWarning, PlenoptrackError, PlenoptrackWarning)

__version__ = "0.1.0"

__all__ = [
    "CameraSpec", "load_camera", "preset", "save_camera",
    "PlenoptrackError", "InputFileError", "CameraSpecError", "CalibrationError",
    "ImageSizeError", "PlenoptrackWarning", "NoParticlesWarning", "__version__",
]
