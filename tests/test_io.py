import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile

from plenoptrack.errors import ImageSizeError, InputFileError, OutputConflictError
from plenoptrack.io import (atomic_path, check_image_shape, check_outputs, count_frames,
                            exposure_problem, interrupts_deferred, read_frames, read_raw,
                            read_table, staged_outputs, write_table, write_tiff)


def test_tiff_round_trip_single_and_multi(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 4096, size=(7, 9), dtype=np.uint16)
    stack = rng.integers(0, 4096, size=(3, 7, 9), dtype=np.uint16)
    write_tiff(tmp_path / "one.tif", img)
    write_tiff(tmp_path / "many.tif", stack)
    np.testing.assert_array_equal(read_raw(tmp_path / "one.tif"), img)
    np.testing.assert_array_equal(read_frames(tmp_path / "many.tif"), stack)
    np.testing.assert_array_equal(read_raw(tmp_path / "many.tif", frame=2), stack[2])
    assert count_frames(tmp_path / "many.tif") == 3
    assert count_frames(tmp_path / "one.tif") == 1


def test_tiff_is_deflate_compressed_unless_asked_not_to_and_keeps_every_pixel(tmp_path):
    import tifffile

    rng = np.random.default_rng(2)
    img = (2000 + rng.normal(0, 40, size=(300, 400))).astype(np.uint16)   # a noisy frame
    write_tiff(tmp_path / "z.tif", img)
    write_tiff(tmp_path / "raw.tif", img, compression=None)
    for name, tag in (("z.tif", "ADOBE_DEFLATE"), ("raw.tif", "NONE")):
        with tifffile.TiffFile(tmp_path / name) as tif:
            assert tif.pages[0].compression.name == tag
        np.testing.assert_array_equal(read_raw(tmp_path / name), img)
    assert (tmp_path / "z.tif").stat().st_size < 0.8 * (tmp_path / "raw.tif").stat().st_size


def test_missing_file(tmp_path):
    with pytest.raises(InputFileError, match="absent.tif: file not found"):
        read_raw(tmp_path / "absent.tif")


def test_not_a_tiff(tmp_path):
    path = tmp_path / "notes.tif"
    path.write_text("hello")
    with pytest.raises(InputFileError, match="not a readable TIFF"):
        read_raw(path)


def test_truncated_tiff(tmp_path):
    path = tmp_path / "cut.tif"
    tifffile.imwrite(path, np.ones((200, 300), np.uint16) * 7)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputFileError, match="cut.tif"):
        read_raw(path)


def test_wrong_dtype(tmp_path):
    path = tmp_path / "float.tif"
    tifffile.imwrite(path, np.ones((4, 4), np.float32))
    with pytest.raises(InputFileError, match="must be uint16; got float32"):
        read_raw(path)


def test_missing_frame(tmp_path):
    write_tiff(tmp_path / "one.tif", np.zeros((3, 3), np.uint16))
    with pytest.raises(InputFileError, match="frame 4 does not exist"):
        read_raw(tmp_path / "one.tif", frame=4)


def test_check_image_shape():
    check_image_shape(np.zeros((4, 5)), (4, 5))
    with pytest.raises(ImageSizeError, match="image is 4 x 5 pixels but the camera description expects 6 x 5"):
        check_image_shape(np.zeros((4, 5)), (6, 5))


@pytest.mark.parametrize("name", ["t.parquet", "t.csv"])
def test_table_round_trip(tmp_path, name):
    df = pd.DataFrame({"frame": [0, 0, 1], "x": [0.5, -1.25, 3.0]})
    write_table(df, tmp_path / name)
    pd.testing.assert_frame_equal(read_table(tmp_path / name), df)


def test_corrupt_table(tmp_path):
    path = tmp_path / "bad.parquet"
    path.write_text("not parquet")
    with pytest.raises(InputFileError, match="bad.parquet: not a readable Parquet table"):
        read_table(path)


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "result.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.txt"]


# --------------------------------------------------------------------------- safe outputs


def test_staged_outputs_replace_all_targets_or_none(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    with pytest.raises(RuntimeError):
        with staged_outputs(a, b) as (ta, tb):
            ta.write_text("new a")  # complete
            raise RuntimeError("the second output failed")
    assert a.read_text() == "old a" and not b.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    with staged_outputs(a, None, b) as (ta, none, tb):
        assert none is None
        ta.write_text("new a")
        tb.write_text("new b")
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


def test_a_failed_rename_restores_every_old_target(tmp_path, monkeypatch):
    import plenoptrack.io

    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    b.write_text("old b")
    real_replace = os.replace
    onto_b = []

    def replace(src, dst):
        if Path(dst) == b:
            onto_b.append(src)
            if len(onto_b) == 1:  # committing the new b fails; restoring the old one works
                raise OSError(28, "No space left on device", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(plenoptrack.io.os, "replace", replace)
    with pytest.raises(OSError, match="No space"):
        with staged_outputs(a, b) as (ta, tb):
            ta.write_text("new a")
            tb.write_text("new b")
    monkeypatch.undo()
    assert (a.read_text(), b.read_text()) == ("old a", "old b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


def test_staged_outputs_remove_the_folders_they_created_on_failure(tmp_path):
    with pytest.raises(RuntimeError):
        with staged_outputs(tmp_path / "new" / "deeper" / "a.txt"):
            raise RuntimeError
    assert list(tmp_path.iterdir()) == []


def test_files_get_the_umask_mode(tmp_path):
    previous = os.umask(0o002)
    try:
        write_table(pd.DataFrame({"x": [1.0]}), tmp_path / "t.parquet")
        write_tiff(tmp_path / "i.tif", np.zeros((2, 2), np.uint16))
    finally:
        os.umask(previous)
    for name in ("t.parquet", "i.tif"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o664


def test_check_outputs_refuses_inputs_links_duplicates_and_folders(tmp_path):
    raw = tmp_path / "raw.tif"
    raw.write_bytes(b"raw")
    (tmp_path / "soft.tif").symlink_to(raw)
    os.link(raw, tmp_path / "hard.tif")
    (tmp_path / "dir").mkdir()
    inputs = {"RAW": [raw], "--calib": None}
    check_outputs({"--out": tmp_path / "new.parquet", "--detections": None}, inputs)
    for target in (raw, tmp_path / "soft.tif", tmp_path / "hard.tif", tmp_path / "dir" / ".." / "raw.tif"):
        with pytest.raises(OutputConflictError, match="--out is also the input RAW"):
            check_outputs({"--out": target}, inputs)
    with pytest.raises(OutputConflictError, match="both --out and --mosaic"):
        check_outputs({"--out": tmp_path / "v.tif", "--mosaic": tmp_path / "v.tif"}, inputs)
    with pytest.raises(OutputConflictError, match="is a folder"):
        check_outputs({"--out": tmp_path / "dir"}, inputs)
    with pytest.raises(OutputConflictError, match="would replace a folder holding the input"):
        check_outputs({"--out": tmp_path}, inputs, folders=["--out"])
    assert raw.read_bytes() == b"raw"


def test_interrupts_are_deferred_to_the_end_of_the_block():
    import signal

    done = []
    # a shell starts background jobs with SIGINT ignored: give the test the usual handler
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt), interrupts_deferred():
            # raise_signal delivers to this thread; os.kill may pick another thread of the
            # process (numba's workers), whose handler can run after the block has ended
            signal.raise_signal(signal.SIGINT)
            done.append("finished the block first")
    finally:
        signal.signal(signal.SIGINT, previous)
    assert done == ["finished the block first"]


def test_ctrl_c_while_the_temporaries_are_made_leaves_none_behind(tmp_path, monkeypatch):
    # Ctrl-C arriving right after the second temporary file was created, before the
    # staging had recorded it, used to leave an empty ".b.parquet.*.tmp.parquet" behind
    import signal

    import plenoptrack.io as pio

    made = []
    original = pio._temporary_beside

    def temporary_then_ctrl_c(path):
        tmp = original(path)
        made.append(tmp)
        if len(made) == 2:
            signal.raise_signal(signal.SIGINT)
        return tmp

    monkeypatch.setattr(pio, "_temporary_beside", temporary_then_ctrl_c)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt), \
                pio.staged_outputs(tmp_path / "a.parquet", tmp_path / "b.parquet"):
            pass
    finally:
        signal.signal(signal.SIGINT, previous)
    assert len(made) == 2
    assert list(tmp_path.iterdir()) == []


def test_a_ctrl_c_swallowed_by_a_c_callback_stops_the_next_commit(tmp_path, monkeypatch):
    """A KeyboardInterrupt raised in a ctypes callback is dropped by C (as llvmlite's are
    while numba compiles); the command line's hook records it and no output is committed."""
    import ctypes
    import ctypes.util
    import sys

    import plenoptrack.io as pio
    from plenoptrack.cli import _unraisable

    monkeypatch.setattr(pio, "_lost_interrupts", [])
    seen = []
    monkeypatch.setattr(sys, "unraisablehook", _unraisable(seen.append))

    compare = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))

    def interrupted(a, b):
        raise KeyboardInterrupt

    values = (ctypes.c_int * 3)(3, 1, 2)
    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    libc.qsort(values, 3, ctypes.sizeof(ctypes.c_int), compare(interrupted))  # returns normally
    assert seen == [] and pio._lost_interrupts  # recorded, not printed

    target = tmp_path / "out.txt"
    with pytest.raises(KeyboardInterrupt), atomic_path(target) as tmp:
        tmp.write_text("never committed")
    assert list(tmp_path.iterdir()) == []

    def failing(a, b):
        raise ValueError("not an interrupt")

    libc.qsort(values, 3, ctypes.sizeof(ctypes.c_int), compare(failing))
    assert seen and all(type(info.exc_value) is ValueError for info in seen)  # the old hook


def test_a_ctrl_c_printed_by_compiled_code_is_recorded_without_a_traceback(monkeypatch, capsys):
    """Cython code that cannot raise (scipy.stats._sobol while it initialises) prints a
    KeyboardInterrupt through sys.excepthook and drops it: the command line's hook records
    it instead of printing a traceback, and passes other exceptions on."""
    import sys

    import plenoptrack.io as pio
    from plenoptrack.cli import _excepthook

    monkeypatch.setattr(pio, "_lost_interrupts", [])
    seen = []
    hook = _excepthook(lambda *exc: seen.append(exc[0]))
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt:
        hook(*sys.exc_info())
    assert seen == [] and pio._lost_interrupts
    assert capsys.readouterr().err == ""
    try:
        raise ValueError("not an interrupt")
    except ValueError:
        hook(*sys.exc_info())
    assert seen == [ValueError]


def test_compiler_finalizer_errors_are_silent_and_others_are_not(monkeypatch):
    """A Ctrl-C during compilation leaves llvmlite objects whose finalizers fail when the
    garbage collector meets them: the command line's hook drops those, and only those."""
    import gc
    import sys

    from llvmlite.binding import ffi

    from plenoptrack.cli import _unraisable

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", _unraisable(seen.append))

    class HalfBuilt(ffi.ObjectRef):   # what an interrupted compile leaves: no handle set
        def __init__(self):
            pass

    HalfBuilt()
    gc.collect()
    assert seen == []

    class Other:
        def __del__(self):
            raise AttributeError("a real fault elsewhere")

    Other()
    gc.collect()
    assert [type(info.exc_value) for info in seen] == [AttributeError]


def test_colour_tiff_is_refused_and_a_stack_of_three_frames_read(tmp_path):
    grey = np.arange(4 * 5, dtype=np.uint16).reshape(4, 5)
    tifffile.imwrite(tmp_path / "rgb.tif", np.stack([grey] * 3, axis=-1), photometric="rgb")
    with pytest.raises(InputFileError, match="rgb.tif: is a 3-channel \\(RGB\\) colour image"):
        read_raw(tmp_path / "rgb.tif")
    stack = np.stack([grey, grey + 1, grey + 2])
    tifffile.imwrite(tmp_path / "planes.tif", stack, photometric="rgb", planarconfig="separate")
    np.testing.assert_array_equal(read_frames(tmp_path / "planes.tif"), stack)


def test_exposure_problem():
    rng = np.random.default_rng(0)
    lit = rng.integers(1500, 3000, size=(60, 80)).astype(np.uint16)
    assert exposure_problem(lit, 4095) is None
    assert exposure_problem(np.zeros((60, 80), np.uint16), 4095) == "black"
    assert exposure_problem(rng.integers(0, 40, size=(60, 80)), 4095) == "black"
    assert exposure_problem(np.full((60, 80), 4095, np.uint16), 4095) == "saturated"
    dark_particles = lit.copy()
    dark_particles[:, :30] = 0  # a third of the frame shadowed is still a usable frame
    assert exposure_problem(dark_particles, 4095) is None
    # black means 99 % of the (sampled) pixels below 2 % of full scale, not fewer
    frame = np.zeros((300, 300), np.uint16)
    frame[:6] = 2000                    # 2 % of the rows lit
    assert exposure_problem(frame, 4095) is None
    frame[3:] = 0                       # 1 % lit, 99 % black
    assert exposure_problem(frame, 4095) == "black"


# --------------------------------------------------------------------------- fuzzed readers

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


def _readers(tmp_path_factory):
    """(suffix, reader) of every reader of the file contract."""
    from plenoptrack.calibrate import read_dotcards
    from plenoptrack.calibration import load_calibration
    from plenoptrack.camera import load_camera
    from plenoptrack.simulate import load_scene

    return {
        ".tif": read_frames, ".parquet": read_table, ".csv": read_table,
        ".json": load_calibration, "camera.toml": load_camera,
        "dotcards.toml": read_dotcards, "scene.toml": load_scene,
    }


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory):
    """One valid file per reader, to be truncated."""
    from plenoptrack.calibration import calibrate_from_white, save_calibration
    from plenoptrack.simulate import simulate_dataset

    folder = tmp_path_factory.mktemp("valid")
    sim = simulate_dataset("small", folder / "sim", seed=0, n_particles=2, dotcard_depths=[0.0])
    calib, _ = calibrate_from_white(sim.white_path, sim.camera)
    save_calibration(calib, folder / "c.json")
    write_table(sim.truth, folder / "t.csv")
    (folder / "scene.toml").write_text("camera = 'small'\n[random]\nn = 2\n")
    return {".tif": sim.frame_paths[0], ".parquet": sim.truth_path, ".csv": folder / "t.csv",
            ".json": folder / "c.json", "camera.toml": sim.camera_path,
            "dotcards.toml": sim.dotcards_path, "scene.toml": folder / "scene.toml"}


KINDS = [".tif", ".parquet", ".csv", ".json", "camera.toml", "dotcards.toml", "scene.toml"]


def _only_own_errors(reader, path):
    from plenoptrack.errors import PlenoptrackError

    try:
        reader(path)
    except PlenoptrackError:
        pass


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(KINDS), data=st.binary(max_size=600))
def test_random_bytes_raise_only_project_errors(tmp_path_factory, kind, data):
    folder = tmp_path_factory.mktemp("fuzz")
    path = folder / (f"f{kind}" if kind.startswith(".") else kind)
    path.write_bytes(data)
    _only_own_errors(_readers(tmp_path_factory)[kind], path)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(KINDS), fraction=st.floats(0.0, 1.0))
def test_truncated_files_raise_only_project_errors(tmp_path_factory, valid_files, kind, fraction):
    source = valid_files[kind]
    full = source.read_bytes()
    folder = tmp_path_factory.mktemp("cut")
    path = folder / source.name
    if kind == "dotcards.toml":  # keep the card images beside it
        for card in source.parent.glob("*.tif"):
            (folder / card.name).write_bytes(card.read_bytes())
    path.write_bytes(full[: int(len(full) * fraction)])
    _only_own_errors(_readers(tmp_path_factory)[kind], path)


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_table_metadata_round_trips(tmp_path, suffix):
    from plenoptrack.io import METADATA_KEY, read_table, write_table

    df = pd.DataFrame({"frame": [0, 1], "x": [0.5, -1.25], "z": [3.0, float("nan")]})
    meta = {"method": "perspective", "settings": {"segment": {"area_range": [2.0, 7.5]}}}
    df.attrs[METADATA_KEY] = meta
    path = write_table(df, tmp_path / f"t{suffix}")
    back = read_table(path)
    assert back.attrs[METADATA_KEY] == meta
    pd.testing.assert_frame_equal(back, df)
    if suffix == ".csv":   # other tools read the table by skipping the comment line
        pd.testing.assert_frame_equal(pd.read_csv(path, comment="#"), df)
        plain = write_table(pd.DataFrame(df.to_dict("list")),
                            tmp_path / "plain.csv")
        assert not plain.read_text().startswith("#")
        assert METADATA_KEY not in read_table(plain).attrs
