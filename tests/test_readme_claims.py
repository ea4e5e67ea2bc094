"""Claims of the README that the code decides: they must be what cca prints and does today."""

from pathlib import Path

import numpy as np

from cca_cli.commands.info import derived_lines
from cca_cli.config.load import load_config
from cca_cli.report.summary import derived_quantities
from cca_cli.stages.simulate import simulation_geometry
from cca_cli.library.simulation import simulation_layout

README = (Path(__file__).resolve().parents[1] / "README.md").read_text()


def test_the_headlines_derived_quantities_are_what_cca_prints():
    config = load_config()
    geometry, sensor = simulation_geometry(config)
    layout = simulation_layout(geometry)
    derived = derived_quantities(geometry, sensor_pixels=sensor, hires_size=layout.hires_size,
                                 lowres_size=layout.lowres_size)
    block = "\n".join(["derived quantities:", *derived_lines(derived)])
    assert block in README, block


def test_the_headlines_band_grid_is_what_the_readme_says():
    layout = simulation_layout(simulation_geometry(load_config())[0])
    assert f"{layout.lowres_size} px band grid per capture" in README
    assert f"{layout.lowres_size}² for the headline" in README
    assert np.isclose(layout.pupil_radius_px, 20.95, atol=0.005)


def _readme_block(marker: str) -> str:
    """The fenced block after ``<!-- led-lab-example: NAME -->`` in the README."""
    start = README.index(f"<!-- led-lab-example: {marker}")
    fence = README.index("```", start)
    body = README.index("\n", fence) + 1
    return README[body:README.index("```", body)]


def test_the_readme_s_led_array_lab_example_ingests_and_reconstructs_as_written(tmp_path):
    from typer.testing import CliRunner

    import cca_cli as cca
    from cca_cli.commands.app import app
    from cca_cli.io.images import write_image

    (tmp_path / "lab.yaml").write_text(_readme_block("lab.yaml"))
    shown = _readme_block("leds.csv").strip().splitlines()
    assert shown[0] == "path,row,col,exposure_ms"
    # the whole table the example's rows come from: 9 x 9 LEDs, the bright field at a tenth of the exposure
    sines = cca.led_grid_sines(9, pitch_m=4e-3, height_m=70e-3)
    geometry = cca.led_array(sines, wavelength_m=530e-9, numerical_aperture=0.1, pixel_pitch_object_m=1.625e-6,
                             image_pixels=48)
    images = cca.simulate(cca.resolution_chart(144, widths=(6, 4, 3, 2)).image, geometry, snr_db=40)
    bright = np.hypot(*geometry.spectrum_centres_yx_px.T) < geometry.pupil_radius_px
    rows = ["path,row,col,exposure_ms"]
    for i in range(81):
        exposure = 20 if bright[i] else 200
        write_image(tmp_path / f"img_{i:03d}.tif",
                    np.clip(np.rint(100 + images[i] / images.max() * 40000 * exposure / 200), 0, 65535).astype(np.uint16),
                    bit_depth=16)
        rows.append(f"img_{i:03d}.tif,{i // 9},{i % 9},{exposure}")
    assert all(line in rows for line in shown[1:]), "the README's rows are rows of this table"
    (tmp_path / "leds.csv").write_text("\n".join(rows) + "\n")
    runner = CliRunner()
    for argv in (["ingest", "lab.yaml", "-o", "raw.h5"], ["reconstruct", "raw.h5", "-o", "recon.h5"],
                 ["report", "recon.h5", "-o", "report"]):
        quiet = ["-q"] if argv[0] != "report" else []
        result = runner.invoke(app, [*argv[:1], str(tmp_path / argv[1]), argv[2], str(tmp_path / argv[3]), *quiet])
        assert result.exit_code == 0, (argv, result.output)
        assert "warning" not in result.output, result.output
    recovered = cca.load(tmp_path / "recon.h5")
    assert recovered.fit.all < 0.1


def _flat(text: str) -> str:
    """``text`` with every run of white space (line breaks included) as one space."""
    return " ".join(text.split())


def test_the_exit_codes_the_readme_lists_are_the_errors_codes():
    from cca_cli.errors import ConfigError, InputError, OutputError, ResourceError, RunLockedError

    text = _flat(README)
    assert (f"config or command line {ConfigError.exit_code}, input file {InputError.exit_code}, "
            f"output {OutputError.exit_code} (an unwritable output folder too), memory or disk "
            f"{ResourceError.exit_code}, a run folder or output that another cca command is writing "
            f"{RunLockedError.exit_code}, Ctrl-C 130") in text
    assert "in use 6" not in text


def test_the_python_section_names_the_force_that_save_and_export_take(tmp_path, small_camera_array):
    import inspect

    import pytest

    import cca_cli as cca
    from cca_cli.errors import OutputExistsError

    section = _flat(README[README.index("## Python\n"):README.index("## Config format\n")])
    assert "`OutputExistsError`" in section and "pass `force=True`" in section
    for function in (cca.save, cca.export):
        assert inspect.signature(function).parameters["force"].default is False
    captures = cca.CaptureSet(*small_camera_array())
    path = cca.save(captures, tmp_path / "captures.h5")
    with pytest.raises(OutputExistsError):   # the example run a second time
        cca.save(captures, path)
    assert cca.save(captures, path, force=True) == path


def test_the_readme_s_python_versions_are_pyproject_s():
    import re

    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    oldest = re.search(r'requires-python = ">=(3\.\d+)"', pyproject).group(1)
    ci = (Path(__file__).resolve().parents[1] / ".ci" / "run").read_text()
    tested = sorted(set(re.findall(r"find_python (3\.\d+)", ci)), key=lambda v: int(v.split(".")[1]))
    assert f"(Python {oldest} or newer; CI tests {' and '.join(tested)})" in _flat(README)
    assert not re.search(r"Python 3\.\d+ to 3\.\d+", README)   # no upper bound that pyproject does not state
