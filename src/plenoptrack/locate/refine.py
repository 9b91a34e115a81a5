"""Refining overlapping particles against the view images themselves.

Where two particle images overlap in a view, both centroids are pulled towards each
other, and a particle seen apart from its neighbour in only part of the aperture gets a
biased depth from the rest. This step refits such a particle to the pixels of every
usable view around its predicted image. The model of a view patch is the product of the
particles' images, each a disc of radius ``r`` (view pixels) and contrast ``c`` with an
error-function edge, centred on the DLFC prediction of the particle's ``(x, y, z)``::

    I(p) = prod_q (1 - c_q D(|p - mu_q| ; r_q)),   D(rho; r) = erfc((rho - r) / (sqrt 2 w)) / 2

with the edge width ``w`` of the pixel's direction from the centre,
``w^2 = (w_s^2 ds^2 + w_t^2 dt^2) / rho^2`` (:class:`ImageEdge`: wider along ``s`` on a
hexagonal grid; :data:`EDGE_PX` in every direction by default), and each patch divided
by its local background (the 60th percentile of its pixels more than 2 pixels outside
every predicted image).

Two images that run together. The product of two blurred discs is the blurred union of
their shadows only where their edges cross at right angles: where the edges run together
(one image nearly inside the other, as for two particles on nearly one line of sight) it
squares the edge's transmission, which widens the dark disc by about half an edge width,
and a fit of the two pushes them apart across the views to undo it. Two 2 mm spheres
0.1-0.3 mm apart laterally and about 6 mm in depth on the ``small`` camera came out
0.35-1.0 mm too far apart in depth (``benchmarks/line_of_sight_pairs.py``). With each
edge taken as straight across the blur, the chance that the blur places a point inside
both discs is a bivariate normal, ``B = Phi2(h0, h1; r)`` (:func:`_overlapping_edges`),
and the pixel's transmission ``1 - c0 D0 - c1 D1 + c0 c1 B``: the product where the
edges cross at right angles (``r = 0``), the outer edge alone where they run together
(``r = 1``). A fit with ``union`` (:func:`fit_images`) draws its two free images so,
after a first pass with the product: at a split's start the two images coincide, where
the union's derivatives turn on which edge lies outside and give the steps no direction.
The split of merged images (:mod:`~plenoptrack.locate.split`) decides with the product,
whose smooth misfit its thresholds were chosen on, and measures the pair it keeps with the
union; held neighbours and fits of one or of three or more images are drawn as the
product.

The particle's ``(x, y, z, r, c)`` are fitted by
Levenberg-Marquardt with analytic derivatives (the DLFC's view-factorised form,
:attr:`~plenoptrack.locate.dlfc.DLFC.view_model`, in one compiled loop), its neighbours
held at their current positions; a particle whose strongest neighbour
overlaps it in most views is fitted jointly with that neighbour.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np
from scipy.special import erfc, ndtr

from .dlfc import _views_kernel

_KERNEL = dict(cache=True, nogil=True, error_model="numpy")
"""Options of the compiled kernels. numba's default error model checks the divisor of every
float division and raises ``ZeroDivisionError`` on zero, a branch that keeps the compiler
from vectorising the per-pixel passes of :func:`_pixel_normal_equations` (the image fits
ran 1.6 times slower with it: ``benchmarks/bench_locate.py --kernels``); with ``"numpy"`` a
zero divisor gives inf or NaN, as numpy's would. Every division here is guarded where its
divisor can vanish."""

EDGE_PX = 0.6
"""Width (standard deviation, view pixels) of the blurred edge of a particle image when
the calibration measured none (:class:`ImageEdge`)."""

HEX_RESAMPLING_PX2 = 2.0 / 9.0
"""Variance (view pixels squared) that decoding a hexagonal lattice adds along ``s``: a
sample between two lenses of a row, ``2 / sqrt(3)`` samples apart, is their linear
blend (:func:`~plenoptrack.lightfield.decode`), whose spread averaged over the sample's
place between them is ``(2 / sqrt 3)^2 / 6``. Along ``t`` (one lens row per sample) and
on a rectangular lattice nothing is resampled."""


@dataclasses.dataclass(frozen=True)
class ImageEdge:
    """Edge blur of particle images in the views, along ``s`` and ``t``.

    A view samples a particle's shadow through each lens's footprint and the optics'
    blur; decoding a hexagonal lattice blends neighbouring lenses along ``s`` on top
    (:data:`HEX_RESAMPLING_PX2`), so an image's edge is wider along ``s`` than along
    ``t``: on the ``small`` camera about 0.65 against 0.40 view pixels (isolated
    particle images fitted with both widths free). A disc model with one width
    misplaces the images of overlapping particles, whose shapes together it cannot
    match.

    Attributes
    ----------
    blur_by_depth : (K, 2) float ndarray or None
        ``(z mm, sigma px)``: the views' edge blur the calibration measured on its dot
        cards (:func:`~plenoptrack.locate.opacity.edge_blur_by_depth`), taken as the
        geometric mean ``sqrt(w_s w_t)`` (a small dot's peak darkness is set by the
        blurred area ``2 pi w_s w_t``); None: :data:`EDGE_PX` at every depth.
    anisotropy_px2 : float
        ``w_s^2 - w_t^2``, view pixels squared.
    """

    blur_by_depth: np.ndarray | None = None
    anisotropy_px2: float = 0.0

    @classmethod
    def of_frame(cls, grid_type: str, blur_by_depth=None) -> "ImageEdge":
        """The edge of a light field decoded from a ``grid_type`` lattice (``"hex"`` or
        ``"rect"``), with the calibration's measured blur when it has one."""
        rows = None
        if blur_by_depth is not None and len(blur_by_depth):
            rows = np.asarray(blur_by_depth, dtype=float).reshape(-1, 2)
        return cls(rows, HEX_RESAMPLING_PX2 if grid_type == "hex" else 0.0)

    def widths(self, z) -> np.ndarray:
        """Edge widths ``(w_s, w_t)`` of images at depths ``z`` (N,), mm: (N, 2) view
        pixels, ``w_s w_t`` the blur at that depth and ``w_s^2 - w_t^2`` the
        anisotropy."""
        z = np.atleast_1d(np.asarray(z, dtype=float))
        mean = np.full(z.shape, EDGE_PX)
        if self.blur_by_depth is not None:
            rows = self.blur_by_depth
            mean = np.interp(np.nan_to_num(z, nan=float(np.median(rows[:, 0]))),
                             rows[:, 0], rows[:, 1])
        d = float(self.anisotropy_px2)
        wt2 = 0.5 * (np.sqrt(d * d + 4.0 * mean ** 4) - d)
        return np.sqrt(np.stack([wt2 + d, wt2], axis=-1))

    def area_radius(self, radius, z) -> np.ndarray:
        """Radius of the sharp disc that casts as much shadow as a fitted image.

        A particle's image is its silhouette blurred, and blur moves no light: the
        image's summed darkness is ``c pi R^2`` for a silhouette of radius ``R``, at any
        blur. The image model of :func:`fit_images`, ``c D(rho)`` with an edge of width
        ``w`` about the radius ``r``, sums to ``c pi E[rho^2; rho > 0]`` for ``rho``
        normal about ``r`` with spread ``w``::

            R^2 = (r^2 + w^2) Phi(r / w) + r w phi(r / w)

        with ``w^2 = (w_s^2 + w_t^2) / 2`` (the edge width averaged over directions;
        :meth:`widths` at the particle's depth). ``c R^2`` is what the pixels fix; the
        split between ``c`` and ``R`` is the model's (``R`` is the body's radius when
        ``c`` is its opacity). For images a few edge widths across, ``r`` itself lies
        well inside the silhouette: on the realistic ``small`` camera (development seeds
        of the accuracy matrix) ``2 r`` read 0.90 of a 0.4 mm sphere's image diameter
        and 0.99 of a 1 mm one's, ``2 R`` 1.00 and 1.01.

        Parameters
        ----------
        radius : (N,) float array_like
            Fitted image radii ``r``, view pixels.
        z : (N,) float array_like
            The particles' depths, mm.

        Returns
        -------
        (N,) float ndarray
            ``R``, view pixels (NaN where ``radius`` is).
        """
        r = np.asarray(radius, dtype=float)
        w = np.sqrt(np.mean(self.widths(z) ** 2, axis=-1)).reshape(r.shape)
        a = r / w
        inside = ndtr(a)
        density = np.exp(-0.5 * a * a) / math.sqrt(2.0 * math.pi)
        return np.sqrt((r * r + w * w) * inside + r * w * density)

_SQRT2 = math.sqrt(2.0)
_BOUNDS = np.array([[-np.inf, -np.inf, -np.inf, 0.5, 0.05],
                    [np.inf, np.inf, np.inf, 20.0, 1.3]])


@dataclasses.dataclass(frozen=True)
class ImageFit:
    """Result of :func:`fit_images`.

    Attributes
    ----------
    params : (k, 5) float ndarray
        Fitted ``(x, y, z, r, c)`` of each free particle: position (mm), image radius
        (view pixels) and contrast.
    sigma : (k, 3) float ndarray
        Standard errors of ``(x, y, z)``, mm, robust to correlated pixel errors within a
        view (:func:`_view_robust_sigma`); errors shared between neighbouring views are
        not in it.
    n_pixels, n_views : int
        Pixels and views fitted.
    cost : float
        Sum of squared residuals of the normalised pixels.
    noise : float
        Robust standard deviation (1.4826 MAD) of the normalised background pixels of
        the patches (at most about :data:`_NOISE_SAMPLES` of them, evenly spaced): the
        pixel noise the fit would leave if its model were exact.
    reference_cost : float
        Sum of squared residuals of the ``reference`` model given to :func:`fit_images`
        on the same pixels (NaN without one).
    n_evaluations : int
        Evaluations of the model and its normal equations the fit took (the start
        included, the reference not).
    """

    params: np.ndarray
    sigma: np.ndarray
    n_pixels: int
    n_views: int
    cost: float
    noise: float
    reference_cost: float = math.nan
    n_evaluations: int = 0

    @property
    def model_error(self) -> float:
        """RMS residual of the fitted pixels beyond their noise,
        ``sqrt(max(cost / n_pixels - noise**2, 0))``, in units of the local background:
        how far the model (discs, neighbours where they are held) is from explaining the
        pixels. Large where it cannot: a missed or misplaced neighbour, an image that is
        not a disc. Infinite when the noise could not be measured."""
        if not np.isfinite(self.noise):
            return math.inf
        return math.sqrt(max(self.cost / max(self.n_pixels, 1) - self.noise ** 2, 0.0))

    @property
    def vanished(self) -> np.ndarray:
        """(k,) bool: the images the fit drove to the lower bound of their radius or
        contrast, which no longer draw a particle (a group of images started with one
        too many puts the spare one there)."""
        return np.any(self.params[:, 3:] <= _BOUNDS[0, 3:] * (1.0 + 1e-6), axis=1)

    @property
    def reference_error(self) -> float:
        """:attr:`model_error` of the ``reference`` model on the fit's own pixels (NaN
        without a reference): two models compared on the same pixels, where images that
        neither draws add the same to both."""
        if not np.isfinite(self.noise):
            return math.inf if np.isfinite(self.reference_cost) else math.nan
        return math.sqrt(max(self.reference_cost / max(self.n_pixels, 1) - self.noise ** 2,
                             0.0))


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
    view whose centre pixel lies in the view; returns ``(keep (V,) bool, origin (K, 2)
    float, values (K, n, n) float, inside (K, n, n) bool)``, where ``origin`` is the
    ``(s, t)`` of each kept patch's pixel ``[0, 0]``. A patch may reach beyond its view
    (a large image, or one near the edge): ``inside`` marks its pixels within the view;
    those beyond hold the nearest edge pixel's value and must not be used."""
    n_t, n_s = data.shape[2:]
    cs = np.rint(centre[:, 0]).astype(np.int64)
    ct = np.rint(centre[:, 1]).astype(np.int64)
    keep = (cs >= 0) & (ct >= 0) & (cs < n_s) & (ct < n_t)
    s0 = cs[keep] - half
    t0 = ct[keep] - half
    values, inside = _gather_patches(data, np.ascontiguousarray(view_rc[keep], dtype=np.int64),
                                     s0, t0, 2 * half + 1)
    origin = np.stack([s0, t0], axis=1).astype(np.float64)
    return keep, origin, values, inside


@numba.njit(**_KERNEL)
def _gather_patches(data, view_rc, s0, t0, n):  # pragma: no cover - compiled
    """The ``n x n`` patches of ``data[v, u]`` (``view_rc`` (K, 2) rows ``(v, u)``) with
    pixel ``[0, 0]`` at ``(s0, t0)`` (K,), as float64, pixels beyond the view clamped to
    its edge, and the mask of pixels within the view."""
    n_t, n_s = data.shape[2], data.shape[3]
    k = view_rc.shape[0]
    values = np.empty((k, n, n))
    inside = np.empty((k, n, n), dtype=np.bool_)
    for m in range(k):
        view = data[view_rc[m, 0], view_rc[m, 1]]
        for i in range(n):
            t = t0[m] + i
            tt = min(max(t, 0), n_t - 1)
            for j in range(n):
                s = s0[m] + j
                values[m, i, j] = view[tt, min(max(s, 0), n_s - 1)]
                inside[m, i, j] = 0 <= t < n_t and 0 <= s < n_s
    return values, inside


def fit_images(dlfc, views_uv, view_rc, data, free_xyz, free_rc, fixed_xyz, fixed_rc, *,
               margin_px: float = 3.0, max_iter: int = 30, xyz_tol: float = 1e-4,
               step_sigma: float = 0.05, max_depth_shift: float = math.inf,
               view_basis: np.ndarray | None = None, reference: np.ndarray | None = None,
               edge: ImageEdge | None = None, union: bool = False):
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
    xyz_tol : float
        The fit has converged when an accepted step (or the next proposed one) moves
        every particle by less than this (mm, each coordinate) and its radius and
        contrast by less than 0.001, or moves every parameter by less than
        ``step_sigma`` times its standard error at the current fit.
    step_sigma : float
        See ``xyz_tol``: steps far inside a parameter's own uncertainty change nothing a
        caller can see, and the fit does not pay for them.
    max_depth_shift : float
        Give up, returning None, as soon as an accepted step has moved a particle's depth
        by more than this from its start (mm): a fit the caller would discard anyway
        stops paying for its remaining iterations.
    view_basis : (V, B) float ndarray, optional
        ``dlfc.view_basis`` of ``views_uv``, for a caller that fits many particles in the
        same views (computed here when not given).
    reference : (j, 5) float ndarray, optional
        Another model of the same place, ``(x, y, z, r, c)`` per image (e.g. one image
        where the fit has two): its residuals on the fitted pixels give
        :attr:`ImageFit.reference_cost`.
    edge : ImageEdge, optional
        Edge blur of the images, each particle's at its starting depth (default:
        :data:`EDGE_PX` along both axes).
    union : bool
        Two free images (``k = 2``): fitted as the product of their blurred discs, then
        from there as the blurred union of their shadows (module notes), which measures
        two images that run together without pushing them apart. Off: the product only,
        a smooth model that decides well whether two images are there.

    Returns
    -------
    ImageFit or None
        The fitted parameters and their standard errors; None when fewer than 6 views
        have a usable patch (its centre in the view, enough background pixels), the free
        images lie further apart than a view is wide, or the fit wandered beyond
        ``max_depth_shift``. Pixels beyond a view's edge are left
        out, so an image cut by the edge is fitted on its part in the view.
    """
    k = len(free_xyz)
    u, v = views_uv[:, 0], views_uv[:, 1]
    # every prediction below is in these views
    basis = dlfc.view_basis(u, v) if view_basis is None else view_basis
    st_free = dlfc.predict_in_views(free_xyz, basis)
    centre = st_free.mean(axis=0)
    reach = np.max(np.hypot(*(st_free - centre[None]).transpose(2, 0, 1)))
    extent = reach + free_rc[:, 0].max() + margin_px
    if not extent <= max(data.shape[2:]):
        # the free images lie further apart than a view is wide (a fit that ran off):
        # no patch holds them
        return None
    half = int(math.ceil(extent))
    keep, origin, values, inside = _patches(data, view_rc, centre, half)
    if keep.sum() < 6:
        return None
    basis = basis[keep]
    st_held = dlfc.predict_in_views(fixed_xyz, basis)
    edge = ImageEdge() if edge is None else edge
    held_edge = edge.widths(np.asarray(fixed_xyz, dtype=float).reshape(-1, 3)[:, 2])
    fixed, near, fit = _patch_masks(origin, values.shape[1], st_held,
                                    np.ascontiguousarray(fixed_rc, dtype=np.float64),
                                    np.ascontiguousarray(st_free[:, keep]),
                                    np.ascontiguousarray(free_rc[:, 0], dtype=np.float64),
                                    margin_px, held_edge)
    fit &= inside                      # pixels beyond the view are neither fitted
    near |= ~inside                    # nor background
    background = _masked_row_percentile(values, near, 60.0, min_count=5)
    use = np.isfinite(background) & (background > 0)
    if use.sum() < 6:
        return None
    y = values[use] / background[use, None, None]
    far = y[~near[use]]
    # every pixel of a large patch is far more than the noise level needs
    far = far[::max(1, far.size // _NOISE_SAMPLES)]
    noise = _robust_sd(far) if far.size else math.nan
    origin, fixed, fit = origin[use], fixed[use], fit[use]
    basis = basis[use]
    theta = np.concatenate([free_xyz, free_rc], axis=1).astype(float)
    lo, hi = np.tile(_BOUNDS[0], (k, 1)), np.tile(_BOUNDS[1], (k, 1))
    absolute = np.tile([xyz_tol, xyz_tol, xyz_tol, 1e-3, 1e-3], (k, 1))
    xyz_e, tensor, centre_xyz, scale_xyz = dlfc.view_model
    ref = (np.zeros((0, 5)) if reference is None
           else np.ascontiguousarray(np.asarray(reference, dtype=float).reshape(-1, 5)))
    y, basis = np.ascontiguousarray(y), np.ascontiguousarray(basis)
    # every evaluation reads the same pixels: listed once, view by view
    pixels = _fit_pixels(origin, y, fixed, fit)
    widths = edge.widths(theta[:, 2])
    n_evaluations = 0
    # With union, two images are fitted with the product of their blurred discs first,
    # then with their blurred union from there: at a split's start the two images nearly
    # coincide, where the union's derivatives turn on which edge lies outside and the
    # damped steps have no direction to take; the product's do.
    stages = (False, True) if union and k == 2 else (False,)
    for stage, as_union in enumerate(stages):
        last = stage == len(stages) - 1            # the reference is scored on the last
        theta, sigma, cost, within, evaluations, reference_cost = _levenberg_marquardt(
            *pixels, basis, xyz_e, tensor, centre_xyz, scale_xyz, theta, lo, hi, absolute,
            float(step_sigma), int(max_iter), float(max_depth_shift), widths,
            ref if last else np.zeros((0, 5)), as_union)
        n_evaluations += evaluations
        if not within:
            return None
    return ImageFit(theta, sigma[:, :3], int(fit.sum()),
                    len(y), cost, noise, reference_cost, int(n_evaluations))


def _robust_sd(values: np.ndarray) -> float:
    """``median(|x - median(x)|) / 0.6745`` of a 1-D array: the standard deviation of a
    normal sample, robust to outliers (scipy's ``median_abs_deviation(x, scale="normal")``
    without its per-call overhead, which is most of the cost on patch-sized arrays)."""
    values = np.asarray(values, dtype=np.float64)
    return float(_median(np.abs(values - _median(values))) / _NORMAL_MAD)


def _median(values: np.ndarray) -> float:
    """:func:`numpy.median` of a 1-D array with one partition: the same order statistics
    (the lower middle of an even count is the largest of the half below), at a fraction
    of the cost of ``np.median``'s two-point partition. NaN if any value is."""
    n = values.size
    half = n // 2
    if n == 0 or np.isnan(values).any():
        return math.nan
    part = np.partition(values, half)
    if n % 2:
        return float(part[half])
    return float((part[:half].max() + part[half]) / 2.0)


_NOISE_SAMPLES = 8192
"""At most about this many background pixels (evenly spaced through the patches) give
an image fit's noise level: its robust standard deviation is then known to about 1.5 %."""

_NORMAL_MAD = 0.6744897501960817
"""``scipy.special.ndtri(0.75)``: the median absolute deviation of a unit normal."""


@numba.njit(**_KERNEL)
def _levenberg_marquardt(starts, ps, pt, fixed, y, basis, xyz_e, tensor, centre, scale, theta,
                         lo, hi, absolute, step_sigma, max_iter, max_depth_shift, edge,
                         reference, union):  # pragma: no cover - compiled
    """The damped Gauss-Newton iterations of :func:`fit_images` on the fitted pixels
    ``starts, ps, pt, fixed, y`` (:func:`_fit_pixels`), compiled: from
    ``theta`` (k, 5), steps ``(J^T J + lam diag(J^T J)) d = -J^T r`` within the bounds
    ``lo, hi`` (k, 5); a step that lowers the cost is taken and the damping divided by 3,
    otherwise the damping is multiplied by 4 (stop above 1e8). Stops when a proposed or
    taken step moves every parameter by less than ``max(absolute, step_sigma * sigma)``
    (sigma the view-robust standard errors at the current fit), when the cost falls by
    less than 1e-9 of itself, or after ``max_iter`` steps. Returns ``(theta, sigma, cost,
    within, n_evaluations, reference_cost)``: ``sigma`` (k, 5) the view-robust standard
    errors at the final ``theta`` (:func:`_view_robust_sigma`); ``within`` is False once a
    taken step has moved a depth by more than ``max_depth_shift`` from the start;
    ``reference_cost`` is the cost of the ``reference`` parameters (j, 5) on the same
    pixels (NaN if j = 0). ``union``: two free images as the blurred union of their
    shadows (:func:`_pixel_normal_equations`)."""
    k = theta.shape[0]
    n_views = starts.shape[0] - 1
    z0 = theta[:, 2].copy()
    theta = theta.copy()
    pixels = (starts, ps, pt, fixed, y)
    cost, jtj, grad, meat = _model_normal_equations(pixels, basis, xyz_e, tensor, centre,
                                                    scale, theta, edge, union)
    tol = _step_tolerance(absolute, step_sigma, jtj, meat, n_views)
    n_eval = 1
    lam = 1e-3
    for _ in range(max_iter):
        damped = jtj + lam * np.diag(np.diag(jtj) + 1e-12)
        solved = True
        try:
            step = np.linalg.solve(damped, -grad)
        except Exception:
            solved = False
        if not solved:
            lam *= 4.0
            if lam > 1e8:
                break
            continue
        trial = np.empty_like(theta)
        small = True
        for q in range(k):
            for a in range(5):
                v = theta[q, a] + step[5 * q + a]
                if v < lo[q, a]:
                    v = lo[q, a]
                if v > hi[q, a]:
                    v = hi[q, a]
                trial[q, a] = v
                if not abs(v - theta[q, a]) < tol[q, a]:
                    small = False
        if small:
            # At the minimum a rejected step only raises the damping until the steps
            # are this small; stop there instead of paying for ever smaller trials.
            break
        cost_new, jtj_new, grad_new, meat_new = _model_normal_equations(
            pixels, basis, xyz_e, tensor, centre, scale, trial, edge, union)
        n_eval += 1
        if cost_new < cost:
            converged = cost - cost_new < 1e-9 * cost
            theta, jtj, grad, cost, meat = trial, jtj_new, grad_new, cost_new, meat_new
            tol = _step_tolerance(absolute, step_sigma, jtj, meat, n_views)
            for q in range(k):
                if abs(theta[q, 2] - z0[q]) > max_depth_shift:
                    return theta, np.full((k, 5), np.nan), cost, False, n_eval, math.nan
            lam = max(lam / 3.0, 1e-9)
            if converged:
                break
        else:
            lam *= 4.0
            if lam > 1e8:
                break
    reference_cost = math.nan
    if reference.shape[0] > 0:
        reference_cost = _model_normal_equations(pixels, basis, xyz_e, tensor, centre, scale,
                                                 reference, edge, union)[0]
    return (theta, _view_robust_sigma(jtj, meat, n_views), cost, True, n_eval,
            reference_cost)


@numba.njit(**_KERNEL)
def _model_normal_equations(pixels, basis, xyz_e, tensor, centre, scale, theta, edge,
                            union):  # pragma: no cover - compiled
    """:func:`_pixel_normal_equations` of the fitted ``pixels`` (:func:`_fit_pixels`) at
    parameters ``theta`` (k, 5), the image centres and their derivatives from the DLFC's
    view model."""
    # the flag computed, not the literal True: a literal argument would make numba compile
    # (and cache) a second specialisation of _views_kernel beside the one Python calls
    with_jac = theta.shape[0] >= 0
    st, jac = _views_kernel(np.ascontiguousarray(theta[:, :3]), basis, xyz_e, tensor,
                            centre, scale, with_jac)
    starts, ps, pt, fixed, y = pixels
    return _pixel_normal_equations(starts, ps, pt, fixed, y, st, jac,
                                   np.ascontiguousarray(theta[:, 3:]), edge, union)


@numba.njit(**_KERNEL)
def _step_tolerance(absolute, step_sigma, jtj, meat, n_views):  # pragma: no cover - compiled
    """``fmax(absolute, step_sigma * sigma)`` (k, 5) with sigma :func:`_view_robust_sigma`
    (a NaN sigma leaves ``absolute``)."""
    sigma = _view_robust_sigma(jtj, meat, n_views)
    out = absolute.copy()
    for q in range(out.shape[0]):
        for a in range(5):
            v = step_sigma * sigma[q, a]
            if v > out[q, a]:          # False for NaN: fmax keeps the other
                out[q, a] = v
    return out


@numba.njit(**_KERNEL)
def _view_robust_sigma(jtj, meat, n_views):  # pragma: no cover - compiled
    """(k, 5) standard errors of the parameters, robust to any correlation of the pixel
    errors within a view (views as independent clusters)::

        cov = V / (V - p) (J^T J)^-1 [sum_v J_v^T r_v r_v^T J_v] (J^T J)^-1

    NaN where ``J^T J`` is singular (its inverse found by solving against the identity,
    as :func:`numpy.linalg.inv` does) or there are no more views than parameters."""
    n_par = jtj.shape[0]
    out = np.full((n_par // 5, 5), np.nan)
    if n_views <= n_par:
        return out
    try:
        inv = np.linalg.solve(jtj, np.eye(n_par))
    except Exception:
        return out
    cov = (n_views / (n_views - n_par) * inv) @ meat @ inv
    for i in range(n_par):
        v = cov[i, i]
        if v == v:                     # NaN stays NaN, as np.sqrt(np.clip(v, 0, None))
            out[i // 5, i % 5] = math.sqrt(max(v, 0.0))
    return out


def _masked_row_percentile(values, exclude, q, *, min_count):
    """Percentile ``q`` (linear interpolation, as :func:`numpy.percentile`) of each row's
    ``values[k]`` outside ``exclude[k]``; NaN for rows with fewer than ``min_count``."""
    flat = np.where(exclude, np.inf, values).reshape(len(values), -1)
    count = (~exclude).reshape(len(values), -1).sum(axis=1)
    ordered = np.sort(flat, axis=1)
    pos = q / 100.0 * np.maximum(count - 1, 0)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, np.maximum(count - 1, 0))
    rows = np.arange(len(values))
    a, b = ordered[rows, lo], ordered[rows, hi]
    with np.errstate(invalid="ignore"):   # rows with nothing left hold inf - inf
        out = a + (pos - lo) * np.where(hi > lo, b - a, 0.0)
    return np.where(count >= min_count, out, np.nan)


_LOG2_E = 1.4426950408889634
_LN2_HIGH = 0.6931471803691238       # ln 2 in two parts (fdlibm's): the high part's
_LN2_LOW = 1.9082149292705877e-10    # products with the exponents below are exact
_EXP_LIMIT = 708.0                   # exp(-708) is about 3e-308, just above the subnormals


@numba.njit(**_KERNEL, fastmath={"contract"})
def _exp_neg_squares(x, out, powers, m):  # pragma: no cover - compiled
    """``out[:m] = exp(-x[:m]**2)`` in passes the compiler vectorises, within about one
    unit in the last place of :func:`math.exp` (which numba calls one value at a time):
    ``exp(-a) = 2^k exp(r)`` with ``k`` the nearest integer to ``-a / ln 2``, ``r = -a -
    k ln 2`` (at most ``ln 2 / 2`` in size) in the Taylor series to ``r^13`` (truncation
    below 1e-17), and ``2^k`` built from its exponent bits in ``powers`` (int64, at least
    ``m``). ``a`` is capped at :data:`_EXP_LIMIT` (a NaN too): the result is then about
    3e-308 instead of smaller or NaN, which no image model can tell from 0. Compiled
    without reassociation, which would undo the two-part ``ln 2``."""
    scale = powers.view(np.float64)
    for p in range(m):
        a = x[p] * x[p]
        a = a if a < _EXP_LIMIT else _EXP_LIMIT
        k = math.floor(0.5 - a * _LOG2_E)
        r = (-a - k * _LN2_HIGH) - k * _LN2_LOW
        out[p] = 1.0 + r * (1.0 + r * (1 / 2 + r * (1 / 6 + r * (1 / 24 + r * (1 / 120 + r * (
            1 / 720 + r * (1 / 5040 + r * (1 / 40320 + r * (1 / 362880 + r * (
                1 / 3628800 + r * (1 / 39916800 + r * (1 / 479001600
                                                       + r / 6227020800))))))))))))
        powers[p] = (np.int64(k) + 1023) << 52
    for p in range(m):
        out[p] *= scale[p]


@numba.njit(**_KERNEL)
def _half_erfc(x, gauss):  # pragma: no cover - compiled
    """``erfc(x) / 2`` given ``gauss = exp(-x**2)``, absolute error below 1e-7
    (Abramowitz and Stegun 7.1.26), without a second transcendental call."""
    t = 1.0 / (1.0 + 0.3275911 * abs(x))
    h = 0.5 * t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (
        -1.453152027 + t * 1.061405429)))) * gauss
    return h if x >= 0.0 else 1.0 - h


@numba.njit(**_KERNEL, inline="always")
def _edge_argument(ds, dt, rho, radius, w_s, w_t):  # pragma: no cover - compiled
    """``x = (rho - r) / (sqrt 2 w)`` of a pixel at ``(ds, dt)`` (``rho`` its distance)
    from an image's centre, with the edge width ``w`` of the pixel's direction
    (``w^2 = (w_s^2 ds^2 + w_t^2 dt^2) / rho^2``), and its derivatives with respect to
    ``ds``, ``dt`` and ``r``."""
    ws2, wt2 = w_s * w_s, w_t * w_t
    q2 = ws2 * ds * ds + wt2 * dt * dt
    if rho < 1e-6 or q2 <= 0.0:
        w = math.sqrt(0.5 * (ws2 + wt2))
        return (rho - radius) / (math.sqrt(2.0) * w), 0.0, 0.0, -1.0 / (math.sqrt(2.0) * w)
    q = math.sqrt(q2)
    c = 1.0 / (math.sqrt(2.0) * q)
    x = (rho - radius) * rho * c
    a = (2.0 * rho - radius) / rho       # d[(rho - r) rho] / d ds = a ds
    b = (rho - radius) * rho / q2         # d q / d ds = ws2 ds / q
    return x, c * ds * (a - b * ws2), c * dt * (a - b * wt2), -rho * c


@numba.njit(**_KERNEL)
def _patch_masks(origin, n, st_held, rc_held, st_free, r_free, margin,
                 edge):  # pragma: no cover - compiled
    """The held neighbours' image ``fixed`` (K, n, n; computed on the ``fit`` pixels only,
    1 elsewhere), the pixels ``near`` (within 2 px of any particle's image, excluded from
    the background) and the pixels ``fit`` (within ``margin`` px of a free image) of
    patches with pixel ``[0, 0]`` at ``origin`` (K, 2). ``st_held`` (m, K, 2) and
    ``rc_held`` (m, 2) are the held particles' image centres, radii and contrasts;
    ``st_free`` (k, K, 2) and ``r_free`` (k,) the free particles' centres and radii;
    ``edge`` (m, 2) the held images' edge widths ``(w_s, w_t)`` (:class:`ImageEdge`).
    Each image is visited only over the pixels it can reach (its box of the patch)."""
    n_views = origin.shape[0]
    fixed = np.ones((n_views, n, n))
    near = np.zeros((n_views, n, n), dtype=np.bool_)
    fit = np.zeros((n_views, n, n), dtype=np.bool_)
    for view in range(n_views):
        s0, t0 = origin[view, 0], origin[view, 1]
        for q in range(st_free.shape[0]):
            cs, ct = st_free[q, view, 0], st_free[q, view, 1]
            reach = r_free[q] + max(margin, 2.0)
            i0, i1, j0, j1 = _box(ct - t0, cs - s0, reach, n)
            for i in range(i0, i1):
                dt = t0 + i - ct
                for j in range(j0, j1):
                    ds = s0 + j - cs
                    rho = math.sqrt(ds * ds + dt * dt)
                    near[view, i, j] |= rho < r_free[q] + 2.0
                    fit[view, i, j] |= rho <= r_free[q] + margin
        for q in range(st_held.shape[0]):
            cs, ct = st_held[q, view, 0], st_held[q, view, 1]
            radius, contrast = rc_held[q, 0], rc_held[q, 1]
            # beyond this from its rim a held image is 1 to 1e-17
            tail = 6.0 * math.sqrt(2.0) * max(edge[q, 0], edge[q, 1])
            i0, i1, j0, j1 = _box(ct - t0, cs - s0, radius + max(tail, 2.0), n)
            for i in range(i0, i1):
                dt = t0 + i - ct
                for j in range(j0, j1):
                    ds = s0 + j - cs
                    rho = math.sqrt(ds * ds + dt * dt)
                    near[view, i, j] |= rho < radius + 2.0
                    x = _edge_argument(ds, dt, rho, radius, edge[q, 0], edge[q, 1])[0]
                    if fit[view, i, j] and x < 6.0:   # the model reads the held image only there
                        fixed[view, i, j] *= 1.0 - contrast * _half_erfc(x, math.exp(-x * x))
    return fixed, near, fit


@numba.njit(**_KERNEL)
def _box(ci, cj, reach, n):  # pragma: no cover - compiled
    """Row and column ranges ``[i0, i1) x [j0, j1)`` of an ``n x n`` patch within
    ``reach`` of the point ``(ci, cj)`` (patch pixel coordinates); empty when none."""
    if not (math.isfinite(ci) and math.isfinite(cj)):
        return 0, 0, 0, 0
    i0 = max(int(math.floor(ci - reach)), 0)
    i1 = min(int(math.ceil(ci + reach)) + 1, n)
    j0 = max(int(math.floor(cj - reach)), 0)
    j1 = min(int(math.ceil(cj + reach)) + 1, n)
    return i0, max(i1, i0), j0, max(j1, j0)


_EDGE_BAND = 1e-9
"""Where both of two images' darkness ``D`` lies within this of 0 or 1 the product of
the blurred shadows equals their blurred union to within it: the bivariate normal of
:func:`_overlapping_edges` is computed only where both edges cross a pixel's blur."""

_MAX_EDGE_CORRELATION = 0.999999
"""Bound on the correlation of :func:`_overlapping_edges`, which keeps
``sqrt(1 - r^2)`` away from 0 (two edges that run exactly together)."""

# 12-point Gauss-Legendre nodes and weights on [-1, 1]
_GL_NODES = np.array([-0.9815606342467192, -0.9041172563704749, -0.7699026741943047,
                      -0.5873179542866175, -0.3678314989981802, -0.1252334085114689,
                      0.1252334085114689, 0.3678314989981802, 0.5873179542866175,
                      0.7699026741943047, 0.9041172563704749, 0.9815606342467192])
_GL_WEIGHTS = np.array([0.0471753363865118, 0.1069393259953184, 0.1600783285433462,
                        0.2031674267230659, 0.2334925365383548, 0.2491470458134028,
                        0.2491470458134028, 0.2334925365383548, 0.2031674267230659,
                        0.1600783285433462, 0.1069393259953184, 0.0471753363865118])


@numba.njit(**_KERNEL, inline="always")
def _normal_cdf(h):  # pragma: no cover - compiled
    """Standard normal ``Phi(h)`` (absolute error below 1e-7, :func:`_half_erfc`)."""
    x = -h / math.sqrt(2.0)
    return _half_erfc(x, math.exp(-x * x))


@numba.njit(**_KERNEL)
def _bivariate_normal_cdf(h, k, r):  # pragma: no cover - compiled
    """``P(Z1 < h, Z2 < k)`` for standard normals of correlation ``r`` (|r| < 1).

    Plackett's integral over the correlation in the angle form, ``dP / dr = phi2`` and
    ``r = sin(theta)``: from ``r = 0`` (``Phi(h) Phi(k)``) for ``|r| < 0.925``, else from the
    nearer of ``r = 1`` (``Phi(min(h, k))``) and ``r = -1`` (``max(0, Phi(h) + Phi(k) -
    1)``), whose integrands have no layer at the end of the interval; 12 Gauss-Legendre
    points, absolute error below about 1e-6."""
    if abs(r) < 0.925:
        start, end = 0.0, math.asin(r)
        base = _normal_cdf(h) * _normal_cdf(k)
    elif r > 0.0:
        start, end = 0.5 * math.pi, math.asin(r)
        base = _normal_cdf(min(h, k))
    else:
        start, end = -0.5 * math.pi, math.asin(r)
        base = max(0.0, _normal_cdf(h) + _normal_cdf(k) - 1.0)
    half = 0.5 * (end - start)
    mid = 0.5 * (end + start)
    total = 0.0
    hk = h * k
    hh = h * h + k * k
    for n in range(_GL_NODES.shape[0]):
        theta = mid + half * _GL_NODES[n]
        sin = math.sin(theta)
        cos2 = 1.0 - sin * sin
        if cos2 > 0.0:
            total += _GL_WEIGHTS[n] * math.exp(-(hh - 2.0 * hk * sin) / (2.0 * cos2))
    return base + total * half / (2.0 * math.pi)


@numba.njit(**_KERNEL)
def _overlapping_edges(xs, delta, edge, r_grad):  # pragma: no cover - compiled
    """The darkness two overlapping images share at a pixel both their edges cross.

    A blurred edge is the chance that the pixel's blur places a point inside the image's
    disc, ``D = Phi(h)`` with ``h = -sqrt 2 x`` (``x`` of :func:`_edge_argument`), the
    edge taken as straight across the blur. The blurred union of two opaque shadows
    needs the chance that the point lies inside both, ``B = Phi2(h0, h1; r)``, with ``r``
    the correlation of the two edges' normal offsets under the blur, the cosine of the
    angle between the normals weighted by the edge widths ``edge`` (2, 2) ``(w_s, w_t)``:
    ``r = 1`` for two edges that run together (one image inside the other: the inner
    edge is hidden, ``B = min(D0, D1)``), ``r = 0`` for edges at right angles (``B = D0
    D1``, the product model), ``r = -1`` for edges facing each other. ``xs`` (2,) and
    ``delta`` (2, 2) are the pixel's edge arguments and offsets ``(ds, dt)`` from the two
    centres.

    Returns ``(B, inside0, inside1, density)``: with contrasts ``c`` the pixel's
    transmission is ``1 - c0 D0 - c1 D1 + c0 c1 B``; ``inside0`` is the chance that the
    point lies inside image 1 given that it lies on image 0's edge, ``Phi((h1 - r h0) /
    sqrt(1 - r^2))``, which takes the place of image 1's ``D`` in image 0's derivatives
    (``inside1`` the other way round); ``density`` is ``dB / dr``, and ``r_grad`` (2, 2)
    is filled with ``dr / d(ds, dt)`` of each image's offset."""
    w = edge
    q0 = math.sqrt((w[0, 0] * delta[0, 0]) ** 2 + (w[0, 1] * delta[0, 1]) ** 2)
    q1 = math.sqrt((w[1, 0] * delta[1, 0]) ** 2 + (w[1, 1] * delta[1, 1]) ** 2)
    r_grad[:] = 0.0
    r = 0.0
    if q0 > 0.0 and q1 > 0.0:
        a, b = w[0, 0] * w[1, 0], w[0, 1] * w[1, 1]
        r = (a * delta[0, 0] * delta[1, 0] + b * delta[0, 1] * delta[1, 1]) / (q0 * q1)
        if abs(r) < _MAX_EDGE_CORRELATION:
            for q in range(2):
                p = 1 - q
                qq = q0 * q0 if q == 0 else q1 * q1
                r_grad[q, 0] = (a * delta[p, 0] / (q0 * q1)
                                - r * w[q, 0] * w[q, 0] * delta[q, 0] / qq)
                r_grad[q, 1] = (b * delta[p, 1] / (q0 * q1)
                                - r * w[q, 1] * w[q, 1] * delta[q, 1] / qq)
    r = min(max(r, -_MAX_EDGE_CORRELATION), _MAX_EDGE_CORRELATION)
    h0 = -math.sqrt(2.0) * xs[0]
    h1 = -math.sqrt(2.0) * xs[1]
    s2 = 1.0 - r * r
    s = math.sqrt(s2)
    density = (math.exp(-(h0 * h0 - 2.0 * r * h0 * h1 + h1 * h1) / (2.0 * s2))
               / (2.0 * math.pi * s))
    return (_bivariate_normal_cdf(h0, h1, r), _normal_cdf((h1 - r * h0) / s),
            _normal_cdf((h0 - r * h1) / s), density)



@numba.njit(**_KERNEL)
def _fit_pixels(origin, y, fixed, fit):  # pragma: no cover - compiled
    """The pixels ``fit`` (K, n, n) of patches with pixel ``[0, 0]`` at ``origin`` (K, 2),
    listed view by view in row-major order: ``(starts (K + 1,), s (N,), t (N,), fixed (N,),
    y (N,))``, view ``v``'s pixels at ``starts[v]:starts[v + 1]``."""
    n_views = y.shape[0]
    starts = np.zeros(n_views + 1, dtype=np.int64)
    for view in range(n_views):
        starts[view + 1] = starts[view] + np.count_nonzero(fit[view])
    n = starts[n_views]
    ps, pt = np.empty(n), np.empty(n)
    fixed_out, y_out = np.empty(n), np.empty(n)
    m = 0
    for view in range(n_views):
        for i in range(y.shape[1]):
            for j in range(y.shape[2]):
                if fit[view, i, j]:
                    ps[m] = origin[view, 0] + j
                    pt[m] = origin[view, 1] + i
                    fixed_out[m] = fixed[view, i, j]
                    y_out[m] = y[view, i, j]
                    m += 1
    return starts, ps, pt, fixed_out, y_out


@numba.njit(**_KERNEL, fastmath=True)
def _pixel_normal_equations(starts, ps, pt, fixed, y, st, jac, rc, edge,
                            union):  # pragma: no cover - compiled
    """Cost ``sum r**2``, ``J^T J``, ``J^T r`` and ``sum_v J_v^T r_v r_v^T J_v`` (the sum
    over views of the outer products of each view's score) of the patch model,
    ``r = model - y``.

    The fitted pixels are listed view by view (:func:`_fit_pixels`): view ``v``'s at
    ``starts[v]:starts[v + 1]`` of ``ps, pt`` (their ``(s, t)``), ``fixed`` (the held
    neighbours' image there) and ``y`` (the normalised pixels). ``st`` (k, K, 2), ``jac``
    (k, K, 2, 3) and ``rc`` (k, 2) are each free particle's predicted centres, their
    derivatives and its radius and contrast, ``edge`` (k, 2) its edge widths ``(w_s,
    w_t)`` (:class:`ImageEdge`). The parameters are ordered ``(x, y, z, r, c)`` per
    particle. With ``union`` two free images (``k = 2``) are drawn as the blurred union of
    their shadows where both edges cross a pixel's blur (:func:`_overlapping_edges`), else
    every image as a factor of the product.

    Each view is computed in tight passes over its pixels (the edge arguments, the
    exponentials, the discs, the Jacobian rows), which the compiler vectorises where it
    can, and the rows are then reduced as dot products.
    """
    k = st.shape[0]
    n_par = 5 * k
    n_views = starts.shape[0] - 1
    n_pix = 0
    for view in range(n_views):
        n_pix = max(n_pix, starts[view + 1] - starts[view])
    jtj = np.zeros((n_par, n_par))
    jtr = np.zeros(n_par)
    meat = np.zeros((n_par, n_par))
    score = np.empty(n_par)
    cost = 0.0
    rows = np.empty((n_par, n_pix))
    res = np.empty(n_pix)
    rest = np.empty(n_pix)              # the other images' product at each pixel
    xs = np.empty((k, n_pix))           # edge argument of each pixel and image
    dxs = np.empty((k, n_pix))          # and its derivatives along s and t
    dxt = np.empty((k, n_pix))
    dxr = np.empty((k, n_pix))          # and with respect to the radius
    gauss = np.empty((k, n_pix))
    powers = np.empty(n_pix, dtype=np.int64)     # work space of _exp_neg_squares
    disc = np.empty((k, n_pix))
    f = np.empty((k, n_pix))            # each image's factor of the product
    x2 = np.empty(2)
    delta = np.empty((2, 2))
    inside = np.empty(2)
    r_grad = np.empty((2, 2))
    norm = 1.0 / math.sqrt(math.pi)
    for view in range(n_views):
        o = starts[view]
        m = starts[view + 1] - o
        for q in range(k):
            cs, ct = st[q, view, 0], st[q, view, 1]
            radius, w_s, w_t = rc[q, 0], edge[q, 0], edge[q, 1]
            for p in range(m):
                ds = ps[o + p] - cs
                dt = pt[o + p] - ct
                rho = math.sqrt(ds * ds + dt * dt)
                xs[q, p], dxs[q, p], dxt[q, p], dxr[q, p] = _edge_argument(ds, dt, rho, radius,
                                                                           w_s, w_t)
            _exp_neg_squares(xs[q], gauss[q], powers, m)
            contrast = rc[q, 1]
            for p in range(m):
                disc[q, p] = _half_erfc(xs[q, p], gauss[q, p])
                f[q, p] = 1.0 - contrast * disc[q, p]
        for p in range(m):
            res[p] = fixed[o + p]
        for q in range(k):
            for p in range(m):
                res[p] *= f[q, p]
        for p in range(m):
            res[p] -= y[o + p]
        for q in range(k):
            j0, j1, j2 = jac[q, view, 0, 0], jac[q, view, 0, 1], jac[q, view, 0, 2]
            k0, k1, k2 = jac[q, view, 1, 0], jac[q, view, 1, 1], jac[q, view, 1, 2]
            contrast = rc[q, 1]
            for p in range(m):                 # the held images and the other free ones
                rest[p] = fixed[o + p]
            for g in range(k):
                if g != q:
                    for p in range(m):
                        rest[p] *= f[g, p]
            for p in range(m):
                others = rest[p]
                slope = others * contrast * gauss[q, p] * norm      # df / dx
                rows[5 * q, p] = -slope * (dxs[q, p] * j0 + dxt[q, p] * k0)
                rows[5 * q + 1, p] = -slope * (dxs[q, p] * j1 + dxt[q, p] * k1)
                rows[5 * q + 2, p] = -slope * (dxs[q, p] * j2 + dxt[q, p] * k2)
                rows[5 * q + 3, p] = slope * dxr[q, p]
                rows[5 * q + 4, p] = -others * disc[q, p]
        if union and k == 2:
            _union_rows(o, m, ps, pt, fixed, y, st, jac, rc, edge, view, xs, dxs, dxt, dxr,
                        gauss, disc, rows, res, x2, delta, inside, r_grad)
        for p in range(m):
            cost += res[p] * res[p]
        for a in range(n_par):
            acc = 0.0
            for p in range(m):
                acc += rows[a, p] * res[p]
            jtr[a] += acc
            score[a] = acc
            for b in range(a, n_par):
                acc = 0.0
                for p in range(m):
                    acc += rows[a, p] * rows[b, p]
                jtj[a, b] += acc
        for a in range(n_par):
            for b in range(n_par):
                meat[a, b] += score[a] * score[b]
    for a in range(n_par):
        for b in range(a):
            jtj[a, b] = jtj[b, a]
    return cost, jtj, jtr, meat


@numba.njit(**_KERNEL, fastmath=True)
def _union_rows(o, m, ps, pt, fixed, y, st, jac, rc, edge, view, xs, dxs, dxt, dxr, gauss,
                disc, rows, res, x2, delta, inside, r_grad):  # pragma: no cover - compiled
    """Residuals and Jacobian rows, in place, of those of view ``view``'s ``m`` pixels
    (from ``o`` in the pixel lists) where both edges of two free images cross the pixel's
    blur: there the images are drawn as the blurred union of their shadows, not as the
    product of their blurred shadows that :func:`_pixel_normal_equations` (whose
    per-image passes ``xs ... disc`` this reads) wrote for every pixel (module notes)."""
    norm = 1.0 / math.sqrt(math.pi)
    for p in range(m):
        if not (_EDGE_BAND < disc[0, p] < 1.0 - _EDGE_BAND
                and _EDGE_BAND < disc[1, p] < 1.0 - _EDGE_BAND):
            continue
        held = fixed[o + p]
        for q in range(2):
            x2[q] = xs[q, p]
            delta[q, 0] = ps[o + p] - st[q, view, 0]
            delta[q, 1] = pt[o + p] - st[q, view, 1]
        both, inside[0], inside[1], density = _overlapping_edges(x2, delta, edge, r_grad)
        res[p] = (held * (1.0 - rc[0, 1] * disc[0, p] - rc[1, 1] * disc[1, p]
                          + rc[0, 1] * rc[1, 1] * both) - y[o + p])
        # the edges' correlation moves with the image centre too
        turn = held * rc[0, 1] * rc[1, 1] * density
        for q in range(2):
            g = 1 - q
            others = held * (1.0 - rc[g, 1] * inside[q])
            slope = rc[q, 1] * gauss[q, p] * norm
            for a in range(3):
                drho = -(dxs[q, p] * jac[q, view, 0, a] + dxt[q, p] * jac[q, view, 1, a])
                rows[5 * q + a, p] = (others * slope * drho
                                      - turn * (r_grad[q, 0] * jac[q, view, 0, a]
                                                + r_grad[q, 1] * jac[q, view, 1, a]))
            rows[5 * q + 3, p] = others * slope * dxr[q, p]
            rows[5 * q + 4, p] = held * (rc[g, 1] * both - disc[q, p])


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
