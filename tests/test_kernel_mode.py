"""The shipped seed cache of generic kernels and the choice of kernel mode (plenoptrack._kernel_mode)."""

import json
import os
import subprocess
import sys

import pytest

from plenoptrack import _kernel_mode as km


@pytest.mark.parametrize("setting, numba_env_set, seeds_ok, host_warm, writable, expected", [
    ("auto", False, True, False, True, "generic"),    # a fresh installation
    ("auto", False, True, True, True, "host"),        # after the warm-up
    ("auto", True, True, False, True, "host"),        # the user configured numba
    ("auto", False, False, False, True, "host"),      # another numba or Python
    ("auto", False, True, False, False, "host"),      # read-only installation
    ("generic", False, True, True, True, "generic"),
    ("generic", False, False, False, True, "host"),   # nothing to load
    ("host", False, True, False, True, "host"),
])
def test_choose_mode(setting, numba_env_set, seeds_ok, host_warm, writable, expected):
    assert km.choose_mode(setting, numba_env_set=numba_env_set, seeds_ok=seeds_ok,
                          host_warm=host_warm, writable=writable) == expected


def test_choose_mode_refuses_unknown_setting():
    with pytest.raises(ValueError, match="PLENOPTRACK_KERNELS"):
        km.choose_mode("fast", numba_env_set=False, seeds_ok=True, host_warm=False, writable=True)


def test_seed_cache_matches_the_sources():
    """Every source file the seed cache was compiled from is unchanged (else numba would
    discard its entries and the first run would compile): rebuild with
    ``python -m plenoptrack._kernel_mode build`` after editing a kernel module."""
    assert km.seed_problems() == []
    manifest = km.read_manifest()
    assert manifest["cpu"] == "generic"
    assert {"locate/triangulate.py", "locate/segment.py", "lightfield/decode.py",
            "simulate/_kernels.py"} <= set(manifest["sources"])


def test_seed_problems_names_an_edited_source(tmp_path):
    manifest = km.read_manifest()
    rel = next(iter(manifest["sources"]))
    package = tmp_path / "pkg"
    (package / rel).parent.mkdir(parents=True)
    for other in manifest["sources"]:
        (package / other).parent.mkdir(parents=True, exist_ok=True)
        (package / other).write_bytes((km.PACKAGE_DIR / other).read_bytes())
    (package / rel).write_bytes((km.PACKAGE_DIR / rel).read_bytes() + b"\n# edited\n")
    assert km.seed_problems(package_dir=package) == [f"{rel}: changed since the seed cache was built"]


def test_warm_up_marker_and_lock(tmp_path, monkeypatch):
    monkeypatch.setattr(km, "_cache_root", lambda: tmp_path)
    manifest = km.read_manifest()
    marker = tmp_path / "host-kernels.json"
    assert not km._host_warm(manifest, marker)
    marker.write_text(json.dumps({"seeds": "another build"}))
    assert not km._host_warm(manifest, marker)
    marker.write_text(json.dumps({"seeds": km._manifest_key(manifest)}))
    assert km._host_warm(manifest, marker)
    # a warm-up already running (fresh lock) is not started twice
    (tmp_path / "host-kernels.lock").write_text("1")
    assert km.start_warm_up({}) is None


_DEMO_WITH_SEEDS = """
import importlib, json, pkgutil, sys
from pathlib import Path
from plenoptrack import _kernel_mode
mode = _kernel_mode.prepare(warm=False, generic_dir=Path(sys.argv[1]))
from numba.core.registry import CPUDispatcher
import plenoptrack
from plenoptrack.demo import run_demo
run_demo(Path(sys.argv[2]))
hits = misses = 0
compiled = []
for info in pkgutil.walk_packages(plenoptrack.__path__, "plenoptrack."):
    mod = sys.modules.get(info.name)
    if mod is None:
        continue
    for name, obj in vars(mod).items():
        if isinstance(obj, CPUDispatcher) and obj.__module__ == info.name:
            hits += sum(obj.stats.cache_hits.values())
            if sum(obj.stats.cache_misses.values()):
                compiled.append(info.name + "." + name)
print(json.dumps({"mode": mode, "hits": hits, "compiled": compiled}))
"""


def test_first_demo_with_the_seed_cache_compiles_nothing(tmp_path):
    """In generic mode the demo loads every kernel from the seed cache: none compiled."""
    if not km.seeds_usable(km.read_manifest()):
        pytest.skip(f"the seed cache was built for {km.read_manifest()}: another numba, "
                    "Python or platform here, where plenoptrack compiles as usual")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env[km.ENV] = "generic"
    done = subprocess.run([sys.executable, "-c", _DEMO_WITH_SEEDS, str(tmp_path / "cache"),
                           str(tmp_path / "demo")], env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["mode"] == "generic"
    assert report["compiled"] == []
    assert report["hits"] > 0


def test_unknown_kernel_mode_is_one_line(tmp_path):
    env = dict(os.environ, PLENOPTRACK_KERNELS="fastest")
    done = subprocess.run([sys.executable, "-m", "plenoptrack", "demo", "--out",
                           str(tmp_path / "demo")], env=env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "PLENOPTRACK_KERNELS" in lines[0] and "auto" in lines[0]
    assert not (tmp_path / "demo").exists()


def test_seeding_replaces_an_older_version_once(tmp_path):
    """A new seed cache replaces the files of an older one (an upgrade); once seeded, the
    files numba has added to since are left alone."""
    manifest = km.read_manifest()
    km.seed_generic_cache(tmp_path)
    copied = sorted(p for p in tmp_path.rglob("*") if p.suffix in (".nbi", ".nbc"))
    assert len(copied) == len(manifest["files"])
    index = next(p for p in copied if p.suffix == ".nbi")
    seed = km.SEED_DIR / next(f for f in manifest["files"] if f.endswith("/" + index.name))
    index.write_bytes(b"added to by numba since")
    km.seed_generic_cache(tmp_path)
    assert index.read_bytes() == b"added to by numba since"
    for done in tmp_path.glob("seeded-*"):  # as an older version left it
        done.unlink()
    km.seed_generic_cache(tmp_path)
    assert index.read_bytes() == seed.read_bytes()
