"""Column names shared by every table (trackpy-compatible)."""

POS_COLUMNS = ("x", "y", "z")
"""Object-space position columns, mm."""
T_COLUMN = "frame"
"""Frame index column."""
ID_COLUMN = "particle"
"""Particle identity column (ground truth or after linking)."""
DIAMETER_COLUMN = "diameter"
"""Particle diameter column, mm."""
LF_COLUMNS = ("u", "v", "s", "t")
"""Light-field coordinates of a detection: view (u, v) and in-view position (s, t)."""
TRUTH_COLUMNS = (T_COLUMN, ID_COLUMN, *POS_COLUMNS, DIAMETER_COLUMN)
"""Columns of a simulator ``truth.parquet``."""
