"""``plenoptrack batch``: resumable batch locating, in-process and on a local Dask cluster.

A small simulated data set (the ``small`` preset, ideal optics, a DLFC fitted on five dot
cards) is located frame by frame with ``plenoptrack locate``; every batch must give exactly
those rows, whatever happens to the batch (killed, a worker killed, a corrupt frame).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
from typer.testing import CliRunner

from plenoptrack import preset
from plenoptrack.batch import (BATCH_FILE, FAILURES_FILE, local_cluster, part_path, read_batch,
                               read_failures, run_batch)
from plenoptrack.calibration import calibrate_from_white, record_white, save_calibration
from plenoptrack.cli import app
from plenoptrack.errors import UsageError
from plenoptrack.io import read_table
from plenoptrack.lightfield import decode
from plenoptrack.locate import PerspectiveLocator
from plenoptrack.locate.dlfc import fit_dlfc
from plenoptrack.locate.dotcards import dotcard_points
from plenoptrack.simulate import (default_dotcard, default_dotcard_depths, make_optics,
                                  make_scene, render_dotcard, render_frame, render_white)

runner = CliRunner()
N_IMAGES = 4


def ok(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    return result


def _import_locator():
    import plenoptrack.batch  # noqa: F401
    import plenoptrack.locate.perspective  # noqa: F401


@pytest.fixture(scope="module")
def cluster():
    """A Dask cluster of 2 worker processes on loopback, and a client of it; the workers
    import the locator while the data are simulated."""
    from distributed import Client

    with local_cluster(2, memory_limit="1.5GB") as c, Client(c) as client:
        warm = [client.submit(_import_locator, workers=[w], pure=False)
                for w in client.scheduler_info()["workers"]]
        yield client
        del warm


@pytest.fixture(scope="module")
def data(tmp_path_factory, cluster):
    """Calibration (with its white image) and N_IMAGES raw frames, and their particles
    located one by one with ``plenoptrack locate``."""
    root = tmp_path_factory.mktemp("batch")
    camera = preset("small")
    optics = make_optics(camera, seed=0)
    white = render_white(optics, seed=np.random.default_rng([0, 2]))
    tifffile.imwrite(root / "white.tif", white)
    calib, _ = calibrate_from_white(white, camera)
    card = default_dotcard(camera)
    points = []
    for k, z in enumerate(default_dotcard_depths(camera, n=5)):
        image = render_dotcard(optics, float(z), card=card, seed=np.random.default_rng([0, 4, k]))
        points.append(dotcard_points(decode(image, calib.grid), spacing_mm=card.spacing_mm,
                                     z_mm=float(z), camera=camera))
    calib = calib.with_dlfc(fit_dlfc(pd.concat(points, ignore_index=True), order=4,
                                     group_by="z", reject_k=5))
    save_calibration(record_white(calib, root / "white.tif", calibration_path=root / "calib.json"),
                     root / "calib.json")
    raw = root / "raw"
    raw.mkdir()
    for k in range(N_IMAGES):
        scene = make_scene(camera, n_particles=0 if k == 1 else 8, seed=k)
        frame = render_frame(optics, scene.truth, seed=np.random.default_rng([k, 3, 0]))
        tifffile.imwrite(raw / f"img_{k}.tif", frame)
    images = sorted(raw.glob("img_*.tif"))
    ok("locate", *images, "--calib", root / "calib.json", "--out", root / "reference.parquet")
    reference = read_table(root / "reference.parquet")
    assert reference["frame"].nunique() == N_IMAGES - 1  # image 1 holds no particle
    return root, images, reference


def frames_of(folder, images, n_frames):
    """``n_frames`` raw files in ``folder``, cycling through ``images`` (hard copies)."""
    folder.mkdir()
    files = []
    for j in range(n_frames):
        target = folder / f"frame_{j:03d}.tif"
        shutil.copyfile(images[j % len(images)], target)
        files.append(target)
    return files


def expected(reference, n_frames):
    """The reference rows of frame j % N_IMAGES, numbered j, for j < n_frames."""
    tables = [reference[reference["frame"] == j % N_IMAGES].assign(frame=j)
              for j in range(n_frames)]
    return pd.concat(tables, ignore_index=True)


def assert_same_rows(actual, wanted):
    pd.testing.assert_frame_equal(actual.reset_index(drop=True), wanted.reset_index(drop=True),
                                  check_exact=True)


def leftovers(out):
    """Files in a batch folder other than the parts, the run record and the failures."""
    return sorted(p.name for p in out.iterdir()
                  if not (p.name.startswith("frame-") and p.name.endswith(".parquet"))
                  and p.name not in (BATCH_FILE, FAILURES_FILE))


def live_members(pgid):
    """Pids of the process group ``pgid`` that are alive and not zombies (Linux /proc)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            pids.append(int(stat.parent.name))
    return pids


def test_two_workers_give_exactly_the_rows_of_locate(data, cluster, tmp_path):
    root, images, reference = data
    out = tmp_path / "out"
    result = run_batch(images, root / "calib.json", out, white_file=root / "white.tif",
                       client=cluster)
    assert (result.done, result.skipped, result.failed) == (N_IMAGES, 0, 0)
    assert result.n_particles == len(reference)
    table = read_batch(out)
    assert_same_rows(table, reference)
    # the folder is one table for pandas and dask too, with the run's provenance
    assert_same_rows(pd.read_parquet(out).sort_values("frame", kind="stable"), reference)
    import dask.dataframe as dd

    assert_same_rows(dd.read_parquet(out).compute().sort_values("frame", kind="stable"),
                     reference)
    record = pd.read_parquet(out).attrs["plenoptrack"]
    assert record["settings"] == reference.attrs["plenoptrack"]["settings"]
    assert record["calibration"]["sha256"] == reference.attrs["plenoptrack"]["calibration"]["sha256"]
    assert record["flat_field"]["sha256"] == reference.attrs["plenoptrack"]["flat_field"]["sha256"]
    assert record["package_version"] == reference.attrs["plenoptrack"]["package_version"]
    assert len(part_path(out, 1).read_bytes()) > 0 and len(read_table(part_path(out, 1))) == 0

    # the same command again, on the same cluster through its address: nothing recomputed
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("frame-*.parquet")}
    again = ok("batch", root / "raw" / "img_*.tif", "--calib", root / "calib.json",
               "--out", out, "--scheduler", cluster.scheduler_info()["address"])
    assert f"0 located (0 particles), {N_IMAGES} already done, 0 failed" in again.stderr
    assert stamps == {p.name: p.stat().st_mtime_ns for p in out.glob("frame-*.parquet")}
    assert leftovers(out) == []


def test_changed_input_is_located_again_and_other_settings_are_refused(data, tmp_path):
    root, images, reference = data
    raw = tmp_path / "raw"
    files = frames_of(raw, images, 2)
    out = tmp_path / "out"
    first = run_batch(files, root / "calib.json", out, white_file=root / "white.tif")
    assert (first.done, first.skipped) == (2, 0)
    shutil.copyfile(images[2], files[1])  # frame 1 now holds another image
    second = run_batch(files, root / "calib.json", out, white_file=root / "white.tif")
    assert (second.done, second.skipped) == (1, 1)
    wanted = pd.concat([reference[reference["frame"] == 0],
                        reference[reference["frame"] == 2].assign(frame=1)])
    assert_same_rows(read_batch(out), wanted)

    other = PerspectiveLocator().updated({"segment": {"window": 41}})
    with pytest.raises(UsageError, match="different settings"):
        run_batch(files, root / "calib.json", out, settings=other, white_file=root / "white.tif")
    with pytest.raises(UsageError, match="different white"):
        run_batch(files, root / "calib.json", out)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(UsageError, match="holds no batch"):
        run_batch(files, root / "calib.json", foreign)


def test_batch_killed_part_way_resumes_with_every_frame_once(data, cluster, tmp_path):
    root, images, reference = data
    n_frames = 6
    frames_of(tmp_path / "raw", images, n_frames)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "plenoptrack", "batch", str(tmp_path / "raw" / "*.tif"),
           "--calib", str(root / "calib.json"), "--out", str(out), "--workers", "1"]
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    deadline = time.monotonic() + 180
    while not list(out.glob("frame-*.parquet")) and proc.poll() is None:
        assert time.monotonic() < deadline, "the batch wrote no part in 180 s"
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)  # the command, its scheduler and its workers
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read()
    for _ in range(200):  # the whole process group is gone (zombies aside)
        if not live_members(proc.pid):
            break
        time.sleep(0.05)
    else:
        pytest.fail(f"processes of the killed batch still run: {live_members(proc.pid)}")
    before = sorted(out.glob("frame-*.parquet"))
    assert 1 <= len(before) < n_frames, "the batch finished before it was killed"

    result = run_batch(sorted((tmp_path / "raw").glob("*.tif")), root / "calib.json", out,
                       white_file=root / "white.tif", client=cluster)
    assert result.skipped == len(before) and result.done == n_frames - len(before)
    assert result.failed == 0
    assert sorted(p.name for p in out.glob("frame-*.parquet")) == [
        f"frame-{j:06d}.parquet" for j in range(n_frames)]
    assert leftovers(out) == []
    assert_same_rows(read_batch(out), expected(reference, n_frames))


def test_corrupt_frame_is_recorded_and_the_others_are_done(data, cluster, tmp_path):
    root, images, reference = data
    n_frames = 6
    files = frames_of(tmp_path / "raw", images, n_frames)
    whole = files[2].read_bytes()
    files[2].write_bytes(whole[: len(whole) // 2])  # truncated pixel data
    files[4].write_bytes(b"not a TIFF at all")      # unreadable header
    out = tmp_path / "out"
    result = runner.invoke(app, [str(a) for a in (
        "batch", tmp_path / "raw" / "*.tif", "--calib", root / "calib.json", "--out", out,
        "--scheduler", cluster.scheduler_info()["address"])])
    assert result.exit_code == 1, (result.stdout, result.stderr)
    assert "2 failed" in result.stderr and FAILURES_FILE in result.stderr
    failures = read_failures(out)
    assert failures["frame"].tolist() == [2, 4]
    assert failures["file"].tolist() == [str(files[2].resolve()), str(files[4].resolve())]
    assert (failures["error"] == "InputFileError").all()
    assert "truncated" in failures["message"][0] and "not a readable TIFF" in failures["message"][1]
    wanted = expected(reference, n_frames)
    assert_same_rows(read_batch(out), wanted[~wanted["frame"].isin([2, 4])])
    assert not part_path(out, 2).exists() and not part_path(out, 4).exists()


def test_command_line_usage_errors(data, tmp_path):
    root, images, _ = data
    cases = [
        (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "not both"),
        (["--method", "magic"], "--method"),
        (["--white", root / "white.tif", "--no-flat-field"], "contradict"),
    ]
    for extra, message in cases:
        result = runner.invoke(app, [str(a) for a in ["batch", images[0], "--calib",
                                                       root / "calib.json", "--out",
                                                       tmp_path / "o", *extra]])
        assert result.exit_code == 2 and message in result.stderr, (extra, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1
    none = runner.invoke(app, ["batch", str(tmp_path / "nothing_*.tif"), "--calib",
                               str(root / "calib.json")])
    assert none.exit_code == 2 and "matches no file" in none.stderr
    inside = runner.invoke(app, ["batch", str(images[0]), "--calib", str(root / "calib.json"),
                                 "--out", str(root / "raw")])
    assert inside.exit_code == 2 and "holding the input" in inside.stderr
    assert not (tmp_path / "o").exists()


def test_worker_killed_mid_batch_still_completes(data, cluster, tmp_path):
    root, images, reference = data
    n_frames = 6
    files = frames_of(tmp_path / "raw", images, n_frames)
    pids = cluster.run(os.getpid)
    killed = []

    def kill_a_busy_worker(outcome):
        if killed:
            return
        busy = [addr for addr, keys in cluster.processing().items() if keys and addr in pids]
        if busy:
            os.kill(pids[busy[0]], signal.SIGKILL)
            killed.append(pids[busy[0]])

    result = run_batch(files, root / "calib.json", tmp_path / "out",
                       white_file=root / "white.tif", client=cluster,
                       on_outcome=kill_a_busy_worker)
    assert killed, "no worker was busy to kill"
    # a frame whose part the killed worker wrote before it could report is found done
    assert result.failed == 0 and result.done + result.skipped == n_frames, result
    assert result.skipped <= 1
    assert_same_rows(read_batch(tmp_path / "out"), expected(reference, n_frames))
    assert leftovers(tmp_path / "out") == []
    assert killed[0] not in cluster.run(os.getpid).values()


def test_other_methods_and_tracking_at_the_end(data, cluster, tmp_path):
    """--method hybrid gives the rows of `locate --method hybrid`; --track writes the
    linked tracks beside the folder."""
    root, images, _ = data
    ok("locate", *images, "--calib", root / "calib.json", "--method", "hybrid",
       "--out", tmp_path / "hybrid.parquet")
    wanted = read_table(tmp_path / "hybrid.parquet")
    out = tmp_path / "out"
    res = ok("batch", root / "raw" / "img_*.tif", "--calib", root / "calib.json", "--out", out,
             "--method", "hybrid", "--track", "--scheduler", cluster.scheduler_info()["address"])
    assert_same_rows(read_batch(out), wanted)
    assert read_batch(out).attrs["plenoptrack"]["method"] == "hybrid"
    tracks = read_table(tmp_path / "out-tracks.parquet")
    assert "particle" in tracks.columns and set(tracks["frame"]) <= set(wanted["frame"])
    assert "out-tracks.parquet" in res.stderr
