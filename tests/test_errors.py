"""Library validation errors are the project's own (and still ValueErrors)."""

import numpy as np
import pandas as pd
import pytest

from plenoptrack.errors import PlenoptrackError, SettingsError, UsageError
from plenoptrack.evaluate import evaluate_particles
from plenoptrack.locate.settings import ClusterSettings, SegmentSettings
from plenoptrack.locate.segment import segment_view

ONE = pd.DataFrame({"frame": [0], "x": [0.0], "y": [0.0], "z": [0.0]})


@pytest.mark.parametrize("call, match", [
    (lambda: SegmentSettings(window=0), "window must be an integer of at least 3"),
    (lambda: SegmentSettings(contrast=-1.0), "contrast must be between 0 and 1"),
    (lambda: ClusterSettings(n_planes=0), "n_planes must be an integer of at least 2"),
    (lambda: evaluate_particles(ONE, ONE, tolerance_mm=-1.0), "tolerance_mm must be positive"),
    (lambda: segment_view(np.ones((20, 20), np.float32), window=1), "window"),
])
def test_settings_errors_are_project_errors(call, match):
    with pytest.raises(SettingsError, match=match) as info:
        call()
    assert isinstance(info.value, PlenoptrackError)
    assert isinstance(info.value, UsageError)
    assert isinstance(info.value, ValueError)  # code catching ValueError keeps working
