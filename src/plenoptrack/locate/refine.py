"""Refining overlapping particles against the view images themselves.

Where two particle images overlap in a view, both centroids are pulled towards each
other, and a particle seen apart from its neighbour in only part of the aperture gets a
biased depth from the rest. This step refits such a particle to the pixels of every
usable view around its predicted image. The model of a view patch is the product of the
particles' images, each a disc of radius ``r`` (view pixels) and contrast ``c`` with an
error-function edge of width :data:`EDGE_PX`, centred on the DLFC prediction of the
particle's ``(x, y, z)``::

    I(p) = prod_q (1 - c_q D(|p - mu_q| ; r_q)),   D(rho; r) = erfc((rho - r) / (sqrt 2 w)) / 2

each patch divided by its local background (the 60th percentile of its pixels more than
2 pixels outside every predicted image). The particle's ``(x, y, z, r, c)`` are fitted by
Levenberg-Marquardt with analytic derivatives (:meth:`~plenoptrack.locate.dlfc.DLFC.predict_with_jacobian`), its
neighbours held at their current positions; a particle whose strongest neighbour
overlaps it in most views is fitted jointly with that neighbour.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import erfc

EDGE_PX = 0.6
"""Width (standard deviation, view pixels) of the blurred edge of a particle image."""

_SQRT2 = math.sqrt(2.0)
_BOUNDS = np.array([[-np.inf, -np.inf, -np.inf, 0.5, 0.05],
                    [np.inf, np.inf, np.inf, 20.0, 1.3]])


def disc_image(rho: np.ndarray, radius, contrast, edge: float = EDGE_PX):
    """One particle's image factor ``1 - c D`` and its derivatives.

    Parameters
    ----------
    rho : ndarray
        Distance of each pixel from the image centre, view pixels.
    radius, contrast : float or ndarray
        Disc radius (view pixels) and contrast (1: opaque).
    edge : float
        Edge width, view pixels.

    Returns
    -------
    f, df_drho, df_dr, df_dc : ndarray
        The factor and its derivatives with respect to ``rho``, ``radius`` and
        ``contrast``.

    Examples
    --------
    >>> f, *_ = disc_image(np.array([0.0, 10.0]), 2.0, 1.0)
    >>> np.round(f, 6).tolist()
    [0.000429, 1.0]
    """
    x = (rho - radius) / (_SQRT2 * edge)
    d = 0.5 * erfc(x)
    g = np.exp(-x * x) / (math.sqrt(2.0 * math.pi) * edge)  # -dD/drho = dD/dr
    return 1.0 - contrast * d, contrast * g, -contrast * g, -d


def _patches(data, view_rc, centre, half):
    """Square patches of side ``2 half + 1`` around ``centre`` (V, 2) ``(s, t)`` in every
    view; returns ``(keep (V,) bool, s (K, n, n), t (K, n, n), values (K, n, n))``."""
    n_t, n_s = data.shape[2:]
    s0 = np.rint(centre[:, 0]).astype(np.int64) - half
    t0 = np.rint(centre[:, 1]).astype(np.int64) - half
    keep = (s0 >= 0) & (t0 >= 0) & (s0 + 2 * half < n_s) & (t0 + 2 * half < n_t)
    off = np.arange(2 * half + 1)
    ss = (s0[keep, None] + off)[:, None, :]
    tt = (t0[keep, None] + off)[:, :, None]
    vr, ur = view_rc[keep, 0], view_rc[keep, 1]
    values = data[vr[:, None, None], ur[:, None, None], tt, ss].astype(np.float64)
    ss, tt = np.broadcast_arrays(ss.astype(np.float64), tt.astype(np.float64))
    return keep, ss, tt, values


def fit_images(dlfc, views_uv, view_rc, data, free_xyz, free_rc, fixed_xyz, fixed_rc, *,
               margin_px: float = 3.0, max_iter: int = 30):
    """Fit ``k`` free particles to the view pixels around them, neighbours held fixed.

    Parameters
    ----------
    dlfc : DLFC
        The calibration.
    views_uv : (V, 2) float ndarray
        ``(u, v)`` of the usable views.
    view_rc : (V, 2) int ndarray
        Index of each of those views into ``data``'s ``(v, u)`` axes.
    data : (n_v, n_u, n_t, n_s) ndarray
        The light field.
    free_xyz : (k, 3) float ndarray
        Starting positions of the particles to fit, mm.
    free_rc : (k, 2) float ndarray
        Their starting image radius (view pixels) and contrast.
    fixed_xyz, fixed_rc : (m, 3), (m, 2) float ndarrays
        Neighbours drawn into the model at fixed positions.
    margin_px : float
        Patch margin beyond the free images, view pixels.
    max_iter : int
        Levenberg-Marquardt iterations.

    Returns
    -------
    (k, 5) float ndarray or None
        Fitted ``(x, y, z, r, c)`` of each free particle; None when fewer than 6 views
        have a usable patch.
    """
    k = len(free_xyz)
    u, v = views_uv[:, 0], views_uv[:, 1]
    st_free, _ = dlfc.predict_with_jacobian(free_xyz[:, None, 0], free_xyz[:, None, 1],
                                            free_xyz[:, None, 2], u[None, :], v[None, :])
    centre = st_free.mean(axis=0)
    reach = np.max(np.hypot(*(st_free - centre[None]).transpose(2, 0, 1)))
    half = int(math.ceil(reach + free_rc[:, 0].max() + margin_px))
    keep, ss, tt, values = _patches(data, view_rc, centre, half)
    if keep.sum() < 6:
        return None
    uk, vk = u[keep], v[keep]
    # Fixed neighbours' images and the background mask.
    fixed = np.ones_like(values)
    near = np.zeros(values.shape, dtype=bool)
    for q in range(len(fixed_xyz)):
        s_q, t_q = dlfc.predict(fixed_xyz[q, 0], fixed_xyz[q, 1], fixed_xyz[q, 2], uk, vk)
        rho = np.hypot(ss - s_q[:, None, None], tt - t_q[:, None, None])
        fixed *= disc_image(rho, fixed_rc[q, 0], fixed_rc[q, 1])[0]
        near |= rho < fixed_rc[q, 0] + 2.0
    for q in range(k):
        rho = np.hypot(ss - st_free[q, keep, 0][:, None, None],
                       tt - st_free[q, keep, 1][:, None, None])
        near |= rho < free_rc[q, 0] + 2.0
    far_count = (~near).sum(axis=(1, 2))
    background = np.full(len(values), np.nan)
    enough = far_count >= 5
    if enough.any():
        background[enough] = np.nanpercentile(np.where(near[enough], np.nan, values[enough]),
                                               60, axis=(1, 2))
    use = enough & np.isfinite(background) & (background > 0)
    if use.sum() < 6:
        return None
    y = (values[use] / background[use, None, None]).ravel()
    ss, tt, fixed = ss[use], tt[use], fixed[use]
    uk, vk = uk[use], vk[use]
    theta = np.concatenate([free_xyz, free_rc], axis=1).astype(float)

    def residual_and_jacobian(th):
        model = fixed.copy()
        factors, parts = [], []
        for q in range(k):
            st, jac = dlfc.predict_with_jacobian(th[q, 0], th[q, 1], th[q, 2], uk, vk)
            ds = ss - st[:, 0, None, None]
            dt = tt - st[:, 1, None, None]
            rho = np.maximum(np.hypot(ds, dt), 1e-9)
            f, df_drho, df_dr, df_dc = disc_image(rho, th[q, 3], th[q, 4])
            # d rho / d mu = -(p - mu) / rho; d mu / d xyz = jac (K, 2, 3)
            drho_dxyz = -(ds[..., None] * jac[:, None, None, 0, :]
                          + dt[..., None] * jac[:, None, None, 1, :]) / rho[..., None]
            parts.append((df_drho[..., None] * drho_dxyz, df_dr, df_dc))
            factors.append(f)
            model = model * f
        cols = []
        for q in range(k):
            others = fixed.copy()
            for p in range(k):
                if p != q:
                    others = others * factors[p]
            d_xyz, df_dr, df_dc = parts[q]
            cols += [others[..., None] * d_xyz, (others * df_dr)[..., None],
                     (others * df_dc)[..., None]]
        jac_all = np.concatenate(cols, axis=-1).reshape(-1, 5 * k)
        return model.ravel() - y, jac_all

    lam = 1e-3
    r, jac = residual_and_jacobian(theta)
    cost = float(r @ r)
    lo, hi = np.tile(_BOUNDS[0], (k, 1)), np.tile(_BOUNDS[1], (k, 1))
    for _ in range(max_iter):
        jtj = jac.T @ jac
        grad = jac.T @ r
        try:
            step = np.linalg.solve(jtj + lam * np.diag(np.diag(jtj) + 1e-12), -grad)
        except np.linalg.LinAlgError:
            lam *= 4.0
            if lam > 1e8:
                break
            continue
        trial = np.clip(theta + step.reshape(k, 5), lo, hi)
        r_new, jac_new = residual_and_jacobian(trial)
        cost_new = float(r_new @ r_new)
        if cost_new < cost:
            converged = cost - cost_new < 1e-9 * cost
            theta, r, jac, cost = trial, r_new, jac_new, cost_new
            lam = max(lam / 3.0, 1e-9)
            if converged:
                break
        else:
            lam *= 4.0
            if lam > 1e8:
                break
    return theta


def overlap_fraction(pred: np.ndarray, radius: np.ndarray, gap_px: float = 1.0) -> np.ndarray:
    """(P, P) fraction of views in which two particles' predicted images overlap.

    Parameters
    ----------
    pred : (P, V, 2) float ndarray
        Predicted ``(s, t)`` of every particle in every view (NaN rows for none).
    radius : (P,) float ndarray
        Image radius of each particle, view pixels.
    gap_px : float
        Images closer than the sum of their radii plus this count as overlapping.
    """
    n = len(pred)
    out = np.zeros((n, n))
    ok = np.flatnonzero(np.all(np.isfinite(pred[:, :, 0]), axis=1) & np.isfinite(radius))
    if len(ok) < 2:
        return out
    from scipy.spatial import cKDTree

    centre = pred[ok].mean(axis=1)
    spread = np.max(np.hypot(*(pred[ok] - centre[:, None]).transpose(2, 0, 1)), axis=1)
    pairs = cKDTree(centre).query_pairs(2 * spread.max() + 2 * radius[ok].max() + gap_px,
                                        output_type="ndarray")
    if len(pairs) == 0:
        return out
    a, b = ok[pairs[:, 0]], ok[pairs[:, 1]]
    d = np.hypot(pred[a, :, 0] - pred[b, :, 0], pred[a, :, 1] - pred[b, :, 1])
    frac = np.mean(d < (radius[a] + radius[b] + gap_px)[:, None], axis=1)
    out[a, b] = frac
    out[b, a] = frac
    return out
