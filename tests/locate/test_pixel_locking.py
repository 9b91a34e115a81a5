"""Pixel-locking correction (plenoptrack.locate.pixel_locking): lattice phases, the
pattern fit, and the pattern the locator learns against one measured from the truth."""

import warnings

import numpy as np
import pytest

from plenoptrack.lightfield import decode
from plenoptrack.locate import perspective
from plenoptrack.locate.pixel_locking import (LockingPattern, fit_locking_pattern,
                                              fourier_terms, lattice_phase)
from plenoptrack.locate.settings import PerspectiveLocator
from plenoptrack.simulate import make_scene, render_frame


def _wrapped(phase):
    """Distance of each phase from the nearest whole number."""
    return np.abs(phase - np.round(phase))


@pytest.fixture(scope="module")
def grid_and_field(small_calibrated):
    _, calib = small_calibrated
    grid = calib.grid
    lf = decode(np.full(grid.sensor_shape_px, 1000.0, dtype=np.float32), grid)
    return grid, lf


def test_lens_centres_are_phase_zero_and_midpoints_half(grid_and_field):
    grid, lf = grid_and_field
    i, j = np.meshgrid(np.arange(10, 16), np.arange(20, 27), indexing="ij")
    centres = grid.centers_of(i.ravel(), j.ravel())
    st = lf.from_sensor(centres)
    np.testing.assert_array_less(_wrapped(lattice_phase(grid, st)), 1e-6)
    # half-way along a row: half a cell along the rows, none across
    along = 0.5 * (centres + grid.centers_of(i.ravel(), j.ravel() + 1))
    phase = lattice_phase(grid, lf.from_sensor(along))
    np.testing.assert_allclose(phase[:, 1], 0.5, atol=1e-6)
    np.testing.assert_array_less(_wrapped(phase[:, 0]), 1e-6)
    # half-way to the next row's nearest lens: half a cell across the rows
    below = grid.centers_of(i.ravel() + 1, j.ravel())
    phase = lattice_phase(grid, lf.from_sensor(0.5 * (centres + below)))
    np.testing.assert_allclose(phase[:, 0], 0.5, atol=1e-6)


def test_fit_recovers_a_known_pattern_through_noise_and_outliers():
    rng = np.random.default_rng(4)
    m = 20000
    phase = rng.random((m, 2))
    travel = rng.uniform(2.0, 9.0, m)
    terms = fourier_terms(phase, 1)
    c = rng.normal(0.0, 0.02, (2, terms.shape[1]))
    d = -0.1 * c                                           # weaker for blurred images
    truth = np.column_stack([terms @ c[k] + travel * (terms @ d[k]) for k in range(2)])
    residual = truth + 0.08 * rng.standard_normal((m, 2)) + 0.01     # noise and an offset
    wild = rng.random(m) < 0.05
    residual[wild] += rng.normal(0.0, 2.0, (wild.sum(), 2))          # wrong members
    pattern = fit_locking_pattern(residual, phase, travel)
    assert pattern is not None and pattern.travel_range[0] >= 2.0
    assert pattern.n_residuals >= 0.9 * m
    # the bias near focus is extrapolated only to the least fitted travel
    probe = rng.random((500, 2))
    at_two = np.column_stack([fourier_terms(probe, 1) @ (c[k] + 2.0 * d[k]) for k in range(2)])
    err = pattern.bias(probe, 0.0) - at_two
    assert np.sqrt(np.mean(err ** 2)) < 0.2 * np.sqrt(np.mean(at_two ** 2))
    # the offset is not a locking effect and is not corrected
    assert abs(float(np.mean(pattern.bias(probe, 5.0)))) < 0.003


def test_too_few_residuals_give_no_pattern():
    rng = np.random.default_rng(5)
    phase, travel = rng.random((300, 2)), rng.uniform(2, 9, 300)
    assert fit_locking_pattern(rng.normal(0, 0.05, (300, 2)), phase, travel) is None


def _checked_frame(small_calibrated, clustered_and_solved, n_particles, seed):
    """Calibration, scene, frame context and particle state of one rendered frame of
    0.4 mm spheres, located up to the consistency checks (where the correction runs)."""
    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=n_particles, seed=seed, diameter_mm=0.4)
    raw = render_frame(optics, scene.truth, seed=np.random.default_rng([seed, 3, 0]))
    locator = PerspectiveLocator()
    ctx, state = clustered_and_solved(raw, calib, locator)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        state = perspective.check_particles(ctx, state, locator)
    return calib, scene, ctx, state


def test_locator_learns_the_pattern_the_truth_shows(small_calibrated, clustered_and_solved):
    """One frame of 40 isolated 0.4 mm particles (ideal optics): the pattern learned from
    the centroids' scatter about the located particles against the same fit to their
    scatter about the predictions of the true positions (an independent reference):
    the two agree at the phases of a 20 x 20 grid (correlation above 0.8, RMS within a
    factor 1.5)."""
    calib, scene, ctx, state = _checked_frame(small_calibrated, clustered_and_solved, 40, 41)
    locator = PerspectiveLocator()
    learned, travel = perspective.learn_pixel_locking(ctx, state, locator.solve, calib.grid)
    assert learned is not None
    # reference: each kept centroid against the true particle nearest its particle
    pos = state.positions
    true_xyz = scene.truth[["x", "y", "z"]].to_numpy()
    nearest = np.argmin(np.linalg.norm(pos[:, None] - true_xyz[None], axis=2), axis=1)
    rows = np.flatnonzero(state.owner >= 0)
    owner = state.owner[rows]
    usable = travel[owner] >= locator.solve.locking_min_travel_px
    rows, owner = rows[usable], owner[usable]
    pred = perspective._predict_all(ctx.dlfc, true_xyz, ctx.views)[nearest[owner],
                                                                   ctx.view[rows]]
    reference = fit_locking_pattern(ctx.st[rows] - pred,
                                    lattice_phase(calib.grid, pred), travel[owner])
    assert reference is not None and np.all(reference.rms_px > 0.01)   # a real effect
    a, b = np.meshgrid(np.linspace(0, 1, 20, endpoint=False),
                       np.linspace(0, 1, 20, endpoint=False))
    probe = np.column_stack([a.ravel(), b.ravel()])
    mid = 0.5 * sum(reference.travel_range)
    got, want = learned.bias(probe, mid), reference.bias(probe, mid)
    for k in range(2):
        assert np.corrcoef(got[:, k], want[:, k])[0, 1] > 0.8
        ratio = np.sqrt(np.mean(got[:, k] ** 2) / np.mean(want[:, k] ** 2))
        assert 1 / 1.5 < ratio < 1.5


def test_a_frame_without_its_own_pattern_uses_the_calibrations(small_calibrated,
                                                                 clustered_and_solved,
                                                                 monkeypatch):
    """With ``solve.locking_from_calibration``, every centroid moves by the calibration's
    pattern at its phase and its particle's travel when the frame shows none; without it,
    or without a calibration pattern, nothing moves."""
    calib, scene, ctx, state = _checked_frame(small_calibrated, clustered_and_solved, 4, 43)
    locator = PerspectiveLocator()
    own, travel = perspective.learn_pixel_locking(ctx, state, locator.solve, calib.grid)
    assert own is None                                       # four particles are too few
    rng = np.random.default_rng(6)
    coef = np.stack([rng.normal(0, 0.03, (2, 8)), rng.normal(0, 0.003, (2, 8))], axis=1)
    pattern = LockingPattern(coef=coef, harmonics=1, travel_range=(0.0, 9.0),
                             n_residuals=1000, rms_px=np.full(2, 0.03))
    with_pattern = calib.with_locking_pattern(pattern)
    # off by default: nothing moves
    same_ctx, same_state = perspective.correct_pixel_locking(ctx, state, locator, with_pattern)
    assert same_ctx is ctx and same_state is state
    locator = locator.updated({"solve": {"locking_from_calibration": True}}, source="test")
    new_ctx, new_state = perspective.correct_pixel_locking(ctx, state, locator, with_pattern)
    owner = state.owner
    own_travel = np.where(owner >= 0, travel[np.maximum(owner, 0)], np.nan)
    expected = ctx.st - pattern.bias(lattice_phase(calib.grid, ctx.st), own_travel)
    np.testing.assert_allclose(new_ctx.st, expected, atol=1e-12)
    np.testing.assert_allclose(new_ctx.detections[["s", "t"]].to_numpy(), expected,
                               atol=1e-12)
    assert not np.array_equal(new_state.positions, state.positions)
    same_ctx, same_state = perspective.correct_pixel_locking(ctx, state, locator, calib)
    assert same_ctx is ctx and same_state is state


def test_a_measured_pattern_applies_to_images_of_about_its_size():
    pattern = LockingPattern(coef=np.zeros((2, 2, 8)), harmonics=1, travel_range=(0.0, 9.0),
                             n_residuals=1000, rms_px=np.zeros(2), image_diameter_px=4.0)
    diameters = np.array([1.5, 2.1, 4.0, 7.9, 9.0])
    np.testing.assert_array_equal(pattern.applies_to(np.pi * diameters ** 2 / 4),
                                  [False, True, True, True, False])
    unknown = LockingPattern.from_dict({k: v for k, v in pattern.to_dict().items()
                                        if k != "image_diameter_px"})
    assert unknown.applies_to(np.array([0.1, 1e4])).all()
    assert LockingPattern.from_dict(pattern.to_dict()).image_diameter_px == 4.0


def test_locking_settings_are_checked():
    from plenoptrack.errors import SettingsError

    for bad in ({"locking_harmonics": 0}, {"locking_harmonics": 5},
                {"locking_harmonics": 1.5}, {"locking_min_travel_px": -1.0},
                {"locking_correction": "yes"}):
        with pytest.raises(SettingsError):
            PerspectiveLocator.from_dict({"solve": bad})
