"""The translation-stage uncertainty study: field, matching, slope-1 fit, statistics,
the end-to-end run (resumable) and the command."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from typer.testing import CliRunner

from plenoptrack import preset
from plenoptrack.cli import app
from plenoptrack.errors import SettingsError
from plenoptrack.io import read_table
from plenoptrack.study import (StudyConfig, binned_statistics, coarse_to_fine, depth_errors,
                               paper_grid, run_study, study_field, traverse_positions)


def _synthetic(n_particles=6, positions=np.arange(0, 21.0, 2.0), repeats=3, noise=0.1, seed=0):
    """Measurements of a rigid field: z = z0 + p + bias(p) + noise, lateral jitter."""
    rng = np.random.default_rng(seed)
    xy = np.column_stack([np.arange(n_particles) * 3.0, rng.uniform(-5, 5, n_particles)])
    z0 = rng.uniform(-3, 3, n_particles)
    rows = []
    for p in positions:
        for r in range(repeats):
            order = rng.permutation(n_particles)       # tables come in any order
            for i in order:
                rows.append({"position_mm": p, "repeat": r,
                             "x": xy[i, 0] + rng.normal(0, 0.01), "y": xy[i, 1] + rng.normal(0, 0.01),
                             "z": z0[i] + p + rng.normal(0, noise), "truth_id": i})
    return pd.DataFrame(rows), z0


def test_traverse_positions_and_coarse_to_fine_order():
    np.testing.assert_allclose(traverse_positions(50, 1), np.arange(51.0))
    np.testing.assert_allclose(traverse_positions(10, 2.5), [0, 2.5, 5, 7.5, 10])
    for n in (1, 2, 7, 51):
        order = coarse_to_fine(n)
        assert sorted(order) == list(range(n))
    # the first few cover the whole range
    first = coarse_to_fine(51)[:5]
    assert first.min() == 0 and first.max() >= 32


def test_depth_errors_match_particles_and_fit_slope_one():
    measured, z0 = _synthetic()
    errs = depth_errors(measured, match_mm=1.0)
    assert len(errs) == len(measured)
    # one matched identity per true particle
    pairs = errs.groupby("particle")["truth_id"].nunique()
    assert (pairs == 1).all() and errs["particle"].nunique() == len(z0)
    # the intercept is the mean of z - p, the residual its deviation (independent sums)
    for pid, g in errs.groupby("particle"):
        b = (g["z"] - g["position_mm"]).mean()
        np.testing.assert_allclose(g["intercept_mm"], b)
        np.testing.assert_allclose(g["error_mm"], g["z"] - g["position_mm"] - b)
        assert abs(b - z0[g["truth_id"].iat[0]]) < 0.05
    assert errs["error_mm"].std() == pytest.approx(0.1, rel=0.15)


def test_depth_errors_prefer_the_measurement_on_the_particles_line():
    measured, z0 = _synthetic()
    one = measured[(measured["truth_id"] == 2) & (measured["position_mm"] == 10.0)]
    # a ghost on particle 2's line of sight in every repeat of one position, nearer its
    # lateral position than its own measurement, 8 mm off in depth; and a lone outlier
    # (the particle's only measurement in its image) 2.5 mm off, inside the 3 mm depth
    # half-axis
    ghosts = one.assign(x=one["x"].mean(), y=one["y"].mean(), z=one["z"] - 8.0, truth_id=-2)
    measured.loc[one.index, "x"] += 0.3
    lone = ((measured["truth_id"] == 4) & (measured["position_mm"] == 4.0)
            & (measured["repeat"] == 1))
    measured.loc[lone, "z"] += 2.5
    errs = depth_errors(pd.concat([measured, ghosts], ignore_index=True), match_mm=1.0)
    assert (errs["truth_id"] != -2).all()                   # the ghosts lost to the particle
    assert len(errs) == len(measured)
    assert errs.groupby("particle")["truth_id"].nunique().max() == 1
    outlier = errs[(errs["truth_id"] == 4) & (errs["position_mm"] == 4.0) & (errs["repeat"] == 1)]
    assert outlier["error_mm"].iat[0] > 2.0                 # outliers stay in the statistics
    # a measurement beyond the depth half-axis is no particle's
    far = measured.copy()
    far.loc[lone, "z"] += 1.0
    assert len(depth_errors(far, match_mm=1.0)) == len(measured) - 1


def test_depth_errors_drop_particles_seen_at_few_positions():
    measured, _ = _synthetic()
    lone = pd.DataFrame({"position_mm": [0.0, 2.0], "repeat": [0, 0], "x": [100.0, 100.0],
                         "y": [0.0, 0.0], "z": [1.0, 3.0], "truth_id": [-1, -1]})
    errs = depth_errors(pd.concat([measured, lone], ignore_index=True), match_mm=1.0,
                        min_positions=3)
    assert (errs["truth_id"] >= 0).all()


def test_binned_statistics_against_independent_computation():
    measured, _ = _synthetic(n_particles=10, repeats=5)
    errs = depth_errors(measured, match_mm=1.0)
    bins = binned_statistics(errs, bin_mm=5.0, depth_limits_mm=(-10.0, 20.0), pitch_mm=0.154)
    k = np.floor(errs["depth_mm"] / 5.0 + 0.5)
    for _, row in bins.iterrows():
        e = errs["error_mm"][k == row["depth_mm"] / 5.0].to_numpy()
        assert row["n"] == len(e)
        assert row["mean_mm"] == pytest.approx(e.mean())
        assert row["std_mm"] == pytest.approx(e.std(ddof=1))
        lo, hi = stats.t.interval(0.99, len(e) - 1, loc=e.mean(), scale=stats.sem(e))
        assert (row["mean_lo_mm"], row["mean_hi_mm"]) == pytest.approx((lo, hi))
        assert row["std_lo_mm"] < row["std_mm"] < row["std_hi_mm"]
        want = row["depth_mm"] / (10.0 if row["depth_mm"] < 0 else 20.0)
        assert row["depth_norm"] == pytest.approx(want)
        assert row["std_norm"] == pytest.approx(row["std_mm"] / 0.154)


def test_std_bounds_cover_the_true_sigma_about_99_percent():
    rng = np.random.default_rng(3)
    n_trials = 1000
    errs = pd.DataFrame({"depth_mm": np.repeat(np.arange(n_trials, dtype=float), 12),
                         "error_mm": rng.normal(0, 0.3, 12 * n_trials)})
    b = binned_statistics(errs, bin_mm=1.0, depth_limits_mm=(-1, 1), pitch_mm=1.0)
    assert len(b) == n_trials
    covered = ((b["std_lo_mm"] <= 0.3) & (0.3 <= b["std_hi_mm"])).mean()
    assert 0.98 <= covered <= 1.0
    mean_covered = ((b["mean_lo_mm"] <= 0) & (0 <= b["mean_hi_mm"])).mean()
    assert 0.98 <= mean_covered <= 1.0


def test_study_field_is_rigid_pins_with_stems_behind_heads():
    cfg = StudyConfig(preset("small"), travel_mm=10, step_mm=1, n_particles=8, seed=4)
    field, offset = study_field(cfg)
    again, offset2 = study_field(cfg)
    pd.testing.assert_frame_equal(field, again)
    assert offset == offset2 and -1 <= offset <= 1
    heads = field[field["shape"] == "sphere"]
    stems = field[field["shape"] == "ellipsoid"]
    assert len(heads) == len(stems) == 8
    # stems point away from the camera, within 60 degrees of the axis, and touch the head
    assert (stems["axis_z"] >= np.cos(np.radians(60)) - 1e-12).all()
    d = np.hypot(np.hypot(stems["x"].to_numpy() - heads["x"].to_numpy(),
                          stems["y"].to_numpy() - heads["y"].to_numpy()),
                 stems["z"].to_numpy() - heads["z"].to_numpy())
    head_d = heads["diameter"].to_numpy()
    np.testing.assert_allclose(d, 0.45 * head_d + 2.0 * head_d)
    # the field at position 0 sits half the travel before the focal plane (plus offset)
    assert heads["z"].mean() == pytest.approx(-5 + offset, abs=cfg.field_depth_mm / 2)
    assert study_field(StudyConfig(preset("small"), travel_mm=10, step_mm=1, n_particles=8,
                                   seed=5))[0]["x"].iloc[0] != field["x"].iloc[0]


def test_paper_grid_has_twelve_configurations_with_matched_apertures():
    grid = paper_grid(preset("hall2019"))
    assert len(grid) == 12
    mags = sorted({abs(c.magnification) for c in grid})
    assert mags[-1] == 0.75 and len(mags) == 4
    for m in mags:   # three object distances at every magnification
        assert len({c.object_distance_mm for c in grid if abs(c.magnification) == m}) == 3
    for c in grid:   # microlens images filled: image-side f-number equals the microlenses'
        assert c.image_side_f_number == pytest.approx(c.microlens_f_number, rel=1e-3)
    labels = [StudyConfig(camera=c).label for c in grid]
    assert len(set(labels)) == 12 and "hall2019_M0.75_F105" in labels  # named once, not twice
    assert StudyConfig(camera=preset("hall2019")).label == (
        f"hall2019_M{abs(preset('hall2019').magnification):g}_F"
        f"{preset('hall2019').focal_length_mm:g}")


@pytest.mark.parametrize("kwargs, match", [
    ({"methods": ("perspective", "magic")}, "methods must be"),
    ({"repeats": 0}, "repeats must be at least 1"),
    ({"repeats": 2, "refocus_repeats": 3}, "refocus repeats"),
    ({"step_mm": 20.0, "travel_mm": 10.0}, "step <= travel"),
])
def test_study_settings_are_validated(kwargs, match):
    with pytest.raises(SettingsError, match=match):
        StudyConfig(preset("small"), **kwargs)


@pytest.fixture(scope="module")
def small_study(tmp_path_factory):
    out = tmp_path_factory.mktemp("study")
    cfg = StudyConfig(preset("small"), travel_mm=4, step_mm=2, repeats=2, refocus_repeats=1,
                      methods=("perspective", "refocus"), n_particles=6, field_depth_mm=1.0,
                      seed=2, realism="ideal")
    summary = run_study([cfg], out, workers=0, progress=False)
    return out, cfg, summary


def test_small_study_writes_summary_table_and_figures(small_study):
    out, cfg, summary = small_study
    s = json.loads((out / "summary.json").read_text())
    methods = s["configurations"][cfg.label]["methods"]
    assert set(methods) == {"perspective", "refocus"}
    assert methods["perspective"]["images"] == 3 * 2 and methods["refocus"]["images"] == 3
    assert methods["perspective"]["repeats"] == 2 and methods["refocus"]["repeats"] == 1
    p = methods["perspective"]
    assert p["matched_particles"] >= 5 and p["detections_per_position"] >= 5
    # perspective-shift depth errors on a 0.4 mm pin field: tenths of a millimetre
    assert p["worst_std_mm"] < 0.5 and p["worst_abs_mean_mm"] < 0.5
    assert p["seconds_per_image"] > 0 and p["peak_mb_per_image"] > 50
    for name in ("comparison.md", "bins.csv", "accuracy.png", "precision.png",
                 "precision_normalised.png"):
        assert (out / name).stat().st_size > 0
    table = (out / "comparison.md").read_text()
    assert "| perspective |" in table and "3600" in table


def test_small_study_resumes_without_redoing_images(small_study):
    out, cfg, _ = small_study
    images = sorted((out / cfg.label / "images").glob("*.parquet"))
    assert len(images) == 6
    before = {p.name: p.stat().st_mtime_ns for p in images}
    victim = images[1]   # a second repeat: its position is traced again, for it alone
    timing = ["seconds", "peak_mb"]
    first = read_table(victim).drop(columns=timing)
    victim.unlink()
    run_study([cfg], out, workers=0, progress=False)
    after = {p.name: p.stat().st_mtime_ns for p in (out / cfg.label / "images").glob("*.parquet")}
    assert set(after) == set(before)
    changed = [n for n in after if after[n] != before[n]]
    assert changed == [victim.name]
    # the same image, located the same way
    pd.testing.assert_frame_equal(read_table(victim).drop(columns=timing), first)


def test_study_command_refuses_unknown_method(tmp_path):
    result = CliRunner().invoke(app, ["study", "--preset", "small", "--out", str(tmp_path / "s"),
                                      "--methods", "perspective,magic"])
    assert result.exit_code == 2
    assert "methods must be" in result.stderr


def test_card_tilt_reaches_the_calibration_and_round_trips(tmp_path, monkeypatch):
    """StudyConfig.card_tilt is passed to calibrate, survives config.json, and a
    config.json written before the option existed loads with it off."""
    import plenoptrack.calibrate as calibrate_module
    import plenoptrack.calibration as calibration_module
    import plenoptrack.simulate as simulate_module
    from plenoptrack.study import _prepare

    seen = {}

    def fake_calibrate(white, dotcards, camera, **kwargs):
        seen.update(kwargs)
        return "calibration", None

    monkeypatch.setattr(simulate_module, "simulate_dataset", lambda *a, **k: None)
    monkeypatch.setattr(calibrate_module, "calibrate", fake_calibrate)
    monkeypatch.setattr(calibration_module, "save_calibration", lambda calib, path: None)
    for tilt in (True, False):
        config = StudyConfig(preset("small"), card_tilt=tilt)
        _prepare(tmp_path / str(tilt), config, None)
        assert seen["card_tilt"] is tilt
        assert StudyConfig.from_dict(json.loads(json.dumps(config.to_dict()))).card_tilt is tilt
    old = StudyConfig(preset("small")).to_dict()
    del old["card_tilt"]
    assert StudyConfig.from_dict(old).card_tilt is False
