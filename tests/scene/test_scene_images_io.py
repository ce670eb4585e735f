"""ctgs.io.images: formats, value ranges, alpha rule, corrupt files, atomic writes."""

from __future__ import annotations

import os

import numpy as np
import pytest

from ctgs.errors import UserError
from ctgs.io.images import image_info, list_images, read_image, read_rgb, resize_image, write_image


@pytest.fixture
def ramp() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.random((9, 13, 3)).astype(np.float32)  # odd sizes catch W/H swaps


@pytest.mark.parametrize("name,bits,tol", [
    ("a.png", 8, 0.5 / 255 + 1e-6),
    ("b.png", 16, 0.5 / 65535 + 1e-7),
    ("c.exr", None, 1e-3),  # half floats: 11-bit mantissa
    ("d.tif", 16, 0.5 / 65535 + 1e-7),
])
def test_roundtrip(tmp_path, ramp, name, bits, tol):
    path = str(tmp_path / name)
    write_image(path, ramp, bits=bits)
    back = read_image(path)
    assert back.dtype == np.float32 and back.shape == ramp.shape
    assert np.abs(back - ramp).max() <= tol
    info = image_info(path)
    assert (info.width, info.height, info.channels) == (13, 9, 3)


def test_jpeg_is_read_in_unit_range(tmp_path):
    smooth = np.linspace(0, 1, 32 * 48 * 3, dtype=np.float32).reshape(32, 48, 3)
    write_image(str(tmp_path / "x.jpg"), smooth)
    back = read_image(str(tmp_path / "x.jpg"))
    assert back.shape == (32, 48, 3) and 0.0 <= back.min() and back.max() <= 1.0
    assert np.abs(back - smooth).mean() < 0.02


def test_rgba_composited_like_3dgs(tmp_path):
    rgba = np.random.default_rng(1).random((6, 5, 4)).astype(np.float32)
    write_image(str(tmp_path / "a.png"), rgba, bits=16)
    stored = read_image(str(tmp_path / "a.png"))
    assert stored.shape[2] == 4
    # Unassociated alpha: the stored colour is not premultiplied on read.
    assert np.abs(stored - rgba).max() < 1e-4
    black = read_rgb(str(tmp_path / "a.png"))
    white = read_rgb(str(tmp_path / "a.png"), background=(1.0, 1.0, 1.0))
    a = rgba[:, :, 3:]
    np.testing.assert_allclose(black, rgba[:, :, :3] * a, atol=1e-4)
    np.testing.assert_allclose(white, rgba[:, :, :3] * a + (1 - a), atol=1e-4)


def test_grey_becomes_rgb(tmp_path):
    grey = np.random.default_rng(2).random((7, 8)).astype(np.float32)
    write_image(str(tmp_path / "g.png"), grey)
    rgb = read_rgb(str(tmp_path / "g.png"))
    assert rgb.shape == (7, 8, 3)
    np.testing.assert_allclose(rgb[:, :, 0], rgb[:, :, 2])
    np.testing.assert_allclose(rgb[:, :, 1], grey, atol=0.5 / 255 + 1e-6)


def test_truncated_and_garbage_files_are_user_errors(tmp_path, ramp):
    good = tmp_path / "good.png"
    write_image(str(good), np.tile(ramp, (8, 8, 1)))
    data = good.read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    (tmp_path / "junk.png").write_bytes(b"not an image at all" * 20)
    for name in ("cut.png", "junk.png", "missing.png"):
        with pytest.raises(UserError) as err:
            read_image(str(tmp_path / name))
        message = str(err.value)
        assert name in message and "\n" not in message


def test_write_is_atomic_and_lists_only_images(tmp_path, ramp):
    write_image(str(tmp_path / "sub" / "x.png"), ramp)
    (tmp_path / "sub" / "notes.txt").write_text("x")
    assert sorted(os.listdir(tmp_path / "sub")) == ["notes.txt", "x.png"]  # no temporary leftovers
    assert list_images(str(tmp_path / "sub")) == ["x.png"]


def test_resize_preserves_mean_and_shape(ramp):
    big = np.repeat(np.repeat(ramp, 4, axis=0), 4, axis=1)  # [36, 52, 3]
    small = resize_image(big, 13, 9)
    assert small.shape == (9, 13, 3)
    assert abs(small.mean() - big.mean()) < 0.01
