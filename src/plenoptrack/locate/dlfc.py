"""Direct Light Field Calibration (DLFC): a polynomial map from object space to views.

The DLFC of Hall et al. relates object-space position and view to the in-view position
of a point's image with two polynomials of full total order ``n`` in five variables::

    s = P_s(x, y, z, u, v)        t = P_t(x, y, z, u, v)

- ``x, y, z``: object-space position, mm (world frame of ``docs/conventions.md``:
  ``z = 0`` at the nominal focal plane, positive away from the camera);
- ``u, v``: view, sensor pixels from the centre of the microlens image (``u`` along
  sensor columns, ``v`` along rows);
- ``s, t``: position inside view ``(u, v)``, view pixels (``s`` columns, ``t`` rows).

The polynomials are fitted by linear least squares to dot-card images at known depths,
so they absorb lens distortion, misalignment and the non-linear depth dependence of
the thin-lens model without an explicit optical model. The total-order-4 basis in five
variables has ``C(4 + 5, 5) = 126`` monomials per output, the choice of the method
papers; orders 1 to 6 are supported.

Conditioning. Every variable is mapped to ``[-1, 1]`` over the fit data,
``q_n = (q - centre) / scale`` with ``centre`` the mid-range and ``scale`` the half-range,
before the monomials are formed. An affine change of variables maps the space of
total-order-``n`` polynomials onto itself, so this changes the coefficients but not the
fitted function. The centre and scale are part of the calibration; the fitted ranges
(``centre +- scale``) also tell where the polynomial would extrapolate.

Monomial order (the coefficient order stored in calibration files): by total degree,
then by exponent tuple ``(e_x, e_y, e_z, e_u, e_v)`` in descending lexicographic order,
i.e. ``1, x, y, z, u, v, x^2, x y, x z, x u, x v, y^2, y z, ...`` (see
:func:`monomial_exponents`).

References
----------
Hall et al., Volumetric calibration of a plenoptic camera (Applied Optics, 2018): the
DLFC. Its use for particle location with a fourth-order fit: the conference and journal
papers on perspective-shifted plenoptic images (2019), section 2.3.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Any

import numba
import numpy as np
import pandas as pd
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.blas import dsyrk

from .._columns import LF_COLUMNS, POS_COLUMNS
from ..errors import CalibrationError

__all__ = [
    "DLFC", "FitReport", "fit_dlfc", "dot_position_errors", "model_error_by_depth",
    "monomial_exponents", "n_monomials",
    "INPUT_VARIABLES", "OUTPUT_VARIABLES", "SUPPORTED_ORDERS", "DLFC_FORMAT", "DLFC_VERSION",
]

INPUT_VARIABLES = (*POS_COLUMNS, LF_COLUMNS[0], LF_COLUMNS[1])
"""Polynomial variables in order: x, y, z (mm), u, v (sensor pixels)."""
OUTPUT_VARIABLES = (LF_COLUMNS[2], LF_COLUMNS[3])
"""Polynomial outputs in order: s, t (view pixels)."""
SUPPORTED_ORDERS = (1, 2, 3, 4, 5, 6)
"""Total polynomial orders accepted by :func:`fit_dlfc` and calibration files."""
DLFC_FORMAT = "plenoptrack-dlfc"
DLFC_VERSION = 1

_N_VARS = len(INPUT_VARIABLES)
_FIT_CHUNK = 16384          # rows of the design matrix formed at once during the fit
_RANK_TOL = 1e-13           # smallest eigenvalue ratio of A^T A accepted as full rank


# --- monomial basis ------------------------------------------------------------------

def n_monomials(order: int, n_vars: int = _N_VARS) -> int:
    """Number of monomials of total degree <= ``order`` in ``n_vars`` variables.

    Equal to ``C(order + n_vars, n_vars)``: 56, 126 and 252 for orders 3, 4 and 5 in
    five variables.
    """
    return math.comb(order + n_vars, n_vars)


def _check_order(order: Any, *, source: str = "order") -> int:
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)) \
            or int(order) not in SUPPORTED_ORDERS:
        raise CalibrationError(f"{source}: DLFC order must be one of {list(SUPPORTED_ORDERS)}; "
                               f"got {order!r}")
    return int(order)


@lru_cache(maxsize=None)
def _basis_tables(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exponents (T, 5), parent index (T,) and multiplying variable (T,) of the basis.

    Monomial ``k > 0`` equals monomial ``parent[k]`` times variable ``var[k]``; parents
    always come earlier, so all monomials are built with one multiplication each.
    """
    exps: list[tuple[int, ...]] = []
    for degree in range(order + 1):
        level = [e for e in _compositions(degree, _N_VARS)]
        level.sort(reverse=True)
        exps.extend(level)
    index = {e: k for k, e in enumerate(exps)}
    parent = np.zeros(len(exps), dtype=np.int64)
    var = np.zeros(len(exps), dtype=np.int64)
    for k, e in enumerate(exps[1:], start=1):
        j = next(i for i, ei in enumerate(e) if ei > 0)
        parent[k] = index[e[:j] + (e[j] - 1,) + e[j + 1:]]
        var[k] = j
    table = np.array(exps, dtype=np.int64)
    for arr in (table, parent, var):
        arr.setflags(write=False)
    return table, parent, var


def _compositions(total: int, parts: int):
    """All tuples of ``parts`` non-negative integers summing to ``total``."""
    if parts == 1:
        yield (total,)
        return
    for first in range(total, -1, -1):
        for rest in _compositions(total - first, parts - 1):
            yield (first, *rest)


def monomial_exponents(order: int = 4) -> np.ndarray:
    """Exponent table of the DLFC basis.

    Parameters
    ----------
    order : int
        Total polynomial order (one of :data:`SUPPORTED_ORDERS`).

    Returns
    -------
    (T, 5) int64 ndarray
        Row ``k`` holds the exponents of ``(x, y, z, u, v)`` in monomial ``k``, ordered
        by total degree, then descending lexicographically; ``T = n_monomials(order)``.
        Row 0 is the constant term.

    Examples
    --------
    >>> monomial_exponents(4).shape
    (126, 5)
    >>> monomial_exponents(2)[:7].tolist()
    [[0, 0, 0, 0, 0], [1, 0, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 1, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 0, 1], [2, 0, 0, 0, 0]]
    """
    return _basis_tables(_check_order(order))[0].copy()


# --- compiled kernels ----------------------------------------------------------------

# The kernels are called with the read-only coefficient arrays that a DLFC holds; the fit
# passes read-only views too, so that numba compiles one specialisation, not two (the
# read-only flag is part of an array's numba type).


def _readonly(arr: np.ndarray) -> np.ndarray:
    """A read-only view of ``arr`` (same data, no copy)."""
    view = arr.view()
    view.setflags(write=False)
    return view


_BLOCK = 128  # points per block: the block's monomials stay in cache


_SERIAL_POINTS = 4 * _BLOCK
"""Inputs up to this many points are evaluated on one thread: waking the thread pool
costs more than the work (and much more on a machine whose cores are busy)."""


@numba.njit(cache=True)
def _eval_block(q, i0, parent, var, coef, with_jac, out, jac):  # pragma: no cover - compiled
    """Evaluate both polynomials (and d/dq0..q2) at points ``i0 .. i0 + _BLOCK`` of ``q``
    (5, N) into ``out`` (2, N) and ``jac`` (2, 3, N)."""
    n_terms = parent.shape[0]
    m = min(_BLOCK, q.shape[1] - i0)
    mono = np.empty((n_terms, _BLOCK))
    acc = np.empty((2, _BLOCK))
    for i in range(m):
        mono[0, i] = 1.0
        acc[0, i] = coef[0, 0]
        acc[1, i] = coef[1, 0]
    if with_jac:
        dmono = np.zeros((3, n_terms, _BLOCK))
        dacc = np.zeros((2, 3, _BLOCK))
    else:
        dmono = np.zeros((3, 0, _BLOCK))
        dacc = np.zeros((2, 3, 0))
    for k in range(1, n_terms):
        p = parent[k]
        j = var[k]
        c0 = coef[0, k]
        c1 = coef[1, k]
        for i in range(m):
            val = mono[p, i] * q[j, i0 + i]
            mono[k, i] = val
            acc[0, i] += c0 * val
            acc[1, i] += c1 * val
        if with_jac:
            for d in range(3):
                same = 1.0 if d == j else 0.0
                for i in range(m):
                    dv = dmono[d, p, i] * q[j, i0 + i] + same * mono[p, i]
                    dmono[d, k, i] = dv
                    dacc[0, d, i] += c0 * dv
                    dacc[1, d, i] += c1 * dv
    for i in range(m):
        out[0, i0 + i] = acc[0, i]
        out[1, i0 + i] = acc[1, i]
    if with_jac:
        for d in range(3):
            for i in range(m):
                jac[0, d, i0 + i] = dacc[0, d, i]
                jac[1, d, i0 + i] = dacc[1, d, i]


@numba.njit(parallel=True, cache=True)
def _eval_kernel(q, parent, var, coef, with_jac):  # pragma: no cover - compiled
    """Evaluate both polynomials (and d/dq0..q2) at normalised points ``q`` (5, N),
    blocks of points in parallel."""
    n = q.shape[1]
    out = np.empty((2, n))
    jac = np.empty((2, 3, n if with_jac else 0))
    for b in numba.prange((n + _BLOCK - 1) // _BLOCK):
        _eval_block(q, b * _BLOCK, parent, var, coef, with_jac, out, jac)
    return out, jac


@numba.njit(cache=True)
def _eval_serial(q, parent, var, coef, with_jac):  # pragma: no cover - compiled
    """:func:`_eval_kernel` on one thread, for few points."""
    n = q.shape[1]
    out = np.empty((2, n))
    jac = np.empty((2, 3, n if with_jac else 0))
    for b in range((n + _BLOCK - 1) // _BLOCK):
        _eval_block(q, b * _BLOCK, parent, var, coef, with_jac, out, jac)
    return out, jac


def _powers(values: np.ndarray, top: int) -> np.ndarray:
    """``values ** j`` for ``j = 0 .. top`` along a new last axis, by repeated products."""
    out = np.empty((*values.shape, top + 1))
    out[..., 0] = 1.0
    for j in range(1, top + 1):
        out[..., j] = out[..., j - 1] * values
    return out


@numba.njit(cache=True)
def _coefficients_one(pos, xyz_e, tensor, centre, scale, powers, c, dc):  # pragma: no cover
    """``C = X(p) G`` (B, 2) and ``dC/d(x, y, z)`` (3, B, 2) at one position, into ``c``
    and ``dc`` (``dc`` with a zero first axis skips the derivatives)."""
    n_a, n_b = tensor.shape[0], tensor.shape[1]
    with_deriv = dc.shape[0] == 3
    top = powers.shape[1] - 1
    for j in range(3):
        qn = (pos[j] - centre[j]) / scale[j]
        powers[j, 0] = 1.0
        for e in range(1, top + 1):
            powers[j, e] = powers[j, e - 1] * qn
    c[:, :] = 0.0
    if with_deriv:
        dc[:, :, :] = 0.0
    for a in range(n_a):
        e0, e1, e2 = xyz_e[a, 0], xyz_e[a, 1], xyz_e[a, 2]
        f0, f1, f2 = powers[0, e0], powers[1, e1], powers[2, e2]
        xm = f0 * f1 * f2
        if with_deriv:
            d0 = e0 * powers[0, e0 - 1] / scale[0] if e0 > 0 else 0.0
            d1 = e1 * powers[1, e1 - 1] / scale[1] if e1 > 0 else 0.0
            d2 = e2 * powers[2, e2 - 1] / scale[2] if e2 > 0 else 0.0
            g0, g1, g2 = d0 * f1 * f2, f0 * d1 * f2, f0 * f1 * d2
        for b in range(n_b):
            for ch in range(2):
                coef = tensor[a, b, ch]
                if coef == 0.0:
                    continue
                c[b, ch] += xm * coef
                if with_deriv:
                    dc[0, b, ch] += g0 * coef
                    dc[1, b, ch] += g1 * coef
                    dc[2, b, ch] += g2 * coef


@numba.njit(cache=True)
def _views_kernel(positions, w, xyz_e, tensor, centre, scale,
                  with_jac):  # pragma: no cover - compiled
    """``(s, t)`` (K, M, 2) and, with ``with_jac``, ``d(s, t)/d(x, y, z)`` (K, M, 2, 3) of
    positions (K, 3) in the views of the basis ``w`` (M, B): ``C = X(p) G`` once per
    position, then one ``B``-term product per view."""
    n_k, n_m, n_b = positions.shape[0], w.shape[0], w.shape[1]
    powers = np.empty((3, xyz_e.max() + 1))
    c = np.empty((n_b, 2))
    dc = np.empty((3 if with_jac else 0, n_b, 2))
    st = np.empty((n_k, n_m, 2))
    jac = np.empty((n_k, n_m if with_jac else 0, 2, 3))
    for k in range(n_k):
        _coefficients_one(positions[k], xyz_e, tensor, centre, scale, powers, c, dc)
        for m in range(n_m):
            for ch in range(2):
                acc = 0.0
                for b in range(n_b):
                    acc += w[m, b] * c[b, ch]
                st[k, m, ch] = acc
                if with_jac:
                    for d in range(3):
                        acc = 0.0
                        for b in range(n_b):
                            acc += w[m, b] * dc[d, b, ch]
                        jac[k, m, ch, d] = acc
    return st, jac


def _evaluate(q, parent, var, coef, with_jac):
    """The polynomials (and their derivatives) at ``q`` (5, N), on one thread for small N."""
    kernel = _eval_serial if q.shape[1] <= _SERIAL_POINTS else _eval_kernel
    return kernel(q, parent, var, coef, with_jac)


@numba.njit(parallel=True, cache=True)
def _design_kernel(q, parent, var):  # pragma: no cover - compiled
    """Design matrix (N, T) of the monomials at normalised points ``q`` (5, N)."""
    n = q.shape[1]
    n_terms = parent.shape[0]
    a = np.empty((n, n_terms))
    for i in numba.prange(n):
        a[i, 0] = 1.0
        for k in range(1, n_terms):
            a[i, k] = a[i, parent[k]] * q[var[k], i]
    return a


# --- fit report ----------------------------------------------------------------------

@dataclass(frozen=True)
class FitReport:
    """How well a DLFC fits its calibration points.

    All residuals are ``measured - predicted`` in view pixels, over the points kept
    after robust rejection.

    Attributes
    ----------
    rms_s_px, rms_t_px : float
        RMS residual of ``s`` and ``t``.
    rms_px : float
        RMS of the residual vector length, ``sqrt(mean(ds**2 + dt**2))``.
    max_px : float
        Largest residual vector length.
    n_points : int
        Points used in the final fit.
    n_rejected : int
        Points dropped by the robust refit (0 without it).
    group_by : str or None
        Name of the grouping of the per-group residuals (e.g. ``"z"`` for one group per
        dot-card depth), None if no grouping was given.
    group_keys : tuple
        Group values, sorted.
    group_rms_px : tuple of float
        ``rms_px`` within each group.
    group_n_points : tuple of int
        Kept points in each group.
    position_rms_mm : tuple of float
        RMS over the calibration dots of ``solved - known`` position (x, y, z), mm, each
        dot solved from its kept views through the fitted DLFC
        (:func:`dot_position_errors`): the DLFC's model error plus the dots' own centroid
        noise. Empty when not measured (dots seen in fewer than 4 views, or a file
        written by an older version).
    model_error_by_depth_mm : tuple of tuple of float
        The DLFC's model error per calibration depth: rows ``(z, e_x, e_y, e_z)``, mm, one
        per dot-card depth (or per depth bin when the dots do not lie on a few cards),
        sorted by ``z``. ``e`` is the error of the fitted mapping that reaches a
        particle (:func:`model_error_by_depth` with the dots' shift leverage): of the dots'
        error beyond their own centroid noise (``d`` the solved-minus-known error,
        :func:`dot_position_errors`), the part neighbouring dots share counts whole and
        each dot's own part only as far as the fit takes it up. The dots' depth errors
        are mostly their noise, which a particle's own least-squares error already
        carries, and their lateral excess on a printed card mostly print error, which a
        particle does not share. A particle's uncertainty uses the value at its depth
        (:func:`~plenoptrack.locate.uncertainty.model_error_mm`). Empty when not
        measured.
    """

    rms_s_px: float
    rms_t_px: float
    rms_px: float
    max_px: float
    n_points: int
    n_rejected: int = 0
    group_by: str | None = None
    group_keys: tuple = ()
    group_rms_px: tuple = ()
    group_n_points: tuple = ()
    position_rms_mm: tuple = ()
    model_error_by_depth_mm: tuple = ()

    def group_table(self) -> pd.DataFrame:
        """Per-group residuals as a DataFrame (columns: group key, rms_px, n_points)."""
        return pd.DataFrame({self.group_by or "group": list(self.group_keys),
                             "rms_px": list(self.group_rms_px),
                             "n_points": list(self.group_n_points)})

    def to_dict(self) -> dict:
        return {
            "rms_s_px": self.rms_s_px, "rms_t_px": self.rms_t_px, "rms_px": self.rms_px,
            "max_px": self.max_px, "n_points": self.n_points, "n_rejected": self.n_rejected,
            "group_by": self.group_by, "group_keys": [_json_scalar(k) for k in self.group_keys],
            "group_rms_px": list(self.group_rms_px),
            "group_n_points": list(self.group_n_points),
            "position_rms_mm": list(self.position_rms_mm),
            "model_error_by_depth_mm": [list(row) for row in self.model_error_by_depth_mm],
        }

    @classmethod
    def from_dict(cls, data: Mapping, *, source: str = "DLFC fit report") -> "FitReport":
        try:
            return cls(
                rms_s_px=float(data["rms_s_px"]), rms_t_px=float(data["rms_t_px"]),
                rms_px=float(data["rms_px"]), max_px=float(data["max_px"]),
                n_points=int(data["n_points"]), n_rejected=int(data.get("n_rejected", 0)),
                group_by=data.get("group_by"),
                group_keys=tuple(data.get("group_keys", ())),
                group_rms_px=tuple(float(r) for r in data.get("group_rms_px", ())),
                group_n_points=tuple(int(n) for n in data.get("group_n_points", ())),
                position_rms_mm=tuple(float(e) for e in data.get("position_rms_mm", ())),
                model_error_by_depth_mm=_depth_rows(data.get("model_error_by_depth_mm", ())),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"{source}: corrupt fit report ({exc!r}); "
                                   "re-run the DLFC calibration") from None


def _depth_rows(rows) -> tuple:
    """Validated ``(z, e_x, e_y, e_z)`` rows, sorted by z."""
    out = tuple(tuple(float(e) for e in row) for row in rows)
    if any(len(row) != 4 or not all(math.isfinite(e) for e in row) for row in out):
        raise ValueError("model_error_by_depth_mm rows must be 4 finite numbers "
                         "(z, e_x, e_y, e_z)")
    return tuple(sorted(out))


def _json_scalar(value):
    return value.item() if isinstance(value, np.generic) else value


# --- the calibration -----------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class DLFC:
    """A fitted Direct Light Field Calibration.

    Parameters
    ----------
    order : int
        Total polynomial order.
    coefficients : (2, T) float ndarray
        Coefficients of ``P_s`` (row 0) and ``P_t`` (row 1) on the normalised monomial
        basis, in the order of :func:`monomial_exponents`; view pixels.
    centre, scale : (5,) float ndarray
        Normalisation of ``(x, y, z, u, v)``: ``q_n = (q - centre) / scale``; mm for
        x, y, z and sensor pixels for u, v. ``scale > 0``.
    report : FitReport or None
        Fit residuals (None for a calibration built by hand).

    Raises
    ------
    CalibrationError
        If the order is unsupported or an array has the wrong shape or is not finite.
    """

    order: int
    coefficients: np.ndarray
    centre: np.ndarray
    scale: np.ndarray
    report: FitReport | None = None
    _parent: np.ndarray = field(init=False, repr=False)
    _var: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        order = _check_order(self.order)
        exps, parent, var = _basis_tables(order)
        n_terms = len(exps)
        coef = _as_finite(self.coefficients, (2, n_terms), "coefficients",
                          f"2 x {n_terms} for order {order}")
        centre = _as_finite(self.centre, (_N_VARS,), "centre", "5 values (x, y, z, u, v)")
        scale = _as_finite(self.scale, (_N_VARS,), "scale", "5 values (x, y, z, u, v)")
        if np.any(scale <= 0):
            raise CalibrationError(f"DLFC scale must be positive for every variable; got "
                                   f"{scale.tolist()}; re-run the DLFC calibration")
        for name, value in (("order", order), ("coefficients", coef), ("centre", centre),
                            ("scale", scale), ("_parent", parent), ("_var", var)):
            object.__setattr__(self, name, value)

    def __repr__(self) -> str:
        rms = "n/a" if self.report is None else f"{self.report.rms_px:.4g} px"
        return f"DLFC(order={self.order}, n_terms={self.n_terms}, rms={rms})"

    # --- properties ---------------------------------------------------------------
    @property
    def n_terms(self) -> int:
        """Number of monomials per output polynomial."""
        return self.coefficients.shape[1]

    @property
    def exponents(self) -> np.ndarray:
        """(T, 5) exponent table of the basis (see :func:`monomial_exponents`)."""
        return monomial_exponents(self.order)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 5) lower and upper limits of ``(x, y, z, u, v)`` in the fit data."""
        return np.stack([self.centre - self.scale, self.centre + self.scale])

    @cached_property
    def view_factorisation(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The polynomials regrouped as polynomials in ``(u, v)`` with xyz-dependent terms.

        ``P_c(x, y, z, u, v) = sum_{a, b} G[a, b, c] X_a(x, y, z) V_b(u, v)`` with ``X_a``
        and ``V_b`` the monomials of the normalised variables. A particle seen in many
        views then costs one evaluation of the ``X_a`` (and their derivatives) plus a
        small product per view, instead of the full basis per view.

        Returns
        -------
        xyz_exponents : (A, 3) int ndarray
            Exponents of (x, y, z) in ``X_a``.
        uv_exponents : (B, 2) int ndarray
            Exponents of (u, v) in ``V_b``; row 0 is the constant (0, 0).
        tensor : (A, B, 2) float ndarray
            Coefficients ``G``, view pixels.
        """
        exps = self.exponents
        xyz_e, xyz_idx = np.unique(exps[:, :3], axis=0, return_inverse=True)
        uv_e, uv_idx = np.unique(exps[:, 3:], axis=0, return_inverse=True)
        tensor = np.zeros((len(xyz_e), len(uv_e), 2))
        tensor[xyz_idx.ravel(), uv_idx.ravel()] = self.coefficients.T
        for arr in (xyz_e, uv_e, tensor):
            arr.setflags(write=False)
        return xyz_e, uv_e, tensor

    @cached_property
    def _view_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:attr:`view_factorisation` as the kernels take it: ``xyz_e`` (A, 3) int64,
        ``uv_e`` (B, 2) int64 and ``tensor`` (A, B, 2), contiguous and read-only."""
        xyz_e, uv_e, tensor = self.view_factorisation
        return tuple(_readonly(np.ascontiguousarray(a, dtype=dt)) for a, dt in
                     ((xyz_e, np.int64), (uv_e, np.int64), (tensor, np.float64)))

    def view_basis(self, u, v) -> np.ndarray:
        """Monomials ``V_b`` of :attr:`view_factorisation` for a set of views.

        Parameters
        ----------
        u, v : (M,) array_like, float
            Views, sensor pixels from the microlens-image centre.

        Returns
        -------
        (M, B) float ndarray
            ``V_b(u_m, v_m)`` of the normalised ``(u, v)``; pass it to
            :meth:`predict_in_views`.
        """
        _, uv_e, _ = self._view_tables
        un = (np.asarray(u, dtype=float).ravel() - self.centre[3]) / self.scale[3]
        vn = (np.asarray(v, dtype=float).ravel() - self.centre[4]) / self.scale[4]
        top = int(uv_e.max())
        return np.ascontiguousarray(_powers(un, top)[:, uv_e[:, 0]]
                                    * _powers(vn, top)[:, uv_e[:, 1]])

    def predict_in_views(self, xyz, basis, *, jacobian: bool = False):
        """:meth:`predict` (and :meth:`jacobian_xyz`) of many positions in one set of views.

        The same polynomials in their view-factorised form: a position costs one
        evaluation of its ``(x, y, z)`` monomials and a ``B``-term product per view, far
        less than the full basis per view when the same views serve many calls.

        Parameters
        ----------
        xyz : (K, 3) array_like, float
            Object-space positions, mm.
        basis : (M, B) float ndarray
            :meth:`view_basis` of the views.
        jacobian : bool
            Also return ``d(s, t) / d(x, y, z)``.

        Returns
        -------
        st : (K, M, 2) float ndarray
            ``(s, t)``, view pixels.
        jac : (K, M, 2, 3) float ndarray
            Only with ``jacobian``: view pixels per mm.
        """
        xyz_e, _, tensor = self._view_tables
        positions = np.ascontiguousarray(np.reshape(xyz, (-1, 3)), dtype=np.float64)
        st, jac = _views_kernel(positions, np.ascontiguousarray(basis, dtype=np.float64),
                                xyz_e, tensor, self._centre_xyz, self._scale_xyz,
                                bool(jacobian))
        return (st, jac) if jacobian else st

    @property
    def view_model(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What a compiled kernel needs to evaluate :meth:`predict_in_views` itself:
        ``(xyz_e, tensor, centre, scale)``, the ``(x, y, z)`` exponents (A, 3) int64 and
        coefficients ``G`` (A, B, 2) of :attr:`view_factorisation`, and the centre and
        scale (3,) that normalise ``(x, y, z)``; with :meth:`view_basis` ``W``,
        ``(s, t) = W X(p) G`` (``plenoptrack.locate.dlfc._views_kernel``)."""
        xyz_e, _, tensor = self._view_tables
        return xyz_e, tensor, self._centre_xyz, self._scale_xyz

    @cached_property
    def _centre_xyz(self) -> np.ndarray:
        return _readonly(np.ascontiguousarray(self.centre[:3], dtype=np.float64))

    @cached_property
    def _scale_xyz(self) -> np.ndarray:
        return _readonly(np.ascontiguousarray(self.scale[:3], dtype=np.float64))

    # --- evaluation ---------------------------------------------------------------
    def _normalised(self, x, y, z, u, v) -> tuple[np.ndarray, tuple[int, ...]]:
        arrays = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (x, y, z, u, v)))
        shape = arrays[0].shape
        q = np.empty((_N_VARS, arrays[0].size))
        for i, a in enumerate(arrays):
            np.subtract(a.ravel(), self.centre[i], out=q[i])
            q[i] /= self.scale[i]
        return q, shape

    def predict(self, x, y, z, u, v) -> tuple[np.ndarray, np.ndarray]:
        """In-view position of object point(s) ``(x, y, z)`` in view(s) ``(u, v)``.

        Parameters
        ----------
        x, y, z : array_like, float
            Object-space position, mm; broadcast together with ``u, v``.
        u, v : array_like, float
            View, sensor pixels from the microlens-image centre.

        Returns
        -------
        s, t : float ndarray
            In-view column and row, view pixels, of the broadcast shape.
        """
        q, shape = self._normalised(x, y, z, u, v)
        out, _ = _evaluate(q, self._parent, self._var, self.coefficients, False)
        return out[0].reshape(shape), out[1].reshape(shape)

    def predict_with_jacobian(self, x, y, z, u, v) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict` and :meth:`jacobian_xyz` from one pass over the basis.

        Returns
        -------
        st : (..., 2) float ndarray
            ``(s, t)``, view pixels.
        jac : (..., 2, 3) float ndarray
            ``d(s, t) / d(x, y, z)``, view pixels per mm.
        """
        q, shape = self._normalised(x, y, z, u, v)
        out, jac = _evaluate(q, self._parent, self._var, self.coefficients, True)
        jac = jac / self.scale[:3, None]
        st = out.T.reshape(*shape, 2)
        return st, np.moveaxis(jac, -1, 0).reshape(*shape, 2, 3)

    def jacobian_xyz(self, x, y, z, u, v) -> np.ndarray:
        """Analytic derivatives of ``(s, t)`` with respect to ``(x, y, z)``.

        Parameters
        ----------
        x, y, z, u, v : array_like, float
            As for :meth:`predict` (mm and sensor pixels), broadcast together.

        Returns
        -------
        (..., 2, 3) float ndarray
            ``J[..., i, j] = d(s, t)_i / d(x, y, z)_j``, view pixels per mm.
        """
        return self.predict_with_jacobian(x, y, z, u, v)[1]

    def local_magnification(self, x, y, z) -> np.ndarray:
        """Lateral magnification at object point(s), view pixels per mm.

        Evaluated in the central view ``u = v = 0`` as ``sqrt(|det J_xy|)`` with
        ``J_xy = d(s, t) / d(x, y)``: the linear scale that preserves areas, so a
        particle of area ``A`` px^2 in a view measures ``A / m**2`` mm^2 and a length of
        ``L`` px measures ``L / m`` mm (for a locally isotropic mapping).

        Parameters
        ----------
        x, y, z : array_like, float
            Object-space position, mm, broadcast together.

        Returns
        -------
        float ndarray
            Magnification ``m``, view pixels per mm, of the broadcast shape.
        """
        jac = self.jacobian_xyz(x, y, z, 0.0, 0.0)
        det = jac[..., 0, 0] * jac[..., 1, 1] - jac[..., 0, 1] * jac[..., 1, 0]
        return np.sqrt(np.abs(det))

    # --- serialisation ------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-ready description (the ``dlfc`` section of a calibration file)."""
        return {
            "format": DLFC_FORMAT,
            "version": DLFC_VERSION,
            "order": self.order,
            "variables": list(INPUT_VARIABLES),
            "outputs": list(OUTPUT_VARIABLES),
            "exponents": self.exponents.tolist(),
            "centre": self.centre.tolist(),
            "scale": self.scale.tolist(),
            "coefficients": self.coefficients.tolist(),
            "fit": None if self.report is None else self.report.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Mapping, *, source: str = "DLFC calibration") -> "DLFC":
        """Rebuild a DLFC from :meth:`to_dict` output, validating every field.

        Raises
        ------
        CalibrationError
            If the section is not a DLFC, of another version, of an unknown order, or
            has arrays of the wrong shape, NaN or infinite values, or another basis.
        """
        if not isinstance(data, Mapping) or data.get("format") != DLFC_FORMAT:
            raise CalibrationError(f"{source}: not a DLFC section (missing format tag "
                                   f"{DLFC_FORMAT!r}); re-run the DLFC calibration")
        if data.get("version") != DLFC_VERSION:
            raise CalibrationError(f"{source}: DLFC version {data.get('version')!r} is not "
                                   f"supported (this plenoptrack reads version {DLFC_VERSION}); "
                                   "re-run the DLFC calibration")
        missing = [k for k in ("order", "centre", "scale", "coefficients") if k not in data]
        if missing:
            raise CalibrationError(f"{source}: DLFC section lacks {missing}; "
                                   "re-run the DLFC calibration")
        order = _check_order(data["order"], source=source)
        for key, expected in (("variables", INPUT_VARIABLES), ("outputs", OUTPUT_VARIABLES)):
            if key in data and tuple(data[key]) != expected:
                raise CalibrationError(f"{source}: DLFC {key} are {list(data[key])}, expected "
                                       f"{list(expected)}")
        if "exponents" in data:
            try:
                exps = np.asarray(data["exponents"], dtype=np.int64)
            except (TypeError, ValueError):
                exps = None
            if exps is None or not np.array_equal(exps, _basis_tables(order)[0]):
                raise CalibrationError(f"{source}: DLFC exponent table does not match the "
                                       f"order-{order} basis of this plenoptrack; the "
                                       "coefficients cannot be interpreted")
        report = data.get("fit")
        try:
            return cls(order=order, coefficients=data["coefficients"], centre=data["centre"],
                       scale=data["scale"],
                       report=None if report is None else FitReport.from_dict(report, source=source))
        except CalibrationError as exc:
            raise CalibrationError(f"{source}: {exc}") from None


def _as_finite(value, shape: tuple[int, ...], name: str, expected: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"DLFC {name} must be numeric, {expected}; got "
                               f"{type(value).__name__}") from None
    if arr.shape != shape:
        raise CalibrationError(f"DLFC {name} must have shape {shape} ({expected}); "
                               f"got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"DLFC {name} contains NaN or infinite values; "
                               "re-run the DLFC calibration")
    arr.setflags(write=False)
    return arr


# --- fitting -------------------------------------------------------------------------

def fit_dlfc(data, *, order: int = 4, group_by=None, reject_k: float | None = None,
             max_reject_iter: int = 10) -> DLFC:
    """Fit the DLFC polynomials to calibration points by linear least squares.

    Parameters
    ----------
    data : DataFrame or mapping of array_like
        Calibration points with columns/keys ``x, y, z`` (mm), ``u, v`` (sensor pixels)
        and ``s, t`` (view pixels), one row per dot per view, all of the same length.
    order : int, default 4
        Total polynomial order (126 terms per output for 4).
    group_by : str or array_like, optional
        Report residuals per group: a column/key name (e.g. ``"z"`` for one group per
        dot-card depth, or a card id column) or an array of labels, one per point. The
        model error by depth (:func:`model_error_by_depth`) is then measured per group
        too, each at the mean depth of its dots (one group per card: a card tilted on
        its mount has its dots at many depths); without groups, per distinct depth.
    reject_k : float, optional
        If given, refit robustly: drop points whose residual length exceeds
        ``median + reject_k * 1.4826 * MAD`` of the residual lengths and refit, until
        none is dropped (at most ``max_reject_iter`` rounds). ``None`` fits once.
    max_reject_iter : int, default 10
        Maximum number of robust refits.

    Returns
    -------
    DLFC
        Fitted calibration; ``DLFC.report`` holds the residuals and rejection count.

    Raises
    ------
    CalibrationError
        If a column is missing, values are not finite, a variable does not vary, there
        are fewer points than coefficients, or the points do not determine the
        polynomial (rank-deficient design, e.g. too few depths for the order).

    Notes
    -----
    The design matrix is formed in blocks and reduced to the normal equations on the
    normalised basis, so memory stays ``O(block * T)`` however many points are given.
    They are formed once: each robust refit subtracts the rows it rejects, so a refit
    costs one evaluation of the polynomials, not a new pass over the design.
    The normalised design is well conditioned (condition number about 70 for order 4
    on dot-card grids), so the Cholesky solve with one step of iterative refinement is
    as accurate as ``lstsq``/QR here and several times faster.
    """
    order = _check_order(order)
    pts, groups, group_name = _fit_inputs(data, group_by)
    n_terms = n_monomials(order)
    if len(pts) <= n_terms:
        raise CalibrationError(f"DLFC order {order} has {n_terms} coefficients per output but "
                               f"only {len(pts)} calibration points were given; use more dots, "
                               "depths or views, or a lower order")
    lo, hi = pts[:, :_N_VARS].min(axis=0), pts[:, :_N_VARS].max(axis=0)
    flat = np.flatnonzero(hi <= lo)
    if flat.size:
        names = [INPUT_VARIABLES[i] for i in flat]
        raise CalibrationError(f"calibration points do not vary in {names}; dot-card data must "
                               "span x, y, z, u and v")
    centre, scale = (lo + hi) / 2, (hi - lo) / 2
    _, parent, var = _basis_tables(order)
    q = ((pts[:, :_N_VARS] - centre) / scale).T.copy()
    st = pts[:, _N_VARS:]
    keep = np.ones(len(pts), dtype=bool)
    gram, atb = _normal_equations(q, st, parent, var)
    for round_ in range(max_reject_iter + 2):
        factor = _factor_gram(gram, order)
        coef = cho_solve(factor, atb).T.copy()
        model, _ = _eval_kernel(q, parent, var, _readonly(coef), False)
        resid = st - model.T
        if reject_k is None or round_ > max_reject_iter:
            break
        length = np.hypot(resid[:, 0], resid[:, 1])
        threshold = _robust_threshold(length[keep], reject_k)
        new_keep = keep & (length <= threshold)
        if new_keep.sum() == keep.sum():
            break
        if new_keep.sum() <= n_terms:
            raise CalibrationError(f"robust DLFC refit would keep only {new_keep.sum()} points "
                                   f"for {n_terms} coefficients; raise reject_k")
        # remove the rejected points from the normal equations instead of re-forming them
        dropped = keep & ~new_keep
        gram_r, atb_r = _normal_equations(q[:, dropped], st[dropped], parent, var)
        gram -= gram_r
        atb -= atb_r
        keep = new_keep
    # one step of iterative refinement on the final point set
    _, atr = _normal_equations(q[:, keep], resid[keep], parent, var, with_gram=False)
    coef = coef + cho_solve(factor, atr).T
    model, _ = _eval_kernel(q, parent, var, _readonly(coef), False)
    resid = st - model.T
    report = _fit_report(resid, keep, groups, group_name)
    dlfc = DLFC(order=order, coefficients=coef, centre=centre, scale=scale, report=report)
    errors = dot_position_errors(dlfc, pts[keep])
    if len(errors):
        leverage = dot_shift_leverage(dlfc, pts[keep], cho_solve(factor, np.eye(len(gram))))
        errors = errors.merge(leverage, on=["x", "y", "z"], how="left")
        rms = np.sqrt(np.mean(errors[["dx", "dy", "dz"]].to_numpy() ** 2, axis=0))
        dot_groups = None
        if groups is not None:       # each dot's group: that of its points
            known, first = np.unique(pts[keep][:, :3], axis=0, return_index=True)
            label = pd.Series(np.asarray(groups)[keep][first],
                              index=pd.MultiIndex.from_arrays(known.T))
            dot_groups = label.reindex(pd.MultiIndex.from_frame(errors[["x", "y", "z"]])
                                       ).to_numpy()
        dlfc = dataclasses.replace(dlfc, report=dataclasses.replace(
            report, position_rms_mm=tuple(float(e) for e in rms),
            model_error_by_depth_mm=model_error_by_depth(
                errors, groups=dot_groups, leverage=errors[list(_LEVERAGE_COLUMNS)])))
    return dlfc


_MIN_DOTS_PER_DEPTH = 5


def model_error_by_depth(errors: pd.DataFrame, max_depths: int = 25, *,
                         groups=None, leverage=None) -> tuple:
    """The DLFC's model error per calibration depth: the error of the fitted mapping
    that the dots' own noise does not explain and that reaches a particle.

    Parameters
    ----------
    errors : DataFrame
        :func:`dot_position_errors`: known ``x, y, z``, errors ``dx, dy, dz`` and
        least-squares standard errors ``sigma_x, sigma_y, sigma_z`` of each dot, mm.
    max_depths : int
        Dots on at most this many distinct depths (or groups) are grouped by depth (one
        group per dot card); otherwise into ``max_depths // 2`` bins of equal dot count.
    groups : (n,) array-like, optional
        A group label per row of ``errors`` (its dot card): grouped by label instead of
        by distinct depth, each group at the mean depth of its dots (the dots of a card
        tilted on its mount lie at many depths). NaN labels are left out.
    leverage : (n, 3) array-like, optional
        Each dot's shift leverage in x, y, z (:func:`dot_shift_leverage`). With it, the
        dots' excess error is split (Notes) and their independent errors count only
        through the fit. None (or no ``x, y`` columns): the whole excess is counted.

    Returns
    -------
    tuple of (z, e_x, e_y, e_z)
        One row per group of at least 5 dots: ``z`` the group's mean depth and the
        model error ``e`` per axis, mm; sorted by ``z``. Empty when no group has 5 dots.

    Notes
    -----
    Per group and axis the excess is ``X^2 = max(0, mean(d^2) - mean(sigma^2))``, ``d``
    the solved-minus-known error and ``sigma`` the dot's own least-squares standard
    error. Part of it is shared by neighbouring dots: an error of the mapping that
    varies smoothly (a misplaced or tilted card, a lens error the polynomial cannot
    follow), which a particle between the dots has too. Its variance is the covariance
    of each dot's error with its nearest neighbour's on the same card,
    ``S^2 = min(X^2, max(0, mean(d_i d_nn(i)) - its standard error))``. The rest is each dot's own (a dot
    printed off its lattice point). It does not move a particle, except through the
    fitted coefficients: a dot whose shift leverage is ``h`` shows ``1 - h`` of its own
    error and passes ``h`` (as a variance) on to the mapping near it, so
    ``e^2 = S^2 + (X^2 - S^2) h / (1 - h)`` with ``h`` the group's mean leverage. On the
    realistic simulated ``small`` camera the dots' 5 um print error is almost all of the
    lateral excess (neighbour covariance below 0) and about 1.5 um of it reaches the
    particles; the cards' depth errors and tilts are shared by neighbours and kept whole.
    """
    z = errors["z"].to_numpy(float)
    labelled = np.ones(len(z), dtype=bool)
    if groups is None:
        depths, group = np.unique(z, return_inverse=True)
    else:
        label = pd.Series(np.asarray(groups)).reset_index(drop=True)
        labelled = label.notna().to_numpy()
        codes, depths = pd.factorize(label)
        group = np.asarray(codes)
    if len(depths) > max_depths:
        edges = np.quantile(z, np.linspace(0, 1, max_depths // 2 + 1)[1:-1])
        group = np.searchsorted(edges, z, side="right")
        labelled = np.ones(len(z), dtype=bool)
    err = errors[["dx", "dy", "dz"]].to_numpy(float)
    noise = errors[["sigma_x", "sigma_y", "sigma_z"]].to_numpy(float)
    split = leverage is not None and {"x", "y"} <= set(errors.columns)
    if split:
        xy = errors[["x", "y"]].to_numpy(float)
        lev = np.clip(np.asarray(leverage, dtype=float).reshape(len(errors), 3), 0.0, 0.9)
    rows = []
    for g in np.unique(group[labelled]):
        mine = np.flatnonzero((group == g) & labelled)
        if len(mine) < _MIN_DOTS_PER_DEPTH:
            continue
        excess = np.mean(err[mine] ** 2, axis=0) - np.nanmean(noise[mine] ** 2, axis=0)
        excess = np.maximum(np.nan_to_num(excess, nan=0.0), 0.0)
        e2 = excess
        if split:
            shared = np.clip(_neighbour_covariance(xy[mine], err[mine]), 0.0, excess)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)   # a group without leverage
                h = np.nanmean(lev[mine], axis=0)
            e2 = np.where(np.isfinite(h), shared + (excess - shared) * h / (1.0 - h), excess)
        e = np.sqrt(e2)
        rows.append((float(z[mine].mean()), *(float(v) for v in e)))
    return tuple(sorted(rows))


_LEVERAGE_COLUMNS = ("leverage_x", "leverage_y", "leverage_z")


def dot_shift_leverage(dlfc: DLFC, points, gram_inverse: np.ndarray) -> pd.DataFrame:
    """How much of a dot's own position error the fitted DLFC takes up, per axis.

    Move dot ``i`` by ``delta`` in object space (a dot printed off its lattice point):
    every one of its views' ``(s, t)`` moves by ``J_v delta``, and the least-squares fit
    follows a part of that, ``H_ii`` (the fit's hat matrix on the dot's rows). Solving
    the dot back through the fitted DLFC then gives ``L_i delta`` with
    ``L_i = (J^T J)^-1 J^T (I_2 x H_ii) J`` (``J`` the dot's ``(2V, 3)`` Jacobian). The
    diagonal of ``L_i`` is the dot's shift leverage: the share of an independent error
    (as a variance) that the mapping near the dot inherits, and the share the dot's own
    solved error does not show. Its mean over the dots is ``p_eff / n_dots``, the
    number of coefficients that position errors can move over the number of dots.

    Parameters
    ----------
    dlfc : DLFC
        The fitted calibration.
    points : (N, 7) float ndarray
        The points it was fitted to, columns ``x, y, z, u, v, s, t``.
    gram_inverse : (T, T) float ndarray
        ``(A^T A)^-1`` of the fit's design ``A`` on those points.

    Returns
    -------
    DataFrame
        One row per dot (distinct ``x, y, z``, mm): ``x, y, z, leverage_x, leverage_y,
        leverage_z`` (each from 0 to 1 for a well-posed fit; NaN for a dot whose
        Jacobian is singular).
    """
    pts = np.asarray(points, dtype=float)
    known, dot = np.unique(pts[:, :3], axis=0, return_inverse=True)
    order = np.argsort(dot.ravel(), kind="stable")
    pts = pts[order]
    # row ranges of the dots, and blocks of whole dots of about _FIT_CHUNK rows
    edges = np.r_[0, np.flatnonzero(np.diff(dot.ravel()[order])) + 1, len(pts)]
    blocks = np.unique(np.r_[np.searchsorted(edges, np.arange(0, len(pts), _FIT_CHUNK)),
                             len(edges) - 1])
    lev = np.full((len(known), 3), np.nan)
    for b0, b1 in zip(blocks[:-1], blocks[1:]):
        r0, r1 = edges[b0], edges[b1]
        q, _ = dlfc._normalised(*pts[r0:r1, :5].T)
        a = _design_kernel(q, dlfc._parent, dlfc._var)               # (rows, T)
        _, jac = dlfc.predict_with_jacobian(*pts[r0:r1, :5].T)       # (rows, 2, 3)
        # per dot: A^T J for s and t (T, 3); the part of its shift the fit takes up
        for k in range(b0, b1):
            rows = slice(edges[k] - r0, edges[k + 1] - r0)
            j = jac[rows]
            p_s, p_t = a[rows].T @ j[:, 0], a[rows].T @ j[:, 1]
            taken = p_s.T @ gram_inverse @ p_s + p_t.T @ gram_inverse @ p_t
            try:
                lev[k] = np.diag(np.linalg.solve(np.einsum("vij,vik->jk", j, j), taken))
            except np.linalg.LinAlgError:
                pass
    return pd.DataFrame({"x": known[:, 0], "y": known[:, 1], "z": known[:, 2],
                         **{c: lev[:, i] for i, c in enumerate(_LEVERAGE_COLUMNS)}})


def _neighbour_covariance(xy: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``mean(v_i * v_nn(i))`` per column of ``values`` (n, k), each point's value times
    that of its nearest other point in ``xy`` (n, 2), less one standard error of that
    mean: a covariance that its own sampling noise could give counts for nothing (a
    card of 40 dots with independent errors shows about +-0.15 of their variance)."""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(xy).query(xy, k=2)
    products = values * values[nearest[:, 1]]
    return products.mean(axis=0) - products.std(axis=0) / math.sqrt(len(products))


def dot_position_errors(dlfc: DLFC, points) -> pd.DataFrame:
    """Object-space error of each calibration dot solved through the DLFC.

    Every dot (one known ``(x, y, z)``) seen in at least 4 views is located from its
    views' ``(s, t)`` by the same least-squares solve that locates particles
    (:func:`~plenoptrack.locate.triangulate.triangulate_clusters`, no outlier rejection),
    starting at its known position.

    Parameters
    ----------
    dlfc : DLFC
    points : DataFrame or (N, 7) float ndarray
        Calibration points, columns ``x, y, z, u, v, s, t`` (as for :func:`fit_dlfc`).

    Returns
    -------
    DataFrame
        One row per dot: ``x, y, z`` (known, mm), ``dx, dy, dz`` (solved minus known,
        mm), ``sigma_x, sigma_y, sigma_z`` (least-squares standard errors of the solve,
        ``sqrt(s^2 diag (J^T J)^-1)`` from the scatter of the dot's views about the
        fit, mm; NaN when singular) and ``n_views``.

    Notes
    -----
    The dots are the points the DLFC was fitted to, so these errors are in-sample: they
    measure how well the polynomial represents the camera where it was calibrated, not
    its error between the cards.
    """
    from .triangulate import triangulate_clusters

    names = [*INPUT_VARIABLES, *OUTPUT_VARIABLES]
    table = (points if isinstance(points, pd.DataFrame)
             else pd.DataFrame(np.asarray(points, dtype=float), columns=names))
    cols = ["x", "y", "z", "dx", "dy", "dz", "sigma_x", "sigma_y", "sigma_z", "n_views"]
    if len(table) == 0:
        return pd.DataFrame(columns=cols)
    known, dot = np.unique(table[["x", "y", "z"]].to_numpy(float), axis=0, return_inverse=True)
    dot = dot.ravel()
    counts = np.bincount(dot, minlength=len(known))
    seen = counts[dot] >= 4
    if not seen.any():
        return pd.DataFrame(columns=cols)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tri = triangulate_clusters(dlfc, table[seen].assign(dot=dot[seen]),
                                   known[np.unique(dot[seen])], cluster_column="dot",
                                   reject_k=np.inf, min_views=4)
    known = known[tri.clusters]
    err = tri.positions - known
    ok = np.all(np.isfinite(err), axis=1)
    return pd.DataFrame({"x": known[ok, 0], "y": known[ok, 1], "z": known[ok, 2],
                         "dx": err[ok, 0], "dy": err[ok, 1], "dz": err[ok, 2],
                         "sigma_x": tri.sigma[ok, 0], "sigma_y": tri.sigma[ok, 1],
                         "sigma_z": tri.sigma[ok, 2], "n_views": tri.n_views[ok]})


def _robust_threshold(values: np.ndarray, k: float) -> float:
    """``median + k * 1.4826 * MAD`` of ``values``."""
    med = np.median(values)
    return float(med + k * 1.4826 * np.median(np.abs(values - med)))


def _fit_inputs(data, group_by) -> tuple[np.ndarray, np.ndarray | None, str | None]:
    """Stack the calibration columns into (N, 7) floats; resolve the grouping."""
    names = (*INPUT_VARIABLES, *OUTPUT_VARIABLES)
    if not isinstance(data, (pd.DataFrame, Mapping)):
        raise CalibrationError(f"DLFC fit data must be a DataFrame or a mapping with keys "
                               f"{list(names)}; got {type(data).__name__}")
    missing = [n for n in names if n not in data]
    if missing:
        raise CalibrationError(f"DLFC fit data lacks column(s) {missing}; need {list(names)}")
    try:
        cols = [np.asarray(data[n], dtype=float).ravel() for n in names]
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"DLFC fit data must be numeric ({exc})") from None
    lengths = {len(c) for c in cols}
    if len(lengths) != 1:
        raise CalibrationError(f"DLFC fit columns differ in length: "
                               f"{dict(zip(names, map(len, cols)))}")
    pts = np.column_stack(cols)
    bad = ~np.all(np.isfinite(pts), axis=1)
    if bad.any():
        raise CalibrationError(f"DLFC fit data has {int(bad.sum())} row(s) with NaN or infinite "
                               "values; drop undetected dots before fitting")
    if group_by is None:
        return pts, None, None
    if isinstance(group_by, str):
        if group_by not in data:
            raise CalibrationError(f"group_by column {group_by!r} is not in the fit data")
        groups, name = np.asarray(data[group_by]).ravel(), group_by
    else:
        groups, name = np.asarray(group_by).ravel(), "group"
    if len(groups) != len(pts):
        raise CalibrationError(f"group_by has {len(groups)} labels for {len(pts)} points")
    return pts, groups, name


def _normal_equations(q: np.ndarray, rhs: np.ndarray, parent, var, *,
                      with_gram: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
    """Gram matrix ``A^T A`` (T, T) and ``A^T rhs`` (T, 2), accumulated block by block.

    ``A`` is the design (N, T) of the normalised points ``q`` (5, N). The Gram matrix is
    accumulated with the symmetric rank-k update (BLAS ``syrk``, half the work of
    ``A.T @ A``); ``with_gram=False`` skips it and returns None in its place.
    """
    n_terms = parent.shape[0]
    gram = np.zeros((n_terms, n_terms)) if with_gram else None
    atb = np.zeros((n_terms, rhs.shape[1]))
    for start in range(0, q.shape[1], _FIT_CHUNK):
        a = _design_kernel(np.ascontiguousarray(q[:, start:start + _FIT_CHUNK]), parent, var)
        if with_gram:
            # a.T is Fortran-ordered (T, n): syrk(a.T) = a.T @ a, upper triangle
            gram = dsyrk(1.0, a.T, beta=1.0, c=gram, trans=0, lower=0, overwrite_c=1)
        atb += a.T @ rhs[start:start + _FIT_CHUNK]
    if with_gram:
        gram = np.triu(gram) + np.triu(gram, 1).T
    return gram, atb


def _factor_gram(gram: np.ndarray, order: int):
    """Cholesky factor of the Gram matrix, refusing a rank-deficient design.

    On ``[-1, 1]``-normalised calibration data the design matrix is well conditioned
    (condition number ~20, ~70 and ~200 for orders 3, 4 and 5 on dot-card grids), so
    solving the normal equations loses nothing measurable, and forming ``A^T A`` with
    matrix products is several times faster than a Householder QR of the design. One
    step of iterative refinement on the final fit (in :func:`fit_dlfc`) recovers the
    last digits.
    """
    eig = np.linalg.eigvalsh(gram)
    if eig[0] <= _RANK_TOL * eig[-1]:
        raise CalibrationError(f"the calibration points do not determine an order-{order} DLFC "
                               "(rank-deficient design); use more depths, dots or views, or a "
                               "lower order")
    return cho_factor(gram)


def _fit_report(resid: np.ndarray, keep: np.ndarray, groups, group_name) -> FitReport:
    kept = resid[keep]
    length2 = (kept ** 2).sum(axis=1)
    keys: tuple = ()
    rms_groups: tuple = ()
    counts: tuple = ()
    if groups is not None:
        g = groups[keep]
        uniq, inv = np.unique(g, return_inverse=True)
        n = np.bincount(inv, minlength=len(uniq))
        ss = np.bincount(inv, weights=length2, minlength=len(uniq))
        keys = tuple(_json_scalar(k) for k in uniq)
        rms_groups = tuple(float(v) for v in np.sqrt(ss / np.maximum(n, 1)))
        counts = tuple(int(c) for c in n)
    return FitReport(
        rms_s_px=float(np.sqrt(np.mean(kept[:, 0] ** 2))),
        rms_t_px=float(np.sqrt(np.mean(kept[:, 1] ** 2))),
        rms_px=float(np.sqrt(np.mean(length2))),
        max_px=float(np.sqrt(length2.max())),
        n_points=int(keep.sum()),
        n_rejected=int((~keep).sum()),
        group_by=group_name, group_keys=keys, group_rms_px=rms_groups, group_n_points=counts,
    )
