import json

import numpy as np
import pytest

from plenoptrack import preset
from plenoptrack.calibration import (Calibration, find_white, load_calibration, record_white,
                                     save_calibration)
from plenoptrack.errors import CalibrationError
from plenoptrack.lightfield import LensletGrid


@pytest.fixture
def calibration():
    cam = preset("small")
    grid = LensletGrid("hex", (49, 66), (3.2, 4.1), (0.01, 14.03), (12.15, -0.01), 0.5,
                       cam.sensor_shape_px)
    return Calibration(camera=cam, grid=grid, vignetting=np.linspace(0, 1, 225).reshape(15, 15))


def test_round_trip(tmp_path, calibration):
    path = save_calibration(calibration, tmp_path / "calib.json")
    loaded = load_calibration(path, camera=preset("small"))
    assert loaded.grid == calibration.grid
    assert loaded.camera == calibration.camera
    np.testing.assert_allclose(loaded.vignetting, calibration.vignetting)


def test_other_camera_refused(tmp_path, calibration):
    path = save_calibration(calibration, tmp_path / "calib.json")
    with pytest.raises(CalibrationError, match="made for another camera .*magnification"):
        load_calibration(path, camera=preset("small").with_changes(magnification=-0.75))


def test_wrong_image_size_refused(calibration):
    with pytest.raises(CalibrationError, match="image is 10 x 10 pixels but the calibration is for a 600 x 910"):
        calibration.check_image(np.zeros((10, 10)))


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d.pop("format"), "not a plenoptrack calibration file"),
    (lambda d: d.update(version=99), "version 99 is not supported"),
    (lambda d: d.pop("lenslet_grid"), "no 'lenslet_grid' section"),
    (lambda d: d["lenslet_grid"].update(odd_row_shift=0.3), "odd_row_shift"),
    (lambda d: d["lenslet_grid"].update(origin_px=["a", 1]), "corrupt lenslet grid|origin_px"),
    (lambda d: d["lenslet_grid"].update(sensor_shape_px=[10, 10]), "measured on a"),
])
def test_corrupt_files(tmp_path, calibration, mutate, match):
    data = calibration.to_dict()
    mutate(data)
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=match):
        load_calibration(path)


def test_not_json(tmp_path):
    path = tmp_path / "calib.json"
    path.write_text("{truncated")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_calibration(path)


def test_lattice_centres_and_coordinates(calibration):
    g = calibration.grid
    c = g.centers()
    assert c.shape == (49, 66, 2)
    # odd rows shifted by half a column step
    np.testing.assert_allclose(c[1, 0] - c[0, 0], np.add(g.row_step_px, np.multiply(0.5, g.col_step_px)))
    ij = g.lattice_coords(c[2:4, 5])
    np.testing.assert_allclose(ij, [[2, 5], [3, 5.5]], atol=1e-9)
    assert g.pitch_px == pytest.approx(np.hypot(0.01, 14.03))
    assert g.rotation_deg == pytest.approx(np.degrees(np.arctan2(0.01, 14.03)))


def test_white_image_record(tmp_path, calibration):
    (tmp_path / "data").mkdir()
    white = tmp_path / "data" / "white.tif"
    white.write_bytes(b"white image bytes")
    path = tmp_path / "calib.json"
    save_calibration(record_white(calibration, white, calibration_path=path), path)
    loaded = load_calibration(path)
    assert loaded.extra["white_image"]["file"] == "data/white.tif"   # relative: movable
    assert find_white(loaded, path) == (white, "")
    # the folder moved as a whole: still found
    (tmp_path / "data").rename(tmp_path / "moved")
    moved = tmp_path / "moved"
    (moved / "data").mkdir()
    (moved / "white.tif").rename(moved / "data" / "white.tif")
    path.rename(moved / "calib.json")
    assert find_white(loaded, moved / "calib.json") == (moved / "data" / "white.tif", "")
    # gone, or changed: not found, and the reason names the file
    found, why = find_white(loaded, tmp_path / "calib.json")
    assert found is None and "data/white.tif" in why and "not there" in why
    (moved / "data" / "white.tif").write_bytes(b"another image")
    found, why = find_white(loaded, moved / "calib.json")
    assert found is None and "changed since" in why
    assert find_white(calibration, path)[0] is None                   # nothing recorded
    # a white image outside the calibration's folder is recorded by its absolute path
    outside = tmp_path / "elsewhere" / "w.tif"
    outside.parent.mkdir()
    outside.write_bytes(b"w")
    rec = record_white(calibration, outside, calibration_path=moved / "calib.json")
    assert rec.extra["white_image"]["file"] == str(outside.resolve())
