"""Numba ray-tracing kernels of the simulator (private).

Every kernel traces the same per-pixel function, :func:`_trace_pixel`, so an image
rendered pixel by pixel, lens by lens or over the whole sensor is bit-identical wherever
the same occluders are tested. Geometry and symbols as in :mod:`.optics`.

``par`` is a float64 vector holding the optics (indices below). ``samples`` is an
``(n, 4)`` float64 array: the sub-pixel offset (dX, dY) of the sensor point P and the
offset (dX, dY) of the microlens point Q from the lens centre, mm, camera frame.
``occluders`` is an ``(m, 4)`` float64 array of spheres (X, Y, Z, radius^2) in the
camera frame, mm.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

PP, ROWS, COLS, SCALE, F_ML, S_I, S_O, R_AP2, K1, K2, INV_RN2 = range(11)
E1X, E1Y, E2X, E2Y, OFFX, OFFY, SHIFT, PITCH, ROW_STEP, CELL_PX = range(11, 21)
N_PAR = 21


def pack_params(optics) -> np.ndarray:
    """Flatten a :class:`~.optics.SimOptics` into the ``par`` vector of the kernels."""
    rows, cols = optics.camera.sensor_shape_px
    e1, e2 = optics.lattice_vectors
    par = np.zeros(N_PAR)
    par[PP] = optics.pixel_pitch
    par[ROWS] = rows
    par[COLS] = cols
    par[SCALE] = optics.image_scale
    par[F_ML] = optics.f_ml
    par[S_I] = optics.s_i
    par[S_O] = optics.s_o
    par[R_AP2] = optics.aperture_radius ** 2
    par[K1] = optics.k1
    par[K2] = optics.k2
    par[INV_RN2] = 1.0 / optics.distortion_radius_mm ** 2
    par[E1X], par[E1Y] = e1
    par[E2X], par[E2Y] = e2
    par[OFFX], par[OFFY] = optics.offset_mm
    par[SHIFT] = optics.odd_row_shift
    par[PITCH] = optics.pitch
    par[ROW_STEP] = optics.row_step
    par[CELL_PX] = optics.cell_radius * optics.image_scale / optics.pixel_pitch
    return par


@njit(cache=True)
def _nearest_lens(x, y, par):
    """Lens (i, j) whose physical centre is nearest to MLA-plane point (x, y) mm."""
    px = x - par[OFFX]
    py = y - par[OFFY]
    a = (px * par[E1X] + py * par[E1Y]) / (par[PITCH] * par[PITCH])
    fi = (px * par[E2X] + py * par[E2Y]) / (par[ROW_STEP] * par[ROW_STEP])
    ic = int(math.floor(fi + 0.5))
    best_i = ic
    best_j = 0
    best_d = np.inf
    for i in range(ic - 1, ic + 2):
        sh = par[SHIFT] * (i & 1)
        j = int(math.floor(a - sh + 0.5))
        da = (a - j - sh) * par[PITCH]
        di = (fi - i) * par[ROW_STEP]
        d = da * da + di * di
        if d < best_d:
            best_d = d
            best_i = i
            best_j = j
    return best_i, best_j


@njit(cache=True)
def _lens_center(i, j, par):
    a = j + par[SHIFT] * (i & 1)
    return (a * par[E1X] + i * par[E2X] + par[OFFX],
            a * par[E1Y] + i * par[E2Y] + par[OFFY])


@njit(cache=True)
def _pixel_lens(row, col, par):
    """Lens owning sensor pixel (row, col): nearest microlens-image centre."""
    x0 = (col - (par[COLS] - 1.0) * 0.5) * par[PP]
    y0 = (row - (par[ROWS] - 1.0) * 0.5) * par[PP]
    return _nearest_lens(x0 / par[SCALE], y0 / par[SCALE], par)


@njit(cache=True)
def _trace_pixel(row, col, par, samples, occluders, idx, p0, p1, card):
    """Number of lit samples of pixel (row, col).

    Each sample point P uses the microlens whose image centre is nearest to P.
    Occluders tested are ``occluders[idx[p0:p1]]``. ``card`` is (Z, spacing, r^2) of a
    dot card (Z > 0) or Z <= 0 for none.
    """
    x0 = (col - (par[COLS] - 1.0) * 0.5) * par[PP]
    y0 = (row - (par[ROWS] - 1.0) * 0.5) * par[PP]
    tan_s = par[S_I] / par[F_ML]
    s_o = par[S_O]
    conj = -s_o / par[S_I]
    lit = 0
    for k in range(samples.shape[0]):
        px = x0 + samples[k, 0]
        py = y0 + samples[k, 1]
        i, j = _nearest_lens(px / par[SCALE], py / par[SCALE], par)
        cx, cy = _lens_center(i, j, par)
        qx = cx + samples[k, 2]
        qy = cy + samples[k, 3]
        # Main-lens plane: thin microlens, P in its focal plane.
        hx = qx + (cx - px) * tan_s
        hy = qy + (cy - py) * tan_s
        if hx * hx + hy * hy > par[R_AP2]:
            continue
        # Distorted conjugate of Q on the focal plane; ray H -> Q_obj, per unit Z.
        rho2 = (qx * qx + qy * qy) * par[INV_RN2]
        g = 1.0 + par[K1] * rho2 + par[K2] * rho2 * rho2
        dx = (qx * conj * g - hx) / s_o
        dy = (qy * conj * g - hy) / s_o
        dd = dx * dx + dy * dy + 1.0
        blocked = False
        for m in range(p0, p1):
            q = idx[m]
            wx = occluders[q, 0] - hx
            wy = occluders[q, 1] - hy
            wz = occluders[q, 2]
            wd = wx * dx + wy * dy + wz
            if wx * wx + wy * wy + wz * wz - wd * wd / dd < occluders[q, 3]:
                blocked = True
                break
        if blocked:
            continue
        if card[0] > 0.0:
            xw = -(hx + dx * card[0])
            yw = -(hy + dy * card[0])
            mx = xw - card[1] * math.floor(xw / card[1] + 0.5)
            my = yw - card[1] * math.floor(yw / card[1] + 0.5)
            if mx * mx + my * my < card[2]:
                continue
        lit += 1
    return lit


@njit(parallel=True, cache=True)
def render_all(par, samples, occluders, card, r0, r1, c0, c1):
    """Trace every pixel of the window rows [r0, r1), cols [c0, c1) against all occluders.

    Returns a ``(r1 - r0, c1 - c0)`` float32 irradiance image in [0, 1].
    """
    out = np.empty((r1 - r0, c1 - c0), dtype=np.float32)
    idx = np.arange(occluders.shape[0])
    inv_n = 1.0 / samples.shape[0]
    for r in prange(r0, r1):
        for c in range(c0, c1):
            lit = _trace_pixel(r, c, par, samples, occluders, idx, 0, idx.shape[0], card)
            out[r - r0, c - c0] = lit * inv_n
    return out


@njit(parallel=True, cache=True)
def render_lenses(out, lenses, ptr, idx, par, samples, occluders, card):
    """Re-trace, in place, every pixel of ``out`` owned by one of ``lenses``.

    A pixel is owned by the lens whose image centre is nearest to the pixel centre (its
    samples may still use a neighbouring lens). ``lenses`` is ``(L, 2)`` int64 (i, j);
    the pixels of lens ``k`` are tested against ``occluders[idx[ptr[k]:ptr[k + 1]]]``.
    """
    rows = out.shape[0]
    cols = out.shape[1]
    inv_n = 1.0 / samples.shape[0]
    half_r = (par[ROWS] - 1.0) * 0.5
    half_c = (par[COLS] - 1.0) * 0.5
    reach = par[CELL_PX] + 1.0
    for k in prange(lenses.shape[0]):
        i = lenses[k, 0]
        j = lenses[k, 1]
        cx, cy = _lens_center(i, j, par)
        crow = cy * par[SCALE] / par[PP] + half_r
        ccol = cx * par[SCALE] / par[PP] + half_c
        ra = max(0, int(math.floor(crow - reach)))
        rb = min(rows, int(math.ceil(crow + reach)) + 1)
        ca = max(0, int(math.floor(ccol - reach)))
        cb = min(cols, int(math.ceil(ccol + reach)) + 1)
        for r in range(ra, rb):
            for c in range(ca, cb):
                pi, pj = _pixel_lens(r, c, par)
                if pi != i or pj != j:
                    continue
                lit = _trace_pixel(r, c, par, samples, occluders, idx, ptr[k], ptr[k + 1], card)
                out[r, c] = lit * inv_n
