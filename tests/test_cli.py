"""The ``plenoptrack`` command: simulate, calibrate-grid, views and refocus.

One simulated 'small' data set (fixed seed) is made through the command line and shared by
the module; each command is checked against the file contract, against the simulator's
ground truth, and on bad input (one readable line on stderr, exit code 1, no output file).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
from scipy.spatial import cKDTree
from typer.main import get_command
from typer.testing import CliRunner

from plenoptrack.calibration import load_calibration
from plenoptrack.cli import app
from plenoptrack.io import read_raw
from plenoptrack.lightfield import LensletGrid, decode, sharpness

SEED = 3
N_PARTICLES = 4
DIAMETER_MM = 0.5
N_FRAMES = 2
SIMULATE_ARGS = ["simulate", "--preset", "small", "--seed", str(SEED), "--particles",
                 str(N_PARTICLES), "--diameter", str(DIAMETER_MM), "--frames", str(N_FRAMES),
                 "--optics", "ideal"]   # geometry checked against the exact model
CENTRE_RMS_PX = 0.05

runner = CliRunner()


def run(*args) -> "CliRunner.Result":
    return runner.invoke(app, [str(a) for a in args])


def ok(*args):
    result = run(*args)
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    return result


def contract_files(folder: Path, frames: int) -> list[Path]:
    """Every file the simulator must write (file contract in README.md)."""
    files = [folder / "raw" / f"frame_{f:04d}.tif" for f in range(frames)]
    files += [folder / name for name in ("white.tif", "camera.toml", "truth.parquet",
                                         "truth_optics.json", "dotcards/dotcards.toml")]
    return files


def assert_error_line(result, *fragments: str, code: int = 1) -> None:
    """Exit ``code`` (1 data error, 2 usage error), one ``error: ...`` line on stderr naming
    ``fragments``, no traceback."""
    assert result.exit_code == code, (result.stdout, result.stderr, result.exception)
    assert isinstance(result.exception, SystemExit), repr(result.exception)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ")
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


def assert_nothing_written(folder: Path, before: set[str]) -> None:
    """No output and no temporary file was left in ``folder``."""
    assert {p.name for p in folder.iterdir()} == before


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("cli") / "sim"
    ok(*SIMULATE_ARGS, "--out", folder)
    return folder


@pytest.fixture(scope="module")
def calib_file(sim) -> Path:
    path = sim.parent / "calib.json"
    ok("calibrate-grid", sim / "white.tif", "--camera", sim / "camera.toml", "--out", path)
    return path


@pytest.fixture(scope="module")
def lf(sim, calib_file):
    """Light field of frame 0, decoded through the library."""
    return decode(read_raw(sim / "raw" / "frame_0000.tif"), load_calibration(calib_file).grid)


@pytest.fixture()
def bad_inputs(tmp_path, sim, calib_file):
    """A folder with broken input files; returns (folder, names present before a run)."""
    (tmp_path / "text.tif").write_text("not an image\n")
    tifffile.imwrite(tmp_path / "float.tif", np.zeros(read_raw(sim / "white.tif").shape, np.float32))
    tifffile.imwrite(tmp_path / "small.tif", np.zeros((500, 700), np.uint16))
    (tmp_path / "corrupt.json").write_text('{"format": "plenoptrack-calibration", "vers')
    (tmp_path / "camera_number.json").write_text(json.dumps(
        {"format": "plenoptrack-calibration", "version": 1, "camera": 5, "lenslet_grid": {}}))
    good = json.loads(calib_file.read_text())
    good["camera"]["bogus"] = 1
    (tmp_path / "unknown_key.json").write_text(json.dumps(good))
    (tmp_path / "corrupt.toml").write_text("[camera\nfocal_length_mm = 105\n")
    text = (sim / "camera.toml").read_text()
    (tmp_path / "negative_f.toml").write_text(text.replace("focal_length_mm = 105.0",
                                                           "focal_length_mm = -105.0"))
    assert "focal_length_mm = -105.0" in (tmp_path / "negative_f.toml").read_text()
    (tmp_path / "not_a_folder").write_text("")
    return tmp_path, {p.name for p in tmp_path.iterdir()}


# --------------------------------------------------------------------------- --help

KEY_OPTIONS = {
    "simulate": ["--out", "--preset", "--seed", "--particles", "--diameter", "--magnification",
                 "--frames", "--scene"],
    "calibrate-grid": ["--camera", "--out"],
    "views": ["--calib", "--out", "--mosaic", "--frame"],
    "refocus": ["--calib", "--depth", "--alpha", "--stack", "--zmin", "--zmax", "--out"],
}


def test_app_help_lists_the_commands():
    result = ok("--help")
    for name in KEY_OPTIONS:
        assert name in result.stdout


def test_no_arguments_shows_help():
    result = run()
    assert "Usage" in result.stdout + result.stderr
    assert "Traceback" not in result.stdout + result.stderr


@pytest.mark.parametrize("command", sorted(KEY_OPTIONS))
def test_command_help_mentions_key_options(command):
    result = ok(command, "--help")
    for option in KEY_OPTIONS[command]:
        assert option in result.stdout, (command, option)


def test_every_command_has_help():
    commands = get_command(app).commands
    assert set(KEY_OPTIONS) <= set(commands)
    for name in commands:
        result = ok(name, "--help")
        assert "Usage" in result.stdout


# --------------------------------------------------------------------------- simulate


def test_simulate_writes_the_file_contract(sim):
    for path in contract_files(sim, N_FRAMES):
        assert path.is_file(), path
    assert not (sim / "raw" / f"frame_{N_FRAMES:04d}.tif").exists()
    cards = tomllib.loads((sim / "dotcards" / "dotcards.toml").read_text())
    assert cards["spacing_mm"] > 0 and len(cards["cards"]) > 0
    for card in cards["cards"]:
        assert (sim / "dotcards" / card["file"]).is_file()
        assert np.isfinite(card["z_mm"])
    assert sorted(p.name for p in (sim / "dotcards").glob("*.tif")) == sorted(
        c["file"] for c in cards["cards"])
    camera = tomllib.loads((sim / "camera.toml").read_text())["camera"]
    for path in [sim / "white.tif", *sorted((sim / "raw").glob("*.tif"))]:
        image = read_raw(path)
        assert image.dtype == np.uint16
        assert image.shape == tuple(camera["sensor_shape_px"])
    assert "true_grid" in json.loads((sim / "truth_optics.json").read_text())
    # every written file is final: no temporary files beside them
    assert not [p for p in sim.rglob("*") if p.name.endswith(".tmp") or ".tmp." in p.name]


def test_simulate_honours_particles_diameter_frames(sim):
    truth = pd.read_parquet(sim / "truth.parquet")
    assert {"frame", "particle", "x", "y", "z", "diameter"} <= set(truth.columns)
    assert sorted(truth["frame"].unique()) == list(range(N_FRAMES))
    assert (truth.groupby("frame").size() == N_PARTICLES).all()
    np.testing.assert_allclose(truth["diameter"], DIAMETER_MM)
    # the particles are in the images: frame 0 differs from the white image
    assert not np.array_equal(read_raw(sim / "raw" / "frame_0000.tif"), read_raw(sim / "white.tif"))


def test_simulate_same_seed_gives_same_bytes(sim, tmp_path):
    again = tmp_path / "again"
    ok(*SIMULATE_ARGS, "--out", again)
    written = sorted(p.relative_to(sim) for p in sim.rglob("*") if p.is_file())
    assert written == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    for rel in written:
        assert (sim / rel).read_bytes() == (again / rel).read_bytes(), rel


def test_simulate_magnification_and_particle_count(tmp_path):
    out = tmp_path / "m"
    ok("simulate", "--seed", SEED, "--particles", 1, "--magnification", -0.4, "--samples", 2,
       "--out", out)
    camera = tomllib.loads((out / "camera.toml").read_text())["camera"]
    assert camera["magnification"] == pytest.approx(-0.4)
    assert len(pd.read_parquet(out / "truth.parquet")) == 1
    assert (out / "raw" / "frame_0000.tif").is_file()
    assert not (out / "raw" / "frame_0001.tif").exists()


def test_simulate_diameter_range_and_realistic_optics(tmp_path):
    out = tmp_path / "r"
    ok("simulate", "--seed", SEED, "--particles", 30, "--diameter", "0.2:0.8", "--samples", 2,
       "--optics", "realistic", "--out", out)
    diameters = pd.read_parquet(out / "truth.parquet")["diameter"]
    assert diameters.between(0.2, 0.8).all() and diameters.max() / diameters.min() > 2
    optics = json.loads((out / "truth_optics.json").read_text())
    assert optics["realism"]["sensor"]["gain_sigma"] > 0
    assert optics["camera"] != optics["nominal_camera"]  # true optics differ from camera.toml
    result = run("simulate", "--optics", "perfect", "--out", tmp_path / "x")
    assert_error_line(result, "--optics", "ideal", code=2)
    result = run("simulate", "--shape", "cube", "--out", tmp_path / "x")
    assert_error_line(result, "--shape", "ellipsoid", code=2)


def test_simulate_ellipsoids(tmp_path):
    out = tmp_path / "e"
    ok("simulate", "--seed", SEED, "--particles", 12, "--shape", "ellipsoid", "--max-aspect", 2.5,
       "--samples", 2, "--out", out)
    truth = pd.read_parquet(out / "truth.parquet")
    assert (truth["shape"] == "ellipsoid").all() and truth["aspect"].between(1, 2.5).all()
    spheres = np.pi * truth["diameter"] ** 2 / 4
    assert (truth["projected_area"] != spheres).any()


def test_simulate_fragments(tmp_path):
    out = tmp_path / "f"
    ok("simulate", "--seed", SEED, "--particles", 6, "--shape", "fragment", "--max-aspect", 2.0,
       "--samples", 2, "--optics", "ideal", "--out", out)
    truth = pd.read_parquet(out / "truth.parquet")
    assert (truth["shape"] == "fragment").all() and truth["aspect"].between(1, 2.0).all()
    assert (truth["shape_seed"] >= 0).all() and truth["shape_seed"].nunique() == 6
    assert "transmission" not in truth.columns           # ideal optics: no particle effects


# A particle on the optical axis, 6 mm behind the focal plane, in its own data set made
# from a scene file with another seed.
SCENE_Z_MM = 6.0
SCENE_TOML = f"""
camera = "small"
seed = {SEED + 1}
[[particles]]
x = 0.0
y = 0.0
z = {SCENE_Z_MM}
diameter = 0.6
"""


@pytest.fixture(scope="module")
def scene_sim(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("scene")
    (folder / "scene.toml").write_text(SCENE_TOML)
    ok("simulate", "--scene", folder / "scene.toml", "--optics", "ideal", "--out", folder / "sim")
    return folder / "sim"


def test_simulate_scene_file(scene_sim):
    truth = pd.read_parquet(scene_sim / "truth.parquet")
    assert len(truth) == 1
    np.testing.assert_allclose(truth[["x", "y", "z", "diameter"]].to_numpy()[0],
                               [0.0, 0.0, SCENE_Z_MM, 0.6])
    for path in contract_files(scene_sim, 1):
        assert path.is_file(), path


def test_simulate_different_seed_gives_different_images(sim, scene_sim):
    assert (sim / "white.tif").read_bytes() != (scene_sim / "white.tif").read_bytes()
    assert not np.array_equal(read_raw(sim / "white.tif"), read_raw(scene_sim / "white.tif"))


def test_simulate_scene_file_seed_governs_the_optics_and_noise(scene_sim, tmp_path):
    """The scene file's seed seeds everything; --seed may repeat it but not contradict it."""
    scene = scene_sim.parent / "scene.toml"
    ok("simulate", "--scene", scene, "--seed", SEED + 1, "--optics", "ideal", "--out", tmp_path / "same")
    assert (tmp_path / "same" / "white.tif").read_bytes() == (scene_sim / "white.tif").read_bytes()
    ok("simulate", "--preset", "small", "--seed", SEED + 1, "--particles", 0, "--optics", "ideal",
       "--out", tmp_path / "p")
    assert (tmp_path / "p" / "white.tif").read_bytes() == (scene_sim / "white.tif").read_bytes()
    result = run("simulate", "--scene", scene, "--seed", SEED, "--out", tmp_path / "other")
    assert_error_line(result, "--seed", f"seed ({SEED + 1})", code=2)
    assert not (tmp_path / "other").exists()


def test_simulate_scene_for_another_camera_or_magnification(tmp_path):
    scene = tmp_path / "scene.toml"
    scene.write_text('camera = "small-rect"\nmagnification = -0.45\n[random]\nn = 1\n')
    ok("simulate", "--scene", scene, "--samples", 2, "--out", tmp_path / "sim")
    camera = tomllib.loads((tmp_path / "sim" / "camera.toml").read_text())["camera"]
    assert camera["grid_type"] == "rect"
    assert camera["magnification"] == pytest.approx(-0.45)
    # options the scene file decides are refused rather than silently ignored
    for extra in (["--preset", "small"], ["--magnification", "-0.5"]):
        result = run("simulate", "--scene", scene, *extra, "--out", tmp_path / "other")
        assert result.exit_code == 2
        assert not (tmp_path / "other").exists()


# --------------------------------------------------------------------------- calibrate-grid


def test_calibrate_grid_matches_the_true_grid(sim, calib_file):
    calib = load_calibration(calib_file)
    assert json.loads(calib_file.read_text())["format"] == "plenoptrack-calibration"
    true = LensletGrid.from_dict(json.loads((sim / "truth_optics.json").read_text())["true_grid"])
    assert calib.grid.grid_type == true.grid_type
    rows, cols = calib.grid.sensor_shape_px
    centres = calib.grid.centers().reshape(-1, 2)
    on_sensor = ((centres >= -0.5) & (centres <= [rows - 0.5, cols - 0.5])).all(axis=1)
    true_centres = true.centers().reshape(-1, 2)
    true_on_sensor = ((true_centres >= -0.5) & (true_centres <= [rows - 0.5, cols - 0.5])).all(axis=1)
    assert abs(on_sensor.sum() - true_on_sensor.sum()) <= 0.02 * true_on_sensor.sum()
    distance, _ = cKDTree(true_centres).query(centres[on_sensor])
    assert np.sqrt(np.mean(distance ** 2)) < CENTRE_RMS_PX


# --------------------------------------------------------------------------- views


def test_views_writes_every_view_and_a_mosaic(sim, calib_file, lf, tmp_path):
    from PIL import Image

    out, mosaic = tmp_path / "views.tif", tmp_path / "views.png"
    ok("views", sim / "raw" / "frame_0000.tif", "--calib", calib_file, "--out", out,
       "--mosaic", mosaic)
    n_v, n_u, n_t, n_s = lf.data.shape
    with tifffile.TiffFile(out) as tif:
        assert len(tif.pages) == n_v * n_u
        pages = tif.asarray()
    assert pages.shape == (n_v * n_u, n_t, n_s)
    # page = v * n_u + u
    iv, iu = n_v // 2, n_u // 2 + 1
    np.testing.assert_array_equal(pages[iv * n_u + iu], lf.data[iv, iu])
    with Image.open(mosaic) as png:
        assert png.format == "PNG" and png.mode == "L"
        width, height = png.size
    assert n_v * n_t <= height < n_v * (n_t + 5)
    assert n_u * n_s <= width < n_u * (n_s + 5)


def test_views_of_a_later_frame(sim, calib_file, tmp_path):
    ok("views", sim / "raw" / "frame_0001.tif", "--calib", calib_file, "--out", tmp_path / "v.tif")
    assert (tmp_path / "v.tif").is_file()
    result = run("views", sim / "raw" / "frame_0001.tif", "--calib", calib_file, "--frame", 1,
                 "--out", tmp_path / "w.tif")
    assert_error_line(result, "frame 1")
    assert not (tmp_path / "w.tif").exists()


# --------------------------------------------------------------------------- refocus


def _planes(path: Path) -> np.ndarray:
    planes = tifffile.imread(path)
    return planes[None] if planes.ndim == 2 else planes


def test_refocus_depth_alpha_and_stack(sim, calib_file, lf, tmp_path):
    raw = sim / "raw" / "frame_0000.tif"
    shape = lf.data.shape[2:]
    ok("refocus", raw, "--calib", calib_file, "--depth", -5, "--depth", 0, "--alpha", 1.0,
       "--out", tmp_path / "a.tif")
    planes = _planes(tmp_path / "a.tif")
    assert planes.shape == (3, *shape) and planes.dtype == np.float32
    # alpha = 1 is the nominal focal plane, depth 0
    np.testing.assert_allclose(planes[2], planes[1], rtol=1e-4, atol=1e-3 * planes[1].max())
    assert not np.allclose(planes[0], planes[1])
    ok("refocus", raw, "--calib", calib_file, "--stack", 7, "--zmin", -6, "--zmax", 6,
       "--out", tmp_path / "s.tif")
    assert _planes(tmp_path / "s.tif").shape == (7, *shape)
    ok("refocus", raw, "--calib", calib_file, "--depth", 2, "--alpha", 1.05, "--stack", 3,
       "--out", tmp_path / "m.tif")
    assert _planes(tmp_path / "m.tif").shape == (5, *shape)


def test_refocus_particle_sharpest_in_the_plane_nearest_its_depth(scene_sim, tmp_path):
    calib = tmp_path / "calib.json"
    ok("calibrate-grid", scene_sim / "white.tif", "--camera", scene_sim / "camera.toml",
       "--out", calib)
    depths = np.linspace(-10.0, 10.0, 11)  # 2 mm apart
    raw = scene_sim / "raw" / "frame_0000.tif"
    ok("refocus", raw, "--calib", calib, "--stack", len(depths), "--zmin", depths[0],
       "--zmax", depths[-1], "--out", tmp_path / "stack.tif")
    stack = _planes(tmp_path / "stack.tif")
    assert stack.shape[0] == len(depths)
    lf = decode(read_raw(raw), load_calibration(calib).grid)
    curve = sharpness(stack, center=lf.axis_st, half_width=8)  # the particle is on the axis
    assert depths[int(np.argmax(curve))] == pytest.approx(SCENE_Z_MM)
    assert curve.max() > 2 * curve[0] and curve.max() > 2 * curve[-1]


def test_refocus_needs_planes(sim, calib_file, tmp_path):
    result = run("refocus", sim / "raw" / "frame_0000.tif", "--calib", calib_file,
                 "--out", tmp_path / "r.tif")
    assert result.exit_code == 2
    assert "--depth" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "r.tif").exists()


@pytest.mark.parametrize("args", [["--alpha", "0"], ["--alpha", "-1"], ["--depth", "nan"],
                                  ["--depth", "-250"], ["--stack", "3", "--zmin", "nan"]],
                         ids=["alpha0", "alpha-neg", "depth-nan", "depth-before-lens", "zmin-nan"])
def test_refocus_refuses_impossible_planes(sim, calib_file, tmp_path, args):
    result = run("refocus", sim / "raw" / "frame_0000.tif", "--calib", calib_file, *args,
                 "--out", tmp_path / "r.tif")
    assert result.exit_code == 2, (result.stderr, result.exception)
    assert "Traceback" not in result.stderr and isinstance(result.exception, SystemExit)
    assert not (tmp_path / "r.tif").exists()


# --------------------------------------------------------------------------- bad input

RAW_CASES = {
    "missing": ("missing.tif", "not found"),
    "text": ("text.tif", "not a readable TIFF"),
    "float32": ("float.tif", "uint16"),
    "wrong-size": ("small.tif", "500 x 700"),
}


@pytest.mark.parametrize("command", ["views", "refocus"])
@pytest.mark.parametrize("case", sorted(RAW_CASES))
def test_bad_raw_image(bad_inputs, calib_file, command, case):
    folder, before = bad_inputs
    name, fragment = RAW_CASES[case]
    extra = ["--depth", "0"] if command == "refocus" else ["--mosaic", folder / "m.png"]
    result = run(command, folder / name, "--calib", calib_file, *extra, "--out", folder / "out.tif")
    assert_error_line(result, name, fragment)
    assert_nothing_written(folder, before)


CALIB_CASES = {
    "missing": ("missing.json", "not found"),
    "corrupt": ("corrupt.json", "corrupt"),
    "camera-not-a-table": ("camera_number.json", "camera must be a table"),
    "not-json": ("corrupt.toml", "not valid JSON"),
    # square brackets in a message are printed as they are
    "unknown-camera-key": ("unknown_key.json", "[camera]: unknown key(s) ['bogus']"),
}


@pytest.mark.parametrize("command", ["views", "refocus"])
@pytest.mark.parametrize("case", sorted(CALIB_CASES))
def test_bad_calibration_file(bad_inputs, sim, command, case):
    folder, before = bad_inputs
    name, fragment = CALIB_CASES[case]
    extra = ["--depth", "0"] if command == "refocus" else []
    result = run(command, sim / "raw" / "frame_0000.tif", "--calib", folder / name, *extra,
                 "--out", folder / "out.tif")
    assert_error_line(result, name, fragment)
    assert_nothing_written(folder, before)


@pytest.mark.parametrize("camera, white, fragment", [
    ("corrupt.toml", None, "not valid TOML"),
    ("negative_f.toml", None, "focal_length_mm"),
    ("missing.toml", None, "not found"),
    (None, "text.tif", "not a readable TIFF"),
    (None, "float.tif", "uint16"),
    (None, "small.tif", "500 x 700"),
    (None, "missing.tif", "not found"),
])
def test_calibrate_grid_bad_input(bad_inputs, sim, camera, white, fragment):
    folder, before = bad_inputs
    camera_path = sim / "camera.toml" if camera is None else folder / camera
    white_path = sim / "white.tif" if white is None else folder / white
    result = run("calibrate-grid", white_path, "--camera", camera_path, "--out", folder / "c.json")
    assert_error_line(result, camera or white, fragment)
    assert_nothing_written(folder, before)


def test_simulate_unknown_preset(tmp_path):
    result = run("simulate", "--preset", "nope", "--out", tmp_path / "sim")
    assert_error_line(result, "nope", "small")
    assert not (tmp_path / "sim").exists()


@pytest.mark.parametrize("text, fragment", [
    ("camera = 'small'\n[[particles]]\nx =\n", "not valid TOML"),
    ("camera = 'small'\n[[particles]]\nx = 0.0\ny = 0.0\nz = 500.0\ndiameter = 1.0\n", "outside"),
    ("camera = 'nope'\n[random]\nn = 1\n", "unknown camera preset"),
    ("camera = 'small'\n", "exactly one of"),
])
def test_simulate_bad_scene(tmp_path, text, fragment):
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    result = run("simulate", "--scene", scene, "--out", tmp_path / "sim")
    assert_error_line(result, fragment)
    assert not (tmp_path / "sim").exists()


def test_simulate_bad_values(tmp_path):
    for args, fragment in ((["--diameter", "0"], "diameter"), (["--magnification", "0"], "magnification")):
        result = run("simulate", *args, "--out", tmp_path / "sim")
        assert_error_line(result, fragment, code=2)
        assert not (tmp_path / "sim").exists()


def test_output_in_place_of_a_folder(bad_inputs, sim, calib_file):
    folder, before = bad_inputs
    raw = sim / "raw" / "frame_0000.tif"
    # the output's parent is a file
    result = run("views", raw, "--calib", calib_file, "--out", folder / "not_a_folder" / "v.tif")
    assert_error_line(result, "not_a_folder")
    # the mosaic path is a folder: the views TIFF of the failed run is not kept either
    (folder / "a_folder").mkdir()
    result = run("views", raw, "--calib", calib_file, "--out", folder / "v.tif",
                 "--mosaic", folder / "a_folder")
    assert_error_line(result, "a_folder", "is a folder", code=2)
    assert_nothing_written(folder, before | {"a_folder"})
    assert not list((folder / "a_folder").iterdir())


def test_views_and_refocus_read_a_frame_of_a_multi_page_raw(sim, calib_file, tmp_path):
    frames = np.stack([read_raw(sim / "raw" / f"frame_{f:04d}.tif") for f in range(N_FRAMES)])
    multi = tmp_path / "frames.tif"
    tifffile.imwrite(multi, frames)
    ok("views", multi, "--calib", calib_file, "--frame", 1, "--out", tmp_path / "multi.tif")
    ok("views", sim / "raw" / "frame_0001.tif", "--calib", calib_file, "--out", tmp_path / "one.tif")
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "multi.tif"),
                                  tifffile.imread(tmp_path / "one.tif"))
    ok("refocus", multi, "--calib", calib_file, "--frame", 1, "--depth", 3, "--out", tmp_path / "r1.tif")
    ok("refocus", multi, "--calib", calib_file, "--depth", 3, "--out", tmp_path / "r0.tif")
    assert not np.array_equal(tifffile.imread(tmp_path / "r1.tif"), tifffile.imread(tmp_path / "r0.tif"))
