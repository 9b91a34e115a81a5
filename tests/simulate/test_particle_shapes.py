"""Ellipsoidal (prolate spheroid) particles: rendering, silhouettes, scenes; spheres unchanged."""

import hashlib
import math

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack._columns import SHAPE_COLUMNS, TRUTH_COLUMNS
from plenoptrack.simulate import (make_optics, make_scene, particle_silhouettes, random_particles,
                                  render_irradiance)
from plenoptrack.simulate.render import background_irradiance
from plenoptrack.simulate.scene import SceneError, Volume


def _spheroid(x, y, z, d, aspect, axis):
    u = np.asarray(axis, dtype=float)
    u = u / np.linalg.norm(u)
    return {"x": x, "y": y, "z": z, "diameter": d, "shape": "ellipsoid", "aspect": aspect,
            "axis_x": u[0], "axis_y": u[1], "axis_z": u[2]}


def _spheres(rows):
    return pd.DataFrame(rows, columns=["x", "y", "z", "diameter"])


SPHERES = [[0.5, -0.3, 2.0, 0.8], [-2.0, 1.0, -6.0, 1.0], [1.0, 1.0, 0.0, 0.6]]


def test_sphere_render_bytes_unchanged(small_optics):
    # Digest of this render before ellipsoids existed (same optics, seed and samples).
    irr = render_irradiance(small_optics, _spheres(SPHERES))
    assert hashlib.sha256(irr.tobytes()).hexdigest() == (
        "17018194a4adbb0daaf662691db0954c6b92c0e4e7567ba4ba1d3e05c2838d75")


def test_sphere_scene_unchanged_by_shape_option():
    camera = preset("small")
    a = make_scene(camera, n_particles=10, seed=3)
    b = make_scene(camera, n_particles=10, seed=3, shape="sphere", max_aspect=5.0)
    cols = ["frame", "particle", "x", "y", "z", "diameter"]
    digest = hashlib.sha256(pd.util.hash_pandas_object(a.truth[cols]).values.tobytes()).hexdigest()
    assert digest == "c2e3dc351322379b67645e9eec2170b00c2409b5ad984db519e215d3b0b0efe6"
    assert list(a.truth.columns) == list(TRUTH_COLUMNS)
    pd.testing.assert_frame_equal(a.truth, b.truth)
    np.testing.assert_array_equal(a.truth["projected_area"], math.pi * a.truth["diameter"] ** 2 / 4)
    assert (a.truth["orientation"] == 0).all()


@pytest.mark.parametrize("realism", ["ideal", "realistic"])
def test_aspect_one_ellipsoid_renders_exactly_like_sphere(realism):
    optics = make_optics(preset("small"), seed=0, realism=realism)
    axes = [(1, 2, 3), (0, 0, 1), (-1, 0.3, 0.2)]
    ell = pd.DataFrame([_spheroid(*row, 1.0, ax) for row, ax in zip(SPHERES, axes)])
    a = render_irradiance(optics, _spheres(SPHERES))
    b = render_irradiance(optics, ell)
    assert (a < background_irradiance(optics)).any()
    np.testing.assert_array_equal(a, b)


def test_culled_equals_exact_with_ellipsoids(small_optics):
    parts = pd.DataFrame([
        _spheroid(0.5, -0.3, 2.0, 0.6, 2.5, (1, 1, 0.2)),
        _spheroid(-2.0, 1.0, -6.0, 0.7, 3.0, (0, 0.2, 1)),
        {"x": 1.5, "y": 1.2, "z": 0.0, "diameter": 0.5, "shape": "sphere", "aspect": 1.0,
         "axis_x": 0.0, "axis_y": 0.0, "axis_z": 1.0},
        _spheroid(-1.0, -1.5, 4.0, 0.5, 1.7, (1, -2, 0.5)),
    ])
    culled = render_irradiance(small_optics, parts)
    exact = render_irradiance(small_optics, parts, cull=False)
    np.testing.assert_array_equal(culled, exact)


def _shadow(optics, particle):
    """Shadow area (mm^2, focal plane) and orientation (rad) measured in the irradiance."""
    irr = render_irradiance(optics, pd.DataFrame([particle])).astype(np.float64)
    bg = background_irradiance(optics).astype(np.float64)
    rows, cols = bg.shape
    win = (slice(rows // 2 - 200, rows // 2 + 200), slice(cols // 2 - 200, cols // 2 + 200))
    dark = (bg - irr)[win]
    # Focal-plane area of one pixel: pixel pitch back through the microlens image scale
    # and the main-lens magnification s_i / s_o; the lit fraction is the mean back-light.
    px_area = (optics.pixel_pitch / optics.image_scale * optics.s_o / optics.s_i) ** 2
    area = dark.sum() / bg[win].mean() * px_area
    rr, cc = np.mgrid[win]
    w = dark / dark.sum()
    mr, mc = (w * rr).sum(), (w * cc).sum()
    mrr = (w * (rr - mr) ** 2).sum()
    mcc = (w * (cc - mc) ** 2).sum()
    mrc = (w * (rr - mr) * (cc - mc)).sum()
    # Sensor columns run along world +x and rows along world +y (tested below).
    angle = 0.5 * math.atan2(2 * mrc, mcc - mrr)
    return area, angle, (mr, mc)


@pytest.mark.parametrize("axis", [(1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (-0.3, 1.0, 0.6),
                                  (0.5, -0.2, 1.0), (0.0, 0.0, 1.0)])
def test_in_focus_shadow_area_and_orientation(small_optics, axis):
    particle = _spheroid(0.0, 0.0, 0.0, 1.0, 2.5, axis)
    truth = particle_silhouettes(pd.DataFrame([particle])).iloc[0]
    area, angle, _ = _shadow(small_optics, particle)
    assert area == pytest.approx(truth["projected_area"], rel=0.03)
    u = np.asarray(axis) / np.linalg.norm(axis)
    if math.hypot(u[0], u[1]) > 0.3:
        diff = (angle - truth["orientation"] + math.pi / 2) % math.pi - math.pi / 2
        assert abs(diff) < math.radians(3)


def test_sensor_axes_follow_world_axes(small_optics):
    # The orientation convention of _shadow: the shadow moves right with +x, down with +y.
    _, _, (r0, c0) = _shadow(small_optics, _spheroid(0.0, 0.0, 0.0, 0.8, 1.0, (0, 0, 1)))
    _, _, (r1, c1) = _shadow(small_optics, _spheroid(0.5, 0.3, 0.0, 0.8, 1.0, (0, 0, 1)))
    assert c1 > c0 + 5 and r1 > r0 + 3


def test_silhouette_formula():
    d, k = 1.0, 2.0
    a, b = d / 2 * k ** (2 / 3), d / 2 * k ** (-1 / 3)
    t = pd.DataFrame([_spheroid(0, 0, 0, d, k, (1, 0, 0)), _spheroid(0, 0, 0, d, k, (0, 0, 1)),
                      _spheroid(0, 0, 0, d, k, (0, -1, 1)),
                      {"x": 0, "y": 0, "z": 0, "diameter": d, "shape": "sphere", "aspect": 1.0,
                       "axis_x": 0.0, "axis_y": 0.0, "axis_z": 1.0}])
    s = particle_silhouettes(t)
    np.testing.assert_allclose(s["projected_area"],
                               [math.pi * a * b, math.pi * b * b,
                                math.pi * b * math.sqrt((a * a + b * b) / 2), math.pi * d * d / 4])
    np.testing.assert_allclose(s["orientation"], [0.0, 0.0, -math.pi / 2, 0.0])


def test_random_ellipsoids():
    vol = Volume((-3, 3), (-2, 2), (-5, 5))
    t = random_particles(30, volume=vol, diameter_mm=0.4, seed=5, shape="ellipsoid",
                         max_aspect=3.0)
    assert list(t.columns) == [*TRUTH_COLUMNS, *SHAPE_COLUMNS]
    assert ((t["aspect"] >= 1) & (t["aspect"] <= 3)).all()
    np.testing.assert_allclose(np.linalg.norm(t[["axis_x", "axis_y", "axis_z"]], axis=1), 1.0)
    again = random_particles(30, volume=vol, diameter_mm=0.4, seed=5, shape="ellipsoid")
    pd.testing.assert_frame_equal(t, again)
    # Bounding spheres (radius = long semi-axis) do not overlap.
    xyz = t[["x", "y", "z"]].to_numpy()
    reach = t["diameter"].to_numpy() * t["aspect"].to_numpy() ** (2 / 3)
    gap = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    need = (reach[:, None] + reach[None]) / 2
    np.fill_diagonal(gap, np.inf)
    assert (gap >= need).all()
    scene = make_scene(preset("small"), n_particles=5, frames=2, seed=1, shape="ellipsoid",
                       velocity_mm_per_frame=(0.1, 0, 0))
    assert list(scene.truth.columns) == [*TRUTH_COLUMNS, *SHAPE_COLUMNS]
    f0, f1 = (g.reset_index(drop=True) for _, g in scene.truth.groupby("frame"))
    np.testing.assert_array_equal(f0["aspect"], f1["aspect"])


@pytest.mark.parametrize("kw, match", [({"shape": "cube"}, "shape must be one of"),
                                       ({"shape": "ellipsoid", "max_aspect": 0.5},
                                        "max_aspect must be")])
def test_invalid_shape_options(kw, match):
    with pytest.raises(SceneError, match=match):
        random_particles(3, volume=Volume((-1, 1), (-1, 1), (-1, 1)), diameter_mm=0.1, **kw)


def test_invalid_ellipsoid_rows(small_optics):
    bad = pd.DataFrame([_spheroid(0, 0, 0, 0.5, 0.5, (0, 0, 1))])
    with pytest.raises(SceneError, match="aspect must be finite and >= 1"):
        render_irradiance(small_optics, bad)
    with pytest.raises(SceneError, match="need column"):
        render_irradiance(small_optics, bad.drop(columns=["axis_z"]))
