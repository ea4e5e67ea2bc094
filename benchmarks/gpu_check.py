"""What the GPU backend does on this machine's GPU: the FFT floor, time per pass, whole runs, CPU agreement.

    python benchmarks/gpu_check.py [--iterations N] [--only PART] [--no-whole-runs] [--skip-cpu] [--json FILE]
                                   [--require-gpu]

Prints, on a machine with CuPy and a CUDA GPU (``pip install 'cca[gpu]'``), in about 3-5 minutes:

1. the GPU FFT floor: one batched ``fft2`` + ``ifft2`` of 441 x 128², 225 x 128², 441 x 84² and
   441 x 32² complex64 fields (the headline sensor grid, the blood smear's, the headline band grid and a
   small one);
2. the headline simulation (``configs/headline.yaml``: 441 captures; it prints their band grid and the
   output grid): the time per pass of the GPU engines (``altmin``, ``momentum``) against the floor of the
   FFTs of one pass on that grid, and whole runs to the config's stopping rule on the GPU and the CPU;
3. the blood smear (``configs/bloodsmear_green.yaml``, 225 LED-array captures, pupil recovered), when
   ``../shared/datasets/fpm-zheng-bloodsmear`` is there (skipped with a note when not); its capped runs
   set ``threads`` to the CPU engine's (at most 4) on both devices, so that the GPU engine visits the
   captures in the CPU engine's order (unset, it takes 8 lanes; the whole runs keep the default);
4. the wide field (``configs/widefield.yaml``: a 2048² frame, 25 captures), recovered whole for
   ``--iterations`` passes on both devices;
5. the same wide field in the config's tiles (81 tiles of 256², each with its pupil), whole runs on the GPU
   (cca's local Dask cluster: a worker per core, as many per GPU as its memory holds) and, unless ``--skip-cpu``,
   on the CPU (a worker per core),
   with the blended objects' agreement.

Each comparison runs the CPU engine (``device: cpu``) and the GPU engine on the same captures and options
for ``--iterations`` passes (default 50, ``tol`` 0) and prints ``max |I_gpu − I_cpu| / max I_cpu`` of the
recovered intensities (``interior_diff_over_peak``: the same, 8 frame pixels in from each edge); the headline's
``capped_momentum`` runs the ``momentum`` engine for those passes on the GPU (the whole ``reconstruct`` call
timed), ``capped_momentum_cpu_order`` on both devices with the CPU engine's threads; the
headline's and the blood smear's GPU runs go twice, and ``gpu_repeat_diff`` is
the same measure between the two (0: the same bits). Without CuPy or without a GPU it prints why on one line and exits 0 (2 with
``--require-gpu``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from cca_cli.optics import backend  # noqa: E402

#: Field stacks whose batched fft2 + ifft2 make the floor: (captures, side).
FLOOR_SHAPES = ((441, 128), (225, 128), (441, 84), (441, 32))
BLOODSMEAR = ROOT.parent / "shared" / "datasets" / "fpm-zheng-bloodsmear"


def gpu_seconds(func, *, repeats: int = 10, warmup: int = 2) -> float:
    """Median wall time of ``func()`` on the GPU (synchronised before and after each call)."""
    cupy = backend.cupy_module()
    for _ in range(warmup):
        func()
    cupy.cuda.Device().synchronize()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        func()
        cupy.cuda.Device().synchronize()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def random_fields(count: int, side: int) -> np.ndarray:
    """``count`` random complex64 fields of ``side`` x ``side`` (on the host)."""
    rng = np.random.default_rng(0)
    shape = (count, side, side)
    return (rng.standard_normal(shape, np.float32) + 1j * rng.standard_normal(shape, np.float32)).astype(np.complex64)


def fft_floor() -> dict:
    """Seconds of one batched fft2 + ifft2 per stack of :data:`FLOOR_SHAPES`."""
    cupy = backend.cupy_module()
    out = {}
    for count, side in FLOOR_SHAPES:
        fields = backend.to_device(random_fields(count, side), cupy)

        def round_trip(fields=fields):
            backend.ifft2(cupy, backend.fft2(cupy, fields))

        out[f"{count}x{side}^2"] = gpu_seconds(round_trip)
        del fields
    return out


def time_per_pass(engine, passes: int = 5) -> float:
    """Median seconds of one ``engine.update()`` (after two warm-up passes)."""
    return gpu_seconds(engine.update, repeats=passes, warmup=2)


#: Frame pixels left out at each edge for the interior agreement (the common reading's residual margin, 3-8 px).
INTERIOR_MARGIN_FRAME_PX = 8


def peak_difference(cpu_object: np.ndarray, gpu_object: np.ndarray, margin: int = 0) -> float:
    """``max |I_gpu − I_cpu| / max I_cpu`` of two recovered fields' intensities, ``margin`` pixels in from each edge."""
    cpu, gpu = np.abs(cpu_object) ** 2, np.abs(gpu_object) ** 2
    inner = (slice(margin, cpu.shape[0] - margin), slice(margin, cpu.shape[1] - margin))
    return float(np.abs(gpu[inner] - cpu[inner]).max() / max(cpu.max(), 1e-30))


def interior_margin(result) -> int:
    """Object pixels that make :data:`INTERIOR_MARGIN_FRAME_PX` frame pixels of a recovery (0 without a frame)."""
    frame = getattr(result, "observed", None)
    if frame is None:
        return 0
    return int(np.ceil(INTERIOR_MARGIN_FRAME_PX * result.object.shape[-1] / np.shape(frame)[-1]))


def run_both(recover, iterations: int, skip_cpu: bool, repeat: bool = False) -> dict:
    """The same recovery on the CPU and the GPU for ``iterations`` passes: times and agreement.

    With ``repeat`` the GPU run goes twice and ``gpu_repeat_diff`` says how far the two differ (0: the same bits).
    """
    out = {}
    start = time.perf_counter()
    gpu = recover("cuda", iterations)
    out["gpu_seconds"] = time.perf_counter() - start
    out["iterations"] = gpu.history.iterations
    if repeat:
        again = recover("cuda", iterations)
        out["gpu_repeat_diff"] = peak_difference(gpu.object, again.object)
    if not skip_cpu:
        start = time.perf_counter()
        cpu = recover("cpu", iterations)
        out["cpu_seconds"] = time.perf_counter() - start
        out["max_diff_over_peak"] = peak_difference(cpu.object, gpu.object)
        # an open frame's edge is held by fewer captures, and rounding grows there first
        out["interior_diff_over_peak"] = peak_difference(cpu.object, gpu.object, interior_margin(cpu))
    return out


def headline(iterations: int, skip_cpu: bool, whole_runs: bool = True) -> dict:
    """Per-pass times against the FFT floor, capped runs on both devices and whole runs, on the headline case."""
    from common import headline_problem

    from cca_cli.engines.batched import BatchedAlternatingMinimization, BatchedMomentum
    from cca_cli.engines.registry import resolve
    from cca_cli.library.data import CaptureSet
    from cca_cli.library.recovery import reconstruct

    cupy = backend.cupy_module()
    problem, simulation = headline_problem()
    m = problem.model.layout.lowres_size
    k = problem.model.n_images
    fields = backend.to_device(random_fields(k, m), cupy)
    floor = gpu_seconds(lambda: backend.ifft2(cupy, backend.fft2(cupy, fields)))
    del fields
    out = {"captures": k, "band_grid": m, "output_grid": problem.model.layout.hires_size, "fft_floor_s": floor}
    for name, engine in (("altmin", BatchedAlternatingMinimization), ("momentum", BatchedMomentum)):
        _, options = resolve(name, "simulation", {"tol": 0.0})
        seconds = time_per_pass(engine(problem, options, xp=cupy))
        out[f"{name}_pass_s"] = seconds
        out[f"{name}_pass_over_floor"] = seconds / floor
    captures = CaptureSet(simulation.intensity, simulation.geometry)
    given = {"tau": 1e-3, "iterations": 1500, "tol": 1e-5}     # configs/headline.yaml's reconstruct section

    def capped(device, passes):
        return reconstruct(captures, engine="altmin", options={**given, "iterations": passes, "tol": 0.0},
                           device=device)

    def whole(device, _):
        return reconstruct(captures, engine="altmin", options=given, device=device)

    from cca_cli.engines.momentum import MAX_THREADS
    from cca_cli.optics import fft

    def momentum(threads):
        def run(device, passes):
            options = {"iterations": passes, "tol": 0.0, **({"threads": threads} if threads else {})}
            return reconstruct(captures, engine="momentum", options=options, device=device)
        return run

    out["capped"] = run_both(capped, iterations, skip_cpu, repeat=True)
    # the GPU's own lanes (its speed), then the CPU engine's thread count on both (the same visiting order)
    out["capped_momentum"] = run_both(momentum(None), iterations, skip_cpu=True)
    out["capped_momentum_cpu_order"] = run_both(momentum(min(fft.cpu_count(), MAX_THREADS)), iterations, skip_cpu)
    if whole_runs:
        out["whole_run"] = run_both(whole, 0, skip_cpu)
    return out


def bloodsmear(iterations: int, skip_cpu: bool, whole_runs: bool = True, captures_file: Path | None = None) -> dict:
    """The blood smear (ingested once, or read from ``captures_file``) on both devices: capped and whole runs."""
    from cca_cli.config.load import load_config
    from cca_cli.engines.momentum import MAX_THREADS
    from cca_cli.io.captures import read_captures
    from cca_cli.optics import fft
    from cca_cli.stages.runner import run_pipeline
    from cca_cli.workflows.recovery import reconstruct_captures

    config = load_config(ROOT / "configs" / "bloodsmear_green.yaml")
    if captures_file is not None:
        path = captures_file
    elif not BLOODSMEAR.is_dir():
        return {"skipped": f"{BLOODSMEAR} is not there (the blood smear lives in ../shared/datasets; or give "
                           f"--bloodsmear-captures FILE from `cca ingest configs/bloodsmear_green_manifest.yaml`)"}
    else:
        folder = Path(tempfile.mkdtemp(prefix="cca-gpu-check-"))
        config = config.model_copy(update={"run": config.run.model_copy(update={"stages": ["ingest"]})})
        run_pipeline(config, folder)
        path = folder / "captures.h5"
    captures = read_captures(path)
    section = config.reconstruct

    # the CPU engine's thread count for both devices: the GPU engine then visits the captures in the same order
    threads = min(fft.cpu_count(), MAX_THREADS)

    def capped(device, passes):
        options = {**section.options, "plateau": 0.0, "threads": threads}
        capped_section = section.model_copy(update={"device": device, "iterations": passes, "tol": 0.0,
                                                    "options": options})
        return reconstruct_captures(captures, capped_section, source=path)

    def whole(device, _):
        return reconstruct_captures(captures, section.model_copy(update={"device": device}), source=path)

    out = {"captures": int(captures.intensity.shape[0]), "capped": run_both(capped, iterations, skip_cpu, repeat=True)}
    if whole_runs:
        # one call, then WHOLE_REPEATS timed: a call's time after the process has made its kernels and plans
        whole("cuda", 0)
        seconds = []
        for _ in range(WHOLE_REPEATS):
            start = time.perf_counter()
            result = whole("cuda", 0)
            seconds.append(time.perf_counter() - start)
        out["whole_run"] = {"gpu_seconds": seconds, "iterations": result.history.iterations}
    return out


#: Whole blood-smear calls timed after a first one.
WHOLE_REPEATS = 3


def widefield(iterations: int, skip_cpu: bool) -> dict:
    """The wide-field frame recovered whole (no tiles) for ``iterations`` passes on both devices."""
    from cca_cli.config.load import load_config
    from cca_cli.library.data import CaptureSet
    from cca_cli.library.recovery import reconstruct
    from cca_cli.stages.simulate import simulate

    config = load_config(ROOT / "configs" / "widefield.yaml")
    simulation = simulate(config)
    captures = CaptureSet(simulation.intensity, simulation.geometry)

    def capped(device, passes):
        return reconstruct(captures, engine="altmin", options={"iterations": passes, "tol": 0.0}, device=device)

    return {"captures": int(captures.intensity.shape[0]), "frame": int(captures.intensity.shape[-1]),
            "capped": run_both(capped, iterations, skip_cpu)}


def tiles(skip_cpu: bool) -> dict:
    """The wide field in the config's tiles, whole runs on the GPU and the CPU: times and agreement."""
    from cca_cli import api
    from cca_cli.config.load import load_config
    from cca_cli.library.data import CaptureSet
    from cca_cli.stages.simulate import simulate

    config = load_config(ROOT / "configs" / "widefield.yaml")
    simulation = simulate(config)
    layout = config.reconstruct.tiles
    from cca_cli.workflows.tiled import local_tile_workers

    out: dict = {"tiles_px": layout.size_px, "overlap_px": layout.overlap_px,
                 "gpu_workers": local_tile_workers(None, None, "cuda")}
    objects = {}
    with tempfile.TemporaryDirectory(prefix="cca-gpu-tiles-") as folder:
        path = api.save(CaptureSet(simulation.intensity, simulation.geometry), Path(folder) / "captures.h5")
        for device in ("cuda",) if skip_cpu else ("cuda", "cpu"):
            start = time.perf_counter()
            result = api.reconstruct_tiles(path, size_px=layout.size_px, overlap_px=layout.overlap_px, device=device)
            out[f"{device}_whole_s"] = time.perf_counter() - start
            out[f"{device}_tiles"] = int(len(result.boxes_px))
            objects[device] = np.abs(result.object) ** 2
    if "cpu" in objects:
        out["diff_over_peak"] = float(np.abs(objects["cuda"] - objects["cpu"]).max() / objects["cpu"].max())
    return out


def _print_section(name: str, result: dict) -> None:
    print(f"\n{name}")
    for key, value in result.items():
        if isinstance(value, dict):
            print(f"  {key}: " + ", ".join(f"{k} {_text(v)}" for k, v in value.items()))
        else:
            print(f"  {key}: {_text(value)}")


def _text(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=50, help="Passes of the capped CPU/GPU comparisons.")
    parser.add_argument("--json", type=Path, help="Also write the results to this JSON file.")
    parser.add_argument("--skip-cpu", action="store_true", help="GPU runs only (no CPU runs, no agreement).")
    parser.add_argument("--no-whole-runs", action="store_true", help="Capped comparisons only (no whole runs).")
    parser.add_argument("--require-gpu", action="store_true", help="Exit 2 (not 0) when there is no GPU.")
    parser.add_argument("--bloodsmear-captures", type=Path, default=None,
                        help="The blood smear already ingested (cca ingest configs/bloodsmear_green_manifest.yaml).")
    parser.add_argument("--only", choices=("floor", "headline", "bloodsmear", "widefield", "tiles"), action="append",
                        help="Run only these parts (repeatable).")
    args = parser.parse_args(argv)
    status = backend.device_status()
    if not status.cuda:
        print(f"no GPU: {status.summary.removeprefix('cpu only: ')}; nothing measured "
              f"({backend.GPU_INSTALL} on a machine with an NVIDIA GPU)")
        return 2 if args.require_gpu else 0
    from cca_cli.optics import fft

    print(f"device: {status.summary}; CPU: {fft.cpu_count()} cores, FFT backend {fft.backend_name()}")
    whole = not args.no_whole_runs
    parts = {"floor": lambda: fft_floor(), "headline": lambda: headline(args.iterations, args.skip_cpu, whole),
             "bloodsmear": lambda: bloodsmear(args.iterations, args.skip_cpu, whole, args.bloodsmear_captures),
             "widefield": lambda: widefield(args.iterations, args.skip_cpu),
             "tiles": lambda: tiles(args.skip_cpu)}
    results = {"device": status.summary}
    for name, part in parts.items():
        if args.only and name not in args.only:
            continue
        start = time.perf_counter()
        try:
            results[name] = part()
        except Exception as exc:  # noqa: BLE001 - one part failing must not hide the others' numbers
            results[name] = {"failed": f"{type(exc).__name__}: {exc}"}
        results[name]["part_seconds"] = time.perf_counter() - start
        _print_section(name, results[name])
        sys.stdout.flush()
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
