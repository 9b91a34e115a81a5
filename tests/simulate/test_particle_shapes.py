"""Ellipsoidal (prolate spheroid) and fragment particles: rendering, silhouettes, scenes;
spheres unchanged."""

import hashlib
import math

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack._columns import SHAPE_COLUMNS, TRUTH_COLUMNS
from plenoptrack.simulate import (fragment_geometry, make_optics, make_scene, particle_silhouettes,
                                  random_particles, render_irradiance)
from plenoptrack.simulate.fragments import FRAGMENT_REACH
from plenoptrack.simulate.render import _particle_geometry, background_irradiance
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


PINS = [  # pin heads with their stems (aspect 13), as in the translation-stage study
    _spheroid(0.5, -0.3, 2.0, 0.35, 13.3, (0.3, 0.2, 1.0)),
    _spheroid(-2.0, 1.0, -6.0, 0.4, 13.3, (1.0, -0.5, 0.4)),
    _spheroid(1.5, 1.0, 5.0, 0.3, 8.0, (0.0, 1.0, 0.1)),
    {"x": 0.4, "y": -0.5, "z": -0.2, "diameter": 0.8, "shape": "sphere", "aspect": 1.0,
     "axis_x": 0.0, "axis_y": 0.0, "axis_z": 1.0},
    _spheroid(-1.0, -1.5, 4.0, 0.5, 2.5, (1, -2, 0.5)),
]


@pytest.mark.parametrize("realism", ["ideal", "realistic"])
def test_culled_equals_exact_with_chained_spheroids(realism):
    # Long spheroids are culled with chains of small balls (the realistic optics add lens
    # effects, highlights and the extended shape rows); the image must not change.
    optics = make_optics(preset("small"), seed=2, realism=realism)
    parts = pd.DataFrame(PINS)
    culled = render_irradiance(optics, parts)
    assert (culled != background_irradiance(optics)).sum() > 3000
    np.testing.assert_array_equal(culled, render_irradiance(optics, parts, cull=False))


def test_culling_balls_contain_long_spheroids():
    rng = np.random.default_rng(4)
    parts = pd.DataFrame(PINS)
    optics = make_optics(preset("small"), seed=0, realism="ideal")
    occ, shapes, balls = _particle_geometry(optics, parts)
    # every occluder keeps at least one ball; the pins get chains of small ones
    counts = np.bincount(balls[:, 4].astype(int), minlength=len(parts))
    assert counts.tolist() == [14, 14, 8, 1, 3]
    for q, row in parts.iterrows():
        k, d = row["aspect"], row["diameter"]
        a, b = d / 2 * k ** (2 / 3), d / 2 * k ** (-1 / 3)
        v = np.array([-row["axis_x"], -row["axis_y"], row["axis_z"]])     # camera frame
        e1 = np.cross(v, [1.0, 0.0, 0.0] if abs(v[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(v, e1)
        # points on the surface of the body (the hardest to cover; a hair inside, so
        # that a sphere, its own ball, is not judged on rounding)
        s = rng.uniform(-1, 1, 20000) * (1 - 1e-9)
        phi = rng.uniform(0, 2 * np.pi, s.size)
        rad = b * np.sqrt(1 - s ** 2) * (1 - 1e-9)
        pts = (occ[q, :3] + (a * s)[:, None] * v + (rad * np.cos(phi))[:, None] * e1
               + (rad * np.sin(phi))[:, None] * e2)
        own = balls[balls[:, 4] == q]
        dist2 = ((pts[:, None, :] - own[None, :, :3]) ** 2).sum(axis=2)
        assert (dist2 <= own[None, :, 3]).any(axis=1).all()
        if k >= 8:      # the balls of a pin are much tighter than its bounding sphere
            assert own[0, 3] < 0.1 * occ[q, 3]


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


# --- irregular fragments ---------------------------------------------------------------------

def _fragment(x, y, z, d, aspect, axis, seed):
    return {**_spheroid(x, y, z, d, aspect, axis), "shape": "fragment", "shape_seed": seed}


FRAGMENTS = [(1, 1.0, (0, 0, 1)), (2, 2.5, (1, 1, 0)), (3, 2.0, (-0.3, 1, 0.6)),
             (4, 3.0, (1, -0.2, 0.3))]


@pytest.mark.parametrize("seed, aspect, axis", FRAGMENTS)
def test_fragment_volume_moments_by_monte_carlo(seed, aspect, axis):
    # Points inside the union of the pieces' half-space sets, drawn in the bounding cube.
    frag = fragment_geometry(seed, 0.8, aspect, axis)
    assert 1 <= len(frag.planes) <= 3 and all(8 <= len(p) <= 14 for p in frag.planes)
    again = fragment_geometry(seed, 0.8, aspect, axis)
    for a, b in zip(frag.planes, again.planes):
        np.testing.assert_array_equal(a, b)
    r = frag.bounding_radius
    pts = np.random.default_rng(seed).uniform(-r, r, (300_000, 3))
    inside = np.zeros(len(pts), dtype=bool)
    for planes in frag.planes:
        inside |= (pts @ planes[:, :3].T <= planes[:, 3]).all(axis=1)
        # The core point every piece contains lies inside every piece: star-shaped union.
    assert inside.mean() * (2 * r) ** 3 == pytest.approx(math.pi / 6 * 0.8 ** 3, rel=0.02)
    p = pts[inside]
    np.testing.assert_allclose(p.mean(axis=0), 0.0, atol=0.01)     # centre = centroid
    lam, vec = np.linalg.eigh(np.cov(p.T))
    assert math.sqrt(lam[2] / lam[0]) == pytest.approx(aspect, rel=0.03)
    assert math.sqrt(lam[1] / lam[0]) == pytest.approx(1.0, rel=0.03)
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    if aspect > 1.2:
        assert abs(vec[:, 2] @ u) > 0.999
    # Vertices: all within the bounding radius and the enclosing balls; on the planes.
    for planes, verts, ball in zip(frag.planes, frag.vertices, frag.piece_balls):
        assert (np.abs(verts @ planes[:, :3].T - planes[:, 3]).min(axis=1) < 1e-9).all()
        assert (np.linalg.norm(verts - ball[:3], axis=1) <= ball[3] + 1e-12).all()
        assert (np.linalg.norm(verts - frag.ball[:3], axis=1) <= frag.ball[3] + 1e-12).all()
    assert frag.bounding_radius <= FRAGMENT_REACH * 0.4 * aspect ** (2 / 3)


@pytest.mark.parametrize("seed, aspect, axis", FRAGMENTS)
def test_fragment_silhouette_against_a_raster(seed, aspect, axis):
    from scipy.spatial import ConvexHull

    frag = fragment_geometry(seed, 1.0, aspect, axis)
    truth = particle_silhouettes(pd.DataFrame([_fragment(0, 0, 0, 1.0, aspect, axis, seed)]))
    r = frag.bounding_radius
    n = 700
    g = (np.arange(n) + 0.5) / n * 2 * r - r
    xx, yy = np.meshgrid(g, g)
    pts = np.column_stack([xx.ravel(), yy.ravel()])
    inside = np.zeros(len(pts), dtype=bool)
    for verts in frag.vertices:
        eq = ConvexHull(verts[:, :2]).equations
        inside |= (pts @ eq[:, :2].T + eq[:, 2] <= 0).all(axis=1)
    area = inside.mean() * (2 * r) ** 2
    assert truth["projected_area"].iloc[0] == pytest.approx(area, rel=0.005)
    p = pts[inside]
    c = np.cov(p.T)
    angle = 0.5 * math.atan2(2 * c[0, 1], c[0, 0] - c[1, 1])
    diff = (angle - truth["orientation"].iloc[0] + math.pi / 2) % math.pi - math.pi / 2
    assert abs(diff) < math.radians(0.5)
    assert -math.pi / 2 <= truth["orientation"].iloc[0] < math.pi / 2


@pytest.mark.parametrize("seed, aspect, axis", FRAGMENTS)
def test_fragment_shadow_area_and_orientation(small_optics, seed, aspect, axis):
    # In focus, the shadow summed over all views is the silhouette (times M^2 in pixels).
    particle = _fragment(0.0, 0.0, 0.0, 1.0, aspect, axis, seed)
    truth = particle_silhouettes(pd.DataFrame([particle])).iloc[0]
    area, angle, _ = _shadow(small_optics, particle)
    assert area == pytest.approx(truth["projected_area"], rel=0.03)
    if aspect >= 2:
        diff = (angle - truth["orientation"] + math.pi / 2) % math.pi - math.pi / 2
        assert abs(diff) < math.radians(3)


def test_culled_equals_exact_with_fragments(small_optics):
    parts = pd.DataFrame([
        _fragment(0.5, -0.3, 2.0, 0.7, 2.0, (1, 1, 0.2), 11),
        _fragment(-2.0, 1.0, -6.0, 0.8, 1.3, (0, 0.2, 1), 12),
        {**_spheroid(1.5, 1.2, 0.0, 0.5, 1.0, (0, 0, 1)), "shape": "sphere", "shape_seed": -1},
        {**_spheroid(-1.0, -1.5, 4.0, 0.5, 1.7, (1, -2, 0.5)), "shape_seed": -1},
        _fragment(0.9, -0.5, 5.0, 0.6, 3.0, (1, -2, 0.5), 13),        # overlaps the first in view
    ])
    culled = render_irradiance(small_optics, parts)
    assert (culled != background_irradiance(small_optics)).sum() > 10000
    np.testing.assert_array_equal(culled, render_irradiance(small_optics, parts, cull=False))


def test_random_fragments():
    vol = Volume((-3, 3), (-2, 2), (-5, 5))
    t = random_particles(30, volume=vol, diameter_mm=0.4, seed=5, shape="fragment",
                         max_aspect=3.0)
    assert list(t.columns) == [*TRUTH_COLUMNS, *SHAPE_COLUMNS, "shape_seed"]
    assert (t["shape"] == "fragment").all() and t["aspect"].between(1, 3).all()
    assert t["shape_seed"].dtype == np.int64 and t["shape_seed"].nunique() == 30
    pd.testing.assert_frame_equal(t, random_particles(30, volume=vol, diameter_mm=0.4, seed=5,
                                                      shape="fragment"))
    # Geometry reproducible from the truth row alone; bounding spheres do not overlap.
    reach = np.array([fragment_geometry(r.shape_seed, r.diameter, r.aspect,
                                        (r.axis_x, r.axis_y, r.axis_z)).bounding_radius
                      for r in t.itertuples()])
    xyz = t[["x", "y", "z"]].to_numpy()
    gap = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    np.fill_diagonal(gap, np.inf)
    assert (gap >= reach[:, None] + reach[None]).all()
    # Fragments of one volume have more varied, mostly larger silhouettes than spheres.
    ratio = t["projected_area"] / (math.pi * t["diameter"] ** 2 / 4)
    assert ratio.median() > 1.1 and ratio.std() > 0.1
    scene = make_scene(preset("small"), n_particles=4, frames=2, seed=1, shape="fragment",
                       velocity_mm_per_frame=(0.1, 0, 0))
    f0, f1 = (g.reset_index(drop=True) for _, g in scene.truth.groupby("frame"))
    np.testing.assert_array_equal(f0["shape_seed"], f1["shape_seed"])
    np.testing.assert_array_equal(f0["projected_area"], f1["projected_area"])


def test_invalid_fragment_rows(small_optics):
    good = _fragment(0, 0, 0, 0.5, 2.0, (1, 0, 0), 3)
    with pytest.raises(SceneError, match="need column 'shape_seed'"):
        render_irradiance(small_optics, pd.DataFrame([good]).drop(columns=["shape_seed"]))
    with pytest.raises(SceneError, match="shape_seed must be an integer >= 0"):
        render_irradiance(small_optics, pd.DataFrame([{**good, "shape_seed": -2}]))
    with pytest.raises(SceneError, match="shape_seed must be an integer >= 0"):
        particle_silhouettes(pd.DataFrame([{**good, "shape_seed": 1.5}]))
