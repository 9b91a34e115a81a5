"""Pieces of one body tracked apart: which track pairs are merged, and where the merged
body stands, against the synthetic truth the tables are made from."""

import math

import numpy as np
import pandas as pd
import pytest

from plenoptrack.errors import SettingsError
from plenoptrack.pieces import merge_pieces, piece_pairs, track_velocities, union_diameter
from plenoptrack.track import TrackSettings, link_particles, track_particles

SIGMA = np.array([0.02, 0.02, 0.15])        # mm, per-point sigma (x, y, z)
FRAMES = np.arange(6)


def _points(track, start, velocity, diameter, rng, *, frames=FRAMES, sigma=SIGMA):
    """Rows of one track: truth ``start + velocity * frame`` plus noise of ``sigma``."""
    true = np.asarray(start) + np.outer(frames, velocity)
    noise = rng.standard_normal(true.shape) * sigma
    return pd.DataFrame({"frame": frames, "particle": track,
                         "x": true[:, 0] + noise[:, 0], "y": true[:, 1] + noise[:, 1],
                         "z": true[:, 2] + noise[:, 2],
                         "sigma_x": sigma[0], "sigma_y": sigma[1], "sigma_z": sigma[2],
                         "diameter": diameter, "major_axis": diameter, "minor_axis": diameter,
                         "flags": np.uint8(1)})


def _scene(seed=0, tracer_sigma=0.003):
    """A body of two pieces (tracks 0, 1) flying at about 1.2 mm per frame, a fragment
    that crosses it in frame 2 (track 2), and two touching tracers (tracks 3, 4) whose
    velocities differ by 0.05 mm per frame, measured with sigma ``tracer_sigma``.

    Returns the linked table, the body's centre per frame (the area-weighted centroid of
    its pieces) and the pieces' offsets from it."""
    rng = np.random.default_rng(seed)
    velocity = np.array([1.0, 0.6, -0.3])
    d = np.array([1.6, 1.0])
    area = d ** 2 / (d ** 2).sum()
    first = np.array([0.9, 0.0, 0.8])                 # piece 0 from piece 1, tilted in depth
    offsets = np.stack([first * (1 - area[0]), -first * area[0]])  # sum area * o = 0
    centre = np.outer(FRAMES, velocity)
    rows = [_points(p, offsets[p], velocity, d[p], rng) for p in (0, 1)]
    crossing = np.array([1.0, -2.0, 0.0])
    rows.append(_points(2, centre[2] - 2 * crossing, crossing, 1.2, rng))
    sigma = np.array([1.0, 1.0, 3.0]) * tracer_sigma
    rows.append(_points(3, [10.0, 0.0, 0.0], [0.5, 0.0, 0.0], 0.4, rng, sigma=sigma))
    rows.append(_points(4, [10.4, 0.0, 0.0], [0.55, 0.0, 0.0], 0.4, rng, sigma=sigma))
    return pd.concat(rows, ignore_index=True), centre, offsets


def test_pieces_that_touch_and_move_together_are_paired_and_nothing_else_is():
    linked, centre, _ = _scene()
    np.testing.assert_array_equal(piece_pairs(linked), [[0, 1]])
    # tracers 20 times less certain: their velocity difference is no longer resolved
    loose, _, _ = _scene(tracer_sigma=0.06)
    np.testing.assert_array_equal(piece_pairs(loose), [[0, 1], [3, 4]])
    # a track that moves with the body: paired when it touches it, not 3 mm away
    rng = np.random.default_rng(5)
    for gap, paired in ((0.0, True), (3.0, False)):
        start = np.array([0.0, -(0.8 + 0.5 + gap), 0.0])
        near = _points(5, start, [1.0, 0.6, -0.3], 1.0, rng)
        pairs = piece_pairs(pd.concat([linked, near], ignore_index=True)).tolist()
        assert ([0, 5] in pairs or [1, 5] in pairs) == paired
    # no touching allowed: nothing pairs
    assert len(piece_pairs(linked.assign(major_axis=0.0, diameter=0.0), touch_sigma=0.0)) == 0


def test_the_track_velocities_and_their_errors_are_those_of_a_weighted_line():
    linked, _, _ = _scene()
    v = track_velocities(linked)
    one = linked[linked["particle"] == 0]
    slope, cov = np.polyfit(one["frame"], one["z"], 1, w=1 / one["sigma_z"], cov="unscaled")
    assert v.loc[0, "velocity_z"] == pytest.approx(slope[0], rel=1e-9)
    assert v.loc[0, "sigma_vz"] == pytest.approx(math.sqrt(cov[0, 0]), rel=1e-9)
    assert v.loc[0, "sigma_vz"] == pytest.approx(0.15 / math.sqrt(17.5), rel=1e-9)


def test_without_sigmas_nothing_is_paired():
    linked, _, _ = _scene()
    assert len(piece_pairs(linked.drop(columns=["sigma_z"]))) == 0


def test_the_merged_body_stands_at_the_pieces_centroid_also_where_a_piece_was_missed():
    errors = []
    for seed in range(20):
        linked, centre, _ = _scene(seed)
        linked = linked[~((linked["particle"] == 1) & (linked["frame"] == 3))]  # missed once
        merged = merge_pieces(linked, piece_pairs(linked))
        body = merged[merged["pieces"] > 0].groupby("particle").filter(
            lambda g: g["pieces"].max() == 2)
        assert body["frame"].tolist() == FRAMES.tolist()
        assert body["pieces"].tolist() == [2, 2, 2, 1, 2, 2]
        for k, axis in enumerate("xyz"):
            errors.append((body[axis].to_numpy() - centre[:, k]) / body[f"sigma_{axis}"].to_numpy())
    z = np.concatenate(errors)
    # the sigmas are the fit's standard errors: about one unit of scatter, no bias
    assert 0.8 < z.std() < 1.2 and abs(z.mean()) < 0.2
    assert np.mean(np.abs(z) <= 1) == pytest.approx(0.68, abs=0.08)


def test_merging_keeps_the_other_tracks_and_renumbers_in_order_of_appearance():
    linked, _, _ = _scene()
    merged = merge_pieces(linked, np.array([[0, 1]]))
    assert merged["particle"].nunique() == 4
    assert sorted(merged["particle"].unique()) == [0, 1, 2, 3]
    assert (merged.groupby("particle").size() == 6).all()
    others = merged[merged["pieces"] == 1].sort_values(["frame", "x"]).reset_index(drop=True)
    kept = linked[linked["particle"] >= 2].sort_values(["frame", "x"]).reset_index(drop=True)
    pd.testing.assert_frame_equal(others[["frame", "x", "y", "z"]], kept[["frame", "x", "y", "z"]])
    assert len(merge_pieces(linked, np.zeros((0, 2), dtype=int))) == len(linked)
    assert linked["particle"].nunique() == 5         # the input is not changed


def test_the_merged_diameter_is_that_of_the_union_of_the_pieces_discs():
    linked, centre, offsets = _scene()
    merged = merge_pieces(linked, piece_pairs(linked))
    body = merged[merged["pieces"] == 2]
    expected = union_diameter(offsets[:, :2] + centre[0, :2], [1.6, 1.0])
    np.testing.assert_allclose(body["diameter"], expected, rtol=0.03)
    assert (body["diameter"] < math.hypot(1.6, 1.0)).all()     # the discs overlap
    assert body["flags"].dtype == np.uint8


def test_union_diameter_against_the_geometry_of_two_discs():
    assert union_diameter([[0, 0], [0, 0]], [2.0, 1.0]) == pytest.approx(2.0, rel=0.01)
    assert union_diameter([[0, 0], [5, 0]], [2.0, 2.0]) == pytest.approx(2 * math.sqrt(2), rel=0.01)
    # two unit discs one radius apart: union 2 pi - lens (2 pi / 3 - sqrt(3) / 2)
    lens = 2 * math.pi / 3 - math.sqrt(3) / 2
    expected = math.sqrt(4 * (2 * math.pi - lens) / math.pi)
    assert union_diameter([[0, 0], [1, 0]], [2.0, 2.0]) == pytest.approx(expected, rel=0.005)
    assert union_diameter([[0, 0]], [1.5]) == 1.5
    assert math.isnan(union_diameter(np.zeros((0, 2)), []))


def test_track_particles_merges_the_pieces_unless_told_not_to():
    linked, _, _ = _scene()
    linked = linked[linked["particle"] != 2]           # no crossing: linking is not at stake
    particles = linked.drop(columns=["particle"]).sample(frac=1.0, random_state=1)
    merged = track_particles(particles)
    apart = track_particles(particles, TrackSettings(merge_pieces=False))
    assert apart.n_pieces_merged == 0 and len(apart.statistics) == 4
    assert merged.n_pieces_merged == 1 and len(merged.statistics) == 3
    assert merged.summary()["tracks merged as pieces of one body"] == 1
    body = merged.tracks[merged.tracks["pieces"] == 2]
    assert body["speed"].iloc[0] == pytest.approx(np.linalg.norm([1.0, 0.6, -0.3]), rel=0.05)
    assert sorted(merged.statistics["pieces"]) == [1, 1, 2]
    assert len(link_particles(particles)) == len(particles)   # linking alone keeps every row


@pytest.mark.parametrize("field, value", [("piece_touch_sigma", -1.0),
                                          ("piece_touch_sigma", math.inf),
                                          ("piece_velocity_p", 0.0),
                                          ("piece_velocity_p", 1.0)])
def test_out_of_range_piece_settings_are_refused(field, value):
    with pytest.raises(SettingsError, match=field):
        TrackSettings(**{field: value})
    with pytest.raises(SettingsError):
        piece_pairs(_scene()[0], **{field.removeprefix("piece_"): value})


def test_a_frame_whose_only_piece_has_no_sigma_keeps_the_body_centre_without_one():
    linked, centre, _ = _scene(3)
    linked = linked[~((linked["particle"] == 1) & (linked["frame"] == 4))]
    only = (linked["particle"] == 0) & (linked["frame"] == 4)
    linked.loc[only, "sigma_z"] = np.nan                    # a singular solve: no sigma
    merged = merge_pieces(linked, np.array([[0, 1]]))
    body = merged[merged["particle"] == 0].set_index("frame")
    assert body.loc[4, "pieces"] == 1
    assert math.isnan(body.loc[4, "sigma_z"]) and np.isfinite(body.loc[4, "sigma_x"])
    # the lone point moved by its piece's offset (its mean residual in the other frames)
    piece = linked[linked["particle"] == 0].set_index("frame")["z"]
    offset = (piece.drop(index=4) - body["z"].drop(index=4)).mean()
    assert body.loc[4, "z"] == pytest.approx(piece.loc[4] - offset, abs=1e-12)
    assert offset == pytest.approx(0.8 * (1.0 - 1.6 ** 2 / (1.6 ** 2 + 1.0)), abs=0.1)
    assert np.isfinite(body["z"]).all() and np.isfinite(body.drop(index=4)["sigma_z"]).all()
