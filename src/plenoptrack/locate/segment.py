"""Particle segmentation in perspective views.

Particles are dark on a bright background. In every view a local background level is
estimated with a box window, pixels darker than that background by a relative margin
form the foreground, 8-connected foreground regions are the detections, and each region
is summarised by its darkness-weighted centroid and its (unweighted) second moments.

All views of a light field are processed by one compiled kernel that runs in parallel
over views (numba ``prange``); no Python loop runs over views or pixels. See
:func:`segment_array` for the array-level function, :func:`segment_view` for a single
image and :func:`segment_views` for a :class:`~plenoptrack.lightfield.decode.LightField`.

References
----------
E. M. Hall, D. R. Guildenbecher, B. S. Thurow, "Development and uncertainty
characterization of 3D particle location from perspective shifted plenoptic images",
Opt. Express 27 (2019), section 2.1.
"""

from __future__ import annotations

import math
import warnings

import numba
import numpy as np
import pandas as pd

from .._columns import T_COLUMN
from ..errors import NoParticlesWarning, SettingsError

__all__ = ["DETECTION_COLUMNS", "segment_view", "segment_array", "segment_views"]

DETECTION_COLUMNS = (T_COLUMN, "u", "v", "s", "t", "area", "diameter_px", "major_axis_px",
                     "minor_axis_px", "orientation", "eccentricity", "darkness", "dark_area")
"""Columns of a detections table, in order (see :func:`segment_array` for units)."""

# Per-region accumulator layout written by the kernel.
_N, _SW, _SWS, _SWT, _SS, _ST, _SSS, _STT, _SST, _DARK, _EDGE, _S0, _T0, _SD, _PART, _PARENT_N = (
    range(16))
_N_STATS = 16
_OFFSET_SAMPLES = 2000
"""About this many background samples (on a grid of every k'th row and column) give the
median of a view's background relative darkness (to about 3 % of the pixel noise)."""
# Regions per view the kernel's buffer has room for at least (see _region_stats).
_INITIAL_CAPACITY = 256


# --------------------------------------------------------------------------------------
# compiled kernel
@numba.njit(cache=True)
def _find(parent, x):  # pragma: no cover - compiled
    root = x
    while parent[root] != root:
        root = parent[root]
    while parent[x] != root:  # path compression
        nxt = parent[x]
        parent[x] = root
        x = nxt
    return root


@numba.njit(cache=True)
def _union(parent, a, b):  # pragma: no cover - compiled
    ra = _find(parent, a)
    rb = _find(parent, b)
    if ra < rb:
        parent[rb] = ra
        return ra
    if rb < ra:
        parent[ra] = rb
    return rb


@numba.njit(cache=True)
def _block_mean(bsum, bcnt, rb, out):  # pragma: no cover - compiled
    """Mean over a (2 rb + 1)^2 window of blocks from block sums and counts; NaN if empty."""
    nbi, nbj = bsum.shape
    sat_v = np.zeros((nbi + 1, nbj + 1), dtype=np.float64)
    sat_c = np.zeros((nbi + 1, nbj + 1), dtype=np.float64)
    for bi in range(nbi):
        rv = 0.0
        rc = 0.0
        for bj in range(nbj):
            rv += bsum[bi, bj]
            rc += bcnt[bi, bj]
            sat_v[bi + 1, bj + 1] = sat_v[bi, bj + 1] + rv
            sat_c[bi + 1, bj + 1] = sat_c[bi, bj + 1] + rc
    for bi in range(nbi):
        i0 = max(0, bi - rb)
        i1 = min(nbi, bi + rb + 1)
        for bj in range(nbj):
            j0 = max(0, bj - rb)
            j1 = min(nbj, bj + rb + 1)
            sc = sat_c[i1, j1] - sat_c[i0, j1] - sat_c[i1, j0] + sat_c[i0, j0]
            if sc > 0.5:
                sv = sat_v[i1, j1] - sat_v[i0, j1] - sat_v[i1, j0] + sat_v[i0, j0]
                out[bi, bj] = sv / sc
            else:
                out[bi, bj] = np.nan


@numba.njit(cache=True)
def _fill_nan(grid, fallback):  # pragma: no cover - compiled
    for bi in range(grid.shape[0]):
        for bj in range(grid.shape[1]):
            if not np.isfinite(grid[bi, bj]):
                grid[bi, bj] = fallback[bi, bj]


@numba.njit(cache=True)
def _interp_axis(n, b):  # pragma: no cover - compiled
    """Lower block index and weight to linearly interpolate block centres at 0 ... n-1."""
    nb = (n + b - 1) // b
    lo = np.empty(n, dtype=np.int64)
    wt = np.empty(n, dtype=np.float64)
    for i in range(n):
        f = (i - 0.5 * (b - 1)) / b
        if f <= 0.0 or nb == 1:
            lo[i] = 0
            wt[i] = 0.0
        elif f >= nb - 1:
            lo[i] = nb - 2
            wt[i] = 1.0
        else:
            k = int(f)
            lo[i] = k
            wt[i] = f - k
    return lo, wt


@numba.njit(cache=True)
def _grid_row(grid, ilo, iw, i, row):  # pragma: no cover - compiled
    """Block grid interpolated (linearly) to pixel row ``i``; written into ``row``."""
    i0 = ilo[i]
    i1 = min(i0 + 1, grid.shape[0] - 1)
    a = iw[i]
    for bj in range(grid.shape[1]):
        row[bj] = (1.0 - a) * grid[i0, bj] + a * grid[i1, bj]


@numba.njit(cache=True)
def _at(row, jlo, jw, j):  # pragma: no cover - compiled
    j0 = jlo[j]
    j1 = min(j0 + 1, row.shape[0] - 1)
    c = jw[j]
    return (1.0 - c) * row[j0] + c * row[j1]


@numba.njit(cache=True)
def _label_pixel(labels, parent, n_lab, i, j, conn8):  # pragma: no cover - compiled
    """Label foreground pixel ``(i, j)`` in a raster scan with union-find; return ``n_lab``.

    Joins the neighbours already visited (W, N, and NW, NE with 8-connectivity); a pixel
    with none starts a new label.
    """
    w = labels.shape[1]
    lab = 0
    if j > 0 and labels[i, j - 1] > 0:
        lab = labels[i, j - 1]
    if i > 0:
        if labels[i - 1, j] > 0:
            lab = labels[i - 1, j] if lab == 0 else _union(parent, lab, labels[i - 1, j])
        if conn8:
            if j > 0 and labels[i - 1, j - 1] > 0:
                lab = labels[i - 1, j - 1] if lab == 0 else _union(parent, lab, labels[i - 1, j - 1])
            if j < w - 1 and labels[i - 1, j + 1] > 0:
                lab = labels[i - 1, j + 1] if lab == 0 else _union(parent, lab, labels[i - 1, j + 1])
    if lab == 0:
        n_lab += 1
        parent[n_lab] = n_lab
        lab = n_lab
    labels[i, j] = lab
    return n_lab


@numba.njit(cache=True)
def _reset(arr, pi, pj, value):  # pragma: no cover - compiled
    """Set ``arr`` back to ``value`` at the pixels ``(pi, pj)``."""
    for p in range(pi.shape[0]):
        arr[pi[p], pj[p]] = value


@numba.njit(cache=True)
def _label_cores(reg, n_reg, rel_dark, core_contrast, min_core_ratio, conn8, pi, pj,
                 labels, core):  # pragma: no cover - compiled
    """Connected cores of the regions ``reg``: pixels darker than ``core_contrast`` times
    the region's peak relative darkness, capped at 1 (an opaque shadow).

    Relative to the region's own peak so that a translucent particle, whose shadow never
    reaches the darkness of an opaque one, still has a core. A core of a single pixel
    smaller than ``min_core_ratio`` times the largest core of its region is not counted:
    it is a dark fleck on the same particle (noise on the plateau, the ridge of a thin
    appendage breaking up on the pixel grid), not the core of another particle. Cores of
    two or more pixels always count: in a crowded region the largest core is often the
    fused core of several particles, and judging the others against it loses them.
    ``pi, pj`` list the region pixels in raster order (every other pixel is outside the
    regions). ``labels`` (all 0) and ``core`` (all -1) are work arrays of the view's shape;
    ``labels`` is left as it was found. Writes the core index of every region pixel into
    ``core`` (cores numbered in raster order of their first pixel) and returns the number
    of cores.
    """
    n_px = pi.shape[0]
    threshold = np.zeros(n_reg)
    for p in range(n_px):
        i, j = pi[p], pj[p]
        r = reg[i, j]
        if rel_dark[i, j] > threshold[r]:
            threshold[r] = rel_dark[i, j]
    for r in range(n_reg):
        threshold[r] = core_contrast * min(threshold[r], 1.0)
    parent = np.empty(n_px + 2, dtype=np.int32)
    parent[0] = 0
    n_lab = 0
    for p in range(n_px):
        i, j = pi[p], pj[p]
        if rel_dark[i, j] > threshold[reg[i, j]]:
            n_lab = _label_pixel(labels, parent, n_lab, i, j, conn8)
    size = np.zeros(n_lab + 1, dtype=np.int64)
    largest = np.zeros(n_reg, dtype=np.int64)
    for p in range(n_px):
        i, j = pi[p], pj[p]
        if labels[i, j] > 0:
            root = _find(parent, labels[i, j])
            labels[i, j] = root
            size[root] += 1
            if size[root] > largest[reg[i, j]]:
                largest[reg[i, j]] = size[root]
    compact = np.full(n_lab + 1, -1, dtype=np.int64)
    n_core = 0
    for p in range(n_px):
        i, j = pi[p], pj[p]
        root = labels[i, j]
        labels[i, j] = 0
        if root > 0 and (size[root] > 1
                         or size[root] >= min_core_ratio * largest[reg[i, j]]):
            if compact[root] < 0:
                compact[root] = n_core
                n_core += 1
            core[i, j] = compact[root]
    return n_core


@numba.njit(cache=True)
def _split_by_cores(reg, n_reg, rel_dark, core_contrast, min_core_ratio, conn8, pi, pj,
                    unit, labels, core):  # pragma: no cover - compiled
    """Unit of every pixel: its region, or the core it is nearest to in a merged region.

    A region holding two or more cores is the merged image of several particles. Its
    pixels are shared out between its cores by a breadth-first flood from the cores
    through the region (nearest core by path length within the region), so that each
    part keeps the region's soft edge for its centroid. Units ``0 .. n_reg - 1`` are
    regions; unit ``n_reg + c`` is the part of core ``c``. ``pi, pj``: the region pixels
    in raster order. ``unit`` (all -1), ``labels`` (all 0) and ``core`` (all -1) are work
    arrays of the view's shape; ``labels`` and ``core`` are left as they were found.
    Writes the unit of every region pixel into ``unit`` and returns the number of unit
    indices.
    """
    h, w = reg.shape
    n_px = pi.shape[0]
    n_core = _label_cores(reg, n_reg, rel_dark, core_contrast, min_core_ratio, conn8, pi, pj,
                          labels, core)
    cores_in = np.zeros(n_reg, dtype=np.int64)
    core_region = np.full(n_core, -1, dtype=np.int64)
    for p in range(n_px):
        i, j = pi[p], pj[p]
        c = core[i, j]
        if c >= 0 and core_region[c] < 0:
            core_region[c] = reg[i, j]
            cores_in[reg[i, j]] += 1
    n_split_px = 0
    for p in range(n_px):
        i, j = pi[p], pj[p]
        unit[i, j] = reg[i, j]
        if cores_in[reg[i, j]] >= 2:
            n_split_px += 1
            unit[i, j] = -2  # not yet reached
    if n_split_px == 0:
        _reset(core, pi, pj, -1)
        return n_reg + n_core
    qi = np.empty(n_split_px, dtype=np.int64)
    qj = np.empty(n_split_px, dtype=np.int64)
    tail = 0
    for p in range(n_px):
        i, j = pi[p], pj[p]
        if unit[i, j] == -2 and core[i, j] >= 0:
            unit[i, j] = n_reg + core[i, j]
            qi[tail] = i
            qj[tail] = j
            tail += 1
    head = 0
    while head < tail:
        i = qi[head]
        j = qj[head]
        head += 1
        for di in range(-1, 2):
            for dj in range(-1, 2):
                if (di == 0 and dj == 0) or (not conn8 and di != 0 and dj != 0):
                    continue
                ii = i + di
                jj = j + dj
                if 0 <= ii < h and 0 <= jj < w and unit[ii, jj] == -2:
                    unit[ii, jj] = unit[i, j]
                    qi[tail] = ii
                    qj[tail] = jj
                    tail += 1
    _reset(core, pi, pj, -1)
    return n_reg + n_core


@numba.njit(cache=True)
def _background_offset(rel_dark, valid, contrast):  # pragma: no cover - compiled
    """Median relative darkness of the background (valid samples not darker than the
    threshold) on a grid of every k'th row and column (about :data:`_OFFSET_SAMPLES`
    samples), limited to +-0.5; 0 when there are none."""
    h, w = rel_dark.shape
    k = max(1, int(math.sqrt(h * w / _OFFSET_SAMPLES)))
    sample = np.empty(((h + k - 1) // k) * ((w + k - 1) // k), dtype=np.float64)
    n = 0
    for i in range(0, h, k):
        for j in range(0, w, k):
            if valid[i, j] and rel_dark[i, j] <= contrast:
                sample[n] = rel_dark[i, j]
                n += 1
    if n == 0:
        return 0.0
    return min(max(np.median(sample[:n]), -0.5), 0.5)


@numba.njit(cache=True)
def _centroid_caps(weight, unit, pi, pj, n_reg, n_units, clip):  # pragma: no cover - compiled
    """(n_units,) cap on the centroid weight of each unit's pixels: ``clip`` times the
    largest weight of a whole region (unit below ``n_reg``) that has a plateau above
    that level, some pixel above it with its four neighbours; infinite (no cap) for the
    rest, for the parts of regions shared out between cores and for every unit when
    ``clip`` is 1. A small image has no plateau: its peak is its edge, and capping it
    would only pull the centroid towards the pixel grid."""
    top = np.full(n_units, np.inf)
    if clip >= 1.0:
        return top
    h, w = unit.shape
    top[:n_reg] = 0.0
    for p in range(pi.shape[0]):
        un = unit[pi[p], pj[p]]
        if 0 <= un < n_reg and weight[pi[p], pj[p]] > top[un]:
            top[un] = weight[pi[p], pj[p]]
    top[:n_reg] *= clip
    plateau = np.zeros(n_reg, dtype=np.bool_)
    for p in range(pi.shape[0]):
        i, j = pi[p], pj[p]
        un = unit[i, j]
        if un < 0 or un >= n_reg or plateau[un] or weight[i, j] < top[un]:
            continue
        if 0 < i < h - 1 and 0 < j < w - 1:
            plateau[un] = (unit[i - 1, j] == un and weight[i - 1, j] >= top[un]
                           and unit[i + 1, j] == un and weight[i + 1, j] >= top[un]
                           and unit[i, j - 1] == un and weight[i, j - 1] >= top[un]
                           and unit[i, j + 1] == un and weight[i, j + 1] >= top[un])
    for un in range(n_reg):
        if not plateau[un]:
            top[un] = np.inf
    return top


@numba.njit(cache=True)
def _segment_one(img, mask, zero_invalid, b, rb, contrast, core_contrast, min_core_ratio,
                 conn8, centroid_clip, out, work):  # pragma: no cover - compiled
    """Segment one view; write per-region sums into ``out``; return the region count.

    A pixel's centroid weight is capped at ``centroid_clip`` times the largest weight
    in its region, in regions not shared out between cores that have a plateau above
    the cap; 1 leaves the weights as they are.

    With ``core_contrast > 0`` a region with several cores is written as one row per
    core (its part of the region, see :func:`_split_by_cores`) instead of one row.
    ``work`` is the view-sized work space of :func:`_work_arrays`, left as it was found:
    only the few per cent of pixels in and around regions are touched, so one work space
    serves many views without clearing (or allocating) whole images for each.
    """
    valid, weight, rel_dark, labels, reg, unit, core, near, pi, pj, parent = work
    h, w = img.shape
    cap = out.shape[0]
    nbi = (h + b - 1) // b
    nbj = (w + b - 1) // b
    jblock = np.empty(w, dtype=np.int64)
    for j in range(w):
        jblock[j] = j // b
    bsum = np.zeros((nbi, nbj), dtype=np.float64)
    bcnt = np.zeros((nbi, nbj), dtype=np.float64)
    for i in range(h):
        bi = i // b
        for j in range(w):
            x = img[i, j]
            ok = mask[i, j] and np.isfinite(x)
            if zero_invalid and x == 0.0:
                ok = False
            valid[i, j] = ok
            if ok:
                bsum[bi, jblock[j]] += x
                bcnt[bi, jblock[j]] += 1.0
    bg1 = np.empty((nbi, nbj), dtype=np.float64)
    _block_mean(bsum, bcnt, rb, bg1)
    ilo, iw = _interp_axis(h, b)
    jlo, jw = _interp_axis(w, b)
    # second pass: background from samples the first pass did not call dark
    scale = 1.0 - contrast
    bsum[:, :] = 0.0
    bcnt[:, :] = 0.0
    row = np.empty(nbj, dtype=np.float64)
    for i in range(h):
        bi = i // b
        _grid_row(bg1, ilo, iw, i, row)
        for j in range(w):
            if valid[i, j]:
                x = img[i, j]
                if not (x < _at(row, jlo, jw, j) * scale):
                    bsum[bi, jblock[j]] += x
                    bcnt[bi, jblock[j]] += 1.0
    bg = np.empty((nbi, nbj), dtype=np.float64)
    _block_mean(bsum, bcnt, rb, bg)
    _fill_nan(bg, bg1)
    parent[0] = 0
    n_lab = 0
    n_px = 0   # the foreground pixels in raster order: every later pass visits only them
    for i in range(h):
        _grid_row(bg, ilo, iw, i, row)
        for j in range(w):
            if not valid[i, j]:
                continue
            bgv = _at(row, jlo, jw, j)
            rel_dark[i, j] = (bgv - img[i, j]) / bgv if bgv > 0.0 else 0.0
            if not (bgv > 0.0 and img[i, j] < bgv * scale):
                continue
            weight[i, j] = bgv * scale - img[i, j]
            n_lab = _label_pixel(labels, parent, n_lab, i, j, conn8)
            pi[n_px] = i
            pj[n_px] = j
            n_px += 1
    if n_lab == 0:
        return 0
    # The box mean takes in the faint tails of every image around, so it lies a little
    # below the true background and the bright background reads slightly negative in
    # rel_dark: its median ``o`` over the background. The summed shadow is taken as
    # (rel_dark - o) / (1 - o), the darkness against the background level itself.
    offset = _background_offset(rel_dark, valid, contrast)
    pi = pi[:n_px]
    pj = pj[:n_px]
    reg_n = np.zeros(n_lab + 1, dtype=np.float64)
    compact = np.full(n_lab + 1, -1, dtype=np.int64)
    n_reg = 0
    for p in range(n_px):
        i, j = pi[p], pj[p]
        root = _find(parent, labels[i, j])
        labels[i, j] = 0
        if compact[root] < 0:
            compact[root] = n_reg
            n_reg += 1
        reg[i, j] = compact[root]
        reg_n[compact[root]] += 1.0
    if core_contrast > 0.0:
        n_units = _split_by_cores(reg, n_reg, rel_dark, core_contrast, min_core_ratio, conn8,
                                  pi, pj, unit, labels, core)
    else:
        n_units = n_reg
        for p in range(n_px):
            unit[pi[p], pj[p]] = reg[pi[p], pj[p]]
    top = _centroid_caps(weight, unit, pi, pj, n_reg, n_units, centroid_clip)
    row_of = np.full(n_units, -1, dtype=np.int64)
    n_row = 0
    for p in range(n_px):
        i, j = pi[p], pj[p]
        un = unit[i, j]
        if un < 0:
            continue
        k = row_of[un]
        if k < 0:
            k = n_row
            row_of[un] = k
            n_row += 1
            if k < cap:
                for c in range(_N_STATS):
                    out[k, c] = 0.0
                out[k, _S0] = j
                out[k, _T0] = i
                out[k, _PART] = 1.0 if un >= n_reg else 0.0
                out[k, _PARENT_N] = reg_n[reg[i, j]]
        if k >= cap:
            continue
        wgt = weight[i, j]
        if wgt > top[un]:
            wgt = top[un]
        ds = j - out[k, _S0]
        dt = i - out[k, _T0]
        out[k, _N] += 1.0
        out[k, _SW] += wgt
        out[k, _SWS] += wgt * ds
        out[k, _SWT] += wgt * dt
        out[k, _SS] += ds
        out[k, _ST] += dt
        out[k, _SSS] += ds * ds
        out[k, _STT] += dt * dt
        out[k, _SST] += ds * dt
        out[k, _SD] += (rel_dark[i, j] - offset) / (1.0 - offset)
        if rel_dark[i, j] > out[k, _DARK]:
            out[k, _DARK] = rel_dark[i, j]
        if out[k, _EDGE] == 0.0:
            edge = i == 0 or j == 0 or i == h - 1 or j == w - 1
            if not edge:
                for di in range(-1, 2):
                    for dj in range(-1, 2):
                        if not valid[i + di, j + dj]:
                            edge = True
            if edge:
                out[k, _EDGE] = 1.0
    _add_rim_shadow(reg, unit, row_of, valid, rel_dark, offset, out, pi, pj, near, core,
                    labels)
    _reset(reg, pi, pj, -1)
    _reset(unit, pi, pj, -1)
    return n_row


@numba.njit(cache=True, inline="always")
def _add_unique(touched, n, value):  # pragma: no cover - compiled
    """Append ``value`` to ``touched[:n]`` unless it is there; return the new length."""
    for m in range(n):
        if touched[m] == value:
            return n
    touched[n] = value
    return n + 1


@numba.njit(cache=True, inline="always")
def _share_shadow(out, row_of, touched, n, darkness):  # pragma: no cover - compiled
    """Add ``darkness`` to the summed shadow of the units ``touched[:n]``, in equal shares
    (units beyond the buffer ``out`` are skipped)."""
    share = darkness / n
    for m in range(n):
        k = row_of[touched[m]]
        if 0 <= k < out.shape[0]:
            out[k, _SD] += share


@numba.njit(cache=True)
def _add_rim_shadow(reg, unit, row_of, valid, rel_dark, offset, out, pi, pj, near,
                    ring_region, ring_unit):  # pragma: no cover - compiled
    """Add to each unit's summed darkness that of the pixels just outside it.

    A blurred edge leaves part of a shadow below the segmentation threshold, in the
    pixels around the region; a small image loses a large share of its shadow there.
    The rim is two pixels wide: an edge blurred by a Gaussian of standard deviation
    1.2 view pixels leaves 7 % of the shadow of an opaque disc of radius 1.3 px beyond a
    one-pixel rim, 2 % beyond two (0.2 % either way at 0.6 px). Every valid pixel
    outside all regions whose 8 neighbours touch exactly one region (the first ring)
    gives that region its relative darkness
    (of either sign, so that noise does not bias it), shared equally between the parts
    of the region it touches when the region was split; pixels between two regions are
    left out. A pixel of the second ring (outside all regions and the first ring) whose
    8 neighbours include first-ring pixels of exactly one region and none between two
    regions gives its darkness likewise, shared between the parts its first-ring
    neighbours touched alone. Darkness is counted against the background level itself,
    ``(rel_dark - offset) / (1 - offset)`` with ``offset`` the background's median
    ``rel_dark``. ``pi, pj``: the region pixels in raster order; ``near``
    (all False), ``ring_region`` (all -1) and ``ring_unit`` (all 0) are work arrays of
    the view's shape, left as they were found.
    """
    h, w = unit.shape
    touched = np.empty(9, dtype=np.int64)
    # Mark the pixels within two pixels of a region first: regions are sparse, and only
    # those pixels need their 8 neighbours read. Raster order (and so every sum) is kept.
    # Each row's marked pixels lie within columns [near_lo, near_hi] (empty: lo > hi).
    near_lo = np.full(h, w, dtype=np.int64)
    near_hi = np.full(h, -1, dtype=np.int64)
    _mark_runs(pi, pj, near, True, near_lo, near_hi)
    # first ring: ring_region holds the region touched (-2: several), ring_unit the unit
    # + 1 when the pixel touched one unit alone (0 otherwise)
    for i in range(h):
        for j in range(near_lo[i], near_hi[i] + 1):
            if not near[i, j] or reg[i, j] >= 0:
                continue
            region = -1
            several = False
            n_touched = 0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    ii = i + di
                    jj = j + dj
                    if not (0 <= ii < h and 0 <= jj < w) or reg[ii, jj] < 0:
                        continue
                    if region < 0:
                        region = reg[ii, jj]
                    elif reg[ii, jj] != region:
                        several = True
                    n_touched = _add_unique(touched, n_touched, unit[ii, jj])
            if region < 0:
                continue
            ring_region[i, j] = -2 if several else region
            if several or not valid[i, j]:
                continue
            if n_touched == 1:
                ring_unit[i, j] = touched[0] + 1
            _share_shadow(out, row_of, touched, n_touched,
                          (rel_dark[i, j] - offset) / (1.0 - offset))
    # second ring
    for i in range(h):
        for j in range(near_lo[i], near_hi[i] + 1):
            if not near[i, j] or reg[i, j] >= 0 or ring_region[i, j] != -1 or not valid[i, j]:
                continue
            region = -1
            several = False
            n_touched = 0
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    ii = i + di
                    jj = j + dj
                    if not (0 <= ii < h and 0 <= jj < w) or ring_region[ii, jj] == -1:
                        continue
                    rr = ring_region[ii, jj]
                    if rr == -2 or (region >= 0 and rr != region):
                        several = True
                    region = rr
                    if ring_unit[ii, jj] > 0:
                        n_touched = _add_unique(touched, n_touched, ring_unit[ii, jj] - 1)
            if region < 0 or several or n_touched == 0:
                continue
            _share_shadow(out, row_of, touched, n_touched,
                          (rel_dark[i, j] - offset) / (1.0 - offset))
    for i in range(h):
        for j in range(near_lo[i], near_hi[i] + 1):
            if near[i, j]:
                near[i, j] = False
                ring_region[i, j] = -1
                ring_unit[i, j] = 0


@numba.njit(cache=True)
def _mark_runs(pi, pj, near, value, lo, hi):  # pragma: no cover - compiled
    """Set ``near`` to ``value`` within two pixels (8-neighbourhood, twice) of the
    pixels ``(pi, pj)`` (raster order), one horizontal run of them at a time; widen each
    row's column span ``[lo, hi]`` to what was set."""
    h, w = near.shape
    n = pi.shape[0]
    p = 0
    while p < n:
        i, j0 = pi[p], pj[p]
        q = p + 1
        while q < n and pi[q] == i and pj[q] == pj[q - 1] + 1:
            q += 1
        c0, c1 = max(j0 - 2, 0), min(pj[q - 1] + 2, w - 1)
        for ii in range(max(i - 2, 0), min(i + 3, h)):
            for jj in range(c0, c1 + 1):
                near[ii, jj] = value
            if c0 < lo[ii]:
                lo[ii] = c0
            if c1 > hi[ii]:
                hi[ii] = c1
        p = q


@numba.njit(cache=True)
def _work_arrays(h, w):  # pragma: no cover - compiled
    """A clean work space for :func:`_segment_one` on views of ``h x w`` samples:
    ``valid, weight, rel_dark`` (filled per view), ``labels`` (0), ``reg, unit, core``
    (-1), ``near`` (False), the foreground pixel list ``pi, pj`` and the union-find
    ``parent``."""
    return (np.empty((h, w), dtype=np.bool_), np.empty((h, w), dtype=np.float32),
            np.empty((h, w), dtype=np.float32), np.zeros((h, w), dtype=np.int32),
            np.full((h, w), -1, dtype=np.int32), np.full((h, w), -1, dtype=np.int32),
            np.full((h, w), -1, dtype=np.int32), np.zeros((h, w), dtype=np.bool_),
            np.empty(h * w, dtype=np.int32), np.empty(h * w, dtype=np.int32),
            np.empty(h * w // 2 + 2, dtype=np.int32))


@numba.njit(parallel=True, cache=True)
def _segment_stack(stack, views, mask, zero_invalid, b, rb, contrast, core_contrast,
                   min_core_ratio, conn8, centroid_clip, out, counts, n_chunks):  # pragma: no cover - compiled
    """Segment the views ``stack[views[k]]``; region sums into ``out[k]``, region counts
    into ``counts[k]``. The views are dealt out to ``n_chunks`` chunks (one per thread),
    each with one work space (:func:`_work_arrays`) for all its views."""
    for c in numba.prange(n_chunks):
        work = _work_arrays(stack.shape[1], stack.shape[2])
        for k in range(c, views.shape[0], n_chunks):
            counts[k] = _segment_one(stack[views[k]], mask, zero_invalid, b, rb, contrast,
                                     core_contrast, min_core_ratio, conn8, centroid_clip,
                                     out[k], work)


# --------------------------------------------------------------------------------------
# array level
def _region_stats(stack, use, mask, zero_invalid, b, rb, contrast, conn8, core_contrast=0.0,
                  min_core_ratio=0.0, centroid_clip=1.0):
    """Per-region sums of every view: ``(stats (M, _N_STATS), view index (M,))``.

    Regions are in view order, and in raster order of their first pixel within a view.
    The kernel writes at most a fixed number of regions per view into its buffer, whose
    size is what segmentation adds to peak memory: the first views (one per thread) are
    segmented with room for ``_INITIAL_CAPACITY`` regions, the rest with room for 1.5
    times the most those held (a power of two, at least ``_INITIAL_CAPACITY``); a view
    that found more is segmented again with room for all of its regions.
    """
    views = np.flatnonzero(use)
    args = (mask, zero_invalid, b, rb, contrast, core_contrast, min_core_ratio, conn8,
            centroid_clip)
    probe = _n_chunks(len(views))
    first, first_counts = _segment_batch(stack, views[:probe], _INITIAL_CAPACITY, args)
    wanted = math.ceil(1.5 * int(first_counts.max(initial=0)))
    capacity = max(_INITIAL_CAPACITY, 1 << (wanted - 1).bit_length())   # a power of two
    rest, rest_counts = _segment_batch(stack, views[probe:], capacity, args)
    counts = np.concatenate([first_counts, rest_counts])
    return np.concatenate([first, rest]), np.repeat(views, counts)


def _segment_batch(stack, views, capacity, args):
    """Region sums ``(M, _N_STATS)`` of the views ``stack[views]`` in order, and the
    number of regions of each view, with room for ``capacity`` regions per view and a
    second pass for the views that found more."""
    counts = np.zeros(len(views), dtype=np.int64)
    out = np.empty((len(views), capacity, _N_STATS), dtype=np.float64)
    if len(views):
        _segment_stack(stack, views, *args, out, counts, _n_chunks(len(views)))
    full = np.flatnonzero(counts > capacity)
    if len(full):
        more = np.empty((len(full), int(counts[full].max()), _N_STATS), dtype=np.float64)
        _segment_stack(stack, views[full], *args, more, counts[full].copy(),
                       _n_chunks(len(full)))
    rows = []
    for k in range(len(views)):
        if counts[k] > capacity:
            rows.append(more[np.searchsorted(full, k), :counts[k]])
        else:
            rows.append(out[k, :counts[k]])
    if not rows:
        return np.empty((0, _N_STATS), dtype=np.float64), counts
    return np.concatenate(rows), counts


def _n_chunks(n_views: int) -> int:
    """Chunks of views for :func:`_segment_stack`: one per numba thread."""
    return max(1, min(int(n_views), numba.get_num_threads()))


def _background_blocks(window) -> tuple[int, int]:
    """Block size ``b`` (px) and half-width ``rb`` (blocks) approximating a box window."""
    if not (isinstance(window, (int, np.integer)) and window >= 3):
        raise SettingsError(f"window must be an integer of at least 3 px; got {window!r}")
    b = max(1, int(window) // 8)
    rb = max(1, int(round((window / b - 1) / 2)))
    return b, rb


def _check_range(name, value) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        raise SettingsError(f"{name} must be a pair (min, max); got {value!r}") from None
    if not (lo >= 0 and hi >= lo):
        raise SettingsError(f"{name} must satisfy 0 <= min <= max; got {value!r}")
    return lo, hi


def _region_properties(stats: np.ndarray) -> dict[str, np.ndarray]:
    """Centroid and shape of regions from accumulated sums ``stats`` (n, _N_STATS)."""
    n = stats[:, _N]
    sw = stats[:, _SW]
    s = stats[:, _S0] + stats[:, _SWS] / sw
    t = stats[:, _T0] + stats[:, _SWT] / sw
    ms = stats[:, _SS] / n
    mt = stats[:, _ST] / n
    css = np.maximum(stats[:, _SSS] / n - ms * ms, 0.0)
    ctt = np.maximum(stats[:, _STT] / n - mt * mt, 0.0)
    cst = stats[:, _SST] / n - ms * mt
    half_tr = 0.5 * (css + ctt)
    root = np.sqrt((0.5 * (css - ctt)) ** 2 + cst * cst)
    l1 = half_tr + root
    l2 = np.maximum(half_tr - root, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        ecc = np.where(l1 > 0, np.sqrt(np.clip(1.0 - l2 / l1, 0.0, 1.0)), 0.0)
    return {
        "s": s, "t": t, "area": n.astype(np.int64),
        "diameter_px": np.sqrt(4.0 * n / math.pi),
        "major_axis_px": 4.0 * np.sqrt(l1), "minor_axis_px": 4.0 * np.sqrt(l2),
        "orientation": 0.5 * np.arctan2(2.0 * cst, css - ctt),
        "eccentricity": ecc, "darkness": stats[:, _DARK], "dark_area": stats[:, _SD],
    }


def _empty_detections() -> pd.DataFrame:
    dtypes = {T_COLUMN: np.int64, "area": np.int64}
    return pd.DataFrame({c: np.zeros(0, dtype=dtypes.get(c, np.float64))
                         for c in DETECTION_COLUMNS})


def segment_array(data: np.ndarray, u, v, *, view_mask=None, spatial_mask=None,
                  frame: int = 0, window: int = 31, contrast: float = 0.15,
                  area_range=(2, np.inf), max_eccentricity: float = 1.0,
                  exclude_edge: bool = True, zero_invalid: bool = False,
                  connectivity: int = 2, core_contrast: float | None = None,
                  min_core_ratio: float = 0.0, centroid_clip: float = 1.0) -> pd.DataFrame:
    """Segment dark particles in every view of a 4-D light-field array.

    Parameters
    ----------
    data : (n_v, n_u, n_t, n_s) float ndarray
        Light field ``L[v, u, t, s]`` (views are ``(n_t, n_s)`` images), bright background,
        dark particles. Non-finite values are treated as masked.
    u, v : (n_u,), (n_v,) float ndarray
        Angular coordinates of the view columns and rows (copied into the table).
    view_mask : (n_v, n_u) bool ndarray, optional
        Views to segment (default: all).
    spatial_mask : (n_t, n_s) bool ndarray, optional
        Samples that carry data in every view (default: all). Masked samples are neither
        background nor foreground.
    frame : int
        Frame index written to the ``frame`` column.
    window : int
        Side of the square window, in view pixels, over which the local background is
        averaged (at least 3; a few particle diameters is a good choice).
    contrast : float
        Relative margin: a pixel is foreground when darker than ``(1 - contrast)`` times
        the local background (0 < contrast < 1).
    area_range : (float, float)
        Accepted region area, pixels, inclusive.
    max_eccentricity : float
        Regions with a larger eccentricity (0 = circle, 1 = line) are dropped.
    exclude_edge : bool
        Drop regions that touch the view border or a masked sample (their centroids are
        biased).
    zero_invalid : bool
        Treat values exactly 0 as masked (a flat-fielded light field marks vignetted
        samples with 0).
    connectivity : {1, 2}
        Pixel connectivity of a region: 1 = 4-neighbours, 2 = 8-neighbours.
    core_contrast : float, optional
        Split merged images: a region holding two or more cores (connected pixels whose
        relative darkness exceeds ``core_contrast`` times the region's peak relative
        darkness, the peak capped at 1; ``contrast < core_contrast < 1``) is the merged
        image of several particles and is replaced by one detection
        per core, made of the region's pixels nearest that core (path length within the
        region). Such parts keep the region's soft-edged centroid weights; the area range
        applies to the whole region and the eccentricity limit not at all. Adds the
        column ``whole`` (False for parts). Default: no splitting.
    min_core_ratio : float
        With ``core_contrast``: a core of a single pixel beside a core more than
        ``1 / min_core_ratio`` pixels large in the same region is not counted as a
        particle of its own (in [0, 1); 0 counts every core).
    centroid_clip : float
        Cap on a pixel's centroid weight, as a fraction of the largest weight in its
        region, in (0, 1]; 1 (default) leaves the weights uncapped. Only a region with a
        plateau above the cap (a pixel above it whose four neighbours are too) is
        capped, and the parts of a region shared out between its cores keep their
        weights. A capped image weighs its dark plateau evenly, so a bright spot on it
        (a specular glint, light let through the body) no longer pulls the centroid away
        from itself; the soft edge, which carries the position, keeps its grey levels. A
        small image has no plateau: capping its peak, which is its edge, would only
        pull the centroid towards the pixel grid (1.7 times the centroid scatter of a
        blurred 3-pixel disc at a cap of 0.7 against none).

    Returns
    -------
    pandas.DataFrame
        One row per detection, columns :data:`DETECTION_COLUMNS` (and ``whole`` with
        ``core_contrast``):
        ``frame`` (int); ``u, v`` view coordinates; ``s, t`` darkness-weighted centroid (see
        Notes), view pixels (column, row; pixel centres at integers); ``area`` pixels (int);
        ``diameter_px`` equivalent-circle diameter; ``major_axis_px, minor_axis_px``
        lengths of the ellipse with the region's second moments (as
        ``skimage.measure.regionprops``); ``orientation`` angle of the major axis from
        the +s axis towards +t, radians in [-pi/2, pi/2]; ``eccentricity`` in [0, 1];
        ``darkness`` peak relative darkness ``max (background - value) / background``;
        ``dark_area`` the summed relative darkness of the region and of the two-pixel rim
        around it (pixels near no other region), counted against the view's bright level
        (``(d - o) / (1 - o)`` with ``o`` the median relative darkness of the view's
        background: the box-mean background lies a little below it where images crowd),
        pixels: the area of an opaque object of the same shadow, little changed by defocus
        blur (unlike ``area``, which grows with blur and with a lower ``contrast``), also
        for images of a few pixels.
        Rows are ordered by view (v, then u) and by first pixel in raster order.

    Notes
    -----
    The background is a two-pass box mean: a plain local mean over valid samples, then
    the local mean over samples not already darker than ``(1 - contrast)`` times the
    first estimate, so that dense dark particles do not pull the background down. Both
    means are taken on blocks of ``b = max(1, window // 8)`` pixels (window rounded to a
    whole odd number of blocks) and interpolated bilinearly between block centres, which
    keeps the cost at a few operations per pixel.

    The centroid weight of a foreground pixel is its darkness beyond the threshold,
    ``(1 - contrast) * background - value``. It falls continuously to zero at the region
    border, so the sub-pixel position of a blob relative to the pixel grid does not
    bias the centroid through pixels entering or leaving the region (with the plain
    darkness ``background - value`` the weight jumps at the border; on Gaussian blobs
    of sigma 1.2 px that doubles the centroid error, 0.07 px instead of 0.01 px
    without noise). The shape moments are unweighted (pixel count), as in
    scikit-image.
    """
    data = np.asarray(data)
    if data.ndim != 4:
        raise SettingsError(f"data must be 4-D (v, u, t, s); got shape {data.shape}")
    if not np.issubdtype(data.dtype, np.floating):
        data = data.astype(np.float32)
    n_v, n_u, n_t, n_s = data.shape
    u = np.asarray(u, dtype=float)
    v = np.asarray(v, dtype=float)
    if u.shape != (n_u,) or v.shape != (n_v,):
        raise SettingsError(f"u and v must have {n_u} and {n_v} entries to match data "
                         f"{data.shape}; got {u.shape} and {v.shape}")
    use = (np.ones((n_v, n_u), bool) if view_mask is None
           else np.asarray(view_mask, dtype=bool))
    if use.shape != (n_v, n_u):
        raise SettingsError(f"view_mask must be ({n_v}, {n_u}); got {use.shape}")
    smask = (np.ones((n_t, n_s), bool) if spatial_mask is None
             else np.ascontiguousarray(spatial_mask, dtype=bool))
    if smask.shape != (n_t, n_s):
        raise SettingsError(f"spatial_mask must be ({n_t}, {n_s}); got {smask.shape}")
    b, rb = _background_blocks(window)
    if not 0.0 < contrast < 1.0:
        raise SettingsError(f"contrast must be between 0 and 1; got {contrast!r}")
    a_lo, a_hi = _check_range("area_range", area_range)
    if core_contrast is not None and not contrast < core_contrast < 1.0:
        raise SettingsError(f"core_contrast must be between contrast ({contrast}) and 1; "
                            f"got {core_contrast!r}")
    if connectivity not in (1, 2):
        raise SettingsError(f"connectivity must be 1 or 2; got {connectivity!r}")
    if not 0.0 <= min_core_ratio < 1.0:
        raise SettingsError(f"min_core_ratio must be in [0, 1); got {min_core_ratio!r}")
    if not 0.0 < centroid_clip <= 1.0:
        raise SettingsError(f"centroid_clip must be in (0, 1]; got {centroid_clip!r}")

    stack = np.ascontiguousarray(data).reshape(n_v * n_u, n_t, n_s)
    stats, view_idx = _region_stats(stack, np.ascontiguousarray(use.ravel()), smask,
                                    bool(zero_invalid), b, rb, float(contrast),
                                    connectivity == 2,
                                    0.0 if core_contrast is None else float(core_contrast),
                                    float(min_core_ratio), float(centroid_clip))
    props = _region_properties(stats)
    part = stats[:, _PART] > 0.0
    keep = (stats[:, _PARENT_N] >= a_lo) & (stats[:, _PARENT_N] <= a_hi)
    keep &= part | (props["eccentricity"] <= max_eccentricity)
    if exclude_edge:
        keep &= stats[:, _EDGE] == 0.0
    iv, iu = np.divmod(view_idx[keep], n_u)
    table = pd.DataFrame({T_COLUMN: np.full(int(keep.sum()), int(frame), dtype=np.int64),
                          "u": u[iu], "v": v[iv],
                          **{k: props[k][keep] for k in DETECTION_COLUMNS[3:]}})
    if core_contrast is not None:
        table["whole"] = ~part[keep]
    if len(table) == 0:
        warnings.warn("no particles found in any view; returning an empty detections table",
                      NoParticlesWarning, stacklevel=2)
        empty = _empty_detections()
        return empty if core_contrast is None else empty.assign(whole=np.zeros(0, bool))
    return table.reset_index(drop=True)


def segment_view(image: np.ndarray, *, mask=None, u: float = 0.0, v: float = 0.0,
                 frame: int = 0, window: int = 31, contrast: float = 0.15,
                 area_range=(2, np.inf), max_eccentricity: float = 1.0,
                 exclude_edge: bool = True, zero_invalid: bool = False,
                 connectivity: int = 2, core_contrast: float | None = None,
                 min_core_ratio: float = 0.0, centroid_clip: float = 1.0) -> pd.DataFrame:
    """Segment dark particles in one perspective view.

    Parameters
    ----------
    image : (n_t, n_s) float ndarray
        The view, rows ``t``, columns ``s``; bright background, dark particles.
    mask : (n_t, n_s) bool ndarray, optional
        True where the view carries data (default: everywhere).
    u, v : float
        View coordinates written to the ``u`` and ``v`` columns.
    frame, window, contrast, area_range, max_eccentricity, exclude_edge, zero_invalid, connectivity, core_contrast, min_core_ratio
        As in :func:`segment_array`.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`DETECTION_COLUMNS` (and ``whole`` with ``core_contrast``), see
        :func:`segment_array`.
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise SettingsError(f"image must be 2-D (t, s); got shape {image.shape}")
    return segment_array(image[None, None], [u], [v], spatial_mask=mask, frame=frame,
                         window=window, contrast=contrast, area_range=area_range,
                         max_eccentricity=max_eccentricity, exclude_edge=exclude_edge,
                         zero_invalid=zero_invalid, connectivity=connectivity,
                         core_contrast=core_contrast, min_core_ratio=min_core_ratio,
                         centroid_clip=centroid_clip)


def segment_views(lf, *, frame: int = 0, views=None, window: int = 31,
                  contrast: float = 0.15, area_range=(2, np.inf),
                  max_eccentricity: float = 1.0, exclude_edge: bool = True,
                  connectivity: int = 2, core_contrast: float | None = None,
                  min_core_ratio: float = 0.0, centroid_clip: float = 1.0) -> pd.DataFrame:
    """Segment dark particles in every valid view of a light field.

    Parameters
    ----------
    lf : LightField
        Decoded light field (``data`` ``(n_v, n_u, n_t, n_s)``, ``u``, ``v``,
        ``view_mask``, ``spatial_mask``, ``flat_fielded``).
    frame : int
        Frame index written to the ``frame`` column.
    views : (n_v, n_u) bool ndarray, optional
        Views to segment; default ``lf.view_mask``.
    window, contrast, area_range, max_eccentricity, exclude_edge, connectivity, core_contrast, min_core_ratio
        As in :func:`segment_array`.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`DETECTION_COLUMNS` (and ``whole`` with ``core_contrast``), see
        :func:`segment_array`. Samples outside
        ``lf.spatial_mask`` and, for a flat-fielded light field, samples set to 0
        (vignetted) are masked.
    """
    return segment_array(lf.data, lf.u, lf.v,
                         view_mask=lf.view_mask if views is None else views,
                         spatial_mask=lf.spatial_mask, frame=frame, window=window,
                         contrast=contrast, area_range=area_range,
                         max_eccentricity=max_eccentricity, exclude_edge=exclude_edge,
                         zero_invalid=bool(getattr(lf, "flat_fielded", False)),
                         connectivity=connectivity, core_contrast=core_contrast,
                         min_core_ratio=min_core_ratio, centroid_clip=centroid_clip)
