"""Tests of perspective views: the sign and size of the parallax across views (pinning
``docs/conventions.md``), mosaics and the TIFF / PNG writers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack.lightfield import (decode, perspective_views, view, view_mosaic,
                                    view_shift_per_u, write_mosaic_png, write_views_tiff)

SEED_OPTICS = 11
DIAMETER_MM = 0.6


@pytest.fixture(scope="module")
def camera():
    return preset("small")


@pytest.fixture(scope="module")
def optics(camera):
    from plenoptrack.simulate import make_optics

    return make_optics(camera, SEED_OPTICS)


@pytest.fixture(scope="module")
def white(optics):
    from plenoptrack.simulate import render_white

    return render_white(optics, seed=1)


def _decode_particles(optics, white, xyz, seed=2):
    from plenoptrack.simulate import render_frame

    df = pd.DataFrame(np.asarray(xyz, float), columns=["x", "y", "z"]).assign(diameter=DIAMETER_MM)
    raw = render_frame(optics, df, seed=seed)
    return decode(raw, optics.true_grid, white=white)


def _centroid(image, mask, centre_st, half_width=7):
    """Darkness-weighted centroid (s, t) of a dark spot in a window about ``centre_st``."""
    s_c, t_c = (int(round(c)) for c in centre_st)
    win = (slice(t_c - half_width, t_c + half_width + 1), slice(s_c - half_width, s_c + half_width + 1))
    sub = image[win]
    bg = np.median(image[mask])
    dark = np.clip(1.0 - sub / bg, 0.0, None)
    dark[dark < 0.15] = 0.0                 # ignore noise in the background
    tt, ss = np.mgrid[win]
    return np.array([(dark * ss).sum(), (dark * tt).sum()]) / dark.sum()


def _track(lf, start_st, axis):
    """Centroids across the central row (axis='u') or column (axis='v') of valid views.

    Returns (coordinates, centroids (n, 2) as (s, t))."""
    c = lf.n_u // 2
    coords, cents = [], []
    for k in range(lf.n_u):
        iv, iu = (c, k) if axis == "u" else (k, c)
        if not lf.view_mask[iv, iu]:
            continue
        coords.append(lf.u[iu] if axis == "u" else lf.v[iv])
        cents.append(_centroid(lf.data[iv, iu], lf.spatial_mask, start_st))
    return np.array(coords), np.array(cents)


def _start(lf, optics, xyz):
    return lf.from_sensor(optics.world_to_pixels(xyz))


@pytest.mark.parametrize("z", [12.0, -12.0])
def test_particle_parallax_matches_thin_lens_geometry(camera, optics, white, z):
    """Behind the focal plane (z > 0) a particle moves towards larger s as u grows, and
    towards larger t as v grows; in front, the other way; by (s_i + f_ml)/f_ml (1 - 1/alpha)
    sensor pixels per unit u."""
    xyz = [0.8, -0.6, z]
    lf = _decode_particles(optics, white, [xyz])
    start = _start(lf, optics, xyz)
    predicted = view_shift_per_u(camera, camera.alpha_for_depth(z)) / lf.sample_spacing_px
    assert np.sign(predicted) == np.sign(z)
    assert abs(predicted) > 0.5           # samples per unit u: a clear, measurable shift

    u, cu = _track(lf, start, "u")
    assert len(u) >= 11
    slope_s = np.polyfit(u, cu[:, 0], 1)[0]
    slope_t_along_u = np.polyfit(u, cu[:, 1], 1)[0]
    assert np.sign(slope_s) == np.sign(z)
    assert slope_s == pytest.approx(predicted, rel=0.05)
    assert abs(slope_t_along_u) < 0.05

    v, cv = _track(lf, start, "v")
    slope_t = np.polyfit(v, cv[:, 1], 1)[0]
    slope_s_along_v = np.polyfit(v, cv[:, 0], 1)[0]
    assert np.sign(slope_t) == np.sign(z)
    assert slope_t == pytest.approx(predicted, rel=0.05)
    assert abs(slope_s_along_v) < 0.05


def test_particle_on_focal_plane_is_sharp_and_still(camera, optics, white):
    xyz = [-0.7, 0.9, 0.0]
    lf = _decode_particles(optics, white, [xyz])
    start = _start(lf, optics, xyz)

    # no parallax
    for axis in ("u", "v"):
        coords, cents = _track(lf, start, axis)
        assert np.abs(np.polyfit(coords, cents, 1)[0]).max() < 0.05
        assert np.ptp(cents, axis=0).max() < 0.3

    # central view: at the predicted place, dark core, sharp edge, size as imaged
    centre = lf.view(0, 0)
    got = _centroid(centre, lf.spatial_mask, start)
    np.testing.assert_allclose(got, start, atol=0.25)
    bg = np.median(centre[lf.spatial_mask])
    s_c, t_c = np.round(start).astype(int)
    patch = centre[t_c - 6: t_c + 7, s_c - 6: s_c + 7] / bg
    assert patch.min() < 0.1
    spacing_mm = lf.sample_spacing_px * camera.pixel_pitch_um * 1e-3 / (
        1 + camera.microlens_focal_length_um * 1e-3 / camera.image_distance_mm)
    diameter_samples = DIAMETER_MM * abs(camera.magnification) / spacing_mm
    area = (1.0 - np.clip(patch, 0, 1)).sum()  # dark area, samples^2
    assert area == pytest.approx(np.pi * diameter_samples ** 2 / 4, rel=0.25)

    # a defocused particle is blurrier in every view but the central one barely: its
    # sub-aperture is one pixel wide. Compare the mean over valid views of the darkest value.
    far = _decode_particles(optics, white, [[-0.7, 0.9, 20.0]])
    def mean_min(lf_, xyz_):
        st = _start(lf_, optics, xyz_)
        s0, t0 = np.round(st).astype(int)
        sel = lf_.data[lf_.view_mask][:, t0 - 8: t0 + 9, s0 - 8: s0 + 9]
        return float(sel.min(axis=(1, 2)).mean())
    assert mean_min(lf, xyz) < mean_min(far, [-0.7, 0.9, 20.0])


# --- views, mosaics and writers -----------------------------------------------------------

@pytest.fixture(scope="module")
def small_lf(optics, white):
    return _decode_particles(optics, white, [[0.0, 0.0, 5.0]])


def test_perspective_views_is_the_data(small_lf):
    views = perspective_views(small_lf)
    assert views.shape == small_lf.data.shape
    assert np.shares_memory(views, small_lf.data)
    np.testing.assert_array_equal(view(small_lf, 3, -2), views[-2 + 7, 3 + 7])


def test_view_mosaic_layout(small_lf):
    lf = small_lf
    n_t, n_s = lf.view_shape
    m = view_mosaic(lf)
    assert m.shape == (lf.n_v * n_t, lf.n_u * n_s)
    np.testing.assert_array_equal(m[2 * n_t:3 * n_t, 5 * n_s:6 * n_s], lf.data[2, 5])
    g = view_mosaic(lf, views="valid", gap=3, fill=-1.0)
    assert g.shape == (lf.n_v * (n_t + 3) - 3, lf.n_u * (n_s + 3) - 3)
    r0, c0 = 7 * (n_t + 3), 6 * (n_s + 3)
    np.testing.assert_array_equal(g[r0:r0 + n_t, c0:c0 + n_s], lf.data[7, 6])
    assert np.all(g[r0 + n_t:r0 + n_t + 3] == -1.0)
    assert np.all(g[:n_t, :n_s] == -1.0)  # corner view is not valid
    with pytest.raises(ValueError, match="views must be"):
        view_mosaic(lf, views="central")
    with pytest.raises(ValueError, match="boolean array of shape"):
        view_mosaic(lf, views=np.ones((3, 3), bool))


def test_write_views_tiff_and_png(small_lf, tmp_path):
    import tifffile
    from PIL import Image

    path = write_views_tiff(tmp_path / "views.tif", small_lf, views="valid")
    stack = tifffile.imread(path)
    assert stack.shape == (int(small_lf.view_mask.sum()), *small_lf.view_shape)
    assert stack.dtype == np.float32
    np.testing.assert_array_equal(stack, small_lf.data[small_lf.view_mask])

    png = write_mosaic_png(tmp_path / "mosaic.png", small_lf, gap=2)
    img = np.asarray(Image.open(png))
    assert img.dtype == np.uint8
    assert img.shape == view_mosaic(small_lf, gap=2).shape
    assert img.max() == 255 and img.min() == 0
    assert not list(tmp_path.glob(".*.tmp*"))  # atomic writes leave no temporaries
