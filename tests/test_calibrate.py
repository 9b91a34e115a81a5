"""Tests of the calibration workflow (white image + dot cards -> calibration file).

One simulated 'small' data set (seed 7105, 11 dot cards from -10 to +10 mm) is shared by
the module; its true optics give an independent check of the fitted DLFC. Seed 7105 is the
one whose calibration used to stop: the segmentation drops dot (0, 0) in the central view
of the card at -8 mm (its 13-pixel region is too eccentric), and the indexing needed that
dot.
"""

import json
import shutil
import time
import warnings

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from plenoptrack.calibrate import (CalibrationReport, CardDepthWarning, DotCardImage,
                                   DotCardSet, calibrate, check_card_depths, dlfc_points,
                                   read_dotcards)
from plenoptrack.calibration import Calibration, load_calibration, save_calibration
from plenoptrack.cli import app
from plenoptrack.errors import CalibrationError, InputFileError
from plenoptrack.io import read_raw
from plenoptrack.lightfield import decode
from plenoptrack.locate.dlfc import DLFC
from plenoptrack.locate.segment import segment_views
from plenoptrack.simulate import render_frame, simulate_dataset

# well-separated particles: every view shows each one whole and alone
PARTICLES = pd.DataFrame({"x": [-3.0, 3.0, -2.5, 2.5, 0.0], "y": [-1.2, 1.2, 1.5, -1.5, 0.0],
                          "z": [-8.0, 7.5, 3.0, -3.5, 0.5], "diameter": 0.6})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return simulate_dataset("small", tmp_path_factory.mktemp("sim"), seed=7105, n_particles=0,
                            realism="ideal")


@pytest.fixture(scope="module")
def white(dataset):
    return read_raw(dataset.white_path)


@pytest.fixture(scope="module")
def points(dataset, white):
    """Dot measurements of all cards, flat-fielded (what calibrate fits)."""
    from plenoptrack.calibration import calibrate_from_white

    calib, _ = calibrate_from_white(white, dataset.camera)
    return calib, dlfc_points(dataset.out_dir / "dotcards", calib.grid, dataset.camera,
                              white=white)


@pytest.fixture(scope="module")
def calibrated(dataset, white):
    return calibrate(white, dataset.out_dir / "dotcards", dataset.camera, order=4)


# --- dot-card folder --------------------------------------------------------------------

def test_read_dotcards(dataset):
    cards = read_dotcards(dataset.out_dir / "dotcards")
    assert isinstance(cards, DotCardSet) and len(cards) == 11
    assert cards.spacing_mm == dataset.dotcard.spacing_mm
    assert cards.dot_diameter_mm == dataset.dotcard.dot_diameter_mm
    np.testing.assert_array_equal(cards.depths_mm, dataset.dotcard_depths_mm)
    assert [c.path for c in cards.cards] == list(dataset.dotcard_paths)
    # the TOML file itself is accepted too
    assert read_dotcards(dataset.dotcards_path) == cards


def _copy_cards(dataset, tmp_path, toml_text=None):
    folder = tmp_path / "cards"
    shutil.copytree(dataset.out_dir / "dotcards", folder)
    if toml_text is not None:
        (folder / "dotcards.toml").write_text(toml_text)
    return folder


@pytest.mark.parametrize("toml_text, match", [
    (None, "dot-card description not found"),
    ("spacing_mm = 1.25\ncards = []\n", "lists no dot cards"),
    ("spacing_mm = 1.25\n", "lists no dot cards"),
    ('cards = [{ file = "card_00.tif", z_mm = 0.0 }]\n', "spacing_mm .* is missing"),
    ('spacing_mm = -1.0\ncards = [{ file = "card_00.tif", z_mm = 0.0 }]\n',
     "spacing_mm must be a positive number"),
    ('spacing_mm = 1.25\ncards = [{ file = "card_00.tif" }]\n', r"cards\[0\] must have `file` and `z_mm`"),
    ('spacing_mm = 1.25\ncards = [{ file = "card_00.tif", z_mm = 0.0 }, '
     '{ file = "card_01.tif", z_mm = 0.0 }]\n', r"several cards at z_mm = \[0.0\]"),
    ("spacing_mm = [\n", "not valid TOML"),
])
def test_bad_dotcards_toml(dataset, tmp_path, toml_text, match):
    folder = _copy_cards(dataset, tmp_path, toml_text)
    if toml_text is None:
        (folder / "dotcards.toml").unlink()
    with pytest.raises(InputFileError, match=match) as info:
        read_dotcards(folder)
    assert "dotcards.toml" in str(info.value)  # the message names the file


def test_missing_card_file(dataset, tmp_path):
    folder = _copy_cards(dataset, tmp_path)
    (folder / "card_03.tif").unlink()
    with pytest.raises(InputFileError, match=r"card_03.tif: dot-card image listed in "
                       r"dotcards.toml \(cards\[3\]\) not found"):
        read_dotcards(folder)


def test_missing_folder(tmp_path):
    with pytest.raises(InputFileError, match="dot-card folder not found"):
        read_dotcards(tmp_path / "nowhere")


# --- calibration points -------------------------------------------------------------

def test_dlfc_points_table(points, dataset):
    _, table = points
    assert {"u", "v", "s", "t", "x", "y", "z", "i", "j", "card"} <= set(table.columns)
    assert table["card"].dtype == np.int64
    assert sorted(table["card"].unique()) == list(range(11))
    for k, z in enumerate(dataset.dotcard_depths_mm):
        sub = table[table["card"] == k]
        assert (sub["z"] == z).all()
        assert sub.groupby(["u", "v"]).ngroups == 145      # every valid view
    np.testing.assert_allclose(table["x"] / dataset.dotcard.spacing_mm, table["i"])


def test_dlfc_points_central_view_match_truth(points, dataset):
    """Dot centroids in the central view sit where the simulator's chief ray lands."""
    calib, table = points
    lf = decode(read_raw(dataset.dotcard_paths[0]), calib.grid)
    centre = table[(table["u"] == 0) & (table["v"] == 0)]
    true_st = lf.from_sensor(dataset.optics.world_to_pixels(centre[["x", "y", "z"]].to_numpy()))
    err = np.hypot(centre["s"] - true_st[:, 0], centre["t"] - true_st[:, 1])
    assert np.sqrt(np.mean(err ** 2)) < 0.1


# --- the fit ------------------------------------------------------------------------

def test_calibrate_order4_residual(calibrated):
    calib, report = calibrated
    assert isinstance(calib, Calibration) and isinstance(report, CalibrationReport)
    assert calib.dlfc.order == 4 and report.order == 4
    assert report.rms_px <= 0.1
    assert report.fit.n_rejected < 0.02 * (report.fit.n_points + report.fit.n_rejected)
    cards = report.cards
    assert list(cards["z_mm"]) == sorted(cards["z_mm"]) and len(cards) == 11
    assert (cards["rms_px"] <= 0.1).all()
    assert (cards["n_views"] == 145).all()
    assert cards["n_points"].sum() == report.fit.n_points + report.fit.n_rejected
    # the model error per card is the fit report's row at the mean depth of the card's
    # dots: within a micrometre of the stated depth on these untilted cards
    rows = np.asarray(report.fit.model_error_by_depth_mm)
    assert rows.shape == (11, 4)
    for card in cards.itertuples():
        z, ex, ey, ez = rows[np.argmin(np.abs(rows[:, 0] - card.z_mm))]
        assert z == pytest.approx(card.z_mm, abs=1e-3)
        assert card.model_error_lateral_mm == pytest.approx(np.hypot(ex, ey))
        assert card.model_error_z_mm == pytest.approx(ez)
    # the cards of the ideal simulator stand perpendicular to the axis: their measured
    # slopes are noise, within 3 standard errors of 0, and none is applied
    tilt = cards[["tilt_x", "tilt_y"]].to_numpy()
    error = cards[["tilt_x_error", "tilt_y_error"]].to_numpy()
    print("slopes / standard errors:", np.round(tilt / error, 2).tolist())
    assert np.all(np.isfinite(tilt)) and np.all(np.abs(tilt) < 3 * error)
    assert np.all(cards[["tilt_x_applied", "tilt_y_applied"]].to_numpy() == 0)
    # on this ideal camera the dots' errors are nearly all their own noise
    assert cards["model_error_z_mm"].max() < report.fit.position_rms_mm[2]
    assert set(report.seconds) == {"grid", "dots", "fit", "total"}


def test_order_comparison(calibrated, points, dataset):
    """Order 4 fits better than 3; order 5 is refused: the card shows only 5 dot rows."""
    from plenoptrack.locate.dlfc import fit_dlfc

    _, table = points
    # the dots where calibrate puts them: each card tilted by its measured slopes
    tilt = calibrated[1].cards[["tilt_x_applied", "tilt_y_applied"]].to_numpy()[
        table["card"].to_numpy()]
    table = table.assign(z_card=table["z"],
                         z=table["z"] + tilt[:, 0] * table["x"] + tilt[:, 1] * table["y"])
    rms = {order: fit_dlfc(table, order=order, group_by="z_card", reject_k=5.0).report.rms_px
           for order in (3, 4)}
    print(f"DLFC RMS residual, small preset: order 3 {rms[3]:.4f} px, order 4 {rms[4]:.4f} px")
    assert rms[4] < rms[3]
    assert rms[4] == pytest.approx(calibrated[1].rms_px)
    with pytest.raises(CalibrationError, match=r"only 5 distinct dot rows \(y\); an order-5 "
                       r"DLFC needs at least 6.*at most 4"):
        calibrate(dataset.white_path, dataset.out_dir / "dotcards", dataset.camera, order=5)


def test_too_few_depths_for_order(dataset, tmp_path):
    folder = _copy_cards(dataset, tmp_path, 'spacing_mm = 1.25\ncards = [\n' + "".join(
        f'  {{ file = "card_{k:02d}.tif", z_mm = {z} }},\n'
        for k, z in enumerate(dataset.dotcard_depths_mm[:3])) + "]\n")
    with pytest.raises(CalibrationError, match="3 card depth.*cannot determine an order-4 DLFC"):
        calibrate(dataset.white_path, folder, dataset.camera, order=4)


def test_dlfc_central_view_matches_true_optics(calibrated, dataset):
    """Between dots and between card depths, P(x, y, z, 0, 0) is where the chief ray lands."""
    calib, _ = calibrated
    dlfc = calib.dlfc
    lf = decode(read_raw(dataset.white_path), calib.grid)
    rng = np.random.default_rng(7)
    n = 2000
    xyz = np.column_stack([rng.uniform(-4.5, 4.5, n), rng.uniform(-2.2, 2.2, n),
                           rng.uniform(-10, 10, n)])
    true_st = lf.from_sensor(dataset.optics.world_to_pixels(xyz))
    s, t = dlfc.predict(xyz[:, 0], xyz[:, 1], xyz[:, 2], 0.0, 0.0)
    err = np.hypot(s - true_st[:, 0], t - true_st[:, 1])
    assert np.sqrt(np.mean(err ** 2)) < 0.03
    assert err.max() < 0.1


def test_dlfc_predicts_particle_views(calibrated, dataset, white):
    """A rendered particle is found, view by view, where the DLFC says it should be."""
    calib, _ = calibrated
    dlfc = calib.dlfc
    raw = render_frame(dataset.optics, PARTICLES, seed=5)
    lf = decode(raw, calib.grid, white=white)
    det = segment_views(lf)
    views = det[["u", "v"]].drop_duplicates().to_numpy()
    for p in PARTICLES.itertuples():
        s, t = dlfc.predict(p.x, p.y, p.z, views[:, 0], views[:, 1])
        dists = []
        for (u, v), ps, pt in zip(views, s, t):
            in_view = det[(det["u"] == u) & (det["v"] == v)]
            dists.append(np.hypot(in_view["s"] - ps, in_view["t"] - pt).min())
        dists = np.asarray(dists)
        found = dists < 2.0        # the segmentation misses a particle in a few views
        assert found.mean() > 0.85, (p, found.mean())
        assert np.median(dists[found]) < 0.1, (p, np.median(dists[found]))
        # the worst are rim views, whose partial vignetting biases the centroid
        assert np.mean(dists[found] < 0.3) > 0.9, (p, np.sort(dists[found])[-5:])


def test_seed_7105_dot_origin_on_the_axis(calibrated, dataset):
    """Regression: seed 7105 calibrates, and every card's dot (0, 0) is on the axis.

    At u = v = 0 the image of a point on the optical axis does not move with depth, so the
    DLFC must map (0, 0, z) of every card to one (s, t): the true axis image.
    """
    calib, report = calibrated
    assert report.rms_px < 0.08
    assert (report.cards["rms_px"] < 0.1).all()
    assert not report.cards["reindexed"].any() and (report.cards["origin_miss"] < 0.01).all()
    z = np.asarray(dataset.dotcard_depths_mm)
    s, t = calib.dlfc.predict(np.zeros_like(z), np.zeros_like(z), z, 0.0, 0.0)
    lf = decode(read_raw(dataset.white_path), calib.grid)
    axis = lf.from_sensor(dataset.optics.world_to_pixels([0.0, 0.0, 0.0]))
    assert np.hypot(s - axis[0], t - axis[1]).max() < 0.03
    # one whole dot off (9.6 view px) on any card would move its row far more
    s1, _ = calib.dlfc.predict(np.full_like(z, 1.25), np.zeros_like(z), z, 0.0, 0.0)
    assert (s1 - s).min() > 9.0


def test_card_without_dot_on_the_axis_refused(dataset, tmp_path):
    """A card moved sideways by half a dot spacing has no dot where the others see (0, 0)."""
    import tifffile

    shifted = tmp_path / "card_03_shifted.tif"
    # 5 lenslets (70 px) to the side: about half a dot spacing (9.6 samples) in every view
    tifffile.imwrite(shifted, np.roll(read_raw(dataset.dotcard_paths[3]), 70, axis=1))
    cards = read_dotcards(dataset.out_dir / "dotcards")
    cards = DotCardSet(source=cards.source, spacing_mm=cards.spacing_mm, cards=tuple(
        DotCardImage(path=shifted, z_mm=c.z_mm) if k == 3 else c
        for k, c in enumerate(cards.cards)))
    with pytest.raises(CalibrationError, match=r"card_03_shifted.tif: the dot lattice of this "
                       r"card \(z_mm = -4\) has no dot where 10 of the 11 cards see dot "
                       r"\(0, 0\).*0\.[3-5]\d dot spacings away.*remove it from dotcards.toml"):
        calibrate(dataset.white_path, cards, dataset.camera)


# --- card depths -------------------------------------------------------------------

def _restated(dataset, tmp_path, depths):
    """A dotcards.toml for the simulated card images with other stated depths."""
    folder = tmp_path / "restated"
    folder.mkdir()
    entries = "".join(f'  {{ file = "{p}", z_mm = {float(z)!r} }},\n'
                      for p, z in zip(dataset.dotcard_paths, depths))
    (folder / "dotcards.toml").write_text(
        f"spacing_mm = {dataset.dotcard.spacing_mm}\ncards = [\n{entries}]\n")
    return folder


def test_card_depths_match_parallax(calibrated, dataset):
    _, report = calibrated
    check = report.depth_check
    np.testing.assert_array_equal(check.stated_mm, dataset.dotcard_depths_mm)
    assert 0.95 < check.scale < 1.02 and abs(check.offset_mm) < 0.1
    assert np.abs(check.residual_mm).max() < 0.1 and not check.outliers.any()
    np.testing.assert_allclose(report.cards["z_implied_mm"], report.cards["z_mm"], atol=0.2)


@pytest.mark.parametrize("change, match", [
    (lambda z: -z, "reversed in sign"),
    (lambda z: z / 10, "about 9.* times too small .are they in cm"),
])
def test_wrong_card_depths_refused(dataset, tmp_path, change, match):
    z = np.asarray(dataset.dotcard_depths_mm) + 0.0
    folder = _restated(dataset, tmp_path, change(z) + 0.0)
    with pytest.raises(CalibrationError, match=match) as info:
        calibrate(dataset.white_path, folder, dataset.camera)
    message = str(info.value)
    assert str(folder / "dotcards.toml") in message
    assert "card_00.tif stated" in message and "implied" in message


def test_depth_check_can_be_switched_off(dataset, tmp_path):
    folder = _restated(dataset, tmp_path, -np.asarray(dataset.dotcard_depths_mm) + 0.0)
    _, report = calibrate(dataset.white_path, folder, dataset.camera, check_depths=False)
    assert report.depth_check is None
    np.testing.assert_allclose(report.cards["z_implied_mm"], -report.cards["z_mm"], atol=0.3)


def test_single_wrong_card_warned(dataset, tmp_path):
    z = np.array(dataset.dotcard_depths_mm)
    z[[3, 4]] = z[[4, 3]]                                   # two files swapped
    folder = _restated(dataset, tmp_path, z)
    with pytest.warns(CardDepthWarning, match=r"2 card\(s\) disagree.*card_03.tif z_mm = -2 "
                      r"reads as -3.9.*card_04.tif z_mm = -4 reads as -1.9"):
        _, report = calibrate(dataset.white_path, folder, dataset.camera)
    assert report.depth_check.outliers.tolist() == [k in (3, 4) for k in range(11)]


@pytest.mark.parametrize("change, outcome", [
    (lambda z: -z, "reversed in sign"),
    (lambda z: z / 10, "about 9.* times too small .are they in cm"),
    (lambda z: z * 25.4, "about 25.* times too large"),
    (lambda z: z * 1.03, None),                      # nominal optics 3 % off
    (lambda z: z / 1.03, None),
    (lambda z: z + 2.0, None),                       # traverse zero 2 mm off focus
    (lambda z: np.where(z == 6.0, 5.0, z), "card_08.tif z_mm = 5 reads as 6.0"),
    (lambda z: np.where(z == -10.0, 10.0, z), "card_00.tif z_mm = 10 reads as -10"),
])
def test_check_card_depths(calibrated, change, outcome):
    """The check on the depths the seed-7105 cards' parallax implies."""
    _, report = calibrated
    implied = report.cards["z_implied_mm"].to_numpy()
    stated = change(report.cards["z_mm"].to_numpy()) + 0.0
    files = report.cards["file"].tolist()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        if outcome is None:
            check = check_card_depths(stated, implied, source="cards.toml", files=files)
            assert not check.outliers.any()
        elif "reads as" in outcome:
            with pytest.warns(CardDepthWarning, match=outcome):
                check = check_card_depths(stated, implied, source="cards.toml", files=files)
            assert check.outliers.sum() == 1 and 0.95 < check.scale < 1.02
        else:
            with pytest.raises(CalibrationError, match="cards.toml: the card depths look "
                               + outcome):
                check_card_depths(stated, implied, source="cards.toml", files=files)


# --- calibration file ---------------------------------------------------------------

def test_calibration_file_round_trip(calibrated, tmp_path):
    calib, _ = calibrated
    path = save_calibration(calib, tmp_path / "calib.json")
    loaded = load_calibration(path, camera=calib.camera)
    assert loaded.has_dlfc and isinstance(loaded.dlfc, DLFC)
    np.testing.assert_array_equal(loaded.dlfc.coefficients, calib.dlfc.coefficients)
    x = np.array([1.0, -2.0]), np.array([0.5, 1.0]), np.array([-3.0, 7.0])
    np.testing.assert_array_equal(loaded.dlfc.predict(*x, 2.0, -1.0),
                                  calib.dlfc.predict(*x, 2.0, -1.0))
    doc = json.loads(path.read_text())
    assert doc["format"] == "plenoptrack-calibration" and doc["version"] == 1
    assert doc["dlfc"]["order"] == 4 and doc["dlfc"]["fit"]["group_by"] == "z"


def test_calibration_measures_the_views_edge_blur(calibrated, dataset, tmp_path):
    calib, _ = calibrated
    rows = calib.edge_blur_by_depth
    cards = read_dotcards(dataset.out_dir / "dotcards")
    # one row per card depth; a view's small aperture blurs an image away from focus
    np.testing.assert_allclose(rows[:, 0], np.sort(cards.depths_mm))
    assert np.all((rows[:, 1] > 0.3) & (rows[:, 1] < 1.0)), rows
    focus = np.argmin(np.abs(rows[:, 0]))
    assert rows[0, 1] > rows[focus, 1] + 0.1 and rows[-1, 1] > rows[focus, 1] + 0.1, rows
    loaded = load_calibration(save_calibration(calib, tmp_path / "calib.json"))
    np.testing.assert_array_equal(loaded.edge_blur_by_depth, rows)
    assert Calibration(camera=calib.camera, grid=calib.grid).edge_blur_by_depth is None


@pytest.mark.parametrize("rows", [[[0.0, -0.5]], [[0.0, 0.5, 1.0]], [[None, 0.5]], "x"])
def test_corrupt_edge_blur_refused(calibrated, tmp_path, rows):
    calib, _ = calibrated
    path = save_calibration(calib, tmp_path / "calib.json")
    doc = json.loads(path.read_text())
    doc["edge_blur_by_depth_px"] = rows
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="corrupt edge blur table") as info:
        load_calibration(path)
    assert str(path) in str(info.value)


def test_calibration_measures_the_pixel_locking_pattern(calibrated, tmp_path):
    """The dot cards' centroids scatter about the DLFC's predictions by a pull that
    repeats with the lens lattice: the calibration stores it (every card depth, so from
    near focus on), and the file keeps it."""
    calib, _ = calibrated
    pattern = calib.locking_pattern
    assert pattern is not None and pattern.harmonics == 1
    assert pattern.travel_range[0] < 0.5 < 4.0 < pattern.travel_range[1]
    assert np.all(pattern.rms_px > 0.005) and np.all(pattern.rms_px < 0.1), pattern.rms_px
    # the dots' images: 0.4 mm dots at magnification -0.5 are about 2.6 view pixels wide
    assert 1.5 < pattern.image_diameter_px < 4.5, pattern.image_diameter_px
    loaded = load_calibration(save_calibration(calib, tmp_path / "calib.json"))
    np.testing.assert_array_equal(loaded.locking_pattern.coef, pattern.coef)
    assert loaded.locking_pattern.travel_range == pattern.travel_range
    assert Calibration(camera=calib.camera, grid=calib.grid).locking_pattern is None


@pytest.mark.parametrize("change", [{"harmonics": 0}, {"coef_px": [[1.0]]},
                                    {"travel_range_px": [2.0, 1.0]}, {"rms_px": "x"}, None])
def test_corrupt_locking_pattern_refused(calibrated, tmp_path, change):
    calib, _ = calibrated
    path = save_calibration(calib, tmp_path / "calib.json")
    doc = json.loads(path.read_text())
    doc["locking_pattern"] = None if change is None else {**doc["locking_pattern"], **change}
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="corrupt pixel-locking pattern") as info:
        load_calibration(path)
    assert str(path) in str(info.value)


def test_grid_only_calibration_has_no_dlfc(calibrated):
    calib, _ = calibrated
    grid_only = Calibration(camera=calib.camera, grid=calib.grid, vignetting=calib.vignetting)
    assert not grid_only.has_dlfc
    with pytest.raises(CalibrationError, match="calibration file has no DLFC; run "
                       "`plenoptrack calibrate` with dot cards"):
        grid_only.dlfc
    assert grid_only.with_dlfc(calib.dlfc).dlfc.order == 4


@pytest.mark.parametrize("corrupt, match", [
    (lambda d: d.__setitem__("dlfc", 3), "not a DLFC section"),
    (lambda d: d["dlfc"].__setitem__("coefficients", [[1.0, 2.0]]), "coefficients must have shape"),
    (lambda d: d["dlfc"].__setitem__("order", 9), "DLFC order must be one of"),
    (lambda d: d["dlfc"].__setitem__("version", 99), "DLFC version 99 is not supported"),
    (lambda d: d["dlfc"]["centre"].__setitem__(0, None), "centre"),
])
def test_corrupt_dlfc_section_refused(calibrated, tmp_path, corrupt, match):
    calib, _ = calibrated
    path = save_calibration(calib, tmp_path / "calib.json")
    doc = json.loads(path.read_text())
    corrupt(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match=match) as info:
        load_calibration(path)
    assert str(path) in str(info.value)


# --- command line -------------------------------------------------------------------

def test_cli_calibrate(dataset, tmp_path):
    out = tmp_path / "calib.json"
    result = CliRunner().invoke(app, [
        "calibrate", "--white", str(dataset.white_path), "--dotcards",
        str(dataset.out_dir / "dotcards"), "--camera", str(dataset.camera_path),
        "--out", str(out), "--order", "3"])
    assert result.exit_code == 0, result.output
    for text in ("DLFC order", "points used", "card_00.tif", "card_10.tif", "RMS", "pitch"):
        assert text in result.output
    calib = load_calibration(out, camera=dataset.camera)
    assert calib.dlfc.order == 3 and calib.dlfc.report.rms_px < 0.1
    # a table gives each card's model error at its depth, lateral and depth in um
    table = result.output.split("DLFC model error per dot card")[1]
    first = next(line for line in table.splitlines() if "card_00.tif" in line).split()
    _, ex, ey, ez = calib.dlfc.report.model_error_by_depth_mm[0]
    assert f"{1e3 * np.hypot(ex, ey):.1f}" in first and f"{1e3 * ez:.1f}" in first


@pytest.mark.parametrize("breakage, match", [
    ("no-toml", "dot-card description not found"),
    ("no-card", "card_02.tif: dot-card image listed"),
    ("no-cards", "lists no dot cards"),
])
def test_cli_calibrate_bad_dotcards(dataset, tmp_path, breakage, match):
    folder = _copy_cards(dataset, tmp_path, "spacing_mm = 1.25\ncards = []\n"
                         if breakage == "no-cards" else None)
    if breakage == "no-toml":
        (folder / "dotcards.toml").unlink()
    elif breakage == "no-card":
        (folder / "card_02.tif").unlink()
    out = tmp_path / "calib.json"
    result = CliRunner().invoke(app, [
        "calibrate", "--white", str(dataset.white_path), "--dotcards", str(folder),
        "--camera", str(dataset.camera_path), "--out", str(out)])
    assert result.exit_code == 1
    assert match in " ".join(result.output.split())
    assert "Traceback" not in result.output
    assert not out.exists()


# --- full sensor ----------------------------------------------------------------------

@pytest.mark.slow
def test_full_sensor_hall2019(tmp_path):
    """hall2019, 11 full-sensor cards (6600 x 4400) over +-25 mm: residual and time."""
    data = simulate_dataset("hall2019", tmp_path / "hall", seed=0, n_particles=0,
                            realism="ideal")
    t0 = time.perf_counter()
    calib, report = calibrate(data.white_path, data.out_dir / "dotcards", data.camera)
    seconds = time.perf_counter() - t0
    print(f"hall2019 calibration: {seconds:.1f} s, {report.seconds}, RMS {report.rms_px:.4f} px")
    print(report.cards.to_string())
    assert report.rms_px < 0.1
    assert (report.cards["rms_px"] < 0.15).all()
    assert (report.cards["n_views"] == 145).all()
    lf = decode(read_raw(data.white_path), calib.grid)
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(-10, 10, 500), rng.uniform(-7, 7, 500),
                           rng.uniform(-25, 25, 500)])
    true_st = lf.from_sensor(data.optics.world_to_pixels(xyz))
    s, t = calib.dlfc.predict(xyz[:, 0], xyz[:, 1], xyz[:, 2], 0.0, 0.0)
    assert np.sqrt(np.mean((s - true_st[:, 0]) ** 2 + (t - true_st[:, 1]) ** 2)) < 0.06


# --- card tilts ----------------------------------------------------------------------

def _card_points(camera, geometry, z_mm, tilt, *, spacing=1.25, n=9, noise_px=0.0, rng=None):
    """Dot measurements of one card whose dot (i, j) lies at depth
    ``z_mm + tilt[0] x + tilt[1] y``: each dot's image moves across the views by the
    parallax of that depth (:meth:`ProjectionGeometry.parallax_per_u` of the camera's
    ``alpha`` there), the independent forward model of what :func:`card_tilts` inverts."""
    views = np.arange(-3, 4, dtype=float)
    rows = []
    for i in range(-n // 2 + 1, n // 2 + 1):
        for j in range(-n // 2 + 1, n // 2 + 1):
            x, y = i * spacing, j * spacing
            depth = z_mm + tilt[0] * x + tilt[1] * y
            p = float(geometry.parallax_per_u(camera.alpha_for_depth(depth)))
            for u in views:
                for v in views:
                    s = 50.0 + 10.0 * i + p * u
                    t = 40.0 + 10.0 * j + p * v
                    if rng is not None:
                        s, t = s + noise_px * rng.standard_normal(), t + noise_px * rng.standard_normal()
                    rows.append((0, i, j, u, v, s, t, x, y, z_mm))
    return pd.DataFrame(rows, columns=["card", "i", "j", "u", "v", "s", "t", "x", "y", "z"])


def test_card_tilts_recovers_a_known_tilt():
    """A card tilted by (0.004, -0.007) at 5 mm behind focus reads back its slopes; with
    centroid noise, the slopes stay within 3 standard errors of the truth, and an
    untilted card's slopes within 3 standard errors of 0."""
    from plenoptrack import preset
    from plenoptrack.calibrate import card_tilts
    from plenoptrack.locate.cluster import ProjectionGeometry

    camera = preset("small")
    geometry = ProjectionGeometry.from_camera(camera, sample_spacing_px=camera.microlens_pitch_um
                                              / camera.pixel_pitch_um, axis_st=(50.0, 40.0))
    exact = _card_points(camera, geometry, 5.0, (0.004, -0.007))
    slopes, errors = card_tilts(exact, geometry, camera)
    np.testing.assert_allclose(slopes[0], [0.004, -0.007], atol=2e-5)
    assert np.all(errors[0] < 1e-5)
    rng = np.random.default_rng(3)
    for tilt in ((0.004, -0.007), (0.0, 0.0)):
        noisy = _card_points(camera, geometry, 5.0, tilt, noise_px=0.05, rng=rng)
        slopes, errors = card_tilts(noisy, geometry, camera)
        assert np.all(np.abs(slopes[0] - tilt) < 3 * errors[0]), (slopes, errors)
        assert np.all(errors[0] < 2e-3)
    # the depth scale of the nominal camera divides the slopes
    slopes, _ = card_tilts(exact, geometry, camera, scale=0.5)
    np.testing.assert_allclose(slopes[0], [0.008, -0.014], atol=4e-5)


def test_calibrate_measures_and_applies_the_cards_tilts(tmp_path):
    """Cards tilted on their mount (up to 1 degree, the simulator's target effects alone):
    calibrate reads each card's tilt from its dots' parallax within 3 standard errors
    (and 0.001) of the truth, applies the significant ones, and the DLFC then fits the
    dots better than with every card taken as perpendicular; without card_tilt (the
    default) the same tilts are reported and none applied."""
    import dataclasses

    from plenoptrack.simulate.realism import Realism, TargetEffects

    realism = dataclasses.replace(Realism.ideal(), target=TargetEffects(
        tilt_deg=1.0, depth_sigma_um=0.0, zero_offset_mm=0.0, print_sigma_um=0.0,
        centre_offset_mm=0.0))
    sim = simulate_dataset("small", tmp_path / "sim", seed=41, n_particles=0, realism=realism)
    truth = np.array([card["tilt"] for card in
                      json.loads((sim.out_dir / "truth_optics.json").read_text())["dotcards"]])
    white = read_raw(sim.white_path)
    _, tilted = calibrate(white, sim.out_dir / "dotcards", sim.camera, card_tilt=True)
    _, flat = calibrate(white, sim.out_dir / "dotcards", sim.camera)      # off by default
    measured = tilted.cards[["tilt_x", "tilt_y"]].to_numpy()
    error = tilted.cards[["tilt_x_error", "tilt_y_error"]].to_numpy()
    print("true tilts", np.round(truth, 4).tolist())
    print("measured - true", np.round(measured - truth, 4).tolist())
    assert np.abs(truth).max() > 0.01
    assert np.all(np.abs(measured - truth) < np.maximum(3 * error, 1e-3))
    applied = tilted.cards[["tilt_x_applied", "tilt_y_applied"]].to_numpy()
    significant = np.abs(measured) >= 3 * error
    assert significant.sum() >= len(truth)          # most slopes stand out of the noise
    np.testing.assert_array_equal(applied, np.where(significant, measured, 0.0))
    np.testing.assert_array_equal(flat.cards[["tilt_x", "tilt_y"]].to_numpy(), measured)
    assert np.all(flat.cards[["tilt_x_applied", "tilt_y_applied"]].to_numpy() == 0)
    print(f"DLFC RMS: tilts applied {tilted.rms_px:.4f} px, cards flat {flat.rms_px:.4f} px")
    assert tilted.rms_px < flat.rms_px


def test_a_card_is_called_tilted_only_when_its_measured_tilt_is_clearly_beyond_the_limit():
    """The far cards of a small field are measured from few blurred dots (slope 0.13 +-
    0.03 on a simulated card within 0.5 degrees): no warning. A tilt beyond the limit by
    more than three standard errors is reported, with what the user can do in each mode."""
    from pathlib import Path
    from types import SimpleNamespace

    from plenoptrack.calibrate import MAX_CARD_TILT_DEG, _warn_tilted_cards

    cards = SimpleNamespace(cards=[SimpleNamespace(path=Path(f"card_{k:02d}.tif"))
                                   for k in range(4)])
    limit = np.tan(np.radians(MAX_CARD_TILT_DEG))
    tilts = np.array([[-0.015, 0.134], [0.0, 2 * limit], [0.001, 0.002], [np.nan, np.nan]])
    errors = np.array([[0.019, 0.029], [0.003, 0.003], [0.001, 0.001], [np.nan, np.nan]])
    for applied, fix in ((False, "calibrate with --card-tilt"),
                         (True, "calibrate without --card-tilt")):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _warn_tilted_cards(cards, tilts, errors, applied=applied)
        assert [type(w.message) for w in caught] == [CardDepthWarning]
        message = str(caught[0].message)
        assert message.startswith("card_01.tif") and fix in message
        assert f"{np.degrees(np.arctan(2 * limit)):.1f} degrees" in message
