"""Image-domain realism: microlens blur (psf), back-light and dust (illumination), sensor
fixed patterns (sensor); each effect checked against its physics on the ``small`` preset."""

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree

from plenoptrack import preset
from plenoptrack.simulate import (make_optics, render_dotcard, render_frame, render_repeats,
                                  render_white)
from plenoptrack.simulate.illumination import (backlight_field, dust_patches, dust_table,
                                               illuminate, illuminated, image_rng)
from plenoptrack.simulate.psf import (AIRY_FIRST_ZERO, DIRECT_MAX_TAPS, _optics_transfer,
                                      apply_crosstalk, apply_transfer, blur_image,
                                      convolve_direct, convolve_psf, crosstalk_shifts,
                                      fill_transmission, psf_kernel)
from plenoptrack.simulate.realism import (BlurEffects, IlluminationEffects, Realism,
                                          SensorEffects)
from plenoptrack.simulate.render import background_irradiance, render_dark
from plenoptrack.simulate.sensor import SensorModel, expose, fixed_pattern, output_regions

CAM = preset("small")
NO_BLUR = BlurEffects().scaled(0)
NO_LIGHT = IlluminationEffects().scaled(0)
NO_SENSOR = SensorEffects().scaled(0)
LEVELS = 0.7 / 0.9  # frame over white exposure (SensorModel background_level / white_level)


def _optics(seed=0, *, blur=NO_BLUR, illumination=NO_LIGHT, sensor=NO_SENSOR):
    """`small` camera (spec and target off: the geometry of make_optics(seed)) with the
    given image-domain effects."""
    realism = replace(Realism.ideal(), blur=blur, illumination=illumination, sensor=sensor)
    return make_optics(CAM, seed, realism=realism)


@pytest.fixture(scope="module")
def ideal():
    return make_optics(CAM, 0)


@pytest.fixture(scope="module")
def image_realistic():
    """All three image groups at their defaults (spec, target off)."""
    return _optics(blur=BlurEffects(), illumination=IlluminationEffects(),
                   sensor=SensorEffects())


def _delta(n=401):
    img = np.zeros((n, n), dtype=np.float32)
    img[n // 2, n // 2] = 1.0
    return img


def _first_minimum(profile, step):
    i = int(np.argmin(profile))
    a, b, c = profile[i - 1:i + 2]
    return (i + 0.5 * (a - c) / (a - 2 * b + c)) * step


# --- blur ------------------------------------------------------------------------------------

@pytest.mark.parametrize("f_number", [CAM.microlens_f_number, 2.5])
def test_airy_first_zero_of_a_rendered_point(f_number):
    # A point imaged by the PSF code on a 0.1 um pixel grid (pixel integration over 0.1 um
    # moves the minimum by < 0.01 um; parabolic interpolation of the sampled minimum is
    # good to < 0.01 um): the first dark ring sits at 1.22 lambda N.
    step = 0.1
    k = psf_kernel(BlurEffects(550.0, 0, 0, 0, 0), f_number=f_number, pixel_pitch_um=step)
    image = convolve_psf(_delta(501), k)     # the kernel reaches 10 lambda N = 22 um
    row = image[250, 250:310].astype(float)
    expected = AIRY_FIRST_ZERO * 0.55 * f_number
    stop = int(1.5 * expected / step)
    assert _first_minimum(row[:stop], step) == pytest.approx(expected, abs=0.03)
    assert image.sum() == pytest.approx(1.0, abs=1e-5)


def test_defocus_disc_and_aberration_sizes():
    step, n = 0.1, CAM.microlens_f_number
    # Uniform disc of diameter defocus / N: mean r^2 = R^2 / 2.
    disc = psf_kernel(BlurEffects(0, 20.0, 0, 0, 0), f_number=n, pixel_pitch_um=step)
    rr = (np.indices(disc.shape) - disc.shape[0] // 2) * step
    r2 = (disc * (rr ** 2).sum(axis=0)).sum()
    assert np.sqrt(2 * r2) == pytest.approx(20.0 / n / 2, rel=0.02)
    # Gaussian aberration of RMS radius a.
    gauss = psf_kernel(BlurEffects(0, 0, 1.0, 0, 0), f_number=n, pixel_pitch_um=step)
    rr = (np.indices(gauss.shape) - gauss.shape[0] // 2) * step
    assert np.sqrt((gauss * (rr ** 2).sum(axis=0)).sum()) == pytest.approx(1.0, rel=0.02)


def test_blur_and_crosstalk_conserve_light(ideal):
    rng = np.random.default_rng(0)
    img = np.zeros((200, 240), dtype=np.float32)
    img[40:160, 40:200] = rng.random((120, 160))
    k = psf_kernel(BlurEffects(), f_number=CAM.microlens_f_number, pixel_pitch_um=CAM.pixel_pitch_um)
    shifts = crosstalk_shifts(ideal)
    out = apply_transfer(img, k, shifts, 0.05)
    assert out.sum() == pytest.approx(img.sum(), rel=1e-5)
    assert out.min() >= 0
    # A point: 1 - c stays, c / 6 lands one image-lattice step away in each direction.
    ghost = apply_crosstalk(_delta(101), shifts, 0.06)
    assert ghost[50, 50] == pytest.approx(0.94, abs=1e-6)
    assert len(shifts) == 6
    pitch_px = ideal.pitch * ideal.image_scale / ideal.pixel_pitch
    np.testing.assert_allclose(np.hypot(*shifts.T), pitch_px, rtol=1e-9)
    for dr, dc in shifts:
        r, c = int(np.floor(50 + dr)), int(np.floor(50 + dc))
        assert ghost[r:r + 2, c:c + 2].sum() == pytest.approx(0.01, abs=1e-6)


def test_direct_blur_is_the_fft_blur_up_to_rounding():
    o = _optics(blur=BlurEffects())
    k = psf_kernel(o.realism.blur, f_number=CAM.microlens_f_number,
                   pixel_pitch_um=CAM.pixel_pitch_um)
    assert k.size <= DIRECT_MAX_TAPS        # blur_image sums the taps directly
    shifts, xt = crosstalk_shifts(o), o.realism.blur.crosstalk
    # Points at the edges and corners: light blurred just off the sensor is scattered
    # back in by the crosstalk in both; random pixels elsewhere.
    img = np.zeros(CAM.sensor_shape_px, dtype=np.float32)
    img[[0, 1, 2, -1, -3, 300], [0, 2, -1, 5, -2, 450]] = 1.0
    rng = np.random.default_rng(0)
    img[100:200, 100:300] = rng.random((100, 200))
    for kern, sh, f in ((k, shifts, xt), (k, shifts[:0], 0.0), (np.ones((1, 1)), shifts, xt)):
        fft = apply_transfer(img, kern, sh, f).astype(float)
        direct = convolve_direct(img, kern, sh, f)
        assert np.abs(direct - fft).max() < 2e-6
        assert direct.sum() == pytest.approx(fft.sum(), rel=1e-5)
    # A realistic white image: against the cached FFT transfer of blur_image before.
    irr = background_irradiance(o)
    fft = apply_transfer(irr, k, shifts, xt, transfer=_optics_transfer(o)).astype(float)
    direct = blur_image(irr, o)
    assert np.abs(direct - fft).max() < 1e-5      # of the back-light: far below the noise
    assert 0 < np.count_nonzero(direct != fft)    # (a different rounding, not the same sum)
    # Raw counts without noise: at most 1 count (of 4095) apart, in rare pixels.
    sensor = SensorModel()
    a, b = (expose(x, level=0.7, bit_depth=CAM.bit_depth, sensor=sensor, rng=None, noise=False)
            for x in (fft, direct))
    diff = np.abs(a.astype(int) - b)
    assert diff.max() <= 1 and diff.mean() < 1e-3


def test_illuminated_is_a_copy_then_illuminate():
    o = _optics(illumination=IlluminationEffects(dust_particles=4, dust_diameter_um=120))
    irr = background_irradiance(o)
    for rng in (None, np.random.default_rng(3)):
        before = irr.copy()
        a = illuminated(irr, o, None if rng is None else image_rng(rng))
        b = illuminate(irr.copy(), o, None if rng is None else image_rng(np.random.default_rng(3)))
        assert np.array_equal(irr, before)
        assert a.dtype == np.float32 and np.array_equal(a, b)
        assert not np.array_equal(a, irr)


def test_fill_gap_loses_the_dead_cell_area(ideal):
    gap = 0.02
    o = _optics(blur=replace(NO_BLUR, fill_gap=gap))
    ref = background_irradiance(ideal).astype(float)
    irr = blur_image(background_irradiance(o), o).astype(float)
    full = ref == 1.0   # pixels whose every sample passes the aperture
    assert full.sum() > 10000
    # (a few pixels next to the disc edge lose a sample: Q moved inwards moves H too)
    assert np.mean(np.abs(irr[full] - (1 - gap) ** 2) < 1e-6) > 0.999
    assert fill_transmission(o.realism.blur) == pytest.approx(0.9604)
    # Over the whole image the loss is the dead area fraction, up to the sharper disc edge.
    assert irr.sum() / ref.sum() == pytest.approx((1 - gap) ** 2, rel=0.01)


def test_blurred_white_image_conserves_light(ideal):
    o = _optics(blur=replace(BlurEffects(), fill_gap=0.0))
    ref = background_irradiance(ideal).astype(float)
    irr = blur_image(background_irradiance(o), o).astype(float)
    # Only the light blurred or scattered off the sensor edge is lost.
    assert irr.sum() / ref.sum() == pytest.approx(1.0, abs=0.004)
    assert irr.sum() < ref.sum()
    # The blur fills the dark corners between lenses a little and softens the disc edges.
    assert np.abs(irr - ref).max() > 0.05


# --- illumination ----------------------------------------------------------------------------

def test_backlight_field_sizes():
    eff = IlluminationEffects(dust_particles=0)
    o = _optics(illumination=eff)
    white = backlight_field(o).astype(float)
    assert np.ptp(white) == pytest.approx(eff.backlight_nonuniformity, rel=0.01)
    f1 = backlight_field(o, image_rng(np.random.default_rng(1))).astype(float)
    f2 = backlight_field(o, image_rng(np.random.default_rng(2))).astype(float)
    c = eff.backlight_frame_change
    assert np.ptp(f1 / white) == pytest.approx(c, rel=0.01)
    assert np.ptp(f2 / white) == pytest.approx(c, rel=0.01)
    assert c * 0.5 < np.ptp(f1 / f2) <= 2 * c * 1.01
    # fixed per camera, different between cameras
    np.testing.assert_array_equal(backlight_field(o), white.astype(np.float32))
    other = _optics(1, illumination=eff)
    assert np.abs(backlight_field(other) - white).max() > 0.01


def test_frame_over_white_shows_the_backlight_change():
    eff = IlluminationEffects(dust_particles=0)
    o = _optics(illumination=eff)
    white = render_white(o, noise=False).astype(float)
    frame = render_frame(o, None, seed=5, noise=False).astype(float)
    lit = white > 0.5 * white.max()
    ratio = frame[lit] / white[lit] / LEVELS
    assert np.ptp(ratio) == pytest.approx(eff.backlight_frame_change, abs=0.004)
    # and it is the field of that seed
    expect = backlight_field(o, image_rng(np.random.default_rng(5))) / backlight_field(o)
    np.testing.assert_allclose(ratio, expect[lit], atol=2e-3)


def test_dust_shadows_are_fixed_and_flat_field_away():
    eff = IlluminationEffects(backlight_nonuniformity=0, backlight_frame_change=0.03,
                              dust_particles=6, dust_opacity=0.8)
    o = _optics(illumination=eff)
    base = _optics()
    assert len(dust_table(o)) == 6 and len(dust_patches(o)) >= 5
    white = render_white(o, noise=False).astype(float)
    white0 = render_white(base, noise=False).astype(float)
    frame = render_frame(o, None, seed=3, noise=False).astype(float)
    frame0 = render_frame(base, None, seed=3, noise=False).astype(float)
    lit = white0 > 0.5 * white0.max()
    shadow_w = lit & (white < 0.9 * white0)
    change = (backlight_field(o, image_rng(np.random.default_rng(3)))).astype(float)
    shadow_f = lit & (frame < 0.9 * frame0 * change)
    assert shadow_w.sum() > 50
    assert (shadow_w == shadow_f).mean() > 0.999           # same pixels
    # Flat-fielding removes the shadows, leaving the back-light change.
    ratio = frame[lit] / white[lit] / LEVELS / change[lit]
    assert np.abs(ratio - 1).max() < 3e-3
    # A shadow blurred by the cone of light: partial transmission, not a hard edge.
    t = white[shadow_w] / white0[shadow_w]
    assert t.min() > 0.2 - 1e-3 and (t > 0.5).any()


# --- sensor ----------------------------------------------------------------------------------

def test_flat_field_cancels_the_fixed_patterns(image_realistic):
    # Every image-domain effect on; dark subtraction and flat-fielding with the white
    # image leave the back-light change only.
    o = image_realistic
    dark = render_dark(o, noise=False).astype(float)
    white = render_white(o, noise=False).astype(float) - dark
    frame = render_frame(o, None, seed=7, noise=False).astype(float) - dark
    fp = fixed_pattern(o)
    good = white > 0.5 * np.median(white[white > 100])
    good.ravel()[fp.hot] = False
    change = backlight_field(o, image_rng(np.random.default_rng(7))) / backlight_field(o)
    ratio = frame[good] / white[good] / LEVELS / change[good]
    assert np.abs(ratio - 1).max() < 2e-3               # 1 count in ~1500
    # Without flat-fielding the gain map shows: ~1 % pixel to pixel.
    raw = render_frame(o, None, seed=7, noise=False).astype(float)
    ideal = render_frame(_optics(), None, seed=7, noise=False).astype(float)
    assert np.std(raw[good] / ideal[good]) > 0.008
    # With noise, flat-fielded: scatter as expected from shot and read noise alone.
    noisy = render_frame(o, None, seed=7).astype(float) - dark
    ratio = noisy[good] / white[good] / LEVELS / change[good]
    electrons = frame[good] * 20000 / 4095
    expected = np.sqrt(np.mean(1 / electrons))
    assert np.std(ratio) == pytest.approx(expected, rel=0.1)


def test_hot_dead_pixels_and_dead_column():
    eff = SensorEffects()
    o = _optics(sensor=eff)
    fp = fixed_pattern(o)
    n = CAM.sensor_shape_px[0] * CAM.sensor_shape_px[1]
    assert len(fp.hot) == round(eff.hot_fraction * n)
    assert len(fp.dead) == round(eff.dead_fraction * n)
    assert len(fp.dead_columns) == 1
    dark = render_dark(o, noise=False)
    white = render_white(o, noise=False)
    assert (dark.ravel()[fp.hot] >= 0.9 * CAM.full_scale - 1).all()
    hot_share = (dark >= 0.9 * CAM.full_scale - 1).mean()
    assert hot_share == pytest.approx(eff.hot_fraction, rel=0.05)
    # Dead pixels and the dead column read their dark level in a lit white image.
    np.testing.assert_array_equal(white.ravel()[fp.dead], dark.ravel()[fp.dead])
    col = fp.dead_columns[0]
    np.testing.assert_array_equal(white[:, col], dark[:, col])
    assert np.median(white[:, col]) == pytest.approx(eff.pedestal_counts, abs=1.0)
    assert white[:, col - 1].mean() > 10 * eff.pedestal_counts


def test_output_gains_of_the_quadrants(ideal):
    eff = replace(NO_SENSOR, output_gain_mismatch=0.02, outputs=4)
    o = _optics(sensor=eff)
    gains = fixed_pattern(o).output_gains
    assert len(gains) == 4 and np.ptp(gains) > 0.005
    white = render_white(o, noise=False).astype(float)
    ref = render_white(ideal, noise=False).astype(float)
    for g, (rs, cs) in zip(gains, output_regions(CAM.sensor_shape_px, 4)):
        w, r = white[rs, cs], ref[rs, cs]
        lit = r > 1000
        # rounding the few discrete irradiance levels (1/16 steps) to counts: < 1 count
        # in the 3686 of a fully lit pixel
        assert (w[lit].sum() / r[lit].sum()) == pytest.approx(g, abs=3e-4)
    halves = _optics(sensor=replace(eff, outputs=2))
    assert len(fixed_pattern(halves).output_gains) == 2


# --- switches, seeds, reproducibility --------------------------------------------------------

def _card_frame_white(o, particles):
    return (render_white(o, seed=1), render_frame(o, particles, seed=2),
            render_dotcard(o, 1.0, seed=3))


PARTS = pd.DataFrame([[0.5, -0.3, 2.0, 0.8], [-2.0, 1.0, -6.0, 1.0]],
                     columns=["x", "y", "z", "diameter"])


def test_repeats_of_a_still_scene_are_the_frames_of_their_seeds(image_realistic):
    o = image_realistic
    seeds = [np.random.default_rng([0, 72, 3, r]) for r in range(3)]
    alone = [render_frame(o, PARTS, seed=np.random.default_rng([0, 72, 3, r]))
             for r in range(3)]
    repeats = list(render_repeats(o, PARTS, seeds))
    assert len(repeats) == 3
    for a, b in zip(repeats, alone):
        assert a.tobytes() == b.tobytes()
    assert repeats[0].tobytes() != repeats[1].tobytes()   # fresh noise per repeat


def test_groups_scaled_to_zero_give_the_ideal_bytes(ideal):
    off = Realism.realistic()
    for g in ("blur", "illumination", "sensor", "spec", "lens", "particles"):
        off = off.scaled(0.0, group=g)
    o = make_optics(CAM, 0, realism=off)
    for a, b in zip(_card_frame_white(o, PARTS), _card_frame_white(ideal, PARTS)):
        assert a.tobytes() == b.tobytes()


def test_same_seed_same_bytes_and_fixed_patterns_per_camera(image_realistic):
    o = image_realistic
    a = _card_frame_white(o, PARTS)
    b = _card_frame_white(_optics(blur=BlurEffects(), illumination=IlluminationEffects(),
                                  sensor=SensorEffects()), PARTS)
    for x, y in zip(a, b):
        assert x.tobytes() == y.tobytes()
    assert render_frame(o, PARTS, seed=3).tobytes() != a[1].tobytes()
    # One camera's pattern: dead pixels, dead column and hot pixels read the same in the
    # white image, a frame and a dot card (noise-free).
    fp = fixed_pattern(o)
    imgs = [render_white(o, noise=False), render_frame(o, PARTS, seed=2, noise=False),
            render_dotcard(o, 1.0, seed=3, noise=False), render_dark(o, noise=False)]
    for img in imgs[:3]:
        np.testing.assert_array_equal(img.ravel()[fp.dead], imgs[3].ravel()[fp.dead])
        assert (img.ravel()[fp.hot] >= imgs[3].ravel()[fp.hot]).all()   # hot + light
        np.testing.assert_array_equal(img[:, fp.dead_columns], imgs[3][:, fp.dead_columns])
    # Another camera seed: other patterns.
    other = fixed_pattern(_optics(1, sensor=SensorEffects()))
    assert not np.array_equal(other.hot, fp.hot)
    assert np.abs(other.gain - fp.gain).max() > 0.01
    assert not np.array_equal(dust_table(_optics(1, illumination=IlluminationEffects())),
                              dust_table(o))


def test_grid_calibration_on_a_realistic_white_image(ideal, image_realistic):
    from plenoptrack.calibration import calibrate_from_white

    def rms(optics):
        calib, _ = calibrate_from_white(render_white(optics, seed=4), CAM)
        true = optics.true_grid.centers().reshape(-1, 2)
        rows, cols = CAM.sensor_shape_px
        inside = ((true >= 7) & (true <= np.array([rows, cols]) - 8)).all(axis=1)
        d, _ = cKDTree(calib.grid.centers().reshape(-1, 2)).query(true[inside])
        return np.sqrt(np.mean(d ** 2))

    e_ideal, e_real = rms(ideal), rms(image_realistic)
    print(f"grid centre RMS error: ideal {e_ideal:.4f} px, realistic {e_real:.4f} px")
    assert e_ideal < 0.02
    assert e_real < 0.05
