"""The reported uncertainty: scaled least-squares errors plus the DLFC's model error."""

import numpy as np
import pytest

from plenoptrack.locate.uncertainty import (centroid_geometry, image_travel_px,
                                           model_error_mm, reduced_chi2, sampling_groups,
                                           total_sigma, typical_scatter_px2,
                                           with_offset_range, with_unexplained_pixels)


class _Report:
    position_rms_mm = (0.003, 0.004, 0.02)


class _DLFC:
    report = _Report()


def test_total_sigma_adds_the_model_error_in_quadrature():
    stat = np.array([[0.001, 0.002, 0.01], [np.nan, 0.0, 0.0]])
    out = total_sigma(stat, _DLFC(), error_scale=2.0)
    np.testing.assert_allclose(out[0], np.hypot(2 * stat[0], [0.003, 0.004, 0.02]))
    assert np.isnan(out[1, 0])
    np.testing.assert_allclose(out[1, 1:], [0.004, 0.02])
    plain = total_sigma(stat, _DLFC(), error_scale=1.0, include_model_error=False)
    np.testing.assert_array_equal(plain, stat)


def test_model_error_of_a_dlfc_without_it_is_zero():
    class Bare:
        report = None
    np.testing.assert_array_equal(model_error_mm(Bare()), np.zeros(3))
    np.testing.assert_array_equal(model_error_mm(_DLFC()), [0.003, 0.004, 0.02])


class _DepthReport:
    position_rms_mm = (0.003, 0.004, 0.02)
    model_error_by_depth_mm = ((-5.0, 0.002, 0.002, 0.04), (0.0, 0.001, 0.003, 0.01),
                                (5.0, 0.004, 0.004, 0.03))


class _DepthDLFC:
    report = _DepthReport()


def test_model_error_is_taken_at_each_particle_depth():
    z = np.array([-8.0, -5.0, -2.5, 0.0, 1.0, 5.0, 9.0, np.nan])
    got = model_error_mm(_DepthDLFC(), z)
    assert got.shape == (8, 3)
    np.testing.assert_allclose(got[:, 2], [0.04, 0.04, 0.025, 0.01, 0.014, 0.03, 0.03, 0.02])
    np.testing.assert_allclose(got[2, :2], [0.0015, 0.0025])
    np.testing.assert_allclose(got[-1], [0.003, 0.004, 0.02])   # no depth: the overall RMS
    # a calibration without per-depth values gives the overall RMS at every depth
    np.testing.assert_allclose(model_error_mm(_DLFC(), z[:3]), [[0.003, 0.004, 0.02]] * 3)
    stat = np.full((2, 3), 0.01)
    out = total_sigma(stat, _DepthDLFC(), error_scale=1.0, z=np.array([0.0, -5.0]))
    np.testing.assert_allclose(out[:, 2], np.hypot(0.01, [0.01, 0.04]))


def test_reduced_chi2_finds_the_particle_with_twice_the_noise():
    rng = np.random.default_rng(0)
    n = rng.integers(20, 120, 200)
    noise = np.full(200, 0.1)
    noise[17] = 0.2
    residual = np.array([np.sqrt(np.mean(rng.normal(0, s, (k, 2)) ** 2) * 2)
                         for s, k in zip(noise, n)])
    chi2 = reduced_chi2(residual, n)
    assert np.median(chi2) == pytest.approx(1.0)
    assert chi2[17] == pytest.approx(4.0, rel=0.35)
    others = np.delete(chi2, 17)
    assert chi2[17] > others.max()
    assert np.isnan(reduced_chi2(np.array([0.1]), np.array([1]))).all()


def test_excess_scatter_shared_by_views_is_covered():
    """Monte Carlo: a particle's centroids scatter independently (0.1 px) and, for one
    particle in ten, a random 20-80 % of its views is also shifted by one common amount
    (an overlapping image). The position is the mean of the centroids. The excess form
    of total_sigma covers the disturbed particles' errors nearly as a standard uncertainty
    should; the plain form, which averages the excess over the views, is several times
    too small. Clean particles (chi2 about 1) keep the plain sigma, and the frame's errors
    as a whole are covered as a Gaussian's would be."""
    rng = np.random.default_rng(5)
    n, per_frame, frames = 60, 10, 400
    errors, plain, excess, clean_errors, clean_sigma = [], [], [], [], []
    for _ in range(frames):
        obs = rng.normal(0.0, 0.1, (per_frame, n, 2))            # truth at 0
        some = rng.permutation(n)[: rng.integers(n // 5, 4 * n // 5 + 1)]
        obs[0, some] += rng.normal(0.0, 0.5, 2)                   # particle 0 disturbed
        est = obs.mean(axis=1)
        resid = obs - est[:, None, :]
        residual_px = np.sqrt((resid ** 2).sum(axis=(1, 2)) / n)
        views = np.full(per_frame, n, dtype=float)
        chi2 = reduced_chi2(residual_px, views)
        s2 = residual_px ** 2 * n / (2 * n - 3)
        stat = np.repeat(np.sqrt(s2 / n)[:, None], 3, axis=1)     # G = 1 / n for a mean
        a = total_sigma(stat, None, error_scale=1.0, include_model_error=False)
        b = total_sigma(stat, None, error_scale=1.0, include_model_error=False, chi2=chi2,
                        n_views=views)
        errors.append(est[0])
        plain.append(a[0, :2])
        excess.append(b[0, :2])
        clean_errors.append(np.abs(est[1:]))
        clean_sigma.append(b[1:, :2])
    errors, plain, excess = np.abs(errors), np.array(plain), np.array(excess)
    # the excess form: 0.52 / 0.85 / 0.039 within 1 / 2 / beyond 3 sigma here (those
    # disturbed so little that their chi2 stays within chance are not widened)
    assert 0.5 <= np.mean(errors <= excess) <= 0.85
    assert np.mean(errors <= 2 * excess) >= 0.8
    assert np.mean(errors > 3 * excess) < 0.06
    # the plain form: 0.09 within 1 sigma, 0.71 beyond 3 sigma
    assert np.mean(errors <= plain) < 0.2
    assert np.mean(errors > 3 * plain) > 0.5
    # clean particles: a chi2 above 1 by chance widens nothing (0.69 / 0.95 / 0.003 here;
    # 0.79 within 1 sigma when every chi2 above 1 counted)
    clean_errors, clean_sigma = np.concatenate(clean_errors), np.concatenate(clean_sigma)
    assert 0.6 <= np.mean(clean_errors <= clean_sigma) <= 0.76
    assert np.mean(clean_errors <= 2 * clean_sigma) >= 0.92
    # the frame as a whole (one particle in ten disturbed): 0.68 / 0.94 / 0.006 (0.77 /
    # 0.96 / 0.003 when every chi2 above 1 counted)
    everyone = np.concatenate([errors.ravel() / excess.ravel(),
                               clean_errors.ravel() / clean_sigma.ravel()])
    assert 0.6 <= np.mean(everyone <= 1) <= 0.76
    assert np.mean(everyone <= 2) >= 0.92
    assert np.mean(everyone > 3) <= 0.01


def test_excess_form_reduces_to_the_plain_one_and_never_below_it():
    stat = np.full((4, 3), 0.01)
    chi2 = np.array([0.5, 1.0, np.nan, 3.0])
    n = np.array([40.0, 40.0, 40.0, 4.0])        # the last: fewer views than k^2
    plain = total_sigma(stat, _DLFC(), error_scale=2.3)
    got = total_sigma(stat, _DLFC(), error_scale=2.3, chi2=chi2, n_views=n)
    np.testing.assert_allclose(got, plain)
    # chi2 = 2 with 40 views: k^2 / 2 + 40 (1 - c / 2) times the variance of sigma_stat,
    # c = 1 + 2 sqrt(2 k^2 / 77) the chi2 a particle of typical scatter reaches by chance
    c = 1.0 + 2.0 * np.sqrt(2.0 * 2.3 ** 2 / 77.0)
    one = total_sigma(stat[:1], _DLFC(), error_scale=2.3, chi2=np.array([2.0]),
                      n_views=np.array([40.0]))
    expected = np.sqrt(0.01 ** 2 * (2.3 ** 2 / 2 + 40 * (1 - c / 2))
                       + np.array([0.003, 0.004, 0.02]) ** 2)
    np.testing.assert_allclose(one[0], expected)
    # within chance (chi2 1.5 < c = 1.74): the plain form
    np.testing.assert_allclose(
        total_sigma(stat[:1], _DLFC(), error_scale=2.3, chi2=np.array([1.5]),
                    n_views=np.array([40.0])), plain[:1])


class _LinearDLFC:
    """``s = x + z u``, ``t = y + z v``: the image moves by ``z`` view pixels per view."""

    def predict(self, x, y, z, u, v):
        return x + z * u, y + z * v

    def jacobian_xyz(self, x, y, z, u, v):
        x, y, z, u, v = np.broadcast_arrays(x, y, z, u, v)
        jac = np.zeros(x.shape + (2, 3))
        jac[..., 0, 0] = jac[..., 1, 1] = 1.0
        jac[..., 0, 2], jac[..., 1, 2] = u, v
        return jac


def _disc_views(radius=6):
    g = np.arange(-radius, radius + 1)
    uu, vv = np.meshgrid(g, g)
    disc = uu ** 2 + vv ** 2 <= radius ** 2
    return np.column_stack([uu[disc], vv[disc]]).astype(float)


def test_image_travel_is_the_diameter_the_image_sweeps():
    uv = _disc_views(6)
    n = len(uv)
    positions = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 0.25], [0.0, 0.0, -0.5], [5.0, 5.0, 1.0]])
    owner = np.repeat(np.arange(3), n)                   # particle 3 has no centroids
    travel = image_travel_px(_LinearDLFC(), positions, owner, np.tile(uv, (3, 1)))
    # a disc of radius 6 views: |z| * 12 view pixels across (within the grid's coarseness)
    np.testing.assert_allclose(travel[:3], [0.0, 3.0, 6.0], rtol=0.05, atol=1e-12)
    assert np.isnan(travel[3])
    # centroids owned by no particle (-1) are ignored
    more = image_travel_px(_LinearDLFC(), positions, np.append(owner, [-1, -1]),
                           np.vstack([np.tile(uv, (3, 1)), [[50.0, 0.0], [-50.0, 0.0]]]))
    np.testing.assert_allclose(more, travel)
    np.testing.assert_allclose(sampling_groups(np.array([0.0, 1.0, np.nan])), [1.0, 9.0, np.nan])


def test_sampling_error_term_adds_the_views_that_share_it():
    stat = np.full((3, 3), 0.01)
    n = np.array([100.0, 100.0, 100.0])
    travel = np.array([0.0, 4.5, np.nan])
    got = total_sigma(stat, None, error_scale=2.0, include_model_error=False, n_views=n,
                      travel_px=travel)
    np.testing.assert_allclose(got[:, 0], 0.01 * np.sqrt([4.0 + 100.0, 4.0 + 1.0, 4.0]))
    # the shared part is sized by the frame's typical scatter: chi2 = 0.25 -> 4 times
    low = total_sigma(stat[:1], None, error_scale=2.0, include_model_error=False,
                      n_views=n[:1], travel_px=np.array([4.5]), chi2=np.array([0.25]))
    np.testing.assert_allclose(low[0, 0], 0.01 * np.sqrt(4.0 + 4.0))


def test_image_fit_sigma_keeps_the_excess_scatter_but_not_the_typical_scale():
    """A sigma from an image fit (``from_centroids`` False) is not the centroids'
    scatter, so the shared sampling error is sized by that sigma itself, not by the
    frame's typical scatter 1 / chi2; the centroids' excess scatter (chi2 > 1) still
    counts as shared by all views."""
    stat = np.full((2, 3), 0.01)
    n = np.array([100.0, 100.0])
    chi2 = np.array([0.25, 4.0])
    travel = np.array([4.5, 4.5])                    # g = 100: n / g = 1
    kw = dict(error_scale=2.0, include_model_error=False, n_views=n, chi2=chi2,
              travel_px=travel)
    fit = total_sigma(stat, None, from_centroids=np.array([False, False]), **kw)
    # chi2 0.25: k^2 + n / g, no 1 / chi2; chi2 4: (k^2 + n / g) / 4 + n (1 - c / 4),
    # c = 1 + 2 sqrt(2 k^2 / 197) the chi2 reached by chance
    shared = 100.0 * (1.0 - (1.0 + 2.0 * np.sqrt(8.0 / 197.0)) / 4.0)
    np.testing.assert_allclose(fit[:, 0], 0.01 * np.sqrt([4.0 + 1.0, 5.0 / 4 + shared]))
    cent = total_sigma(stat, None, from_centroids=np.array([True, True]), **kw)
    np.testing.assert_allclose(cent[:, 0],
                               0.01 * np.sqrt([4.0 + 4.0, (4.0 + 0.25) / 4 + shared]))
    np.testing.assert_allclose(total_sigma(stat, None, **kw), cent)


def test_unexplained_pixels_scale_sigma_by_the_model_error_beyond_an_explained_fit():
    """A fit leaving twice the model error of an explained one doubles sigma_stat on
    every axis; explained fits (at or below the threshold) and particles never fitted
    (NaN) keep theirs."""
    stat = np.array([[0.001, 0.002, 0.02]] * 4)
    error = np.array([0.16, 0.08, 0.03, np.nan])
    out = with_unexplained_pixels(stat, error, 0.08)
    np.testing.assert_allclose(out[0], 2.0 * stat[0])
    np.testing.assert_array_equal(out[1:], stat[1:])


def test_sampling_error_covers_particles_near_the_focal_plane():
    """Monte Carlo: each centroid is pulled towards the nearest view-pixel centre
    (pixel-locking, 0.08 px) plus independent 0.03 px noise; positions are solved by
    least squares. Near the focal plane (image travel below 1 view pixel) every view
    sees the image at the same sub-pixel phase, so the pull is shared: the residuals do
    not show it and the plain least-squares sigma leaves most of those particles beyond
    3 sigma. With the sampling term they are covered; far from focus the pull averages
    out and the term adds little."""
    rng = np.random.default_rng(3)
    uv = _disc_views(6)
    n = len(uv)
    design = np.zeros((2 * n, 3))
    design[:n, 0] = design[n:, 1] = 1.0
    design[:n, 2], design[n:, 2] = uv[:, 0], uv[:, 1]
    cov = np.linalg.inv(design.T @ design)
    errors, plain, sampled, travels = [], [], [], []
    for _ in range(40):
        xyz = np.column_stack([rng.uniform(0, 1, (50, 2)), rng.uniform(-0.4, 0.4, 50)])
        st = xyz[:, None, :2] + xyz[:, None, 2:] * uv[None]                   # (P, n, 2)
        obs = st - 0.08 * np.sin(2 * np.pi * st) + rng.normal(0, 0.03, st.shape)
        rhs = np.concatenate([obs[..., 0], obs[..., 1]], axis=1)               # (P, 2n)
        sol = rhs @ np.linalg.pinv(design).T
        ssr = ((rhs - sol @ design.T) ** 2).sum(axis=1)
        stat = np.sqrt(ssr[:, None] / (2 * n - 3) * np.diag(cov))
        views = np.full(50, float(n))
        chi2 = reduced_chi2(np.sqrt(ssr / n), views)
        travel = image_travel_px(_LinearDLFC(), sol, np.repeat(np.arange(50), n),
                                 np.tile(uv, (50, 1)))
        kw = dict(error_scale=1.0, include_model_error=False, chi2=chi2, n_views=views)
        plain.append(total_sigma(stat, None, **kw))
        sampled.append(total_sigma(stat, None, travel_px=travel, **kw))
        errors.append(np.abs(sol - xyz))
        travels.append(travel)
    errors, plain, sampled = map(np.concatenate, (errors, plain, sampled))
    near = np.concatenate(travels) < 1.0
    assert near.sum() > 200
    assert np.mean(errors[near] > 3 * plain[near]) > 0.5          # 0.64-0.76 per axis
    assert np.mean(errors[near] > 3 * sampled[near]) < 0.03        # 0.000-0.007
    assert 0.4 <= np.mean(errors[near] <= sampled[near]) <= 0.9    # 0.54-0.63
    # far from focus the pull averages out and the term fades to n / g (1.4 views per
    # group at 4 px of travel) against k^2 (1 here; the default 5.3 would make it 1.12)
    far = np.concatenate(travels) > 4.0
    assert far.sum() > 200
    assert np.median(sampled[far] / plain[far]) < 1.6                # 1.46
    assert np.mean(errors[far] > 3 * sampled[far]) < 0.01


def test_reduced_chi2_typical_scatter_from_chosen_particles():
    """The frame's typical scatter can be taken from some particles only (those of the
    frame's own centroids); the others are still measured against it."""
    from plenoptrack.locate.uncertainty import reduced_chi2

    residual = np.array([1.0, 1.0, 1.0, 3.0, 3.0, 3.0, 3.0])
    n = np.full(7, 10.0)
    everyone = reduced_chi2(residual, n)
    np.testing.assert_allclose(everyone, (residual / 3.0) ** 2)     # median s2 is 9's
    own = np.array([True, True, True, False, False, False, False])
    chosen = reduced_chi2(residual, n, typical_of=own)
    np.testing.assert_allclose(chosen, residual ** 2)
    np.testing.assert_allclose(reduced_chi2(residual, n, typical_of=np.zeros(7, bool)),
                               everyone)


def test_centroid_geometry_is_the_inverse_normal_matrix_of_the_particle_views():
    """Against the explicit design matrix of ``s = x + z u, t = y + z v``: the diagonal
    of ``(J^T J)^-1`` over each particle's own centroids; NaN for one centroid."""
    uv = _disc_views(4)
    n = len(uv)
    positions = np.array([[0.0, 0.0, 0.1], [1.0, 2.0, -0.3], [0.0, 0.0, 0.0]])
    owner = np.concatenate([np.repeat(0, n), np.repeat(1, n - 5), [2], [-1]])
    views = np.vstack([uv, uv[5:], uv[:1], [[9.0, 9.0]]])
    got = centroid_geometry(_LinearDLFC(), positions, owner, views)
    for row, use in ((0, uv), (1, uv[5:])):
        design = np.zeros((2 * len(use), 3))
        design[:len(use), 0] = design[len(use):, 1] = 1.0
        design[:len(use), 2], design[len(use):, 2] = use[:, 0], use[:, 1]
        np.testing.assert_allclose(got[row], np.diag(np.linalg.inv(design.T @ design)))
    assert np.isnan(got[2]).all()


def test_typical_scatter_is_what_reduced_chi2_divides_by():
    residual = np.array([0.1, 0.2, 0.3, 0.05, np.nan])
    n = np.array([10.0, 20.0, 30.0, 1.0, 10.0])        # one view: no degrees of freedom
    s0 = typical_scatter_px2(residual, n)
    s2 = residual ** 2 * n / (2 * n - 3)
    np.testing.assert_allclose(s0, np.median(s2[:3]))
    np.testing.assert_allclose(reduced_chi2(residual, n)[:3], s2[:3] / s0)
    assert np.isnan(typical_scatter_px2(np.array([0.1]), np.array([1.0])))


def test_image_fit_sampling_error_is_sized_by_the_typical_centroid_scatter():
    """With ``typical_sigma`` a refined particle's shared sampling error is ``n / g``
    times the variance its centroid solve would have at the frame's typical scatter,
    whatever its image fit's (pixel-noise) sigma; a centroid-solved particle is
    unchanged by it, and a NaN falls back to the fit's own sigma."""
    stat = np.array([[0.001, 0.001, 0.004]] * 3)
    typical = np.array([[0.003, 0.002, 0.02]] * 3)
    typical[2] = np.nan
    n = np.full(3, 100.0)
    kw = dict(error_scale=2.0, include_model_error=False, n_views=n, chi2=np.full(3, 0.5),
              travel_px=np.zeros(3))                   # g = 1: n / g = 100
    from_centroids = np.array([False, True, False])
    got = total_sigma(stat, None, from_centroids=from_centroids, typical_sigma=typical, **kw)
    np.testing.assert_allclose(got[0], np.sqrt(4.0 * stat[0] ** 2 + 100.0 * typical[0] ** 2))
    before = total_sigma(stat, None, from_centroids=from_centroids, **kw)
    np.testing.assert_allclose(got[1:], before[1:])
    np.testing.assert_allclose(before[2], stat[2] * np.sqrt(4.0 + 100.0))


def test_an_offset_range_adds_the_rms_of_a_shift_up_to_the_offset():
    """A particle off by anything from none to the offset (a uniform fraction: half a
    companion's offset, or the whole disagreement of a fit and a centroid solution) is
    off by that shift: its RMS, per axis, is added in quadrature; rows without one (NaN)
    keep their sigma."""
    sigma = np.array([[0.004, 0.003, 0.05], [0.004, 0.003, 0.05], [0.01, 0.01, 0.1]])
    offset = np.array([[0.1, -0.05, 0.75], [np.nan] * 3, [0.0, 0.0, 0.0]])
    out = with_offset_range(sigma, offset)
    np.testing.assert_allclose(out[0], np.sqrt(sigma[0] ** 2 + offset[0] ** 2 / 3))
    rng = np.random.default_rng(0)
    shift = rng.uniform(0.0, 1.0, (200_000, 1)) * offset[0]
    rms = np.sqrt(np.mean(shift ** 2, axis=0))
    np.testing.assert_allclose(out[0], np.hypot(sigma[0], rms), rtol=2e-3)
    np.testing.assert_array_equal(out[1:], sigma[1:])
    # a particle off by such a shift lies within 2 sigma of it (uniform: at most sqrt 3)
    assert np.all(np.abs(shift).max(axis=0) <= 2 * out[0])
