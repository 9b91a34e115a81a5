"""sphinx-gallery scraper for the matplotlib ``Figure`` objects of :mod:`plenoptrack.plots`.

The plotting functions build ``matplotlib.figure.Figure`` objects directly, without
pyplot, so sphinx-gallery's own matplotlib scraper (which asks pyplot for its open
figures) sees none of them. This scraper looks through the example's global names after
each code block and saves every ``Figure`` it has not saved before, in the order the names
were first bound. Figures that pyplot manages are left to the matplotlib scraper.
"""

from __future__ import annotations

from matplotlib.figure import Figure

_seen: dict[str, set[int]] = {}


def new_figures(namespace: dict, seen: set[int]) -> list[Figure]:
    """Figures bound to names in ``namespace`` (directly, or inside a list, tuple or dict)
    whose ``id`` is not in ``seen``, in the order of the names; adds their ids to ``seen``.
    Figures with a pyplot canvas manager are skipped."""
    found = []
    for value in list(namespace.values()):
        if isinstance(value, dict):
            candidates = list(value.values())
        elif isinstance(value, (list, tuple)):
            candidates = list(value)
        else:
            candidates = [value]
        for fig in candidates:
            if (isinstance(fig, Figure) and id(fig) not in seen
                    and getattr(fig.canvas, "manager", None) is None):
                seen.add(id(fig))
                found.append(fig)
    return found


def scrape_figures(block, block_vars, gallery_conf, **kwargs):
    """Save the new figures of one code block and return the reST that shows them."""
    from sphinx_gallery.scrapers import figure_rst

    seen = _seen.setdefault(str(block_vars.get("src_file")), set())
    paths = []
    for fig, path in zip(new_figures(block_vars["example_globals"], seen),
                         block_vars["image_path_iterator"]):
        fig.savefig(path, dpi=90)
        paths.append(path)
    return figure_rst(paths, gallery_conf["src_dir"])


def reset(gallery_conf, fname, when):
    """Forget the figures of the previous example."""
    _seen.clear()
