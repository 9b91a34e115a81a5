"""Built-in scenes: the fragment ring's kinematics and geometry, Hill's vortex field, overrides."""

import math

import numpy as np
import pytest

from plenoptrack.errors import SettingsError
from plenoptrack.simulate.scenes import (FragmentField, VortexRing, builtin_scene,
                                         fragment_field_scene, hill_vortex_velocity,
                                         read_scene_spec, scene_params, vortex_ring_scene)

VEL = ["velocity_x", "velocity_y", "velocity_z"]
POS = ["x", "y", "z"]


@pytest.fixture(scope="module")
def fragments():
    return fragment_field_scene(FragmentField(n_fragments=10, frames=4))


@pytest.fixture(scope="module")
def vortex():
    return vortex_ring_scene(VortexRing(n_particles=60, frames=6))


def _by_particle(truth, frame):
    return truth[truth["frame"] == frame].set_index("particle").sort_index()


def test_fragments_move_ballistically_at_the_drawn_speed(fragments):
    p = FragmentField(n_fragments=10, frames=4)
    truth = fragments.truth
    f0, f3 = _by_particle(truth, 0), _by_particle(truth, 3)
    step = (f3[POS].to_numpy() - f0[POS].to_numpy()) / 3
    np.testing.assert_allclose(step, f0[VEL].to_numpy(), atol=1e-9)
    speed_m_s = np.linalg.norm(f0[VEL].to_numpy(), axis=1) / p.frame_interval_s * 1e-3
    assert (speed_m_s >= p.speed_m_per_s[0] - 1e-6).all()
    assert (speed_m_s <= p.speed_m_per_s[1] + 1e-6).all()


def test_fragments_fly_out_from_a_tilted_cylinder(fragments):
    p = FragmentField()
    t = math.radians(p.tilt_deg)
    axis = np.array([0.0, math.sin(t), math.cos(t)])
    f0 = _by_particle(fragments.truth, 0)
    v = f0[VEL].to_numpy()
    r = f0[POS].to_numpy() - np.asarray(p.centre_mm)
    radial = r - (r @ axis)[:, None] * axis
    # velocity within spread_deg of the radial direction
    cos_out = (v @ axis) / np.linalg.norm(v, axis=1)
    assert (np.abs(cos_out) <= math.sin(math.radians(p.spread_deg)) + 1e-9).all()
    v_plane = v - (v @ axis)[:, None] * axis
    cosang = (v_plane * radial).sum(1) / np.linalg.norm(v_plane, axis=1) / np.linalg.norm(radial, axis=1)
    assert (cosang > 0.999).all()
    # tilted towards the camera: the upper part of the ring (y < 0) is farther away
    up = np.abs(radial[:, 1]) > 0.1
    assert up.sum() >= 5
    assert (np.sign(radial[up, 1]) == -np.sign(radial[up, 2])).all()


def test_fragments_sizes_shapes_and_no_overlap(fragments):
    truth = fragments.truth
    assert (truth["shape"] == "fragment").all()
    assert truth["diameter"].between(0.5, 5.0).all()
    assert (truth["projected_area"] > 0).all()
    # silhouettes do not change (no tumbling) and the truth has one row per fragment and frame
    assert truth.groupby("particle")["projected_area"].nunique().eq(1).all()
    assert len(truth) == 10 * 4
    from plenoptrack.simulate.scene import _bounding_radii

    for _, g in truth.groupby("frame"):
        xyz = g[POS].to_numpy()
        r = _bounding_radii(g)
        d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        assert (d >= r[:, None] + r[None] - 1e-9).all()
    assert fragments.realism.particles.exposure_fraction == pytest.approx(0.04)
    assert fragments.realism.particles.max_transmission == 0.0


def test_hill_vortex_is_continuous_divergence_free_and_still_far_away():
    a, U, axis = 5.0, 0.7, np.array([0.3, -0.2, 1.0])
    rng = np.random.default_rng(0)
    # continuity across the sphere r = a
    d = rng.standard_normal((50, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    inside = hill_vortex_velocity(d * a * (1 - 1e-9), radius_mm=a, speed=U, axis=axis)
    outside = hill_vortex_velocity(d * a * (1 + 1e-9), radius_mm=a, speed=U, axis=axis)
    np.testing.assert_allclose(inside, outside, atol=1e-6)
    # divergence by central differences, inside and outside
    for scale in (0.5, 2.0):
        p = rng.standard_normal((30, 3)) * a * scale
        h = 1e-4
        div = sum((hill_vortex_velocity(p + h * e, radius_mm=a, speed=U, axis=axis)[:, i]
                   - hill_vortex_velocity(p - h * e, radius_mm=a, speed=U, axis=axis)[:, i]) / (2 * h)
                  for i, e in enumerate(np.eye(3)))
        np.testing.assert_allclose(div, 0.0, atol=1e-6)
    # fluid at rest far away; the centre moves forward at 5U/2 along the axis
    far = hill_vortex_velocity(np.array([[200 * a, 0, 0]]), radius_mm=a, speed=U, axis=axis)
    assert np.linalg.norm(far) < 1e-5
    centre = hill_vortex_velocity(np.zeros((1, 3)), radius_mm=a, speed=U, axis=axis)[0]
    np.testing.assert_allclose(centre, 2.5 * U * axis / np.linalg.norm(axis), atol=1e-12)


def test_vortex_tracers_follow_the_field(vortex):
    p = VortexRing(n_particles=60, frames=6)
    truth = vortex.truth
    f2, f3, f4 = (_by_particle(truth, f) for f in (2, 3, 4))
    central = (f4[POS].to_numpy() - f2[POS].to_numpy()) / 2
    np.testing.assert_allclose(central, f3[VEL].to_numpy(), atol=0.01)
    # the truth velocity is the analytic field at the truth position
    axis = np.asarray(p.axis) / np.linalg.norm(p.axis)
    drift = np.asarray(p.stream_mm_per_frame) + p.speed_mm_per_frame * axis
    centre = np.asarray(p.start_mm) + 3 * drift
    v = hill_vortex_velocity(f3[POS].to_numpy() - centre, radius_mm=p.radius_mm,
                             speed=p.speed_mm_per_frame, axis=axis) + p.stream_mm_per_frame
    np.testing.assert_allclose(v, f3[VEL].to_numpy(), atol=1e-12)
    # seeded in the sphere, at least one diameter apart
    f0 = _by_particle(truth, 0)[POS].to_numpy()
    assert (np.linalg.norm(f0 - p.start_mm, axis=1) <= p.seed_radius_factor * p.radius_mm + 1e-9).all()
    d = np.linalg.norm(f0[:, None] - f0[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d.min() >= p.diameter_mm


def test_overrides_from_a_file_and_their_errors(tmp_path):
    f = tmp_path / "scene.toml"
    f.write_text('scene = "vortex-ring"\nn_particles = 7\nframes = 3\nstart_mm = [0, 1, 2]\n')
    name, overrides = read_scene_spec(f)
    scene, doc = builtin_scene(name, overrides)
    assert scene.truth["particle"].nunique() == 7 and scene.frames == 3
    assert doc["start_mm"] == [0.0, 1.0, 2.0] and doc["scene"] == "vortex-ring"
    assert read_scene_spec("fragments") == ("fragments", {})
    assert read_scene_spec(tmp_path / "missing.toml") is None
    with pytest.raises(SettingsError, match="unknown key"):
        scene_params("fragments", {"n_fragmnets": 3})
    with pytest.raises(SettingsError, match="must be an integer"):
        scene_params("vortex-ring", {"frames": 2.5})
    with pytest.raises(SettingsError, match="scene must be one of"):
        scene_params("tornado")
    with pytest.raises(SettingsError, match="exposure_s"):
        scene_params("fragments", {"exposure_s": 1.0})


def test_scene_camera_from_a_file(tmp_path):
    from dataclasses import replace

    from plenoptrack.camera import preset, save_camera

    camera = replace(preset("small"), name="my-camera")
    save_camera(camera, tmp_path / "camera.toml")
    scene, doc = builtin_scene("vortex-ring", {"camera": str(tmp_path / "camera.toml"),
                                               "n_particles": 3, "frames": 2, "radius_mm": 1.0})
    assert scene.camera == camera and doc["camera"] == str(tmp_path / "camera.toml")
    with pytest.raises(ValueError, match="unknown camera preset"):
        builtin_scene("vortex-ring", {"camera": str(tmp_path / "missing.toml")})
