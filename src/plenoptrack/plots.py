"""Figures of light fields, focal stacks, located particles and their errors.

Every function builds a new :class:`matplotlib.figure.Figure` with the object API (no
pyplot state, so it works headless and in threads) and returns it; nothing is shown.
Save it with ``fig.savefig("name.png")``, or hand it to pyplot to show it in a window.
Axes are labelled with their units: object space in mm (``docs/conventions.md``), views
in view pixels ``(s, t)``, angular coordinates ``(u, v)`` in sensor pixels.

Examples
--------
>>> import numpy as np
>>> import pandas as pd
>>> from plenoptrack.plots import plot_particles_3d
>>> rng = np.random.default_rng(0)
>>> truth = pd.DataFrame(rng.uniform(-5, 5, (10, 3)), columns=["x", "y", "z"])
>>> fig = plot_particles_3d(truth + 0.05, truth=truth)
>>> [ax.get_xlabel() for ax in fig.axes[:3]]
['x (mm)', 'z (mm)', 'x (mm)']
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from ._columns import POS_COLUMNS
from .errors import SettingsError
from .evaluate import match_particles
from .lightfield.decode import LightField
from .lightfield.refocus import best_focus_depth, sharpness
from .lightfield.views import view_mosaic

__all__ = ["plot_view_mosaic", "plot_view", "plot_particles_3d", "plot_errors_vs_depth",
           "plot_focal_stack_sharpness", "plot_fragment_field", "plot_tracks", "outline_points",
           "plot_study_bins", "plot_study"]

_U_LABEL = "u (sensor px from microlens-image centre)"
_V_LABEL = "v (sensor px from microlens-image centre)"


# --------------------------------------------------------------------------------------
# checks


def _check_lf(lf) -> LightField:
    if not isinstance(lf, LightField):
        raise SettingsError("lf must be a LightField (see plenoptrack.lightfield.decode); "
                         f"got {type(lf).__name__}")
    return lf


def _check_table(df, name: str, columns) -> pd.DataFrame:
    if not isinstance(df, pd.DataFrame):
        raise SettingsError(f"{name} must be a pandas DataFrame with columns {list(columns)}; "
                         f"got {type(df).__name__}")
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise SettingsError(f"{name} has no column(s) {missing}; expected {list(columns)}")
    return df


def _display_limits(image: np.ndarray, percentiles=(0.5, 99.5)) -> tuple[float, float]:
    finite = image[np.isfinite(image) & (image != 0)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, percentiles)
    return (float(lo), float(hi)) if hi > lo else (float(lo), float(lo) + 1.0)


# --------------------------------------------------------------------------------------
# light fields


def plot_view_mosaic(lf: LightField, *, views: str | np.ndarray = "valid", gap: int = 2,
                     percentiles: tuple[float, float] = (0.5, 99.5),
                     figsize: tuple[float, float] = (9.0, 6.5)) -> Figure:
    """All perspective views of a light field tiled in one image.

    Parameters
    ----------
    lf : LightField
        Decoded light field ``L[v, u, t, s]``.
    views : {"valid", "all"} or (n_v, n_u) bool ndarray
        Views to show (see :func:`plenoptrack.lightfield.view_mosaic`); the others are
        left black.
    gap : int
        Black pixels between tiles.
    percentiles : (float, float)
        Grey-scale limits as percentiles of the shown (non-zero) samples.
    figsize : (float, float)
        Figure size, inches.

    Returns
    -------
    Figure
        One axes; tile ``(iv, iu)`` shows view ``(lf.u[iu], lf.v[iv])``, ``u`` growing to
        the right and ``v`` downwards as on the sensor. Ticks mark the tile centres and
        are labelled with ``u`` and ``v``.
    """
    lf = _check_lf(lf)
    gap = int(gap)
    mosaic = view_mosaic(lf, views=views, gap=gap, fill=0.0)
    vmin, vmax = _display_limits(mosaic, percentiles)
    fig = Figure(figsize=figsize, layout="constrained")
    ax = fig.add_subplot()
    ax.imshow(mosaic, cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
    step = max(1, int(np.ceil(lf.n_u / 8)))
    iu = np.arange(0, lf.n_u)
    iv = np.arange(0, lf.n_v)
    # label every `step`-th view but keep the central one (u = v = 0) labelled
    cu, cv = int(np.argmin(np.abs(lf.u))), int(np.argmin(np.abs(lf.v)))
    iu, iv = iu[(iu - cu) % step == 0], iv[(iv - cv) % step == 0]
    ax.set_xticks(iu * (lf.n_s + gap) + (lf.n_s - 1) / 2, [f"{u:g}" for u in lf.u[iu]])
    ax.set_yticks(iv * (lf.n_t + gap) + (lf.n_t - 1) / 2, [f"{v:g}" for v in lf.v[iv]])
    ax.set_xlabel(_U_LABEL)
    ax.set_ylabel(_V_LABEL)
    title = f"{lf.n_v} x {lf.n_u} perspective views, {lf.n_t} x {lf.n_s} samples each"
    if isinstance(views, str) and views == "valid":
        title += f" ({int(np.count_nonzero(lf.view_mask))} valid shown)"
    ax.set_title(title)
    return fig


def plot_view(lf: LightField, u: float, v: float, *, detections: pd.DataFrame | None = None,
              percentiles: tuple[float, float] = (0.5, 99.5),
              figsize: tuple[float, float] = (7.0, 5.0)) -> Figure:
    """One perspective view, optionally with the centroids detected in it.

    Parameters
    ----------
    lf : LightField
        Decoded light field.
    u, v : float
        Angular coordinates of the view, sensor pixels (integers ``-R ... R``).
    detections : DataFrame, optional
        Centroids with columns ``s, t`` (view pixels); when it has ``u`` and ``v``
        columns only the rows of this view are drawn (e.g. the ``detections`` of a
        :class:`~plenoptrack.locate.LocateResult`). With a ``particle`` column,
        centroids assigned to a particle (``particle >= 0``) and unused ones are drawn
        differently.
    percentiles : (float, float)
        Grey-scale limits as percentiles of the view's non-zero samples.
    figsize : (float, float)
        Figure size, inches.

    Returns
    -------
    Figure
        One axes: ``s`` (view px) to the right, ``t`` (view px) downwards; the
        centroids as open circles, with a legend when there are any.
    """
    lf = _check_lf(lf)
    image = lf.view(u, v)
    fig = Figure(figsize=figsize, layout="constrained")
    ax = fig.add_subplot()
    vmin, vmax = _display_limits(image, percentiles)
    im = ax.imshow(image, cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
    fig.colorbar(im, ax=ax, shrink=0.8,
                 label="radiance (fraction of white)" if lf.flat_fielded else "radiance (counts)")
    ax.set_xlabel("s (view px)")
    ax.set_ylabel("t (view px)")
    ax.set_title(f"view (u, v) = ({u:g}, {v:g})")
    if detections is not None:
        det = _check_table(detections, "detections", ("s", "t"))
        if "u" in det.columns and "v" in det.columns:
            det = det[np.isclose(det["u"].to_numpy(float), u)
                      & np.isclose(det["v"].to_numpy(float), v)]
        if "particle" in det.columns:
            used = det["particle"].to_numpy() >= 0
            groups = [(det[used], "tab:green", f"assigned to a particle ({used.sum()})"),
                      (det[~used], "tab:red", f"not used ({(~used).sum()})")]
        else:
            groups = [(det, "tab:red", f"centroids ({len(det)})")]
        for rows, colour, label in groups:
            ax.scatter(rows["s"], rows["t"], s=60, facecolors="none", edgecolors=colour,
                       linewidths=1.2, label=label)
        ax.set_xlim(-0.5, lf.n_s - 0.5)
        ax.set_ylim(lf.n_t - 0.5, -0.5)
        ax.legend(loc="upper right", fontsize="small", framealpha=0.8)
    return fig


def plot_focal_stack_sharpness(stack: np.ndarray, depths_mm, *,
                               center: tuple[float, float] | None = None,
                               half_width: int | None = None,
                               method: Literal["laplacian", "gradient"] = "laplacian",
                               true_depth_mm: float | None = None, n_images: int = 5,
                               figsize: tuple[float, float] = (9.0, 5.5)) -> Figure:
    """A focal stack: a few refocused images and the sharpness against depth.

    Parameters
    ----------
    stack : (n, n_t, n_s) ndarray
        Refocused images (:func:`plenoptrack.lightfield.focal_stack`).
    depths_mm : (n,) array_like
        Depth ``z`` of each image, mm.
    center : (s, t), optional
        Centre of the window, spatial samples, over which sharpness is measured; the
        images are cropped around it and the window is outlined. Requires
        ``half_width``.
    half_width : int, optional
        Half side of the window, samples.
    method : {"laplacian", "gradient"}
        Focus metric, see :func:`plenoptrack.lightfield.sharpness`.
    true_depth_mm : float, optional
        Known depth, mm, drawn as a dashed line.
    n_images : int
        Refocused images shown above the curve (spread evenly over the stack, the one
        nearest the best focus among them), at least 1.
    figsize : (float, float)
        Figure size, inches.

    Returns
    -------
    Figure
        ``n_images`` image axes in the top row (``s``, ``t`` in view px) and one axes
        below: sharpness relative to its maximum against depth (mm), with the best-focus
        depth of :func:`plenoptrack.lightfield.best_focus_depth` as a solid line.
    """
    stack = np.asarray(stack)
    depths = np.asarray(depths_mm, dtype=float)
    if stack.ndim != 3:
        raise SettingsError(f"stack must be 3-D (n, n_t, n_s); got shape {stack.shape}")
    if depths.ndim != 1 or len(depths) != len(stack):
        raise SettingsError(f"depths_mm must have one depth per image ({len(stack)}); "
                         f"got shape {depths.shape}")
    if len(stack) < 2:
        raise SettingsError(f"stack must hold at least 2 images; got {len(stack)}")
    n_images = int(n_images)
    if n_images < 1:
        raise SettingsError(f"n_images must be at least 1; got {n_images}")
    order = np.argsort(depths)
    stack, depths = stack[order], depths[order]
    curve = sharpness(stack, center=center, half_width=half_width, method=method)
    best = best_focus_depth(stack, depths, center=center, half_width=half_width, method=method)
    peak = float(np.max(curve))
    rel = curve / peak if peak > 0 else curve

    picks = np.unique(np.linspace(0, len(depths) - 1, min(n_images, len(depths))).round().astype(int))
    k_best = int(np.argmin(np.abs(depths - best)))
    if k_best not in picks:
        picks[np.argmin(np.abs(picks - k_best))] = k_best
        picks = np.unique(picks)
    if center is not None:
        # show some context around the window; the window itself is outlined
        s_c, t_c = (int(round(c)) for c in center)
        hw = int(half_width)
        margin = max(2 * hw, hw + 4)
        t0, t1 = max(t_c - margin, 0), min(t_c + margin + 1, stack.shape[1])
        s0, s1 = max(s_c - margin, 0), min(s_c + margin + 1, stack.shape[2])
    else:
        t0, t1, s0, s1 = 0, stack.shape[1], 0, stack.shape[2]
    crops = stack[picks, t0:t1, s0:s1]
    vmin, vmax = _display_limits(crops, (1, 99))

    fig = Figure(figsize=figsize, layout="constrained")
    grid = fig.add_gridspec(2, len(picks), height_ratios=[1, 1.3])
    for j, k in enumerate(picks):
        ax = fig.add_subplot(grid[0, j])
        ax.imshow(crops[j], cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest",
                  extent=(s0 - 0.5, s1 - 0.5, t1 - 0.5, t0 - 0.5))
        ax.set_title(f"z = {depths[k]:+.1f} mm" + (" (best)" if k == k_best else ""),
                     fontsize="medium")
        if center is not None:
            ax.add_patch(Rectangle((s_c - hw - 0.5, t_c - hw - 0.5), 2 * hw + 1, 2 * hw + 1,
                                   fill=False, edgecolor="tab:orange", lw=1.2))
        ax.set_xlabel("s (view px)")
        if j == 0:
            ax.set_ylabel("t (view px)")
    ax = fig.add_subplot(grid[1, :])
    ax.plot(depths, rel, "o-", color="tab:blue", ms=3, label=f"sharpness ({method})")
    ax.axvline(best, color="tab:blue", lw=1.5, label=f"best focus {best:+.2f} mm")
    if true_depth_mm is not None:
        ax.axvline(float(true_depth_mm), color="k", ls="--", lw=1.2,
                   label=f"true depth {float(true_depth_mm):+.2f} mm")
    ax.set_xlabel("refocus depth z (mm)")
    ax.set_ylabel("sharpness (relative to max)")
    ax.legend(fontsize="small")
    ax.grid(alpha=0.3)
    return fig


# --------------------------------------------------------------------------------------
# particles


def plot_particles_3d(particles: pd.DataFrame, *, truth: pd.DataFrame | None = None,
                      cmap: str = "viridis",
                      figsize: tuple[float, float] = (9.0, 7.0)) -> Figure:
    """Located particles in three orthogonal projections, coloured by depth.

    Parameters
    ----------
    particles : DataFrame
        Columns ``x, y, z``, mm (e.g. ``locate_frame(...).particles``).
    truth : DataFrame, optional
        True positions, columns ``x, y, z`` in mm, drawn as open black circles.
    cmap : str
        Colour map of the depth ``z``.
    figsize : (float, float)
        Figure size, inches.

    Returns
    -------
    Figure
        Axes in this order: ``x-y`` (top left; ``y`` grows downwards as on the sensor),
        ``z-y`` (top right, same ``y`` axis), ``x-z`` (bottom left, same ``x`` axis), and
        a colour bar of ``z`` (mm). The legend sits in the empty bottom-right corner.

    Notes
    -----
    The layout follows the seed paper's Fig. 12: the ``x-z`` projection below the
    ``x-y`` one and the ``z-y`` projection beside it, so that each shares an axis with
    the front view.
    """
    particles = _check_table(particles, "particles", POS_COLUMNS)
    if truth is not None:
        truth = _check_table(truth, "truth", POS_COLUMNS)
    z_all = [particles["z"].to_numpy(float)]
    if truth is not None:
        z_all.append(truth["z"].to_numpy(float))
    z_all = np.concatenate(z_all)
    z_all = z_all[np.isfinite(z_all)]
    zlim = (float(z_all.min()), float(z_all.max())) if z_all.size else (-1.0, 1.0)
    if zlim[1] <= zlim[0]:
        zlim = (zlim[0] - 1.0, zlim[1] + 1.0)

    fig = Figure(figsize=figsize, layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=[1.6, 1], height_ratios=[1, 1])
    ax_xy = fig.add_subplot(grid[0, 0])
    ax_zy = fig.add_subplot(grid[0, 1], sharey=ax_xy)
    ax_xz = fig.add_subplot(grid[1, 0], sharex=ax_xy)
    ax_legend = fig.add_subplot(grid[1, 1])
    ax_legend.axis("off")
    panels = [(ax_xy, "x", "y"), (ax_zy, "z", "y"), (ax_xz, "x", "z")]
    scatter = None
    for ax, h, w in panels:
        scatter = ax.scatter(particles[h], particles[w], c=particles["z"], cmap=cmap,
                             vmin=zlim[0], vmax=zlim[1], s=22, edgecolors="none",
                             label=f"located ({len(particles)})")
        if truth is not None:
            ax.scatter(truth[h], truth[w], s=70, facecolors="none", edgecolors="k",
                       linewidths=0.9, label=f"true ({len(truth)})")
        ax.set_xlabel(f"{h} (mm)")
        ax.set_ylabel(f"{w} (mm)")
        ax.grid(alpha=0.3)
    ax_xy.invert_yaxis()
    ax_xy.set_title("x-y (front view)")
    ax_zy.set_title("z-y (side view)")
    ax_xz.set_title("x-z (top view)")
    fig.colorbar(scatter, ax=[ax_xy, ax_zy, ax_xz], label="z (mm)", shrink=0.8)
    handles, labels = ax_xy.get_legend_handles_labels()
    ax_legend.legend(handles, labels, loc="center")
    return fig


def plot_errors_vs_depth(particles: pd.DataFrame, truth: pd.DataFrame, *,
                         tolerance_mm: float = 1.0, bins: int | np.ndarray = 10,
                         figsize: tuple[float, float] = (8.0, 6.0)) -> Figure:
    """Depth error (accuracy and precision) against true depth.

    Measured particles are paired with true ones by
    :func:`plenoptrack.evaluate.match_particles`; the depth errors ``dz`` (measured minus
    true, mm) of the pairs are binned by true depth.

    Parameters
    ----------
    particles, truth : DataFrame
        Columns ``x, y, z`` in mm and optionally ``frame``.
    tolerance_mm : float
        Largest 3D distance of a pair, mm.
    bins : int or (n + 1,) array_like
        Number of equal-width depth bins over the true depths of the pairs, or the bin
        edges, mm.
    figsize : (float, float)
        Figure size, inches.

    Returns
    -------
    Figure
        Two axes sharing the depth axis. Top: each pair's ``dz`` (grey dots) and, per
        bin, the mean error with a bar of plus and minus one standard deviation (the
        seed paper's Fig. 9). Bottom: the standard deviation of ``dz`` per bin (Fig. 10);
        bins with fewer than 2 pairs have none.

    Raises
    ------
    ValueError
        A table lacks ``x, y, z``, ``tolerance_mm`` or ``bins`` is invalid, or no pair
        lies within the tolerance.
    """
    particles = _check_table(particles, "particles", POS_COLUMNS)
    truth = _check_table(truth, "truth", POS_COLUMNS)
    if not (np.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise SettingsError(f"tolerance_mm must be positive; got {tolerance_mm!r}")
    pairs = match_particles(particles, truth, tolerance_mm=tolerance_mm)
    if len(pairs) == 0:
        raise SettingsError(f"no measured particle lies within tolerance_mm = {tolerance_mm:g} mm "
                         "of a true one; nothing to plot (raise the tolerance or check the "
                         "tables use the same frame and units)")
    z_true = truth.loc[pairs["truth_index"], "z"].to_numpy(float)
    dz = pairs["dz"].to_numpy(float)
    if np.ndim(bins) == 0:
        n_bins = int(bins)
        if n_bins < 1:
            raise SettingsError(f"bins must be a positive number of bins or bin edges; got {bins!r}")
        lo, hi = float(z_true.min()), float(z_true.max())
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        edges = np.linspace(lo, hi, n_bins + 1)
    else:
        edges = np.asarray(bins, dtype=float)
        if edges.ndim != 1 or len(edges) < 2 or not np.all(np.diff(edges) > 0):
            raise SettingsError("bins as edges must be a 1-D increasing sequence of at least 2 "
                             f"depths, mm; got {np.asarray(bins).tolist()!r}")
    which = np.digitize(z_true, edges[1:-1])
    inside = (z_true >= edges[0]) & (z_true <= edges[-1])
    centres = 0.5 * (edges[:-1] + edges[1:])
    n = np.array([np.count_nonzero(inside & (which == k)) for k in range(len(centres))])
    mean = np.full(len(centres), np.nan)
    std = np.full(len(centres), np.nan)
    for k in range(len(centres)):
        sel = dz[inside & (which == k)]
        if sel.size:
            mean[k] = sel.mean()
        if sel.size > 1:
            std[k] = sel.std(ddof=1)

    fig = Figure(figsize=figsize, layout="constrained")
    ax_mean, ax_std = fig.subplots(2, 1, sharex=True, height_ratios=[1.4, 1])
    ax_mean.axhline(0.0, color="k", lw=0.8)
    ax_mean.plot(z_true, dz, ".", color="0.6", ms=4, label=f"pairs ({len(pairs)})")
    has = n > 0
    ax_mean.errorbar(centres[has], mean[has], yerr=np.nan_to_num(std[has]), fmt="o",
                     color="tab:blue", capsize=3, label="bin mean \u00b1 1 sd")
    ax_mean.set_ylabel("depth error dz (mm)")
    ax_mean.set_title(f"depth error vs depth: {len(pairs)} of {len(truth)} true particles "
                      f"matched within {tolerance_mm:g} mm")
    ax_mean.legend(fontsize="small")
    ax_mean.grid(alpha=0.3)
    ok = np.isfinite(std)
    ax_std.bar(centres[ok], std[ok], width=0.8 * np.diff(edges)[ok], color="tab:orange",
               label="sd of dz per bin")
    ax_std.set_xlabel("true depth z (mm)")
    ax_std.set_ylabel("sd of dz (mm)")
    ax_std.set_ylim(bottom=0)
    ax_std.grid(alpha=0.3)
    return fig


# --------------------------------------------------------------------------------------
# fragment fields and tracks


def outline_points(particles: pd.DataFrame, *, n: int = 48) -> np.ndarray:
    """Ellipse outlines of particles in the x-y plane, mm.

    Parameters
    ----------
    particles : DataFrame
        Columns ``x, y`` (mm) and ``major_axis, minor_axis`` (full axes, mm) and
        ``orientation`` (rad, major axis from +x towards +y); without the axes,
        ``diameter`` (mm) gives circles.
    n : int
        Points per outline.

    Returns
    -------
    (len(particles), n, 2) float ndarray
        ``(x, y)`` of each outline point, mm.
    """
    x = particles["x"].to_numpy(float)
    y = particles["y"].to_numpy(float)
    if {"major_axis", "minor_axis"} <= set(particles.columns):
        a = particles["major_axis"].to_numpy(float) / 2
        b = particles["minor_axis"].to_numpy(float) / 2
    else:
        a = b = particles["diameter"].to_numpy(float) / 2
    th = (particles["orientation"].to_numpy(float) if "orientation" in particles.columns
          else np.zeros(len(x)))
    th = np.nan_to_num(th)
    phi = np.linspace(0, 2 * np.pi, n)
    ca, sa = np.cos(phi)[None, :] * a[:, None], np.sin(phi)[None, :] * b[:, None]
    ox = x[:, None] + ca * np.cos(th)[:, None] - sa * np.sin(th)[:, None]
    oy = y[:, None] + ca * np.sin(th)[:, None] + sa * np.cos(th)[:, None]
    return np.stack([ox, oy], axis=-1)


def _area_mm2(particles: pd.DataFrame) -> np.ndarray:
    """Measured image area of each particle, mm^2 (from ``diameter``, or 1 when absent)."""
    if "diameter" in particles.columns:
        d = particles["diameter"].to_numpy(float)
        return np.where(np.isfinite(d), np.pi * d ** 2 / 4, 0.0)
    return np.ones(len(particles))


def plot_fragment_field(particles: pd.DataFrame, *, view: np.ndarray | None = None,
                        dlfc=None, cmap: str = "coolwarm",
                        figsize: tuple[float, float] = (11.0, 8.5)) -> Figure:
    """The seed paper's Fig. 12: measured fragments in a view and three projections.

    Parameters
    ----------
    particles : DataFrame
        One frame of located particles: ``x, y, z`` (mm) and, for the outlines and
        marker sizes, ``diameter``, ``major_axis``, ``minor_axis`` (mm) and
        ``orientation`` (rad), as ``plenoptrack locate`` writes.
    view : (n_t, n_s) ndarray, optional
        Central perspective view (``lf.view(0, 0)``) to draw the outlines on; needs
        ``dlfc``. Without it the outlines are drawn in the x-y plane, mm.
    dlfc : DLFC, optional
        Calibration that maps each outline point at the particle's depth into the
        central view (``dlfc.predict(x, y, z, 0, 0)``).
    cmap : str
        Colour map of depth for the outlines (blue near the camera, red far).
    figsize : (float, float)
        Figure size, inches.

    Returns
    -------
    Figure
        Axes in this order: top-down view ``x-z`` (top left), isometric 3D view (top
        right), central view with outlines coloured by depth ``z`` (bottom left, ``s, t``
        in view px, or ``x, y`` in mm), side view ``z-y`` (bottom right), colour bar of
        ``z``. In the three projections grey level and marker area are proportional to
        the measured image area.
    """
    particles = _check_table(particles, "particles", POS_COLUMNS)
    if view is not None and dlfc is None:
        raise SettingsError("view needs dlfc to place the outlines in it")
    z = particles["z"].to_numpy(float)
    finite = z[np.isfinite(z)]
    zlim = (float(finite.min()), float(finite.max())) if finite.size else (-1.0, 1.0)
    if zlim[1] <= zlim[0]:
        zlim = (zlim[0] - 1.0, zlim[1] + 1.0)
    area = _area_mm2(particles)
    amax = float(area.max()) if area.size and area.max() > 0 else 1.0
    sizes = 8 + 220 * area / amax
    grey = [str(0.75 * (1 - a / amax)) for a in area]     # dark = large

    from matplotlib import colormaps
    from matplotlib.colors import Normalize
    from matplotlib.cm import ScalarMappable

    norm = Normalize(*zlim)
    colours = colormaps[cmap](norm(z))
    fig = Figure(figsize=figsize, layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=[1.5, 1], height_ratios=[1, 1.35])
    ax_top = fig.add_subplot(grid[0, 0])
    ax_iso = fig.add_subplot(grid[0, 1], projection="3d")
    ax_view = fig.add_subplot(grid[1, 0])
    ax_side = fig.add_subplot(grid[1, 1])

    outlines = outline_points(particles)
    if view is not None:
        vmin, vmax = _display_limits(np.asarray(view, float))
        ax_view.imshow(view, cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
        s_pts, t_pts = dlfc.predict(outlines[..., 0], outlines[..., 1], z[:, None], 0.0, 0.0)
        pts = np.stack([s_pts, t_pts], axis=-1)
        ax_view.set_xlabel("s (view px)")
        ax_view.set_ylabel("t (view px)")
        ax_view.set_xlim(-0.5, view.shape[1] - 0.5)
        ax_view.set_ylim(view.shape[0] - 0.5, -0.5)
        ax_view.set_title("central view, measured outlines coloured by depth")
    else:
        pts = outlines
        ax_view.set_aspect("equal")
        ax_view.invert_yaxis()
        ax_view.set_xlabel("x (mm)")
        ax_view.set_ylabel("y (mm)")
        ax_view.set_title("front view, measured outlines coloured by depth")
        ax_view.grid(alpha=0.3)
    from matplotlib.collections import PolyCollection

    ax_view.add_collection(PolyCollection(list(pts), facecolors="none", edgecolors=colours,
                                          linewidths=1.4))
    if view is None:
        ax_view.autoscale_view()
        ax_view.invert_yaxis()

    for ax, h, w, title in ((ax_top, "x", "z", "top-down view"), (ax_side, "z", "y", "side view")):
        ax.scatter(particles[h], particles[w], s=sizes, c=grey, edgecolors="k", linewidths=0.4)
        ax.set_xlabel(f"{h} (mm)")
        ax.set_ylabel(f"{w} (mm)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    ax_side.invert_yaxis()                      # y grows downwards, as in the view
    ax_iso.scatter(particles["x"], particles["z"], particles["y"], s=sizes, c=grey,
                   edgecolors="k", linewidths=0.3, depthshade=False)
    ax_iso.set_xlabel("x (mm)")
    ax_iso.set_ylabel("z (mm)")
    ax_iso.set_zlabel("y (mm)")
    ax_iso.invert_zaxis()
    ax_iso.view_init(elev=25, azim=-55)
    ax_iso.set_title("isometric view")
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax_view, label="z (mm)", shrink=0.85)
    n = len(particles)
    fig.suptitle(f"{n} particle{'s' if n != 1 else ''}; grey level and marker size "
                 "proportional to measured image area")
    return fig


def plot_tracks(tracks: pd.DataFrame, *, cmap: str = "viridis", speed_unit: str = "mm/frame",
                figsize: tuple[float, float] = (11.0, 8.0)) -> Figure:
    """3D tracks in three projections coloured by speed, and speed against frame.

    Parameters
    ----------
    tracks : DataFrame
        ``plenoptrack track`` output: ``frame, particle`` and ``x_smooth, y_smooth,
        z_smooth`` (mm; else ``x, y, z``) and ``speed`` (mm per frame; ``speed_m_per_s``
        is used when ``speed_unit`` is ``"m/s"``).
    cmap : str
        Colour map of the speed.
    speed_unit : {"mm/frame", "m/s"}
        Unit of the colours and of the speed panel.
    figsize : (float, float)
        Figure size, inches.

    Returns
    -------
    Figure
        Axes: front ``x-y`` (top left), side ``z-y`` (top right), top ``x-z`` (bottom
        left), speed against frame (bottom right), colour bar of speed. Each track is a
        line coloured by its speed along the track.
    """
    from matplotlib import colormaps
    from matplotlib.collections import LineCollection
    from matplotlib.colors import Normalize
    from matplotlib.cm import ScalarMappable

    cols = ["frame", "particle"]
    tracks = _check_table(tracks, "tracks", cols)
    pos = ["x_smooth", "y_smooth", "z_smooth"] if "z_smooth" in tracks.columns else list(POS_COLUMNS)
    speed_col = {"mm/frame": "speed", "m/s": "speed_m_per_s"}.get(speed_unit)
    if speed_col is None:
        raise SettingsError(f"speed_unit must be 'mm/frame' or 'm/s'; got {speed_unit!r}")
    _check_table(tracks, "tracks", [*pos, speed_col])
    df = tracks.sort_values(["particle", "frame"], kind="stable")
    speed = df[speed_col].to_numpy(float)
    ok = np.isfinite(speed)
    lo, hi = (np.percentile(speed[ok], [1, 99]) if ok.any() else (0.0, 1.0))
    norm = Normalize(float(lo), float(hi) if hi > lo else float(lo) + 1.0)
    cm = colormaps[cmap]
    fig = Figure(figsize=figsize, layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=[1.5, 1])
    ax_xy = fig.add_subplot(grid[0, 0])
    ax_zy = fig.add_subplot(grid[0, 1], sharey=ax_xy)
    ax_xz = fig.add_subplot(grid[1, 0], sharex=ax_xy)
    ax_sp = fig.add_subplot(grid[1, 1])
    xyz = df[pos].to_numpy(float)
    pid = df["particle"].to_numpy()
    same = pid[1:] == pid[:-1]
    seg_speed = 0.5 * (speed[1:] + speed[:-1])[same]
    for ax, (i, j), title in ((ax_xy, (0, 1), "front view x-y"), (ax_zy, (2, 1), "side view z-y"),
                              (ax_xz, (0, 2), "top view x-z")):
        segs = np.stack([xyz[:-1][same][:, [i, j]], xyz[1:][same][:, [i, j]]], axis=1)
        lc = LineCollection(segs, colors=cm(norm(seg_speed)), linewidths=1.2)
        ax.add_collection(lc)
        ax.scatter(xyz[:, i], xyz[:, j], s=3, c=cm(norm(speed)), edgecolors="none")
        ax.autoscale_view()
        ax.set_xlabel(f"{'xyz'[i]} (mm)")
        ax.set_ylabel(f"{'xyz'[j]} (mm)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    ax_xy.invert_yaxis()
    frames = df["frame"].to_numpy(float)
    segs = np.stack([np.column_stack([frames[:-1], speed[:-1]])[same],
                     np.column_stack([frames[1:], speed[1:]])[same]], axis=1)
    ax_sp.add_collection(LineCollection(segs, colors=cm(norm(seg_speed)), linewidths=0.8,
                                        alpha=0.7))
    ax_sp.autoscale_view()
    ax_sp.set_xlabel("frame")
    ax_sp.set_ylabel(f"speed ({speed_unit})")
    n_tracks = len(np.unique(pid))
    ax_sp.set_title(f"speed along {n_tracks} tracks")
    ax_sp.grid(alpha=0.3)
    fig.colorbar(ScalarMappable(norm=norm, cmap=cm), ax=[ax_xy, ax_zy, ax_xz],
                 label=f"speed ({speed_unit})", shrink=0.8)
    return fig


_STUDY_PANELS = {
    "accuracy": ("depth_mm", "mean", "_mm", "z (mm)", "mean depth error (mm)"),
    "precision": ("depth_mm", "std", "_mm", "z (mm)", "std of depth error (mm)"),
    "precision_normalised": ("depth_norm", "std", "_norm",
                             "z / depth-of-field limit (near < 0, far > 0)",
                             "std of depth error / object-space microlens pitch"),
}


def plot_study_bins(bins: pd.DataFrame, kind: str = "precision") -> Figure:
    """Accuracy or precision against depth, one panel per method, shared axes (the
    layout of figures 9-11 of the method paper).

    Parameters
    ----------
    bins : DataFrame
        Rows of :func:`plenoptrack.study.binned_statistics` with ``method`` and
        ``configuration`` columns.
    kind : {"accuracy", "precision", "precision_normalised"}
        Mean error (mm), standard deviation (mm), or standard deviation over the
        object-space microlens pitch against depth over the depth-of-field limits. Error
        bars are the 99 % confidence bounds.
    """
    if kind not in _STUDY_PANELS:
        raise SettingsError(f"kind must be one of {sorted(_STUDY_PANELS)}; got {kind!r}")
    xcol, stat, unit, xlabel, ylabel = _STUDY_PANELS[kind]
    methods = list(dict.fromkeys(bins["method"]))
    configs = list(dict.fromkeys(bins["configuration"]))
    fig = Figure(figsize=(4.2 * len(methods) + 0.8, 3.8), layout="constrained")
    axes = fig.subplots(1, len(methods), sharex=True, sharey=True, squeeze=False)[0]
    for ax, method in zip(axes, methods):
        for k, cfg in enumerate(configs):
            b = bins[(bins["method"] == method) & (bins["configuration"] == cfg)]
            if b.empty:
                continue
            y = b[f"{stat}{unit}"].to_numpy(float)
            lo = y - b[f"{stat}_lo{unit}"].to_numpy(float)
            hi = b[f"{stat}_hi{unit}"].to_numpy(float) - y
            ax.errorbar(b[xcol], y, yerr=[lo, hi], fmt="o", ms=3, capsize=2, lw=0.8,
                        color=f"C{k % 10}", label=cfg)
        if stat == "mean":
            ax.axhline(0, color="0.5", lw=0.6)
        if xcol == "depth_norm":
            for v in (-1, 1):
                ax.axvline(v, color="0.6", lw=0.6, ls="--")
        ax.set_title(method)
        ax.set_xlabel(xlabel)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(ylabel)
    if stat == "std":
        axes[0].set_ylim(bottom=0)
    if len(configs) > 1:
        axes[-1].legend(fontsize=7, loc="best")
    return fig


def plot_study(bins: pd.DataFrame, out_dir, *, dof=None) -> list:
    """Write ``accuracy.png``, ``precision.png`` and ``precision_normalised.png``
    (:func:`plot_study_bins`) into ``out_dir`` (atomically); returns the paths."""
    from pathlib import Path

    from .io import atomic_path

    paths = []
    for kind in _STUDY_PANELS:
        fig = plot_study_bins(bins, kind)
        path = Path(out_dir) / f"{kind}.png"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=120, format="png")
        paths.append(path)
    return paths
