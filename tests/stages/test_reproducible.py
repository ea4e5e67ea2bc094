"""The same inputs and thread count give bit-identical results, whatever FFTW learned on the machine before."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

pytestmark = pytest.mark.slow  # subprocesses, each a run of seconds: the whole suite only


def _cca(args, *, cache: Path, planning: str | None = None, cwd: Path) -> None:
    env = {key: value for key, value in os.environ.items() if key != "CCA_FFTW_PLANNING"}
    env["CCA_CACHE_DIR"] = str(cache)
    if planning is not None:
        env["CCA_FFTW_PLANNING"] = planning
    result = subprocess.run([sys.executable, "-m", "cca_cli", *args, "-q"], env=env, cwd=cwd, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr


def _recon(path: Path) -> tuple[int, np.ndarray, str]:
    with h5py.File(path, "r") as handle:
        return (int(handle["recon"].attrs["iterations"]), np.asarray(handle["/recon/intensity"]),
                str(handle["recon"].attrs["stopped_by"]))


@pytest.mark.parametrize("engine", ["altmin", "momentum"])
def test_a_run_with_an_empty_cache_and_one_after_timed_plans_were_saved_agree_bit_for_bit(engine, tmp_path,
                                                                                         write_config,
                                                                                         tiny_config_data):
    tiny_config_data["reconstruct"].update(engine=engine, iterations=60, tol=1e-4)
    config = write_config(tiny_config_data)
    cache = tmp_path / "cache"
    _cca(["simulate", str(config), "-o", "captures.h5"], cache=cache, cwd=tmp_path)
    _cca(["reconstruct", "captures.h5", "-o", "first.h5", "--config", str(config)], cache=cache, cwd=tmp_path)
    # A run that opts into timed plans leaves FFTW's wisdom in the cache; the default must not use it.
    _cca(["reconstruct", "captures.h5", "-o", "timed.h5", "--config", str(config)], cache=cache, planning="measure",
         cwd=tmp_path)
    assert any(cache.glob("fftw-wisdom-*")), "the timed run saved no wisdom, so this test checks nothing"
    _cca(["reconstruct", "captures.h5", "-o", "second.h5", "--config", str(config)], cache=cache, cwd=tmp_path)

    first, second = _recon(tmp_path / "first.h5"), _recon(tmp_path / "second.h5")
    assert first[0] == second[0] and first[2] == second[2]
    assert np.array_equal(first[1], second[1])
