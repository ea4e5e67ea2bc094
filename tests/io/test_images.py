"""Tests for cca_cli.io.images: round trips, raw counts, and one-line errors."""

import os

import numpy as np
import OpenImageIO as oiio
import pytest

from cca_cli.errors import InputError
from cca_cli.io.images import RawImage, read_image, saturation_mask, to_linear, write_image

RNG = np.random.default_rng(7)


def _oiio_write(path, data, fmt, **attrs):
    """Write (H, W, C) data with OpenImageIO directly (files our writer does not make)."""
    h, w, c = data.shape
    spec = oiio.ImageSpec(w, h, c, fmt)
    for key, value in attrs.items():
        spec.attribute(key, value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    assert out.write_image(np.ascontiguousarray(data))
    out.close()


def test_png_8bit_round_trip(tmp_path):
    data = RNG.integers(0, 256, size=(37, 53)).astype(np.float32)
    path = tmp_path / "v.png"
    write_image(path, data, bit_depth=8)
    img = read_image(path)
    assert isinstance(img, RawImage)
    assert img.pixels.dtype == np.float32 and img.pixels.shape == (37, 53)
    np.testing.assert_array_equal(img.pixels, data)
    assert img.bit_depth == 8 and img.format == "uint8" and img.white_level == 255
    assert img.path == str(path)


def test_tiff_16bit_keeps_12bit_counts(tmp_path):
    data = RNG.integers(0, 4096, size=(40, 60)).astype(np.float32)
    data[0, 0], data[0, 1] = 0, 4095
    path = tmp_path / "x_0_3.tif"
    write_image(path, data, bit_depth=16)
    img = read_image(path)
    np.testing.assert_array_equal(img.pixels, data)  # raw counts, not normalised
    assert img.pixels.max() == 4095
    assert img.bit_depth == 16 and img.format == "uint16"


def test_packed_12bit_tiff_returns_codes(tmp_path):
    codes = RNG.integers(0, 4096, size=(16, 24)).astype(np.uint16)
    path = tmp_path / "packed12.tif"
    # OpenImageIO takes full-range 16-bit data and stores the top 12 bits.
    _oiio_write(path, (codes << 4)[..., None], "uint16", **{"oiio:BitsPerSample": 12})
    img = read_image(path)
    assert img.bit_depth == 12 and img.white_level == 4095
    np.testing.assert_array_equal(img.pixels, codes.astype(np.float32))


@pytest.mark.parametrize("name, depth", [("f.exr", 16), ("f.tif", 32)])
def test_float_round_trip(tmp_path, name, depth):
    data = (RNG.standard_normal((30, 20)) * 1e4).astype(np.float32)
    path = tmp_path / name
    write_image(path, data, bit_depth=depth)
    img = read_image(path)
    np.testing.assert_array_equal(img.pixels, data)
    assert img.bit_depth is None and img.format == "float"


def test_rgb_average_and_channel(tmp_path):
    rgb = RNG.integers(0, 256, size=(8, 9, 3)).astype(np.uint8)
    path = tmp_path / "rgb.png"
    _oiio_write(path, rgb, "uint8")
    np.testing.assert_allclose(read_image(path).pixels, rgb.mean(axis=-1), rtol=1e-6)
    np.testing.assert_array_equal(read_image(path, channel=1).pixels, rgb[..., 1])
    with pytest.raises(InputError, match="channel 3"):
        read_image(path, channel=3)


def _assert_one_line_error(path, phrase):
    """Reading ``path`` raises an InputError: one line naming the file and containing ``phrase``."""
    with pytest.raises(InputError) as err:
        read_image(path)
    msg = str(err.value)
    assert str(path) in msg and phrase in msg and "\n" not in msg


def test_missing_file(tmp_path):
    _assert_one_line_error(tmp_path / "captures" / "x_0_3.tif", "not found")


def test_corrupt_file(tmp_path):
    path = tmp_path / "x_0_3.tif"
    path.write_bytes(np.random.default_rng(3).bytes(2000))
    _assert_one_line_error(path, "cannot read image")


def test_truncated_file(tmp_path):
    good = tmp_path / "good.tif"
    write_image(good, RNG.integers(0, 4096, size=(200, 300)), bit_depth=16)
    bad = tmp_path / "truncated.tif"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(InputError, match="truncated.tif"):
        read_image(bad)


def test_nan_in_float_image(tmp_path):
    data = np.ones((10, 12), np.float32)
    data[3, 4] = np.nan
    path = tmp_path / "nan.exr"
    write_image(path, data)
    _assert_one_line_error(path, "NaN")


def test_write_is_atomic_and_overwrites(tmp_path):
    path = tmp_path / "a.tif"
    write_image(path, np.zeros((5, 5)))
    write_image(path, np.full((5, 5), 7.0))
    assert os.listdir(tmp_path) == ["a.tif"]  # no temporary files left behind
    np.testing.assert_array_equal(read_image(path).pixels, 7.0)


def test_write_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="outside 0..255"):
        write_image(tmp_path / "a.png", np.full((4, 4), 300.0), bit_depth=8)
    with pytest.raises(ValueError, match="extension"):
        write_image(tmp_path / "a.jpg", np.zeros((4, 4)))
    with pytest.raises(ValueError, match="shape"):
        write_image(tmp_path / "a.tif", np.zeros((4, 4, 3)))
    assert os.listdir(tmp_path) == []


def test_to_linear_and_saturation_mask():
    raw = np.array([[60, 64, 100], [4000, 4095, 0]], np.float32)
    lin = to_linear(raw, black_level=64)
    assert lin.dtype == np.float32
    np.testing.assert_array_equal(lin, [[0, 0, 36], [3936, 4031, 0]])
    clipped = to_linear(raw, black_level=64, white_level=4000)
    assert clipped.max() == 4000 - 64
    np.testing.assert_array_equal(saturation_mask(raw, 4000), [[0, 0, 0], [1, 1, 0]])
    img = RawImage(pixels=raw, bit_depth=12, format="uint16", path="x.tif")
    np.testing.assert_array_equal(to_linear(img, black_level=64), lin)
    with pytest.raises(ValueError):
        to_linear(raw, black_level=100, white_level=50)
