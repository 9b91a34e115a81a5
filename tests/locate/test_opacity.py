"""Opacity of particles from their images, and the views' edge blur from dot images."""

import math

import numpy as np
import pandas as pd
import pytest
from scipy.ndimage import gaussian_filter

from plenoptrack.locate.opacity import (MAX_BLUR_SENSITIVITY, blur_at, blur_sensitivity,
                                        edge_blur_by_depth, opacity)
from plenoptrack.locate.segment import segment_view

try:
    from .test_segment import _coverage
except ImportError:  # tests/locate is not a package
    from test_segment import _coverage


def _images(radius, contrast, blur, n=12, seed=0):
    """Segmented images of a disc (radius px, opacity ``contrast``) blurred by ``blur`` px
    at random sub-pixel positions: (peak darkness, shadow radius) of each."""
    rng = np.random.default_rng(seed)
    peaks, radii = [], []
    for _ in range(n):
        centre = 30.0 + rng.uniform(-0.5, 0.5, 2)
        img = 1.0 - contrast * gaussian_filter(_coverage((60, 60), centre, radius), blur)
        img *= 1.0 + 0.005 * rng.standard_normal(img.shape)
        det = segment_view(img.astype(np.float32))
        assert len(det) == 1
        peaks.append(det["darkness"].iloc[0])
        radii.append(math.sqrt(det["dark_area"].iloc[0] / math.pi))
    return np.array(peaks), np.array(radii)


def test_edge_blur_from_opaque_dots_at_two_depths():
    rows = []
    for z, blur in ((-5.0, 0.5), (5.0, 0.8)):
        peak, r = _images(1.5, 1.0, blur, seed=int(z + 10))
        rows.append(pd.DataFrame({"z": z, "darkness": peak, "dark_area": math.pi * r ** 2}))
    table = edge_blur_by_depth(pd.concat(rows, ignore_index=True))
    assert [z for z, _ in table] == [-5.0, 5.0]
    # the model's Gaussian takes in the pixel's own width (variance 1/12) and the image's
    # sub-pixel phase: an effective blur a little above the blur itself
    for (_, measured), blur in zip(table, (0.5, 0.8)):
        assert math.sqrt(blur ** 2 + 1 / 12) - 0.02 <= measured <= blur + 0.2
    assert table[1][1] > table[0][1] + 0.2
    # fewer than 5 usable dots at a depth: no row
    assert edge_blur_by_depth(rows[0].iloc[:4]) == ()
    np.testing.assert_allclose(blur_at(table, [-9.0, 0.0, 9.0]),
                               [table[0][1], np.mean([table[0][1], table[1][1]]), table[1][1]])
    assert np.isnan(blur_at((), [0.0])).all()


@pytest.mark.parametrize("radius", [1.6, 2.0, 4.0])
@pytest.mark.parametrize("contrast", [1.0, 0.9, 0.75])
def test_opacity_and_body_radius_of_blurred_translucent_discs(radius, contrast):
    blur = 0.6
    # the blur as the calibration measures it, on opaque discs of about this size
    dot_peak, dot_r = _images(1.5, 1.0, blur, seed=1)
    blur_px = edge_blur_by_depth(pd.DataFrame({"z": 0.0, "darkness": dot_peak,
                                               "dark_area": math.pi * dot_r ** 2}))[0][1]
    peak, r_shadow = _images(radius, contrast, blur, seed=2)
    c = opacity(np.median(peak), np.median(r_shadow), blur_px)
    assert c == pytest.approx(contrast, abs=0.03)
    # the shadow's disc is sqrt(c) of the body; divided by it, the body's radius
    assert np.median(r_shadow) / math.sqrt(c) == pytest.approx(radius, rel=0.03)


def test_opacity_solves_the_peak_equation():
    rng = np.random.default_rng(5)
    c_true = rng.uniform(0.6, 1.0, 50)
    r_body = rng.uniform(1.0, 4.0, 50)
    sigma = rng.uniform(0.4, 0.8, 50)
    x = r_body ** 2 / (2 * sigma ** 2)
    peak = c_true * -np.expm1(-x)
    c = opacity(peak, r_body * np.sqrt(c_true), sigma)
    sure = blur_sensitivity(x) <= MAX_BLUR_SENSITIVITY
    assert 10 < sure.sum() < 50
    np.testing.assert_allclose(c[sure], c_true[sure], atol=1e-9)
    # beyond the bar the correction is damped by (bar / sensitivity)^2 in ln c: between
    # the solution and opaque, nearer opaque the less the peak can tell
    weight = (MAX_BLUR_SENSITIVITY / blur_sensitivity(x[~sure])) ** 2
    np.testing.assert_allclose(c[~sure], c_true[~sure] ** weight, rtol=1e-9)
    assert np.all((c[~sure] > c_true[~sure]) & (c[~sure] < 1.0))


def test_blur_sensitivity_is_the_derivative_of_the_opacity():
    # numerically: d ln c / d ln sigma of the solution for a fixed peak and shadow
    c, r_body, sigma = 0.85, 1.4, 0.6
    r_shadow = r_body * math.sqrt(c)
    peak = c * -np.expm1(-r_body ** 2 / (2 * sigma ** 2))
    up = opacity(peak, r_shadow, sigma * 1.001)
    down = opacity(peak, r_shadow, sigma / 1.001)
    slope = (math.log(up) - math.log(down)) / (2 * math.log(1.001))
    assert abs(slope) == pytest.approx(blur_sensitivity(r_body ** 2 / (2 * sigma ** 2)),
                                       rel=1e-3)


def test_opacity_where_the_peak_cannot_tell():
    # a body of radius 1 px and opacity 0.8 blurred by 0.6 px peaks at 0.75 of its
    # opacity; a 10 % error in the blur would move the opacity found by 17 %
    x = 1.0 / (2 * 0.6 ** 2)
    assert blur_sensitivity(x) == pytest.approx(1.71, abs=0.01)
    c = opacity([0.999, 0.8 * -np.expm1(-x), np.nan, 0.9], [1.5, math.sqrt(0.8), 1.5, 1.5],
                [0.6, 0.6, 0.6, np.nan])
    # darker than an opaque disc of that shadow (two images overlapping): opaque
    assert c[0] == 1.0
    # the blurred image that says little about its opacity: a third of the way in ln c
    # (1 / 1.71^2 = 0.34) from opaque to the solution 0.8
    assert c[1] == pytest.approx(0.8 ** (1 / blur_sensitivity(x) ** 2), rel=1e-6)
    assert 0.9 < c[1] < 1.0
    # no peak or no blur: unknown
    assert np.isnan(c[2]) and np.isnan(c[3])
