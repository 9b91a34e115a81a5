"""Large images and the views the aperture rim cuts (``solve.rim_min_valid``)."""

import math

import numpy as np
import pandas as pd
import pytest

from plenoptrack.errors import SettingsError
from plenoptrack.locate import refine
from plenoptrack.locate.frame import FrameContext, _fit_views, _large_image_px
from plenoptrack.locate.perspective import (PerspectiveLocator, _decoded, locate_frame,
                                            segment_frame)
from plenoptrack.locate.pixel_locking import SIZE_FACTOR
from plenoptrack.locate.settings import SolveSettings
from plenoptrack.simulate import render_frame


def _truth(rows, diameter):
    return pd.DataFrame({"frame": 0, "particle": np.arange(len(rows)),
                         "x": [r[0] for r in rows], "y": [r[1] for r in rows],
                         "z": [r[2] for r in rows], "diameter": diameter,
                         "projected_area": np.pi * diameter ** 2 / 4, "orientation": 0.0})


@pytest.fixture(scope="module")
def realistic_with_dots():
    """The 'small' camera with realistic optics (seed 0), calibrated on its flat-fielded
    dot cards with the dots' pixel-locking pattern (and so their image size) recorded,
    as ``plenoptrack calibrate`` does; and its decoded white image."""
    from plenoptrack.lightfield import decode
    from plenoptrack.simulate import render_white

    try:
        from .test_perspective import _calibrated
    except ImportError:  # tests/locate is not a package
        from test_perspective import _calibrated
    optics, calib = _calibrated("small", realism="realistic", locking=True)
    white = render_white(optics, seed=np.random.default_rng([0, 2]))   # the same white
    return optics, calib, decode(white, calib.grid)


def test_the_setting_is_a_fraction():
    assert SolveSettings(rim_min_valid=0.0).rim_min_valid == 0.0
    for bad in (-0.1, 1.5, True, "0.9"):
        with pytest.raises(SettingsError, match="rim_min_valid"):
            SolveSettings(rim_min_valid=bad)


def test_large_means_twice_the_dots_and_nothing_without_their_size(realistic_with_dots):
    _, calib, _ = realistic_with_dots
    dots = calib.locking_pattern.image_diameter_px
    assert 2.0 < dots < 4.5                    # 0.4 mm dots at magnification -0.5
    assert _large_image_px(calib) == pytest.approx(SIZE_FACTOR * dots)

    class NoDots:
        locking_pattern = None
    assert _large_image_px(NoDots()) == math.inf


def test_image_fits_of_large_images_leave_out_the_views_the_rim_cuts(realistic_with_dots,
                                                                      monkeypatch):
    optics, calib, white = realistic_with_dots
    truth = _truth([(0.0, 0.0, 5.0)], 1.0)
    raw = render_frame(optics, truth, seed=np.random.default_rng([0, 11]))
    locator = PerspectiveLocator()
    lf = _decoded(raw, calib, 0, white)
    ctx = FrameContext.build(lf, calib, segment_frame(lf, locator.segment), locator)
    views = _fit_views(ctx)
    cut = ctx.rim_cut(views[1])
    assert 0 < cut.sum() < len(cut) // 2       # the outer ring of views
    seen = []
    monkeypatch.setattr(refine, "fit_images", lambda dlfc, uv, rc, *a, **k: seen.append(len(uv)))
    large = 0.6 * ctx.large_image_px             # radius: 1.2 times the bar's diameter
    for radius in (0.4 * ctx.large_image_px, large):
        ctx.fit_images(views, np.zeros((1, 3)), np.array([[radius, 0.9]]),
                       np.zeros((0, 3)), np.zeros((0, 2)))
    assert seen == [len(cut), len(cut) - cut.sum()]


def test_large_particles_depths_are_not_drawn_towards_focus(realistic_with_dots):
    """Four 1.5 mm spheres 6 mm from focus on either side (realistic optics), whose
    images the locator refits to the view pixels: with the views the rim cuts, their
    depths came out 0.06-0.08 mm nearer the focal plane; fitted without them, within
    0.02 mm of the truth."""
    seed = 0
    optics, calib, white = realistic_with_dots
    truth = _truth([(-1.8, -0.8, -6.0), (1.8, 0.8, 6.0), (-1.8, 0.9, 6.0),
                    (1.8, -0.9, -6.0)], 1.5)
    raw = render_frame(optics, truth, seed=np.random.default_rng([seed, 12]))

    def towards_focus(rim_min_valid):
        locator = PerspectiveLocator.from_dict({"solve": {"rim_min_valid": rim_min_valid}})
        found = locate_frame(raw, calib, white=white, locator=locator).particles
        assert len(found) == len(truth)
        nearest = np.argmin(np.hypot(found["x"].to_numpy()[:, None] - truth["x"].to_numpy(),
                                     found["y"].to_numpy()[:, None] - truth["y"].to_numpy()),
                            axis=0)
        z = found["z"].to_numpy()[nearest]
        return -(z - truth["z"].to_numpy()) * np.sign(truth["z"].to_numpy())

    without = towards_focus(0.0)
    with_rule = towards_focus(SolveSettings().rim_min_valid)
    assert without.min() > 0.04
    assert np.all(np.abs(with_rule) < 0.03)
