"""Lens realism (``LensEffects``): drawn distortion, Seidel field curvature, astigmatism and
coma, cat's-eye vignetting, optical axis off the sensor centre, tilted microlens array;
each effect checked against its physics on rendered ``small`` images, plus exactness of
the culled rendering and unchanged ideal bytes."""

import hashlib
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from plenoptrack import preset
from plenoptrack.simulate import (SimOptics, make_optics, render_dotcard, render_frame,
                                  render_irradiance, render_white)
from plenoptrack.simulate.dotcard import dotcard_irradiance, draw_card_placements
from plenoptrack.simulate.realism import LensEffects, Realism
from plenoptrack.simulate.render import background_irradiance

CAM = preset("small")
OFF = LensEffects().scaled(0)


def _optics(seed=0, camera=CAM, **lens):
    """``small`` optics of ``make_optics(seed)`` with only the given lens effects on."""
    return make_optics(camera, seed, realism=replace(Realism.ideal(), lens=replace(OFF, **lens)))


def _particles(rows):
    return pd.DataFrame(rows, columns=["x", "y", "z", "diameter"])


def _rho2(o, x, y):
    """Squared normalised field of the world point (x, y, 0)."""
    u = o.world_to_mla([x, y, 0.0]) - np.asarray(o.axis_offset_mm)
    return float((u ** 2).sum()) / o.distortion_radius_mm ** 2


# Views: the pixel at offset e (row, col px) from every microlens-image centre sees the
# pupil point H = -e * pp * s_i / f_ml (camera frame), p = H / (D / 2).
VIEWS = np.array([(r, c) for r in range(-4, 5) for c in range(-4, 5) if r * r + c * c <= 16],
                 dtype=float)


def _view_centroids(o, irr, world_xy, views=VIEWS):
    """Shadow centroid (row, col px of lens-image centres) of a particle in each view."""
    bg = background_irradiance(o).astype(float)
    centres = o.true_grid.centers().reshape(-1, 2)
    near = centres[np.hypot(*(centres - o.world_to_pixels([*world_xy, 0.0])).T) < 120]
    out = []
    for e in views:
        shadow = np.clip(ndimage.map_coordinates(bg - irr, (near + e).T, order=1), 0, None)
        out.append((shadow[:, None] * near).sum(0) / shadow.sum())
    return np.array(out)


def _disparity_slopes(o, irr, world_xy):
    """d(centroid row)/d(view row), d(centroid col)/d(view col): zero at best focus."""
    cen = _view_centroids(o, irr, world_xy)
    design = np.column_stack([np.ones(len(VIEWS)), VIEWS])
    coef, *_ = np.linalg.lstsq(design, cen, rcond=None)
    return coef[1, 0], coef[2, 1]


def _focus_depth(depths, slopes):
    """Depth where a (nearly linear) disparity slope crosses zero."""
    p = np.polyfit(depths, slopes, 1)
    return -p[1] / p[0]


# --- distortion ------------------------------------------------------------------------------

def test_distortion_drawn_per_camera_within_sigma_and_followed_by_the_image():
    lens = LensEffects()
    draws = np.array([(o.k1, o.k2) for o in
                      (make_optics(CAM, s, realism=replace(Realism.ideal(), lens=lens))
                       for s in range(300))])
    assert draws[:, 0].mean() == pytest.approx(0.02, abs=3 * 0.01 / math.sqrt(300))
    assert draws[:, 1].mean() == pytest.approx(-0.005, abs=3 * 0.003 / math.sqrt(300))
    assert draws[:, 0].std() == pytest.approx(0.01, rel=0.15)
    assert draws[:, 1].std() == pytest.approx(0.003, rel=0.15)
    assert _optics(0).k1 == 0.02     # sigmas off: the fixed values
    # A camera with a strong draw: an in-focus particle near the field edge appears where
    # world_to_pixels of the drawn coefficients says, not where the fixed ones put it.
    o = _optics(0, distortion_k1_sigma=0.05, distortion_k2_sigma=0.01)
    fixed = replace(o, k1=0.02, k2=-0.005)
    xy = (4.0, 2.4)
    bg = background_irradiance(o).astype(float)
    shadow = bg - render_irradiance(o, _particles([[*xy, 0.0, 0.4]])).astype(float)
    rr, cc = np.mgrid[0:shadow.shape[0], 0:shadow.shape[1]]
    centroid = np.array([(shadow * rr).sum(), (shadow * cc).sum()]) / shadow.sum()
    predicted = o.world_to_pixels([*xy, 0.0])
    moved = np.hypot(*(predicted - fixed.world_to_pixels([*xy, 0.0])))
    assert moved > 4.0
    assert np.hypot(*(centroid - predicted)) < 0.15 * moved


# --- Seidel terms ----------------------------------------------------------------------------

def test_field_curvature_moves_best_focus_at_the_field_edge_only():
    fc = 2.0
    o = _optics(field_curvature_mm=fc)
    axis, edge = (0.0, 0.0), (4.0, 2.3)
    depths = [-2.0, -1.0, 0.0]
    slopes = {axis: [], edge: []}
    for z in depths:
        irr = render_irradiance(o, _particles([[*axis, z, 0.8], [*edge, z, 0.8]])).astype(float)
        for xy in slopes:
            slopes[xy].append(np.mean(_disparity_slopes(o, irr, xy)))
    z_axis, z_edge = _focus_depth(depths, slopes[axis]), _focus_depth(depths, slopes[edge])
    expected = -fc * _rho2(o, *edge)
    print(f"best focus: axis {z_axis:.3f} mm, edge {z_edge:.3f} mm, expected {expected:.3f} mm")
    assert abs(z_axis) < 0.1
    assert z_edge - z_axis == pytest.approx(expected, rel=0.1)


def test_astigmatism_separates_tangential_and_sagittal_foci():
    ast = 2.0
    o = _optics(astigmatism_mm=ast)
    edge = (4.2, 0.0)                       # field along +x: tangential = columns
    depths = [-1.5, 0.0, 1.5]
    sag, tan = [], []
    for z in depths:
        irr = render_irradiance(o, _particles([[*edge, z, 0.8]])).astype(float)
        s_row, s_col = _disparity_slopes(o, irr, edge)
        sag.append(s_row)
        tan.append(s_col)
    z_sag, z_tan = _focus_depth(depths, sag), _focus_depth(depths, tan)
    rho2 = _rho2(o, *edge)
    print(f"sagittal focus {z_sag:.3f} mm, tangential {z_tan:.3f} mm, "
          f"expected +-{ast / 2 * rho2:.3f} mm")
    assert z_sag - z_tan == pytest.approx(ast * rho2, rel=0.1)
    assert z_sag == pytest.approx(ast / 2 * rho2, abs=0.12 * ast * rho2)
    assert z_tan == pytest.approx(-ast / 2 * rho2, abs=0.12 * ast * rho2)


def _shadow_centroid(o, particles):
    bg = background_irradiance(o).astype(float)
    shadow = bg - render_irradiance(o, particles).astype(float)
    rr, cc = np.mgrid[0:shadow.shape[0], 0:shadow.shape[1]]
    return np.array([(shadow * rr).sum(), (shadow * cc).sum()]) / shadow.sum()


def test_coma_blur_is_a_comet_pointing_away_from_the_axis():
    coma = 0.2
    o = _optics(coma_mm=coma)
    # A large particle: its view images are sampled by many lenses (a 0.8 mm one shows
    # +-1 px of lattice-sampling error in a single view).
    edge = (3.8, 0.0)
    parts = _particles([[*edge, 0.0, 1.6]])
    cen = _view_centroids(o, render_irradiance(o, parts).astype(float), edge)
    shift = cen - cen[np.all(VIEWS == 0, axis=1)][0]
    # Object side: a view through pupil p sees the point moved by c [|p|^2 u + 2 (p.u) p],
    # c = coma / 3, u the outward field vector ((rho, 0) in the world; world +x is +col).
    p = -VIEWS[:, ::-1] * o.pixel_pitch * o.s_i / o.f_ml / o.aperture_radius   # (X, Y)
    rho = math.sqrt(_rho2(o, *edge))
    c = coma / 3
    px_per_mm = (o.s_i / o.s_o) * o.image_scale / o.pixel_pitch
    expected_col = c * rho * ((p ** 2).sum(1) + 2 * p[:, 0] ** 2) * px_per_mm
    expected_row = c * rho * 2 * p[:, 0] * p[:, 1] * px_per_mm
    top = expected_col.max()
    print(f"largest view shift {shift[:, 1].max():.3f} px, expected {top:.3f} px")
    assert (shift[:, 1] > -0.05 * top).all()                      # outward only
    np.testing.assert_allclose(shift[:, 1], expected_col, atol=0.12 * top)
    np.testing.assert_allclose(shift[:, 0], expected_row, atol=0.12 * top)
    # Along the radius the comet is three times longer than across it.
    radial = shift[(VIEWS[:, 0] == 0) & (np.abs(VIEWS[:, 1]) == 4), 1]
    across = shift[(VIEWS[:, 1] == 0) & (np.abs(VIEWS[:, 0]) == 4), 1]
    assert radial.mean() / across.mean() == pytest.approx(3.0, rel=0.15)
    # The whole blur's centroid moves outward by the pupil mean c rho (|p|^2 + 2 p_x^2) =
    # c rho (1/2 + 1/2), and not across the radius.
    moved = _shadow_centroid(o, parts) - _shadow_centroid(_optics(), parts)
    assert moved[1] == pytest.approx(c * rho * px_per_mm, rel=0.1)
    assert abs(moved[0]) < 0.1 * moved[1]


# --- vignetting and the axis -----------------------------------------------------------------

def _lens_light(o, irr):
    """Light of each microlens image (pixels nearest to its centre) and the centres."""
    centres = o.true_grid.centers().reshape(-1, 2)
    rows, cols = irr.shape
    _, owner = cKDTree(centres).query(np.indices((rows, cols)).reshape(2, -1).T)
    light = np.bincount(owner, weights=irr.ravel().astype(float), minlength=len(centres))
    inside = ((centres >= 8) & (centres <= np.array([rows, cols]) - 9)).all(axis=1)
    return centres[inside], light[inside]


def _circle_overlap(r1, r2, d):
    """Area common to discs of radii r1, r2 whose centres are d apart."""
    d = np.asarray(d, dtype=float)
    out = np.where(d <= abs(r1 - r2), math.pi * min(r1, r2) ** 2, 0.0)
    part = (d > abs(r1 - r2)) & (d < r1 + r2)
    dd = d[part]
    a1 = r1 ** 2 * np.arccos((dd ** 2 + r1 ** 2 - r2 ** 2) / (2 * dd * r1))
    a2 = r2 ** 2 * np.arccos((dd ** 2 + r2 ** 2 - r1 ** 2) / (2 * dd * r2))
    a3 = 0.5 * np.sqrt((-dd + r1 + r2) * (dd + r1 - r2) * (dd - r1 + r2) * (dd + r1 + r2))
    out[part] = a1 + a2 - a3
    return out


def test_cats_eye_vignetting_darkens_the_corners_by_the_cone_overlap():
    ratio = 0.2
    ideal = _optics()
    o = _optics(vignetting_radius_ratio=ratio)
    dist, radius = o.front_stop
    # The front stop clips the field-edge cone as the ratio says.
    need = dist * o.field_edge_slope + o.aperture_radius * (1 - dist / o.s_o)
    assert radius == pytest.approx((1 - ratio) * need)
    centres, light = _lens_light(o, background_irradiance(o))
    _, light0 = _lens_light(ideal, background_irradiance(ideal))
    frac = light / light0
    # Expected: the lens's cone (radius D/2 (1 - L/s_o), centred L * chief slope off the
    # axis) overlapping the stop.
    q = o.pixels_to_sensor_mm(centres) / o.image_scale
    slope = np.hypot(*q.T) * o.distortion_factor(np.hypot(*q.T)) / o.s_i
    r_cone = o.aperture_radius * (1 - dist / o.s_o)
    expected = _circle_overlap(radius, r_cone, dist * slope) / (math.pi * r_cone ** 2)
    rho = np.hypot(*q.T) / o.distortion_radius_mm
    print(f"corner light {frac.min():.3f} (expected {expected[np.argmin(frac)]:.3f})")
    assert frac.min() < 0.9
    np.testing.assert_allclose(frac, expected, atol=0.015)
    # Within half the field radius nothing changes, to the bit.
    xy = o.pixels_to_sensor_mm(np.indices(CAM.sensor_shape_px).transpose(1, 2, 0))
    centre = np.hypot(xy[..., 0], xy[..., 1]) < 0.45 * o.distortion_radius_mm
    np.testing.assert_array_equal(background_irradiance(o)[centre],
                                  background_irradiance(ideal)[centre])
    assert (frac[rho < 0.45] == 1).all()


def test_axis_offset_moves_the_axis_image_and_the_vignetting_centre():
    pp = CAM.pixel_pitch_um * 1e-3
    rows, cols = CAM.sensor_shape_px
    sensor_centre = np.array([(rows - 1) / 2, (cols - 1) / 2])
    drawn = [_optics(s, axis_offset_px=20.0).axis_offset_px for s in range(200)]
    r = np.hypot(*np.array(drawn).T)
    assert r.max() <= 20.0 and r.max() > 19.0
    assert np.mean(r < 20 / math.sqrt(2)) == pytest.approx(0.5, abs=0.1)   # uniform in the disc
    offset_px = np.array([10.0, -60.0])                                    # (row, col)
    base = _optics(vignetting_radius_ratio=0.2)
    for off in (np.zeros(2), offset_px):
        o = replace(base, axis_offset_mm=(off[1] * pp, off[0] * pp))
        axis_px = o.world_to_pixels([0.0, 0.0, 0.0])
        np.testing.assert_allclose(axis_px, sensor_centre + off, atol=1e-9)
        # A particle on the axis shows up at the axis image.
        bg = background_irradiance(o).astype(float)
        shadow = bg - render_irradiance(o, _particles([[0.0, 0.0, 0.0, 0.4]])).astype(float)
        rr, cc = np.mgrid[0:rows, 0:cols]
        centroid = np.array([(shadow * rr).sum(), (shadow * cc).sum()]) / shadow.sum()
        np.testing.assert_allclose(centroid, axis_px, atol=1.5)   # as test_render
        # The unvignetted microlens images form a disc about the axis image.
        centres, light = _lens_light(o, bg)
        _, light0 = _lens_light(base, background_irradiance(replace(base, realism=Realism.ideal())))
        full = centres[light >= light0 * (1 - 1e-9)]
        print("unvignetted centre", full.mean(0) - sensor_centre, "axis", off)
        np.testing.assert_allclose(full.mean(0), axis_px, atol=3.0)


# --- tilted microlens array ------------------------------------------------------------------

def _image_centroids_and_pitch_slope(o):
    """Centroids of the isolated aperture images against their exact centres, and the
    change of the local pitch along lens rows with X, px per mm (least-squares line)."""
    grid = o.true_grid
    i, j = np.meshgrid(np.arange(grid.shape[0]), np.arange(grid.shape[1]), indexing="ij")
    i0, j0 = np.round(o.lattice_coords(o.pixels_to_sensor_mm(grid.origin_px) / o.image_scale))
    exact = o.lens_image_centers_px(i + int(i0), j + int(j0)).reshape(-1, 2)
    rows, cols = o.camera.sensor_shape_px
    exact = exact[((exact >= 8) & (exact <= np.array([rows, cols]) - 9)).all(axis=1)]
    irr = background_irradiance(o).astype(float)
    dr, dc = np.mgrid[-7:8, -7:8]
    measured = []
    for r0, c0 in exact:
        a, b = int(round(r0)), int(round(c0))
        rr, cc = dr + a, dc + b
        win = irr[a - 7:a + 8, b - 7:b + 8] * (np.hypot(rr - r0, cc - c0) < 7)
        measured.append([(win * rr).sum() / win.sum(), (win * cc).sum() / win.sum()])
    measured = np.array(measured)
    err = np.sqrt(np.mean(np.sum((measured - exact) ** 2, axis=1)))
    d, k = cKDTree(exact).query(exact + np.asarray(grid.col_step_px), distance_upper_bound=2.0)
    has = np.isfinite(d)
    pitch = np.hypot(*(measured[k[has]] - measured[has]).T)
    x_mid = o.pixels_to_sensor_mm(0.5 * (exact[has] + exact[k[has]]))[:, 0] / o.image_scale
    return err, np.polyfit(x_mid, pitch, 1)[0], exact


def test_mla_tilt_changes_image_size_and_local_pitch_across_the_sensor():
    cam = CAM.with_changes(f_number=4.0)          # isolated aperture images
    slope = math.tan(math.radians(1.0))           # 1 degree about the Y axis: d grows with X
    flat = _optics(camera=cam)
    o = replace(flat, mla_tilt=(slope, 0.0))
    # Aperture-image light ~ (D/2 * d / s_l)^2 with d = f_ml + delta, s_l = s_i - delta.
    centres, light = _lens_light(o, background_irradiance(o))
    _, light0 = _lens_light(flat, background_irradiance(flat))
    q = o.pixels_to_sensor_mm(centres) / o.image_scale
    delta = o.mla_delta_mm(q)
    expected = ((o.f_ml + delta) / (o.s_i - delta) / (o.f_ml / o.s_i)) ** 2
    print(f"aperture-image light, tilted / flat: left third "
          f"{(light / light0)[q[:, 0] < -0.8].mean():.3f}, right third "
          f"{(light / light0)[q[:, 0] > 0.8].mean():.3f}")
    np.testing.assert_allclose(light / light0, expected, rtol=0.03)
    # The image centres follow lens_image_centers_px; the local pitch along a lens row
    # grows with X as the scale (s_i + f_ml) / (s_i - t X) does: by 2 t X / s_i.
    err, pitch_slope, exact = _image_centroids_and_pitch_slope(o)
    err0, pitch_slope0, _ = _image_centroids_and_pitch_slope(flat)
    expected_slope = 2 * slope / o.s_i * o.true_grid.pitch_px
    bend, _ = cKDTree(o.true_grid.centers().reshape(-1, 2)).query(exact)
    print(f"centroid - exact centre RMS {err:.4f} px (flat {err0:.4f}); exact centres off "
          f"the fitted lattice by up to {bend.max():.3f} px; pitch change "
          f"{pitch_slope:.5f} px/mm, expected {expected_slope:.5f} (flat {pitch_slope0:.5f})")
    assert err < 0.04
    assert pitch_slope == pytest.approx(expected_slope, rel=0.25)
    assert abs(pitch_slope0) < 0.2 * expected_slope


# --- exactness, switches, reproducibility ----------------------------------------------------

STRONG = LensEffects().scaled(5.0)


@pytest.mark.parametrize("name", ["small", "small-rect"])
def test_culled_render_equals_brute_force_with_all_lens_effects(name):
    o = make_optics(preset(name), 2, realism=replace(Realism.ideal(), lens=STRONG))
    assert o.axis_offset_mm != (0, 0) and o.mla_tilt != (0, 0) and o.front_stop is not None
    rng = np.random.default_rng(2)
    n = 10
    parts = _particles(np.column_stack([rng.uniform(-4.5, 4.5, n), rng.uniform(-3.5, 3.5, n),
                                        rng.uniform(-12, 12, n), rng.uniform(0.2, 1.2, n)]))
    culled = render_irradiance(o, parts)
    assert (culled != background_irradiance(o)).sum() > 10000
    np.testing.assert_array_equal(culled, render_irradiance(o, parts, cull=False))
    _, _, (placement,) = draw_card_placements(Realism.realistic().target, 1, 3)
    for z, pl in ((3.0, None), (-6.0, placement)):
        np.testing.assert_array_equal(dotcard_irradiance(o, z, placement=pl),
                                      dotcard_irradiance(o, z, placement=pl, exact=True))


def test_culled_equals_brute_force_for_a_strong_tilt_and_offset():
    o = SimOptics(CAM, rotation_deg=0.3, k1=0.1, k2=-0.05, axis_offset_mm=(0.3, -0.2),
                  mla_tilt=(0.03, -0.02),
                  realism=replace(Realism.ideal(), lens=replace(STRONG, vignetting_radius_ratio=0.3)))
    parts = _particles([[4.0, 2.5, -9.0, 0.9], [-4.6, -3.0, 9.0, 0.7], [0.2, 0.1, 30.0, 2.0]])
    np.testing.assert_array_equal(render_irradiance(o, parts),
                                  render_irradiance(o, parts, cull=False))


def _digest(*images):
    return [hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16] for a in images]


# sha256 (first 16 hex digits) of make_optics(small, 3) renders before the lens group
# existed: white (seed 1), frame (seed 2), placed dot card at 3 mm (seed 4), dot-card
# irradiance at -5 mm; ideal, then realistic with the lens group off (and the particle
# group, which came later still). The raw images of "no-lens" are those of the direct
# blur, which replaced the FFT blur: it differs by float32 rounding only
# (test_realism_image.py::test_direct_blur_is_the_fft_blur_up_to_rounding); the
# irradiance is the one from before the lens group.
BEFORE = {
    "ideal": ["2a4fd82eec1ca2b2", "81062c9b65bd57e2", "9a265afede7c6769", "c39b5e71cbcd4ddd"],
    "no-lens": ["00c8533fff95bf44", "e4443bd3f7603925", "5e18764956a2b1dc", "3607d481a8c4c560"],
}


@pytest.mark.parametrize("mode", ["ideal", "no-lens"])
def test_lens_group_off_keeps_the_bytes(mode):
    realism = (Realism.ideal() if mode == "ideal"
               else replace(Realism.realistic(), lens=OFF, particles=Realism.ideal().particles))
    o = make_optics(CAM, 3, realism=realism)
    assert o.axis_offset_mm == (0.0, 0.0) and o.mla_tilt == (0.0, 0.0)
    parts = _particles([[0.5, -0.3, 2.0, 0.8], [-2.0, 1.0, -6.0, 1.0], [4.0, 2.5, -9.0, 0.9]])
    _, _, (pl,) = draw_card_placements(o.realism.target, 1, 5)
    got = _digest(render_white(o, seed=1), render_frame(o, parts, seed=2),
                  render_dotcard(o, 3.0, seed=4, placement=pl), dotcard_irradiance(o, -5.0))
    assert got == BEFORE[mode]


def test_lens_draws_come_after_the_others_and_repeat_with_the_seed():
    real = make_optics(CAM, 7, realism="realistic")
    no_lens = make_optics(CAM, 7, realism=replace(Realism.realistic(), lens=OFF))
    assert (real.rotation_deg, real.offset_mm, real.pitch_scale, real.camera) == \
        (no_lens.rotation_deg, no_lens.offset_mm, no_lens.pitch_scale, no_lens.camera)
    again = make_optics(CAM, 7, realism="realistic")
    assert again == real
    other = make_optics(CAM, 8, realism="realistic")
    assert (other.k1, other.axis_offset_mm, other.mla_tilt) != (real.k1, real.axis_offset_mm,
                                                                 real.mla_tilt)
    assert 0 < math.degrees(math.atan(math.hypot(*real.mla_tilt))) <= 0.02
    parts = _particles([[0.5, -0.3, 2.0, 0.8], [4.0, 2.5, -9.0, 0.9]])
    a = _digest(render_white(real, seed=1), render_frame(real, parts, seed=2))
    b = _digest(render_white(again, seed=1), render_frame(again, parts, seed=2))
    assert a == b
    # Different draws never share a cached background.
    assert background_irradiance(real) is not background_irradiance(other)
    assert not np.array_equal(background_irradiance(real), background_irradiance(no_lens))


def test_truth_file_records_the_lens_draws():
    import json
    o = make_optics(CAM, 4, realism="realistic")
    doc = json.loads(json.dumps(o.to_dict()))
    assert doc["lens"]["axis_offset_mm"] == list(o.axis_offset_mm)
    assert doc["lens"]["mla_tilt"] == list(o.mla_tilt)
    assert SimOptics.from_dict(doc) == o
    assert doc["true_grid"] == o.true_grid.to_dict()


def _grid_rms(o):
    from plenoptrack.calibration import calibrate_from_white

    calib, _ = calibrate_from_white(render_white(o, seed=4), o.nominal_camera)
    true = o.true_grid.centers().reshape(-1, 2)
    rows, cols = CAM.sensor_shape_px
    inside = ((true >= 7) & (true <= np.array([rows, cols]) - 8)).all(axis=1)
    d, _ = cKDTree(calib.grid.centers().reshape(-1, 2)).query(true[inside])
    return np.sqrt(np.mean(d ** 2)), d.max()


def test_grid_calibration_on_a_fully_realistic_white_image():
    # Cat's-eye vignetting clips the aperture images of the outer lenses on the side away
    # from the axis, so their centroids move towards it: the white-image grid is biased
    # by about 0.1 px; every other lens effect leaves it within 0.01 px.
    real = Realism.realistic()
    rms, worst = _grid_rms(make_optics(CAM, 0, realism=real))
    rms_nv, worst_nv = _grid_rms(make_optics(
        CAM, 0, realism=replace(real, lens=replace(real.lens, vignetting_radius_ratio=0.0))))
    print(f"grid centre error, all effects: RMS {rms:.4f} px (max {worst:.4f}); without "
          f"vignetting: RMS {rms_nv:.4f} px (max {worst_nv:.4f})")
    assert rms < 0.15
    assert rms_nv < 0.01
