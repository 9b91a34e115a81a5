"""The locator's steps that compare particles with each other or with centroids, against
the all-pairs versions they replaced (``_previous.py``): identical outputs on random
inputs (NaN predictions, views without centroids, tied distances, confidences and
centroid counts) and, with every replaced step (k-means and triangulation included) put
back, identical particle tables from :func:`locate_frame`."""

import sys

import numpy as np
import pytest

from plenoptrack.locate import _assign, perspective
from plenoptrack.locate.dlfc import fit_dlfc
from plenoptrack.simulate import make_scene

try:
    from . import _previous as previous
    from .test_dlfc import PlenopticModel, dot_cards, views
    from .test_perspective import _frame
except ImportError:  # tests/locate is not a package
    import _previous as previous
    from test_dlfc import PlenopticModel, dot_cards, views
    from test_perspective import _frame

SEEDS = range(100)


def _state(seed):
    """Random predictions (P, V, 2), centroids near them and the per-particle values.

    Every third seed puts everything on an integer grid, so that distances, confidences
    and centroid counts tie; some particles are near-copies of others (duplicates to
    merge); some have no prediction, and odd seeds blank single views of others.
    """
    rng = np.random.default_rng(seed)
    n_p, n_v = int(rng.integers(0, 30)), int(rng.integers(1, 9))
    grid = seed % 3 == 0
    if grid:
        pred = rng.integers(0, 12, (n_p, 1, 2)) + rng.integers(-1, 2, (n_p, n_v, 2)).astype(float)
    else:
        pred = rng.uniform(0, 30, (n_p, 1, 2)) + rng.normal(0, 1.0, (n_p, n_v, 2))
    if n_p > 3:
        copy, of = rng.integers(0, n_p, (2, n_p // 3))
        pred[copy] = pred[of] + (0.0 if grid else rng.normal(0, 0.5, pred[of].shape))
    pred[rng.random(n_p) < 0.1] = np.nan
    if seed % 2:
        pred[rng.random((n_p, n_v)) < 0.05] = np.nan
    m = int(rng.integers(0, 120))
    view = rng.integers(0, n_v, m)
    view[view == n_v - 1] = max(n_v - 2, 0)              # the last view has no centroid
    if n_p:
        st = pred[rng.integers(0, n_p, m), view] + (
            rng.integers(-1, 2, (m, 2)) if grid else rng.normal(0, 0.7, (m, 2)))
        lost = ~np.isfinite(st)
        st[lost] = rng.uniform(0, 30, (m, 2))[lost]
        owner = np.where(rng.random(m) < 0.5, -1, rng.integers(-2, n_p, m))
    else:
        st = rng.uniform(0, 30, (m, 2))
        owner = np.full(m, -1)
    return {
        "pred": pred, "st": st, "view": view, "owner": owner,
        "n_views": np.bincount(owner[owner >= 0], minlength=n_p),
        "residual": rng.choice([np.nan, 0.1, 0.3, 0.5, 2.0], n_p),
        "confidence": (rng.choice([np.nan, 1.0, 2.0, 3.0, np.inf], n_p) if grid
                       else rng.uniform(0, 5, n_p)),
        "radius": (rng.choice([0.5, 1.0, 2.0, 3.0], m) if grid else rng.uniform(0.2, 3, m)),
        "ok": rng.random(n_p) < 0.8,
    }


def test_add_centroids_matches_all_pairs():
    changed = 0
    for seed in SEEDS:
        a = _state(seed)
        for tol in (0.5, 1.0):
            args = (a["pred"], a["st"], a["view"], a["owner"], a["residual"],
                    a["confidence"], tol)
            want = previous._add_centroids(*args)
            assert np.array_equal(_assign._add_centroids(*args), want), (seed, tol)
            changed += int(np.any(want != a["owner"]))
    assert changed > 60


def test_merge_duplicates_matches_all_pairs():
    changed = 0
    for seed in SEEDS:
        a = _state(seed)
        for merge_px in (0.5, 1.0, 2.0):
            args = (a["pred"], a["st"], a["view"], a["owner"], a["n_views"], merge_px)
            want = previous._merge_duplicates(*args)
            assert np.array_equal(_assign._merge_duplicates(*args), want), (seed, merge_px)
            changed += int(np.any(want != a["owner"]))
    assert changed > 30


def _explained_at_once(a, explainers, limit):
    """The particles over ``limit`` with every particle of ``explainers`` explaining."""
    frac = previous._explained_by_others(a["pred"], a["st"], a["view"], a["owner"],
                                         a["radius"], explainers)
    return a["ok"] & (frac > limit)


def test_particles_explained_away_are_judged_weakest_first():
    differs = 0
    for seed in SEEDS:
        a = _state(seed)
        limit = np.random.default_rng(seed).choice([0.0, 0.3, 0.5, 0.85], len(a["ok"]))
        judged = a["ok"]
        explainers = judged & (np.random.default_rng(seed + 1).random(len(judged)) < 0.9)
        got = _assign._explained_away(a["pred"], a["st"], a["view"], a["owner"], a["radius"],
                                      explainers, judged, limit, a["n_views"])
        want = previous._explained_away(a["pred"], a["st"], a["view"], a["owner"],
                                        a["radius"], explainers, judged, limit, a["n_views"])
        assert np.array_equal(got, want), seed
        at_once = _explained_at_once(a, explainers, limit)
        # every particle explained away is explained with all the others explaining
        assert not np.any(got & ~at_once), seed
        # and without the ones explained away, no other one is
        assert not np.any(_explained_at_once(a, explainers & ~got, limit) & ~got), seed
        differs += int(np.any(got != at_once))
    assert differs > 0


def test_a_particle_is_not_explained_away_by_weaker_particles_it_explains():
    """One real particle (30 views) and two ghosts on its line of sight (10 views each):
    in every view of the ghosts, the other two are predicted on their centroid, and in
    every view of the real one the ghosts are predicted on its. Judged at once, all
    three go. Weakest first, the first ghost goes; without it neither the second ghost
    nor the real particle lies between two others, and both stay (the next grow and
    solve decide on the ghost). A ghost between two real particles goes as before."""
    n_v = 30
    pred = np.zeros((5, n_v, 2))
    pred[:, :, 0] = np.arange(n_v)[None] * 10.0           # one image per view
    pred[1, :, 1] = pred[2, :, 1] = 0.3                    # the ghosts, on the real one
    pred[3, :, 1], pred[4, :, 1] = 50.0, 53.0              # two real ones, and a ghost
    views = np.arange(n_v)
    owner_real = np.zeros(n_v, dtype=np.int64)
    st = [pred[0], pred[1, :10], pred[2, 10:20], pred[3], pred[4]]
    view = [views, views[:10], views[10:20], views, views]
    owner = [owner_real, np.full(10, 1), np.full(10, 2), np.full(n_v, 3), np.full(n_v, 4)]
    # a ghost of 3 and 4 between them, in 12 views
    ghost = np.c_[pred[3, :12, 0], np.full(12, 51.5)]
    pred = np.concatenate([pred, np.c_[pred[3, :, 0], np.full(n_v, 51.5)][None]])
    st, view = np.vstack(st + [ghost]), np.concatenate(view + [views[:12]])
    owner = np.concatenate(owner + [np.full(12, 5)])
    radius = np.where(owner == 5, 1.6, 1.0)               # the ghost's regions are larger
    ok = np.ones(6, dtype=bool)
    n_views = np.bincount(owner, minlength=6)
    limit = np.full(6, 0.5)
    at_once = previous._explained_by_others(pred, st, view, owner, radius, ok) > limit
    assert at_once.tolist() == [True, True, True, False, False, True]
    got = _assign._explained_away(pred, st, view, owner, radius, ok, ok, limit, n_views)
    assert got.tolist() == [False, True, False, False, False, True]
    want = previous._explained_away(pred, st, view, owner, radius, ok, ok, limit, n_views)
    assert np.array_equal(got, want)


class _ShiftModel:
    """Stand-in calibration: a point at (x, y, z) shows at (x + u z, y + v z)."""

    def predict(self, x, y, z, u, v):
        return x + u * z, y + v * z

    def view_basis(self, u, v):
        return np.c_[u, v].astype(float)

    def predict_in_views(self, xyz, basis):
        xyz = np.reshape(xyz, (-1, 3))
        return np.stack(self.predict(xyz[:, None, 0], xyz[:, None, 1], xyz[:, None, 2],
                                     basis[None, :, 0], basis[None, :, 1]), axis=-1)


def test_release_unclaimed_matches_all_pairs():
    released = 0
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        a = _state(seed)
        n_p, n_v = a["pred"].shape[:2]
        positions = np.column_stack([rng.uniform(0, 30, (n_p, 2)), rng.uniform(-1, 1, n_p)])
        positions[rng.random(n_p) < 0.1] = np.nan
        views = rng.integers(-2, 3, (n_v, 2)).astype(float)
        owner = np.where(rng.random(len(a["owner"])) < 0.5, _assign._MERGED, a["owner"])
        round_ = rng.random(len(owner)) < 0.8
        halves = rng.random(len(owner)) < 0.3
        area = rng.uniform(10, 30, len(owner))
        args = (_ShiftModel(), positions, views, a["st"], a["view"], owner, a["radius"], round_)
        for kw in ({}, {"halves": halves, "tolerance_px": 1.0},
                   {"halves": halves, "tolerance_px": 1.0, "area": area,
                    "max_area_ratio": 1.3}):
            want = previous._release_unclaimed(*args, **kw)
            assert np.array_equal(_assign._release_unclaimed(*args, **kw), want), seed
            released += int(np.any(want != owner))
    assert released > 60


def test_a_half_its_located_partner_leaves_is_released():
    """Two halves of a split pair 3 px apart in each of 5 views. A particle located on
    one half leaves the other to the pool; one located between them (an elongated image
    of one particle) claims both."""
    views = np.column_stack([np.arange(5.0), np.zeros(5)])
    st = np.vstack([np.tile([[10.0, 10.0]], (5, 1)), np.tile([[13.0, 10.0]], (5, 1))])
    view = np.tile(np.arange(5), 2)
    owner = np.full(10, _assign._MERGED)
    radius = np.full(10, 3.5)
    halves = np.ones(10, dtype=bool)
    round_ = np.ones(10, dtype=bool)
    on_first = np.array([[10.0, 10.0, 0.0]])
    got = _assign._release_unclaimed(_ShiftModel(), on_first, views, st, view, owner,
                                        radius, round_, halves=halves, tolerance_px=1.0)
    assert np.all(got[:5] == _assign._MERGED) and np.all(got[5:] == -1)
    between = np.array([[11.5, 10.0, 0.0]])
    got = _assign._release_unclaimed(_ShiftModel(), between, views, st, view, owner,
                                        radius, round_, halves=halves, tolerance_px=1.0)
    assert np.all(got == _assign._MERGED)
    # without the halves flag only the round-and-empty rule applies: nothing is released
    got = _assign._release_unclaimed(_ShiftModel(), on_first, views, st, view, owner,
                                        radius, round_)
    assert np.all(got == _assign._MERGED)


def test_trim_refit_matches_per_particle_scan():
    model = PlenopticModel()
    dlfc = fit_dlfc(dot_cards(model), order=4)
    u, v = views(7)
    grid = np.unique(np.column_stack([u, v]), axis=0)
    rng = np.random.default_rng(4)
    truth = np.column_stack([rng.uniform(-20, 20, (12, 2)), rng.uniform(-15, 15, 12)])
    lab = np.repeat(np.arange(12), len(grid))
    view = np.tile(np.arange(len(grid)), 12)
    s, t = model(truth[lab, 0], truth[lab, 1], truth[lab, 2], grid[view, 0], grid[view, 1])
    st = np.column_stack([s, t]) + rng.normal(0, 0.05, (len(s), 2))
    pulled = rng.random(len(s)) < 0.3                    # centroids pulled by overlaps
    st[pulled] += rng.normal(0, 2.0, (pulled.sum(), 2))
    owner = np.where(rng.random(len(s)) < 0.1, -1, lab)
    start = truth + rng.normal(0, 0.2, truth.shape)
    start[3] = np.nan
    for particles in (np.arange(12), np.array([1, 3, 5, 8]), np.array([], dtype=np.int64)):
        args = (dlfc, st, view, grid, owner, start, particles, 6, 1.0)
        want_owner, want_pos = previous._trim_refit(*args)
        got_owner, got_pos = _assign._trim_refit(*args)
        assert np.array_equal(got_owner, want_owner)
        assert np.array_equal(got_pos, want_pos, equal_nan=True)
        assert np.any(want_owner != owner) == (len(particles) > 0)


def _use_previous_steps(monkeypatch):
    for module, names in previous.REPLACED.items():
        for name in names:
            monkeypatch.setattr(sys.modules[module], name, getattr(previous, name))


@pytest.mark.parametrize("n_particles, diameter_mm", [(80, 0.2), (30, None)])
def test_locate_frame_matches_previous_steps(small_calibrated, monkeypatch, n_particles,
                                              diameter_mm):
    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=n_particles, seed=3, diameter_mm=diameter_mm)
    raw = _frame(optics, scene.truth, 3)
    new = perspective.locate_frame(raw, calib)
    with monkeypatch.context() as m:
        _use_previous_steps(m)
        old = perspective.locate_frame(raw, calib)
    assert len(new.particles) >= 0.9 * n_particles
    assert new.particles.equals(old.particles)
    assert new.detections.equals(old.detections)


def test_a_crowd_of_shares_does_not_raise_the_size_reference_of_pair_splitting():
    """Shares of merged images (``whole`` False) are as large as a particle's image; were
    they counted in the median area, a crowd of them would let a merged pair pass for
    one image."""
    import pandas as pd

    from plenoptrack.locate._regions import _split_pairs

    def regions(n, area, major, minor, whole):
        return pd.DataFrame({"frame": 0, "u": 0.0, "v": 0.0, "s": np.arange(n) * 20.0,
                             "t": 5.0, "area": area, "diameter_px": np.sqrt(4 * area / np.pi),
                             "major_axis_px": major, "minor_axis_px": minor,
                             "orientation": 0.0, "eccentricity": 0.0, "darkness": 0.9,
                             "dark_area": area * 0.8, "whole": whole})

    singles = regions(5, 12, 4.0, 4.0, True)
    pair = regions(1, 26, 8.0, 4.0, True)             # two touching 12-pixel images
    shares = regions(20, 24, 5.0, 5.0, False)         # a crowd split between its cores
    out = _split_pairs(pd.concat([singles, pair, shares], ignore_index=True), 1.3, 1.25)
    halves = out[out["split_pair"]]
    assert len(halves) == 2 and np.allclose(sorted(halves["s"]), [-1.732, 1.732], atol=0.01)
    assert (~out["whole"] & ~out["split_pair"]).sum() == 20  # every share left as it was


def _own_image_case(n_own, held_area=52.0, second=None):
    """A particle at (10, 10) (the same in every one of 10 views) owning regions of area
    50 in its first ``n_own`` views; held round regions on its prediction in the rest
    and in view 0 (where it has one already)."""
    views = np.column_stack([np.arange(10.0), np.zeros(10)])
    own, held = np.arange(n_own), np.r_[0, np.arange(n_own, 10)]
    view = np.r_[own, held]
    st = np.tile([[10.0, 10.0]], (len(view), 1)) + [[0.2, 0.0]]
    owner = np.r_[np.zeros(n_own, dtype=np.int64), np.full(len(held), _assign._MERGED)]
    area = np.r_[np.full(n_own, 50.0), np.full(len(held), held_area)]
    positions = np.array([[10.0, 10.0, 0.0]] + ([] if second is None else [second]))
    radius = np.full(len(view), 4.0)
    got = _assign._release_unclaimed(_ShiftModel(), positions, views, st, view, owner,
                                     radius, np.ones(len(view), dtype=bool),
                                     tolerance_px=1.0, area=area, max_area_ratio=1.3)
    return got[n_own:], held


def test_a_large_particles_held_images_join_it():
    """In a frame of mixed sizes a large particle's images are held back as merged
    (larger than the frame's typical image). Those on its own prediction, of its own
    regions' size, join it where it has none in their view; merged images (larger than
    its own), images another particle is predicted in, and a particle most of whose
    views it owns (its held images merge with another particle's) keep them held."""
    got, held = _own_image_case(3)
    assert got[0] == _assign._MERGED                # view 0: it has a region there
    assert np.all(got[1:] == 0)
    got, _ = _own_image_case(3, held_area=80.0)     # more than 1.3 times its own
    assert np.all(got == _assign._MERGED)
    got, _ = _own_image_case(3, second=[10.5, 10.0, 0.0])
    assert np.all(got == _assign._MERGED)            # two particles predicted inside
    got, _ = _own_image_case(8)                      # 8 own views, 3 held
    assert np.all(got == _assign._MERGED)


def test_a_solve_reuses_exactly_the_particles_whose_centroids_did_not_change(small_calibrated,
                                                                          clustered_and_solved):
    """:class:`~plenoptrack.locate.perspective.SolveMemo`: after a frame's solve rounds,
    solving again with the memo gives what solving every particle afresh gives (positions
    within 1e-6 mm, the same centroids kept); a particle that lost a centroid is the one
    solved again, and a new frame context solves them all."""
    import dataclasses

    from plenoptrack.locate.settings import PerspectiveLocator

    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=30, seed=4, diameter_mm=0.4)
    raw = _frame(optics, scene.truth, 4)
    locator = PerspectiveLocator()
    ctx, state = clustered_and_solved(raw, calib, locator)
    settings = locator.solve
    assert state.solved is not None and state.n_particles >= 25

    def solve(s):
        return perspective.solve_particles(ctx, s, settings)

    def assert_same(a, b):
        assert np.array_equal(a.owner, b.owner)
        assert np.allclose(a.positions, b.positions, atol=1e-6, rtol=0, equal_nan=True)
        for column in ("n_views", "flags"):
            assert np.array_equal(a.table[column].to_numpy(float), b.table[column].to_numpy(float))

    memo = state.solved
    assert not memo.to_solve(ctx, settings, state.owner, state.n_particles).any()
    assert_same(solve(state), solve(dataclasses.replace(state, solved=None)))

    # one particle loses a centroid: it alone is solved again
    particle = int(np.argmax(state.table["n_views"].to_numpy()))
    lost = np.flatnonzero(state.owner == particle)[0]
    owner = state.owner.copy()
    owner[lost] = -1
    changed = dataclasses.replace(state, owner=owner)
    assert np.flatnonzero(memo.to_solve(ctx, settings, owner, state.n_particles)).tolist() == [particle]
    assert_same(solve(changed), solve(dataclasses.replace(changed, solved=None)))

    # another context, other settings or a new particle: not the memo's
    other_ctx = dataclasses.replace(ctx)
    assert memo.to_solve(other_ctx, settings, state.owner, state.n_particles).all()
    other = dataclasses.replace(settings, reject_k=settings.reject_k + 1)
    assert memo.to_solve(ctx, other, state.owner, state.n_particles).all()
    grown = memo.to_solve(ctx, settings, state.owner, state.n_particles + 1)
    assert np.flatnonzero(grown).tolist() == [state.n_particles]


def test_each_refine_sweep_refits_the_overlapped_particles_again(small_calibrated, monkeypatch):
    """``check.refine_sweeps``: the refit of overlapped particles runs that many passes,
    each fitting the same particles (their neighbours held at their latest fits)."""
    import sys as _sys

    from plenoptrack.locate import refine
    from plenoptrack.locate.settings import PerspectiveLocator

    optics, calib = small_calibrated
    scene = make_scene(calib.camera, n_particles=60, seed=6, diameter_mm=0.4)
    raw = _frame(optics, scene.truth, 6)
    calls = {}
    fit = refine.fit_images

    def counted(*args, **kwargs):
        # called by FrameContext.fit_images, on behalf of refine_particles
        if _sys._getframe(2).f_code.co_name == "refine_particles":
            calls[sweeps] = calls.get(sweeps, 0) + 1
        return fit(*args, **kwargs)

    monkeypatch.setattr(refine, "fit_images", counted)
    for sweeps in (1, 2):
        locator = PerspectiveLocator.from_dict({"check": {"refine_sweeps": sweeps,
                                                          "find_hidden": False}})
        perspective.locate_frame(raw, calib, locator=locator)
    assert calls[1] >= 5
    assert calls[2] >= 1.8 * calls[1]


def test_weak_particles_made_of_the_halves_of_one_region_in_the_same_views_are_pieces():
    """Particles 0 and 1: only split-pair halves, in the same three views (one region
    cut in two there): pieces. Particle 2: halves in other views, alone there. Particle
    3: a whole region among its halves. Particle 4: as 0 and 1 in views of its own, but
    seen strongly (not weak). Particle 5 pairs with 4's views but 4 is not weak."""
    import pandas as pd
    from types import SimpleNamespace

    rows = [  # (owner, view, split half)
        (0, 1, True), (0, 2, True), (0, 3, True),
        (1, 1, True), (1, 2, True), (1, 3, True),
        (2, 1, True), (2, 2, True), (2, 4, True),
        (3, 1, True), (3, 2, True), (3, 3, False),
        (4, 7, True), (4, 8, True),
        (5, 7, True), (5, 8, True),
        (-1, 1, True),
    ]
    owner, view, half = (np.array(c) for c in zip(*rows))
    ctx = SimpleNamespace(detections=pd.DataFrame({"split_pair": half}), view=view)
    weak = np.array([True, True, True, True, False, True])
    pieces = perspective._pieces_of_one_region(ctx, owner, weak)
    assert pieces.tolist() == [True, True, False, False, False, False]
