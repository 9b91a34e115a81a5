"""
Locating particles in 3D
========================

The perspective-shift method finds every particle in every perspective view, groups the
centroids that belong to one particle across views, and triangulates its position
through the Direct Light Field Calibration (DLFC): a 4th-order polynomial, fitted to
images of dot cards at known depths, that maps an object position and a view to the
position in that view.

This example simulates a scene with dot cards, calibrates, locates the particles and
compares them with the ground truth.
"""

import tempfile

import pandas as pd

from plenoptrack.calibrate import calibrate
from plenoptrack.evaluate import evaluate_particles, match_particles
from plenoptrack.io import read_raw
from plenoptrack.lightfield import decode
from plenoptrack.locate import locate_frame
from plenoptrack.plots import plot_errors_vs_depth, plot_particles_3d
from plenoptrack.simulate import simulate_dataset

# %%
# Simulate
# --------
# 40 particles of 0.4 mm in the 20 mm deep volume of the ``small`` camera, plus the
# white image and 11 dot cards from 10 mm in front of the focal plane to 10 mm behind.

workdir = tempfile.TemporaryDirectory()
sim = simulate_dataset("small", workdir.name, seed=2, n_particles=40)
print(f"{len(sim.truth)} particles; dot cards at {sim.dotcard_depths_mm} mm")

# %%
# Calibrate
# ---------
# :func:`plenoptrack.calibrate.calibrate` measures the lenslet grid from the white
# image, finds the dots of every card in every view and fits the DLFC. The report gives
# the fit residual per card, in view pixels.

calib, report = calibrate(sim.white_path, sim.dotcards_path.parent, sim.camera)
print(f"DLFC order {calib.dlfc.order}: {report.n_points} dot centroids, "
      f"RMS residual {report.rms_px:.3f} px")
print(report.cards.round(3).to_string(index=False))

# %%
# Locate
# ------
# One call per raw frame, flat-fielded with the white image (decoded once): dust
# shadows and dead pixels the frames share with it are then not taken for particles.
# The table holds the position, its standard uncertainty, the number of views the
# particle was found in and its size and shape.

white = decode(read_raw(sim.white_path), calib.grid)
result = locate_frame(read_raw(sim.frame_paths[0]), calib, white=white)
particles = result.particles
print(f"{len(particles)} particles from {len(result.detections)} centroids "
      f"in {result.detections[['u', 'v']].drop_duplicates().shape[0]} views")
print(particles[["x", "y", "z", "sigma_z", "n_views", "diameter"]].head().round(3)
      .to_string(index=False))

# %%
# Compare with the ground truth
# -----------------------------
# Measured and true particles are paired one-to-one within 1 mm. Lateral errors are
# much smaller than depth errors: depth comes from the small parallax across the
# aperture. The three largest errors are listed below.

evaluation = evaluate_particles(particles, sim.truth, tolerance_mm=1.0)
errors = pd.DataFrame({
    "mean (mm)": [evaluation.mean_error_x, evaluation.mean_error_y, evaluation.mean_error_z],
    "sd (mm)": [evaluation.std_error_x, evaluation.std_error_y, evaluation.std_error_z],
}, index=["x", "y", "z"])
print(f"recall {evaluation.recall:.3f}, precision {evaluation.precision:.3f}")
print(errors.to_string(float_format="{:+.4f}".format))

pairs = match_particles(particles, sim.truth, tolerance_mm=1.0)
print(pairs.sort_values("distance", ascending=False).head(3).round(4).to_string(index=False))

# %%
# Where the particles are
# -----------------------
# Three orthogonal projections, coloured by depth; the open circles are the true
# positions.

fig_3d = plot_particles_3d(particles, truth=sim.truth)

# %%
# Depth error against depth
# -------------------------
# The mean depth error (accuracy) and its spread (precision) in 2 mm bins of true depth.

fig = plot_errors_vs_depth(particles, sim.truth, tolerance_mm=1.0, bins=10)
workdir.cleanup()
