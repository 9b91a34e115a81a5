"""Lenslet-grid calibration against the simulator's true microlens-image lattice."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plenoptrack import preset
from plenoptrack.errors import CalibrationError, InputFileError
from plenoptrack.lightfield import LensletGrid
from plenoptrack.lightfield.grid import GridMeasurement, calibrate_grid, measure_grid
from plenoptrack.simulate import make_optics, render_white

CENTRE_RMS_PX = 0.05
ROTATION_DEG = 0.01


def _on_sensor(centres: np.ndarray, sensor_shape) -> np.ndarray:
    rows, cols = sensor_shape
    return ((centres[:, 0] >= -0.5) & (centres[:, 0] <= rows - 0.5)
            & (centres[:, 1] >= -0.5) & (centres[:, 1] <= cols - 0.5))


def _centre_errors(grid: LensletGrid, true: LensletGrid) -> np.ndarray:
    """Distance of every on-sensor calibrated centre to its nearest true centre, px."""
    centres = grid.centers().reshape(-1, 2)
    centres = centres[_on_sensor(centres, grid.sensor_shape_px)]
    distance, _ = cKDTree(true.centers().reshape(-1, 2)).query(centres)
    return distance


def _assert_matches_truth(grid: LensletGrid, true: LensletGrid) -> None:
    assert grid.grid_type == true.grid_type
    errors = _centre_errors(grid, true)
    assert np.sqrt(np.mean(errors ** 2)) < CENTRE_RMS_PX
    assert abs(grid.rotation_deg - true.rotation_deg) < ROTATION_DEG
    # every true lens clearly on the sensor has a calibrated lens
    true_centres = true.centers().reshape(-1, 2)
    rows, cols = true.sensor_shape_px
    inside = ((true_centres >= -0.4) & (true_centres <= np.array([rows, cols]) - 0.6)).all(axis=1)
    distance, _ = cKDTree(grid.centers().reshape(-1, 2)).query(true_centres[inside])
    assert distance.max() < 0.2


@pytest.fixture(scope="module", params=[("small", 0), ("small", 3), ("small", 5),
                                        ("small-rect", 1), ("small-rect", 3), ("small-rect", 4)],
                ids=lambda p: f"{p[0]}-seed{p[1]}")
def simulated(request):
    name, seed = request.param
    optics = make_optics(preset(name), seed)
    return optics, render_white(optics, seed=seed, noise=True)


def test_matches_truth_without_hints(simulated):
    optics, white = simulated
    measurement = measure_grid(white)
    _assert_matches_truth(measurement.grid, optics.true_grid)


def test_matches_truth_with_camera_hints(simulated):
    optics, white = simulated
    camera = optics.camera
    grid = calibrate_grid(white, grid_type=camera.grid_type, pitch_px=camera.pixels_per_lenslet)
    _assert_matches_truth(grid, optics.true_grid)


def test_measurement_is_consistent(simulated):
    optics, white = simulated
    m = measure_grid(white)
    assert isinstance(m, GridMeasurement)
    n = m.n_detected
    assert m.centres_px.shape == m.indices.shape == m.residuals_px.shape == (n, 2)
    assert m.indices.dtype.kind == "i"
    # most lenses on the sensor are detected, with small residuals
    centres = m.grid.centers().reshape(-1, 2)
    assert n > 0.85 * _on_sensor(centres, m.grid.sensor_shape_px).sum()
    assert m.rms_residual_px < 0.2
    np.testing.assert_allclose(m.rms_residual_px,
                               np.sqrt(np.mean(np.sum(m.residuals_px ** 2, axis=1))))
    # indices follow the LensletGrid convention: detection = lattice centre + residual
    i, j = m.indices.T
    assert i.min() >= 0 and j.min() >= 0
    assert i.max() < m.grid.shape[0] and j.max() < m.grid.shape[1]
    np.testing.assert_allclose(m.grid.centers_of(i, j) + m.residuals_px, m.centres_px, atol=1e-9)


def test_grid_covers_sensor_from_top_left(simulated):
    optics, white = simulated
    grid = calibrate_grid(white)
    centres = grid.centers()
    on = _on_sensor(centres.reshape(-1, 2), grid.sensor_shape_px).reshape(grid.shape)
    # the first and last lattice rows and columns each hold a lens on the sensor
    assert on[0].any() and on[-1].any() and on[:, 0].any() and on[:, -1].any()
    # lens (0, 0) is the top-left: rows run down and columns to the right
    assert grid.col_step_px[1] > 0 and grid.row_step_px[0] > 0
    assert grid.sensor_shape_px == white.shape


@pytest.mark.parametrize("dtype", [np.uint16, np.float32, np.float64, np.int32])
def test_dtypes_agree(dtype):
    optics = make_optics(preset("small"), 2)
    white = render_white(optics, seed=2)
    reference = calibrate_grid(white)
    grid = calibrate_grid(white.astype(dtype))
    np.testing.assert_allclose(grid.origin_px, reference.origin_px, atol=1e-6)
    np.testing.assert_allclose(grid.basis, reference.basis, atol=1e-6)


def test_outlier_lenses_are_rejected():
    optics = make_optics(preset("small"), 1)
    white = render_white(optics, seed=1).astype(np.float64)
    true = optics.true_grid
    # deface a few lenses: a bright blob off-centre inside each microlens image
    rng = np.random.default_rng(0)
    centres = true.centers().reshape(-1, 2)
    inside = centres[(centres[:, 0] > 40) & (centres[:, 0] < 560)
                     & (centres[:, 1] > 40) & (centres[:, 1] < 870)]
    defaced = inside[rng.choice(len(inside), 40, replace=False)]
    for r, c in defaced.round().astype(int):
        white[r - 6:r + 1, c + 1:c + 5] = 3 * white.max()
    m = measure_grid(white)
    _assert_matches_truth(m.grid, true)
    # the defaced lenses are left out of the fit
    distance, _ = cKDTree(m.centres_px).query(defaced)
    assert np.sum(distance < 1.0) <= 2


def test_progress_flag_gives_same_result():
    optics = make_optics(preset("small"), 0)
    white = render_white(optics, seed=0)
    assert calibrate_grid(white, progress=True) == calibrate_grid(white)


# --- errors -----------------------------------------------------------------------------

def test_not_2d():
    with pytest.raises(InputFileError, match="must be 2-D"):
        measure_grid(np.zeros((3, 100, 100)))


def test_not_numbers():
    with pytest.raises(InputFileError, match="real numbers"):
        measure_grid(np.full((100, 100), "a"))


def test_nan():
    white = np.ones((100, 100))
    white[5, 5] = np.nan
    with pytest.raises(InputFileError, match="NaN"):
        measure_grid(white)


@pytest.mark.parametrize("value", [0, 4095])
def test_blank(value):
    with pytest.raises(CalibrationError, match="blank"):
        measure_grid(np.full((600, 910), value, dtype=np.uint16))


def test_noise_is_no_grid():
    white = np.random.default_rng(0).poisson(1000, size=(600, 910)).astype(np.uint16)
    with pytest.raises(CalibrationError, match="no lenslet grid found in the white image"):
        measure_grid(white)


def test_smooth_image_is_no_grid():
    rows, cols = np.mgrid[0:600, 0:910]
    white = (1000 + 500 * np.sin(rows / 90.0) * np.cos(cols / 70.0)).astype(np.uint16)
    with pytest.raises(CalibrationError, match="no lenslet grid found"):
        measure_grid(white)


def test_wrong_grid_type():
    optics = make_optics(preset("small-rect"), 0)
    with pytest.raises(CalibrationError, match="shows a rect lenslet grid but grid_type='hex'"):
        measure_grid(render_white(optics, seed=0), grid_type="hex")


def test_wrong_pitch_hint():
    optics = make_optics(preset("small"), 0)
    with pytest.raises(CalibrationError, match="lenslets 14.0. px apart but pitch_px=30"):
        measure_grid(render_white(optics, seed=0), pitch_px=30.0)


@pytest.mark.parametrize("kwargs, match", [({"grid_type": "square"}, "grid_type"),
                                           ({"pitch_px": 1.0}, "pitch_px")])
def test_bad_options(kwargs, match):
    with pytest.raises(CalibrationError, match=match):
        measure_grid(np.ones((50, 50)), **kwargs)


def test_too_few_lenses():
    optics = make_optics(preset("small"), 0)
    white = render_white(optics, seed=0)
    with pytest.raises(CalibrationError, match="too small|lenslets|no lenslet grid"):
        measure_grid(white[:40, :40])


# --- full sensor --------------------------------------------------------------------------

@pytest.mark.slow
def test_full_sensor_hall2019():
    optics = make_optics(preset("hall2019"), 7)
    white = render_white(optics, seed=7)
    m = measure_grid(white, grid_type="hex", pitch_px=optics.camera.pixels_per_lenslet)
    _assert_matches_truth(m.grid, optics.true_grid)
    assert m.n_detected > 160_000
