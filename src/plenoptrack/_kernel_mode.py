"""Which machine code the numba kernels run: this processor's, or the shipped generic build.

plenoptrack's kernels are compiled by numba the first time they run and cached (see
:mod:`plenoptrack._precompile`). numba keys each cache entry on the processor model and
features of the machine that compiled it, so a cache compiled on one machine is of no use
on another, and a fresh installation would spend most of its first ``plenoptrack demo``
compiling. The package therefore ships a *seed cache* (``_seed_cache/``): every kernel the
demo and the user guide's other commands run, compiled for the generic x86-64 processor
(``NUMBA_CPU_NAME=generic``, no processor-specific instructions) by :func:`build_seeds`,
for one numba release and one Python minor version (both recorded in its
``manifest.json``).

A command-line run chooses a *kernel mode* before numba is imported (:func:`prepare`):

``host``
    Kernels compiled for this processor, cached beside the installed modules (numba's own
    default). The fastest code; the first run of each kernel compiles it.
``generic``
    The shipped build: ``NUMBA_CPU_NAME=generic`` and ``NUMBA_CACHE_DIR`` pointing at a copy of
    the seed cache in the package's ``__pycache__/numba-generic``. Nothing the demo runs is
    compiled, at the cost of simulator frames that take 25-40 % longer.

With ``PLENOPTRACK_KERNELS=auto`` (the default) a run uses ``generic`` until the host
kernels have been compiled once, and the first such run starts a *warm-up*: a detached
process that waits for that run to end and then, at low priority (nice 10), runs the demo
in host mode in a temporary folder, which compiles and caches this processor's kernels, and
writes a marker (``__pycache__/host-kernels.json``). Later runs find the marker and use ``host``.
``PLENOPTRACK_KERNELS=host`` or ``generic`` forces a mode (no warm-up). The seed cache is
not used (``host``) when the user has set ``NUMBA_CPU_NAME`` or ``NUMBA_CACHE_DIR``, when
the installed numba, Python or platform differs from the manifest's, or when the package
folder is not writable.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

__all__ = ["MODES", "ENV", "read_setting", "choose_mode", "prepare", "seeds_usable",
           "seed_problems", "seed_generic_cache", "start_warm_up", "warm_up", "build_seeds"]

ENV = "PLENOPTRACK_KERNELS"
"""Environment variable that sets the kernel mode: ``auto`` (default), ``host`` or ``generic``."""

MODES = ("auto", "host", "generic")

# os.path.abspath, not Path.resolve: numba names cache folders after the unresolved path
PACKAGE_DIR = Path(os.path.abspath(__file__)).parent
SEED_DIR = PACKAGE_DIR / "_seed_cache"
_MANIFEST = "manifest.json"
_LOCK_STALE_S = 15 * 60  # a warm-up lock older than this is from a process that died


def _cache_root() -> Path:
    return PACKAGE_DIR / "__pycache__"


def _marker_path() -> Path:
    return _cache_root() / "host-kernels.json"


def _lock_path() -> Path:
    return _cache_root() / "host-kernels.lock"


def read_setting(environ) -> str:
    """The ``PLENOPTRACK_KERNELS`` setting of ``environ``, normalised (default ``auto``);
    may be outside :data:`MODES`, which the caller reports."""
    return environ.get(ENV, "auto").strip().lower() or "auto"


def _python_tag() -> str:
    return f"py{sys.version_info.major}{sys.version_info.minor}"


def _numba_version() -> str | None:
    try:
        return metadata.version("numba")
    except metadata.PackageNotFoundError:  # pragma: no cover - numba is a dependency
        return None


def _file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_manifest(seed_dir: Path = SEED_DIR) -> dict | None:
    """The seed cache's manifest, or None when the package ships no (readable) seed cache."""
    try:
        return json.loads((seed_dir / _MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def _manifest_key(manifest: dict) -> str:
    return hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()[:16]


def seeds_usable(manifest: dict | None) -> bool:
    """Whether this interpreter can load the seed cache of ``manifest``.

    numba reads an index only with the numba version that wrote it, and the cache files are
    named by Python minor version and hold machine code for one architecture.
    """
    return (manifest is not None and manifest.get("numba") == _numba_version()
            and manifest.get("python") == _python_tag()
            and manifest.get("machine") == platform.machine()
            and manifest.get("platform") == sys.platform)


def seed_problems(seed_dir: Path = SEED_DIR, package_dir: Path = PACKAGE_DIR) -> list[str]:
    """Why the seed cache no longer matches the package's sources (empty when it does).

    numba discards an index whose source file's content hash differs from the one it was
    compiled from; a source edit therefore needs :func:`build_seeds` again.
    """
    manifest = read_manifest(seed_dir)
    if manifest is None:
        return [f"{seed_dir / _MANIFEST}: missing or unreadable"]
    problems = []
    for rel, digest in sorted(manifest.get("sources", {}).items()):
        source = package_dir / rel
        if not source.is_file():
            problems.append(f"{rel}: listed in the manifest but not in the package")
        elif _file_sha256(source) != digest:
            problems.append(f"{rel}: changed since the seed cache was built")
    for rel in manifest.get("files", []):
        if not (seed_dir / rel).is_file():
            problems.append(f"{rel}: listed in the manifest but missing from {seed_dir.name}")
    return problems


def choose_mode(setting: str, *, numba_env_set: bool, seeds_ok: bool, host_warm: bool,
                writable: bool) -> str:
    """The kernel mode of a run (``"host"`` or ``"generic"``), from what it knows.

    Parameters
    ----------
    setting : {"auto", "host", "generic"}
        The ``PLENOPTRACK_KERNELS`` setting.
    numba_env_set : bool
        Whether ``NUMBA_CPU_NAME`` or ``NUMBA_CACHE_DIR`` is set already (then numba is left
        as the user configured it).
    seeds_ok : bool
        Whether the shipped seed cache can be loaded (:func:`seeds_usable`).
    host_warm : bool
        Whether the host kernels have been compiled once (the warm-up's marker).
    writable : bool
        Whether the package's ``__pycache__`` can be written (the seed cache is copied there).
    """
    if setting not in MODES:
        raise ValueError(f"{ENV} must be one of {', '.join(MODES)}; got {setting!r}")
    if setting == "host" or numba_env_set or not seeds_ok or not writable:
        return "host"
    if setting == "generic":
        return "generic"
    return "host" if host_warm else "generic"


def _cache_subdir(source_dir: Path) -> str:
    """numba's folder name, inside ``NUMBA_CACHE_DIR``, for the modules of ``source_dir``."""
    absolute = os.path.abspath(source_dir)
    return "_".join([os.path.basename(absolute), hashlib.sha1(absolute.encode()).hexdigest()])


def seed_generic_cache(cache_dir: Path, seed_dir: Path = SEED_DIR,
                       package_dir: Path = PACKAGE_DIR) -> None:
    """Copy the seed cache into ``cache_dir`` laid out as numba's ``NUMBA_CACHE_DIR`` expects.

    Does nothing when ``cache_dir`` holds this seed cache already (numba may have added
    entries to its indexes since); otherwise every file is replaced, so that an upgrade
    never keeps an index of the previous version's sources. Each file is written under a
    temporary name and renamed, so that a concurrent run never reads half a file.
    """
    manifest = read_manifest(seed_dir)
    if manifest is None:
        return
    done = cache_dir / f"seeded-{_manifest_key(manifest)}"
    if done.exists():
        return
    for rel in manifest["files"]:
        rel_path = Path(rel)
        target = cache_dir / _cache_subdir(package_dir / rel_path.parent) / rel_path.name
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f"{target.name}.tmp.{os.getpid()}")
        shutil.copyfile(seed_dir / rel_path, tmp)
        os.replace(tmp, target)
    done.touch()


def _host_warm(manifest: dict | None, marker: Path) -> bool:
    try:
        recorded = json.loads(marker.read_text())
    except (OSError, ValueError):
        return False
    return manifest is not None and recorded.get("seeds") == _manifest_key(manifest)


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
        return True
    except OSError:
        return False


def prepare(environ=None, *, warm: bool = True, generic_dir: Path | None = None) -> str:
    """Choose the kernel mode of this process and set numba's environment for it.

    Must run before numba is imported (numba reads ``NUMBA_CPU_NAME`` and
    ``NUMBA_CACHE_DIR`` once, at import); if numba is imported already the mode is
    ``host`` and nothing changes.

    Parameters
    ----------
    environ : mapping, optional
        The environment to read and update (default ``os.environ``; child processes inherit
        it, so that worker processes run the same kernels).
    warm : bool
        Start the host warm-up (:func:`start_warm_up`) when the mode is ``generic`` under
        ``auto``.
    generic_dir : Path, optional
        Where the seed cache is copied (default the package's ``__pycache__/numba-generic``).

    Returns
    -------
    str
        ``"host"`` or ``"generic"``.
    """
    environ = os.environ if environ is None else environ
    if "numba" in sys.modules:
        return "host"
    setting = read_setting(environ)
    if setting not in MODES:
        setting = "auto"  # the CLI reports a bad value as a usage error itself
    manifest = read_manifest()
    generic_dir = _cache_root() / "numba-generic" if generic_dir is None else generic_dir
    known = dict(
        numba_env_set=bool(environ.get("NUMBA_CPU_NAME") or environ.get("NUMBA_CACHE_DIR")),
        seeds_ok=seeds_usable(manifest),
        host_warm=_host_warm(manifest, _marker_path()))
    mode = choose_mode(setting, **known, writable=True)
    if mode == "generic":  # only now touch the package folder
        mode = choose_mode(setting, **known, writable=_writable(generic_dir))
    if mode == "generic":
        try:
            seed_generic_cache(generic_dir)
        except OSError:
            return "host"
        environ["NUMBA_CPU_NAME"] = "generic"
        environ["NUMBA_CACHE_DIR"] = str(generic_dir)
        if warm and setting == "auto":
            start_warm_up(environ)
    return mode


def start_warm_up(environ=None) -> subprocess.Popen | None:
    """Start the detached host warm-up (:func:`warm_up`) unless one is running already.

    Returns
    -------
    subprocess.Popen or None
        The warm-up process, or None when another one holds the lock.
    """
    environ = os.environ if environ is None else environ
    lock = _lock_path()
    try:
        if lock.exists() and time.time() - lock.stat().st_mtime < _LOCK_STALE_S:
            return None
        lock.unlink(missing_ok=True)
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except OSError:
        return None
    os.write(fd, str(os.getpid()).encode())
    os.close(fd)
    env = {k: v for k, v in environ.items() if k not in ("NUMBA_CPU_NAME", "NUMBA_CACHE_DIR")}
    env[ENV] = "host"
    env["PLENOPTRACK_PRECOMPILE"] = "0"
    try:
        return subprocess.Popen([sys.executable, "-m", "plenoptrack._kernel_mode", "warm",
                                 str(os.getpid())],
                                env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
    except OSError:
        lock.unlink(missing_ok=True)
        return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, but belongs to someone else
        return True
    return True


def warm_up(after_pid: int | None = None) -> None:
    """Compile and cache this processor's kernels by running the demo, then mark them warm.

    Runs in the process :func:`start_warm_up` starts (host mode, low priority). It first
    waits for the process ``after_pid`` (the command that started it) to end, so that it
    does not slow that command down, keeping its lock fresh meanwhile. The demo's files go
    to a temporary folder that is removed. The marker is written only when the demo
    succeeded; the lock is always released.
    """
    lock = _lock_path()
    try:
        while after_pid is not None and _alive(after_pid):
            with contextlib.suppress(OSError):
                os.utime(lock)
            time.sleep(1.0)
        if hasattr(os, "nice"):
            os.nice(10)
        from .demo import run_demo

        with tempfile.TemporaryDirectory(prefix="plenoptrack-warm-up-") as tmp:
            run_demo(Path(tmp) / "demo")
        marker = _marker_path()
        tmp_marker = marker.with_name(f"{marker.name}.tmp.{os.getpid()}")
        tmp_marker.write_text(json.dumps({"seeds": _manifest_key(read_manifest() or {}),
                                          "numba": _numba_version()}))
        os.replace(tmp_marker, marker)
    finally:
        lock.unlink(missing_ok=True)


def _seed_commands(demo: Path) -> list[list[str]]:
    """The commands whose kernels the seed cache holds: the demo, then the user guide's
    other commands that run kernels (views, refocusing, the refocus locator, a fragment
    scene) on the demo's data."""
    raw, calib = str(demo / "sim" / "raw" / "frame_0000.tif"), str(demo / "calib.json")
    return [["demo", "--out", str(demo)],
            ["views", raw, "--calib", calib, "--out", "views.tif"],
            ["refocus", raw, "--calib", calib, "--stack", "21", "--zmin", "-10", "--zmax", "10",
             "--out", "stack.tif"],
            ["locate", raw, "--calib", calib, "--method", "refocus", "--out", "refocus.parquet"],
            ["simulate", "--preset", "small", "--seed", "3", "--particles", "10", "--frames", "2",
             "--shape", "fragment", "--out", "sim-frag"]]


def build_seeds(seed_dir: Path = SEED_DIR) -> dict:
    """Rebuild the seed cache: run the demo and the user guide's other kernel commands with
    generic kernels, and keep what they compiled (:func:`_seed_commands`).

    The commands run in child processes with ``NUMBA_CPU_NAME=generic`` and an empty
    ``NUMBA_CACHE_DIR``; every index and data file they write for plenoptrack's modules is
    copied to ``seed_dir`` (replacing its contents) with a manifest of the numba and Python
    versions, the platform and the content hash of every source file involved.

    Returns
    -------
    dict
        The manifest written.
    """
    with tempfile.TemporaryDirectory(prefix="plenoptrack-seeds-") as tmp:
        tmp = Path(tmp)
        env = dict(os.environ, NUMBA_CPU_NAME="generic", NUMBA_CACHE_DIR=str(tmp / "cache"))
        env[ENV] = "host"
        demo = tmp / "demo"
        for args in _seed_commands(demo):
            done = subprocess.run([sys.executable, "-m", "plenoptrack", *args], env=env,
                                  cwd=tmp, capture_output=True, text=True)
            if done.returncode:
                raise RuntimeError(f"plenoptrack {' '.join(args)} failed while building the "
                                   f"seed cache:\n{done.stderr}")
        folders = {_cache_subdir(d): d for d in [PACKAGE_DIR, *PACKAGE_DIR.rglob("*")]
                   if d.is_dir() and "__pycache__" not in d.parts}
        files, sources = [], {}
        staged = tmp / "seeds"
        for cached in sorted((tmp / "cache").rglob("*")):
            if cached.suffix not in (".nbi", ".nbc"):
                continue
            source_dir = folders[cached.parent.name]
            rel_dir = source_dir.relative_to(PACKAGE_DIR)
            (staged / rel_dir).mkdir(parents=True, exist_ok=True)
            shutil.copyfile(cached, staged / rel_dir / cached.name)
            files.append((rel_dir / cached.name).as_posix())
            module = cached.name.split(".")[0]
            source = source_dir / f"{module}.py"
            sources[(rel_dir / source.name).as_posix()] = _file_sha256(source)
        manifest = {"numba": _numba_version(), "python": _python_tag(),
                    "machine": platform.machine(), "platform": sys.platform,
                    "cpu": "generic", "built_by": [" ".join(c) for c in _seed_commands(Path("demo"))],
                    "files": files,
                    "sources": dict(sorted(sources.items()))}
        (staged / _MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        if seed_dir.exists():
            shutil.rmtree(seed_dir)
        shutil.copytree(staged, seed_dir)
    return manifest


if __name__ == "__main__":  # pragma: no cover - run as a child process or by a developer
    if sys.argv[1:2] == ["warm"]:
        warm_up(int(sys.argv[2]) if len(sys.argv) > 2 else None)
    elif sys.argv[1:] == ["build"]:
        built = build_seeds()
        print(f"{len(built['files'])} files from {len(built['sources'])} modules in {SEED_DIR}")
    else:
        sys.exit("usage: python -m plenoptrack._kernel_mode build|warm")
