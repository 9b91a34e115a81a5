"""Tests of dot-card detection and grid indexing."""

from types import SimpleNamespace

import numpy as np
import pytest

from plenoptrack.errors import CalibrationError
from plenoptrack.locate.dotcards import dotcard_points, index_dotcard, index_lattice
from plenoptrack.locate.segment import segment_view

AXIS = (61.3, 40.6)        # (s, t) of the optical axis
SHAPE = (84, 124)          # view (n_t, n_s)


def _render(points_st, shape=SHAPE, sigma=1.0, depth=0.7):
    img = np.ones(shape)
    h = 5
    for ps, pt in points_st:
        c, r = int(round(ps)), int(round(pt))
        r0, r1, c0, c1 = max(r - h, 0), min(r + h + 1, shape[0]), max(c - h, 0), min(c + h + 1, shape[1])
        if r0 >= r1 or c0 >= c1:
            continue
        t, s = np.mgrid[r0:r1, c0:c1]
        img[r0:r1, c0:c1] -= depth * np.exp(-((s - ps) ** 2 + (t - pt) ** 2) / (2 * sigma ** 2))
    return img


def _card(parallax, *, spacing_px=9.0, angle=0.03, radius=3, noise=0.01, seed=0):
    """Fake light field of a dot card: every view shows the grid shifted by parallax*(u, v)."""
    rng = np.random.default_rng(seed)
    ang = np.arange(-radius, radius + 1.0)
    n = len(ang)
    ij = np.array([(i, j) for i in range(-9, 10) for j in range(-7, 8)], dtype=float)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    base = np.asarray(AXIS) + spacing_px * ij @ rot.T
    data = np.empty((n, n, *SHAPE), np.float32)
    truth = {}
    for iv, v in enumerate(ang):
        for iu, u in enumerate(ang):
            pos = base + parallax * np.array([u, v])
            data[iv, iu] = _render(pos) + rng.normal(0, noise, SHAPE)
            truth[(u, v)] = (pos, ij)
    mask = np.add.outer(ang ** 2, ang ** 2) <= (radius + 0.5) ** 2
    lf = SimpleNamespace(data=data, u=ang, v=ang.copy(), view_mask=mask,
                         spatial_mask=np.ones(SHAPE, bool), flat_fielded=False,
                         axis_st=AXIS, sample_spacing_px=12.0)
    return lf, truth


def _check_against_truth(table, truth, spacing_mm):
    for (u, v), grp in table.groupby(["u", "v"]):
        pos, ij = truth[(u, v)]
        for row in grp.itertuples():
            k = np.argmin(np.hypot(pos[:, 0] - row.s, pos[:, 1] - row.t))
            assert np.hypot(pos[k, 0] - row.s, pos[k, 1] - row.t) < 0.15
            assert (row.i, row.j) == tuple(ij[k].astype(int))
            assert (row.x, row.y) == pytest.approx(tuple(ij[k] * spacing_mm))


@pytest.mark.parametrize("parallax", [0.0, 1.5, -4.0])
def test_dotcard_indices_and_world_positions(parallax):
    lf, truth = _card(parallax)
    table = dotcard_points(lf, spacing_mm=2.5, z_mm=-10.0, parallax_per_u=parallax)
    assert list(table.columns) == ["u", "v", "s", "t", "x", "y", "z", "i", "j"]
    assert (table["z"] == -10.0).all()
    _check_against_truth(table, truth, 2.5)
    n_views = int(lf.view_mask.sum())
    assert table.groupby(["u", "v"]).ngroups == n_views
    # +x is +s, +y is +t (the sensor sees the world upright)
    centre = table[(table["u"] == 0) & (table["v"] == 0)]
    assert np.corrcoef(centre["x"], centre["s"])[0, 1] > 0.99
    assert np.corrcoef(centre["y"], centre["t"])[0, 1] > 0.99
    origin = centre[(centre["i"] == 0) & (centre["j"] == 0)]
    assert (origin["s"].iloc[0], origin["t"].iloc[0]) == pytest.approx(AXIS, abs=0.1)
    # most of the dots inside the view are found in every view
    assert table.groupby(["u", "v"]).size().min() > 0.8 * len(centre)


def test_prediction_error_is_refitted():
    # true parallax 4.5 px per view, predicted 3.8 px: the error grows to 2.1 px at
    # |u| = 3 (more than tol * spacing), but the refit from inner views absorbs it
    lf, truth = _card(4.5)
    table = dotcard_points(lf, spacing_mm=1.0, z_mm=5.0, parallax_per_u=3.8)
    _check_against_truth(table, truth, 1.0)
    assert table.groupby(["u", "v"]).ngroups == int(lf.view_mask.sum())


def test_dots_cut_by_view_edge_are_rejected():
    lf, truth = _card(2.0)
    table = dotcard_points(lf, spacing_mm=1.0, z_mm=0.0, parallax_per_u=2.0)
    # a dot's foreground reaches ~1.75 px from its centre: dots whose centre is within
    # 1 px of the border touch it and are dropped, whole dots near the border are kept
    for (u, v), grp in table.groupby(["u", "v"]):
        pos, _ = truth[(u, v)]
        def inside(m):
            return ((pos[:, 0] > m) & (pos[:, 0] < SHAPE[1] - 1 - m)
                    & (pos[:, 1] > m) & (pos[:, 1] < SHAPE[0] - 1 - m)).sum()
        assert inside(2.5) <= len(grp) <= inside(1.0)
    assert table["s"].min() > 1.0 and table["t"].min() > 1.0
    assert table["s"].max() < SHAPE[1] - 2.0 and table["t"].max() < SHAPE[0] - 2.0


def test_index_lattice_rotated_grid_with_missing_dots():
    rng = np.random.default_rng(4)
    ij = np.array([(i, j) for i in range(-5, 6) for j in range(-4, 5)], dtype=float)
    a = 0.3
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    pts = np.array([100.0, 80.0]) + 11.0 * ij @ rot.T + rng.normal(0, 0.1, ij.shape)
    keep = rng.random(len(pts)) > 0.1
    keep[np.flatnonzero((ij == 0).all(axis=1))] = True
    idx = index_lattice(pts[keep], (100.4, 79.7))
    reached = idx[:, 0] > -1000
    assert reached.mean() > 0.9
    np.testing.assert_array_equal(idx[reached], ij[keep][reached].astype(int))


def test_origin_far_from_any_dot_raises():
    pts = np.array([(i * 10.0 + 5, j * 10.0 + 5) for i in range(5) for j in range(5)])
    with pytest.raises(CalibrationError, match="optical-axis position"):
        index_lattice(pts, (10.0, 10.0))


def test_no_dots_raises():
    lf, _ = _card(0.0)
    lf.data[:] = 1.0
    with pytest.raises(CalibrationError, match="no dots"):
        dotcard_points(lf, spacing_mm=1.0, z_mm=0.0)


def test_index_dotcard_needs_columns():
    import pandas as pd
    with pytest.raises(ValueError, match="lacks column"):
        index_dotcard(pd.DataFrame({"u": [0.0]}), origin_st=(0, 0))
    assert len(segment_view(_render([(20.0, 20.0)], shape=(40, 40)))) == 1
