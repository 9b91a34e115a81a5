"""Exceptions and warnings raised by plenoptrack.

Every error message says what was wrong and what to do about it; the command-line
interface prints it as one line and exits with a non-zero code. Catch
:class:`PlenoptrackError` to handle any of them.
"""

__all__ = [
    "PlenoptrackError", "InputFileError", "CameraSpecError", "CalibrationError",
    "ImageSizeError", "PlenoptrackWarning", "NoParticlesWarning", "VignettingWarning",
]


class PlenoptrackError(Exception):
    """Base class of all plenoptrack errors."""


class InputFileError(PlenoptrackError, ValueError):
    """A file is missing, unreadable, truncated or of the wrong kind or dtype."""


class CameraSpecError(PlenoptrackError, ValueError):
    """A camera description is incomplete or inconsistent."""


class CalibrationError(PlenoptrackError, ValueError):
    """A calibration failed, or a calibration file is corrupt or belongs to another camera."""


class ImageSizeError(PlenoptrackError, ValueError):
    """An image does not have the size the camera description or calibration expects."""


class PlenoptrackWarning(UserWarning):
    """Base class of plenoptrack warnings (filter them with ``warnings.filterwarnings``)."""


class NoParticlesWarning(PlenoptrackWarning):
    """An image or view contained no particles; an empty result was returned."""


class VignettingWarning(PlenoptrackWarning):
    """Part of the data is vignetted more than expected."""
