"""Particles hidden by others: the residual light field and the second search
(check.find_hidden)."""

import dataclasses
import math

import numpy as np
import pandas as pd
import pytest

from plenoptrack.evaluate import match_particles
from plenoptrack.lightfield import LightField
from plenoptrack.locate import hidden, perspective, split
from plenoptrack.locate.perspective import ParticleState, PerspectiveLocator, locate_frame
from plenoptrack.locate.refine import ImageEdge, disc_image
from plenoptrack.locate.triangulate import TriangulationFlag
from plenoptrack.locate.residual import (divide_out_particles, residual_light_field,
                                         transmission_model)
from plenoptrack.simulate import make_scene, render_frame


def test_transmission_is_the_product_of_the_image_model_discs():
    """Two overlapping discs in two views, against refine.disc_image evaluated
    independently on the pixel grid."""
    pred = np.array([[[10.2, 8.7], [11.0, 9.0]],      # particle 0 in views 0 and 1
                     [[13.1, 9.4], [np.nan, np.nan]]])  # particle 1 only in view 0
    radius, contrast = np.array([3.0, 2.2]), np.array([0.95, 0.6])
    t = transmission_model(20, 25, pred, radius, contrast)
    assert t.shape == (2, 20, 25) and t.dtype == np.float32
    tt, ss = np.mgrid[0:20, 0:25].astype(float)
    for v in range(2):
        expected = np.ones((20, 25))
        for p in range(2):
            s, c = pred[p, v], contrast[p]
            if np.isfinite(s).all():
                expected *= disc_image(np.hypot(ss - s[0], tt - s[1]), radius[p], c)[0]
        # the model leaves out erfc's last 6e-5 beyond 4 edge widths of each rim
        np.testing.assert_allclose(t[v], expected, atol=1e-4)


def test_transmission_with_an_edge_width_per_particle_and_direction():
    """Each image with its own edge widths along s and t, against the blurred disc of
    the pixel's direction evaluated independently in plain numpy."""
    from test_refine import anisotropic_disc

    pred = np.array([[[10.2, 8.7]], [[13.1, 9.4]]])
    radius, contrast = np.array([3.0, 2.2]), np.array([0.95, 0.6])
    widths = np.array([[0.8, 0.4], [0.45, 0.7]])
    t = transmission_model(20, 25, pred, radius, contrast, edge=widths)
    tt, ss = np.mgrid[0:20, 0:25].astype(float)
    expected = np.ones((20, 25))
    for p in range(2):
        expected *= anisotropic_disc(ss - pred[p, 0, 0], tt - pred[p, 0, 1], radius[p],
                                     contrast[p], *widths[p])
    np.testing.assert_allclose(t[0], expected, atol=1e-4)
    # not the round model: the widths reach the kernel
    assert np.abs(t[0] - transmission_model(20, 25, pred, radius, contrast)[0]).max() > 0.02
    with pytest.raises(ValueError, match="edge"):
        transmission_model(20, 25, pred, radius, contrast, edge=widths[:1])


def test_transmission_of_elliptical_images():
    """An ellipse is the disc of its long semi-axis in coordinates turned onto its axes
    and stretched across them (edge widths with them), against that construction in
    plain numpy; its opaque core and the free background are where the ellipse says;
    turned by a right angle it is the transposed image; semi-axes equal: the disc."""
    from test_refine import anisotropic_disc

    pred = np.array([[[15.3, 14.6]]])
    a, b, angle, c, w = 9.0, 3.0, 0.6, 0.9, 0.7
    t = transmission_model(30, 30, pred, np.array([a]), np.array([c]), edge=w,
                           axes=np.array([[a, b, angle]]))
    tt, ss = np.mgrid[0:30, 0:30].astype(float)
    ds, dt = ss - pred[0, 0, 0], tt - pred[0, 0, 1]
    along = math.cos(angle) * ds + math.sin(angle) * dt
    across = math.cos(angle) * dt - math.sin(angle) * ds
    expected = anisotropic_disc(along, across * a / b, a, c, w, w * a / b)
    np.testing.assert_allclose(t[0], expected, atol=1e-4)
    inside = (along / a) ** 2 + (across / b) ** 2
    assert np.allclose(t[0][inside < 0.25], 1 - c, atol=0.02)
    assert np.allclose(t[0][inside > 4.0], 1.0, atol=1e-3)
    assert (t[0] < 0.5).sum() == pytest.approx(math.pi * a * b, rel=0.1)
    square = np.array([[[15.0, 15.0]]])
    flat = transmission_model(31, 31, square, np.array([a]), np.array([c]),
                              axes=np.array([[a, b, 0.0]]))
    upright = transmission_model(31, 31, square, np.array([a]), np.array([c]),
                                 axes=np.array([[a, b, math.pi / 2]]))
    np.testing.assert_allclose(upright[0], flat[0].T, atol=1e-5)
    np.testing.assert_array_equal(
        transmission_model(31, 31, square, np.array([a]), np.array([c]),
                           axes=np.array([[a, a, 0.0]])),
        transmission_model(31, 31, square, np.array([a]), np.array([c])))
    with pytest.raises(ValueError, match="axes"):
        transmission_model(31, 31, square, np.array([a]), np.array([c]),
                           axes=np.array([a, b, 0.0]))


def _lightfield(data):
    n_v, n_u, n_t, n_s = data.shape
    return LightField(data=data, u=np.arange(n_u) - n_u // 2.0, v=np.arange(n_v) - n_v // 2.0,
                      valid_fraction=np.ones((n_v, n_u)), spatial_mask=np.ones((n_t, n_s), bool),
                      origin_px=(0.0, 0.0), s_step_px=(0.0, 1.0), t_step_px=(1.0, 0.0),
                      sensor_shape_px=(n_t, n_s))


def test_dividing_out_a_modelled_image_leaves_the_background_and_the_input_untouched():
    rng = np.random.default_rng(0)
    background = 0.8
    pred = np.array([[[12.0, 10.0]]])
    t = transmission_model(24, 30, pred, np.array([4.0]), np.array([1.0]))
    hidden = transmission_model(24, 30, np.array([[[18.5, 10.0]]]), np.array([2.0]),
                                np.array([1.0]))
    noise = 1 + 0.01 * rng.standard_normal((24, 30))
    data = (background * t[0] * hidden[0] * noise).astype(np.float32)[None, None]
    lf = _lightfield(data.copy())
    out = residual_light_field(lf, np.array([[0, 0]]), t, floor=0.5)
    np.testing.assert_array_equal(lf.data, data)             # the input is not changed
    res = out.data[0, 0]
    blocked = t[0] < 0.5
    assert blocked.any()
    # the located image is gone: its blocked core reads the background, its rim as well
    # (up to the noise it amplifies by at most 1 / floor)
    sample = data[0, 0, ::3, ::3]
    np.testing.assert_allclose(res[blocked], np.median(sample[sample > 0]), rtol=1e-6)
    rim = ~blocked & (t[0] < 0.99) & (hidden[0] > 0.99)
    assert np.all(np.abs(res[rim] / background - 1) < 0.1)
    # the hidden particle's shadow is left where the located image does not cover it
    free = (hidden[0] < 0.05) & (t[0] > 0.99)
    assert free.any() and np.all(res[free] < 0.1 * background)


def test_dividing_out_in_one_pass_equals_the_transmission_then_the_division():
    """Many overlapping discs (opaque and faint, some blocked below the floor, some views
    without an image of a particle), NaN and zero pixels, a view with no valid pixel and
    a view left unmodelled: value for value what the two-step form gives."""
    rng = np.random.default_rng(4)
    n_v, n_u, n_t, n_s, n_p = 3, 3, 40, 50, 30
    data = (0.8 + 0.05 * rng.standard_normal((n_v, n_u, n_t, n_s))).astype(np.float32)
    data[0, 1, 5:9, 7:30] = np.nan
    data[1, 1, 20:25, :] = 0.0
    data[2, 2] = 0.0                                    # no valid pixel: left as it is
    view_rc = np.array([[0, 0], [0, 1], [1, 1], [2, 2], [1, 2]])   # (0, 2) etc. unmodelled
    pred = np.c_[rng.uniform(-5, n_s + 5, (n_p * len(view_rc), 1)),
                 rng.uniform(-5, n_t + 5, (n_p * len(view_rc), 1))].reshape(n_p, len(view_rc), 2)
    pred[rng.random((n_p, len(view_rc))) < 0.2] = np.nan
    radius = rng.uniform(0.5, 6.0, n_p)
    radius[3] = 0.0
    contrast = rng.uniform(0.2, 1.0, n_p)
    contrast[5] = 0.0
    lf = _lightfield(data.copy())
    widths = rng.uniform(0.3, 0.9, (n_p, 2))
    for floor, edge in ((0.5, 0.6), (0.2, 0.6), (0.5, widths)):
        expected = residual_light_field(
            lf, view_rc, transmission_model(n_t, n_s, pred, radius, contrast, edge=edge),
            floor=floor)
        got = divide_out_particles(lf, view_rc, pred, radius, contrast, floor=floor,
                                   edge=edge)
        np.testing.assert_array_equal(got.data, expected.data)
        assert not np.array_equal(got.data, data)        # something was divided out
    # elliptical images too
    axes = np.c_[radius, radius * rng.uniform(0.2, 1.0, n_p), rng.uniform(-3, 3, n_p)]
    expected = residual_light_field(
        lf, view_rc, transmission_model(n_t, n_s, pred, radius, contrast, axes=axes))
    got = divide_out_particles(lf, view_rc, pred, radius, contrast, axes=axes)
    np.testing.assert_array_equal(got.data, expected.data)
    assert not np.array_equal(got.data, divide_out_particles(lf, view_rc, pred, radius,
                                                              contrast).data)
    np.testing.assert_array_equal(lf.data, data)             # the input is not changed
    # written into a given array: the same residual, in that array
    out = np.full_like(data, 7.0)
    into = divide_out_particles(lf, view_rc, pred, radius, contrast, axes=axes, out=out)
    assert into.data is out
    np.testing.assert_array_equal(out, got.data)
    np.testing.assert_array_equal(lf.data, data)
    for wrong in (out[:2], out.astype(np.float64), lf.data):
        with pytest.raises(ValueError, match="out must be a separate array"):
            divide_out_particles(lf, view_rc, pred, radius, contrast, out=wrong)
    np.testing.assert_array_equal(lf.data, data)


@pytest.fixture(scope="module")
def mixed_scenes(small_calibrated):
    """Random frames of 60 particles of 0.2-1 mm (log-uniform) on the small camera:
    small particles often stand behind large ones."""
    optics, calib = small_calibrated
    out = []
    for seed in (11, 12):
        scene = make_scene(calib.camera, n_particles=60, seed=seed, diameter_mm=(0.2, 1.0))
        raw = render_frame(optics, scene.truth, seed=np.random.default_rng([seed, 3, 0]))
        out.append((scene.truth, raw))
    return calib, out


def test_the_second_search_finds_hidden_particles(mixed_scenes):
    """Each frame: more true particles found, each new one a true particle (matched, and
    no more unmatched particles than without the search beyond one per frame); at least
    9 more over both frames. (Frame 12 gained 3 until the merged-image check judged
    particles weakest first: the first search now finds 2 of them, and both searches
    together the same 41.)"""
    calib, scenes = mixed_scenes
    on = PerspectiveLocator.from_dict({"check": {"find_hidden": True}})
    off = PerspectiveLocator.from_dict({"check": {"find_hidden": False}})
    gained = 0
    for truth, raw in scenes:
        counts = {}
        for name, locator in (("off", off), ("on", on)):
            found = locate_frame(raw, calib, locator=locator).particles
            matched = len(match_particles(found, truth, tolerance_mm=1.0))
            counts[name] = (matched, len(found) - matched)
        assert counts["on"][0] >= counts["off"][0] + 1
        assert counts["on"][1] <= counts["off"][1] + 1
        gained += counts["on"][0] - counts["off"][0]
    assert gained >= 9


def test_further_rounds_find_particles_the_first_left_hidden(mixed_scenes):
    """Frame 11: the particles found in the first search, divided out with the located
    ones, uncover two more true particles (47 matched against 45 with one round), at
    the cost of at most one unmatched particle more."""
    calib, scenes = mixed_scenes
    truth, raw = scenes[0]
    counts = {}
    for rounds in (1, 4):
        locator = PerspectiveLocator.from_dict({"check": {"hidden_rounds": rounds}})
        found = locate_frame(raw, calib, locator=locator).particles
        matched = len(match_particles(found, truth, tolerance_mm=1.0))
        counts[rounds] = (matched, len(found) - matched)
    assert counts[4][0] >= counts[1][0] + 2
    assert counts[4][1] <= counts[1][1] + 1


def test_candidates_turned_down_where_nothing_changed_are_not_fitted_again(
        mixed_scenes, monkeypatch):
    """A candidate an earlier round fitted and turned down, found again where nothing has
    changed, is not fitted again: on both frames the same true particles are matched as
    when every candidate of every round is fitted, with no more unmatched ones, and
    fewer candidates are fitted."""
    calib, scenes = mixed_scenes
    fitted = []
    admit, joint = hidden._ResidualSearch.admit, hidden._ResidualSearch.fit_jointly

    def counting(method):
        def wrapper(self, q):
            fitted[-1] += 1
            return method(self, q)
        return wrapper

    monkeypatch.setattr(hidden._ResidualSearch, "admit", counting(admit))
    monkeypatch.setattr(hidden._ResidualSearch, "fit_jointly", counting(joint))
    skipped = 0
    for truth, raw in scenes:
        counts = {}
        for name in ("skipping", "every candidate"):
            fitted.append(0)
            with monkeypatch.context() as patch:
                if name == "every candidate":
                    patch.setattr(hidden._ResidualSearch, "turned_down_before",
                                  lambda self, rows: np.zeros(len(rows), dtype=bool))
                found = locate_frame(raw, calib).particles
            pairs = match_particles(found, truth, tolerance_mm=1.0)
            counts[name] = (sorted(pairs["truth_index"]), len(found) - len(pairs))
        assert counts["skipping"][0] == counts["every candidate"][0]
        assert counts["skipping"][1] <= counts["every candidate"][1]
        skipped += fitted[-1] - fitted[-2]
    assert skipped > 0


def _linear_predict(dlfc, xyz, views_uv):
    """Image centres of a stand-in camera: 10 px per mm, 0.25 px of parallax per mm of
    depth per unit of view coordinate."""
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    return 10.0 * xyz[:, None, :2] + 0.25 * xyz[:, None, 2:] * views_uv[None]


_VIEWS = np.array([[u, v] for u in (-2.0, 0.0, 2.0) for v in (-2.0, 0.0, 2.0)])


def test_a_candidate_turned_down_before_is_one_whose_images_coincide(monkeypatch):
    """Images within the grow tolerance (1 px, median over the views) of a turned-down
    candidate's: 0.2 px beside it, or 1 mm deeper (0.5-0.7 px off the central view) are
    the same candidate; 3 mm deeper (1.5-2.1 px) is another."""
    monkeypatch.setattr(hidden, "_predict_all", _linear_predict)
    search = object.__new__(hidden._ResidualSearch)
    search.ctx = type("Ctx", (), {"dlfc": None, "tolerance_px": 1.0})()
    search.views_uv = _VIEWS
    candidates = np.array([[0.0, 0.0, 1.0], [0.02, 0.0, 1.0], [0.0, 0.0, 2.0],
                           [0.0, 0.0, 4.0], [5.0, 5.0, 0.0], [5.0, 5.0, 4.1]])
    search.pred2 = _linear_predict(None, candidates, _VIEWS)
    search.earlier = hidden.EarlierRounds()
    rows = np.arange(len(candidates))
    assert not search.turned_down_before(rows).any()           # nothing turned down yet
    search.earlier.add([[0.0, 0.0, 1.0], [5.0, 5.0, 0.0]], [2.0, 2.0])
    np.testing.assert_array_equal(search.turned_down_before(rows),
                                  [True, True, True, False, True, False])
    np.testing.assert_array_equal(search.turned_down_before(rows[3:]), [False, True, False])
    assert not search.turned_down_before(np.array([], dtype=np.int64)).any()


def test_turned_down_candidates_near_a_changed_particle_are_forgotten(monkeypatch):
    """A changed particle's image closer than the two radii and 4 px to a turned-down
    candidate's in some view makes it a candidate to fit again; one at that distance
    does not."""
    monkeypatch.setattr(hidden, "_predict_all", _linear_predict)
    earlier = hidden.EarlierRounds()
    earlier.add([[0.0, 0.0, 1.0], [5.0, 5.0, 0.0], [-5.0, 0.0, 0.0]], [2.0, 2.0, 1.0])
    earlier.forget_near(None, _VIEWS, np.zeros((0, 3)), np.zeros(0))
    assert len(earlier.xyz) == 3
    # beside the first in every view: 6.7 px (= 2 + 0.7 + 4) is too far, 6.5 px is not
    earlier.forget_near(None, _VIEWS, np.array([[0.67, 0.0, 1.0]]), np.array([0.7]))
    assert len(earlier.xyz) == 3
    earlier.forget_near(None, _VIEWS, np.array([[0.65, 0.0, 1.0]]), np.array([0.7]))
    np.testing.assert_array_equal(earlier.xyz, [[5.0, 5.0, 0.0], [-5.0, 0.0, 0.0]])
    np.testing.assert_array_equal(earlier.radius, [2.0, 1.0])


def test_a_rounds_changes_are_its_particles_where_found_and_where_refitted():
    """``near`` rows and every other row whose position, image fit or regions changed,
    where the round found them and after their refit, with the particles the refit's
    split added; radius from the image fit, else half the regions' diameter; particles
    without a position (dropped) or a radius left out."""
    detections = pd.DataFrame({"diameter_px": [6.0] * 4, "whole": [True] * 4,
                               "dark_area": [20.0] * 4})
    ctx = type("Ctx", (), {"detections": detections})()

    def state(positions, radius, owner=(1, 1, 1, -1)):
        n = len(positions)
        return ParticleState(owner=np.array(owner), initial=np.zeros((n, 3)),
                             positions=np.array(positions, dtype=float),
                             table=pd.DataFrame({"n_views": np.full(n, 20),
                                                 hidden._FIT_RADIUS: radius}))

    nan = math.nan
    found = state([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3], [4, 4, 4], [6, 6, 6]],
                  [2.0, nan, 3.0, 4.0, 2.5, 2.5])
    after = state([[0, 0, 0], [1.5, 1, 1], [2, 2, 2], [nan] * 3, [4, 4, 4], [6, 6, 6],
                   [5, 5, 5]],
                  [2.0, nan, 3.5, 4.0, 2.5, 2.5, 5.0], owner=(1, 1, 1, 5))
    xyz, radius = perspective._changed_images(ctx, found, after,
                                              np.array([False, True, False, True, False,
                                                        False]))
    # rows 1 and 3 near; row 2's image fit and row 5's regions changed; rows 0, 4 kept
    np.testing.assert_array_equal(xyz, [[1, 1, 1], [2, 2, 2], [3, 3, 3], [6, 6, 6],
                                        [1.5, 1, 1], [2, 2, 2], [6, 6, 6], [5, 5, 5]])
    np.testing.assert_array_equal(radius, [3.0, 3.0, 4.0, 2.5, 3.0, 3.5, 2.5, 5.0])


def _pin_pieces(found: pd.DataFrame, field: pd.DataFrame) -> tuple[int, np.ndarray]:
    """Heads matched within 0.3 mm, and the particles (not heads) within 0.3 mm of each
    stem's axis, of pins from :func:`~plenoptrack.study.study_field`."""
    heads, stems = field[field["shape"] == "sphere"], field[field["shape"] != "sphere"]
    xyz = found[["x", "y", "z"]].to_numpy()
    d_head = np.linalg.norm(xyz[:, None] - heads[["x", "y", "z"]].to_numpy()[None], axis=2)
    rel = xyz[:, None] - stems[["x", "y", "z"]].to_numpy()[None]
    axis = stems[["axis_x", "axis_y", "axis_z"]].to_numpy()[None]
    half_length = 2.0 * heads["diameter"].iloc[0]             # the stems' long semi-axis
    along = np.clip((rel * axis).sum(axis=2), -half_length, half_length)
    d_stem = np.linalg.norm(rel - along[..., None] * axis, axis=2)
    on_stem = (d_head.min(axis=1) >= 0.3) & (d_stem.min(axis=1) < 0.3)
    pieces = np.bincount(d_stem.argmin(axis=1)[on_stem], minlength=len(stems))
    return int((d_head.min(axis=0) < 0.3).sum()), pieces


@pytest.fixture(scope="module")
def pin_frames(small_calibrated):
    """Frames of 12 pins (0.4 mm heads, stems of aspect 13 behind them) on the `small`
    camera, seeds 1 and 2: ``[(field, raw), ...]``."""
    from plenoptrack.study import StudyConfig, study_field

    optics, calib = small_calibrated
    frames = []
    for seed in (1, 2):
        cfg = StudyConfig(calib.camera, travel_mm=0.1, step_mm=0.1, n_particles=12,
                          seed=seed, field_depth_mm=4.0)
        field = study_field(cfg)[0].assign(frame=0)
        frames.append((field, render_frame(optics, field, seed=np.random.default_rng([seed, 3]))))
    return frames


def test_an_elongated_particles_regions_are_divided_out_with_it(small_calibrated, pin_frames,
                                                                monkeypatch):
    """Pins, the search dividing out elongated particles with their regions' ellipse
    (``elongated``, as the locator does) or with their disc only: the stems' ends left
    beyond the disc are found as particles of their own less often. Seeds 1 and 2: 11
    and 11 particles on stems against 17 and 14, no stem in more pieces than the most
    without (3 against 3, 2 against 3; the stem in three pieces with the ellipses is in
    two without them), the same heads matched (10 and 11 of 12 within 0.3 mm)."""
    _, calib = small_calibrated
    search = perspective.find_hidden_particles
    for field, raw in pin_frames:
        counts = {}
        for elongated in (True, False):
            monkeypatch.setattr(perspective, "find_hidden_particles",
                                lambda *args, force=elongated, **kwargs:
                                search(*args, **{**kwargs, "elongated": force}))
            counts[elongated] = _pin_pieces(locate_frame(raw, calib).particles, field)
        (heads, pieces), (heads_without, pieces_without) = counts[True], counts[False]
        assert heads >= heads_without
        assert pieces.sum() < pieces_without.sum() and pieces.max() <= pieces_without.max()
        assert pieces_without.max() >= 3                   # the case is one to test


def test_a_head_measured_with_its_stem_is_fitted_on_the_head(small_calibrated, pin_frames,
                                                             monkeypatch):
    """A pin head whose image merges with its stem's into one elongated region: its disc
    fitted from the region's ends as well as its centre (``split._end_starts``) lies on
    the head. Seeds 1 and 2: 10 and 11 of 12 heads within 0.3 mm, against 5 and 6 from
    the centre alone."""
    from plenoptrack.locate import split

    _, calib = small_calibrated
    for field, raw in pin_frames:
        heads = _pin_pieces(locate_frame(raw, calib).particles, field)[0]
        with monkeypatch.context() as patch:
            patch.setattr(split, "_end_starts", lambda *args: None)
            centred = _pin_pieces(locate_frame(raw, calib).particles, field)[0]
        assert heads >= centred + 3 and heads >= 9


class _Rounds:
    """Stand-ins for the stages :func:`search_hidden_rounds` calls: round ``i`` of
    ``script`` finds ``found`` particles of which the refit drops ``dropped``; ``earlier``
    records the memory of earlier rounds each round was given, ``forgotten`` the
    particles the rounds changed."""

    def __init__(self, script):
        self.script = list(script)
        self.calls = 0
        self.earlier, self.forgotten = [], []

    def state(self, n):
        table = pd.DataFrame({"n_views": np.full(n, 20)})
        return ParticleState(owner=np.zeros(0, dtype=np.int64), initial=np.zeros((n, 3)),
                             positions=np.zeros((n, 3)), table=table)

    def find(self, ctx, state, locator, calibration, *, frame=0, elongated=True,
             earlier=None):
        found, self.dropped = self.script[self.calls]
        self.earlier.append(earlier)
        self.calls += 1
        grown = dataclasses.replace(
            state, positions=np.zeros((state.n_particles + found, 3)),
            initial=np.zeros((state.n_particles + found, 3)),
            table=pd.concat([state.table, self.state(found).table], ignore_index=True))
        return ctx, grown, found

    def drop(self, ctx, state, first, n, locator):
        table = state.table.copy()
        table.loc[first + np.arange(self.dropped), "n_views"] = 0
        return dataclasses.replace(state, table=table)


@pytest.mark.parametrize("script, rounds, calls, kept, went_on", [
    ([(2, 0), (0, 0), (5, 0)], 4, 2, 2, 1),          # a round that finds nothing ends them
    ([(2, 0), (1, 1), (5, 0)], 4, 2, 2, 1),          # so does one whose finds are all dropped
    ([(2, 1), (3, 0), (1, 0), (4, 0)], 3, 3, 5, 3),  # at most hidden_rounds
    ([(3, 0)], 1, 1, 3, 1),
])
def test_hidden_rounds_stop_when_a_round_keeps_nothing_more(monkeypatch, script, rounds,
                                                             calls, kept, went_on):
    fake = _Rounds(script)
    monkeypatch.setattr(perspective, "find_hidden_particles", fake.find)
    monkeypatch.setattr(perspective, "_drop_unexplained_hidden", fake.drop)
    monkeypatch.setattr(perspective, "_near_particles", lambda ctx, state, rows: None)
    monkeypatch.setattr(perspective, "refine_particles", lambda ctx, state, *a, **k: state)
    monkeypatch.setattr(perspective, "split_merged_particles",
                        lambda ctx, state, *a, **k: state)
    # every round is given the same memory of the earlier ones, which forgets the
    # candidates near what each round that goes on changed
    monkeypatch.setattr(perspective, "_fit_views", lambda ctx: ("views", None))
    monkeypatch.setattr(perspective, "_changed_images",
                        lambda ctx, found, state, near: ("changed", state.n_particles))
    monkeypatch.setattr(hidden.EarlierRounds, "forget_near",
                        lambda self, dlfc, views, *changed: fake.forgotten.append(changed))
    locator = PerspectiveLocator.from_dict({"check": {"hidden_rounds": rounds}})
    ctx = type("Ctx", (), {"dlfc": None})()
    _, state = perspective.search_hidden_rounds(ctx, fake.state(10), locator, None)
    assert fake.calls == calls
    assert perspective._n_live(state, locator.solve.min_views) == 10 + kept
    assert all(earlier is fake.earlier[0] for earlier in fake.earlier)
    n = 10 + np.cumsum([found for found, _ in script])
    assert fake.forgotten == [("changed", int(k)) for k in n[:went_on]]


def test_hidden_search_settings_are_checked():
    from plenoptrack.errors import SettingsError

    for bad in ({"hidden_floor": 0.0}, {"hidden_floor": 1.0}, {"hidden_floor": -0.5},
                {"hidden_rounds": 0}, {"hidden_rounds": 1.5}, {"hidden_rounds": True},
                {"hidden_joint": 1}, {"hidden_joint": "yes"}):
        with pytest.raises(SettingsError):
            PerspectiveLocator.from_dict({"check": bad})
    check = dataclasses.asdict(PerspectiveLocator().check)
    assert check["hidden_floor"] == 0.5 and check["hidden_rounds"] == 8
    assert check["hidden_joint"] is True


def test_coinciding_names_the_particles_whose_images_are_one_with_the_image():
    """``_coinciding`` against the definition computed view by view: the same particle
    (median distance below the larger radius) or merged images that keep their offset
    (median distance below the sum of the radii, offset changing by under a view pixel);
    ``_coincides`` is whether there is any."""
    from plenoptrack.locate._nearby import ImageSpans

    rng = np.random.default_rng(7)
    views = 12
    u = np.linspace(-1, 1, views)[:, None]
    hits = 0
    for _ in range(60):
        others = rng.uniform(0, 12, (15, 1, 2)) + rng.normal(0, 1.5, (15, 1, 2)) * u
        other_r = rng.uniform(0.5, 3.0, 15)
        image = rng.uniform(0, 12, (1, 1, 2)) + rng.normal(0, 1.5, (1, 1, 2)) * u
        r = rng.uniform(0.5, 3.0, 1)
        rows = split._coinciding(image, r, others, other_r, ImageSpans(others))
        expected = []
        for k in range(15):
            offset = image[0] - others[k]                                  # (V, 2)
            dist = np.median(np.hypot(offset[:, 0], offset[:, 1]))
            parallax = np.sqrt(8.0 * offset.var(axis=0).sum())
            if dist < max(r[0], other_r[k]) or (dist < r[0] + other_r[k] and parallax < 1.0):
                expected.append(k)
        assert sorted(rows.tolist()) == expected
        assert split._coincides(image, r, others, other_r) == bool(expected)
        hits += bool(expected)
    assert 10 < hits < 50                   # both answers occur


def test_a_particle_a_located_fit_swallowed_is_fitted_with_it(small_calibrated):
    """160 particles of 0.4 mm in one frame (about 0.05 per microlens): particles found
    in the residual on top of a located particle, fitted together with it
    (``check.hidden_joint``), find 9 more true particles (139 against 130 matched)
    with fewer unmatched (6 against 7); at least 6 more and no more unmatched are
    required."""
    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=160, seed=21, diameter_mm=0.4)
    raw = render_frame(optics, scene.truth, seed=np.random.default_rng([21, 3, 0]))
    counts = {}
    for joint in (False, True):
        locator = PerspectiveLocator.from_dict({"check": {"hidden_joint": joint}})
        found = locate_frame(raw, calib, locator=locator).particles
        matched = len(match_particles(found, scene.truth, tolerance_mm=1.0))
        counts[joint] = (matched, len(found) - matched)
    assert counts[True][0] >= counts[False][0] + 6
    assert counts[True][1] <= counts[False][1]


def _stand_in_context(**fields):
    """A stand-in for a FrameContext with just ``fields``, and its ``fit_images`` method
    (which reads ``dlfc``, ``lf.data``, ``image_edge`` and ``large_image_px``: no image
    is large unless given)."""
    from functools import partial
    from types import SimpleNamespace

    from plenoptrack.locate.frame import FrameContext

    ctx = SimpleNamespace(**{"large_image_px": math.inf, **fields})
    ctx.fit_images = partial(FrameContext.fit_images, ctx)
    return ctx


def _three_particle_frame(render_hidden: bool, b_offset_mm: float = 0.0,
                          hidden_start=(0.25, 0.0, -2.0), a_contrast: float = 0.95):
    """A frame context and particle state for a hidden particle (row 2, started at
    ``hidden_start``) between two located ones whose images overlap its own (the linear
    stand-in DLFC of the image-fit tests); located particle 1 held ``b_offset_mm`` off
    its true depth, particle 0 drawn with contrast ``a_contrast`` (0.95 in the image)."""
    from types import SimpleNamespace

    from test_refine import LinearCalibration, _render, _views

    class Calibration(LinearCalibration):
        def local_magnification(self, x, y, z):
            return np.full(np.shape(x), 10.0)           # view pixels per mm

    dlfc = Calibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 1.0], [0.5, 0.05, 3.0], [0.25, 0.0, -2.0]])
    rc = np.array([[2.0, 0.95], [2.0, 0.95], [2.0, 0.95]])
    drawn = slice(None) if render_hidden else slice(0, 2)
    data = _render(dlfc, truth[drawn], rc[drawn], views_uv, view_rc, noise=0.01, seed=2)
    lf = SimpleNamespace(data=data, u=np.arange(9) - 4.0, v=np.arange(9) - 4.0,
                         valid_fraction=np.ones((9, 9)))
    detections = pd.DataFrame({"dark_area": [10.0], "diameter_px": [4.0], "whole": [True]})
    # the images are drawn with the round edge of EDGE_PX: the fits model them so
    ctx = _stand_in_context(lf=lf, views=views_uv, dlfc=dlfc, detections=detections,
                            volume_depth_mm=20.0, image_edge=ImageEdge())
    positions = np.vstack([truth[:2] + [[0, 0, 0], [0, 0, b_offset_mm]], hidden_start])
    table = pd.DataFrame({"n_views": [81, 81, 81], "_fit_radius_px": rc[:, 0],
                          "_fit_contrast": [a_contrast, 0.95, 0.95],
                          "flags": [33, 33, 33 | 64]})
    state = ParticleState(owner=np.array([0]), initial=positions.copy(),
                          positions=positions, table=table)
    return ctx, state


@pytest.mark.parametrize("case, kept", [
    # a real particle beside well-fitted neighbours
    ({"render_hidden": True}, True),
    # ... and beside a neighbour whose fit is off: the place stays unexplained for all
    ({"render_hidden": True, "b_offset_mm": 1.5}, True),
    # nothing there: the model without it explains the pixels
    ({"render_hidden": False}, False),
    # nothing there but a neighbour drawn too faint: the fit moves into its body
    ({"render_hidden": False, "hidden_start": (0.05, 0.0, 0.6), "a_contrast": 0.5}, False),
])
def test_an_unexplained_hidden_particle_is_kept_only_if_it_still_explains_its_pixels(
        case, kept):
    ctx, state = _three_particle_frame(**case)
    locator = PerspectiveLocator()
    assert hidden._still_explains_more(ctx, state, np.array([2]), locator).tolist() == [kept]
    after = hidden._drop_unexplained_hidden(ctx, state, 2, 1, locator)
    assert np.isfinite(after.positions[2]).all() == kept
    assert (after.table.loc[2, "n_views"] > 0) == kept
    np.testing.assert_array_equal(after.positions[:2], state.positions[:2])


def test_uncovered_views_count_the_free_regions_no_located_image_covers():
    """``_n_uncovered_views`` against the definition checked region by region: the
    views (usable ones only) holding a region that no particle owns whose centroid is
    farther than radius + grow tolerance from every located image's centre there."""
    from types import SimpleNamespace

    rng = np.random.default_rng(5)
    n_u = n_v = 5
    views = np.array([[u, v] for v in range(n_v) for u in range(n_u)], float) - 2.0
    valid = rng.uniform(0.2, 1.0, (n_v, n_u))                # some views not usable
    usable = valid[(views[:, 1] + 2).astype(int), (views[:, 0] + 2).astype(int)] > 0.5
    lf = SimpleNamespace(u=np.arange(n_u) - 2.0, v=np.arange(n_v) - 2.0,
                         valid_fraction=valid)
    n_fit = int(usable.sum())
    counts = []
    for _ in range(20):
        m = 30
        view = rng.integers(0, len(views), m)
        st = rng.uniform(0, 30, (m, 2))
        owner = rng.choice([-2, -1, 0, 1], m)
        pred = rng.uniform(0, 30, (6, n_fit, 2))
        pred[rng.random((6, n_fit)) < 0.1] = np.nan
        radius = rng.uniform(1.0, 6.0, 6)
        ctx = SimpleNamespace(lf=lf, views=views, view=view, st=st, tolerance_px=1.0)
        fit_index = np.cumsum(usable) - 1
        expected = set()
        for k in range(m):
            if owner[k] >= 0 or not usable[view[k]]:
                continue
            d = np.hypot(*(pred[:, fit_index[view[k]]] - st[k]).T)
            if not np.any(d <= radius + 1.0):
                expected.add(view[k])
        got = hidden._n_uncovered_views(ctx, owner, pred, radius)
        assert got == len(expected)
        counts.append(got)
        assert hidden._n_uncovered_views(ctx, owner, pred[:0], radius[:0]) == len(
            np.unique(view[(owner < 0) & usable[view]]))
    assert 0 < min(counts) < max(counts) < n_fit           # neither none nor all covered


def _frame_with_freed_regions(small_calibrated, clustered_and_solved):
    """A sparse frame (12 particles of 0.6 mm), located up to the image fits; one
    particle is then dropped and its regions freed, as when a particle built from
    merged images is dropped and the real ones it took regions from are left
    unclustered: ``(ctx, freed state, locator, calibration, dropped particle's true
    xyz, state before)``."""
    import warnings

    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=12, seed=31, diameter_mm=0.6)
    raw = render_frame(optics, scene.truth, seed=np.random.default_rng([31, 3, 0]))
    locator = PerspectiveLocator()
    ctx, state = clustered_and_solved(raw, calib, locator)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        state = perspective.check_particles(ctx, state, locator)
        state = perspective.refine_particles(ctx, state, locator)
    fit_error = state.table[perspective._FIT_ERROR].to_numpy(float)
    live = state.live(locator.solve.min_views)
    explained = live & (fit_error <= locator.check.refine_max_model_error)
    # the best-seen particle whose fit explains its pixels, matched to a true one
    found = pd.DataFrame(state.positions, columns=["x", "y", "z"])
    pairs = match_particles(found[explained], scene.truth, tolerance_mm=0.2)
    n_views = state.table["n_views"].to_numpy(float)
    drop = int(max(pairs["measured_index"], key=lambda j: n_views[j]))
    true_xyz = scene.truth.loc[pairs.set_index("measured_index").loc[drop, "truth_index"],
                               ["x", "y", "z"]].to_numpy(float)
    keep = explained.copy()
    keep[drop] = False
    owner = np.where(np.isin(state.owner, np.flatnonzero(~keep)), -1, state.owner)
    positions = state.positions.copy()
    positions[~keep] = np.nan
    table = state.table.assign(n_views=np.where(keep, n_views, 0))
    freed = dataclasses.replace(state, owner=owner, positions=positions, table=table)
    return ctx, freed, locator, calib, true_xyz, state


def test_a_particle_whose_regions_were_freed_is_found_when_every_fit_explains(
        small_calibrated, clustered_and_solved):
    """Every fit left explains its pixels (:func:`_frame_with_freed_regions`), so the
    fit test alone would not search; the regions no located image covers (in more than
    ``min_views`` views) start the search, which finds the particle again within 0.1 mm."""
    import warnings

    ctx, freed, locator, calib, true_xyz, state = _frame_with_freed_regions(
        small_calibrated, clustered_and_solved)
    fit_error = state.table[perspective._FIT_ERROR].to_numpy(float)
    # the fit test alone would not search
    assert not np.any(freed.live(locator.solve.min_views)
                      & (fit_error > locator.check.refine_max_model_error))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, joined, n_new = perspective.find_hidden_particles(ctx, freed, locator, calib)
    assert n_new >= 1
    new_xyz = joined.positions[state.n_particles:]
    err = np.abs(new_xyz - true_xyz)
    assert np.any(np.all(err <= [0.05, 0.05, 0.1], axis=1)), new_xyz


def test_the_residual_search_locates_the_frame_with_the_located_images_divided_out(
        small_calibrated, clustered_and_solved):
    """``search_residual`` hands the stages it re-runs one light field: the frame with
    the located particles' images divided out (darker than the frame nowhere, lighter
    where a located image was, the freed particle's image still dark). When those stages
    find nothing, the state comes back as it was."""
    import warnings

    ctx, freed, locator, calib, true_xyz, _ = _frame_with_freed_regions(
        small_calibrated, clustered_and_solved)
    seen = []

    def nothing_found(residual):
        seen.append(residual)
        return None

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out_ctx, out_state, n_new = hidden.search_residual(ctx, freed, locator, calib,
                                                           nothing_found)
    assert (out_ctx, out_state, n_new) == (ctx, freed, 0)
    assert len(seen) == 1
    before, after = ctx.lf.data, seen[0].data
    assert after.shape == before.shape and after is not before
    finite = np.isfinite(before) & np.isfinite(after)
    assert np.all(after[finite] >= before[finite] - 1e-6)
    changed = finite & (after > before + 1e-3)
    assert changed.mean() > 1e-4                     # the located images, lifted
    # the freed particle's image is not divided out: in the central view its centre
    # stays as dark in the residual as in the frame
    v0, u0 = (np.argmin(np.abs(ctx.lf.v)), np.argmin(np.abs(ctx.lf.u)))
    s, t = calib.dlfc.predict(*true_xyz, 0.0, 0.0)
    i, j = int(round(float(t))), int(round(float(s)))
    assert before[v0, u0, i, j] < 0.5 * np.nanmedian(before[v0, u0])      # its shadow
    assert after[v0, u0, i, j] == pytest.approx(before[v0, u0, i, j], abs=1e-6)

def test_a_companion_offset_is_kept_per_particle_the_farthest_laterally():
    """Offsets to darkness the search could not take apart: each particle keeps the one
    farthest from it laterally, over the candidates of a round and over the rounds."""
    table = pd.DataFrame({"n_views": [20, 20, 20]})
    state = ParticleState(owner=np.zeros(0, dtype=np.int64), initial=np.zeros((3, 3)),
                          positions=np.zeros((3, 3)), table=table)
    assert hidden._with_companions(state, {}) is state
    found = {}
    hidden._note_companion(found, 0, [0.1, 0.0, 2.0])
    hidden._note_companion(found, 0, [0.0, 0.05, -3.0])      # nearer: not kept
    hidden._note_companion(found, 2, [np.nan, 0.0, 0.0])     # not a position
    hidden._note_companion(found, 1, [0.0, -0.2, 0.5])
    assert sorted(found) == [0, 1]
    first = hidden._with_companions(state, found)
    columns = list(hidden._COMPANION)
    np.testing.assert_array_equal(first.table.loc[0, columns], [0.1, 0.0, 2.0])
    np.testing.assert_array_equal(first.table.loc[1, columns], [0.0, -0.2, 0.5])
    assert first.table.loc[2, columns].isna().all()
    # a later round: a farther one replaces, a nearer one does not
    later = hidden._with_companions(first, {0: np.array([0.0, 0.3, 0.0]),
                                                 1: np.array([0.1, 0.0, 0.0])})
    np.testing.assert_array_equal(later.table.loc[0, columns], [0.0, 0.3, 0.0])
    np.testing.assert_array_equal(later.table.loc[1, columns], [0.0, -0.2, 0.5])
    assert columns[0] not in state.table.columns                 # the input is not changed


def _sigma_term_on_and_off(small_calibrated, switch: str, n_particles: int, seed: int):
    """A frame of ``n_particles`` of 0.4 mm located with the sigma term ``solve.<switch>``
    on (the default, checked) and off: the particles found with it, a mask of those whose
    sigma it widened, and how many matched particles lie beyond 3 sigma with and
    without it. Asserts what every such term keeps: positions identical, sigma never
    smaller."""
    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=n_particles, seed=seed, diameter_mm=0.4)
    raw = render_frame(optics, scene.truth, seed=np.random.default_rng([seed, 3, 0]))
    assert getattr(PerspectiveLocator().solve, switch)                  # on by default
    off = PerspectiveLocator.from_dict({"solve": {switch: False}})
    on_found = locate_frame(raw, calib).particles
    off_found = locate_frame(raw, calib, locator=off).particles
    xyz, sigma = ["x", "y", "z"], ["sigma_x", "sigma_y", "sigma_z"]
    np.testing.assert_array_equal(on_found[xyz].to_numpy(), off_found[xyz].to_numpy())
    on_sigma, off_sigma = on_found[sigma].to_numpy(), off_found[sigma].to_numpy()
    assert np.all(on_sigma >= off_sigma)
    widened = np.any(on_sigma > off_sigma, axis=1)
    pairs = match_particles(on_found, scene.truth, tolerance_mm=1.0)
    error = np.abs(on_found.loc[pairs["measured_index"], xyz].to_numpy()
                   - scene.truth.loc[pairs["truth_index"], xyz].to_numpy())
    rows = pairs["measured_index"].to_numpy()
    beyond = {name: int(np.any(error > 3 * s[rows], axis=1).sum())
              for name, s in (("on", on_sigma), ("off", off_sigma))}
    return on_found, widened, beyond


def test_darkness_the_search_cannot_take_apart_widens_sigma(small_calibrated):
    """160 particles of 0.4 mm (about 0.05 per microlens): some particles have darkness
    beside them that the hidden-particle search finds and cannot take apart from them;
    ``solve.companion_error`` widens their sigma and no one else's, moves nothing, and
    leaves fewer of the matched particles beyond 3 sigma."""
    _, widened, beyond = _sigma_term_on_and_off(small_calibrated, "companion_error", 160, 21)
    assert widened.sum() >= 5
    assert beyond["on"] < beyond["off"]


def test_a_fit_that_disagrees_with_its_centroid_solution_widens_sigma(small_calibrated):
    """80 particles of 0.4 mm (about 0.025 per microlens): ``solve.refit_error`` widens
    the sigma of refitted particles (not the halves of a split) by the RMS of a shift
    anywhere between their image fit and their earlier centroid solution, moves nothing,
    and leaves fewer of the matched particles beyond 3 sigma."""
    found, widened, beyond = _sigma_term_on_and_off(small_calibrated, "refit_error", 80, 22)
    flags = found["flags"].to_numpy(np.int64)
    assert widened.sum() >= 5
    assert np.all(flags[widened] & int(TriangulationFlag.REFINED))
    assert not np.any(flags[widened] & int(TriangulationFlag.SPLIT))
    assert beyond["on"] < beyond["off"]


def _duplicate_frame(render_candidate: bool, candidate=(0.05, 0.0, 2.5),
                     candidate_views: int = 7, third=None, neighbour_flags: int = 33):
    """A frame context and particle state for a weakly seen, unexplained particle (row
    1, at ``candidate``) whose images nearly coincide with a strongly seen particle's
    (row 0, at (0, 0, 1), drawn in the image, with ``neighbour_flags``); the candidate
    is drawn in the image only with ``render_candidate``; ``third``, a strongly seen
    particle drawn in the image beside them (the linear stand-in DLFC of the image-fit
    tests)."""
    from types import SimpleNamespace

    from test_refine import LinearCalibration, _render, _views

    class Calibration(LinearCalibration):
        def local_magnification(self, x, y, z):
            return np.full(np.shape(x), 10.0)           # view pixels per mm

    dlfc = Calibration()
    views_uv, view_rc = _views()
    xyz = [(0.0, 0.0, 1.0), candidate] + ([] if third is None else [third])
    rc = np.full((len(xyz), 2), [2.0, 0.95])
    drawn = [0] + ([1] if render_candidate else []) + ([2] if third is not None else [])
    data = _render(dlfc, np.array(xyz)[drawn], rc[drawn], views_uv, view_rc, noise=0.01,
                   seed=3)
    lf = SimpleNamespace(data=data, u=np.arange(9) - 4.0, v=np.arange(9) - 4.0,
                         valid_fraction=np.ones((9, 9)), view_mask=np.ones((9, 9), bool))
    detections = pd.DataFrame({"dark_area": [10.0], "diameter_px": [4.0], "whole": [True]})
    ctx = _stand_in_context(lf=lf, views=views_uv, dlfc=dlfc, detections=detections,
                            volume_depth_mm=20.0, image_edge=ImageEdge())
    positions = np.array(xyz, dtype=float)
    n_views = [81, candidate_views] + ([81] if third is not None else [])
    flags = [neighbour_flags, 1 | 64] + ([33] if third is not None else [])
    table = pd.DataFrame({"n_views": n_views, "_fit_radius_px": rc[:, 0],
                          "_fit_contrast": rc[:, 1], "flags": flags})
    state = ParticleState(owner=np.array([0]), initial=positions.copy(),
                          positions=positions, table=table)
    return ctx, state


@pytest.mark.parametrize("case, kept", [
    # nothing there: the strongly seen particle's image found again
    ({"render_candidate": False}, False),
    # a real particle behind it on nearly the same line of sight explains its pixels
    ({"render_candidate": True}, True),
    # seen in a quarter of the views: not tested
    ({"render_candidate": False, "candidate_views": 21}, True),
    # its images meet a second particle's too: not tested
    ({"render_candidate": False, "third": (0.45, 0.0, 1.0)}, True),
    # its images lie apart from the neighbour's (median distance above the radius)
    ({"render_candidate": False, "candidate": (0.3, 0.0, 1.0)}, True),
    # the neighbour's own fit leaves its pixels unexplained: it may be two images
    # merged on nearly one line of sight, of which the weak particle is one
    ({"render_candidate": False, "neighbour_flags": 1 | 64}, True),
])
def test_a_weak_particle_that_duplicates_one_neighbour_is_dropped(case, kept):
    ctx, state = _duplicate_frame(**case)
    after = hidden.drop_duplicate_particles(ctx, state, PerspectiveLocator())
    assert np.isfinite(after.positions[1]).all() == kept
    assert (after.table.loc[1, "n_views"] > 0) == kept
    others = np.r_[0, 2:len(state.positions)]
    np.testing.assert_array_equal(after.positions[others], state.positions[others])
    np.testing.assert_array_equal(after.owner, state.owner)


def test_a_particle_between_two_images_on_one_line_of_sight_moves_to_its_own_depth():
    """Two particles nearly on one line of sight, 6 mm apart in depth: their images
    merge in the middle views, so the centroids put one particle between them (row 0,
    at z = 0); the other is seen alone only in the outer views (row 1, at its own
    depth). Fitted jointly with the other, row 0 has to move 3 mm, more than a tenth of
    the volume depth: that fit is kept because it explains the pixels, and row 0 keeps
    only the centroids on its new image."""
    from types import SimpleNamespace

    from test_refine import LinearCalibration, _render, _views

    class Calibration(LinearCalibration):
        def local_magnification(self, x, y, z):
            return np.full(np.shape(x), 10.0)           # view pixels per mm

    dlfc = Calibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, -3.0], [0.03, 0.0, 3.0]])
    rc = np.array([[2.0, 0.95], [2.0, 0.95]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.01, seed=4)
    lf = SimpleNamespace(data=data, u=np.arange(9) - 4.0, v=np.arange(9) - 4.0,
                         valid_fraction=np.ones((9, 9)), view_mask=np.ones((9, 9), bool))
    positions = np.array([[0.0, 0.0, 0.0], truth[1]])
    # row 0's centroids: one per view, on the image of its solution; row 1's: the 12
    # outermost views, on its image
    outer = np.argsort(-np.hypot(*views_uv.T), kind="stable")[:12]
    view = np.r_[np.arange(len(views_uv)), outer]
    owner = np.r_[np.zeros(len(views_uv), int), np.ones(12, int)]
    st = np.array([dlfc.predict(*positions[o], *views_uv[k]) for o, k in zip(owner, view)])
    detections = pd.DataFrame({"dark_area": 12.6, "diameter_px": 4.0, "whole": True},
                              index=range(len(view)))
    ctx = _stand_in_context(lf=lf, views=views_uv, dlfc=dlfc, detections=detections,
                            volume_depth_mm=20.0, image_edge=ImageEdge(), st=st,
                            view=view, tolerance_px=1.0)
    table = pd.DataFrame({"x": positions[:, 0], "y": positions[:, 1], "z": positions[:, 2],
                          "sigma_x": 0.01, "sigma_y": 0.01, "sigma_z": 0.1,
                          "n_views": [81, 12], "residual_px": [1.5, 0.0], "flags": [1, 1]})
    state = ParticleState(owner=owner, initial=positions.copy(), positions=positions,
                          table=table)
    after = perspective.refine_particles(ctx, state, PerspectiveLocator())
    np.testing.assert_allclose(after.positions, truth, atol=0.05)
    # row 0 keeps the centroids on its new image (the central view and its four
    # neighbours: 0.9 view px of parallax per view step), row 1 all of its own
    np.testing.assert_array_equal(np.flatnonzero(after.owner == 0),
                                  np.flatnonzero(np.hypot(*views_uv.T) <= 1))
    assert after.table["n_views"].tolist() == [5, 12]
    np.testing.assert_array_equal(after.owner[81:], 1)
    assert (after.table[perspective._FIT_ERROR].max()
            <= PerspectiveLocator().check.refine_max_model_error)
    assert np.all(after.table["flags"].to_numpy() & int(TriangulationFlag.REFINED))


@pytest.mark.slow
def test_a_misplaced_particle_takes_the_image_found_in_the_residual(tmp_path):
    """First frame of the built-in fragment field, seed 1, simulated, calibrated and
    located as ``plenoptrack simulate``, ``calibrate`` and the README's fragment settings
    do. A 2.8 mm fragment's images merge with a 0.6 mm and a 0.9 mm fragment's; its
    centroids put it 1.2 mm off its centroid, where no image fit tried it. The residual
    search finds it there and turns the candidate down as that particle's own image;
    the candidate's image now replaces the centroid solution (0.13 mm off)."""
    import warnings

    from plenoptrack.calibrate import calibrate
    from plenoptrack.camera import load_camera
    from plenoptrack.io import read_raw, read_table
    from plenoptrack.lightfield import decode
    from plenoptrack.simulate import simulate_dataset
    from plenoptrack.simulate.scenes import builtin_scene

    folder = tmp_path / "frag"
    scene, params = builtin_scene("fragments", {"seed": 1, "frames": 1})
    simulate_dataset(scene.camera, folder, seed=scene.seed, frames=1, scene=scene,
                     scene_params=params)
    calib, _ = calibrate(folder / "white.tif", folder / "dotcards",
                         load_camera(folder / "camera.toml"))
    truth = read_table(folder / "truth.parquet")
    locator = PerspectiveLocator().updated(
        {"segment": {"max_area_ratio": 100, "split_pairs": False, "window": 51},
         "solve": {"shape_error": 0.02}})
    white = decode(read_raw(folder / "white.tif"), calib.grid)
    raw = read_raw(sorted((folder / "raw").glob("frame_*.tif"))[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        found = locate_frame(raw, calib, white=white, locator=locator).particles
    frag = truth[truth["particle"] == 1].iloc[0]
    assert frag["diameter"] == pytest.approx(2.77, abs=0.01)
    lateral = np.hypot(found["x"] - frag["x"], found["y"] - frag["y"])
    assert lateral.min() <= 0.3, lateral.min()
    assert int(found.loc[lateral.idxmin(), "flags"]) & TriangulationFlag.REFINED
