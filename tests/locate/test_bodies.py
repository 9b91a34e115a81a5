"""Pieces of one body merged back (plenoptrack.locate.bodies, check.merge_pieces)."""

import numpy as np
import pandas as pd
import pytest

from plenoptrack.locate.bodies import merge_bodies, one_body_pairs, parallax_px
from plenoptrack.locate.perspective import PARTICLE_COLUMNS
from plenoptrack.locate.settings import PerspectiveLocator


def _images(xyz, n_views=25, parallax_per_mm=2.0, px_per_mm=5.0):
    """Image centres (N, V, 2) of particles at ``xyz`` in a square of views: lateral
    position times ``px_per_mm`` plus a view offset growing with depth (the parallax)."""
    uv = np.stack(np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5)), -1).reshape(-1, 2)
    uv = uv[:n_views]
    xyz = np.asarray(xyz, dtype=float)
    return (xyz[:, None, :2] * px_per_mm + xyz[:, None, 2:3] * parallax_per_mm * uv[None])


def test_parallax_is_zero_at_one_depth_and_grows_with_the_depth_difference():
    pred = _images([[0, 0, 1.0], [0.3, 0, 1.0], [0.3, 0, 2.0]])
    assert parallax_px(pred[0] - pred[1]) == pytest.approx(0.0, abs=1e-12)
    # offsets spread over views at +-1 (var 0.5 per axis): sqrt(8 * 2 * 0.5 * 2**2) = 5.66
    assert parallax_px(pred[0] - pred[2]) == pytest.approx(np.sqrt(8 * 2 * 0.5 * 4.0))


def test_pieces_of_one_body_pair_but_neighbours_and_lines_of_sight_do_not():
    xyz = np.array([[0.0, 0.0, 1.0],      # 0: a body
                    [0.5, 0.0, 1.0],      # 1: a piece of it (centres 0.5 < 0.4 + 0.2)
                    [0.0, 0.3, 3.0],      # 2: behind 0 on nearly its line of sight
                    [5.0, 0.0, 1.0],      # 3: a second body ...
                    [5.7, 0.0, 1.0]])     # 4: ... and its neighbour, touching (0.7 > 0.6)
    diameter = np.array([0.8, 0.4, 0.8, 0.8, 0.4])
    pairs = one_body_pairs(xyz, diameter, _images(xyz))
    np.testing.assert_array_equal(pairs, [[0, 1]])
    # the same two pieces one depth step apart in the images move apart: no pair
    moved = xyz.copy()
    moved[1, 2] = 1.25
    assert len(one_body_pairs(moved, diameter, _images(moved))) == 0
    # an unknown diameter never pairs
    assert len(one_body_pairs(xyz, np.array([0.8, np.nan, 0.8, 0.8, 0.4]), _images(xyz))) == 0


def _table(rows):
    base = {c: 0.0 for c in PARTICLE_COLUMNS}
    table = pd.DataFrame([base | r for r in rows])[list(PARTICLE_COLUMNS)]
    table["n_views"] = table["n_views"].astype(np.int64)
    table["flags"] = table["flags"].astype(np.uint8)
    return table


def test_merged_piece_is_the_joined_silhouette():
    table = _table([
        {"x": 0.0, "y": 0.0, "z": 1.0, "sigma_x": 0.03, "sigma_y": 0.03, "sigma_z": 0.4,
         "diameter": 1.6, "n_views": 80, "flags": 33, "major_axis": 1.8, "minor_axis": 1.5},
        {"x": 5.0, "y": 5.0, "z": 2.0, "diameter": 0.5, "n_views": 50, "flags": 1},
        {"x": 1.2, "y": 0.0, "z": 1.4, "sigma_x": 0.04, "sigma_y": 0.04, "sigma_z": 0.8,
         "diameter": 1.2, "n_views": 60, "flags": 65, "major_axis": 1.3, "minor_axis": 0.9}])
    merged, new_row = merge_bodies(table, np.array([[0, 2]]))
    np.testing.assert_array_equal(new_row, [0, 1, 0])
    assert len(merged) == 2
    w = np.array([1.6 ** 2, 1.2 ** 2]) / (1.6 ** 2 + 1.2 ** 2)       # 0.64, 0.36
    one = merged.loc[0]
    assert one["x"] == pytest.approx(w[1] * 1.2)
    assert one["z"] == pytest.approx(w[0] * 1.0 + w[1] * 1.4)
    assert one["diameter"] == pytest.approx(2.0)                     # sqrt(1.6^2 + 1.2^2)
    assert one["sigma_z"] == pytest.approx(np.hypot(w[0] * 0.4, w[1] * 0.8))
    assert one["flags"] == 33 | 65 and one["n_views"] == 80
    assert np.isnan(one["orientation"]) and np.isnan(one["chi2"])
    pd.testing.assert_series_equal(merged.loc[1], table.loc[1], check_names=False)
    assert merged["flags"].dtype == np.uint8 and merged["n_views"].dtype == np.int64


def test_chains_of_pieces_become_one_particle():
    table = _table([{"x": float(i), "y": 0.0, "z": 0.0, "diameter": 1.0, "n_views": 10}
                    for i in range(4)])
    merged, new_row = merge_bodies(table, np.array([[0, 1], [1, 2]]))
    np.testing.assert_array_equal(new_row, [0, 0, 0, 1])
    assert merged["x"].tolist() == pytest.approx([1.0, 3.0])
    assert merged.loc[0, "diameter"] == pytest.approx(np.sqrt(3.0))


def test_merge_pieces_setting_round_trips():
    assert PerspectiveLocator().check.merge_pieces is True
    off = PerspectiveLocator.from_dict({"check": {"merge_pieces": False}})
    assert off.check.merge_pieces is False
