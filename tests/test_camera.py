import math

import pytest

from plenoptrack import CameraSpecError, load_camera, preset, save_camera
from plenoptrack.camera import PRESETS


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_have_matched_f_numbers(name):
    cam = preset(name)
    # the main lens's image-side working f-number matches the microlenses (fills the images)
    assert cam.image_side_f_number == pytest.approx(cam.microlens_f_number, rel=1e-3)


def test_hall2019_matches_the_paper_camera():
    cam = preset("hall2019")
    assert cam.sensor_shape_px == (4400, 6600)
    assert cam.grid_shape == (362, 471)
    assert cam.pixels_per_lenslet == pytest.approx(14.0)
    assert cam.magnification == -0.5
    # thin lens: 1/F = 1/s_o + 1/s_i and s_i / s_o = |M|
    assert 1 / cam.object_distance_mm + 1 / cam.image_distance_mm == pytest.approx(1 / cam.focal_length_mm)
    assert cam.image_distance_mm / cam.object_distance_mm == pytest.approx(0.5)


def test_alpha_convention():
    cam = preset("hall2019")
    assert cam.alpha_for_depth(0.0) == pytest.approx(1.0)
    assert cam.alpha_for_depth(10.0) < 1.0 < cam.alpha_for_depth(-10.0)
    for z in (-25.0, -3.0, 0.5, 25.0):
        assert cam.depth_for_alpha(cam.alpha_for_depth(z)) == pytest.approx(z, abs=1e-9)
    # independent thin-lens check at z = +25 mm: d = 1 / (1/105 - 1/340)
    assert cam.image_distance_for_depth(25.0) == pytest.approx(1 / (1 / 105 - 1 / 340))


def test_camera_toml_round_trip(tmp_path):
    cam = preset("small").with_changes(magnification=-0.75)
    path = save_camera(cam, tmp_path / "camera.toml")
    assert load_camera(path) == cam


def test_unknown_preset():
    with pytest.raises(CameraSpecError, match="unknown camera preset 'nope'"):
        preset("nope")


@pytest.mark.parametrize("text, match", [
    ("[camera]\nfocal_length_mm = 105\n", "missing key"),
    ("not = [toml", "not valid TOML"),
    ("[camera]\nbogus = 1\n", "unknown key"),
])
def test_bad_camera_files(tmp_path, text, match):
    path = tmp_path / "camera.toml"
    path.write_text(text)
    with pytest.raises(CameraSpecError, match=match):
        load_camera(path)


def test_missing_camera_file(tmp_path):
    with pytest.raises(CameraSpecError, match="not found"):
        load_camera(tmp_path / "absent.toml")


@pytest.mark.parametrize("field, value, match", [
    ("f_number", -2.0, "f_number must be a positive"),
    ("grid_type", "triangle", "grid_type must be"),
    ("magnification", 0.0, "magnification must be non-zero"),
    ("sensor_shape_px", (10,), "sensor_shape_px must be two"),
    ("focal_length_mm", math.nan, "focal_length_mm must be a positive"),
])
def test_invalid_values(field, value, match):
    with pytest.raises(CameraSpecError, match=match):
        preset("small").with_changes(**{field: value})
