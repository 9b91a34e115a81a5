import numpy as np
import pandas as pd
import pytest
import tifffile

from plenoptrack.errors import ImageSizeError, InputFileError
from plenoptrack.io import (atomic_path, check_image_shape, count_frames, read_frames, read_raw,
                            read_table, write_table, write_tiff)


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
