"""Image coverage of a frame and the source density of a field of particles."""

import math
import warnings
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from test_perspective import _frame

from plenoptrack import preset
from plenoptrack.errors import CrowdedFrameWarning
from plenoptrack.locate.crowding import CROWDED_COVERAGE, image_coverage, source_density
from plenoptrack.locate.perspective import locate_frame
from plenoptrack.simulate import make_scene


def _lf(n_views, pixels=100):
    """One row of ``n_views`` valid views at u = 0, 1, ... and two rim views beyond."""
    return SimpleNamespace(spatial_mask=np.ones(pixels, bool),
                           u=np.arange(n_views + 2, dtype=float), v=np.zeros(1),
                           valid_fraction=np.r_[np.ones(n_views), np.full(2, 0.2)][None, :])


def test_image_coverage_is_the_median_valid_view_and_counts_empty_views():
    det = pd.DataFrame({"u": [0.0, 0.0, 1.0, 2.0], "v": [0.0, 0.0, 0.0, 0.0],
                        "area": [6, 4, 30, 50]})
    # three valid views with regions (0.1, 0.3, 0.5 of their 100 pixels)
    assert image_coverage(det, _lf(3)) == pytest.approx(0.3)
    # two more valid views without a region: the median falls to the second
    assert image_coverage(det, _lf(5)) == pytest.approx(0.1)
    assert image_coverage(det.iloc[:0], _lf(5)) == 0.0
    # regions in the rim views (less than half valid) do not count
    rim = pd.DataFrame({"u": [3.0, 4.0], "v": [0.0, 0.0], "area": [90, 90]})
    assert image_coverage(pd.concat([det, rim]), _lf(3)) == pytest.approx(0.3)


def test_source_density_is_the_image_area_over_the_array():
    camera = preset("small")
    rows, cols = camera.grid_shape
    array_mm2 = rows * camera.row_pitch_um * cols * camera.microlens_pitch_um * 1e-6
    # in focus an image is the particle times the magnification
    field = pd.DataFrame({"z": np.zeros(30), "diameter": np.full(30, 0.4)})
    in_focus = 30 * math.pi / 4 * (abs(camera.magnification) * 0.4) ** 2 / array_mm2
    assert source_density(field, camera) == pytest.approx(in_focus, rel=1e-12)
    # it adds up over particles, and out of focus the sub-aperture blur widens images
    assert source_density(pd.concat([field, field]), camera) == pytest.approx(2 * in_focus)
    for z in (-5.0, 5.0):
        assert source_density(field.assign(z=z), camera) > in_focus * (
            camera.object_distance_mm / (camera.object_distance_mm + z)) ** 2


@pytest.mark.parametrize("n, crowded", [(20, False), (160, True)])
def test_locate_reports_the_coverage_and_warns_when_crowded(small_calibrated, n, crowded):
    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=n, seed=5)
    truth_ns = source_density(scene.truth, calib.camera)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = locate_frame(_frame(optics, scene.truth, 5), calib)
    warned = any(issubclass(w.category, CrowdedFrameWarning) for w in caught)
    # the measured coverage follows the true source density while images seldom merge
    # (measured 0.067 for 0.046 and 0.367 for 0.376: the thresholded regions are a little
    # larger than the images, and merged images cover less than their summed area)
    assert abs(result.image_coverage - truth_ns) < 0.05, (result.image_coverage, truth_ns)
    assert (result.image_coverage > CROWDED_COVERAGE) == crowded == warned
