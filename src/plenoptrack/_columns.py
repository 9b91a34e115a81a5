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
PROJECTED_AREA_COLUMN = "projected_area"
"""Area of a particle's silhouette seen along the optical axis (orthographic), mm^2."""
ORIENTATION_COLUMN = "orientation"
"""Angle of the silhouette's long axis in the x-y plane, rad, from +x towards +y, in
[-pi/2, pi/2); 0 for a circular silhouette."""
SILHOUETTE_COLUMNS = (PROJECTED_AREA_COLUMN, ORIENTATION_COLUMN)
"""Silhouette columns of the simulator truth (every particle)."""
SHAPE_COLUMN = "shape"
"""Particle shape column: ``"sphere"`` or ``"ellipsoid"`` (prolate spheroid)."""
ASPECT_COLUMN = "aspect"
"""Long semi-axis over the two equal short semi-axes of a spheroid (>= 1; 1 for spheres)."""
AXIS_COLUMNS = ("axis_x", "axis_y", "axis_z")
"""Unit vector of a spheroid's long axis, world frame."""
SHAPE_COLUMNS = (SHAPE_COLUMN, ASPECT_COLUMN, *AXIS_COLUMNS)
"""Optional shape columns of a particles or truth table; absent means spheres. With them,
``diameter`` is the volume-equivalent diameter."""
PARTICLE_TABLE_COLUMNS = (T_COLUMN, ID_COLUMN, *POS_COLUMNS, DIAMETER_COLUMN)
"""Columns every truth table must have (the silhouette columns are derived)."""
TRUTH_COLUMNS = (*PARTICLE_TABLE_COLUMNS, *SILHOUETTE_COLUMNS)
"""Columns of a simulator ``truth.parquet`` (ellipsoid scenes add :data:`SHAPE_COLUMNS`)."""
