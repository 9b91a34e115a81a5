"""The ``plenoptrack`` commands calibrate -> locate -> evaluate, and the demo."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import tifffile
from typer.testing import CliRunner

from plenoptrack.cli import app
from plenoptrack.evaluate import evaluate_particles
from plenoptrack.calibration import file_sha256
from plenoptrack.io import read_table
from plenoptrack.locate.perspective import PARTICLE_COLUMNS

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def ok(*args):
    result = run(*args)
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    return result


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli_locate")
    sim = root / "sim"
    ok("simulate", "--preset", "small", "--seed", 1, "--particles", 12, "--frames", 2,
       "--optics", "realistic", "--out", sim)
    ok("calibrate", "--white", sim / "white.tif", "--dotcards", sim / "dotcards",
       "--camera", sim / "camera.toml", "--out", root / "calib.json")
    return root, sim


def test_locate_then_evaluate_against_truth(calibrated):
    root, sim = calibrated
    frames = sorted((sim / "raw").glob("frame_*.tif"))
    out = root / "particles.csv"
    ok("locate", *frames, "--calib", root / "calib.json", "--out", out)
    particles = read_table(out)
    assert list(particles.columns) == list(PARTICLE_COLUMNS)
    assert sorted(particles["frame"].unique()) == [0, 1]
    truth = read_table(sim / "truth.parquet")
    ev = evaluate_particles(particles, truth, tolerance_mm=1.0)
    assert ev.recall >= 0.9 and ev.precision >= 0.9
    assert ev.rms_error_lateral < 0.05
    # the evaluate command prints the same numbers as one JSON object
    res = ok("evaluate", out, sim / "truth.parquet", "--tolerance", 1.0, "--json")
    printed = json.loads(res.stdout)
    assert printed["n_matched"] == ev.n_matched
    assert printed["mean_error_z"] == pytest.approx(ev.mean_error_z)
    table = ok("evaluate", out, sim / "truth.parquet")
    assert "recall" in table.stdout and "precision" in table.stdout


def test_locate_flat_fields_with_the_recorded_white_image(calibrated, tmp_path):
    root, sim = calibrated
    record = json.loads((root / "calib.json").read_text())["white_image"]
    assert record["file"] == "sim/white.tif" and len(record["sha256"]) == 64
    frame = sim / "raw" / "frame_0000.tif"
    truth = read_table(sim / "truth.parquet").query("frame == 0")

    def false_positives(result_path):
        found = read_table(result_path)
        return len(found) - evaluate_particles(found, truth, tolerance_mm=1.0).n_matched

    ok("locate", frame, "--calib", root / "calib.json", "--out", tmp_path / "flat.parquet")
    res = ok("locate", frame, "--calib", root / "calib.json", "--no-flat-field",
             "--out", tmp_path / "raw.parquet")
    assert "flat-field" not in res.stderr          # asked for: no warning
    # the realistic camera's dust shadows and dead pixels pass for particles without it
    assert false_positives(tmp_path / "flat.parquet") <= 1
    assert false_positives(tmp_path / "raw.parquet") >= 3

    # a calibration whose white image is gone: located unflat-fielded, with one warning line
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "calib.json").write_bytes((root / "calib.json").read_bytes())
    res = ok("locate", frame, "--calib", moved / "calib.json", "--out", tmp_path / "m.parquet")
    assert "sim/white.tif" in res.stderr and "not flat-fielded" in res.stderr
    assert "--white" in res.stderr and "Traceback" not in res.stderr
    assert false_positives(tmp_path / "m.parquet") >= 3
    res = ok("locate", frame, "--calib", moved / "calib.json", "--white", sim / "white.tif",
             "--out", tmp_path / "w.parquet")
    assert "flat-field" not in res.stderr
    assert read_table(tmp_path / "w.parquet").equals(read_table(tmp_path / "flat.parquet"))
    # a changed white image is not used silently
    (moved / "sim").mkdir()
    white = tifffile.imread(sim / "white.tif")
    tifffile.imwrite(moved / "sim" / "white.tif", white // 2)
    res = ok("locate", frame, "--calib", moved / "calib.json", "--out", tmp_path / "c.parquet")
    assert "changed since" in res.stderr and "not flat-fielded" in res.stderr
    res = run("locate", frame, "--calib", root / "calib.json", "--white", sim / "white.tif",
              "--no-flat-field", "--out", tmp_path / "x.parquet")
    assert res.exit_code == 2 and "contradict" in res.stderr
    assert not (tmp_path / "x.parquet").exists()


def test_locate_empty_image_gives_empty_table(calibrated, tmp_path):
    root, sim = calibrated
    white = tifffile.imread(sim / "raw" / "frame_0000.tif")
    blank = np.full_like(white, int(np.median(white)))
    tifffile.imwrite(tmp_path / "blank.tif", blank)
    out = tmp_path / "p.parquet"
    res = ok("locate", tmp_path / "blank.tif", "--calib", root / "calib.json", "--out", out)
    assert "without particles" in res.stderr
    assert len(pd.read_parquet(out)) == 0


def test_locate_refuses_calibration_without_dlfc(calibrated, tmp_path):
    root, sim = calibrated
    ok("calibrate-grid", sim / "white.tif", "--camera", sim / "camera.toml",
       "--out", tmp_path / "grid.json")
    res = run("locate", sim / "raw" / "frame_0000.tif", "--calib", tmp_path / "grid.json",
              "--out", tmp_path / "p.parquet")
    assert res.exit_code == 1
    assert "no DLFC" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "p.parquet").exists()


def test_evaluate_missing_table(tmp_path):
    res = run("evaluate", tmp_path / "absent.parquet", tmp_path / "truth.parquet")
    assert res.exit_code == 1 and "absent.parquet: table not found" in res.stderr


def test_demo_runs_end_to_end(tmp_path):
    res = ok("demo", "--out", tmp_path / "demo")
    assert "recall" in res.stdout
    particles = read_table(tmp_path / "demo" / "particles.parquet")
    truth = read_table(tmp_path / "demo" / "sim" / "truth.parquet")
    ev = evaluate_particles(particles, truth, tolerance_mm=1.0)
    assert ev.recall >= 0.9 and ev.precision >= 0.9


def test_locate_config_settings_reach_the_locator_and_the_table_metadata(calibrated, tmp_path):
    root, sim = calibrated
    frame = sim / "raw" / "frame_0000.tif"
    config = tmp_path / "locate.toml"
    config.write_text("[segment]\nwindow = 41\ncore_contrast = false\n\n"
                      "[cluster]\nn_planes = 12\n")
    out = tmp_path / "p.csv"
    ok("locate", frame, "--calib", root / "calib.json", "--config", config, "--planes", 14,
       "--shape-error", 0.02, "--out", out, "--detections", tmp_path / "d.parquet")
    meta = read_table(out).attrs["plenoptrack"]
    assert meta["settings"]["solve"]["shape_error"] == 0.02
    assert meta["method"] == "perspective" and meta["package_version"]
    seg = meta["settings"]["segment"]
    assert seg["window"] == 41 and seg["core_contrast"] is None     # from the file
    assert meta["settings"]["cluster"]["n_planes"] == 14           # the flag wins
    assert meta["calibration"]["sha256"] == file_sha256(root / "calib.json")
    assert meta["flat_field"]["white"].endswith("white.tif")
    assert read_table(tmp_path / "d.parquet").attrs["plenoptrack"] == meta
    # the settings written back from the table locate the same particles again
    res = ok("settings", "--from-table", out)
    again = tmp_path / "again.toml"
    again.write_text(res.stdout)
    ok("locate", frame, "--calib", root / "calib.json", "--config", again,
       "--out", tmp_path / "again.csv")
    pd.testing.assert_frame_equal(read_table(tmp_path / "again.csv"), read_table(out))


@pytest.mark.parametrize("text, message", [
    ("[segment]\nwindow = 2\n", "window must be an integer of at least 3"),
    ("[segmnt]\nwindow = 41\n", "unknown section"),
    ("[cluster]\nplanes = 4\n", "unknown setting"),
    ("[solve\n", "not a valid TOML"),
])
def test_locate_bad_config_is_one_line_usage_error(calibrated, tmp_path, text, message):
    root, sim = calibrated
    config = tmp_path / "bad.toml"
    config.write_text(text)
    res = run("locate", sim / "raw" / "frame_0000.tif", "--calib", root / "calib.json",
              "--config", config, "--out", tmp_path / "p.parquet")
    assert res.exit_code == 2, res.stderr
    assert message in res.stderr and str(config) in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "p.parquet").exists()


@pytest.mark.parametrize("method", ["refocus", "hybrid"])
def test_locate_other_methods_write_the_same_columns(calibrated, method):
    root, sim = calibrated
    frames = sorted((sim / "raw").glob("frame_*.tif"))[:1]
    out = root / f"particles_{method}.csv"
    ok("locate", *frames, "--calib", root / "calib.json", "--out", out, "--method", method,
       "--stack-planes", 60)
    particles = read_table(out)
    assert list(particles.columns) == list(PARTICLE_COLUMNS)
    truth = read_table(sim / "truth.parquet")
    ev = evaluate_particles(particles, truth[truth["frame"] == 0], tolerance_mm=2.0)
    assert ev.n_matched >= (3 if method == "refocus" else 0.9 * ev.n_true)


def test_locate_refuses_unknown_method(calibrated):
    root, sim = calibrated
    frames = sorted((sim / "raw").glob("frame_*.tif"))[:1]
    result = run("locate", *frames, "--calib", root / "calib.json", "--out", root / "x.csv",
                 "--method", "magic")
    assert result.exit_code == 2 and "perspective, refocus or hybrid" in result.stderr
