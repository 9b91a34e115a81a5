"""Provenance of a result table: what made it, so that it can be made again.

Every particle table plenoptrack writes carries, in ``df.attrs["plenoptrack"]`` (stored in
the Parquet schema metadata or a CSV comment line, see :func:`plenoptrack.io.write_table`),
the package version, the method and its full settings, the calibration (file, SHA-256 and
format version) and the flat-field image. :func:`provenance` builds that record;
``plenoptrack locate --config`` accepts the ``settings`` part written back as TOML
(``plenoptrack settings --from-table particles.parquet``).
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

__all__ = ["provenance", "table_provenance"]


def provenance(*, method: str, settings: dict | None = None, calibration=None,
               calibration_file: str | Path | None = None,
               white_file: str | Path | None = None,
               inputs=None) -> dict:
    """The provenance record of a result table.

    Parameters
    ----------
    method : str
        Locating method, e.g. ``"perspective"``.
    settings : dict, optional
        The method's settings as nested plain data
        (:meth:`~plenoptrack.locate.PerspectiveLocator.to_dict`).
    calibration : Calibration, optional
        Its camera and format version are recorded.
    calibration_file : path, optional
        Recorded with its SHA-256, so a later run can tell whether it changed.
    white_file : path, optional
        The flat-field image frames were divided by (None: not flat-fielded).
    inputs : sequence of paths, optional
        The raw images located.

    Returns
    -------
    dict
        Plain JSON-serialisable data.
    """
    from . import __version__
    from .calibration import VERSION, file_sha256

    record = {"package": "plenoptrack", "package_version": __version__, "method": method,
              "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}
    if settings is not None:
        record["settings"] = settings
    if calibration is not None or calibration_file is not None:
        calib = {"format_version": VERSION}
        if calibration_file is not None:
            calib["file"] = str(calibration_file)
            calib["sha256"] = file_sha256(calibration_file)
        if calibration is not None:
            calib["camera"] = calibration.camera.to_dict()
        record["calibration"] = calib
    record["flat_field"] = None if white_file is None else {"white": str(white_file),
                                                            "sha256": file_sha256(white_file)}
    if inputs is not None:
        record["inputs"] = [str(p) for p in inputs]
    return record


def table_provenance(df) -> dict | None:
    """The provenance record a table was read with, or None (``df.attrs``)."""
    from .io import METADATA_KEY

    return df.attrs.get(METADATA_KEY)
