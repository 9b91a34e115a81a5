"""Compile the numba kernels of calibrating and locating ahead of need, in a second process.

Every kernel of :mod:`plenoptrack.lightfield` and :mod:`plenoptrack.locate` is compiled
with ``cache=True``: numba writes the machine code to ``__pycache__`` beside the module
(or to ``NUMBA_CACHE_DIR``) the first time a signature is compiled, and later processes
load it in milliseconds. After a fresh installation that cache is empty, and the first
``calibrate`` or ``locate`` spends most of its time compiling. This module lists the exact
signatures those two steps use (:data:`KERNELS`), so that they can be compiled before the
data they will run on exist: ``plenoptrack demo`` compiles them in a child process on the
second core while it simulates its scene, and the main process then loads them from the
cache.

The package also ships the demo's kernels compiled for the generic x86-64 processor
(:mod:`plenoptrack._kernel_mode`); a command-line run that loads them finds every index
present and starts no child here. This module serves runs that compile for this processor.

Set ``PLENOPTRACK_PRECOMPILE=0`` to switch the child process off.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

from numba import types as nt

__all__ = ["KERNELS", "STEPS", "HELPERS", "kernels_for", "missing", "precompile", "start_background",
           "finish_background"]


def _a(dtype, ndim: int, *, layout: str = "C", readonly: bool = False) -> nt.Array:
    return nt.Array(dtype, ndim, layout, readonly=readonly)


_f8, _f4, _i8, _u2, _b1 = nt.float64, nt.float32, nt.int64, nt.uint16, nt.boolean
_F1, _F2, _F3 = _a(_f8, 1), _a(_f8, 2), _a(_f8, 3)
_I1, _I2 = _a(_i8, 1), _a(_i8, 2)
_B1 = _a(_b1, 1)
# read-only arrays: the DLFC's monomial tables and coefficients
_I1r, _I2r, _F1r, _F2r, _F3r = (_a(_i8, 1, readonly=True), _a(_i8, 2, readonly=True),
                                _a(_f8, 1, readonly=True), _a(_f8, 2, readonly=True),
                                _a(_f8, 3, readonly=True))

KERNELS: dict[str, tuple[str, str, tuple]] = {
    # name: (module, function, argument types)
    "grid": ("plenoptrack.lightfield.grid", "_symmetry_centres",
             (_a(_u2, 2), _F2, _a(_i8, 3), _F2, _I1, _f8, _i8, _i8)),
    "decode": ("plenoptrack.lightfield.decode", "_gather",
               (_a(_u2, 2), _F3, _I2, _F2, _i8, _a(_b1, 2), _i8, _i8, _a(_f4, 4))),
    "segment": ("plenoptrack.locate.segment", "_segment_stack",
                (_a(_f4, 3), _I1, _a(_b1, 2), _b1, _i8, _i8, _f8, _f8, _f8, _b1, _f8, _F3,
                 _I1, _i8)),
    "dlfc_eval": ("plenoptrack.locate.dlfc", "_eval_kernel", (_F2, _I1r, _I1r, _F2r, _b1)),
    "dlfc_eval_serial": ("plenoptrack.locate.dlfc", "_eval_serial",
                         (_F2, _I1r, _I1r, _F2r, _b1)),
    "dlfc_design": ("plenoptrack.locate.dlfc", "_design_kernel", (_F2, _I1r, _I1r)),
    "dlfc_views": ("plenoptrack.locate.dlfc", "_views_kernel",
                   (_F2, _F2, _I2r, _F3r, _F1r, _F1r, _b1)),
    "kmeans_lloyd": ("plenoptrack.locate.cluster", "_lloyd", (_F2, _F2, _i8)),
    "kmeans_topup": ("plenoptrack.locate.cluster", "_kmeanspp_topup", (_F2, _F2, _i8, _F1)),
    "kmeans_evaluate": ("plenoptrack.locate.cluster", "_evaluate",
                        (_F2, _F2, _I1, _F2, _I1, _F1, _i8, _f8, _f8, _i8, _f8, _f8)),
    "robust_thresholds": ("plenoptrack.locate.triangulate", "_robust_thresholds",
                          (_F1, _I1, _I1, _B1, _I1, _f8, _f8)),
    "normal": ("plenoptrack.locate.triangulate", "_normal_kernel",
               (_F2, _I1, _F3, _F3, _F1, _F2, _I2r, _F3r, _F1r, _F1r)),
    "lm": ("plenoptrack.locate.triangulate", "_lm_kernel",
           (_F2, _I1, _F3, _F3, _F1, _F2, _I2r, _F3r, _F1r, _F1r, _i8, _f8, _f8, _B1)),
    "moments": ("plenoptrack.locate.triangulate", "_moments_kernel",
                (_F2, _F2, _I1, _B1, _I1, _i8)),
    "residual": ("plenoptrack.locate.triangulate", "_residual_kernel",
                 (_F2, _I1, _I1, _F2, _F2, _I1, _F2, _I2r, _F3r, _F1r, _F1r)),
    "nearby_bucket": ("plenoptrack.locate._nearby", "_bucket", (_I1, _a(_f8, 1, layout="A"), _i8)),
    "nearby_scan": ("plenoptrack.locate._nearby", "_scan",
                    (_F1, _F1, _I1, _F1, _I1, _F1, _F1, _f8, _f8, _i8)),
    "first_untaken": ("plenoptrack.locate._assign", "_first_untaken", (_I1, _I1, _i8)),
    "absorb": ("plenoptrack.locate._assign", "_absorb", (_I1, _I1, _I1, _I1)),
    "refine_gather": ("plenoptrack.locate.refine", "_gather_patches",
                      (_a(_f4, 4), _I2, _I1, _I1, _i8)),
    "refine_masks": ("plenoptrack.locate.refine", "_patch_masks",
                     (_F2, _i8, _F3, _F2, _F3, _F1, _f8, _F2)),
    "refine_pixels": ("plenoptrack.locate.refine", "_fit_pixels",
                      (_F2, _F3, _F3, _a(_b1, 3))),
    "refine_lm": ("plenoptrack.locate.refine", "_levenberg_marquardt",
                  (_I1, _F1, _F1, _F1, _F1, _F2, _I2r, _F3r, _F1r, _F1r, _F2, _F2, _F2, _F2,
                   _f8, _i8, _f8, _F2, _F2, _b1)),
}
"""Every kernel signature that calibrating and locating a frame compile, by short name.
Pinned by ``tests/test_precompile.py`` against the signatures a real run compiles."""

STEPS: dict[str, tuple[str, ...]] = {
    "calibrate": ("grid", "decode", "segment", "dlfc_eval", "dlfc_design",
                  # the dots' position errors through the fitted DLFC (its model error)
                  "robust_thresholds", "normal", "lm", "moments", "residual"),
    "locate": ("decode", "segment", "dlfc_eval", "dlfc_eval_serial", "dlfc_views", "kmeans_lloyd",
               "kmeans_topup", "kmeans_evaluate", "robust_thresholds", "normal", "lm", "moments",
               "residual", "nearby_bucket", "nearby_scan", "first_untaken", "absorb",
               "refine_gather", "refine_masks", "refine_pixels", "refine_lm"),
}
"""The kernels each step needs (``calibrate``: lenslet grid and DLFC fit from a white image
and dot cards; ``locate``: decoding and the perspective-shift locator)."""


HELPERS: frozenset[str] = frozenset({
    "plenoptrack.lightfield.decode._corner", "plenoptrack.lightfield.grid._symmetry_step",
    "plenoptrack.lightfield.grid._bilinear", "plenoptrack.lightfield.grid._reflected_step",
    "plenoptrack.locate.cluster._centre_grid", "plenoptrack.locate.cluster._nearest_two",
    "plenoptrack.locate.cluster._local_max_shift",
    "plenoptrack.locate.segment._find", "plenoptrack.locate.segment._union",
    "plenoptrack.locate.segment._block_mean", "plenoptrack.locate.segment._fill_nan",
    "plenoptrack.locate.segment._interp_axis", "plenoptrack.locate.segment._grid_row",
    "plenoptrack.locate.segment._at", "plenoptrack.locate.segment._segment_one",
    "plenoptrack.locate.segment._centroid_caps",
    "plenoptrack.locate.segment._label_pixel", "plenoptrack.locate.segment._label_cores",
    "plenoptrack.locate.segment._split_by_cores", "plenoptrack.locate.segment._add_rim_shadow",
    "plenoptrack.locate.segment._reset", "plenoptrack.locate.segment._work_arrays",
    "plenoptrack.locate.segment._background_offset", "plenoptrack.locate.segment._mark_runs",
    "plenoptrack.locate._order._before",
    "plenoptrack.locate._order.median", "plenoptrack.locate._order.stable_argsort",
    "plenoptrack.locate.dlfc._coefficients_one",
    "plenoptrack.locate.triangulate._normal_one", "plenoptrack.locate.triangulate._solve3",
    "plenoptrack.locate.refine._half_erfc", "plenoptrack.locate.refine._box",
    "plenoptrack.locate.refine._edge_argument",
    "plenoptrack.locate.refine._normal_cdf",
    "plenoptrack.locate.refine._bivariate_normal_cdf",
    "plenoptrack.locate.refine._overlapping_edges",
    "plenoptrack.locate.refine._model_normal_equations",
    "plenoptrack.locate.refine._pixel_normal_equations",
    "plenoptrack.locate.refine._union_rows",
    "plenoptrack.locate.refine._step_tolerance",
    "plenoptrack.locate.refine._view_robust_sigma",
    "plenoptrack.locate.dlfc._eval_block",
})
"""Jitted functions called only from other kernels: compiled into their callers' cache
entries, never needed on their own."""


def kernels_for(steps) -> list[str]:
    """Short names of the kernels the given steps need, each once, in a stable order.

    Parameters
    ----------
    steps : iterable of str
        Keys of :data:`STEPS`.

    Returns
    -------
    list of str
        Keys of :data:`KERNELS`.
    """
    names: list[str] = []
    for step in steps:
        if step not in STEPS:
            raise ValueError(f"step must be one of {sorted(STEPS)}; got {step!r}")
        names.extend(k for k in STEPS[step] if k not in names)
    return names


def _dispatcher(name: str):
    module, func, _ = KERNELS[name]
    return getattr(importlib.import_module(module), func)


def _index_path(dispatcher) -> Path | None:
    """The cache index file of a dispatcher, or None if it has no disk cache."""
    cache = getattr(dispatcher, "_cache", None)
    cache_file = getattr(cache, "_cache_file", None)
    path = getattr(cache_file, "_index_path", None)
    return None if path is None else Path(path)


def missing(names) -> list[str]:
    """Kernels among ``names`` that have no cache index on disk yet.

    A present index may still hold another signature or a stale entry (numba then
    compiles as usual); a missing one means the kernel has never been compiled here.
    """
    out = []
    for name in names:
        path = _index_path(_dispatcher(name))
        if path is None or not path.exists():
            out.append(name)
    return out


def precompile(names) -> None:
    """Compile (or load from the cache) the kernels ``names`` in this process.

    Parameters
    ----------
    names : iterable of str
        Keys of :data:`KERNELS`.
    """
    for name in names:
        _dispatcher(name).compile(KERNELS[name][2])


def start_background(steps) -> subprocess.Popen | None:
    """Start a child process that compiles the kernels of ``steps`` not yet cached.

    Parameters
    ----------
    steps : iterable of str
        Keys of :data:`STEPS`.

    Returns
    -------
    subprocess.Popen or None
        The child (wait for it before the steps run, so they load its results instead of
        compiling the same kernels again), or None when every kernel has a cache index
        already or ``PLENOPTRACK_PRECOMPILE=0`` is set.
    """
    if os.environ.get("PLENOPTRACK_PRECOMPILE", "1") == "0":
        return None
    todo = missing(kernels_for(steps))
    if not todo:
        return None
    return subprocess.Popen([sys.executable, "-m", "plenoptrack._precompile", *todo],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def finish_background(child: subprocess.Popen | None, steps) -> None:
    """Help a child from :func:`start_background` finish, then wait for it.

    While the child is still running, this process compiles the kernels that are still
    missing from the cache, starting at the end of the child's list, so that the two
    processes meet in the middle (at most the kernel both reach at once is compiled
    twice). When it returns, every kernel of ``steps`` is cached or compiled here.

    Parameters
    ----------
    child : subprocess.Popen or None
        The child process (None: nothing to do).
    steps : iterable of str
        The same steps the child was started with.
    """
    if child is None:
        return
    for name in reversed(kernels_for(steps)):
        if child.poll() is not None:
            break
        if missing([name]):
            precompile([name])
    child.wait()


if __name__ == "__main__":  # pragma: no cover - run as the child process
    precompile(sys.argv[1:])
