"""Numba ray-tracing kernels of the simulator (private).

Every kernel counts lit samples with the same per-sample loop, :func:`_sample_loop`;
the shortcuts of :func:`_trace_pixel` only skip work whose outcome is provably known,
so an image rendered lens by lens, over the whole sensor with shortcuts, or by brute
force is bit-identical. Geometry and symbols as in :mod:`.optics`.

``par`` is a float64 vector holding the optics (indices below). ``samples`` is an
``(n, 4)`` or ``(n, 5)`` float64 array: the sub-pixel offset (dX, dY) of the sensor point
P and the offset (dX, dY) of the microlens point Q from the lens centre, mm, camera frame;
the fifth column, the sample's time in the exposure, is read only with motion blur.
``occluders`` is an ``(m, 4)`` float64 array of spheres (X, Y, Z, radius^2) relative to
the optical axis (``X - a_x``, ``Y - a_y``, ``Z``), mm; for an ellipsoid the row holds its
centre and its *bounding* sphere (radius = long semi-axis ``a``), which every culling bound
uses. ``shapes`` is either a zero-row ``(0, 7)`` float64 array (all occluders are spheres)
or ``(m, 7)``, row ``q`` describing occluder ``q``: column 0 is 1.0 for an ellipsoid (0.0
for a sphere), columns 1..6 the scaled inverse-shape matrix ``M' = a^2 M`` (dimensionless,
symmetric; entries ``M'xx, M'yy, M'zz, M'xy, M'xz, M'yz``), with the ellipsoid the set
``(p - c)^T M (p - c) <= 1``. For a prolate spheroid of aspect ``k = a / b`` and unit long
axis ``v``: ``M' = k^2 I + (1 - k^2) v v^T``, exactly the identity when ``k = 1``.

Particle effects (:class:`~.realism.ParticleEffects`, fragments). When a frame has
fragments, translucent particles, specular highlights or motion blur, ``shapes`` has
``W >= 28`` columns (the *extended* rows; ``W = 7`` otherwise and the code above runs
unchanged, so such images keep their bytes): columns 0..6 as above with column 0 the
type (0 sphere, 1 ellipsoid, 2 fragment); 7 the squared radius of the body's own test
(sphere ``r^2``, ellipsoid ``a^2``, fragment bounding sphere); 8 the transmission
``tau``; 9..11 the displacement ``s`` over the whole exposure (camera frame, mm); 12
the number of convex pieces of a fragment and 13..15 their plane counts; 16..27 a sphere
enclosing each piece (centre relative to ``c`` and radius^2, 4 columns per piece); from
column 28 the planes, piece by piece, 4 columns each: unit outward normal
``(nx, ny, nz)`` and offset ``d`` (mm) of the half-space ``n . (p - c) <= d``, camera
frame. For a fragment ``c`` is the centre of a sphere enclosing it, not its centroid. ``occluders``
then holds the centre at mid-exposure and the squared radius of a sphere that bounds the
body over its whole path (bounding radius plus ``|s| / 2``), which every culling bound
uses. ``samples`` has a fifth column, the sample's time ``t`` in [-0.5, 0.5) within the
exposure: the body is tested at ``c + s t``. A sample's value is the product of ``tau``
over every body its ray meets, plus, with highlights on (``par[HL_ON]``), the
Blinn-Phong term ``S max(0, n . h)^E`` of the body met nearest the camera (``n`` the
outward normal at the entry point: the gradient ``M'(p - c)`` on a quadric, the entry
facet's normal on a fragment), clipped to 1 (the unoccluded value). Candidates are
tested in increasing occluder index (:func:`_sort_head`), so the product's rounding is
the same for the culled and the brute-force renderer. Fragment pieces are clipped by the
Cyrus-Beck slab test on the line (not the half-line) after bounding-sphere rejections
(the whole fragment's, then the piece's).

Ray-occluder test. A ray ``p(Z) = H + Z d`` with ``H = (hx, hy, 0)``, ``d = (dx, dy, 1)``
and ``w = c - H`` meets the ellipsoid iff the quadratic
``Z^2 (d.M'd) - 2 Z (d.M'w) + (w.M'w - a^2) < 0`` has real roots, i.e.
``(w.M'w - a^2)(d.M'd) < (d.M'w)^2``. For a sphere (``M' = I``, ``a^2 = r^2``) this is the
sphere test of :func:`_sample_loop`, which spheres keep verbatim; an ellipsoid row with
``M' = I`` evaluates the same products and sums in the same order, so an aspect-1
ellipsoid is bit-identical to the sphere.

Culling balls. Every bound that decides which occluders a pixel or a sample ray may meet
tests spheres: ``balls`` is a ``(B, 5)`` float64 array of rows (X, Y, Z, r^2, q), a sphere
in the frame of ``occluders`` and the index ``q`` of the occluder it helps to bound; the
balls of an occluder together contain it (over the whole exposure). A sphere, a fragment
or a mildly elongated ellipsoid has one ball, its ``occluders`` row; a long thin spheroid
(a pin's stem) has a chain of small balls along its axis (:func:`~.render._culling_balls`),
which is far tighter than its bounding sphere of radius ``a``. Lens lists (``idx``) index
balls; candidate lists (``cand``) hold occluders, each once.

Lens effects (:class:`~.realism.LensEffects`, see :mod:`.optics`). With any of axis offset,
MLA tilt, Seidel terms or front stop on (``par[LENS_ON]``), every kernel takes a second
code path, :func:`_lens_ray_at` for the rays and the general branch of :func:`_bundle` for
the bounds; with all of them off the original expressions run unchanged, so ideal images
keep their bytes. The bounds of the general branch: a ray leaving lens ``C`` crosses the
main-lens plane within ``r_h`` of ``h0`` (thin tilted-microlens model), its point on the
nominal MLA plane lies within ``r'`` of ``c'``, its distorted conjugate within
``r' conj lip`` of ``qo0`` (``lip`` bounds the derivative of ``Q g(|Q|)`` over the disc)
and the Seidel errors add at most ``(F + 1.5 A) rho_m^2 D/2 / s_o + coma rho_m``
(``|p| <= 1`` for every ray that passes the aperture, ``rho_m`` bounding ``|rho|``).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

PP, ROWS, COLS, SCALE, F_ML, S_I, S_O, R_AP2, K1, K2, INV_RN2 = range(11)
E1X, E1Y, E2X, E2Y, OFFX, OFFY, SHIFT, PITCH, ROW_STEP, CELL_PX = range(11, 21)
CELL_R, HALF_DIAG, INRADIUS_IMG, INV_SCALE, INV_P2, INV_RS2, R_AP = range(21, 28)
LENS_ON, AXX, AXY, TX, TY, SEID_A, SEID_B, COMA_K, E_DEF, E_COMA = range(28, 38)
VIG_ON, VIG_L, VIG_R2, VIG_R = range(38, 42)
HL_ON, HL_S, HL_EXP, HL_LX, HL_LY, HL_LZ = range(42, 48)
INV_F_ML, INV_S_O, CONJ = range(48, 51)
N_PAR = 51

N_SHAPE_BASE = 7
"""Columns of the ``shapes`` rows of spheres and ellipsoids without particle effects."""
S_R2, S_TAU, S_VX, S_VY, S_VZ, S_NPIECE, S_PIECES, S_BALLS = 7, 8, 9, 10, 11, 12, 13, 16
S_PLANES = 28
"""First plane column of the extended ``shapes`` rows (module notes)."""
MAX_PIECES = 3
SPHERE_T, ELLIPSOID_T, FRAGMENT_T = 0.0, 1.0, 2.0


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
    par[INV_F_ML] = 1.0 / optics.f_ml
    par[S_I] = optics.s_i
    par[S_O] = optics.s_o
    par[INV_S_O] = 1.0 / optics.s_o
    par[CONJ] = -optics.s_o / optics.s_i
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
    par[CELL_R] = optics.cell_radius
    par[HALF_DIAG] = optics.pixel_pitch * math.sqrt(0.5)
    par[INRADIUS_IMG] = 0.5 * optics.pitch * optics.image_scale
    par[INV_SCALE] = 1.0 / optics.image_scale
    par[INV_P2] = 1.0 / optics.pitch ** 2
    par[INV_RS2] = 1.0 / optics.row_step ** 2
    par[R_AP] = optics.aperture_radius
    lens = optics.realism.lens
    stop = optics.front_stop
    seidel = (lens.field_curvature_mm, lens.astigmatism_mm, lens.coma_mm)
    if (optics.axis_offset_mm != (0.0, 0.0) or optics.mla_tilt != (0.0, 0.0)
            or any(v != 0 for v in seidel) or stop is not None):
        fc, ast, coma = seidel
        par[LENS_ON] = 1.0
        par[AXX], par[AXY] = optics.axis_offset_mm
        par[TX], par[TY] = optics.mla_tilt
        par[SEID_A] = (-fc + 0.5 * ast) / optics.s_o
        par[SEID_B] = -ast / optics.s_o
        par[COMA_K] = coma / 3.0 / (optics.distortion_radius_mm * optics.aperture_radius ** 2)
        par[E_DEF] = (fc + 1.5 * ast) * optics.aperture_radius / optics.s_o
        par[E_COMA] = coma
        if stop is not None:
            par[VIG_ON] = 1.0
            par[VIG_L] = stop[0]
            par[VIG_R2] = stop[1] ** 2
            par[VIG_R] = stop[1]
    eff = optics.realism.particles
    if eff.highlight_strength > 0:
        lx, ly, lz = eff.light_direction                     # world frame
        par[HL_ON] = 1.0
        par[HL_S] = eff.highlight_strength
        par[HL_EXP] = eff.highlight_exponent
        par[HL_LX], par[HL_LY], par[HL_LZ] = -lx, -ly, lz    # camera frame
    return par


@njit(cache=True)
def _nearest_lens(x, y, par):
    """Lens (i, j) whose physical centre is nearest to MLA-plane point (x, y) mm."""
    px = x - par[OFFX]
    py = y - par[OFFY]
    a = (px * par[E1X] + py * par[E1Y]) * par[INV_P2]
    fi = (px * par[E2X] + py * par[E2Y]) * par[INV_RS2]
    ic = int(math.floor(fi + 0.5))
    best_i = ic
    best_j = 0
    best_d = 1e300
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
def _nearest_lens_rows(x, y, par, row_lo, row_hi):
    """:func:`_nearest_lens` searching only lens rows ``row_lo..row_hi``.

    The rows are scanned in increasing order with the arithmetic of
    :func:`_nearest_lens`, so when they hold the nearest lens (and every lens as near)
    the answer is the same lens, ties included; rows further than 1.5 row steps from
    the point never win there, so a range wider than its three rows changes nothing.
    """
    px = x - par[OFFX]
    py = y - par[OFFY]
    a = (px * par[E1X] + py * par[E1Y]) * par[INV_P2]
    fi = (px * par[E2X] + py * par[E2Y]) * par[INV_RS2]
    best_i = row_lo
    best_j = 0
    best_d = 1e300
    for i in range(row_lo, row_hi + 1):
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
    return _nearest_lens(x0 * par[INV_SCALE], y0 * par[INV_SCALE], par)


@njit(cache=True)
def _lens_geom(cx, cy, par):
    """Tilted-MLA geometry of lens C (camera frame, mm): (delta, d, s_l).

    ``d = f_ml + delta`` is its distance to the sensor, ``s_l = s_i - delta`` to the main
    lens, ``delta = t . C``.
    """
    delta = par[TX] * cx + par[TY] * cy
    return delta, par[F_ML] + delta, par[S_I] - delta


@njit(cache=True)
def _lens_consts(cx, cy, par):
    """``(1 / d, s_l, delta / s_l)`` of lens C (:func:`_lens_geom`)."""
    delta, d, s_l = _lens_geom(cx, cy, par)
    return 1.0 / d, s_l, delta / s_l


@njit(cache=True)
def _aperture_point(px, py, qx, qy, cx, cy, par, inv_d, s_l):
    """Where the ray of sensor point P through point Q of lens C meets the aperture plane,
    relative to the optical axis (lens effects on; ``inv_d, s_l`` from :func:`_lens_consts`)."""
    # Thin microlens at distance d from the sensor: slope out = (Q - P) / d - (Q - C) / f.
    sx = (qx - px) * inv_d - (qx - cx) * par[INV_F_ML]
    sy = (qy - py) * inv_d - (qy - cy) * par[INV_F_ML]
    return qx + sx * s_l - par[AXX], qy + sy * s_l - par[AXY]


@njit(cache=True)
def _lens_ray_at(px, py, qx, qy, cx, cy, par, inv_d, s_l, w):
    """Object-side ray of sensor point P through point Q of lens C with the lens effects.

    ``inv_d, s_l, w`` are lens C's :func:`_lens_consts`, computed once per lens by the
    sample loops (multiplications by reciprocals instead of per-sample divisions).
    Returns (ok, hx, hy, dx, dy): ``ok`` False when the ray is stopped by the aperture or
    the front stop; otherwise the ray ``H + Z (d, 1)`` relative to the optical axis.
    """
    hx, hy = _aperture_point(px, py, qx, qy, cx, cy, par, inv_d, s_l)
    h2 = hx * hx + hy * hy
    if h2 > par[R_AP2]:
        return False, hx, hy, 0.0, 0.0
    # Point of the nominal MLA plane (Z = -s_i) on the ray, relative to the axis.
    ux = qx - par[AXX]
    uy = qy - par[AXY]
    ux += (ux - hx) * w
    uy += (uy - hy) * w
    rho2 = (ux * ux + uy * uy) * par[INV_RN2]
    g = 1.0 + par[K1] * rho2 + par[K2] * rho2 * rho2
    conj = par[CONJ]
    hu = hx * ux + hy * uy
    # Seidel transverse errors on the focal plane (module notes of .optics).
    ex = par[SEID_A] * rho2 * hx + par[SEID_B] * hu * ux * par[INV_RN2]
    ey = par[SEID_A] * rho2 * hy + par[SEID_B] * hu * uy * par[INV_RN2]
    ex += par[COMA_K] * (h2 * ux + 2.0 * hu * hx)
    ey += par[COMA_K] * (h2 * uy + 2.0 * hu * hy)
    inv_so = par[INV_S_O]
    dx = (ux * conj * g + ex - hx) * inv_so
    dy = (uy * conj * g + ey - hy) * inv_so
    if par[VIG_ON] != 0.0:
        vx = hx + par[VIG_L] * dx
        vy = hy + par[VIG_L] * dy
        if vx * vx + vy * vy > par[VIG_R2]:
            return False, hx, hy, dx, dy
    return True, hx, hy, dx, dy


@njit(cache=True)
def _ellipsoid_hit(q, hx, hy, dx, dy, occluders, shapes):
    """True if the line ``H + Z (d, 1)`` meets ellipsoid ``q`` (module notes)."""
    wx = occluders[q, 0] - hx
    wy = occluders[q, 1] - hy
    wz = occluders[q, 2]
    mxx = shapes[q, 1]
    myy = shapes[q, 2]
    mzz = shapes[q, 3]
    mxy = shapes[q, 4]
    mxz = shapes[q, 5]
    myz = shapes[q, 6]
    # M' w and M' d, row by row (for M' = I these are w and d exactly).
    mwx = mxx * wx + mxy * wy + mxz * wz
    mwy = mxy * wx + myy * wy + myz * wz
    mwz = mxz * wx + myz * wy + mzz * wz
    mdx = mxx * dx + mxy * dy + mxz
    mdy = mxy * dx + myy * dy + myz
    mdz = mxz * dx + myz * dy + mzz
    dmd = dx * mdx + dy * mdy + mdz
    wmw = wx * mwx + wy * mwy + wz * mwz
    dmw = dx * mwx + dy * mwy + mwz
    return (wmw - occluders[q, 3]) * dmd < dmw * dmw


@njit(cache=True)
def _no_table():
    """The ``tab`` argument of :func:`_sample_loop` when no clear table applies."""
    return np.empty((0, 4))


@njit(cache=True)
def _clear_table(cx, cy, par, balls, idx, p0, p1, cand, nc):
    """Bounds that prove a sample ray through lens C clear (:func:`_surely_clear`).

    Every ray through C of a sensor point within the lens's cell crosses the focal plane
    within ``r_q`` of ``qo0`` (:func:`_bundle_h` over the cell) with ``sec`` bounding
    1 / cos of its angle, so a ray leaving the main lens at H lies, at depth ``t s_o``,
    within ``r_q t`` of ``H (1 - t) + qo0 t``. Row 0 holds ``(qo0x, qo0y, t_stop,
    limit^2)`` of the front stop (``limit`` = stop radius less ``r_q t_stop``, 0 when
    it cannot be proved), then one row ``(t, X, Y, reach^2)`` per culling ball
    ``balls[idx[p0:p1]]`` of an occluder in ``cand[:nc]`` (as in :func:`_bundle_cands`).
    The balls of a candidate that are not in ``idx[p0:p1]`` cannot meet the rays of the
    pixels those lists serve (:func:`~.render.particle_lenses`), so they need no row.
    """
    _, _, qo0x, qo0y, _, r_q, sec = _bundle_h(cx * par[SCALE], cy * par[SCALE], cx, cy, par,
                                              par[CELL_R] * par[SCALE] * (1.0 + 1e-6))
    rows = 0
    for m in range(p0, p1):
        if _in_head(cand, nc, int(balls[idx[m], 4])):
            rows += 1
    tab = np.empty((rows + 1, 4))
    tab[0, 0] = qo0x
    tab[0, 1] = qo0y
    tab[0, 2] = par[VIG_L] / par[S_O]
    lim = par[VIG_R] * (1.0 - 1e-9) - r_q * tab[0, 2] * (1.0 + 1e-7) - 1e-12
    tab[0, 3] = lim * lim if lim > 0.0 else 0.0
    n = 0
    for m in range(p0, p1):
        b = idx[m]
        if not _in_head(cand, nc, int(balls[b, 4])):
            continue
        n += 1
        t = balls[b, 2] / par[S_O]
        reach = (r_q * t + math.sqrt(balls[b, 3]) * sec) * (1.0 + 1e-7) + 1e-9
        tab[n, 0] = t
        tab[n, 1] = balls[b, 0]
        tab[n, 2] = balls[b, 1]
        tab[n, 3] = reach * reach
    return tab


@njit(cache=True)
def _in_head(cand, nc, q):
    """True if ``q`` is one of ``cand[:nc]``."""
    for k in range(nc):
        if cand[k] == q:
            return True
    return False


@njit(cache=True)
def _surely_clear(hx, hy, tab, vig_on):
    """True if the ray through the lens of :func:`_clear_table` that leaves the main
    lens at (hx, hy) (relative to the axis) provably passes the front stop and meets no
    occluder of the table: its sample is fully lit, value 1."""
    qo0x = tab[0, 0]
    qo0y = tab[0, 1]
    if vig_on:
        t = tab[0, 2]
        vx = hx + (qo0x - hx) * t
        vy = hy + (qo0y - hy) * t
        if not vx * vx + vy * vy < tab[0, 3]:
            return False
    for m in range(1, tab.shape[0]):
        t = tab[m, 0]
        bx = hx + (qo0x - hx) * t - tab[m, 1]
        by = hy + (qo0y - hy) * t - tab[m, 2]
        if bx * bx + by * by <= tab[m, 3]:
            return False
    return True


@njit(cache=True)
def _sample_loop(x0, y0, par, samples, occluders, shapes, cand, nc, card, use_card, lens_i,
                 lens_j, row_lo, row_hi, own_i, own_j, tab):
    """Lit samples of the pixel centred at sensor point (x0, y0) mm.

    ``lens_i`` < -2**40 means "find the lens of every sample" (:func:`_nearest_lens`, or
    :func:`_nearest_lens_rows` over rows ``row_lo..row_hi`` when ``row_lo <= row_hi``:
    the caller guarantees that they hold every sample's lens; a sample within the
    inradius of the cell of lens (own_i, own_j) takes that lens without a search);
    otherwise every sample uses lens (lens_i, lens_j). Occluders tested: ``occluders[cand[:nc]]`` (ellipsoids
    where ``shapes`` flags them, module notes); the dot card ``card`` only if ``use_card``.
    Extended ``shapes`` rows (particle effects, module notes) go to :func:`_sample_loop_ext`,
    which returns the summed sample values instead of a count. With nothing to test
    (``nc == 0``, no card) a sample that passes the aperture (and the front stop) is lit
    without computing the rest of its ray; so is one whose ray provably passes and meets
    nothing when ``tab`` (lens effects on, no card) has rows: :func:`_clear_table` of
    lens (lens_i, lens_j), or with a lens per sample of lens (own_i, own_j), which then
    applies to the samples that use that lens; :func:`_no_table` otherwise.

    Every caller passes every argument with the same non-literal types (``np.int64``,
    ``np.bool_`` around constants), so that numba compiles this loop, and everything it
    calls, once instead of once per combination of literal arguments.
    """
    if shapes.shape[1] > N_SHAPE_BASE:
        return _sample_loop_ext(x0, y0, par, samples, occluders, shapes, cand, nc, card,
                                use_card, lens_i, lens_j, row_lo, row_hi, own_i, own_j, tab)
    has_shapes = shapes.shape[0] > 0
    bare = nc == 0 and not use_card
    rows = row_lo <= row_hi
    cur_i, cur_j = -(1 << 62), 0
    tan_s = par[S_I] / par[F_ML]
    s_o = par[S_O]
    inv_so = 1.0 / s_o
    conj = -s_o / par[S_I]
    per_sample = lens_i < -(1 << 40)
    # A point within the inradius of lens (own_i, own_j)'s cell is nearest to that lens.
    own_x, own_y = _lens_center(own_i, own_j, par)
    inr2 = (0.5 * min(par[PITCH], par[ROW_STEP]) * (1.0 - 1e-7)) ** 2
    cx, cy = 0.0, 0.0
    lens_on = par[LENS_ON] != 0.0
    inv_d, s_l, w = 0.0, 0.0, 0.0
    if not per_sample:
        cx, cy = _lens_center(lens_i, lens_j, par)
        if lens_on:
            inv_d, s_l, w = _lens_consts(cx, cy, par)
    vig_on = par[VIG_ON] != 0.0
    has_tab = tab.shape[0] > 0
    lit = 0
    for k in range(samples.shape[0]):
        px = x0 + samples[k, 0]
        py = y0 + samples[k, 1]
        if per_sample:
            if rows:
                mx = px * par[INV_SCALE] - own_x
                my = py * par[INV_SCALE] - own_y
                if mx * mx + my * my < inr2:
                    i, j = own_i, own_j
                else:
                    i, j = _nearest_lens_rows(px * par[INV_SCALE], py * par[INV_SCALE], par,
                                              row_lo, row_hi)
            else:
                i, j = _nearest_lens(px * par[INV_SCALE], py * par[INV_SCALE], par)
            if i != cur_i or j != cur_j:
                cur_i, cur_j = i, j
                cx, cy = _lens_center(i, j, par)
                if lens_on:
                    inv_d, s_l, w = _lens_consts(cx, cy, par)
        qx = cx + samples[k, 2]
        qy = cy + samples[k, 3]
        if has_tab and (not per_sample or (cur_i == own_i and cur_j == own_j)):
            # The aperture test of _lens_ray_at.
            hx, hy = _aperture_point(px, py, qx, qy, cx, cy, par, inv_d, s_l)
            if hx * hx + hy * hy > par[R_AP2]:
                continue
            if _surely_clear(hx, hy, tab, vig_on):
                lit += 1
                continue
        if lens_on:
            ok, hx, hy, dx, dy = _lens_ray_at(px, py, qx, qy, cx, cy, par, inv_d, s_l, w)
            if not ok:
                continue
            if bare:
                lit += 1
                continue
            if _ray_blocked(hx, hy, dx, dy, occluders, cand, nc, shapes, has_shapes):
                continue
            if use_card and _on_dot(hx, hy, dx, dy, card):
                continue
            lit += 1
            continue
        # Main-lens plane: thin microlens, P in its focal plane.
        hx = qx + (cx - px) * tan_s
        hy = qy + (cy - py) * tan_s
        if hx * hx + hy * hy > par[R_AP2]:
            continue
        if bare:
            lit += 1
            continue
        # Distorted conjugate of Q on the focal plane; ray H -> Q_obj, per unit Z.
        rho2 = (qx * qx + qy * qy) * par[INV_RN2]
        g = 1.0 + par[K1] * rho2 + par[K2] * rho2 * rho2
        dx = (qx * conj * g - hx) * inv_so
        dy = (qy * conj * g - hy) * inv_so
        if _ray_blocked(hx, hy, dx, dy, occluders, cand, nc, shapes, has_shapes):
            continue
        if use_card and _on_dot(hx, hy, dx, dy, card):
            continue
        lit += 1
    return lit


@njit(cache=True)
def _sort_head(cand, nc):
    """Sort ``cand[:nc]`` in place (insertion sort; writes nothing when already sorted)."""
    for a in range(1, nc):
        v = cand[a]
        b = a - 1
        if cand[b] <= v:
            continue
        while b >= 0 and cand[b] > v:
            cand[b + 1] = cand[b]
            b -= 1
        cand[b + 1] = v


@njit(cache=True)
def _sample_loop_ext(x0, y0, par, samples, occluders, shapes, cand, nc, card, use_card,
                     lens_i, lens_j, row_lo, row_hi, own_i, own_j, tab):
    """:func:`_sample_loop` with the particle effects: the sum of the sample values."""
    _sort_head(cand, nc)
    rows = row_lo <= row_hi
    cur_i, cur_j = -(1 << 62), 0
    tan_s = par[S_I] / par[F_ML]
    s_o = par[S_O]
    inv_so = 1.0 / s_o
    conj = -s_o / par[S_I]
    per_sample = lens_i < -(1 << 40)
    # A point within the inradius of lens (own_i, own_j)'s cell is nearest to that lens.
    own_x, own_y = _lens_center(own_i, own_j, par)
    inr2 = (0.5 * min(par[PITCH], par[ROW_STEP]) * (1.0 - 1e-7)) ** 2
    has_t = samples.shape[1] > 4
    cx, cy = 0.0, 0.0
    lens_on = par[LENS_ON] != 0.0
    inv_d, s_l, w = 0.0, 0.0, 0.0
    if not per_sample:
        cx, cy = _lens_center(lens_i, lens_j, par)
        if lens_on:
            inv_d, s_l, w = _lens_consts(cx, cy, par)
    vig_on = par[VIG_ON] != 0.0
    has_tab = tab.shape[0] > 0
    total = 0.0
    for k in range(samples.shape[0]):
        px = x0 + samples[k, 0]
        py = y0 + samples[k, 1]
        if per_sample:
            if rows:
                mx = px * par[INV_SCALE] - own_x
                my = py * par[INV_SCALE] - own_y
                if mx * mx + my * my < inr2:
                    i, j = own_i, own_j
                else:
                    i, j = _nearest_lens_rows(px * par[INV_SCALE], py * par[INV_SCALE], par,
                                              row_lo, row_hi)
            else:
                i, j = _nearest_lens(px * par[INV_SCALE], py * par[INV_SCALE], par)
            if i != cur_i or j != cur_j:
                cur_i, cur_j = i, j
                cx, cy = _lens_center(i, j, par)
                if lens_on:
                    inv_d, s_l, w = _lens_consts(cx, cy, par)
        qx = cx + samples[k, 2]
        qy = cy + samples[k, 3]
        if has_tab and (not per_sample or (cur_i == own_i and cur_j == own_j)):
            # The aperture test of _lens_ray_at.
            hx, hy = _aperture_point(px, py, qx, qy, cx, cy, par, inv_d, s_l)
            if hx * hx + hy * hy > par[R_AP2]:
                continue
            if _surely_clear(hx, hy, tab, vig_on):
                total += 1.0
                continue
        if lens_on:
            ok, hx, hy, dx, dy = _lens_ray_at(px, py, qx, qy, cx, cy, par, inv_d, s_l, w)
            if not ok:
                continue
        else:
            hx = qx + (cx - px) * tan_s
            hy = qy + (cy - py) * tan_s
            if hx * hx + hy * hy > par[R_AP2]:
                continue
            rho2 = (qx * qx + qy * qy) * par[INV_RN2]
            g = 1.0 + par[K1] * rho2 + par[K2] * rho2 * rho2
            dx = (qx * conj * g - hx) * inv_so
            dy = (qy * conj * g - hy) * inv_so
        t = samples[k, 4] if has_t else 0.0
        value = _ray_value(hx, hy, dx, dy, t, occluders, cand, nc, shapes, par)
        if value == 0.0:
            continue
        if use_card and _on_dot(hx, hy, dx, dy, card):
            continue
        total += value
    return total


@njit(cache=True)
def _quadric_entry(q, wx, wy, wz, dx, dy, shapes, entry):
    """Ray test of sphere or ellipsoid ``q`` with centre offset ``w = c - H`` (module
    notes). Returns (hit, Z, nx, ny, nz): with ``entry``, the ray parameter of the entry
    point and the (unnormalised) outward normal there."""
    if shapes[q, 0] == SPHERE_T:
        dmd = dx * dx + dy * dy + 1.0
        dmw = wx * dx + wy * dy + wz
        c0 = wx * wx + wy * wy + wz * wz - shapes[q, S_R2]
        if not c0 * dmd < dmw * dmw:
            return False, 0.0, 0.0, 0.0, 0.0
        if not entry:
            return True, 0.0, 0.0, 0.0, 0.0
        z = (dmw - math.sqrt(dmw * dmw - c0 * dmd)) / dmd
        return True, z, z * dx - wx, z * dy - wy, z - wz
    mxx = shapes[q, 1]
    myy = shapes[q, 2]
    mzz = shapes[q, 3]
    mxy = shapes[q, 4]
    mxz = shapes[q, 5]
    myz = shapes[q, 6]
    mwx = mxx * wx + mxy * wy + mxz * wz
    mwy = mxy * wx + myy * wy + myz * wz
    mwz = mxz * wx + myz * wy + mzz * wz
    mdx = mxx * dx + mxy * dy + mxz
    mdy = mxy * dx + myy * dy + myz
    mdz = mxz * dx + myz * dy + mzz
    dmd = dx * mdx + dy * mdy + mdz
    c0 = wx * mwx + wy * mwy + wz * mwz - shapes[q, S_R2]
    dmw = dx * mwx + dy * mwy + mwz
    if not c0 * dmd < dmw * dmw:
        return False, 0.0, 0.0, 0.0, 0.0
    if not entry:
        return True, 0.0, 0.0, 0.0, 0.0
    z = (dmw - math.sqrt(dmw * dmw - c0 * dmd)) / dmd
    return True, z, z * mdx - mwx, z * mdy - mwy, z * mdz - mwz


@njit(cache=True)
def _fragment_entry(q, wx, wy, wz, dx, dy, shapes, entry):
    """Ray test of fragment ``q`` (module notes): bounding sphere, then Cyrus-Beck per
    piece. Returns (hit, Z, nx, ny, nz): with ``entry``, the smallest entry parameter over
    the pieces met and the normal of its entry facet."""
    dd = dx * dx + dy * dy + 1.0
    wd = wx * dx + wy * dy + wz
    if not (wx * wx + wy * wy + wz * wz - shapes[q, S_R2]) * dd < wd * wd:
        return False, 0.0, 0.0, 0.0, 0.0
    hit = False
    best = math.inf
    bx, by, bz = 0.0, 0.0, 0.0
    col = S_PLANES
    for piece in range(int(shapes[q, S_NPIECE])):
        k = int(shapes[q, S_PIECES + piece])
        b0 = S_BALLS + 4 * piece
        px = wx + shapes[q, b0]
        py = wy + shapes[q, b0 + 1]
        pz = wz + shapes[q, b0 + 2]
        pd = px * dx + py * dy + pz
        if not (px * px + py * py + pz * pz - shapes[q, b0 + 3]) * dd < pd * pd:
            col += 4 * k
            continue
        lo = -math.inf
        hi = math.inf
        lx, ly, lz = 0.0, 0.0, 0.0
        inside = True
        for c in range(col, col + 4 * k, 4):
            nx = shapes[q, c]
            ny = shapes[q, c + 1]
            nz = shapes[q, c + 2]
            # n . (Z d - w) <= offset  <=>  Z (n . d) <= offset + n . w
            a = nx * dx + ny * dy + nz
            b = shapes[q, c + 3] + nx * wx + ny * wy + nz * wz
            if a > 0.0:
                hi = min(hi, b / a)
            elif a < 0.0:
                z = b / a
                if z > lo:
                    lo = z
                    lx, ly, lz = nx, ny, nz
            elif b < 0.0:
                inside = False
            if not inside or lo >= hi:
                inside = False
                break
        col += 4 * k
        if inside:
            hit = True
            if not entry:
                return True, 0.0, 0.0, 0.0, 0.0
            if lo < best:
                best = lo
                bx, by, bz = lx, ly, lz
    return hit, best, bx, by, bz


@njit(cache=True)
def _ray_value(hx, hy, dx, dy, t, occluders, cand, nc, shapes, par):
    """Value of the ray ``H + Z (d, 1)`` at exposure time ``t`` against the extended
    occluders ``cand[:nc]`` (module notes): transmission product plus highlight, <= 1."""
    hl_on = par[HL_ON] != 0.0
    trans = 1.0
    best = math.inf
    bx, by, bz = 0.0, 0.0, 0.0
    for m in range(nc):
        q = cand[m]
        wx = occluders[q, 0] + shapes[q, S_VX] * t - hx
        wy = occluders[q, 1] + shapes[q, S_VY] * t - hy
        wz = occluders[q, 2] + shapes[q, S_VZ] * t
        if shapes[q, 0] == FRAGMENT_T:
            hit, z, nx, ny, nz = _fragment_entry(q, wx, wy, wz, dx, dy, shapes, hl_on)
        else:
            hit, z, nx, ny, nz = _quadric_entry(q, wx, wy, wz, dx, dy, shapes, hl_on)
        if not hit:
            continue
        trans *= shapes[q, S_TAU]
        if hl_on:
            if z < best:
                best = z
                bx, by, bz = nx, ny, nz
        elif trans == 0.0:
            return 0.0
    if not hl_on or best == math.inf:
        return trans
    # Half vector of the light and the direction back to the camera, -(d, 1) / |(d, 1)|.
    inv_d = 1.0 / math.sqrt(dx * dx + dy * dy + 1.0)
    h_x = par[HL_LX] - dx * inv_d
    h_y = par[HL_LY] - dy * inv_d
    h_z = par[HL_LZ] - inv_d
    nh = bx * h_x + by * h_y + bz * h_z
    if nh <= 0.0:
        return trans
    nh /= math.sqrt((bx * bx + by * by + bz * bz) * (h_x * h_x + h_y * h_y + h_z * h_z))
    value = trans + par[HL_S] * nh ** par[HL_EXP]
    return min(value, 1.0)


@njit(cache=True)
def _ray_blocked(hx, hy, dx, dy, occluders, cand, nc, shapes, has_shapes):
    """True if the ray H + Z (d, 1) meets one of ``occluders[cand[:nc]]``.

    Spheres are tested exactly: the squared distance of the centre from the ray, times
    ``|(d, 1)|^2``, against the squared radius; rows ``shapes[q, 0] != 0`` are
    ellipsoids (:func:`_ellipsoid_hit`).
    """
    dd = dx * dx + dy * dy + 1.0
    for m in range(nc):
        q = cand[m]
        if has_shapes and shapes[q, 0] != 0.0:
            if _ellipsoid_hit(q, hx, hy, dx, dy, occluders, shapes):
                return True
            continue
        wx = occluders[q, 0] - hx
        wy = occluders[q, 1] - hy
        wz = occluders[q, 2]
        wd = wx * dx + wy * dy + wz
        if (wx * wx + wy * wy + wz * wz - occluders[q, 3]) * dd < wd * wd:
            return True
    return False


@njit(cache=True)
def _hash_normal(m, n, seed):
    """Two deterministic standard-normal numbers for dot (m, n) of a card seed."""
    h = (int(m) * 73856093) ^ (int(n) * 19349663) ^ (int(seed) * 83492791)
    h = (h * 6364136223846793005 + 1442695040888963407) & 0xFFFFFFFFFFFF
    u1 = (h & 0xFFFFFF) / 16777216.0 + 0.5 / 16777216.0
    u2 = (h >> 24) / 16777216.0 + 0.5 / 16777216.0
    r = math.sqrt(-2.0 * math.log(u1))
    return r * math.cos(2.0 * math.pi * u2), r * math.sin(2.0 * math.pi * u2)


@njit(cache=True)
def _card_point(hx, hy, dx, dy, card):
    """Where the ray H + Z (d, 1) meets the card, in card coordinates (world x, y minus
    the card centre), mm.

    ``card`` is (Z, spacing, r^2) for a card perpendicular to the axis at Z with dot
    (0, 0) on it, or (Z, spacing, r^2, ox, oy, ax, ay, print_sigma, seed) for a card
    whose plane is ``Z = Z0 + ax X + ay Y`` (tilted; camera frame) with dot (0, 0) at
    world (ox, oy) and dots printed off their lattice points by a normal error of
    ``print_sigma`` mm (drawn per dot from ``seed``).
    """
    z = card[0]
    if card.shape[0] > 3:
        z = (card[0] + card[5] * hx + card[6] * hy) / (1.0 - card[5] * dx - card[6] * dy)
    xw = -(hx + dx * z)
    yw = -(hy + dy * z)
    if card.shape[0] > 3:
        xw -= card[3]
        yw -= card[4]
    return xw, yw


@njit(cache=True)
def _on_dot(hx, hy, dx, dy, card):
    """True if the ray lands inside a dot of the card (see :func:`_card_point`)."""
    xw, yw = _card_point(hx, hy, dx, dy, card)
    fm = math.floor(xw / card[1] + 0.5)
    fn = math.floor(yw / card[1] + 0.5)
    mx = xw - card[1] * fm
    my = yw - card[1] * fn
    if card.shape[0] > 3 and card[7] > 0.0:
        reach = math.sqrt(card[2]) + 8.0 * card[7]  # print errors stay below 6 sigma
        if mx * mx + my * my >= reach * reach:
            return False
        ex, ey = _hash_normal(fm, fn, card[8])
        mx -= card[7] * ex
        my -= card[7] * ey
    return mx * mx + my * my < card[2]


_PER_SAMPLE = -(1 << 41)


@njit(cache=True)
def _bundle(x0, y0, cx, cy, par):
    """Bounds on the rays of one pixel through lens C.

    (x0, y0) is the pixel centre, sensor mm; (cx, cy) the lens centre, mm. Every such
    ray that passes the aperture leaves the main lens within ``r_h`` of ``h0`` and
    crosses the focal plane within ``r_q`` of ``qo0`` (relative to the optical axis), so
    at depth Z (t = Z / s_o) it lies within ``r_h |1 - t| + r_q t`` of
    ``h0 + (qo0 - h0) t``; ``sec`` bounds 1 / cos of the ray angle to the axis. Returns
    (h0x, h0y, qo0x, qo0y, r_h, r_q, sec).
    """
    return _bundle_h(x0, y0, cx, cy, par, par[HALF_DIAG])


@njit(cache=True)
def _bundle_h(x0, y0, cx, cy, par, half):
    """:func:`_bundle` of the rays through lens C of every sensor point within ``half``
    (mm) of (x0, y0): the pixel's bounds with its half-diagonal replaced by ``half``."""
    if par[LENS_ON] != 0.0:
        return _bundle_lens(x0, y0, cx, cy, par, half)
    ex = x0 - cx * par[SCALE]
    ey = y0 - cy * par[SCALE]
    tan_s = par[S_I] / par[F_ML]
    conj = par[S_O] / par[S_I]
    r_h = half * tan_s + par[CELL_R]
    h0x = -ex * tan_s
    h0y = -ey * tan_s
    rc2 = (cx * cx + cy * cy) * par[INV_RN2]
    g0 = 1.0 + par[K1] * rc2 + par[K2] * rc2 * rc2
    qo0x = -cx * conj * g0
    qo0y = -cy * conj * g0
    rm = math.sqrt(rc2) + par[CELL_R] * math.sqrt(par[INV_RN2])
    rm2 = rm * rm
    lip = 1.0 + 3.0 * abs(par[K1]) * rm2 + 5.0 * abs(par[K2]) * rm2 * rm2
    r_q = par[CELL_R] * conj * lip
    slope = (math.sqrt(qo0x * qo0x + qo0y * qo0y) + r_q + math.sqrt(h0x * h0x + h0y * h0y)
             + r_h) / par[S_O]
    sec = math.sqrt(1.0 + slope * slope) * (1.0 + 1e-9)
    return h0x, h0y, qo0x, qo0y, r_h, r_q, sec


@njit(cache=True)
def _bundle_lens(x0, y0, cx, cy, par, half):
    """:func:`_bundle_h` with the lens effects (module notes)."""
    delta, d, s_l = _lens_geom(cx, cy, par)
    # Pixel centre minus the exact image centre a + (C - a) (s_l + d) / s_l.
    sc = (s_l + d) / s_l
    ex = x0 - par[AXX] - (cx - par[AXX]) * sc
    ey = y0 - par[AXY] - (cy - par[AXY]) * sc
    tan_d = s_l / d
    h0x = -ex * tan_d
    h0y = -ey * tan_d
    # H = h0 + q (1 + s_l/d - s_l/f) - dP s_l/d for q in the cell, dP in the pixel.
    r_h = (half * tan_d + par[CELL_R] * abs(1.0 + tan_d - s_l / par[F_ML])) * (1.0 + 1e-12)
    # Nominal-plane point U = (Q - a)(1 + w) - H w.
    w = delta / s_l
    ux = (cx - par[AXX]) * (1.0 + w) - h0x * w
    uy = (cy - par[AXY]) * (1.0 + w) - h0y * w
    r_u = par[CELL_R] * (1.0 + abs(w)) + r_h * abs(w)
    conj = par[S_O] / par[S_I]
    rc2 = (ux * ux + uy * uy) * par[INV_RN2]
    g0 = 1.0 + par[K1] * rc2 + par[K2] * rc2 * rc2
    qo0x = -ux * conj * g0
    qo0y = -uy * conj * g0
    rm = math.sqrt(rc2) + r_u * math.sqrt(par[INV_RN2])
    rm2 = rm * rm
    lip = 1.0 + 3.0 * abs(par[K1]) * rm2 + 5.0 * abs(par[K2]) * rm2 * rm2
    r_q = (r_u * conj * lip + par[E_DEF] * rm2 + par[E_COMA] * rm) * (1.0 + 1e-9)
    slope = (math.sqrt(qo0x * qo0x + qo0y * qo0y) + r_q + math.sqrt(h0x * h0x + h0y * h0y)
             + r_h) / par[S_O]
    sec = math.sqrt(1.0 + slope * slope) * (1.0 + 1e-9)
    return h0x, h0y, qo0x, qo0y, r_h, r_q, sec


@njit(cache=True)
def _bundle_candidates(x0, y0, cx, cy, par, balls, idx, p0, p1, cand, nc):
    """Append to ``cand[:nc]`` the occluders the pixel's rays through lens C may meet.

    Each occluder is bounded by one or more culling balls (``balls[idx[p0:p1]]``, module
    notes); a ball further from the bundle (:func:`_bundle`) than its radius, stretched by
    ``sec``, is never hit. Returns the new count.
    """
    h0x, h0y, qo0x, qo0y, r_h, r_q, sec = _bundle(x0, y0, cx, cy, par)
    return _bundle_cands(h0x, h0y, qo0x, qo0y, r_h, r_q, sec, par, balls, idx, p0, p1,
                         cand, nc)


@njit(cache=True)
def _bundle_cands(h0x, h0y, qo0x, qo0y, r_h, r_q, sec, par, balls, idx, p0, p1, cand, nc):
    """:func:`_bundle_candidates` of an already computed bundle."""
    s_o = par[S_O]
    for m in range(p0, p1):
        b = idx[m]
        t = balls[b, 2] / s_o
        bx = h0x + (qo0x - h0x) * t - balls[b, 0]
        by = h0y + (qo0y - h0y) * t - balls[b, 1]
        reach = r_h * abs(1.0 - t) + r_q * t + math.sqrt(balls[b, 3]) * sec + 1e-9
        if bx * bx + by * by <= reach * reach:
            q = int(balls[b, 4])
            seen = False
            for k in range(nc):
                if cand[k] == q:
                    seen = True
                    break
            if not seen:
                cand[nc] = q
                nc += 1
    return nc


@njit(cache=True)
def _card_missed(x0, y0, cx, cy, par, card):
    """True if no ray of the pixel through lens C can land on a dot of the card."""
    h0x, h0y, qo0x, qo0y, r_h, r_q, sec = _bundle(x0, y0, cx, cy, par)
    t = card[0] / par[S_O]
    spread = r_h * abs(1.0 - t) + r_q * t
    margin = 0.0
    if card.shape[0] > 3:
        # The card plane is tilted: rays of the bundle meet it at depths that differ by
        # up to |a| * 2 * (spread + 1 mm); with slopes below 1 that moves them laterally
        # by as much (a generous bound). Printed dots sit up to 8 sigma off their nodes.
        margin = (abs(card[5]) + abs(card[6])) * 2.0 * (spread + 1.0) + 8.0 * card[7]
    xw, yw = _card_point(h0x, h0y, (qo0x - h0x) / par[S_O], (qo0y - h0y) / par[S_O], card)
    mx = xw - card[1] * math.floor(xw / card[1] + 0.5)
    my = yw - card[1] * math.floor(yw / card[1] + 0.5)
    reach = spread + math.sqrt(card[2]) + margin + 1e-9
    return mx * mx + my * my > reach * reach


KEEP = -1
"""Returned by :func:`_trace_pixel` with ``keep``: no occluder can touch the pixel."""


@njit(cache=True)
def _trace_pixel(row, col, par, samples, occluders, shapes, balls, idx, p0, p1, card, cand,
                 keep):
    """Number of lit samples of pixel (row, col), with provably exact shortcuts.

    Each sample point P uses the microlens whose image centre is nearest to P. Bounds
    on the pixel's ray bundle (:func:`_bundle_candidates`) decide which occluders can be
    met; a pixel whose bundle misses the aperture is dark and one inside one lens cell
    whose bundle passes it entirely, meeting nothing, is fully lit. With ``keep`` True,
    a pixel that no occluder can touch and whose rays provably miss every dot of the
    card (:func:`_card_missed`) returns :data:`KEEP`: its value is the unoccluded one
    (the background irradiance), unchanged. Candidates are the occluders of the culling
    balls ``balls[idx[p0:p1]]``; ``cand`` is a scratch buffer of at least ``p1 - p0``
    entries. ``card`` is
    (Z, spacing, r^2) of a dot card (Z > 0) or Z <= 0 for none.
    """
    n = samples.shape[0]
    no_card = card[0] <= 0.0
    x0 = (col - (par[COLS] - 1.0) * 0.5) * par[PP]
    y0 = (row - (par[ROWS] - 1.0) * 0.5) * par[PP]
    i, j = _nearest_lens(x0 * par[INV_SCALE], y0 * par[INV_SCALE], par)
    cx, cy = _lens_center(i, j, par)
    # Offset of the pixel centre from the lens-image centre, sensor mm.
    ex = x0 - cx * par[SCALE]
    ey = y0 - cy * par[SCALE]
    e = math.sqrt(ex * ex + ey * ey)
    if e + par[HALF_DIAG] > par[INRADIUS_IMG] * (1.0 - 1e-9):
        return _trace_straddling(x0, y0, i, j, e, par, samples, occluders, shapes, balls, idx,
                                 p0, p1, card, no_card, cand, keep)
    if par[LENS_ON] != 0.0:
        return _trace_pixel_lens(x0, y0, i, j, cx, cy, par, samples, occluders, shapes, balls,
                                 idx, p0, p1, card, no_card, cand, keep)
    tan_s = par[S_I] / par[F_ML]
    r_h = par[HALF_DIAG] * tan_s + par[CELL_R]          # spread of H about its centre
    h_lo = e * tan_s - r_h
    h_hi = e * tan_s + r_h
    if h_lo > par[R_AP] * (1.0 + 1e-9):
        return 0
    if not no_card and _card_missed(x0, y0, cx, cy, par, card):
        no_card = True
    nc = np.int64(0)
    if p1 > p0:
        nc = _bundle_candidates(x0, y0, cx, cy, par, balls, idx, p0, p1, cand, np.int64(0))
    if nc == 0 and no_card and keep:
        return KEEP
    if nc == 0 and no_card and h_hi < par[R_AP] * (1.0 - 1e-9):
        return n
    return _sample_loop(x0, y0, par, samples, occluders, shapes, cand, nc, card, not no_card,
                        i, j, i, i - 1, i, j, _no_table())


@njit(cache=True)
def _trace_pixel_lens(x0, y0, i, j, cx, cy, par, samples, occluders, shapes, balls, idx, p0,
                      p1, card, no_card, cand, keep):
    """The in-cell part of :func:`_trace_pixel` with the lens effects: the same
    shortcuts on the bounds of :func:`_bundle_lens`; a pixel is fully lit only if its
    whole bundle also passes the front stop."""
    n = samples.shape[0]
    h0x, h0y, qo0x, qo0y, r_h, r_q, sec = _bundle_lens(x0, y0, cx, cy, par, par[HALF_DIAG])
    h = math.sqrt(h0x * h0x + h0y * h0y)
    if h - r_h > par[R_AP] * (1.0 + 1e-9):
        return 0
    if not no_card and _card_missed(x0, y0, cx, cy, par, card):
        no_card = True
    nc = np.int64(0)
    if p1 > p0:
        nc = _bundle_cands(h0x, h0y, qo0x, qo0y, r_h, r_q, sec, par, balls, idx, p0, p1,
                           cand, np.int64(0))
    if nc == 0 and no_card and keep:
        return KEEP
    if nc == 0 and no_card and h + r_h < par[R_AP] * (1.0 - 1e-9):
        if par[VIG_ON] == 0.0:
            return n
        t = par[VIG_L] / par[S_O]
        vx = h0x + (qo0x - h0x) * t
        vy = h0y + (qo0y - h0y) * t
        if math.sqrt(vx * vx + vy * vy) + r_h * (1.0 - t) + r_q * t < par[VIG_R] * (1.0 - 1e-9):
            return n
    if no_card and nc > 0:
        # Samples whose rays provably pass and meet nothing are lit without the rest of
        # their ray (the pixel lies inside lens (i, j)'s cell).
        return _sample_loop(x0, y0, par, samples, occluders, shapes, cand, nc, card,
                            np.bool_(False), i, j, i, i - 1, i, j,
                            _clear_table(cx, cy, par, balls, idx, p0, p1, cand, nc))
    return _sample_loop(x0, y0, par, samples, occluders, shapes, cand, nc, card, not no_card,
                        i, j, i, i - 1, i, j, _no_table())


@njit(cache=True)
def _bundle_dark(x0, y0, cx, cy, par):
    """True if no ray of the pixel through lens C passes the main-lens aperture (the
    bounds of :func:`_bundle`, as in :func:`_trace_pixel`)."""
    if par[LENS_ON] != 0.0:
        h0x, h0y, qo0x, qo0y, r_h, r_q, sec = _bundle_lens(x0, y0, cx, cy, par,
                                                           par[HALF_DIAG])
        return math.sqrt(h0x * h0x + h0y * h0y) - r_h > par[R_AP] * (1.0 + 1e-9)
    ex = x0 - cx * par[SCALE]
    ey = y0 - cy * par[SCALE]
    tan_s = par[S_I] / par[F_ML]
    r_h = par[HALF_DIAG] * tan_s + par[CELL_R]
    return math.sqrt(ex * ex + ey * ey) * tan_s - r_h > par[R_AP] * (1.0 + 1e-9)


@njit(cache=True)
def _trace_straddling(x0, y0, i, j, e, par, samples, occluders, shapes, balls, idx, p0, p1,
                      card, no_card, cand, keep):
    """The part of :func:`_trace_pixel` for a pixel that straddles lens cells.

    Its samples may use any lens whose image centre lies within ``e + 2 * half-diagonal``
    of the pixel centre (``e``: distance to the image centre of the pixel's own lens
    (i, j)): the pixel is dark when every such lens's bundle misses the aperture, keeps
    its unoccluded value (``keep``) when no occluder can touch the bundle of any of them
    that passes the aperture and none can land on a dot, and otherwise traces every
    sample, searching its lens only in the rows of those lenses
    (:func:`_nearest_lens_rows`) unless it lies within the inradius of lens (i, j)'s
    cell.
    """
    lim = (e + 2.0 * par[HALF_DIAG]) * (1.0 + 1e-9)
    nc = np.int64(0)
    dark = True
    missed = True
    row_lo, row_hi = i, i
    for ni in range(i - 1, i + 2):
        for nj in range(j - 1, j + 2):
            lx, ly = _lens_center(ni, nj, par)
            fx = x0 - lx * par[SCALE]
            fy = y0 - ly * par[SCALE]
            if fx * fx + fy * fy <= lim * lim:
                row_lo = min(row_lo, ni)
                row_hi = max(row_hi, ni)
                if not no_card and missed and not _card_missed(x0, y0, lx, ly, par, card):
                    missed = False
                # A lens whose bundle misses the aperture has no lit sample: its
                # candidates are not needed.
                if p1 > p0 and par[LENS_ON] != 0.0:
                    # One bundle for both tests (the arithmetic of _bundle_dark).
                    h0x, h0y, qo0x, qo0y, r_h, r_q, sec = _bundle_lens(x0, y0, lx, ly, par,
                                                                       par[HALF_DIAG])
                    if not (math.sqrt(h0x * h0x + h0y * h0y) - r_h > par[R_AP] * (1.0 + 1e-9)):
                        dark = False
                        nc = _bundle_cands(h0x, h0y, qo0x, qo0y, r_h, r_q, sec, par,
                                           balls, idx, p0, p1, cand, nc)
                    continue
                if p1 > p0:
                    if not _bundle_dark(x0, y0, lx, ly, par):
                        dark = False
                        nc = _bundle_candidates(x0, y0, lx, ly, par, balls, idx, p0, p1,
                                                cand, nc)
                elif dark and not _bundle_dark(x0, y0, lx, ly, par):
                    dark = False
    if dark:
        return 0
    if nc == 0 and missed and keep:
        return KEEP
    if par[LENS_ON] != 0.0 and nc > 0 and (no_card or missed):
        # The samples that use lens (i, j) may be proved lit (its cell holds their P).
        cx, cy = _lens_center(i, j, par)
        return _sample_loop(x0, y0, par, samples, occluders, shapes, cand, nc, card,
                            np.bool_(False), np.int64(_PER_SAMPLE), j, row_lo, row_hi, i, j,
                            _clear_table(cx, cy, par, balls, idx, p0, p1, cand, nc))
    return _sample_loop(x0, y0, par, samples, occluders, shapes, cand, nc, card,
                        not (no_card or missed), np.int64(_PER_SAMPLE), j, row_lo, row_hi, i, j,
                        _no_table())


_LENS_CHUNK = 16
"""Lenses handed to a thread at a time by :func:`render_lenses` (dynamic scheduling: the
lenses near a particle cost far more than the others)."""

NO_SHAPES = np.zeros((0, 7))
"""``shapes`` argument for occluders that are all spheres (module notes). Kept writeable
so that numba compiles one specialisation for both cases; never written to."""


def _balls_arg(balls, occluders):
    """The culling balls (module notes); None: one per occluder, its bounding sphere."""
    if balls is None:
        m = occluders.shape[0]
        return np.column_stack([np.asarray(occluders, dtype=np.float64).reshape(m, 4),
                                np.arange(m, dtype=np.float64)])
    balls = np.ascontiguousarray(balls, dtype=np.float64)
    if balls.ndim != 2 or balls.shape[1] != 5:
        raise ValueError(f"balls must be (B, 5) rows (X, Y, Z, r^2, occluder); got shape "
                         f"{balls.shape}")
    return balls


def _shapes_arg(shapes, occluders):
    if shapes is None or len(shapes) == 0:
        return NO_SHAPES
    shapes = np.ascontiguousarray(shapes, dtype=np.float64)
    m = occluders.shape[0]
    if (shapes.ndim != 2 or shapes.shape[0] != m
            or not (shapes.shape[1] == N_SHAPE_BASE or shapes.shape[1] >= S_PLANES)):
        raise ValueError(f"shapes must be (0, 7), ({m}, 7) or ({m}, W >= {S_PLANES}), one row "
                         f"per occluder; got shape {shapes.shape}")
    return shapes


def render_all(par, samples, occluders, card, r0, r1, c0, c1, exact, shapes=None, balls=None):
    """Trace every pixel of the window rows [r0, r1), cols [c0, c1) against all occluders.

    ``exact`` True traces every sample of every pixel against every occluder (the
    brute-force reference); False uses the per-pixel shortcuts of :func:`_trace_pixel`.
    ``shapes`` (module notes) marks ellipsoids; None: all spheres. ``balls``: the culling
    balls (module notes); None: each occluder's bounding sphere.
    Returns a ``(r1 - r0, c1 - c0)`` float32 irradiance image in [0, 1].
    """
    return _render_all(par, samples, occluders, _shapes_arg(shapes, occluders),
                       _balls_arg(balls, occluders), card, r0, r1, c0, c1, exact)


def render_lenses(out, lenses, ptr, idx, par, samples, occluders, card, shapes=None,
                  balls=None):
    """Re-trace, in place, every pixel of ``out`` owned by one of ``lenses``.

    ``out`` must hold the unoccluded irradiance: pixels no occluder can touch keep it.

    A pixel is owned by the lens whose image centre is nearest to the pixel centre (its
    samples may still use a neighbouring lens). ``lenses`` is ``(L, 2)`` int64 (i, j);
    the pixels of lens ``k`` are tested against the occluders of the culling balls
    ``balls[idx[ptr[k]:ptr[k + 1]]]`` (module notes; None: ``balls`` are the occluders'
    bounding spheres and ``idx`` indexes the occluders).
    ``shapes`` (module notes) marks ellipsoids; None: all spheres.
    """
    with numba.parallel_chunksize(_LENS_CHUNK):
        _render_lenses(out, lenses, ptr, idx, par, samples, occluders,
                       _shapes_arg(shapes, occluders), _balls_arg(balls, occluders), card)


@njit(parallel=True, cache=True)
def _render_all(par, samples, occluders, shapes, balls, card, r0, r1, c0, c1, exact):
    """:func:`render_all` (numba core)."""
    out = np.empty((r1 - r0, c1 - c0), dtype=np.float32)
    m = occluders.shape[0]
    idx = np.arange(m)
    n_balls = balls.shape[0]
    ball_idx = np.arange(n_balls)
    inv_n = 1.0 / samples.shape[0]
    for r in prange(r0, r1):
        cand = np.empty(m, dtype=np.int64)
        for c in range(c0, c1):
            if exact:
                x0 = (c - (par[COLS] - 1.0) * 0.5) * par[PP]
                y0 = (r - (par[ROWS] - 1.0) * 0.5) * par[PP]
                lit = _sample_loop(x0, y0, par, samples, occluders, shapes, idx, m, card,
                                   card[0] > 0.0, np.int64(_PER_SAMPLE), c, r, r - 1, r, c,
                                   _no_table())
            else:
                lit = _trace_pixel(r, c, par, samples, occluders, shapes, balls, ball_idx,
                                   np.int64(0), n_balls, card, cand, np.bool_(False))
            out[r - r0, c - c0] = lit * inv_n
    return out


@njit(cache=True)
def _image_centre(cx, cy, par):
    """Where lens C's rays leave the main lens: ``(ex, ey, tan)`` such that the rays
    through C of a sensor point P pass the main-lens plane near ``h0 = -(P - E) tan``
    (``E`` the exact centre of the lens image, sensor mm; the ``h0`` of :func:`_bundle`)."""
    if par[LENS_ON] != 0.0:
        delta, d, s_l = _lens_geom(cx, cy, par)
        sc = (s_l + d) / s_l
        return (par[AXX] + (cx - par[AXX]) * sc, par[AXY] + (cy - par[AXY]) * sc, s_l / d)
    return cx * par[SCALE], cy * par[SCALE], par[S_I] / par[F_ML]


@njit(cache=True)
def _shadow_discs(i, j, par, balls, idx, p0, p1, discs):
    """Sensor discs holding every pixel centre whose rays may meet a culling ball
    ``balls[idx[p0:p1]]`` (module notes).

    The rays are those of the pixels' sample points through lens (i, j) or one of its 8
    index neighbours (every lens a sample of a pixel owned by lens (i, j) can use). For
    neighbour C and occluder q: every ray of a pixel centred at P through C leaves the
    main lens within ``r_h`` of ``h0 = -(P - E) tan`` (:func:`_image_centre`, the
    pixel's ``r_h`` of :func:`_bundle`) and crosses the focal plane within ``r_q`` of
    ``qo0``, with ``qo0``, ``r_q`` and ``sec`` the bounds of :func:`_bundle_h` over C's
    whole cell (every sensor point that uses C); so it may meet q (depth ``t s_o``)
    only if ``|h0 (1 - t) + qo0 t - o| <= reach``, which is a disc in P of centre
    ``E + (qo0 t - o) / (tan (1 - t))`` and radius ``reach / (tan |1 - t|)``. These bounds
    contain those of :func:`_bundle_candidates` for any pixel. Writes rows
    ``(x, y, radius^2)`` (sensor mm; radius^2 = inf for every pixel) to ``discs`` and
    returns their number.
    """
    nd = 0
    s_o = par[S_O]
    r_cell = par[CELL_R] * par[SCALE] * (1.0 + 1e-6)
    for ni in range(i - 1, i + 2):
        for nj in range(j - 1, j + 2):
            lx, ly = _lens_center(ni, nj, par)
            ex, ey, tan = _image_centre(lx, ly, par)
            r_h = _bundle_h(ex, ey, lx, ly, par, par[HALF_DIAG])[4]
            _, _, qo0x, qo0y, _, r_q, sec = _bundle_h(lx * par[SCALE], ly * par[SCALE], lx, ly,
                                                      par, r_cell)
            for m in range(p0, p1):
                q = idx[m]
                t = balls[q, 2] / s_o
                reach = ((r_h * abs(1.0 - t) + r_q * t + math.sqrt(balls[q, 3]) * sec)
                         * (1.0 + 1e-7) + 1e-9)
                kx = qo0x * t - balls[q, 0]
                ky = qo0y * t - balls[q, 1]
                u = tan * (1.0 - t)
                if abs(u) < 1e-6:
                    # |u (P - E)| < 1e-6 mm over the lens's pixels: all of them or none.
                    lim = reach + 1e-6
                    if kx * kx + ky * ky <= lim * lim:
                        discs[nd, 0] = ex
                        discs[nd, 1] = ey
                        discs[nd, 2] = math.inf
                        nd += 1
                    continue
                rad = reach / abs(u) * (1.0 + 1e-9) + 1e-9
                discs[nd, 0] = ex + kx / u
                discs[nd, 1] = ey + ky / u
                discs[nd, 2] = rad * rad
                nd += 1
    return nd


@njit(parallel=True, cache=True)
def _render_lenses(out, lenses, ptr, idx, par, samples, occluders, shapes, balls, card):
    """:func:`render_lenses` (numba core).

    Without a card, a lens's pixels are visited only where one of its
    :func:`_shadow_discs` holds their centre (row by row, between the first and last
    column any disc reaches): every other pixel has no candidate occluder for any of its
    lenses in :func:`_trace_pixel`, so it keeps the unoccluded value.
    """
    rows = out.shape[0]
    cols = out.shape[1]
    inv_n = 1.0 / samples.shape[0]
    half_r = (par[ROWS] - 1.0) * 0.5
    half_c = (par[COLS] - 1.0) * 0.5
    reach = par[CELL_PX] + 1.0
    filtered = card[0] <= 0.0
    pp = par[PP]
    for k in prange(lenses.shape[0]):
        i = lenses[k, 0]
        j = lenses[k, 1]
        cand = np.empty(ptr[k + 1] - ptr[k], dtype=np.int64)
        discs = np.empty((9 * (ptr[k + 1] - ptr[k]), 3))
        nd = 0
        if filtered:
            nd = _shadow_discs(i, j, par, balls, idx, ptr[k], ptr[k + 1], discs)
            if nd == 0:
                continue
        cx, cy = _lens_center(i, j, par)
        crow = cy * par[SCALE] / par[PP] + half_r
        ccol = cx * par[SCALE] / par[PP] + half_c
        ra = max(0, int(math.floor(crow - reach)))
        rb = min(rows, int(math.ceil(crow + reach)) + 1)
        ca = max(0, int(math.floor(ccol - reach)))
        cb = min(cols, int(math.ceil(ccol + reach)) + 1)
        for r in range(ra, rb):
            c_lo, c_hi = ca, cb
            if filtered:
                y0 = (r - half_r) * pp
                lo = float(cb)
                hi = float(ca - 1)
                for m in range(nd):
                    dy = y0 - discs[m, 1]
                    rem = discs[m, 2] - dy * dy
                    if rem < 0.0:
                        continue
                    w = math.sqrt(rem)
                    lo = min(lo, (discs[m, 0] - w) / pp + half_c - 1.0)
                    hi = max(hi, (discs[m, 0] + w) / pp + half_c + 1.0)
                lo = max(lo, float(ca))
                hi = min(hi, float(cb - 1))
                if hi < lo:
                    continue
                c_lo = int(math.floor(lo))
                c_hi = int(math.ceil(hi)) + 1
            for c in range(c_lo, min(c_hi, cb)):
                if filtered:
                    x0 = (c - half_c) * pp
                    y0 = (r - half_r) * pp
                    inside = False
                    for m in range(nd):
                        dx = x0 - discs[m, 0]
                        dy = y0 - discs[m, 1]
                        if dx * dx + dy * dy <= discs[m, 2]:
                            inside = True
                            break
                    if not inside:
                        continue
                pi, pj = _pixel_lens(r, c, par)
                if pi != i or pj != j:
                    continue
                lit = _trace_pixel(r, c, par, samples, occluders, shapes, balls, idx, ptr[k],
                                   ptr[k + 1], card, cand, np.bool_(True))
                if lit != KEEP:
                    out[r, c] = lit * inv_n


def render_card(out, par, samples, card, r0=0, c0=0):
    """Re-trace, in place, every pixel of ``out`` whose rays may land on a dot of ``card``.

    ``out`` holds the window of sensor rows ``[r0, r0 + out.shape[0])`` and columns
    ``[c0, c0 + out.shape[1])`` of the unoccluded irradiance (the background, traced with
    the same ``par`` and ``samples``): a pixel whose ray bundles provably miss every dot
    (:func:`_card_missed`) keeps it, since tracing it against the card would count the
    same samples. The result is identical to :func:`render_all` of that window with the
    card.
    """
    rows, cols = int(par[ROWS]), int(par[COLS])
    if (out.ndim != 2 or out.dtype != np.float32 or r0 < 0 or c0 < 0
            or r0 + out.shape[0] > rows or c0 + out.shape[1] > cols):
        raise ValueError(f"out must be a float32 window of the ({rows}, {cols}) background "
                         f"irradiance; got {out.dtype} {out.shape} at ({r0}, {c0})")
    _render_card(out, par, samples, card, NO_SHAPES, r0, c0)


@njit(parallel=True, cache=True)
def _render_card(out, par, samples, card, shapes, r0, c0):
    """:func:`render_card` (numba core)."""
    occluders = np.zeros((0, 4))
    balls = np.zeros((0, 5))
    idx = np.zeros(0, dtype=np.int64)
    cand = np.zeros(0, dtype=np.int64)
    inv_n = 1.0 / samples.shape[0]
    for r in prange(out.shape[0]):
        for c in range(out.shape[1]):
            lit = _trace_pixel(r0 + r, c0 + c, par, samples, occluders, shapes, balls, idx,
                               np.int64(0), np.int64(0), card, cand, np.bool_(True))
            if lit != KEEP:
                out[r, c] = lit * inv_n
