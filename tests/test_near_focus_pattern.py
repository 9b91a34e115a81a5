"""The pieces of ``benchmarks/near_focus_pattern.py`` that its numbers rest on."""

import numpy as np
import pytest


@pytest.fixture(scope="module")
def script(benchmark_module):
    with benchmark_module("near_focus_pattern") as module:
        yield module


def test_lattice_share_finds_a_pattern_that_repeats_with_the_lattice(script):
    steps, step, repeat = 24, 0.014, 0.154
    x = np.arange(steps) * step
    pattern = 0.06 * np.sin(2 * np.pi * x / repeat + 0.4) + 0.02 * np.cos(4 * np.pi * x / repeat)
    assert script.lattice_share(pattern + 0.3, step, repeat) == pytest.approx(1.0)
    rng = np.random.default_rng(1)
    shares = [script.lattice_share(rng.normal(size=steps), step, repeat) for _ in range(200)]
    assert np.mean(shares) < 0.3            # 4 of 23 degrees of freedom: about 0.17
    noisy = pattern + rng.normal(0, 0.01, steps)
    assert 0.8 < script.lattice_share(noisy, step, repeat) < 1.0
    assert np.isnan(script.lattice_share(np.full(5, 1.0), step, repeat))


@pytest.mark.parametrize("axis", ["x", "y"])
def test_scene_steps_along_the_axis_and_lines_cross_the_cell(script, axis):
    from plenoptrack.simulate.scene import Volume

    volume = Volume((-5.0, 5.0), (-3.0, 3.0), (-10.0, 10.0))
    depths = (-2.0, -1.0, 1.0, 2.0)
    truth = script.scene_truth(volume, 0.4, depths, steps=6, step_mm=0.01, repeats=2,
                               seed=0, axis=axis, lines=3, across_mm=0.3)
    assert truth["frame"].nunique() == 3 * 2 * 6 and len(truth) == 3 * 2 * 6 * len(depths)
    assert truth["particle"].is_unique
    other = "y" if axis == "x" else "x"
    first = truth[(truth.line == 0) & (truth.step == 0) & (truth.repeat == 0)].set_index("slot")
    for _, row in truth.iterrows():
        start = first.loc[row.slot]
        assert row[axis] == pytest.approx(start[axis] + 0.01 * row.step)
        assert row[other] == pytest.approx(start[other] + 0.1 * row.line)
        assert row.z == start.z
    inside = truth[["x", "y"]].abs().to_numpy() < [5.0, 3.0]
    assert inside.all()
