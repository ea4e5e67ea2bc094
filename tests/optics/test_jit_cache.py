"""A read-only install: numba can write no cache folder beside the package, in NUMBA_CACHE_DIR or the user's home.

numba's ``cache=True`` then raised at import ("no locator available"). The package is copied to a folder where numba
cannot write its cache and imported from there in a fresh interpreter. The tests run as root, which file permissions
do not stop, so each folder numba would write is blocked by a file standing where the folder should be: numba (and
the fallback) cannot create a folder there, as in a read-only install.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import cca_cli

pytest.importorskip("numba")
pytestmark = pytest.mark.slow  # subprocesses, each a run of seconds: the whole suite only

SCRIPT = """
import numpy as np
import cca_cli
from cca_cli.optics import kernels

assert cca_cli.__file__.startswith({copy!r}), cca_cli.__file__
spectrum = np.arange(64, dtype=np.complex64).reshape(8, 8)
origins = np.array([[2, 3]], np.int64)
pupils = np.full((1, 4, 4), 2, np.complex64)
fields = np.zeros((1, 8, 8), np.complex64)
kernels.place_boxes(spectrum, origins, pupils, fields, 0)
expected = np.zeros((8, 8), np.complex64)
expected[2:6, 2:6] = 2 * spectrum[2:6, 3:7]
assert np.array_equal(fields[0], expected)
print(kernels.kernels_name(), kernels._cache)
"""


def _run_read_only(tmp_path: Path, temp_dir: Path) -> subprocess.CompletedProcess:
    """Run :data:`SCRIPT` on a copy of the package whose cache folders numba cannot create."""
    copy = tmp_path / "site"
    shutil.copytree(Path(cca_cli.__file__).parent, copy / "cca_cli", ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "cca_cli" / "optics" / "__pycache__").write_text("a file, where numba would make its folder\n")
    blocked = tmp_path / "home-is-a-file"
    blocked.write_text("")
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "CCA_KERNELS", "PYTHONPATH")}
    env.update(HOME=str(blocked), XDG_CACHE_HOME=str(blocked), TMPDIR=str(temp_dir), PYTHONPATH=str(copy),
               PYTHONDONTWRITEBYTECODE="1")
    return subprocess.run([sys.executable, "-c", SCRIPT.format(copy=str(copy))], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)


def _notes(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("note:")]


def test_read_only_install_caches_in_a_private_temporary_folder(tmp_path):
    temp_dir = tmp_path / "tmp"
    temp_dir.mkdir()
    result = _run_read_only(tmp_path, temp_dir)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["numba", "True"]
    folder = temp_dir / f"cca-numba-{os.getuid()}"
    notes = _notes(result.stderr)
    assert len(notes) == 1 and str(folder) in notes[0], result.stderr
    assert list(folder.rglob("*.nbi"))  # numba's index of the kernels it compiled and kept
    assert folder.stat().st_mode & 0o077 == 0


def test_without_any_writable_folder_the_kernels_compile_uncached(tmp_path):
    temp_dir = tmp_path / "tmp"
    temp_dir.mkdir()
    (temp_dir / f"cca-numba-{os.getuid()}").write_text("not a folder\n")
    result = _run_read_only(tmp_path, temp_dir)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["numba", "False"]
    notes = _notes(result.stderr)
    assert len(notes) == 1 and "compiled in every run" in notes[0], result.stderr


def test_a_temporary_folder_others_may_write_is_not_used(tmp_path):
    # numba loads compiled code from its cache: a folder another user could write into must not be trusted.
    temp_dir = tmp_path / "tmp"
    shared = temp_dir / f"cca-numba-{os.getuid()}"
    shared.mkdir(parents=True)
    shared.chmod(0o777)
    result = _run_read_only(tmp_path, temp_dir)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["numba", "False"]
    assert not list(shared.iterdir())


ORDER_SCRIPT = """
import hashlib, sys
import numpy as np
from cca_cli.optics import kernels

if sys.argv[1] == "after":   # another kernel compiled first, as warm_up does
    kernels._place_boxes_numba(np.zeros((8, 8), np.complex64), np.zeros((1, 2), np.int64),
                               np.zeros((1, 4, 4), np.complex64), np.zeros((1, 8, 8), np.complex64), 0)
rng = np.random.default_rng(3)
spectrum, anchor, velocity = ((rng.standard_normal((96, 96)) + 1j * rng.standard_normal((96, 96))).astype(np.complex64)
                              for _ in range(3))
change, norm = kernels.momentum_step(spectrum, anchor, velocity, 0.3)
print(hashlib.sha256(spectrum.tobytes() + velocity.tobytes()).hexdigest(), repr(change), repr(norm))
"""


def test_the_momentum_kernel_gives_the_same_bits_whatever_was_compiled_before_it(tmp_path):
    """Compiled with fastmath, the momentum step's code (and so its results) depended on whether another kernel
    had been compiled first in the process: two caches of one install gave two results."""
    outputs = []
    for order in ("first", "after"):
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / order))
        run = subprocess.run([sys.executable, "-c", ORDER_SCRIPT, order], env=env, capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
        outputs.append(run.stdout.strip())
    assert outputs[0] == outputs[1]
