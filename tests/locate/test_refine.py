"""Image-model refinement of overlapping particles (plenoptrack.locate.refine)."""

import math

import numpy as np
import pandas as pd
import pytest

from plenoptrack.evaluate import match_particles
from plenoptrack.locate.perspective import PerspectiveLocator, locate_frame
from plenoptrack.locate.triangulate import TriangulationFlag
from plenoptrack.locate.refine import (EDGE_PX, HEX_RESAMPLING_PX2, ImageEdge,
                                       _fit_pixels, _masked_row_percentile, _patch_masks,
                                       _patches, _pixel_normal_equations, _robust_sd,
                                       disc_image, fit_images, overlap_fraction)
from plenoptrack.simulate import make_scene, render_frame
from scipy.special import erfc, ndtr, ndtri, owens_t

EDGE_WIDTHS = np.array([[0.75, 0.45], [0.5, 0.62], [0.6, 0.6]])
"""Edge widths ``(w_s, w_t)`` of the images in the kernel tests: wider along s, wider
along t, and round."""


def anisotropic_disc(ds, dt, radius, contrast, w_s, w_t):
    """``1 - c erfc(x) / 2`` with ``x = (rho - r) / (sqrt 2 w)`` and the edge width of the
    pixel's direction, ``w^2 = (w_s^2 ds^2 + w_t^2 dt^2) / rho^2``, in plain numpy."""
    rho = np.hypot(ds, dt)
    width = np.sqrt((w_s ** 2 * ds ** 2 + w_t ** 2 * dt ** 2) / np.maximum(rho, 1e-12) ** 2)
    return 1.0 - contrast * 0.5 * erfc((rho - radius) / (math.sqrt(2.0) * width))


def bivariate_normal_cdf(h, k, r):
    """``P(Z1 < h, Z2 < k)`` for standard normals of correlation ``r``, elementwise, by
    Owen's T function (Owen 1956): ``Phi2 = (Phi(h) + Phi(k)) / 2 - T(h, a_h) - T(k, a_k)
    - beta``, ``beta = 1/2`` where ``h k < 0`` (or one is 0 and their sum negative)."""
    h, k, r = np.broadcast_arrays(*map(np.asarray, (h, k, r)))
    s = np.sqrt(1.0 - r ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        a_h = np.where(h != 0, (k - r * h) / (h * s), np.inf * np.sign(k - r * h))
        a_k = np.where(k != 0, (h - r * k) / (k * s), np.inf * np.sign(h - r * k))
    beta = np.where((h * k < 0) | ((h * k == 0) & (h + k < 0)), 0.5, 0.0)
    return 0.5 * (ndtr(h) + ndtr(k)) - owens_t(h, a_h) - owens_t(k, a_k) - beta


def blurred_union(offsets, rc, edge):
    """Transmission of two overlapping images as the blurred union of their shadows, in
    plain numpy: ``1 - c0 D0 - c1 D1 + c0 c1 B``, ``D = Phi(h)`` each image's blurred
    disc, ``B = Phi2(h0, h1; r)`` the chance of lying inside both, ``r`` the correlation
    of the two edges' normal offsets under the blur (edge widths ``edge`` (2, 2));
    ``B = D0 D1`` (the product) wherever either ``D`` is within 1e-9 of 0 or 1."""
    (ds0, dt0), (ds1, dt1) = offsets
    darkness, h = [], []
    for (ds, dt), (r_, c), (w_s, w_t) in zip(offsets, rc, edge):
        d = 1.0 - anisotropic_disc(ds, dt, r_, 1.0, w_s, w_t)
        darkness.append(d)
        h.append(ndtri(d))
    q0 = np.hypot(edge[0, 0] * ds0, edge[0, 1] * dt0)
    q1 = np.hypot(edge[1, 0] * ds1, edge[1, 1] * dt1)
    r = (edge[0, 0] * edge[1, 0] * ds0 * ds1 + edge[0, 1] * edge[1, 1] * dt0 * dt1) / (q0 * q1)
    r = np.clip(r, -0.999999, 0.999999)
    band = np.all([(d > 1e-9) & (d < 1 - 1e-9) for d in darkness], axis=0)
    both = np.where(band, bivariate_normal_cdf(np.where(band, h[0], 0.0),
                                               np.where(band, h[1], 0.0), r),
                    darkness[0] * darkness[1])
    (c0, c1) = rc[:, 1]
    return 1.0 - c0 * darkness[0] - c1 * darkness[1] + c0 * c1 * both


class LinearCalibration:
    """A stand-in DLFC: ``s = 50 + 10 x + 0.3 z u``, ``t = 40 + 10 y + 0.3 z v``."""

    def predict(self, x, y, z, u, v):
        x, y, z, u, v = np.broadcast_arrays(*map(np.asarray, (x, y, z, u, v)))
        return 50 + 10 * x + 0.3 * z * u, 40 + 10 * y + 0.3 * z * v

    def predict_with_jacobian(self, x, y, z, u, v):
        x, y, z, u, v = np.broadcast_arrays(*map(np.asarray, (x, y, z, u, v)))
        s, t = self.predict(x, y, z, u, v)
        jac = np.zeros(x.shape + (2, 3))
        jac[..., 0, 0] = 10
        jac[..., 0, 2] = 0.3 * u
        jac[..., 1, 1] = 10
        jac[..., 1, 2] = 0.3 * v
        return np.stack([s, t], axis=-1), jac

    # the view-factorised interface of DLFC, on the same map: basis (1, u, v), monomials
    # (1, x, y, z) of the position
    def view_basis(self, u, v):
        return np.c_[np.ones(len(u)), u, v].astype(float)

    def predict_in_views(self, xyz, basis, *, jacobian=False):
        xyz = np.reshape(xyz, (-1, 3))
        st, jac = self.predict_with_jacobian(xyz[:, None, 0], xyz[:, None, 1], xyz[:, None, 2],
                                             basis[None, :, 1], basis[None, :, 2])
        return (st, jac) if jacobian else st

    @property
    def view_model(self):
        xyz_e = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.int64)
        tensor = np.zeros((4, 3, 2))
        tensor[0, 0] = 50.0, 40.0          # constant
        tensor[1, 0, 0] = tensor[2, 0, 1] = 10.0   # 10 x, 10 y
        tensor[3, 1, 0] = tensor[3, 2, 1] = 0.3    # 0.3 z u, 0.3 z v
        return xyz_e, tensor, np.zeros(3), np.ones(3)


def _views():
    u, v = np.meshgrid(np.arange(-4, 5), np.arange(-4, 5))
    views_uv = np.c_[u.ravel(), v.ravel()].astype(float)
    return views_uv, (views_uv[:, ::-1] + 4).astype(int)   # (v, u) index


def _render(dlfc, xyz, rc, views_uv, view_rc, noise, seed=0):
    data = np.ones((9, 9, 90, 110))
    tt, ss = np.mgrid[0:90, 0:110].astype(float)
    for (u, v), (vi, ui) in zip(views_uv, view_rc):
        for (x, y, z), (r, c) in zip(xyz, rc):
            s, t = dlfc.predict(x, y, z, u, v)
            data[vi, ui] *= disc_image(np.hypot(ss - s, tt - t), r, c)[0]
    return data + np.random.default_rng(seed).normal(0, noise, data.shape)


def test_disc_image_derivatives_match_finite_differences():
    rho = np.linspace(0, 5, 41)
    f, d_rho, d_r, d_c = disc_image(rho, 2.0, 0.9)
    h = 1e-6
    assert np.allclose(d_rho, (disc_image(rho + h, 2.0, 0.9)[0] - f) / h, atol=1e-5)
    assert np.allclose(d_r, (disc_image(rho, 2.0 + h, 0.9)[0] - f) / h, atol=1e-5)
    assert np.allclose(d_c, (disc_image(rho, 2.0, 0.9 + h)[0] - f) / h, atol=1e-5)
    assert f[0] < 0.11 and f[-1] > 0.999   # dark inside, background outside


@pytest.mark.parametrize("k, union", [(1, True), (2, False), (2, True)])
def test_normal_equations_match_a_finite_difference_jacobian(k, union):
    """The compiled cost, J^T J and J^T r against the model built from anisotropic_disc (a
    different edge width along s and t for each image; two images as their product, or
    with ``union`` as their blurred union) and differentiated numerically with respect
    to (x, y, z, r, c) through a linear DLFC."""
    dlfc = LinearCalibration()
    views_uv, _ = _views()
    rng = np.random.default_rng(k)
    n = 15
    origin = np.c_[rng.integers(40, 45, len(views_uv)), rng.integers(30, 35, len(views_uv))]
    origin = origin.astype(float)
    y = rng.uniform(0.2, 1.1, (len(views_uv), n, n))
    held = rng.uniform(0.8, 1.0, y.shape)
    fit = rng.uniform(size=y.shape) < 0.8
    theta = np.array([[0.6, 0.3, 1.5, 2.5, 0.9], [0.8, 0.2, -1.0, 1.8, 0.7]])[:k]
    tt, ss = np.mgrid[0:n, 0:n].astype(float)
    ss = origin[:, 0, None, None] + ss
    tt = origin[:, 1, None, None] + tt

    def model(th):
        offsets = []
        for x, yy, z, *_ in th:
            s, t = dlfc.predict(x, yy, z, views_uv[:, 0], views_uv[:, 1])
            offsets.append((ss - s[:, None, None], tt - t[:, None, None]))
        if k == 2 and union:
            return (held * blurred_union(offsets, th[:, 3:], EDGE_WIDTHS[:2]))[fit] - y[fit]
        out = held.copy()
        for (ds, dt), (_, _, _, r, c), (w_s, w_t) in zip(offsets, th, EDGE_WIDTHS):
            out *= anisotropic_disc(ds, dt, r, c, w_s, w_t)
        return out[fit] - y[fit]

    h = 1e-6
    jac = np.stack([(model(theta + h * np.eye(5 * k)[i].reshape(k, 5)) - model(theta)) / h
                    for i in range(5 * k)], axis=1)
    st, dst = dlfc.predict_with_jacobian(theta[:, None, 0], theta[:, None, 1],
                                         theta[:, None, 2], views_uv[None, :, 0],
                                         views_uv[None, :, 1])
    cost, jtj, jtr, meat = _pixel_normal_equations(*_fit_pixels(origin, y, held, fit),
                                                   np.ascontiguousarray(st),
                                                   np.ascontiguousarray(dst),
                                                   theta[:, 3:].copy(), EDGE_WIDTHS[:k], union)
    res = model(theta)
    assert cost == pytest.approx(res @ res, rel=1e-6)
    view_of = np.broadcast_to(np.arange(len(views_uv))[:, None, None], y.shape)[fit]
    scores = np.array([jac[view_of == v].T @ res[view_of == v] for v in range(len(views_uv))])
    assert np.allclose(meat, scores.T @ scores, rtol=1e-3, atol=1e-3 * np.abs(meat).max())
    assert np.allclose(jtr, jac.T @ res, rtol=1e-3, atol=1e-3 * np.abs(jtr).max())
    assert np.allclose(jtj, jac.T @ jac, rtol=1e-3, atol=1e-3 * np.abs(jtj).max())


def test_the_bivariate_normal_matches_owens_t():
    from plenoptrack.locate.refine import _bivariate_normal_cdf

    rng = np.random.default_rng(3)
    h, k = rng.normal(0, 2, (2, 400))
    r = np.r_[rng.uniform(-0.99, 0.99, 200), rng.uniform(0.99, 0.999999, 100),
              -rng.uniform(0.99, 0.999999, 100)]
    ours = np.array([_bivariate_normal_cdf(*args) for args in zip(h, k, r)])
    assert np.allclose(ours, bivariate_normal_cdf(h, k, r), atol=3e-5, rtol=0)
    # the limits the locator relies on: independent edges, and edges running together
    assert _bivariate_normal_cdf(0.3, -0.4, 0.0) == pytest.approx(ndtr(0.3) * ndtr(-0.4),
                                                                 abs=1e-7)
    assert _bivariate_normal_cdf(0.3, -0.4, 0.999999) == pytest.approx(ndtr(-0.4), abs=1e-3)


@pytest.mark.parametrize("contrast", [1.0, 0.8])
def test_two_images_on_one_spot_darken_the_pixels_as_one_opaque_shadow(contrast):
    """Two identical images at one place: the blurred union of two opaque shadows is the
    shadow of one. (The product of two blurred discs squares the edge's transmission and
    widens the dark disc by about half an edge width; a pair fitted with it was pushed
    apart in depth.) Where partly transparent images overlap, their transmissions
    multiply."""
    views_uv, _ = _views()
    n = 15
    origin = np.zeros((len(views_uv), 2))
    st = np.tile([7.2, 6.9], (1, len(views_uv), 1))
    jac = np.zeros((1, len(views_uv), 2, 3))
    held = np.ones((len(views_uv), n, n))
    fit = np.ones(held.shape, dtype=bool)
    rc = np.array([[3.5, contrast]])
    tt, ss = np.mgrid[0:n, 0:n].astype(float)
    single = anisotropic_disc(ss - 7.2, tt - 6.9, 3.5, contrast, *EDGE_WIDTHS[0])

    def cost(y, k):
        return _pixel_normal_equations(*_fit_pixels(origin, y, held, fit),
                                       np.concatenate([st] * k), np.concatenate([jac] * k),
                                       np.repeat(rc, k, axis=0),
                                       np.repeat(EDGE_WIDTHS[:1], k, axis=0), True)[0]

    data = np.broadcast_to(single, held.shape).copy()
    assert cost(data, 1) < 1e-9                  # the kernel's one image is anisotropic_disc
    if contrast == 1.0:
        product_misfit = len(views_uv) * np.sum((single ** 2 - single) ** 2)
        assert product_misfit > 1.0
        assert cost(data, 2) < 1e-4 * product_misfit
    else:
        # partly transparent: inside both discs (1 - c)^2, at their common edge between
        # (1 - c D)^2 and 1 - c D
        zeros = np.zeros(held.shape)             # cost = sum of the model's squares
        assert cost(zeros, 1) * (1 - contrast) ** 2 < cost(zeros, 2) < cost(zeros, 1)
        assert cost(zeros, 2) > len(views_uv) * np.sum(single ** 4)


def test_patch_masks_against_disc_image():
    rng = np.random.default_rng(5)
    n, views = 13, 4
    origin = rng.uniform(0, 5, (views, 2)).round()
    st_held = origin[None] + rng.uniform(0, 13, (3, views, 2))
    st_held[2] += 40.0                      # a held image far outside every patch
    rc_held = np.array([[2.0, 0.9], [1.5, 0.6], [2.0, 1.0]])
    st_free = origin[None] + rng.uniform(3, 10, (1, views, 2))
    fixed, near, fit = _patch_masks(origin, n, st_held, rc_held, st_free, np.array([2.5]),
                                    3.0, EDGE_WIDTHS)
    tt, ss = np.mgrid[0:n, 0:n].astype(float)
    for v in range(views):
        s, t = origin[v, 0] + ss, origin[v, 1] + tt
        rho = [np.hypot(s - st_held[q, v, 0], t - st_held[q, v, 1]) for q in range(3)]
        expected = np.prod([anisotropic_disc(s - st_held[q, v, 0], t - st_held[q, v, 1],
                                             *rc_held[q], *EDGE_WIDTHS[q])
                            for q in range(3)], axis=0)
        rho_free = np.hypot(s - st_free[0, v, 0], t - st_free[0, v, 1])
        assert np.array_equal(fit[v], rho_free <= 5.5)
        # the held image is what the model reads: on the fitted pixels; 1 elsewhere
        assert fit[v].any() and (~fit[v]).any()
        assert np.allclose(fixed[v][fit[v]], expected[fit[v]], atol=1e-6)
        assert np.all(fixed[v][~fit[v]] == 1.0)
        assert np.array_equal(near[v], (rho_free < 4.5) | np.any(
            [rho[q] < rc_held[q, 0] + 2 for q in range(3)], axis=0))


def test_image_edge_widths_split_the_measured_blur_by_the_lattice():
    """w_s w_t is the calibration's blur at the depth (interpolated between its card
    depths), w_s^2 - w_t^2 the hexagonal resampling; a rectangular lattice is round, and
    without a measured blur the widths multiply to EDGE_PX^2."""
    rows = np.array([[-10.0, 0.7], [0.0, 0.5], [10.0, 0.7]])
    z = np.array([-10.0, -5.0, 0.0, 3.0, 20.0, np.nan])
    blur = np.array([0.7, 0.6, 0.5, 0.56, 0.7])
    hexagonal = ImageEdge.of_frame("hex", rows).widths(z)
    assert hexagonal.shape == (6, 2) and np.all(np.isfinite(hexagonal))
    np.testing.assert_allclose(np.prod(hexagonal[:5], axis=1), blur ** 2)
    np.testing.assert_allclose(np.diff(hexagonal[:, ::-1] ** 2, axis=1)[:, 0],
                               HEX_RESAMPLING_PX2)
    assert np.all(hexagonal[:, 0] > hexagonal[:, 1])
    np.testing.assert_allclose(ImageEdge.of_frame("rect", rows).widths(z[:5]),
                               np.c_[blur, blur])
    np.testing.assert_allclose(ImageEdge().widths(z), EDGE_PX)
    no_blur = ImageEdge.of_frame("hex", None).widths(z)
    np.testing.assert_allclose(np.prod(no_blur, axis=1), EDGE_PX ** 2)


@pytest.mark.parametrize("camera, anisotropy", [("small", HEX_RESAMPLING_PX2),
                                                ("small-rect", 0.0)])
def test_hexagonal_decoding_widens_image_edges_along_s(camera, anisotropy):
    """A 1 mm particle rendered by the simulator (ideal optics, no noise) and decoded:
    its images, fitted with a free edge width along s and along t, are wider along s by
    about HEX_RESAMPLING_PX2 on a hexagonal lattice and round on a rectangular one."""
    from scipy.optimize import least_squares

    from plenoptrack import preset
    from plenoptrack.lightfield import decode
    from plenoptrack.simulate import make_optics

    optics = make_optics(preset(camera), seed=0)
    truth = pd.DataFrame({"x": [0.0], "y": [0.0], "z": [0.0], "diameter": [1.0]})
    raw = render_frame(optics, truth, seed=1, noise=False)
    lf = decode(raw, optics.true_grid, white=render_frame(optics, None, seed=1, noise=False))
    tt, ss = np.mgrid[-7:8, -7:8].astype(float)
    excess = []
    for vi, ui in list(zip(*np.nonzero(lf.view_mask)))[::4]:
        view = np.where(lf.spatial_mask, lf.data[vi, ui], np.nan).astype(float)
        i, j = np.unravel_index(np.nanargmin(view), view.shape)
        patch = view[i - 7:i + 8, j - 7:j + 8]

        def residual(p):
            s0, t0, r, c, w_s, w_t, level = p
            return (level * anisotropic_disc(ss - s0, tt - t0, r, c, w_s, w_t) - patch).ravel()

        fit = least_squares(residual, [0, 0, 3, 0.9, 0.6, 0.6, np.percentile(patch, 90)],
                            bounds=([-3, -3, 0.5, 0.1, 0.1, 0.1, 0], [3, 3, 8, 1.2, 3, 3, 5]))
        excess.append(fit.x[4] ** 2 - fit.x[5] ** 2)
    assert len(excess) > 20
    assert abs(np.median(excess) - anisotropy) < 0.1


def test_edge_widths_along_s_and_t_remove_the_bias_of_a_round_edge():
    """Two images overlapping along s, their edges wider along s than along t (as a
    hexagonal lattice decodes them): a round edge misplaces them, the measured widths
    recover them."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 1.0], [0.32, 0.02, -1.0]])
    rc = np.array([[2.0, 0.9], [2.0, 0.9]])
    widths = (0.75, 0.4)
    data = np.ones((9, 9, 90, 110))
    tt, ss = np.mgrid[0:90, 0:110].astype(float)
    for (u, v), (vi, ui) in zip(views_uv, view_rc):
        for (x, y, z), (r, c) in zip(truth, rc):
            s, t = dlfc.predict(x, y, z, u, v)
            data[vi, ui] *= anisotropic_disc(ss - s, tt - t, r, c, *widths)
    data += np.random.default_rng(0).normal(0, 0.005, data.shape)
    measured = ImageEdge(np.array([[0.0, np.sqrt(widths[0] * widths[1])]]),
                         widths[0] ** 2 - widths[1] ** 2)
    errors = {}
    for name, edge in (("round", ImageEdge()), ("measured", measured)):
        fit = fit_images(dlfc, views_uv, view_rc, data, truth, rc, np.zeros((0, 3)),
                         np.zeros((0, 2)), edge=edge)
        errors[name] = np.abs(fit.params[:, :3] - truth).max()
    assert errors["measured"] < 0.002
    assert errors["round"] > 3 * errors["measured"]


@pytest.mark.parametrize("radius, w_s, w_t", [(1.2, 0.65, 0.40), (0.8, 0.65, 0.40),
                                              (3.0, 0.5, 0.5), (6.0, 0.9, 0.6)])
def test_area_radius_is_the_radius_of_the_models_summed_darkness(radius, w_s, w_t):
    """The fitted image model's darkness summed over a fine grid is c pi R^2 with R
    ImageEdge.area_radius of its radius, at the edge widths of the image's depth."""
    edge = ImageEdge(np.array([[-5.0, np.sqrt(w_s * w_t)], [5.0, np.sqrt(w_s * w_t)]]),
                     w_s ** 2 - w_t ** 2)
    np.testing.assert_allclose(edge.widths([0.0])[0], [w_s, w_t])
    step = 0.01
    grid = np.arange(-radius - 8, radius + 8, step)
    ss, tt = np.meshgrid(grid, grid)
    darkness = 1.0 - anisotropic_disc(ss, tt, radius, 0.7, w_s, w_t)
    summed = darkness.sum() * step ** 2
    r_area = edge.area_radius(np.array([radius]), np.array([0.0]))[0]
    np.testing.assert_allclose(0.7 * np.pi * r_area ** 2, summed, rtol=2e-3)
    assert r_area > radius                 # the edge's spread lies mostly outside r
    assert np.isnan(edge.area_radius(np.array([np.nan]), np.array([0.0]))[0])


@pytest.mark.parametrize("silhouette, blur", [(1.3, 0.55), (2.5, 0.55), (1.6, 0.8)])
def test_a_fitted_image_casts_the_shadow_of_the_blurred_silhouette(silhouette, blur):
    """Views of an opaque disc blurred by a Gaussian, rendered by supersampling and
    filtering (not with the fit's own model): the fitted image's shadow, ``c pi R^2``
    with ``R`` its area radius, is the disc's within 4 % (2 % in radius), at sizes where
    the fitted radius alone misses it by 6-22 % in area."""
    from scipy.ndimage import gaussian_filter

    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    xyz, sub = np.array([[0.0, 0.0, 2.0]]), 8
    data = np.ones((9, 9, 90, 110))
    fine = (np.arange(90 * sub) + 0.5) / sub - 0.5, (np.arange(110 * sub) + 0.5) / sub - 0.5
    for (u, v), (vi, ui) in zip(views_uv, view_rc):
        s, t = dlfc.predict(*xyz[0], u, v)
        ss, tt = np.meshgrid(fine[1] - s, fine[0] - t)
        shadow = gaussian_filter((np.hypot(ss, tt) < silhouette).astype(float), blur * sub)
        data[vi, ui] -= shadow.reshape(90, sub, 110, sub).mean(axis=(1, 3))
    data += np.random.default_rng(0).normal(0, 0.002, data.shape)
    edge = ImageEdge(np.array([[0.0, blur]]))
    fit = fit_images(dlfc, views_uv, view_rc, data, xyz, np.array([[1.5, 0.9]]),
                     np.zeros((0, 3)), np.zeros((0, 2)), edge=edge)
    radius, contrast = fit.params[0, 3:]
    shadow_radius = math.sqrt(contrast) * edge.area_radius(np.array([radius]), xyz[:, 2])[0]
    assert abs(shadow_radius / silhouette - 1) < 0.02
    assert abs(math.sqrt(contrast) * radius / silhouette - 1) > 0.02   # r alone does not


def test_the_vectorised_exponential_matches_math_exp():
    from plenoptrack.locate.refine import _EXP_LIMIT, _exp_neg_squares

    rng = np.random.default_rng(5)
    x = np.r_[rng.normal(0, 3, 20000), rng.uniform(-26.6, 26.6, 20000),
              np.linspace(-26.6, 26.6, 4001), 0.0, -0.0]
    out = np.full(len(x) + 3, -1.0)
    _exp_neg_squares(x, out, np.empty(len(x) + 3, dtype=np.int64), len(x))
    exact = np.exp(-x * x)
    ulp = np.spacing(exact)
    assert np.max(np.abs(out[:len(x)] - exact) / ulp) <= 2.0
    assert out[len(x) - 2] == 1.0 and out[len(x) - 1] == 1.0       # exp(0) exactly
    assert np.all(out[len(x):] == -1.0)            # only the first m are written
    # beyond the cap (and for inf or NaN) the value is exp(-cap): about 3e-308, not 0
    far = np.array([27.0, 1e3, np.inf, -np.inf, np.nan])
    got = np.empty(5)
    _exp_neg_squares(far, got, np.empty(5, dtype=np.int64), 5)
    assert np.all(got == got[0]) and got[0] == pytest.approx(math.exp(-_EXP_LIMIT), rel=1e-12)


def test_masked_row_percentile_matches_numpy():
    rng = np.random.default_rng(2)
    values = rng.normal(size=(6, 5, 5))
    exclude = rng.uniform(size=values.shape) < 0.5
    exclude[4] = True                      # nothing left
    exclude[5] = True
    exclude[5, 0, :4] = False              # fewer than min_count
    got = _masked_row_percentile(values, exclude, 60.0, min_count=5)
    for k in range(4):
        assert got[k] == pytest.approx(np.percentile(values[k][~exclude[k]], 60))
    assert np.isnan(got[4]) and np.isnan(got[5])


def test_a_crossing_pair_is_recovered_from_biased_starts():
    """Two images 0.8 px apart at the central view that cross over across the aperture."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 2.0], [0.08, 0.0, -3.0]])
    rc = np.array([[2.0, 0.95], [2.0, 0.95]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.01)
    start = truth + np.array([[0.03, -0.02, -1.2], [-0.03, 0.02, 1.0]])  # pulled together
    theta = fit_images(dlfc, views_uv, view_rc, data, start, np.array([[1.6, 0.8]] * 2),
                       np.zeros((0, 3)), np.zeros((0, 2))).params
    assert np.abs(theta[:, :3] - truth).max() < 0.02
    assert np.allclose(theta[:, 3:], rc, atol=0.1)


def test_a_reference_model_is_scored_on_the_fits_own_pixels():
    """Two images crossing over, fitted as one and as two. An image nobody located next
    to them adds the same residual to both models: the ratio of their model errors
    collapses towards 1, their difference in mean square hardly moves."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 2.0], [0.08, 0.0, -3.0]])
    rc = np.array([[2.0, 0.95], [2.0, 0.95]])
    start = truth + np.array([[0.03, -0.02, -1.2], [-0.03, 0.02, 1.0]])
    none = (np.zeros((0, 3)), np.zeros((0, 2)))
    scores = {}
    for unseen in (False, True):
        xyz = np.vstack([truth, [0.6, 0.1, 1.0]]) if unseen else truth
        data = _render(dlfc, xyz, np.vstack([rc, rc[:1]]) if unseen else rc, views_uv, view_rc,
                       noise=0.01)
        one = fit_images(dlfc, views_uv, view_rc, data, truth.mean(axis=0)[None],
                         np.array([[2.0, 0.9]]), *none)
        pair = fit_images(dlfc, views_uv, view_rc, data, start, np.array([[1.6, 0.8]] * 2),
                          *none, reference=one.params)
        assert np.isnan(fit_images(dlfc, views_uv, view_rc, data, start,
                                   np.array([[1.6, 0.8]] * 2), *none).reference_error)
        assert np.abs(pair.params[:, :3] - truth).max() < 0.03
        scores[unseen] = (one.model_error / max(pair.model_error, 1e-9),
                          math.sqrt(pair.reference_error ** 2 - pair.model_error ** 2))
        # restarted at its own solution, the fit scores its start as the reference: the
        # cost it ends with, at most a hair lower
        again = fit_images(dlfc, views_uv, view_rc, data, pair.params[:, :3],
                           pair.params[:, 3:], *none, reference=pair.params)
        assert again.cost <= again.reference_cost <= again.cost * 1.01
    assert scores[False][0] > 10 and scores[True][0] < 2.5
    assert scores[True][1] > 0.7 * scores[False][1] > 0.2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_fit_stops_once_its_steps_are_below_tolerance(seed):
    """A step proposed below the tolerance ends the fit without being evaluated."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 2.0]])
    rc = np.array([[2.0, 0.95]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.01, seed=seed)
    args = (dlfc, views_uv, view_rc, data, truth + [0.02, -0.01, 0.5], np.array([[1.6, 0.8]]),
            np.zeros((0, 3)), np.zeros((0, 2)))
    fitted = fit_images(*args)
    # the start and three accepted steps; evaluating the last, negligible step made 5
    assert fitted.n_evaluations <= 4
    tight = fit_images(*args, xyz_tol=1e-8, step_sigma=0.0)
    assert tight.n_evaluations > 4
    assert np.abs(fitted.params[0, :3] - tight.params[0, :3]).max() < 1e-3
    assert np.abs(tight.params[0, :3] - truth[0]).max() < 0.005


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_steps_far_inside_the_uncertainty_end_the_fit(seed):
    """With ``step_sigma`` the fit stops once a step moves every parameter by less than
    that fraction of its standard error: fewer model evaluations than without (the
    absolute tolerance made negligible in both), and a result within a tenth of a
    standard error."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 2.0], [0.3, 0.1, -1.5]])
    rc = np.array([[2.0, 0.95], [2.2, 0.9]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.02, seed=seed)
    args = (dlfc, views_uv, view_rc, data, truth + [[0.02, -0.01, 0.5], [-0.01, 0.02, 0.4]],
            rc + [[-0.4, -0.1], [-0.3, -0.05]], np.zeros((0, 3)), np.zeros((0, 2)))
    quick = fit_images(*args, xyz_tol=1e-9, step_sigma=0.05)
    strict = fit_images(*args, xyz_tol=1e-9, step_sigma=0.0)
    assert quick.n_evaluations < strict.n_evaluations
    assert np.all(np.abs(quick.params[:, :3] - strict.params[:, :3]) <= 0.1 * strict.sigma)
    assert np.allclose(quick.sigma, strict.sigma, rtol=0.05)


def test_a_particle_is_refitted_beside_a_held_neighbour():
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 1.0], [0.25, 0.05, -2.0]])
    rc = np.array([[1.8, 0.9], [2.2, 0.95]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.01, seed=1)
    fitted = fit_images(dlfc, views_uv, view_rc, data, truth[:1] + [0.02, 0.0, 0.6],
                        np.array([[1.5, 0.8]]), truth[1:], rc[1:])
    theta = fitted.params
    assert np.abs(theta[0, :3] - truth[0]).max() < 0.02
    # without the neighbour in the model, its image pulls the fit
    missed = fit_images(dlfc, views_uv, view_rc, data, truth[:1] + [0.02, 0.0, 0.6],
                        np.array([[1.5, 0.8]]), np.zeros((0, 3)), np.zeros((0, 2)))
    alone = missed.params
    assert np.abs(alone[0, :3] - truth[0]).max() > np.abs(theta[0, :3] - truth[0]).max()
    # ... and the fit says so: the model explains the pixels to their noise (0.01) only
    # with the neighbour in it
    assert fitted.noise == pytest.approx(0.01, rel=0.2)
    assert fitted.model_error < 0.01 < 0.08 < missed.model_error


def test_fit_sigma_covers_errors_correlated_within_a_view():
    """Each view's image is displaced at random (an error shared by all of a view's
    pixels, as a neighbour's blur or a resampling bias would be): the view-robust
    standard errors cover the position errors about as a standard error should."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([0.0, 0.0, 1.0])
    tt, ss = np.mgrid[0:90, 0:110].astype(float)
    ratios = []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        data = np.ones((9, 9, 90, 110))
        for (u, v), (vi, ui) in zip(views_uv, view_rc):
            s, t = dlfc.predict(*truth, u, v)
            s, t = s + rng.normal(0, 0.15), t + rng.normal(0, 0.15)
            data[vi, ui] = disc_image(np.hypot(ss - s, tt - t), 2.0, 0.9)[0]
        data += rng.normal(0, 0.01, data.shape)
        fitted = fit_images(dlfc, views_uv, view_rc, data, truth[None] + [0.01, -0.01, 0.3],
                            np.array([[1.7, 0.8]]), np.zeros((0, 3)), np.zeros((0, 2)))
        error = fitted.params[0, :3] - truth
        ratios.append(error / fitted.sigma[0])
    ratios = np.abs(np.concatenate(ratios))
    assert 0.55 <= np.mean(ratios <= 1) <= 0.82, np.mean(ratios <= 1)
    assert np.mean(ratios <= 2) >= 0.88, np.mean(ratios <= 2)


def test_a_fit_that_wanders_beyond_the_depth_bound_gives_none():
    """The start is 0.6 mm from the truth in depth: a bound of 0.3 mm stops the fit (the
    caller discards such fits), a bound of 1 mm lets it converge on the truth."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 1.0]])
    rc = np.array([[1.8, 0.9]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.01, seed=4)
    args = (dlfc, views_uv, view_rc, data, truth + [0.02, 0.0, 0.6], np.array([[1.5, 0.8]]),
            np.zeros((0, 3)), np.zeros((0, 2)))
    assert fit_images(*args, max_depth_shift=0.3) is None
    fitted = fit_images(*args, max_depth_shift=1.0)
    assert np.abs(fitted.params[0, :3] - truth[0]).max() < 0.02


def test_a_patch_outside_every_view_gives_none():
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    data = np.ones((9, 9, 90, 110))
    assert fit_images(dlfc, views_uv, view_rc, data, np.array([[20.0, 0.0, 0.0]]),
                      np.array([[2.0, 0.9]]), np.zeros((0, 3)), np.zeros((0, 2))) is None


def test_free_images_further_apart_than_a_view_give_none():
    """Two images run far off to either side (x -+1e7 mm; their mean in the view) would
    need one patch spanning both: no view holds it, and the fit gives none instead of
    trying to gather a patch of about 1e8 pixels a side."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[0.0, 0.0, 1.0]])
    rc = np.array([[1.8, 0.9]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.01, seed=4)
    off = np.array([[-1e7, 0.0, 1.0], [1e7, 0.0, 1.0]])
    args = (dlfc, views_uv, view_rc, data)
    assert fit_images(*args, off, np.tile(rc, (2, 1)), np.zeros((0, 3)),
                      np.zeros((0, 2))) is None
    assert fit_images(*args, truth, rc, np.zeros((0, 3)), np.zeros((0, 2))) is not None


def test_patches_reaching_beyond_the_view_mark_their_pixels_outside():
    data = np.arange(2 * 1 * 6 * 8, dtype=float).reshape(2, 1, 6, 8)
    view_rc = np.array([[0, 0], [1, 0]])
    centre = np.array([[1.0, 4.0], [9.0, 2.0]])          # (s, t): in view 0, beyond view 1
    keep, origin, values, inside = _patches(data, view_rc, centre, 2)
    assert keep.tolist() == [True, False]
    assert origin.tolist() == [[-1.0, 2.0]]
    t, s = np.mgrid[2:7, -1:4]
    assert np.array_equal(inside[0], (t < 6) & (s >= 0))
    assert np.array_equal(values[0][inside[0]], data[0, 0][t[inside[0]], s[inside[0]]])


def test_an_image_cut_by_the_view_edge_is_fitted_on_its_part_in_the_view():
    """The image lies across the view's left edge in every view (its patch cannot fit
    inside any view): the fit uses the pixels in the view and finds the particle."""
    dlfc = LinearCalibration()
    views_uv, view_rc = _views()
    truth = np.array([[-4.85, 0.0, 1.0]])                # s = 1.5 +- 1.2 over the views
    rc = np.array([[2.5, 0.95]])
    data = _render(dlfc, truth, rc, views_uv, view_rc, noise=0.01, seed=3)
    fitted = fit_images(dlfc, views_uv, view_rc, data, truth + [0.03, -0.02, 0.4],
                        np.array([[2.0, 0.8]]), np.zeros((0, 3)), np.zeros((0, 2)))
    assert fitted is not None and fitted.n_views == len(views_uv)
    assert np.abs(fitted.params[0, :3] - truth[0]).max() < 0.02
    assert fitted.params[0, 3] == pytest.approx(2.5, abs=0.1)
    assert fitted.model_error < 0.01


def test_overlap_fraction_against_brute_force():
    rng = np.random.default_rng(3)
    pred = rng.uniform(0, 30, (12, 1, 2)) + rng.normal(0, 2, (12, 25, 2))
    pred[4] = np.nan
    radius = rng.uniform(1, 2, 12)
    got = overlap_fraction(pred, radius, gap_px=1.0)
    for a in range(12):
        for b in range(12):
            if a == b or 4 in (a, b):
                assert got[a, b] == 0
                continue
            d = np.hypot(*(pred[a] - pred[b]).T)
            assert got[a, b] == pytest.approx(np.mean(d < radius[a] + radius[b] + 1.0))


def test_refinement_keeps_recall_and_reduces_depth_error(small_calibrated):
    """Denser small scenes: refitting overlapped particles loses none and lowers the
    depth RMS error of the particles it moves."""
    optics, calib = small_calibrated
    assert PerspectiveLocator().check.refine_images   # on by default
    # the refinement alone: the split and the hidden-particle search (which run only
    # with it) would add particles the plain solve has no row for
    on = PerspectiveLocator.from_dict({"check": {"split_merged": False, "find_hidden": False}})
    off = PerspectiveLocator.from_dict({"check": {"refine_images": False}})
    base_err, ref_err, n_base, n_ref = [], [], 0, 0
    refined = int(TriangulationFlag.REFINED)
    for seed in (11, 12):
        scene = make_scene(calib.camera, n_particles=40, seed=seed)
        raw = render_frame(optics, scene.truth, seed=np.random.default_rng([seed, 3, 0]))
        tables = {}
        for locator, errs in ((off, base_err), (on, ref_err)):
            found = tables[locator is on] = locate_frame(raw, calib, locator=locator).particles
            pairs = match_particles(found, scene.truth, tolerance_mm=1.0)
            dz = (found.loc[pairs["measured_index"], "z"].to_numpy()
                  - scene.truth.loc[pairs["truth_index"], "z"].to_numpy())
            errs.append(dz)
        # the REFINED flag marks exactly the particles the refinement moved
        plain, fitted = tables[False], tables[True]
        assert len(plain) == len(fitted)
        flagged = (fitted["flags"].to_numpy() & refined) > 0
        moved = np.any(fitted[["x", "y", "z"]].to_numpy() != plain[["x", "y", "z"]].to_numpy(),
                       axis=1)
        assert flagged.any() and np.array_equal(flagged, moved)
        assert not ((plain["flags"].to_numpy() & refined) > 0).any()
        n_base += len(base_err[-1])
        n_ref += len(ref_err[-1])
    assert n_ref >= n_base - 1
    base, ref = np.concatenate(base_err), np.concatenate(ref_err)
    assert np.sqrt(np.mean(ref ** 2)) < np.sqrt(np.mean(base ** 2))


def test_robust_sd_is_scipys_normal_scaled_mad():
    from scipy.stats import median_abs_deviation

    rng = np.random.default_rng(4)
    for n in (1, 2, 3, 4, 7, 8, 1000, 1001):
        for x in (rng.standard_t(3, n), np.round(rng.normal(0.0, 1.0, n), 1)):  # ties too
            assert _robust_sd(x) == float(median_abs_deviation(x, scale="normal"))
    assert _robust_sd(rng.normal(0.0, 2.0, 200_000)) == pytest.approx(2.0, rel=0.01)
    with_nan = rng.normal(size=50)
    with_nan[7] = np.nan
    assert np.isnan(_robust_sd(with_nan))
    assert np.isnan(_robust_sd(np.zeros(0)))

