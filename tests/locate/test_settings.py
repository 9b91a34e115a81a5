"""Locator settings: sections, validation, TOML round trip."""

import inspect
import math

import pytest

from plenoptrack.errors import SettingsError
from plenoptrack.locate import (ClusterSettings, PerspectiveLocator, cluster_detections,
                                read_settings, settings_toml)


def test_cluster_section_defaults_are_those_of_cluster_detections():
    params = inspect.signature(cluster_detections).parameters
    section = ClusterSettings()
    shared = [name for name in vars(section) if name in params]
    assert len(shared) == len(vars(section)) - 2      # all but n_planes, depth_range_mm
    for name in shared:
        assert getattr(section, name) == params[name].default, name


@pytest.mark.parametrize("changes", [
    {},
    {"segment": {"window": 45, "area_range": [3.0, 500.0], "core_contrast": None}},
    {"segment": {"max_view_ratio": None}, "cluster": {"depth_range_mm": (-4.0, 6.0)}},
    {"grow": {"merge_distance_px": 2.5, "passes": 3}, "solve": {"solver": "scipy"}},
    {"check": {"max_explained": 0.6}, "cluster": {"density_sweep": False, "seed": 7}},
    {"check": {"refine_sweeps": 2}},
])
def test_toml_round_trip(tmp_path, changes):
    locator = PerspectiveLocator.from_dict(changes)
    path = tmp_path / "locate.toml"
    path.write_text(settings_toml(locator))
    assert read_settings(path) == locator
    assert read_settings(path).digest() == locator.digest()


def test_from_dict_changes_only_what_it_names():
    base = PerspectiveLocator()
    loc = base.updated({"segment": {"contrast": 0.2}})
    assert loc.segment.contrast == 0.2 and loc.segment.window == base.segment.window
    assert loc.cluster == base.cluster and loc.digest() != base.digest()
    assert loc.segment.area_range == (2.0, math.inf)


@pytest.mark.parametrize("data, match", [
    ({"segmnt": {}}, r"unknown section\(s\) \['segmnt'\]"),
    ({"segment": {"windw": 3}}, r"unknown setting\(s\) \['windw'\] in \[segment\]"),
    ({"segment": 5}, r"\[segment\] must be a table"),
    ({"segment": {"window": 31.5}}, "window must be an integer"),
    ({"segment": {"area_range": [5.0]}}, "area_range must be a pair"),
    ({"cluster": {"min_fraction": 1.5}}, r"min_fraction must be in \[0, 1\)"),
    ({"solve": {"solver": "newton"}}, "solver must be 'lm' or 'scipy'"),
    ({"grow": {"merge_distance_px": -1.0}}, "merge_distance_px must be None or positive"),
    ({"check": {"max_residual_ratio": 0.5}}, "max_residual_ratio must be above 1"),
    ({"check": {"refine_sweeps": 0}}, "refine_sweeps must be a whole number of at least 1"),
    ({"check": {"refine_sweeps": 1.5}}, "refine_sweeps must be a whole number of at least 1"),
    ({"check": {"merge_pieces": "yes"}}, "merge_pieces must be true or false; got 'yes'"),
    ({"segment": {"split_pairs": 1}}, "split_pairs must be true or false; got 1"),
    ({"solve": {"opacity": "false"}}, "opacity must be true or false"),
    ({"cluster": {"density_sweep": None}}, "density_sweep must be true or false"),
])
def test_bad_settings_name_the_setting(data, match):
    with pytest.raises(SettingsError, match=match):
        PerspectiveLocator.from_dict(data, source="my.toml")


def test_sections_must_have_their_type():
    with pytest.raises(SettingsError, match="segment must be a SegmentSettings"):
        PerspectiveLocator(segment={"window": 3})


def test_missing_settings_file(tmp_path):
    with pytest.raises(Exception, match="settings file not found"):
        read_settings(tmp_path / "nope.toml")
