"""The documentation gallery's scraper finds the Figure objects an example binds."""

import importlib.util
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

_PATH = Path(__file__).resolve().parents[1] / "docs" / "sphinxext" / "plenoptrack_scraper.py"
_spec = importlib.util.spec_from_file_location("plenoptrack_scraper", _PATH)
scraper = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(scraper)


def test_new_figures_in_binding_order_once_each():
    a, b, c = Figure(), Figure(), Figure()
    seen = set()
    namespace = {"fig_b": b, "n": 3, "figs": [a, "x"], "by_name": {"c": c}}
    assert scraper.new_figures(namespace, seen) == [b, a, c]
    namespace["again"] = b
    d = Figure()
    namespace["fig_d"] = d
    assert scraper.new_figures(namespace, seen) == [d]
    assert scraper.new_figures(namespace, seen) == []


def test_pyplot_figures_are_left_to_the_matplotlib_scraper():
    managed = plt.figure()
    try:
        plain = Figure()
        assert scraper.new_figures({"m": managed, "p": plain}, set()) == [plain]
    finally:
        plt.close(managed)
