import numpy as np
import pandas as pd
import pytest

from plenoptrack.evaluate import evaluate_particles, hidden_particles, match_particles


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


class _ShiftDLFC:
    """Stand-in calibration: ``s = 10 x + z u``, ``t = 10 y + z v`` (10 view pixels per mm
    laterally; the image moves by ``z`` view pixels per unit of ``u``)."""

    def view_basis(self, u, v):
        return np.column_stack([u, v]).astype(float)

    def predict_in_views(self, xyz, basis):
        xyz = np.reshape(xyz, (-1, 3))
        s = 10.0 * xyz[:, None, 0] + xyz[:, None, 2] * basis[None, :, 0]
        t = 10.0 * xyz[:, None, 1] + xyz[:, None, 2] * basis[None, :, 1]
        return np.stack([s, t], axis=-1)


_VIEWS = np.array([[u, v] for u in (-1.0, 0.0, 1.0) for v in (-1.0, 0.0, 1.0)])


def _scene(rows, frame=0):
    return pd.DataFrame(rows, columns=["x", "y", "z", "diameter"]).assign(frame=frame)


def test_hidden_behind_a_larger_image_in_every_view():
    # a 1 mm particle's image (radius 5 px) holds a 0.2 mm one's (radius 1 px) in every
    # view while their centres part by at most 2.8 sqrt 2 = 3.96 px (the corner views);
    # parting by 5 px frees it in some
    big_and_small = _scene([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 2.8, 0.2]])
    assert hidden_particles(big_and_small, _ShiftDLFC(), _VIEWS).tolist() == [False, True]
    apart = _scene([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 5.0, 0.2]])
    assert not hidden_particles(apart, _ShiftDLFC(), _VIEWS).any()
    # only the central view: 4.5 px off centre, its rim pokes out
    off_centre = _scene([[0.0, 0.0, 0.0, 1.0], [0.45, 0.0, 0.0, 0.2]])
    assert not hidden_particles(off_centre, _ShiftDLFC(), _VIEWS[[4]]).any()
    assert hidden_particles(off_centre.assign(x=[0.0, 0.35]), _ShiftDLFC(),
                            _VIEWS[[4]]).tolist() == [False, True]


def test_hidden_by_two_neighbours_together_not_by_another_frame():
    # two 1 mm images 6 px apart cover a 0.4 mm one (radius 2 px) between them, which
    # neither covers alone; in another frame they hide nothing
    trio = _scene([[-0.3, 0.0, 0.0, 1.0], [0.3, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.4]])
    assert hidden_particles(trio, _ShiftDLFC(), _VIEWS[[4]]).tolist() == [False, False, True]
    split = pd.concat([trio.iloc[:2], trio.iloc[2:].assign(frame=1)], ignore_index=True)
    assert not hidden_particles(split, _ShiftDLFC(), _VIEWS[[4]]).any()


def test_hidden_uses_the_silhouette_area():
    # an ellipsoid's silhouette larger than its volume-equivalent sphere's hides more
    pair = _scene([[0.0, 0.0, 0.0, 0.5], [0.15, 0.0, 0.0, 0.2]])
    assert not hidden_particles(pair, _ShiftDLFC(), _VIEWS[[4]]).any()
    wide = pair.assign(projected_area=[np.pi * 0.4 ** 2, np.pi * 0.1 ** 2])
    assert hidden_particles(wide, _ShiftDLFC(), _VIEWS[[4]]).tolist() == [False, True]
