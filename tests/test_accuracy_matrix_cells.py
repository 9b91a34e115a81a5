"""The acceptance envelope's cells (``benchmarks/accuracy_matrix.py``): what "sparse" means."""

import pytest


@pytest.fixture(scope="module")
def matrix(benchmark_module):
    with benchmark_module("accuracy_matrix") as module:
        yield module


def test_sparse_cells_are_sparse_where_their_particles_are(matrix):
    """Every sparse cell holds ACCEPTANCE_SPARSE particles per microlens of the field its
    volume covers, whatever the particles' size; a density cell counts the whole array."""
    cells, skipped = matrix.build_cells(quick=False, hall=False, shapes=None, acceptance=True)
    assert not skipped
    sparse = [c for c in cells if c.axis == "sparse"]
    assert {str(c.size) for c in sparse} >= {"0.2", "1.0", "2.0", "(0.2, 2.0)"}
    for cell in sparse:
        lenses = matrix.n_microlenses(matrix._camera(cell)) * matrix.footprint_fraction(cell)
        local = matrix.n_particles(cell) / lenses
        # rounding to whole particles: within half a particle of the density
        assert abs(local - matrix.ACCEPTANCE_SPARSE) <= 0.5 / lenses + 1e-12, cell.name
        assert local <= matrix.ACCEPTANCE_SPARSE_MAX, cell.name
    large = next(c for c in sparse if c.size == (0.2, 2.0))
    assert matrix.footprint_fraction(large) < 0.2           # the 2 mm volume is narrow
    for cell in (c for c in cells if c.axis == "density"):
        whole = matrix.n_microlenses(matrix._camera(cell))
        assert matrix.n_particles(cell) == round(cell.density * whole)


def test_more_frames_per_seed_keep_the_earlier_frames(matrix):
    """``frames_per_seed``: at least ``min_frames`` frames and ``min_particles``
    particles per cell and seed; and a cell's scene of more frames starts with the same
    frames (the acceptance's extra frames of crowded cells add frames, they do not
    redraw the first)."""
    cells, _ = matrix.build_cells(quick=False, hall=False, shapes=None, acceptance=True)
    crowded = next(c for c in cells if c.axis == "density" and c.density == 0.05)
    n = matrix.n_particles(crowded)
    assert n > 80                                                  # one frame holds 80
    assert matrix.frames_per_seed(crowded, 80) == 1
    assert matrix.frames_per_seed(crowded, 80, 3) == 3
    assert matrix.frames_per_seed(crowded, 3 * n + 1, 3) == 4
    sparse = next(c for c in cells if c.axis == "sparse")
    assert matrix.frames_per_seed(sparse, 80, 3) * matrix.n_particles(sparse) >= 80
    one = matrix.make_cell_scene(crowded, 900, 1).truth
    three = matrix.make_cell_scene(crowded, 900, 3).truth
    assert sorted(three["frame"].unique()) == [0, 1, 2]
    first = three[three["frame"] == 0].reset_index(drop=True)
    assert first[["x", "y", "z", "diameter"]].equals(one[["x", "y", "z", "diameter"]])
    later = three[three["frame"] == 1][["x", "y", "z"]].to_numpy()
    assert not (later[:, None, :] == first[["x", "y", "z"]].to_numpy()[None]).all(-1).any()


def test_a_log_axis_labels_only_two_and_five_between_its_decades(matrix):
    """The depth-spread panels span one or two decades on a short axis: every minor tick
    labelled ran the labels into each other."""
    label = matrix._two_and_five
    assert [label(v) for v in (0.02, 0.05, 0.2, 5.0, 500.0)] == ["0.02", "0.05", "0.2", "5",
                                                                 "5e+02"]
    assert [label(v) for v in (0.03, 0.04, 0.06, 0.07, 0.08, 0.09, 0.3, 7.0)] == [""] * 8
    assert label(0.0) == "" and label(-0.2) == ""


def test_recall_of_the_particles_some_view_shows(matrix):
    """``recall_seen`` leaves out the true particles hidden in every view, matched or not;
    ``recall`` counts them all."""
    import pandas as pd

    pairs = pd.DataFrame({"dx": [0.0] * 3, "dy": [0.0] * 3, "dz": [0.01, -0.01, 0.02],
                          "sigma_x": [1.0] * 3, "sigma_y": [1.0] * 3, "sigma_z": [1.0] * 3,
                          "diameter": [1.0] * 3, "true_diameter": [1.0] * 3,
                          "hidden": [False, False, True]})
    m = matrix.metrics(pairs, n_true=10, n_measured=4, n_hidden=3)
    assert m["recall"] == pytest.approx(0.3)
    assert m["hidden"] == pytest.approx(0.3)
    assert m["recall_seen"] == pytest.approx(2 / 7)
    assert matrix.metrics(pairs.drop(columns="hidden"), 10, 4)["recall_seen"] == \
        pytest.approx(0.3)
