"""Release hygiene: one version everywhere, and a changelog entry for it."""

from importlib.metadata import metadata, version
from pathlib import Path

import plenoptrack

ROOT = Path(__file__).resolve().parents[1]


def test_installed_version_is_the_package_version():
    assert version("plenoptrack") == plenoptrack.__version__


def test_changelog_has_an_entry_for_this_version():
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert f"\n## {plenoptrack.__version__} " in changelog or \
        f"\n## {plenoptrack.__version__}\n" in changelog


def test_metadata_names_licence_and_python():
    meta = metadata("plenoptrack")
    assert meta["License-Expression"] == "BSD-3-Clause"
    assert meta["Requires-Python"] == ">=3.11"
