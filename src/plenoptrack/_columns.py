"""Column names shared by every table (trackpy-compatible)."""

POS_COLUMNS = ("x", "y", "z")
"""Object-space position columns, mm."""
SIGMA_COLUMNS = ("sigma_x", "sigma_y", "sigma_z")
"""Standard uncertainty of each position column, mm."""
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
"""Particle shape column: ``"sphere"``, ``"ellipsoid"`` (prolate spheroid) or
``"fragment"`` (irregular body)."""
ASPECT_COLUMN = "aspect"
"""Long semi-axis over the two equal short semi-axes of a spheroid (>= 1; 1 for spheres);
for a fragment, that of its equivalent ellipsoid (the ellipsoid with the same second
moments of volume)."""
AXIS_COLUMNS = ("axis_x", "axis_y", "axis_z")
"""Unit vector of a spheroid's long axis (of a fragment's equivalent ellipsoid), world frame."""
SHAPE_COLUMNS = (SHAPE_COLUMN, ASPECT_COLUMN, *AXIS_COLUMNS)
"""Optional shape columns of a particles or truth table; absent means spheres. With them,
``diameter`` is the volume-equivalent diameter."""
SHAPE_SEED_COLUMN = "shape_seed"
"""Seed (integer >= 0) of a fragment's irregular geometry; with ``diameter``, ``aspect`` and
the axis it fixes the body (:func:`plenoptrack.simulate.fragments.fragment_geometry`).
Present in tables that hold fragments (-1 on their other rows)."""
TRANSMISSION_COLUMN = "transmission"
"""Fraction of the back-light a particle lets through, in [0, 1); absent means opaque."""
VELOCITY_COLUMNS = ("velocity_x", "velocity_y", "velocity_z")
"""Particle velocity, mm per frame, world frame; absent means still. With an exposure
fraction, the image is blurred along ``velocity * exposure_fraction``."""
PARTICLE_TABLE_COLUMNS = (T_COLUMN, ID_COLUMN, *POS_COLUMNS, DIAMETER_COLUMN)
"""Columns every truth table must have (the silhouette columns are derived)."""
TRUTH_COLUMNS = (*PARTICLE_TABLE_COLUMNS, *SILHOUETTE_COLUMNS)
"""Columns of a simulator ``truth.parquet`` (ellipsoid scenes add :data:`SHAPE_COLUMNS`,
fragment scenes also :data:`SHAPE_SEED_COLUMN`; the particle effects add
:data:`TRANSMISSION_COLUMN` and :data:`VELOCITY_COLUMNS`)."""
OPTIONAL_TRUTH_COLUMNS = (*SHAPE_COLUMNS, SHAPE_SEED_COLUMN, TRANSMISSION_COLUMN,
                          *VELOCITY_COLUMNS)
"""Optional truth columns, in the order they follow :data:`TRUTH_COLUMNS`."""
