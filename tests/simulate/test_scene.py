"""Scenes: random non-overlapping particles, motion, TOML scene files, validation."""

import numpy as np
import pytest

from plenoptrack import preset
from plenoptrack._columns import TRUTH_COLUMNS
from plenoptrack.errors import InputFileError
from plenoptrack.simulate import (SceneError, Volume, default_volume, load_scene, make_scene,
                                  moving_particles, random_particles)


def test_default_volumes():
    hall = default_volume(preset("hall2019"))
    assert hall.z_mm == (-25.0, 25.0)
    small = default_volume(preset("small"))
    assert small.z_mm == (-10.0, 10.0)
    # Inside the focal-plane field of view, with a margin.
    h, w = preset("small").sensor_size_mm
    assert 0 < small.x_mm[1] < w / 0.5 / 2 and 0 < small.y_mm[1] < h / 0.5 / 2


def test_random_particles_inside_non_overlapping_deterministic():
    vol = default_volume(preset("small"))
    a = random_particles(60, volume=vol, diameter_mm=0.8, seed=4)
    b = random_particles(60, volume=vol, diameter_mm=0.8, seed=4)
    assert list(a.columns) == list(TRUTH_COLUMNS)
    assert a.equals(b)
    assert not a.equals(random_particles(60, volume=vol, diameter_mm=0.8, seed=5))
    xyz = a[["x", "y", "z"]].to_numpy()
    assert vol.contains(xyz).all()
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1) + np.eye(len(xyz)) * 1e9
    assert d.min() >= 0.8


def test_dense_random_particles_never_overlap():
    vol = Volume((-5, 5), (-5, 5), (-5, 5))
    a = random_particles(2000, volume=vol, diameter_mm=0.5, seed=7)   # 13 % of the volume
    xyz = a[["x", "y", "z"]].to_numpy()
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xyz).query(xyz, k=2)
    assert d[:, 1].min() >= 0.5
    assert vol.contains(xyz).all()


def test_random_particles_errors():
    vol = Volume((-1, 1), (-1, 1), (-1, 1))
    with pytest.raises(SceneError, match="would fill 327% of the volume"):
        random_particles(50, volume=vol, diameter_mm=1.0, seed=0)
    with pytest.raises(SceneError, match="diameter_mm must be positive"):
        random_particles(2, volume=vol, diameter_mm=-1.0, seed=0)


def test_moving_particles_constant_velocity():
    first = random_particles(5, volume=default_volume(preset("small")), seed=1)
    truth = moving_particles(first, frames=4, velocity_mm_per_frame=(0.1, -0.2, 0.5))
    assert len(truth) == 20 and sorted(truth.frame.unique()) == [0, 1, 2, 3]
    for pid, track in truth.groupby("particle"):
        steps = np.diff(track.sort_values("frame")[["x", "y", "z"]].to_numpy(), axis=0)
        np.testing.assert_allclose(steps, [[0.1, -0.2, 0.5]] * 3)


def test_make_scene_frames():
    scene = make_scene(preset("small"), n_particles=7, frames=3, seed=2,
                       velocity_mm_per_frame=(0, 0, 1))
    assert scene.frames == 3 and len(scene.truth) == 21


def test_load_scene_random(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text('camera = "small"\nseed = 3\nframes = 2\n'
                    'velocity_mm_per_frame = [0.1, 0.0, 0.0]\n'
                    '[volume]\ndepth_mm = 10.0\n[random]\nn = 6\ndiameter_mm = 0.5\n')
    scene = load_scene(path)
    assert scene.camera == preset("small")
    assert scene.volume.z_mm == (-5.0, 5.0)
    assert len(scene.truth) == 12 and (scene.truth.diameter == 0.5).all()
    assert scene.truth.equals(load_scene(path).truth)


def test_load_scene_explicit_particles(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text('camera = "hall2019"\nmagnification = -0.4\nframes = 2\n'
                    '[[particles]]\nx = 0.0\ny = 0.0\nz = 0.0\ndiameter = 1.0\n'
                    '[[particles]]\nx = 5.0\ny = -3.0\nz = 10.0\ndiameter = 0.5\n'
                    'velocity_mm_per_frame = [0.0, 0.0, -1.0]\n')
    scene = load_scene(path)
    assert scene.camera.magnification == -0.4
    last = scene.truth[scene.truth.frame == 1].set_index("particle")
    assert last.loc[1, "z"] == 9.0 and last.loc[0, "z"] == 0.0


@pytest.mark.parametrize("body, error, match", [
    ('camera = "small"\n[[particles]]\nx = 0.0\ny = 0.0\nz = 99.0\ndiameter = 1.0\n',
     SceneError, "outside the volume"),
    ('camera = "small"\n[[particles]]\nx = 0.0\ny = 0.0\nz = 0.0\ndiameter = -1.0\n',
     SceneError, "diameters must be positive"),
    ('camera = "small"\n[[particles]]\nx = 0.0\ny = 0.0\nz = 0.0\ndiameter = 1.0\n'
     '[[particles]]\nx = 0.2\ny = 0.0\nz = 0.0\ndiameter = 1.0\n', SceneError, "overlap"),
    ('camera = "small"\n', InputFileError, "exactly one of"),
    ('camera = "small"\ncolour = 1\n[random]\nn = 1\n', InputFileError, "unknown key"),
    ('camera = "small"\n[random]\ndiameter_mm = 1.0\n', InputFileError, "missing key"),
    ('camera = [\n', InputFileError, "not valid TOML"),
])
def test_load_scene_errors(tmp_path, body, error, match):
    path = tmp_path / "scene.toml"
    path.write_text(body)
    with pytest.raises(error, match=match):
        load_scene(path)


def test_random_particles_log_uniform_diameter_range():
    vol = default_volume(preset("small"), diameter_mm=1.0)
    a = random_particles(400, volume=vol, diameter_mm=(0.2, 1.0), seed=3)
    assert a.equals(random_particles(400, volume=vol, diameter_mm=(0.2, 1.0), seed=3))
    d = a["diameter"].to_numpy()
    assert list(a.columns) == list(TRUTH_COLUMNS)
    assert d.min() >= 0.2 and d.max() <= 1.0 and len(np.unique(d)) == len(d)
    # Log-uniform: log d is uniform, so its median is the geometric mean of the range
    # and each half of the log range holds about half the particles.
    assert abs(np.median(np.log(d)) - np.log(np.sqrt(0.2 * 1.0))) < 0.1
    assert 0.4 < np.mean(d < np.sqrt(0.2 * 1.0)) < 0.6
    xyz = a[["x", "y", "z"]].to_numpy()
    assert vol.contains(xyz).all()
    gap = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1) + np.eye(len(xyz)) * 1e9
    assert (gap >= (d[:, None] + d[None]) / 2).all()


def test_diameter_range_equal_bounds_matches_single_diameter():
    vol = default_volume(preset("small"))
    single = random_particles(30, volume=vol, diameter_mm=0.5, seed=2)
    assert single.equals(random_particles(30, volume=vol, diameter_mm=(0.5, 0.5), seed=2))
    assert (single["diameter"] == 0.5).all()


def test_make_scene_diameter_range_records_each_diameter():
    scene = make_scene(preset("small"), n_particles=25, diameter_mm=(0.2, 0.8), frames=2,
                       velocity_mm_per_frame=(0.1, 0.0, 0.0), seed=5)
    first = scene.truth[scene.truth.frame == 0]
    assert first["diameter"].between(0.2, 0.8).all() and first["diameter"].nunique() == 25
    # Each particle keeps its diameter over the frames.
    assert (scene.truth.groupby("particle")["diameter"].nunique() == 1).all()
    # The volume leaves the margin of the largest diameter.
    assert scene.volume == default_volume(preset("small"), diameter_mm=0.8)


@pytest.mark.parametrize("bad, match", [
    ((1.0, 0.5), "min <= max"), ((0.0, 1.0), "min <= max"), ((0.2, np.inf), "min <= max"),
    ((0.1, 0.2, 0.3), "number or a \\(min, max\\) pair"), ("big", "number or a \\(min, max\\)"),
    (-1.0, "must be positive")])
def test_diameter_range_errors(bad, match):
    vol = Volume((-5, 5), (-5, 5), (-5, 5))
    with pytest.raises(SceneError, match=match):
        random_particles(3, volume=vol, diameter_mm=bad, seed=0)


def test_diameter_range_fill_limit_names_the_range():
    vol = Volume((-1, 1), (-1, 1), (-1, 1))
    with pytest.raises(SceneError, match="particles of 0.5-2 mm would fill"):
        random_particles(50, volume=vol, diameter_mm=(0.5, 2.0), seed=0)


def test_scene_file_diameter_range(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text('camera = "small"\nseed = 3\n[random]\nn = 10\ndiameter_mm = [0.2, 0.6]\n')
    truth = load_scene(path).truth
    assert truth["diameter"].between(0.2, 0.6).all() and truth["diameter"].nunique() == 10
