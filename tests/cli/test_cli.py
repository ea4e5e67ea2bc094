"""The `cca` command line: stage commands, `run`, `info`, and one-line errors with non-zero exits."""

import json

import h5py
import pytest
from typer.testing import CliRunner

from cca_cli.commands.app import app


def _out(result) -> str:
    """stdout with rich's line wrapping undone."""
    return " ".join(result.stdout.split())


@pytest.fixture
def runner():
    return CliRunner()


def _error_line(result) -> str:
    """The single line a failing command prints (stderr), asserting it is one line."""
    assert result.exit_code != 0, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.output
    return lines[0]


@pytest.fixture
def small_config(write_config, tiny_config_data):
    tiny_config_data["report"]["figures"] = False
    return write_config(tiny_config_data)


def test_the_same_command_started_twice_is_refused_while_the_first_writes(runner, small_config, tmp_path):
    from cca_cli.io.lock import output_lock, output_lock_path

    captures, recon = tmp_path / "captures.h5", tmp_path / "recon.h5"
    assert runner.invoke(app, ["simulate", str(small_config), "-o", str(captures), "--quiet"]).exit_code == 0
    command = ["reconstruct", str(captures), "-o", str(recon), "--iterations", "3", "--quiet"]
    with output_lock(recon):          # the first command, still running
        result = runner.invoke(app, command)
        assert result.exit_code == 6
        line = _error_line(result)
        assert line.startswith(f"error: {recon}: another cca command (pid ") and "is writing it; wait" in line
        assert not recon.exists()
    assert not output_lock_path(recon).exists()
    output_lock_path(recon).write_text(json.dumps({"pid": 4_194_309}))   # left by a killed command
    result = runner.invoke(app, command)
    assert result.exit_code == 0, result.output
    assert recon.is_file() and not output_lock_path(recon).exists()


def test_help_lists_the_commands(runner):
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("run", "simulate", "reconstruct", "report", "info"):
        assert command in result.stdout
    assert runner.invoke(app, ["--version"]).stdout.startswith("cca ")


def test_simulate_reconstruct_report_info(runner, small_config, tmp_path):
    captures, recon, report = tmp_path / "captures.h5", tmp_path / "recon.h5", tmp_path / "report"
    result = runner.invoke(app, ["simulate", str(small_config), "-o", str(captures), "--quiet"])
    assert result.exit_code == 0, result.output
    assert captures.is_file() and "25 captures" in _out(result)
    result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(recon), "--iterations", "5", "--quiet"])
    assert result.exit_code == 0, result.output
    with h5py.File(recon, "r") as handle:
        assert handle["recon"].attrs["iterations"] == 5
        assert handle.attrs["stage"] == "reconstruct"
    assert "5 iterations" in _out(result)
    result = runner.invoke(app, ["report", str(recon), "-o", str(report)])
    assert result.exit_code == 0, result.output
    summary = json.loads((report / "report.json").read_text())
    assert summary["iterations"] == 5 and summary["n_images"] == 25
    assert "MTF20" in _out(result)
    result = runner.invoke(app, ["info", str(recon)])
    assert result.exit_code == 0, result.output
    assert "/recon/spectrum" in _out(result) and "stage reconstruct" in _out(result)
    assert "[√irradiance · px]" in _out(result)


def test_reconstruct_takes_options_from_a_config(runner, small_config, tmp_path):
    captures, recon = tmp_path / "captures.h5", tmp_path / "recon.h5"
    assert runner.invoke(app, ["simulate", str(small_config), "-o", str(captures), "-q"]).exit_code == 0
    result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(recon), "-c", str(small_config),
                                 "--tau", "0.01", "-q"])
    assert result.exit_code == 0, result.output
    with h5py.File(recon, "r") as handle:
        assert handle["recon"].attrs["iterations"] == 30
        assert json.loads(handle["recon"].attrs["engine_options"])["tau"] == pytest.approx(0.01)


def test_run_end_to_end_and_resume(runner, small_config, tmp_path):
    config = small_config
    out = tmp_path / "runs"
    result = runner.invoke(app, ["run", str(config), "--out-dir", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    assert (out / "captures.h5").is_file() and (out / "recon.h5").is_file()
    report = json.loads((out / "report" / "report.json").read_text())
    assert report["mtf20_recovered_px"] < report["mtf20_observed_px"]
    assert "synthetic aperture ratio" in _out(result)
    again = runner.invoke(app, ["run", str(config), "--out-dir", str(out), "--quiet"])
    assert again.exit_code == 0, again.output
    assert _out(again).count("skipped") == 3


@pytest.mark.parametrize(
    ("section", "key", "value", "expected"),
    [
        ("array", "gird", 5, "array.gird"),
        ("optics", "distance_m", "far", "optics.distance_m"),
        ("reconstruct", "engine", "magic", "reconstruct.engine"),
    ],
)
def test_bad_config_is_one_line_naming_file_and_key(runner, write_config, tiny_config_data, tmp_path, section, key,
                                                    value, expected):
    tiny_config_data[section][key] = value
    config = write_config(tiny_config_data, name="bad.yaml")
    for args in (["simulate", str(config), "-o", str(tmp_path / "c.h5"), "-q"],
                 ["run", str(config), "--out-dir", str(tmp_path / "runs"), "-q"]):
        result = runner.invoke(app, args)
        line = _error_line(result)
        assert result.exit_code == 2
        assert "bad.yaml" in line and expected in line
    assert not (tmp_path / "c.h5").exists() and not (tmp_path / "runs" / "captures.h5").exists()


def test_missing_and_non_hdf5_inputs(runner, tmp_path):
    missing = tmp_path / "missing.h5"
    result = runner.invoke(app, ["reconstruct", str(missing), "-o", str(tmp_path / "r.h5"), "-q"])
    assert "missing.h5" in _error_line(result) and result.exit_code == 3
    text = tmp_path / "notes.h5"
    text.write_text("hello")
    for args in (["reconstruct", str(text), "-o", str(tmp_path / "r.h5"), "-q"],
                 ["report", str(text), "-o", str(tmp_path / "rep")],
                 ["info", str(text)]):
        result = runner.invoke(app, args)
        line = _error_line(result)
        assert "notes.h5" in line and "HDF5" in line
    assert not (tmp_path / "r.h5").exists() and not (tmp_path / "rep").exists()
    result = runner.invoke(app, ["simulate", str(tmp_path / "nope.yaml"), "-q"])
    assert "nope.yaml" in _error_line(result)


def test_existing_output_without_force_is_refused_and_kept(runner, small_config, tmp_path):
    captures = tmp_path / "captures.h5"
    assert runner.invoke(app, ["simulate", str(small_config), "-o", str(captures), "-q"]).exit_code == 0
    before, mtime = captures.read_bytes(), captures.stat().st_mtime_ns
    result = runner.invoke(app, ["simulate", str(small_config), "-o", str(captures), "-q"])
    line = _error_line(result)
    assert result.exit_code == 4 and "captures.h5" in line and "--force" in line
    assert captures.read_bytes() == before and captures.stat().st_mtime_ns == mtime
    recon = tmp_path / "recon.h5"
    recon.write_bytes(b"precious")
    result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(recon), "--iterations", "2", "-q"])
    assert "recon.h5" in _error_line(result)
    assert recon.read_bytes() == b"precious"
    result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(recon), "--iterations", "2", "-q",
                                 "--force"])
    assert "recon.h5" in _error_line(result) and result.exit_code == 4  # --force never replaces what cca did not write
    assert recon.read_bytes() == b"precious"
    recon.unlink()
    for iterations in ("3", "2"):  # a file cca wrote is replaced with --force
        result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(recon), "--iterations", iterations, "-q",
                                     "--force"])
        assert result.exit_code == 0, result.output
    with h5py.File(recon, "r") as handle:
        assert handle["recon"].attrs["iterations"] == 2


def test_bad_option_values_are_one_line_errors(runner, small_config, tmp_path):
    captures = tmp_path / "captures.h5"
    assert runner.invoke(app, ["simulate", str(small_config), "-o", str(captures), "-q"]).exit_code == 0
    result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(tmp_path / "r.h5"), "--engine", "magic",
                                 "-q"])
    line = _error_line(result)
    assert "--engine" in line and "magic" in line and "altmin" in line
    result = runner.invoke(app, ["reconstruct", str(captures), "-o", str(tmp_path / "r.h5"), "--tau", "-1", "-q"])
    assert "--tau" in _error_line(result)
    assert not (tmp_path / "r.h5").exists()


def test_starting_the_command_line_loads_no_stage():
    """`cca reconstruct` must not pay for the report's, registration's and ingest's modules (nor the engines'
    before it runs): each command imports its own stage when it starts."""
    import subprocess
    import sys

    watched = ("cca_cli.stages.", "cca_cli.engines", "cca_cli.optics.fft", "cca_cli.optics.kernels",
               "cca_cli.registration", "cca_cli.report", "cca_cli.metrics", "cv2", "numba")
    code = ("import json, sys, cca_cli.commands.app; "
            f"print(json.dumps(sorted(m for m in sys.modules if m.startswith({watched!r}))))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded = set(json.loads(run.stdout))
    # the config's engine names and options, and what every stage command checks before it starts
    allowed = {"cca_cli.engines", "cca_cli.engines.registry", "cca_cli.engines.options", "cca_cli.engines.presets",
               "cca_cli.stages.footprint", "cca_cli.stages.progress", "cca_cli.stages.provenance"}
    assert loaded <= allowed, sorted(loaded - allowed)


def test_the_command_line_leaves_no_image_library_objects_for_its_leak_check():
    """The console script skips the collector's passes at exit, except when OpenImageIO is loaded: its
    objects in reference cycles would then stay alive, and its bindings print a warning for each."""
    import subprocess
    import sys

    code = ("import sys, OpenImageIO; from cca_cli.commands.entry import main\n"
            "cycle = [OpenImageIO.ImageSpec(4, 4, 1, 'float')]; cycle.append(cycle); del cycle\n"
            "sys.argv = ['cca', '--version']; main()")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "leaked" not in run.stderr, run.stderr


def test_the_command_line_skips_the_collectors_passes_at_exit_without_the_image_library():
    import subprocess
    import sys

    code = ("import gc, sys; from cca_cli.commands.entry import main\n"
            "sys.argv = ['cca', '--version']\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            "print(gc.get_freeze_count() > 0, 'OpenImageIO' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split()[-2:] == ["True", "False"], run.stdout


def test_a_recovery_that_explains_the_captures_poorly_is_one_warning():
    """A data residual near 1 (a unit slip in the positions, say) is named with what to check; a good fit is not."""
    import types

    from cca_cli.commands.console import POOR_FIT, poor_fit_warning

    def recovery(residual):
        return types.SimpleNamespace(fit=types.SimpleNamespace(all=residual))

    assert poor_fit_warning(recovery(0.08)) is None and poor_fit_warning(recovery(float("nan"))) is None
    text = poor_fit_warning(recovery(0.96))
    assert "0.96" in text and "positions and their unit" in text and POOR_FIT < 0.96
    tiles = types.SimpleNamespace(results=[types.SimpleNamespace(residual={"all": v}) for v in (0.9, 0.8, 0.1)])
    assert "0.80" in poor_fit_warning(tiles)


def test_an_error_before_any_progress_is_the_only_line_on_stderr(tmp_path):
    """A command that fails before its first progress event prints its error line and nothing else (no empty
    line from a progress display that never showed a bar)."""
    import subprocess
    import sys

    import cv2
    import numpy as np

    for i in range(2):
        cv2.imwrite(str(tmp_path / f"led{i}.png"), np.full((16, 16), 1000 + i, np.uint16))
    (tmp_path / "leds.csv").write_text("path,kx_norm,ky_norm\nled0.png,0,0\nled1.png,0.05,0\nled0.png,0,0.05\n")
    manifest = tmp_path / "lab.yaml"
    manifest.write_text("illumination: {wavelength_m: 5e-7, numerical_aperture: 0.1, pixel_pitch_object_m: 1e-6}\n"
                        "images_csv: leds.csv\n")   # one file at two positions: refused once the images are grouped
    proc = subprocess.run([sys.executable, "-m", "cca_cli", "ingest", str(manifest), "-o", str(tmp_path / "raw.h5")],
                          capture_output=True, text=True)
    assert proc.returncode != 0
    assert proc.stderr.splitlines()[0].startswith("error:"), repr(proc.stderr)
    assert "lines 2 and 4 of leds.csv both name the same file led0.png" in proc.stderr   # the table's own lines


def test_cca_info_of_recorded_led_captures_shows_the_grid_reconstruct_uses_and_no_camera_stand_ins(tmp_path):
    """An LED array's geometry line leaves out the camera-array stand-ins; recorded frames get the guard-band grid."""
    import cca_cli as cca

    sines = cca.led_grid_sines(5, pitch_m=4e-3, height_m=60e-3)
    geometry = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                             image_pixels=48)
    images = cca.simulate(cca.resolution_chart(96, widths=(4, 3, 2)).image, geometry, snr_db=None)
    cropped = cca.led_array(sines, wavelength_m=532e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.845e-6,
                            image_pixels=40)
    recorded = cca.CaptureSet(images[:, 8:40, 4:44], geometry=cropped, boundary="open")
    path = cca.save(recorded, tmp_path / "raw.h5")
    result = CliRunner().invoke(app, ["info", str(path)])
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    geometry_line = next(line for line in result.output.splitlines() if line.startswith("geometry:"))
    assert "kind=led_array" in geometry_line and "focal_length_m" not in geometry_line and "overlap" not in geometry_line
    assert "(1.22·λ/NA)" in text and "spot at sensor" not in text
    assert "reconstruct recorded 40 x 32 px frames on a" in text and "with a guard band" in text
    recon = cca.reconstruct(recorded, iterations=2)
    assert f"output grid {recon.spectrum.shape[-1]} x {recon.spectrum.shape[-1]} px" in text


def test_an_mtf20_at_the_chart_s_finest_bar_reads_as_a_bound():
    from cca_cli.commands.console import summary_table

    summary = {"mtf20_observed_px": 4, "mtf20_recovered_px": 1, "resolution_gain": 4.0,
               "mtf20_at_finest_bar": {"observed": False, "recovered": True}}
    cells = dict(zip((str(c) for c in summary_table(summary).columns[0].cells),
                     (str(c) for c in summary_table(summary).columns[1].cells)))
    assert cells["MTF20 recovered (px)"] == "≤ 1 (the chart's finest bar)"
    assert cells["MTF20 observed (px)"] == "4" and cells["resolution gain"] == "≥ 4.00"


@pytest.mark.parametrize("residual, marked", [(0.11, False), (0.36, True)])
def test_the_report_gives_the_fit_before_the_gains_and_marks_gains_read_from_a_poor_fit(residual, marked):
    from cca_cli.commands.console import summary_table

    summary = {"seconds": 1.0, "spot_size_object_m": 1e-5, "residual_all": residual, "sharpness_gain": 3.74,
               "energy_beyond_cutoff_recovered": 0.28, "dropped_captures": [49]}
    table = summary_table(summary)
    labels = [str(c) for c in table.columns[0].cells]
    cells = dict(zip(labels, (str(c) for c in table.columns[1].cells)))
    assert labels.index("data residual, all images") < labels.index("spot size at object") \
        < labels.index("sharpness gain (reach)")
    assert (cells["sharpness gain (reach)"] == "3.74 (from a poor fit: artefacts raise it)") is marked
    assert cells["sharpness gain (reach)"].startswith("3.74")
    assert cells["captures left out, dead or unlit (images)"] == "49"


def test_a_report_of_a_set_without_dark_field_is_valid_json_and_shows_no_nan(tmp_path, small_camera_array):
    import json

    import cca_cli as cca
    from cca_cli.commands.console import summary_table

    images, array = small_camera_array(first_id=1)   # the lab numbers its cameras from 1
    result = cca.reconstruct(images, array, engine="momentum", pupil_recovery="per_camera", iterations=2)
    cca.save(result, tmp_path / "recon.h5")
    run = CliRunner().invoke(app, ["report", str(tmp_path / "recon.h5"), "-o", str(tmp_path / "report")])
    assert run.exit_code == 0, run.output
    text = (tmp_path / "report" / "report.json").read_text()
    document = json.loads(text, parse_constant=lambda name: pytest.fail(f"report.json holds {name}"))
    assert document["camera_ids"] == list(range(1, 10)) and document["zernike_waves_camera"] == 1
    assert len(document["zernike_waves_per_camera"]) == 9
    cells = dict(zip((str(c) for c in summary_table(document).columns[0].cells),
                     (str(c) for c in summary_table(document).columns[1].cells)))
    assert "nan" not in " ".join(cells.values())
    assert "largest pupil aberrations (waves RMS, camera 1)" in cells
