"""Sphinx configuration of the plenoptrack documentation.

Build offline with warnings as errors, from the repository root::

    python -m sphinx -W --keep-going -b html docs docs/_build/html
"""

import os
import sys
from pathlib import Path

import plenoptrack

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "sphinxext"))
os.environ.setdefault("MPLBACKEND", "Agg")

project = "plenoptrack"
author = "the plenoptrack developers"
copyright = "the plenoptrack developers"
release = plenoptrack.__version__
version = ".".join(release.split(".")[:2])

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.viewcode",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "auto_examples/*.ipynb", "auto_examples/*.py",
                    "auto_examples/*/*.ipynb", "auto_examples/*/*.py",
                    "auto_examples/*.zip", "auto_examples/*/*.zip", "**.codeobj.json"]
templates_path = ["_templates"]

myst_enable_extensions = ["colon_fence"]
myst_heading_anchors = 3

autosummary_generate = True
autosummary_imported_members = False
autodoc_default_options = {}
autodoc_typehints = "none"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

sphinx_gallery_conf = {
    "examples_dirs": ["../examples"],
    "gallery_dirs": ["auto_examples"],
    "filename_pattern": r"/plot_",
    "image_scrapers": ("matplotlib", "plenoptrack_scraper.scrape_figures"),
    "reset_modules": ("matplotlib", "plenoptrack_scraper.reset"),
    "doc_module": ("plenoptrack",),
    "backreferences_dir": "gen_modules/backreferences",
    "download_all_examples": False,
    "remove_config_comments": True,
    "show_memory": False,
    "min_reported_time": 1.0,
    "abort_on_example_error": True,
}

html_theme = "furo"
html_title = f"plenoptrack {release}"
html_static_path = []
html_show_sourcelink = False


def _join_wrapped_terms(app, what, name, obj, options, lines):
    """Join a definition-list term that wraps onto a second unindented line (as in some
    module docstrings of plenoptrack.simulate), which docutils would otherwise end the
    list at."""
    if what != "module":
        return
    i = 0
    while i + 2 < len(lines):
        a, b, c = lines[i], lines[i + 1], lines[i + 2]
        if (a.strip() and b.strip() and c.strip() and not a[0].isspace()
                and not b[0].isspace() and c[0].isspace()
                and a.count("(") > a.count(")")):
            lines[i:i + 2] = [a + " " + b]
        i += 1


def setup(app):
    app.connect("autodoc-process-docstring", _join_wrapped_terms)
