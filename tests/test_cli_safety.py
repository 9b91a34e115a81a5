"""No command loses data or answers bad input with a traceback.

Classes of failure, each tested on every command it applies to:

- an output that is one of the inputs (the same path, a symbolic or a hard link) is
  refused before any work, with exit code 2 and the input untouched;
- a command with several outputs writes all or none: a failure or Ctrl-C after one output
  was complete leaves every pre-existing file as it was and no new or temporary file;
- every out-of-range option is one ``error:`` line with exit code 2, every bad file one
  line with exit code 1;
- Ctrl-C (SIGINT to a real process) ends with exit code 130 and one line, keeping partial
  results only when asked (``locate --partial``); an interrupt that lands as the outputs
  are committed names the complete outputs it leaves;
- black or saturated frames are reported; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
from typer.testing import CliRunner

from plenoptrack.cli import app
from plenoptrack.io import read_frames, read_raw, read_table

runner = CliRunner()
N_FRAMES = 3


def run(*args, env=None):
    return runner.invoke(app, [str(a) for a in args], env=env)


def ok(*args):
    result = run(*args)
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    return result


def assert_error_line(result, *fragments: str, code: int) -> None:
    assert result.exit_code == code, (result.stdout, result.stderr, result.exception)
    assert isinstance(result.exception, SystemExit), repr(result.exception)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden temporaries included) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A calibrated 'small' data set; ``work`` holds copies that commands may be aimed at."""
    root = tmp_path_factory.mktemp("safety")
    sim = root / "sim"
    ok("simulate", "--preset", "small", "--seed", 2, "--particles", 8, "--frames", N_FRAMES,
       "--out", sim)
    ok("calibrate", "--white", sim / "white.tif", "--dotcards", sim / "dotcards",
       "--camera", sim / "camera.toml", "--out", root / "calib.json")
    ok("calibrate-grid", sim / "white.tif", "--camera", sim / "camera.toml",
       "--out", root / "grid.json")
    frames = np.stack([read_raw(p) for p in sorted((sim / "raw").glob("frame_*.tif"))])
    tifffile.imwrite(root / "frames.tif", frames, photometric="minisblack")
    ok("locate", root / "frames.tif", "--calib", root / "calib.json", "--out", root / "particles.parquet")
    return root


@pytest.fixture()
def work(data, tmp_path):
    """A folder with copies of the inputs, so that a failed test cannot spoil the others."""
    for name in ("calib.json", "grid.json", "frames.tif", "particles.parquet"):
        (tmp_path / name).write_bytes((data / name).read_bytes())
    for name in ("white.tif", "camera.toml", "truth.parquet", "raw/frame_0000.tif"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes((data / "sim" / name).read_bytes())
    (tmp_path / "sim").mkdir()   # where calib.json records its white image, for flat-fielding
    (tmp_path / "sim" / "white.tif").write_bytes((data / "sim" / "white.tif").read_bytes())
    cards = tmp_path / "dotcards"
    cards.mkdir()
    for path in (data / "sim" / "dotcards").iterdir():
        (cards / path.name).write_bytes(path.read_bytes())
    _write_cards_toml(cards, "reversed.toml", lambda z: -z)
    _write_cards_toml(cards, "in_cm.toml", lambda z: z / 10)
    raw = read_raw(tmp_path / "white.tif")
    tifffile.imwrite(tmp_path / "rgb.tif", np.stack([raw] * 3, axis=-1), photometric="rgb")
    tifffile.imwrite(tmp_path / "float.tif", raw.astype(np.float32))
    tifffile.imwrite(tmp_path / "cropped.tif", raw[:-2])
    full = (tmp_path / "frames.tif").read_bytes()
    (tmp_path / "truncated.tif").write_bytes(full[: len(full) // 3])
    (tmp_path / "empty.parquet").write_bytes(b"")
    pd.DataFrame({"frame": [0], "x": [0.0]}).to_parquet(tmp_path / "no_z.parquet")
    os.symlink(tmp_path / "frames.tif", tmp_path / "link_to_frames.tif")
    os.link(tmp_path / "calib.json", tmp_path / "hardlink_to_calib.json")
    (tmp_path / "a_folder").mkdir()
    (tmp_path / "a_file").write_text("x")
    return tmp_path


def _write_cards_toml(folder: Path, name: str, depth, order=None) -> None:
    """A dot-card description beside the cards with the depths changed by ``depth``."""
    import tomllib

    import tomli_w

    doc = tomllib.loads((folder / "dotcards.toml").read_text())
    cards = doc["cards"]
    depths = [c["z_mm"] for c in cards]
    for k, card in enumerate(cards):
        card["z_mm"] = float(depth(depths[k if order is None else order[k]]))
    (folder / name).write_text(tomli_w.dumps(doc))


# --------------------------------------------------------------------------- bad input table

LOCATE = ["locate", "frames.tif", "--calib", "calib.json"]
EVALUATE = ["evaluate", "particles.parquet", "truth.parquet"]
CALIBRATE = ["calibrate", "--white", "white.tif", "--dotcards", "dotcards", "--camera", "camera.toml"]
GRID = ["calibrate-grid", "white.tif", "--camera", "camera.toml"]
VIEWS = ["views", "raw/frame_0000.tif", "--calib", "grid.json"]
REFOCUS = ["refocus", "raw/frame_0000.tif", "--calib", "grid.json"]
SIMULATE = ["simulate", "--particles", "1"]

# (command line relative to the work folder, exit code, fragments of the error line)
BAD_INPUTS = {
    # locate: options
    "locate-window-0": (LOCATE + ["--window", "0", "--out", "p.parquet"], 2, ["--window"]),
    "locate-window-2": (LOCATE + ["--window", "2", "--out", "p.parquet"], 2, ["--window"]),
    "locate-contrast-negative": (LOCATE + ["--contrast", "-1", "--out", "p.parquet"], 2, ["--contrast", "positive"]),
    "locate-contrast-1": (LOCATE + ["--contrast", "1", "--out", "p.parquet"], 2, ["--contrast", "below 1"]),
    "locate-contrast-nan": (LOCATE + ["--contrast", "nan", "--out", "p.parquet"], 2, ["--contrast", "finite"]),
    "locate-planes-0": (LOCATE + ["--planes", "0", "--out", "p.parquet"], 2, ["--planes"]),
    "locate-shape-error-1": (LOCATE + ["--shape-error", "1", "--out", "p.parquet"], 2, ["--shape-error", "below 1"]),
    "locate-shape-error-negative": (LOCATE + ["--shape-error", "-0.1", "--out", "p.parquet"], 2, ["--shape-error", "at least 0"]),
    "locate-planes-1": (LOCATE + ["--planes", "1", "--out", "p.parquet"], 2, ["--planes"]),
    "locate-window-text": (LOCATE + ["--window", "wide", "--out", "p.parquet"], 2, ["--window"]),
    "locate-unknown-option": (LOCATE + ["--speed", "3", "--out", "p.parquet"], 2, ["--speed"]),
    "locate-no-calib": (["locate", "frames.tif", "--out", "p.parquet"], 2, ["--calib"]),
    # locate: files
    "locate-missing-raw": (["locate", "nope.tif", "--calib", "calib.json", "--out", "p.parquet"], 1, ["nope.tif", "not found"]),
    "locate-colour-raw": (["locate", "rgb.tif", "--calib", "calib.json", "--out", "p.parquet"], 1, ["rgb.tif", "colour image", "single-channel"]),
    "locate-float-raw": (["locate", "float.tif", "--calib", "calib.json", "--out", "p.parquet"], 1, ["float.tif", "uint16"]),
    "locate-truncated-raw": (["locate", "truncated.tif", "--calib", "calib.json", "--out", "p.parquet"], 1, ["truncated.tif"]),
    "locate-bad-second-raw": (["locate", "frames.tif", "truncated.tif", "--calib", "calib.json", "--out", "p.parquet"], 1, ["truncated.tif"]),
    "locate-grid-only-calib": (["locate", "frames.tif", "--calib", "grid.json", "--out", "p.parquet"], 1, ["DLFC"]),
    "locate-calib-is-an-image": (["locate", "frames.tif", "--calib", "white.tif", "--out", "p.parquet"], 1, ["white.tif"]),
    "locate-missing-white": (LOCATE + ["--white", "nope.tif", "--out", "p.parquet"], 1, ["nope.tif", "not found"]),
    "locate-white-wrong-size": (LOCATE + ["--white", "cropped.tif", "--out", "p.parquet"], 1, ["cropped.tif", "pixels"]),
    "locate-colour-white": (LOCATE + ["--white", "rgb.tif", "--out", "p.parquet"], 1, ["rgb.tif", "colour image"]),
    "locate-white-and-no-flat-field": (LOCATE + ["--white", "white.tif", "--no-flat-field", "--out", "p.parquet"], 2, ["--white", "contradict"]),
    # locate: outputs
    "locate-out-is-raw": (LOCATE + ["--out", "frames.tif"], 2, ["frames.tif", "--out", "input RAW"]),
    "locate-out-is-calib": (LOCATE + ["--out", "calib.json"], 2, ["--out", "input --calib"]),
    "locate-out-is-white": (LOCATE + ["--white", "white.tif", "--out", "white.tif"], 2, ["--out", "input --white"]),
    "locate-out-is-symlink-to-raw": (LOCATE + ["--out", "link_to_frames.tif"], 2, ["input RAW"]),
    "locate-out-is-raw-via-dots": (LOCATE + ["--out", "a_folder/../frames.tif"], 2, ["input RAW"]),
    "locate-detections-is-calib": (LOCATE + ["--out", "p.parquet", "--detections", "calib.json"], 2, ["--detections", "input --calib"]),
    "locate-out-twice": (LOCATE + ["--out", "p.parquet", "--detections", "p.parquet"], 2, ["both --out and --detections"]),
    "locate-out-is-a-folder": (LOCATE + ["--out", "a_folder"], 2, ["a_folder", "is a folder"]),
    "locate-out-under-a-file": (LOCATE + ["--out", "a_file/p.parquet"], 1, ["a_file"]),
    # evaluate
    "evaluate-tolerance-negative": (EVALUATE + ["--tolerance", "-1"], 2, ["--tolerance", "positive"]),
    "evaluate-tolerance-zero": (EVALUATE + ["--tolerance", "0"], 2, ["--tolerance", "positive"]),
    "evaluate-tolerance-nan": (EVALUATE + ["--tolerance", "nan"], 2, ["--tolerance", "finite"]),
    "evaluate-tolerance-inf": (EVALUATE + ["--tolerance", "inf"], 2, ["--tolerance", "finite"]),
    "evaluate-missing-table": (["evaluate", "nope.parquet", "truth.parquet"], 1, ["nope.parquet", "not found"]),
    "evaluate-empty-file": (["evaluate", "empty.parquet", "truth.parquet"], 1, ["empty.parquet", "Parquet"]),
    "evaluate-no-z-column": (["evaluate", "no_z.parquet", "truth.parquet"], 1, ["'z'"]),
    # calibrate
    "calibrate-order-0": (CALIBRATE + ["--order", "0", "--out", "c.json"], 2, ["--order"]),
    "calibrate-order-7": (CALIBRATE + ["--order", "7", "--out", "c.json"], 2, ["--order"]),
    "calibrate-out-is-camera": (CALIBRATE + ["--out", "camera.toml"], 2, ["input --camera"]),
    "calibrate-out-is-white": (CALIBRATE + ["--out", "white.tif"], 2, ["input --white"]),
    "calibrate-out-is-dotcards-toml": (CALIBRATE + ["--out", "dotcards/dotcards.toml"], 2, ["input dotcards.toml"]),
    "calibrate-out-is-a-card": (CALIBRATE + ["--out", "dotcards/card_03.tif"], 2, ["dot-card image"]),
    "calibrate-out-is-hardlink-to-calib-input": (["calibrate", "--white", "white.tif", "--dotcards", "dotcards", "--camera", "hardlink_to_calib.json", "--out", "calib.json"], 2, ["input --camera"]),
    "calibrate-missing-dotcards": (["calibrate", "--white", "white.tif", "--dotcards", "nope", "--camera", "camera.toml", "--out", "c.json"], 1, ["nope", "not found"]),
    "calibrate-colour-white": (["calibrate", "--white", "rgb.tif", "--dotcards", "dotcards", "--camera", "camera.toml", "--out", "c.json"], 1, ["rgb.tif", "colour"]),
    "calibrate-depths-reversed": (["calibrate", "--white", "white.tif", "--dotcards", "dotcards/reversed.toml", "--camera", "camera.toml", "--out", "c.json"], 1, ["reversed.toml", "reversed in sign"]),
    "calibrate-depths-in-cm": (["calibrate", "--white", "white.tif", "--dotcards", "dotcards/in_cm.toml", "--camera", "camera.toml", "--out", "c.json"], 1, ["in_cm.toml", "times too small", "cm"]),
    # calibrate-grid
    "grid-out-is-white": (GRID + ["--out", "white.tif"], 2, ["input WHITE"]),
    "grid-out-is-camera": (GRID + ["--out", "camera.toml"], 2, ["input --camera"]),
    "grid-colour-white": (["calibrate-grid", "rgb.tif", "--camera", "camera.toml", "--out", "c.json"], 1, ["colour"]),
    # views
    "views-out-is-raw": (VIEWS + ["--out", "raw/frame_0000.tif"], 2, ["input RAW"]),
    "views-out-is-calib": (VIEWS + ["--out", "grid.json"], 2, ["input --calib"]),
    "views-mosaic-is-raw": (VIEWS + ["--out", "v.tif", "--mosaic", "raw/frame_0000.tif"], 2, ["--mosaic", "input RAW"]),
    "views-mosaic-is-out": (VIEWS + ["--out", "v.tif", "--mosaic", "v.tif"], 2, ["both --out and --mosaic"]),
    "views-colour-raw": (["views", "rgb.tif", "--calib", "grid.json", "--out", "v.tif"], 1, ["colour"]),
    "views-frame-out-of-range": (VIEWS + ["--frame", "5", "--out", "v.tif"], 1, ["frame 5 does not exist"]),
    # refocus
    "refocus-out-is-raw": (REFOCUS + ["--depth", "0", "--out", "raw/frame_0000.tif"], 2, ["input RAW"]),
    "refocus-stack-negative": (REFOCUS + ["--stack", "-1", "--out", "r.tif"], 2, ["--stack"]),
    "refocus-zmin-above-zmax": (REFOCUS + ["--stack", "3", "--zmin", "5", "--zmax", "-5", "--out", "r.tif"], 2, ["--zmin"]),
    "refocus-depth-inf": (REFOCUS + ["--depth", "inf", "--out", "r.tif"], 2, ["--depth", "finite"]),
    "refocus-alpha-nan": (REFOCUS + ["--alpha", "nan", "--out", "r.tif"], 2, ["--alpha", "finite"]),
    # simulate
    "simulate-samples-0": (SIMULATE + ["--samples", "0", "--out", "s"], 2, ["--samples"]),
    "simulate-frames-0": (SIMULATE + ["--frames", "0", "--out", "s"], 2, ["--frames"]),
    "simulate-particles-negative": (SIMULATE[:1] + ["--particles", "-1", "--out", "s"], 2, ["--particles"]),
    "simulate-diameter-nan": (SIMULATE + ["--diameter", "nan", "--out", "s"], 2, ["--diameter", "positive"]),
    "simulate-diameter-range-reversed": (SIMULATE + ["--diameter", "2:0.2", "--out", "s"], 2, ["--diameter", "MIN <= MAX"]),
    "simulate-diameter-text": (SIMULATE + ["--diameter", "big", "--out", "s"], 2, ["--diameter", "range MIN:MAX"]),
    "simulate-magnification-inf": (SIMULATE + ["--magnification", "inf", "--out", "s"], 2, ["--magnification", "finite"]),
    "simulate-out-is-a-file": (SIMULATE + ["--out", "a_file"], 2, ["a_file", "is a file"]),
    "simulate-out-holds-other-files": (SIMULATE + ["--out", "."], 1, ["not part of a simulated data set"]),
    "simulate-unknown-preset": (SIMULATE + ["--preset", "tiny", "--out", "s"], 1, ["tiny"]),
    # demo
    "demo-out-is-a-file": (["demo", "--out", "a_file"], 2, ["a_file", "is a file"]),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_input_is_one_line_and_changes_nothing(work, case, monkeypatch):
    args, code, fragments = BAD_INPUTS[case]
    monkeypatch.chdir(work)
    before = snapshot(work)
    result = run(*args)
    assert_error_line(result, *fragments, code=code)
    assert snapshot(work) == before


def test_every_command_has_bad_input_cases():
    commands = {args[0] for args, _, _ in BAD_INPUTS.values()}
    assert commands == {"locate", "evaluate", "calibrate", "calibrate-grid", "views", "refocus",
                        "simulate", "demo"}


# --------------------------------------------------------------------------- several outputs


def test_views_failing_mosaic_keeps_the_old_views_file(work, data):
    old = work / "old.tif"
    old.write_bytes(b"earlier views")
    result = run("views", work / "raw/frame_0000.tif", "--calib", work / "grid.json",
                 "--out", old, "--mosaic", work / "a_file" / "m.png")
    assert result.exit_code == 1
    assert old.read_bytes() == b"earlier views"


def test_locate_failing_detections_keeps_the_old_table(work):
    before = snapshot(work)
    result = run("locate", work / "frames.tif", "--calib", work / "calib.json",
                 "--out", work / "particles.parquet", "--detections", work / "a_file" / "d.parquet")
    assert result.exit_code == 1
    assert snapshot(work) == before


def test_locate_failure_after_the_first_output_was_written_changes_nothing(work, monkeypatch):
    """The table is complete, writing the detections fails: neither file is replaced."""
    import plenoptrack.io

    real = plenoptrack.io.write_table
    calls = []

    def second_write_fails(df, path):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(28, "No space left on device", str(path))
        return real(df, path)

    monkeypatch.setattr(plenoptrack.io, "write_table", second_write_fails)
    (work / "d.parquet").write_bytes(b"old detections")
    before = snapshot(work)
    result = run("locate", work / "frames.tif", "--calib", work / "calib.json",
                 "--out", work / "particles.parquet", "--detections", work / "d.parquet")
    assert_error_line(result, "No space left", code=1)
    assert len(calls) == 2
    assert snapshot(work) == before


def test_outputs_are_written_with_the_umask_mode(work):
    previous = os.umask(0o027)
    try:
        ok("locate", work / "frames.tif", "--calib", work / "calib.json",
           "--out", work / "new" / "p.csv", "--detections", work / "new" / "d.parquet")
    finally:
        os.umask(previous)
    for name in ("p.csv", "d.parquet"):
        assert (work / "new" / name).stat().st_mode & 0o777 == 0o640


def test_a_card_listed_at_the_wrong_depth_is_warned_about(work):
    n = len(list((work / "dotcards").glob("card_*.tif")))
    order = list(range(n))
    order[2], order[3] = 3, 2  # two cards' depths swapped in the description
    _write_cards_toml(work / "dotcards", "swapped.toml", lambda z: z, order=order)
    result = ok("calibrate", "--white", work / "white.tif", "--dotcards", work / "dotcards" / "swapped.toml",
                "--camera", work / "camera.toml", "--out", work / "c.json")
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1, result.stderr
    import re

    read = {m[0]: (float(m[1]), float(m[2])) for m in
            re.findall(r"(card_\d+\.tif) z_mm = (-?\d+(?:\.\d+)?) reads as (-?\d+(?:\.\d+)?)", warnings[0])}
    assert set(read) == {"card_02.tif", "card_03.tif"}
    # each card reads as the depth of the other (within the 1.7 % scale of the fit)
    assert abs(read["card_02.tif"][1] - read["card_03.tif"][0]) < 0.1
    assert abs(read["card_03.tif"][1] - read["card_02.tif"][0]) < 0.1
    assert (work / "c.json").is_file()
    result = ok("calibrate", "--white", work / "white.tif", "--dotcards", work / "dotcards" / "reversed.toml",
                "--camera", work / "camera.toml", "--out", work / "c2.json", "--no-check-depths")
    assert (work / "c2.json").is_file()


# --------------------------------------------------------------------------- exposure, debug


@pytest.mark.parametrize("level, word", [(0, "black"), (4095, "saturated")])
def test_black_or_saturated_frame_is_reported(work, level, word):
    image = np.full(read_raw(work / "white.tif").shape, level, np.uint16)
    tifffile.imwrite(work / "flat.tif", image)
    result = ok("locate", work / "flat.tif", "--calib", work / "calib.json", "--out", work / "p.parquet")
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and word in warnings[0] and "flat.tif frame 0" in warnings[0], result.stderr
    assert len(read_table(work / "p.parquet")) == 0
    result = ok("views", work / "flat.tif", "--calib", work / "grid.json", "--out", work / "v.tif")
    assert f"the frame is {word}" in result.stderr


def test_an_ordinary_frame_gives_no_exposure_warning(work):
    result = ok("views", work / "raw/frame_0000.tif", "--calib", work / "grid.json", "--out", work / "v.tif")
    assert "warning" not in result.stderr


@pytest.mark.parametrize("how", ["flag", "env"])
def test_debug_shows_the_traceback(work, how):
    args = ["evaluate", work / "nope.parquet", work / "truth.parquet"]
    plain = run(*args)
    assert "Traceback" not in plain.stderr
    result = run("--debug", *args) if how == "flag" else run(*args, env={"PLENOPTRACK_DEBUG": "1"})
    assert result.exit_code == 1
    assert "Traceback" in result.stderr and "InputFileError" in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith("error: ")


def test_an_internal_error_is_one_line_asking_for_a_report(work, monkeypatch):
    import plenoptrack.evaluate

    def bug(*args, **kwargs):
        raise TypeError("unsupported operand")

    monkeypatch.setattr(plenoptrack.evaluate, "evaluate_particles", bug)
    result = run("evaluate", work / "particles.parquet", work / "truth.parquet")
    assert_error_line(result, "internal error", "TypeError", "--debug", code=1)


def test_interrupt_inside_a_compiled_kernel_exits_130(work, monkeypatch):
    """Ctrl-C inside numba code can surface as a SystemError whose cause is the interrupt."""
    import plenoptrack.locate.perspective

    def interrupted(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("returned a result with an exception set") from exc

    monkeypatch.setattr(plenoptrack.locate.perspective, "locate_frame", interrupted)
    before = snapshot(work)
    result = run("locate", work / "frames.tif", "--calib", work / "calib.json", "--out", work / "particles.parquet")
    assert_error_line(result, "interrupted", code=130)
    assert snapshot(work) == before


def test_interrupt_as_the_outputs_are_committed_names_them(work, monkeypatch):
    """Ctrl-C held back during the renames ends the command with complete new outputs."""
    import plenoptrack.io

    real = plenoptrack.io.os.replace
    renamed = []

    def replace_then_ctrl_c(src, dst):
        real(src, dst)
        renamed.append(Path(dst).name)
        if Path(dst).name == "d.parquet":
            # held back until both renames are done; raise_signal delivers to this thread,
            # where os.kill may pick another thread of the process (numba's workers), whose
            # handler can run after the renames have ended
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(plenoptrack.io.os, "replace", replace_then_ctrl_c)
    # a shell starts background jobs with SIGINT ignored: give the test the usual handler
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        result = run("locate", work / "frames.tif", "--calib", work / "calib.json",
                     "--out", work / "new.parquet", "--detections", work / "d.parquet")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert_error_line(result, "interrupted; nothing half-written was kept; complete before the "
                      f"interrupt: wrote {work / 'new.parquet'}, {work / 'd.parquet'}", code=130)
    assert [name for name in renamed if not name.startswith(".")] == ["new.parquet", "d.parquet"]
    assert len(read_table(work / "new.parquet")) > 0 and len(read_table(work / "d.parquet")) > 0


def test_an_interrupt_before_any_commit_names_no_output(work, monkeypatch):
    import plenoptrack.locate.perspective

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    ok("locate", work / "frames.tif", "--calib", work / "calib.json", "--out", work / "x.parquet")
    monkeypatch.setattr(plenoptrack.locate.perspective, "locate_frame", interrupted)
    result = run("locate", work / "frames.tif", "--calib", work / "calib.json",
                 "--out", work / "y.parquet")
    assert_error_line(result, "interrupted", code=130)
    assert "wrote" not in result.stderr  # the previous command's output is not this one's
    assert not (work / "y.parquet").exists()


def test_version():
    from plenoptrack import __version__

    assert ok("--version").stdout.strip() == f"plenoptrack {__version__}"


# --------------------------------------------------------------------------- Ctrl-C, for real


def _default_sigint() -> None:
    # A shell starts background jobs with SIGINT ignored, and children inherit that: the
    # command under test must see Ctrl-C as it would in a terminal.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(args, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "plenoptrack", *map(str, args)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sigint)


def _interrupt_when(proc: subprocess.Popen, ready, delay_s: float, timeout_s: float = 120.0):
    """Send SIGINT ``delay_s`` after ``ready()`` first holds; return (code, stderr)."""
    t_end = time.monotonic() + timeout_s
    while not ready() and proc.poll() is None and time.monotonic() < t_end:
        time.sleep(0.01)
    time.sleep(delay_s)
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=timeout_s)
    return proc.returncode, err


def _staged(folder: Path, name: str):
    return lambda: any(p.name.startswith(f".{name}.") for p in folder.iterdir())


@pytest.mark.parametrize("delay_s", [0.0, 0.4, 1.2])
def test_ctrl_c_during_locate_keeps_the_old_table(work, delay_s):
    before = snapshot(work)
    proc = _start(["locate", "frames.tif", "--calib", "calib.json", "--out", "particles.parquet",
                   "--detections", "d.parquet"], work)
    code, err = _interrupt_when(proc, _staged(work, "particles.parquet"), delay_s)
    assert "Traceback" not in err, err
    if code == 0:  # finished before the signal: a complete result
        assert len(read_table(work / "d.parquet")) > 0
        return
    if "wrote particles.parquet" in err:  # the signal came as it finished: all written
        assert code == 130 and len(read_table(work / "d.parquet")) > 0
        return
    assert code == 130, err
    assert err.strip().splitlines()[-1] == "error: interrupted; nothing half-written was kept"
    assert snapshot(work) == before


def test_ctrl_c_during_locate_with_partial_keeps_the_complete_frames(work, data):
    """Interrupted after some frames, ``--partial`` writes exactly those frames' particles.

    The raw file repeats the three frames forty times (several seconds of locating); the
    signal is sent later and later until it lands after the first frame and before the
    last. Every run on the way must have a clean outcome too.
    """
    full = read_table(data / "particles.parquet")
    frames = read_frames(work / "frames.tif")
    n_long = 40 * len(frames)
    tifffile.imwrite(work / "long.tif", np.concatenate([frames] * 40), photometric="minisblack")

    def expected(done: int) -> pd.DataFrame:
        parts = [full[full["frame"] == f % len(frames)].assign(frame=f) for f in range(done)]
        return pd.concat(parts, ignore_index=True)

    seen_partial = False
    for delay_s in (0.3, 0.6, 1.0, 2.0, 4.0, 8.0):
        out = work / f"part_{delay_s}.parquet"
        proc = _start(["locate", "long.tif", "--calib", "calib.json", "--out", out.name,
                       "--partial"], work)
        code, err = _interrupt_when(proc, _staged(work, out.name), delay_s)
        assert "Traceback" not in err, err
        if code == 0 or f"wrote {out.name}" in err:  # finished before the signal
            assert code in (0, 130), err
            pd.testing.assert_frame_equal(read_table(out), expected(n_long), check_dtype=False)
            break
        assert code == 130, err
        if "nothing half-written" in err:  # before the first frame was complete
            assert not out.exists()
            continue
        done = int(err.split("interrupted after ")[1].split(" of ")[0])
        assert 0 < done < n_long
        pd.testing.assert_frame_equal(read_table(out), expected(done), check_dtype=False)
        seen_partial = True
        break
    assert seen_partial, "no interrupt landed between the first and the last frame"


@pytest.mark.parametrize("delay_s", [0.0, 0.5, 1.5])
def test_ctrl_c_during_simulate_keeps_the_old_data_set_whole(data, tmp_path, delay_s):
    import shutil

    sim = tmp_path / "sim"
    shutil.copytree(data / "sim", sim)
    before = snapshot(sim)
    proc = _start(["simulate", "--preset", "small", "--seed", 5, "--particles", 3, "--frames", 2,
                   "--out", sim], tmp_path)
    code, err = _interrupt_when(proc, _staged(tmp_path, "sim"), delay_s)
    assert "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim"]  # no temporary folder left
    if code == 0 or f"wrote {sim}" in err:  # finished, or interrupted as it was swapped in
        assert code in (0, 130), err
        assert len(read_table(sim / "truth.parquet")) == 6 and len(list((sim / "raw").iterdir())) == 2
        return
    assert code == 130, err
    assert snapshot(sim) == before


def test_a_ctrl_c_dropped_by_compiled_code_inside_a_command_prints_no_traceback(tmp_path):
    """Cython code that cannot raise prints a Ctrl-C through sys.excepthook and drops it
    (scipy.stats._sobol does so when the interrupt lands while it initialises): through the
    real entry point, the command line's hook is the one in place while a command runs,
    so the interrupt is recorded, nothing is written and no traceback is printed."""
    script = tmp_path / "probe.py"
    script.write_text(
        "import sys\n"
        "from plenoptrack import cli\n"
        "from plenoptrack.io import atomic_write_text\n"
        "@cli.app.command('probe')\n"
        "@cli._reports_errors\n"
        "def probe(out: str):\n"
        "    try:\n"
        "        raise KeyboardInterrupt\n"
        "    except KeyboardInterrupt:\n"
        "        sys.excepthook(*sys.exc_info())  # what compiled code does with it\n"
        "    atomic_write_text(out, 'complete')\n"
        "sys.argv = ['plenoptrack', 'probe', sys.argv[1]]\n"
        "cli.main()\n")
    out = tmp_path / "out.txt"
    proc = subprocess.run([sys.executable, str(script), str(out)], capture_output=True,
                          text=True, timeout=120, preexec_fn=_default_sigint)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == "error: interrupted; nothing half-written was kept"
    assert not out.exists()
