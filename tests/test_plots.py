"""Tests of plenoptrack.plots: every function returns a labelled Figure, bad input a ValueError."""

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import PathCollection
from matplotlib.figure import Figure
from matplotlib.image import AxesImage

from plenoptrack.lightfield import LightField
from plenoptrack.plots import (plot_errors_vs_depth, plot_focal_stack_sharpness,
                               plot_particles_3d, plot_view, plot_view_mosaic)


@pytest.fixture(scope="module")
def lf():
    """A 5 x 5-view light field of 12 x 16 samples with one dark spot moving with u."""
    rng = np.random.default_rng(0)
    data = np.ones((5, 5, 12, 16), dtype=np.float32) + 0.01 * rng.standard_normal((5, 5, 12, 16)).astype(np.float32)
    for iv in range(5):
        for iu in range(5):
            data[iv, iu, 6, 8 + iu - 2] = 0.2
    ang = np.arange(-2.0, 3.0)
    valid = np.ones((5, 5))
    valid[0, 0] = valid[0, -1] = valid[-1, 0] = valid[-1, -1] = 0.3
    return LightField(data=data, u=ang, v=ang.copy(), valid_fraction=valid,
                      spatial_mask=np.ones((12, 16), bool), origin_px=(10.0, 10.0),
                      s_step_px=(0.0, 5.0), t_step_px=(5.0, 0.0), sensor_shape_px=(70, 90),
                      grid_type="rect", flat_fielded=True)


@pytest.fixture(scope="module")
def truth():
    rng = np.random.default_rng(1)
    n = 60
    return pd.DataFrame({"frame": 0, "x": rng.uniform(-4, 4, n), "y": rng.uniform(-2, 2, n),
                         "z": rng.uniform(-10, 10, n)})


@pytest.fixture(scope="module")
def measured(truth):
    rng = np.random.default_rng(2)
    out = truth.copy()
    out["z"] += rng.normal(0.1, 0.2, len(out))
    out[["x", "y"]] += rng.normal(0, 0.01, (len(out), 2))
    return out.iloc[:-5]  # five particles missed


def _labels(ax):
    return ax.get_xlabel(), ax.get_ylabel()


# --- plot_view_mosaic ----------------------------------------------------------------

def test_view_mosaic_figure(lf):
    fig = plot_view_mosaic(lf, gap=1)
    assert isinstance(fig, Figure)
    (ax,) = fig.axes
    (im,) = ax.get_images()
    assert im.get_array().shape == (5 * 13 - 1, 5 * 17 - 1)
    assert _labels(ax)[0].startswith("u (sensor px")
    assert _labels(ax)[1].startswith("v (sensor px")
    assert [t.get_text() for t in ax.get_xticklabels()] == ["-2", "-1", "0", "1", "2"]
    assert "21 valid shown" in ax.get_title()


def test_view_mosaic_rejects_non_lightfield():
    with pytest.raises(ValueError, match="lf must be a LightField"):
        plot_view_mosaic(np.zeros((5, 5, 12, 16)))


def test_view_mosaic_bad_views(lf):
    with pytest.raises(ValueError, match="views must be"):
        plot_view_mosaic(lf, views="some")


# --- plot_view -------------------------------------------------------------------------

def test_view_with_detections(lf):
    det = pd.DataFrame({"u": [1.0, 1.0, 0.0], "v": [0.0, 0.0, 0.0], "s": [9.0, 3.0, 8.0],
                        "t": [6.0, 2.0, 6.0], "particle": [0, -1, 0]})
    fig = plot_view(lf, 1, 0, detections=det)
    assert isinstance(fig, Figure)
    ax = fig.axes[0]
    assert _labels(ax) == ("s (view px)", "t (view px)")
    assert ax.get_images()[0].get_array().shape == (12, 16)
    points = [c for c in ax.collections if isinstance(c, PathCollection)]
    # only the two centroids of view (1, 0): one assigned, one not
    assert sorted(len(c.get_offsets()) for c in points) == [1, 1]
    assert "(1, 0)" in ax.get_title()
    assert fig.axes[1].get_ylabel() == "radiance (fraction of white)"
    assert ax.get_legend() is not None


def test_view_without_detections(lf):
    fig = plot_view(lf, 0, 0)
    assert not [c for c in fig.axes[0].collections if isinstance(c, PathCollection)]


def test_view_unknown_view(lf):
    with pytest.raises(ValueError, match="no view at"):
        plot_view(lf, 7, 0)


def test_view_detections_need_s_t(lf):
    with pytest.raises(ValueError, match=r"detections has no column\(s\) \['t'\]"):
        plot_view(lf, 0, 0, detections=pd.DataFrame({"s": [1.0]}))


# --- plot_particles_3d -------------------------------------------------------------------

def test_particles_3d_panels(measured, truth):
    fig = plot_particles_3d(measured, truth=truth)
    assert isinstance(fig, Figure)
    xy, zy, xz, legend_ax, cbar = fig.axes
    assert _labels(xy) == ("x (mm)", "y (mm)")
    assert _labels(zy) == ("z (mm)", "y (mm)")
    assert _labels(xz) == ("x (mm)", "z (mm)")
    assert cbar.get_ylabel() == "z (mm)"
    assert xy.yaxis_inverted()  # y grows downwards, as on the sensor
    for ax in (xy, zy, xz):
        located, true = ax.collections
        assert len(located.get_offsets()) == len(measured)
        assert len(true.get_offsets()) == len(truth)
    np.testing.assert_allclose(xz.collections[0].get_offsets()[:, 1], measured["z"])
    labels = [t.get_text() for t in legend_ax.get_legend().get_texts()]
    assert labels == [f"located ({len(measured)})", f"true ({len(truth)})"]


def test_particles_3d_without_truth_and_empty(truth):
    fig = plot_particles_3d(truth.iloc[:0])
    assert all(len(ax.collections) == 1 for ax in fig.axes[:3])


def test_particles_3d_missing_column(truth):
    with pytest.raises(ValueError, match=r"particles has no column\(s\) \['z'\]"):
        plot_particles_3d(truth[["x", "y"]])
    with pytest.raises(ValueError, match="truth must be a pandas DataFrame"):
        plot_particles_3d(truth, truth=np.zeros((3, 3)))


# --- plot_errors_vs_depth ----------------------------------------------------------------

def test_errors_vs_depth(measured, truth):
    fig = plot_errors_vs_depth(measured, truth, bins=5)
    assert isinstance(fig, Figure)
    ax_mean, ax_sd = fig.axes
    assert ax_mean.get_ylabel() == "depth error dz (mm)"
    assert ax_sd.get_xlabel() == "true depth z (mm)"
    assert ax_sd.get_ylabel() == "sd of dz (mm)"
    assert f"{len(measured)} of {len(truth)}" in ax_mean.get_title()
    assert len(ax_sd.patches) == 5
    # the grey points are the per-pair errors
    pts = ax_mean.lines[1].get_ydata()
    assert len(pts) == len(measured)
    assert abs(np.mean(pts) - 0.1) < 0.1
    heights = np.array([p.get_height() for p in ax_sd.patches])
    assert np.all((heights > 0.05) & (heights < 0.5))


def test_errors_vs_depth_bin_edges(measured, truth):
    fig = plot_errors_vs_depth(measured, truth, bins=[-10, 0, 10])
    assert len(fig.axes[1].patches) == 2


@pytest.mark.parametrize("bins, match", [(0, "bins must be a positive"),
                                         ([1.0, 0.0], "increasing")])
def test_errors_vs_depth_bad_bins(measured, truth, bins, match):
    with pytest.raises(ValueError, match=match):
        plot_errors_vs_depth(measured, truth, bins=bins)


def test_errors_vs_depth_no_match(truth):
    far = truth.assign(x=truth["x"] + 100.0)
    with pytest.raises(ValueError, match="no measured particle lies within"):
        plot_errors_vs_depth(far, truth)
    with pytest.raises(ValueError, match="tolerance_mm must be positive"):
        plot_errors_vs_depth(truth, truth, tolerance_mm=0.0)


# --- plot_focal_stack_sharpness ------------------------------------------------------------

@pytest.fixture(scope="module")
def stack():
    """A blob that is sharpest at z = 2 mm."""
    depths = np.linspace(-6.0, 6.0, 13)
    tt, ss = np.mgrid[0:30, 0:40]
    images = [1.0 - 0.8 * np.exp(-((ss - 20) ** 2 + (tt - 15) ** 2) / (2 * (0.8 + 0.5 * abs(z - 2.0)) ** 2))
              for z in depths]
    return np.array(images, dtype=np.float32), depths


def test_focal_stack_sharpness(stack):
    images, depths = stack
    fig = plot_focal_stack_sharpness(images, depths, center=(20, 15), half_width=4,
                                     true_depth_mm=2.0, n_images=4)
    assert isinstance(fig, Figure)
    *thumbs, curve = fig.axes
    assert len(thumbs) == 4
    assert all(isinstance(ax.get_images()[0], AxesImage) for ax in thumbs)
    assert thumbs[0].get_ylabel() == "t (view px)"
    assert any("(best)" in ax.get_title() for ax in thumbs)
    assert _labels(curve) == ("refocus depth z (mm)", "sharpness (relative to max)")
    best_line = curve.lines[1]
    assert abs(best_line.get_xdata()[0] - 2.0) < 0.5
    assert max(curve.lines[0].get_ydata()) == pytest.approx(1.0)


def test_focal_stack_sharpness_whole_image_unsorted(stack):
    images, depths = stack
    fig = plot_focal_stack_sharpness(images[::-1], depths[::-1])
    np.testing.assert_allclose(fig.axes[-1].lines[0].get_xdata(), depths)


@pytest.mark.parametrize("args, match", [
    ((np.zeros((3, 4)), [0, 1, 2]), "stack must be 3-D"),
    ((np.zeros((3, 4, 4)), [0, 1]), "one depth per image"),
    ((np.zeros((1, 4, 4)), [0]), "at least 2 images"),
])
def test_focal_stack_sharpness_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        plot_focal_stack_sharpness(*args)


def test_focal_stack_sharpness_center_needs_half_width(stack):
    with pytest.raises(ValueError, match="give both center and half_width"):
        plot_focal_stack_sharpness(*stack, center=(20, 15))


# --- plot_fragment_field and plot_tracks ---------------------------------------------

@pytest.fixture(scope="module")
def fragments_frame():
    rng = np.random.default_rng(5)
    n = 15
    phi = rng.uniform(0, 2 * np.pi, n)
    return pd.DataFrame({"frame": 0, "x": 10 * np.cos(phi), "y": 10 * np.sin(phi),
                         "z": -5 * np.sin(phi), "diameter": rng.uniform(0.5, 4, n),
                         "major_axis": 3.0, "minor_axis": 1.5,
                         "orientation": rng.uniform(-1.5, 1.5, n)})


def test_outline_points_are_the_measured_ellipses():
    from plenoptrack.plots import outline_points

    p = pd.DataFrame({"x": [1.0], "y": [2.0], "major_axis": [4.0], "minor_axis": [2.0],
                      "orientation": [np.pi / 2]})
    pts = outline_points(p, n=400)[0]
    r = pts - [1.0, 2.0]
    # long axis along +y: half-lengths 2 (y) and 1 (x); area pi a b
    assert np.abs(r[:, 1]).max() == pytest.approx(2.0, abs=1e-3)
    assert np.abs(r[:, 0]).max() == pytest.approx(1.0, abs=1e-3)
    area = 0.5 * abs(np.dot(pts[:-1, 0], pts[1:, 1]) - np.dot(pts[1:, 0], pts[:-1, 1]))
    assert area == pytest.approx(np.pi * 2 * 1, rel=1e-3)


def test_fragment_field_layout(fragments_frame):
    from matplotlib.collections import PolyCollection

    from plenoptrack.plots import plot_fragment_field

    fig = plot_fragment_field(fragments_frame)
    ax_top, ax_iso, ax_view, ax_side = fig.axes[:4]
    assert (_labels(ax_top), _labels(ax_side)) == (("x (mm)", "z (mm)"), ("z (mm)", "y (mm)"))
    assert ax_iso.name == "3d" and "isometric" in ax_iso.get_title()
    (outlines,) = [c for c in ax_view.collections if isinstance(c, PolyCollection)]
    assert len(outlines.get_paths()) == len(fragments_frame)
    # outlines coloured by depth: the farthest is the reddest
    colours = outlines.get_edgecolor()
    far, near = fragments_frame["z"].idxmax(), fragments_frame["z"].idxmin()
    assert colours[far][0] > colours[far][2] and colours[near][2] > colours[near][0]
    # marker area proportional to the measured image area, largest darkest
    sizes = ax_top.collections[0].get_sizes()
    big = fragments_frame["diameter"].idxmax()
    assert sizes.argmax() == big
    assert ax_top.collections[0].get_facecolors()[big][0] < 0.05
    assert fig.axes[-1].get_ylabel() == "z (mm)"


def test_fragment_field_on_the_central_view(fragments_frame):
    from matplotlib.collections import PolyCollection

    from plenoptrack.plots import plot_fragment_field

    class Linear:                               # a stand-in calibration: 10 px per mm
        def predict(self, x, y, z, u, v):
            return 100 + 10 * np.asarray(x), 60 + 10 * np.asarray(y)

    view = np.ones((120, 200))
    fig = plot_fragment_field(fragments_frame, view=view, dlfc=Linear())
    ax_view = fig.axes[2]
    assert _labels(ax_view) == ("s (view px)", "t (view px)")
    (outlines,) = [c for c in ax_view.collections if isinstance(c, PolyCollection)]
    v = outlines.get_paths()[0].vertices
    row = fragments_frame.iloc[0]
    assert v[:, 0].mean() == pytest.approx(100 + 10 * row["x"], abs=0.5)
    with pytest.raises(ValueError, match="dlfc"):
        plot_fragment_field(fragments_frame, view=view)


def test_tracks_figure():
    from matplotlib.collections import LineCollection

    from plenoptrack.plots import plot_tracks

    f = np.tile(np.arange(5), 3)
    t = pd.DataFrame({"frame": f, "particle": np.repeat([0, 1, 2], 5), "x": f * 1.0,
                      "y": np.repeat([0.0, 1.0, 2.0], 5), "z": 0.0,
                      "speed": np.repeat([1.0, 2.0, 3.0], 5)})
    fig = plot_tracks(t)
    ax_xy, ax_zy, ax_xz, ax_sp = fig.axes[:4]
    (lines,) = [c for c in ax_xy.collections if isinstance(c, LineCollection)]
    assert len(lines.get_segments()) == 3 * 4          # no segment joins two tracks
    assert "3 tracks" in ax_sp.get_title()
    assert fig.axes[-1].get_ylabel() == "speed (mm/frame)"
    with pytest.raises(ValueError, match="speed_unit"):
        plot_tracks(t, speed_unit="km/h")
