"""The pieces of ``benchmarks/separability.py`` that its bounds rest on."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def script(benchmark_module):
    with benchmark_module("separability") as module:
        yield module


def test_group_share_counts_chains_of_pairs_as_one(script):
    assert script.group_share(np.zeros((0, 2), dtype=int), 5) == 1.0
    # 0-1-2 one group, 3 and 4 alone: 3 groups of 5
    assert script.group_share(np.array([[0, 1], [1, 2]]), 5) == pytest.approx(0.6)
    assert np.isnan(script.group_share(np.zeros((0, 2), dtype=int), 0))


def test_frame_bounds_tell_touching_images_from_coinciding_centres(script):
    """A and B touch in every view but their centres stay more than a radius apart; B and
    C stay within a radius of each other in every view; D is far away."""
    views = 4
    a = np.zeros((views, 2))
    b = a + np.array([[1.5, 0.0], [1.5, 0.0], [1.8, 0.0], [1.8, 0.0]])   # radius 1 and 1
    c = b + np.array([0.5, 0.0])                                          # within a radius
    d = a + np.array([0.0, 10.0])                                         # far away
    centres = np.stack([a, b, c, d])
    radius = np.ones(4)
    xy = np.array([[0.0, 0.0], [0.1, 0.0], [0.15, 0.0], [0.0, 5.0]])
    # touch: a-b (< 2 in every view), b-c, not a-c (2.0-2.3) -> {a, b, c}, {d}: 2 / 4
    # core: only b-c (< 1 in every view) -> {a}, {b, c}, {d}: 3 / 4
    bounds = script.frame_bounds(centres, radius, xy, reach_mm=1.0)
    assert bounds == {"touch": pytest.approx(0.5), "core": pytest.approx(0.75)}
    # pairs beyond the lateral reach are never compared
    assert script.frame_bounds(centres, radius, xy, reach_mm=0.01) == {"touch": 1.0, "core": 1.0}
