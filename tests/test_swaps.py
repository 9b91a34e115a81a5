"""Tracks that took each other's particles: the exchange of their tails, against the
synthetic truth the tables are made from."""

import numpy as np
import pandas as pd
import pytest

from plenoptrack.swaps import SWAP_MIN_GAIN, repair_swaps, track_chi2
from plenoptrack.track import TrackSettings, track_particles

SIGMA = np.array([0.03, 0.03, 0.3])


def _track(truth_id, start, velocity, frames, rng, sigma=SIGMA):
    true = np.asarray(start) + np.outer(frames, velocity)
    noisy = true + rng.standard_normal(true.shape) * sigma
    return pd.DataFrame({"frame": frames, "truth": truth_id, "x": noisy[:, 0],
                         "y": noisy[:, 1], "z": noisy[:, 2], "sigma_x": sigma[0],
                         "sigma_y": sigma[1], "sigma_z": sigma[2]})


def _crossing(seed=0):
    """Two fragments whose paths pass 0.3 mm apart at frame 3, and a third far away;
    ``particle`` holds the truth (tracks 0, 1, 2)."""
    rng = np.random.default_rng(seed)
    frames = np.arange(7)
    a = _track(0, [0.0, 0.0, 0.0], [1.5, 0.2, 0.5], frames, rng)
    b = _track(1, [0.0, 1.2, 1.5], [1.5, -0.3, 0.0], frames, rng)
    c = _track(2, [20.0, 0.0, 0.0], [-1.0, 0.0, 0.0], frames, rng)
    table = pd.concat([a, b, c], ignore_index=True)
    return table.assign(particle=table["truth"])


def test_swapped_tails_are_exchanged_back():
    true = _crossing()
    swapped = true.copy()
    late = swapped["frame"] >= 4
    swapped.loc[late & (swapped["truth"] == 0), "particle"] = 1
    swapped.loc[late & (swapped["truth"] == 1), "particle"] = 0
    repaired, n = repair_swaps(swapped, search_range_mm=(1.0, 3.0), degree=1,
                                 window=7)
    assert n == 1
    assert (repaired.groupby("particle")["truth"].nunique() == 1).all()
    assert swapped["particle"].tolist() != repaired["particle"].tolist()   # input kept
    pd.testing.assert_frame_equal(repaired.drop(columns="particle"),
                                  swapped.drop(columns="particle"))


def test_right_tracks_are_left_alone():
    for seed in range(10):
        true = _crossing(seed)
        repaired, n = repair_swaps(true, search_range_mm=(1.0, 3.0), degree=1,
                                 window=7)
        assert n == 0 and repaired["particle"].tolist() == true["particle"].tolist()


def test_a_track_too_short_to_fit_takes_no_points():
    # a four-point track that zigzags (its middle points 7 sigma off) beside a two-point
    # track: exchanged at frame 2 both would hold three points, too few for a quadratic,
    # and the zigzag would vanish from the sum for free
    rng = np.random.default_rng(1)
    kinked = _track(0, [0.0, 0.0, 0.0], [1.5, 0.0, 0.0], np.arange(4), rng)
    kinked.loc[1, "x"] += 0.2
    kinked.loc[2, "x"] -= 0.2
    short = _track(1, [0.0, 0.5, 0.0], [1.5, 0.0, 0.0], np.array([1, 2]), rng)
    table = pd.concat([kinked, short], ignore_index=True)
    table = table.assign(particle=table["truth"])
    assert track_chi2(kinked["frame"], kinked[["x", "y", "z"]].to_numpy(),
                      kinked[["sigma_x", "sigma_y", "sigma_z"]].to_numpy(), degree=2,
                      cap=np.inf) > SWAP_MIN_GAIN
    _, n = repair_swaps(table, search_range_mm=(1.0, 3.0), degree=2, window=7,
                        clip=0.0)
    assert n == 0


def test_without_sigmas_the_table_comes_back_as_it_is():
    table = _crossing().drop(columns="sigma_z")
    repaired, n = repair_swaps(table, search_range_mm=(1.0, 3.0), degree=1,
                                 window=7)
    assert n == 0 and repaired is table


def test_the_chi_square_of_a_track():
    frames = np.arange(5)
    xyz = np.c_[frames * 1.0, np.zeros(5), [0.0, 0.1, -0.1, 0.1, 0.0]]
    sigma = np.full((5, 3), 0.1)
    z = xyz[:, 2]
    coef = np.polyfit(frames, z, 1, w=np.full(5, 10.0))
    expected = (((z - np.polyval(coef, frames)) / 0.1) ** 2).sum()
    assert track_chi2(frames, xyz, sigma, degree=1, cap=np.inf) == pytest.approx(expected)
    # each point's term capped; too few points for the degree: no chi-square
    assert track_chi2(frames, xyz, sigma, degree=1, cap=0.5) <= 5 * 0.5
    assert track_chi2(frames[:2], xyz[:2], sigma[:2], degree=1, cap=np.inf) == 0.0
    assert SWAP_MIN_GAIN == pytest.approx(9.21, abs=0.01)


def test_track_particles_repairs_unless_told_not_to():
    true = _crossing()
    points = true.drop(columns="particle")
    on = track_particles(points, TrackSettings(order=1, window=5))
    off = track_particles(points, TrackSettings(order=1, window=5, repair_swaps=False))
    assert off.n_swaps_repaired == 0
    assert on.summary()["track tails exchanged (swapped particles)"] == on.n_swaps_repaired
    for result in (on, off):
        assert (result.tracks.groupby("particle")["truth"].nunique() == 1).all()


def test_sigma_scale_is_the_scatter_the_sigmas_understate():
    from plenoptrack.swaps import sigma_scale

    rng = np.random.default_rng(4)
    frames = np.arange(30)
    tracks = {}
    for k in range(40):
        xyz = np.outer(frames, [1.0, 0.5, -0.2]) + rng.standard_normal((30, 3)) * SIGMA
        tracks[k] = {"frames": frames, "xyz": xyz, "sigma": np.tile(SIGMA / 3, (30, 1))}
    np.testing.assert_allclose(sigma_scale(tracks), 3.0, rtol=0.1)
    for track in tracks.values():
        track["sigma"] = np.tile(SIGMA * 2, (30, 1))      # larger than the scatter: kept
    np.testing.assert_array_equal(sigma_scale(tracks), 1.0)
