"""Tests of dot-card detection and grid indexing."""

from types import SimpleNamespace

import numpy as np
import pytest

from plenoptrack.errors import CalibrationError
from plenoptrack.locate.dotcards import (DOTCARD_COLUMNS, CardLattice, card_lattice,
                                         consistent_origins, dotcard_points, fit_lattice,
                                         index_dotcard, index_lattice)
from plenoptrack.locate.segment import segment_array, segment_view

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
    assert list(table.columns) == list(DOTCARD_COLUMNS)
    assert list(DOTCARD_COLUMNS) == ["u", "v", "s", "t", "x", "y", "z", "i", "j", "darkness",
                                     "dark_area"]
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


def _rotated_lattice(seed=4, angle=0.3, spacing=11.0, centre=(100.0, 80.0)):
    rng = np.random.default_rng(seed)
    ij = np.array([(i, j) for i in range(-5, 6) for j in range(-4, 5)], dtype=float)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    pts = np.asarray(centre) + spacing * ij @ rot.T + rng.normal(0, 0.1, ij.shape)
    return pts, ij.astype(int)


@pytest.mark.parametrize("offset", [(0.0, 0.0), (3.5, -2.0), (-4.0, 3.0)])
def test_index_lattice_origin_dot_not_detected(offset):
    """Dot (0, 0) missing from the detections: (0, 0) is still the node at the axis.

    The old indexing started at the detected dot nearest the predicted axis and stopped
    when none was within half a spacing (seed 7105 of 'small', where the segmentation
    dropped the axis dot of one card as too eccentric).
    """
    pts, ij = _rotated_lattice()
    keep = ~(ij == 0).all(axis=1)
    origin = np.array([100.0, 80.0]) + offset      # up to 0.45 spacings off the node
    idx = index_lattice(pts[keep], origin)
    np.testing.assert_array_equal(idx, ij[keep])
    # and with the axis dot and its four neighbours all missing
    keep &= np.abs(ij).sum(axis=1) > 1
    np.testing.assert_array_equal(index_lattice(pts[keep], origin), ij[keep])


def test_index_lattice_origin_in_a_gap_between_dots():
    """The axis may fall between detected dots: (0, 0) is the lattice node nearest it."""
    pts = np.array([(i * 10.0 + 5, j * 10.0 + 5) for i in range(5) for j in range(5)])
    idx = index_lattice(pts, (23.0, 36.0))              # nearest node (25, 35)
    np.testing.assert_array_equal(idx[(pts == (25.0, 35.0)).all(axis=1)], [[0, 0]])
    np.testing.assert_array_equal(idx - idx[0], np.array([(i, j) for i in range(5)
                                                           for j in range(5)]))
    # far outside the card, the index is extrapolated along the lattice
    idx = index_lattice(pts, (-35.0, 5.0))
    np.testing.assert_array_equal(idx[0], [4, 0])


def test_index_lattice_keeps_the_largest_connected_set():
    pts, ij = _rotated_lattice()
    stray = np.array([[101.5, 84.5]])                  # a speck between lattice dots
    idx = index_lattice(np.vstack([stray, pts]), (101.0, 84.0))
    assert idx[0, 0] == np.iinfo(np.int32).min          # not part of the lattice
    np.testing.assert_array_equal(idx[1:], ij)


def test_fit_lattice_extrapolates_to_missing_node():
    pts, ij = _rotated_lattice()
    keep = ~(ij == 0).all(axis=1)
    origin, basis = fit_lattice(pts[keep], ij[keep])
    np.testing.assert_allclose(origin, (100.0, 80.0), atol=0.1)
    np.testing.assert_allclose(np.hypot(*basis), [11.0, 11.0], atol=0.05)
    with pytest.raises(CalibrationError, match="cannot fit a dot lattice"):
        fit_lattice(pts[:2], ij[:2])


def test_index_dotcard_origin_dot_missing_in_central_view():
    """Dots of a whole card indexed right when dot (0, 0) is not found in the centre view."""
    lf, truth = _card(-1.5)
    det = segment_array(lf.data, lf.u, lf.v, view_mask=lf.view_mask,
                        spatial_mask=lf.spatial_mask, max_eccentricity=0.8)
    centre = (det["u"] == 0) & (det["v"] == 0)
    at_axis = np.hypot(det["s"] - AXIS[0], det["t"] - AXIS[1]) < 3
    assert (centre & at_axis).sum() == 1
    table = index_dotcard(det[~(centre & at_axis)], origin_st=AXIS, parallax_per_u=-1.5)
    table = table.assign(x=table["i"] * 1.0, y=table["j"] * 1.0)
    _check_against_truth(table, truth, 1.0)
    assert len(table) > 0.95 * len(det)


def test_index_dotcard_refuses_aliased_prediction():
    lf, _ = _card(0.0)
    det = segment_array(lf.data, lf.u, lf.v, view_mask=lf.view_mask,
                        spatial_mask=lf.spatial_mask)
    with pytest.raises(CalibrationError, match="more than half the dot spacing"):
        index_dotcard(det, origin_st=AXIS, parallax_per_u=5.0)   # spacing 9 px


@pytest.mark.parametrize("parallax", [0.0, -2.5])
def test_card_lattice_measures_parallax_and_origin(parallax):
    lf, _ = _card(parallax, angle=0.03)
    table = dotcard_points(lf, spacing_mm=1.0, z_mm=0.0, parallax_per_u=parallax)
    lat = card_lattice(table)
    np.testing.assert_allclose(lat.parallax, parallax * np.eye(2), atol=0.01)
    assert lat.parallax_per_u == pytest.approx(parallax, abs=0.01)
    np.testing.assert_allclose(lat.origin_st, AXIS, atol=0.05)
    np.testing.assert_allclose(lat.spacing_px, 9.0, atol=0.02)
    assert lat.rms_px < 0.1
    # the same without dot (0, 0) in any view, and with indices shifted by one dot
    other = table[(table["i"] != 0) | (table["j"] != 0)].assign(i=lambda d: d["i"] + 1)
    shifted = card_lattice(other)
    np.testing.assert_allclose(shifted.origin_st, AXIS - lat.basis[:, 0], atol=0.05)


def _lattices(origins, scales, spacing=9.0):
    return [CardLattice(origin_st=np.asarray(o, float), basis=spacing * k * np.eye(2),
                        parallax=np.zeros((2, 2)), n_dots=100, rms_px=0.05)
            for o, k in zip(origins, scales)]


def test_consistent_origins_reindexes_a_card_a_step_off():
    scales = np.linspace(0.97, 1.03, 6)
    origins = [(40.0, 30.0)] * 6
    origins[2] = (40.0 - 9.0 * scales[2], 30.0)        # its (0, 0) is the dot at i = -1
    origins[4] = (40.02, 30.0 + 9.0 * scales[4])       # its (0, 0) is the dot at j = +1
    c = consistent_origins(_lattices(origins, scales), origin_st=(41.0, 31.0))
    np.testing.assert_allclose(c.axis_st, (40.0, 30.0), atol=0.02)
    expected = np.zeros((6, 2), int)
    expected[2], expected[4] = (1, 0), (0, -1)
    np.testing.assert_array_equal(c.shifts, expected)
    assert c.n_agree == 4 and c.miss.max() < 0.01


def test_consistent_origins_tie_goes_to_the_predicted_axis():
    origins = [(40.0, 30.0), (49.0, 30.0), (40.0, 30.0), (49.0, 30.0)]
    c = consistent_origins(_lattices(origins, [1.0] * 4), origin_st=(47.0, 30.0))
    np.testing.assert_allclose(c.axis_st, (49.0, 30.0))
    np.testing.assert_array_equal(c.shifts[:, 0], [1, 0, 1, 0])  # their dot i = 1


def test_consistent_origins_flags_a_card_off_the_lattice():
    origins = [(40.0, 30.0)] * 4 + [(44.5, 30.0)]       # half a spacing sideways
    c = consistent_origins(_lattices(origins, [1.0] * 5), origin_st=(40.0, 30.0))
    assert c.miss[:4].max() == 0 and c.miss[4] == pytest.approx(0.5)


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
