"""simulate_dataset writes the whole file contract, and the truth files round-trip."""

import json
import tomllib

import numpy as np
import pytest

from plenoptrack import load_camera, preset
from plenoptrack._columns import TRANSMISSION_COLUMN, TRUTH_COLUMNS, VELOCITY_COLUMNS
from plenoptrack.io import read_raw, read_table
from plenoptrack.simulate import SceneError, SimOptics, make_scene, simulate_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    return simulate_dataset("small", out, seed=5, n_particles=6, frames=2,
                            velocity_mm_per_frame=(0.2, 0.0, 0.5), magnification=-0.45,
                            dotcard_depths=[-5.0, 0.0, 5.0])


def test_writes_every_file(dataset):
    out = dataset.out_dir
    names = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert names == ["camera.toml", "dotcards/card_00.tif", "dotcards/card_01.tif",
                     "dotcards/card_02.tif", "dotcards/dotcards.toml", "raw/frame_0000.tif",
                     "raw/frame_0001.tif", "truth.parquet", "truth_optics.json", "white.tif"]
    for path in (*dataset.frame_paths, dataset.white_path, *dataset.dotcard_paths):
        image = read_raw(path)
        assert image.dtype == np.uint16 and image.shape == (600, 910)


def test_camera_and_cards_files(dataset):
    camera = load_camera(dataset.camera_path)
    assert camera == preset("small").with_magnification(-0.45)
    assert camera.image_side_f_number == pytest.approx(preset("small").image_side_f_number, rel=1e-4)
    cards = tomllib.loads(dataset.dotcards_path.read_text())
    assert cards["spacing_mm"] == dataset.dotcard.spacing_mm
    assert [c["z_mm"] for c in cards["cards"]] == [-5.0, 0.0, 5.0]
    assert [c["file"] for c in cards["cards"]] == ["card_00.tif", "card_01.tif", "card_02.tif"]


def test_truth_round_trips(dataset):
    truth = read_table(dataset.truth_path)
    # the default (realistic) optics add each particle's transmission and velocity
    assert list(truth.columns) == [*TRUTH_COLUMNS, TRANSMISSION_COLUMN, *VELOCITY_COLUMNS]
    assert truth["transmission"].between(0, 0.1).all()
    np.testing.assert_allclose(truth[list(VELOCITY_COLUMNS)], [[0.2, 0.0, 0.5]] * len(truth))
    assert truth.equals(dataset.truth)
    assert len(truth) == 12
    doc = json.loads(dataset.optics_path.read_text())
    assert SimOptics.from_dict(doc) == dataset.optics
    assert doc["true_grid"] == dataset.optics.true_grid.to_dict()


def test_frames_reproducible(dataset, tmp_path):
    again = simulate_dataset("small", tmp_path, seed=5, n_particles=6, frames=2,
                             velocity_mm_per_frame=(0.2, 0.0, 0.5), magnification=-0.45,
                             dotcard_depths=[])
    assert again.dotcard_paths == ()
    for a, b in zip(dataset.frame_paths, again.frame_paths):
        assert read_raw(a).tobytes() == read_raw(b).tobytes()
    assert read_raw(dataset.white_path).tobytes() == read_raw(again.white_path).tobytes()


def test_scene_camera_must_match(tmp_path):
    scene = make_scene(preset("small-rect"), n_particles=1)
    with pytest.raises(SceneError, match="pass scene.camera"):
        simulate_dataset("small", tmp_path, scene=scene, dotcard_depths=[])


def test_rerun_into_the_same_folder_replaces_the_data_set_as_a_whole(tmp_path):
    simulate_dataset("small", tmp_path, seed=1, n_particles=2, frames=3,
                     dotcard_depths=[-5.0, 0.0, 5.0])
    again = simulate_dataset("small", tmp_path, seed=1, n_particles=2, frames=1,
                             dotcard_depths=[0.0])
    assert sorted(p.name for p in (tmp_path / "raw").iterdir()) == ["frame_0000.tif"]
    assert sorted(p.name for p in (tmp_path / "dotcards").glob("*.tif")) == ["card_00.tif"]
    assert read_table(again.truth_path)["frame"].max() == 0
    assert sorted(p.name for p in tmp_path.parent.iterdir() if p.name.startswith(f".{tmp_path.name}")) == []


def test_a_folder_with_other_files_is_refused_untouched(tmp_path):
    simulate_dataset("small", tmp_path, seed=1, n_particles=1, dotcard_depths=[0.0])
    (tmp_path / "raw" / "notes.txt").write_text("mine")
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    with pytest.raises(SceneError, match=r"not part of a simulated data set \(raw/notes.txt\)"):
        simulate_dataset("small", tmp_path, seed=2, n_particles=1, dotcard_depths=[0.0])
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before


def test_a_failed_simulation_keeps_the_old_data_set_whole(tmp_path, monkeypatch):
    old = simulate_dataset("small", tmp_path / "sim", seed=1, n_particles=1, frames=2,
                           dotcard_depths=[0.0])
    before = {p: p.read_bytes() for p in (tmp_path / "sim").rglob("*") if p.is_file()}
    import plenoptrack.simulate.dataset as dataset

    def broken(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(dataset, "render_dotcard", broken)
    with pytest.raises(KeyboardInterrupt):
        simulate_dataset("small", tmp_path / "sim", seed=2, n_particles=3, frames=1,
                         dotcard_depths=[0.0])
    assert {p: p.read_bytes() for p in (tmp_path / "sim").rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim"]  # no temporary left
    assert old.truth_path.is_file()


def test_files_get_the_umask_mode(tmp_path):
    import os

    previous = os.umask(0o022)
    try:
        out = simulate_dataset("small", tmp_path / "sim", seed=1, n_particles=0,
                               dotcard_depths=[0.0])
    finally:
        os.umask(previous)
    for path in (out.white_path, out.truth_path, out.camera_path, out.dotcard_paths[0]):
        assert path.stat().st_mode & 0o777 == 0o644, path
    for folder in (out.out_dir, out.out_dir / "raw", out.out_dir / "dotcards"):
        assert folder.stat().st_mode & 0o777 == 0o755, folder


def test_overlapping_microlens_images_are_refused_with_the_f_number_that_works(tmp_path):
    camera = preset("small").with_changes(magnification=-0.3)  # f-number not re-set
    with pytest.raises(SceneError, match=r"overlap.*use f/\d"):
        simulate_dataset(camera, tmp_path / "sim", n_particles=0, dotcard_depths=[0.0])
    assert not (tmp_path / "sim").exists()


def test_another_magnification_still_gives_a_measurable_lenslet_grid(tmp_path):
    """The f-number follows the magnification, so the microlens images stay separate."""
    from plenoptrack.calibration import calibrate_from_white

    out = simulate_dataset("small", tmp_path / "sim", seed=2, n_particles=0,
                           magnification=-0.3, dotcard_depths=[])
    assert out.camera.microlens_fill == pytest.approx(1.0, abs=1e-3)
    calib, report = calibrate_from_white(out.white_path, load_camera(out.camera_path))
    assert calib.grid.shape == out.camera.grid_shape
    assert report.rms_residual_px < 0.2


def test_the_default_volume_and_cards_follow_the_depth_of_field_at_another_magnification(
        tmp_path):
    """A preset used at magnification M keeps its volume within the depth of field: the
    depth scales as 1/M^2 (small: 20 mm at -0.5, 5 mm at -1), and so do the default dot
    cards, which then calibrate. With 20 mm at M -1 the far cards lay five times the
    plenoptic depth of field out of focus and their dot lattice could not be found
    (seed 100 failed so)."""
    from plenoptrack.calibrate import calibrate
    from plenoptrack.locate.refocusing import depth_of_field_mm
    from plenoptrack.simulate.dotcard import default_dotcard_depths
    from plenoptrack.simulate.scene import default_volume, volume_depth_mm

    small = preset("small")
    assert volume_depth_mm(small) == 20.0
    assert volume_depth_mm(preset("hall2019")) == 50.0
    closer = small.with_magnification(-1.0)
    assert volume_depth_mm(closer) == pytest.approx(5.0)
    assert volume_depth_mm(small.with_magnification(-0.25)) == pytest.approx(80.0)
    near, far = depth_of_field_mm(closer)
    assert near < default_volume(closer).z_mm[0] and default_volume(closer).z_mm[1] < far
    np.testing.assert_allclose(default_dotcard_depths(closer)[[0, -1]], [-2.5, 2.5])
    custom = small.with_changes(name="mine")                 # not a preset: 15 % of s_o
    assert volume_depth_mm(custom) == pytest.approx(round(0.15 * custom.object_distance_mm, 1))
    out = simulate_dataset("small", tmp_path / "sim", seed=100, n_particles=0,
                           magnification=-1.0)
    calib, report = calibrate(out.white_path, out.out_dir / "dotcards", out.camera)
    assert report.rms_px < 0.3 and len(report.cards) == 11
