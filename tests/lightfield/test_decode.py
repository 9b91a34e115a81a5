"""Tests of plenoptrack.lightfield.decode: raw image + lenslet grid -> LightField."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plenoptrack import preset
from plenoptrack.errors import CalibrationError, ImageSizeError, InputFileError, SettingsError
from plenoptrack.lightfield import VIEW_MASK_THRESHOLD, LensletGrid, LightField, decode


def _lattice(grid_type: str, *, shape=(30, 36), pitch=14.0274, rot_deg=0.3,
             centre=(200.37, 250.61), sensor=(420, 520)) -> LensletGrid:
    """A rotated lattice with sub-pixel offsets, centred near ``centre``."""
    th = math.radians(rot_deg)
    a = np.array([math.sin(th), math.cos(th)]) * pitch             # along a lens row
    spacing = pitch * (math.sqrt(3) / 2 if grid_type == "hex" else 1.0)
    b = np.array([math.cos(th), -math.sin(th)]) * spacing           # to the next row
    shift = 0.5 if grid_type == "hex" else 0.0
    origin = np.asarray(centre) - ((shape[1] - 1) / 2 + shift / 2) * a - (shape[0] - 1) / 2 * b
    return LensletGrid(grid_type, shape, tuple(origin), tuple(a), tuple(b), shift, sensor)


def _paint(grid: LensletGrid, func) -> np.ndarray:
    """Independent forward model: every pixel belongs to its nearest lens centre and gets
    ``func(dv, du, centre_row, centre_col)`` with ``(dv, du)`` its offset from that centre."""
    centres = grid.centers().reshape(-1, 2)
    rows, cols = grid.sensor_shape_px
    rr, cc = np.indices((rows, cols), dtype=float)
    _, k = cKDTree(centres).query(np.column_stack([rr.ravel(), cc.ravel()]))
    c = centres[k]
    dv = rr.ravel() - c[:, 0]
    du = cc.ravel() - c[:, 1]
    return func(dv, du, c[:, 0], c[:, 1]).reshape(rows, cols)


def _linear(dv, du, row, col):
    return 500.0 + 7.0 * du - 4.0 * dv + 0.6 * col + 0.9 * row


@pytest.mark.parametrize("grid_type", ["hex", "rect"])
def test_decode_recovers_analytic_light_field(grid_type):
    grid = _lattice(grid_type)
    raw = _paint(grid, _linear).astype(np.float32)
    lf = decode(raw, grid)

    rad = int(grid.pitch_px // 2)
    assert lf.data.dtype == np.float32
    assert (lf.n_v, lf.n_u) == (2 * rad + 1, 2 * rad + 1)
    np.testing.assert_array_equal(lf.u, np.arange(-rad, rad + 1))
    np.testing.assert_array_equal(lf.v, np.arange(-rad, rad + 1))
    if grid_type == "rect":
        assert lf.view_shape == grid.shape
    else:
        assert lf.n_t == grid.shape[0]
        assert lf.sample_spacing_px == pytest.approx(grid.row_spacing_px)
        # square samples: equal steps, perpendicular
        assert np.hypot(*lf.s_step_px) == pytest.approx(np.hypot(*lf.t_step_px))
        assert np.dot(lf.s_step_px, lf.t_step_px) == pytest.approx(0.0, abs=1e-9)

    # views whose bilinear taps all stay inside the lens's own cell are exact
    t, s = np.nonzero(lf.spatial_mask)
    assert len(t) > 0.8 * lf.spatial_mask.size
    pos = lf.to_sensor(s, t)
    checked = 0
    for iv, v in enumerate(lf.v):
        for iu, u in enumerate(lf.u):
            if math.hypot(abs(u) + 1, abs(v) + 1) >= grid.pitch_px / 2:
                continue
            expected = _linear(v, u, pos[:, 0], pos[:, 1])
            np.testing.assert_allclose(lf.data[iv, iu, t, s], expected, rtol=2e-6, atol=1e-3)
            checked += 1
    assert checked >= 60


def test_decode_smooth_field_hex_resampling_error_is_small():
    """A field curved across lenses is interpolated linearly along lens rows."""
    grid = _lattice("hex")

    def func(dv, du, row, col):
        return 1000.0 + 50.0 * np.sin(col / 60.0) * np.cos(row / 45.0) + 3.0 * du

    lf = decode(_paint(grid, func).astype(np.float32), grid)
    t, s = np.nonzero(lf.spatial_mask)
    pos = lf.to_sensor(s, t)
    iv, iu = lf.index_of(2, -1)
    expected = func(-1.0, 2.0, pos[:, 0], pos[:, 1])
    err = np.abs(lf.data[iv, iu, t, s] - expected)
    # linear interpolation over one pitch: |f''| h^2 / 8 ~ 50 / 60^2 * 14^2 / 8 ~ 0.35
    assert err.max() < 0.5


def test_spatial_mask_marks_lenses_off_the_sensor():
    # a lattice larger than the sensor: border lenses have images partly off the sensor
    grid = _lattice("hex", shape=(36, 42), sensor=(420, 520))
    raw = np.full(grid.sensor_shape_px, 1000, dtype=np.uint16)
    lf = decode(raw, grid)
    assert not lf.spatial_mask.all()
    assert lf.spatial_mask.any()
    t, s = np.nonzero(lf.spatial_mask)
    pos = lf.to_sensor(s, t)
    rad = lf.u.max()
    assert pos[:, 0].min() >= rad - 1 and pos[:, 1].min() >= rad - 1
    assert pos[:, 0].max() <= 419 - rad + 1 and pos[:, 1].max() <= 519 - rad + 1
    # the image is uniform, so every sample of every view reads 1000 (edges replicate)
    np.testing.assert_allclose(lf.data, 1000.0, rtol=1e-6)


def test_to_sensor_and_from_sensor_are_inverse():
    lf = decode(np.zeros((420, 520), np.uint16), _lattice("hex"))
    st = np.array([[3.25, 7.5], [0.0, 0.0], [40.0, 20.0]])
    back = lf.from_sensor(lf.to_sensor(st[:, 0], st[:, 1]))
    np.testing.assert_allclose(back, st, atol=1e-9)
    np.testing.assert_allclose(lf.to_sensor(0, 0), lf.origin_px)
    s_ax, t_ax = lf.axis_st
    np.testing.assert_allclose(lf.to_sensor(s_ax, t_ax), [419 / 2, 519 / 2], atol=1e-9)


def test_valid_fraction_without_white_is_the_disc_geometry():
    grid = _lattice("hex")
    lf = decode(np.zeros(grid.sensor_shape_px, np.uint16), grid)
    vf = lf.valid_fraction
    c = lf.n_u // 2
    assert vf[c, c] == 1.0
    np.testing.assert_allclose(vf, vf[::-1, :])
    np.testing.assert_allclose(vf, vf[:, ::-1])
    np.testing.assert_allclose(vf, vf.T)
    assert vf[0, 0] == 0.0                  # corner view lies outside the disc
    assert 0.4 < vf[c, 0] < 0.6             # rim view: about half inside
    np.testing.assert_array_equal(lf.view_mask, vf >= VIEW_MASK_THRESHOLD)
    assert not lf.view_mask[c, 0] and lf.view_mask[c, 1]
    # all views are kept, including the flagged ones
    assert lf.data.shape[:2] == (15, 15)


def test_white_flat_field_and_valid_fraction():
    grid = _lattice("hex")
    radius = grid.pitch_px / 2

    def white_f(dv, du, row, col):  # disc-shaped microlens images, dimmer on one side
        r = np.hypot(dv, du)
        return np.where(r < radius - 1.5, 3000.0 * (1.0 - 0.02 * du), 0.0)

    def scene_f(dv, du, row, col):
        return white_f(dv, du, row, col) * (0.5 + 0.001 * col)

    white = _paint(grid, white_f).astype(np.uint16)
    raw = _paint(grid, scene_f).astype(np.float32)
    lf = decode(raw, grid, white=white)
    assert lf.flat_fielded
    c = lf.n_u // 2
    t, s = np.nonzero(lf.spatial_mask)
    col = lf.to_sensor(s, t)[:, 1]
    for (iv, iu) in [(c, c), (c - 2, c + 3), (c + 4, c - 1)]:
        np.testing.assert_allclose(lf.data[iv, iu, t, s], 0.5 + 0.001 * col, rtol=2e-3)
    # views in the dark ring around each image are zero, not noise divided by noise
    assert np.all(lf.data[c, 0][lf.spatial_mask] == 0.0)
    assert lf.valid_fraction[c, 0] < 0.2
    # relative to the brightest view (u < 0 is brighter here by 2 % per pixel)
    assert lf.valid_fraction.max() == pytest.approx(1.0)
    assert lf.valid_fraction[c, c + 2] < lf.valid_fraction[c, c] < lf.valid_fraction[c, c - 2]
    assert np.all(lf.valid_fraction <= 1.0) and np.all(lf.valid_fraction >= 0.0)


def test_decode_is_deterministic_and_accepts_uint16_and_float():
    grid = _lattice("hex")
    raw = (_paint(grid, _linear)).astype(np.uint16)
    a = decode(raw, grid)
    b = decode(raw.astype(np.float64), grid)
    np.testing.assert_array_equal(a.data, decode(raw, grid).data)
    np.testing.assert_allclose(a.data, b.data, rtol=1e-6)


def test_decode_with_progress_bar_gives_same_result():
    grid = _lattice("rect")
    raw = _paint(grid, _linear).astype(np.float32)
    np.testing.assert_array_equal(decode(raw, grid, progress=True).data, decode(raw, grid).data)


# --- bad input -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def grid():
    return _lattice("hex")


def test_wrong_shape_raises_image_size_error(grid):
    with pytest.raises(ImageSizeError, match="raw image: image is 400 x 520 pixels but the "
                                             "lenslet grid expects 420 x 520"):
        decode(np.zeros((400, 520), np.uint16), grid)


@pytest.mark.parametrize("shape", [(2, 420, 520), (420 * 520,), ()])
def test_wrong_ndim_raises_image_size_error(grid, shape):
    with pytest.raises(ImageSizeError, match="raw image must be a 2-D"):
        decode(np.zeros(shape, np.uint16), grid)


def test_wrong_white_shape_raises(grid):
    with pytest.raises(ImageSizeError, match="white image: image is"):
        decode(np.zeros((420, 520), np.uint16), grid, white=np.ones((420, 521), np.uint16))


def test_white_decoded_once_equals_raw_white():
    grid = _lattice("hex")
    radius = grid.pitch_px / 2

    def white_f(dv, du, row, col):
        return np.where(np.hypot(dv, du) < radius - 1.5, 3000.0 * (1.0 + 0.0005 * row), 0.0)

    white = _paint(grid, white_f).astype(np.uint16)
    raw = (_paint(grid, white_f) * 0.6).astype(np.uint16)
    by_raw = decode(raw, grid, white=white)
    by_lf = decode(raw, grid, white=decode(white, grid))
    np.testing.assert_array_equal(by_lf.data, by_raw.data)
    np.testing.assert_array_equal(by_lf.valid_fraction, by_raw.valid_fraction)
    assert by_lf.flat_fielded
    with pytest.raises(CalibrationError, match="without a white image"):
        decode(raw, grid, white=by_raw)          # already flat-fielded: not a white


def test_black_samples_stay_valid_after_flat_fielding():
    """A perfectly black particle (raw 0, no dark level) is data, not a hole: only samples
    the white image leaves dark are set to 0, the invalid marker."""
    grid = _lattice("hex")
    radius = grid.pitch_px / 2

    def white_f(dv, du, row, col):
        return np.where(np.hypot(dv, du) < radius - 1.5, 3000.0, 0.0)

    def scene_f(dv, du, row, col):   # a black disc over the middle of the sensor
        black = np.hypot(row - 210.0, col - 260.0) < 60.0
        return np.where(black, 0.0, white_f(dv, du, row, col))

    lf = decode(_paint(grid, scene_f).astype(np.uint16), grid,
                white=_paint(grid, white_f).astype(np.uint16))
    c = lf.n_u // 2
    central = lf.data[c, c][lf.spatial_mask]
    assert central.min() == pytest.approx(1e-6) and (central == 0).sum() == 0
    assert (central < 1e-3).sum() > 50           # the black disc: about 66 lenses
    assert np.all(lf.data[c, 0][lf.spatial_mask] == 0.0)   # dark rim views: invalid


def test_dark_white_raises(grid):
    with pytest.raises(InputFileError, match="white image is dark"):
        decode(np.zeros((420, 520), np.uint16), grid, white=np.zeros((420, 520), np.uint16))


@pytest.mark.parametrize("dtype", [bool, complex, object])
def test_non_numeric_dtype_raises(grid, dtype):
    with pytest.raises(InputFileError, match="integer or float pixel values"):
        decode(np.zeros((420, 520), dtype=dtype), grid)


def test_not_a_grid_raises():
    with pytest.raises(CalibrationError, match="grid must be a LensletGrid"):
        decode(np.zeros((420, 520), np.uint16), {"pitch": 14})


def test_bad_white_floor_raises(grid):
    with pytest.raises(ValueError, match="white_floor must be between 0 and 1"):
        decode(np.zeros((420, 520), np.uint16), grid, white_floor=1.5)


def test_lightfield_validates_shapes():
    with pytest.raises(ValueError, match="must be a 4-D array"):
        LightField(np.zeros((3, 3, 4), np.float32), np.arange(3), np.arange(3), np.ones((3, 3)),
                   np.ones((3, 4), bool), (0, 0), (0, 1), (1, 0), (10, 10))
    with pytest.raises(ValueError, match="spatial_mask must be"):
        LightField(np.zeros((3, 3, 4, 5), np.float32), np.arange(3), np.arange(3),
                   np.ones((3, 3)), np.ones((5, 4), bool), (0, 0), (0, 1), (1, 0), (10, 10))


def test_index_of_unknown_view_raises(grid):
    lf = decode(np.zeros((420, 520), np.uint16), grid)
    with pytest.raises(ValueError, match=r"no view at \(u, v\) = \(8, 0\)"):
        lf.view(8, 0)


# --- full sensor --------------------------------------------------------------------------

@pytest.mark.slow
def test_full_sensor_decode_shape():
    from plenoptrack.simulate import make_optics, render_white

    cam = preset("hall2019")
    optics = make_optics(cam, seed=5)
    white = render_white(optics, seed=1)
    lf = decode(white, optics.true_grid)
    assert lf.data.shape[:2] == (15, 15)
    assert lf.n_t >= cam.grid_shape[0] - 2 and lf.n_s >= 530
    assert lf.spatial_mask.mean() > 0.95


@pytest.mark.parametrize("white_kind", ["none", "raw", "decoded"])
def test_views_below_min_view_fraction_are_left_out(white_kind):
    """``min_view_fraction``: the views it keeps are the full decode's, value for value
    (flat-fielded ones too); the others hold zeros and a valid fraction of 0."""
    grid = _lattice("hex")
    radius = grid.pitch_px / 2

    def white_f(dv, du, row, col):  # dimmer on one side: the white level matters too
        return np.where(np.hypot(dv, du) < radius - 1.5, 3000.0 * (1.0 - 0.04 * du), 0.0)

    raw = (_paint(grid, _linear) + 50).astype(np.float32)
    white = {"none": None, "raw": _paint(grid, white_f).astype(np.uint16)}.get(white_kind)
    if white_kind == "decoded":
        white = decode(_paint(grid, white_f).astype(np.uint16), grid)
    full = decode(raw, grid, white=white)
    part = decode(raw, grid, white=white, min_view_fraction=0.5)
    kept = full.valid_fraction >= 0.5
    assert 0 < kept.sum() < kept.size
    np.testing.assert_array_equal(part.data[kept], full.data[kept])
    np.testing.assert_array_equal(part.valid_fraction[kept], full.valid_fraction[kept])
    assert not part.data[~kept].any() and not part.valid_fraction[~kept].any()
    np.testing.assert_array_equal(part.view_mask, full.view_mask)
    with pytest.raises(SettingsError):
        decode(raw, grid, min_view_fraction=1.5)


def test_sampling_is_cached_per_grid_and_equals_a_fresh_computation():
    decode_module = importlib.import_module("plenoptrack.lightfield.decode")

    grid = _lattice("hex")
    rad = int(grid.pitch_px // 2)
    cached = decode_module._sampling(grid, rad)
    # an equal grid built anew (a calibration read again) hits the same entry
    again = decode_module._sampling(_lattice("hex"), rad)
    assert again is cached
    fresh = decode_module._sampling.__wrapped__(grid, rad)
    for name in ("j0", "w", "mask", "origin_px", "s_step_px", "t_step_px"):
        np.testing.assert_array_equal(getattr(cached, name), getattr(fresh, name))
    # another grid gets its own sampling
    other = decode_module._sampling(_lattice("hex", pitch=14.5), rad)
    assert other is not cached
    np.testing.assert_array_equal(decode_module._lens_centres(grid), grid.centers())


def test_light_fields_do_not_share_the_cached_sampling_arrays():
    grid = _lattice("hex")
    raw = _paint(grid, _linear).astype(np.float32)
    first = decode(raw, grid)
    mask = first.spatial_mask.copy()
    first.spatial_mask[:] = ~first.spatial_mask     # a caller writing to its light field
    second = decode(raw, grid)
    np.testing.assert_array_equal(second.spatial_mask, mask)
    np.testing.assert_array_equal(second.data, decode(raw, grid).data)
