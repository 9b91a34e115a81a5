"""Every gallery example runs headless and leaves at least one figure behind."""

import runpy
from pathlib import Path

import pytest
from matplotlib.figure import Figure

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").rglob("plot_*.py"))


def test_examples_found():
    assert len(EXAMPLES) >= 3


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_example_runs(path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg")
    namespace = runpy.run_path(str(path), run_name="__main__")
    figures = [v for v in namespace.values() if isinstance(v, Figure)]
    assert figures, f"{path.name} produced no matplotlib Figure"
    assert isinstance(namespace.get("fig"), Figure), f"{path.name} should end with `fig = ...`"
    for fig in figures:
        assert fig.axes
