"""Tests of shift-and-add refocusing, focal stacks and the focus metric."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack.errors import CameraSpecError, ImageSizeError
from plenoptrack.lightfield import (LightField, best_focus_depth, decode, focal_stack, refocus,
                                    refocus_shifts, sharpness, view_shift_per_u)

DEPTHS_MM = np.linspace(-25.0, 25.0, 50)   # the simulated volume, 50 planes
STEP_MM = DEPTHS_MM[1] - DEPTHS_MM[0]
# lateral positions far enough apart that defocus blur of one particle stays out of the
# other particles' windows over the whole stack
PARTICLES = pd.DataFrame({"x": [-2.6, 0.3, 2.8, -1.2], "y": [1.5, -1.6, 1.2, -0.2],
                          "z": [-17.3, 6.2, 14.9, -4.4], "diameter": 0.5})


@pytest.fixture(scope="module")
def camera():
    return preset("small")


@pytest.fixture(scope="module")
def scene(camera):
    from plenoptrack.simulate import make_optics, render_frame, render_white

    optics = make_optics(camera, 7)
    white = render_white(optics, seed=3)
    raw = render_frame(optics, PARTICLES, seed=4)
    return optics, decode(raw, optics.true_grid, white=white)


def test_focal_stack_peaks_within_one_plane_of_true_depth(camera, scene):
    optics, lf = scene
    stack = focal_stack(lf, camera, DEPTHS_MM)
    assert stack.shape == (len(DEPTHS_MM), *lf.view_shape)
    assert stack.dtype == np.float32
    for _, p in PARTICLES.iterrows():
        xyz = [p.x, p.y, p.z]
        s, t = lf.from_sensor(optics.world_to_pixels(xyz))
        # in the refocused image of plane alpha the particle sits at axis + alpha (X - axis)
        s_ax, t_ax = lf.axis_st
        alpha = camera.alpha_for_depth(p.z)
        centre = (s_ax + alpha * (s - s_ax), t_ax + alpha * (t - t_ax))
        curve = sharpness(stack, center=centre, half_width=7)
        k = int(np.argmax(curve))
        assert abs(DEPTHS_MM[k] - p.z) <= STEP_MM, (p.z, DEPTHS_MM[k])
        z_fit = best_focus_depth(stack, DEPTHS_MM, center=centre, half_width=7)
        assert abs(z_fit - p.z) <= STEP_MM
        # refocusing far from the particle blurs it
        assert curve[k] > 3 * curve[0] and curve[k] > 3 * curve[-1]


def test_refocus_at_alpha_one_is_the_mean_of_the_views(camera, scene):
    _, lf = scene
    img = refocus(lf, camera, alpha=1.0)
    sel = lf.view_mask
    inside = lf.spatial_mask
    np.testing.assert_allclose(img[inside], lf.data[sel].mean(axis=0)[inside], rtol=1e-5)
    np.testing.assert_allclose(refocus(lf, camera, depth_mm=0.0), img, rtol=1e-6)
    every = refocus(lf, camera, alpha=1.0, views="all")
    np.testing.assert_allclose(every[inside], lf.data[lf.valid_fraction > 0].mean(axis=0)[inside],
                               rtol=1e-5)


def test_refocus_matches_focal_stack_and_view_subsets(camera, scene):
    _, lf = scene
    stack = focal_stack(lf, camera, [-10.0, 3.0], progress=True)
    np.testing.assert_array_equal(stack[1], refocus(lf, camera, depth_mm=3.0))
    only_centre = np.zeros((lf.n_v, lf.n_u), bool)
    only_centre[7, 7] = True
    img = refocus(lf, camera, alpha=1.0, views=only_centre)
    np.testing.assert_allclose(img[lf.spatial_mask], lf.view(0, 0)[lf.spatial_mask], rtol=1e-6)


def test_refocus_shifts_follow_the_conventions(camera, scene):
    _, lf = scene
    behind = refocus_shifts(lf, camera, camera.alpha_for_depth(10.0))
    assert behind.shape == (lf.n_v, lf.n_u, 2)
    c = lf.n_u // 2
    np.testing.assert_allclose(behind[c, c], 0.0)
    assert behind[c, c + 1, 1] > 0 and behind[c + 1, c, 0] > 0          # larger s, t
    in_front = refocus_shifts(lf, camera, camera.alpha_for_depth(-10.0))
    assert in_front[c, c + 1, 1] < 0 and in_front[c + 1, c, 0] < 0
    assert np.abs(refocus_shifts(lf, camera, 1.0)).max() == 0.0
    k = view_shift_per_u(camera, camera.alpha_for_depth(10.0)) / lf.sample_spacing_px
    assert behind[c, c + 3, 1] == pytest.approx(3 * k, rel=1e-3)


def test_refocus_synthetic_shifted_views_aligns_them(camera):
    """Views built as shifted copies of one blob refocus to a sharp blob at their alpha."""
    n_t, n_s = 40, 50
    rad = 3
    ang = np.arange(-rad, rad + 1.0)
    lf0 = LightField(np.zeros((7, 7, n_t, n_s), np.float32), ang, ang, np.ones((7, 7)),
                     np.ones((n_t, n_s), bool), (0.0, 0.0), (0.0, 12.0), (12.0, 0.0),
                     (600, 910))
    alpha = camera.alpha_for_depth(8.0)
    shifts = refocus_shifts(lf0, camera, alpha)
    tt, ss = np.mgrid[:n_t, :n_s]
    s_ax, t_ax = lf0.axis_st
    t_true, s_true = 22.0, 18.0  # position in the alpha-plane image
    t0, s0 = t_ax + (t_true - t_ax) / alpha, s_ax + (s_true - s_ax) / alpha
    data = np.exp(-((tt[None, None] - t0 - shifts[..., 0, None, None]) ** 2
                    + (ss[None, None] - s0 - shifts[..., 1, None, None]) ** 2) / 2.0)
    lf = LightField(data.astype(np.float32), ang, ang, np.ones((7, 7)), np.ones((n_t, n_s), bool),
                    (0.0, 0.0), (0.0, 12.0), (12.0, 0.0), (600, 910))
    img = refocus(lf, camera, alpha=alpha, views="all")
    peak = np.unravel_index(np.argmax(img), img.shape)
    assert peak == (22, 18)
    assert img.max() > 0.8  # bilinear sampling of a sigma = 1 blob between samples
    assert refocus(lf, camera, alpha=1.0, views="all").max() < 0.5


def test_sharpness_prefers_sharp_images():
    rng = np.random.default_rng(0)
    img = np.zeros((40, 40))
    img[15:25, 15:25] = 1.0
    from scipy import ndimage

    blurred = ndimage.gaussian_filter(img, 2.0)
    for method in ("laplacian", "gradient"):
        sh = sharpness(np.stack([blurred, img]), method=method)
        assert sh.shape == (2,)
        assert sh[1] > sh[0]
    assert np.ndim(sharpness(img)) == 0
    noisy = img + rng.normal(0, 0.01, img.shape)
    assert sharpness(noisy, center=(20, 20), half_width=6) > sharpness(noisy, center=(5, 5), half_width=3)


# --- bad input --------------------------------------------------------------------------------

def test_refocus_bad_arguments(camera, scene):
    _, lf = scene
    with pytest.raises(ValueError, match="exactly one of alpha or depth_mm"):
        refocus(lf, camera)
    with pytest.raises(ValueError, match="exactly one of alpha or depth_mm"):
        refocus(lf, camera, alpha=1.0, depth_mm=0.0)
    with pytest.raises(ValueError, match="alpha must be a positive finite number"):
        refocus(lf, camera, alpha=-1.0)
    with pytest.raises(ValueError, match="no views selected"):
        refocus(lf, camera, alpha=1.0, views=np.zeros((lf.n_v, lf.n_u), bool))
    with pytest.raises(ImageSizeError, match="use the matching camera description"):
        refocus(lf, preset("hall2019"), alpha=1.0)
    with pytest.raises(CameraSpecError, match="camera must be a CameraSpec"):
        refocus(lf, "small", alpha=1.0)
    with pytest.raises(TypeError, match="lf must be a LightField"):
        refocus(lf.data, camera, alpha=1.0)
    with pytest.raises(ValueError, match="depths_mm must be 1-D"):
        focal_stack(lf, camera, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="give both center and half_width"):
        sharpness(lf.data[0, 0], center=(3, 3))
    with pytest.raises(ValueError, match="method must be"):
        sharpness(lf.data[0, 0], method="fft")
