"""End-to-end tests of the perspective-shift locator on simulated images.

One calibration (white image, lenslet grid, dot cards, DLFC) per camera is shared by the
scenes of a module: the optics seed is fixed, the scene and noise seeds vary.
"""

import math
import warnings

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack.calibration import calibrate_from_white
from plenoptrack.errors import NoParticlesWarning, SettingsError
from plenoptrack.evaluate import evaluate_particles, match_particles
from plenoptrack.lightfield import decode
from plenoptrack.locate.dlfc import fit_dlfc
from plenoptrack.locate.dotcards import dotcard_points
from plenoptrack.locate.opacity import edge_blur_by_depth
from plenoptrack.locate.perspective import (PARTICLE_COLUMNS, PerspectiveLocator, locate_frame,
                                          segment_frame)
from plenoptrack.simulate import (default_dotcard, default_dotcard_depths, make_optics,
                                  make_scene, render_dotcard, render_frame, render_white)


def _calibrated(camera_name: str, depths=None, realism=None, locking: bool = False):
    """Optics (seed 0) and a calibration with a DLFC fitted on simulated dot cards; with
    ``realism`` (e.g. ``"realistic"``) the optics have those effects and the dot cards
    are flat-fielded with the white image, as ``plenoptrack calibrate`` does; with
    ``locking`` the calibration records the dots' pixel-locking pattern (and so their
    image size), as ``plenoptrack calibrate`` does too."""
    camera = preset(camera_name)
    optics = make_optics(camera, seed=0, realism=realism)
    white = render_white(optics, seed=np.random.default_rng([0, 2]))
    calib, _ = calibrate_from_white(white, camera)
    card = default_dotcard(camera)
    depths = default_dotcard_depths(camera) if depths is None else depths
    points = []
    for k, z in enumerate(depths):
        image = render_dotcard(optics, float(z), card=card, seed=np.random.default_rng([0, 4, k]))
        points.append(dotcard_points(decode(image, calib.grid,
                                            white=white if realism is not None else None),
                                     spacing_mm=card.spacing_mm, z_mm=float(z), camera=camera))
    points = pd.concat(points, ignore_index=True)
    dlfc = fit_dlfc(points, order=4, group_by="z", reject_k=5)
    # as plenoptrack.calibrate does: the views' edge blur from the dots
    calib = calib.with_dlfc(dlfc).with_edge_blur(edge_blur_by_depth(points))
    if locking:
        from plenoptrack.locate.pixel_locking import pattern_from_dots

        calib = calib.with_locking_pattern(pattern_from_dots(points, dlfc, calib.grid))
    return optics, calib


def _frame(optics, truth, seed: int) -> np.ndarray:
    return render_frame(optics, truth, seed=np.random.default_rng([seed, 3, 0]))


@pytest.fixture(scope="module")
def small(small_calibrated):
    return small_calibrated


def test_small_scenes_recall_and_precision(small):
    optics, calib = small
    n_true = n_found = n_matched = 0
    per_seed = []
    ratios = []   # |error| / sigma of every matched particle, x, y, z
    for seed in range(5):
        scene = make_scene(calib.camera, n_particles=20, seed=seed)
        result = locate_frame(_frame(optics, scene.truth, seed), calib)
        ev = evaluate_particles(result.particles, scene.truth, tolerance_mm=1.0)
        pairs = match_particles(result.particles, scene.truth, tolerance_mm=1.0)
        found = result.particles.loc[pairs["measured_index"]].reset_index(drop=True)
        true = scene.truth.loc[pairs["truth_index"]].reset_index(drop=True)
        ratios.append(np.abs(found[["x", "y", "z"]].to_numpy() - true[["x", "y", "z"]].to_numpy())
                      / found[["sigma_x", "sigma_y", "sigma_z"]].to_numpy())
        per_seed.append((seed, ev.recall, ev.precision))
        n_true += ev.n_true
        n_found += ev.n_measured
        n_matched += ev.n_matched
        # Well-located: depth within a few tenths of a mm, lateral within a few hundredths.
        assert abs(ev.mean_error_z) < 0.15 and ev.rms_error_lateral < 0.06, per_seed[-1]
    assert n_matched / n_true >= 0.98, per_seed
    assert n_matched / n_found >= 0.98, per_seed
    assert min(min(r, p) for _, r, p in per_seed) >= 0.95, per_seed
    # sigma covers the error: the plain least-squares sigma covered 30-45 % at 1 sigma
    within = np.concatenate(ratios)
    one, two = np.mean(within <= 1, axis=0), np.mean(within <= 2, axis=0)
    # at most 0.95: on this ideal camera the refined particles' lateral errors (about
    # 2 um RMS) are no larger than the DLFC's model error (about 2 um), which every
    # sigma includes (measured 0.81 / 0.85 / 0.74 within 1 sigma, 0.98 / 0.97 / 0.93
    # within 2)
    assert np.all((one >= 0.5) & (one <= 0.95)), one
    assert np.all(two >= 0.8), two


def test_raw_and_lightfield_inputs_agree(small):
    optics, calib = small
    scene = make_scene(calib.camera, n_particles=8, seed=11)
    raw = _frame(optics, scene.truth, 11)
    from_raw = locate_frame(raw, calib, frame=3)
    from_lf = locate_frame(decode(raw, calib.grid), calib, frame=3)
    pd.testing.assert_frame_equal(from_raw.particles, from_lf.particles)
    assert list(from_raw.particles.columns) == list(PARTICLE_COLUMNS)
    assert (from_raw.particles["frame"] == 3).all()
    assert len(from_raw.particles) >= 7
    det = from_raw.detections
    assert det["particle"].max() == len(from_raw.particles) - 1
    assert (det.loc[det["inlier"], "particle"] >= 0).all()


def test_locating_without_splitting_regions(small):
    # With neither cores nor pairs split every region is whole; the later stages read
    # the column (it was missing and refinement failed)
    optics, calib = small
    scene = make_scene(calib.camera, n_particles=8, seed=11)
    locator = PerspectiveLocator.from_dict({"segment": {"core_contrast": None,
                                                         "split_pairs": False}})
    raw = _frame(optics, scene.truth, 11)
    regions = segment_frame(decode(raw, calib.grid), locator.segment)
    assert regions["whole"].all() and not regions["split_pair"].any()
    result = locate_frame(raw, calib, locator=locator)
    ev = evaluate_particles(result.particles, scene.truth, tolerance_mm=1.0)
    assert ev.n_matched >= 7 and ev.precision == 1.0, ev


def test_locking_pattern_asked_of_a_calibration_without_one(small):
    optics, calib = small
    assert calib.locking_pattern is None
    locator = PerspectiveLocator.from_dict({"solve": {"locking_from_calibration": True}})
    with pytest.raises(SettingsError, match="no pixel-locking pattern"):
        locate_frame(np.ones(calib.camera.sensor_shape_px), calib, locator=locator)


def test_no_particles_gives_empty_table_and_warning(small):
    optics, calib = small
    empty = make_scene(calib.camera, n_particles=0).truth
    raw = _frame(optics, empty, 0)
    with pytest.warns(NoParticlesWarning):
        result = locate_frame(raw, calib)
    assert len(result.particles) == 0
    assert list(result.particles.columns) == list(PARTICLE_COLUMNS)
    assert result.particles["n_views"].dtype == np.int64
    assert result.particles["flags"].dtype == np.uint8


@pytest.mark.parametrize("settings, match", [
    ({"segment": {"window": 2}}, "window"),
    ({"segment": {"contrast": 1.5}}, "contrast"),
    ({"segment": {"core_contrast": 0.1}}, "core_contrast"),
    ({"solve": {"min_views": 1}}, "min_views"),
    ({"cluster": {"depth_range_mm": (5.0, -5.0)}}, "depth_range_mm"),
])
def test_locator_settings_are_validated(settings, match):
    with pytest.raises(ValueError, match=match):
        PerspectiveLocator.from_dict(settings)


def test_locator_repr_and_settings():
    loc = PerspectiveLocator.from_dict({"segment": {"core_contrast": None},
                                        "grow": {"merge_distance_px": 2.0}})
    assert "merge_distance_px=2.0" in repr(loc)
    assert loc.settings()["segment"]["core_contrast"] is None


def test_split_pairs_places_halves_from_moments():
    # Two discs of radius r with centres c +- a e: second moments r^2/4 + a^2 along e and
    # r^2/4 across it; the halves land on the disc centres.
    from plenoptrack.locate._regions import _split_pairs

    r, a, theta = 4.0, 3.0, 0.4
    single = dict(frame=0, u=0.0, v=0.0, s=10.0, t=10.0, area=50, diameter_px=8.0,
                  major_axis_px=8.2, minor_axis_px=7.9, orientation=0.0, eccentricity=0.2,
                  darkness=1.0, dark_area=48.0)
    pair = dict(single, s=40.0, t=30.0, area=90, diameter_px=10.7, dark_area=88.0,
                major_axis_px=4 * np.sqrt(r ** 2 / 4 + a ** 2), minor_axis_px=2 * r,
                orientation=theta, eccentricity=0.8)
    det = pd.DataFrame([single, single, pair])
    out = _split_pairs(det, 1.3, 1.25)
    assert len(out) == 4 and out["split_pair"].sum() == 2
    halves = out[out["split_pair"]].sort_values("s")
    expected_s = 40.0 + np.array([-a, a]) * np.cos(theta)
    expected_t = 30.0 + np.array([-a, a]) * np.sin(theta)
    np.testing.assert_allclose(halves["s"], expected_s, atol=1e-9)
    np.testing.assert_allclose(halves["t"], expected_t, atol=1e-9)
    np.testing.assert_allclose(halves["major_axis_px"], 2 * r)
    assert (halves["area"] == 45).all()
    np.testing.assert_allclose(halves["dark_area"], 44.0)
    assert not halves["whole"].any()
    # Nothing large and elongated: unchanged apart from the flag column.
    kept = _split_pairs(det.iloc[:2], 1.3, 1.25)
    assert len(kept) == 2 and not kept["split_pair"].any()


def test_stage_times_are_reported(small):
    optics, calib = small
    scene = make_scene(calib.camera, n_particles=5, seed=3)
    result = locate_frame(_frame(optics, scene.truth, 3), calib)
    assert set(result.stage_seconds) == {"decode", "segment", "cluster", "triangulate", "checks",
                                         "refine"}
    assert all(t >= 0 for t in result.stage_seconds.values())


@pytest.mark.slow
def test_hall2019_full_sensor_accuracy():
    camera = preset("hall2019")
    optics, calib = _calibrated("hall2019", depths=np.linspace(-25.0, 25.0, 7))
    scene = make_scene(camera, n_particles=100, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", NoParticlesWarning)
        result = locate_frame(_frame(optics, scene.truth, 0), calib)
    ev = evaluate_particles(result.particles, scene.truth, tolerance_mm=2.0)
    assert ev.recall >= 0.99 and ev.precision >= 0.99, ev
    assert ev.std_error_z <= 0.2 and abs(ev.mean_error_z) <= 0.05, ev
    assert ev.rms_error_lateral <= 0.05, ev
    _assert_sizes(result.particles, scene.truth, rel=0.05)


def _assert_sizes(particles, truth, *, rel):
    """Median measured diameter within ``rel`` of the truth, axes of a round particle."""
    pairs = match_particles(particles, truth, tolerance_mm=1.0)
    measured = particles.loc[pairs["measured_index"]]
    true_d = truth.loc[pairs["truth_index"], "diameter"].to_numpy()
    ratio = measured["diameter"].to_numpy() / true_d
    assert abs(np.median(ratio) - 1) <= rel, np.percentile(ratio, [10, 50, 90])
    assert np.percentile(ratio, 10) >= 1 - 3 * rel, np.percentile(ratio, [10, 50, 90])
    # spheres: the axes bracket the diameter, the minor axis no longer than the major
    assert (measured["minor_axis"] <= measured["major_axis"] + 1e-9).all()
    assert abs(np.median(measured["major_axis"].to_numpy() / true_d) - 1) <= 3 * rel


def test_particle_sizes_from_shadow_areas(small):
    optics, calib = small
    scene = make_scene(calib.camera, n_particles=20, seed=1)
    result = locate_frame(_frame(optics, scene.truth, 1), calib)
    _assert_sizes(result.particles, scene.truth, rel=0.06)


def test_translucent_particles_measured_by_their_body_not_their_shadow(small):
    # particles passing 15 % of the light cast an opaque disc sqrt(0.85) = 0.92 of their
    # diameter; their opacity, from their images' peak darkness against the calibrated
    # edge blur, gives the body's diameter back
    import dataclasses

    optics, calib = small
    scene = make_scene(calib.camera, n_particles=20, seed=4)
    truth = scene.truth.assign(transmission=0.15)
    raw = _frame(optics, truth, 4)
    body = locate_frame(raw, calib)
    _assert_sizes(body.particles, truth, rel=0.04)
    shadow = locate_frame(raw, calib, locator=PerspectiveLocator().updated(
        {"solve": {"opacity": False}}, source="test"))
    no_blur = locate_frame(raw, dataclasses.replace(
        calib, extra={k: v for k, v in calib.extra.items() if k != "edge_blur_by_depth_px"}))
    for plain in (shadow, no_blur):
        pairs = match_particles(plain.particles, truth, tolerance_mm=1.0)
        ratio = (plain.particles.loc[pairs["measured_index"], "diameter"].to_numpy()
                 / truth.loc[pairs["truth_index"], "diameter"].to_numpy())
        assert abs(np.median(ratio) - math.sqrt(0.85)) < 0.03, np.median(ratio)


def test_views_vignetted_in_the_white_image_are_not_searched(small):
    import dataclasses

    optics, calib = small
    scene = make_scene(calib.camera, n_particles=6, seed=21)
    raw = _frame(optics, scene.truth, 21)
    vignetting = np.array(calib.vignetting, copy=True)
    n_u = vignetting.shape[1]
    vignetting[:, : n_u // 2] = 0.0          # as if the aperture hid every u < 0 view
    half = dataclasses.replace(calib, vignetting=vignetting)
    result = locate_frame(raw, half)
    assert (result.detections["u"] >= 0).all()
    full = locate_frame(raw, calib)
    assert (full.detections["u"] < 0).any()
    # fewer views, still the same particles
    ev = evaluate_particles(result.particles, scene.truth, tolerance_mm=1.0)
    assert ev.recall >= 0.8 and ev.precision >= 0.8


def test_member_diameter_of_regions_and_of_their_shadows():
    """A particle's diameter is the median over its whole regions (all of them when it
    has fewer than three whole ones); its shadow's, the median of ``sqrt(4 dark_area /
    pi)``, smaller than the thresholded regions by their blurred edge."""
    import math

    from plenoptrack.locate.frame import _member_diameter

    detections = pd.DataFrame({
        "diameter_px": [4.0, 5.0, 6.0, 9.0, 3.0, 3.5, 9.0],
        "dark_area": [4.0, 9.0, 16.0, 50.0, 2.0, 3.0, 1.0],
        "whole": [True, True, True, False, True, False, True]})
    owner = np.array([0, 0, 0, 0, 1, 1, -1])
    assert _member_diameter(detections, owner, 3)[:2].tolist() == [5.0, 3.25]
    assert np.isnan(_member_diameter(detections, owner, 3)[2])
    shadow = _member_diameter(detections, owner, 3, shadow=True)
    assert shadow[0] == pytest.approx(math.sqrt(4.0 * 9.0 / math.pi))
    assert shadow[1] == pytest.approx(np.median(np.sqrt(4.0 * np.array([2.0, 3.0]) / math.pi)))


@pytest.mark.parametrize("seed", [1, 2])
def test_the_larger_of_two_particles_keeps_all_its_views(small, seed):
    """A frame of a 0.6 mm and a 0.95 mm particle: the larger one's images are more than
    ``segment.max_area_ratio`` times the frame's typical image and are held back as
    merged. The clustering finds it on the few views whose images are smaller; the held
    images on its prediction, of the size of its own, then join it, so that it is seen
    in as many views as the smaller one and not dropped for a narrow aperture."""
    optics, calib = small
    truth = pd.DataFrame({"frame": 0, "particle": [0, 1], "x": [-2.602, -1.239],
                          "y": [0.147, 0.523], "z": [-2.008, -0.126],
                          "diameter": [0.596, 0.951], "orientation": 0.0})
    truth["projected_area"] = np.pi * truth["diameter"] ** 2 / 4
    found = locate_frame(_frame(optics, truth, seed), calib).particles
    pairs = match_particles(found, truth, tolerance_mm=0.5)
    assert len(found) == 2 and len(pairs) == 2
    m = found.loc[pairs["measured_index"]].reset_index(drop=True)
    large = pairs["truth_index"].to_numpy() == 1
    assert m.loc[large, "n_views"].iloc[0] >= 0.9 * m.loc[~large, "n_views"].iloc[0]
    assert abs(m.loc[large, "z"].iloc[0] - truth["z"].iloc[1]) < 0.1
