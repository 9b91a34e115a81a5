"""Realistic dot cards and spec sheets: the target and spec effects of the simulator.

The cards are tilted, misprinted, off-centre and off their stated depths; the true focal
lengths differ from camera.toml. The calibration absorbs what it can, and the truth table
is in the frame the target defines, so locating against it stays unbiased.
"""

import json
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from plenoptrack import load_camera, preset
from plenoptrack.simulate import (CardPlacement, Realism, SpecEffects, TargetEffects,
                                  draw_card_placements, load_scene, make_optics,
                                  simulate_dataset, true_camera)
from plenoptrack.simulate.dotcard import dot_grid, dotcard_irradiance

PLACED = CardPlacement(depth_error_mm=0.3, tilt=(0.0087, -0.004), centre_mm=(0.2, -0.1),
                       print_sigma_mm=0.005, print_seed=11)


def test_culling_is_exact_for_tilted_misprinted_cards():
    optics = make_optics(preset("small"), seed=3)
    fast = dotcard_irradiance(optics, 4.0, placement=PLACED)
    exact = dotcard_irradiance(optics, 4.0, placement=PLACED, exact=True)
    np.testing.assert_array_equal(fast, exact)
    assert not np.array_equal(fast, dotcard_irradiance(optics, 4.0))


def test_a_perfect_placement_renders_the_ideal_card():
    optics = make_optics(preset("small"), seed=3)
    np.testing.assert_array_equal(dotcard_irradiance(optics, -3.0, placement=CardPlacement()),
                                  dotcard_irradiance(optics, -3.0))


def test_dot_shadows_follow_the_placed_dots():
    """The darkest microlens images of an in-focus card sit where dot_grid puts the dots."""
    optics = make_optics(preset("small"), seed=3)
    shifted = CardPlacement(centre_mm=(0.31, -0.17))
    for placement in (None, shifted):
        irr = dotcard_irradiance(optics, 0.0, placement=placement)
        dots = dot_grid(optics, 0.0, _card(optics), placement)
        inner = dots[(dots.row > 40) & (dots.row < 560) & (dots.col > 40) & (dots.col < 870)]
        r = np.rint(inner.row.to_numpy()).astype(int)
        c = np.rint(inner.col.to_numpy()).astype(int)
        # at the focal plane a dot darkens the whole microlens image it falls on
        darkness = [1 - irr[rr - 3:rr + 4, cc - 3:cc + 4].mean() / irr.mean() for rr, cc in zip(r, c)]
        assert np.median(darkness) > 0.5


def _card(optics):
    from plenoptrack.simulate import default_dotcard

    return default_dotcard(optics.camera)


def test_placements_are_drawn_within_their_sizes():
    effects = TargetEffects()
    zero, centre, cards = draw_card_placements(effects, 200, seed=1)
    assert abs(zero) <= effects.zero_offset_mm
    assert np.hypot(*centre) <= effects.centre_offset_mm
    errors = np.array([c.depth_error_mm for c in cards]) - zero
    assert np.std(errors) == pytest.approx(effects.depth_sigma_um * 1e-3, rel=0.2)
    tilts = np.degrees(np.arctan(np.hypot(*np.array([c.tilt for c in cards]).T)))
    assert tilts.max() <= effects.tilt_deg and tilts.max() > 0.9 * effects.tilt_deg
    assert len({c.print_seed for c in cards}) == 200
    zero0, centre0, perfect = draw_card_placements(TargetEffects().scaled(0), 3, seed=1)
    assert zero0 == 0 and centre0 == (0.0, 0.0) and all(c.is_perfect for c in perfect)


def test_true_camera_differs_from_the_spec_sheet_within_the_stated_errors():
    nominal = preset("small")
    spec = SpecEffects()
    rng = np.random.default_rng(0)
    trues = [true_camera(nominal, spec, rng) for _ in range(300)]
    f = np.array([t.focal_length_mm for t in trues]) / nominal.focal_length_mm - 1
    fml = np.array([t.microlens_focal_length_um for t in trues]) / nominal.microlens_focal_length_um - 1
    assert np.abs(f).max() <= spec.focal_length_error and np.abs(f).max() > 0.9 * spec.focal_length_error
    assert np.abs(fml).max() <= spec.microlens_focal_length_error
    # the aperture is never wider than the true microlenses allow: images do not overlap
    assert max(t.microlens_fill for t in trues) <= 1.0 + 1e-9
    assert min(t.microlens_fill for t in trues) >= 1.0 / (1.0 + spec.f_number_mismatch) - 1e-9
    assert all(t.magnification == nominal.magnification for t in trues)


def test_make_optics_keeps_the_nominal_camera():
    optics = make_optics(preset("small"), seed=4, realism=replace(Realism.ideal(), spec=SpecEffects()))
    assert optics.nominal_camera == preset("small")
    assert optics.camera != preset("small")
    assert make_optics(preset("small"), seed=4).nominal is None


def test_scene_file_optics_table(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text("camera = 'small'\n[random]\nn = 1\n[optics]\nmode = 'ideal'\n"
                    "[optics.target]\ntilt_deg = 0.2\n")
    scene = load_scene(path)
    assert scene.realism.target.tilt_deg == 0.2 and scene.realism.target.depth_sigma_um == 0
    assert not scene.realism.sensor.enabled
    path.write_text("camera = 'small'\n[random]\nn = 1\n[optics]\n[optics.target]\ntilt = 1\n")
    from plenoptrack.errors import InputFileError

    with pytest.raises(InputFileError, match=r"\[optics\].target: unknown key\(s\) \['tilt'\]"):
        load_scene(path)


@pytest.fixture(scope="module")
def realistic_target(tmp_path_factory):
    """A 'small' data set with realistic cards and spec sheet (image effects off).

    The card is centred 0.9 mm off the axis (seed 21: x 0.81 mm, more than half its
    1.25 mm spacing), so the dot nearest the axis is not the one it was printed around.
    """
    realism = replace(Realism.ideal(), target=TargetEffects(zero_offset_mm=0.5,
                                                            centre_offset_mm=1.0),
                      spec=SpecEffects())
    out = tmp_path_factory.mktemp("target") / "sim"
    return simulate_dataset("small", out, seed=21, n_particles=12, realism=realism)


def test_files_record_nominal_and_true_optics(realistic_target):
    sim = realistic_target
    assert load_camera(sim.camera_path) == preset("small")
    doc = json.loads(sim.optics_path.read_text())
    assert doc["nominal_camera"] == preset("small").to_dict()
    assert doc["camera"] != doc["nominal_camera"]
    origin = doc["target_frame"]["origin_world_mm"]
    assert origin[2] != 0 and abs(origin[2]) <= 0.5
    # the frame's origin is the dot nearest the axis: one spacing back from the 0.81 mm centre
    assert origin[0] == pytest.approx(0.811 - 1.25, abs=0.001)
    assert origin[1] == pytest.approx(0.398, abs=0.001)
    cards = tomllib.loads((sim.dotcards_path).read_text())["cards"]
    assert [c["z_mm"] for c in cards] == [d["z_stated_mm"] for d in doc["dotcards"]]
    assert len({d["depth_error_mm"] for d in doc["dotcards"]}) == len(cards)


def test_locating_against_the_target_frame_truth_is_unbiased(realistic_target):
    """The calibration's frame is the target's: no bias of the traverse zero offset."""
    from plenoptrack.calibrate import calibrate
    from plenoptrack.evaluate import evaluate_particles
    from plenoptrack.io import read_raw
    from plenoptrack.locate.perspective import locate_frame

    sim = realistic_target
    calib, report = calibrate(sim.white_path, sim.out_dir / "dotcards", sim.camera)
    particles = locate_frame(read_raw(sim.frame_paths[0]), calib).particles
    ev = evaluate_particles(particles, sim.truth, tolerance_mm=1.0)
    zero = json.loads(sim.optics_path.read_text())["target_frame"]["origin_world_mm"][2]
    assert ev.recall >= 0.9
    assert abs(ev.mean_error_z) < 0.25 * abs(zero) + 0.05
    # the calibration's dot (0, 0) is the truth's: no whole-spacing (1.25 mm) lateral shift
    assert abs(ev.mean_error_x) < 0.05 and abs(ev.mean_error_y) < 0.05


def test_origin_dot_is_the_one_the_sensor_centre_sees():
    """An optical axis off the sensor centre moves the point the calibration takes for
    the axis; the truth's origin is the dot nearest that point, not nearest the axis."""
    from plenoptrack.simulate import SimOptics, origin_dot_mm, sensor_centre_aim_mm

    optics = SimOptics(camera=preset("small").with_magnification(-1.0),
                       axis_offset_mm=(0.03, -0.09))
    aim = sensor_centre_aim_mm(optics)
    assert aim == pytest.approx((-0.03, 0.09))
    # dot printed around (-0.16, -0.18), spacing 0.5: +0.32 is nearer the aim than -0.18
    assert origin_dot_mm((-0.16, -0.18), 0.5, aim) == pytest.approx((-0.16, 0.32))
    assert origin_dot_mm((-0.16, -0.18), 0.5) == pytest.approx((-0.16, -0.18))


def test_realistic_camera_with_an_off_centre_axis_is_scored_in_its_own_frame(tmp_path):
    """small at M -1, seed 901: the axis is 0.09 mm off the sensor centre and the card
    0.18 mm off the axis, so the dot the calibration makes (0, 0) is one spacing (0.5 mm)
    from the one the card was printed around. Scored in the calibration's frame the
    lateral errors stay far below that spacing."""
    from plenoptrack.calibrate import calibrate
    from plenoptrack.evaluate import evaluate_particles
    from plenoptrack.io import read_raw
    from plenoptrack.lightfield import decode
    from plenoptrack.locate.perspective import locate_frame

    sim = simulate_dataset("small", tmp_path / "sim", seed=901, n_particles=15,
                           magnification=-1.0, realism="realistic")
    origin = json.loads(sim.optics_path.read_text())["target_frame"]["origin_world_mm"]
    assert origin[1] == pytest.approx(0.32, abs=0.01)
    calib, _ = calibrate(sim.white_path, sim.out_dir / "dotcards", sim.camera)
    white = decode(read_raw(sim.white_path), calib.grid)
    particles = locate_frame(read_raw(sim.frame_paths[0]), calib, white=white).particles
    ev = evaluate_particles(particles, sim.truth, tolerance_mm=0.3)
    assert ev.recall >= 0.6          # none within 0.3 mm if the frame were 0.5 mm off
    assert abs(ev.mean_error_x) < 0.05 and abs(ev.mean_error_y) < 0.05
