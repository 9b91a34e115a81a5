"""The terms of sigma change sigma only, and ``benchmarks/uncertainty_coverage.py
--ablate`` (which turns them off one at a time) relies on that."""

import warnings

import numpy as np
import pandas as pd
import pytest

from plenoptrack.locate.perspective import PerspectiveLocator, locate_frame
from plenoptrack.simulate import make_scene, render_frame


@pytest.fixture(scope="module")
def script(benchmark_module):
    with benchmark_module("uncertainty_coverage") as module:
        yield module


def test_every_ablation_is_a_real_change_of_the_solve_settings(script):
    defaults = PerspectiveLocator()
    assert script.ABLATIONS["defaults"] == {}
    for name, change in script.ABLATIONS.items():
        if name == "defaults":
            continue
        solve = defaults.updated({"solve": change}, source=name).solve
        assert solve != defaults.solve, name


def test_ablation_summary_gives_each_band_and_all_in_the_variants_order(script):
    # errors 0.5 and 2.5 sigma: half within 1 sigma, half beyond 2 and none beyond 3
    rows = []
    for variant, scale in (("refit_error off", 1.0), ("defaults", 2.0)):
        for band in ("sparse", "0.05"):
            e = np.array([0.5, 2.5, 0.5, 2.5])
            rows.append(pd.DataFrame({"dx": e, "dy": -e, "dz": e, "sigma_x": scale,
                                      "sigma_y": scale, "sigma_z": scale, "variant": variant,
                                      "band": band, "optics": "realistic"}))
    table = script.ablation_summary(pd.concat(rows, ignore_index=True))
    assert list(table["band"]) == ["0.05"] * 2 + ["all"] * 2 + ["sparse"] * 2
    assert list(table["variant"]) == ["defaults", "refit_error off"] * 3
    first = table[table["variant"] == "refit_error off"].iloc[0]
    assert first["x 1s"] == 0.5 and first["x 2s"] == 0.5 and first["x >3s"] == 0.0
    assert table[table["band"] == "all"]["n"].tolist() == [8, 8]
    # twice the sigma: every error within 2 sigma
    assert (table[table["variant"] == "defaults"]["z 2s"] == 1.0).all()


def test_turning_a_term_off_changes_sigma_but_never_a_position(small_calibrated):
    """A crowded frame (110 particles on the small camera: overlapping images, refitted
    and split particles), located with every term on and with each one off."""
    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=110, seed=21)
    raw = render_frame(optics, scene.truth, seed=np.random.default_rng([21, 3, 0]))
    changes = {"model_error": False, "sampling_error": False, "excess_scatter": False,
               "unexplained_error": False, "companion_error": False, "refit_error": False,
               "error_scale": 1.6}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        base = locate_frame(raw, calib).particles
        assert len(base) > 40
        sigma = ["sigma_x", "sigma_y", "sigma_z"]
        changed = {}
        for key, value in changes.items():
            locator = PerspectiveLocator().updated({"solve": {key: value}})
            found = locate_frame(raw, calib, locator=locator).particles
            np.testing.assert_array_equal(found[["x", "y", "z"]].to_numpy(),
                                          base[["x", "y", "z"]].to_numpy(), err_msg=key)
            ratio = found[sigma].to_numpy() / base[sigma].to_numpy()
            if key not in ("excess_scatter", "error_scale"):
                # a term only ever adds. Without the excess scatter the particle's own
                # centroid scatter, not the frame's typical one, sizes its sampling term,
                # which can be the larger of the two; a smaller error scale counts more
                # of a scatter as beyond chance (uncertainty.chance_chi2)
                assert np.nanmax(ratio) <= 1.0 + 1e-12, key
            changed[key] = np.nanmean(np.abs(ratio - 1.0) > 1e-9)
    # each term reaches some particles of this frame
    assert all(share > 0 for share in changed.values()), changed
