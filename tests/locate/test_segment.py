"""Tests of per-view particle segmentation."""

import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree
from skimage.measure import label, regionprops

from plenoptrack.errors import NoParticlesWarning
from plenoptrack.locate import segment as segment_module
from plenoptrack.locate.segment import DETECTION_COLUMNS, segment_array, segment_view
from plenoptrack.locate.settings import SegmentSettings


def _blobs(shape, positions, *, sigma=1.2, depth=0.7, background=1.0):
    """View with dark Gaussian blobs at (row, col) ``positions`` on a flat background."""
    img = np.full(shape, background, dtype=np.float64)
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    for r, c in positions:
        img -= depth * background * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * sigma ** 2))
    return img


def _random_positions(rng, n, shape, margin=10, min_sep=9.0):
    pts = []
    while len(pts) < n:
        p = rng.uniform([margin, margin], [shape[0] - margin, shape[1] - margin])
        if all(np.hypot(*(p - q)) > min_sep for q in pts):
            pts.append(p)
    return np.array(pts)


def _match(det, truth_rc):
    dist, idx = cKDTree(truth_rc[:, ::-1]).query(det[["s", "t"]].to_numpy())
    return dist, idx


def test_centroids_subpixel_with_noise():
    rng = np.random.default_rng(0)
    shape = (120, 160)
    truth = _random_positions(rng, 40, shape)
    img = _blobs(shape, truth) + rng.normal(0, 0.02, shape)
    det = segment_view(img.astype(np.float32))
    assert list(det.columns) == list(DETECTION_COLUMNS)
    assert len(det) == len(truth)
    dist, idx = _match(det, truth)
    assert len(np.unique(idx)) == len(truth)
    assert np.sqrt(np.mean(dist ** 2)) < 0.1
    assert dist.max() < 0.25


def test_noise_alone_gives_no_detections():
    rng = np.random.default_rng(1)
    img = 1.0 + rng.normal(0, 0.025, (200, 300))
    with pytest.warns(NoParticlesWarning):
        det = segment_view(img)
    assert len(det) == 0
    assert list(det.columns) == list(DETECTION_COLUMNS)


def test_shape_properties_match_skimage():
    shape = (80, 80)
    rows, cols = np.mgrid[:80, :80]
    img = np.ones(shape)
    # tilted ellipse, semi-axes 9 and 4 px, 30 degrees from +s towards +t
    th = np.deg2rad(30)
    ds, dt = cols - 40.3, rows - 39.6
    a = (ds * np.cos(th) + dt * np.sin(th)) / 9.0
    b = (-ds * np.sin(th) + dt * np.cos(th)) / 4.0
    inside = a ** 2 + b ** 2 <= 1
    img[inside] = 0.3
    det = segment_view(img, window=61)
    assert len(det) == 1
    rp = regionprops(label(inside))[0]
    row = det.iloc[0]
    assert row["area"] == rp.area
    assert row["major_axis_px"] == pytest.approx(rp.axis_major_length, rel=1e-9)
    assert row["minor_axis_px"] == pytest.approx(rp.axis_minor_length, rel=1e-9)
    assert row["eccentricity"] == pytest.approx(rp.eccentricity, rel=1e-9)
    assert row["diameter_px"] == pytest.approx(rp.equivalent_diameter_area, rel=1e-9)
    assert row["orientation"] == pytest.approx(th, abs=0.03)
    assert (row["s"], row["t"]) == pytest.approx((rp.centroid[1], rp.centroid[0]), abs=1e-9)
    assert row["darkness"] == pytest.approx(0.7, abs=0.02)


def test_area_and_eccentricity_limits():
    img = np.ones((60, 120))
    img[20:23, 10:13] = 0.2       # 9 px square
    img[20:40, 40:60] = 0.2       # 400 px square
    img[30:32, 80:100] = 0.2      # elongated bar
    det = segment_view(img, window=41, area_range=(5, 100))
    assert sorted(det["area"]) == [9, 40]
    det = segment_view(img, window=41, area_range=(5, 100), max_eccentricity=0.9)
    assert list(det["area"]) == [9]


def test_edge_and_masked_regions_rejected():
    img = _blobs((60, 80), [(30, 1.0), (30, 40), (30, 60)])
    mask = np.ones((60, 80), bool)
    mask[:, 62:] = False          # blob at column 60 touches the mask
    det = segment_view(img, mask=mask)
    assert len(det) == 1 and det["s"].iloc[0] == pytest.approx(40, abs=0.05)
    assert len(segment_view(img, mask=mask, exclude_edge=False)) == 3


def test_dense_particles_and_background_gradient():
    # a lattice of dark dots every 7 px on a background with a strong gradient
    shape = (100, 140)
    pos = [(r, c) for r in np.arange(8, 93, 7.0) for c in np.arange(8, 133, 7.0)]
    grad = np.linspace(0.5, 1.5, shape[1])[None, :]
    img = _blobs(shape, pos, sigma=1.0, depth=0.6) * grad
    det = segment_view(img, window=21)
    assert len(det) == len(pos)
    dist, _ = _match(det, np.array(pos))
    assert dist.max() < 0.1


def test_zero_invalid_masks_vignetted_samples():
    img = _blobs((50, 50), [(25, 25)])
    img[:, :5] = 0.0
    assert len(segment_view(img, zero_invalid=True)) == 1
    assert len(segment_view(img, zero_invalid=False, exclude_edge=False)) == 2


def test_segment_array_views_and_columns():
    rng = np.random.default_rng(2)
    n_v, n_u, shape = 3, 5, (60, 90)
    truth = _random_positions(rng, 8, shape)
    data = np.empty((n_v, n_u, *shape), np.float32)
    u = np.arange(n_u) - 2.0
    v = np.arange(n_v) - 1.0
    for iv in range(n_v):
        for iu in range(n_u):
            data[iv, iu] = _blobs(shape, truth + [0.5 * v[iv], 0.7 * u[iu]])
    use = np.ones((n_v, n_u), bool)
    use[0, 0] = False
    det = segment_array(data, u, v, view_mask=use, frame=4)
    assert len(det) == 8 * (n_v * n_u - 1)
    assert (det["frame"] == 4).all()
    assert not ((det["u"] == -2) & (det["v"] == -1)).any()
    for (uu, vv), grp in det.groupby(["u", "v"]):
        dist, idx = _match(grp, truth + [0.5 * vv, 0.7 * uu])
        assert dist.max() < 0.05 and len(np.unique(idx)) == 8


def test_many_regions_beyond_initial_capacity(monkeypatch):
    monkeypatch.setattr(segment_module, "_INITIAL_CAPACITY", 512)
    shape = (200, 400)
    pos = [(r, c) for r in np.arange(4, 197, 6.0) for c in np.arange(4, 397, 6.0)]
    img = _blobs(shape, pos, sigma=0.8)
    det = segment_view(img, window=15)
    assert len(det) == len(pos) > 512


def test_only_views_beyond_capacity_are_segmented_again(monkeypatch):
    # views with more regions than the first pass has room for are segmented a second
    # time on their own; the table must be the one a pass with room for all gives
    rng = np.random.default_rng(5)
    n_v, n_u, shape = 2, 3, (60, 90)
    data = np.empty((n_v, n_u, *shape), np.float32)
    for k in range(n_v * n_u):
        data.flat[k * shape[0] * shape[1]:(k + 1) * shape[0] * shape[1]] = _blobs(
            shape, _random_positions(rng, 2 + 3 * k, shape)).ravel()
    u, v = np.arange(n_u) - 1.0, np.arange(n_v) - 0.5
    roomy = segment_array(data, u, v)
    per_view = roomy.groupby(["v", "u"]).size().to_numpy()
    monkeypatch.setattr(segment_module, "_INITIAL_CAPACITY", 7)
    assert (per_view > 7).any() and (per_view <= 7).any()
    pd.testing.assert_frame_equal(segment_array(data, u, v), roomy)


def test_deterministic_and_input_unchanged():
    rng = np.random.default_rng(3)
    img = _blobs((70, 70), _random_positions(rng, 5, (70, 70))) + rng.normal(0, 0.01, (70, 70))
    before = img.copy()
    a, b = segment_view(img), segment_view(img)
    pd.testing.assert_frame_equal(a, b)
    np.testing.assert_array_equal(img, before)


@pytest.mark.parametrize("kwargs, match", [
    (dict(window=2), "window must be an integer"),
    (dict(contrast=1.5), "contrast must be between 0 and 1"),
    (dict(area_range=(5, 1)), "area_range must satisfy"),
    (dict(connectivity=3), "connectivity must be 1 or 2"),
    (dict(min_core_ratio=1.0), r"min_core_ratio must be in \[0, 1\)"),
    (dict(centroid_clip=0.0), r"centroid_clip must be in \(0, 1\]"),
    (dict(centroid_clip=1.2), r"centroid_clip must be in \(0, 1\]"),
])
def test_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        segment_view(np.ones((10, 10)), **kwargs)


def test_bad_shapes():
    with pytest.raises(ValueError, match="must be 2-D"):
        segment_view(np.ones((2, 10, 10)))
    with pytest.raises(ValueError, match="must be 4-D"):
        segment_array(np.ones((10, 10)), [0], [0])
    with pytest.raises(ValueError, match="view_mask must be"):
        segment_array(np.ones((1, 2, 10, 10)), [0, 1], [0], view_mask=np.ones((2, 2), bool))


@pytest.mark.parametrize("blur_px", [0.0, 1.0, 2.0])
def test_dark_area_is_the_shadow_area_whatever_the_blur(blur_px):
    from scipy.ndimage import gaussian_filter

    rows, cols = np.mgrid[:100, :100]
    opaque = (cols - 50.2) ** 2 + (rows - 49.7) ** 2 <= 6.0 ** 2   # 113 px disc
    img = np.where(opaque, 0.0, 1.0)
    if blur_px:
        img = gaussian_filter(img, blur_px)
    det = segment_view(img, window=61)
    assert len(det) == 1
    row = det.iloc[0]
    # the thresholded area grows with blur; the summed darkness (with the one-pixel rim
    # around the region) stays near the disc's area, losing only the faintest tails
    true = opaque.sum()
    assert row["dark_area"] == pytest.approx(true, rel=0.03)
    if blur_px:
        assert abs(row["area"] - true) > 5 * abs(row["dark_area"] - true)


@pytest.mark.parametrize(("radius_px", "blur_px", "lowest"),
                         [(1.0, 0.7, 0.97), (1.5, 0.7, 0.97), (2.5, 0.7, 0.97),
                          (1.3, 1.2, 0.95), (1.0, 1.2, 0.93)])
def test_dark_area_of_a_small_blurred_image_keeps_its_rim(radius_px, blur_px, lowest):
    # A small image loses much of its shadow below the threshold: without the rim around
    # the region, a disc of radius 1.5 px blurred by 0.7 px kept 86 % of its area; with a
    # rim of one pixel, a disc of radius 1.3 px (1.0 px) blurred by 1.2 px kept 92 % (84 %).
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(7)
    ratios = []
    for _ in range(8):
        centre = 30.0 + rng.uniform(-0.5, 0.5, 2)
        img = 1.0 - gaussian_filter(_coverage((60, 60), centre, radius_px), blur_px)
        img *= 1.0 + 0.01 * rng.standard_normal(img.shape)
        det = segment_view(img.astype(np.float32))
        assert len(det) == 1
        ratios.append(det["dark_area"].iloc[0] / (np.pi * radius_px ** 2))
    # what is left beyond the two-pixel rim is the faintest tail of a wide blur
    assert lowest <= np.mean(ratios) <= 1.03


def test_dark_area_in_a_crowded_view_is_counted_against_the_background_itself():
    # 200 blurred discs in a 200 x 200 view: the box-mean background takes in their faint
    # tails and lies about 1 % low, so a wide rim of true background read as negative
    # darkness; counted against the background's median it is not (0.96 before, 0.98 now)
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(3)
    centres = []
    while len(centres) < 200:
        p = rng.uniform(5, 195, 2)
        if all(np.hypot(*(p - q)) > 7.0 for q in centres):
            centres.append(p)
    coverage = sum(_coverage((200, 200), c, 1.3) for c in centres)
    img = 1.0 - gaussian_filter(np.clip(coverage, 0, 1), 0.7)
    img *= 1.0 + 0.01 * rng.standard_normal(img.shape)
    det = segment_view(img.astype(np.float32))
    assert len(det) == 200
    ratio = det["dark_area"] / (np.pi * 1.3 ** 2)
    assert np.median(ratio) == pytest.approx(1.0, abs=0.025)


def _coverage(shape, centre, radius):
    """Fraction of each pixel (centres at integers) inside a disc, 8 x 8 supersampled."""
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    covered = np.zeros(shape)
    for dr in sub:
        for dc in sub:
            covered += np.hypot(rows + dr - centre[0], cols + dc - centre[1]) < radius
    return covered / 64


def _opaque_discs(shape, centres, radius, blur):
    """View of opaque discs (row, col centres, radius px) in front of a flat back-light."""
    from scipy.ndimage import gaussian_filter

    rows, cols = np.mgrid[:shape[0], :shape[1]] + 0.5 - 0.5  # pixel centres at integers
    transmission = np.ones(shape)
    # 8x8 supersampled coverage keeps the sub-pixel position in the image
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    for r, c in centres:
        covered = np.zeros(shape)
        for dr in sub:
            for dc in sub:
                covered += np.hypot(rows + dr - r, cols + dc - c) < radius
        transmission *= 1.0 - covered / 64
    return gaussian_filter(transmission, blur)


def test_merged_images_are_shared_out_between_their_cores():
    shape = (40, 60)
    centres = np.array([[20.3, 24.6], [21.1, 32.2], [10.4, 48.7]])  # a touching pair, one alone
    img = _opaque_discs(shape, centres, radius=3.2, blur=0.8).astype(np.float32)
    plain = segment_view(img)
    assert len(plain) == 2  # the pair is one region
    det = segment_view(img, core_contrast=0.9)
    assert list(det.columns) == [*DETECTION_COLUMNS, "whole"]
    assert len(det) == 3
    dist, idx = _match(det, centres)
    assert sorted(idx) == [0, 1, 2]
    assert det.loc[idx == 2, "whole"].all() and not det.loc[idx < 2, "whole"].any()
    # the parts share out the region's pixels and shadow exactly
    merged = plain.loc[plain["area"].idxmax()]
    parts = det[~det["whole"]]
    assert parts["area"].sum() == merged["area"]
    assert parts["dark_area"].sum() == pytest.approx(merged["dark_area"])
    # each part's centroid is its particle's (a part misses the shared rim: < 0.35 px)
    assert dist.max() < 0.35, dist
    # the area range judges the merged region as a whole
    assert len(segment_view(img, core_contrast=0.9,
                            area_range=(2, merged["area"] - 1))) == 1


@pytest.mark.parametrize("transmission", [0.0, 0.05, 0.1, 0.2])
def test_a_translucent_pair_is_split_like_an_opaque_one(transmission):
    # A particle passing 10 % of the back-light never reaches a relative darkness of 0.93;
    # its core is measured against the region's own peak darkness.
    shape = (40, 60)
    centres = np.array([[20.3, 24.6], [21.1, 32.2], [10.4, 48.7]])
    opaque = _opaque_discs(shape, centres, radius=3.2, blur=0.8)
    img = (transmission + (1.0 - transmission) * opaque).astype(np.float32)
    rng = np.random.default_rng(3)
    img = img * (1.0 + 0.01 * rng.standard_normal(shape)).astype(np.float32)
    det = segment_view(img, core_contrast=0.93)
    assert len(det) == 3
    dist, idx = _match(det, centres)
    assert sorted(idx) == [0, 1, 2]
    assert dist.max() < 0.5, dist


def test_a_lone_translucent_image_keeps_one_core_in_noise():
    # The relative threshold must not break a flat translucent shadow into noise cores.
    shape = (60, 60)
    centres = np.array([[30.0, 30.0]])
    rng = np.random.default_rng(4)
    for seed in range(20):
        img = 0.1 + 0.9 * _opaque_discs(shape, centres, radius=6.0, blur=0.8)
        img = img * (1.0 + 0.01 * rng.standard_normal(shape))
        det = segment_view(img.astype(np.float32), core_contrast=0.93)
        assert len(det) == 1, seed


def _ellipse_coverage(shape, centre, semi_axes, angle):
    """Fraction of each pixel inside an ellipse (row, col centre; semi-axes px; angle of
    the long axis from +col towards +row, rad), 8 x 8 supersampled."""
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    a, b = semi_axes
    covered = np.zeros(shape)
    for dr in sub:
        for dc in sub:
            y, x = rows + dr - centre[0], cols + dc - centre[1]
            along = x * np.cos(angle) + y * np.sin(angle)
            across = -x * np.sin(angle) + y * np.cos(angle)
            covered += (along / a) ** 2 + (across / b) ** 2 < 1
    return covered / 64


def test_a_thin_stem_is_not_split_from_its_head():
    # A pin: a translucent head of radius 6 px with a thin opaque stem leaving it. Where the
    # stem's ridge crosses the pixel grid it breaks into dark flecks of one pixel; counted
    # as cores they split the stem off as an extra particle.
    from scipy.ndimage import gaussian_filter

    shape = (44, 64)
    angle = 0.2
    head = 1.0 - _coverage(shape, (20.0, 20.0), 6.0)
    stem_centre = (20.4 + 7.0 * np.sin(angle), 26.0 + 7.0 * np.cos(angle))
    stem = 1.0 - _ellipse_coverage(shape, stem_centre, (8.0, 1.4), angle)
    clean = gaussian_filter((0.08 + 0.92 * head) * stem, 0.9)
    rng = np.random.default_rng(1)
    for _ in range(5):
        img = (clean * (1 + 0.01 * rng.standard_normal(shape))).astype(np.float32)
        assert len(segment_view(img, core_contrast=0.93)) == 2  # the fleck is a core
        det = segment_view(img, core_contrast=0.93, min_core_ratio=0.08)
        assert len(det) == 1 and det["whole"].all()


@pytest.mark.parametrize("transmission", [0.0, 0.1])
def test_a_smaller_neighbour_keeps_its_core(transmission):
    # Radius 2.5 px beside 4 px: the smaller core is about a fifth of the larger (blur takes
    # a constant width off both) but has several pixels, so the pair is still split.
    shape = (40, 60)
    centres = np.array([[20.3, 24.6], [20.8, 31.6]])
    big = _opaque_discs(shape, centres[:1], radius=4.0, blur=0.8)
    small = _opaque_discs(shape, centres[1:], radius=2.5, blur=0.8)
    clean = transmission + (1 - transmission) * big * small
    rng = np.random.default_rng(2)
    for _ in range(5):
        img = (clean * (1 + 0.01 * rng.standard_normal(shape))).astype(np.float32)
        det = segment_view(img, core_contrast=0.93, min_core_ratio=0.08)
        assert len(det) == 2
        dist, idx = _match(det, centres)
        assert sorted(idx) == [0, 1]
        assert dist.max() < 0.3, dist
        # a core of several pixels counts however large its neighbour's
        assert len(segment_view(img, core_contrast=0.93, min_core_ratio=0.9)) == 2


def test_core_contrast_must_lie_between_contrast_and_one():
    with pytest.raises(ValueError, match="core_contrast must be between"):
        segment_view(np.ones((10, 10)), contrast=0.3, core_contrast=0.2)


def test_a_translucent_image_beside_an_opaque_one_keeps_its_core():
    # Two touching images form one region, whose peak darkness is the opaque particle's
    # (1). The neighbour passing 9-12 % of the light has a plateau of 0.88-0.91 only: below
    # a core threshold of 0.93 of the peak it has no core, the region is not split, and
    # the pair is measured as one image 3 px off both. Cores must hold the plateau of a
    # particle of transmission tau next to an opaque one: threshold < 1 - tau.
    shape = (40, 60)
    centres = np.array([[20.3, 24.6], [21.1, 31.4], [10.4, 48.7]])
    rng = np.random.default_rng(5)
    for trial in range(4):
        tau = np.array([rng.uniform(0, 0.02), rng.uniform(0.08, 0.12), 0.05])
        img = np.ones(shape)
        for (r, c), t in zip(centres, tau):
            img *= t + (1.0 - t) * _opaque_discs(shape, [(r, c)], radius=3.2, blur=0.8)
        img = (img * (1.0 + 0.01 * rng.standard_normal(shape))).astype(np.float32)
        assert len(segment_view(img, core_contrast=0.93, min_core_ratio=0.08)) == 2
        settings = SegmentSettings()
        det = segment_view(img, core_contrast=settings.core_contrast,
                           min_core_ratio=settings.min_core_ratio)
        assert len(det) == 3, trial
        dist, idx = _match(det, centres)
        assert sorted(idx) == [0, 1, 2]
        assert dist.max() < 0.3, dist


def test_the_rim_marks_every_pixel_within_two_of_a_region_one_run_at_a_time():
    """``_mark_runs`` against a brute-force dilation: pixels within two (8-neighbour
    steps) of random region pixels, given in raster order, and each row's span of them;
    setting back to False leaves the work array clean."""
    from plenoptrack.locate.segment import _mark_runs

    rng = np.random.default_rng(3)
    h, w = 17, 23
    for _ in range(30):
        region = rng.random((h, w)) < rng.uniform(0.02, 0.3)
        pi, pj = (a.astype(np.int32) for a in np.nonzero(region))       # raster order
        near = np.zeros((h, w), dtype=bool)
        lo, hi = np.full(h, w, dtype=np.int64), np.full(h, -1, dtype=np.int64)
        _mark_runs(pi, pj, near, True, lo, hi)
        expected = np.zeros((h, w), dtype=bool)
        for i, j in zip(pi, pj):
            expected[max(i - 2, 0):i + 3, max(j - 2, 0):j + 3] = True
        np.testing.assert_array_equal(near, expected)
        for i in range(h):
            cols = np.flatnonzero(expected[i])
            if len(cols):
                assert (lo[i], hi[i]) == (cols.min(), cols.max())
            else:
                assert lo[i] > hi[i]
        _mark_runs(pi, pj, near, False, lo, hi)
        assert not near.any()


def _glinting_disc(shape, centre, radius, *, glint, blur=0.5):
    """An opaque disc with a specular spot of peak ``glint`` (of the back-light) a
    third of the radius from its centre towards +row and +col."""
    from scipy.ndimage import gaussian_filter

    rows, cols = np.mgrid[:shape[0], :shape[1]]
    spot = np.exp(-((rows - centre[0] - radius / 3) ** 2 + (cols - centre[1] - radius / 3) ** 2)
                  / (2 * (0.15 * radius) ** 2))
    covered = _coverage(shape, centre, radius)
    return gaussian_filter(1.0 - covered + glint * spot * covered, blur)


@pytest.mark.parametrize("radius", [3.0, 6.0])
def test_a_capped_centroid_is_not_pulled_off_by_a_glint(radius):
    rng = np.random.default_rng(3)
    errors = {1.0: [], 0.7: []}
    for _ in range(12):
        centre = np.array([20.0, 20.0]) + rng.uniform(-0.5, 0.5, 2)
        image = _glinting_disc((41, 41), centre, radius, glint=0.5)
        for clip in errors:
            det = segment_view(image, centroid_clip=clip)
            assert len(det) == 1
            errors[clip].append([det["t"].iloc[0] - centre[0], det["s"].iloc[0] - centre[1]])
    bias = {clip: np.mean(e, axis=0) for clip, e in errors.items()}
    # uncapped, the dark-weighted centroid moves away from the spot (-row, -col) ...
    assert np.all(bias[1.0] < -0.02)
    # ... capped, the plateau weighs evenly and the bias is a fraction of that
    assert np.all(np.abs(bias[0.7]) < 0.35 * np.abs(bias[1.0]))


@pytest.mark.parametrize("clip", [1.0, 0.7, 0.4])
def test_a_cap_leaves_a_symmetric_image_centred(clip):
    rng = np.random.default_rng(4)
    errors = []
    for _ in range(40):
        centre = np.array([20.0, 20.0]) + rng.uniform(-0.5, 0.5, 2)
        det = segment_view(_glinting_disc((41, 41), centre, 5.0, glint=0.0, blur=1.0),
                           centroid_clip=clip)
        errors.append([det["t"].iloc[0] - centre[0], det["s"].iloc[0] - centre[1]])
    # no bias over the sub-pixel phases; what remains is pixel-locking, which grows as
    # the cap flattens the image (about 0.015 px at most uncapped, 0.027 px at 0.4)
    assert np.all(np.abs(np.mean(errors, axis=0)) < 0.005)
    assert np.abs(errors).max() < 0.04


def test_the_cap_changes_only_the_centroid():
    image = _glinting_disc((41, 41), (20.2, 19.7), 4.0, glint=0.5)
    plain, capped = segment_view(image), segment_view(image, centroid_clip=0.7)
    moved = ["s", "t"]
    pd.testing.assert_frame_equal(plain.drop(columns=moved), capped.drop(columns=moved))
    assert not np.allclose(plain[moved].to_numpy(), capped[moved].to_numpy())


def test_an_image_without_a_plateau_is_not_capped():
    """A 2-pixel image's peak is its edge: no pixel above the cap has its four
    neighbours above it too, and its centroid is the uncapped one."""
    rng = np.random.default_rng(5)
    for _ in range(10):
        centre = np.array([20.0, 20.0]) + rng.uniform(-0.5, 0.5, 2)
        image = _glinting_disc((41, 41), centre, 1.0, glint=0.5)
        plain, capped = segment_view(image), segment_view(image, centroid_clip=0.7)
        pd.testing.assert_frame_equal(plain, capped)
    # a large image has a plateau, and its centroid moves
    image = _glinting_disc((41, 41), (20.2, 19.7), 4.0, glint=0.5)
    assert not np.allclose(segment_view(image)[["s", "t"]].to_numpy(),
                           segment_view(image, centroid_clip=0.7)[["s", "t"]].to_numpy())
