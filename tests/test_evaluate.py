import numpy as np
import pandas as pd
import pytest

from plenoptrack.evaluate import evaluate_particles, match_particles


def _truth(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return pd.DataFrame({"frame": np.repeat([0, 1], n // 2),
                         "x": rng.uniform(-10, 10, n), "y": rng.uniform(-10, 10, n),
                         "z": rng.uniform(-25, 25, n)})


def test_perfect_measurement_shuffled():
    truth = _truth()
    measured = truth.sample(frac=1.0, random_state=3).reset_index(drop=True)
    ev = evaluate_particles(measured, truth, tolerance_mm=0.5)
    assert (ev.recall, ev.precision) == (1.0, 1.0)
    assert ev.rms_error_lateral == pytest.approx(0.0, abs=1e-12)


def test_errors_statistics_match_independent_computation():
    truth = _truth(200, seed=1)
    rng = np.random.default_rng(2)
    measured = truth.copy()
    measured["z"] += 0.1 + rng.normal(0, 0.2, len(truth))
    measured["x"] += rng.normal(0, 0.03, len(truth))
    measured = measured.drop(index=[0, 1, 2])                      # three missed
    extra = pd.DataFrame({"frame": [0, 1], "x": [50.0, 60.0], "y": [0.0, 0.0], "z": [0.0, 0.0]})
    measured = pd.concat([measured, extra], ignore_index=True)     # two false positives
    ev = evaluate_particles(measured, truth, tolerance_mm=1.5)
    assert ev.n_matched == 197
    assert ev.recall == pytest.approx(197 / 200)
    assert ev.precision == pytest.approx(197 / 199)
    dz = (measured.iloc[:197]["z"].to_numpy() - truth.iloc[3:]["z"].to_numpy())
    assert ev.mean_error_z == pytest.approx(dz.mean())
    assert ev.std_error_z == pytest.approx(dz.std(ddof=1))


def test_one_to_one_and_frames_are_separate():
    truth = pd.DataFrame({"frame": [0, 1], "x": [0.0, 0.0], "y": [0.0, 0.0], "z": [0.0, 0.0]})
    # two measurements near the frame-0 particle, none in frame 1
    measured = pd.DataFrame({"frame": [0, 0], "x": [0.1, 0.05], "y": [0.0, 0.0], "z": [0.0, 0.0]})
    pairs = match_particles(measured, truth, tolerance_mm=1.0)
    assert len(pairs) == 1 and pairs.loc[0, "measured_index"] == 1
    ev = evaluate_particles(measured, truth)
    assert ev.recall == 0.5 and ev.precision == 0.5


def test_optimal_not_greedy():
    # greedy nearest-first would pair m0-t1 (0.4) and leave t0 unmatched within tolerance
    truth = pd.DataFrame({"x": [0.0, 1.0], "y": [0.0, 0.0], "z": [0.0, 0.0]})
    measured = pd.DataFrame({"x": [0.6, 1.7], "y": [0.0, 0.0], "z": [0.0, 0.0]})
    assert len(match_particles(measured, truth, tolerance_mm=0.8)) == 2


def test_empty_measurement():
    ev = evaluate_particles(pd.DataFrame({"x": [], "y": [], "z": []}), _truth())
    assert ev.recall == 0.0 and np.isnan(ev.mean_error_z)
    assert ev.to_dict()["mean_error_z"] is None


def test_missing_columns():
    with pytest.raises(ValueError, match=r"measured table has no column\(s\) \['z'\]"):
        evaluate_particles(pd.DataFrame({"x": [1.0], "y": [1.0]}), _truth())
