"""benchmarks/gpu_check.py on a machine without a GPU: one line saying so, exit 0 (2 when a GPU is required)."""

import subprocess
import sys
from pathlib import Path

import pytest

from cca_cli.optics import backend

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_check.py"


@pytest.mark.skipif(backend.device_status().cuda, reason="a GPU is here: the check would measure it")
def test_gpu_check_says_there_is_no_gpu_and_exits_cleanly():
    done = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("no GPU: ") and "pip install 'cca[gpu]'" in lines[0]
    assert "Traceback" not in done.stderr
    required = subprocess.run([sys.executable, str(SCRIPT), "--require-gpu"], capture_output=True, text=True,
                              timeout=120)
    assert required.returncode == 2 and required.stdout.startswith("no GPU: ")
