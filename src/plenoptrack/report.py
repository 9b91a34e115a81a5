"""A self-contained interactive HTML report of particles and tracks (plotly).

One HTML file holds a rotatable 3D view of the particles (every frame) and the tracks
joining them, coloured by depth or speed, with hover details, and the run's summary table.
plotly.js is embedded in the file, so it opens with no network.

Examples
--------
>>> import numpy as np, pandas as pd
>>> from plenoptrack.report import report_html
>>> p = pd.DataFrame({"frame": [0, 1], "x": [0.0, 1.0], "y": [0.0, 0.0], "z": [0.0, 0.5]})
>>> html = report_html(p, title="two points")
>>> html.startswith("<!DOCTYPE html>") and "plotly" in html
True
"""

from __future__ import annotations

import html as _html
import json
import math

import numpy as np
import pandas as pd

from ._columns import ID_COLUMN, POS_COLUMNS, T_COLUMN
from .errors import InputFileError, SettingsError

__all__ = ["report_figure", "report_html", "summary_rows", "REPORT_DIV_ID"]

REPORT_DIV_ID = "plenoptrack-3d"
"""HTML id of the 3D view's element."""

_HOVER_COLUMNS = (("frame", "frame", "{:.0f}"), ("particle", "track", "{:.0f}"),
                  ("x", "x (mm)", "{:.3f}"), ("y", "y (mm)", "{:.3f}"), ("z", "z (mm)", "{:.3f}"),
                  ("sigma_z", "sigma z (mm)", "{:.3f}"), ("z_smooth", "z smoothed (mm)", "{:.3f}"),
                  ("speed", "speed (mm/frame)", "{:.3f}"), ("speed_m_per_s", "speed (m/s)", "{:.1f}"),
                  ("diameter", "diameter (mm)", "{:.3f}"))


def _hover_text(df: pd.DataFrame) -> list[str]:
    parts = []
    for col, label, fmt in _HOVER_COLUMNS:
        if col in df.columns:
            values = df[col].to_numpy(float)
            parts.append([f"{label}: " + (fmt.format(v) if np.isfinite(v) else "-") for v in values])
    return ["<br>".join(row) for row in zip(*parts)] if parts else [""] * len(df)


def report_figure(table: pd.DataFrame, *, color_by: str = "depth"):
    """The 3D plotly figure: particles as markers, tracks as lines.

    Parameters
    ----------
    table : DataFrame
        Particles (``frame, x, y, z`` mm) or tracks (with ``particle`` and, from
        ``plenoptrack track``, ``x_smooth, y_smooth, z_smooth`` and ``speed``).
    color_by : {"depth", "speed"}
        Colour of markers and lines: ``z`` (mm) or ``speed`` (mm per frame, tracks only).

    Returns
    -------
    plotly.graph_objects.Figure
        Scene axes ``x`` (mm), ``z`` (mm, depth, pointing away from the viewer at start)
        and ``y`` (mm, downwards as on the sensor). Trace 0 holds every particle; trace 1,
        when there are tracks, every track as one line (``None`` between tracks).
    """
    import plotly.graph_objects as go

    if not isinstance(table, pd.DataFrame):
        raise SettingsError(f"table must be a DataFrame; got {type(table).__name__}")
    missing = [c for c in POS_COLUMNS if c not in table.columns]
    if missing:
        raise InputFileError(f"table has no column(s) {missing}; expected x, y, z in mm")
    if color_by not in ("depth", "speed"):
        raise SettingsError(f"color_by must be 'depth' or 'speed'; got {color_by!r}")
    if color_by == "speed" and "speed" not in table.columns:
        raise SettingsError("color_by='speed' needs a tracks table with a speed column "
                            "(`plenoptrack track`)")
    df = table.reset_index(drop=True)
    colour = df["z"].to_numpy(float) if color_by == "depth" else df["speed"].to_numpy(float)
    label = "z (mm)" if color_by == "depth" else "speed (mm/frame)"
    ok = np.isfinite(colour)
    cmin, cmax = (float(np.min(colour[ok])), float(np.max(colour[ok]))) if ok.any() else (0.0, 1.0)
    scale = "RdBu_r" if color_by == "depth" else "Viridis"
    tracked = ID_COLUMN in df.columns
    size = np.full(len(df), 2.5 if tracked else 4.0)
    if "diameter" in df.columns:
        d = df["diameter"].to_numpy(float)
        if np.isfinite(d).any() and np.nanmax(d) > 0:
            size = (2.0 if tracked else 3.0) + (5.0 if tracked else 9.0) * np.sqrt(
                np.clip(np.nan_to_num(d), 0, None) / np.nanmax(d))
    fig = go.Figure()
    fig.add_trace(go.Scatter3d(
        x=df["x"], y=df["z"], z=df["y"], mode="markers", name="particles",
        text=_hover_text(df), hoverinfo="text",
        marker=dict(size=size, color=colour, colorscale=scale, cmin=cmin, cmax=cmax,
                    colorbar=dict(title=dict(text=label)), opacity=0.9, line=dict(width=0))))
    if ID_COLUMN in df.columns and T_COLUMN in df.columns:
        pos = ["x_smooth", "y_smooth", "z_smooth"] if "z_smooth" in df.columns else list(POS_COLUMNS)
        tr = df.sort_values([ID_COLUMN, T_COLUMN], kind="stable")
        pieces_x, pieces_y, pieces_z, pieces_c = [], [], [], []
        c_tr = colour[tr.index.to_numpy()]
        for _, idx in tr.groupby(ID_COLUMN, sort=False).indices.items():
            if len(idx) < 2:
                continue
            rows = tr.iloc[idx]
            pieces_x += list(rows[pos[0]]) + [None]
            pieces_y += list(rows[pos[2]]) + [None]
            pieces_z += list(rows[pos[1]]) + [None]
            pieces_c += list(c_tr[idx]) + [float(c_tr[idx][-1])]
        if pieces_x:
            fig.add_trace(go.Scatter3d(
                x=pieces_x, y=pieces_y, z=pieces_z, mode="lines", name="tracks",
                hoverinfo="skip", connectgaps=False, showlegend=False,
                line=dict(width=3, color=pieces_c, colorscale=scale, cmin=cmin, cmax=cmax)))
    fig.update_layout(
        scene=dict(xaxis_title="x (mm)", yaxis_title="z (mm)", zaxis_title="y (mm)",
                   zaxis=dict(autorange="reversed"), aspectmode="data",
                   camera=dict(eye=dict(x=1.4, y=-1.6, z=0.9))),
        margin=dict(l=0, r=0, t=30, b=0), height=700, legend=dict(x=0.01, y=0.99),
        title=dict(text=f"3D view coloured by {color_by}"))
    return fig


def summary_rows(table: pd.DataFrame) -> list[tuple[str, str]]:
    """Summary of a particles or tracks table as (quantity, value) strings.

    Counts of frames, particles and tracks, track lengths, speeds, outliers, the depth
    range, and the estimated depth-scatter reduction of track smoothing; with tracking
    settings in the table's provenance (:func:`plenoptrack.track.tracking_record`), those
    too.
    """
    rows = [("frames", f"{table[T_COLUMN].nunique() if T_COLUMN in table.columns else 1}"),
            ("particle positions", f"{len(table)}")]
    if len(table):
        rows.append(("depth range z (mm)", f"{table['z'].min():.2f} to {table['z'].max():.2f}"))
    if ID_COLUMN in table.columns:
        lengths = table.groupby(ID_COLUMN).size()
        rows += [("tracks", f"{len(lengths)}"),
                 ("mean track length (frames)", f"{lengths.mean():.1f}" if len(lengths) else "-")]
    if "speed" in table.columns and len(table):
        rows.append(("median speed (mm/frame)", f"{np.nanmedian(table['speed']):.3f}"))
    if "speed_m_per_s" in table.columns and len(table):
        rows.append(("median speed (m/s)", f"{np.nanmedian(table['speed_m_per_s']):.1f}"))
    if "outlier" in table.columns:
        rows.append(("points rejected from the fits", f"{int(table['outlier'].sum())}"))
    if "sigma_z_smooth" in table.columns and len(table):
        from .track import depth_scatter_ratio

        ratio = depth_scatter_ratio(table)
        rows.append(("depth scatter, per frame / track-smoothed (estimated)",
                     f"{ratio:.2f}" if math.isfinite(ratio) else "-"))
    from .track import tracking_record

    settings = tracking_record(table).get("settings")
    if settings:
        rows.append(("tracking settings", json.dumps(settings)))
    return rows


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
body {{ font-family: sans-serif; margin: 1em 2em; color: #222; }}
table.summary {{ border-collapse: collapse; margin-top: 1em; }}
table.summary td, table.summary th {{ border: 1px solid #bbb; padding: 0.25em 0.8em; text-align: left; }}
table.summary th {{ background: #eee; }}
</style>
</head>
<body>
<h1>{title}</h1>
<p>Drag to rotate, scroll to zoom; hover over a particle for its details. Depth z points
away from the camera; y grows downwards as on the sensor.</p>
{figure}
<h2>Summary</h2>
<table class="summary"><tr><th>quantity</th><th>value</th></tr>
{rows}
</table>
</body>
</html>
"""


def report_html(table: pd.DataFrame, *, color_by: str = "depth",
                title: str = "plenoptrack report", extra_rows=()) -> str:
    """The whole report as one HTML string, plotly.js embedded (no network needed).

    Parameters
    ----------
    table : DataFrame
        Particles or tracks (see :func:`report_figure`).
    color_by : {"depth", "speed"}
        Colouring of the 3D view.
    title : str
        Page title.
    extra_rows : iterable of (str, str)
        More summary rows (e.g. the input file names).

    Returns
    -------
    str
        A complete HTML document. The 3D view's element has id :data:`REPORT_DIV_ID`; once
        plotly has drawn it, the page's ``body`` gets the attribute
        ``data-plot-ready="1"``.
    """
    fig = report_figure(table, color_by=color_by)
    post = (f"document.body.setAttribute('data-plot-ready', "
            f"document.getElementById('{REPORT_DIV_ID}').querySelector('canvas') ? '1' : '0');")
    div = fig.to_html(full_html=False, include_plotlyjs=True, div_id=REPORT_DIV_ID,
                      post_script=post, config={"displaylogo": False})
    rows = list(summary_rows(table)) + [(str(k), str(v)) for k, v in extra_rows]
    body = "\n".join(f"<tr><td>{_html.escape(k)}</td><td>{_html.escape(v)}</td></tr>"
                     for k, v in rows)
    return _PAGE.format(title=_html.escape(title), figure=div, rows=body)
