"""Triangulation through a DLFC fitted to the independent model of ``test_dlfc``."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from plenoptrack.errors import NoParticlesWarning
from plenoptrack.locate.dlfc import fit_dlfc
from plenoptrack.locate.triangulate import (FLAG_DESCRIPTIONS, TriangulationFlag, confidence,
                                            predict_detection, triangulate_cluster,
                                            triangulate_clusters)

try:
    from . import _previous as previous
    from .test_dlfc import PlenopticModel, dot_cards, views
except ImportError:  # tests/locate is not a package
    import _previous as previous
    from test_dlfc import PlenopticModel, dot_cards, views

F = TriangulationFlag


@pytest.fixture(scope="module")
def model():
    return PlenopticModel()


@pytest.fixture(scope="module")
def dlfc(model):
    return fit_dlfc(dot_cards(model), order=4)


def particle_detections(model, truth, *, noise_px, seed, view_radius=7):
    """Detections table of particles ``truth`` (K, 3) mm in every view, with noise."""
    u, v = views(view_radius)
    k = len(truth)
    lab = np.repeat(np.arange(k), len(u))
    uu, vv = np.tile(u, k), np.tile(v, k)
    s, t = model(truth[lab, 0], truth[lab, 1], truth[lab, 2], uu, vv)
    rng = np.random.default_rng(seed)
    return pd.DataFrame({"u": uu, "v": vv, "s": s + rng.normal(0, noise_px, s.shape),
                         "t": t + rng.normal(0, noise_px, t.shape), "cluster": lab})


def random_particles(n, seed):
    rng = np.random.default_rng(seed)
    truth = np.column_stack([rng.uniform(-25, 25, n), rng.uniform(-25, 25, n),
                             rng.uniform(-22, 22, n)])
    start = truth + rng.normal(0, [0.3, 0.3, 2.0], truth.shape)
    return truth, start


def test_recovers_positions_from_noisy_views(model, dlfc):
    truth, start = random_particles(100, seed=1)
    det = particle_detections(model, truth, noise_px=0.05, seed=2)
    res = triangulate_clusters(dlfc, det, start, n_possible_views=149)
    err = res.positions - truth
    assert np.all(res.flags & F.CONVERGED)
    assert np.abs(err[:, :2]).max() < 0.01 and np.abs(err[:, 2]).max() < 0.08
    assert np.sqrt(np.mean(err[:, 2] ** 2)) < 0.025
    # residuals at the noise level: |r| of isotropic noise has RMS sqrt(2) * 0.05
    assert np.median(res.residual_px) == pytest.approx(np.sqrt(2) * 0.05, rel=0.1)
    frame = res.to_frame()
    assert list(frame.columns[:10]) == ["cluster", "x", "y", "z", "sigma_x", "sigma_y",
                                        "sigma_z", "n_views", "residual_px", "mean_residual_px"]
    assert {"confidence", "flags"} <= set(frame.columns) and len(frame) == 100


def test_noise_free_is_exact_to_model_error(model, dlfc):
    truth, start = random_particles(20, seed=7)
    res = triangulate_clusters(dlfc, particle_detections(model, truth, noise_px=0.0, seed=0),
                               start)
    assert np.abs(res.positions - truth).max() < 0.01
    assert np.all(res.n_views == 149) and not np.any(res.flags & F.OUTLIERS_REMOVED)
    assert np.all(np.isnan(res.confidence))


def test_rejects_injected_outliers(model, dlfc):
    truth, start = random_particles(30, seed=11)
    det = particle_detections(model, truth, noise_px=0.05, seed=12)
    rng = np.random.default_rng(13)
    bad = np.concatenate([rng.choice(np.flatnonzero(det.cluster == k), 5, replace=False)
                          for k in range(30)])
    det.loc[bad, "s"] += rng.choice([-1, 1], len(bad)) * rng.uniform(3, 8, len(bad))
    res = triangulate_clusters(dlfc, det, start)
    assert not res.inliers[bad].any()
    assert np.all(res.flags & F.OUTLIERS_REMOVED)
    assert np.abs(res.positions - truth)[:, 2].max() < 0.08
    wrongly_dropped = (~res.inliers).sum() - len(bad)
    assert wrongly_dropped < 0.03 * len(det)
    clean = triangulate_clusters(dlfc, det, start, reject_k=np.inf)
    assert np.abs(clean.positions - truth)[:, 2].max() > 0.1     # outliers do bias it


def test_sigma_matches_empirical_scatter(model, dlfc):
    """Predicted sigma vs the scatter of 150 noise draws (one cluster per draw)."""
    points = np.array([[5.0, -8.0, 15.0], [-10.0, 4.0, -5.0]])
    n_draws = 150
    truth = np.repeat(points, n_draws, axis=0)
    det = particle_detections(model, truth, noise_px=0.05, seed=100)
    res = triangulate_clusters(dlfc, det, truth + [0.2, -0.2, 1.0], reject_k=np.inf)
    pos = res.positions.reshape(2, n_draws, 3)
    sig = res.sigma.reshape(2, n_draws, 3)
    scatter = pos.std(axis=1, ddof=1)
    predicted = sig.mean(axis=1)
    np.testing.assert_allclose(predicted, scatter, rtol=0.2)
    assert np.all(predicted[:, 2] > 10 * predicted[:, :2])     # depth is the weak axis


def test_scipy_solver_agrees(model, dlfc):
    truth, start = random_particles(8, seed=21)
    det = particle_detections(model, truth, noise_px=0.05, seed=22)
    a = triangulate_clusters(dlfc, det, start, solver="lm")
    b = triangulate_clusters(dlfc, det, start, solver="scipy")
    np.testing.assert_allclose(a.positions, b.positions, atol=1e-5)
    np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-4)


def test_single_cluster_and_too_few_views(model, dlfc):
    truth = np.array([3.0, 2.0, -10.0])
    u = np.array([-4.0, 0.0, 4.0])
    v = np.array([0.0, 3.0, -3.0])
    s, t = model(*truth, u, v)
    res = triangulate_cluster(dlfc, u, v, s, t, truth + [0.1, 0.1, 1.0])
    assert res.flags[0] & F.TOO_FEW_VIEWS and res.flags[0] & F.CONVERGED
    assert np.abs(res.positions[0] - truth).max() < 0.05 and res.inliers.all()
    one = triangulate_cluster(dlfc, u[:1], v[:1], s[:1], t[:1], truth)
    assert np.all(np.isnan(one.positions)) and one.flags[0] & F.TOO_FEW_VIEWS
    assert not one.flags[0] & F.CONVERGED and one.n_views[0] == 1
    two = triangulate_cluster(dlfc, u[:2], v[:2], s[:2], t[:2], truth + [0, 0, 0.5])
    assert np.isfinite(two.positions).all()


def test_single_view_cluster_is_singular(model, dlfc):
    """All centroids from one view: depth is unobservable, sigma is withheld."""
    u = v = np.zeros(6)
    s, t = model(1.0, 2.0, 3.0, u, v)
    res = triangulate_cluster(dlfc, u, v, s + 0.01 * np.arange(6), t, [1.0, 2.0, 5.0])
    assert res.flags[0] & F.SINGULAR and np.all(np.isnan(res.sigma))


def test_unassigned_rows_ignored_and_dataframe_start(model, dlfc):
    truth, start = random_particles(3, seed=31)
    det = particle_detections(model, truth, noise_px=0.03, seed=32)
    det["cluster"] = det.cluster * 10 + 5                  # labels 5, 15, 25
    det.loc[::7, "cluster"] = -1
    initial = pd.DataFrame(start, columns=["x", "y", "z"], index=[5, 15, 25])
    res = triangulate_clusters(dlfc, det, initial)
    assert res.clusters.tolist() == [5, 15, 25]
    assert not res.inliers[det.cluster.to_numpy() == -1].any()
    assert np.abs(res.positions - truth).max() < 0.1


def test_volume_edge_flag(model, dlfc):
    truth = np.array([[0.0, 0.0, 40.0]])                   # fitted z range is -25..25
    det = particle_detections(model, truth, noise_px=0.0, seed=0)
    res = triangulate_clusters(dlfc, det, truth)
    assert res.flags[0] & F.AT_VOLUME_EDGE
    assert set(FLAG_DESCRIPTIONS) == set(TriangulationFlag)


def test_confidence_formula_and_guard():
    c = confidence(100, 149, 0.05, 12.5, 50.0)
    assert c == pytest.approx((100 / 149) / (0.05 / 0.25))
    near_focus = confidence(100, 149, 0.05, np.array([0.0, -0.1, 2.5]), 50.0)
    assert np.all(near_focus == near_focus[-1])             # floored at 5 % of the depth
    assert confidence(100, 149, 0.0, 10.0, 50.0) == pytest.approx((100 / 149) / (1e-3 / 0.2))
    assert confidence(10, 149, 0.05, -12.5, 50.0) == pytest.approx(c / 10)


def test_predict_detection_broadcasts(model, dlfc):
    xyz = np.array([[1.0, 2.0, 3.0], [-4.0, 0.0, 10.0]])
    u, v = views(3)
    s, t = predict_detection(dlfc, xyz[:, None, :], u[None], v[None])
    assert s.shape == (2, len(u))
    ms, mt = model(xyz[:, None, 0], xyz[:, None, 1], xyz[:, None, 2], u[None], v[None])
    assert np.abs(s - ms).max() < 0.05 and np.abs(t - mt).max() < 0.05
    with pytest.raises(ValueError, match=r"xyz must have shape \(\.\.\., 3\)"):
        predict_detection(dlfc, [1.0, 2.0], u, v)


def test_argument_errors(dlfc):
    det = pd.DataFrame({"u": [0.0, 1.0], "v": [0.0, 0.0], "s": [1.0, 2.0], "t": [1.0, 1.0],
                        "cluster": [0, 0]})
    with pytest.raises(ValueError, match=r"lack column\(s\) \['cluster'\]"):
        triangulate_clusters(dlfc, det.drop(columns="cluster"), np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"initial_xyz must have shape \(1, 3\)"):
        triangulate_clusters(dlfc, det, np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"no row for cluster\(s\) \[0\]"):
        triangulate_clusters(dlfc, det, pd.DataFrame({"x": [0.0], "y": [0.0], "z": [0.0]},
                                                     index=[7]))
    with pytest.raises(ValueError, match="solver must be 'lm' or 'scipy'"):
        triangulate_clusters(dlfc, det, np.zeros((1, 3)), solver="gn")
    with pytest.raises(ValueError, match=r"initial position is NaN or infinite for cluster\(s\) \[0\]"):
        triangulate_clusters(dlfc, det, np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(ValueError, match="reject_k must be positive"):
        triangulate_clusters(dlfc, det, np.zeros((1, 3)), reject_k=0)
    with pytest.raises(ValueError, match="same length"):
        triangulate_cluster(dlfc, [0.0, 1.0], [0.0], [1.0, 2.0], [1.0, 2.0], [0, 0, 0])


def test_empty_input_warns(dlfc):
    det = pd.DataFrame({"u": [], "v": [], "s": [], "t": [], "cluster": []})
    with pytest.warns(NoParticlesWarning):
        res = triangulate_clusters(dlfc, det, np.zeros((0, 3)))
    assert len(res) == 0 and res.to_frame().shape == (0, 12)


def test_200_particles_all_converge_without_warnings(model, dlfc):
    truth, start = random_particles(200, seed=41)
    det = particle_detections(model, truth, noise_px=0.05, seed=42)
    triangulate_clusters(dlfc, det.iloc[:298], start[:2])          # warm up
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = triangulate_clusters(dlfc, det, start, n_possible_views=149)
    assert len(res) == 200 and np.all(res.flags & F.CONVERGED)


@pytest.mark.parametrize("solver", ["lm", "scipy"])
def test_rejection_rounds_match_the_previous_solve(model, dlfc, monkeypatch, solver):
    """Re-testing only the clusters solved in a round gives what re-testing every
    centroid in every round gave (``_previous.py``), to the bit."""
    import plenoptrack.locate.triangulate as triangulate_module

    n = 40 if solver == "lm" else 8
    results = {}
    for version in ("new", "previous"):
        with monkeypatch.context() as m:
            if version == "previous":
                m.setattr(triangulate_module, "_triangulate", previous._triangulate)
            runs = []
            for seed in range(3):
                truth, start = random_particles(n, seed=10 + seed)
                det = particle_detections(model, truth, noise_px=0.05, seed=seed)
                rng = np.random.default_rng(seed)
                bad = rng.random(len(det)) < 0.15              # outliers in most clusters
                det.loc[bad, ["s", "t"]] += rng.normal(0, 3.0, (bad.sum(), 2))
                det.loc[rng.random(len(det)) < 0.05, "cluster"] = -1
                det.loc[det["cluster"] == 3, "cluster"] = np.where(
                    np.arange((det["cluster"] == 3).sum()) < 2, 3, -1)   # a 2-view cluster
                runs.append(triangulate_clusters(dlfc, det, start, n_possible_views=149,
                                                 min_views=6, solver=solver))
            runs.append(triangulate_cluster(dlfc, det["u"][:60], det["v"][:60],
                                            det["s"][:60], det["t"][:60], start[0],
                                            solver=solver))
            results[version] = runs
    assert any(np.any(r.flags & F.OUTLIERS_REMOVED) for r in results["new"])
    for new, old in zip(results["new"], results["previous"], strict=True):
        for name in ("clusters", "positions", "sigma", "residual_px", "mean_residual_px",
                     "n_views", "confidence", "flags", "inliers"):
            assert np.array_equal(getattr(new, name), getattr(old, name), equal_nan=True), name
