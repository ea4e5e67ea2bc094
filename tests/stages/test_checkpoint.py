"""Reconstruction checkpoints: a killed run resumes where it was; --init starts from an earlier recon.h5."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from cca_cli.stages import reconstruct as reconstruct_stage
from cca_cli.stages import simulate as simulate_stage
from cca_cli.stages.runner import pick_sections, stage_provenance


class _Stop(Exception):
    """Stands for an interruption between two iterations."""


@pytest.fixture(scope="module")
def tiny(tiny_run_config, tmp_path_factory):
    """The tiny config's captures (read only) and its reconstruct section."""
    config = tiny_run_config
    captures = tmp_path_factory.mktemp("captures") / "captures.h5"
    simulate_stage.run(config, captures, provenance=stage_provenance("simulate", pick_sections(config, ("simulate",))))
    return captures, config.reconstruct


def _run(captures: Path, section, output: Path, **kwargs):
    provenance = stage_provenance("reconstruct", {"reconstruct": section}, [captures])
    return reconstruct_stage.run(captures, section, output, provenance=provenance, **kwargs)


def _interrupted(captures: Path, section, output: Path) -> Path:
    """Run until a checkpoint exists, then stop between two iterations (as Ctrl-C would); return the checkpoint."""
    checkpoint = output.with_name(output.name + ".checkpoint")

    def progress(event):
        if checkpoint.exists():
            raise _Stop

    with pytest.raises(_Stop):
        _run(captures, section, output, progress=progress)
    assert checkpoint.is_file() and not output.exists()
    return checkpoint


def _spectrum(path: Path) -> np.ndarray:
    with h5py.File(path, "r") as handle:
        return np.asarray(handle["/recon/spectrum"])


@pytest.mark.slow
def test_kill_9_mid_run_then_the_rerun_resumes_from_the_checkpoint_and_matches_an_uninterrupted_run(tiny, tmp_path):
    captures, section = tiny
    iterations = 1000
    args = [sys.executable, "-m", "cca_cli", "reconstruct", str(captures), "-o", str(tmp_path / "recon.h5"),
            "--engine", "altmin", "--iterations", str(iterations), "--tol", "0", "--checkpoint-every", "5", "--quiet"]
    env = {**os.environ, "COLUMNS": "250"}
    checkpoint = tmp_path / "recon.h5.checkpoint"
    proc = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not checkpoint.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL, "the run ended before it wrote a checkpoint"
    assert checkpoint.is_file() and not (tmp_path / "recon.h5").exists()

    resumed = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert resumed.returncode == 0, resumed.stderr
    note = [line for line in resumed.stderr.splitlines() if "resuming from iteration" in line]
    assert len(note) == 1, resumed.stderr
    start = int(note[0].split("resuming from iteration")[1].split()[0])
    assert 5 <= start < iterations
    assert not checkpoint.exists(), "the checkpoint outlived the finished output"

    plain = section.model_copy(update={"engine": "altmin", "iterations": iterations, "tol": 0.0,
                                       "checkpoint_every": 0})
    _run(captures, plain, tmp_path / "plain.h5")
    with h5py.File(tmp_path / "recon.h5", "r") as handle:
        assert handle["/history/residual"].shape == (iterations,)
        assert handle["recon"].attrs["iterations"] == iterations
        seconds = np.asarray(handle["/history/seconds"])
        total = float(handle["recon"].attrs["seconds"])
    assert np.all(np.diff(seconds) >= 0), "wall time restarted at the resume"
    assert total >= seconds[-1] > seconds[start - 1] > 0, "the run's time counts the iterations before the resume"
    got, want = _spectrum(tmp_path / "recon.h5"), _spectrum(tmp_path / "plain.h5")
    assert np.linalg.norm(got - want) <= 1e-4 * np.linalg.norm(want)


@pytest.mark.parametrize("options", [{}, {"pupil_recovery": "shared", "pupil_model": "full", "brightness": True,
                                      "position_refinement": "per_image", "pupil_momentum": 0.3}],
                         ids=["plain", "calibrating"])
def test_momentum_resumes_with_its_velocity_and_ends_as_well_as_an_uninterrupted_run(tiny, tmp_path, caplog, options):
    captures, section = tiny
    section = section.model_copy(update={"engine": "momentum", "iterations": 40, "tol": 0.0, "checkpoint_every": 3,
                                         "options": options})
    _interrupted(captures, section, tmp_path / "recon.h5")
    with caplog.at_level(logging.WARNING, logger="cca"):
        resumed = _run(captures, section, tmp_path / "recon.h5")
    assert "resuming from iteration" in caplog.text
    first = resumed.history.records[0]
    assert first.iteration == 1 and resumed.history.iterations == 40
    plain = _run(captures, section.model_copy(update={"checkpoint_every": 0}), tmp_path / "plain.h5")
    assert resumed.history.records[-1].residual <= 1.05 * plain.history.records[-1].residual


def test_a_checkpoint_of_other_options_is_ignored_with_a_note_and_the_run_starts_afresh(tiny, tmp_path, caplog):
    captures, section = tiny
    section = section.model_copy(update={"iterations": 60, "checkpoint_every": 2})
    _interrupted(captures, section, tmp_path / "recon.h5")
    other = section.model_copy(update={"tau": 1e-2})
    with caplog.at_level(logging.WARNING, logger="cca"):
        recovery = _run(captures, other, tmp_path / "recon.h5")
    assert "belongs to other captures or reconstruct options" in caplog.text
    assert "resuming" not in caplog.text
    fresh = _run(captures, other.model_copy(update={"checkpoint_every": 0}), tmp_path / "fresh.h5")
    assert recovery.history.array("residual")[0] == pytest.approx(fresh.history.array("residual")[0], rel=1e-6)
    assert not (tmp_path / "recon.h5.checkpoint").exists()


def test_a_file_cca_did_not_write_at_the_checkpoint_path_is_neither_read_nor_replaced(tiny, tmp_path, caplog):
    captures, section = tiny
    foreign = tmp_path / "recon.h5.checkpoint"
    foreign.write_text("my notes\n")
    with caplog.at_level(logging.WARNING, logger="cca"):
        _run(captures, section.model_copy(update={"iterations": 20, "checkpoint_every": 1}), tmp_path / "recon.h5")
    assert "is not a checkpoint cca wrote" in caplog.text
    assert foreign.read_text() == "my notes\n"


def test_init_starts_from_an_earlier_recon_at_a_lower_residual(tiny, tmp_path):
    captures, section = tiny
    earlier = tmp_path / "earlier.h5"
    _run(captures, section.model_copy(update={"iterations": 30}), earlier)
    cold = _run(captures, section.model_copy(update={"iterations": 2}), tmp_path / "cold.h5")
    warm = _run(captures, section.model_copy(update={"iterations": 2, "init": earlier}), tmp_path / "warm.h5")
    assert warm.history.records[0].residual < 0.5 * cold.history.records[0].residual


def test_init_from_a_recon_of_another_grid_is_one_line_naming_the_file(tiny, tmp_path):
    from typer.testing import CliRunner

    from cca_cli.commands.app import app

    captures, section = tiny
    other = tmp_path / "other.h5"
    provenance = stage_provenance("reconstruct", {"reconstruct": section}, [])
    from cca_cli.io.h5 import atomic_h5, write_dataset

    with atomic_h5(other, provenance) as handle:
        write_dataset(handle, "/recon/spectrum", np.ones((32, 32), np.complex64))
    result = CliRunner().invoke(app, ["reconstruct", str(captures), "-o", str(tmp_path / "recon.h5"), "--init",
                                      str(other), "--iterations", "2", "--quiet"])
    assert result.exit_code != 0
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "other.h5" in lines[0] and "32x32" in lines[0], result.stderr
    assert not (tmp_path / "recon.h5").exists()


def test_the_python_api_starts_from_an_earlier_result():
    from cca_cli.api import camera_scan, reconstruct, resolution_chart, simulate

    g = camera_scan(wavelength_m=550e-9, focal_length_m=0.8, aperture_diameter_m=45e-3, pixel_pitch_m=2e-6,
                    distance_m=50.0, field_width_m=12e-3, grid=3, overlap=0.61)
    chart = resolution_chart(96, widths=(6, 4, 3))
    images = simulate(chart.image, g, snr_db=40)
    earlier = reconstruct(images, g, engine="altmin", iterations=30, tol=0)
    cold = reconstruct(images, g, engine="altmin", iterations=2, tol=0)
    warm = reconstruct(images, g, engine="altmin", iterations=2, tol=0, init=earlier)
    assert warm.history["residual"][0] < 0.5 * cold.history["residual"][0]
    with pytest.raises(ValueError, match="init"):
        reconstruct(images, g, engine="altmin", iterations=2, init=np.zeros((8, 8), np.complex64))


def test_cca_run_resumes_an_interrupted_reconstruction_from_its_checkpoint(tiny_run_config, tmp_path, caplog):
    from cca_cli.config.load import apply_overrides
    from cca_cli.stages.runner import run_pipeline

    config = apply_overrides(tiny_run_config, {"run.stages": ["simulate", "reconstruct"],
                                               "reconstruct.iterations": 60, "reconstruct.checkpoint_every": 2})
    out = tmp_path / "out"
    checkpoint = out / "recon.h5.checkpoint"

    def progress(event):
        if event.stage == "reconstruct" and checkpoint.exists():
            raise _Stop

    with pytest.raises(_Stop):
        run_pipeline(config, out, progress=progress)
    assert checkpoint.is_file() and not (out / "recon.h5").exists()
    with caplog.at_level(logging.WARNING, logger="cca"):
        outcomes = run_pipeline(config, out)
    assert {o.name: o.status for o in outcomes} == {"simulate": "skipped", "reconstruct": "ran"}
    assert "resuming from iteration" in caplog.text
    with h5py.File(out / "recon.h5", "r") as handle:
        assert handle["/history/residual"].shape == (60,)
    assert not checkpoint.exists()


def test_a_checkpoint_made_under_other_engine_defaults_does_not_resume(tiny, monkeypatch):
    """The same config and captures resolve to other engine options when cca's presets change; a checkpoint
    (or a tiled run's finished tiles) made under the old ones must not be continued with the new ones."""
    from cca_cli.workflows import tiled

    captures, section = tiny
    provenance = stage_provenance("reconstruct", {"reconstruct": section}, [captures])
    before = reconstruct_stage.checkpoint_fingerprint(section, dict(provenance, engine_recipe="a"), captures)
    after = reconstruct_stage.checkpoint_fingerprint(section, dict(provenance, engine_recipe="b"), captures)
    assert before != after

    tiles_before = tiled.run_fingerprint(section, [], captures)
    name, options = tiled.tile_engine(section, "simulation")
    monkeypatch.setattr(tiled, "tile_engine", lambda *a, **k: (name, options.model_copy(update={"tau": 0.5})))
    assert tiled.run_fingerprint(section, [], captures) != tiles_before


def test_a_run_stopped_while_it_replaced_an_outdated_recon_goes_on_without_force(tiny_run_config, tmp_path, caplog):
    """`cca run --force` of a changed config, stopped in its reconstruction: the same `cca run` again (no --force)
    resumes from the checkpoint instead of refusing the outdated recon.h5 it was already replacing."""
    from cca_cli.config.load import apply_overrides
    from cca_cli.errors import OutputExistsError
    from cca_cli.stages.runner import run_pipeline

    first = apply_overrides(tiny_run_config, {"reconstruct.iterations": 30, "reconstruct.tol": 0.0,
                                              "reconstruct.checkpoint_every": 2})
    run_pipeline(first, tmp_path)
    changed = apply_overrides(first, {"noise.seed": first.noise.seed + 1})
    checkpoint = tmp_path / "recon.h5.checkpoint"

    def stop_once_checkpointed(event):
        if checkpoint.exists():
            raise _Stop

    with pytest.raises(_Stop):
        run_pipeline(changed, tmp_path, force=True, progress=stop_once_checkpointed)
    assert checkpoint.is_file()
    with caplog.at_level(logging.WARNING, logger="cca"):
        outcomes = run_pipeline(changed, tmp_path)
    assert "resuming from iteration" in caplog.text and not checkpoint.exists()
    assert [o.status for o in outcomes][:2] == ["skipped", "ran"]
    other = apply_overrides(first, {"noise.seed": first.noise.seed + 2})   # no checkpoint of its own: refused
    with pytest.raises(OutputExistsError):
        run_pipeline(other, tmp_path)


def test_a_second_run_is_told_of_the_lock_first_and_a_failed_fresh_run_leaves_no_folder(tiny_run_config, tmp_path):
    from cca_cli.config.load import apply_overrides
    from cca_cli.errors import InputError, RunLockedError
    from cca_cli.io.lock import folder_lock
    from cca_cli.stages.runner import run_pipeline

    run_pipeline(tiny_run_config, tmp_path / "run")
    changed = apply_overrides(tiny_run_config, {"noise.seed": tiny_run_config.noise.seed + 1})
    with folder_lock(tmp_path / "run"):          # another run writing there: said before "made from another config"
        with pytest.raises(RunLockedError):
            run_pipeline(changed, tmp_path / "run")
    broken = apply_overrides(tiny_run_config, {"scene.kind": "image", "scene.image_path": str(tmp_path / "none.png")})
    with pytest.raises(InputError):
        run_pipeline(broken, tmp_path / "runs" / "fresh")
    assert not (tmp_path / "runs").exists()          # the folders it made, parents included, go again


def test_a_user_s_file_in_a_report_folder_cca_wrote_is_named_when_it_blocks_the_run(tiny_run_config, tmp_path):
    from cca_cli.errors import OutputError
    from cca_cli.stages.runner import run_pipeline

    run_pipeline(tiny_run_config, tmp_path)
    reports = [p for p in tmp_path.iterdir() if p.is_dir()]
    assert reports, "the tiny config writes a report folder"
    (reports[0] / "my_notes.txt").write_text("mine")
    # up to date: nothing would be replaced, so the run goes on and skips the report
    outcomes = run_pipeline(tiny_run_config, tmp_path)
    assert [o.status for o in outcomes] == ["skipped"] * len(outcomes)
    written = {p: p.stat().st_mtime_ns for p in tmp_path.glob("*.h5")}
    with pytest.raises(OutputError, match="cca wrote this folder, but not my_notes.txt in it"):
        run_pipeline(tiny_run_config, tmp_path, force=True)
    assert (reports[0] / "my_notes.txt").read_text() == "mine"
    assert {p: p.stat().st_mtime_ns for p in tmp_path.glob("*.h5")} == written   # refused before any stage ran


def test_a_damaged_report_json_is_made_again_without_force(tiny_run_config, tmp_path):
    from cca_cli.stages.runner import run_pipeline

    run_pipeline(tiny_run_config, tmp_path)
    report = next(p for p in tmp_path.iterdir() if p.is_dir()) / "report.json"
    report.write_text("junk")
    outcomes = {o.name: o.status for o in run_pipeline(tiny_run_config, tmp_path)}
    assert outcomes["report"] == "ran" and {s for k, s in outcomes.items() if k != "report"} == {"skipped"}
    assert report.read_text().startswith("{")
