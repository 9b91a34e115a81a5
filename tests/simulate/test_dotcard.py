"""Dot cards: dots where the optics predict them, shortcuts exact."""

import numpy as np
import pytest

from plenoptrack import preset
from plenoptrack.simulate import (DotCard, default_dotcard, default_dotcard_depths, dot_grid,
                                  dotcard_irradiance, render_dotcard)


def test_default_layouts():
    assert default_dotcard(preset("hall2019")) == DotCard(2.0, 0.6)
    assert default_dotcard(preset("small")) == DotCard(1.25, 0.4)
    np.testing.assert_allclose(default_dotcard_depths(preset("hall2019")), np.linspace(-25, 25, 11))
    np.testing.assert_allclose(default_dotcard_depths(preset("small")), np.linspace(-10, 10, 11))


def _central_view(optics, irr):
    """Irradiance at the pixel nearest each lens-image centre, and those centres."""
    c = optics.true_grid.centers().reshape(-1, 2)
    rows, cols = irr.shape
    ok = (c[:, 0] > 1) & (c[:, 0] < rows - 2) & (c[:, 1] > 1) & (c[:, 1] < cols - 2)
    c = c[ok]
    r, k = np.round(c).astype(int).T
    return c, irr[r, k]


@pytest.mark.parametrize("z", [-8.0, 0.0, 8.0])
def test_dots_at_predicted_positions(small_optics, z):
    o = small_optics
    card = default_dotcard(o.camera)
    irr = dotcard_irradiance(o, z, card=card)
    centres, view = _central_view(o, irr)
    dots = dot_grid(o, z, card)
    assert len(dots) >= 12 and ((dots.m == 0) & (dots.n == 0)).sum() == 1
    pitch = o.true_grid.pitch_px
    for row, col in dots[["row", "col"]].to_numpy():
        d = np.hypot(centres[:, 0] - row, centres[:, 1] - col)
        if d.min() > 0.3 * pitch:
            continue
        assert view[np.argmin(d)] < 0.1          # the lens seeing the dot centre is dark
    # Half-way between dots the card is clear.
    half = card.spacing_mm / 2
    mids = o.world_to_pixels(np.column_stack([dots.x + half, dots.y + half, np.full(len(dots), z)]))
    for row, col in mids:
        d = np.hypot(centres[:, 0] - row, centres[:, 1] - col)
        if d.min() < 0.3 * pitch:
            assert view[np.argmin(d)] > 0.9


def test_shortcuts_are_exact(small_rect_optics):
    a = dotcard_irradiance(small_rect_optics, 6.0)
    b = dotcard_irradiance(small_rect_optics, 6.0, exact=True)
    np.testing.assert_array_equal(a, b)


def test_render_dotcard_deterministic(small_optics):
    a = render_dotcard(small_optics, 2.0, seed=3)
    b = render_dotcard(small_optics, 2.0, seed=3)
    assert a.dtype == np.uint16 and a.tobytes() == b.tobytes()


def test_invalid_cards(small_optics):
    with pytest.raises(ValueError, match="dot_diameter_mm"):
        DotCard(1.0, 1.5)
    with pytest.raises(ValueError, match="in front of the lens"):
        dotcard_irradiance(small_optics, -500.0)


@pytest.mark.parametrize("mode", ["ideal", "realistic"])
def test_cards_over_the_background_are_exact(mode):
    # Cards start from the cached background and re-trace only pixels whose rays may land
    # on a dot; pixels straddling two lens cells use the dark and kept shortcuts and a
    # nearest-lens search over their candidate rows. The brute force traces every sample
    # of every pixel with the full search.
    from plenoptrack.simulate import draw_card_placements, make_optics
    from plenoptrack.simulate import _kernels
    from plenoptrack.simulate.render import background_irradiance, sample_pattern

    o = make_optics(preset("small"), 5, realism=mode)
    _, _, (pl,) = draw_card_placements(o.realism.target, 1, 2)
    placement = pl if mode == "realistic" else None
    bg = background_irradiance(o)
    rows, cols = o.camera.sensor_shape_px
    brute_bg = _kernels.render_all(_kernels.pack_params(o), sample_pattern(o, 16),
                                   np.zeros((0, 4)), np.zeros(3), 0, rows, 0, cols, True)
    np.testing.assert_array_equal(bg, brute_bg)
    for z in (-9.0, 4.0):
        a = dotcard_irradiance(o, z, placement=placement)
        np.testing.assert_array_equal(a, dotcard_irradiance(o, z, placement=placement, exact=True))
        changed = (a != bg).mean()
        assert 0.005 < changed < 0.3                       # dots shade some pixels, not all
