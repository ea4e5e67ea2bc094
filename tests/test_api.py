"""The Python API (`import cca_cli as cca`): doctests, the same files as the CLI, light import, clear errors."""

from __future__ import annotations

import doctest
import importlib
import os
import pydoc
import subprocess
import sys

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

import cca_cli as cca
from cca_cli.commands.app import app
from cca_cli.optics import kernels

DOCUMENTED = ["cca_cli.api", "cca_cli.io.export", "cca_cli.report.figures", "cca_cli.report.regions"]


@pytest.mark.parametrize("module", DOCUMENTED)
def test_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0


def test_help_shows_the_api():
    text = pydoc.render_doc(cca, renderer=pydoc.plaintext)
    for name in ("camera_scan", "led_array", "simulate", "reconstruct", "load", "save", "export", "mtf20",
                 "usaf_reading", "rmse", "Reconstruction"):
        assert name in text
    for name in cca.__all__:
        assert getattr(cca, name) is not None
        if name != "__version__":
            assert getattr(cca, name).__doc__, name


def test_importing_the_package_loads_no_numerics():
    code = "import sys, cca_cli; print(sorted(m for m in sys.modules if m.startswith(('cca_cli.', 'numpy'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['cca_cli.version']"


def test_the_command_line_starts_without_dask_or_scipy_fft_and_both_still_import_after():
    """pyfftw would import dask.array and scipy.fft (about 0.65 s) for interfaces cca never uses."""
    code = ("import sys, cca_cli.optics.hidden_imports as h; h.running_the_command(); "
            "import cca_cli.commands.app, cca_cli.optics.fft as fft, cca_cli.stages.reconstruct; "
            "loaded = [m in sys.modules for m in ('dask', 'scipy.fft', 'scipy.fftpack')]; "
            "import dask.array, dask.distributed, scipy.fft; "
            "print(fft.backend_name(), *loaded, dask.array.ones(3).sum().compute(), scipy.fft.fft([1.0, 0.0])[1].real)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[1:] == ["False", "False", "False", "3.0", "1.0"]


def test_a_hidden_package_is_hidden_from_the_importing_thread_only():
    """Other threads import it as usual while another package loads, and this one afterwards."""
    code = """
import sys, threading
from cca_cli.optics.hidden_imports import hidden_in_this_thread
sys.modules.pop("dask", None)
with hidden_in_this_thread(("dask", "scipy.fftpack")):
    try:
        import dask
    except ModuleNotFoundError as error:
        print("hidden here:", "hidden while another package loads" in str(error))
    outcome = []
    thread = threading.Thread(target=lambda: outcome.append(__import__("dask").__name__))
    thread.start()
    thread.join()
    print("other thread:", outcome)
import dask
print("afterwards:", dask.__name__)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split("\n")[:3] == ["hidden here: True", "other thread: ['dask']", "afterwards: dask"]


def test_the_command_runs_numpy_s_blas_on_one_thread_unless_told_otherwise():
    """OpenBLAS's own threads wait actively for cores others hold: 24-31 ms instead of 0.12 ms a small product
    on a busy 2-core machine. The command asks for one thread before numpy loads; a user's setting stands."""
    code = """
import os, sys
from cca_cli.commands import entry
assert "numpy" not in sys.modules   # so the setting reaches numpy's BLAS when it loads
sys.argv = ["cca", "--help"]
try:
    entry.main()
except SystemExit:
    pass
print(*(os.environ.get(name, "-") for name in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")), file=sys.stderr)
"""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "OMP_NUM_THREADS")}

    def seen(extra):
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**env, **extra})
        return run.stderr.split()[-2:]

    assert seen({}) == ["1", "1"]
    assert seen({"OPENBLAS_NUM_THREADS": "3"}) == ["3", "1"]
    assert seen({"OMP_NUM_THREADS": "4"}) == ["-", "-"]     # the user's OpenMP setting is left to reach the BLAS


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_command_keeps_freed_memory_for_the_next_arrays():
    """Arrays of tens of MB made and dropped in turn: with the command's malloc setting their pages are
    reused (a handful of page faults) instead of mapped and zeroed afresh (thousands); a user's own
    MALLOC_* setting is left alone."""
    code = """
import resource, sys
import numpy as np
from cca_cli.commands import entry
kept = entry.keep_freed_memory() if sys.argv[1] == "command" else False

def page_faults(rounds):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for i in range(rounds):
        a = np.ones((5 + i % 3) * 1_000_000, np.float32)
        b = np.ones(3_000_000 + 1000 * i, np.float32)
        del a, b
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

page_faults(3)
print(kept, page_faults(10))
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MALLOC_", "GLIBC_TUNABLES"))}

    def run(mode, extra=None):
        out = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True, check=True,
                             env={**env, **(extra or {})}).stdout.split()
        return out[0] == "True", int(out[1])

    kept, faults = run("command")
    if not kept:
        pytest.skip("not glibc")
    assert faults < 100
    assert run("library")[1] > 20 * max(faults, 10)   # glibc's default: the arrays' pages are mapped anew
    assert run("command", {"MALLOC_ARENA_MAX": "2"})[0] is False


@pytest.mark.skipif(kernels.numba is None, reason="numba is not installed or CCA_KERNELS=numpy")
def test_the_command_leaves_out_numbas_blas_and_a_library_process_keeps_it():
    """The `cca` command skips scipy (pyfftw's scipy interfaces, numba's BLAS: about 0.2 s); a library keeps them."""
    code = """
import sys
from cca_cli.optics import hidden_imports
if sys.argv[1] == "command":
    hidden_imports.running_the_command()
from cca_cli.optics import fftw_plans, kernels
kernels.warm_up()
import numba.np.arraymath
print("scipy.linalg" in sys.modules, numba.np.arraymath._HAVE_BLAS,
      fftw_plans.pyfftw is None or hasattr(fftw_plans.pyfftw.interfaces, "scipy_fft"))
"""
    out = {mode: subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True,
                                check=True).stdout.split() for mode in ("command", "library")}
    assert out["command"][:2] == ["False", "False"] and out["library"] == ["True", "True", "True"]


def test_the_package_and_the_api_list_the_same_names():
    from cca_cli import api

    assert cca.__all__ == ["__version__", *api.__all__]
    assert cca.reconstruct_tiles is api.reconstruct_tiles
    assert set(api.__all__) <= set(dir(cca))


def test_unknown_names_engines_and_options_are_clear():
    with pytest.raises(AttributeError, match="no attribute 'reconstrut'"):
        cca.reconstrut  # noqa: B018
    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    images = np.ones((9, 64, 64), np.float32)
    with pytest.raises(ValueError, match="choose auto or one of altmin, momentum"):
        cca.reconstruct(images, g, engine="altmn")
    with pytest.raises(ValueError, match="unknown option.*taw.*accepted: tau, iterations, tol"):
        cca.reconstruct(images, g, taw=1e-3)
    with pytest.raises(ValueError, match="K = 9 images"):
        cca.reconstruct(images[:4], g)
    with pytest.raises(ValueError, match="grid .* or sar"):
        cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3)


def test_cli_and_api_write_the_same_recon_datasets(tmp_path, write_config, tiny_config_data):
    tiny_config_data["reconstruct"].update(iterations=5)
    config = write_config(tiny_config_data)
    runner = CliRunner()
    assert runner.invoke(app, ["simulate", str(config), "-o", str(tmp_path / "captures.h5"), "-q"]).exit_code == 0
    result = runner.invoke(app, ["reconstruct", str(tmp_path / "captures.h5"), "-o", str(tmp_path / "cli.h5"),
                                 "--config", str(config), "-q"])
    assert result.exit_code == 0, result.output

    section = tiny_config_data["reconstruct"]
    recovery = cca.reconstruct(cca.load(tmp_path / "captures.h5"), engine=section["engine"], tau=section["tau"],
                               iterations=section["iterations"], tol=section["tol"])
    cca.save(recovery, tmp_path / "api.h5")
    with h5py.File(tmp_path / "cli.h5") as cli, h5py.File(tmp_path / "api.h5") as api:
        names = set()
        cli.visititems(lambda name, obj: names.add(name) if isinstance(obj, h5py.Dataset) else None)
        assert {"recon/object", "recon/spectrum", "observed/centre", "truth/object", "geometry/grid_indices"} <= names
        for name in sorted(names - {"history/seconds"}):
            assert name in api, name
            assert np.array_equal(cli[name][()], api[name][()]), name
            assert dict(cli[name].attrs) == dict(api[name].attrs), name
        for key in ("engine", "engine_options", "iterations", "stopped_by", "hires_size", "lowres_size",
                    "pixel_pitch_object_m"):
            assert cli["recon"].attrs[key] == api["recon"].attrs[key], key
    loaded = cca.load(tmp_path / "api.h5")                 # the residuals come back with the result
    assert loaded.fit is not None and loaded.fit.all == recovery.fit.all
    np.testing.assert_array_equal(loaded.fit.per_image, recovery.fit.per_image)
    np.testing.assert_array_equal(loaded.fit.bright_field_mask, recovery.fit.bright_field_mask)


@pytest.fixture(scope="module")
def recorded_led_file(tmp_path_factory):
    """A small LED-array capture saved as recorded frames (open boundary, a known pupil on file)."""
    geometry = cca.led_array(cca.led_grid_sines(5, pitch_m=4e-3, height_m=60e-3), wavelength_m=532e-9,
                             numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6, image_pixels=48)
    chart = cca.resolution_chart(48 * 3, widths=(6, 4, 3, 2)).image
    images = cca.simulate(chart, geometry, snr_db=35)
    pupil = np.exp(0.3j * np.linspace(-1, 1, 16)[None, :] ** 2 * np.ones((16, 1))).astype(np.complex64)
    path = tmp_path_factory.mktemp("recorded") / "raw.h5"
    cca.save(cca.CaptureSet(images, geometry, units="counts/s", boundary="open", initial_pupil=pupil), path)
    return path, pupil


def test_load_keeps_what_a_recorded_file_says(recorded_led_file):
    path, pupil = recorded_led_file
    data = cca.load(path)
    assert data.boundary == "open"
    assert np.array_equal(data.initial_pupil, pupil)
    with pytest.raises(ValueError, match="boundary must be"):
        cca.CaptureSet(data.intensity, data.geometry, boundary="closed")


def test_a_momentum_run_on_many_cores_takes_no_more_threads_than_its_lanes(recorded_led_file, monkeypatch):
    """A momentum run that names no threads takes two for everything (on 16 cores, four were slower)."""
    from cca_cli.engines.momentum import DEFAULT_THREADS
    from cca_cli.engines.problem import PhaseRetrievalProblem
    from cca_cli.optics import fft

    monkeypatch.setattr(fft, "cpu_count", lambda: 16)
    asked = []
    build = PhaseRetrievalProblem.from_sensor_images.__func__
    monkeypatch.setattr(PhaseRetrievalProblem, "from_sensor_images", classmethod(
        lambda cls, *a, **k: asked.append((k["threads"], fft.default_threads())) or build(cls, *a, **k)))
    captures = cca.load(recorded_led_file[0])
    cca.reconstruct(captures, engine="momentum", max_iterations=2)
    cca.reconstruct(captures, engine="momentum", threads=8, max_iterations=2)      # named: as asked
    cca.reconstruct(captures, engine="altmin", max_iterations=2)                   # altmin splits batches further
    assert asked == [(DEFAULT_THREADS, DEFAULT_THREADS), (8, 16), (16, 16)]
    assert fft.default_threads() == 16                                              # the limit ends with the run


def test_api_recovers_recorded_frames_as_the_cli_does(recorded_led_file, tmp_path):
    """Recorded frames get the CLI's guard band and engine defaults through the API too."""
    path, _ = recorded_led_file
    config = tmp_path / "c.yaml"
    config.write_text("reconstruct:\n  engine: momentum\n  iterations: 6\n  options: {threads: 1}\n")
    result = CliRunner().invoke(app, ["reconstruct", str(path), "-o", str(tmp_path / "cli.h5"), "--config",
                                      str(config), "-q"])
    assert result.exit_code == 0, result.output
    api = cca.reconstruct(cca.load(path), engine="momentum", threads=1, max_iterations=6)
    cli = cca.load(tmp_path / "cli.h5")
    assert api.region is not None and api.object.shape == cli.object.shape
    assert api.spectrum.shape == cli.spectrum.shape
    np.testing.assert_allclose(api.spectrum, cli.spectrum, rtol=0, atol=1e-5 * np.abs(cli.spectrum).max())
    # Named outright on recorded LED-array frames, momentum recovers the pupil as engine: auto does.
    assert api.options["pupil_recovery"] == "shared" and api.pupil is not None
    periodic = cca.reconstruct(cca.load(path), engine="momentum", threads=1, max_iterations=6, padding="off")
    assert periodic.region is None
    with pytest.raises(ValueError, match="padding must be"):
        cca.reconstruct(cca.load(path), padding="none")


def test_api_refusals_name_the_argument_first_and_the_fix():
    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, g, snr_db=40)
    with pytest.raises(ValueError, match=r"^engine: 'epry' is not an engine"):
        cca.reconstruct(images, g, engine="epry")
    with pytest.raises(ValueError, match=r"^options: unknown option\(s\) iteration"):
        cca.reconstruct(images, g, engine="momentum", iteration=2)
    with pytest.raises(ValueError, match=r"^geometry: give the capture geometry"):
        cca.reconstruct(images)
    with pytest.raises(ValueError, match=r"np.moveaxis\(intensities, -1, 0\)"):
        cca.reconstruct(np.moveaxis(images, 0, -1), g)
    sines = cca.led_grid_sines(3, pitch_m=4e-3, height_m=60e-3)
    led = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                        image_pixels=48)
    with pytest.raises(ValueError, match="build the geometry with image_pixels = 40"):
        cca.reconstruct(np.ones((9, 40, 40), np.float32), led)


def test_plain_arrays_of_recorded_frames_get_the_guard_band_with_boundary_open():
    sines = cca.led_grid_sines(3, pitch_m=4e-3, height_m=60e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=32)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, geometry, snr_db=None)
    plain = cca.reconstruct(images, geometry, engine="momentum", iterations=2)
    recorded = cca.reconstruct(images, geometry, engine="momentum", iterations=2, boundary="open")
    as_set = cca.reconstruct(cca.CaptureSet(images, geometry, boundary="open"), engine="momentum", iterations=2)
    assert plain.region is None and recorded.region is not None
    np.testing.assert_array_equal(recorded.spectrum, as_set.spectrum)
    with pytest.raises(ValueError, match="^boundary: 'open'"):
        cca.reconstruct(images, geometry, boundary="closed")


def test_a_notebook_s_reconstruction_runs_blas_on_one_thread_unless_its_environment_says_otherwise(monkeypatch):
    """A library process has BLAS threads on every core (the command sets one before numpy loads)."""
    from threadpoolctl import threadpool_info

    from cca_cli.optics.fft import BLAS_THREAD_SETTINGS

    def blas_threads():
        return sorted({pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"})

    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, g, snr_db=40)
    for name in BLAS_THREAD_SETTINGS:
        monkeypatch.delenv(name, raising=False)
    outside = blas_threads()
    assert outside, "numpy's BLAS is seen"
    during = []
    cca.reconstruct(images, g, engine="momentum", iterations=2, callback=lambda record: during.append(blas_threads()))
    assert during == [[1], [1]] and blas_threads() == outside
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")   # the user's own setting (here the same number) is left alone
    with monkeypatch.context() as patch:
        import threadpoolctl

        patch.setattr(threadpoolctl, "threadpool_limits", lambda **kwargs: pytest.fail("BLAS threads were changed"))
        cca.reconstruct(images, g, engine="momentum", iterations=1)


def test_a_callback_that_returns_false_ends_the_run_there():
    g = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=8e-3, grid=3, overlap=0.61)
    images = cca.simulate(cca.resolution_chart(64, widths=(4, 3, 2)).image, g, snr_db=40)
    seen = []
    result = cca.reconstruct(images, g, engine="altmin", iterations=50, tol=0,
                             callback=lambda record: seen.append(record.iteration) or record.iteration < 4)
    assert seen == [1, 2, 3, 4] and result.iterations == 4 and result.stopped_by == "callback"
    full = cca.reconstruct(images, g, engine="altmin", iterations=6, tol=0, callback=lambda record: None)
    assert full.iterations == 6 and full.stopped_by == "cap"


def test_an_led_grid_whose_axis_is_off_its_middle_puts_that_led_on_axis():
    sines = cca.led_grid_sines(10, pitch_m=4e-3, height_m=70e-3, axis_m=(2e-3, -2e-3))
    np.testing.assert_array_equal(sines[4 * 10 + 5], [0.0, 0.0])          # row 4, column 5
    centred = cca.led_grid_sines(10, pitch_m=4e-3, height_m=70e-3)
    assert np.all(centred[4 * 10 + 5] != 0)
    with pytest.raises(ValueError, match=r"^axis_m: give \[x, y\] in metres"):
        cca.led_grid_sines(3, pitch_m=4e-3, height_m=70e-3, axis_m=(0.0,))


def test_per_camera_pupils_of_one_capture_each_are_said_to_be_weakly_determined(caplog, small_camera_array):
    images, array = small_camera_array()
    with caplog.at_level("WARNING", logger="cca"):
        cca.reconstruct(images, array, engine="momentum", pupil_recovery="per_camera", iterations=2)
    assert sum("its one capture only" in r.getMessage() for r in caplog.records) == 1
    caplog.clear()
    with caplog.at_level("WARNING", logger="cca"):
        cca.reconstruct(images, array, engine="momentum", pupil_recovery="shared", iterations=2)
    assert not any("its one capture only" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("build, named", [
    (lambda s: cca.led_array(s, wavelength_m=532e-9, numerical_aperture=0.5, pixel_pitch_object_m=1.845e-6,
                             image_pixels=64), r"^numerical_aperture: an NA of 0.5 .* at most λ/\(2 NA\) = 5.32e-07 m"),
    (lambda s: cca.led_array(s, wavelength_m=550e-6, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=64), r"^wavelength_m is 0.00055 m \(550 µm\).*\(550e-9 for 550 nm\)"),
    (lambda s: cca.led_array(s + 0j, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=64), r"^sin_yx holds complex numbers"),
    (lambda s: cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.075, aperture_diameter_m=2.5,
                               pixel_pitch_m=2e-6, distance_m=50, field_width_m=0.064, grid=5, overlap=0.6),
     r"^aperture_diameter_m: 2.5 m behind a lens of focal_length_m 0.075 m is f/0.03"),
])
def test_optics_no_setup_has_are_refused_naming_the_argument(build, named):
    sines = cca.led_grid_sines(5, pitch_m=4e-3, height_m=60e-3)
    with pytest.raises(ValueError, match=named):
        build(sines)


@pytest.mark.parametrize("data, name, kwargs, named", [
    (np.ones((4, 4)), "a.jpg", {"pixel_size_m": 1e-6}, r"^path .*a\.jpg': its suffix \.jpg names no format"),
    (np.ones((4, 4)), "a.tif", {"pixel_size_m": 125}, r"^pixel_size_m 125: give the object pixel size in metres"),
    (np.ones((4, 4)) + 0j, "a.tif", {"pixel_size_m": 1e-6}, r"^data: give a finite, real 2-D image"),
    (np.full((4, 4), np.nan), "a.tif", {"pixel_size_m": 1e-6}, r"^data: .* some not finite"),
    (np.ones((4, 4)), "a.tif", {"pixel_size_m": 1e-6, "format": "jpeg"}, r"^format 'jpeg': choose one of"),
])
def test_export_refuses_a_bad_argument_with_a_value_error_naming_it(tmp_path, data, name, kwargs, named):
    with pytest.raises(ValueError, match=named):
        cca.export(data, tmp_path / name, **kwargs)
    assert not (tmp_path / name).exists()


def test_sizes_no_machine_holds_are_refused_before_anything_is_allocated(monkeypatch):
    with pytest.raises(ValueError, match=r"^grid 100000 is beyond any array \(at most 1001"):
        cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=0.064, grid=100000)
    with pytest.raises(ValueError, match=r"^sar 1000000.0 needs a grid of \d+ positions per side"):
        cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3, pixel_pitch_m=2e-6,
                        distance_m=50, field_width_m=0.064, sar=1e6)
    wide = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3, pixel_pitch_m=2e-6,
                           distance_m=50, field_width_m=64, grid=3)          # 64 m typed for 64 mm
    with pytest.raises(ValueError, match=r"^geometry: 9 images of 5.12e\+05² px need at least .* of memory"):
        cca.simulate(np.ones((64, 64)), wide)
    monkeypatch.setenv("CCA_MEMORY_LIMIT", "1M")                                   # a small one, over its limit too
    small = cca.camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=18e-3, pixel_pitch_m=2e-6,
                            distance_m=50, field_width_m=0.064, grid=3)
    with pytest.raises(ValueError, match=r"^geometry: 9 images of 512² px need at least 9\.44 MB"):
        cca.simulate(np.ones((64, 64)), small)


def test_an_iteration_record_reads_like_the_history_it_joins():
    from cca_cli.engines.base import IterationRecord

    record = IterationRecord(3, 0.25, 0.01, 1.5)
    assert record["residual"] == record.residual == 0.25 and record["iteration"] == 3
    with pytest.raises(KeyError, match="'misfit': a record holds iteration, residual"):
        record["misfit"]
