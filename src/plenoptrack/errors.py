"""Exceptions and warnings raised by plenoptrack.

Every error message says what was wrong and what to do about it; the command-line
interface prints it as one line and exits with a non-zero code: 2 for a usage error (an
option out of range, an output that would overwrite an input), 1 for a data error (a
missing, corrupt or implausible file). Catch :class:`PlenoptrackError` to handle any of
them. The errors about values also derive from :class:`ValueError`, so code written
against plain ``ValueError`` keeps working.
"""

__all__ = [
    "PlenoptrackError", "UsageError", "SettingsError", "OutputConflictError",
    "InputFileError", "CameraSpecError", "CalibrationError", "ImageSizeError",
    "PlenoptrackWarning", "NoParticlesWarning", "VignettingWarning", "ExposureWarning",
    "CardDepthWarning", "CrowdedFrameWarning",
]


class PlenoptrackError(Exception):
    """Base class of all plenoptrack errors."""


class UsageError(PlenoptrackError, ValueError):
    """The request itself is invalid, whatever the data (exit code 2 on the command line)."""


class SettingsError(UsageError):
    """An option or setting is out of range, of the wrong kind or inconsistent."""


class OutputConflictError(UsageError):
    """An output path is one of the inputs, holds an input, or is given twice."""


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


class ExposureWarning(PlenoptrackWarning):
    """A raw frame is black (no light) or saturated, so it cannot show particles."""


class FlatFieldWarning(PlenoptrackWarning):
    """Frames are located without flat-fielding: the calibration's white image is missing
    or changed. Dust shadows and dead pixels may then be taken for particles."""


class CardDepthWarning(PlenoptrackWarning):
    """A dot card's stated depth disagrees with the depth its parallax across views shows."""


class CrowdedFrameWarning(PlenoptrackWarning):
    """A frame's particle images cover so much of each view that the locator will miss
    particles whose images merge with others' (:mod:`plenoptrack.locate.crowding`)."""
