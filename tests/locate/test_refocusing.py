"""The refocusing-based locator, its focal stack and focus measure, and the hybrid."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack.errors import NoParticlesWarning, SettingsError
from plenoptrack.evaluate import evaluate_particles
from plenoptrack.lightfield import decode
from plenoptrack.lightfield.refocus import focal_stack
from plenoptrack.locate import locate_frame
from plenoptrack.locate.perspective import PARTICLE_COLUMNS
from plenoptrack.locate.refocusing import (HybridLocator, RefocusLocator, _fitted_parallax,
                                           _to_object, alpha_for_parallax, depth_of_field_mm,
                                           focus_peaks, locate_frame_hybrid,
                                           locate_frame_refocus, parallax_per_u, window_stack)
from plenoptrack.simulate import make_scene, render_frame


def _frame(optics, truth, seed):
    return render_frame(optics, truth, seed=np.random.default_rng([seed, 3, 0]))


@pytest.fixture(scope="module")
def small(small_calibrated):
    return small_calibrated


@pytest.fixture(scope="module")
def scene_frame(small):
    optics, calib = small
    scene = make_scene(calib.camera, n_particles=20, seed=1)
    return scene.truth, _frame(optics, scene.truth, 1)


def test_window_stack_matches_focal_stack_and_its_crops(small, scene_frame):
    _, calib = small
    lf = decode(scene_frame[1], calib.grid)
    depths = np.array([-6.0, 0.5, 7.0])
    alphas = calib.camera.alpha_for_depth(depths)
    # with the 1/alpha magnification it is refocus.focal_stack, an independent kernel
    full = window_stack(lf, calib.camera, alphas, magnify=True)
    np.testing.assert_allclose(full, focal_stack(lf, calib.camera, depths), atol=1e-6)
    # a window is the same crop of the whole plane
    shifted = window_stack(lf, calib.camera, alphas)
    crop = window_stack(lf, calib.camera, alphas, origin_ts=(7, 11), shape_ts=(9, 13))
    np.testing.assert_array_equal(crop, shifted[:, 7:16, 11:24])
    # without magnification, the focal-plane image is the plain mean of the valid views
    mean = window_stack(lf, calib.camera, [1.0])[0]
    sel = lf.data[lf.view_mask]
    inner = (slice(5, -5), slice(5, -5))
    want = (sel * lf.spatial_mask).sum(0) / lf.view_mask.sum()
    np.testing.assert_allclose(mean[inner][lf.spatial_mask[inner]],
                               want[inner][lf.spatial_mask[inner]], rtol=1e-5)


def test_parallax_and_alpha_are_inverse_and_signed(small, scene_frame):
    _, calib = small
    lf = decode(scene_frame[1], calib.grid)
    alpha = np.array([0.95, 1.0, 1.04])
    par = parallax_per_u(lf, calib.camera, alpha)
    # behind the focal plane (alpha < 1) a point moves towards larger s as u grows
    assert par[0] > 0 and par[1] == 0 and par[2] < 0
    np.testing.assert_allclose(alpha_for_parallax(lf, calib.camera, par), alpha, rtol=1e-12)


def test_depth_of_field_limits_blur_one_microlens_pitch():
    camera = preset("hall2019")
    for extended, n_u in ((False, 1.0), (True, camera.pixels_per_lenslet)):
        near, far = depth_of_field_mm(camera, extended=extended)
        assert near < 0 < far
        d_ap = camera.aperture_diameter_mm / n_u
        for z in (near, far):
            d = camera.image_distance_for_depth(z)
            blur = d_ap * abs(d - camera.image_distance_mm) / d
            assert blur == pytest.approx(camera.microlens_pitch_um * 1e-3, rel=1e-9)
    assert depth_of_field_mm(camera)[1] > depth_of_field_mm(camera, extended=False)[1]
    # a larger magnification has a shallower depth of field
    assert depth_of_field_mm(camera.with_magnification(-0.75))[1] < depth_of_field_mm(camera)[1]


def test_focus_peaks_of_gaussian_curves():
    x = np.linspace(-10, 10, 101)
    centres = np.array([-3.13, 0.0, 4.71])
    sig = np.array([1.0, 2.0, 1.5])
    curves = 1.0 + np.exp(-0.5 * ((x[None] - centres[:, None]) / sig[:, None]) ** 2)
    edge = 1.0 + np.exp(-0.5 * ((x + 12) / 2) ** 2)       # peak beyond the first plane
    out = focus_peaks(np.vstack([curves, edge[None]]), x)
    np.testing.assert_allclose(out["peak"][:3], centres, atol=0.02)
    np.testing.assert_allclose(out["fwhm"][:3], 2.3548 * sig, rtol=0.02)
    assert not out["interior"][3] and math.isnan(out["peak"][3])
    assert out["interior"][:3].all()


def test_dlfc_conversion_recovers_the_point_its_rays_come_from(small, scene_frame):
    _, calib = small
    lf = decode(scene_frame[1], calib.grid)
    pos = np.array([[0.5, -0.8, -6.0], [-1.2, 1.0, 0.3], [2.0, 0.4, 7.5]])
    ts, par = _fitted_parallax(calib.dlfc, lf, pos)
    tri = _to_object(calib.dlfc, lf, ts, par, pos + 0.5)
    # the rays are the DLFC's own projection straightened to lines: a small model error
    np.testing.assert_allclose(tri.positions, pos, atol=0.05)


def test_refocus_locator_finds_particles_with_the_perspective_columns(small, scene_frame):
    from scipy.spatial import cKDTree

    found = true = 0
    dz = []
    for truth_table, raw in (scene_frame,):
        result = locate_frame_refocus(raw, small[1])
        p = result.particles
        assert list(p.columns) == list(PARTICLE_COLUMNS)
        assert p["sigma_x"].isna().all() and p["sigma_y"].isna().all()
        assert (p["n_views"] == p["n_views"].iloc[0]).all() and p["n_views"].iloc[0] > 50
        # lateral position from the in-focus image is good (particles are well apart
        # laterally); depth is the weak axis
        truth = truth_table[["x", "y", "z"]].to_numpy()
        d, j = cKDTree(truth[:, :2]).query(p[["x", "y"]].to_numpy())
        assert np.median(d) < 0.05
        good = d < 0.1
        found += len(np.unique(j[good]))
        true += len(truth)
        dz.append(np.median(np.abs(p["z"].to_numpy()[good] - truth[j[good], 2])))
        # sizes from the in-focus image: 0.4 mm particles
        assert 0.25 < p["diameter"].median() < 0.6
        assert set(result.stage_seconds) == {"decode", "stack", "detect", "focus", "convert"}
    assert found / true >= 0.4
    assert max(dz) < 1.0


def test_refocus_depth_scale_follows_the_particle(small):
    """One particle at several depths: the refocus depth tracks the true one."""
    optics, calib = small
    z_true = np.array([-7.0, -4.0, 6.0])
    got = []
    for k, z in enumerate(z_true):
        truth = pd.DataFrame({"frame": 0, "particle": 0, "x": [0.8], "y": [-0.5], "z": [z],
                              "diameter": [0.4]})
        p = locate_frame_refocus(_frame(optics, truth, 10 + k), calib).particles
        assert len(p) == 1
        got.append(p["z"].iat[0])
    assert np.all(np.diff(got) > 0)
    np.testing.assert_allclose(got, z_true, atol=1.0)


def test_hybrid_keeps_perspective_lateral_and_changes_only_depth(small, scene_frame):
    _, calib = small
    truth, raw = scene_frame
    base = locate_frame(raw, calib).particles
    hyb = locate_frame_hybrid(raw, calib)
    assert list(hyb.particles.columns) == list(PARTICLE_COLUMNS)
    pd.testing.assert_frame_equal(hyb.particles.drop(columns="z"), base.drop(columns="z"))
    near, far = depth_of_field_mm(calib.camera)
    z = base["z"].to_numpy()
    outside = np.abs(z) > np.where(z < 0, -near, far) * HybridLocator().max_depth_fraction
    np.testing.assert_array_equal(hyb.particles["z"].to_numpy()[outside], z[outside])
    ev_h = evaluate_particles(hyb.particles, truth, tolerance_mm=1.0)
    ev_p = evaluate_particles(base, truth, tolerance_mm=1.0)
    assert ev_h.n_matched == ev_p.n_matched
    assert abs(ev_h.mean_error_z) < 0.3
    assert "refine" in hyb.stage_seconds


def test_empty_frame_gives_empty_table_and_warning(small):
    optics, calib = small
    raw = _frame(optics, pd.DataFrame(columns=["frame", "particle", "x", "y", "z", "diameter"]), 5)
    with pytest.warns(NoParticlesWarning):
        p = locate_frame_refocus(raw, calib, locator=RefocusLocator(n_planes=20)).particles
    assert len(p) == 0 and list(p.columns) == list(PARTICLE_COLUMNS)


@pytest.mark.parametrize("kwargs, match", [
    ({"n_planes": 2}, "n_planes must be at least 3"),
    ({"contrast": 1.5}, "contrast must be between 0 and 1"),
    ({"depth_range_mm": (3.0, -3.0)}, "far > near"),
    ({"min_peak_ratio": 0.5}, "min_peak_ratio must be at least 1"),
])
def test_refocus_settings_are_validated(kwargs, match):
    with pytest.raises(SettingsError, match=match):
        RefocusLocator(**kwargs)


def test_window_stack_refuses_bad_alphas(small, scene_frame):
    _, calib = small
    lf = decode(scene_frame[1], calib.grid)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SettingsError, match="positive"):
            window_stack(lf, calib.camera, [1.0, -0.5])
