"""Shared fixtures: small simulated cameras with fixed seeds; benchmark scripts as modules."""

import contextlib
import importlib.util
import os
import sys
from pathlib import Path

import pytest

# Commands run by the tests compile this processor's kernels as they always did: no seed
# cache and no background warm-up (tests/test_kernel_mode.py covers those).
os.environ.setdefault("PLENOPTRACK_KERNELS", "host")

from plenoptrack import preset


@pytest.fixture(scope="module")
def small_optics():
    """True optics of the 'small' hexagonal preset, seed 0."""
    from plenoptrack.simulate import make_optics

    return make_optics(preset("small"), seed=0)


@pytest.fixture(scope="module")
def small_rect_optics():
    """True optics of the 'small-rect' rectangular preset, seed 1."""
    from plenoptrack.simulate import make_optics

    return make_optics(preset("small-rect"), seed=1)


BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@contextlib.contextmanager
def _benchmark_module(name: str):
    """``benchmarks/NAME.py`` imported as a module (the folder on ``sys.path`` for the
    scripts it imports, e.g. ``accuracy_matrix``); everything it added to ``sys.modules``
    and ``sys.path`` is removed afterwards."""
    before = set(sys.modules)
    sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module          # dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        for added in {name, "accuracy_matrix"} - before:
            sys.modules.pop(added, None)
        sys.path.remove(str(BENCHMARKS))


@pytest.fixture(scope="session")
def benchmark_module():
    """:func:`_benchmark_module`, for module fixtures that import a benchmark script
    (``with benchmark_module("accuracy_matrix") as matrix: ...``)."""
    return _benchmark_module
