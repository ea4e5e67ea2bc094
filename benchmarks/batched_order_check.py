"""How far the GPU engine's arithmetic drifts from the CPU engine's, without a GPU.

    python benchmarks/batched_order_check.py blood_raw.h5 [--passes 5,20,50] [--threads 4]

Runs the blood smear's default (``configs/bloodsmear_green.yaml``) capped at each number of passes twice: with
the CPU engine and with the batched (GPU) engine on numpy arrays, both visiting the captures in the CPU engine's
order for ``--threads``. Prints ``max |ΔI| / max I`` of the recovered intensities over the whole frame and 11 frame
px in, and the largest relative difference of the two runs' misfits over the passes. What it separates: a
difference that grows with the passes while the misfits agree is the batched engine's order of operations
(rounding, grown by the momentum), not the GPU; ``gpu_check.py`` reads the same on a GPU.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cca_cli.config.load import load_config  # noqa: E402
from cca_cli.io.captures import read_captures  # noqa: E402
from cca_cli.library import recovery  # noqa: E402
from cca_cli.optics import backend  # noqa: E402
from cca_cli.workflows.recovery import reconstruct_captures  # noqa: E402

INTERIOR_FRAME_PX = 11


def run(captures, path: Path, passes: int, threads: int, batched: bool):
    """The blood smear's default for ``passes`` passes: the CPU engine, or the batched one on numpy."""
    section = load_config(ROOT / "configs" / "bloodsmear_green.yaml").reconstruct
    options = {**section.options, "plateau": 0.0, "threads": threads}
    capped = section.model_copy(update={"device": "cpu", "iterations": passes, "tol": 0.0, "options": options})
    if not batched:
        return reconstruct_captures(captures, capped, source=path)
    # the batched engine, as device cuda builds it, with numpy as its array module
    device, module = recovery.engine_device, backend.array_module
    recovery.engine_device = lambda *_: "cuda"
    backend.array_module = lambda _: np
    try:
        return reconstruct_captures(captures, capped, source=path)
    finally:
        recovery.engine_device, backend.array_module = device, module


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("captures", type=Path,
                        help="The ingested blood smear (cca ingest configs/bloodsmear_green_manifest.yaml).")
    parser.add_argument("--passes", default="5,20,50", help="Comma-separated pass counts.")
    parser.add_argument("--threads", type=int, default=4, help="The CPU engine's threads (its visiting order).")
    args = parser.parse_args(argv)
    captures = read_captures(args.captures)
    print("passes  max|dI|/peak  11 frame px in  max misfit difference")
    for passes in (int(p) for p in args.passes.split(",")):
        cpu = run(captures, args.captures, passes, args.threads, batched=False)
        gpu_like = run(captures, args.captures, passes, args.threads, batched=True)
        a, b = np.abs(cpu.object) ** 2, np.abs(gpu_like.object) ** 2
        margin = int(np.ceil(INTERIOR_FRAME_PX * a.shape[-1] / np.shape(cpu.observed)[-1]))
        inner = (slice(margin, -margin), slice(margin, -margin))
        misfit = max(abs(x.residual - y.residual) / x.residual
                     for x, y in zip(cpu.history.records, gpu_like.history.records))
        print(f"{passes:6d}  {np.abs(a - b).max() / a.max():12.2e}  {np.abs(a - b)[inner].max() / a.max():14.2e}"
              f"  {misfit:21.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
