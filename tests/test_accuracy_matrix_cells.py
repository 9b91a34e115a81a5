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
