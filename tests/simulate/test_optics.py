"""True optics: perturbation draws, true lenslet grid, sign conventions, serialisation."""

import json

import numpy as np
import pytest

from plenoptrack import preset
from plenoptrack.errors import CalibrationError, CameraSpecError
from plenoptrack.simulate import SimOptics, make_optics


@pytest.mark.parametrize("name", ["hall2019", "small", "small-rect"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_perturbation_ranges(name, seed):
    cam = preset(name)
    o = make_optics(cam, seed)
    assert 0.05 <= abs(o.rotation_deg) <= 0.5
    pp = cam.pixel_pitch_um * 1e-3
    assert all(abs(v) <= 0.5 * pp for v in o.offset_mm)
    assert abs(o.pitch_scale - 1) <= 0.002
    assert (o.k1, o.k2) == (0.02, -0.005)


def test_same_seed_same_optics_and_signs_vary():
    cam = preset("small")
    assert make_optics(cam, 5) == make_optics(cam, 5)
    signs = {np.sign(make_optics(cam, s).rotation_deg) for s in range(10)}
    assert signs == {-1.0, 1.0}


@pytest.mark.parametrize("name", ["small", "small-rect", "hall2019"])
def test_true_grid_matches_lens_centres_and_covers_sensor(name):
    o = make_optics(preset(name), 3)
    grid = o.true_grid
    assert grid.grid_type == o.camera.grid_type
    assert grid.rotation_deg == pytest.approx(o.rotation_deg, abs=1e-9)
    assert grid.pitch_px == pytest.approx(o.pitch * o.image_scale / o.pixel_pitch, rel=1e-12)
    centres = grid.centers()
    # Grid lens (a, b) is physical lens (i0 + a, j0 + b); compare via the optics.
    i0, j0 = np.round(o.lattice_coords(o.pixels_to_sensor_mm(grid.origin_px) / o.image_scale))
    i, j = np.meshgrid(np.arange(grid.shape[0]), np.arange(grid.shape[1]), indexing="ij")
    expected = o.mla_to_pixels(o.lens_centers_mm(i + int(i0), j + int(j0)))
    np.testing.assert_allclose(centres, expected, atol=1e-9)
    rows, cols = o.camera.sensor_shape_px
    assert centres[..., 0].min() < 0 and centres[..., 0].max() > rows - 1
    assert centres[..., 1].min() < 0 and centres[..., 1].max() > cols - 1


def test_axis_maps_to_sensor_centre_and_world_signs():
    o = SimOptics(preset("small"))  # unperturbed, no distortion
    rows, cols = o.camera.sensor_shape_px
    centre = o.world_to_pixels([0.0, 0.0, 0.0])
    np.testing.assert_allclose(centre, [(rows - 1) / 2, (cols - 1) / 2])
    right = o.world_to_pixels([1.0, 0.0, 0.0])
    down = o.world_to_pixels([0.0, 1.0, 0.0])
    scale = abs(o.camera.magnification) * o.image_scale / o.pixel_pitch
    np.testing.assert_allclose(right - centre, [0.0, scale])     # +x -> larger column
    np.testing.assert_allclose(down - centre, [scale, 0.0])      # +y -> larger row


def test_distortion_inverse_round_trips():
    o = make_optics(preset("hall2019"), 0, k1=0.05, k2=-0.01)
    q = np.array([[0.0, 0.0], [1.0, -2.0], [15.0, 10.0]])
    focal = -q * (o.s_o / o.s_i) * o.distortion_factor(np.hypot(q[:, 0], q[:, 1]))[:, None]
    np.testing.assert_allclose(o.focal_plane_to_mla(focal), q, atol=1e-12)


def test_to_dict_round_trip_through_json():
    o = make_optics(preset("small-rect"), 9)
    doc = json.loads(json.dumps(o.to_dict()))
    back = SimOptics.from_dict(doc)
    assert back == o
    assert doc["true_grid"] == o.true_grid.to_dict()


def test_from_dict_rejects_corrupt():
    doc = make_optics(preset("small"), 1).to_dict()
    doc["true_grid"]["origin_px"] = [0.0, 0.0]
    with pytest.raises(CalibrationError, match="does not match"):
        SimOptics.from_dict(doc)
    with pytest.raises(CalibrationError, match="not a simulator optics"):
        SimOptics.from_dict({"format": "other"})


def test_invalid_optics():
    with pytest.raises(CameraSpecError, match="pitch_scale"):
        SimOptics(preset("small"), pitch_scale=2.0)
    with pytest.raises(CameraSpecError, match="camera must be a CameraSpec"):
        make_optics("small", 0)
