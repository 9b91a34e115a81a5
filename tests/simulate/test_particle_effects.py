"""Particle effects: partial translucency, specular highlights, motion blur over the exposure
(the ``particles`` group of Realism); their physics, exact culling and unchanged bytes."""

import hashlib
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from plenoptrack import preset
from plenoptrack._columns import TRUTH_COLUMNS, VELOCITY_COLUMNS
from plenoptrack.errors import InputFileError, SettingsError
from plenoptrack.simulate import (
    LensEffects,
    ParticleEffects,
    Realism,
    SceneError,
    SimOptics,
    _kernels,
    fragment_geometry,
    load_scene,
    make_optics,
    make_scene,
    realism_from_dict,
    render_irradiance,
    simulate_dataset,
    with_particle_effects,
)
from plenoptrack.simulate.render import (
    _particle_arrays,
    background_irradiance,
    sample_pattern,
)

CAM = preset("small")
OFF = Realism.ideal().particles


def _optics(seed=0, lens=None, **particles):
    real = replace(Realism.ideal(), particles=replace(OFF, **particles))
    if lens is not None:
        real = replace(real, lens=lens)
    return make_optics(CAM, seed, realism=real)


def _sphere(x, y, z, d, **extra):
    return {"x": x, "y": y, "z": z, "diameter": d, **extra}


def _shape(kind, x, y, z, d, aspect, axis, seed=-1, **extra):
    u = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return {"x": x, "y": y, "z": z, "diameter": d, "shape": kind, "aspect": aspect,
            "axis_x": u[0], "axis_y": u[1], "axis_z": u[2], "shape_seed": seed, **extra}


# --- the settings group ----------------------------------------------------------------------

def test_particle_group_switches_and_scales():
    assert not Realism.ideal().particles.enabled
    real = Realism.realistic().particles
    assert (real.max_transmission, real.highlight_strength, real.exposure_fraction) == (0.1, 0.5, 0.05)
    half = Realism.realistic().scaled(0.5, group="particles").particles
    assert (half.max_transmission, half.highlight_strength, half.exposure_fraction) == (0.05, 0.25, 0.025)
    assert (half.highlight_exponent, half.light_elevation_deg) == (50.0, 45.0)   # not sizes
    light = np.array(real.light_direction)
    assert np.linalg.norm(light) == pytest.approx(1.0) and light[2] < 0   # camera side
    table = realism_from_dict({"mode": "ideal", "particles": {"exposure_fraction": 0.2}})
    assert table.particles.exposure_fraction == 0.2 and table.particles.max_transmission == 0


@pytest.mark.parametrize("kw, match", [
    ({"max_transmission": 1.0}, "max_transmission must be in \\[0, 1\\)"),
    ({"exposure_fraction": 1.5}, "exposure_fraction must be in \\[0, 1\\]"),
    ({"highlight_exponent": 0.0}, "highlight_exponent must be > 0"),
    ({"light_elevation_deg": 95.0}, "light_elevation_deg must be in \\[0, 90\\]"),
    ({"light_azimuth_deg": 360.0}, "light_azimuth_deg must be in \\[0, 360\\)"),
    ({"highlight_strength": -1.0}, "highlight_strength must be a finite number >= 0"),
])
def test_bad_particle_settings(kw, match):
    with pytest.raises(SettingsError, match=match):
        ParticleEffects(**kw)


def test_old_optics_files_read_without_particle_effects():
    for mode in ("ideal", "realistic"):
        doc = make_optics(CAM, 1, realism=mode).to_dict()
        del doc["realism"]["particles"]
        assert SimOptics.from_dict(doc).realism.particles == OFF


# --- unchanged bytes -------------------------------------------------------------------------

SPHERES = [[0.5, -0.3, 2.0, 0.8], [-2.0, 1.0, -6.0, 1.0], [1.0, 1.0, 0.0, 0.6]]


def test_effects_off_keep_the_bytes(small_optics):
    # Same digest as tests/simulate/test_particle_shapes.py (spheres before any effect):
    # effect columns at zero, or their group off, take the original code path.
    parts = pd.DataFrame(SPHERES, columns=["x", "y", "z", "diameter"]).assign(
        transmission=0.0, velocity_x=0.3, velocity_y=0.0, velocity_z=1.0)
    o = replace(small_optics, realism=replace(small_optics.realism,
                                              particles=replace(OFF, max_transmission=0.1)))
    _, shapes = _particle_arrays(o, parts)
    assert shapes.shape == (0, 7)
    irr = render_irradiance(o, parts)
    assert hashlib.sha256(irr.tobytes()).hexdigest() == (
        "17018194a4adbb0daaf662691db0954c6b92c0e4e7567ba4ba1d3e05c2838d75")
    truth = make_scene(CAM, n_particles=3, seed=2).truth
    assert with_particle_effects(truth, OFF, seed=0) is truth


def test_sample_times_stratified_symmetric_and_decorrelated():
    for n in (15, 16, 64):
        s = np.asarray(sample_pattern(make_optics(CAM, 0), n))
        assert s.shape == (n, 5)
        np.testing.assert_allclose(np.sort(s[:, 4]), (np.arange(n) + 0.5) / n - 0.5, atol=1e-15)
        np.testing.assert_array_equal(s[n // 2:2 * (n // 2), 4], -s[:n // 2, 4])
        corr = np.corrcoef(s.T)[4, :4]
        assert np.abs(corr).max() < 0.05


# --- translucency ----------------------------------------------------------------------------

def test_translucent_shadow_level_equals_tau():
    o = _optics()
    bg = background_irradiance(o)
    tau = 0.3
    irr = render_irradiance(o, pd.DataFrame([_sphere(0.1, -0.2, 0.0, 1.6, transmission=tau)]))
    opaque = render_irradiance(o, pd.DataFrame([_sphere(0.1, -0.2, 0.0, 1.6)]))
    core = (opaque == 0) & (bg > 0.5)                  # every sample meets the particle
    assert core.sum() > 1000
    np.testing.assert_allclose(irr[core], tau * bg[core], rtol=1e-6)
    assert (irr >= opaque).all() and (irr <= bg).all()
    # The shadow's depth scales by 1 - tau everywhere.
    dark_t = (bg - irr).astype(float).sum()
    dark_o = (bg - opaque).astype(float).sum()
    assert dark_t / dark_o == pytest.approx(1 - tau, rel=1e-5)


def _ray_values(optics, particles, rays, t=0.0):
    occ, shapes = _particle_arrays(optics, pd.DataFrame(particles))
    par = _kernels.pack_params(optics)
    cand = np.arange(len(occ))
    return np.array([_kernels._ray_value(hx, hy, dx, dy, t, occ, cand, len(occ), shapes, par)
                     for hx, hy, dx, dy in rays])


def test_rays_through_several_translucent_particles_multiply():
    o = _optics()
    parts = [_shape("sphere", 0.0, 0.0, -3.0, 0.6, 1.0, (0, 0, 1), transmission=0.4),
             _shape("sphere", 0.05, 0.0, 4.0, 0.6, 1.0, (0, 0, 1), transmission=0.25),
             _shape("fragment", -0.02, 0.03, 8.0, 0.6, 1.5, (1, 0, 0), 7, transmission=0.5)]
    on_axis = [(0.0, 0.0, 0.0, 0.0)]
    assert _ray_values(o, parts, on_axis)[0] == 0.4 * 0.25 * 0.5
    assert _ray_values(o, parts[:2], on_axis)[0] == 0.4 * 0.25
    assert _ray_values(o, parts[:1], [(5.0, 0.0, 0.0, 0.0)])[0] == 1.0     # misses


# --- specular highlights ---------------------------------------------------------------------

S, E = 0.8, 40.0


def _camera(p):
    return np.array([-p["x"], -p["y"], p["z"]])


def _entry_sphere_or_spheroid(p, c, h, d, optics):
    """Entry parameter and outward normal of the line h + Z d (camera frame), or None."""
    r = p["diameter"] / 2
    k = p.get("aspect", 1.0) if p.get("shape", "sphere") == "ellipsoid" else 1.0
    a, b = r * k ** (2 / 3), r * k ** (-1 / 3)
    v = np.array([-p.get("axis_x", 0), -p.get("axis_y", 0), p.get("axis_z", 1)])
    m = (np.eye(3) - np.outer(v, v)) / b ** 2 + np.outer(v, v) / a ** 2
    w = h - c
    qa, qb, qc = d @ m @ d, 2 * d @ m @ w, w @ m @ w - 1
    disc = qb * qb - 4 * qa * qc
    if disc <= 0:
        return None
    z = (-qb - math.sqrt(disc)) / (2 * qa)
    return z, m @ (w + z * d)


def _entry_fragment(p, c, h, d):
    frag = fragment_geometry(p["shape_seed"], p["diameter"], p["aspect"],
                             (p["axis_x"], p["axis_y"], p["axis_z"]))
    best = None
    for planes in frag.planes:
        n = planes[:, :3] * np.array([-1.0, -1.0, 1.0])
        a = n @ d
        b = planes[:, 3] - n @ (h - c)
        with np.errstate(divide="ignore"):
            z = b / a
        lo = z[a < 0].max()
        hi = z[a > 0].min()
        if lo < hi and (best is None or lo < best[0]):
            best = (lo, n[a < 0][np.argmax(z[a < 0])])
    return best


def _mirror_light(normal):
    """(elevation, azimuth) deg of the light that a facet of world normal ``normal``
    reflects straight back along the axis to the camera (world -z)."""
    v = np.array([0.0, 0.0, -1.0])
    light = 2 * (normal @ v) * normal - v
    return (math.degrees(math.acos(-light[2])),
            math.degrees(math.atan2(light[1], light[0])) % 360.0)


@pytest.mark.parametrize("kind", ["sphere", "ellipsoid", "fragment"])
def test_highlight_follows_blinn_phong_at_the_entry_point(kind):
    tau = 0.05
    p = (_sphere(0.2, -0.1, 1.0, 0.9, transmission=tau) if kind == "sphere" else
         _shape(kind, 0.2, -0.1, 1.0, 0.9, 2.0, (1, 0.5, -0.7), 5, transmission=tau))
    elev, az = 40.0, 120.0
    if kind == "fragment":
        # Light mirrored by the facet that faces the camera most: a glint of a flat facet.
        frag = fragment_geometry(5, 0.9, 2.0, (1, 0.5, -0.7))
        normals = np.concatenate([planes[:, :3] for planes in frag.planes])
        elev, az = _mirror_light(normals[np.argmin(normals[:, 2])])
    o = _optics(highlight_strength=S, highlight_exponent=E, light_elevation_deg=elev,
                light_azimuth_deg=az)
    c = _camera(p) + np.array([0, 0, o.s_o])
    rng = np.random.default_rng(3)
    n_rays = 3000
    h = np.column_stack([rng.uniform(-1, 1, (n_rays, 2)) * o.aperture_radius * 0.7,
                         np.zeros(n_rays)])
    aim = c + rng.uniform(-0.6, 0.6, (n_rays, 3))
    d = (aim - h) / (aim[:, 2:] - h[:, 2:])
    rays = np.column_stack([h[:, :2], d[:, :2]])
    got = _ray_values(o, [p], rays)
    light = np.array(o.realism.particles.light_direction) * np.array([-1.0, -1.0, 1.0])
    expected, nh_all, hits = [], [], 0
    for hi, di in zip(h, d):
        entry = (_entry_fragment(p, c, hi, di) if kind == "fragment"
                 else _entry_sphere_or_spheroid(p, c, hi, di, o))
        if entry is None:
            expected.append(1.0)
            nh_all.append(np.nan)
            continue
        hits += 1
        n = entry[1] / np.linalg.norm(entry[1])
        half = light - di / np.linalg.norm(di)
        nh = n @ half / np.linalg.norm(half)
        nh_all.append(nh)
        expected.append(min(1.0, tau + S * max(nh, 0.0) ** E))
    expected, nh_all = np.array(expected), np.array(nh_all)
    assert hits > 1000
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-9)
    glint = (got - tau > 0.05 * S) & (got < 1.0)
    assert glint.sum() > 20
    assert (nh_all[glint] > 0.05 ** (1 / E)).all()          # only where n . h is near 1
    assert got.max() <= 1.0


def test_highlight_in_the_image_sits_where_n_h_is_one_and_never_exceeds_the_back_light():
    elev, az = 60.0, 200.0
    lit = _optics(highlight_strength=0.8, highlight_exponent=50.0, light_elevation_deg=elev,
                  light_azimuth_deg=az)
    o = _optics()
    c = np.array([0.3, -0.2, 0.0])
    r = 1.0
    part = pd.DataFrame([_sphere(*c, 2 * r)])
    with_hl = render_irradiance(lit, part)
    without = render_irradiance(o, part)
    bg = background_irradiance(o)
    assert (with_hl <= bg).all() and (with_hl >= without).all()
    glint = with_hl.astype(float) - without
    assert (glint[without == bg] == 0).all()                 # only on the particle
    rows, cols = np.indices(glint.shape)
    w = glint / glint.sum()
    centroid = np.array([(w * rows).sum(), (w * cols).sum()])
    # Where the normal is the half vector of the light and the view (chief ray).
    light = np.array(lit.realism.particles.light_direction)
    half = light + np.array([0.0, 0.0, -1.0])
    half /= np.linalg.norm(half)
    predicted = lit.world_to_pixels(c + r * half) - lit.world_to_pixels(c)
    measured = centroid - lit.world_to_pixels(c)
    assert np.linalg.norm(measured - predicted) < 0.1 * np.linalg.norm(predicted) + 1.0


# --- motion blur -----------------------------------------------------------------------------

def _moments(optics, irr):
    """Shadow area (mm^2) and covariance (mm^2, x then y) on the focal plane."""
    bg = background_irradiance(optics).astype(float)
    dark = bg - irr.astype(float)
    mm_px = optics.pixel_pitch / optics.image_scale * optics.s_o / optics.s_i
    rows, cols = np.indices(dark.shape)
    s = dark.sum()
    xy = np.stack([cols, rows]) * mm_px
    mean = (dark * xy).reshape(2, -1).sum(axis=1) / s
    cen = xy - mean[:, None, None]
    cov = np.einsum("iab,jab,ab->ij", cen, cen, dark) / s
    return s / bg.mean() * mm_px ** 2, mean, cov


@pytest.mark.parametrize("z, velocity", [(0.0, (0.0, -1.2, 0.0)), (4.0, (1.0, 0.5, 0.0)),
                                         (-3.0, (-0.6, 0.9, 1.5))])
def test_motion_blur_elongates_the_shadow_along_the_velocity(z, velocity):
    fraction = 0.5
    o = _optics(exposure_fraction=fraction)
    still = _sphere(0.2, -0.1, z, 0.8)
    moving = {**still, **dict(zip(VELOCITY_COLUMNS, velocity))}
    a0, m0, c0 = _moments(o, render_irradiance(o, pd.DataFrame([still])))
    a1, m1, c1 = _moments(o, render_irradiance(o, pd.DataFrame([moving])))
    path = np.array(velocity[:2]) * fraction * o.s_o / (o.s_o + z)   # on the focal plane
    along = path / np.linalg.norm(path)
    across = np.array([-along[1], along[0]])
    grown = c1 - c0
    # A uniform sweep of length L adds L^2 / 12 to the variance along it, nothing across.
    assert math.sqrt(12 * along @ grown @ along) == pytest.approx(np.linalg.norm(path), rel=0.1)
    assert abs(across @ grown @ across) < 0.1 * (along @ grown @ along)
    assert a1 == pytest.approx(a0, rel=0.02)                        # same total shadow
    np.testing.assert_allclose(m1, m0, atol=0.01)                   # centred on the truth


# --- exact culling with every effect ---------------------------------------------------------

EFFECT_PARTS = [
    _sphere(0.5, -0.3, 2.0, 0.7, transmission=0.2, velocity_x=0.6, velocity_y=0.1, velocity_z=3.0),
    _sphere(-2.0, 1.0, -6.0, 0.9),
    _shape("ellipsoid", 0.9, -0.1, 5.0, 0.5, 2.5, (1, 1, 0.2), transmission=0.5,
           velocity_x=0.0, velocity_y=-1.0, velocity_z=0.0),
    _shape("fragment", -1.0, -1.5, 4.0, 0.6, 2.0, (0, 0.2, 1), 21, transmission=0.05,
           velocity_x=-0.8, velocity_y=0.0, velocity_z=0.0),
    _shape("fragment", 0.7, -0.4, -4.0, 0.5, 1.2, (1, -2, 0.5), 22),
]


@pytest.mark.parametrize("lens", [None, LensEffects().scaled(5.0)], ids=["thin-lens", "lens-effects"])
def test_culled_equals_exact_with_every_particle_effect(lens):
    o = _optics(2, lens=lens, highlight_strength=0.6, highlight_exponent=20.0,
                exposure_fraction=0.4)
    parts = pd.DataFrame(EFFECT_PARTS).fillna({"velocity_x": 0.0, "velocity_y": 0.0,
                                               "velocity_z": 0.0, "transmission": 0.0})
    parts["shape"] = parts["shape"].fillna("sphere")
    parts = parts.fillna({"aspect": 1.0, "axis_x": 0.0, "axis_y": 0.0, "axis_z": 1.0,
                          "shape_seed": -1})
    culled = render_irradiance(o, parts)
    assert (culled != background_irradiance(o)).sum() > 10000
    assert (culled <= background_irradiance(o)).all()
    np.testing.assert_array_equal(culled, render_irradiance(o, parts, cull=False))


# --- scenes, data sets, errors ---------------------------------------------------------------

def test_data_set_records_transmission_and_velocity(tmp_path):
    eff = ParticleEffects()
    real = replace(Realism.ideal(), particles=eff)
    res = simulate_dataset("small", tmp_path / "a", seed=4, n_particles=3, frames=2,
                           velocity_mm_per_frame=(0.2, 0.0, -0.1), dotcard_depths=[],
                           realism=real, samples_per_pixel=4)
    truth = pd.read_parquet(res.truth_path)
    assert list(truth.columns) == [*TRUTH_COLUMNS, "transmission", *VELOCITY_COLUMNS]
    assert truth["transmission"].between(0, eff.max_transmission).all()
    per_particle = truth.groupby("particle")["transmission"].nunique()
    assert (per_particle == 1).all() and truth["transmission"].nunique() == 3
    np.testing.assert_array_equal(truth[list(VELOCITY_COLUMNS)].drop_duplicates().to_numpy(),
                                  [[0.2, 0.0, -0.1]])
    ideal = simulate_dataset("small", tmp_path / "b", seed=4, n_particles=3, frames=1,
                             dotcard_depths=[], samples_per_pixel=4, realism="ideal")
    assert list(pd.read_parquet(ideal.truth_path).columns) == list(TRUTH_COLUMNS)


def test_scene_file_fragments_and_particle_effects(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text('camera = "small"\nseed = 2\nvelocity_mm_per_frame = [0.0, 0.3, 0.0]\n'
                    '[random]\nn = 4\nshape = "fragment"\nmax_aspect = 2.0\n'
                    '[optics]\nmode = "ideal"\n[optics.particles]\nexposure_fraction = 0.1\n')
    scene = load_scene(path)
    assert (scene.truth["shape"] == "fragment").all() and scene.truth["aspect"].le(2.0).all()
    assert scene.realism.particles.exposure_fraction == 0.1
    v = scene.particle_velocities()
    np.testing.assert_array_equal(v[list(VELOCITY_COLUMNS)].to_numpy(), [[0.0, 0.3, 0.0]] * 4)
    path.write_text('camera = "small"\n[random]\nn = 1\n'
                    '[optics.particles]\nmax_transmission = 1.5\n')
    with pytest.raises(InputFileError, match="max_transmission must be in"):
        load_scene(path)


def test_bad_particle_effect_columns():
    o = _optics()
    with pytest.raises(SceneError, match="transmission must be in \\[0, 1\\)"):
        render_irradiance(o, pd.DataFrame([_sphere(0, 0, 0, 0.5, transmission=1.0)]))
    with pytest.raises(SceneError, match="needs all of"):
        render_irradiance(o, pd.DataFrame([_sphere(0, 0, 0, 0.5, velocity_x=1.0)]))
    with pytest.raises(SceneError, match="velocities must be finite"):
        render_irradiance(o, pd.DataFrame([_sphere(0, 0, 0, 0.5, velocity_x=np.inf,
                                                   velocity_y=0.0, velocity_z=0.0)]))
    with pytest.raises(SettingsError, match="effects must be a ParticleEffects"):
        with_particle_effects(make_scene(CAM, n_particles=1).truth, Realism.ideal(), seed=0)
