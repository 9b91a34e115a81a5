"""DLFC fit, evaluation, Jacobian and file round trip on an independent optical model.

The forward model here is written from ``docs/conventions.md`` alone (no simulator): a
thin main lens with radial distortion in the image plane, views as aperture points
``U = -u * pixel_pitch * s_i / f_ml``, and view pixels as the microlens-plane crossing
divided by the lenslet pitch plus an axis offset.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pandas as pd
import pytest

from plenoptrack.errors import CalibrationError
from plenoptrack.locate.dlfc import (DLFC, dot_position_errors, fit_dlfc, monomial_exponents,
                                    n_monomials, model_error_by_depth)


@dataclass(frozen=True)
class PlenopticModel:
    """Thin-lens plenoptic camera (hall2019-like) with radial distortion; mm throughout."""

    focal_length: float = 105.0
    magnification: float = 0.5          # |M|
    pixel_pitch: float = 0.0055
    f_ml: float = 0.308
    lenslet_pitch: float = 0.077        # view pixel spacing on the microlens plane
    s_offset: float = 235.3             # view pixel of the optical axis
    t_offset: float = 180.6
    k1: float = 0.005                   # radial distortion at image radius r_ref
    r_ref: float = 18.0

    @property
    def s_o(self) -> float:
        return self.focal_length * (1 + 1 / self.magnification)

    @property
    def s_i(self) -> float:
        return self.focal_length * (1 + self.magnification)

    def __call__(self, x, y, z, u, v):
        """(s, t) in view pixels of world points (x, y, z) mm seen in views (u, v)."""
        x, y, z, u, v = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (x, y, z, u, v)))
        depth = self.s_o + z
        d = 1.0 / (1.0 / self.focal_length - 1.0 / depth)
        # camera frame X = -x; the lens inverts, so the image point is at +x d / depth
        xi, yi = x * d / depth, y * d / depth
        warp = 1 + self.k1 * (xi ** 2 + yi ** 2) / self.r_ref ** 2
        xi, yi = xi * warp, yi * warp
        ux = -u * self.pixel_pitch * self.s_i / self.f_ml
        uy = -v * self.pixel_pitch * self.s_i / self.f_ml
        xm = ux + (xi - ux) * self.s_i / d
        ym = uy + (yi - uy) * self.s_i / d
        return xm / self.lenslet_pitch + self.s_offset, ym / self.lenslet_pitch + self.t_offset


def views(radius: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Integer views inside a circular aperture of ``radius`` sensor pixels."""
    uu, vv = np.meshgrid(np.arange(-radius, radius + 1), np.arange(-radius, radius + 1))
    inside = uu ** 2 + vv ** 2 <= radius ** 2
    return uu[inside].astype(float), vv[inside].astype(float)


def dot_cards(model: PlenopticModel, *, step: float = 7.5, half_width: float = 30.0,
              depths=np.linspace(-25, 25, 11), view_radius: int = 7,
              noise_px: float = 0.0, seed: int = 0) -> pd.DataFrame:
    """Dot-card calibration table: a square dot grid at each depth, seen in every view."""
    g = np.arange(-half_width, half_width + 1e-9, step)
    xs, ys, zs = (a.ravel() for a in np.meshgrid(g, g, depths, indexing="ij"))
    u, v = views(view_radius)
    n = len(xs)
    table = pd.DataFrame({"x": np.repeat(xs, len(u)), "y": np.repeat(ys, len(u)),
                          "z": np.repeat(zs, len(u)), "u": np.tile(u, n), "v": np.tile(v, n)})
    s, t = model(table.x, table.y, table.z, table.u, table.v)
    rng = np.random.default_rng(seed)
    return table.assign(s=s + rng.normal(0, noise_px, s.shape) if noise_px else s,
                        t=t + rng.normal(0, noise_px, t.shape) if noise_px else t)


@pytest.fixture(scope="module")
def model() -> PlenopticModel:
    return PlenopticModel()


@pytest.fixture(scope="module")
def cards(model) -> pd.DataFrame:
    return dot_cards(model)


@pytest.fixture(scope="module")
def dlfc4(cards) -> DLFC:
    return fit_dlfc(cards, order=4, group_by="z")


# --- basis ---------------------------------------------------------------------------

@pytest.mark.parametrize("order, n", [(3, 56), (4, 126), (5, 252)])
def test_basis_size_and_order(order, n):
    exps = monomial_exponents(order)
    assert exps.shape == (n, 5) == (n_monomials(order), 5)
    degree = exps.sum(axis=1)
    assert degree.max() == order and np.all(np.diff(degree) >= 0)
    assert len({tuple(e) for e in exps}) == n
    assert exps[:6].tolist() == [[0] * 5, [1, 0, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, 0, 0],
                                 [0, 0, 0, 1, 0], [0, 0, 0, 0, 1]]


def test_model_parallax_sign(model):
    """Behind the focal plane a particle moves to larger s as u grows (conventions)."""
    s_behind = model(0.0, 0.0, 10.0, np.array([-3.0, 3.0]), 0.0)[0]
    s_front = model(0.0, 0.0, -10.0, np.array([-3.0, 3.0]), 0.0)[0]
    s_focus = model(2.0, 0.0, 0.0, np.array([-3.0, 3.0]), 0.0)[0]
    assert s_behind[1] > s_behind[0] and s_front[1] < s_front[0]
    assert s_focus[1] == pytest.approx(s_focus[0], abs=1e-9)


# --- fit -----------------------------------------------------------------------------

def test_order4_fits_noise_free_model(dlfc4, cards):
    rep = dlfc4.report
    assert dlfc4.n_terms == 126 and rep.n_points == len(cards) and rep.n_rejected == 0
    assert rep.rms_px < 0.01
    assert rep.rms_px == pytest.approx(np.hypot(rep.rms_s_px, rep.rms_t_px))
    assert len(rep.group_keys) == 11 and max(rep.group_rms_px) < 0.02
    s, t = dlfc4.predict(cards.x, cards.y, cards.z, cards.u, cards.v)
    assert np.sqrt(np.mean((s - cards.s) ** 2 + (t - cards.t) ** 2)) == pytest.approx(rep.rms_px)


def test_order3_has_larger_systematic_residual(cards, dlfc4):
    """Measured: order 3 ~0.064 px, order 4 ~0.0073 px, order 5 ~0.0007 px RMS."""
    rms3 = fit_dlfc(cards, order=3).report.rms_px
    assert rms3 > 5 * dlfc4.report.rms_px
    assert rms3 > 0.03


def test_noisy_fit_reaches_noise_level(model, dlfc4):
    noise = 0.05
    table = dot_cards(model, noise_px=noise, seed=3)
    fitted = fit_dlfc(table, order=4)
    # residual vector length of isotropic noise: sqrt(2) * noise
    assert fitted.report.rms_px == pytest.approx(np.sqrt(2) * noise, rel=0.05)
    s0, t0 = dlfc4.predict(table.x, table.y, table.z, table.u, table.v)
    s1, t1 = fitted.predict(table.x, table.y, table.z, table.u, table.v)
    assert np.sqrt(np.mean((s1 - s0) ** 2 + (t1 - t0) ** 2)) < 0.01


def test_robust_refit_drops_bad_points(model):
    table = dot_cards(model, noise_px=0.02, seed=4, step=15.0)
    rng = np.random.default_rng(5)
    bad = rng.choice(len(table), 20, replace=False)
    table.loc[bad, "s"] += 3.0
    plain = fit_dlfc(table)
    robust = fit_dlfc(table, reject_k=5.0)
    assert 20 <= robust.report.n_rejected < 40
    assert robust.report.rms_px < 0.05 < plain.report.rms_px


def test_fit_accepts_mapping_and_group_array(cards):
    arrays = {c: cards[c].to_numpy() for c in cards.columns}
    dlfc = fit_dlfc(arrays, order=3, group_by=np.round(cards.z.to_numpy()).astype(int))
    assert dlfc.report.group_by == "group" and len(dlfc.report.group_keys) == 11
    assert list(dlfc.report.group_table().columns) == ["group", "rms_px", "n_points"]


# --- evaluation ----------------------------------------------------------------------

def test_predict_broadcasts(dlfc4):
    x = np.linspace(-10, 10, 4)[:, None]
    u = np.arange(-3.0, 4.0)[None, :]
    s, t = dlfc4.predict(x, 1.0, 5.0, u, 0.0)
    assert s.shape == t.shape == (4, 7)
    s0, _ = dlfc4.predict(x[2, 0], 1.0, 5.0, u[0, 5], 0.0)
    assert s[2, 5] == pytest.approx(float(s0))


def test_few_points_on_one_thread_match_many_in_parallel(dlfc4):
    """Small inputs take the serial kernel, large ones the parallel one: same numbers."""
    rng = np.random.default_rng(4)
    x, y, z = rng.uniform(-3, 3, (3, 2000))
    u, v = rng.uniform(-5, 5, (2, 2000))
    many_st, many_jac = dlfc4.predict_with_jacobian(x, y, z, u, v)
    for part in (slice(0, 1), slice(7, 140), slice(500, 1012)):
        few_st, few_jac = dlfc4.predict_with_jacobian(x[part], y[part], z[part], u[part],
                                                      v[part])
        assert np.array_equal(few_st, many_st[part])
        assert np.array_equal(few_jac, many_jac[part])


def test_view_factorised_prediction_matches_the_full_basis(dlfc4):
    """predict_in_views regroups the same polynomials: same (s, t) and derivatives."""
    rng = np.random.default_rng(5)
    p = rng.uniform(-20, 20, (6, 3))
    u, v = rng.uniform(-6, 6, (2, 40))
    basis = dlfc4.view_basis(u, v)
    st, jac = dlfc4.predict_in_views(p, basis, jacobian=True)
    assert st.shape == (6, 40, 2) and jac.shape == (6, 40, 2, 3)
    full_st, full_jac = dlfc4.predict_with_jacobian(p[:, None, 0], p[:, None, 1],
                                                    p[:, None, 2], u[None], v[None])
    scale = np.abs(full_st).max()
    np.testing.assert_allclose(st, full_st, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(jac, full_jac, rtol=1e-9, atol=1e-12 * np.abs(full_jac).max())
    assert np.array_equal(dlfc4.predict_in_views(p, basis), st)
    assert dlfc4.predict_in_views(np.empty((0, 3)), basis).shape == (0, 40, 2)


def test_jacobian_matches_finite_differences(dlfc4):
    rng = np.random.default_rng(0)
    p = rng.uniform(-20, 20, (50, 3))
    u, v = rng.uniform(-6, 6, (2, 50))
    jac = dlfc4.jacobian_xyz(p[:, 0], p[:, 1], p[:, 2], u, v)
    assert jac.shape == (50, 2, 3)
    h = 1e-4
    for j in range(3):
        dp = np.zeros(3)
        dp[j] = h
        hi = np.stack(dlfc4.predict(*(p + dp).T, u, v), axis=-1)
        lo = np.stack(dlfc4.predict(*(p - dp).T, u, v), axis=-1)
        np.testing.assert_allclose(jac[:, :, j], (hi - lo) / (2 * h), rtol=1e-6, atol=1e-7)


def test_jacobian_sign_and_magnification(dlfc4, model):
    """s grows with x (conventions); magnification ~ |M| / lenslet pitch px per mm."""
    jac = dlfc4.jacobian_xyz(0.0, 0.0, 0.0, 0.0, 0.0)
    assert jac[0, 0] > 0 and jac[1, 1] > 0
    expected = model.magnification / model.lenslet_pitch
    assert dlfc4.local_magnification(0.0, 0.0, 0.0) == pytest.approx(expected, rel=2e-3)
    # farther objects look smaller
    assert dlfc4.local_magnification(0.0, 0.0, 20.0) < dlfc4.local_magnification(0.0, 0.0, -20.0)


# --- serialisation -------------------------------------------------------------------

def test_dict_round_trip_through_json(dlfc4):
    back = DLFC.from_dict(json.loads(json.dumps(dlfc4.to_dict())))
    np.testing.assert_array_equal(back.coefficients, dlfc4.coefficients)
    np.testing.assert_array_equal(back.centre, dlfc4.centre)
    assert back.report == dlfc4.report
    assert back.predict(1.0, 2.0, 3.0, 1.0, -2.0) == dlfc4.predict(1.0, 2.0, 3.0, 1.0, -2.0)


def _corrupt(dlfc, **changes):
    data = dlfc.to_dict()
    data.update(changes)
    return data


def test_from_dict_rejects_bad_content(dlfc4):
    good = dlfc4.to_dict()
    coef = np.array(good["coefficients"])
    with pytest.raises(CalibrationError, match=r"coefficients must have shape \(2, 126\)"):
        DLFC.from_dict(_corrupt(dlfc4, coefficients=coef[:, :-1].tolist()))
    coef[1, 7] = np.nan
    with pytest.raises(CalibrationError, match="coefficients contains NaN"):
        DLFC.from_dict(_corrupt(dlfc4, coefficients=coef.tolist()))
    with pytest.raises(CalibrationError, match=r"order must be one of \[1, 2, 3, 4, 5, 6\]; got 9"):
        DLFC.from_dict(_corrupt(dlfc4, order=9))
    with pytest.raises(CalibrationError, match="exponent table does not match"):
        DLFC.from_dict(_corrupt(dlfc4, exponents=good["exponents"][::-1]))
    with pytest.raises(CalibrationError, match="scale must be positive"):
        DLFC.from_dict(_corrupt(dlfc4, scale=[1.0, 1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(CalibrationError, match="not a DLFC section"):
        DLFC.from_dict({"order": 4})
    with pytest.raises(CalibrationError, match="version 2 is not supported"):
        DLFC.from_dict(_corrupt(dlfc4, version=2))


def test_fit_errors(cards):
    with pytest.raises(CalibrationError, match=r"lacks column\(s\) \['t'\]"):
        fit_dlfc(cards.drop(columns="t"))
    with pytest.raises(CalibrationError, match=r"do not vary in \['z'\]"):
        fit_dlfc(cards[cards.z == 0])
    with pytest.raises(CalibrationError, match="only 50 calibration points"):
        fit_dlfc(cards.iloc[:50])
    with pytest.raises(CalibrationError, match="rank-deficient"):
        fit_dlfc(cards[cards.z.isin([-25.0, 25.0])], order=4)   # 2 depths: z^2 not determined
    with pytest.raises(CalibrationError, match="order must be one of"):
        fit_dlfc(cards, order="4")
    bad = cards.copy()
    bad.loc[3, "s"] = np.nan
    with pytest.raises(CalibrationError, match="1 row"):
        fit_dlfc(bad)


# --- model error in object space ---------------------------------------------------------

def test_dot_position_errors_of_an_exact_fit_are_tiny(dlfc4, cards):
    errors = dot_position_errors(dlfc4, cards)
    assert len(errors) == cards.groupby(["x", "y", "z"]).ngroups
    assert (errors["n_views"] == len(views()[0])).all()
    # what is left is the order-4 polynomial's own misfit (0.007 px RMS): a few microns
    assert np.abs(errors[["dx", "dy", "dz"]].to_numpy()).max() < 5e-3
    assert dlfc4.report.position_rms_mm == pytest.approx(
        tuple(np.sqrt(np.mean(errors[["dx", "dy", "dz"]].to_numpy() ** 2, axis=0))))


def test_dot_position_errors_follow_centroid_noise(model):
    """With independent centroid noise, each dot's error is the least-squares error of
    its views, RMS sqrt(noise^2 mean diag (J^T J)^-1) (J from the fitted DLFC), added in
    quadrature to the polynomial's own misfit (the same cards without noise)."""
    noise = 0.05
    misfit = np.asarray(fit_dlfc(dot_cards(model, step=10.0), order=4).report.position_rms_mm)
    table = dot_cards(model, noise_px=noise, seed=7, step=10.0)
    fitted = fit_dlfc(table, order=4)
    errors = dot_position_errors(fitted, table)
    u, v = views()
    expected = []
    for _, dot in errors.iloc[::7].iterrows():
        jac = fitted.jacobian_xyz(dot.x, dot.y, dot.z, u, v).reshape(-1, 3)
        expected.append(np.diag(np.linalg.inv(jac.T @ jac)))
    expected = np.hypot(noise * np.sqrt(np.mean(expected, axis=0)), misfit)
    measured = np.asarray(fitted.report.position_rms_mm)
    # in-sample: the fit absorbs a little of the noise (126 terms per output)
    np.testing.assert_allclose(measured, expected, rtol=0.15)
    assert measured[2] > 3 * measured[0]        # depth is the poorly determined axis


def test_position_rms_survives_the_file_round_trip(dlfc4):
    back = DLFC.from_dict(json.loads(json.dumps(dlfc4.to_dict())))
    assert back.report.position_rms_mm == dlfc4.report.position_rms_mm
    assert back.report.model_error_by_depth_mm == dlfc4.report.model_error_by_depth_mm
    old = dlfc4.to_dict()
    del old["fit"]["position_rms_mm"]            # a file from an older version
    del old["fit"]["model_error_by_depth_mm"]
    assert DLFC.from_dict(old).report.position_rms_mm == ()
    assert DLFC.from_dict(old).report.model_error_by_depth_mm == ()
    bad = dlfc4.to_dict()
    bad["fit"]["model_error_by_depth_mm"] = [[0.0, 0.1, 0.1]]
    with pytest.raises(CalibrationError, match="corrupt fit report"):
        DLFC.from_dict(bad)


def _excess(errors):
    d = errors[["dx", "dy", "dz"]].to_numpy()
    noise = errors[["sigma_x", "sigma_y", "sigma_z"]].to_numpy()
    return np.sqrt(np.maximum(np.mean(d ** 2, axis=0) - np.mean(noise ** 2, axis=0), 0.0))


def test_model_error_by_depth_is_the_error_the_dots_noise_does_not_explain(model):
    depths = np.linspace(-25, 25, 11)
    noisy = dot_cards(model, noise_px=0.05, seed=3, step=10.0, depths=depths)
    fitted = fit_dlfc(noisy, order=4)
    errors = dot_position_errors(fitted, noisy)
    rows = np.array(fitted.report.model_error_by_depth_mm)
    np.testing.assert_allclose(rows[:, 0], depths)
    # without the dots' leverage: the whole excess of each card
    whole = np.array(model_error_by_depth(errors))
    for z, *e in whole:
        np.testing.assert_allclose(e, _excess(errors[errors["z"] == z]))
    # the fit's report counts the dots' own errors only as far as the fit takes them up
    assert np.all(rows[:, 1:] <= whole[:, 1:] + 1e-12)
    assert rows[:, 1:3].mean() < 0.7 * whole[:, 1:3].mean()
    # centroid noise alone: the dots' depth errors are that noise, and little is left
    noise_only = rows[:, 3].mean()
    assert noise_only < 0.3 * fitted.report.position_rms_mm[2]
    # a traverse that misplaces the cards alternately by +-0.2 mm: an error of the
    # calibration that no noise explains, and the polynomial cannot follow
    misplaced = noisy.assign(z=noisy["z"] + 0.2 * np.where(np.round(noisy["z"] / 5) % 2, 1, -1))
    wrong = np.array(fit_dlfc(misplaced, order=4).report.model_error_by_depth_mm)
    assert wrong[:, 3].mean() > max(0.1, 3 * noise_only)


def _seen_at(model, xyz, known=None) -> pd.DataFrame:
    """Calibration-style rows of points at ``xyz`` (n, 3) in every view, labelled with
    the positions ``known`` (default ``xyz``): a misprinted dot is imaged where it is but
    listed where it should be."""
    u, v = views()
    known = xyz if known is None else known
    rows = pd.DataFrame(np.repeat(known, len(u), axis=0), columns=["x", "y", "z"])
    rows["u"], rows["v"] = np.tile(u, len(xyz)), np.tile(v, len(xyz))
    where = np.repeat(xyz, len(u), axis=0)
    rows["s"], rows["t"] = model(where[:, 0], where[:, 1], where[:, 2], rows.u, rows.v)
    return rows


def test_model_error_counts_misprinted_dots_only_through_the_fit(model):
    # every dot printed 20 um off its lattice point, independently: its own error, which
    # reaches a particle between the dots only through the fitted coefficients
    g = np.arange(-30.0, 30.1, 7.5)
    known = np.stack([a.ravel() for a in np.meshgrid(g, g, np.linspace(-25, 25, 11),
                                                     indexing="ij")], axis=1)
    rng = np.random.default_rng(5)
    printed = known + np.c_[rng.normal(0, 0.02, (len(known), 2)), np.zeros(len(known))]
    fitted = fit_dlfc(_seen_at(model, printed, known), order=4, group_by="z")
    rows = np.array(fitted.report.model_error_by_depth_mm)
    lateral = np.sqrt(np.mean(rows[:, 1:3] ** 2))
    # the DLFC's real error between the dots: points at random places, solved through it
    inside = rng.uniform([-25, -25, -22], [25, 25, 22], (300, 3))
    between = dot_position_errors(fitted, _seen_at(model, inside))
    real = np.sqrt(np.mean(between[["dx", "dy"]].to_numpy() ** 2))
    assert 0.002 < real < 0.008           # well below the 20 um print error
    # the model error covers it without being several times too large (the mean
    # leverage over the dots, edge dots included, is above that of points inside)
    assert real < lateral < 2 * real
    # the dots' whole excess error (the estimate without the split) is the print error
    errors = dot_position_errors(fitted, _seen_at(model, printed, known))
    whole = np.array(model_error_by_depth(errors))
    assert np.sqrt(np.mean(whole[:, 1:3] ** 2)) > 0.015


def test_model_error_by_depth_bins_dots_that_are_not_on_cards():
    rng = np.random.default_rng(0)
    errors = pd.DataFrame({"z": rng.uniform(-10, 10, 400),
                           "dx": 0.001 * rng.standard_normal(400),
                           "dy": 0.001 * rng.standard_normal(400),
                           "sigma_x": 0.0, "sigma_y": 0.0, "sigma_z": 0.0})
    errors["dz"] = 0.01 * (1 + np.abs(errors["z"])) * rng.standard_normal(400)
    rows = np.array(model_error_by_depth(errors))
    assert len(rows) == 12 and np.all(np.diff(rows[:, 0]) > 0)
    # the per-bin error follows the depth dependence: the ends are several times the middle
    middle = rows[np.argmin(np.abs(rows[:, 0])), 3]
    assert rows[0, 3] > 3 * middle and rows[-1, 3] > 3 * middle
