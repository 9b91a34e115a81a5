"""
Perspective views and parallax
==============================

A plenoptic camera records, behind every microlens, a small image of the main-lens
aperture. Taking the same pixel ``(u, v)`` from behind every microlens gives a
*perspective view*: the scene seen through one small part of the aperture. A particle
off the focal plane moves from view to view, and that parallax is what the
perspective-shift method turns into depth.

This example simulates a few particles, measures the lenslet grid from the white image,
decodes the raw frame into the light field ``L[v, u, t, s]``, shows every view, and
follows one particle across a row of views.
"""

import tempfile

import numpy as np
from matplotlib.figure import Figure

from plenoptrack.io import read_raw
from plenoptrack.lightfield import calibrate_grid, decode, view_shift_per_u
from plenoptrack.locate import segment_views
from plenoptrack.plots import plot_view, plot_view_mosaic
from plenoptrack.simulate import simulate_dataset

# %%
# Simulate a scene
# ----------------
# Ten 0.4 mm particles in the volume of the ``small`` camera (about 65 x 49 hexagonally
# packed microlenses, 14 pixels each). No dot cards are needed here: the lenslet grid
# comes from the white image alone.

workdir = tempfile.TemporaryDirectory()
sim = simulate_dataset("small", workdir.name, seed=3, n_particles=10, dotcard_depths=[])
camera = sim.camera
print(sim.truth[["particle", "x", "y", "z"]].round(2).to_string(index=False))

# %%
# Calibrate the grid and decode
# -----------------------------
# The grid of microlens-image centres is measured from the white image; the raw frame is
# then decoded and divided by the decoded white image (flat field), so the background is
# close to 1 and particles are dark.

white = read_raw(sim.white_path)
grid = calibrate_grid(white, grid_type=camera.grid_type)
lf = decode(read_raw(sim.frame_paths[0]), grid, white=white)
print(f"light field L[v, u, t, s]: {lf.data.shape}, {int(lf.view_mask.sum())} valid views")

fig_mosaic = plot_view_mosaic(lf)

# %%
# The views at the rim of the microlens images are vignetted (black in the mosaic): only
# the ``valid`` ones, at least 60 % unvignetted, are used to locate particles.
#
# Parallax across a row of views
# ------------------------------
# Take the particle farthest from the focal plane and predict where it sits in the
# central view ``u = v = 0``: the chief ray images world ``(x, y)`` at depth ``z`` at
# ``(x, y) s_i / (s_o + z)`` on the microlens plane (see ``docs/conventions.md``).
# Its centroid is then followed along the row ``v = 0``.

particle = sim.truth.loc[sim.truth["z"].abs().idxmax()]
s_i, s_o = camera.image_distance_mm, camera.object_distance_mm
f_ml = camera.microlens_focal_length_um / 1000.0
scale = s_i / (s_o + particle["z"]) * (1.0 + f_ml / s_i) / (camera.pixel_pitch_um / 1000.0)
rows, cols = lf.sensor_shape_px
sensor_rc = ((rows - 1) / 2 + particle["y"] * scale, (cols - 1) / 2 + particle["x"] * scale)
s0, t0 = lf.from_sensor(sensor_rc)
print(f"particle {int(particle['particle'])} at z = {particle['z']:+.2f} mm: "
      f"central view (s, t) = ({s0:.1f}, {t0:.1f}) predicted")

# Expected shift per unit u, in view pixels (positive: behind the focal plane).
slope = float(view_shift_per_u(camera, camera.alpha_for_depth(particle["z"]))) / lf.sample_spacing_px

detections = segment_views(lf)
row = detections[detections["v"] == 0]
us = [u for u in lf.u if lf.view_mask[lf.index_of(u, 0.0)]]
track = []
for u in us:
    in_view = row[row["u"] == u]
    guess = np.array([s0 + slope * u, t0])
    dist = np.hypot(in_view["s"] - guess[0], in_view["t"] - guess[1])
    if len(dist) and dist.min() < 3.0:
        best = in_view.loc[dist.idxmin()]
        track.append((u, best["s"], best["t"]))
track = np.array(track)
fit_slope = np.polyfit(track[:, 0], track[:, 1], 1)[0]
print(f"found in {len(track)} of {len(us)} views of the row v = 0")
print(f"ds/du measured {fit_slope:+.3f}, predicted {slope:+.3f} view px per u")

# %%
# The crops below (every second view of the row, red crosses at the centroids) are
# centred on the particle's mean position: in front of the focal plane it slides
# towards smaller ``s`` as ``u`` grows, by the same amount per view. Its neighbour,
# close to the focal plane, hardly moves.

half = 8
sc, tc = (int(round(c)) for c in track[:, 1:].mean(axis=0))
t_lo, t_hi = max(tc - half, 0), min(tc + half + 1, lf.n_t)
s_lo, s_hi = max(sc - half, 0), min(sc + half + 1, lf.n_s)
fig_parallax = Figure(figsize=(9.0, 2.6), layout="constrained")
shown = [u for u in us if u % 2 == 0]
axes = fig_parallax.subplots(1, len(shown), sharey=True)
for ax, u in zip(axes, shown):
    crop = lf.view(u, 0.0)[t_lo:t_hi, s_lo:s_hi]
    ax.imshow(crop, cmap="gray", vmin=0.0, vmax=1.1,
              extent=(s_lo - 0.5, s_hi - 0.5, t_hi - 0.5, t_lo - 0.5))
    hit = track[track[:, 0] == u]
    if len(hit):
        ax.plot(hit[0, 1], hit[0, 2], "+", color="tab:red", ms=10)
    ax.set_title(f"u = {u:g}", fontsize="small")
    ax.set_xlabel("s (view px)")
axes[0].set_ylabel("t (view px)")
fig_parallax.suptitle(f"particle at z = {particle['z']:+.1f} mm across views v = 0")

# %%
# Detections in one view
# ----------------------
# Every valid view is segmented on its own; these are the centroids found in the view
# ``u = 4, v = 0``.

fig = plot_view(lf, 4, 0, detections=detections)
workdir.cleanup()
