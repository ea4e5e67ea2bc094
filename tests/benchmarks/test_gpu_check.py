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


def test_the_interior_agreement_leaves_out_the_frame_s_edge():
    sys.path.insert(0, str(SCRIPT.parent))
    import gpu_check
    from types import SimpleNamespace

    import numpy as np

    cpu = np.ones((128, 128), np.complex64)
    gpu = cpu.copy()
    gpu[2, 30] = np.sqrt(2)        # |ΔI| = 1 at the edge
    gpu[64, 64] = np.sqrt(1.01)    # 0.01 in the middle
    assert gpu_check.peak_difference(cpu, gpu) == pytest.approx(1.0)
    recovery = SimpleNamespace(object=cpu, observed=np.ones((32, 32)))   # 4 object px a frame px
    margin = gpu_check.interior_margin(recovery)
    assert margin == 4 * gpu_check.INTERIOR_MARGIN_FRAME_PX
    assert gpu_check.peak_difference(cpu, gpu, margin) == pytest.approx(0.01, rel=1e-4)
    assert gpu_check.interior_margin(SimpleNamespace(object=cpu, observed=None)) == 0
