"""Hostile photo files at the reader: 16-bit PNGs decode to the same 8-bit values the detectors
would get from the 8-bit file (rounded, not clipped), and a folder or a FIFO given as a photo
is named for what it is, not "not found" (docs/reliability.md, photos)."""
import os

import numpy as np
import png
import pytest

from softras_cl.errors import InputError
from softras_cl.io.images import read_photo, read_rgb8


def _write_png16(path, data: np.ndarray) -> None:
    """(H, W) or (H, W, 3) uint16 -> a 16-bit PNG (grey or RGB)."""
    h, w = data.shape[:2]
    channels = 1 if data.ndim == 2 else data.shape[2]
    with open(path, "wb") as f:
        png.Writer(width=w, height=h, greyscale=channels == 1, bitdepth=16).write(f, data.reshape(h, w * channels))


@pytest.mark.parametrize("channels", [1, 3])
def test_read_rgb8_of_a_16bit_png_equals_the_8bit_conversion(tmp_path, channels):
    rng = np.random.default_rng(3)
    shape = (24, 32) if channels == 1 else (24, 32, 3)
    eight = rng.integers(0, 256, shape).astype(np.uint16)
    _write_png16(tmp_path / "exact.png", eight * 257)                # 8-bit values widened exactly
    expected = np.repeat(eight[..., None], 3, -1) if channels == 1 else eight
    assert np.array_equal(read_rgb8(tmp_path / "exact.png"), expected.astype(np.uint8))
    sixteen = rng.integers(0, 65536, shape).astype(np.uint16)       # any 16-bit value: rounded
    _write_png16(tmp_path / "any.png", sixteen)
    rounded = np.round(sixteen * (255.0 / 65535.0)).astype(np.uint8)
    got = read_rgb8(tmp_path / "any.png")
    assert np.array_equal(got, np.repeat(rounded[..., None], 3, -1) if channels == 1 else rounded)
    assert np.array_equal(read_photo(tmp_path / "any.png").rgb8, got)   # the detectors' copy too


def test_a_folder_given_as_a_photo_is_named_a_folder(tmp_path):
    folder = tmp_path / "photo.png"
    folder.mkdir()
    with pytest.raises(InputError, match=r"photo\.png is a directory, not an image file"):
        read_rgb8(folder)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_a_fifo_given_as_a_photo_is_not_a_regular_file(tmp_path):
    fifo = tmp_path / "photo.png"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match=r"photo\.png is not a regular file \(a FIFO\)"):
        read_photo(fifo)                 # and does not block opening it


def test_a_missing_photo_is_still_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="image file not found"):
        read_rgb8(tmp_path / "missing.png")
