"""Tests of projected-plane k-means clustering."""


import numpy as np
import pandas as pd
import pytest

from plenoptrack.camera import preset
from plenoptrack.errors import NoParticlesWarning
from plenoptrack.locate.cluster import (ProjectionGeometry, _kmeanspp_topup, _lloyd,
                                        cluster_detections, plane_alphas, project,
                                        size_thresholds)

try:
    from . import _previous as previous
except ImportError:  # tests/locate is not a package
    import _previous as previous

CAMERA = preset("hall2019")
AXIS = (271.5, 180.5)
GEOM = ProjectionGeometry.from_camera(CAMERA, sample_spacing_px=12.15, axis_st=AXIS)
DEPTHS = (-25.0, 25.0)


def _views(radius=7):
    u, v = np.meshgrid(np.arange(-radius, radius + 1.0), np.arange(-radius, radius + 1.0))
    inside = u ** 2 + v ** 2 <= (radius + 0.5) ** 2
    return u[inside], v[inside]


def _detections(rng, n_particles, *, noise_px=0.1, dropout=0.1, n_spurious=0,
                shape=(362, 544), depths=DEPTHS):
    """Thin-lens detections of random particles; returns table and true particle ids."""
    z = rng.uniform(*depths, n_particles)
    alpha_p = CAMERA.alpha_for_depth(z)
    # image-space point at plane alpha_p, placed so that the central view sees it inside
    s0 = rng.uniform(30, shape[1] - 30, n_particles)
    t0 = rng.uniform(30, shape[0] - 30, n_particles)
    uu, vv = _views()
    rows = []
    for pid in range(n_particles):
        par = GEOM.parallax_per_u(alpha_p[pid])
        keep = rng.random(len(uu)) >= dropout
        s = s0[pid] + par * uu[keep] + rng.normal(0, noise_px, keep.sum())
        t = t0[pid] + par * vv[keep] + rng.normal(0, noise_px, keep.sum())
        area = rng.normal(20, 2, keep.sum())
        rows.append(pd.DataFrame({"frame": 0, "u": uu[keep], "v": vv[keep], "s": s, "t": t,
                                  "area": area, "truth": pid}))
    if n_spurious:
        idx = rng.integers(0, len(uu), n_spurious)
        rows.append(pd.DataFrame({"frame": 0, "u": uu[idx], "v": vv[idx],
                                  "s": rng.uniform(0, shape[1], n_spurious),
                                  "t": rng.uniform(0, shape[0], n_spurious),
                                  "area": rng.normal(20, 2, n_spurious), "truth": -1}))
    det = pd.concat(rows, ignore_index=True)
    return det.sample(frac=1.0, random_state=int(rng.integers(1 << 31))).reset_index(drop=True)


def _purity_completeness(det):
    """Fraction of clustered detections in their cluster's majority particle, and
    fraction of particles with a cluster holding most of their detections."""
    assigned = det[det["cluster"] >= 0]
    majority = assigned.groupby("cluster")["truth"].agg(lambda x: x.value_counts().index[0])
    purity = (assigned["truth"].to_numpy() == majority.loc[assigned["cluster"]].to_numpy()).mean()
    real = det[det["truth"] >= 0]
    best = real.groupby("truth")["cluster"].agg(
        lambda x: (x[x >= 0].value_counts().max() if (x >= 0).any() else 0) / len(x))
    completeness = (best > 0.5).mean()
    return purity, completeness


def test_projection_converges_at_particle_plane():
    # rays of one point imaged at alpha_p meet at alpha_p
    uu, vv = _views()
    alpha_p = CAMERA.alpha_for_depth(12.0)
    par = GEOM.parallax_per_u(alpha_p)
    s = 300.0 + par * uu
    t = 100.0 + par * vv
    at_p = project(uu, vv, s, t, alpha_p, GEOM)
    assert np.ptp(at_p, axis=0).max() < 1e-9
    spread = np.ptp(project(uu, vv, s, t, 1.0, GEOM), axis=0)
    assert spread.min() > 10 * GEOM.mm_per_sample


def test_parallax_sign_behind_focal_plane():
    # a particle behind the focal plane moves towards larger s as u grows
    assert GEOM.aperture_mm_per_u < 0
    assert GEOM.parallax_per_u(CAMERA.alpha_for_depth(10.0)) > 0
    assert GEOM.parallax_per_u(CAMERA.alpha_for_depth(-10.0)) < 0
    assert GEOM.parallax_per_u(1.0) == 0


def test_threshold_bounds_spread_of_half_way_particle():
    alphas = plane_alphas(CAMERA, DEPTHS, 10)
    uu, vv = _views()
    # the views reach a little beyond the nominal aperture rim (pixel centres up to
    # radius 7.5 px); the threshold uses the wider of the two
    r = np.hypot(uu, vv).max() * abs(GEOM.aperture_mm_per_u)
    assert 2 * r > GEOM.aperture_diameter_mm
    thr = size_thresholds(alphas, 2 * r, margin=1.0)
    for i in range(len(alphas) - 1):
        half = 0.5 * (alphas[i] + alphas[i + 1])
        par = GEOM.parallax_per_u(half)
        pts = project(uu, vv, 200 + par * uu, 150 + par * vv, alphas[i], GEOM)
        diam = np.max(np.hypot(*(pts[:, None] - pts[None]).transpose(2, 0, 1)))
        assert diam <= thr[i] + 1e-12
        assert diam == pytest.approx(thr[i], rel=0.02)


@pytest.mark.parametrize("n_particles", [10, 100])
def test_clustering_recovers_particles(n_particles):
    rng = np.random.default_rng(n_particles)
    det = _detections(rng, n_particles)
    res = cluster_detections(det, GEOM, plane_alphas(CAMERA, DEPTHS))
    purity, completeness = _purity_completeness(res.detections)
    # a stray ray of another particle can pass within a sample of a cluster's line in a
    # view where the particle itself was missed; triangulation rejects those
    assert purity > 0.995
    assert completeness >= 0.97
    assert res.n_clusters == pytest.approx(n_particles, abs=max(1, n_particles // 50))
    assert (res.detections["cluster"] >= 0).mean() > 0.95
    # at most one detection per view in a cluster
    assert not res.detections[res.detections["cluster"] >= 0].duplicated(
        ["cluster", "u", "v"]).any()


def test_clustering_with_spurious_detections():
    rng = np.random.default_rng(7)
    det = _detections(rng, 60, n_spurious=300, noise_px=0.2)
    res = cluster_detections(det, GEOM, plane_alphas(CAMERA, DEPTHS))
    purity, completeness = _purity_completeness(res.detections)
    assert purity > 0.99 and completeness >= 0.95
    spurious = res.detections[res.detections["truth"] < 0]
    assert (spurious["cluster"] >= 0).mean() < 0.1


def test_cluster_alpha_near_true_depth():
    rng = np.random.default_rng(3)
    det = _detections(rng, 40, noise_px=0.05)
    alphas = plane_alphas(CAMERA, DEPTHS, 10)
    res = cluster_detections(det, GEOM, alphas)
    d = res.detections[res.detections["cluster"] >= 0]
    # the accepted plane is within two plane spacings of the truth
    step = alphas[1] - alphas[0]
    z = {}
    for pid, grp in d.groupby("truth"):
        par = np.polyfit(grp["u"], grp["s"], 1)[0]
        # parallax -> alpha: par = g (1 - 1/alpha) / mm
        a_true = 1.0 / (1.0 - par * GEOM.mm_per_sample / GEOM.aperture_mm_per_u)
        z[pid] = abs(grp["cluster_alpha"].iloc[0] - a_true)
    assert max(z.values()) < 2 * step


def test_clusters_table_and_determinism():
    rng = np.random.default_rng(11)
    det = _detections(rng, 30)
    alphas = plane_alphas(CAMERA, DEPTHS)
    a = cluster_detections(det, GEOM, alphas, seed=5)
    b = cluster_detections(det, GEOM, alphas, seed=5)
    pd.testing.assert_frame_equal(a.detections, b.detections)
    pd.testing.assert_frame_equal(a.clusters, b.clusters)
    assert "cluster" not in det.columns  # input unchanged
    c = a.clusters
    assert list(c.columns) == ["cluster", "alpha", "n", "size_mm", "threshold_mm",
                               "plane_x_mm", "plane_y_mm", "s", "t"]
    assert (c["size_mm"] <= c["threshold_mm"]).all()
    counts = a.detections[a.detections["cluster"] >= 0].groupby("cluster").size()
    np.testing.assert_array_equal(counts.to_numpy(), c.set_index("cluster").loc[counts.index, "n"])
    # the cluster position in refocused view pixels is the central-view position
    for cid, grp in a.detections[a.detections["cluster"] >= 0].groupby("cluster"):
        centre = grp[(grp["u"] == 0) & (grp["v"] == 0)]
        if len(centre):
            row = c.set_index("cluster").loc[cid]
            assert row["s"] == pytest.approx(centre["s"].iloc[0], abs=1.0)
            assert row["t"] == pytest.approx(centre["t"].iloc[0], abs=1.0)


def test_no_clusters_warns():
    det = pd.DataFrame({"u": [0.0, 1.0], "v": [0.0, 0.0], "s": [10.0, 50.0],
                        "t": [10.0, 10.0], "area": [5.0, 5.0]})
    with pytest.warns(NoParticlesWarning):
        res = cluster_detections(det, GEOM, plane_alphas(CAMERA, DEPTHS))
    assert res.n_clusters == 0 and (res.detections["cluster"] == -1).all()


def test_bad_inputs():
    with pytest.raises(ValueError, match="lacks column"):
        cluster_detections(pd.DataFrame({"u": [0.0]}), GEOM, [1.0])
    with pytest.raises(ValueError, match="strictly ascending"):
        size_thresholds([1.0, 0.9], 10.0)
    with pytest.raises(ValueError, match="mm_per_sample must be a positive"):
        ProjectionGeometry(-1.0, 0.0, (0, 0), 10.0)
    with pytest.raises(ValueError, match="depth_range_mm"):
        plane_alphas(CAMERA, (5.0, -5.0))


def test_end_to_end_simulated_small_frame():
    from plenoptrack.lightfield.decode import decode
    from plenoptrack.locate.segment import segment_views
    from plenoptrack.simulate import make_optics, render_frame, render_white

    cam = preset("small")
    optics = make_optics(cam, seed=1)
    rng = np.random.default_rng(0)
    n = 12
    parts = pd.DataFrame({"x": rng.uniform(-3.5, 3.5, n), "y": rng.uniform(-2.2, 2.2, n),
                          "z": rng.uniform(-10, 10, n), "diameter": 0.35})
    lf = decode(render_frame(optics, parts, seed=0), optics.true_grid,
                white=render_white(optics, seed=1))
    det = segment_views(lf, window=15, contrast=0.2)
    res = cluster_detections(det, ProjectionGeometry.from_lightfield(lf, cam),
                             plane_alphas(cam, (-12.0, 12.0)))
    full = res.clusters["n"] > 0.6 * lf.view_mask.sum()
    # particles seen whole in every view give one full cluster each; particles cut by
    # the field edge may split into partial clusters
    assert n - 2 <= full.sum() <= n
    assert n - 2 <= res.n_clusters <= n + 4
    true_alpha = np.sort(cam.alpha_for_depth(parts["z"].to_numpy()))
    step = np.diff(plane_alphas(cam, (-12.0, 12.0)))[0]
    for a in res.clusters.loc[full, "alpha"]:
        assert np.min(np.abs(true_alpha - a)) < 1.5 * step


def _point_sets(seed):
    """Projected points of four kinds: an integer grid (tied distances), a thin strip,
    repeated points (coincident centres) and a wide scatter."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    kind = seed % 4
    if kind == 0:
        pts = rng.integers(0, 6, (n, 2)).astype(float)
    elif kind == 1:
        pts = rng.normal(0, 1, (n, 2)) * [1.0, 1e-6]
    elif kind == 2:
        pts = np.repeat(rng.uniform(0, 10, (n // 5 + 1, 2)), 5, axis=0)[:n]
    else:
        pts = rng.uniform(-1e3, 1e3, (n, 2))
    k = int(rng.integers(1, min(n, 60) + 1))
    return rng, pts, pts[rng.choice(n, k, replace=False)].copy()


@pytest.mark.parametrize("block", range(4))
def test_grid_search_kernels_match_all_pairs_search(block):
    for seed in range(block * 40, (block + 1) * 40):
        rng, pts, centres = _point_sets(seed)
        want_c, got_c = centres.copy(), centres.copy()
        want = previous._lloyd(pts, want_c, 50)
        assert np.array_equal(_lloyd(pts, got_c, 50), want), seed
        assert np.array_equal(got_c, want_c), seed
        k0 = int(rng.integers(0, len(centres) + 1))
        uniforms = rng.random(10)
        assert np.array_equal(_kmeanspp_topup(pts, centres[:k0].copy(), 10, uniforms),
                              previous._kmeanspp_topup(pts, centres[:k0].copy(), 10, uniforms))


def test_lloyd_with_local_bounds_matches_plain_lloyd_on_a_crowded_plane():
    """Many centres, most settling at once and a few travelling far: the lower bounds
    drop by the moves of nearby centres only, and the labels stay plain Lloyd's."""
    rng = np.random.default_rng(3)
    blobs = rng.uniform(0, 100, (400, 2))
    pts = np.concatenate([np.repeat(blobs, 8, axis=0) + rng.normal(0, 0.3, (3200, 2)),
                          rng.uniform(-50, 150, (300, 2))])
    for k in (50, 400, 700):
        start = pts[rng.choice(len(pts), k, replace=False)].copy()
        want_c, got_c = start.copy(), start.copy()
        want = previous._lloyd(pts, want_c, 50)
        assert np.array_equal(_lloyd(pts, got_c, 50), want), k
        assert np.array_equal(got_c, want_c), k


def test_clustering_unchanged_by_grid_search(monkeypatch):
    import plenoptrack.locate.cluster as cluster_module

    det = _detections(np.random.default_rng(11), 150, n_spurious=300)
    alphas = plane_alphas(CAMERA, DEPTHS, 10)
    got = cluster_detections(det, GEOM, alphas, seed=2)
    monkeypatch.setattr(cluster_module, "_lloyd", previous._lloyd)
    monkeypatch.setattr(cluster_module, "_kmeanspp_topup", previous._kmeanspp_topup)
    want = cluster_detections(det, GEOM, alphas, seed=2)
    assert got.n_clusters > 100
    assert got.detections.equals(want.detections)
    assert got.clusters.equals(want.clusters)
