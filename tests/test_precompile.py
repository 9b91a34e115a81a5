"""The kernel table of plenoptrack._precompile against what calibrating and locating compile.

Each step runs in a fresh interpreter (so that no other test's calls add signatures), as the
``calibrate`` and ``locate`` commands do, and reports every signature that any dispatcher
of ``plenoptrack.lightfield`` and ``plenoptrack.locate`` holds afterwards.
"""

import json
import os
import subprocess
import sys

import pytest

from plenoptrack import _precompile
from plenoptrack.simulate import simulate_dataset

_REPORT = """
import importlib, json, pkgutil, sys
from numba.core.registry import CPUDispatcher
import plenoptrack.lightfield, plenoptrack.locate
from plenoptrack.calibrate import calibrate
from plenoptrack.calibration import load_calibration, save_calibration
from plenoptrack.camera import load_camera
from plenoptrack.io import read_raw
from plenoptrack.locate.perspective import locate_frame

step, sim, calib_path = sys.argv[1:]
if step == "calibrate":
    calib, _ = calibrate(f"{sim}/white.tif", f"{sim}/dotcards", load_camera(f"{sim}/camera.toml"))
    save_calibration(calib, calib_path)
else:
    calib = load_calibration(calib_path)
    locate_frame(read_raw(f"{sim}/raw/frame_0000.tif"), calib, white=read_raw(f"{sim}/white.tif"))
seen = {}
for pkg in (plenoptrack.lightfield, plenoptrack.locate):
    for info in pkgutil.iter_modules(pkg.__path__):
        mod = importlib.import_module(pkg.__name__ + "." + info.name)
        for name, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.__module__ == mod.__name__ and obj.signatures:
                seen[mod.__name__ + "." + name] = sorted(str(s) for s in obj.signatures)
print(json.dumps(seen))
"""


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    """Signatures compiled by the calibrate step and by the locate step, in that order."""
    tmp = tmp_path_factory.mktemp("precompile")
    sim = simulate_dataset("small", tmp / "sim", seed=11, n_particles=12, realism="ideal")
    out = {}
    for step in ("calibrate", "locate"):
        done = subprocess.run([sys.executable, "-c", _REPORT, step, str(sim.white_path.parent),
                               str(tmp / "calib.json")], capture_output=True, text=True,
                              timeout=900)
        assert done.returncode == 0, done.stderr[-2000:]
        out[step] = json.loads(done.stdout.strip().splitlines()[-1])
    return out


def _table(step):
    return {f"{module}.{func}": [str(tuple(sig))]
            for module, func, sig in (_precompile.KERNELS[k] for k in _precompile.STEPS[step])}


@pytest.mark.parametrize("step", ["calibrate", "locate"])
def test_table_is_what_the_step_compiles(compiled, step):
    """Exactly the listed kernels, each with exactly the listed signature: a missing or
    different entry would leave a kernel to compile on the first run. Helpers compiled
    into their callers hold signatures only when the callers were compiled in that
    process (not when loaded from the cache), so they are left out."""
    seen = {k: v for k, v in compiled[step].items() if k not in _precompile.HELPERS}
    assert seen == _table(step)


def test_precompiled_kernels_are_found_by_later_processes(tmp_path):
    """Kernels compiled by precompile() land in the cache a later process reads (its
    index files exist, so missing() is empty)."""
    code = ("import sys; from plenoptrack import _precompile as p; "
            "names = ['first_untaken', 'absorb']; "
            "assert p.missing(names) == names, p.missing(names); p.precompile(names)")
    check = ("from plenoptrack import _precompile as p; "
             "print(p.missing(['first_untaken', 'absorb', 'lm']))")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=600)
    done = subprocess.run([sys.executable, "-c", check], env=env, capture_output=True, text=True,
                          check=True, timeout=600)
    assert done.stdout.strip() == "['lm']"


def test_unknown_step_is_refused():
    with pytest.raises(ValueError, match="step must be one of"):
        _precompile.kernels_for(["calibrate", "views"])


def test_switched_off_by_environment(monkeypatch):
    monkeypatch.setenv("PLENOPTRACK_PRECOMPILE", "0")
    assert _precompile.start_background(["locate"]) is None
