"""Image stacks in one file (io.stacks): MATLAB v5/v7 and v7.3 variables and numpy arrays, any image axis."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import scipy.io

from cca_cli.errors import InputError
from cca_cli.io.stacks import read_stack

RNG = np.random.default_rng(3)
IMAGES = RNG.integers(0, 4096, (5, 12, 16)).astype(np.uint16)   # (K, H, W)


def test_every_container_and_axis_order_gives_the_same_images(tmp_path):
    scipy.io.savemat(tmp_path / "hwk.mat", {"frames": np.moveaxis(IMAGES, 0, -1)})   # MATLAB's (H, W, K)
    scipy.io.savemat(tmp_path / "khw.mat", {"frames": IMAGES})
    with h5py.File(tmp_path / "v73.mat", "w") as handle:   # as MATLAB's -v7.3 writes (H, W, K): axes reversed
        handle["frames"] = np.moveaxis(IMAGES, 0, -1).transpose()
    np.save(tmp_path / "stack.npy", IMAGES)
    for name in ("hwk.mat", "khw.mat", "v73.mat", "stack.npy"):
        stack = read_stack(tmp_path / name, "frames", 5)
        assert stack.dtype == np.float32
        np.testing.assert_array_equal(stack, IMAGES, err_msg=name)


def test_a_stack_of_another_count_or_content_is_one_line_naming_the_file(tmp_path):
    np.save(tmp_path / "stack.npy", IMAGES)
    with pytest.raises(InputError, match=r"stack.npy: no axis of its \(5, 12, 16\) stack holds the 7 images leds.csv"):
        read_stack(tmp_path / "stack.npy", "frames", 7, table="leds.csv")
    np.save(tmp_path / "text.npy", np.array(["a", "b"]))
    with pytest.raises(InputError, match="text.npy: the array holds <U1 values; expected real numbers"):
        read_stack(tmp_path / "text.npy", "frames", 2)
    scipy.io.savemat(tmp_path / "other.mat", {"imlow": np.moveaxis(IMAGES, 0, -1)})
    with pytest.raises(InputError, match="other.mat: has no variable 'frames'"):
        read_stack(tmp_path / "other.mat", "frames", 5)
    (tmp_path / "stack.tif").write_bytes(b"II*\x00" + bytes(64))
    with pytest.raises(InputError, match=r"stack.tif: cannot read MATLAB file .*v7.3 files and numpy's .npy"):
        read_stack(tmp_path / "stack.tif", "frames", 5)
