"""Rendering: white image geometry, particle shadows, culling exactness, determinism."""

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack.simulate import (SimOptics, make_optics, render_frame, render_irradiance,
                                  render_white)
from plenoptrack.simulate.render import background_irradiance


def _particles(rows):
    return pd.DataFrame(rows, columns=["x", "y", "z", "diameter"])


def test_frame_is_deterministic(small_optics):
    parts = _particles([[0.5, -0.3, 2.0, 0.8], [-2.0, 1.0, -6.0, 1.0]])
    a = render_frame(small_optics, parts, seed=11)
    b = render_frame(small_optics, parts, seed=11)
    c = render_frame(small_optics, parts, seed=12)
    assert a.dtype == np.uint16 and a.shape == small_optics.camera.sensor_shape_px
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()
    assert a.max() <= small_optics.camera.full_scale


@pytest.mark.parametrize("name", ["small", "small-rect"])
@pytest.mark.parametrize("seed", [0, 4])
def test_white_microlens_images_centred_on_true_grid(name, seed):
    # Stopped down so that the aperture images are isolated discs.
    optics = make_optics(preset(name).with_changes(f_number=3.2), seed)
    irr = background_irradiance(optics).astype(float)
    centres = optics.true_grid.centers()
    rows, cols = irr.shape
    ci, cj = np.argwhere(np.hypot(centres[..., 0] - rows / 2, centres[..., 1] - cols / 2) < 60).T
    rr, cc = np.mgrid[0:rows, 0:cols]
    for i, j in zip(ci, cj):
        r0, c0 = centres[i, j]
        w = irr * (np.hypot(rr - r0, cc - c0) < 6.8)
        assert (w * rr).sum() / w.sum() == pytest.approx(r0, abs=0.05)
        assert (w * cc).sum() / w.sum() == pytest.approx(c0, abs=0.05)


def test_white_discs_and_dark_corners(small_optics):
    optics = small_optics
    white = render_white(optics, seed=0).astype(float)
    full = white.max()
    c = optics.true_grid.centers()
    i, j = 24, 32
    r0, c0 = c[i, j]
    assert white[int(round(r0)), int(round(c0))] > 0.8 * full
    # Corners between three lenses (hexagonal packing) receive no light.
    a, b, d = c[i, j], c[i, j + 1], c[i + 1, j + (i % 2)]
    corner = (a + b + d) / 3
    assert white[int(round(corner[0])), int(round(corner[1]))] < 0.05 * full
    # Discs: lit within the aperture-image radius, dark well outside it.
    radius_px = (optics.aperture_radius * optics.f_ml / optics.s_i) / optics.pixel_pitch
    assert radius_px == pytest.approx(7.0, abs=0.01)


def test_sphere_on_axis_darkens_central_lenses(small_optics):
    o = small_optics
    bg = background_irradiance(o)
    irr = render_irradiance(o, _particles([[0.0, 0.0, 0.0, 0.5]]))
    grid = o.true_grid
    c = grid.centers()
    rows, cols = o.camera.sensor_shape_px
    d = np.hypot(c[..., 0] - (rows - 1) / 2, c[..., 1] - (cols - 1) / 2)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    r0, c0 = np.round(c[i, j]).astype(int)
    # In focus: the whole image of the central lens is dark.
    assert bg[r0 - 4:r0 + 5, c0 - 4:c0 + 5].min() > 0.9
    assert irr[r0 - 4:r0 + 5, c0 - 4:c0 + 5].max() == 0
    # Lenses 1 mm (about 6.5 lenses) away on the MLA are untouched.
    far = np.argwhere((d > 120) & (d < 200))
    for fi, fj in far[:20]:
        fr, fc = np.round(c[fi, fj]).astype(int)
        np.testing.assert_array_equal(irr[fr - 3:fr + 4, fc - 3:fc + 4], bg[fr - 3:fr + 4, fc - 3:fc + 4])


@pytest.mark.parametrize("x, y", [(1.0, 0.0), (0.0, 1.0), (-1.2, 0.8)])
def test_sphere_appears_at_thin_lens_position(small_optics, x, y):
    o = small_optics
    bg = background_irradiance(o).astype(float)
    irr = render_irradiance(o, _particles([[x, y, 0.0, 0.4]])).astype(float)
    shadow = bg - irr
    rr, cc = np.mgrid[0:shadow.shape[0], 0:shadow.shape[1]]
    centroid = np.array([(shadow * rr).sum(), (shadow * cc).sum()]) / shadow.sum()
    predicted = o.world_to_pixels([x, y, 0.0])
    np.testing.assert_allclose(centroid, predicted, atol=1.5)
    rows, cols = o.camera.sensor_shape_px
    # Sign convention: world +x -> larger column, +y -> larger row.
    assert np.sign(centroid[1] - (cols - 1) / 2) == np.sign(x) or x == 0
    assert np.sign(centroid[0] - (rows - 1) / 2) == np.sign(y) or y == 0


@pytest.mark.parametrize("fixture", ["small_optics", "small_rect_optics"])
def test_culled_render_equals_brute_force(fixture, request):
    o = request.getfixturevalue(fixture)
    rng = np.random.default_rng(2)
    n = 10
    parts = _particles(np.column_stack([rng.uniform(-4.5, 4.5, n), rng.uniform(-3.5, 3.5, n),
                                        rng.uniform(-12, 12, n), rng.uniform(0.2, 1.2, n)]))
    culled = render_irradiance(o, parts)
    brute = render_irradiance(o, parts, cull=False)
    assert (culled != background_irradiance(o)).sum() > 10000
    np.testing.assert_array_equal(culled, brute)


def test_culled_equals_brute_force_strong_distortion():
    o = SimOptics(preset("small"), rotation_deg=-0.4, offset_mm=(0.001, -0.002),
                  pitch_scale=0.999, k1=0.3, k2=-0.1)
    parts = _particles([[4.0, 2.5, -9.0, 0.9], [-4.6, -3.0, 9.0, 0.7], [0.2, 0.1, 30.0, 2.0]])
    np.testing.assert_array_equal(render_irradiance(o, parts),
                                  render_irradiance(o, parts, cull=False))


def test_noise_free_white_is_scaled_background(small_optics):
    white = render_white(small_optics, noise=False)
    bg = background_irradiance(small_optics)
    np.testing.assert_array_equal(white, np.floor(bg.astype(np.float64) * 0.9 * 4095 + 0.5))


@pytest.mark.parametrize("rows, match", [
    ([[0.0, 0.0, 0.0, -1.0]], "diameters must be positive"),
    ([[0.0, 0.0, -400.0, 1.0]], "reach the main lens"),
    ([[np.nan, 0.0, 0.0, 1.0]], "NaN"),
])
def test_invalid_particles(small_optics, rows, match):
    with pytest.raises(ValueError, match=match):
        render_irradiance(small_optics, _particles(rows))


def test_invalid_arguments(small_optics):
    with pytest.raises(ValueError, match="missing column"):
        render_irradiance(small_optics, pd.DataFrame({"x": [0.0]}))
    with pytest.raises(ValueError, match="several frames"):
        render_irradiance(small_optics, _particles([[0, 0, 0, 1], [1, 1, 0, 1]]).assign(frame=[0, 1]))
    with pytest.raises(ValueError, match="samples_per_pixel"):
        render_irradiance(small_optics, None, samples_per_pixel=0)
    with pytest.raises(TypeError, match="SimOptics"):
        render_white(preset("small"))


@pytest.mark.parametrize("z, direction", [(8.0, 1), (-8.0, -1)])
@pytest.mark.parametrize("axis", [0, 1])
def test_view_shift_sign_convention(small_optics, z, direction, axis):
    """A particle behind the focal plane moves towards larger s (t) as u (v) grows."""
    o = small_optics
    bg = background_irradiance(o).astype(float)
    irr = render_irradiance(o, _particles([[0.0, 0.0, z, 0.6]])).astype(float)
    centres = o.true_grid.centers().reshape(-1, 2)
    rows, cols = irr.shape
    positions = []
    for step in (-3, 3):
        px = np.round(centres + np.eye(2)[axis] * step).astype(int)
        ok = (px[:, 0] >= 0) & (px[:, 0] < rows) & (px[:, 1] >= 0) & (px[:, 1] < cols)
        shadow = bg[px[ok, 0], px[ok, 1]] - irr[px[ok, 0], px[ok, 1]]
        positions.append((shadow * centres[ok, axis]).sum() / shadow.sum())
    assert direction * (positions[1] - positions[0]) > 2.0
